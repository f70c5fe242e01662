"""The rope's observable on the device: each chain's critical state (its state at the first self-collision,
resampled to K common arc-length points) and its error to a target critical state, as two Warp kernels, so that
a generation's rollouts, critical states and errors stay where the chains ran and only (chains x terms) numbers
cross to the host. The same kernels score host-side states (a real trial, a planner's candidate states) on the
CPU: there is one implementation of the observable (tasks/rope/observable.py says what it measures and why).

chain_states_kernel   rollout events (ChainEvents) -> critical states at K points, float64
critical_terms_kernel critical states -> error terms, their weighted total (a miss costs the no-hit rule), and
                      optionally the weighted residual vector e = W (Z - Z_target)
"""
from __future__ import annotations

import numpy as np
import warp as wp

TERMS = ("shape", "velocity", "time", "place", "total")  # columns of the terms array
wp.set_module_options({"enable_backward": False, "optimization_level": 3})


@wp.struct
class TargetStates:
    """One target critical state per condition (float64)."""

    pos: wp.array2d(dtype=wp.vec3d)  # (C, K) m
    vel: wp.array2d(dtype=wp.vec3d)  # (C, K) m/s
    time: wp.array(dtype=wp.float64)  # (C,) s from the start of the motion
    s: wp.array(dtype=wp.vec2d)  # (C,) arc-length fractions of the contact
    speed: wp.array(dtype=wp.float64)  # (C,) m/s, RMS speed of the target state (>= the observable's floor)
    length: wp.array(dtype=wp.float64)  # (C,) m, the rope's length (shape errors are relative to it)
    weights: wp.array(dtype=wp.vec4d)  # (C,) weights of shape, velocity, time, place


@wp.struct
class NoHitRule:
    cost: wp.float64  # what a rope that never hits costs, before its closest approach
    scale: wp.float64  # of the length: a closest approach this far (or farther) adds 1


@wp.func
def resample_at(p: wp.array2d(dtype=wp.vec3), b: int, n: int, k: int, samples: int) -> wp.vec3d:
    """Piecewise-linear value at the k-th of `samples` evenly spaced arc-length points of chain b's n nodes
    (evenly spaced too): as numpy's searchsorted(side="right") picks the interval, the upper node of an exact
    hit is its interval's start."""
    x = wp.float64(k) * wp.float64(n - 1) / wp.float64(samples - 1)
    i = wp.min(int(wp.floor(x)), n - 2)
    u = x - wp.float64(i)
    a = p[b, i]
    c = p[b, i + 1]
    one = wp.float64(1.0)
    return wp.vec3d(wp.float64(a[0]) * (one - u) + wp.float64(c[0]) * u,
                    wp.float64(a[1]) * (one - u) + wp.float64(c[1]) * u,
                    wp.float64(a[2]) * (one - u) + wp.float64(c[2]) * u)


@wp.kernel
def chain_states_kernel(status: wp.array(dtype=wp.int32), hit_frame: wp.array(dtype=wp.int32),
                        hit_alpha: wp.array(dtype=float), hit_s: wp.array(dtype=wp.vec2),
                        crit_pos: wp.array2d(dtype=wp.vec3), crit_vel: wp.array2d(dtype=wp.vec3),
                        clearance: wp.array(dtype=float), condition: wp.array(dtype=wp.int32),
                        horizon: wp.array(dtype=wp.int32), dt: wp.float64, t0: wp.float64, samples: int,
                        out_status: wp.array(dtype=wp.int32), out_time: wp.array(dtype=wp.float64),
                        out_s: wp.array(dtype=wp.vec2d), out_clearance: wp.array(dtype=wp.float64),
                        out_pos: wp.array2d(dtype=wp.vec3d), out_vel: wp.array2d(dtype=wp.vec3d)):
    """Chain b's critical state: status (0 no hit, 1 hit, 2 blew up), a hit after its condition's horizon
    counted as none; the hit time from t0; the contact's arc-length fractions; the closest approach of a chain
    that never hit (inf for a blow-up, 0 for a hit); positions and velocities at the K points (NaN unless hit)."""
    b = wp.tid()
    st = status[b]
    if st == 1 and hit_frame[b] > horizon[condition[b]]:
        st = 0
    out_status[b] = st
    n = crit_pos.shape[1]
    nan = wp.float64(wp.nan)
    if st == 1:
        out_time[b] = t0 + (wp.float64(hit_frame[b] - 1) + wp.float64(hit_alpha[b])) * dt
        out_s[b] = wp.vec2d(wp.float64(hit_s[b][0]), wp.float64(hit_s[b][1]))
        out_clearance[b] = wp.float64(0.0)
        for k in range(samples):
            out_pos[b, k] = resample_at(crit_pos, b, n, k, samples)
            out_vel[b, k] = resample_at(crit_vel, b, n, k, samples)
    else:
        out_time[b] = nan
        out_s[b] = wp.vec2d(nan, nan)
        c = wp.float64(clearance[b])
        if st == 2:
            c = wp.float64(wp.inf)
        out_clearance[b] = c
        for k in range(samples):
            out_pos[b, k] = wp.vec3d(nan, nan, nan)
            out_vel[b, k] = wp.vec3d(nan, nan, nan)


