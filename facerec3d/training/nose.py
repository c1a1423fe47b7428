"""Training the nose proposer (`preprocess.propose`; PyTorch, the `[train]` extra only).

A small fully convolutional encoder-decoder (`NoseNet`) maps the proposer's input (3 × H × W at 5 mm cells)
to one score per 10 mm cell. The loss is the cross-entropy between the softmax of the scores over all cells and a
Gaussian (σ = one output cell) around the true nose tip: one nose per scan, wherever it is.

Samples (`training.nose_data`) are crops of the height maps of synthetic scans as the detector sees them, each
with the nose cell; each batch is cut at random around the nose, mirrored, given a wall behind the head and hair,
noised and holed.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from facerec3d.errors import FaceRec3DError
from facerec3d.preprocess.propose import CELL_MM, STRIDE
from facerec3d.training.nose_data import augment, target

try:
    import torch
    from torch import nn
except ImportError:  # pragma: no cover - the [train] extra
    raise FaceRec3DError("training a nose proposer needs PyTorch: pip install 'facerec3d[train]'") from None

def _block(cin: int, cout: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, padding=dilation, dilation=dilation, bias=False),
                         nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class NoseNet(nn.Module):
    """Input (B, 3, H, W), H and W multiples of 8; output (B, 1, H/2, W/2) nose scores (logits).

    5 mm cells in, 10 mm at once (a stride-2 first layer), 20 and 40 mm (two dilated convolutions: a 40 mm cell
    sees ~0.5 m), back to 10 mm by nearest upsampling added to the encoder's features (~45 M multiply-adds for a
    96 × 96 map)."""

    def __init__(self, width: int = 16):
        super().__init__()
        w = width
        self.enc1 = nn.Sequential(_block(3, w, 2), _block(w, 3 * w // 2))
        self.enc2 = nn.Sequential(_block(3 * w // 2, 2 * w, 2), _block(2 * w, 2 * w))
        self.enc3 = nn.Sequential(_block(2 * w, 3 * w, 2), _block(3 * w, 3 * w, dilation=2),
                                  _block(3 * w, 3 * w, dilation=2))
        self.lat3 = nn.Conv2d(3 * w, 2 * w, 1)
        self.dec2 = _block(2 * w, 2 * w)
        self.lat2 = nn.Conv2d(2 * w, 3 * w // 2, 1)
        self.dec1 = _block(3 * w // 2, 3 * w // 2)
        self.out = nn.Conv2d(3 * w // 2, 1, 1)
        self.up = nn.Upsample(scale_factor=2, mode="nearest")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        e1 = self.enc1(x)
        e2 = self.enc2(e1)
        e3 = self.enc3(e2)
        d2 = self.dec2(self.up(self.lat3(e3)) + e2)
        d1 = self.dec1(self.up(self.lat2(d2)) + e1)
        return self.out(d1)


def train_nose(maps: np.ndarray, noses: np.ndarray, *, epochs: int = 12, batch: int = 32, size: int = 96,
               lr: float = 3e-3, seed: int = 0, threads: int = 2, validation: int = 300,
               log=print) -> tuple[NoseNet, dict[str, Any]]:
    """A NoseNet trained on height-map crops (N, S, S) with NaN for empty and their nose (row, col, ...)."""
    torch.manual_seed(seed)
    torch.set_num_threads(threads)
    rng = np.random.default_rng(seed)
    n = len(maps)
    order = rng.permutation(n)
    val, tr = order[:validation], order[validation:]
    net = NoseNet()
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-4)
    steps = epochs * (len(tr) // batch)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps)
    vrng = np.random.default_rng(seed + 1)
    vx, vt = zip(*(augment(maps[i], noses[i], vrng, size) for i in val))
    vx, vt = torch.from_numpy(np.stack(vx)), np.stack(vt)
    history = []
    for epoch in range(epochs):
        net.train()
        t0, total = time.perf_counter(), 0.0
        perm = rng.permutation(tr)
        for b in range(len(tr) // batch):
            xs, ts = [], []
            for i in perm[b * batch:(b + 1) * batch]:
                x, rc = augment(maps[i], noses[i], rng, size)
                xs.append(x)
                ts.append(target(rc, (size // STRIDE, size // STRIDE)))
            logits = net(torch.from_numpy(np.stack(xs))).flatten(1)
            loss = -(torch.from_numpy(np.stack(ts)).flatten(1) * torch.log_softmax(logits, 1)).sum(1).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += float(loss)
        err = validation_errors(net, vx, vt)
        history.append({"epoch": epoch + 1, "loss": round(total / (len(tr) // batch), 4),
                        "median_mm": round(float(np.median(err)), 2), "within_10mm": round(float((err <= 10).mean()), 4),
                        "within_20mm": round(float((err <= 20).mean()), 4), "s": round(time.perf_counter() - t0, 1)})
        log(json.dumps(history[-1]))
    return net, {"history": history}


def validation_errors(net: NoseNet, x: torch.Tensor, rc: np.ndarray) -> np.ndarray:
    """Distance (mm, in the x-y plane) between each crop's best-scoring cell centre and its true nose."""
    net.eval()
    with torch.no_grad():
        s = torch.cat([net(x[i:i + 128]) for i in range(0, len(x), 128)])[:, 0].numpy()
    flat = s.reshape(len(s), -1).argmax(1)
    r, c = np.unravel_index(flat, s.shape[1:])
    best = np.stack([(r + 0.5) * STRIDE, (c + 0.5) * STRIDE], 1)
    return np.linalg.norm(best - rc, axis=1) * CELL_MM


def export(net: NoseNet, out: str | Path, card: dict[str, Any]) -> Path:
    """Write the ONNX model (height and width free) and its card."""
    out = Path(out)
    net.eval()
    with open(out.with_suffix(".weights.npz"), "wb") as f:
        np.savez(f, **{k: v.detach().numpy() for k, v in net.state_dict().items()})
    dummy = torch.zeros(1, 3, 96, 96)
    h, w = torch.export.Dim("h8", max=64), torch.export.Dim("w8", max=64)
    torch.onnx.export(net, (dummy,), str(out), dynamo=True, external_data=False, verbose=False, opset_version=18,
                      input_names=["height_map"], output_names=["nose_score"],
                      dynamic_shapes=({2: 8 * h, 3: 8 * w},))
    out.with_suffix(".json").write_text(json.dumps({"name": out.stem, "format": "onnx", "license": "MIT", **card},
                                                   indent=1) + "\n")
    return out
