"""Enrol into, identify against and verify with a gallery store (what `facerec3d enroll / identify / verify` do).

    with Engine.create(jobs=4) as engine:          # or Engine.create(scheduler="tcp://host:8786")
        report = enroll_scans(store, scan_records(["data/"]), make_matcher("icp"), engine=engine)
        hits = identify_scan(store, "probe.abs.gz", k=5, cascade=CascadeConfig(), engine=engine)
    accepted, score, threshold = verify_scan(store, "probe.abs.gz", claim="04200", threshold=-1.0)

Enrolment and identification read and preprocess the scans on the engine's workers too (with the preprocessing
cache, a folder the workers share); without an engine, everything runs in this process.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from os import PathLike
from pathlib import Path

from facerec3d.config import DEFAULT_THRESHOLDS
from facerec3d.datasets.catalog import (Dataset, DatasetError, ScanRecord, manifest_record, open_dataset,
                                        scan_record)
from facerec3d.datasets.protocols import split
from facerec3d.errors import InputError
from facerec3d.gallery.cascade import CascadeConfig
from facerec3d.gallery.engine import Engine
from facerec3d.gallery.store import AlreadyEnrolled, Entry, GalleryError, GalleryStore
from facerec3d.io import scan_stem
from facerec3d.matching.base import Matcher, Template, check_k, check_threshold
from facerec3d.preprocess.batch import preprocess_file, printable
from facerec3d.preprocess.pipeline import PreprocessConfig
from facerec3d.scan import FaceScan


def gallery_threshold(store: GalleryStore, method: str) -> float:
    """The verification threshold a gallery uses when none is given: its calibrated one, else the method's default
    (laser-scan data), else a GalleryError saying how to get one."""
    record = store.threshold()
    if record is not None:
        return float(record["value"])
    if method in DEFAULT_THRESHOLDS:
        return DEFAULT_THRESHOLDS[method]
    raise GalleryError(f"{store.path}: no calibrated verification threshold for method {method!r}: run "
                       f"'facerec3d gallery {store.path} calibrate' or give a threshold")


def scan_records(data: Iterable[str | Path], subject: str | None = None,
                 gallery_only: bool = False) -> list[ScanRecord]:
    """The scans of DATA arguments: dataset folders and manifest CSVs (all their scans, or with `gallery_only` the
    gallery of their protocol), and scan files (subject from a FRGC or Bosphorus name, else `subject`, else
    the manifest.csv of the file's folder or one above it that lists it, else the file's stem); ScanRecords among
    them are kept as they are. Files in different folders whose subjects would all be the same stem
    (`a/front_1.png`, `b/front_1.png`: two people made one) are refused with a DatasetError that says how to name
    them."""
    out: list[ScanRecord] = []
    from_stem: dict[str, set[Path]] = {}
    for item in data:
        if isinstance(item, ScanRecord):
            out.append(item)
            continue
        item = Path(item)
        if (dataset := _dataset_of(item)) is not None:
            chosen = split(dataset, None).gallery if gallery_only else range(len(dataset))
            out += [dataset.records[i] for i in chosen]
        else:
            named = None if subject is not None else scan_record(item) or manifest_record(item)
            if named is None and subject is None:
                from_stem.setdefault(scan_stem(item), set()).add(item.resolve().parent)
            out.append(named or ScanRecord(item, subject or scan_stem(item), scan_stem(item)))
    for stem, folders in from_stem.items():
        if len(folders) > 1:
            raise DatasetError(f"{len(folders)} scans named {stem!r} in different folders would all be subject "
                               f"{stem!r}: give --subject, or a manifest.csv (path,subject) beside or above them")
    return out


def scan_paths(data: Iterable[str | Path]) -> list[Path]:
    """The scan files of DATA arguments, found as `scan_records` finds them (every scan of dataset folders and
    manifest CSVs; scan files as given), where their subjects do not matter (`facerec3d preprocess`)."""
    out: list[Path] = []
    for item in map(Path, data):
        dataset = _dataset_of(item)
        out += [item] if dataset is None else [r.path for r in dataset]
    return out


def _dataset_of(item: Path) -> Dataset | None:
    """The dataset a DATA argument names (a folder, or a manifest CSV), or None for a scan file."""
    return open_dataset(item) if item.is_dir() or _is_manifest(item) else None


def _is_manifest(path: Path) -> bool:
    """A CSV file whose header names the columns path and subject (other CSV files are point-cloud scans)."""
    if path.suffix.lower() != ".csv" or not path.is_file():  # a missing file: the reader says so
        return False
    with open(path, newline="", encoding="utf-8-sig", errors="replace") as f:  # -sig: Excel's "CSV UTF-8" BOM
        header = {c.strip().lower() for c in f.readline().split(",")}
    return {"path", "subject"} <= header


@dataclass
class EnrolReport:
    """What an enrolment did: entries added, sources skipped (already enrolled), failures (source, reason)."""

    enrolled: int = 0
    skipped: list[str] = field(default_factory=list)
    failures: list[tuple[str, str]] = field(default_factory=list)
    elsewhere: list[tuple[str, str, str]] = field(default_factory=list)  # skipped sources enrolled under another
    #   subject than the one asked now: (source, the entry's subject, the subject asked)


def content_hash(path: str | Path) -> str | None:
    """SHA-256 of a file's bytes (None when it cannot be read): the same scan under another path has the same."""
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            while block := f.read(1 << 20):
                digest.update(block)
    except OSError:
        return None
    return digest.hexdigest()


