"""facerec3d: 3D face recognition after Mian & Pears, "3D Face Recognition" (2012).

Package layout follows the chapter: `io` (scan formats), `facemodel` (the
ICT-FaceKit morphable model), `preprocess` (§8.5), `geometry` (normals,
curvature, rigid transforms; §8.9), `datasets` (FRGC v2, Bosphorus,
manifests, evaluation protocols, the synthetic generator), `matching` (ICP
§8.6, PCA §8.7, LDA §8.8, curvature §8.9, regions, keypoints and fusion
§8.10), `gallery` (store, engine, cascade; §8.6.2), `evaluation` (§8.4),
`server` and `client` (the gallery service); `workers` runs the work on
local processes or a Dask cluster.
"""

from facerec3d.jit import guard_kernel_caches

guard_kernel_caches()  # before any module defines a kernel (stale or damaged caches of compiled kernels)

from facerec3d.errors import FailureToAcquire, ScanFormatError  # noqa: E402
from facerec3d.scan import FaceScan, ScanMeta  # noqa: E402

__version__ = "0.1.0"

__all__ = ["FaceScan", "ScanMeta", "ScanFormatError", "FailureToAcquire", "__version__"]
