"""Why a 10-link correction stalls: the fine rope's error around a run's best trial and along the straight line to
the goal's own command, against what the chain plus its offset predicts there (README, "Campaign at 10 links").
The goal's command is used for this diagnosis only; the correction never sees it.

    python -m wrenorm correct rope --variant default --seed 5 --params fitted --no-record --out runs/dev-s5
    python examples/diagnostics/correct_stall.py runs/dev-s5 fitted

About 25 fine-rope simulations (2-3 minutes here).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from wrenorm.tasks.rope import observable as crit
from wrenorm.tasks.rope.control.command import CommandSpace
from wrenorm.tasks.rope.control.correct import CoarseModel, NewtonRope, StoredTrials
from wrenorm.tasks.rope.control.correct_cli import builtin_is_the_real_rope, builtin_throws_of
from wrenorm.tasks.rope.control.plan import Offset, predicted_states, state_vector
from wrenorm.tasks.rope.problem import RopeProblem, resample
from wrenorm.tasks.rope.reference.generate import DEFAULT_SEGMENTS, builtin_reference_path, load_reference
from wrenorm.tasks.rope.reference.paths import get_hand_path

FRACTIONS = np.array([0.0, 0.25, 0.5, 0.75, 0.9])


def _fail(message: str) -> None:
    print(f"correct_stall: {message}", file=sys.stderr)
    sys.exit(2)


def main(run: str, arm: str) -> None:
    try:
        r = json.load(open(f"{run}/correct.json"))
    except (OSError, ValueError) as e:
        _fail(f"{run}/correct.json: not a finished `correct rope` run ({e})")
    if arm not in r.get("runs", {}):
        _fail(f"{run}/correct.json: runs: no run {arm!r}; it has {', '.join(r.get('runs', {}))}")
    settings = r.get("settings", {})
    try:  # the fine rope's resolution is in settings.json (and in correct.json's settings from stop 34 on)
        settings = settings | json.loads(Path(run, "settings.json").read_text())
    except (OSError, ValueError):
        pass
    if not (settings.get("real", "fine") == "fine" and builtin_throws_of(settings)
            and builtin_is_the_real_rope(settings)):
        _fail(f"{run}/correct.json: this diagnostic replays the run on newton's built-in {DEFAULT_SEGMENTS}-segment "
              f"rope; this run's real rope was {r.get('real_system', 'another')!r}")
    gref = load_reference(builtin_reference_path(r["goal"]["path"], r["variant"]))
    goal = crit.Target.from_reference(gref)
    space = CommandSpace(get_hand_path(r["start"]["path"]))
    problem = RopeProblem([gref], segments=r["model"]["segments"], dt=r["model"]["dt"], names=["goal"])
    model = CoarseModel(problem, np.array([r["runs"][arm]["parameters"][n] for n in problem.space.names]), space)
    real = NewtonRope(r["variant"], DEFAULT_SEGMENTS, float(min(goal.state.time[0] + 0.5, 1.5)))
    best = min(r["runs"][arm]["trials"], key=lambda t: t["error"])
    u, u_goal = np.array(best["command_u"]), np.array(r["goal"]["command_u_of_goal_path"])

    def real_error(v):
        v, _ = space.limit_step(np.zeros(space.dim), v)
        return float(goal.terms(crit.from_reference(real(space.decode(v))))["total"][0])

    print(f"best trial {best['trial']}: error {best['error']:.3f}; {np.linalg.norm(u_goal - u):.2f} units of u "
          "from the goal's own command")
    rng = np.random.default_rng(0)
    for h in (0.05, 0.15):
        steps = rng.normal(size=(5, u.size))
        steps *= h / np.linalg.norm(steps, axis=1, keepdims=True)
        print(f"fine rope, 5 random steps of {h}:", np.round([real_error(u + d) for d in steps], 3))
    line = u[None] + FRACTIONS[:, None] * (u_goal - u)[None]
    print("fine rope along the line to the goal command (0, 25, 50, 75, 90 %):",
          np.round([real_error(v) for v in line], 3))

    z_real = state_vector(crit.from_reference(real(space.decode(u))))
    offset = Offset.zero(u.size, np.size(z_real), centre=u)
    offset.d = (np.atleast_2d(z_real) - np.atleast_2d(state_vector(model.states(u[None]))))[0]
    pred, _ = predicted_states(model, line, offset)
    print("chain + offset along the same line:", np.round(goal.terms(pred)["total"], 3))
    steps = rng.normal(size=(2000, u.size))
    steps *= 1.5 / np.linalg.norm(steps, axis=1, keepdims=True)
    pred, _ = predicted_states(model, u[None] + steps, offset)
    tot = goal.terms(pred)["total"]
    print(f"chain + offset, 2000 random steps of 1.5: best {np.nanmin(tot):.3f}, median {np.nanmedian(tot):.3f}")

    # the chain's state at the best trial's critical time: no event in the model
    st_best = crit.from_reference(real(space.decode(u)))
    t_star, K = float(st_best.time[0]), goal.state.pos.shape[1]
    s_nodes, s_k = np.linspace(0, 1, problem.n), np.linspace(0, 1, K)

    def at_fixed_time(U):
        res = model.rollout(U, trajectory_every=1)
        k = min(int(np.floor(t_star / problem.dt)), res.trajectory.shape[0] - 2)
        a = t_star / problem.dt - k
        pos = [(1 - a) * res.trajectory[k, b] + a * res.trajectory[k + 1, b] for b in range(len(U))]
        vel = [(res.trajectory[k + 1, b] - res.trajectory[k, b]) / problem.dt for b in range(len(U))]
        return (np.stack([resample(p, s_nodes, s_k) for p in pos]), np.stack([resample(v, s_nodes, s_k) for v in vel]))

    p0, v0 = at_fixed_time(u[None])

    def predicted_fixed(U):
        p, v = at_fixed_time(U)
        B = len(U)
        return crit.CriticalStates(p + st_best.pos[0] - p0[0], v + st_best.vel[0] - v0[0], np.full(B, t_star),
                                   np.repeat(st_best.s[:1], B, 0), np.ones(B, bool), np.zeros(B))

    print("chain at a fixed time + offset along the line:", np.round(goal.terms(predicted_fixed(line))["total"], 3))
    tot = goal.terms(predicted_fixed(u[None] + steps[:300]))["total"]
    print(f"chain at a fixed time + offset, 300 random steps of 1.5: best {np.nanmin(tot):.3f}, "
          f"median {np.nanmedian(tot):.3f}")

    # the trials alone: an affine (secant) model through the run's own trials, read back from OUT/real-trials
    stored = StoredTrials(real, f"{run}/real-trials")
    hits = [t for t in r["runs"][arm]["trials"] if t["self_collision"] and t["trial"] != best["trial"]]
    dU = np.array([t["command_u"] for t in hits]) - u
    r_best = goal.residual(crit.from_reference(stored(space.decode(u))))[0]
    dR = np.array([goal.residual(crit.from_reference(stored(space.decode(u + d))))[0] for d in dU]) - r_best
    J = np.linalg.lstsq(dU, dR, rcond=None)[0].T
    step = -np.linalg.solve(J.T @ J + 1e-3 * np.eye(u.size), J.T @ r_best)
    towards = (u_goal - u) / np.linalg.norm(u_goal - u)
    print(f"secant model through {len(hits) + 1} trials: Gauss-Newton step {np.linalg.norm(step):.2f} long, predicts "
          f"sum of squares {r_best @ r_best:.4f} -> {np.sum((r_best + J @ step) ** 2):.4f}, cosine with the line to "
          f"the goal command {step @ towards / np.linalg.norm(step):.2f}")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2] if len(sys.argv) > 2 else "fitted")
