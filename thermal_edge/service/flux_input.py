"""The optional voltage input: the inverter's dq voltage references, a flux-linkage estimate of the
magnet temperature per tick, fused into the observer.

Only with ``flux.calibration`` set in ``edge.yaml`` (:class:`~thermal_edge.config.FluxConfig`);
without it the engine has no :class:`FluxInput` and runs exactly as without voltages.

Per tick (the frames of ``[t - Δt, t)``): the mean of ``u_d``, ``u_q`` over the voltage frames and
of ``i_d``, ``i_q`` over the current frames; with the tick's mean speed and the observer's estimate
of the winding node (the stator resistance's temperature) the commissioned
:class:`~thermal_edge.estimation.flux.FluxModel` gives a magnet temperature and its σ. What happens
to it, :data:`OUTCOMES`:

- ``low_speed``: below the commissioning's lowest speed the voltages hold no magnet information
  (nothing is computed, nothing counted: the observer is the one without voltages);
- ``transient``: the speed moved by more than the steady-state tolerance since the last tick
  (the voltage equations are steady-state);
- ``stale``: no voltage frame within ``flux.timeout_s`` (refused);
- ``old``: the tick's voltage (or current) frames lie further behind the frame clock than
  ``flux.timeout_s`` and a tick (:meth:`~thermal_edge.service.clock.Clock.behind`): a measurement
  that old describes another moment (a sender's clock off, a log's segments out of order, a
  corrupt stamp), so those frames never enter the tick's means; refused when the tick has no
  other. The wall clock takes every frame as of the time it arrives (never ``old``);
- ``implausible``: the voltages imply a magnet temperature outside ``signals.valid_range_c``: a
  voltage in another unit (mV, kV, RMS instead of peak), a sign turned round or a frame of zeros
  gives hundreds of kelvin (refused);
- ``uninformative``: an operating point the commissioning did not cover, or σ above its limit;
- ``disagreement``: the estimate's 95 % band does not overlap the model's
  (:meth:`~thermal_edge.estimation.observer.Observer.update_node`; refused): a wrong electrical
  calibration must not cool the magnet;
- ``used``: the observer corrected by it; the magnet's band narrows.

The refusals (:data:`REFUSALS`) are counted (metrics) and logged with their journald priority:
``disagreement``, ``implausible`` and ``old`` at WARNING (4), ``stale`` at NOTICE (5).
"""
from __future__ import annotations

import json
import logging
import math
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..bus.codec import DecodedFrame
from ..config import EdgeConfig, FluxConfig
from ..estimation.flux import Electrical, FluxError, FluxModel, steady
from ..estimation.fusion import FluxFusion, FluxObserver, flux_samples
from ..estimation.observer import Observer
from ..lptn import Model
from .journal import notice

__all__ = ["OUTCOMES", "REFUSALS", "FluxInput", "FluxTick", "load_flux_model"]

log = logging.getLogger(__name__)

#: What became of a tick's flux estimate (see the module docstring).
OUTCOMES = ("used", "disagreement", "stale", "old", "implausible", "uninformative", "transient", "low_speed")
#: The outcomes that refuse an estimate the tick should have had.
REFUSALS = ("disagreement", "stale", "old", "implausible")
#: The WARNING lines, one format per cause: the journal's rate limit counts per format, so a flood
#: of one cause (voltages in kV for minutes) never uses up the lines of another (a disagreement)
_WARNINGS = {"disagreement": "flux estimate refused (disagreement): %s",
             "implausible": "flux estimate refused (implausible): %s",
             "old": "flux estimate refused (old): %s"}


def load_flux_model(config: EdgeConfig) -> FluxModel:
    """The commissioned flux model named by ``flux.calibration``.

    Raises
    ------
    ConfigError
        ``<file>: flux.calibration: ...`` when it is not set, cannot be read or is not a flux model.
    """
    path = config.flux.calibration
    if path is None:
        raise config.error("flux.calibration", "not set")
    try:
        return FluxModel.from_dict(json.loads(Path(path).read_text(encoding="utf-8")))
    except (OSError, UnicodeDecodeError) as exc:
        raise config.error("flux.calibration", f"cannot read {path}: {getattr(exc, 'strerror', None) or exc}") from None
    except (json.JSONDecodeError, FluxError, TypeError, ValueError, AttributeError) as exc:
        raise config.error("flux.calibration", f"{path} is not a flux model (thermal-edge flux calibrate --out): {exc}") \
            from None


@dataclass(frozen=True)
class FluxTick:
    """One tick's flux estimate: its outcome (:data:`OUTCOMES`), the magnet temperature it implies
    (°C, NaN when none was computed) and its σ (K, inf where uninformative)."""

    outcome: str
    estimate_c: float = math.nan
    sigma_k: float = math.inf


