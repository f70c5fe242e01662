"""Batched planar swimmer: a free rigid head driven by a tail with prescribed kinematics.

Every body part carries MuJoCo's stateless "ellipsoid" fluid model (mj_ellipsoidFluidModel in
engine_passive.c), restricted to motion in the horizontal plane: velocity (a, b, 0) and angular
velocity (0, 0, w) in the part's frame keep every term of that model in the plane, so the planar
formulas below are MuJoCo's exactly (checked against the `mujoco` package in
tests/test_swimmer_fluid.py).

Virtual (added) mass. MuJoCo applies only the velocity-dependent Kirchhoff terms
(m_A v) x w, (m_A v) x v; the acceleration term is "disabled due to dependency on qacc". Here the
head's acceleration is solved from the momentum balance of the whole fish, so the full Kirchhoff
force is cheap to include: with `virtual_mass=1` each part also gets -m_A (dv/dt)_body, where
(dv/dt)_body = R^T a - w x v is the rate of its body-frame velocity components; the part of it
that is linear in the head's unknown acceleration goes into the 3x3 mass matrix. With
`virtual_mass=0` the model is MuJoCo's as published (added mass acts only through velocities).

Time stepping: the forces depend on the head's velocity and the tail's phase only, never on the
head's pose, so the velocity equation M(t) dV/dt = F(V, t) is integrated on its own with ROS2 (a
second-order Rosenbrock W-method, two force evaluations per step) whose W is the parts' drag
factors: drag is linearly implicit and large drag coefficients stay stable; the pose follows with
the trapezoid rule. scheme=1 keeps the first-order linearly implicit Euler of the first version.

Equations (head frame, origin at the front head marker, x towards the tail, so the fish swims
towards -x): unknowns (du/dt, dv/dt, dw/dt) of the head's frame velocity (u, v, w). Part e sits at
p_e with angle psi_e relative to the head (tabulated per condition, candidate-independent):
    a_e = (du, dv) + dw (-p_y, p_x) + k_e,   k_e = (-w v, w u) - w^2 p + 2 w (-pd_y, pd_x) + pdd
    sum_e M_e a_e = sum_e F_e,    sum_e [p_e x M_e a_e + J_e (dw + psidd_e)] = sum_e [p_e x F_e + tau_e]
with M_e = m_e I + R_e diag(m_A) R_e^T. Everything candidate-independent (M, and the inertial
force as a polynomial in the head's velocity) is summed over parts once per tail-phase sample on
the host (reduce_table); the kernel visits only the fluid parts.

One thread simulates one (candidate, condition) pair over its whole run, state in registers, and
accumulates a least-squares line fit of the head position (the speed measurement) and the first
harmonic of the yaw rate (the head's yaw oscillation) on the fly.
"""
from __future__ import annotations

import warp as wp

from wrenorm.kernels.swimmer.fluid import fluid_planar, geo9

wp.config.quiet = True

ROW = 10  # per part per sample: px, py, cos psi, sin psi, pdx, pdy, psid, pddx, pddy, psidd


vec15 = wp.types.vector(length=15, dtype=wp.float32)
INERTIAL = 17  # per sample: 15 candidate-independent sums over all parts (reduce_table), cos, sin of the beat phase
FLUID_ROW = 7  # per fluid part per sample: px, py, cos psi, sin psi, pdx, pdy, psid


