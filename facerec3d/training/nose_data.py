"""Samples to train the nose proposer on (`preprocess.propose`, `training.nose`): height maps of the generator's
scans as the face detector sees them, and the augmentation of each batch. NumPy only: the tests and the sample
synthesis need no PyTorch."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy import ndimage

from facerec3d.datasets.synthetic import (EXPRESSIONS, OCCLUDERS, FaceScanner, ScanSpec, identity_profile,
                                          sensor_profile)
from facerec3d.errors import FaceRec3DError
from facerec3d.preprocess import PreprocessConfig, Preprocessor
from facerec3d.preprocess.propose import CELL_MM, STRIDE, HeightMap, height_map, proposer_input
from facerec3d.scan import FaceScan

if TYPE_CHECKING:
    from facerec3d.workers import Workers

CROP = 160  # stored samples: height-map crops this many cells wide (800 mm) around the nose
SENSORS = ("frgc", "kinect-v2", "kinect-v2-8bit", "realsense")
IDENTITIES = ("model", "outside-model")
FIRST_SUBJECT = 30000  # the samples' faces: subjects no test, benchmark or embedding training uses


def detector_view(scan: FaceScan, config: PreprocessConfig = PreprocessConfig()) -> tuple[FaceScan, bool]:
    """A raw scan as the face detector sees it (`Preprocessor.detector_view`) and whether orienting turned it."""
    seen, _, _, view = Preprocessor(config).detector_view(scan)
    return seen, bool(view.turned or view.roll_deg)


def sample_specs(n: int, seed: int) -> list[tuple[str, str, ScanSpec]]:
    """n (sensor, identity profile, scan) draws: any sensor profile, the model's faces and faces outside its span
    (with hands, glasses, fringes), half within ±40° of yaw, the rest up to ±90° (a sixth 55–90°), pitch ±30°,
    roll ±15°, any expression."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        sensor, ident = SENSORS[rng.integers(len(SENSORS))], IDENTITIES[rng.integers(len(IDENTITIES))]
        occ = None if ident == "model" else (None,) + OCCLUDERS
        occluder = None if occ is None else occ[rng.integers(len(occ))]
        u = rng.random()
        yaw = (rng.uniform(-40, 40) if u < 0.5 else rng.uniform(-90, 90) if u < 0.85
               else rng.choice([-1, 1]) * rng.uniform(55, 90))
        spec = ScanSpec(subject=FIRST_SUBJECT + seed * n + k, expression=(("neutral",) + EXPRESSIONS)[rng.integers(6)],
                        strength=float(rng.uniform(0.3, 1.0)), yaw=float(yaw), pitch=float(rng.uniform(-30, 30)),
                        roll=float(rng.uniform(-15, 15)), seed=int(rng.integers(1 << 30)), occluder=occluder)
        out.append((sensor, ident, spec))
    return out


def add_hair(z: np.ndarray, nose: np.ndarray, rng: np.random.Generator, cell_mm: float = CELL_MM) -> np.ndarray:
    """A volume of hair on a height map's head (the generator's heads are bald; real ones seldom are): the surface
    between `inner` and 160 mm from the nose tip and above `level` is raised towards the camera by up to 5–40 mm,
    and the head's outline there grown outwards by up to 40 mm."""
    rows, cols = np.mgrid[: z.shape[0], : z.shape[1]]
    dist = cell_mm * np.hypot(rows + 0.5 - nose[0], cols + 0.5 - nose[1])
    above = cell_mm * (nose[0] - rows - 0.5)
    inner, level = rng.uniform(70, 100), rng.uniform(-40, 10)
    zone = (dist < 160) & (dist > inner - 30) & (above > level)
    seen = np.isfinite(z)
    ramp = np.clip((dist - inner + 30) / 30, 0, 1)
    out = np.where(seen & zone, z + rng.uniform(5, 40) * ramp, z)
    grow = int(rng.integers(0, 9))
    if grow:
        filled = ndimage.grey_dilation(np.where(seen & zone, out, -np.inf), size=2 * grow + 1)
        new = ~seen & zone & np.isfinite(filled)
        out = np.where(new, filled - rng.uniform(0, 15, z.shape), out)
    return out


