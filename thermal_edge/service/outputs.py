"""What one tick produced, and the contents of the frames the service sends from it.

:class:`TickOutput` is the tick's result, read by the bus (``TE_Estimates``, ``TE_Forecast``,
``TE_Status``; ``TE_Limits`` from :class:`.derating.Limits`), the metrics and the tests. Values
outside a signal's DBC range are left to the codec, which saturates them to the range (and counts
them in ``frames_clamped``); only what the codec cannot encode is decided here: a temperature
without an estimate is "no value" (NaN), an unknown look-ahead current or time to limit is sent as
"not limited within the horizon" (+inf, saturated to the range's top).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..bus.frames import DerateReason, TeState
from .adaptation import AdaptationResult
from .derating import Limits, NodeBand
from .flux_input import FluxTick

__all__ = ["TickOutput"]


def _finite_or(x: float, default: float) -> float:
    return x if math.isfinite(x) else default


@dataclass
class TickOutput:
    """Everything one tick produced (for the bus, the metrics and the tests).

    Temperatures in °C, currents in A rms, times in s; ``estimate``, ``sigma`` and ``prediction``
    in the model's node order (NaN before the state is initialised).
    """

    t: float
    state: TeState
    limits: Limits
    initialized: bool
    estimate: np.ndarray
    sigma: np.ndarray
    prediction: np.ndarray
    measured: dict[str, float]
    inputs: dict[str, float]
    pred_error: dict[str, float]
    pred_err_rms: float
    bands: list[NodeBand]
    lookahead_a: float  # 30 min look-ahead current (advice, TE_Forecast)
    time_to_limit_s: float
    horizon_s: float
    adapt_runs: int
    adapt_accepted: int
    adapt_rejected: int
    param_version: int
    forced: list[DerateReason]
    stale: list[str]
    faults: dict[str, str]
    new_results: list[AdaptationResult] = field(default_factory=list)
    compute_s: float = 0.0  # CPU time of the tick's thread, s
    wall_s: float = 0.0  # wall time of the tick, s
    hot_spot: NodeBand | None = None
    magnet: NodeBand | None = None
    reaction_a: float = math.inf  # largest current keeping every upper band below max over the reaction time
    adapt_status: str = ""  # what the adaptation is doing (:data:`.adaptation.ADAPT_STATUSES`)
    adapt_refusal: str = ""  # why the last challenger was dropped ("" if none was)
    #: sensor/input name -> seconds from its last valid reading to this tick (inf: none yet); as of the
    #: tick, so that it is never measured against a reading that arrived after it
    ages: dict[str, float] = field(default_factory=dict)
    #: the tick's flux estimate of the magnet and what became of it (None without the voltage input)
    flux: FluxTick | None = None

    # -- frame contents ---------------------------------------------------------------------------
    def estimates_signals(self) -> dict[str, float]:
        """``TE_Estimates``: hot spot and magnet, estimate and upper band (°C; NaN = no value)."""
        def temp(band: NodeBand | None, upper: bool) -> float:
            if band is None or not self.initialized:
                return math.nan
            return _finite_or(band.upper_c if upper else band.estimate_c, math.nan)

        hs, mg = self.hot_spot, self.magnet
        return {"TE_T_HotSpot": temp(hs, False), "TE_T_HotSpotUpper": temp(hs, True),
                "TE_T_Magnet": temp(mg, False), "TE_T_MagnetUpper": temp(mg, True)}

    def forecast_signals(self) -> dict[str, float]:
        """``TE_Forecast``: time to limit (s), look-ahead current (A rms), horizon (s).

        Until the model is initialised the look-ahead current is 0 A: nothing is known to be
        holdable yet, and an unknown value would saturate to the signal's top (3276.75 A), which a
        controller reads as a current it may hold for the whole horizon.
        """
        lookahead = _finite_or(self.lookahead_a, math.inf) if self.initialized else 0.0
        return {"TE_TimeToLimit": _finite_or(self.time_to_limit_s, math.inf),
                "TE_LookaheadCurrent": lookahead, "TE_Horizon": self.horizon_s}

    def status_signals(self) -> dict[str, float]:
        """``TE_Status``: state, RMS prediction error (K; 0 while it means nothing, the range's top
        when the model diverged), adaptation count and parameter version (wrapping)."""
        e = self.pred_err_rms
        no_error = not self.initialized or (math.isnan(e) and self.state != TeState.FAULT)
        return {
            "TE_State": int(self.state),
            "TE_PredErrRms": 0.0 if no_error else _finite_or(e, math.inf),
            "TE_AdaptCount": self.adapt_accepted % 65536,  # the matrix: accepted adaptations since start
            "TE_ParamVersion": self.param_version % 256,
        }
