"""Point-cloud codecs: round trips, and every malformed input rejected with a typed error."""

from __future__ import annotations

import contextlib
import io
import pickle
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from pypcd4 import Encoding
from pypcd4 import PointCloud as PcdCloud

from overlapmamba.core.errors import (
    DataTooLargeError,
    DecodeError,
    NonFiniteError,
    PointCloudError,
    PointCountError,
)
from overlapmamba.core.io import (
    decode,
    decode_npy,
    decode_pcd,
    decode_raw,
    read_points,
    read_xyzi,
)
from overlapmamba.core.points import PointCloud, PointLimits, validate

finite32 = st.floats(-1e4, 1e4, allow_nan=False, width=32)


def clouds(cols: int, dtype=np.float32, max_n: int = 64):
    return arrays(dtype, st.tuples(st.integers(1, max_n), st.just(cols)), elements=finite32)


@given(clouds(4))
def test_raw_xyzi_round_trip(xyzi):
    pc = decode_raw(xyzi.astype("<f4").tobytes(), "xyzi")
    np.testing.assert_array_equal(pc.xyz, xyzi[:, :3])
    np.testing.assert_array_equal(pc.intensity, xyzi[:, 3])
    np.testing.assert_array_equal(pc.as_xyzi(), xyzi)


@given(clouds(3))
def test_raw_xyz_round_trip(xyz):
    pc = decode(xyz.astype("<f4").tobytes(), "raw", fields="xyz")
    np.testing.assert_array_equal(pc.xyz, xyz)
    assert pc.intensity is None


@settings(suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=512), st.sampled_from(["xyz", "xyzi"]))
def test_raw_any_bytes_decode_or_raise_typed(data, fields):
    try:
        pc = decode_raw(data, fields)
    except PointCloudError:
        return
    assert np.isfinite(pc.xyz).all() and len(pc) >= 1


@given(st.sampled_from(["npy", "pcd", "raw"]), st.binary(max_size=400))
def test_any_format_any_bytes_never_crashes(fmt, data):
    with contextlib.suppress(PointCloudError):
        decode(data, fmt)


def test_raw_rejections_name_the_problem():
    good = np.ones((10, 4), "<f4")
    with pytest.raises(DecodeError, match="not a multiple of the 16-byte xyzi record"):
        decode_raw(good.tobytes()[:-3], "xyzi")
    with pytest.raises(DecodeError, match="allowed: xyz, xyzi"):
        decode_raw(good.tobytes(), "xyzrgb")
    with pytest.raises(PointCountError, match="0 points; allowed: 1 to"):
        decode_raw(b"", "xyzi")
    bad = good.copy()
    bad[3, 1] = np.nan
    bad[5, 0] = np.inf
    with pytest.raises(NonFiniteError, match="2 points with NaN or infinite"):
        decode_raw(bad.tobytes(), "xyzi")
    bad = good.copy()
    bad[0, 3] = np.nan
    with pytest.raises(NonFiniteError, match="intensities"):
        decode_raw(bad.tobytes(), "xyzi")


def test_point_limits_are_checked_before_decoding():
    limits = PointLimits(min_points=5, max_points=8)
    with pytest.raises(PointCountError, match="9 points; allowed: 5 to 8"):
        decode_raw(np.zeros((9, 4), "<f4").tobytes(), limits=limits)
    with pytest.raises(PointCountError, match="4 points"):
        decode_raw(np.ones((4, 3), "<f4").tobytes(), "xyz", limits=limits)
    assert len(decode_raw(np.ones((8, 3), "<f4").tobytes(), "xyz", limits=limits)) == 8
    with pytest.raises(ValueError):
        PointLimits(min_points=10, max_points=2)


