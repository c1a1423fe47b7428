"""The hidden side of a turned face, completed from its mirror image (Passalis et al., "Using facial symmetry to
handle pose variations in real-world 3D face recognition", TPAMI 2011).

A face turned 20–45° from the camera shows one side of its nose and cheek; after frontalisation the other side
is empty, and two faces turned different ways share only the middle of the face. A face is nearly mirror
symmetric, and the morphable model's fit puts its plane of symmetry at x = 0 of the frontal frame (the model is
symmetric and its nose tip is the origin), so the resampling grid's columns c and size − 1 − c are mirror images
(x → −x). `complete_by_symmetry` gives every cell that holds nothing, but whose mirror cell holds what the
camera saw (or hole filling interpolated), the mirror's depth, marked MIRRORED in the face's provenance so that
matchers can weigh it (`FaceScan.provenance`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facerec3d.preprocess.resample import ResampleConfig, grid_xy
from facerec3d.scan import MIRRORED, FaceScan

MODES = ("off", "mirror")


@dataclass(frozen=True)
class SymmetryConfig:
    """Completing a turned face from its mirror image (module docstring)."""

    mode: str = "off"  # "mirror": fill the cells of the unseen side from their mirror cells; "off": keep what was seen

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"unknown symmetry mode {self.mode!r}: use one of {', '.join(MODES)}")


def complete_by_symmetry(face: FaceScan, config: SymmetryConfig = SymmetryConfig(),
                         grid: ResampleConfig = ResampleConfig()) -> FaceScan:
    """The resampled frontal face with its empty cells filled from their mirror cells (x → −x; module docstring)."""
    if config.mode == "off" or face.n_points == 0:
        return face
    n = grid.size
    if face.grid_shape != (n, n):
        raise ValueError(f"symmetry completion needs the {n}×{n} resampling grid, not {face.grid_shape}")
    xyz, valid = face.to_range_image()
    prov = np.zeros(face.n_points, np.uint8) if face.provenance is None else face.provenance
    source = np.zeros((n, n), bool)
    source[face.grid[:, 0], face.grid[:, 1]] = prov != MIRRORED
    wanted = ~valid & source[:, ::-1]
    rows, cols = np.nonzero(wanted)
    X, Y = grid_xy(grid)
    added = np.stack([X[rows, cols], Y[rows, cols], xyz[rows, n - 1 - cols, 2]], axis=1)
    return face.replace(points=np.concatenate([face.points, added]),
                        grid=np.concatenate([face.grid, np.stack([rows, cols], axis=1)]),
                        normals=None, colors=None,
                        provenance=np.concatenate([prov, np.full(len(added), MIRRORED, np.uint8)]))
