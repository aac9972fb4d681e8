"""Which way of running the selective scan the service picks at load, and what each way
costs (``benchmarks/scan_choice.py``), and what the kernel's flush of subnormals changed
(``benchmarks/scan_subnormals.py``): the ``scan-choice`` and ``scan-subnormals`` blocks of
docs/results.md."""

from __future__ import annotations

from figures_kit import load, ms, source, table, when

AFTER = "reports/service/scan-choice.json"
BEFORE = "reports/service/scan-choice-before.json"
SUBNORMALS = "reports/service/scan-subnormals.json"


def _picked(r: dict) -> dict[str, str]:
    out = {}
    for model, got in r["models"].items():
        picked = got["loads"]["picked"]
        loads = sum(picked.values())
        out[model] = f"{picked.get('c-kernel', 0)} of {loads}"
    return out


def scan_choice() -> str:
    """Loads that picked the C kernel, by the load-time timing before and after it counted
    CPU time in blocks, and each path's cost a scan at one and eight scans a call."""
    after, before = load(AFTER), load(BEFORE)
    out = source(BEFORE, "python benchmarks/scan_choice.py --out " + BEFORE, when(before))
    out += source(AFTER, "python benchmarks/scan_choice.py", when(after))
    out += (
        f"\nMachine: {after['machine'].get('cpu', '?')}, {after['machine']['cores']} cores; "
        f"{after['threads']}; {next(iter(after['models'].values()))['cost']['images']}. "
        f"Loads that picked the C kernel: before (commit {before['commit'][:7]}, the two "
        "paths timed call by call on one image, by wall time) and after (CPU time, in "
        "blocks, on one scan's views). Cost a scan, each path in blocks of its own (the "
        "run after):\n\n"
    )
    rows = []
    was = _picked(before)
    now = _picked(after)
    for model, got in after["models"].items():
        label = f"`{model}` ({got['views']} view{'s' * (got['views'] > 1)})"
        for n in ("1", "8"):
            c = got["cost"][f"{n}_scans_a_call"]
            first = n == "1"
            rows.append(
                [
                    label if first else "",
                    f"{was.get(model, '—')} → {now[model]}" if first else "",
                    n,
                    f"{ms(c['c-kernel']['wall_ms'])} / {ms(c['c-kernel']['cpu_ms'])}",
                    f"{ms(c['portable']['wall_ms'])} / {ms(c['portable']['cpu_ms'])}",
                ]
            )
    head = ["file", "loads picking the kernel", "scans a call", "C kernel: wall / CPU a scan"]
    return out + table([*head, "portable graph: wall / CPU a scan"], rows)


def scan_subnormals() -> str:
    """CPU a scan by the kernel with and without its flush of subnormals, and by the
    portable graph, per shipped file and real sequence; the path each load picked."""
    r = load(SUBNORMALS)
    p = r["processor"]
    out = source(SUBNORMALS, "python benchmarks/scan_subnormals.py", when(r))
    out += (
        f"\nMachine: {r['machine']['cpu']} ({p.get('vendor_id', '?')}, family "
        f"{p.get('cpu family', '?')} model {p.get('model', '?')}, AVX-512 "
        f"{'yes' if p.get('avx512f') else 'no'}), {r['machine']['cores']} cores; one "
        "onnxruntime thread and one kernel thread; the median of "
        f"{next(iter(r['files'][0]['sequences'].values()))['scans_timed']} timed encodes a "
        "sequence, the three ways interleaved scan by scan. In brackets, the kernel's own part:\n\n"
    )
    rows = []
    for f in r["files"]:
        label = f"`{f['model']}` ({f['views']} view{'s' * (f['views'] > 1)})"
        for i, (seq, s) in enumerate(f["sequences"].items()):
            rows.append(
                [
                    label if i == 0 else "",
                    seq,
                    f"{ms(s['no flush_cpu_ms'])} ({ms(s['no flush_scan_ms'])})",
                    f"{ms(s['flush_cpu_ms'])} ({ms(s['flush_scan_ms'])})",
                    ms(s["portable_cpu_ms"]),
                    f"{f['max_abs_difference_flush_vs_not']:.1g}" if i == 0 else "",
                    f["served_at_load"].split(" (")[0] if i == 0 else "",
                ]
            )
    head = ["file", "real scans", "C kernel, subnormals kept", "C kernel, flushed"]
    head += ["portable graph", "largest output difference", "served at load"]
    return out + table(head, rows)


RENDERERS = {"scan-choice": scan_choice, "scan-subnormals": scan_subnormals}
