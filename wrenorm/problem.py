"""What a system supplies to the engine for one fit: parameters, conditions, and a batched observable.

A *condition* is one experiment (a command profile, a motor rate, a hand path). The engine fits on
`train` conditions and validates on `held_out` ones the search never sees.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .params import ParameterSpace


@dataclass
class Condition:
    name: str
    data: Any = None
    meta: dict = field(default_factory=dict)


class Problem(ABC):
    """A system at one resolution, to fit. Subclasses set the attributes in __init__ and implement
    `errors`, and `residuals` where the observable is a vector of signed differences.

    Attributes
    ----------
    task:        the system's registered name ("pd", "rope", "swimmer")
    space:       ParameterSpace (measured values are the search's starting point)
    train:       conditions the search fits
    held_out:    conditions kept back for validation
    tolerance:   the largest held-out error (same units as `errors`; the worst condition, not the mean) under
                 which the verdict is `absorbed`
    resolution:  what sets the coarse model's resolution, e.g. {"f_sim": 100.0}
    device:      Warp device string ("cpu" or "cuda:0")
    error_doc:   one sentence saying what `errors` measures (goes into result.json)
    least_squares: the search minimises the sum of squared residuals (and prior residuals) instead of the
                 mean error; set it where the residuals are the observable (a Gaussian likelihood)
    noise_normalised: the residuals are in units of their measurement noise, so the uncertainty takes the
                 noise as given (sigma = 1) rather than estimating it from the misfit
    """

    task: str
    space: ParameterSpace
    train: list[Condition]
    held_out: list[Condition]
    tolerance: float
    resolution: dict
    device: str = "cpu"
    error_doc: str = ""
    least_squares: bool = False
    noise_normalised: bool = False

    @abstractmethod
    def errors(self, values: np.ndarray, conditions: Sequence[Condition]) -> np.ndarray:
        """values (B, P) full parameter sets -> (B, C) non-negative errors, one per condition.

        One call simulates every candidate under every condition (batched). A candidate whose
        simulation blows up gets a non-finite error; it must never raise.
        """

    def residuals(self, values: np.ndarray, conditions: Sequence[Condition]) -> np.ndarray:
        """values (B, P) -> (B, R) signed residuals whose sum of squares the observable measures (NaN in a
        row whose candidate has no value there). Systems with a vector observable override this; it gives
        the Gauss-Newton uncertainty and least-squares searches."""
        raise NotImplementedError(f"task {self.task!r} exposes no residual vector")

    def residual_series(self, conditions: Sequence[Condition]) -> list[int] | None:
        """Lengths of the time-ordered series that `residuals` concatenates, in its order; None where its entries are
        separate measurements. Where given, the uncertainty allows for residuals correlated in time (coloured noise,
        a structured misfit), which the white-noise formula understates."""
        return None

    @property
    def has_residuals(self) -> bool:
        return type(self).residuals is not Problem.residuals

    def validation_errors(self, values: np.ndarray, conditions: Sequence[Condition]):
        """(B, C) held-out errors for the verdict, and per condition a dict of what else the validation should
        report (e.g. whether an event happened). Default: `errors`, nothing else. A system whose training
        error carries a penalty (a missing event) overrides this to score states, so that fitted and measured
        errors compare like with like; where the fitted values (the second of two candidates) show no event at all,
        its dict says `fitted_misses: True`, and the verdict counts that condition outside tolerance."""
        return self.errors(values, conditions), [{} for _ in conditions]

    def errors_and_grad(self, values: np.ndarray, conditions: Sequence[Condition]):
        """(B, C) errors and (B, C, P) d error / d value, for gradient searches.

        Systems with a differentiable kernel override this (Warp tape). The default says no.
        """
        raise NotImplementedError(f"task {self.task!r} has no differentiable error")

    @property
    def differentiable(self) -> bool:
        return type(self).errors_and_grad is not Problem.errors_and_grad

    def report(self, fitted: np.ndarray, measured: np.ndarray) -> dict:
        """Task-specific fields added to result.json (e.g. analytic predictions, speeds)."""
        return {}

    def fit_warnings(self, fitted: np.ndarray) -> list[str]:
        """What the fitted model fails to show on the training conditions that the loss alone does not say (e.g. a
        chain that never reaches the observed event on some of them): result.json's and a flow point's warnings."""
        return []

    def tolerance_for(self, condition: Condition) -> float:
        """The held-out error up to which `condition` counts as reproduced: `tolerance` for every condition unless a
        system's conditions differ in scale (a slow clip beside a fast one) and it tightens it per condition."""
        return float(self.tolerance)

    def data_flags(self, condition: Condition) -> list[str]:
        """What the system's checks doubt in this condition's data (said, not refused). A held-out condition so
        flagged is shown but does not decide the verdict; with every one flagged the fit stays unvalidated."""
        return []

    def charts(self, fitted: np.ndarray, measured: np.ndarray) -> list[str]:
        """SVG charts, one or more per condition: the reference against the model with measured and with fitted
        parameters (report.html shows them; viz/svg.py draws them)."""
        return []

    def record(self, recorder, fitted: np.ndarray, measured: np.ndarray) -> None:  # noqa: B027 (optional hook)
        """Log reference, measured-parameter and fitted-parameter behaviour to a viz.Recorder."""


def finite_or_inf(errors: np.ndarray) -> np.ndarray:
    """Blow-ups (NaN, Inf, negative garbage) cost the candidate, never the run."""
    errors = np.asarray(errors, dtype=np.float64)
    return np.where(np.isfinite(errors) & (errors >= 0), errors, np.inf)
