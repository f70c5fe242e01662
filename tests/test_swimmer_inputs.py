"""Robotic-fish inputs in foreign shapes: head-frame (rotated) clips, their units, the frame rate, duplicated
frames, tracking dropouts, byte-order marks and doubled labels. Each is refused in one line naming the file, or
used and said so; never fitted as nonsense in silence."""
import argparse

import numpy as np
import pytest

from wrenorm.errors import InputError
from wrenorm.tasks.swimmer import data as sd
from wrenorm.tasks.swimmer import problem as swimmer


@pytest.fixture(scope="module")
def rates():
    return sd.load_builtin()


def _file_name(kind: str, label: float) -> str:
    return f"{kind}_f{label:.2f}".replace(".", "_") + ".csv"


def _write_pixels(folder, rate, scale=950.0, markers=None, name=None):
    """A markers_*.csv of the rate (or of `markers`, metres) in pixels at `scale` px/m."""
    m = rate.markers if markers is None else markers
    path = folder / (name or _file_name("markers", rate.label))
    np.savetxt(path, (m * scale).reshape(len(m), -1), delimiter=",")
    return path


def _write_rotated(folder, rate, scale=1.0):
    """A rotatedMarkers_*.csv as fishsim writes it: the head frame, the head's forward progress added back (the fish
    swims towards -x of its head frame), 9 rows per frame; `scale` 1000 is a millimetre export."""
    rot = sd.head_frame(rate.markers)
    rot[..., 0] -= rate.speed * np.arange(len(rot))[:, None] / sd.FPS
    path = folder / _file_name("rotatedMarkers", rate.label)
    np.savetxt(path, rot.reshape(-1, 2) * scale, delimiter=",")
    return path


def _mixed_folder(folder, rates, rotated=(1.0, 1.75)):
    """Pixel files for every rate but `rotated`, which come as head-frame files only."""
    for r in rates:
        (_write_rotated if r.label in rotated else _write_pixels)(folder, r)
    return folder


# --- 1. head-frame clips: yaw and sway are not measurable ---------------------------------------


def test_head_frame_clips_leave_yaw_and_sway_out_and_say_so(tmp_path, rates, capsys):
    got = sd.load_dir(_mixed_folder(tmp_path, rates))
    assert [r.frame for r in got] == ["world", "head", "world", "head", "world"]
    args = argparse.Namespace(data=tmp_path, train=[1.0, 1.75], dt=0.016, features=None, fps=60.0)
    prob = swimmer.build_problems(args, "cpu")[0]
    assert prob.features == ("speed", "surge2_amp", "surge2_phase")
    err = capsys.readouterr().err
    assert "rotatedMarkers_f1_00.csv" in err and "yaw_amp" in err and "left out of the fit" in err
    # every training feature's noise is a real beat-to-beat spread, not ~1e-17 (the objective was ~1e31)
    for c in prob.train:
        assert all(prob.sigma(c, f) > 1e-6 for f in prob.features)
    rep = prob.report(prob.space.measured, prob.space.measured)
    assert any("head frame" in w for w in rep["warnings"])
    assert rep["features"]["not_measurable"] == ["yaw_amp", "yaw_phase", "sway_amp", "sway_phase"]
    head, world = rep["speeds"]["1.00"], rep["speeds"]["0.50"]
    assert head["frame"] == "head" and head["features"]["yaw_amp"]["real"] is None
    yaw = head["features"]["yaw_amp"]
    assert not yaw["in_fit"] and yaw["fitted_normalised_residual"] is None
    assert world["features"]["yaw_amp"]["real"] > 0.05  # a world clip still measures its yaw, out of the fit


def test_a_yaw_or_sway_feature_asked_for_on_head_frame_clips_is_refused(tmp_path, rates):
    got = sd.load_dir(_mixed_folder(tmp_path, rates))
    for asked in ("yaw", "all", "speed,sway_phase"):
        with pytest.raises(InputError) as e:
            swimmer.SwimmerProblem(got, [1.0, 1.75], dt=0.016, features=asked)
        assert e.value.source == "rotatedMarkers_f1_00.csv" and e.value.field == "--features"
        assert "head frame" in e.value.problem
    assert swimmer.SwimmerProblem(got, [1.0, 1.75], dt=0.016, features="surge2").features[1:] == ("surge2_amp",
                                                                                                   "surge2_phase")


