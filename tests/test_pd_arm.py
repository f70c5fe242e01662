"""Two-link arm: the appendix's joint-space corrections come out of the fit."""
import numpy as np
import pytest

from wrenorm import search
from wrenorm.kernels import arm
from wrenorm.tasks.pd.arm import K_D, ArmProblem


def test_mass_matrix_is_symmetric_positive_and_matches_energy():
    g = arm.geometry()
    q2 = np.linspace(-3, 3, 7)
    M = arm.mass_matrix(g, q2)
    assert np.allclose(M, np.swapaxes(M, -1, -2))
    assert np.all(np.linalg.eigvalsh(M) > 0)
    # kinetic energy from link velocities equals 0.5 v^T M v (independent derivation)
    m1, m2, l1, lc1, lc2, i1, i2 = (float(x) for x in (g.m1, g.m2, g.l1, g.lc1, g.lc2, g.i1, g.i2))
    q1, qq2, v1, v2 = 0.4, 1.1, 0.7, -1.3
    p1 = np.array([-np.sin(q1), np.cos(q1)]) * lc1 * v1
    p2 = (np.array([-np.sin(q1), np.cos(q1)]) * l1 * v1
          + np.array([-np.sin(q1 + qq2), np.cos(q1 + qq2)]) * lc2 * (v1 + v2))
    T = 0.5 * m1 * p1 @ p1 + 0.5 * m2 * p2 @ p2 + 0.5 * i1 * v1**2 + 0.5 * i2 * (v1 + v2) ** 2
    v = np.array([v1, v2])
    assert 0.5 * v @ arm.mass_matrix(g, np.array([qq2]))[0] @ v == pytest.approx(T, rel=1e-12)


def test_fit_recovers_armature_and_kd_matrix():
    p = ArmProblem(200.0)
    r = search.cmaes(p, seed=2, popsize=24, generations=150, sigma0=0.15, quiet=True)
    fit = p.space.as_dict(r.best_values)
    a = p.analytic(fit)
    assert a["A_relative_error_second_order"] < 0.1
    assert np.allclose(a["K_D_sim_fitted"], K_D, rtol=0.03, atol=0.003)  # semi-implicit: K_D unchanged
    errs = p.errors(np.stack([p.space.measured, r.best_values]), p.held_out)
    assert np.all(errs[1] < 0.3 * errs[0])
