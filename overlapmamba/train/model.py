"""OverlapMamba: range image → yaw-invariant 256-d descriptor + yaw-equivariant column features.

    range image (B, 1, H, W)
      → backbone: bias-free (k, 1) convolutions that shrink the height to 1     (B, 128, 1, W)
      → SPP (optional): 1×1 conv, three sequential circular max-pools, concat   (B, 128, 1, W)
      → convLast1: 1×1 conv + ReLU, W tokens of d_model                         (B, W, d)
        (token_views V > 1: the network takes V sub-column views of each scan, (B·V, 1, H, W),
        and its tokens are their mean: every step before is per column or a circular pool,
        every step after runs once a scan)
      → OverlapMamba blocks: x + Σ_directions mixer(RMSNorm(x))                 (B, W, d)
      → head (GDG): concat(in, out) → convLast2 → NetVLAD → gating → L2        (B, 256)
      → yaw head: 1×1 projection of the block output                            (B, C, W)

**Exact yaw equivariance.** Turning the sensor rolls the range image along its width. Every
operation that spans columns is circular: the max-pools pad circularly, the depthwise conv
of the mixer pads circularly, and the selective scan starts from the ring's periodic state
(:mod:`overlapmamba.train.scan`). So rolling the input by k columns rolls every per-column feature
by k, and NetVLAD, which ignores order, makes the descriptor invariant.

**Directions.** Forward and backward (flipped) scans share one weight set. A third branch,
with its own conv/x_proj/dt_proj like the reference's shifted branches, scans the sequence
rolled by a random shift in training and by none at inference, so inference is
deterministic and still evaluates the network that was trained (dropping the branch at
inference would not). With the circular scan the shift changes nothing but rounding; without
it, the shift is an augmentation. Every branch is un-flipped/un-rolled *before* the gate, so
the gate multiplies the tokens it was computed from (the reference gates misaligned tokens).
"""

from __future__ import annotations

import math
from typing import ClassVar

import torch
import torch.nn.functional as F
from pydantic import Field, model_validator
from torch import Tensor, nn

from overlapmamba.core.configs import Config
from overlapmamba.core.sensors.input import MODES
from overlapmamba.core.views import COLUMN_PHASES, MAX_VIEWS
from overlapmamba.train.errors import ConfigError
from overlapmamba.train.scan_backends import BACKENDS, scan

MIXERS = ("mamba", "transformer")
BACKBONES = ("reference", "all-rows")