def augment(z: np.ndarray, nose: np.ndarray, rng: np.random.Generator, size: int,
            hair: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """One training crop (size × size cells) of a stored height map z (NaN = empty) and its nose (row, col)."""
    r, c = nose[:2]
    lo_r, hi_r = int(np.ceil(r)) - size + 8, int(np.floor(r)) - 8
    lo_c, hi_c = int(np.ceil(c)) - size + 8, int(np.floor(c)) - 8
    r0 = int(np.clip(rng.integers(lo_r, hi_r + 1), 0, z.shape[0] - size))
    c0 = int(np.clip(rng.integers(lo_c, hi_c + 1), 0, z.shape[1] - size))
    crop = z[r0:r0 + size, c0:c0 + size].astype(np.float64)
    rc = np.array([r - r0, c - c0])
    if rng.random() < 0.5:
        crop = crop[:, ::-1]
        rc[1] = size - rc[1]
    if rng.random() < hair:
        crop = add_hair(crop, rc, rng)
    seen = np.isfinite(crop)
    if seen.any():
        front = np.nanmax(crop)
        if rng.random() < 0.35:  # a wall behind the head
            crop = np.where(seen, crop, front - rng.uniform(250, 1000) + rng.normal(0, 5, crop.shape))
        crop = crop + rng.normal(0, rng.uniform(0, 1.5), crop.shape)
        if rng.random() < 0.5:  # cells lost
            crop[rng.random(crop.shape) < rng.uniform(0, 0.08)] = np.nan
    return proposer_input(HeightMap(crop, 0.0, 0.0, CELL_MM)), rc


def target(rc: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The loss's target over the output cells: a Gaussian of one output cell around the nose (row, col), sum 1."""
    rows = (np.arange(shape[0]) + 0.5) * STRIDE
    cols = (np.arange(shape[1]) + 0.5) * STRIDE
    g = np.exp(-((rows[:, None] - rc[0]) ** 2 + (cols[None, :] - rc[1]) ** 2) / (2 * STRIDE**2))
    return (g / g.sum()).astype(np.float32)


def make_samples(draws: list[tuple[str, str, ScanSpec]], config: PreprocessConfig = PreprocessConfig()
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Height-map crops (n, CROP, CROP) float16 (NaN = empty) of synthetic scans as the detector sees them, each
    with its nose tip's (row, col) in the crop, placed at random within its middle, and its z (mm); scans the
    orientation step turned are left out (the generator's never are)."""
    rng = np.random.default_rng([d[2].seed for d in draws[:1]] + [len(draws)])
    scanners: dict[tuple[str, str], FaceScanner] = {}
    maps, noses = [], []
    for sensor, ident, spec in draws:
        if (sensor, ident) not in scanners:
            scanners[sensor, ident] = FaceScanner(sensor_profile(sensor), identity=identity_profile(ident))
        syn = scanners[sensor, ident].scan(spec)
        try:
            scan, turned = detector_view(syn.scan, config)
        except FaceRec3DError:
            continue
        if turned:  # the truth is in the scan's frame
            continue
        hm = height_map(scan.points)
        rc = hm.cell_of(syn.landmarks["nose_tip"][:2])
        r0 = int(np.floor(rc[0])) - int(rng.integers(30, CROP - 30))
        c0 = int(np.floor(rc[1])) - int(rng.integers(30, CROP - 30))
        crop = np.full((CROP, CROP), np.nan, np.float32)
        h, w = hm.z.shape
        rs, re, cs, ce = max(r0, 0), min(r0 + CROP, h), max(c0, 0), min(c0 + CROP, w)
        crop[rs - r0:re - r0, cs - c0:ce - c0] = hm.z[rs:re, cs:ce]
        maps.append(crop.astype(np.float16))
        noses.append((rc[0] - r0, rc[1] - c0, syn.landmarks["nose_tip"][2]))
    return np.array(maps).reshape(-1, CROP, CROP), np.array(noses, np.float32).reshape(-1, 3)


def training_samples(n: int, seed: int, workers: "Workers", chunk: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """`make_samples` of n `sample_specs`, in chunks over the workers."""
    draws = sample_specs(n, seed)
    parts = workers.map(make_samples, [draws[i:i + chunk] for i in range(0, n, chunk)])
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
