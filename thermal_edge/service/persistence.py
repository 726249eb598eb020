"""Persistence of parameters, their history and the thermal state.

One JSON file, ``state.json`` in the state directory, written atomically: a temporary file in
the same directory, ``fsync``, ``rename`` over the old file, ``fsync`` of the directory. A reader
therefore sees the old or the new file, never a torn one, even after a power cut.

Loading never crashes the service: a missing file starts from the defaults; an unreadable or
inconsistent one (bad JSON, another model, wrong node list, non-finite values, parameters outside
their bounds) is logged with the reason, counted (:attr:`StateStore.load_errors`), moved aside
to ``state.json.corrupt-<time>`` and the service starts from the defaults.

On start the thermal state is **cooled over the downtime** with the model (zero current and
speed, at the last ambient; one zero-order-hold step is exact for held inputs), then corrected by
the first measurements through the observer.
"""
from __future__ import annotations

import json
import logging
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..lptn import Model, Stepper

__all__ = ["PersistedState", "StateError", "StateStore", "cool_down"]

log = logging.getLogger(__name__)

FORMAT = "thermal_edge.state"
VERSION = 1
FILENAME = "state.json"


class StateError(ValueError):
    """A state file that cannot be used (the message says why)."""


@dataclass
class PersistedState:
    """What survives a restart."""

    model: str
    saved_at: float  # clock time of the state, s since the epoch
    parameters: dict[str, float]  # every parameter that differs from the model file is kept here
    param_version: int = 0
    adapt_runs: int = 0
    decisions: list[dict[str, Any]] = field(default_factory=list)
    nodes: list[str] = field(default_factory=list)
    T: list[float] = field(default_factory=list)  # best estimate, degC
    sigma: list[float] = field(default_factory=list)  # its standard deviation, K
    T_pred: list[float] = field(default_factory=list)  # open-loop prediction, degC
    P: list[list[float]] = field(default_factory=list)  # covariance of the estimate, K²
    inputs: dict[str, float] = field(default_factory=dict)  # last inputs (ambient for the cool-down)
    saved_wall: float = 0.0

    def as_json(self) -> dict[str, Any]:
        return {"format": FORMAT, "version": VERSION, **self.__dict__}

    @classmethod
    def from_json(cls, raw: Any, model: Model) -> "PersistedState":
        if not isinstance(raw, dict):
            raise StateError("not a JSON object")
        if raw.get("format") != FORMAT:
            raise StateError(f"format is {raw.get('format')!r}, expected {FORMAT!r}")
        if raw.get("version") != VERSION:
            raise StateError(f"version {raw.get('version')!r} is not supported (expected {VERSION})")
        if raw.get("model") != model.name:
            raise StateError(f"it belongs to model {raw.get('model')!r}, the service runs {model.name!r}")
        try:
            st = cls(
                model=str(raw["model"]),
                saved_at=float(raw["saved_at"]),
                parameters={str(k): float(v) for k, v in dict(raw["parameters"]).items()},
                param_version=int(raw.get("param_version", 0)),
                adapt_runs=int(raw.get("adapt_runs", 0)),
                decisions=list(raw.get("decisions", [])),
                nodes=[str(x) for x in raw.get("nodes", [])],
                T=[float(x) for x in raw.get("T", [])],
                sigma=[float(x) for x in raw.get("sigma", [])],
                T_pred=[float(x) for x in raw.get("T_pred", [])],
                P=[[float(x) for x in row] for row in raw.get("P", [])],
                inputs={str(k): float(v) for k, v in dict(raw.get("inputs", {})).items()},
                saved_wall=float(raw.get("saved_wall", 0.0)),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise StateError(f"missing or malformed field: {exc}") from None
        if not math.isfinite(st.saved_at):
            raise StateError("saved_at is not finite")
        names = model.parameter_names
        lo, hi = model.bounds()
        for k, v in st.parameters.items():
            if k not in names:
                raise StateError(f"unknown parameter {k!r}")
            i = names.index(k)
            if not (math.isfinite(v) and lo[i] <= v <= hi[i]):
                raise StateError(f"parameter {k} = {v!r} outside its bounds [{lo[i]:g}, {hi[i]:g}]")
        if st.T:
            if st.nodes != list(model.nodes):
                raise StateError("its node list differs from the model's")
            for arr, what in ((st.T, "T"), (st.sigma, "sigma"), (st.T_pred, "T_pred")):
                if arr and (len(arr) != len(model.nodes) or not all(math.isfinite(x) for x in arr)):
                    raise StateError(f"{what} has the wrong length or non-finite values")
            n = len(model.nodes)
            if st.P and (len(st.P) != n or any(len(r) != n for r in st.P)
                         or not all(math.isfinite(x) for r in st.P for x in r)):
                raise StateError("P has the wrong shape or non-finite values")
            if not all(-100.0 < x < 500.0 for x in st.T):
                raise StateError("temperatures outside -100..500 degC")
        return st


class StateStore:
    """Load and save :class:`PersistedState` in a directory.

    Parameters
    ----------
    directory : path
        The state directory (created if needed).
    model : Model
        The machine model (for validation on load).
    """

    def __init__(self, directory: str | os.PathLike[str], model: Model) -> None:
        self.dir = Path(directory)
        self.model = model
        self.path = self.dir / FILENAME
        #: Files that could not be used on load (each moved aside).
        self.load_errors = 0
        #: Saves that failed (disk full, read-only, ...).
        self.save_errors = 0
        self.saves = 0
        self.last_error: str | None = None
        self.quarantined: list[Path] = []

    def load(self) -> PersistedState | None:
        """The saved state, or None (missing or unusable: then logged, counted, moved aside)."""
        try:
            text = self.path.read_text(encoding="utf-8")
        except FileNotFoundError:
            log.info("no saved state in %s: starting from the model's parameters", self.dir)
            return None
        except (OSError, UnicodeDecodeError) as exc:
            return self._bad(f"cannot read: {exc}")
        try:
            raw = json.loads(text)
        except json.JSONDecodeError as exc:
            return self._bad(f"not valid JSON ({exc.msg} at line {exc.lineno})")
        try:
            return PersistedState.from_json(raw, self.model)
        except StateError as exc:
            return self._bad(str(exc))

    def _bad(self, why: str) -> None:
        self.load_errors += 1
        self.last_error = why
        aside = self.path.with_name(f"{FILENAME}.corrupt-{time.strftime('%Y%m%dT%H%M%S')}-{os.getpid()}")
        try:
            os.replace(self.path, aside)
            self.quarantined.append(aside)
            where = f"moved aside to {aside.name}"
        except OSError as exc:
            where = f"could not move it aside: {exc}"
        log.error("state file %s is unusable: %s; %s; starting from the model's parameters", self.path, why, where)
        return None

    def save(self, state: PersistedState) -> bool:
        """Write atomically; False (logged, counted) on failure. Never raises."""
        tmp = self.path.with_name(f".{FILENAME}.{os.getpid()}.tmp")
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            data = json.dumps(state.as_json(), separators=(",", ":"), allow_nan=False).encode()
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            try:
                view = memoryview(data)
                while view:
                    n = os.write(fd, view)
                    view = view[n:]
                os.fsync(fd)
            finally:
                os.close(fd)
            os.replace(tmp, self.path)
            try:
                dfd = os.open(self.dir, os.O_RDONLY)
                try:
                    os.fsync(dfd)
                finally:
                    os.close(dfd)
            except OSError:
                pass
        except (OSError, ValueError, TypeError) as exc:
            self.save_errors += 1
            self.last_error = str(exc)
            if self.save_errors == 1 or self.save_errors % 100 == 0:
                log.error("cannot save state to %s: %s (failures so far: %d)", self.path, exc, self.save_errors)
            try:
                tmp.unlink(missing_ok=True)
            except OSError:
                pass
            return False
        self.saves += 1
        return True


def cool_down(model: Model, theta: np.ndarray, T: np.ndarray, downtime_s: float, inputs: Mapping[str, float],
              current_input: str = "i_rms") -> tuple[np.ndarray, np.ndarray]:
    """Node temperatures after ``downtime_s`` at standstill (zero current and speed) at the last
    ambient, and the transition matrix ``Φ`` of the downtime (to carry a covariance over it).

    One exact zero-order-hold step of the whole downtime (the inputs are held), so any downtime
    costs one discretisation.
    """
    n = len(model.nodes)
    if downtime_s <= 0:
        return np.asarray(T, dtype=float).copy(), np.eye(n)
    u = {k: float(v) for k, v in inputs.items()}
    temperatures = set(model.boundaries.values())
    for k in model.inputs:  # standstill: every input that is not a boundary temperature is zero
        if k not in temperatures or k == current_input:
            u[k] = 0.0
    for k in model.inputs:
        if k not in u or not math.isfinite(u[k]):
            raise ValueError(f"cool-down needs the last value of input {k!r}")
    st = Stepper(model, theta, float(downtime_s), method="zoh")
    Phi, _ = st.matrices(u)
    T1, _ = st.step(np.asarray(T, dtype=float), u)
    return T1, Phi
