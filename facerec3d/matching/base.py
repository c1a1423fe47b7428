"""The matcher interface shared by ICP (§8.6), PCA (§8.7), LDA (§8.8) and curvature matchers.

Scikit-learn-like and small:

    matcher.fit(training_scans, subjects)          # learnt matchers only
    matcher.save("model.npz"); load_matcher("model.npz")   # settings + what fit learnt (registry)
    gallery = [matcher.enroll(scan) for scan in gallery_scans]
    probe = matcher.prepare(scan)                  # optional: done by score() when given a FaceScan
    matcher.identify(probe, gallery, k=5)          # [(gallery index, score), ...] best first
    matcher.verify(probe, gallery[i], threshold)   # score >= threshold

Scores are similarities: higher means more alike (ICP gives −MSE in mm²).
A `Template` is what a matcher keeps of a scan; it saves to .npz without
pickle.
"""

from __future__ import annotations

import json
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, is_dataclass
from os import PathLike
from typing import Any

import numpy as np

from facerec3d.config import from_dict
from facerec3d.scan import FaceScan

#: Relative score difference under which two scores count as tied (then the tiebreak decides).
TIE_TOLERANCE = 1e-9

_META_KEY = "__template__"
_RESERVED = (_META_KEY, "file", "allow_pickle")  # np.savez's own argument names


@dataclass(eq=False)
class Template:
    """A matcher's representation of one scan: named arrays plus JSON-able attributes."""

    subject: str | None
    scan_id: str | None
    method: str
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    attrs: dict[str, Any] = field(default_factory=dict)

    @property
    def nbytes(self) -> int:
        """Bytes held by the arrays."""
        return sum(int(a.nbytes) for a in self.arrays.values())

    def save(self, path: str | PathLike) -> None:
        """Write to an .npz file at exactly `path`: the arrays and a JSON string with the rest (no pickle)."""
        if clash := set(_RESERVED) & set(self.arrays):
            raise ValueError(f"array names {sorted(clash)} are reserved")
        meta = json.dumps({"subject": self.subject, "scan_id": self.scan_id, "method": self.method,
                           "attrs": self.attrs})
        with open(path, "wb") as f:
            np.savez(f, allow_pickle=False, **self.arrays, **{_META_KEY: np.array(meta)})

    @classmethod
    def load(cls, path: str | PathLike) -> "Template":
        """Read a template written by `save` (no pickle)."""
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data[_META_KEY]))
            arrays = {name: data[name] for name in data.files if name != _META_KEY}
        return cls(meta["subject"], meta["scan_id"], meta["method"], arrays, meta["attrs"])


def rank(scores: np.ndarray, tiebreak: np.ndarray | None = None, tolerance: float = TIE_TOLERANCE) -> np.ndarray:
    """Indices ordering scores best (highest) first; runs of near-ties (relative difference < tolerance between
    neighbours) are ordered by the larger tiebreak."""
    s = np.asarray(scores, dtype=np.float64)
    order = np.argsort(-s, kind="stable")
    if tiebreak is None or len(s) < 2:
        return order
    a, b = s[order[:-1]], s[order[1:]]
    with np.errstate(invalid="ignore"):
        tied = (a == b) | (np.abs(a - b) < tolerance * np.maximum(np.abs(a), np.abs(b)))
    group = np.concatenate([[0], np.cumsum(~tied)])
    return order[np.lexsort((-np.asarray(tiebreak, dtype=np.float64)[order], group))]


