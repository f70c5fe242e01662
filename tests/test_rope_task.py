"""Rope task: known-truth recovery with CMA-ES, penalties, input errors."""
import cma
import numpy as np
import pytest

from wrenorm.errors import InputError
from wrenorm.tasks.rope import problem as task
from wrenorm.tasks.rope.reference.generate import RopeReference, first_self_collision
from wrenorm.tasks.rope.reference.paths import builtin_hand_paths

SEG, DT = 10, 0.005
LENGTH, MASS, RADIUS, EI = 1.1, 0.2, 0.005, 3e-3


def synthetic_reference(path_name, values, horizon=1.2):
    """A reference made by the coarse chain itself with hidden parameter values."""
    path = builtin_hand_paths()[path_name]
    steps = int(round(horizon / DT))
    t = np.arange(steps + 1) * DT
    hand = path.positions(t)
    n = SEG + 1
    pos0 = hand[0] - np.outer(np.linspace(0, LENGTH, n), [0, 0, 1])
    ref0 = RopeReference(t, np.repeat(pos0[None], steps + 1, 0), hand, LENGTH, MASS, RADIUS, EI,
                         np.linspace(0, 1, n), "synthetic")
    probe = task.RopeProblem([_with_hit(ref0)], segments=SEG, dt=DT)
    res = probe.simulate(values[None], probe.train, trajectory_every=1)
    return RopeReference(t, res.trajectory[:, 0].astype(np.float64), hand, LENGTH, MASS, RADIUS, EI,
                         np.linspace(0, 1, n), "synthetic")


def _with_hit(ref):
    """A placeholder reference whose last frame touches itself, only to build a probe problem."""
    m = ref.markers.copy()
    m[-1] = m[-1, ::-1] * 0 + np.linspace([0, 0, 0], [0.1, 0, 0], m.shape[1]) + ref.hand[-1]
    m[-1, -1] = m[-1, 0]
    return RopeReference(ref.time, m, ref.hand, ref.length, ref.mass, ref.radius, ref.bend_stiffness,
                         ref.marker_arclength, "probe")


@pytest.fixture(scope="module")
def problem_and_truth():
    seed_problem = task.RopeProblem([_with_hit(synthetic_placeholder())], segments=SEG, dt=DT)
    space = seed_problem.space
    truth = space.measured.copy()
    truth[space.index("lead_fraction")] *= 2.0
    truth[space.index("bend_stiffness")] *= 2.5
    refs = [synthetic_reference(p, truth) for p in ("flick", "flick_fast")]
    for r in refs:
        assert first_self_collision(r) is not None
    return task.RopeProblem(refs, segments=SEG, dt=DT, names=["flick", "flick_fast"]), truth


def synthetic_placeholder():
    t = np.arange(241) * DT
    hand = builtin_hand_paths()["flick"].positions(t)
    pos0 = hand[0] - np.outer(np.linspace(0, LENGTH, SEG + 1), [0, 0, 1])
    return RopeReference(t, np.repeat(pos0[None], len(t), 0), hand, LENGTH, MASS, RADIUS, EI,
                         np.linspace(0, 1, SEG + 1), "placeholder")


def test_truth_has_zero_error_and_measured_does_not(problem_and_truth):
    prob, truth = problem_and_truth
    err = prob.errors(np.stack([truth, prob.space.measured]), prob.train)
    # 2e-3, not 0: the reference detector counts surfaces within 0.5 mm as touching (events.CONTACT_LEVEL), the
    # chain's kernel at 0 mm, so the two critical moments differ by 0.5 mm / closing speed (~0.2 ms)
    assert np.all(err[0] < 2e-3)
    assert np.all(err[1] > 0.05)


def test_cmaes_recovers_hidden_parameters(problem_and_truth):
    prob, truth = problem_and_truth
    free = {"lead_fraction", "bend_stiffness"}
    space = prob.space.with_changes(**{n: {"frozen": True} for n in prob.space.names if n not in free})
    prob.space = space
    es = cma.CMAEvolutionStrategy(space.to_unit(space.measured), 0.2,
                                  {"seed": 3, "popsize": 10, "bounds": [0, 1], "verbose": -9, "maxiter": 60})
    while not es.stop():
        x = np.array(es.ask())
        es.tell(list(x), list(prob.errors(space.from_unit(x), prob.train).mean(1)))
    best = space.from_unit(es.result.xbest)
    for name in free:
        i = space.index(name)
        assert best[i] == pytest.approx(truth[i], rel=0.05), name
    assert es.result.fbest < 0.01


