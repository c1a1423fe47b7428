"""The fusion matcher (chapter §8.10: fusion across methods): member methods' scores, normalised per probe over
the gallery and combined by a rule (`matching.normalisation`).

`FusionMatcher` ("fusion") combines member methods built by name (`matching.methods`: every method but fusion),
e.g. ICP and region ICP, or ICP with PCA / LDA. Its template packs the members' templates into one.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np

from facerec3d.config import check_ranges
from facerec3d.errors import SettingsError
from facerec3d.matching.base import (GalleryNormalised, Matcher, Template, merge_shard_scores, shard_rows, shard_scores,
                                     with_added)
from facerec3d.matching.methods import make_method, method_class
from facerec3d.matching.normalisation import check_fusion, fuse, minus_best_other
from facerec3d.scan import FaceScan


# ----------------------------------------------------------------------------- sub-templates
def pack(templates: Sequence[Template], method: str) -> Template:
    """One template holding several (members' or regions') templates: arrays under "k__name"."""
    first = templates[0]
    arrays = {f"{k}__{name}": a for k, t in enumerate(templates) for name, a in t.arrays.items()}
    attrs = {"parts": [{"method": t.method, "attrs": t.attrs} for t in templates]}
    return Template(first.subject, first.scan_id, method, arrays, attrs)


def unpack(template: Template) -> list[Template]:
    """The templates that `pack` put together."""
    parts = template.attrs["parts"]
    arrays: list[dict[str, np.ndarray]] = [{} for _ in parts]
    for key, a in template.arrays.items():
        k, _, name = key.partition("__")
        arrays[int(k)][name] = a
    return [Template(template.subject, template.scan_id, p["method"], arrays[k], p["attrs"])
            for k, p in enumerate(parts)]


def _fields(options: Mapping[str, Any], names: Mapping[str, Any]) -> dict[str, Any]:
    """The fields of `options` that `names` names (nested tables by nested tables)."""
    return {k: _fields(options[k], v) if isinstance(v, Mapping) and isinstance(options[k], Mapping) else options[k]
            for k, v in names.items() if k in options}


def _without_defaults(options: Mapping[str, Any], names: Mapping[str, Any], defaults: Mapping[str, Any]) -> dict:
    """`options` without the fields `names` names whose value is today's default (so that options stored today load
    as the config they were made from), nested tables left out when nothing else is left in them."""
    out = dict(options)
    for k, v in names.items():
        if k not in out or k not in defaults:
            continue
        if isinstance(v, Mapping) and isinstance(out[k], Mapping) and isinstance(defaults[k], Mapping):
            out[k] = _without_defaults(out[k], v, defaults[k])
            if not out[k]:
                del out[k]
        elif out[k] == defaults[k]:
            del out[k]
    return out


@lru_cache(maxsize=65536)  # the same gallery's subjects, probe after probe
def subject_key(subject: str) -> float:
    """A subject's name as a number that shards carry with their scores (a 52-bit hash: exact in a float64, equal
    for equal names, two names alike by chance once in ~10^15)."""
    return float(int.from_bytes(hashlib.blake2b(str(subject).encode(), digest_size=8).digest(), "big") >> 12)


# ----------------------------------------------------------------------------- the fusion matcher
@dataclass(frozen=True)
class FusionConfig:
    """Fusion of member methods (§8.10; Jain et al. 2005). Scores are normalised per probe over the gallery
    it is compared with, so a fused score is relative to the templates scored together."""

    members: tuple[str, ...] = ("icp", "region-icp", "embedding")  # method names (matching.methods); the default
    #   method's members, chosen across every set (config.DEFAULT_METHOD, docs/methods.md)
    member_options: dict[str, dict[str, Any]] = field(default_factory=dict)  # method name -> its config table
    normalisation: str = "z-score"  # one of normalisation.NORMALISATIONS (z-score: the robust default of Jain et al. 2005)
    rule: str = "sum"  # one of normalisation.RULES (sum: Kittler et al. 1998's most robust rule)
    weights: tuple[float, ...] = ()  # one per member, for rule = "weighted-sum"
    top: int = 0  # Borda points only for each source's `top` best (0 = all), rules borda / consensus
    cohort: float = 0.0  # share of the best other person's fused score taken off each (normalisation.minus_best_other;
    #   no rank moves). Off by default: it lowers the EER where impostors are enrolled people (rap3df-2019 held-out
    #   11.8 -> 10.5 % at 0.5) but not for strangers' claims (13.9 -> 14.8 %; docs/methods.md)

    def __post_init__(self) -> None:
        check_ranges(self)  # NaN or a negative weight named before the checks below compute with it
        if not self.members:
            raise ValueError("fusion needs at least one member method")
        if unknown := set(self.member_options) - set(self.members):
            raise ValueError(f"member_options for methods that are not members: {sorted(unknown)}")
        check_fusion(self.rule, self.normalisation, self.weights, len(self.members))


class FusionMatcher(GalleryNormalised, Matcher[list]):
    """Score-level fusion of member methods (§8.10): each member scores the probe against the gallery, the
    scores are normalised per probe and combined by the rule. `score` of one template is that template's
    fused score among a gallery of one (degenerate for the normalisations): use `scores` on a gallery."""

    name = "fusion"
    config_class = FusionConfig

    def __init__(self, config: FusionConfig = FusionConfig()):
        self.config = config
        self.members: list[Matcher] = []
        for m in config.members:
            try:
                self.members.append(make_method(m, config.member_options.get(m)))
            except SettingsError as e:
                raise e.within(section=f"member_options.{m}" if m in config.member_options else "members") from None

    @classmethod
    def from_stored(cls, options: Mapping[str, Any] | None) -> FusionMatcher:
        """Stored fusion options: each member keeps the behaviour of its time too (its `added_options` where the
        stored member options lack them; `options` stores today's values of those fields)."""
        options = dict(options or {})
        members = options.get("members", FusionConfig.members)
        stored = options.get("member_options") or {}
        if isinstance(members, (list, tuple)) and isinstance(stored, Mapping):
            completed = {}
            for m in members:
                if isinstance(m, str) and ((added := method_class(m).added_options) or m in stored):
                    today = asdict(method_class(m).config_class()) if added else {}
                    completed[m] = _without_defaults(with_added(added, stored.get(m) or {}), added, today)
            options["member_options"] = {m: o for m, o in completed.items() if o}
        return super().from_stored(options)

    def options(self) -> dict[str, Any]:
        """The config, each member's options holding also the fields its method added since galleries were first
        stored (today's values), so that a gallery stored now is told from one stored before (`from_stored`)."""
        out = super().options()
        given = out["member_options"]
        for m in self.members:
            if m.added_options:
                given[m.name] = with_added(_fields(m.options(), m.added_options), given.get(m.name) or {})
        return out

    @property
    def needs_training(self) -> bool:
        return any(m.needs_training for m in self.members)

    def learners(self) -> list[str]:
        return [name for m in self.members for name in m.learners()]

    def fit(self, scans: Sequence[FaceScan], subjects: Sequence[str]) -> FusionMatcher:
        for m in self.members:
            m.fit(scans, subjects)
        return self

    def state(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        arrays, attrs = {}, []
        for k, m in enumerate(self.members):
            a, s = m.state()
            arrays.update({f"{k}__{name}": v for name, v in a.items()})
            attrs.append(s)
        return arrays, {"members": attrs}

    def set_state(self, arrays: Mapping[str, np.ndarray], attrs: Mapping[str, Any]) -> None:
        for k, m in enumerate(self.members):
            prefix = f"{k}__"
            try:
                m.set_state({n[len(prefix):]: a for n, a in arrays.items() if n.startswith(prefix)},
                            attrs["members"][k])
            except ValueError as e:
                raise ValueError(f"member {m.name!r}: {e}") from None

    def enroll(self, scan: FaceScan) -> Template:
        return pack([m.enroll(scan) for m in self.members], self.name)

    def prepare(self, scan: FaceScan) -> list:
        """Each member's prepared probe."""
        return [m.prepare(scan) for m in self.members]

    @property
    def n_partial(self) -> int:
        return sum(shard_rows(m) for m in self.members) + 1

    def partial_scores(self, probe: FaceScan | list, templates: Sequence[Template]) -> np.ndarray:
        """The members' shard scores, stacked, and a last row naming each template's subject (`subject_key`; zeros
        when `cohort` is 0, which never reads it): (Σ members' shard_rows + 1, n)."""
        p = self._probe(probe, templates)
        parts = [unpack(t) for t in templates]
        rows = [shard_scores(m, p[k], [q[k] for q in parts]) for k, m in enumerate(self.members)]
        keys = [subject_key(t.subject) for t in templates] if self.config.cohort else np.zeros(len(templates))
        return np.concatenate([*rows, [keys]])

    def merge_scores(self, partial: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Each member's scores merged over the whole gallery, then normalised and fused, and the best other
        person's share taken off (`cohort`)."""
        bounds = np.cumsum([0] + [shard_rows(m) for m in self.members])
        S = np.stack([merge_shard_scores(m, partial[a:b])[0]
                      for m, a, b in zip(self.members, bounds[:-1], bounds[1:])])
        c = self.config
        fused, tiebreak = fuse(S, c.rule, c.normalisation, c.weights, c.top)
        return minus_best_other(fused, partial[-1], c.cohort), tiebreak
