"""Correction by Gauss-Newton steps through the coarse chain's sensitivity, corrected by the real trials.

The chain is used LINEARLY: its sensitivity S = dZ/du (the critical state per unit of command, a central
difference over GN_FD_STEP units, all 2 dim(u) + 1 chains in one rollout) is the prior of the real rope's
sensitivity, and the real trials correct it along the directions they moved (secant pairs: the change of the
real critical state between each trial and the best one), all pairs together by ridge regression toward the
prior, each pair one directional derivative, the prior weighing RIDGE of one. The next command is the
trust-region Gauss-Newton step from the best trial on the real residual,

    du = argmin |R (W (S du) + e_best)|^2 + lam |du|^2,   |du| <= radius, inside the box and the hand limits,

with the radius fixed (fixed parameters, by default: README, "A fixed step instead of the adaptive trust region")
or following how well the linear model predicted the last trial (renormalise.TrustRegion, rho on the correction's
own error; the renormalised runs). R weighs the velocity rows VELOCITY_WEIGHT in the fixed-parameter steps (1 in the
renormalised ones): the trials showed the velocity at the contact to be the block the corrected sensitivity predicts
worst, while its residual is as large as the positions', so a step that weighs it fully aims much of its length at
changes it cannot predict. lam follows the weighted rows (qp_step). The norm |du| of the trust region is the
inf-norm (a box, qp_step) by default; `--trust-norm ball` takes the Euclidean norm over BALL_PER_RADIUS (ball_step),
where the box's corners would make the step longer than its radius in a direction no row asked for; measured on
held-out seeds, it reached as many runs as the box (README, "Steps in a ball").

Why linear, and why the chain's sensitivity is measured once: at 10 links the chain's critical state as a
function of the command is rough (the first contact jumps between segment pairs), so a plan on the chain's own
map plus an offset (plan.py) finds commands where the chain's jumps, not the rope, predict progress. The chain's
local sensitivity is much better than its map, and re-measuring it at every new best command swaps one roughness
for another and discards what the trials taught; measured once and corrected by every trial it stays consistent
(README, "Why Gauss-Newton steps through the chain's sensitivity", has the development runs).

Where the sensitivity is measured (space mapping's parameter extraction): not at the trial's own command but at
the command under which the chain reproduces the critical state the real rope showed there (matched_command).
The chain at its own command is in another state than the rope was; at the matched command it passes through the
rope's state, and its sensitivity there is the closer one (development runs in the README).

Renormalised ("renormalise", steps "gn"): after every trial the chain's parameters are refitted to the trials
(renormalise.refit) and its sensitivity is re-measured on the refitted chain, where it matches the same first trial
(at that trial's command with linearise_at "trial"); the trials then correct that new prior the same way.

Why ridge over all pairs rather than Broyden's update one pair at a time (the loop's first version): Broyden keeps
each earlier correction only as far as later ones leave it alone, and a pair taken against an earlier best command
is corrected again against the new best; the ridge fit weighs every pair the same at every step (README has the
development runs). Weighing far pairs down (pair_weight, `--secant-locality`) predicted the next trial no better and
reached as many runs on unseen seeds (README, "Near pairs before far ones"), so every pair counts alike by default.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from wrenorm.jacobian import jacobian
from wrenorm.tasks.rope import observable as crit
from wrenorm.tasks.rope.control.plan import state_vector, with_offset

GN_FD_STEP = 0.3  # units of u: the chain's sensitivity over 1.5 cm, 15 cm/s, 3 % of a segment's time
GN_RADIUS = 1.0  # initial trust radius (units of u)
GN_REG = 1e-2  # Levenberg term relative to mean diag(F^T F)
RIDGE = 0.05  # weight of the prior sensitivity against one secant pair's directional derivative
MATCH_REG = 1e-2  # per unit of u squared, against the squared weighted residual: keeps the matched command near
MATCH_SIGMA = 0.3  # the trial's command where the chain cannot tell commands apart; CMA-ES step, generations and
MATCH_GENERATIONS = 40  # population of the match (40 x 48 chains, about 0.2 s here)
MATCH_POPSIZE = 48
VELOCITY_WEIGHT = 0.5  # the fixed-parameter steps' weight on the velocity rows: the block they predict worst (README,
# "Which part of the critical state the steps can predict"); renormalised steps keep 1
VELOCITY_MODES = 2  # the renormalised steps' velocity rows: the velocity profile's first Legendre modes in arc length
# per axis, the part of its change the corrected sensitivity predicts (README, "The velocity profile's smooth part";
# 3 in stop 49); fixed-parameter steps keep every row
TRUST_NORMS = ("box", "ball")
BALL_PER_RADIUS = 2.5  # the ball's radius per unit of trust radius: the Euclidean length of the box's steps at its edge
# (median 2.3-2.55 on stop 50's runs), so a ball changes the step's direction, not its length
BALL_BISECTIONS = 50  # halvings of ball_step's bracket on the damping, 20 decades wide in log10: far below any step
FIRST_PLAN_REG = 3e-3  # trial 1's plan, per squared unit of u from the start, where Gauss-Newton steps follow: the
# chain reproduces the goal about as well over a long stretch of commands, and steps from the nearer end reach more
# often (README, "Trial 1 nearer the start")


def residual_weights(goal: crit.Target) -> np.ndarray:
    """(m,) w with goal.residual(Z) = w * (Z - Z_goal) in state_vector's layout: the observable's residual is
    linear block by block (shape / length, velocity / speed, time / t_goal, place), measured here once from
    unit changes of the goal's own state rather than restated."""
    m = goal.dim
    st = goal.state.take(np.zeros(m, dtype=int))
    return np.diag(goal.residual(with_offset(st, np.eye(m)))).astype(np.float64)


