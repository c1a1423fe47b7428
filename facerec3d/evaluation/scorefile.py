"""Score files in the formats of Idiap's bob framework.

facerec3d writes the 4-column text format, one comparison per line, fields
separated by white space::

    claimed_id real_id probe_label score

claimed_id is the gallery subject compared against, real_id the probe's true
subject, probe_label the probe scan's id, score the similarity (higher = more
similar). A gallery subject with several templates gives several lines for
the same probe. A comparison is genuine when claimed_id == real_id.

`read_score_matrix` also reads bob's 5-column format (``claimed_id
model_label real_id probe_label score``, the template named) and bob 5's CSV
score files (a header naming ``probe_subject_id`` or ``probe_subject``,
``probe_template_id`` / ``probe_reference_id`` / ``probe_key``,
``bio_ref_subject_id`` or ``bio_ref_subject``, optionally
``bio_ref_template_id`` / ``bio_ref_reference_id``, and ``score``; other
columns are ignored), so any system's scores can be evaluated.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import NamedTuple

import numpy as np

from facerec3d.datasets.catalog import one_field
from facerec3d.errors import InputError, SettingsError


class ScoreRows(NamedTuple):
    """The columns of a score file, one element per line."""

    claimed_id: np.ndarray  # str
    real_id: np.ndarray  # str
    probe_label: np.ndarray  # str
    score: np.ndarray  # float64


def _fields(values: Sequence, what: str) -> list[str]:
    """Labels as fields of the white-space separated format (`one_field`: "person a" -> "person%20a"); an empty one
    is refused."""
    out = [one_field(str(v)) for v in values]
    for v in out:
        if not v:
            raise ValueError(f"{what} is empty")
    return out


def write_scores(path: str | Path, S, probe_ids: Sequence, probe_labels: Sequence, gallery_ids: Sequence) -> int:
    """Write score matrix S (n_probes, n_gallery) as a 4-column score file.

    probe_ids are the probes' true subjects, probe_labels their scan ids,
    gallery_ids the gallery templates' subjects. NaN scores (comparisons not
    made) are skipped. Scores are written in shortest round-trip form. Returns
    the number of lines written.
    """
    S = np.asarray(S, dtype=float)
    if S.ndim != 2:
        raise ValueError(f"score matrix must be 2-D, got shape {S.shape}")
    real = _fields(probe_ids, "probe id")
    labels = _fields(probe_labels, "probe label")
    claimed = _fields(gallery_ids, "gallery id")
    if (len(real), len(claimed)) != S.shape or len(labels) != len(real):
        raise ValueError(
            f"score matrix {S.shape} does not match {len(real)} probe ids, "
            f"{len(labels)} probe labels and {len(claimed)} gallery ids"
        )
    n = 0
    with open(path, "w", encoding="utf-8") as f:
        for i, row in enumerate(S.tolist()):
            lines = [f"{c} {real[i]} {labels[i]} {s!r}\n" for c, s in zip(claimed, row) if s == s]
            f.writelines(lines)
            n += len(lines)
    return n


def read_score_rows(path: str | Path) -> ScoreRows:
    """All lines of a 4-column score file as columns; blank lines are skipped.

    Raises ValueError naming the file and line on a malformed line.
    """
    claimed, real, label, score = _read_columns(path, 4)
    return ScoreRows(claimed, real, label, score)


def _read_columns(path: str | Path, n: int) -> list[np.ndarray]:
    """The n white-space separated columns of a score file (str, the last float); blank lines skipped."""
    cols: list[list] = [[] for _ in range(n)]
    with text_file(path) as f:
        for line_no, line in enumerate(f, 1):
            parts = line.split()
            if not parts:
                continue
            try:
                if len(parts) != n:
                    raise ValueError(f"expected {n} fields, got {len(parts)}")
                parts[-1] = float(parts[-1])
                if parts[-1] != parts[-1]:  # NaN: no comparison (−inf, a match not found, is a score)
                    raise ValueError(f"the score {parts[-1]} is not a number")
            except ValueError as e:
                raise InputError(f"{path}:{line_no}: {e}") from None
            for col, value in zip(cols, parts):
                col.append(value)
    return [np.array(c, dtype=str) for c in cols[:-1]] + [np.array(cols[-1], dtype=float)]


@contextmanager
def text_file(path: str | Path, newline: str | None = None):
    """A score file (or a run's CSV file) opened as UTF-8 text, a byte-order mark (Excel's "CSV UTF-8") skipped; a
    byte that is not UTF-8, or a line the csv module cannot read inside the block (a field over its limit, a NUL
    byte), is one InputError naming the file."""
    try:
        with open(path, encoding="utf-8-sig", newline=newline) as f:
            yield f
    except UnicodeDecodeError as e:
        raise InputError(f"{path}: not UTF-8 text (a byte {e.object[e.start:e.start + 1]!r}): save it as UTF-8") \
            from None
    except csv.Error as e:
        raise InputError(f"{path}: not a readable CSV file ({e})") from None
    except OSError as e:  # missing, a folder, no permission
        raise InputError(f"{path}: cannot read ({e.strerror or type(e).__name__})") from None


def read_scores(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """The (genuine, impostor) scores of a 4-column score file, in file order."""
    rows = read_score_rows(path)
    same = rows.claimed_id == rows.real_id
    return rows.score[same], rows.score[~same]


SCORE_FORMATS = ("bob4", "bob5", "csv")
CSV_COLUMNS = {  # role -> accepted column names of a bob CSV score file, first found wins
    "real_id": ("probe_subject_id", "probe_subject"),
    "probe_label": ("probe_template_id", "probe_reference_id", "probe_key"),
    "claimed_id": ("bio_ref_subject_id", "bio_ref_subject"),
    "model_label": ("bio_ref_template_id", "bio_ref_reference_id"),
}


class ScoreMatrix(NamedTuple):
    """A score file as a matrix: rows are probes (in order of first appearance), columns gallery templates."""

    S: np.ndarray  # (n_probes, n_templates), NaN where the file has no comparison
    probe_ids: np.ndarray  # str: each probe's subject
    probe_labels: np.ndarray  # str
    gallery_ids: np.ndarray  # str: each template's subject
    template_labels: np.ndarray | None = None  # str: each template's label (model_label; bob4: k for the k-th)


def _csv_columns(path: str | Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray, np.ndarray]:
    with text_file(path, newline="") as f:
        reader = csv.DictReader(f)
        header = reader.fieldnames or []
        chosen = {role: next((c for c in names if c in header), None) for role, names in CSV_COLUMNS.items()}
        missing = [f"{role} ({' or '.join(CSV_COLUMNS[role])})" for role, c in chosen.items()
                   if c is None and role != "model_label"] + ([] if "score" in header else ["score"])
        if missing:
            raise InputError(f"{path}: not a bob CSV score file: no column for {', '.join(missing)}")
        rows = []
        for r in reader:  # an empty id would be a subject or probe called "" (and no field of bob4)
            if empty := next((c for role, c in chosen.items() if role != "model_label" and not r[c]), None):
                raise InputError(f"{path}:{reader.line_num}: the {empty} field is empty")
            rows.append(r)
    try:
        score = np.array([float(r["score"]) for r in rows])
    except (TypeError, ValueError) as e:
        raise InputError(f"{path}: a score is not a number ({e})") from None
    col = {role: None if c is None else np.array([r[c] for r in rows], dtype=str) for role, c in chosen.items()}
    return col["claimed_id"], col["model_label"], col["real_id"], col["probe_label"], score


def _first_order(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct values in order of first appearance, and each element's index among them."""
    distinct, first, index = np.unique(values, return_index=True, return_inverse=True)
    order = np.argsort(first)
    position = np.empty_like(order)
    position[order] = np.arange(order.size)
    return distinct[order], position[index]


