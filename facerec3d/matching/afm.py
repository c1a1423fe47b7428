"""Annotated face model matching (chapter §8.10.1; Kakadiaris et al., "Three-dimensional face recognition in the
presence of facial expressions: an annotated deformable model approach", TPAMI 2007).

Kakadiaris et al. fit an annotated face model to each scan, turn the fitted surface into a *geometry image* in
the model's UV space and compare faces by the wavelet coefficients of those images. Here the model is the
ICT-FaceKit morphable model preprocessing already fits (`morphable`): its dense correspondence gives each face a
64 × 64 geometry image (x, y, z of the scan's surface at fixed points of the model face, missing where nothing
was seen); its expression fit can be subtracted first.

Wavelets: an orthonormal 2D Haar pyramid of each channel (`haar_pyramid`). A coefficient is *valid* only when
every cell under its support holds data, so missing data is masked, never filled with zeros. The finest detail
bands (`drop_finest`) are left out (sensor noise; Kakadiaris et al. keep a subset of bands too), which leaves 1,024
coefficients per channel. A template is those 3 × 1,024 coefficients (float32) and their validity.

Distance: the RMS difference of the coefficients both faces have, d² = Σ m_p m_g ‖c_p − c_g‖² / Σ m_p m_g
(orthonormal Haar: mm). Expanded, d² is linear in the gallery's [m, m·c, m·‖c‖²], so a probe is scored against a
whole gallery by one matrix product (`scores`): about a microsecond per comparison. The score is −d (mm).

Expression handling (`expression`, §8.10.3), to compare with each other and with masking (`mask_mobility_mm`:
points that some expression moves more than that are missing, as in region ICP's rigid region):
* "none": the geometry image as seen;
* "blendshapes": the fitted expression's blendshape displacements are subtracted from the geometry image, so the
  face is compared as if neutral (model-based removal, cf. Amberg, Knothe & Vetter, FG 2008);
* "residue": Al-Osaimi, Bennamoun & Mian's expression deformation model (IJCV 2009; chapter eqs. 8.46–8.47),
  learnt from the residues between neutral and non-neutral scans of training subjects (`--train`): the
  probe–gallery residue is scored by the part of it the model cannot reconstruct (`expression.ResidueModel`);
* "blendshapes+residue": both, the residue model learnt on geometry images with the blendshapes removed (it
  learns what the removal leaves).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from facerec3d.config import check_ranges
from facerec3d.errors import InputError
from facerec3d.matching.base import Matcher, Template, check_face, check_training
from facerec3d.matching.expression import ResidueConfig, ResidueModel
from facerec3d.matching.morphable import GeometryImageConfig, RefitConfig, face_fit, geometry_image, refit, uv_basis
from facerec3d.scan import FaceScan

EXPRESSION_HANDLING = ("none", "blendshapes", "residue", "blendshapes+residue")


def haar_pyramid(images: np.ndarray, valid: np.ndarray, levels: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Orthonormal 2D Haar analysis of images (C, n, n) with a validity mask (n, n), `levels` times.

    Returns [(coefficients (C, 3, h, w), valid (h, w)) of the detail bands (horizontal, vertical, diagonal) of
    level 1 (finest), 2, ..., then (coefficients (C, 1, h, w), valid) of the last approximation]. A coefficient
    is valid when its whole support is (invalid cells may hold anything, even NaN: they never reach a valid one).
    """
    x = np.where(valid, images, 0.0)
    ok = np.asarray(valid, dtype=bool)
    out = []
    for _ in range(levels):
        a, b, c, d = x[:, 0::2, 0::2], x[:, 0::2, 1::2], x[:, 1::2, 0::2], x[:, 1::2, 1::2]
        ok = ok[0::2, 0::2] & ok[0::2, 1::2] & ok[1::2, 0::2] & ok[1::2, 1::2]
        detail = np.stack([a - b + c - d, a + b - c - d, a - b - c + d], axis=1) / 2
        out.append((np.where(ok, detail, 0.0), ok))
        x = np.where(ok, (a + b + c + d) / 2, 0.0)
    out.append((x[:, None], ok))
    return out