@wp.func
def fish_rhs(tab: wp.array2d(dtype=float), row: int, n_fluid: int, u: float, v: float, w: float,
             geo: wp.array(dtype=geo9), amass: wp.array(dtype=wp.vec3),
             cb: float, cs: float, ca: float, ck: float, cm: float, rho: float, mu: float, vm: float):
    """Mass matrix M (6 entries, symmetric), drag factor matrix C (6) and force F (3) of the head's
    equation M dV/dt = F(V, t) at table row `row`, for head velocity V = (u, v, w).

    The inertial part is linear in (1, w, w^2, w u, w v) with per-sample coefficients summed over
    parts on the host; only the fluid parts are visited here."""
    m00 = tab[row, 0]
    m01 = tab[row, 1]
    m11 = tab[row, 2]
    m02 = tab[row, 3]
    m12 = tab[row, 4]
    m22 = tab[row, 5]
    w2 = w * w
    # minus sum_e M_e k_e: the inertial forces of the prescribed tail motion in the moving frame
    f0 = -(m00 * (-w * v) + m01 * (w * u) - w2 * tab[row, 6] + 2.0 * w * tab[row, 9] + tab[row, 12])
    f1 = -(m01 * (-w * v) + m11 * (w * u) - w2 * tab[row, 7] + 2.0 * w * tab[row, 10] + tab[row, 13])
    f2 = -(m02 * (-w * v) + m12 * (w * u) - w2 * tab[row, 8] + 2.0 * w * tab[row, 11] + tab[row, 14])
    c00 = float(0.0)
    c02 = float(0.0)
    c12 = float(0.0)
    c22 = float(0.0)
    for e in range(n_fluid):
        o = INERTIAL + FLUID_ROW * e
        px = tab[row, o]
        py = tab[row, o + 1]
        cp = tab[row, o + 2]
        sp = tab[row, o + 3]
        vx = u - w * py + tab[row, o + 4]
        vy = v + w * px + tab[row, o + 5]
        we = w + tab[row, o + 6]
        la = cp * vx + sp * vy
        lb = -sp * vx + cp * vy
        am = amass[e]
        fl = fluid_planar(la, lb, we, geo[e], cb, cs, ca, ck, cm, rho, mu, am[0], am[1])
        # the velocity part of -m_A (dv/dt)_body: + m_A (w x v)
        lfx = fl[0] - am[0] * vm * we * lb
        lfy = fl[1] + am[1] * vm * we * la
        fx = cp * lfx - sp * lfy
        fy = sp * lfx + cp * lfy
        f0 += fx
        f1 += fy
        f2 += px * fy - py * fx + fl[2]
        d = fl[3]
        # linear drag acts on v_e = V + w r_e + pd_e, r_e = (-py, px)
        c00 += d
        c02 -= d * py
        c12 += d * px
        c22 += d * (px * px + py * py) + fl[4]
    return vec15(m00, m01, m11, m02, m12, m22, c00, 0.0, c00, c02, c12, c22, f0, f1, f2)


@wp.func
def solve_sym3(a00: float, a01: float, a11: float, a02: float, a12: float, a22: float,
               r0: float, r1: float, r2: float):
    """Cramer on a symmetric 3x3."""
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    inv = 1.0 / (a00 * c00 + a01 * c01 + a02 * c02)
    return wp.vec3((c00 * r0 + c01 * r1 + c02 * r2) * inv, (c01 * r0 + c11 * r1 + c12 * r2) * inv,
                   (c02 * r0 + c12 * r1 + c22 * r2) * inv)


# L-stable ROS2 (Verwer et al. 1999): second order for any approximation W of the Jacobian, here the
# drag factors only; gamma = 1 + 1/sqrt(2)
ROS2_GAMMA = 1.7071067811865475


