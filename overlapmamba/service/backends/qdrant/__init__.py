"""The scale-out engine: one Qdrant collection per map (``backend``, ``map``), keyframes laid
out as points (``codec``)."""
