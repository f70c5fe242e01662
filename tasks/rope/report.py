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
