"""Searches over a Problem's free parameters, in normalised [0, 1] coordinates.

- `cmaes`: pycma, seeded and bounded; each generation's whole population is one batched
  `Problem.errors` call. The search state is saved after every generation so a killed fit
  resumes to the same result as an uninterrupted one.
- `gradient`: Adam (torch) on gradients from the system's differentiable kernel (Warp tape).
"""
from __future__ import annotations

import os
import pickle
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from .errors import AllCandidatesFailed, InputError
from .problem import Problem, finite_or_inf
from .results import write_atomic

# pycma ranks candidates, so a blown-up candidate only needs to rank last.
_BLOWUP_LOSS = 1e30
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


def mean_loss(problem: Problem, values: np.ndarray, conditions) -> tuple[np.ndarray, np.ndarray]:
    """(B,) loss = mean error over conditions, inf for any blown-up condition; and (B, C) errors."""
    errs = finite_or_inf(problem.errors(np.atleast_2d(values), conditions))
    with np.errstate(invalid="ignore"):
        return errs.mean(axis=1), errs


def _progress(msg: str, quiet: bool) -> None:
    if not quiet:
        print(msg, file=sys.stderr, flush=True)


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
    tolfun: float = 1e-12,
    on_generation: Callable[[dict], None] | None = None,
) -> SearchResult:
    import cma

    space = problem.space
    nfree = len(space.free)
    if nfree == 0:
        loss, _ = mean_loss(problem, space.measured[None], problem.train)
        return SearchResult("cmaes", space.measured.copy(), float(loss[0]), stop="no free parameters")
    x0 = space.to_unit(space.measured if start is None else start)
    state = None
    if resume and checkpoint and Path(checkpoint).exists():
        with open(checkpoint, "rb") as f:
            state = pickle.load(f)
        saved_free = state.get("free", [p.name for p in space.free])
        if saved_free != [p.name for p in space.free]:
            raise InputError(str(checkpoint), "free parameters",
                             f"the interrupted search fits {saved_free}, this run {[p.name for p in space.free]}; "
                             "resume with the same --free/--freeze")
        es, history, counts = state["es"], state["history"], state["counts"]
        np.random.set_state(state["np_random"])
        _progress(f"resuming {problem.task} search at generation {len(history)}", quiet)
    else:
        np.random.seed(seed)
        opts = {
            "seed": seed + 1,  # pycma treats seed 0 as "random"
            "bounds": [0.0, 1.0],
            "maxiter": generations,
            "tolfun": tolfun,
            "tolx": 1e-10,
            "verbose": -9,
        }
        if popsize:
            opts["popsize"] = popsize
        if nfree == 1:
            # pycma needs at least 2 dimensions; pad with a dummy coordinate
            x0 = np.append(x0, 0.5)
        es = cma.CMAEvolutionStrategy(np.clip(x0, 1e-6, 1 - 1e-6), sigma0, opts)
        history, counts = [], {"evaluations": 0, "blowups": 0}
    best = state["best"] if state else (np.inf, space.measured.copy())
    t0 = time.perf_counter()
    while not es.stop() and len(history) < generations:
        units = np.asarray(es.ask())
        values = space.from_unit(units[:, :nfree])
        loss, _ = mean_loss(problem, values, problem.train)
        failed = ~np.isfinite(loss)
        counts["evaluations"] += len(loss)
        counts["blowups"] += int(failed.sum())
        if failed.all():
            raise AllCandidatesFailed(
                f"generation {len(history)}: every one of {len(loss)} candidates blew up (NaN/Inf or runaway). "
                "Narrow the parameter bounds, lower sigma0, or use a finer resolution (smaller time step)."
            )
        es.tell(list(units), list(np.where(failed, _BLOWUP_LOSS, loss)))
        i = int(np.argmin(loss))
        if loss[i] < best[0]:
            best = (float(loss[i]), values[i].copy())
        rec = {
            "generation": len(history),
            "best": float(loss[i]),
            "median": float(np.median(loss[~failed])),
            "best_so_far": best[0],
            "blowups": int(failed.sum()),
            "sigma": float(es.sigma),
            "values": values[i].tolist(),
        }
        history.append(rec)
        if on_generation:
            on_generation(rec)
        _progress(
            f"[{problem.task}] gen {rec['generation'] + 1:3d}/{generations}  best {rec['best']:.4e}  "
            f"median {rec['median']:.4e}  sigma {rec['sigma']:.3g}  blowups {rec['blowups']}  "
            f"{time.perf_counter() - t0:6.1f}s",
            quiet,
        )
        if checkpoint:
            blob = {"es": es, "history": history, "counts": counts, "best": best, "np_random": np.random.get_state(),
                    "free": [p.name for p in space.free]}
            write_atomic(checkpoint, pickle.dumps(blob))
        if _SLOW:  # fault-injection hook for the kill -9 / --resume test
            time.sleep(_SLOW)
    stop = ", ".join(f"{k}" for k in es.stop()) or ("generations" if len(history) >= generations else "")
    return SearchResult("cmaes", best[1], best[0], history, counts["evaluations"], counts["blowups"], stop)


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
    _progress(f"[{problem.task}] L-BFGS polish: {len(history)} evaluations, loss {history[0]['loss']:.4e} -> {best[0]:.4e}", quiet)
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
        if it % 10 == 0 or it == iterations - 1:
            _progress(f"[{problem.task}] grad it {it + 1:4d}/{iterations}  loss {loss:.4e}", quiet)
    return SearchResult("gradient", best[1], best[0], history, evaluations, 0, "iterations")


