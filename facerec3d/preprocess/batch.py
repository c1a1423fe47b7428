"""Preprocessing many files: on parallel workers, with failures recorded rather than raised, and cached.

A failure to acquire (ISO/IEC 19795-1: unreadable file, no face found) is
reported with its reason and the batch goes on. With a cache folder, each
face, and each failure that belongs to the scan itself (`SCAN_FAILURES`; not an
internal error or memory running out, which are that run's), is kept under a
key made of the file's path, size, modification time, the whole preprocessing
configuration and the code that preprocesses (`code_stamp`: a new version of
facerec3d makes new entries), so a rerun or a second method reuses the work.
Entries are written atomically, so workers in several processes or on several
machines (a Dask cluster sharing the folder) can fill one cache at the same time.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import time
import uuid
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path

from facerec3d.errors import FaceRec3DError, FailureToAcquire, ScanFormatError
from facerec3d.preprocess.pipeline import PreprocessConfig, Preprocessor
from facerec3d.scan import FaceScan
from facerec3d.workers import Workers, one_thread_per_process  # noqa: F401 (server.app imports it from here)

#: The preprocessing cache of the command line (`--cache` changes it).
DEFAULT_CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "facerec3d" / "preprocessed"


@dataclass(frozen=True)
class Outcome:
    """The result of preprocessing one file: a face, or the reason it failed."""

    path: str
    face: FaceScan | None
    error: str | None = None
    cached: bool = False  # read from the cache, not computed
    seconds: float = 0.0  # time to load or compute it (in the worker)


#: The failures that belong to the scan itself, which every run would meet again (a file that cannot be read, no
#: face found in it): the only ones cached. Any other (an internal error, memory running out, a model file that
#: cannot be read) is that run's: reported, never kept (a MemoryError once failed every scan of later runs too).
SCAN_FAILURES = (FailureToAcquire, ScanFormatError)


PACKAGE = Path(__file__).resolve().parent.parent
#: What a preprocessed face is made by: the modules that read and preprocess a scan (those `preprocess` imports)
#: and the morphable model's data. The nose proposer's model is in the settings' fingerprint already.
CODE = ("scan.py", "config.py", "io/*.py", "preprocess/*.py", "geometry/*.py", "facemodel/*.py",
        "facemodel/data/*.npz")


@lru_cache(maxsize=None)
def code_stamp(package: Path = PACKAGE) -> str:
    """A digest of the text of the code (and model data) that preprocesses a scan (`CODE`, under `package`): part of
    every cache key, so that faces preprocessed by another version of facerec3d (an upgrade, a `git pull`, an edit
    of an editable install) are made again rather than mixed with the new ones. Read once per process (~20 ms)."""
    digest = hashlib.sha256()
    for path in sorted({p for pattern in CODE for p in package.glob(pattern) if p.is_file()}):
        digest.update(path.relative_to(package).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()


def printable(path: str | Path) -> str:
    """A path as UTF-8 text: itself, or for a file name that is not UTF-8 (its bytes held as surrogates by Python)
    those bytes written as \\xNN, which any report or store can hold."""
    text = str(path)
    try:
        text.encode("utf-8")
        return text
    except UnicodeEncodeError:
        return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


def cache_key(path: str | Path, config: PreprocessConfig, intrinsics: str | Path | None = None) -> str:
    """The cache key of a file under a configuration (path, size, mtime, settings and `code_stamp`; for a depth frame
    also the intrinsics file it is read with, by content)."""
    from facerec3d.io import DEPTH_SUFFIXES, find_intrinsics, scan_suffix

    p = Path(path).resolve()
    st = p.stat()
    text = f"{p}|{st.st_size}|{st.st_mtime_ns}|{config.fingerprint()}|{code_stamp()}"
    camera = intrinsics if intrinsics is not None else (
        find_intrinsics(p) if scan_suffix(p) in DEPTH_SUFFIXES + (".npy",) else None)
    if camera is not None and Path(camera).is_file():
        text += "|" + Path(camera).read_bytes().hex()
    return hashlib.sha1(text.encode("utf-8", "surrogateescape")).hexdigest()


def preprocess_file(path: str | Path, config: PreprocessConfig = PreprocessConfig(),
                    cache: str | Path | None = None, intrinsics: str | Path | None = None) -> Outcome:
    """Load and preprocess one scan file (a depth frame with `intrinsics` when given); errors of facerec3d become a
    failed Outcome with their reason, and so does any other exception (an internal error, named), so that a batch
    records the failure and goes on."""
    from facerec3d.io import load_scan

    t0 = time.perf_counter()
    if (shown := printable(path)) != str(path):  # every report and store holds names as UTF-8 text
        return Outcome(shown, None, "the file name is not UTF-8 text (the bytes shown as \\x..): rename the file")
    stored = None
    if cache is not None and Path(path).is_file():
        stored = Path(cache) / cache_key(path, config, intrinsics)
        if (outcome := _read_cache(stored, path)) is not None:
            return replace(outcome, seconds=time.perf_counter() - t0)
    failure = None  # the SCAN_FAILURES type the scan failed with, which is cached
    try:
        outcome = Outcome(str(path), Preprocessor(config)(load_scan(path, intrinsics)))
    except FaceRec3DError as e:
        outcome = Outcome(str(path), None, getattr(e, "reason", str(e)))
        failure = type(e).__name__ if isinstance(e, SCAN_FAILURES) else None
    except Exception as e:  # noqa: BLE001 - a scan no check foresaw: recorded as its failure, the batch goes on
        outcome = Outcome(str(path), None, f"internal error ({type(e).__name__}: {e}); please report it"[:500])
    if stored is not None and (outcome.face is not None or failure is not None):
        _write_cache(stored, outcome, failure)
    return replace(outcome, seconds=time.perf_counter() - t0)


_ENTRY = re.compile(r"^[0-9a-f]{40}(\.npz|\.fail|\..+\.tmp\.(npz|fail))$")  # cache_key + suffix, or a write's temp file


def cache_entries(cache: str | Path) -> list[Path]:
    """The entries of a cache folder (faces `.npz`, failures `.fail`, unfinished writes), nothing else in it."""
    folder = Path(cache)
    return sorted(p for p in folder.iterdir() if _ENTRY.match(p.name) and p.is_file()) if folder.is_dir() else []


def _read_cache(stored: Path, path: str | Path) -> Outcome | None:
    """The cached outcome under key path `stored` (face `.npz` or failure `.fail`), or None when there is none or
    it is damaged (truncated, garbled, or a folder under an entry's name): a damaged entry is removed, to be
    computed again (a folder stayed, and the new entry's rename onto it stopped the whole run)."""
    from facerec3d.io import load_scan, scan_stem

    face_file, fail_file = stored.with_suffix(".npz"), stored.with_suffix(".fail")
    try:
        if face_file.is_file():
            face = load_scan(face_file)
            return Outcome(str(path), face.replace(meta=face.meta.replace(path=str(path), scan_id=scan_stem(path))),
                           cached=True)
        if fail_file.is_file():
            if reason := _failure_reason(fail_file.read_text(encoding="utf-8")):
                return Outcome(str(path), None, reason, cached=True)
        elif not (os.path.lexists(face_file) or os.path.lexists(fail_file)):
            return None  # no entry (nothing removed: another worker may be writing it now)
    except (FaceRec3DError, OSError, UnicodeDecodeError):
        pass
    for damaged in (face_file, fail_file):
        if damaged.is_dir() and not damaged.is_symlink():
            shutil.rmtree(damaged, ignore_errors=True)
        else:
            damaged.unlink(missing_ok=True)
    return None


def _failure_reason(text: str) -> str | None:
    """The reason a `.fail` entry records (`_write_cache`), or None when the text is no such record (damaged)."""
    try:
        entry = json.loads(text)
    except (ValueError, RecursionError):
        return None
    if (isinstance(entry, dict) and entry.keys() == {"failure", "reason"} and isinstance(entry["reason"], str)
            and entry["failure"] in {t.__name__ for t in SCAN_FAILURES}):
        return entry["reason"]
    return None


def _write_cache(stored: Path, outcome: Outcome, failure: str | None = None) -> None:
    """Cache an outcome atomically: written to a temporary file, then renamed over the entry (os.replace), so a
    killed process or a concurrent writer never leaves a partial entry. A failure (of type `failure`, a name of
    `SCAN_FAILURES`) is kept as JSON `{"failure": ..., "reason": ...}`, which `_failure_reason` reads back."""
    from facerec3d.io import save_scan

    suffix = ".npz" if outcome.face is not None else ".fail"
    stored.parent.mkdir(parents=True, exist_ok=True)
    tmp = stored.with_name(f"{stored.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp{suffix}")
    try:
        if outcome.face is not None:
            save_scan(outcome.face, tmp)
        else:
            tmp.write_text(json.dumps({"failure": failure, "reason": outcome.error}), encoding="utf-8")
        try:
            os.replace(tmp, stored.with_suffix(suffix))
        except IsADirectoryError:
            pass  # a folder under the entry's name that could not be removed: this scan goes uncached, the run on
    finally:
        tmp.unlink(missing_ok=True)


def preprocess_files(paths: Sequence[str | Path], config: PreprocessConfig = PreprocessConfig(), *,
                     workers: Workers | None = None, jobs: int = 1, cache: str | Path | None = None,
                     intrinsics: str | Path | None = None) -> Iterator[Outcome]:
    """Outcomes in the order of `paths`, computed on `workers` (an engine's: local processes or Dask workers), or
    else by `jobs` local processes started for the batch; reusing `cache` when given (a folder the workers
    share); depth frames read with `intrinsics` when given. One path alone (a string) is one file, not a
    sequence of characters."""
    args = (config, None if cache is None else str(cache), None if intrinsics is None else str(intrinsics))
    files = [str(paths)] if isinstance(paths, (str, os.PathLike)) else [str(p) for p in paths]
    if workers is not None:
        yield from workers.imap(preprocess_file, files, *args)
        return
    with Workers.create(jobs, items=len(files)) as own:
        yield from own.imap(preprocess_file, files, *args)
