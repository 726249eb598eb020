"""Runs read for the offline commands: checked against the model and summarised before any fit.

Every offline command that reads a recorded run (``replay``, ``calibrate``, ``discover``,
``fleet``) goes through :func:`read_checked`: the file is read (:func:`thermal_edge.data.read_run`),
the model's inputs and sensors are looked up in it, units that cannot be right are refused
(:func:`thermal_edge.data.check_run`), and a one-line summary says what will be used. A CAN log
(``--format can``) is read into runs by the service's pipeline (:func:`read_checked_runs`,
:mod:`thermal_edge.service.logruns`) and each run checked the same way. A result
that is not finite (a law of the model that overflows) is refused by :func:`require_finite`
instead of being printed as ``inf`` or ``nan``.
"""
from __future__ import annotations

import argparse
import difflib
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from ..data import PADERBORN_COLUMNS, Run, RunError, check_run, describe, read_run
from ..lptn import Model, ModelError
from ..shipped import config_path

if TYPE_CHECKING:
    from ..service.logruns import LogRuns

#: ``--format`` of a CAN log (any format python-can reads, by its suffix)
CAN_FORMAT = "can"

#: How alike a column name and a missing sensor's name must be to be called a misspelling
#: (difflib ratio; "housng" and "housing" are 0.92, "housing" and "hot_spot" 0.53).
TYPO_RATIO = 0.8


def read_checked(path: str, fmt: str, model: Model, sensors: Sequence[str] | None = None) -> tuple[Run, str]:
    """Read a run for ``model`` and refuse what cannot be fitted or scored.

    Parameters
    ----------
    path : str
        The run file.
    fmt : {"csv", "paderborn"}
        Its format (:data:`thermal_edge.data.FORMATS`).
    model : Model
        The model the run is for: its inputs must be columns of the run, and at least one of its
        sensors.
    sensors : sequence of str, optional
        The sensors the command will use (default: every model sensor the run has).

    Returns
    -------
    run : Run
    summary : str
        One line: samples, sample period (s), duration (h), the columns used with their ranges,
        the columns ignored and the model's sensors the run lacks.

    Raises
    ------
    RunError
        One line naming the file and the column (or line) at fault: an input or sensor column
        missing (a misspelt sensor column is named with the sensor it resembles), no sensor of the
        model in the run, time not in seconds, temperatures not in degC, uneven sample times.
    """
    return _checked(read_run(path, fmt), path, fmt, model, sensors)


def read_checked_runs(path: str, fmt: str, model: Model, sensors: Sequence[str] | None = None,
                      config: str | None = None) -> list[tuple[Run, str]]:
    """:func:`read_checked` for a run file or a CAN log (``fmt`` ``"can"``): a CAN log gives one
    run per stretch of traffic, read through the service's pipeline with the service
    configuration ``config`` (:func:`thermal_edge.service.logruns.log_runs`), each checked as a run
    file is; the first summary line says what the log held.

    Parameters
    ----------
    config : str, optional
        ``fmt == "can"``: the service configuration (default: the shipped ``edge.yaml``).

    Raises
    ------
    RunError, ConfigError
        As :func:`read_checked`; a CAN log without two complete ticks of the configuration's inputs.
    """
    if fmt != CAN_FORMAT:
        return [read_checked(path, fmt, model, sensors)]
    from ..config import load_config
    from ..service.logruns import log_runs

    cfg_path = config if config is not None else config_path("edge.yaml")
    got = log_runs(path, load_config(cfg_path))
    try:
        out = [_checked(run, run.source, fmt, model, sensors) for run in got.runs]
    except RunError as exc:  # the columns come from the configuration: say so
        raise RunError(f"{exc}; a CAN log's columns are the inputs and sensors that the signals: of {cfg_path} "
                       "map (give the configuration of this model with --config)") from None
    head = f"{path}: {log_line(got)}"
    return [(run, f"{head}\n{summary}" if i == 0 else summary) for i, (run, summary) in enumerate(out)]


def log_line(got: LogRuns) -> str:
    """What a CAN log held: frames used and dropped, damaged lines, the runs and their ticks."""
    dropped = sum(got.dropped.values())
    why = f" ({', '.join(f'{k} {v}' for k, v in got.dropped.items())})" if dropped else ""
    ticks = sum(len(r) for r in got.runs)
    return (f"{got.frames} frames of the drive's CAN matrix, {dropped} dropped by the integrity checks{why}, "
            f"{got.malformed_lines} damaged lines skipped; {len(got.runs)} run(s) of {ticks} ticks in all"
            + (f" ({got.ticks_left_out} ticks left out: before every input had a value, or in stretches of fewer "
               "than two complete ticks)" if got.ticks_left_out else "")
            + (f"; {got.current_doubted} ticks the service would not believe the current at ({got.current_rule} "
               "for 3 ticks or more: a DBC scaling, a second sender of its frame?)" if got.current_doubted else ""))


