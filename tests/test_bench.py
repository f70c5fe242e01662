"""The bench command writes its results file and table; bad batch sizes are refused."""
import json

from wrenorm.cli import main


def test_bench_writes_results_and_table(tmp_path):
    out = tmp_path / "bench"
    rc = main(["bench", "--quick", "--no-fits", "--no-cuda-build", "--only", "rope", "pd", "--batches", "256",
               "--out", str(out)])
    assert rc == 0
    res = json.loads((out / "results.json").read_text())
    rope = [r for r in res["rope"] if not r.get("comparison")]
    assert {r["n_nodes"] for r in rope} == {8, 16, 32}
    variants = {r["variant"] for r in res["rope"] if r.get("comparison")}
    assert {"culled", "allpairs", "scalar", "numpy", "torch"} <= variants
    for r in res["rope"]:
        assert r["chain_steps_per_s"] > 0 and r["kernel_chain_steps_per_s"] >= r["chain_steps_per_s"] * 0.99
    assert res["pd"][0]["joint_steps_per_s"] > 0
    table = (out / "results.md").read_text()
    assert "x numpy" in table and "PD joint" in table
    assert (out / "results.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bench_refuses_nonpositive_batches(tmp_path, capsys):
    rc = main(["bench", "--quick", "--no-fits", "--no-cuda-build", "--only", "pd", "--batches", "0",
               "--out", str(tmp_path / "b")])
    assert rc == 2
    assert "--batches" in capsys.readouterr().err
