"""NumPy scans (`.npy`, `.npz`), read without pickle.

`.npy` holds one array:
- (H, W, 3) points in mm, NaN in any coordinate marking an invalid pixel;
- (H, W) depth map in mm with NaN invalid, read as x = column·1 mm, y = −row·1 mm, z = depth
  (W = 3 is taken as the next case);
- (N, 3) points in mm (rows with NaN dropped).
`.npz` holds `xyz` (H, W, 3) with optional `valid` (H, W) bool (else NaN marks
invalid pixels), or `points` (N, 3), and landmarks as (3,) arrays named
`landmark_<name>`, the scan's `meta.extra` (quality, frontal transform) as JSON text in
`meta_json`, and a grid scan's point provenance (seen, filled, mirrored) as an (H, W) uint8 image `provenance`. Either suffix reads either kind of file.
"""

from __future__ import annotations

from pathlib import Path

import json

import numpy as np

from facerec3d.errors import ScanFormatError
from facerec3d.io.common import MAX_POINTS, grid_scan, library_errors, point_scan
from facerec3d.scan import FaceScan

LANDMARK_PREFIX = "landmark_"
META_KEY = "meta_json"  # the scan's meta.extra (quality, frontal transform) as JSON text
PROVENANCE_KEY = "provenance"  # (H, W) uint8 image of a grid scan's FaceScan.provenance
MAX_MEMBER_BYTES = MAX_POINTS * 3 * 8 + 4096  # largest .npz member accepted (uncompressed)


def _from_array(path: str | Path, a: np.ndarray, valid: np.ndarray | None = None) -> FaceScan:
    """A scan from an (H, W, 3), (H, W) or (N, 3) array (see the module docstring)."""
    if a.dtype.kind not in "fiu":
        raise ScanFormatError(path, f"array of {a.dtype} is not numeric")
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == 2 and a.shape[1] != 3:  # a depth map
        rows, cols = np.indices(a.shape, dtype=np.float64)
        a = np.stack([cols, -rows, a], axis=-1)
    if a.ndim == 3 and a.shape[2] == 3:
        if valid is None:
            return grid_scan(path, a, ~np.isnan(a).any(axis=-1))
        if valid.shape != a.shape[:2] or valid.dtype.kind not in "biu":
            raise ScanFormatError(path, f"'valid' must be an {a.shape[:2]} boolean mask, not {valid.dtype} {valid.shape}")
        return grid_scan(path, a, valid.astype(bool))
    if a.ndim == 2:
        return point_scan(path, a[~np.isnan(a).any(axis=1)])
    raise ScanFormatError(path, f"array of shape {a.shape} is neither (H, W, 3), (H, W) nor (N, 3)")


def read_numpy(path: str | Path) -> FaceScan:
    """A scan from an `.npy` or `.npz` file (see the module docstring)."""
    with library_errors(path, "NumPy file"):
        with open(path, "rb") as f:
            magic = f.read(4)
        if not magic.startswith(b"PK"):  # not a zip: a single .npy array, memory-mapped until checked
            return _from_array(path, np.load(path, mmap_mode="r", allow_pickle=False))
        with np.load(path, allow_pickle=False) as z:
            for name in z.zip.namelist():
                if z.zip.getinfo(name).file_size > MAX_MEMBER_BYTES:
                    raise ScanFormatError(path, f"absurd size: member {name[:80]!r} is over {MAX_MEMBER_BYTES} bytes")
            key = "xyz" if "xyz" in z.files else "points" if "points" in z.files else None
            if key is None:
                raise ScanFormatError(path, "an .npz scan needs an 'xyz' or a 'points' array")
            scan = _from_array(path, z[key], z["valid"] if key == "xyz" and "valid" in z.files else None)
            landmarks = {k[len(LANDMARK_PREFIX) :]: z[k] for k in z.files if k.startswith(LANDMARK_PREFIX)}
            extra = _meta_extra(path, z[META_KEY]) if META_KEY in z.files else {}
            if PROVENANCE_KEY in z.files and scan.grid is not None:
                image = z[PROVENANCE_KEY]
                if image.shape != scan.grid_shape or image.dtype != np.uint8:
                    raise ScanFormatError(path, f"'{PROVENANCE_KEY}' must be a {scan.grid_shape} uint8 image")
                scan = scan.replace(provenance=image[scan.grid[:, 0], scan.grid[:, 1]])
    for name, v in landmarks.items():
        if v.shape != (3,) or v.dtype.kind not in "fiu" or not np.isfinite(v).all():
            raise ScanFormatError(path, f"landmark {name[:80]!r} is not a finite 3-vector")
    return scan.replace(landmarks=landmarks, meta=scan.meta.replace(extra=extra))


def _meta_extra(path: str | Path, value: np.ndarray) -> dict:
    """The scan's `meta.extra` from its JSON text member (quality, frontal transform); ScanFormatError if bad."""
    if value.dtype.kind != "U" or value.shape != ():
        raise ScanFormatError(path, f"'{META_KEY}' must be one JSON text")
    try:
        extra = json.loads(str(value))
    except json.JSONDecodeError as e:
        raise ScanFormatError(path, f"'{META_KEY}' is not valid JSON ({e.msg})") from None
    if not isinstance(extra, dict):
        raise ScanFormatError(path, f"'{META_KEY}' must hold a JSON object")
    return extra


def _jsonable(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON: {type(value).__name__}")


def write_npz(scan: FaceScan, path: str | Path) -> None:
    """Write a scan as compressed `.npz`: `xyz` + `valid` for a grid scan, else `points`; landmarks too (mm)."""
    arrays = {LANDMARK_PREFIX + name: v for name, v in scan.landmarks.items()}
    if scan.meta.extra:
        try:  # plain JSON, never pickle: a scan whose extra is not JSON-representable is written without it
            arrays[META_KEY] = np.array(json.dumps(scan.meta.extra, default=_jsonable))
        except (TypeError, ValueError):
            pass
    if scan.grid is not None:
        arrays["xyz"], arrays["valid"] = scan.to_range_image()
        if scan.provenance is not None:
            image = np.zeros(scan.grid_shape, np.uint8)
            image[scan.grid[:, 0], scan.grid[:, 1]] = scan.provenance
            arrays[PROVENANCE_KEY] = image
    else:
        arrays["points"] = scan.points
    with open(path, "wb") as f:  # a file object, so NumPy does not append '.npz' to the name
        np.savez_compressed(f, **arrays)
