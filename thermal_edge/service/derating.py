"""Derating policy: node estimates -> current and torque limits, with the reason that limits now.

How drives protect a machine, and what this policy takes from each:

* **Fixed thermistor derate** (open drive firmware, e.g. VESC's motor temperature start/end): the
  current falls linearly from full at a start temperature to zero at an end temperature of the
  *measured* winding. Simple and safe only as far as the sensor is the hottest point; the start
  temperature must sit far below the max because the hot spot and the magnet are not measured.
* **I²t / thermal image** (IEC 60947-4-1 overload classes, the motor thermal model of industrial
  drives): a first-order image of the winding heated by ``I²`` and set to the continuous rating;
  full overload current while the image is cool, the continuous current once it is "full". It
  gives short-time overload but knows neither the machine's real state nor its cooling.
* **Thermal-model protection** (what this service is): a network model, corrected by the PT100s,
  estimates every limited node with a 95 % band; the limit is what that model says the machine can
  take *now*.

The policy, per tick (1 s):

1. **Reaction-time current** ``I_react``: the largest RMS current that, held for
   ``derating.reaction_time_s`` from the present upper-band state (estimate + z σ, z = 1.96), keeps
   every limited node below its max less ``derating.margin_k`` (:class:`.lookahead.Lookahead` over
   that short horizon, the copper losses at the highest max, so never underestimated). A limited
   node's upper band is never taken below the reading of a sensor that bounds it from below (see
   step 3). While it is at least the rated
   maximum, the machine gets the **full maximum current**: a cold or warm machine has its whole
   short-time overload capacity. As a node's upper band approaches its max, ``I_react`` falls
   continuously to the current that holds the upper band just below the max: the limit follows
   the machine's own heat balance, and whatever happens within the reaction time (the service
   stops, an input goes stale), the present limit cannot take the upper band past the max. The
   reason is the node that binds (``winding``, ``magnet``). A fixed linear derate from the warning
   temperature on the estimate (the thermistor rule) is *not* applied: it would give away the
   headroom between warn and max that the model's prediction makes usable, which is the point of
   the model (``thermal-edge bench protection`` measures the difference).
2. **Approach**: the limit also falls linearly from full to zero over the last
   ``derating.approach_k`` (3 K) below ``max - margin_k`` on each node's upper band. The
   reaction-time current alone is a deadbeat law (it allows whatever reaches the max exactly at the
   end of the reaction time, so 0.3 K change its value from 30 A to 0); with the slow rise rate it
   limit-cycles between zero and the maximum. The approach is a proportional law (13 A per K at
   40 A over 3 K) that settles at the holding current a little below ``max - margin``; the
   reaction-time current stays the net for fast heating.
3. **Forced safe limit**: starting, a model fault, stale input or a faulty sensor force the limit
   to at most ``derating.safe_current_a`` (in this order of precedence), and the reason is the
   cause. The model is then not trusted, so the limit is also held to the **band derate at the
   measured temperatures**: the readings of the sensors that bound a limited
   node from below (a sensor whose node is never hotter than the limited node in the model's steady
   states, :func:`bounding_sensors`; the end-winding PT100 for the end-winding hot spot)
   with that node's band, full current at ``warn_c`` falling linearly to zero at ``max_c`` (the
   thermistor rule, what is left when the model is not trusted): ``min(safe, band at measured)``.
4. **Slew**: a limit falls at once; it rises at most ``rise_rate_a_per_s`` and only once the
   candidate exceeds the present limit by more than ``hysteresis_a``.

**Between ticks** (:meth:`DeratingPolicy.between_ticks`, for every ``TE_Limits`` sent, 10 Hz): the
last tick's limits, unless the bus has been silent longer than ``transmit.bus_silence_s`` (safe
limit, ``stale_input``: the inverter went silent, and with the frame clock the ticks stop with the
frames) or, with the wall clock, no tick ran for ``STALL_TICKS`` periods (safe limit,
``model_fault``: something is stuck). Decided between ticks, such a limit is never above the last
tick's, which already held the band at the measured temperatures.

The 30 min look-ahead (the current that could be held for the whole horizon and the time to limit)
is advice for the vehicle or plant controller in ``TE_Forecast``: it never limits by itself. While a
forced limit holds (the estimate not trusted) it is never above the current limit sent. It is
a limit only where holding the present limit would reach a max within the reaction time, which is
exactly step 1.

**The margin** (``derating.margin_k``, default 1.5 K): the 95 % band carries the state noise and
the declared spread of the parameters the adapter does not estimate; for the end-winding hot spot,
next to a PT100, that is σ ~0.15 K. It does not cover a stator model that is wrong before the
adapter has corrected it (the adapter needs 30 min of history; the winding resistance is a
constant, not a parameter with a spread): with the winding conductivity 25 % lower than modelled (copper losses +33 %) the
unmeasured hot spot's estimate trails the truth by up to 1.5 K. The margin covers that, and costs
~1 % of the current held at the max; the readings of the bounding sensors are the second line.
A band may carry a margin of its own (:attr:`NodeBand.margin_k`): the magnet's while the
inverter's voltages observe it (``flux.magnet_margin_k``), whose band is then a measured one.

**The magnet's band carries the rotor model's error.** The magnet is far from every sensor, and no
reading tells a wrong rotor model: with the rotor-side coefficients as exact constants, magnet
losses twice the model's and an air-gap heat transfer 30 % lower (``--plant P_pm_ref=+100% --plant
h_gap1=-30%``) make the estimate trail the true magnet by up to 6.1 K while σ is ~1.1 K, and the
policy lets the magnet reach 121.1 °C (372 s over max). So the model file declares the rotor-side loss
coefficients (``P_pm_ref``, the iron-loss, friction and windage coefficients) as parameters with
their spread (``P_pm_ref`` 0.4: magnet eddy-loss estimates are off by ~2x) and the convection
coefficients with 0.3; the observer carries them into the band as the first-order error ``S δφ``
of its estimate (:mod:`..estimation.observer`), and a saved state keeps that part of the
covariance across a restart. The magnet's σ is then 2.2-3.9 K near its max; in that case the true
magnet stays within 1.5 σ of the estimate and reaches 116.2 °C (0 s over). The price is 1.9-4.0
points of the oracle's delivery in the bench's cases (the magnet binds a few kelvin lower). z stays
1.96: a factor 2 on ``P_pm_ref`` lies at 1.7 σ of its spread, inside this band but outside the
one-sided 95 % bound (z 1.645: its error is above that bound 53 % of the time on a 70 min heat-up,
``tests/estimation/test_observer_bands.py``), which would give back only 0.4-0.6 points. The
housing PT100 counts as a floor under the magnet (:func:`bounding_sensors`, steady states only)
although an overload heats the housing long before the rotor; that false bound holds the limit low
at times, but it only ever raises the magnet's bound, so it costs current, not safety.

**The reason names what limits now**: the forced cause; else the candidate's cause when the limit
sits at its candidate (within the hysteresis); ``recovering`` while the limit climbs back at the
rise rate after a reduction whose cause has gone (not the past cause: after a 1 s dropout the
reason is ``stale_input`` for that second, then ``recovering``); ``none`` at the maximum.

**Choice of the reaction time** (``derating.reaction_time_s``, default 10 s): the time in which the
present limit must stay valid, because nothing can lower the current sooner: one tick until the
service recomputes (1 s), the inverter's fallback after a lost ``TE_Limits`` (0.3 s), an input going
stale before the safe limit is forced (the input timeouts, 0.5–1 s), and a restart of the service
by the systemd watchdog during which the inverter runs on its own protection (a few seconds). 10 s
covers these with a margin; longer times cost overload capacity near the max (at 40 A the hot spot
rises ~1 K/s), shorter ones leave no margin. ``thermal-edge bench protection`` measures the effect.

The torque limit follows the current limit through the torque constant, capped at the maximum
torque (safe torque when forced).
"""
from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..bus.frames import DerateReason
from ..config import DeratingConfig
from ..lptn import Model, NodeRole, Role

