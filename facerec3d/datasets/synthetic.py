"""Realistic synthetic 3D face scans with ground truth.

Faces come from the ICT-FaceKit morphable model (identity coefficients
~ N(0, 1), ARKit blendshape expressions). A simulated structured-light /
laser range scanner (a Minolta Vivid 910 as used for FRGC v2 is the model)
images the head, neck and a torso surface with a perspective camera about
1 m away and produces a range image with what real scans have:
self-occlusion, depth noise along the ray, dropouts at grazing angles and in
the eyes and mouth, random holes, and spikes nearer and farther than the
surface. Scan coordinates are the camera frame of FRGC v2 (.abs): X right,
Y up, the camera at the origin looking along −Z, so Z is negative (mm).

The generator knows the truth: the head pose, the nose tip and the other
fiducials in scan coordinates, which pixels are spikes or holes, and the
clean surface before noise.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numba import njit

from facerec3d.datasets.model import EXPRESSION_PRESETS, MorphableModel, load_model
from facerec3d.geometry.transforms import rotation_from_euler
from facerec3d.scan import FaceScan, ScanMeta

#: Landmark names written to the manifest (subset of model fiducials).
TRUTH_LANDMARKS = ("nose_tip", "nose_bridge", "left_eye_inner", "right_eye_inner")


@dataclass(frozen=True)
class ScannerConfig:
    """The simulated range scanner. Defaults follow FRGC v2's Minolta Vivid 910 (480×640, ~0.6–0.8 mm/pixel at 1 m)."""

    rows: int = 480
    cols: int = 640
    focal_px: float = 1450.0  # focal length in pixels: ~0.7 mm per pixel at 1 m
    distance_mm: float = 1000.0  # camera to nose tip
    distance_jitter_mm: float = 50.0  # uniform ± jitter of that distance per scan
    noise_mm: float = 0.25  # Gaussian depth noise σ along the ray
    grazing_cos: float = 0.2  # surfaces seen more obliquely than this cosine are lost
    grazing_soft_cos: float = 0.35  # between the two cosines, pixels drop out with rising probability
    n_holes: int = 3  # random missing discs on the face (specular dropouts)
    hole_radius_mm: tuple[float, float] = (2.0, 5.0)
    spike_fraction: float = 0.002  # share of valid pixels turned into spikes
    spike_range_mm: tuple[float, float] = (15.0, 150.0)  # |offset| along the ray, nearer or farther
    torso: bool = True  # a torso / shoulders surface below the head


@dataclass(frozen=True)
class ScanSpec:
    """One scan to synthesise: who, which expression, which pose (degrees)."""

    subject: int
    expression: str = "neutral"  # a key of EXPRESSION_PRESETS
    strength: float = 1.0  # expression strength in [0, 1]
    yaw: float = 0.0
    pitch: float = 0.0
    roll: float = 0.0
    seed: int = 0  # scanner noise, holes, spikes and distance


@dataclass(frozen=True, eq=False)
class SyntheticScan:
    """A synthesised scan with its ground truth (all in scan coordinates, mm)."""

    scan: FaceScan
    spec: ScanSpec
    rotation: np.ndarray  # head rotation from the frontal pose (3×3)
    landmarks: dict[str, np.ndarray]  # true fiducials (the nose tip among them)
    spike: np.ndarray  # (N,) bool: the point is an injected spike
    clean_xyz: np.ndarray  # (H, W, 3) the surface before noise, holes and spikes (NaN = nothing there)
    hole: np.ndarray  # (H, W) bool: pixels removed by the random holes


def identity_coefficients(subject: int, seed: int = 0, n_modes: int = 100) -> np.ndarray:
    """Identity coefficients α ~ N(0, 1) of a synthetic subject, deterministic in (seed, subject)."""
    rng = np.random.default_rng([seed, 7919, subject])
    return rng.standard_normal(n_modes)


