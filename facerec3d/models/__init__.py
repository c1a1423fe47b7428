"""The models the package ships (the learned embedding: embedding.onnx and its card embedding.json)."""
