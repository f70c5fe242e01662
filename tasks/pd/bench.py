"""Throughput of the PD joint kernel, for `python -m wrenorm bench`."""
from __future__ import annotations

import time

import numpy as np
import warp as wp

from wrenorm.kernels.pd import SEMI_IMPLICIT, PDCommands, simulate, simulate_start_fitted


def benchmark(batch: int, steps: int = 1000, device: str = "cpu", repeats: int = 3, start_fitted: bool = False) -> dict:
    """Joint-steps per second of the rollout kernel (batch slots x steps); start_fitted: of the rollout that fits a
    log's start velocity as it goes (a log's `errors`), beside it in one run."""
    rng = np.random.default_rng(0)
    C = 1
    cmds = PDCommands(rng.normal(size=(C, steps)) * 0.1, np.zeros((C, steps)), np.zeros((C, steps)),
                      np.zeros((C, steps + 1)) + 0.1, np.zeros((C, 2)), device)
    values = np.tile([0.05, 20.0, 0.5, 0.0, 0.0], (batch, 1))

    def run():
        simulate_start_fitted(values, cmds, [start_fitted], SEMI_IMPLICIT, 1e-3)

    run()
    wp.synchronize_device(device)
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        wp.synchronize_device(device)
        best = min(best, time.perf_counter() - t0)
    return {"batch": batch, "steps": steps, "seconds": best, "joint_steps_per_s": batch * steps / best}


def bench(device: str, batches: list[int], quick: bool) -> tuple[list[dict], str]:
    """Rows for results.json and the PD section of results.md: the plain rollout and, measured right after it on the
    same batch, the rollout of a log's fitted start."""
    rows = []
    for b in batches:
        for series in ("joint", "joint, start fitted"):
            r = benchmark(b, 200 if quick else 1000, device, start_fitted=series != "joint")
            r.update(device=device, panel="PD joint", series=series, value=r["joint_steps_per_s"] / 1e6,
                     unit="M joint-steps/s")
            rows.append(r)
            print(f"pd batch {b:6d} ({series}): {r['joint_steps_per_s'] / 1e6:8.2f} M joint-steps/s", flush=True)
    table = ["PD joint (a log's rollout also fits its start velocity: the unit response runs beside it):", "",
             "| batch | M joint-steps/s | start fitted |", "|---|---|---|"]
    table += [f"| {p['batch']} | {p['joint_steps_per_s'] / 1e6:.2f} | {f['joint_steps_per_s'] / 1e6:.2f} |"
              for p, f in zip(rows[::2], rows[1::2])]
    return rows, "\n".join(table)


def parity(device: str) -> dict:
    """Largest relative difference of the PD kernel's errors between the CPU and `device`, same inputs."""
    steps = 500
    q_des = np.random.default_rng(0).normal(size=(2, steps)) * 0.1
    zeros = np.zeros((2, steps))
    values = np.tile([0.05, 20.0, 0.5, 0.0, 0.0], (32, 1)) * np.linspace(0.9, 1.1, 32)[:, None]
    errs = {dev: simulate(values, PDCommands(q_des, zeros, zeros, np.full((2, steps + 1), 0.1), np.zeros((2, 2)), dev),
                          SEMI_IMPLICIT, 1e-3)[0]
            for dev in ("cpu", device)}
    return {"error_max_rel": float(np.max(np.abs(errs[device] / errs["cpu"] - 1.0)))}


def kernel_modules() -> dict:
    from wrenorm.kernels import arm, pd

    return {"pd": pd, "arm": arm}


PEER_REPEATS = 3


def peer(device: str, repeats: int = PEER_REPEATS) -> dict:
    """The paper's PD job fitted by wrenorm and by MuJoCo's mujoco.sysid, whole processes side by side (runs
    interleaved, medians): process wall time and held-out error of each, and their ratios."""
    import json
    import subprocess
    import sys

    from wrenorm.bench import timed_fit

    try:
        import mujoco.sysid  # noqa: F401
    except ImportError as e:
        return {"table": f"mujoco.sysid comparison skipped: {e} (pip install 'mujoco[sysid]')", "skipped": str(e)}
    ours, theirs = [], []
    for _ in range(repeats):
        ours.append(timed_fit("pd", ["--f-sim", "200"], device))
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "wrenorm.tasks.pd.sysid_peer", "--f-sim", "200"],
                              capture_output=True, text=True)
        row = {"wall_seconds": time.perf_counter() - t0, "ok": proc.returncode == 0}
        if row["ok"]:
            row.update(json.loads(proc.stdout.strip().splitlines()[-1]))
        theirs.append(row)
    med = lambda rows, k: float(np.median([r[k] for r in rows if r.get("ok")]))  # noqa: E731
    out = {"wrenorm": ours, "sysid": theirs, "repeats": repeats}
    if all(r["ok"] for r in ours + theirs):
        out.update(wall_ratio=med(ours, "wall_seconds") / med(theirs, "wall_seconds"),
                   held_out_ratio=med(ours, "held_out_error") / med(theirs, "held_out_error"))
        out["table"] = "\n".join([
            f"PD job at 200 Hz, whole processes side by side ({repeats} interleaved runs, medians):", "",
            "| tool | process wall s | held-out error | evaluations |", "|---|---|---|---|",
            f"| `python -m wrenorm fit pd --f-sim 200` | {med(ours, 'wall_seconds'):.2f} | "
            f"{med(ours, 'held_out_error'):.3g} | {int(med(ours, 'candidates'))} candidates |",
            f"| mujoco.sysid (`python -m wrenorm.tasks.pd.sysid_peer`) | {med(theirs, 'wall_seconds'):.2f} | "
            f"{med(theirs, 'held_out_error'):.3g} | {int(med(theirs, 'parameter_points'))} parameter points |",
            "", f"wrenorm / sysid: wall {out['wall_ratio']:.2f}, held-out error {out['held_out_ratio']:.2f}"])
    else:
        out["table"] = "PD peer comparison: a run failed (see results.json)"
    return out
