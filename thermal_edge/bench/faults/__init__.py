"""``bench faults``: the edge service attacked as a black box, one row per fault case.

The service runs as ``thermal-edge run`` in a process of its own on a ``udp_multicast`` group and
port of its own (hop limit 0), metrics on 127.0.0.1, state in a temporary directory. The bench
speaks to it only as ``can-matrix.md`` says (frames built with cantools from the DBC, its own
CRC), and watches ``TE_Limits`` from an independent monitor process stamped by the kernel. Each case
reports how often it was tried, what the service did, what was lost (frames or persisted state
items) and the unsafe events (:mod:`.harness`). Long runs are shortened unless ``full``.
"""
from __future__ import annotations

import sys
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import asdict
from typing import Any

from . import bus, clock, state
from .harness import Case

#: group name -> cases of the group (``full``: the full lengths and counts)
GROUPS: dict[str, Callable[[bool], Iterator[Case]]] = {**bus.GROUPS, **state.GROUPS, **clock.GROUPS}


def run(full: bool = False, only: list[str] | None = None, progress: bool = True) -> dict[str, Any]:
    """Run the groups (all, or ``only``) and return ``{"total_cases", "lost", "unsafe", "cases"}``.

    A group that raises becomes one case of its own with one unsafe event (the bench could not
    finish it), so nothing fails silently.
    """
    unknown = sorted(set(only or ()) - set(GROUPS))
    if unknown:
        raise ValueError(f"unknown group(s) {', '.join(unknown)}; the groups: {', '.join(GROUPS)}")
    cases: list[Case] = []
    t_all = time.monotonic()
    for name, group in GROUPS.items():
        if only and name not in only:
            continue
        t = time.monotonic()
        try:
            for case in group(full):
                case.seconds = round(time.monotonic() - t, 1)
                t = time.monotonic()
                cases.append(case)
                if progress:
                    print(f"[{case.group}] {case.name}: tried {case.tried}, lost {case.lost}, unsafe {case.unsafe} "
                          f"({case.seconds:.1f} s) {case.did}", file=sys.stderr, flush=True)
        except Exception as exc:  # the bench's own failure is reported as a case, not hidden
            tb = traceback.format_exc(limit=3).strip().splitlines()[-1]
            cases.append(Case(f"{name}_bench_error", name, 0, f"bench could not finish: {type(exc).__name__}: {exc} ({tb})",
                              0, 1))
            if progress:
                print(f"[{name}] bench error: {exc}", file=sys.stderr, flush=True)
    return {"total_cases": len(cases), "lost": sum(c.lost for c in cases), "unsafe": sum(c.unsafe for c in cases),
            "full": full, "wall_s": round(time.monotonic() - t_all, 1), "cases": [asdict(c) for c in cases]}


def report_table(r: dict[str, Any]) -> str:
    """The bench's result as one Markdown table (case, tried, what the service did, lost, unsafe)
    with the totals under it."""
    lines = ["| group | case | tried | what the service did | lost | unsafe |", "|---|---|---:|---|---:|---:|"]
    for c in r["cases"]:
        did = c["did"].replace("|", "/")
        lines.append(f"| {c['group']} | {c['name']} | {c['tried']:,} | {did} | {c['lost']:,} | {c['unsafe']:,} |")
    failed = sum(1 for c in r["cases"] if c["lost"] or c["unsafe"])
    lines.append(f"\n{r['total_cases']} cases ({'full' if r['full'] else 'short'} form, {r['wall_s']:.0f} s): lost "
                 f"{r['lost']:,}, unsafe {r['unsafe']:,}; {failed} case(s) with a loss or an unsafe event")
    return "\n".join(lines)
