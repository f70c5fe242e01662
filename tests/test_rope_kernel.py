"""Coarse rope kernel: collision geometry, analytic motions, peer implementations, culling."""
import math

import numpy as np
import pytest
import warp as wp

from wrenorm.kernels import rope
from wrenorm.tasks.rope import baselines as rb
from wrenorm.tasks.rope.bench import swing_paths

KERNEL_VARIANTS = {"generic": dict(fixed=False), "lanes": dict(), "fixed": dict(lanes=0, tiled=False),
                   "tiled": dict(tiled=True)}  # RopeSim options that pick each rollout kernel


def _params(batch, **kw):
    base = dict(node_mass=0.02, lead_mass=0.02, bend_k=1e-12, bend_b=0.0, drag_lin=0.0, drag_quad=0.0, radius=0.005)
    base.update(kw)
    return rope.ChainParams.uniform(batch, **base)


@wp.kernel
def _closest(p: wp.array(dtype=wp.vec3), out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    out[i] = rope.seg_closest(p[4 * i], p[4 * i + 1], p[4 * i + 2], p[4 * i + 3])


def test_segment_distance_crossing_parallel_and_against_sampling():
    cases = np.array([
        [[-1, 0, 0], [1, 0, 0], [0.5, -1, 0.3], [0.5, 1, 0.3]],   # crossing at x=0.5, 0.3 apart
        [[0, 0, 0], [1, 0, 0], [0.2, 0.4, 0], [1.7, 0.4, 0]],     # parallel, overlapping, 0.4 apart
        [[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]],             # collinear, end to end
        [[0, 0, 0], [0, 0, 0], [1, -1, 2], [1, 1, 2]],            # degenerate first segment
    ], np.float32)
    out = wp.zeros(len(cases), dtype=wp.vec3)
    wp.launch(_closest, dim=len(cases), inputs=[wp.array(cases.reshape(-1, 3), dtype=wp.vec3)], outputs=[out])
    got = out.numpy()
    assert got[0] == pytest.approx([0.3, 0.75, 0.5], abs=1e-6)
    assert got[1][0] == pytest.approx(0.4, abs=1e-6)
    assert got[2][0] == pytest.approx(1.0, abs=1e-6) and got[2][1:] == pytest.approx([1.0, 0.0])
    assert got[3] == pytest.approx([math.sqrt(5.0), 0.0, 0.5], abs=1e-6)
    # random segments against dense sampling of both segments
    rng = np.random.default_rng(0)
    segs = rng.normal(size=(64, 4, 3)).astype(np.float32)
    out = wp.zeros(64, dtype=wp.vec3)
    wp.launch(_closest, dim=64, inputs=[wp.array(segs.reshape(-1, 3), dtype=wp.vec3)], outputs=[out])
    u = np.linspace(0, 1, 401)
    for s, g in zip(segs, out.numpy()):
        a = s[0] + u[:, None] * (s[1] - s[0])
        b = s[2] + u[:, None] * (s[3] - s[2])
        brute = np.linalg.norm(a[:, None] - b[None], axis=-1).min()
        assert g[0] <= brute + 1e-6 and g[0] >= brute - 5e-3
        d, _, _ = rb.seg_closest(rb._Np(), *[x[None] for x in s])
        assert d[0] == pytest.approx(g[0], abs=1e-5)


def _sweep_case(n_frames=200, dt=0.005, omega=2.0, link=0.1, radius=0.005):
    """Nodes 1-4 at rest as a square hook; the hand (node 0) swings on a circle of radius `link`
    about node 1 so link 0 keeps its length and segment 0 sweeps toward node 4.
    gap(t) = link cos(omega t) - 2 r exactly."""
    t = np.arange(n_frames + 1) * dt
    phi = np.pi - omega * t
    hand = np.stack([link * np.cos(phi), link * np.sin(phi), 0 * t], 1)[None].astype(np.float32)
    pos0 = np.array([hand[0, 0], [0, 0, 0], [link, 0, 0], [link, link, 0], [0, link, 0]], np.float32)
    return hand, pos0, np.zeros_like(pos0)


@pytest.mark.parametrize("cull", [True, False])
def test_interpolated_hit_time_of_a_known_approach_and_adjacent_excluded(cull):
    link, r, omega, dt = 0.1, 0.005, 2.0, 0.005
    hand, pos0, vel0 = _sweep_case(dt=dt, omega=omega, link=link, radius=r)
    sim = rope.RopeSim(5, link, dt, gravity=(0, 0, 0), cull=cull)
    res = sim.rollout(pos0, vel0, hand, [0], _params(1, radius=r), 199)
    t_star = math.acos(2 * r / link) / omega
    assert res.status[0] == 1
    # adjacent segments 0/1 touch at node 1 from the start; they must not count
    assert res.hit_frame[0] == math.ceil(t_star / dt)
    assert res.hit_time[0] == pytest.approx(t_star, abs=2e-5)  # frame times are 5e-3 apart
    assert res.s_b[0] == pytest.approx(1.0, abs=1e-5)
    # contact place is taken at the first touching frame k (the reference detector's convention)
    assert res.s_a[0] == pytest.approx((1 - math.sin(omega * res.hit_frame[0] * dt)) / 4, abs=2e-5)
    assert res.crit_pos[0, 2:] == pytest.approx(pos0[2:], abs=1e-4)  # the hook did not move


@pytest.mark.parametrize("first_step", [False, True])
@pytest.mark.parametrize("variant", ["generic", "lanes", "fixed", "tiled", "numpy"])
def test_critical_velocity_is_the_velocity_at_the_crossing(variant, first_step):
    """The hand node of the swinging hook (above) moves on a known circle, so its velocity at the contact is known:
    link omega (sin phi, -cos phi, 0) at t*. A position-based step's velocity is its mean over the step; the hit
    interpolates it to the crossing from the step before's (model.hit_velocity). The crossing falls 0.06 of the way
    into its step, where the step's mean alone was link omega^2 dt 0.44 = 9e-4 m/s off; interpolated, the error is
    second order (about 1e-6). first_step: the same swing started 0.3 of a step before the contact, 1-2 m from the
    origin, the hand's true velocity as the start's, so the hit falls in the rollout's first step, where the velocity
    before is the start's own, at the step's start (a review's case: the mid-step rule there was 2e-4 off). Every
    kernel and the numpy peer agree."""
    link, r, omega, dt = 0.1, 0.005, 2.0, 0.005
    t_star = math.acos(2 * r / link) / omega
    if first_step:
        t = t_star - 0.3 * dt + np.arange(40) * dt
        phi = np.pi - omega * t
        off = np.array([1.3, -0.7, 0.9])
        hand = (np.stack([link * np.cos(phi), link * np.sin(phi), 0 * t], 1) + off)[None].astype(np.float32)
        pos0 = (np.array([hand[0, 0] - off, [0, 0, 0], [link, 0, 0], [link, link, 0], [0, link, 0]]) + off)
        pos0 = pos0.astype(np.float32)
        vel0 = np.zeros_like(pos0)
        vel0[0] = link * omega * np.array([np.sin(phi[0]), -np.cos(phi[0]), 0.0])
        steps = 30
    else:
        hand, pos0, vel0 = _sweep_case(dt=dt, omega=omega, link=link, radius=r)
        steps = 199
    if variant == "numpy":
        res = rb.rollout("numpy", pos0, vel0, hand, [0], _params(1, radius=r), 5, link, dt, steps=steps,
                         gravity=(0, 0, 0), iterations=rope.RopeSim(5, link, dt).iterations)
    else:
        sim = rope.RopeSim(5, link, dt, gravity=(0, 0, 0), **KERNEL_VARIANTS[variant])
        res = sim.rollout(pos0, vel0, hand, [0], _params(1, radius=r), steps)
    assert res.status[0] == 1
    assert res.hit_frame[0] == 1 and 0.25 < res.hit_alpha[0] < 0.35 if first_step else 0.03 < res.hit_alpha[0] < 0.1
    phi = np.pi - omega * t_star
    exact = link * omega * np.array([np.sin(phi), -np.cos(phi), 0.0])
    step_mean = (hand[0, res.hit_frame[0]] - hand[0, res.hit_frame[0] - 1]) / dt
    assert np.linalg.norm(step_mean - exact) > (3e-4 if first_step else 8e-4)  # what the step's mean alone gave
    assert res.crit_vel[0, 0] == pytest.approx(exact, abs=2e-5)
    assert np.abs(res.crit_vel[0, 2:]).max() < 1e-5  # the hook stays at rest


def test_whole_chain_free_fall_follows_g_t2_over_2():
    n, link, dt, steps = 8, 0.1, 0.005, 100
    g = 9.81
    k = np.arange(steps + 1)
    z_disc = -g * dt * dt * k * (k + 1) / 2  # semi-implicit Euler free fall of the hand
    hand = np.zeros((1, steps + 1, 3), np.float32)
    hand[0, :, 2] = 2.0 + z_disc
    p0, v0 = rope.hanging_state(hand[0, 0], n, link)
    res = rope.RopeSim(n, link, dt).rollout(p0, v0, hand, [0], _params(1, bend_k=0.05, drag_quad=0.0), steps)
    t = steps * dt
    com0, com = p0[1:, 2].mean(), res.final_pos[0, 1:, 2].mean()
    assert com - com0 == pytest.approx(-0.5 * g * t * t, abs=0.5 * g * t * dt + 1e-4)
    assert com - com0 == pytest.approx(z_disc[-1], abs=1e-4)
    assert np.linalg.norm(np.diff(res.final_pos[0], axis=0), axis=1) == pytest.approx(link, rel=1e-3)


def test_stiff_hanging_chain_swings_with_the_rigid_pendulum_period():
    n, link, dt, steps = 5, 0.1, 0.002, 1500
    hand = np.tile(np.array([0, 0, 1.0], np.float32), (1, steps + 1, 1))
    th = np.radians(5.0)
    p0 = np.array([[link * i * math.sin(th), 0, 1.0 - link * i * math.cos(th)] for i in range(n)], np.float32)
    res = rope.RopeSim(n, link, dt, iterations=8).rollout(
        p0, np.zeros_like(p0), hand, [0], _params(1, bend_k=50.0, radius=0.001), steps, trajectory_every=1)
    x = res.trajectory[:, 0, -1, 0]
    up = np.flatnonzero((x[:-1] < 0) & (x[1:] >= 0))
    frac = x[up] / (x[up] - x[up + 1])
    period = np.diff((up + frac) * dt).mean()
    analytic = 2 * math.pi * math.sqrt(sum(i * i for i in range(1, n)) * link / (sum(range(1, n)) * 9.81))
    assert period == pytest.approx(analytic, rel=0.02)
    lengths = np.linalg.norm(np.diff(res.trajectory[:, 0], axis=1), axis=-1)
    assert np.abs(lengths / link - 1).max() < 2e-3


def _swing(B=16, n=12, steps=160, seed=0):
    dt, link = 0.005, 1.1 / (n - 1)
    paths = swing_paths(4, steps, dt, seed)
    pidx = np.arange(B) % 4
    rng = np.random.default_rng(seed)
    params = rope.ChainParams(node_mass=np.full(B, 0.02), lead_mass=rng.uniform(0.02, 0.1, B),
                              bend_k=rng.uniform(0.002, 0.05, B), bend_b=rng.uniform(1e-5, 1e-3, B),
                              drag_lin=rng.uniform(0, 0.05, B), drag_quad=np.full(B, 0.02),
                              radius=rng.uniform(0.005, 0.03, B))
    p0, v0 = rope.hanging_state(paths[0, 0], n, link)
    pos0 = np.broadcast_to(p0, (B, n, 3)) + (paths[pidx, 0] - paths[0, 0])[:, None, :]
    return pos0, v0, paths, pidx, params, n, link, dt, steps


@pytest.mark.parametrize("profile", [False, True])
def test_numpy_and_torch_baselines_match_the_warp_kernel(profile):
    pos0, v0, paths, pidx, params, n, link, dt, steps = _swing()
    if profile:  # non-uniform interior masses and compliant links
        params.mass_slope[:] = np.linspace(-0.6, 0.6, params.batch)
        params.stretch[:] = np.linspace(0.0, 5e-4, params.batch)
    w = rope.RopeSim(n, link, dt, min_sep=3).rollout(pos0, v0, paths, pidx, params, steps)
    assert (w.status == 1).sum() >= 3  # some chains hit inside the horizon
    npy = rb.rollout("numpy", pos0, v0, paths, pidx, params, n, link, dt, steps=steps, min_sep=3)
    assert np.array_equal(npy.status, w.status) and np.array_equal(npy.hit_frame, w.hit_frame)
    hit = w.status == 1
    # float32 round-off in a different operation order (compliant links amplify it a little)
    assert npy.hit_time[hit] == pytest.approx(w.hit_time[hit], abs=5e-5 if profile else 1e-5)
    assert npy.s_a[hit] == pytest.approx(w.s_a[hit], abs=1e-3)
    assert np.abs(npy.crit_pos - w.crit_pos).max() < 1e-4
    assert np.abs(npy.clearance - w.clearance).max() < 1e-4
    short = rope.RopeSim(n, link, dt).rollout(pos0, v0, paths, pidx, params, 30)
    th = rb.rollout("torch", pos0, v0, paths, pidx, params, n, link, dt, steps=30)
    assert np.abs(th.final_pos - short.final_pos).max() < 1e-5
    assert np.abs(th.final_vel - short.final_vel).max() < 1e-3


def test_fast_culled_kernel_equals_the_plain_all_pairs_kernel():
    """The per-size unrolled kernel with culling (fixed.py) against the generic kernel testing
    every pair, with non-uniform masses and stretchy links so every code path is used."""
    pos0, v0, paths, pidx, params, n, link, dt, steps = _swing(B=256, n=16, steps=240, seed=0)
    params.mass_slope[:] = np.linspace(-0.8, 0.8, params.batch)
    params.stretch[:] = np.linspace(0.0, 1e-3, params.batch)
    a = rope.RopeSim(n, link, dt, cull=True).rollout(pos0, v0, paths, pidx, params, steps, stop_at_hit=False)
    b = rope.RopeSim(n, link, dt, cull=False, fixed=False).rollout(pos0, v0, paths, pidx, params, steps,
                                                                   stop_at_hit=False)
    assert a.status.tolist().count(1) > 20
    assert rope.RopeSim(n, link, dt).kernel is not rope.rollout_kernel
    for f in ("status", "hit_frame", "hit_alpha", "crit_pos", "crit_vel", "clearance", "final_pos"):
        assert np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True), f


