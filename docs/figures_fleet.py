"""The service's measured behaviour under load: sizing, the fleet simulator and the
end-to-end runs (``docs/figures_kit.py`` says how the tables are made; the verified closures'
tables are ``docs/figures_verify.py``'s)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from figures_kit import ROOT, f3, load, ms, source, table, when

from overlapmamba.core.poses import POSE_RIGHT

# ---- deployment ----------------------------------------------------------------------------
SIZING = "reports/deploy/sizing.json"
SIZING_ONE_VIEW = "reports/deploy/sizing-one-view.json"


def _file(m: dict[str, Any]) -> str:
    """A model file as a sizing row names it: its file, views and columns."""
    views = f"{m['views']} view{'s' if m['views'] > 1 else ''}"
    aligned = ", aligned columns" if m.get("column_phase") == "aligned" else ""
    return f"`{Path(m['path']).name}` ({views}{aligned})"


def sizing() -> str:
    """What a node needs: the encoder's rate, each backend's costs a keyframe, the search
    stage at 10,000 keyframes."""
    r, twin = load(SIZING), load(SIZING_ONE_VIEW)
    out = source(SIZING, "python benchmarks/sizing.py", when(r))
    out += source(SIZING_ONE_VIEW, twin["command"], when(twin))
    out += (
        f"\n{r['scans']}; project + encode as the service runs it, one scan a call; lanes: "
        "calls at once, each on its own thread (the service's default: one a core), scans/s "
        "for all of them together:\n\n"
    )
    out += table(
        ["model", "lanes", "threads a lane", "p50 a scan", "scans/s"],
        [
            [
                _file(x["model"]),
                e.get("lanes", 1),  # reports before 2026-12-01 timed one lane only
                e["threads"],
                ms(e["median_ms"]),
                f"{e['scans_per_s']:.0f}",
            ]
            for x in (r, twin)
            for e in x["encoder"]
        ],
    )
    f, q = r["backends"]["faiss"], r["backends"]["qdrant"]
    out += "\n" + table(
        [
            "backend",
            "keyframes",
            "insert p50",
            "query p50",
            "filtered query p50",
            "disk a keyframe",
        ],
        [
            [
                "FAISS",
                f["n"],
                ms(f["insert_p50_ms"]),
                ms(f["query_p50_ms"]),
                ms(f["filtered_query_p50_ms"]),
                f"{f['store_bytes_per_keyframe'] / 1e3:.1f} KB",
            ],
            [
                "Qdrant (local)",
                q["n"],
                ms(q["insert_p50_ms"]),
                ms(q["query_p50_ms"]),
                ms(q["filtered_query_p50_ms"]),
                f"{q['local_storage_bytes_per_point'] / 1e3:.1f} KB",
            ],
        ],
    )
    rows = []
    two = bool(r["search_stage"]) and all("search_two_stage" in s for s in r["search_stage"])
    for s in r["search_stage"]:
        parts = " / ".join(f"{k} {s[k]['p50_ms']:.2f}" for k in ("index", "rows", "yaw") if k in s)
        served = s["search_two_stage"] if two else s["search"]
        rows.append(
            [
                s["load"],
                s["keyframes"],
                s["faiss_threads"],
                f"{served['p50_ms']:.2f} ms",
                f"{served['p90_ms']:.2f} ms",
                *([f"{s['search']['p50_ms']:.2f} ms"] if two else []),
                parts,
            ]
        )
    if two:
        short = r["search_stage"][0]["search_two_stage"].get("shortlist")
        out += (
            "\nA scan query's search stage as the service runs it: the first stage's shortlist "
            f"of {short} re-ranked by the yaw features (two stages); the one-stage search (the "
            "k nearest descriptors alone) beside it:\n\n"
        )
    else:
        out += "\nA scan query's search stage (one stage):\n\n"
    head = ["encoder", "keyframes", "FAISS threads", "p50", "p90"]
    head += ["one stage, p50"] * two + ["one stage by part, p50 (ms)"]
    return out + table(head, rows)


def fleet() -> str:
    """The fleet simulator at 1, 4 and 8 robots, each against a fresh service of the shipped
    model with default settings."""
    rows = []
    said: set[str] = set()
    days: set[str] = set()
    for n in (1, 4, 8):
        rel = f"reports/client/fleet-{n}.json"
        if not (ROOT / rel).is_file():
            continue
        r = load(rel)
        days.add(r.get("when", "")[:10] or "an unrecorded day")
        pe = (r.get("pose_error") or {}).get("translation_m")
        server = r.get("server") or {}
        said.add(
            f"`{server.get('model_id') or 'unrecorded'}` on {', '.join(r.get('drives') or [])}"
        )
        rows.append(
            [
                r["robots"],
                r["observations"],
                f"{r['throughput_per_s']:.1f}",
                ms(r["latency_ms"]["p50"]),
                ms(r["latency_ms"]["p95"]),
                sum(r["errors"].values()) if r["errors"] else 0,
                f3(r["precision"]),
                f3(r["recall"]),
                f"{pe['median'] * 100:.1f} cm" if pe else "—",
            ]
        )
    out = source(
        "reports/client/fleet-{1,4,8}.json",
        "overlapmamba-client simulate-fleet --robots N --map fleet --sequence data/synth/test "
        "--duration 60 --rate 10 --out reports/client/fleet-N.json",
    )
    models = "; ".join(sorted(said))
    out += (
        f"\nEach against a fresh `overlapmamba serve` with the default settings of "
        f"{', '.join(sorted(days))}: model {models}.\n"
    )
    head = ["robots", "observations", "observations/s", "p50", "p95", "errors", "precision"]
    return out + "\n" + table([*head, "recall", "pose error p50"], rows)


FLEET_VIEWS = "reports/client/fleet-views.json"
FLEET_ANY_SENSOR = "reports/client/fleet-any-sensor.json"  # the shipped file and the option
FLEET_LANES = "reports/client/fleet-lanes.json"  # the service's threads, before and now
FLEET_BATCHES = "reports/client/fleet-batches.json"  # encoder batches of 8, 2 and 1 a lane
FLEET_BATCHES_ONE_VIEW = "reports/client/fleet-batches-one-view.json"  # the same, one view
FLEET_REGISTRAR = "reports/client/fleet-registrar.json"  # registration in a child or threads


def _round(r: dict[str, Any]) -> str:
    """What a round of a fleet_views report asked: a fixed time, or a count of scans."""
    n = r.get("scans_per_robot")  # since 2026-12-03 where --scans; before, a fixed time
    if n is None:
        return f"{r['duration_s']:.0f} s a round"
    return f"{n} scans a robot a round (at most {r['duration_s']:.0f} s)"


def fleet_views(path: str = FLEET_VIEWS) -> str:
    """The fleet simulator against each model of a ``benchmarks/fleet_views.py`` report
    (each way of meeting the views, by default), alternating rounds, and where an
    observation's CPU time goes."""
    r = load(path)
    # reports since the fleet judged verified closures by their pose too
    every_run = [x for m in r["models"].values() for x in m["runs"]]
    posed = all(x.get("verified_pose_right") is not None for x in every_run)
    rows = []
    for name, m in r["models"].items():
        runs = m["runs"]
        cpu = [x["cpu_ms_per_observation"] for x in runs]
        row = [
            f"{name} (`{m['model_id']}`)",
            ", ".join(f"{x['throughput_per_s']:.1f}" for x in runs),
            ", ".join(ms(x["latency_ms"]["p50"]) for x in runs),
            sum(sum((x["errors"] or {}).values()) for x in runs),
            ", ".join(f3(x["precision"]) for x in runs),
        ]
        if posed:
            shares = [
                f3(x["verified_pose_right"] / x["verified_closures"])
                if x["verified_closures"]
                else "—"  # nothing verified: no pose to judge
                for x in runs
            ]
            row.append(", ".join(shares))
        rows.append(
            [
                *row,
                ", ".join(f3(x["recall"]) for x in runs),
                ", ".join(f"{c['server']:.0f} + {c['client']:.0f} ms" for c in cpu),
                ", ".join(f"{x['ceiling_per_s']:.1f}" for x in runs),
                ", ".join(ms(x["stage_p50_ms"]["verify"]) for x in runs),
            ]
        )
    out = source(path, r.get("command") or "python benchmarks/fleet_views.py", when(r))
    busy = r.get("other_load")
    note = (
        f"; other processes used {100 * busy:.0f}% of the CPU meanwhile" if busy is not None else ""
    )
    out += (
        f"\n{r['robots']} robots on `{r['sequence']}`, {r['rate_hz']:g} Hz asked each, "
        f"{_round(r)}, {r['rounds']} rounds of each model in turn{note}. "
        "CPU an observation: the server's and the simulator's (its robots share the "
        f"{r['cores']} cores), over the observations answered; ceiling: "
        f"{r['cores']} cores ÷ their sum, observations a second; verify: the server's median "
        "time in that stage a scan query."
        + (
            " Precision counts a closure right when its keyframe lies within the drive's loop "
            "radius; pose right: the share of verified closures whose relative pose is within "
            f"{POSE_RIGHT[0]:g} m and {POSE_RIGHT[1]:g}° of the truth, wherever the keyframe lies."
            if posed
            else ""
        )
        + "\n\n"
    )
    head = ["model", "observations/s", "p50", "errors", "precision"]
    head += ["pose right"] * posed + ["recall"]
    return out + table([*head, "CPU an observation", "ceiling", "verify"], rows)