@given(clouds(4), st.sampled_from(["C", "F", "strided", "float64", ">f4"]))
def test_validate_splits_xyzi_alike_in_every_layout(xyzi, layout):
    """The KITTI-layout fast path (a float32 C array) and the others give the same points,
    C-contiguous float32; the fast path's are copies, not views of the caller's buffer."""
    arr = {
        "C": xyzi,
        "F": np.asfortranarray(xyzi),
        "strided": np.repeat(xyzi, 2, axis=0)[::2],
        "float64": xyzi.astype(np.float64),
        ">f4": xyzi.astype(">f4"),
    }[layout]
    pc = validate(arr)
    assert pc.xyz.tobytes() == np.ascontiguousarray(xyzi[:, :3]).tobytes()  # bit for bit
    assert pc.intensity is not None
    assert pc.intensity.tobytes() == np.ascontiguousarray(xyzi[:, 3]).tobytes()
    for part in (pc.xyz, pc.intensity):
        assert part.dtype == np.float32 and part.flags.c_contiguous
        assert layout != "C" or not np.shares_memory(part, arr)
    assert pc.as_xyzi().tobytes() == xyzi.tobytes()


def test_as_xyzi_of_a_cloud_built_directly_takes_any_layout():
    """A PointCloud made without validate (float64, Fortran order, strided) still gives
    the KITTI layout, and zero intensity where it has none."""
    xyzi = np.arange(24, dtype=np.float32).reshape(6, 4) - 7.5
    xyz64 = np.asfortranarray(xyzi[:, :3].astype(np.float64))
    got = PointCloud(xyz=xyz64, intensity=xyzi[:, 3]).as_xyzi()  # a strided column
    assert got.dtype == np.float32 and got.tobytes() == xyzi.tobytes()
    bare = PointCloud(xyz=xyzi[:, :3]).as_xyzi()
    np.testing.assert_array_equal(bare[:, :3], xyzi[:, :3])
    assert not bare[:, 3].any()


def test_validate_refuses_a_nan_in_a_kitti_layout_scan():
    xyzi = np.ones((5, 4), np.float32)
    xyzi[2, 1] = np.nan
    with pytest.raises(NonFiniteError, match="1 points with NaN"):
        validate(xyzi)
    xyzi[2, 1], xyzi[3, 3] = 1.0, np.inf
    with pytest.raises(NonFiniteError, match="1 NaN or infinite intensities"):
        validate(xyzi)


def test_validate_rejects_wrong_shapes_and_dtypes():
    with pytest.raises(PointCloudError, match=r"shape \(10, 5\)"):
        validate(np.zeros((10, 5), np.float32))
    with pytest.raises(PointCloudError, match="dtype int32"):
        validate(np.zeros((10, 3), np.int32))
    with pytest.raises(NonFiniteError):  # finite float64 that overflows float32
        validate(np.full((2, 3), 1e300))


def _npy_bytes(arr) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=True)
    return buf.getvalue()


@given(
    st.sampled_from([np.float32, np.float64, ">f4"]),
    st.sampled_from([3, 4]),
    st.booleans(),
    st.data(),
)
def test_npy_round_trip(dtype, cols, fortran, data):
    arr = data.draw(clouds(cols, dtype=np.dtype(dtype)))
    if fortran:
        arr = np.asfortranarray(arr)
    pc = decode_npy(_npy_bytes(arr))
    np.testing.assert_array_equal(pc.xyz, arr[:, :3].astype(np.float32))
    assert (pc.intensity is not None) == (cols == 4)


def test_npy_refuses_pickles_objects_and_bad_shapes():
    with pytest.raises(DecodeError, match="no object arrays"):
        decode_npy(_npy_bytes(np.array([[1, 2, 3]], dtype=object)))
    with pytest.raises(DecodeError, match="not a valid .npy"):
        decode_npy(pickle.dumps(np.zeros((3, 3))))
    with pytest.raises(DecodeError, match=r"allowed: \(N, 3\) or \(N, 4\)"):
        decode_npy(_npy_bytes(np.zeros((4, 4, 4), np.float32)))
    with pytest.raises(DecodeError, match="dtype int64"):
        decode_npy(_npy_bytes(np.zeros((4, 3), np.int64)))
    with pytest.raises(DecodeError, match="holds"):
        decode_npy(_npy_bytes(np.zeros((40, 3), np.float32))[:-8])


def test_npy_header_bomb_is_refused_before_allocation():
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        header, {"descr": "<f4", "fortran_order": False, "shape": (10**12, 3)}
    )
    with pytest.raises(PointCountError, match="1000000000000 points"):
        decode_npy(header.getvalue() + b"\0" * 64)


