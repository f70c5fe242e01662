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

import math
import os
import time

import numpy as np
import warp as wp

from wrenorm.parallel import launch_sliced

wp.config.quiet = True

ROW = 10  # per part per sample: px, py, cos psi, sin psi, pdx, pdy, psid, pddx, pddy, psidd
MINVAL = 1e-15  # mjMINVAL


geo9 = wp.types.vector(length=9, dtype=wp.float32)
wrench5 = wp.types.vector(length=5, dtype=wp.float32)


@wp.func
def fluid_geometry(r0: float, r1: float, r2: float):
    """Shape constants of an ellipsoid for fluid_planar: volume, A_max, I_max, I_D along z,
    Stokes force and torque factors, (r1 r2)^2 and (r2 r0)^2 divided by the larger of the two,
    and the square root of that larger one. The normalisation keeps the projection terms of
    small parts far from float32 underflow and from the MINVAL guards (MuJoCo 4 evaluates the
    Kutta term at these scales without clamping)."""
    pi = 3.14159265358979
    vol = 4.0 / 3.0 * pi * r0 * r1 * r2
    d_max = wp.max(wp.max(r0, r1), r2)
    d_min = wp.min(wp.min(r0, r1), r2)
    d_mid = r0 + r1 + r2 - d_max - d_min
    a_max = pi * d_max * d_mid
    i_max = 8.0 / 15.0 * pi * d_mid * d_max * d_max * d_max * d_max
    rr = wp.max(r0, r1)
    i_z = 8.0 / 15.0 * pi * r2 * rr * rr * rr * rr
    eq_d = 2.0 / 3.0 * (r0 + r1 + r2)
    q12 = (r1 * r2) * (r1 * r2)
    q20 = (r2 * r0) * (r2 * r0)
    qm = wp.max(q12, q20)
    return geo9(vol, a_max, i_max, i_z, 3.0 * pi * eq_d, pi * eq_d * eq_d * eq_d,
                q12 / qm, q20 / qm, wp.sqrt(qm))


@wp.func
def fluid_planar(a: float, b: float, w: float, g: geo9,
                 c_blunt: float, c_slender: float, c_ang: float, c_kutta: float, c_magnus: float,
                 rho: float, mu: float, ma0: float, ma1: float):
    """MuJoCo ellipsoid fluid force (fx, fy) and torque tz in the part frame, planar motion,
    plus the linear and angular drag factors (force = -drag_lin v - ..., torque = -drag_ang w + ...)
    that the integrator treats implicitly.

    (a, b): linear velocity of the ellipsoid centre, w: angular velocity about z, all local;
    g = fluid_geometry(semi-axes); ma0, ma1: virtual masses along local x, y times the density.
    """
    pi = 3.14159265358979
    speed = wp.sqrt(a * a + b * b)

    # Magnus: C_M rho V (w x v)
    mag = c_magnus * rho * g[0] * w
    q12 = g[6]
    q20 = g[7]
    n0 = q12 * a  # non-unit normal of the cross-section generating the projection (scaled)
    n1 = q20 * b
    proj_num = q12 * a * a + q20 * b * b
    proj_denom = q12 * q12 * a * a + q20 * q20 * b * b
    a_proj = pi * g[8] * wp.sqrt(proj_denom / wp.max(MINVAL, proj_num))
    cos_alpha = proj_num / wp.max(MINVAL, speed * proj_denom)
    # Kutta: circulation (n x v) along z, force = circ x v
    circ = (n0 * b - n1 * a) * c_kutta * rho * cos_alpha * a_proj

    mom_z = w * (c_ang * g[3] + c_slender * (g[2] - g[3]))
    drag_lin = mu * g[4] + rho * speed * (a_proj * c_blunt + c_slender * (g[1] - a_proj))
    drag_ang = mu * g[5] + rho * wp.abs(mom_z)

    # velocity-dependent added-mass terms: (m_A v) x w and (m_A v) x v
    fx = -(mag + circ) * b - drag_lin * a + ma1 * b * w
    fy = (mag + circ) * a - drag_lin * b - ma0 * a * w
    tz = -drag_ang * w + (ma0 - ma1) * a * b
    return wrench5(fx, fy, tz, drag_lin, drag_ang)


