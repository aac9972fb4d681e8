"""The configured engine's maps:

    faiss   overlapmamba.service.backends.faiss    SQLite store + FAISS index in the data folder;
    embedded,
                                      the default. The process owns its maps (one per data
                                      folder).
    qdrant  overlapmamba.service.backends.qdrant   one Qdrant collection per map; durability,
    replication
                                      and sharding are Qdrant's. The process keeps no state,
                                      so any number of replicas can serve one Qdrant cluster.

Each engine is imported only when chosen (qdrant-client is not needed by the default).
"""

from __future__ import annotations

from overlapmamba.service.backends.base import MapBackend
from overlapmamba.service.settings import Settings


def open_backend(settings: Settings, *, model_id: str, dim: int) -> MapBackend:
    """The configured engine's maps (not yet loaded: call ``load_all``)."""
    if settings.index.backend == "qdrant":
        from overlapmamba.service.backends.qdrant.backend import QdrantBackend

        return QdrantBackend(settings.qdrant, settings.index, model_id=model_id, dim=dim)
    from overlapmamba.service.backends.faiss.backend import FaissBackend

    return FaissBackend(settings.data_dir, settings.index, model_id=model_id, dim=dim)
