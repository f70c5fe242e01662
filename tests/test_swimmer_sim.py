"""Swimmer simulation: conservation checks, step-size convergence and a known-truth fit."""

import cma
import numpy as np
import pytest
from swimmer_checks import PUBLISHED, com_drift

from wrenorm.tasks.swimmer import body as sb
from wrenorm.tasks.swimmer import data as sd
from wrenorm.tasks.swimmer import problem as swimmer


@pytest.fixture(scope="module")
def rates():
    return sd.load_builtin()


def test_no_fluid_no_gait_no_motion(rates):
    g = sb.gait(rates[1])
    g["a"] = np.zeros_like(g["a"])
    g["b"] = np.zeros_like(g["b"])
    sim = sb.build_batch([rates[1]], rho=0.0, mu=0.0, gaits=[g], warm_seconds=1.0, meas_seconds=2.0,
                         max_warm_seconds=None)
    speed = sim.run(PUBLISHED[None])
    assert abs(speed[0, 0]) < 1e-12
    assert np.all(sim.last_state[0, 0, :6] == 0.0)


def test_no_fluid_centre_of_mass_stays_put(rates):
    """Without water the tail only shakes the head: momentum stays zero, the centre of mass fixed
    (to the integrator's first order)."""
    coarse, excursion = com_drift(rates[1], 0.004)
    fine, _ = com_drift(rates[1], 0.001)
    assert excursion > 0.003          # the head does move
    assert coarse < 1e-3 and fine < 0.4 * coarse


