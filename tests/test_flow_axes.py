"""Resolution flow over further axes: rope time step, swimmer tail-body count (merged links)."""
import json

import numpy as np
import pytest
from swimmer_checks import com_drift

from wrenorm.cli import main
from wrenorm.flow import _digest
from wrenorm.tasks.swimmer import body as sb
from wrenorm.tasks.swimmer import data as sd
from wrenorm.tasks.swimmer import problem as swimmer
from wrenorm.viz.flow_plot import _axis


@pytest.fixture(scope="module")
def rates():
    return sd.load_builtin()


def _straight(links):
    """Total length, mass, first mass moment and yaw inertia about the first joint, lateral
    projected area and volume (up to 4/3 pi) of a straight tail."""
    start = np.concatenate([[0.0], np.cumsum([lk[0] for lk in links])[:-1]])
    x = start + np.array([lk[1] for lk in links])
    r = np.array([lk[2] for lk in links])
    m = np.array([lk[3] for lk in links])
    j = np.array([lk[4] for lk in links])
    return np.array([sum(lk[0] for lk in links), m.sum(), (m * x).sum(), (j + m * x * x).sum(),
                     (r[:, 0] * r[:, 2]).sum(), r.prod(1).sum()])


@pytest.mark.parametrize("bodies", [2, 3, 4, 5])
def test_merged_tail_keeps_length_mass_inertia_area_volume(bodies):
    merged = sb.merge_links(bodies)
    assert len(merged) == bodies
    assert merged[-1] == sb.LINKS[-1]  # the fin stays its own body
    np.testing.assert_allclose(_straight(merged), _straight(sb.LINKS), rtol=1e-12)


def test_all_bodies_is_the_default_fish_bit_for_bit(rates):
    assert sb.merge_links(len(sb.LINKS)) == sb.LINKS
    vals = np.array([swimmer.parameter_space().measured, [0.2, 5.0, 1.0, 2.0, 0.1, swimmer.VISCOSITY]])
    default = swimmer.SwimmerProblem(rates, [1.0, 1.75], dt=0.016)
    full = swimmer.SwimmerProblem(rates, [1.0, 1.75], dt=0.016, bodies=6)
    conds = default.train + default.held_out
    assert np.array_equal(default.speeds(vals, conds), full.speeds(vals, conds))
    coarse = swimmer.SwimmerProblem(rates, [1.0, 1.75], dt=0.016, bodies=2)
    sp = coarse.speeds(vals, conds)
    assert np.all(np.isfinite(sp)) and np.abs(sp - default.speeds(vals, conds)).max() > 1e-3


def test_merged_joints_move_with_the_robots(rates):
    """The joints a merged tail keeps follow the full gait's joints at its run ends, off by the
    foreshortening of one straight link over a bent run: less the shorter the runs."""
    for rate in rates:
        t = np.linspace(0.0, 1.0 / rate.tail_freq, 40, endpoint=False)
        full = sb.tail_points(sb.gait(rate), t)
        amp = np.abs(full[:, -1, 1]).max()
        assert amp > 0.05
        err = {}
        for bodies in (2, 3, 5):
            pts = sb.tail_points(sb.gait(rate, bodies=bodies), t)
            assert pts.shape == (40, bodies + 1, 2)
            ends = [r[-1] + 1 for r in sb.merge_runs(bodies)]
            err[bodies] = np.abs(pts[:, 1:] - full[:, ends]).max() / amp
        assert err[5] < err[3] < err[2] < 0.1 and err[5] < 0.02


def test_merged_fish_without_water_keeps_its_centre_of_mass(rates):
    """Momentum balance of the merged parts: with no fluid the tail only shakes the head."""
    drift, excursion = com_drift(rates[1], 0.002, bodies=2, seconds=2.0)
    assert excursion > 0.003
    assert drift < 5e-4


@pytest.mark.parametrize("system,axis,points,fixed,key,order,bad", [
    ("swimmer", "bodies", ["2", "6", "--dt", "0.016", "--generations", "3"], ("dt", 0.016), "tail_bodies", [6, 2], "1"),
    ("rope", "dt", ["0.01", "0.005", "--segments", "6", "--generations", "2"], ("segments", 6), "dt", [0.005, 0.01],
     "0.2"),
])
def test_flow_over_a_second_resolution_axis(tmp_path, system, axis, points, fixed, key, order, bad):
    """Each system's flow varies the axis asked for, holds the other resolution fixed, orders the points
    finest first, and refuses a value outside the axis' range."""
    out = tmp_path / "flow"
    assert main(["flow", system, "--axis", axis, "--resolutions", *points, "--out", str(out), "--quiet", "--no-record",
                 "--restarts", "2"]) == 0
    flow = json.loads((out / "flow.json").read_text())
    assert [p["resolution"][key] for p in flow["points"]] == order
    assert all(p["resolution"][fixed[0]] == fixed[1] for p in flow["points"])
    got_key, x = _axis(flow)
    assert got_key == key and x.tolist() == [float(v) for v in order]
    assert (out / "flow.png").stat().st_size > 10_000
    assert main(["flow", system, "--axis", axis, "--resolutions", bad, "--out", str(tmp_path / "bad")]) == 2


@pytest.mark.parametrize("system,axis,option", [("rope", "segments", "--segments"), ("rope", "dt", "--dt"),
                                                ("swimmer", "dt", "--dt"), ("swimmer", "bodies", "--bodies")])
