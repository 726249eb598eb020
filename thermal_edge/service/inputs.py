"""Input accumulation per tick: CAN frames -> the model's inputs and the sensor readings.

Per tick (the frames of ``[t - period, t)``):

- currents: the **mean of i²** over the tick (copper loss needs the mean square, not the square
  of the mean): ``dq_rms`` gives ``i_rms = sqrt(mean(i_d² + i_q²) / 2)`` from amplitude-invariant
  d/q currents (peak amplitudes; ``/ 3`` power-invariant, ``/ 1`` RMS-scaled: the input's ``dq:``,
  :data:`~thermal_edge.config.DQ_SQUARE_SHARE`), ``rms`` gives ``sqrt(mean(x²))`` of one signal
  (e.g. ``INV_IphRms``);
- ``mean`` inputs (speed, torque): the mean over the tick (optionally rounded to a resolution,
  which keeps the model's per-operating-point matrix cache effective).

The means are over **time**, not over frames: each frame's value holds until the next frame of
its input (zero-order hold), and the tick's mean weighs it by that time. A burst of frames
therefore weighs what the milliseconds it spans weigh: counted per frame, 2,000 frames at 0 A
sent once a second beside a steady 40 A would make the model see 8.7 A, the limit would rise to
the maximum and the stuck-sensor check would go blind. A tick whose
frames all carry one time stamp has no durations to weigh: its frames count alike.
- ``latest`` inputs (ambient) and the sensors: the latest valid reading, with its age and status.

A frame type that has not arrived for longer than its timeout makes its inputs *stale*; a sensor
reporting open/short circuit or "not fitted", or a value outside the plausible range, is *faulty*
(a sensor marked ``required: false`` is then only unmeasured). A current, speed or torque frame outside
its plausible range (:func:`input_ranges`) is left out of the tick's mean and makes the input faulty
(``out_of_range``) for that tick: a physically absurd value is a bad reading, not a load for the model. An input with
no fresh value keeps its last value (the model must keep running) and is flagged. Bad readings
are counted by kind in :attr:`InputAccumulator.bad_readings`.
"""
from __future__ import annotations

import dataclasses
import math
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import partial

from ..bus.codec import DecodedFrame
from ..bus.frames import SensorStatus
from ..config import DQ_SQUARE_SHARE, EdgeConfig, InputSignal, SensorSignal
from ..lptn import Role
from ..lptn.vocabulary import TEMPERATURE

__all__ = ["FAULT_KINDS", "InputAccumulator", "TickInputs", "input_ranges"]


@dataclass
class TickInputs:
    """What one tick knows about the machine.

    Attributes
    ----------
    t : float
        Tick time (end of the interval), s.
    inputs : dict
        Model input name -> value (held from earlier ticks when nothing fresh arrived; NaN if
        never received).
    measured : dict
        Sensor name -> reading in degC, NaN when not usable (faulty, stale, not fitted).
    ages : dict
        Sensor/input name -> seconds since its last valid value (inf if never).
    status : dict
        Sensor/input name -> last :class:`SensorStatus` (None when it has no status signal).
    stale : list of str
        Frames (by name) missing for longer than their timeout.
    faults : dict
        Sensor/input name -> fault kind (``open_circuit``, ``short_circuit``, ``not_fitted``,
        ``out_of_range``, ``no_value``; ``stuck`` is added by the engine's plausibility check over
        time, :class:`.health.StuckSensors`) for the required ones.
    frames : Counter
        Accepted frames of the tick per frame name.
    fresh : set of str
        Inputs that received at least one value during this tick.
    """

    t: float
    inputs: dict[str, float]
    measured: dict[str, float]
    ages: dict[str, float] = field(default_factory=dict)
    status: dict[str, int | None] = field(default_factory=dict)
    stale: list[str] = field(default_factory=list)
    faults: dict[str, str] = field(default_factory=dict)
    frames: Counter[str] = field(default_factory=Counter)
    fresh: set[str] = field(default_factory=set)

    @property
    def complete(self) -> bool:
        """Every model input has a finite value."""
        return all(math.isfinite(v) for v in self.inputs.values())


class _Latest:
    __slots__ = ("value", "t", "status", "fault", "tick_fault")

    def __init__(self) -> None:
        self.value = math.nan
        self.t = -math.inf
        self.status: int | None = None
        self.fault: str | None = None  # of the latest reading
        self.tick_fault: str | None = None  # any fault seen during the current tick (reported with it)


