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

# forward only: nothing differentiates the swimmer, and the adjoint of the step loop (255 registers and a 448-byte
# stack frame on sm_90, against 141 and 72 for the forward kernel) is built for nothing
wp.set_module_options({"enable_backward": False})

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


@wp.struct
class Schedule:
    """Per condition (motor rate): its rows in the table, samples per tail beat, step, warm-up (at least,
    at most) and measured steps; and when the warm-up counts as settled (beat-averaged surge change
    below settle_abs + settle_rel |surge|)."""

    tab_off: wp.array(dtype=int)
    n_per: wp.array(dtype=int)
    dt: wp.array(dtype=float)
    n_warm: wp.array(dtype=int)
    n_meas: wp.array(dtype=int)
    max_warm: wp.array(dtype=int)
    settle_abs: float
    settle_rel: float


@wp.struct
class Water:
    """The fluid (density, viscosity), whether the added mass acts through accelerations too, and the head
    point whose speed is measured (x in the head frame)."""

    rho: float
    mu: float
    virtual_mass: int
    ref_x: float


vec12d = wp.types.vector(length=12, dtype=wp.float64)


@wp.func
def line_sums_add(acc: vec12d, tt: wp.float64, hx: wp.float64, hy: wp.float64, ct: float, st: float):
    """Running sums for the straight-line speed fit (float64: thousands of samples): n, t, x, y, tt, tx, ty,
    xx, yy, xy and the heading's cos, sin."""
    return acc + vec12d(wp.float64(1.0), tt, hx, hy, tt * tt, tt * hx, tt * hy, hx * hx, hy * hy, hx * hy,
                        wp.float64(ct), wp.float64(st))


@wp.func
def line_speed(acc: vec12d) -> float:
    """Slope of the head's position along the principal direction of its path, oriented along the mean
    heading (-x of the head frame): the forward speed as measured on the real fish."""
    n = acc[0]
    cxx = acc[7] / n - (acc[2] / n) * (acc[2] / n)
    cyy = acc[8] / n - (acc[3] / n) * (acc[3] / n)
    cxy = acc[9] / n - (acc[2] / n) * (acc[3] / n)
    ctx = acc[5] / n - (acc[1] / n) * (acc[2] / n)
    cty = acc[6] / n - (acc[1] / n) * (acc[3] / n)
    ctt = acc[4] / n - (acc[1] / n) * (acc[1] / n)
    ang = wp.float64(0.5) * wp.atan2(wp.float64(2.0) * cxy, cxx - cyy)
    dx = wp.cos(ang)
    dy = wp.sin(ang)
    if dx * (-acc[10]) + dy * (-acc[11]) < wp.float64(0.0):
        dx = -dx
        dy = -dy
    return float((dx * ctx + dy * cty) / ctt)


SETTLE_BEATS = wp.constant(2)  # consecutive calm beat-to-beat changes that end the warm-up


@wp.func
def beat_advance(k: int, step: int, per: int, meas_start: int, beat_u: float, prev_u: float, calm: int, u: float,
                 nw: int, mw: int, settle_abs: float, settle_rel: float):
    """One step along the tail beat. Warm-up runs whole beats until the beat-averaged surge settles (at least
    nw steps, at most mw; quadratic drag makes slow candidates creep up to cruising speed for many beats),
    then the measurement starts. Settled: SETTLE_BEATS consecutive beat-to-beat changes within tolerance; one
    alone is met at a turning point of a slow start-up (e.g. Kutta lift x0.95 near blunt 0.26, slender 0.54:
    measured at 2.7 s instead of 13 s, speed 0.0075 instead of 0.080 m/s), which made the speed jump between
    neighbouring coefficients. Returns (k, step, meas_start, beat_u, prev_u, calm)."""
    k += 1
    step += 1
    if meas_start < 0:
        beat_u += u
    if k >= per:
        k = 0
        if meas_start < 0:
            avg = beat_u / float(per)
            if wp.abs(avg - prev_u) <= settle_abs + settle_rel * wp.abs(avg):
                calm += 1
            else:
                calm = 0
            if step >= nw:
                if calm >= SETTLE_BEATS or step >= mw:
                    meas_start = step
            prev_u = avg
            beat_u = float(0.0)
    return k, step, meas_start, beat_u, prev_u, calm


