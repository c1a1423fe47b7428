"""One evaluation run end to end (chapter §8.4): preprocess (cached), enrol, match, score, report.

    evaluate("data/", method="icp", out="runs/icp")

Probes whose scan could not be preprocessed are failures to acquire (FTA);
gallery scans that could not be are failures to enrol (FTE), and their
subjects have no template. Both are listed in metrics.json under
`failed_scans` and counted in the figures "over all probes".
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from facerec3d.datasets.catalog import open_dataset
from facerec3d.evaluation.protocols import split
from facerec3d.evaluation.report import write_run
from facerec3d.matching.base import Matcher, Template
from facerec3d.preprocess.batch import one_thread_per_process, preprocess_files
from facerec3d.preprocess.pipeline import PreprocessConfig


def _icp() -> Matcher:
    from facerec3d.matching.icp import ICPMatcher

    return ICPMatcher()


#: Matching methods by name (`--method`).
METHODS: dict[str, Callable[[], Matcher]] = {"icp": _icp}

DEFAULT_CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "facerec3d" / "preprocessed"

_worker: dict = {}


def _init_worker(matcher: Matcher, gallery: list[Template], single_thread: bool = False) -> None:
    if single_thread:
        one_thread_per_process()
    _worker["matcher"], _worker["gallery"] = matcher, gallery


def _match(face) -> tuple[np.ndarray, np.ndarray]:
    scores, tiebreak = _worker["matcher"].scores(face, _worker["gallery"])
    return scores, (np.zeros_like(scores) if tiebreak is None else tiebreak)


def evaluate(data: str | Path, method: str = "icp", out: str | Path = "run", protocol: str | None = None,
             jobs: int = 1, cache: str | Path | None = DEFAULT_CACHE, config: PreprocessConfig = PreprocessConfig(),
             progress: bool = True) -> dict:
    """Evaluate `method` on the dataset at `data` and write the run folder `out`; returns metrics.json's content."""
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}: use one of {', '.join(METHODS)}")
    dataset = open_dataset(data)
    sp = split(dataset, protocol)
    recs = dataset.records
    timings: dict[str, float] = {}

    t0 = time.perf_counter()
    needed = sorted(set(sp.gallery) | set(sp.probes))
    outcomes = list(tqdm(preprocess_files([recs[i].path for i in needed], config, jobs, cache), total=len(needed),
                         desc="preprocessing", unit="scan", disable=not progress))
    faces, failed = {}, []
    for i, outcome in zip(needed, outcomes):
        if outcome.face is None:
            failed.append({"path": str(recs[i].path), "reason": outcome.error,
                           "role": "gallery" if i in sp.gallery else "probe"})
        else:
            faces[i] = outcome.face
    timings["preprocess_s"] = time.perf_counter() - t0

    matcher = METHODS[method]()
    t0 = time.perf_counter()
    enrolled = [i for i in sp.gallery if i in faces]
    gallery = [matcher.enroll(faces[i]) for i in enrolled]
    timings["enrol_s"] = time.perf_counter() - t0

    probes = [i for i in sp.probes if i in faces]
    t0 = time.perf_counter()
    prepared = [faces[i] for i in probes]
    if jobs > 1 and len(prepared) > 1:
        with ProcessPoolExecutor(jobs, initializer=_init_worker, initargs=(matcher, gallery, True)) as pool:
            rows = list(tqdm(pool.map(_match, prepared, chunksize=1), total=len(prepared), desc="matching",
                             unit="probe", disable=not progress))
    else:
        _init_worker(matcher, gallery)
        with threadpool_limits(1):
            rows = [_match(p) for p in tqdm(prepared, desc="matching", unit="probe", disable=not progress)]
    S = np.array([r[0] for r in rows]).reshape(len(probes), len(gallery))
    tiebreak = np.array([r[1] for r in rows]).reshape(S.shape)
    if sp.exclude_self:
        S[np.equal.outer(probes, enrolled)] = np.nan
    match_s = time.perf_counter() - t0
    n_matches = max(S.size, 1)
    timings.update(match_s=match_s, match_ms=1000 * match_s / n_matches, matches_per_s=n_matches / max(match_s, 1e-9))

    failed_probe = {i for i in sp.probes if i not in faces}
    masks, subset_failures = {}, {}
    for name, members in sp.subsets.items():
        chosen = {sp.probes[k] for k in members}
        masks[name] = np.array([i in chosen for i in probes], dtype=bool)
        subset_failures[name] = len(chosen & failed_probe)
    info = {"method": method, "protocol": sp.protocol, "dataset": str(data), "layout": dataset.layout,
            "n_gallery": len(gallery), "failures_to_enrol": sum(f["role"] == "gallery" for f in failed),
            "failed_scans": failed, "timings": timings, "jobs": jobs}
    return write_run(out, S, [recs[i].subject for i in probes], [recs[i].scan_id for i in probes],
                     [recs[i].subject for i in enrolled], info, tiebreak=tiebreak, subsets=masks,
                     n_failed=len(failed_probe), subset_failures=subset_failures)