def test_blow_up_is_flagged_not_raised():
    pos0, v0, paths, pidx, params, n, link, dt, steps = _swing(B=4, steps=20)
    bad = rope.ChainParams(**{f: getattr(params, f) for f in rope.ChainParams.FIELDS})
    bad.node_mass[:] = np.nan
    res = rope.RopeSim(n, link, dt).rollout(pos0, v0, paths, pidx, bad, steps)
    assert np.all(res.status == 2)


@pytest.mark.parametrize("lanes", [0, 16])
@pytest.mark.parametrize("n,stop,chunk", [(8, True, None), (16, False, 37), (16, True, 50)])
def test_temporally_culled_kernel_is_bit_identical_to_all_pairs(n, stop, chunk, lanes):
    """collide.py skips block pairs whose gap bound (last tested gap minus accumulated relative
    motion) stays above min(clearance, margin); swung chains that hit, near-miss and stay clear
    must give exactly the all-pairs generic kernel's record (chunked launches restart the bounds)."""
    from wrenorm.kernels.rope import collide

    assert n <= collide.TEMPORAL_MAX_NODES
    pos0, v0, paths, pidx, params, n, link, dt, steps = _swing(B=192, n=n, steps=220, seed=0)
    params.bend_k[::3] *= 40.0  # stiff chains: many never touch, some pass within the margin
    params.mass_slope[:] = np.linspace(-0.5, 0.5, params.batch)
    kw = dict(stop_at_hit=stop, chunk=chunk)
    sim = rope.RopeSim(n, link, dt, lanes=lanes)
    assert sim.lanes == lanes
    a = sim.rollout(pos0, v0, paths, pidx, params, steps, **kw)
    b = rope.RopeSim(n, link, dt, cull=False, fixed=False).rollout(pos0, v0, paths, pidx, params, steps, **kw)
    margin = 0.25 * link
    clear = a.status == 0
    assert (a.status == 1).sum() >= 20 and clear.sum() >= 100
    assert np.any(clear & (a.clearance < margin) & (a.clearance > 0))  # near misses: clearance is live
    for f in ("status", "hit_frame", "hit_alpha", "hit_time", "s_a", "s_b", "crit_pos", "crit_vel", "clearance",
              "final_pos", "final_vel"):
        assert np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True), f


