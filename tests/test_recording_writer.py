"""The recording writer process: a recording written there holds what one written in this process holds, and a
writer that dies costs nothing but the time to write it here instead."""
import numpy as np
import pytest

from wrenorm.viz import record
from wrenorm.viz.readback import entity_paths


def _log(rec):
    rec.log_scalar("fitted/a", 0.0, 1.0)
    rec.log_scalar("fitted/a", 1.0, 2.0)
    rec.log_points3d("reference/rope", 0.5, np.zeros((4, 3)), radii=0.01, labels=["x", "", "", ""])
    rec.log_series("measured/q", np.linspace(0, 1, 50), np.sin(np.linspace(0, 1, 50)))
    rec.log_text("summary", "# hi")
    rec.add_view("v", ["/fitted/**", "/measured/**"])
    rec.show_timeline("sim_time")


def _data(rrd) -> set[str]:
    """Entities other than the blueprint's (whose views get fresh ids in every recording)."""
    return {p for p in entity_paths(rrd) if not p.startswith(("/view/", "/container/"))}


@pytest.fixture
def writer(monkeypatch):
    monkeypatch.setattr(record, "_WRITER", None)
    record.start_writer()
    assert record._WRITER is not None and record._WRITER.alive
    w = record._WRITER
    yield w
    w.stop()


def test_a_recording_from_the_writer_holds_what_one_written_here_holds(tmp_path, writer, monkeypatch):
    via_writer = record.Recorder(tmp_path / "w.rrd", recording_id="r")
    assert via_writer._calls is not None  # deferred to the writer
    _log(via_writer)
    assert via_writer.close() == tmp_path / "w.rrd"
    monkeypatch.setattr(record, "_WRITER", None)
    here = record.Recorder(tmp_path / "h.rrd", recording_id="r")
    assert here._live is not None
    _log(here)
    here.close()
    assert _data(tmp_path / "w.rrd") == _data(tmp_path / "h.rrd") >= {
        "/fitted/a", "/reference/rope", "/measured/q", "/summary"}
    assert not list(tmp_path.glob("*.partial"))


def test_a_dead_writer_costs_only_the_time_to_write_here(tmp_path, writer, capsys):
    rec = record.Recorder(tmp_path / "r.rrd", recording_id="r")
    _log(rec)
    writer.proc.kill()
    writer.proc.wait()
    rec.close()
    assert "/fitted/a" in entity_paths(tmp_path / "r.rrd")
    assert "writing the recording here" in capsys.readouterr().err


def test_a_writer_that_cannot_write_says_why_and_the_recording_is_written_here(tmp_path, writer, capsys):
    rec = record.Recorder(tmp_path / "r.rrd", recording_id="r")
    _log(rec)
    rec._calls.append(("log_scalar", ("fitted/b", 0.0, "not a number"), {}))
    with pytest.raises(ValueError):  # the same call fails here too: a real error, not swallowed
        rec.close()
    err = capsys.readouterr().err
    assert "recording writer failed (error: ValueError" in err
    assert writer.alive  # the writer survives a bad recording and serves the next one
    ok = record.Recorder(tmp_path / "ok.rrd", recording_id="r")
    _log(ok)
    ok.close()
    assert "/fitted/a" in entity_paths(tmp_path / "ok.rrd")
    assert "writer failed" not in capsys.readouterr().err
