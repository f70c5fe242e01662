"""Searches over a Problem's free parameters, in normalised [0, 1] coordinates.

- `cmaes`: the engine's batched CMA-ES (wrenorm.cmaes) on the training loss, one search or several seeded
  ones side by side; each generation of all of them is one batched `Problem.errors` call. With a checkpoint
  every generation is appended to a plain JSON-lines log as it ends, so a killed fit resumes to the same result.
- `restarts`: further seeded searches side by side, for the spread of what the data leave open.
- `polish` / `gradient`: L-BFGS / Adam (torch) on gradients from the system's differentiable kernel (Warp tape).

The loss of a candidate is the mean of its training errors (inf if any condition blew up), weighted where
conditions carry `meta["weight"]` (e.g. real trials weighted toward the latest), plus the sum of squared
prior deviations when parameters carry a prior.
"""
from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .cmaes import STATE_SCHEMA, BatchedCMAES
from .errors import AllCandidatesFailed, InputError
from .problem import Problem, finite_or_inf
from .progress import Progress
from .results import jsonable, write_atomic
from .runfolder import check_same_settings

# fault-injection hook for the kill -9 / --resume tests: seconds to sleep after each generation
_SLOW = float(os.environ.get("WRENORM_TEST_SLOW_GENERATION", "0") or 0)


@dataclass
class SearchResult:
    method: str
    best_values: np.ndarray  # (P,) full parameter vector
    best_loss: float
    history: list = field(default_factory=list)  # one dict per generation / iteration
    evaluations: int = 0
    blowups: int = 0
    stop: str = ""
    seed: int | None = None
    evaluation_s: float = 0.0  # of the search's wall time, the batched evaluations' (rollouts, observable, device)


def mean_loss(problem: Problem, values: np.ndarray, conditions) -> tuple[np.ndarray, np.ndarray]:
    """(B,) loss = mean error over conditions (inf for any blown-up condition; weighted by the conditions'
    `meta["weight"]` where given, default 1) + prior penalty; and (B, C) errors."""
    values = np.atleast_2d(values)
    errs = finite_or_inf(problem.errors(values, conditions))
    w = np.array([float(c.meta.get("weight", 1.0)) for c in conditions])
    if not (np.all(np.isfinite(w)) and np.all(w >= 0) and w.sum() > 0):
        raise ValueError(f"condition weights must be finite, >= 0 and not all 0, got {w}")
    with np.errstate(invalid="ignore"):
        loss = (errs * (w / w.sum())[None]).sum(axis=1) if np.any(w != w[0]) else errs.mean(axis=1)
    prior = problem.space.prior_residuals(values)
    if prior.shape[-1]:
        with np.errstate(invalid="ignore"):
            loss = loss + np.sum(prior ** 2, axis=-1)
        loss = np.where(np.isfinite(loss), loss, np.inf)  # a NaN parameter value costs the candidate, as a blow-up
    return loss, errs


def objective(problem: Problem, values: np.ndarray) -> np.ndarray:
    """(B,) what the searches minimise on the training conditions: the mean error plus the prior penalty, or,
    for a least-squares problem, the sum of squared residuals and prior residuals (inf where not finite)."""
    values = np.atleast_2d(values)
    if not getattr(problem, "least_squares", False):
        return mean_loss(problem, values, problem.train)[0]
    r = np.concatenate([np.asarray(problem.residuals(values, problem.train), np.float64),
                        problem.space.prior_residuals(values)], axis=1)
    with np.errstate(invalid="ignore", over="ignore"):
        cost = np.sum(r * r, axis=1)
    return np.where(np.isfinite(cost), cost, np.inf)


def _progress(msg: str, quiet: bool) -> None:
    if not quiet:
        print(msg, file=sys.stderr, flush=True)


def _unit_start(problem: Problem, start) -> np.ndarray:
    space = problem.space
    return np.clip(space.to_unit(space.measured if start is None else start), 0.0, 1.0)


