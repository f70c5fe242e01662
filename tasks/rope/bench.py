"""Throughput of the coarse rope kernels (and of the numpy / torch peers in baselines.py), for
`python -m wrenorm bench`."""
from __future__ import annotations

import time

import numpy as np

from wrenorm.kernels.rope import ChainParams, RopeSim, hanging_state


def swing_paths(n_paths: int, steps: int, dt: float, seed: int = 0) -> np.ndarray:
    """Hand paths for benchmarks: vertical circles of random radius, rate and phase, (P, steps+1, 3)."""
    rng = np.random.default_rng(seed)
    t = np.arange(steps + 1) * dt
    out = np.zeros((n_paths, steps + 1, 3), np.float32)
    for p in range(n_paths):
        rad, om, ph = rng.uniform(0.1, 0.3), rng.uniform(4.0, 9.0), rng.uniform(0, 2 * np.pi)
        ramp = np.minimum(t / 0.3, 1.0)  # start at rest
        out[p, :, 0] = rad * ramp * (np.cos(om * t + ph) - np.cos(ph))
        out[p, :, 2] = 1.5 + rad * ramp * (np.sin(om * t + ph) - np.sin(ph))
    return out


def benchmark(n_nodes: int = 16, batch: int = 4096, steps: int = 200, device: str = "cpu",
              variant: str = "culled", repeats: int = 2) -> dict:
    """Chain-steps per second of a swung-rope rollout (chains keep running after their first hit).

    variant: "culled" (the default kernel: SIMD lanes on the CPU), "allpairs" (all cores, no culling),
    "culled-1core" (one slice), "scalar" (rope_fast.py, one chain per thread), "generic" (the
    size-generic kernel, culled), "numpy" | "torch" (vectorised baselines of the same step).
    `kernel_chain_steps_per_s` counts the launches only (on CUDA the copies to and from the host
    are otherwise a large share at a million chains).
    """
    dt = 0.005
    link = 1.1 / (n_nodes - 1)
    paths = swing_paths(8, steps, dt)
    pidx = np.arange(batch, dtype=np.int32) % paths.shape[0]
    rng = np.random.default_rng(1)
    params = ChainParams(node_mass=np.full(batch, 0.2 / n_nodes), lead_mass=np.full(batch, 0.05),
                         bend_k=rng.uniform(0.5, 2.0, batch) * 1e-2 * (n_nodes - 1) / 10,
                         bend_b=np.full(batch, 1e-3), drag_lin=np.zeros(batch), drag_quad=np.full(batch, 0.02),
                         radius=np.full(batch, 0.01))
    p0, v0 = hanging_state(paths[0, 0], n_nodes, link)
    pos0 = np.broadcast_to(p0, (batch, n_nodes, 3)) + (paths[pidx, 0] - paths[0, 0])[:, None, :]
    if variant in ("numpy", "torch"):
        from wrenorm.tasks.rope import baselines as rope_baselines
        run = lambda: rope_baselines.rollout(variant, pos0, v0, paths, pidx, params, n_nodes, link, dt,  # noqa: E731
                                             iterations=4, margin=0.25 * link, steps=steps, stop_at_hit=False)
        repeats = 1
    else:
        sim = RopeSim(n_nodes, link, dt, device, iterations=4, cull=variant != "allpairs",
                      workers=1 if variant.endswith("1core") else None, fixed=variant != "generic",
                      lanes=0 if variant == "scalar" else None)
        run = lambda: sim.rollout(pos0, v0, paths, pidx, params, steps, stop_at_hit=False)  # noqa: E731
        sim.rollout(pos0[:64], v0, paths, pidx[:64], ChainParams(**{f: getattr(params, f)[:64] for f in ChainParams.FIELDS}), 2)
    times, kernel_times = [], []
    for _ in range(repeats):
        t = time.perf_counter()
        res = run()
        times.append(time.perf_counter() - t)
        kernel_times.append(getattr(sim, "last_kernel_seconds", times[-1]) if variant not in ("numpy", "torch") else times[-1])
    best, best_kernel = min(times), min(kernel_times)
    return {"variant": variant, "n_nodes": n_nodes, "batch": batch, "steps": steps, "device": device,
            "seconds": best, "chain_steps_per_s": batch * steps / best,
            "kernel_seconds": best_kernel, "kernel_chain_steps_per_s": batch * steps / best_kernel,
            "hit_fraction": float(np.mean(res.status == 1)), "blown_fraction": float(np.mean(res.status == 2))}
