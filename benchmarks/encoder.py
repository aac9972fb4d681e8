"""ONNX encoder speed: the exported graph against the same graph with the scan taken out.

Variants, all the reference configuration (18.1 M parameters, three scan directions; or
the narrow one with ``--narrow``) with the same random weights, exported by
``overlapmamba.train.export`` and run by onnxruntime on CPU:

- ``shipped file (served)`` (``--narrow``, the shipped width) — ``models/overlapmamba-hdl64.onnx``
  itself, trained weights, loaded as the service loads it (``scan_kernel = "auto"``: the C
  kernel where it agrees and is not the slower, else the portable graph; the path it took is
  recorded), one image a call;
- ``c-kernel`` — the same random weights as the rows below on the C-kernel path, forced
  (``overlapmamba.service.encoder``): the graph cut at its scan nodes, each scan by the C
  kernel (``overlapmamba.service.fastscan``);
- ``scan-loop`` — the portable form: the scan as ONNX Scan loops over L/T chunks side by
  side (T = √L = 30), NetVLAD's reduction matrix stored int8;
- ``scan-loop fp32`` — the same with every weight float32;
- ``scan-seq`` — one chunk (T = L = 900): the same loops, step by step, as a plain
  per-column loop would run;
- ``no-scan`` — the scan replaced by y = u (everything else identical): the yardstick of
  the goal "encoder ÷ encoder without scan ≤ 1.25" (timed interleaved with the served
  encoder for that ratio, and on its own in the table);
- ``torch eager`` — PyTorch on the same inputs (fused C scan kernel).

**Peer** (``--no-peer`` skips it; with ``--narrow`` ours is the shipped file, as the service
loads it): OverlapTransformer's network as our OT-style config
(``mixer="transformer", spp=False``: OT's backbone, one transformer layer d 256 / 4 heads /
feed-forward 1024, convLast2 1024, NetVLAD 64 clusters → 256, gating), exported to ONNX with
the same int8 head and timed **interleaved** with the served encoder on the same image: each
repetition runs ours as the product runs it (``--views``, default the shipped model's
sub-column views: that many images a scan in one encoder call), ours in one pass, and the
peer, in turn, so load on the shared machine hits all three alike.

Reports medians and p90 (B = 1 at 1 and 2 threads, B = 8 at 2 threads per scan), max
error against PyTorch, node count (loop bodies included), file size, load time, the ratios,
the FLOP count of the shipped graph with the fraction of this machine's peak, and
onnxruntime's per-operator-type profile of the shipped graph. Prints tables and writes JSON
(default reports/service/encoder.json). Real KITTI range images when ../shared/data is
present, else seeded random ones (speed does not depend on the content).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import onnxruntime as ort
import torch
from encoder_tables import print_tables
from onnx_profile import op_profile
from reports_kit import REPORTS, write_report
from rich.console import Console
from torch.utils.flop_counter import FlopCounterMode

import overlapmamba.train.model as model_module
from overlapmamba.core.sensors import get_profile
from overlapmamba.train.export import count_nodes, export_onnx
from overlapmamba.train.model import OverlapMamba, OverlapMambaConfig
from overlapmamba.train.modelfile import read_metadata
from overlapmamba.train.presets import NARROW

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "kitti00_0000-0100"
SHIPPED_MODEL = ROOT / "models" / "overlapmamba-hdl64.onnx"
PROFILE = get_profile("kitti-hdl64")


def images(n: int) -> tuple[np.ndarray, str]:
    if (REAL / "velodyne").is_dir():
        from overlapmamba.core.io import read_points
        from overlapmamba.core.projection import project

        paths = sorted((REAL / "velodyne").glob("*.bin"))[:n]
        x = np.stack([project(read_points(p), PROFILE) for p in paths])[:, None]
        return x.astype(np.float32), f"real KITTI 00 frames 0–{n - 1}"
    rng = np.random.default_rng(0)
    return rng.uniform(0, 50, (n, 1, 64, 900)).astype(np.float32), "random images"


@contextlib.contextmanager
def scan_taken_out():
    """Benchmark only: the model's scan call returns its input u (no recurrence)."""
    real = model_module.scan
    model_module.scan = lambda u, *args, **kwargs: u * 1.0
    try:
        yield
    finally:
        model_module.scan = real


