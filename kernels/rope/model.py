"""The coarse rope chain's one definition: its state, parameters, settings and first-contact record as Warp
structs (every rollout variant takes the same four), and the pieces of its step (per-chain constants,
node prediction, the bending and link projections, segment distance, the first-contact candidate).

Every rollout variant (generic.py, fixed.py, lanes.py, tiled.py, grad.py) steps the model through these, so all
of them step the same model; the faster variants are tested bit for bit against generic.py.
"""
from __future__ import annotations

from typing import Any

import warp as wp

GRAVITY = (0.0, 0.0, -9.81)  # z up, as in newton
VMAX = 1.0e3  # m/s; a node faster than this means the step blew up
# forward-only modules (the tape-safe variant sets its own); -march=native lets clang use the host's SIMD and
# FMA for the per-chain arithmetic. No fast-math: blow-up detection needs NaN.
FORWARD_OPTIONS = {"enable_backward": False, "optimization_level": 3, "cpu_compiler_flags": "-march=native"}


@wp.func
def spheres_apart(sa: wp.vec4, sb: wp.vec4, two_r: float, margin: float) -> bool:
    """Two segments' bounding spheres (centre, half length) are farther apart than contact plus the margin, with a
    relative and an absolute allowance for rounding: the pair cannot touch, and is culled."""
    dx = sa[0] - sb[0]
    dy = sa[1] - sb[1]
    dz = sa[2] - sb[2]
    reach = (sa[3] + sb[3] + two_r + margin) * 1.00001 + 1.0e-6
    return dx * dx + dy * dy + dz * dz > reach * reach


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



@wp.struct
class ChainState:
    """Per chain and node: positions, velocities, positions at the start of the step, velocities of the step
    before (the generic kernel's, for record_hit), bending and link multipliers, and segment bounding spheres
    (midpoint, half length); and the recorded trajectory, frames[f] the positions after step
    min(f * frame_every, frame_end) (ChainSettings), written by the kernel itself."""

    pos: wp.array2d(dtype=wp.vec3)
    vel: wp.array2d(dtype=wp.vec3)
    prev: wp.array2d(dtype=wp.vec3)
    prev_vel: wp.array2d(dtype=wp.vec3)
    lam: wp.array2d(dtype=wp.vec3)
    lam_link: wp.array2d(dtype=float)
    seg: wp.array2d(dtype=wp.vec4)
    frames: wp.array3d(dtype=wp.vec3)  # (frames, chains, nodes); frame 0, the initial state, is the caller's


@wp.struct
class ChainParameters:
    """Per chain (see sim.ChainParams for units)."""

    node_mass: wp.array(dtype=float)
    lead_mass: wp.array(dtype=float)
    bend_k: wp.array(dtype=float)
    bend_b: wp.array(dtype=float)
    drag_lin: wp.array(dtype=float)
    drag_quad: wp.array(dtype=float)
    radius: wp.array(dtype=float)
    mass_slope: wp.array(dtype=float)
    stretch: wp.array(dtype=float)


@wp.struct
class ChainSettings:
    """What every chain of a launch shares: the resolution and the collision test's settings."""

    n: int  # nodes
    min_sep: int  # segment pairs closer than this along the chain are bending, not contact
    link: float  # m
    dt: float  # s
    gravity: wp.vec3
    iters: int  # constraint passes per step
    cull: int  # 1: skip pairs that provably cannot touch (results identical to testing all pairs)
    margin: float  # m, the clearance below which a pair counts toward `clearance`
    vmax: float  # m/s, faster means the step blew up
    frame_every: int  # steps between recorded frames (ChainState.frames); 0: no trajectory
    frame_end: int  # the rollout's last step, recorded whether or not a multiple of frame_every


@wp.struct
class ChainEvents:
    """Per chain: status (0 no hit yet, 1 hit, 2 blew up), the first hit's frame, its fraction of the step,
    arc-length fractions of the hit pair, the state at the hit, and the closest approach so far."""

    status: wp.array(dtype=wp.int32)
    hit_frame: wp.array(dtype=wp.int32)
    hit_alpha: wp.array(dtype=float)
    hit_s: wp.array(dtype=wp.vec2)
    crit_pos: wp.array2d(dtype=wp.vec3)
    crit_vel: wp.array2d(dtype=wp.vec3)
    clearance: wp.array(dtype=float)


