"""The swimmer step written part by part, as first derived (one 3x3 system assembled from every
part's inertia and fluid wrench each step, linearly implicit Euler). Kept (here, beside the tests) as the reference the
restructured kernel in swimmer.py is tested against (tests/test_swimmer_sim.py); not used in fits.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from wrenorm.kernels.swimmer.fluid import fluid_geometry_kernel, fluid_planar, geo9

wp.config.quiet = True


@wp.kernel
def swim_kernel_direct(offset: int, n_cond: int,
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


def run_direct(batch, coef: np.ndarray) -> np.ndarray:
    """Speeds (B, C) of this reference kernel for a SwimBatch's conditions (CPU, one launch)."""
    coef = np.atleast_2d(np.asarray(coef, np.float32))
    n = coef.shape[0] * batch.n_cond
    d = batch.device
    speed = wp.zeros(n, dtype=float, device=d)
    state = wp.zeros((n, 7), dtype=float, device=d)
    traj = wp.zeros((1, 1, 4), dtype=float, device=d)
    semi = np.asarray(batch.parts["semi"], np.float32)
    semi_w = wp.array(semi, dtype=wp.vec3, device=d)
    geo_all = wp.zeros(len(semi), dtype=geo9, device=d)
    wp.launch(fluid_geometry_kernel, dim=len(semi), inputs=[semi_w, geo_all], device=d)
    amass_all = wp.array(np.asarray(batch.parts["amass"], np.float32) * batch.rho, dtype=wp.vec3, device=d)
    inert = wp.array(np.asarray(batch.parts["inert"], np.float32), dtype=wp.vec2, device=d)
    part_table = wp.array(np.ascontiguousarray(batch.part_table, np.float32), dtype=float, device=d)
    wp.launch(swim_kernel_direct, dim=n, device=d, inputs=[
        0, batch.n_cond, wp.array(coef, dtype=float, device=d), part_table, semi_w, geo_all,
        amass_all, inert, batch.tab_off, batch.n_per, batch.dt, batch.n_warm, batch.n_meas,
        batch.max_warm, batch.settle_abs, batch.settle_rel, batch.ref_x, batch.rho, batch.mu, batch.virtual_mass,
        0, traj, speed, state])
    return speed.numpy().reshape(coef.shape[0], batch.n_cond).astype(np.float64)
