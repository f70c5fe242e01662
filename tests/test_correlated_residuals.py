"""Stds of a fit whose residuals are time series with correlated noise, against the spread of the fitted values over
many noise draws (Monte Carlo): the white-noise formula sigma^2 (J^T J)^-1 understates it by the square root of the
noise's correlation length; the Newey-West sandwich over each series does not, and stays at the white std on white
noise."""
import numpy as np
import pytest

from wrenorm.params import Parameter, ParameterSpace
from wrenorm.problem import Condition, Problem
from wrenorm.uncertainty import uncertainty

T = np.linspace(0.0, 4.0, 800)
X = np.stack([np.sin(1.3 * T), np.cos(0.7 * T), 0.3 * T], axis=1)  # the response to each parameter, per sample
TRUE = np.array([1.0, -0.5, 2.0])


def ar1(rng, n, rho):
    e = rng.standard_normal(n)
    out = np.empty(n)
    out[0] = e[0]
    for i in range(1, n):
        out[i] = rho * out[i - 1] + np.sqrt(1 - rho ** 2) * e[i]
    return out


class Regression(Problem):
    """Two logs of the same system, residuals X b - y per sample; `series` says they are time series."""

    task = "regression"
    least_squares = True

    def __init__(self, y: np.ndarray, series: bool = True, prior_scale=None, design: np.ndarray = X):
        self.y, self.series, self.X = y, series, design
        self.space = ParameterSpace([Parameter(n, 0.0, -10.0, 10.0, "linear",
                                               prior=(0.0, prior_scale) if prior_scale else None) for n in "abc"])
        self.train, self.held_out = [Condition("log1"), Condition("log2")], [Condition("log3")]
        self.tolerance, self.resolution = 1.0, {}

    def residuals(self, values, conditions):
        pred = np.atleast_2d(values) @ self.X.T
        return np.concatenate([pred - self.y[int(c.name[-1]) - 1][None] for c in conditions], axis=1)

    def errors(self, values, conditions):
        r = self.residuals(values, conditions)
        return np.sqrt(np.mean(r ** 2, axis=1, keepdims=True))

    def residual_series(self, conditions):
        return [len(T)] * len(conditions) if self.series else None


def fit_and_std(rho: float, draws: int, series: bool = True):
    fits, stds = [], []
    for k in range(draws):
        rng = np.random.default_rng(k)
        y = np.stack([X @ TRUE + 0.1 * ar1(rng, len(T), rho) for _ in range(3)])
        b = np.linalg.lstsq(np.concatenate([X, X]), np.concatenate(y[:2]), rcond=None)[0]
        unc = uncertainty(Regression(y, series), b, step=1e-4)
        fits.append(b)
        stds.append([unc["std"][n] for n in "abc"])
    return np.std(fits, axis=0, ddof=1), np.mean(stds, axis=0), unc


def test_stds_of_residuals_correlated_in_time_cover_the_spread_of_the_fits():
    spread, stated, unc = fit_and_std(0.95, 150)
    np.testing.assert_allclose(stated / spread, 1.0, atol=0.3)
    assert min(unc["correlated_residuals"]["widening"].values()) > 3 and "Newey-West" in unc["method"]
    # the white-noise formula (the residuals called separate measurements) understates it ~sqrt((1+rho)/(1-rho))
    _, white, unc_white = fit_and_std(0.95, 20, series=False)
    assert np.all(white / spread < 0.4) and "correlated_residuals" not in unc_white


def test_on_white_noise_the_stds_stay_the_white_formulas():
    spread, stated, unc = fit_and_std(0.0, 150)
    np.testing.assert_allclose(stated / spread, 1.0, atol=0.2)
    assert max(unc["correlated_residuals"]["widening"].values()) < 1.3


def test_a_prior_narrows_the_widened_data_std_as_the_closed_form_posterior_does():
    rng = np.random.default_rng(7)
    y = np.stack([X @ TRUE + 0.1 * ar1(rng, len(T), 0.95) for _ in range(3)])
    b = np.linalg.lstsq(np.concatenate([X, X]), np.concatenate(y[:2]), rcond=None)[0]
    data = uncertainty(Regression(y), b, step=1e-4)
    post = uncertainty(Regression(y, prior_scale=0.05), b, step=1e-4)
    # the data's widened covariance C and the prior's combine as independent Gaussians: (C^-1 + I / 0.05^2)^-1
    d = np.array([data["std"][n] for n in "abc"])
    C = np.outer(d, d) * np.array(data["correlation"]["matrix"])
    closed = np.sqrt(np.diag(np.linalg.inv(np.linalg.inv(C) + np.eye(3) / 0.05 ** 2)))
    np.testing.assert_allclose([post["std"][n] for n in "abc"], closed, rtol=1e-2)
    for n in "abc":
        assert post["data_only_std"][n] == pytest.approx(data["std"][n], rel=1e-6)