__all__ = ["STALL_TICKS", "DeratingPolicy", "LimitSpec", "Limits", "MeasuredFloor", "NodeBand", "bounding_sensors"]

#: reasons that force the safe limit, in order of precedence
FORCED_ORDER = (DerateReason.STARTING, DerateReason.MODEL_FAULT, DerateReason.STALE_INPUT, DerateReason.SENSOR_FAULT)
#: ticks of bounding-sensor readings averaged for the floor under a limited node's upper band: the
#: PT100 noise (σ 0.1 K, 0.1 K steps) averaged down, so the reaction-time current (very sensitive
#: near the max) does not jump with each reading; at 0.35 K/s (40 A) the mean lags by 0.7 K
FLOOR_TICKS = 5
#: tick periods without a tick (wall clock) after which the tick loop counts as stalled: one late
#: tick is load, three in a row something stuck
STALL_TICKS = 3


@dataclass(frozen=True)
class NodeBand:
    """A limited node's estimate and band for one tick (°C).

    ``upper_c`` is the upper band the policy derates on and the service sends
    (``TE_T_HotSpotUpper``, ``TE_T_MagnetUpper``): the observer's band ``observer_upper_c``
    (estimate + ``derating.band_z`` σ, the parameters' declared spread included) raised to the
    mean of the last :data:`FLOOR_TICKS` readings of each sensor that bounds the node from below
    (:class:`MeasuredFloor`). Where such a reading is above the observer's band (the housing PT100
    under the magnet while an overload heats the stator first), ``upper_c`` is that reading, and
    what narrows the observer's band (the inverter's voltages on the magnet) does not move it.
    ``observer_upper_c`` is NaN for a band that is a reading (:meth:`MeasuredFloor.bands`).
    """

    name: str
    estimate_c: float
    upper_c: float
    warn_c: float
    max_c: float
    reason: DerateReason
    observer_upper_c: float = math.nan
    #: the margin below ``max_c`` the approach ends at, K (None: ``derating.margin_k``)
    margin_k: float | None = None

    @property
    def observer_lower_c(self) -> float:
        """Lower end of the observer's band (estimate - ``band_z`` σ), °C; NaN without it."""
        return 2.0 * self.estimate_c - self.observer_upper_c

    @property
    def factor(self) -> float:
        """Linear band derate factor on ``upper_c``: 1 at or below warn, 0 at or above max."""
        if not math.isfinite(self.upper_c):
            return 0.0
        return min(1.0, max(0.0, (self.max_c - self.upper_c) / (self.max_c - self.warn_c)))


