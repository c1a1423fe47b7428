"""Evaluation protocols (chapter §8.4): which scans are the gallery, which are probes, and the reported subsets.

- `frgc`: the first neutral frontal scan of each subject (in semester, then
  scan-id order; the first scan when expressions are unknown) is the
  gallery; every other scan is a probe. Subsets: neutral and non-neutral
  probes, both frontal only, and one subset per head-pose label (a
  manifest's `pose` column, `pose:<label>`; a probe with a label other than
  empty, `frontal` or `front` is in no expression subset, so a ±25° yaw
  probe does not count as neutral).
- `frgc-exp3`: FRGC v2 Experiment 3 (3D versus 3D): every Fall 2003 and
  Spring 2004 scan against every other (Spring 2003 is Experiment 3's
  training partition and is left out), scored once and reported under
  FRGC's three masks of comparisons (query = probe row, target = gallery
  column): ROC I, both in the same semester; ROC II, both in the same
  academic year (Fall 2003 and Spring 2004 are both 2003/04, so every
  pair); ROC III, target in Fall 2003 and query in Spring 2004. The
  semester comes from the `Fall2003range` / `Spring2003range` /
  `Spring2004range` folder or a manifest's `session` column. Probe
  subsets as for `frgc`.
- `bosphorus`: the first neutral scan of each subject is the gallery; the
  other scans are probes, reported by subset: neutral (N), non-neutral (E,
  LFAU, UFAU, CAU), each of E, LFAU, UFAU, CAU, each emotion (E_HAPPY, ...),
  pose (YR, PR, CR), each of YR, PR, CR, and occlusion (O). A dataset none
  of whose scans has a Bosphorus type (a bsNNN_TYPE_SUB_k.bnt name, or a
  manifest label such as E_HAPPY) is refused: its gallery would be nonsense.
- `roles`: a manifest's `role` column says gallery or probe.
- `all-vs-all`: every scan is in the gallery and is a probe; a scan is never
  compared with itself, so a person's only scan has no mate: its probe is a
  search of a person not enrolled (evaluation.run marks it `mateless`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from facerec3d.errors import InputError
from facerec3d.datasets.catalog import BOSPHORUS_KINDS, BOSPHORUS_PATTERN, Dataset, ScanRecord

PROTOCOLS = ("frgc", "frgc-exp3", "bosphorus", "roles", "all-vs-all")
SEMESTERS = ("Spring2003", "Fall2003", "Spring2004")  # FRGC's, in time order
ACADEMIC_YEAR = {"Spring2003": "2002/03", "Fall2003": "2003/04", "Spring2004": "2003/04"}
EXP3_SEMESTERS = ("Fall2003", "Spring2004")
FRONTAL = ("", "frontal", "front")  # pose labels that count as frontal (no label: frontal)
BOSPHORUS_SUBSETS = ("E", "LFAU", "UFAU", "CAU", "YR", "PR", "CR")  # besides neutral (N) and occlusion (O)


@dataclass(frozen=True)
class Split:
    """Indices into the dataset's records: gallery, probes, and named probe subsets (indices into `probes`).

    masks: named boolean (len(probes), len(gallery)) matrices of the comparisons a figure is computed over
    (FRGC's ROC I / II / III); excluded: records the protocol leaves out, with why (`note`).
    """

    protocol: str
    gallery: list[int]
    probes: list[int]
    subsets: dict[str, list[int]] = field(default_factory=dict)
    exclude_self: bool = False
    masks: dict[str, np.ndarray] = field(default_factory=dict)
    excluded: list[int] = field(default_factory=list)
    note: str = ""


def default_protocol(dataset: Dataset) -> str:
    """Roles for a manifest with a role column; Bosphorus for a Bosphorus folder (or a manifest of Bosphorus
    files); FRGC otherwise."""
    if any(r.role for r in dataset.records):
        return "roles"
    if dataset.layout == "bosphorus" or dataset.records and all(BOSPHORUS_PATTERN.match(r.path.name)
                                                                for r in dataset.records):
        return "bosphorus"
    return "frgc"


def semester(session: str | None) -> str | None:
    """The FRGC semester (`Fall2003`, ...) of a session label such as `Fall2003range` or `fall 2003`; None if none."""
    m = re.search(r"(spring|fall)[\s_-]*(\d{4})", session or "", re.IGNORECASE)
    name = f"{m[1].capitalize()}{m[2]}" if m else None
    return name if name in SEMESTERS else None


def _order(r: ScanRecord) -> tuple:
    """Time order: FRGC semester (chronologically), then session label, then scan id."""
    s = semester(r.session)
    return (SEMESTERS.index(s) if s else len(SEMESTERS), r.session or "", r.scan_id)


def _frontal(r: ScanRecord) -> bool:
    return (r.pose or "").strip().lower() in FRONTAL


def _first_neutral(records: tuple[ScanRecord, ...], usable: set[int]) -> dict[str, int]:
    """Subject -> index of its first neutral frontal scan (its first scan if none is labelled so)."""
    first: dict[str, int] = {}
    for i in sorted(usable, key=lambda i: (not (records[i].expression == "neutral" and _frontal(records[i])),
                                           _order(records[i]))):
        first.setdefault(records[i].subject, i)
    return first


def _bosphorus_type(r: ScanRecord) -> str | None:
    """The Bosphorus TYPE (N, E, LFAU, ...) of a record named as in Bosphorus (label TYPE_SUB)."""
    return (r.label or "").split("_")[0].upper() if r.kind else None


def _subsets(records, probes: list[int], bosphorus: bool = False) -> dict[str, list[int]]:
    """Named probe subsets (see the module docstring), each a list of indices into `probes`."""
    def members(test) -> list[int]:
        return [k for k, i in enumerate(probes) if test(records[i])]

    if bosphorus:
        kinds = {"neutral": "neutral", "non-neutral": "expression", "pose": "pose", "occlusion": "occlusion"}
        named = {name: members(lambda r, kind=kind: r.kind == kind) for name, kind in kinds.items()}
        named |= {t: members(lambda r, t=t: _bosphorus_type(r) == t) for t in BOSPHORUS_SUBSETS}
        named |= {label: members(lambda r, label=label: r.label == label)
                  for label in sorted({records[i].label for i in probes if _bosphorus_type(records[i]) == "E"})}
    else:
        named = {e: members(lambda r, e=e: r.expression == e and _frontal(r)) for e in ("neutral", "non-neutral")}
    for pose in sorted({records[i].pose for i in probes if records[i].pose}):  # a manifest's pose column
        named[f"pose:{pose}"] = members(lambda r, pose=pose: r.pose == pose)
    return {name: m for name, m in named.items() if m}


def _exp3(dataset: Dataset) -> Split:
    """FRGC Experiment 3: all against all over Fall 2003 and Spring 2004, with the ROC I / II / III masks."""
    recs = dataset.records
    sem = [semester(r.session) for r in recs]
    unknown = [r for r, s in zip(recs, sem) if s is None]
    if unknown:
        raise InputError(f"{dataset.source}: frgc-exp3: {len(unknown)} scans have no FRGC semester (a Fall2003range / "
                         f"Spring2003range / Spring2004range folder or a session column), e.g. {unknown[0].path}")
    every = [i for i, s in enumerate(sem) if s in EXP3_SEMESTERS]
    if not every:
        raise InputError(f"{dataset.source}: frgc-exp3: no Fall 2003 or Spring 2004 scans")
    s = np.array([sem[i] for i in every])
    year = np.array([ACADEMIC_YEAR[x] for x in s])
    masks = {"ROC I": s[:, None] == s[None, :], "ROC II": year[:, None] == year[None, :],
             "ROC III": (s[:, None] == "Spring2004") & (s[None, :] == "Fall2003")}
    left_out = sorted(set(range(len(recs))) - set(every))
    note = f"{len(left_out)} Spring 2003 scans (Experiment 3's training partition) left out" if left_out else ""
    return Split("frgc-exp3", every, every, _subsets(recs, every), True, masks, left_out, note)


def split(dataset: Dataset, protocol: str | None = None) -> Split:
    """The gallery/probe split of a dataset (`catalog.open_dataset`'s) under a protocol (default:
    `default_protocol`)."""
    if not isinstance(dataset, Dataset):
        raise InputError(f"split takes a Dataset (facerec3d.datasets.catalog.open_dataset(path)), not {dataset!r:.60}")
    protocol = protocol or default_protocol(dataset)
    recs = dataset.records
    everything = set(range(len(recs)))
    if protocol == "frgc":
        gallery = sorted(_first_neutral(recs, everything).values())
        probes = sorted(everything - set(gallery))
        return Split(protocol, gallery, probes, _subsets(recs, probes))
    if protocol == "frgc-exp3":
        return _exp3(dataset)
    if protocol == "bosphorus":
        if not any(_bosphorus_type(r) in BOSPHORUS_KINDS or BOSPHORUS_PATTERN.match(r.path.name) for r in recs):
            raise InputError(f"{dataset.source}: the bosphorus protocol needs Bosphorus scan types (N, E, LFAU, UFAU, "
                             "CAU, YR, PR, CR, O: bsNNN_TYPE_SUB_k.bnt names, or a manifest label such as E_HAPPY) "
                             "and none of its scans has one; use --protocol frgc, roles or all-vs-all")
        neutral = {i for i in everything if recs[i].kind == "neutral"}
        gallery = sorted(_first_neutral(recs, neutral or everything).values())
        probes = sorted(everything - set(gallery))
        return Split(protocol, gallery, probes, _subsets(recs, probes, bosphorus=True))
    if protocol == "roles":
        if not any(r.role for r in recs):
            raise InputError(f"{dataset.source}: the roles protocol needs a manifest with a role column")
        gallery = [i for i, r in enumerate(recs) if r.role == "gallery"]
        probes = [i for i, r in enumerate(recs) if r.role == "probe"]
        return Split(protocol, gallery, probes, _subsets(recs, probes))
    if protocol == "all-vs-all":
        every = sorted(everything)
        return Split(protocol, every, every, _subsets(recs, every), exclude_self=True)
    raise InputError(f"{dataset.source}: unknown protocol {protocol!r}: use one of {', '.join(PROTOCOLS)}")