@pytest.mark.parametrize("encoding", [Encoding.ASCII, Encoding.BINARY, Encoding.BINARY_COMPRESSED])
@pytest.mark.parametrize("with_intensity", [False, True])
def test_pcd_round_trip(encoding, with_intensity):
    rng = np.random.default_rng(0)
    arr = rng.uniform(-50, 50, (257, 4 if with_intensity else 3)).astype(np.float32)
    if encoding == Encoding.ASCII:
        arr = np.round(arr, 3)  # ascii PCD keeps limited digits
    pcd = PcdCloud.from_xyzi_points(arr) if with_intensity else PcdCloud.from_xyz_points(arr)
    buf = io.BytesIO()
    pcd.save(buf, encoding=encoding)
    pc = decode_pcd(buf.getvalue())
    np.testing.assert_allclose(pc.xyz, arr[:, :3], rtol=1e-6)
    assert pc.has_intensity == with_intensity


def _pcd(points: int = 3, data: str = "binary", fields: str = "x y z") -> bytes:
    n = len(fields.split())
    return (
        f"VERSION 0.7\nFIELDS {fields}\nSIZE {' '.join(['4'] * n)}\nTYPE {' '.join(['F'] * n)}\n"
        f"COUNT {' '.join(['1'] * n)}\nWIDTH {points}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
        f"POINTS {points}\nDATA {data}\n"
    ).encode()


def test_an_organised_pcds_nan_points_are_missing_returns_an_unorganised_ones_an_error():
    """PCL saves a driver's organised cloud (HEIGHT > 1, a row a beam) with NaN where a beam
    had no return, as a non-dense PointCloud2 carries it: those points are dropped. In an
    unorganised cloud a NaN is a fault, and an infinity is one in either: 422 naming it."""
    rows = np.random.default_rng(1).uniform(-20, 20, (4, 8, 4)).astype(np.float32)
    rows[1, 3, :3] = np.nan
    rows[2, 5, 0] = np.nan
    head = _pcd(32, fields="x y z intensity").replace(b"WIDTH 32\nHEIGHT 1", b"WIDTH 8\nHEIGHT 4")
    pc = decode_pcd(head + rows.reshape(-1, 4).tobytes())
    keep = ~np.isnan(rows.reshape(-1, 4)[:, :3]).any(axis=1)
    assert len(pc) == 30
    np.testing.assert_array_equal(pc.xyz, rows.reshape(-1, 4)[keep, :3])
    np.testing.assert_array_equal(pc.intensity, rows.reshape(-1, 4)[keep, 3])
    with pytest.raises(NonFiniteError, match="2 points with NaN"):
        decode_pcd(_pcd(32, fields="x y z intensity") + rows.reshape(-1, 4).tobytes())
    rows[0, 0, 2] = np.inf
    with pytest.raises(NonFiniteError, match="1 points with NaN or infinite"):
        decode_pcd(head + rows.reshape(-1, 4).tobytes())


