"""The bench's throughput against batch size, one panel per kernel, and each system's variants and
baselines side by side (bench/results.png). Rows carry `panel`, `series`, `batch`, `value`, `unit`
(and `comparison` for the side-by-side variants), so this needs no system's names."""
from __future__ import annotations

from pathlib import Path

from wrenorm.viz.plots import _figure, save_figure


def plot_bench(path: Path, res: dict) -> None:
    plt = _figure()
    rows = [r for name in res.get("systems", []) for r in res.get(name, []) if "panel" in r]
    panels = list(dict.fromkeys(r["panel"] for r in rows))
    if not panels:
        return
    fig, axes = plt.subplots(1, len(panels), figsize=(4.4 * len(panels), 3.8), squeeze=False)
    fmt = plt.matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}")
    for ax, panel in zip(axes[0], panels):
        sel = [r for r in rows if r["panel"] == panel]
        unit = sel[0]["unit"]
        if all(r.get("comparison") for r in sel):
            names, vals = [r["series"] for r in sel], [r["value"] for r in sel]
            bars = ax.barh(range(len(vals)), vals, color=["tab:orange" if i == 0 else "0.6" for i in range(len(vals))])
            ax.set_yticks(range(len(vals)), names)
            ax.invert_yaxis()
            ax.set_xscale("log")
            slowest = min(vals)
            for b, v in zip(bars, vals):
                ax.annotate(f" {v:.3g} ({v / slowest:.2g}x slowest)", (b.get_width(), b.get_y() + b.get_height() / 2),
                            va="center", fontsize=7)
            ax.set_xlim(right=max(vals) * 30)
            ax.set_xlabel(unit)
            ax.grid(True, axis="x", which="both", alpha=0.3)
        else:
            for series in dict.fromkeys(r["series"] for r in sel):
                pts = sorted((r["batch"], r["value"]) for r in sel if r["series"] == series)
                ax.plot([b for b, _ in pts], [v for _, v in pts], "o-", label=series)
            ax.set_yscale("log")
            ax.yaxis.set_major_formatter(fmt)
            ax.yaxis.set_minor_formatter(fmt)
            ax.set_xscale("log", base=2)
            ax.xaxis.set_major_formatter(plt.matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:.0f}"))
            ax.set_xlabel("batch (models per launch)")
            ax.set_ylabel(unit)
            if len({r["series"] for r in sel}) > 1:
                ax.legend(fontsize=7, loc="center right")
            ax.grid(True, which="both", alpha=0.3)
        ax.set_title(panel, fontsize=10)
    m = res["machine"]
    fig.suptitle(f"{m.get('cpu_model', m['processor'])}, {m['cpu_count']} cores"
                 + (f", {m['gpu']}" if "gpu" in m else "") + f"; {res['date']}", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)