def test_a_feature_without_beat_to_beat_noise_is_an_error_not_a_division_by_zero(tmp_path, rates):
    """A head-frame export named like a pixel file: the frame cannot tell, the noise model can (its yaw is ~1e-17
    rad in every beat)."""
    flat = {}
    for r in rates:
        if r.label in (1.0, 1.75):
            flat[r.label] = sd.read_rotated_markers(_write_rotated(tmp_path, r))
    got = [sd.analyse(sd.Rate(label=r.label, markers=flat.get(r.label, r.markers), source=f"clip_{r.label:.2f}"))
           for r in rates]
    with pytest.raises(InputError) as e:
        swimmer.SwimmerProblem(got, [1.0, 1.75], dt=0.016, features="yaw")
    assert e.value.field == "yaw_amp" and "not measurable" in e.value.problem
    assert "clip_1.00" in e.value.source and "clip_1.75" in e.value.source
    # out of the fit, the same clips build (the feature is only reported)
    swimmer.SwimmerProblem(got, [1.0, 1.75], dt=0.016, features="surge2")


# --- 2. rotated files must be in metres ------------------------------------------------------------

@pytest.mark.parametrize("scale,shown", [(1000.0, "142"), (100.0, "14.2")])
def test_rotated_files_in_millimetres_or_centimetres_are_refused(tmp_path, rates, scale, shown):
    _write_rotated(tmp_path, rates[1], scale=scale)
    with pytest.raises(InputError) as e:
        sd.load_dir(tmp_path)
    assert "rotatedMarkers_f1_00.csv" in e.value.source and e.value.field == "units"
    assert shown in e.value.problem and "metres expected" in e.value.problem


# --- 3. frame rate -----------------------------------------------------------------------------------

def _upsampled(markers, factor=2):
    """Linear interpolation to `factor` x the frame rate (a 120 fps export of the same swim)."""
    n = len(markers)
    t = np.arange(0, n - 1 + 1e-9, 1.0 / factor)
    flat = markers.reshape(n, -1)
    return np.stack([np.interp(t, np.arange(n), flat[:, j]) for j in range(flat.shape[1])], 1).reshape(len(t), -1, 2)


def test_fps_carries_into_the_rates_and_a_wrong_one_is_flagged(tmp_path, rates):
    r = rates[1]
    _write_pixels(tmp_path, r, markers=_upsampled(r.markers))
    at60 = sd.load_dir(tmp_path)[0]
    at120 = sd.load_dir(tmp_path, fps=120.0)[0]
    assert at120.fps == 120.0
    assert abs(at120.speed - r.speed) < 0.002 and abs(at120.tail_freq - r.tail_freq) < 0.01
    assert abs(at60.tail_freq - r.tail_freq / 2) < 0.01  # read at 60 fps: half the speed and beat
    flagged = sd.tail_beat_check([at60])["flagged"]
    assert len(flagged) == 1 and "markers_f1_00.csv" in flagged[0] and "--fps" in flagged[0]
    assert sd.tail_beat_check([at120])["flagged"] == [] and sd.tail_beat_check(rates)["flagged"] == []
    # 50 fps read as 60: every beat 20 % fast, 0.90 x the label, inside the band of before (0.5-1.0)
    _write_pixels(tmp_path, r, markers=_upsampled(r.markers, 50.0 / 60.0))
    assert len(sd.tail_beat_check(sd.load_dir(tmp_path))["flagged"]) == 1
    # 55 and 66 fps read as 60 (every speed and beat 9 % off) passed the +-15 % band of before (review of stop 54)
    for fps in (55.0, 66.0):
        _write_pixels(tmp_path, r, markers=_upsampled(r.markers, fps / 60.0))
        assert len(sd.tail_beat_check(sd.load_dir(tmp_path))["flagged"]) == 1, fps
    for bad in (0.0, -60.0, float("nan")):
        with pytest.raises(InputError, match="fps"):
            sd.load_dir(tmp_path, fps=bad)
    # the built-in tracks carry their rate: another --fps would be ignored, so it is refused
    with pytest.raises(InputError, match="built-in"):
        swimmer._rates(argparse.Namespace(data=None, fps=120.0))


