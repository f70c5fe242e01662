"""Resolution flow: effective parameters as functions of the resolution a (the paper's theta*(a)).

At each resolution the system is fitted by several seeded CMA-ES searches side by side (one
batched evaluation per generation for all of them), starting from the neighbouring
resolution's result; or, on CUDA (`together`), every resolution's searches in one generation loop (each
generation one batched evaluation per resolution, in turn), all starting from the measured values. The
spread across searches is the reported uncertainty ("restarts");
where the system exposes residuals, the Gauss-Newton std at the best optimum is given too.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from .errors import InputError
from .fit import stalled_search
from .results import SCHEMA, stored_digest, versions, write_json
from .runfolder import check_same_settings
from .search import mean_loss, restarts_together
from .search import restarts as seeded_searches
from .uncertainty import check_against_optima, uncertainty

POINTS_FILE = "flow_points.json"  # finished resolutions, written after each: what --resume continues from


def _larger_std(restarts: float, jacobian) -> float | None:
    """A flow point's std: the restarts' spread alone had stated K_D +-5e-8 where the Jacobian gives 3e-5 (restarts
    from one start end together; review of stop 55), and the Jacobian alone misses a search that does not repeat."""
    known = [float(v) for v in (restarts, jacobian) if v is not None and not np.isnan(v)]
    return max(known) if known else None  # an infinite Jacobian std (a direction the data do not see) stays infinite


def _settings(problems, seed, restarts, popsize, generations, identity, together) -> dict:
    return {"task": problems[0].task, "resolutions": [p.resolution for p in problems], "seed": seed,
            "restarts": restarts, "popsize": popsize, "generations": generations, "together": together,
            "free": [[q.name for q in p.space.free] for p in problems]} | (identity or {})


def _digest(points: list, start) -> str:
    """What the finished points hold, as written: a resume continues only from points this run wrote itself."""
    return stored_digest([points, start])


def _resumed(out: Path, settings: dict, problems: list) -> tuple[list, object]:
    f = out / POINTS_FILE  # prepare_out checked that it exists
    try:
        saved = json.loads(f.read_text())
    except (OSError, ValueError) as e:
        raise InputError(str(f), POINTS_FILE, f"cannot be read: {e}") from None
    if not isinstance(saved, dict) or not isinstance(saved.get("points"), list) or "start" not in saved:
        raise InputError(str(f), "points", "is not a flow's list of finished resolutions; rerun without --resume")
    check_same_settings(str(f), saved.get("settings") or {}, json.loads(json.dumps(settings)), "flow")
    points, start = saved["points"], saved["start"]
    if saved.get("digest") != _digest(points, start):
        raise InputError(str(f), "points", "changed since the flow wrote them (or written before resumes checked "
                                           "them): a resume would report them as fitted; rerun without --resume")
    if len(points) > len(problems) or any(not isinstance(p, dict) or p.get("resolution") != q.resolution
                                          for p, q in zip(points, problems)):
        raise InputError(str(f), "points", "do not follow this flow's resolutions; rerun without --resume")
    return points, (np.array(start) if start is not None else None)


def run_flow(problems: list, out: Path, seed: int = 0, restarts: int = 4, popsize: int = 16,
             generations: int = 60, quiet: bool = False, analytic=None, record: bool = True,
             resume: bool = False, identity: dict | None = None, command: str | None = None,
             together: bool = False) -> dict:
    t0 = time.perf_counter()
    settings = _settings(problems, seed, restarts, popsize, generations, identity, together)
    points, start = _resumed(out, settings, problems) if resume else ([], None)
    seeds = [seed + 1000 * k for k in range(restarts)]
    todo = problems[len(points):]
    found = restarts_together(todo, seeds, popsize, generations, quiet=quiet) if together and todo else None
    for k, prob in enumerate(todo):
        if found is not None:
            res = found[k]
        else:
            res = seeded_searches(prob, seeds, popsize=popsize, generations=generations, start=start, quiet=quiet)
        best = min(res, key=lambda r: r.best_loss)
        fitted = best.best_values
        stalled = stalled_search(prob, prob.space.measured, fitted)
        if stalled is not None:
            fitted = prob.space.measured.copy()
        vals = np.array([r.best_values for r in res if np.isfinite(r.best_loss)])
        # the searches' spread over a flat objective (stalled) is no uncertainty
        spread = vals.std(axis=0, ddof=1) if len(vals) > 1 and stalled is None else np.full(len(prob.space.names),
                                                                                               np.nan)
        unc = uncertainty(prob, fitted)
        if stalled is None:
            check_against_optima(unc, prob.space, fitted, float(best.best_loss),
                                 [(r.best_values[prob.space.free_mask], float(r.best_loss)) for r in res
                                  if r is not best], unc["std"])
        loss, _ = mean_loss(prob, np.stack([prob.space.measured, fitted]), prob.train)
        point = {
            "resolution": prob.resolution,
            "parameters": {
                p.name: {"measured": p.measured, "fitted": float(fitted[i]),
                         "std": None if p.frozen else _larger_std(spread[i], unc["std"].get(p.name)),
                         "std_restarts": None if p.frozen else float(spread[i]),
                         "std_jacobian": unc["std"].get(p.name), "frozen": p.frozen, "scale": p.scale,
                         "restarts": vals[:, i].tolist()}
                for i, p in enumerate(prob.space.parameters)},
            "loss": {"measured": float(loss[0]), "fitted": float(loss[1])},
            "undetermined": unc.get("undetermined", []),
            "correlation": unc.get("correlation"),
            "warning": "; ".join(w for w in (stalled, *prob.fit_warnings(fitted), unc.get("warning")) if w) or None,
        }
        if analytic is not None:
            point["analytic"] = analytic(prob, prob.space.as_dict(fitted))
        points.append(point)
        start = fitted
        write_json(out / POINTS_FILE, {"settings": settings, "points": points, "start": start.tolist(),
                                       "digest": _digest(points, start.tolist())})
    flow = {"schema": SCHEMA.replace("result", "flow"), "task": problems[0].task, "points": points,
            "uncertainty_method": f"std: the larger of the spread of {restarts} seeded CMA-ES restarts run side "
                                  "by side (std_restarts; they start together, so they say how well the search "
                                  "repeats, not what the data allow) and the Gauss-Newton sigma^2 (J^T J)^-1 where "
                                  "residuals exist (std_jacobian)",
            "resolutions_searched": ("together: every resolution's searches in one generation loop, from the "
                                     "measured values" if together else
                                     "in turn: each resolution's searches start from the previous one's result"),
            "seed": seed, "device": problems[0].device, "versions": versions(),
            "wall_seconds": time.perf_counter() - t0,
            # the data flags every point was fitted under (a fit's result.json carries the same list)
            "warnings": list(dict.fromkeys(w for prob in problems for w in getattr(prob, "warnings", [])))}
    if command:
        flow["command"] = command
    write_json(out / "flow.json", flow)
    from wrenorm.fit import write_report_or_warn

    write_report_or_warn(out, flow, quiet)
    from wrenorm.viz.flow_plot import plot_flow

    plot_flow(out / "flow.png", flow)
    if record:
        from wrenorm.viz.flow_plot import record_flow

        record_flow(out / "recording.rrd", flow)
    return flow
