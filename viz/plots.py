"""Static plots (PNG) of a fit: what a person would rather see than read."""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from wrenorm.results import write_atomic


def _figure():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: Path) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    write_atomic(path, buf.getvalue())


def search_charts(problem, history: dict) -> list[str]:
    """SVG charts of a fit's search: the objective per generation / iteration, and each free parameter
    relative to its measured value."""
    from wrenorm.viz.svg import line_chart

    cm = history.get("cmaes", [])
    hist = cm + [{"generation": len(cm) + h["iteration"], "best": h["cost"], "values": h["values"], "polish": True}
                 for h in history.get("least_squares", [])]
    if not hist:
        return []
    gens = [h["generation"] for h in hist]
    # the best so far, so both charts end at what the fit reports (each generation's best had ended at 0.259
    # beside a reported loss of 0.227; review of stop 55)
    best, so_far = [], None
    for h in hist:
        if so_far is None or h["best"] <= so_far["best"] or h.get("polish"):  # least squares: its own iterate
            so_far = h
        best.append(so_far)
    series = [{"x": gens, "y": [h["best"] for h in best], "label": "best so far"}]
    if cm:
        series.append({"x": gens[:len(cm)], "y": [h["median"] for h in cm], "label": "each generation's median",
                       "dash": "4,3"})
    how = " then ".join(k.replace("_", " ") for k in history)
    loss = line_chart(series, f"{problem.task}: search objective ({how})", "generation / iteration", "objective",
                      log_y=True)
    vals = np.array([h["values"] for h in best])
    params = [{"x": gens, "y": vals[:, i] / p.measured if p.measured else vals[:, i],
               "label": p.name if p.measured else f"{p.name} (value: measured 0)"}
              for i, p in enumerate(problem.space.parameters) if not p.frozen]
    return [loss, line_chart(params, "parameters of the best so far", "generation / iteration", "value / measured",
                             hline=1.0, hline_label="measured")]


def write_svg_page(path: Path, charts: list[str]) -> None:
    """A bare page of inline SVG charts (search.html, conditions.html): viewable alone, inlined by report.html."""
    if charts:
        write_atomic(path, "<!DOCTYPE html><meta charset=\"utf-8\"><body style=\"margin:0\">" + "".join(charts)
                     + "</body>\n")


def write_search_svg(path: Path, problem, history: dict) -> None:
    write_svg_page(path, search_charts(problem, history))