# --------------------------------------------------------------------- geometry
def _torso_mesh(neck_y: float, neck_z: float) -> tuple[np.ndarray, np.ndarray]:
    """A shoulders-and-chest surface below the neck, as a grid mesh (mm, model frame)."""
    xs = np.linspace(-230.0, 230.0, 93)
    top = neck_y + 15.0 - 0.45 * np.maximum(0.0, np.abs(xs) - 65.0)  # shoulders slope down
    t = np.linspace(0.0, 1.0, 36)[:, None]
    X = np.broadcast_to(xs, (len(t), len(xs)))
    Y = neck_y - 160.0 + t * (top - neck_y + 160.0)
    Z = neck_z - 30.0 + 95.0 * np.sqrt(np.clip(1.0 - (X / 235.0) ** 2, 0.0, None))
    verts = np.stack([X, Y, Z], axis=-1).reshape(-1, 3)
    idx = np.arange(X.size).reshape(X.shape)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    # winding chosen so that normals face +z (towards the camera)
    tris = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)])
    return verts, tris.astype(np.int32)


@njit(cache=True)
def _raycast(verts, tris, focal, cx, cy, rows, cols):  # pragma: no cover - compiled
    """Z-buffer ray casting of a triangle mesh in camera coordinates (camera looks along −Z).

    Returns the ray length s (pixel ray direction d = ((c−cx)/f, −(r−cy)/f, −1);
    point = s·d), the triangle hit and the cosine between its normal and the
    reversed ray (negative for a back face).
    """
    depth = np.full((rows, cols), np.inf)
    tri_id = np.full((rows, cols), -1, np.int64)
    cosine = np.zeros((rows, cols))
    for k in range(tris.shape[0]):
        v0 = verts[tris[k, 0]]
        v1 = verts[tris[k, 1]]
        v2 = verts[tris[k, 2]]
        if v0[2] >= -1.0 or v1[2] >= -1.0 or v2[2] >= -1.0:
            continue
        u0 = cx + focal * v0[0] / -v0[2]
        w0 = cy - focal * v0[1] / -v0[2]
        u1 = cx + focal * v1[0] / -v1[2]
        w1 = cy - focal * v1[1] / -v1[2]
        u2 = cx + focal * v2[0] / -v2[2]
        w2 = cy - focal * v2[1] / -v2[2]
        cmin = max(int(np.ceil(min(u0, u1, u2))), 0)
        cmax = min(int(np.floor(max(u0, u1, u2))), cols - 1)
        rmin = max(int(np.ceil(min(w0, w1, w2))), 0)
        rmax = min(int(np.floor(max(w0, w1, w2))), rows - 1)
        if cmin > cmax or rmin > rmax:
            continue
        area = (u1 - u0) * (w2 - w0) - (u2 - u0) * (w1 - w0)
        if abs(area) < 1e-12:
            continue
        e1 = v1 - v0
        e2 = v2 - v0
        n = np.array([e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]])
        nn = np.sqrt(n[0] ** 2 + n[1] ** 2 + n[2] ** 2)
        if nn == 0.0:
            continue
        n = n / nn
        nv0 = n[0] * v0[0] + n[1] * v0[1] + n[2] * v0[2]
        for r in range(rmin, rmax + 1):
            for c in range(cmin, cmax + 1):
                b1 = ((c - u0) * (w2 - w0) - (u2 - u0) * (r - w0)) / area
                b2 = ((u1 - u0) * (r - w0) - (c - u0) * (w1 - w0)) / area
                if b1 < 0.0 or b2 < 0.0 or b1 + b2 > 1.0:
                    continue
                dx = (c - cx) / focal
                dy = -(r - cy) / focal
                nd = n[0] * dx + n[1] * dy - n[2]
                if abs(nd) < 1e-12:
                    continue
                s = nv0 / nd
                if 0.0 < s < depth[r, c]:
                    dn = np.sqrt(dx * dx + dy * dy + 1.0)
                    depth[r, c] = s
                    tri_id[r, c] = k
                    cosine[r, c] = -nd / dn
    return depth, tri_id, cosine


