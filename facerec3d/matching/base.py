"""The matcher interface shared by ICP (§8.6), PCA (§8.7), LDA (§8.8), curvature (§8.9) and the §8.10 matchers.

Scikit-learn-like and small:

    matcher = make_matcher("icp", options)         # registry; matcher.options() gives the options back
    matcher.fit(training_scans, subjects)          # learnt matchers only (needs_training); learnt state ends in _
    matcher.save("model.npz"); load_matcher("model.npz")   # settings + what fit learnt (state / set_state)
    gallery = [matcher.enroll(scan) for scan in gallery_scans]
    probe = matcher.prepare(scan)                  # the matcher's probe type; done by score() when given a FaceScan
    matcher.score(probe, gallery[i]); matcher.scores(probe, gallery)   # similarity; (scores, tiebreak or None)
    matcher.identify(probe, gallery, k=5)          # [(gallery index, score), ...] best first
    matcher.verify(probe, gallery[i], threshold)   # score >= threshold

Scores are similarities: higher means more alike (ICP gives −MSE in mm²).
A `Template` is what a matcher keeps of a scan; it saves to .npz without
pickle. Matchers whose scores are normalised over the gallery scored with
the probe (region ICP, fusion) are `GalleryNormalised`: a sharded gallery
(gallery.engine) scores them shard by shard through `shard_scores` and
`merge_shard_scores`.
"""

from __future__ import annotations

import json
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, is_dataclass
from os import PathLike
from typing import Any, Generic, NamedTuple, TypeVar, get_args, get_origin

import numpy as np

from facerec3d.config import check_ranges, from_dict
from facerec3d.errors import InputError, SettingsError
from facerec3d.scan import FaceScan, column_bounds

#: Relative score difference under which two scores count as tied (then the tiebreak decides).
TIE_TOLERANCE = 1e-9

#: A matcher's probe type: what `prepare` returns (ICP: ProbeData; PCA, LDA: a feature vector; by default
#: the probe's gallery Template).
P = TypeVar("P")

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


def vector_similarity(p: np.ndarray, G: np.ndarray, distance: str, scale: np.ndarray | None = None) -> np.ndarray:
    """Similarities of a feature vector `p` to each row of `G`: the cosine, or else minus the Euclidean distance
    (of the differences divided by `scale` when given: Mahalanobis in a whitened space, §8.7.3). A `p` of another
    length is an InputError (the Euclidean distance broadcast a 1-vector silently, the cosine gave matmul's error)."""
    if G.ndim == 2 and G.shape[1] != len(p):
        raise InputError(f"a probe of {len(p)} features against templates of {G.shape[1]}: "
                         "prepared by another model or method")
    if distance == "cosine":
        return G @ p / np.maximum(np.linalg.norm(G, axis=1) * np.linalg.norm(p), np.finfo(float).tiny)
    diff = G - p if scale is None else (G - p) / scale
    return -np.sqrt(np.einsum("ij,ij->i", diff, diff))


class GalleryScores(NamedTuple):
    """A probe's scores against a gallery, one per entry: similarity and tiebreak (0 where the method has none)."""

    scores: np.ndarray
    tiebreak: np.ndarray


#: A face as preprocessing leaves it has its nose tip at the origin: its bounding box holds the origin (§8.5.5). A raw
#: scan lies where its camera saw it (a Kinect frame ~1 m away along −z); `check_face` allows this much slack.
NEAR_ORIGIN_MM = 50.0


def check_face(scan: FaceScan) -> None:
    """Refuse (InputError) what no matcher can use: a scan with no points, or one that preprocessing has not put in
    the frontal frame, nose tip at the origin (matchers gave −inf, 0 or a KeyError for raw scans)."""
    if not isinstance(scan, FaceScan):  # an array of points, None: an AttributeError ("no attribute 'meta'") was
        raise InputError(f"scan must be a FaceScan, not {type(scan).__name__}")  # all a caller saw
    who = scan.meta.path or scan.meta.scan_id or "the scan"
    if not scan.n_points:
        raise InputError(f"{who}: an empty face, nothing to match")
    lo, hi = column_bounds(scan.points)
    if (lo > NEAR_ORIGIN_MM).any() or (hi < -NEAR_ORIGIN_MM).any():
        far = float(np.max(np.maximum(lo, -hi)))
        raise InputError(f"{who}: not a preprocessed face (its points lie {far:.0f} mm or more from the origin, where "
                         "preprocessing puts the nose tip): preprocess it first (facerec3d preprocess, or "
                         "facerec3d.preprocess.Preprocessor)")


