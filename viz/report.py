"""The report page of a run folder: one self-contained HTML file (inline SVG, no scripts, no network), written
beside result.json and rebuilt from it by `python -m wrenorm view OUT --report`.

It answers the paper's procedure in order: what was observed, what the coarse model leaves out, which
parameters were fitted from which measured values, how the fit did on conditions it did not see, and whether
the omission was absorbed. A system adds its own sections through `System.report` (tasks/<name>/report.py).
"""
from __future__ import annotations

import html
import json
import math
import re
from pathlib import Path
from urllib.parse import quote

from wrenorm.errors import InputError
from wrenorm.results import flow_point_std, write_atomic
from wrenorm.uncertainty import not_pinned_text

REPORT_FILE = "report.html"

VERDICT_STYLE = {
    "absorbed": ("#1f7a3a", "#e6f4ea", "The fitted parameters keep every held-out condition within tolerance: the "
                 "omitted physics is absorbed at this resolution."),
    "expand": ("#9a4b00", "#fdf0e1", "The fitted parameters do not keep every held-out condition within tolerance: "
               "the omission is not absorbed by this parameter set. Free another parameter (--free) or refine the "
               "resolution, then fit again."),
    "unvalidated": ("#555", "#eee", "No held-out condition decides (none given, or the data checks flag each): "
                    "nothing says whether the omission was absorbed."),
}

CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",sans-serif;max-width:1100px;margin:24px auto;padding:0 16px;
color:#1d1d1f;line-height:1.45}
h1{font-size:1.6em;margin-bottom:4px}h2{font-size:1.2em;margin-top:28px;border-bottom:1px solid #ddd;padding-bottom:3px}
table{border-collapse:collapse;margin:8px 0;font-size:.92em}th,td{padding:4px 10px;border-bottom:1px solid #e5e5e5;
text-align:right}th{background:#f6f6f6}td:first-child,th:first-child{text-align:left}td:not(:last-child){white-space:nowrap}
.verdict{border-radius:8px;padding:12px 16px;margin:12px 0}.verdict b{font-size:1.15em;text-transform:uppercase}
.flag{display:inline-block;border-radius:4px;padding:0 6px;margin:0 2px;font-size:.82em;background:#eee}
.flag.warn{background:#fde2c8;color:#7a3b00}.flag.bad{background:#f9d0d0;color:#8a1010}.flag.ok{background:#d8efdc}
.charts{display:flex;flex-wrap:wrap;gap:12px}.muted{color:#666}
code{background:#f3f3f3;padding:1px 4px;border-radius:3px}
dl{display:grid;grid-template-columns:max-content 1fr;gap:4px 16px}dt{font-weight:600}dd{margin:0}
details{margin:10px 0}summary{cursor:pointer;font-weight:600}.scroll{overflow-x:auto}
"""


def esc(x) -> str:
    return html.escape(str(x))


def num(v, digits: int = 4) -> str:
    if v is None:
        return "–"
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return esc(v)
    if not math.isfinite(v):
        return "∞" if v > 0 else ("−∞" if v < 0 else "NaN")
    return f"{v:.{digits}g}"


class _Html(str):
    """A string that is already HTML (not escaped again by `table`)."""


def table(header: list[str], rows: list[list]) -> str:
    """An HTML table; cells are escaped unless they are already HTML (`_Html`)."""
    cell = lambda c: c if isinstance(c, _Html) else esc(c)  # noqa: E731
    head = "".join(f"<th>{esc(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{cell(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<div class='scroll'><table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table></div>"


def flag(text: str, kind: str = "") -> _Html:
    return _Html(f'<span class="flag {kind}">{esc(text)}</span>')


def _svgs_of(path: Path) -> list[str]:
    """The inline <svg> charts of an HTML file the run wrote (search.html), so the report needs no history."""
    try:
        return re.findall(r"<svg\b.*?</svg>", path.read_text(), flags=re.S)
    except OSError:
        return []


# --------------------------------------------------------------------------------------------------- a fit

def _verdict_block(v: dict) -> str:
    verdict = v.get("verdict", "unvalidated")
    fg, bg, meaning = VERDICT_STYLE.get(verdict, VERDICT_STYLE["unvalidated"])
    numbers = ""
    if "mean_measured_error" in v:
        numbers = (f" Mean held-out error with the measured parameters {num(v['mean_measured_error'])}, with the "
                   f"fitted ones {num(v['mean_fitted_error'])}")
        worst = ("no event, error at least " if v.get("worst_is_miss") else "") + num(v.get("worst_fitted_error"))
        numbers += (f" (worst {worst}, {v.get('worst_condition', '')}; its tolerance "
                    f"{num(v.get('worst_tolerance', v.get('tolerance')))})." if "worst_fitted_error" in v else ".")
    if v.get("note") and (v.get("flagged_conditions") or v.get("fitted_misses") or v.get("measured_misses")):
        numbers += f" Note: {v['note']}."
    return (f'<div class="verdict" style="color:{fg};background:{bg}"><b>{esc(verdict)}</b> &nbsp; '
            f"{esc(meaning)}{esc(numbers)}</div>")


def _procedure(r: dict, system) -> str:
    params = r.get("parameters", {})
    free = [n for n, p in params.items() if not p.get("frozen")]
    frozen = [n for n, p in params.items() if p.get("frozen")]
    v = r.get("validation", {})
    items = [
        ("observable", getattr(system, "observable", "") or "not stated by this system"),
        ("loss", r.get("loss", {}).get("meaning", "")),
        ("omitted physics", getattr(system, "omitted", "") or "not stated by this system"),
        ("fitted", f"{', '.join(free) or 'nothing'} (starting from measured values; held at measured: "
                   f"{', '.join(frozen) or 'none'})"),
        ("trained on", ", ".join(map(str, r.get("train", []))) or "–"),
        ("validated on", ", ".join(v.get("conditions", {})) or "no held-out condition"),
        ("resolution", ", ".join(f"{k} = {x}" for k, x in (r.get("resolution") or {}).items())),
    ]
    return "<dl>" + "".join(f"<dt>{esc(k)}</dt><dd>{esc(x)}</dd>" for k, x in items) + "</dl>"


def _parameter_rows(r: dict) -> list[list]:
    unc = r.get("uncertainty", {}) or {}
    undetermined, at_bound = set(unc.get("undetermined", [])), set(unc.get("at_bound", []))
    by_prior = set(unc.get("held_by_prior", []))
    # where the uncertainty says which the data pin (std within DETERMINED, 30 %, of the value), "determined" means
    # that; the rest of the not-undetermined ones are loose
    by_data = set(unc["determined_by_data"]) if isinstance(unc.get("determined_by_data"), list) else None
    not_pinned = set((r.get("restarts") or {}).get("not_pinned", [])) | set(
        (r.get("searches_spread") or {}).get("not_pinned", []))
    rows = []
    for name, p in r.get("parameters", {}).items():
        flags = []
        if p.get("frozen"):
            flags.append(flag("held at measured"))
        else:
            if name in undetermined:
                flags.append(flag("data cannot determine", "bad"))
            if name in by_prior:
                flags.append(flag("held by prior", "warn"))
            if name in at_bound:
                flags.append(flag("at bound", "warn"))
            said_by_data = bool(flags)  # cannot determine, held by the prior, at a bound: each says more than loose
            if name in not_pinned:
                flags.append(flag("differs across seeds", "warn"))
            if not said_by_data and by_data is not None and name not in by_data and p.get("fitted"):
                # relative to a value near zero (a freed feed-forward gain measured 0) every std is large: the
                # undetermined rule, against the bounds, speaks for those. Beside "differs across seeds" it says
                # what the std says too (a rope radius at +-61 % had shown the seeds' word alone; review of stop 57)
                flags.append(flag("loosely determined", "warn"))
            if not flags:
                flags.append(flag("determined", "ok"))
        lo, hi = p.get("bounds", [None, None])
        std = "" if p.get("std") is None else f"± {num(p['std'], 3)}"
        fitted, measured = p.get("fitted"), p.get("measured")  # the ratio from the values shown, not a stored copy
        ratio = f"{fitted / measured:.3g}×" if fitted is not None and measured and math.isfinite(fitted / measured) \
            else ""
        rows.append([name, p.get("unit", ""), num(p.get("measured")), num(p.get("fitted")), std, ratio,
                     f"[{num(lo, 3)}, {num(hi, 3)}]", _Html(" ".join(flags))])
    return rows


def _held_out(r: dict) -> str:
    from wrenorm.viz.svg import bar_chart

    v = r.get("validation", {})
    cond = v.get("conditions", {})
    if not cond:
        return "<p class='muted'>No held-out condition was given, so the fit is not validated.</p>"
    tol = v.get("tolerance")
    rows = []
    for name, c in cond.items():
        fe, own = c.get("fitted_error"), c.get("tolerance", tol)
        ok = c.get("within_tolerance", fe is not None and own is not None and fe <= own)
        mark = flag("within tolerance", "ok") if ok else flag("outside tolerance", "bad")
        if c.get("data_flags"):
            mark = _Html(mark + " " + flag("data flagged: not deciding", "warn"))
        rows.append([name, num(c.get("measured_error")), num(fe), num(own), mark])
    own_tols = {c.get("tolerance", tol) for c in cond.values()} - {None}
    line = max(own_tols) if own_tols else tol
    chart = bar_chart(list(cond), {"measured parameters": [c.get("measured_error") for c in cond.values()],
                                   "fitted parameters": [c.get("fitted_error") for c in cond.values()]},
                      "held-out error per condition", "error", hline=line,
                      hline_label="tolerance" if len(own_tols) <= 1 else "largest tolerance")
    return table(["condition", "error, measured parameters", "error, fitted parameters", "tolerance", ""],
                 rows) + chart


def _search(r: dict) -> str:
    s = r.get("search", {})
    rows = [["methods", " then ".join(s.get("methods", []))], ["evaluations", s.get("evaluations")],
            ["candidates blown up (NaN/Inf or runaway)", s.get("blowups")], ["stopped by", s.get("stop")],
            ["searches side by side", s.get("searches")], ["seed", r.get("seed")]]
    loss = r.get("loss", {})
    rows += [["loss with measured parameters", num(loss.get("measured"))],
             ["loss with fitted parameters", num(loss.get("fitted"))]]
    for key, who in (("searches_spread", "searches side by side"), ("restarts", "further seeded searches")):
        spread = r.get(key) or {}
        if spread.get("optima"):
            lo, hi = spread.get("held_out_mean_error_range") or [None, None]
            rows.append([f"{len(spread['optima'])} {who}: held-out mean error", f"{num(lo)} .. {num(hi)}"])
            rows.append([f"{len(spread['optima'])} {who}: parameters not pinned",
                         not_pinned_text(spread, r.get("uncertainty") or {})])
    return table(["", ""], [[a, b if isinstance(b, str) else num(b)] for a, b in rows])


def _uncertainty(r: dict) -> str:
    unc = r.get("uncertainty") or {}
    out = f"<p>{esc(unc.get('method', ''))}"
    if unc.get("condition_number") is not None:
        out += f"; condition number {num(unc['condition_number'], 3)}"
    out += ".</p>"
    corr_res = unc.get("correlated_residuals") if isinstance(unc.get("correlated_residuals"), dict) else {}
    widening = corr_res.get("widening") if isinstance(corr_res.get("widening"), dict) else {}
    wide = {n: f for n, f in widening.items() if isinstance(f, (int, float)) and f > 1.05}
    if wide:
        bw = corr_res.get("bandwidth")
        out += ("<p>The residuals are correlated in time" + (f" (Bartlett bandwidth {num(bw, 3)} samples after "
                                                              "prewhitening)" if isinstance(bw, (int, float)) else "")
                + ": the stds are the sandwich's, wider than the white-noise formula's by "
                + esc(", ".join(f"{n} {f:.2f}x" for n, f in wide.items())) + ".</p>")
    if unc.get("warning") and unc["warning"] not in (r.get("warnings") or []):  # since stop 56 said at the top
        out += f"<p><span class='flag bad'>warning</span> {esc(unc['warning'])}</p>"
    corr = unc.get("correlation")
    if corr and corr.get("names"):
        names, m = corr["names"], corr["matrix"]
        out += "<details><summary>correlation of the fitted parameters</summary>" + table(
            [""] + names, [[n] + [num(x, 2) for x in row] for n, row in zip(names, m)]) + "</details>"
    return out


def _run_info(r: dict, folder: Path | None) -> str:
    rows = []
    if r.get("command"):
        rows.append(["reproduce", _Html(f"<code>{esc(r['command'])}</code>")])
    rows.append(["device", r.get("device", "")])
    t = r.get("timing") or {}
    if r.get("wall_seconds") is not None:
        rows.append(["wall time of the fit", f"{r['wall_seconds']:.2f} s"])
    labels = {"start_up_s": "start up", "search_s": "search", "search_evaluating_s": "of the search: evaluating",
              "validation_s": "validation", "uncertainty_s": "uncertainty", "writing_s": "writing"}
    for k, label in labels.items():
        if t.get(k) is not None:
            rows.append([label, f"{t[k]:.2f} s"])
    rows.append(["versions", ", ".join(f"{k} {v}" for k, v in (r.get("versions") or {}).items())])
    if folder is not None:
        files = sorted(p.name for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
        # the page lies in the run's folder: each file a link beside it
        rows.append(["files", _Html(", ".join(f"<a href='{esc(quote(f))}'>{esc(f)}</a>" for f in files))])
        if (folder / "recording.rrd").exists():
            rows.append(["view", _Html(f"<code>python -m wrenorm view {esc(folder)}</code> (Rerun: fitted against "
                                       "reference)")])
    return table(["", ""], rows)


def fit_body(r: dict, folder: Path | None, system) -> str:
    parts = [_verdict_block(r.get("validation", {}))]
    parts += [f"<p><span class='flag warn'>warning</span> {esc(w)}</p>" for w in r.get("warnings") or []]
    parts += ["<h2>The procedure</h2>", _procedure(r, system)]
    parts += ["<h2>Parameters</h2>", table(["parameter", "unit", "measured", "fitted", "std", "fitted / measured",
                                             "bounds", "what the data say"], _parameter_rows(r)),
              "<h2>Held-out conditions</h2>", _held_out(r)]
    if system is not None and getattr(system, "report", None):
        from wrenorm.system import resolve

        for title, body in resolve(system.report)(r):
            parts += [f"<h2>{esc(title)}</h2>", body]
    per_condition = _svgs_of(folder / "conditions.html") if folder is not None else []
    if per_condition:
        parts += ["<h2>Each condition: reference, measured and fitted parameters</h2>",
                  '<div class="charts">' + "".join(per_condition) + "</div>"]
    charts = _svgs_of(folder / "search.html") if folder is not None else []
    parts += ["<h2>Search</h2>", _search(r)]
    if charts:
        parts.append('<div class="charts">' + "".join(charts) + "</div>")
    parts += ["<h2>Uncertainty</h2>", _uncertainty(r), "<h2>Run</h2>", _run_info(r, folder)]
    return "".join(parts)


# -------------------------------------------------------------------------------- several fits, a flow

def runs_body(result: dict, folder: Path, system) -> str:
    rows = []
    for r in result["runs"]:
        v = r.get("validation", {})
        rows.append([", ".join(f"{k} {x}" for k, x in r["resolution"].items()), num(r["loss"]["measured"]),
                     num(r["loss"]["fitted"]), num(v.get("mean_fitted_error")), v.get("verdict", "")])
    parts = ["<h2>Every resolution</h2>", table(["resolution", "loss measured", "loss fitted",
                                                   "held-out mean error", "verdict"], rows)]
    for r in result["runs"]:
        sub = folder / r["folder"] if r.get("folder") else None
        parts.append(f"<details><summary>{esc(r.get('folder') or r['resolution'])}</summary>"
                     f"{fit_body(r, sub if sub and sub.is_dir() else None, system)}</details>")
    if result.get("command"):
        parts.append(f"<h2>Run</h2><p>reproduce: <code>{esc(result['command'])}</code></p>")
    return "".join(parts)


def flow_body(flow: dict, folder: Path | None) -> str:
    from wrenorm.viz.svg import line_chart

    points = flow["points"]
    res = [p["resolution"] for p in points]
    numeric = [k for k, v in res[0].items() if isinstance(v, (int, float)) and not isinstance(v, bool)]
    key = next((k for k in numeric if len({r.get(k) for r in res}) > 1), numeric[0] if numeric else None)
    x = [r.get(key) for r in res]
    names = [n for n, p in points[0]["parameters"].items() if not p["frozen"]]
    charts = []
    for n in names:
        fitted = [p["parameters"][n]["fitted"] for p in points]
        series = [{"x": x, "y": fitted, "label": "fitted", "markers": True, "color": "#2891e6"}]
        std = [flow_point_std(p["parameters"][n]) or 0.0 for p in points]
        series += [{"x": x, "y": [f + s for f, s in zip(fitted, std)], "label": "± std",
                    "dash": "3,3", "color": "#9cc9f0"},
                   {"x": x, "y": [f - s for f, s in zip(fitted, std)], "dash": "3,3", "color": "#9cc9f0"}]
        for order, dash in (("first", "6,3"), ("second", "")):
            analytic = [(p.get("analytic") or {}).get(f"{n}_sim_{order}_order") for p in points]
            if any(isinstance(a, (int, float)) for a in analytic):
                series.append({"x": x, "y": [a if isinstance(a, (int, float)) else float("nan") for a in analytic],
                               "label": f"analytic, {order} order", "color": "#50c850", "dash": dash})
        # measured values depend on resolution too (the rope's per-link stiffness is EI / link length)
        series.append({"x": x, "y": [p["parameters"][n]["measured"] for p in points], "label": "measured",
                       "dash": "2,4", "color": "#555555"})
        charts.append(line_chart(series, n, str(key), n, width=360, height=260))
    rows = []
    for p in points:
        und = p.get("undetermined") or []
        # what the data cannot pin down first: the last columns of a wide table run off a page
        rows.append([f"{key} {p['resolution'].get(key)}", ", ".join(und) or "–", num(p["loss"]["fitted"])]
                    + [f"{num(p['parameters'][n]['fitted'])} ± {num(flow_point_std(p['parameters'][n]), 2)}"
                       + (" (undetermined)" if n in und else "") for n in names])
    parts = ["<p>Each effective parameter against resolution, with its measured value: the paper's "
             "renormalisation flow.</p>", '<div class="charts">' + "".join(charts) + "</div>",
             table(["resolution", "undetermined", "loss"] + names, rows),
             f"<p class='muted'>{esc(flow.get('uncertainty_method', ''))}</p>"]
    # the data's flags first: every point below was fitted under them
    parts[:0] = [f"<p><span class='flag warn'>warning</span> {esc(w)}</p>" for w in flow.get("warnings") or []]
    info = [["device", flow.get("device", "")], ["seed", flow.get("seed", "")],
            ["wall time", f"{flow.get('wall_seconds', 0):.1f} s"],
            ["versions", ", ".join(f"{k} {v}" for k, v in (flow.get("versions") or {}).items())]]
    if flow.get("command"):
        info.insert(0, ["reproduce", _Html(f"<code>{esc(flow['command'])}</code>")])
    return "".join(parts) + "<h2>Run</h2>" + table(["", ""], info)


# ------------------------------------------------------------------------------------------------ entry

def _system(task: str | None):
    if not task:
        return None
    from wrenorm.system import systems

    return systems().get(task)


def page(title: str, body: str) -> str:
    return (f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{esc(title)}</title>"
            f"<meta name='viewport' content='width=device-width, initial-scale=1'><style>{CSS}</style></head>"
            f"<body><h1>{esc(title)}</h1>{body}</body></html>\n")


def images(folder: Path | None) -> str:
    """The run's PNG plots, embedded (data URIs), so the page stays one self-contained file."""
    import base64

    if folder is None:
        return ""
    out = []
    for png in sorted(folder.glob("*.png")):
        data = base64.b64encode(png.read_bytes()).decode()
        out.append(f'<figure><img alt="{esc(png.stem)}" style="max-width:100%" src="data:image/png;base64,{data}">'
                   f"<figcaption class='muted'>{esc(png.name)}</figcaption></figure>")
    return "".join(out)


def other_body(result: dict, folder: Path | None, system) -> str:
    """A run that is not a fit (sensitivity, correction): the system's sections, its plots, how to rerun it."""
    parts = []
    if system is not None and getattr(system, "report", None):
        from wrenorm.system import resolve

        for title, body in resolve(system.report)(result):
            parts += [f"<h2>{esc(title)}</h2>", body]
    pictures = images(folder)
    if pictures:
        parts += ["<h2>Plots</h2>", pictures]
    info = [["device", result.get("device", "")], ["wall time", f"{result.get('wall_seconds', 0):.1f} s"],
            ["versions", ", ".join(f"{k} {v}" for k, v in (result.get("versions") or {}).items())]]
    if result.get("command_line"):
        info.insert(0, ["reproduce", _Html(f"<code>{esc(result['command_line'])}</code>")])
    return "".join(parts) + "<h2>Run</h2>" + table(["", ""], info)


RESULT_FILES = ("result.json", "flow.json", "sensitivity.json", "correct.json")


def render(result: dict, folder: Path | None = None) -> str:
    """The report page for a result (a fit, a fit per resolution, a flow, or a system's own run) as HTML."""
    system = _system(result.get("task") or result.get("system"))
    task = result.get("task") or result.get("system") or "wrenorm"
    kind = str(result.get("schema", "")).removeprefix("wrenorm.").split("/")[0]
    if kind not in ("result", "flow", ""):
        return page(f"{task}: {kind}", other_body(result, folder, system))
    if "points" in result:
        return page(f"{task}: parameter flow", flow_body(result, folder))
    if "runs" in result:
        return page(f"{task}: fits at {len(result['runs'])} resolutions", runs_body(result, folder, system))
    return page(f"{task} fit", fit_body(result, folder, system))


# ------------------------------------------------------------------------------- a result read back from disk

_FIT_NEEDS = {"parameters": dict, "loss": dict, "validation": dict, "resolution": dict}
_FIT_OPTIONAL = {"uncertainty": dict, "search": dict, "train": list, "warnings": list, "restarts": dict,
                 "searches_spread": dict, "timing": dict, "versions": dict}


def _json_kind(v) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true/false"
    return {dict: "an object", list: "a list", str: "a string"}.get(type(v), "a number")


def _field(r: dict, key: str, kind: type, src: str, where: str = "", required: bool = True):
    """r[key] if it is a `kind` (null or absent allowed unless required); an InputError naming the field if not."""
    if key not in r or (r[key] is None and not required):
        if required:
            raise InputError(src, where + key, "missing: the report needs it")
        return None
    if not isinstance(r[key], kind):
        want = "a number" if isinstance(kind, tuple) else _json_kind(kind())
        raise InputError(src, where + key, f"is {_json_kind(r[key])}, expected {want}")
    return r[key]


def _check_parameters(params: dict, src: str, where: str) -> None:
    if not params:
        raise InputError(src, where + "parameters", "is empty: a fit has at least one parameter")
    for name, p in params.items():
        if not isinstance(p, dict):
            raise InputError(src, f"{where}parameters.{name}", f"is {_json_kind(p)}, expected an object")
        for key in ("measured", "fitted"):  # null: a non-finite value as results.jsonable writes it (shown as –)
            if key not in p:
                raise InputError(src, f"{where}parameters.{name}.{key}", "missing: the report needs it")
            if p[key] is not None and (isinstance(p[key], bool) or not isinstance(p[key], (int, float))):
                raise InputError(src, f"{where}parameters.{name}.{key}", f"is {_json_kind(p[key])}, expected a number")


def _check_fit(r, src: str, where: str = "") -> None:
    if not isinstance(r, dict):
        raise InputError(src, where.rstrip(".") or "top level", f"is {_json_kind(r)}, expected an object")
    for key, kind in _FIT_NEEDS.items():
        _field(r, key, kind, src, where)
    for key, kind in _FIT_OPTIONAL.items():
        _field(r, key, kind, src, where, required=False)
    _check_parameters(r["parameters"], src, where)
    _field(r["validation"], "conditions", dict, src, where + "validation.", required=False)
    verdict = _field(r["validation"], "verdict", str, src, where + "validation.", required=False)
    if verdict is not None and verdict not in VERDICT_STYLE:
        raise InputError(src, f"{where}validation.verdict", f"{verdict!r} is not a verdict wrenorm gives "
                                                            f"({', '.join(VERDICT_STYLE)})")


def check_result(result, src: str) -> None:
    """Refuse (InputError naming the file and the field) a result the report cannot be made from: not a JSON
    object, a field it needs missing or of the wrong kind, or an unknown system."""
    from wrenorm.system import systems

    if not isinstance(result, dict):
        raise InputError(src, "top level", f"is {_json_kind(result)}, expected an object (a run's result)")
    schema = _field(result, "schema", str, src, required=False)
    if schema is not None and not re.fullmatch(r"wrenorm\.\w+/\d+", schema):
        raise InputError(src, "schema", f"{schema!r} is not a wrenorm result's (wrenorm.<kind>/<version>)")
    key = "task" if "task" in result or "system" not in result else "system"
    task = _field(result, key, str, src)
    if task not in systems():
        raise InputError(src, key, f"{task!r} is not a system of this wrenorm ({', '.join(systems())})")
    kind = (schema or "").removeprefix("wrenorm.").split("/")[0]
    if kind not in ("result", "flow", ""):
        return  # a system's own run (sensitivity, correction): its sections read what they need
    if "points" in result:
        points = _field(result, "points", list, src)
        if not points:
            raise InputError(src, "points", "is empty: a flow has at least one resolution")
        for i, p in enumerate(points):
            where = f"points[{i}]."
            if not isinstance(p, dict):
                raise InputError(src, where.rstrip("."), f"is {_json_kind(p)}, expected an object")
            _field(p, "resolution", dict, src, where)
            _field(_field(p, "loss", dict, src, where), "fitted", (int, float), src, where + "loss.", required=False)
            _check_parameters(_field(p, "parameters", dict, src, where), src, where)
        _field(result, "warnings", list, src, required=False)
    elif "runs" in result:
        runs = _field(result, "runs", list, src)
        if not runs:
            raise InputError(src, "runs", "is empty: a fit at several resolutions has at least one")
        for i, r in enumerate(runs):
            _check_fit(r, src, f"runs[{i}].")
    else:
        _check_fit(result, src)


def load_result(folder: Path) -> tuple[dict, Path]:
    """The folder's result (result.json, flow.json, ...) and its path, checked by `check_result`."""
    for name in RESULT_FILES:
        if (folder / name).exists():
            path = folder / name
            break
    else:
        kind = "not a finished run folder"
        if (folder / "sweep.json").exists():
            kind = ("a sweep's folder (sweep.json): its table is sweep.csv and sweep.png, `view DIR` opens its "
                    "recording, and each cell's report is in its folder under DIR/cells")
        elif (folder / "select.json").exists():
            kind = "a select run's folder (select.json): its answer is that file"
        raise InputError(str(folder), "result.json", f"none of {', '.join(RESULT_FILES)}: {kind}")
    try:
        result = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise InputError(str(path), "file", "is not UTF-8 text (not a result written by wrenorm)") from None
    except json.JSONDecodeError as e:
        raise InputError(str(path), f"line {e.lineno} column {e.colno}", f"not valid JSON ({e.msg}): truncated or "
                                                                         "edited?") from None
    check_result(result, str(path))
    return result, path


def write_report(folder: Path, result: dict | None = None) -> Path:
    """Write FOLDER/report.html from `result` (default: the folder's result.json or flow.json, checked)."""
    folder = Path(folder)
    if result is not None:
        text = render(result, folder)
    else:
        result, source = load_result(folder)
        try:
            text = render(result, folder)
        except (AttributeError, KeyError, TypeError, IndexError, ValueError) as e:
            # what check_result does not look at, laid out otherwise than wrenorm writes it: a line, not a traceback
            raise InputError(str(source), "contents", f"the report cannot be made from it ({e.__class__.__name__}: "
                                                      f"{e}): laid out otherwise than wrenorm writes a result, or a "
                                                      "bug of the report's to file") from None
    path = folder / REPORT_FILE
    write_atomic(path, text)
    return path
