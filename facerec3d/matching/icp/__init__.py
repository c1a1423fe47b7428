"""ICP matching (chapter §8.6.1): rigidly align a probe face to a gallery face; the score is −MSE.

* `config`: the settings (`ICPConfig`);
* `index`: the gallery side, built once per face at enrolment (`GalleryIndex`: voxel lookup, x–y buckets,
  normals, boundary) and its compiled closest-point query;
* `align`: the probe side (`ProbeData`), the ICP loop step by step, `icp()` and the matcher (`ICPMatcher`).
"""

from facerec3d.matching.icp.align import ICPMatcher, ICPResult, ProbeData, icp
from facerec3d.matching.icp.config import VARIANTS, ICPConfig
from facerec3d.matching.icp.index import GalleryIndex, matching_resolution

__all__ = ["ICPConfig", "VARIANTS", "GalleryIndex", "matching_resolution", "ProbeData", "ICPResult", "ICPMatcher",
           "icp"]
