"""A learned nose proposer: where in a scan the nose tip is likely to be, in a few milliseconds (§8.5.1).

The face detector (`detect.detect_face`) verifies each nose candidate by rigid fits of the mean face from several
yaws and fits the full model to the best placements; on a Kinect frame that is ~47 rigid and 8 full fits, most of
preprocessing's time. A small fully convolutional network, trained on the generator's faces as the detector sees
them (every sensor profile, any pose, hands, glasses and fringes), reads an orthographic height map of the scan
and scores every cell as the nose tip; its few best peaks replace the hand-made candidates, so the detector
fits a handful of placements instead.

The input (`height_map`, `proposer_input`) is metric, not per sensor: the scan's points binned on the camera's
x-y plane in `cell_mm` cells, each cell the nearest surface (largest z; the camera looks along -z). Three
channels: the cells that hold data; each cell's height above its neighbourhood (a normalised Gaussian average over
`local_mm`), which is what tells a nose; and its depth behind the nearest part of the scan, which tells a head from
a wall. The network (trained with PyTorch by `facerec3d.training.nose`, run here with onnxruntime on one thread)
returns a score per 10 mm cell; `NoseProposer.propose` gives the points under its best distinct peaks.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from facerec3d.errors import FaceRec3DError
from facerec3d.models import onnx_session
from facerec3d.scan import column_bounds

CELL_MM = 5.0  # the height map's cell (mm): a nose tip ~6 cells wide
LOCAL_MM = 20.0  # σ of the neighbourhood a cell's height is measured against (mm)
MAX_CELLS = 256  # a height map is at most this many cells per side (1.28 m at 5 mm); larger scans are cut around the
#                 nearest surface


@dataclass(frozen=True)
class HeightMap:
    """Nearest surface per cell: z (H, W), NaN where the scan has nothing; cell (row, col) covers x from
    x0 + col·cell to x0 + (col + 1)·cell and y from y0 − row·cell down to y0 − (row + 1)·cell."""

    z: np.ndarray
    x0: float
    y0: float
    cell: float

    def cell_of(self, xy: np.ndarray) -> np.ndarray:
        """(row, col) of points (N, 2) or (2,), as floats (cell centres at .5)."""
        xy = np.asarray(xy, dtype=np.float64)
        return np.stack([(self.y0 - xy[..., 1]) / self.cell, (xy[..., 0] - self.x0) / self.cell], axis=-1)

    def centre(self, rc: np.ndarray) -> np.ndarray:
        """x, y of cell (row, col) centres (N, 2)."""
        rc = np.asarray(rc, dtype=np.float64)
        return np.stack([self.x0 + (rc[..., 1] + 0.5) * self.cell, self.y0 - (rc[..., 0] + 0.5) * self.cell], axis=-1)


def height_map(points: np.ndarray, cell_mm: float = CELL_MM, max_cells: int = MAX_CELLS) -> HeightMap:
    """The nearest surface (largest z) of points (N, 3) per `cell_mm` cell of the x-y plane (module docstring)."""
    p = np.asarray(points, dtype=np.float64)
    lo, hi = column_bounds(p[:, :2])
    span = np.floor((hi - lo) / cell_mm).astype(int) + 1
    if (span > max_cells).any():  # a wide frame: keep the max_cells square around the nearest surfaces
        near = p[p[:, 2] >= np.quantile(p[:, 2], 0.9), :2].mean(axis=0)
        half = max_cells * cell_mm / 2
        lo = np.maximum(lo, np.minimum(near - half, hi - 2 * half))
        hi = np.minimum(hi, lo + 2 * half - 1e-6)
        keep = (p[:, :2] >= lo).all(axis=1) & (p[:, :2] <= hi).all(axis=1)
        p = p[keep]
        span = np.minimum(np.floor((hi - lo) / cell_mm).astype(int) + 1, max_cells)
    cols = np.minimum(((p[:, 0] - lo[0]) / cell_mm).astype(np.int64), span[0] - 1)
    rows = np.minimum(((hi[1] - p[:, 1]) / cell_mm).astype(np.int64), span[1] - 1)
    z = np.full((span[1], span[0]), np.nan)
    order = np.argsort(p[:, 2], kind="stable")  # the last write to a cell is its nearest point
    z[rows[order], cols[order]] = p[order, 2]
    return HeightMap(z, float(lo[0]), float(hi[1]), float(cell_mm))


def proposer_input(hm: HeightMap, local_mm: float = LOCAL_MM) -> np.ndarray:
    """The network's input (3, H, W) float32: data mask, height above the neighbourhood / 10 mm (clipped to ±3),
    depth behind the scan's nearest part / 300 mm (clipped to [−2, 0]; −2 where nothing)."""
    seen = np.isfinite(hm.z)
    z = np.where(seen, hm.z, 0.0)
    s = local_mm / hm.cell
    weight = ndimage.gaussian_filter(seen.astype(np.float64), s, mode="constant")
    local = ndimage.gaussian_filter(z, s, mode="constant") / np.maximum(weight, 1e-6)
    height = np.where(seen, np.clip((z - local) / 10.0, -3.0, 3.0), 0.0)
    front = np.quantile(hm.z[seen], 0.99) if seen.any() else 0.0
    depth = np.where(seen, np.clip((z - front) / 300.0, -2.0, 0.0), -2.0)
    return np.stack([seen.astype(np.float64), height, depth]).astype(np.float32)


