"""A CAN log as runs: the model's inputs and sensors per tick, as the edge service saw them.

A CAN log (``.log`` candump -L, ``.asc``, ``.blf``, ``.trc``, python-can's ``.csv``, ``.mf4`` with
asammdf; the text formats gzipped too: :mod:`thermal_edge.bus.logs`) holds frames, not samples.
The service configuration decides everything the live service decides: the CAN matrix and its
integrity checks (``codec:``, :class:`~thermal_edge.bus.codec.FrameCodec` with each frame's declared protection: a
frame with a bad CRC or counter is dropped here as on the drive), which frame and signal is which model input and sensor
(``signals:``), the tick period and the frame clock (``clock:``, :class:`.clock.FrameClock`: ticks
where the frames' timestamps cross a tick boundary, timestamps out of order judged as live), and
the input accumulation (:class:`.inputs.InputAccumulator`: the time mean of i² for the current,
time means of speed and torque, the latest valid reading of the temperatures). So every offline
command that reads a recording (``replay``, ``calibrate``, ``discover``, ``export``, the fleet)
sees exactly what the service on the drive saw, one row per tick.

A log with silences (the drive off, the service restarted) gives one run per stretch of traffic:
a silence longer than the longest frame timeout of the configuration ends a run (its inputs would
be stale). Ticks before every input has had a value are left out; a sensor without a usable
reading (stale, faulty, out of the plausible range) is NaN. A reading the live service would have
withheld as stuck (its plausibility check over time, :class:`.health.StuckSensors`) is kept: the
run is the data, and judging the model against it is the offline commands' job.
"""
from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..bus.logs import FrameLogReader, LogFormatError, log_suffix, readable_suffixes
from ..config import EdgeConfig
from ..data import Run, RunError
from ..lptn import Model, Role, load_model
from .clock import FrameClock
from .current_torque import CurrentTorqueCheck
from .flux_input import DqMeans
from .inputs import InputAccumulator, TickInputs

__all__ = ["CAN_LOG_SUFFIXES", "LogRuns", "is_can_log", "log_runs", "read_log_runs"]

#: CAN log suffixes found by a directory search: what the bus module reads here (``.mf4`` with
#: asammdf), except ``.csv``, which in a directory of runs is a run CSV
CAN_LOG_SUFFIXES = tuple(s for s in readable_suffixes() if s != ".csv")


def is_can_log(path: str | os.PathLike[str]) -> bool:
    """True for a file whose suffix names a CAN log format the bus module reads (not ``.csv``)."""
    try:
        return log_suffix(Path(path)) != ".csv"
    except LogFormatError:
        return False


@dataclass
class LogRuns:
    """The runs of one CAN log and what the reading counted.

    Attributes
    ----------
    runs : list of Run
        One per stretch of traffic (see :func:`log_runs`).
    frames : int
        Frames received (the recording node's own frames left out) that passed the codec's
        integrity checks and belong to the configuration's CAN matrix.
    dropped : dict
        Frames the codec refused, by reason (:data:`thermal_edge.bus.stats.DROP_REASONS`).
    malformed_lines : int
        Damaged lines or records of the file, skipped.
    ticks_left_out : int
        Ticks before every model input had a value, and stretches of fewer than two complete ticks.
    current_judged, current_low, current_doubted : int
        Ticks whose torque the current is judged against, those whose current read below
        ``derating.faults.current_torque_ratio`` of what the torque takes, and those the service
        would not believe it at (three such in a row): a DBC scaling, a second sender of the
        current's frame (:mod:`.current_torque`). ``current_rule`` says what was judged.
    """

    runs: list[Run]
    frames: int
    dropped: dict[str, int] = field(default_factory=dict)
    malformed_lines: int = 0
    ticks_left_out: int = 0
    current_judged: int = 0
    current_low: int = 0
    current_doubted: int = 0
    current_rule: str = ""


@functools.lru_cache(maxsize=4)
def _model(model_path: str, mtime_ns: int) -> Model:
    """The configuration's model, loaded once per file version, not once per log (a fleet reads
    many logs of one model): its inputs' roles and its torque constant."""
    return load_model(model_path)


