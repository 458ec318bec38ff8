"""Model runtime: onnxruntime sessions and the manifest of exported models."""