def test_lane_kernel_is_the_cpu_default_and_handles_ragged_batches_and_stretch():
    """16 chains per thread (kernels/rope/lanes.py): a batch that is not a multiple of 16, split
    across threads, with stretchy links and uneven masses, gives the generic all-pairs kernel's
    bits in every output field; blown-up chains stay blown up without disturbing their lane mates."""
    from wrenorm.kernels.rope import lanes as rope_lanes

    pos0, v0, paths, pidx, params, n, link, dt, steps = _swing(B=203, n=11, steps=240, seed=0)
    params.stretch[:] = np.linspace(0.0, 1e-3, params.batch)
    params.mass_slope[:] = np.linspace(0.6, -0.6, params.batch)
    params.node_mass[5] = np.nan  # one chain blows up at once
    sim = rope.RopeSim(n, link, dt)
    assert sim.lanes == rope_lanes.LANES and sim.kernel is rope_lanes.lanes_kernel(n)
    for kw in (dict(stop_at_hit=True), dict(stop_at_hit=False, chunk=45)):
        a = sim.rollout(pos0, v0, paths, pidx, params, steps, **kw)
        b = rope.RopeSim(n, link, dt, cull=False, fixed=False).rollout(pos0, v0, paths, pidx, params, steps, **kw)
        assert a.status[5] == 2 and (a.status == 1).sum() >= 5
        for f in ("status", "hit_frame", "hit_alpha", "crit_pos", "crit_vel", "clearance", "final_pos", "final_vel"):
            assert np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True), f
    assert rope.RopeSim(n, link, dt, device="cpu", fixed=False).lanes == 0
    with pytest.raises(ValueError):
        rope_lanes.lanes_kernel(rope_lanes.MAX_NODES + 1)


