"""One evaluation run end to end (chapter §8.4): preprocess (cached), enrol, match, score, report.

    evaluate("data/", method="icp", out="runs/icp", jobs=4)      # or scheduler="tcp://host:8786"

All the work (reading and preprocessing the training and test scans, enrolment, matching) runs on one
`gallery.engine.Engine`: local processes, or the workers of a Dask cluster.

Probes whose scan could not be preprocessed are failures to acquire (FTA);
gallery scans that could not be are failures to enrol (FTE), and their
subjects have no template. Both are listed in metrics.json under
`failed_scans` and counted in the figures "over all probes".
"""

from __future__ import annotations

import json
import time
from collections import Counter
from collections.abc import Callable, Mapping
from typing import Any
from dataclasses import asdict
from pathlib import Path

import numpy as np
from tqdm import tqdm

from facerec3d.datasets.catalog import open_dataset
from facerec3d.datasets.protocols import split
from facerec3d.evaluation.metrics import BOOTSTRAP
from facerec3d.evaluation.provenance import provenance
from facerec3d.evaluation.report import run_folder, write_run
from facerec3d.gallery.cascade import Cascade, CascadeConfig, check_cascadable
from facerec3d.gallery.engine import Engine, merged
from facerec3d.matching.base import GalleryNormalised, scores_over
from facerec3d.matching.registry import DEFAULT_METHOD, make_matcher, trained_matcher
from facerec3d.preprocess.batch import DEFAULT_CACHE
from facerec3d.preprocess.pipeline import QUALITY_FIELDS, PreprocessConfig, scan_quality


def evaluate(data: str | Path, method: str = DEFAULT_METHOD, out: str | Path = "run", *, protocol: str | None = None,
             jobs: int = 1, scheduler: Any = None, cache: str | Path | None = DEFAULT_CACHE,
             config: PreprocessConfig = PreprocessConfig(), options: Mapping[str, Any] | None = None,
             train: str | Path | None = None, model: str | Path | None = None, cascade: CascadeConfig | None = None,
             intrinsics: str | Path | None = None, bootstrap: int = BOOTSTRAP, seed: int = 0,
             progress: bool = True, overwrite: bool = True, echo: Callable[[str], None] | None = None) -> dict:
    """Evaluate `method` (with config `options`) on the dataset at `data` and write the run folder `out`;
    returns metrics.json's content. Learnt methods are fitted on the dataset `train` (and the model saved
    as out/model.npz) or loaded from `model`. Everything runs on a `gallery.engine.Engine`: `jobs` processes,
    or the workers of a Dask `scheduler` (address or Client; the data, and the `cache` folder, on storage they
    see under the same paths). With `cascade` (ICP only)
    identification goes through the cascade (gallery.cascade; its screen the depth descriptor or the keypoint
    matcher, whose gallery is then enrolled too): faces off the shortlist score −inf, and
    metrics.json's "cascade" gives its settings and recall (share of probes of enrolled subjects whose
    subject is on the shortlist). Depth frames are read with `intrinsics` (a JSON file) when given, else with
    the intrinsics.json found beside them. Figures get 95 % intervals from `bootstrap` subject-level
    replicates drawn with `seed` (see metrics.summarize).

    The run folder also keeps the settings: method.json (the method's options; model.npz instead for a learnt
    or loaded model) and preprocess.json, and metrics.json's "provenance" holds the command that repeats the
    run from them (`rerun`), with version, git commit, date and machine. Timings separate first use (worker
    start, JIT compilation: the first template and the first probe of each worker) from the steady state, and
    cached from computed preprocessing.

    A folder `out` that holds an earlier run is refused unless `overwrite` (the command line's --overwrite; here
    the default), and then that run's files are removed first (`report.RUN_FILES`), so none is left over. The new
    run is written beside `out` and moved into it at the end (`report.run_folder`): an interrupted run leaves none
    of its files there.
    `echo` (the command line's stderr) is told what a learnt method learnt from (`registry.trained_matcher`)."""
    dataset = open_dataset(data)
    sp = split(dataset, protocol)  # a dataset the protocol does not suit is refused before any work
    with run_folder(out, overwrite, keep=[model]) as work:  # the run is written there, moved into `out` at the end
        if cascade is not None and model is None:  # refused before any training, not after
            check_cascadable(make_matcher(method, options))
        with Engine.create(jobs, scheduler, items=len(dataset.records)) as engine:  # no more processes than scans
            matcher, training = trained_matcher(method, options, train=train, model=model, workers=engine,
                                                cache=cache, config=config, progress=progress, echo=echo)
            if cascade is not None:
                check_cascadable(matcher)
            return _evaluate(engine, matcher, training, dataset, sp, data, out, work, jobs=jobs, cache=cache,
                             config=config, model=model, cascade=cascade, intrinsics=intrinsics,
                             bootstrap=bootstrap, seed=seed, progress=progress)


