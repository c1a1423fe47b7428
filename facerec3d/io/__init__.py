"""Reading and writing scans: `load_scan(path)` and `save_scan(scan, path)` dispatch on the file name.

| suffix (any case) | format | read | write |
|---|---|---|---|
| .abs, .abs.gz | FRGC v2 range image (`abs`) | yes | yes |
| .bnt (+ .lm3) | Bosphorus range image and landmarks (`bnt`) | yes | yes |
| .ply | PLY mesh or point cloud, ASCII or binary, plyfile (`mesh`) | yes | yes |
| .obj | meshes and point clouds, Wavefront OBJ (`mesh`) | yes | yes |
| .off, .stl | meshes and point clouds, trimesh (`mesh`) | yes | no |
| .xyz, .csv, .txt | text point clouds (`text`) | yes | no |
| .npy, .npz | NumPy range images, depth maps, point sets (`arrays`) | yes | .npz |
| .png, .tif, .tiff (+ intrinsics.json) | 16-bit depth frames of depth cameras (`depth`) | yes | no (`write_depth_image`) |

A 2-D `.npy` depth array with an `intrinsics.json` beside it (or given) is read
as a depth frame too.

All coordinates are in mm. Every reader raises `ScanFormatError` naming the
file and the reason on bad input (truncated, corrupt, mis-sized, non-numeric,
empty, no valid points, absurdly large, non-finite), never another exception.
"""

from __future__ import annotations

from pathlib import Path

from facerec3d.errors import ScanFormatError
from facerec3d.io.abs import read_abs, write_abs
from facerec3d.io.arrays import read_numpy, write_npz
from facerec3d.io.depth import Intrinsics, find_intrinsics, read_depth_image, write_depth_image
from facerec3d.io.bnt import load_landmarks_lm3, read_bnt, write_bnt, write_lm3
from facerec3d.io.common import scan_stem, scan_suffix
from facerec3d.io.mesh import read_mesh, read_obj, read_ply, write_obj, write_ply
from facerec3d.io.text import read_text_points
from facerec3d.scan import FaceScan

READERS = {
    ".abs": read_abs, ".abs.gz": read_abs, ".bnt": read_bnt, ".ply": read_ply,
    ".obj": read_obj, ".off": read_mesh, ".stl": read_mesh,
    ".xyz": read_text_points, ".csv": read_text_points, ".txt": read_text_points,
    ".npy": read_numpy, ".npz": read_numpy, ".png": read_depth_image, ".tif": read_depth_image,
    ".tiff": read_depth_image,
}
DEPTH_SUFFIXES = (".png", ".tif", ".tiff")
WRITERS = {".abs": write_abs, ".abs.gz": write_abs, ".bnt": write_bnt, ".ply": write_ply, ".obj": write_obj, ".npz": write_npz}
SUPPORTED_SUFFIXES = tuple(READERS)


def unique_stems(paths) -> list[str]:
    """A distinct output name for each path: its `scan_stem`; when files in different folders share a stem, every
    name is prefixed with the file's folder, which is usually the person (`s000/front_1.png`, `s000/front_2.png`,
    `s001/front_1.png` give `s000_front_1`, `s000_front_2`, `s001_front_1`); and `name-2`, `name-3`, ... where an
    earlier path (or another path's name) still has it, so that no output overwrites another (compared without
    case, as some file systems do)."""
    bare = [scan_stem(p) for p in paths]
    folders: dict[str, set[str]] = {}
    for p, stem in zip(paths, bare):
        folders.setdefault(stem.lower(), set()).add(str(Path(p).resolve().parent))
    by_folder = any(len(f) > 1 for f in folders.values())
    stems = [f"{folder}_{stem}" if by_folder and (folder := Path(p).resolve().parent.name) else stem
             for p, stem in zip(paths, bare)]
    own, used, out = {s.lower() for s in stems}, set(), []
    for stem in stems:
        name, k = stem, 1
        while name.lower() in used or name != stem and name.lower() in own:
            k += 1
            name = f"{stem}-{k}"
        used.add(name.lower())
        out.append(name)
    return out


def load_scan(path: str | Path, intrinsics: "Intrinsics | str | Path | None" = None) -> FaceScan:
    """Read a scan; `meta.path` is str(path) and `meta.scan_id` the file stem. ScanFormatError on any bad file.

    `intrinsics` (an `Intrinsics` or a JSON file) are for depth frames; without them a frame's
    `intrinsics.json` is looked for beside it and in its parent folders.
    """
    suffix = scan_suffix(path)
    reader = READERS.get(suffix)
    if reader is None:
        raise ScanFormatError(path, f"unknown scan format (supported: {', '.join(SUPPORTED_SUFFIXES)})")
    if not Path(path).is_file():
        raise ScanFormatError(path, "no such file" if not Path(path).exists() else "not a regular file")
    if suffix in DEPTH_SUFFIXES or suffix == ".npy" and _is_depth_npy(path, intrinsics):
        scan = read_depth_image(path, intrinsics)
    else:
        scan = reader(path)
    return scan.replace(meta=scan.meta.replace(path=str(path), scan_id=scan_stem(path)))


def _is_depth_npy(path: str | Path, intrinsics) -> bool:
    """A 2-D `.npy` array that is not an (N, 3) point set, with intrinsics given or found: a depth frame."""
    if intrinsics is None and find_intrinsics(path) is None:
        return False
    try:
        import numpy as np

        a = np.load(path, mmap_mode="r", allow_pickle=False)
    except Exception:  # let the reader say what is wrong
        return False
    if not isinstance(a, np.ndarray):  # an .npz archive named .npy: not a depth frame, the reader says what it is
        a.close()
        return False
    return a.ndim == 2 and a.shape[1] != 3


def save_scan(scan: FaceScan, path: str | Path) -> None:
    """Write a scan in the format its file name says (.abs, .abs.gz, .bnt, .ply binary, .obj, .npz)."""
    writer = WRITERS.get(scan_suffix(path))
    if writer is None:
        raise ScanFormatError(path, f"cannot write this format (writable: {', '.join(WRITERS)})")
    writer(scan, path)


__all__ = [
    "SUPPORTED_SUFFIXES", "load_scan", "save_scan", "load_landmarks_lm3", "scan_stem", "scan_suffix", "unique_stems",
    "read_abs", "write_abs", "read_bnt", "write_bnt", "write_lm3", "read_ply", "write_ply", "read_obj", "read_mesh",
    "DEPTH_SUFFIXES", "read_text_points", "read_numpy", "write_npz", "Intrinsics", "find_intrinsics", "read_depth_image",
    "write_depth_image",
]
