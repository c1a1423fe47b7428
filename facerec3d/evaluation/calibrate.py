"""A gallery's verification threshold, calibrated on its own sensor's data (§8.4: the operating point of a
verification system is a threshold on its score distribution).

A fixed default cannot suit every sensor: ICP's score of a genuine pair is ~−0.3 mm² on 0.7 mm laser scans and
−1.5 to −5 mm² on Kinect frames in 4–8 mm depth steps, so the −1.8 mm² that sits at the equal error rate of
synthetic laser scans rejects many genuine Kinect claims (their EER threshold on rap3df-2019 is about −3.7 mm²). `calibrate`
scores labelled scans of the gallery's own sensor against the gallery, the scan itself left out, and records in
the store the threshold at a chosen false-match rate (FMR, the operating point access control sets), or at the
equal error rate; `verify` and the service then use it whenever no threshold is given.

A scan's own entry is the one enrolled from the same file or from the same bytes (entries record their scan's
SHA-256): a copy of an enrolled scan, or a scan uploaded to the service (`facerec3d serve`, whose entries have no
file), is left out of its own comparisons as the original is. The service calibrates the same way on scans its
client sends (`POST /v1/calibrate`: `enroll --server` sends those it enrolled), scoring them against its live
gallery (`server.live.LiveGallery.calibration_scores`), with the rule of `threshold_record`.

With one scan per subject, as galleries usually are, only impostor pairs exist: the threshold at an FMR needs
nothing else (the score above which `fmr` of the impostor comparisons lie; with fewer than 1 / `fmr` pairs, as
a gallery of ten people has, just above the highest of them, which the record says, with the false-match rate to
expect of it, `expected_fmr`: 1 in n + 1, which scans of other people, enrolled or not, bring down); the equal
error rate needs genuine pairs too, i.e. a second scan of some subjects (`facerec3d gallery G calibrate MORE_SCANS`).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from facerec3d.datasets.catalog import ScanRecord
from facerec3d.gallery.engine import Engine
from facerec3d.gallery.service import content_hash
from facerec3d.gallery.store import GalleryError, GalleryStore
from facerec3d.evaluation.metrics import _eer, roc
from facerec3d.matching.base import scores_over

DEFAULT_FMR = 0.01  # the false-match rate the recorded threshold keeps (1 %: one impostor in a hundred accepted)
OWN_SCANS = "the gallery's own scans"  # a threshold record's "data" when calibrated on the gallery itself (enroll's)
MAX_SCANS = 100  # calibration scans scored against the gallery at the most (an even selection of them)


def gallery_records(store: GalleryStore) -> list[ScanRecord]:
    """The scans the gallery was enrolled from that are still on disk (the gallery calibrates on itself)."""
    return [ScanRecord(Path(e.source), str(e.subject), str(e.scan_id)) for e in store.entries()
            if Path(e.source).is_file()]


def calibration_selection(records: Sequence, max_scans: int = MAX_SCANS) -> list:
    """The records a calibration scores: all of them, or an even selection of `max_scans` (first and last kept)."""
    if len(records) <= max_scans:
        return list(records)
    return [records[i] for i in np.linspace(0, len(records) - 1, max_scans).round().astype(int)]


def pair_scores(matcher, rows: np.ndarray, own: np.ndarray, same: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(genuine, impostor) scores of one calibration scan from its `shard_scores` rows against the whole gallery
    (`Gallery.shard_rows`; `own`: its own entries, left out; `same`: the entries of its subject). A method that
    normalises over the gallery scores a genuine claim as a new scan of an enrolled person meets it, among every
    other entry, and an impostor claim as a stranger's meets it, among entries none of which is the claimant's:
    scored among its own subject's entries, whose high scores raise the cohort's mean and spread, the impostor
    scores came out lower than a stranger's, and a gallery of three scans per person calibrated a threshold that
    let 44 % of strangers' claims through at a stated FMR of 0.56 %. Other methods' scores do not depend on the
    cohort: the same either way."""
    genuine, impostor = ~own & same, ~own & ~same
    return scores_over(matcher, rows, ~own)[genuine], scores_over(matcher, rows, impostor)[impostor]