@wp.func
def record_pose(traj: wp.array3d(dtype=float), tid: int, rec_i: int, step: int, rec_stride: int, rec_meas: int,
                meas_start: int, X: float, Y: float, th: float, k: int) -> int:
    """Every rec_stride steps, the head pose and tail phase sample into traj[tid]; returns the next slot. Counted
    from the start, or (rec_meas) from the measurement start, so that the recorded frames are the states the
    speed's line fit sees."""
    out = rec_i
    rec_step = step
    if rec_meas != 0:
        rec_step = step - meas_start
        if meas_start < 0:
            rec_step = -1
    if rec_stride > 0 and rec_step >= 0:
        if rec_step % rec_stride == 0 and rec_i < traj.shape[1]:
            traj[tid, rec_i, 0] = X
            traj[tid, rec_i, 1] = Y
            traj[tid, rec_i, 2] = th
            traj[tid, rec_i, 3] = float(k)
            out = rec_i + 1
    return out


@wp.func
def slot_coefficients(coef: wp.array2d(dtype=float), tid: int, n_cond: int, mu: float):
    """Slot tid = candidate b x condition c: (c, the candidate's five coefficients, its viscosity): a sixth
    column of coef, where there is one, is the viscosity [Pa s] (an effective parameter); else the water's."""
    b = tid / n_cond
    visc = mu
    if coef.shape[1] > 5:
        visc = coef[b, 5]
    return tid - b * n_cond, coef[b, 0], coef[b, 1], coef[b, 2], coef[b, 3], coef[b, 4], visc


@wp.kernel
def swim_kernel(offset: int, n_cond: int,
                coef: wp.array2d(dtype=float),        # (B, 5) or (B, 6): + viscosity [Pa s]
                tab: wp.array2d(dtype=float),         # (samples, INERTIAL + FLUID_ROW * fluid parts)
                n_fluid: int,
                geo: wp.array(dtype=geo9),            # (fluid parts,) fluid_geometry(semi)
                amass: wp.array(dtype=wp.vec3),       # (fluid parts,) rho * (m_A x, m_A y, I_A z)
                v0: wp.array(dtype=wp.vec3),          # (conditions,) zero-momentum start velocity
                sched: Schedule, water: Water,
                scheme: int,
                rec_stride: int, rec_meas: int,
                traj: wp.array3d(dtype=float),        # (n, frames, 4): X, Y, theta, beat sample
                speed: wp.array(dtype=float), yaw: wp.array(dtype=float), state: wp.array2d(dtype=float)):
    tid = wp.tid() + offset
    c, cb, cs, ca, ck, cm, mu = slot_coefficients(coef, tid, n_cond, water.mu)
    off = sched.tab_off[c]
    per = sched.n_per[c]
    dt = sched.dt[c]
    nw = sched.n_warm[c]
    nm = sched.n_meas[c]
    rho = water.rho
    ref_x = water.ref_x
    vm = float(water.virtual_mass)
    gam = float(ROS2_GAMMA)

    X = float(0.0)
    Y = float(0.0)
    th = float(0.0)
    vel0 = v0[c]
    u = vel0[0]
    v = vel0[1]
    w = vel0[2]

    acc = vec12d()  # running sums of the straight-line speed fit
    # first harmonic of the yaw rate at the beat frequency (the head's yaw oscillation)
    s_wc = float(0.0)
    s_ws = float(0.0)

    # warm-up: whole beats until the beat-averaged surge settles (at least nw steps, at most
    # max_warm); quadratic drag makes slow candidates creep up to cruising speed for many beats
    k = int(0)
    rec_i = int(0)
    step = int(0)
    meas_start = int(-1)
    mw = sched.max_warm[c]
    beat_u = float(0.0)
    prev_u = float(1.0e9)
    calm = int(0)
    while meas_start < 0 or step < meas_start + nm:
        ct = wp.cos(th)
        st = wp.sin(th)
        if meas_start >= 0:
            s_wc += w * tab[off + k, 15]
            s_ws += w * tab[off + k, 16]
            acc = line_sums_add(acc, wp.float64(float(step - meas_start) * dt), wp.float64(X + ct * ref_x),
                                wp.float64(Y + st * ref_x), ct, st)
        rec_i = record_pose(traj, tid, rec_i, step, rec_stride, rec_meas, meas_start, X, Y, th, k)

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
        k, step, meas_start, beat_u, prev_u, calm = beat_advance(k, step, per, meas_start, beat_u, prev_u, calm, u,
                                                                 nw, mw, sched.settle_abs, sched.settle_rel)

    speed[tid] = line_speed(acc)
    yaw[tid] = 2.0 * wp.sqrt(s_wc * s_wc + s_ws * s_ws) / (float(nm) * 2.0 * 3.14159265358979 / (float(per) * dt))
    state[tid, 0] = X
    state[tid, 1] = Y
    state[tid, 2] = th
    state[tid, 3] = u
    state[tid, 4] = v
    state[tid, 5] = w
    state[tid, 6] = float(meas_start) * dt


