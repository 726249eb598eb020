"""Derating policy: node estimates -> current and torque limits with a reason.

1. **Band derate** per limited node (model ``limits``, thresholds overridable in ``edge.yaml``):
   the upper band of the estimate ``T + z σ`` (z = 1.96: 95 %) gives a factor falling linearly
   from 1 at the warning temperature to 0 at the maximum; the current limit is that factor times
   the maximum current. The node with the lowest factor names the reason (winding, magnet).
2. **Look-ahead**: the largest RMS current that keeps every limited node under its maximum over
   the horizon (:mod:`.lookahead`); when it is the lower one the reason is ``LOOK_AHEAD``.
3. **Forced safe limit**: starting, a model fault, stale input or a faulty sensor force the
   limit to at most the configured safe current, with that reason (in this order of precedence).
4. **Slew**: a limit falls at once; it rises at most ``rise_rate_a_per_s`` and only once the
   candidate exceeds the present limit by more than ``hysteresis_a``.

The torque limit follows the current limit through the torque constant, capped at the maximum
torque (safe torque when forced).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

from ..bus.frames import DerateReason
from ..config import DeratingConfig

__all__ = ["DeratingPolicy", "Limits", "NodeBand"]


@dataclass(frozen=True)
class NodeBand:
    """A limited node's estimate and band for one tick."""

    name: str
    estimate_c: float
    upper_c: float
    warn_c: float
    max_c: float
    reason: DerateReason

    @property
    def factor(self) -> float:
        if not math.isfinite(self.upper_c):
            return 0.0
        return min(1.0, max(0.0, (self.max_c - self.upper_c) / (self.max_c - self.warn_c)))


@dataclass(frozen=True)
class Limits:
    """Limits sent in TE_Limits."""

    current_a: float
    torque_nm: float
    reason: DerateReason
    active: bool

    def signals(self) -> dict[str, float | int]:
        return {
            "TE_TorqueLimit": self.torque_nm,
            "TE_CurrentLimit": self.current_a,
            "TE_DerateActive": int(self.active),
            "TE_DerateReason": int(self.reason),
        }


class DeratingPolicy:
    """Turns bands, look-ahead and health into limits, one tick at a time.

    Parameters
    ----------
    config : DeratingConfig
    kt_nm_per_arms : float
        Torque constant (Nm per A rms) linking the current and the torque limit.
    tick_s : float
        Tick period (s), for the rise rate.
    """

    FORCED_ORDER = (DerateReason.STARTING, DerateReason.MODEL_FAULT, DerateReason.STALE_INPUT, DerateReason.SENSOR_FAULT)

    def __init__(self, config: DeratingConfig, kt_nm_per_arms: float, tick_s: float = 1.0) -> None:
        self.config = config
        self.kt = float(kt_nm_per_arms)
        self.tick_s = float(tick_s)
        self.safe_current = config.safe_current_a
        self.safe_torque = config.safe_torque_nm if config.safe_torque_nm is not None else min(
            config.max_torque_nm, self.kt * config.safe_current_a)
        self.current: float = self.safe_current  # output of the slew limiter
        self.reason: DerateReason = DerateReason.STARTING
        self.last: Limits = self.safe(DerateReason.STARTING)

    def safe(self, reason: DerateReason) -> Limits:
        """The configured safe limit with a reason (also the TE_Limits fallback)."""
        return Limits(self.safe_current, self.safe_torque, reason, True)

    def update(self, bands: Sequence[NodeBand], lookahead_a: float | None, forced: Sequence[DerateReason] = ()) -> Limits:
        """Limits for this tick."""
        cfg = self.config
        imax = cfg.max_current_a
        candidate, reason = imax, DerateReason.NONE
        for b in bands:
            i = b.factor * imax
            if i < candidate:
                candidate, reason = i, b.reason
        if lookahead_a is not None and math.isfinite(lookahead_a) and lookahead_a < candidate:
            candidate, reason = max(0.0, lookahead_a), DerateReason.LOOK_AHEAD
        if not math.isfinite(candidate):
            candidate, forced = 0.0, [*forced, DerateReason.MODEL_FAULT]
        force = next((r for r in self.FORCED_ORDER if r in forced), None)
        if force is not None:
            candidate, reason = min(candidate, self.safe_current), force
        # slew: fall at once; rise slowly and with hysteresis
        if candidate <= self.current:
            self.current = candidate
            self.reason = reason
        elif candidate > self.current + cfg.hysteresis_a or (candidate >= imax and self.current < imax):
            self.current = min(candidate, self.current + cfg.rise_rate_a_per_s * self.tick_s)
        # else: within the hysteresis, hold
        if force is not None:
            self.reason = force
        elif self.current >= imax - 1e-9:
            self.reason = DerateReason.NONE
        elif self.current >= candidate - cfg.hysteresis_a - 1e-9:  # at the candidate: its cause
            if reason != DerateReason.NONE:
                self.reason = reason
            elif self.reason in (DerateReason.NONE, *self.FORCED_ORDER):
                self.reason = DerateReason.LOOK_AHEAD
        # else: still rising after a reduction: the reason that caused it stays
        torque_cap = self.safe_torque if force is not None else cfg.max_torque_nm
        torque = min(torque_cap, self.kt * self.current)
        active = self.reason != DerateReason.NONE
        self.last = Limits(self.current, torque, self.reason, active)
        return self.last
