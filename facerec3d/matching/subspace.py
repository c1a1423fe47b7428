"""Subspace matchers on depth maps: PCA (chapter §8.7) and PCA + Fisher LDA (§8.8).

Each face is its depth-map vector x (`depthmap`: a window around the nose
tip on the resampling grid, missing cells filled). Training learns a mean m
and a projection P (d × k); a face's features are y = Pᵀ(x − m), computed
once per gallery face (enrol) and once per probe (prepare), so comparing a
probe with the whole gallery is one matrix operation on k-vectors.

* PCA (§8.7.2): the principal directions are the right singular vectors of
  the mean-centred N × d training matrix (numpy SVD; with N ≪ d this is the
  chapter's route instead of the d × d covariance), eigenvalues s²/(N − 1).
* LDA (§8.8): PCA to at most N − c dimensions first (§8.8.3: the within-class
  scatter S_w of N faces of c subjects has rank ≤ N − c, so it is invertible
  only there), then the directions w maximising the Fisher ratio
  J(w) = wᵀS_b w / wᵀS_w w: the generalised eigenvectors S_b w = λ S_w w
  (scipy.linalg.eigh) of the c − 1 largest eigenvalues (§8.8.2, multi-class;
  for two classes the one direction is S_w⁻¹(m₁ − m₂), §8.8.1).

Distances (§8.7.3) between feature vectors, turned into similarities:
euclidean → −‖p − g‖; mahalanobis → −‖(p − g)/σ‖ with σ the training
features' standard deviations (for PCA σ² are the eigenvalues: whitened
space); cosine → pᵀg / (‖p‖‖g‖). The learnt arrays are the matcher's
state (mean, projection, σ), saved in the model .npz without pickle.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.linalg

from facerec3d.errors import InputError
from facerec3d.matching.base import (Matcher, Template, check_face, check_training, learnt_arrays,
                                    vector_similarity)
from facerec3d.matching.depthmap import DepthMapConfig, depth_window, fill_nearest
from facerec3d.scan import FaceScan

DISTANCES = ("euclidean", "cosine", "mahalanobis")


def pca(X: np.ndarray, n_components: int | None = None,
        variance: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """PCA of the rows of X (N × d) by SVD of the centred data (§8.7.2).

    Returns (mean (d,), components (d × k) orthonormal columns, eigenvalues (k,) of the covariance, largest
    first). k is `n_components` when given, else the fewest retaining `variance` (a share, ≤ 1) of the total;
    never more than the rank N − 1.
    """
    X = np.asarray(X, dtype=np.float64)
    mean = X.mean(axis=0)
    _, s, Vt = np.linalg.svd(X - mean, full_matrices=False)
    eigenvalues = s**2 / max(len(X) - 1, 1)
    rank = int(np.sum(s > s.max(initial=0) * max(X.shape) * np.finfo(float).eps))
    if n_components is None:
        share = np.cumsum(eigenvalues) / max(eigenvalues.sum(), np.finfo(float).tiny)
        n_components = int(np.searchsorted(share, variance - 1e-12) + 1)
    k = max(min(n_components, rank), 1)
    return mean, Vt[:k].T, eigenvalues[:k]


def scatter_matrices(X: np.ndarray, labels: Sequence) -> tuple[np.ndarray, np.ndarray]:
    """(S_w, S_b) of the rows of X (N × d) by class (§8.8.1): within-class Σ_c Σ_i (x − m_c)(x − m_c)ᵀ and
    between-class Σ_c n_c (m_c − m)(m_c − m)ᵀ."""
    X = np.asarray(X, dtype=np.float64)
    _, y = np.unique(np.asarray(labels), return_inverse=True)
    counts = np.bincount(y)
    means = np.zeros((len(counts), X.shape[1]))
    np.add.at(means, y, X)
    means /= counts[:, None]
    within = X - means[y]
    between = (means - X.mean(axis=0)) * np.sqrt(counts)[:, None]
    return within.T @ within, between.T @ between


def fisher_lda(X: np.ndarray, labels: Sequence, n_components: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Fisher LDA of the rows of X (N × d) by class (§8.8): (W (d × k), Fisher ratios (k,), largest first).

    The columns solve S_b w = λ S_w w (scipy.linalg.eigh; S_w must be positive definite: reduce with PCA
    first, §8.8.3), scaled so that wᵀ S_w w = 1; λ = J(w). k = c − 1 by default (two classes: one direction).
    """
    Sw, Sb = scatter_matrices(X, labels)
    n_classes = len(np.unique(np.asarray(labels)))
    k = min(n_classes - 1 if n_components is None else n_components, X.shape[1])
    ratios, W = scipy.linalg.eigh(Sb, Sw, subset_by_index=[X.shape[1] - k, X.shape[1] - 1])
    return W[:, ::-1], ratios[::-1]


