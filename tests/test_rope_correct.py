"""Command correction and sensitivity on the coarse rope (fast: the coarse chain plays the real rope)."""
import json
import shlex
from types import SimpleNamespace

import numpy as np
import pytest

from wrenorm.errors import InputError
from wrenorm.tasks.rope import observable as crit
from wrenorm.tasks.rope.control import secant
from wrenorm.tasks.rope.control.command import CommandSpace
from wrenorm.tasks.rope.control.correct import CoarseModel, CoarseRope, correct, parameters_from_file, qp_step
from wrenorm.tasks.rope.control.plan import Offset, plan, predicted_cost, state_vector, with_offset
from wrenorm.tasks.rope.control.sensitivity import resolvable
from wrenorm.tasks.rope.observable import SAMPLES
from wrenorm.tasks.rope.problem import RopeProblem
from wrenorm.tasks.rope.reference.generate import builtin_reference_path, load_reference
from wrenorm.tasks.rope.reference.paths import HandPath, builtin_hand_paths

PATHS = builtin_hand_paths()


@pytest.fixture(scope="module")
def problem():
    ref = load_reference(builtin_reference_path("flick", "default"))
    return RopeProblem([ref], segments=10, dt=0.005)


def shifted(problem):
    v = problem.space.measured.copy()
    v[problem.space.index("bend_stiffness")] *= 2.0
    v[problem.space.index("drag_quad")] *= 0.5
    return v


# ------------------------------------------------------------------------------ command
def test_command_roundtrip_and_limits():
    space = CommandSpace(PATHS["flick"])
    u = space.encode(PATHS["flick_high"])
    assert np.allclose(space.decode(u).control_points, PATHS["flick_high"].control_points, atol=1e-12)
    assert np.allclose(space.encode(space.decode(0.7 * u)), 0.7 * u, atol=1e-12)
    # a step far outside the hand's limits is shortened until they hold
    big = np.zeros(space.dim)
    big[space.names.index("v1.x")] = 50.0
    new, s = space.limit_step(np.zeros(space.dim), big)
    assert 0.0 < s < 1.0 or np.all(np.abs(new) <= space.bound)
    assert space.feasible(new)
    assert space.decode(new).max_speed() <= space.max_speed + 1e-9
    with pytest.raises(InputError):
        # a kink at the middle waypoint: incoming velocity along x, outgoing along z
        CommandSpace(HandPath(np.array([[0, 0, 1.6], [0, 0, 1.6], [0.1, 0, 1.7], [0.2, 0, 1.7],
                                        [0.2, 0, 1.9], [0.3, 0, 1.9], [0.3, 0, 1.9]]), np.array([0.3, 0.3])))


def test_qp_step_respects_trust_region_and_solves_linear_case():
    space = CommandSpace(PATHS["flick"])
    rng = np.random.default_rng(1)
    F = rng.normal(size=(20, space.dim))
    du_true = rng.uniform(-0.3, 0.3, space.dim)
    e = -F @ du_true
    du = qp_step(F, e, np.zeros(space.dim), space, radius=1.0, reg=1e-8)
    assert np.allclose(du, du_true, atol=1e-4)
    du = qp_step(F, 10 * e, np.zeros(space.dim), space, radius=0.5, reg=1e-8)
    assert np.abs(du).max() <= 0.5 + 1e-9


def test_ball_step_is_the_least_squares_step_on_the_balls_surface():
    """secant.ball_step against the trust-region subproblem solved independently: without active box bounds its step
    is -(F^T F + (lam + mu) I)^-1 F^T e with mu >= 0 the root of |du(mu)|_2 = ball (More and Sorensen), found here on
    F's eigenbasis by brentq; inside the ball it is qp_step's; with the command box active it stays inside both and
    is no worse than any feasible point of the ball tried at random."""
    from scipy.optimize import brentq

    space = CommandSpace(PATHS["flick"])
    rng = np.random.default_rng(5)
    F = rng.normal(size=(30, space.dim)) * np.geomspace(3.0, 0.03, space.dim)  # ill-conditioned, as the chain's
    e = rng.normal(size=30)
    u = np.zeros(space.dim)
    reg = secant.GN_REG
    lam = reg * np.mean(np.sum(F * F, axis=0))
    evals, evecs = np.linalg.eigh(F.T @ F)
    g = evecs.T @ (F.T @ e)

    def step(mu):
        return -evecs @ (g / (evals + lam + mu))

    full = step(0.0)
    assert np.abs(full).max() < space.bound  # the box is not what binds below
    for ball in (0.05, 0.3, 0.8 * np.linalg.norm(full)):
        mu = brentq(lambda m, r=ball: np.linalg.norm(step(m)) - r, 0.0, 1e12)
        du = secant.ball_step(F, e, u, space, ball, reg)
        assert np.isclose(np.linalg.norm(du), ball, rtol=1e-8)
        assert np.allclose(du, step(mu), atol=1e-7 * ball)
    inside = secant.ball_step(F, e, u, space, 2.0 * np.linalg.norm(full), reg)
    assert np.array_equal(inside, secant.qp_step(F, e, u, space, 2.0 * np.linalg.norm(full), reg))
    # the box active: from a command near its upper bound the ball reaches past it
    near = space.upper - 0.05
    du = secant.ball_step(F, 10 * e, near, space, 1.0, reg)
    assert np.all(near + du <= space.upper + 1e-12) and np.linalg.norm(du) <= 1.0 + 1e-9

    def cost(d):
        return np.sum((F @ d + 10 * e) ** 2) + lam * np.sum(d * d)

    tries = rng.normal(size=(2000, space.dim))
    tries *= rng.uniform(0, 1, (2000, 1)) / np.linalg.norm(tries, axis=1, keepdims=True)
    tries = tries[np.all(near + tries <= space.upper, axis=1)]
    assert len(tries) > 100 and cost(du) <= min(cost(d) for d in tries) + 1e-9
    # the step's length in trust-radius units, as the trust region reads it
    d = np.array([0.3, -0.4] + [0.0] * (space.dim - 2))
    assert secant.step_length(d, "box") == 0.4
    assert np.isclose(secant.step_length(d, "ball"), 0.5 / secant.BALL_PER_RADIUS)


def test_gn_step_row_weights_scale_the_least_squares_rows():
    """A velocity weight of 0 is the step on the other rows alone (the velocity rows deleted from the problem), and
    a weight w the step on those rows scaled by w; the weights touch the velocity block only."""
    space = CommandSpace(PATHS["flick"])
    goal = crit.Target.from_reference(load_reference(builtin_reference_path("flick_fast", "default")))
    rng = np.random.default_rng(3)
    w = secant.residual_weights(goal)
    S = rng.normal(size=(goal.dim, space.dim)) / w[:, None]  # every weighted row of one size
    vel = goal.blocks["velocity"]
    # the velocity rows ask for one step, the others for another
    du_vel, du_other = rng.uniform(-0.3, 0.3, space.dim), rng.uniform(-0.3, 0.3, space.dim)
    e = -(w[:, None] * S) @ du_other
    e[vel] = -((w[:, None] * S) @ du_vel)[vel]
    rows = secant.step_row_weights(goal, 0.0)
    assert np.all(rows[vel] == 0.0) and np.sum(rows == 1.0) == goal.dim - (vel.stop - vel.start)
    keep = np.ones(goal.dim, bool)
    keep[vel] = False
    u0 = np.zeros(space.dim)
    without = secant.gn_step(S[keep], w[keep], e[keep], u0, space, 0.7)[0]
    assert np.allclose(secant.gn_step(S, w, e, u0, space, 0.7, rows=rows)[0], without, atol=1e-8)
    half = secant.step_row_weights(goal, 0.5)
    Sw, ew = S.copy(), e.copy()
    Sw[vel] *= 0.5
    ew[vel] *= 0.5
    assert np.allclose(secant.gn_step(S, w, e, u0, space, 0.7, rows=half)[0], secant.gn_step(Sw, w, ew, u0, space,
                                                                                              0.7)[0], atol=1e-8)
    assert np.allclose(without, du_other, atol=0.02)
    assert np.abs(secant.gn_step(S, w, e, u0, space, 0.7)[0] - du_other).max() > 0.1  # weighed fully, they pull apart


def _smoothed_floor(goal, best, S, w, u0, space, groups):
    """An independent solution of the floor's problem: the error's group norms smoothed, sqrt(|r_g|^2 + mu^2),
    minimised by L-BFGS-B inside the box while mu falls from 1e-2 to 1e-8 (continuation; no epigraph, no SLSQP)."""
    from scipy.optimize import minimize

    F, e = w[:, None] * S, goal.residual(best)[0]
    x = np.zeros(len(u0))
    for mu in 10.0 ** -np.arange(2, 9):
        def f(du, mu=mu):
            r = e + F @ du
            size = [np.sqrt(r[g] @ r[g] + mu * mu) for g in groups]
            return sum(size), sum(F[g].T @ r[g] / sz for g, sz in zip(groups, size))
        x = minimize(f, x, jac=True, method="L-BFGS-B", bounds=list(zip(space.lower - u0, space.upper - u0)),
                     options={"maxiter": 5000, "ftol": 1e-15, "gtol": 1e-12}).x
    return float(secant.predicted_errors(goal, best, S, x)[0])


def test_model_floor_is_the_least_error_the_linear_model_predicts_in_the_box():
    """The floor: the error is the sum of the residual's group norms (checked against the observable's kernel); a
    best state that a command 2.5 units away undoes (beyond a 1.0 trust radius) has floor ~0 there; for any best
    state the floor agrees with an independent solution of the same convex problem (smoothed norms, L-BFGS-B with
    continuation) and no trust-region step is predicted better."""
    space = CommandSpace(PATHS["flick"])
    goal = crit.Target.from_reference(load_reference(builtin_reference_path("flick_fast", "default")))
    rng = np.random.default_rng(5)
    w = secant.residual_weights(goal)
    groups = goal.error_groups
    for _ in range(5):
        st = with_offset(goal.state, rng.normal(size=goal.dim) * 0.05 / w)
        r = goal.residual(st)[0]
        assert float(goal.terms(st)["total"][0]) == pytest.approx(sum(np.linalg.norm(r[g]) for g in groups))
    S = rng.normal(size=(goal.dim, space.dim)) * 0.02 / w[:, None]
    u0 = np.zeros(space.dim)
    du_true = rng.uniform(-2.5, 2.5, space.dim)
    best = with_offset(goal.state, -S @ du_true)
    e = goal.residual(best)[0]
    floor = secant.model_floor(goal, best, S, w, e, u0, space)
    rec = secant.floor_record(goal, best, S, u0, floor)
    assert isinstance(rec["solver_status"], int) and rec["solver_message"]  # recorded however SLSQP ended
    stepped = secant.model_floor(goal, best, S, w, e, u0, space, also=(du_true,))  # the exact answer, given as a step
    assert stepped.found_by in ("step", "search", "least squares")
    assert secant.predicted_errors(goal, best, S, stepped.u)[0] <= secant.predicted_errors(goal, best, S, du_true)[0]
    assert rec["error"] < 1e-4 and rec["distance"] == pytest.approx(np.abs(du_true).max(), abs=0.01)
    assert set(rec["terms"]) == {"shape", "velocity", "time", "place"}
    assert secant.predicted_errors(goal, best, S, secant.gn_step(S, w, e, u0, space, 1.0)[0])[0] > 0.05
    for _ in range(4):
        # a sensitivity of falling singular values, as the chain's, and a best state it cannot undo
        U, sv, Vt = np.linalg.svd(rng.normal(size=(goal.dim, space.dim)) * 0.02 / w[:, None], full_matrices=False)
        S = (U * sv * np.exp(-0.5 * np.arange(space.dim))) @ Vt
        best = with_offset(goal.state, rng.normal(size=goal.dim) * 0.03 / w)
        e = goal.residual(best)[0]
        rows = secant.step_row_weights(goal, 0.5)
        found = secant.model_floor(goal, best, S, w, e, u0, space, rows)
        assert (found.found_by, found.solver_status) == ("search", 0), found
        floor = secant.predicted_errors(goal, best, S, found.u)[0]
        assert floor == pytest.approx(_smoothed_floor(goal, best, S, w, u0, space, groups), rel=1e-4)
        steps = [secant.gn_step(S, w, e, u0, space, radius, rows=rows)[0] for radius in (0.25, 1.0, 3.0)]
        assert floor <= secant.predicted_errors(goal, best, S, np.stack(steps)).min() + 1e-9


# ------------------------------------------------------------------------------ correction
FAST_PLAN = {"popsize": 16, "generations": 15}


def test_batched_commands_match_hand_paths():
    space = CommandSpace(PATHS["flick"])
    U = np.random.default_rng(3).normal(size=(40, space.dim))
    times = np.linspace(-0.1, 1.6, 250)
    H = space.batch_positions(U, times)
    vs, acc = space.batch_peaks(U)
    for i, u in enumerate(U):
        path = space.decode(u)
        assert np.allclose(H[i], path.positions(times), atol=1e-12)
        assert np.isclose(vs[i], path.max_speed(), rtol=1e-12) and np.isclose(acc[i], path.max_acceleration(),
                                                                               rtol=1e-12)
        assert (space.limit_excess(u[None])[0] == 0.0) == space.feasible(np.clip(u, -space.bound, space.bound)) \
            or np.abs(u).max() > space.bound


def test_offset_broyden_reproduces_the_trials():
    rng = np.random.default_rng(2)
    off = Offset.zero(5, 7, centre=rng.normal(size=5))
    off.d = rng.normal(size=7)
    u1, d1 = rng.normal(size=5), rng.normal(size=7)
    off.broyden(u1, d1)
    assert np.allclose(off(u1)[0], d1) and np.allclose(off(off.centre)[0], off.d)
    off.recentre(u1, d1)
    u2, d2 = rng.normal(size=5), rng.normal(size=7)
    off.broyden(u2, d2)
    assert np.allclose(off(u2)[0], d2) and np.allclose(off(u1)[0], d1)


@pytest.mark.parametrize("freeze", [False, True])
def test_offset_prediction_is_exact_at_the_trials(problem, freeze):
    """Model + offset must reproduce the real error at the centre trial and (Broyden) at a second
    trial, whatever the model's own error there; with the place frozen as well."""
    space = CommandSpace(PATHS["flick"])
    real = CoarseRope(problem, shifted(problem))
    model = CoarseModel(problem, problem.space.measured, space)
    goal = crit.Target.from_reference(real(PATHS["flick_fast"]))
    U = np.stack([np.zeros(space.dim), 0.3 * np.ones(space.dim)])
    Zr = [crit.from_reference(real(space.decode(u))) for u in U]
    Zm = model.states(U)
    d = state_vector(Zr[0])[0] - state_vector(Zm)[0]
    off = Offset.zero(space.dim, goal.dim)
    off.recentre(U[0], d)
    if freeze:
        off.model_place = Zm.s[0].copy()
    d1 = state_vector(Zr[1])[0] - state_vector(Zm)[1]
    if freeze:
        d1[-2:] = Zr[1].s[0] - off.model_place
    off.broyden(U[1], d1)
    _, pred, alone = predicted_cost(model, goal, U, off, U[0], 0.0)
    real_err = [goal.terms(z)["total"][0] for z in Zr]
    assert np.allclose(pred, real_err, atol=1e-9)
    assert abs(alone[0] - real_err[0]) > 0.05  # the model alone is off: the offset did the work


def test_plan_on_the_model_alone_reaches_a_reachable_goal(problem):
    """With the model as the system (zero offset), the batched plan must find a command whose
    critical state is within the tolerance of a goal the model can reach."""
    space = CommandSpace(PATHS["flick"])
    model = CoarseModel(problem, problem.space.measured, space)
    goal = crit.Target.from_reference(CoarseRope(problem, problem.space.measured)(PATHS["flick_fast"]))
    start = goal.terms(model.states(np.zeros((1, space.dim))))["total"][0]
    p = plan(model, goal, np.zeros(space.dim), 2 * space.bound, Offset.zero(space.dim, goal.dim), seed=0,
             popsize=16, generations=30)
    # 2400 chains in 13 dimensions of a rough event map: measured 0.055 (0.01 with 9600 chains)
    assert start > 0.3 and p["predicted_total"] < 0.08
    assert np.isclose(goal.terms(model.states(p["u"][None]))["total"][0], p["predicted_total"])
    assert space.feasible(p["u"])


