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

Other sensors are named presets of `ScannerConfig` (`SENSOR_PROFILES`:
``frgc``, ``kinect-v2``, ``kinect-v2-8bit``, ``realsense``): depth noise
that grows with distance, time-of-flight flying pixels at depth edges,
coarse depth steps, and active-stereo disparity quantisation with holes in
the occlusion shadow of the second imager. Faces that the linear model
cannot express (the matcher's model is the same ICT-FaceKit model) come from
`IdentityConfig` (`IDENTITY_PROFILES`: ``model``, ``outside-model``): a wider
identity spread, a smooth non-linear per-subject deformation, and occluders
(hair fringe, glasses, a hand) ray-cast with the head.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from facerec3d.errors import InputError
from facerec3d.facemodel import EXPRESSION_PRESETS, MorphableModel, load_model
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
    # --- consumer depth cameras (the defaults leave all of this off) ---
    noise_z2_mm: float = 0.0  # extra depth noise: σ(Z) = noise_mm + noise_z2_mm·(Z / 1 m)²
    flying_pixel_fraction: float = 0.0  # share of depth-edge pixels given a mixed depth (ToF flying pixels)
    flying_jump_mm: float = 20.0  # a pixel is on a depth edge when its 3×3 neighbourhood spans more than this
    stereo_baseline_mm: float = 0.0  # active stereo: second imager this far along +x (0 = not stereo)
    disparity_noise_px: float = 0.0  # σ of the disparity noise (px); depth σ = Z²·σ_d / (f·b)
    disparity_step_px: float = 0.0  # disparity quantisation (subpixel resolution, px); 0 = none
    depth_step_mm: float = 0.0  # depth −Z rounded to this step (mm), applied last; 0 = none
    depth_steps: tuple[tuple[float, float], ...] = ()  # (from depth mm, step mm): coarser steps from a depth on


# Kinect v2, time of flight: 512×424 depth, 70.6° horizontal field of view (focal ≈ 365 px, its usual
# factory intrinsics), subject at 0.8–1.5 m. Axial noise ≈ 1.5 mm at 1 m growing with distance, after
# Fankhauser et al., "Kinect v2 for mobile robot navigation: evaluation and modeling", ICAR 2015, and
# Sarbolandi et al., "Kinect range sensing: structured-light versus time-of-flight Kinect", CVIU 2015
# (which also describes the flying pixels at depth edges). The SDK reports whole millimetres.
_KINECT_V2 = ScannerConfig(
    rows=424, cols=512, focal_px=365.0, distance_mm=1150.0, distance_jitter_mm=350.0,
    noise_mm=0.5, noise_z2_mm=1.0, n_holes=1, flying_pixel_fraction=0.5, flying_jump_mm=20.0,
    depth_step_mm=1.0)

#: Named scanner presets. Each is a `ScannerConfig`; `dataclasses.replace` adapts one.
SENSOR_PROFILES: dict[str, ScannerConfig] = {
    # FRGC v2's Minolta Vivid 910 (Phillips et al., CVPR 2005): the defaults.
    "frgc": ScannerConfig(),
    "kinect-v2": _KINECT_V2,
    # The same Kinect v2 frames stored with 8-bit depth: 4 mm steps below 1024 mm, 8 mm from there on.
    "kinect-v2-8bit": replace(_KINECT_V2, depth_step_mm=4.0, depth_steps=((1024.0, 8.0),)),
    # RealSense D435, active stereo at 640×480 (focal ≈ 385 px, baseline 50 mm), subject at 0.4–0.9 m.
    # Depth RMS error = Z²·subpixel / (f·b) with subpixel ≈ 0.08 px (Grunnet-Jepsen et al., Intel,
    # "Tuning depth cameras for best performance"); disparity kept in 1/8 px steps, depth in mm.
    # Pixels the right imager cannot see (occlusion shadow) have no depth.
    "realsense": ScannerConfig(
        rows=480, cols=640, focal_px=385.0, distance_mm=650.0, distance_jitter_mm=250.0, noise_mm=0.0,
        stereo_baseline_mm=50.0, disparity_noise_px=0.08, disparity_step_px=0.125, depth_step_mm=1.0),
}


def sensor_profile(name: str) -> ScannerConfig:
    """The `ScannerConfig` of a named sensor (a key of `SENSOR_PROFILES`)."""
    try:
        return SENSOR_PROFILES[name]
    except KeyError:
        raise ValueError(f"unknown sensor profile {name!r}: use one of {', '.join(SENSOR_PROFILES)}") from None


#: Occluders a scan can have (`ScanSpec.occluder`), besides None.
OCCLUDERS = ("fringe", "glasses", "hand")


@dataclass(frozen=True)
class IdentityConfig:
    """How far synthetic faces stray from the morphable model (the defaults: not at all)."""

    identity_sigma: float = 1.0  # spread of the identity coefficients (1 = the model's prior)
    deformation_mm: float = 0.0  # largest smooth non-linear displacement of the face along its normals
    occluders: tuple[str | None, ...] = (None,)  # drawn uniformly per scan (None = no occluder)


#: Named identity presets, to combine with any sensor.
IDENTITY_PROFILES: dict[str, IdentityConfig] = {
    "model": IdentityConfig(),
    "outside-model": IdentityConfig(identity_sigma=1.6, deformation_mm=3.0, occluders=(None,) + OCCLUDERS),
    # the same faces with nothing in front of them: tells what the face's shape costs a method from what the
    # occluders do (the plan and every face are those of "outside-model", the occluders left out)
    "outside-model-unoccluded": IdentityConfig(identity_sigma=1.6, deformation_mm=3.0),
}


def identity_profile(name: str) -> IdentityConfig:
    """The `IdentityConfig` of a named identity profile (a key of `IDENTITY_PROFILES`)."""
    try:
        return IDENTITY_PROFILES[name]
    except KeyError:
        raise ValueError(f"unknown identity profile {name!r}: use one of {', '.join(IDENTITY_PROFILES)}") from None


def _check_occluder(name: str | None) -> None:
    if name is not None and name not in OCCLUDERS:
        raise ValueError(f"unknown occluder {name!r}: use None or one of {', '.join(OCCLUDERS)}")


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
    occluder: str | None = None  # None or one of OCCLUDERS


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
    flying: np.ndarray | None = None  # (H, W) bool: pixels given a mixed depth between two surfaces
    shadow: np.ndarray | None = None  # (H, W) bool: pixels lost in the stereo occlusion shadow
    occluded: np.ndarray | None = None  # (H, W) bool: pixels that see the occluder, not the head


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


def _vertex_normals(verts: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (outward for the model's winding)."""
    n = np.cross(verts[tris[:, 1]] - verts[tris[:, 0]], verts[tris[:, 2]] - verts[tris[:, 0]])
    vn = np.zeros_like(verts)
    for k in range(3):
        np.add.at(vn, tris[:, k], n)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)


def _grid_tris(n_rows: int, n_cols: int) -> np.ndarray:
    """Triangles of a row-major vertex grid; facing +z when rows run along +y and columns along +x."""
    idx = np.arange(n_rows * n_cols).reshape(n_rows, n_cols)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    return np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)])