# ---- end to end ----------------------------------------------------------------------------
def _load_row(rel: str, label: str) -> list[str]:
    """One load run (``tests/test_e2e_load.py``): its fleet, mapper and closures."""
    lt = load(rel)
    fl = lt["fleet"]
    served = lt.get("model") or {}  # recorded since 2026-11-29
    views = served.get("views", 0)
    model = f" (model `{served['model_id']}`, {views} view{'s' * (views != 1)})" if served else ""
    rss = lt.get("server_resident_mb") or {}  # recorded since 2026-12-01 (its /metrics)
    notes = (
        f"; the server's resident memory {rss['ready']:.0f} MB ready, {rss['after']:.0f} MB after"
        if rss.get("ready") is not None and rss.get("after") is not None
        else ""
    )
    kids = lt.get("registration_resident_mb") or {}  # recorded since 2026-12-02
    if kids.get("ready") is not None and kids.get("after") is not None:
        notes += (
            f"; its registration process {kids['ready']:.0f} MB ready, {kids['after']:.0f} MB after"
        )
    bars = fl.get("bars") or {}
    for what in ("precision", "recall"):  # a run under its floor failed its test
        got = fl.get(f"closure_{what}")
        if bars.get("asserted") and got is not None and got < bars[what]:
            notes += f" (under the run's {what} floor, {bars[what]:g}: the test failed)"
    if lt.get("machine", {}).get("cpu"):  # recorded since the subnormals fix, 2026-12-02
        notes += f"; on {lt['machine']['cpu']}, {lt['machine']['cores']} cores"
    cpu = lt.get("cpu") or {}  # recorded since 2026-12-02
    if cpu.get("server_cores") is not None and cpu.get("machine_busy_cores") is not None:
        n = lt.get("registration_processes")
        where = (
            "registration in the server's threads"
            if n == 0
            else f"registration in {n} child process{'es' * (n != 1)}"
        )
        children = cpu.get("registration_cores")  # recorded apart since 2026-12-02
        own = (
            f"the server {cpu['server_cores']:.2f} cores, its registration {children:.2f}, "
            f"the rest {cpu['other_cores']:.2f}"
            if children is not None
            else f"the server {cpu['server_cores']:.2f} cores, its children and the rest "
            f"{cpu['other_cores']:.2f}"
        )
        notes += (
            f"; {where}; CPU in use: {own}, the fleet, mapper and dashboard "
            f"{cpu['load_cores']:.2f}: {cpu['machine_busy_cores']:.2f} of "
            f"{cpu['machine_cores']} busy"
        )
    n = lt.get("scans_per_robot")  # a fixed count since 2026-12-02; before, 60 s
    each = f", {n} scans each," if n else ""
    return [
        label,
        lt["when"][:10],
        f"{lt['robots']} robots on `{lt['drive']}`{each} for {lt['duration_s']:.0f} s{model}, "
        f"while a mapper inserted {lt['mapper']['keyframes_acknowledged']:,} keyframes: "
        f"{fl['throughput_per_s']:.1f} observations/s, p50 {ms(fl['latency_ms']['p50'])}, "
        f"{lt['errors_total']} errors, {lt['acknowledged_missing']} keyframes lost; "
        f"verified closures precision {fl['closure_precision']:.3f}, recall "
        f"{fl['closure_recall']:.3f}{notes}",
    ]