class OverlapMambaConfig(Config):
    """The network's shape (and how its scan runs): travels in checkpoints and config files."""

    config_error: ClassVar[type[Exception]] = ConfigError

    sensor: str = "kitti-hdl64"  # overlapmamba.core sensor profile the range images come from
    height: int = 64  # range-image rows (beams)
    width: int = 900  # range-image columns: the token count
    # How scans become the image (overlapmamba.core.sensors.input, the exported metadata's
    # sensor_input): elevation (the profile's own sensor natively, others by elevation),
    # rows, common (every sensor, the profile's own too, thinned to common beams),
    # structure (common, above the ground and within a common range), bev (rows: rings of
    # range × height bands, a polar bird's-eye occupancy of every scan), bev-soft or bev-span
    # (bev's cells shared between columns, so the image moves with a turn: core.sensors.bev)
    sensor_input: str = "elevation"
    # Where the image's columns start (overlapmamba.core.views, the exported metadata's
    # column_phase): sensor (the sensor's own azimuth) or aligned (each scan's mean bearing
    # at a column centre, so a turn rolls the image by whole columns)
    column_phase: str = "sensor"
    # reference (the reference code's layers: on 64 rows the descriptor sees rows 0–26 only)
    # or all-rows (every row reaches it): _backbone
    backbone: str = "reference"
    spp: bool = True  # sequential spatial-pyramid pooling after the backbone
    d_model: int = 256  # token width after convLast1
    d_state: int = 16  # N: SSM state per channel
    expand: int = 2  # E = expand · d_model channels inside the mixer
    d_conv: int = 4  # depthwise conv kernel inside the mixer
    dt_rank: int = 16  # rank of the Δ projection
    n_blocks: int = 1  # stacked OverlapMamba blocks (paper Table III: 1 vs 2)
    mixer: str = "mamba"  # mamba (OverlapMamba blocks) or transformer (OverlapTransformer-style)
    heads: int = 4  # attention heads of the transformer mixer
    ff_dim: int = 1024  # feed-forward width of the transformer mixer
    bidirectional: bool = True  # also scan the flipped sequence (shared weights)
    shift: bool = True  # third branch; its sequence is rolled at random in training only
    circular: bool = True  # ring start for the scan, circular conv padding
    conv_last2: int = 1024  # head width before NetVLAD
    clusters: int = 64  # NetVLAD clusters
    out_dim: int = 256  # descriptor size
    gating: bool = True  # context gating on the descriptor
    yaw_channels: int = 16  # per-column features for yaw estimation
    # Sub-column views (overlapmamba.core.views) met at the tokens: the network takes
    # token_views images a scan, scan-major, and averages their tokens before the blocks, so
    # the mixer and head run once a scan. 1: one image a scan.
    token_views: int = 1
    scan_backend: str = "auto"  # auto, fused, chunked, loop, onnx or ref (scan_backends.scan)
    scan_chunk: int | None = None  # chunked-scan chunk length (None: √W)
    extra: dict = Field(default_factory=dict)  # free-form notes carried in checkpoints

    @model_validator(mode="after")
    def _check(self) -> OverlapMambaConfig:
        sizes: tuple[str, ...] = ("height", "width", "d_model", "d_state", "expand", "d_conv")
        sizes += ("dt_rank",)
        sizes += ("n_blocks", "conv_last2", "clusters", "out_dim", "yaw_channels", "heads")
        sizes += ("ff_dim", "token_views")
        for name in sizes:
            if not isinstance(getattr(self, name), int) or getattr(self, name) < 1:
                raise ValueError(f"{name} must be a positive integer, got {getattr(self, name)!r}")
        if self.token_views > MAX_VIEWS:
            raise ValueError(f"token_views must be at most {MAX_VIEWS}, got {self.token_views}")
        if self.sensor_input not in MODES:
            raise ValueError(
                f"sensor_input {self.sensor_input!r} is unknown; allowed: {', '.join(MODES)}"
            )
        if self.column_phase not in COLUMN_PHASES:
            allowed = ", ".join(COLUMN_PHASES)
            raise ValueError(f"column_phase {self.column_phase!r} is unknown; allowed: {allowed}")
        if self.backbone not in BACKBONES:
            raise ValueError(
                f"backbone {self.backbone!r} is unknown; allowed: {', '.join(BACKBONES)}"
            )
        if self.mixer not in MIXERS:
            raise ValueError(f"mixer {self.mixer!r} is unknown; allowed: {', '.join(MIXERS)}")
        if self.mixer == "transformer" and self.d_model % self.heads:
            raise ValueError(f"d_model {self.d_model} is not divisible by heads {self.heads}")
        if self.scan_backend not in BACKENDS:
            raise ValueError(
                f"scan_backend {self.scan_backend!r} is unknown; allowed: {', '.join(BACKENDS)}"
            )
        return self

    @property
    def d_inner(self) -> int:
        return self.expand * self.d_model


def _backbone(height: int, kind: str = "reference") -> nn.Sequential:
    """Bias-free (k, 1) convs with ReLU; strides (2, 1) halve the height until it is 1.

    ``reference``: the reference code's layers. A strided conv drops the rows its last step
    does not reach, and the 1 × 1 convs with stride (2, 1) that finish the height keep only
    their first row: on a 64-row image the descriptor depends on rows 0–26 alone, the upper
    part of KITTI's field of view (``benchmarks/receptive_rows.py`` measures it on a file).
    ``all-rows``: the same convolutions, each strided one given the zero rows below the
    image that let its last step reach the bottom row, and one (h, 1) convolution in place
    of the 1 × 1 convs that finish the height: every row reaches the descriptor (on a
    64-row image, 102 k backbone weights against 86 k)."""
    if kind not in BACKBONES:
        raise ValueError(f"backbone {kind!r} is unknown; allowed: {', '.join(BACKBONES)}")
    specs = [(1, 16, 5, 1), (16, 32, 3, 2), (32, 64, 3, 2), (64, 64, 3, 2), (64, 128, 2, 2)]
    layers: list[nn.Module] = []
    h = height
    for cin, cout, k, s in specs:
        if h < k:  # short images (few beams): keep the kernel inside the image
            k, s = h, 1
        pad = (-(h - k)) % s if kind == "all-rows" else 0
        if pad:
            layers.append(nn.ZeroPad2d((0, 0, 0, pad)))
        layers += [nn.Conv2d(cin, cout, (k, 1), stride=(s, 1), bias=False), nn.ReLU(inplace=True)]
        h = (h + pad - k) // s + 1
    if kind == "all-rows":
        layers += [nn.Conv2d(128, 128, (h, 1), bias=False), nn.ReLU(inplace=True)]
        return nn.Sequential(*layers)
    layers += [nn.Conv2d(128, 128, 1, bias=False), nn.ReLU(inplace=True)]
    while h > 1:
        layers += [nn.Conv2d(128, 128, 1, stride=(2, 1), bias=False), nn.ReLU(inplace=True)]
        h = (h - 1) // 2 + 1
    return nn.Sequential(*layers)


