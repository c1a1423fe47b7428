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

import json
import math
import zipfile
from pathlib import Path

import numpy as np

from facerec3d.errors import ScanFormatError
from facerec3d.io.common import MAX_POINTS, grid_scan, library_errors, point_scan
from facerec3d.scan import FaceScan

LANDMARK_PREFIX = "landmark_"
META_KEY = "meta_json"  # the scan's meta.extra (quality, frontal transform) as JSON text
PROVENANCE_KEY = "provenance"  # (H, W) uint8 image of a grid scan's FaceScan.provenance
MAX_MEMBERS = 256  # members of an .npz (the scan, its mask, its meta and landmarks)
MAX_META_CHARS = 1 << 20  # characters of the meta_json text
MAX_ITEM_BYTES = 8  # bytes per value: float64 is the widest numeric type read
NPY_MAGIC = b"\x93NUMPY"  # the start of an .npy file (an .npz is a zip archive of them: "PK")


def _points(path: str | Path, shape: tuple[int, ...]) -> int:
    """The points an (H, W, 3), (H, W) or (N, 3) array would make, from its shape alone."""
    if len(shape) == 3 and shape[2] == 3:
        return shape[0] * shape[1]
    if len(shape) == 2:
        return shape[0] if shape[1] == 3 else shape[0] * shape[1]
    raise ScanFormatError(path, f"array of shape {shape} is neither (H, W, 3), (H, W) nor (N, 3)")


def _check_array(path: str | Path, what: str, shape: tuple[int, ...], dtype: np.dtype) -> None:
    """Refuse, from its header alone (before anything is read or converted), a scan array that is not numeric
    or would hold more than MAX_POINTS points."""
    if dtype.kind not in "fiub" or dtype.itemsize > MAX_ITEM_BYTES:
        raise ScanFormatError(path, f"{what}: array of {dtype} is not numeric")
    n = _points(path, shape) if what != "valid" else math.prod(shape)
    if n > MAX_POINTS:
        raise ScanFormatError(path, f"absurd size: {what} array of shape {shape} has {n} points "
                                    f"(more than {MAX_POINTS})")


def _from_array(path: str | Path, a: np.ndarray, valid: np.ndarray | None = None) -> FaceScan:
    """A scan from an (H, W, 3), (H, W) or (N, 3) array (see the module docstring), its size checked first."""
    _check_array(path, "the scan", a.shape, a.dtype)
    if a.dtype.kind == "b":
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
    return point_scan(path, a[~np.isnan(a).any(axis=1)])


def _npy_header(path: str | Path, f, where: str = "") -> tuple[tuple[int, ...], np.dtype]:
    """(shape, dtype) from the .npy header that `f` starts with, read without the data; an array of Python
    objects (stored pickled) is refused here, before NumPy is asked to load it. `where` prefixes messages."""
    version = np.lib.format.read_magic(f)
    read_header = {(1, 0): np.lib.format.read_array_header_1_0,
                   (2, 0): np.lib.format.read_array_header_2_0}.get(version)
    if read_header is None:
        raise ScanFormatError(path, f"{where}unsupported .npy version {version}")
    shape, _, dtype = read_header(f)
    if dtype.hasobject:
        raise ScanFormatError(path, f"{where}holds pickled Python objects, which are refused for safety")
    return shape, dtype


def _member_header(path: str | Path, z: zipfile.ZipFile, member: str) -> tuple[tuple[int, ...], np.dtype]:
    """(shape, dtype) of an .npz member from its .npy header, read without inflating the data."""
    with z.open(member) as f:
        return _npy_header(path, f, f"member {member[:80]!r}: ")


def read_numpy(path: str | Path) -> FaceScan:
    """A scan from an `.npy` or `.npz` file (see the module docstring). Every array's size and type are checked
    from its header before it is read, so no file (whatever it claims) takes more memory than the largest scan
    accepted (MAX_POINTS points)."""
    with library_errors(path, "NumPy file"):
        with open(path, "rb") as f:
            magic = f.read(len(NPY_MAGIC))
            if magic == NPY_MAGIC:  # a single .npy array, memory-mapped until checked
                f.seek(0)
                _npy_header(path, f)
        if magic == NPY_MAGIC:
            return _from_array(path, np.load(path, mmap_mode="r", allow_pickle=False))
        if not magic.startswith(b"PK"):  # NumPy would take it for a pickle, and name an option to load it unsafely
            raise ScanFormatError(path, "not a NumPy file: neither an .npy array nor an .npz archive")
        with np.load(path, allow_pickle=False) as z:
            members = z.zip.namelist()
            if len(members) > MAX_MEMBERS:
                raise ScanFormatError(path, f"absurd .npz: {len(members)} members (more than {MAX_MEMBERS})")
            headers = {m[:-4] if m.endswith(".npy") else m: _member_header(path, z.zip, m) for m in members}
            key = "xyz" if "xyz" in headers else "points" if "points" in headers else None
            if key is None:
                raise ScanFormatError(path, "an .npz scan needs an 'xyz' or a 'points' array")
            _check_array(path, key, *headers[key])
            mask = key == "xyz" and "valid" in headers
            if mask:
                _check_array(path, "valid", *headers["valid"])
            names = [k for k in headers if k.startswith(LANDMARK_PREFIX)]
            for name in names:
                shape, dtype = headers[name]
                if shape != (3,) or dtype.kind not in "fiu" or dtype.itemsize > MAX_ITEM_BYTES:
                    raise ScanFormatError(path, f"landmark {name[len(LANDMARK_PREFIX):][:80]!r} is not a finite "
                                                "3-vector")
            if META_KEY in headers:
                shape, dtype = headers[META_KEY]
                if dtype.kind != "U" or shape != () or dtype.itemsize > 4 * MAX_META_CHARS:
                    raise ScanFormatError(path, f"'{META_KEY}' must be one JSON text of at most {MAX_META_CHARS} "
                                                "characters")
            scan = _from_array(path, z[key], z["valid"] if mask else None)
            landmarks = {k[len(LANDMARK_PREFIX) :]: z[k] for k in names}
            extra = _meta_extra(path, z[META_KEY]) if META_KEY in headers else {}
            if PROVENANCE_KEY in headers and scan.grid is not None:
                if headers[PROVENANCE_KEY] != (scan.grid_shape, np.dtype(np.uint8)):
                    raise ScanFormatError(path, f"'{PROVENANCE_KEY}' must be a {scan.grid_shape} uint8 image")
                scan = scan.replace(provenance=z[PROVENANCE_KEY][scan.grid[:, 0], scan.grid[:, 1]])
    for name, v in landmarks.items():
        if not np.isfinite(v).all():
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