def test_a_flagged_tail_beat_reaches_the_problem_warnings_and_stderr(tmp_path, rates, capsys):
    for r in rates:
        _write_pixels(tmp_path, r, markers=_upsampled(r.markers) if r.label == 2.25 else None)
    args = argparse.Namespace(data=tmp_path, train=[1.0, 1.75], dt=0.016, features=None, fps=60.0)
    prob = swimmer.build_problems(args, "cpu")[0]
    assert len(prob.warnings) == 1 and "markers_f2_25.csv" in prob.warnings[0]
    assert prob.data_checks["flagged"] == prob.warnings
    assert abs(prob.data_checks["tail_beat_per_label"]["2.25"] - 0.37) < 0.03
    assert "markers_f2_25.csv" in capsys.readouterr().err


def test_a_flagged_training_clip_is_said_by_flow_and_select_and_kept_in_their_json(tmp_path, rates, capsys):
    """fit swimmer keeps the data's flags in result.json; flow and select said them on stderr only (flow) or not at
    all (select, whose study sees the training clips alone), so their JSON looked clean."""
    import json

    from wrenorm.cli import main

    data = tmp_path / "data"
    data.mkdir()
    for r in rates:
        _write_pixels(data, r, markers=_upsampled(r.markers) if r.label == 1.75 else None)
    assert main(["flow", "swimmer", "--data", str(data), "--resolutions", "0.016", "0.008", "--generations", "2",
                 "--restarts", "2", "--popsize", "4", "--no-record", "--quiet", "--out", str(tmp_path / "flow")]) == 0
    flow = json.loads((tmp_path / "flow" / "flow.json").read_text())
    assert len(flow["warnings"]) == 1 and "markers_f1_75.csv" in flow["warnings"][0]
    assert "markers_f1_75.csv" in (tmp_path / "flow" / "report.html").read_text()
    capsys.readouterr()
    assert main(["select", "swimmer", "--data", str(data), "--quick", "--generations", "2", "--quiet",
                 "--out", str(tmp_path / "select")]) == 0
    chosen = json.loads((tmp_path / "select" / "select.json").read_text())
    assert len(chosen["warnings"]) == 1 and "markers_f1_75.csv" in chosen["warnings"][0]
    assert "markers_f1_75.csv" in capsys.readouterr().err


def test_duplicated_frames_are_refused(tmp_path, rates):
    _write_pixels(tmp_path, rates[1], markers=np.repeat(rates[1].markers, 2, axis=0))
    with pytest.raises(InputError) as e:
        sd.load_dir(tmp_path)
    assert "markers_f1_00.csv" in e.value.source and "duplicated frames" in e.value.problem
    rot = tmp_path / "rot"
    rot.mkdir()
    path = _write_rotated(rot, rates[1])
    frames = np.loadtxt(path, delimiter=",").reshape(-1, 9, 2)
    np.savetxt(path, np.repeat(frames, 3, axis=0).reshape(-1, 2), delimiter=",")
    with pytest.raises(InputError, match="duplicated frames"):
        sd.load_dir(rot)