def read_score_matrix(path: str | Path, fmt: str = "bob4", higher_is_better: bool = True) -> ScoreMatrix:
    """A score file (`SCORE_FORMATS`) as a score matrix, similarities (negated when not higher_is_better).

    A probe is a probe label; a gallery template is (claimed_id, model_label),
    or in the 4-column format (claimed_id, k) for the k-th line of that probe
    with that claimed_id (templates of one subject are told apart by order,
    which leaves every figure unchanged: a subject scores its best template).
    Comparisons missing from the file are NaN. Raises ValueError on a probe
    label with two subjects or a comparison given twice.
    """
    if fmt == "bob4":
        claimed, real, label, score = _read_columns(path, 4)
        model = None
    elif fmt == "bob5":
        claimed, model, real, label, score = _read_columns(path, 5)
    elif fmt == "csv":
        claimed, model, real, label, score = _csv_columns(path)
    else:
        raise InputError(f"unknown score format {fmt!r}: use one of {', '.join(SCORE_FORMATS)}")
    if score.size == 0:
        raise InputError(f"{path}: no scores")
    labels, row = _first_order(label)
    subjects = real[np.unique(row, return_index=True)[1]]
    clash = subjects[row] != real
    if clash.any():
        first = np.flatnonzero(clash)[0]
        raise InputError(f"{path}: probe label {str(label[first])!r} has two subjects ({str(subjects[row][first])!r}, "
                         f"{str(real[first])!r}): each probe needs its own label (e.g. its path)")
    if model is None:  # the k-th line of a (probe, claimed subject): its k-th template
        _, pair = np.unique(np.stack([row.astype(str), claimed], axis=1), axis=0, return_inverse=True)
        order = np.argsort(pair, kind="stable")
        starts = np.flatnonzero(np.r_[True, np.diff(pair[order]) != 0])
        pair = pair.ravel()
        occurrence = np.empty(pair.size, int)
        occurrence[order] = np.arange(pair.size) - np.repeat(starts, np.diff(np.r_[starts, pair.size]))
        model = occurrence.astype(str)
    templates, col = np.unique(np.stack([claimed, model], axis=1), axis=0, return_inverse=True)
    col = col.ravel()
    cell = row * len(templates) + col
    if np.unique(cell).size < cell.size:
        twice = np.flatnonzero(np.bincount(cell)[cell] > 1)[0]
        raise InputError(f"{path}: probe {str(label[twice])!r} is compared twice with {str(claimed[twice])!r} "
                         f"{str(model[twice])!r}")
    S = np.full((labels.size, len(templates)), np.nan)
    S[row, col] = score if higher_is_better else -score
    return ScoreMatrix(S, subjects, labels, templates[:, 0], templates[:, 1])


