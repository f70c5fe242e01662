"""Identifiability restarts: after a fit, further seeded searches side by side (one batched evaluation per
generation for all), each optimum validated on the held-out conditions.

What the data leave open shows as spread: of the fitted values (in normalised coordinates, so parameters of
any magnitude compare) and, what a user ships, of the held-out prediction. A parameter is called pinned only
where every search that fits about as well as the best agrees on it; the Gauss-Newton std cannot say this
when there are fewer residuals than parameters (it then scales with a near-zero residual).
"""
from __future__ import annotations

import numpy as np

from .problem import Problem, finite_or_inf
from .search import objective, restarts

PINNED_SPREAD = 0.05  # max - min of a parameter's normalised value across the good searches
GOOD_LOSS_FACTOR = 2.0  # a search "fits as well" when its training loss is within this factor of the best


def identifiability_restarts(problem: Problem, fitted: np.ndarray, seeds: list[int], popsize: int | None = 16,
                             generations: int = 100, sigma0: float = 0.2, quiet: bool = True,
                             method: str = "cmaes") -> dict:
    """method: the fit's search; where it ends in a least-squares polish, each restart is polished the same way,
    so that the spread is the data's, not that of an unfinished search."""
    res = restarts(problem, seeds, popsize=popsize, generations=generations, sigma0=sigma0, quiet=quiet)
    polished = method.endswith("least-squares") and problem.has_residuals
    if polished:
        from .least_squares import polish_if_better

        for r in res:
            if np.isfinite(r.best_loss):
                r.best_values, r.best_loss = polish_if_better(problem, r.best_values, r.best_loss)
    out = spread_of_optima(problem, fitted, [r.seed for r in res], np.array([r.best_values for r in res]),
                           np.array([r.best_loss for r in res]))
    return {"seeds": [int(s) for s in seeds], "popsize": popsize, "generations": generations,
            "search": "cmaes+least-squares" if polished else "cmaes"} | out


def spread_of_optima(problem: Problem, fitted: np.ndarray, seeds: list[int], vals: np.ndarray,
                     loss: np.ndarray) -> dict:
    """What a set of optima (one per seeded search) says: each one's held-out errors, the spread of the fitted
    values over those that fit about as well as the best, which parameters that pins, and the held-out spread.
    One batched evaluation for all optima."""
    space = problem.space
    fitted_loss = float(objective(problem, fitted[None])[0])
    if problem.held_out:
        held = finite_or_inf(problem.validation_errors(np.concatenate([fitted[None], vals]), problem.held_out)[0])
        held_fit, held = held[0], held[1:]
    else:
        held_fit, held = None, np.full((len(vals), 0), np.nan)
    best = np.nanmin(np.append(loss, fitted_loss))
    good = loss <= max(GOOD_LOSS_FACTOR * best, 1e-12)
    units = space.to_unit(vals[good] if good.any() else vals)
    spread = units.max(0) - units.min(0)
    free = space.free
    out = {
        "optima": [{"seed": int(sd), "values": space.as_dict(v), "train_loss": float(lo),
                    "held_out_errors": {c.name: float(e) for c, e in zip(problem.held_out, h)},
                    "held_out_mean_error": float(np.mean(h)) if len(h) else None, "fits_as_well": bool(g)}
                   for sd, v, lo, h, g in zip(seeds, vals, loss, held, good)],
        "spread_unit": {p.name: float(d) for p, d in zip(free, spread)},
        "pinned": [p.name for p, d in zip(free, spread) if d < PINNED_SPREAD],
        "not_pinned": [p.name for p, d in zip(free, spread) if d >= PINNED_SPREAD],
        "meaning": (f"spread_unit: max - min over the searches whose training loss is within {GOOD_LOSS_FACTOR:g}x "
                    "of the best, in normalised [0, 1] coordinates (log scale across the bounds); pinned: < "
                    f"{PINNED_SPREAD}; held_out_spread: max - min of each held-out error over those searches and the "
                    "fit itself (searches_fitting_as_well of them; _all: every search)"),
    }
    if problem.has_residuals:
        n_res = int(np.asarray(problem.residuals(fitted[None], problem.train)).shape[1])
        out["residuals"] = n_res
        out["unconstrained_directions_at_least"] = max(len(free) - n_res, 0)
    if problem.held_out:
        rows = np.concatenate([held_fit[None], held[good]]) if good.any() else held_fit[None]
        out["held_out_spread"] = {c.name: float(np.ptp(rows[:, j])) for j, c in enumerate(problem.held_out)}
        means = rows.mean(axis=1)
        out["held_out_mean_error_spread"] = float(np.ptp(means))
        out["held_out_mean_error_range"] = [float(means.min()), float(means.max())]
        # every search, also those that did not fit as well (a search stuck elsewhere predicts elsewhere)
        every = np.concatenate([held_fit[None], held])
        out["held_out_mean_error_spread_all"] = float(np.ptp(every.mean(axis=1)))
    out["searches_fitting_as_well"] = int(good.sum())
    return out
