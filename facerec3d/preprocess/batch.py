"""Preprocessing many files: in parallel processes, with failures recorded rather than raised, and cached.

A failure to acquire (ISO/IEC 19795-1: unreadable file, no face found) is
reported with its reason and the batch goes on. With a cache folder, each
result (face or failure) is kept under a key made of the file's path, size,
modification time and the whole preprocessing configuration, so a rerun or a
second method reuses the work.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from facerec3d.errors import FaceRec3DError
from facerec3d.preprocess.pipeline import PreprocessConfig, Preprocessor
from facerec3d.scan import FaceScan


@dataclass(frozen=True)
class Outcome:
    """The result of preprocessing one file: a face, or the reason it failed."""

    path: str
    face: FaceScan | None
    error: str | None = None


def cache_key(path: str | Path, config: PreprocessConfig, intrinsics: str | Path | None = None) -> str:
    """The cache key of a file under a configuration (path, size, mtime and settings; for a depth frame also the
    intrinsics file it is read with, by content)."""
    from facerec3d.io import DEPTH_SUFFIXES, find_intrinsics, scan_suffix

    p = Path(path).resolve()
    st = p.stat()
    text = f"{p}|{st.st_size}|{st.st_mtime_ns}|{config.fingerprint()}"
    camera = intrinsics if intrinsics is not None else (
        find_intrinsics(p) if scan_suffix(p) in DEPTH_SUFFIXES + (".npy",) else None)
    if camera is not None and Path(camera).is_file():
        text += "|" + Path(camera).read_bytes().hex()
    return hashlib.sha1(text.encode()).hexdigest()


def preprocess_file(path: str | Path, config: PreprocessConfig = PreprocessConfig(),
                    cache: str | Path | None = None, intrinsics: str | Path | None = None) -> Outcome:
    """Load and preprocess one scan file (a depth frame with `intrinsics` when given); errors of facerec3d become a
    failed Outcome."""
    from facerec3d.io import load_scan, save_scan, scan_stem

    stored = None
    if cache is not None and Path(path).is_file():
        stored = Path(cache) / cache_key(path, config, intrinsics)
        if stored.with_suffix(".npz").is_file():
            face = load_scan(stored.with_suffix(".npz"))
            return Outcome(str(path), face.replace(meta=face.meta.replace(path=str(path), scan_id=scan_stem(path))))
        if stored.with_suffix(".fail").is_file():
            return Outcome(str(path), None, stored.with_suffix(".fail").read_text())
    try:
        outcome = Outcome(str(path), Preprocessor(config)(load_scan(path, intrinsics)))
    except FaceRec3DError as e:
        outcome = Outcome(str(path), None, getattr(e, "reason", str(e)))
    if stored is not None:
        stored.parent.mkdir(parents=True, exist_ok=True)
        if outcome.face is not None:
            save_scan(outcome.face, stored.with_suffix(".npz"))
        else:
            stored.with_suffix(".fail").write_text(outcome.error)
    return outcome


def one_thread_per_process() -> None:
    """Worker initialiser: one BLAS/OpenMP thread per process, so N processes use N cores, not N²."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)


def _run(args: tuple[str, PreprocessConfig, str | None, str | None]) -> Outcome:
    return preprocess_file(*args)


def preprocess_files(paths: Sequence[str | Path], config: PreprocessConfig = PreprocessConfig(),
                     jobs: int = 1, cache: str | Path | None = None,
                     intrinsics: str | Path | None = None) -> Iterator[Outcome]:
    """Outcomes in the order of `paths`, computed by `jobs` processes (reusing `cache` when given; depth frames
    read with `intrinsics` when given)."""
    work = [(str(p), config, None if cache is None else str(cache), None if intrinsics is None else str(intrinsics))
            for p in paths]
    if jobs <= 1 or len(work) <= 1:
        from threadpoolctl import threadpool_limits

        with threadpool_limits(1):
            yield from map(_run, work)
        return
    with ProcessPoolExecutor(max_workers=jobs, initializer=one_thread_per_process) as pool:
        yield from pool.map(_run, work, chunksize=1)
