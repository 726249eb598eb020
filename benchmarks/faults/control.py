"""Control cases: faults the service cannot mask, made by the bench itself. Each must be judged
unsafe; one that is not shows a check that cannot fail."""
from __future__ import annotations

import signal
import time
from collections.abc import Iterator

from .harness import GAP_S, Case, bed, common_checks, gaps

#: how long the service's process is stopped, s: longer than the contract's bound (GAP_S), so
#: ``TE_Limits`` is missing at the inverter whatever the host's load
PAUSE_S = 0.5
#: watched before and after the pause, s
AROUND_S = 1.5


def paused_sender(full: bool) -> Iterator[Case]:
    """The service's process stopped (SIGSTOP) for :data:`PAUSE_S` and continued (SIGCONT): its
    ``TE_Limits`` sender pauses at least as long. One length in both forms (``full`` unused)."""
    with bed("control") as b:
        time.sleep(AROUND_S)
        t0 = time.time()
        b.service.kill(signal.SIGSTOP)
        try:
            time.sleep(PAUSE_S)
        finally:
            b.service.kill(signal.SIGCONT)
        time.sleep(AROUND_S)
        t1 = time.time()
        c = common_checks(b, t0 - AROUND_S, t1)
        longest = max(gaps(b.monitor.read(), t0 - AROUND_S, t1, GAP_S), default=0.0)
        did = f"stopped {PAUSE_S * 1e3:.0f} ms; longest TE_Limits gap {longest * 1e3:.0f} ms"
        yield Case.of(f"te_limits_paused_{PAUSE_S * 1e3:.0f}ms", "control", 1, did, c, control=True)


GROUPS = {"control": paused_sender}