class DqMeans:
    """Per tick, the means of the dq voltage references and currents from the frames and signals
    ``flux:`` names (voltages and currents in one frame or in two); NaN where a tick had none.

    Parameters
    ----------
    config : FluxConfig
        ``flux:`` (read whether or not the input is on: a CAN log is exported with it).
    """

    def __init__(self, config: FluxConfig) -> None:
        self.sources = ((0, config.frame, (config.voltage_d, config.voltage_q)),
                        (2, config.currents_frame, (config.current_d, config.current_q)))
        self.sums, self.n = np.zeros(4), np.zeros(4, dtype=int)  # u_d, u_q, i_d, i_q over the tick
        self.seen = False  # a voltage frame at all

    def add(self, frame: DecodedFrame) -> bool:
        """Accumulate an accepted frame (others are ignored); True if it carried the voltages. Never raises."""
        voltages = False
        for first, name, signals in self.sources:
            if frame.name != name:
                continue
            try:
                vals = [float(frame.signals[n]) for n in signals]
            except (KeyError, TypeError, ValueError):
                continue
            if not all(math.isfinite(v) for v in vals):
                continue
            self.sums[first:first + 2] += vals
            self.n[first:first + 2] += 1
            voltages |= first == 0
        self.seen |= voltages
        return voltages

    def take(self) -> np.ndarray:
        """The tick's means (u_d, u_q in V, i_d, i_q in A, peak; NaN: no frame); the sums restart."""
        out = np.full(4, np.nan)
        np.divide(self.sums, self.n, out=out, where=self.n > 0)
        self.sums[:], self.n[:] = 0.0, 0
        return out


