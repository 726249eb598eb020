"""Replay a ``candump -L`` log through the service pipeline.

The log's received frames go through the same codec checks, input accumulation and tick engine
as in the live service, with the **frame-timestamp clock** (ticks at the boundaries the frames'
timestamps cross) and the adapter run synchronously, its results applied at the same tick as in
a live frame-clock run. A log recorded by a live frame-clock run therefore replays to the same
estimates, tick by tick.

Timestamps out of order are judged as the live frame clock judges them (:class:`.clock.FrameClock`):
jitter of less than a tick is used and counted; a jump back of a tick or more that the frames
after it keep to is a new segment, joined on without a gap (ticked through, nothing dropped); a
jump that they contradict is a corrupt stamp, ignored for the clock. The summary says how many of
each (:func:`format_summary`).

What the summary reports (ticks, first and last tick, final estimate, peaks, lowest current
limit) is folded in tick by tick (:class:`ReplayTotals`): a replay that asks for the summary alone
(``per_tick=False``, ``thermal-edge replay --format can`` without ``--out``/``--plot``) keeps
nothing per tick, so its memory does not grow with the log's length.
"""
from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..bus.logs import FrameLogReader, LogFormatError
from ..bus.stats import DROP_REASONS
from ..config import ClockConfig, EdgeConfig, MetricsConfig
from ..lptn import Model
from .clock import FrameClock
from .engine import ThermalEngine, load_service_model
from .flux_input import OUTCOMES
from .outputs import TickOutput
from .persistence import PersistedState

__all__ = ["ReplayResult", "ReplayTotals", "clock_line", "format_summary", "replay_candump", "replay_log", "replay_summary",
           "summarise", "voltage_line"]


class ReplayTotals:
    """What the summary of a replay reports, folded in tick by tick (constant memory).

    Parameters
    ----------
    n_nodes : int
        Nodes of the model.

    Attributes
    ----------
    ticks : int
        Ticks folded in.
    t_first, t_last : float
        Time of the first and the last tick, s since the epoch (NaN before the first).
    final_estimate : ndarray (nodes,)
        The last tick's estimate, °C (NaN before the first).
    peak : ndarray (nodes,)
        Highest estimate per node over the ticks, NaN left out (``np.nanmax`` of the column), °C.
    finite : ndarray of bool (nodes,)
        Whether the node had a finite estimate at any tick (its peak is meaningless otherwise).
    min_current_limit_a : float
        Lowest current limit sent, A rms; NaN if one was NaN (as ``np.min`` of the column).
    """

    def __init__(self, n_nodes: int) -> None:
        self.ticks = 0
        self.t_first = self.t_last = math.nan
        self.final_estimate = np.full(n_nodes, math.nan)
        self.peak = np.full(n_nodes, math.nan)
        self.finite = np.zeros(n_nodes, dtype=bool)
        self.min_current_limit_a = math.inf

    def add(self, out: TickOutput) -> None:
        """Fold in one tick's output."""
        if not self.ticks:
            self.t_first = float(out.t)
        self.ticks += 1
        self.t_last = float(out.t)
        self.final_estimate = out.estimate
        np.fmax(self.peak, out.estimate, out=self.peak)
        self.finite |= np.isfinite(out.estimate)
        self.min_current_limit_a = float(np.minimum(self.min_current_limit_a, out.limits.current_a))