def _on(record: dict) -> str:
    """The machine a run's speed-bound figures (times, cases in a budget) were measured on."""
    m = record.get("machine")
    return f"; on {m['cpu']}, {m['cores']} cores" if m else ""


def e2e() -> str:
    """The end-to-end runs (``make e2e``), one line each from its JSON."""
    rows = [_load_row("reports/e2e/load.json", "load (`tests/test_e2e_load.py`)")]
    for twin in sorted((ROOT / "reports" / "e2e").glob("load-*.json")):
        stem = twin.stem.removeprefix("load-")
        # a run with settings given by variables: load[-MODEL][-margin-VALUE][-processes-N]
        if stem.startswith(("margin-", "processes-")):  # the default file's
            stem = "overlapmamba-hdl64-" + stem
        stem, _, processes = stem.partition("-processes-")
        stem, _, margin = stem.partition("-margin-")
        label = f"load, `OVERLAPMAMBA_E2E_MODEL=models/{stem}.onnx`"
        if margin:
            label += f", `OVERLAPMAMBA_VERIFY__AMBIGUITY_MARGIN={margin}`"
        if processes:
            label += f", `OVERLAPMAMBA_VERIFY__PROCESSES={processes}`"
        rows.append(_load_row(f"reports/e2e/{twin.name}", label))
    crash = load("reports/e2e/crash.json")
    rows.append(
        [
            "crash (`tests/test_e2e_crash.py`)",
            crash["when"][:10],
            f"{crash['crashes']} SIGKILLs under load; {crash['lost']} acknowledged writes lost; "
            f"ready in {crash['ready_s']['median']:.1f} s median, {crash['ready_s']['max']:.1f} s "
            f"at most{_on(crash)}",
        ]
    )
    fz = load("reports/e2e/fuzz_schemathesis.json")
    corpus = load("reports/e2e/fuzz_corpus.json")
    rows.append(
        [
            "fuzz (`tests/test_e2e_fuzz.py`)",
            fz["when"][:10],
            f"schemathesis for {fz['budget_s']} s: {fz['test_cases']:,} cases, exit code "
            f"{fz['exit_code']}, server alive: {fz['server_alive']}; {len(corpus['cases'])} "
            f"hostile bodies, all answered 4xx: {corpus['all_4xx']}{_on(fz)}",
        ]
    )
    auth = load("reports/e2e/auth_matrix.json")
    rows.append(
        [
            "auth matrix (`tests/test_e2e_auth.py`)",
            auth["when"][:10],
            f"{len(auth['cells'])} routes × {len(auth['roles'])} roles and three wrong keys: "
            "the status of every cell (the test asserts each)",
        ]
    )
    b = load("reports/e2e/browser.json")
    rows.append(
        [
            "browser (`tests/test_e2e_browser.py`)",
            b["when"][:10],
            f"Chromium {b['chromium_version']}: {len(b['charts_changed'])} of "
            f"{len(b['canvases'])} charts changed between two looks, "
            f"{len(b['page_errors'])} page errors",
        ]
    )
    out = source("reports/e2e/*.json", "make e2e")
    return out + "\n" + table(["test", "run", "result"], rows)


