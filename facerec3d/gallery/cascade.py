"""A cascade for ICP identification: a cheap screen passes a shortlist to full ICP (chapter §8.6.2 costs
one full ICP per enrolled face; this costs one full ICP per shortlisted face).

1. Depth screen: both faces are frontal with the nose tip at the origin (preprocessing §8.5.5), so each is
   summarised by its mean depth z in `cell_mm` × `cell_mm` x–y cells of the upper face (within
   `radius_mm` of the nose tip and at y ≥ `min_y_mm`, which leaves out the mouth and jaw that expressions
   move most). Two faces differ by the mean squared depth difference over the `keep` share of their
   common cells that agree best, after removing the median difference (a z shift). One vectorised pass
   over the gallery; the best `shortlist` faces go on.
   Or (`screen = "embedding"`) the learned embedding (`matching.embedding`): each enrolled face's embedding is
   made once from its ICP template's points (kept with the gallery's shards like the depth descriptors), the
   probe's from its face, and the `shortlist` faces of highest cosine go on (about a microsecond per face).
   Or (`screen = "keypoints"`, evaluation only) the keypoint matcher (§8.10.2, `matching.keypoints`):
   the gallery's keypoint templates are made at enrolment and the `shortlist` faces with the most
   consistent keypoint matches go on.
2. Full ICP with the matcher's own settings on the shortlist: the same scores as exhaustive matching.
Faces off the shortlist score −inf (no match); a gallery no larger than the shortlist passes whole.
A coarse ICP (few points and iterations) was tried as a middle stage and dropped: on the synthetic
60-subject protocol it predicted full ICP's best match worse than this screen at ~100× its cost.

`Cascade` is the whole of it over a gallery loaded in an engine (gallery.engine.ShardedGallery): the
descriptors kept in the gallery's shards, the screen, the shortlist, full ICP on it, and the keypoint screen's
own gallery; each probe's result is a `CascadeScores` (scores, tiebreak, shortlist).

    cascade = Cascade(CascadeConfig(shortlist=20))
    probes = engine.prepare(matcher, faces, cascade.config)     # with their depth descriptors
    results = cascade.search(gallery, probes)                   # [CascadeScores, ...]
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache, partial
from typing import Any, NamedTuple

import numpy as np
from numba import njit

from facerec3d.config import check_ranges
from facerec3d.errors import InputError
from facerec3d.matching.base import GalleryScores, Matcher, Template, rank
from facerec3d.matching.icp import ICPMatcher
from facerec3d.matching.keypoints import KeypointMatcher
from facerec3d.scan import FaceScan


SCREENS = ("depth", "embedding", "keypoints")


@dataclass(frozen=True)
class CascadeConfig:
    """Cascade settings (chosen on the synthetic train60 set; see the README for test60's figures)."""

    cell_mm: float = 6.0  # mm: side of the depth screen's x–y cells
    radius_mm: float = 64.0  # mm: cells whose centre is within this of the nose tip ...
    min_y_mm: float = -15.0  # mm: ... and at or above this height (the nose tip is at y = 0, +y up)
    keep: float = 0.8  # share of the common cells, those that agree best, that the screen distance uses
    shortlist: int = 20  # faces passed from the screen to full ICP
    screen: str = "depth"  # "depth" (the descriptor above), "embedding" (the learned embedding's cosine) or
    #                        "keypoints" (§8.10.2; evaluation only)
    screen_model: str = ""  # the embedding screen's ONNX model; "": the shipped one

    def __post_init__(self) -> None:
        check_ranges(self)  # as a settings file's values are
        if self.shortlist < 1 or not 0 < self.keep <= 1:
            raise InputError("cascade shortlist must be >= 1 and keep in (0, 1]")
        if self.screen not in SCREENS:
            raise ValueError(f"unknown cascade screen {self.screen!r}: use one of {SCREENS}")
        if self.cell_mm <= 0 or self.radius_mm <= 0:
            raise ValueError("cascade cell_mm and radius_mm must be positive")


def check_cascadable(matcher: Matcher) -> ICPMatcher:
    """The matcher if the cascade applies to it (ICP), else a ValueError."""
    if not isinstance(matcher, ICPMatcher):
        raise InputError(f"the cascade works with the icp method, not {matcher.name!r}")
    return matcher


def depth_descriptor(points: np.ndarray, config: CascadeConfig) -> np.ndarray:
    """(C,) mean z (mm) of a frontal face's points in each screen cell; NaN where a cell holds none."""
    n = int(np.ceil(config.radius_mm / config.cell_mm))
    centres = (np.arange(-n, n) + 0.5) * config.cell_mm
    cx, cy = np.meshgrid(centres, centres, indexing="ij")
    inside = ((cx**2 + cy**2 <= config.radius_mm**2) & (cy >= config.min_y_mm)).ravel()
    p = np.asarray(points, dtype=np.float64)
    ix = np.floor(p[:, 0] / config.cell_mm).astype(np.int64) + n
    iy = np.floor(p[:, 1] / config.cell_mm).astype(np.int64) + n
    ok = (ix >= 0) & (ix < 2 * n) & (iy >= 0) & (iy < 2 * n)
    cell = ix[ok] * (2 * n) + iy[ok]
    count = np.bincount(cell, minlength=4 * n * n)
    total = np.bincount(cell, weights=p[ok, 2], minlength=4 * n * n)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, total / count, np.nan)
    return mean[inside]


