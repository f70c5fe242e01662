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