class Matcher(ABC):
    """Base class of face matchers. Subclasses set `name` and implement `enroll` and `score`.

    A matcher with settings keeps them in `self.config`, an instance of its
    dataclass `config_class`, given as the first argument of its constructor.
    A matcher that learns (`fit`) returns what it learnt from `state()` and
    takes it back in `set_state()`, so that `save` / `load_matcher` keep it.
    """

    name: str = "matcher"
    config_class: type | None = None
    #: True when a template's score depends on the other templates scored with it (normalisation over the
    #: gallery): verification must then score the probe against the whole gallery, not the claim alone.
    cohort_scores: bool = False

    @classmethod
    def from_options(cls, options: Mapping[str, Any] | None = None) -> "Matcher":
        """A matcher whose config has these fields changed (a method config file's table)."""
        if not options:
            return cls()
        if cls.config_class is None:
            raise ValueError(f"method {cls.name!r} takes no options (given {sorted(options)})")
        return cls(from_dict(cls.config_class, dict(options)))

    def options(self) -> dict[str, Any]:
        """The config as JSON-able fields (what `from_options` takes back)."""
        config = getattr(self, "config", None)
        return asdict(config) if is_dataclass(config) else {}

    def fit(self, scans: Sequence[FaceScan], subjects: Sequence[str]) -> "Matcher":
        """Learn from training scans (PCA, LDA); matchers that learn nothing return self."""
        return self

    @property
    def needs_training(self) -> bool:
        """True when `fit` must be called (with `--train`) before enrolling."""
        return False

    def state(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """What `fit` learnt: (named arrays, JSON-able attributes); empty for matchers that learn nothing."""
        return {}, {}

    def set_state(self, arrays: Mapping[str, np.ndarray], attrs: Mapping[str, Any]) -> None:
        """Take back what `state()` returned."""

    def save(self, path: str | PathLike) -> None:
        """Write the method name, its settings and what it learnt to an .npz file (no pickle)."""
        arrays, attrs = self.state()
        Template(None, None, self.name, dict(arrays), {"options": self.options(), "state": attrs}).save(path)

    @abstractmethod
    def enroll(self, scan: FaceScan) -> Template:
        """The gallery template of a scan, with whatever search structures matching needs."""

    def prepare(self, scan: FaceScan) -> Any:
        """The probe-side representation of a scan (by default its gallery template)."""
        return self.enroll(scan)

    def _probe(self, probe: FaceScan | Any) -> Any:
        return self.prepare(probe) if isinstance(probe, FaceScan) else probe

    @abstractmethod
    def score(self, probe: FaceScan | Any, template: Template) -> float:
        """Similarity of a probe (scan or prepared) to a template; higher is more similar."""

    def scores(self, probe: FaceScan | Any, templates: Sequence[Template]) -> tuple[np.ndarray, np.ndarray | None]:
        """(scores (n,), tiebreak (n,) or None) of a probe against many templates."""
        p = self._probe(probe)
        return np.array([self.score(p, t) for t in templates], dtype=np.float64), None

    # A gallery split into shards (gallery.engine) is scored shard by shard: `partial_scores` on each shard,
    # concatenated along the last axis, then `merge_scores` once, so that matchers whose scores depend on the
    # whole gallery (normalisation over it: region ICP, fusion) give the same scores however it is split.
    @property
    def n_partial(self) -> int:
        """Rows of `partial_scores`."""
        return 2

    def partial_scores(self, probe: FaceScan | Any, templates: Sequence[Template]) -> np.ndarray:
        """(n_partial, n): what can be computed template by template (by default the scores and tiebreak)."""
        s, t = self.scores(probe, templates)
        return np.stack([s, np.zeros_like(s) if t is None else np.asarray(t, dtype=np.float64)])

    def merge_scores(self, partial: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """(scores, tiebreak) of a whole gallery from its partial scores."""
        return partial[0], partial[1]

    def identify(self, probe: FaceScan | Any, gallery: Sequence[Template], k: int = 5) -> list[tuple[int, float]]:
        """The k best gallery entries as (index, score), best first; near-ties broken by the larger tiebreak."""
        s, tiebreak = self.scores(probe, gallery)
        return [(int(i), float(s[i])) for i in rank(s, tiebreak)[:k]]

    def verify(self, probe: FaceScan | Any, template: Template, threshold: float) -> bool:
        """Accept the claimed identity when the score reaches the threshold."""
        return bool(self.score(probe, template) >= threshold)