@wp.kernel
def swim_kernel(offset: int, n_cond: int,
                coef: wp.array2d(dtype=float),        # (B, 5)
                tab: wp.array2d(dtype=float),         # (samples, INERTIAL + FLUID_ROW * fluid parts)
                n_fluid: int,
                geo: wp.array(dtype=geo9),            # (fluid parts,) fluid_geometry(semi)
                amass: wp.array(dtype=wp.vec3),       # (fluid parts,) rho * (m_A x, m_A y, I_A z)
                v0: wp.array(dtype=wp.vec3),          # (conditions,) zero-momentum start velocity
                tab_off: wp.array(dtype=int), n_per: wp.array(dtype=int), dt_c: wp.array(dtype=float),
                n_warm: wp.array(dtype=int), n_meas: wp.array(dtype=int), max_warm: wp.array(dtype=int),
                settle_abs: float, settle_rel: float, ref_x: float, rho: float, mu: float, virtual_mass: int,
                scheme: int,
                rec_stride: int, traj: wp.array3d(dtype=float),   # (n, frames, 4): X, Y, theta, sample
                speed: wp.array(dtype=float), yaw: wp.array(dtype=float), state: wp.array2d(dtype=float)):
    tid = wp.tid() + offset
    b = tid / n_cond
    c = tid - b * n_cond
    cb = coef[b, 0]
    cs = coef[b, 1]
    ca = coef[b, 2]
    ck = coef[b, 3]
    cm = coef[b, 4]
    off = tab_off[c]
    per = n_per[c]
    dt = dt_c[c]
    nw = n_warm[c]
    nm = n_meas[c]
    vm = float(virtual_mass)
    gam = float(ROS2_GAMMA)

    X = float(0.0)
    Y = float(0.0)
    th = float(0.0)
    vel0 = v0[c]
    u = vel0[0]
    v = vel0[1]
    w = vel0[2]

    # least-squares sums for the speed (float64: thousands of samples)
    s_n = wp.float64(0.0)
    s_t = wp.float64(0.0)
    s_x = wp.float64(0.0)
    s_y = wp.float64(0.0)
    s_tt = wp.float64(0.0)
    s_tx = wp.float64(0.0)
    s_ty = wp.float64(0.0)
    s_xx = wp.float64(0.0)
    s_yy = wp.float64(0.0)
    s_xy = wp.float64(0.0)
    s_c = wp.float64(0.0)
    s_s = wp.float64(0.0)
    # first harmonic of the yaw rate at the beat frequency (the head's yaw oscillation)
    s_wc = float(0.0)
    s_ws = float(0.0)

    # warm-up: whole beats until the beat-averaged surge settles (at least nw steps, at most
    # max_warm); quadratic drag makes slow candidates creep up to cruising speed for many beats
    k = int(0)
    rec_i = int(0)
    step = int(0)
    meas_start = int(-1)
    mw = max_warm[c]
    beat_u = float(0.0)
    prev_u = float(1.0e9)
    while meas_start < 0 or step < meas_start + nm:
        ct = wp.cos(th)
        st = wp.sin(th)
        if meas_start >= 0:
            s_wc += w * tab[off + k, 15]
            s_ws += w * tab[off + k, 16]
            hx = wp.float64(X + ct * ref_x)
            hy = wp.float64(Y + st * ref_x)
            tt = wp.float64(float(step - meas_start) * dt)
            s_n += wp.float64(1.0)
            s_t += tt
            s_x += hx
            s_y += hy
            s_tt += tt * tt
            s_tx += tt * hx
            s_ty += tt * hy
            s_xx += hx * hx
            s_yy += hy * hy
            s_xy += hx * hy
            s_c += wp.float64(ct)
            s_s += wp.float64(st)
        if rec_stride > 0:
            if step % rec_stride == 0:
                if rec_i < traj.shape[1]:
                    traj[tid, rec_i, 0] = X
                    traj[tid, rec_i, 1] = Y
                    traj[tid, rec_i, 2] = th
                    traj[tid, rec_i, 3] = float(k)
                    rec_i += 1

        s1 = fish_rhs(tab, off + k, n_fluid, u, v, w, geo, amass, cb, cs, ca, ck, cm, rho, mu, vm)
        if scheme == 1:
            # linearly implicit Euler: (M + dt C) dV = dt F(V); pose with the new velocity
            dv = solve_sym3(s1[0] + dt * s1[6], s1[1], s1[2] + dt * s1[8], s1[3] + dt * s1[9],
                            s1[4] + dt * s1[10], s1[5] + dt * s1[11], s1[12], s1[13], s1[14])
            u += dt * dv[0]
            v += dt * dv[1]
            w += dt * dv[2]
            X += dt * (ct * u - st * v)
            Y += dt * (st * u + ct * v)
            th += dt * w
        else:
            # ROS2 on (V, pose): (M + g dt C) k1 = F(V_n, t_n); V' = V_n + dt k1;
            # (M + g dt C) k2 = M (M_{n+1}^-1 F(V', t_{n+1}) - 2 k1); V_{n+1} = V_n + dt (3 k1 + k2) / 2
            g00 = s1[0] + gam * dt * s1[6]
            g11 = s1[2] + gam * dt * s1[8]
            g02 = s1[3] + gam * dt * s1[9]
            g12 = s1[4] + gam * dt * s1[10]
            g22 = s1[5] + gam * dt * s1[11]
            k1 = solve_sym3(g00, s1[1], g11, g02, g12, g22, s1[12], s1[13], s1[14])
            u2 = u + dt * k1[0]
            v2 = v + dt * k1[1]
            w2 = w + dt * k1[2]
            k_next = k + 1
            if k_next >= per:
                k_next = 0
            s2 = fish_rhs(tab, off + k_next, n_fluid, u2, v2, w2, geo, amass, cb, cs, ca, ck, cm, rho, mu, vm)
            a2 = solve_sym3(s2[0], s2[1], s2[2], s2[3], s2[4], s2[5], s2[12], s2[13], s2[14])
            e0 = a2[0] - 2.0 * k1[0]
            e1 = a2[1] - 2.0 * k1[1]
            e2 = a2[2] - 2.0 * k1[2]
            k2 = solve_sym3(g00, s1[1], g11, g02, g12, g22,
                            s1[0] * e0 + s1[1] * e1 + s1[3] * e2,
                            s1[1] * e0 + s1[2] * e1 + s1[4] * e2,
                            s1[3] * e0 + s1[4] * e1 + s1[5] * e2)
            # the pose has no implicit part: the scheme reduces to the trapezoid (Heun) there
            th2 = th + dt * w
            c2 = wp.cos(th2)
            sn2 = wp.sin(th2)
            X += 0.5 * dt * (ct * u - st * v + c2 * u2 - sn2 * v2)
            Y += 0.5 * dt * (st * u + ct * v + sn2 * u2 + c2 * v2)
            th += 0.5 * dt * (w + w2)
            u += dt * (1.5 * k1[0] + 0.5 * k2[0])
            v += dt * (1.5 * k1[1] + 0.5 * k2[1])
            w += dt * (1.5 * k1[2] + 0.5 * k2[2])
        k += 1
        step += 1
        if meas_start < 0:
            beat_u += u
        if k >= per:
            k = 0
            if meas_start < 0:
                avg = beat_u / float(per)
                if step >= nw:
                    if wp.abs(avg - prev_u) <= settle_abs + settle_rel * wp.abs(avg) or step >= mw:
                        meas_start = step
                prev_u = avg
                beat_u = float(0.0)

    # straight-line fit: principal direction of the path, oriented along the mean heading (-x)
    n = s_n
    cxx = s_xx / n - (s_x / n) * (s_x / n)
    cyy = s_yy / n - (s_y / n) * (s_y / n)
    cxy = s_xy / n - (s_x / n) * (s_y / n)
    ctx = s_tx / n - (s_t / n) * (s_x / n)
    cty = s_ty / n - (s_t / n) * (s_y / n)
    ctt = s_tt / n - (s_t / n) * (s_t / n)
    ang = wp.float64(0.5) * wp.atan2(wp.float64(2.0) * cxy, cxx - cyy)
    dx = wp.cos(ang)
    dy = wp.sin(ang)
    if dx * (-s_c) + dy * (-s_s) < wp.float64(0.0):
        dx = -dx
        dy = -dy
    speed[tid] = float((dx * ctx + dy * cty) / ctt)
    yaw[tid] = 2.0 * wp.sqrt(s_wc * s_wc + s_ws * s_ws) / (float(nm) * 2.0 * 3.14159265358979 / (float(per) * dt))
    state[tid, 0] = X
    state[tid, 1] = Y
    state[tid, 2] = th
    state[tid, 3] = u
    state[tid, 4] = v
    state[tid, 5] = w
    state[tid, 6] = float(meas_start) * dt


