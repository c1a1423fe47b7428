"""Training the learned embedding (`facerec3d train-embedding`; PyTorch, the `[train]` extra only).

The network (`EmbeddingNet`) is a compact Led3D-style CNN (Mu et al., "Led3D: a lightweight and efficient deep
approach to recognizing low-quality 3D faces", CVPR 2019) on depth and normals: four blocks of two 3 × 3
convolutions with batch norm and ReLU, each halving the image, then batch norm, dropout and a linear layer to the
embedding (the ArcFace paper's "BN-Dropout-FC-BN" output). It is trained with the CosFace large-margin cosine
loss (Wang et al., CVPR 2018): logits s·(cos θ_y − m) for the true identity, s·cos θ_j for the others.

Augmentation on top of what the synthetic scanner and preprocessing already give (`augment`, NumPy): the window
shifted by up to `margin` cells (alignment error), mirrored left–right half of the time, turned in the image
plane (roll residue, σ 4°, half of the time), tilted (yaw / pitch residue, σ 4°), depth noise, a missing side
(self-occlusion beyond the data's poses), a missing patch (occluders) and, with `terraces`, the ripple of coarse
depth steps.

Output: `OUT` (ONNX, opset 18; 17 with a torch before 2.5), `OUT` with `.json` (the card: input and data recipes, seed, epochs, loss and
validation figures) and `.weights.npz` (the weights as plain arrays, no pickle: `--init` fine-tunes from them).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from facerec3d.errors import FaceRec3DError
from facerec3d.matching.embedding import N_CHANNELS, InputRecipe, card_path, input_channels

try:
    import torch
    from torch import nn
except ImportError:  # pragma: no cover - the [train] extra
    raise FaceRec3DError("training an embedding needs PyTorch: pip install 'facerec3d[train]'") from None
try:  # the ONNX exporter's own needs, checked before hours of training rather than after
    import onnx  # noqa: F401
    import onnxscript  # noqa: F401
except ImportError as e:  # pragma: no cover - the [train] extra
    raise FaceRec3DError(f"exporting a trained embedding needs {e.name}: pip install 'facerec3d[train]'") from None


@dataclass(frozen=True)
class TrainConfig:
    """Network and optimisation settings (`train-embedding` options)."""

    width: int = 24  # channels of the first block (then ×2 per block): embedding stays near 1 ms per face
    dim: int = 128  # embedding size
    epochs: int = 40
    batch: int = 64
    lr: float = 2e-3  # AdamW, cosine decay to zero
    weight_decay: float = 5e-4
    scale: float = 30.0  # CosFace s
    margin: float = 0.35  # CosFace m
    dropout: float = 0.2
    seed: int = 0
    threads: int = 2  # torch CPU threads
    validation_share: float = 0.1  # share of the identities kept out of training for the card's figures
    terraces: float = 0.0  # share of the windows given depth terraces (`augment`); 0: the shipped model's recipe


class EmbeddingNet(nn.Module):
    """Four conv blocks (width, 2w, 4w, 8w channels; each two 3×3 conv + BN + ReLU and a 2×2 max pool), then
    BN, dropout, a linear layer to `dim` and BN."""

    def __init__(self, size: int, width: int = 16, dim: int = 128, dropout: float = 0.2) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        cin = N_CHANNELS
        for k in range(4):
            cout = width * 2**k
            layers += [nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
                       nn.Conv2d(cout, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
                       nn.MaxPool2d(2)]
            cin = cout
        self.features = nn.Sequential(*layers)
        side = size // 16
        self.head = nn.Sequential(nn.BatchNorm2d(cin), nn.Dropout(dropout), nn.Flatten(),
                                  nn.Linear(cin * side * side, dim), nn.BatchNorm1d(dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(x))


class CosFace(nn.Module):
    """Large-margin cosine loss (CosFace): cross-entropy of s·(cos θ − m·onehot)."""

    def __init__(self, dim: int, classes: int, scale: float, margin: float) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.randn(classes, dim) * 0.01)
        self.scale, self.margin = scale, margin

    def forward(self, embedding: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        cos = nn.functional.normalize(embedding) @ nn.functional.normalize(self.weight).T
        logits = self.scale * (cos - self.margin * nn.functional.one_hot(labels, cos.shape[1]))
        return nn.functional.cross_entropy(logits, labels)


def augment(windows: np.ndarray, rng: np.random.Generator, recipe: InputRecipe, margin: int,
            train: bool = True, terraces: float = 0.0) -> np.ndarray:
    """(B, C, n, n) network inputs of windows with a margin (B, n + 2·margin, …) of depth (mm, NaN: unseen):
    randomly shifted, tilted, noised and cut when `train`, else the centre crop as it is. A share `terraces` of
    them also gets the ripple that coarse depth steps leave after dequantisation (z + a·sin(2π(z/p + φ)), a
    0.2–1 mm, p 4–10 mm: contour-like bands in the normals, as on rap3df-2019's 8 mm steps)."""
    n = recipe.size
    out = np.empty((len(windows), N_CHANNELS, n, n), dtype=np.float32)
    yy, xx = (np.mgrid[0:n, 0:n] - (n - 1) / 2) * recipe.step_mm
    for i, w in enumerate(windows):
        if not train:
            out[i] = input_channels(w[margin:margin + n, margin:margin + n], recipe)
            continue
        r, c = rng.integers(0, 2 * margin + 1, 2)
        z = w[r:r + n, c:c + n].copy()
        if rng.random() < 0.5:  # the mirror face: the same person to the network (faces are near symmetric)
            z = z[:, ::-1].copy()
        if rng.random() < 0.5:  # a residual roll of the frontalisation, about the nose tip
            z = _rolled(z, rng.normal(0.0, 4.0))
        tilt = np.tan(np.radians(rng.normal(0.0, 4.0, 2)))  # a residual yaw / pitch
        z += tilt[0] * xx + tilt[1] * yy
        if terraces > 0 and rng.random() < terraces:  # (no draw at 0: the shipped recipe's random stream)
            z = _terraced(z, rng)
        z += rng.normal(0.0, rng.uniform(0.0, 1.0), z.shape)
        if rng.random() < 0.2:  # a side the camera did not see
            edge = rng.uniform(0.25, 0.45) * n
            side = xx if rng.random() < 0.5 else -xx
            z[side / recipe.step_mm > edge] = np.nan
        if rng.random() < 0.2:  # a patch lost to an occluder or a dropout
            h, v = rng.integers(n // 8, n // 3, 2)
            r0, c0 = rng.integers(0, n - h), rng.integers(0, n - v)
            z[r0:r0 + h, c0:c0 + v] = np.nan
        out[i] = input_channels(z, recipe)
    return out


def _terraced(z: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A depth window (mm, NaN: unseen) with the ripple dequantised depth steps leave: z + a·sin(2π(z/p + φ)),
    a 0.2–1 mm, period p 4–10 mm along the depth, phase φ at random."""
    a, p, phase = rng.uniform(0.2, 1.0), rng.uniform(4.0, 10.0), rng.random()
    return z + a * np.sin(2 * np.pi * (z / p + phase))


def _rolled(z: np.ndarray, degrees: float) -> np.ndarray:
    """A depth window (NaN: unseen) turned by `degrees` in the image plane about its centre (bilinear)."""
    from scipy import ndimage

    seen = np.isfinite(z)
    turned = ndimage.rotate(np.where(seen, z, 0.0), degrees, reshape=False, order=1, cval=0.0)
    kept = ndimage.rotate(seen.astype(np.float64), degrees, reshape=False, order=1, cval=0.0) > 0.999
    return np.where(kept, turned, np.nan)


def _embed(net: EmbeddingNet, inputs: np.ndarray, batch: int = 256) -> np.ndarray:
    net.eval()
    with torch.no_grad():
        e = np.concatenate([net(torch.from_numpy(inputs[i:i + batch])).numpy() for i in range(0, len(inputs), batch)])
    return e / np.maximum(np.linalg.norm(e, axis=1, keepdims=True), 1e-12)


def identification_rank1(embeddings: np.ndarray, labels: np.ndarray) -> dict[str, float]:
    """Rank-1 and EER-free summary on a labelled set: each identity's first face is its gallery face, every other
    face a probe."""
    _, first = np.unique(labels, return_index=True)
    gallery = np.zeros(len(labels), bool)
    gallery[first] = True
    G, gl = embeddings[gallery], labels[gallery]
    P, pl = embeddings[~gallery], labels[~gallery]
    if not len(P):
        return {"rank1": float("nan"), "probes": 0}
    s = P @ G.T
    hits = gl[np.argmax(s, axis=1)] == pl
    genuine = s[np.arange(len(P)), np.searchsorted(gl, pl)] if np.all(np.diff(gl) > 0) else None
    out = {"rank1": round(float(hits.mean()), 4), "probes": int(len(P)), "identities": int(len(G))}
    if genuine is not None:
        out["mean_genuine_cosine"] = round(float(genuine.mean()), 4)
    return out


def train_embedding(windows: np.ndarray, labels: np.ndarray, recipe: InputRecipe, margin: int,
                    config: TrainConfig = TrainConfig(), init: str | Path | None = None,
                    progress: bool = True) -> tuple[EmbeddingNet, dict[str, Any]]:
    """Train on windows (N, n + 2·margin, …) with integer identity labels; a share of the identities is kept out
    for validation. Returns (network in eval mode, figures for the card)."""
    torch.manual_seed(config.seed)
    torch.set_num_threads(config.threads)
    rng = np.random.default_rng(config.seed)
    ids = np.unique(labels)
    held = rng.choice(ids, int(round(config.validation_share * len(ids))), replace=False) \
        if config.validation_share > 0 else np.zeros(0, ids.dtype)
    val = np.isin(labels, held)
    train_ids = np.unique(labels[~val])
    if len(train_ids) < 2:
        raise FaceRec3DError("training needs at least 2 identities outside the validation share")
    y = np.searchsorted(train_ids, labels[~val])
    X = windows[~val]
    net = EmbeddingNet(recipe.size, config.width, config.dim, config.dropout)
    if init is not None:
        load_weights(net, init)
    head = CosFace(config.dim, len(train_ids), config.scale, config.margin)
    params = list(net.parameters()) + list(head.parameters())
    opt = torch.optim.AdamW(params, lr=config.lr, weight_decay=config.weight_decay)
    steps = config.epochs * max(1, len(X) // config.batch)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, config.lr, total_steps=steps, pct_start=0.1)
    history = []
    t0 = time.perf_counter()
    for epoch in range(config.epochs):
        net.train()
        order = rng.permutation(len(X))
        losses = []
        for b in range(len(X) // config.batch):
            idx = order[b * config.batch:(b + 1) * config.batch]
            x = torch.from_numpy(augment(X[idx], rng, recipe, margin, terraces=config.terraces))
            loss = head(net(x), torch.from_numpy(y[idx]))
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            losses.append(float(loss.detach()))
        entry = {"epoch": epoch + 1, "loss": round(float(np.mean(losses)), 4), "seconds": round(time.perf_counter() - t0, 1)}
        if val.any() and (epoch + 1) % 5 == 0 or epoch + 1 == config.epochs:
            inputs = augment(windows[val], rng, recipe, margin, train=False)
            entry.update(identification_rank1(_embed(net, inputs), labels[val]) if val.any() else {})
        history.append(entry)
        if progress:
            print(json.dumps(entry), flush=True)
    net.eval()
    figures = {"train_scans": int(len(X)), "train_identities": int(len(train_ids)),
               "validation_identities": int(len(held)), "final_loss": history[-1]["loss"],
               "train_seconds": round(time.perf_counter() - t0, 1), "history": history}
    if val.any():
        figures["validation"] = identification_rank1(
            _embed(net, augment(windows[val], rng, recipe, margin, train=False)), labels[val])
    return net, figures


def save_weights(net: EmbeddingNet, path: str | Path) -> None:
    """The network's weights and buffers as plain arrays (.npz, no pickle)."""
    with open(path, "wb") as f:
        np.savez(f, **{k: v.detach().numpy() for k, v in net.state_dict().items()})


def load_weights(net: EmbeddingNet, path: str | Path) -> None:
    """Weights saved by `save_weights` into a network of the same shape."""
    try:
        with np.load(path, allow_pickle=False) as d:
            state = {k: torch.from_numpy(d[k].copy()) for k in d.files}
        net.load_state_dict(state)
    except (OSError, ValueError, KeyError, RuntimeError) as e:
        raise FaceRec3DError(f"{path}: not weights of this network ({str(e).splitlines()[0]})") from None


def export(net: EmbeddingNet, out: str | Path, recipe: InputRecipe, card: dict[str, Any]) -> Path:
    """Write the ONNX model, its card and its weights; returns the model's path."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    net.eval()
    save_weights(net, out.with_suffix(".weights.npz"))  # first: a failed export keeps the trained network
    dummy = torch.zeros(1, N_CHANNELS, recipe.size, recipe.size)
    names: dict[str, Any] = {"input_names": ["face"], "output_names": ["embedding"]}
    try:  # torch.export's exporter (onnxscript), one self-contained file, the batch axis free
        torch.onnx.export(net, (dummy,), str(out), dynamo=True, external_data=False, verbose=False, opset_version=18,
                          dynamic_shapes=({0: torch.export.Dim("batch")},), **names)
    except TypeError:  # a torch before 2.5 knows only the TorchScript exporter
        torch.onnx.export(net, (dummy,), str(out), opset_version=17,
                          dynamic_axes={"face": {0: "batch"}, "embedding": {0: "batch"}}, **names)
    card = {"name": out.stem, "format": "onnx", "embedding_dim": net.head[-1].num_features,
            "input": asdict(recipe), "license": "MIT", **card}
    card_path(out).write_text(json.dumps(card, indent=1) + "\n")
    return out
