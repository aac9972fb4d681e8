"""Top-down picture of a generated world: surfaces, buildings, trees and the drive.

The trajectory is coloured by frame index; frames that revisit a place (from the loop ground
truth) are marked, reverse-direction revisits in another marker than same-direction ones.
Written without timestamps so the same seed gives a byte-identical PNG.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from overlapmamba.synth.geometry import MAT
from overlapmamba.synth.world import World

_SURFACE_RGB = {
    MAT["asphalt"]: (0.35, 0.35, 0.38),
    MAT["pavement"]: (0.78, 0.76, 0.72),
    MAT["grass"]: (0.72, 0.85, 0.62),
}
_KIND_RGB = {"urban": "#8c4a3c", "house": "#c98b5a", "hall": "#6b7a8f"}


def draw_map(
    world: World,
    path: str | Path,
    positions: np.ndarray | None = None,
    same_dir: np.ndarray | None = None,
    reverse_dir: np.ndarray | None = None,
    title: str = "",
) -> None:
    """positions: (N, 2) drive; same_dir / reverse_dir: frame indices of revisits."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon

    surf = world.surface
    assert surf is not None
    rgb = np.ones((*surf.shape, 3))
    for mid, colour in _SURFACE_RGB.items():
        rgb[surf == mid] = colour
    fig, ax = plt.subplots(figsize=(9, 9), dpi=110)
    ax.imshow(
        rgb.transpose(1, 0, 2),
        origin="lower",
        extent=(
            world.lo[0],
            world.lo[0] + surf.shape[0] * world.surface_res,
            world.lo[1],
            world.lo[1] + surf.shape[1] * world.surface_res,
        ),
        interpolation="nearest",
    )
    for corners, kind in world.footprints:
        ax.add_patch(Polygon(corners, closed=True, fc=_KIND_RGB[kind], ec="none"))
    if len(world.trees):
        ax.scatter(world.trees[:, 0], world.trees[:, 1], s=2, c="#2e7d32", lw=0)
    if positions is not None and len(positions):
        sc = ax.scatter(
            positions[:, 0],
            positions[:, 1],
            c=np.arange(len(positions)),
            s=1.5,
            cmap="viridis",
            lw=0,
        )
        fig.colorbar(sc, ax=ax, fraction=0.035, pad=0.02, label="frame")
        for idx, marker, edge, label in (
            (same_dir, "o", "#1565c0", "revisit, same direction"),
            (reverse_dir, "^", "#d81b60", "revisit, opposite direction"),
        ):
            if idx is not None and len(idx):
                ax.scatter(
                    positions[idx, 0],
                    positions[idx, 1],
                    s=9,
                    marker=marker,
                    facecolors="none",
                    edgecolors=edge,
                    lw=0.6,
                    label=f"{label} ({len(idx)})",
                )
        ax.plot(*positions[0], "k*", ms=10, label="start")
        ax.legend(loc="upper right", fontsize=7, framealpha=0.85)
    ax.set_xlim(world.lo[0] + 100, world.hi[0] - 100)
    ax.set_ylim(world.lo[1] + 100, world.hi[1] - 100)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, metadata={"Software": None})
    plt.close(fig)