def _face_outward(verts: np.ndarray, tris: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Triangles re-wound so that each normal points away from its centre (per triangle)."""
    n = np.cross(verts[tris[:, 1]] - verts[tris[:, 0]], verts[tris[:, 2]] - verts[tris[:, 0]])
    flip = ((verts[tris].mean(axis=1) - centres) * n).sum(axis=1) < 0
    tris = tris.copy()
    tris[flip] = tris[flip][:, [0, 2, 1]]
    return tris


def _tube(path: np.ndarray, radius: float, closed: bool = False, sides: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """A thin tube of `radius` along a polyline (open ends), outward facing."""
    path = np.asarray(path, float)
    tangent = (np.roll(path, -1, 0) - np.roll(path, 1, 0)) if closed else np.gradient(path, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    ref = np.where(np.abs(tangent[:, 2:3]) < 0.9, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    u = np.cross(tangent, ref)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(tangent, u)
    ang = 2 * np.pi * np.arange(sides) / sides
    rings = path[:, None] + radius * (np.cos(ang)[None, :, None] * u[:, None] + np.sin(ang)[None, :, None] * v[:, None])
    idx = np.arange(len(path) * sides).reshape(len(path), sides)
    if closed:
        idx = np.concatenate([idx, idx[:1]])
    idx = np.concatenate([idx, idx[:, :1]], axis=1)  # wrap around the tube
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    tris = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)])
    ring = np.tile(np.repeat(np.arange(len(idx) - 1), sides), 2)  # ring index of each triangle
    centres = (path[ring] + path[(ring + 1) % len(path)]) / 2
    verts = rings.reshape(-1, 3)
    return verts, _face_outward(verts, tris, centres)


def _ellipsoid(centre: np.ndarray, axes: tuple[float, float, float], n: int = 14) -> tuple[np.ndarray, np.ndarray]:
    """A closed ellipsoid (x, y, z semi-axes), outward facing."""
    lat = np.linspace(-np.pi / 2, np.pi / 2, n)[1:-1]
    lon = np.linspace(0.0, 2 * np.pi, 2 * n, endpoint=False)
    ring = np.stack([np.cos(lat)[:, None] * np.cos(lon), np.sin(lat)[:, None] * np.ones_like(lon),
                     np.cos(lat)[:, None] * np.sin(lon)], axis=-1).reshape(-1, 3)
    unit = np.concatenate([ring, [[0.0, -1.0, 0.0], [0.0, 1.0, 0.0]]])
    verts = centre + unit * np.asarray(axes)
    m = len(lon)
    idx = np.arange(len(lat) * m).reshape(len(lat), m)
    idx = np.concatenate([idx, idx[:, :1]], axis=1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    tris = [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)]
    south, north = len(ring), len(ring) + 1
    tris.append(np.stack([np.full(m, south), idx[0, 1:], idx[0, :-1]], -1))
    tris.append(np.stack([np.full(m, north), idx[-1, :-1], idx[-1, 1:]], -1))
    tris = np.concatenate(tris)
    return verts, _face_outward(verts, tris, np.broadcast_to(centre, (len(tris), 3)))


def _front_z(head: np.ndarray, normals: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """z of the head's front surface (facing +z) at model-frame (x, y), from its nearest vertices."""
    front = head[normals[:, 2] > 0.3]
    _, nearest = cKDTree(front[:, :2]).query(np.stack([np.ravel(x), np.ravel(y)], axis=1), k=6)
    return front[nearest, 2].max(axis=1).reshape(np.shape(x))


def occluder_mesh(kind: str | None, head: np.ndarray, normals: np.ndarray, fiducials: dict[str, np.ndarray],
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """An occluder's triangle mesh (model frame, mm) placed from the head's fiducials.

    `fringe`: a ragged sheet of hair 6 mm in front of the forehead, 124 mm
    wide, from 75 mm above the nose bridge (50 at the temples) down to 8–26 mm
    above it. `glasses`: 2 mm rims round the eyes 5 mm in front of the nose
    bridge, a bridge over the nose and temples to the ears. `hand`: a
    palm-sized ellipsoid over one cheek (at least 25 mm beside the nose tip)
    or under the chin. None of them reaches the nose tip. `rng` draws the
    sizes and places. Returns (vertices, triangles facing outwards).
    """
    _check_occluder(kind)
    if kind is None:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    bridge, tip = fiducials["nose_bridge"], fiducials["nose_tip"]
    if kind == "fringe":
        xs = bridge[0] + np.linspace(-62.0, 62.0, 51)
        bottom = bridge[1] + rng.uniform(8.0, 20.0) + 6.0 * np.abs(np.sin(np.pi * xs / rng.uniform(8.0, 14.0)
                                                                         + rng.uniform(0, np.pi)))
        top = bridge[1] + 75.0 - 25.0 * ((xs - bridge[0]) / 62.0) ** 2  # the hairline, lower at the temples
        t = np.linspace(0.0, 1.0, 15)[:, None]
        X = np.broadcast_to(xs, (len(t), len(xs)))
        Y = bottom + t * (top - bottom)
        Z = _front_z(head, normals, X, Y) + 6.0
        return np.stack([X, Y, Z], axis=-1).reshape(-1, 3), _grid_tris(*X.shape)
    if kind == "glasses":
        z0 = bridge[2] + 5.0
        parts, inner_ends = [], []
        theta = np.linspace(0.0, 2 * np.pi, 32, endpoint=False)
        for side in ("left", "right"):
            inner, outer = fiducials[f"{side}_eye_inner"], fiducials[f"{side}_eye_outer"]
            centre = (inner + outer) / 2 - [0.0, 2.0, 0.0]
            a, b = abs(outer[0] - inner[0]) / 2 + 6.0, 14.0

            def rim_z(x):  # the frame wraps back towards the temples
                return z0 - 0.15 * np.maximum(np.abs(x - tip[0]) - abs(inner[0] - tip[0]), 0.0)

            x = centre[0] + a * np.cos(theta)
            parts.append(_tube(np.stack([x, centre[1] + b * np.sin(theta), rim_z(x)], 1), 2.0, closed=True))
            sign = np.sign(outer[0] - inner[0])
            edge = np.array([centre[0] + sign * a, centre[1], rim_z(centre[0] + sign * a)])
            temple = np.array([edge, edge + [sign * 10.0, 2.0, -25.0], edge + [sign * 16.0, 4.0, -95.0]])
            parts.append(_tube(temple, 1.5))
            inner_ends.append(np.array([centre[0] - sign * a, centre[1] + 4.0, z0]))
        arch = np.linspace(0.0, 1.0, 9)[:, None]
        span = inner_ends[0] + arch * (inner_ends[1] - inner_ends[0])
        span[:, 1] = max(span[0, 1], bridge[1]) + 3.0 * np.sin(np.pi * arch[:, 0])
        span[:, 2] = z0 + 1.0
        parts.append(_tube(span, 1.5))
    else:  # hand
        where = rng.integers(3)
        if where < 2:  # over a cheek, beside the mouth corner
            side = ("left", "right")[where]
            corner, eye = fiducials[f"{side}_mouth_corner"], fiducials[f"{side}_eye_outer"]
            sign = np.sign(corner[0] - tip[0])
            axes = (26.0, rng.uniform(38.0, 48.0), 13.0)
            x = tip[0] + sign * max(abs(corner[0] - tip[0]) + 28.0, 25.0 + axes[0])
            y = (corner[1] + eye[1]) / 2 - 10.0
        else:  # under the chin
            axes = (rng.uniform(36.0, 46.0), 22.0, 14.0)
            x, y = fiducials["chin"][0], fiducials["chin"][1] - 8.0
        z = float(_front_z(head, normals, np.array([x]), np.array([y]))[0]) + axes[2] - 1.0
        parts = [_ellipsoid(np.array([x, y, z]), axes)]
    verts = np.concatenate([v for v, _ in parts])
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    return verts, np.concatenate([t + o for (_, t), o in zip(parts, offsets)])


def _deformation(subject_seed: list[int], neutral: np.ndarray, model: MorphableModel, amplitude: float) -> np.ndarray:
    """A smooth non-linear displacement (V, 3) of a subject's face: Gaussian bumps along the normals.

    Eight bumps of radius 12–35 mm and random sign, centred on face vertices,
    summed and scaled so that the largest displacement on the face is
    `amplitude` mm. Localised bumps along the surface normals are not a
    linear combination of the model's global identity modes (cf. the
    free-form offsets beyond a 3DMM in Tran & Liu, "Nonlinear 3D face
    morphable model", CVPR 2018).
    """
    rng = np.random.default_rng(subject_seed)
    face = np.flatnonzero(model.region == 0)
    k = 8
    centres = neutral[rng.choice(face, k, replace=False)]
    radii = rng.uniform(12.0, 35.0, k)
    signs = rng.choice([-1.0, 1.0], k) * rng.uniform(0.5, 1.0, k)
    d2 = ((neutral[:, None, :] - centres[None]) ** 2).sum(axis=-1)
    field = (signs * np.exp(-d2 / (2 * radii**2))).sum(axis=1)
    field *= amplitude / np.abs(field[face]).max()
    return field[:, None] * _vertex_normals(neutral, model.triangles.astype(np.int64))


def quantise_depth(depth: np.ndarray, step_mm: float, steps: tuple[tuple[float, float], ...] = ()) -> np.ndarray:
    """Depth rounded to `step_mm` (0 = untouched); from each (depth, step) of `steps` on, to that step."""
    step = np.full(np.shape(depth), float(step_mm))
    for start, s in steps:
        step = np.where(depth >= start, s, step)
    coarse = step > 0
    return np.where(coarse, np.round(depth / np.where(coarse, step, 1.0)) * step, depth)


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

    def __init__(self, config: ScannerConfig = ScannerConfig(), model: MorphableModel | None = None, seed: int = 0,
                 identity: IdentityConfig = IdentityConfig()):
        self.config = config
        self.identity = identity
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
        self._deformed: tuple[int, np.ndarray] | None = None  # the last subject's deformation

    def face_shape(self, subject: int, expression: str = "neutral", strength: float = 1.0) -> np.ndarray:
        """A subject's head vertices (V, 3) in the model frame (mm), before pose, with the identity options."""
        m, ident = self.model, self.identity
        alpha = identity_coefficients(subject, self.seed)
        if ident.identity_sigma != 1.0:
            alpha = alpha * ident.identity_sigma
        blend = {k: v * strength for k, v in EXPRESSION_PRESETS[expression].items()}
        head = m.shape(alpha, blend)
        if ident.deformation_mm:
            if self._deformed is None or self._deformed[0] != subject:
                neutral = m.shape(alpha)
                self._deformed = subject, _deformation([self.seed, 6113, subject], neutral, m, ident.deformation_mm)
            head = head + self._deformed[1]
        return head

    def scan(self, spec: ScanSpec) -> SyntheticScan:
        """Synthesise one scan with its ground truth."""
        cfg, m = self.config, self.model
        rng = np.random.default_rng([self.seed, spec.subject, spec.seed, 104729])
        # the sensor and occluder effects draw from their own stream, so rng's draws stay as they always were
        extra = np.random.default_rng([self.seed, spec.subject, spec.seed, 15485863])
        head = self.face_shape(spec.subject, spec.expression, spec.strength)
        _check_occluder(spec.occluder)
        occ_verts, occ_tris = np.zeros((0, 3)), np.zeros((0, 3), np.int64)
        if spec.occluder:
            normals = _vertex_normals(head, self._tris[: self._n_head_tris])
            occ_verts, occ_tris = occluder_mesh(spec.occluder, head, normals, m.fiducials(head), extra)
        R = rotation_from_euler(spec.yaw, spec.pitch, spec.roll)
        head = (head - self._pivot) @ R.T + self._pivot
        occ_verts = (occ_verts - self._pivot) @ R.T + self._pivot
        verts = np.concatenate([head, self._torso_verts, occ_verts])
        tris = np.concatenate([self._tris, occ_tris + len(head) + len(self._torso_verts)])
        face_tri = np.concatenate([self._face_tri, np.zeros(len(occ_tris), bool)])
        # camera: on the +z axis in front of the nose, looking along -z
        nose = head[m.nose_tip]
        dist = cfg.distance_mm + rng.uniform(-cfg.distance_jitter_mm, cfg.distance_jitter_mm)
        cam = np.array([nose[0] + rng.normal(0, 25.0), nose[1] + rng.normal(-10.0, 25.0), nose[2] + dist])
        vc = verts - cam
        cx, cy = (cfg.cols - 1) / 2.0, (cfg.rows - 1) / 2.0
        s, tri, cosine = _raycast(vc, tris, cfg.focal_px, cx, cy, cfg.rows, cfg.cols)
        rr, cc = np.mgrid[0 : cfg.rows, 0 : cfg.cols]
        dirs = np.stack([(cc - cx) / cfg.focal_px, -(rr - cy) / cfg.focal_px, -np.ones(rr.shape)], axis=-1)
        hit = np.isfinite(s) & (cosine > 0.0)  # back faces: rays through the eye and mouth openings
        with np.errstate(invalid="ignore"):  # inf × 0 on the rays that hit nothing: masked out here
            clean = np.where(hit[..., None], s[..., None] * dirs, np.nan)
        occluded = hit & (tri >= len(self._tris))

        # scanner effects (s is the Z-depth: the ray direction has z = -1)
        valid = hit & (cosine > cfg.grazing_cos)
        soft = (cosine - cfg.grazing_cos) / (cfg.grazing_soft_cos - cfg.grazing_cos)
        valid &= ~(rng.random(s.shape) > soft) | (cosine >= cfg.grazing_soft_cos)
        tri_safe = np.where(tri >= 0, tri, 0)
        on_face = hit & face_tri[tri_safe]
        nose_px = self._project(nose - cam, cx, cy)
        hole = self._holes(rng, on_face, clean, nose - cam, nose_px)
        shadow = np.zeros(s.shape, bool)
        if cfg.stereo_baseline_mm > 0:
            shadow = hit & ~self._seen_by_second_imager(vc, tris, np.where(hit, s, np.inf), dirs, cx, cy)
            valid &= ~shadow
        flying = np.zeros(s.shape, bool)
        if cfg.flying_pixel_fraction > 0:
            s, flying = self._flying_pixels(extra, s, hit)
            valid |= flying
        valid &= ~hole
        if cfg.noise_z2_mm:
            z = np.where(np.isfinite(s), s, 0.0) / 1000.0
            noisy_s = s + rng.normal(0.0, cfg.noise_mm + cfg.noise_z2_mm * z**2)
        else:
            noisy_s = s + rng.normal(0.0, cfg.noise_mm, s.shape)
        if cfg.stereo_baseline_mm > 0:
            noisy_s = self._stereo_depth(extra, noisy_s)
        spike_px = valid & (rng.random(s.shape) < cfg.spike_fraction)
        offs = rng.uniform(*cfg.spike_range_mm, size=s.shape) * rng.choice([-1.0, 1.0], size=s.shape)
        noisy_s = np.where(spike_px, noisy_s - offs, noisy_s)
        if cfg.depth_step_mm or cfg.depth_steps:
            noisy_s = quantise_depth(noisy_s, cfg.depth_step_mm, cfg.depth_steps)
        with np.errstate(invalid="ignore"):  # as `clean`: invalid rays are masked out
            xyz = np.where(valid[..., None], noisy_s[..., None] * dirs, np.nan)

        truth = {k: v - cam for k, v in m.fiducials(head).items()}
        label = spec.expression
        meta = ScanMeta(
            subject=subject_id(spec.subject),
            expression="neutral" if label == "neutral" else "non-neutral",
            extra={"label": label, "yaw": spec.yaw, "pitch": spec.pitch, "roll": spec.roll},
        )
        if spec.occluder:
            meta.extra["occluder"] = spec.occluder
        scan = FaceScan.from_range_image(xyz, valid, meta=meta)
        spike = spike_px[scan.grid[:, 0], scan.grid[:, 1]]
        return SyntheticScan(scan, spec, R, truth, spike, clean, hole, flying, shadow, occluded)

    def _flying_pixels(self, rng, s, hit) -> tuple[np.ndarray, np.ndarray]:
        """Time-of-flight mixed pixels: edge pixels take a depth between the near and far surface.

        A pixel whose footprint straddles a depth edge integrates the returns
        of both surfaces and reports a depth between them (Sarbolandi et al.,
        CVIU 2015, §4 "mixed pixels"). Edge pixels (3×3 neighbourhood spanning
        more than `flying_jump_mm`) become flying with `flying_pixel_fraction`
        probability, at a uniform 15–85 % of the way from near to far.
        """
        cfg = self.config
        pad_near = np.pad(np.where(hit, s, np.inf), 1, constant_values=np.inf)
        pad_far = np.pad(np.where(hit, s, -np.inf), 1, constant_values=-np.inf)
        h, w = s.shape
        shifts = [(i, j) for i in range(3) for j in range(3)]
        near = np.min([pad_near[i : i + h, j : j + w] for i, j in shifts], axis=0)
        far = np.max([pad_far[i : i + h, j : j + w] for i, j in shifts], axis=0)
        edge = hit & (far - near > cfg.flying_jump_mm)
        flying = edge & (rng.random(s.shape) < cfg.flying_pixel_fraction)
        share = rng.uniform(0.15, 0.85, s.shape)
        mixed = s.copy()
        mixed[flying] = near[flying] + share[flying] * (far[flying] - near[flying])
        return mixed, flying

    def _seen_by_second_imager(self, vc, tris, s, dirs, cx, cy) -> np.ndarray:
        """Pixels whose surface point the second stereo imager (at +baseline along x) also sees.

        Active stereo has no depth where one imager's view is blocked: the
        occlusion shadow beside the near side of a depth edge. The scene is
        ray-cast from the second imager; a point is seen when its projection
        there is not more than 3 mm behind the nearest surface at one of the
        four surrounding pixels. Points outside the second image are lost too.
        """
        cfg = self.config
        b = np.array([cfg.stereo_baseline_mm, 0.0, 0.0])
        s2, _, _ = _raycast(vc - b, tris, cfg.focal_px, cx, cy, cfg.rows, cfg.cols)
        finite = np.isfinite(s)
        z = np.where(finite, s, 1.0)
        p = z[..., None] * dirs - b  # the point in the second imager's frame (same Z-depth)
        c2 = cx + cfg.focal_px * p[..., 0] / z
        r2 = cy - cfg.focal_px * p[..., 1] / z
        seen = np.zeros(s.shape, bool)
        inside = finite & (c2 > -0.5) & (c2 < cfg.cols - 0.5) & (r2 > -0.5) & (r2 < cfg.rows - 0.5)
        for dr in (0, 1):
            for dc in (0, 1):
                rr = np.clip(np.floor(r2).astype(int) + dr, 0, cfg.rows - 1)
                cc = np.clip(np.floor(c2).astype(int) + dc, 0, cfg.cols - 1)
                seen |= s2[rr, cc] >= z - 3.0
        return seen & inside

    def _stereo_depth(self, rng, s) -> np.ndarray:
        """Depth through the disparity d = f·b/Z: Gaussian disparity noise, then subpixel quantisation.

        Depth error σ_Z = Z²·σ_d/(f·b) and step ΔZ = Z²·δ/(f·b) both grow
        with Z² (Intel RealSense D400 depth error model, Grunnet-Jepsen et al.).
        """
        cfg = self.config
        fb = cfg.focal_px * cfg.stereo_baseline_mm
        finite = np.isfinite(s) & (s > 0)
        d = fb / np.where(finite, s, 1.0) + rng.normal(0.0, cfg.disparity_noise_px, s.shape)
        if cfg.disparity_step_px:
            d = np.round(d / cfg.disparity_step_px) * cfg.disparity_step_px
        return np.where(finite & (d > 0), fb / np.maximum(d, 1e-9), np.where(finite, np.inf, s))

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


def bosphorus_id(subject: int) -> str:
    """Bosphorus-style subject id (`bs000`) of a synthetic subject number: the `bnt` layout's, in its file names
    and its manifest alike. A Bosphorus name's subject keeps its `bs` (catalog.BOSPHORUS_PATTERN), so a name cannot
    carry `04200`; with another id in the manifest, a file enrolled on its own would be another person."""
    return f"bs{subject:03d}"


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
    identity: IdentityConfig = field(default_factory=IdentityConfig)  # faces beyond the model, occluders


def plan_dataset(cfg: DatasetConfig) -> list[ScanSpec]:
    """The scan specifications of a dataset, deterministic for its seed."""
    specs = []
    unknown = set(cfg.expressions) - set(EXPRESSIONS)
    if unknown or not cfg.expressions:
        raise InputError(f"unknown expressions {sorted(unknown)}: use some of {', '.join(EXPRESSIONS)}")
    low, high = cfg.expression_strength
    if not 0.0 <= low <= high <= 1.0:  # nan fails too; beyond 1 the blendshapes tear the face (a 444 mm wide smile)
        raise InputError(f"expression strength {low:g} {high:g}: give a range 0 <= low <= high <= 1 (1 1: full "
                         "strength)")
    if cfg.seed < 0 or cfg.first_subject < 0:
        raise InputError(f"seed {cfg.seed} and first subject {cfg.first_subject} must be 0 or more")
    occluders = cfg.identity.occluders
    if not occluders:
        raise ValueError("identity.occluders is empty: give (None,) for no occluders")
    for name in occluders:
        _check_occluder(name)
    for subject in range(cfg.first_subject, cfg.first_subject + cfg.subjects):
        rng = np.random.default_rng([cfg.seed, subject, 31337])
        occ_rng = np.random.default_rng([cfg.seed, subject, 7331])  # its own stream: the poses stay as they were
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
            occluder = occluders[occ_rng.integers(len(occluders))] if len(occluders) > 1 else occluders[0]
            specs.append(ScanSpec(subject, expression, float(strength), float(yaw), float(pitch), float(roll), seed=k,
                                  occluder=occluder))
    return specs


BOSPHORUS_TYPES = {"neutral": ("N", "N"), "smile": ("E", "HAPPY"), "open-mouth": ("LFAU", "27"),
                   "surprise": ("E", "SURPRISE"), "frown": ("UFAU", "4"), "puffed-cheeks": ("CAU", "A22")}
FRGC_SESSIONS = ("Spring2003range", "Fall2003range", "Spring2004range")


#: The head-pose label (manifest `pose` column) of the scan plan's kinds that are not frontal.
POSE_LABELS = {"yaw": "yaw", "pose": "yaw-pitch-roll"}


def scan_session(spec: ScanSpec) -> str:
    """The FRGC semester folder of a scan: a subject's scans go round Spring 2003, Fall 2003, Spring 2004, so
    with three or more scans per subject every semester has some (FRGC Experiment 3 can be run), and with six or
    more each person has two in each semester (genuine pairs for every mask, ROC I's within one semester too)."""
    return FRGC_SESSIONS[spec.seed % len(FRGC_SESSIONS)]


def scan_path(spec: ScanSpec, index: int, fmt: str) -> str:
    """Relative path of a scan in FRGC (`abs`, in its semester's folder) or Bosphorus (`bnt`) layout."""
    if fmt == "abs":
        return f"nd1/{scan_session(spec)}/{subject_id(spec.subject)}d{index + 100:03d}.abs.gz"
    if fmt == "bnt":
        kind, sub = BOSPHORUS_TYPES[spec.expression]
        if spec.expression == "neutral" and SCAN_PLAN[spec.seed % len(SCAN_PLAN)] in POSE_LABELS:  # as the manifest
            #   labels it: a turned scan, not a frontal one whose small random yaw reached 10°
            kind, sub = "YR", f"{'R' if spec.yaw > 0 else 'L'}{max(10, int(round(abs(spec.yaw) / 10) * 10))}"
        bs = bosphorus_id(spec.subject)
        return f"{bs}/{bs}_{kind}_{sub}_{spec.seed}.bnt"
    if fmt in ("png", "obj", "ply"):  # a camera's frames or a scanner's meshes, one folder per person
        kind = SCAN_PLAN[spec.seed % len(SCAN_PLAN)]
        return f"{subject_id(spec.subject)}/{'front' if kind == 'neutral' else kind}_{spec.seed + 1}.{fmt}"
    raise ValueError(f"unknown format {fmt!r}: use 'abs', 'bnt', 'png', 'obj' or 'ply'")


def frame_intrinsics(scanner: ScannerConfig) -> "Intrinsics":
    """The pinhole intrinsics of the simulated camera, as `intrinsics.json` gives them for its depth frames
    (1 mm depth units where the sensor reports millimetres, else 0.1 mm)."""
    from facerec3d.io import Intrinsics

    return Intrinsics(fx=scanner.focal_px, fy=scanner.focal_px, cx=(scanner.cols - 1) / 2.0,
                      cy=(scanner.rows - 1) / 2.0, depth_unit_mm=1.0 if scanner.depth_step_mm >= 1.0 else 0.1,
                      width=scanner.cols, height=scanner.rows)


MANIFEST_COLUMNS = ("path", "subject", "expression", "label", "session", "pose", "yaw", "pitch", "roll") + tuple(
    f"{name}_{axis}" for name in TRUTH_LANDMARKS for axis in "xyz"
) + ("occluder",)


def write_dataset(out: str | Path, cfg: DatasetConfig = DatasetConfig(), fmt: str = "abs", progress: bool = False,
                  spacing_mm: float = 2.0) -> Path:
    """Write a synthetic dataset in FRGC (`abs`) or Bosphorus (`bnt`) layout, or as a depth camera's 16-bit
    frames (`png`: `<subject>/front_1.png`, ... with `intrinsics.json` at the top), or as a scanner's meshes
    (`obj`) or point clouds (`ply`) with vertices about `spacing_mm` apart, each in a random frame of its own
    (`random_frame`: a stereo scanner's or a world frame, not the camera's), with `manifest.csv`.

    The manifest has `path,subject,expression,label,session,pose` (as
    `facerec3d` datasets read it: the subject as the file name gives it, `04200` or for `bnt` `bs000`;
    the FRGC semester folder, empty for `bnt`;
    the head-pose label of the ±yaw_probe scans, `yaw`, and of the free-pose
    scans, `yaw-pitch-roll`, empty for near-frontal ones) plus the ground
    truth: head pose (degrees) and the fiducials in scan coordinates (mm), and
    last the scan's occluder (empty for none). Returns the manifest's path.
    """
    from facerec3d.io import save_scan, write_depth_image
    from facerec3d.io.depth import scan_to_frame

    out = Path(out)
    scanner = FaceScanner(cfg.scanner, seed=cfg.seed, identity=cfg.identity)
    if fmt == "png":
        camera = frame_intrinsics(cfg.scanner)
        out.mkdir(parents=True, exist_ok=True)
        camera.save(out / "intrinsics.json")
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
        landmarks = s.landmarks
        if fmt == "png":
            write_depth_image(out / rel, scan_to_frame(s.scan, camera), camera)
        elif fmt in ("obj", "ply"):
            R, t = random_frame(cfg.seed * 100_003 + i)
            save_scan(export_surface(s.scan, spacing_mm, mesh=fmt == "obj", rotation=R, translation=t), out / rel)
            landmarks = {k: R @ v + t for k, v in landmarks.items()}
        else:
            save_scan(s.scan, out / rel)
        row = {"path": rel, "subject": bosphorus_id(spec.subject) if fmt == "bnt" else s.scan.meta.subject,
               "expression": s.scan.meta.expression,
               "label": s.scan.meta.extra["label"], "session": scan_session(spec) if fmt == "abs" else "",
               "pose": POSE_LABELS.get(SCAN_PLAN[spec.seed % len(SCAN_PLAN)], ""), "yaw": f"{spec.yaw:.3f}",
               "pitch": f"{spec.pitch:.3f}", "roll": f"{spec.roll:.3f}"}
        for name in TRUTH_LANDMARKS:
            for axis, value in zip("xyz", landmarks[name]):
                row[f"{name}_{axis}"] = f"{value:.4f}"
        row["occluder"] = spec.occluder or ""
        rows.append(row)
    manifest = out / "manifest.csv"
    with open(manifest, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=MANIFEST_COLUMNS)
        w.writeheader()
        w.writerows(rows)
    return manifest


def quick_scan(subject: int = 0, expression: str = "neutral", *, yaw: float = 0.0, pitch: float = 0.0,
               roll: float = 0.0, seed: int = 0, scanner: ScannerConfig = ScannerConfig(),
               identity: IdentityConfig = IdentityConfig(), occluder: str | None = None, **changes) -> SyntheticScan:
    """One synthetic scan in a line (tests, examples). Extra keywords change the ScannerConfig."""
    cfg = replace(scanner, **changes) if changes else scanner
    spec = ScanSpec(subject, expression, 1.0, yaw, pitch, roll, seed, occluder)
    return FaceScanner(cfg, identity=identity).scan(spec)


def random_frame(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of a random frame x -> R x + t: a uniformly random rotation and an offset of ~500 mm (σ per axis), as a
    scanner's or world frame places a face that its camera saw along +z."""
    from scipy.spatial.transform import Rotation

    return Rotation.random(random_state=seed).as_matrix(), np.random.default_rng(seed).normal(0.0, 500.0, 3)


def export_surface(scan: FaceScan, spacing_mm: float, *, mesh: bool = True, rotation: np.ndarray | None = None,
                   translation: np.ndarray | None = None) -> FaceScan:
    """A range scan as a mesh or point cloud file would hold it: no grid, vertices about `spacing_mm` apart (every
    k-th row and column of the range image, k from the scan's pitch), with the grid's triangles (`mesh`) or none,
    moved into another frame x -> R x + t (a scanner's or world frame), landmarks moved along."""
    step = max(1, int(round(spacing_mm / scan.resolution())))
    keep = (scan.grid[:, 0] % step == 0) & (scan.grid[:, 1] % step == 0)
    coarse = scan.subset(keep)
    coarse = coarse.replace(grid=coarse.grid // step, grid_shape=(-(-scan.grid_shape[0] // step),
                                                                   -(-scan.grid_shape[1] // step)))
    tris = coarse.triangles() if mesh else None
    out = coarse.replace(grid=None, grid_shape=None, normals=None, colors=None, mesh=tris)
    R = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
    t = np.zeros(3) if translation is None else np.asarray(translation, dtype=np.float64)
    return out.transformed(R, t)
