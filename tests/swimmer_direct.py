"""The swimmer step written part by part, as first derived (one 3x3 system assembled from every
part's inertia and fluid wrench each step, linearly implicit Euler). Kept (here, beside the tests) as the reference the
restructured kernel in swimmer.py is tested against (tests/test_swimmer_sim.py); not used in fits.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from wrenorm.kernels.swimmer.fluid import fluid_geometry_kernel, fluid_planar, geo9
from wrenorm.kernels.swimmer.kernel import (
    Schedule,
    Water,
    beat_advance,
    line_speed,
    line_sums_add,
    record_pose,
    slot_coefficients,
    solve_sym3,
    vec12d,
)

sym6 = wp.types.vector(length=6, dtype=float)  # a symmetric 3x3: a00, a01, a11, a02, a12, a22


@wp.func
def inertia_rows(e00: float, e01: float, e11: float, j_e: float, px: float, py: float):
    """A part's share of the head's 3x3 mass matrix (translation and yaw about the head origin)."""
    rx = -py
    ry = px
    mrx = e00 * rx + e01 * ry
    mry = e01 * rx + e11 * ry
    return sym6(e00, e01, e11, mrx, mry, rx * mrx + ry * mry + j_e)


@wp.func
def part_pose(table: wp.array3d(dtype=float), row: int, e: int):
    """Part e's position, orientation (cos, sin) and velocity in the head frame at table row `row`."""
    return table[row, e, 0], table[row, e, 1], table[row, e, 2], table[row, e, 3], table[row, e, 4], table[row, e, 5]


@wp.func
def part_mass(am: wp.vec3, mj: wp.vec2, vm: float, cp: float, sp: float):
    """A part's effective translational mass in the head frame (its mass plus the rotated added mass), its
    yaw inertia with added inertia, and the added masses along its axes."""
    m0 = am[0] * vm
    m1 = am[1] * vm
    e00 = mj[0] + m0 * cp * cp + m1 * sp * sp
    e11 = mj[0] + m0 * sp * sp + m1 * cp * cp
    e01 = (m0 - m1) * cp * sp
    return e00, e01, e11, mj[1] + am[2] * vm, m0, m1


@wp.kernel
def swim_kernel_direct(offset: int, n_cond: int,
                coef: wp.array2d(dtype=float),        # (B, 5) or (B, 6): + viscosity [Pa s]
                table: wp.array3d(dtype=float),       # (samples, parts, ROW)
                semi: wp.array(dtype=wp.vec3),        # (parts,) zero: no fluid
                geo: wp.array(dtype=geo9),            # (parts,) fluid_geometry(semi)
                amass: wp.array(dtype=wp.vec3),       # (parts,) rho * (m_A x, m_A y, I_A z)
                inert: wp.array(dtype=wp.vec2),       # (parts,) mass, yaw inertia about the part centre
                sched: Schedule, water: Water,
                rec_stride: int, traj: wp.array3d(dtype=float),   # (n, frames, 4): X, Y, theta, sample
                speed: wp.array(dtype=float), state: wp.array2d(dtype=float)):
    tid = wp.tid() + offset
    c, cb, cs, ca, ck, cm, mu = slot_coefficients(coef, tid, n_cond, water.mu)
    n_parts = semi.shape[0]
    vm = float(water.virtual_mass)
    rho, ref_x = water.rho, water.ref_x
    off, per, dt = sched.tab_off[c], sched.n_per[c], sched.dt[c]
    nw, nm = sched.n_warm[c], sched.n_meas[c]

    X = float(0.0)
    Y = float(0.0)
    th = float(0.0)
    u = float(0.0)
    v = float(0.0)
    w = float(0.0)

    acc = vec12d()  # running sums of the straight-line speed fit

    # start with zero linear and angular momentum (fluid's virtual momentum included): the head
    # moves so that the tail's prescribed velocity at t=0 does not launch the whole fish
    B = sym6()
    q = wp.vec3(0.0)
    for e in range(n_parts):
        px, py, cp, sp, pdx, pdy = part_pose(table, off, e)
        e00, e01, e11, j_e, m0, m1 = part_mass(amass[e], inert[e], vm, cp, sp)
        B = B + inertia_rows(e00, e01, e11, j_e, px, py)
        gx = e00 * pdx + e01 * pdy
        gy = e01 * pdx + e11 * pdy
        q = q - wp.vec3(gx, gy, -py * gx + px * gy + j_e * table[off, e, 6])
    v_start = solve_sym3(B[0], B[1], B[2], B[3], B[4], B[5], q[0], q[1], q[2])
    u = v_start[0]
    v = v_start[1]
    w = v_start[2]

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
        row = off + k
        ct = wp.cos(th)
        st = wp.sin(th)
        if meas_start >= 0:
            acc = line_sums_add(acc, wp.float64(float(step - meas_start) * dt), wp.float64(X + ct * ref_x),
                                wp.float64(Y + st * ref_x), ct, st)
        rec_i = record_pose(traj, tid, rec_i, step, rec_stride, 0, meas_start, X, Y, th, k)

        # 3x3 symmetric system A [du, dv, dw] = r
        A = sym6()
        r = wp.vec3(0.0)
        for e in range(n_parts):
            px, py, cp, sp, pdx, pdy = part_pose(table, row, e)
            psid = table[row, e, 6]
            pddx = table[row, e, 7]
            pddy = table[row, e, 8]
            psidd = table[row, e, 9]
            ax = semi[e]
            am = amass[e]
            e00, e01, e11, j_e, m0, m1 = part_mass(am, inert[e], vm, cp, sp)

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
            kx = -w * v - w * w * px - 2.0 * w * pdy + pddx
            ky = w * u - w * w * py + 2.0 * w * pdx + pddy
            mkx = e00 * kx + e01 * ky
            mky = e01 * kx + e11 * ky
            rx = -py
            ry = px
            A = A + inertia_rows(e00, e01, e11, j_e, px, py)
            # linearly implicit drag: (A + dt C) dV = dt F(V), C from v_e = V + w r_e + pd_e
            A = A + sym6(dt * dlin, 0.0, dt * dlin, dt * dlin * rx, dt * dlin * ry,
                         dt * (dlin * (rx * rx + ry * ry) + dang))
            r = r + wp.vec3(fx - mkx, fy - mky, px * fy - py * fx + tz - (rx * mkx + ry * mky) - j_e * psidd)

        dV = solve_sym3(A[0], A[1], A[2], A[3], A[4], A[5], r[0], r[1], r[2])
        u += dt * dV[0]
        v += dt * dV[1]
        w += dt * dV[2]
        X += dt * (ct * u - st * v)
        Y += dt * (st * u + ct * v)
        th += dt * w
        k, step, meas_start, beat_u, prev_u, calm = beat_advance(k, step, per, meas_start, beat_u, prev_u, calm, u,
                                                                 nw, mw, sched.settle_abs, sched.settle_rel)

    speed[tid] = line_speed(acc)
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
        amass_all, inert, batch.schedule, batch.water,
        0, traj, speed, state])
    return speed.numpy().reshape(coef.shape[0], batch.n_cond).astype(np.float64)
