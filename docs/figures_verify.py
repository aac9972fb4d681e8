"""The service's verified closures on the test towns, registration's cost, and MapClosures
beside it (``docs/figures_kit.py`` says how the tables are made)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from figures_kit import load, ms, source, table, when

# ---- verification --------------------------------------------------------------------------
VERIFY = "reports/service/verify-test.json"
VERIFY_ONE_VIEW = "reports/service/verify-test-one-view.json"


def verify(path: str = VERIFY, both: bool = True) -> str:
    """Verified loop closures on the test towns at the model's thresholds, as the service
    answers by default (``verify.stop_at_first``: the first verified candidate; files before
    2026-11-29 hold only the best-fitting one); ``both``: and beside the other setting."""
    r = load(path)
    rows = []
    for t in r["towns"]:
        v, d = t.get("verified_stop_at_first", t["verified"]), t["descriptor"]
        rows.append(
            [
                Path(t["town"]).name,
                t["queries"],
                t["with_loop"],
                v["accepted"],
                f"{v['precision']:.3f}",
                f"{v['recall']:.3f}",
                f"{d['recall@1']:.3f}",
                f"{d['recall@5']:.3f}",
                f"{v['registered_per_query']:.1f}",
                ms(t["verify_ms"]["median"]),
            ]
        )
    th = r["thresholds"]
    gate = th.get("gate_distance", th.get("max_distance"))  # older files: max_distance
    out = source(
        path,
        r.get("command")
        or "python benchmarks/verify_threshold.py --town data/synth/test --town data/synth/test-b "
        "--town data/synth/test-c",
        when(r),
    )
    out += (
        f"\nModel {r['model_id']}; thresholds: fitness ≥ {th['min_fitness']}, "
        + (  # verify_threshold.py's grid holds 1e9 m for no bound on the rmse
            "rmse unbounded" if th["max_rmse_m"] >= 1e9 else f"rmse ≤ {th['max_rmse_m']} m"
        )
        + f", descriptor gate {gate}"
        + (
            f", ambiguity margin {th['ambiguity_margin']:g}"
            if th.get("ambiguity_margin") is not None
            else ""
        )
        + ". A closure is correct when its pose is "
        "within 1 m and 2° of the truth; recall counts queries with a loop. Verify p50: a "
        "query's registrations when every candidate under the gate is registered (with the "
        "margin, and the three more of each candidate that passes).\n\n"
    )
    out += table(
        [
            "town",
            "queries",
            "with loop",
            "accepted",
            "precision",
            "recall",
            "answer Recall@1",
            "Recall@5",
            "registered a query",
            "verify p50",
        ],
        rows,
    )
    return out + _stop_at_first(r) if both else out


def _stop_at_first(r: dict) -> str:
    """The same registrations scored both ways: the first verified candidate is the closure
    and none after it is registered (``verify.stop_at_first``, the default), or every
    candidate is and the best-fitting verified one is the closure (files since 2026-11-29)."""
    rows = []
    for t in r["towns"]:
        if "verified_stop_at_first" not in t:
            return ""
        for label, v in (("first", t["verified_stop_at_first"]), ("best-fitting", t["verified"])):
            err = v.get("translation_error_m", {}).get("median")
            rows.append(
                [
                    Path(t["town"]).name,
                    label,
                    v["accepted"],
                    f"{v['precision']:.3f}",
                    f"{v['recall']:.3f}",
                    f"{err * 100:.1f} cm" if err is not None else "—",
                    f"{v['registered_per_query']:.2f}",
                ]
            )
    head = ["town", "closure", "accepted", "precision", "recall", "pose error p50"]
    return (
        "\nThe same registrations as the default answers them (`verify.stop_at_first = true`: "
        "the first verified candidate in the answer's order is the closure, none after it "
        "registered) beside `verify.stop_at_first = false` (every candidate registered, the "
        "best-fitting verified one the closure):\n\n" + table([*head, "registered a query"], rows)
    )


REGISTRATION = "reports/service/registration.json"


def registration() -> str:
    """Relative poses on real KITTI 00, and what verification costs a query over HTTP."""
    r = load(REGISTRATION)
    h = r["http"]
    rows = [
        [
            "translation error",
            f"{r['t_err']['median'] * 100:.1f} cm",
            f"{r['t_err']['p90'] * 100:.1f} cm",
            f"{r['t_err']['max'] * 100:.1f} cm",
        ],
        [
            "yaw error",
            f"{r['yaw_err']['median']:.3f}°",
            f"{r['yaw_err']['p90']:.3f}°",
            f"{r['yaw_err']['max']:.3f}°",
        ],
        [
            "fitness",
            f"{r['fitness']['median']:.3f}",
            f"{r['fitness']['p90']:.3f}",
            f"{r['fitness']['max']:.3f}",
        ],
        [
            "registration time",
            ms(r["register_ms"]["median"]),
            ms(r["register_ms"]["p90"]),
            ms(r["register_ms"]["max"]),
        ],
        *(
            [
                label,
                ms(r[key]["median"]),
                ms(r[key]["p90"]),
                ms(r[key]["max"]),
            ]
            for key, label in (
                ("check_screened_ms", "ambiguity check, as served"),
                ("check_every_turn_ms", "ambiguity check, every turn registered"),
            )
            if key in r
        ),
        [
            "geometry a keyframe",
            f"{r['geometry_bytes']['median'] / 1e3:.1f} KB",
            f"{r['geometry_bytes']['p90'] / 1e3:.1f} KB",
            f"{r['geometry_bytes']['max'] / 1e3:.1f} KB",
        ],
    ]
    out = source(REGISTRATION, "python benchmarks/registration.py", when(r))
    m = r.get("model")
    served = (
        f" Model {m['model_id']} ({m['views']} view{'s' if m['views'] > 1 else ''} a scan), "
        "its yaw features seeding the registration and serving the queries."
        if m
        else ""
    )
    out += f"\n{r['scans']}.{served}\n\n" + table(["", "median", "p90", "max"], rows)
    if "check_turns_registered" in r:
        turns = r["check_turns_registered"]
        out += (
            f"\nThe ambiguity check (`verify.ambiguity_margin` {r['ambiguity_margin']:g}) on each "
            "of these true closures: as served, a turn is registered only where its seed could "
            f"rival; it registered {turns['median']:g} of the 3 turns at the median "
            f"({turns['max']:g} at most), and decided differently from registering every "
            f"turn on {r['check_decisions_differ']} closures.\n"
        )
    out += (
        f"\nOver HTTP ({h['queries']} queries, up to {h['candidates']} candidates registered, "
        f"{h.get('registered_per_query', h['candidates']):.1f} a query"
        + (", each that verifies checked for ambiguity too" if r.get("ambiguity_margin") else "")
        + "): a "
        f"query's client time {ms(h['verify_true']['client_ms'])} with verification against "
        f"{ms(h['verify_false']['client_ms'])} without (+{h['added_share'] * 100:.0f} %), the "
        f"verify stage {ms(h['verify_true']['server_verify_ms'])}.\n"
    )
    return out


MAPCLOSURES = "reports/service/mapclosures-test.json"


def mapclosures() -> str:
    """Against MapClosures on the first test town."""
    r = load(MAPCLOSURES)
    med = lambda xs: sorted(xs)[len(xs) // 2] if xs else float("nan")  # noqa: E731
    out = source(MAPCLOSURES, "python benchmarks/mapclosures_compare.py", when(r))
    out += (
        f"\n{Path(r['town']).name}: {r['scans']:,} scans, {r['revisiting_scans']:,} revisiting.\n\n"
    )
    out += table(
        ["method", "closures", "revisits covered", "translation error p50", "yaw error p50"],
        [
            [
                "MapClosures",
                r["closures"],
                r["covered_revisits"],
                f"{med(r['pose_error_m']) * 100:.1f} cm",
                f"{med(r['yaw_error_deg']):.2f}°",
            ]
        ],
    )
    ours = r.get("ours", {})
    ours = ours.get("verified_stop_at_first", ours.get("verified"))  # as the service answers
    if ours:
        said = r["ours"].get("model_id")
        which = (
            f"model `{said}`"
            if said
            else "no model named; measured before the shipped file had its three views and "
            f"its ambiguity check, at fitness ≥ {ours['min_fitness']:g} and rmse ≤ "
            f"{ours['max_rmse_m']:g} m. The shipped file's own verified closures on the test "
            "towns are under [Verified loop closures](#verified-loop-closures)"
        )
        out += (
            f"\nThis service on the same town, as the JSON recorded it ({which}): "
            f"{ours['accepted']:,} verified closures, precision {ours['precision']:.3f}, "
            f"recall {ours['recall']:.3f}.\n"
        )
    return out


RENDERERS: dict[str, Callable[[], str]] = {
    "verify": verify,
    "verify-one-view": lambda: verify(VERIFY_ONE_VIEW, both=False),
    "registration": registration,
    "mapclosures": mapclosures,
}