@wp.kernel
def critical_terms_kernel(status: wp.array(dtype=wp.int32), time: wp.array(dtype=wp.float64),
                          s: wp.array(dtype=wp.vec2d), clearance: wp.array(dtype=wp.float64),
                          pos: wp.array2d(dtype=wp.vec3d), vel: wp.array2d(dtype=wp.vec3d),
                          condition: wp.array(dtype=wp.int32), target: TargetStates, miss: NoHitRule,
                          with_residual: int, terms: wp.array2d(dtype=wp.float64),
                          residual: wp.array2d(dtype=wp.float64)):
    """Row b's error to its condition's target: shape (RMS distance at the K points / length), velocity (RMS
    velocity difference / target speed), time (|t - t*| / t*), place (mean |s - s*|) and the weighted total; a
    row that never hit costs no_hit + min(clearance, scale) / scale (a blow-up: no_hit + 1), its terms NaN.
    with_residual: also the weighted residual row (NaN for a miss)."""
    b = wp.tid()
    c = condition[b]
    K = pos.shape[1]
    w = target.weights[c]
    length = target.length[c]
    nan = wp.float64(wp.nan)
    zero = wp.float64(0.0)
    if status[b] == 1:
        dp = zero
        dv = zero
        rp = w[0] / (length * wp.sqrt(wp.float64(K)))
        rv = w[1] / (target.speed[c] * wp.sqrt(wp.float64(K)))
        for k in range(K):
            ep = pos[b, k] - target.pos[c, k]
            ev = vel[b, k] - target.vel[c, k]
            dp += wp.dot(ep, ep)
            dv += wp.dot(ev, ev)
            if with_residual != 0:
                for j in range(3):
                    residual[b, 3 * k + j] = rp * ep[j]
                    residual[b, 3 * K + 3 * k + j] = rv * ev[j]
        shape = wp.sqrt(dp / wp.float64(K)) / length
        velocity = wp.sqrt(dv / wp.float64(K)) / target.speed[c]
        t_err = wp.abs(time[b] - target.time[c]) / target.time[c]
        ds = s[b] - target.s[c]
        place = wp.float64(0.5) * (wp.abs(ds[0]) + wp.abs(ds[1]))
        terms[b, 0] = shape
        terms[b, 1] = velocity
        terms[b, 2] = t_err
        terms[b, 3] = place
        terms[b, 4] = w[0] * shape + w[1] * velocity + w[2] * t_err + w[3] * place
        if with_residual != 0:
            residual[b, 6 * K] = (w[2] / target.time[c]) * (time[b] - target.time[c])
            residual[b, 6 * K + 1] = wp.float64(0.5) * w[3] * ds[0]
            residual[b, 6 * K + 2] = wp.float64(0.5) * w[3] * ds[1]
    else:
        for j in range(4):
            terms[b, j] = nan
        gap = clearance[b]
        if wp.isnan(gap):
            gap = wp.float64(wp.inf)
        scale = miss.scale * length
        gap = wp.min(wp.max(gap, zero), scale)
        terms[b, 4] = miss.cost + gap / scale
        if with_residual != 0:
            for j in range(6 * K + 3):
                residual[b, j] = nan


