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


def plot_det(curves: Mapping[str, tuple], path: str | Path, title: str = "DET",
             xlabel: str = "False match rate (FMR)", ylabel: str = "False non-match rate (FNMR)") -> None:
    """DET curves {name: (fmr, fnmr)} on normal-deviate axes, ticks labelled in %, as PNG
    (also the open-set DET: FNIR against FPIR, with those labels).

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
    ax.set(xlabel=xlabel, ylabel=ylabel, title=title)
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


def plot_score_histograms(genuine, impostor, path: str | Path, title: str = "Score distributions") -> list[str]:
    """Genuine and impostor score densities on shared bins (higher = more similar), as PNG; returns the legend labels.

    Every score is drawn and counted: ±inf scores (e.g. comparisons the cascade
    skipped, or that could not be aligned) fall in an extra bin just past the
    finite ones, and each label gives the class's count with how many of them
    are infinite, so the counts are those of the metrics table.
    """
    fig, ax = _figure()
    genuine, impostor = np.asarray(genuine, float), np.asarray(impostor, float)
    both = np.r_[genuine, impostor]
    finite = both[np.isfinite(both)]
    infinite = finite.size < both.size
    labels = []
    if both.size:
        edges = np.histogram_bin_edges(finite if finite.size else [0.0], bins=min(100, max(10, int(np.sqrt(both.size)))))
        if infinite:  # one bin each side for -inf and +inf, shaded
            step = edges[1] - edges[0]
            edges = np.r_[edges[0] - step, edges, edges[-1] + step]
            ax.axvspan(edges[0], edges[1], color="0.9", zorder=0)
            ax.axvspan(edges[-2], edges[-1], color="0.9", zorder=0)
        mids = (edges[0] + edges[1]) / 2, (edges[-2] + edges[-1]) / 2
        for scores, name, color in ((genuine, "genuine", "tab:green"), (impostor, "impostor", "tab:red")):
            if not scores.size:
                continue
            counts = [(sign, int((scores == sign * np.inf).sum())) for sign in (-1, 1)]
            extra = "".join(f", {n} at {'−' if sign < 0 else '+'}inf" for sign, n in counts if n)
            labels.append(f"{name} ({scores.size}{extra})")
            ax.hist(np.clip(scores, *mids), bins=edges, density=True, histtype="stepfilled", alpha=0.45, color=color,
                    label=labels[-1])
    ax.set(xlabel="Score (higher = more similar)" + ("; shaded bins: ±inf" if infinite else ""), ylabel="Density",
           title=title)
    _save(fig, ax, path, legend=True)
    return labels