@pytest.mark.parametrize("how", ["every tenth written twice", "held for 11 frames"])
def test_a_few_repeated_or_held_frames_are_refused(tmp_path, rates, how):
    """Under the old 20 % share, every tenth frame written twice slowed every speed 9 % and 11 held frames moved the
    slender drag 4x, both in silence; two repeats in a row still pass (a pixel's rounding may repeat once)."""
    m = rates[1].markers
    if how.startswith("every"):
        bad = np.repeat(m, [2 if i % 10 == 0 else 1 for i in range(len(m))], axis=0)
    else:
        bad = m.copy()
        bad[201:212] = bad[200]
    _write_pixels(tmp_path, rates[1], markers=bad)
    with pytest.raises(InputError) as e:
        sd.load_dir(tmp_path)
    assert "markers_f1_00.csv" in e.value.source and "repeat" in e.value.problem
    if how.startswith("held"):
        assert e.value.field == "frames 202-212"
    fine = m.copy()
    fine[101:103] = fine[100]
    _write_pixels(tmp_path, rates[1], markers=fine)
    assert len(sd.load_dir(tmp_path)) == 1
    # a fish filmed still before it swims repeats exactly (half-pixel steps): not a held tracker (review of stop 45)
    _write_pixels(tmp_path, rates[1], markers=np.concatenate([np.repeat(m[:1], 40, axis=0), m]))
    assert len(sd.load_dir(tmp_path)) == 1


@pytest.mark.parametrize("stretch", [1.4, 0.7])
def test_a_clip_of_another_body_is_refused(tmp_path, rates, stretch):
    """A tail 1.4x as long (markers 2-8 stretched about marker 1) was fitted as this robot, every coefficient
    'determined' and the angular drag 8x: the tail base is rigid with the head, 0.286 m from its midpoint."""
    m = rates[1].markers.astype(np.float64).copy()
    m[:, 2:] = m[:, 1:2] + stretch * (m[:, 2:] - m[:, 1:2])
    _write_pixels(tmp_path, rates[1], markers=m)
    with pytest.raises(InputError) as e:
        sd.load_dir(tmp_path)
    assert e.value.field == "marker 2" and "another fish" in e.value.problem
    _write_pixels(tmp_path, rates[1])  # the robot's own clip loads
    assert len(sd.load_dir(tmp_path)) == 1


def test_columns_written_x_then_y_are_refused_naming_the_layout(tmp_path, rates):
    """x0..x8, y0..y8 instead of x0, y0, x1, y1, ...: the "markers" read as pairs do not lie one behind another along
    the body; the refusal names the layout the file must have (it used to say only 'fewer than 3 distinct tail
    markers', true but not the cause)."""
    for r in rates:
        px = r.markers * 950.0
        folder = tmp_path / f"{r.label:.2f}"
        folder.mkdir()
        path = folder / _file_name("markers", r.label)
        np.savetxt(path, np.concatenate([px[..., 0], px[..., 1]], axis=1), delimiter=",")
        with pytest.raises(InputError) as e:
            sd.load_dir(folder)
        assert e.value.source == path.name and e.value.field == "tail markers", e.value
        assert "x0, y0, x1, y1, ..., x8, y8" in e.value.problem


def test_tail_markers_out_of_order_are_refused(tmp_path, rates):
    """Two tail markers' columns swapped: the loader kept the markers that lie one behind another and dropped the
    others in silence (the fit then saw two tail markers fewer); now the marker ahead of its place is named."""
    px = rates[1].markers.copy()
    px[:, [4, 6]] = px[:, [6, 4]]
    _write_pixels(tmp_path, rates[1], markers=px)
    with pytest.raises(InputError) as e:
        sd.load_dir(tmp_path)
    assert "markers_f1_00.csv" in e.value.source and e.value.field == "tail marker 5", e.value
    assert "head to tail" in e.value.problem


# --- 4. tracking dropouts ----------------------------------------------------------------------------

@pytest.mark.parametrize("marker", [1, 8])
def test_a_marker_at_exactly_zero_is_a_dropout(tmp_path, rates, marker):
    px = rates[1].markers * 950.0
    px[100:103, marker] = 0.0
    _write_pixels(tmp_path, rates[1], scale=1.0, markers=px)
    with pytest.raises(InputError) as e:
        sd.load_dir(tmp_path)
    assert "markers_f1_00.csv" in e.value.source and e.value.field == f"row 101 marker {marker}"
    assert "tracking dropout" in e.value.problem


# --- 5. byte-order mark, two files of one label -----------------------------------------------------


