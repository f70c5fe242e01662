"""One fit, start to finish: search, validation on held-out conditions, uncertainty, identifiability restarts,
results, recording.

This is the paper's procedure as code: the Problem names the observable and the parameters (measured
values are the start); the search fits the free ones on the training conditions; validation re-runs the
held-out conditions with measured and with fitted parameters and says whether the omitted physics was
absorbed.
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from . import search as searches
from .clock import process_age
from .errors import InputError
from .problem import Problem, finite_or_inf
from .restarts import identifiability_restarts, spread_of_optima
from .results import SCHEMA, versions, write_json
from .uncertainty import check_against_optima, optima_from_report, uncertainty

STATE_FILE = "search_log.jsonl"
ADOPT_BETTER = 0.01  # a restart whose objective is lower than the main search's by more than this share replaces it


@dataclass(frozen=True)
class FitSettings:
    """What a fit's search does; saved with the run, and a resumed run must repeat it."""

    seed: int = 0
    generations: int = 60
    popsize: int | None = None
    sigma0: float = 0.2
    polish: int = 0
    restarts: int = 0
    searches: int = 1  # seeded searches side by side in the main fit (width on a wide device)
    method: str = "cmaes"  # "cmaes", "least-squares" or "cmaes+least-squares" (a global search, then polished)


def check_tolerances(problem: Problem) -> np.ndarray:
    """Each held-out condition's tolerance (Problem.tolerance_for), checked before any search: the verdict divides
    by them."""
    tolerances = np.array([problem.tolerance_for(c) for c in problem.held_out], dtype=np.float64)
    if not np.all(tolerances > 0):
        raise ValueError(f"{problem.task}: tolerance_for gave {tolerances.tolist()}; each must be a number > 0")
    return tolerances


def _validation(problem: Problem, measured: np.ndarray, fitted: np.ndarray) -> dict:
    if not problem.held_out:
        return {"conditions": {}, "verdict": "unvalidated", "tolerance": problem.tolerance,
                "note": "no held-out conditions: nothing to validate on"}
    errs, details = problem.validation_errors(np.stack([measured, fitted]), problem.held_out)
    errs = finite_or_inf(errs)
    tolerances = check_tolerances(problem)
    flags = [list(problem.data_flags(c)) for c in problem.held_out]
    # a fitted model that shows none of the observable on a condition (a chain that never reaches its contact) is
    # scored by a bound, not an error: never within tolerance (a recording cut 8 ms after its contact made the bound
    # small and the verdict "absorbed")
    misses = np.array([bool(d.get("fitted_misses")) for d in details])
    conditions = {
        c.name: {"measured_error": float(errs[0, j]), "fitted_error": float(errs[1, j]),
                 "tolerance": float(tolerances[j]),
                 "within_tolerance": bool(errs[1, j] <= tolerances[j] and not misses[j])}
        | ({"data_flags": flags[j]} if flags[j] else {}) | dict(details[j])
        for j, c in enumerate(problem.held_out)
    }
    out = {
        "conditions": conditions,
        "mean_measured_error": float(np.mean(errs[0])),
        "mean_fitted_error": float(np.mean(errs[1])),
        "ratio_of_means": float(np.mean(errs[1]) / np.mean(errs[0])) if np.mean(errs[0]) > 0 else None,
        "tolerance": problem.tolerance,
    }
    deciding = np.array([not f for f in flags])
    flagged = [c.name for c, f in zip(problem.held_out, flags) if f]
    notes = []
    if flagged:
        out["flagged_conditions"] = flagged
        notes.append(f"decided by {int(deciding.sum())} of {len(deciding)} held-out conditions: the data checks "
                     f"flag {', '.join(flagged)}, shown but not deciding" if deciding.any() else
                     f"the data checks flag every held-out condition ({', '.join(flagged)}): a verdict on them would "
                     "rest on data the checks doubt; see each condition's data_flags")
    missed = [c.name for c, m in zip(problem.held_out, misses) if m]
    if missed:
        out["fitted_misses"] = missed
        notes.append(f"the fitted model shows no event on {', '.join(missed)}: its error there is a lower bound "
                     "(and so are the means that include it), and the condition is outside tolerance")
    measured_missed = [c.name for c, d in zip(problem.held_out, details) if d.get("measured_misses")]
    if measured_missed:
        out["measured_misses"] = measured_missed
        notes.append(f"the measured values show no event on {', '.join(measured_missed)}: their error there is a "
                     "lower bound, which grows with the recording's length after the event, and so does the mean "
                     "measured error (ratio_of_means compares against it)")
    if notes:
        out["note"] = "; ".join(notes)
    if not deciding.any():
        return out | {"verdict": "unvalidated"}
    # the condition furthest outside (or least inside) its own tolerance decides; a miss is outside it
    over = np.where(deciding, np.where(misses, np.inf, errs[1] / tolerances), -np.inf)
    j = int(np.argmax(over))
    verdict = "absorbed" if over[j] <= 1.0 else "expand"
    out |= {
        "worst_fitted_error": float(errs[1, j]),
        "worst_condition": problem.held_out[j].name,
        "worst_tolerance": float(tolerances[j]),
        "worst_is_miss": bool(misses[j]),
        "verdict": verdict,
        "meaning": (
            "absorbed: the fitted parameters reproduce conditions the search never saw within tolerance, so the "
            "omitted physics is absorbed into them" if verdict == "absorbed" else
            "expand: fitted parameters do not keep held-out conditions within tolerance; the parameter set or the "
            "simulator must grow"
        ),
    }
    return out