def session(path: Path, threads: int) -> ort.InferenceSession:
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    # Workers stop spinning when a run ends: a session timed in turn with another must not
    # leave its workers spinning into the other's time.
    so.add_session_config_entry("session.force_spinning_stop", "1")
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


def timed(fn, reps: int) -> np.ndarray:
    for _ in range(3):
        fn()
    out = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return np.asarray(out) * 1e3


def stats(ms: np.ndarray) -> dict[str, float]:
    return {"median_ms": float(np.median(ms)), "p90_ms": float(np.percentile(ms, 90))}


def measure(run_b1, run_b8, reps: int, set_threads) -> dict[str, Any]:
    res: dict[str, Any] = {}
    for threads in (1, 2):
        set_threads(threads)
        res[f"b1_t{threads}"] = stats(timed(run_b1, reps))
    set_threads(2)
    b8 = timed(run_b8, max(5, reps // 4))
    res["b8_t2"] = stats(b8)
    res["b8_t2_per_scan_ms"] = float(np.median(b8)) / 8
    return res


def onnx_variant(path: Path, x1, x8, ref, reps: int) -> dict[str, Any]:
    t = time.perf_counter()
    session(path, 1)
    load_s = time.perf_counter() - t
    sessions = {th: session(path, th) for th in (1, 2)}
    current = {"t": 1}

    def run(x):
        return sessions[current["t"]].run(None, {"range_image": x})

    res = measure(lambda: run(x1), lambda: run(x8), reps, lambda th: current.update(t=th))
    d, y = sessions[2].run(None, {"range_image": x8})
    total, loops = count_nodes(onnx.load(str(path)))
    res |= {
        "descriptor_max_abs": float(np.abs(d - ref[0]).max()),
        "yaw_max_abs": float(np.abs(y - ref[1]).max()),
        "nodes": total,
        "scan_nodes": loops,
        "file_mb": path.stat().st_size / 1e6,
        "load_s": load_s,
    }
    return res


SHIPPED_ONE_VIEW = ROOT / "models" / "overlapmamba-hdl64-one-view.onnx"  # its weights, one view


def _encode(enc: Any, x: np.ndarray) -> Any:
    """One call of ``enc`` on one image a scan ``x`` (B, 1, H, W), shaped as the file takes
    it: its views (the same image, so the same cost as a scan's views), and zero column
    offsets where it aligns its columns."""
    xv = np.repeat(x, enc.views, axis=1)
    return enc.encode(xv, np.zeros(len(x)) if enc.meta.aligned else None)


def served_variant(path: Path, x1, x8, ref, reps: int, scan_kernel: Any) -> dict[str, Any]:
    """The file through the service's encoder: ``scan_kernel`` True forces the C-kernel
    path, "auto" chooses as the service does. ``ref`` None: weights other than PyTorch's
    model here (the shipped file), no error against it."""
    from overlapmamba.service.encoder import Encoder

    t = time.perf_counter()
    encoders = {th: Encoder(path, intra_op_threads=th, scan_kernel=scan_kernel) for th in (1, 2)}
    load_s = (time.perf_counter() - t) / 2
    current = {"t": 1}

    def run(x):
        return _encode(encoders[current["t"]], x)

    res = measure(lambda: run(x1), lambda: run(x8), reps, lambda th: current.update(t=th))
    out = res | {
        "model_id": encoders[2].model_id,
        "views": encoders[2].views,  # images a scan, one call
        "scan_path": encoders[2].scan_path,
        "scan_path_t1": encoders[1].scan_path,
        "load_s": load_s,
    }
    if ref is not None:
        d, y = encoders[2].encode(x8)
        out["descriptor_max_abs"] = float(np.abs(d - ref[0]).max())
        out["yaw_max_abs"] = float(np.abs(y - ref[1]).max())
    return out


def alternate(*fns, n: int) -> list[float]:  # type: ignore[no-untyped-def]
    """Median seconds of each of ``fns`` called in turn ``n`` times (after 3 warm-ups), so
    load on the shared machine hits them all alike."""
    times: list[list[float]] = [[] for _ in fns]
    for i in range(n + 3):
        for f, t in zip(fns, times, strict=True):
            t0 = time.perf_counter()
            f()
            if i >= 3:
                t.append(time.perf_counter() - t0)
    return [float(np.median(t)) for t in times]


def yardstick_comparison(ours_path: Path, noscan_path: Path, x1, reps: int) -> dict[str, Any]:
    """Served encoder vs the same graph without its scan, B = 1, alternating every repetition,
    at 1 and 2 threads: the goal's ratio, free of drift between separately timed variants."""
    from overlapmamba.service.encoder import Encoder

    out: dict[str, Any] = {}
    for th in (1, 2):
        ours, base = Encoder(ours_path, intra_op_threads=th), session(noscan_path, th)
        a, b = alternate(
            lambda o=ours: o.encode(x1), lambda s=base: s.run(None, {"range_image": x1}), n=reps
        )
        out[f"b1_t{th}"] = {"served_ms": a * 1e3, "noscan_ms": b * 1e3, "ratio": a / b}
        if ours.staged is not None:  # where the served time goes: kernel vs sessions
            g, parts = ours.staged, {"sessions": 0.0, "scan": 0.0}
            alternate(
                lambda g=g, p=parts: g.run(x1, p),
                lambda s=base: s.run(None, {"range_image": x1}),
                n=reps,
            )
            n = reps + 3  # alternate's warm-ups run too
            sessions, scan = parts["sessions"] / n * 1e3, parts["scan"] / n * 1e3
            out[f"b1_t{th}"] |= {
                "sessions_ms": sessions,
                "kernel_ms": scan,
                # the ratio left if the kernel took no time: the stages alone ÷ the yardstick
                "ratio_with_a_free_scan": sessions / (b * 1e3),
            }
    return out


def peer_comparison(
    ours_path: Path, one_path: Path | None, peer_path: Path, x1, x8, reps: int, views: int
) -> dict[str, Any]:
    """Served encoder vs the OT-style peer, 2 threads, alternating every repetition: ours as
    the product runs it (its sub-column views, one encoder batch: a file with views takes
    them, a one-view graph ``views`` images a scan), ours in one pass (``one_path``, else the
    same graph on one image), and the peer, in turn; each file loaded as the service loads
    it (``scan_kernel`` "auto")."""
    from overlapmamba.service.encoder import Encoder

    ours = Encoder(ours_path, intra_op_threads=2)
    one = Encoder(one_path, intra_op_threads=2) if one_path is not None else ours
    peer = session(peer_path, 2)
    out: dict[str, Any] = {
        "model_id": ours.model_id,
        "scan_path": ours.scan_path,
        "one_pass_model_id": one.model_id,
        "one_pass_scan_path": one.scan_path,
        "views": ours.views if ours.views > 1 else views,
    }

    def as_shipped(x: np.ndarray) -> Any:
        if ours.views > 1:
            return _encode(ours, x)
        return ours.encode(np.repeat(x, views, axis=0))  # a scan's views, one batch

    for name, x, n in (("b1", x1, reps), ("b8", x8, max(5, reps // 4))):
        v, a, b = alternate(
            lambda x=x: as_shipped(x),
            lambda x=x: _encode(one, x),
            lambda x=x: peer.run(None, {"range_image": x}),
            n=n,
        )
        out[name] = {
            "ours_views_ms_per_scan": v * 1e3 / len(x),
            "ours_ms_per_scan": a * 1e3 / len(x),
            "peer_ms_per_scan": b * 1e3 / len(x),
            "ours_views_over_peer": v / b,
            "ours_over_peer": a / b,
        }
    return out


def flops(cfg: OverlapMambaConfig, x1: torch.Tensor) -> dict[str, float]:
    """Convolution/matmul FLOPs counted by PyTorch, plus the scan's elementwise work as the
    shipped graph runs it: per (direction, channel, state, column) 7 operations in the
    chunk loop (Δ·A, exp, ·h, B·Δu, +, and C·h as a multiply-add) and 5 in the correction
    loop; exp counts as one."""
    model = OverlapMamba(cfg).eval()
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        model(x1)
    dense = float(counter.get_total_flops())
    directions = 1 + cfg.bidirectional + cfg.shift
    scan = 12.0 * directions * cfg.d_inner * cfg.d_state * cfg.width * cfg.n_blocks
    return {"dense_flops": dense, "scan_flops": scan, "total_flops": dense + scan}


def cpu_peak_gflops(cores: int) -> tuple[float, str]:
    """AVX2 + 2 FMA units: 32 float32 FLOP per cycle per core, at the reported clock."""
    try:
        info = Path("/proc/cpuinfo").read_text()
        mhz = max(float(ln.split(":")[1]) for ln in info.splitlines() if ln.startswith("cpu MHz"))
        model = next(ln.split(":")[1].strip() for ln in info.splitlines() if "model name" in ln)
    except (OSError, StopIteration, ValueError):
        return float("nan"), "unknown"
    return cores * 32 * mhz / 1e3, f"{model}, {mhz:.0f} MHz"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reps", type=int, default=30, help="timed runs per B = 1 setting")
    ap.add_argument("--json", type=Path, default=REPORTS / "service" / "encoder.json")
    ap.add_argument("--narrow", action="store_true", help="the narrow configuration (presets)")
    ap.add_argument("--no-peer", action="store_true", help="skip the OT-style peer comparison")
    ap.add_argument(
        "--views",
        type=int,
        default=read_metadata(SHIPPED_MODEL).views,
        help="sub-column views a scan against the peer (default: the shipped model's)",
    )
    args = ap.parse_args()
    console = Console()
    x8, source = images(8)
    x1 = x8[:1]
    base_cfg = NARROW if args.narrow else {}
    cfg = OverlapMambaConfig(**base_cfg)
    torch.manual_seed(0)
    model = OverlapMamba(cfg).eval()
    with torch.no_grad():
        ref = tuple(t.numpy() for t in model(torch.from_numpy(x8)))

    results: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        paths = {}
        for name, over, wf in (
            ("scan-loop", {}, "int8"),
            ("scan-loop fp32", {}, "float32"),
            ("scan-seq (T=L)", {"scan_chunk": cfg.width}, "int8"),
        ):
            m = OverlapMamba(OverlapMambaConfig(**base_cfg, **over)).eval()
            m.load_state_dict(model.state_dict())
            out = Path(tmp) / f"{len(paths)}.onnx"
            paths[name] = export_onnx(m, PROFILE, out, weight_format=wf, images=x8[:2]).path
        with scan_taken_out():
            # No verification against PyTorch here: without the scan the graphs differ.
            path = Path(tmp) / "noscan.onnx"
            paths["no-scan"] = _export_unverified(model, path)
        shipped = args.narrow  # the shipped file has the narrow configuration
        if shipped:
            console.print("timing the shipped file as the service loads it …")
            results["shipped file (served)"] = served_variant(
                SHIPPED_MODEL, x1, x8, None, args.reps, "auto"
            )
        console.print("timing c-kernel …")
        results["c-kernel"] = served_variant(paths["scan-loop"], x1, x8, ref, args.reps, True)
        for name, path in paths.items():
            console.print(f"timing {name} …")
            results[name] = onnx_variant(path, x1, x8, ref, args.reps)
        console.print("timing the served encoder against no-scan, interleaved …")
        yard = yardstick_comparison(paths["scan-loop"], paths["no-scan"], x1, args.reps)
        profile = op_profile(paths["scan-loop"], x1)
        peer: dict[str, Any] | None = None
        if not args.no_peer:
            console.print("timing the OT-style peer, interleaved with the served encoder …")
            torch.manual_seed(1)
            ot = OverlapMamba(OverlapMambaConfig(mixer="transformer", spp=False)).eval()
            ot_path = export_onnx(ot, PROFILE, Path(tmp) / "ot.onnx", images=x8[:2]).path
            ours = SHIPPED_MODEL if shipped else paths["scan-loop"]
            one = SHIPPED_ONE_VIEW if shipped else None
            peer = peer_comparison(ours, one, ot_path, x1, x8, args.reps, args.views) | {
                "peer_params": sum(p.numel() for p in ot.parameters()),
                "ours_params": sum(p.numel() for p in model.parameters()),
                "peer_file_mb": ot_path.stat().st_size / 1e6,
                "ours_file_mb": ours.stat().st_size / 1e6,
            }

    console.print("timing torch eager …")
    before = torch.get_num_threads()
    t1, t8 = torch.from_numpy(x1), torch.from_numpy(x8)

    def eager(x):
        with torch.no_grad():
            return model(x)

    results["torch eager"] = measure(
        lambda: eager(t1), lambda: eager(t8), max(5, args.reps // 3), torch.set_num_threads
    )
    torch.set_num_threads(before)

    base = results["no-scan"]
    ship = results["scan-loop"]
    served = results["c-kernel"]
    ratios = {
        # the goal's ratio from the interleaved run (yardstick_comparison)
        "served_over_noscan_b1_t1": yard["b1_t1"]["ratio"],
        "served_over_noscan_b1_t2": yard["b1_t2"]["ratio"],
        "c_kernel_b8_throughput_over_b1_t2": served["b1_t2"]["median_ms"]
        / served["b8_t2_per_scan_ms"],
        "scan_over_noscan_b1_t1": ship["b1_t1"]["median_ms"] / base["b1_t1"]["median_ms"],
        "scan_over_noscan_b1_t2": ship["b1_t2"]["median_ms"] / base["b1_t2"]["median_ms"],
        "b8_throughput_over_b1_t2": ship["b1_t2"]["median_ms"] / ship["b8_t2_per_scan_ms"],
        "onnx_over_torch_b1_t2": ship["b1_t2"]["median_ms"]
        / results["torch eager"]["b1_t2"]["median_ms"],
    }
    work = flops(cfg, t1)
    peak, cpu = cpu_peak_gflops(2)
    achieved = work["total_flops"] / (ship["b1_t2"]["median_ms"] / 1e3) / 1e9
    work |= {"achieved_gflops_b1_t2": achieved, "peak_gflops_2_cores": peak}
    work["fraction_of_peak"] = achieved / peak

    record = {
        "machine": {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version()},
        "model_config": cfg.to_dict(),
        "onnxruntime": ort.__version__,
        "torch": torch.__version__,
        "inputs": source,
        "variants": results,
        "ratios": ratios,
        "yardstick_interleaved": yard,
        "flops": work,
        "op_profile_ms": profile,
        "peer": peer,
    }
    print_tables(console, record)
    write_report(args.json, record)
    console.print(f"wrote {args.json}")


def _export_unverified(model: OverlapMamba, path: Path) -> Path:
    from overlapmamba.train.export import _trace, quantize_int8

    proto = _trace(model)  # (no interface check: it requires the Scan loops)
    quantize_int8(proto)
    onnx.save(proto, path)
    return path


if __name__ == "__main__":
    main()
