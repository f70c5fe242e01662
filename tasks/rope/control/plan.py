"""Command planning on the coarse rope: CMA-ES over commands u with every generation of every
search evaluated as ONE batched coarse rollout (thousands of chains per trial).

The plan minimises the PREDICTED error of the real rope

    J(u) = total( Z_model(u) + d(u) )  +  reg |u - c|^2  +  LIMIT_PENALTY * hand-limit excess

inside the box and the trust region |u - c|_inf <= radius around the centre c, where `total` is
the correction's own error (observable.Target.terms, the number held to the tolerance) and
d(u) = d_c + D (u - c) is the model's offset learned from real trials (model-offset iterative
learning control): d_c = Z_real(c) - Z_model(c) at the centre trial, D a rank-one (Broyden)
estimate of how the offset changes, from pairs of trials. With d = 0 this is pure planning on
the model ("trial 0"). Because the offset is added in Z, a real trial at a fixed point of the
loop satisfies Z_real(u) = Z_model(u) + d = Z_goal whatever the model's error at u: the model
only needs the right SHAPE of Z(u) near the goal, not the right values. A global search (rather
than a linear step) lets the plan jump between the model's basins, e.g. to a throw whose loop
closes at another place along the rope.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from wrenorm.cmaes import BatchedCMAES
from wrenorm.tasks.rope import observable as crit

LIMIT_PENALTY = 10.0  # per unit of relative excess over the speed/acceleration limit: above any error
DEFAULT_REG = 1e-4  # per unit of u squared: a tie-breaker toward the centre, far below the tolerance
DEFAULT_POPSIZE = 48
DEFAULT_GENERATIONS = 30
DEFAULT_RESTARTS = 4


def state_vector(st: crit.CriticalStates) -> np.ndarray:
    """(B, 6K + 3) flat Z = positions, velocities, time, contact place (NaN rows for misses)."""
    B = st.batch
    return np.concatenate([st.pos.reshape(B, -1), st.vel.reshape(B, -1), st.time[:, None], st.s], axis=1)


def with_offset(st: crit.CriticalStates, dz: np.ndarray) -> crit.CriticalStates:
    """Z + dz (dz (B, 6K+3) or (6K+3,)); misses stay misses."""
    B, K = st.batch, st.pos.shape[1]
    dz = np.broadcast_to(np.asarray(dz, dtype=np.float64), (B, 6 * K + 3))
    return crit.CriticalStates(st.pos + dz[:, :3 * K].reshape(B, K, 3), st.vel + dz[:, 3 * K:6 * K].reshape(B, K, 3),
                               st.time + dz[:, 6 * K], st.s + dz[:, 6 * K + 1:], st.hit, st.clearance)


@dataclass
class Offset:
    """d(u) = d_c + D (u - c): the real rope minus the model, learned from trials."""

    centre: np.ndarray  # (n,) command of the centre trial
    d: np.ndarray  # (m,) Z_real - Z_model there
    D: np.ndarray  # (m, n) rank-one updates from trial pairs
    model_place: np.ndarray | None = None  # (2,) the model's contact place at the centre (frozen-place mode)

    @classmethod
    def zero(cls, n: int, m: int, centre=None) -> Offset:
        return cls(np.zeros(n) if centre is None else np.asarray(centre, dtype=np.float64), np.zeros(m),
                   np.zeros((m, n)))

    def __call__(self, U: np.ndarray) -> np.ndarray:
        return self.d[None] + (np.atleast_2d(U) - self.centre[None]) @ self.D.T

    def broyden(self, u_new: np.ndarray, d_new: np.ndarray) -> None:
        """Make d(u_new) = d_new with the smallest change of D (Broyden's good update)."""
        du = np.asarray(u_new, dtype=np.float64) - self.centre
        if du @ du > 0 and np.all(np.isfinite(d_new)):
            self.D += np.outer(d_new - self(u_new)[0], du) / (du @ du)

    def recentre(self, u: np.ndarray, d: np.ndarray) -> None:
        self.centre, self.d = np.asarray(u, dtype=np.float64).copy(), np.asarray(d, dtype=np.float64).copy()


def start_offset(model, u: np.ndarray, real_state: crit.CriticalStates) -> tuple[Offset | None, crit.CriticalStates]:
    """(the offset that makes the chain reproduce the real rope's critical state under a recorded command u, the
    chain's own state there): output space mapping's correction from the start throw, before any trial. Constant in
    u, with the contact place frozen at the chain's there as the trials' offsets freeze it, so the predicted place is
    the rope's under u wherever the chain goes. The offset is None where the rope or the chain misses under u.

    A constant offset is exact under u; near it the prediction is off by the difference of the rope's and the chain's
    sensitivity times the distance, where the chain alone is off by the whole miss. Measured on the fine rope and not
    the default (README, "Trial 1 on the chain plus the start throw's offset")."""
    u = np.asarray(u, dtype=np.float64)
    st = model.states(u[None])
    d = (state_vector(real_state) - state_vector(st))[0]
    if not (st.hit[0] and real_state.hit[0] and np.all(np.isfinite(d))):
        return None, st
    offset = Offset.zero(u.size, d.size, u)
    offset.recentre(u, d)
    offset.model_place = st.s[0].copy()
    return offset, st


def predicted_states(model, U: np.ndarray, offset: Offset) -> tuple[crit.CriticalStates, crit.CriticalStates]:
    """(predicted real critical states, the model's own) for a batch of commands: ONE rollout."""
    st = model.states(U)
    alone = crit.CriticalStates(st.pos, st.vel, st.time, st.s.copy(), st.hit, st.clearance)
    if offset.model_place is not None:
        # The coarse chain's contact place jumps between segment pairs where the real rope's moves
        # smoothly; predict the place from the trials alone (the real place at the centre, plus the
        # Broyden term), the rest of Z from the model.
        st.s = np.where(st.hit[:, None], offset.model_place[None], st.s)
    with np.errstate(invalid="ignore"):
        return with_offset(st, offset(U)), alone


def predicted_cost(model, goal: crit.Target, U: np.ndarray, offset: Offset, centre: np.ndarray, reg: float):
    """(cost (B,), predicted total (B,), model-alone total (B,)) for a batch of commands: ONE rollout."""
    pred, st = predicted_states(model, U, offset)
    with np.errstate(invalid="ignore"):
        total = goal.terms(pred)["total"]
        alone = goal.terms(st)["total"]
    excess = model.space.limit_excess(U)
    return total + reg * np.sum((U - centre[None]) ** 2, 1) + LIMIT_PENALTY * excess, total, alone


def plan(model, goal: crit.Target, centre: np.ndarray, radius: float, offset: Offset, seed: int = 0,
         popsize: int = DEFAULT_POPSIZE, generations: int = DEFAULT_GENERATIONS, restarts: int = DEFAULT_RESTARTS,
         reg: float = DEFAULT_REG, starts: list | None = None) -> dict:
    """Best command found by `restarts` CMA-ES searches side by side (one rollout per generation).

    The first search starts at the centre, the others at `starts` (e.g. earlier plans) and then at
    seeded random points of the trust box. The centre itself is always a candidate, so the plan
    never predicts worse than staying put.
    """
    space = model.space
    c = np.asarray(centre, dtype=np.float64)
    lo = np.maximum(space.lower, c - radius)
    hi = np.minimum(space.upper, c + radius)
    rng = np.random.default_rng(seed)
    x0s = [c] + [np.clip(np.asarray(s, dtype=np.float64), lo, hi) for s in (starts or [])]
    while len(x0s) < restarts:
        x0s.append(rng.uniform(lo, hi))
    t = time.perf_counter()
    cost, total, alone = predicted_cost(model, goal, c[None], offset, c, reg)
    best = {"u": c.copy(), "cost": float(cost[0]), "predicted_total": float(total[0]),
            "model_total": float(alone[0]), "evaluations": 1}
    # global stage from spread starts, then a local polish around the best: the event map is rough
    # (contact-pair switches), so a wide search alone stalls a few hundredths above its floor
    span = float(np.mean(hi - lo))
    _search(model, goal, offset, c, reg, x0s[:max(restarts, 1)], 0.3 * span, lo, hi, popsize, generations, seed, best)
    _search(model, goal, offset, c, reg, [best["u"]] * max(restarts // 2, 1), 0.05 * span, lo, hi, popsize,
            max(generations // 2, 1), seed + 500, best)
    best.update({"wall_s": time.perf_counter() - t, "radius": radius, "restarts": max(restarts, 1)})
    return best


def _search(model, goal, offset, c, reg, x0s, sigma, lo, hi, popsize, generations, seed, best) -> None:
    """CMA-ES searches side by side, one batched rollout per generation; updates `best` in place."""
    es = BatchedCMAES(np.array(x0s), sigma, lo, hi, [seed * 1000 + i + 1 for i in range(len(x0s))], popsize,
                      generations, tolfun=1e-9, tolx=1e-6)
    while not es.done:
        U = es.ask()
        cost, total, alone = predicted_cost(model, goal, U, offset, c, reg)
        best["evaluations"] += len(U)
        es.tell(cost)
        j = int(np.argmin(cost))
        if cost[j] < best["cost"]:
            best.update({"u": U[j].copy(), "cost": float(cost[j]), "predicted_total": float(total[j]),
                         "model_total": float(alone[j])})
