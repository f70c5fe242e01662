"""Interrupted fits resume to the same answer; same seed, same bits; runs are never clobbered."""
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from wrenorm.cli import main

FIT = ["fit", "pd", "--search", "cmaes", "--quiet", "--no-record", "--generations", "25", "--seed", "7"]


def _fitted(out):
    r = json.loads((out / "result.json").read_text())
    return {k: v["fitted"] for k, v in r["parameters"].items()}


def test_same_seed_gives_bit_identical_parameters(tmp_path):
    assert main([*FIT, "--out", str(tmp_path / "a")]) == 0
    assert main([*FIT, "--out", str(tmp_path / "b")]) == 0
    assert _fitted(tmp_path / "a") == _fitted(tmp_path / "b")
    assert main([*FIT[:-1], "8", "--out", str(tmp_path / "c")]) == 0
    assert _fitted(tmp_path / "a") != _fitted(tmp_path / "c")


def test_kill_9_then_resume_matches_uninterrupted_run(tmp_path):
    ref, out = tmp_path / "ref", tmp_path / "killed"
    assert main([*FIT, "--out", str(ref)]) == 0
    env = dict(os.environ, WRENORM_TEST_SLOW_GENERATION="0.4")
    proc = subprocess.Popen([sys.executable, "-m", "wrenorm", *FIT, "--out", str(out)], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    log = out / "search_log.jsonl"
    deadline = time.time() + 120
    gens = 0
    while time.time() < deadline:
        if log.exists():
            gens = log.read_text().count("\n") - 1  # lines after the header
            if gens >= 4:
                break
        time.sleep(0.1)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert 4 <= gens < 25
    assert not (out / "result.json").exists()  # nothing left looking complete
    assert main([*FIT, "--out", str(out), "--resume"]) == 0
    assert _fitted(out) == _fitted(ref)


def test_resume_drops_a_torn_last_line_and_matches_the_uninterrupted_run(tmp_path):
    """What a kill in the middle of appending a generation leaves: the log up to generation 5 and half a line."""
    ref, out = tmp_path / "ref", tmp_path / "torn"
    assert main([*FIT, "--out", str(ref)]) == 0
    assert main([*FIT, "--out", str(out)]) == 0
    (out / "result.json").unlink()
    lines = (out / "search_log.jsonl").read_text().splitlines(keepends=True)
    assert len(lines) == 1 + 25 and all(line.endswith("\n") for line in lines)
    (out / "search_log.jsonl").write_text("".join(lines[:6]) + lines[6][: len(lines[6]) // 2])
    assert main([*FIT, "--out", str(out), "--resume"]) == 0
    assert _fitted(out) == _fitted(ref)
    assert (out / "search_log.jsonl").read_text() == (ref / "search_log.jsonl").read_text()


def test_existing_run_is_not_overwritten_without_force(tmp_path, capsys):
    out = tmp_path / "run"
    assert main([*FIT, "--out", str(out)]) == 0
    before = (out / "result.json").read_bytes()
    assert main([*FIT, "--out", str(out)]) == 2
    assert "--force" in capsys.readouterr().err
    assert (out / "result.json").read_bytes() == before
    assert main([*FIT, "--out", str(out), "--force"]) == 0


def test_resume_without_state_is_a_clear_error(tmp_path, capsys):
    assert main([*FIT, "--out", str(tmp_path / "nothing"), "--resume"]) == 2
    assert "no such run folder" in capsys.readouterr().err
    out = tmp_path / "run"
    assert main([*FIT, "--out", str(out)]) == 0
    (out / "search_log.jsonl").rename(out / "search_state.json")  # what an earlier wrenorm left
    assert main([*FIT, "--out", str(out), "--resume"]) == 2
    assert "earlier wrenorm" in capsys.readouterr().err
    (out / "search_state.json").unlink()
    assert main([*FIT, "--out", str(out), "--resume"]) == 2
    assert "search_log.jsonl" in capsys.readouterr().err
    (out / "sub").mkdir()  # an earlier multi-problem fit kept its state in a sub-run's folder
    (out / "sub" / "search_state.json").write_text("{}")
    assert main([*FIT, "--out", str(out), "--resume"]) == 2
    assert "earlier wrenorm" in capsys.readouterr().err


def test_resume_reads_a_log_with_crlf_line_ends_and_a_lone_cr_tail(tmp_path):
    """Line ends as a text editor or a copy might leave them: each line is the bytes up to a newline, and a last
    line without one (here a lone carriage return at its end) is a torn tail, cut before the resumed run appends."""
    ref, out = tmp_path / "ref", tmp_path / "crlf"
    assert main([*FIT, "--out", str(ref)]) == 0
    assert main([*FIT, "--out", str(out)]) == 0
    (out / "result.json").unlink()
    lines = (out / "search_log.jsonl").read_text().splitlines()
    (out / "search_log.jsonl").write_bytes(("\r\n".join(lines[:5]) + "\r\n" + lines[5] + "\r").encode())
    assert main([*FIT, "--out", str(out), "--resume"]) == 0
    assert _fitted(out) == _fitted(ref)
    parsed = [[json.loads(line) for line in (d / "search_log.jsonl").read_text().splitlines()] for d in (out, ref)]
    assert parsed[0] == parsed[1]  # every generation on disk once, in order


def test_every_candidate_blowing_up_says_so():
    from wrenorm import search
    from wrenorm.errors import AllCandidatesFailed
    from wrenorm.tasks.pd.problem import PDProblem

    class Exploding(PDProblem):
        def errors(self, values, conditions):
            return np.full((len(values), len(conditions)), np.nan)

        def residuals(self, values, conditions):
            return np.full((len(values), 3), np.nan)

    with pytest.raises(AllCandidatesFailed, match="every one of"):
        search.cmaes(Exploding(100.0), generations=3, quiet=True)


def test_the_search_times_its_evaluations_apart_from_its_own_work(tmp_path):
    """search_evaluating_s (result.json timing) is the time spent in the batched evaluations: with every evaluation
    made 20 ms slower it grows by at least 20 ms a generation, and it stays within the search's wall time."""
    from wrenorm import search
    from wrenorm.tasks.pd.problem import PDProblem

    class Slow(PDProblem):
        def errors(self, values, conditions):
            time.sleep(0.02)
            return super().errors(values, conditions)

        def residuals(self, values, conditions):  # what the search's loss reads for a least-squares problem
            time.sleep(0.02)
            return super().residuals(values, conditions)

    t = time.perf_counter()
    slow = search.cmaes(Slow(100.0), generations=10, quiet=True)
    wall = time.perf_counter() - t
    assert 10 * 0.02 <= slow.evaluation_s < wall
    assert main([*FIT, "--out", str(tmp_path / "a")]) == 0
    timing = json.loads((tmp_path / "a" / "result.json").read_text())["timing"]
    assert 0 < timing["search_evaluating_s"] < timing["search_s"]


def test_blowups_are_counted_not_fatal():
    from wrenorm import search
    from wrenorm.tasks.pd.problem import PDProblem

    class Flaky(PDProblem):
        def errors(self, values, conditions):
            e = super().errors(values, conditions)
            e[::3] = np.inf  # a third of the candidates blow up
            return e

        def residuals(self, values, conditions):
            r = super().residuals(values, conditions)
            r[::3] = np.nan
            return r

    r = search.cmaes(Flaky(100.0), generations=5, popsize=12, quiet=True)
    assert r.blowups == 5 * 4
    assert np.isfinite(r.best_loss)
