"""Figures in the style of the paper's Figs. 7 and 9."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; no display needed
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

_MARKERS = ("o", "s", "^", "D", "v")


def plot_displacement(results: dict, step: float, path: Path) -> Path:
    """Per-pair displacement of each centre for each configuration vs the reference (paper Fig. 7)."""
    names = list(results)
    fig, axes = plt.subplots(1, 3, figsize=(13, 4), sharey=True)
    for c, ax in enumerate(axes):
        for k, name in enumerate(names):
            m = np.asarray(results[name]["displacement"]["measured"], float)
            ax.plot(np.arange(1, len(m) + 1), m[:, c], marker=_MARKERS[k % 5], ms=4, lw=1, label=name)
        ax.axhline(step, color="k", ls="--", lw=1, label=f"reference {step:g} mm")
        ax.set_title(f"centre c{c}")
        ax.set_xlabel("pair of consecutive frames")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("estimated displacement (mm)")
    axes[0].legend(fontsize=8)
    fig.suptitle("Displacement experiment (10 mm steps)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_rotation(results: dict, step: float, path: Path) -> Path:
    """Per-pair rotation angle for each configuration vs the reference (paper Fig. 9)."""
    fig, ax = plt.subplots(figsize=(6, 4))
    for k, name in enumerate(results):
        a = np.asarray(results[name]["rotation"]["measured"], float)
        ax.plot(np.arange(1, len(a) + 1), a, marker=_MARKERS[k % 5], ms=5, lw=1, label=name)
    ax.axhline(step, color="k", ls="--", lw=1, label=f"reference {step:g}°")
    ax.set_xlabel("pair of consecutive frames")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_ylabel("estimated rotation (°)")
    ax.set_title("Rotation experiment (5° steps)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