@pytest.mark.parametrize("stop,chunk", [(False, None), (True, 60)])
def test_lane_kernel_with_spatial_culling_is_bit_identical_to_all_pairs(stop, chunk):
    """Chains longer than TEMPORAL_MAX_NODES cull in space (block and segment spheres), per lane."""
    from wrenorm.kernels.rope import collide

    n = collide.TEMPORAL_MAX_NODES + 1
    pos0, v0, paths, pidx, params, n, link, dt, steps = _swing(B=150, n=n, steps=220, seed=0)
    params.mass_slope[:] = np.linspace(-0.5, 0.5, params.batch)
    kw = dict(stop_at_hit=stop, chunk=chunk)
    sim = rope.RopeSim(n, link, dt)
    assert sim.lanes > 0
    a = sim.rollout(pos0, v0, paths, pidx, params, steps, **kw)
    b = rope.RopeSim(n, link, dt, cull=False, fixed=False).rollout(pos0, v0, paths, pidx, params, steps, **kw)
    assert (a.status == 1).sum() >= 20
    for f in ("status", "hit_frame", "hit_alpha", "crit_pos", "crit_vel", "clearance", "final_pos", "final_vel"):
        assert np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True), f


def _tiled_case(n, B=203, steps=220):
    """Swung chains of every kind for the tiled kernel: hits, near misses, stiff chains that stay clear, uneven
    masses, stretchy links, one chain that is NaN from the start and one whose negative drag makes it blow up part
    way; B is not a multiple of the block, so the last block is partly past the end of the batch."""
    pos0, v0, paths, pidx, params, n, link, dt, steps = _swing(B=B, n=n, steps=steps, seed=0)
    params.bend_k[::3] *= 40.0
    params.mass_slope[:] = np.linspace(-0.6, 0.6, B)
    params.stretch[:] = np.linspace(0.0, 1e-3, B)
    params.node_mass[5] = np.nan
    params.drag_lin[40] = -20.0  # negative drag: the chain speeds up every step until it passes VMAX
    return pos0, v0, paths, pidx, params, n, link, dt, steps