def cmaes(
    problem: Problem,
    seed: int = 0,
    popsize: int | None = None,
    generations: int = 60,
    sigma0: float = 0.2,
    start: np.ndarray | None = None,
    checkpoint: str | Path | None = None,
    resume: bool = False,
    quiet: bool = False,
    searches: int = 1,
    settings: dict | None = None,
    on_generation: Callable[[dict], None] | None = None,
) -> SearchResult:
    """Fit the training loss; `searches` seeded searches side by side (seeds seed, seed + 1000, ...), the
    best one returned with the others' optima in `history[-1]["optima"]`. `start` is one full parameter
    vector (every search starts there; default the measured values) or one row per search (K, P), e.g. a
    warm start beside the measured values."""
    space = problem.space
    if not space.free:
        loss = objective(problem, space.measured[None])
        return SearchResult("cmaes", space.measured.copy(), float(loss[0]), stop="no free parameters", seed=seed)
    starts = None if start is None else np.atleast_2d(np.asarray(start, dtype=np.float64))
    if starts is not None and len(starts) > 1:
        searches = len(starts)
    seeds = [seed + 1000 * k for k in range(max(1, int(searches)))]
    x0s = (np.repeat(_unit_start(problem, None)[None], len(seeds), 0) if starts is None else
           np.stack([_unit_start(problem, starts[k % len(starts)]) for k in range(len(seeds))]))
    es = BatchedCMAES(x0s, sigma0, 0.0, 1.0, seeds, popsize, generations)
    saved = {"free": space.free_names, "settings": settings or {}}
    history = []
    if resume and checkpoint and Path(checkpoint).exists():
        history = _resume(checkpoint, es, saved)
        _progress(f"resuming {problem.task} search at generation {len(history)}", quiet)
    elif checkpoint:
        _start_log(checkpoint, saved | {"seeds": es.seeds})
    bar = Progress(generations, f"{problem.task} cmaes", quiet, unit="gen", done=len(history))
    evaluation_s = 0.0
    while not es.done:
        U = es.ask()
        values = space.from_unit(U)
        t_eval = time.perf_counter()
        loss = objective(problem, values)
        evaluation_s += time.perf_counter() - t_eval
        es.tell(loss)
        rec = _generation_record(es, values, loss)
        history.append(rec)
        if on_generation:
            on_generation(rec)
        bar.update(best=f"{rec['best_so_far']:.4e}", median=f"{rec['median']:.3e}", sigma=f"{rec['sigma']:.3g}",
                   blowups=rec["blowups"])
        if checkpoint:
            _append_generation(checkpoint, es.last_told, rec)
        if _SLOW:
            time.sleep(_SLOW)
    bar.close()
    found = [s for s in es.finish() if np.isfinite(s.best_loss)]
    if not found:
        raise AllCandidatesFailed(
            f"{es.searches[0].stop or 'no candidate evaluated'}: every candidate blew up (NaN/Inf or runaway). "
            "Narrow the parameter bounds, lower sigma0, or use a finer resolution (smaller time step).")
    best = min(found, key=lambda s: s.best_loss)
    if len(seeds) > 1 and history:
        history[-1]["optima"] = [{"seed": s.seed, "loss": s.best_loss, "values": space.from_unit(s.best_x).tolist()}
                                 for s in found]
    return SearchResult("cmaes", space.from_unit(best.best_x), best.best_loss, history,
                        sum(s.evaluations for s in es.searches), sum(s.blowups for s in es.searches), best.stop,
                        best.seed, evaluation_s)


def _generation_record(es: BatchedCMAES, values: np.ndarray, loss: np.ndarray) -> dict:
    ok = np.isfinite(loss)
    i = int(np.argmin(np.where(ok, loss, np.inf)))
    lead = min(es.searches, key=lambda s: s.best_loss)
    return {"generation": es.generation - 1, "best": float(loss[i]) if ok.any() else float("inf"),
            "median": float(np.median(loss[ok])) if ok.any() else float("inf"), "best_so_far": lead.best_loss,
            "blowups": int((~ok).sum()), "sigma": es.sigma(es.searches.index(lead)), "values": values[i].tolist()}


LOG_SCHEMA = "wrenorm.search-log/1"


def _line(obj) -> str:
    return json.dumps(jsonable(obj), allow_nan=False) + "\n"


def _start_log(checkpoint, header: dict) -> None:
    """A new search log, written atomically: its header line naming the run (free parameters, settings, the
    searches' seeds). Each generation is then appended (`_append_generation`): a state rewritten whole every
    generation grows with the run, and re-serialising it took 2/3 of a 32-search rope fit on an H100."""
    write_atomic(checkpoint, _line({"schema": LOG_SCHEMA} | header), durable=False)


def _append_generation(checkpoint, told: list, record: dict) -> None:
    """One line per generation, flushed as it ends: each search's candidates' digest and losses, and the
    generation's record. A process killed mid-write leaves at most a torn last line, which a resume drops."""
    with open(checkpoint, "a") as f:
        f.write(_line({"told": [list(t) for t in told], "record": record}))


