"""The morphable-model fit of a preprocessed face as a matching representation (chapter §8.10.1, §8.10.3).

Preprocessing fits the ICT-FaceKit model to every scan (`preprocess.pose.fit_face_model`: pose, 40 identity
modes, 53 expression blendshapes) and keeps the coefficients in `meta.extra["model_fit"]`; a face that has
none (made before that was kept, or built directly in the frontal frame) is fitted again here, from the
frontal pose it is already in. The fit gives three things the model-based methods use:

* **dense correspondence** (the role of Kakadiaris et al.'s annotated face model, TPAMI 2007): a fixed UV
  grid over the model's mean face (its frontal x–y projection, the front-most triangle of each cell) names the
  same point of the face — barycentric in the same model triangle — on every fitted face. Sampling the scan's
  surface along the fitted normals at those points gives the face's *geometry image* (`GeometryImage`):
  x, y, z at each cell, with a mask where the scan has no surface near the fit (holes, occluders);
* **expression coefficients**, whose blendshape displacements can be subtracted from the geometry image (a
  model-based expression removal, after Amberg, Knothe & Vetter, FG 2008);
* **identity coefficients**, a 40-number description of the face (Blanz & Vetter, PAMI 2003): `MorphIDMatcher`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from facerec3d.config import check_ranges
from facerec3d.facemodel import load_model
from facerec3d.matching.base import Matcher, Template, check_face, vector_similarity
from facerec3d.preprocess.pipeline import MODEL_FIT_KEY
from facerec3d.preprocess.pose import ModelFit, ModelFitConfig, fit_face_model, model_nose_tip
from facerec3d.preprocess.resample import front_triangles
from facerec3d.scan import FaceScan


@dataclass(frozen=True)
class FaceFit:
    """A face's morphable-model fit: identity coefficients α, expression weights w and the pose x -> R x + t
    from the face's frame into the fitted model's (nose tip at the origin); identity pose when the fit is the
    one preprocessing made, since the face was moved into that frame."""

    identity: np.ndarray  # (K,)
    expression: np.ndarray  # (E,)
    R: np.ndarray
    t: np.ndarray


def face_fit(face: FaceScan, config: ModelFitConfig = ModelFitConfig()) -> FaceFit:
    """The model fit of a preprocessed face: the one preprocessing kept, else fitted now from the frontal pose
    (about 0.3 s)."""
    n_expressions = len(load_model().expression_names)
    if stored := face.meta.extra.get(MODEL_FIT_KEY):
        expression = np.asarray(stored["expression"], dtype=np.float64)
        return FaceFit(np.asarray(stored["identity"], dtype=np.float64),
                       np.pad(expression, (0, n_expressions - len(expression))), np.eye(3), np.zeros(3))
    fit = fit_face_model(face.points, np.eye(3), np.zeros(3), config)
    return _face_fit(fit, config.identity_modes, n_expressions)


def _face_fit(fit: ModelFit, k: int, n_expressions: int) -> FaceFit:
    expression = np.pad(fit.coefficients[k:], (0, n_expressions - len(fit.coefficients[k:])))
    return FaceFit(fit.coefficients[:k].copy(), expression, fit.R, fit.t)


@dataclass(frozen=True)
class RefitConfig:
    """A robust refit of a face's model fit, from the fit preprocessing kept (§8.10.1: the annotated model is fitted
    to each scan; Kakadiaris et al. deform it onto the scan after a rigid alignment).

    Preprocessing fits with a cut-off shrinking from 10 to 3 mm and plain least squares, which is what finding and
    posing the face needs; but the points of an occluder (a hand, glasses, a fringe) lying within that reach pull the
    identity and expression modes towards them, and the fit's correspondence with it. The refit starts from that fit,
    pairs only points within a few mm, weighs each pair by the Cauchy M-estimator (`pose.fit_face_model`'s
    `robust_mm`) and holds the modes nearer the prior, so the surface that is no face counts little. Measured on
    the synthetic outside-model 60 × 5 set (occluders in 3 of 4 scans; docs/model-methods.md): afm rank-1 36.7 % →
    71.3 % (with the geometry image in the refit's frame), morph-id 67.5 → 87.9 %; on the model-identity sets and
    on both halves of rap3df-2019 the same or better."""

    enabled: bool = True
    iterations: int = 6
    start_distance_mm: float = 3.0  # pairs nearer than this at the first iteration ...
    end_distance_mm: float = 2.0  # ... shrinking to this at the last (the preprocessing fit is already within reach)
    regularisation: float = 3.0  # λ of the Gaussian prior on the modes (preprocessing's is 1.0): 1.0 gave 58.8 %,
    #   3.0 71.2 %, 10 62.1 % on the outside-model set
    robust_mm: float = 0.7  # Cauchy scale (mm): least squares instead gave 27.9 % on the outside-model set
    fine_iterations: int = 48  # iterations instead of `iterations` for a face scanned finer than `fine_mm` (its
    #   preprocessing's measured pitch, `quality.pitch_mm`); 0: `iterations` for every face. The refit had not
    #   converged on laser scans: 48 chosen on a tuning set of outside-model faces (tune60-outside, afm 92.5 → 95.8 %,
    #   morph-id 96.3 → 97.5 %); test60-outside afm 91.7 → 96.3 %, morph-id 92.5 → 99.2 %; on rap3df-2019's Kinect
    #   faces 48 lost (afm tuning half 39.2 → 31.9 %), so coarser faces keep `iterations` (docs/model-methods.md)
    fine_mm: float = 1.5  # the pitch (mm) below which a scan counts as fine: a laser's 0.7 mm, not a depth camera's
    #   2.5-4 mm faces (the same bound as `preprocess.holes.HoleConfig.fine_mm`)

    def __post_init__(self) -> None:
        if self.iterations < 1 or self.regularisation < 0 or self.fine_iterations < 0 or not self.fine_mm > 0:
            raise ValueError("iterations must be ≥ 1, fine_iterations ≥ 0, fine_mm > 0 and regularisation ≥ 0")
        if not 0 < self.end_distance_mm <= self.start_distance_mm or not self.robust_mm > 0:
            raise ValueError("need 0 < end_distance_mm ≤ start_distance_mm and robust_mm > 0")


def refit(face: FaceScan, config: RefitConfig = RefitConfig(), fit: FaceFit | None = None) -> FaceFit:
    """A face's model fit refined robustly (`RefitConfig`) from `fit` (default: `face_fit(face)`, the fit
    preprocessing kept), `fine_iterations` long on a face its preprocessing measured finer than `fine_mm`; that fit
    itself when the refit is off or finds too few points."""
    fit = face_fit(face) if fit is None else fit
    if not config.enabled:
        return fit
    k = len(fit.identity)
    pitch = face.meta.extra.get("quality", {}).get("pitch_mm")  # none recorded (an older face): `iterations`
    fine = config.fine_iterations and pitch is not None and float(pitch) < config.fine_mm
    fit_config = ModelFitConfig(identity_modes=k, iterations=config.fine_iterations if fine else config.iterations,
                                start_distance_mm=config.start_distance_mm, end_distance_mm=config.end_distance_mm,
                                regularisation=config.regularisation)
    start = np.concatenate([fit.identity, fit.expression])
    # fit_face_model's frame has the model's mean nose tip at the origin; the fit's has the fitted nose tip there
    nose = model_nose_tip(start, fit_config)
    new = fit_face_model(face.points, fit.R, fit.t + nose, fit_config, start=start, robust_mm=config.robust_mm)
    if not np.isfinite(new.rms_mm):
        return fit
    return _face_fit(new, k, len(fit.expression))


@dataclass(frozen=True)
class GeometryImageConfig:
    """The UV grid of the geometry image and how the scan is sampled on it (§8.10.1)."""

    size: int = 64  # cells per side (a power of two for the Haar pyramid)
    cell_mm: float = 2.0  # on the mean face: 64 × 2 mm spans 128 mm, eyebrows to chin, cheek to cheek
    top_mm: float = 56.0  # y of the top row's centres on the mean face (nose tip at the origin), mm: the grid spans
    #   y from +56 (forehead) down to −70 (above the chin) and x ±63 mm
    max_offset_mm: float = 10.0  # the scan's surface must lie this near the fitted surface along its normal, else the
    #   cell is missing (an occluder, hair, a hole): the outside-model faces of the generator stray ≤ 3 mm from the
    #   model's span, a hand or glasses 10 mm and more (datasets.synthetic.IDENTITY_PROFILES)

    def __post_init__(self) -> None:
        check_ranges(self)  # NaN or a negative named before the checks below compute with it
        if self.size < 2 or self.size & (self.size - 1):
            raise ValueError("size must be a power of two ≥ 2")
        if self.cell_mm <= 0 or self.max_offset_mm <= 0:
            raise ValueError("cell_mm and max_offset_mm must be positive")


@dataclass(frozen=True, eq=False)
class UVBasis:
    """The model at the UV grid's points: mean, identity and expression modes (n², 3[, K]), mm, in the frame with
    the nose tip at the origin, and each mode's nose-tip displacement; `inside` marks cells on the model face."""

    config: GeometryImageConfig
    inside: np.ndarray  # (n²,) bool
    mean: np.ndarray  # (n², 3)
    identity: np.ndarray  # (n², 3, K)
    expression: np.ndarray  # (n², 3, E)
    nose_identity: np.ndarray  # (3, K)
    nose_expression: np.ndarray  # (3, E)
    mobility: np.ndarray  # (n²,) mm: the largest displacement any one blendshape gives the point (expression.py)

    def surface(self, fit: FaceFit, expression: bool = True) -> np.ndarray:
        """(n², 3) the fitted surface at the UV points, in the face's frame; without the fitted expression's
        displacements when `expression` is False (the face's nose tip stays at the origin)."""
        a = fit.identity[: self.identity.shape[2]]
        s = self.mean + self.identity[:, :, : len(a)] @ a - self.nose_identity[:, : len(a)] @ a
        if expression:
            s = s + self.expression @ fit.expression - self.nose_expression @ fit.expression
        return (s - fit.t) @ fit.R

    def expression_displacement(self, fit: FaceFit) -> np.ndarray:
        """(n², 3) what the fitted expression moves each UV point by, in the face's frame (nose tip fixed)."""
        return (self.expression @ fit.expression - self.nose_expression @ fit.expression) @ fit.R