@pytest.mark.parametrize("cpu_blocks", [False, True])
@pytest.mark.parametrize("n,stop,chunk", [(8, True, None), (12, False, None), (16, False, 37), (16, True, 50)])
def test_tiled_kernel_is_bit_identical_to_all_pairs(n, stop, chunk, cpu_blocks):
    """kernels/rope/tiled.py (the CUDA default) against the generic kernel testing every pair, every output field.
    With cpu_blocks the CPU runs real blocks of tiled.BLOCK threads that meet at every barrier (Warp's CPU fibers),
    as a GPU does: chains that finish early keep stepping beside the others but must write nothing more."""
    from wrenorm.kernels.rope import tiled

    pos0, v0, paths, pidx, params, n, link, dt, steps = _tiled_case(n)
    kw = dict(stop_at_hit=stop, chunk=chunk)
    sim = rope.RopeSim(n, link, dt, tiled=True)
    assert sim.kernel is tiled.tiled_kernel(n) and sim.block == tiled.BLOCK and sim.lanes == 0
    old = wp.config.enable_cpu_blocks
    wp.config.enable_cpu_blocks = cpu_blocks
    try:
        a = sim.rollout(pos0, v0, paths, pidx, params, steps, **kw)
    finally:
        wp.config.enable_cpu_blocks = old
    b = rope.RopeSim(n, link, dt, cull=False, fixed=False).rollout(pos0, v0, paths, pidx, params, steps, **kw)
    assert a.status[5] == 2 and (stop or a.status[40] == 2)
    assert (a.status == 1).sum() >= 20 and (a.status == 0).sum() >= 50
    assert np.any((a.status == 0) & (a.clearance < 0.25 * link) & (a.clearance > 0))  # near misses
    for f in ("status", "hit_frame", "hit_alpha", "hit_time", "s_a", "s_b", "crit_pos", "crit_vel", "clearance",
              "final_pos", "final_vel"):
        assert np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True), f