def strangers_file(path: str | Path) -> Path:
    """The file beside a score file holding its impostor pairs scored as strangers' claims (`scores.txt`:
    `scores.strangers.txt`), as `evaluate` and `fuse` write it for scores normalised over the gallery."""
    path = Path(path)
    return path.with_name(f"{path.stem}.strangers{path.suffix}")


def fuse_score_files(paths: Sequence[str | Path], fmt: str = "bob4", rule: str = "sum",
                     normalisation: str = "z-score", weights: Sequence[float] = (),
                     top: int = 0, cohort: float = 0.0) -> tuple[ScoreMatrix, int, ScoreMatrix]:
    """Score-level fusion of several systems' score files (chapter §8.10; `matching.normalisation.fuse`, what the
    `fusion` method computes from its members' scores): each probe's scores of each file normalised over the
    gallery templates it was compared with, then combined by `rule`, and `cohort` × the best other person's fused
    score taken off (`normalisation.minus_best_other`; 0: the plain combination); InputError when the files share
    none. Probes are matched by label, templates by (subject, label). Returns the fused matrix, the number of
    comparisons left out because some file lacks them (a comparison is fused only where every file has it; a score
    of −inf, a match not found, counts as that probe's worst), and the strangers' matrix: each probe's impostor
    pairs fused over the gallery without the probe's person, as a stranger's claim meets it
    (`matching.base.scores_over`; its own person's comparisons NaN). Raises InputError naming the file when the
    files disagree on a probe's subject, and the fusion method's errors for its settings (SettingsError naming
    `weights` or `top` out of range, InputError otherwise: weights with a rule that ignores them too). The
    strangers' scores are exact where the files' own scores do not depend
    on the gallery (icp, the embedding); a file of a method normalised over the gallery itself (region ICP) keeps
    the normalisation it was written with (on rap3df-2019 the default's EER for strangers over all 80 people reads
    11.5 % so, 11.6 % from the fusion method)."""
    from facerec3d.matching.fusion import FusionConfig
    from facerec3d.matching.normalisation import fuse, minus_best_other

    if len(paths) < 2:
        raise InputError("fusion needs at least two score files")
    try:  # the checks of the fusion method's settings (ranges: SettingsError naming the field)
        FusionConfig(members=tuple(map(str, paths)), normalisation=normalisation, rule=rule, weights=tuple(weights),
                     top=top, cohort=cohort)
    except SettingsError:
        raise
    except ValueError as e:
        raise InputError(str(e)) from None
    mats = [read_score_matrix(p, fmt) for p in paths]
    first = mats[0]
    probes = {str(label): i for i, label in enumerate(first.probe_labels)}
    templates = {(str(g), str(t)): j for j, (g, t) in enumerate(zip(first.gallery_ids, first.template_labels))}
    stack = np.full((len(mats), len(probes), len(templates)), np.nan)
    stack[0] = first.S
    for k, (path, m) in enumerate(zip(paths[1:], mats[1:]), 1):
        rows = np.array([probes.get(str(label), -1) for label in m.probe_labels])
        cols = np.array([templates.get((str(g), str(t)), -1) for g, t in zip(m.gallery_ids, m.template_labels)])
        clash = [(i, label, subject) for i, label, subject in zip(rows, m.probe_labels, m.probe_ids)
                 if i >= 0 and first.probe_ids[i] != subject]
        if clash:
            i, label, subject = clash[0]
            raise InputError(f"{path}: probe {str(label)!r} is subject {str(subject)!r} here and "
                             f"{str(first.probe_ids[i])!r} in {paths[0]}")
        keep_r, keep_c = rows >= 0, cols >= 0
        stack[k][np.ix_(rows[keep_r], cols[keep_c])] = m.S[np.ix_(keep_r, keep_c)]
    made = ~np.isnan(stack).any(axis=0)
    if not made.any():
        seen = ~np.isnan(stack)
        alone = next((k for k in range(1, len(paths)) if not (seen[0] & seen[k]).any()), None)
        raise InputError(f"{paths[alone]}: shares no comparison with {paths[0]} (other probes or gallery faces): "
                         "nothing to fuse" if alone is not None else
                         f"{', '.join(map(str, paths))}: no comparison is in every file (each shares some with "
                         f"{paths[0]}, but not the same ones): nothing to fuse")
    left_out = sum(int((~np.isnan(m.S)).sum()) for m in mats) - len(mats) * int(made.sum())
    people = np.asarray(first.gallery_ids)

    def fused_over(made: np.ndarray) -> ScoreMatrix:
        fused = np.full(made.shape, np.nan)
        for i in np.flatnonzero(made.any(axis=1)):
            cols = np.flatnonzero(made[i])
            score, tiebreak = fuse(stack[:, i, cols], rule, normalisation, weights, top)
            score = minus_best_other(score, people[cols], cohort)
            # consensus: whole votes, ties broken by the Borda count (below one vote), as the matchers rank
            fused[i, cols] = score if tiebreak is None else score + tiebreak / (tiebreak.max() + 1.0)
        return ScoreMatrix(fused, first.probe_ids, first.probe_labels, first.gallery_ids, first.template_labels)

    others = people.astype(str)[None, :] != np.asarray(first.probe_ids).astype(str)[:, None]
    return fused_over(made), left_out, fused_over(made & others)