def adopt_better_restart(problem: Problem, fitted: np.ndarray, seed: int, report: dict) -> tuple[dict, dict | None]:
    """The identifiability restarts are further searches of the same objective: where one of them ends clearly
    lower than the main search (by more than ADOPT_BETTER of its objective), the main search stopped in a worse
    basin, and reporting it would ship values the fit itself knows to be worse (a probe: objective 133 reported where
    all four restarts reached 98, the viscosity 150x off). That restart's values are then the fit's, the main
    search's optimum joins the others, and the spread is taken again around the values reported."""
    space = problem.space
    optima = report.get("optima") or []
    main = float(searches.objective(problem, fitted[None])[0])
    losses = np.array([o["train_loss"] for o in optima], dtype=np.float64)
    finite = np.where(np.isfinite(losses), losses, np.inf)
    if not len(losses) or not np.isfinite(finite).any():
        return report, None
    k = int(np.argmin(finite))
    if np.isfinite(main) and not finite[k] < main - ADOPT_BETTER * abs(main):
        return report, None
    values = np.array([optima[k]["values"][p.name] for p in space.parameters], dtype=np.float64)
    seeds = [seed] + [o["seed"] for o in optima]
    vals = np.concatenate([fitted[None], [[o["values"][p.name] for p in space.parameters] for o in optima]])
    redone = {key: v for key, v in report.items() if key in ("popsize", "generations", "search")}
    redone |= {"seeds": [int(x) for x in seeds], "main_search_included": True}
    redone |= spread_of_optima(problem, values, seeds, vals, np.append(main, losses))
    said = (f"the main search (seed {seed}) ended at objective {main:.4g}, its restart with seed {optima[k]['seed']} "
            f"at {losses[k]:.4g}: the restart's values are reported (the main search stopped in a worse basin)")
    return redone, {"values": values.tolist(), "seed": int(optima[k]["seed"]), "objective": float(losses[k]),
                    "main_objective": main, "said": said}


def stalled_search(problem: Problem, measured: np.ndarray, fitted: np.ndarray) -> str | None:
    """A search that found nothing better than the measured values, said in one line (None when it did). Its best
    candidate is then whichever it met first on a flat objective (a chain that never reaches the observed event,
    a simulation that diverges everywhere), so the fit reports the measured values instead of that candidate."""
    if np.array_equal(fitted, measured):  # a search that stayed at the start (an exact start, or a flat one)
        return None
    objectives = searches.objective(problem, np.stack([measured, fitted]))
    if objectives[1] < objectives[0]:
        return None
    return (f"the search found no values better than the measured ones (objective {objectives[0]:.4g} measured, "
            f"{objectives[1]:.4g} at its best), so the measured values are reported: they are already as good as "
            "anything found, or the objective does not see the parameters here (the model never shows the observed "
            "event, or diverges), or the search was too short")


