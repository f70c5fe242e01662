"""The rope's sections of report.html: each throw's critical moment, reference against the chain with the
measured and the fitted parameters."""
from __future__ import annotations

from wrenorm.viz.report import flag, num, table


def _chain(c: dict) -> list:
    status = c.get("status", "")
    hit = num(c.get("hit_time")) if status == "hit" else flag("never hits" if status else "?", "bad")
    return [hit, num(c.get("total"), 3)]


def sections(result: dict) -> list[tuple[str, str]]:
    points = result.get("critical_points") or {}
    if not points:
        return []
    rows = []
    for name, p in points.items():
        ref = p.get("reference") or {}
        rows.append([name, "held out" if p.get("held_out") else "train", num(ref.get("time")),
                     f"{num(ref.get('s_a'), 3)} / {num(ref.get('s_b'), 3)}",
                     *_chain(p.get("measured") or {}), *_chain(p.get("fitted") or {})])
    body = ("<p>The observable is the state at the first self-collision. Times in s; contact places as arc-length "
            "fractions of the two touching points; errors are the weighted sum the fit minimises.</p>"
            + table(["throw", "", "reference time", "reference place", "measured: hit time", "measured: error",
                     "fitted: hit time", "fitted: error"], rows))
    comp = result.get("held_out_comparison") or {}
    if comp:
        crow = [[k.replace("_", " "), num(v.get("ratio_of_means"), 3)] for k, v in comp.items() if isinstance(v, dict)]
        body += table(["held-out scoring", "fitted / measured mean error"], crow)
        body += f"<p class='muted'>{comp.get('meaning', '')}</p>"
    return [("Critical moments", body)]


def condition_charts(problem, fitted, measured) -> list[str]:
    """Per throw, the critical state seen from the side (x-z, the samples the error compares): the reference's
    and each chain's at its own first self-collision, or a note in the legend where a chain never hits."""
    import numpy as np

    from wrenorm.viz.svg import ROLE_COLORS, line_chart

    conds = problem.train + problem.held_out
    _, st = problem._critical(np.stack([measured, fitted]), conds)
    out = []
    for j, c in enumerate(conds):
        g = c.data.target.state
        split = "held out" if j >= len(problem.train) else "train"
        series = [{"x": g.pos[0, :, 0], "y": g.pos[0, :, 2], "label": f"reference, t = {float(g.time[0]):.3f} s",
                   "color": ROLE_COLORS["reference"], "markers": True}]
        for i, who in enumerate(("measured", "fitted")):
            b = i * len(conds) + j
            if st.hit[b]:
                series.append({"x": st.pos[b, :, 0], "y": st.pos[b, :, 2], "color": ROLE_COLORS[who],
                               "label": f"{who} parameters, t = {float(st.time[b]):.3f} s", "markers": True})
            else:
                series.append({"x": [], "y": [], "color": ROLE_COLORS[who], "label": f"{who} parameters: never hits"})
        out.append(line_chart(series, f"{split}: {c.name}, critical state from the side", "x [m]", "z [m]",
                              width=360, height=300))
    return out
