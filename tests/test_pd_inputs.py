"""PD log CSVs as spreadsheets and loggers leave them: a byte-order mark is read past; a column named twice and a
hole in the sample times are refused in one line naming the file, the column and the problem."""
import json

import numpy as np
import pytest

from wrenorm.cli import main
from wrenorm.errors import InputError
from wrenorm.tasks.pd.problem import MAX_GAP_STEPS, load_log

JOINT = ["--J", "0.05", "--K-P", "20", "--K-D", "0.5"]  # the built-in joint that made the logs

T = np.arange(0, 4.0, 0.001)


def _write(path, t=T, header="time,q,q_d,qd_d", extra=None, prefix=b""):
    cols = [t, 0.3 * np.sin(2 * t), 0.3 * np.sin(2 * t + 0.1), 0.6 * np.cos(2 * t + 0.1)]
    if extra is not None:
        cols.append(extra(t))
    body = "\n".join([header] + [",".join(f"{x:.9g}" for x in row) for row in np.stack(cols, 1)]) + "\n"
    path.write_bytes(prefix + body.encode())
    return path


def test_a_byte_order_mark_is_read_past(tmp_path):
    plain = load_log(_write(tmp_path / "plain.csv"))
    bom = load_log(_write(tmp_path / "bom.csv", prefix=b"\xef\xbb\xbf"))
    for a, b in ((plain.time, bom.time), (plain.q, bom.q), (plain.q_d, bom.q_d), (plain.qd_d, bom.qd_d)):
        assert np.array_equal(a, b)


def test_a_column_named_twice_is_refused(tmp_path):
    f = _write(tmp_path / "dup.csv", header="time,q,q_d,qd_d,q", extra=lambda t: 0 * t)
    with pytest.raises(InputError) as e:
        load_log(f)
    assert e.value.source == str(f) and e.value.field == "q" and "2 times" in e.value.problem


def test_an_unused_extra_column_is_still_fine(tmp_path):
    assert len(load_log(_write(tmp_path / "extra.csv", header="time,q,q_d,qd_d,torque", extra=np.cos)).time) == len(T)


def test_a_hole_in_the_sample_times_is_refused_with_where_and_how_long(tmp_path):
    keep = np.r_[0:2000, 3500:len(T)]  # 1.5 s of rows cut out after t = 1.999 s
    f = _write(tmp_path / "gap.csv", t=T[keep])
    with pytest.raises(InputError) as e:
        load_log(f)
    assert e.value.source == str(f) and e.value.field == "time"
    assert "1.999" in e.value.problem and "1.501 s" in e.value.problem, e.value.problem


@pytest.mark.parametrize("dropped", [1, 3])
def test_a_few_dropped_samples_and_jitter_still_load(tmp_path, dropped):
    rng = np.random.default_rng(0)
    t = T + rng.uniform(-2e-4, 2e-4, len(T))  # jitter of a fifth of a step
    keep = np.r_[0:1000, 1000 + dropped:len(T)]
    assert np.max(np.diff(t[keep])) < MAX_GAP_STEPS * 0.001
    log = load_log(_write(tmp_path / "jitter.csv", t=t[keep]))
    assert len(log.time) == len(keep)


