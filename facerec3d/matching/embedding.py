"""A learned 3D face embedding, run on the CPU with onnxruntime (`--method embedding`).

Each preprocessed face (§8.5: frontal, nose tip at the origin, on the 1 mm resampling grid) becomes a small
image of its depth and surface normals around the nose tip (`face_input`), which a compact convolutional network
maps to a unit vector (`EmbeddingModel`). Faces are registered once, by preprocessing; a comparison is then one
dot product (the cosine of the two embeddings), as in Spreeuwers (IET Biometrics 2015) or FR3DNet (Gilani &
Mian, CVPR 2018), instead of an ICP per pair.

The network is trained on the synthetic scanner's faces (`facerec3d train-embedding`, `training.embedding`: a
Led3D-style CNN on depth and normals with a CosFace margin loss) and saved as ONNX with a JSON *card* beside it
(`<model>.json`) that records the input recipe (window, cell, depth scale), the data recipe, the seed, the
epochs, the loss and the validation figures. The input recipe travels with the model, so a model trained on
another window is fed the window it was trained on. The package ships one model (`SHIPPED_MODEL`, MIT); users'
installs need onnxruntime only, never PyTorch.

A camera the network never saw varies a person's embeddings in its own ways: `adapt = "wccn"` learns them from
scans of other people taken by that camera (`fit`, `--train`) and shrinks them (`wccn`), before the cosine.

Input channels (`face_input`), each (n, n) on a `step_mm` grid over ±`half_width_mm` around the nose tip:
  0. depth z / depth_scale_mm, missing cells filled with their nearest seen cell (scipy distance transform);
  1–3. the unit normal (n_x, n_y, n_z) of that depth map (central differences), 0 where nothing was seen;
  4. the validity mask (1 where the camera saw the face).
A cell is the mean of the seen 1 mm cells under it (averaging `step_mm`² cells cuts sensor noise).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from facerec3d.errors import FaceRec3DError, InputError
from facerec3d.matching.base import Matcher, Template, check_face, check_training, learnt_arrays
from facerec3d.matching.depthmap import fill_nearest
from facerec3d.models import onnx_session
from facerec3d.preprocess.resample import ResampleConfig, depth_map
from facerec3d.scan import MIRRORED, FaceScan

#: The model the package ships: trained on synthetic faces only (`facerec3d train-embedding`), MIT.
SHIPPED_MODEL = Path(__file__).resolve().parent.parent / "models" / "embedding.onnx"
N_CHANNELS = 5


@dataclass(frozen=True)
class InputRecipe:
    """How a preprocessed face becomes the network's input (recorded in the model's card)."""

    half_width_mm: float = 64.0  # the window is [−w, w)² mm around the nose tip: the face inside the 95 mm crop
    step_mm: float = 2.0  # input cell: the mean of step² 1 mm cells (Led3D feeds 128² crops of similar faces)
    depth_scale_mm: float = 50.0  # depth is divided by this (a face is ~100 mm deep): values of order 1

    @property
    def size(self) -> int:
        """Cells along each side of the input image."""
        return int(round(2 * self.half_width_mm / self.step_mm))

    def __post_init__(self) -> None:
        if self.step_mm <= 0 or self.half_width_mm <= 0 or self.depth_scale_mm <= 0:
            raise ValueError("half_width_mm, step_mm and depth_scale_mm must be positive")
        if abs(self.half_width_mm / self.step_mm - round(self.half_width_mm / self.step_mm)) > 1e-9:
            raise ValueError("half_width_mm must be a multiple of step_mm")


def seen_depth(scan: FaceScan, grid: ResampleConfig = ResampleConfig()) -> np.ndarray:
    """(size, size) depth z (mm) of a preprocessed face on the resampling grid, NaN where the camera saw nothing
    (cells mirrored by symmetry completion are left out: the network learnt faces as cameras see them)."""
    z, _ = depth_map(scan, grid)
    if scan.provenance is not None and (scan.provenance == MIRRORED).any():
        mirrored = scan.grid[scan.provenance == MIRRORED]
        z = z.copy()
        z[mirrored[:, 0], mirrored[:, 1]] = np.nan
    return z


def window_depth(z: np.ndarray, recipe: InputRecipe, grid: ResampleConfig = ResampleConfig(),
                 margin: int = 0) -> np.ndarray:
    """The input window (size + 2·margin cells a side, step_mm cells) of a depth image on the resampling grid:
    each cell the mean of the seen grid cells under it, NaN where none was seen. `margin` extra cells on each
    side let training shift the window (simulated alignment error)."""
    k = int(round(recipe.step_mm / grid.resolution_mm))
    if abs(recipe.step_mm / grid.resolution_mm - k) > 1e-9 or k < 1:
        raise FaceRec3DError(f"input step {recipe.step_mm} mm is not a multiple of the grid's "
                             f"{grid.resolution_mm} mm cell")
    n = recipe.size + 2 * margin
    centre = (grid.size - 1) // 2
    first = centre - (n // 2) * k
    rows = np.arange(first, first + n * k)
    inside = (rows >= 0) & (rows < grid.size)
    window = np.full((n * k, n * k), np.nan)
    idx = rows[inside]
    window[np.ix_(inside, inside)] = z[np.ix_(idx, idx)]
    blocks = window.reshape(n, k, n, k)
    seen = np.isfinite(blocks)
    count = seen.sum(axis=(1, 3))
    total = np.where(seen, blocks, 0.0).sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def input_channels(window: np.ndarray, recipe: InputRecipe) -> np.ndarray:
    """(N_CHANNELS, n, n) float32 network input of a window of depth (mm, NaN where unseen): module docstring."""
    valid = np.isfinite(window)
    z = fill_nearest(window)
    dzr, dzc = np.gradient(z, recipe.step_mm)  # rows, columns
    normal = np.stack([-dzc, dzr, np.ones_like(z)])  # rows run along −y on the resampling grid
    normal /= np.linalg.norm(normal, axis=0, keepdims=True)
    out = np.empty((N_CHANNELS, *z.shape), dtype=np.float32)
    out[0] = z / recipe.depth_scale_mm
    out[1:4] = normal * valid
    out[4] = valid
    return out


def face_from_points(points: np.ndarray, grid: ResampleConfig = ResampleConfig()) -> FaceScan:
    """A preprocessed face rebuilt from its points alone (an ICP template keeps those): each point put in the
    resampling grid's cell under it (the points of a preprocessed face lie on that grid)."""
    p = np.asarray(points, dtype=np.float64)
    centre = (grid.size - 1) // 2
    col = np.rint(p[:, 0] / grid.resolution_mm).astype(np.int64) + centre
    row = centre - np.rint(p[:, 1] / grid.resolution_mm).astype(np.int64)
    ok = (row >= 0) & (row < grid.size) & (col >= 0) & (col < grid.size)
    return FaceScan(p[ok], grid=np.stack([row[ok], col[ok]], axis=1), grid_shape=(grid.size, grid.size))


