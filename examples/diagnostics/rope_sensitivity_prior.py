"""How much of the correction's gap is the chain's sensitivity? Run the loop with the ROPE's own sensitivity as
its prior, or with a finer chain's, and compare the chain's sensitivity with the rope's (README, "How much of the gap
is the chain's sensitivity" and "Is a chain of 11 masses enough"). A diagnosis, not a method: the rope's sensitivity
costs 26 extra fine runs (real trials on a robot).

    python examples/diagnostics/rope_sensitivity_prior.py run --variant heavy --seed 4 --params fitted \\
        --linearise-at trial --no-record --out runs/oracle-heavy-s4
    python examples/diagnostics/rope_sensitivity_prior.py every-best --variant stiff --seed 0 \\
        --params renormalised-from-fitted --no-record --out runs/oracle-every-best-stiff-s0
    python examples/diagnostics/rope_sensitivity_prior.py chain 20 --variant heavy --seed 4 --params fitted \\
        --no-record --out runs/chain20-heavy-s4
    python examples/diagnostics/rope_sensitivity_prior.py compare runs/oracle-heavy-s4 [--segments 20]
        [--best-parameters [--also-free mass_slope stretch]]

`run` is `correct rope` (its options after `run`; fixed parameters, `--linearise-at trial`) with the chain's
central difference at trial 1's command replaced by the fine rope's (the same step, 26 fine runs, not counted as
trials), kept in OUT/rope-sensitivity.npz; the secant pairs then correct it as they correct the chain's.
`every-best` is `correct rope` (its options after `every-best`; any arm) with every step taken through the rope's own
central difference at the best trial's command, re-measured at each new best (27 fine runs each) and used as it is
(README, "The rope's own sensitivity at every best").
`chain N` is `correct rope` (its options after N; fixed parameters) with the chain's sensitivity and the match it is
measured at taken on an N-link chain fitted as the run's, trial 1 still planned on the run's own chain.
`compare` prints, per block of the critical state, how far the chain's sensitivity (fitted parameters, at trial 1's
command and where it matches trial 1's state; measured parameters at that match) lies from the rope's: the weighted
relative error (0 alike, 1 no better than zero) and the mean cosine of the columns (position and velocity).
`--segments N` asks the same of an N-link chain, its parameters fitted as the run's were (same throws, seed and
generations); `--best-parameters` adds the chain whose parameters were chosen to bring its sensitivity closest to the
rope's (on the answer itself: a bound on what the parameters can absorb at that resolution, not a method);
`--also-free NAME ...` repeats that bound with parameters the fit holds fixed set free as well, each set alone and all
together (README, "Is a chain of 11 masses enough": the mass profile and the links' compliance).
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from wrenorm.jacobian import jacobian
from wrenorm.tasks.rope import observable as crit
from wrenorm.tasks.rope.control import secant
from wrenorm.tasks.rope.control.correct_cli import builtin_is_the_real_rope, builtin_throws_of
from wrenorm.tasks.rope.control.plan import state_vector

FILE = "rope-sensitivity.npz"


def _fail(message: str) -> None:
    print(f"rope_sensitivity_prior: {message}", file=sys.stderr)
    sys.exit(2)


def _refit_matches_the_run(settings: dict, where: Path) -> None:
    """The refits here fit newton's three built-in throws, as the run's chain was unless it was fitted to the throws of
    another rope (another engine, or newton at another resolution) or its goal was one of them (correct rope
    --fit-throws real leaves the goal's out)."""
    from wrenorm.tasks.rope.reference.paths import FIT_PATHS

    if settings.get("fit_throws", "newton") == "real" and (not builtin_throws_of(settings)
                                                            or settings.get("goal") in FIT_PATHS):
        _fail(f"{where}: the run's chain was fitted to other throws than newton's built-in {', '.join(FIT_PATHS)} "
              f"(engine {settings.get('engine')}, {settings.get('fine_segments')} segments, goal "
              f"{settings.get('goal')}); this diagnostic refits to those")


def _option(argv: list[str], flag: str) -> str | None:
    """The value after `flag` (or in `flag=value`) in `correct rope`'s options, or None."""
    for i, a in enumerate(argv):
        if a.startswith(flag + "="):
            return a.split("=", 1)[1]
        if a == flag and i + 1 < len(argv):
            return argv[i + 1]
    return None


def _fixed_parameters_only(argv: list[str], command: str, why: str = "") -> None:
    """Both loops patch the sensitivity measured once per run; a renormalised arm re-measures it after every trial."""
    params = argv[argv.index("--params") + 1:] if "--params" in argv else []
    if any(a.startswith("renormalised") for a in params):
        _fail(f"{command} takes fixed parameters only (--params fitted or measured){why}")


def _on_builtin_rope(argv: list[str]) -> bool:
    """The run's real rope is newton's at the built-in references' resolution, the one measured here."""
    from wrenorm.tasks.rope.reference.generate import DEFAULT_SEGMENTS

    return (_option(argv, "--engine") in (None, "newton")
            and _option(argv, "--fine-segments") in (None, str(DEFAULT_SEGMENTS)))


def _rope_sensitivity(out: Path, ropes: dict, space, u: np.ndarray, step: float = secant.GN_FD_STEP):
    """The fine rope's central difference at u (2n + 1 fine runs): the loop's own fine rope is not reachable from
    here, so an equal one (the run's variant and segments, the CLI's horizon)."""
    from wrenorm.tasks.rope.control.correct import NewtonRope
    from wrenorm.tasks.rope.reference.generate import DEFAULT_SEGMENTS, builtin_reference_path, load_reference

    settings = json.loads((out / "settings.json").read_text())
    if not (builtin_throws_of(settings) and builtin_is_the_real_rope(settings)):
        _fail(f"{out / 'settings.json'}: the run's fine rope is not the built-in references' "
              f"{DEFAULT_SEGMENTS}-segment one")
    if "rope" not in ropes:
        goal_ref = load_reference(builtin_reference_path(settings["goal"], settings["variant"]))
        horizon = min(float(goal_ref.time[-1]), float(crit.from_reference(goal_ref).time[0]) + 0.5)
        ropes["rope"] = NewtonRope(settings["variant"], settings["fine_segments"], horizon, settings["device"])
    rope = ropes["rope"]

    def states(U):
        return np.concatenate([state_vector(crit.from_reference(rope(space.decode(x)))) for x in U])

    return jacobian(states, u, step, space.lower, space.upper)


def run(argv: list[str]) -> int:
    from wrenorm.cli import main
    from wrenorm.tasks.rope.reference.generate import DEFAULT_SEGMENTS

    if _option(argv, "--out") is None or _option(argv, "--linearise-at") != "trial" or not _on_builtin_rope(argv):
        _fail("run needs --out OUT and --linearise-at trial (the rope's sensitivity is measured at trial 1's "
              f"command), on the newton rope of the built-in references ({DEFAULT_SEGMENTS} segments)")
    out = Path(_option(argv, "--out"))
    _fixed_parameters_only(argv, "run", ": a renormalised arm re-measures its sensitivity after every trial, 26 fine "
                                        "runs each (every-best measures the rope's at each new best)")
    ropes = {}

    def of_rope(cls, model, u, step=secant.GN_FD_STEP):
        t = time.perf_counter()
        jac = _rope_sensitivity(out, ropes, model.space, u, step)
        J = np.where(np.isfinite(jac.J), jac.J, 0.0)
        np.savez(out / FILE, J=J, u=u, step=step)
        print(f"rope_sensitivity_prior: the rope's own sensitivity from {jac.evaluations} fine runs "
              f"({time.perf_counter() - t:.0f} s)", file=sys.stderr, flush=True)
        return cls(J.copy(), J, jac.kinds, 0, jac.evaluations, time.perf_counter() - t)

    secant.Sensitivity.of_chain = classmethod(of_rope)
    return main(["correct", "rope", *argv])


def every_best(argv: list[str]) -> int:
    """The loop, any arm, with every Gauss-Newton step taken through the rope's own central difference at the best
    trial's command, re-measured whenever the best changes and not corrected by the secant pairs: a perfect local
    linear model where each step starts. Everything else (trial 1, the refits, the trust region, the velocity modes)
    is the arm's own. Each is kept as OUT/rope-sensitivity-at-trial-NN.npz."""
    from wrenorm.cli import main
    from wrenorm.tasks.rope.reference.generate import DEFAULT_SEGMENTS

    if _option(argv, "--out") is None or not _on_builtin_rope(argv):
        _fail(f"every-best needs --out OUT, on the newton rope of the built-in references ({DEFAULT_SEGMENTS} "
              "segments)")
    out = Path(_option(argv, "--out"))
    ropes, current = {}, {}
    secant_pairs, ridge = secant.secant_pairs, secant.Sensitivity.ridge

    def pairs_from_best(trials, best, recorded, recorded_until):
        current["best"] = best  # the loop asks for the pairs from its best just before the step
        return secant_pairs(trials, best, recorded, recorded_until)

    def rope_in_place(self, dus, dzs, weight=secant.RIDGE, locality=None):
        ridge(self, dus, dzs, weight, locality)
        best = current["best"]
        if ropes.get("at") is not best:
            t = time.perf_counter()
            if "space" not in ropes:
                ropes["space"] = _space(out)
            jac = _rope_sensitivity(out, ropes, ropes["space"], best.u)
            ropes.update(at=best, J=np.where(np.isfinite(jac.J), jac.J, 0.0))
            np.savez(out / f"rope-sensitivity-at-trial-{best.index + 1:02d}.npz", J=ropes["J"], u=best.u)
            print(f"rope_sensitivity_prior: the rope's own sensitivity at trial {best.index + 1} from "
                  f"{jac.evaluations} fine runs ({time.perf_counter() - t:.0f} s)", file=sys.stderr, flush=True)
        self.S = ropes["J"].copy()

    secant.secant_pairs, secant.Sensitivity.ridge = pairs_from_best, rope_in_place
    return main(["correct", "rope", *argv])


def _space(out: Path):
    from wrenorm.tasks.rope.control.command import CommandSpace
    from wrenorm.tasks.rope.reference.paths import get_hand_path

    return CommandSpace(get_hand_path(json.loads((out / "settings.json").read_text())["start"]))


def chain(segments: int, argv: list[str]) -> int:
    """The loop with its sensitivity (and the match it is measured at) taken on a chain of `segments` links, fitted
    as the run's own chain is (the same throws, seed and generations); trial 1 is still the run's own chain's plan."""
    from wrenorm.cli import main
    from wrenorm.tasks.rope.control.correct import CoarseModel, fit_parameters
    from wrenorm.tasks.rope.problem import RopeProblem

    if _option(argv, "--out") is None:
        _fail("chain needs --out OUT")
    _fixed_parameters_only(argv, "chain")
    out = Path(_option(argv, "--out"))
    models = {}
    of_chain, matched_command = secant.Sensitivity.of_chain.__func__, secant.matched_command

    def other(model):
        if model.label not in models:
            settings = json.loads((out / "settings.json").read_text())
            problem = model.problem
            other_problem = RopeProblem([c.data.ref for c in problem.train], segments=segments, dt=settings["dt"],
                                        names=[c.name for c in problem.train])
            if model.label == "measured":
                values = other_problem.space.measured
            else:
                _refit_matches_the_run(settings, out / "settings.json")
                values, _ = fit_parameters(settings["variant"], segments, settings["dt"], settings["seed"],
                                           settings["fit_generations"], settings["device"])
            models[model.label] = CoarseModel(other_problem, values, model.space, f"{model.label}, {segments} links")
            print(f"rope_sensitivity_prior: the sensitivity from a {segments}-link chain ({model.label})",
                  file=sys.stderr, flush=True)
        return models[model.label]

    secant.Sensitivity.of_chain = classmethod(lambda cls, model, u, step=secant.GN_FD_STEP:
                                              of_chain(cls, other(model), u, step))
    secant.matched_command = lambda model, z, w, u, seed=0, reg=secant.MATCH_REG: matched_command(
        other(model), z, w, u, seed, reg)
    return main(["correct", "rope", *argv])


def _block_cells(goal, w: np.ndarray, P: np.ndarray, J: np.ndarray) -> str:
    cells = []
    for block, sl in list(goal.blocks.items()) + [("all", slice(None))]:
        A, B = w[sl, None] * P[sl], w[sl, None] * J[sl]
        rel = float(np.linalg.norm(A - B) / max(np.linalg.norm(B), 1e-15))
        cell = f"{block} {rel:.2f}"
        if block in ("position", "velocity"):
            keep = np.linalg.norm(B, axis=0) > 1e-9
            cos = np.sum(A * B, 0)[keep] / (np.linalg.norm(A, axis=0) * np.linalg.norm(B, axis=0) + 1e-15)[keep]
            cell += f" ({float(np.mean(cos)):.2f})"
        cells.append(cell)
    return ", ".join(cells)


def best_parameters(model, J: np.ndarray, w: np.ndarray, u: np.ndarray, step: float, seed: int,
                    generations: int = 40, popsize: int = 24) -> tuple[np.ndarray, float]:
    """The chain's parameters whose sensitivity at u lies closest to the rope's J (weighted relative error), by
    CMA-ES over the free parameters. Chosen on the answer: a bound on what parameters can absorb, not a method.
    A candidate whose chain misses on either side of any column scores as infinitely far."""
    from wrenorm.cmaes import BatchedCMAES

    problem, space, pspace = model.problem, model.space, model.problem.space
    n = space.dim
    X = np.concatenate([u[None], np.clip(u[None] + step * np.eye(n), space.lower, space.upper),
                        np.clip(u[None] - step * np.eye(n), space.lower, space.upper)])
    hands, span = model.hands(X), np.diag(X[1:n + 1] - X[n + 1:])
    B_ = np.linalg.norm(w[:, None] * J)

    def distance(values):
        st = crit.from_rollout(problem.simulate(values, hands), problem.n, 0.0)
        Z = state_vector(st).reshape(len(values), len(X), -1)
        with np.errstate(invalid="ignore", divide="ignore"):
            S = np.transpose((Z[:, 1:n + 1] - Z[:, n + 1:]) / span[None, :, None], (0, 2, 1))
            d = np.linalg.norm((w[None, :, None] * (S - J[None])).reshape(len(values), -1), axis=1) / B_
        return np.where(np.isfinite(d), d, np.inf)

    best_v, best_d = model.values.copy(), float(distance(model.values[None])[0])
    F = int(pspace.free_mask.sum())
    es = BatchedCMAES(pspace.to_unit(model.values)[None], 0.2, np.zeros(F), np.ones(F), [seed + 1], popsize,
                      generations)
    while not es.done:
        unit = es.ask()
        values = pspace.from_unit(unit)
        values[:, ~pspace.free_mask] = model.values[~pspace.free_mask]
        d = distance(values)
        es.tell(d)
        j = int(np.argmin(d))
        if d[j] < best_d:
            best_v, best_d = values[j].copy(), float(d[j])
    return best_v, best_d


def compare(folder: Path, segments: int | None = None, best: bool = False, also_free: tuple = ()) -> int:
    from wrenorm.tasks.rope.control.command import CommandSpace
    from wrenorm.tasks.rope.control.correct import CoarseModel, StoredTrials, fit_parameters
    from wrenorm.tasks.rope.problem import RopeProblem
    from wrenorm.tasks.rope.reference.generate import builtin_reference_path, load_reference
    from wrenorm.tasks.rope.reference.paths import get_hand_path

    try:
        saved = np.load(folder / FILE)
        settings = json.loads((folder / "settings.json").read_text())
        J, u = saved["J"], saved["u"]
        result = json.loads((folder / "correct.json").read_text())
    except (OSError, ValueError, KeyError) as e:
        _fail(f"{folder / FILE}: not the output of `run` ({type(e).__name__})")
    if "fitted" not in result["runs"]:
        _fail(f"{folder / 'correct.json'}: no fitted run (run with --params fitted)")
    if settings.get("engine", "newton") == "newton" and not builtin_throws_of(settings):
        _fail(f"{folder / 'settings.json'}: the run's goal was recorded on its own {settings.get('fine_segments')}-"
              "segment newton rope, not the built-in one that this comparison reads")
    goal_ref = load_reference(builtin_reference_path(settings["goal"], settings["variant"]))
    goal = crit.Target.from_reference(goal_ref)
    segments = settings["segments"] if segments is None else segments
    problem = RopeProblem([goal_ref], segments=segments, dt=settings["dt"], names=[settings["goal"]])
    unknown = [n for n in also_free if n not in problem.space.names or not problem.space.parameters[
        problem.space.index(n)].frozen]
    if unknown:  # before the fit and the match, which take a while
        _fail(f"--also-free {' '.join(unknown)}: not among the chain's fixed parameters "
              f"({', '.join(p.name for p in problem.space.parameters if p.frozen)})")
    space = CommandSpace(get_hand_path(settings["start"]))
    if segments == settings["segments"]:  # the run's own chain
        fitted = np.array([result["runs"]["fitted"]["parameters"][name] for name in problem.space.names])
    else:  # the same fit as the run's, at the other resolution
        _refit_matches_the_run(settings, folder / "settings.json")
        fitted, _ = fit_parameters(settings["variant"], segments, settings["dt"], settings["seed"],
                                   settings["fit_generations"], settings["device"])
    w = secant.residual_weights(goal)
    trial = load_reference(StoredTrials(None, folder / "real-trials").file_for(space.decode(u)))
    z = state_vector(crit.from_reference(trial))[0]
    model = CoarseModel(problem, fitted, space, "fitted")
    match = secant.matched_command(model, z, w, u, settings["seed"])
    step = float(saved["step"])
    priors = {"fitted, at trial 1's command": secant.Sensitivity.of_chain(model, u, step).S,
              "fitted, where it matches trial 1": secant.Sensitivity.of_chain(model, match.u, step).S,
              "measured, at that match": secant.Sensitivity.of_chain(
                  CoarseModel(problem, problem.space.measured, space, "measured"), match.u, step).S}
    if best:
        values, _ = best_parameters(model, J, w, u, step, settings["seed"])
        priors["best parameters, at trial 1's command"] = secant.Sensitivity.of_chain(
            CoarseModel(problem, values, space, "best"), u, step).S
        six, frozen = values, problem.space
        try:
            for names in [(n,) for n in also_free] + ([tuple(also_free)] if len(also_free) > 1 else []):
                problem.space = frozen.with_changes(**{n: {"frozen": False} for n in names})
                # from the six-parameter bound: a parameter more can then only come closer
                values, _ = best_parameters(CoarseModel(problem, six, space, "six"), J, w, u, step, settings["seed"])
                priors[f"best, {' and '.join(names)} free too"] = secant.Sensitivity.of_chain(
                    CoarseModel(problem, values, space, "best"), u, step).S
        finally:
            problem.space = frozen
    print(f"{folder}: the {segments}-link chain's sensitivity against the rope's (relative error; mean column cosine)")
    for name, P in priors.items():
        print(f"  {name:38s} " + _block_cells(goal, w, P, J))
    return 0


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["run"]:
        return run(argv[1:])
    if argv[:1] == ["every-best"]:
        return every_best(argv[1:])
    if argv[:1] == ["chain"]:
        if len(argv) < 2 or not argv[1].isdigit() or not 3 <= int(argv[1]) <= 63:
            _fail(f"chain {argv[1] if len(argv) > 1 else ''}: give the chain's links first, 3-63")
        return chain(int(argv[1]), argv[2:])
    if argv[:1] == ["compare"]:
        import argparse

        from wrenorm.options import add_list

        p = argparse.ArgumentParser(prog="rope_sensitivity_prior.py compare")
        p.add_argument("folder", type=Path)
        p.add_argument("--segments", type=int, default=None, help="a chain of this many links, fitted as the run's")
        p.add_argument("--best-parameters", action="store_true",
                       help="also the parameters whose sensitivity lies closest to the rope's (a bound)")
        add_list(p, "--also-free", default=[], metavar="NAME",
                 help="with --best-parameters: the bound again with these fixed parameters free as well")
        args = p.parse_args(argv[1:])
        if args.segments is not None and not 3 <= args.segments <= 63:
            _fail(f"--segments {args.segments}: the chain takes 3-63 links")
        if args.also_free and not args.best_parameters:
            _fail("--also-free widens the --best-parameters bound; give both")
        return compare(args.folder, args.segments, args.best_parameters, tuple(args.also_free))
    _fail("usage: rope_sensitivity_prior.py run [correct rope options] | every-best [correct rope options] | "
          "chain N [correct rope options] | "
          "compare RUN_FOLDER [--segments N] [--best-parameters [--also-free NAME ...]]")
    return 2


if __name__ == "__main__":
    sys.exit(main())