def _current_check(runs: list[Run], config: EdgeConfig, model: Model, out: LogRuns) -> None:
    """The current against the torque, tick by tick, as the service judges it
    (:class:`.current_torque.CurrentTorqueCheck`): the ticks it would not believe counted in
    ``out``. Every judged tick reading low is a scaling error of the whole log: refused."""
    for run in runs:
        chk = CurrentTorqueCheck.of(model, config.derating, config.kt(model))  # a fresh one per stretch
        if chk is None:
            return
        current, torque = chk.current_input, chk.torque_input
        for i, tq in zip(run.columns[current], run.columns[torque]):
            v = chk.judge({current: float(i), torque: float(tq)})
            if math.isfinite(v.needed):
                out.current_judged += 1
                out.current_low += float(i) < chk.ratio * v.needed
            out.current_doubted += v.doubted
        out.current_rule = (f"{_signal_of(config, current)} below {chk.ratio:g} of |{torque}| / kt "
                            f"(kt {chk.kt:g} Nm/A)")


#: the columns of the dq voltages and currents (``voltages=True``), as ``thermal-edge flux calibrate`` reads them
VOLTAGE_COLUMNS = ("u_d_v", "u_q_v", Role.CURRENT_D.default_column, Role.CURRENT_Q.default_column)


def _run(ticks: list[TickInputs], config: EdgeConfig, source: str, part: int,
         dq: list[np.ndarray] | None = None) -> tuple[Run | None, int]:
    """The run of one stretch of ticks (None if it has fewer than two complete ticks) and the
    number of its ticks left out; with ``dq`` (per tick, :class:`.flux_input.DqMeans`) the voltage columns too."""
    first = next((i for i, tk in enumerate(ticks) if tk.complete), None)
    if first is None or len(ticks) - first < 2:
        return None, len(ticks)
    kept = ticks[first:]
    t_abs = np.array([tk.t for tk in kept])
    cols = {name: np.array([tk.inputs[name] for tk in kept]) for name in config.inputs}
    cols.update({name: np.array([tk.measured[name] for tk in kept]) for name in config.sensors})
    if dq is not None:
        table = np.array(dq[first:]).reshape(-1, 4)
        cols.update({name: table[:, k] for k, name in enumerate(VOLTAGE_COLUMNS) if name not in cols or k < 2})
    run = Run(t_abs - t_abs[0], cols, f"{source}#{part}" if part else source, {"epoch_s": f"{t_abs[0]:.6f}"})
    return run, first