def test_a_pd_logs_stds_cover_the_spread_of_its_fits_under_noise_correlated_over_50_ms(tmp_path):
    """The joint's exact response with 2 mrad of AR(1) noise correlated over 50 ms at 1 kHz (rho 0.98 a sample), 24
    draws, `fit pd` each: the stated stds had been 0.31-0.45 of the fits' spread (white-noise formula); now 0.7-2x.
    The estimator was developed on the regression above, not on this log."""
    from wrenorm.fit import FitSettings, run_fit
    from wrenorm.tasks.pd.problem import Command, PDProblem, exact_reference, load_log

    cmd = Command("mix", "multisine", 0.5, 0.6, 1.7)
    t = np.arange(6001) / 1000.0
    q0 = exact_reference(cmd, 0.05, 20.0, 0.5, t)
    q_d, qd_d, _ = cmd(t)
    fits, stds, white = [], [], []
    for k in range(24):
        path = tmp_path / f"log{k}.csv"
        q = q0 + 2e-3 * ar1(np.random.default_rng(1000 + k), len(t), 0.98)
        np.savetxt(path, np.c_[t, q, q_d, qd_d], delimiter=",", header="time,q,q_d,qd_d", comments="")
        r = run_fit(PDProblem(100.0, log=load_log(path)), tmp_path / f"run{k}", FitSettings(method="least-squares"),
                    record=False, quiet=True)
        free = [n for n, v in r["parameters"].items() if not v["frozen"]]
        widening = r["uncertainty"]["correlated_residuals"]["widening"]
        fits.append([r["parameters"][n]["fitted"] for n in free])
        stds.append([r["parameters"][n]["std"] for n in free])
        white.append([r["parameters"][n]["std"] / widening[n] for n in free])
    spread = np.std(fits, axis=0, ddof=1)
    assert free == ["J", "K_D", "K_FF", "K_AFF"]
    assert np.all(np.mean(white, axis=0) / spread < 0.6)
    ratio = np.mean(stds, axis=0) / spread
    assert np.all((ratio > 0.7) & (ratio < 2.0)), ratio
    from wrenorm.viz.report import render

    assert "wider than the white-noise formula's by J " in render(r)


def test_a_direction_the_data_never_see_stays_undetermined_and_its_widening_is_a_number():
    import json

    blind = np.stack([X[:, 0], X[:, 1], 0.0 * X[:, 2]], axis=1)
    rng = np.random.default_rng(3)
    y = np.stack([blind @ TRUE + 0.1 * ar1(rng, len(T), 0.9) for _ in range(3)])
    unc = uncertainty(Regression(y, design=blind), np.array([1.0, -0.5, 0.0]), step=1e-4)
    assert np.isinf(unc["std"]["c"]) and np.isfinite(unc["std"]["a"]) and "c" in unc["undetermined"]
    assert unc["correlated_residuals"]["widening"]["c"] == 1.0 and unc["correlated_residuals"]["widening"]["a"] > 2
    json.loads(json.dumps(unc["correlated_residuals"], allow_nan=False))


def test_with_a_prior_a_combination_the_data_see_keeps_its_information():
    """p0 and p1 enter only as p0 + p1: the data see their sum, the prior the rest. The widened posterior had taken
    both as the prior's alone (1.0 instead of 0.707), on white noise (review of stop 57)."""
    both = np.stack([X[:, 0], X[:, 0], X[:, 1]], axis=1)
    rng = np.random.default_rng(0)
    y = np.stack([both @ np.array([0.5, 0.5, 1.0]) + 0.1 * rng.standard_normal(len(T)) for _ in range(3)])
    b = np.array([0.5, 0.5, 1.0])
    plain = uncertainty(Regression(y, series=False, prior_scale=1.0, design=both), b, step=1e-4)
    timed = uncertainty(Regression(y, prior_scale=1.0, design=both), b, step=1e-4)
    for n in "abc":
        assert timed["std"][n] == pytest.approx(plain["std"][n], rel=1e-3)
    assert plain["std"]["a"] == pytest.approx(np.sqrt(0.5), rel=1e-3)


class KnownNoise(Regression):
    """The same residuals divided by a stated noise of 0.05 while the draws carry 0.1: chi^2/dof about 4."""

    noise_normalised = True

    def residuals(self, values, conditions):
        return super().residuals(values, conditions) / 0.05


def test_a_known_noise_is_not_widened_twice_by_the_misfit():
    """The sandwich of raw residuals already holds the misfit's scale; the std inflated by the misfit multiplied it in
    again (2x the spread of the fits on white noise at chi^2/dof 4; review of stop 57)."""
    fits, inflated = [], []
    for k in range(60):
        rng = np.random.default_rng(100 + k)
        y = np.stack([X @ TRUE + 0.1 * rng.standard_normal(len(T)) for _ in range(3)])
        b = np.linalg.lstsq(np.concatenate([X, X]), np.concatenate(y[:2]), rcond=None)[0]
        unc = uncertainty(KnownNoise(y), b, step=1e-4)
        fits.append(b)
        inflated.append([unc["std_inflated_by_misfit"][n] for n in "abc"])
    assert unc["chi2_per_dof"] == pytest.approx(4.0, rel=0.15)
    np.testing.assert_allclose(np.mean(inflated, axis=0) / np.std(fits, axis=0, ddof=1), 1.0, atol=0.25)


def test_the_built_in_commands_exact_reference_keeps_the_white_formula():
    """No noise there: the misfit is the step's own deterministic effect, which the flow measures; widening it by its
    correlation had made `flow pd`'s stds 4-5x wider with its page still naming the white formula (review of stop
    57)."""
    from wrenorm.tasks.pd.problem import PDProblem

    p = PDProblem(100.0)
    unc = uncertainty(p, p.space.measured)
    assert p.residual_series(p.train) is None and "correlated_residuals" not in unc and unc["std"]


def test_a_perfect_fit_keeps_its_correlations_and_a_wrong_series_layout_is_an_error():
    y = np.stack([X @ TRUE] * 3)
    plain = uncertainty(KnownNoise(y, series=False), TRUE, step=1e-4)
    timed = uncertainty(KnownNoise(y), TRUE, step=1e-4)
    assert timed["correlation"] == plain["correlation"] and abs(plain["correlation"]["matrix"][0][1]) > 0.05
    assert "correlated_residuals" not in timed  # no residual left to estimate a correlation in time from

    class Miscounted(Regression):
        def residual_series(self, conditions):
            return [len(T)]

    with pytest.raises(ValueError, match="residual_series sums to 800 rows, its residuals have 1600"):
        uncertainty(Miscounted(y), TRUE, step=1e-4)