def face_input(scan: FaceScan, recipe: InputRecipe = InputRecipe()) -> np.ndarray:
    """The network input of a preprocessed face: `input_channels` of its `window_depth`."""
    return input_channels(window_depth(seen_depth(scan), recipe), recipe)


class EmbeddingModel:
    """An ONNX face-embedding network and its card, run with onnxruntime (one thread: the engine runs processes).

    `embed(inputs (N, C, n, n))` returns (N, dim) unit vectors."""

    def __init__(self, path: str | Path = SHIPPED_MODEL, threads: int = 1) -> None:
        self.path = Path(path)
        self.card = read_card(self.path)
        self.recipe = InputRecipe(**self.card.get("input", {}))
        self.threads = threads
        self._session: Any = None

    def __getstate__(self) -> dict:
        """Sent to worker processes without the onnxruntime session (each process opens its own)."""
        return {**self.__dict__, "_session": None}

    @property
    def session(self) -> Any:
        if self._session is None:
            self._session = onnx_session(self.path, "embedding model", self.threads)
            shape = self._session.get_inputs()[0].shape
            wanted = [N_CHANNELS, self.recipe.size, self.recipe.size]
            if len(shape) != 4 or [d if isinstance(d, int) else None for d in shape[1:]] != wanted:
                self._session = None
                raise FaceRec3DError(f"{self.path}: not a usable ONNX embedding model (it takes input {shape[1:]}, "
                                     f"its card {card_path(self.path).name} says {wanted})")
        return self._session

    def embed(self, inputs: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(inputs, dtype=np.float32)
        if x.ndim != 4 or x.shape[1:] != (N_CHANNELS, self.recipe.size, self.recipe.size):
            raise FaceRec3DError(f"{self.path}: input of shape {x.shape[1:]}, the model takes "
                                 f"{(N_CHANNELS, self.recipe.size, self.recipe.size)}")
        session = self.session
        e = session.run(None, {session.get_inputs()[0].name: x})[0].astype(np.float32)
        return e / np.maximum(np.linalg.norm(e, axis=1, keepdims=True), 1e-12)


def card_path(model: str | Path) -> Path:
    """The JSON card beside an ONNX model: `embedding.onnx` → `embedding.json`."""
    return Path(model).with_suffix(".json")


def read_card(model: str | Path) -> dict[str, Any]:
    """A model's card (input recipe, data recipe, training figures); one clear error when missing or broken."""
    model, card = Path(model), card_path(model)
    if not model.is_file():
        raise FaceRec3DError(f"{model}: no such embedding model (train one with facerec3d train-embedding)")
    try:
        data = json.loads(card.read_text())
        if not isinstance(data, dict):
            raise ValueError("not a JSON object")
        InputRecipe(**data.get("input", {}))
    except (OSError, ValueError, TypeError) as e:
        raise FaceRec3DError(f"{card}: not a usable model card ({e})") from None
    return data


ADAPTATIONS = ("none", "wccn")


@dataclass(frozen=True)
class EmbeddingConfig:
    """Learned-embedding matcher settings."""

    model: str = ""  # ONNX model path; "": the shipped model (SHIPPED_MODEL)
    threads: int = 1  # onnxruntime threads per process (the engine already runs one process per core)
    adapt: str = "none"  # "wccn": adapt the embeddings to a camera with scans of other people taken by it (`--train`:
    #                      several scans a person), by within-class covariance normalisation (`wccn`)
    wccn_ridge: float = 1.0  # ρ of `wccn`, relative to the mean within-person variance; 1.0 chosen by two-fold
    #                          cross-validation within the rap3df-2019 tuning half (0.1–10 tried; docs/embedding.md)

    def __post_init__(self) -> None:
        if self.threads < 1:
            raise ValueError("threads must be ≥ 1")
        if self.adapt not in ADAPTATIONS:
            raise ValueError(f"adapt must be one of {', '.join(ADAPTATIONS)}")
        if not self.wccn_ridge > 0:
            raise ValueError("wccn_ridge must be > 0")


def wccn(embeddings: np.ndarray, subjects: Sequence[str], ridge: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Within-class covariance normalisation (Hatch, Kajarekar & Stolcke, ICSLP 2006): (mean (d,), W (d, d)) such
    that x ↦ W (x − mean) whitens the spread of a person's embeddings about their own mean (S_w, pooled over the
    subjects with two or more scans), S_w regularised by ρ = `ridge` × its mean eigenvalue: W = (S_w + ρ I)^(-1/2).
    Directions in which a camera's scans of one person vary (noise, pose, what the synthetic training never showed)
    are shrunk, those in which people differ are kept; the cosine is then taken of the whitened vectors."""
    E = np.asarray(embeddings, dtype=np.float64)
    labels = np.asarray(subjects)
    groups = [E[labels == s] for s in dict.fromkeys(labels.tolist())]
    deviations = [g - g.mean(axis=0) for g in groups if len(g) > 1]
    if len(deviations) < 2:
        raise InputError("adapting the embedding (wccn) needs two or more subjects with two or more scans each "
                         f"(given {len(groups)} subjects, {len(deviations)} with two or more scans)")
    D = np.concatenate(deviations)
    Sw = D.T @ D / len(D)
    rho = ridge * np.trace(Sw) / len(Sw)
    w, V = np.linalg.eigh(Sw + rho * np.eye(len(Sw)))
    return E.mean(axis=0), (V / np.sqrt(w)) @ V.T


class EmbeddingMatcher(Matcher[np.ndarray]):
    """Faces compared by the cosine of their learned embeddings (module docstring)."""

    name = "embedding"
    config_class = EmbeddingConfig

    def __init__(self, config: EmbeddingConfig | None = None) -> None:
        self.config = EmbeddingConfig() if config is None else config
        self.model = EmbeddingModel(self.config.model or SHIPPED_MODEL, self.config.threads)
        self.wccn_: tuple[np.ndarray, np.ndarray] | None = None  # (mean, W) learnt by `fit` when adapt = "wccn"
        self._stacked: tuple[tuple[Template, ...], np.ndarray] | None = None

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_stacked": None}

    @property
    def needs_training(self) -> bool:
        return self.config.adapt != "none"

    def fit(self, scans: Sequence[FaceScan], subjects: Sequence[str]) -> EmbeddingMatcher:
        """adapt = "wccn": learn the camera's within-person spread from its scans of other people (`wccn`)."""
        if self.needs_training:
            check_training(scans, subjects, self.name)
            self.wccn_ = wccn(self.network_embed(scans), subjects, self.config.wccn_ridge)
        return self

    def state(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        return ({}, {}) if self.wccn_ is None else ({"wccn_mean": self.wccn_[0], "wccn_matrix": self.wccn_[1]}, {})

    def set_state(self, arrays: Mapping[str, np.ndarray], attrs: Mapping[str, Any]) -> None:
        if arrays:
            dim = self.model.card.get("embedding_dim")  # the network's, when its card says
            sizes = {"d": dim} if isinstance(dim, int) and not isinstance(dim, bool) else {}
            mean, W = learnt_arrays(arrays, {"wccn_mean": ("d",), "wccn_matrix": ("d", "d")}, **sizes)
            self.wccn_ = mean, W

    def network_embed(self, scans: Sequence[FaceScan]) -> np.ndarray:
        """(N, dim) the network's unit embeddings of preprocessed faces, in one batch (no adaptation)."""
        if not scans:
            return np.zeros((0, int(self.model.card.get("embedding_dim", 0))), dtype=np.float32)
        return self.model.embed(np.stack([face_input(s, self.model.recipe) for s in scans]))

    def embed(self, scans: Sequence[FaceScan]) -> np.ndarray:
        """(N, dim) unit embeddings of preprocessed faces, in one batch: the network's, adapted to the camera
        (x ↦ W (x − mean), normalised again) once `fit` has learnt the adaptation."""
        e = self.network_embed(scans)
        if self.needs_training:
            if self.wccn_ is None:
                raise FaceRec3DError("the embedding's adaptation (adapt = \"wccn\") is not learnt: give scans of "
                                     "the camera (--train DATA) or a saved model (--model FILE)")
            mean, W = self.wccn_
            if len(mean) != e.shape[1]:
                raise FaceRec3DError(f"embedding adaptation for {len(mean)} values, the model gives {e.shape[1]}: "
                                     "learnt with another model")
            a = (e - mean) @ W
            e = (a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)).astype(np.float32)
        return e

    def enroll(self, scan: FaceScan) -> Template:
        check_face(scan)
        return Template(scan.meta.subject, scan.meta.scan_id, self.name, {"embedding": self.embed([scan])[0]},
                        {"model": self.model.card.get("name", self.model.path.name)})

    def prepare(self, scan: FaceScan) -> np.ndarray:
        check_face(scan)
        return self.embed([scan])[0]

    def _gallery(self, templates: Sequence[Template]) -> np.ndarray:
        key = tuple(templates)
        if self._stacked is None or len(self._stacked[0]) != len(key) or any(
                a is not b for a, b in zip(self._stacked[0], key)):
            rows = [t.arrays.get("embedding") for t in templates]
            if any(r is None or r.shape != rows[0].shape for r in rows):
                raise FaceRec3DError("gallery templates are not embeddings of one model: enrol them again "
                                     "with --method embedding")
            self._stacked = key, np.stack(rows).astype(np.float32) if rows else np.zeros((0, 0), np.float32)
        return self._stacked[1]

    def scores(self, probe: FaceScan | np.ndarray, templates: Sequence[Template]) -> tuple[np.ndarray, None]:
        p = self._probe(probe, templates)
        if not templates:
            return np.zeros(0), None
        G = self._gallery(templates)
        if G.shape[1] != p.shape[0]:
            raise FaceRec3DError(f"probe embedding of {p.shape[0]} values, gallery of {G.shape[1]}: "
                                 "the gallery was enrolled with another model")
        return (G @ p).astype(np.float64), None

    def score(self, probe: FaceScan | np.ndarray, template: Template) -> float:
        return float(self.scores(probe, [template])[0][0])

