"""A machine's recorded CAN traffic as runs: every log format the bus module reads, decoded with
the DBC and reduced to the model's inputs and sensors tick by tick, as the edge service does.

A CAN log (``.log`` candump, ``.asc``, ``.blf``, ``.trc``, gzipped or not; see
:mod:`thermal_edge.bus.logs`) holds frames, not samples. The service configuration's ``signals:``
say which frame and signal is which model input and sensor; its input accumulation
(:class:`thermal_edge.service.inputs.InputAccumulator`: mean of i² for the current, means of
speed and torque, the latest valid reading of the temperatures) on its frame clock gives one row
per tick. So a fleet calibrated from its drives' recordings sees exactly what their services saw.

A log with silences (the drive off, the service restarted) gives one run per stretch of traffic:
a silence longer than the longest frame timeout of the configuration ends a run. Ticks before
every input has had a value are left out; a sensor without a usable reading is NaN.
"""
from __future__ import annotations

import functools
import math
import os
from pathlib import Path

import numpy as np

from ..bus.logs import FrameLogReader, LogFormatError, log_suffix, readable_suffixes
from ..config import EdgeConfig, load_config
from ..data import Run, RunError
from ..lptn import Role, load_model
from ..service.clock import FrameClock
from ..service.inputs import InputAccumulator, TickInputs
from ..shipped import config_path

__all__ = ["CAN_LOG_SUFFIXES", "DEFAULT_CONFIG", "is_can_log", "read_can_runs"]

#: the service configuration whose ``signals:`` decode the logs by default
DEFAULT_CONFIG = config_path("edge.yaml")
#: CAN log suffixes a machine's directory is searched for: what the bus module reads here (``.mf4``
#: with asammdf), except ``.csv``, which is always a run CSV
CAN_LOG_SUFFIXES = tuple(s for s in readable_suffixes() if s != ".csv")


def is_can_log(path: str | os.PathLike[str]) -> bool:
    """True for a file whose suffix names a CAN log format the bus module reads (not ``.csv``)."""
    try:
        return log_suffix(path) != ".csv"
    except LogFormatError:
        return False


@functools.lru_cache(maxsize=4)
def _config(path: str) -> EdgeConfig:
    return load_config(path)


@functools.lru_cache(maxsize=4)
def _input_roles(model_path: str) -> dict[str, Role]:
    """Which of the model's inputs is the current, the speed, the torque: loaded once per model, not per log."""
    return dict(load_model(model_path).input_roles)


def _rows(ticks: list[TickInputs], config: EdgeConfig, source: str, part: int) -> Run | None:
    """The run of one stretch of ticks (None if it has fewer than two complete ticks)."""
    first = next((i for i, tk in enumerate(ticks) if tk.complete), None)
    if first is None or len(ticks) - first < 2:
        return None
    ticks = ticks[first:]
    t_abs = np.array([tk.t for tk in ticks])
    cols = {name: np.array([tk.inputs[name] for tk in ticks]) for name in config.inputs}
    cols.update({name: np.array([tk.measured[name] for tk in ticks]) for name in config.sensors})
    return Run(t_abs - t_abs[0], cols, f"{source}#{part}" if part else source, {"epoch_s": f"{t_abs[0]:.6f}"})


def read_can_runs(path: str | os.PathLike[str], config: str | os.PathLike[str] | EdgeConfig | None = None) -> list[Run]:
    """The runs of one CAN log: the model's inputs and sensors per tick, one run per stretch of traffic.

    Parameters
    ----------
    path : path-like
        The log; its suffix names the format.
    config : path-like or EdgeConfig, optional
        The service configuration whose ``signals:``, ``timeouts:``, ``codec:`` and tick period
        are used (default :data:`DEFAULT_CONFIG`, the packaged example ``edge.yaml``).

    Returns
    -------
    list of Run
        ``t`` in s from the run's first tick (its epoch time in ``meta["epoch_s"]``); columns
        named as the configuration's model inputs and sensors (°C, A, rpm, Nm). The first run's
        source is the file, the next ones ``<file>#1``, ``#2`` ...

    Raises
    ------
    RunError
        The log is no CAN log of its suffix's format, holds no decodable frame of the
        configuration, or not two complete ticks.
    FileNotFoundError
        No such file.
    """
    cfg = config if isinstance(config, EdgeConfig) else _config(str(config if config is not None else DEFAULT_CONFIG))
    codec = cfg.codec.frame_codec(cfg.fname)
    silence = max(cfg.timeouts.values(), default=cfg.clock.tick_s)
    source = str(path)
    runs: list[Run] = []
    ticks: list[TickInputs] = []
    roles = _input_roles(str(cfg.model.path))
    acc, clock = InputAccumulator(cfg, roles), FrameClock(cfg.clock.tick_s)
    last = -math.inf
    frames = 0
    try:
        for frame in FrameLogReader(path, codec, include_tx=False):
            ts = float(frame.timestamp)
            if ts - last > silence and ticks:  # the drive was silent: this stretch ends
                run = _rows(ticks, cfg, source, len(runs))
                if run is not None:
                    runs.append(run)
                ticks, acc, clock = [], InputAccumulator(cfg, roles), FrameClock(cfg.clock.tick_s)
            last = max(last, ts)
            ticks += [acc.take(b) for b in clock.observe(ts)]
            acc.add(frame, clock.now())
            frames += 1
    except LogFormatError as exc:
        raise RunError(str(exc)) from None
    run = _rows(ticks, cfg, source, len(runs))
    if run is not None:
        runs.append(run)
    if not runs:
        raise RunError(f"{Path(path)}: {frames} frames of the configuration's signals, not two complete ticks of "
                       f"every input ({', '.join(cfg.inputs)}): no run in this CAN log")
    return runs
