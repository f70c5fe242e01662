"""Sweeps (issue #21): a bad spec is one line and exit 2 before Ray starts; cells run as Ray tasks on a local Ray with
2 CPUs and give the table; a failing cell is recorded and the others go on; a lost worker is recorded; a sweep
killed with SIGKILL resumes to the same table, running only the missing cells; every cell's result equals what
`fit` writes for the same options and seed. Bad inputs (issue: sweep inputs): a spec not in UTF-8, or with a
byte-order mark; a file or folder a cell is given that does not exist; a cell failing on a malformed file."""
import codecs
import contextlib
import csv
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from wrenorm.cli import main
from wrenorm.errors import InputError

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
VOLATILE_RESULT = {"wall_seconds", "timing", "command"}  # what differs between two runs of the same fit
ROPE_NPZ = ROOT / "wrenorm" / "data" / "rope_default_flick.npz"  # a good rope reference

# 6 cells: restarts = 1 is refused by `fit` itself (not by the parser), so two cells fail and two succeed; the slow
# generations (a test hook of the engine) keep cells running long enough to kill the sweep or a worker mid-way
SPEC = """
task = "fit pd"
description = "test sweep"

[options]
search = "cmaes"
generations = 12
popsize = 8
no-record = true

[axes]
f-sim = [100, 200, 400]
restarts = [0, 1]
"""


def _ray():
    if os.environ.get("CI"):
        import ray  # CI installs the `sweep` extra: a missing Ray is a failure there, not a skip

        return ray
    return pytest.importorskip("ray")


def _write(tmp_path, text=SPEC, name="spec.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def _sweep(spec, out, *extra, env=None, wait=True):
    cmd = [sys.executable, "-m", "wrenorm", "sweep", str(spec), "--out", str(out), "--cpus", "2", "--quiet", *extra]
    env = dict(os.environ, **(env or {}))
    if not wait:
        return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                start_new_session=True)
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)


def _rows(out: Path) -> list[dict]:
    return list(csv.DictReader(io.StringIO((out / "sweep.csv").read_text())))


def _stable(rows):
    from wrenorm.sweep.table import VOLATILE

    return [{k: v for k, v in r.items() if k not in VOLATILE} for r in rows]