@lru_cache(maxsize=4)
def uv_basis(config: GeometryImageConfig = GeometryImageConfig()) -> UVBasis:
    """The model sampled at the UV grid of `config` (cached)."""
    m = load_model()
    nose = m.mean[m.nose_tip].astype(np.float64)
    V = m.mean.astype(np.float64) - nose
    face_tris = m.triangles[(m.region[m.triangles] == 0).all(axis=1)].astype(np.int64)
    n, cell = config.size, config.cell_mm
    x0, y0 = -(n - 1) / 2 * cell, config.top_mm
    _, tri, bary = front_triangles(V, face_tris, x0, y0, cell, n, n)
    tri, bary = tri.ravel(), bary.reshape(-1, 3)
    inside = tri >= 0
    corners = face_tris[np.maximum(tri, 0)]  # (n², 3) vertex indices

    def at_uv(field: np.ndarray) -> np.ndarray:  # (V, ...) -> (n², ...), barycentric
        f = field[corners].astype(np.float64)
        return np.einsum("uc,uc...->u...", bary, f)

    identity = at_uv(m.identity_basis.transpose(1, 2, 0))  # (n², 3, K)
    expression = at_uv(m.expression_basis.transpose(1, 2, 0))
    mobility = np.linalg.norm(expression, axis=1).max(axis=1)
    return UVBasis(config, inside, at_uv(V), identity, expression,
                   m.identity_basis[:, m.nose_tip].astype(np.float64).T,
                   m.expression_basis[:, m.nose_tip].astype(np.float64).T, mobility)


