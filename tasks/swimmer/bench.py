"""Throughput of the swimmer kernel on the real fish's gait, for `python -m wrenorm bench`."""
from __future__ import annotations

import os
import time

import numpy as np
import warp as wp


def benchmark(batch: int = 2048, seconds: float = 2.0, device: str = "cpu", dt: float | None = None,
              scheme: int = 2) -> dict:
    """Fish-seconds simulated per wall second for the robot fish at label 1.00 (built-in data), at
    the task's default step unless `dt` is given. Also per CPU second of this process (the
    machine may be shared: wall time then undercounts what the kernel can do)."""
    import resource

    from wrenorm.tasks.swimmer import body as swimmer_body, data as swimmer_data

    rates = swimmer_data.load_builtin()
    rate = min(rates, key=lambda r: abs(r.label - 1.0))
    dt = swimmer_body.DEFAULT_DT if dt is None else dt
    sim = swimmer_body.build_batch([rate], device=device, dt=dt, warm_seconds=0.0, meas_seconds=seconds,
                                   max_warm_seconds=None, scheme=scheme)
    coef = np.tile(np.array([0.4, 7.79, 2.81, 3.84, 0.27]), (batch, 1))
    sim.run(coef[:2])  # compile and warm caches outside the timing
    if not str(device).startswith("cpu"):
        wp.synchronize_device(device)
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    t0 = time.perf_counter()
    sim.run(coef)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    steps = int(sim.steps[0])
    fish_seconds = batch * float(sim.sim_seconds[0])
    return {"batch": batch, "sim_seconds": float(sim.sim_seconds[0]), "steps": steps, "dt": float(sim.sim_seconds[0] / steps),
            "scheme": "ros2" if scheme == 2 else "implicit-euler", "wall_s": wall, "cpu_s": cpu,
            "fish_seconds_per_s": fish_seconds / wall, "fish_steps_per_s": batch * steps / wall,
            "fish_seconds_per_cpu_s": fish_seconds / cpu if cpu > 0 else None,
            "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None, "device": str(device)}