@wp.kernel
def fluid_planar_kernel(vel: wp.array(dtype=wp.vec3), semi: wp.array(dtype=wp.vec3),
                        coef: wp.array2d(dtype=float), amass: wp.array(dtype=wp.vec3),
                        rho: float, mu: float, out: wp.array(dtype=wp.vec3)):
    """Local fluid wrench for single ellipsoids (the MuJoCo peer test drives this)."""
    i = wp.tid()
    v = vel[i]
    r = semi[i]
    m = amass[i]
    g = fluid_geometry(r[0], r[1], r[2])
    f = fluid_planar(v[0], v[1], v[2], g, coef[i, 0], coef[i, 1], coef[i, 2],
                          coef[i, 3], coef[i, 4], rho, mu, m[0], m[1])
    out[i] = wp.vec3(f[0], f[1], f[2])


@wp.kernel
def fluid_geometry_kernel(semi: wp.array(dtype=wp.vec3), out: wp.array(dtype=geo9)):
    i = wp.tid()
    r = semi[i]
    if r[0] > 0.0:
        out[i] = fluid_geometry(r[0], r[1], r[2])


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


# --- host side ---------------------------------------------------------------------------------

def ellipsoid_kappa(semi) -> np.ndarray:
    """kappa_i = int_0^inf r_x r_y r_z / sqrt((r_i^2+l)^3 (r_j^2+l)(r_k^2+l)) dl (Tuckerman)."""
    from scipy.integrate import quad

    r = np.asarray(semi, dtype=np.float64)
    out = np.zeros(3)
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3

        # substitute l = s^2 r_max^2 / (1 - s)^2 ... keep it simple: integrate in log space
        def f(t, i=i, j=j, k=k):
            lam = math.exp(t)
            return lam * r.prod() / math.sqrt((r[i] ** 2 + lam) ** 3 * (r[j] ** 2 + lam) * (r[k] ** 2 + lam))

        lo, hi = math.log(r.min() ** 2) - 40.0, math.log(r.max() ** 2) + 40.0
        val, _ = quad(f, lo, hi, limit=400, epsabs=1e-13, epsrel=1e-11)
        out[i] = val
    return out


def virtual_mass_inertia(semi) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo's virtual masses and moments of inertia of an ellipsoid, per unit fluid density."""
    r = np.asarray(semi, dtype=np.float64)
    kap = ellipsoid_kappa(r)
    vol = 4.0 / 3.0 * math.pi * r.prod()
    mass = vol * kap / (2.0 - kap)
    inertia = np.zeros(3)
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        dj, dk = r[j] ** 2, r[k] ** 2
        num = (dj - dk) ** 2 * (kap[k] - kap[j])
        den = 2.0 * (dj - dk) + (dj + dk) * (kap[j] - kap[k])
        inertia[i] = vol / 5.0 * num / den if abs(den) > 1e-300 else 0.0
    return mass, inertia


def fluid_wrench_local(vel, semi, coef, amass, rho: float, mu: float, device: str = "cpu") -> np.ndarray:
    """Evaluate fluid_planar for N ellipsoids: vel (N,3)=(vx, vy, wz) local -> (N,3) (fx, fy, tz)."""
    n = len(vel)
    out = wp.zeros(n, dtype=wp.vec3, device=device)
    wp.launch(fluid_planar_kernel, dim=n, device=device, inputs=[
        wp.array(np.asarray(vel, np.float32), dtype=wp.vec3, device=device),
        wp.array(np.asarray(semi, np.float32), dtype=wp.vec3, device=device),
        wp.array(np.asarray(coef, np.float32), dtype=float, device=device),
        wp.array(np.asarray(amass, np.float32), dtype=wp.vec3, device=device),
        float(rho), float(mu), out])
    return out.numpy()


