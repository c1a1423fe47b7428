"""The single matching methods by name, each module imported only when its method is used.

The registry (`matching.registry`) adds "fusion", which combines these; fusion builds its members from here,
so no module imports one that leads back to it.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from typing import Any

from facerec3d.errors import SettingsError
from facerec3d.matching.base import Matcher

#: Method name → "module:class". Chapter sections: ICP §8.6, PCA §8.7, LDA §8.8, curvature §8.9,
#: regions and keypoints §8.10, the model-based afm (§8.10.1, §8.10.3) and morph-id (Blanz & Vetter), and the
#: learned embedding (an ONNX network trained on synthetic faces, run with onnxruntime).
METHODS: dict[str, str] = {
    "icp": "facerec3d.matching.icp:ICPMatcher",
    "pca": "facerec3d.matching.subspace:PCAMatcher",
    "lda": "facerec3d.matching.subspace:LDAMatcher",
    "curvature": "facerec3d.matching.curvature:CurvatureMatcher",
    "region-icp": "facerec3d.matching.regions:RegionICPMatcher",
    "keypoints": "facerec3d.matching.keypoints:KeypointMatcher",
    "afm": "facerec3d.matching.afm:AFMMatcher",
    "morph-id": "facerec3d.matching.morphable:MorphIDMatcher",
    "embedding": "facerec3d.matching.embedding:EmbeddingMatcher",
}


def method_class(method: str, table: Mapping[str, str] = METHODS) -> type[Matcher]:
    """The Matcher subclass of a method name in `table` (name → "module:class")."""
    if method not in table:
        raise SettingsError(None, None, f"unknown method {method!r}: use one of {', '.join(table)}")
    module, _, cls = table[method].partition(":")
    return getattr(importlib.import_module(module), cls)


def make_method(method: str, options: Mapping[str, Any] | None = None) -> Matcher:
    """A new matcher of a single method with these config fields changed (a method config's table)."""
    return method_class(method).from_options(options)
