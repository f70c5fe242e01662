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
critical positions x_{k-1} + alpha (x_k - x_{k-1}) and critical velocities (x_k - x_{k-1}) / dt
(the velocity the position-based step carries over that interval), and the arc-length
fractions of the closest points of the hit pair at frame k (as tasks/rope_collision.py does).

`clearance` is min over frames and pairs of min(gap, margin): continuous in the state and equal
under culling and all-pairs; searches use it to pull non-colliding chains toward a collision.
Status: 0 no hit yet, 1 hit, 2 blew up (non-finite or speed above vmax).
"""
from __future__ import annotations

import warp as wp

from wrenorm.kernels.rope.model import FORWARD_OPTIONS, node_w, seg_closest

wp.set_module_options(FORWARD_OPTIONS)


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


