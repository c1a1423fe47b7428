"""Preprocessing many files: in parallel processes, with failures recorded rather than raised.

A failure to acquire (ISO/IEC 19795-1: unreadable file, no face found) is
reported with its reason and the batch goes on.
"""

from __future__ import annotations

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


def preprocess_file(path: str | Path, config: PreprocessConfig = PreprocessConfig()) -> Outcome:
    """Load and preprocess one scan file; errors of facerec3d become a failed Outcome."""
    from facerec3d.io import load_scan

    try:
        return Outcome(str(path), Preprocessor(config)(load_scan(path)))
    except FaceRec3DError as e:
        return Outcome(str(path), None, getattr(e, "reason", str(e)))


def _run(args: tuple[str, PreprocessConfig]) -> Outcome:
    return preprocess_file(*args)


def preprocess_files(paths: Sequence[str | Path], config: PreprocessConfig = PreprocessConfig(),
                     jobs: int = 1) -> Iterator[Outcome]:
    """Outcomes in the order of `paths`, computed by `jobs` processes."""
    work = [(str(p), config) for p in paths]
    if jobs <= 1 or len(work) <= 1:
        yield from map(_run, work)
        return
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        yield from pool.map(_run, work, chunksize=1)
