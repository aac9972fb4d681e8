"""Training and ONNX export of OverlapMamba (PyTorch). Built by issues 4–6."""
