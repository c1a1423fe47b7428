"""Verification and identification metrics (Mian & Pears 2012, §8.4), with subject-level bootstrap intervals.

Every function takes scores where HIGHER means MORE SIMILAR (callers negate
distances such as the ICP error). A score matrix ``S`` is (n_probes, n_gallery);
``probe_ids`` and ``gallery_ids`` are the subject labels of its rows and
columns; a comparison is *genuine* when both labels are equal. A NaN score means
the comparison could not be made. A comparison is accepted when its score is
>= the decision threshold. Terms are those of ISO/IEC 19795-1: FMR (false match
rate, per impostor comparison), FNMR (false non-match rate, per genuine
comparison), TAR = 1 - FNMR, FTA (failure to acquire); open-set identification
follows NIST FRVT 1:N (FPIR, FNIR). All rates are fractions in [0, 1].

Uncertainty: `summarize(..., bootstrap=B)` adds 95 % percentile intervals
from B bootstrap replicates that resample probe *subjects* with replacement
(not scores: the scores of one person are correlated). A subject drawn k
times brings all its probes, their comparisons and its failed probes k
times; the gallery stays as it is.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from sklearn.metrics import det_curve

FAR_LEVELS = (0.001, 0.01)  # FMR operating points reported by summarize (FRGC: 0.1 %)
FPIR_LEVELS = (0.001, 0.01, 0.1)  # open-set operating points (NIST FRVT)
CI_LEVEL = 0.95  # coverage of the bootstrap intervals
BOOTSTRAP = 1000  # replicates used by reports unless told otherwise


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


def _checked(genuine, impostor) -> tuple[np.ndarray, np.ndarray]:
    """Genuine and impostor scores as 1-D float arrays; both non-empty, no NaN."""
    genuine = np.asarray(genuine, dtype=float).ravel()
    impostor = np.asarray(impostor, dtype=float).ravel()
    if genuine.size == 0 or impostor.size == 0:
        raise ValueError(f"need genuine and impostor scores, got {genuine.size} and {impostor.size}")
    if np.isnan(genuine).any() or np.isnan(impostor).any():
        raise ValueError("scores contain NaN; leave them out (split_scores does)")
    return genuine, impostor


def _finite_ranks(scores: np.ndarray) -> np.ndarray:
    """Scores with ±inf (e.g. a comparison that could not be aligned) moved just past the finite ones.

    Order, and so every DET point, is unchanged; sklearn refuses infinities.
    """
    inf = np.isinf(scores)
    if not inf.any():
        return scores
    finite = scores[~inf]
    lo, hi = (finite.min(), finite.max()) if finite.size else (0.0, 0.0)
    return np.where(scores == -np.inf, lo - 1.0, np.where(scores == np.inf, hi + 1.0, scores))


def _descending(scores: np.ndarray, *columns: np.ndarray) -> tuple[np.ndarray, ...]:
    """scores sorted from highest to lowest (±inf allowed), and the other arrays in the same order."""
    order = np.argsort(-scores, kind="stable")
    return (scores[order], *(c[order] for c in columns))


def _counts(scores: np.ndarray, genuine: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(impostor weight, genuine weight, threshold) accepted at each distinct score.

    scores are sorted decreasingly (see _descending); genuine flags each score;
    weights count each score (1, or a bootstrap multiplicity). Threshold i is the
    i-th distinct score; accepting score >= it accepts the cumulated weights.
    """
    ends = np.r_[scores[1:] != scores[:-1], True]
    return (np.cumsum(np.where(genuine, 0.0, weights))[ends], np.cumsum(np.where(genuine, weights, 0.0))[ends],
            scores[ends])