@dataclass(frozen=True)
class Limits:
    """Limits sent in TE_Limits (A rms, Nm)."""

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


@dataclass(frozen=True)
class LimitSpec:
    """A limited node: its name, node row, warning and max temperature (°C) and derate reason."""

    name: str
    row: int
    warn_c: float
    max_c: float
    reason: DerateReason


def bounding_sensors(model: Model, theta: np.ndarray, sensors: dict[str, int], limits: dict[str, int],
                     max_current_a: float, kt_nm_per_arms: float, rated_speed_rpm: float = 1000.0) -> dict[str, list[str]]:
    """Sensors whose reading is a lower bound of a limited node's temperature.

    A sensor bounds a limited node if, in the model's steady states over a grid of operating points
    (speeds 0, ½, 1 and 2 times ``rated_speed_rpm``; currents ¼, ½ and 1 times the maximum; 25 °C),
    its node is never hotter than the limited node: then a reading at or above the node's warning
    temperature means the limited node is at least that hot, whatever the model's state (the
    end-winding PT100 for the end-winding hot spot; not for the magnet, which is cooler than the
    winding at low speed). A sensor on a winding node also bounds every limited winding node: the
    winding's limit holds for all of its copper, so a slot-winding reading above the end-winding hot
    spot's estimate is a winding at least that hot, whatever point the model calls the hot spot (a
    model that runs the hot spot cold, or a steady state where the slot is the hotter point).

    Parameters
    ----------
    model : Model
    theta : ndarray
        Parameters of the steady states.
    sensors, limits : dict of str to int
        Sensor name -> node row, limit name -> node row.
    max_current_a : float
        Maximum current, A rms.
    kt_nm_per_arms : float
        Torque constant (for a torque input).

    Returns
    -------
    dict of str to list of str
        Limit name -> the sensors that bound it from below (only limits with at least one).
    """
    from ..lptn import steady_state

    rest = model.at_rest({k: 25.0 for k in model.temperature_inputs})
    role = {row: model.node_roles.get(node) for row, node in enumerate(model.nodes)}
    winding = {(lim, s) for lim in limits for s in sensors
               if role[limits[lim]] == NodeRole.WINDING and role[sensors[s]] == NodeRole.WINDING}
    # the other pairs bound where no steady state puts the sensor's node above the limited one
    ok = {(lim, s): True for lim in limits for s in sensors if (lim, s) not in winding}
    for speed in (0.0, 0.5 * rated_speed_rpm, rated_speed_rpm, 2.0 * rated_speed_rpm):
        for frac in (0.25, 0.5, 1.0):
            i = frac * max_current_a
            u = dict(rest)
            u.update({k: v for k, v in ((model.find_input(Role.SPEED), speed),
                                        (model.find_input(Role.TORQUE), kt_nm_per_arms * i),
                                        (model.input_name(Role.CURRENT), i)) if k in u})
            try:
                T, _ = steady_state(model, u, theta)
            except Exception:  # no steady state at this point: decide on the others
                continue
            for (lim, s) in ok:
                if T[sensors[s]] > T[limits[lim]] + 1e-6:
                    ok[(lim, s)] = False
    out: dict[str, list[str]] = {}
    for lim in limits:  # in the sensors' order
        for s in sensors:
            if (lim, s) in winding or ok.get((lim, s), False):
                out.setdefault(lim, []).append(s)
    return out


