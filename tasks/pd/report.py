"""The PD joint's section of report.html: the fitted effective parameters beside the analytic prediction of
the integrator's delay at this f_sim."""
from __future__ import annotations

from wrenorm.viz.report import num, table


def sections(result: dict) -> list[tuple[str, str]]:
    a = result.get("analytic") or {}
    if not a:
        return []
    rows = [[k.replace("_", " "), num(v)] for k, v in a.items() if isinstance(v, (int, float))]
    return [(f"Analytic prediction at f_sim = {result.get('f_sim')} Hz ({result.get('integrator')})",
             "<p>First- and second-order predictions of the effective parameters from the integrator's delay, and "
             "the delay the fit implies.</p>" + table(["quantity", "value"], rows))]


def condition_charts(problem, fitted, measured, points: int = 400) -> list[str]:
    """Per condition: the joint angle of the reference and of the model with measured and fitted parameters,
    and what differs (q - q_ref), which the overlaid angles hide at this scale."""
    import numpy as np

    from wrenorm.viz.svg import ROLE_COLORS, line_chart

    out = []
    for split, group in (("train", problem.train), ("held out", problem.held_out)):
        if not group:
            continue
        for c in group:  # one at a time: a batch runs to its shortest condition
            traj = problem.trajectories(np.stack([measured, fitted]), [c])[:, 0]
            t = c.data["t"][: traj.shape[1]]
            ref = c.data["q_ref"][: len(t)]
            keep = np.unique(np.linspace(0, len(t) - 1, min(points, len(t))).astype(int))
            sims = {"measured": traj[0][keep], "fitted": traj[1][keep]}
            out.append(line_chart(
                [{"x": t[keep], "y": ref[keep], "label": "reference", "color": ROLE_COLORS["reference"]}]
                + [{"x": t[keep], "y": q, "label": f"{who} parameters", "color": ROLE_COLORS[who],
                    "dash": "5,3" if who == "measured" else ""} for who, q in sims.items()],
                f"{split}: {c.name}", "t [s]", "q [rad]", width=360, height=240))
            out.append(line_chart(
                [{"x": t[keep], "y": q - ref[keep], "label": f"{who} parameters", "color": ROLE_COLORS[who]}
                 for who, q in sims.items()], f"{split}: {c.name}, q - q_ref", "t [s]", "q - q_ref [rad]",
                width=360, height=240, hline=0.0))
    return out
