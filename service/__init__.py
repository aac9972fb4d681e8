"""The place-recognition HTTP service (FastAPI, onnxruntime, faiss). Built by issue 7."""
