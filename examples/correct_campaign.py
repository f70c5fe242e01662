"""The correction campaign: every rope variant x seed, each with the chain renormalised as it goes (`correct
rope`'s default arm, started from the values fitted to the rope's reference throws), the measured parameters and the
parameters fitted once before the trials (`correct rope --params renormalised-from-fitted measured fitted`: the
issue's three arms; `renormalised`, the renormalised arm started from the measured values, which the README names
for MuJoCo's rod, is named with --params), one `correct rope` run per (variant, seed), one after the other (they
share the CPU).

    python examples/correct_campaign.py --out runs/campaign [--variants stiff soft ...] [--seeds 0 1 2]
        [--segments 10] [--engine newton] [--params renormalised-from-fitted measured fitted] [--workers 2]
        [--table-only]

Each run goes to OUT/<variant>-s<seed>/ (a finished run is kept, an interrupted one continues with
--resume), its command line and wall time to OUT/campaign.json, and the table to OUT/campaign.md:
trials to reach the tolerance, or "- (best)" where a run never reached it within its trials. The summary
counts runs that reached it and the median trials per arm, a run that never reached counting as
max_trials + 1, and how many of the misses ended with the corrected model's floor above the tolerance (at its last
step the model predicted no command in the box reaching it; runs that record the floor).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

import numpy as np

from wrenorm.results import write_atomic
from wrenorm.tasks.rope.control.correct_cli import last_floor

ROPES = ["stiff", "soft", "heavy", "light", "long", "damped", "heavy_end"]


class Outcome(NamedTuple):
    """One run of one arm in the summary: trials to the tolerance (max_trials + 1 when never), best error, and for a
    miss that recorded the corrected model's floor whether its last floor lay above the tolerance (else None)."""

    rope: str
    trials: int
    best_error: float
    floor_above: bool | None


def run_one(out: Path, variant: str, seed: int, args) -> dict:
    folder = out / f"{variant}-s{seed}"
    done = folder / "correct.json"
    cmd = [sys.executable, "-m", "wrenorm", "correct", "rope", "--variant", variant, "--seed", str(seed),
           "--segments", str(args.segments), "--engine", args.engine, "--params", *args.params, "--no-record",
           "--quiet", "--out", str(folder)] + list(args.extra)
    if done.exists():
        return {"command": " ".join(cmd[1:]), "skipped": "finished before"}
    if (folder / "settings.json").exists():
        cmd = [sys.executable, "-m", "wrenorm", "correct", "rope", "--resume", "--no-record", "--quiet", "--out",
               str(folder)]
    t = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if proc.returncode != 0:
        print(proc.stderr[-2000:], file=sys.stderr)
    return {"command": " ".join(["python"] + cmd[1:]), "returncode": proc.returncode, "wall_s": wall}


def mixed_settings(settings_of: dict) -> list[str]:
    """Lines saying which `correct rope` settings differ between the campaign's runs (e.g. a campaign resumed after a
    default changed: its finished runs keep the old setting, its new ones take the new); none when all agree."""
    keys = sorted({k for st in settings_of.values() for k in st})
    lines = []
    for k in keys:
        values = {}
        for run, st in settings_of.items():
            values.setdefault(json.dumps(st.get(k)), []).append(run)
        if len(values) > 1:
            lines.append(f"**The runs differ in `{k}`**: " + "; ".join(f"{val}: {', '.join(runs)}"
                                                                       for val, runs in values.items()))
    return lines + ([""] if lines else [])