def test_no_hit_is_finite_penalty_and_report_fields(problem_and_truth):
    prob, truth = problem_and_truth
    short = [task.Condition(c.name, task.RopeCase(**{**c.data.__dict__, "steps": 20})) for c in prob.train]
    err = prob.errors(truth[None], short)
    assert np.all(np.isfinite(err)) and np.all(err >= task.NO_HIT)
    rep = prob.report(truth, prob.space.measured)
    row = rep["critical_points"]["flick"]
    assert row["fitted"]["hit_time"] == pytest.approx(row["reference"]["time"], abs=1e-3)
    assert row["measured"]["status"] in ("hit", "no_hit")


def test_bad_resolution_is_input_error():
    with pytest.raises(InputError):
        task.RopeProblem([synthetic_placeholder()], segments=1)


def test_no_hit_score_equals_the_error_of_hits_and_drops_the_penalty(problem_and_truth):
    prob, truth = problem_and_truth
    vals = np.stack([truth, prob.space.measured])
    assert np.array_equal(prob.no_hit_bound(vals, prob.train), prob.errors(vals, prob.train))
    short = [task.Condition(c.name, task.RopeCase(**{**c.data.__dict__, "steps": 20})) for c in prob.train]
    pen, score = prob.errors(truth[None], short), prob.no_hit_bound(truth[None], short)
    assert np.all(pen >= task.NO_HIT)
    for j, c in enumerate(short):
        t_ref = c.data.event.time - c.data.ref.time[0]
        late = task.WEIGHTS["time"] * abs(20 * prob.dt - t_ref) / t_ref
        # time term of a hit at the horizon's end plus a positive state error, no penalty constant
        assert late < score[0, j] < late + 1.0 < task.NO_HIT


def test_flow_problems_one_per_segment_count():
    import argparse

    probs = task.flow_problems(argparse.Namespace(resolutions=[16.0, 6.0], dt=0.005, iterations=4), "cpu")
    assert [p.segments for p in probs] == [6, 16] and [p.n for p in probs] == [7, 17]
    # per-joint stiffness EI / link grows with the segment count
    assert probs[0].held_out and probs[0].space["bend_stiffness"].measured * 16 == pytest.approx(
        probs[1].space["bend_stiffness"].measured * 6)
    with pytest.raises(InputError):
        task.flow_problems(argparse.Namespace(resolutions=[6.5], dt=0.005, iterations=4), "cpu")


class _Recorder:
    def __init__(self):
        self.calls, self.views, self.around = [], [], []

    def __getattr__(self, name):
        return lambda path, *a, **k: self.calls.append((name, path))

    def add_view(self, name, contents, kind="timeseries", around=None):
        self.views.append((name, contents, kind))
        self.around.append(around)


def test_record_declares_one_3d_view_per_path_with_all_three_ropes(problem_and_truth):
    prob, truth = problem_and_truth
    rec = _Recorder()
    prob.record(rec, truth, prob.space.measured)
    spatial = [v for v in rec.views if v[2] == "spatial3d"]
    assert [v[0] for v in spatial] == ["train: flick", "train: flick_fast"]
    for name, contents, _ in spatial:
        cond = name.split(": ")[1]
        assert contents == [f"/{who}/train/{cond}/**" for who in ("reference", "measured", "fitted")]
        for who in ("reference", "measured", "fitted"):
            assert ("log_lines3d", f"{who}/train/{cond}/rope") in rec.calls
        assert ("log_points3d", f"fitted/train/{cond}/contact") in rec.calls  # the truth hits
    # the camera frames the reference rope and hand over the whole throw
    assert all(a is not None and np.asarray(a).shape[1] == 3 for a in rec.around if a is not None)
    assert sum(a is not None for a in rec.around) == len(spatial)


def test_side_eye_frames_the_points():
    from wrenorm.viz.record import _side_eye

    pts = np.array([[0.0, 0.0, 0.0], [1.0, 0.2, 2.0], [np.nan, 0.0, 0.0]])
    eye, target = _side_eye(pts)
    assert np.allclose(target, [0.5, 0.1, 1.0])
    assert eye[1] < target[1] - 2.0 and abs(eye[0] - target[0]) < 1e-12  # from -y, outside the box


