"""Calibrate and score the covariance a verified loop closure carries.

Per town, as the service answers a scan query (``benchmarks/verify_threshold.py``'s town:
every scan encoded by the shipped encoder and kept as a keyframe's geometry; each query's
candidates in the service's order, registered and judged at the model's thresholds, the
verified one of highest fitness its closure), every verified closure whose pose is right
(within 1 m and 2° of the truth T = P_keyframe⁻¹ · P_query) gives its error δ against the
truth (``overlapmamba.core.posecov``: translation, then rotation, on the right) and
GICP's final Hessian ``H``. Wrong closures are counted, not fitted: no covariance
describes a pose at another place.

Three covariances, each Σ = s · A⁻¹ for one scale s:

- ``hessian``: A = H, GICP's information;
- ``residual``: A = H / r, with r the registration's cost per inlier pair (the classic
  σ̂² · (JᵀJ)⁻¹ of least squares);
- ``constant``: A = C⁻¹, C the validation closures' sample covariance of δ: one ellipsoid for
  every closure, blind to the geometry (the yardstick the other two must beat).

``--calibrate`` (validation towns only; ``--val`` repeated pools their closures, as the
every-sensor option's calibration takes one town of each sensor): s is the one that puts
95 % of the validation closures inside their 95 % ellipsoid (δᵀ Σ⁻¹ δ ≤ χ²₆(0.95)); the
Hessian-based covariance of lower mean negative log-likelihood on the validation closures
is chosen; with
``--write-calibration`` it is recorded in the model file (``covariance.estimator``,
``covariance.scale``), which the service then answers with. Without it, the model's
calibration (and the constant one, fitted on ``--val``, or read from the calibration's JSON
with ``--fit-from``) is scored on each town given: the
share of closures inside each ellipsoid (50, 90, 95, 99 %), the mean negative
log-likelihood, and the predicted and observed spread along x, y and yaw. Prints tables,
writes JSON (``reports/service/pose_covariance.json`` calibrating, else
``pose-covariance-test.json``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
from bench_kit import ROOT, provenance, served_rerank, served_settings, write_calibration
from reports_kit import REPORTS, write_report
from rich.console import Console
from rich.table import Table
from scipy.stats import chi2
from town_kit import encode_town
from tqdm import tqdm

from overlapmamba.core import posecov
from overlapmamba.core.poses import POSE_RIGHT, pose_error
from overlapmamba.service.calibrated_settings import CovarianceSettings
from overlapmamba.service.encoder import Encoder
from overlapmamba.service.verify import params_of, verify_candidates

ESTIMATORS = posecov.ESTIMATORS
LEVELS = (0.5, 0.9, 0.95, 0.99)
CALIBRATE_AT = 0.95  # the share of validation closures inside their ellipsoid of this level


def town_closures(enc: Encoder, path: Path, served: Any, rerank: Any) -> dict[str, Any]:
    """Each query's closure as the service answers it: δ, H and r of the right ones, and how
    many were wrong; each record and each wrong one (``wrong_closures``) names its query and
    keyframe (scan numbers) and carries the relative pose answered."""
    v = served.verify
    t = encode_town(enc, path, params_of(v), rerank)
    right: list[dict[str, Any]] = []
    wrong_closures: list[dict[str, Any]] = []
    queries = 0
    for i in tqdm(range(t.recent + 1, len(t.seq)), desc=f"verify {path.name}", unit="query"):
        top, deg = t.order(i, v.candidates)
        queries += 1
        pairs = zip(top, deg, strict=True)
        cands = [(t.blobs[j], float(a), float(np.sqrt(t.d2[i, j]))) for j, a in pairs]
        verdicts = verify_candidates(t.prepared[i], cands, v)
        t.prepared[i].spectra.clear()
        ok = [(j, x) for j, x in zip(top, verdicts, strict=True) if x.verified]
        if not ok:
            continue
        j, best = max(ok, key=lambda jx: jx[1].fitness or 0.0)  # as the service answers
        truth = np.linalg.inv(t.seq.poses[j]) @ t.seq.poses[i]
        t_err, yaw_err = pose_error(best.relative_pose, truth)
        record = {
            "query": i,
            "keyframe": int(j),
            "pose": best.relative_pose,
            "delta": posecov.error(best.relative_pose, truth),
            "hessian": best.hessian,
            "residual": best.residual,
        }
        if t_err > POSE_RIGHT[0] or yaw_err > POSE_RIGHT[1] or best.hessian is None:
            wrong_closures.append(record)
        else:
            right.append(record)
    return {
        "town": str(path),
        "queries": queries,
        "right": right,
        "wrong": len(wrong_closures),
        "wrong_closures": wrong_closures,
    }


def information(
    records: list[dict[str, Any]], estimator: str, constant: np.ndarray | None = None
) -> tuple[list[dict[str, Any]], list[np.ndarray]]:
    """The closures that have a covariance under ``estimator`` and each one's A (Σ = s ·
    A⁻¹, δ's order): ``constant`` is C⁻¹ for all; the others as the service computes
    (``overlapmamba.core.posecov.covariance`` at scale 1), which leaves out a closure whose
    Hessian gives no finite covariance."""
    if estimator == "constant":
        assert constant is not None
        return records, [np.linalg.inv(constant)] * len(records)
    kept, infos = [], []
    for r in records:
        cov = posecov.covariance(r["hessian"], r["residual"], estimator, 1.0)
        if cov is not None:
            kept.append(r)
            infos.append(np.linalg.inv(cov))
    return kept, infos


def raw_chi2(records: list[dict[str, Any]], infos: list[np.ndarray]) -> np.ndarray:
    """δᵀ A δ of each closure: its χ² when s = 1."""
    return np.array([r["delta"] @ a @ r["delta"] for r, a in zip(records, infos, strict=True)])


def fit_scale(raw: np.ndarray) -> float:
    """The s that puts :data:`CALIBRATE_AT` of the closures inside that level's ellipsoid."""
    return float(np.quantile(raw, CALIBRATE_AT) / chi2.ppf(CALIBRATE_AT, 6))


