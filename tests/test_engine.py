"""The engine's shared pieces: the one Jacobian, the one batched CMA-ES and its plain-format resume."""
import json

import numpy as np
import pytest

from wrenorm.cmaes import BatchedCMAES
from wrenorm.errors import InputError
from wrenorm.jacobian import jacobian


def test_central_jacobian_on_a_known_map():
    A = np.array([[1.0, 2.0, 0.0], [0.0, -1.0, 0.0]])
    f = lambda X: X @ A.T + 0.5 * X[:, :1] ** 2  # noqa: E731
    jac = jacobian(f, np.array([0.0, 0.3, 1.0]), 1e-3, np.zeros(3), np.ones(3))
    J, kinds = jac.J, jac.kinds
    assert kinds == ["forward", "central", "backward"]
    assert np.allclose(J, A + np.array([[0.0005, 0, 0], [0.0005, 0, 0]]), atol=1e-6)
    assert jac.evaluations == 7


def test_jacobian_falls_back_where_a_side_has_no_value():
    def f(X):
        out = X.copy()
        out[X[:, 0] > 0.5] = np.nan  # the + side of the first coordinate blows up
        return out
    jac = jacobian(f, np.array([0.5, 0.5]), 0.1)
    assert jac.kinds == ["backward", "central"]
    assert np.allclose(jac.J, np.eye(2))


def _sphere(X):
    return np.sum((X - 0.3) ** 2, axis=1)


def test_batched_searches_converge_and_stop_on_their_own():
    es = BatchedCMAES(np.full((3, 2), 0.8), 0.2, 0.0, 1.0, seeds=[1, 2, 3], popsize=8, max_generations=80)
    gens = 0
    while not es.done:
        X = es.ask()
        assert X.shape[0] == 8 * len(set(es.owners.tolist()))
        es.tell(_sphere(X))
        gens += 1
    for s in es.finish():
        assert s.best_loss < 1e-8 and np.allclose(s.best_x, 0.3, atol=1e-4)
    assert gens <= 80


def test_a_search_whose_whole_generation_blows_up_stops_alone():
    es = BatchedCMAES(np.full((2, 2), 0.5), 0.2, 0.0, 1.0, seeds=[1, 2], popsize=6, max_generations=5)
    X = es.ask()
    losses = _sphere(X)
    losses[es.owners == 0] = np.nan
    es.tell(losses)
    assert es.searches[0].failed and es.active == [1]
    assert "every one of 6 candidates blew up" in es.searches[0].stop


def _run(es, gens):
    for _ in range(gens):
        X = es.ask()
        loss = _sphere(X)
        loss[::5] = np.inf  # blow-ups are part of the state too
        es.tell(loss)


def test_replayed_state_continues_bit_identically_and_refuses_other_settings():
    make = lambda seeds=(4, 5): BatchedCMAES(np.full((2, 3), 0.7), 0.25, 0.0, 1.0, list(seeds), 10, 40)  # noqa: E731
    a = make()
    _run(a, 12)
    state = json.loads(json.dumps(a.state()))  # survives a plain JSON round trip
    _run(a, 6)
    b = make()
    b.replay(state)
    _run(b, 6)
    for sa, sb in zip(a.finish(), b.finish()):
        assert sa.best_loss == sb.best_loss and np.array_equal(sa.best_x, sb.best_x)
        assert sa.blowups == sb.blowups and sa.generations == sb.generations
    with pytest.raises(InputError, match="other seeds"):
        make((4, 6)).replay(state)
    state["told"][0][3]["candidates"] = "0" * 16
    with pytest.raises(InputError, match="other candidates"):
        make().replay(state)
    with pytest.raises(InputError, match="not a wrenorm search state"):
        make().replay({"schema": "something else"})


def test_population_wide_bound_transform_asks_exactly_what_pycma_asks(monkeypatch):
    """BatchedCMAES maps a whole population into the box at once (wrenorm.cmaes._ask); pycma's own ask maps one
    candidate at a time. Same seeds, a start near the box's corner and a wide step, so that most candidates are
    folded back: every candidate and every search's best must agree to the bit."""
    from wrenorm import cmaes

    def run(ask):
        monkeypatch.setattr(cmaes, "_ask", ask)
        es = BatchedCMAES(np.array([[0.02, 0.97, 0.5, 0.5], [0.9, 0.1, 0.05, 0.95]]), 0.6, [0, -1, 0, 2], [1, 1, 3, 4],
                          [11, 12], 12, 25)
        asked = []
        while not es.done:
            X = es.ask()
            asked.append(X)
            es.tell(_sphere(X - 0.3))
        return asked, es.finish()

    fast, fast_end = run(cmaes._ask)
    slow, slow_end = run(lambda es: np.asarray(es.ask()))
    assert len(fast) == len(slow) == 25
    assert all(np.array_equal(a, b) for a, b in zip(fast, slow))
    X = np.concatenate(slow)
    near_a_bound = (X - np.array([0, -1, 0, 2]) < 0.05) | (np.array([1, 1, 3, 4]) - X < 0.05)
    assert near_a_bound.mean() > 0.05  # the box's quadratic margins are in play
    for a, b in zip(fast_end, slow_end):
        assert a.best_loss == b.best_loss and np.array_equal(a.best_x, b.best_x)


