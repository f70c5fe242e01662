"""`view`: a run folder's result that the report cannot be made from, or a file that is not a Rerun recording, is
refused in one line naming the file and the field (exit 2), before any page is written or any viewer starts."""
import json

import pytest

from wrenorm.cli import main


def _fit(**over) -> dict:
    r = {"schema": "wrenorm.result/1", "task": "pd", "resolution": {"f_sim": 100.0}, "train": ["a"], "seed": 0,
         "parameters": {"J": {"measured": 0.05, "fitted": 0.0525, "bounds": [0.01, 0.25], "std": 1e-4,
                              "frozen": False},
                        "K_P": {"measured": 20.0, "fitted": 20.0, "bounds": [5, 80], "std": None, "frozen": True}},
         "loss": {"measured": 1.0, "fitted": 0.5, "meaning": "m"},
         "validation": {"verdict": "absorbed", "tolerance": 0.1,
                        "conditions": {"held": {"measured_error": 0.2, "fitted_error": 0.01}}},
         "uncertainty": {"method": "gauss-newton"}, "search": {"methods": ["cmaes"], "evaluations": 10}}
    r.update(over)
    return r


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


def test_a_well_formed_result_still_makes_its_report(tmp_path):
    (tmp_path / "result.json").write_text(json.dumps(_fit()))
    assert main(["view", str(tmp_path), "--report"]) == 0
    assert "<b>absorbed</b>" in (tmp_path / "report.html").read_text()


@pytest.mark.parametrize("text,field", [
    (json.dumps(_fit(), indent=2)[:300], "line "),  # truncated: not valid JSON, where it stops
    ("[]", "top level"),
    (json.dumps(_fit(parameters=[1, 2])), "parameters"),
    (json.dumps({"task": "rope"}), "parameters"),  # nothing the report needs
    (json.dumps({k: v for k, v in _fit().items() if k != "validation"}), "validation"),
    (json.dumps(_fit(task="nosuchsystem")), "task"),
    (json.dumps({k: v for k, v in _fit().items() if k != "task"}), "task"),
    (json.dumps(_fit(parameters={"J": 0.05})), "parameters.J"),
    (json.dumps(_fit(parameters={"J": {"measured": 0.05, "fitted": "0.05"}})), "parameters.J.fitted"),
    (json.dumps(_fit(parameters={"J": {"measured": 0.05}})), "parameters.J.fitted"),
    (json.dumps(_fit(parameters={})), "parameters"),
    (json.dumps(_fit(loss=3)), "loss"),
    (json.dumps(_fit(uncertainty=[1])), "uncertainty"),
    (json.dumps(_fit(schema=7)), "schema"),
    (json.dumps({"schema": "wrenorm.result/1", "task": "pd", "runs": [_fit(), {"task": "pd"}]}), "runs[1].parameters"),
    (json.dumps({"schema": "wrenorm.flow/1", "task": "pd", "points": []}), "points"),
    (json.dumps({"schema": "wrenorm.flow/1", "task": "pd", "points": [{"resolution": {}, "loss": {}}]}),
     "points[0].parameters"),
    # a part check_result does not look at, laid out otherwise: still one line naming the file
    (json.dumps(_fit(validation={"conditions": {"held": 5}})), "contents"),
    (json.dumps(_fit(validation={"verdict": "bogus", "tolerance": 0.1})), "validation.verdict"),  # was shown
])
def test_a_result_the_report_cannot_be_made_from_is_one_line_exit_2(tmp_path, capsys, text, field):
    (tmp_path / "result.json").write_text(text)
    assert main(["view", str(tmp_path), "--report"]) == 2
    err = _one_line(capsys)
    assert str(tmp_path / "result.json") in err and f": {field}" in err, err
    assert not (tmp_path / "report.html").exists()  # no page from a result it cannot stand behind


def test_the_ratio_shown_is_the_values_shown(tmp_path):
    """A stored ratio_to_measured is not trusted: an edited fitted value (here NaN) showed the old 1.05x beside it."""
    r = _fit()
    r["parameters"]["J"].update(fitted=float("nan"), ratio_to_measured=1.05)
    (tmp_path / "result.json").write_text(json.dumps(r))
    assert main(["view", str(tmp_path), "--report"]) == 0
    page = (tmp_path / "report.html").read_text()
    assert "1.05×" not in page
    r["parameters"]["J"].update(fitted=0.06)
    (tmp_path / "result.json").write_text(json.dumps(r))
    assert main(["view", str(tmp_path), "--report"]) == 0
    assert "1.2×" in (tmp_path / "report.html").read_text()


def test_a_std_larger_than_its_value_is_not_called_determined(tmp_path):
    """The page called a parameter "determined" whenever the data did not fail to determine it outright, beside a std
    of 1100 % of its value; where the uncertainty lists what the data pin, the page follows it."""
    r = _fit(uncertainty={"method": "gauss-newton", "undetermined": [], "determined_by_data": []})
    r["parameters"]["J"]["std"] = 0.06
    (tmp_path / "result.json").write_text(json.dumps(r))
    assert main(["view", str(tmp_path), "--report"]) == 0
    page = (tmp_path / "report.html").read_text()
    assert "loosely determined" in page and ">determined<" not in page
    r["uncertainty"]["determined_by_data"] = ["J"]
    (tmp_path / "result.json").write_text(json.dumps(r))
    assert main(["view", str(tmp_path), "--report"]) == 0
    assert "loosely determined" not in (tmp_path / "report.html").read_text()
    # seeds that end apart and a loose std are two things said, side by side (the rope's radius at +-61 % had shown
    # "differs across seeds" alone); a prior that holds it says more than loose, and takes its place
    r["uncertainty"]["determined_by_data"] = []
    r["restarts"] = {"not_pinned": ["J"]}
    (tmp_path / "result.json").write_text(json.dumps(r))
    assert main(["view", str(tmp_path), "--report"]) == 0
    page = (tmp_path / "report.html").read_text()
    assert "differs across seeds" in page and "loosely determined" in page
    r["uncertainty"]["held_by_prior"] = ["J"]
    (tmp_path / "result.json").write_text(json.dumps(r))
    assert main(["view", str(tmp_path), "--report"]) == 0
    page = (tmp_path / "report.html").read_text()
    assert "held by prior" in page and "loosely determined" not in page