def table(out: Path, variants, seeds, params, max_trials_default: int = 10) -> tuple[str, dict, dict]:
    """The campaign's table, its summary per arm, and every run's trials (error, accepted, predicted error), so
    that two campaigns can be compared trial for trial without the run folders."""
    cells, summary, trials_of, settings_of = {}, {p: [] for p in params}, {}, {}
    meta = json.loads((out / "campaign.json").read_text()) if (out / "campaign.json").exists() else {}
    for v in variants:
        for s in seeds:
            f = out / f"{v}-s{s}" / "correct.json"
            if not f.exists():
                continue
            r = json.loads(f.read_text())
            settings_of[f"{v}-s{s}"] = {k: val for k, val in r.get("settings", {}).items() if k != "seed"}
            for p in params:
                run = r["runs"].get(p)
                if run is None:
                    continue
                n = run["trials_to_tolerance"]
                cells[(v, s, p)] = str(n) if run["success"] else f"- ({run['best_error']:.3f})"
                floor = None if run["success"] else last_floor(run)
                summary[p].append(Outcome(v, n if run["success"] else r["max_trials"] + 1, run["best_error"],
                                          None if floor is None else floor["error"] > r["tolerance"]))
                trials_of.setdefault(f"{v}-s{s}", {})[p] = [
                    {"error": t["error"], "accepted": t["accepted"], "predicted_error": t.get("predicted_error")}
                    for t in run["trials"]]
    lines = mixed_settings(settings_of)
    lines += ["| rope | seed | " + " | ".join(params) + " | wall (min) |", "|---|---|" + "---|" * (len(params) + 1)]
    for v in variants:
        for s in seeds:
            if not any((v, s, p) in cells for p in params):
                continue
            wall = (meta.get("runs", {}).get(f"{v}-s{s}") or {}).get("wall_s")
            lines.append(f"| {v} | {s} | " + " | ".join(cells.get((v, s, p), "") for p in params)
                         + f" | {'' if wall is None else f'{wall / 60:.1f}'} |")
    lines += ["", "| arm | runs | reached | median trials (never = max + 1) | per-rope median trials | median best "
                  "error | per-rope median best error | misses whose last model floor was above the tolerance (of "
                  "those that record one) |",
              "|---|---|---|---|---|---|---|---|"]
    stats = {}
    for p in params:
        rows = summary[p]
        if not rows:
            continue
        trials = [o.trials for o in rows]
        ropes = [v for v in variants if any(o.rope == v for o in rows)]
        per_rope = {v: float(np.median([o.trials for o in rows if o.rope == v])) for v in ropes}
        per_rope_err = {v: float(np.median([o.best_error for o in rows if o.rope == v])) for v in ropes}
        reached = sum(1 for o in rows if o.trials <= max_trials_default)
        best = float(np.median([o.best_error for o in rows]))
        floors = [o.floor_above for o in rows if o.floor_above is not None]
        stats[p] = {"runs": len(rows), "reached": reached, "median": float(np.median(trials)), "per_rope": per_rope,
                    "median_best_error": best, "per_rope_median_best_error": per_rope_err,
                    "misses_with_floor": len(floors), "misses_floor_above_tolerance": sum(floors)}
        lines.append(f"| {p} | {len(rows)} | {reached} | {np.median(trials):g} | "
                     + ", ".join(f"{v} {m:g}" for v, m in per_rope.items()) + f" | {best:.3f} | "
                     + ", ".join(f"{v} {m:.3f}" for v, m in per_rope_err.items())
                     + (f" | {sum(floors)} of {len(floors)} |" if floors else " | |"))
    return "\n".join(lines) + "\n", stats, trials_of


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("runs/campaign"))
    ap.add_argument("--variants", nargs="+", default=ROPES)
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--segments", type=int, default=10)
    ap.add_argument("--engine", default="newton")
    ap.add_argument("--params", nargs="+", default=["renormalised-from-fitted", "measured", "fitted"],
                    help="the arms, each a `correct rope --params` value (default: the issue's three, the renormalised "
                         "one started from the fitted values as `correct rope` is)")
    ap.add_argument("--workers", type=int, default=1,
                    help="correct rope processes at once (each uses one core; wall times then share the machine)")
    ap.add_argument("--table-only", action="store_true", help="rebuild the table from finished runs")
    ap.add_argument("extra", nargs="*", help="further `correct rope` options, after --")
    args = ap.parse_args(argv)
    if args.workers < 1:
        ap.error(f"--workers: must be >= 1, got {args.workers}")
    args.out.mkdir(parents=True, exist_ok=True)
    meta_file = args.out / "campaign.json"
    meta = json.loads(meta_file.read_text()) if meta_file.exists() else {"runs": {}}
    if not args.table_only:
        # one seed over every rope first, then the next seed: a campaign cut short still covers all ropes
        cells = [(v, s) for s in args.seeds for v in args.variants]
        lock = threading.Lock()

        def one(cell):
            v, s = cell
            print(f"{time.strftime('%H:%M:%S')} {v} seed {s} ...", flush=True)
            rec = run_one(args.out, v, s, args)
            with lock:
                if "skipped" not in rec:
                    meta["runs"][f"{v}-s{s}"] = rec
                    write_atomic(meta_file, json.dumps(meta, indent=1))
                print(f"   {v} seed {s}: {rec}", flush=True)

        with ThreadPoolExecutor(max_workers=args.workers) as pool:  # each cell is its own process
            list(pool.map(one, cells))
    text, stats, trials_of = table(args.out, args.variants, args.seeds, args.params)
    write_atomic(args.out / "campaign.md", text)
    meta["summary"], meta["trials"] = stats, trials_of
    write_atomic(meta_file, json.dumps(meta, indent=1))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
