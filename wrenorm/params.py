"""Named, bounded, freezable parameters and the normalised space searches work in.

A search sees only the free parameters, each mapped to [0, 1] (linear or log scale), so one
step size suits parameters of any magnitude. Frozen parameters keep their measured value.
A parameter may carry a Gaussian prior (centre, scale): the paper's procedure starts from the
measured values and lets a parameter move only as far as the data demand; its normalised
deviation (value - centre) / scale (in log space for log-scale parameters) joins the residuals.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .errors import InputError


@dataclass(frozen=True)
class Parameter:
    name: str
    measured: float
    lower: float
    upper: float
    scale: str = "linear"  # "linear" or "log"
    frozen: bool = False
    unit: str = ""
    doc: str = ""
    prior: tuple[float, float] | None = None  # (centre, scale); log-scale parameters: scale in natural-log units

    def __post_init__(self):
        if self.scale not in ("linear", "log"):
            raise InputError("parameters", self.name, f"scale must be 'linear' or 'log', got {self.scale!r}")
        if not (np.isfinite(self.lower) and np.isfinite(self.upper) and self.lower < self.upper):
            raise InputError("parameters", self.name,
                             f"bounds must be finite with lower < upper, got [{self.lower}, {self.upper}]")
        if self.scale == "log" and self.lower <= 0:
            raise InputError("parameters", self.name, f"log-scale bounds must be positive, got lower={self.lower}")
        if not (self.lower <= self.measured <= self.upper):
            raise InputError("parameters", self.name,
                             f"measured value {self.measured} outside bounds [{self.lower}, {self.upper}]")
        if self.prior is not None:
            centre, scale = (float(x) for x in self.prior)
            if not (np.isfinite(centre) and np.isfinite(scale) and scale > 0):
                raise InputError("parameters", self.name,
                                 f"prior needs a finite centre and a scale > 0, got {self.prior}")
            if self.scale == "log" and centre <= 0:
                raise InputError("parameters", self.name,
                                 f"a log-scale parameter's prior centre must be > 0, got {centre}")


@dataclass
class ParameterSpace:
    parameters: list[Parameter]
    _index: dict = field(init=False, repr=False)

    def __post_init__(self):
        names = [p.name for p in self.parameters]
        if len(set(names)) != len(names):
            raise InputError("parameters", "name", f"duplicate names in {names}")
        self._index = {n: i for i, n in enumerate(names)}

    # --- views -----------------------------------------------------------
    @property
    def names(self) -> list[str]:
        return [p.name for p in self.parameters]

    @property
    def free(self) -> list[Parameter]:
        return [p for p in self.parameters if not p.frozen]

    @property
    def free_names(self) -> list[str]:
        return [p.name for p in self.free]

    @property
    def free_mask(self) -> np.ndarray:
        return np.array([not p.frozen for p in self.parameters])

    @property
    def measured(self) -> np.ndarray:
        return np.array([p.measured for p in self.parameters], dtype=np.float64)

    def index(self, name: str) -> int:
        return self._index[name]

    def __getitem__(self, name: str) -> Parameter:
        return self.parameters[self._index[name]]

    def with_changes(self, **changes: dict) -> ParameterSpace:
        """New space with per-parameter field changes, e.g. with_changes(J={"frozen": True})."""
        out = []
        for p in self.parameters:
            out.append(replace(p, **changes[p.name]) if p.name in changes else p)
        unknown = set(changes) - set(self.names)
        if unknown:
            raise InputError("parameters", ",".join(sorted(unknown)), f"unknown parameter; known: {self.names}")
        return ParameterSpace(out)

    def as_dict(self, values: np.ndarray) -> dict[str, float]:
        return {n: float(v) for n, v in zip(self.names, np.asarray(values).reshape(-1))}

    # --- normalised coordinates -------------------------------------------
    def _lo_hi(self):
        free = self.free
        log = np.array([p.scale == "log" for p in free])
        lo = np.array([np.log(p.lower) if p.scale == "log" else p.lower for p in free])
        hi = np.array([np.log(p.upper) if p.scale == "log" else p.upper for p in free])
        return log, lo, hi

    def to_unit(self, values: np.ndarray) -> np.ndarray:
        """Full parameter values (..., P) -> free normalised coordinates (..., F) in [0, 1]."""
        values = np.asarray(values, dtype=np.float64)
        v = values[..., self.free_mask]
        log, lo, hi = self._lo_hi()
        v = np.where(log, np.log(np.maximum(v, 1e-300)), v)
        return (v - lo) / (hi - lo)

    def from_unit(self, unit: np.ndarray) -> np.ndarray:
        """Free normalised coordinates (..., F) -> full parameter values (..., P), clipped to bounds."""
        unit = np.clip(np.asarray(unit, dtype=np.float64), 0.0, 1.0)
        log, lo, hi = self._lo_hi()
        v = lo + unit * (hi - lo)
        v = np.where(log, np.exp(v), v)
        out = np.broadcast_to(self.measured, unit.shape[:-1] + (len(self.parameters),)).copy()
        out[..., self.free_mask] = v
        return out

    # --- prior ---------------------------------------------------------------
    @property
    def priors(self) -> list[Parameter]:
        """Free parameters that carry a prior (a frozen one does not move, so its prior is moot)."""
        return [p for p in self.free if p.prior is not None]

    def prior_residuals(self, values: np.ndarray) -> np.ndarray:
        """(..., n_prior) normalised deviations from the priors' centres; empty when none is set."""
        values = np.asarray(values, dtype=np.float64)
        cols = []
        for p in self.priors:
            v = values[..., self.index(p.name)]
            centre, scale = p.prior
            cols.append((np.log(np.maximum(v, 1e-300)) - np.log(centre) if p.scale == "log" else v - centre) / scale)
        return np.stack(cols, axis=-1) if cols else np.zeros(values.shape[:-1] + (0,))

    def prior_jacobian_unit(self, values: np.ndarray) -> np.ndarray:
        """(n_prior, F) d prior residual / d unit coordinate at one full parameter vector."""
        values = np.asarray(values, dtype=np.float64).reshape(-1)
        log, lo, hi = self._lo_hi()
        out = np.zeros((len(self.priors), len(self.free)))
        free = self.free_names
        for r, p in enumerate(self.priors):
            f = free.index(p.name)
            out[r, f] = (hi[f] - lo[f]) / p.prior[1]  # linear in unit coordinates on either scale
        return out

    def dvalue_dunit(self, values: np.ndarray) -> np.ndarray:
        """d(free value)/d(unit coordinate) at `values` (..., P) -> (..., F); for chain rules."""
        log, lo, hi = self._lo_hi()
        v = np.asarray(values, dtype=np.float64)[..., self.free_mask]
        return np.where(log, v * (hi - lo), (hi - lo))
