"""The embedded engine: per map a SQLite store (the source of truth, ``store``) and a FAISS
index derived from it (``index``), kept together by ``map`` with a snapshot (``snapshot``)
and the replay of newer store changes on start; ``backend`` holds every map of a data
folder."""
