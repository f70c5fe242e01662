"""A sweep at a glance: each fitted parameter against each varied axis, the seed spread as error bars (min to max
over seeds, every seed's value a faint dot), one line per combination of the other axes; and the same in Rerun."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from wrenorm.viz.plots import _figure, save_figure

MAX_LINES = 8  # per panel; further combinations of the other axes are drawn without a legend entry


def _number(v):
    try:
        return float(v)
    except (TypeError, ValueError):
        return None


def _axes(spec, rows, part: str | None = None) -> list[str]:
    axes = [k for k in spec.axes if len(spec.axes[k]) > 1]
    if part is not None:
        if len({r.get(part) for r in rows}) > 1:
            axes.append(part)  # e.g. a correction's arms: each its own line against the axes, and an axis itself
    elif len(rows) > len({r["cell"] for r in rows}):
        axes.append("resolution")  # cells that fit several resolutions each: every resolution is a point
    return axes or ["seed"]


def plot_sweep(path: Path, spec, rows: list[dict], names: list[str], part: str | None = None) -> bool:
    """names: the columns drawn, one row of panels each (a fit's or flow's fitted parameters, or a command's
    ExtraCommand.sweep_plot); part: the column that splits one cell into rows (ExtraCommand.sweep_part)."""
    done = [r for r in rows if r.get("status") == "done"]
    if not done or not names:
        return False
    axes = _axes(spec, done, part)
    plt = _figure()
    fig, grid = plt.subplots(len(names), len(axes), figsize=(4.4 * len(axes), 3.0 * len(names)), squeeze=False)
    for j, axis in enumerate(axes):
        values = list(dict.fromkeys(r.get(axis) for r in done))
        numeric = all(_number(v) is not None for v in values)
        xs = {v: (_number(v) if numeric else i) for i, v in enumerate(values)}
        others = [a for a in axes if a != axis and a != "seed"]
        groups = {}
        for r in done:
            groups.setdefault(tuple(r.get(a) for a in others), []).append(r)
        for i, name in enumerate(names):
            ax = grid[i][j]
            for g, (key, members) in enumerate(groups.items()):
                x, mid, lo, hi = [], [], [], []
                for v in values:
                    ys = np.array([m[name] for m in members if m.get(axis) == v and m.get(name) is not None], float)
                    if len(ys) == 0:
                        continue
                    x.append(xs[v])
                    mid.append(ys.mean())
                    # equal values: their mean can round a hair past them, and a negative bar is refused
                    lo.append(max(ys.mean() - ys.min(), 0.0))
                    hi.append(max(ys.max() - ys.mean(), 0.0))
                    ax.plot([xs[v]] * len(ys), ys, ".", color=f"C{g % 10}", alpha=0.35, ms=4)
                label = ", ".join(f"{a}={k}" for a, k in zip(others, key)) if others and g < MAX_LINES else None
                if x:
                    order = np.argsort(x)
                    ax.errorbar(np.array(x)[order], np.array(mid)[order],
                                yerr=[np.array(lo)[order], np.array(hi)[order]], marker="o", ms=4, capsize=3,
                                color=f"C{g % 10}", label=label)
            if numeric and len(values) > 2 and min(xs.values()) > 0 and max(xs.values()) / min(xs.values()) > 20:
                ax.set_xscale("log")
            if not numeric:
                ax.set_xticks(list(xs.values()), [str(v) for v in values], rotation=20, fontsize=7)
            ax.set_xlabel(axis)
            ax.set_ylabel(name)
            if i == 0 and others and len(groups) > 1:
                ax.legend(fontsize=6)
    seeds = len(spec.seeds)
    what = "fitted parameters" if spec.verb in ("fit", "flow") else ", ".join(names)
    fig.suptitle(f"{spec.task}: {what} against the swept axes"
                 + (f" (error bars: min-max over {seeds} seeds)" if seeds > 1 else ""), fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.35 / (3.0 * len(names))))
    save_figure(fig, path)
    plt.close(fig)
    return True


def _path_part(value) -> str:
    """A value as one part of an entity path."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in str(value)) or "_"


def _markdown(spec, rows: list[dict], names: list[str], part: str | None = None) -> str:
    cols = ["cell", "status", *([part] if part else []), *names,
            *(("loss_fitted", "verdict") if spec.verb in ("fit", "flow") else ())]
    lines = [f"# sweep: {spec.task}", "", f"{len(rows)} rows; axes: "
             + (", ".join(f"{k} = {v}" for k, v in spec.axes.items()) or "none") + f"; seeds {spec.seeds}", "",
             "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        cells = []
        for c in cols:
            v = r.get(c)
            cells.append(f"{v:.6g}" if isinstance(v, float) else ("" if v is None else str(v)))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def record_sweep(path: Path, spec, rows: list[dict], names: list[str], part: str | None = None) -> bool:
    """A Rerun recording: the table as text, and per plotted column (plot_sweep's names) its value on a `cell`
    timeline, one series per value of `part` where a cell has several rows (one series per other-axes combination
    is left to the table; the timeline follows the cell order)."""
    from wrenorm.viz.record import Recorder, rerun_available

    if not rerun_available() or not rows:
        return False
    rec = Recorder(path, recording_id=f"sweep-{spec.task.replace(' ', '-')}")
    try:
        rec.log_text("sweep/table", _markdown(spec, rows, names, part))
        numeric_axes = [a for a in spec.axes if all(_number(v) is not None for v in spec.axes[a])]
        cells = {c: i for i, c in enumerate(dict.fromkeys(r["cell"] for r in rows))}
        for k, r in enumerate(rows):
            if r.get("status") != "done":
                continue
            if part is not None:
                k = cells[r["cell"]]  # a cell's rows (its arms) share its place on the timeline
            for name in names:
                if _number(r.get(name)) is not None:
                    series = f"{name}/{_path_part(r.get(part))}" if part is not None else name
                    rec.log_scalar(f"sweep/parameters/{series}", k, _number(r[name]), timeline="cell")
            for key in ("loss_fitted", "heldout_mean_fitted"):
                if r.get(key) is not None:
                    rec.log_scalar(f"sweep/{key}", k, float(r[key]), timeline="cell")
            for a in numeric_axes + ["seed"]:
                if _number(r.get(a)) is not None:
                    rec.log_scalar(f"sweep/axes/{a}", k, _number(r.get(a)), timeline="cell")
        for name in names:
            rec.add_view(f"{name} per cell", [f"/sweep/parameters/{name}" + ("/**" if part is not None else "")])
        rec.add_view("losses per cell", ["/sweep/loss_fitted", "/sweep/heldout_mean_fitted"])
        rec.add_view("axes per cell", ["/sweep/axes/**"])
        rec.add_view("table", ["/sweep/table"], kind="text")
        rec.close()
    except BaseException:
        rec.abort()
        raise
    return True
