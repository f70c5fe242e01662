"""Swimmer task: residuals, identifiability report, resolution-flow problems, yaw estimator."""
import argparse

import numpy as np
import pytest

from wrenorm.errors import InputError
from wrenorm.tasks.swimmer import data as sd
from wrenorm.tasks.swimmer import problem as swimmer


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
    from wrenorm.restarts import identifiability_restarts

    prob = swimmer.SwimmerProblem(rates, [1.0, 1.75], dt=0.016)
    rs = identifiability_restarts(prob, prob.space.measured, seeds=[101, 102, 103], popsize=16, generations=25)
    assert rs["unconstrained_directions_at_least"] == 3
    assert len(rs["optima"]) == 3
    assert all(np.isfinite(o["train_loss"]) and o["train_loss"] < 0.0095 for o in rs["optima"])
    assert set(rs["pinned"]) | set(rs["not_pinned"]) == set(prob.space.names)
    assert rs["not_pinned"], "five coefficients pinned by two speeds would be a bug"


def test_flow_problems_sorted_time_steps_and_bad_input(rates):
    args = argparse.Namespace(resolutions=[0.008, 0.002], data=None, train="1.00,1.75", virtual_mass=False,
                              gait="chain", yaw_weight=0.0, integrator="ros2", command="flow")
    probs = swimmer.flow_problems(args, "cpu")
    assert [p.dt for p in probs] == [0.002, 0.008]
    assert all(p.resolution["dt"] == p.dt for p in probs)
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


def test_real_heading_on_a_synthetic_crabbing_turning_fish():
    """A head that travels along +x while its marker axis points 20 deg off the tailward direction and
    turns by 10 deg over the clip: path direction 0, crab ~ -(20 + 5), turn 10."""
    fps, secs, freq = 50.0, 4.0, 1.0
    t = np.arange(int(fps * secs)) / fps
    yaw = np.radians(180.0 + 20.0 + 10.0 * t / secs) + 0.1 * np.sin(2 * np.pi * freq * t)
    head = np.stack([0.05 * t, np.zeros_like(t)], 1)
    axis = 0.04 * np.stack([np.cos(yaw), np.sin(yaw)], 1)
    markers = np.zeros((len(t), 9, 2))
    markers[:, 0], markers[:, 1] = head - axis / 2, head + axis / 2
    h = swimmer.real_heading(sd.Rate(label=1.0, markers=markers, fps=fps, tail_freq=freq))
    assert abs(h["path_direction_deg"]) < 1e-9
    assert h["turn_deg"] == pytest.approx(10.0 * (secs - 1.0) / secs, abs=0.2)
    assert h["crab_deg"] == pytest.approx(-25.0, abs=0.3)


def test_simulated_fish_in_the_view_start_at_the_real_head_and_follow_the_real_path(rates):
    prob = swimmer.SwimmerProblem(rates, [1.0, 1.75], dt=0.016)
    cond = prob.train[0]
    rate = prob.rates[cond.name]
    real_dir = swimmer.real_heading(rate)["path_direction_deg"]
    for align in (True, False):
        bodies = prob.simulated_bodies(cond, prob.space.measured, duration=3.0, every=0.1, align_path=align)
        head = np.array([0.5 * (p[0] + p[1]) for _, p in bodies])
        assert np.linalg.norm(head[0] - 0.5 * (rate.markers[0, 0] + rate.markers[0, 1])) < 0.01
        d = head[-1] - head[0]
        off = (np.degrees(np.arctan2(d[1], d[0])) - real_dir + 180.0) % 360.0 - 180.0
        if align:
            assert abs(off) < 1e-6
        else:
            assert abs(off) > 5.0  # started at the real head pose, the straight-swimming model drifts off
