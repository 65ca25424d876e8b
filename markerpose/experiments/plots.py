"""Figures in the style of the paper's Figs. 7 and 9."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; no display needed
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.ticker import MaxNLocator

_MARKERS = ("o", "s", "^", "D", "v")
# The series a figure shows: the default and the paper's two configurations (and our
# classical one); every other preset stays in the report's tables, where a dozen lines
# in one panel would be unreadable.
PLOTTED = ("default", "paper", "paper-classical", "classical")


def _plotted(names) -> list:
    """The names to draw: those of :data:`PLOTTED` present, in that order (all if none)."""
    shown = [n for n in PLOTTED if n in names]
    return shown or list(names)


def _dodge(k: int, n: int, width: float = 0.36) -> float:
    """The x shift of series ``k`` of ``n`` drawn at the same x: side by side, so that a series
    equal to another is not hidden under it."""
    return 0.0 if n < 2 else (k / (n - 1) - 0.5) * width


def legend_below(fig, ax, ncol: int = 5):
    """One legend for the figure, under the panels, covering no data: the handles and
    labels of ``ax``, in ``ncol`` columns; the panels are laid out above it."""
    handles, labels = ax.get_legend_handles_labels()
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    fig.legend(handles, labels, loc="lower center", ncol=ncol, fontsize=8, frameon=False)


def plot_displacement(results: dict, step: float, path: Path) -> Path:
    """Per-pair displacement of each centre for the plotted presets vs the reference (paper Fig. 7)."""
    names = _plotted(results)
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.4), sharey=True)
    for c, ax in enumerate(axes):
        for k, name in enumerate(names):
            m = np.asarray(results[name]["displacement"]["measured"], float)
            x = np.arange(1, len(m) + 1) + _dodge(k, len(names))
            ax.plot(x, m[:, c], marker=_MARKERS[k % 5], ms=4, lw=1, label=name, zorder=3 + len(names) - k)
        ax.axhline(step, color="k", ls="--", lw=1, label=f"reference {step:g} mm")
        ax.set_title(f"centre c{c}")
        ax.set_xlabel("pair of consecutive frames (series side by side)")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("estimated displacement (mm)")
    fig.suptitle("Displacement experiment (10 mm steps)")
    legend_below(fig, axes[0])
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_rotation(results: dict, step: float, path: Path) -> Path:
    """Per-pair rotation angle for the plotted presets vs the reference (paper Fig. 9)."""
    fig, ax = plt.subplots(figsize=(7, 4.6))
    names = _plotted(results)
    for k, name in enumerate(names):  # the first (the default) drawn on top
        a = np.asarray(results[name]["rotation"]["measured"], float)
        x = np.arange(1, len(a) + 1) + _dodge(k, len(names))
        ax.plot(x, a, marker=_MARKERS[k % 5], ms=5, lw=1, label=name, zorder=3 + len(names) - k)
    ax.axhline(step, color="k", ls="--", lw=1, label=f"reference {step:g}°")
    ax.set_xlabel("pair of consecutive frames (series side by side)")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_ylabel("estimated rotation (°)")
    ax.set_title("Rotation experiment (5° steps)")
    ax.grid(alpha=0.3)
    legend_below(fig, ax, ncol=3)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_detection(levels: dict, path: Path) -> Path:
    """Detection rate with 95 % intervals versus darkness α and motion blur, per plotted preset (Fig. 10)."""
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2), sharey=True)
    for ax, kind, label in ((axes[0], "alpha", "darkness α (log scale)"), (axes[1], "blur", "motion blur kernel (px)")):
        xs = [float(v) for v in levels[kind]]
        names = _plotted(next(iter(levels[kind].values())))
        for k, name in enumerate(names):
            d = [levels[kind][v][name]["detection"] for v in levels[kind]]
            p = np.array([x["p"] for x in d]) * 100
            # Wilson bounds can sit a rounding error beyond p at 0 % and 100 %: clip.
            err = np.clip(np.array([[x["p"] - x["lo"], x["hi"] - x["p"]] for x in d]).T * 100, 0, None)
            ax.errorbar(xs, p, yerr=err, marker=_MARKERS[k % 5], ms=4, lw=1, capsize=3, label=name)
        if kind == "alpha":
            ax.set_xscale("log", base=2)
            ax.invert_xaxis()
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("pairs detected (%), 95 % interval")
    axes[0].set_ylim(-2, 102)
    fig.suptitle("Detection versus darkness and motion blur")
    legend_below(fig, axes[1])
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_accuracy(per_config: dict, path: Path) -> Path:
    """Median translation and rotation error by distance and by tilt bin, per plotted preset."""
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
    names = _plotted(per_config)
    bins = [b["bin"] for b in per_config[names[0]]["by_condition"]]
    x = np.arange(len(bins))
    width = 0.8 / len(names)
    for ax, key, label in (
        (axes[0], "t_median_mm", "translation error, median (mm)"),
        (axes[1], "r_median_deg", "rotation error, median (°)"),
    ):
        for k, name in enumerate(names):
            v = np.array([b[key] for b in per_config[name]["by_condition"]], float)
            ax.bar(x + (k - (len(names) - 1) / 2) * width, np.where(np.isfinite(v), v, np.nan), width, label=name)
        ax.set_xticks(x, bins, rotation=30, ha="right", fontsize=8)
        ax.set_yscale("log")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3, axis="y")
    fig.suptitle("Absolute pose error by distance (mm) and tilt (°), α = 1")
    legend_below(fig, axes[0])
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
