"""The replay figure: per sensor, measured against predicted against the observer's 95 % band;
speed and current below; adaptation decisions marked on every panel."""
from __future__ import annotations

import os
from collections.abc import Mapping, Sequence

import numpy as np

#: Figure width, in; each panel's height, in.
WIDTH_IN, PANEL_IN = 11.0, 2.4


def replay_figure(path: str | os.PathLike[str], title: str, t_s: np.ndarray, sensors: Mapping[str, Mapping[str, np.ndarray]],
                  speed_rpm: np.ndarray | None, current_a: np.ndarray | None,
                  decisions: Sequence[tuple[float, bool]] = ()) -> None:
    """Write the replay figure.

    Parameters
    ----------
    path : path-like
        Image file; its suffix picks the format (``.png``, ``.svg``, ``.pdf``).
    title : str
    t_s : ndarray (N,)
        Sample times, s (shown in hours when the run is longer than two hours, else minutes).
    sensors : mapping
        Per sensor: ``measured``, ``predicted``, ``observer``, ``band_low``, ``band_high`` (N,), degC.
    speed_rpm, current_a : ndarray (N,) or None
        The operating point drawn below (omitted when the model has no such input).
    decisions : sequence of (t_s, accepted)
        Triggered adaptation decisions: promoted challengers solid green, the rest dotted grey.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    hours = t_s[-1] - t_s[0] > 2 * 3600.0
    scale, unit = (3600.0, "h") if hours else (60.0, "min")
    x = (t_s - t_s[0]) / scale
    n = len(sensors) + 1
    fig, axes = plt.subplots(n, 1, sharex=True, figsize=(WIDTH_IN, PANEL_IN * n), squeeze=False,
                             gridspec_kw={"height_ratios": [3] * (n - 1) + [2]})
    axes = axes[:, 0]
    for ax, (name, s) in zip(axes, sensors.items()):
        # the readings underneath, so that on a long run the two model lines stay visible on them
        ax.plot(x, s["measured"], color="0.45", ls="none", marker=".", ms=1.5, alpha=0.6, label="measured")
        ax.fill_between(x, s["band_low"], s["band_high"], color="tab:orange", alpha=0.3, lw=0,
                        label="observer 95 % band")
        ax.plot(x, s["observer"], color="tab:orange", lw=1.0, label="observer")
        ax.plot(x, s["predicted"], color="tab:blue", lw=1.0, label="predicted")
        ax.set_ylabel(f"{name} (°C)")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper left", ncol=4, fontsize=8)
    ax = axes[-1]
    if speed_rpm is not None:
        ax.plot(x, speed_rpm, color="tab:green", lw=1.0, label="speed")
        ax.set_ylabel("speed (rpm)", color="tab:green")
    if current_a is not None:
        ax2 = ax.twinx()
        ax2.plot(x, current_a, color="tab:red", lw=1.0, label="current")
        ax2.set_ylabel("current (A rms)", color="tab:red")
    ax.grid(alpha=0.3)
    ax.set_xlabel(f"time ({unit})")
    for t, accepted in decisions:
        xd = (t - t_s[0]) / scale
        for a in axes:
            a.axvline(xd, color="tab:green" if accepted else "grey", lw=1.0 if accepted else 0.6,
                      ls="-" if accepted else ":", alpha=0.8)
    if decisions:
        promoted = sum(1 for _, a in decisions if a)
        title += f" — {len(decisions)} adaptation decisions ({promoted} promoted: green lines; others dotted)"
    axes[0].set_title(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
