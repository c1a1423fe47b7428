"""Shaded depth renderings of scans for people to look at (`facerec3d view`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from facerec3d.scan import FaceScan


def shaded(scan: FaceScan, light=(0.3, 0.4, 1.0)) -> np.ndarray:
    """(H, W) Lambertian shading in [0, 1] of a grid scan (NaN where there is no data)."""
    xyz, valid = scan.to_range_image()
    dr = np.gradient(xyz, axis=0)
    dc = np.gradient(xyz, axis=1)
    n = np.cross(dc, dr)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n *= np.sign(n[..., 2:3])  # towards the viewer (+z)
    light = np.asarray(light, float) / np.linalg.norm(light)
    img = np.clip(n @ light, 0.0, 1.0)
    img[~valid] = np.nan
    return img


def _landmark_pixels(scan: FaceScan) -> dict[str, tuple[int, int]]:
    from scipy.spatial import cKDTree

    if not scan.landmarks:
        return {}
    tree = cKDTree(scan.points)
    return {k: tuple(scan.grid[tree.query(v)[1]]) for k, v in scan.landmarks.items()}


def check_image_path(path: str | Path) -> None:
    """InputError unless `path` names an image format matplotlib writes (by its suffix) in an existing folder."""
    from matplotlib.backend_bases import FigureCanvasBase

    from facerec3d.errors import InputError

    path = Path(path)
    formats = FigureCanvasBase.get_supported_filetypes()
    suffix = path.suffix.lower().lstrip(".")
    if suffix not in formats:
        raise InputError(f"{path}: cannot write a {suffix or 'suffix-less'} image (use .png, or one of "
                         f"{', '.join(sorted(formats))})")
    if not path.parent.is_dir():
        raise InputError(f"{path}: no such folder {path.parent}")


def render(panels: list[tuple[str, FaceScan]], path: str | Path) -> None:
    """Write a PNG with one shaded panel per (title, grid scan), landmarks marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 5), squeeze=False)
    for ax, (title, scan) in zip(axes[0], panels):
        img = shaded(scan)
        rows, cols = np.nonzero(np.isfinite(img))
        ax.imshow(img, cmap="gray", vmin=0, vmax=1)
        if len(rows):
            pad = 5
            ax.set_xlim(cols.min() - pad, cols.max() + pad)
            ax.set_ylim(rows.max() + pad, rows.min() - pad)
        for name, (r, c) in _landmark_pixels(scan).items():
            ax.plot(c, r, "r+", markersize=10, markeredgewidth=2)
        ax.set_title(title)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
