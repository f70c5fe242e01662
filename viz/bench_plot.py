"""The bench's throughput against batch size, one panel per kernel, and the rope's variants and
baselines side by side (bench/results.png)."""
from __future__ import annotations

from pathlib import Path

from wrenorm.viz.plots import _figure, save_figure


def plot_bench(path: Path, res: dict) -> None:
    plt = _figure()
    gpu = not res["machine"]["device"].startswith("cpu")
    rope_key = "kernel_chain_steps_per_s" if gpu else "chain_steps_per_s"
    comparison = [r for r in res.get("rope", []) if r.get("comparison")]
    panels = (["rope"] if res.get("rope") else []) + (["variants"] if comparison else []) + \
        [k for k in ("swimmer", "pd") if res.get(k)]
    if not panels:
        return
    fig, axes = plt.subplots(1, len(panels), figsize=(4.4 * len(panels), 3.8), squeeze=False)
    for ax, name in zip(axes[0], panels):
        if name == "variants":
            names = [r["variant"] for r in comparison]
            vals = [r[rope_key] / 1e6 for r in comparison]
            bars = ax.barh(range(len(vals)), vals, color=["tab:orange" if n == "culled" else "0.6" for n in names])
            ax.set_yticks(range(len(vals)), names)
            ax.invert_yaxis()
            ax.set_xscale("log")
            base = next((r[rope_key] for r in comparison if r["variant"] == "numpy"), None)
            for b, r in zip(bars, comparison):
                ax.annotate(f" {r[rope_key] / 1e6:.3g}" + (f" ({r[rope_key] / base:.2g}x numpy)" if base else ""),
                            (b.get_width(), b.get_y() + b.get_height() / 2), va="center", fontsize=7)
            ax.set_xlim(right=max(vals) * 30)
            ax.set_xlabel("M chain-steps / s")
            ax.set_title(f"rope N = 16, batch {comparison[0]['batch']}, same run", fontsize=10)
            ax.grid(True, axis="x", which="both", alpha=0.3)
            continue
        rows = sorted(res[name], key=lambda r: r["batch"])
        if name == "rope":
            main = [r for r in rows if not r.get("comparison")]
            for n in sorted({r["n_nodes"] for r in main}):
                sel = [r for r in main if r["n_nodes"] == n]
                ax.plot([r["batch"] for r in sel], [r[rope_key] / 1e6 for r in sel], "o-", label=f"N = {n}")
            ax.set_yscale("log")
            ax.yaxis.set_major_formatter(plt.matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
            ax.yaxis.set_minor_formatter(plt.matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
            ax.set_ylabel("M chain-steps / s")
            ax.set_title("rope, culled" + (" (launches alone)" if gpu else ", all cores"), fontsize=10)
            ax.legend(fontsize=7, loc="center right")
        elif name == "swimmer":
            ax.plot([r["batch"] for r in rows], [r["fish_seconds_per_s"] for r in rows], "o-", color="tab:blue")
            ax.set_ylabel("fish-seconds simulated / s")
            ax.set_title("swimmer", fontsize=10)
            ax.set_ylim(bottom=0)
        else:
            ax.plot([r["batch"] for r in rows], [r["joint_steps_per_s"] / 1e6 for r in rows], "o-", color="tab:green")
            ax.set_ylabel("M joint-steps / s")
            ax.set_title("PD joint", fontsize=10)
            ax.set_ylim(bottom=0)
        ax.set_xscale("log", base=2)
        ax.xaxis.set_major_formatter(plt.matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:.0f}"))
        ax.set_xlabel("batch (models per launch)")
        ax.grid(True, which="both", alpha=0.3)
    m = res["machine"]
    fig.suptitle(f"{m.get('cpu_model', m['processor'])}, {m['cpu_count']} cores"
                 + (f", {m['gpu']}" if "gpu" in m else "") + f"; {res['date']}", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)