@dataclass
class Sensitivity:
    """S = dZ/du of the real rope near the best command: the chain's, corrected by the trials."""

    prior: np.ndarray  # (m, n) the chain's central difference
    S: np.ndarray  # (m, n) the current estimate
    columns: list  # per command component: central / forward / backward / none (the chain missed both sides)
    pairs: int = 0  # secant pairs learned so far
    chain_rollouts: int = 0
    wall_s: float = 0.0
    match: Match | None = None  # where it was measured, when not at a trial's own command
    pair_weights: list = field(default_factory=list)  # each secant pair's weight in the last ridge fit

    @classmethod
    def of_chain(cls, model, u: np.ndarray, step: float = GN_FD_STEP) -> Sensitivity:
        t = time.perf_counter()
        space = model.space
        jac = jacobian(lambda U: state_vector(model.states(U)), u, step, space.lower, space.upper)
        S = np.where(np.isfinite(jac.J), jac.J, 0.0)
        return cls(S.copy(), S, jac.kinds, 0, jac.evaluations, time.perf_counter() - t)

    def ridge(self, dus: list, dzs: list, weight: float = RIDGE, locality: float | None = None) -> None:
        """S = argmin sum c_k |(dz_k - S du_k) / |du_k||^2 + weight |S - prior|_F^2 over all pairs at once: each pair
        is one directional derivative. locality None: every pair counts alike whatever its length (c_k = 1);
        a length L: c_k = pair_weight(du_k, L), pairs farther than L from the best fading as (L / |du_k|_inf)^2.
        With one pair and weight -> 0 this is Broyden's update of the prior."""
        n = self.prior.shape[1]
        A, B = weight * np.eye(n), weight * self.prior
        self.pairs, self.pair_weights = 0, []
        for du, dz in zip(dus, dzs):
            norm2 = float(du @ du)
            if norm2 > 0 and np.all(np.isfinite(dz)):
                c = pair_weight(du, locality)
                A += c * np.outer(du, du) / norm2
                B = B + c * np.outer(dz, du) / norm2
                self.pairs += 1
                self.pair_weights.append(c)
        self.S = np.linalg.solve(A.T, B.T).T

    def record(self) -> dict:
        return {"chain_rollouts": self.chain_rollouts, "chain_wall_s": self.wall_s, "secant_pairs": self.pairs,
                "secant_pair_weights": [float(c) for c in self.pair_weights],
                "columns_not_central": [i for i, c in enumerate(self.columns) if c != "central"],
                "relative_correction": float(np.linalg.norm(self.S - self.prior)
                                             / max(np.linalg.norm(self.prior), 1e-12))} | (
            {} if self.match is None else self.match.record())


def pair_weight(du: np.ndarray, locality: float | None) -> float:
    """A secant pair's weight in the ridge fit: 1 within `locality` units of u of the best command (|du|_inf), then
    (locality / |du|_inf)^2; 1 for every pair without a locality. A pair across several steps is the mean slope over
    a long stretch of a map that is not linear there, which the nearer pairs describe better (README, "Near pairs
    before far ones")."""
    if locality is None:
        return 1.0
    d = float(np.abs(du).max())
    return 1.0 if d <= locality else (locality / d) ** 2


