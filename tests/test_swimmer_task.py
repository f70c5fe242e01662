"""Swimmer task: residuals, identifiability report, resolution-flow problems, yaw estimator."""
import argparse

import numpy as np
import pytest

from wrenorm.errors import InputError
from wrenorm.tasks import swimmer, swimmer_data as sd


@pytest.fixture(scope="module")
def rates():
    return sd.load_builtin()


def test_residuals_are_signed_errors(rates):
    prob = swimmer.SwimmerProblem(rates, [1.0, 1.75], dt=0.016)
    vals = np.array([swimmer.parameter_space().measured, [0.01, 0.3, 0.05, 0.3, 0.01]])
    r = prob.residuals(vals, prob.train)
    assert r.shape == (2, 2)
    np.testing.assert_allclose(np.abs(r), prob.errors(vals, prob.train))
    assert np.sign(r[0]).tolist() != np.sign(r[1]).tolist() or np.abs(r[0] - r[1]).max() > 5e-3
    yawed = swimmer.SwimmerProblem(rates, [1.0, 1.75], dt=0.016, yaw_weight=0.1)
    ry = yawed.residuals(vals, yawed.train)
    assert ry.shape == (2, 4)
    np.testing.assert_allclose(ry[:, :2], r, atol=1e-7)
    np.testing.assert_allclose(yawed.errors(vals, yawed.train), np.hypot(ry[:, :2], ry[:, 2:]), rtol=1e-6)


def test_identifiability_says_two_speeds_do_not_pin_five_coefficients(rates):
    prob = swimmer.SwimmerProblem(rates, [1.0, 1.75], dt=0.016, restarts=3)
    prob.restart_generations = 25
    ident = prob.identifiability(prob.space.measured)
    assert ident["unconstrained_directions_at_least"] == 3
    rs = ident["restarts"]
    assert len(rs["optima"]) == 3
    assert all(np.isfinite(o["train_loss"]) and o["train_loss"] < 0.0095 for o in rs["optima"])
    assert set(rs["pinned"]) | set(rs["not_pinned"]) == set(prob.space.names)
    assert rs["not_pinned"], "five coefficients pinned by two speeds would be a bug"


def test_flow_problems_sorted_time_steps_and_bad_input(rates):
    args = argparse.Namespace(resolutions=[0.008, 0.002], data=None, train="1.00,1.75", virtual_mass=False,
                              gait="chain", yaw_weight=0.0, integrator="ros2", command="flow")
    probs = swimmer.flow_problems(args, "cpu")
    assert [p.dt for p in probs] == [0.002, 0.008]
    assert all(p.resolution["dt"] == p.dt and p.restarts == 0 for p in probs)
    args.resolutions = [0.5]
    with pytest.raises(InputError, match="dt"):
        swimmer.flow_problems(args, "cpu")
    args.resolutions = [0.004, 0.004]
    with pytest.raises(InputError, match="repeated"):
        swimmer.flow_problems(args, "cpu")


def test_yaw_estimator_recovers_known_amplitude():
    fps, f, amp = 60.0, 0.9, np.radians(6.0)
    t = np.arange(600) / fps
    heading = 0.3 + 0.05 * t + amp * np.sin(2 * np.pi * f * t + 0.4)   # slow turn plus oscillation
    front = np.stack([np.cos(heading), np.sin(heading)], 1) * 0.142 + np.array([[2.0, 1.0]])
    markers = np.zeros((len(t), 9, 2))
    markers[:, 0] = front
    markers[:, 1] = [2.0, 1.0]
    np.testing.assert_allclose(sd.yaw_amplitude(markers, f, fps), amp, rtol=1e-6)