def calibration_scores(store: GalleryStore, records: Sequence[ScanRecord], *, engine: Engine,
                       cache: str | Path | None = None, max_scans: int = MAX_SCANS,
                       intrinsics: str | Path | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """(genuine scores, impostor scores, scans that failed to acquire) of up to `max_scans` labelled scans against
    every entry of the gallery, leaving out each scan's own entry (same source file, or same bytes), on the engine's
    workers; a method whose scores are normalised over the gallery (fusion, region ICP) normalises each pair's
    score as `pair_scores` says (an impostor's without the claimant's entries, as a stranger's). Depth frames are read
    with `intrinsics` (a JSON file) when given, else with the intrinsics.json found beside them. GalleryError
    with the first reason when no scan can be read and preprocessed (e.g. depth frames without their intrinsics)."""
    records = calibration_selection(records, max_scans)
    matcher, entries = store.matcher(), store.entries()
    if not entries:
        raise GalleryError(f"{store.path}: empty gallery (nothing enrolled yet)")
    outcomes = list(engine.preprocess([r.path for r in records], store.preprocess_config(), cache=cache,
                                      intrinsics=intrinsics))
    kept = [(r, o.face) for r, o in zip(records, outcomes) if o.face is not None]
    if records and not kept:  # else "no impostor pair" would hide why
        raise GalleryError(f"{store.path}: none of the {len(records)} calibration scans could be used; "
                           f"{outcomes[0].path}: {outcomes[0].error}")
    genuine: list[float] = []
    impostor: list[float] = []
    if kept:
        subjects = np.array([str(e.subject) for e in entries])
        sources = np.array([str(Path(e.source).resolve()) for e in entries])
        stored = store.contents()
        contents = np.array([stored.get(e.id) or "" for e in entries])
        owns = [(sources == str(Path(r.path).resolve())) | (contents == (content_hash(r.path) or "-"))
                for r, _ in kept]
        gallery = engine.load(matcher, store.templates(entries))
        try:
            rows = gallery.shard_rows(engine.prepare(matcher, [f for _, f in kept]))
        finally:
            gallery.release()
        for (record, _), own, row in zip(kept, owns, rows):
            g, i = pair_scores(matcher, row, own, subjects == str(record.subject))
            genuine += g.tolist()
            impostor += i.tolist()
    return np.array(genuine), np.array(impostor), len(records) - len(kept)


def threshold_at_fmr(impostor: np.ndarray, fmr: float) -> float:
    """The lowest threshold (accept score >= t) at which at most `fmr` of the impostor scores are accepted: the
    k-th highest impostor score, k = ⌊fmr · n⌋, or just above it where ties would accept more (just above the
    highest when k = 0). Needs no genuine score."""
    ranked = np.sort(np.asarray(impostor, dtype=np.float64))[::-1]
    k = int(np.floor(fmr * ranked.size + 1e-9))
    if k == 0:
        return float(np.nextafter(ranked[0], np.inf))
    t = ranked[k - 1]
    return float(t if np.sum(ranked >= t) <= k else np.nextafter(t, np.inf))


def calibrate(store: GalleryStore, records: Sequence[ScanRecord] | None = None, *, fmr: float | None = DEFAULT_FMR,
              engine: Engine, cache: str | Path | None = None, max_scans: int = MAX_SCANS,
              intrinsics: str | Path | None = None) -> dict:
    """Calibrate the gallery's verification threshold on labelled scans (default: the gallery's own) and record
    it in the store: the threshold at false-match rate `fmr`, or at the equal error rate when `fmr` is None.
    Depth frames are read with `intrinsics` when given (as they were enrolled).
    Returns the record: value, rule, pair counts, the EER and the TAR at the threshold where genuine pairs exist."""
    store.check_writable()  # before the work: a store that cannot be written, or that a service holds, is refused
    own = records is None
    records = gallery_records(store) if own else list(records)
    genuine, impostor, failed = calibration_scores(store, records, engine=engine, cache=cache, max_scans=max_scans,
                                                   intrinsics=intrinsics)
    try:
        record = threshold_record(genuine, impostor, fmr, scans=min(len(records), max_scans), failed=failed,
                                  data=OWN_SCANS if own else "calibration scans", entries=len(store.entries()))
    except ValueError as e:
        raise GalleryError(f"{store.path}: {e}") from None
    store.set_threshold(record)
    return record


def expected_fmr(impostor_pairs: int) -> float:
    """The false-match rate to expect of a threshold just above the highest of `impostor_pairs` impostor scores
    (what `threshold_at_fmr` gives when there are fewer than 1 / fmr of them): a stranger's claim is as likely as
    any of those pairs to be the highest of them all, so it passes 1 time in n + 1. Six pairs, as three enrolled
    people give, let about 14 % of strangers' claims through, whatever false-match rate was asked and though none
    of the six passes (measured: 15 of 108 claims of 12 synthetic strangers against a gallery of 3 with the default
    fusion, docs/depth-camera.md)."""
    return 1.0 / (impostor_pairs + 1)


def too_few_pairs(record: dict | None) -> float | None:
    """The false-match rate to expect of a recorded threshold (`threshold_record`) calibrated on too few impostor
    pairs for the rate asked (`expected_fmr` more than twice it); None when it rests on enough, or the record does
    not say (records of earlier versions, calibrated at the equal error rate, or damaged)."""
    expected, asked = (record or {}).get("expected_fmr"), (record or {}).get("asked_fmr")
    if not all(isinstance(x, (int, float)) and not isinstance(x, bool) and 0 < x <= 1 for x in (expected, asked)):
        return None
    return float(expected) if expected > 2 * asked else None


def threshold_record(genuine: np.ndarray, impostor: np.ndarray, fmr: float | None, *, scans: int, failed: int,
                     data: str, entries: int) -> dict:
    """The threshold record of calibration scores (what `calibrate` records, and the service for its gallery): the
    threshold at false-match rate `fmr`, or at the equal error rate when `fmr` is None, with how it was chosen;
    `scans` scored (`failed` of them unusable), `data` what they were, `entries` the gallery's size. ValueError
    (the reason) when the scores cannot give one."""
    if impostor.size == 0:
        raise ValueError("no impostor pair to calibrate on: the gallery and the calibration scans need at least two "
                         "subjects")
    finite = impostor[np.isfinite(impostor)]
    if impostor.size < 2 or (finite.size == impostor.size and finite.max() == finite.min()):
        raise ValueError(f"the {impostor.size} impostor pair{'s' * (impostor.size != 1)} give no spread of scores to "
                         "place a threshold in (a fusion normalises each probe's scores over the gallery, which "
                         "needs several people): calibrate with more scans, or once the gallery holds more people")
    if fmr is None and genuine.size == 0:
        raise ValueError("the equal error rate needs genuine pairs (a second scan of some enrolled subjects); give "
                         "them, or calibrate at a false-match rate")
    rule = "eer" if fmr is None else f"fmr={fmr:g}"
    if fmr is None:
        fmrs, tars, thresholds = roc(genuine, impostor)
        value = float(thresholds[_eer(fmrs, tars)[1]])
    else:
        value = threshold_at_fmr(impostor, fmr)
        if fmr * impostor.size < 1:
            rule += f" (too few impostor pairs: just above the highest of {impostor.size})"
    if not np.isfinite(value):  # no impostor matched at all (-inf): accept any finite score
        finite = np.r_[genuine, impostor][np.isfinite(np.r_[genuine, impostor])]
        value = float(np.min(finite, initial=0.0))
    record = {"value": value, "rule": rule,
              "fmr": float(np.mean(impostor >= value)), "impostor_pairs": int(impostor.size),
              "genuine_pairs": int(genuine.size), "scans": scans, "failed_scans": failed, "data": data,
              "entries": entries, "calibrated_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    if fmr is not None:
        record["asked_fmr"] = float(fmr)
        if fmr * impostor.size < 1:  # the threshold is the highest impostor's: see `expected_fmr`
            record["expected_fmr"] = expected_fmr(impostor.size)
    if genuine.size:
        record["tar"] = float(np.mean(genuine >= value))
        record["eer"] = float(_eer(*roc(genuine, impostor)[:2])[0])
    return record
