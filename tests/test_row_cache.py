"""The row cache of the faiss backend: the keyframes searched last, with their yaw spectra
(overlapmamba/service/backends/rows.py). Answers are the same with it and without it, a
deleted keyframe is never answered from it, and it keeps to its budget."""

from __future__ import annotations

import numpy as np
import pytest
from test_backends import DIM, MODEL_ID, row

from overlapmamba.core.yaw import spectra
from overlapmamba.service.backends.factory import open_backend
from overlapmamba.service.backends.rows import ENTRY_OVERHEAD, RowCache
from overlapmamba.service.domain import Filters, Keyframe
from overlapmamba.service.settings import Settings


def _backend(tmp_path, mb: int, kind: str = "faiss"):
    index = {"row_cache_mb": mb, "backend": kind}
    extra = {"qdrant": {"path": tmp_path / "q"}} if kind == "qdrant" else {}
    b = open_backend(
        Settings(data_dir=tmp_path / "data", index=index, **extra), model_id=MODEL_ID, dim=DIM
    )
    b.load_all()
    return b


def _answer(m, q, yaw, k=8, yaw_k=6):
    return [
        (x.keyframe.keyframe_id, x.distance, x.yaw_deg, x.yaw_confidence)
        for x in m.search(q, k, Filters(), yaw, yaw_k=yaw_k)
    ]


def _keyframe(i: int) -> Keyframe:
    return Keyframe(i, f"kf-{i}", "r", "s", 0.0, None, "h", i, 0.0)


@pytest.mark.parametrize("kind", ["faiss", "qdrant"])
def test_answers_are_the_same_from_the_cache_and_from_the_store(tmp_path, kind):
    rng = np.random.default_rng(0)
    rows = [row(i, rng, yaw=i % 7 != 0) for i in range(60)]  # some keyframes without yaw
    queries = [(r.descriptor, rng.normal(size=(4, 36)).astype(np.float32)) for r in rows[:12]]
    got = {}
    for mb in (0, 64):
        b = _backend(tmp_path / str(mb), mb, kind)
        try:
            m, _ = b.create("town", "flat")
            m.insert(rows)
            # twice: the second time the first yaw_k of each query come from the cache
            got[mb] = [[_answer(m, q, y) for q, y in queries] for _ in range(2)]
            info = b.row_cache_info()
        finally:
            b.close()
    for a, b in zip(got[0][0], got[64][1], strict=True):  # Qdrant's scores: float32
        assert [x[0] for x in a] == [x[0] for x in b]
        np.testing.assert_allclose(
            [x[1:] for x in a if x[2] is not None], [x[1:] for x in b if x[2] is not None]
        )
    assert got[0][0] == got[0][1] and got[64][0] == got[64][1]
    assert any(a[2] is not None for a in got[64][1][0])  # yaw was estimated
    assert info["hits"] >= 12 * 5 and info["rows"] > 0 and info["bytes"] <= 64 * 2**20


def test_a_deleted_keyframe_is_never_answered_from_the_cache(tmp_path):
    rng = np.random.default_rng(1)
    rows = [row(i, rng, yaw=True) for i in range(30)]
    yaw = rng.normal(size=(4, 36)).astype(np.float32)
    b = _backend(tmp_path, 64)
    try:
        m, _ = b.create("town", "flat")
        m.insert(rows)
        first = _answer(m, rows[3].descriptor, yaw)
        assert first[0][0] == "kf-3"
        held = b.row_cache.info()["rows"]
        m.delete("kf-3")
        assert b.row_cache.info()["rows"] == held - 1
        again = _answer(m, rows[3].descriptor, yaw)
        assert "kf-3" not in [a[0] for a in again]
        assert again[:5] == [a for a in first if a[0] != "kf-3"][:5]
        # the map deleted and made again under its id: nothing of the old one is answered
        b.delete("town")
        assert b.row_cache.info()["rows"] == 0
        m2, _ = b.create("town", "flat")
        m2.insert(rows[10:])
        assert {a[0] for a in _answer(m2, rows[3].descriptor, yaw)} <= {
            r.keyframe_id for r in rows[10:]
        }
    finally:
        b.close()


def test_the_cache_keeps_to_its_budget_least_recently_used_out_first():
    sp = spectra(np.random.default_rng(2).normal(size=(5, 4, 36)))
    size = ENTRY_OVERHEAD + sp[0].nbytes
    c = RowCache(3 * size)
    t = c.token()
    c.put(t, {i: (_keyframe(i), sp[i]) for i in range(3)})
    assert set(c.get(t, [0])) == {0}  # 0 is now the most recently used
    c.put(t, {3: (_keyframe(3), sp[3])})
    assert set(c.get(t, [0, 1, 2, 3])) == {0, 2, 3}  # 1 went
    assert c.info()["bytes"] == 3 * size
    other = c.token()
    assert c.get(other, [0, 2, 3]) == {}  # another map's rows of the same ids are apart
    c.discard(t, [2])
    c.put(other, {0: (_keyframe(0), None)})  # a keyframe without yaw features costs little
    assert c.info()["bytes"] == 2 * size + ENTRY_OVERHEAD
    c.drop(other)
    assert set(c.get(t, [0, 2, 3])) == {0, 3} and c.get(other, [0]) == {}
    assert c.info()["bytes"] == 2 * size
    c.put(t, {9: (_keyframe(9), spectra(np.zeros((1, 4, 4000)))[0])})  # over the whole budget
    assert 9 not in c.get(t, [9])
    none = RowCache(0)
    none.put(none.token(), {0: (_keyframe(0), sp[0])})
    assert none.info()["rows"] == 0
    with pytest.raises(ValueError, match="max_bytes"):
        RowCache(-1)


def test_a_qdrant_point_written_again_between_the_two_calls_is_answered_without_yaw_once(
    tmp_path, monkeypatch
):
    """The search's answer and the second call (the features the cache lacks) are two reads:
    a keyframe deleted or written again with other content between them is answered without
    yaw that once and not kept, so no spectrum is ever kept under the wrong content."""
    rng = np.random.default_rng(3)
    rows = [row(i, rng, yaw=True) for i in range(20)]
    yaw = rng.normal(size=(4, 36)).astype(np.float32)
    b = _backend(tmp_path, 64, "qdrant")
    try:
        m, _ = b.create("town", "flat")
        m.insert(rows)
        real = type(m)._call

        def racing(self, fn):  # the second call finds other content behind every point
            out = real(self, fn)
            if isinstance(out, list) and out and "yaw" in (out[0].payload or {}):
                for r in out:
                    r.payload["content_hash"] = "written-again"
            return out

        monkeypatch.setattr(type(m), "_call", racing)
        raced = _answer(m, rows[3].descriptor, yaw)
        assert all(a[2] is None for a in raced) and b.row_cache_info()["rows"] == 0
        monkeypatch.undo()
        calm = _answer(m, rows[3].descriptor, yaw)
        assert [a[0] for a in calm] == [a[0] for a in raced]
        assert all(a[2] is not None for a in calm[:6]) and b.row_cache_info()["rows"] == 6
    finally:
        b.close()