# ---------------------------------------------------------------- generator
class FaceScanner:
    """Synthesises range scans of morphable-model faces, as a range scanner would see them."""

    def __init__(self, config: ScannerConfig = ScannerConfig(), model: MorphableModel | None = None, seed: int = 0):
        self.config = config
        self.model = model or load_model()
        self.seed = seed
        m = self.model
        neck = m.mean[m.region == 1]
        lowest = neck[neck[:, 1] < neck[:, 1].min() + 20.0]
        self._pivot = np.array([0.0, float(lowest[:, 1].mean()) + 60.0, float(lowest[:, 2].mean())])
        if config.torso:
            tv, tt = _torso_mesh(float(lowest[:, 1].mean()) + 20.0, float(lowest[:, 2].mean()))
        else:
            tv, tt = np.zeros((0, 3)), np.zeros((0, 3), np.int32)
        self._torso_verts = tv
        self._tris = np.concatenate([m.triangles, tt + len(m.mean)]).astype(np.int64)
        self._n_head_tris = len(m.triangles)
        face_tri = (m.region[m.triangles] == 0).all(axis=1)
        self._face_tri = np.concatenate([face_tri, np.zeros(len(tt), bool)])

    def scan(self, spec: ScanSpec) -> SyntheticScan:
        """Synthesise one scan with its ground truth."""
        cfg, m = self.config, self.model
        rng = np.random.default_rng([self.seed, spec.subject, spec.seed, 104729])
        blend = {k: v * spec.strength for k, v in EXPRESSION_PRESETS[spec.expression].items()}
        head = m.shape(identity_coefficients(spec.subject, self.seed), blend)
        R = rotation_from_euler(spec.yaw, spec.pitch, spec.roll)
        head = (head - self._pivot) @ R.T + self._pivot
        verts = np.concatenate([head, self._torso_verts])
        # camera: on the +z axis in front of the nose, looking along -z
        nose = head[m.nose_tip]
        dist = cfg.distance_mm + rng.uniform(-cfg.distance_jitter_mm, cfg.distance_jitter_mm)
        cam = np.array([nose[0] + rng.normal(0, 25.0), nose[1] + rng.normal(-10.0, 25.0), nose[2] + dist])
        vc = verts - cam
        cx, cy = (cfg.cols - 1) / 2.0, (cfg.rows - 1) / 2.0
        s, tri, cosine = _raycast(vc, self._tris, cfg.focal_px, cx, cy, cfg.rows, cfg.cols)
        rr, cc = np.mgrid[0 : cfg.rows, 0 : cfg.cols]
        dirs = np.stack([(cc - cx) / cfg.focal_px, -(rr - cy) / cfg.focal_px, -np.ones(rr.shape)], axis=-1)
        hit = np.isfinite(s) & (cosine > 0.0)  # back faces: rays through the eye and mouth openings
        clean = np.where(hit[..., None], s[..., None] * dirs, np.nan)

        # scanner effects
        valid = hit & (cosine > cfg.grazing_cos)
        soft = (cosine - cfg.grazing_cos) / (cfg.grazing_soft_cos - cfg.grazing_cos)
        valid &= ~(rng.random(s.shape) > soft) | (cosine >= cfg.grazing_soft_cos)
        tri_safe = np.where(tri >= 0, tri, 0)
        on_face = hit & self._face_tri[tri_safe]
        nose_px = self._project(nose - cam, cx, cy)
        hole = self._holes(rng, on_face, clean, nose - cam, nose_px)
        valid &= ~hole
        noisy_s = s + rng.normal(0.0, cfg.noise_mm, s.shape)
        xyz = np.where(valid[..., None], noisy_s[..., None] * dirs, np.nan)
        spike_px = valid & (rng.random(s.shape) < cfg.spike_fraction)
        offs = rng.uniform(*cfg.spike_range_mm, size=s.shape) * rng.choice([-1.0, 1.0], size=s.shape)
        xyz = np.where(spike_px[..., None], (noisy_s - offs)[..., None] * dirs, xyz)

        truth = {k: v - cam for k, v in m.fiducials(head).items()}
        label = spec.expression
        meta = ScanMeta(
            subject=subject_id(spec.subject),
            expression="neutral" if label == "neutral" else "non-neutral",
            extra={"label": label, "yaw": spec.yaw, "pitch": spec.pitch, "roll": spec.roll},
        )
        scan = FaceScan.from_range_image(xyz, valid, meta=meta)
        spike = spike_px[scan.grid[:, 0], scan.grid[:, 1]]
        return SyntheticScan(scan, spec, R, truth, spike, clean, hole)

    def _project(self, p: np.ndarray, cx: float, cy: float) -> tuple[float, float]:
        f = self.config.focal_px
        return cy - f * p[1] / -p[2], cx + f * p[0] / -p[2]

    def _holes(self, rng, on_face, clean, nose, nose_px) -> np.ndarray:
        """Random missing discs on the face, kept 10 mm clear of the nose tip."""
        cfg = self.config
        hole = np.zeros(on_face.shape, bool)
        candidates = np.argwhere(on_face)
        if not len(candidates) or cfg.n_holes == 0:
            return hole
        px_per_mm = self.config.focal_px / -nose[2]
        rr, cc = np.mgrid[0 : hole.shape[0], 0 : hole.shape[1]]
        made = 0
        for r, c in candidates[rng.permutation(len(candidates))[: 20 * cfg.n_holes]]:
            if made == cfg.n_holes:
                break
            radius = rng.uniform(*cfg.hole_radius_mm)
            if np.linalg.norm(clean[r, c] - nose) < radius + 10.0:
                continue
            hole |= (rr - r) ** 2 + (cc - c) ** 2 <= (radius * px_per_mm) ** 2
            made += 1
        return hole & on_face