def run_fit(problem: Problem, out: str | Path, settings: FitSettings = FitSettings(), resume: bool = False,
            start: np.ndarray | None = None, record: bool = True, quiet: bool = False,
            identity: dict | None = None, command: str | None = None) -> dict:
    """Fit `problem`, write OUT/result.json (+ recording.rrd, search.html, report.html); return the result dict.

    identity: what else a resumed run must share with the interrupted one (inputs' hashes, versions).
    command: the command line that reproduces the fit, for the report."""
    check_tolerances(problem)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = process_age()
    t0 = time.perf_counter()
    space = problem.space
    measured = space.measured
    saved = asdict(settings) | (identity or {})
    history, methods = {}, []
    first_generation = []  # seconds from the process's start to the first evaluated generation
    t_evaluating = None  # of the search, the CMA-ES's batched evaluations (the rest is its own host work)
    if settings.method.startswith("cmaes"):
        res = searches.cmaes(
            problem, seed=settings.seed, popsize=settings.popsize, generations=settings.generations,
            sigma0=settings.sigma0, start=start, checkpoint=out / STATE_FILE, resume=resume, quiet=quiet,
            searches=settings.searches, settings=saved,
            on_generation=lambda rec: first_generation or first_generation.append(process_age()))
        history["cmaes"], methods = res.history, ["cmaes"]
        t_evaluating = res.evaluation_s
    else:
        searches.check_resume(out / STATE_FILE, problem, saved, resume)
    if settings.method.endswith("least-squares"):
        from .least_squares import levenberg_marquardt

        first = res.best_values if methods else (space.measured if start is None else start)
        lsq, _, _ = levenberg_marquardt(problem, first, quiet=quiet)
        history["least_squares"] = lsq.history
        methods.append("least-squares")
        if not methods[:-1] or lsq.best_loss <= res.best_loss:
            lsq.evaluations += res.evaluations if methods[:-1] else 0
            res = lsq
    t_search = time.perf_counter() - t0
    polish_report = None
    fitted = res.best_values
    if settings.polish and problem.differentiable:
        g = searches.polish(problem, fitted, iterations=settings.polish, quiet=quiet)
        history["gradient"] = g.history
        methods.append("lbfgs")
        improved = g.best_loss < res.best_loss
        if improved:
            fitted = g.best_values
        polish_report = {"iterations": settings.polish, "loss_before": res.best_loss, "loss_after": g.best_loss,
                         "kept": improved}
    unpolished = (f"--polish {settings.polish}: this {problem.task} problem has no tape gradient of its objective "
                  "(no errors_and_grad, or, for a PD log, its fitted start velocities), so the search's values are not "
                  "polished") if settings.polish and not problem.differentiable else None
    stalled = stalled_search(problem, measured, fitted)
    if stalled is not None:
        fitted = measured.copy()
    restart_report, adopted = None, None
    t_restarts = time.perf_counter()
    if settings.restarts >= 2:
        seeds = [settings.seed + 1 + k for k in range(settings.restarts)]
        restart_report = identifiability_restarts(problem, fitted, seeds, popsize=settings.popsize,
                                                  generations=settings.generations, sigma0=settings.sigma0,
                                                  quiet=quiet, method=settings.method)
        restart_report, adopted = adopt_better_restart(problem, fitted, settings.seed, restart_report)
        if adopted is not None:
            fitted = np.array(adopted["values"])
            stalled = stalled_search(problem, measured, fitted)
    t_restarts = time.perf_counter() - t_restarts
    both = np.stack([measured, fitted])
    # the training error (the observable's units) and, apart, what the search minimised (errors or squared
    # residuals, plus the prior's squared deviations)
    if problem.least_squares:
        losses = finite_or_inf(problem.errors(both, problem.train)).mean(axis=1)
        objectives = searches.objective(problem, both)
    else:  # the objective is the (weighted) mean error plus the prior: one evaluation gives both
        objectives, errs = searches.mean_loss(problem, both, problem.train)
        losses = errs.mean(axis=1)
    # the uncertainty's own Jacobian, never the least-squares search's: its 1e-4 step sat inside the swimmer's residual
    # jitter, which gave its weak columns false slope (Kutta's data-only std 4 % there, 17-24 % at 1e-3 to 1e-2), so
    # the stds, and what the data determine, changed with the seed and with an adopted restart (review of stop 55)
    unc = uncertainty(problem, fitted)
    params = {}
    for i, p in enumerate(space.parameters):
        params[p.name] = {
            "measured": p.measured,
            "fitted": float(fitted[i]),
            "bounds": [p.lower, p.upper],
            "std": unc["std"].get(p.name),
            "scale": p.scale,
            "frozen": p.frozen,
            "unit": p.unit,
            "ratio_to_measured": float(fitted[i] / p.measured) if p.measured else None,
        }
        if p.prior is not None:
            params[p.name]["prior"] = {"centre": p.prior[0], "scale": p.prior[1]}
        if "data_only_std" in unc and not p.frozen:  # where any parameter has a prior: every free one's
            params[p.name]["data_only_std"] = unc["data_only_std"].get(p.name)
    t_validate = time.perf_counter()
    result = {
        "schema": SCHEMA,
        "task": problem.task,
        "resolution": problem.resolution,
        "parameters": params,
        "loss": {"measured": float(losses[0]), "fitted": float(losses[1]), "meaning": problem.error_doc,
                 "objective": {"measured": float(objectives[0]), "fitted": float(objectives[1]),
                               "meaning": ("sum of squared residuals" if problem.least_squares else
                                           "mean training error") + (" plus the prior's squared normalised "
                                                                     "deviations" if space.priors else "")}},
        "train": [c.name for c in problem.train],
        "validation": _validation(problem, measured, fitted),
        "uncertainty": {k: v for k, v in unc.items() if k not in ("std", "data_only_std")},
        "search": {
            "methods": methods,
            "generations": len(history.get("cmaes", [])),
            "least_squares_iterations": len(history.get("least_squares", [])) - 1 if "least_squares" in history
            else None,
            "evaluations": res.evaluations,
            "blowups": res.blowups,
            "stop": res.stop,
            "searches": settings.searches,
            "popsize": settings.popsize,
            "sigma0": settings.sigma0,
            "gradient_polish": polish_report,
        },
        "seed": settings.seed,
        "device": problem.device,
        "versions": versions(),
    }
    optima = history.get("cmaes", [{}])[-1].get("optima") if history.get("cmaes") else None
    # a stalled search's optima say nothing of a spread, nor do those of a main search a restart replaced
    if settings.searches > 1 and optima and stalled is None and adopted is None:
        # width-first: the searches run side by side anyway, so their optima give the spread for free
        result["searches_spread"] = spread_of_optima(
            problem, fitted, [o["seed"] for o in optima], np.array([o["values"] for o in optima]),
            np.array([o["loss"] for o in optima]))
    if restart_report is not None:
        result["restarts"] = restart_report
    if stalled is None:  # else the values reported are the measured ones, which no search ended at
        check_against_optima(result["uncertainty"], space, fitted, float(objectives[1]),
                             optima_from_report(space, restart_report)
                             + optima_from_report(space, result.get("searches_spread")), unc["std"])
    result.update(problem.report(fitted, measured))
    if stalled is not None:
        result["search"]["stalled"] = stalled
    if adopted is not None:
        result["search"]["adopted_restart"] = {k: adopted[k] for k in ("seed", "objective", "main_objective")}
    unconverged = None
    if (res.stop == "iterations" and "least_squares" in history and len(history["least_squares"]) > 5
            and stalled is None and adopted is None):  # else the values reported are not this search's
        costs = [h["cost"] for h in history["least_squares"]]
        unconverged = (f"the least-squares search stopped at its limit of {len(costs) - 1} iterations, still moving "
                       f"(cost {costs[-6]:.4g} -> {costs[-1]:.4g} over its last 5): the values may not be its optimum, "
                       "and a slow, long valley often means the data do not determine them; see the restarts")
    result["warnings"] = [*([stalled] if stalled else []), *([adopted["said"]] if adopted else []),
                          *([unpolished] if unpolished else []), *([unconverged] if unconverged else []),
                          *problem.fit_warnings(fitted), *result.get("warnings", []),
                          # what the data cannot determine is said with the rest: a sweep's table and a reader of
                          # `warnings` had not seen it (review of stop 55)
                          *([result["uncertainty"]["warning"]] if result["uncertainty"].get("warning") else [])]
    t_write = time.perf_counter()
    if record:
        _record(problem, out, result, history, fitted, measured, quiet)
    _plot(out, problem, history, fitted, measured)
    result["wall_seconds"] = time.perf_counter() - t0
    result["timing"] = {"start_up_s": t_start, "search_s": t_search, "search_evaluating_s": t_evaluating,
                        "validation_s": t_write - t_validate + t_restarts, "restarts_s": t_restarts,
                        "writing_s": time.perf_counter() - t_write,
                        "uncertainty_s": t_validate - t0 - t_search - t_restarts,
                        "first_generation_after_process_start_s": first_generation[0] if first_generation else None,
                        "meaning": "start_up_s: from the process's start to the fit's start (interpreter, imports, "
                                   "building the problem: references, kernels); the rest in the fit's order "
                                   "(validation_s includes restarts_s, the identifiability restarts); "
                                   "search_evaluating_s: of search_s, the CMA-ES's batched evaluations (rollouts "
                                   "and observable, on the device where there is one), the rest being its own host "
                                   "work (pycma, the search log)"}
    if command:
        result["command"] = command
    write_json(out / "result.json", result)
    write_report_or_warn(out, result, quiet)
    return result