def _checked(run: Run, path: str, fmt: str, model: Model, sensors: Sequence[str] | None) -> tuple[Run, str]:
    cols = list(run.columns)
    missing = [c for c in model.inputs if c not in run.columns]
    if missing:
        hint = ""
        if fmt != "paderborn" and any(c in run.columns for c in PADERBORN_COLUMNS):
            hint = "; a Paderborn file? use --format paderborn"
        else:
            hint = _did_you_mean(missing[0], cols)
        raise RunError(f"{path}: no column {missing[0]!r}: model {model.name} needs input column(s) "
                       f"{', '.join(missing)} (the run has: {', '.join(cols)}){hint}")
    if sensors is not None:
        unknown = [s for s in sensors if s not in model.sensors]
        if unknown:
            raise RunError(f"{path}: --sensors {unknown[0]!r}: model {model.name} has no such sensor "
                           f"(has: {', '.join(model.sensors)})")
        absent = [s for s in sensors if s not in run.columns]
        if absent:
            raise RunError(f"{path}: no column {absent[0]!r} for the sensor given in --sensors"
                           f"{_did_you_mean(absent[0], cols)}")
    present = [s for s in model.sensors if s in run.columns]
    lacking = [s for s in model.sensors if s not in run.columns]
    spare = [c for c in cols if c not in model.inputs and c not in model.sensors]
    for s in lacking:  # a sensor column under a misspelt name would be dropped without a word
        close = difflib.get_close_matches(s, spare, n=1, cutoff=TYPO_RATIO)
        if close:
            raise RunError(f"{path}: column {close[0]!r} is not a sensor of model {model.name}; "
                           f"did you mean {s!r}? (the run has no column {s!r})")
    if not model.sensors:  # nothing of the run can be compared with the model
        raise RunError(f"{model.where}: sensors: model {model.name} declares no sensors: nothing of the run {path} can be "
                       "compared with it")
    if not present:
        raise RunError(f"{path}: none of model {model.name}'s sensors ({', '.join(model.sensors)}) is a column "
                       f"of the run (it has: {', '.join(cols)}); the wrong model or the wrong file?")
    used_sensors = list(sensors) if sensors is not None else present
    check_run(run, [*used_sensors, *model.temperature_inputs], dict(model.input_roles))
    run.dt  # uneven sample times are refused here, before anything is fitted  # noqa: B018
    summary = describe(run, [*model.inputs, *used_sensors])
    not_used = [s for s in model.sensors if s not in used_sensors]
    if not_used:
        summary += (f"; model sensors not used: {', '.join(not_used)}"
                    + (f" (not in the run: {', '.join(lacking)})" if lacking else ""))
    return run, summary


def add_can_args(p: argparse.ArgumentParser, formats: Sequence[str]) -> None:
    """``--format`` (the run formats and ``can``) and ``--config`` (the service configuration that
    decodes a CAN log)."""
    p.add_argument("--format", default="csv", choices=(*formats, CAN_FORMAT),
                   help="run file format (default csv); can: a CAN log of any format python-can reads, by its "
                        "suffix (.log candump -L, .asc, .blf, .trc, .csv, .mf4), read as the service sees it")
    p.add_argument("--config", default=str(config_path("edge.yaml")),
                   help="can: the service configuration whose CAN matrix, signal mapping and tick decode the log "
                        "(default: the example edge.yaml)")


def _did_you_mean(name: str, candidates: Sequence[str]) -> str:
    close = difflib.get_close_matches(name, candidates, n=1, cutoff=TYPO_RATIO)
    return f"; did you mean {close[0]!r}?" if close else ""


#: A predicted node temperature beyond this, degC, is a law of the model out of bounds (far beyond
#: any material's melting point), refused as the overflow it leads to instead of printed.
DIVERGED_C = 1e4


def require_finite(model: Model, run: Run, T: np.ndarray, what: str) -> None:
    """Refuse a node-temperature series that is not finite everywhere or beyond :data:`DIVERGED_C`.

    Parameters
    ----------
    model : Model
    run : Run
        The run the series was computed on (same samples).
    T : ndarray (N, n)
        Node temperatures, degC.
    what : str
        What ``T`` is ("the open-loop prediction", "the observer's estimate"), for the message.

    Raises
    ------
    ModelError
        One line naming the model file, the first node and sample that are not finite, and the
        inputs there: a loss or conductance law of the model overflows (or divides by zero).
    """
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(T) | (np.abs(T) > DIVERGED_C)
    if not bad.any():
        return
    k, i = (int(x) for x in np.argwhere(bad)[0])
    inputs = ", ".join(f"{c} = {run.columns[c][k]:g}" for c in model.inputs if c in run.columns)
    how = "is not finite" if not np.isfinite(T[k, i]) else f"diverges ({T[k, i]:.3g} degC)"
    law = _first_infinite_law(model, run, T, k)
    raise ModelError(f"{model.path}: {what} {how} from sample {k + 1} (t = {run.t[k]:g} s) on, node "
                     f"{model.nodes[i]!r}: " + (f"{law} at {inputs}" if law else
                                                f"a loss or conductance law overflows at {inputs}"))


def _first_infinite_law(model: Model, run: Run, T: np.ndarray, k: int) -> str | None:
    """The first loss law that is not finite at sample ``k``'s inputs and the temperatures of the
    sample before, with its value (``losses[1].power is -inf``); None when every one is finite
    there (the state itself ran away). A conductance that is not finite is refused where the
    network is made (:class:`~thermal_edge.lptn.Network`)."""
    from ..lptn import Network
    from ..lptn.losses import LossLaws

    try:
        env = Network(model).env(model.nominal(), {c: float(run.columns[c][k]) for c in model.inputs})
        laws = LossLaws(model)
        with np.errstate(all="ignore"):
            law = laws.not_finite(laws.power(env, T[max(k - 1, 0)]))
    except Exception:  # naming the law is a courtesy: the refusal stands without it
        return None
    return None if law is None else f"{law} (a logarithm of 0, a division by 0?)"


def require_finite_prediction(model: Model, run: Run) -> None:
    """Predict ``run`` open loop at the model's nominal parameters and refuse it (as
    :func:`require_finite`) if the prediction is not finite: a fit would fail on it without
    saying why."""
    from ..estimation.predict import open_loop

    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        traj, _ = open_loop(model, run)
    require_finite(model, run, traj.T, "the open-loop prediction at the nominal parameters")