def test_symmetric_gait_swims_straight(rates):
    """Odd harmonics only (psi(t + T/2) = -psi(t)): no net turning once cruising."""
    gaits = []
    for r in rates[1:4]:
        g = sb.gait(r)
        g["a"][:, 1::2] = 0.0
        g["b"][:, 1::2] = 0.0
        gaits.append(g)
    sim = sb.build_batch(rates[1:4], gaits=gaits, warm_seconds=2.0, meas_seconds=6.0, max_warm_seconds=None)
    _, traj, _ = sim.run(PUBLISHED[None], rec_stride=1, rec_frames=int(sim.steps.max()))
    for j, g in enumerate(gaits):
        per = int(np.ceil(1.0 / g["freq"] / sb.DEFAULT_DT))
        th = traj[0, j, :sim.steps[j], 2]
        beats = np.array([th[i * per:(i + 1) * per].mean() for i in range(len(th) // per)])
        drift = np.diff(beats)[len(beats) // 2:]
        assert np.abs(drift).max() < 5e-4, drift
    # the measured gait's even harmonic does turn the fish: the check above is not vacuous
    g = sb.gait(rates[1])
    sim = sb.build_batch([rates[1]], gaits=[g], warm_seconds=2.0, meas_seconds=6.0, max_warm_seconds=None)
    _, traj, _ = sim.run(PUBLISHED[None], rec_stride=1, rec_frames=int(sim.steps.max()))
    per = int(np.ceil(1.0 / g["freq"] / sb.DEFAULT_DT))
    th = traj[0, 0, :sim.steps[0], 2]
    beats = np.array([th[i * per:(i + 1) * per].mean() for i in range(len(th) // per)])
    assert np.abs(np.diff(beats)[len(beats) // 2:]).mean() > 2e-3


def test_speed_converges_in_dt(rates):
    coef = np.array([PUBLISHED, [0.5, 0.25, 1.5, 1.0, 1.0]])
    fine = sb.build_batch(rates, dt=0.001).run(coef)
    default = sb.build_batch(rates).run(coef)
    assert np.all(fine[0] > 0)
    # within 2 mm/s (a tenth of the task tolerance) also for the low-drag MuJoCo defaults
    np.testing.assert_allclose(default, fine, atol=2e-3)


def test_integrators_converge_at_their_order(rates):
    """Against 0.5 ms steps: implicit Euler's speed error halves with the step (first order); the
    ROS2 error at 4 ms is several times smaller than Euler's at the same step."""
    coef = np.array([PUBLISHED, [0.0136, 5.73, 0.054, 1.52, 4.44]])
    sel = rates[1:4]
    ref = sb.build_batch(sel, dt=0.0005, scheme=2).run(coef)
    e_euler = [np.abs(sb.build_batch(sel, dt=h, scheme=1).run(coef) - ref).max() for h in (0.004, 0.008)]
    e_ros2 = np.abs(sb.build_batch(sel, dt=0.004, scheme=2).run(coef) - ref).max()
    assert 1.5 < e_euler[1] / e_euler[0] < 2.6, e_euler
    assert e_ros2 < 0.4 * e_euler[0], (e_ros2, e_euler)


def test_restructured_kernel_equals_part_by_part_kernel(rates):
    """Inertial sums precomputed per sample (reduce_table) give what assembling every part's mass
    matrix and inertial force each step gives (the first derivation, kernels/swimmer_direct.py)."""
    import swimmer_direct

    coef = np.array([PUBLISHED, [0.5, 0.25, 1.5, 1.0, 1.0], [5.0, 50.0, 20.0, 0.3, 0.02]])
    # a sixth column is a per-candidate viscosity, in both kernels alike: the water's gives the same bits
    with_mu = np.concatenate([coef, [[0.0013], [0.0013], [0.0013]]], 1)
    thick = with_mu.copy()
    thick[:, 5] = [0.05, 0.2, 1.0]
    for vm in (False, True):
        b = sb.build_batch(rates[:2], dt=0.004, scheme=1, virtual_mass=vm, warm_seconds=1.0, meas_seconds=2.0,
                           max_warm_seconds=None)
        new, old = b.run(coef), swimmer_direct.run_direct(b, coef)
        assert np.abs(new).max() > 0.01
        np.testing.assert_allclose(new, old, atol=2e-6)
        np.testing.assert_array_equal(b.run(with_mu), new)
        slow, slow_old = b.run(thick), swimmer_direct.run_direct(b, thick)
        # the published fish slows down; a draggy one can gain (its tail's resistive thrust grows as well)
        assert np.all(slow[:2] < new[:2]) and np.abs(slow - new).max() > 1e-3
        np.testing.assert_allclose(slow, slow_old, atol=2e-6)


def test_yaw_amplitude_matches_recorded_heading(rates):
    """The kernel's on-the-fly yaw amplitude equals a least-squares sinusoid through the recorded
    heading over the measurement window."""
    sim = sb.build_batch(rates[1:3], warm_seconds=2.0, meas_seconds=4.0, max_warm_seconds=None)
    _, traj, _ = sim.run(PUBLISHED[None], rec_stride=1, rec_frames=int(sim.steps.max()))
    dt = sim.sim_seconds / sim.steps
    for j in range(2):
        nw = int(round(sim.last_state[0, j, 6] / dt[j]))
        th = traj[0, j, nw:sim.steps[j], 2]
        t = np.arange(len(th)) * dt[j]
        w = 2 * np.pi * sim_freq(rates[1 + j])
        basis = np.stack([np.ones_like(t), t, np.cos(w * t), np.sin(w * t)], 1)
        c = np.linalg.lstsq(basis, th, rcond=None)[0]
        assert np.hypot(c[2], c[3]) > np.radians(2.0)
        np.testing.assert_allclose(sim.last_yaw[0, j], np.hypot(c[2], c[3]), rtol=0.03)


def sim_freq(rate):
    return sb.gait(rate)["freq"]


def test_warm_up_reaches_cruising_speed(rates):
    """The settled warm-up gives the speed a much longer fixed warm-up gives, also for a low-drag
    candidate that creeps up to speed for many beats, and for one whose slow start-up has a turning point: at
    1.00 Hz its beat-averaged surge changes by less than the tolerance once on the way up (a warm-up ended by
    one calm beat measured 0.007 m/s there instead of 0.079; the warm-up now needs two in a row). Left: in a
    scan of 3200 random coefficient sets around the fit, 5 nearly-stalled bistable ones (tail first or
    forward) still differ from a 30 s warm-up (18 with one calm beat)."""
    coef = np.array([PUBLISHED, [0.01, 1.6, 0.4, 0.5, 9.0], [0.26, 0.54, 3.09, 1.0408, 0.22]])
    adaptive = sb.build_batch(rates[:3]).run(coef)
    long = sb.build_batch(rates[:3], warm_seconds=30.0, max_warm_seconds=None).run(coef)
    short = sb.build_batch(rates[:3], warm_seconds=2.0, max_warm_seconds=None).run(coef)
    np.testing.assert_allclose(adaptive, long, atol=1e-3)
    assert np.abs(short - long).max() > 5e-3


def test_errors_are_inf_for_broken_candidates(rates):
    prob = swimmer.SwimmerProblem(rates, [1.0, 1.75])
    vals = np.array([PUBLISHED, [np.nan, 1, 1, 1, 1]])
    err = prob.errors(vals, prob.train)
    assert err.shape == (2, 2) and np.all(np.isfinite(err[0])) and np.all(np.isinf(err[1]))


def test_known_truth_speeds_recovered_by_cma(rates):
    """Speeds simulated with hidden coefficients are matched by a short CMA-ES from the published ones."""
    hidden = np.array([0.8, 3.0, 1.2, 1.5, 0.6])
    prob = swimmer.SwimmerProblem(rates, [0.5, 1.0, 1.75, 2.25], dt=0.008, free_viscosity=False)
    truth = prob.speeds(hidden[None], prob.train + prob.held_out)[0]
    for c, v in zip(prob.train + prob.held_out, truth):
        c.meta["speed"] = float(v)
    sp = prob.space
    start = prob.errors(sp.measured[None], prob.train).mean()
    # the speed landscape has a second basin against the slender-drag and Magnus upper bounds;
    # two short seeded runs, best kept, is the restart strategy a real fit would use as well
    best, best_loss = None, np.inf
    for seed in (4, 5):
        es = cma.CMAEvolutionStrategy(sp.to_unit(sp.measured), 0.25,
                                      {"seed": seed, "popsize": 32, "bounds": [0, 1], "verbose": -9})
        for _ in range(60):
            x = np.array(es.ask())
            es.tell(list(x), list(prob.errors(sp.from_unit(x), prob.train).mean(1)))
        if es.result.fbest < best_loss:
            best, best_loss = sp.from_unit(es.result.xbest), es.result.fbest
    assert start > 5e-3
    # four speeds do not pin five coefficients (the fit lands elsewhere on the set of exact fits),
    # so the test asks for the speeds, trained and held out, not the coefficients
    assert prob.errors(best[None], prob.train).max() < 2e-3
    assert prob.errors(best[None], prob.held_out).max() < 4e-3
