"""The bird's-eye inputs (``input``'s ``bev`` modes): :func:`project_bev_offset` finds each
levelled return's row (ring × band) and its column as a continuous number (column c spans
[c, c + 1)); :func:`bev_cells` then says what each cell of a (views, H, W) image shows.
Sub-column view j moves every return j/views of a column on; empty cells are the profile's
``empty_value``, a full one 1.

    bev        occupied: 1 where any return falls in the cell
    bev-soft   shared: each return gives the two columns whose centres lie either side of it
               1 − its distance to each centre; a cell shows the largest share it is given. It
               moves with a turn, but a cell's value grows with how many returns it holds
    bev-span   spanned: each return spans one column's width centred on it, and a cell shows
               how much of its column the union of its returns' spans covers. It moves with a
               turn as ``bev-soft`` does, and a surface sampled at least once a column reads 1
               however densely it is sampled: only where the returns end does the value fall

The columns wrap round (azimuth is a circle) in ``bev-soft`` and ``bev-span``; ``bev``'s first
view clips, as the range images do. :func:`cells_reference` and :func:`project_bev_reference`
are the slow per-return versions for tests.
"""

from __future__ import annotations

import numpy as np

from overlapmamba.core.points import PointCloud, xyz_of
from overlapmamba.core.sensors.catalogue import COMMON_MAX_RANGE
from overlapmamba.core.sensors.mount import GROUND_CLEARANCE, REFERENCE_HEIGHT
from overlapmamba.core.sensors.profile import SensorProfile
from overlapmamba.core.views import check_views, scan_offset

BEV_MODES = ("bev", "bev-soft", "bev-span")  # the bird's-eye inputs: rows of rings × bands
# m above the reference ground: the bands of the ``bev`` input (the lowest starts above the
# ground, as ``structure``'s clearance; the top one ends where a car-mounted HDL-64E, 2.7°
# up at most, still reaches from 27 m on)
BEV_BANDS = (GROUND_CLEARANCE, 1.7, 3.0)
BEV_RINGS = 32  # rings of horizontal range within COMMON_MAX_RANGE
_PI = np.float32(np.pi)


def bev_cells(
    u: np.ndarray, row: np.ndarray, model: SensorProfile, views: int, mode: str
) -> np.ndarray:
    """(views, H, W) float32 cells of ``mode`` (one of :data:`BEV_MODES`) from the returns'
    continuous columns ``u`` (N,) float32 and rows ``row`` (N,) int."""
    if mode == "bev":
        return _occupied(u, row, model, views)
    if mode == "bev-soft":
        return _scaled(_shared(u, row, model, views), model)
    if mode == "bev-span":
        return _scaled(_spanned(u, row, model, views), model)
    raise ValueError(f"{mode!r} is not a bird's-eye input; allowed: {', '.join(BEV_MODES)}")


def _occupied(u: np.ndarray, row: np.ndarray, model: SensorProfile, views: int) -> np.ndarray:
    out = np.full((views, model.height, model.width), np.float32(model.empty_value), np.float32)
    for j in range(views):
        col = np.floor(u + np.float32(j / views) if j else u).astype(np.int64)
        col = np.clip(col, 0, model.width - 1) if j == 0 else col % model.width
        out[j, row, col] = 1.0
    return out


def _scaled(share: np.ndarray, model: SensorProfile) -> np.ndarray:
    """Shares in [0, 1] → cells: 0 empty, else from ``empty_value`` up to 1."""
    empty = np.float32(model.empty_value)
    cells = np.where(share > 0, empty + share.astype(np.float32) * (np.float32(1.0) - empty), empty)
    return cells.reshape(-1, model.height, model.width).astype(np.float32, copy=False)


def _shared(u: np.ndarray, row: np.ndarray, model: SensorProfile, views: int) -> np.ndarray:
    W = model.width
    share = np.zeros((views, model.height * W), np.float32)
    for j in range(views):
        at = u + np.float32(j / views - 0.5)  # from the centre of column 0
        left = np.floor(at)
        right_share = (at - left).astype(np.float32)
        left_col = left.astype(np.int64) % W
        np.maximum.at(share[j], row * W + left_col, np.float32(1.0) - right_share)
        np.maximum.at(share[j], row * W + (left_col + 1) % W, right_share)
    return share


def _spanned(u: np.ndarray, row: np.ndarray, model: SensorProfile, views: int) -> np.ndarray:
    """Per view, row and column, how much of the column the union of the returns' spans
    [u − ½, u + ½) covers (the columns wrap round).

    A span meets two columns: the one holding u + ½, from its left edge up to u + ½ (a share
    f = frac(u + ½)), and the one before it, from u − ½ to its right edge (1 − f). Within a
    column every span that reaches in from the left covers a piece starting at the left edge
    and every other one a piece ending at the right edge, so the union is the longest piece
    from each side, together, at most the whole column: one pass over the returns, two
    per-cell maxima, no sort of the returns (it replaced a union of sorted spans: on KITTI 00
    the same cells to the last bit, in about a fifth of the time)."""
    H, W = model.height, model.width
    row = np.asarray(row, np.int64) * W
    cover = np.zeros((views, H * W), np.float64)
    for j in range(views):
        at = np.asarray(u, np.float64) + (j / views + 0.5)
        col = np.floor(at)
        f = at - col
        col = col.astype(np.int64) % W
        from_left = np.zeros(H * W, np.float64)
        from_right = np.zeros(H * W, np.float64)
        np.maximum.at(from_left, row + col, f)
        np.maximum.at(from_right, row + (col - 1) % W, 1.0 - f)
        cover[j] = np.minimum(from_left + from_right, 1.0)
    return cover.reshape(views, H, W)


