"""Drive cycles (a file, or a packaged one by name: :mod:`thermal_edge.shipped`): segments of speed,
torque and ambient, turned into a run.

A segment holds its speed (rpm), torque (Nm), ambient and coolant (°C) for ``duration_s``; with
``ramp_s`` it starts with a linear ramp from the previous segment's values. The simulated inverter
turns torque into currents with the machine's torque constant (``drive.kt_nm_per_arms``, i_d = 0
control): ``i_rms = |torque| / kt``, ``i_q = sqrt(2) i_rms · sign(torque)``.
"""
from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..data import Run
from ..errors import ThermalEdgeError
from ..lptn.loader import read_yaml
from ..lptn.vocabulary import DEFAULT_COLUMNS, Role

SPEED, TORQUE, AMBIENT, COOLANT = (DEFAULT_COLUMNS[r] for r in (Role.SPEED, Role.TORQUE, Role.AMBIENT, Role.COOLANT))
#: a segment's values: the keys of a cycle file and the columns of its run (data without a model)
FIELDS = (SPEED, TORQUE, AMBIENT, COOLANT)


class CycleError(ThermalEdgeError, ValueError):
    """An invalid cycle file; the message names the file and the key."""


#: Samples a cycle may be turned into: 116 days at 1 s, about 1 GB of input columns; beyond it a
#: ``dt_s`` or a duration typed in ms is the usual cause.
MAX_SAMPLES = 10_000_000


def samples(duration_s: float, dt_s: float) -> int:
    """Samples of a run of ``duration_s`` at ``dt_s`` (both ends)."""
    return int(round(duration_s / dt_s)) + 1


@dataclass(frozen=True)
class Segment:
    """One segment: its duration, its values (:data:`FIELDS` -> speed rpm, torque Nm, ambient and
    coolant °C) and the ramp from the previous segment's values, s."""

    duration_s: float
    values: Mapping[str, float]
    ramp_s: float = 0.0


@dataclass(frozen=True)
class Cycle:
    name: str
    dt_s: float
    segments: tuple[Segment, ...]
    description: str = ""

    @property
    def duration_s(self) -> float:
        return sum(s.duration_s for s in self.segments)


def load_cycle(path: str | os.PathLike[str]) -> Cycle:
    """Load and validate a cycle file."""
    path = Path(path)
    f = path.name
    raw = read_yaml(path, CycleError)
    if not isinstance(raw, dict):
        raise CycleError(f"{f}: (top): expected a mapping")

    def num(key: str, v: Any, positive: bool = False) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise CycleError(f"{f}: {key}: expected a finite number, got {v!r}")
        if positive and not v > 0:
            raise CycleError(f"{f}: {key}: must be positive, got {v}")
        return float(v)

    def temperature(key: str, v: Any, role: Role) -> float:
        x = num(key, v)
        why = role.plausible.problem(x)  # an air at 298.15 "degC" is a kelvin value
        if why:
            raise CycleError(f"{f}: {key}: {why}")
        return x

    dt = num("dt_s", raw.get("dt_s", 1.0), positive=True)
    defaults = {AMBIENT: temperature(AMBIENT, raw.get(AMBIENT, 25.0), Role.AMBIENT),
                COOLANT: temperature(COOLANT, raw.get(COOLANT, raw.get(AMBIENT, 25.0)), Role.COOLANT)}
    roles = {AMBIENT: Role.AMBIENT, COOLANT: Role.COOLANT}
    segs_raw = raw.get("segments")
    if not isinstance(segs_raw, list) or not segs_raw:
        raise CycleError(f"{f}: segments: expected a non-empty list")
    segs = []
    for i, s in enumerate(segs_raw):
        key = f"segments[{i}]"
        if not isinstance(s, dict):
            raise CycleError(f"{f}: {key}: expected a mapping")
        unknown = set(s) - set(FIELDS) - {"duration_s", "ramp_s"}
        if unknown:
            raise CycleError(f"{f}: {key}.{sorted(unknown)[0]}: unknown key")
        for req in ("duration_s", SPEED, TORQUE):
            if req not in s:
                raise CycleError(f"{f}: {key}.{req}: is required")
        values = {k: (temperature(f"{key}.{k}", s[k], roles[k]) if k in roles and k in s else
                      num(f"{key}.{k}", s[k] if k in s else defaults[k])) for k in FIELDS}
        duration, ramp = num(f"{key}.duration_s", s["duration_s"], positive=True), num(f"{key}.ramp_s", s.get("ramp_s", 0.0))
        if not 0.0 <= ramp <= duration:  # the ramp is the start of its segment: it cannot outlast it
            raise CycleError(f"{f}: {key}.ramp_s: {ramp:g} s must lie within 0 and the segment's duration_s ({duration:g} s)")
        segs.append(Segment(duration, values, ramp))
    repeat = int(num("repeat", raw.get("repeat", 1), positive=True))
    n = samples(sum(s.duration_s for s in segs) * repeat, dt)
    if n > MAX_SAMPLES:
        raise CycleError(f"{f}: dt_s: {dt:g} s steps over the cycle's {sum(s.duration_s for s in segs) * repeat:g} s are "
                         f"{n:.3g} samples, more than {MAX_SAMPLES:.0e} (dt_s and duration_s are in seconds)")
    return Cycle(str(raw.get("name", path.stem)), dt, tuple(segs) * repeat, str(raw.get("description", "")))