class MeasuredFloor:
    """The readings of the sensors that bound a limited node from below (:func:`bounding_sensors`).

    Two uses: a limited node's upper band is never below the mean of its bounding sensors' last
    ``FLOOR_TICKS`` readings (an estimate the readings have outrun, a model that runs cold, does not
    hide that), and while the model is not trusted the readings with that node's band are the
    thermistor rule's input (step 3).

    Parameters
    ----------
    limits : sequence of LimitSpec
    bound_by : mapping of str to list of str
        Limit name -> its bounding sensors.
    """

    def __init__(self, limits: Sequence[LimitSpec], bound_by: Mapping[str, list[str]]) -> None:
        self.specs = [(s, lim) for lim in limits for s in bound_by.get(lim.name, [])]
        self._history: dict[str, deque[float]] = {s: deque(maxlen=FLOOR_TICKS) for s, _ in self.specs}

    def bands(self, measured: Mapping[str, float]) -> list[NodeBand]:
        """The readings as bands of the nodes they bound (finite readings only), °C."""
        return [NodeBand(lim.name, measured[s], measured[s], lim.warn_c, lim.max_c, lim.reason)
                for s, lim in self.specs if math.isfinite(measured.get(s, math.nan))]

    def raise_upper(self, upper: np.ndarray, measured: Mapping[str, float]) -> None:
        """Record this tick's readings and raise ``upper`` (°C, by node row, in place) to their means."""
        for s, hist in self._history.items():  # once per sensor, whatever number of nodes it bounds
            v = measured.get(s, math.nan)
            if math.isfinite(v):
                hist.append(v)
        for s, lim in self.specs:
            hist = self._history[s]
            if hist:
                upper[lim.row] = max(upper[lim.row], sum(hist) / len(hist))