def _descendants(pid: int) -> list[int]:
    """Processes below `pid` (this test's own children and theirs), from /proc."""
    parent = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                parent[int(d.name)] = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                pass
    out, frontier = [], [pid]
    while frontier:
        kids = [p for p, pp in parent.items() if pp in frontier]
        out += kids
        frontier = kids
    return out


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def _end(pids) -> None:
    for p in pids:
        try:
            os.kill(p, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass


# --- the spec: no Ray needed ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("text, key", [
    ('task = "fit nosuch"', "task"),
    ('task = "view pd"', "task"),
    ('task = "fit pd"\n[options]\nbogus = 1', "options.bogus"),
    ('task = "fit pd"\n[options]\nseed = 3', "options.seed"),
    ('task = "fit pd"\n[options]\nout = "x"', "options.out"),
    ('task = "fit pd"\n[options]\narm = 3', "options.arm"),
    ('task = "fit pd"\n[options]\ngenerations = 0', "--generations"),
    ('task = "fit pd"\n[axes]\nf-sim = [100, 100]', "axes.f-sim"),
    ('task = "fit pd"\n[axes]\nf-sim = [100, 1]', "axes.f-sim"),
    ('task = "fit pd"\n[axes]\nf-sim = []', "axes.f-sim"),
    ('task = "fit pd"\n[axes]\nintegrator = ["explicit", "rk4"]', "axes.integrator"),
    ('task = "fit pd"\n[options]\nf-sim = 100\n[axes]\nf-sim = [200]', "options.f-sim"),
    ('task = "fit pd"\n[options]\nK_D = 0.9\n[axes]\nK-D = [0.3, 0.5]', "options.K_D"),
    ('task = "fit pd"\n[options]\nf_sim = [400]\n[axes]\nf-sim = [100, 200]', "options.f_sim"),
    ('task = "fit pd"\n[axes]\nf-sim = [100, 100.0]', "axes.f-sim"),
    ('task = "fit swimmer"\n[axes]\ntrain = [[1, 1.75], [1.0, 1.75]]', "axes.train"),
    ('task = "fit swimmer"\n[axes]\ntrain = [[1, 1.75], [1.75, 1]]', "axes.train: repeated value [1.75, 1]"),
    ('task = "fit pd"\nseeds = [1, 1]', "seeds"),
    ('task = "fit pd"\n[axis]\nf-sim = [100]', "axis"),
    ('task = fit pd', "toml"),
    ('task = "fit pd"\n[options]\nfree = ["nope"]', "options.free: --free nope: unknown parameter of pd"),
    ('task = "fit rope"\n[axes]\nfreeze = [["radius"], ["bend_stifness"]]',
     "axes.freeze: combination freeze=['bend_stifness']: --freeze bend_stifness: unknown parameter of rope"),
    ('task = "fit pd"\n[options]\narm = true\n[axes]\nfree = [["KD12"], ["J"]]', "--free J: unknown parameter of pd"),
    ('task = "flow pd"\n[options]\nfree = ["K_P"]\n[axes]\nfreeze = [["J"], ["K_P"]]', "named both free and frozen"),
    ('task = "fit pd"\n[options]\nreference = ""', "options.reference: every cell: --reference: an empty path"),
])
def test_a_bad_spec_exits_2_naming_the_key_before_anything_runs(tmp_path, capsys, text, key):
    spec = _write(tmp_path, text)
    out = tmp_path / "out"
    assert main(["sweep", str(spec), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("wrenorm: error: ") and err.count("\n") == 1 and "Traceback" not in err, err
    assert key in err, err
    assert not out.exists()


@pytest.mark.parametrize("text, message", [
    ('[options]\nK_D = 0.9\n[axes]\nK-D = [0.3, 0.5]',
     "options.K_D: is also an axis ([axes] K-D): fix it or vary it, not both"),
    ('[axes]\nK_D = [0.3]\nK-D = [0.5]', "axes.K-D: is the same option as axes.K_D (--K-D): give it once"),
    ('[options]\nf_sim = 100\nf-sim = 200', "options.f-sim: is the same option as options.f_sim (--f-sim)"),
    ('[axes]\nf-sim = [100, 200, 100.0]', "axes.f-sim: repeated value 100.0 (the same as 100)"),
    ('[axes]\nf-sim = [[100, 200], [100.0, 200]]', "axes.f-sim: repeated value [100.0, 200] (the same as [100, 200])"),
    ('[axes]\nfree = [["K_P", "K_FF"], ["K_FF", "K_P"]]',
     "axes.free: repeated value ['K_FF', 'K_P'] (the same as ['K_P', 'K_FF'])"),
])
def test_one_option_or_value_written_two_ways_is_refused(tmp_path, text, message):
    """`K_D` and `K-D` are one option (the cell's command would keep only the last), 100 and 100.0 one value, and so
    are two orders of one set of free parameters."""
    from wrenorm.sweep.spec import load

    with pytest.raises(InputError) as e:
        load(_write(tmp_path, 'task = "fit pd"\n' + text))
    assert message in str(e.value), e.value


def test_a_spec_expands_into_cells_with_the_tasks_own_command_lines(tmp_path):
    from wrenorm.sweep.spec import load

    spec = load(_write(tmp_path, 'task = "fit swimmer"\nseeds = [0, 5]\n[options]\nno_record = true\n'
                                 '[axes]\ntrain = [[1.0, 1.75], [0.5, 2.25]]\nvirtual-mass = [false, true]\n'))
    assert len(spec.cells) == 8 and len({c.id for c in spec.cells}) == 8
    first, last = spec.cells[0], spec.cells[-1]
    assert first.argv == ("fit", "swimmer", "--no-record", "--train", "1.0", "1.75", "--seed", "0")
    assert last.argv == ("fit", "swimmer", "--no-record", "--train", "0.5", "2.25", "--virtual-mass", "--seed", "5")
    assert last.id == "007_train-0.5,2.25_virtual-mass-True_seed-5"
    assert "--out" in first.command("DIR/cells/x")


def test_a_spec_not_in_utf8_is_one_line_naming_the_byte_and_exit_2(tmp_path, capsys):
    spec = tmp_path / "spec.toml"
    spec.write_bytes('task = "fit pd"  # café\n'.encode("latin-1"))  # 0xe9 at offset 22
    out = tmp_path / "out"
    assert main(["sweep", str(spec), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("wrenorm: error: ") and err.count("\n") == 1 and "Traceback" not in err, err
    assert f"{spec}: encoding: " in err and "byte 0xe9 at offset 22 (line 1, column 23)" in err, err
    assert not out.exists()


def test_a_spec_with_a_byte_order_mark_reads_as_one_without(tmp_path):
    from wrenorm.sweep.spec import load

    text = 'task = "fit pd"\n[axes]\nf-sim = [100, 200]\n'
    (tmp_path / "bom.toml").write_bytes(codecs.BOM_UTF8 + text.encode())
    bom, plain = load(tmp_path / "bom.toml"), load(_write(tmp_path, text))
    assert len(bom.cells) == 2 and [c.argv for c in bom.cells] == [c.argv for c in plain.cells]
    assert bom.text == text  # DIR/spec.toml, what --resume reads


@pytest.mark.parametrize("text, key, cells, given, problem", [
    ('task = "fit rope"\n[axes]\nreference = [["{good}"], ["{tmp}/nosuch.npz"]]', "axes.reference",
     "cell 001_reference-", "--reference {tmp}/nosuch.npz", "does not exist"),
    ('task = "fit rope"\nseeds = [0, 1]\n[axes]\nreference = [["nosuch.npz"]]', "axes.reference",
     "cell 000_reference-nosuch.npz_seed-0 and 1 more", "--reference nosuch.npz", "does not exist (relative to {tmp}"),
    ('task = "fit rope"\n[options]\nvalidate = ["{good}", "{tmp}"]', "options.validate", "every cell",
     "--validate {tmp}", "is a folder, not a file"),
    ('task = "fit pd"\n[options]\nreference = "{tmp}/log.csv"', "options.reference", "every cell",
     "--reference {tmp}/log.csv", "does not exist"),
    ('task = "fit swimmer"\n[options]\ndata = "{good}"', "options.data", "every cell", "--data {good}",
     "is a file, not a folder"),
    ('task = "correct rope"\n[options]\nparams = ["measured", "{tmp}/result.json"]', "options.params",
     "every cell", "--params {tmp}/result.json", "does not exist"),
])
def test_a_file_a_cell_is_given_that_does_not_exist_is_refused_before_anything_runs(
        tmp_path, capsys, monkeypatch, text, key, cells, given, problem):
    """Which options take files or folders is read from the commands' own parsers (metavar FILE or DIR)."""
    monkeypatch.chdir(tmp_path)
    fill = {"good": ROPE_NPZ, "tmp": tmp_path}
    spec = _write(tmp_path, text.format(**fill))
    out = tmp_path / "out"
    assert main(["sweep", str(spec), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("wrenorm: error: ") and err.count("\n") == 1 and "Traceback" not in err, err
    assert f"{spec}: {key}: {cells}" in err and f"{given.format(**fill)}: {problem.format(**fill)}" in err, err
    assert not out.exists()


def test_files_and_folders_that_exist_and_labels_pass_the_check(tmp_path, monkeypatch):
    from wrenorm.sweep.spec import load

    monkeypatch.chdir(tmp_path)  # relative paths: from the folder the sweep starts in
    shutil.copy(ROPE_NPZ, tmp_path / "a.npz")
    (tmp_path / "clips").mkdir()
    for text in (f'task = "fit rope"\n[axes]\nreference = [["a.npz"], ["{ROPE_NPZ}"]]',
                 'task = "fit swimmer"\n[options]\ndata = "clips"',
                 'task = "correct rope"\n[options]\nparams = ["measured", "fitted", "a.npz"]',
                 'task = "correct rope"\n[options]\nparams = "fitted,measured,a.npz"',  # the parser splits commas
                 f'task = "fit rope"\n[options]\nreference = "a.npz, {ROPE_NPZ}"'):
        assert load(_write(tmp_path, text)).cells, text
    with pytest.raises(InputError, match="nosuch.npz: does not exist"):  # and each part is checked
        load(_write(tmp_path, 'task = "fit rope"\n[options]\nreference = "a.npz,nosuch.npz"'))


def test_an_axis_named_like_a_fitted_parameter_keeps_the_swept_value_beside_the_fitted_one(tmp_path):
    """An axis `J` (the measured inertia each cell is given) and the fitted J are two numbers: the axis column keeps
    the swept value, the fitted one is `fitted_J` in the table and in what the plot draws."""
    from wrenorm.sweep import table
    from wrenorm.sweep.spec import load

    spec = load(_write(tmp_path, 'task = "fit pd"\n[axes]\nJ = [0.03, 0.08]\n'))
    records = {c.id: {"status": "done"} for c in spec.cells}
    results = {c.id: {"schema": "wrenorm.result/1", "loss": {"measured": 1.0, "fitted": 0.5},
                      "parameters": {"J": {"fitted": 0.05 + c.index, "std": 0.001, "frozen": False},
                                     "K_D": {"fitted": 0.4, "std": 0.01, "frozen": False}}} for c in spec.cells}
    rows = table.build(spec, records, results)
    assert [r["J"] for r in rows] == ["0.03", "0.08"]
    assert [r["fitted_J"] for r in rows] == [0.05, 1.05] and rows[0]["fitted_J_std"] == 0.001
    assert rows[0]["K_D"] == 0.4 and "fitted_K_D" not in rows[0]
    assert table.free_names("fit", results, spec.axes) == ["fitted_J", "K_D"]
    table.write_csv(tmp_path / "sweep.csv", spec, rows)
    written = _rows(tmp_path)
    assert [r["J"] for r in written] == ["0.03", "0.08"] and [r["fitted_J"] for r in written] == ["0.05", "1.05"]


def test_a_failed_cell_records_the_warnings_that_name_the_file_and_why(tmp_path):
    """`fit rope` leaves a malformed reference out with a warning, then fails with "all left out (warnings above)":
    the cell's error (what sweep.csv shows) carries the warning, not only its log."""
    from wrenorm.sweep.cell import WARNINGS_KEPT, _error_line, run_cell

    bad, other = tmp_path / "trunc.npz", tmp_path / "trunc2.npz"
    bad.write_bytes(ROPE_NPZ.read_bytes()[:1000])
    other.write_bytes(ROPE_NPZ.read_bytes()[:1000])
    # two files: each is left out with a warning, then the run fails (one file alone is refused in its own line)
    res = run_cell(["fit", "rope", "--no-record", "--reference", str(bad), str(other), "--seed", "0"],
                   str(tmp_path / "sweep"), "000_x", token="t")
    assert res["rc"] == 2 and res["result"] is None
    assert f"warning: {bad}: file: is not a readable .npz archive" in res["error"], res["error"]
    assert "no usable fit reference remains" in res["error"] and "\n" not in res["error"]
    log = "".join(f"wrenorm: warning: w{i}\n" for i in range(WARNINGS_KEPT + 2)) + "wrenorm: error: x: y: z\n"
    assert _error_line(log, 2) == "; ".join(["x: y: z", *(f"warning: w{i}" for i in range(2, WARNINGS_KEPT + 2)),
                                             "2 earlier warnings in the cell's log"])


def test_progress_is_a_plain_line_off_a_terminal_and_nothing_when_quiet():
    from wrenorm.sweep.progress import Progress

    buf = io.StringIO()
    p = Progress(4, label="sweep fit pd", stream=buf, every=0.0)
    p.update(0, 2, 0)
    p.update(1, 2, 1)  # a failure prints at once
    p.close()
    lines = buf.getvalue().splitlines()
    assert lines[0].startswith("[sweep fit pd] 0/4 cells  done 0  running 2  failed 0")
    assert "2/4 cells  done 1  running 2  failed 1" in lines[1] and "left" in lines[1] and "\r" not in buf.getvalue()
    quiet = io.StringIO()
    q = Progress(4, stream=quiet, quiet=True)
    q.update(1, 1, 1, force=True)
    q.note("x")
    q.close()
    assert quiet.getvalue() == ""


def test_a_cell_on_a_worker_that_does_not_see_the_sweep_folder_sends_its_files_back(tmp_path):
    """A cluster without a shared file system: the cell runs in a local temporary folder and its run folder travels
    back with the result."""
    from wrenorm.sweep.cell import run_cell

    argv = ["fit", "pd", "--no-record", "--f-sim", "100", "--seed", "0"]
    res = run_cell(argv, str(tmp_path / "sweep"), "000_x", token="t", ship=None)
    assert res["rc"] == 0 and res["error"] is None and res["files"]
    assert "result.json" in res["files"] and ".wrenorm-run" in res["files"]
    assert json.loads(res["files"]["result.json"]) == res["result"]
    assert not (tmp_path / "sweep").exists()  # nothing written where the worker could not see the sweep
    bad = run_cell([*argv[:-2], "--restarts", "1", "--seed", "0"], str(tmp_path / "sweep"), "001_x", token="t")
    assert bad["rc"] == 2 and "--restarts" in bad["error"] and bad["result"] is None


def test_a_killed_cells_run_is_resumed_not_run_again(tmp_path):
    """A cell killed before it finished left its run folder: its command continues it with --resume (a fit from its
    search log, torn mid-line as a kill leaves it; a correction from its stored trials) and gives the uninterrupted
    result; where its command cannot resume (killed before it saved a state), the cell runs afresh and says so."""
    from wrenorm.fit import STATE_FILE
    from wrenorm.sweep.cell import RESUME_REFUSED, run_cell

    sweep = tmp_path / "sweep"
    fit = ["fit", "rope", "--no-record", "--generations", "6", "--popsize", "8", "--seed", "0"]
    whole = run_cell(fit, str(sweep), "000_fit", token="t", ship=False)
    assert whole["rc"] == 0 and not whole["resumed"]
    folder = sweep / "cells" / "000_fit"
    log = (folder / STATE_FILE).read_text().splitlines(keepends=True)
    assert len(log) > 4
    (folder / STATE_FILE).write_text("".join(log[:3]) + log[3][: len(log[3]) // 2])  # killed mid-generation
    (folder / "result.json").unlink()
    again = run_cell(fit, str(sweep), "000_fit", token="t", ship=False)
    assert again["rc"] == 0 and again["resumed"] and RESUME_REFUSED not in again["log"]
    assert again["result"]["parameters"] == whole["result"]["parameters"]
    assert again["result"]["loss"] == whole["result"]["loss"]
    (folder / STATE_FILE).unlink()  # killed before its first state: nothing to continue
    (folder / "result.json").unlink()
    fresh = run_cell(fit, str(sweep), "000_fit", token="t", ship=False)
    assert fresh["rc"] == 0 and not fresh["resumed"] and RESUME_REFUSED in fresh["log"]
    assert fresh["result"]["parameters"] == whole["result"]["parameters"] and fresh["error"] is None

    correct = ["correct", "rope", "--real", "coarse", "--max-trials", "3", "--no-record", "--seed", "0"]
    first = run_cell(correct, str(sweep), "001_correct", token="t", ship=False)
    assert first["rc"] == 0, first["log"][-2000:]
    folder = sweep / "cells" / "001_correct"
    (folder / "correct.json").unlink()  # killed after its trials were stored, before its result
    resumed = run_cell(correct, str(sweep), "001_correct", token="t", ship=False)
    assert resumed["rc"] == 0 and resumed["resumed"]
    errors = [[t["error"] for t in r["runs"]["renormalised-from-fitted"]["trials"]]
              for r in (first["result"], resumed["result"])]
    assert errors[0] == errors[1] and len(errors[0]) == 3
    # its trials were read back, not run again (the stand-in's goal and start throws are not stored trials)
    assert resumed["result"]["real_trials_read_back"] == 3 and first["result"]["real_trials_read_back"] == 0
    assert resumed["result"]["real_runs"] <= first["result"]["real_runs"] - 3


# --- on a local Ray with 2 CPUs --------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """The test spec swept once, uninterrupted."""
    _ray()
    tmp = tmp_path_factory.mktemp("sweep")
    spec = _write(tmp)
    out = tmp / "out"
    proc = _sweep(spec, out)
    return spec, out, proc


def test_the_sweep_writes_one_row_per_cell_and_records_the_failing_ones(finished):
    spec, out, proc = finished
    assert proc.returncode == 3, proc.stderr  # some cells failed; the others' results are all there
    assert proc.stderr == "" or "Traceback" not in proc.stderr
    rows = _rows(out)
    assert [r["cell"] for r in rows][:3] == ["000_f-sim-100_restarts-0_seed-0", "001_f-sim-100_restarts-1_seed-0",
                                             "002_f-sim-200_restarts-0_seed-0"]
    assert [r["status"] for r in rows] == ["done", "failed"] * 3
    for r in rows:
        assert r["f-sim"] in ("100", "200", "400") and r["restarts"] in ("0", "1") and r["seed"] == "0"
        if r["status"] == "done":
            assert float(r["J"]) > 0 and float(r["J_std"]) > 0 and r["verdict"] in ("absorbed", "expand")
            assert float(r["loss_fitted"]) > 0 and float(r["loss_measured"]) > 0
            assert float(r["heldout_sine_2.5Hz_fitted"]) >= 0 and float(r["wall_seconds"]) > 0
            assert r["host"] and r["started"] and r["finished"] and not r["error"]
        else:
            assert "--restarts" in r["error"] and not r["J"]
    summary = json.loads((out / "sweep.json").read_text())
    assert summary["counts"] == {"done": 3, "failed": 3, "pending": 0}
    assert summary["timing"]["ray_start_s"] > 0 and summary["timing"]["cells_s"] > 0
    assert summary["cell_overhead"]["cells"] == 3
    assert (out / "sweep.png").stat().st_size > 10_000
    assert (out / "recording.rrd").exists() and (out / "spec.toml").read_text() == spec.read_text()
    assert "3/6 cells done, 3 failed" in proc.stdout


def test_every_cell_equals_what_fit_writes_for_the_same_options_and_seed(finished, tmp_path):
    from wrenorm.sweep.spec import load

    _, out, _ = finished
    for cell in load(out / "spec.toml").cells:
        mine = out / "cells" / cell.id / "result.json"
        if not mine.exists():
            continue
        assert main([*cell.argv, "--out", str(tmp_path / cell.id), "--quiet"]) == 0
        theirs = json.loads((tmp_path / cell.id / "result.json").read_text())
        mine = json.loads(mine.read_text())
        assert {k: v for k, v in mine.items() if k not in VOLATILE_RESULT} == \
               {k: v for k, v in theirs.items() if k not in VOLATILE_RESULT}, cell.id


def test_resume_of_a_finished_sweep_runs_nothing_and_keeps_the_table(finished, tmp_path):
    _, out, _ = finished
    before = (out / "sweep.csv").read_text()
    assert main(["sweep", str(out / "spec.toml"), "--out", str(out), "--resume", "--quiet"]) == 3
    assert (out / "sweep.csv").read_text() == before  # nothing re-run: even the timestamps are the same
    other = _write(tmp_path, SPEC.replace("[100, 200, 400]", "[100, 800]"))
    assert main(["sweep", str(other), "--out", str(out), "--resume", "--quiet"]) == 2  # another spec: refused
    assert main(["sweep", str(other), "--out", str(out), "--quiet"]) == 2  # an existing sweep needs --force


def test_a_sweep_killed_with_sigkill_resumes_to_the_same_table_running_only_missing_cells(finished, tmp_path):
    spec, ref, _ = finished
    out = tmp_path / "killed"
    proc = _sweep(spec, out, env={"WRENORM_TEST_SLOW_GENERATION": "0.4"}, wait=False)
    state, records, below = out / "sweep-state.json", {}, []
    deadline = time.time() + 240
    try:
        while time.time() < deadline and proc.poll() is None:
            below = sorted(set(below) | set(_descendants(proc.pid)))
            try:
                records = json.loads(state.read_text()).get("records", {})
            except (OSError, ValueError):
                records = {}
            if any(r["status"] == "done" for r in records.values()):
                break
            time.sleep(0.1)
        below = sorted(set(below) | set(_descendants(proc.pid)))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    finally:
        time.sleep(1.0)
        _end(p for p in below if "ray" in _cmdline(p))  # Ray's helpers outlive a killed driver
    assert 1 <= len(records) < 6, records
    kept = {k: r["started"] for k, r in records.items()}
    resumed = _sweep(spec, out, "--resume")
    assert resumed.returncode == 3, resumed.stderr
    after = json.loads(state.read_text())["records"]
    assert {k: after[k]["started"] for k in kept} == kept  # the finished cells were not run again
    assert len(after) == 6
    assert _stable(_rows(out)) == _stable(_rows(ref))


@pytest.mark.parametrize("how", ["replaced", "deleted"])
def test_resume_runs_a_cell_again_whose_result_the_table_cannot_read(finished, tmp_path, how):
    """A finished cell's result.json replaced by something else, or its folder deleted, is not a finished cell: said,
    and run again (a deleted folder was run again without a word until stop 48)."""
    _, ref, _ = finished
    out = tmp_path / "copy"
    shutil.copytree(ref, out)
    cell = next(r["cell"] for r in _rows(ref) if r["status"] == "done")
    bad = out / "cells" / cell / "result.json"
    if how == "replaced":
        bad.write_text('{"schema": "x", "parameters": {}}')
    else:
        shutil.rmtree(bad.parent)
    before = json.loads((out / "sweep-state.json").read_text())["records"]
    proc = _sweep(out / "spec.toml", out, "--resume")
    assert proc.returncode == 3, proc.stderr
    why = "schema is 'x', not wrenorm.result/*" if how == "replaced" else "recorded as done but missing"
    assert f"wrenorm: warning: {bad}: {why}; running cell {cell} again" in proc.stderr
    after = json.loads((out / "sweep-state.json").read_text())["records"]
    assert after[cell]["started"] != before[cell]["started"]
    assert {k: after[k]["started"] for k in before if k != cell} == {k: r["started"] for k, r in before.items()
                                                                       if k != cell}
    assert _stable(_rows(out)) == _stable(_rows(ref))


@pytest.mark.parametrize("sig,code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_ctrl_c_says_on_the_terminal_how_to_resume(tmp_path, sig, code):
    """While cells run, stderr is ray.log: the interrupt's line must still reach the terminal. SIGTERM too (Ray's init
    puts its own handler in place: sys.exit(15), no line)."""
    _ray()
    spec = _write(tmp_path, SPEC.replace("restarts = [0, 1]", ""))
    out = tmp_path / "out"
    proc = _sweep(spec, out, env={"WRENORM_TEST_SLOW_GENERATION": "0.4"}, wait=False)
    below, running = [], False
    deadline = time.time() + 240
    try:
        while time.time() < deadline and proc.poll() is None and not running:
            below = sorted(set(below) | set(_descendants(proc.pid)))
            state = out / "sweep-state.json"
            done = state.is_file() and sum(r.get("status") == "done"
                                           for r in json.loads(state.read_text()).get("records", {}).values())
            running = done >= 2 and any(_cmdline(p).startswith("ray::run_cell") for p in below)
            time.sleep(0.05)
        # two cells done (they ran side by side and ended within the table's 2 s) and the third running: the
        # interrupt lands before the table's next write
        assert running
        proc.send_signal(sig)
        _, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        time.sleep(1.0)
        _end(p for p in below if "ray" in _cmdline(p))
    assert proc.returncode == code, stderr
    hint = next(line for line in stderr.splitlines() if line.startswith("wrenorm: interrupted"))
    assert hint.startswith(f"wrenorm: interrupted; continue with: python -m wrenorm sweep {spec} --out {out}"), stderr
    assert hint.endswith(" --resume"), stderr
    # the table says what the saved state says: written before Ray's shut-down, which outlasts the one-second grace
    state = json.loads((out / "sweep-state.json").read_text())["records"]
    assert {r["cell"]: r["status"] for r in _rows(out)} == {c: state.get(c, {}).get("status", "pending")
                                                            for c in (r["cell"] for r in _rows(out))}


def test_resume_refuses_an_input_whose_content_changed_naming_it(tmp_path, capsys, monkeypatch):
    """The same spec and cells, but `logs/a.csv` edited in place, or the spec resumed from another folder where the
    relative path names another file: refused, as `fit --resume` refuses it."""
    _ray()
    from wrenorm.cli import content_hashes
    from wrenorm.runfolder import prepare_out
    from wrenorm.sweep.run import _load_state, _save_state
    from wrenorm.sweep.spec import load

    monkeypatch.chdir(tmp_path)
    (tmp_path / "logs").mkdir()
    log = tmp_path / "logs" / "a.csv"
    log.write_text("time,q,q_d,qd_d\n0,0,0,0\n")
    spec_file = _write(tmp_path, 'task = "fit pd"\n[options]\nreference = "logs/a.csv"\n[axes]\nf-sim = [100, 200]\n')
    spec = load(spec_file)
    spec.hashes = content_hashes(spec.inputs)
    out = prepare_out(tmp_path / "out")
    _save_state(out, spec, {})  # the sweep as it started
    assert _load_state(out, spec)["inputs"] == {"logs/a.csv": spec.hashes["logs/a.csv"]}  # the same: resumes

    log.write_text("time,q,q_d,qd_d\n0,0.1,0,0\n")
    assert main(["sweep", str(spec_file), "--out", str(out), "--resume"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{out / 'sweep-state.json'}: inputs: logs/a.csv is not what the interrupted " \
                                    "sweep read" in err, err

    log.write_text("time,q,q_d,qd_d\n0,0,0,0\n")  # back as it was; but from another folder
    elsewhere = tmp_path / "elsewhere"
    (elsewhere / "logs").mkdir(parents=True)
    (elsewhere / "logs" / "a.csv").write_text("time,q,q_d,qd_d\n0,0.2,0,0\n")
    monkeypatch.chdir(elsewhere)
    assert main(["sweep", str(spec_file), "--out", str(out), "--resume"]) == 2
    assert "inputs: logs/a.csv is not what the interrupted sweep read" in capsys.readouterr().err
    # a sweep saved before it kept its inputs' hashes resumes, unchecked, and says so
    monkeypatch.chdir(tmp_path)
    state = json.loads((out / "sweep-state.json").read_text())
    del state["inputs"]
    (out / "sweep-state.json").write_text(json.dumps(state))
    assert _load_state(out, spec)["cells"] == state["cells"]
    assert "did not record its inputs' content" in capsys.readouterr().err


def test_force_never_clears_a_sweep_folder_that_holds_an_input(tmp_path, capsys):
    _ray()
    from wrenorm.runfolder import prepare_out

    out = prepare_out(tmp_path / "out")  # an earlier run's folder, where a reference was then put
    log = out / "log.csv"
    log.write_text("time,q,q_d,qd_d\n0,0,0,0\n")
    spec = _write(tmp_path, f'task = "fit pd"\n[options]\nreference = "{log}"\n')
    assert main(["sweep", str(spec), "--out", str(out), "--force"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"--out: holds an input of this command ({log})" in err, err
    assert log.exists()


@pytest.mark.parametrize("extra, message", [
    (["--cpus", "1", "--cpus-per-cell", "2"],
     "--cpus-per-cell: 2: a cell cannot hold more CPUs than the local Ray has (--cpus 1)"),
    (["--device", "cuda"], "--device: device: cuda requested but no CUDA device is available"),
])
def test_a_cell_the_local_ray_cannot_hold_is_refused_before_out_is_made(tmp_path, capsys, extra, message):
    _ray()
    if "cuda" in extra:
        from wrenorm.warp_init import init_warp

        if init_warp("cuda").is_cuda_available():
            pytest.skip("this machine has a CUDA device")
    spec = _write(tmp_path, 'task = "fit pd"\n[options]\nno-record = true\n')
    out = tmp_path / "out"
    assert main(["sweep", str(spec), "--out", str(out), *extra]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_a_lost_worker_is_recorded_and_the_other_cells_go_on(tmp_path):
    _ray()
    spec = _write(tmp_path, SPEC.replace("restarts = [0, 1]", ""))
    out = tmp_path / "out"
    proc = _sweep(spec, out, env={"WRENORM_TEST_SLOW_GENERATION": "0.4"}, wait=False)
    victim, below = None, []
    deadline = time.time() + 240
    try:
        while time.time() < deadline and proc.poll() is None and victim is None:
            below = sorted(set(below) | set(_descendants(proc.pid)))
            cells = [p for p in below if _cmdline(p).startswith("ray::run_cell")]
            if cells:
                time.sleep(1.0)  # into its fit
                victim = cells[0]
                os.kill(victim, signal.SIGKILL)
            time.sleep(0.1)
        stdout, stderr = proc.communicate(timeout=240)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        _end(p for p in below if "ray" in _cmdline(p))
    assert victim is not None
    assert proc.returncode == 3, stderr
    rows = _rows(out)
    assert [r["status"] for r in rows].count("failed") == 1 and [r["status"] for r in rows].count("done") == 2
    lost = next(r for r in rows if r["status"] == "failed")
    assert "worker lost" in lost["error"], lost


def test_a_cell_failing_on_a_malformed_file_names_it_in_the_table_and_the_others_go_on(tmp_path):
    _ray()
    bad = tmp_path / "trunc.npz"
    bad.write_bytes(ROPE_NPZ.read_bytes()[:1000])  # exists, so the spec passes; its cell fails
    spec = _write(tmp_path, f'task = "fit rope"\n[options]\ngenerations = 2\nno-record = true\n'
                            f'[axes]\nreference = [["{ROPE_NPZ}"], ["{bad}"]]\n')
    out = tmp_path / "out"
    proc = _sweep(spec, out)
    assert proc.returncode == 3, proc.stderr
    rows = _rows(out)
    assert [r["status"] for r in rows] == ["done", "failed"]
    reason = f"{bad}: file: is not a readable .npz archive"
    assert reason in rows[1]["error"], rows[1]
    assert reason in json.loads((out / "sweep.json").read_text())["cells"][1]["error"]
    assert reason in proc.stdout  # the summary at the end


def test_a_sweep_joins_a_running_cluster_with_address(tmp_path):
    """`ray start --head` on one machine, `--address` on the others: here both on this one (the head in a session of
    its own, ended by its process group)."""
    _ray()
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    ray_cli = str(Path(sys.executable).parent / "ray")
    env = dict(os.environ, RAY_USAGE_STATS_ENABLED="0")
    head = subprocess.Popen([ray_cli, "start", "--head", "--block", "--num-cpus", "2", "--port", str(port),
                             "--node-ip-address", "127.0.0.1", "--include-dashboard=false"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        started = []

        def watch():  # `ray start` says when the head is up; keep reading so that it never blocks on a full pipe
            for line in head.stdout:
                if "Ray runtime started" in line:
                    started.append(line)

        threading.Thread(target=watch, daemon=True).start()
        deadline = time.time() + 120
        while time.time() < deadline and not started and head.poll() is None:
            time.sleep(0.2)
        assert started, "ray start --head did not come up"
        spec = _write(tmp_path, 'task = "fit pd"\n[options]\nno-record = true\n[axes]\nf-sim = [100, 200]\n')
        out = tmp_path / "out"
        proc = subprocess.run([sys.executable, "-m", "wrenorm", "sweep", str(spec), "--out", str(out), "--address",
                               f"127.0.0.1:{port}", "--quiet"], env=env, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
        summary = json.loads((out / "sweep.json").read_text())
        assert summary["ray"]["address"] == f"127.0.0.1:{port}" and summary["counts"]["done"] == 2
    finally:
        below = _descendants(head.pid)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(head.pid, signal.SIGKILL)  # the head and everything it started: its own process group
        head.wait()
        _end(p for p in below if "ray" in _cmdline(p))


def test_nothing_at_the_address_is_one_line_and_exit_2(tmp_path, capsys):
    _ray()
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    spec = _write(tmp_path, 'task = "fit pd"\n')
    assert main(["sweep", str(spec), "--out", str(tmp_path / "out"), "--address", f"127.0.0.1:{port}"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--address" in err and "ray start --head" in err
    assert not (tmp_path / "out").exists()


def test_a_done_cells_warnings_are_in_the_table_and_equal_seeds_plot(tmp_path):
    """A cell whose coarse model diverged said so in its result.json, but sweep.csv showed it as done beside the others
    (a probe of stop 47): the fit's warnings are a column. Three seeds with one value: their mean can round a hair past
    them, and the plot's negative error bar ended a finished sweep in a traceback (the same probe)."""
    import numpy as np

    from wrenorm.sweep import table
    from wrenorm.sweep.spec import load
    from wrenorm.viz.sweep_plot import plot_sweep

    x = next(v for v in np.random.default_rng(0).uniform(0.01, 0.1, 1000) if np.mean([v, v, v]) > v)
    spec = load(_write(tmp_path, 'task = "fit pd"\nseeds = [0, 1, 2]\n[axes]\nf-sim = [100, 200]\n'))
    records = {c.id: {"status": "done"} for c in spec.cells}
    said = "the semi-implicit update at f_sim 100 Hz is unstable with the fitted values"
    results = {c.id: {"schema": "wrenorm.result/1", "loss": {"measured": 1.0, "fitted": 0.5},
                      "warnings": [said] if c.index == 0 else [],
                      "parameters": {"J": {"fitted": float(x), "std": 0.001, "frozen": False}}} for c in spec.cells}
    rows = table.build(spec, records, results)
    assert rows[0]["warnings"] == said and all(r["warnings"] == "" for r in rows[1:])
    table.write_csv(tmp_path / "sweep.csv", spec, rows)
    assert _rows(tmp_path)[0]["warnings"] == said
    assert plot_sweep(tmp_path / "sweep.png", spec, rows, ["J"]) is not False
    assert (tmp_path / "sweep.png").read_bytes()[:4] == b"\x89PNG"
    # a flow's points say theirs in one string, `warning` (the review of stop 47: the column stayed empty there)
    flow = {"points": [{"resolution": {"f_sim": 50}, "parameters": {}, "loss": {}, "warning": said},
                       {"resolution": {"f_sim": 100}, "parameters": {}, "loss": {}, "warning": None}]}
    assert [r["warnings"] for r in table.result_rows("flow", flow)] == [said, ""]


def test_a_sweep_folder_another_process_writes_is_refused_and_resume_force_too(tmp_path, capsys):
    """A second sweep on the same --out with --force while the first ran emptied the folder under it: both said "done"
    over a mix of the two (a probe of stop 47). The folder is held by the process writing it; --resume with --force is
    refused as `fit` refuses it."""
    _ray()
    spec = _write(tmp_path)
    out = tmp_path / "out"
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from wrenorm.runfolder import hold_folder; "
                               f"hold_folder({str(out)!r}); print('held', flush=True); time.sleep(60)"],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        for extra in (["--force"], ["--resume"]):
            assert main(["sweep", str(spec), "--out", str(out), *extra]) == 2
            err = capsys.readouterr().err
            assert err.count("\n") == 1 and "another wrenorm process is writing this folder now" in err, err
    finally:
        holder.kill()
        holder.wait()
    assert main(["sweep", str(spec), "--out", str(out), "--resume", "--force"]) == 2
    assert "--force: cannot go with --resume" in capsys.readouterr().err
    mine = tmp_path / "mine"  # not wrenorm's: refused, and nothing is left in it
    mine.mkdir()
    (mine / "notes.txt").write_text("x")
    assert main(["sweep", str(spec), "--out", str(mine), "--force"]) == 2
    assert "not written by wrenorm" in capsys.readouterr().err and sorted(os.listdir(mine)) == ["notes.txt"]


CORRECT_SPEC = """
task = "correct rope"
seeds = [0, 1]

[options]
real = "coarse"
max-trials = 2
no-record = true
params = ["measured", "fitted"]
"""


def test_a_correction_sweep_tabulates_each_arms_outcome_as_its_run_wrote_it(tmp_path):
    """A sweep of `correct rope` cells gave a table of the result's top-level numbers (tolerance, max_trials, ...)
    and none of what the runs did: a campaign run as a sweep could not be read from it. Each arm is a row now, with
    the trials to the tolerance as the campaign counts them, and the sweep counts the runs reached per arm. The real
    rope is the coarse chain here (`--real coarse`): seconds, not minutes."""
    _ray()
    spec, out = _write(tmp_path, CORRECT_SPEC), tmp_path / "out"
    proc = _sweep(spec, out)
    assert proc.returncode == 0, proc.stderr
    rows = _rows(out)
    assert [(r["seed"], r["arm"]) for r in rows] == [("0", "measured"), ("0", "fitted"), ("1", "measured"),
                                                     ("1", "fitted")]
    for r in rows:
        mine = json.loads((out / "cells" / r["cell"] / "correct.json").read_text())
        run = mine["runs"][r["arm"]]
        want = run["trials_to_tolerance"] if run["success"] else mine["max_trials"] + 1
        assert int(r["trials"]) == want and r["reached"] == str(run["success"])
        assert float(r["best_error"]) == run["best_error"]
        assert float(r["first_trial_error"]) == run["trials"][0]["error"]
        assert r["resolution"] == "segments=10;dt=0.005" and r["status"] == "done"
    assert (out / "sweep.png").read_bytes()[:4] == b"\x89PNG" and f"plot: {out / 'sweep.png'}" in proc.stdout
    summary = json.loads((out / "sweep.json").read_text())["summary"]
    for arm in ("measured", "fitted"):
        mine = [r for r in rows if r["arm"] == arm]
        reached = sum(r["reached"] == "True" for r in mine)
        assert any(line.startswith(f"{arm}: reached the tolerance in {reached} of 2 runs") for line in summary), summary
    # the cell is the command: a separate `correct rope` with the cell's options and seed tried the same commands
    direct = tmp_path / "direct"
    assert main(["correct", "rope", "--real", "coarse", "--max-trials", "2", "--no-record", "--quiet", "--params",
                 "measured", "fitted", "--seed", "0", "--out", str(direct)]) == 0
    theirs = json.loads((direct / "correct.json").read_text())["runs"]
    mine = json.loads((out / "cells" / rows[0]["cell"] / "correct.json").read_text())["runs"]
    for arm in ("measured", "fitted"):
        assert [t["command_u"] for t in mine[arm]["trials"]] == [t["command_u"] for t in theirs[arm]["trials"]]
        assert [t["error"] for t in mine[arm]["trials"]] == [t["error"] for t in theirs[arm]["trials"]]


@pytest.mark.filterwarnings("ignore:No artists with labels")  # errorbar is replaced by a recorder of its lines
def test_a_correction_sweeps_plot_and_recording_draw_each_arms_trials_against_the_axes(tmp_path, monkeypatch):
    """A correction sweep drew no sweep.png (the plot knew only fitted parameters): each arm is now a line of trials
    and best error against the swept axes, and a series of its own in the recording."""
    import matplotlib

    from wrenorm.sweep import table
    from wrenorm.sweep.spec import load
    from wrenorm.viz import sweep_plot

    spec = load(_write(tmp_path, 'task = "correct rope"\nseeds = [0, 1]\n[options]\nno-record = true\n'
                                 '[axes]\nvariant = ["stiff", "soft"]\n'))
    records = {c.id: {"status": "done"} for c in spec.cells}
    trials = {"measured": [4, 11, 6, 7], "fitted": [3, 5, 11, 2]}
    results = {c.id: {"tolerance": 0.05, "max_trials": 10, "runs": {
        arm: {"success": n[c.index] <= 10, "trials_to_tolerance": n[c.index] if n[c.index] <= 10 else None,
              "best_error": 0.01 * n[c.index], "trials": [{"error": 0.3}]} for arm, n in trials.items()}}
        for c in spec.cells}
    names, part = table.plotted(spec, results)
    assert (names, part) == (["trials", "best_error"], "arm")
    rows = table.build(spec, records, results)
    drawn = []
    monkeypatch.setattr(matplotlib.axes.Axes, "errorbar",
                        lambda ax, x, y, **kw: drawn.append((ax.get_xlabel() or None, kw.get("label"), list(y))))
    assert sweep_plot.plot_sweep(tmp_path / "sweep.png", spec, rows, names, part)
    assert (tmp_path / "sweep.png").read_bytes()[:4] == b"\x89PNG"
    # first panel: trials against the variant, one line per arm, each point the mean over the two seeds
    assert drawn[0][1:] == ("arm=measured", [(4 + 11) / 2, (6 + 7) / 2])
    assert drawn[1][1:] == ("arm=fitted", [(3 + 5) / 2, (11 + 2) / 2])
    logged = []
    from wrenorm.viz import record

    if record.rerun_available():
        monkeypatch.setattr(record.Recorder, "log_scalar",
                            lambda self, path, k, v, timeline=None: logged.append((path, k, v)))
        assert sweep_plot.record_sweep(tmp_path / "recording.rrd", spec, rows, names, part)
        assert ("sweep/parameters/trials/fitted", 3, 2.0) in logged  # the fourth cell (soft, seed 1), its arm fitted
        assert ("sweep/parameters/best_error/measured", 0, 0.04) in logged


def test_a_commands_own_columns_keep_off_the_axes_and_other_commands_keep_their_numbers():
    from wrenorm.sweep import table

    result = {"schema": "wrenorm.correct/1", "tolerance": 0.05, "max_trials": 10,
              "model": {"segments": 10, "dt": 0.005},
              "runs": {"measured": {"success": False, "trials_to_tolerance": None, "best_error": 0.08, "best_trial": 3,
                                    "trials_used": 10, "trials": [{"error": 0.3}]}}}
    row, = table.result_rows("correct", result, axes=("arm",), system="rope")
    assert row["result_arm"] == "measured" and "arm" not in row and row["trials"] == 11 and row["reached"] is False
    assert row["first_trial_error"] == 0.3 and row["last_floor"] is None
    # a command without its own rows: the result's top-level numbers and strings, as before
    assert table.result_rows("sensitivity", {"schema": "s", "directions": 5, "nested": {}}, system="rope") == \
        [{"directions": 5}]


@pytest.mark.parametrize("name, task, cells", [("sweep-pd.toml", "fit pd", None), ("sweep-rope.toml", "fit rope", 8),
                                               ("sweep-swimmer.toml", "fit swimmer", None),
                                               ("sweep-correct-rope.toml", "correct rope", 21)])
def test_the_example_specs_load_with_the_commands_own_parsers(name, task, cells, monkeypatch):
    from wrenorm.sweep.spec import load

    monkeypatch.chdir(ROOT)  # their paths, if any, are relative to the checkout
    spec = load(EXAMPLES / name)
    assert spec.task == task and spec.cells
    assert cells is None or len(spec.cells) == cells


def test_a_sweep_state_that_is_not_a_sweeps_is_one_line_on_resume(finished, tmp_path):
    """A sweep-state.json holding a list, a null or a string record had ended in an AttributeError (review of stop
    54)."""
    _, ref, _ = finished
    for i, text in enumerate(("[]", '{"records": null}', '{"records": {"a": "done"}}')):
        out = tmp_path / f"copy{i}"
        shutil.copytree(ref, out)
        (out / "sweep-state.json").write_text(text)
        proc = _sweep(out / "spec.toml", out, "--resume")
        assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr, proc.stderr
        assert "sweep-state.json: records: not a sweep's state" in proc.stderr


def test_an_empty_part_of_a_list_path_is_skipped_as_the_command_skips_it(tmp_path):
    """`--reference a.npz,` and ["a.npz", ""] parse to a.npz on the command line; the spec check had refused them
    (review of stop 54's change). A value with no path at all is still refused."""
    from wrenorm.sweep.spec import load

    for value in (f'"{ROPE_NPZ},"', f'["{ROPE_NPZ}", ""]'):
        spec = _write(tmp_path, f'task = "fit rope"\n[options]\nreference = {value}\ngenerations = 1\n')
        assert [str(ROPE_NPZ)] == load(spec).inputs
