"""A cascade for ICP identification: a cheap screen passes a shortlist to full ICP (chapter §8.6.2 costs
one full ICP per enrolled face; this costs one full ICP per shortlisted face).

1. Depth screen: both faces are frontal with the nose tip at the origin (preprocessing §8.5.5), so each is
   summarised by its mean depth z in `cell_mm` × `cell_mm` x–y cells of the upper face (within
   `radius_mm` of the nose tip and at y ≥ `min_y_mm`, which leaves out the mouth and jaw that expressions
   move most). Two faces differ by the mean squared depth difference over the `keep` share of their
   common cells that agree best, after removing the median difference (a z shift). One vectorised pass
   over the gallery; the best `shortlist` faces go on.
   Or (`screen = "keypoints"`, evaluation only) the keypoint matcher (§8.10.2, `matching.keypoints`):
   the gallery's keypoint templates are made at enrolment and the `shortlist` faces with the most
   consistent keypoint matches go on.
2. Full ICP with the matcher's own settings on the shortlist: the same scores as exhaustive matching.
Faces off the shortlist score −inf (no match); a gallery no larger than the shortlist passes whole.
A coarse ICP (few points and iterations) was tried as a middle stage and dropped: on the synthetic
60-subject protocol it predicted full ICP's best match worse than this screen at ~100× its cost.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facerec3d.matching.base import Matcher, rank
from facerec3d.matching.icp import ICPMatcher


SCREENS = ("depth", "keypoints")


@dataclass(frozen=True)
class CascadeConfig:
    """Cascade settings (chosen on the synthetic train60 set; see the README for test60's figures)."""

    cell_mm: float = 6.0  # mm: side of the depth screen's x–y cells
    radius_mm: float = 64.0  # mm: cells whose centre is within this of the nose tip ...
    min_y_mm: float = -15.0  # mm: ... and at or above this height (the nose tip is at y = 0, +y up)
    keep: float = 0.8  # share of the common cells, those that agree best, that the screen distance uses
    shortlist: int = 20  # faces passed from the screen to full ICP
    screen: str = "depth"  # "depth" (the descriptor above) or "keypoints" (§8.10.2; evaluation only)

    def __post_init__(self) -> None:
        if self.shortlist < 1 or not 0 < self.keep <= 1:
            raise ValueError("cascade shortlist must be >= 1 and keep in (0, 1]")
        if self.screen not in SCREENS:
            raise ValueError(f"unknown cascade screen {self.screen!r}: use one of {SCREENS}")
        if self.cell_mm <= 0 or self.radius_mm <= 0:
            raise ValueError("cascade cell_mm and radius_mm must be positive")


def check_cascadable(matcher: Matcher) -> ICPMatcher:
    """The matcher if the cascade applies to it (ICP), else a ValueError."""
    if not isinstance(matcher, ICPMatcher):
        raise ValueError(f"the cascade works with the icp method, not {matcher.name!r}")
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
    d = gallery - probe
    common = ~np.isnan(d)
    w = common.sum(axis=1)
    if d.size == 0:
        return np.full(len(gallery), np.inf)
    with np.errstate(invalid="ignore"):
        shift = np.nanmedian(np.where(w[:, None] > 0, d, 0.0), axis=1, keepdims=True)
    r = np.sort(np.where(common, (d - shift) ** 2, np.inf), axis=1)
    k = np.maximum((w * keep).astype(np.int64), 1)
    total = np.cumsum(np.where(np.isfinite(r), r, 0.0), axis=1)[np.arange(len(r)), k - 1]
    return np.where(w >= 8, total / k, np.inf)


def best(scores: np.ndarray, n: int, tiebreak: np.ndarray | None = None) -> np.ndarray:
    """Indices of the n best (highest) scores, ranked as identification ranks them."""
    return rank(scores, tiebreak)[:n]
