"""The models the package ships (the learned embedding: embedding.onnx and its card embedding.json; the nose
proposer: nose.onnx and nose.json), and how one is opened."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from facerec3d.errors import FaceRec3DError


def onnx_session(path: str | Path, what: str, threads: int = 1) -> Any:
    """An onnxruntime CPU session of the ONNX model at `path` on `threads` threads; one clear error naming the file
    and `what` it should be when it cannot be opened."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.log_severity_level = 3
    try:
        return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types for unreadable models
        raise FaceRec3DError(f"{path}: not a usable ONNX {what} ({str(e).splitlines()[0]})") from None