def peaks(score: np.ndarray, count: int, separation: int) -> np.ndarray:
    """(row, col) of up to `count` local maxima of a score map over separation × separation windows, best first."""
    top = np.isfinite(score) & (score == ndimage.maximum_filter(score, separation, mode="constant", cval=-np.inf))
    rows, cols = np.nonzero(top)
    order = np.argsort(-score[rows, cols], kind="stable")[:count]
    return np.stack([rows[order], cols[order]], axis=1)


SHIPPED_PROPOSER = Path(__file__).resolve().parent.parent / "models" / "nose.onnx"
STRIDE = 2  # input cells per output cell side


class NoseProposer:
    """The ONNX nose proposer, run with onnxruntime on one thread (the engine runs one process per core)."""

    def __init__(self, path: str | Path = SHIPPED_PROPOSER) -> None:
        self.path = Path(path)
        self._session: Any = None
        self._sha256: str | None = None

    @property
    def sha256(self) -> str:
        """The model file's SHA-256 (part of the preprocessing settings' fingerprint)."""
        if self._sha256 is None:
            try:
                self._sha256 = hashlib.sha256(self.path.read_bytes()).hexdigest()
            except OSError as e:
                raise FaceRec3DError(f"{self.path}: the nose proposer cannot be read ({e.strerror})") from None
        return self._sha256

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_session": None}

    @property
    def session(self) -> Any:
        if self._session is None:
            self._session = onnx_session(self.path, "nose proposer")
            shape = self._session.get_inputs()[0].shape
            if len(shape) != 4 or shape[1] != 3:  # another model (an embedding's): it would fail on every scan
                self._session = None
                raise FaceRec3DError(f"{self.path}: not a usable ONNX nose proposer (it takes input {shape[1:]}, a "
                                     "nose proposer a height map [3, H, W])")
        return self._session

    def scores(self, hm: HeightMap) -> np.ndarray:
        """The network's nose score per output cell (H / 2, W / 2) of a height map (padded to multiples of 8)."""
        x = proposer_input(hm)
        h, w = x.shape[1:]
        H, W = -(-h // 8) * 8, -(-w // 8) * 8
        pad = np.zeros((1, 3, H, W), np.float32)
        pad[0, 2] = -2.0  # what an empty cell reads
        pad[0, :, :h, :w] = x
        s = self.session
        out = s.run(None, {s.get_inputs()[0].name: pad})[0][0, 0]
        return out[: -(-h // STRIDE), : -(-w // STRIDE)]

    def propose(self, points: np.ndarray, count: int, separation_mm: float = 25.0) -> np.ndarray:
        """Indices of up to `count` points (N, 3) at the best distinct peaks of the nose score: under each peak's
        10 mm cell, the point nearest the camera (the first of equals); where the cell is empty, the point nearest
        it within two cells."""
        hm = height_map(points)
        score = self.scores(hm)
        sep = max(3, int(round(separation_mm / (hm.cell * STRIDE))) | 1)
        xy = hm.centre((peaks(score, count, sep) + 0.5) * STRIDE - 0.5)
        out: list[int] = []
        for c in xy:
            d = np.abs(points[:, :2] - c).max(axis=1)
            near = np.flatnonzero(d <= hm.cell * STRIDE / 2)
            if len(near):
                out.append(int(near[np.argmax(points[near, 2])]))
            elif d.min() <= 2 * hm.cell * STRIDE:  # a peak just off the data (a nose in profile): its nearest point
                out.append(int(np.argmin(d)))
        return np.array(out, dtype=np.int64)
