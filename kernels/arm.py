"""A two-link planar arm (horizontal plane) under joint-space PD control at a finite frequency.

Slot s simulates parameters params[s] = (A11, A12, A22, KD11, KD12, KD21, KD22, KP11, KP12,
KP21, KP22): a symmetric joint-space inertia correction A (armature-like) added to the
configuration-dependent M(q), and full gain matrices. Semi-implicit Euler, controller sampled
and held for one step:
    v += dt (M(q) + A)^-1 [K_P (q_d - q) + K_D (qd_d - v) - c(q, v)];  q += dt v
"""
from __future__ import annotations

import numpy as np
import warp as wp

N_PARAMS = 11


@wp.struct
class ArmGeometry:
    m1: wp.float64
    m2: wp.float64
    l1: wp.float64
    lc1: wp.float64
    lc2: wp.float64
    i1: wp.float64
    i2: wp.float64


def geometry(m1=1.0, m2=0.8, l1=0.3, l2=0.25) -> ArmGeometry:
    g = ArmGeometry()
    g.m1, g.m2, g.l1 = wp.float64(m1), wp.float64(m2), wp.float64(l1)
    g.lc1, g.lc2 = wp.float64(l1 / 2), wp.float64(l2 / 2)
    g.i1, g.i2 = wp.float64(m1 * l1 * l1 / 12), wp.float64(m2 * l2 * l2 / 12)
    return g


def mass_matrix(g: ArmGeometry, q2: np.ndarray) -> np.ndarray:
    """M(q) (..., 2, 2) in numpy, for the reference and the analytic predictions."""
    m1, m2, l1, lc1, lc2, i1, i2 = (float(x) for x in (g.m1, g.m2, g.l1, g.lc1, g.lc2, g.i1, g.i2))
    c = np.cos(q2)
    m11 = i1 + i2 + m1 * lc1**2 + m2 * (l1**2 + lc2**2 + 2 * l1 * lc2 * c)
    m12 = i2 + m2 * (lc2**2 + l1 * lc2 * c)
    m22 = np.full_like(c, i2 + m2 * lc2**2)
    return np.stack([np.stack([m11, m12], -1), np.stack([m12, m22], -1)], -2)


def bias_force(g: ArmGeometry, q2, v1, v2):
    """Coriolis and centrifugal terms c(q, v)."""
    h = float(g.m2) * float(g.l1) * float(g.lc2) * np.sin(q2)
    return np.stack([-h * (2 * v1 * v2 + v2 * v2), h * v1 * v1], -1)


@wp.kernel
def rollout(
    params: wp.array2d(dtype=wp.float64),
    cond: wp.array(dtype=int),
    q_des: wp.array3d(dtype=wp.float64),  # (C, T, 2)
    qd_des: wp.array3d(dtype=wp.float64),
    q_ref: wp.array3d(dtype=wp.float64),  # (C, T + 1, 2)
    ref_scale: wp.array2d(dtype=wp.float64),  # (C, 2)
    geo: ArmGeometry,
    dt: wp.float64,
    n_steps: int,
    record: int,
    offset: int,
    err: wp.array(dtype=wp.float64),
    traj: wp.array3d(dtype=wp.float64),
):
    s = wp.tid() + offset
    c = cond[s]
    a11 = params[s, 0]
    a12 = params[s, 1]
    a22 = params[s, 2]
    q1 = q_ref[c, 0, 0]
    q2 = q_ref[c, 0, 1]
    v1 = wp.float64(0.0)
    v2 = wp.float64(0.0)
    e1 = wp.float64(0.0)
    e2 = wp.float64(0.0)
    for k in range(n_steps):
        u1 = q_des[c, k, 0] - q1
        u2 = q_des[c, k, 1] - q2
        w1 = qd_des[c, k, 0] - v1
        w2 = qd_des[c, k, 1] - v2
        t1 = params[s, 7] * u1 + params[s, 8] * u2 + params[s, 3] * w1 + params[s, 4] * w2
        t2 = params[s, 9] * u1 + params[s, 10] * u2 + params[s, 5] * w1 + params[s, 6] * w2
        cq = wp.cos(q2)
        h = geo.m2 * geo.l1 * geo.lc2 * wp.sin(q2)
        t1 = t1 + h * (wp.float64(2.0) * v1 * v2 + v2 * v2)
        t2 = t2 - h * v1 * v1
        m11 = (geo.i1 + geo.i2 + geo.m1 * geo.lc1 * geo.lc1
               + geo.m2 * (geo.l1 * geo.l1 + geo.lc2 * geo.lc2 + wp.float64(2.0) * geo.l1 * geo.lc2 * cq) + a11)
        m12 = geo.i2 + geo.m2 * (geo.lc2 * geo.lc2 + geo.l1 * geo.lc2 * cq) + a12
        m22 = geo.i2 + geo.m2 * geo.lc2 * geo.lc2 + a22
        det = m11 * m22 - m12 * m12
        acc1 = (m22 * t1 - m12 * t2) / det
        acc2 = (m11 * t2 - m12 * t1) / det
        v1 = v1 + dt * acc1
        v2 = v2 + dt * acc2
        q1 = q1 + dt * v1
        q2 = q2 + dt * v2
        d1 = q1 - q_ref[c, k + 1, 0]
        d2 = q2 - q_ref[c, k + 1, 1]
        e1 += d1 * d1
        e2 += d2 * d2
        if record != 0:
            traj[s, k + 1, 0] = q1
            traj[s, k + 1, 1] = q2
    n = wp.float64(n_steps)
    err[s] = wp.float64(0.5) * (wp.sqrt(e1 / n) / ref_scale[c, 0] + wp.sqrt(e2 / n) / ref_scale[c, 1])


def simulate(values, q_des, qd_des, q_ref, geo, dt, device="cpu", record=False):
    """values (B, 11); q_des, qd_des (C, T, 2); q_ref (C, T+1, 2) -> errors (B, C)[, traj (B, C, T+1, 2)]."""
    from wrenorm.kernels.launch import launch_sliced

    B, (C, T, _) = len(values), q_des.shape
    slot = np.repeat(np.asarray(values, np.float64), C, axis=0)
    cond = np.tile(np.arange(C, dtype=np.int32), B)
    S = B * C
    scale = np.maximum(np.sqrt(np.mean(q_ref[:, 1:] ** 2, axis=1)), 1e-12)
    arrs = [wp.array(x, dtype=wp.float64, device=device) for x in (slot,)]
    params = arrs[0]
    cond_w = wp.array(cond, dtype=int, device=device)
    qd_w, qdd_w, ref_w = (wp.array(x, dtype=wp.float64, device=device) for x in (q_des, qd_des, q_ref))
    scale_w = wp.array(scale, dtype=wp.float64, device=device)
    err = wp.zeros(S, dtype=wp.float64, device=device)
    traj = wp.zeros((S, T + 1, 2) if record else (1, 1, 2), dtype=wp.float64, device=device)

    def launch(offset, count):
        wp.launch(rollout, dim=count, device=device, inputs=[params, cond_w, qd_w, qdd_w, ref_w, scale_w, geo,
                                                             wp.float64(dt), T, int(record), offset, err, traj])

    launch_sliced(launch, S, device)
    errors = err.numpy().reshape(B, C)
    if not record:
        return errors
    tr = traj.numpy().reshape(B, C, T + 1, 2)
    tr[:, :, 0] = q_ref[None, :, 0]
    return errors, tr
