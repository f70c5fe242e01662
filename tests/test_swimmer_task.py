"""Swimmer task: normalised feature residuals, MAP objective, reported stds, restarts, resolution-flow problems,
yaw estimator."""
import argparse

import numpy as np
import pytest

from wrenorm.errors import InputError
from wrenorm.tasks.swimmer import data as sd
from wrenorm.tasks.swimmer import problem as swimmer


@pytest.fixture(scope="module")
def rates():
    return sd.load_builtin()


def test_residuals_are_normalised_feature_differences_and_the_prior_joins_the_objective(rates):
    from wrenorm.search import objective

    prob = swimmer.SwimmerProblem(rates, [1.0, 1.75], dt=0.016, features="yaw", prior_scale=None)
    assert prob.least_squares and prob.noise_normalised
    vals = prob.space.from_unit(np.array([prob.space.to_unit(prob.space.measured), [0.3, 0.4, 0.5, 0.6, 0.7, 0.35]]))
    r = prob.residuals(vals, prob.train)
    assert prob.features == ("speed", "yaw_amp", "yaw_phase") and r.shape == (2, 6)
    sim = prob.simulate(vals, prob.train)
    for j, c in enumerate(prob.train):
        np.testing.assert_allclose(r[:, 3 * j], (sim["speed"][:, j] - c.meta["speed"]) / prob.sigma(c, "speed"))
        np.testing.assert_allclose(r[:, 3 * j + 1],
                                   (sim["yaw_amp"][:, j] - c.meta["features"]["yaw_amp"]) / prob.sigma(c, "yaw_amp"))
    # the headline error stays the speed error in m/s
    np.testing.assert_allclose(prob.errors(vals, prob.train),
                               np.abs(sim["speed"] - [c.meta["speed"] for c in prob.train]), atol=1e-9)
    # the engine's MAP objective: data residuals squared, plus the prior's (in e-folds of ln c / scale)
    np.testing.assert_allclose(objective(prob, vals), (r ** 2).sum(1), rtol=1e-9)
    priored = swimmer.SwimmerProblem(rates, [1.0, 1.75], dt=0.016, features="yaw", prior_scale=0.5)
    z = np.log(vals[:, :5] / np.array(list(swimmer.PUBLISHED.values()))) / 0.5
    np.testing.assert_allclose(objective(priored, vals), (r ** 2).sum(1) + (z ** 2).sum(1), rtol=1e-6)
    # a heavier speed weight scales the speed residuals only
    heavy = swimmer.SwimmerProblem(rates, [1.0, 1.75], dt=0.016, features="yaw", prior_scale=None, speed_weight=3.0)
    rh = heavy.residuals(vals, heavy.train)
    np.testing.assert_allclose(rh[:, [0, 3]], 3.0 * r[:, [0, 3]], rtol=1e-9)
    np.testing.assert_allclose(rh[:, [1, 2, 4, 5]], r[:, [1, 2, 4, 5]], rtol=1e-9)
    with pytest.raises(InputError, match="feature"):
        swimmer.parse_features("speed,crab")


def test_the_viscosity_is_a_sixth_parameter_fitted_without_prior_unless_frozen(rates):
    prob = swimmer.SwimmerProblem(rates, [1.0, 1.75], dt=0.016, features="speed")
    assert prob.space.names[-1] == "viscosity" and not prob.space["viscosity"].frozen
    assert prob.space["viscosity"].measured == swimmer.VISCOSITY and prob.space["viscosity"].prior is None
    assert [p.prior for p in prob.space.priors] == [(v, 0.5) for v in swimmer.PUBLISHED.values()]
    five = swimmer.SwimmerProblem(rates, [1.0, 1.75], dt=0.016, features="speed", free_viscosity=False)
    assert five.space.free_names == list(swimmer.PUBLISHED)
    v = np.tile(prob.space.measured, (2, 1))
    v[1, 5] = 0.05
    sp = prob.speeds(v, prob.train)
    # a drag linear in the speed slows the slow rate more than the fast one: the stride grows with the rate
    assert np.all(sp[1] < sp[0])
    assert sp[1, 0] / sp[0, 0] < sp[1, 1] / sp[0, 1]


