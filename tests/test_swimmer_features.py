"""Trajectory features: recovered from a fish whose motion is known in closed form, measured the same
on real-format markers and in the fit, the noise model, the measured-window recording."""
import numpy as np
import pytest
from swimmer_checks import PUBLISHED

from wrenorm.tasks.swimmer import body as sb
from wrenorm.tasks.swimmer import data as sd
from wrenorm.tasks.swimmer import features as sf
from wrenorm.tasks.swimmer import problem as swimmer


def synthetic_fish(turn=0.0, seconds=6.0, fps=60.0, f=0.8):
    """Head markers of a fish with a known swimming pattern (complex amplitudes y = Re(c e^{i k w t}),
    phases relative to the tail tip's lateral motion): forward speed U with a 2f surge, yaw and sway
    at f, the whole path turning slowly at `turn` rad/s about the start."""
    w = 2 * np.pi * f
    t = np.arange(int(seconds * fps)) / fps
    tip_phase = 0.7
    truth = {"speed": 0.1, "yaw_amp": 0.12, "yaw_phase": 2.6, "sway_amp": 0.015, "sway_phase": 1.4,
             "surge2_amp": 0.012, "surge2_phase": -2.5}
    tip = 0.1 * np.cos(w * t + tip_phase)
    c_yaw = truth["yaw_amp"] * np.exp(1j * (truth["yaw_phase"] + tip_phase))
    c_sway = truth["sway_amp"] * np.exp(1j * (truth["sway_phase"] + tip_phase))
    c_v2 = truth["surge2_amp"] * np.exp(1j * (truth["surge2_phase"] + 2 * tip_phase))   # velocity at 2f
    l = np.real(c_sway * np.exp(1j * w * t))
    psi = np.real(c_yaw * np.exp(1j * w * t))
    a = 0.3 + turn * t                                    # path direction, turning slowly
    d = np.stack([np.cos(a), np.sin(a)], 1)
    n = np.stack([-np.sin(a), np.cos(a)], 1)
    # turning: integrate the forward motion along the turning direction
    v = truth["speed"] + np.real(c_v2 * np.exp(2j * w * t))
    vel = v[:, None] * d
    pos = np.concatenate([[[0.0, 0.0]], np.cumsum(0.5 * (vel[1:] + vel[:-1]), 0) / fps]) + l[:, None] * n
    e = np.stack([np.cos(a + psi), np.sin(a + psi)], 1)   # heading, marker 1 -> marker 0
    m0, m1 = pos + 0.071 * e, pos - 0.071 * e
    return t, m0, m1, tip, f, truth


@pytest.mark.parametrize("turn", [0.0, 0.03])
def test_features_recover_a_known_swimming_pattern(turn):
    t, m0, m1, tip, f, truth = synthetic_fish(turn=turn)
    beats = sf.beat_features(t, m0, m1, tip, f)
    assert beats["yaw"].shape == (4,)                    # 6 s at 0.8 Hz: four complete beats
    got = sf.clip_features(beats, sd.line_speed(t, 0.5 * (m0 + m1), m0 - m1))
    # a turning path mixes the sway (1f, modulated by the slow turn) into the forward signal within a
    # beat: ~1.7 % of the 2f surge amplitude per 0.01 rad/s of turn (the real clips turn < 0.06 rad/s)
    tol = {"speed": 2e-3, "yaw_amp": 2e-3, "sway_amp": 3e-4, "surge2_amp": 5e-4 + 0.025 * turn}
    for k, v in truth.items():
        if k.endswith("_phase"):
            assert abs(np.angle(np.exp(1j * (got[k] - v)))) < 0.03, (k, got[k], v)
        else:
            assert abs(got[k] - v) < tol[k], (k, got[k], v)
    # per-beat speeds of a steady fish: the speed itself, no spread to speak of
    spread = sf.beat_spread(beats)
    assert spread["beats"] == 4 and spread["speed"] < 1e-3 and spread["yaw_phase"] < 0.02


