"""Training, evaluation and ONNX export of OverlapMamba (PyTorch)."""