def scored(records: list[dict[str, Any]], infos: list[np.ndarray], scale: float) -> dict:
    """How well Σ = ``scale`` · A⁻¹ describes the closures' errors: the share inside each
    level's ellipsoid, the mean negative log-likelihood (Gaussian, nats), and the median
    predicted σ against the observed RMS error along x, y (m) and yaw (°)."""
    c2 = raw_chi2(records, infos) / scale
    logdet = np.array([6 * np.log(scale) - np.linalg.slogdet(a)[1] for a in infos])
    nll = 0.5 * (c2 + logdet + 6 * np.log(2 * np.pi))
    sig = np.sqrt(np.array([np.diag(np.linalg.inv(a)) * scale for a in infos]))
    deltas = np.array([r["delta"] for r in records])
    return {
        "closures": len(records),
        "inside": {f"{lv:g}": float((c2 <= chi2.ppf(lv, 6)).mean()) for lv in LEVELS},
        "nll": float(nll.mean()),
        "chi2_median": float(np.median(c2)),
        "sigma_median": {
            "x_m": float(np.median(sig[:, 0])),
            "y_m": float(np.median(sig[:, 1])),
            "yaw_deg": float(np.degrees(np.median(sig[:, 5]))),
        },
        "error_rms": {
            "x_m": float(np.sqrt((deltas[:, 0] ** 2).mean())),
            "y_m": float(np.sqrt((deltas[:, 1] ** 2).mean())),
            "yaw_deg": float(np.degrees(np.sqrt((deltas[:, 5] ** 2).mean()))),
        },
    }


def scored_kinds(
    records: list[dict[str, Any]],
    kinds: dict[str, tuple[str, float]],
    constant: np.ndarray,
) -> dict[str, dict[str, Any]]:
    """:func:`scored` for each covariance of ``kinds`` (label: estimator, scale; ``constant``
    the one ellipsoid's C) on the right closures ``records``; a covariance that none of
    them has is scored as ``closures`` 0."""
    out = {}
    for label, (name, scale) in kinds.items():
        kept, infos = information(records, name, constant)
        out[label] = {
            "estimator": name,
            "scale": scale,
            "without_covariance": len(records) - len(kept),
            **(scored(kept, infos, scale) if kept else {"closures": 0}),
        }
    return out


