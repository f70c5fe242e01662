"""The engine's one finite-difference Jacobian: every perturbed point and the centre as rows of ONE batched
evaluation (on a batched simulator a column costs as much as the centre alone).

Central differences where both sides exist; one-sided where a side leaves the box [lower, upper] or where
its evaluation has no value (NaN: a blown-up candidate, a rope that never hits itself); a column with no
usable side is zero and marked "none", so the caller can tell an unknown sensitivity from a null one.
Used for the Gauss-Newton uncertainty, least-squares fits, the rope's command sensitivity and the
correction's local model.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass
class Jacobian:
    J: np.ndarray  # (m, n) d f / d x
    f0: np.ndarray  # (m,) f at the centre
    kinds: list  # per column: "central", "forward", "backward" or "none"
    evaluations: int  # rows in the one batched call

    @property
    def usable(self) -> np.ndarray:
        return np.array([k != "none" for k in self.kinds])


def jacobian(f: Callable[[np.ndarray], np.ndarray], x, step, lower=None, upper=None) -> Jacobian:
    """d f / d x at x for a batched map f: (B, n) -> (B, m), in one call of f with 2n + 1 rows.

    step: scalar or (n,) perturbation; lower, upper: the box the perturbed points must stay in.
    """
    x = np.asarray(x, dtype=np.float64).reshape(-1)
    n = x.shape[0]
    h = np.broadcast_to(np.asarray(step, dtype=np.float64), (n,))
    lo = np.full(n, -np.inf) if lower is None else np.broadcast_to(np.asarray(lower, np.float64), (n,))
    hi = np.full(n, np.inf) if upper is None else np.broadcast_to(np.asarray(upper, np.float64), (n,))
    eye = np.eye(n, dtype=bool)
    plus = np.where(eye, np.minimum(x + h, hi)[None], x[None])
    minus = np.where(eye, np.maximum(x - h, lo)[None], x[None])
    X = np.concatenate([x[None], plus, minus])
    e = np.asarray(f(X), dtype=np.float64)
    e = e.reshape(len(X), -1)
    ok = np.all(np.isfinite(e), axis=1)
    J = np.zeros((e.shape[1], n))
    kinds = []
    for i in range(n):
        p, m = 1 + i, 1 + n + i
        dp, dm = plus[i, i] - x[i], x[i] - minus[i, i]
        if ok[p] and ok[m] and dp > 0 and dm > 0:
            J[:, i] = (e[p] - e[m]) / (dp + dm)
            kinds.append("central")
        elif ok[p] and ok[0] and dp > 0:
            J[:, i] = (e[p] - e[0]) / dp
            kinds.append("forward")
        elif ok[m] and ok[0] and dm > 0:
            J[:, i] = (e[0] - e[m]) / dm
            kinds.append("backward")
        else:
            kinds.append("none")
    return Jacobian(J, e[0], kinds, len(X))