def test_a_byte_order_mark_is_read_past(tmp_path, rates):
    path = _write_pixels(tmp_path, rates[1])
    text = path.read_text().replace("\n", "\r\n")
    path.write_bytes(b"\xef\xbb\xbf" + text.encode())
    got = sd.load_dir(tmp_path)[0]
    assert abs(got.speed - rates[1].speed) < 1e-6


def test_two_files_of_one_label_are_refused_naming_both(tmp_path, rates):
    _write_pixels(tmp_path, rates[1])
    _write_pixels(tmp_path, rates[4], name="markers_f1_0.csv")
    with pytest.raises(InputError) as e:
        sd.load_dir(tmp_path)
    assert "markers_f1_0.csv" in e.value.problem and "markers_f1_00.csv" in e.value.problem
    # a pixel file and a rotated file of one label stay fine: the pixel file is used
    ok = tmp_path / "ok"
    ok.mkdir()
    _write_pixels(ok, rates[1])
    _write_rotated(ok, rates[1])
    assert [r.frame for r in sd.load_dir(ok)] == ["world"]


def test_frames_cut_from_a_rotated_file_are_refused_by_the_head_jump(tmp_path, rates):
    """A head-frame file keeps the head's forward progress, so frames cut out of it leave the head's jump as in a
    pixel file; before the check was applied to these files, a cut clip was read through and swam too fast."""
    whole = _write_rotated(tmp_path, rates[1])
    rows = np.loadtxt(whole, delimiter=",").reshape(-1, sd.N_MARKERS, 2)
    assert sd.load_dir(tmp_path)[0].speed > 0  # the uncut clip loads
    np.savetxt(whole, np.delete(rows, np.s_[100:160], axis=0).reshape(-1, 2), delimiter=",")
    with pytest.raises(InputError) as e:
        sd.load_dir(tmp_path)
    # frames 100 and 101 of the cut clip are rows 892-909 (9 rows a frame)
    assert whole.name in str(e.value) and e.value.field == "rows 892-909" and "jumps" in e.value.problem


def test_clip_names_with_a_decimal_point_or_capitals_read_alike_and_clip_like_names_are_refused(tmp_path, rates):
    """markers_f2.25.csv was skipped in silence (the fit ran on one rate fewer); it and MARKERS_F1_00.CSV now read as
    their labels, while a name that starts like a clip but holds no label X.YZ is refused, naming the file."""
    _write_pixels(tmp_path, rates[0], name="markers_f0.50.csv")
    _write_pixels(tmp_path, rates[1], name="MARKERS_F1_00.CSV")
    (tmp_path / "notes.csv").write_text("not a clip")
    got = sd.load_dir(tmp_path)
    assert [(r.label, r.source) for r in got] == [(0.5, "markers_f0.50.csv"), (1.0, "MARKERS_F1_00.CSV")]
    _write_pixels(tmp_path, rates[2], name="markers_f1_25_take2.csv")
    with pytest.raises(InputError) as e:
        sd.load_dir(tmp_path)
    assert "markers_f1_25_take2.csv" in str(e.value) and e.value.field == "file name"


def test_a_clip_too_short_for_one_tail_beat_is_refused_in_one_line(tmp_path, rates):
    """121 frames of the 1.00 Hz clip (2 s, 1.5 beats): the beat scan found 0.05 Hz in its trend, no beat window
    remained, and the fit ended in a traceback."""
    _write_pixels(tmp_path, rates[1], markers=rates[1].markers[:121])
    with pytest.raises(InputError) as e:
        sd.load_dir(tmp_path)
    assert e.value.field == "rows" and "too short to measure the tail beat" in e.value.problem
    assert "160 frames" in e.value.problem  # two beats at this robot's 0.75 x 1.00 Hz