def subject_id(subject: int) -> str:
    """FRGC-style five-digit subject id of a synthetic subject number."""
    return f"{subject + 4200:05d}"


# ------------------------------------------------------------------ datasets
#: The scan plan of each subject, repeated as needed: (kind, expression).
SCAN_PLAN = ("neutral", "neutral", "expression", "yaw", "expression", "pose", "neutral", "expression")
EXPRESSIONS = ("smile", "open-mouth", "surprise", "frown", "puffed-cheeks")


@dataclass(frozen=True)
class DatasetConfig:
    """A synthetic dataset: subjects × scans, expressions and poses."""

    subjects: int = 20
    scans: int = 4  # per subject; the first is always a near-frontal neutral scan
    seed: int = 0
    first_subject: int = 0  # subject numbers first_subject.. (a disjoint training set starts after the test set)
    expressions: tuple[str, ...] = EXPRESSIONS  # drawn uniformly for the "expression" scans
    expression_strength: tuple[float, float] = (0.6, 1.0)  # uniform range of blendshape weights' scale
    yaw_probe: float = 25.0  # |yaw| of the "yaw" scans, degrees
    pose_jitter: float = 5.0  # σ of yaw/pitch/roll on the other scans, degrees
    max_pose: tuple[float, float, float] = (30.0, 20.0, 10.0)  # |yaw|, |pitch|, |roll| of the "pose" scans
    scanner: ScannerConfig = field(default_factory=ScannerConfig)


def plan_dataset(cfg: DatasetConfig) -> list[ScanSpec]:
    """The scan specifications of a dataset, deterministic for its seed."""
    specs = []
    unknown = set(cfg.expressions) - set(EXPRESSIONS)
    if unknown or not cfg.expressions:
        raise ValueError(f"unknown expressions {sorted(unknown)}: use some of {', '.join(EXPRESSIONS)}")
    for subject in range(cfg.first_subject, cfg.first_subject + cfg.subjects):
        rng = np.random.default_rng([cfg.seed, subject, 31337])
        for k in range(cfg.scans):
            kind = SCAN_PLAN[k % len(SCAN_PLAN)]
            yaw, pitch, roll = rng.normal(0.0, cfg.pose_jitter, 3) * (0.4 if k == 0 else 1.0)
            expression, strength = "neutral", 1.0
            if kind == "expression":
                expression = cfg.expressions[rng.integers(len(cfg.expressions))]
                strength = rng.uniform(*cfg.expression_strength)
            elif kind == "yaw":
                yaw = cfg.yaw_probe * rng.choice([-1.0, 1.0])
            elif kind == "pose":
                yaw, pitch, roll = rng.uniform(-1.0, 1.0, 3) * np.asarray(cfg.max_pose)
            specs.append(ScanSpec(subject, expression, float(strength), float(yaw), float(pitch), float(roll), seed=k))
    return specs


