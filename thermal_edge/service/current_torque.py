"""The RMS current against the torque: a current that reads far below what the torque takes is not
believed.

A permanent-magnet machine makes its torque with the q-axis current: ``|T| ≈ kt · i_q`` and the RMS
phase current is at least ``i_q`` (field weakening only adds ``i_d``). A current that reads well
below ``|T| / kt`` is a scaling error in the DBC (0.1 A read as 1 A), a second sender of the current
frame diluting the tick's mean, or a dq convention mixed up: the copper losses, which go with the
square of the current, would be underestimated for as long as it lasts, and only a model error of
tens of kelvin would show it. The check judges only where the torque takes a sizeable current
(:data:`JUDGED_FROM` of the maximum), so the inverter's torque estimate at light load (its offset,
friction) cannot trip it; the margin ``derating.faults.current_torque_ratio`` (0.5) leaves room
for the reluctance torque of an interior-magnet machine and a ``kt`` that falls when saturated.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

from ..lptn import Model, Role

if TYPE_CHECKING:  # pragma: no cover
    from ..config import DeratingConfig

#: the check judges ticks whose torque takes at least this fraction of ``derating.max_current_a``
JUDGED_FROM = 0.2
#: ... and a disagreement counts after this many ticks in a row (one tick can hold a torque step
#: the current's mean has not followed yet)
CONFIRM_TICKS = 3


@dataclass(frozen=True)
class CurrentVerdict:
    """One tick's verdict: ``needed`` is ``|T| / kt`` (A rms, NaN when not judged); ``doubted``
    whether the current is not believed this tick; ``started``/``ended`` whether that began or
    ended at this tick."""

    needed: float
    doubted: bool
    started: bool = False
    ended: bool = False


class CurrentTorqueCheck:
    """The current input against the torque input (see the module docstring).

    Parameters
    ----------
    current_input, torque_input : str
        The model's RMS current (A) and shaft torque (Nm) inputs.
    kt_nm_per_arms : float
        Torque constant, Nm per A rms.
    max_current_a : float
        The drive's maximum current, A rms (sets where the check judges).
    ratio : float
        The current must read at least this fraction of ``|T| / kt``.
    """

    def __init__(self, current_input: str, torque_input: str, kt_nm_per_arms: float, max_current_a: float,
                 ratio: float) -> None:
        self.current_input, self.torque_input = current_input, torque_input
        self.kt, self.ratio = float(kt_nm_per_arms), float(ratio)
        self.judged_from_a = JUDGED_FROM * float(max_current_a)
        self._low_ticks = 0
        self.doubted = False

    @classmethod
    def of(cls, model: Model, derating: DeratingConfig, kt_nm_per_arms: float | None) -> CurrentTorqueCheck | None:
        """The check of ``model``'s current and torque inputs with ``derating``'s maximum current and
        ratio (``derating.faults.current_torque_ratio``); None when the model reads either not, or
        without a torque constant."""
        current, torque = model.find_input(Role.CURRENT), model.find_input(Role.TORQUE)
        if current is None or torque is None or kt_nm_per_arms is None:
            return None
        return cls(current, torque, kt_nm_per_arms, derating.max_current_a, derating.faults.current_torque_ratio)

    def judge(self, inputs: Mapping[str, float]) -> CurrentVerdict:
        """The verdict on one tick's inputs (the current in A rms, the torque in Nm)."""
        i = float(inputs.get(self.current_input, math.nan))
        torque = float(inputs.get(self.torque_input, math.nan))
        needed = abs(torque) / self.kt if math.isfinite(torque) else math.nan
        judged = math.isfinite(i) and math.isfinite(needed) and needed >= self.judged_from_a
        low = judged and i < self.ratio * needed
        self._low_ticks = self._low_ticks + 1 if low else 0
        was = self.doubted
        if low and self._low_ticks >= CONFIRM_TICKS:
            self.doubted = True
        elif not low:
            self.doubted = False
        return CurrentVerdict(needed if judged else math.nan, self.doubted, self.doubted and not was,
                              was and not self.doubted)
