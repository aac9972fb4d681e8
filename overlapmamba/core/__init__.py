"""Shared LiDAR core: sensor profiles, codecs, projection, poses, datasets, overlap, metrics.

Imports numpy, pydantic and small pure-Python libraries only; never torch, onnxruntime,
faiss or a sibling package (tested in tests/test_boundaries.py).
"""
