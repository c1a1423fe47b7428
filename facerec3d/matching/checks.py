"""Checks of a template read back from storage, before any compiled (Numba) kernel touches it.

Compiled code does no bounds checking: an ICP template whose index arrays point outside its points would read
or write arbitrary memory. `check_template` verifies every array's dtype and shape and every index's bounds,
so a damaged or forged template raises ValueError (with the reason) instead of crashing the process.
Methods that use only NumPy need no check here: they raise on arrays of the wrong shape themselves.
"""

from __future__ import annotations

import math

import numpy as np

from facerec3d.matching.base import Template


def check_template(template: Template) -> None:
    """Raise ValueError naming what is wrong when a template's arrays could make a compiled kernel misbehave."""
    if template.method in ("icp", "region-icp"):
        _check_icp_index(template)
    elif template.method == "fusion":
        from facerec3d.matching.fusion import unpack

        try:
            parts = unpack(template)
        except (KeyError, TypeError, ValueError, IndexError) as e:
            raise ValueError(f"fusion template does not unpack ({type(e).__name__}: {e})") from None
        for part in parts:
            check_template(part)


def _array(arrays: dict, name: str, dtypes: tuple[str, ...], shape: tuple) -> np.ndarray:
    """The array `name`, of one of `dtypes` and `shape` (None: any length)."""
    a = arrays.get(name)
    if a is None:
        raise ValueError(f"no array {name!r}")
    if a.dtype.name not in dtypes:
        raise ValueError(f"array {name!r} is {a.dtype.name}, not {' or '.join(dtypes)}")
    if a.ndim != len(shape) or any(want is not None and got != want for got, want in zip(a.shape, shape)):
        raise ValueError(f"array {name!r} has shape {a.shape}, not {tuple('N' if s is None else s for s in shape)}")
    return a


def _offsets(name: str, a: np.ndarray, end: int) -> None:
    """Offsets into another array: start at 0, never decrease, end at `end`."""
    if a[0] != 0 or a[-1] != end or (np.diff(a.astype(np.int64)) < 0).any():
        raise ValueError(f"array {name!r} is not a run of offsets from 0 to {end}")


def _check_icp_index(t: Template) -> None:
    """The invariants of matching.icp.GalleryIndex that its compiled search relies on."""
    a, s = t.arrays, t.attrs
    integers = {k: s.get(k) for k in ("nx", "ny", "nz")}
    if not all(isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 2**31 for v in integers.values()):
        raise ValueError(f"bad voxel grid size {integers}")
    reals = {k: s.get(k) for k in ("voxel_size", "resolution", "margin")}
    if not all(isinstance(v, (int, float)) and math.isfinite(v) and v > 0 for v in reals.values()):
        raise ValueError(f"bad voxel size, resolution or margin {reals}")
    origin = s.get("origin")
    if not (isinstance(origin, list) and len(origin) == 3 and all(isinstance(v, (int, float)) and math.isfinite(v)
                                                                  for v in origin)):
        raise ValueError(f"bad origin {origin!r}"[:200])
    points = _array(a, "points", ("float32",), (None, 3))
    n = len(points)
    if n < 3 or not np.isfinite(points).all():
        raise ValueError("the points must be at least 3, all finite")
    _array(a, "normals", ("int8",), (n, 3))
    _array(a, "boundary", ("bool",), (n,))
    colors = _array(a, "colors", ("uint8",), (None, 3))
    if len(colors) not in (0, n):
        raise ValueError(f"array 'colors' has {len(colors)} rows for {n} points (need 0 or {n})")
    columns = integers["nx"] * integers["ny"]
    _array(a, "voxel_first", ("int16",), (columns,))
    offset = _array(a, "voxel_offset", ("int32",), (columns + 1,))
    index = _array(a, "voxel_index", ("uint16", "int32"), (None,))
    _offsets("voxel_offset", offset, len(index))
    if index.dtype == np.int32 and len(index) and index.min() < 0:  # >= n means "no point"; < 0 is out of bounds
        raise ValueError("array 'voxel_index' holds negative indices")
    _offsets("bucket_start", _array(a, "bucket_start", ("int32",), (columns + 1,)), n)
