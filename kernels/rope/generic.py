"""The size-generic rollout kernel of the coarse rope chain: (flying-knot model) with first self-collision detection.

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
critical positions x_{k-1} + alpha (x_k - x_{k-1}) and critical velocities at the same time, from the velocity the
position-based step carries over that interval, (x_k - x_{k-1}) / dt, and the interval's before (model.hit_velocity),
and the arc-length
fractions of the closest points of the hit pair at frame k (as tasks/rope_collision.py does).

`clearance` is min over frames and pairs of min(gap, margin): continuous in the state and equal
under culling and all-pairs; searches use it to pull non-colliding chains toward a collision.
Status: 0 no hit yet, 1 hit, 2 blew up (non-finite or speed above vmax).
"""
from __future__ import annotations

import warp as wp

from wrenorm.kernels.rope.model import (
    FORWARD_OPTIONS,
    ChainState,
    bend_project,
    chain_constants,
    first_contact,
    frame_after,
    frames_from,
    link_project,
    node_w,
    predict,
    record_hit,
    rollout_variant,
    running,
    seg_closest,
    spheres_apart,
)

wp.set_module_options(FORWARD_OPTIONS)


@wp.func
def fill_remaining_frames(state: ChainState, b: int, n: int, step: int, every: int, end: int):
    """A chain that stops in `step` (blown up, or at its hit) keeps its final positions in every frame still to come."""
    fr = frames_from(step, every, end)
    for k in range(fr[0], fr[1] + 1):
        for i in range(n):
            state.frames[k, b, i] = state.pos[b, i]


@rollout_variant()
def rollout_kernel(state, hand, path_index, params, cfg, step0, nsteps, stop_at_hit, events, offset, end):
    b = wp.tid() + offset
    st = events.status[b]
    if running(st, stop_at_hit) == 0:
        return
    pos = state.pos
    prev = state.prev
    m, ml, slope, alpha_t, gamma, at_s, dl, dq = chain_constants(params, cfg, b)
    n = cfg.n
    dt = cfg.dt
    link = cfg.link
    two_r = 2.0 * params.radius[b]
    margin = cfg.margin
    cl = events.clearance[b]
    vmax2 = cfg.vmax * cfg.vmax
    inv_dt = 1.0 / dt
    nseg = n - 1
    for step in range(step0, step0 + nsteps):
        # 1-2: forces (implicit per node) and prediction
        prev[b, 0] = pos[b, 0]
        pos[b, 0] = hand[path_index[b], step + 1]
        for i in range(1, n):
            xi = pos[b, i]
            prev[b, i] = xi
            li = link
            if i == n - 1:
                li = 0.5 * link
            xn, vn = predict(xi, state.vel[b, i], node_w(i, n, m, ml, slope), li, dl, dq, dt, cfg.gravity)
            pos[b, i] = xn
            state.lam[b, i] = wp.vec3(0.0)
            state.lam_link[b, i - 1] = 0.0
        # 3: constraint passes in colour order: constraints of one colour share no node, so
        # they are independent and the CPU overlaps them (a plain Gauss-Seidel sweep is one
        # serial dependency chain and runs at the latency of sqrt/div, 3x slower).
        for _ in range(cfg.iters):
            for colour in range(3):
                for i in range(1 + colour, n - 1, 3):
                    # plain path: masses recomputed per constraint (fixed.py precomputes them)
                    w0 = node_w(i - 1, n, m, ml, slope)
                    w1 = node_w(i, n, m, ml, slope)
                    w2 = node_w(i + 1, n, m, ml, slope)
                    inv = 1.0 / ((1.0 + gamma) * (w0 + 4.0 * w1 + w2) + alpha_t)
                    x0, x1, x2, lm = bend_project(pos[b, i - 1], pos[b, i], pos[b, i + 1],
                                                  prev[b, i - 1] - 2.0 * prev[b, i] + prev[b, i + 1], state.lam[b, i],
                                                  w0, w1, w2, inv, alpha_t, gamma)
                    pos[b, i - 1] = x0
                    pos[b, i] = x1
                    pos[b, i + 1] = x2
                    state.lam[b, i] = lm
            for parity in range(2):
                for i in range(parity, n - 1, 2):
                    wa = node_w(i, n, m, ml, slope)
                    wb = node_w(i + 1, n, m, ml, slope)
                    den = wa + wb + at_s
                    xa, xb, ll = link_project(pos[b, i], pos[b, i + 1], state.lam_link[b, i], link, at_s, wa / den,
                                              wb / den, den)
                    pos[b, i] = xa
                    pos[b, i + 1] = xb
                    state.lam_link[b, i] = ll
        # 4: velocities (the step before's kept for the hit's, record_hit)
        vv = float(0.0)
        for i in range(n):
            v = (pos[b, i] - prev[b, i]) * inv_dt
            state.prev_vel[b, i] = state.vel[b, i]
            state.vel[b, i] = v
            vv = vv + wp.dot(v, v)  # a sum propagates NaN (max would drop it)
        if not (vv < vmax2):
            events.status[b] = 2
            events.clearance[b] = cl
            fill_remaining_frames(state, b, n, step, cfg.frame_every, cfg.frame_end)
            return
        # 5: self-collision
        for a in range(nseg):
            pa = pos[b, a]
            pb = pos[b, a + 1]
            mid = 0.5 * (pa + pb)
            state.seg[b, a] = wp.vec4(mid[0], mid[1], mid[2], 0.5 * wp.length(pb - pa))
        best = float(2.0)
        best_a = int(-1)
        best_b = int(-1)
        for a in range(nseg - cfg.min_sep):
            sa = state.seg[b, a]
            for j in range(a + cfg.min_sep, nseg):
                sb = state.seg[b, j]
                far = spheres_apart(sa, sb, two_r, margin)
                if cfg.cull == 0 or not far:
                    res = seg_closest(pos[b, a], pos[b, a + 1], pos[b, j], pos[b, j + 1])
                    gap = res[0] - two_r
                    if not far:
                        cl = wp.min(cl, wp.min(gap, margin))
                    if gap <= 0.0 and st == 0:
                        best, best_a, best_b = first_contact(gap, prev[b, a], prev[b, a + 1], prev[b, j],
                                                             prev[b, j + 1], two_r, a, j, best, best_a, best_b)
                elif margin < cl:
                    cl = margin
        if best_a >= 0:
            st = 1
            record_hit(events, b, step, best, best_a, best_b, pos[b], prev[b], state.vel[b], state.prev_vel[b], nseg)
            if stop_at_hit != 0:
                events.clearance[b] = cl
                fill_remaining_frames(state, b, n, step, cfg.frame_every, cfg.frame_end)
                return
        frame = frame_after(step, cfg.frame_every, cfg.frame_end)
        if frame >= 0:
            for i in range(n):
                state.frames[frame, b, i] = pos[b, i]
    events.clearance[b] = cl
