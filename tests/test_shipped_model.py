"""The bundled default model: its metadata agrees with its model card, it is small enough,
and on a real KITTI scan its descriptor does not move when the sensor turns.

It is read the way the service reads it: onnxruntime and overlapmamba.core only, no torch."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from overlapmamba.core.modelmeta import INPUT, OUTPUTS, EncoderMetadata

ort = pytest.importorskip("onnxruntime")

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "models" / "overlapmamba-hdl64.onnx"
CARD = ROOT / "models" / "README.md"


def card_facts() -> dict[str, str]:
    """The ``key: value`` lines of the card's fenced ``facts`` block."""
    m = re.search(r"```facts\n(.*?)```", CARD.read_text(), re.S)
    assert m, f"{CARD} has no ```facts block"
    return dict(
        (k.strip(), v.strip()) for k, v in (line.split(":", 1) for line in m[1].splitlines())
    )


@pytest.fixture(scope="module")
def session():
    assert MODEL.is_file(), f"the default model {MODEL} is missing from the repository"
    so = ort.SessionOptions()
    so.intra_op_num_threads = 2
    return ort.InferenceSession(str(MODEL), so, providers=["CPUExecutionProvider"])


@pytest.fixture(scope="module")
def meta(session) -> EncoderMetadata:
    return EncoderMetadata.from_props(session.get_modelmeta().custom_metadata_map)


def test_shipped_model_metadata_matches_its_card(session, meta):
    facts = card_facts()
    assert MODEL.stat().st_size <= 25e6
    assert f"{MODEL.stat().st_size / 1e6:.1f} MB" == facts["file_size"]
    assert meta.weights == "trained" == facts["weights"]
    assert meta.model_id == facts["model_id"]
    assert meta.weight_format == facts["weight_format"]
    assert str(meta.views) == facts["views"]
    assert meta.sensor_input == facts["sensor_input"]
    # the thresholds the service answers with come from the file, each from its benchmark
    assert ", ".join(meta.calibration) == facts["calibrated"]
    for section, entry in meta.calibration.items():
        assert entry.chosen_by.startswith("python benchmarks/") and "--write-calibration" in (
            entry.chosen_by
        ), section
        assert entry.data.startswith("data/synth/val"), section  # never a test town
    assert meta.source_commit == facts["source_commit"]
    assert meta.profile.name == facts["sensor"]
    assert f"{meta.profile.height}x{meta.profile.width}" == facts["range_image"]
    assert str(meta.descriptor_dim) == facts["descriptor_dim"]
    assert meta.network["mixer"] == "mamba" and meta.network["n_blocks"] == 1
    best = meta.metrics["best"]
    assert str(best["epoch"]) == facts["best_epoch"]
    assert f"{best['f1max']:.3f}" == facts["val_f1max"]
    assert f"{meta.metrics['val']['all']['recall@1']:.3f}" == facts["val_recall@1"]
    train = [Path(d["path"]).name for d in meta.training_data["train"]]
    assert train == facts["train_data"].split(",")
    assert Path(meta.training_data["val"]["path"]).name == facts["val_data"]
    assert "test" not in train  # never trained on the test preset, nor on real scans
    assert [i.name for i in session.get_inputs()] == [INPUT]
    assert [o.name for o in session.get_outputs()] == list(OUTPUTS)


def describe(session, meta: EncoderMetadata, clouds: list[np.ndarray]) -> tuple[np.ndarray, ...]:
    """Descriptors and yaw features of point clouds as the service makes them: the model's
    sub-column views of each (overlapmamba.core.views), one graph row each, combined."""
    from overlapmamba.core.views import combine_views, project_views

    views = np.stack([project_views(xyz, meta.profile, meta.views) for xyz in clouds])
    images = views.reshape(-1, 1, *views.shape[2:])
    return combine_views(*session.run(list(OUTPUTS), {INPUT: images}), meta.views)


