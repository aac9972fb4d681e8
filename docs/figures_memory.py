"""Memory figures, rendered from the JSON their commands wrote (``docs/render.py`` pastes
them; nothing here types a measured number):

- a node's memory under load (``benchmarks/server_memory.py``): a real server's resident
  memory when ready and after each round of concurrent scan queries, with the service's
  defaults and with glibc's malloc held to two arenas;
- a bag's transform tree (``benchmarks/tf_memory.py``): bytes a /tf sample, and an hour's."""

from __future__ import annotations

from collections.abc import Callable

from figures_kit import load, source, table, when

SERVER_MEMORY = "reports/service/server-memory.json"


def server_memory() -> str:
    """Resident memory ready and after rounds of concurrent queries, for each configuration."""
    r = load(SERVER_MEMORY)
    out = source(SERVER_MEMORY, r["command"], when(r))
    out += (
        f"\n{r['scans']}; {r['rounds']} rounds of {r['per_round']} scan queries from "
        f"{r['clients']} clients at once (full encoder batches, by default of "
        f"{r['max_batch']} scans a lane, three views each), on a fresh server for each "
        "configuration; resident memory from its own `/metrics`:\n\n"
    )
    rows = []
    for name, c in r["configs"].items():
        mb = [x["resident_mb"] for x in c["rounds"]]
        rate = [x["queries_per_s"] for x in c["rounds"]]
        half = len(mb) // 2
        rows.append(
            [
                f"`{name}`" if name != "defaults" else "the defaults",
                f"{c['ready_mb']:.0f} MB",
                f"{mb[0]:.0f} MB",
                f"{mb[half - 1]:.0f} MB",
                f"{mb[-1]:.0f} MB",
                f"{max(mb):.0f} MB",
                f"{sum(rate) / len(rate):.1f}",
                sum(x["errors"] for x in c["rounds"]),
            ]
        )
        kids = [x.get("registration_mb") for x in c["rounds"]]  # recorded since 2026-12-02
        if None not in kids:
            rows[-1].insert(6, f"{max(kids):.0f} MB")
    head = ["configuration", "ready", "after round 1", f"after round {len(mb) // 2}"]
    head += [f"after round {len(mb)}", "most"]
    if len(rows[-1]) > 8:
        head += ["registration process, most"]
    head += ["queries/s (mean of rounds)", "errors"]
    return out + table(head, rows)


TF_MEMORY = "reports/client/tf_memory.json"


def tf_memory() -> str:
    """What a bag's /tf takes in memory while it is replayed, the tree as shipped and as a
    list of matrices a link."""
    r = load(TF_MEMORY)
    tf, hour = r["tf"], r["an_hour"]
    diff = r["max_abs_pose_difference"]
    same = "the same poses" if diff == 0 else f"poses within {diff:.0e}"
    out = source(TF_MEMORY, r["command"], when(r))
    out += (
        f"\n{tf['links']} timed links at {tf['rate_hz']:.0f} Hz for {tf['minutes']:.0f} min "
        f"({same}); an hour of it is "
        f"{hour['samples']:,} samples:\n\n"
    )
    names = {
        "shipped": "the tree (blocks of 3×4 rows)",
        "list": "a list of 4×4 arrays a link (until 2026-12-04)",
    }
    rows = [
        [
            names[way],
            f"{w['held_bytes_per_sample']:.0f} B",
            f"{w['lookup_peak_above_held_bytes_per_sample']:.0f} B",
            f"{hour['held_mb'][way]:.0f} MB",
        ]
        for way, w in sorted(r["ways"].items(), reverse=True)
    ]
    head = ["held as", "a sample", "more at the lookup, a sample", "an hour"]
    return out + table(head, rows)


RENDERERS: dict[str, Callable[[], str]] = {
    "server-memory": server_memory,
    "tf-memory": tf_memory,
}
