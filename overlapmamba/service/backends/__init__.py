"""Where maps live: the protocol every engine implements (``base``), the factory that opens
the configured one (``factory``), and the engines (``faiss``, ``qdrant``)."""