def _read_log(checkpoint, saved: dict) -> tuple[dict, list[dict], int | None]:
    """The header and the generations of a run in progress, after checking that it was made with the same
    parameter set and settings as this run (naming the first that differs), and where a last line cut short by a
    kill begins (None if there is none): it is dropped; any other line that is not a generation is refused."""
    src = str(checkpoint)
    try:
        data = Path(checkpoint).read_bytes()
        lines = data.decode("utf-8").split("\n")  # split on the bytes a torn tail is cut at
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(src, "file", f"cannot be read as a search log: {e}") from None
    rows = []
    for i, text in enumerate(lines[:-1]):  # lines[-1], after the last newline, is empty or a killed write's torn tail
        try:
            rows.append(json.loads(text))
        except ValueError as e:
            raise InputError(src, f"line {i + 1}", f"is not JSON ({e}): edited, or not wrenorm's") from None
    if not rows or not isinstance(rows[0], dict) or rows[0].get("schema") != LOG_SCHEMA:
        raise InputError(src, "line 1", f"is not a wrenorm search log (expected schema {LOG_SCHEMA})")
    header, generations = rows[0], rows[1:]
    if header.get("free") != saved["free"]:
        raise InputError(src, "free parameters", f"the interrupted search fits {header.get('free')}, this run "
                                                 f"{saved['free']}; resume with the same --free/--freeze")
    check_same_settings(src, header.get("settings") or {}, saved["settings"], "fit")
    for i, g in enumerate(generations):
        if not (isinstance(g, dict) and isinstance(g.get("told"), list) and isinstance(g.get("record"), dict)):
            raise InputError(src, f"line {i + 2}", "is not a generation of this search (told, record)")
    return header, generations, None if data.endswith(b"\n") else data.rfind(b"\n") + 1


def _resume(checkpoint, es: BatchedCMAES, saved: dict) -> list:
    """Replay the logged generations into `es` (bit-identical, see wrenorm.cmaes), cut a torn last line from the
    log, and return the generations' records."""
    header, generations, torn_at = _read_log(checkpoint, saved)
    told = [[] for _ in es.searches]
    try:
        for g in generations:
            for k, digest, losses in g["told"]:
                if not 0 <= int(k) < len(told):
                    raise ValueError(f"search {k} of {len(told)}")
                told[int(k)].append({"candidates": digest, "losses": losses})
    except (IndexError, TypeError, ValueError) as e:
        raise InputError(str(checkpoint), "told", f"is not a wrenorm search log of this run ({e})") from None
    es.replay({"schema": STATE_SCHEMA, "seeds": header.get("seeds"), "told": told}, str(checkpoint))
    if torn_at is not None:  # cut the torn line, so that the next generation starts a line of its own
        os.truncate(checkpoint, torn_at)
    return [g["record"] for g in generations]


def check_finished(checkpoint, problem: Problem, settings: dict) -> None:
    """A finished run's log against this run's parameter set and settings (naming the first that differs), before
    its result is reused: a resumed multi-rate fit had taken finished rates' results made with another --K-D."""
    if not Path(checkpoint).exists():
        raise InputError(str(checkpoint), "file", "missing beside a finished result: cannot tell which settings made "
                                                  "it; fit again with --force")
    _read_log(checkpoint, {"free": problem.space.free_names, "settings": settings})


def check_resume(checkpoint, problem: Problem, settings: dict, resume: bool) -> None:
    """A search without per-generation state (least squares, a second or so): check a resumed run's settings,
    then record this run's, so that a later --resume can check them in turn."""
    saved = {"free": problem.space.free_names, "settings": settings}
    if resume and Path(checkpoint).exists():
        _read_log(checkpoint, saved)
    _start_log(checkpoint, saved)


def restarts(problem: Problem, seeds: list[int], popsize: int = 16, generations: int = 60, sigma0: float = 0.2,
             start: np.ndarray | None = None, quiet: bool = False) -> list[SearchResult]:
    """Independent seeded searches side by side (one batched evaluation per generation for all). The spread
    of their optima is an honest uncertainty for parameters the observable barely constrains, where a
    Jacobian-based std can mislead."""
    return restarts_together([problem], seeds, popsize, generations, sigma0, [start], quiet)[0]