@dataclass
class ReplayResult:
    """Results of a replay: its totals and, unless the replay was asked for its summary alone,
    its per-tick arrays.

    ``estimate``, ``sigma``, ``prediction`` are (ticks, nodes) arrays in the model's node order;
    ``current_limit_a``, ``reason``, ``state`` one value per tick; all of them with no row when
    the replay kept nothing per tick (``per_tick=False``): ``totals`` then has what the summary
    reports.
    """

    nodes: tuple[str, ...]
    t: np.ndarray
    estimate: np.ndarray
    sigma: np.ndarray
    prediction: np.ndarray
    current_limit_a: np.ndarray
    reason: np.ndarray
    state: np.ndarray
    pred_err_rms: np.ndarray
    decisions: list[dict[str, Any]]
    parameters: dict[str, float]
    frame_stats: dict[str, Any]
    frames: int
    malformed_lines: int
    outputs: list[TickOutput] = field(default_factory=list)
    #: the frame clock's counters (:meth:`.clock.FrameClockStats.as_dict`), ``gaps`` (bridged by the
    #: engine) and ``judging`` (frames of a jump the log ended before judging)
    clock: dict[str, float] = field(default_factory=dict)
    #: the voltage input's ticks per outcome (:data:`.flux_input.OUTCOMES`, every one listed), None
    #: without ``flux.calibration`` (the service then fuses no voltages)
    flux: dict[str, int] | None = None
    #: ticks, first and last tick, final estimate, peaks and lowest current limit (kept also without
    #: the per-tick arrays)
    totals: ReplayTotals = field(default_factory=lambda: ReplayTotals(0))

    def node(self, name: str) -> np.ndarray:
        return self.estimate[:, self.nodes.index(name)]


def replay_candump(path: str | os.PathLike[str], config: EdgeConfig, *, model: Model | None = None,
                   state: PersistedState | None = None, keep_outputs: bool = False,
                   per_tick: bool = True) -> ReplayResult:
    """Feed a candump log through the service pipeline; returns the estimates per tick.

    Parameters
    ----------
    path : path-like
        ``candump -L`` log (received frames are replayed; the service's own ``T`` lines are not).
    config : EdgeConfig
        The service configuration (the clock is forced to ``frame``, the adapter runs in-line).
    model : Model, optional
        Default: the configuration's model with its offline parameters.
    state : PersistedState, optional
        Start from this saved state (as the live service did, if it had one).
    keep_outputs : bool
        Also return every :class:`TickOutput` (and the per-tick arrays).
    per_tick : bool
        Return the per-tick arrays. False (and no ``keep_outputs``): only :attr:`ReplayResult.totals`,
        what the summary reports, and nothing is kept per tick (memory independent of the log's length).

    Raises
    ------
    FileNotFoundError, thermal_edge.bus.LogFormatError
        Missing file, or not a candump log.
    """
    cfg = replace(config, clock=ClockConfig("frame", config.clock.tick_s, config.clock.max_catchup_s),
                  metrics=MetricsConfig(enabled=False))
    model = model if model is not None else load_service_model(cfg)
    codec = cfg.codec.frame_codec(cfg.fname)
    cfg.check_dbc(codec, model.input_roles)
    engine = ThermalEngine(cfg, model, state, worker_mode="sync")
    clock = FrameClock(cfg.clock.tick_s, cfg.clock.max_catchup_s)
    reader = FrameLogReader(Path(path), codec, include_tx=False)
    n = len(model.nodes)
    totals = ReplayTotals(n)
    outs: list[TickOutput] = []
    # the per-tick rows, as compact as the arrays they become (a TickOutput is several times larger)
    rows: dict[str, list[Any]] = {k: [] for k in ("t", "estimate", "sigma", "prediction", "current_limit_a", "reason",
                                                  "state", "pred_err_rms")}
    rowwise = per_tick or keep_outputs
    n_frames = 0
    try:
        for frame in reader:
            n_frames += 1
            for b in engine.ticks_for(clock.observe(frame.timestamp)):
                o = engine.tick(b)
                totals.add(o)
                if keep_outputs:
                    outs.append(o)
                if rowwise:
                    for k, v in (("t", o.t), ("estimate", o.estimate), ("sigma", o.sigma), ("prediction", o.prediction),
                                 ("current_limit_a", o.limits.current_a), ("reason", int(o.limits.reason)),
                                 ("state", int(o.state)), ("pred_err_rms", o.pred_err_rms)):
                        rows[k].append(v)
            engine.add_frame(frame, clock.now(), clock.behind(frame.timestamp))
    finally:
        engine.close()
    table = {k: np.array(v) for k, v in rows.items()}
    for k in ("estimate", "sigma", "prediction"):
        if not rows[k]:
            table[k] = np.zeros((0, n))
    return ReplayResult(
        nodes=tuple(model.nodes), t=table["t"], estimate=table["estimate"], sigma=table["sigma"],
        prediction=table["prediction"], current_limit_a=table["current_limit_a"], reason=table["reason"],
        state=table["state"], pred_err_rms=table["pred_err_rms"],
        decisions=engine.adaptation.decisions, parameters=engine.adaptation.values(), frame_stats=codec.stats.as_dict(),
        frames=n_frames, malformed_lines=len(reader.malformed_lines), outputs=outs,
        clock={**clock.stats.as_dict(), "gaps": engine.gaps, "judging": clock.judging},
        flux=None if engine.flux is None else {k: int(engine.flux.counts[k]) for k in OUTCOMES},
        totals=totals,
    )