class DeratingPolicy:
    """Turns the reaction-time current, readings and health into limits, one tick at a time.

    Parameters
    ----------
    config : DeratingConfig
    kt_nm_per_arms : float
        Torque constant (Nm per A rms) linking the current and the torque limit.
    tick_s : float
        Tick period (s), for the rise rate and the stall of the tick loop.
    bus_silence_s : float
        Silence of the bus (s) after which the safe limit is sent between ticks (the service's
        ``transmit.bus_silence_s``; infinite: never).
    """

    FORCED_ORDER = FORCED_ORDER

    def __init__(self, config: DeratingConfig, kt_nm_per_arms: float, tick_s: float = 1.0,
                 bus_silence_s: float = math.inf) -> None:
        self.config = config
        self.kt = float(kt_nm_per_arms)
        self.tick_s = float(tick_s)
        self.bus_silence_s = float(bus_silence_s)
        self.safe_current = config.safe_current_a
        # one safe torque wherever it is sent (a tick's forced limit and the sender's between ticks):
        # never above the torque the safe current carries, as every torque limit
        configured = config.safe_torque_nm if config.safe_torque_nm is not None else math.inf
        self.safe_torque = min(configured, config.max_torque_nm, self.kt * config.safe_current_a)
        self.current: float = self.safe_current  # output of the slew limiter
        self.reason: DerateReason = DerateReason.STARTING
        self.last: Limits = self.safe(DerateReason.STARTING)

    def safe(self, reason: DerateReason) -> Limits:
        """The configured safe limit with a reason (also the TE_Limits fallback)."""
        return Limits(self.safe_current, self.safe_torque, reason, True)

    def candidate(self, bands: Sequence[NodeBand], reaction: tuple[float, DerateReason] | None,
                  forced: Sequence[DerateReason] = (), measured: Sequence[NodeBand] = ()
                  ) -> tuple[float, DerateReason, DerateReason | None]:
        """The limit before the slew (A rms), its cause, and the forcing reason (None if not forced).

        Parameters
        ----------
        bands : sequence of NodeBand
            Limited nodes' estimates with their upper bands (a non-finite one is a model fault).
        reaction : (float, DerateReason) or None
            Reaction-time current and the reason of the node that sets it (None: no estimate, e.g.
            not initialised; a NaN current: it could not be computed, a model fault).
        forced : sequence of DerateReason
            Health reasons that force the safe limit.
        measured : sequence of NodeBand
            Readings of sensors bounding a limited node from below, with that node's band.
        """
        cfg = self.config
        imax = cfg.max_current_a
        forced = list(forced)
        cand, reason = imax, DerateReason.NONE
        if any(not math.isfinite(b.upper_c) for b in bands) or (reaction is not None and math.isnan(reaction[0])):
            forced.append(DerateReason.MODEL_FAULT)
        else:
            for b in bands:  # the approach: linear over approach_k below max - margin
                margin = cfg.margin_k if b.margin_k is None else b.margin_k
                i = imax * min(1.0, max(0.0, (b.max_c - margin - b.upper_c) / cfg.approach_k))
                if i < cand:
                    cand, reason = i, b.reason
            if reaction is not None and reaction[0] < cand:
                cand, reason = max(0.0, reaction[0]), reaction[1]
        force = next((r for r in FORCED_ORDER if r in forced), None)
        if force is not None:
            cand = min(cand, self.safe_current)
            for b in measured:  # the model is not trusted: the band at the measured temperatures
                cand = min(cand, b.factor * imax)
        return cand, reason, force

    def update(self, bands: Sequence[NodeBand], reaction: tuple[float, DerateReason] | None,
               forced: Sequence[DerateReason] = (), measured: Sequence[NodeBand] = ()) -> Limits:
        """Limits for this tick (see the module docstring and :meth:`candidate`)."""
        cfg = self.config
        imax = cfg.max_current_a
        candidate, reason, force = self.candidate(bands, reaction, forced, measured)
        # slew: fall at once; rise at the rise rate, and only past the hysteresis
        if candidate <= self.current:
            self.current = candidate
        elif candidate > self.current + cfg.hysteresis_a or (candidate >= imax and self.current < imax):
            self.current = min(candidate, self.current + cfg.rise_rate_a_per_s * self.tick_s)
        # else: within the hysteresis, hold
        # the reason: what limits now
        eps = 1e-9
        if force is not None:
            self.reason = force
        elif self.current >= imax - eps:
            self.reason = DerateReason.NONE
        elif self.current >= candidate - cfg.hysteresis_a - eps and reason != DerateReason.NONE:
            self.reason = reason  # at (or held within the hysteresis below) the candidate: its cause
        else:
            self.reason = DerateReason.RECOVERING  # only the rise rate holds it down
        torque_cap = self.safe_torque if force is not None else cfg.max_torque_nm
        torque = min(torque_cap, self.kt * self.current)
        self.last = Limits(self.current, torque, self.reason, self.reason != DerateReason.NONE)
        return self.last

    # -- between ticks (called from the TE_Limits sender thread: reads only constants and ``last``) --
    def stalled(self, tick_age_s: float | None) -> bool:
        """True if ``tick_age_s`` (s since the last tick; None: not judged) means the tick loop is stuck."""
        return tick_age_s is not None and tick_age_s > STALL_TICKS * self.tick_s

    def between_ticks(self, last: Limits | None, frame_age_s: float | None, tick_age_s: float | None) -> Limits:
        """The limits to send now (see the module docstring).

        Parameters
        ----------
        last : Limits or None
            The last tick's limits (None before the first tick).
        frame_age_s : float or None
            Seconds since the last accepted frame (or since the start); None where silence is
            expected (the frame clock waiting for an adaptation's result holds the sender back).
        tick_age_s : float or None
            Seconds since the last tick; None where ticks follow the frames (frame clock) or
            before the first tick.
        """
        if frame_age_s is not None and frame_age_s > self.bus_silence_s:
            return self._forced_after(DerateReason.STALE_INPUT, last)
        if last is None:
            return self.safe(DerateReason.STARTING)
        if self.stalled(tick_age_s):
            return self._forced_after(DerateReason.MODEL_FAULT, last)
        return last

    def _forced_after(self, reason: DerateReason, last: Limits | None) -> Limits:
        """The safe limit with ``reason``, never above ``last`` (decided between ticks, it cannot know better)."""
        safe = self.safe(reason)
        if last is not None and last.current_a < safe.current_a:
            return Limits(last.current_a, min(last.torque_nm, safe.torque_nm), reason, True)
        return safe
