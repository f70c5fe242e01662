"""Host side of the swimmer: candidate-independent per-sample sums (reduce_table) and SwimBatch, the
device-resident inputs of one set of conditions, launched over slices of the batch."""
from __future__ import annotations

import numpy as np
import warp as wp

from wrenorm.kernels.launch import launch_sliced
from wrenorm.kernels.swimmer.fluid import fluid_geometry_kernel, geo9
from wrenorm.kernels.swimmer.kernel import ROW, Schedule, Water, swim_kernel


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
        self.part_table, self.parts = table, parts  # per-part inputs, for reference implementations
        sched = Schedule()
        ints = lambda a: wp.array(np.asarray(a, np.int32), dtype=int, device=d)  # noqa: E731
        sched.tab_off, sched.n_per, sched.n_warm, sched.n_meas = ints(tab_off), ints(n_per), ints(n_warm), ints(n_meas)
        sched.dt = wp.array(np.asarray(dt, np.float32), dtype=float, device=d)
        sched.max_warm = ints(n_warm if max_warm is None else max_warm)
        sched.settle_abs, sched.settle_rel = float(settle_abs), float(settle_rel)
        self.schedule = sched
        self.water = Water()
        self.water.rho, self.water.mu, self.water.virtual_mass, self.water.ref_x = (self.rho, self.mu,
                                                                                    self.virtual_mass, self.ref_x)
        # host copies: steps per beat, step [s] and measured steps per condition
        self.n_per_host = np.asarray(n_per, np.int64)
        self.dt_host = np.asarray(dt, np.float64)
        self.n_meas_host = np.asarray(n_meas, np.int64)
        self.steps = np.asarray(n_warm) + np.asarray(n_meas)  # at least; warm-up may run longer
        self.sim_seconds = self.steps * np.asarray(dt, np.float64)

    def run(self, coef: np.ndarray, rec_stride: int = 0, rec_frames: int = 0, rec_meas: bool = False):
        """Speeds (B, C) for coefficients (B, 5), or (B, 6) whose last column is the viscosity [Pa s] (else the
        water's); with rec_stride > 0 also the recorded (B, C, rec_frames, 4) trajectory (X, Y, theta, beat
        sample) every rec_stride steps, from the start or (rec_meas) from the first measured step (a beat
        start), and the final state (B, C, 7)."""
        coef = np.atleast_2d(np.asarray(coef, np.float32))
        if coef.shape[1] not in (5, 6):
            raise ValueError(f"coefficients must have 5 or 6 columns, got {coef.shape[1]}")
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
                self.schedule, self.water, self.scheme,
                int(rec_stride), int(bool(rec_meas)), traj, speed, yaw, state])

        launch_sliced(launch, n, d)
        shape = (coef.shape[0], self.n_cond)
        out = speed.numpy().reshape(shape).astype(np.float64)
        # amplitude [rad] of the head's yaw oscillation at the beat frequency, per run
        self.last_yaw = yaw.numpy().reshape(shape).astype(np.float64)
        self.last_state = state.numpy().reshape(shape + (7,))
        if rec_stride > 0:
            return out, traj.numpy().reshape(shape + traj.shape[1:]), self.last_state
        return out


