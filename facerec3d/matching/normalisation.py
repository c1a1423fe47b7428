"""Score normalisation and fusion (chapter §8.10: fusion across regions and across methods).

Normalisations (Jain, Nandakumar & Ross 2005, "Score normalization in
multimodal biometric systems") map one source's similarity scores to a
common scale, with parameters estimated from a reference sample — in the
matchers here, the probe's own scores against the gallery it is compared
with (a per-probe, cohort-style normalisation that needs no training):

  * min-max: (s − min) / (max − min), in [0, 1];
  * z-score: (s − mean) / std;
  * tanh:    ½ (tanh(0.01 (s − μ) / σ) + 1), in (0, 1), with μ, σ the mean and
    std ("tanh") or Hampel's robust estimates ("tanh-hampel");
  * none.

Non-finite scores (an ICP that found no match: −inf) count as the worst finite
score of the sample. Rules combine k sources' normalised scores for n
templates (a k × n matrix): sum, product (needs min-max or tanh, which are
non-negative), weighted sum, and the rank-level votes of Faltemier, Bowyer &
Flynn 2008 ("A region ensemble for 3-D face recognition"): Borda count
(each source gives n − 1 − rank points, or top − rank for its `top` best
only: their modified Borda) and consensus voting (the number of sources
that rank a template first; the Borda count breaks ties).

After the rule, `minus_best_other` may subtract from each template's fused score a share of the best fused score
among the *other* people's templates (the best impostor as a cohort; the "second best" of open-set
identification): the people keep their order for every probe, so no rank moves; a claim by an enrolled impostor
scores lower, one by a stranger does not (docs/methods.md).

`matching.fusion.FusionMatcher` ("fusion") fuses member methods with these;
`matching.regions.RegionICPMatcher` fuses a face's regions.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.stats import rankdata

NORMALISATIONS = ("none", "min-max", "z-score", "tanh", "tanh-hampel")
RULES = ("sum", "product", "weighted-sum", "borda", "consensus")


def hampel_location_scale(x: np.ndarray, quantiles: tuple[float, float, float] = (0.7, 0.85, 0.95),
                          iterations: int = 10) -> tuple[float, float]:
    """Hampel M-estimates (μ, σ) of a sample: deviations d = x − μ are weighted by ψ(d)/d with Hampel's
    three-part redescending ψ, whose knees a ≤ b ≤ c are these quantiles of |x − median| (Jain et al. 2005:
    70 %, 85 %, 95 %); points beyond c get weight 0. σ is the weighted RMS deviation."""
    x = np.asarray(x, dtype=np.float64)
    a, b, c = np.quantile(np.abs(x - np.median(x)), quantiles)
    mu = float(np.median(x))
    w = np.ones_like(x)
    for _ in range(iterations):
        d = np.abs(x - mu)
        w = np.where(d <= a, 1.0, np.where(d <= b, a / np.maximum(d, 1e-300),
                     np.where(d <= c, a * (c - d) / (np.maximum(c - b, 1e-300) * np.maximum(d, 1e-300)), 0.0)))
        if w.sum() <= 0:
            break
        mu = float(np.sum(w * x) / w.sum())
    return mu, float(np.sqrt(np.sum(w * (x - mu) ** 2) / max(w.sum(), 1e-300)))


def normalise(scores: np.ndarray, method: str, reference: np.ndarray | None = None) -> np.ndarray:
    """Scores (n,) on a common scale, parameters from `reference` (default: the scores themselves).
    A degenerate reference (all equal) maps every score to 0 (z-score) or 0.5 (min-max, tanh)."""
    if method not in NORMALISATIONS:
        raise ValueError(f"unknown normalisation {method!r}: use one of {', '.join(NORMALISATIONS)}")
    s = np.asarray(scores, dtype=np.float64)
    ref = s if reference is None else np.asarray(reference, dtype=np.float64)
    finite = ref[np.isfinite(ref)]
    if len(finite) == 0:
        return np.zeros_like(s)
    s = np.where(np.isfinite(s), s, np.where(s > 0, finite.max(), finite.min()))
    if method == "none":
        return s
    if method == "min-max":
        lo, hi = finite.min(), finite.max()
        return (s - lo) / (hi - lo) if hi > lo else np.full_like(s, 0.5)
    mu, sd = hampel_location_scale(finite) if method == "tanh-hampel" else (finite.mean(), finite.std())
    if sd <= 0:
        return np.zeros_like(s) if method == "z-score" else np.full_like(s, 0.5)
    z = (s - mu) / sd
    return z if method == "z-score" else 0.5 * (np.tanh(0.01 * z) + 1.0)


def borda(scores: np.ndarray, top: int = 0) -> np.ndarray:
    """Borda points (n,) from k sources' scores (k, n): a source gives n − 1 − rank points (rank 0 = its best;
    ties share the average rank), or with top > 0 only max(top − rank, 0)."""
    S = np.atleast_2d(np.asarray(scores, dtype=np.float64))
    S = np.where(np.isnan(S), -np.inf, S)
    ranks = rankdata(-S, method="average", axis=1) - 1.0
    points = np.maximum(top - ranks, 0.0) if top > 0 else S.shape[1] - 1.0 - ranks
    return points.sum(axis=0)


def fuse(scores: np.ndarray, rule: str = "sum", normalisation: str = "z-score",
         weights: Sequence[float] = (), top: int = 0) -> tuple[np.ndarray, np.ndarray | None]:
    """(fused scores (n,), tiebreak (n,) or None) of k sources' similarity scores (k, n) for n templates.
    Each source is normalised over its own n scores first (the vote rules use ranks and ignore it)."""
    S = np.atleast_2d(np.asarray(scores, dtype=np.float64))
    check_fusion(rule, normalisation, weights, len(S))
    if rule == "borda":
        return borda(S, top), None
    if rule == "consensus":
        best = np.nanmax(np.where(np.isnan(S), -np.inf, S), axis=1, keepdims=True)
        return (S == best).sum(axis=0).astype(np.float64), borda(S, top)
    N = np.stack([normalise(row, normalisation) for row in S])
    if rule == "sum":
        return N.sum(axis=0), None
    if rule == "product":
        return N.prod(axis=0), None
    return np.asarray(weights, dtype=np.float64) @ N, None


def minus_best_other(fused: np.ndarray, subjects: np.ndarray, share: float) -> np.ndarray:
    """`fused` (n,) less `share` × the best score among templates of other subjects than each one's (`subjects`
    (n,): any keys, equal for one person's templates); unchanged where no other subject has a finite score (a
    gallery of one person) or `share` is 0. For a probe, the people keep their order (each by their best
    template), and each person's templates theirs: no subject's rank moves."""
    fused = np.asarray(fused, dtype=np.float64)
    if share == 0 or len(fused) == 0:
        return fused
    keys, person = np.unique(np.asarray(subjects), return_inverse=True)
    finite = np.where(np.isfinite(fused), fused, -np.inf)
    best = np.full(len(keys), -np.inf)
    np.maximum.at(best, person, finite)
    order = np.argsort(best)[::-1]
    first, second = best[order[0]], best[order[1]] if len(keys) > 1 else -np.inf
    other = np.where(person == order[0], second, first)
    return np.where(np.isfinite(other), fused - share * other, fused)


def check_fusion(rule: str, normalisation: str, weights: Sequence[float], n_sources: int) -> None:
    """Raise ValueError for settings `fuse` would refuse (checked when a config is made)."""
    if rule not in RULES:
        raise ValueError(f"unknown fusion rule {rule!r}: use one of {', '.join(RULES)}")
    if normalisation not in NORMALISATIONS:
        raise ValueError(f"unknown normalisation {normalisation!r}: use one of {', '.join(NORMALISATIONS)}")
    if rule == "product" and normalisation not in ("min-max", "tanh", "tanh-hampel"):
        raise ValueError("the product rule needs a non-negative normalisation: min-max, tanh or tanh-hampel")
    if len(weights) and rule != "weighted-sum":  # given for nothing: silently ignored (a fusion's method config)
        raise ValueError(f"weights are for the weighted-sum rule: {rule} does not use them")
    if rule == "weighted-sum" and len(weights) != n_sources:
        raise ValueError(f"weighted-sum needs one weight per source: {n_sources} sources, {len(weights)} weights")
    if rule == "weighted-sum" and not any(weights):  # every fused score 0: no ranking at all
        raise ValueError("weighted-sum needs a weight above 0: all weights are 0")