@pytest.mark.real_data
def test_shipped_model_descriptor_ignores_yaw_on_a_real_scan(session, meta, kitti_seq_dir):
    from overlapmamba.core.datasets import open_sequence
    from overlapmamba.core.poses import rotation_z, transform_points

    seq = open_sequence(kitti_seq_dir)
    rng = np.random.default_rng(7)
    xyz = seq.points(40).xyz
    angles = rng.uniform(-180, 180, 4)
    clouds = [xyz] + [transform_points(xyz, rotation_z(a)) for a in angles]
    desc, yaw = describe(session, meta, clouds)
    assert desc.shape == (5, meta.descriptor_dim) and yaw.shape[1] == meta.yaw_channels
    np.testing.assert_allclose(np.linalg.norm(desc, axis=1), 1.0, atol=1e-4)
    cos = desc[1:] @ desc[0]
    assert cos.min() >= 0.999, (angles, cos)
    # … while another place is clearly further away than any turned copy.
    d_other = describe(session, meta, [seq.points(100).xyz])[0][0]
    assert d_other @ desc[0] < cos.min()


@pytest.mark.real_data
def test_shipped_model_views_hold_the_cosine_where_one_view_does_not(session, meta, kitti_seq_dir):
    """On the scans and turns where a single projection moves the descriptor most, the
    model's views keep the cosine at ≥ 0.999 (`eval-real` checks all 101 scans)."""
    from overlapmamba.core.datasets import open_sequence
    from overlapmamba.core.poses import rotation_z, transform_points

    assert meta.views > 1
    one = meta.model_copy(update={"views": 1})
    seq = open_sequence(kitti_seq_dir)
    theta = np.random.default_rng(0).uniform(-180, 180, len(seq))  # eval-real's seed 0
    frames = range(0, len(seq), 10)
    plain = [seq.points(i).xyz for i in frames]
    turned = [transform_points(plain[n], rotation_z(-theta[i])) for n, i in enumerate(frames)]
    cos = {}
    for m in (one, meta):
        desc = describe(session, m, plain + turned)[0]
        cos[m.views] = (desc[: len(plain)] * desc[len(plain) :]).sum(1)
    assert cos[meta.views].min() >= 0.999, cos
    assert cos[1].min() < cos[meta.views].min()


@pytest.mark.real_data
def test_the_one_view_twin_holds_the_cosine_in_one_pass(kitti_seq_dir):
    """The one-view twin aligns each scan's columns: on the scans and turns where a single
    plain projection moves the descriptor most (the test above), one pass a scan keeps the
    cosine at ≥ 0.999, and the yaw features still give the turn (`benchmarks/views.py`
    checks every scan of KITTI 00 and nuScenes)."""
    from overlapmamba.core.datasets import open_sequence
    from overlapmamba.core.poses import rotation_z, transform_points
    from overlapmamba.core.yaw import estimate_yaw
    from overlapmamba.service.encoder import Encoder

    enc = Encoder(ROOT / "models" / "overlapmamba-hdl64-one-view.onnx", intra_op_threads=2)
    seq = open_sequence(kitti_seq_dir)
    theta = np.random.default_rng(0).uniform(-180, 180, len(seq))  # eval-real's seed 0
    frames = range(0, len(seq), 10)
    plain = [seq.points(i).xyz for i in frames]
    turned = [transform_points(plain[n], rotation_z(-theta[i])) for n, i in enumerate(frames)]
    desc, yaw = enc.describe(plain + turned)
    k = len(plain)
    assert (desc[:k] * desc[k:]).sum(1).min() >= 0.999
    for n, i in enumerate(frames):
        est = estimate_yaw(yaw[n], yaw[k + n])[0][0]
        assert abs((est - theta[i] + 180) % 360 - 180) < 0.1, (i, est, theta[i])


# the documented twins of the shipped file (the model card): its weights, other views, and
# where a scan's columns start
TWINS = {
    "overlapmamba-hdl64-one-view.onnx": (1, "descriptors", "aligned"),
    "overlapmamba-hdl64-tokens.onnx": (3, "tokens", "sensor"),
}