def test_first_plan_weight_picks_a_command_nearer_the_start(problem):
    """The chain reproduces the goal about as well along a long stretch of commands; weighing the distance from the
    start in trial 1's plan picks one nearer it, at a chain error that grows by no more than the weight's own cost
    (the plan minimises error + reg |u|^2, so error(reg) <= error(0) + reg |u(0)|^2, up to the search's slack)."""
    from wrenorm.tasks.rope.control.correct import _first_plan

    space = CommandSpace(PATHS["flick"])
    model = CoarseModel(problem, shifted(problem), space)
    goal = crit.Target.from_reference(CoarseRope(problem, problem.space.measured)(PATHS["flick_fast"]))
    opts = {"popsize": 16, "generations": 20, "reg": 1e-4}
    plans = {reg: _first_plan(model, goal, np.zeros(space.dim), 0, opts, None, reg) for reg in (None, 0.01)}
    (_, u0, _, rec0, _), (_, u1, _, rec1, _) = plans[None], plans[0.01]
    assert rec0["reg"] == 1e-4 and rec1["reg"] == 0.01  # as-plans: the plans' own weight
    assert np.isclose(rec1["distance_from_start"], np.linalg.norm(u1)) and space.feasible(u1)
    assert np.linalg.norm(u1) < 0.8 * np.linalg.norm(u0), (np.linalg.norm(u0), np.linalg.norm(u1))
    slack = 0.05  # the search's own: two CMA-ES runs of 1600 chains on a rough event map
    assert rec1["model_total_at_plan"] <= rec0["model_total_at_plan"] + 0.01 * np.sum(u0 ** 2) + slack
    # left out, the plan loop weighs trial 1 as its other plans (its --reg), Gauss-Newton loops by FIRST_PLAN_REG
    real = CoarseRope(problem, problem.space.measured)
    for method, reg, weight in (("plan", 0.02, 0.02), ("gn", None, secant.FIRST_PLAN_REG)):
        res = correct(real, model, goal, np.zeros(space.dim), max_trials=1, method=method, reg=reg, **FAST_PLAN)
        assert res["trial0_plan"]["reg"] == weight, method
    with pytest.raises(InputError, match="first_plan_reg"):
        correct(real, model, goal, np.zeros(space.dim), first_plan_reg=True)  # a bool is no weight


@pytest.mark.parametrize("method", ["gn", "plan", "renormalise"])
def test_first_plan_on_the_chain_plus_the_start_throws_offset(problem, method):
    """--first-plan-offset: the real rope's critical state under the start command, recorded before the trials, makes
    the chain plus a constant offset reproduce it exactly there (output space mapping; the contact place frozen as the
    trials' offsets freeze it); trial 1 is planned on that, in every loop that plans one, and its recorded prediction
    is the shifted chain's. A recording that missed gives no offset and the plain plan; a loop that plans no trial 1
    refuses it."""
    from wrenorm.tasks.rope.control.plan import predicted_states, start_offset

    space = CommandSpace(PATHS["flick"])
    real = CoarseRope(problem, shifted(problem))
    goal = crit.Target.from_reference(real(PATHS["flick_fast"]))
    start = crit.from_reference(real(PATHS["flick"]))
    model = CoarseModel(problem, problem.space.measured, space)
    u_start = np.zeros(space.dim)
    off, chain_there = start_offset(model, u_start, start)
    there, alone = predicted_states(model, u_start[None], off)
    assert np.allclose(chain_there.pos, alone.pos)
    for key in ("pos", "vel", "time", "s"):
        assert np.allclose(getattr(there, key), getattr(start, key), atol=1e-9), key
    assert not np.allclose(alone.pos, start.pos, atol=1e-3)  # the chain alone misses it: the offset does the work
    # near the start the shifted chain is off by the difference of the two sensitivities times the distance, the
    # chain alone by the whole miss: 0.05 units of u away the shifted chain predicts the rope's critical state several
    # times closer (in the observable's weights, the contact place aside: the prediction freezes it), in every
    # direction tried
    w = secant.residual_weights(goal)[:-2]
    for direction in np.random.default_rng(0).normal(size=(3, space.dim)):
        u_near = 0.05 * direction / np.abs(direction).max()
        z_real = state_vector(crit.from_reference(real(space.decode(u_near))))[0][:-2]
        z_shifted, z_alone = (state_vector(z)[0][:-2] for z in predicted_states(model, u_near[None], off))
        miss_shifted, miss_alone = np.linalg.norm(w * (z_shifted - z_real)), np.linalg.norm(w * (z_alone - z_real))
        assert miss_shifted < 0.35 * miss_alone, (miss_shifted, miss_alone)

    kw = dict(max_trials=1, tolerance=1e-6, method=method, **FAST_PLAN)
    plain = correct(real, model, goal, u_start, **kw)
    shifted_plan = correct(real, model, goal, u_start, first_plan_offset=(u_start, start), **kw)
    rec = shifted_plan["trial0_plan"]["offset"]
    miss = crit.Target(start, goal.length, goal.speed, dict(goal.weights)).terms(model.states(u_start[None]))
    assert "offset" not in plain["trial0_plan"] and np.isclose(rec["chain_error_to_rope_there"], miss["total"][0])
    t1 = shifted_plan["trials"][0]
    assert np.isclose(t1.predicted_total, rec["predicted_total_at_plan"])
    assert np.isclose(goal.terms(t1.predicted_state)["total"][0], rec["predicted_total_at_plan"])
    pred = predicted_states(model, t1.u[None], off)[0]
    assert np.allclose(t1.predicted_state.pos, pred.pos) and not np.allclose(t1.u, plain["trials"][0].u)
    assert space.feasible(t1.u)

    nan = np.full_like(start.pos, np.nan)
    missed = crit.CriticalStates(nan, nan.copy(), np.full(1, np.nan), np.full((1, 2), np.nan), np.zeros(1, bool),
                                 np.array([0.02]))
    assert start_offset(model, u_start, missed)[0] is None
    none = correct(real, model, goal, u_start, first_plan_offset=(u_start, missed), **kw)
    assert none["trial0_plan"]["offset"] is None and np.array_equal(none["trials"][0].u, plain["trials"][0].u)
    if method != "gn":
        return
    for bad in ({"method": "qp"}, {"plan_first": False}, {"first_plan_offset": True},
                {"first_plan_offset": (np.zeros(3), start)}, {"first_plan_offset": (u_start, None)}):
        with pytest.raises(InputError, match="first_plan_offset"):
            correct(real, model, goal, u_start, **({"first_plan_offset": (u_start, start)} | kw | bad))


@pytest.mark.parametrize("method,plan_first", [("plan", True), ("plan", False), ("gn", True)])
def test_correction_converges_on_a_system_with_known_answer(problem, method, plan_first):
    """The coarse chain with shifted parameters is the 'real' rope; the goal is its own critical
    state under another throw, so the goal is reachable and the loop must get there."""
    space = CommandSpace(PATHS["flick"])
    truth = shifted(problem)
    real = CoarseRope(problem, truth)
    goal = crit.Target.from_reference(real(PATHS["flick_fast"]))
    start = goal.terms(crit.from_reference(real(PATHS["flick"])))["total"][0]
    assert start > 0.3  # the start is far from the goal
    exact = correct(real, CoarseModel(problem, truth, space), goal, np.zeros(space.dim), max_trials=8,
                    plan_first=plan_first, method=method, **FAST_PLAN)
    assert exact["success"] and exact["trials_to_tolerance"] <= 3
    wrong = correct(real, CoarseModel(problem, problem.space.measured, space), goal, np.zeros(space.dim),
                    max_trials=10, plan_first=plan_first, method=method, **FAST_PLAN)
    assert wrong["success"]
    # the model with the system's own parameters needs no more trials than the mismatched one
    assert exact["trials_to_tolerance"] <= wrong["trials_to_tolerance"]
    accepted = [t.total for t in wrong["trials"] if t.accepted]
    assert all(b < a for a, b in zip(accepted, accepted[1:]))
    for t in wrong["trials"]:
        assert space.feasible(t.u)
    if not plan_first:
        assert np.all(wrong["trials"][0].u == 0.0)
    else:  # by method: the plan loop weighs trial 1 as its other plans, Gauss-Newton steps nearer the start
        assert wrong["trial0_plan"]["reg"] == (secant.FIRST_PLAN_REG if method == "gn" else FAST_PLAN.get("reg", 1e-4))


def test_residual_weights_make_the_observables_residual_linear_in_the_state(problem):
    """secant.residual_weights: goal.residual(Z_goal + dz) = w * dz for any dz, block by block (the GN step
    and the predicted state rely on it)."""
    goal = crit.Target.from_reference(problem.train[0].data.ref)
    w = secant.residual_weights(goal)
    dz = np.random.default_rng(4).normal(scale=0.05, size=(3, goal.dim))
    st = goal.state.take(np.zeros(3, dtype=int))
    assert np.allclose(goal.residual(with_offset(st, dz)), w[None] * dz, rtol=1e-4, atol=1e-7)
    b = goal.blocks
    # shape = RMS distance over the K points / length: each coordinate weighs 1 / (length sqrt(K))
    assert np.allclose(w[b["position"]], 1.0 / (goal.length * np.sqrt(crit.SAMPLES)), rtol=1e-5)
    assert np.all(w > 0)


def test_velocity_projection_is_a_polynomial_fit_of_the_velocity_profile_and_keeps_the_rest(problem):
    """secant.velocity_projection keeps, of the velocity rows, each axis's least-squares polynomial of degree modes - 1
    in arc length (checked against numpy's polyfit, an independent fit) and every other row as it is; every mode
    (SAMPLES) keeps everything."""
    goal = crit.Target.from_reference(problem.train[0].data.ref)
    b = goal.blocks
    assert secant.velocity_projection(goal, SAMPLES) is None
    s = np.linspace(0.0, 1.0, SAMPLES)
    r = np.random.default_rng(7).normal(size=goal.dim)
    for modes in (1, 3, 6):
        Q = secant.velocity_projection(goal, modes)
        assert np.allclose(Q @ Q, Q) and np.allclose(Q, Q.T)
        kept = Q @ r
        rest = np.r_[b["position"], b["time"], b["place"]]
        assert np.array_equal(kept[rest], r[rest])
        v, fit = r[b["velocity"]].reshape(SAMPLES, 3), kept[b["velocity"]].reshape(SAMPLES, 3)
        for axis in range(3):
            expected = np.polyval(np.polyfit(s, v[:, axis], modes - 1), s)
            assert np.allclose(fit[:, axis], expected, atol=1e-10)
    # a profile of degree 2 is kept whole by 3 modes; what lies off every quadratic is dropped whole
    smooth = np.zeros(goal.dim)
    smooth[b["velocity"]] = np.stack([1 + s, s**2, 2 - s + 3 * s**2], axis=1).ravel()
    Q = secant.velocity_projection(goal, 3)
    assert np.allclose(Q @ smooth, smooth)
    rough = np.zeros(goal.dim)
    rough[b["velocity"]] = (np.eye(SAMPLES * 3)[5] - Q[b["velocity"], b["velocity"]] @ np.eye(SAMPLES * 3)[5])
    assert np.allclose(Q @ rough, 0.0, atol=1e-12)


def test_secant_corrections_reproduce_the_trials():
    """Ridge over the secant pairs: with one pair and a vanishing prior weight it is Broyden's update (the pair
    reproduced exactly, directions orthogonal to it left at the prior); with several, a vanishing weight reproduces
    every pair (within their span), a heavy one keeps the prior; refitting counts the pairs afresh."""
    rng = np.random.default_rng(5)
    prior = rng.normal(size=(9, 4))
    sens = secant.Sensitivity(prior.copy(), prior.copy(), ["central"] * 4)
    du, dz = rng.normal(size=4), rng.normal(size=9)
    sens.ridge([du], [dz], weight=1e-9)
    assert np.allclose(sens.S @ du, dz, atol=1e-6) and sens.pairs == 1
    ortho = np.linalg.svd(du[None])[2][1:]
    assert np.allclose(sens.S @ ortho.T, prior @ ortho.T)
    broyden = prior + np.outer(dz - prior @ du, du) / (du @ du)
    assert np.allclose(sens.S, broyden, atol=1e-6)
    sens.ridge([du, 2 * du], [dz, 2 * dz])
    assert sens.pairs == 2
    dus, dzs = [rng.normal(size=4) for _ in range(3)], [rng.normal(size=9) for _ in range(3)]
    tight = secant.Sensitivity(prior.copy(), prior.copy(), ["central"] * 4)
    tight.ridge(dus, dzs, weight=1e-9)
    assert all(np.allclose(tight.S @ a, b, atol=1e-6) for a, b in zip(dus, dzs))
    loose = secant.Sensitivity(prior.copy(), prior.copy(), ["central"] * 4)
    loose.ridge(dus, dzs, weight=1e9)
    assert np.allclose(loose.S, prior, atol=1e-6)


def test_secant_locality_weighs_far_pairs_down_as_weighted_least_squares():
    """--secant-locality: each pair's weight is 1 within L of the best command (largest component) and (L / d)^2
    beyond; the ridge fit with those weights equals the weighted least-squares problem stacked row by row and solved
    by lstsq (an independent formulation); without a locality every pair weighs 1, as before. Two pairs along one
    direction that disagree: the near one's slope wins with the locality, the mean of both without it."""
    assert secant.pair_weight(np.array([0.3, -1.0]), 1.0) == 1.0
    assert secant.pair_weight(np.array([0.3, -2.0]), 1.0) == pytest.approx(0.25)
    assert secant.pair_weight(np.array([9.0, 0.0]), None) == 1.0
    rng = np.random.default_rng(7)
    m, n, ridge = 6, 3, 0.05
    prior = rng.normal(size=(m, n))
    dus = [rng.normal(scale=s, size=n) for s in (0.3, 1.0, 2.5, 4.0)]
    dzs = [rng.normal(size=m) for _ in dus]
    sens = secant.Sensitivity(prior.copy(), prior.copy(), ["central"] * n)
    sens.ridge(dus, dzs, weight=ridge, locality=1.0)
    c = [min(1.0, 1.0 / np.abs(du).max() ** 2) for du in dus]
    assert sens.pair_weights == pytest.approx(c) and min(c) < 0.2 < max(c) == 1.0
    # row i of S: min sum_k c_k (dz_ki - S_i du_k)^2 / |du_k|^2 + ridge |S_i - prior_i|^2
    A = np.vstack([np.sqrt(ck) * du / np.linalg.norm(du) for ck, du in zip(c, dus)] + [np.sqrt(ridge) * np.eye(n)])
    for i in range(m):
        b = np.concatenate([[np.sqrt(ck) * dz[i] / np.linalg.norm(du) for ck, du, dz in zip(c, dus, dzs)],
                            np.sqrt(ridge) * prior[i]])
        assert np.allclose(sens.S[i], np.linalg.lstsq(A, b, rcond=None)[0], atol=1e-10)
    alike = secant.Sensitivity(prior.copy(), prior.copy(), ["central"] * n)
    alike.ridge(dus, dzs, weight=ridge)
    assert alike.pair_weights == [1.0] * 4 and not np.allclose(alike.S, sens.S)
    e = np.eye(n)[0]
    near, far = (0.5 * e, 0.5 * np.ones(m)), (4.0 * e, 4.0 * 3.0 * np.ones(m))  # slopes 1 and 3 along e
    local = secant.Sensitivity(np.zeros((m, n)), np.zeros((m, n)), ["central"] * n)
    local.ridge([near[0], far[0]], [near[1], far[1]], weight=1e-9, locality=1.0)
    mean = secant.Sensitivity(np.zeros((m, n)), np.zeros((m, n)), ["central"] * n)
    mean.ridge([near[0], far[0]], [near[1], far[1]], weight=1e-9)
    assert np.allclose(mean.S @ e, 2.0) and np.allclose(local.S @ e, (1 + 3 / 16) / (1 + 1 / 16))


def test_matched_command_is_where_the_chain_reproduces_a_state(problem):
    """Space mapping's extraction: given a state the chain makes under some command, started elsewhere, the match
    finds a command that reproduces it far better than the start does; given the chain's own state at the start,
    nothing beats the start and it is returned unchanged."""
    space = CommandSpace(PATHS["flick"])
    model = CoarseModel(problem, problem.space.measured, space)
    goal = crit.Target.from_reference(CoarseRope(problem, problem.space.measured)(PATHS["flick_fast"]))
    w = secant.residual_weights(goal)
    u_star = space.encode(PATHS["flick_fast"])
    z_star = state_vector(model.states(u_star[None]))[0]
    u_trial = u_star + np.where(np.arange(space.dim) < 6, 0.5, 0.0)
    assert space.feasible(u_star) and space.feasible(u_trial) and np.all(np.isfinite(z_star))
    m = secant.matched_command(model, z_star, w, u_trial, seed=1, reg=1e-6)
    assert m.misfit_at_trial > 0.05 and m.misfit < 0.3 * m.misfit_at_trial
    assert np.isclose(np.linalg.norm(w * (state_vector(model.states(m.u[None]))[0] - z_star)), m.misfit)
    assert np.all(m.u >= space.lower) and np.all(m.u <= space.upper)
    own = secant.matched_command(model, state_vector(model.states(u_trial[None]))[0], w, u_trial, seed=1)
    assert own.misfit_at_trial == 0.0 and np.array_equal(own.u, u_trial)
    rec = m.record()
    assert rec["misfit_at_match"] == m.misfit and rec["distance_from_trial"] > 0