def check_probe(matcher: "Matcher", probe: Any) -> Any:
    """A prepared probe as the matcher's `prepare` makes it (its declared probe type `P`; a vector of numbers for a
    feature vector), else InputError naming what was expected: an array of points, say, reached the ICP kernel as a
    Numba TypingError, the subspace matchers as a broadcast error, the others as an AttributeError."""
    expected = probe_type(type(matcher))
    what = f"probe must be a FaceScan or a prepared probe ({matcher.name}: {expected.__name__}, from prepare())"
    if not isinstance(probe, expected):
        raise InputError(f"{what}, not {type(probe).__name__}")
    if isinstance(probe, np.ndarray) and (probe.ndim != 1 or not probe.size or probe.dtype.kind not in "iuf"):
        raise InputError(f"{what}, a vector of features, not an array of shape {probe.shape} ({probe.dtype})")
    return probe


def unused_weights_dropped(options: Any) -> Any:
    """Stored options with the `weights` of a fusion or region ICP whose `rule` ignores them left out, in nested
    tables too (a fusion's member options): such settings were taken, and the weights unused, until 2026-12-06,
    when a method config holding them began to be refused (`normalisation.check_fusion`); a gallery stored with
    them loads and scores as it did."""
    if not isinstance(options, Mapping):
        return options
    return {k: unused_weights_dropped(v) for k, v in options.items()
            if not (k == "weights" and "rule" in options and options["rule"] != "weighted-sum")}


def check_templates(matcher: "Matcher", templates: Any) -> None:
    """InputError unless `templates` are gallery templates (`enroll` makes them): a scan given as the template
    reached each matcher's arrays as an AttributeError. Only a sequence is looked at (an iterator is left unread)."""
    for t in templates if isinstance(templates, Sequence) else ():
        if not isinstance(t, Template):
            raise InputError(f"{matcher.name} scores a probe against gallery templates (from enroll()), not "
                             f"{type(t).__name__}")


def probe_type(cls: type) -> type:
    """The probe type `P` a matcher class declares (`Matcher[ProbeData]`); Template, `prepare`'s default, when none."""
    for klass in cls.__mro__:
        for base in getattr(klass, "__orig_bases__", ()):
            if get_origin(base) is Matcher and isinstance(arg := get_args(base)[0], type):
                return arg
    return Template


def check_threshold(threshold: Any) -> float:
    """A verification threshold: a finite number (every score compares False with NaN: all rejected silently; an
    infinite one accepts all or none; a string gave Python's TypeError). `Matcher.verify` and
    `gallery.service.verify_scan` take it through here."""
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float, np.integer, np.floating)) \
            or not np.isfinite(threshold):
        raise InputError(f"a verification threshold is a finite number, not {threshold!r}")
    return float(threshold)


def check_training(scans: Sequence[FaceScan], subjects: Sequence[str], name: str, least: int = 2) -> None:
    """Refuse (InputError) training data a matcher cannot learn from: not one subject per scan, or fewer than
    `least` scans."""
    if len(scans) != len(subjects):
        raise InputError(f"{name}: {len(scans)} training scans and {len(subjects)} subjects: give one subject per scan")
    if len(scans) < least:
        raise InputError(f"{name}: {len(scans)} training scans, it learns from {least} or more")


def check_k(k: int) -> int:
    """The number of candidates an identification lists: a whole number of 1 or more, else InputError (a slice of
    k = -1 would drop the last candidate, 0 give none)."""
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise InputError(f"k must be a whole number of 1 or more, not {k!r}")
    return int(k)


def best_k(scores: np.ndarray, tiebreak: np.ndarray | None, k: int) -> np.ndarray:
    """The indices of the k best scores, best first (`rank`; `check_k`)."""
    return rank(scores, tiebreak)[:check_k(k)]


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


def learnt_arrays(arrays: Mapping[str, Any], shapes: Mapping[str, tuple[int | str, ...]],
                  **sizes: int) -> list[np.ndarray]:
    """The learnt arrays `shapes` names, in that order, as float64, checked as `set_state` takes them back from a
    model file or a gallery: each there, of numbers, of its shape (a size given as a letter is the same wherever it
    appears, and equals `sizes[letter]` when given: what the method's settings imply), not empty, and finite.
    ValueError in one line naming the array otherwise (`restore_state` names the file): a damaged model was
    accepted and crashed later, or scored everything NaN."""
    out = []
    for name, shape in shapes.items():
        if name not in arrays:
            raise ValueError(f"no {name!r} array")
        a = np.asarray(arrays[name])
        if a.dtype.kind not in "iuf":
            raise ValueError(f"{name!r} holds {a.dtype} values, not numbers")
        wanted = tuple(sizes.setdefault(n, a.shape[i]) if isinstance(n, str) and i < a.ndim else n
                       for i, n in enumerate(shape))
        if a.shape != wanted or not a.size:
            shown = ", ".join(str(sizes.get(n, n)) for n in shape) + ("," if len(shape) == 1 else "")
            raise ValueError(f"{name!r} of shape {a.shape}, not ({shown})")
        if not np.isfinite(a).all():
            raise ValueError(f"{name!r} holds NaN or infinite values")
        out.append(a.astype(np.float64))
    return out


