"""The rope state at its first self-collision ("critical state" Z) as one vector, for the real
rope (a RopeReference) and for batches of coarse chains, and the weighted residual to a goal.

Z = positions and velocities at SAMPLES common arc-length points, the collision time from the
start, and the two arc-length fractions of the contact. The residual e = W (Z - Z_goal) uses the
normalisations and weights of tasks/rope.py, block by block:
  positions  w_shape (x - x_g) / (L sqrt K)        -> |e_pos| = w_shape * RMS / L  (rope.py's shape term)
  velocities w_vel (v - v_g) / (speed_g sqrt K)    -> |e_vel| = w_vel * velocity term
  time       w_time (t - t_g) / t_g                -> |e_t|   = w_time * time term
  place      w_place (s - s_g) / 2                 -> |e_s| <= w_place * place term (L2 <= L1 mean)
so |e|^2 is the QP's objective (Q = I in these units) and `total` is the fit's error, the number
the correction drives below its tolerance.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wrenorm.errors import InputError
from wrenorm.tasks.rope.problem import NO_HIT, SAMPLES, WEIGHTS, prepare_case, resample


@dataclass
class CriticalStates:
    """A batch of critical states; rows with hit == False carry no state (NaN)."""

    pos: np.ndarray  # (B, K, 3) m
    vel: np.ndarray  # (B, K, 3) m/s
    time: np.ndarray  # (B,) s from the start of the motion
    s: np.ndarray  # (B, 2) arc-length fractions of the contact (held-end side, free-end side)
    hit: np.ndarray  # (B,) bool
    clearance: np.ndarray  # (B,) m, closest approach of chains that never hit (0 for hits)

    @property
    def batch(self) -> int:
        return self.pos.shape[0]

    def row(self, i: int) -> "CriticalStates":
        return CriticalStates(self.pos[i:i + 1], self.vel[i:i + 1], self.time[i:i + 1], self.s[i:i + 1],
                              self.hit[i:i + 1], self.clearance[i:i + 1])


def from_reference(ref, name: str = "real") -> CriticalStates:
    """Critical state of one rope trajectory (the real rope), interpolated as tasks/rope.py does."""
    try:
        case = prepare_case(name, ref, 3, ref.dt)
    except InputError:
        from wrenorm.tasks.rope.reference.events import gap_series

        gap = gap_series(ref.markers, ref.marker_arclength, ref.length, ref.radius)[0]
        nan = np.full((1, SAMPLES, 3), np.nan)
        return CriticalStates(nan, nan.copy(), np.full(1, np.nan), np.full((1, 2), np.nan), np.zeros(1, bool),
                              np.array([max(float(np.min(gap[1:])), 0.0)]))
    ev = case.event
    return CriticalStates(case.ref_pos[None], case.ref_vel[None], np.array([ev.time - ref.time[0]]),
                          np.array([[ev.s_a, ev.s_b]]), np.ones(1, bool), np.zeros(1))


def from_rollout(res, n_nodes: int, t0: float = 0.0) -> CriticalStates:
    """Critical states of a batch of coarse chains (kernels.rope.RolloutResult)."""
    s_nodes = np.linspace(0.0, 1.0, n_nodes)
    s_k = np.linspace(0.0, 1.0, SAMPLES)
    hit = res.status == 1
    mask = np.where(hit, 1.0, np.nan)[:, None, None]
    return CriticalStates(resample(res.crit_pos, s_nodes, s_k) * mask, resample(res.crit_vel, s_nodes, s_k) * mask,
                          np.where(hit, res.hit_time - t0, np.nan), np.stack([res.s_a, res.s_b], 1),
                          hit, np.where(hit, 0.0, res.clearance.astype(np.float64)))


@dataclass
class Goal:
    """The critical state to reproduce, with the scales that make residuals dimensionless."""

    state: CriticalStates  # batch of one
    length: float  # m
    speed: float  # m/s, RMS speed of the goal's critical state (>= tasks.rope.MIN_SPEED)
    weights: dict

    @classmethod
    def from_reference(cls, ref, weights: dict | None = None) -> "Goal":
        st = from_reference(ref, "goal")
        if not st.hit[0]:
            raise InputError("goal", "markers", "the goal rope never hits itself (no critical state to reach)")
        case = prepare_case("goal", ref, 3, ref.dt)
        return cls(st, float(ref.length), float(case.speed), dict(WEIGHTS if weights is None else weights))

    @property
    def dim(self) -> int:
        return 6 * SAMPLES + 3

    @property
    def blocks(self) -> dict:
        K = SAMPLES
        return {"position": slice(0, 3 * K), "velocity": slice(3 * K, 6 * K), "time": slice(6 * K, 6 * K + 1),
                "place": slice(6 * K + 1, 6 * K + 3)}

    def residual(self, st: CriticalStates) -> np.ndarray:
        """(B, dim) weighted residual e = W (Z - Z_goal); NaN rows for chains that never hit."""
        g, w, K = self.state, self.weights, SAMPLES
        B = st.batch
        return np.concatenate([
            (w["shape"] / (self.length * np.sqrt(K))) * (st.pos - g.pos).reshape(B, -1),
            (w["velocity"] / (self.speed * np.sqrt(K))) * (st.vel - g.vel).reshape(B, -1),
            (w["time"] / g.time[0]) * (st.time - g.time)[:, None],
            (0.5 * w["place"]) * (st.s - g.s),
        ], axis=1)

    def terms(self, st: CriticalStates) -> dict:
        """rope.py's error terms and their weighted total per row; a miss costs NO_HIT (+ clearance)."""
        g, w = self.state, self.weights
        rms = lambda d: np.sqrt(np.mean(np.sum(d ** 2, -1), -1))  # noqa: E731
        t = {
            "shape": rms(st.pos - g.pos) / self.length,
            "velocity": rms(st.vel - g.vel) / self.speed,
            "time": np.abs(st.time - g.time) / g.time[0],
            "place": 0.5 * np.abs(st.s - g.s).sum(-1),
        }
        total = sum(w[k] * t[k] for k in t)
        # clearance is in metres; over a tenth of the length it is O(1), like rope.py's / margin
        # a rope that blew up (non-finite clearance) costs the largest miss, not NaN
        clear = np.minimum(np.nan_to_num(np.asarray(st.clearance, np.float64), nan=1.0, posinf=1.0), 1.0)
        t["total"] = np.where(st.hit, total, NO_HIT + clear / (0.1 * self.length))
        return t
