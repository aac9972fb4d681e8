"""OverlapMamba network: shapes, configurations and exact yaw equivariance."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from overlapmamba.train.model import OverlapMamba, OverlapMambaConfig  # noqa: E402

SMALL = dict(width=120, d_model=32, d_state=4, dt_rank=4, conv_last2=48, clusters=6, out_dim=32)


def model(**kw) -> OverlapMamba:
    torch.manual_seed(0)
    return OverlapMamba(OverlapMambaConfig(**{**SMALL, **kw})).eval()


def image(B: int = 2, H: int = 64, W: int = 120, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(B, 1, H, W, generator=g) * 60
    x[torch.rand(B, 1, H, W, generator=g) < 0.2] = -1.0  # empty pixels, as projected
    return x


def test_reference_configuration_has_the_reference_size():
    m = OverlapMamba()
    n = sum(p.numel() for p in m.parameters())
    assert 17.5e6 < n < 18.8e6  # model-facts.md: ≈18.2M effective
    d, yaw = m.eval()(image(1, W=900))
    assert d.shape == (1, 256) and yaw.shape == (1, 16, 900)
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(1))


@pytest.mark.parametrize(
    "kw",
    [
        {},
        {"spp": False},
        {"shift": False},
        {"bidirectional": False},
        {"n_blocks": 2},
        {"gating": False},
        {"height": 32},
        {"backbone": "all-rows"},
        {"backbone": "all-rows", "height": 32},
    ],
)
def test_ablations_are_config_changes_and_stay_equivariant(kw):
    m = model(**kw)
    x = image(H=kw.get("height", 64))
    with torch.no_grad():
        d, yaw = m(x)
        for k in (1, 37, 119):
            d_k, yaw_k = m(torch.roll(x, k, dims=-1))
            assert (d * d_k).sum(-1).min() >= 0.99999
            torch.testing.assert_close(yaw_k, torch.roll(yaw, k, dims=-1), rtol=1e-4, atol=1e-5)


def rows_reaching_the_descriptor(m: OverlapMamba, H: int) -> list[int]:
    x = image(1, H=H)
    with torch.no_grad():
        d = m(x)[0]
        rows = []
        for r in range(H):
            y = x.clone()
            y[..., r, :] = 123.0  # a change the row cannot hide from a network that reads it
            if (m(y)[0] - d).abs().max() > 1e-6:
                rows.append(r)
    return rows


@pytest.mark.parametrize(
    ("H", "reference_rows"), [(64, range(27)), (32, range(27)), (16, range(15)), (5, range(5))]
)
def test_the_all_rows_backbone_reads_every_row_the_reference_drops_some(H, reference_rows):
    """The reference layers' strided 1 × 1 convolutions keep their first row only: on 64 rows
    the descriptor never reads rows 27–63 (benchmarks/receptive_rows.py measures the shipped
    file). ``all-rows`` pads the strided convolutions and ends in one (h, 1) convolution."""
    assert rows_reaching_the_descriptor(model(height=H), H) == list(reference_rows)
    assert rows_reaching_the_descriptor(model(height=H, backbone="all-rows"), H) == list(range(H))


def test_without_circular_mode_equivariance_breaks():
    m = model(circular=False)
    x = image()
    with torch.no_grad():
        y = m(x)[1]
        y_k = m(torch.roll(x, 37, dims=-1))[1]
    assert (y_k - torch.roll(y, 37, dims=-1)).abs().max() > 1e-4


def test_inference_is_deterministic_and_the_shift_is_training_only():
    x = image()
    # Circular: the random shift changes nothing, so training evaluates the inference network
    # (no SPP here: its batch norm uses batch statistics in training).
    m = model(spp=False)
    with torch.no_grad():
        torch.testing.assert_close(m(x)[0], m(x)[0], rtol=0, atol=0)
        ref = m(x)[0]
        m.train()
        torch.testing.assert_close(m(x)[0], ref, rtol=1e-5, atol=1e-6)
    # Open scan: the shift is an augmentation, different on each training call.
    m = model(spp=False, circular=False).train()
    torch.manual_seed(1)
    a = m(x)[0]
    torch.manual_seed(2)
    b = m(x)[0]
    assert not torch.allclose(a, b)
    a.sum().backward()
    assert m.blocks[0].shifted.x_proj.weight.grad is not None


@pytest.mark.real_data
def test_descriptor_is_invariant_to_yaw_on_a_real_scan(kitti_seq_dir):
    from overlapmamba.core.io import read_points
    from overlapmamba.core.projection import project
    from overlapmamba.core.sensors import get_profile

    scan = read_points(kitti_seq_dir / "velodyne" / "000040.bin")
    x = torch.from_numpy(project(scan, get_profile("kitti-hdl64")))[None, None]
    torch.manual_seed(0)
    m = OverlapMamba().eval()
    rng = np.random.default_rng(7)
    with torch.no_grad():
        d, yaw = m(x)
        for k in rng.integers(1, 900, 2):
            d_k, yaw_k = m(torch.roll(x, int(k), dims=-1))
            assert float((d * d_k).sum()) >= 0.99999
            torch.testing.assert_close(
                yaw_k, torch.roll(yaw, int(k), dims=-1), rtol=1e-4, atol=1e-5
            )


def test_backends_give_the_same_network():
    x = image()
    m = model()
    with torch.no_grad():
        outs = {}
        for backend in ("fused", "chunked", "ref"):
            m.cfg.scan_backend = backend
            for b in m.blocks:
                b.cfg.scan_backend = backend
            outs[backend] = m(x)
    for backend in ("chunked", "ref"):
        for a, b in zip(outs["fused"], outs[backend], strict=True):
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


def test_untrained_network_tells_scans_apart():
    # Regression: with PyTorch's default init the bias-free backbone shrank the signal ~5000×
    # and every scan got the same descriptor in eval mode (pairwise distance ~1e-9).
    torch.manual_seed(0)
    m = OverlapMamba().eval()
    with torch.no_grad():
        d, _ = m(image(3, W=900))
    dist = torch.cdist(d, d)[~torch.eye(3, dtype=torch.bool)]
    assert dist.min() > 1e-3


def test_config_round_trips_and_rejects_bad_values():
    cfg = OverlapMambaConfig(**SMALL)
    assert OverlapMambaConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError, match="unknown config fields \\['d_modle'\\]"):
        OverlapMambaConfig.from_dict({"d_modle": 8})
    with pytest.raises(ValueError, match="d_state must be a positive integer"):
        OverlapMambaConfig(d_state=0)
    with pytest.raises(ValueError, match="allowed: auto, fused, chunked, loop, onnx, ref"):
        OverlapMambaConfig(scan_backend="gpu")
    with pytest.raises(ValueError, match="backbone 'all' is unknown; allowed: reference, all-rows"):
        OverlapMambaConfig(backbone="all")


@pytest.mark.real_data
def test_yaw_features_give_the_turn_of_a_real_scan(kitti_seq_dir):
    """A real scan turned about z by θ (any angle, not a column multiple): the yaw estimated
    from the model's per-column features is within 1° of θ."""
    from overlapmamba.core.io import read_points
    from overlapmamba.core.poses import rotation_z, transform_points
    from overlapmamba.core.projection import project
    from overlapmamba.core.sensors import get_profile
    from overlapmamba.core.yaw import estimate_yaw

    profile = get_profile("kitti-hdl64")
    m = model(width=900)
    for frame, theta in ((10, 13.37), (55, -71.9), (90, 158.2)):
        xyz = read_points(kitti_seq_dir / "velodyne" / f"{frame:06d}.bin").xyz
        views = [project(xyz, profile), project(transform_points(xyz, rotation_z(-theta)), profile)]
        with torch.no_grad():
            _, feats = m(torch.from_numpy(np.stack(views))[:, None])
        yaw, _ = estimate_yaw(feats[0].numpy(), feats[1].numpy())
        assert abs(yaw[0] - theta) < 1.0, (frame, theta, yaw)