def covariances(
    served: CovarianceSettings, fit: dict[str, Any] | None
) -> dict[str, tuple[str, float]]:
    """The covariances to score (label: estimator, scale): the file's (``served``) when it
    is calibrated, and the validation closures' one ellipsoid (``constant``) when a fit
    (:func:`validation_fit`, :func:`read_fit`) is given."""
    out = {}
    if served.estimator is not None and served.scale is not None:
        out["served"] = (served.estimator, served.scale)
    if fit is not None:
        out["constant"] = ("constant", fit["fits"]["constant"]["scale"])
    return out


def calibrate(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Each covariance's scale on ``records`` (:func:`fit_scale`) and its scores there; the
    Hessian-based one of lower mean negative log-likelihood is ``chosen``."""
    constant = sample_covariance(records)
    out: dict[str, Any] = {"fits": {}, "constant_covariance": constant.tolist()}
    for name in (*ESTIMATORS, "constant"):
        kept, infos = information(records, name, constant)
        scale = fit_scale(raw_chi2(kept, infos))
        out["fits"][name] = {
            "scale": scale,
            "without_covariance": len(records) - len(kept),
            **scored(kept, infos, scale),
        }
    out["chosen"] = min(ESTIMATORS, key=lambda n: out["fits"][n]["nll"])
    return out


def sample_covariance(records: list[dict[str, Any]]) -> np.ndarray:
    deltas = np.array([r["delta"] for r in records])
    return np.atleast_2d(np.cov(deltas, rowvar=False))


def validation_fit(each: list[dict[str, Any]]) -> dict[str, Any]:
    """The fit (:func:`calibrate`) on the validation towns' closures pooled (``each``:
    :func:`town_closures` of each town) and, for several towns, how the chosen covariance
    sits on each (validation data: a diagnosis, not a result)."""
    fit = calibrate([r for t in each for r in t["right"]])
    val: dict[str, Any] = {
        "town": ", ".join(t["town"] for t in each),
        "queries": sum(t["queries"] for t in each),
        "wrong": sum(t["wrong"] for t in each),
        **fit,
    }
    if len(each) > 1:
        chosen = fit["chosen"]
        scale = fit["fits"][chosen]["scale"]
        val["each"] = [
            {"town": t["town"], "wrong": t["wrong"], **scored(*fitted, scale)}
            for t in each
            if (fitted := information(t["right"], chosen))[0]  # a town with a right closure
        ]
    return val


def read_fit(path: Path, model_id: str) -> dict[str, Any]:
    """The validation fit ``--calibrate`` wrote to ``path`` (its JSON's ``val``), which must
    be of this model; it names the file it came from (``from``), and its towns (``town``,
    comma-separated) relative to the checkout where they lie in it, as a clone has them."""
    if not path.is_file():
        raise SystemExit(f"{path} is missing: run benchmarks/pose_covariance.py --calibrate")
    report = json.loads(path.read_text())
    if not {"model_id", "val"} <= report.keys() or "fits" not in report["val"]:
        raise SystemExit(
            f"{path} is not a benchmarks/pose_covariance.py --calibrate report (it needs "
            "model_id and val.fits)"
        )
    if report["model_id"] != model_id:
        raise SystemExit(
            f"{path} is of model {report['model_id']}, not {model_id}: run "
            "benchmarks/pose_covariance.py --calibrate --model on this one"
        )
    towns = ", ".join(_in_checkout(Path(t.strip())) for t in report["val"]["town"].split(","))
    return {**report["val"], "town": towns, "from": _in_checkout(path)}


def _in_checkout(path: Path) -> str:
    where = path.resolve()
    return str(where.relative_to(ROOT)) if where.is_relative_to(ROOT) else str(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=ROOT / "models" / "overlapmamba-hdl64.onnx")
    ap.add_argument("--town", type=Path, action="append", help="default: data/synth/test")
    ap.add_argument(
        "--val",
        type=Path,
        action="append",
        help="validation town (repeat: their closures pooled); default data/synth/val",
    )
    ap.add_argument(
        "--calibrate", action="store_true", help="choose on --val, and score nothing else"
    )
    ap.add_argument(
        "--fit-from",
        type=Path,
        help="scoring: the validation fit (the one ellipsoid) from this --calibrate JSON of "
        "the same model, instead of computing it on --val again",
    )
    ap.add_argument(
        "--write-calibration",
        action="store_true",
        help="with --calibrate: record the chosen covariance in the model file",
    )
    ap.add_argument(
        "--json",
        type=Path,
        help="default reports/service/pose_covariance.json calibrating, else "
        "pose-covariance-test.json",
    )
    args = ap.parse_args()
    if args.fit_from is not None and (args.calibrate or args.val):
        ap.error("--fit-from takes an earlier calibration's fit: not with --calibrate or --val")
    if args.write_calibration and not args.calibrate:
        ap.error("--write-calibration records what --calibrate chose: give both")
    vals = args.val or [ROOT / "data" / "synth" / "val"]
    if any(v.name.startswith("test") for v in vals):
        ap.error("calibrate on validation towns, never on a test town")
    towns = [] if args.calibrate else args.town or [ROOT / "data" / "synth" / "test"]
    enc = Encoder(args.model)
    served = served_settings(enc.meta)
    rerank = served_rerank(enc.meta)
    console = Console()
    if args.fit_from is not None:  # the calibration's fit, as it wrote it
        val = read_fit(args.fit_from, enc.model_id)
        fitted = {Path(t.strip()).name for t in val["town"].split(",")}
        if used := sorted(fitted & {t.name for t in towns}):
            ap.error(f"{', '.join(used)}: the fit was calibrated there; score other towns")
    else:
        val = validation_fit([town_closures(enc, v, served, rerank) for v in vals])
    fit = {k: val[k] for k in ("fits", "constant_covariance", "chosen")}
    report: dict[str, Any] = {
        **provenance(),
        "model_id": enc.model_id,
        "val": val,
        "towns": [],
    }
    names = ", ".join(v.name for v in vals)
    if args.calibrate:
        table = Table(title=f"right closures on {names}: each covariance's fit")
        for col in ("covariance", "scale", "closures", "inside 50/90/95/99 %", "NLL"):
            table.add_column(col, justify="right")
        for name, f in fit["fits"].items():
            inside = " / ".join(f"{x:.3f}" for x in f["inside"].values())
            table.add_row(name, f"{f['scale']:.4g}", str(f["closures"]), inside, f"{f['nll']:.2f}")
        console.print(table)
        chosen = fit["chosen"]
        console.print(f"chosen on {names}: {chosen}, scale {fit['fits'][chosen]['scale']:.4g}")
        for t in val.get("each", []):
            inside = " / ".join(f"{x:.3f}" for x in t["inside"].values())
            console.print(f"  {Path(t['town']).name}: {t['closures']} right, inside {inside}")
        if args.write_calibration:
            values = {"estimator": chosen, "scale": fit["fits"][chosen]["scale"]}
            write_calibration(args.model, "covariance", values, ",".join(map(str, vals)))
    constant = np.asarray(fit["constant_covariance"])
    table = Table(title=f"verified closures' covariance ({enc.model_id})")
    for col in ("town", "covariance", "closures", "wrong", "inside 50/90/95/99 %", "NLL"):
        table.add_column(col, justify="right")
    kinds = covariances(served.covariance, fit)
    for path in towns:  # none when calibrating
        town = town_closures(enc, path, served, rerank)
        row: dict[str, Any] = {"town": town["town"], "queries": town["queries"]}
        row["wrong"] = town["wrong"]
        row.update(scored_kinds(town["right"], kinds, constant))
        for label, (name, _) in kinds.items():
            s = row[label]
            table.add_row(
                Path(town["town"]).name,
                f"{label} ({name})" if label != name else name,
                str(s["closures"]),
                str(town["wrong"]),
                " / ".join(f"{x:.3f}" for x in s["inside"].values()) if s["closures"] else "-",
                f"{s['nll']:.2f}" if s["closures"] else "no right closure",
            )
        report["towns"].append(row)
    if towns:
        console.print(table)
    name = "pose_covariance.json" if args.calibrate else "pose-covariance-test.json"
    out = args.json or REPORTS / "service" / name
    write_report(out, report)
    console.print(f"wrote {out}")


if __name__ == "__main__":
    main()
