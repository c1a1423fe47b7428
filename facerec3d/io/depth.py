"""Depth frames from consumer depth cameras (Kinect, RealSense, phone depth): a 16-bit depth image and the
camera's pinhole intrinsics.

    load_scan("s000/front_1.png")                  # intrinsics.json found beside it or in a parent folder
    read_depth_image("f.png", Intrinsics.load("cam.json"))

Images: 16-bit PNG or TIFF (Pillow), or a 2-D `.npy` array, holding depth in
`depth_unit_mm` units (1 = millimetres; a RealSense `depth_scale` of 0.001 m
is 1 mm), `invalid` (default 0) where nothing was measured. Depth is the
Z-depth along the optical axis, as Kinect and RealSense deliver it. Pixel
(u, v) = (column, row) with depth d maps to

    X = (u − cx) · d / fx,   Y = −(v − cy) · d / fy,   Z = −d

which is FRGC's camera frame (X right, Y up, the camera looking along −Z), so a
depth frame and the equivalent `.abs` file give the same points.

`intrinsics.json` holds `fx, fy, cx, cy` (pixels) and optionally
`depth_unit_mm` (or `depth_scale_m`, metres per unit), `invalid`, `width`,
`height` (checked against the image when given), and `encoding`: "plain" (the
default: each pixel is depth) or "depth16", Android's `ImageFormat.DEPTH16`
(phones' time-of-flight cameras through Camera2): the 13 low bits of each
16-bit pixel are the range in mm, the 3 high bits its confidence (0: 100 %,
1: 0 %, k: (k − 1)/7), taken as Z-depth like any other frame's; pixels below
`min_confidence` (default 1/7: those the sensor gives no confidence) are left
out. It is looked for beside the
frame and in up to `INTRINSICS_SEARCH_DEPTH` parent folders, so a dataset with
one camera needs one file at its root.
"""

from __future__ import annotations

import difflib
import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from facerec3d.errors import ScanFormatError
from facerec3d.io.common import MAX_POINTS, grid_scan, library_errors, scan_suffix
from facerec3d.scan import FaceScan

