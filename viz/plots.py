"""Static plots (PNG) of a fit: what a person would rather see than read."""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from wrenorm.results import write_atomic


def _figure():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: Path) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    write_atomic(path, buf.getvalue())


def plot_search(path: Path, problem, history: dict) -> None:
    """Loss per generation and each free parameter relative to its measured value."""
    plt = _figure()
    cm = history.get("cmaes", [])
    hist = cm + [{"generation": len(cm) + h["iteration"], "best": h["cost"], "values": h["values"]}
                 for h in history.get("least_squares", [])]
    if not hist:
        return
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(10, 3.8))
    gens = [h["generation"] for h in hist]
    ax0.semilogy(gens, [max(h["best"], 1e-300) for h in hist], label="best")
    if cm:
        ax0.semilogy(gens[:len(cm)], [max(h["median"], 1e-300) for h in cm], label="median", alpha=0.6)
    ax0.set_xlabel("generation / iteration")
    ax0.set_ylabel("search objective")
    ax0.set_title(f"{problem.task}: " + " then ".join(k.replace("_", " ") for k in history))
    ax0.legend()
    vals = np.array([h["values"] for h in hist])
    for i, p in enumerate(problem.space.parameters):
        if p.frozen:
            continue
        ax1.plot(gens, vals[:, i] / p.measured if p.measured else vals[:, i], label=p.name)
    ax1.axhline(1.0, color="k", lw=0.5)
    ax1.set_xlabel("generation")
    ax1.set_ylabel("value / measured")
    ax1.legend(fontsize=7)
    save_figure(fig, path)
    plt.close(fig)