def test_beat_spread_sees_beat_to_beat_variation():
    """Yaw amplitude alternating 0.10 / 0.14 between beats: std over beats about 0.02."""
    fps, f = 60.0, 1.0
    t = np.arange(int(8 * fps)) / fps
    amp = np.where(np.floor(t * f) % 2 == 0, 0.10, 0.14)
    psi = amp * np.cos(2 * np.pi * f * t)
    e = np.stack([np.cos(psi), np.sin(psi)], 1)
    pos = np.stack([-0.1 * t, np.zeros_like(t)], 1)
    m0, m1 = pos - 0.071 * e, pos + 0.071 * e                # swimming towards -x, heading -x
    beats = sf.beat_features(t, m0, m1, np.cos(2 * np.pi * f * t), f)
    np.testing.assert_allclose(np.abs(beats["yaw"]), np.tile([0.10, 0.14], 4), atol=2e-3)
    assert sf.beat_spread(beats)["yaw_amp"] == pytest.approx(np.std(np.tile([0.10, 0.14], 4), ddof=1), rel=0.05)


@pytest.fixture(scope="module")
def rates():
    return sd.load_builtin()


def test_real_pipeline_on_simulated_markers_matches_the_fit(rates):
    """The fit measures simulated fish in the kernel's step times; render the same fish as a 60 fps
    marker clip (head markers from the trajectory, tail markers on the gait's wave), run the real-data
    pipeline on it, and get the same features: the two are measured identically."""
    prob = swimmer.SwimmerProblem(rates, [1.75], features="all")
    cond = prob.train[0]
    coef = np.array([0.2, 1.0, 1.0, 1.0, 0.3])
    fit_side = prob.simulate(coef[None], [cond], features=sf.FEATURES)
    sim = prob.batch([cond])
    t_sim, _ = sim.clock[0]
    _, traj, _ = sim.run(coef[None], rec_stride=1, rec_frames=len(t_sim), rec_meas=True)
    X, Y, th = (traj[0, 0, :, i].astype(np.float64) for i in range(3))
    fps = 60.0
    t = np.arange(int(t_sim[-1] * fps)) / fps
    X, Y, th = (np.interp(t, t_sim, q) for q in (X, Y, th))
    g = prob.gaits[cond.name]
    xs = np.linspace(sb.TAIL_BASE_X, sb.TAIL_TIP_X, 7)
    local = np.zeros((len(t), 9, 2))
    local[:, 1, 0] = sb.HEAD_MARKER_X1
    local[:, 2:, 0] = xs
    local[:, 2:, 1] = sb.wave_eval(g, xs, t)[0]
    c, s = np.cos(th), np.sin(th)
    world = np.stack([X[:, None] + c[:, None] * local[..., 0] - s[:, None] * local[..., 1],
                      Y[:, None] + s[:, None] * local[..., 0] + c[:, None] * local[..., 1]], -1)
    clip = sd.Rate(label=1.75, markers=world, fps=fps, tail_freq=g["freq"])
    clip.meta = {"local": sd.head_frame(world), "tail_markers": list(range(2, 9))}
    real_side, _, _ = sf.real_features(clip)
    assert real_side["speed"] == pytest.approx(fit_side["speed"][0, 0], abs=1.5e-3)
    for k in ("yaw_amp", "sway_amp", "surge2_amp"):
        assert real_side[k] == pytest.approx(fit_side[k][0, 0], rel=0.03), k
    for k in ("yaw_phase", "sway_phase", "surge2_phase"):
        assert abs(np.angle(np.exp(1j * (real_side[k] - fit_side[k][0, 0])))) < 0.03, k