def test_gn_correction_records_what_each_step_learned(problem):
    """The GN loop's records: each trial's prediction is the linear model's (the best trial's state moved by
    S du), the sensitivity is measured once (one chain rollout) and corrected by every later trial that hit."""
    space = CommandSpace(PATHS["flick"])
    real = CoarseRope(problem, shifted(problem))
    goal = crit.Target.from_reference(real(PATHS["flick_fast"]))
    res = correct(real, CoarseModel(problem, problem.space.measured, space), goal, np.zeros(space.dim),
                  max_trials=4, tolerance=1e-6, method="gn", **FAST_PLAN)
    tr = res["trials"]
    assert res["method"] == "gn" and len(tr) == 4
    assert res["trial0_plan"]["reg"] == secant.FIRST_PLAN_REG  # by method: Gauss-Newton steps follow
    assert all(t.trust is not None for t in tr[1:])
    # every step records the corrected model's floor: its error is its terms' weighted sum, and no higher than the
    # prediction of the step that was taken from the same model
    floors = [t.sensitivity["model_floor"] for t in tr[:-1] if t.hit]
    assert len(floors) == sum(t.hit for t in tr[:-1]) and all(
        f["error"] == pytest.approx(sum(crit.WEIGHTS[k] * v for k, v in f["terms"].items())) for f in floors)
    assert all(t.sensitivity["model_floor"]["error"] <= tr[k + 1].predicted_total + 1e-9
               for k, t in enumerate(tr[:-1]) if t.hit)
    pairs = [t.sensitivity["secant_pairs"] for t in tr[:-1]]
    assert pairs == sorted(pairs) and pairs[-1] == sum(t.hit for t in tr[1:-1])
    assert len({t.sensitivity["chain_rollouts"] for t in tr[:-1]}) == 1  # measured once
    assert res["best_error"] < tr[0].total
    # measured where the chain matches the first hit's real state, which it does at least as well as at the trial
    where = {tuple(t.sensitivity["linearised_at"]) for t in tr[:-1]}
    assert len(where) == 1 and all(t.sensitivity["misfit_at_match"] <= t.sensitivity["misfit_at_trial"]
                                   for t in tr[:-1])
    at_trial = correct(real, CoarseModel(problem, problem.space.measured, space), goal, np.zeros(space.dim),
                       max_trials=2, tolerance=1e-6, method="gn", linearise_at="trial", **FAST_PLAN)
    assert "linearised_at" not in at_trial["trials"][0].sensitivity
    # the options the plan loop takes mean the same here: the start command as trial 1, no secant corrections
    plain = correct(real, CoarseModel(problem, problem.space.measured, space), goal, np.zeros(space.dim),
                    max_trials=3, tolerance=1e-6, method="gn", plan_first=False, secant=False, **FAST_PLAN)
    assert np.all(plain["trials"][0].u == 0.0) and plain["trial0_plan"] is None and not plain["secant"]
    assert all(t.sensitivity["secant_pairs"] == 0 and t.sensitivity["relative_correction"] == 0.0
               for t in plain["trials"][:-1] if t.hit)
    # fixed parameters step a fixed radius by default; the adaptive region moves between its bounds
    assert res["gauss_newton"]["trust_region"]["rule"] == "fixed"
    assert all(t.trust["verdict"] == "fixed" and t.trust["radius_after"] == secant.GN_RADIUS for t in tr[1:])
    assert all(np.abs(tr[k].u - min(tr[:k], key=lambda t: t.total).u).max() <= secant.GN_RADIUS + 1e-9
               for k in range(1, len(tr)))
    adaptive = correct(real, CoarseModel(problem, problem.space.measured, space), goal, np.zeros(space.dim),
                       max_trials=4, tolerance=1e-6, method="gn", trust_region="adaptive", min_radius=0.5,
                       max_radius=1.5, **FAST_PLAN)
    region = adaptive["gauss_newton"]["trust_region"]
    assert region["rule"] == "adaptive" and (region["min_radius"], region["max_radius"]) == (0.5, 1.5)
    assert all(t.trust["verdict"] in ("grow", "keep", "shrink") and 0.5 <= t.trust["radius_after"] <= 1.5
               for t in adaptive["trials"][1:])
    assert [t.trust["rho"] for t in tr[1:2]] == [t.trust["rho"] for t in adaptive["trials"][1:2]]  # same trial 2
    # fixed parameters weigh the steps' velocity rows secant.VELOCITY_WEIGHT by default; a given weight is used
    assert res["gauss_newton"]["velocity_weight"] == secant.VELOCITY_WEIGHT == 0.5
    alike = correct(real, CoarseModel(problem, problem.space.measured, space), goal, np.zeros(space.dim),
                    max_trials=2, tolerance=1e-6, method="gn", velocity_weight=1.0, **FAST_PLAN)
    assert alike["gauss_newton"]["velocity_weight"] == 1.0
    assert np.array_equal(alike["trials"][0].u, tr[0].u)  # trial 1 is the chain's plan, no step
    assert not np.allclose(alike["trials"][1].u, tr[1].u)  # trial 2 is the first step, and the weight moves it
    # fixed parameters keep every velocity row in their steps by default; fewer modes move the first step
    assert res["gauss_newton"]["velocity_modes"] == SAMPLES
    smooth = correct(real, CoarseModel(problem, problem.space.measured, space), goal, np.zeros(space.dim),
                     max_trials=2, tolerance=1e-6, method="gn", velocity_modes=3, **FAST_PLAN)
    assert smooth["gauss_newton"]["velocity_modes"] == 3 and np.array_equal(smooth["trials"][0].u, tr[0].u)
    assert not np.allclose(smooth["trials"][1].u, tr[1].u)


def test_space_mapping_first_step_moves_by_the_match_the_other_way(problem):
    """Space mapping's step: on a rope that is the chain under a shifted command, trial 2 is trial 1's command moved by
    the match's offset the other way (inside the box and the hand limits), and it improves on trial 1; the renormalised
    loop, whose refitted chain reproduces trial 1 at its own command, keeps the Gauss-Newton step."""
    space = CommandSpace(PATHS["flick"])
    chain = CoarseRope(problem, problem.space.measured)
    delta = np.where(np.arange(space.dim) % 3 == 0, 0.4, 0.0)

    class ShiftedCommand:
        runs, wall_s = 0, 0.0

        def __call__(self, path):
            return chain(space.decode(space.encode(path) + delta))

    goal = crit.Target.from_reference(chain(PATHS["flick_fast"]))
    model = CoarseModel(problem, problem.space.measured, space)
    res = correct(ShiftedCommand(), model, goal, np.zeros(space.dim), max_trials=2, tolerance=1e-6, method="gn",
                  first_step="space-mapping", **FAST_PLAN)
    t1, t2 = res["trials"]
    match = np.array(t1.sensitivity["linearised_at"])
    assert res["first_step"] == t1.sensitivity["step"] == "space mapping"
    np.testing.assert_allclose(t2.u, space.limit_step(t1.u, t1.u - match)[0])
    assert np.abs(match - t1.u).max() > 0.1 and t2.total < 0.7 * t1.total
    gn = correct(ShiftedCommand(), model, goal, np.zeros(space.dim), max_trials=2, tolerance=1e-6, method="gn",
                 **FAST_PLAN)
    assert gn["first_step"] == gn["trials"][0].sensitivity["step"] == "gauss-newton"
    assert np.array_equal(gn["trials"][0].u, t1.u) and not np.allclose(gn["trials"][1].u, t2.u)
    renorm = correct(ShiftedCommand(), model, goal, np.zeros(space.dim), max_trials=2, tolerance=1e-6,
                     method="renormalise", first_step="space-mapping", refit_generations=2, **FAST_PLAN)
    assert renorm["first_step"] == renorm["trials"][0].sensitivity["step"] == "gauss-newton"


def test_qp_correction_still_improves(problem):
    space = CommandSpace(PATHS["flick"])
    real = CoarseRope(problem, shifted(problem))
    goal = crit.Target.from_reference(real(PATHS["flick_fast"]))
    res = correct(real, CoarseModel(problem, problem.space.measured, space), goal, np.zeros(space.dim),
                  max_trials=4, method="qp")
    assert res["best_error"] < 0.5 * res["trials"][0].total


# ------------------------------------------------------------------------------ sensitivity
def test_batched_sensitivity_matches_separate_runs(problem):
    space = CommandSpace(PATHS["flick"])
    goal = crit.Target.from_reference(problem.train[0].data.ref)
    model = CoarseModel(problem, problem.space.measured, space)
    h = 0.05
    F, info = model.sensitivity(np.zeros(space.dim), goal, h)
    assert info["rollouts"] == 2 * space.dim + 1 and info["centre_hit"]
    # one column from two separate single-chain rollouts: a chain's result must not depend on its batch
    i = space.names.index("p1.z")
    e = [goal.residual(model.states(s * h * np.eye(space.dim)[i][None]))[0] for s in (1, -1)]
    assert np.allclose((e[0] - e[1]) / (2 * h), F[:, i], rtol=1e-5, atol=1e-7)
    # a random direction: the columns must combine into the directional difference. Positions and
    # the collision time are smooth in the command; the frame-interval velocity and the contact's
    # arc-length (closest segment pair) jump at this scale, so only the smooth blocks are held to it.
    rng = np.random.default_rng(0)
    smooth = np.r_[goal.blocks["position"], goal.blocks["time"]]
    for _ in range(3):
        v = rng.normal(size=space.dim)
        v /= np.linalg.norm(v)
        ep, em = (goal.residual(model.states(s * h * v[None]))[0] for s in (1, -1))
        d = ((ep - em) / (2 * h))[smooth]
        assert np.linalg.norm((F @ v)[smooth] - d) < 0.1 * np.linalg.norm(d)


def test_dead_command_direction_gives_zero_singular_values(problem):
    """A hand motion after the rope has hit itself cannot change the critical state."""
    base = PATHS["flick"]
    times = np.concatenate([[0.0], np.cumsum(base.durations)])
    from wrenorm.tasks.rope.control.command import waypoints

    _, p, v = waypoints(base)
    late = HandPath.through(np.append(times, [1.2, 1.45]), np.vstack([p, p[-1], p[-1] + [0.1, 0.0, 0.1]]),
                            np.vstack([v, np.zeros((2, 3))]))
    space = CommandSpace(late)
    goal = crit.Target.from_reference(problem.train[0].data.ref)
    model = CoarseModel(problem, problem.space.measured, space)
    F, info = model.sensitivity(np.zeros(space.dim), goal, 0.1)
    assert info["centre_hit"]
    t_hit = float(model.states(np.zeros((1, space.dim))).time[0])
    assert t_hit < 1.2  # the last motion starts after the collision
    dead = [space.names.index(n) for n in ("p5.x", "p5.z", "log_T5")]
    assert np.abs(F[:, dead]).max() == 0.0
    sv = np.linalg.svd(F, compute_uv=False)
    assert sv[0] > 0.05 and np.all(sv[-3:] <= 1e-9 * sv[0])
    Uf = np.linalg.svd(F, full_matrices=False)[0]
    _, ok = resolvable(sv, Uf, np.eye(F.shape[0]) * 1e-8, step=1.0, snr=3.0)
    assert ok.sum() <= space.dim - 3 and ok[0]


def test_parameters_file_errors(problem, tmp_path):
    bad = tmp_path / "result.json"
    bad.write_text(json.dumps({"task": "rope", "resolution": {"segments": 10}, "parameters": {}}))
    with pytest.raises(InputError, match="bend_stiffness|lead_fraction"):
        parameters_from_file(bad, problem)
    good = {p.name: {"fitted": p.measured * 1.1 if p.measured else 0.0} for p in problem.space.parameters}
    bad.write_text(json.dumps({"runs": [{"task": "rope", "resolution": {"segments": 10}, "parameters": good}]}))
    v = parameters_from_file(bad, problem)
    assert np.isclose(v[problem.space.index("bend_stiffness")], 1.1 * problem.space["bend_stiffness"].measured)
    with pytest.raises(InputError, match="not readable JSON"):
        (tmp_path / "x.json").write_text("{")
        parameters_from_file(tmp_path / "x.json", problem)
    # a resolution that is not an object, a fit at another time step or constraint-pass count, and a parameter the
    # file fitted that the correction's chain holds fixed: each refused, naming the field
    for resolution, field in (("10", "resolution"), ({"segments": 10, "dt": 0.002}, "resolution.dt"),
                              ({"segments": 10, "iterations": 1}, "resolution.iterations")):
        bad.write_text(json.dumps({"task": "rope", "resolution": resolution, "parameters": good}))
        with pytest.raises(InputError, match=field.replace(".", r"\.")):
            parameters_from_file(bad, problem)
    frozen = next(p.name for p in problem.space.parameters if p.frozen)
    bad.write_text(json.dumps({"task": "rope", "resolution": dict(problem.resolution),
                               "parameters": good | {frozen: {"fitted": 0.1, "frozen": False}}}))
    with pytest.raises(InputError, match=f"parameters.{frozen}"):
        parameters_from_file(bad, problem)
    bad.write_text(json.dumps({"task": "rope", "resolution": dict(problem.resolution),
                               "parameters": good | {frozen: {"fitted": 0.1, "frozen": True}}}))
    assert np.isclose(parameters_from_file(bad, problem)[problem.space.index("bend_stiffness")],
                      1.1 * problem.space["bend_stiffness"].measured)


def test_a_fit_of_another_rope_is_refused(problem, tmp_path):
    """A fit rope result of the default rope steered the heavy rope with the default's effective values and no word (a
    probe of stop 47): the file's measured values (the rope's mass, thickness, stiffness) must be this rope's."""
    f = tmp_path / "result.json"
    same = {p.name: {"measured": p.measured, "fitted": p.measured * 1.1 if p.measured else 0.0}
            for p in problem.space.parameters}
    f.write_text(json.dumps({"task": "rope", "resolution": dict(problem.resolution), "parameters": same}))
    assert np.isclose(parameters_from_file(f, problem)[problem.space.index("radius")],
                      1.1 * problem.space["radius"].measured)
    stiffer = same | {"bend_stiffness": {"measured": 3.3 * problem.space["bend_stiffness"].measured,
                                         "fitted": problem.space["bend_stiffness"].measured}}
    f.write_text(json.dumps({"task": "rope", "resolution": dict(problem.resolution), "parameters": stiffer}))
    with pytest.raises(InputError) as e:
        parameters_from_file(f, problem)
    assert e.value.field == "parameters.bend_stiffness.measured" and "another rope" in e.value.problem
    heavier = same | {"mass": {"measured": 2.0 * problem.space["mass"].measured, "frozen": True}}
    f.write_text(json.dumps({"task": "rope", "resolution": dict(problem.resolution), "parameters": heavier}))
    with pytest.raises(InputError, match=r"parameters\.mass\.measured"):
        parameters_from_file(f, problem)


