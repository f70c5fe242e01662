"""How well each Gauss-Newton step was predicted, block by block: for every step of finished `correct rope` runs (a
trial after the first that hit, as did the best trial before it), the change of each weighted error term (shape,
velocity, time, place) that the step predicted against the change the real rope showed. A block whose changes are
not predicted (correlation near 0) is one the steps chase blindly (README, "Which part of the critical state the
steps can predict"). The steps of all runs named are pooled; each run's arm must step by Gauss-Newton (`--method gn`,
or a renormalised arm of it), whose prediction is the linear model's, not the plan loops' model plus offset.
Runs that recorded the corrected model's floor (secant.model_floor: the least error the linear model predicted for
any command in the box when the step was planned) get a second table: the floor against the best error, the step's
prediction and the rope's answer, and which terms the floor keeps (README, "What the steps can still reach").
A second table, printed before the floors' and pooled over every run named, sets the rope's change of the weighted
residual against the predicted change as vectors: how much of the predicted change it made along it, at what angle,
and the multiple of the step that would have left the least squared weighted residual had the rope answered in
proportion along it (1: the step as taken; README, "More changes to the default arm").
A further table splits the velocity block's change into the velocity profile's first N Legendre modes in arc length
per axis and the rest (secant.velocity_projection, N = 1, 2, 3, 5): the rope's share in the first N, and how well the
step predicted each part (README, "The velocity profile's smooth part"); the next does the same for the position
block (secant.mode_projection).

    python examples/diagnostics/step_prediction.py RUN_OR_CAMPAIGN [...] [--arm fitted]

Reads correct.json and the goal only (newton's built-in throw, or the run's own OUT/goal on another engine); no
simulation. The goal is checked against the errors stored with the trials.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from wrenorm.tasks.rope import observable as crit
from wrenorm.tasks.rope.control import secant
from wrenorm.tasks.rope.control.correct_cli import builtin_throws_of
from wrenorm.tasks.rope.reference.generate import builtin_reference_path, load_reference

TERMS = ("shape", "velocity", "time", "place")
MODES = (1, 2, 3, 5)
STAGES = (("best error above 0.1", lambda b: b > 0.1), ("best error at or below 0.1", lambda b: b <= 0.1))


def _fail(message: str) -> None:
    print(f"step_prediction: {message}", file=sys.stderr)
    sys.exit(2)


def run_folders(paths) -> list[Path]:
    """The run folders named, or inside the campaign folders named (one level down); each once."""
    out = []
    for p in map(Path, paths):
        if (p / "correct.json").exists():
            out.append(p)
        elif p.is_dir() and any(p.glob("*/correct.json")):
            out += sorted(q.parent for q in p.glob("*/correct.json"))
        else:
            _fail(f"{p}/correct.json: not a finished `correct rope` run, nor a folder of them")
    return list(dict.fromkeys(q.resolve() for q in out))


def goal_of(folder: Path, r: dict) -> crit.Target:
    """The run's goal: newton's built-in throw, or the goal throw kept in OUT/goal (another engine, or newton at
    another resolution than the built-in references')."""
    settings = r.get("settings", {})
    if settings.get("real", "fine") != "fine":
        _fail(f"{folder}/correct.json: settings.real: {settings.get('real')!r}, a coarse stand-in's goal is not kept "
              "with the run")
    engine = settings.get("engine", "newton")
    if builtin_throws_of(settings):
        f = builtin_reference_path(r["goal"]["path"], r["variant"])
    else:
        stored = sorted((folder / "goal").glob("trial-*.npz"))
        if len(stored) != 1:
            _fail(f"{folder}/goal: expected the {engine} goal throw kept with the run, found {len(stored)} files")
        f = stored[0]
    try:
        return crit.Target.from_reference(load_reference(f))
    except (OSError, ValueError, KeyError) as e:
        _fail(f"{f}: the goal throw cannot be read ({e})")


def _state(record: dict) -> crit.CriticalStates:
    return crit.CriticalStates(np.asarray(record["positions"], np.float64)[None],
                               np.asarray(record["velocities"], np.float64)[None], np.array([record["time"]]),
                               np.asarray(record["contact_arclength"], np.float64)[None], np.ones(1, bool),
                               np.zeros(1))


def step_rows(folder: Path, arm: str) -> list[dict]:
    """One row per predicted step: the best error before it, the predicted and the actual change of each weighted
    term."""
    try:
        r = json.loads((folder / "correct.json").read_text())
    except (OSError, ValueError) as e:
        _fail(f"{folder}/correct.json: not a finished `correct rope` run ({e})")
    if arm not in r.get("runs", {}):
        _fail(f"{folder}/correct.json: runs: no run {arm!r}; it has {', '.join(r.get('runs', {})) or 'none'}")
    run = r["runs"][arm]
    if run.get("steps") != "gn":
        _fail(f"{folder}/correct.json: runs.{arm}: method {run.get('method')!r} does not step by Gauss-Newton")
    if not isinstance(r.get("tolerance"), (int, float)):
        _fail(f"{folder}/correct.json: tolerance: {r.get('tolerance')!r}, not a number (the floor is judged by it)")
    goal = goal_of(folder, r)
    rows, best, best_state, floor = [], None, None, None
    for t in run["trials"]:
        state = _state(t["measured_state"]) if t["self_collision"] else None
        if state is not None and not np.isclose(float(goal.terms(state)["total"][0]), t["error"], rtol=1e-4,
                                                atol=1e-6):
            _fail(f"{folder}/correct.json: runs.{arm}: trial {t['trial']}'s stored error {t['error']:.4f} is not its "
                  "state's error to this goal (another goal throw than the run's?)")
        if (best is not None and best["self_collision"] and t["self_collision"]
                and (t.get("predicted_state") or {}).get("self_collision")):
            predicted_state = _state(t["predicted_state"])
            predicted = goal.terms(predicted_state)
            r_best, r_predicted, r_actual = (goal.residual(st)[0] for st in (best_state, predicted_state, state))
            rows.append({"best": best["error"], "accepted": bool(t["accepted"]), "error": t["error"],
                         "predicted": float(predicted["total"][0]), "tolerance": float(r["tolerance"]),
                         "floor": None if floor is None else floor["error"],
                         "floor_terms": None if floor is None else {k: goal.weights[k] * floor["terms"][k]
                                                                    for k in TERMS},
                         "best_terms": {k: goal.weights[k] * best["terms"][k] for k in TERMS}}
                        | along_the_step(r_best, r_predicted - r_best, r_actual - r_best)
                        | block_modes(goal, "velocity", r_predicted - r_best, r_actual - r_best)
                        | block_modes(goal, "position", r_predicted - r_best, r_actual - r_best)
                        | {f"{k}_actual": goal.weights[k] * (t["terms"][k] - best["terms"][k]) for k in TERMS}
                        | {f"{k}_predicted": goal.weights[k] * (float(predicted[k][0]) - best["terms"][k])
                           for k in TERMS})
        if t["accepted"]:
            best, best_state = t, state
        floor = (t.get("next_step") or {}).get("model_floor")  # the floor when the next trial was planned
    return rows


def along_the_step(r_best: np.ndarray, predicted: np.ndarray, actual: np.ndarray) -> dict:
    """The rope's change of the weighted residual (actual) against the change the step predicted: the share of the
    predicted length it made along it (projection), the cosine between them, and the multiple a of the step that
    would have minimised |r_best + a actual|^2 had the rope answered in proportion along it (best_length; the least
    squares of the step's own problem, not the observable's sum of block norms). A change below 1e-9 of the best
    residual's length, predicted or made, has no direction: all three are NaN and along_table leaves the step out."""
    pp, aa = float(predicted @ predicted), float(actual @ actual)
    tiny = 1e-18 * max(float(r_best @ r_best), 1e-300)
    if pp <= tiny or aa <= tiny:
        return {"projection": np.nan, "cosine": np.nan, "best_length": np.nan}
    return {"projection": float(actual @ predicted) / pp, "cosine": float(actual @ predicted) / np.sqrt(pp * aa),
            "best_length": -float(r_best @ actual) / aa}


def block_modes(goal: crit.Target, block: str, predicted: np.ndarray, actual: np.ndarray) -> dict:
    """Per number of modes N in MODES (keys `<block>_modesN`), of the weighted residual's rows of `block` (velocity or
    position): the share of the rope's change in the profile's first N Legendre modes (squared norm), and for that part
    and the rest the cosine between the predicted and the actual change and the relative error |actual - predicted| /
    |actual| (NaN where a part has no length)."""
    def compare(p, a):
        pn, an = np.linalg.norm(p), np.linalg.norm(a)
        if pn < 1e-15 or an < 1e-15:
            return np.nan, np.nan
        return float(p @ a / (pn * an)), float(np.linalg.norm(a - p) / an)

    out = {}
    for n in MODES:
        Q = secant.mode_projection(goal, block, n)
        keep_p, keep_a = Q @ predicted, Q @ actual
        rest_p, rest_a = predicted - keep_p, actual - keep_a
        v = goal.blocks[block]
        total = float(actual[v] @ actual[v])
        out[f"{block}_modes{n}"] = {"share": float(keep_a[v] @ keep_a[v]) / total if total > 0 else np.nan,
                                    "kept": compare(keep_p[v], keep_a[v]), "rest": compare(rest_p[v], rest_a[v])}
    return out


def by_stage(rows: list[dict], scored=lambda x: True):
    """(stage label, its steps that `scored` keeps) per stage of STAGES, in order."""
    for label, keep in STAGES:
        yield label, [x for x in rows if keep(x["best"]) and scored(x)]


def _finite_median(values) -> float:
    values = [v for v in values if np.isfinite(v)]
    return float(np.median(values)) if values else np.nan


def modes_table(rows: list[dict], block: str) -> str:
    """Per stage and number of modes, the medians of block_modes over the steps."""
    lines = [f"| steps | modes per axis | rope's {block} change in them (share) | cosine, predicted vs actual: in "
             "them / the rest | relative error: in them / the rest |", "|---|---|---|---|---|"]
    for label, sub in by_stage(rows):
        for n in MODES:
            parts = [x[f"{block}_modes{n}"] for x in sub]
            med = _finite_median
            lines.append(f"| {label}: {len(sub)} | {n} | {med([p['share'] for p in parts]):.2f} | "
                         f"{med([p['kept'][0] for p in parts]):.2f} / {med([p['rest'][0] for p in parts]):.2f} | "
                         f"{med([p['kept'][1] for p in parts]):.2f} / {med([p['rest'][1] for p in parts]):.2f} |")
    return "\n".join(lines)


def along_table(rows: list[dict]) -> str:
    """Per stage (best error above or below 0.1), the medians of along_the_step over the steps that have one; the
    step count says how many did."""
    lines = ["| steps | rope's change along the predicted one / predicted (median) | cosine (median) | best length "
             "along the step, 1 = as taken: median (quartiles) |", "|---|---|---|---|"]
    for label, sub in by_stage(rows, lambda x: np.isfinite(x["cosine"])):
        if not sub:
            lines.append(f"| {label}: 0 | | | |")
            continue
        q = np.percentile([x["best_length"] for x in sub], [25, 50, 75])
        lines.append(f"| {label}: {len(sub)} | {np.median([x['projection'] for x in sub]):.2f} | "
                     f"{np.median([x['cosine'] for x in sub]):.2f} | {q[1]:.2f} ({q[0]:.2f}-{q[2]:.2f}) |")
    return "\n".join(lines)


def table(rows: list[dict]) -> str:
    lines = ["| steps | block | correlation, predicted vs actual change | median predicted change | median actual "
             "change |", "|---|---|---|---|---|"]
    for label, sub in by_stage(rows):
        for k in TERMS:
            a = np.array([x[f"{k}_actual"] for x in sub])
            p = np.array([x[f"{k}_predicted"] for x in sub])
            corr = float(np.corrcoef(a, p)[0, 1]) if len(sub) > 2 and a.std() > 0 and p.std() > 0 else float("nan")
            lines.append(f"| {label}: {len(sub)} | {k} | {corr:.2f} | {np.median(p) if len(p) else np.nan:+.4f} | "
                         f"{np.median(a) if len(a) else np.nan:+.4f} |")
    return "\n".join(lines)


def floor_table(rows: list[dict]) -> str:
    """Per stage, what the corrected model said any command could still reach (its floor, secant.model_floor)
    against the best error, the step's own prediction and what the rope did; and each weighted term at the best
    trial and at the floor: the part of the error the model sees no command remove."""
    lines = ["| steps | floor / best error | step's prediction / best | actual / best | floor above the tolerance "
             "| shape, velocity, time, place at the best | ... at the floor |", "|---|---|---|---|---|---|---|"]
    for label, sub in by_stage(rows, lambda x: x["floor"] is not None):
        if not sub:
            lines.append(f"| {label}: 0 | | | | | | |")
            continue
        b = np.array([x["best"] for x in sub])
        ratio = [np.median(np.array(v) / b) for v in ([x["floor"] for x in sub],
                                                      [x["predicted"] for x in sub], [x["error"] for x in sub])]
        above = sum(x["floor"] > x["tolerance"] for x in sub)
        at_best = ", ".join(f"{np.median([x['best_terms'][k] for x in sub]):.3f}" for k in TERMS)
        at_floor = ", ".join(f"{np.median([x['floor_terms'][k] for x in sub]):.3f}" for k in TERMS)
        lines.append(f"| {label}: {len(sub)} | {ratio[0]:.2f} | {ratio[1]:.2f} | {ratio[2]:.2f} | {above} of "
                     f"{len(sub)} | {at_best} | {at_floor} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="run folders of `correct rope`, or campaign folders holding them")
    ap.add_argument("--arm", default="fitted", help="which run of each folder (measured, fitted, renormalised, ...)")
    args = ap.parse_args(argv)
    rows = [x for folder in run_folders(args.runs) for x in step_rows(folder, args.arm)]
    if not rows:
        _fail("no step to score: every run ended at trial 1 or never hit after it")
    print(table(rows))
    print("\nThe rope's change of the weighted residual against the step's prediction, as vectors:\n")
    print(along_table(rows))
    print("\nThe velocity block's change split into the velocity profile's first modes in arc length and the rest:\n")
    print(modes_table(rows, "velocity"))
    print("\nThe same for the position block (the shape at the contact):\n")
    print(modes_table(rows, "position"))
    if any(x["floor"] is not None for x in rows):
        print("\nWhat the corrected model said any command in the box could still reach (its floor), per step:\n")
        print(floor_table(rows))
    else:
        print("\nNo step recorded the corrected model's floor (runs made before it was recorded).")
    return 0


if __name__ == "__main__":
    sys.exit(main())
