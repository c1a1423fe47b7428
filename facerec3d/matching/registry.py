"""Matching methods by name (`facerec3d evaluate --method NAME`), built with options, saved and loaded.

    matcher = make_matcher("icp", {"variant": "point-to-plane"})
    matcher.save("model.npz"); same = load_matcher("model.npz")

Each method's module is imported only when the method is used.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from os import PathLike
from typing import Any

from facerec3d.errors import FaceRec3DError
from facerec3d.matching.base import Matcher, Template

#: Method name → "module:class". Chapter sections: ICP §8.6, PCA §8.7, LDA §8.8, curvature §8.9,
#: regions, keypoints and fusion §8.10.
METHODS: dict[str, str] = {
    "icp": "facerec3d.matching.icp:ICPMatcher",
    "pca": "facerec3d.matching.subspace:PCAMatcher",
    "lda": "facerec3d.matching.subspace:LDAMatcher",
    "curvature": "facerec3d.matching.curvature:CurvatureMatcher",
    "region-icp": "facerec3d.matching.regions:RegionICPMatcher",
    "keypoints": "facerec3d.matching.keypoints:KeypointMatcher",
    "fusion": "facerec3d.matching.fusion:FusionMatcher",
}


def matcher_class(method: str) -> type[Matcher]:
    """The Matcher subclass of a method name."""
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}: use one of {', '.join(METHODS)}")
    module, _, cls = METHODS[method].partition(":")
    return getattr(importlib.import_module(module), cls)


def make_matcher(method: str, options: Mapping[str, Any] | None = None) -> Matcher:
    """A new matcher of this method with these config fields changed (a method config's table)."""
    return matcher_class(method).from_options(options)


def load_matcher(path: str | PathLike) -> Matcher:
    """A matcher saved by `Matcher.save`: its method, settings and what it learnt."""
    try:
        t = Template.load(path)
        options, state = t.attrs["options"], t.attrs["state"]
    except (OSError, ValueError, KeyError) as e:
        raise FaceRec3DError(f"{path}: not a facerec3d model file ({e})") from None
    matcher = make_matcher(t.method, options)
    matcher.set_state(t.arrays, state)
    return matcher
