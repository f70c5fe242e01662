"""The report page: written with every fit and flow, rebuilt by `view --report`, self-contained, saying what the
result says (verdict, flags, held-out errors), and rendered by a real browser (Chromium, headless)."""
import json
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from wrenorm.cli import main
from wrenorm.viz.report import render, write_report


def _run(args):
    env = dict(os.environ, RERUN_ANALYTICS="0")
    return subprocess.run([sys.executable, "-m", "wrenorm", *args], capture_output=True, text=True, env=env)


@pytest.fixture(scope="module")
def pd_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("report") / "pd"
    assert main(["fit", "pd", "--no-record", "--quiet", "--out", str(out)]) == 0
    return out


def _svgs(text: str) -> list[str]:
    import re

    return re.findall(r"<svg\b.*?</svg>", text, flags=re.S)


def test_a_fit_writes_a_report_that_says_what_its_result_says(pd_run):
    result = json.loads((pd_run / "result.json").read_text())
    text = (pd_run / "report.html").read_text()
    assert f"<b>{result['validation']['verdict']}</b>" in text
    for name in result["parameters"]:
        assert f"<td>{name}</td>" in text
    for cond in result["validation"]["conditions"]:
        assert f"<td>{cond}</td>" in text
    assert "python -m wrenorm fit pd --no-record --quiet --out" in text  # the command to reproduce it
    assert result["command"].startswith("python -m wrenorm fit pd")
    # self-contained: nothing fetched from anywhere (the page opens offline and from a copied folder)
    for attr in ("src=", "href=", "@import", "url(http"):
        assert attr not in text.replace('href="#', ""), attr
    charts = _svgs(text)
    assert len(charts) >= 3  # held-out bars, search objective, parameters during the search
    for svg in charts:
        ET.fromstring(svg)  # every chart is well-formed XML


def test_view_report_rebuilds_the_page_from_the_result(pd_run, capsys):
    page = pd_run / "report.html"
    before = page.read_text()
    page.unlink()
    assert main(["view", str(pd_run), "--report"]) == 0
    assert page.read_text() == before
    assert str(page) in capsys.readouterr().out


def test_view_report_of_a_folder_without_a_result_is_a_one_line_error(tmp_path, capsys):
    assert main(["view", str(tmp_path), "--report"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "result.json" in err[0] and str(tmp_path) in err[0]


def _result(**over) -> dict:
    r = {"task": "pd", "resolution": {"f_sim": 100.0}, "train": ["a"], "seed": 0, "device": "cpu",
         "parameters": {
             "J": {"measured": 1.0, "fitted": 1.1, "bounds": [0.1, 10], "std": 0.01, "frozen": False, "unit": "kg m^2",
                   "ratio_to_measured": 1.1},
             "K_D": {"measured": 1.0, "fitted": 9.9, "bounds": [0.1, 10], "std": 5.0, "frozen": False, "unit": "",
                     "ratio_to_measured": 9.9}},
         "loss": {"measured": 1.0, "fitted": 0.5, "meaning": "m"},
         "validation": {"verdict": "expand", "tolerance": 0.1, "mean_measured_error": 1.0, "mean_fitted_error": 0.5,
                        "conditions": {"held": {"measured_error": 1.0, "fitted_error": float("nan")}}},
         "uncertainty": {"undetermined": ["K_D"], "at_bound": ["K_D"], "method": "gauss-newton"},
         "search": {"methods": ["cmaes"], "evaluations": 10, "blowups": 3, "stop": "maxiter"}}
    r.update(over)
    return r


def test_the_report_flags_what_the_data_cannot_determine_and_never_drops_a_failed_condition():
    text = render(_result())
    row = text[text.index("<td>K_D</td>"):].split("</tr>")[0]
    assert "data cannot determine" in row and "at bound" in row
    j_row = text[text.index("<td>J</td>"):].split("</tr>")[0]
    assert "determined" in j_row and "cannot" not in j_row
    held = text[text.index("<td>held</td>"):].split("</tr>")[0]
    assert "NaN" in held and "outside tolerance" in held  # a NaN error is shown and fails, not hidden
    assert "n/a" in text  # ... and the chart marks its missing bar
    assert "<b>expand</b>" in text and "not absorbed" in text


def test_text_from_a_result_is_escaped():
    text = render(_result(train=["<script>alert(1)</script>"]))
    assert "<script>" not in text and "&lt;script&gt;" in text


def _browser() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "chrome"):
        if shutil.which(name):
            return shutil.which(name)
    return None


def test_the_report_renders_in_a_real_browser(pd_run, tmp_path):
    browser = _browser()
    if browser is None:
        if os.environ.get("WRENORM_BROWSER_TEST") == "required":
            pytest.fail("WRENORM_BROWSER_TEST=required but no chromium on PATH")
        pytest.skip("no chromium on PATH (CI installs it and sets WRENORM_BROWSER_TEST=required)")
    page = (pd_run / "report.html").resolve().as_uri()
    flags = ["--headless", "--no-sandbox", "--disable-gpu", f"--user-data-dir={tmp_path / 'profile'}"]
    dom = subprocess.run([browser, *flags, "--dump-dom", page], capture_output=True, text=True, timeout=120)
    assert dom.returncode == 0, dom.stderr[-2000:]
    result = json.loads((pd_run / "result.json").read_text())
    # the browser parsed the tables and the charts as the page means them
    assert dom.stdout.count("<svg") == (pd_run / "report.html").read_text().count("<svg")
    for name in result["parameters"]:
        assert f"<td>{name}</td>" in dom.stdout
    shot = tmp_path / "report.png"
    subprocess.run([browser, *flags, f"--screenshot={shot}", "--window-size=1200,1600", page], capture_output=True,
                   timeout=120, check=True)
    data = shot.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    import zlib

    # not a blank page: decompressed pixel rows hold more than one byte value
    idat = b"".join(data[i + 8:i + 8 + int.from_bytes(data[i:i + 4], "big")]
                    for i in _chunks(data, b"IDAT"))
    assert len(set(zlib.decompress(idat)[:200000])) > 8


def _chunks(data: bytes, kind: bytes):
    i = 8
    while i < len(data):
        n = int.from_bytes(data[i:i + 4], "big")
        if data[i + 4:i + 8] == kind:
            yield i
        i += 12 + n


def test_a_flow_writes_its_report(tmp_path):
    out = tmp_path / "flow"
    r = _run(["flow", "pd", "--resolutions", "100", "400", "--restarts", "2", "--no-record", "--quiet",
              "--out", str(out)])
    assert r.returncode == 0, r.stderr
    text = (out / "report.html").read_text()
    flow = json.loads((out / "flow.json").read_text())
    assert "parameter flow" in text and "analytic, first order" in text
    names = [n for n, p in flow["points"][0]["parameters"].items() if not p["frozen"]]
    assert len(_svgs(text)) == len(names)
    write_report(out)
    assert (out / "report.html").read_text() == text
    assert Path(out / "report.html").stat().st_size < 200_000
