"""How much of the correction's gap is the chain's sensitivity? Run the loop with the ROPE's own sensitivity as
its prior, and compare the chain's sensitivity with the rope's (README, "How much of the gap is the chain's
sensitivity"). A diagnosis, not a method: the rope's sensitivity costs 26 extra fine runs (real trials on a robot).

    python examples/diagnostics/rope_sensitivity_prior.py run --variant heavy --seed 4 --params fitted \\
        --linearise-at trial --no-record --out runs/oracle-heavy-s4
    python examples/diagnostics/rope_sensitivity_prior.py compare runs/oracle-heavy-s4

`run` is `correct rope` (its options after `run`; fixed parameters, `--linearise-at trial`) with the chain's
central difference at trial 1's command replaced by the fine rope's (the same step, 26 fine runs, not counted as
trials), kept in OUT/rope-sensitivity.npz; the secant pairs then correct it as they correct the chain's.
`compare` prints, per block of the critical state, how far the chain's sensitivity (fitted parameters, at trial 1's
command and where it matches trial 1's state; measured parameters at that match) lies from the rope's: the weighted
relative error (0 alike, 1 no better than zero) and the mean cosine of the columns (position and velocity).
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
from wrenorm.tasks.rope.control.plan import state_vector

FILE = "rope-sensitivity.npz"


def _fail(message: str) -> None:
    print(f"rope_sensitivity_prior: {message}", file=sys.stderr)
    sys.exit(2)


def run(argv: list[str]) -> int:
    from wrenorm.cli import main
    from wrenorm.tasks.rope.control.correct import NewtonRope

    def value(flag):
        return argv[argv.index(flag) + 1] if flag in argv[:-1] else None

    if value("--out") is None or value("--linearise-at") != "trial" or value("--engine") not in (None, "newton"):
        _fail("run needs --out OUT and --linearise-at trial (the rope's sensitivity is measured at trial 1's "
              "command), on the newton rope")
    params = argv[argv.index("--params") + 1:] if "--params" in argv else []
    if any(a.startswith("renormalised") for a in params):
        _fail("run takes fixed parameters only (--params fitted or measured): a renormalised arm re-measures its "
              "sensitivity after every trial, 26 fine runs each")
    out = Path(value("--out"))
    ropes = {}

    def of_rope(cls, model, u, step=secant.GN_FD_STEP):
        from wrenorm.tasks.rope.reference.generate import builtin_reference_path, load_reference

        # the loop's own fine rope is not reachable from here: an equal one (variant, segments, the CLI's horizon)
        t = time.perf_counter()
        settings = json.loads((out / "settings.json").read_text())
        if "rope" not in ropes:
            goal_ref = load_reference(builtin_reference_path(settings["goal"], settings["variant"]))
            horizon = min(float(goal_ref.time[-1]), float(crit.from_reference(goal_ref).time[0]) + 0.5)
            ropes["rope"] = NewtonRope(settings["variant"], settings["fine_segments"], horizon, settings["device"])
        rope, space = ropes["rope"], model.space

        def states(U):
            return np.concatenate([state_vector(crit.from_reference(rope(space.decode(x)))) for x in U])

        jac = jacobian(states, u, step, space.lower, space.upper)
        J = np.where(np.isfinite(jac.J), jac.J, 0.0)
        np.savez(out / FILE, J=J, u=u, step=step)
        print(f"rope_sensitivity_prior: the rope's own sensitivity from {jac.evaluations} fine runs "
              f"({time.perf_counter() - t:.0f} s)", file=sys.stderr, flush=True)
        return cls(J.copy(), J, jac.kinds, 0, jac.evaluations, time.perf_counter() - t)

    secant.Sensitivity.of_chain = classmethod(of_rope)
    return main(["correct", "rope", *argv])


def compare(folder: Path) -> int:
    from wrenorm.tasks.rope.control.command import CommandSpace
    from wrenorm.tasks.rope.control.correct import CoarseModel, StoredTrials
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
    goal_ref = load_reference(builtin_reference_path(settings["goal"], settings["variant"]))
    goal = crit.Target.from_reference(goal_ref)
    problem = RopeProblem([goal_ref], segments=settings["segments"], dt=settings["dt"], names=[settings["goal"]])
    space = CommandSpace(get_hand_path(settings["start"]))
    fitted = np.array([result["runs"]["fitted"]["parameters"][name] for name in problem.space.names])  # the run's chain
    w = secant.residual_weights(goal)
    trial = load_reference(StoredTrials(None, folder / "real-trials").file_for(space.decode(u)))
    z = state_vector(crit.from_reference(trial))[0]
    model = CoarseModel(problem, fitted, space, "fitted")
    match = secant.matched_command(model, z, w, u, settings["seed"])
    priors = {"fitted, at trial 1's command": secant.Sensitivity.of_chain(model, u, float(saved["step"])).S,
              "fitted, where it matches trial 1": secant.Sensitivity.of_chain(model, match.u, float(saved["step"])).S,
              "measured, at that match": secant.Sensitivity.of_chain(
                  CoarseModel(problem, problem.space.measured, space, "measured"), match.u, float(saved["step"])).S}
    print(f"{folder}: the chain's sensitivity against the rope's (relative error; mean column cosine)")
    for name, P in priors.items():
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
        print(f"  {name:34s} " + ", ".join(cells))
    return 0


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["run"]:
        return run(argv[1:])
    if argv[:1] == ["compare"] and len(argv) == 2:
        return compare(Path(argv[1]))
    _fail("usage: rope_sensitivity_prior.py run [correct rope options] | compare RUN_FOLDER")
    return 2


if __name__ == "__main__":
    sys.exit(main())