@dataclass
class Match:
    """The command under which the chain best reproduces a measured critical state."""

    u: np.ndarray
    trial_u: np.ndarray  # the real trial's command
    misfit_at_trial: float  # |w (Z_chain - Z_real)| at the trial's command (NaN: the chain misses there)
    misfit: float  # the same at the matched command
    chain_rollouts: int
    wall_s: float

    @property
    def distance(self) -> float:
        """How far the match lies from the trial's command (units of u, the largest component)."""
        return float(np.abs(self.u - self.trial_u).max())

    def record(self) -> dict:
        return {"linearised_at": self.u.tolist(), "distance_from_trial": self.distance,
                "misfit_at_trial": self.misfit_at_trial, "misfit_at_match": self.misfit,
                "match_rollouts": self.chain_rollouts, "match_wall_s": self.wall_s}


def matched_command(model, z_real: np.ndarray, w: np.ndarray, u_trial: np.ndarray, seed: int = 0,
                    reg: float = MATCH_REG) -> Match:
    """argmin_u |w (Z_chain(u) - z_real)|^2 + reg |u - u_trial|^2 by CMA-ES from the trial's command (the chain's map
    is rough, so no gradient); the trial's own command when nothing matches better."""
    from wrenorm.cmaes import BatchedCMAES

    t = time.perf_counter()
    space = model.space
    u_trial = np.asarray(u_trial, dtype=np.float64)

    def misfit(U):
        with np.errstate(invalid="ignore"):
            r = w[None] * (state_vector(model.states(U)) - z_real[None])
            return np.sum(r * r, axis=1), np.sum((U - u_trial[None]) ** 2, axis=1)

    m0, _ = misfit(u_trial[None])
    best_u, best_m, rollouts = u_trial.copy(), float(m0[0]), 1
    best_cost = best_m if np.isfinite(best_m) else np.inf
    es = BatchedCMAES(u_trial[None], MATCH_SIGMA, space.lower, space.upper, [seed + 1], MATCH_POPSIZE,
                      MATCH_GENERATIONS, tolfun=1e-12, tolx=1e-8)
    while not es.done:
        U = es.ask()
        m, d = misfit(U)
        cost = np.where(np.isfinite(m), m + reg * d, np.inf)
        rollouts += len(U)
        es.tell(cost)
        j = int(np.argmin(cost))
        if cost[j] < best_cost:
            best_u, best_m, best_cost = U[j].copy(), float(m[j]), float(cost[j])
    return Match(best_u, u_trial.copy(), float(np.sqrt(m0[0])), float(np.sqrt(best_m)), rollouts,
                 time.perf_counter() - t)


def space_mapping_step(match: Match, space) -> tuple[np.ndarray, float]:
    """Aggressive space mapping's first step (its mapping's Jacobian taken as the identity): the rope under the
    trial's command acted as the chain under the matched command, and the trial's command was the chain's own plan,
    so the command moves by the match's offset the other way, for the rope to act as the chain did under its plan.
    The feasible command (box and hand limits) and its step scale."""
    return space.limit_step(match.trial_u, match.trial_u - match.u)


def qp_step(F: np.ndarray, e: np.ndarray, u: np.ndarray, space, radius: float, reg: float = GN_REG,
            damping: float = 0.0) -> np.ndarray:
    """du minimising |F du + e|^2 + lam |du|^2 inside the box and the trust radius, lam = reg mean diag(F^T F)
    + damping."""
    from scipy.optimize import lsq_linear

    n = u.shape[0]
    scale = float(np.mean(np.sum(F * F, axis=0)))
    lam = reg * (scale if scale > 0 else 1.0) + damping
    A = np.concatenate([F, np.sqrt(lam) * np.eye(n)])
    b = np.concatenate([-e, np.zeros(n)])
    lo = np.maximum(space.lower - u, -radius)
    hi = np.minimum(space.upper - u, radius)
    hi = np.maximum(hi, lo + 1e-12)  # lsq_linear needs lo < hi
    return lsq_linear(A, b, bounds=(lo, hi), method="bvls").x


def ball_step(F: np.ndarray, e: np.ndarray, u: np.ndarray, space, ball: float, reg: float = GN_REG) -> np.ndarray:
    """qp_step's du inside the command box and the Euclidean ball |du|_2 <= ball instead of a box of the radius: where
    the least-squares step is longer, Levenberg-Marquardt's path, the extra damping mu of |F du + e|^2 + (lam + mu)
    |du|^2 found by bisection so that the step just reaches the ball (its length falls as mu grows)."""
    du = qp_step(F, e, u, space, ball, reg)  # the box of side 2 ball holds the ball
    if np.linalg.norm(du) <= ball:
        return du
    scale = float(np.mean(np.sum(F * F, axis=0))) or 1.0

    def length(log_mu: float) -> float:
        return float(np.linalg.norm(qp_step(F, e, u, space, ball, reg, scale * 10.0 ** log_mu)))

    low, high = -12.0, 8.0  # log10 of mu over mean diag(F^T F); the bisection keeps high's step inside the ball
    while length(high) > ball:
        high += 4.0
    for _ in range(BALL_BISECTIONS):
        mid = 0.5 * (low + high)
        low, high = (mid, high) if length(mid) > ball else (low, mid)
    return qp_step(F, e, u, space, ball, reg, scale * 10.0 ** high)


