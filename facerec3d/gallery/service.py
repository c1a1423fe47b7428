"""Enrol into, identify against and verify with a gallery store (what `facerec3d enroll / identify / verify` do).

    report = enroll_scans(store, scan_records(["data/"]), make_matcher("icp"), jobs=4)
    hits = identify_scan(store, "probe.abs.gz", k=5, cascade=CascadeConfig())
    accepted, score = verify_scan(store, "probe.abs.gz", claim="04200", threshold=-1.0)
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from facerec3d.datasets.catalog import ScanRecord, open_dataset, scan_record
from facerec3d.evaluation.protocols import split
from facerec3d.gallery.cascade import CascadeConfig
from facerec3d.gallery.engine import Engine
from facerec3d.gallery.store import Entry, GalleryError, GalleryStore
from facerec3d.io import scan_stem
from facerec3d.matching.base import Matcher, Template
from facerec3d.preprocess.batch import preprocess_file
from facerec3d.preprocess.pipeline import PreprocessConfig
from facerec3d.scan import FaceScan

#: Default verification thresholds (score = similarity) by method: ICP's −MSE (mm²) at the equal error rate
#: of the synthetic test60 protocol (README).
DEFAULT_THRESHOLDS: dict[str, float] = {"icp": -1.0}


def scan_records(data: Iterable[str | Path], subject: str | None = None,
                 gallery_only: bool = False) -> list[ScanRecord]:
    """The scans of DATA arguments: dataset folders and manifest CSVs (all their scans, or with `gallery_only` the
    gallery of their protocol), and scan files (subject from a FRGC or Bosphorus name, else `subject`, else
    the file's stem)."""
    out: list[ScanRecord] = []
    for item in map(Path, data):
        if item.is_dir() or _is_manifest(item):
            dataset = open_dataset(item)
            chosen = split(dataset, None).gallery if gallery_only else range(len(dataset))
            out += [dataset.records[i] for i in chosen]
        else:
            named = None if subject is not None else scan_record(item)
            out.append(named or ScanRecord(item, subject or scan_stem(item), scan_stem(item)))
    return out


def _is_manifest(path: Path) -> bool:
    """A CSV file whose header names the columns path and subject (other CSV files are point-cloud scans)."""
    if path.suffix.lower() != ".csv":
        return False
    with open(path, newline="", errors="replace") as f:
        header = {c.strip().lower() for c in f.readline().split(",")}
    return {"path", "subject"} <= header


@dataclass
class EnrolReport:
    """What an enrolment did: entries added, sources skipped (already enrolled), failures (source, reason)."""

    enrolled: int = 0
    skipped: list[str] = field(default_factory=list)
    failures: list[tuple[str, str]] = field(default_factory=list)


def _enrol_one(record: ScanRecord, config: PreprocessConfig, matcher: Matcher,
               cache: str | None) -> tuple[Template | None, str | None]:
    """(template, None) or (None, reason) for one scan: preprocess (cached) and enrol."""
    outcome = preprocess_file(record.path, config, cache)
    if outcome.face is None:
        return None, outcome.error
    try:
        template = matcher.enroll(outcome.face)
    except ValueError as e:  # e.g. too few points to enrol
        return None, str(e)
    template.subject, template.scan_id = record.subject, record.scan_id
    return template, None


def enroll_scans(store: GalleryStore, records: Sequence[ScanRecord], matcher: Matcher,
                 config: PreprocessConfig = PreprocessConfig(), engine: Engine | None = None,
                 cache: str | Path | None = None, on_result=None) -> EnrolReport:
    """Preprocess and enrol scans into the store, each in its own transaction as soon as it is ready.

    The store must be new or made with these settings. Scans already in it are skipped; a scan that
    cannot be read, preprocessed or enrolled is recorded as a failure to enrol and the batch goes on.
    `on_result(source, status)` is called after each scan ("enrolled", "skipped" or the failure reason).
    """
    store.bind(config, matcher)
    report = EnrolReport()
    done = store.sources()
    todo = []
    for r in records:
        source = str(Path(r.path).resolve())
        if source in done:
            report.skipped.append(source)
            if on_result:
                on_result(source, "skipped")
        else:
            done.add(source)
            todo.append((source, r))
    own = engine is None
    engine = engine or Engine.create(1)
    try:
        results = engine.imap(_enrol_one, [r for _, r in todo], config, matcher, None if cache is None else str(cache))
        for (source, _), (template, error) in zip(todo, results):
            if template is None:
                store.add_failure(source, error)
                report.failures.append((source, error))
            else:
                store.add(template, source)
                report.enrolled += 1
            if on_result:
                on_result(source, "enrolled" if template is not None else error)
    finally:
        if own:
            engine.close()
    return report


def load_probe(store: GalleryStore, path: str | Path, config: PreprocessConfig | None = None,
               cache: str | Path | None = None) -> FaceScan:
    """A probe scan preprocessed with the gallery's settings; `config`, if given, must be those settings."""
    if config is not None:
        store.check_preprocess(config)
    outcome = preprocess_file(path, store.preprocess_config(), cache)
    if outcome.face is None:
        raise GalleryError(f"{path}: {outcome.error}")
    return outcome.face


def identify_scan(store: GalleryStore, probe: str | Path, k: int = 5, cascade: CascadeConfig | None = None,
                  config: PreprocessConfig | None = None, matcher: Matcher | None = None, engine: Engine | None = None,
                  cache: str | Path | None = None) -> list[tuple[Entry, float]]:
    """The k best gallery entries for a probe scan, (entry, score) best first. A `matcher` given must be the
    gallery's (method and options)."""
    stored = store.matcher()
    if matcher is not None:
        store.check_matcher(matcher)
    face = load_probe(store, probe, config, cache)
    entries = store.entries()
    if not entries:
        raise GalleryError(f"{store.path}: the gallery is empty")
    own = engine is None
    engine = engine or Engine.create(1)
    try:
        gallery = engine.load(stored, store.templates(entries))
        hits = gallery.identify(face, k, cascade)
        gallery.release()
    finally:
        if own:
            engine.close()
    return [(entries[i], s) for i, s in hits]


def verify_scan(store: GalleryStore, probe: str | Path, claim: str, threshold: float | None = None,
                config: PreprocessConfig | None = None, cache: str | Path | None = None) -> tuple[bool, float, float]:
    """(accepted, score, threshold): the probe's best score against the claimed subject's templates, accepted
    when it reaches the threshold (default: DEFAULT_THRESHOLDS of the gallery's method). Methods whose scores
    are normalised over the gallery (`Matcher.cohort_scores`) score the probe against the whole gallery."""
    matcher = store.matcher()
    if threshold is None:
        if matcher.name not in DEFAULT_THRESHOLDS:
            raise GalleryError(f"no default threshold for method {matcher.name!r}: give --threshold")
        threshold = DEFAULT_THRESHOLDS[matcher.name]
    claimed = [e.id for e in store.entries(subject=claim)]
    if not claimed:
        raise GalleryError(f"{store.path}: subject {claim!r} is not enrolled")
    entries = store.entries() if matcher.cohort_scores else store.entries(subject=claim)
    face = load_probe(store, probe, config, cache)
    scores, _ = matcher.scores(matcher.prepare(face), store.templates(entries))
    score = float(max(s for s, e in zip(scores, entries) if e.id in claimed))
    return score >= threshold, score, threshold

