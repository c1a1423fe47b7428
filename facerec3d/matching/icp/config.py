"""ICP settings (chapter §8.6.1)."""

from __future__ import annotations

from dataclasses import dataclass

VARIANTS = ("point-to-point", "point-to-plane")


@dataclass(frozen=True)
class ICPConfig:
    """ICP settings (chapter §8.6.1). Distances marked × res are multiples of the gallery's resolution
    (its median point spacing, ~1 mm for preprocessed faces)."""

    variant: str = "point-to-point"  # §8.6.1 (Besl & McKay); or "point-to-plane" (Chen & Medioni 1992; chapter 6)
    max_iterations: int = 40  # transform updates in all; §8.6.1 stops at convergence or an iteration cap
    tolerance: float = 1e-4  # mm²: converged when the MSE changes by less between iterations (§8.6.1)
    coarse_points: int = 300  # probe points of the coarse iterations (§8.6.1: coarse to fine)
    fine_points: int = 1000  # probe points of the fine iterations and of the score; 0 = all
    fine_iterations: int = 2  # at most this many updates in the fine phase
    distance_start: float = 10.0  # × res: initial pair distance threshold (§8.6.1: a multiple of the resolution)
    distance_end: float = 2.0  # × res: final threshold (§8.6.1: about the resolution; 2× keeps the pairs
    #                            of two differently sampled 1 mm scans with 0.3 mm noise)
    shrink_iterations: int = 10  # iterations over which the threshold falls geometrically to distance_end
    max_normal_angle: float | None = 45.0  # degrees between probe and gallery normals; None = off (§8.6.1)
    drop_boundary: bool = True  # reject pairs on gallery boundary points (§8.6.1)
    max_color_difference: float | None = None  # RGB distance (0–255); None = off; needs colours on both (§8.6.1)
    min_overlap: float = 0.1  # final pairs fewer than this share of the fine probe points: no match (MSE = inf)
    max_reach_mm: float = 30.0  # mm, enrolment: the voxel lookup reaches at most this far (or the final threshold),
    #                            so a coarse source (large res) does not blow up the template; faces arrive pre-aligned
    voxel_size: float = 2.0  # mm, enrolment: voxel lookup cell and x–y bucket (§8.6.1); ~0.4 MB per template
    normal_neighbours: int = 16  # k of the PCA normals (§8.6.1; geometry.normals)
    sensor_scale: float = 1.0  # res = max(point spacing, this × the source scan's pitch or depth step, whichever is
    #                            larger, as preprocessing measured them): a 1 mm grid resampled from 3.5 mm Kinect
    #                            pixels in 8 mm depth steps is not 1 mm data (§8.6.1: thresholds follow the resolution)
    score_cap: float | None = None  # × res: None = the score is −MSE of the kept pairs (§8.6.1); a value c = −mean over
    #                                 every fine probe point of min(d, c·res)², d its distance to the closest gallery
    #                                 point at the final transform (a truncated MSE: a probe point without a partner
    #                                 costs (c·res)², so a partial overlap no longer scores like a good fit)
    plane_cap_mm: float = 3.0  # mm: 0 = the score above; a value c = −mean over every fine probe point of
    #                                 min(e, cap)², e its distance to the tangent plane of its closest gallery point
    #                                 (along that point's normal; Chen & Medioni's error) at the final transform, and
    #                                 cap = the lesser of c and the final pair threshold (distance_end × res), also
    #                                 the cost of a point with no gallery point within that threshold: a truncated
    #                                 point-to-plane MSE, blind to where the two samplings fall along the surface
    probe_mirrored: bool = False  # points of the probe completed from its mirror image (`FaceScan.provenance`,
    #                               preprocess.symmetry) take part; False: the probe aligns only what its camera saw
    #                               (and hole filling interpolated) onto the gallery face, mirrored side included
    seed: int = 0  # random probe subsets

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown ICP variant {self.variant!r}: use one of {', '.join(VARIANTS)}")
        if not 0 < self.distance_end <= self.distance_start:
            raise ValueError("need 0 < distance_end <= distance_start")
        if self.score_cap is not None and not self.score_cap > 0:
            raise ValueError("score_cap must be positive (or None)")
        if not self.plane_cap_mm >= 0:
            raise ValueError("plane_cap_mm must be ≥ 0 (0: off)")
        if self.score_cap is not None and self.plane_cap_mm:
            raise ValueError("score_cap and plane_cap_mm each replace the score: set plane_cap_mm = 0 to use score_cap")
        if self.voxel_size <= 0 or self.coarse_points < 1 or self.fine_points < 0:
            raise ValueError("voxel_size and coarse_points must be positive, fine_points >= 0")
