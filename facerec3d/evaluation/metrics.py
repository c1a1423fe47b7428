"""Verification and identification metrics (Mian & Pears 2012, §8.4).

Every function takes scores where HIGHER means MORE SIMILAR (callers negate
distances such as the ICP error). A score matrix ``S`` is (n_probes, n_gallery);
``probe_ids`` and ``gallery_ids`` are the subject labels of its rows and
columns; a comparison is *genuine* when both labels are equal. A NaN score means
the comparison could not be made. A comparison is accepted when its score is
>= the decision threshold. Terms are those of ISO/IEC 19795-1: FMR (false match
rate, per impostor comparison), FNMR (false non-match rate, per genuine
comparison), TAR = 1 - FNMR, FTA (failure to acquire). All rates are fractions
in [0, 1].
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from sklearn.metrics import det_curve, roc_curve

FAR_LEVELS = (0.001, 0.01)  # FMR operating points reported by summarize (FRGC: 0.1 %)


def _ids(ids: Sequence, n: int, what: str) -> np.ndarray:
    """Subject labels as a 1-D array of str, checked against the matrix size."""
    ids = np.asarray(ids).astype(str)
    if ids.shape != (n,):
        raise ValueError(f"{what} has shape {ids.shape}, expected ({n},)")
    return ids


def _matrix(S, probe_ids, gallery_ids) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """S as a float 2-D array and the labels as str arrays, shapes checked."""
    S = np.asarray(S, dtype=float)
    if S.ndim != 2:
        raise ValueError(f"score matrix must be 2-D, got shape {S.shape}")
    return S, _ids(probe_ids, S.shape[0], "probe_ids"), _ids(gallery_ids, S.shape[1], "gallery_ids")


def split_scores(S, probe_ids, gallery_ids) -> tuple[np.ndarray, np.ndarray]:
    """The genuine and impostor scores of a score matrix, NaN entries left out.

    Returns two 1-D float arrays (row-major order of S).
    """
    S, p, g = _matrix(S, probe_ids, gallery_ids)
    same = p[:, None] == g[None, :]
    made = ~np.isnan(S)
    return S[same & made], S[~same & made]


def _labelled(genuine, impostor) -> tuple[np.ndarray, np.ndarray]:
    """Labels (1 genuine, 0 impostor) and scores for sklearn; both sets must be non-empty."""
    genuine = np.asarray(genuine, dtype=float).ravel()
    impostor = np.asarray(impostor, dtype=float).ravel()
    if genuine.size == 0 or impostor.size == 0:
        raise ValueError(f"need genuine and impostor scores, got {genuine.size} and {impostor.size}")
    if np.isnan(genuine).any() or np.isnan(impostor).any():
        raise ValueError("scores contain NaN; leave them out (split_scores does)")
    y = np.r_[np.ones(genuine.size, np.int8), np.zeros(impostor.size, np.int8)]
    return y, _finite_ranks(np.r_[genuine, impostor])


def _finite_ranks(scores: np.ndarray) -> np.ndarray:
    """Scores with ±inf (e.g. a comparison that could not be aligned) moved just past the finite ones.

    Order, and so every ROC / DET point, is unchanged; sklearn refuses infinities.
    """
    inf = np.isinf(scores)
    if not inf.any():
        return scores
    finite = scores[~inf]
    lo, hi = (finite.min(), finite.max()) if finite.size else (0.0, 0.0)
    return np.where(scores == -np.inf, lo - 1.0, np.where(scores == np.inf, hi + 1.0, scores))


def roc(genuine, impostor, *, drop_intermediate: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ROC curve: (FMR, TAR, thresholds), thresholds decreasing from +inf.

    Point i accepts every score >= thresholds[i]; the first point (+inf) is
    (FMR 0, TAR 0). With ``drop_intermediate=False`` there is one point per
    distinct score (what `eer` and `verification_rate` need);
    ``drop_intermediate=True`` removes collinear points only, so the drawn curve
    is the same with far fewer points.
    """
    y, s = _labelled(genuine, impostor)
    fmr, tar, thr = roc_curve(y, s, drop_intermediate=drop_intermediate)
    return fmr, tar, thr


