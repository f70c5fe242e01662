#!/usr/bin/env bash
# The CUDA bench on the GPU machine (`device` tool), from the repository root there, after
# ../shared/tools/device-wheels.sh has installed warp, newton and cma into /tmp/site. The package is not
# pip-installed there: this lays it out as installed (kernels/, tasks/, viz/ inside wrenorm/, as pyproject maps
# them), puts that on PYTHONPATH and runs from outside the checkout, whose own wrenorm/ (without the mapped
# folders) would otherwise come first on sys.path.
#   bash bench/gpu.sh [extra bench options]      results: $OUT/bench/results-cuda.{json,md} (+ the fits, each
#                                                against the CPU default on two cores of the same machine)
# Without $OUT the results go to the checkout's bench/, where the committed ones stand: add --force to replace them.
set -euo pipefail
repo=$(cd "$(dirname "$0")/.." && pwd)
src=$(mktemp -d /tmp/wrenorm-src.XXXXXX)
mkdir -p "$src/wrenorm"
cp -r "$repo/wrenorm/." "$src/wrenorm/"
for d in kernels tasks viz; do cp -r "$repo/$d" "$src/wrenorm/$d"; done
export PYTHONPATH="/tmp/site:$src${PYTHONPATH:+:$PYTHONPATH}"
device=cuda
[ "${WRENORM_BENCH_DEVICE:-}" = cpu ] && device=cpu  # to try this script on a CPU-only machine
out="${OUT:-$repo}/bench"
cd "$src"
"${PYTHON:-python3}" -c "import wrenorm.kernels as k; print('wrenorm.kernels from', k.__file__)" >&2
"${PYTHON:-python3}" -m wrenorm bench --device "$device" --out "$out" "$@"
