"""Parameter uncertainty and identifiability at the optimum.

Systems that expose signed residuals get the Gauss-Newton covariance sigma^2 (J^T J)^-1 with
J from central finite differences in normalised coordinates, all 2F perturbed candidates in
one batched evaluation. A parameter whose standard deviation spans a large part of its
bounds (or whose column of J vanishes) is reported as undetermined.
"""
from __future__ import annotations

import numpy as np

from .problem import Problem

UNDETERMINED_FRACTION = 0.25  # std larger than this share of the (normalised) bound range


def uncertainty(problem: Problem, fitted: np.ndarray, step: float = 1e-3) -> dict:
    space = problem.space
    out = {"method": None, "std": {}, "correlation": None, "undetermined": [], "warning": None}
    residuals = getattr(problem, "residuals", None)
    free = space.free
    if residuals is None or not free:
        out["method"] = "none: this system exposes no residual vector"
        return out
    u0 = space.to_unit(fitted)
    F = len(u0)
    h = np.full(F, step)
    lo = np.clip(u0 - h, 0.0, 1.0)
    hi = np.clip(u0 + h, 0.0, 1.0)
    units = np.concatenate([u0[None], np.where(np.eye(F, dtype=bool), hi[None], u0[None]),
                            np.where(np.eye(F, dtype=bool), lo[None], u0[None])])
    r = np.asarray(residuals(space.from_unit(units), problem.train), dtype=np.float64)  # (1+2F, R)
    if not np.all(np.isfinite(r)):
        out["method"] = "none: residuals not finite near the optimum"
        return out
    r0 = r[0]
    at_bound = [p.name for p, u in zip(free, u0) if u < 1e-3 or u > 1 - 1e-3]
    out["at_bound"] = at_bound
    if len(r0) <= F:
        # as many unknowns as data: an exact fit exists along a whole family, so no std means anything
        names = [p.name for p in free]
        out.update(method=f"none: {len(r0)} residuals for {F} free parameters", undetermined=names,
                   warning=f"the data ({len(r0)} residuals) cannot determine {F} free parameters: {', '.join(names)}"
                           "; trust the predictions, not the individual values")
        return out
    J = ((r[1:F + 1] - r[F + 1:]) / (hi - lo)[:, None]).T  # (R, F) in unit coordinates
    dof = max(len(r0) - F, 1)
    sigma2 = float(r0 @ r0) / dof
    JtJ = J.T @ J
    cov_u = sigma2 * np.linalg.pinv(JtJ, rcond=1e-12)
    std_u = np.sqrt(np.maximum(np.diag(cov_u), 0.0))
    scale = space.dvalue_dunit(fitted)
    std = std_u * np.abs(scale)
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov_u / np.outer(std_u, std_u)
    col_norm = np.linalg.norm(J, axis=0)
    und = [p.name for i, p in enumerate(free)
           if std_u[i] > UNDETERMINED_FRACTION or col_norm[i] < 1e-9 * max(col_norm.max(), 1e-300)]
    notes = []
    if und:
        notes.append(f"the data cannot determine: {', '.join(und)}")
    if at_bound:
        notes.append(f"at a bound (the optimum may lie outside; std not meaningful): {', '.join(at_bound)}")
    out.update(
        method="gauss-newton: sigma^2 (J^T J)^-1, J by batched central finite differences",
        std={p.name: float(s) for p, s in zip(free, std)},
        correlation={"names": [p.name for p in free], "matrix": np.nan_to_num(corr).round(4).tolist()},
        undetermined=und,
        warning="; ".join(notes) or None,
        condition_number=float(np.linalg.cond(JtJ)) if np.all(np.isfinite(JtJ)) else None,
    )
    return out