class FluxInput:
    """Voltages and currents per tick, and the fusion of their magnet estimate into the observer.

    Parameters
    ----------
    config : EdgeConfig
        ``flux:`` (frames, signals, nodes, timeout), ``signals.valid_range_c`` and the tick.
    model : Model
        The machine model (node indices).
    flux : FluxModel
        The commissioned estimator (:func:`load_flux_model`).
    speed_input : str
        The model input that carries the speed, rpm.
    """

    def __init__(self, config: EdgeConfig, model: Model, flux: FluxModel, speed_input: str) -> None:
        fx = config.flux
        self.config = fx
        self.flux = flux
        self.dt = config.clock.tick_s
        self.valid_c = config.valid_range_c
        self.speed_input = speed_input
        assert fx.winding_node is not None  # EdgeConfig.check_model requires it when the input is on
        self.winding_row = model.node_index(fx.winding_node)
        if fx.magnet_nodes:
            magnets = list(fx.magnet_nodes)
        else:
            magnets = [next(lim.node for lim in model.limits if lim.name == config.transmit.magnet_limit)]
        self.magnet_rows = [model.node_index(n) for n in magnets]
        #: the observer fused into and its fusion (estimation.fusion: the estimate's error correlated over
        #: tau_s as a state of its own; with flux.extrapolate the changes at unseen currents)
        self._observer: FluxObserver | None = None
        self._fusion = FluxFusion(flux, self.magnet_rows, self.dt)
        self._dq = DqMeans(fx)
        #: how far a voltage or current frame may lie behind the clock, s: the timeout, and at least
        #: a tick (the frame clock's own tolerance of senders' jitter)
        self.max_behind_s = max(float(fx.timeout_s), float(self.dt))
        self._flux_frames = {fx.frame, fx.currents_frame}
        self._old = (0, 0.0)  # the tick's frames refused as old, and the furthest behind (s)
        self._last_u_t = -math.inf
        self._prev_speed: float | None = None
        #: ticks per outcome (:data:`OUTCOMES`)
        self.counts: Counter[str] = Counter()
        #: the last tick's result (None before the first tick with a state)
        self.last: FluxTick | None = None
        #: the last tick whose estimate corrected the observer (what /metrics shows: a refused value is no estimate)
        self.last_used: FluxTick | None = None

    # -- frames -------------------------------------------------------------------------------------
    def add(self, frame: DecodedFrame, t: float, behind_s: float = 0.0) -> None:
        """Accumulate an accepted frame (clock time ``t``; its own time ``behind_s`` s before it);
        other frames are ignored; never raises. The voltages and the currents may come in one
        frame or in two. One more than :attr:`max_behind_s` behind is kept out of the tick's means
        (the tick is ``old`` if it has no other)."""
        if behind_s > self.max_behind_s and frame.name in self._flux_frames:
            self._old = (self._old[0] + 1, max(self._old[1], float(behind_s)))
            return
        if self._dq.add(frame):
            self._last_u_t = t

    def reset(self) -> None:
        """Forget the tick's sums and the last speed (after a gap in the frames)."""
        self._dq.take()
        self._old = (0, 0.0)
        self._prev_speed = None

    # -- the tick -----------------------------------------------------------------------------------
    def fuse(self, t: float, observer: Observer | None, speed_rpm: float) -> FluxTick | None:
        """The tick ending at ``t``: its estimate, fused into ``observer`` where it is informative
        and agrees with the model; the sums restart. With no observer (no state yet) nothing is
        fused or counted (None)."""
        means = self._dq.take()
        (old, old_s), self._old = self._old, (0, 0.0)
        prev, self._prev_speed = self._prev_speed, speed_rpm
        if observer is None:  # no state yet: nothing to fuse into, nothing counted
            return None
        if not math.isfinite(speed_rpm):
            return self._done(FluxTick("low_speed"))
        fm = self.flux
        if abs(speed_rpm) < fm.speed_min_rpm:
            return self._done(FluxTick("low_speed"))
        if prev is None or not bool(steady(np.array([prev, speed_rpm]))[1]):
            return self._done(FluxTick("transient"))
        if math.isnan(means[0]) or math.isnan(means[2]) or t - self._last_u_t > self.config.timeout_s:
            if old:
                return self._done(FluxTick("old"), f"{old} frame(s) {' or '.join(sorted(self._flux_frames))} up to "
                                  f"{old_s:.1f} s behind the frame clock (more than {self.max_behind_s:g} s: "
                                  f"another moment) at {speed_rpm:.0f} rpm")
            return self._done(FluxTick("stale"), f"no voltage frame {self.config.frame} within "
                              f"{self.config.timeout_s:g} s at {speed_rpm:.0f} rpm")
        u_d, u_q, i_d, i_q = (float(v) for v in means)
        winding_c = float(observer.T[self.winding_row])
        e = Electrical(*(np.array([v]) for v in (u_d, u_q, i_d, i_q, speed_rpm, winding_c)))
        T, sig, ok = fm.estimate(e)
        value, sigma = float(T[0]), float(sig[0])
        lo, hi = self.valid_c
        if not (math.isfinite(value) and lo <= value <= hi):
            return self._done(FluxTick("implausible", value), f"u_d {u_d:.1f} V, u_q {u_q:.1f} V at {speed_rpm:.0f} rpm "
                              f"and {math.hypot(i_d, i_q):.1f} A imply a magnet at {value:.0f} degC, outside "
                              f"[{lo:g}, {hi:g}] degC (a voltage in another unit or scaling?)")
        if not isinstance(observer, FluxObserver):
            raise TypeError("the voltage input fuses into a FluxObserver (the engine makes one with flux.calibration)")
        if observer is not self._observer:  # a new state (start, restart after a fault): nothing fused into it yet
            self._observer, self._fusion = observer, FluxFusion(fm, self.magnet_rows, self.dt)
        fs = flux_samples(fm, e, self.dt, steady_mask=np.array([True]), extrapolate=self.config.extrapolate)
        if not (bool(ok[0]) or bool(fs.changes[0])):
            return self._done(FluxTick("uninformative", value, sigma))
        model_c = float(np.mean(observer.T[self.magnet_rows]))
        refused = observer.node_updates_refused
        used, changes = self._fusion.step(observer, t, fs, 0, e)
        if used:
            # the magnet the voltages show: their estimate less the offset the filter carries for it
            shown = value - float(observer.xe[0]) if observer.anchored else value
            return self._done(FluxTick("used", shown, math.sqrt(float(fs.white[0])) if changes else sigma))
        if observer.node_updates_refused > refused:
            return self._done(FluxTick("disagreement", value, sigma), f"magnet {value:.1f} degC +- {1.96 * sigma:.1f} K "
                              f"from the voltages, {model_c:.1f} degC from the thermal model: beyond both 95 % bands "
                              "(is the electrical calibration still right?)")
        return self._done(FluxTick("uninformative", value, sigma))

    def observing(self, t: float) -> bool:
        """Whether an estimate was fused into the observer within the error's correlation time
        before ``t`` (s): the magnet's band is then the measured one."""
        return self._observer is not None and t - self._fusion.last_ok <= self._fusion.window

    def _done(self, tick: FluxTick, why: str = "") -> FluxTick:
        self.counts[tick.outcome] += 1
        self.last = tick
        if tick.outcome == "used":
            self.last_used = tick
        if tick.outcome == "stale":
            notice(log, "flux estimate refused (stale): %s", why)
        elif tick.outcome in _WARNINGS:
            log.warning(_WARNINGS[tick.outcome], why)
        return tick
