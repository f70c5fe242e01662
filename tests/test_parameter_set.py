"""--free / --freeze grow or shrink the fitted set (the paper's procedure when the held-out verdict
says 'expand'); names are checked, and a resumed search must fit the same set."""
import json

from wrenorm.cli import main

FIT = ["fit", "pd", "--quiet", "--no-record", "--generations", "8"]


def _params(out):
    return json.loads((out / "result.json").read_text())["parameters"]


def test_free_and_freeze_change_what_is_fitted(tmp_path):
    out = tmp_path / "run"
    assert main([*FIT, "--free", "K_P", "--freeze", "K_AFF", "--out", str(out)]) == 0
    p = _params(out)
    assert p["K_P"]["frozen"] is False and p["K_AFF"]["frozen"] is True
    assert p["K_AFF"]["fitted"] == p["K_AFF"]["measured"]
    assert p["K_P"]["fitted"] != p["K_P"]["measured"]


def test_bad_parameter_sets_exit_2(tmp_path, capsys):
    assert main([*FIT, "--free", "spring", "--out", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err
    assert "spring" in err and "K_D" in err  # names the unknown one and lists the known ones
    assert main([*FIT, "--free", "J", "--freeze", "J", "--out", str(tmp_path / "b")]) == 2
    assert "both" in capsys.readouterr().err
    assert main([*FIT, "--freeze", "J", "K_D", "K_FF", "K_AFF", "--out", str(tmp_path / "c")]) == 2
    assert "no free parameter" in capsys.readouterr().err


def test_resume_with_another_parameter_set_is_refused(tmp_path, capsys):
    out = tmp_path / "run"
    assert main([*FIT, "--out", str(out)]) == 0
    assert main([*FIT, "--freeze", "K_FF", "--out", str(out), "--resume"]) == 2
    assert "same --free/--freeze" in capsys.readouterr().err