def det(genuine, impostor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """DET curve from sklearn.metrics.det_curve: (FMR, FNMR, thresholds increasing).

    sklearn keeps only the points between the last one with FNMR = 0 and the
    first one with FMR = 0 (the part a DET plot shows).
    """
    y, s = _labelled(genuine, impostor)
    return det_curve(y, s)


def eer(genuine, impostor) -> float:
    """Equal error rate, the rate where FMR = FNMR.

    Rule: take every ROC point (one per distinct score, plus the +inf point
    (FMR 0, FNMR 1)), joined by straight segments in the (FMR, FNMR) plane. As
    the threshold falls, d = FNMR - FMR decreases from 1 to -1. At the first
    point with d <= 0: if d == 0 the EER is that point's FMR; otherwise it is
    the FMR where the segment from the previous point crosses FNMR = FMR,
    ``FMR_a + d_a / (d_a - d_b) * (FMR_b - FMR_a)``. Without ties between a
    genuine and an impostor score this equals min over thresholds of
    max(FMR, FNMR); a tied block is crossed along its segment, i.e. as if the
    ties were broken at random. Perfect separation gives 0.0; identical
    genuine and impostor scores give 0.5; every genuine below every impostor
    gives 1.0.
    """
    return _eer(*roc(genuine, impostor)[:2])


def _eer(fmr: np.ndarray, tar: np.ndarray) -> float:
    """EER from full ROC points (see eer)."""
    d = (1.0 - tar) - fmr
    b = int(np.argmax(d <= 0))  # exists: the last point has FMR 1, FNMR 0
    if d[b] == 0:
        return float(fmr[b])
    a = b - 1  # b >= 1 since d[0] = 1
    return float(fmr[a] + d[a] / (d[a] - d[b]) * (fmr[b] - fmr[a]))


def verification_rate(genuine, impostor, far: float) -> float:
    """Verification rate (TAR) at a false accept rate, as FRGC reports it.

    Defined as the highest TAR among the ROC operating points (thresholds on the
    observed scores, accepting score >= threshold, plus +inf) whose FMR <= far:
    no interpolation, so a genuine score tied with an impostor score is only
    accepted if accepting that impostor keeps FMR <= far. ``far`` is a fraction
    (0.001 = 0.1 %).
    """
    return _verification_rate(*roc(genuine, impostor)[:2], far)


def _verification_rate(fmr: np.ndarray, tar: np.ndarray, far: float) -> float:
    """VR from full ROC points (see verification_rate)."""
    if not 0.0 <= far <= 1.0:
        raise ValueError(f"far must be a fraction in [0, 1], got {far}")
    return float(tar[fmr <= far].max())  # the +inf point has FMR 0


def cmc(S, probe_ids, gallery_ids, max_rank: int | None = None, tiebreak=None) -> np.ndarray:
    """Cumulative match characteristic: element k-1 is the rank-k identification rate.

    A gallery may hold several templates per subject: each gallery SUBJECT is
    scored by its best template, and the rank of a probe is the position of its
    true subject among the gallery subjects. Ties are pessimistic: the true
    subject ranks below every other subject with the same score. ``tiebreak``
    (same shape as S, higher is better, e.g. the ICP correspondence count) is
    compared among equal scores first; a subject's tiebreak value is the best
    among its templates that reach its best score. NaN scores (and their
    tiebreak values) count as -inf, so they rank last. Closed set: probes whose
    subject is not in the gallery are left out; raises ValueError if none is
    left. ``max_rank`` defaults to the number of gallery subjects; longer
    curves are padded with 1.0.
    """
    S, p, g = _matrix(S, probe_ids, gallery_ids)
    subjects, col_subject = np.unique(g, return_inverse=True)
    keep = np.isin(p, subjects)
    if not keep.any():
        raise ValueError("no probe's subject is in the gallery")
    S = np.where(np.isnan(S[keep]), -np.inf, S[keep])
    order = np.argsort(col_subject, kind="stable")
    starts = np.searchsorted(col_subject[order], np.arange(subjects.size))
    best = np.maximum.reduceat(S[:, order], starts, axis=1)  # (probes, subjects)
    true = np.searchsorted(subjects, p[keep])
    rows = np.arange(true.size)
    b_true = best[rows, true][:, None]
    at_least = best >= b_true
    if tiebreak is not None:
        T = np.asarray(tiebreak, dtype=float)
        if T.shape != keep.shape + (g.size,):
            raise ValueError(f"tiebreak has shape {T.shape}, expected {(keep.size, g.size)}")
        T = np.where(np.isnan(T[keep]) | (S == -np.inf), -np.inf, T[keep])
        T = np.where(S == best[:, col_subject], T, -np.inf)  # templates reaching their subject's best
        best_t = np.maximum.reduceat(T[:, order], starts, axis=1)
        at_least = (best > b_true) | ((best == b_true) & (best_t >= best_t[rows, true][:, None]))
    ranks = at_least.sum(axis=1)  # includes the true subject itself
    n = subjects.size if max_rank is None else int(max_rank)
    if n < 1:
        raise ValueError(f"max_rank must be >= 1, got {max_rank}")
    return np.cumsum(np.bincount(ranks, minlength=n + 1)[1 : n + 1]) / ranks.size


def rank_k(cmc_curve, k: int) -> float:
    """Rank-k identification rate from a CMC; k beyond the curve gives its last value."""
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    cmc_curve = np.asarray(cmc_curve, dtype=float)
    return float(cmc_curve[min(k, cmc_curve.size) - 1])


def summarize(S, probe_ids, gallery_ids, n_failed: int = 0, tiebreak=None) -> dict:
    """Headline metrics of one run, as a JSON-ready dict of plain ints/floats.

    Keys: ``n_probes`` (processed + failed), ``n_processed`` (rows of S),
    ``failures`` (n_failed: probes with no usable scan, FTA), ``fta_rate``
    (failures / n_probes), ``n_ranked`` (processed probes whose subject is in the
    gallery, the CMC's probes), ``n_genuine`` / ``n_impostor`` (comparisons
    made), ``rank1``, ``rank5`` (rank at the largest rank if fewer than 5
    gallery subjects), ``eer``, ``vr_at_far_0.001``, ``vr_at_far_0.01``
    (see `verification_rate`), all over the processed probes only.

    The ``*_all`` variants (``rank1_all``, ``rank5_all``,
    ``vr_at_far_0.001_all``, ``vr_at_far_0.01_all``) count failed probes as
    misses. A failed probe is assumed to be of an enrolled subject (closed
    set), so it adds one identification attempt and, for VR, as many genuine
    comparisons as an average ranked probe, all rejected: both rates are
    scaled by n_ranked / (n_ranked + n_failed), which is
    n_processed / (n_processed + n_failed) in a closed-set test. Failed probes
    make no impostor comparisons, so FMR and EER are unaffected.

    A metric that cannot be computed (no genuine or no impostor scores, no
    ranked probe) is None.
    """
    S, p, g = _matrix(S, probe_ids, gallery_ids)
    if n_failed < 0:
        raise ValueError(f"n_failed must be >= 0, got {n_failed}")
    n_processed = S.shape[0]
    n_probes = n_processed + int(n_failed)
    n_ranked = int(np.isin(p, g).sum())
    genuine, impostor = split_scores(S, p, g)
    out: dict = {
        "n_probes": n_probes,
        "n_processed": n_processed,
        "failures": int(n_failed),
        "fta_rate": float(n_failed / n_probes) if n_probes else None,
        "n_ranked": n_ranked,
        "n_genuine": int(genuine.size),
        "n_impostor": int(impostor.size),
    }
    share = n_ranked / (n_ranked + n_failed) if n_ranked + n_failed else None
    curve = cmc(S, p, g, tiebreak=tiebreak) if n_ranked else None
    for k in (1, 5):
        r = rank_k(curve, k) if curve is not None else None
        out[f"rank{k}"] = r
        out[f"rank{k}_all"] = r * share if r is not None else (0.0 if share is not None else None)
    points = roc(genuine, impostor)[:2] if genuine.size and impostor.size else None
    out["eer"] = _eer(*points) if points else None
    for far in FAR_LEVELS:
        vr = _verification_rate(*points, far) if points else None
        out[f"vr_at_far_{far}"] = vr
        out[f"vr_at_far_{far}_all"] = vr * share if vr is not None and share is not None else None
    return out