def fleet_reach() -> str:
    """The same server and fleet, robots asking for fewer scans a second: how far they got
    and the recall (``benchmarks/fleet_reach.py``)."""
    rel = "reports/client/fleet-reach.json"
    r = load(rel)
    out = source(rel, "python benchmarks/fleet_reach.py", when(r))
    out += (
        f"\n{r['robots']} robots on `{r['drive']}`, `{r['model']}`, a fresh server each run "
        f"(machine: {r['machine']['cpu']}, {r['machine']['cores']} cores).\n\n"
    )
    rows = []
    for run in r["runs"]:
        n = run["scans_asked"]
        asked = f"{run['rate_hz_asked']:g} Hz, " + (f"{n} scans a robot" if n else "for a minute")
        rows.append(
            [
                asked,
                f"{run['duration_s']:.0f} s",
                f"{run['scans_per_robot']:.0f}",
                f"{run['throughput_per_s']:.1f}",
                f3(run["precision"]),
                f3(run["recall"]),
            ]
        )
    head = ["robots asked", "run", "scans a robot", "observations/s", "precision", "recall"]
    return out + table(head, rows)


def server_profile() -> str:
    """Where the server's CPU goes under a fleet, each file's share of py-spy's samples
    (``benchmarks/server_profile.py``)."""
    rel = "reports/service/server-profile.json"
    r = load(rel)
    out = source(rel, "python benchmarks/server_profile.py", when(r))
    out += (
        f"\n{r['robots']} robots on `{r['drive']}`, {r['rate_hz']:g} Hz asked each, "
        f"{r['scans_per_robot']} scans a robot, a fresh server of each file with its "
        f"defaults; {r['py_spy']} recording the server and its registration process for "
        f"{r['recorded_s']} s at {r['sample_hz']} Hz after {r['warmup_s']:g} s "
        f"(machine: {r['machine']['cpu']}, {r['machine']['cores']} cores). A sample counts in "
        "the first part its stack holds; the observations a second are those of the "
        "recorded runs, py-spy's own cost included.\n\n"
    )
    rows = [
        [
            f"`{Path(run['model']).name}` ({run['views']} view{'s' if run['views'] > 1 else ''})",
            *(f"{100 * run['shares'][p]:.1f}%" for p in r["parts"]),
            f"{run['fleet']['throughput_per_s']:.1f}",
        ]
        for run in r["runs"]
    ]
    return out + table(["file", *r["parts"], "observations/s"], rows)


RENDERERS: dict[str, Callable[[], str]] = {
    "server-profile": server_profile,
    "fleet-reach": fleet_reach,
    "sizing": sizing,
    "fleet": fleet,
    "fleet-views": fleet_views,
    "fleet-any-sensor": lambda: fleet_views(FLEET_ANY_SENSOR),
    "fleet-lanes": lambda: fleet_views(FLEET_LANES),
    "fleet-registrar": lambda: fleet_views(FLEET_REGISTRAR),
    "fleet-batches": lambda: fleet_views(FLEET_BATCHES),
    "fleet-batches-one-view": lambda: fleet_views(FLEET_BATCHES_ONE_VIEW),
    "e2e": e2e,
}