@dataclass(frozen=True)
class PCAConfig:
    """PCA matcher settings (chapter §8.7)."""

    depth: DepthMapConfig = field(default_factory=DepthMapConfig)  # the depth-map vector (§8.7.1)
    n_components: int | None = None  # subspace dimension k; None: by `variance`
    variance: float = 0.99  # share of the training variance the kept components retain (§8.7.2)
    distance: str = "mahalanobis"  # "euclidean", "cosine" or "mahalanobis" (whitened PCA space, §8.7.3)

    def __post_init__(self) -> None:
        if self.distance not in DISTANCES:
            raise ValueError(f"unknown distance {self.distance!r}: use one of {', '.join(DISTANCES)}")
        if not 0 < self.variance <= 1 or (self.n_components is not None and self.n_components < 1):
            raise ValueError("need 0 < variance <= 1 and n_components >= 1")


@dataclass(frozen=True)
class LDAConfig:
    """PCA + LDA (Fisherfaces on depth) matcher settings (chapter §8.8)."""

    depth: DepthMapConfig = field(default_factory=DepthMapConfig)  # the depth-map vector (§8.7.1)
    pca_components: int | None = None  # PCA dimension before LDA (§8.8.3), capped at N − c (S_w invertible);
    #                                    None: pca_share × (N − c), at least c − 1
    pca_share: float = 0.5  # fewer than N − c dimensions keep S_w well conditioned: half was best on the
    #                         synthetic sets (60 subjects × 5: 120 of 240; 30 × 4: 45 of 90, vs 88 % rank-1 at N − c)
    n_components: int | None = None  # LDA dimension; None: c − 1 (§8.8.2)
    distance: str = "cosine"  # "euclidean", "cosine" or "mahalanobis" (§8.7.3, in the LDA space)

    def __post_init__(self) -> None:
        if self.distance not in DISTANCES:
            raise ValueError(f"unknown distance {self.distance!r}: use one of {', '.join(DISTANCES)}")
        if any(n is not None and n < 1 for n in (self.pca_components, self.n_components)):
            raise ValueError("pca_components and n_components must be >= 1")
        if not 0 < self.pca_share <= 1:
            raise ValueError("pca_share must be in (0, 1]")