@pytest.mark.parametrize("name", TWINS)
def test_twins_are_the_shipped_weights_with_their_own_calibration(meta, name):
    """Each twin is the shipped network described by other views (a model id of its own, so
    its maps are its own), calibrated on val by the benchmarks' commands naming that file: a
    shipped file retrained without its twins made again fails here."""
    path = ROOT / "models" / name
    twin = EncoderMetadata.from_props(
        ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        .get_modelmeta()
        .custom_metadata_map
    )
    views, meet, phase = TWINS[name]
    assert (twin.views, "tokens" if twin.graph_views > 1 else "descriptors") == (views, meet)
    assert twin.column_phase == phase
    assert twin.model_id != meta.model_id and twin.model_id in CARD.read_text()
    assert twin.training_data == meta.training_data and twin.metrics == meta.metrics
    if meet == "descriptors":  # the same graph and weights, byte for byte
        assert twin.graph == meta.graph
    assert list(twin.calibration) == list(meta.calibration)
    for section, entry in twin.calibration.items():
        assert f"--model models/{name}" in entry.chosen_by, (section, entry.chosen_by)
        assert "--write-calibration" in entry.chosen_by, section
        assert entry.data.startswith("data/synth/val"), section  # never a test town


ONE_PASS = ROOT / "models" / "overlapmamba-hdl64-one-pass.onnx"


def test_the_one_pass_file_is_the_shipped_weights_once_a_scan_with_a_spectrum_first_stage(meta):
    """The model card's one-pass file: the shipped network once a scan, columns aligned, its
    descriptor joined to the yaw features' spectrum (chosen on val by
    benchmarks/first_stage.py), calibrated on val by the commands naming that file."""
    from overlapmamba.service.encoder import Encoder

    enc = Encoder(ONE_PASS, intra_op_threads=2)
    got = enc.meta
    assert (enc.views, got.column_phase, got.first_stage) == (1, "aligned", "mixed:0.75:32:sqrt")
    assert got.training_data == meta.training_data and got.metrics == meta.metrics
    assert got.model_id != meta.model_id and got.model_id in CARD.read_text()
    assert list(got.calibration) == list(meta.calibration)
    for section, entry in got.calibration.items():
        assert f"--model models/{ONE_PASS.name}" in entry.chosen_by, (section, entry.chosen_by)
        assert "--write-calibration" in entry.chosen_by, section
        assert entry.data.startswith("data/synth/val"), section  # never a test town
    desc, yaw = enc.describe([np.random.default_rng(0).normal(0, 10, (4000, 3))])
    assert desc.shape == (1, 256 + yaw.shape[1] * 32)  # NetVLAD + 32 frequencies a channel
    assert abs(float(np.linalg.norm(desc)) - 1.0) < 1e-5


@pytest.mark.real_data
@pytest.mark.parametrize(
    "name", ["overlapmamba-hdl64-one-pass.onnx", "overlapmamba-hdl64-one-pass-256.onnx"]
)
def test_the_one_pass_file_keeps_the_cosine_under_turns_of_real_scans(kitti_seq_dir, name):
    """Issue 40's turn bar (0.999) in one pass with the spectrum in the descriptor (in 768
    floats, and reduced to 256), on a sample of KITTI 00 (``benchmarks/first_stage.py``
    turns every scan of both real sets)."""
    from overlapmamba.core.datasets import open_sequence
    from overlapmamba.core.poses import rotation_z, transform_points
    from overlapmamba.service.encoder import Encoder

    enc = Encoder(ROOT / "models" / name, intra_op_threads=2)
    seq = open_sequence(kitti_seq_dir)
    theta = np.random.default_rng(1).uniform(-180, 180, len(seq))
    frames = range(0, len(seq), 10)
    plain = [seq.points(i).xyz for i in frames]
    turned = [transform_points(plain[n], rotation_z(theta[i])) for n, i in enumerate(frames)]
    desc, _ = enc.describe(plain + turned)
    k = len(plain)
    assert (desc[:k] * desc[k:]).sum(1).min() >= 0.999