def test_frames_repeated_while_swimming_are_refused_from_one_percent_and_flagged_below(tmp_path, rates):
    """Every 33rd frame written twice (3 %, a frame-rate conversion) passed the old 5 % limit and moved the slender
    drag +4 std in silence (review of stop 54); clips tracked from video, rounded to whole pixels or not, never repeat
    while the fish swims. Copies under 1 % are flagged, not refused."""
    m = rates[1].markers
    _write_pixels(tmp_path, rates[1], markers=np.repeat(m, [2 if i % 33 == 5 else 1 for i in range(len(m))], axis=0))
    with pytest.raises(InputError) as e:
        sd.load_dir(tmp_path)
    assert e.value.field == "rows" and "duplicated frames" in e.value.problem
    two = np.repeat(m, [2 if i in (100, 200) else 1 for i in range(len(m))], axis=0)
    _write_pixels(tmp_path, rates[1], markers=two)
    flags = sd.clip_flags(sd.load_dir(tmp_path)[0])
    assert any("of 303 frames repeat" in f for f in flags)
    _write_pixels(tmp_path, rates[1])
    assert not any("repeat" in f for f in sd.clip_flags(sd.load_dir(tmp_path)[0]))
    _write_pixels(tmp_path, rates[1], markers=np.round(m * 950.0) / 950.0)  # whole pixels: no repeats while swimming
    assert not any("repeat" in f for f in sd.clip_flags(sd.load_dir(tmp_path)[0]))


def test_an_empty_line_between_rows_is_a_lost_frame_and_refused_by_its_line(tmp_path, rates):
    """np.loadtxt skipped empty lines: an empty line for every 25th row of the 0.50 Hz clip made it swim 4 % fast in
    silence (review of stop 54). Empty lines before the first row or after the last are no frames."""
    path = _write_pixels(tmp_path, rates[1])
    lines = path.read_text().splitlines()
    path.write_text("\n" + "\n".join(lines) + "\n\n")
    assert len(sd.load_dir(tmp_path)[0].markers) == len(lines)
    lines[99] = ""
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError) as e:
        sd.load_dir(tmp_path)
    assert e.value.source == str(path) and e.value.field == "row 100" and "empty line" in e.value.problem


def test_unreadable_empty_or_misnamed_clip_files_are_refused_naming_the_file(tmp_path, rates):
    """A dangling link (git-annex data not fetched) was reported as a bare FileNotFoundError, an empty file as one
    column, a cell's position by numpy's 0-based row, and markers_f1_25.txt was left out in silence (review of stop
    54)."""
    (tmp_path / "markers_f1_00.csv").symlink_to(tmp_path / "not-fetched")
    with pytest.raises(InputError) as e:
        sd.load_dir(tmp_path)
    assert e.value.source == str(tmp_path / "markers_f1_00.csv") and e.value.field == "file"
    (tmp_path / "markers_f1_00.csv").unlink()
    (tmp_path / "markers_f1_00.csv").write_text("")
    with pytest.raises(InputError, match="empty file"):
        sd.load_dir(tmp_path)
    path = _write_pixels(tmp_path, rates[1])
    lines = path.read_text().splitlines()
    cells = lines[41].split(",")
    cells[2] = "x"
    lines[41] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError) as e:
        sd.load_dir(tmp_path)
    assert e.value.field == "row 42 column 3" and "'x' is not a number" in e.value.problem
    path.unlink()
    _write_pixels(tmp_path, rates[1], name="markers_f1_25.txt")
    with pytest.raises(InputError) as e:
        sd.load_dir(tmp_path)
    assert "markers_f1_25.txt" in e.value.source and e.value.field == "file name"


def test_files_beside_the_clips_and_comments_in_them_are_no_clips(tmp_path, rates):
    """A plot, an editor's backup or a folder named like a clip had refused the whole folder, and a comment after a row
    (which np.loadtxt read past) was refused as a number (review of stop 54's change)."""
    path = _write_pixels(tmp_path, rates[1])
    lines = path.read_text().splitlines()
    lines[3] += "  # the tracker re-found marker 5"
    lines.insert(50, "# a comment line is no lost frame")
    path.write_text("\n".join(lines) + "\n")
    (tmp_path / "markers_f1_00.png").write_bytes(b"\x89PNG")
    (tmp_path / "markers_f1_00.csv~").write_text("an editor's backup")
    (tmp_path / "markers_f1_00_plots").mkdir()
    got = sd.load_dir(tmp_path)
    assert len(got) == 1 and len(got[0].markers) == len(rates[1].markers)