def with_added(added: Mapping[str, Any], stored: Mapping[str, Any]) -> dict[str, Any]:
    """Stored options with the fields `added` names that they lack; a nested table stored is completed field by
    field (`Matcher.added_options`)."""
    out = dict(stored)
    for name, value in added.items():
        if name not in out:
            out[name] = value
        elif isinstance(value, Mapping) and isinstance(out[name], Mapping):
            out[name] = with_added(value, out[name])
    return out


class Matcher(ABC, Generic[P]):
    """Base class of face matchers. Subclasses set `name` and implement `enroll` and `score`; those with their
    own probe type `P` implement `prepare` and declare it (`class ICPMatcher(Matcher[ProbeData])`).

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
    #: Config fields added after templates of this method were first stored, with the value that works as the method
    #: did before each: options stored without such a field (an older gallery or model file) take that value, not
    #: today's default, so old templates keep meeting probes prepared and scored their way (`from_stored`). A field
    #: of a nested table is given as a nested table ({"icp": {"plane_cap_mm": 0.0}}).
    added_options: dict[str, Any] = {}

    @property
    def config(self) -> Any:
        """The matcher's settings, an instance of `config_class`."""
        return self._config

    @config.setter
    def config(self, value: Any) -> None:
        """Settings are checked as they are set, those built in Python (`ICPMatcher(ICPConfig(max_iterations=-3))`)
        as a settings file's are (`config.check_ranges`): a SettingsError naming the field, not a failure later."""
        if self.config_class is not None and not isinstance(value, self.config_class):
            raise InputError(f"method {self.name!r} takes {self.config_class.__name__} settings, "
                             f"not a {type(value).__name__}")
        if is_dataclass(value):
            check_ranges(value)
        self._config = value

    @classmethod
    def from_stored(cls, options: Mapping[str, Any] | None) -> "Matcher":
        """The matcher of options stored with templates (a gallery, a model file): fields missing from them that
        were added later (`added_options`) keep the behaviour of their time."""
        return cls.from_options(unused_weights_dropped(with_added(cls.added_options, options or {})))

    @classmethod
    def from_options(cls, options: Mapping[str, Any] | None = None) -> "Matcher":
        """A matcher whose config has these fields changed (a method config file's table)."""
        if not options:
            return cls()
        source = getattr(options, "source", None)  # the settings file, when read with config.read_settings
        if cls.config_class is None:
            raise SettingsError(source, None, f"method {cls.name!r} takes no options (given {sorted(options)})")
        config = from_dict(cls.config_class, options)
        try:
            return cls(config)
        except SettingsError as e:  # settings of a fusion's members
            raise e.within(source) from None

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

    def learners(self) -> list[str]:
        """The names of the methods in this matcher that learn from data: its own when it does (a fusion: its
        members that do), for messages that say which one needs `--train`."""
        return [self.name] if self.needs_training else []

    def state(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """What `fit` learnt: (named arrays, JSON-able attributes); empty for matchers that learn nothing."""
        return {}, {}

    def set_state(self, arrays: Mapping[str, np.ndarray], attrs: Mapping[str, Any]) -> None:
        """Take back what `state()` returned, checked (`learnt_arrays`): ValueError, one line, for a damaged one."""

    def save(self, path: str | PathLike) -> None:
        """Write the method name, its settings and what it learnt to an .npz file (no pickle)."""
        arrays, attrs = self.state()
        Template(None, None, self.name, dict(arrays), {"options": self.options(), "state": attrs}).save(path)

    @abstractmethod
    def enroll(self, scan: FaceScan) -> Template:
        """The gallery template of a scan, with whatever search structures matching needs."""

    def prepare(self, scan: FaceScan) -> P:
        """The probe-side representation of a scan (by default its gallery template)."""
        return self.enroll(scan)

    def _probe(self, probe: FaceScan | P, templates: Sequence[Template] = ()) -> P:
        """A probe as `prepare` makes it, from a scan or an already prepared probe (`check_probe`), the templates
        it is to be scored against checked (`check_templates`): every matcher's score and scores come through
        here, so the checks are in one place."""
        check_templates(self, templates)
        return self.prepare(probe) if isinstance(probe, FaceScan) else check_probe(self, probe)

    @abstractmethod
    def score(self, probe: FaceScan | P, template: Template) -> float:
        """Similarity of a probe (scan or prepared) to a template; higher is more similar."""

    def scores(self, probe: FaceScan | P, templates: Sequence[Template]) -> tuple[np.ndarray, np.ndarray | None]:
        """(scores (n,), tiebreak (n,) or None) of a probe against many templates."""
        p = self._probe(probe, templates)
        return np.array([self.score(p, t) for t in templates], dtype=np.float64), None

    def identify(self, probe: FaceScan | P, gallery: Sequence[Template], k: int = 5) -> list[tuple[int, float]]:
        """The k best gallery entries as (index, score), best first; near-ties broken by the larger tiebreak."""
        s, tiebreak = self.scores(probe, gallery)
        return [(int(i), float(s[i])) for i in best_k(s, tiebreak, k)]

    def verify(self, probe: FaceScan | P, template: Template, threshold: float) -> bool:
        """Accept the claimed identity when the score reaches the threshold (a number: `check_threshold`)."""
        threshold = check_threshold(threshold)
        return bool(self.score(probe, template) >= threshold)


class GalleryNormalised(ABC):
    """Mixin of matchers whose scores are normalised over the gallery scored with the probe (region ICP, fusion).

    A gallery split into shards (gallery.engine) is scored shard by shard: `partial_scores` on each shard,
    concatenated along the last axis, then `merge_scores` once, so that the scores are the same however the
    gallery is split. Verification scores the probe against the whole gallery (`cohort_scores`)."""

    cohort_scores = True

    @property
    @abstractmethod
    def n_partial(self) -> int:
        """Rows of `partial_scores`."""

    @abstractmethod
    def partial_scores(self, probe: Any, templates: Sequence[Template]) -> np.ndarray:
        """(n_partial, n): what can be computed template by template."""

    @abstractmethod
    def merge_scores(self, partial: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """(scores, tiebreak) of a whole gallery from its partial scores."""

    def scores(self, probe: Any, templates: Sequence[Template]) -> tuple[np.ndarray, np.ndarray | None]:
        return self.merge_scores(self.partial_scores(probe, templates))

    def score(self, probe: Any, template: Template) -> float:
        """The template's score among a gallery of one (degenerate for the normalisations: use `scores`)."""
        return float(self.scores(probe, [template])[0][0])


def shard_rows(matcher: Matcher) -> int:
    """Rows of `shard_scores` for this matcher."""
    return matcher.n_partial if isinstance(matcher, GalleryNormalised) else 2


def shard_scores(matcher: Matcher, probe: Any, templates: Sequence[Template]) -> np.ndarray:
    """(shard_rows, n): a probe's scores against one shard of a gallery, to be joined with the other shards' along
    the last axis and merged by `merge_shard_scores`: a GalleryNormalised matcher's partial scores, or the
    scores and tiebreak (0 where none) of any other."""
    if isinstance(matcher, GalleryNormalised):
        return matcher.partial_scores(probe, templates)
    s, t = matcher.scores(probe, templates)
    return np.stack([s, np.zeros_like(s) if t is None else np.asarray(t, dtype=np.float64)])


def merge_shard_scores(matcher: Matcher, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """(scores, tiebreak) of a whole gallery from its shards' `shard_scores`, joined."""
    return matcher.merge_scores(rows) if isinstance(matcher, GalleryNormalised) else (rows[0], rows[1])


def scores_over(matcher: Matcher, rows: np.ndarray, cohort: np.ndarray) -> np.ndarray:
    """(n,) the scores of the entries in `cohort` (booleans over the gallery's `shard_scores` columns), merged as a
    gallery of those entries alone, NaN elsewhere: a method that normalises over the gallery normalises over them. A
    claim by someone not enrolled (a stranger's) is scored over every entry but the claimant's own, as it meets a
    gallery that does not hold them (`evaluation.calibrate.pair_scores`, `evaluate`'s strangers' claims)."""
    cohort = np.asarray(cohort, dtype=bool)
    out = np.full(cohort.shape, np.nan)
    if cohort.any():
        out[cohort] = merge_shard_scores(matcher, rows[:, cohort])[0]
    return out