BOSPHORUS_TYPES = {"neutral": ("N", "N"), "smile": ("E", "HAPPY"), "open-mouth": ("LFAU", "27"),
                   "surprise": ("E", "SURPRISE"), "frown": ("UFAU", "4"), "puffed-cheeks": ("CAU", "A22")}
FRGC_SESSIONS = ("Spring2003range", "Fall2003range", "Spring2004range")


def scan_path(spec: ScanSpec, index: int, fmt: str) -> str:
    """Relative path of a scan in FRGC (`abs`) or Bosphorus (`bnt`) layout."""
    if fmt == "abs":
        session = FRGC_SESSIONS[min(spec.seed * len(FRGC_SESSIONS) // 8, len(FRGC_SESSIONS) - 1)]
        return f"nd1/{session}/{subject_id(spec.subject)}d{index + 100:03d}.abs.gz"
    if fmt == "bnt":
        kind, sub = BOSPHORUS_TYPES[spec.expression]
        if spec.expression == "neutral" and abs(spec.yaw) >= 10:
            kind, sub = "YR", f"{'R' if spec.yaw > 0 else 'L'}{int(round(abs(spec.yaw) / 10) * 10)}"
        bs = f"bs{spec.subject:03d}"
        return f"{bs}/{bs}_{kind}_{sub}_{spec.seed}.bnt"
    raise ValueError(f"unknown format {fmt!r}: use 'abs' or 'bnt'")


MANIFEST_COLUMNS = ("path", "subject", "expression", "label", "yaw", "pitch", "roll") + tuple(
    f"{name}_{axis}" for name in TRUTH_LANDMARKS for axis in "xyz"
)


def write_dataset(out: str | Path, cfg: DatasetConfig = DatasetConfig(), fmt: str = "abs", progress: bool = False) -> Path:
    """Write a synthetic dataset in FRGC (`abs`) or Bosphorus (`bnt`) layout with `manifest.csv`.

    The manifest has `path,subject,expression` (as `facerec3d` datasets read
    it) plus the ground truth: fine expression label, head pose (degrees) and
    the fiducials in scan coordinates (mm). Returns the manifest's path.
    """
    from facerec3d.io import save_scan

    out = Path(out)
    scanner = FaceScanner(cfg.scanner, seed=cfg.seed)
    specs = plan_dataset(cfg)
    rows = []
    it = specs
    if progress:
        from tqdm import tqdm

        it = tqdm(specs, desc="synthesising", unit="scan")
    for i, spec in enumerate(it):
        rel = scan_path(spec, i, fmt)
        s = scanner.scan(spec)
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        save_scan(s.scan, out / rel)
        row = {"path": rel, "subject": s.scan.meta.subject, "expression": s.scan.meta.expression,
               "label": s.scan.meta.extra["label"], "yaw": f"{spec.yaw:.3f}", "pitch": f"{spec.pitch:.3f}",
               "roll": f"{spec.roll:.3f}"}
        for name in TRUTH_LANDMARKS:
            for axis, value in zip("xyz", s.landmarks[name]):
                row[f"{name}_{axis}"] = f"{value:.4f}"
        rows.append(row)
    manifest = out / "manifest.csv"
    with open(manifest, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=MANIFEST_COLUMNS)
        w.writeheader()
        w.writerows(rows)
    return manifest


def quick_scan(subject: int = 0, expression: str = "neutral", yaw: float = 0.0, pitch: float = 0.0,
               roll: float = 0.0, seed: int = 0, scanner: ScannerConfig = ScannerConfig(), **changes) -> SyntheticScan:
    """One synthetic scan in a line (tests, examples). Extra keywords change the ScannerConfig."""
    cfg = replace(scanner, **changes) if changes else scanner
    return FaceScanner(cfg).scan(ScanSpec(subject, expression, 1.0, yaw, pitch, roll, seed))
