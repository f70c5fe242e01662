"""The swimmer's section of report.html: swimming speed per tail-motor rate, real against the coarse fish with
fitted and with measured (published) coefficients and the elongated-body-theory baseline."""
from __future__ import annotations

from wrenorm.viz.report import flag, num, table
from wrenorm.viz.svg import line_chart


def sections(result: dict) -> list[tuple[str, str]]:
    speeds = result.get("speeds") or {}
    if not speeds:
        return []
    rates = sorted(speeds, key=float)
    rows = [[r, flag("train") if speeds[r].get("train") else flag("held out", "warn"),
             *(num(speeds[r].get(k), 3) for k in ("real", "fitted", "measured", "ebt"))] for r in rates]
    x = [float(r) for r in rates]
    chart = line_chart([{"x": x, "y": [speeds[r].get(k) for r in rates], "label": label, "markers": True,
                         "color": color} for k, label, color in
                        (("real", "real fish", "#5a5a5a"), ("fitted", "fitted coefficients", "#2891e6"),
                         ("measured", "measured coefficients", "#e6782a"), ("ebt", "EBT baseline", "#50c850"))],
                       "swimming speed against motor rate", "motor rate", "speed [m/s]")
    mae = result.get("speed_mae") or {}
    body = (table(["motor rate", "", "real speed", "fitted", "measured", "EBT"], rows) + chart
            + "<p>Held-out speed error (mean absolute, m/s): " + ", ".join(f"{k} {num(v, 3)}" for k, v in mae.items())
            + "</p>")
    return [("Swimming speed", body)]
