"""Datasets: the list of scans of a FRGC v2 directory, a Bosphorus directory or a manifest CSV.

Real FRGC v2 and Bosphorus data are licence-gated: obtain them from their
owners and point facerec3d at them in place; nothing is copied.

- FRGC v2: `<subject>d<seq>.abs[.gz]` files; the subject is the text before
  `d`, the session the `Spring2003range` / `Fall2003range` / `Spring2004range`
  folder the file is in. FRGC file names carry no expression label: give one
  with a manifest (a `manifest.csv` in the folder is used when present).
- Bosphorus: `bsNNN_TYPE_SUB_k.bnt`; TYPE N is neutral, E / LFAU / UFAU / CAU
  are expressions, YR / PR / CR are poses, O occlusions.
- Manifest CSV: columns `path,subject` and optional `expression`
  (`neutral` / `non-neutral` or a finer label), `role` (`gallery` / `probe`),
  `session` (default: the FRGC session folder in the path, if any), `label` (a Bosphorus scan type such as
  `E_HAPPY` types the scan as a bsNNN_TYPE_SUB_k name would) and `pose` (a head-pose label, reported as
  its own probe subsets; empty or `frontal` is frontal); scans may be
  depth frames (`.png`, `.tif`) with an `intrinsics.json` beside them or above; relative paths are relative to the manifest's folder.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from urllib.parse import quote

from facerec3d.errors import FaceRec3DError
from facerec3d.io import scan_stem

FRGC_PATTERN = re.compile(r"^(?P<subject>\d+)d(?P<seq>\d+)\.abs(\.gz)?$", re.IGNORECASE)
BOSPHORUS_PATTERN = re.compile(r"^(?P<subject>bs\d+)_(?P<type>[A-Z]+)_(?P<sub>[A-Za-z0-9]+)_(?P<k>\d+)\.bnt$", re.IGNORECASE)
FRGC_SESSIONS = ("Spring2003range", "Fall2003range", "Spring2004range")
BOSPHORUS_KINDS = {"N": "neutral", "E": "expression", "LFAU": "expression", "UFAU": "expression",
                   "CAU": "expression", "YR": "pose", "PR": "pose", "CR": "pose", "O": "occlusion"}


class DatasetError(FaceRec3DError):
    """A dataset folder or manifest cannot be read."""


@dataclass(frozen=True)
class ScanRecord:
    """One scan of a dataset: where it is and who it is.

    expression: `neutral`, `non-neutral` or None when unknown.
    kind:       `neutral`, `expression`, `pose`, `occlusion` or None (Bosphorus-style category).
    label:      the finer label (Bosphorus TYPE_SUB, or a manifest's label).
    """

    path: Path
    subject: str
    scan_id: str
    expression: str | None = None
    kind: str | None = None
    label: str | None = None
    session: str | None = None
    role: str | None = None
    pose: str | None = None  # a manifest's head-pose label (e.g. front, left, up): its own probe subset


@dataclass(frozen=True)
class Dataset:
    """The scans of a dataset and the layout they were found in (`frgc`, `bosphorus`, `manifest`)."""

    records: tuple[ScanRecord, ...]
    layout: str
    source: Path

    def __len__(self) -> int:
        return len(self.records)

    def __iter__(self):
        return iter(self.records)

    @property
    def subjects(self) -> list[str]:
        return sorted({r.subject for r in self.records})

    @property
    def root(self) -> Path:
        """The folder scan paths are given relative to: the dataset folder, or a manifest's folder."""
        return self.source.parent if self.source.is_file() else self.source

    def label(self, record: ScanRecord) -> str:
        """The scan's label in score files and reports: its path relative to `root` (`/`-separated; absolute
        when outside it), unique where file stems are not (`s000/front_1.png` and `s001/front_1.png`), with
        white space percent-encoded so that it stays one field of a score file."""
        try:
            rel = record.path.relative_to(self.root).as_posix()
        except ValueError:
            rel = record.path.as_posix()
        return one_field(rel)


def one_field(text: str) -> str:
    """`text` as one field of a white-space separated score file: its white space and `%` percent-encoded as
    URLs are (UTF-8 bytes: "person a" -> "person%20a"), so that different texts stay different."""
    return re.sub(r"[\s%]", lambda m: quote(m[0], safe=""), text)


def open_dataset(source: str | Path) -> Dataset:
    """The dataset at `source`: a manifest CSV, or a folder in FRGC or Bosphorus layout (auto-detected).

    A folder holding `manifest.csv` is read through that manifest.
    """
    source = Path(source)
    if source.is_file():
        return read_manifest(source)
    if not source.is_dir():
        raise DatasetError(f"{source}: no such file or folder")
    if (source / "manifest.csv").is_file():
        return read_manifest(source / "manifest.csv")
    if (inside := _within_a_manifest(source)) is not None:
        return inside
    files = sorted(p for p in source.rglob("*") if p.is_file())
    frgc = [p for p in files if FRGC_PATTERN.match(p.name)]
    bos = [p for p in files if BOSPHORUS_PATTERN.match(p.name)]
    if frgc and len(frgc) >= len(bos):
        return Dataset(tuple(_frgc_record(p) for p in frgc), "frgc", source)
    if bos:
        return Dataset(tuple(_bosphorus_record(p) for p in bos), "bosphorus", source)
    raise DatasetError(f"{source}: no FRGC (<subject>d<seq>.abs) or Bosphorus (bsNNN_TYPE_SUB_k.bnt) scans found, and "
                       "no manifest.csv (other scans, depth frames among them: give the files themselves, or a "
                       "manifest.csv listing them with their subjects)")


def scan_record(path: str | Path) -> ScanRecord | None:
    """The record of one scan file named as in FRGC (`<subject>d<seq>.abs`) or Bosphorus (`bsNNN_TYPE_SUB_k.bnt`);
    None for other names."""
    path = Path(path)
    if FRGC_PATTERN.match(path.name):
        return _frgc_record(path)
    if BOSPHORUS_PATTERN.match(path.name):
        return _bosphorus_record(path)
    return None


def manifest_record(path: str | Path, levels: int = 3) -> ScanRecord | None:
    """The record of a scan file that a `manifest.csv` in its folder or in one of the `levels` folders above it
    lists (a `facerec3d synth --format png` or rap3df-style `<subject>/<frame>.png` layout: the frame's name does
    not say whose it is, its manifest does); None when no readable manifest lists it."""
    target = Path(path).resolve()
    for folder in list(target.parents)[:levels + 1]:
        manifest = folder / "manifest.csv"
        if manifest.is_file() and (record := _manifest_index(str(manifest), manifest.stat().st_mtime_ns).get(target)):
            return record
    return None


@lru_cache(maxsize=8)
def _manifest_index(manifest: str, mtime_ns: int) -> dict[Path, ScanRecord]:
    """A manifest's records by their resolved paths (read once per version of the file: enrolling a folder's frames
    one by one asks for each); empty when the manifest cannot be read."""
    try:
        return {r.path.resolve(): r for r in read_manifest(manifest).records}
    except DatasetError:
        return {}


def _frgc_session(path: Path) -> str | None:
    """The FRGC session folder (`Fall2003range`, ...) a file is in, or None."""
    return next((part for part in path.parts if part in FRGC_SESSIONS), None)


def _frgc_record(path: Path) -> ScanRecord:
    m = FRGC_PATTERN.match(path.name)
    return ScanRecord(path, m["subject"], f"{m['subject']}d{m['seq']}", session=_frgc_session(path))


def _bosphorus_record(path: Path) -> ScanRecord:
    m = BOSPHORUS_PATTERN.match(path.name)
    kind = BOSPHORUS_KINDS.get(m["type"].upper())
    expression = {"neutral": "neutral", "expression": "non-neutral"}.get(kind)
    return ScanRecord(path, m["subject"], path.stem, expression, kind, f"{m['type']}_{m['sub']}")


MANIFEST_SEARCH_DEPTH = 3  # parent folders searched for the manifest of a sub-folder given as a dataset


def _within_a_manifest(folder: Path) -> Dataset | None:
    """The scans under `folder` that the nearest manifest.csv of a folder above it lists (a person's folder of a
    depth-camera recording, `<subject>/front_1.png`, whose manifest is at the top), or None when no manifest above
    lists any."""
    here = folder.resolve()
    for parent in list(here.parents)[:MANIFEST_SEARCH_DEPTH]:
        if (parent / "manifest.csv").is_file():
            whole = read_manifest(parent / "manifest.csv")
            records = tuple(r for r in whole.records if Path(r.path).resolve().is_relative_to(here))
            return Dataset(records, whole.layout, folder) if records else None
    return None


def read_manifest(path: str | Path) -> Dataset:
    """A dataset from a manifest CSV (`path,subject[,expression][,role][,session][,label][,pose]`)."""
    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:  # -sig: a BOM (Excel's "CSV UTF-8") is no column name
            rows = list(csv.DictReader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise DatasetError(f"{path}: cannot read manifest ({e})") from None
    if not rows or not {"path", "subject"} <= set(rows[0]):
        raise DatasetError(f"{path}: a manifest needs a header with at least the columns path,subject")
    records = []
    seen: dict[Path, int] = {}  # each file's line: a file listed twice would be compared with itself
    for line, row in enumerate(rows, start=2):
        subject = (row.get("subject") or "").strip()
        if not (row.get("path") or "").strip() or not subject:
            raise DatasetError(f"{path}, line {line}: empty path or subject")
        p = Path(row["path"])
        p = p if p.is_absolute() else path.parent / p
        if (twice := seen.setdefault(p.resolve(), line)) != line:
            raise DatasetError(f"{path}, line {line}: {row['path']} is listed on line {twice} already (a scan "
                               "listed twice would be compared with itself)")
        label = row.get("label") or row.get("expression") or None
        expression = _expression_class(row.get("expression"))
        role = (row.get("role") or "").strip().lower() or None
        if role not in (None, "gallery", "probe"):
            raise DatasetError(f"{path}, line {line}: role must be gallery or probe, not {role!r}")
        kind = None if expression is None else ("neutral" if expression == "neutral" else "expression")
        if (typed := BOSPHORUS_KINDS.get((label or "").split("_")[0].upper())) is not None:
            # a Bosphorus scan type as the label (N_N, E_HAPPY, YR_R10): its category, as a bsNNN_TYPE_SUB_k name
            # gives it; the bosphorus protocol reads the category, so a file of any name can be typed so
            kind = typed
            expression = expression or {"neutral": "neutral", "expression": "non-neutral"}.get(typed)
        elif BOSPHORUS_PATTERN.match(p.name):
            named = _bosphorus_record(p)  # a Bosphorus file: its type and label from its name, as in its folder
            kind, label, expression = named.kind, named.label, expression or named.expression
        session = (row.get("session") or "").strip() or _frgc_session(p)
        records.append(ScanRecord(p, subject, scan_stem(p), expression, kind, label,
                                  session, role, (row.get("pose") or "").strip() or None))
    return Dataset(tuple(records), "manifest", path)


def _expression_class(value: str | None) -> str | None:
    """`neutral` / `non-neutral` from a manifest's expression column (any non-neutral label counts as such)."""
    value = (value or "").strip().lower()
    if not value:
        return None
    return "neutral" if value in ("neutral", "n", "blank") else "non-neutral"