def screen_distances(probe: np.ndarray, gallery: np.ndarray, keep: float) -> np.ndarray:
    """(n,) mm²: mean squared depth difference between a probe descriptor (C,) and each gallery descriptor
    (n, C) over the `keep` share of their common cells that agree best, after removing the median
    difference; inf when they share fewer than 8 cells."""
    gallery = np.asarray(gallery, dtype=np.float64)
    if gallery.size == 0:
        return np.full(len(gallery), np.inf)
    d = gallery - probe
    w = d.shape[1] - np.isnan(d).sum(axis=1)  # common cells
    rows, h = np.arange(len(d)), w // 2
    ordered = np.sort(d, axis=1)  # NaN last: each row's common differences first, in order (NumPy's SIMD sort)
    middle = ordered[rows, h]
    shift = np.where(w % 2 == 1, middle, (ordered[rows, np.maximum(h - 1, 0)] + middle) / 2)  # nanmedian's value
    residues = np.sort((d - shift[:, None]) ** 2, axis=1)
    return _mean_of_smallest(residues, w, keep)


@njit(cache=True)
def _mean_of_smallest(residues, w, keep):  # pragma: no cover - compiled
    """Per row, the mean of its k = max(⌊w·keep⌋, 1) first (smallest) residues, summed in order as NumPy's cumsum
    adds them; inf for rows of fewer than 8 common cells. (The whole screen was a nanmedian and a cumsum over every
    cell: 4.3 ms against 466 faces, now ~0.7; the same distances to the bit, tests/test_cascade.py.)"""
    out = np.empty(residues.shape[0])
    for i in range(residues.shape[0]):
        if w[i] < 8:
            out[i] = np.inf
            continue
        k = max(int(w[i] * keep), 1)
        total = 0.0
        for c in range(k):
            total += residues[i, c]
        out[i] = total / k
    return out


def best(scores: np.ndarray, n: int, tiebreak: np.ndarray | None = None) -> np.ndarray:
    """Indices of the n best (highest) scores, ranked as identification ranks them."""
    return rank(scores, tiebreak)[:n]


@lru_cache(maxsize=4)
def _embedder(model: str):
    """The embedding screen's matcher of a model, one per process: its ONNX session is opened once, not per face."""
    from facerec3d.matching.embedding import EmbeddingConfig, EmbeddingMatcher

    return EmbeddingMatcher(EmbeddingConfig(model=model))


def face_descriptor(face: FaceScan, config: CascadeConfig) -> np.ndarray:
    """What the screen compares of a probe face: its depth descriptor, or its embedding (unit vector)."""
    if config.screen == "embedding":
        return _embedder(config.screen_model).prepare(face)
    return depth_descriptor(face.points, config)


def template_descriptor(template: Template, config: CascadeConfig) -> np.ndarray:
    """The screen's descriptor of an enrolled (ICP) face, from its points."""
    if config.screen == "embedding":
        from facerec3d.matching.embedding import face_from_points

        return _embedder(config.screen_model).prepare(face_from_points(ICPMatcher.gallery_points(template)))
    return depth_descriptor(ICPMatcher.gallery_points(template), config)


class CascadeScores(NamedTuple):
    """A probe's result through the cascade: full-ICP scores and tiebreak for the shortlisted gallery entries,
    −inf (tiebreak 0) for the others; the shortlist's gallery indices, sorted."""

    scores: np.ndarray
    tiebreak: np.ndarray
    shortlist: np.ndarray


def _descriptors(shard: Any, config: CascadeConfig) -> np.ndarray:
    """The shard's depth descriptors for `config` (gallery.engine.Shard.derived; made once, kept up to date
    by gallery updates)."""
    key = ("cascade", config)
    if key not in shard.derived:
        describe = partial(template_descriptor, config=config)
        shard.derived[key] = describe, np.array([describe(t) for t in shard.templates])
    return shard.derived[key][1]


