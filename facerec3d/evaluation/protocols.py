"""Evaluation protocols (chapter §8.4): which scans are the gallery, which are probes, and the reported subsets.

- `frgc`: the first neutral scan of each subject (in session, then scan-id
  order; the first scan when expressions are unknown) is the gallery; every
  other scan is a probe. Subsets: neutral and non-neutral probes.
- `bosphorus`: the first neutral scan of each subject is the gallery; the
  other scans are probes, and the neutral, expression (E, LFAU, UFAU, CAU),
  pose and occlusion probes are reported separately, as subsets.
- `roles`: a manifest's `role` column says gallery or probe.
- `all-vs-all`: every scan is in the gallery and is a probe; a scan is never
  compared with itself.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from facerec3d.datasets.catalog import Dataset, ScanRecord

PROTOCOLS = ("frgc", "bosphorus", "roles", "all-vs-all")


@dataclass(frozen=True)
class Split:
    """Indices into the dataset's records: gallery, probes, and named probe subsets (indices into `probes`)."""

    protocol: str
    gallery: list[int]
    probes: list[int]
    subsets: dict[str, list[int]] = field(default_factory=dict)
    exclude_self: bool = False


def default_protocol(dataset: Dataset) -> str:
    """Bosphorus for a Bosphorus folder, roles for a manifest with a role column, FRGC otherwise."""
    if dataset.layout == "bosphorus":
        return "bosphorus"
    if any(r.role for r in dataset.records):
        return "roles"
    return "frgc"


def _order(r: ScanRecord) -> tuple:
    return (r.session or "", r.scan_id)


def _first_neutral(records: tuple[ScanRecord, ...], usable: set[int]) -> dict[str, int]:
    """Subject -> index of its first neutral scan (its first scan if none is labelled neutral)."""
    first: dict[str, int] = {}
    for i in sorted(usable, key=lambda i: (records[i].expression != "neutral", _order(records[i]))):
        first.setdefault(records[i].subject, i)
    return first


def _subsets(records, probes: list[int], kinds=("neutral", "non-neutral")) -> dict[str, list[int]]:
    out: dict[str, list[int]] = {}
    for name in kinds:
        if name in ("neutral", "non-neutral"):
            members = [k for k, i in enumerate(probes) if records[i].expression == name]
        else:
            members = [k for k, i in enumerate(probes) if records[i].kind == name]
        if members:
            out[name] = members
    for pose in sorted({records[i].pose for i in probes if records[i].pose}):  # a manifest's pose column
        out[f"pose:{pose}"] = [k for k, i in enumerate(probes) if records[i].pose == pose]
    return out


def split(dataset: Dataset, protocol: str | None = None) -> Split:
    """The gallery/probe split of a dataset under a protocol (default: `default_protocol`)."""
    protocol = protocol or default_protocol(dataset)
    recs = dataset.records
    everything = set(range(len(recs)))
    if protocol == "frgc":
        gallery = sorted(_first_neutral(recs, everything).values())
        probes = sorted(everything - set(gallery))
        return Split(protocol, gallery, probes, _subsets(recs, probes))
    if protocol == "bosphorus":
        neutral = {i for i in everything if recs[i].kind == "neutral"}
        gallery = sorted(_first_neutral(recs, neutral or everything).values())
        probes = sorted(everything - set(gallery))
        return Split(protocol, gallery, probes, _subsets(recs, probes, ("neutral", "non-neutral", "pose", "occlusion")))
    if protocol == "roles":
        if not any(r.role for r in recs):
            raise ValueError("the roles protocol needs a manifest with a role column")
        gallery = [i for i, r in enumerate(recs) if r.role == "gallery"]
        probes = [i for i, r in enumerate(recs) if r.role == "probe"]
        return Split(protocol, gallery, probes, _subsets(recs, probes))
    if protocol == "all-vs-all":
        every = sorted(everything)
        return Split(protocol, every, every, _subsets(recs, every), exclude_self=True)
    raise ValueError(f"unknown protocol {protocol!r}: use one of {', '.join(PROTOCOLS)}")
