"""The signature picture: each effective parameter against resolution, beside its measured
value (and the analytic prediction where one exists)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from wrenorm.results import flow_point_std
from wrenorm.viz.plots import _figure, save_figure


def _axis(flow):
    """The resolution key the flow varies: the first numeric one whose value differs between points
    (a flow over rope time steps also records its fixed segment count first); with one point, the
    first numeric key."""
    res = [p["resolution"] for p in flow["points"]]
    numeric = [k for k, v in res[0].items() if isinstance(v, (int, float)) and not isinstance(v, bool)]
    key = next((k for k in numeric if len({r.get(k) for r in res}) > 1), numeric[0])
    return key, np.array([r[key] for r in res], float)


def plot_flow(path: Path, flow: dict) -> None:
    plt = _figure()
    key, x = _axis(flow)
    names = [n for n, p in flow["points"][0]["parameters"].items() if not p["frozen"]]
    ncols = min(3, len(names))
    nrows = -(-len(names) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.2 * ncols, 3.4 * nrows), squeeze=False)
    for ax in axes.flat[len(names):]:
        ax.set_visible(False)
    for ax, name in zip(axes.flat, names):
        ps = [pt["parameters"][name] for pt in flow["points"]]
        y = np.array([p["fitted"] for p in ps])
        err = np.array([flow_point_std(p) or 0.0 for p in ps])
        ax.errorbar(x, y, yerr=err, marker="o", capsize=3, label="fitted")
        # measured values can depend on resolution too (the rope's per-link stiffness is EI / link length)
        ax.plot(x, [p["measured"] for p in ps], "k:", label="measured")
        pred = [pt.get("analytic", {}).get(f"{name}_sim_first_order") for pt in flow["points"]]
        if all(v is not None for v in pred):
            ax.plot(x, pred, "--", label="analytic (1st order)")
        ax.set_xscale("log")
        if ps[0].get("scale") == "log" and np.all(y > 0):
            ax.set_yscale("log")
        from matplotlib.ticker import NullFormatter, ScalarFormatter

        ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xticks(x)
        ax.set_xlabel(key)
        ax.set_title(name)
        ax.legend(fontsize=7)
    fig.suptitle(f"{flow['task']}: effective parameters against resolution (error bars: std)")
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


def record_flow(path: Path, flow: dict) -> None:
    from wrenorm.viz.record import Recorder, rerun_available

    if not rerun_available():
        return
    key, x = _axis(flow)
    res = [p["resolution"] for p in flow["points"]]
    # the x axis the viewer draws is a timeline: a time step becomes a duration timeline (read as
    # 10ms, 5ms, ...), an integer resolution (segments, bodies) a sequence; anything else its index
    if all("dt" in r for r in res) and len({r["dt"] for r in res}) == len(res):
        timeline, ticks = "dt", [float(r["dt"]) for r in res]
    elif np.allclose(x, np.round(x)) and len(set(x)) == len(x):
        timeline, ticks = key, [int(round(v)) for v in x]
    else:
        timeline, ticks = "resolution", list(range(len(res)))
    rec = Recorder(path, recording_id=f"flow-{flow['task']}")
    try:
        names = [n for n, p in flow["points"][0]["parameters"].items() if not p["frozen"]]
        for pt, tick, xv in zip(flow["points"], ticks, x):
            at = {"t": tick, "timeline": timeline}
            rec.log_scalar(f"resolution/{key}", value=float(xv), **at)
            for name in names:
                p = pt["parameters"][name]
                rec.log_scalar(f"flow/{name}/fitted", value=p["fitted"], **at)
                rec.log_scalar(f"flow/{name}/measured", value=p["measured"], **at)
                a = pt.get("analytic", {}).get(f"{name}_sim_first_order")
                if a is not None:
                    rec.log_scalar(f"flow/{name}/analytic", value=a, **at)
        for name in names:
            rec.add_view(f"{name}: fitted, measured" + (", analytic" if any(
                f"{name}_sim_first_order" in pt.get("analytic", {}) for pt in flow["points"]) else "")
                + f" against {timeline}", [f"/flow/{name}/**"])
        rec.add_view(f"{key} at each point", ["/resolution/**"])
        rec.close()
    except BaseException:
        rec.abort()
        raise
