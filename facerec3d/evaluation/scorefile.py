"""Score files in the 4-column text format of Idiap's bob framework.

One comparison per line, fields separated by white space::

    claimed_id real_id probe_label score

claimed_id is the gallery subject compared against, real_id the probe's true
subject, probe_label the probe scan's id, score the similarity (higher = more
similar). A gallery subject with several templates gives several lines for
the same probe. A comparison is genuine when claimed_id == real_id.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np


class ScoreRows(NamedTuple):
    """The columns of a score file, one element per line."""

    claimed_id: np.ndarray  # str
    real_id: np.ndarray  # str
    probe_label: np.ndarray  # str
    score: np.ndarray  # float64


def _fields(values: Sequence, what: str) -> list[str]:
    """Labels as str, refusing ones that would break the white-space separated format."""
    out = [str(v) for v in values]
    for v in out:
        if not v or any(c.isspace() for c in v):
            raise ValueError(f"{what} {v!r} is empty or contains white space")
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
    cols: tuple[list, list, list, list] = ([], [], [], [])
    with open(path, encoding="utf-8") as f:
        for n, line in enumerate(f, 1):
            parts = line.split()
            if not parts:
                continue
            try:
                if len(parts) != 4:
                    raise ValueError(f"expected 4 fields, got {len(parts)}")
                score = float(parts[3])
            except ValueError as e:
                raise ValueError(f"{path}:{n}: {e}") from None
            for col, value in zip(cols, (*parts[:3], score)):
                col.append(value)
    return ScoreRows(*(np.array(c, dtype=str) for c in cols[:3]), np.array(cols[3], dtype=float))


def read_scores(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """The (genuine, impostor) scores of a 4-column score file, in file order."""
    rows = read_score_rows(path)
    same = rows.claimed_id == rows.real_id
    return rows.score[same], rows.score[~same]
