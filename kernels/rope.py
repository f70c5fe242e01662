"""Batched coarse rope chains (flying-knot model) with first self-collision detection.

One thread simulates one chain (one candidate x hand path) for many steps per launch.

Model (N point masses, N-1 links of length `link`; node 0 sits on the fingertip and follows
the hand path, node N-1 is the lead mass):
  1. forces, implicit per node: v <- (v + dt g) / (1 + dt c_i / m_i) with
     c_i = (drag_lin + drag_quad |v|) * l_i (drag per unit rope length, l_i = link, lead l/2);
     implicit so any drag coefficient is stable.
  2. prediction x* = x + dt v; node 0 placed on the hand sample of the new frame.
  3. `iters` passes, each: bending triplets in 3 colours (centre i mod 3), then links in 2 colours
     (even, odd); links last, so lengths are best met at the end of a pass. Within a colour the
     constraints share no node (order-free), between colours it is Gauss-Seidel.
     Bending is an XPBD constraint on the discrete curvature vector C = x_{i-1} - 2 x_i + x_{i+1}
     with compliance l^2/k and XPBD damping gamma = b / (k dt). For inextensible links
     |C| = l * 2 sin(theta/2), so the energy is 0.5 k (2 sin(theta/2))^2 = 0.5 k theta^2 + O(theta^4),
     and the damping 0.5 b theta_dot^2 to the same order. Unlike explicit theta forces it is
     unconditionally stable, which matters at N = 64 where explicit bending at dt = 5 ms blows up.
     Links are XPBD distance constraints with compliance `stretch` (m/N; 0 = exact mass-weighted
     projection onto the link length), node 0 infinite mass.
  Masses: interior nodes node_mass (1 + mass_slope (1 - 2u)), u = 0 next to the hand and 1 next
  to the lead (see node_w), the free end lead_mass.
  4. v = (x - x_prev) / dt (position-based velocity update).
  5. self-collision: capsules of radius r around segments (a, a+1); pairs with b >= a + min_sep
     (2 = every non-adjacent pair, the flying-knot rule; tasks exclude folds shorter than a loop).
     gap = segment distance - 2 r. Culling: a pair whose bounding spheres (segment midpoint,
     half length) are farther apart than 2 r + margin is skipped; such a pair cannot have
     gap <= margin, so the first-hit record is identical to testing all pairs.

First hit (frame k is the first frame with some gap <= 0): alpha = g_{k-1} / (g_{k-1} - g_k)
(0 if the pair already touched at frame k-1); among pairs hitting in that frame the smallest
alpha wins. Recorded: hit_frame = k, hit_alpha, time t0 + (k - 1 + alpha) dt (done in Python),
critical positions x_{k-1} + alpha (x_k - x_{k-1}) and critical velocities (x_k - x_{k-1}) / dt
(the velocity the position-based step carries over that interval), and the arc-length
fractions of the closest points of the hit pair at frame k (as tasks/rope_collision.py does).

`clearance` is min over frames and pairs of min(gap, margin): continuous in the state and equal
under culling and all-pairs; searches use it to pull non-colliding chains toward a collision.
Status: 0 no hit yet, 1 hit, 2 blew up (non-finite or speed above vmax).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import warp as wp

from wrenorm.parallel import launch_sliced

wp.config.quiet = True
# forward-only module (the tape-safe variant lives in rope_grad.py); -march=native lets clang use
# the host's SIMD and FMA for the per-chain arithmetic. No fast-math: blow-up detection needs NaN.
wp.set_module_options({"enable_backward": False, "optimization_level": 3, "cpu_compiler_flags": "-march=native"})

GRAVITY = (0.0, 0.0, -9.81)  # z up, as in newton
VMAX = 1.0e3  # m/s; a node faster than this means the step blew up


@wp.func
def seg_closest(p1: wp.vec3, q1: wp.vec3, p2: wp.vec3, q2: wp.vec3) -> wp.vec3:
    """(distance, s, t) between segments p1q1 and p2q2 (Ericson, Real-Time Collision Detection 5.1.9)."""
    eps = 1.0e-12
    d1 = q1 - p1
    d2 = q2 - p2
    r = p1 - p2
    a = wp.dot(d1, d1)
    e = wp.dot(d2, d2)
    f = wp.dot(d2, r)
    s = float(0.0)
    t = float(0.0)
    if a <= eps and e <= eps:
        s = 0.0
        t = 0.0
    elif a <= eps:
        s = 0.0
        t = wp.clamp(f / e, 0.0, 1.0)
    else:
        c = wp.dot(d1, r)
        if e <= eps:
            t = 0.0
            s = wp.clamp(-c / a, 0.0, 1.0)
        else:
            bb = wp.dot(d1, d2)
            denom = a * e - bb * bb
            if denom > 1.0e-10 * a * e:
                s = wp.clamp((bb * f - c * e) / denom, 0.0, 1.0)
            else:
                s = 0.0
            t = (bb * s + f) / e
            if t < 0.0:
                t = 0.0
                s = wp.clamp(-c / a, 0.0, 1.0)
            elif t > 1.0:
                t = 1.0
                s = wp.clamp((bb - c) / a, 0.0, 1.0)
    c1 = p1 + d1 * s
    c2 = p2 + d2 * t
    return wp.vec3(wp.length(c1 - c2), s, t)


@wp.func
def node_w(i: int, n: int, m: float, ml: float, slope: float) -> float:
    """Inverse mass of node i: 0 for the held node, 1/lead for the free end; interior nodes
    m (1 + slope (1 - 2u)), u = 0 next to the hand and 1 next to the lead (mean m for any slope)."""
    w = float(0.0)
    if i == n - 1:
        w = 1.0 / ml
    elif i > 0:
        u = float(0.5)
        if n > 3:
            u = float(i - 1) / float(n - 3)
        w = 1.0 / (m * (1.0 + slope * (1.0 - 2.0 * u)))
    return w


@wp.kernel
def rollout_kernel(
    pos: wp.array2d(dtype=wp.vec3),
    vel: wp.array2d(dtype=wp.vec3),
    prev: wp.array2d(dtype=wp.vec3),
    lam: wp.array2d(dtype=wp.vec3),
    lam_link: wp.array2d(dtype=float),
    seg: wp.array2d(dtype=wp.vec4),
    hand: wp.array2d(dtype=wp.vec3),
    path_index: wp.array(dtype=wp.int32),
    node_mass: wp.array(dtype=float),
    lead_mass: wp.array(dtype=float),
    bend_k: wp.array(dtype=float),
    bend_b: wp.array(dtype=float),
    drag_lin: wp.array(dtype=float),
    drag_quad: wp.array(dtype=float),
    radius: wp.array(dtype=float),
    mass_slope: wp.array(dtype=float),
    stretch: wp.array(dtype=float),
    n: int,
    min_sep: int,
    link: float,
    dt: float,
    gravity: wp.vec3,
    iters: int,
    cull: int,
    margin: float,
    vmax: float,
    step0: int,
    nsteps: int,
    stop_at_hit: int,
    status: wp.array(dtype=wp.int32),
    hit_frame: wp.array(dtype=wp.int32),
    hit_alpha: wp.array(dtype=float),
    hit_s: wp.array(dtype=wp.vec2),
    crit_pos: wp.array2d(dtype=wp.vec3),
    crit_vel: wp.array2d(dtype=wp.vec3),
    clearance: wp.array(dtype=float),
    offset: int,
):
    b = wp.tid() + offset
    st = status[b]
    if st == 2:
        return
    if st == 1 and stop_at_hit != 0:
        return
    path = path_index[b]
    m = node_mass[b]
    ml = lead_mass[b]
    slope = mass_slope[b]
    k = wp.max(bend_k[b], 1.0e-12)
    alpha_t = link * link / (k * dt * dt)
    gamma = bend_b[b] / (k * dt)
    at_s = stretch[b] / (dt * dt)  # XPBD link compliance / dt^2
    dl = drag_lin[b]
    dq = drag_quad[b]
    r = radius[b]
    two_r = 2.0 * r
    cl = clearance[b]
    vmax2 = vmax * vmax
    inv_dt = 1.0 / dt
    nseg = n - 1
    for step in range(step0, step0 + nsteps):
        # 1-2: forces (implicit per node) and prediction
        prev[b, 0] = pos[b, 0]
        pos[b, 0] = hand[path, step + 1]
        for i in range(1, n):
            xi = pos[b, i]
            vi = vel[b, i]
            prev[b, i] = xi
            wi = node_w(i, n, m, ml, slope)
            li = link
            if i == n - 1:
                li = 0.5 * link
            c = (dl + dq * wp.length(vi)) * li
            # one division per node (a vector divide is three)
            vi = (vi + dt * gravity) * (1.0 / (1.0 + dt * c * wi))
            pos[b, i] = xi + dt * vi
            lam[b, i] = wp.vec3(0.0)
            lam_link[b, i - 1] = 0.0
        # 3: constraint passes in colour order: constraints of one colour share no node, so
        # they are independent and the CPU overlaps them (a plain Gauss-Seidel sweep is one
        # serial dependency chain and runs at the latency of sqrt/div, 3x slower).
        for it in range(iters):
            for colour in range(3):
                for i in range(1 + colour, n - 1, 3):
                    # plain path: masses recomputed per constraint (rope_fast.py precomputes them)
                    w0 = node_w(i - 1, n, m, ml, slope)
                    w1 = node_w(i, n, m, ml, slope)
                    w2 = node_w(i + 1, n, m, ml, slope)
                    inv = 1.0 / ((1.0 + gamma) * (w0 + 4.0 * w1 + w2) + alpha_t)
                    x0 = pos[b, i - 1]
                    x1 = pos[b, i]
                    x2 = pos[b, i + 1]
                    cv = x0 - 2.0 * x1 + x2
                    dcv = cv - (prev[b, i - 1] - 2.0 * prev[b, i] + prev[b, i + 1])
                    lm = lam[b, i]
                    dlam = (-cv - alpha_t * lm - gamma * dcv) * inv
                    lam[b, i] = lm + dlam
                    pos[b, i - 1] = x0 + w0 * dlam
                    pos[b, i] = x1 - (2.0 * w1) * dlam
                    pos[b, i + 1] = x2 + w2 * dlam
            # links: exact projection onto |d| = l (a sqrt-free first-order factor diverges once a
            # whipping tip stretches a link past ~2.4 l in one step)
            for parity in range(2):
                for i in range(parity, n - 1, 2):
                    wa = node_w(i, n, m, ml, slope)
                    wb = node_w(i + 1, n, m, ml, slope)
                    den = wa + wb + at_s
                    fa = wa / den
                    fb = wb / den
                    xa = pos[b, i]
                    xb = pos[b, i + 1]
                    d = xb - xa
                    ln = wp.length(d)
                    ll = lam_link[b, i]
                    e = ln - link + at_s * ll  # C + alpha~ lambda (C alone when inextensible)
                    corr = wp.vec3(0.0)
                    if ln > 1.0e-9:
                        corr = d * (e / ln)
                        lam_link[b, i] = ll - e / den
                    pos[b, i] = xa + fa * corr
                    pos[b, i + 1] = xb - fb * corr
        # 4: velocities
        vv = float(0.0)
        for i in range(n):
            v = (pos[b, i] - prev[b, i]) * inv_dt
            vel[b, i] = v
            vv = vv + wp.dot(v, v)  # a sum propagates NaN (max would drop it)
        if not (vv < vmax2):
            status[b] = 2
            clearance[b] = cl
            return
        # 5: self-collision
        for a in range(nseg):
            pa = pos[b, a]
            pb = pos[b, a + 1]
            mid = 0.5 * (pa + pb)
            seg[b, a] = wp.vec4(mid[0], mid[1], mid[2], 0.5 * wp.length(pb - pa))
        best = float(2.0)
        best_a = int(-1)
        best_b = int(-1)
        for a in range(nseg - min_sep):
            sa = seg[b, a]
            for j in range(a + min_sep, nseg):
                sb = seg[b, j]
                dx = sa[0] - sb[0]
                dy = sa[1] - sb[1]
                dz = sa[2] - sb[2]
                reach = (sa[3] + sb[3] + two_r + margin) * 1.00001 + 1.0e-6
                far = dx * dx + dy * dy + dz * dz > reach * reach
                if cull == 0 or not far:
                    res = seg_closest(pos[b, a], pos[b, a + 1], pos[b, j], pos[b, j + 1])
                    gap = res[0] - two_r
                    if not far:
                        cl = wp.min(cl, wp.min(gap, margin))
                    if gap <= 0.0 and st == 0:
                        r0 = seg_closest(prev[b, a], prev[b, a + 1], prev[b, j], prev[b, j + 1])
                        g0 = r0[0] - two_r
                        al = float(0.0)
                        if g0 > 0.0:
                            al = g0 / (g0 - gap)
                        if al < best:
                            best = al
                            best_a = a
                            best_b = j
                elif margin < cl:
                    cl = margin
        if best_a >= 0:
            st = 1
            status[b] = 1
            hit_frame[b] = step + 1
            hit_alpha[b] = best
            for i in range(n):
                p0 = prev[b, i]
                crit_pos[b, i] = p0 + best * (pos[b, i] - p0)
                crit_vel[b, i] = vel[b, i]
            res = seg_closest(pos[b, best_a], pos[b, best_a + 1], pos[b, best_b], pos[b, best_b + 1])
            hit_s[b] = wp.vec2((float(best_a) + res[1]) / float(nseg), (float(best_b) + res[2]) / float(nseg))
            if stop_at_hit != 0:
                clearance[b] = cl
                return
    clearance[b] = cl


# ----------------------------------------------------------------------------------------
@dataclass
class ChainParams:
    """Per-chain physical parameters, each (B,) float: masses in kg, k in N m/rad per joint,
    b in N m s/rad per joint, drag_lin in N s/m^2 and drag_quad in N s^2/m^3 (per unit length),
    radius in m (collision capsule)."""

    node_mass: np.ndarray
    lead_mass: np.ndarray
    bend_k: np.ndarray
    bend_b: np.ndarray
    drag_lin: np.ndarray
    drag_quad: np.ndarray
    radius: np.ndarray
    mass_slope: np.ndarray | float = 0.0  # interior mass profile, see node_w (0: uniform)
    stretch: np.ndarray | float = 0.0  # link compliance in m/N (XPBD; 0: inextensible)

    FIELDS = ("node_mass", "lead_mass", "bend_k", "bend_b", "drag_lin", "drag_quad", "radius", "mass_slope",
              "stretch")
    DEFAULTS = {"mass_slope": 0.0, "stretch": 0.0}

    def __post_init__(self):
        arrs = [np.atleast_1d(np.asarray(getattr(self, f), dtype=np.float32)) for f in self.FIELDS]
        size = max(a.shape[0] for a in arrs)
        for f, a in zip(self.FIELDS, arrs):
            setattr(self, f, np.array(np.broadcast_to(a, (size,))))

    @property
    def batch(self) -> int:
        return self.node_mass.shape[0]

    @classmethod
    def uniform(cls, batch: int, **values) -> "ChainParams":
        return cls(**{f: np.full(batch, values.get(f, cls.DEFAULTS.get(f)), dtype=np.float32) for f in cls.FIELDS})

    def node_masses(self, n: int) -> np.ndarray:
        """(B, n) masses as the kernels use them (node 0, held by the hand, as inf)."""
        u = np.linspace(0.0, 1.0, n - 2) if n > 3 else np.array([0.5])
        interior = self.node_mass[:, None] * (1.0 + self.mass_slope[:, None] * (1.0 - 2.0 * u[None]))
        return np.concatenate([np.full((self.batch, 1), np.inf), interior, self.lead_mass[:, None]], 1)


@dataclass
class RolloutResult:
    status: np.ndarray      # (B,) 0 no hit, 1 hit, 2 blew up
    hit_frame: np.ndarray   # (B,) first frame with a gap <= 0 (-1 if none)
    hit_alpha: np.ndarray   # (B,) fraction of the step [hit_frame-1, hit_frame] at the crossing
    hit_time: np.ndarray    # (B,) s, nan if no hit
    s_a: np.ndarray         # (B,) arc-length fraction of the hit point on the segment nearer the hand
    s_b: np.ndarray         # (B,) ... on the segment nearer the free end
    crit_pos: np.ndarray    # (B, N, 3)
    crit_vel: np.ndarray    # (B, N, 3)
    clearance: np.ndarray   # (B,) min over frames and pairs of min(gap, margin)
    final_pos: np.ndarray   # (B, N, 3) state after the last simulated step
    final_vel: np.ndarray
    trajectory: np.ndarray | None = None        # (K, B, N, 3) positions every `trajectory_every` steps
    trajectory_times: np.ndarray | None = None  # (K,) s


class RopeSim:
    """Coarse chains of `n_nodes` masses (node 0 held) with links of `link_length` metres."""

    def __init__(self, n_nodes: int, link_length: float, dt: float = 0.005, device: str = "cpu",
                 iterations: int = 4, cull: bool = True, margin: float | None = None,
                 gravity=GRAVITY, workers: int | None = None, min_sep: int = 2, fixed: bool = True,
                 lanes: int | None = None):
        if not (3 <= int(n_nodes) <= 256):
            raise ValueError(f"n_nodes must be in [3, 256], got {n_nodes}")
        wp.init()
        self.n = int(n_nodes)
        self.link = float(link_length)
        self.dt = float(dt)
        self.device = str(device)
        self.iterations = int(iterations)
        self.cull = bool(cull)
        self.margin = float(0.25 * self.link if margin is None else margin)
        self.gravity = tuple(float(g) for g in gravity)
        self.workers = workers
        self.min_sep = max(2, int(min_sep))
        # fixed: the per-size unrolled kernel (kernels/rope_fast.py), same results, faster on CPU
        self.kernel = rollout_kernel
        self.lanes = 0  # chains per thread of the SIMD-lane kernel (kernels/rope_lanes.py); 0: one
        if fixed:
            from wrenorm.kernels import rope_fast, rope_lanes

            if self.n <= rope_fast.MAX_NODES:
                self.kernel = rope_fast.fast_kernel(self.n)
            # lanes fill a CPU's vector units; a GPU runs one chain per thread
            if lanes is None:
                lanes = rope_lanes.LANES if self.device.startswith("cpu") and self.n <= rope_lanes.MAX_NODES else 0
            if lanes:
                self.kernel = rope_lanes.lanes_kernel(self.n, lanes)
                self.lanes = int(lanes)
        self._loaded = False

    def rollout(self, pos0: np.ndarray, vel0: np.ndarray, hand: np.ndarray, path_index: np.ndarray,
                params: ChainParams, steps: int, t0: float = 0.0, stop_at_hit: bool = True,
                chunk: int | None = None, trajectory_every: int | None = None) -> RolloutResult:
        """pos0/vel0 (B, N, 3); hand (P, S, 3) hand samples at t0 + s dt with S > steps."""
        n, dev = self.n, self.device
        B = params.batch
        hand = np.asarray(hand, dtype=np.float32)
        if hand.ndim != 3 or hand.shape[1] <= steps:
            raise ValueError(f"hand must be (paths, >{steps}, 3), got {hand.shape}")
        pos0 = np.broadcast_to(np.asarray(pos0, np.float32), (B, n, 3))
        vel0 = np.broadcast_to(np.asarray(vel0, np.float32), (B, n, 3))
        path_index = np.broadcast_to(np.asarray(path_index, np.int32), (B,))
        f32 = lambda a: wp.array(np.ascontiguousarray(a, dtype=np.float32), dtype=float, device=dev)  # noqa: E731
        v3 = lambda a: wp.array(np.ascontiguousarray(a, dtype=np.float32), dtype=wp.vec3, device=dev)  # noqa: E731
        pos, vel = v3(pos0), v3(vel0)
        prev = wp.zeros((B, n), dtype=wp.vec3, device=dev)
        lam = wp.zeros((B, n), dtype=wp.vec3, device=dev)
        lam_link = wp.zeros((B, n), dtype=float, device=dev)
        seg = wp.zeros((B, n), dtype=wp.vec4, device=dev)
        hand_w = v3(hand)
        pidx = wp.array(np.ascontiguousarray(path_index), dtype=wp.int32, device=dev)
        pa = [f32(getattr(params, f)) for f in ChainParams.FIELDS]
        status = wp.zeros(B, dtype=wp.int32, device=dev)
        hit_frame = wp.array(np.full(B, -1, np.int32), dtype=wp.int32, device=dev)
        hit_alpha = wp.zeros(B, dtype=float, device=dev)
        hit_s = wp.zeros(B, dtype=wp.vec2, device=dev)
        crit_pos = wp.zeros((B, n), dtype=wp.vec3, device=dev)
        crit_vel = wp.zeros((B, n), dtype=wp.vec3, device=dev)
        clearance = wp.array(np.full(B, self.margin, np.float32), dtype=float, device=dev)
        if not self._loaded:
            # build before the sliced launch: two threads meeting an unbuilt module both compile it
            wp.load_module(self.kernel.module, device=dev)
            self._loaded = True
        chunk = int(trajectory_every or chunk or steps)
        frames = [pos.numpy().copy()] if trajectory_every else None
        wp.synchronize_device(dev)
        t_kernel = time.perf_counter()
        for s0 in range(0, steps, chunk):
            ns = min(chunk, steps - s0)

            def launch(offset, count, s0=s0, ns=ns):
                inputs = [pos, vel, prev, lam, lam_link, seg, hand_w, pidx, *pa,
                          n, self.min_sep, self.link, self.dt, wp.vec3(*self.gravity), self.iterations, int(self.cull),
                          self.margin, VMAX, s0, ns, int(stop_at_hit),
                          status, hit_frame, hit_alpha, hit_s, crit_pos, crit_vel, clearance, offset]
                if self.lanes:
                    wp.launch(self.kernel, dim=-(-count // self.lanes), device=dev, inputs=inputs + [offset + count])
                else:
                    wp.launch(self.kernel, dim=count, device=dev, inputs=inputs)

            launch_sliced(launch, B, dev, self.workers)
            if frames is not None:
                frames.append(pos.numpy().copy())  # CPU .numpy() is a view
        wp.synchronize_device(dev)
        # launches alone, without host<->device copies: what a GPU kernel sustains
        self.last_kernel_seconds = time.perf_counter() - t_kernel
        st = status.numpy()
        hf = hit_frame.numpy()
        ha = hit_alpha.numpy()
        hs = hit_s.numpy()
        hit = st == 1
        return RolloutResult(
            status=st, hit_frame=hf, hit_alpha=ha,
            hit_time=np.where(hit, t0 + (hf - 1 + ha.astype(np.float64)) * self.dt, np.nan),
            s_a=np.where(hit, hs[:, 0], np.nan), s_b=np.where(hit, hs[:, 1], np.nan),
            crit_pos=crit_pos.numpy(), crit_vel=crit_vel.numpy(), clearance=clearance.numpy(),
            final_pos=pos.numpy(), final_vel=vel.numpy(),
            trajectory=None if frames is None else np.stack(frames),
            trajectory_times=None if frames is None else t0 + self.dt * np.minimum(
                np.arange(len(frames)) * chunk, steps))


# ---------------------------------------------------------------------------------- helpers
def hanging_state(hand0: np.ndarray, n_nodes: int, link: float) -> tuple[np.ndarray, np.ndarray]:
    """A chain hanging straight down from the hand at rest: (N, 3) positions and velocities."""
    pos = np.asarray(hand0, np.float64)[None, :] + np.outer(np.arange(n_nodes) * link, [0.0, 0.0, 1.0]) * -1.0
    return pos.astype(np.float32), np.zeros_like(pos, dtype=np.float32)


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
        from wrenorm.kernels import rope_baselines
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
