"""The engine's least-squares search: bounded Levenberg-Marquardt on a Problem's residuals (plus its parameters'
prior residuals), in the normalised [0, 1] coordinates of the free parameters.

Smooth residuals (a PD joint's trajectory, a fish's speed and gait features) want a local second-order method,
not thousands of samples: every iteration is ONE batched evaluation holding the trial point and its central-
difference neighbours (wrenorm.jacobian), so an accepted trial brings its own Jacobian and needs no extra call.
CMA-ES stays the search for event observables and for global restarts; a system declares which it uses.
"""
from __future__ import annotations

import numpy as np

from .errors import AllCandidatesFailed
from .jacobian import jacobian
from .problem import Problem
from .progress import Progress

STEP = 1e-4  # finite-difference step in normalised coordinates


def _evaluate(problem: Problem, u: np.ndarray, step: float):
    """Residuals (data, then prior) and their Jacobian at unit point u, one batched call."""
    space = problem.space
    jac = jacobian(lambda U: problem.residuals(space.from_unit(U), problem.train), u, step, 0.0, 1.0)
    values = space.from_unit(u[None])
    r = np.concatenate([jac.f0, space.prior_residuals(values)[0]])
    J = np.concatenate([jac.J, space.prior_jacobian_unit(values[0])])
    return r, J, jac


def levenberg_marquardt(problem: Problem, start: np.ndarray, iterations: int = 50, step: float = STEP,
                        quiet: bool = False):
    """Minimise |r|^2 + |prior|^2 from `start` (full parameter values). Returns (SearchResult, r, J) at the
    optimum: the residuals and Jacobian the uncertainty can reuse."""
    from .search import SearchResult

    space = problem.space
    u = np.clip(space.to_unit(start), 0.0, 1.0)
    r, J, jac = _evaluate(problem, u, step)
    evaluations = jac.evaluations
    if not np.all(np.isfinite(r)):
        raise AllCandidatesFailed(f"[{problem.task}] the residuals are not finite at the start of the least-squares "
                                  "search; use --search cmaes or narrow the bounds")
    cost = float(r @ r)
    mu = 1e-3
    history = [{"iteration": 0, "cost": cost, "values": space.from_unit(u[None])[0].tolist(), "mu": mu}]
    stop = "iterations"
    bar = Progress(iterations, f"{problem.task} least squares", quiet, unit="it")
    for it in range(1, iterations + 1):
        g = J.T @ r
        JtJ = J.T @ J
        pg = u - np.clip(u - g, 0.0, 1.0)  # projected gradient: zero at a constrained optimum
        if np.max(np.abs(pg)) < 1e-14 * max(1.0, cost):
            stop = "gradient"
            break
        scale = np.maximum(np.diag(JtJ), 1e-30)
        while True:
            u_new = np.clip(u + np.linalg.solve(JtJ + mu * np.diag(scale), -g), 0.0, 1.0)
            r_new, J_new, jac = _evaluate(problem, u_new, step)
            evaluations += jac.evaluations
            cost_new = float(r_new @ r_new) if np.all(np.isfinite(r_new)) else np.inf
            du = u_new - u
            predicted = -(2.0 * g @ du + du @ JtJ @ du)
            if cost_new < cost:
                break
            mu *= 4.0
            if mu > 1e12:
                stop = "no decrease"
                break
        if stop == "no decrease":
            break
        gain = (cost - cost_new) / predicted if predicted > 0 else 0.0
        dcost, dx = cost - cost_new, float(np.max(np.abs(u_new - u)))
        u, r, J, cost = u_new, r_new, J_new, cost_new
        mu = max(mu / 3.0 if gain > 0.75 else (mu * 2.0 if gain < 0.25 else mu), 1e-12)
        history.append({"iteration": it, "cost": cost, "values": space.from_unit(u[None])[0].tolist(), "mu": mu})
        bar.update(cost=f"{cost:.6e}", mu=f"{mu:.2g}")
        if dcost <= 1e-12 * cost or dx < 1e-10:
            stop = "cost" if dcost <= 1e-12 * cost else "step"
            break
    if stop != "iterations":  # done early: the bar ends full at the iterations it took, with why
        bar.set_total(bar.n)
        bar.update(0, force=True, stop=stop)
    bar.close()
    result = SearchResult("least-squares", space.from_unit(u[None])[0], cost, history, evaluations, 0, stop)
    return result, r, J


def polish_if_better(problem: Problem, values: np.ndarray, loss: float, quiet: bool = True) -> tuple[np.ndarray, float]:
    """A search's optimum polished by Levenberg-Marquardt: (values, loss) of whichever of the two fits better
    (the polish wins ties)."""
    lsq, _, _ = levenberg_marquardt(problem, values, quiet=quiet)
    return (lsq.best_values, lsq.best_loss) if lsq.best_loss <= loss else (values, loss)