def log_runs(path: str | os.PathLike[str], config: EdgeConfig, voltages: bool = False) -> LogRuns:
    """Read a CAN log into runs through the service's codec, frame clock and input accumulation.

    Parameters
    ----------
    path : path-like
        The log; its suffix names the format.
    config : EdgeConfig
        The service configuration whose ``codec:``, ``signals:``, ``timeouts:`` and ``clock:``
        (tick period, ``max_catchup_s``) are used; its model gives the inputs' roles.
    voltages : bool
        Also the per-tick means of the dq voltage references and currents (:data:`VOLTAGE_COLUMNS`,
        V and A peak) from the frames and signals ``flux:`` names, when the log holds such frames.

    Returns
    -------
    LogRuns
        The runs: ``t`` in s from the run's first tick (that tick's epoch time, s, in
        ``meta["epoch_s"]``), the tick period apart; one column per model input and sensor of the
        configuration (°C, A rms, rpm, Nm). The first run's source is the file, the next ones
        ``<file>#1``, ``#2`` ...

    Raises
    ------
    RunError
        The file is no CAN log of its suffix's format, or holds not two complete ticks of the
        configuration's signals, or does not exist.
    ConfigError
        The configuration's CAN matrix lacks a frame or signal its ``signals:`` name.
    """
    codec = config.codec.frame_codec(config.fname)
    path_m = Path(config.model.path)
    model = _model(str(path_m), path_m.stat().st_mtime_ns if path_m.exists() else 0)
    roles = dict(model.input_roles)
    config.check_dbc(codec, roles)
    tick_s, catchup = config.clock.tick_s, config.clock.max_catchup_s
    silence = max(config.timeouts.values(), default=tick_s)
    source = str(path)
    out = LogRuns([], 0)
    ticks: list[TickInputs] = []
    acc, clock = InputAccumulator(config, roles), FrameClock(tick_s, catchup)
    dq_means = DqMeans(config.flux)
    dq: list[np.ndarray] = []
    last = -math.inf

    why: dict[str, str] = {}  # input or sensor -> why its last refused reading was refused

    def close_stretch() -> None:
        why.update({name: w for name in [*config.inputs, *config.sensors] if (w := acc.refusal(name))})
        run, left_out = _run(ticks, config, source, len(out.runs), dq if voltages and dq_means.seen else None)
        out.ticks_left_out += left_out
        if run is not None:
            out.runs.append(run)

    try:
        reader = FrameLogReader(Path(path), codec, include_tx=False)
        for frame in reader:
            if frame.timestamp is None:  # no time, no tick (python-can's "none"; the recorder never writes it)
                continue
            ts = float(frame.timestamp)
            # the drive was silent (judged on the stamps, before the clock would bridge the gap):
            # this stretch ends, also one of less than a tick (its frames would otherwise be held
            # as the inputs of every tick across the silence)
            if ts - last > silence and math.isfinite(last):
                close_stretch()
                ticks, acc, clock = [], InputAccumulator(config, roles), FrameClock(tick_s, catchup)
                dq_means.take()
                dq = []
            last = max(last, ts)
            for b in clock.observe(ts):
                ticks.append(acc.take(b))
                dq.append(dq_means.take())
            acc.add(frame, clock.now())
            if voltages:
                dq_means.add(frame)
            out.frames += 1
    except LogFormatError as exc:
        raise RunError(str(exc)) from None
    except FileNotFoundError:
        raise RunError(f"{path}: no such CAN log") from None
    close_stretch()
    out.dropped = {k: v for k, v in codec.stats.dropped.items() if v}
    out.malformed_lines = len(reader.malformed_lines)
    if not reader.messages_read:
        raise RunError(f"{Path(path)}: not one CAN frame read: an empty log, or not a {log_suffix(Path(path))} log"
                       + (f" ({out.malformed_lines} damaged lines)" if out.malformed_lines else ""))
    if not out.runs:
        refused = "; ".join(f"{_signal_of(config, k)} refused: {w}" for k, w in why.items() if k in config.inputs)
        raise RunError(f"{Path(path)}: {out.frames} frames of the configuration's CAN matrix, not two complete "
                       f"ticks of every input ({', '.join(config.inputs)}): no run in this CAN log"
                       + (f" ({refused})" if refused else ""))
    # a column no reading of which was used, because they were implausible: a unit or scaling error
    # of the CAN matrix, named rather than written as a column of NaN
    for name, w in why.items():
        if all(np.all(np.isnan(r.columns[name])) for r in out.runs if name in r.columns):
            raise RunError(f"{Path(path)}: every reading of {_signal_of(config, name)} was refused: {w}")
    _current_check(out.runs, config, model, out)
    if out.current_doubted and out.current_low == out.current_judged:
        raise RunError(f"{Path(path)}: every one of the {out.current_judged} ticks judged reads {out.current_rule}: "
                       "a scaling of the current in the DBC? (the copper losses go with its square)")
    return out


def _signal_of(config: EdgeConfig, name: str) -> str:
    """``name (frame signal)`` of a mapped input or sensor, for a message."""
    spec = config.inputs.get(name) or config.sensors[name]
    signals = "/".join(spec.signals) if hasattr(spec, "signals") else spec.signal
    return f"{name} ({spec.frame} {signals})"


def read_log_runs(path: str | os.PathLike[str], config: EdgeConfig) -> list[Run]:
    """The runs of one CAN log (:func:`log_runs` without the counts)."""
    return log_runs(path, config).runs