def _enrol_one(record: ScanRecord, config: PreprocessConfig, matcher: Matcher, cache: str | None,
               intrinsics: str | None = None) -> tuple[Template | None, str | None, str | None]:
    """(template, None, content hash) or (None, reason, content hash) for one scan: preprocess (cached; a depth
    frame read with `intrinsics` when given) and enrol."""
    content = content_hash(record.path)
    outcome = preprocess_file(record.path, config, cache, intrinsics)
    if outcome.face is None:
        return None, outcome.error, content
    try:
        template = matcher.enroll(outcome.face)
    except ValueError as e:  # e.g. too few points to enrol
        return None, str(e), content
    template.subject, template.scan_id = record.subject, record.scan_id
    return template, None, content


def enroll_scans(store: GalleryStore, records: Sequence[ScanRecord | str | PathLike] | str | PathLike,
                 matcher: Matcher, *, config: PreprocessConfig = PreprocessConfig(), engine: Engine | None = None,
                 cache: str | Path | None = None, intrinsics: str | Path | None = None,
                 on_result=None) -> EnrolReport:
    """Preprocess and enrol scans into the store, each in its own transaction as soon as it is ready; each scan is
    read, preprocessed and enrolled in one call on the `engine`'s workers.

    `records` are ScanRecords (`scan_records`) or paths: scan files, dataset folders and manifest CSVs, whose
    scans and subjects are found as `scan_records` finds them (as `facerec3d enroll DATA...` does); InputError for
    anything else, before any work.

    The store must be new or made with these settings. Scans already in it (by path, or by content: a copy of
    an enrolled scan) are skipped, also when another enrolment running at the same time adds them first; a scan
    that cannot be read, preprocessed or enrolled is recorded as a failure to enrol (its latest, until it enrols)
    and the batch goes on. `on_result(source, status)` is called after each scan ("enrolled", "skipped" or the
    failure reason). Depth frames are read with `intrinsics` (a JSON file) when given, else with the
    intrinsics.json found beside them.
    """
    given = records
    try:
        records = [records] if isinstance(records, (str, PathLike)) else list(records)
    except TypeError:  # not iterable
        records = [given]
    if bad := [r for r in records if not isinstance(r, (ScanRecord, str, PathLike))]:
        raise InputError(f"enroll_scans takes scan records (scan_records) or paths of scans, dataset folders and "
                         f"manifests, not {bad[0]!r:.60}")
    if not isinstance(matcher, Matcher):
        raise InputError(f"enroll_scans takes a matcher (facerec3d.matching.registry.make_matcher(name)), not "
                         f"{matcher!r:.60}")
    records = scan_records(records)
    store.bind(config, matcher)
    report = EnrolReport()
    done = store.sources()
    todo = []
    enrolled_as = None  # source -> subject of its entry, read when a skipped record asks for a subject
    for r in records:
        source = printable(Path(r.path).resolve())  # a file name that is not UTF-8 is stored as \\x.. text
        if source in done:
            report.skipped.append(source)
            if r.subject is not None:
                enrolled_as = enrolled_as or {e.source: e.subject for e in store.entries()}
                if source in enrolled_as and enrolled_as[source] != r.subject:
                    report.elsewhere.append((source, str(enrolled_as[source]), str(r.subject)))
            if on_result:
                on_result(source, "skipped")
        else:
            done.add(source)
            todo.append((source, r))
    own = engine is None
    engine = engine or Engine.create(1)
    try:
        results = engine.imap(_enrol_one, [r for _, r in todo], config, matcher, None if cache is None else str(cache),
                              None if intrinsics is None else str(intrinsics))
        for (source, _), (template, error, content) in zip(todo, results):
            status = "enrolled"
            if template is None:
                store.add_failure(source, error)
                report.failures.append((source, error))
                status = error
            else:
                try:
                    store.add(template, source, content)
                    report.enrolled += 1
                except AlreadyEnrolled:  # a copy of an enrolled scan, or enrolled meanwhile by another run
                    report.skipped.append(source)
                    status = "skipped"
            if on_result:
                on_result(source, status)
    finally:
        if own:
            engine.close()
    return report


