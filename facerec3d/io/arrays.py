"""NumPy range images and point clouds (.npy, .npz), without pickle."""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path

import numpy as np

from facerec3d.errors import ScanFormatError
from facerec3d.io.rangeformats import _grid_scan
from facerec3d.scan import FaceScan

LANDMARK_PREFIX = "landmark_"


def _load(path: Path, loader):
    try:
        return loader(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error, KeyError) as e:
        raise ScanFormatError(path, f"not a readable NumPy file ({e})") from None


def _from_array(path: Path, a: np.ndarray, valid: np.ndarray | None = None) -> FaceScan:
    if a.dtype.kind not in "fiu":
        raise ScanFormatError(path, f"array of {a.dtype} is not numeric")
    a = a.astype(np.float64)
    if a.ndim == 2 and a.shape[1] != 3:  # a depth map: x = column, y = −row, 1 mm pixels
        rows, cols = np.mgrid[0 : a.shape[0], 0 : a.shape[1]]
        a = np.stack([cols.astype(float), -rows.astype(float), a], axis=-1)
    if a.ndim == 3 and a.shape[2] == 3:
        ok = np.isfinite(a).all(axis=-1) if valid is None else valid.astype(bool) & np.isfinite(a).all(axis=-1)
        if valid is not None and valid.shape != a.shape[:2]:
            raise ScanFormatError(path, f"valid mask {valid.shape} does not match image {a.shape[:2]}")
        return _grid_scan(path, a, ok)
    if a.ndim == 2 and a.shape[1] == 3:
        a = a[np.isfinite(a).all(axis=1)]
        if not len(a):
            raise ScanFormatError(path, "no valid points")
        return FaceScan(points=a)
    raise ScanFormatError(path, f"array of shape {a.shape} is neither (H, W, 3), (H, W) nor (N, 3)")


def read_npy(path: str | Path) -> FaceScan:
    """An (H, W, 3) point image or (H, W) depth map (NaN = invalid), or (N, 3) points."""
    path = Path(path)
    return _from_array(path, _load(path, np.load))


def read_npz(path: str | Path) -> FaceScan:
    """An .npz with `xyz` (H, W, 3) and optional `valid`, or `points` (N, 3); `landmark_<name>` arrays too."""
    path = Path(path)
    with _load(path, np.load) as z:
        try:
            if "xyz" in z:
                scan = _from_array(path, z["xyz"], z["valid"] if "valid" in z else None)
            elif "points" in z:
                scan = _from_array(path, z["points"])
            else:
                raise ScanFormatError(path, "an .npz scan needs an 'xyz' or a 'points' array")
            landmarks = {k[len(LANDMARK_PREFIX):]: z[k] for k in z.files if k.startswith(LANDMARK_PREFIX)}
        except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error) as e:
            raise ScanFormatError(path, f"corrupt .npz ({e})") from None
    if any(np.shape(v) != (3,) for v in landmarks.values()):
        raise ScanFormatError(path, "landmarks must be 3-vectors")
    return scan.replace(landmarks=landmarks)


def write_npz(scan: FaceScan, path: str | Path) -> None:
    """Write a scan as .npz: `xyz` + `valid` when it has a grid, else `points`; landmarks as `landmark_<name>`."""
    arrays = {LANDMARK_PREFIX + k: v for k, v in scan.landmarks.items()}
    if scan.grid is not None:
        arrays["xyz"], arrays["valid"] = scan.to_range_image()
    else:
        arrays["points"] = scan.points
    np.savez_compressed(path, **arrays)
