"""The bench command writes its results file and table; bad batch sizes are refused."""
import json

from wrenorm.cli import main


def test_bench_writes_results_and_table(tmp_path):
    out = tmp_path / "bench"
    rc = main(["bench", "--quick", "--no-fits", "--no-cuda-build", "--only", "rope", "pd", "--batches", "256",
               "--out", str(out)])
    assert rc == 0
    res = json.loads((out / "results.json").read_text())
    rope = [r for r in res["rope"] if not r.get("comparison") and not r.get("task_level")]
    assert {r["n_nodes"] for r in rope} == {8, 16, 32}
    task = [r for r in res["rope"] if r.get("task_level")]
    assert len(task) == 1 and task[0]["candidates"] == 240 and 0 < task[0]["fraction_of_kernel"] <= 1.0
    variants = {r["variant"] for r in res["rope"] if r.get("comparison")}
    assert {"culled", "allpairs", "scalar", "numpy", "torch"} <= variants
    for r in res["rope"]:
        assert r["chain_steps_per_s"] > 0 and r["kernel_chain_steps_per_s"] >= r["chain_steps_per_s"] * 0.99
    assert res["pd"][0]["joint_steps_per_s"] > 0 and res["pd"][1]["series"] == "joint, start fitted"
    assert res["pd"][1]["joint_steps_per_s"] > 0
    table = (out / "results.md").read_text()
    assert "x numpy" in table and "PD joint" in table and "Rope task-level" in table
    assert (out / "results.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bench_refuses_nonpositive_batches(tmp_path, capsys):
    rc = main(["bench", "--quick", "--no-fits", "--no-cuda-build", "--only", "pd", "--batches", "0",
               "--out", str(tmp_path / "b")])
    assert rc == 2
    assert "--batches" in capsys.readouterr().err
    # a batch no machine holds, and an --out that is a file: refused before anything runs
    assert main(["bench", "--no-fits", "--only", "pd", "--batches", "1000000000000", "--out", str(tmp_path / "b")]) == 2
    assert "--batches" in capsys.readouterr().err
    (tmp_path / "f").write_text("x")
    assert main(["bench", "--no-fits", "--only", "pd", "--out", str(tmp_path / "f")]) == 2
    assert "--out" in capsys.readouterr().err and (tmp_path / "f").read_text() == "x"
    # a repeated batch or system gave duplicate rows and tables; an unknown system, a word for a batch: one line
    for bad in (["--batches", "256", "256"], ["--only", "pd", "pd"], ["--only", "fish"], ["--batches", "abc"]):
        assert main(["bench", "--no-fits", "--no-cuda-build", "--out", str(tmp_path / "b2"), *bad]) == 2
        err = capsys.readouterr().err
        assert bad[0] in err and len(err.strip().splitlines()) == 1, err


def test_bench_keeps_earlier_results_without_force(tmp_path, capsys):
    """A quick run into a folder holding measured tables is refused before it runs; --force replaces them."""
    out = tmp_path / "b"
    out.mkdir()
    (out / "results.md").write_text("measured")
    args = ["bench", "--quick", "--no-fits", "--no-cuda-build", "--only", "pd", "--batches", "256", "--out", str(out)]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "results.md" in err and "--force" in err and (out / "results.md").read_text() == "measured"
    assert main([*args, "--force"]) == 0
    assert "PD joint" in (out / "results.md").read_text()


def test_gpu_script_runs_from_the_repository_root_on_the_installed_layout(tmp_path):
    """bench/gpu.sh lays the package out as installed and runs it from outside the checkout (tried here on the
    CPU: WRENORM_BENCH_DEVICE=cpu)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    env = dict(os.environ, WRENORM_BENCH_DEVICE="cpu", OUT=str(tmp_path), PYTHON=sys.executable, RERUN_ANALYTICS="0")
    r = subprocess.run(["bash", "bench/gpu.sh", "--quick", "--no-fits", "--no-cuda-build", "--only", "pd",
                        "--batches", "256"], cwd=repo, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    line = next(x for x in r.stderr.splitlines() if x.startswith("wrenorm.kernels from"))
    assert "/tmp/wrenorm-src." in line and "/wrenorm/kernels/" in line  # the laid-out copy, not the checkout
    assert (tmp_path / "bench" / "results.json").exists()


def test_a_gpu_fit_row_holds_its_ratios_against_the_cpu_default_on_two_cores(monkeypatch):
    from wrenorm import bench

    calls = []

    def fake(system, args, device="cpu", prefix=None):
        calls.append((device, prefix))
        gpu = device.startswith("cuda")
        return {"task": system, "command": "c", "ok": True, "wall_seconds": 2.0 if gpu else 4.0,
                "candidates": 60000 if gpu else 500}

    monkeypatch.setattr(bench, "timed_fit", fake)
    monkeypatch.setattr("shutil.which", lambda name: "/usr/bin/" + name)
    rows = bench.bench_fits("cuda:0", ["rope"])
    assert calls == [("cuda:0", None), ("cpu", bench.TWO_CORES)]
    assert rows[0]["candidates_ratio_vs_cpu"] == 120.0 and rows[0]["wall_ratio_vs_cpu"] == 0.5
    table = bench._table({"machine": {"processor": "x", "cpu_count": 16, "device": "cuda:0"}, "date": "d",
                          "fits": rows})
    assert "| rope | 2.00 | 4.00 | 120.0 | 0.50 |" in table


def test_bench_writes_to_the_checkouts_folder_from_anywhere(tmp_path, monkeypatch):
    """`bench --force` replaces the committed results wherever it is typed (a relative ./bench had written a second
    set of results into the current folder); outside a checkout it falls back to ./bench."""
    import argparse
    from pathlib import Path

    from wrenorm import bench

    monkeypatch.chdir(tmp_path)
    p = argparse.ArgumentParser()
    bench.add_arguments(p)
    out = p.parse_args([]).out
    checkout = Path(bench.__file__).resolve().parents[1] / "bench"
    assert out == (checkout if (checkout / "results.md").is_file() else Path("bench"))
    assert out.is_absolute() == (checkout / "results.md").is_file()


def test_only_names_the_default_fits_too(tmp_path):
    """`--only pd` benched the PD kernel and then ran every system's default fit (a review of stop 57)."""
    out = tmp_path / "bench"
    assert main(["bench", "--quick", "--no-cuda-build", "--only", "pd", "--batches", "256", "--out", str(out)]) == 0
    res = json.loads((out / "results.json").read_text())
    assert [f["task"] for f in res["fits"]] == ["pd"] and res["fits"][0]["ok"]