def cmaes_restarts(
    problem: Problem,
    seeds: list[int],
    popsize: int = 16,
    generations: int = 60,
    sigma0: float = 0.2,
    start: np.ndarray | None = None,
    quiet: bool = False,
) -> list[SearchResult]:
    """Independent seeded CMA-ES searches side by side: every generation, all their populations
    are evaluated in ONE batched call. The spread of their optima is an honest uncertainty for
    parameters the observable barely constrains (where a Jacobian-based std can mislead)."""
    import cma

    space = problem.space
    nfree = len(space.free)
    x0 = np.clip(space.to_unit(space.measured if start is None else start), 1e-6, 1 - 1e-6)
    pad = nfree == 1
    ess = []
    for s in seeds:
        np.random.seed(s)
        ess.append(cma.CMAEvolutionStrategy(np.append(x0, 0.5) if pad else x0, sigma0, {
            "seed": s + 1, "bounds": [0.0, 1.0], "maxiter": generations, "popsize": popsize,
            "tolfun": 1e-12, "tolx": 1e-10, "verbose": -9}))
    results = [SearchResult("cmaes", space.measured.copy(), np.inf) for _ in seeds]
    t0 = time.perf_counter()
    for gen in range(generations):
        active = [i for i, es in enumerate(ess) if not es.stop()]
        if not active:
            break
        asked = {i: np.asarray(ess[i].ask()) for i in active}
        units = np.concatenate([asked[i] for i in active])
        loss, _ = mean_loss(problem, space.from_unit(units[:, :nfree]), problem.train)
        start_row = 0
        for i in active:
            n = len(asked[i])
            li = loss[start_row:start_row + n]
            vals = space.from_unit(asked[i][:, :nfree])
            start_row += n
            failed = ~np.isfinite(li)
            results[i].evaluations += n
            results[i].blowups += int(failed.sum())
            if failed.all():
                continue
            ess[i].tell(list(asked[i]), list(np.where(failed, _BLOWUP_LOSS, li)))
            j = int(np.argmin(li))
            if li[j] < results[i].best_loss:
                results[i].best_loss, results[i].best_values = float(li[j]), vals[j].copy()
            results[i].history.append({"generation": gen, "best": float(li[j])})
        _progress(f"[{problem.task}] {len(active)} searches, gen {gen + 1:3d}/{generations}  best "
                  f"{min(r.best_loss for r in results):.4e}  {time.perf_counter() - t0:6.1f}s", quiet)
    return results
