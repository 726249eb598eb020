"""A :class:`~.snapshot.Snapshot` as a screen of text (``thermal-edge monitor``)."""
from __future__ import annotations

import math
import time

from ..bus.frames import TE_LIMITS
from .snapshot import Snapshot

__all__ = ["render"]


def _f(x: float | None, fmt: str = "6.1f") -> str:
    if x is None or not math.isfinite(x):
        return "inf" if x == math.inf else "--"
    return format(x, fmt)


def _bar(value: float, lo: float, hi: float, width: int = 24) -> str:
    """How far ``value`` lies from ``lo`` to ``hi``, as a bar of ``width`` characters."""
    if not (math.isfinite(value) and math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return ""
    k = int(round(width * min(1.0, max(0.0, (value - lo) / (hi - lo)))))
    return "[" + "#" * k + "." * (width - k) + "]"


def render(snap: Snapshot, now: float | None = None) -> str:
    """Text of one screen: limits and reason, limited nodes with bands, forecast, model, inputs."""
    stamp = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(now if now is not None else time.time()))
    lines = [f"thermal-edge monitor  {snap.source}  {stamp}", ""]
    lines.append(f"state {snap.state:10s} limit {_f(snap.current_limit_a)} A {_f(snap.torque_limit_nm)} Nm"
                 f"   reason {snap.reason}")
    lines.append("")
    if snap.nodes:
        lines.append("node          estimate  upper(95%)   warn    max")
        for n in snap.nodes:
            lines.append(f"{n.name:12s} {_f(n.estimate_c, '8.1f')}  {_f(n.upper_c, '9.1f')}  {_f(n.warn_c)} {_f(n.max_c)}"
                         f"  {_bar(n.upper_c, 20.0, n.max_c)}")
        lines.append("")
    to_limit = ("not within the horizon" if snap.time_to_limit_s == math.inf
                else f"{_f(snap.time_to_limit_s, '.0f')} s")
    lines.append(f"look-ahead {_f(snap.lookahead_a)} A over {_f(snap.horizon_s, '.0f')} s;"
                 f" time to limit at this load {to_limit}")
    if snap.flux_used is not None:
        refused = sum(snap.flux_refused.values())
        why = ", ".join(f"{k} {v}" for k, v in sorted(snap.flux_refused.items()) if v)
        fused = (f"; last fused magnet {_f(snap.flux_magnet_c, '.1f')} °C, σ {_f(snap.flux_magnet_sigma_k, '.1f')} K"
                 if math.isfinite(snap.flux_magnet_c) else "; none fused yet")
        lines.append(f"voltages: used {snap.flux_used} ticks, refused {refused}" + (f" ({why})" if why else "") + fused)
    adapt = []
    if snap.adapt_runs is not None:
        adapt.append(f"runs {snap.adapt_runs}")
    if snap.adapt_accepted is not None:
        adapt.append(f"accepted {snap.adapt_accepted}")
    if snap.adapt_rejected is not None:
        adapt.append(f"rolled back {snap.adapt_rejected}")
    if snap.param_version is not None:
        adapt.append(f"parameter version {snap.param_version}")
    lines.append(f"prediction error {_f(snap.pred_err_rms_k, '.2f')} K rms   adaptation: {', '.join(adapt) or '--'}")
    if snap.adapt_status or snap.adapt_refusal:
        status = snap.adapt_status.replace("_", " ") or "--"
        refusal = ""
        if snap.adapt_refusal:
            ago = snap.tick_t - snap.adapt_refusal_t
            refusal = f"   last refusal: {snap.adapt_refusal}" + (f" ({ago:.0f} s ago)" if math.isfinite(ago) else "")
        lines.append(f"adaptation status: {status}{refusal}")
    if snap.sensors:
        lines.append("")
        lines.append("sensor          reading  pred-meas   age s  fault")
        for s in snap.sensors:
            lines.append(f"{s.name:14s} {_f(s.measured_c, '8.1f')}  {_f(s.error_k, '9.2f')}  {_f(s.age_s, '6.1f')}  {s.fault}")
    if snap.frame_ages:
        lines.append("")
        lines.append("frame               last seen s")
        for name, age in snap.frame_ages.items():
            lines.append(f"{name:18s} {age:11.2f}{'  STALE' if name in snap.stale else ''}")
    lines.append("")
    if snap.unheard:
        lines.append(f"never heard: {', '.join(snap.unheard)}")
        if TE_LIMITS in snap.unheard:
            lines.append("no TE_Limits heard: the inverter is on its own protection")
    if snap.bus_silent_s > 0.0:
        lines.append(f"BUS SILENT for {snap.bus_silent_s:.1f} s: TE_Limits carries the safe limit")
    lines.append(f"stale inputs: {', '.join(snap.stale) if snap.stale else 'none'}"
                 + (f"   frames dropped: {snap.dropped}" if snap.dropped is not None else ""))
    return "\n".join(lines)