def test_shipped_model_is_served_by_the_c_kernel(meta):
    """Each block's scan (its forward, backward and shifted directions side by side) is one
    marked node of the shipped file, so the service's C-kernel path can bind it; where a C
    compiler is there, the service builds that path and it agrees with the portable graph."""
    import onnx

    from overlapmamba.core.modelmeta import SCAN_DOMAIN, SCAN_OPS
    from overlapmamba.core.scan_kernel import KernelBuildError, load
    from overlapmamba.service.encoder import Encoder

    model = onnx.load(str(MODEL))
    scans = [n.op_type for n in model.graph.node if n.domain == SCAN_DOMAIN]
    assert scans == [SCAN_OPS[True]] * meta.network["n_blocks"]
    try:
        load()
    except KernelBuildError as err:
        pytest.skip(f"no C kernel here: {err}")
    enc = Encoder(MODEL, intra_op_threads=2, scan_kernel=True)
    assert enc.scan_path.startswith("c-kernel ("), enc.scan_path


def test_the_c_kernel_serves_only_where_it_is_not_slower(monkeypatch, caplog):
    """scan_kernel = auto (the default) times the two paths at load on one scan (its
    views), and keeps the C kernel unless it costs more than the portable graph here."""
    from overlapmamba.core.scan_kernel import KernelBuildError, load
    from overlapmamba.service import encoder as encoder_mod
    from overlapmamba.service.encoder import Encoder

    try:
        load()
    except KernelBuildError as err:
        pytest.skip(f"no C kernel here: {err}")
    calls = []

    def timed(kernel, portable):
        calls.append((kernel(), portable()))  # each runs the parity image once
        return times

    monkeypatch.setattr(encoder_mod, "_time_both", timed)
    times = (30.0, 10.0)  # the kernel three times the portable graph's time
    with caplog.at_level("WARNING", logger="overlapmamba"):
        slow = Encoder(MODEL, intra_op_threads=2)
    assert slow.staged is None and slow.scan_path.startswith("portable (the C kernel was slower")
    assert "30.0 against 10.0 ms" in caplog.text
    views = slow.meta.views
    for (kd, ky), (pd, py) in calls:  # both paths were timed on one scan's views, and agree
        assert kd.shape == pd.shape and abs(kd - pd).max() < 1e-4
        assert views == 3 and ky.shape == py.shape == (views, 16, 900)
    times = (10.5, 10.0)  # within the margin: the kernel (trained with) serves
    fast = Encoder(MODEL, intra_op_threads=2)
    assert fast.staged is not None and fast.scan_path.startswith("c-kernel (")
    assert "10.5 against 10.0 ms" in fast.scan_path
    forced = Encoder(MODEL, intra_op_threads=2, scan_kernel=True)
    assert forced.staged is not None and len(calls) == 2  # True: no timing, the kernel serves


def test_the_load_time_timing_counts_cpu_in_blocks():
    """The two paths are timed by the process's CPU time, each in a block of its own, the
    kernel's first: a call that waits costs nothing there, one that computes costs what it
    computes (by wall time the two below would tie)."""
    import time

    from overlapmamba.service import encoder as encoder_mod

    order = []

    def waits():  # 10 ms of wall time, no CPU
        order.append("kernel")
        time.sleep(0.01)

    def computes():  # 10 ms of CPU time
        order.append("portable")
        t = time.process_time()
        while time.process_time() - t < 0.01:
            pass

    kernel_ms, portable_ms = encoder_mod._time_both(waits, computes)
    calls = encoder_mod.TIMING_CALLS + 1
    assert order == ["kernel"] * calls + ["portable"] * calls
    assert kernel_ms < 2.0 <= 10.0 <= portable_ms < 50.0