def _evaluate(engine: Engine, matcher, training: dict, dataset, sp, data: str | Path, out: str | Path, work: Path, *,
              jobs, cache, config, model, cascade, intrinsics, bootstrap, seed, progress) -> dict:
    """`evaluate` with its engine, (trained) matcher, dataset and split; the run folder `out` written in `work`
    (run_folder), its files named where they will be, in `out`."""
    method = matcher.name
    recs = dataset.records
    out = Path(out)
    timings: dict[str, float] = {}
    if "fit_s" in training:
        timings["fit_s"] = training.pop("fit_s")
        matcher.save(work / "model.npz")
        model = out / "model.npz"

    t0 = time.perf_counter()
    needed = sorted(set(sp.gallery) | set(sp.probes))
    outcomes = list(tqdm(engine.preprocess([recs[i].path for i in needed], config, cache=cache, intrinsics=intrinsics),
                         total=len(needed), desc="preprocessing", unit="scan", disable=not progress))
    faces, failed = {}, []
    for i, outcome in zip(needed, outcomes):
        if outcome.face is None:
            failed.append({"path": str(recs[i].path), "reason": outcome.error,
                           "role": "gallery" if i in sp.gallery else "probe"})
        else:  # the face named as the protocol names it (a frame's meta may not know its person: PNG frames)
            face = outcome.face
            faces[i] = face if face.meta.subject == recs[i].subject else \
                face.replace(meta=face.meta.replace(subject=recs[i].subject))
    timings["preprocess_s"] = time.perf_counter() - t0
    for kind, chosen in (("computed", [o for o in outcomes if not o.cached]), ("cached", [o for o in outcomes if o.cached])):
        timings[f"preprocess_{kind}"] = len(chosen)
        timings[f"preprocess_{kind}_ms"] = 1000 * float(np.mean([o.seconds for o in chosen])) if chosen else 0.0

    enrolled = [i for i in sp.gallery if i in faces]
    probes = [i for i in sp.probes if i in faces]
    workers = engine.workers
    t0 = time.perf_counter()
    with tqdm(total=len(enrolled), desc="enrolling", unit="scan", disable=not progress) as bar:
        gallery = engine.enroll(matcher, [faces[i] for i in enrolled[:workers]])  # first use: one per worker
        bar.update(len(gallery))
        timings["enrol_first_s"] = time.perf_counter() - t0
        t1 = time.perf_counter()
        for a in range(workers, len(enrolled), 8 * workers):  # in batches, so that the bar moves
            gallery += engine.enroll(matcher, [faces[i] for i in enrolled[a:a + 8 * workers]])
            bar.update(len(gallery) - bar.n)
        steady = (time.perf_counter() - t1, len(enrolled) - workers) if len(enrolled) > workers else \
            (timings["enrol_first_s"], len(enrolled))
        search = None if cascade is None else Cascade(cascade)
        if search is not None:  # the keypoint screen's own gallery, sharded alike
            bar.set_postfix_str("keypoint screen")
            search.load_screen(engine, [faces[i] for i in enrolled])
    timings["enrol_s"] = time.perf_counter() - t0
    timings["enrol_ms"] = 1000 * steady[0] / max(steady[1], 1)

    t0 = time.perf_counter()
    sharded = engine.load(matcher, gallery)
    rows = []  # GalleryScores, or CascadeScores with the cascade
    # a method normalised over the gallery scores a stranger's claim (someone not enrolled) over every entry but
    # the claimant's own, not among them: those impostor scores too, for the strangers' figures (write_run)
    cohort_normalised = search is None and isinstance(matcher, GalleryNormalised)
    gallery_subjects = np.array([str(recs[i].subject) for i in enrolled])
    strangers = []
    batch = 8 * workers  # probes in flight at once (progress is shown per batch)
    batches = [(0, min(workers, len(probes)))] + [(b, min(b + batch, len(probes)))
                                                   for b in range(workers, len(probes), batch)]
    spent = []  # (seconds, preparation seconds, probes) per batch
    with tqdm(total=len(probes), desc="matching", unit="probe", disable=not progress) as bar:
        for a, b in batches:
            t1 = time.perf_counter()
            chunk_faces = [faces[i] for i in probes[a:b]]
            chunk = engine.prepare(matcher, chunk_faces, cascade)
            prepare_s = time.perf_counter() - t1
            if cohort_normalised:
                for i, r in zip(probes[a:b], sharded.shard_rows(chunk)):
                    rows.append(merged(matcher, r))
                    strangers.append(scores_over(matcher, r, gallery_subjects != str(recs[i].subject)))
            elif search is None:
                rows += sharded.scores(chunk)
            else:
                rows += search.search(sharded, chunk, search.screen_scores(engine, chunk_faces))
            spent.append((time.perf_counter() - (t0 if a == 0 else t1), prepare_s, b - a))
            bar.update(len(chunk))
    S = np.array([r.scores for r in rows]).reshape(len(probes), len(gallery))
    tiebreak = np.array([r.tiebreak for r in rows]).reshape(S.shape)
    info_cascade = {}
    if search is not None:
        recall = search.recall(rows, [recs[p].subject for p in probes], [recs[i].subject for i in enrolled])
        info_cascade = {"cascade": {**asdict(cascade), "recall": recall}}
    mateless = None
    if sp.exclude_self:
        S[np.equal.outer(probes, enrolled)] = np.nan
        # a probe whose person's only enrolled scan is itself has no mate to find: a search of a person not
        # enrolled (as in the other protocols), not a rank-1 miss
        scans, enrolled_set = Counter(recs[i].subject for i in enrolled), set(enrolled)
        mateless = [scans[recs[i].subject] - (i in enrolled_set) == 0 for i in probes]
    # first use: the gallery loaded into the workers and one probe each; steady state: the other batches.
    # match_ms: per comparison, the probe's preparation (features, normals: once per probe) not included
    timings["match_first_s"] = spent[0][0]
    match_s, prepare_s, n_steady = np.sum(spent[1:] or spent[:1], axis=0)
    n_matches = n_steady * len(gallery)
    timings.update(match_s=time.perf_counter() - t0)
    if n_matches:  # (none when no probe or no gallery face was left)
        timings.update(prepare_ms=1000 * prepare_s / n_steady, match_ms=1000 * (match_s - prepare_s) / n_matches,
                       matches_per_s=n_matches / max(match_s, 1e-9))

    failed_probes = [i for i in sp.probes if i not in faces]
    masks, subset_failures = {}, {}
    for name, members in sp.subsets.items():
        chosen = {sp.probes[k] for k in members}
        masks[name] = np.array([i in chosen for i in probes], dtype=bool)
        subset_failures[name] = [dataset.label(recs[i]) for i in failed_probes if i in chosen]
    position = {i: k for k, i in enumerate(sp.probes)}, {i: k for k, i in enumerate(sp.gallery)}
    pair_masks = {name: m[np.ix_([position[0][i] for i in probes], [position[1][i] for i in enrolled])]
                  for name, m in sp.masks.items()}
    quality = [{"path": str(recs[i].path), "role": "gallery" if i in sp.gallery else "probe", **scan_quality(faces[i])}
               for i in needed if i in faces]
    settings = {"preprocess": out / "preprocess.json", "method": out / "method.json"}
    (work / settings["preprocess"].name).write_text(json.dumps(config.to_dict(), indent=2) + "\n", encoding="utf-8")
    if model is None:
        (work / settings["method"].name).write_text(json.dumps(matcher.options(), indent=2) + "\n", encoding="utf-8")
    rerun = ["facerec3d", "evaluate", Path(data).resolve(), "--out", out.resolve(),
             *(["--model", Path(model).resolve()] if model is not None else
               ["--method", method, "--method-config", settings["method"].resolve()]),
             "--config", settings["preprocess"].resolve(), "--protocol", sp.protocol, "--jobs", jobs,
             "--bootstrap", bootstrap, "--seed", seed,
             *(["--cache", Path(cache).resolve()] if cache is not None else []),
             *(["--cascade", "--shortlist", cascade.shortlist, "--screen", cascade.screen] if cascade else []),
             *(["--intrinsics", Path(intrinsics).resolve()] if intrinsics is not None else [])]
    info = {"method": method, "options": matcher.options(), **training, "protocol": sp.protocol,
            **({"protocol_note": sp.note} if sp.note else {}), "dataset": str(data), "layout": dataset.layout,
            "n_gallery": len(gallery), "failures_to_enrol": sum(f["role"] == "gallery" for f in failed),
            "failed_scans": failed, "timings": timings, "jobs": jobs, "workers": workers, **info_cascade,
            "preprocess": config.to_dict(), "provenance": provenance(rerun),
            "quality_median": {k: float(np.median([q[k] for q in quality if k in q]))
                               for k in QUALITY_FIELDS if any(k in q for q in quality)},
            "scan_quality": quality}
    return write_run(work, S, [recs[i].subject for i in probes], [dataset.label(recs[i]) for i in probes],
                     [recs[i].subject for i in enrolled], info, tiebreak=tiebreak, subsets=masks,
                     subset_failures=subset_failures, failed=[(dataset.label(recs[i]), recs[i].subject) for i in failed_probes],
                     masks=pair_masks, bootstrap=bootstrap, seed=seed,
                     mateless=mateless, strangers=np.array(strangers).reshape(S.shape) if cohort_normalised else None,
                     unenrolled=sorted({recs[i].subject for i in sp.gallery if i not in faces} - {recs[i].subject for i in enrolled}))
