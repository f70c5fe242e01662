"""The System contract, checked on every registered system, and a toy system added the way a newcomer would:
one new folder plus one registry line."""
import argparse
import json
import sys
import textwrap

import numpy as np
import pytest

from wrenorm import system as registry
from wrenorm.cli import build_parser, main
from wrenorm.search import mean_loss
from wrenorm.system import resolve

SYSTEMS = list(registry.systems())


@pytest.fixture(scope="module", params=SYSTEMS)
def built(request):
    s = registry.systems()[request.param]
    args = build_parser(["fit", s.name]).parse_args(["fit", s.name])
    return s, resolve(s.build)(args, "cpu")


def test_registry_lists_the_three_systems():
    assert {"pd", "rope", "swimmer"} <= set(SYSTEMS)


def test_the_parameter_names_said_without_a_problem_are_the_built_problems(built):
    """A sweep and `fit` check --free/--freeze names with System.parameter_names before building anything."""
    s, problems = built
    args = build_parser(["fit", s.name]).parse_args(["fit", s.name])
    assert registry.parameter_names(s, args) == problems[0].space.names
    if s.name == "pd":
        from wrenorm.tasks.pd.arm import ArmProblem

        arm = build_parser(["fit", "pd"]).parse_args(["fit", "pd", "--arm"])
        assert registry.parameter_names(s, arm) == ArmProblem(400.0).space.names != problems[0].space.names


def test_errors_are_one_per_candidate_and_condition(built):
    _, problems = built
    p = problems[0]
    rng = np.random.default_rng(0)
    U = np.clip(p.space.to_unit(p.space.measured)[None] + rng.normal(0, 0.05, (3, len(p.space.free))), 0, 1)
    values = p.space.from_unit(U)
    for group in (p.train, p.held_out):
        if group:
            e = p.errors(values, group)
            assert e.shape == (3, len(group))
    e0 = p.errors(p.space.measured[None], p.train)
    assert np.all(np.isfinite(e0)) and np.all(e0 >= 0)


def test_a_blown_up_candidate_costs_only_itself(built):
    _, problems = built
    p = problems[0]
    good = p.space.measured.copy()
    bad = good.copy()
    bad[p.space.index(p.space.free[0].name)] = np.nan
    batch = p.errors(np.stack([good, bad, good]), p.train)
    alone = p.errors(good[None], p.train)
    assert not np.all(np.isfinite(batch[1]))
    np.testing.assert_array_equal(batch[0], alone[0])
    np.testing.assert_array_equal(batch[2], alone[0])
    assert np.isinf(mean_loss(p, np.stack([good, bad]), p.train)[0][1])


def test_residuals_agree_with_errors(built):
    """Where a system exposes residuals, each condition owns an equal block of them, a perfect candidate's
    residuals and errors vanish together, and the two rank candidates alike (a wiring check)."""
    _, problems = built
    p = problems[0]
    if not p.has_residuals:
        pytest.skip(f"{p.task} exposes no residual vector")
    rng = np.random.default_rng(1)
    U = np.clip(p.space.to_unit(p.space.measured)[None] + rng.normal(0, 0.15, (8, len(p.space.free))), 0, 1)
    values = p.space.from_unit(U)
    r = p.residuals(values, p.train)
    e = p.errors(values, p.train)
    assert r.shape[0] == 8 and r.shape[1] % len(p.train) == 0
    blocks = r.reshape(8, len(p.train), -1)
    hit = np.all(np.isfinite(blocks), axis=2) & np.isfinite(e)
    assert hit.sum() >= 4
    norms = np.linalg.norm(blocks, axis=2)
    order = lambda x: np.argsort(np.argsort(x))  # noqa: E731
    for c in range(len(p.train)):
        rows = hit[:, c]
        if rows.sum() >= 4:
            rho = np.corrcoef(order(norms[rows, c]), order(e[rows, c]))[0, 1]
            assert rho > 0.7, (p.task, c, rho)


def test_bad_options_exit_2_naming_the_option(tmp_path, capsys):
    for name in SYSTEMS:
        assert main(["fit", name, "--generations", "0", "--out", str(tmp_path / name)]) == 2
        err = capsys.readouterr().err
        assert "--generations" in err and err.count("\n") == 1 and "Traceback" not in err
        assert main(["fit", name, "--free", "no_such_parameter", "--out", str(tmp_path / name)]) == 2
        assert "no_such_parameter" in capsys.readouterr().err
        assert not (tmp_path / name).exists()  # refused before anything was written


@pytest.mark.parametrize("name", SYSTEMS)
def test_a_tiny_fit_runs_end_to_end(tmp_path, name):
    out = tmp_path / name
    assert main(["fit", name, "--generations", "2", "--popsize", "6", "--restarts", "0", "--polish", "0", "--quiet",
                 "--no-record", "--out", str(out)]) == 0
    result = json.loads((out / "result.json").read_text())
    runs = result.get("runs", [result])
    assert all(r["validation"]["verdict"] in ("absorbed", "expand", "unvalidated") for r in runs)
    assert all(set(r["parameters"]) for r in runs)