def test_noise_model_pools_training_clips_by_degrees_of_freedom(rates):
    prob = swimmer.SwimmerProblem(rates, [1.0, 1.75], features="all")
    a, b = prob.train
    na, nb = a.meta["feature_spread"]["beats"], b.meta["feature_spread"]["beats"]
    sa, sb_ = a.meta["feature_spread"]["speed"], b.meta["feature_spread"]["speed"]
    pooled = np.sqrt(((na - 1) * sa ** 2 + (nb - 1) * sb_ ** 2) / (na + nb - 2))
    assert prob.noise["speed"]["per_beat"] == pytest.approx(pooled)
    assert prob.sigma(a, "speed") == pytest.approx(pooled / np.sqrt(na))
    ra = a.meta["feature_spread"]["yaw_amp"] / a.meta["features"]["yaw_amp"]
    rb = b.meta["feature_spread"]["yaw_amp"] / b.meta["features"]["yaw_amp"]
    rel = np.sqrt(((na - 1) * ra ** 2 + (nb - 1) * rb ** 2) / (na + nb - 2))
    assert prob.sigma(b, "yaw_amp") == pytest.approx(rel * b.meta["features"]["yaw_amp"] / np.sqrt(nb))
    # the held-out clips do not enter the noise model
    other = swimmer.SwimmerProblem(rates, [1.0, 1.75, 2.25], features="all")
    assert other.noise["speed"]["per_beat"] != pytest.approx(pooled)


def test_recording_from_the_measurement_start(rates):
    sim = sb.build_batch(rates[1:3], meas_seconds=2.0)
    coef = np.array([PUBLISHED, [0.01, 1.6, 0.4, 0.5, 9.0]])
    frames = int(sim.steps.max()) + 4000
    sp_all, full, state = sim.run(coef, rec_stride=1, rec_frames=frames)
    sp_meas, meas, _ = sim.run(coef, rec_stride=1, rec_frames=int(sim.n_meas_host.max()), rec_meas=True)
    np.testing.assert_array_equal(sp_all, sp_meas)
    for b in range(2):
        for j in range(2):
            start = int(round(state[b, j, 6] / sim.dt_host[j]))
            nm = int(sim.n_meas_host[j])
            np.testing.assert_array_equal(meas[b, j, :nm], full[b, j, start:start + nm])
            assert meas[b, j, 0, 3] == 0.0       # the measured window starts at a beat start


def test_waveforms_carry_the_features_and_reach_the_recording(rates):
    t, m0, m1, tip, f, truth = synthetic_fish()
    beats = sf.beat_features(t, m0, m1, tip, f)
    w = sf.waveforms(beats, samples=64)
    c1 = 2 * np.mean(w["yaw"] * np.exp(-2j * np.pi * w["phase"]))       # first harmonic of the waveform
    assert abs(c1) == pytest.approx(truth["yaw_amp"], rel=2e-3)
    assert np.angle(c1) == pytest.approx(truth["yaw_phase"], abs=0.02)

    class Recorder:
        def __init__(self):
            self.series, self.views = {}, []

        def log_series(self, path, times, values, timeline="sim_time"):
            self.series[path] = (timeline, np.asarray(values))

        def add_view(self, name, contents, kind="timeseries", around=None):
            self.views.append((name, kind))

    prob = swimmer.SwimmerProblem(rates, [1.0, 1.75], dt=0.016, features="yaw")
    rec = Recorder()
    prob._record_waveforms(rec, PUBLISHED, PUBLISHED, prob.train + prob.held_out)
    for lab in ("f0.50", "f1.00", "f1.75", "f2.25"):
        for k in ("yaw", "sway"):
            for who in ("reference", "fitted", "measured"):
                timeline, vals = rec.series[f"beat/{lab}/{k}/{who}"]
                assert timeline == "beat_time" and np.all(np.isfinite(vals)) and np.ptp(vals) > 0
    # the real 1.00 Hz fish yaws about 7.5 deg each way: the recorded real curve says so
    yaw = rec.series["beat/f1.00/yaw/reference"][1]
    assert 6.0 < 0.5 * np.ptp(yaw) < 9.5
    assert sum(kind == "timeseries" for _, kind in rec.views) == 15
