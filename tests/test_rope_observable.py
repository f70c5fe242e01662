"""The rope's observable runs in Warp kernels (kernels/rope/critical.py) on the chains' device; here it is held
to the plain-numpy oracle (tests/rope_observable_oracle.py) on real rollouts and on the edge cases: chains that
never hit, blow-ups, a hit after its condition's horizon, a NaN clearance."""
import numpy as np
import pytest
import rope_observable_oracle as oracle

from wrenorm.tasks.rope import observable as crit
from wrenorm.tasks.rope.problem import RopeProblem
from wrenorm.tasks.rope.reference.generate import builtin_references

RTOL = 1e-10


@pytest.fixture(scope="module")
def problem():
    refs = builtin_references("fit")
    return RopeProblem(refs[:2], refs[2:], segments=10, dt=0.005, device="cpu", names=["a", "b"],
                       held_names=["c"])


@pytest.fixture(scope="module")
def candidates(problem):
    rng = np.random.default_rng(7)
    u = np.clip(problem.space.to_unit(problem.space.measured)[None] + rng.normal(0, 0.3, (24, len(problem.space.free))),
                0, 1)
    return problem.space.from_unit(u)


def _close(a, b):
    np.testing.assert_allclose(a, b, rtol=RTOL, atol=1e-12, equal_nan=True)


def test_chain_states_equal_the_numpy_extraction_and_resampling(problem, candidates):
    conds = problem.train + problem.held_out
    res = problem.simulate(candidates, conds)
    assert 0 < np.mean(res.status == 1) < 1  # hits and misses both exercised
    got, want = crit.from_rollout(res, problem.n, 0.0), oracle.from_rollout(res, problem.n, 0.0)
    np.testing.assert_array_equal(got.hit, want.hit)
    for f in ("pos", "vel", "time", "clearance"):
        _close(getattr(got, f), getattr(want, f))
    _close(got.s[got.hit], want.s[want.hit])


def test_terms_and_residuals_equal_the_oracle_for_every_condition(problem, candidates):
    conds = problem.train + problem.held_out
    B, C = len(candidates), len(conds)
    res = problem.simulate(candidates, conds)
    st = oracle.from_rollout(res, problem.n, 0.0)
    terms = problem.error_terms(candidates, conds)
    resid = problem.residuals(candidates, conds).reshape(B, C, -1)
    for j, c in enumerate(conds):
        rows = st.take(np.arange(B) * C + j)
        want = oracle.terms(c.data.target, rows)
        for k in ("shape", "velocity", "time", "place"):
            _close(terms[k][:, j], want[k])
        total = np.where(res.status.reshape(B, C)[:, j] == 2, np.inf, want["total"])
        _close(terms["total"][:, j], total)
        _close(resid[:, j], oracle.residual(c.data.target, rows))
        # the host path (correction, planner) is the same kernel
        _close(c.data.target.terms(rows)["total"], want["total"])
        _close(c.data.target.residual(rows), oracle.residual(c.data.target, rows))


def test_misses_blowups_and_a_nan_clearance_cost_the_one_no_hit_rule(problem):
    target = problem.train[0].data.target
    K = crit.SAMPLES
    nan = np.full((4, K, 3), np.nan)
    st = crit.CriticalStates(nan, nan.copy(), np.full(4, np.nan), np.full((4, 2), np.nan), np.zeros(4, bool),
                             np.array([0.0, 0.02, np.inf, np.nan]))
    got = target.terms(st)["total"]
    _close(got, oracle.terms(target, st)["total"])
    assert got[0] == crit.NO_HIT and got[2] == got[3] == crit.NO_HIT + 1.0
    assert np.all(np.isnan(target.residual(st)))


def test_a_hit_after_its_conditions_horizon_counts_as_none(problem):
    from wrenorm.kernels.rope import critical

    conds = problem.train[:1]
    m = problem.space.measured[None]
    res = problem.simulate(m, conds, host=False)
    states = critical.chain_states(res.events, [0], [10**6], res.dt, 0.0, crit.SAMPLES)
    assert states.status.numpy()[0] == 1
    frame = int(res.events.hit_frame.numpy()[0])
    early = critical.chain_states(res.events, [0], [frame - 1], res.dt, 0.0, crit.SAMPLES)
    assert early.status.numpy()[0] == 0 and np.isnan(early.time.numpy()[0])


def test_state_error_is_the_terms_with_the_contact_where_the_target_has_it(problem):
    target = problem.train[0].data.target
    rng = np.random.default_rng(3)
    pos = target.state.pos[0] + rng.normal(0, 0.01, target.state.pos[0].shape)
    vel = target.state.vel[0] + rng.normal(0, 0.1, target.state.vel[0].shape)
    _close(target.state_error(pos, vel, 0.7), oracle.state_error(target, pos, vel, 0.7))
