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

    variant: "culled" (the default kernel: SIMD lanes on the CPU, tiled.py on a GPU), "allpairs" (all cores, no
    culling), "culled-1core" (one slice), "scalar" (fixed.py, one chain per thread, its state in local memory),
    "tiled" (tiled.py, one chain per thread, its state in registers and shared memory), "generic" (the
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
                      lanes=0 if variant in ("scalar", "tiled") else None,
                      tiled={"scalar": False, "tiled": True}.get(variant))
        run = lambda: sim.rollout(pos0, v0, paths, pidx, params, steps, stop_at_hit=False)  # noqa: E731
        warm = ChainParams(**{f: getattr(params, f)[:64] for f in ChainParams.FIELDS})
        sim.rollout(pos0[:64], v0, paths, pidx[:64], warm, 2)
    times, kernel_times = [], []
    for _ in range(repeats):
        t = time.perf_counter()
        res = run()
        times.append(time.perf_counter() - t)
        peer = variant in ("numpy", "torch")
        kernel_times.append(times[-1] if peer else getattr(sim, "last_kernel_seconds", times[-1]))
    best, best_kernel = min(times), min(kernel_times)
    return {"variant": variant, "n_nodes": n_nodes, "batch": batch, "steps": steps, "device": device,
            "seconds": best, "chain_steps_per_s": batch * steps / best,
            "kernel_seconds": best_kernel, "kernel_chain_steps_per_s": batch * steps / best_kernel,
            "hit_fraction": float(np.mean(res.status == 1)), "blown_fraction": float(np.mean(res.status == 2))}


def bench(device: str, batches: list[int], quick: bool) -> tuple[list[dict], str]:
    """Throughput over batch sizes for N = 8, 16, 32, then every kernel variant and the numpy / torch peers
    side by side at one batch (N = 16): rows for results.json and the rope section of results.md."""
    gpu = not device.startswith("cpu")
    key = "kernel_chain_steps_per_s" if gpu else "chain_steps_per_s"
    rows = []
    steps = 50 if quick else 200
    for n in (8, 16, 32):
        for b in batches:
            r = benchmark(n, b, steps, device, "culled")
            r.update(panel="rope, culled" + (" (launches alone)" if gpu else ", all cores"), series=f"N = {n}",
                     value=r[key] / 1e6, unit="M chain-steps/s")
            rows.append(r)
            print(f"rope N={n:2d} batch {b:7d}: {r['chain_steps_per_s'] / 1e6:8.3f} M chain-steps/s"
                  f" (launches alone {r['kernel_chain_steps_per_s'] / 1e6:8.3f})", flush=True)
    b = 1024 if quick else (4096 if not gpu else 262144)
    base_steps = 20 if quick else 50
    peers = ("numpy", "torch")
    # on a GPU "culled" is tiled.py, "scalar" fixed.py; on the CPU "culled" is lanes.py
    variants = ["culled", "allpairs"] + (["scalar", "generic"] if gpu else ["culled-1core", "scalar", "tiled"])
    variants += list(peers)
    for v in variants:
        # the numpy and torch peers run on the CPU at a CPU-sized batch wherever the bench runs
        r = benchmark(16, min(b, 4096) if v in peers else b, base_steps if v in peers else steps,
                      "cpu" if v in peers else device, v)
        r.update(comparison=True, panel=f"rope N = 16, batch {b}, same run", series=v, value=r[key] / 1e6,
                 unit="M chain-steps/s")
        rows.append(r)
        print(f"rope N=16 batch {r['batch']} {v:>13}: {r['chain_steps_per_s'] / 1e6:8.3f} M chain-steps/s", flush=True)
    task = task_level(device, 240 if quick else (24000 if gpu else 2400))
    rows.append(task)
    print(f"rope task-level, {task['candidates']} candidates x {task['conditions']} throws: "
          f"{task['chain_steps_per_s'] / 1e6:.3f} M chain-steps/s, {task['fraction_of_kernel']:.2f} of its launches "
          f"alone", flush=True)
    return rows, _table(rows, gpu)


def task_level(device: str, candidates: int) -> dict:
    """One generation of the default rope fit at `candidates` candidates (every one under the three built-in
    throws), whole: the rollouts, the observable on the device and the copy of the errors. Against the same
    rollouts' launches alone: how much of the kernel's throughput a fit keeps."""
    from wrenorm.tasks.rope.problem import RopeProblem
    from wrenorm.tasks.rope.reference.generate import builtin_references

    refs = builtin_references("fit")
    prob = RopeProblem(refs, device=device, names=[f"r{i}" for i in range(len(refs))])
    rng = np.random.default_rng(11)
    space = prob.space
    u = np.clip(space.to_unit(space.measured)[None] + rng.normal(0, 0.15, (candidates, len(space.free))), 0, 1)
    values = space.from_unit(u)
    prob.errors(values[:8], prob.train)  # kernels built and loaded
    times, kernel = [], []
    for _ in range(2):
        t = time.perf_counter()
        prob.errors(values, prob.train)
        times.append(time.perf_counter() - t)
        kernel.append(prob.sim.last_kernel_seconds)
    steps = max(c.data.steps for c in prob.train)
    chains = candidates * len(prob.train)
    # chains stop at their first hit: count the steps the batch launched for, as the kernel-only figure does
    best, best_kernel = min(times), min(kernel)
    return {"variant": "task-level", "candidates": candidates, "conditions": len(prob.train), "steps": steps,
            "device": device, "seconds": best, "kernel_seconds": best_kernel,
            "chain_steps_per_s": chains * steps / best, "kernel_chain_steps_per_s": chains * steps / best_kernel,
            "fraction_of_kernel": best_kernel / best, "task_level": True}


