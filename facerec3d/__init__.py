"""facerec3d: 3D face recognition after Mian & Pears, "3D Face Recognition" (2012).

Package layout follows the chapter: `io` (scan formats), `datasets` (FRGC v2,
Bosphorus, manifests, the synthetic generator), `preprocess` (§8.5),
`geometry` (normals, curvature, rigid transforms; §8.9), `matching`
(ICP §8.6, PCA §8.7, LDA §8.8), `evaluation` (§8.4).
"""

from facerec3d.errors import FailureToAcquire, ScanFormatError
from facerec3d.scan import FaceScan, ScanMeta

__version__ = "0.1.0"

__all__ = ["FaceScan", "ScanMeta", "ScanFormatError", "FailureToAcquire", "__version__"]