def write_report_or_warn(out: Path, result: dict, quiet: bool = False) -> None:
    """report.html beside result.json. The result is already safe on disk, so a failure here costs the page
    only, and says so."""
    from wrenorm.viz.report import write_report

    try:
        write_report(out, result)
    except Exception as e:  # noqa: BLE001  (a report bug must not lose a finished fit)
        print(f"wrenorm: report.html not written: {type(e).__name__}: {e}", file=sys.stderr)


def _summary_markdown(result: dict) -> str:
    lines = [f"# {result['task']} fit", "", f"resolution: `{result['resolution']}`", "",
             "| parameter | measured | fitted | std |", "|---|---|---|---|"]
    for name, p in result["parameters"].items():
        std = "" if p["std"] is None else f"{p['std']:.4g}"
        lines.append(f"| {name} | {p['measured']:.6g} | {p['fitted']:.6g} | {std} |")
    v = result["validation"]
    lines += ["", f"loss: measured {result['loss']['measured']:.4g}, fitted {result['loss']['fitted']:.4g}",
              f"validation verdict: **{v['verdict']}** (tolerance {v['tolerance']})"]
    for name, c in v["conditions"].items():
        tol = f" (tolerance {c['tolerance']:.4g})" if c.get("tolerance", v["tolerance"]) != v["tolerance"] else ""
        flagged = " (data flagged: not deciding)" if c.get("data_flags") else ""
        lines.append(f"- {name}: measured-parameter error {c['measured_error']:.4g}, fitted {c['fitted_error']:.4g}"
                     f"{tol}{flagged}")
    lines += [text for text in ("", v.get("meaning"), v.get("note")) if text is not None]
    lines += ["", "Colours: reference grey / white, measured parameters orange, fitted parameters blue, analytic "
                  "green. report.html beside this recording has the same result as a page."]
    return "\n".join(lines)


