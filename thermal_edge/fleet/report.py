"""The fleet's Markdown report, with plots when matplotlib is installed (the ``report`` extra).

Plots go to ``<report stem>-plots/`` next to the report and are linked relatively:

* calibrate / screen: per parameter, every machine's value (relative to the design's) with its
  ±1σ bar, the fleet's median and robust band, outliers marked and named;
* screen: per outlier, its ``z`` over all parameters against the threshold;
* evaluate: per sensor, the distribution of the machines' RMS errors.
"""
from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..text_table import table
from .screen import Outlier, Spread


def _md_table(headers: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    def fmt(v: object) -> str:
        return f"{v:.4g}" if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(fmt(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)


def _pyplot() -> Any:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    return plt


def spread_rows(spreads: Sequence[Spread]) -> list[list[object]]:
    """Rows of the parameter-distribution table (also printed by the command)."""
    return [[s.parameter, s.nominal, s.median, 100 * s.spread_rel, s.p05, s.p95, f"{s.identifiable}/{s.machines}"]
            for s in spreads]


SPREAD_HEADERS = ["parameter", "design", "fleet median", "robust spread %", "p5", "p95", "identifiable"]
SENSOR_HEADERS = ["sensor", "machines", "median RMS K", "p95 RMS K", "worst RMS K", "worst machine"]
OUTLIER_HEADERS = ["machine", "parameter", "value", "fleet median", "ratio", "z", "own σ %"]


def outlier_rows(outliers: Sequence[Outlier]) -> list[list[object]]:
    """Rows of the outlier table (also printed by the command)."""
    return [[o.machine, o.parameter, o.value, o.fleet_median, o.ratio, o.z, 100 * o.rel_std] for o in outliers]


def errors_section(rows: Sequence[dict[str, Any]]) -> list[str]:
    errs = [r for r in rows if r["kind"] == "error"]
    if not errs:
        return []
    return ["## Machines not processed", "",
            _md_table(["machine", "error", "message", "runs"],
                      [[r["machine"], r["name"], r["message"], r["runs"]] for r in errs]), ""]


def _plot_parameter(plt: Any, rows: Sequence[dict[str, Any]], sp: Spread, threshold: float, path: Path) -> None:
    group = sorted((r for r in rows if r["kind"] == "parameter" and r["name"] == sp.parameter), key=lambda r: r["machine"])
    ref = sp.nominal if sp.nominal and math.isfinite(sp.nominal) else sp.median
    y = np.array([r["value"] / ref for r in group])
    sd = np.array([r["rel_std"] if r["rel_std"] is not None else np.nan for r in group])
    out = np.array([bool(r["outlier"]) for r in group])
    x = np.arange(len(group))
    fig, ax = plt.subplots(figsize=(8, 3.2))
    ax.errorbar(x[~out], y[~out], yerr=y[~out] * np.minimum(sd[~out], 1.0), fmt=".", ms=3, lw=0.5, color="0.4",
                label="machine ±1σ")
    med = sp.median / ref
    ax.axhline(med, color="C0", lw=1, label="fleet median")
    if sp.spread_rel > 0 and threshold > 0:
        ax.axhspan(med * math.exp(-threshold * sp.spread_rel), med * math.exp(threshold * sp.spread_rel), color="C0",
                   alpha=0.1, label=f"|z| ≤ {threshold:g} (own σ = 0)")
    if out.any():
        ax.errorbar(x[out], y[out], yerr=y[out] * np.minimum(sd[out], 1.0), fmt="o", color="C3", label="outlier")
        for xi, yi, r in zip(x[out], y[out], [g for g, o in zip(group, out) if o]):
            ax.annotate(r["machine"], (xi, yi), textcoords="offset points", xytext=(4, 4), fontsize=7, color="C3")
    ax.set_yscale("log")
    ax.set_xlabel("machine")
    ax.set_ylabel(f"{sp.parameter} / design")
    ax.set_title(f"{sp.parameter}: fleet of {sp.machines}")
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _plot_outlier(plt: Any, rows: Sequence[dict[str, Any]], o: Outlier, threshold: float, path: Path) -> None:
    mine = [r for r in rows if r["kind"] == "parameter" and r["machine"] == o.machine and r["z"] is not None]
    fig, ax = plt.subplots(figsize=(6, 2.8))
    z = [r["z"] for r in mine]
    ax.bar([r["name"] for r in mine], z, color=["C3" if abs(v) > threshold else "0.6" for v in z])
    for t in (-threshold, threshold):
        ax.axhline(t, color="C3", lw=0.8, ls="--")
    ax.set_ylabel("z")
    ax.set_title(f"{o.machine}: {o.parameter} × {o.ratio:.2f} of the fleet median (z = {o.z:.1f})")
    ax.tick_params(axis="x", rotation=45, labelsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _plot_sensor(plt: Any, rows: Sequence[dict[str, Any]], sensor: str, path: Path) -> None:
    rms = [r["rms_k"] for r in rows if r["kind"] == "sensor" and r["name"] == sensor]
    fig, ax = plt.subplots(figsize=(6, 2.8))
    ax.hist(rms, bins=min(40, max(5, len(rms) // 4)), color="0.5")
    ax.set_xlabel(f"{sensor}: RMS error, K")
    ax.set_ylabel("machines")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def write_report(path: str | os.PathLike[str], title: str, rows: Sequence[dict[str, Any]], intro: Sequence[str] = (),
                 spreads: Sequence[Spread] = (), outliers: Sequence[Outlier] | None = None,
                 threshold: float = math.nan) -> Path:
    """Write the Markdown report (and its plots); returns its path.

    Parameters
    ----------
    rows : sequence of dict
        The result table's rows.
    intro : sequence of str
        Lines under the title (what was run, on what).
    spreads, outliers : optional
        The screen's results (``outliers=None``: no screen was run).
    threshold : float
        The screen's ``|z|`` threshold (for the plots' bands).
    """
    path = Path(path)
    plots = path.with_name(path.stem + "-plots")
    plt = _pyplot()
    if plt is not None:
        plots.mkdir(parents=True, exist_ok=True)
    rel = os.path.relpath(plots, path.parent)
    machines = sorted({r["machine"] for r in rows})
    lines = [f"# {title}", "", *intro, "", f"{len(machines)} machines."]
    if plt is None:
        lines += ["", "(no plots: matplotlib is not installed; pip install thermal-edge[report])"]
    lines.append("")
    if outliers is not None:
        th = f"{threshold:g}"
        lines += [f"## Outliers (|z| > {th})", "",
                  "z = (log θ − fleet median) / sqrt(robust spread² + the machine's own σ²), in log θ.", ""]
        lines += [_md_table(OUTLIER_HEADERS, outlier_rows(outliers)) if outliers else "No machine stands out.", ""]
        for o in outliers:
            if plt is not None:
                f = plots / f"outlier-{o.machine}.png"
                _plot_outlier(plt, rows, o, threshold, f)
                lines += [f"![{o.machine}]({rel}/{f.name})", ""]
    if spreads:
        lines += ["## Parameter distribution", "", _md_table(SPREAD_HEADERS, spread_rows(spreads)), ""]
        if plt is not None:
            for sp in spreads:
                f = plots / f"param-{sp.parameter}.png"
                _plot_parameter(plt, rows, sp, threshold if math.isfinite(threshold) else 0.0, f)
                lines += [f"![{sp.parameter}]({rel}/{f.name})", ""]
    sensors = list(dict.fromkeys(r["name"] for r in rows if r["kind"] == "sensor"))
    if sensors:
        lines += ["## Errors per sensor", "", _md_table(SENSOR_HEADERS, sensor_rows(rows)), ""]
        worst = sorted((r for r in rows if r["kind"] == "sensor"), key=lambda r: -r["rms_k"])[:10]
        lines += ["Worst machine-sensor pairs:", "",
                  _md_table(["machine", "sensor", "RMS K", "max |e| K"],
                            [[r["machine"], r["name"], r["rms_k"], r["max_abs_k"]] for r in worst]), ""]
        if plt is not None:
            for s in sensors:
                f = plots / f"sensor-{s}.png"
                _plot_sensor(plt, rows, s, f)
                lines += [f"![{s}]({rel}/{f.name})", ""]
    lines += errors_section(rows)
    path.write_text("\n".join(lines) + "\n")
    return path


def sensor_rows(rows: Sequence[dict[str, Any]]) -> list[list[object]]:
    """Per sensor: the distribution of the machines' RMS errors (also printed by the command)."""
    out = []
    for s in dict.fromkeys(r["name"] for r in rows if r["kind"] == "sensor"):
        g = [r for r in rows if r["kind"] == "sensor" and r["name"] == s]
        rms = np.array([r["rms_k"] for r in g])
        w = g[int(np.argmax(rms))]
        out.append([s, len(g), float(np.median(rms)), float(np.percentile(rms, 95)), float(rms.max()), w["machine"]])
    return out


def summary_text(rows: Sequence[dict[str, Any]], spreads: Sequence[Spread] = (),
                 outliers: Sequence[Outlier] | None = None) -> str:
    """The command's plain-text summary of the same tables."""
    parts = []
    if spreads:
        parts.append(table(SPREAD_HEADERS, spread_rows(spreads)))
    if any(r["kind"] == "sensor" for r in rows):
        parts.append(table(SENSOR_HEADERS, sensor_rows(rows)))
    if outliers is not None:
        parts.append(table(OUTLIER_HEADERS, outlier_rows(outliers)) if outliers else "no machine stands out")
    errs = [r for r in rows if r["kind"] == "error"]
    if errs:
        parts.append(f"{len(errs)} machine(s) not processed: " + "; ".join(f"{r['machine']}: {r['message']}" for r in errs))
    return "\n\n".join(parts)
