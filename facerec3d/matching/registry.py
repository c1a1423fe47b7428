"""Matching methods by name (`facerec3d evaluate --method NAME`), built with options, trained, saved and loaded.

    matcher = make_matcher("icp", {"variant": "point-to-plane"})
    matcher.save("model.npz"); same = load_matcher("model.npz")
    matcher, info = trained_matcher("lda", train="train-data/", workers=engine)

Each method's module is imported only when the method is used.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from os import PathLike
from pathlib import Path
from typing import Any

from tqdm import tqdm

from facerec3d.config import DEFAULT_METHOD  # noqa: F401 - the default method, beside the methods
from facerec3d.datasets.catalog import open_dataset
from facerec3d.errors import FaceRec3DError
from facerec3d.matching.base import Matcher, Template
from facerec3d.matching.methods import METHODS as SINGLE_METHODS
from facerec3d.matching.methods import method_class
from facerec3d.preprocess.batch import DEFAULT_CACHE, preprocess_files
from facerec3d.preprocess.pipeline import PreprocessConfig
from facerec3d.workers import Workers

#: Method name → "module:class": the single methods (matching.methods) and their fusion (§8.10).
METHODS: dict[str, str] = {**SINGLE_METHODS, "fusion": "facerec3d.matching.fusion:FusionMatcher"}



def matcher_class(method: str) -> type[Matcher]:
    """The Matcher subclass of a method name."""
    return method_class(method, METHODS)


def make_matcher(method: str, options: Mapping[str, Any] | None = None) -> Matcher:
    """A new matcher of this method with these config fields changed (a method config's table)."""
    return matcher_class(method).from_options(options)


def stored_matcher(method: str, options: Mapping[str, Any] | None) -> Matcher:
    """The matcher of a method and options stored with templates (`Matcher.from_stored`)."""
    return matcher_class(method).from_stored(options)


def load_matcher(path: str | PathLike) -> Matcher:
    """A matcher saved by `Matcher.save`: its method, settings and what it learnt."""
    try:
        t = Template.load(path)
        options, state = t.attrs["options"], t.attrs["state"]
    except (OSError, ValueError, KeyError) as e:
        raise FaceRec3DError(f"{path}: not a facerec3d model file ({e})") from None
    matcher = stored_matcher(t.method, options)
    try:
        matcher.set_state(t.arrays, state)
    except (ValueError, KeyError, TypeError) as e:  # learnt arrays missing or of the wrong shape
        raise FaceRec3DError(f"{path}: not a usable {t.method} model ({e})") from None
    return matcher


def trained_matcher(method: str, options: Mapping[str, Any] | None = None, *, train: str | Path | None = None,
                    model: str | Path | None = None, workers: Workers | None = None,
                    cache: str | Path | None = DEFAULT_CACHE, config: PreprocessConfig = PreprocessConfig(),
                    progress: bool = True) -> tuple[Matcher, dict]:
    """A matcher ready to enrol: loaded from `model`, or built from (method, options) and fitted on the
    dataset `train` (every scan that preprocesses, on `workers` (default: this process); failures are skipped
    and counted). Returns (matcher, info about the training)."""
    if model is not None:
        return load_matcher(model), {"model": str(model)}
    matcher = make_matcher(method, options)
    if train is None:
        if matcher.needs_training:
            raise FaceRec3DError(f"method {method!r} learns from data: give a training set (--train DATA) "
                                 "of subjects not in the test set, or a saved model (--model FILE)")
        return matcher, {}
    records = open_dataset(train).records
    t0 = time.perf_counter()
    outcomes = list(tqdm(preprocess_files([r.path for r in records], config, workers=workers, cache=cache),
                         total=len(records), desc="training set", unit="scan", disable=not progress))
    kept = [(o.face, r.subject) for o, r in zip(outcomes, records) if o.face is not None]
    if not kept:
        raise FaceRec3DError(f"{train}: no training scan could be preprocessed")
    matcher.fit([f for f, _ in kept], [s for _, s in kept])
    return matcher, {"train": str(train), "n_train": len(kept), "train_failures": len(records) - len(kept),
                     "n_train_subjects": len({s for _, s in kept}), "fit_s": time.perf_counter() - t0}