TOY = {
    "__init__.py": '''
        """A toy system: a line y = a x + b through noisy points."""
        from wrenorm.system import Flow, SearchDefaults, from_package


        def add_flow_arguments(p):  # the engine adds --resolutions; the toy's flow has no options of its own
            pass


        SYSTEM = from_package(__name__, "fit a line", search=SearchDefaults(generations=30),
                              flow=Flow(add_flow_arguments, "toy.problem:flow_problems", "points", generations=20))
    ''',
    "options.py": '''
        from wrenorm.options import add_number


        def add_arguments(p):
            add_number(p, "--noise", default=0.01, lo=0.0, hi=1.0, help="noise of the points")
            p.add_argument("--weights", default=None, metavar="FILE.txt", help="a file of point weights (read only)")
    ''',
    "problem.py": '''
        import numpy as np

        from wrenorm.params import Parameter, ParameterSpace
        from wrenorm.problem import Condition, Problem


        class Line(Problem):
            task = "toy"

            def __init__(self, noise, points=20):
                x = np.linspace(0, 1, points)
                y = 2.0 * x + 0.5 + noise * np.random.default_rng(0).normal(size=x.size)
                self.space = ParameterSpace([Parameter("a", 1.0, 0.0, 5.0), Parameter("b", 0.0, -2.0, 2.0)])
                self.train = [Condition("left", (x[::2], y[::2]))]
                self.held_out = [Condition("right", (x[1::2], y[1::2]))]
                self.tolerance, self.resolution = 0.05, {"points": points}

            def residuals(self, values, conditions):
                return np.concatenate([values[:, :1] * c.data[0] + values[:, 1:] - c.data[1] for c in conditions], 1)

            def errors(self, values, conditions):
                r = self.residuals(values, conditions).reshape(len(values), len(conditions), -1)
                return np.sqrt(np.mean(r ** 2, axis=2))


        def build_problems(args, device):
            return [Line(args.noise)]


        def flow_problems(args, device):
            return [Line(0.01, int(n)) for n in (args.resolutions or [40, 20, 10])]
    ''',
}


def test_a_new_system_is_one_folder_and_one_registry_line(tmp_path, monkeypatch):
    import wrenorm.tasks

    pkg = tmp_path / "toy"
    pkg.mkdir()
    for name, text in TOY.items():
        (pkg / name).write_text(textwrap.dedent(text))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(wrenorm.tasks, "SYSTEMS", wrenorm.tasks.SYSTEMS + ("toy",))  # the registry line
    monkeypatch.setattr(registry, "_LOADED", False)
    monkeypatch.setattr(registry, "_REGISTRY", {})
    try:
        out = tmp_path / "run"
        assert main(["fit", "toy", "--quiet", "--no-record", "--out", str(out)]) == 0
        result = json.loads((out / "result.json").read_text())
        assert result["parameters"]["a"]["fitted"] == pytest.approx(2.0, abs=0.05)
        assert result["validation"]["verdict"] == "absorbed"
        assert result["uncertainty"]["method"].startswith("gauss-newton")
        assert main(["fit", "toy", "--noise", "nan", "--out", str(tmp_path / "bad")]) == 2
        # the system's own input option (metavar FILE...) is an input like the engine's: --force never clears a
        # folder holding it, and a resume sees its content (it was neither)
        weights = out / "weights.txt"
        weights.write_text("1 1 1")
        assert main(["fit", "toy", "--quiet", "--no-record", "--weights", str(weights), "--out", str(out),
                     "--force"]) == 2
        assert weights.exists()
        # a resume after the system's code changed is refused (it mixed two problems' losses in silence)
        from wrenorm.cli import code_digest

        before = code_digest("toy")
        (pkg / "problem.py").write_text((pkg / "problem.py").read_text().replace("20)", "21)"))
        assert code_digest("toy") != before
        # recorded and reported like the built-in systems, with nothing system-specific written for either
        recorded = tmp_path / "recorded"
        assert main(["fit", "toy", "--quiet", "--out", str(recorded)]) == 0
        assert (recorded / "recording.rrd").read_bytes()[:4] == b"RRF2"
        page = (recorded / "report.html").read_text()
        assert "toy fit" in page and "absorbed" in page and "right" in page  # the system, verdict, held-out
        # a flow over the system's own resolution axis, one fit per point
        flow = tmp_path / "flow"
        assert main(["flow", "toy", "--resolutions", "40", "10", "--quiet", "--no-record", "--out", str(flow)]) == 0
        points = json.loads((flow / "flow.json").read_text())["points"]
        assert [p["resolution"]["points"] for p in points] == [40, 10]
        assert all(abs(p["parameters"]["a"]["fitted"] - 2.0) < 0.1 for p in points)
        # no bench.py: no kernel benchmark, said in one line (was a ModuleNotFoundError)
        assert registry.systems()["toy"].bench is None
        assert main(["bench", "--only", "toy", "--no-fits", "--no-cuda-build", "--out", str(tmp_path / "b")]) == 2
    finally:
        sys.modules.pop("toy", None)


def test_a_flow_parser_exists_only_for_systems_with_a_flow():
    with_flow = [n for n, s in registry.systems().items() if s.flow is not None]
    for name in with_flow:
        args = build_parser(["flow", name]).parse_args(["flow", name])
        assert isinstance(args, argparse.Namespace) and args.system == name