# "not fitted" on a sensor the configuration maps is a fault too: the model would run blind on it.
# A sensor the machine may lack is marked ``required: false`` and then only goes unmeasured.
_STATUS_FAULT = {int(SensorStatus.OPEN_CIRCUIT): "open_circuit", int(SensorStatus.SHORT_CIRCUIT): "short_circuit",
                 int(SensorStatus.NOT_FITTED): "not_fitted"}


def _status_code(x: float) -> int:
    """A status signal's value as its code; -1 (no code: a fault) for a value that is not a whole number."""
    return int(x) if math.isfinite(x) and x == int(x) else -1


def _age(t: float, t_reading: float) -> float:
    """Seconds from a reading (clock time ``t_reading``) to the tick ending at ``t``; never negative.

    On the wall clock a tick runs a moment after its boundary ``t`` and takes the readings that
    arrived meanwhile: such a reading is the tick's freshest, age 0, not one from the future.
    """
    return max(0.0, t - t_reading)


#: Every kind of rejected reading, in the order metrics list them.
FAULT_KINDS = ("open_circuit", "short_circuit", "not_fitted", "out_of_range", "no_value", "stuck", "current_below_torque",
               "unknown_status")


def input_ranges(config: EdgeConfig, roles: Mapping[str, Role]) -> dict[str, tuple[float, float]]:
    """The plausible range of each checked mean/rms input, per frame, found by its role in the
    model: the current (A rms) from 0 to ``signals.valid_current_factor`` x
    ``derating.max_current_a``, the speed within +-``signals.valid_speed_rpm`` rpm, the torque
    within +-``signals.valid_torque_factor`` x ``derating.max_torque_nm`` Nm.

    Parameters
    ----------
    config : EdgeConfig
    roles : mapping of str to Role
        The model's inputs and their roles (:attr:`~thermal_edge.lptn.Model.input_roles`).
    """
    sig, der = config.signals, config.derating
    by_role = {Role.CURRENT: (0.0, sig.valid_current_factor * der.max_current_a),
               Role.SPEED: (-sig.valid_speed_rpm, sig.valid_speed_rpm),
               Role.TORQUE: (-sig.valid_torque_factor * der.max_torque_nm, sig.valid_torque_factor * der.max_torque_nm)}
    return {name: by_role[role] for name, role in roles.items()
            if role in by_role and name in config.inputs and config.inputs[name].reduce != "latest"}


