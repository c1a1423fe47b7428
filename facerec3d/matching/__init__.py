"""Matching (chapter §8.6–8.8): the matcher interface and ICP (§8.6)."""

from facerec3d.matching.base import Matcher, Template, rank
from facerec3d.matching.icp import GalleryIndex, ICPConfig, ICPMatcher, ICPResult, ProbeData, icp

__all__ = ["Matcher", "Template", "rank", "ICPConfig", "ICPMatcher", "ICPResult", "GalleryIndex", "ProbeData", "icp"]