def test_residual_blocks_are_the_weighted_loss_terms(problem_and_truth):
    prob, truth = problem_and_truth
    vals = np.stack([truth, prob.space.measured, 0.5 * (truth + prob.space.measured)])
    terms = prob.error_terms(vals, prob.train)
    r = prob.residuals(vals, prob.train).reshape(len(vals), len(prob.train), -1)
    K3 = task.SAMPLES * 3
    w = prob.weights
    for b in range(len(vals)):
        for c in range(len(prob.train)):
            if terms["status"][b, c] != 1:
                assert np.all(np.isnan(r[b, c]))
                continue
            assert np.linalg.norm(r[b, c, :K3]) == pytest.approx(w["shape"] * terms["shape"][b, c], rel=1e-9)
            vel = np.linalg.norm(r[b, c, K3:2 * K3])
            assert vel == pytest.approx(w["velocity"] * terms["velocity"][b, c], rel=1e-9)
            assert abs(r[b, c, 2 * K3]) == pytest.approx(w["time"] * terms["time"][b, c], rel=1e-9, abs=1e-15)
    assert (terms["status"] == 1).sum() >= 4


def test_rope_fit_reports_gauss_newton_uncertainty(problem_and_truth):
    from wrenorm.uncertainty import uncertainty

    prob, truth = problem_and_truth
    off = truth.copy()
    off[prob.space.index("bend_stiffness")] *= 1.1  # a small misfit, so sigma^2 > 0
    u = uncertainty(prob, off)
    assert u["method"].startswith("gauss-newton")
    free = [p.name for p in prob.space.free]
    assert set(u["std"]) == set(free) and all(np.isfinite(v) and v > 0 for v in u["std"].values())


def test_validation_scores_a_chain_that_never_hits_by_its_state_not_a_penalty():
    """Held-out errors measure states: a chain that never hits itself is scored by its state at the reference's
    critical time (plus the least time error a later hit could have), never by the penalty constant, and
    result.json says per condition whether each chain hit."""
    from wrenorm.tasks.rope.observable import NO_HIT
    from wrenorm.tasks.rope.reference.generate import builtin_references

    held = builtin_references("held_out")
    prob = task.RopeProblem(held, held, segments=SEG, dt=DT, names=["a", "b"], held_names=["a", "b"])
    vals = np.stack([prob.space.measured, prob.space.measured])
    vals[1, prob.space.index("radius")] *= 3.0  # a fat chain hits itself sooner
    errs, details = prob.validation_errors(vals, prob.held_out)
    pen = prob.errors(vals, prob.held_out)
    status = prob.error_terms(vals, prob.held_out)["status"]
    assert (status == 0).any(), "the measured chain is expected to miss on a held-out path"
    for i in range(2):
        for j, d in enumerate(details):
            assert d[f"{['measured', 'fitted'][i]}_hit"] == bool(status[i, j] == 1)
            if status[i, j] == 1:
                assert errs[i, j] == pytest.approx(pen[i, j])
            else:
                assert pen[i, j] >= NO_HIT and errs[i, j] < NO_HIT


def test_moving_the_origin_sideways_does_not_change_the_loss(tmp_path):
    """The same throw recorded 90 m and -60 m from the origin (the chain's state is float32: 8 um resolution there)
    scores as the original at the measured parameters: the loader starts x and y at the held end."""
    from wrenorm.tasks.rope.reference.generate import (
        builtin_reference_path,
        load_reference,
        reference_arrays,
        save_reference,
    )

    ref = load_reference(builtin_reference_path("flick_fast"))
    far = reference_arrays(ref)
    far.update(markers=far["markers"] + [90.0, -60.0, 0.0], hand=far["hand"] + [90.0, -60.0, 0.0])
    np.savez(tmp_path / "far.npz", **far)
    moved = load_reference(tmp_path / "far.npz")
    here, there = (task.RopeProblem([r], segments=SEG, dt=DT) for r in (ref, moved))
    measured = here.space.measured[None]
    assert there.errors(measured, there.train)[0, 0] == pytest.approx(here.errors(measured, here.train)[0, 0],
                                                                      abs=1e-6)
    save_reference(tmp_path / "again.npz", moved)  # what the loader moved loads again unchanged
    np.testing.assert_array_equal(load_reference(tmp_path / "again.npz").hand[0], moved.hand[0])


