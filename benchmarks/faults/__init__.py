"""The fault bench: the edge service attacked as a black box, one row per fault case.

The service runs as ``thermal-edge run`` in a process of its own on a ``udp_multicast`` group and
port of its own (hop limit 0), metrics on 127.0.0.1, state in a temporary directory. The bench
speaks to it only as the CAN matrix says (frames built with cantools from the DBC, its own CRC), and
watches ``TE_Limits`` from an independent monitor process stamped by the kernel. Each case reports
how often it was tried, what the service did, what was lost (frames or persisted state items), the
unsafe events and the performance targets missed (:mod:`.harness`). Long runs are shortened unless
``full``. The control group (:mod:`.control`) is a fault made by the bench that must be judged unsafe;
it runs only when asked for (``only``).

Run from the checkout: ``make bench-faults`` (``python -m benchmarks.faults``).
"""
from __future__ import annotations

import sys
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from typing import Any

from . import bus, clock, control, readings, stamps, state, units
from .harness import Case

#: group name -> cases of the group (``full``: the full lengths and counts)
GROUPS: dict[str, Callable[[bool], Iterator[Case]]] = {**bus.GROUPS, **state.GROUPS, **clock.GROUPS, **stamps.GROUPS,
                                                     **units.GROUPS, **readings.GROUPS}
#: groups that run only when named: cases the bench must judge unsafe
CONTROLS: dict[str, Callable[[bool], Iterator[Case]]] = {**control.GROUPS, **readings.CONTROLS}


@dataclass
class Result:
    """What a run of the bench found."""

    cases: list[Case] = field(default_factory=list)
    full: bool = False  #: full lengths and counts (else the short form)
    wall_s: float = 0.0  #: the run's wall time, s

    @property
    def lost(self) -> int:
        """Frames or persisted state items lost, over the cases that are not controls."""
        return sum(c.lost for c in self.cases if not c.control)

    @property
    def unsafe(self) -> int:
        """Unsafe events, over the cases that are not controls."""
        return sum(c.unsafe for c in self.cases if not c.control)

    @property
    def missed(self) -> int:
        """Performance targets missed."""
        return sum(c.missed for c in self.cases)

    @property
    def failed(self) -> list[Case]:
        """The cases that did not pass (:attr:`Case.passed`)."""
        return [c for c in self.cases if not c.passed]

    def to_dict(self) -> dict[str, Any]:
        return {"total_cases": len(self.cases), "lost": self.lost, "unsafe": self.unsafe, "missed": self.missed,
                "failed": len(self.failed), "full": self.full, "wall_s": self.wall_s,
                "cases": [asdict(c) for c in self.cases]}


def run(full: bool = False, only: list[str] | None = None, progress: bool = True) -> Result:
    """Run the groups (all but the controls, or ``only``).

    A group that raises becomes one case of its own with one unsafe event (the bench could not
    finish it), so nothing fails silently.

    Raises
    ------
    ValueError
        ``only`` names a group that does not exist.
    """
    known = {**GROUPS, **CONTROLS}
    unknown = sorted(set(only or ()) - set(known))
    if unknown:
        raise ValueError(f"unknown group(s) {', '.join(unknown)}; the groups: {', '.join(known)}")
    result = Result(full=full)
    t_all = time.monotonic()
    for name, group in known.items():
        if (only and name not in only) or (not only and name in CONTROLS):
            continue
        t = time.monotonic()
        try:
            for case in group(full):
                case.seconds = round(time.monotonic() - t, 1)
                t = time.monotonic()
                result.cases.append(case)
                if progress:
                    print(f"[{case.group}] {case.name}: tried {case.tried}, lost {case.lost}, unsafe {case.unsafe} "
                          f"({case.seconds:.1f} s) {case.did}", file=sys.stderr, flush=True)
        except Exception as exc:  # the bench's own failure is reported as a case, not hidden
            tb = traceback.format_exc(limit=3).strip().splitlines()[-1]
            result.cases.append(Case(f"{name}_bench_error", name, 0,
                                     f"bench could not finish: {type(exc).__name__}: {exc} ({tb})", 0, 1))
            if progress:
                print(f"[{name}] bench error: {exc}", file=sys.stderr, flush=True)
    result.wall_s = round(time.monotonic() - t_all, 1)
    return result


def report_table(r: Result) -> str:
    """The bench's result as one Markdown table (case, tried, what the service did, lost, unsafe,
    targets missed) with the totals under it."""
    lines = ["| group | case | tried | what the service did | lost | unsafe | targets missed |",
             "|---|---|---:|---|---:|---:|---:|"]
    for c in r.cases:
        did = c.did.replace("|", "/") + (" (control: must be unsafe)" if c.control else "")
        lines.append(f"| {c.group} | {c.name} | {c.tried:,} | {did} | {c.lost:,} | {c.unsafe:,} | {c.missed:,} |")
    controls = [c for c in r.cases if c.control]
    judged = f"; control cases judged unsafe: {sum(c.unsafe > 0 for c in controls)} of {len(controls)}" if controls else ""
    lines.append(f"\n{len(r.cases)} cases ({'full' if r.full else 'short'} form, {r.wall_s:.0f} s): lost {r.lost:,}, "
                 f"unsafe {r.unsafe:,}, targets missed {r.missed:,} (controls apart){judged}; {len(r.failed)} case(s) failed")
    return "\n".join(lines)
