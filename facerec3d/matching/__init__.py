"""Matching (chapter §8.6–8.10): the matcher interface and the methods.

* `base`: `Matcher` (fit, needs_training, options, state / set_state, save, enroll, prepare, score, scores,
  identify, verify), the `GalleryNormalised` mixin of matchers normalised over the gallery, `Template`, `rank`;
* `methods` / `registry`: the methods by name (`make_matcher`, `load_matcher`, `trained_matcher`);
* `icp` (§8.6), `subspace` (PCA §8.7, LDA §8.8), `curvature` (§8.9), `regions`, `keypoints` and `fusion`
  (§8.10), with `depthmap`, `expression`, `normalisation` and `checks` beside them.
"""

from facerec3d.matching.base import GalleryNormalised, Matcher, Template, rank
from facerec3d.matching.icp import GalleryIndex, ICPConfig, ICPMatcher, ICPResult, ProbeData, icp

__all__ = ["Matcher", "GalleryNormalised", "Template", "rank", "ICPConfig", "ICPMatcher", "ICPResult", "GalleryIndex",
           "ProbeData", "icp"]