def test_cli_bad_input_exits_2(tmp_path, capsys):
    from wrenorm.cli import main

    assert main(["correct", "rope", "--variant", "rubber", "--out", str(tmp_path / "o")]) == 2
    assert "variant" in capsys.readouterr().err
    for bad, word in ((["--engine", "bullet"], "engine"), (["--prior-scale", "-1"], "prior_scale"),
                      (["--decay", "1.5"], "decay"), (["--params", "measured", "measured"], "repeated"),
                      (["--segments", "2"], "segments"), (["--method", "newton"], "--method"),
                      (["--tolerance", "inf"], "tolerance"), (["--reg", "inf"], "reg"), (["--radius", "inf"], "radius"),
                      (["--perturb", "nan"], "perturb"), (["--perturb", "-1"], "perturb"),
                      (["--fit-generations", "0"], "fit_generations"), (["--fine-segments", "0"], "fine_segments"),
                      (["--engine", "mujoco", "--fine-segments", "0"], "fine_segments")):
        assert main(["correct", "rope", "--out", str(tmp_path / "o")] + bad) == 2
        err = capsys.readouterr().err
        assert word in err and len(err.strip().splitlines()) == 1, err
    assert main(["sensitivity", "rope", "--path", "nope", "--out", str(tmp_path / "s")]) == 2
    assert "--path" in capsys.readouterr().err
    for bad, word in ((["--seed", "-1"], "--seed"), (["--marker-noise", "nan"], "--marker-noise"),
                      (["--time-noise", "inf"], "--time-noise"), (["--snr", "inf"], "--snr"),
                      (["--fd-step", "inf"], "--fd-step"), (["--fit-generations", "0"], "--fit-generations"),
                      (["--segments", "2"], "--segments"), (["--dt", "-0.005"], "--dt"),
                      (["--noise-samples", "1"], "--noise-samples"), (["--real-repeats", "-1"], "--real-repeats")):
        assert main(["sensitivity", "rope", "--out", str(tmp_path / "s")] + bad) == 2
        err = capsys.readouterr().err
        assert word in err and len(err.strip().splitlines()) == 1, err
    with pytest.raises(InputError, match="steps"):  # the loop itself names a step kind it does not have
        correct(None, None, None, np.zeros(13), method="renormalise", steps="newton")
    with pytest.raises(InputError, match="linearise_at"):
        correct(None, None, None, np.zeros(13), linearise_at="goal")
    assert main(["correct", "rope", "--out", str(tmp_path / "o"), "--linearise-at", "goal"]) == 2
    assert "--linearise-at" in capsys.readouterr().err
    with pytest.raises(InputError, match="first_step"):
        correct(None, None, None, np.zeros(13), first_step="newton")
    for needs in ({"method": "qp"}, {"method": "plan"}, {"linearise_at": "trial"}):
        with pytest.raises(InputError, match="space mapping's step needs"):
            correct(None, None, None, np.zeros(13), first_step="space-mapping", **needs)
    assert main(["correct", "rope", "--out", str(tmp_path / "o2"), "--first-step", "newton"]) == 2
    assert "--first-step" in capsys.readouterr().err
    assert main(["correct", "rope", "--out", str(tmp_path / "o3"), "--first-step", "space-mapping", "--method",
                 "plan"]) == 2
    assert "space mapping's step needs" in capsys.readouterr().err and not (tmp_path / "o3").exists()
    assert main(["correct", "rope", "--out", str(tmp_path / "o4"), "--start-pair", "first", "--method", "plan"]) == 2
    assert "--start-pair" in capsys.readouterr().err and not (tmp_path / "o4").exists()
    # newton's built-in throws cannot stand for another engine's rope
    assert main(["correct", "rope", "--out", str(tmp_path / "o4"), "--engine", "mujoco", "--builtin-throws"]) == 2
    assert "builtin_throws" in capsys.readouterr().err and not (tmp_path / "o4").exists()
    assert main(["correct", "rope", "--out", str(tmp_path / "o5"), "--start-pair", "always"]) == 2
    assert "--start-pair" in capsys.readouterr().err
    with pytest.raises(InputError, match="needs --method gn"):
        correct(None, None, None, np.zeros(13), method="plan", recorded=[(np.zeros(13), None)])
    with pytest.raises(InputError, match="recorded_until"):
        correct(None, None, None, np.zeros(13), recorded_until="sometimes")
    for kw, what in (({"method": "qp", "trust_region": "fixed"}, "no trust region"),
                     ({"method": "plan", "min_radius": 0.5}, "no trust region"),
                     ({"trust_region": "fixed", "min_radius": 0.5}, "is fixed at 1"),
                     ({"trust_region": "adaptive", "max_radius": 0.5}, "between the smallest 0.25 and the largest 0.5"),
                     ({"trust_region": "sometimes"}, "'fixed' or 'adaptive'")):
        space = CommandSpace(PATHS["flick"])
        with pytest.raises(InputError, match=what):
            correct(None, SimpleNamespace(space=space), None, np.zeros(space.dim), **kw)
    for kw in ({"method": "plan", "velocity_weight": 0.5}, {"velocity_weight": -1.0},
               {"velocity_weight": float("nan")}, {"velocity_weight": "0.5"}):
        space = CommandSpace(PATHS["flick"])
        with pytest.raises(InputError, match="velocity_weight"):
            correct(None, SimpleNamespace(space=space), None, np.zeros(space.dim), **kw)
    for kw in ({"method": "plan", "velocity_modes": 3}, {"velocity_modes": 0}, {"velocity_modes": 22},
               {"velocity_modes": 3.0}, {"velocity_modes": True}):
        space = CommandSpace(PATHS["flick"])
        with pytest.raises(InputError, match="velocity_modes"):
            correct(None, SimpleNamespace(space=space), None, np.zeros(space.dim), **kw)
    for kw in ({"method": "plan", "secant_locality": 1.0}, {"secant_locality": 0.0}, {"secant": False,
                                                                                     "secant_locality": 1.0},
               {"secant_locality": float("inf")}, {"secant_locality": "1"}):
        space = CommandSpace(PATHS["flick"])
        with pytest.raises(InputError, match="secant_locality"):
            correct(None, SimpleNamespace(space=space), None, np.zeros(space.dim), **kw)
    for kw in ({"method": "qp", "first_plan_reg": 0.01}, {"plan_first": False, "first_plan_reg": 0.01},
               {"first_plan_reg": -1.0}, {"first_plan_reg": float("nan")}, {"first_plan_reg": "0.01"}):
        space = CommandSpace(PATHS["flick"])
        with pytest.raises(InputError, match="first_plan_reg"):
            correct(None, SimpleNamespace(space=space), None, np.zeros(space.dim), **kw)
    for bad, word in ((["--secant-locality", "0"], "neither a finite number > 0 nor none"),
                      (["--first-plan-reg", "-0.1"], "neither a finite number >= 0 nor by-method nor as-plans"),
                      (["--first-plan-reg", "near"], "neither a finite number >= 0 nor by-method nor as-plans"),
                      (["--first-plan-reg", "0.01", "--no-plan-first"], "no run here plans it"),
                      (["--first-plan-reg", "0.01", "--method", "qp", "--params", "measured"], "no run here plans it"),
                      (["--first-plan-offset", "start", "--no-plan-first"], "no run here plans it"),
                      (["--first-plan-offset", "start", "--method", "qp", "--params", "measured"],
                       "no run here plans it"),
                      (["--first-plan-offset", "sometimes"], "invalid choice"),
                      (["--secant-locality", "near"], "neither a finite number > 0 nor none"),
                      (["--secant-locality", "1", "--method", "plan", "--params", "measured"], "--method plan"),
                      (["--secant-locality", "1", "--no-secant"], "--no-secant uses none"),
                      (["--velocity-weight", "-0.5"], "neither a finite number >= 0 nor by-arm"),
                      (["--velocity-weight", "half"], "neither a finite number >= 0 nor by-arm"),
                      (["--velocity-weight", "inf"], "neither a finite number >= 0 nor by-arm"),
                      (["--velocity-weight", "0.5", "--method", "plan", "--params", "measured"], "--method plan"),
                      (["--velocity-modes", "0"], "neither a whole number of modes in 1-21 nor by-arm or all"),
                      (["--velocity-modes", "22"], "neither a whole number of modes in 1-21 nor by-arm or all"),
                      (["--velocity-modes", "2.5"], "neither a whole number of modes in 1-21 nor by-arm or all"),
                      (["--velocity-modes", "3", "--method", "plan", "--params", "measured"], "--method plan"),
                      (["--max-radius", "0.5", "--params", "renormalised"], "largest 0.5"),
                      (["--max-radius", "7"], "(0, 6]"),
                      (["--min-radius", "0.5", "--params", "fitted"], "no run here has one"),
                      # the default arm renormalises: options for fixed parameters alone are refused, not ignored
                      (["--method", "qp"], "acts on fixed parameters, and every run here renormalises"),
                      (["--first-step", "space-mapping"], "acts on fixed parameters, and every run here renormalises"),
                      (["--method", "qp", "--params", "renormalised", "renormalised-from-fitted"],
                       "every run here renormalises"),
                      (["--trust-region", "fixed", "--params", "renormalised", "--min-radius", "0.5"], "no run here"),
                      (["--trust-region", "adaptive", "--method", "plan", "--params", "measured"], "--method plan"),
                      (["--trust-region", "sometimes"], "invalid choice"),
                      # MuJoCo's rod cannot mesh the 25 mm rope at 64 segments: said before any folder or throw
                      (["--engine", "mujoco", "--variant", "thick"], "--fine-segments: fine_segments: 64: MuJoCo's "
                                                                     "rope needs 4 to 39 segments")):
        assert main(["correct", "rope", "--out", str(tmp_path / "o6")] + bad) == 2
        err = capsys.readouterr().err
        assert word in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "o6").exists(), err


CORRECT_QUICK = ["correct", "rope", "--real", "coarse", "--segments", "10", "--fit-generations", "4",
                 "--generations", "8", "--popsize", "16", "--max-trials", "4", "--params", "measured",
                 "--tolerance", "0.001", "--no-record", "--quiet"]


@pytest.mark.parametrize("params", ["measured", "renormalised"])
def test_correct_resume_reads_back_real_trials_and_repeats_the_run(tmp_path, params):
    """An interrupted correction (here: all but its first two real trials lost) resumes with its saved
    settings, reads the two trials back instead of re-running them, and ends exactly where an
    uninterrupted run ends; each trial's record (command, predicted and measured critical state, error,
    parameters, trust radius) is on disk."""
    import shutil

    from wrenorm.cli import main
    from wrenorm.tasks.rope.control.correct import StoredTrials

    full = tmp_path / "full"
    quick = [a if a != "measured" else params for a in CORRECT_QUICK]
    assert main(quick + ["--out", str(full)]) == 0
    done = json.loads((full / "correct.json").read_text())
    trials = done["runs"][params]["trials"]
    records = sorted((full / "real-trials").glob(f"{params}-trial-*.json"))
    assert [json.loads(f.read_text())["trial"] for f in records] == [1, 2, 3, 4]
    rec = json.loads(records[1].read_text())
    for key in ("command_u", "predicted_state", "measured_state", "error", "model_parameters", "trust_radius"):
        assert rec[key] is not None, key
    assert len(rec["measured_state"]["positions"]) == len(rec["predicted_state"]["positions"])
    if params == "renormalised":
        assert rec["refit"]["values"] and rec["trust"]["verdict"] in ("grow", "keep", "shrink")
        for a, b in zip(trials, trials[1:]):  # each trial records the radius it was planned in: the rule's, or less
            if a["trust"]:
                assert b["trust_radius"] <= a["trust"]["radius_after"] + 1e-12, (a["trust"], b["trust_radius"])
    assert "| trial | error |" in (full / "report.md").read_text()
    page = (full / "report.html").read_text()  # the same per-trial rows on the run's report page
    assert "did not reach the tolerance in 4 trials" in page
    assert all(f"<td>{t['error']:.4f}</td>" in page for t in trials), page
    assert len(trials) == 4 and done["real_trials_read_back"] == 0

    cut = tmp_path / "cut"
    shutil.copytree(full, cut)
    (cut / "correct.json").unlink()
    store = StoredTrials(None, cut / "real-trials")
    keep = {store.file_for(CommandSpace(PATHS["flick"]).decode(np.array(t["command_u"]))).name for t in trials[:2]}
    for f in store.folder.glob("trial-*.npz"):
        if f.name not in keep:
            f.unlink()
    assert len(list(store.folder.glob("trial-*.npz"))) == 2
    # settings come from the folder: an option given now with another value is refused, naming it (issue 17)
    assert main(["correct", "rope", "--resume", "--quiet", "--no-record", "--max-trials", "9", "--out", str(cut)]) == 2
    # also at its default (10): typed, it asks for 10 trials where the run had 4, and was silently given 4
    assert main(["correct", "rope", "--resume", "--quiet", "--no-record", "--max-trials", "10", "--out", str(cut)]) == 2
    assert len(list(store.folder.glob("trial-*.npz"))) == 2  # the refused resume touched nothing
    assert main(["correct", "rope", "--resume", "--quiet", "--no-record", "--out", str(cut)]) == 0
    again = json.loads((cut / "correct.json").read_text())
    # the two kept trials and the start throw's recording (OUT/start) are read back, not run again
    assert again["real_trials_read_back"] == 2 and again["real_runs"] == done["real_runs"] - 3
    assert [t["error"] for t in again["runs"][params]["trials"]] == [t["error"] for t in trials]
    values = lambda rows: [t["refit"] and t["refit"]["values"] for t in rows]  # noqa: E731
    assert values(again["runs"][params]["trials"]) == values(trials)
    assert again["max_trials"] == 4
    # the resumed run records the command that repeats it from scratch, not `--resume --out` without --resume
    line = shlex.split(again["command_line"])
    assert line[:3] == ["python", "-m", "wrenorm"] and "--resume" not in line and "--max-trials" in line, line
    line[line.index("--out") + 1] = str(tmp_path / "again")
    assert main(line[3:]) == 0
    fresh = json.loads((tmp_path / "again" / "correct.json").read_text())
    assert [t["error"] for t in fresh["runs"][params]["trials"]] == [t["error"] for t in trials]


def test_correct_resume_without_saved_settings_exits_2(tmp_path, capsys):
    from wrenorm.cli import main

    (tmp_path / "empty").mkdir()
    assert main(["correct", "rope", "--resume", "--out", str(tmp_path / "empty")]) == 2
    assert "settings.json" in capsys.readouterr().err
    assert main(["correct", "rope", "--resume"]) == 2
    assert "--out" in capsys.readouterr().err