@dataclass(frozen=True, eq=False)
class GeometryImage:
    """A face's geometry image: the scan's surface at each UV point (n, n, 3) mm in the face's frame, and where it
    was seen (n, n); with the fitted surface and what the fitted expression moved each point by."""

    points: np.ndarray  # (n, n, 3)
    valid: np.ndarray  # (n, n) bool
    fitted: np.ndarray  # (n, n, 3) the fitted model surface
    expression: np.ndarray  # (n, n, 3) the fitted expression's displacement


def _depth_grid(face: FaceScan) -> tuple[np.ndarray, float, float, float]:
    """(depth image (H, W) NaN where none, x of column 0, y of row 0, cell mm) of a face on a uniform x–y grid."""
    xyz, valid = face.to_range_image()
    r, c = face.grid[:, 0], face.grid[:, 1]
    span = c.max() - c.min()
    res = float((face.points[:, 0].max() - face.points[:, 0].min()) / span) if span else 1.0
    x0 = float(np.median(face.points[:, 0] - c * res))
    y0 = float(np.median(face.points[:, 1] + r * res))
    return np.where(valid, xyz[..., 2], np.nan), x0, y0, res


def _bilinear(z: np.ndarray, x0: float, y0: float, res: float, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Depth at (x, y) by bilinear interpolation of the grid's four nearest cells; NaN unless all four hold data."""
    fc, fr = (x - x0) / res, (y0 - y) / res
    ok = np.isfinite(fc) & np.isfinite(fr) & (fc >= 0) & (fr >= 0) & (fc < z.shape[1] - 1) & (fr < z.shape[0] - 1)
    c = np.where(ok, np.floor(np.where(ok, fc, 0)), 0).astype(np.int64)
    r = np.where(ok, np.floor(np.where(ok, fr, 0)), 0).astype(np.int64)
    u, v = fc - c, fr - r
    out = ((1 - u) * (1 - v) * z[r, c] + u * (1 - v) * z[r, c + 1] + (1 - u) * v * z[r + 1, c] + u * v * z[r + 1, c + 1])
    return np.where(ok, out, np.nan)


def geometry_image(face: FaceScan, fit: FaceFit | None = None,
                   config: GeometryImageConfig = GeometryImageConfig()) -> GeometryImage:
    """The geometry image of a preprocessed face (module docstring): at each UV point of the fitted surface F with
    unit normal n, the scan's surface F + s·n where the normal line meets it (three Newton steps on the depth map,
    which is a height field on the resampling grid), missing where the scan has no surface there or it lies more
    than `max_offset_mm` from F."""
    fit = face_fit(face) if fit is None else fit
    basis = uv_basis(config)
    n = config.size
    F = basis.surface(fit).reshape(n, n, 3)
    du, dv = np.gradient(F, axis=1), np.gradient(F, axis=0)
    normal = np.cross(dv, du)  # rows run down (−y), columns along +x: this points along +z on a frontal face
    normal /= np.maximum(np.linalg.norm(normal, axis=2, keepdims=True), 1e-12)
    z, x0, y0, res = _depth_grid(face)
    s = np.zeros((n, n))
    nz = np.maximum(normal[..., 2], 0.1)
    for _ in range(3):
        q = F + s[..., None] * normal
        gap = _bilinear(z, x0, y0, res, q[..., 0], q[..., 1]) - q[..., 2]
        s = s + np.nan_to_num(gap) * nz
    q = F + s[..., None] * normal
    gap = _bilinear(z, x0, y0, res, q[..., 0], q[..., 1]) - q[..., 2]
    valid = (basis.inside.reshape(n, n) & np.isfinite(gap) & (np.abs(np.nan_to_num(gap, nan=np.inf)) < 0.25 * res)
             & (np.abs(s) <= config.max_offset_mm))
    points = np.where(valid[..., None], q, np.nan)
    return GeometryImage(points, valid, F, basis.expression_displacement(fit).reshape(n, n, 3))


# ------------------------------------------------------------------------------------------------ morph-id
@dataclass(frozen=True)
class MorphIDConfig:
    """Identity coefficients as the feature (Blanz & Vetter, "Face recognition based on fitting a 3D morphable
    model", PAMI 2003: the fitted coefficients, scaled by the model's standard deviations, compared by angle)."""

    modes: int = 40  # leading identity modes compared (preprocessing fits 40, pose.ModelFitConfig)
    distance: str = "cosine"  # "cosine" (Blanz & Vetter's angle) or "euclidean"
    refit: RefitConfig = field(default_factory=RefitConfig)  # the coefficients of the robust refit (outside-model
    #   faces with occluders, synthetic 60 × 5: rank-1 67.5 % → 87.9 %; docs/model-methods.md)

    def __post_init__(self) -> None:
        if self.distance not in ("cosine", "euclidean"):
            raise ValueError("distance must be 'cosine' or 'euclidean'")
        if self.modes < 1:
            raise ValueError("modes must be ≥ 1")


class MorphIDMatcher(Matcher[np.ndarray]):
    """The fitted identity coefficients α (unit prior: ICT-FaceKit's modes are scaled by their standard
    deviations) as a face's template; similarity cos(α_p, α_g) or −‖α_p − α_g‖."""

    name = "morph-id"
    config_class = MorphIDConfig
    added_options = {"refit": {"enabled": False, "fine_iterations": 0}}  # templates stored before the robust refit
    #   (December 2026), or before its longer run on fine faces (2026-12-06)

    def __init__(self, config: MorphIDConfig | None = None) -> None:
        self.config = MorphIDConfig() if config is None else config

    def features(self, scan: FaceScan) -> np.ndarray:
        a = refit(scan, self.config.refit).identity[: self.config.modes]
        return np.pad(a, (0, self.config.modes - len(a)))

    def enroll(self, scan: FaceScan) -> Template:
        check_face(scan)
        return Template(scan.meta.subject, scan.meta.scan_id, self.name, {"identity": self.features(scan)})

    def prepare(self, scan: FaceScan) -> np.ndarray:
        check_face(scan)
        return self.features(scan)

    def _similarity(self, p: np.ndarray, G: np.ndarray) -> np.ndarray:
        return vector_similarity(p, G, self.config.distance)

    def scores(self, probe: FaceScan | np.ndarray, templates: Sequence[Template]) -> tuple[np.ndarray, None]:
        p = self._probe(probe, templates)
        if not templates:
            return np.zeros(0), None
        return self._similarity(p, np.stack([t.arrays["identity"] for t in templates])), None

    def score(self, probe: FaceScan | np.ndarray, template: Template) -> float:
        return float(self.scores(probe, [template])[0][0])