def roc(genuine, impostor, *, drop_intermediate: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ROC curve: (FMR, TAR, thresholds), thresholds decreasing from +inf.

    Point i accepts every score >= thresholds[i]; the first point (+inf) is
    (FMR 0, TAR 0), then there is one point per distinct score (±inf scores
    included). ``drop_intermediate=True`` removes collinear points only (as
    sklearn's roc_curve does), so the drawn curve is the same with far fewer
    points; `eer` and `verification_rate` use every point.
    """
    genuine, impostor = _checked(genuine, impostor)
    scores, flags = _descending(np.r_[genuine, impostor], np.r_[np.ones(genuine.size, bool), np.zeros(impostor.size, bool)])
    fp, tp, thr = _counts(scores, flags, np.ones(scores.size))
    if drop_intermediate and fp.size > 2:
        keep = np.r_[True, (np.diff(fp, 2) != 0) | (np.diff(tp, 2) != 0), True]
        fp, tp, thr = fp[keep], tp[keep], thr[keep]
    return np.r_[0.0, fp / fp[-1]], np.r_[0.0, tp / tp[-1]], np.r_[np.inf, thr]


def det(genuine, impostor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """DET curve from sklearn.metrics.det_curve: (FMR, FNMR, thresholds increasing).

    sklearn keeps only the points between the last one with FNMR = 0 and the
    first one with FMR = 0 (the part a DET plot shows). ±inf scores are moved
    just past the finite ones (thresholds there are not the scores).
    """
    genuine, impostor = _checked(genuine, impostor)
    y = np.r_[np.ones(genuine.size, np.int8), np.zeros(impostor.size, np.int8)]
    return det_curve(y, _finite_ranks(np.r_[genuine, impostor]))


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

    The crossing lies between FMR and FNMR of both points either side of it,
    so it is inside the [EER_low, EER_high] interval of FVC2000 (Maio et al.
    2002) that pyeer reports, whose midpoint pyeer gives as its EER.
    """
    return _eer(*roc(genuine, impostor)[:2])[0]


def _eer(fmr: np.ndarray, tar: np.ndarray) -> tuple[float, int]:
    """EER from full ROC points (see eer), and the index of the point either side of the crossing nearer to it
    (smaller |FNMR - FMR|): its threshold is the threshold at the EER."""
    d = (1.0 - tar) - fmr
    b = int(np.argmax(d <= 0))  # exists: the last point has FMR 1, FNMR 0
    if d[b] == 0:
        return float(fmr[b]), b
    a = b - 1  # b >= 1 since d[0] = 1
    return float(fmr[a] + d[a] / (d[a] - d[b]) * (fmr[b] - fmr[a])), (a if d[a] < -d[b] else b)


def verification_rate(genuine, impostor, far: float) -> float:
    """Verification rate (TAR) at a false accept rate, as FRGC reports it.

    Defined as the highest TAR among the ROC operating points (thresholds on the
    observed scores, accepting score >= threshold, plus +inf) whose FMR <= far:
    no interpolation, so a genuine score tied with an impostor score is only
    accepted if accepting that impostor keeps FMR <= far. ``far`` is a fraction
    (0.001 = 0.1 %). Of the thresholds that reach it, the highest is the
    threshold at that FMR.
    """
    fmr, tar, _ = roc(genuine, impostor)
    return float(tar[_operating_point(fmr, tar, far)])


def _operating_point(fmr: np.ndarray, tar: np.ndarray, far: float) -> int:
    """Index of the first (highest-threshold) point with the highest TAR among those with FMR <= far."""
    if not 0.0 <= far <= 1.0:
        raise ValueError(f"far must be a fraction in [0, 1], got {far}")
    allowed = np.flatnonzero(fmr <= far)  # the +inf point has FMR 0
    return int(allowed[np.argmax(tar[allowed])])


def _flags(mask, n: int) -> np.ndarray:
    """A per-probe boolean mask, its length checked."""
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != (n,):
        raise ValueError(f"mateless: need {n} booleans, got shape {mask.shape}")
    return mask


def mates_not_compared(S, probe_ids, gallery_ids) -> np.ndarray:
    """(n_probes,) booleans: the probes whose subject is in the gallery but compared with none of its templates
    (NaN in every such cell). In an all-vs-all run's scores.txt a scan is never compared with itself, so a person's
    only scan has no line against its subject: such a probe had no mate to find, as in the run that wrote the file
    (`search`'s `mateless`), and `facerec3d metrics` on that file gives the run's figures again."""
    S, p, g = _matrix(S, probe_ids, gallery_ids)
    own = p[:, None] == g[None, :]
    return own.any(axis=1) & ~(own & ~np.isnan(S)).any(axis=1)


class Searches(NamedTuple):
    """Each probe (row of S) searched against the gallery's subjects (a subject scores its best template).

    ranked:   the probe's subject is in the gallery (a mated search), unless the probe is `mateless`;
    rank:     its true subject's rank (ties pessimistic, see cmc); 0 when not ranked;
    mated:    the true subject's score (NaN when not ranked);
    nonmated: the best score of any other subject (NaN when the gallery has no other subject).
    Comparisons not made (NaN) count as -inf. mateless: optional booleans, the probes whose subject's only gallery
    templates are the probe itself, left out of the comparison (all-vs-all, a person with one scan): they have no
    mate to find, so they are searches of a subject not enrolled (not ranked, non-mated only), as a probe of a
    subject missing from the gallery is; a NaN alone cannot say so, as a mate not compared ranks last.
    """

    ranked: np.ndarray
    rank: np.ndarray
    mated: np.ndarray
    nonmated: np.ndarray


def search(S, probe_ids, gallery_ids, tiebreak=None, mateless=None) -> Searches:
    """Every probe's identification search: see `Searches`; ties as in `cmc`."""
    S, p, g = _matrix(S, probe_ids, gallery_ids)
    subjects, col_subject = np.unique(g, return_inverse=True)
    n = p.size
    if subjects.size == 0:
        empty = np.full(n, np.nan)
        return Searches(np.zeros(n, bool), np.zeros(n, int), empty, empty.copy())
    S = np.where(np.isnan(S), -np.inf, S)
    order = np.argsort(col_subject, kind="stable")
    starts = np.searchsorted(col_subject[order], np.arange(subjects.size))
    best = np.maximum.reduceat(S[:, order], starts, axis=1) if n else np.empty((0, subjects.size))
    enrolled = np.isin(p, subjects)
    ranked = enrolled if mateless is None else enrolled & ~_flags(mateless, n)
    true = np.minimum(np.searchsorted(subjects, p), subjects.size - 1)
    rows = np.arange(n)
    b_true = best[rows, true][:, None]
    at_least = best >= b_true
    if tiebreak is not None:
        T = np.asarray(tiebreak, dtype=float)
        if T.shape != S.shape:
            raise ValueError(f"tiebreak has shape {T.shape}, expected {S.shape}")
        T = np.where(np.isnan(T) | (S == -np.inf), -np.inf, T)
        T = np.where(S == best[:, col_subject], T, -np.inf)  # templates reaching their subject's best
        best_t = np.maximum.reduceat(T[:, order], starts, axis=1) if n else best
        at_least = (best > b_true) | ((best == b_true) & (best_t >= best_t[rows, true][:, None]))
    rank = np.where(ranked, at_least.sum(axis=1), 0)  # includes the true subject itself
    others = np.where(enrolled[:, None] & (np.arange(subjects.size) == true[:, None]), np.nan, best)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a row with no other subject: NaN
        nonmated = np.nanmax(others, axis=1)
    return Searches(ranked, rank, np.where(ranked, best[rows, true], np.nan), nonmated)


def cmc(S, probe_ids, gallery_ids, max_rank: int | None = None, tiebreak=None, mateless=None) -> np.ndarray:
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
    s = search(S, probe_ids, gallery_ids, tiebreak, mateless)
    if not s.ranked.any():
        raise ValueError("no probe's subject is in the gallery")
    n = np.unique(np.asarray(gallery_ids).astype(str)).size if max_rank is None else int(max_rank)
    if n < 1:
        raise ValueError(f"max_rank must be >= 1, got {max_rank}")
    ranks = s.rank[s.ranked]
    return np.cumsum(np.bincount(ranks, minlength=n + 1)[1 : n + 1]) / ranks.size


def rank_k(cmc_curve, k: int) -> float:
    """Rank-k identification rate from a CMC; k beyond the curve gives its last value."""
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    cmc_curve = np.asarray(cmc_curve, dtype=float)
    return float(cmc_curve[min(k, cmc_curve.size) - 1])


def open_set(S, probe_ids, gallery_ids, tiebreak=None, mateless=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Open-set identification curve (NIST FRVT): (FPIR, FNIR, thresholds), thresholds decreasing from +inf.

    Every probe is a non-mated search by its best non-mated score (the best
    other subject: as if its own subject were not enrolled; a probe of a
    subject not in the gallery uses its best score), so FPIR(T) is the share
    of probes whose best non-mated score is >= T. A probe of an enrolled
    subject is also a mated search, which succeeds at T when its subject is the
    top candidate (rank 1, as for rank-1) with a score >= T; FNIR(T) is the
    share of mated searches that do not. Raises ValueError without mated or
    non-mated searches.
    """
    r = _rows(S, probe_ids, gallery_ids, tiebreak, mateless=mateless)
    fpir, tpir, thr = _open_curve(r, np.ones(r.subject.size))
    if fpir is None:
        raise ValueError("need mated and non-mated searches")
    return fpir, 1.0 - tpir, thr


class _Rows(NamedTuple):
    """What the figures of a score matrix need, once (weights are applied per bootstrap replicate)."""

    subject: np.ndarray  # (n_rows,) index of each processed probe's subject
    failed: np.ndarray  # (n_failed,) index of each failed probe's subject, -1 when not known
    n_subjects: int
    searches: Searches
    scores: np.ndarray  # comparisons made, sorted decreasingly (see _descending)
    genuine: np.ndarray
    row: np.ndarray  # their rows
    open_scores: np.ndarray  # open set: rank-1 mated scores and non-mated scores, sorted decreasingly
    open_mated: np.ndarray
    open_row: np.ndarray


def _rows(S, probe_ids, gallery_ids, tiebreak=None, failed_ids: Sequence = (), mateless=None) -> _Rows:
    S, p, g = _matrix(S, probe_ids, gallery_ids)
    subjects, index = np.unique(np.r_[p, np.asarray(failed_ids, dtype=str)], return_inverse=True)
    s = search(S, p, g, tiebreak, mateless)
    made = ~np.isnan(S)
    rows, cols = np.nonzero(made)
    scores, genuine, row = _descending(S[rows, cols], p[rows] == g[cols], rows)
    hit = s.ranked & (s.rank == 1)
    nm = ~np.isnan(s.nonmated)
    o_rows = np.r_[np.flatnonzero(hit), np.flatnonzero(nm)]
    o_scores, o_mated, o_row = _descending(np.r_[s.mated[hit], s.nonmated[nm]],
                                           np.r_[np.ones(hit.sum(), bool), np.zeros(nm.sum(), bool)], o_rows)
    return _Rows(index[: p.size], index[p.size:], subjects.size, s, scores, genuine, row, o_scores, o_mated, o_row)


def _open_curve(r: _Rows, w: np.ndarray):
    """(FPIR, TPIR, thresholds) of the open-set curve under row weights w, thresholds decreasing from +inf;
    Nones without mated or non-mated searches. TPIR divides by every mated search, found at rank 1 or not."""
    mated_w = w[r.searches.ranked].sum()
    if not r.open_scores.size or mated_w <= 0:
        return None, None, None
    fp, tp, thr = _counts(r.open_scores, r.open_mated, w[r.open_row])
    if fp[-1] <= 0:
        return None, None, None
    return np.r_[0.0, fp / fp[-1]], np.r_[0.0, tp / mated_w], np.r_[np.inf, thr]


RATE_FIGURES = ("fta_rate", "rank1", "rank5", "rank1_all", "rank5_all", "eer",
                *(f"vr_at_far_{f}" for f in FAR_LEVELS), *(f"vr_at_far_{f}_all" for f in FAR_LEVELS),
                *(f"fnir_at_fpir_{f}" for f in FPIR_LEVELS))
THRESHOLD_FIGURES = ("threshold_at_eer", *(f"threshold_at_far_{f}" for f in FAR_LEVELS))
FIGURES = RATE_FIGURES + THRESHOLD_FIGURES  # what summarize estimates (and gives intervals for)


def _figures(r: _Rows, w: np.ndarray, failed_w: float, identification: bool,
             lost: np.ndarray | None = None) -> dict[str, float]:
    """Every figure under row weights w (1 each, or a bootstrap replicate's subject multiplicities) and a
    failed-probe weight; NaN where undefined. `lost` marks the rows of probes whose subject failed to enrol:
    misses in the *_all figures."""
    nan = float("nan")
    out = dict.fromkeys(FIGURES, nan)
    total = w.sum() + failed_w
    out["fta_rate"] = failed_w / total if total else nan
    ranked_w = w[r.searches.ranked].sum()
    missed_w = failed_w + (w[lost].sum() if lost is not None else 0.0)  # failures as misses (ISO/IEC 19795-1)
    share = ranked_w / (ranked_w + missed_w) if ranked_w + missed_w else nan
    if identification:
        for k in (1, 5):
            rate = (w * (r.searches.ranked & (r.searches.rank <= k))).sum() / ranked_w if ranked_w else nan
            out[f"rank{k}"] = rate
            out[f"rank{k}_all"] = rate * share if ranked_w else (0.0 if missed_w else nan)
        fpir, tpir, _ = _open_curve(r, w)
        if fpir is not None:
            for level in FPIR_LEVELS:
                out[f"fnir_at_fpir_{level}"] = 1.0 - tpir[_operating_point(fpir, tpir, level)]
    if r.scores.size:
        fp, tp, thr = _counts(r.scores, r.genuine, w[r.row])
        if fp[-1] > 0 and tp[-1] > 0:
            fmr, tar, thr = np.r_[0.0, fp / fp[-1]], np.r_[0.0, tp / tp[-1]], np.r_[np.inf, thr]
            out["eer"], at = _eer(fmr, tar)
            out["threshold_at_eer"] = thr[at]
            for far in FAR_LEVELS:
                at = _operating_point(fmr, tar, far)
                out[f"vr_at_far_{far}"] = tar[at]
                out[f"vr_at_far_{far}_all"] = tar[at] * share
                out[f"threshold_at_far_{far}"] = thr[at]
    return out


def _plain(value: float) -> float | None:
    """A figure for JSON: a float, or None when undefined or infinite (a threshold that accepts nothing)."""
    return float(value) if np.isfinite(value) else None


def summarize(S, probe_ids, gallery_ids, n_failed: int = 0, tiebreak=None, *, failed_ids: Sequence | None = None,
              identification: bool = True, bootstrap: int = 0, seed: int = 0, unenrolled: Sequence = (),
              mateless=None) -> dict:
    """Headline metrics of one run, as a JSON-ready dict of plain ints/floats.

    Keys: ``n_probes`` (processed + failed), ``n_processed`` (rows of S),
    ``failures`` (n_failed: probes with no usable scan, FTA), ``fta_rate``
    (failures / n_probes), ``n_ranked`` (processed probes whose subject is in the
    gallery, the CMC's probes: the mated searches), ``n_genuine`` /
    ``n_impostor`` (comparisons made), ``n_subjects`` (probe subjects, processed
    or failed: the bootstrap's unit), ``rank1``, ``rank5`` (rank at the largest
    rank if fewer than 5 gallery subjects), ``eer``, ``vr_at_far_0.001``,
    ``vr_at_far_0.01`` (see `verification_rate`), ``threshold_at_eer``,
    ``threshold_at_far_0.001``, ``threshold_at_far_0.01`` (the decision
    thresholds of those operating points, for `verify --threshold`; None when
    only +inf reaches it), ``n_nonmated`` (non-mated searches) and
    ``fnir_at_fpir_0.001`` / ``_0.01`` / ``_0.1`` (open-set FNIR at the
    highest threshold with FPIR <= the level, see `open_set`), all over the
    processed probes only.

    The ``*_all`` variants (``rank1_all``, ``rank5_all``,
    ``vr_at_far_0.001_all``, ``vr_at_far_0.01_all``) count failed probes as
    misses. A failed probe is assumed to be of an enrolled subject (closed
    set), so it adds one identification attempt and, for VR, as many genuine
    comparisons as an average ranked probe, all rejected: both rates are
    scaled by n_ranked / (n_ranked + n_failed), which is
    n_processed / (n_processed + n_failed) in a closed-set test. Failed probes
    make no impostor comparisons, so FMR and EER are unaffected. Likewise the
    processed probes of the ``unenrolled`` subjects (whose gallery scans all
    failed to enrol, FTE) are misses there: they add to n_failed in that share.
    ``mateless`` marks the probes whose subject's only gallery template is the probe itself (see `search`):
    not ranked, like probes of subjects not enrolled, and not misses either.

    ``failed_ids`` (the subjects of the failed probes; n_failed is then their
    number) lets the bootstrap draw failures with their subject; without
    them a replicate has n_failed failures per processed probe drawn.
    ``identification=False`` (a mask of comparisons, e.g. FRGC's ROC I) leaves
    the rank and open-set figures None. With ``bootstrap`` = B > 0, ``ci95``
    maps every figure of `FIGURES` to its 95 % interval [low, high]: the
    2.5th and 97.5th percentiles over B replicates resampling the probe
    subjects (numpy.random.default_rng(seed)), taken as the replicate values
    at or beyond them; None where the figure is undefined in every replicate,
    and an end is None where it is an infinite threshold (one no score
    reaches).

    A metric that cannot be computed (no genuine or no impostor scores, no
    ranked probe) is None.
    """
    S, p, g = _matrix(S, probe_ids, gallery_ids)
    if failed_ids is not None:
        failed_ids = np.asarray(failed_ids).astype(str)
        n_failed = failed_ids.size
    if n_failed < 0:
        raise ValueError(f"n_failed must be >= 0, got {n_failed}")
    r = _rows(S, p, g, tiebreak, () if failed_ids is None else failed_ids, mateless)
    n_processed = S.shape[0]
    out: dict = {
        "n_probes": n_processed + int(n_failed),
        "n_processed": n_processed,
        "failures": int(n_failed),
        "n_ranked": int(r.searches.ranked.sum()),
        "n_genuine": int(r.genuine.sum()),
        "n_impostor": int(r.genuine.size - r.genuine.sum()),
        "n_subjects": r.n_subjects,
        "n_nonmated": int((~np.isnan(r.searches.nonmated)).sum()) if identification else None,
    }
    lost = np.isin(p, [str(u) for u in unenrolled]) & ~r.searches.ranked
    point = _figures(r, np.ones(n_processed), float(n_failed), identification, lost)
    out.update({k: _plain(v) for k, v in point.items()})
    if bootstrap > 0:
        out["ci95"] = _intervals(r, int(n_failed) if failed_ids is None else 0, identification, bootstrap, seed,
                                 lost)
    return out


def _intervals(r: _Rows, unattributed: int, identification: bool, replicates: int, seed: int,
               lost: np.ndarray | None = None) -> dict:
    """{figure: [low, high] or None}: percentile intervals over subject-level bootstrap replicates."""
    n = r.n_subjects
    if n == 0:
        return dict.fromkeys(FIGURES)
    draws = np.random.default_rng(seed).multinomial(n, np.full(n, 1.0 / n), size=replicates)
    values = np.empty((replicates, len(FIGURES)))
    per_row = unattributed / max(r.subject.size, 1)
    for b, counts in enumerate(draws.astype(float)):
        w = counts[r.subject]
        failed_w = counts[r.failed].sum() + per_row * w.sum()
        values[b] = list(_figures(r, w, failed_w, identification, lost).values())
    tail = 100 * (1 - CI_LEVEL) / 2
    out = {}
    for k, column in zip(FIGURES, values.T):
        column = column[~np.isnan(column)]
        if column.size:  # sample values at or beyond the percentiles (no interpolation: thresholds may be ±inf)
            out[k] = [_plain(np.percentile(column, tail, method="lower")),
                      _plain(np.percentile(column, 100 - tail, method="higher"))]
        else:
            out[k] = None
    return out