@dataclass(frozen=True)
class AFMConfig:
    """Geometry-image wavelet matching settings (§8.10.1)."""

    image: GeometryImageConfig = field(default_factory=GeometryImageConfig)  # UV grid and sampling
    refit: RefitConfig = field(default_factory=RefitConfig)  # the robust refit of the fit before sampling (48
    #   iterations on laser-fine faces, 6 on depth-camera faces: `RefitConfig.fine_iterations`)
    levels: int = 3  # Haar levels: 64 → 32 → 16 → 8 (the 8 × 8 approximation covers 16 mm cells)
    drop_finest: int = 1  # finest detail levels left out (2 mm-scale noise): 3 × 1,024 coefficients remain
    expression: str = "blendshapes"  # one of EXPRESSION_HANDLING (module docstring)
    mask_mobility_mm: float | None = None  # leave out points some expression moves more than this (mm; None: keep
    #   all). 4 mm is region ICP's rigid region (regions.RegionConfig.rigid_mobility), today's masking
    residue: ResidueConfig = field(default_factory=ResidueConfig)  # "residue": the expression deformation model
    regions: int = 8  # the UV square is cut into regions × regions squares (8: 16 mm on the mean face), each scored on
    #   its own (1: one score for the whole face)
    keep_regions: float = 0.375  # the score averages the best (nearest) share of the regions the two faces share, so
    #   an occluder or a badly removed expression in some regions does not decide (Kakadiaris et al. weight the
    #   annotated regions; region ICP, §8.10.1, fuses regions for the same reason). 8 × 8 squares, nearest 3/8: on the
    #   synthetic outside-model 60 × 5 set 87.5 % rank-1 against 75.4 % for the whole face (nearest 1/4 as good, 5/8
    #   3 points lower, 4 × 4 squares and 16 × 16 lower still); strong expressions 100 % either way; rap3df-2019
    #   tuning half 33.8 against 26.5 % (docs/model-methods.md)

    def __post_init__(self) -> None:
        check_ranges(self)  # NaN or a negative named before the checks below compute with it
        if self.expression not in EXPRESSION_HANDLING:
            raise ValueError(f"unknown expression handling {self.expression!r}: use one of {', '.join(EXPRESSION_HANDLING)}")
        if not 1 <= self.levels or 2**self.levels > self.image.size or not 0 <= self.drop_finest < self.levels:
            raise ValueError("need 1 ≤ levels, 2**levels ≤ image.size and 0 ≤ drop_finest < levels")
        if self.regions < 1 or (self.image.size >> self.levels) % self.regions:
            raise ValueError("regions must be ≥ 1 and divide the coarsest band (image.size / 2**levels)")
        if not 0 < self.keep_regions <= 1:
            raise ValueError("keep_regions must be in (0, 1]")