@wp.func
def chain_constants(p: ChainParameters, cfg: ChainSettings, b: int):
    """Per-chain constants of the step: node mass, lead mass, mass slope, XPBD bending compliance / dt^2,
    bending damping factor, link compliance / dt^2, linear and quadratic drag."""
    link = cfg.link
    dt = cfg.dt
    k = wp.max(p.bend_k[b], 1.0e-12)
    alpha_t = link * link / (k * dt * dt)
    gamma = p.bend_b[b] / (k * dt)
    at_s = p.stretch[b] / (dt * dt)
    return p.node_mass[b], p.lead_mass[b], p.mass_slope[b], alpha_t, gamma, at_s, p.drag_lin[b], p.drag_quad[b]


@wp.func
def predict(x: wp.vec3, v: wp.vec3, w: float, li: float, dl: float, dq: float, dt: float, gravity: wp.vec3):
    """Forces (gravity, implicit per-node drag over rope length li, so any drag coefficient is stable) and the
    predicted position: (x + dt v', v')."""
    c = (dl + dq * wp.length(v)) * li
    # one division per node (a vector divide is three)
    vn = (v + dt * gravity) * (1.0 / (1.0 + dt * c * w))
    return x + dt * vn, vn


@wp.func
def bend_project(x0: wp.vec3, x1: wp.vec3, x2: wp.vec3, c_start: wp.vec3, lm: wp.vec3, w0: float, w1: float,
                 w2: float, inv: float, alpha_t: float, gamma: float):
    """One XPBD bending projection of a triplet on its curvature vector C = x0 - 2 x1 + x2, with damping
    against C's change since the start of the step; inv = 1 / ((1 + gamma)(w0 + 4 w1 + w2) + alpha_t)."""
    cv = x0 - 2.0 * x1 + x2
    dcv = cv - c_start
    dlam = (-cv - alpha_t * lm - gamma * dcv) * inv
    return x0 + w0 * dlam, x1 - (2.0 * w1) * dlam, x2 + w2 * dlam, lm + dlam


@wp.func
def link_project(xa: wp.vec3, xb: wp.vec3, ll: float, link: float, at_s: float, fa: float, fb: float, den: float):
    """One XPBD link projection onto |xb - xa| = link (compliance at_s); fa, fb the mass-weighted shares of
    the correction, den = wa + wb + at_s. Exact, not first-order: a sqrt-free factor diverges once a whipping
    tip stretches a link past ~2.4 links in one step."""
    d = xb - xa
    ln = wp.length(d)
    e = ln - link + at_s * ll  # C + alpha~ lambda (C alone when inextensible)
    corr = wp.vec3(0.0)
    lln = ll
    if ln > 1.0e-9:
        corr = d * (e / ln)
        lln = ll - e / den
    return xa + fa * corr, xb - fb * corr, lln


@wp.func
def first_contact(gap: float, qa0: wp.vec3, qa1: wp.vec3, qb0: wp.vec3, qb1: wp.vec3, two_r: float, a: int,
                  j: int, best: float, best_a: int, best_b: int):
    """A pair (a, j) whose gap closed in this step: its crossing fraction alpha = g0 / (g0 - g1) from the gap
    at the start of the step (0 if it already touched); the smallest alpha of the step is the first hit."""
    r0 = seg_closest(qa0, qa1, qb0, qb1)
    g0 = r0[0] - two_r
    al = float(0.0)
    if g0 > 0.0:
        al = g0 / (g0 - gap)
    nb = best
    na = best_a
    nj = best_b
    if al < best:
        nb = al
        na = a
        nj = j
    return nb, na, nj


# The one signature of every rollout variant (generic.py, fixed.py, lanes.py, tiled.py): the same launch serves
# them all.
ROLLOUT_ARGUMENTS = {
    "state": ChainState,
    "hand": wp.array2d(dtype=wp.vec3),  # (paths, steps + 1) hand samples
    "path_index": wp.array(dtype=wp.int32),  # per chain
    "params": ChainParameters,
    "cfg": ChainSettings,
    "step0": int,  # first step of this launch
    "nsteps": int,
    "stop_at_hit": int,
    "events": ChainEvents,
    "offset": int,  # first chain of this launch's slice of the batch
    "end": int,  # one past its last chain
}


