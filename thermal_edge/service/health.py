"""Health of the inputs and of the model: which reasons force the safe limit this tick.

- the inputs (:class:`.inputs.TickInputs`): a stale frame forces ``stale_input``, a faulty required
  sensor ``sensor_fault``;
- the model (:class:`ModelHealth`): diverged when its state is not finite, when an innovation
  (reading minus the observer's prediction) stays above ``derating.faults.innovation_k`` for
  ``innovation_ticks`` ticks, or when the open-loop prediction error exceeds
  ``prediction_error_k``; a fault forces ``model_fault`` for ``hold_s``. It also keeps the window of
  squared open-loop prediction errors over the adaptation period, whose RMS is ``TE_PredErrRms``.
"""
from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Iterable, Mapping

from ..bus.frames import DerateReason
from ..config import FaultConfig
from .inputs import TickInputs

__all__ = ["ModelHealth", "input_reasons"]

log = logging.getLogger(__name__)


def input_reasons(ti: TickInputs) -> list[DerateReason]:
    """The reasons the inputs of a tick force (stale frames, then faulty sensors)."""
    out: list[DerateReason] = []
    if ti.stale:
        out.append(DerateReason.STALE_INPUT)
    if ti.faults:
        out.append(DerateReason.SENSOR_FAULT)
    return out


class ModelHealth:
    """Fault detection on the model and the window of its prediction errors.

    Parameters
    ----------
    config : FaultConfig
        ``derating.faults``: thresholds and the hold time.
    window_s : float
        Span of the prediction-error window (the adaptation period), s.
    """

    def __init__(self, config: FaultConfig, window_s: float) -> None:
        self.config = config
        self.window_s = float(window_s)
        self._window: deque[tuple[float, float]] = deque()  # (t, squared error)
        self._sum = 0.0
        self._innovation_ticks = 0
        self._fault_until = -math.inf
        self._faults = 0

    # -- read-only views -------------------------------------------------------------------------
    @property
    def faults(self) -> int:
        """Times the model was found diverged or a tick failed."""
        return self._faults

    def holding(self, t: float) -> bool:
        """True while a fault's hold (``hold_s``) lasts at ``t``."""
        return t < self._fault_until

    @property
    def rms_error(self) -> float:
        """RMS open-loop prediction error over the window, K (NaN with no reading in it)."""
        n = len(self._window)
        return math.sqrt(self._sum / n) if n > 0 and self._sum >= 0 else math.nan

    # -- updates ----------------------------------------------------------------------------------
    def judge(self, t: float, innovations: Iterable[float], pred_error: Mapping[str, float], finite: bool) -> str | None:
        """Record this tick's errors; returns why the model diverged (None: it did not).

        Parameters
        ----------
        t : float
            Tick time, s.
        innovations : iterable of float
            Absolute innovations of the sensors with a reading, K.
        pred_error : mapping of str to float
            Open-loop prediction minus reading per sensor, K.
        finite : bool
            Whether the observer's state, its covariance and the open-loop state are finite.
        """
        for e in pred_error.values():
            self._window.append((t, e * e))
            self._sum += e * e
        while self._window and self._window[0][0] <= t - self.window_s:
            self._sum -= self._window.popleft()[1]
        fc = self.config
        innov = list(innovations)
        self._innovation_ticks = self._innovation_ticks + 1 if innov and max(innov) > fc.innovation_k else 0
        if not finite:
            return "non-finite state"
        if self._innovation_ticks >= fc.innovation_ticks:
            return f"innovation above {fc.innovation_k:.0f} K for {fc.innovation_ticks} ticks"
        if any(abs(e) > fc.prediction_error_k for e in pred_error.values()):
            return f"open-loop prediction error above {fc.prediction_error_k:.0f} K"
        return None

    def fault(self, t: float) -> None:
        """A model fault at ``t``: count it and hold the safe limit for ``hold_s``."""
        self._faults += 1
        self._fault_until = t + self.config.hold_s

    def restart(self) -> None:
        """The state was re-initialised: the errors of the old one no longer count."""
        self._window.clear()
        self._sum = 0.0
        self._innovation_ticks = 0

    def new_state(self) -> None:
        """A fresh state (first initialisation): innovations count from zero, the window is kept."""
        self._innovation_ticks = 0