def cycle_run(cycle: Cycle, kt_nm_per_arms: float, duration_s: float | None = None) -> Run:
    """Sample a cycle into a run of inputs (no sensor columns).

    Parameters
    ----------
    cycle : Cycle
    kt_nm_per_arms : float
        Torque constant, Nm per RMS ampere.
    duration_s : float, optional
        Truncate (or repeat the cycle up to) this duration, s.

    Raises
    ------
    CycleError
        More than :data:`MAX_SAMPLES` samples.
    """
    total = cycle.duration_s if duration_s is None else duration_s
    n = samples(total, cycle.dt_s)
    if n > MAX_SAMPLES:
        raise CycleError(f"--duration {total:g} s: cycle {cycle.name} at its {cycle.dt_s:g} s steps gives {n:.3g} samples, "
                         f"more than {MAX_SAMPLES:.0e} (--duration is in seconds)")
    t = np.arange(n) * cycle.dt_s
    bounds = np.cumsum([0.0] + [s.duration_s for s in cycle.segments])
    cols = {k: np.empty(n) for k in FIELDS}
    repeats = duration_s is not None and duration_s > cycle.duration_s
    tt = np.mod(t, cycle.duration_s) if repeats else np.minimum(t, cycle.duration_s)
    idx = np.clip(np.searchsorted(bounds, tt, side="right") - 1, 0, len(cycle.segments) - 1)
    for i, seg in enumerate(cycle.segments):
        sel = idx == i
        prev = cycle.segments[i - 1] if i > 0 else seg
        local = tt[sel] - bounds[i]
        frac = np.clip(local / seg.ramp_s, 0.0, 1.0) if seg.ramp_s > 0 else np.ones(sel.sum())
        for k in FIELDS:
            a, b = prev.values[k], seg.values[k]
            cols[k][sel] = a + (b - a) * frac
    i_rms = np.abs(cols[TORQUE]) / kt_nm_per_arms
    cols[DEFAULT_COLUMNS[Role.CURRENT]] = i_rms
    cols[DEFAULT_COLUMNS[Role.CURRENT_D]] = np.zeros(n)
    cols[DEFAULT_COLUMNS[Role.CURRENT_Q]] = math.sqrt(2.0) * i_rms * np.sign(cols[TORQUE])
    return Run(t, cols, f"cycle:{cycle.name}")
