"""Parameter uncertainty and identifiability at the optimum.

Systems that expose signed residuals get the Gauss-Newton covariance sigma^2 (J^T J)^-1 with J from the
engine's batched central differences in normalised coordinates (all 2F perturbed candidates in one
evaluation). A parameter whose standard deviation spans a large part of its bounds (or whose column of J
vanishes) is reported as undetermined. Where parameters carry a prior, the posterior std adds the prior's
rows to J (a MAP estimate's covariance); the data-only std leaves them out, so the report can say which
parameters the data determine and which the prior holds.
"""
from __future__ import annotations

import numpy as np

from .jacobian import jacobian
from .problem import Problem

UNDETERMINED_FRACTION = 0.25  # std larger than this share of the (normalised) bound range


def _std(J: np.ndarray, sigma2: float):
    """Covariance sigma^2 (J^T J)^+ and the std per column; a column with any share in a direction that J does not
    see at all (fewer independent rows than columns) gets an infinite std: the pseudo-inverse would give that
    direction zero variance, i.e. call it perfectly determined."""
    JtJ = J.T @ J
    cov = sigma2 * np.linalg.pinv(JtJ, rcond=1e-12)
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    if J.size:
        # parameter space only: the full left factor would be rows x rows (a 3000 s log at 100 Hz: 298 GiB)
        _, s, vt = np.linalg.svd(J, full_matrices=J.shape[0] < J.shape[1])
        rank = int(np.sum(s > 1e-6 * max(s.max(initial=0.0), 1e-300))) if s.size else 0
        null = vt[rank:]
        if len(null):
            std = np.where(np.linalg.norm(null, axis=0) > 1e-6, np.inf, std)
    return cov, std, JtJ