def reduce_table(table: np.ndarray, tab_off, n_per, parts: dict, rho: float, virtual_mass: bool):
    """Per-part kinematics (samples, parts, ROW) -> the kernel's table (samples, INERTIAL +
    FLUID_ROW * fluid parts), plus the zero-momentum start velocity of each condition.

    Everything that does not depend on a candidate's coefficients or the head's velocity is summed
    here once, in float64: with M_e = m_e I + R_e diag(m_A) R_e^T and r_e = (-p_y, p_x),
      M = [sum M_e, sum M_e r_e; ., sum r_e.M_e r_e + J_e]      (entries 0-5)
      P = sum [M_e p_e; r_e.M_e p_e]                            (6-8, times -w^2)
      Q = sum [M_e (-pd_y, pd_x); r_e.M_e (-pd_y, pd_x)]        (9-11, times 2 w)
      S = sum [M_e pdd_e; r_e.M_e pdd_e + J_e psidd_e]          (12-14)
    """
    t = np.asarray(table, np.float64)
    semi = np.asarray(parts["semi"], np.float64)
    am = np.asarray(parts["amass"], np.float64) * rho
    inert = np.asarray(parts["inert"], np.float64)
    vm = 1.0 if virtual_mass else 0.0
    px, py, cp, sp, pdx, pdy, psid, pddx, pddy, psidd = (t[..., i] for i in range(ROW))
    m, m0, m1 = inert[:, 0], am[:, 0] * vm, am[:, 1] * vm
    je = inert[:, 1] + am[:, 2] * vm
    e00 = m + m0 * cp * cp + m1 * sp * sp
    e11 = m + m0 * sp * sp + m1 * cp * cp
    e01 = (m0 - m1) * cp * sp
    rx, ry = -py, px

    def apply(x, y):
        mx, my = e00 * x + e01 * y, e01 * x + e11 * y
        return mx.sum(1), my.sum(1), (rx * mx + ry * my).sum(1)

    b0, b1, b2 = apply(rx, ry)
    cols = [e00.sum(1), e01.sum(1), e11.sum(1), b0, b1, b2 + je.sum()]
    cols += list(apply(px, py)) + list(apply(-pdy, pdx))
    s0, s1, s2 = apply(pddx, pddy)
    cols += [s0, s1, s2 + (je * psidd).sum(1)]
    phase = np.concatenate([2.0 * np.pi * np.arange(n) / n for n in n_per])
    cols += [np.cos(phase), np.sin(phase)]
    fluid = semi[:, 0] > 0
    kin = np.stack([px, py, cp, sp, pdx, pdy, psid], axis=-1)[:, fluid]      # (samples, fluid, 7)
    out = np.concatenate([np.stack(cols, axis=1), kin.reshape(len(t), -1)], axis=1)
    # start with zero linear and angular momentum (fluid's virtual momentum included): the head
    # moves so that the tail's prescribed velocity at t=0 does not launch the whole fish
    v0 = []
    for o in tab_off:
        g0, g1, g2 = (x[o] for x in apply(pdx, pdy))
        g2 = g2 + (je * psid[o]).sum()
        M = np.array([[out[o, 0], out[o, 1], out[o, 3]], [out[o, 1], out[o, 2], out[o, 4]],
                      [out[o, 3], out[o, 4], out[o, 5]]])
        v0.append(np.linalg.solve(M, -np.array([g0, g1, g2])))
    return out, np.array(v0), fluid


