"""How close are synthetic scans to real ones? Statistics computed the same way on both.

* points per beam: valid pixels per range-image row (kitti-hdl64 projection), mean over scans;
* range histogram: 1 m bins up to 120 m, as a density;
* empty pixels: fraction of range-image pixels without a return;
* ground returns: fraction of points less than 0.3 m above the ground plane, which is
  found per scan as the median height of the points in a 4–20 m ring below the sensor;
* intensity histogram (real intensity exists only in the two OverlapNet reference scans).

Each comparison also gets one number: the total-variation distance between the two
histograms (0 = identical, 1 = disjoint), or the relative difference for scalars.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from overlapmamba.core.errors import DatasetError
from overlapmamba.core.io import read_points
from overlapmamba.core.projection import project, valid_mask
from overlapmamba.core.sensors import get_profile

RANGE_BINS = np.arange(0.0, 121.0, 1.0)
INTENSITY_BINS = np.linspace(0.0, 1.0, 41)


def max_range_of(paths: list[Path]) -> float:
    """The largest range in these scans (real KITTI files here are clipped at 80 m)."""
    return max(float(np.linalg.norm(read_points(p).xyz, axis=1).max()) for p in paths)


def scan_stats(paths: list[Path], sensor: str = "kitti-hdl64", max_range: float = 120.0) -> dict:
    """Statistics of the points closer than ``max_range``."""
    profile = get_profile(sensor).replace(max_range=max_range)
    rows, ranges, empty, ground, intensity, counts = [], [], [], [], [], []
    for p in paths:
        pc = read_points(p)
        r = np.linalg.norm(pc.xyz, axis=1)
        near = r < max_range
        xyz, r = pc.xyz[near], r[near]
        inten = None if pc.intensity is None else pc.intensity[near]
        img = project(xyz, profile)
        valid = valid_mask(img, profile)
        rows.append(valid.sum(1))
        empty.append(1.0 - valid.mean())
        ranges.append(np.histogram(r, RANGE_BINS)[0])
        horiz = np.linalg.norm(xyz[:, :2], axis=1)
        ring = (horiz > 4) & (horiz < 20) & (xyz[:, 2] < -1.0)
        ground_z = float(np.median(xyz[ring, 2])) if ring.any() else -1.73
        ground.append(float((xyz[:, 2] < ground_z + 0.3).mean()))
        counts.append(len(xyz))
        if inten is not None and np.any(inten > 0):
            intensity.append(np.histogram(inten, INTENSITY_BINS)[0])
    rng_hist = np.sum(ranges, axis=0).astype(float)
    out = {
        "scans": len(paths),
        "points_per_scan": float(np.mean(counts)),
        "points_per_beam": np.mean(rows, axis=0).tolist(),
        "range_density": (rng_hist / rng_hist.sum()).tolist(),
        "range_median_m": _hist_quantile(rng_hist, RANGE_BINS, 0.5),
        "range_p90_m": _hist_quantile(rng_hist, RANGE_BINS, 0.9),
        "empty_pixel_fraction": float(np.mean(empty)),
        "ground_fraction": float(np.mean(ground)),
        "intensity_density": None,
        "intensity_mean": None,
    }
    if intensity:
        ih = np.sum(intensity, axis=0).astype(float)
        out["intensity_density"] = (ih / ih.sum()).tolist()
        centres = (INTENSITY_BINS[1:] + INTENSITY_BINS[:-1]) / 2
        out["intensity_mean"] = float((ih * centres).sum() / ih.sum())
    return out


def _hist_quantile(hist: np.ndarray, bins: np.ndarray, q: float) -> float:
    c = np.cumsum(hist) / hist.sum()
    return float(bins[1:][np.searchsorted(c, q)])


def _tv(a, b) -> float | None:
    if a is None or b is None:
        return None
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(0.5 * np.abs(a / a.sum() - b / b.sum()).sum())


def compare(real: dict, synthetic: dict, real_intensity: dict | None) -> list[dict]:
    """Rows: statistic, real, synthetic, gap."""

    def rel(a, b):
        return float((b - a) / a) if a else None

    beams_r, beams_s = np.array(real["points_per_beam"]), np.array(synthetic["points_per_beam"])
    return [
        {
            "statistic": "points per scan",
            "real": real["points_per_scan"],
            "synthetic": synthetic["points_per_scan"],
            "gap": rel(real["points_per_scan"], synthetic["points_per_scan"]),
            "gap_kind": "relative",
        },
        {
            "statistic": "points per beam (TV distance of the profiles)",
            "real": float(beams_r.mean()),
            "synthetic": float(beams_s.mean()),
            "gap": _tv(beams_r, beams_s),
            "gap_kind": "total variation",
        },
        {
            "statistic": "range histogram",
            "real": real["range_median_m"],
            "synthetic": synthetic["range_median_m"],
            "gap": _tv(real["range_density"], synthetic["range_density"]),
            "gap_kind": "total variation",
            "note": "values are median ranges (m)",
        },
        {
            "statistic": "range p90 (m)",
            "real": real["range_p90_m"],
            "synthetic": synthetic["range_p90_m"],
            "gap": rel(real["range_p90_m"], synthetic["range_p90_m"]),
            "gap_kind": "relative",
        },
        {
            "statistic": "empty range-image pixels",
            "real": real["empty_pixel_fraction"],
            "synthetic": synthetic["empty_pixel_fraction"],
            "gap": synthetic["empty_pixel_fraction"] - real["empty_pixel_fraction"],
            "gap_kind": "difference",
        },
        {
            "statistic": "ground-return fraction",
            "real": real["ground_fraction"],
            "synthetic": synthetic["ground_fraction"],
            "gap": synthetic["ground_fraction"] - real["ground_fraction"],
            "gap_kind": "difference",
        },
        {
            "statistic": "intensity histogram",
            "real": (real_intensity or {}).get("intensity_mean"),
            "synthetic": synthetic["intensity_mean"],
            "gap": _tv(
                (real_intensity or {}).get("intensity_density"), synthetic["intensity_density"]
            ),
            "gap_kind": "total variation",
            "note": "values are mean intensities; real: 2 reference scans",
        },
    ]


def plot(real: dict, synthetic: dict, real_intensity: dict | None, path: str | Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 2, figsize=(11, 7.5), dpi=100)
    a = ax[0, 0]
    a.plot(real["points_per_beam"], label="real KITTI 00", color="k")
    a.plot(synthetic["points_per_beam"], label="synthetic", color="tab:orange")
    a.set(title="valid pixels per range-image row", xlabel="row (0 = top)", ylabel="pixels of 900")
    a.legend()
    a = ax[0, 1]
    centres = (RANGE_BINS[1:] + RANGE_BINS[:-1]) / 2
    a.plot(centres, real["range_density"], color="k", label="real")
    a.plot(centres, synthetic["range_density"], color="tab:orange", label="synthetic")
    a.set(title="range histogram", xlabel="range (m)", ylabel="density", yscale="log")
    a.legend()
    a = ax[1, 0]
    labels = ["empty pixels", "ground returns"]
    x = np.arange(2)
    a.bar(
        x - 0.18,
        [real["empty_pixel_fraction"], real["ground_fraction"]],
        0.36,
        color="k",
        label="real",
    )
    a.bar(
        x + 0.18,
        [synthetic["empty_pixel_fraction"], synthetic["ground_fraction"]],
        0.36,
        color="tab:orange",
        label="synthetic",
    )
    a.set_xticks(x, labels)
    a.set(title="fractions", ylim=(0, 1))
    a.legend()
    a = ax[1, 1]
    ic = (INTENSITY_BINS[1:] + INTENSITY_BINS[:-1]) / 2
    if real_intensity and real_intensity.get("intensity_density"):
        a.plot(ic, real_intensity["intensity_density"], color="k", label="real (2 reference scans)")
    if synthetic.get("intensity_density"):
        a.plot(ic, synthetic["intensity_density"], color="tab:orange", label="synthetic")
    a.set(title="intensity histogram", xlabel="intensity", ylabel="density")
    a.legend()
    fig.tight_layout()
    fig.savefig(path, metadata={"Software": None})
    plt.close(fig)


def report(
    real: Path, synthetic: Path | None, reference: Path, scans: int, output: Path
) -> dict[str, Any]:
    """Compare up to ``scans`` scans of a real KITTI sequence (``real``/velodyne) with as many
    synthetic ones (``synthetic``, or a small town generated for the purpose) and the real
    scans that carry intensity (``reference``), within the real data's range. Writes
    ``output``/realism.json and realism.png; returns the JSON's content plus the scan counts
    (``scans``). Raises DatasetError for a missing or empty side."""
    real_dir = Path(real) / "velodyne"
    if not real_dir.is_dir():
        raise DatasetError(f"{real_dir} does not exist; point --real at a KITTI sequence")
    real_paths = sorted(real_dir.glob("*.bin"))[:scans]
    with tempfile.TemporaryDirectory() as tmp:
        if synthetic is None:
            from overlapmamba.synth.config import GenConfig
            from overlapmamba.synth.generate import generate

            synthetic = Path(tmp) / "synthetic"
            generate(
                synthetic, GenConfig(seed=4242, frames=scans), ground_truth=False, progress=False
            )
        syn_paths = sorted((Path(synthetic) / "velodyne").glob("*.bin"))[:scans]
        if not syn_paths:
            raise DatasetError(f"{synthetic} holds no velodyne/*.bin scans")
        # Compare within the real data's range: its files may be clipped (KITTI here: 80 m).
        cap = min(120.0, np.ceil(max_range_of(real_paths)))
        r_stats = scan_stats(real_paths, max_range=cap)
        s_stats = scan_stats(syn_paths, max_range=cap)
    ref_paths = sorted(Path(reference).glob("*.bin")) if Path(reference).is_dir() else []
    i_stats = scan_stats(ref_paths, max_range=cap) if ref_paths else None
    record = {
        "rows": compare(r_stats, s_stats, i_stats),
        "compared_within_m": cap,
        "real": r_stats,
        "synthetic": s_stats,
        "real_intensity": i_stats,
    }
    output.mkdir(parents=True, exist_ok=True)
    (output / "realism.json").write_text(json.dumps(record, indent=2) + "\n")
    plot(r_stats, s_stats, i_stats, output / "realism.png")
    return {**record, "scans": {"real": len(real_paths), "synthetic": len(syn_paths)}}
