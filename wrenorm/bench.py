"""`python -m wrenorm bench`: kernel throughput over batch sizes, baselines side by side, and the
end-to-end wall time of each default fit. Writes a results file and prints a table.

Ratios are measured in one run on one machine (shared machines are noisy: compare within a run).
"""
from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .results import versions, write_atomic, write_json

BATCHES = [256, 1024, 4096, 16384, 65536]
# a GPU needs far more chains than cores to fill; REFERENCES.md measured 4096 .. 1 M chains on an H100
CUDA_BATCHES = [4096, 32768, 262144, 1048576]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    p.add_argument("--out", type=Path, default=Path("bench"), help="folder for results.json / results.md")
    p.add_argument("--quick", action="store_true", help="small batches only (smoke test)")
    p.add_argument("--no-fits", action="store_true", help="skip the end-to-end default fits")
    p.add_argument("--batches", type=int, nargs="+", default=None)
    p.add_argument("--only", choices=["rope", "swimmer", "pd"], nargs="+", default=None)
    p.add_argument("--no-cuda-build", action="store_true",
                   help="skip the ahead-of-time sm_90 build of every kernel (registers, stack per thread)")


def _machine(device: str) -> dict:
    import warp as wp

    info = {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(), "device": device}
    try:
        with open("/proc/cpuinfo") as f:
            info["cpu_model"] = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    if device.startswith("cuda"):
        info["gpu"] = wp.get_device(device).name
    return info


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def bench_rope(device: str, batches: list[int], quick: bool) -> list[dict]:
    from wrenorm.tasks.rope import bench as rope

    rows = []
    steps = 50 if quick else 200
    for n in (8, 16, 32):
        for b in batches:
            r = rope.benchmark(n, b, steps, device, "culled")
            rows.append(r)
            _log(f"rope N={n:2d} batch {b:7d}: {r['chain_steps_per_s'] / 1e6:8.3f} M chain-steps/s"
                 f" (launches alone {r['kernel_chain_steps_per_s'] / 1e6:8.3f})")
    # baselines and variants side by side at one batch size
    b = 1024 if quick else (4096 if device == "cpu" else 262144)
    base_steps = 20 if quick else 50
    variants = ["culled", "allpairs"] + (["culled-1core", "scalar"] if device == "cpu" else ["generic"]) + ["numpy", "torch"]
    for v in variants:
        r = rope.benchmark(16, b, base_steps if v in ("numpy", "torch") else steps, device if v not in ("numpy", "torch") else "cpu", v)
        r["comparison"] = True
        rows.append(r)
        _log(f"rope N=16 batch {b} {v:>13}: {r['chain_steps_per_s'] / 1e6:8.3f} M chain-steps/s")
    return rows


def bench_swimmer(device: str, batches: list[int], quick: bool) -> list[dict]:
    from wrenorm.tasks.swimmer import bench as swimmer

    rows = []
    for b in batches[:4]:
        r = swimmer.benchmark(b, 0.5 if quick else 2.0, device)
        rows.append(r)
        _log(f"swimmer batch {b:6d}: {r['fish_seconds_per_s']:10.0f} fish-s/s  {r['fish_steps_per_s'] / 1e6:.3f} M fish-steps/s")
    return rows


def bench_pd(device: str, batches: list[int], quick: bool) -> list[dict]:
    from wrenorm.tasks.pd import bench as pd

    rows = []
    for b in batches:
        r = pd.benchmark(b, 200 if quick else 1000, device)
        r["device"] = device
        rows.append(r)
        _log(f"pd batch {b:6d}: {r['joint_steps_per_s'] / 1e6:8.2f} M joint-steps/s")
    return rows


def bench_fits(device: str, tasks: list[str]) -> list[dict]:
    rows = []
    for task in tasks:
        with tempfile.TemporaryDirectory() as tmp:
            cmd = [sys.executable, "-m", "wrenorm", "fit", task, "--quiet", "--no-record", "--out", f"{tmp}/run",
                   "--device", "cuda" if device.startswith("cuda") else "cpu"]
            t0 = time.perf_counter()
            proc = subprocess.run(cmd, capture_output=True, text=True)
            wall = time.perf_counter() - t0
        rows.append({"task": task, "wall_seconds": wall, "ok": proc.returncode == 0,
                     "command": " ".join(["python -m wrenorm fit", task])})
        _log(f"fit {task}: {wall:6.1f} s" + ("" if proc.returncode == 0 else f"  FAILED: {proc.stderr[-300:]}"))
    return rows