def _record(problem, out, result, history, fitted, measured, quiet):
    from wrenorm.viz.record import Recorder, rerun_available

    if not rerun_available():
        if not quiet:
            print("rerun-sdk not installed: no recording written (pip install 'wrenorm[viz]')", file=sys.stderr)
        return
    rec = Recorder(out / "recording.rrd", recording_id=f"{problem.task}-seed{result['seed']}")
    try:
        rec.log_text("summary", _summary_markdown(result))
        names = problem.space.names
        steps = [(h["generation"], h["best"], h.get("median"), h["values"]) for h in history.get("cmaes", [])]
        # least-squares iterations continue the search's timeline after any CMA-ES generations
        steps += [(len(steps) + h["iteration"], h["cost"], None, h["values"]) for h in history.get("least_squares", [])]
        for g, best, median, values in steps:
            rec.log_scalar("search/loss/best", g, best, timeline="generation")
            if median is not None:
                rec.log_scalar("search/loss/median", g, median, timeline="generation")
            for name, v, m in zip(names, values, problem.space.measured):
                if not problem.space[name].frozen:
                    rec.log_scalar(f"search/parameters/{name}", g, v / m if m else v, timeline="generation")
        problem.record(rec, fitted, measured)
        rec.close()
    except BaseException:
        rec.abort()
        raise