def test_uncertainty_reports_posterior_and_data_only_std_and_who_holds_each_coefficient(rates):
    from wrenorm.uncertainty import uncertainty

    prob = swimmer.SwimmerProblem(rates, [1.0, 1.75], dt=0.016, features="yaw", prior_scale=1.0)
    unc = uncertainty(prob, prob.space.measured)
    names = set(prob.space.free_names)
    assert set(unc["std"]) == names == set(unc["data_only_std"])
    # the prior can only add information: posterior std <= data-only std, never wider than the prior itself
    five = set(swimmer.PUBLISHED)
    for n in names:
        assert unc["std"][n] <= unc["data_only_std"][n] * (1 + 1e-9)
    for n in five:
        assert unc["std"][n] <= 1.0 * prob.space[n].measured * (1 + 1e-6)
    # Magnus lift acts on the plates' tiny volumes: the data cannot hold it, the prior does; at the water's
    # viscosity the linear drag is invisible (no prior holds it either: undetermined there)
    assert "magnus_lift" in unc["held_by_prior"] and "magnus_lift" not in unc["determined_by_data"]
    assert set(unc["determined_by_data"]) | set(unc["held_by_prior"]) == five
    assert "viscosity" in unc["undetermined"]
    assert unc["chi2_per_dof"] > 0 and set(unc["std_inflated_by_misfit"]) == names


def test_restarts_report_the_spread_of_held_out_predictions(rates):
    from wrenorm.restarts import identifiability_restarts

    prob = swimmer.SwimmerProblem(rates, [1.0, 1.75], dt=0.016, features="yaw", prior_scale=1.0)
    rs = identifiability_restarts(prob, prob.space.measured, seeds=[101, 102], popsize=8, generations=4,
                                  method="cmaes+least-squares")
    assert rs["search"] == "cmaes+least-squares" and len(rs["optima"]) == 2
    assert set(rs["held_out_spread"]) == {"f0.50", "f1.25", "f2.25"}
    held = np.array([list(o["held_out_errors"].values()) for o in rs["optima"]])
    assert np.all(np.isfinite(held)) and rs["held_out_mean_error_spread_all"] >= 0


def test_flow_problems_sorted_time_steps_and_bad_input(rates):
    args = argparse.Namespace(resolutions=[0.008, 0.002], data=None, train="1.00,1.75", virtual_mass=False,
                              gait="chain", features="speed", prior_scale=0.0, integrator="ros2", command="flow")
    probs = swimmer.flow_problems(args, "cpu")
    assert [p.dt for p in probs] == [0.002, 0.008]
    assert all(p.resolution["dt"] == p.dt for p in probs)
    assert probs[0].features == ("speed",) and not probs[0].space.priors
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


def test_known_truth_features_and_determined_coefficients_recovered(rates):
    """A simulated fish stands in for the real one: its speed, yaw and 2f surge at the training rates become the
    'real' features; the least-squares search from the published coefficients (no prior) reproduces them, and
    recovers the coefficients the data determine (blunt drag, Kutta lift, the viscosity) where Gauss-Newton says
    they are determined."""
    from wrenorm.least_squares import levenberg_marquardt
    from wrenorm.uncertainty import uncertainty

    prob = swimmer.SwimmerProblem(rates, [1.0, 1.75], dt=0.016, prior_scale=None)
    hidden = np.array([0.3, 0.5, 2.0, 1.3, 0.25, 0.05])
    sim = prob.simulate(hidden[None], prob.train)
    for j, c in enumerate(prob.train):
        c.meta["features"] = dict(c.meta["features"], **{f: float(sim[f][0, j]) for f in prob.features})
    start = prob.space.measured.copy()
    start[5] = 0.02
    res, r, _ = levenberg_marquardt(prob, start, iterations=40, quiet=True)
    assert res.best_loss < 1e-2 * float(np.sum(prob.residuals(start[None], prob.train) ** 2))
    assert np.abs(r).max() < 0.5  # every feature within half its noise
    unc = uncertainty(prob, res.best_values)
    assert {"blunt_drag", "kutta_lift"} <= set(unc["determined_by_data"])
    for n in unc["determined_by_data"]:
        i = prob.space.index(n)
        assert abs(np.log(res.best_values[i] / hidden[i])) < 3 * unc["std"][n] / res.best_values[i] + 0.02, n