class InputAccumulator:
    """Accumulate decoded frames into :class:`TickInputs`, one tick at a time.

    Parameters
    ----------
    config : EdgeConfig
        Signal mapping (``signals``), plausible range and frame timeouts.
    roles : mapping of str to Role
        The model's inputs and their roles (which input is the current, the speed, the torque).
    """

    def __init__(self, config: EdgeConfig, roles: Mapping[str, Role]) -> None:
        self.config = config
        self.roles = dict(roles)
        self.lo, self.hi = config.valid_range_c
        self.reduced: dict[str, InputSignal] = {k: s for k, s in config.inputs.items() if s.reduce != "latest"}
        self.latest_inputs: dict[str, InputSignal] = {k: s for k, s in config.inputs.items() if s.reduce == "latest"}
        # a temperature input (ambient, coolant) within its role's range too: 215 degC (an 8-bit
        # channel's raw maximum, the sensor unplugged) is a winding's temperature, never the air's
        self._latest_range: dict[str, tuple[float, float]] = {
            k: (max(self.lo, r.plausible.lo), min(self.hi, r.plausible.hi))
            for k in self.latest_inputs if (r := self.roles.get(k)) is not None and r.is_temperature}
        self.sensors: dict[str, SensorSignal] = dict(config.sensors)
        # per frame: what to do with it (each action is called with the frame's signals and its time)
        self._by_frame: dict[str, list[Callable[[Mapping[str, float], float], None]]] = {}
        for name, spec in self.reduced.items():
            self._by_frame.setdefault(spec.frame, []).append(partial(self._reduce, name, spec))
        for name, spec in self.latest_inputs.items():
            self._by_frame.setdefault(spec.frame, []).append(partial(self._latest_value, name, spec.signals[0], spec.status))
        for name, sensor in self.sensors.items():
            self._by_frame.setdefault(sensor.frame, []).append(partial(self._latest_value, name, sensor.signal, sensor.status))
        self._sum = {k: 0.0 for k in self.reduced}  # Σ x over the tick's frames (no durations to weigh)
        self._n = {k: 0 for k in self.reduced}
        self._area = {k: 0.0 for k in self.reduced}  # ∫ x dt over the tick, each value held until the next frame
        self._span = {k: 0.0 for k in self.reduced}  # the time that integral covers, s
        self._hold: dict[str, tuple[float, float] | None] = dict.fromkeys(self.reduced)  # (value, since t)
        self._tick_start: float | None = None
        self.ranges = input_ranges(config, roles)
        self._implausible: set[str] = set()  # checked inputs with a frame out of range this tick
        self._was_implausible: set[str] = set()  # ... and in the last tick (a fault is counted when it starts)
        self._no_value: set[str] = set()  # mean/rms inputs with a frame carrying no value (NaN, inf) this tick
        self._held = {k: math.nan for k in config.inputs}
        self._latest: dict[str, _Latest] = {k: _Latest() for k in [*self.latest_inputs, *self.sensors]}
        self._last_frame_t: dict[str, float] = {}
        self._frames: Counter[str] = Counter()
        self.started_t: float | None = None
        #: Readings rejected, by kind (``open_circuit``, ``short_circuit``, ``not_fitted``, ``out_of_range``,
        #: ``no_value``; ``stuck``, counted by the engine), counted when a sensor enters the fault.
        self.bad_readings: Counter[str] = Counter()
        #: Frames whose signals did not have the expected names/values (counted, ignored).
        self.malformed: int = 0
        #: The last reading refused as out of range, by input or sensor (:meth:`refusal` says why).
        self.refused: dict[str, float] = {}

    # ------------------------------------------------------------------------------------------
    def add(self, frame: DecodedFrame, t: float) -> None:
        """Accumulate one accepted frame received at clock time ``t``; never raises."""
        actions = self._by_frame.get(frame.name)
        if self.started_t is None:
            self.started_t = t
        if actions is None:
            return
        try:
            sig = frame.signals
            for action in actions:
                action(sig, t)
        except (KeyError, TypeError, ValueError):
            self.malformed += 1
            return
        self._last_frame_t[frame.name] = t
        self._frames[frame.name] += 1

    def _integrate(self, name: str, t: float) -> None:
        """Add the held value of ``name`` over (its start or the tick's, whichever later, ``t``]."""
        hold = self._hold[name]
        if hold is None:
            return
        x, since = hold
        start = since if self._tick_start is None else max(since, self._tick_start)
        if t > start:
            self._area[name] += x * (t - start)
            self._span[name] += t - start

    def _reduce(self, name: str, spec: InputSignal, sig: Mapping[str, float], t: float) -> None:
        if spec.reduce == "dq_rms":
            d, q = float(sig[spec.signals[0]]), float(sig[spec.signals[1]])
            x = DQ_SQUARE_SHARE[spec.dq] * (d * d + q * q)
        else:
            x = float(sig[spec.signals[0]])
            if spec.reduce == "rms":
                x = x * x
        self._integrate(name, t)
        self._hold[name] = None  # a bad frame holds nothing: its time is left out of the mean
        if not math.isfinite(x):  # the signal's "no value" (NoValueRaw) or a float NaN/inf: no reading
            self.bad_readings["no_value"] += 1
            self._no_value.add(name)
            return
        rng = self.ranges.get(name)
        if rng is not None:
            v = math.sqrt(x) if spec.reduce in ("rms", "dq_rms") else x  # this frame's value (rms: its magnitude)
            if not rng[0] <= v <= rng[1]:
                self._implausible.add(name)
                self.refused[name] = v
                return
        self._hold[name] = (x, t)
        self._sum[name] += x
        self._n[name] += 1

    def _latest_value(self, name: str, signal: str, status_sig: str | None, sig: Mapping[str, float], t: float) -> None:
        slot = self._latest[name]
        value = float(sig[signal])
        status = _status_code(float(sig[status_sig])) if status_sig else None
        slot.status = status
        fault: str | None = None
        if status is not None and status != int(SensorStatus.VALID):
            # a code the matrix does not define (a wider status signal of another inverter) is not "valid"
            fault = _STATUS_FAULT.get(status, "unknown_status")
        elif not math.isfinite(value):
            fault = "no_value"
        elif not (rng := self._latest_range.get(name, (self.lo, self.hi)))[0] <= value <= rng[1]:
            fault = "out_of_range"
            self.refused[name] = value
        if fault is not None:
            if slot.fault != fault:
                self.bad_readings[fault] += 1
            slot.fault = slot.tick_fault = fault
            return
        slot.fault = None
        slot.value = value
        slot.t = t

    def refusal(self, name: str) -> str | None:
        """Why the last reading of ``name`` refused as out of range was refused, naming the unit
        it looks like where it is plausible in one ("300.2 degC looks like kelvin"); None if no
        reading of ``name`` was."""
        x = self.refused.get(name)
        if x is None:
            return None
        role, rng = self.roles.get(name), self.ranges.get(name)
        if rng is not None and role is not None:
            plausible = dataclasses.replace(role.plausible, lo=rng[0], hi=rng[1])
        else:  # a temperature: the configured valid range
            base = role.plausible if role is not None and role.is_temperature else TEMPERATURE
            lo, hi = self._latest_range.get(name, (self.lo, self.hi))
            plausible = dataclasses.replace(base, lo=lo, hi=hi)
        return plausible.problem(x)

    # ------------------------------------------------------------------------------------------
    def take(self, t: float) -> TickInputs:
        """The tick ending at ``t``; resets the per-tick sums."""
        inputs: dict[str, float] = {}
        fresh: set[str] = set()
        for name, spec in self.reduced.items():
            n = self._n[name]
            if n:
                self._integrate(name, t)
                span = self._span[name]
                mean = self._area[name] / span if span > 0 else self._sum[name] / n
                v = math.sqrt(max(mean, 0.0)) if spec.reduce in ("rms", "dq_rms") else mean
                if spec.resolution:
                    v = round(v / spec.resolution) * spec.resolution
                self._held[name] = v
                fresh.add(name)
            inputs[name] = self._held[name]
            self._sum[name] = self._area[name] = self._span[name] = 0.0
            self._n[name] = 0
        self._tick_start = t
        ages: dict[str, float] = {}
        status: dict[str, int | None] = {}
        # a frame of a mean/rms input without a value makes the tick's value unknown: the last one is
        # not carried on as if it were current (frames keep coming, so the input never goes stale)
        faults: dict[str, str] = dict.fromkeys(sorted(self._no_value), "no_value")
        faults.update(dict.fromkeys(sorted(self._implausible), "out_of_range"))
        self.bad_readings["out_of_range"] += len(self._implausible - self._was_implausible)
        self._was_implausible, self._implausible = self._implausible, set()
        self._no_value = set()
        for name in self.latest_inputs:
            slot = self._latest[name]
            inputs[name] = slot.value
            ages[name] = _age(t, slot.t)
            status[name] = slot.status
            if (fault := slot.fault or slot.tick_fault):
                faults[name] = fault
            slot.tick_fault = None
            if slot.t > t - self.config.clock.tick_s:
                fresh.add(name)
        measured: dict[str, float] = {}
        timeouts = self.config.timeouts
        for name, sensor in self.sensors.items():
            slot = self._latest[name]
            ages[name] = _age(t, slot.t)
            status[name] = slot.status
            limit = timeouts.get(sensor.frame)
            usable = slot.fault is None and math.isfinite(slot.value) and (limit is None or ages[name] <= limit)
            measured[name] = slot.value if usable else math.nan
            if (fault := slot.fault or slot.tick_fault) and sensor.required:
                faults[name] = fault
            slot.tick_fault = None
        never = self.started_t if self.started_t is not None else -math.inf  # a frame not seen yet: since the start
        stale = [f for f, limit in timeouts.items() if t - self._last_frame_t.get(f, never) > limit]
        frames, self._frames = self._frames, Counter()
        return TickInputs(t, inputs, measured, ages, status, stale, faults, frames, fresh)

    @property
    def fault_sources(self) -> list[str]:
        """The names whose fault is reported in :attr:`TickInputs.faults`: mean/rms inputs (no value,
        out of range), latest-value inputs and required sensors."""
        return [*self.reduced, *self.latest_inputs, *(n for n, spec in self.sensors.items() if spec.required)]

    def last_valid_t(self, name: str) -> float:
        """Clock time (s) of the last valid reading of a sensor or a latest-value input (-inf: none yet)."""
        return self._latest[name].t

    def reset(self) -> None:
        """Forget the per-tick sums (after a gap)."""
        for k in self._sum:
            self._sum[k] = self._area[k] = self._span[k] = 0.0
            self._n[k] = 0
            self._hold[k] = None
        self._implausible.clear()