def test_a_blown_up_real_trial_costs_that_trial_not_the_run(problem, tmp_path):
    """A real trial with non-finite markers cannot be stored as a reference file; the store hands it
    back anyway, and the correction scores it as a trial without self-collision."""
    from dataclasses import replace as dc_replace

    from wrenorm.tasks.rope.control.correct import StoredTrials

    space = CommandSpace(PATHS["flick"])
    good = CoarseRope(problem, problem.space.measured)
    goal = crit.Target.from_reference(load_reference(builtin_reference_path("flick_high")))

    class BlowsUp:
        runs, wall_s = 0, 0.0

        def __call__(self, path):
            self.runs += 1
            ref = good(path)
            markers = ref.markers.copy()
            markers[len(markers) // 3:] = np.nan
            return dc_replace(ref, markers=markers)

    store = StoredTrials(BlowsUp(), tmp_path / "trials")
    st = crit.from_reference(store(space.decode(np.zeros(space.dim))))
    assert store.unstored == 1 and not list(store.folder.glob("trial-*.npz"))
    assert not st.hit[0]
    assert goal.terms(st)["total"][0] >= 1.0  # a miss costs, and is finite


def test_newton_at_another_resolution_records_its_own_goal_and_start_throw(tmp_path):
    """The built-in references are newton's 64-segment rod. A run whose real rope is newton at another resolution
    steers that rope to ITS goal state (recorded before the trials, as on another engine), not to the 64-segment
    rod's: at 16 segments the goal's first contact comes ~0.2 s later."""
    import subprocess
    import sys
    from pathlib import Path

    from wrenorm.cli import main
    from wrenorm.tasks.rope.control.correct_cli import _builtin_reference

    out = tmp_path / "n16"
    assert main(["correct", "rope", "--fine-segments", "16", "--params", "measured", "--max-trials", "1",
                 "--generations", "3", "--popsize", "8", "--no-record", "--quiet", "--out", str(out)]) == 0
    done = json.loads((out / "correct.json").read_text())
    assert done["goal"]["from"].startswith("recorded on the real rope") and any((out / "goal").glob("trial-*.npz"))
    assert done["start"]["recorded_pair"]["source"].startswith("one newton run")
    builtin = crit.from_reference(_builtin_reference("flick_high", "default", print)).time[0]
    assert abs(done["goal"]["critical_time"] - builtin) > 0.1, (done["goal"]["critical_time"], builtin)
    assert "16 segments" in done["real_system"] and done["settings"]["fine_segments"] == 16
    assert json.loads((out / "settings.json").read_text())["builtin_throws"] is False
    # resumed, it reads its goal, start throw and trial back (no fine run) and repeats itself
    (out / "correct.json").unlink()
    assert main(["correct", "rope", "--resume", "--quiet", "--no-record", "--out", str(out)]) == 0
    again = json.loads((out / "correct.json").read_text())
    assert again["real_runs"] == 0 and again["goal"] == done["goal"]
    assert [t["error"] for t in again["runs"]["measured"]["trials"]] == [
        t["error"] for t in done["runs"]["measured"]["trials"]]
    line = shlex.split(again["command_line"])
    assert line[line.index("--fine-segments") + 1] == "16" and "--builtin-throws" not in line, line
    # the stall diagnosis replays on the built-in 64-segment rope: it refuses this run in one line
    stall = Path(__file__).parents[1] / "examples" / "diagnostics" / "correct_stall.py"
    r = subprocess.run([sys.executable, str(stall), str(out), "measured"], capture_output=True, text=True)
    assert r.returncode == 2 and "built-in 64-segment rope" in r.stderr.strip().splitlines()[-1], r.stderr


def test_mujoco_cable_plays_the_real_rope_and_agrees_with_its_reference_generator():
    from wrenorm.tasks.rope.control.correct import MujocoRope, real_rope_class
    from wrenorm.tasks.rope.reference.generate import generate_reference

    assert real_rope_class("mujoco") is MujocoRope
    real = real_rope_class("mujoco")("heavy", segments=32, duration=0.4)
    path = PATHS["flick"]
    first = real(path)
    assert real(path) is first and real.runs == 1  # a repeated command is not simulated again
    assert "mujoco" in first.source.lower()
    direct = generate_reference(path, segments=32, variant="heavy", duration=0.4, engine="mujoco")
    np.testing.assert_array_equal(first.markers, direct.markers)
    assert first.mass == pytest.approx(direct.mass)


def test_correction_recording_shows_each_runs_best_throw_whole(tmp_path):
    """The recording holds the whole throw (goal and each run's best trial, read back from the stored trials) on
    the simulation timeline, beside the per-trial critical states and errors."""
    from wrenorm.cli import main
    from wrenorm.viz.readback import entity_paths

    out = tmp_path / "rec"
    argv = [a for a in CORRECT_QUICK if a != "--no-record"] + ["--max-trials", "2", "--out", str(out)]
    assert main(argv) == 0
    paths = entity_paths(out / "recording.rrd")
    for who in ("goal", "measured"):
        assert f"/throw/{who}/rope" in paths and f"/throw/{who}/hand" in paths and f"/throw/{who}/critical" in paths
    assert "/shape/goal" in paths and "/error/measured" in paths


def test_the_campaign_and_stall_scripts_refuse_bad_input_in_one_line(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    examples = Path(__file__).resolve().parents[1] / "examples"
    diagnostics = examples / "diagnostics"
    measured_only = tmp_path / "measured-only"  # a `run` folder of another arm: compare needs the fitted chain
    measured_only.mkdir()
    np.savez(measured_only / "rope-sensitivity.npz", J=np.zeros((129, 13)), u=np.zeros(13), step=0.3)
    (measured_only / "settings.json").write_text("{}")
    (measured_only / "correct.json").write_text('{"runs": {"measured": {}}}')
    own_throws = tmp_path / "mujoco-fitted"  # a chain fitted to another engine's throws: a refit here would not be it
    own_throws.mkdir()
    np.savez(own_throws / "rope-sensitivity.npz", J=np.zeros((129, 13)), u=np.zeros(13), step=0.3)
    (own_throws / "settings.json").write_text(json.dumps({"goal": "flick_high", "variant": "default", "segments": 10,
                                                          "dt": 0.005, "start": "flick", "engine": "mujoco",
                                                          "fit_throws": "real"}))
    (own_throws / "correct.json").write_text('{"runs": {"fitted": {}}}')
    mujoco_run = tmp_path / "mujoco-run"  # the stall diagnosis replays runs on newton's rope only
    mujoco_run.mkdir()
    (mujoco_run / "correct.json").write_text(json.dumps({"runs": {"fitted": {}}, "settings": {"engine": "mujoco"},
                                                         "goal": {"path": "flick_high"}, "real_system": "mujoco"}))
    fine32 = tmp_path / "newton-32"  # its goal was recorded on its own 32-segment rope, not the built-in one
    fine32.mkdir()
    np.savez(fine32 / "rope-sensitivity.npz", J=np.zeros((129, 13)), u=np.zeros(13), step=0.3)
    (fine32 / "settings.json").write_text(json.dumps({"goal": "flick_high", "variant": "default", "segments": 10,
                                                      "engine": "newton", "fine_segments": 32,
                                                      "builtin_throws": False}))
    (fine32 / "correct.json").write_text('{"runs": {"fitted": {}}}')
    newton_run = tmp_path / "newton-run"  # a run the comparison can read, up to the parameters it is asked to free
    newton_run.mkdir()
    np.savez(newton_run / "rope-sensitivity.npz", J=np.zeros((129, 13)), u=np.zeros(13), step=0.3)
    (newton_run / "settings.json").write_text(json.dumps({"goal": "flick_high", "variant": "default", "segments": 10,
                                                          "dt": 0.005, "start": "flick", "engine": "newton",
                                                          "fine_segments": 64}))
    (newton_run / "correct.json").write_text('{"runs": {"fitted": {}}}')
    bad = {"correct.json: no fitted run": [diagnostics / "rope_sensitivity_prior.py", "compare", measured_only],
           "workers: must be >= 1": [examples / "correct_campaign.py", "--workers", "0", "--out", tmp_path / "c"],
           "no-run/correct.json: not a finished": [diagnostics / "correct_stall.py", tmp_path / "no-run"],
           "no-run/correct.json: not a finished `correct rope` run, nor a folder": [
               diagnostics / "step_prediction.py", tmp_path / "no-run"],
           "correct.json: runs: no run 'fitted'; it has measured": [diagnostics / "step_prediction.py", measured_only],
           "no-run/correct.json: not a finished correction": [diagnostics / "critical_velocity.py",
                                                               tmp_path / "no-run", "fitted"],
           "rope-sensitivity.npz: not the output of `run`": [diagnostics / "rope_sensitivity_prior.py", "compare",
                                                             tmp_path / "no-run"],
           "needs --out OUT and --linearise-at trial": [diagnostics / "rope_sensitivity_prior.py", "run",
                                                        "--variant", "heavy", "--out", tmp_path / "o"],
           "run takes fixed parameters only": [diagnostics / "rope_sensitivity_prior.py", "run", "--linearise-at",
                                               "trial", "--out", tmp_path / "o", "--params", "renormalised"],
           "--also-free widens the --best-parameters bound": [diagnostics / "rope_sensitivity_prior.py", "compare",
                                                              measured_only, "--also-free", "mass_slope"],
           "--also-free lead_fraction: not among the chain's fixed parameters": [
               diagnostics / "rope_sensitivity_prior.py", "compare", newton_run, "--best-parameters", "--also-free",
               "lead_fraction"],
           "repeated value stretch": [diagnostics / "rope_sensitivity_prior.py", "compare", measured_only,
                                      "--best-parameters", "--also-free", "stretch", "stretch"],
           "--segments 2: the chain takes 3-63 links": [diagnostics / "rope_sensitivity_prior.py", "compare",
                                                        measured_only, "--segments", "2"],
           "chain 64: give the chain's links first, 3-63": [diagnostics / "rope_sensitivity_prior.py", "chain", "64",
                                                            "--out", tmp_path / "o"],
           "chain needs --out OUT": [diagnostics / "rope_sensitivity_prior.py", "chain", "20", "--variant", "heavy"],
           "every-best needs --out OUT": [diagnostics / "rope_sensitivity_prior.py", "every-best", "--variant",
                                          "heavy", "--fine-segments", "32", "--out", tmp_path / "o"],
           "fitted to other throws than newton's": [diagnostics / "rope_sensitivity_prior.py", "compare", own_throws,
                                                     "--segments", "20"],
           "own 32-segment newton rope": [diagnostics / "rope_sensitivity_prior.py", "compare", fine32],
           "replays the run on newton's built-in 64-segment rope": [diagnostics / "correct_stall.py", mujoco_run],
           "newton rope of the built-in references (64 segments)": [
               diagnostics / "rope_sensitivity_prior.py", "run", "--linearise-at", "trial", "--out", tmp_path / "o",
               "--fine-segments", "32"]}
    for expected, argv in bad.items():
        r = subprocess.run([sys.executable, *map(str, argv)], capture_output=True, text=True)
        assert r.returncode == 2, r.stderr
        last = r.stderr.strip().splitlines()[-1]  # argparse prints its usage first; the error names the field
        assert expected in last, r.stderr


def _script_module(name: str):
    """A script of examples/diagnostics imported as a module."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "examples" / "diagnostics" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_best_steps_through_the_sensitivity_measured_at_each_best(tmp_path, monkeypatch):
    """rope_sensitivity_prior.py every-best: the sensitivity is measured at the best trial's command, again only when
    the best changes, and kept per best; every step after it is taken and predicted through exactly that matrix, not
    the chain's nor the secant-corrected one (the rope's central difference stands in as a known matrix here)."""
    from wrenorm.jacobian import Jacobian

    module, state_of = _script_module("rope_sensitivity_prior"), _script_module("step_prediction")._state
    monkeypatch.setattr(secant, "secant_pairs", secant.secant_pairs)  # every_best replaces both: restored after
    monkeypatch.setattr(secant.Sensitivity, "ridge", secant.Sensitivity.ridge)
    measured_at = []

    def known(out, ropes, space, u, step=secant.GN_FD_STEP):
        measured_at.append(np.array(u))
        rng = np.random.default_rng(len(measured_at))
        J = rng.normal(0.0, 0.02, (6 * SAMPLES + 3, space.dim))
        return Jacobian(J, np.zeros(len(J)), ["central"] * space.dim, 2 * space.dim + 1)

    monkeypatch.setattr(module, "_rope_sensitivity", known)
    out = tmp_path / "every-best"
    assert module.every_best([*CORRECT_QUICK[2:], "--max-trials", "5", "--out", str(out)]) == 0
    trials = json.loads((out / "correct.json").read_text())["runs"]["measured"]["trials"]
    bests, best = [], None
    for t in trials[:-1]:
        best = t if t["accepted"] else best
        bests.append(best)
    distinct = [b for i, b in enumerate(bests) if b is not None and (i == 0 or b is not bests[i - 1])]
    assert len(measured_at) == len(distinct) >= 1
    for u, b in zip(measured_at, distinct):
        assert np.array_equal(u, b["command_u"])
        assert np.array_equal(np.load(out / f"rope-sensitivity-at-trial-{b['trial']:02d}.npz")["u"], u)
    for b, nxt in zip(bests, trials[1:]):
        J = np.load(out / f"rope-sensitivity-at-trial-{b['trial']:02d}.npz")["J"]
        z_best = state_vector(state_of(b["measured_state"]))[0]
        z_predicted = state_vector(state_of(nxt["predicted_state"]))[0]
        du = np.array(nxt["command_u"]) - np.array(b["command_u"])
        assert np.allclose(z_predicted, z_best + J @ du, atol=1e-9), nxt["trial"]


def test_step_prediction_pairs_each_steps_prediction_with_what_the_rope_did(tmp_path):
    """The step-prediction diagnosis on a run whose every prediction came true scores each block's correlation 1,
    and its table of changes as vectors the share 1 at cosine 1; shuffling the predictions across trials breaks both;
    a rope that makes half of each predicted change shows the share 0.5 at cosine 1 and the best step lengths
    computed independently; runs it cannot score are refused in one line."""
    import subprocess
    import sys
    from pathlib import Path

    from wrenorm.tasks.rope.control.correct import state_record

    script = Path(__file__).resolve().parents[1] / "examples" / "diagnostics" / "step_prediction.py"
    goal = crit.Target.from_reference(load_reference(builtin_reference_path("flick_high", "default")))
    rng = np.random.default_rng(5)
    g, trials, states, best = goal.state, [], [], np.inf
    for k, scale in enumerate(np.geomspace(1.0, 0.05, 14)):
        place = np.clip(g.s + scale * rng.normal(0, 0.05, 2), 0, 1)
        st = crit.CriticalStates(g.pos + scale * rng.normal(0, 0.04, g.pos.shape),
                                 g.vel + scale * rng.normal(0, 1.0, g.vel.shape),
                                 g.time * (1 + scale * rng.normal(0, 0.05)), place, np.ones(1, bool), np.zeros(1))
        terms = {key: float(v[0]) for key, v in goal.terms(st).items()}
        states.append(st)
        trials.append({"trial": k + 1, "error": terms["total"], "accepted": terms["total"] < best,
                       "self_collision": True, "terms": terms, "measured_state": state_record(st),
                       "predicted_state": state_record(st)})
        best = min(best, terms["total"])

    def scored(folder, run=None, settings=None, trials=trials, tolerance=0.05):
        folder.mkdir()
        (folder / "correct.json").write_text(json.dumps({
            "variant": "default", "goal": {"path": "flick_high"}, "tolerance": tolerance,
            "settings": settings or {"engine": "newton", "real": "fine"},
            "runs": {"fitted": (run or {"method": "gn", "steps": "gn"}) | {"trials": trials}}}))
        return subprocess.run([sys.executable, str(script), str(folder)], capture_output=True, text=True)

    r = scored(tmp_path / "true")
    assert r.returncode == 0, r.stderr
    cells = [line.split("|")[3].strip() for line in r.stdout.splitlines() if line.startswith("| best error")][:8]
    assert len(cells) == 8 and sum(c == "1.00" for c in cells) >= 6 and set(cells) <= {"1.00", "nan"}, r.stdout
    assert "No step recorded the corrected model's floor" in r.stdout
    along = [line.split("|") for line in r.stdout.splitlines() if line.startswith("| best error")][8:10]
    assert len(along) == 2 and all(row[2].strip() == row[3].strip() == "1.00" for row in along), r.stdout
    # every prediction came true: each part of the velocity change, in the first modes and the rest, at cosine 1
    split = [line.split("|") for line in r.stdout.splitlines() if line.startswith("| best error")][10:]
    assert [int(row[2]) for row in split] == [1, 2, 3, 5] * 4, r.stdout  # velocity, then position
    assert all(row[4].strip() == "1.00 / 1.00" and row[5].strip() == "0.00 / 0.00" for row in split), r.stdout
    # each step's floor, recorded with the trial before it, set to 0.6 of the best error then: the table says 0.60
    with_floor, best = [], np.inf
    for t in trials:
        best = min(best, t["error"]) if t["accepted"] else best
        terms = {k: 0.6 * v for k, v in t["terms"].items() if k != "total"}
        with_floor.append(t | {"next_step": {"model_floor": {"error": 0.6 * best, "terms": terms}}})
    r = scored(tmp_path / "floor", trials=with_floor)
    floor_rows = [line.split("|") for line in r.stdout.splitlines()[-2:]]
    assert r.returncode == 0 and all(row[2].strip() == "0.60" for row in floor_rows), r.stdout
    floors = [t["next_step"]["model_floor"]["error"] for t in with_floor[:-1]]  # the 13 steps' floors
    assert sum(int(row[5].split()[0]) for row in floor_rows) == sum(f > 0.05 for f in floors), r.stdout
    shuffled = [t | {"predicted_state": trials[(i + 5) % len(trials)]["predicted_state"]}
                for i, t in enumerate(trials)]
    r = scored(tmp_path / "shuffled", trials=shuffled)
    assert r.returncode == 0 and not set([line.split("|")[3].strip() for line in r.stdout.splitlines()
                                          if line.startswith("| best error")][:8]) <= {"1.00", "nan"}, r.stdout
    along = [line.split("|") for line in r.stdout.splitlines() if line.startswith("| best error")][8:10]
    assert all(float(row[3]) < 0.99 for row in along), r.stdout
    # a rope that makes half of every predicted change, straight along it: the share 0.50 at cosine 1.00, and the
    # best length per step as computed here from the residuals themselves
    half, best_state, best_error, lengths = [], None, np.inf, []
    for k, st in enumerate(states):
        made = st if best_state is None else crit.CriticalStates(
            *(b + 0.5 * (p - b) for b, p in ((best_state.pos, st.pos), (best_state.vel, st.vel),
                                               (best_state.time, st.time), (best_state.s, st.s))),
            np.ones(1, bool), np.zeros(1))
        terms = {key: float(v[0]) for key, v in goal.terms(made).items()}
        if best_state is not None:
            r_best = goal.residual(best_state)[0]
            change = goal.residual(made)[0] - r_best
            lengths.append((best_error, -float(r_best @ change) / float(change @ change)))
        half.append({"trial": k + 1, "error": terms["total"], "accepted": terms["total"] < best_error,
                     "self_collision": True, "terms": terms, "measured_state": state_record(made),
                     "predicted_state": state_record(st)})
        if terms["total"] < best_error:
            best_state, best_error = made, terms["total"]
    r = scored(tmp_path / "half", trials=half)
    along = [line.split("|") for line in r.stdout.splitlines() if line.startswith("| best error")][8:10]
    assert r.returncode == 0 and all(row[2].strip() == "0.50" and row[3].strip() == "1.00" for row in along), r.stdout
    for row, keep in zip(along, (lambda b: b > 0.1, lambda b: b <= 0.1)):
        mine = [a for b, a in lengths if keep(b)]
        assert int(row[1].split(":")[1]) == len(mine) and float(row[4].split()[0]) == pytest.approx(
            np.median(mine), abs=0.006), (row, mine)
    # the rope moved half as far as predicted, straight along it, from a best whose residual the step would cancel:
    # half the predicted change made, at no angle, and twice the step would have been best
    diag = _script_module("step_prediction")
    p = np.array([0.3, -0.4, 0.1])
    assert diag.along_the_step(-p, p, 0.5 * p) == pytest.approx({"projection": 0.5, "cosine": 1.0, "best_length": 2.0})
    assert diag.along_the_step(-p, p, np.array([0.4, 0.3, 0.0]))["cosine"] == pytest.approx(0.0)
    assert all(np.isnan(v) for v in diag.along_the_step(-p, p, np.zeros(3)).values())  # no change: no direction
    # the velocity split: a change on a straight line in arc length lies in the first two modes whole; predicted
    # right there and wrong in the rest (the opposite sign), the parts score cosine 1 and -1
    v, arc = goal.blocks["velocity"], np.linspace(0.0, 1.0, crit.SAMPLES)
    smooth, rough = np.zeros(goal.dim), np.zeros(goal.dim)
    smooth[v] = np.stack([1 + arc, 2 * arc, -arc], axis=1).ravel()
    rough[v] = rng.normal(size=3 * crit.SAMPLES)
    rough -= secant.velocity_projection(goal, 2) @ rough
    split = diag.block_modes(goal, "velocity", smooth - rough, smooth + rough)["velocity_modes2"]
    assert split["share"] == pytest.approx(smooth @ smooth / (smooth @ smooth + rough @ rough))
    assert split["kept"] == pytest.approx((1.0, 0.0), abs=1e-12) and split["rest"] == pytest.approx((-1.0, 2.0))
    # the same split of the position block, the velocity block then untouched by its projection
    x = goal.blocks["position"]
    moved = np.zeros(goal.dim)
    moved[x] = smooth[v]
    assert np.allclose(secant.mode_projection(goal, "position", 2) @ moved, moved)
    assert np.allclose(secant.mode_projection(goal, "position", 2) @ rough, rough)  # velocity rows kept whole
    shape = diag.block_modes(goal, "position", moved, moved)["position_modes2"]
    assert shape["share"] == pytest.approx(1.0) and shape["kept"] == pytest.approx((1.0, 0.0), abs=1e-12)
    wrong_goal = [t | {"error": t["error"] + 0.01} for t in trials]
    for name, kw, expected in (("plan", {"run": {"method": "plan"}}, "does not step by Gauss-Newton"),
                               ("coarse", {"settings": {"engine": "newton", "real": "coarse"}}, "coarse stand-in"),
                               ("other-goal", {"trials": wrong_goal}, "is not its state's error to this goal"),
                               ("no-tolerance", {"tolerance": None}, "tolerance: None, not a number")):
        r = scored(tmp_path / name, **kw)
        assert r.returncode == 2 and expected in r.stderr.strip().splitlines()[-1], r.stderr


def test_the_campaign_compares_the_issues_three_arms_by_default(tmp_path):
    """Without --params the campaign's arms are the issue's three with the renormalised one as `correct rope` runs it
    (started from the fitted values): a table over finished runs has those columns, in that order."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    examples = Path(__file__).resolve().parents[1] / "examples"
    arms = ("renormalised-from-fitted", "measured", "fitted")
    run = {"success": True, "trials_to_tolerance": 2, "best_error": 0.04,
           "trials": [{"error": e, "accepted": True} for e in (0.3, 0.04)]}
    (tmp_path / "stiff-s0").mkdir()
    (tmp_path / "stiff-s0" / "correct.json").write_text(json.dumps({"max_trials": 10, "tolerance": 0.05,
                                                                    "runs": {a: run for a in arms},
                                                                    "settings": {"seed": 0}}))
    r = subprocess.run([sys.executable, str(examples / "correct_campaign.py"), "--out", str(tmp_path), "--variants",
                        "stiff", "--seeds", "0", "--table-only"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "| rope | seed | renormalised-from-fitted | measured | fitted | wall (min) |" in (tmp_path /
                                                                                        "campaign.md").read_text()
    assert list(json.loads((tmp_path / "campaign.json").read_text())["summary"]) == list(arms)


def test_the_campaign_table_keeps_every_runs_trials(tmp_path):
    """--table-only over finished runs: the counts follow the runs' trials, campaign.json keeps those trials, and
    the table says which settings differ between its runs."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    examples = Path(__file__).resolve().parents[1] / "examples"
    errors = {("stiff", 0): [0.3, 0.2, 0.04], ("stiff", 1): [0.3, 0.25, 0.2, 0.1], ("soft", 0): [0.3, 0.05],
              ("soft", 1): [0.3, 0.2, 0.09], ("heavy", 0): [0.3, 0.2, 0.08]}
    floors = {("soft", 1): 0.07, ("heavy", 0): 0.03}  # the model's floor at the last step of two misses
    for (v, s), errs in errors.items():
        reached = next((i + 1 for i, e in enumerate(errs) if e <= 0.05), None)
        run = {"success": reached is not None, "trials_to_tolerance": reached, "best_error": min(errs),
               "trials": [{"error": e, "accepted": True, "predicted_error": e / 2} for e in errs]}
        if (v, s) in floors:
            run["trials"][-2]["next_step"] = {"model_floor": {"error": floors[(v, s)]}}
        (tmp_path / f"{v}-s{s}").mkdir()
        settings = {"seed": s, "method": "gn", "start_pair": "none" if v == "stiff" else "first"}
        (tmp_path / f"{v}-s{s}" / "correct.json").write_text(json.dumps({"max_trials": 10, "tolerance": 0.05,
                                                                          "runs": {"fitted": run},
                                                                          "settings": settings}))
    r = subprocess.run([sys.executable, str(examples / "correct_campaign.py"), "--out", str(tmp_path), "--variants",
                        "stiff", "soft", "heavy", "--seeds", "0", "1", "--params", "fitted", "--table-only"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    meta = json.loads((tmp_path / "campaign.json").read_text())
    summary = meta["summary"]["fitted"]
    assert summary["runs"] == 5 and summary["reached"] == 2 and summary["median"] == 11.0  # 3, 11, 2, 11, 11
    assert summary["per_rope"] == {"stiff": 7.0, "soft": 6.5, "heavy": 11.0}
    # two of the three misses recorded a floor at their last step; soft s1's lay above the tolerance, heavy s0's not
    assert (summary["misses_with_floor"], summary["misses_floor_above_tolerance"]) == (2, 1)
    assert [t["error"] for t in meta["trials"]["stiff-s1"]["fitted"]] == errors[("stiff", 1)]
    assert meta["trials"]["soft-s0"]["fitted"][1] == {"error": 0.05, "accepted": True, "predicted_error": 0.025}
    text = (tmp_path / "campaign.md").read_text()
    assert "| stiff | 1 | - (0.100) |" in text and "| 1 of 2 |" in text
    # runs made under different settings (a campaign resumed after a default changed) are said to differ, and how
    assert '**The runs differ in `start_pair`**: "none": stiff-s0, stiff-s1; "first": soft-s0' in text
    assert "differ in `seed`" not in text and "differ in `method`" not in text


def test_the_best_parameters_bound_recovers_a_chains_own_sensitivity(problem):
    """rope_sensitivity_prior's bound (parameters whose sensitivity lies closest to a given one): handed the
    sensitivity of a chain with known parameters, it must find parameters whose sensitivity is that one, from the
    measured values that are far from it."""
    diag = _script_module("rope_sensitivity_prior")
    space = CommandSpace(PATHS["flick"])
    u = np.zeros(space.dim)
    goal = crit.Target.from_reference(CoarseRope(problem, problem.space.measured)(PATHS["flick_fast"]))
    w = secant.residual_weights(goal)
    J = secant.Sensitivity.of_chain(CoarseModel(problem, shifted(problem), space), u).S
    start = CoarseModel(problem, problem.space.measured, space)
    P0 = secant.Sensitivity.of_chain(start, u).S
    d0 = np.linalg.norm(w[:, None] * (P0 - J)) / np.linalg.norm(w[:, None] * J)
    values, d = diag.best_parameters(start, J, w, u, secant.GN_FD_STEP, seed=0)
    P = secant.Sensitivity.of_chain(CoarseModel(problem, values, space), u).S
    assert d0 > 0.1 and d < 0.2 * d0
    assert np.isclose(np.linalg.norm(w[:, None] * (P - J)) / np.linalg.norm(w[:, None] * J), d)


def test_the_bound_with_a_fixed_parameter_set_free_reaches_a_sensitivity_only_it_can_make(problem):
    """--also-free: the bound searches the named fixed parameter too, from the six-parameter bound, so it ends no
    further from the given sensitivity. Handed the sensitivity of a chain whose mass profile is not the start's
    (mass_slope 0.6, stiffness and drag as in the test above), it comes closer with mass_slope free."""
    diag = _script_module("rope_sensitivity_prior")
    space = CommandSpace(PATHS["flick"])
    u = np.zeros(space.dim)
    goal = crit.Target.from_reference(CoarseRope(problem, problem.space.measured)(PATHS["flick_fast"]))
    w = secant.residual_weights(goal)
    truth = shifted(problem)
    truth[problem.space.index("mass_slope")] = 0.6
    J = secant.Sensitivity.of_chain(CoarseModel(problem, truth, space), u).S
    frozen = problem.space
    six, d_six = diag.best_parameters(CoarseModel(problem, frozen.measured, space), J, w, u, secant.GN_FD_STEP, 0)
    try:
        problem.space = frozen.with_changes(mass_slope={"frozen": False})
        values, d_free = diag.best_parameters(CoarseModel(problem, six, space), J, w, u, secant.GN_FD_STEP, 0)
    finally:
        problem.space = frozen
    assert d_free < d_six and values[frozen.index("mass_slope")] != 0.0


def test_the_start_throws_recording_is_one_more_secant_pair(problem, tmp_path):
    """--start-pair: the real rope's critical state under the start command, recorded before the trials, corrects
    the chain's sensitivity as a trial's pair would: after trial 1 the estimate predicts the change from trial 1 to
    the start closer than the chain's own, and it is counted as a pair but not as a trial; "first" drops it once a
    trial gives a pair of its own, "every" keeps it; a recording without a collision is left out. Through the CLI
    (the coarse stand-in plays the rope) it is recorded once in OUT/start and named in correct.json."""
    space = CommandSpace(PATHS["flick"])
    real = CoarseRope(problem, shifted(problem))
    goal = crit.Target.from_reference(real(PATHS["flick_fast"]))
    start = crit.from_reference(real(PATHS["flick"]))
    model = CoarseModel(problem, problem.space.measured, space)
    kw = dict(max_trials=3, tolerance=1e-6, method="gn", **FAST_PLAN)
    plain = correct(real, model, goal, np.zeros(space.dim), **kw)
    paired = correct(real, model, goal, np.zeros(space.dim), recorded=[(np.zeros(space.dim), start)], **kw)
    t1 = paired["trials"][0]
    assert np.array_equal(t1.u, plain["trials"][0].u) and len(paired["trials"]) == 3
    assert plain["trials"][0].sensitivity["secant_pairs"] == 0 and t1.sensitivity["secant_pairs"] == 1
    assert paired["recorded_pairs"] == 1 and plain["recorded_pairs"] == 0
    every = correct(real, model, goal, np.zeros(space.dim), recorded=[(np.zeros(space.dim), start)],
                    recorded_until="every", **kw)
    assert np.array_equal(every["trials"][1].u, paired["trials"][1].u)  # the same first step
    assert paired["trials"][1].hit and every["trials"][1].hit
    assert paired["trials"][1].sensitivity["secant_pairs"] == 1 and every["trials"][1].sensitivity["secant_pairs"] == 2
    assert not np.allclose(paired["trials"][1].u, plain["trials"][1].u)  # the pair changed the step

    # the pair itself: the corrected sensitivity reproduces the start's change from trial 1 better than the prior
    w = secant.residual_weights(goal)
    z1, z0 = state_vector(t1.state)[0], state_vector(start)[0]
    sens = secant.Sensitivity.of_chain(model, np.array(t1.sensitivity["linearised_at"]))
    prior_miss = np.linalg.norm(w * (sens.S @ (0.0 - t1.u) - (z0 - z1)))
    sens.ridge([0.0 - t1.u], [z0 - z1])
    assert np.linalg.norm(w * (sens.S @ (0.0 - t1.u) - (z0 - z1))) < 0.2 * prior_miss

    nan = np.full_like(start.pos, np.nan)
    missed = crit.CriticalStates(nan, nan.copy(), np.full(1, np.nan), np.full((1, 2), np.nan), np.zeros(1, bool),
                                 np.array([0.02]))
    none = correct(real, model, goal, np.zeros(space.dim), recorded=[(np.zeros(space.dim), missed)], **kw)
    assert none["recorded_pairs"] == 0 and [t.u.tolist() for t in none["trials"]] == [
        t.u.tolist() for t in plain["trials"]]

    from wrenorm.cli import main

    out = tmp_path / "paired"  # "first" is the default with Gauss-Newton steps
    assert main(CORRECT_QUICK + ["--max-trials", "2", "--out", str(out)]) == 0
    done = json.loads((out / "correct.json").read_text())
    rec = done["start"]["recorded_pair"]
    assert rec["path"] == "flick" and rec["hit"] and rec["error"] > 0 and "coarse" in rec["source"]
    assert done["runs"]["measured"]["recorded_pairs"] == 1 and done["settings"]["start_pair"] == "first"
    assert len(list((out / "start").glob("trial-*.npz"))) == 1
    assert "offset" not in done["runs"]["measured"]["trial0_plan"]  # trial 1 on the chain alone by default
    # without the pair the start throw is still recorded where trial 1 is planned with its offset
    out = tmp_path / "offset-only"
    assert main(CORRECT_QUICK + ["--max-trials", "1", "--start-pair", "none", "--first-plan-offset", "start", "--out",
                                 str(out)]) == 0
    done = json.loads((out / "correct.json").read_text())
    run = done["runs"]["measured"]
    assert run["recorded_pairs"] == 0 and run["trial0_plan"]["offset"]["chain_error_to_rope_there"] > 0
    assert done["settings"]["first_plan_offset"] == "start" and done["start"]["recorded_pair"]["hit"]
    assert len(list((out / "start").glob("trial-*.npz"))) == 1


def test_start_pair_default_follows_the_method_and_old_runs_resume_without_it(tmp_path):
    """Left out, --start-pair is "first" with Gauss-Newton steps and "none" with plan and qp (which would ignore
    it); named with them it is refused. A run saved before the option existed resumes without a start pair, as it
    ran, and asking for one there is refused."""
    import argparse

    from wrenorm.tasks.rope.control import correct_cli

    assert correct_cli.start_pair_for(None, "gn") == "first"
    assert correct_cli.start_pair_for(None, "plan") == "none" and correct_cli.start_pair_for(None, "qp") == "none"
    assert correct_cli.start_pair_for("every", "gn") == "every"
    assert correct_cli.start_pair_for("none", "plan") == "none"
    with pytest.raises(InputError, match="--method gn"):
        correct_cli.start_pair_for("first", "qp")

    parser = argparse.ArgumentParser()
    correct_cli.add_arguments(parser)
    old = {k: v for k, v in vars(parser.parse_args(["--segments", "12"])).items()
           if k not in correct_cli._NOT_SAVED and k not in ("start_pair", "trust_region", "max_radius",
                                                             "velocity_weight", "secant_locality",
                                                             "first_plan_reg", "first_plan_offset", "velocity_modes")}
    (tmp_path / correct_cli.SETTINGS_FILE).write_text(json.dumps(old))
    args = parser.parse_args(["--resume", "--out", str(tmp_path)])
    correct_cli._restore_settings(args)
    assert args.start_pair == "none" and args.segments == 12
    typed = ["--resume", "--out", str(tmp_path), "--segments", "10"]  # the default, typed: not what the run had
    args = parser.parse_args(typed)
    args.command, args.system, args._argv = "correct", "rope", ["correct", "rope", *typed]
    with pytest.raises(InputError, match="ran with 12"):
        correct_cli._restore_settings(args)
    args = parser.parse_args(typed[:3])
    args.command, args.system, args._argv = "correct", "rope", ["correct", "rope", *typed[:3]]
    correct_cli._restore_settings(args)
    assert args.segments == 12
    assert args.first_plan_reg == "as-plans" and correct_cli._first_plan_reg(args, "fitted") == 1e-4  # as it ran
    assert args.first_plan_offset == "none" and not correct_cli._first_plan_offset(args, "fitted")  # as it ran
    with pytest.raises(InputError, match="on the chain alone"):
        correct_cli._restore_settings(parser.parse_args(["--resume", "--out", str(tmp_path), "--first-plan-offset",
                                                         "start"]))
    with pytest.raises(InputError, match="'by-method' is not none or start"):  # a saved value argparse never saw
        correct_cli._check_first_plan(argparse.Namespace(**(vars(args) | {"first_plan_offset": "by-method"})))
    with pytest.raises(InputError, match="other plans' weight"):
        correct_cli._restore_settings(parser.parse_args(["--resume", "--out", str(tmp_path), "--first-plan-reg",
                                                         "0.01"]))
    assert args.builtin_throws  # a newton run saved before the setting used the built-in throws, as it resumes
    (tmp_path / correct_cli.SETTINGS_FILE).write_text(json.dumps(old | {"fine_segments": 32, "device": "cuda:0"}))
    args = parser.parse_args(["--resume", "--out", str(tmp_path), "--device", "cuda"])  # "cuda:0" saved is "cuda"
    correct_cli._restore_settings(args)
    assert args.builtin_throws and args.fine_segments == 32 and args.device == "cuda"
    args.device = "cuda:0"  # as run() resolves it
    line = shlex.split(correct_cli.reproduce_command(args))  # at 32 segments it took the built-in throws: said so
    assert "--builtin-throws" in line and line[line.index("--device") + 1] == "cuda", line
    assert parser.parse_args(line[5:]).builtin_throws is True
    (tmp_path / correct_cli.SETTINGS_FILE).write_text(json.dumps(old))
    args = parser.parse_args(["--resume", "--out", str(tmp_path), "--start-pair", "first"])
    with pytest.raises(InputError, match="without a start pair"):
        correct_cli._restore_settings(args)
    # so does one saved before --trust-region: every run adapted its radius then, and resumes that way
    args = parser.parse_args(["--resume", "--out", str(tmp_path)])
    correct_cli._restore_settings(args)
    assert args.trust_region == "adaptive" and correct_cli._trust_rule(args, "fitted") == "adaptive"
    args = parser.parse_args(["--resume", "--out", str(tmp_path), "--trust-region", "fixed"])
    with pytest.raises(InputError, match="adapted its trust radius"):
        correct_cli._restore_settings(args)
    args = parser.parse_args(["--resume", "--out", str(tmp_path), "--max-radius", "2"])
    with pytest.raises(InputError, match="had no --max-radius"):
        correct_cli._restore_settings(args)
    # and before --velocity-weight: its steps weighed the velocity rows as the others
    args = parser.parse_args(["--resume", "--out", str(tmp_path)])
    correct_cli._restore_settings(args)
    assert correct_cli._step_options(args, "fitted") == {"velocity_weight": 1.0, "velocity_modes": SAMPLES,
                                                         "trust_norm": "box", "secant_locality": None}
    args.resume, args.out = True, tmp_path / "x"  # the line that repeats it names what the old run did
    line = shlex.split(correct_cli.reproduce_command(args))
    for flag, value in (("--velocity-weight", "1.0"), ("--trust-region", "adaptive"), ("--start-pair", "none"),
                        ("--segments", "12"), ("--velocity-modes", "all")):
        assert line[line.index(flag) + 1] == value, line
    assert "--builtin-throws" not in line  # at 64 segments the built-in throws are what a fresh run takes anyway
    derived = lambda ns: {k: v for k, v in vars(ns).items() if k != "builtin_throws"}  # noqa: E731 (run() derives it)
    assert derived(parser.parse_args(line[5:])) | {"resume": True} == derived(args) | {"out": tmp_path / "x"}
    args = parser.parse_args(["--resume", "--out", str(tmp_path), "--velocity-weight", "0.5"])
    with pytest.raises(InputError, match="weighed the velocity rows"):
        correct_cli._restore_settings(args)
    args = parser.parse_args(["--resume", "--out", str(tmp_path), "--secant-locality", "1"])
    with pytest.raises(InputError, match="weighed every secant pair alike"):
        correct_cli._restore_settings(args)
    args = parser.parse_args(["--resume", "--out", str(tmp_path), "--velocity-weight", "1.0"])  # what it ran
    correct_cli._restore_settings(args)
    assert correct_cli._step_options(args, "renormalised") == {"velocity_weight": 1.0, "velocity_modes": SAMPLES,
                                                               "trust_norm": "box", "secant_locality": None}
    # and before --velocity-modes: its steps kept every velocity row; another number on its resume is refused
    args = parser.parse_args(["--resume", "--out", str(tmp_path), "--velocity-modes", "3"])
    with pytest.raises(InputError, match="kept every velocity row"):
        correct_cli._restore_settings(args)
    # an old plan run: its fixed arms had no trust region and its renormalised arms adapted, which is by-arm now;
    # its --min-radius, where no arm used it, is dropped rather than refused
    for params, kept in ((["measured"], None), (["measured", "renormalised"], 0.5)):
        (tmp_path / correct_cli.SETTINGS_FILE).write_text(json.dumps(old | {"method": "plan", "params": params,
                                                                             "min_radius": 0.5}))
        args = parser.parse_args(["--resume", "--out", str(tmp_path)])
        correct_cli._restore_settings(args)
        assert args.trust_region == "by-arm" and args.method == "plan" and args.min_radius == kept
        assert args.velocity_weight == "by-arm" and correct_cli._step_options(args, "measured") == {}
        correct_cli._check_step_options(args)  # what it ran with is no step option it lacks a step for
    # a run saved today resumes with its own, and is refused another
    today = vars(parser.parse_args(["--trust-region", "adaptive", "--max-radius", "2"]))
    (tmp_path / correct_cli.SETTINGS_FILE).write_text(json.dumps(
        {k: v for k, v in today.items() if k not in correct_cli._NOT_SAVED}))
    args = parser.parse_args(["--resume", "--out", str(tmp_path)])
    correct_cli._restore_settings(args)
    assert args.trust_region == "adaptive" and args.max_radius == 2.0
    with pytest.raises(InputError, match="ran with 'adaptive'"):
        correct_cli._restore_settings(parser.parse_args(["--resume", "--out", str(tmp_path), "--trust-region",
                                                         "fixed"]))
    assert args.velocity_weight == "by-arm"  # by-arm saved today stays by-arm, not the old runs' 1
    today = vars(parser.parse_args(["--velocity-weight", "0.5"]))
    (tmp_path / correct_cli.SETTINGS_FILE).write_text(json.dumps(
        {k: v for k, v in today.items() if k not in correct_cli._NOT_SAVED}))
    for given in ([], ["--velocity-weight", ".5"]):
        args = parser.parse_args(["--resume", "--out", str(tmp_path)] + given)
        correct_cli._restore_settings(args)
        assert correct_cli._step_options(args, "fitted") == {"velocity_weight": 0.5, "velocity_modes": None,
                                                             "trust_norm": "box", "secant_locality": None}
    with pytest.raises(InputError, match="ran with 0.5"):
        correct_cli._restore_settings(parser.parse_args(["--resume", "--out", str(tmp_path), "--velocity-weight",
                                                         "1"]))
    # a weight is refused only where no arm steps by Gauss-Newton: renormalised arms of --method qp do, of plan not
    correct_cli._check_step_options(parser.parse_args(["--velocity-weight", "1", "--method", "qp", "--params",
                                                          "measured", "renormalised"]))
    with pytest.raises(InputError, match="no run here takes one"):
        correct_cli._check_step_options(parser.parse_args(["--velocity-weight", "1", "--method", "plan",
                                                              "--params", "measured", "renormalised"]))
    new = argparse.Namespace(**vars(parser.parse_args([])))  # left out: fixed for fixed parameters
    assert new.trust_region == "by-arm" and correct_cli._trust_rule(new, "fitted") == "fixed"
    # the default arm renormalises from the fitted values, in the renormalised arms' adaptive trust region
    assert new.params == ["renormalised-from-fitted"] and correct_cli._trust_rule(new, new.params[0]) == "adaptive"
    assert correct_cli._trust_rule(new, "renormalised") == "adaptive"
    assert correct_cli._step_options(new, "fitted") == {"velocity_weight": None, "velocity_modes": None,
                                                        "trust_norm": "box", "secant_locality": None}  # by arm
    # trial 1's weight: by method (correct() gives Gauss-Newton arms FIRST_PLAN_REG); as-plans is each loop's own
    assert new.first_plan_reg == "by-method" and correct_cli._first_plan_reg(new, "fitted") is None
    as_plans = parser.parse_args(["--first-plan-reg", "as-plans", "--method", "plan"])
    assert correct_cli._first_plan_reg(as_plans, "fitted") is None  # the plan loop's --reg
    assert correct_cli._first_plan_reg(as_plans, "renormalised") is None  # renormalised arms of plan plan too
    assert correct_cli._first_plan_reg(parser.parse_args(["--first-plan-reg", "as-plans"]), "renormalised") == 1e-4
    assert correct_cli._first_plan_reg(parser.parse_args(["--first-plan-reg", ".01"]), "measured") == 0.01
    # trial 1's offset: none by default; with start wherever a trial 1 is planned
    assert new.first_plan_offset == "none" and not correct_cli._first_plan_offset(new, "fitted")
    start = parser.parse_args(["--first-plan-offset", "start"])
    assert correct_cli._first_plan_offset(start, "fitted") and correct_cli._first_plan_offset(start, "renormalised")
    assert correct_cli._first_plan_offset(parser.parse_args(["--first-plan-offset", "start", "--method", "plan"]),
                                          "fitted")
    for argv in (["--first-plan-offset", "start", "--no-plan-first"], ["--first-plan-offset", "start", "--method",
                                                                       "qp"], ["--first-plan-offset", "none"]):
        assert not correct_cli._first_plan_offset(parser.parse_args(argv), "measured"), argv
    # a run that plans no trial 1 gets no weight, whatever was asked or restored, so that correct() accepts every arm
    from wrenorm.tasks.rope.control.correct import plans_first

    for argv in (["--first-plan-reg", "as-plans", "--no-plan-first"], ["--first-plan-reg", ".01", "--no-plan-first",
                                                                       "--method", "plan"],
                 ["--first-plan-reg", ".01", "--method", "qp"], ["--first-plan-reg", "as-plans", "--method", "qp"],
                 ["--no-plan-first"]):
        args = parser.parse_args(argv)
        for label in ("fitted", "measured", "renormalised"):
            method, steps = correct_cli._arm_method(args, label)
            value = correct_cli._first_plan_reg(args, label)
            assert value is None or plans_first(method, steps, not args.no_plan_first), (argv, label)
            if label == "renormalised" and "plan" in argv:  # the renormalised plan loop always plans trial 1
                assert value == 0.01
    (tmp_path / correct_cli.SETTINGS_FILE).write_text(json.dumps(old | {"no_plan_first": True}))
    args = parser.parse_args(["--resume", "--out", str(tmp_path)])
    correct_cli._restore_settings(args)  # an old --no-plan-first run resumes with no first-plan weight
    assert args.first_plan_reg == "as-plans" and correct_cli._first_plan_reg(args, "fitted") is None


class ChainEngine:
    """A third 'fine' engine for the CLI: the coarse chain with shifted parameters (so fitting can tell it from the
    measured values); under the hand paths in NO_HIT the hand carries it rigidly, a throw that never hits itself."""

    NO_HIT = ("flick_wide",)
    runs_by_path: list = []

    def __init__(self, variant, segments, duration, device):
        ref = load_reference(builtin_reference_path("flick", "default"))
        problem = RopeProblem([ref], segments=10, dt=0.005)
        self.chain = CoarseRope(problem, shifted(problem))
        self.runs, self.wall_s = 0, 0.0

    def __call__(self, path):
        from dataclasses import replace as dc_replace

        self.runs += 1
        name = next((n for n, p in PATHS.items() if np.array_equal(p.control_points, path.control_points)
                     and np.array_equal(p.durations, path.durations)), "trial")
        ChainEngine.runs_by_path.append(name)
        ref = self.chain(path)
        if name in self.NO_HIT:
            # the rope carried rigidly by the hand: held end on the hand, never touching itself
            ref = dc_replace(ref, markers=ref.markers[:1] + (ref.hand - ref.hand[:1])[:, None, :])
        return ref


def test_fitted_on_another_engine_is_fitted_to_that_ropes_own_throws(tmp_path, monkeypatch, capsys):
    """--params fitted on an engine other than newton fits the chain to that rope's own fit throws, each run once
    before the trials (OUT/fit-throws), leaving out the goal's throw (never run for the fit) and a throw that never
    hits itself, both named; the start pair reuses the start throw's fit recording, and a resumed run reads them
    back. On newton the goal's throw is left out too. --fit-throws newton keeps the newton rope's built-in throws; a
    run saved before the option resumes with them. No fittable throw, or "real" with the coarse stand-in: exit 2."""
    import argparse

    from wrenorm.cli import main
    from wrenorm.tasks.rope.control import correct as rope_correct
    from wrenorm.tasks.rope.control import correct_cli

    monkeypatch.setitem(rope_correct.REAL_ROPES, "chain", ChainEngine)
    ChainEngine.runs_by_path = []
    cmd = ["correct", "rope", "--engine", "chain", "--goal", "flick_fast", "--params", "fitted", "--segments", "10",
           "--fit-generations", "4", "--generations", "8", "--popsize", "16", "--max-trials", "2", "--no-record",
           "--quiet"]
    out = tmp_path / "own"
    assert main(cmd + ["--out", str(out)]) == 0
    done = json.loads((out / "correct.json").read_text())
    fit = done["model"]["fit"]
    assert fit["throws"] == ["flick"] and fit["throws_from"] == "real"
    assert fit["left_out"] == {"flick_fast": "the goal's own throw",
                               "flick_wide": "the chain rope never hits itself under it"}
    assert fit["loss_fitted"] < fit["loss_measured"]
    assert sorted(ChainEngine.runs_by_path[:3]) == ["flick", "flick_fast", "flick_wide"]  # 2 fit throws + the goal
    assert ChainEngine.runs_by_path.count("flick") == 1 and ChainEngine.runs_by_path.count("flick_fast") == 1
    assert len(list((out / "fit-throws").glob("trial-*.npz"))) == 2 and not (out / "start").exists()
    assert done["start"]["recorded_pair"]["source"] == "the fit throw recorded before the trials"
    assert done["settings"]["fit_throws"] == "real" and fit["engine"] == "chain"

    (out / "correct.json").unlink()  # a resumed run reads its fit throws, goal and trials back: nothing runs again
    ChainEngine.runs_by_path = []
    assert main(["correct", "rope", "--resume", "--quiet", "--no-record", "--out", str(out)]) == 0
    again = json.loads((out / "correct.json").read_text())
    assert ChainEngine.runs_by_path == [] and again["model"]["fit"]["values"] == fit["values"]
    assert [t["error"] for t in again["runs"]["fitted"]["trials"]] == [
        t["error"] for t in done["runs"]["fitted"]["trials"]]

    # on newton too the goal's throw is left out of the fit; the coarse stand-in has no throws of its own
    ns = argparse.Namespace(fit_throws="real", real="fine", engine="newton", variant="default", builtin_throws=True)
    throws, dropped, _ = correct_cli._fit_throws(ns, PATHS["flick_wide"], tmp_path, lambda m: None)
    assert list(throws) == ["flick", "flick_fast"] and dropped == {"flick_wide": "the goal's own throw"}
    assert main(CORRECT_QUICK + ["--fit-throws", "real", "--out", str(tmp_path / "coarse")]) == 2
    assert "no throws of its own" in capsys.readouterr().err

    newton = tmp_path / "newton"
    assert main(cmd + ["--fit-throws", "newton", "--out", str(newton)]) == 0
    fit_n = json.loads((newton / "correct.json").read_text())["model"]["fit"]
    assert fit_n["throws"] == ["flick", "flick_fast", "flick_wide"] and fit_n["left_out"] == {}
    assert fit_n["values"] != fit["values"]

    # a run saved before --fit-throws existed was fitted to newton's throws: it resumes so, and refuses "real"
    parser = argparse.ArgumentParser()
    correct_cli.add_arguments(parser)
    saved = json.loads((out / correct_cli.SETTINGS_FILE).read_text())
    del saved["fit_throws"], saved[correct_cli.DIGEST_KEY]  # as saved then: no digest either
    (tmp_path / correct_cli.SETTINGS_FILE).write_text(json.dumps(saved))
    args = parser.parse_args(["--resume", "--out", str(tmp_path)])
    correct_cli._restore_settings(args)
    assert args.fit_throws == "newton"
    with pytest.raises(InputError, match="fitted to the newton rope's throws"):
        correct_cli._restore_settings(parser.parse_args(["--resume", "--out", str(tmp_path), "--fit-throws", "real"]))

    monkeypatch.setattr(ChainEngine, "NO_HIT", ("flick", "flick_wide"))
    capsys.readouterr()
    assert main(cmd + ["--out", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err
    assert "--fit-throws" in err and "none of the fit throws" in err and "never hits itself" in err


def test_a_resume_reads_no_trial_recorded_for_another_command_or_rope(tmp_path, problem):
    """Stored trials are named by their command; each also carries a key of the command and the real rope it ran
    on. A file copied under another trial's name, or a folder whose run was on another rope (settings.json edited
    to another variant), is refused, naming the file, instead of being read as that trial."""
    from wrenorm.tasks.rope.control.correct import StoredTrials

    space = CommandSpace(PATHS["flick"])
    u0, u1 = np.zeros(space.dim), np.full(space.dim, 0.3)
    store = StoredTrials(CoarseRope(problem, problem.space.measured), tmp_path / "trials")
    first = store(space.decode(u0))
    store(space.decode(u1))
    again = StoredTrials(CoarseRope(problem, problem.space.measured), tmp_path / "trials")  # a resume
    assert np.array_equal(again(space.decode(u0)).markers, first.markers) and again.reused == 1
    other = StoredTrials(CoarseRope(problem, problem.space.measured * 1.5), tmp_path / "trials")  # another rope
    with pytest.raises(InputError, match="trial_key"):
        other(space.decode(u0))
    f0, f1 = store.file_for(space.decode(u0)), store.file_for(space.decode(u1))
    f0.write_bytes(f1.read_bytes())  # trial 2's file under trial 1's name
    with pytest.raises(InputError, match=f0.name):
        StoredTrials(CoarseRope(problem, problem.space.measured), tmp_path / "trials")(space.decode(u0))


def test_a_resume_refuses_settings_changed_since_the_run_wrote_them(tmp_path):
    """settings.json carries a digest: an edited value (another variant, a word where a number was) is refused in
    one line rather than read as the run's (the trials belong to the settings they ran with)."""
    import argparse

    from wrenorm.tasks.rope.control import correct_cli

    parser = argparse.ArgumentParser()
    correct_cli.add_arguments(parser)
    saved = {k: v for k, v in vars(parser.parse_args([])).items() if k not in correct_cli._NOT_SAVED}
    saved = json.loads(json.dumps(saved, default=str))
    f = tmp_path / correct_cli.SETTINGS_FILE
    f.write_text(json.dumps(saved | {"_digest": correct_cli._settings_digest(saved)}))
    correct_cli._restore_settings(parser.parse_args(["--resume", "--out", str(tmp_path)]))  # as written: accepted
    f.write_text(json.dumps(saved | {"variant": "stiff", "_digest": correct_cli._settings_digest(saved)}))
    with pytest.raises(InputError, match="changed since the run wrote it"):
        correct_cli._restore_settings(parser.parse_args(["--resume", "--out", str(tmp_path)]))
    f.write_text(json.dumps(saved | {"tolerance": "abc"}))  # a file without a digest (an older run): types checked
    with pytest.raises(InputError, match="tolerance"):
        correct_cli._restore_settings(parser.parse_args(["--resume", "--out", str(tmp_path)]))


def test_correct_says_what_it_cannot_steer_by(tmp_path, capsys):
    """The goal's own throw as the start is refused (nothing to correct); a perturbed start clipped to the command
    box is said; a chain that never hits itself (3 links) stops the run naming that, not the trust radius."""
    from wrenorm.cli import main

    assert main(["correct", "rope", "--start", "flick_high", "--goal", "flick_high", "--out", str(tmp_path / "g")]) == 2
    err = capsys.readouterr().err
    assert "--start" in err and "nothing to correct" in err and len(err.strip().splitlines()) == 1
    out = tmp_path / "p"
    assert main([*CORRECT_QUICK[:-4], "--max-trials", "1", "--perturb", "100", "--no-plan-first", "--method", "qp",
                 "--no-record", "--quiet", "--out", str(out)]) == 0
    assert "--perturb 100" in capsys.readouterr().err
    done = json.loads((out / "correct.json").read_text())
    assert max(abs(x) for x in done["start"]["command_u"]) <= 3.0 + 1e-9
    out = tmp_path / "c"
    assert main(["correct", "rope", "--segments", "3", "--params", "measured", "--generations", "3", "--popsize", "8",
                 "--max-trials", "2", "--no-record", "--quiet", "--out", str(out)]) == 0
    run = json.loads((out / "correct.json").read_text())["runs"]["measured"]
    assert run["stop_reason"] == "chain_never_hits" and "does not hit itself" in run["stopped"]
    assert run["trials_used"] == 1
    assert "3 links" in (out / "report.md").read_text()


def test_the_report_divides_a_refit_by_the_measured_values_as_its_column_says():
    """The column "parameters changed (x measured)" divided the refit by the run's start values, the fitted ones in the
    default arm (a probe of stop 47): it divides by the refit's prior centre, the measured values."""
    from wrenorm.tasks.rope.control.correct_cli import TRIAL_COLUMNS, trial_cells

    trial = {"trial": 1, "error": 0.3, "predicted_error": None, "model_alone_error": None, "accepted": True,
             "measured_state": {"self_collision": False}, "trust_radius": 1.0, "trust": {},
             "refit": {"values": {"bend_stiffness": 0.06, "radius": 0.005}, "loss_before": 1.0, "loss": 0.5}}
    run = {"parameters": {"bend_stiffness": 0.02, "radius": 0.005}, "trials": [trial],
           "renormalise": {"prior_centre": {"bend_stiffness": 0.03, "radius": 0.005}}}
    cells = trial_cells({"runs": {"arm": run}}, "arm")
    assert TRIAL_COLUMNS[-1] == "parameters changed (x measured)" and cells[0][-1] == "bend_stiffness 2"


def test_the_report_names_its_start_seed_and_budget_and_does_not_blame_the_model_for_a_spent_budget():
    """A run from another start read like one from flick, and a 3-trial budget that ran out was said to be "stopped
    by the model" (a probe of stop 47)."""
    from wrenorm.tasks.rope.control.correct_cli import report_markdown

    trial = {"trial": 3, "error": 0.34, "predicted_error": 0.1, "model_alone_error": None, "accepted": False,
             "measured_state": {"self_collision": False}, "trust_radius": 1.0, "trust": {},
             "next_step": {"model_floor": {"error": 0.0744}}}
    run = {"success": False, "trials_used": 3, "best_error": 0.2, "method": "gn", "parameters": {},
           "trials": [trial]}
    text = report_markdown({"variant": "soft", "goal": {"path": "flick_high"}, "start": {"path": "flick_wide"},
                            "settings": {"seed": 73}, "max_trials": 3, "real_system": "newton", "model":
                            {"segments": 10}, "tolerance": 0.05, "error_meaning": "e", "runs": {"fitted": run}})
    assert "from flick_wide" in text and "seed 73" in text and "at most 3 trials" in text
    assert "when its last trial was planned" in text and "stopped it" not in text


def test_a_run_saved_when_by_arm_kept_three_velocity_modes_resumes_with_three(tmp_path):
    """By arm, the renormalised arms' steps kept 3 velocity modes in stop 49 and keep secant.VELOCITY_MODES (2) since
    stop 50. A run saved then resumes as it ran (3 modes in its renormalised arms, every row in its fixed ones), and
    the line that repeats it says so where one number can; a run saved today keeps today's by-arm number."""
    import argparse

    from wrenorm.tasks.rope.control import correct_cli
    from wrenorm.tasks.rope.control.secant import VELOCITY_MODES

    assert VELOCITY_MODES == 2
    parser = argparse.ArgumentParser()
    correct_cli.add_arguments(parser)
    stop49 = {k: v for k, v in vars(parser.parse_args([])).items() if k not in correct_cli._NOT_SAVED}
    assert stop49["velocity_modes"] == "by-arm" and correct_cli.BY_ARM_MODES_KEY not in stop49
    for params, arms in ((["renormalised-from-fitted"], {"renormalised-from-fitted": 3}),
                         (["renormalised-from-fitted", "measured"], {"renormalised-from-fitted": 3, "measured": None})):
        (tmp_path / correct_cli.SETTINGS_FILE).write_text(json.dumps(stop49 | {"params": params}))
        args = parser.parse_args(["--resume", "--out", str(tmp_path)])
        correct_cli._restore_settings(args)
        assert {label: correct_cli._step_options(args, label)["velocity_modes"] for label in params} == arms
        line = shlex.split(correct_cli.reproduce_command(args))
        # one number says it where every arm that steps renormalises; beside a fixed arm (every row) none can
        assert ("--velocity-modes" in line) == (len(params) == 1)
        if len(params) == 1:
            assert line[line.index("--velocity-modes") + 1] == "3"
            again = parser.parse_args(line[5:])
            assert correct_cli._step_options(again, params[0])["velocity_modes"] == 3
    today = stop49 | {correct_cli.BY_ARM_MODES_KEY: VELOCITY_MODES}
    (tmp_path / correct_cli.SETTINGS_FILE).write_text(json.dumps(today))
    args = parser.parse_args(["--resume", "--out", str(tmp_path)])
    correct_cli._restore_settings(args)
    assert correct_cli._step_options(args, "renormalised-from-fitted")["velocity_modes"] == VELOCITY_MODES
    assert "--velocity-modes" not in correct_cli.reproduce_command(args)
    fresh = parser.parse_args([])  # not a resume: by arm is left to correct(), which gives VELOCITY_MODES
    assert correct_cli._step_options(fresh, "renormalised-from-fitted")["velocity_modes"] is None


def test_the_trust_norm_resumes_as_it_ran_and_needs_a_gauss_newton_step(tmp_path):
    """--trust-norm: a run saved before the option stepped in a box and resumes so, refusing a ball; a run saved with
    the ball resumes with it and its reproduce line says so; only an arm that steps by Gauss-Newton takes it."""
    import argparse

    from wrenorm.tasks.rope.control import correct_cli

    parser = argparse.ArgumentParser()
    correct_cli.add_arguments(parser)
    fresh = {k: v for k, v in vars(parser.parse_args([])).items() if k not in correct_cli._NOT_SAVED}
    assert fresh["trust_norm"] == "box"
    stop50 = {k: v for k, v in fresh.items() if k != "trust_norm"}
    (tmp_path / correct_cli.SETTINGS_FILE).write_text(json.dumps(stop50))
    args = parser.parse_args(["--resume", "--out", str(tmp_path)])
    correct_cli._restore_settings(args)
    assert correct_cli._step_options(args, "renormalised-from-fitted")["trust_norm"] == "box"
    with pytest.raises(InputError, match="stepped inside a box"):
        correct_cli._restore_settings(parser.parse_args(["--resume", "--out", str(tmp_path), "--trust-norm", "ball"]))
    ball = fresh | {"trust_norm": "ball"}
    (tmp_path / correct_cli.SETTINGS_FILE).write_text(json.dumps(ball))
    args = parser.parse_args(["--resume", "--out", str(tmp_path)])
    correct_cli._restore_settings(args)
    assert correct_cli._step_options(args, "measured")["trust_norm"] == "ball"
    line = shlex.split(correct_cli.reproduce_command(args))
    assert line[line.index("--trust-norm") + 1] == "ball"
    correct_cli._check_step_options(parser.parse_args(["--trust-norm", "ball"]))
    with pytest.raises(InputError, match="trust_norm"):
        correct_cli._check_step_options(parser.parse_args(["--method", "plan", "--trust-norm", "ball"]))


def test_a_resume_refuses_a_params_file_rewritten_since_the_run_read_it(tmp_path):
    """A --params result.json rewritten under the same name had a resume throw the stored trials away and throw
    every trial again on the new model (real trials, on a robot; review of stop 54): its content is kept in
    settings.json and compared, naming the file. A run saved before that resumes unchecked."""
    import argparse

    from wrenorm.cli import content_hashes
    from wrenorm.tasks.rope.control import correct_cli

    model = tmp_path / "model.json"
    model.write_text('{"parameters": "the model the trials were planned on"}')
    parser = argparse.ArgumentParser()
    correct_cli.add_arguments(parser)
    args = parser.parse_args(["--params", str(model)])
    saved = json.loads(json.dumps({k: v for k, v in vars(args).items() if k not in correct_cli._NOT_SAVED},
                                  default=str))
    saved[correct_cli.PARAMS_HASHES_KEY] = content_hashes([str(model)])
    f = tmp_path / correct_cli.SETTINGS_FILE
    f.write_text(json.dumps(saved | {"_digest": correct_cli._settings_digest(saved)}))
    resume = ["--resume", "--out", str(tmp_path)]
    correct_cli._restore_settings(parser.parse_args(resume))  # the same file: accepted
    model.write_text('{"parameters": "another fit"}')
    with pytest.raises(InputError) as e:
        correct_cli._restore_settings(parser.parse_args(resume))
    assert e.value.source == str(model) and e.value.field == "--params" and "is not the file" in e.value.problem
    older = {k: v for k, v in saved.items() if k != correct_cli.PARAMS_HASHES_KEY}
    f.write_text(json.dumps(older | {"_digest": correct_cli._settings_digest(older)}))
    correct_cli._restore_settings(parser.parse_args(resume))


def test_a_truncated_stored_trial_is_one_line_on_resume(tmp_path, problem):
    """A stored trial cut short (a full disk, a copy interrupted) had ended a resume in a BadZipFile traceback (review
    of stop 54): it is named, with what to do."""
    from wrenorm.tasks.rope.control.correct import StoredTrials

    space = CommandSpace(PATHS["flick"])
    path = space.decode(np.zeros(space.dim))
    store = StoredTrials(CoarseRope(problem, problem.space.measured), tmp_path / "trials")
    store(path)
    f = store.file_for(path)
    f.write_bytes(f.read_bytes()[:100])
    with pytest.raises(InputError) as e:
        StoredTrials(CoarseRope(problem, problem.space.measured), tmp_path / "trials")(path)
    assert e.value.source == str(f) and e.value.field == "file"
    assert "remove it to run that trial again" in e.value.problem


@pytest.mark.parametrize("extra, said", [
    (["--method", "qp", "--fd-step", "1e300"], "--fd-step: fd_step: must be a finite number > 0 and at most 6"),
    (["--velocity-weight", "1e300"], "--velocity-weight: velocity_weight: must be at most 1000"),
    (["--radius", "1e300"], "--radius: radius: must be a finite number > 0 and at most 6"),
    (["--perturb", "1e300"], "--perturb: perturb: must be a finite number in [0, 1000]"),
    (["--dt", "0"], "--dt: dt: 0 s is outside"),
])
def test_absurd_numbers_are_refused_before_any_trial(tmp_path, capsys, extra, said):
    """1e300 had wasted a trial (--fd-step), failed an SVD after trial 1 (--velocity-weight), overflowed (--perturb) or
    been printed as a 300-digit radius; --dt 0 was refused by the chain only after the goal throw (review of stop
    54)."""
    from wrenorm.cli import main

    out = tmp_path / "run"
    assert main([*CORRECT_QUICK, *extra, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert said in err and err.count("\n") == 1 and not out.exists()


def test_params_files_that_would_share_a_name_or_do_not_hold_a_fit_are_refused_before_any_trial(tmp_path, capsys):
    """Every fit writes result.json: two of them made both arms write real-trials/result-trial-NN.json, one over the
    other; a bad file in the second arm was found only after the first arm's trials (review of stop 54)."""
    from wrenorm.cli import main

    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "result.json").write_text("{}")
    out = tmp_path / "run"
    two = [*CORRECT_QUICK[:-6], "--params", str(tmp_path / "a" / "result.json"), str(tmp_path / "b" / "result.json"),
           "--no-record", "--quiet", "--out", str(out)]
    assert main(two) == 2
    err = capsys.readouterr().err
    assert "would be named 'result'" in err and err.count("\n") == 1 and not out.exists()
    bad = [*CORRECT_QUICK[:-6], "--params", "measured", str(tmp_path / "a" / "result.json"), "--no-record", "--quiet",
           "--out", str(out)]
    assert main(bad) == 2
    err = capsys.readouterr().err
    assert str(tmp_path / "a" / "result.json") in err and err.count("\n") == 1
    assert not (out / "real-trials").exists() or not any((out / "real-trials").iterdir())