def step_length(du: np.ndarray, norm: str) -> float:
    """The step's length in units of trust radius: the inf-norm for the box, |du|_2 / BALL_PER_RADIUS for the ball."""
    return float(np.abs(du).max()) if norm == "box" else float(np.linalg.norm(du)) / BALL_PER_RADIUS


def step_row_weights(goal: crit.Target, velocity_weight: float) -> np.ndarray:
    """(m,) the Gauss-Newton step's weight per row of the residual: velocity_weight on the velocity block, 1 elsewhere.
    The step only: the error that accepts a trial and the one reported stay the observable's."""
    rows = np.ones(goal.dim)
    rows[goal.blocks["velocity"]] = velocity_weight
    return rows


def velocity_projection(goal: crit.Target, modes: int) -> np.ndarray | None:
    """(m, m) the orthogonal projection of a residual in state_vector's layout that keeps the velocity profile's first
    `modes` Legendre modes in arc length on each axis and every other row; None where it keeps everything (modes at
    or above the profile's samples). The steps' velocity rows: near the goal the corrected sensitivity predicts the
    profile's smooth change (cosine 0.8-0.9 to the rope's) and not the rest (no better than zero), so a step that
    chases the rest aims at what it cannot predict (README, "The velocity profile's smooth part")."""
    return mode_projection(goal, "velocity", modes)


def mode_projection(goal: crit.Target, block: str, modes: int) -> np.ndarray | None:
    """(m, m) the orthogonal projection that keeps, of the residual's rows of `block` (position or velocity, in
    state_vector's layout), the profile's first `modes` Legendre modes in arc length on each axis, and every other
    row; None where it keeps everything (modes at or above the profile's samples)."""
    from numpy.polynomial import legendre

    rows = np.arange(goal.dim)[goal.blocks[block]]
    samples = len(rows) // 3
    if modes >= samples:
        return None
    basis = legendre.legvander(np.linspace(-1.0, 1.0, samples), modes - 1)  # (samples, modes)
    keep = basis @ np.linalg.pinv(basis)
    Q = np.eye(goal.dim)
    Q[np.ix_(rows, rows)] = np.kron(keep, np.eye(3))  # rows are sample-major: (x, y, z) of sample 0, then 1, ...
    return Q


def gn_step(S: np.ndarray, w: np.ndarray, e_best: np.ndarray, u_best: np.ndarray, space, radius: float,
            reg: float = GN_REG, rows: np.ndarray | None = None,
            projection: np.ndarray | None = None, norm: str = "box") -> tuple[np.ndarray, float]:
    """The feasible command of the trust-region Gauss-Newton step from the best trial, and its step scale; `rows`
    (step_row_weights) scales each row of the least-squares problem, `projection` (velocity_projection) then keeps
    its part of the weighted residual; `norm` "box" bounds each coordinate of the step by the radius, "ball" its
    Euclidean length by BALL_PER_RADIUS x the radius."""
    if rows is not None:
        w, e_best = rows * w, rows * e_best
    F = w[:, None] * S
    if projection is not None:
        F, e_best = projection @ F, projection @ e_best
    if norm == "ball":
        du = ball_step(F, e_best, u_best, space, BALL_PER_RADIUS * radius, reg)
    else:
        du = qp_step(F, e_best, u_best, space, radius, reg)
    return space.limit_step(u_best, du)


FLOOR_REG = 1e-9  # relative Levenberg term of the floor's least-squares start: numerical only


def predicted_errors(goal: crit.Target, best_state: crit.CriticalStates, S: np.ndarray, dU: np.ndarray) -> np.ndarray:
    """(B,) the goal's error of the linear model's states after the steps dU (B, n) from the best trial."""
    dU = np.atleast_2d(dU)
    st = best_state.take(np.zeros(len(dU), dtype=int))
    return goal.terms(with_offset(st, dU @ S.T))["total"]


@dataclass
class Floor:
    """The corrected model's floor: the command, which candidate it was (the SLSQP search, the least-squares start,
    or a step in `also`) and how SLSQP ended (scipy's status and message), so a floor that only fell back is seen."""

    u: np.ndarray
    found_by: str
    solver_status: int
    solver_message: str