def test_the_negative_drag_chain_blows_up_part_way():
    """_tiled_case's chain 40 blows up after some steps, not at once (chain 5 does at once): the bit-identity test
    above covers a chain that leaves its block part way through a launch."""
    pos0, v0, paths, pidx, params, n, link, dt, steps = _tiled_case(16)
    sim = rope.RopeSim(n, link, dt, cull=False, fixed=False)
    short = sim.rollout(pos0, v0, paths, pidx, params, 20, stop_at_hit=False)
    full = sim.rollout(pos0, v0, paths, pidx, params, steps, stop_at_hit=False)
    assert short.status[40] == 0 and full.status[40] == 2 and short.status[5] == 2
    assert np.all(np.isfinite(full.final_pos[40])) and not np.all(np.isfinite(full.final_pos[5]))


def test_tiled_kernel_is_the_cuda_default_and_the_cpu_keeps_its_lanes():
    from wrenorm.kernels.rope import fixed, lanes, tiled

    gpu = rope.RopeSim(16, 0.1, device="cuda:0")
    assert gpu.kernel is tiled.tiled_kernel(16) and gpu.block == tiled.BLOCK and gpu.lanes == 0
    cpu = rope.RopeSim(16, 0.1)
    assert cpu.kernel is lanes.lanes_kernel(16) and cpu.lanes == lanes.LANES and cpu.block == 0
    longer = rope.RopeSim(tiled.MAX_NODES + 1, 0.1, device="cuda:0")
    assert longer.kernel is fixed.fast_kernel(tiled.MAX_NODES + 1) and longer.block == 0
    assert rope.RopeSim(16, 0.1, device="cuda:0", tiled=False).kernel is fixed.fast_kernel(16)
    with pytest.raises(ValueError):
        tiled.tiled_kernel(tiled.MAX_NODES + 1)
    with pytest.raises(ValueError):
        rope.RopeSim(16, 0.1, tiled=True, lanes=16)


@pytest.mark.parametrize("stop", [False, True])
@pytest.mark.parametrize("variant", ["generic", "lanes", "fixed", "tiled"])
def test_every_variant_records_its_trajectory_in_one_launch(variant, stop):
    """The kernels write the trajectory frames themselves (no launch per frame): frame k is the final state of a
    rollout of min(k * every, steps) steps, for chains that run on, hit and stop, or blow up part way."""
    pos0, v0, paths, pidx, params, n, link, dt, steps = _tiled_case(16, B=70, steps=150)
    sim = rope.RopeSim(n, link, dt, **KERNEL_VARIANTS[variant])
    every = 17
    res = sim.rollout(pos0, v0, paths, pidx, params, steps, stop_at_hit=stop, trajectory_every=every)
    marks = np.minimum(np.arange(res.trajectory.shape[0]) * every, steps)
    assert res.trajectory.shape == (len(marks), 70, n, 3) and marks[-1] == steps and marks[-2] < steps
    assert np.array_equal(res.trajectory_times, marks * dt)
    assert np.array_equal(res.trajectory[0], pos0) and np.array_equal(res.trajectory[-1], res.final_pos,
                                                                        equal_nan=True)
    assert res.status[5] == 2 and (res.status == 1).sum() >= 3
    for k in range(1, len(marks) - 1):
        short = sim.rollout(pos0, v0, paths, pidx, params, int(marks[k]), stop_at_hit=stop)
        assert np.array_equal(res.trajectory[k], short.final_pos, equal_nan=True), k
