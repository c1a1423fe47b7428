"""Shared test fixtures: small synthetic range images and scans."""

import numpy as np
import pytest

from facerec3d import FaceScan


def cap_image(rows: int = 12, cols: int = 16, invalid=((0, 0), (5, 7), (11, 15))) -> FaceScan:
    """A sphere cap on a small grid (mm, camera frame, Z < 0) with a few invalid pixels."""
    r, c = np.mgrid[0:rows, 0:cols].astype(float)
    x, y = (c - cols / 2) * 2.0, (rows / 2 - r) * 2.0
    z = -1000.0 + np.sqrt(np.maximum(60.0**2 - x**2 - y**2, 0.0))
    xyz = np.stack([x, y, z], axis=-1) + np.random.default_rng(1).normal(0, 0.01, (rows, cols, 3))
    valid = np.ones((rows, cols), bool)
    for i, j in invalid:
        valid[i, j] = False
    return FaceScan.from_range_image(xyz, valid)


@pytest.fixture
def cap():
    return cap_image()
