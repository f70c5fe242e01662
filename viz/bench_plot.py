"""The bench's throughput against batch size, one panel per kernel (bench/results.png)."""
from __future__ import annotations

from pathlib import Path

from wrenorm.viz.plots import _figure, save_figure


def plot_bench(path: Path, res: dict) -> None:
    plt = _figure()
    panels = [k for k in ("rope", "swimmer", "pd") if res.get(k)]
    if not panels:
        return
    fig, axes = plt.subplots(1, len(panels), figsize=(4.6 * len(panels), 3.8), squeeze=False)
    gpu = not res["machine"]["device"].startswith("cpu")
    for ax, name in zip(axes[0], panels):
        rows = res[name]
        if name == "rope":
            key = "kernel_chain_steps_per_s" if gpu else "chain_steps_per_s"
            main = [r for r in rows if not r.get("comparison")]
            for n in sorted({r["n_nodes"] for r in main}):
                sel = sorted((r for r in main if r["n_nodes"] == n), key=lambda r: r["batch"])
                ax.plot([r["batch"] for r in sel], [r[key] / 1e6 for r in sel], "o-", label=f"N = {n}, culled")
            x0 = min(r["batch"] for r in main)
            for r in (r for r in rows if r.get("comparison") and r["variant"] != "culled"):
                ax.axhline(r[key] / 1e6, ls="--", lw=1, color="0.5" if r["variant"] in ("numpy", "torch") else "0.2")
                ax.annotate(f"N = 16 {r['variant']} (batch {r['batch']})", (x0, r[key] / 1e6),
                            fontsize=7, va="bottom", ha="left", color="0.3")
            ax.set_ylabel("M chain-steps / s")
            ax.set_title("rope" + (" (launches alone)" if gpu else ""))
        elif name == "swimmer":
            sel = sorted(rows, key=lambda r: r["batch"])
            ax.plot([r["batch"] for r in sel], [r["fish_seconds_per_s"] for r in sel], "o-", color="tab:blue")
            ax.set_ylabel("fish-seconds simulated / s")
            ax.set_title("swimmer")
        else:
            sel = sorted(rows, key=lambda r: r["batch"])
            ax.plot([r["batch"] for r in sel], [r["joint_steps_per_s"] / 1e6 for r in sel], "o-", color="tab:green")
            ax.set_ylabel("M joint-steps / s")
            ax.set_title("PD joint")
        ax.set_xscale("log", base=2)
        ax.xaxis.set_major_formatter(plt.matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:.0f}"))
        if name == "rope":
            ax.set_yscale("log")
        else:
            ax.set_ylim(bottom=0)
        ax.set_xlabel("batch (models per launch)")
        ax.grid(True, which="both", alpha=0.3)
        if name == "rope":
            ax.legend(fontsize=7, loc="center right")
    m = res["machine"]
    fig.suptitle(f"{m.get('cpu_model', m['processor'])}, {m['cpu_count']} cores"
                 + (f", {m['gpu']}" if "gpu" in m else "") + f"; {res['date']}", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)
