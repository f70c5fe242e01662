"""Throughput of the PD joint kernel, for `python -m wrenorm bench`."""
from __future__ import annotations

import time

import numpy as np
import warp as wp

from wrenorm.kernels.pd import SEMI_IMPLICIT, PDCommands, simulate


def benchmark(batch: int, steps: int = 1000, device: str = "cpu", repeats: int = 3) -> dict:
    """Joint-steps per second of the rollout kernel (batch slots x steps)."""
    rng = np.random.default_rng(0)
    C = 1
    cmds = PDCommands(rng.normal(size=(C, steps)) * 0.1, np.zeros((C, steps)), np.zeros((C, steps)),
                      np.zeros((C, steps + 1)) + 0.1, np.zeros((C, 2)), device)
    values = np.tile([0.05, 20.0, 0.5, 0.0, 0.0], (batch, 1))
    simulate(values, cmds, SEMI_IMPLICIT, 1e-3)
    wp.synchronize_device(device)
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        simulate(values, cmds, SEMI_IMPLICIT, 1e-3)
        wp.synchronize_device(device)
        best = min(best, time.perf_counter() - t0)
    return {"batch": batch, "steps": steps, "seconds": best, "joint_steps_per_s": batch * steps / best}