def model_floor(goal: crit.Target, best_state: crit.CriticalStates, S: np.ndarray, w: np.ndarray,
                e_best: np.ndarray, u_best: np.ndarray, space, rows: np.ndarray | None = None,
                also: tuple = ()) -> Floor:
    """The command inside the command box whose error the linear model predicts least: what the corrected model
    says any command can still reach, with neither trust radius nor hand limits (which only shorten a step). A
    step predicted no better than this is limited by the model, not by the trust radius (README, "What the steps
    can still reach").

    The predicted error is a sum of norms of linear functions of the command (Target.error_groups: |e_g + F_g du|
    with F = W S), convex with kinks where a term reaches 0, where the floor usually lies (a gradient method stops
    at them). So it is solved as the smooth convex program min sum t_g, t_g >= |e_g + F_g du|, inside the box
    (SLSQP), from the step's least-squares solution without a radius (with the step's row weights `rows`); the
    result (when finite), that start and the commands in `also` (the step taken) are scored by the observable and
    the best kept, so a failed search falls back to them rather than to something worse."""
    from scipy.optimize import minimize

    F = w[:, None] * S
    n = len(u_best)
    lo, hi = space.lower - u_best, space.upper - u_best
    groups = goal.error_groups
    G = len(groups)
    r_rows, e_rows = (w, e_best) if rows is None else (rows * w, rows * e_best)
    du_ls = qp_step(r_rows[:, None] * S, e_rows, u_best, space, np.inf, FLOOR_REG)

    def norms(du):
        r = e_best + F @ du
        return [r[g] for g in groups], np.array([np.sqrt(r[g] @ r[g] + 1e-24) for g in groups])

    def constraint(x):
        return x[n:] - norms(x[:n])[1]

    def constraint_jacobian(x):
        parts, size = norms(x[:n])
        J = np.zeros((G, n + G))
        for i, (g, r_g) in enumerate(zip(groups, parts)):
            J[i, :n] = -(F[g].T @ r_g) / size[i]
        J[:, n:] = np.eye(G)
        return J

    x0 = np.concatenate([du_ls, norms(du_ls)[1] * (1 + 1e-6)])
    found = minimize(lambda x: float(np.sum(x[n:])), x0, jac=lambda x: np.concatenate([np.zeros(n), np.ones(G)]),
                     method="SLSQP", bounds=list(zip(lo, hi)) + [(0.0, None)] * G,
                     constraints=[{"type": "ineq", "fun": constraint, "jac": constraint_jacobian}],
                     options={"maxiter": 500, "ftol": 1e-12})
    searched = np.all(np.isfinite(found.x))
    candidates = [du_ls] + ([np.clip(found.x[:n], lo, hi)] if searched else []) + [np.asarray(u) - u_best for u in also]
    names = ["least squares"] + (["search"] if searched else []) + ["step"] * len(also)
    errors = predicted_errors(goal, best_state, S, np.stack(candidates))
    best = int(np.nanargmin(errors))
    return Floor(u_best + candidates[best], names[best], int(found.status), str(found.message))


def floor_record(goal: crit.Target, best_state: crit.CriticalStates, S: np.ndarray, u_best: np.ndarray,
                 floor: Floor) -> dict:
    """The floor's predicted error, its terms, how far it lies from the best command (units of u, largest
    component), which candidate it was and how the search ended."""
    terms = goal.terms(predicted_state(best_state, S, floor.u - u_best))
    return {"error": float(terms["total"][0]), "terms": {k: float(v[0]) for k, v in terms.items() if k != "total"},
            "distance": float(np.abs(floor.u - u_best).max()), "found_by": floor.found_by,
            "solver_status": floor.solver_status, "solver_message": floor.solver_message}


def secant_pairs(trials: list, best, recorded: list, recorded_until: str) -> tuple[list, list]:
    """The secant pairs the sensitivity is corrected by before a step from `best`: every other trial that hit (its
    change of command and of critical state against the best), and the commands recorded before the trials (u,
    state) while the trials give none (recorded_until "first") or always ("every"). `trials` hold .u, .state, .hit."""
    others = [(tr.u, tr.state) for tr in trials if tr.hit and tr is not best]
    if not others or recorded_until == "every":
        others += recorded
    Zb = state_vector(best.state)[0]
    return [u_k - best.u for u_k, _ in others], [state_vector(st_k)[0] - Zb for _, st_k in others]


def predicted_state(best_state: crit.CriticalStates, S: np.ndarray, du: np.ndarray) -> crit.CriticalStates:
    """The linear model's critical state after the step du from the best trial."""
    return with_offset(best_state, S @ du)
