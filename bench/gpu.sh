#!/usr/bin/env bash
# The CUDA bench on the GPU machine (`device` tool), run from the repository root there, after the
# three staging calls of ../shared/tools/device-wheels.sh have installed warp, newton and cma into
# /tmp/site. The package is not pip-installed there: this lays it out as installed (kernels/, tasks/,
# viz/ inside wrenorm/, as pyproject maps them) and puts that on PYTHONPATH.
#   bash bench/gpu.sh [extra bench options]      results: $OUT/bench/results.{json,md}
set -euo pipefail
src=/tmp/wrenorm-src
rm -rf "$src" && mkdir -p "$src/wrenorm"
cp -r wrenorm/. "$src/wrenorm/"
for d in kernels tasks viz; do cp -r "$d" "$src/wrenorm/$d"; done
export PYTHONPATH="/tmp/site:$src"
device=cuda
[ "${WRENORM_BENCH_DEVICE:-}" = cpu ] && device=cpu  # to try this script on a CPU-only machine
"${PYTHON:-python3}" -m wrenorm bench --device "$device" --no-fits --out "${OUT:-/tmp}/bench" "$@"
