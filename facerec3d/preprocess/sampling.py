"""How a scan was sampled, measured from the scan itself: pixel pitch, depth quantisation and noise (mm).

Every threshold of preprocessing and matching that depends on the sensor is
a multiple of these measured values instead of a number fixed for one
scanner, so the same defaults hold from a 0.3 mm laser scan to a 3.5 mm
Kinect frame whose depth comes in 4–8 mm steps.

* pitch: the median distance between a point and its nearest grid neighbour
  (`FaceScan.resolution`), measured on the face once it is found;
* depth step: range images of consumer cameras store depth in integer units,
  often coarse ones (an 8-bit capture of a Kinect v2 keeps 4 or 8 mm steps).
  Neighbouring pixels on a smooth surface then have equal depth, or depths
  one step apart: when most neighbour differences are zero (within
  `ZERO_SHARE_OF_PITCH` of the pitch, so float round-off or a sub-micron
  jitter added on the way does not hide the steps) the step is the median of
  the others; else the depth is continuous (0);
* noise: for quantised depth the quantisation's σ = step/√12; else σ of depth noise from the second differences of depth along rows and
  columns (σ = 1.4826·MAD / √6 of z[i−1] − 2 z[i] + z[i+1], which a smooth
  surface sampled finely keeps near zero).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from numba import njit

from facerec3d.errors import FailureToAcquire
from facerec3d.scan import FaceScan


@dataclass(frozen=True)
class Sampling:
    """Measured sampling of a scan (mm)."""

    pitch_mm: float  # point spacing
    depth_step_mm: float  # depth quantisation step, 0 when depth is continuous
    noise_mm: float  # σ of the depth noise

    @property
    def surface_mm(self) -> float:
        """The finest depth detail the scan can show: the larger of the quantisation step and 2σ of noise (mm)."""
        return max(self.depth_step_mm, 2.0 * self.noise_mm)

    def to_dict(self) -> dict[str, float]:
        return {k: round(float(v), 4) for k, v in asdict(self).items()}


def _z_image(scan: FaceScan) -> np.ndarray:
    """The Z image of the scan's grid, NaN where no point is."""
    z = np.full(scan.grid_shape, np.nan)
    z[scan.grid[:, 0], scan.grid[:, 1]] = scan.points[:, 2]
    return z


ZERO_SHARE_OF_PITCH = 0.002  # neighbour depths closer than this × pitch count as equal (0.007 mm at a Kinect's
#                             3.5 mm, 0.0014 mm at a laser's 0.7 mm: far below any sensor's noise or step)


def depth_step(scan: FaceScan, min_zero_share: float = 0.3, pitch: float | None = None) -> float:
    """The depth quantisation step (mm) of a grid scan; 0 when depth is continuous (see the module docstring).
    `pitch`: the scan's resolution when already known."""
    if scan.grid is None or scan.n_points < 10:
        return 0.0
    d = _differences(_z_image(scan), 1)
    if len(d) < 10:
        return 0.0
    pitch = scan.resolution() if pitch is None else pitch
    d = d[d <= 3.0 * pitch + 1e-9] if np.isfinite(pitch) else d  # same surface, not across an edge
    zero = d <= max(1e-6, ZERO_SHARE_OF_PITCH * pitch if np.isfinite(pitch) else 0.0)
    if zero.mean() < min_zero_share or zero.all():
        return 0.0
    return float(np.median(d[~zero]))


def depth_noise(scan: FaceScan) -> float:
    """σ of depth noise (mm) from second differences along the grid's rows and columns (robust: MAD)."""
    if scan.grid is None or scan.n_points < 10:
        return 0.0
    second = _differences(_z_image(scan), 2)
    if len(second) < 10:
        return 0.0
    return float(1.4826 * np.median(np.abs(second - np.median(second)), overwrite_input=True) / np.sqrt(6.0))


@njit(cache=True)
def _differences(z, order):  # pragma: no cover - compiled
    """The finite differences of depth image z along its columns and rows, where both (order 1: |z[i+1] − z[i]|) or
    all three (order 2: z[i−1] − 2 z[i] + z[i+1]) pixels hold depth, in no particular order (their medians are
    taken): the values NumPy's diff and slicing give, without their full-size images."""
    rows, cols = z.shape
    out = np.empty(2 * rows * cols)
    n = 0
    for axis in range(2):
        dr, dc = (1, 0) if axis == 0 else (0, 1)
        for r in range(rows - order * dr):
            for c in range(cols - order * dc):
                if order == 1:
                    v = abs(z[r + dr, c + dc] - z[r, c])
                else:
                    v = z[r, c] - 2 * z[r + dr, c + dc] + z[r + 2 * dr, c + 2 * dc]
                if np.isfinite(v):
                    out[n] = v
                    n += 1
    return out[:n]


def measure_sampling(scan: FaceScan) -> Sampling:
    """Pitch, depth step and noise of a grid scan (mm), measured on its own points. Quantised depth has the
    quantisation's own noise, σ = step / √12 (what second differences see there is the steps)."""
    pitch = float(scan.resolution())
    step = depth_step(scan, pitch=pitch)
    noise = step / np.sqrt(12.0) if step > 0 else depth_noise(scan)
    return Sampling(pitch, step, float(noise))


def lateral_pitch(scan: FaceScan) -> float:
    """The typical x–y distance between neighbouring pixels (mm): `FaceScan.resolution` of the points flattened
    onto one plane, so that depth noise, which lengthens the 3D pitch, does not enter."""
    return scan.replace(points=np.c_[scan.points[:, :2], np.zeros(scan.n_points)]).resolution()


def check_surface(scan: FaceScan, sampling: Sampling, max_noise_pitches: float) -> None:
    """FailureToAcquire when the scan's pixels have no spacing across the view (every point at one x, y), or when
    its depth noise σ (`sampling.noise_mm`) exceeds `max_noise_pitches` lateral
    pixel pitches: random depths (a broken sensor, a corrupt frame) rather than a surface. No depth camera comes
    near it (its σ is about one pitch or less), but every threshold of preprocessing scales with the measured
    noise, so smoothing meant for such a frame can turn random depths into a face-like surface. 0 turns it off."""
    pitch = lateral_pitch(scan)
    if not (np.isfinite(pitch) and pitch > 0):
        raise FailureToAcquire(f"the {scan.n_points} points have no measurable spacing across the view (pixel pitch "
                               f"{pitch:.3g} mm)", scan.meta.path)
    if not max_noise_pitches > 0:
        return
    if sampling.noise_mm > max_noise_pitches * pitch:
        raise FailureToAcquire(f"no surface: the depth noise (σ {sampling.noise_mm:.3g} mm) is "
                               f"{sampling.noise_mm / pitch:.3g} pixel pitches ({pitch:.3g} mm), a surface's at most "
                               f"{max_noise_pitches:g}: random depths, not a camera's frame", scan.meta.path)