def test_flow_refuses_a_single_value_on_the_axis_it_varies(tmp_path, capsys, system, axis, option):
    """`flow rope --segments 20` held nothing at 20 and ran the default resolutions: the option on the varied axis
    is refused, named, before anything runs (typed at its default too)."""
    value = {"--segments": "10", "--dt": "0.005", "--bodies": "6"}[option]
    if system == "swimmer" and option == "--dt":
        value = "0.008"
    rc = main(["flow", system, "--axis", axis, option, value, "--out", str(tmp_path / "f"), "--quiet", "--no-record"])
    assert rc == 2
    err = capsys.readouterr().err
    assert option in err and "--resolutions" in err
    assert not (tmp_path / "f" / "flow.json").exists()


def test_plot_axis_is_the_varied_key():
    pts = lambda *res: {"points": [{"resolution": r} for r in res]}  # noqa: E731
    assert _axis(pts({"segments": 10, "dt": 0.01, "on": True}, {"segments": 10, "dt": 0.005, "on": False}))[0] == "dt"
    assert _axis(pts({"segments": 6, "masses": 7}, {"segments": 10, "masses": 11}))[0] == "segments"
    assert _axis(pts({"gait": "chain", "dt": 0.01}))[0] == "dt"


def test_flow_resume_continues_after_the_last_finished_resolution(tmp_path, capsys):
    """A flow killed after its first resolution (its points file cut back to that point) resumes from
    there and ends with the same points as the uninterrupted flow."""
    import shutil

    args = ["flow", "rope", "--axis", "dt", "--resolutions", "0.01", "0.005", "0.0025", "--segments", "6",
            "--quiet", "--no-record", "--restarts", "2", "--generations", "3"]
    full = tmp_path / "full"
    assert main([*args, "--out", str(full)]) == 0
    done = json.loads((full / "flow.json").read_text())
    # the data's flags, as a fit says them (the built-in flick_slow's grazing touch is flagged)
    assert any("flick_slow" in w and "flagged" in w for w in done["warnings"]), done["warnings"]
    cut = tmp_path / "cut"
    shutil.copytree(full, cut)
    (cut / "flow.json").unlink()
    state = json.loads((cut / "flow_points.json").read_text())
    first = state["points"][0]
    state["points"], state["start"] = [dict(first, read_back=True)], [p["fitted"] for p in first["parameters"].values()]
    # a hand edit (the mark) is refused: a resume would report the edited point as fitted
    (cut / "flow_points.json").write_text(json.dumps(state))
    assert main([*args, "--out", str(cut), "--resume"]) == 2
    assert not (cut / "flow.json").exists()
    state["digest"] = _digest(state["points"], state["start"])  # the file as the flow writes it after one point
    (cut / "flow_points.json").write_text(json.dumps(state))
    assert main([*args, "--out", str(cut), "--resume"]) == 0
    again = json.loads((cut / "flow.json").read_text())["points"]
    assert again[0].pop("read_back") is True  # the finished point was read back, not fitted again
    assert again == done["points"]
    # points of other resolutions than the flow's (the file from another flow with the same settings cannot be,
    # but an edit can) are refused too
    state["points"] = [dict(first, resolution=dict(first["resolution"], dt=0.02))]
    state["digest"] = _digest(state["points"], state["start"])
    (cut / "flow_points.json").write_text(json.dumps(state))
    (cut / "flow.json").unlink()
    capsys.readouterr()
    assert main([*args, "--out", str(cut), "--resume"]) == 2
    assert "flow_points.json" in capsys.readouterr().err
    # other options than the interrupted flow's are refused, as is a folder with nothing to resume
    assert main([*args[:-1], "4", "--out", str(cut), "--resume"]) == 2
    (tmp_path / "empty").mkdir()
    assert main([*args, "--out", str(tmp_path / "empty"), "--resume"]) == 2


def test_flow_resume_with_other_resolutions_names_them(tmp_path, capsys):
    """A resume with another resolution list (or another system's folder) names that, not the free parameters that
    follow from it."""
    out = tmp_path / "f"
    tail = ["--quiet", "--no-record", "--restarts", "2", "--generations", "2", "--out", str(out)]
    assert main(["flow", "rope", "--resolutions", "6,8", *tail]) == 0  # commas, as every list takes (was refused)
    capsys.readouterr()
    assert main(["flow", "rope", "--resolutions", "6", "8", "10", *tail, "--resume"]) == 2
    err = capsys.readouterr().err
    assert ": resolutions: " in err, err
    assert main(["flow", "pd", "--out", str(out), "--resume", "--quiet", "--no-record"]) == 2
    err = capsys.readouterr().err
    assert ": task: " in err, err


def test_a_flow_interrupted_after_a_point_without_an_uncertainty_resumes(tmp_path, monkeypatch):
    """A stalled point (3 links: the chain never hits) stores its spreads as null (NaN in memory): the resume's
    digest must be of what was stored, or the flow's own file reads as edited."""
    import wrenorm.flow

    calls = []
    real = wrenorm.flow.uncertainty

    def stop_at_the_second(prob, values, **kw):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(prob, values, **kw)

    out = tmp_path / "f"
    args = ["flow", "rope", "--resolutions", "3,6", "--restarts", "2", "--generations", "2", "--quiet", "--no-record",
            "--out", str(out)]
    monkeypatch.setattr(wrenorm.flow, "uncertainty", stop_at_the_second)
    assert main(args) == 130
    assert len(json.loads((out / "flow_points.json").read_text())["points"]) == 1
    monkeypatch.setattr(wrenorm.flow, "uncertainty", real)
    assert main([*args, "--resume"]) == 0
    p3, p6 = json.loads((out / "flow.json").read_text())["points"]
    assert "no values better" in p3["warning"] and p6["resolution"]["segments"] == 6