def _table(rows: list[dict], gpu: bool) -> str:
    key = "kernel_chain_steps_per_s" if gpu else "chain_steps_per_s"
    what = "launches alone, host copies excluded" if gpu else "whole rollout, all cores"
    main = [r for r in rows if not r.get("comparison") and not r.get("task_level")]
    batches = sorted({r["batch"] for r in main})
    lines = [f"Rope (M chain-steps/s, Warp, culled self-collision, {what}):", "",
             "| N | " + " | ".join(str(b) for b in batches) + " |", "|---|" + "---|" * len(batches)]
    for n in sorted({r["n_nodes"] for r in main}):
        row = {r["batch"]: r[key] / 1e6 for r in main if r["n_nodes"] == n}
        lines.append(f"| {n} | " + " | ".join(f"{row.get(b, float('nan')):.3f}" for b in batches) + " |")
    comp = [r for r in rows if r.get("comparison")]
    if comp:
        numpy = next((r["chain_steps_per_s"] for r in comp if r["variant"] == "numpy"), None)
        lines += ["", f"Rope N=16, batch {comp[0]['batch']}, same run (numpy and torch on the CPU):", "",
                  "| variant | M chain-steps/s | launches alone | x numpy |", "|---|---|---|---|"]
        for r in comp:
            ratio = f"{r['chain_steps_per_s'] / numpy:.1f}" if numpy else ""
            lines.append(f"| {r['variant']} | {r['chain_steps_per_s'] / 1e6:.3f} | "
                         f"{r['kernel_chain_steps_per_s'] / 1e6:.3f} | {ratio} |")
    for r in rows:
        if r.get("task_level"):
            lines += ["", f"Rope task-level (one generation of the default fit: {r['candidates']} candidates x "
                          f"{r['conditions']} throws, rollouts + observable on the device + errors to the host): "
                          f"{r['chain_steps_per_s'] / 1e6:.3f} M chain-steps/s, {r['fraction_of_kernel']:.2f} of "
                          f"its launches alone ({r['kernel_chain_steps_per_s'] / 1e6:.3f} M)"]
    return "\n".join(lines)


def parity(device: str, batch: int = 512, steps: int = 240) -> dict:
    """CPU against `device` on the same swung chains: first-contact status and time (the rope after its first
    self-contact is chaotic, and float32 differs between the two by FMA contraction, so events are compared,
    not states)."""
    n, dt = 16, 0.005
    link = 1.1 / (n - 1)
    paths = swing_paths(8, steps, dt)
    pidx = np.arange(batch, dtype=np.int32) % paths.shape[0]
    rng = np.random.default_rng(3)
    params = ChainParams(node_mass=np.full(batch, 0.2 / n), lead_mass=np.full(batch, 0.05),
                         bend_k=rng.uniform(0.5, 2.0, batch) * 1.5e-2, bend_b=np.full(batch, 1e-3),
                         drag_lin=np.zeros(batch), drag_quad=np.full(batch, 0.02), radius=np.full(batch, 0.01))
    p0, v0 = hanging_state(paths[0, 0], n, link)
    pos0 = np.broadcast_to(p0, (batch, n, 3)) + (paths[pidx, 0] - paths[0, 0])[:, None, :]
    a, b = (RopeSim(n, link, dt, dev).rollout(pos0, v0, paths, pidx, params, steps) for dev in ("cpu", device))
    both = (a.status == 1) & (b.status == 1)
    return {"status_agree": float(np.mean(a.status == b.status)),
            "hit_time_max_abs_s": float(np.max(np.abs(a.hit_time[both] - b.hit_time[both]))) if both.any() else None,
            "hit_fraction_cpu": float(np.mean(a.status == 1))} | _observable_parity(device)


def _observable_parity(device: str, candidates: int = 64) -> dict:
    """The fit's whole observable (rollouts, critical states, error terms on the device) on the built-in throws,
    CPU against `device`: the largest relative difference of the totals where both chains hit."""
    from wrenorm.tasks.rope.problem import RopeProblem
    from wrenorm.tasks.rope.reference.generate import builtin_references

    refs = builtin_references("fit")
    probs = [RopeProblem(refs, device=dev, names=[f"r{i}" for i in range(len(refs))]) for dev in ("cpu", device)]
    rng = np.random.default_rng(5)
    space = probs[0].space
    u = np.clip(space.to_unit(space.measured)[None] + rng.normal(0, 0.2, (candidates, len(space.free))), 0, 1)
    values = space.from_unit(u)
    ta, tb = (p.error_terms(values, p.train) for p in probs)
    hit = (ta["status"] == 1) & (tb["status"] == 1)
    rel = np.abs(ta["total"][hit] - tb["total"][hit]) / np.abs(ta["total"][hit])
    return {"observable_status_agree": float(np.mean(ta["status"] == tb["status"])),
            "observable_total_max_rel": float(rel.max()) if hit.any() else None}


def kernel_modules(sizes=(8, 16)) -> dict:
    """The rope's Warp modules for the ahead-of-time CUDA build (fixed-size kernels for `sizes`)."""
    from wrenorm.kernels.rope import critical, fixed, generic, grad, tiled
    from wrenorm.tasks.rope.reference import newton

    mods = {"rope": generic, "rope_grad": grad, "rope_newton": newton, "rope_critical": critical}
    for n in sizes:
        mods[f"rope_fast[N={n}]"] = fixed.fast_kernel(n).module
    for n in sizes:
        mods[f"rope_tiled[N={n}]"] = tiled.tiled_kernel(n).module
    return mods