def _pairs(G: np.ndarray, lengths: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """(g_{t-1}, g_t) of every series, stacked: no pair crosses from one series into the next."""
    ends = np.cumsum(lengths)
    parts = [(G[e - n:e - 1], G[e - n + 1:e]) for e, n in zip(ends, lengths) if n > 1]
    return np.concatenate([p for p, _ in parts]), np.concatenate([c for _, c in parts])


def _bartlett_bandwidth(E: np.ndarray, lengths: list[int]) -> float:
    """Andrews' (1991) AR(1) plug-in bandwidth S_T for the Bartlett kernel (weights 1 - j / S_T, j < S_T), from each
    component's lag-1 correlation pooled over the series."""
    prev, cur = _pairs(E, lengths)
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = np.clip(np.sum(cur * prev, axis=0) / np.sum(prev * prev, axis=0), -0.97, 0.97)
    s4 = np.mean((cur - rho * prev) ** 2, axis=0) ** 2  # innovation variance, squared
    ok = np.isfinite(rho) & (s4 > 0)
    if not ok.any():
        return 0.0
    rho, s4 = rho[ok], s4[ok]
    alpha = np.sum(4 * rho**2 * s4 / ((1 - rho) ** 6 * (1 + rho) ** 2)) / np.sum(s4 / (1 - rho) ** 4)
    return float(min(1.1447 * (alpha * sum(lengths)) ** (1 / 3), max(lengths)))


PREWHITEN_MAX = 0.97  # largest singular value of the scores' VAR(1) matrix (Andrews and Monahan 1992)


def _scores_long_run(J: np.ndarray, r: np.ndarray, lengths: list[int]) -> tuple[np.ndarray, float]:
    """Long-run covariance of the scores g_t = J_t r_t summed over the series (none correlated with another):
    Andrews and Monahan's prewhitened estimate, a VAR(1) fitted to the scores, the Newey-West (Bartlett) sum over its
    innovations, recoloured. The plain Bartlett sum runs 20-30 % low in variance on AR(1) noise at rho 0.95."""
    G = J * r[:, None]
    prev, cur = _pairs(G, lengths)
    A = np.linalg.lstsq(prev, cur, rcond=None)[0].T  # g_t ~ A g_{t-1}
    u, sv, vt = np.linalg.svd(A)
    A = u @ np.diag(np.minimum(sv, PREWHITEN_MAX)) @ vt
    E = cur - prev @ A.T  # the innovations, series by series as _pairs stacks them
    inner = [n - 1 for n in lengths if n > 1]
    bandwidth = _bartlett_bandwidth(E, inner)
    S = E.T @ E
    a = 0
    for n in inner:
        e = E[a:a + n]
        for k in range(1, min(int(np.ceil(bandwidth)), n)):
            gamma = e[k:].T @ e[:-k]
            S += (1.0 - k / bandwidth) * (gamma + gamma.T)
        a += n
    back = np.linalg.inv(np.eye(len(A)) - A)
    return back @ S @ back.T, bandwidth


def _widened_for_correlation(J: np.ndarray, r: np.ndarray, lengths: list[int], std: np.ndarray, per_noise: float):
    """The sandwich (J^T J)^-1 S (J^T J)^-1 with S the scores' long-run covariance: where the residuals of a time
    series are correlated (coloured noise, a structured misfit) their sum carries fewer independent samples than
    rows, and sigma^2 (J^T J)^-1 understates the spread of the fitted values (PD logs with noise correlated over
    50 ms: 2-3x). per_noise scales it to the white covariance's noise (sigma^2 / the residuals' own variance: 1 where
    sigma^2 is estimated from the misfit), so a known noise is not widened by the misfit twice. Each std is never
    narrower than the white one, since the long-run estimate itself runs low on short series: the sandwich's
    columns are scaled up to it, keeping its correlations. Returns the covariance, std, the bandwidth and the
    widening per column; None where the sandwich is empty (no residual left: nothing to estimate it from)."""
    S, bandwidth = _scores_long_run(J, r, lengths)
    A = np.linalg.pinv(J.T @ J, rcond=1e-12)
    sandwich = per_noise * A @ S @ A
    robust = np.sqrt(np.maximum(np.diag(sandwich), 0.0))
    seen = np.isfinite(std) & (std > 0)
    if np.any(seen & (robust <= 0)):
        return None
    wide = np.where(seen, np.maximum(std, robust), std)
    with np.errstate(invalid="ignore", divide="ignore"):
        up = np.where(seen, wide / robust, 1.0)
    # a direction the data never see stays unseen (infinite std, kept from the white formula); a combination they
    # do see keeps its information, which zeroing the unseen columns' rows had thrown away (review of stop 57)
    return up[:, None] * sandwich * up[None, :], wide, bandwidth, np.where(seen, wide / np.where(seen, std, 1.0), 1.0)


DETERMINED = 0.3  # a parameter is determined by the data when its data-only std is below this share of its value
MISFIT_CHI2 = 100.0  # chi^2/dof of noise-normalised residuals above this is said: the model misses the data by more
# than 10 noise sigmas RMS (the real fish: 13-20; clips from another swimming model: 600 - 850 000, said nothing)
OPTIMA_SPREAD_STDS = 4.0  # searches that fit as well disagreeing by more than this many stated stds: the std is wrong


def _relative(space, fitted: np.ndarray, std: np.ndarray) -> np.ndarray:
    """std as a share of the value: e-folds for log-scale parameters, std / |value| for linear ones."""
    v = np.asarray(fitted, np.float64)[space.free_mask]  # a log-scale parameter's std is d(log v) = dv / v too
    with np.errstate(divide="ignore", invalid="ignore"):
        return std / np.maximum(np.abs(v), 1e-300)


def uncertainty(problem: Problem, fitted: np.ndarray, step: float = 1e-3) -> dict:
    """The training residuals' Jacobian in unit coordinates at `fitted`, by central differences of `step` in one
    batched evaluation: always its own, so the stds are a function of the reported values (a least-squares search's
    1e-4 Jacobian had been reused, inside the swimmer's residual jitter; stop 56)."""
    space = problem.space
    out = {"method": None, "std": {}, "correlation": None, "undetermined": [], "warning": None}
    free = space.free
    if not problem.has_residuals or not free:
        out["method"] = "none: this system exposes no residual vector"
        return out
    u0 = np.clip(space.to_unit(fitted), 0.0, 1.0)
    F = len(u0)
    jac = jacobian(lambda U: problem.residuals(space.from_unit(U), problem.train), u0, step, 0.0, 1.0)
    r0 = jac.f0
    if not np.all(np.isfinite(r0)):
        out["method"] = "none: residuals not finite at the optimum"
        if not np.any(np.isfinite(r0)):  # not one residual: nothing the data say reaches the parameters
            names = [p.name for p in free]
            out.update(undetermined=names,
                       warning="no training residual is finite at the fitted values (the model does not show the "
                               f"observed behaviour, e.g. never reaches the event): the data determine none of "
                               f"{', '.join(names)}")
        return out
    at_bound = [p.name for p, u in zip(free, u0) if u < 1e-3 or u > 1 - 1e-3]
    out["at_bound"] = at_bound
    names = [p.name for p in free]
    n_prior = len(space.priors)
    if len(r0) <= F and not n_prior:
        # as many unknowns as data: an exact fit exists along a whole family, so no std means anything
        out.update(method=f"none: {len(r0)} residuals for {F} free parameters", undetermined=names,
                   warning=f"the data ({len(r0)} residuals) cannot determine {F} free parameters: {', '.join(names)}"
                           "; trust the predictions, not the individual values")
        return out
    J = jac.J  # (R, F) in unit coordinates
    dof = max(len(r0) - F, 1)
    chi2_dof = float(r0 @ r0) / dof
    # noise-normalised residuals: the noise is known (sigma = 1); else estimate it from the misfit
    sigma2 = 1.0 if problem.noise_normalised else chi2_dof
    out["noise_variance"] = sigma2  # of a residual: what a change of the objective is measured in
    cov_u, std_u, JtJ = _std(J, sigma2)
    series = problem.residual_series(problem.train)
    widened = None
    if series:
        if sum(series) != len(r0):
            raise ValueError(f"task {problem.task!r}: residual_series sums to {sum(series)} rows, its residuals have "
                             f"{len(r0)}")
        got = (_widened_for_correlation(J, r0, series, std_u, sigma2 / chi2_dof)
               if max(series) > 2 and chi2_dof > 0 else None)
        if got is not None:
            cov_u, std_u, bandwidth, widened = got
            out["correlated_residuals"] = {"bandwidth": bandwidth,
                                           "widening": {p.name: float(f) for p, f in zip(free, widened)}}
    scale = np.abs(space.dvalue_dunit(fitted))
    col_norm = np.linalg.norm(J, axis=0)
    und = [p.name for i, p in enumerate(free)
           if std_u[i] > UNDETERMINED_FRACTION or col_norm[i] < 1e-9 * max(col_norm.max(), 1e-300)]
    data_rel = _relative(space, fitted, std_u * scale)
    # a value held at a bound is the bound's, not the data's (a fish model's Magnus lift at its upper bound had been
    # listed as determined; review of stop 55)
    out["determined_by_data"] = [p.name for p, x in zip(free, data_rel) if x < DETERMINED and p.name not in at_bound]
    misfit = None
    if problem.noise_normalised:
        out["chi2_per_dof"] = chi2_dof
        if chi2_dof > MISFIT_CHI2:
            misfit = (f"the model misses the training data by {np.sqrt(chi2_dof):.0f} noise sigmas RMS (chi^2/dof "
                      f"{chi2_dof:.3g}): it does not reproduce them, so the fitted values describe no measurement "
                      "and their stds mean little")
        # where the model misses the data by more than their noise, the std with the misfit taken as noise too
        infl = np.sqrt(max(chi2_dof, 1.0))
        out["std_inflated_by_misfit"] = {p.name: float(s) for p, s in zip(free, infl * std_u * scale)}
    if n_prior:
        # the prior rows are exact (no noise estimate): their residuals are already in units of their scale
        data_std = {p.name: float(s) for p, s in zip(free, std_u * scale)}
        P = space.prior_jacobian_unit(fitted)
        if widened is None:
            cov_u, std_u, JtJ = _std(np.concatenate([J / np.sqrt(sigma2), P]), 1.0)
        else:  # the data's information is the pseudo-inverse of their widened covariance
            JtJ = np.linalg.pinv(cov_u, rcond=1e-12) + P.T @ P
            cov_u = np.linalg.pinv(JtJ, rcond=1e-12)
            std_u = np.sqrt(np.maximum(np.diag(cov_u), 0.0))
        out["data_only_std"] = data_std
        out["held_by_prior"] = [p.name for p in free if p.prior is not None and p.name not in out["determined_by_data"]
                                and p.name not in at_bound]
    std = std_u * scale
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov_u / np.outer(std_u, std_u)
    notes = [misfit] if misfit else []
    if und:
        notes.append(f"the data cannot determine: {', '.join(und)}")
    if at_bound:
        notes.append(f"at a bound (the optimum may lie outside; std not meaningful): {', '.join(at_bound)}")
    cols = [n for n, k in zip(names, jac.kinds) if k == "none"]
    if cols:
        notes.append(f"no finite-difference column (no residual on either side): {', '.join(cols)}")
    out.update(
        method="gauss-newton: sigma^2 (J^T J)^-1, J by batched central finite differences"
               + (", at least the prewhitened Newey-West sandwich over each time series" if widened is not None else "")
               + (" (posterior: prior rows added)" if n_prior else ""),
        std={p.name: float(s) for p, s in zip(free, std)},
        correlation={"names": names, "matrix": np.nan_to_num(corr).round(4).tolist()},
        undetermined=und,
        warning="; ".join(notes) or None,
        condition_number=float(np.linalg.cond(JtJ)) if np.all(np.isfinite(JtJ)) else None,
        finite_difference=jac.kinds,
    )
    return out


def optima_from_report(space, report: dict | None) -> list:
    """(free values, objective) of each seeded search in a spread_of_optima report (restarts, searches_spread)."""
    names = [p.name for p in space.free]
    return [(np.array([o["values"][n] for n in names], np.float64), float(o["train_loss"]))
            for o in (report or {}).get("optima", [])]


def check_against_optima(unc: dict, space, fitted: np.ndarray, fitted_objective: float, optima: list,
                         std: dict) -> None:
    """Where seeded searches that fit as well as the best (their objective within the 99 % chi-square region of as
    many parameters, in units of the noise variance) end farther apart than OPTIMA_SPREAD_STDS of a parameter's
    stated std, the local Gauss-Newton std is wrong there (several optima, or a Jacobian that changes faster than
    its step): the parameter is not determined, and this is said. The fish fitted on its rotated-marker files alone
    had stated blunt drag +-0.025 % while its restarts spanned 0.180-0.2025, and called it determined or not by the
    seed (review of stop 55). Edits `unc` in place; optima: (free values, objective) per search."""
    noise = unc.get("noise_variance")
    if not optima or not noise or not np.isfinite(fitted_objective):
        return
    # scipy.special's inverse survival function, not scipy.stats (0.6 s of import, half a fit pd; stop 59's bench)
    from scipy.special import chdtri

    names = [p.name for p in space.free]
    best = min([fitted_objective, *(o for _, o in optima if np.isfinite(o))])
    window = float(chdtri(len(names), 0.01)) * noise
    rows = [np.asarray(fitted, np.float64)[space.free_mask]] + [v for v, o in optima if o - best <= window]
    if len(rows) < 2:
        return
    vals = np.array(rows)
    width = vals.max(0) - vals.min(0)
    wrong = []
    for n, w in zip(names, width):
        sd = std.get(n)
        if sd is not None and np.isfinite(sd) and w > OPTIMA_SPREAD_STDS * sd:
            wrong.append((n, float(w / sd) if sd > 0 else None))  # None: a std of 0
    if not wrong:
        return
    unc["std_understated"] = dict(wrong)
    unc["determined_by_data"] = [n for n in unc.get("determined_by_data", []) if n not in dict(wrong)]
    unc["undetermined"] = list(dict.fromkeys([*unc.get("undetermined", []), *dict(wrong)]))
    said = (f"searches that fit as well as the best end apart by "
            f"{', '.join(f'{r:.0f}x' if r is not None else 'any multiple of' for _, r in wrong)} the stated std of "
            f"{', '.join(n for n, _ in wrong)}: the std from the local Jacobian understates them (several optima, or a "
            "Jacobian that changes within its step); read their spread across the searches")
    unc["warning"] = "; ".join(w for w in (unc.get("warning"), said) if w)


def not_pinned_text(spread: dict, unc: dict) -> str:
    """The parameters seeded searches leave apart, and those they agree on only because a prior holds them: "none"
    beside "the data cannot determine X, held by the prior" had read as a contradiction (review of stop 55)."""
    apart = list(spread.get("not_pinned") or [])
    by_prior = [n for n in (unc or {}).get("held_by_prior") or [] if n not in apart]
    text = ", ".join(apart) or "none"
    if by_prior:
        text += f" ({', '.join(by_prior)} agree because the prior holds them, not the data)"
    return text
