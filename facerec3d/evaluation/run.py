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
from collections.abc import Mapping
from typing import Any
from dataclasses import asdict
from pathlib import Path

import numpy as np
from tqdm import tqdm

from facerec3d.datasets.catalog import open_dataset
from facerec3d.evaluation.protocols import split
from facerec3d.evaluation.report import write_run
from facerec3d.errors import FaceRec3DError
from facerec3d.gallery.cascade import CascadeConfig, check_cascadable
from facerec3d.gallery.engine import Engine
from facerec3d.matching.base import Matcher
from facerec3d.matching.keypoints import KeypointMatcher
from facerec3d.matching.registry import load_matcher, make_matcher
from facerec3d.preprocess.batch import preprocess_files
from facerec3d.preprocess.pipeline import QUALITY_FIELDS, PreprocessConfig, scan_quality


DEFAULT_CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "facerec3d" / "preprocessed"

def _preprocess(paths: list, config: PreprocessConfig, jobs: int, cache, progress: bool, desc: str,
                intrinsics=None) -> list:
    return list(tqdm(preprocess_files(paths, config, jobs, cache, intrinsics), total=len(paths), desc=desc,
                     unit="scan", disable=not progress))


def trained_matcher(method: str, options: Mapping[str, Any] | None = None, train: str | Path | None = None,
                    model: str | Path | None = None, jobs: int = 1, cache: str | Path | None = DEFAULT_CACHE,
                    config: PreprocessConfig = PreprocessConfig(), progress: bool = True) -> tuple[Matcher, dict]:
    """A matcher ready to enrol: loaded from `model`, or built from (method, options) and fitted on the
    dataset `train` (every scan that preprocesses; failures are skipped and counted).
    Returns (matcher, info about the training)."""
    if model is not None:
        matcher = load_matcher(model)
        return matcher, {"model": str(model)}
    matcher = make_matcher(method, options)
    if train is None:
        if matcher.needs_training:
            raise FaceRec3DError(f"method {method!r} learns from data: give a training set (--train DATA) "
                                 "of subjects not in the test set, or a saved model (--model FILE)")
        return matcher, {}
    records = open_dataset(train).records
    t0 = time.perf_counter()
    outcomes = _preprocess([r.path for r in records], config, jobs, cache, progress, "training set")
    kept = [(o.face, r.subject) for o, r in zip(outcomes, records) if o.face is not None]
    if not kept:
        raise FaceRec3DError(f"{train}: no training scan could be preprocessed")
    matcher.fit([f for f, _ in kept], [s for _, s in kept])
    return matcher, {"train": str(train), "n_train": len(kept), "train_failures": len(records) - len(kept),
                     "n_train_subjects": len({s for _, s in kept}), "fit_s": time.perf_counter() - t0}