def replay_log(path: str | os.PathLike[str], config_path: str | os.PathLike[str],
               model_path: str | os.PathLike[str] | None = None, sets: Mapping[str, float] | None = None, *,
               keep_outputs: bool = False, per_tick: bool = True) -> tuple[ReplayResult, Model]:
    """Replay a log with a service configuration file: the result and the model it ran.

    ``model_path`` overrides the configuration's model, ``sets`` (``--set``, checked against the
    model's bounds) is merged into its ``model.parameters``; ``keep_outputs`` keeps every tick's
    :class:`TickOutput`; ``per_tick`` False keeps no per-tick arrays (:func:`replay_candump`).

    Raises ``thermal_edge.config.ConfigError``, ``FileNotFoundError`` or
    ``thermal_edge.bus.LogFormatError`` with one-line messages (the last also for a log without
    one tick).
    """
    from ..config import ModelConfig, load_config

    cfg = load_config(config_path)
    if model_path is not None:
        cfg = replace(cfg, model=ModelConfig(Path(model_path), cfg.model.parameters))
    if sets:
        cfg = replace(cfg, model=ModelConfig(cfg.model.path, {**cfg.model.parameters, **sets}))
    model = load_service_model(cfg)
    res = replay_candump(path, cfg, model=model, keep_outputs=keep_outputs, per_tick=per_tick)
    if not res.frames:  # nothing of the drive's CAN matrix: the wrong log, not a short one
        other = int(res.frame_stats.get("unknown_id", 0))
        raise LogFormatError(f"{path}: no frame of the drive's CAN matrix ({other} frame(s) with other identifiers, "
                             f"{res.malformed_lines} malformed line(s)): not a CAN log of this drive, or an empty one")
    if not res.totals.ticks:  # nothing to report but zeros: refused as a log too short, not printed as a result
        raise LogFormatError(f"{path}: {res.frames} frame(s) of the drive's CAN matrix but not one tick (a tick needs "
                             f"frames on both sides of a {cfg.clock.tick_s:g} s boundary): too short to replay")
    return res, model


def replay_summary(path: str | os.PathLike[str], config_path: str | os.PathLike[str],
                   model_path: str | os.PathLike[str] | None = None,
                   sets: Mapping[str, float] | None = None) -> dict[str, Any]:
    """``thermal-edge replay --format can``: replay a log with a service configuration
    (:func:`replay_log`, nothing kept per tick) and summarise it (:func:`summarise`)."""
    res, model = replay_log(path, config_path, model_path, sets, per_tick=False)
    return summarise(path, res, model)


def summarise(path: str | os.PathLike[str], res: ReplayResult, model: Model) -> dict[str, Any]:
    """The summary of a replay (JSON-serialisable): frames, ticks, drops, adaptations, peaks (from
    :attr:`ReplayResult.totals`: the same with or without the per-tick arrays)."""
    lim = {name: i for i, name in enumerate(res.nodes)}
    tot = res.totals
    out: dict[str, Any] = {
        "log": str(path), "model": model.name, "frames": res.frames, "ticks": tot.ticks,
        "malformed_lines": res.malformed_lines,
        "frames_lost": int(res.frame_stats["lost"]),
        "frames_dropped": {k: int(res.frame_stats[k]) for k in DROP_REASONS},
        "adaptations": {"decisions": len(res.decisions), "accepted": sum(1 for d in res.decisions if d.get("accepted"))},
        "parameters": res.parameters,
        "frame_clock": res.clock,
        "voltage_input": res.flux,
    }
    if tot.ticks:
        out["t_first"], out["t_last"] = tot.t_first, tot.t_last
        out["final_estimate_c"] = {n: float(tot.final_estimate[i]) for n, i in lim.items()}
        # a limited node never estimated (the observer never started: a sensor frame always refused)
        # has no peak: left out, not NaN
        out["max_estimate_c"] = {l.name: float(tot.peak[lim[l.node]]) for l in model.limits if tot.finite[lim[l.node]]}
        out["min_current_limit_a"] = tot.min_current_limit_a
    return out


