"""Safety events in the log, each once when it happens, with its journald priority.

Every change of the state and of the derate reason (NOTICE; WARNING when a fault forces the safe
limit), inputs going stale and coming back, sensor faults and their end. The journal module's rate
limit (:mod:`.journal`) keeps a flapping input from flooding the journal.
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence

from ..bus.frames import DerateReason, TeState
from .derating import Limits
from .journal import NOTICE, notice

__all__ = ["SafetyEvents"]

log = logging.getLogger(__name__)

#: reasons logged at WARNING: a fault forces the safe limit
FAULT_REASONS = (DerateReason.MODEL_FAULT, DerateReason.STALE_INPUT, DerateReason.SENSOR_FAULT)


class SafetyEvents:
    """Logs what changed since the last tick (holds only what it last logged)."""

    def __init__(self) -> None:
        self._reason: DerateReason | None = None
        self._state: TeState | None = None
        self._stale: frozenset[str] = frozenset()
        self._faults: dict[str, str] = {}

    def record(self, state: TeState, limits: Limits, stale: Sequence[str], faults: Mapping[str, str],
               why: Callable[[str], str | None] | None = None) -> None:
        """Log this tick's changes of stale inputs, sensor faults, state and derate reason; ``why``
        gives the cause of an ``out_of_range`` reading (the unit it looks like)."""
        now_stale = frozenset(stale)
        if now_stale - self._stale:
            log.warning("input(s) stale: %s (no valid frame within the timeout); safe limit",
                        ", ".join(sorted(now_stale - self._stale)))
        if self._stale - now_stale:
            notice(log, "input(s) back: %s", ", ".join(sorted(self._stale - now_stale)))
        self._stale = now_stale
        new = {k: v for k, v in faults.items() if self._faults.get(k) != v}
        if new:
            def cause(k: str, v: str) -> str:
                said = why(k) if why is not None and v == "out_of_range" else None
                return f"{k} ({v}: {said})" if said else f"{k} ({v})"

            log.warning("sensor fault: %s; safe limit", ", ".join(cause(k, v) for k, v in sorted(new.items())))
        gone = sorted(set(self._faults) - set(faults))
        if gone:
            notice(log, "sensor fault cleared: %s", ", ".join(gone))
        self._faults = dict(faults)
        if state != self._state:
            level = logging.WARNING if state in (TeState.DEGRADED, TeState.FAULT) else (
                logging.INFO if state == TeState.ADAPTING or self._state == TeState.ADAPTING else NOTICE)
            log.log(level, "state %s -> %s", self._state.name.lower() if self._state is not None else "-",
                    state.name.lower())
            self._state = state
        if limits.reason != self._reason:
            r = limits.reason
            level = logging.WARNING if r in FAULT_REASONS else logging.INFO if r == DerateReason.STARTING else NOTICE
            log.log(level, "derate reason %s -> %s: current limit %.1f A, torque limit %.1f Nm",
                    self._reason.name.lower() if self._reason is not None else "-", r.name.lower(),
                    limits.current_a, limits.torque_nm)
            self._reason = r