def evaluate(data: str | Path, method: str = "icp", out: str | Path = "run", protocol: str | None = None,
             jobs: int = 1, cache: str | Path | None = DEFAULT_CACHE, config: PreprocessConfig = PreprocessConfig(),
             progress: bool = True, options: Mapping[str, Any] | None = None, train: str | Path | None = None,
             model: str | Path | None = None, scheduler=None, cascade: CascadeConfig | None = None,
             intrinsics: str | Path | None = None) -> dict:
    """Evaluate `method` (with config `options`) on the dataset at `data` and write the run folder `out`;
    returns metrics.json's content. Learnt methods are fitted on the dataset `train` (and the model saved
    as out/model.npz) or loaded from `model`. Enrolment and matching run on a `gallery.engine.Engine`:
    `jobs` processes, or the workers of a Dask `scheduler` (address or Client). With `cascade` (ICP only)
    identification goes through the cascade (gallery.cascade; its screen the depth descriptor or the keypoint
    matcher, whose gallery is then enrolled too): faces off the shortlist score −inf, and
    metrics.json's "cascade" gives its settings and recall (share of probes of enrolled subjects whose
    subject is on the shortlist). Depth frames are read with `intrinsics` (a JSON file) when given, else with
    the intrinsics.json found beside them."""
    matcher, training = trained_matcher(method, options, train, model, jobs, cache, config, progress)
    if cascade is not None:
        check_cascadable(matcher)
    method = matcher.name
    dataset = open_dataset(data)
    sp = split(dataset, protocol)
    recs = dataset.records
    timings: dict[str, float] = {}
    if "fit_s" in training:
        timings["fit_s"] = training.pop("fit_s")
        Path(out).mkdir(parents=True, exist_ok=True)
        matcher.save(Path(out) / "model.npz")

    t0 = time.perf_counter()
    needed = sorted(set(sp.gallery) | set(sp.probes))
    outcomes = _preprocess([recs[i].path for i in needed], config, jobs, cache, progress, "preprocessing", intrinsics)
    faces, failed = {}, []
    for i, outcome in zip(needed, outcomes):
        if outcome.face is None:
            failed.append({"path": str(recs[i].path), "reason": outcome.error,
                           "role": "gallery" if i in sp.gallery else "probe"})
        else:
            faces[i] = outcome.face
    timings["preprocess_s"] = time.perf_counter() - t0

    enrolled = [i for i in sp.gallery if i in faces]
    probes = [i for i in sp.probes if i in faces]
    info_cascade = {}
    with Engine.create(jobs, scheduler) as engine:
        workers = engine.workers
        t0 = time.perf_counter()
        gallery = engine.enroll(matcher, [faces[i] for i in enrolled])
        keypoints = KeypointMatcher() if cascade is not None and cascade.screen == "keypoints" else None
        if keypoints is not None:  # the screen's own gallery, sharded alike
            screen_gallery = engine.load(keypoints, engine.enroll(keypoints, [faces[i] for i in enrolled]))
        timings["enrol_s"] = time.perf_counter() - t0
        timings["enrol_ms"] = 1000 * timings["enrol_s"] / max(len(gallery), 1)

        t0 = time.perf_counter()
        sharded = engine.load(matcher, gallery)
        rows, prepare_s = [], 0.0
        batch = 8 * engine.workers  # probes in flight at once (progress is shown per batch)
        with tqdm(total=len(probes), desc="matching", unit="probe", disable=not progress) as bar:
            for b in range(0, len(probes), batch):
                t1 = time.perf_counter()
                chunk_faces = [faces[i] for i in probes[b:b + batch]]
                chunk = engine.prepare(matcher, chunk_faces, cascade)
                prepare_s += time.perf_counter() - t1
                if cascade is None:
                    rows += sharded.scores(chunk)
                else:
                    screen = None if keypoints is None else screen_gallery.scores(
                        engine.prepare(keypoints, chunk_faces))
                    rows += sharded.cascade(chunk, cascade, screen)
                bar.update(len(chunk))
    S = np.array([r[0] for r in rows]).reshape(len(probes), len(gallery))
    tiebreak = np.array([r[1] for r in rows]).reshape(S.shape)
    if cascade is not None:
        enrolled_subjects = {recs[i].subject for i in enrolled}
        hits = [recs[p].subject in {recs[enrolled[j]].subject for j in r[2]}
                for p, r in zip(probes, rows) if recs[p].subject in enrolled_subjects]
        info_cascade = {"cascade": {**asdict(cascade), "recall": float(np.mean(hits)) if hits else None}}
    if sp.exclude_self:
        S[np.equal.outer(probes, enrolled)] = np.nan
    match_s = time.perf_counter() - t0
    n_matches = max(S.size, 1)
    # match_ms: per comparison, the probe's preparation (features, normals: once per probe) not included
    timings.update(match_s=match_s, prepare_ms=1000 * prepare_s / max(len(probes), 1),
                   match_ms=1000 * (match_s - prepare_s) / n_matches, matches_per_s=n_matches / max(match_s, 1e-9))

    failed_probe = {i for i in sp.probes if i not in faces}
    masks, subset_failures = {}, {}
    for name, members in sp.subsets.items():
        chosen = {sp.probes[k] for k in members}
        masks[name] = np.array([i in chosen for i in probes], dtype=bool)
        subset_failures[name] = len(chosen & failed_probe)
    quality = [{"path": str(recs[i].path), "role": "gallery" if i in sp.gallery else "probe", **scan_quality(faces[i])}
               for i in needed if i in faces]
    info = {"method": method, "options": matcher.options(), **training, "protocol": sp.protocol, "dataset": str(data), "layout": dataset.layout,
            "n_gallery": len(gallery), "failures_to_enrol": sum(f["role"] == "gallery" for f in failed),
            "failed_scans": failed, "timings": timings, "jobs": jobs, "workers": workers, **info_cascade,
            "quality_median": {k: float(np.median([q[k] for q in quality if k in q]))
                               for k in QUALITY_FIELDS if any(k in q for q in quality)},
            "scan_quality": quality}
    return write_run(out, S, [recs[i].subject for i in probes], [recs[i].scan_id for i in probes],
                     [recs[i].subject for i in enrolled], info, tiebreak=tiebreak, subsets=masks,
                     n_failed=len(failed_probe), subset_failures=subset_failures)