def cells_reference(u: np.ndarray, row: np.ndarray, model: SensorProfile, mode: str) -> np.ndarray:
    """Slow, obvious (H, W) cells of ``mode`` (one view) for tests: return by return, and for
    ``bev-span`` span by span and column by column."""
    H, W = model.height, model.width
    share = np.zeros((H, W), np.float64)
    spans: dict[int, list[tuple[float, float]]] = {}
    for ui, r in zip(np.asarray(u, np.float32), np.asarray(row), strict=True):
        r = int(r)
        if mode == "bev":
            share[r, min(max(int(np.floor(ui)), 0), W - 1)] = 1.0
        elif mode == "bev-soft":
            at = ui - np.float32(0.5)
            right = np.float32(at - np.floor(at))
            for col, s in (
                (int(np.floor(at)), np.float32(1.0) - right),
                (int(np.floor(at)) + 1, right),
            ):
                share[r, col % W] = max(share[r, col % W], float(s))
        else:
            x = float(ui) % W
            for a in (x, x + W, x - W):  # itself, and across the seam
                spans.setdefault(r, []).append((a - 0.5, a + 0.5))
    for r, row_spans in spans.items():
        merged: list[list[float]] = []
        for a, b in sorted(row_spans):
            if merged and a <= merged[-1][1]:
                merged[-1][1] = max(merged[-1][1], b)
            else:
                merged.append([a, b])
        for a, b in merged:
            for col in range(max(0, int(np.floor(a))), min(W, int(np.ceil(b)))):
                share[r, col] += max(0.0, min(b, col + 1.0) - max(a, float(col)))
    share = np.minimum(share, 1.0)
    if mode == "bev":
        out = np.full((H, W), np.float32(model.empty_value), np.float32)
        out[share > 0] = 1.0
        return out
    return _scaled(share, model)[0]


def bev_rows(
    model: SensorProfile, bands: tuple[float, ...] = BEV_BANDS, rings: int = BEV_RINGS
) -> int:
    """The rows the ``bev`` input fills (``rings`` × the bands); the model's rows below them
    stay empty. A profile with fewer rows cannot take it."""
    rows = rings * (len(bands) - 1)
    if rows > model.height:
        raise ValueError(
            f"the bev input's {rings} rings × {len(bands) - 1} bands need more rows than "
            f"profile {model.name!r} has ({model.height})"
        )
    return rows


def project_bev_offset(
    xyz: np.ndarray,
    model: SensorProfile,
    views: int,
    bands: tuple[float, ...] = BEV_BANDS,
    rings: int = BEV_RINGS,
    mode: str = "bev",
    *,
    aligned: bool = False,
) -> tuple[np.ndarray, float]:
    """(N, 3) levelled points at the reference height → (views, H, W) images of the
    bird's-eye input ``mode`` (``bands`` and ``rings``: the input's own unless a benchmark
    measures others), and the column offset it added: 0 unless ``aligned``, where the
    columns start at the mean bearing of the returns the input keeps
    (:func:`overlapmamba.core.views.scan_offset`), so that a scan turned about the vertical
    gives the plain image rolled by whole columns."""
    views = check_views(views)
    bev_rows(model, bands, rings)
    xyz = np.asarray(xyz, np.float32)
    x, y = xyz[:, 0], xyz[:, 1]
    z = xyz[:, 2] + np.float32(REFERENCE_HEIGHT)  # above the reference ground
    depth = np.sqrt(x * x + y * y + xyz[:, 2] * xyz[:, 2])
    edges = np.asarray(bands, np.float32)
    keep = (depth > np.float32(model.min_range)) & (depth < np.float32(COMMON_MAX_RANGE))
    keep &= (z >= edges[0]) & (z < edges[-1])
    x, y, z = x[keep], y[keep], z[keep]
    horizontal = np.sqrt(x * x + y * y)
    ring = np.minimum(horizontal * np.float32(rings / COMMON_MAX_RANGE), rings - 1)
    band = np.searchsorted(edges, z, side="right") - 1
    row = ring.astype(np.int64) * (len(edges) - 1) + band
    u = np.float32(0.5) * (-np.arctan2(y, x) / _PI + np.float32(1.0)) * np.float32(model.width)
    offset = 0.0
    if aligned:
        offset = scan_offset(x, y, depth[keep], model.width)
        u = np.mod(u + np.float32(offset), np.float32(model.width))
    return bev_cells(u, row, model, views, mode), offset


def project_bev_reference(
    points: PointCloud | np.ndarray, model: SensorProfile, mode: str = "bev"
) -> np.ndarray:
    """Slow, obvious image of the bird's-eye input ``mode`` (one view, no mount) for tests:
    per point, its height above the reference ground, its ring of horizontal range and its
    column, then :func:`~overlapmamba.core.sensors.bev.cells_reference`."""
    us, rows = [], []
    nb = len(BEV_BANDS) - 1
    for x, y, z in np.asarray(xyz_of(points), np.float32):
        depth = np.sqrt(x * x + y * y + z * z)
        above = z + np.float32(REFERENCE_HEIGHT)
        if not (np.float32(model.min_range) < depth < np.float32(COMMON_MAX_RANGE)):
            continue
        band = next((b for b in range(nb) if BEV_BANDS[b] <= above < BEV_BANDS[b + 1]), None)
        if band is None:
            continue
        scale = np.float32(BEV_RINGS / COMMON_MAX_RANGE)
        ring = min(int(np.sqrt(x * x + y * y) * scale), BEV_RINGS - 1)
        u = np.float32(0.5) * (-np.arctan2(y, x) / _PI + np.float32(1.0)) * np.float32(model.width)
        rows.append(ring * nb + band)
        us.append(u)
    return cells_reference(np.array(us, np.float32), np.array(rows, np.int64), model, mode)
