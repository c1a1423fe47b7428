"""PNG plots of verification and identification results.

Each curve function takes a dict {name: curve} so that several runs can be
overlaid. Figures are drawn on matplotlib's Agg canvas directly (no pyplot, no
global backend change, no display). Rates are fractions in [0, 1].
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from scipy.stats import norm

DET_TICKS = (0.0001, 0.001, 0.01, 0.05, 0.2, 0.5, 0.8, 0.95, 0.99)  # candidate DET tick rates


def _figure() -> tuple[Figure, object]:
    """A 6 x 4.5 inch figure on an Agg canvas, and its single axes."""
    fig = Figure(figsize=(6, 4.5), layout="constrained")
    FigureCanvasAgg(fig)
    return fig, fig.subplots()


def _save(fig: Figure, ax, path: str | Path, legend: bool) -> None:
    """Grid, legend (when there are curves) and write the PNG at 120 dpi."""
    ax.grid(True, which="both", alpha=0.3)
    if legend and ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize="small")
    fig.savefig(path, dpi=120)


def _percent(p: float) -> str:
    """0.001 -> '0.1%'."""
    return f"{100 * p:g}%"


def plot_roc(curves: Mapping[str, tuple], path: str | Path, title: str = "ROC") -> None:
    """ROC curves {name: (fmr, tar)}: TAR against FMR on a log axis, as PNG.

    The axis starts at half the lowest non-zero FMR drawn (at most 0.1 %);
    points with FMR = 0 are drawn at that left edge.
    """
    fig, ax = _figure()
    curves = {name: (np.asarray(fmr, float), np.asarray(tar, float)) for name, (fmr, tar) in curves.items()}
    floor = min([1e-3] + [fmr[fmr > 0].min() / 2 for fmr, _ in curves.values() if (fmr > 0).any()])
    for name, (fmr, tar) in curves.items():
        ax.plot(np.maximum(fmr, floor), tar, label=name)
    ax.set_xscale("log")
    ax.set_xlim(floor, 1.0)
    ax.set_ylim(0.0, 1.01)
    ax.set(xlabel="False match rate (FMR)", ylabel="True accept rate (1 - FNMR)", title=title)
    _save(fig, ax, path, legend=True)


def plot_det(curves: Mapping[str, tuple], path: str | Path, title: str = "DET") -> None:
    """DET curves {name: (fmr, fnmr)} on normal-deviate axes, ticks labelled in %, as PNG.

    Each axis shows Φ⁻¹(rate) (scipy.stats.norm.ppf) from the lowest non-zero
    rate drawn (at least 0.01 %) up to 99 %; rates outside, including 0 and 1,
    are clipped to the edge.
    """
    fig, ax = _figure()
    rates = [np.asarray(r, float) for fmr, fnmr in curves.values() for r in (fmr, fnmr)]
    positive = [r[r > 0].min() for r in rates if (r > 0).any()]
    lo, hi = max(min(positive, default=0.001) / 2, DET_TICKS[0]), DET_TICKS[-1]
    for name, (fmr, fnmr) in curves.items():
        x, y = (norm.ppf(np.clip(np.asarray(r, float), lo, hi)) for r in (fmr, fnmr))
        ax.plot(x, y, label=name)
    ticks = [t for t in DET_TICKS if lo <= t <= hi]
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_ticks(norm.ppf(ticks), [_percent(t) for t in ticks])
    ax.set_xlim(norm.ppf(lo), norm.ppf(hi))
    ax.set_ylim(norm.ppf(lo), norm.ppf(hi))
    ax.set(xlabel="False match rate (FMR)", ylabel="False non-match rate (FNMR)", title=title)
    _save(fig, ax, path, legend=True)


def plot_cmc(curves: Mapping[str, np.ndarray], path: str | Path, max_rank: int | None = 50, title: str = "CMC") -> None:
    """CMC curves {name: rates}, rates[k-1] = rank-k identification rate, as PNG.

    Ranks up to max_rank (None: the longest curve) are drawn.
    """
    fig, ax = _figure()
    longest = 1
    for name, rates in curves.items():
        rates = np.asarray(rates, float)[:max_rank]
        longest = max(longest, rates.size)
        ax.plot(np.arange(1, rates.size + 1), rates, marker="." if rates.size <= 30 else None, label=name)
    ax.set_xlim(0.5, longest + 0.5)
    ax.set_ylim(min([0.9] + [float(np.min(r)) for r in curves.values() if np.size(r)]) - 0.02, 1.01)
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.set(xlabel="Rank", ylabel="Identification rate", title=title)
    _save(fig, ax, path, legend=True)


def plot_score_histograms(genuine, impostor, path: str | Path, title: str = "Score distributions") -> None:
    """Genuine and impostor score densities on shared bins (higher = more similar), as PNG."""
    fig, ax = _figure()
    genuine, impostor = np.asarray(genuine, float), np.asarray(impostor, float)
    both = np.r_[genuine, impostor]
    both = both[np.isfinite(both)]
    if both.size:
        bins = np.histogram_bin_edges(both, bins=min(100, max(10, int(np.sqrt(both.size)))))
        for scores, name, color in ((genuine, "genuine", "tab:green"), (impostor, "impostor", "tab:red")):
            scores = scores[np.isfinite(scores)]
            if scores.size:
                ax.hist(scores, bins=bins, density=True, histtype="stepfilled", alpha=0.45, color=color,
                        label=f"{name} ({scores.size})")
    ax.set(xlabel="Score (higher = more similar)", ylabel="Density", title=title)
    _save(fig, ax, path, legend=True)