class DeviceStates:
    """Critical states of a batch, as device arrays (chain_states_kernel's outputs, or host states moved)."""

    def __init__(self, batch: int, samples: int, device: str):
        self.device = device
        self.status = wp.zeros(batch, dtype=wp.int32, device=device)
        self.time = wp.zeros(batch, dtype=wp.float64, device=device)
        self.s = wp.zeros(batch, dtype=wp.vec2d, device=device)
        self.clearance = wp.zeros(batch, dtype=wp.float64, device=device)
        self.pos = wp.zeros((batch, samples), dtype=wp.vec3d, device=device)
        self.vel = wp.zeros((batch, samples), dtype=wp.vec3d, device=device)

    @property
    def batch(self) -> int:
        return self.status.shape[0]

    @classmethod
    def from_host(cls, status, time, s, clearance, pos, vel, device: str = "cpu") -> DeviceStates:
        out = cls.__new__(cls)
        out.device = device
        f64 = lambda a, dt: wp.array(np.ascontiguousarray(a, dtype=np.float64), dtype=dt, device=device)  # noqa: E731
        out.status = wp.array(np.ascontiguousarray(status, dtype=np.int32), dtype=wp.int32, device=device)
        out.time, out.s, out.clearance = f64(time, wp.float64), f64(s, wp.vec2d), f64(clearance, wp.float64)
        out.pos, out.vel = f64(pos, wp.vec3d), f64(vel, wp.vec3d)
        return out

    def to_host(self) -> dict:
        return {"status": self.status.numpy(), "time": self.time.numpy(), "s": self.s.numpy(),
                "clearance": self.clearance.numpy(), "pos": self.pos.numpy(), "vel": self.vel.numpy()}


def chain_states(events, condition, horizon, dt: float, t0: float, samples: int) -> DeviceStates:
    """Critical states of every chain of a rollout (ChainEvents on its device) at `samples` points."""
    device = str(events.status.device)
    B = events.status.shape[0]
    out = DeviceStates(B, samples, device)
    cond = wp.array(np.ascontiguousarray(condition, dtype=np.int32), dtype=wp.int32, device=device)
    hor = wp.array(np.ascontiguousarray(horizon, dtype=np.int32), dtype=wp.int32, device=device)
    wp.launch(chain_states_kernel, dim=B, device=device, inputs=[
        events.status, events.hit_frame, events.hit_alpha, events.hit_s, events.crit_pos, events.crit_vel,
        events.clearance, cond, hor, wp.float64(dt), wp.float64(t0), int(samples)],
        outputs=[out.status, out.time, out.s, out.clearance, out.pos, out.vel])
    return out


def target_states(pos, vel, time, s, speed, length, weights, device: str) -> TargetStates:
    """Targets of C conditions: pos, vel (C, K, 3), time, speed, length (C,), s (C, 2), weights (C, 4)."""
    f64 = lambda a, dt: wp.array(np.ascontiguousarray(a, dtype=np.float64), dtype=dt, device=device)  # noqa: E731
    t = TargetStates()
    t.pos, t.vel, t.s = f64(pos, wp.vec3d), f64(vel, wp.vec3d), f64(s, wp.vec2d)
    t.time, t.speed, t.length = f64(time, wp.float64), f64(speed, wp.float64), f64(length, wp.float64)
    t.weights = f64(weights, wp.vec4d)
    return t


def no_hit_rule(cost: float, scale: float) -> NoHitRule:
    rule = NoHitRule()
    rule.cost, rule.scale = wp.float64(cost), wp.float64(scale)
    return rule


def critical_terms(states: DeviceStates, condition, target: TargetStates, miss: NoHitRule,
                   residual: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
    """(B, 5) terms (TERMS order) and, if asked, the (B, 6K + 3) weighted residuals, on the host."""
    device, B = states.device, states.batch
    K = states.pos.shape[1]
    cond = wp.array(np.ascontiguousarray(condition, dtype=np.int32), dtype=wp.int32, device=device)
    terms = wp.zeros((B, len(TERMS)), dtype=wp.float64, device=device)
    res = wp.zeros((B, 6 * K + 3) if residual else (1, 1), dtype=wp.float64, device=device)
    wp.launch(critical_terms_kernel, dim=B, device=device, inputs=[
        states.status, states.time, states.s, states.clearance, states.pos, states.vel, cond, target, miss,
        int(residual)], outputs=[terms, res])
    return terms.numpy(), (res.numpy() if residual else None)
