"""Matching methods by name (`facerec3d evaluate --method NAME`), built with options, trained, saved and loaded.

    matcher = make_matcher("icp", {"variant": "point-to-plane"})
    matcher.save("model.npz"); same = load_matcher("model.npz")
    matcher, info = trained_matcher("lda", train="train-data/", workers=engine)

Each method's module is imported only when the method is used.
"""

from __future__ import annotations

import time
import zipfile
import zlib
from collections.abc import Callable, Mapping
from os import PathLike
from pathlib import Path
from typing import Any

from tqdm import tqdm

from facerec3d.config import DEFAULT_METHOD  # noqa: F401 - the default method, beside the methods
from facerec3d.datasets.catalog import open_dataset
from facerec3d.errors import FaceRec3DError, InputError
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
    """A matcher saved by `Matcher.save`: its method, settings and what it learnt; FaceRec3DError (one line) for a
    file that is none, or a damaged one."""
    try:
        with open(path, "rb") as f:
            if f.read(4) != b"PK\x03\x04":  # NumPy would take it for a pickle and name an option to load it unsafely
                raise FaceRec3DError(f"{path}: not a facerec3d model file (not an .npz archive)")
        t = Template.load(path)
        options, state = t.attrs["options"], t.attrs["state"]
    except OSError as e:
        raise FaceRec3DError(f"{path}: cannot read the model file ({e.strerror or e})") from None
    except (ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile, zlib.error) as e:
        raise FaceRec3DError(f"{path}: not a facerec3d model file, or a damaged one ({type(e).__name__}: "
                             f"{str(e)[:200]})") from None
    return restore_state(stored_matcher(t.method, options), t.arrays, state,
                         lambda why: FaceRec3DError(f"{path}: not a usable {t.method} model ({why})"))


def restore_state(matcher: Matcher, arrays: Mapping[str, Any], state: Mapping[str, Any],
                  error: Callable[[str], Exception]) -> Matcher:
    """The matcher with what it learnt set back (`Matcher.set_state`); `error(reason)` is raised, one line, when the
    stored arrays are missing or of the wrong shape."""
    try:
        matcher.set_state(arrays, state)
    except (ValueError, KeyError, TypeError) as e:
        raise error(str(e)) from None
    return matcher


#: What --train must hold for every learnt method: the strictest rule, the embedding's (adapt = "wccn",
#: `embedding.wccn`); LDA (`subspace.LDAMatcher.fit`) and the afm residue model need less, PCA nothing.
TRAIN_RULE = "at least 2 people with 2 scans each"

#: Training people below which --train draws a warning: LDA finds at most people − 1 directions, and a camera's
#: within-person spread (adapt = "wccn") is poorly estimated from a handful of people (its ridge was chosen with
#: 20 people a fold, and the depth-camera guide asks for a few dozen).
FEW_TRAINING_PEOPLE = 10


def _learners(matcher: Matcher) -> str:
    """Who learns from data in a matcher, for messages: "method 'lda'", or a fusion's "member 'embedding' of method
    'fusion'"."""
    names = matcher.learners()
    if names == [matcher.name]:
        return f"method {matcher.name!r}"
    return f"member{'s' if len(names) > 1 else ''} {', '.join(map(repr, names))} of method {matcher.name!r}"


def _count(n: int, one: str, many: str) -> str:
    return f"{n} {one if n == 1 else many}"


def trained_matcher(method: str, options: Mapping[str, Any] | None = None, *, train: str | Path | None = None,
                    model: str | Path | None = None, workers: Workers | None = None,
                    cache: str | Path | None = DEFAULT_CACHE, config: PreprocessConfig = PreprocessConfig(),
                    progress: bool = True, echo: Callable[[str], None] | None = None) -> tuple[Matcher, dict]:
    """A matcher ready to enrol: loaded from `model`, or built from (method, options) and fitted on the
    dataset `train` (every scan that preprocesses, on `workers` (default: this process); failures are skipped
    and counted). Returns (matcher, info about the training). `echo` (the command line's stderr) is told in one
    line what the matcher learnt from, with a warning when that is few people; and, when the matcher learns
    nothing, that `train` was not used (it is not read)."""
    if model is not None:
        if train is not None:  # a saved model is trained already: --train would be silently ignored
            raise InputError(f"{model}: a saved model is trained already: give --model or --train, not both")
        return load_matcher(model), {"model": str(model)}
    say = echo or (lambda line: None)
    source = getattr(options, "source", None)  # the settings file, when read with config.read_settings
    matcher = make_matcher(method, options)
    if not matcher.needs_training:
        if train is not None:
            settings = f" with the settings of {source}" if source else ""
            say(f"warning: method {matcher.name!r} learns nothing{settings}: --train {train} not used")
        return matcher, {}
    who = _learners(matcher)
    if train is None:
        raise FaceRec3DError((f"{source}: " if source else "") + f"{who} must learn from data: give --train DATA, "
                             f"scans of people other than those it will match ({TRAIN_RULE}), or a saved model "
                             "(--model FILE)")
    records = open_dataset(train).records
    t0 = time.perf_counter()
    outcomes = list(tqdm(preprocess_files([r.path for r in records], config, workers=workers, cache=cache),
                         total=len(records), desc="training set", unit="scan", disable=not progress))
    kept = [(o.face, r.subject) for o, r in zip(outcomes, records) if o.face is not None]
    if not kept:
        raise FaceRec3DError(f"{train}: no training scan could be preprocessed")
    matcher.fit([f for f, _ in kept], [s for _, s in kept])
    info = {"train": str(train), "n_train": len(kept), "train_failures": len(records) - len(kept),
            "n_train_subjects": len({s for _, s in kept}), "fit_s": time.perf_counter() - t0}
    people = _count(info["n_train_subjects"], "person", "people")
    say(f"{who} learnt from {_count(len(kept), 'scan', 'scans')} of {people} in {train}"
        + (f" ({_count(info['train_failures'], 'scan', 'scans')} failed to preprocess, left out)"
           if info["train_failures"] else ""))
    if info["n_train_subjects"] < FEW_TRAINING_PEOPLE:
        say(f"warning: {train}: {people} only, too few to learn from reliably: give scans of "
            f"{FEW_TRAINING_PEOPLE} or more people (a few dozen are better)")
    return matcher, info