def test_pcd_malformed_inputs_are_rejected():
    body = np.ones((3, 3), "<f4").tobytes()
    assert len(decode_pcd(_pcd() + body)) == 3
    with pytest.raises(DecodeError, match="holds 24 bytes"):
        decode_pcd(_pcd() + body[:24])  # truncated
    with pytest.raises(DecodeError, match="missing"):
        decode_pcd(_pcd(fields="x y intensity") + body)
    with pytest.raises(DecodeError, match="malformed PCD header|DATA"):
        decode_pcd(b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4\nDATA binary\n" + body)
    with pytest.raises(DecodeError):
        decode_pcd(b"\x89PNG\r\n\x1a\n" + body)
    with pytest.raises(DecodeError, match="DATA line"):
        decode_pcd(b"# comment\n" * 100)
    with pytest.raises(PointCountError):
        decode_pcd(_pcd(points=5_000_000) + body)


def test_a_binary_pcd_holding_more_points_than_it_declares_is_refused():
    """A binary PCD whose data holds more whole points than POINTS said was read as its first
    POINTS points: a writer that got WIDTH or POINTS wrong lost the rest of the scan without
    a word. A stray byte or two after the data (a newline some writers add) is no point."""
    body = np.ones((6, 3), "<f4").tobytes()
    with pytest.raises(DecodeError, match=r"declares 3 points \(36 bytes\).*holds 72 bytes"):
        decode_pcd(_pcd(3) + body)
    with pytest.raises(DecodeError, match="holds 48 bytes"):
        decode_pcd(_pcd(3) + body[:48])  # one point more
    assert len(decode_pcd(_pcd(3) + body[:36] + b"\n")) == 3
    assert len(decode_pcd(_pcd(3) + body[:47])) == 3  # less than a point more


def test_pcd_decompression_bomb_is_refused():
    # Declares 3 points but claims 4 GB uncompressed: pypcd4 alone would allocate it.
    payload = struct.pack("<II", 10, 0xFFFFFFF0) + b"\0" * 10
    with pytest.raises(DecodeError, match="inconsistent"):
        decode_pcd(_pcd(data="binary_compressed") + payload)


def test_read_real_scans(kitti_reference_dir, nuscenes_dir):
    pc = read_points(kitti_reference_dir / "000000.bin")
    assert len(pc) > 100_000 and pc.intensity is not None
    assert pc.intensity.min() >= 0 and pc.intensity.max() < 1
    nu = read_points(nuscenes_dir / "clouds" / "0.pcd")
    assert len(nu) == 34688 and nu.intensity is None


def test_read_xyzi_gives_what_read_points_gives_and_refuses_alike(tmp_path, kitti_reference_dir):
    """The replay's fast path: a .bin is its own buffer, checked in one pass; any other file,
    and any .bin that pass finds wrong, goes through read_points and its named errors."""
    real = kitti_reference_dir / "000000.bin"
    got = read_xyzi(real)
    np.testing.assert_array_equal(got, read_points(real).as_xyzi())
    assert got.dtype == np.float32 and got.shape[1] == 4
    xyz = np.random.default_rng(0).normal(size=(200, 3)).astype(np.float32)
    np.save(tmp_path / "s.npy", xyz)  # no intensity: 0, as read_points' as_xyzi
    np.testing.assert_array_equal(read_xyzi(tmp_path / "s.npy")[:, :3], xyz)
    assert (read_xyzi(tmp_path / "s.npy")[:, 3] == 0).all()
    bad = np.ones((200, 4), "<f4")
    bad[7, 3] = np.nan  # an intensity too
    (tmp_path / "nan.bin").write_bytes(bad.tobytes())
    (tmp_path / "cut.bin").write_bytes(bad.tobytes()[:-3])
    (tmp_path / "few.bin").write_bytes(b"")  # no point: fewer than min_points
    for name, error in (("nan", NonFiniteError), ("cut", DecodeError), ("few", PointCountError)):
        with pytest.raises(error) as fast:
            read_xyzi(tmp_path / f"{name}.bin")
        with pytest.raises(error) as full:
            read_points(tmp_path / f"{name}.bin")
        assert str(fast.value) == str(full.value)
    with pytest.raises(DecodeError, match="cannot read"):
        read_xyzi(tmp_path / "absent.bin")


def test_read_points_rejects_unknown_suffix(tmp_path):
    p = tmp_path / "scan.las"
    p.write_bytes(b"x")
    with pytest.raises(DecodeError, match="allowed suffixes: .bin, .npy, .pcd"):
        read_points(p)
    with pytest.raises(DecodeError, match="cannot read"):
        read_points(tmp_path / "absent.bin")


def test_pcd_header_tricks_found_in_review():
    body = np.ones((3, 3), "<f4").tobytes()
    # An alternative spelling pypcd4 accepts would skip our size checks: refused outright.
    with pytest.raises(DecodeError, match="allowed: ascii, binary, binary_compressed"):
        decode_pcd(_pcd(data="binaryscompressed") + body)
    # More than 10 header entries: pypcd4 would stop early and misread the DATA line.
    padded = _pcd().replace(b"VERSION 0.7\n", b"VERSION 0.7\nHEIGHT 1\n")
    with pytest.raises(DecodeError, match="no DATA line in its first 10 entries"):
        decode_pcd(padded + body)
    with pytest.raises(DecodeError, match="header line longer"):
        decode_pcd(b"#" * 5000 + b"\n" + _pcd() + body)
    header = _pcd(points=1, fields="x y z intensity").replace(b"COUNT 1 1 1 1", b"COUNT 1 1 1 2")
    with pytest.raises(DecodeError, match="intensity has COUNT 2; allowed: 1"):
        decode_pcd(header + np.ones(5, "<f4").tobytes())
    # Comments inside the header are fine and do not shift what pypcd4 reads.
    commented = b"# made by a test\n" + _pcd().replace(b"HEIGHT 1\n", b"HEIGHT 1\n# note\n")
    assert len(decode_pcd(commented + body)) == 3


def _npy_with_header(header: bytes, version: bytes = b"\x01\x00") -> bytes:
    header += b" " * (53 - len(header)) + b"\n"
    return b"\x93NUMPY" + version + struct.pack("<H", len(header)) + header + b"\0" * 12


def test_npy_header_tricks_found_in_review():
    with pytest.raises(DecodeError, match="allowed: \\(N, 3\\)"):
        decode_npy(
            _npy_with_header(b"{'descr': '<f4', 'fortran_order': False, 'shape': (True, 3), }")
        )
    with pytest.raises(DecodeError, match="version"):
        decode_npy(
            _npy_with_header(
                b"{'descr': '<f4', 'fortran_order': False, 'shape': (1, 3), }", version=b"\x03\x00"
            )
        )


def test_raw_rejects_non_contiguous_buffers():
    with pytest.raises(DecodeError, match="contiguous"):
        decode_raw(memoryview(np.zeros(32, np.float32)[::2]), "xyzi")


def test_pcd_edge_cases_raise_typed_errors_without_warnings():
    # pytest turns warnings into errors here, so these also prove no warning leaks out.
    with pytest.raises(DecodeError, match="declares 2 points but its data holds 0"):
        decode_pcd(_pcd(points=2, data="ascii"))  # declares rows, holds none
    big = _pcd(points=1).replace(b"SIZE 4 4 4", b"SIZE 8 8 8")
    with pytest.raises(NonFiniteError):
        decode_pcd(big + np.array([1e300, 0, 0], "<f8").tobytes())


def test_pcd_headers_that_would_cost_gigabytes_or_seconds_are_refused_first():
    """A few hundred bytes of header must not buy seconds of CPU or gigabytes of memory
    (found in review, 2026-12-04): each is refused before pypcd4 builds anything."""
    pad = _pcd(100, fields="x y z pad").replace(b"COUNT 1 1 1 1", b"COUNT 1 1 1 5000000")
    with pytest.raises(DecodeError, match="5000003 values .* allowed: at most 256 values"):
        decode_pcd(pad + b"\0" * 64)  # pypcd4 makes one numpy field per element
    with pytest.raises(DecodeError, match="header runs past 65536 bytes"):
        decode_pcd(b"\n" * (1 << 20) + _pcd() + b"\0" * 36)  # blank lines, read one by one
    rows = b"0 0 0\n" * 100_000
    with pytest.raises(DecodeError, match="declares 100 points but its data holds 100000 lines"):
        decode_pcd(_pcd(100, data="ascii") + rows)
    assert len(decode_pcd(_pcd(3, data="ascii") + b"1 2 3\n" * 3 + b"\n\n")) == 3
    # binary_compressed: its uncompressed size consistent with the header, but past the
    # bytes a decoder may build (the service's limits.max_decoded_bytes): 413, never inflated
    big = _pcd(1_000_000, data="binary_compressed", fields="x y z pad")
    big = big.replace(b"SIZE 4 4 4 4", b"SIZE 4 4 4 8").replace(
        b"COUNT 1 1 1 1", b"COUNT 1 1 1 100"
    )
    record = 12 + 800
    payload = struct.pack("<II", 10, 1_000_000 * record) + b"\0" * 10
    with pytest.raises(DataTooLargeError, match="812000000 bytes once inflated"):
        decode_pcd(big + payload, limits=PointLimits(max_bytes=128 << 20))
