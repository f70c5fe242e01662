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

    from wrenorm.tasks.swimmer import body as swimmer_body
    from wrenorm.tasks.swimmer import data as swimmer_data

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
    return {"batch": batch, "sim_seconds": float(sim.sim_seconds[0]), "steps": steps,
            "dt": float(sim.sim_seconds[0] / steps),
            "scheme": "ros2" if scheme == 2 else "implicit-euler", "wall_s": wall, "cpu_s": cpu,
            "fish_seconds_per_s": fish_seconds / wall, "fish_steps_per_s": batch * steps / wall,
            "fish_seconds_per_cpu_s": fish_seconds / cpu if cpu > 0 else None,
            "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None, "device": str(device)}


def bench(device: str, batches: list[int], quick: bool) -> tuple[list[dict], str]:
    rows = []
    for b in batches[:4]:
        r = benchmark(b, 0.5 if quick else 2.0, device)
        r.update(panel="swimmer", series="fish", value=r["fish_seconds_per_s"], unit="fish-seconds simulated / s")
        rows.append(r)
        print(f"swimmer batch {b:6d}: {r['fish_seconds_per_s']:10.0f} fish-s/s  "
              f"{r['fish_steps_per_s'] / 1e6:.3f} M fish-steps/s", flush=True)
    table = ["Swimmer:", "", "| batch | fish-s per s | M fish-steps/s |", "|---|---|---|"]
    table += [f"| {r['batch']} | {r['fish_seconds_per_s']:.0f} | {r['fish_steps_per_s'] / 1e6:.3f} |" for r in rows]
    return rows, "\n".join(table)


def parity(device: str) -> dict:
    """Largest relative difference of simulated speeds between the CPU and `device`, same coefficients."""
    from wrenorm.tasks.swimmer import body as swimmer_body
    from wrenorm.tasks.swimmer import data as swimmer_data

    rates = swimmer_data.load_builtin()
    rate = min(rates, key=lambda r: abs(r.label - 1.0))
    coef = np.tile(np.array([0.4, 7.79, 2.81, 3.84, 0.27]), (64, 1)) * np.linspace(0.8, 1.2, 64)[:, None]
    swim = {dev: swimmer_body.build_batch([rate], device=dev, dt=swimmer_body.DEFAULT_DT, warm_seconds=0.0,
                                          meas_seconds=2.0, max_warm_seconds=None).run(coef)
            for dev in ("cpu", device)}
    return {"speed_max_rel": float(np.max(np.abs(swim[device] / swim["cpu"] - 1.0)))}


def kernel_modules() -> dict:
    from wrenorm.kernels.swimmer import fluid, kernel

    return {"swimmer": kernel, "swimmer_fluid": fluid}