def _table(res: dict) -> str:
    lines = [f"Machine: {res['machine'].get('cpu_model', res['machine']['processor'])}, "
             f"{res['machine']['cpu_count']} cores" + (f", {res['machine']['gpu']}" if "gpu" in res["machine"] else "")
             + f"; device `{res['machine']['device']}`; {res['date']}", ""]
    rope = [r for r in res.get("rope", []) if not r.get("comparison")]
    if rope:
        batches = sorted({r["batch"] for r in rope})
        gpu = not res["machine"]["device"].startswith("cpu")
        key = "kernel_chain_steps_per_s" if gpu else "chain_steps_per_s"
        what = "launches alone, host copies excluded" if gpu else "whole rollout, all cores"
        lines += [f"Rope (M chain-steps/s, Warp, culled self-collision, {what}):", "",
                  "| N | " + " | ".join(str(b) for b in batches) + " |", "|---|" + "---|" * len(batches)]
        for n in sorted({r["n_nodes"] for r in rope}):
            row = {r["batch"]: r[key] / 1e6 for r in rope if r["n_nodes"] == n}
            lines.append(f"| {n} | " + " | ".join(f"{row.get(b, float('nan')):.3f}" for b in batches) + " |")
        comp = [r for r in res["rope"] if r.get("comparison")]
        if comp:
            numpy = next((r["chain_steps_per_s"] for r in comp if r["variant"] == "numpy"), None)
            lines += ["", f"Rope N=16, batch {comp[0]['batch']}, same run (numpy and torch on the CPU):", "",
                      "| variant | M chain-steps/s | launches alone | x numpy |", "|---|---|---|---|"]
            for r in comp:
                ratio = f"{r['chain_steps_per_s'] / numpy:.1f}" if numpy else ""
                lines.append(f"| {r['variant']} | {r['chain_steps_per_s'] / 1e6:.3f} | "
                             f"{r['kernel_chain_steps_per_s'] / 1e6:.3f} | {ratio} |")
    if res.get("swimmer"):
        lines += ["", "Swimmer:", "", "| batch | fish-s per s | M fish-steps/s |", "|---|---|---|"]
        lines += [f"| {r['batch']} | {r['fish_seconds_per_s']:.0f} | {r['fish_steps_per_s'] / 1e6:.3f} |" for r in res["swimmer"]]
    if res.get("pd"):
        lines += ["", "PD joint:", "", "| batch | M joint-steps/s |", "|---|---|"]
        lines += [f"| {r['batch']} | {r['joint_steps_per_s'] / 1e6:.2f} |" for r in res["pd"]]
    if res.get("cuda_build"):
        lines += ["", f"Kernels built ahead of time for sm_{res['cuda_build']['arch']} (NVRTC, no GPU needed): "
                  "registers and stack frame per thread (255 registers = the cap; a frame means spills):", "",
                  "| kernel module | registers | frame bytes |", "|---|---|---|"]
        lines += [f"| {k} | {v['registers']} | {v['frame_bytes']} |" for k, v in res["cuda_build"]["modules"].items()]
    if res.get("parity"):
        p = res["parity"]
        lines += ["", "CPU vs CUDA on the same inputs: rope first-contact status agrees for "
                  f"{100 * p['rope']['status_agree']:.1f} % of chains (contact times within "
                  f"{p['rope']['hit_time_max_abs_s']} s); swimmer speed within {100 * p['swimmer']['speed_max_rel']:.2g} %; "
                  f"PD error within {100 * p['pd']['error_max_rel']:.2g} %."]
    if res.get("fits"):
        lines += ["", "Default fits (end to end, incl. start-up and Warp cache load):", "", "| command | wall s |", "|---|---|"]
        lines += [f"| `{r['command']}` | {r['wall_seconds']:.1f}{'' if r['ok'] else ' (failed)'} |" for r in res["fits"]]
    return "\n".join(lines) + "\n"


def run(args) -> int:
    import warp as wp

    from .errors import InputError

    wp.config.quiet = True
    wp.init()
    if args.device == "cuda" and not wp.is_cuda_available():
        raise InputError("--device", "device", "cuda requested but no CUDA device is available")
    device = "cuda:0" if args.device == "cuda" else "cpu"
    batches = args.batches or ([256, 1024] if args.quick else (CUDA_BATCHES if device != "cpu" else BATCHES))
    if any(b <= 0 for b in batches):
        raise InputError("--batches", "batches", "must be positive")
    only = args.only or ["rope", "swimmer", "pd"]
    res = {"schema": "wrenorm.bench/1", "date": time.strftime("%Y-%m-%d %H:%M"), "machine": _machine(device),
           "versions": versions()}
    for name, fn in (("rope", bench_rope), ("swimmer", bench_swimmer), ("pd", bench_pd)):
        if name in only:
            res[name] = fn(device, batches, args.quick)
    if not args.no_cuda_build:
        from .cuda_check import compile_for_cuda, kernel_modules

        _log("building every kernel for sm_90 ahead of time (NVRTC) ...")
        res["cuda_build"] = {"arch": 90, "modules": compile_for_cuda(kernel_modules(rope_sizes=(8, 16, 32)))}
    if device != "cpu":
        from .cuda_check import parity

        res["parity"] = parity(device)
        _log(f"CPU vs {device}: {res['parity']}")
    if not args.no_fits:
        res["fits"] = bench_fits(device, ["pd", "swimmer", "rope"])
    table = _table(res)
    write_json(args.out / "results.json", res)
    write_atomic(args.out / "results.md", table)
    written = [args.out / "results.json", args.out / "results.md"]
    try:
        from wrenorm.viz.bench_plot import plot_bench

        plot_bench(args.out / "results.png", res)
        written.append(args.out / "results.png")
    except ImportError as e:  # the GPU machine may lack matplotlib: the numbers matter more than the plot
        _log(f"no plot ({e})")
    print(table)
    print("written: " + ", ".join(str(w) for w in written))
    return 0