INTRINSICS_NAME = "intrinsics.json"
INTRINSICS_SEARCH_DEPTH = 3  # parent folders searched for intrinsics.json, beyond the frame's own
ENCODINGS = ("plain", "depth16")  # how a pixel holds depth (`Intrinsics.encoding`)
MAX_INTRINSICS_BYTES = 65536  # an intrinsics.json read at most (a camera's are a few numbers; docs/security.md)
INTRINSICS_FIELDS = ("fx", "fy", "cx", "cy", "depth_unit_mm", "depth_scale_m", "invalid", "width", "height",
                     "encoding", "min_confidence")  # what `Intrinsics.from_dict` reads


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of a depth camera (pixels) and its depth encoding."""

    fx: float
    fy: float
    cx: float
    cy: float
    depth_unit_mm: float = 1.0  # mm per stored depth unit
    invalid: int = 0  # stored value meaning "no measurement"
    width: int | None = None  # image size the intrinsics belong to (checked when given)
    height: int | None = None
    encoding: str = "plain"  # "plain": a pixel is depth; "depth16": Android's DEPTH16 (range and confidence bits)
    min_confidence: float = 1 / 7  # depth16: pixels the sensor is less confident of are left out (0 %: none)

    def __post_init__(self) -> None:  # the values' checks, wherever they come from (from_dict names the file)
        for name in ("fx", "fy", "cx", "cy", "depth_unit_mm", "min_confidence"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"intrinsics: {name} must be a finite number, not {getattr(self, name)!r}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError("intrinsics: fx and fy must be positive")
        if self.depth_unit_mm <= 0:
            raise ValueError("intrinsics: the depth unit must be positive")

    @classmethod
    def from_dict(cls, data: dict, source: str | Path = "intrinsics") -> "Intrinsics":
        """Intrinsics from a JSON object; ScanFormatError naming `source` and the field when a value is wrong."""
        if not isinstance(data, dict):
            raise ScanFormatError(source, "intrinsics must be a JSON object with fx, fy, cx, cy")
        values = {}
        for name in ("fx", "fy", "cx", "cy"):
            if name not in data:
                raise ScanFormatError(source, f"intrinsics lack {name!r} (need fx, fy, cx, cy in pixels)")
            values[name] = _number(data[name], source, name)
        for name in set(data) - set(INTRINSICS_FIELDS):  # other fields (a sensor's name, notes) are the file's own;
            #                                                   a misspelt one of ours is not
            if near := difflib.get_close_matches(str(name), INTRINSICS_FIELDS, n=1, cutoff=0.85):
                raise ScanFormatError(source, f"intrinsics: unknown field {str(name)[:40]!r} (did you mean {near[0]!r}?)")
        if "depth_unit_mm" in data:
            values["depth_unit_mm"] = _number(data["depth_unit_mm"], source, "depth_unit_mm")
            if "depth_scale_m" in data and not math.isclose(
                    1000.0 * _number(data["depth_scale_m"], source, "depth_scale_m"), values["depth_unit_mm"]):
                raise ScanFormatError(source, "intrinsics: depth_unit_mm and depth_scale_m disagree (give one: the "
                                              "millimetres, or the metres, of one stored depth unit)")
        elif "depth_scale_m" in data:
            values["depth_unit_mm"] = 1000.0 * _number(data["depth_scale_m"], source, "depth_scale_m")
        if "invalid" in data:
            v = _number(data["invalid"], source, "invalid")
            if v != int(v):
                raise ScanFormatError(source, "intrinsics: 'invalid' must be an integer")
            values["invalid"] = int(v)
        for name in ("width", "height"):
            if data.get(name) is not None:
                v = _number(data[name], source, name)
                if v != int(v) or v <= 0:
                    raise ScanFormatError(source, f"intrinsics: {name!r} must be a positive integer")
                values[name] = int(v)
        if "encoding" in data:
            if data["encoding"] not in ENCODINGS:
                raise ScanFormatError(source, f"intrinsics: 'encoding' must be one of {', '.join(ENCODINGS)}")
            values["encoding"] = data["encoding"]
        if "min_confidence" in data:
            values["min_confidence"] = _number(data["min_confidence"], source, "min_confidence")
            if not 0.0 <= values["min_confidence"] <= 1.0:
                raise ScanFormatError(source, "intrinsics: 'min_confidence' must lie in [0, 1]")
        try:
            return cls(**values)
        except ValueError as e:  # (__post_init__'s checks of the values)
            raise ScanFormatError(source, str(e)) from None

    @classmethod
    def load(cls, path: str | Path) -> "Intrinsics":
        """Intrinsics from a JSON file of at most `MAX_INTRINSICS_BYTES`; ScanFormatError naming the file and the
        reason."""
        try:
            with open(path, "rb") as f:
                raw = f.read(MAX_INTRINSICS_BYTES + 1)
            text = raw.decode("utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise ScanFormatError(path, f"cannot read intrinsics ({type(e).__name__})") from None
        if len(raw) > MAX_INTRINSICS_BYTES:
            raise ScanFormatError(path, f"intrinsics file over {MAX_INTRINSICS_BYTES // 1024} KiB (a camera's "
                                        "intrinsics are a few numbers)")
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise ScanFormatError(path, f"intrinsics are not valid JSON (line {e.lineno}: {e.msg})") from None
        except (ValueError, RecursionError) as e:  # an integer of thousands of digits, nesting too deep
            raise ScanFormatError(path, f"intrinsics are not usable JSON ({type(e).__name__})") from None
        return cls.from_dict(data, path)

    def save(self, path: str | Path) -> None:
        at_default = lambda k, v: k in ("encoding", "min_confidence") and v == getattr(Intrinsics, k)  # left out
        Path(path).write_text(json.dumps({k: v for k, v in asdict(self).items()
                                          if v is not None and not at_default(k, v)}, indent=1))

    def pixel_pitch_mm(self, depth_mm: float) -> float:
        """Size of one pixel on a surface `depth_mm` away, facing the camera (mm)."""
        return depth_mm / math.sqrt(self.fx * self.fy)


def _float(value: int | float) -> float:
    """The value as a float; infinity for an integer too large for one."""
    try:
        return float(value)
    except OverflowError:
        return math.inf


def _number(value, source, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(_float(value)):
        raise ScanFormatError(source, f"intrinsics: {name!r} must be a finite number, not {value!r}"[:200])
    return float(value)


def find_intrinsics(frame: str | Path) -> Path | None:
    """The `intrinsics.json` beside a frame or in one of its parent folders (nearest first), or None."""
    folder = Path(frame).resolve().parent
    for _ in range(INTRINSICS_SEARCH_DEPTH + 1):
        candidate = folder / INTRINSICS_NAME
        if candidate.is_file():
            return candidate
        if folder.parent == folder:
            break
        folder = folder.parent
    return None


def frame_to_scan(depth_mm: np.ndarray, intrinsics: Intrinsics, path: str | Path = "depth", **fields) -> FaceScan:
    """A grid scan from an (H, W) Z-depth image in mm (NaN or ≤ 0 = no measurement) and pinhole intrinsics."""
    depth_mm = np.asarray(depth_mm, dtype=np.float64)
    rows, cols = depth_mm.shape
    if intrinsics.width is not None and intrinsics.width != cols or intrinsics.height is not None and intrinsics.height != rows:
        raise ScanFormatError(path, f"image is {rows}x{cols} (rows x columns) but the intrinsics are for "
                                    f"{intrinsics.height}x{intrinsics.width}")
    valid = np.isfinite(depth_mm) & (depth_mm > 0)
    d = np.where(valid, depth_mm, np.nan)
    v, u = np.indices(depth_mm.shape, dtype=np.float64)
    xyz = np.stack([(u - intrinsics.cx) * d / intrinsics.fx, -(v - intrinsics.cy) * d / intrinsics.fy, -d], axis=-1)
    return grid_scan(path, xyz, valid, **fields)


def scan_to_frame(scan: FaceScan, intrinsics: Intrinsics) -> np.ndarray:
    """(H, W) Z-depth image in mm (NaN = none) of a grid scan in a camera frame (the inverse of frame_to_scan)."""
    xyz, valid = scan.to_range_image()
    return np.where(valid, -xyz[..., 2], np.nan)


def _read_pixels(path: str | Path) -> np.ndarray:
    """The (H, W) array of stored depth units of a PNG, TIFF or .npy file, checked before decoding."""
    if scan_suffix(path) == ".npy":
        with library_errors(path, "NumPy depth image"):
            a = np.load(path, mmap_mode="r", allow_pickle=False)
        if not isinstance(a, np.ndarray):  # a .npz archive under a .npy name
            a.close()
            raise ScanFormatError(path, "an .npz archive, not one .npy array: a depth image must be one 2-D array")
    else:
        from PIL import Image

        with library_errors(path, "depth image"):
            with Image.open(path) as im:
                w, h = im.size
                if w * h > MAX_POINTS:
                    raise ScanFormatError(path, f"absurd size {h}x{w} for a depth frame (over {MAX_POINTS} pixels)")
                if im.mode not in ("I;16", "I;16B", "I;16L", "I", "L", "F"):
                    raise ScanFormatError(path, f"not a depth image: Pillow mode {im.mode} (need a grey depth "
                                                "image: 16-bit, 8-bit or float)")
                a = np.asarray(im)
    if a.ndim != 2:
        raise ScanFormatError(path, f"a depth image must be 2-D, not of shape {a.shape}")
    if a.size > MAX_POINTS:
        raise ScanFormatError(path, f"absurd size {a.shape[0]}x{a.shape[1]} for a depth frame")
    if a.dtype.kind not in "fiu":
        raise ScanFormatError(path, f"depth of type {a.dtype} is not numeric")
    return np.array(a)


def read_depth_image(path: str | Path, intrinsics: Intrinsics | str | Path | None = None) -> FaceScan:
    """A depth frame as a grid scan in the camera frame (mm). `intrinsics`: given, a JSON file, or found beside
    the frame (`find_intrinsics`); ScanFormatError when none is found or anything is wrong (a file that is not a
    depth image is said to be that first, whatever the intrinsics)."""
    units = _read_pixels(path)
    if intrinsics is None:
        found = find_intrinsics(path)
        if found is None:
            raise ScanFormatError(path, f"a depth image needs pinhole intrinsics: put an {INTRINSICS_NAME} "
                                        "(fx, fy, cx, cy in pixels) beside it or in a parent folder (info, "
                                        "preprocess, evaluate, enroll, identify and verify also take --intrinsics "
                                        "FILE)")
        intrinsics = found
    if not isinstance(intrinsics, Intrinsics):
        try:
            intrinsics = Intrinsics.load(intrinsics)
        except ScanFormatError as e:  # name the frame and the intrinsics file it was read with
            raise ScanFormatError(path, f"{intrinsics}: {e.reason}") from None
    if intrinsics.encoding == "depth16":
        units = depth16_range(units, intrinsics.min_confidence, path)
    depth = np.where(units == intrinsics.invalid, np.nan, units.astype(np.float64) * intrinsics.depth_unit_mm)
    scan = frame_to_scan(depth, intrinsics, path)
    extra = {"pixel_focal": math.sqrt(intrinsics.fx * intrinsics.fy), "depth_unit_mm": intrinsics.depth_unit_mm}
    return scan.replace(meta=scan.meta.replace(extra=extra))


def depth16_range(pixels: np.ndarray, min_confidence: float = 1 / 7, path: str | Path = "depth") -> np.ndarray:
    """The range (mm; 0 = none) of Android DEPTH16 pixels: their 13 low bits, 0 where the confidence in their 3 high
    bits (0: 100 %, 1: 0 %, k: (k − 1)/7) is below `min_confidence`."""
    if pixels.dtype.kind not in "iu" or pixels.size and (pixels.min() < 0 or pixels.max() > 0xFFFF):
        raise ScanFormatError(path, "a DEPTH16 frame holds 16-bit integers (encoding \"depth16\" in the intrinsics)")
    pixels = pixels.astype(np.uint16)
    code = pixels >> 13
    confidence = np.where(code == 0, 1.0, (code.astype(np.float64) - 1.0) / 7.0)
    return np.where(confidence >= min_confidence, pixels & 0x1FFF, 0).astype(np.uint16)


def write_depth_image(path: str | Path, depth_mm: np.ndarray, intrinsics: Intrinsics) -> None:
    """Write a Z-depth image (mm, NaN = none) as a 16-bit PNG or TIFF in the intrinsics' depth unit."""
    from PIL import Image

    depth_mm = np.asarray(depth_mm, dtype=np.float64)
    units = np.where(np.isfinite(depth_mm), np.round(depth_mm / intrinsics.depth_unit_mm), intrinsics.invalid)
    if (units < 0).any() or (units > 65535).any():
        raise ValueError(f"{path}: depth does not fit 16 bits at {intrinsics.depth_unit_mm} mm per unit")
    Image.fromarray(units.astype(np.uint16)).save(path)