def rollout_variant(**kernel_options):
    """Decorator: a Warp kernel with the rollout signature (ROLLOUT_ARGUMENTS); the variant's Python function
    names the arguments only."""
    def wrap(fn):
        fn.__annotations__ = dict(ROLLOUT_ARGUMENTS)
        return wp.kernel(fn, **kernel_options)

    return wrap


@wp.func
def running(status: int, stop_at_hit: int) -> int:
    """1 if a chain with this status still steps in this launch (not blown up, not stopped at its hit)."""
    out = int(1)
    if status == 2 or (status == 1 and stop_at_hit != 0):
        out = 0
    return out


@wp.func
def hit_velocity(v: wp.vec3, v_before: wp.vec3, alpha: float, step: int) -> wp.vec3:
    """A node's velocity at the crossing, alpha of the way through `step`. A position-based step's velocity
    (x_end - x_start) / dt is its mean over the step, the velocity at mid-step; the crossing's follows linearly in
    time from it and the step before's, at mid-step too, except in a rollout's first step, where the velocity
    before is the start's own, at the step's start. The step's mean alone is up to a dt / 2 off and jumps by a dt
    wherever a command moves the crossing into the next step, a staircase in the command that a central difference
    over a few steps' worth of event time reads as all or nothing (README, "The velocity at the contact")."""
    c = wp.where(step == 0, 2.0 * alpha - 1.0, alpha - 0.5)
    return v + c * (v - v_before)


@wp.func
def record_hit(events: ChainEvents, b: int, step: int, best: float, best_a: int, best_b: int, P: Any, Q: Any, V: Any,
               VB: Any, nm1: int):
    """Chain b's first hit in `step`: the state interpolated to the crossing (positions from the step's start Q
    and end P, velocities from the step's V and the step before's VB), and the arc-length fractions of the hit
    pair's closest points."""
    events.status[b] = 1
    events.hit_frame[b] = step + 1
    events.hit_alpha[b] = best
    for i in range(nm1 + 1):
        p0 = Q[i]
        events.crit_pos[b, i] = p0 + best * (P[i] - p0)
        events.crit_vel[b, i] = hit_velocity(V[i], VB[i], best, step)
    res = seg_closest(P[best_a], P[best_a + 1], P[best_b], P[best_b + 1])
    events.hit_s[b] = wp.vec2((float(best_a) + res[1]) / float(nm1), (float(best_b) + res[2]) / float(nm1))


@wp.func
def frame_after(step: int, every: int, end: int) -> int:
    """The trajectory frame that records the positions after `step`, -1 if none records them (or no trajectory is
    recorded: every = 0). Frames every `every` steps, and one at the rollout's last step `end`."""
    s = step + 1
    f = int(-1)
    if every > 0:
        if s % every == 0:
            f = s // every
        elif s == end:
            f = s // every + 1
    return f


@wp.func
def frames_from(step: int, every: int, end: int) -> wp.vec2i:
    """The frames [first, last] a chain that finishes in `step` (blows up, or stops at its hit) fills with its
    final state: every frame recorded after `step`, to the end of the rollout ([0, -1] without a trajectory)."""
    out = wp.vec2i(0, -1)
    if every > 0:
        out = wp.vec2i((step + every) // every, (end + every - 1) // every)
    return out


@wp.func
def inverse_masses(W: Any, n: int, m: float, ml: float, slope: float):
    """W[i] = node_w(i, ...) for every node: the per-node inverse masses, once per launch."""
    for i in range(n):
        W[i] = node_w(i, n, m, ml, slope)
    return W


@wp.func
def bend_lanes(x0: Any, x1: Any, x2: Any, c_start: Any, lm: Any, alpha_t: Any, gamma: Any, inv: Any, w0: Any, w1: Any,
               w2: Any):
    """bend_project for one coordinate of many chains at once (vectors over the lanes), the same arithmetic
    lane by lane."""
    cv = x0 - 2.0 * x1 + x2
    dlam = wp.cw_mul(-cv - wp.cw_mul(alpha_t, lm) - wp.cw_mul(gamma, cv - c_start), inv)
    return x0 + wp.cw_mul(w0, dlam), x1 - wp.cw_mul(2.0 * w1, dlam), x2 + wp.cw_mul(w2, dlam), lm + dlam
