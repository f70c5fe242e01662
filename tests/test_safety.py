"""Nothing the user made is lost, and nonsense does not pass in silence: owned run folders, refused resumes with
changed settings or inputs, range-checked options (property-based), plausibility checks on data, one-line
errors, Ctrl-C, and no Warp CUDA line on a machine without a GPU."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from wrenorm.cli import build_parser, main
from wrenorm.system import systems

JOINT = ["--J", "0.05", "--K-P", "20", "--K-D", "0.5"]  # the built-in joint that made the logs

PD = ["fit", "pd", "--quiet", "--no-record", "--f-sim", "50", *JOINT]


def _one_line_error(capsys, *needles):
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for n in needles:
        assert n in err, (n, err)
    return err


def test_force_never_clears_a_folder_wrenorm_did_not_write(tmp_path, capsys):
    data = tmp_path / "mydata"
    data.mkdir()
    (data / "capture.npz").write_bytes(b"precious")
    assert main([*PD, "--out", str(data), "--force"]) == 2
    _one_line_error(capsys, "--force", "not written by wrenorm")
    assert (data / "capture.npz").read_bytes() == b"precious"


def test_force_clears_only_a_marked_run_and_never_one_holding_an_input(tmp_path, capsys):
    run = tmp_path / "run"
    assert main([*PD, "--out", str(run)]) == 0
    assert (run / ".wrenorm-run").is_file()
    log = run / "log.csv"  # an input put inside an old run folder
    t = np.arange(400) * 0.01
    rows = ["time,q,q_d,qd_d"] + [f"{a},{0.1 * np.sin(a)},{0.1 * np.sin(a + 0.1)},{0.1 * np.cos(a)}" for a in t]
    log.write_text("\n".join(rows))
    assert main([*PD, "--reference", str(log), "--out", str(run), "--force"]) == 2
    _one_line_error(capsys, "holds an input")
    assert log.exists()
    assert main([*PD, "--out", str(run), "--force"]) == 0  # an owned run folder is cleared


def test_force_never_clears_the_working_directory(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main([*PD, "--out", "."]) == 0 or True  # an empty working directory becomes a run
    (tmp_path / "keep.txt").write_text("mine")
    assert main([*PD, "--out", ".", "--force"]) == 2
    _one_line_error(capsys, "working directory")
    assert (tmp_path / "keep.txt").exists()


def test_a_rejected_command_writes_nothing_into_out(tmp_path, capsys):
    out = tmp_path / "run"
    assert main([*PD, "--out", str(out)]) == 0
    before = sorted(p.name for p in out.iterdir())
    assert main([*PD, "--out", str(out), "--force", "--J", "-1"]) == 2
    assert sorted(p.name for p in out.iterdir()) == before


def test_resume_refuses_changed_settings_and_inputs(tmp_path, capsys):
    out = tmp_path / "run"
    log = tmp_path / "log.csv"
    t = np.arange(400) * 0.01
    log.write_text("\n".join(["time,q,q_d,qd_d"] + [f"{a},{0.1 * np.sin(3 * a)},{0.1 * np.sin(3 * a + 0.2)},0"
                                                     for a in t]))
    base = [*PD, "--search", "cmaes", "--generations", "3", "--reference", str(log), "--out", str(out)]
    assert main(base) == 0
    assert main([*base, "--resume", "--J", "0.1"]) == 2
    _one_line_error(capsys, "system_options")
    lines = log.read_text().splitlines()
    lines[5] = lines[5].split(",")[0] + ",0.123,0.0,0"  # the same file name, one sample changed
    log.write_text("\n".join(lines))
    assert main([*base, "--resume"]) == 2
    _one_line_error(capsys, "inputs")


def test_tampered_state_is_refused_in_one_line(tmp_path, capsys):
    out = tmp_path / "run"
    cmd = [*PD, "--search", "cmaes", "--generations", "4", "--out", str(out)]
    assert main(cmd) == 0
    log = out / "search_log.jsonl"
    lines = log.read_text().splitlines()
    generation = json.loads(lines[2])
    generation["told"][0][1] = "f" * 16  # search 0's candidates in generation 1
    log.write_text("\n".join([*lines[:2], json.dumps(generation), *lines[3:]]) + "\n")
    assert main([*cmd, "--resume"]) == 2
    _one_line_error(capsys, "search_log.jsonl", "other candidates")
    generation["told"][0][0] = -1  # a search that does not exist
    log.write_text("\n".join([*lines[:2], json.dumps(generation), *lines[3:]]) + "\n")
    assert main([*cmd, "--resume"]) == 2
    _one_line_error(capsys, "search_log.jsonl", "search -1")
    log.write_text("\n".join([*lines[:2], "{not json", *lines[3:]]) + "\n")
    assert main([*cmd, "--resume"]) == 2
    _one_line_error(capsys, "search_log.jsonl", "line 3")
    log.write_text("{not json\n")
    assert main([*cmd, "--resume"]) == 2
    _one_line_error(capsys, "search_log.jsonl", "line 1")


def _numeric_options(system: str) -> list[tuple[str, object]]:
    """(flag, the action's type) for every option of `fit system` that takes a number."""
    parser = build_parser(["fit", system])
    sub = next(a for a in parser._actions if a.dest == "command").choices["fit"]
    sys_parser = next(a for a in sub._actions if a.dest == "system").choices[system]
    return [(a.option_strings[0], a) for a in sys_parser._actions
            if a.option_strings and getattr(a.type, "__name__", "") in ("number", "integer")]


@pytest.mark.parametrize("system", list(systems()))  # every registered system, a new one too
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_every_numeric_option_rejects_nonsense_in_one_line(tmp_path_factory, system, data):
    options = _numeric_options(system)
    assert len(options) >= 5
    flag, _ = data.draw(st.sampled_from(options))
    bad = data.draw(st.sampled_from(["nan", "inf", "-inf", "1e300", "-1e300", "abc", "", "1,2"]))
    out = tmp_path_factory.mktemp("o") / "run"
    proc_err = []

    class Capture:
        def write(self, s):
            proc_err.append(s)

        def flush(self):
            pass

    old = sys.stderr
    sys.stderr = Capture()
    try:
        rc = main(["fit", system, "--out", str(out), flag, bad])
    finally:
        sys.stderr = old
    err = "".join(proc_err)
    assert rc == 2, (flag, bad)
    assert err.count("\n") == 1 and flag in err and "Traceback" not in err, err
    assert not out.exists()


def test_lists_take_commas_or_spaces_and_refuse_repeats(tmp_path, capsys):
    a = build_parser(["fit", "pd"]).parse_args(["fit", "pd", "--f-sim", "200,400"])
    b = build_parser(["fit", "pd"]).parse_args(["fit", "pd", "--f-sim", "200", "400"])
    assert a.f_sim == b.f_sim == [200.0, 400.0]
    assert main(["fit", "pd", "--f-sim", "100", "100", "--out", str(tmp_path / "r")]) == 2
    _one_line_error(capsys, "--f-sim", "repeated")


@pytest.mark.parametrize("body,field", [
    ("\n".join(["time,q,q_d,qd_d"] + [f"{i * 10},{np.sin(i / 10)},{np.sin(i / 10)},0" for i in range(100)]), "time"),
    ("\n".join(["time,q,q_d,qd_d"] + [f"{i * 0.01},0,0,0" for i in range(100)]), "q"),
    ("\n".join(["time,q,q_d,qd_d"] + [f"{i * 0.01},{90 * np.sin(i / 10)},0.1,0" for i in range(100)]), "q"),
])
def test_pd_logs_that_parse_but_mean_nothing_are_refused(tmp_path, capsys, body, field):
    f = tmp_path / "log.csv"
    f.write_text(body)
    assert main([*PD, "--reference", str(f), "--out", str(tmp_path / "r")]) == 2
    _one_line_error(capsys, str(f), field)


def test_a_fish_that_does_not_swim_forward_is_refused(tmp_path, capsys):
    from wrenorm.tasks.swimmer import data as sd

    for r in sd.load_builtin():
        px = r.markers[::-1] / (sd.HEAD_MARKER_DISTANCE / 100.0)  # the clip played backwards: tail first
        name = "markers_f" + f"{r.label:.2f}".replace(".", "_") + ".csv"
        np.savetxt(tmp_path / name, px.reshape(len(px), -1), delimiter=",")
    assert main(["fit", "swimmer", "--data", str(tmp_path), "--out", str(tmp_path / "r")]) == 2
    _one_line_error(capsys, "does not move forward")


def test_each_rope_reference_keeps_its_own_clock():
    """A reference whose clock starts at 5 s scores exactly as the same throw starting at 0."""
    from dataclasses import replace

    from wrenorm.tasks.rope.problem import RopeProblem
    from wrenorm.tasks.rope.reference.generate import builtin_reference_path, load_reference

    a = load_reference(builtin_reference_path("flick"))
    b = replace(a, time=a.time + 5.0)
    pa = RopeProblem([a, load_reference(builtin_reference_path("flick_fast"))], segments=6)
    pb = RopeProblem([b, load_reference(builtin_reference_path("flick_fast"))], segments=6)
    v = pa.space.measured[None]
    np.testing.assert_allclose(pa.errors(v, pa.train), pb.errors(v, pb.train), rtol=1e-9)


def _run(args, **kw):
    env = dict(os.environ, RERUN_ANALYTICS="0")
    return subprocess.run([sys.executable, "-m", "wrenorm", *args], capture_output=True, text=True, env=env, **kw)


def test_no_warp_cuda_line_without_a_gpu(tmp_path):
    proc = _run([*PD, "--out", str(tmp_path / "r")])
    assert proc.returncode == 0
    assert "CUDA" not in proc.stderr and "Warp" not in proc.stderr and "Warp" not in proc.stdout, proc.stderr
    bad = _run(["fit", "pd", "--generations", "0", "--out", str(tmp_path / "b")])
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "CUDA" not in bad.stderr


@pytest.mark.parametrize("sig,code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_ctrl_c_stops_within_a_second_with_130_and_the_run_resumes(tmp_path, sig, code):
    """Ctrl-C, and SIGTERM (a scheduler's or `timeout`'s stop, which ended the run without the resume line)."""
    out = tmp_path / "run"
    args = ["fit", "rope", "--search", "cmaes", "--generations", "400", "--segments", "6", "--no-record", "--out",
            str(out)]
    env = dict(os.environ, RERUN_ANALYTICS="0", WRENORM_TEST_SLOW_GENERATION="0.05")
    proc = subprocess.Popen([sys.executable, "-m", "wrenorm", *args], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    log = out / "search_log.jsonl"
    deadline = time.time() + 120
    while time.time() < deadline and not (log.exists() and log.read_text().count("\n") >= 2):  # a generation done
        time.sleep(0.05)
    time.sleep(0.3)
    proc.send_signal(sig)
    t0 = time.time()
    rc = proc.wait(timeout=30)
    assert rc == code and time.time() - t0 < 1.5 + 0.5  # the watchdog's second, plus interpreter exit
    assert "--resume" in proc.stderr.read()
    generations = log.read_text().count("\n") - 1  # lines after the header
    assert 0 < generations < 400
    assert main([*args[:-2], "--generations", "400", "--quiet", "--resume", "--out", str(out)]) == 0
    assert json.loads((out / "result.json").read_text())["search"]["generations"] >= generations


def test_os_errors_are_one_line(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main([*PD, "--out", str(blocker / "run")]) == 2
    _one_line_error(capsys, "--out")
    Path(tmp_path / "dir.csv").mkdir()
    assert main([*PD, "--reference", str(tmp_path / "dir.csv"), "--out", str(tmp_path / "r2")]) == 2
    _one_line_error(capsys, "dir.csv")


def test_reference_rope_never_replaces_a_file_without_force(tmp_path, capsys):
    from wrenorm.cli import main

    precious = tmp_path / "capture.npz"
    precious.write_bytes(b"someone's motion capture")
    assert main(["reference", "rope", "--out", str(precious)]) == 2
    assert precious.read_bytes() == b"someone's motion capture"
    _one_line_error(capsys, str(precious), "--force")
    assert main(["reference", "rope", "--out", str(tmp_path / "x.csv")]) == 2
    _one_line_error(capsys, ".npz")
    # a place it cannot write is found before the throw is simulated, not after
    assert main(["reference", "rope", "--out", str(precious / "sub" / "x.npz")]) == 2
    _one_line_error(capsys, "not a writable folder")


def test_resume_and_force_together_are_refused_and_an_empty_reference_is_not_the_built_in(tmp_path, capsys):
    """--resume keeps a run folder and --force empties it: given both, neither is guessed. An empty --reference
    (an unset shell variable) fitted the built-in reference in silence."""
    run = tmp_path / "run"
    assert main([*PD, "--out", str(run)]) == 0
    before = (run / "result.json").read_bytes()
    capsys.readouterr()
    assert main([*PD, "--out", str(run), "--resume", "--force"]) == 2
    _one_line_error(capsys, "--force", "--resume")
    assert (run / "result.json").read_bytes() == before
    assert main([*PD, "--reference", "", "--out", str(tmp_path / "empty")]) == 2
    _one_line_error(capsys, "--reference", "empty")
    assert not (tmp_path / "empty").exists()


def test_cma_settings_under_least_squares_are_said_to_be_unused(tmp_path, capsys):
    """fit pd searches by least squares: --generations and --popsize changed nothing, in silence."""
    assert main([*PD, "--generations", "1", "--popsize", "4", "--out", str(tmp_path / "r")]) == 0
    err = capsys.readouterr().err
    assert "--generations, --popsize" in err and "least-squares" in err
    assert main([*PD, "--out", str(tmp_path / "q")]) == 0
    assert "CMA-ES settings" not in capsys.readouterr().err


def test_a_resume_after_the_code_changed_is_refused(tmp_path, capsys, monkeypatch):
    """The sources a fit's numbers come from are part of what a resume must share (options, inputs, versions)."""
    import wrenorm.cli

    cmd = ["fit", "rope", "--search", "cmaes", "--generations", "2", "--segments", "6", "--no-record", "--quiet",
           "--out", str(tmp_path / "r")]
    assert main(cmd) == 0
    (tmp_path / "r" / "result.json").unlink()  # as if interrupted after its search log
    monkeypatch.setattr(wrenorm.cli, "code_digest", lambda system: "0" * 64)
    assert main([*cmd, "--resume"]) == 2
    assert ": code: wrenorm's sources" in capsys.readouterr().err
    # a run saved before the digest existed resumes as before
    log = tmp_path / "r" / "search_log.jsonl"
    lines = log.read_text().splitlines()
    head = json.loads(lines[0])
    found = [k for k in ("settings", "identity") if isinstance(head.get(k), dict) and "code" in head[k]]
    assert found, head.keys()
    del head[found[0]]["code"]
    log.write_text("\n".join([json.dumps(head), *lines[1:]]) + "\n")
    assert main([*cmd, "--resume"]) == 0


def test_a_resumed_multi_rate_fit_checks_its_finished_rates_and_its_resolutions(tmp_path, capsys):
    """A fit at two rates resumed with another --K-D had reused the finished rates' results made with the old one, and
    one resumed at another --f-sim had started a new fit over the folder's combined result; a cut-short result of a
    finished rate ended in a traceback (review of stop 54). Each is one line, exit 2; the same resume still works."""
    import shutil

    base = ["fit", "pd", "--quiet", "--no-record", "--f-sim", "50,100", "--search", "least-squares"]
    out = tmp_path / "multi"
    assert main([*base, "--out", str(out)]) == 0
    capsys.readouterr()
    assert main([*base, "--out", str(out), "--resume", "--K-D", "0.9"]) == 2
    _one_line_error(capsys, "f_sim50", "search_log.jsonl", "K_D")
    other = ["fit", "pd", "--quiet", "--no-record", "--f-sim", "200", "--search", "least-squares"]
    assert main([*other, "--out", str(out), "--resume"]) == 2
    _one_line_error(capsys, "--resume", "f_sim100, f_sim50", "this one at f_sim200")
    cut = tmp_path / "cut"
    shutil.copytree(out, cut)
    result = cut / "f_sim50" / "result.json"
    result.write_text(result.read_text()[:200])
    assert main([*base, "--out", str(cut), "--resume"]) == 2
    _one_line_error(capsys, "f_sim50", "result.json", "cannot be read back")
    assert main([*base, "--out", str(out), "--resume"]) == 0


def test_a_second_process_on_a_run_folder_in_use_is_refused(tmp_path, capsys):
    """Every command holds its --out while it runs (sweeps did already): a fit resumed while it still ran had written
    each generation twice into its search log, and the state was lost (review of stop 54)."""
    out = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from wrenorm.runfolder import prepare_out; "
                               "prepare_out(sys.argv[1]); print('held', flush=True); time.sleep(60)", str(out)],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        assert main([*PD, "--out", str(out), "--force"]) == 2
        _one_line_error(capsys, "--out", "another wrenorm process is writing this folder")
    finally:
        holder.kill()
        holder.wait()
    assert main([*PD, "--out", str(out), "--force"]) == 0


def test_a_commands_hold_on_its_folder_ends_with_the_command(tmp_path):
    """A fit run in this process (a notebook, a sweep worker's cell) had kept its folder from every later process
    until this one exited (review of stop 54's change)."""
    out = tmp_path / "run"
    assert main([*PD, "--out", str(out)]) == 0
    again = subprocess.run([sys.executable, "-m", "wrenorm", *PD, "--out", str(out), "--force"], capture_output=True,
                           text=True)
    assert again.returncode == 0, again.stderr