def test_a_result_that_is_not_text_is_refused(tmp_path, capsys):
    (tmp_path / "result.json").write_bytes(b"\xff\xfe\x00binary")
    assert main(["view", str(tmp_path), "--report"]) == 2
    assert str(tmp_path / "result.json") in _one_line(capsys)


# ------------------------------------------------------------------------------------------ the recording

@pytest.fixture
def viewer(monkeypatch):
    """The Rerun viewer, replaced: the files it would have been handed."""
    import subprocess

    calls = []
    monkeypatch.setattr(subprocess, "call", lambda argv, *a, **k: calls.append(argv[3:]) or 0)
    monkeypatch.setenv("DISPLAY", ":0")
    return calls


def test_without_a_display_the_viewer_is_not_started_and_the_web_viewer_is_offered(tmp_path, viewer, monkeypatch,
                                                                                   capsys):
    """Without a display the native viewer failed in Rerun's many lines of windowing errors."""
    rrd = tmp_path / "recording.rrd"
    rrd.write_bytes(b"RRF2" + bytes(60))
    monkeypatch.delenv("DISPLAY")
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    assert main(["view", str(tmp_path)]) == 1 and viewer == []
    err = _one_line(capsys)
    assert "no display" in err and "--web" in err and str(rrd) in err
    assert main(["view", str(tmp_path), "--web"]) == 0
    assert viewer == [[str(rrd), "--web-viewer"]]


def test_a_recording_goes_to_the_viewer(tmp_path, viewer):
    rrd = tmp_path / "recording.rrd"
    rrd.write_bytes(b"RRF2" + bytes(60))
    assert main(["view", str(tmp_path)]) == 0
    assert viewer == [[str(rrd)]]


def test_a_fit_at_several_resolutions_shows_each_sub_run(tmp_path, viewer):
    """`fit pd --f-sim 100,400` records f_sim100/ and f_sim400/ and nothing above them; its printed `view` line
    opened nothing ("no recording")."""
    for sub in ("f_sim100", "f_sim400"):
        (tmp_path / sub).mkdir()
        (tmp_path / sub / "recording.rrd").write_bytes(b"RRF2" + bytes(60))
    assert main(["view", str(tmp_path)]) == 0
    assert viewer == [[str(tmp_path / "f_sim100" / "recording.rrd"), str(tmp_path / "f_sim400" / "recording.rrd")]]


@pytest.mark.parametrize("name,data,needle", [
    ("rope.npz", b"PK\x03\x04" + bytes(60), "not a Rerun recording"),
    ("x.rrd", b"", "empty"),
    ("old.rrd", b"RRF1" + bytes(60), "older Rerun"),
])
def test_a_file_that_is_not_a_recording_never_reaches_the_viewer(tmp_path, capsys, viewer, name, data, needle):
    f = tmp_path / name
    f.write_bytes(data)
    assert main(["view", str(f)]) == 2
    err = _one_line(capsys)
    assert str(f) in err and "recording" in err and needle in err, err
    assert viewer == []


def test_a_run_folder_with_one_bad_recording_is_refused(tmp_path, capsys, viewer):
    (tmp_path / "recording.rrd").write_bytes(b"RRF2" + bytes(60))
    (tmp_path / "f_sim100").mkdir()
    (tmp_path / "f_sim100" / "recording.rrd").write_text("not a recording")
    assert main(["view", str(tmp_path)]) == 2
    assert str(tmp_path / "f_sim100" / "recording.rrd") in _one_line(capsys)
    assert viewer == []


def test_view_of_a_path_that_does_not_exist_says_so(tmp_path, capsys):
    """It had said "no recording in this run folder" of a typo (review of stop 54)."""
    assert main(["view", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err
    assert "nope: run: does not exist" in err and err.count("\n") == 1


def test_an_interrupted_command_that_cannot_resume_is_not_told_to():
    """select and sensitivity were told "continue with --resume", which they do not take (review of stop 54)."""
    from wrenorm.cli import build_parser
    from wrenorm.interrupt import resume_hint

    fit, select = (build_parser(argv).parse_args(argv) for argv in (["fit", "pd", "--out", "r"],
                                                                    ["select", "swimmer", "--out", "r"]))
    assert resume_hint(fit) == "; continue with --resume --out r"  # parsed alone, without the command line
    fit._argv = ["flow", "pd", "--resolutions", "50", "100", "--out", "r", "--force"]
    assert resume_hint(fit) == "; continue with: python -m wrenorm flow pd --resolutions 50 100 --out r --resume"
    assert "does not resume" in resume_hint(select) and "--force --out r" in resume_hint(select)


def test_view_report_of_a_sweep_or_select_folder_says_what_the_folder_is(tmp_path, capsys):
    """A finished sweep's folder had been called "not a finished run folder" (a new user's review of stop 55)."""
    (tmp_path / "sweep.json").write_text("{}")
    assert main(["view", str(tmp_path), "--report"]) == 2
    assert "a sweep's folder (sweep.json)" in _one_line(capsys)
    (tmp_path / "sweep.json").unlink()
    (tmp_path / "select.json").write_text("{}")
    assert main(["view", str(tmp_path), "--report"]) == 2
    assert "a select run's folder" in _one_line(capsys)
