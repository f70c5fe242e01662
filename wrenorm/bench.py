"""`python -m wrenorm bench`: kernel throughput over batch sizes, baselines side by side, and the
end-to-end wall time of each default fit. Writes a results file and prints a table.

Ratios are measured in one run on one machine (shared machines are noisy: compare within a run).
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .errors import InputError
from .options import add_list, number
from .results import versions, write_atomic, write_json
from .system import resolve, systems

BATCHES = [256, 1024, 4096, 16384, 65536]
# a GPU needs far more chains than cores to fill; REFERENCES.md measured 4096 .. 1 M chains on an H100
CUDA_BATCHES = [4096, 32768, 262144, 1048576]
MAX_BATCH = 16 * 1048576  # 16x the largest default: far beyond, the run ends out of memory, not in a table


def default_out() -> Path:
    """The checkout's bench/ folder, whose committed results a run replaces, when wrenorm runs from a checkout;
    else ./bench. A relative ./bench wrote a second set of results wherever the command was typed."""
    checkout = Path(__file__).resolve().parents[1] / "bench"
    return checkout if (checkout / "results.md").is_file() else Path("bench")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    p.add_argument("--out", type=Path, default=default_out(),
                   help="folder for results.{json,md,png} (results-cuda.* on cuda; default: the checkout's bench/, "
                        "else ./bench)")
    p.add_argument("--quick", action="store_true", help="small batches only (smoke test)")
    p.add_argument("--no-fits", action="store_true", help="skip the end-to-end default fits")
    add_list(p, "--batches", item=number(integer=True), default=None, metavar="N", help="chains per launch")
    add_list(p, "--only", default=None, metavar="SYSTEM", help=f"systems to bench: {', '.join(systems())}")
    p.add_argument("--no-cuda-build", action="store_true",
                   help="skip the ahead-of-time sm_90 build of every kernel (registers, stack per thread)")
    p.add_argument("--force", action="store_true", help="replace results already in --out")


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


def timed_fit(system: str, args: list[str], device: str = "cpu", prefix: list[str] | None = None) -> dict:
    """One default fit as a user runs it, a whole process: its wall time, the fit's own split of it
    (result.json `timing`), the candidates it evaluated and its held-out error. prefix: e.g. taskset."""
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [*(prefix or []), sys.executable, "-m", "wrenorm", "fit", system, "--quiet", "--out", f"{tmp}/run",
               "--device", "cuda" if device.startswith("cuda") else "cpu", *args]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        row = {"task": system, "command": " ".join([*(prefix or []), "python -m wrenorm fit", system, *args]
                                                   + (["--device cuda"] if device.startswith("cuda") else [])),
               "wall_seconds": wall, "ok": proc.returncode == 0}
        if proc.returncode == 0:
            res = json.loads((Path(tmp) / "run" / "result.json").read_text())
            runs = res.get("runs", [res])
            row.update(candidates=sum(r["search"]["evaluations"] for r in runs),
                       held_out_error=runs[0]["validation"].get("mean_fitted_error"),
                       timing=runs[0].get("timing"), fit_wall_seconds=res.get("wall_seconds"))
        else:
            row["error"] = proc.stderr[-300:]
    return row


TWO_CORES = ["taskset", "-c", "0,1"]  # the CPU default as on the development machines (2 cores)


def bench_fits(device: str, tasks: list[str]) -> list[dict]:
    """Each default fit on `device`; on a GPU also the CPU default on two cores of the same machine, run
    right after it, and the ratios of candidates evaluated and of wall time against it."""
    import shutil

    rows = []
    for task in tasks:
        row = timed_fit(task, [], device)
        if device.startswith("cuda"):
            prefix = TWO_CORES if shutil.which("taskset") else None
            cpu = timed_fit(task, [], "cpu", prefix)
            row["cpu_default"] = {k: cpu.get(k) for k in ("command", "wall_seconds", "candidates", "ok")}
            if row["ok"] and cpu["ok"]:
                row["candidates_ratio_vs_cpu"] = row["candidates"] / cpu["candidates"]
                row["wall_ratio_vs_cpu"] = row["wall_seconds"] / cpu["wall_seconds"]
        rows.append(row)
        t = row.get("timing") or {}
        _log(f"fit {task}: {row['wall_seconds']:6.1f} s" + (
            f" (start-up {t.get('start_up_s', 0):.2f}, search {t.get('search_s', 0):.2f} (evaluating "
            f"{t.get('search_evaluating_s') or 0:.2f}), validation "
            f"{t.get('validation_s', 0):.2f}, writing {t.get('writing_s', 0):.2f})" if row["ok"] else
            f"  FAILED: {row.get('error')}"))
    return rows


def _table(res: dict) -> str:
    lines = [f"Machine: {res['machine'].get('cpu_model', res['machine']['processor'])}, "
             f"{res['machine']['cpu_count']} cores" + (f", {res['machine']['gpu']}" if "gpu" in res["machine"] else "")
             + f"; device `{res['machine']['device']}`; {res['date']}", ""]
    for name in res.get("systems", []):
        lines += [res["tables"][name], ""]
    if res.get("cuda_build"):
        lines += [f"Kernels built ahead of time for sm_{res['cuda_build']['arch']} (NVRTC, no GPU needed): "
                  "registers and stack frame per thread (255 registers = the cap; a frame means spills):", "",
                  "| kernel module | registers | frame bytes |", "|---|---|---|"]
        lines += [f"| {k} | {v['registers']} | {v['frame_bytes']} |" for k, v in res["cuda_build"]["modules"].items()]
        lines.append("")
    if res.get("parity"):
        lines += [f"CPU vs CUDA on the same inputs: {json.dumps(res['parity'])}", ""]
    if res.get("fits"):
        lines += ["Default fits, whole processes (warm kernel cache); the fit's own split of its time:", "",
                  "| command | wall s | start-up | search | of it evaluating | validation | writing | candidates | "
                  "held-out error |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in res["fits"]:
            t = r.get("timing") or {}
            cells = [f"{t.get(k) if t.get(k) is not None else float('nan'):.2f}"
                     for k in ("start_up_s", "search_s", "search_evaluating_s", "validation_s", "writing_s")]
            lines.append(f"| `{r['command']}` | {r['wall_seconds']:.2f}{'' if r['ok'] else ' (failed)'} | "
                         + " | ".join(cells) + f" | {r.get('candidates', '')} | {r.get('held_out_error', '')} |")
        lines.append("")
        against = [r for r in res["fits"] if r.get("cpu_default")]
        if against:
            lines += ["Against the CPU default on two cores of the same machine, run right after each:", "",
                      "| task | cuda wall s | cpu wall s | candidates cuda / cpu | wall cuda / cpu |",
                      "|---|---|---|---|---|"]
            for r in against:
                c = r["cpu_default"]
                lines.append(f"| {r['task']} | {r['wall_seconds']:.2f} | {c['wall_seconds']:.2f} | "
                             f"{r.get('candidates_ratio_vs_cpu', float('nan')):.1f} | "
                             f"{r.get('wall_ratio_vs_cpu', float('nan')):.2f} |")
            lines.append("")
    for peer in (res.get("peers") or {}).values():
        lines += [peer["table"], ""]
    return "\n".join(lines).rstrip() + "\n"


def run(args) -> int:
    from .warp_init import init_warp

    if args.out.exists() and not args.out.is_dir():  # found before the benchmark runs, not after it
        raise InputError(str(args.out), "--out", "is a file: bench writes results.{json,md,png} into a folder")
    stem = "results" if args.device == "cpu" else "results-cuda"  # both live in bench/, side by side
    present = [args.out / f"{stem}.{ext}" for ext in ("json", "md", "png") if (args.out / f"{stem}.{ext}").exists()]
    if present and not args.force:  # a --quick run would replace the measured tables in silence
        raise InputError(str(present[0]), "--out", "holds results of an earlier bench; --force replaces them, or "
                                                   "choose another --out")
    wp = init_warp(args.device)
    if args.device == "cuda" and not wp.is_cuda_available():
        raise InputError("--device", "device", "cuda requested but no CUDA device is available")
    device = "cuda:0" if args.device == "cuda" else "cpu"
    batches = args.batches or ([256, 1024] if args.quick else (CUDA_BATCHES if device != "cpu" else BATCHES))
    if any(not 0 < b <= MAX_BATCH for b in batches):
        raise InputError("--batches", "batches", f"each must be in [1, {MAX_BATCH}], got {batches}")
    registered = systems()
    unknown = [n for n in args.only or [] if n not in registered]
    if unknown:
        raise InputError("--only", "only", f"unknown system {unknown[0]!r}; available: {', '.join(registered)}")
    only = args.only or [n for n, s in registered.items() if s.bench is not None]
    res = {"schema": "wrenorm.bench/2", "date": time.strftime("%Y-%m-%d %H:%M"), "machine": _machine(device),
           "versions": versions(), "systems": [], "tables": {}}
    for name in only:
        if registered[name].bench is None:
            raise InputError("--only", name, "this system has no kernel benchmark")
        res[name], res["tables"][name] = resolve(registered[name].bench)(device, batches, args.quick)
        res["systems"].append(name)
    if not args.no_cuda_build:
        from .cuda_check import compile_for_cuda, kernel_modules

        _log("building every kernel for sm_90 ahead of time (NVRTC) ...")
        res["cuda_build"] = {"arch": 90, "modules": compile_for_cuda(kernel_modules())}
    if device != "cpu":
        from .cuda_check import parity

        res["parity"] = parity(device)
        _log(f"CPU vs {device}: {res['parity']}")
    if not args.no_fits:
        res["fits"] = bench_fits(device, list(args.only or registered))  # --only names the fits too
        res["peers"] = {}
        for name in only:
            module = str(registered[name].bench or "").partition(":")[0]
            peer = getattr(importlib.import_module(module), "peer", None) if module else None
            if peer is not None:
                res["peers"][name] = peer(device)
    table = _table(res)
    write_json(args.out / f"{stem}.json", res)
    write_atomic(args.out / f"{stem}.md", table)
    written = [args.out / f"{stem}.json", args.out / f"{stem}.md"]
    try:
        from wrenorm.viz.bench_plot import plot_bench

        plot_bench(args.out / f"{stem}.png", res)
        written.append(args.out / f"{stem}.png")
    except ImportError as e:  # the GPU machine may lack matplotlib: the numbers matter more than the plot
        _log(f"no plot ({e})")
    print(table)
    print("written: " + ", ".join(str(w) for w in written))
    return 0