def test_scan_choice_times_what_the_service_runs(kitti_seq_dir):
    """benchmarks/scan_choice.py: the images it times are the scans' views as the encoder
    hands them to its graph, and one small run records each load's pick and both paths'
    wall and CPU time a scan."""
    from conftest import benchmark_module

    from overlapmamba.core.datasets import open_sequence
    from overlapmamba.core.scan_kernel import KernelBuildError, load
    from overlapmamba.service.encoder import Encoder

    try:
        load()
    except KernelBuildError as err:
        pytest.skip(f"no C kernel here: {err}")
    bench = benchmark_module("scan_choice")
    enc = Encoder(MODEL, intra_op_threads=1, scan_kernel=True)
    x, source = bench.scans(enc, 2)
    seq = open_sequence(kitti_seq_dir)
    want = np.stack([enc.project_offset(seq.points(i))[0] for i in range(2)])
    assert source.startswith("real KITTI") and x.shape == (2 * enc.views, 1, 64, 900)
    np.testing.assert_array_equal(x.reshape(want.shape), want)
    got = bench.measure(MODEL, loads=1, reps=1)
    assert sum(got["loads"]["picked"].values()) == 1 and len(got["loads"]["logged"]) == 1
    for n in ("1_scans_a_call", "8_scans_a_call"):
        for way in ("c-kernel", "portable"):
            assert got["cost"][n][way]["wall_ms"] > 0 and got["cost"][n][way]["cpu_ms"] > 0


def test_scan_subnormals_times_the_served_views_both_ways_and_restores_the_flush():
    """benchmarks/scan_subnormals.py: one small run gives each real sequence the images the
    service would encode, times the kernel with and without its flush and the portable
    graph, finds the same outputs both ways, and leaves the kernel flushing."""
    from conftest import benchmark_module

    from overlapmamba.core.scan_kernel import KernelBuildError, load

    try:
        lib = load()
    except KernelBuildError as err:
        pytest.skip(f"no C kernel here: {err}")
    if not lib.scan_flush_supported():
        pytest.skip("the kernel flushes subnormals on x86 only")
    bench = benchmark_module("scan_subnormals")
    got = bench.measure(MODEL, scans=2, repeats=1, console=bench.Console(quiet=True))
    assert got is not None and got["max_abs_difference_flush_vs_not"] <= 1e-6
    assert got["served_at_load"].startswith(("c-kernel", "portable"))
    assert "kitti00" in got["sequences"]
    for row in got["sequences"].values():
        assert row["scans_timed"] == 2
        assert min(row[f"{w}_cpu_ms"] for w in ("flush", "no flush", "portable")) > 0
        assert row["flush_scan_ms"] > 0 and row["no flush_scan_ms"] > 0
    assert lib.scan_set_flush(1) == 1  # the run put the service's default back


ONE_PASS_256 = ROOT / "models" / "overlapmamba-hdl64-one-pass-256.onnx"


def test_the_256_float_one_pass_file_is_the_one_pass_first_stage_reduced_on_val(meta):
    """The model card's 256-float one-pass file: the one-pass file's first stage times the
    principal directions fitted on val's vectors (overlapmamba.train.reduce_head: the
    network descriptor's 96 ahead of the spectrum's 160), at unit length; calibrated on val by
    the commands naming that file, its second stage scoring by the network's part."""
    import onnx
    from onnx import numpy_helper

    from overlapmamba.service.encoder import Encoder
    from overlapmamba.train.reduce_head import PREFIX, reduce_vectors

    enc, full = Encoder(ONE_PASS_256, intra_op_threads=2), Encoder(ONE_PASS, intra_op_threads=2)
    got = enc.meta
    assert (enc.views, got.column_phase, got.first_stage) == (1, "aligned", "mixed:0.75:32:sqrt")
    assert got.descriptor_dim == 256 and got.reduction["from_dim"] == 256 + 16 * 32
    assert list(got.reduction["fitted_on"]) == ["val"]  # never a test town
    assert got.training_data == meta.training_data and got.model_id in CARD.read_text()
    assert got.reduction["network_part"] == 96
    assert got.calibration["rerank"].values["score"] == "network"
    for section, entry in got.calibration.items():
        assert f"--model models/{ONE_PASS_256.name}" in entry.chosen_by, (section, entry.chosen_by)
        assert "--write-calibration" in entry.chosen_by, section
        assert entry.data.startswith("data/synth/val"), section
    inits = onnx.load(str(ONE_PASS_256)).graph.initializer
    directions = next(numpy_helper.to_array(t) for t in inits if t.name == PREFIX + "directions")
    points = [np.random.default_rng(s).normal(0, 10, (4000, 3)) for s in range(2)]
    want = reduce_vectors(full.describe(points)[0], directions)
    np.testing.assert_allclose(enc.describe(points)[0], want, atol=1e-5)