def test_a_slow_clip_is_judged_by_its_own_speed_and_clips_the_checks_doubt_do_not_decide(rates):
    """The held-out tolerance was 0.02 m/s for every clip, so a slow clip (0.022 m/s) could miss by 45 % and count as
    reproduced; it is now a quarter of the clip's speed where that is less. Clips read at the wrong frame rate are
    flagged by the tail-beat check, and with every held-out clip flagged the verdict is withheld."""
    from wrenorm.fit import _validation

    prob = swimmer.SwimmerProblem(rates, [1.0, 1.75], dt=0.016)
    by_label = {c.meta["label"]: c for c in prob.held_out}
    slow, fast = by_label[0.5], by_label[2.25]
    assert prob.tolerance_for(slow) == pytest.approx(0.25 * slow.meta["speed"]) and prob.tolerance_for(slow) < 0.006
    assert prob.tolerance_for(fast) == swimmer.TOLERANCE
    measured = prob.space.measured
    v = _validation(prob, measured, measured)
    assert v["conditions"]["f0.50"]["tolerance"] == pytest.approx(prob.tolerance_for(slow))
    assert "flagged_conditions" not in v and v["verdict"] in ("absorbed", "expand")
    # the measured coefficients miss the slow clip by about 0.016 m/s, 73 % of its speed: within the flat 0.02 m/s,
    # outside its own tolerance
    slow_error = v["conditions"]["f0.50"]["fitted_error"]
    assert prob.tolerance_for(slow) < slow_error < swimmer.TOLERANCE
    assert v["conditions"]["f0.50"]["within_tolerance"] is False

    doubled = [sd.analyse(sd.Rate(label=r.label, markers=r.markers, source=r.name, fps=2 * r.fps)) for r in rates]
    wrong = swimmer.SwimmerProblem(doubled, [1.0, 1.75], dt=0.016)
    assert all(wrong.data_flags(c) for c in wrong.held_out)
    v = _validation(wrong, measured, measured)
    assert v["verdict"] == "unvalidated" and "flag every held-out condition" in v["note"]
    assert "worst_fitted_error" not in v and all(c["data_flags"] for c in v["conditions"].values())


def test_a_fitted_model_that_misses_its_training_speed_or_swims_tail_first_is_said(rates):
    """Clips of another swimming model had been fitted with the training 1.00 Hz speed -51 % and held-out rates swum
    backward, nothing said (review of stop 55). The README's fitted coefficients (seed 0) swim every training rate
    within 2 %: nothing said; with half their Kutta lift the model swims the 1.00 Hz beat tail first and the 1.75 Hz
    one 61 % slow, both said."""
    prob = swimmer.SwimmerProblem(rates, [1.0, 1.75], dt=0.016)
    names = [p.name for p in prob.space.parameters]
    fitted = dict(blunt_drag=0.269, slender_drag=0.33, angular_drag=1.91, kutta_lift=1.22, magnus_lift=0.239,
                  viscosity=0.0642)
    vector = np.array([fitted[n] for n in names])
    assert prob.fit_warnings(vector) == []
    weak = vector.copy()
    weak[names.index("kutta_lift")] *= 0.5
    said = prob.fit_warnings(weak)
    assert any("swims tail first or stands at 1.00 Hz" in w for w in said), said
    assert any("misses the training speed at 1.75 Hz by -61 %" in w for w in said), said
