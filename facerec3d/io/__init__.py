"""Reading and writing scans: `load_scan(path)` and `save_scan(scan, path)` dispatch on the file name.

| suffix | format | read | write |
|---|---|---|---|
| .abs, .abs.gz | FRGC v2 range image | yes | yes |
| .bnt (+ .lm3) | Bosphorus range image and landmarks | yes | yes |
| .ply | PLY mesh or point cloud, ASCII or binary (plyfile) | yes | yes |
| .obj, .off, .stl | meshes (trimesh) | yes | no |
| .xyz, .csv, .txt | text point clouds | yes | no |
| .npy | (H, W, 3) points or (H, W) depth, NaN = invalid | yes | no |
| .npz | `xyz` (H, W, 3) [+ `valid`], or `points` (N, 3); + landmarks | yes | yes |

Every reader raises `ScanFormatError` naming the file and the reason on bad input.
"""

from __future__ import annotations

from pathlib import Path

from facerec3d.errors import ScanFormatError
from facerec3d.io.arrays import read_npy, read_npz, write_npz
from facerec3d.io.meshes import read_mesh, read_ply, read_text_points, write_ply
from facerec3d.io.rangeformats import read_abs, read_bnt, read_lm3, write_abs, write_bnt, write_lm3
from facerec3d.scan import FaceScan

READERS = {
    ".abs": read_abs, ".abs.gz": read_abs, ".bnt": read_bnt, ".ply": read_ply, ".obj": read_mesh,
    ".off": read_mesh, ".stl": read_mesh, ".xyz": read_text_points, ".csv": read_text_points,
    ".txt": read_text_points, ".npy": read_npy, ".npz": read_npz,
}
WRITERS = {".abs": write_abs, ".abs.gz": write_abs, ".bnt": write_bnt, ".ply": write_ply, ".npz": write_npz}
SUPPORTED_SUFFIXES = tuple(READERS)


def scan_suffix(path: str | Path) -> str:
    """The format suffix of a file name (`.abs.gz` counts as one), lower case."""
    name = Path(path).name.lower()
    return ".abs.gz" if name.endswith(".abs.gz") else Path(name).suffix


def scan_stem(path: str | Path) -> str:
    """The file name without its format suffix."""
    name = Path(path).name
    return name[: len(name) - len(scan_suffix(path))]


def load_scan(path: str | Path) -> FaceScan:
    """Read a scan; its metadata records the path and the scan id (file stem)."""
    path = Path(path)
    reader = READERS.get(scan_suffix(path))
    if reader is None:
        raise ScanFormatError(path, f"unknown scan format (supported: {', '.join(SUPPORTED_SUFFIXES)})")
    if not path.is_file():
        raise ScanFormatError(path, "no such file")
    scan = reader(path)
    return scan.replace(meta=scan.meta.replace(path=str(path), scan_id=scan_stem(path)))


def save_scan(scan: FaceScan, path: str | Path) -> None:
    """Write a scan in the format its file name says (.abs, .abs.gz, .bnt, .ply, .npz)."""
    writer = WRITERS.get(scan_suffix(path))
    if writer is None:
        raise ValueError(f"{path}: cannot write this format (writable: {', '.join(WRITERS)})")
    writer(scan, path)


__all__ = ["load_scan", "save_scan", "read_lm3", "write_lm3", "SUPPORTED_SUFFIXES", "scan_suffix", "scan_stem"]
