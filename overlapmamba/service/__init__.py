"""The place-recognition HTTP service (FastAPI, onnxruntime, FAISS or Qdrant)."""