def clock_line(c: Mapping[str, float]) -> str:
    """One line of what the frame clock did with timestamps out of order and gaps."""
    behind, jitter = int(c.get("behind", 0)), int(c.get("jitter", 0))
    parts = [f"{behind} frames stamped behind the clock (at most {c.get('behind_max_s', 0.0):.3f} s)"
             if behind else "no frame stamped behind the clock"]
    if jitter:
        parts.append(f"{jitter} of them by less than a tick (used, clock unchanged)")
    if c.get("joined"):
        parts.append(f"{int(c['joined'])} jump(s) back of a tick or more kept to by the frames after: new segment(s) "
                     f"joined on without a gap ({c.get('joined_s', 0.0):.3f} s taken out), ticked through, nothing dropped")
    if c.get("ignored"):
        parts.append(f"{int(c['ignored'])} jump(s) contradicted by the frames after: corrupt stamps, "
                     f"{int(c.get('ignored_frames', 0))} frame(s) ignored for the clock (data used)")
    if c.get("ahead"):
        parts.append(f"{int(c['ahead'])} jump(s) ahead beyond max_catchup_s kept to by the frames after")
    if c.get("gaps"):
        parts.append(f"{int(c['gaps'])} gap(s) bridged by cooling the state")
    if c.get("judging"):
        parts.append(f"{int(c['judging'])} frame(s) at the end after a jump not yet judged (not ticked)")
    return "frame clock: " + "; ".join(parts)


def voltage_line(counts: Mapping[str, int] | None) -> str:
    """One line of what became of the voltage input's estimates of the magnet, tick by tick."""
    if counts is None:
        return "voltage input: off (no flux.calibration: no voltage fused)"
    refused = {k: v for k, v in counts.items() if k != "used" and v}
    why = ", ".join(f"{k} {v}" for k, v in refused.items())
    return (f"voltage input: {counts.get('used', 0)} tick(s) fused into the magnet, "
            f"{sum(refused.values())} not" + (f" ({why})" if why else ""))


def format_summary(s: dict[str, Any]) -> str:
    """Human-readable lines of :func:`replay_summary`."""
    why = ", ".join(f"{k} {v}" for k, v in s["frames_dropped"].items() if v)
    lines = [f"{s['log']}: {s['frames']} frames, {s['ticks']} ticks of model {s['model']}; "
             f"lost {s['frames_lost']}, dropped {sum(s['frames_dropped'].values())}" + (f" ({why})" if why else "")
             + f", malformed lines {s['malformed_lines']}",
             f"adaptations: {s['adaptations']['accepted']} accepted of {s['adaptations']['decisions']} decisions"]
    if "frame_clock" in s:
        lines.append(clock_line(s["frame_clock"]))
    if "voltage_input" in s:
        lines.append(voltage_line(s["voltage_input"]))
    if s.get("max_estimate_c"):
        lines.append("peak estimates: " + ", ".join(f"{k} {v:.1f} °C" for k, v in s["max_estimate_c"].items())
                     + f"; lowest current limit {s['min_current_limit_a']:.1f} A")
    elif "max_estimate_c" in s:
        lines.append(f"no estimate: the observer never started (no usable sensor reading; see the frames dropped); "
                     f"lowest current limit {s['min_current_limit_a']:.1f} A")
    lines.append("parameters: " + ", ".join(f"{k}={v:.4g}" for k, v in s["parameters"].items()))
    return "\n".join(lines)
