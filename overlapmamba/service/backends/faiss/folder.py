"""A new map's folder, made whole or not at all.

    data_dir/maps/.create-<map_id>/store.sqlite   built here, with the map's metadata
    data_dir/maps/<map_id>/                       then renamed into place (and the parent
                                                  folder fsynced)

A crash leaves either no map or a whole one (the backend's start-up removes a
``.create-`` folder), never a store without its metadata.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from overlapmamba.service.backends.faiss.sqlfile import fsync_dir, storage_full
from overlapmamba.service.backends.faiss.store import Store


def make_map_folder(map_id: str, folder: Path, meta: dict[str, str | int | float]) -> None:
    """Create ``folder`` holding a store with ``meta``; a full disk is the 503
    ``storage_full``, and nothing is left behind on any failure."""
    tmp = folder.with_name(f".create-{map_id}")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        tmp.mkdir(parents=True)
        store = Store(tmp / "store.sqlite", new=True)
        try:
            store.set_meta(**meta)
        finally:
            store.close()  # a lingering connection would checkpoint into the file later
        os.replace(tmp, folder)
        fsync_dir(folder.parent)
    except Exception as err:
        shutil.rmtree(tmp, ignore_errors=True)
        full = storage_full(err.__cause__ or err, f"map {map_id!r} cannot be created")
        if full is not None:
            raise full from err
        raise