def test_same_recording_as_fit_and_validation_reference_is_refused(tmp_path, capsys):
    """One recording under two names, as --reference and --validate (or twice among --reference), would validate
    the fit on its own data ("absorbed"): refused in one line naming both files."""
    import shutil
    from pathlib import Path

    from wrenorm.cli import main as cli

    data = Path(__file__).parent / "data"
    fast, wide = data / "mujoco_default_flick_fast.npz", data / "mujoco_default_flick_wide.npz"
    copy = tmp_path / "copy_of_fast.npz"
    shutil.copy(fast, copy)
    from wrenorm.tasks.rope.reference.generate import load_reference, reference_arrays, same_recording

    moved = reference_arrays(load_reference(fast))  # moved 5 m in x, y: the loader's origin move gives it back
    shift = np.array([5.0, -3.0, 0.0])
    moved.update(markers=moved["markers"] + shift, hand=moved["hand"] + shift)
    np.savez(tmp_path / "moved_fast.npz", **moved)
    assert same_recording(load_reference(fast), load_reference(tmp_path / "moved_fast.npz"))
    assert not same_recording(load_reference(fast), load_reference(wide))
    # turned 0.7 rad about the vertical through the hand (other room axes): validated on, it scored the training error
    # as the held-out one, "absorbed" (a probe of stop 46)
    turned = reference_arrays(load_reference(fast))
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    turned.update(markers=turned["markers"] @ R.T, hand=turned["hand"] @ R.T)
    np.savez(tmp_path / "turned_fast.npz", **turned)
    assert same_recording(load_reference(fast), load_reference(tmp_path / "turned_fast.npz"))
    assert not same_recording(load_reference(wide), load_reference(tmp_path / "turned_fast.npz"))
    # the same throw cut to every third marker is still that recording; the same hand path on another simulator's
    # rope is not (the hand agrees, the rope's markers at the common arc lengths do not)
    cut = reference_arrays(load_reference(fast))
    cut.update(markers=cut["markers"][:, ::3], marker_arclength=cut["marker_arclength"][::3])
    np.savez(tmp_path / "cut_fast.npz", **cut)
    assert same_recording(load_reference(fast), load_reference(tmp_path / "cut_fast.npz"))
    newton_fast = load_reference(data / "newton_default_flick_fast.npz")
    assert not same_recording(load_reference(fast), newton_fast)
    # the same throw with its first 30 and last 20 frames cut (its own origin, the hand at its new first frame) is
    # still that recording (stop 47); cut from another throw it is not
    for src, expect in ((fast, True), (wide, False)):
        trimmed = reference_arrays(load_reference(src))
        trimmed.update(time=trimmed["time"][30:-20], markers=trimmed["markers"][30:-20], hand=trimmed["hand"][30:-20])
        np.savez(tmp_path / "trimmed.npz", **trimmed)
        assert same_recording(load_reference(fast), load_reference(tmp_path / "trimmed.npz")) is expect
        assert same_recording(load_reference(tmp_path / "trimmed.npz"), load_reference(fast)) is expect
    common = ["--generations", "2", "--popsize", "4", "--no-record", "--quiet"]
    cases = [(["--reference", str(fast), str(wide), "--validate", str(copy)], "as --reference and as --validate"),
             (["--reference", str(fast), str(copy)], "twice among --reference"),
             (["--reference", str(tmp_path / "moved_fast.npz"), str(wide), "--validate", str(copy)],
              "as --reference and as --validate")]
    for roles, what in cases:
        assert cli(["fit", "rope", *roles, *common, "--out", str(tmp_path / "run")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        first = roles[1]
        assert len(err) == 1 and str(copy) in err[0] and first in err[0] and what in err[0], err
        assert not (tmp_path / "run" / "result.json").exists()


def test_a_chain_that_never_hits_itself_is_said_and_its_fit_reports_the_measured_values(tmp_path, capsys):
    """At 3 links the chain never reaches a self-collision on the fit throws: the loss is the no-hit penalty
    everywhere, so the search's best is whichever candidate it met first. The fit reports the measured values, says
    the search found nothing better and that the chain misses every fit throw, and calls no parameter determined;
    a flow says the same per point (at 4 links the chain misses 2 of 3 throws, which is said too)."""
    import json

    from wrenorm.cli import main

    out = tmp_path / "fit3"
    assert main(["fit", "rope", "--segments", "3", "--generations", "5", "--out", str(out), "--no-record",
                 "--quiet"]) == 0
    res = json.loads((out / "result.json").read_text())
    free = [n for n, p in res["parameters"].items() if not p["frozen"]]
    assert all(p["fitted"] == p["measured"] for p in res["parameters"].values())
    assert res["search"]["stalled"] and "no values better than the measured" in res["warnings"][0]
    assert any("does not hit itself on 3 of 3" in w for w in res["warnings"])
    assert sorted(res["uncertainty"]["undetermined"]) == sorted(free)
    assert "does not hit itself" in capsys.readouterr().out
    flow = tmp_path / "flow"
    assert main(["flow", "rope", "--resolutions", "3", "4", "--restarts", "2", "--generations", "3", "--out",
                 str(flow), "--no-record", "--quiet"]) == 0
    p3, p4 = json.loads((flow / "flow.json").read_text())["points"]
    assert "no values better" in p3["warning"] and sorted(p3["undetermined"]) == sorted(free)
    assert all(q["fitted"] == q["measured"] for q in p3["parameters"].values())
    assert "does not hit itself on 2 of 3" in p4["warning"]
    # a chain that does reach the event says none of this
    from wrenorm.tasks.rope.reference.generate import builtin_references

    ten = task.RopeProblem(builtin_references("fit"), segments=10)
    assert ten.fit_warnings(ten.space.measured) == []


def test_a_rest_before_the_throw_is_said_since_it_scales_the_time_error(tmp_path):
    """The time error is relative to the contact's time from the recording's start: 2 s of rest before the same throw
    cut its weight by three in silence (held-out 0.44 -> 0.36 measured). Said per file; the built-in throws rest
    12-35 ms and say nothing."""
    from wrenorm.tasks.rope.reference.generate import builtin_reference_path, load_reference, save_reference

    ref = load_reference(builtin_reference_path("flick_wide", "default"))
    n = int(round(2.0 / ref.dt))
    rested = RopeReference(ref.time[0] + ref.dt * np.arange(len(ref.time) + n),
                           np.concatenate([np.repeat(ref.markers[:1], n, 0), ref.markers]),
                           np.concatenate([np.repeat(ref.hand[:1], n, 0), ref.hand]), ref.length, ref.mass,
                           ref.radius, ref.bend_stiffness, ref.marker_arclength, "rested")
    f = tmp_path / "rested.npz"
    save_reference(f, rested)
    train = [load_reference(builtin_reference_path("flick", "default"))]
    quiet = task.RopeProblem(train, [ref], segments=10)
    assert not any("rests" in w for w in quiet.warnings)
    said = task.RopeProblem(train, [load_reference(f)], segments=10)
    w = [x for x in said.warnings if "rests" in x]
    assert len(w) == 1 and "rested.npz" in w[0] and "2.0" in w[0]


def test_a_coarse_recording_drives_the_chain_as_the_fine_one_does():
    """The chain's hand comes from the recording's frames. Cut to 62.5 Hz (every fourth frame), linear interpolation
    gives the held end a velocity that jumps at every frame; a cubic spline through the coarse frames scores nearer
    the 250 Hz recording against the same target (on the 50 cached throws of the nine ropes at 62.5 and 50 Hz: nearer in
    44, median 0.0015 against 0.009). Here the three shipped throws the chain hits on: each within 0.02, and nearer
    than linear in sum. The 250 Hz recording itself is read as before (linear: finer than the chain's step)."""
    from dataclasses import replace

    from wrenorm.problem import Condition
    from wrenorm.tasks.rope.reference.generate import builtin_reference_path, load_reference

    off = {"spline": 0.0, "linear": 0.0}
    for path in ("flick", "flick_wide", "flick_fast"):
        fine = load_reference(builtin_reference_path(path))
        coarse = replace(fine, time=fine.time[::4], markers=fine.markers[::4], hand=fine.hand[::4])
        here = task.RopeProblem([fine])
        measured = here.space.measured[None]
        tk = fine.time[0] + here.dt * np.arange(here.train[0].data.steps + 1)
        np.testing.assert_array_equal(task.hand_at(fine, tk)[:, 0], np.interp(tk, fine.time, fine.hand[:, 0]))
        there = task.RopeProblem([coarse])
        spline = Condition("spline", replace(there.train[0].data, target=here.train[0].data.target))
        linear = np.stack([np.interp(tk, coarse.time, coarse.hand[:, a]) for a in range(3)], 1)
        jerky = Condition("linear", replace(spline.data, hand=linear[:len(spline.data.hand)]))
        fine_error = here.errors(measured, here.train)[0, 0]
        assert there.errors(measured, [spline])[0, 0] == pytest.approx(fine_error, abs=0.02)
        off["spline"] += abs(there.errors(measured, [spline])[0, 0] - fine_error)
        off["linear"] += abs(there.errors(measured, [jerky])[0, 0] - fine_error)
    assert off["spline"] < off["linear"]


def _shipped(path):
    from wrenorm.tasks.rope.reference.generate import builtin_reference_path, load_reference

    return load_reference(builtin_reference_path(path))


def test_a_held_out_throw_the_fitted_chain_misses_is_never_within_tolerance():
    """A chain that never reaches a held-out throw's contact is scored by a lower bound that shrinks with the
    recording's length after the contact: cut 8 ms after it, the bound fell under the tolerance and the verdict said
    "absorbed" (a probe of stop 46). Such a condition is outside tolerance whatever its bound, and said."""
    from dataclasses import replace

    from wrenorm.fit import _validation
    from wrenorm.tasks.rope.observable import reference_critical

    high = _shipped("flick_high")
    k = int(np.searchsorted(high.time, reference_critical(high).event.time + 0.008)) + 1
    cut = replace(high, time=high.time[:k], markers=high.markers[:k], hand=high.hand[:k])
    p = task.RopeProblem([_shipped("flick")], [cut], names=["flick"], held_names=["cut_high"])
    p.tolerance = 0.35  # above this chain's bound here (0.30), as the probe's was above its 0.12
    measured = p.space.measured
    v = _validation(p, measured, measured)  # the measured chain misses flick_high's contact
    c = v["conditions"]["cut_high"]
    assert c["fitted_misses"] and c["fitted_error"] < p.tolerance  # the bound alone would have passed
    assert c["within_tolerance"] is False and v["verdict"] == "expand" and v["fitted_misses"] == ["cut_high"]
    assert "lower bound" in v["note"] and v["worst_is_miss"]
    from wrenorm.viz.report import _held_out

    assert "outside tolerance" in _held_out({"validation": v}) and "within tolerance" not in _held_out(
        {"validation": v})


def test_references_of_another_rope_are_refused_naming_the_file_and_the_field(tmp_path):
    """Only length and mass were compared; the measured values come from the first reference, so a stiffer or
    thicker rope's file changed the fit with the order of the files (measured EI 0.09 instead of 0.027)."""
    from dataclasses import replace

    from wrenorm.errors import InputError

    first, other = _shipped("flick"), _shipped("flick_fast")
    for field, value in (("radius", 1.2 * other.radius), ("bend_stiffness", 3.0 * other.bend_stiffness)):
        with pytest.raises(InputError) as e:
            task.RopeProblem([first], [replace(other, **{field: value}, file="thicker.npz")])
        assert e.value.source == "thicker.npz" and e.value.field == field and "--validate" in e.value.problem


@pytest.mark.parametrize("start", [25, 38, 50])
def test_a_throw_recorded_from_mid_flight_with_noisy_markers_still_hits_itself_in_the_chain(start):
    """A clip that starts 0.1-0.2 s into the shipped throw, with 0.5 mm of marker noise at 250 Hz: the chain starts
    from the markers' velocity at the first frame. Read as one frame difference (0.3 m/s RMS of noise) the chain at
    the measured values missed its contact in 10 of 12 such clips (error 5.0-5.3); fitted over a window the data
    choose (events.start_velocity) it hits, with an error like the clean clip's (0.40-0.45 here). The seven other
    ropes' throws, cut alike: 63 of 63 missed before, 2 after (review of stop 54)."""
    from dataclasses import replace

    whole = _shipped("flick")
    clean = replace(whole, time=whole.time[start:], markers=whole.markers[start:], hand=whole.hand[start:])
    noisy = replace(clean, markers=clean.markers + np.random.default_rng(1).normal(0.0, 5e-4, clean.markers.shape))
    a, b = task.RopeProblem([clean]), task.RopeProblem([noisy])
    measured = a.space.measured[None]
    assert np.any(b.train[0].data.vel0)
    assert a.errors(measured, a.train)[0, 0] < 0.6
    assert b.errors(measured, b.train)[0, 0] < 0.6


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_marker_noise_at_the_start_does_not_set_the_chain_moving(seed):
    """0.5 mm of marker noise on a rope at rest read 0.23-0.48 m/s as the chain's start velocity: its error at the
    measured values ran 0.33-5.05 over noise draws against 0.41 clean. A start velocity within the noise is rest."""
    from dataclasses import replace

    clean = _shipped("flick")
    event = task.reference_critical(clean).event
    noisy = replace(clean, markers=clean.markers + np.random.default_rng(seed).normal(0.0, 5e-4, clean.markers.shape),
                    critical_time=event.time)
    a, b = task.RopeProblem([clean]), task.RopeProblem([noisy])
    assert not np.any(b.train[0].data.vel0)
    measured = a.space.measured[None]
    assert b.errors(measured, b.train)[0, 0] == pytest.approx(a.errors(measured, a.train)[0, 0], abs=0.03)


@pytest.mark.parametrize("segments", [3, 10, 16])
def test_measured_masses_lump_each_link_half_on_either_end_the_held_ones_on_the_hand(segments):
    """Lumped masses of a rope of mass M in S links: M / S on each interior node, half that on the free end, and the
    held node's half link on the hand. All of M had been spread over the free nodes, interior ones (2S - 1) / (2S - 2)
    too heavy: 5.6 % at 10 links, 25 % at 3 (review of stop 55)."""
    from wrenorm.tasks.rope.reference.generate import builtin_reference_path, load_reference

    ref = load_reference(builtin_reference_path("flick", "default"))
    p = task.RopeProblem([ref], segments=segments)
    masses = p.chain_params(p.space.measured).node_masses(segments + 1)[0]
    assert np.isinf(masses[0])  # the held node follows the hand
    np.testing.assert_allclose(masses[1:-1], ref.mass / segments, rtol=1e-6)  # float32
    assert masses[-1] == pytest.approx(ref.mass / (2 * segments), rel=1e-6)
    assert masses[1:].sum() == pytest.approx(ref.mass * (1 - 0.5 / segments), rel=1e-6)


def test_a_step_whose_float32_increments_round_away_is_refused(capsys):
    """Below 1 ms a step's change of a coordinate 1.6 m from the origin rounds away in float32 (a pendulum's period
    84 % off at 0.1 ms; review of stop 55): refused with the range, exit 2."""
    from wrenorm.cli import main

    for argv in (["fit", "rope", "--dt", "0.0005"], ["flow", "rope", "--axis", "dt", "--resolutions", "0.0005,0.005"]):
        assert main(argv + ["--quiet", "--no-record"]) == 2
        err = capsys.readouterr().err
        assert "0.001" in err and "0.0005" in err and len(err.strip().splitlines()) == 1


def test_the_default_rope_fit_checks_its_stds_against_seeded_restarts(tmp_path):
    """With one search and no restarts the rope's stds (a finite-difference Jacobian of an event observable, 17x apart
    across seeds) had nothing to be checked against: seeds 2 and 3 put bend_stiffness 10 stated stds apart, each
    "determined by the data" (review of stop 55). The default now runs 4 restarts, and nothing the restarts leave
    farther apart than 4 stated stds is called determined."""
    import json

    from wrenorm.cli import main

    assert main(["fit", "rope", "--out", str(tmp_path / "fit"), "--quiet", "--no-record"]) == 0
    r = json.loads((tmp_path / "fit" / "result.json").read_text())
    optima = r["restarts"]["optima"]
    assert len(optima) == 4
    for name in r["uncertainty"]["determined_by_data"]:
        values = [o["values"][name] for o in optima] + [r["parameters"][name]["fitted"]]
        assert max(values) - min(values) <= 4 * r["parameters"][name]["std"], name