def _plot(out, problem, history, fitted, measured):
    from wrenorm.viz.plots import write_search_svg, write_svg_page

    write_search_svg(out / "search.html", problem, history)
    write_svg_page(out / "conditions.html", problem.charts(fitted, measured))


def _label(problem: Problem) -> str:
    return "_".join(f"{k}{v:g}" if isinstance(v, float) else f"{k}{v}" for k, v in problem.resolution.items()
                    if k not in ("dt", "integrator"))


def _check_same_resolutions(problems: list, out: Path) -> None:
    """A resumed fit runs at the resolutions the interrupted one ran at: one resumed at another --f-sim had started
    a new fit over the folder's combined result (review of stop 54)."""
    here = (out / STATE_FILE).exists()
    subs = sorted(p.parent.name for p in out.glob(f"*/{STATE_FILE}"))
    labels = sorted(_label(p) for p in problems) if len(problems) > 1 else []
    if (len(problems) == 1 and subs and not here) or (labels and (here or set(subs) - set(labels))):
        ran = ", ".join(subs) if subs and not here else "one resolution"
        now = ", ".join(labels) or _label(problems[0]) or "one resolution"
        raise InputError(str(out), "--resume", f"the interrupted fit ran at {ran}, this one at {now}: resume with the "
                                               "same resolutions (--f-sim, --segments, ...)")


def _finished_result(path: Path, problem: Problem) -> dict:
    try:
        r = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise InputError(str(path), "file", f"cannot be read back ({e.__class__.__name__}): remove that resolution's "
                                            "folder to fit it again") from None
    params = r.get("parameters") if isinstance(r, dict) else None
    if not isinstance(params, dict) or any(not isinstance(params.get(n), dict) or "fitted" not in params[n]
                                           for n in problem.space.names):
        raise InputError(str(path), "parameters", "not a finished fit of this parameter set: remove that "
                                                  "resolution's folder to fit it again")
    return r


def run_fits(problems: list, out: Path, settings: FitSettings, resume: bool = False, record: bool = True,
             quiet: bool = False, identity: dict | None = None, command: str | None = None) -> dict:
    """Fit one problem into OUT, or several (e.g. one per f_sim) into OUT/<label>/ with a combined
    OUT/result.json holding `runs`. Each fit starts from its predecessor's result."""
    common = dict(settings=settings, resume=resume, quiet=quiet, record=record, identity=identity)
    if resume:
        _check_same_resolutions(problems, out)
    if len(problems) == 1:
        return run_fit(problems[0], out, command=command, **common)
    t0 = time.perf_counter()
    runs, start = [], None
    for prob in problems:
        label = _label(prob)
        sub = out / label
        done = sub / "result.json"
        if resume and done.exists():
            searches.check_finished(sub / STATE_FILE, prob, asdict(settings) | (identity or {}))
            r = _finished_result(done, prob)
        else:
            r = run_fit(prob, sub, start=start, **common)
        r["folder"] = label
        runs.append(r)
        start = np.array([r["parameters"][n]["fitted"] for n in prob.space.names])
    combined = {
        "schema": SCHEMA,
        "task": problems[0].task,
        "resolutions": [p.resolution for p in problems],
        "runs": runs,
        "seed": settings.seed,
        "device": problems[0].device,
        "versions": versions(),
        "wall_seconds": time.perf_counter() - t0,
    }
    if command:
        combined["command"] = command
    write_json(out / "result.json", combined)
    write_report_or_warn(out, combined, quiet)
    return combined