class SwimBatch:
    """Device-resident inputs for one set of conditions; `run(coef)` -> speeds (B, C).

    scheme 2 (default): ROS2, second order; scheme 1: linearly implicit Euler, first order."""

    def __init__(self, table: np.ndarray, tab_off, n_per, dt, n_warm, n_meas, parts: dict,
                 ref_x: float, rho: float = 1000.0, mu: float = 0.0013, virtual_mass: bool = True,
                 max_warm=None, settle_abs: float = 2e-4, settle_rel: float = 2e-3, device: str = "cpu",
                 scheme: int = 2):
        if scheme not in (1, 2):
            raise ValueError(f"scheme must be 1 or 2, got {scheme}")
        self.device = device
        self.scheme = int(scheme)
        self.n_cond = len(n_per)
        self.ref_x, self.rho, self.mu, self.virtual_mass = float(ref_x), float(rho), float(mu), int(bool(virtual_mass))
        d = device
        reduced, v0, fluid = reduce_table(table, tab_off, n_per, parts, self.rho, bool(virtual_mass))
        self.n_fluid = int(fluid.sum())
        self.tab = wp.array(np.ascontiguousarray(reduced, np.float32), dtype=float, device=d)
        self.v0 = wp.array(np.asarray(v0, np.float32), dtype=wp.vec3, device=d)
        semi = np.asarray(parts["semi"], np.float32)
        amass = np.asarray(parts["amass"], np.float32) * rho
        self.geo = wp.zeros(self.n_fluid, dtype=geo9, device=d)
        wp.launch(fluid_geometry_kernel, dim=self.n_fluid, device=d,
                  inputs=[wp.array(semi[fluid], dtype=wp.vec3, device=d), self.geo])
        self.amass = wp.array(amass[fluid], dtype=wp.vec3, device=d)
        # per-part inputs of the direct reference kernel (kernels/swimmer_direct.py)
        self.part_table = wp.array(np.ascontiguousarray(table, np.float32), dtype=float, device=d)
        self.semi = wp.array(semi, dtype=wp.vec3, device=d)
        self.geo_all = wp.zeros(len(semi), dtype=geo9, device=d)
        wp.launch(fluid_geometry_kernel, dim=len(semi), inputs=[self.semi, self.geo_all], device=d)
        self.amass_all = wp.array(amass, dtype=wp.vec3, device=d)
        self.inert = wp.array(np.asarray(parts["inert"], np.float32), dtype=wp.vec2, device=d)
        self.tab_off = wp.array(np.asarray(tab_off, np.int32), dtype=int, device=d)
        self.n_per = wp.array(np.asarray(n_per, np.int32), dtype=int, device=d)
        self.dt = wp.array(np.asarray(dt, np.float32), dtype=float, device=d)
        self.n_warm = wp.array(np.asarray(n_warm, np.int32), dtype=int, device=d)
        self.n_meas = wp.array(np.asarray(n_meas, np.int32), dtype=int, device=d)
        max_warm = np.asarray(n_warm if max_warm is None else max_warm, np.int32)
        self.max_warm = wp.array(max_warm, dtype=int, device=d)
        self.settle_abs, self.settle_rel = float(settle_abs), float(settle_rel)
        self.steps = np.asarray(n_warm) + np.asarray(n_meas)  # at least; warm-up may run longer
        self.sim_seconds = self.steps * np.asarray(dt, np.float64)

    def run(self, coef: np.ndarray, rec_stride: int = 0, rec_frames: int = 0):
        coef = np.atleast_2d(np.asarray(coef, np.float32))
        n = coef.shape[0] * self.n_cond
        d = self.device
        coef_wp = wp.array(coef, dtype=float, device=d)
        speed = wp.zeros(n, dtype=float, device=d)
        yaw = wp.zeros(n, dtype=float, device=d)
        state = wp.zeros((n, 7), dtype=float, device=d)
        traj = wp.zeros((n if rec_stride > 0 else 1, max(rec_frames, 1), 4), dtype=float, device=d)

        def launch(offset, count):
            wp.launch(swim_kernel, dim=count, device=d, inputs=[
                offset, self.n_cond, coef_wp, self.tab, self.n_fluid, self.geo, self.amass, self.v0,
                self.tab_off, self.n_per, self.dt, self.n_warm, self.n_meas, self.max_warm,
                self.settle_abs, self.settle_rel, self.ref_x, self.rho, self.mu, self.virtual_mass, self.scheme,
                int(rec_stride), traj, speed, yaw, state])

        launch_sliced(launch, n, d)
        shape = (coef.shape[0], self.n_cond)
        out = speed.numpy().reshape(shape).astype(np.float64)
        # amplitude [rad] of the head's yaw oscillation at the beat frequency, per run
        self.last_yaw = yaw.numpy().reshape(shape).astype(np.float64)
        self.last_state = state.numpy().reshape(shape + (7,))
        if rec_stride > 0:
            return out, traj.numpy().reshape(shape + traj.shape[1:]), self.last_state
        return out


def benchmark(batch: int = 2048, seconds: float = 2.0, device: str = "cpu", dt: float | None = None,
              scheme: int = 2) -> dict:
    """Fish-seconds simulated per wall second for the robot fish at label 1.00 (built-in data), at
    the task's default step unless `dt` is given. Also per CPU second of this process (the
    machine may be shared: wall time then undercounts what the kernel can do)."""
    import resource

    from wrenorm.tasks import swimmer_body, swimmer_data

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
    return {"batch": batch, "sim_seconds": float(sim.sim_seconds[0]), "steps": steps, "dt": float(sim.sim_seconds[0] / steps),
            "scheme": "ros2" if scheme == 2 else "implicit-euler", "wall_s": wall, "cpu_s": cpu,
            "fish_seconds_per_s": fish_seconds / wall, "fish_steps_per_s": batch * steps / wall,
            "fish_seconds_per_cpu_s": fish_seconds / cpu if cpu > 0 else None,
            "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None, "device": str(device)}