class CircularMaxPool(nn.Module):
    """Max-pool along the width with wrap-around padding (1, k), stride 1."""

    def __init__(self, k: int) -> None:
        super().__init__()
        self.k = k

    def forward(self, x: Tensor) -> Tensor:  # (B, C, 1, W)
        p = self.k // 2
        return F.max_pool2d(torch.cat([x[..., -p:], x, x[..., :p]], dim=-1), (1, self.k), 1)


class SPP(nn.Module):
    """YOLO-style SPPF: 1×1 conv 128→64, three sequential pools, concat 256 → 1×1 → 128."""

    def __init__(self, c: int = 128, k: int = 5, circular: bool = True) -> None:
        super().__init__()
        h = c // 2
        self.cv1 = nn.Sequential(nn.Conv2d(c, h, 1, bias=False), nn.BatchNorm2d(h), nn.SiLU())
        self.cv2 = nn.Sequential(nn.Conv2d(4 * h, c, 1, bias=False), nn.BatchNorm2d(c), nn.SiLU())
        self.pool = CircularMaxPool(k) if circular else nn.MaxPool2d((1, k), 1, (0, k // 2))

    def forward(self, x: Tensor) -> Tensor:
        x = self.cv1(x)
        p1 = self.pool(x)
        p2 = self.pool(p1)
        return self.cv2(torch.cat([x, p1, p2, self.pool(p2)], dim=1))


class RMSNorm(nn.Module):
    def __init__(self, d: int, eps: float = 1e-5) -> None:
        super().__init__()
        self.eps = eps
        self.weight = nn.Parameter(torch.ones(d))

    def forward(self, x: Tensor) -> Tensor:
        return x * torch.rsqrt(x.pow(2).mean(-1, keepdim=True) + self.eps) * self.weight


class _Branch(nn.Module):
    """The per-direction part of the mixer: depthwise conv, Δ/B/C projections."""

    def __init__(self, cfg: OverlapMambaConfig) -> None:
        super().__init__()
        E, R, N = cfg.d_inner, cfg.dt_rank, cfg.d_state
        self.circular = cfg.circular
        self.conv = nn.Conv1d(E, E, cfg.d_conv, groups=E, bias=True)
        self.x_proj = nn.Linear(E, R + 2 * N, bias=False)
        self.dt_proj = nn.Linear(R, E, bias=True)
        # Initialise the Δ bias so that softplus(bias) lies in [0.001, 0.1] (Mamba's recipe):
        # each channel starts with its own time scale.
        dt = torch.exp(torch.rand(E) * (math.log(0.1) - math.log(0.001)) + math.log(0.001))
        with torch.no_grad():
            self.dt_proj.bias.copy_(dt + torch.log(-torch.expm1(-dt)))
        nn.init.uniform_(self.dt_proj.weight, -(R**-0.5), R**-0.5)

    def prepare(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Tokens (B, L, E) in this branch's order → the scan's u, Δ (B, L, E), B, C (B, L, N)."""
        k = self.conv.kernel_size[0]
        x = x.transpose(1, 2)  # the depthwise conv runs channel-major
        if self.circular:  # the column before the first is the last one
            xc = torch.cat([x[..., -(k - 1) :], x], dim=-1) if k > 1 else x
        else:
            xc = F.pad(x, (k - 1, 0))
        x = F.silu(self.conv(xc)).transpose(1, 2)  # (B, L, E)
        R = self.dt_proj.in_features
        N = (self.x_proj.out_features - R) // 2
        dt, Bm, Cm = self.x_proj(x).split([R, N, N], dim=-1)
        return x, softplus(self.dt_proj(dt)), Bm, Cm


def softplus(x: Tensor) -> Tensor:
    """log(1 + eˣ), stable for any x; the same as F.softplus to float rounding.

    Written out because onnxruntime's Softplus kernel is scalar code: on the reference
    model's Δ it took longer than the rest of the mixer.
    """
    return F.relu(x) + torch.log1p(torch.exp(-x.abs()))


class OverlapMambaBlock(nn.Module):
    """x + Σ_directions mixer(RMSNorm(x)), with the gate aligned to its tokens."""

    def __init__(self, cfg: OverlapMambaConfig) -> None:
        super().__init__()
        self.cfg = cfg
        E, N = cfg.d_inner, cfg.d_state
        self.norm = RMSNorm(cfg.d_model)
        self.in_proj = nn.Linear(cfg.d_model, 2 * E, bias=False)
        self.out_proj = nn.Linear(E, cfg.d_model, bias=False)
        self.A_log = nn.Parameter(
            torch.log(torch.arange(1, N + 1, dtype=torch.float32)).repeat(E, 1)
        )
        self.D = nn.Parameter(torch.ones(E))
        self.main = _Branch(cfg)  # forward and flipped-backward
        self.shifted = _Branch(cfg) if cfg.shift else None

    def forward(self, x: Tensor) -> Tensor:  # (B, L, d) → (B, L, d)
        cfg = self.cfg
        u, z = self.in_proj(self.norm(x)).chunk(2, dim=-1)  # (B, L, E) each
        Bsz, L, _ = u.shape
        # Every direction goes through one scan call, stacked on the batch axis: forward and
        # flipped share the main branch's weights, the shifted branch has its own. A and D
        # are shared by all. Batch slices use explicit bounds (not chunk/split), which keeps
        # the batch size symbolic in an exported graph.
        parts = [self.main.prepare(torch.cat([u, u.flip(1)]) if cfg.bidirectional else u)]
        s = 0
        if self.shifted is not None:
            s = int(torch.randint(1, L, ())) if self.training and L > 1 else 0
            parts.append(self.shifted.prepare(torch.roll(u, s, 1) if s else u))
        u_all, delta, Bm, Cm = (
            torch.cat(p) if len(parts) > 1 else p[0] for p in zip(*parts, strict=True)
        )
        ys = scan(
            u_all,
            delta,
            -torch.exp(self.A_log),
            Bm,
            Cm,
            self.D,
            cfg.circular,
            backend=cfg.scan_backend,
            chunk=cfg.scan_chunk,
        )
        y = ys[:Bsz]
        i = Bsz
        if cfg.bidirectional:
            y = y + ys[i : i + Bsz].flip(1)
            i += Bsz
        if self.shifted is not None:
            shifted = ys[i : i + Bsz]
            y = y + (torch.roll(shifted, -s, 1) if s else shifted)  # un-roll before the gate
        y = y * F.silu(z)  # gate the tokens it was computed from
        return x + self.out_proj(y)


def _mixer_block(cfg: OverlapMambaConfig) -> nn.Module:
    """One token mixer (B, L, d) → (B, L, d).

    ``transformer`` is the OverlapTransformer-style baseline (the paper's "Baseline" row):
    one post-norm encoder layer as in OverlapTransformer (ReLU feed-forward, dropout 0.1).
    It has no positional encoding, so it is permutation-equivariant over columns and the
    descriptor stays yaw-invariant; OverlapTransformer also has no SPP (set ``spp = False``).
    """
    if cfg.mixer == "transformer":
        return nn.TransformerEncoderLayer(
            cfg.d_model, cfg.heads, cfg.ff_dim, dropout=0.1, batch_first=True
        )
    return OverlapMambaBlock(cfg)


class NetVLAD(nn.Module):
    """Soft-assignment VLAD over W column features, intra-normalised, then L2."""

    def __init__(self, dim: int, clusters: int) -> None:
        super().__init__()
        self.assign = nn.Linear(dim, clusters, bias=True)
        self.centroids = nn.Parameter(torch.randn(clusters, dim) / math.sqrt(dim))

    def forward(self, x: Tensor) -> Tensor:  # (B, L, dim) → (B, clusters·dim)
        a = torch.softmax(self.assign(x), dim=-1)  # (B, L, K)
        vlad = torch.einsum("blk,bld->bkd", a, x) - a.sum(1)[..., None] * self.centroids
        vlad = F.normalize(vlad, dim=-1)
        return F.normalize(vlad.flatten(1), dim=-1)


class OverlapMamba(nn.Module):
    def __init__(self, cfg: OverlapMambaConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg = cfg or OverlapMambaConfig()
        self.backbone = _backbone(cfg.height, cfg.backbone)
        self.spp = SPP(128, circular=cfg.circular) if cfg.spp else None
        self.conv_last1 = nn.Sequential(nn.Conv2d(128, cfg.d_model, 1, bias=True), nn.ReLU())
        self.blocks = nn.ModuleList(_mixer_block(cfg) for _ in range(cfg.n_blocks))
        self.conv_last2 = nn.Sequential(
            nn.Conv1d(2 * cfg.d_model, cfg.conv_last2, 1, bias=False), nn.ReLU()
        )
        self.vlad = NetVLAD(cfg.conv_last2, cfg.clusters)
        self.reduce = nn.Linear(cfg.clusters * cfg.conv_last2, cfg.out_dim, bias=False)
        self.gate = nn.Linear(cfg.out_dim, cfg.out_dim) if cfg.gating else None
        self.yaw_head = nn.Conv1d(cfg.d_model, cfg.yaw_channels, 1)
        # He initialisation for the ReLU convolutions. PyTorch's default (uniform, gain 1/√3)
        # shrinks the signal about 4× per bias-free layer: after the 11 backbone layers every
        # scan looked alike (std 2e-4), SPP's batch norm cannot undo that in eval mode, and
        # the untrained network gave one descriptor for every scan.
        for conv in [*self.backbone, self.conv_last1[0], self.conv_last2[0]]:
            if isinstance(conv, nn.Conv1d | nn.Conv2d):
                nn.init.kaiming_normal_(conv.weight, nonlinearity="relu")

    def forward(self, image: Tensor) -> tuple[Tensor, Tensor]:
        """image (B, 1, H, W) → descriptor (B, out_dim) unit norm, yaw features (B, C, W);
        with ``token_views`` V > 1, image (B·V, 1, H, W): each scan's V views in a row."""
        f = self.backbone(image)  # (B·V, 128, 1, W)
        if self.spp is not None:
            f = self.spp(f)
        tokens = self.conv_last1(f).squeeze(2)  # (B·V, d, W)
        if self.cfg.token_views > 1:
            tokens = tokens.unflatten(0, (-1, self.cfg.token_views)).mean(1)
        tokens = tokens.transpose(1, 2)  # (B, W, d)
        x = tokens
        for block in self.blocks:
            x = block(x)
        feats = torch.cat([x, tokens], dim=-1).transpose(1, 2)  # (B, 2d, W)
        h = F.normalize(self.conv_last2(feats), dim=1).transpose(1, 2)  # (B, W, conv_last2)
        d = self.reduce(self.vlad(h))
        if self.gate is not None:
            d = d * torch.sigmoid(self.gate(d))
        return F.normalize(d, dim=-1), self.yaw_head(x.transpose(1, 2))


def channels_last(model: OverlapMamba) -> OverlapMamba:
    """``model`` with its convolutions' weights stored channels-last (in place; the same
    numbers, within float rounding): the backbone's convolutions and pools then run on
    oneDNN's blocked kernels without reordering each layer's input (faster on CPU, for
    training and evaluation alike: ``benchmarks/train_speed.py``). Every training run and
    every checkpoint loaded for evaluation uses it; an export does not need it (an ONNX graph
    has no memory layout)."""
    for m in model.modules():  # Module.to's typing has no memory_format
        for p in m.parameters(recurse=False):
            if p.dim() == 4:
                p.data = p.data.contiguous(memory_format=torch.channels_last)
    return model


def meeting_views(model: OverlapMamba, token_views: int) -> OverlapMamba:
    """``model``'s weights in a network that averages ``token_views`` views of a scan at its
    tokens (1: one image a scan), in eval mode; ``model`` itself when it already does."""
    if model.cfg.token_views == token_views:
        return model
    cfg = OverlapMambaConfig.from_dict({**model.cfg.to_dict(), "token_views": token_views})
    out = OverlapMamba(cfg).eval()
    out.load_state_dict(model.state_dict())
    return out
