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

Drag is integrated linearly implicitly (the drag factors of each part enter the 3x3 matrix),
which keeps large coefficients stable at the default step.

Equations (head frame, origin at the front head marker, x towards the tail, so the fish swims
towards -x): unknowns (du/dt, dv/dt, dw/dt) of the head's frame velocity (u, v, w). Part e sits at
p_e with angle psi_e relative to the head (tabulated per condition, candidate-independent):
    a_e = (du, dv) + dw (-p_y, p_x) + k_e,   k_e = (-w v, w u) - w^2 p + 2 w (-pd_y, pd_x) + pdd
    sum_e M_e a_e = sum_e F_e,    sum_e [p_e x M_e a_e + J_e (dw + psidd_e)] = sum_e [p_e x F_e + tau_e]
with M_e = m_e I + R_e diag(m_A) R_e^T. Semi-implicit Euler (velocities first, then pose).

One thread simulates one (candidate, condition) pair over its whole run, state in registers, and
accumulates a least-squares line fit of the head position (the speed measurement) on the fly.
"""
from __future__ import annotations

import math
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


@wp.kernel
def swim_kernel(offset: int, n_cond: int,
                coef: wp.array2d(dtype=float),        # (B, 5)
                table: wp.array3d(dtype=float),       # (samples, parts, ROW)
                semi: wp.array(dtype=wp.vec3),        # (parts,) zero: no fluid
                geo: wp.array(dtype=geo9),            # (parts,) fluid_geometry(semi)
                amass: wp.array(dtype=wp.vec3),       # (parts,) rho * (m_A x, m_A y, I_A z)
                inert: wp.array(dtype=wp.vec2),       # (parts,) mass, yaw inertia about the part centre
                tab_off: wp.array(dtype=int), n_per: wp.array(dtype=int), dt_c: wp.array(dtype=float),
                n_warm: wp.array(dtype=int), n_meas: wp.array(dtype=int), max_warm: wp.array(dtype=int),
                settle_abs: float, settle_rel: float, ref_x: float, rho: float, mu: float, virtual_mass: int,
                rec_stride: int, traj: wp.array3d(dtype=float),   # (n, frames, 4): X, Y, theta, sample
                speed: wp.array(dtype=float), state: wp.array2d(dtype=float)):
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
    n_parts = semi.shape[0]
    vm = float(virtual_mass)

    X = float(0.0)
    Y = float(0.0)
    th = float(0.0)
    u = float(0.0)
    v = float(0.0)
    w = float(0.0)

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

    # start with zero linear and angular momentum (fluid's virtual momentum included): the head
    # moves so that the tail's prescribed velocity at t=0 does not launch the whole fish
    b00 = float(0.0)
    b01 = float(0.0)
    b02 = float(0.0)
    b11 = float(0.0)
    b12 = float(0.0)
    b22 = float(0.0)
    q0 = float(0.0)
    q1 = float(0.0)
    q2 = float(0.0)
    for e in range(n_parts):
        px = table[off, e, 0]
        py = table[off, e, 1]
        cp = table[off, e, 2]
        sp = table[off, e, 3]
        pdx = table[off, e, 4]
        pdy = table[off, e, 5]
        am = amass[e]
        mj = inert[e]
        m0 = am[0] * vm
        m1 = am[1] * vm
        j_e = mj[1] + am[2] * vm
        e00 = mj[0] + m0 * cp * cp + m1 * sp * sp
        e11 = mj[0] + m0 * sp * sp + m1 * cp * cp
        e01 = (m0 - m1) * cp * sp
        rx = -py
        ry = px
        mrx = e00 * rx + e01 * ry
        mry = e01 * rx + e11 * ry
        b00 += e00
        b01 += e01
        b11 += e11
        b02 += mrx
        b12 += mry
        b22 += rx * mrx + ry * mry + j_e
        gx = e00 * pdx + e01 * pdy
        gy = e01 * pdx + e11 * pdy
        q0 -= gx
        q1 -= gy
        q2 -= rx * gx + ry * gy + j_e * table[off, e, 6]
    d00 = b11 * b22 - b12 * b12
    d01 = b02 * b12 - b01 * b22
    d02 = b01 * b12 - b02 * b11
    d11 = b00 * b22 - b02 * b02
    d12 = b01 * b02 - b00 * b12
    d22 = b00 * b11 - b01 * b01
    det0 = b00 * d00 + b01 * d01 + b02 * d02
    u = (d00 * q0 + d01 * q1 + d02 * q2) / det0
    v = (d01 * q0 + d11 * q1 + d12 * q2) / det0
    w = (d02 * q0 + d12 * q1 + d22 * q2) / det0

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
        row = off + k
        ct = wp.cos(th)
        st = wp.sin(th)
        if meas_start >= 0:
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

        # 3x3 symmetric system A [du, dv, dw] = r
        a00 = float(0.0)
        a01 = float(0.0)
        a02 = float(0.0)
        a11 = float(0.0)
        a12 = float(0.0)
        a22 = float(0.0)
        r0 = float(0.0)
        r1 = float(0.0)
        r2 = float(0.0)
        for e in range(n_parts):
            px = table[row, e, 0]
            py = table[row, e, 1]
            cp = table[row, e, 2]
            sp = table[row, e, 3]
            pdx = table[row, e, 4]
            pdy = table[row, e, 5]
            psid = table[row, e, 6]
            pddx = table[row, e, 7]
            pddy = table[row, e, 8]
            psidd = table[row, e, 9]
            ax = semi[e]
            am = amass[e]
            mj = inert[e]
            m0 = am[0] * vm
            m1 = am[1] * vm
            j_e = mj[1] + am[2] * vm

            vx = u - w * py + pdx
            vy = v + w * px + pdy
            we = w + psid
            fx = float(0.0)
            fy = float(0.0)
            tz = float(0.0)
            dlin = float(0.0)
            dang = float(0.0)
            if ax[0] > 0.0:
                la = cp * vx + sp * vy
                lb = -sp * vx + cp * vy
                fl = fluid_planar(la, lb, we, geo[e], cb, cs, ca, ck, cm, rho, mu, am[0], am[1])
                # the velocity part of -m_A (dv/dt)_body: + m_A (w x v)
                lfx = fl[0] - m0 * we * lb
                lfy = fl[1] + m1 * we * la
                fx = cp * lfx - sp * lfy
                fy = sp * lfx + cp * lfy
                tz = fl[2]
                dlin = fl[3]
                dang = fl[4]
            # effective translational mass of the part in the head frame
            mm = mj[0]
            e00 = mm + m0 * cp * cp + m1 * sp * sp
            e11 = mm + m0 * sp * sp + m1 * cp * cp
            e01 = (m0 - m1) * cp * sp
            kx = -w * v - w * w * px - 2.0 * w * pdy + pddx
            ky = w * u - w * w * py + 2.0 * w * pdx + pddy
            mkx = e00 * kx + e01 * ky
            mky = e01 * kx + e11 * ky
            rx = -py
            ry = px
            mrx = e00 * rx + e01 * ry
            mry = e01 * rx + e11 * ry
            a00 += e00
            a01 += e01
            a11 += e11
            a02 += mrx
            a12 += mry
            a22 += rx * mrx + ry * mry + j_e
            # linearly implicit drag: (A + dt C) dV = dt F(V), C from v_e = V + w r_e + pd_e
            a00 += dt * dlin
            a11 += dt * dlin
            a02 += dt * dlin * rx
            a12 += dt * dlin * ry
            a22 += dt * (dlin * (rx * rx + ry * ry) + dang)
            r0 += fx - mkx
            r1 += fy - mky
            r2 += px * fy - py * fx + tz - (rx * mkx + ry * mky) - j_e * psidd

        # Cramer on the symmetric 3x3
        c00 = a11 * a22 - a12 * a12
        c01 = a02 * a12 - a01 * a22
        c02 = a01 * a12 - a02 * a11
        det = a00 * c00 + a01 * c01 + a02 * c02
        c11 = a00 * a22 - a02 * a02
        c12 = a01 * a02 - a00 * a12
        c22 = a00 * a11 - a01 * a01
        du = (c00 * r0 + c01 * r1 + c02 * r2) / det
        dv = (c01 * r0 + c11 * r1 + c12 * r2) / det
        dw = (c02 * r0 + c12 * r1 + c22 * r2) / det

        u += dt * du
        v += dt * dv
        w += dt * dw
        X += dt * (ct * u - st * v)
        Y += dt * (st * u + ct * v)
        th += dt * w
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


class SwimBatch:
    """Device-resident inputs for one set of conditions; `run(coef)` -> speeds (B, C)."""

    def __init__(self, table: np.ndarray, tab_off, n_per, dt, n_warm, n_meas, parts: dict,
                 ref_x: float, rho: float = 1000.0, mu: float = 0.0013, virtual_mass: bool = True,
                 max_warm=None, settle_abs: float = 2e-4, settle_rel: float = 2e-3, device: str = "cpu"):
        self.device = device
        self.n_cond = len(n_per)
        self.ref_x, self.rho, self.mu, self.virtual_mass = float(ref_x), float(rho), float(mu), int(bool(virtual_mass))
        d = device
        self.table = wp.array(np.ascontiguousarray(table, np.float32), dtype=float, device=d)
        self.semi = wp.array(np.asarray(parts["semi"], np.float32), dtype=wp.vec3, device=d)
        self.geo = wp.zeros(len(parts["semi"]), dtype=geo9, device=d)
        wp.launch(fluid_geometry_kernel, dim=len(parts["semi"]), inputs=[self.semi, self.geo], device=d)
        self.amass = wp.array(np.asarray(parts["amass"], np.float32) * rho, dtype=wp.vec3, device=d)
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
        state = wp.zeros((n, 7), dtype=float, device=d)
        traj = wp.zeros((n if rec_stride > 0 else 1, max(rec_frames, 1), 4), dtype=float, device=d)

        def launch(offset, count):
            wp.launch(swim_kernel, dim=count, device=d, inputs=[
                offset, self.n_cond, coef_wp, self.table, self.semi, self.geo, self.amass, self.inert,
                self.tab_off, self.n_per, self.dt, self.n_warm, self.n_meas, self.max_warm,
                self.settle_abs, self.settle_rel, self.ref_x, self.rho, self.mu, self.virtual_mass, int(rec_stride), traj, speed, state])

        launch_sliced(launch, n, d)
        shape = (coef.shape[0], self.n_cond)
        out = speed.numpy().reshape(shape).astype(np.float64)
        self.last_state = state.numpy().reshape(shape + (7,))
        if rec_stride > 0:
            return out, traj.numpy().reshape(shape + traj.shape[1:]), self.last_state
        return out


def benchmark(batch: int = 2048, seconds: float = 2.0, device: str = "cpu") -> dict:
    """Fish-seconds simulated per wall second for the robot fish at label 1.00 (built-in data)."""
    from wrenorm.tasks import swimmer_body, swimmer_data

    rates = swimmer_data.load_builtin()
    rate = min(rates, key=lambda r: abs(r.label - 1.0))
    sim = swimmer_body.build_batch([rate], device=device, warm_seconds=0.0, meas_seconds=seconds,
                                   max_warm_seconds=None)
    coef = np.tile(np.array([0.4, 7.79, 2.81, 3.84, 0.27]), (batch, 1))
    sim.run(coef[:2])  # compile and warm caches outside the timing
    if not str(device).startswith("cpu"):
        wp.synchronize_device(device)
    t0 = time.perf_counter()
    sim.run(coef)
    wall = time.perf_counter() - t0
    steps = int(sim.steps[0])
    fish_seconds = batch * float(sim.sim_seconds[0])
    return {"batch": batch, "sim_seconds": float(sim.sim_seconds[0]), "steps": steps, "wall_s": wall,
            "fish_seconds_per_s": fish_seconds / wall, "fish_steps_per_s": batch * steps / wall,
            "device": str(device)}