def test_width_is_set_by_the_device_kind_never_its_size():
    from wrenorm.cli import search_width
    from wrenorm.system import get

    rope = get("rope")
    assert search_width(rope, "cpu", None, None, 6) == (1, None)  # the CPU keeps one search, today's wall time
    d = rope.search
    assert search_width(rope, "cuda:0", None, None, 6) == (d.wide_searches, d.wide_popsize_factor * 9)  # 4+3ln6
    assert search_width(rope, "cuda:1", None, None, 6) == search_width(rope, "cuda:0", None, None, 6)
    assert search_width(rope, "cuda:0", 3, 10, 6) == (3, 10)  # options win
    assert search_width(rope, "cuda:0", None, 10, 6) == (d.wide_searches, 10)


def test_searches_side_by_side_report_their_spread_and_each_optimum_is_validated(tmp_path):
    import json

    from wrenorm.cli import build_parser, main
    from wrenorm.system import get, resolve

    out = tmp_path / "wide"
    argv = ["fit", "pd", "--search", "cmaes", "--searches", "3", "--generations", "8", "--no-record", "--quiet",
            "--out", str(out)]
    assert main(argv) == 0
    r = json.loads((out / "result.json").read_text())
    spread = r["searches_spread"]
    assert [o["seed"] for o in spread["optima"]] == [0, 1000, 2000]
    best = min(spread["optima"], key=lambda o: o["train_loss"])
    assert best["values"] == {n: p["fitted"] for n, p in r["parameters"].items()}
    prob = resolve(get("pd").build)(build_parser(argv).parse_args(argv), "cpu")[0]
    for o in spread["optima"]:  # held-out errors re-evaluated here, one optimum at a time
        v = np.array([o["values"][n] for n in prob.space.names])
        again = prob.validation_errors(v[None], prob.held_out)[0][0]
        np.testing.assert_allclose(list(o["held_out_errors"].values()), again, rtol=1e-12)
    lo, hi = spread["held_out_mean_error_range"]
    assert lo <= best["held_out_mean_error"] <= hi
    assert set(spread["pinned"]) | set(spread["not_pinned"]) == {p.name for p in prob.space.free}


# ------------------------------------------------------------------------------ weighted conditions, starts
class _Quadratic:
    """A Problem whose every condition c pulls the one parameter toward its own target c.meta["at"]."""

    task = "toy"

    def __init__(self, targets, weights=None, prior=None):
        from wrenorm.params import Parameter, ParameterSpace
        from wrenorm.problem import Condition

        self.space = ParameterSpace([Parameter("x", 0.5, 0.0, 1.0, prior=prior),
                                     Parameter("y", 0.5, 0.0, 1.0)])
        self.train = [Condition(f"c{i}", None, {"at": t} | ({} if weights is None else {"weight": weights[i]}))
                      for i, t in enumerate(targets)]

    def errors(self, values, conditions):
        v = np.atleast_2d(values)
        return np.stack([(v[:, 0] - c.meta["at"]) ** 2 + (v[:, 1] - 0.5) ** 2 for c in conditions], 1)


def test_mean_loss_weights_conditions_and_adds_the_prior():
    from wrenorm.search import mean_loss

    plain = _Quadratic([0.2, 0.8])
    weighted = _Quadratic([0.2, 0.8], weights=[3.0, 1.0])
    x = np.array([[0.2, 0.5]])
    assert np.isclose(mean_loss(plain, x, plain.train)[0][0], 0.5 * 0.36)
    assert np.isclose(mean_loss(weighted, x, weighted.train)[0][0], 0.25 * 0.36)
    with_prior = _Quadratic([0.2, 0.8], weights=[3.0, 1.0], prior=(0.5, 0.1))
    assert np.isclose(mean_loss(with_prior, x, with_prior.train)[0][0], 0.25 * 0.36 + 9.0)
    bad = _Quadratic([0.2], weights=[-1.0])
    with pytest.raises(ValueError):
        mean_loss(bad, x, bad.train)


def test_weighted_fit_lands_at_the_weighted_optimum_from_several_starts():
    from wrenorm.search import cmaes

    p = _Quadratic([0.2, 0.8], weights=[3.0, 1.0])
    res = cmaes(p, seed=0, popsize=8, generations=80, start=np.array([[0.9, 0.9], [0.1, 0.1]]), quiet=True)
    assert np.allclose(res.best_values, [0.35, 0.5], atol=1e-3)  # 3/4 of the way to 0.2
    assert len(res.history[-1]["optima"]) == 2  # one search per start, side by side