class _SubspaceMatcher(Matcher[np.ndarray]):
    """Features y = Pᵀ(x − m) of the depth-map vector x; subclasses learn m and P in `fit`."""

    config: PCAConfig | LDAConfig

    def __init__(self, config: PCAConfig | LDAConfig | None = None) -> None:
        self.config = self.config_class() if config is None else config
        self.mean_: np.ndarray | None = None  # (d,) mm: training mean depth map
        self.projection_: np.ndarray | None = None  # (d, k)
        self.scale_: np.ndarray | None = None  # (k,) standard deviations of the training features

    @property
    def needs_training(self) -> bool:
        return True

    def vector(self, scan: FaceScan) -> np.ndarray:
        """The depth-map vector (d,) mm of a preprocessed face, missing cells filled (§8.7.1; fill "mean":
        trained matchers only)."""
        z, valid = depth_window(scan, self.config.depth)
        if self.config.depth.fill == "mean":
            return np.where(valid.ravel(), z.ravel(), self.mean_)
        return fill_nearest(z).ravel()

    def _training_matrix(self, scans: Sequence[FaceScan]) -> np.ndarray:
        """(N, d) depth-map vectors; fill "mean" uses the mean of each cell's valid training depths."""
        if self.config.depth.fill != "mean":
            return np.stack([self.vector(s) for s in scans])
        Z = np.stack([depth_window(s, self.config.depth)[0].ravel() for s in scans])
        counts = np.sum(~np.isnan(Z), axis=0)
        mean = np.where(counts > 0, np.nansum(Z, axis=0) / np.maximum(counts, 1), 0.0)
        return np.where(np.isnan(Z), mean, Z)

    def _learnt(self, X: np.ndarray, mean: np.ndarray, projection: np.ndarray) -> None:
        self.mean_, self.projection_ = mean, np.ascontiguousarray(projection)
        self.scale_ = np.maximum(((X - mean) @ self.projection_).std(axis=0), np.finfo(float).tiny)

    def features(self, scan: FaceScan) -> np.ndarray:
        """(k,) the face's coordinates in the learnt subspace."""
        if self.projection_ is None:
            raise InputError(f"the {self.name} matcher is not trained: call fit() (--train) or load a model (--model)")
        return (self.vector(scan) - self.mean_) @ self.projection_

    def state(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        if self.projection_ is None:
            return {}, {}
        return {"mean": self.mean_, "projection": self.projection_, "scale": self.scale_}, {}

    def set_state(self, arrays: Mapping[str, np.ndarray], attrs: Mapping[str, Any]) -> None:
        if arrays:
            rows, cols = self.config.depth.shape
            mean, projection, scale = learnt_arrays(arrays, {"mean": ("d",), "projection": ("d", "k"),
                                                             "scale": ("k",)}, d=rows * cols)
            if not (scale > 0).all():
                raise ValueError("'scale' holds values of 0 or less (standard deviations)")
            self.mean_, self.projection_, self.scale_ = mean, np.ascontiguousarray(projection), scale

    def enroll(self, scan: FaceScan) -> Template:
        check_face(scan)
        return Template(scan.meta.subject, scan.meta.scan_id, self.name, {"features": self.features(scan)})

    def prepare(self, scan: FaceScan) -> np.ndarray:
        check_face(scan)
        return self.features(scan)

    def _similarity(self, p: np.ndarray, G: np.ndarray) -> np.ndarray:
        return vector_similarity(p, G, self.config.distance,
                                 self.scale_ if self.config.distance == "mahalanobis" else None)

    def score(self, probe: FaceScan | np.ndarray, template: Template) -> float:
        return float(self._similarity(self._probe(probe, [template]), template.arrays["features"][None])[0])

    def scores(self, probe: FaceScan | np.ndarray, templates: Sequence[Template]) -> tuple[np.ndarray, None]:
        p = self._probe(probe, templates)
        if not templates:
            return np.zeros(0), None
        return self._similarity(p, np.stack([t.arrays["features"] for t in templates])), None


class PCAMatcher(_SubspaceMatcher):
    """PCA on depth maps (chapter §8.7); see the module docstring."""

    name = "pca"
    config_class = PCAConfig

    def fit(self, scans: Sequence[FaceScan], subjects: Sequence[str]) -> PCAMatcher:
        """Learn the mean and principal directions from preprocessed training faces (§8.7.2)."""
        check_training(scans, subjects, self.name)
        X = self._training_matrix(scans)
        mean, components, _ = pca(X, self.config.n_components, self.config.variance)
        self._learnt(X, mean, components)
        return self


class LDAMatcher(_SubspaceMatcher):
    """PCA then Fisher LDA on depth maps (chapter §8.8); see the module docstring."""

    name = "lda"
    config_class = LDAConfig

    def fit(self, scans: Sequence[FaceScan], subjects: Sequence[str]) -> LDAMatcher:
        """Learn PCA (§8.8.3) then the Fisher directions (§8.8.2) from training faces of ≥ 2 subjects.

        Faces with no variation within a person (copies of one scan) leave S_w singular however far PCA reduces,
        and the chapter's LDA has no regulariser: they are refused (InputError), not scipy's LinAlgError."""
        check_training(scans, subjects, self.name)
        n_classes = len(set(subjects))
        if n_classes < 2 or len(scans) <= n_classes:
            raise InputError(f"LDA needs at least 2 subjects and more faces than subjects "
                             f"(got {len(scans)} faces of {n_classes})")
        X = self._training_matrix(scans)
        limit = len(X) - n_classes
        wanted = self.config.pca_components
        if wanted is None:
            wanted = max(n_classes - 1, round(self.config.pca_share * limit))
        n_pca = min(wanted, limit)
        mean, components, _ = pca(X, n_pca)
        try:
            W, _ = fisher_lda((X - mean) @ components, subjects, self.config.n_components)
        except np.linalg.LinAlgError:  # S_w not positive definite: identical scans of a person (copies)
            raise InputError(f"{self.name}: the training scans show no variation within a person ({len(X)} faces of "
                             f"{n_classes} subjects, the within-person scatter is singular): LDA learns from "
                             "different scans of each subject, not copies of one") from None
        self._learnt(X, mean, components @ W)
        return self