def test_the_fit_refuses_a_log_with_a_hole_in_one_line(tmp_path, capsys):
    f = _write(tmp_path / "gap.csv", t=np.r_[T[:2000], T[3500:]])
    assert main(["fit", "pd", "--quiet", "--no-record", "--reference", str(f), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(f) in err[0] and "time" in err[0] and "Traceback" not in err[0]
    assert not (tmp_path / "r" / "result.json").exists()


def test_arrival_time_stamps_that_bunch_up_are_refused(tmp_path):
    """A logger that stamps samples as they arrive writes a burst after a stall: samples 1 us apart where the median
    step is 1 ms. Read as measurement times they fitted J 14 % high and K_FF -0.36 without a word."""
    t = T.copy()
    t[2001:2006] = t[2000] + 1e-6 * np.arange(1, 6)  # five samples read out at once
    f = _write(tmp_path / "burst.csv", t=t)
    with pytest.raises(InputError) as e:
        load_log(f)
    assert e.value.field == "time" and "arrival" in e.value.problem and "1e-06" in e.value.problem


def test_milliseconds_on_a_fast_log_are_told_by_the_command_velocity(tmp_path):
    """10 kHz for 3 s written in ms: step 0.1 and span 3000 fit a joint log in seconds too, but qd_d is 1000 x the
    rate of change of q_d on that clock. It went on to a 298 GiB allocation."""
    t = np.arange(0, 3.0, 1e-4)
    f = tmp_path / "ms.csv"
    cols = np.stack([t * 1e3, 0.3 * np.sin(2 * t), 0.3 * np.sin(2 * t + 0.1), 0.6 * np.cos(2 * t + 0.1)], 1)
    np.savetxt(f, cols, delimiter=",", header="time,q,q_d,qd_d", comments="")
    with pytest.raises(InputError) as e:
        load_log(f)
    assert e.value.field == "time" and "milliseconds" in e.value.problem
    cols[:, 0] = t
    np.savetxt(f, cols, delimiter=",", header="time,q,q_d,qd_d", comments="")
    assert len(load_log(f).time) == len(t)  # the same log in seconds loads
    cols[:, 3] *= -1  # the command velocity with the wrong sign
    np.savetxt(f, cols, delimiter=",", header="time,q,q_d,qd_d", comments="")
    with pytest.raises(InputError) as e:
        load_log(f)
    assert e.value.field == "qd_d" and "wrong sign" in e.value.problem


def test_a_coarse_log_is_warned_and_a_still_held_out_part_gives_no_verdict(tmp_path, capsys):
    from wrenorm.tasks.pd.problem import Command, PDProblem, continuous_reference

    cmd = Command("mix", "multisine", 0.5, 0.6, 1.7)
    t = np.arange(0, 4.0, 0.05)  # 20 Hz, fitted at 100 Hz
    q_d, qd_d, _ = cmd(t)
    f = tmp_path / "coarse.csv"
    np.savetxt(f, np.c_[t, continuous_reference(cmd, 0.05, 20.0, 0.5, t), q_d, qd_d], delimiter=",",
               header="time,q,q_d,qd_d", comments="")
    problem = PDProblem(100.0, log=load_log(f))
    assert any("coarser than the simulation's step" in w for w in problem.warnings) and problem.held_out
    # a step that settles within the first two thirds: the held-out third is motionless, so it validates nothing
    step = Command("step", "step", 0.3, 0.0, 0.0)
    t = np.arange(0, 6.0, 0.001)
    q_d, qd_d, _ = step(t)
    f = tmp_path / "step.csv"
    np.savetxt(f, np.c_[t, continuous_reference(step, 0.05, 20.0, 2.0, t), q_d, qd_d], delimiter=",",
               header="time,q,q_d,qd_d", comments="")
    out = tmp_path / "run"
    # recorded too: the recording walked the held-out conditions and met none
    assert main(["fit", "pd", *JOINT, "--reference", str(f), "--out", str(out), "--quiet"]) == 0
    assert (out / "recording.rrd").exists()
    import json

    r = json.loads((out / "result.json").read_text())
    assert r["validation"]["verdict"] == "unvalidated"
    assert any("hardly moves" in w for w in r["warnings"]) and "hardly moves" in capsys.readouterr().err


def test_the_joints_zero_does_not_change_the_errors(tmp_path):
    """The relative error was divided by the RMS of q itself: the same log with the encoder's zero 2 rad away (a
    joint working around 115 degrees) read 7x better, and a friction log's "expand" became "absorbed". Now the motion
    from each condition's start is the scale: the same errors either way."""
    from wrenorm.tasks.pd.problem import Command, PDProblem, continuous_reference

    cmd = Command("mix", "multisine", 0.5, 0.6, 1.7)
    t = np.arange(0, 6.0, 0.001)
    q_d, qd_d, _ = cmd(t)
    q = continuous_reference(cmd, 0.05, 20.0, 0.5, t) + 0.01 * np.sin(7 * t)  # a little the model does not have
    errors = []
    for offset in (0.0, 2.0):
        f = tmp_path / f"log{offset}.csv"
        np.savetxt(f, np.c_[t, q + offset, q_d + offset, qd_d], delimiter=",", header="time,q,q_d,qd_d", comments="")
        p = PDProblem(100.0, log=load_log(f))
        values = p.space.measured[None]
        errors.append(np.concatenate([p.errors(values, p.train)[0], p.errors(values, p.held_out)[0]]))
    np.testing.assert_allclose(errors[1], errors[0], rtol=1e-6)


def test_q_in_degrees_beside_a_command_in_radians_is_refused(tmp_path):
    """q 57x its command (degrees beside radians) fitted every gain to its bound and said only "expand"."""
    t = np.arange(0, 4.0, 0.001)
    f = tmp_path / "mixed.csv"
    cols = np.c_[t, np.degrees(0.3 * np.sin(2 * t)), 0.3 * np.sin(2 * t + 0.1), 0.6 * np.cos(2 * t + 0.1)]
    np.savetxt(f, cols, delimiter=",", header="time,q,q_d,qd_d", comments="")
    with pytest.raises(InputError) as e:
        load_log(f)
    assert e.value.field == "q" and "degrees" in e.value.problem
    load_log(_write(tmp_path / "same.csv"))  # both in radians: read


def test_the_held_out_scale_does_not_follow_where_the_log_is_cut(tmp_path):
    """Measured from each part's first sample, the held-out third's scale ran 0.354-0.578 with the phase at the cut
    of one 0.5 rad sine log (review of stop 45): one origin per log, its median q."""
    from wrenorm.tasks.pd.problem import PDProblem

    scales = []
    for span in (6.0, 6.25, 6.5, 6.75):
        t = np.arange(0, span, 0.001)
        f = tmp_path / f"sine{span}.csv"
        w = 2 * np.pi * 0.5
        np.savetxt(f, np.c_[t, 0.5 * np.sin(w * t) + 2.0, 0.5 * np.sin(w * t + 0.05) + 2.0,
                            0.5 * w * np.cos(w * t + 0.05)], delimiter=",", header="time,q,q_d,qd_d", comments="")
        p = PDProblem(100.0, log=load_log(f))
        scales.append(float(p._commands(p.held_out).ref_scale.numpy()[0]))
    np.testing.assert_allclose(scales, 0.5 / np.sqrt(2), rtol=0.1)


def _multisine_log(path, t0=0.0, rate=1000.0, noise=0.0, qd_scale=1.0, seed=0):
    """The joint's exact response (J 0.05, K_P 20, K_D 0.5) to the built-in multisine, logged from t0."""
    from wrenorm.tasks.pd.problem import Command, exact_reference

    cmd = Command("mix", "multisine", 0.5, 0.6, 1.7)
    t = np.arange(int(round(6.0 * rate)) + 1) / rate
    q = exact_reference(cmd, 0.05, 20.0, 0.5, t) + noise * np.random.default_rng(seed).standard_normal(len(t))
    q_d, qd_d, _ = cmd(t)
    keep = t >= t0
    np.savetxt(path, np.c_[t[keep], q[keep], q_d[keep], qd_d[keep] * qd_scale], delimiter=",",
               header="time,q,q_d,qd_d", comments="")
    return path


@pytest.mark.parametrize("f_sim", [100.0, 20.0])
def test_a_log_started_mid_motion_fits_as_one_started_at_rest(tmp_path, f_sim):
    """Each part of a log starts from the logged state; the velocity of the semi-implicit step lives half a step
    before its time, and a start from q'(a) alone put a log cut 1 s into the motion 1.3 % (100 Hz) and 15 % (20 Hz)
    off in K_D, the 20 Hz verdict turned to "expand" (a probe of stop 46). The held-out third always starts
    mid-motion."""
    from wrenorm.fit import FitSettings, run_fit
    from wrenorm.tasks.pd.problem import PDProblem

    fits = [run_fit(PDProblem(f_sim, log=load_log(_multisine_log(tmp_path / f"{t0}.csv", t0=t0))),
                    tmp_path / f"run{t0}", FitSettings(method="least-squares"), record=False, quiet=True)
            for t0 in (0.0, 1.0)]
    rest, mid = (f["parameters"]["K_D"]["fitted"] for f in fits)
    assert mid == pytest.approx(rest, rel=0.005 if f_sim == 100.0 else 0.03)
    assert [f["validation"]["verdict"] for f in fits] == ["absorbed", "absorbed"]


def test_qd_d_in_other_units_than_q_d_per_second_is_refused(tmp_path):
    """qd_d in rpm beside q_d in rad (9.55x) passed the clock check (10x) and came out as K_FF = -0.9 K_D, silent."""
    with pytest.raises(InputError) as e:
        load_log(_multisine_log(tmp_path / "rpm.csv", qd_scale=60 / (2 * np.pi)))
    assert e.value.field == "qd_d" and "rpm" in e.value.problem
    load_log(_multisine_log(tmp_path / "rad.csv"))
    # degrees per second beside radians (57.3x, and its inverse) had been refused as a clock in milliseconds
    for scale in (np.degrees(1.0), np.radians(1.0)):
        with pytest.raises(InputError) as e:
            load_log(_multisine_log(tmp_path / "deg.csv", qd_scale=scale))
        assert e.value.field == "qd_d" and "degrees" in e.value.problem, e.value


def test_a_multi_turn_zero_and_a_step_in_degrees_are_not_refused_as_units_or_wraps(tmp_path):
    """q and q_d 20 turns off zero (a multi-turn encoder) had been refused as "degrees?", and a consistent log in
    degrees whose command steps by 63 had been refused as "wrapped at +-pi" (a probe of stop 58); the law is linear in
    the angle, so both fit as the plain log does. Moving over 100 rad, and a jump of one turn, are still refused."""
    rate = 200.0
    t = np.arange(int(4 * rate)) / rate
    q_d = np.where(t < 1.0, 0.0, 1.1)
    q = 1.1 * (t >= 1.0) * (1 - np.exp(-np.maximum(t - 1.0, 0.0) / 0.2))
    f = tmp_path / "log.csv"
    for shift, scale in ((40 * np.pi, 1.0), (0.0, np.degrees(1.0))):
        np.savetxt(f, np.c_[t, scale * q + shift, scale * q_d + shift, 0 * t], delimiter=",",
                   header="time,q,q_d,qd_d", comments="")
        log = load_log(f)
        assert np.allclose(log.q_d - log.q, scale * (q_d - q))
    np.savetxt(f, np.c_[t, 100 * q, 100 * q_d, 0 * t], delimiter=",", header="time,q,q_d,qd_d", comments="")
    with pytest.raises(InputError, match="moves over"):
        load_log(f)
    wrapped = np.angle(np.exp(1j * (3.0 * t)))  # a joint turning steadily, logged modulo a turn
    np.savetxt(f, np.c_[t, wrapped, wrapped, 3.0 + 0 * t], delimiter=",", header="time,q,q_d,qd_d", comments="")
    with pytest.raises(InputError, match="unwrap"):
        load_log(f)


def test_a_hole_of_exactly_the_longest_allowed_gap_is_read(tmp_path):
    """A 200 Hz log with 4 samples dropped (a hole of exactly 5 steps, 25 ms) had been refused: 0.025000000000000133 s
    in floating point is more than 5 x 0.005 s (a probe of stop 58)."""
    t = np.arange(1200) * 0.005
    k = 600 + int(np.argmax(t[605:] - t[600:-5] > MAX_GAP_STEPS * 0.005))  # a hole that rounds over
    keep = np.ones(len(t), bool)
    keep[k + 1:k + 5] = False
    q_d = 0.3 * np.sin(2 * np.pi * 0.7 * t)
    f = tmp_path / "hole5.csv"
    np.savetxt(f, np.c_[t, q_d, q_d, 0.3 * 2 * np.pi * 0.7 * np.cos(2 * np.pi * 0.7 * t)][keep], delimiter=",",
               header="time,q,q_d,qd_d", comments="")
    assert np.max(np.diff(t[keep])) > MAX_GAP_STEPS * 0.005  # the rounding that had refused it
    load_log(f)
    keep[k + 5] = False  # 6 steps: rows missing
    np.savetxt(f, np.c_[t, q_d, q_d, 0.3 * 2 * np.pi * 0.7 * np.cos(2 * np.pi * 0.7 * t)][keep], delimiter=",",
               header="time,q,q_d,qd_d", comments="")
    with pytest.raises(InputError, match="rows missing"):
        load_log(f)


def test_a_noisy_start_velocity_is_fitted_not_absorbed_by_the_gains(tmp_path):
    """2 mrad of noise at 500 Hz leaves the start velocity from the samples off by about 0.6 rad/s; its start transient
    was absorbed by the gains (K_D 19 % high, "absorbed", nothing said; a probe of stop 46). Each part's start velocity
    is now corrected by the fit: K_D within 2 % of the noise-free log's, the correction reported."""
    from wrenorm.fit import FitSettings, run_fit
    from wrenorm.tasks.pd.problem import PDProblem

    fits = {name: run_fit(PDProblem(100.0, log=load_log(_multisine_log(tmp_path / f"{name}.csv", rate=500.0,
                                                                         noise=noise, seed=202))),
                          tmp_path / name, FitSettings(method="least-squares"), record=False, quiet=True)
            for name, noise in (("clean", 0.0), ("noisy", 2e-3))}
    clean, noisy = (fits[n]["parameters"]["K_D"]["fitted"] for n in ("clean", "noisy"))
    assert noisy == pytest.approx(clean, rel=0.02)
    corrections = fits["noisy"]["start_velocity_correction"]["per_part"]
    assert set(corrections) == {"log_fit", "log_validate"} and abs(corrections["log_fit"]) > 0.05
    assert abs(fits["clean"]["start_velocity_correction"]["per_part"]["log_fit"]) < 0.05


def test_a_logs_residuals_agree_with_its_errors_and_its_trajectories(tmp_path):
    """With the start velocity fitted per part, what the search minimises (residuals), what the verdict reads (errors)
    and what the report and the recording draw (trajectories) are the same corrected rollout."""
    from wrenorm.tasks.pd.problem import PDProblem

    p = PDProblem(100.0, log=load_log(_multisine_log(tmp_path / "log.csv", rate=500.0, noise=2e-3, seed=3)))
    values = p.space.measured[None] * np.array([[1.1, 1.0, 0.9, 1.0, 1.0]]) + np.array([[0, 0, 0, 0.01, 0.0]])
    conds = p.train + p.held_out
    errors = p.errors(values, conds)[0]  # each part whole (since stop 56: a batch had run to the shortest)
    for j, c in enumerate(conds):
        r = p.residuals(values, [c])[0]
        assert np.sqrt(np.sum(r * r)) == pytest.approx(errors[j], rel=1e-9)
        traj = p.trajectories(values, [c])[0, 0]
        n = len(traj) - 1
        assert n == len(c.data["q_d"])
        misfit = (traj[1:] - c.data["q_ref"][1:n + 1]) / np.sqrt(np.mean((c.data["q_ref"][1:n + 1] -
                                                                             c.data["origin"]) ** 2))
        assert np.sqrt(np.mean(misfit ** 2)) == pytest.approx(errors[j], rel=1e-9)


@pytest.mark.parametrize("integrator", ["semi-implicit", "explicit"])
def test_the_fitted_start_is_the_best_shift_of_plain_rollouts(tmp_path, integrator):
    """The one-loop start fit (the unit response run beside the rollout, the misfit a quadratic in the shift) against
    plain rollouts from shifted starts: the same error at its shift, and no error lower a little either side of it."""
    from wrenorm.kernels import pd as kpd
    from wrenorm.tasks.pd.problem import PDProblem

    p = PDProblem(100.0, integrator=integrator,
                  log=load_log(_multisine_log(tmp_path / "log.csv", rate=500.0, noise=2e-3, seed=11)))
    conds = p.train + p.held_out
    values = p.space.measured[None] * np.array([[1.0, 1.0, 1.0, 1.0, 1.0], [1.15, 1.0, 0.8, 1.0, 1.0]])
    values[:, 3] += np.array([0.0, 0.02])
    errors, shifts, traj = kpd.simulate_start_fitted(values, p._commands(conds), [True, False, True][:len(conds)],
                                                     kpd.INTEGRATORS[integrator], p.dt, record=True)
    assert np.all(shifts[:, 1] == 0.0) and np.all(np.abs(shifts[:, 0]) > 1e-3)
    cmds = p._commands(conds)
    init = cmds.init.numpy().copy()
    for b in range(len(values)):
        for j in range(len(conds)):
            plain = []
            for dv in (shifts[b, j] - 0.01, shifts[b, j], shifts[b, j] + 0.01):
                cmds.init = kpd.wp.array(init + np.eye(len(conds))[j][:, None] * [0.0, dv], dtype=kpd.wp.float64)
                e, tr = kpd.simulate(values[b:b + 1], cmds, kpd.INTEGRATORS[integrator], p.dt, record=True)
                plain.append((e[0, j], tr[0, j]))
            assert errors[b, j] == pytest.approx(plain[1][0], rel=1e-9)
            np.testing.assert_allclose(traj[b, j], plain[1][1], rtol=0, atol=1e-12)
            if shifts[b, j] != 0.0:
                assert plain[0][0] > errors[b, j] and plain[2][0] > errors[b, j]
    cmds.init = kpd.wp.array(init, dtype=kpd.wp.float64)


@pytest.mark.parametrize("how,field,needle", [("negated", "q", "sign"), ("wrapped", "q row", "wrapped")])
def test_q_with_another_sign_or_wrapped_at_pi_is_refused(tmp_path, how, field, needle):
    """q logged with the other sign convention, or modulo a turn, ended only in "expand" with gains at their bounds,
    which sent the user to free parameters (a probe of stop 46)."""
    path = _multisine_log(tmp_path / "log.csv")
    data = np.loadtxt(path, delimiter=",", skiprows=1)
    if how == "negated":
        data[:, 1] = -data[:, 1]
    else:
        data[:, 1:3] += 2.9  # the joint works near pi, logged wrapped into (-pi, pi]
        data[:, 1] = (data[:, 1] + np.pi) % (2 * np.pi) - np.pi
    np.savetxt(path, data, delimiter=",", header="time,q,q_d,qd_d", comments="")
    with pytest.raises(InputError) as e:
        load_log(path)
    assert e.value.field.startswith(field) and needle in e.value.problem


def test_the_reported_start_corrections_are_each_parts_own(tmp_path):
    """Evaluated together the parts are cut to the shortest, so the log_fit part's correction came from its first
    third (review of stop 46): each part's correction is its own rollout's."""
    from wrenorm.tasks.pd.problem import PDProblem

    p = PDProblem(50.0, log=load_log(_multisine_log(tmp_path / "log.csv", rate=500.0, noise=2e-3, seed=5)))
    values = p.space.measured * np.array([1.2, 1.0, 0.7, 1.0, 1.0])
    reported = p.report(values, p.space.measured)["start_velocity_correction"]["per_part"]
    for c in p.train + p.held_out:
        assert reported[c.name] == pytest.approx(p._start_corrected(values[None], [c])[1][0, 0], rel=1e-12)
    together = p._start_corrected(values[None], p.train + p.held_out)[1][0, 0]
    assert abs(together - reported["log_fit"]) > 1e-6  # the shortened window gives another value


def _friction_log(path, coulomb=0.0, noise=0.0, scale=1.0, rate=1000.0, seed=0, cmd=None):
    """The continuous joint (J 0.05, K_P 20, K_D 0.5) with Coulomb friction (smoothed over 0.01 rad/s) by LSODA: physics
    the coarse model omits."""
    from scipy.integrate import solve_ivp

    from wrenorm.tasks.pd.problem import Command

    cmd = cmd or Command("mix", "multisine", 0.5 * scale, 0.6, 1.7)

    def rhs(t, y):
        qd, qdd, _ = cmd(np.array([t]))
        return [y[1], (20.0 * (qd[0] - y[0]) + 0.5 * (qdd[0] - y[1]) - coulomb * np.tanh(y[1] / 0.01)) / 0.05]

    t = np.arange(int(6 * rate) + 1) / rate
    sol = solve_ivp(rhs, (0, t[-1]), [0.0, 0.0], t_eval=t, method="LSODA", rtol=1e-10, atol=1e-12, max_step=1e-3)
    q = sol.y[0] + noise * np.random.default_rng(seed).standard_normal(len(t))
    q_d, qd_d, _ = cmd(t)
    np.savetxt(path, np.c_[t, q, q_d, qd_d], delimiter=",", header="time,q,q_d,qd_d", comments="")
    return path


def test_the_noise_of_q_is_estimated_from_the_samples():
    from wrenorm.tasks.pd.problem import q_noise

    t = np.arange(0, 6, 0.001)
    smooth = 0.3 * np.sin(2 * t) + 0.1 * np.sin(11 * t)
    assert q_noise(smooth) < 1e-9
    for sigma in (1e-4, 1e-3):
        noisy = smooth + sigma * np.random.default_rng(1).standard_normal(len(t))
        assert q_noise(noisy) == pytest.approx(sigma, rel=0.05)
    # a 12-bit encoder's counts on a slow, small motion: most 4th differences are exactly 0; its rounding is step /
    # sqrt(12) (review of stop 47: it read 0), written as a log writes it (9 digits)
    count = 2 * np.pi / 4096
    for scale in (0.05, 0.5):
        logged = np.array([float(f"{v:.9g}") for v in np.round(scale * np.sin(0.5 * t) / count) * count])
        assert q_noise(logged) >= count / np.sqrt(12) * 0.999


def test_friction_absorbed_within_tolerance_is_said(tmp_path):
    """Coulomb friction of 0.2 N m: K_D came out 16 % high with "absorbed" and no word (a probe of stop 47). The
    verdict stands (the effective values do reproduce the held-out motion to 2 %), and a warning says that the log's
    noise does not explain the misfit, so the values are effective ones; a friction-free log says nothing."""
    from wrenorm.fit import FitSettings, run_fit
    from wrenorm.tasks.pd.problem import PDProblem

    res = {name: run_fit(PDProblem(100.0, log=load_log(_friction_log(tmp_path / f"{name}.csv", coulomb=c))),
                         tmp_path / name, FitSettings(method="least-squares"), record=False, quiet=True)
           for name, c in (("clean", 0.0), ("friction", 0.2))}
    assert res["friction"]["validation"]["verdict"] == "absorbed"
    assert res["friction"]["parameters"]["K_D"]["fitted"] > 1.1 * 0.5
    said = [w for w in res["friction"]["warnings"] if "structured misfit" in w]
    assert len(said) == 1 and "log_validate" in said[0]
    assert not [w for w in res["clean"]["warnings"] if "structured misfit" in w]
    c = res["friction"]["validation"]["conditions"]["log_validate"]
    assert c["noise_floor"] < 1e-6 and c["fitted_unexplained"] == pytest.approx(c["fitted_error"], rel=1e-6)


def test_a_noisy_logs_tolerance_is_never_below_its_noise(tmp_path):
    """1 mrad of noise on a motion a tenth the size: the held-out error is the noise floor itself (0.04 against the
    tolerance 0.02), and a model that could not be better got "expand" (a probe of stop 47). The tolerance is now at
    least twice the error the noise alone leaves."""
    from wrenorm.fit import FitSettings, run_fit
    from wrenorm.tasks.pd.problem import PDProblem

    p = PDProblem(100.0, log=load_log(_friction_log(tmp_path / "log.csv", noise=1e-3, scale=0.1)))
    c = p.held_out[0]
    motion = float(p._commands([c]).ref_scale.numpy()[0])
    assert c.data["noise_floor"] == pytest.approx(1e-3 / motion, rel=0.1)
    assert p.tolerance_for(c) == pytest.approx(2 * c.data["noise_floor"]) and p.tolerance_for(c) > 0.05
    res = run_fit(p, tmp_path / "run", FitSettings(method="least-squares"), record=False, quiet=True)
    v = res["validation"]
    assert v["verdict"] == "absorbed" and v["conditions"]["log_validate"]["fitted_error"] > 0.02
    assert res["parameters"]["K_D"]["fitted"] == pytest.approx(0.5, rel=0.06)


def _exact_log(path, lag=0.0, qd_lag=0.0, KP=20.0, KD=0.5, wrap=False, still=0.0, rate=1000.0, dur=6.0):
    """A log of the exact PD joint (J 0.05) under a multisine command; the logged command `lag` s late against q (its
    velocity a further `qd_lag` s), a wrapped q_d, or a joint still for its first `still` s."""
    from wrenorm.tasks.pd.problem import Command, exact_reference

    cmd = Command("mix", "multisine", 0.5, 0.6, 1.7)
    t = np.arange(int(round(dur * rate)) + 1) / rate
    move = np.clip(t - still, 0.0, None)
    q = exact_reference(cmd, 0.05, KP, KD, move)
    q_d, qd_d = cmd(np.clip(move - lag, 0.0, None))[0], cmd(np.clip(move - lag - qd_lag, 0.0, None))[1]
    if wrap:
        q, q_d = q + 3.0, (q_d + 3.0 + np.pi) % (2 * np.pi) - np.pi
    if still:
        q = q + 1e-4 * np.random.default_rng(0).standard_normal(len(t))
    np.savetxt(path, np.stack([t, q, q_d, qd_d], 1), delimiter=",", header="time,q,q_d,qd_d", comments="")
    return path


def _fit_warnings(tmp_path, log):
    import json

    out = tmp_path / ("fit-" + log.stem)
    assert main(["fit", "pd", "--quiet", "--no-record", *JOINT, "--reference", str(log), "--out", str(out)]) == 0
    return json.loads((out / "result.json").read_text())["warnings"]


def test_a_command_on_another_clock_or_gains_not_the_logs_are_said(tmp_path):
    """The exact joint's log fits with nothing said; its command logged 20 ms late fitted K_FF 0.39 (77 % of K_D),
    and given gains half the log's fitted J 44 % low, both said only "absorbed" (review of stop 54)."""
    assert _fit_warnings(tmp_path, _exact_log(tmp_path / "clean.csv")) == []
    said = _fit_warnings(tmp_path, _exact_log(tmp_path / "late.csv", lag=0.02))
    assert len(said) == 1 and "K_FF" in said[0] and "time offset of about +19" in said[0]
    said = _fit_warnings(tmp_path, _exact_log(tmp_path / "gains.csv", KP=40.0, KD=1.0))
    assert any(w.startswith("J fitted at") and "this log's gains" in w for w in said)


@pytest.mark.parametrize("how, field, said", [
    ({"qd_lag": 0.02}, "qd_d", "lags the rate of change of q_d by 20 ms"),
    ({"wrap": True}, "q_d row", "wrapped at +-pi"),
    ({"still": 4.5}, "q", "first two thirds of the log, which the fit uses, hardly move"),
])
def test_a_command_velocity_on_another_clock_a_wrapped_command_or_a_still_fit_part_is_refused(tmp_path, how, field,
                                                                                              said):
    """Each had been fitted and said "absorbed" or "expand" with no cause named (review of stop 54)."""
    log = _exact_log(tmp_path / "bad.csv", **how)
    with pytest.raises(InputError) as e:
        from wrenorm.tasks.pd.problem import PDProblem

        PDProblem(100.0, "semi-implicit", log=load_log(log))
    assert e.value.field.startswith(field) and said in e.value.problem


def _sample_and_hold_log(path, rate_c: float, J=0.05, KP=20.0, KD=0.5, rate=1000.0, T=9.0):
    """A servo that samples q, qd and the command at rate_c and holds its PD torque between, on a joint integrated
    exactly (constant acceleration within each 1 ms), logged at 1 kHz."""
    t = np.arange(int(T * rate) + 1) / rate
    w, a = np.array([0.7, 1.9, 3.1]), np.array([0.5, 0.2, 0.08])
    q_d, qd_d = (a * np.sin(np.outer(t, w))).sum(1), (a * w * np.cos(np.outer(t, w))).sum(1)
    q, v, u, rows = 0.0, 0.0, 0.0, []
    every = int(round(rate / rate_c))
    for k in range(len(t)):
        rows.append((t[k], q, q_d[k], qd_d[k]))
        if k % every == 0:
            u = KP * (q_d[k] - q) + KD * (qd_d[k] - v)
        q, v = q + v / rate + u / (2 * J) / rate ** 2, v + u / J / rate
    np.savetxt(path, np.array(rows), delimiter=",", header="time,q,q_d,qd_d", comments="", fmt="%.12g")
    return path


def test_a_servo_that_samples_and_holds_its_torque_is_predicted_with_controller_rate(tmp_path, capsys):
    """A 50 Hz servo moves K_D by -K_P / (2 f_c) = -41 % and J by -K_D / (2 f_c): the fit recovers that (a review's
    peer-simulated logs, stop 55), and without --controller-rate the gains check names the hold as a cause; with it,
    the predictions include the hold and nothing is said. The built-in reference has no servo to give a rate to."""
    log = _sample_and_hold_log(tmp_path / "servo50.csv", 50.0)
    for extra, said in (([], True), (["--controller-rate", "50"], False)):
        out = tmp_path / f"fit{len(extra)}"
        assert main(["fit", "pd", *JOINT, "--reference", str(log), "--f-sim", "200", *extra, "--out", str(out),
                     "--quiet", "--no-record"]) == 0
        r = json.loads((out / "result.json").read_text())
        gains = [w for w in r["warnings"] if "sample and hold" in w]
        assert bool(gains) == said, r["warnings"]
    a, fitted = r["analytic"], {k: v["fitted"] for k, v in r["parameters"].items()}
    assert a["controller_hold_s"] == pytest.approx(0.01)
    assert fitted["K_D"] == pytest.approx(a["K_D_sim_first_order"], rel=0.03)  # 0.3 against 0.5 given
    assert fitted["J"] == pytest.approx(a["J_sim_first_order"], rel=0.03)
    assert main(["fit", "pd", "--controller-rate", "50", "--out", str(tmp_path / "builtin")]) == 2
    assert "--controller-rate: controller_rate: goes with --reference" in capsys.readouterr().err


def test_friction_values_fitted_on_one_command_are_validated_on_another_log(tmp_path, capsys):
    """Coulomb friction of 0.05 N m under 2-5 Hz sines: validated on the same log's last third it was "absorbed" with
    no word (the misfit 2.3x what the noise explains, under the old 3x), while the values miss the same joint's slow
    motion by almost three times the tolerance (review of stop 55). The last third now says so and points to
    --validate, and a log of another command validates whole: "expand"."""
    import json

    from wrenorm.cli import main
    from wrenorm.tasks.pd.problem import Command

    fast = _friction_log(tmp_path / "fast.csv", coulomb=0.05, noise=5e-4, cmd=Command("f", "multisine", 0.3, 1.7, 2.9))
    slow = _friction_log(tmp_path / "slow.csv", coulomb=0.05, noise=5e-4, seed=1,
                         cmd=Command("s", "multisine", 0.12, 0.4, 0.9))
    common = ["fit", "pd", *JOINT, "--reference", str(fast), "--f-sim", "200", "--quiet", "--no-record"]
    assert main(common + ["--out", str(tmp_path / "one")]) == 0
    one = json.loads((tmp_path / "one" / "result.json").read_text())
    assert one["validation"]["verdict"] == "absorbed"
    said = [w for w in one["warnings"] if "structured misfit" in w]
    assert len(said) == 1 and "--validate" in said[0]
    c = one["validation"]["conditions"]["log_validate"]
    assert 1.5 < c["fitted_unexplained"] / c["noise_floor"] < 3.0  # the case the old threshold let pass

    assert main(common + ["--out", str(tmp_path / "two"), "--validate", str(slow)]) == 0
    two = json.loads((tmp_path / "two" / "result.json").read_text())
    assert two["validation"]["verdict"] == "expand" and two["validation"]["worst_condition"] == "slow"
    assert two["parameters"] == one["parameters"]  # the same fit: only what it is validated on changed
    assert two["validation"]["conditions"]["slow"]["fitted_error"] > 2 * two["validation"]["conditions"]["slow"][
        "tolerance"]

    capsys.readouterr()
    for extra, needle in ((["--validate", str(slow)], "goes with --reference"),
                          (["--reference", str(fast), "--validate", str(fast)], "the fitted log itself")):
        assert main(["fit", "pd", "--quiet", "--no-record", "--out", str(tmp_path / "bad")] + extra) == 2
        err = capsys.readouterr().err
        assert "--validate" in err and needle in err and len(err.strip().splitlines()) == 1


def test_a_validate_log_is_judged_whole_not_to_the_length_of_the_last_third(tmp_path):
    """One batch runs its conditions to the shortest: a 6 s --validate log beside the fitted log's 2 s last third was
    judged on its first 2 s (review of stop 56's diff). Here it agrees with the joint there and not after: its error
    alone and in the verdict agree, and are large."""
    from wrenorm.tasks.pd.problem import PDProblem

    fast = load_log(_friction_log(tmp_path / "fast.csv"))
    other = np.loadtxt(_friction_log(tmp_path / "other.csv", seed=1), delimiter=",", skiprows=1)
    late = other[:, 0] > 3.0
    other[late, 1] += 0.3 * np.sin(5 * other[late, 0])  # the joint does something else after 3 s
    np.savetxt(tmp_path / "other.csv", other, delimiter=",", header="time,q,q_d,qd_d", comments="")
    p = PDProblem(200.0, log=fast, validate_logs=[load_log(tmp_path / "other.csv")])
    v = p.space.measured[None]
    together = p.validation_errors(v, p.held_out)[0][0]
    alone = [float(p.errors(v, [c])[0, 0]) for c in p.held_out]
    np.testing.assert_allclose(together, alone, rtol=1e-9)
    assert alone[1] > 10 * alone[0]


def test_a_validate_log_sampled_coarsely_or_standing_still_is_said(tmp_path):
    from wrenorm.tasks.pd.problem import PDProblem

    fast = load_log(_friction_log(tmp_path / "fast.csv"))
    coarse = load_log(_friction_log(tmp_path / "coarse.csv", rate=20.0, seed=1))
    still = np.loadtxt(_friction_log(tmp_path / "still.csv", seed=2), delimiter=",", skiprows=1)
    still[:, 1:] *= 1e-3
    np.savetxt(tmp_path / "still.csv", still, delimiter=",", header="time,q,q_d,qd_d", comments="")
    p = PDProblem(200.0, log=fast, validate_logs=[coarse, load_log(tmp_path / "still.csv")])
    assert any("coarse.csv" in w and "coarser than the simulation's step" in w for w in p.warnings)
    assert any("still.csv" in w and "hardly moves" in w for w in p.warnings)
    assert [c.name for c in p.held_out] == ["log_validate", "coarse"]


@pytest.mark.parametrize("lag_deg", [100.0, 175.0])
def test_a_q_behind_its_command_is_not_called_only_a_sign_convention(tmp_path, lag_deg):
    """A 25-row log caught q behind a turning q_d and was refused as a sign convention alone (stop 58's probe): a
    q that runs against q_d names the fast command and the short log beside the sign, whatever the correlation (a
    lag of 125-150 deg gives one under -0.5; review of stop 59)."""
    t = np.arange(25) * 0.005
    w = 2.0 * np.pi * 8.0
    q_d, qd_d = 0.3 * np.sin(w * t), 0.3 * w * np.cos(w * t)
    q = 0.3 * np.sin(w * t - np.radians(lag_deg))
    path = tmp_path / "short.csv"
    np.savetxt(path, np.column_stack([t, q, q_d, qd_d]), delimiter=",", header="time,q,q_d,qd_d", comments="")
    with pytest.raises(InputError) as e:
        load_log(path)
    assert e.value.field == "q" and "runs against q_d" in e.value.problem and "sign convention" in e.value.problem
    assert "faster than the joint follows" in e.value.problem and "too short" in e.value.problem