def load_probe(store: GalleryStore, path: str | Path, config: PreprocessConfig | None = None,
               cache: str | Path | None = None, *, engine: Engine | None = None,
               intrinsics: str | Path | None = None) -> FaceScan:
    """A probe scan preprocessed with the gallery's settings (on the `engine`'s workers when given); `config`, if
    given, must be those settings; a depth frame is read with `intrinsics` (a JSON file) when given."""
    if config is not None:
        store.check_preprocess(config)
    settings = store.preprocess_config()
    outcome = (preprocess_file(path, settings, cache, intrinsics) if engine is None
               else list(engine.preprocess([path], settings, cache=cache, intrinsics=intrinsics))[0])
    if outcome.face is None:
        raise GalleryError(f"{printable(path)}: {outcome.error}")
    return outcome.face


def identify_scan(store: GalleryStore, probe: str | Path, *, k: int = 5, cascade: CascadeConfig | None = None,
                  config: PreprocessConfig | None = None, matcher: Matcher | None = None, engine: Engine | None = None,
                  cache: str | Path | None = None, intrinsics: str | Path | None = None) -> list[tuple[Entry, float]]:
    """The k best gallery entries for a probe scan, (entry, score) best first; the probe is read (a depth frame
    with `intrinsics` when given), preprocessed and matched on the `engine`'s workers (default: this process).
    A `matcher` given must be the gallery's (method and options)."""
    check_k(k)  # before any work
    stored = store.matcher()
    if matcher is not None:
        store.check_matcher(matcher)
    own = engine is None
    engine = engine or Engine.create(1)
    try:
        face = load_probe(store, probe, config, cache, engine=engine, intrinsics=intrinsics)
        entries = store.entries()
        if not entries:
            raise GalleryError(f"{store.path}: the gallery is empty")
        gallery = engine.load(stored, store.templates(entries))
        hits = gallery.identify(face, k, cascade)
        gallery.release()
    finally:
        if own:
            engine.close()
    return [(entries[i], s) for i, s in hits]


def verify_scan(store: GalleryStore, probe: str | Path, claim: str, *, threshold: float | None = None,
                config: PreprocessConfig | None = None, cache: str | Path | None = None,
                intrinsics: str | Path | None = None) -> tuple[bool, float, float]:
    """(accepted, score, threshold): the probe's best score against the claimed subject's templates, accepted
    when it reaches the threshold (default: the gallery's calibrated one, `gallery_threshold`). Methods whose scores
    are normalised over the gallery (`matching.base.GalleryNormalised`: `cohort_scores`) score the probe against the whole gallery.
    A depth frame is read with `intrinsics` (a JSON file) when given."""
    if not isinstance(claim, str) or not claim:  # entries(subject=None) would be every entry: anyone's claim
        raise GalleryError(f"{store.path}: a verification claims a subject (a non-empty text), not {claim!r}")
    if threshold is not None:  # before any work
        threshold = check_threshold(threshold)
    matcher = store.matcher()
    if threshold is None:
        threshold = float(gallery_threshold(store, matcher.name))
    claimed = [e.id for e in store.entries(subject=claim)]
    if not claimed:
        raise GalleryError(f"{store.path}: subject {claim!r} is not enrolled")
    entries = store.entries() if matcher.cohort_scores else store.entries(subject=claim)
    face = load_probe(store, probe, config, cache, intrinsics=intrinsics)
    scores, _ = matcher.scores(matcher.prepare(face), store.templates(entries))
    score = float(max(s for s, e in zip(scores, entries) if e.id in claimed))
    return score >= threshold, score, threshold