def restarts_together(problems: list[Problem], seeds: list[int], popsize: int = 16, generations: int = 60,
                      sigma0: float = 0.2, starts: list | None = None, quiet: bool = False) -> list[list[SearchResult]]:
    """`restarts` for several problems (a flow's resolutions) in one generation loop, all from their own starts
    (no warm start from a neighbour). Each generation evaluates the problems one after another, every one a
    batched evaluation of all its searches: the device holds one resolution's chains at a time, not all of them
    (different resolutions are different kernels and batch shapes); what runs together is the loop, so no
    resolution waits for another's whole search."""
    starts = starts or [None] * len(problems)
    ess = [BatchedCMAES(np.repeat(_unit_start(p, s)[None], len(seeds), 0), sigma0, 0.0, 1.0, seeds, popsize,
                        generations) for p, s in zip(problems, starts)]
    what = problems[0].task + (f" {len(problems)} resolutions" if len(problems) > 1 else "")
    with Progress(generations, f"{what} x {len(seeds)} searches", quiet, unit="gen") as bar:
        while not all(es.done for es in ess):
            for p, es in zip(problems, ess):
                if not es.done:
                    es.tell(objective(p, p.space.from_unit(es.ask())))
            bar.update(best=" ".join(f"{min(s.best_loss for s in es.searches):.3e}" for es in ess[:4]),
                       searching=sum(len(es.active) for es in ess))
    return [[SearchResult("cmaes", p.space.from_unit(s.best_x), s.best_loss, [], s.evaluations, s.blowups, s.stop,
                          s.seed) for s in es.finish()] for p, es in zip(problems, ess)]


def _loss_and_unit_grad(problem: Problem, u: np.ndarray):
    space = problem.space
    values = space.from_unit(u[None])
    errs, grads = problem.errors_and_grad(values, problem.train)
    g_values = np.mean(grads[0], axis=0)[space.free_mask]  # d loss / d free value
    return float(np.mean(errs)), g_values * space.dvalue_dunit(values[0]), values[0]


def polish(problem: Problem, start: np.ndarray, iterations: int = 20, quiet: bool = False) -> SearchResult:
    """L-BFGS (torch, strong-Wolfe line search) from a CMA-ES optimum: the tape's gradients settle
    a narrow valley in a few evaluations where sampling needs hundreds."""
    import torch

    space = problem.space
    u = torch.tensor(np.clip(space.to_unit(start), 0.0, 1.0), dtype=torch.float64, requires_grad=True)
    opt = torch.optim.LBFGS([u], lr=1.0, max_iter=iterations, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-12, tolerance_change=1e-14)
    history, best = [], [np.inf, np.asarray(start, np.float64).copy()]

    def closure():
        opt.zero_grad()
        loss, g_unit, values = _loss_and_unit_grad(problem, u.detach().numpy().clip(0.0, 1.0))
        history.append({"iteration": len(history), "loss": loss, "values": values.tolist()})
        if np.isfinite(loss) and loss < best[0]:
            best[0], best[1] = loss, values.copy()
        u.grad = torch.tensor(np.nan_to_num(g_unit), dtype=torch.float64)
        return torch.tensor(loss if np.isfinite(loss) else 1e30, dtype=torch.float64)

    opt.step(closure)
    _progress(f"[{problem.task}] L-BFGS polish: {len(history)} evaluations, loss {history[0]['loss']:.4e} -> "
              f"{best[0]:.4e}", quiet)
    return SearchResult("lbfgs", best[1], best[0], history, len(history), 0, "lbfgs")


def gradient(
    problem: Problem,
    start: np.ndarray,
    iterations: int = 100,
    lr: float = 0.01,
    quiet: bool = False,
) -> SearchResult:
    """Adam on the mean training error, in normalised coordinates, from `start` (full values)."""
    import torch

    space = problem.space
    free = space.free_mask
    u = torch.tensor(space.to_unit(start), dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([u], lr=lr)
    # decay to lr/100: large steps to travel, small ones to settle in a narrow valley
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=0.01 ** (1.0 / max(iterations, 1)))
    history, best = [], (np.inf, np.asarray(start, np.float64).copy())
    evaluations = 0
    bar = Progress(iterations, f"{problem.task} gradient", quiet, unit="it")
    for it in range(iterations):
        values = space.from_unit(u.detach().numpy()[None])
        errs, grads = problem.errors_and_grad(values, problem.train)
        evaluations += 1
        loss = float(np.mean(errs))
        if not np.isfinite(loss):
            break
        if loss < best[0]:
            best = (loss, values[0].copy())
        g_values = np.mean(grads[0], axis=0)[free]  # d loss / d free value
        g_unit = g_values * space.dvalue_dunit(values[0])
        opt.zero_grad()
        u.grad = torch.tensor(g_unit, dtype=torch.float64)
        opt.step()
        sched.step()
        with torch.no_grad():
            u.clamp_(0.0, 1.0)
        history.append({"iteration": it, "loss": loss, "values": values[0].tolist()})
        bar.update(loss=f"{loss:.4e}")
    bar.close()
    return SearchResult("gradient", best[1], best[0], history, evaluations, 0, "iterations")