class AFMMatcher(Matcher[Template]):
    """Geometry images of the fitted model compared by Haar wavelet coefficients (module docstring)."""

    name = "afm"
    config_class = AFMConfig
    added_options = {"refit": {"enabled": False, "fine_iterations": 0}}  # templates stored before the robust refit
    #   (December 2026), or before its longer run on fine faces (2026-12-06)

    def __init__(self, config: AFMConfig | None = None) -> None:
        self.config = AFMConfig() if config is None else config
        self.residue_: ResidueModel | None = None
        self._stacked: tuple[tuple[Template, ...], np.ndarray] | None = None

    def __getstate__(self) -> dict:
        """Pickled (sent to worker processes) without the stacked gallery it keeps for reuse."""
        return {**self.__dict__, "_stacked": None}

    @property
    def needs_training(self) -> bool:
        return self.config.expression.endswith("residue")

    # ------------------------------------------------------------------------------------------ features
    def coefficients(self, scan: FaceScan) -> tuple[np.ndarray, np.ndarray]:
        """(coefficients (3·k,) float32 mm, valid (k,) bool) of a preprocessed face's geometry image, channel by
        channel (x, y, z), each relative to the model's mean face so that the values are small."""
        cfg = self.config
        fit = refit(scan, cfg.refit)
        g = geometry_image(scan, fit, cfg.image)
        n = cfg.image.size
        basis = uv_basis(cfg.image)
        # in the fit's frame (x -> R x + t; the identity for the fit preprocessing kept), so that the pose the refit
        # corrects does not reach the coefficients
        points = g.points @ fit.R.T + fit.t - basis.mean.reshape(n, n, 3)
        valid = g.valid
        if cfg.expression.startswith("blendshapes"):
            points = points - g.expression @ fit.R.T
        if cfg.mask_mobility_mm is not None:
            valid = valid & (basis.mobility.reshape(n, n) <= cfg.mask_mobility_mm)
        bands = haar_pyramid(points.transpose(2, 0, 1), valid, cfg.levels)[cfg.drop_finest:]
        c = np.concatenate([b.reshape(3, -1) for b, _ in bands], axis=1)  # (3, k)
        m = np.concatenate([np.broadcast_to(ok, b.shape[1:]).reshape(-1) for b, ok in bands])
        order = self._region_order()
        return c[:, order].reshape(-1).astype(np.float32), m[order]

    def _region_order(self) -> np.ndarray:
        """(k,) the coefficients ordered region by region (regions × regions squares of the UV grid, row-major),
        each region holding the same number of coefficients."""
        cfg = self.config
        n, r = cfg.image.size, cfg.regions
        labels = []
        for level in range(cfg.drop_finest + 1, cfg.levels + 2):
            h = n >> min(level, cfg.levels)
            i, j = np.mgrid[0:h, 0:h]
            region = (i * r // h) * r + j * r // h
            labels.append(np.tile(region.ravel(), 3 if level <= cfg.levels else 1))
        return np.argsort(np.concatenate(labels), kind="stable")

    def enroll(self, scan: FaceScan) -> Template:
        check_face(scan)
        c, m = self.coefficients(scan)
        return Template(scan.meta.subject, scan.meta.scan_id, self.name, {"coefficients": c, "valid": m})

    # ------------------------------------------------------------------------------------------ training
    def fit(self, scans: Sequence[FaceScan], subjects: Sequence[str]) -> AFMMatcher:
        """"residue": learn the expression deformation model from the training subjects' scans (each subject's
        neutral scan against its others; `expression.ResidueModel.learn`); the other handlings learn nothing."""
        if not self.needs_training:
            return self
        check_training(scans, subjects, self.name)
        coeffs = [self.coefficients(s) for s in scans]
        energy = [float(np.linalg.norm(face_fit(s).expression)) for s in scans]
        labels = [s.meta.expression for s in scans]
        self.residue_ = ResidueModel.learn(coeffs, list(subjects), labels, energy, self.config.residue)
        if self.residue_ is None:
            raise InputError("the expression deformation model needs training subjects with two or more scans")
        return self

    def state(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        return ({}, {}) if self.residue_ is None else self.residue_.state()

    def set_state(self, arrays: Mapping[str, np.ndarray], attrs: Mapping[str, Any]) -> None:
        if arrays:
            self.residue_ = ResidueModel.from_state(arrays, 3 * len(self._region_order()))  # x, y, z coefficients

    # ------------------------------------------------------------------------------------------- scoring
    def _gallery(self, templates: Sequence[Template]) -> tuple[np.ndarray, np.ndarray]:
        """((regions², n, 5s), (regions², n, s)) float32: per region of s coefficients, the templates' rows
        [m, m·c (3s), m·‖c‖²], and their masks m again, contiguous (the shared counts read only those); the last
        gallery's are kept for reuse."""
        key, last = tuple(templates), self._stacked  # read once: threads may replace it meanwhile
        if last is not None and len(last[0]) == len(key) and all(a is b for a, b in zip(last[0], key)):
            return last[1]
        R = self.config.regions**2
        m = np.stack([t.arrays["valid"] for t in templates]).astype(np.float32)
        c = np.stack([t.arrays["coefficients"] for t in templates]).astype(np.float32)
        n, k = m.shape
        c3 = c.reshape(n, 3, k) * m[:, None]
        parts = [m.reshape(n, R, 1, -1), c3.reshape(n, 3, R, -1).transpose(0, 2, 1, 3),
                 np.einsum("nck,nck->nk", c3, c3).reshape(n, R, 1, -1)]
        rows = np.ascontiguousarray(np.concatenate(parts, axis=2).reshape(n, R, -1).transpose(1, 0, 2))
        masks = np.ascontiguousarray(m.reshape(n, R, -1).transpose(1, 0, 2))
        self._stacked = (key, (rows, masks))
        return rows, masks

    def distances(self, probe: Template, templates: Sequence[Template]) -> np.ndarray:
        """(n,) distances (mm): the RMS coefficient difference over the coefficients both faces have, per region,
        averaged over the nearest `keep_regions` share of the regions they share; +inf where they share none."""
        if self.needs_training:
            if self.residue_ is None:
                raise InputError(f"the afm matcher with expression = {self.config.expression!r} is not trained: "
                                   "call fit() or load a model")
            return self.residue_.errors(probe.arrays["coefficients"], probe.arrays["valid"],
                                        np.stack([t.arrays["coefficients"] for t in templates]),
                                        np.stack([t.arrays["valid"] for t in templates]))
        G, M = self._gallery(templates)  # (R, n, 5s), (R, n, s)
        R = G.shape[0]
        m = probe.arrays["valid"].astype(np.float32).reshape(R, -1)
        c = probe.arrays["coefficients"].astype(np.float32).reshape(3, R, -1) * m
        q = np.concatenate([np.einsum("crs,crs->rs", c, c)[:, None], -2 * c.transpose(1, 0, 2), m[:, None]],
                           axis=1).reshape(R, -1, 1)
        num = np.matmul(G, q)[..., 0].astype(np.float64)  # (R, n): one matrix-vector product per region (BLAS)
        den = np.matmul(M, m[..., None])[..., 0].astype(np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            d = np.where(den > 0, np.sqrt(np.maximum(num, 0.0) / np.maximum(den, 1.0)), np.inf)
        if R == 1:
            return d[0]
        shared = np.isfinite(d).sum(axis=0)
        keep = np.maximum(np.ceil(self.config.keep_regions * shared).astype(np.int64), 1)
        nearest = np.sort(d, axis=0)  # the shared regions first, nearest first
        best = np.cumsum(np.where(np.isfinite(nearest), nearest, 0.0), axis=0)
        mean = best[np.minimum(keep, R) - 1, np.arange(d.shape[1])] / keep
        return np.where(shared > 0, mean, np.inf)

    def scores(self, probe: FaceScan | Template, templates: Sequence[Template]) -> tuple[np.ndarray, None]:
        p = self._probe(probe, templates)
        if not templates:
            return np.zeros(0), None
        return -self.distances(p, templates), None

    def score(self, probe: FaceScan | Template, template: Template) -> float:
        return float(-self.distances(self._probe(probe, [template]), [template])[0])