def _describe(shard: Any, config: CascadeConfig) -> int:
    return len(_descriptors(shard, config))


def _screen(shard: Any, descriptor: np.ndarray, config: CascadeConfig) -> np.ndarray:
    """Stage 1 on one shard: screen distances of a probe descriptor to the shard's faces (depth: mm²; embedding:
    1 − cosine)."""
    d = _descriptors(shard, config)
    if not shard.templates:
        return np.zeros(0)
    if config.screen == "embedding":
        return 1.0 - d @ descriptor  # cosine distance
    return screen_distances(descriptor, d, config.keep)


class Cascade:
    """The cascade with these settings over galleries loaded in an engine (module docstring)."""

    def __init__(self, config: CascadeConfig = CascadeConfig()):
        self.config = config
        self.screen_gallery = None  # the keypoint screen's gallery (load_screen)

    def probe_descriptor(self, face: FaceScan) -> np.ndarray | None:
        """What the screen needs of a probe face on the gallery's side: its depth descriptor or embedding (None for
        the keypoint screen, which scores the face against its own gallery)."""
        return None if self.config.screen == "keypoints" else face_descriptor(face, self.config)

    def describe(self, gallery: Any) -> None:
        """Make the screen descriptors of a gallery's shards now rather than at its first cascade probe."""
        gallery.per_shard([[(_describe, self.config)] * gallery.shards])

    def load_screen(self, engine: Any, faces: Sequence[FaceScan]) -> None:
        """For the keypoint screen: enrol the gallery faces with the keypoint matcher and load them into the engine
        (sharded like the gallery). Needs the gallery's faces, so evaluation only."""
        if self.config.screen == "keypoints":
            matcher = KeypointMatcher()
            self.screen_gallery = engine.load(matcher, engine.enroll(matcher, faces))

    def screen_scores(self, engine: Any, faces: Sequence[FaceScan]) -> list[GalleryScores] | None:
        """The keypoint screen's scores of probe faces against its gallery (None for the depth screen)."""
        if self.screen_gallery is None:
            return None
        return self.screen_gallery.scores(engine.prepare(self.screen_gallery.matcher, faces))

    def shortlists(self, gallery: Any, probes: Sequence[Any],
                   screen: Sequence[GalleryScores] | None = None) -> list[np.ndarray]:
        """Each probe's shortlist (gallery indices, sorted): the best of the depth screen, or of `screen`: each
        probe's (scores, tiebreak) against the whole gallery by another matcher (e.g. `screen_scores`)."""
        c = self.config
        if screen is not None:
            return [np.sort(best(s, c.shortlist, t)) for s, t in screen]
        if c.screen == "keypoints":
            raise ValueError(f"a {c.screen} screen needs that matcher's scores against the gallery (screen=)")
        if any(p.descriptor is None for p in probes):
            raise ValueError("cascade probes need screen descriptors: Engine.prepare(..., cascade=config)")
        rows = gallery.per_shard([[(_screen, p.descriptor, c)] * gallery.shards for p in probes])
        return [np.sort(best(-np.concatenate(row), c.shortlist)) for row in rows]

    def search(self, gallery: Any, probes: Sequence[Any],
               screen: Sequence[GalleryScores] | None = None) -> list[CascadeScores]:
        """Each prepared probe (gallery.engine.Probe) through the cascade against an ICP gallery: screen,
        shortlist, full ICP on the shortlist."""
        check_cascadable(gallery.matcher)
        shortlists = self.shortlists(gallery, probes, screen)
        out = []
        for shortlist, (s, t) in zip(shortlists, gallery.scores_at_many(probes, shortlists)):
            scores, tiebreak = np.full(len(gallery), -np.inf), np.zeros(len(gallery))
            scores[shortlist], tiebreak[shortlist] = s, t
            out.append(CascadeScores(scores, tiebreak, shortlist))
        return out

    @staticmethod
    def recall(results: Sequence[CascadeScores], probe_subjects: Sequence[str],
               gallery_subjects: Sequence[str]) -> float | None:
        """Share of the probes of enrolled subjects whose subject is on their shortlist (None: no such probe)."""
        enrolled = set(gallery_subjects)
        hits = [subject in {gallery_subjects[j] for j in r.shortlist}
                for r, subject in zip(results, probe_subjects) if subject in enrolled]
        return float(np.mean(hits)) if hits else None
