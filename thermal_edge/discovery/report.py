"""The discovery report: Markdown with PNG figures (matplotlib, imported here only: ``report`` extra)."""
from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

import numpy as np

from ..lptn import Role
from . import effects as E
from . import judge as J
from . import residuals as R
from . import yamlpatch
from .workflow import Discovery

if TYPE_CHECKING:  # matplotlib is imported where a figure is drawn (the ``report`` extra)
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure


def _f(x: float, nd: int = 3) -> str:
    return "–" if x is None or not np.isfinite(x) else f"{x:.{nd}f}"


def _pct(x: float) -> str:
    return "–" if x is None or not np.isfinite(x) else f"{x:+.0%}"


def _table(head: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    out = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    out += ["| " + " | ".join(str(c).replace("|", "\\|") for c in r) + " |" for r in rows]
    return "\n".join(out)


def _effect_of(label: str) -> E.Effect:
    return E.get(label.split(":", 1)[0])


def explained_variable(disc: Discovery) -> str:
    """The operating variable the named effect follows (or the strongest driver when none)."""
    if disc.named is not None:
        return _effect_of(disc.named.fit.label).explains
    worst = disc.rounds[0].analysis.worst()
    return worst.drivers[0][0] if worst.drivers else "time"


def _xvar(an: R.Analysis, sensor: str, var: str) -> np.ndarray | None:
    v = an.vars.get(sensor, {})
    return v.get(var)


def _binned(ax: Axes, x: np.ndarray, e: np.ndarray, color: str, bins: int = 12) -> None:
    """Mean residual in quantile bins of ``x`` (the trend the scatter hides)."""
    ok = np.isfinite(x) & np.isfinite(e)
    if ok.sum() < 2 * bins:
        return
    edges = np.unique(np.quantile(x[ok], np.linspace(0, 1, bins + 1)))
    if len(edges) < 2:
        return
    idx = np.clip(np.searchsorted(edges, x[ok], side="right") - 1, 0, len(edges) - 2)
    xs = [x[ok][idx == b].mean() for b in range(len(edges) - 1) if (idx == b).any()]
    ys = [e[ok][idx == b].mean() for b in range(len(edges) - 1) if (idx == b).any()]
    ax.plot(xs, ys, "-o", color=color, ms=3, lw=1.5)


def figures(disc: Discovery, out: Path) -> dict[str, str]:
    """Write the PNG figures; returns {kind: file name}."""
    import matplotlib.pyplot as plt

    files = {}
    for kind, (name, fig) in build_figures(disc).items():
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        files[kind] = name
    return files


def build_figures(disc: Discovery) -> dict[str, tuple[str, Any]]:
    """The report's figures, unsaved: {kind: (file name, matplotlib figure)}."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figs: dict[str, tuple[str, Any]] = {}
    data = disc.data
    run = data.run
    t_h = (run.t - run.t[0]) / 3600.0
    before = disc.rounds[0].analysis
    after = disc.final_analysis or before
    ns = len(data.sensors)
    step = max(1, len(run) // 4000)
    name_after = " + ".join(r.fit.label for r in disc.added) or "refitted (no effect added)"

    fig, axes = plt.subplots(ns + 1, 1, figsize=(9, 2.0 * ns + 2.2), sharex=True, squeeze=False,
                             gridspec_kw={"height_ratios": [2] * ns + [1.4]})
    for j, s in enumerate(data.sensors):
        ax = axes[j, 0]
        ax.plot(t_h[::step], before.residual[::step, j], lw=0.8, color="tab:red", label="refitted model")
        if disc.added:
            ax.plot(t_h[::step], after.residual[::step, j], lw=0.8, color="tab:blue", label=f"with {name_after}")
        ax.axvline(t_h[data.split], color="k", ls="--", lw=0.8)
        ax.axhline(0.0, color="grey", lw=0.5)
        ax.set_ylabel(f"{s}\nresidual (K)")
        ax.grid(alpha=0.3)
    axes[0, 0].set_title("prediction − reading (open loop from the first sample); dashed: start of the held-out part", fontsize=9)
    axes[0, 0].legend(fontsize=8, loc="best")
    _operating_point(axes[ns, 0], disc, t_h, step)
    axes[ns, 0].axvline(t_h[data.split], color="k", ls="--", lw=0.8)
    fig.tight_layout()
    figs["time"] = ("residual_time.png", fig)

    var = explained_variable(disc)
    fig, axes = plt.subplots(2, ns, figsize=(3.6 * ns + 0.6, 4.4), squeeze=False, sharex="col",
                             gridspec_kw={"height_ratios": [3, 1]})
    for j, s in enumerate(data.sensors):
        ax, low = axes[0, j], axes[1, j]
        x = _xvar(before, s, var)
        if x is None:
            ax.set_visible(False)
            low.set_visible(False)
            continue
        ax.scatter(x[::step], before.residual[::step, j], s=2, alpha=0.25, color="tab:red", label="refitted model")
        _binned(ax, x, before.residual[:, j], "tab:red")
        if disc.added:
            ax.scatter(x[::step], after.residual[::step, j], s=2, alpha=0.25, color="tab:blue", label=f"with {name_after}")
            _binned(ax, x, after.residual[:, j], "tab:blue")
        ax.axhline(0.0, color="grey", lw=0.5)
        ax.set_ylabel("residual (K)")
        ax.set_title(s, fontsize=9)
        ax.grid(alpha=0.3)
        if var == "time":  # against time, the operating point itself is what lies beneath
            _operating_point(low, disc, t_h, step)
            continue
        # where the run was: the share of the training and of the held-out samples along the variable
        ok = np.isfinite(x)
        if ok.any():
            edges = np.histogram_bin_edges(x[ok], bins=30)
            for part, color, label in ((slice(0, data.split), "tab:gray", "training"),
                                       (slice(data.split, None), "k", "held-out")):
                xp = x[part][np.isfinite(x[part])]
                if len(xp):
                    low.hist(xp, bins=edges, weights=np.full(len(xp), 1.0 / len(xp)), histtype="step", color=color,
                             label=label)
        low.set_xlabel(R.label(var))
        low.set_ylabel("share of\nsamples", fontsize=8)
        low.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, markerscale=4, loc="best")
    if var != "time":
        axes[1, 0].legend(fontsize=7, loc="best")
    fig.tight_layout()
    figs["var"] = (f"residual_vs_{var.replace(':', '_')}.png", fig)

    fig = _temperature_figure(disc, plt, t_h, step)
    figs["temperature"] = ("temperature_time.png", fig)

    first = disc.rounds[0]
    win = first.winner.fit.label if first.winner else None
    ru = first.runner_up.fit.label if first.runner_up else None
    sc = [s for s in first.scores if s.fraction > 0][:12]
    labels = [s.cand.label for s in sc]
    for lab in (win, ru):  # winner and runner-up are shown even when the screen, not the test, found them
        if lab and lab not in labels:
            hit = next((s for s in first.scores if s.cand.label == lab), None)
            if hit is None:
                hit = next((s for s in first.screen if s.cand.label == lab), sc[0] if sc else None)
            if hit is not None:  # a label found nowhere and nothing else to show: no bar
                sc.append(hit)
                labels.append(lab)
    if sc:
        fig, ax = plt.subplots(figsize=(9, 0.34 * len(sc) + 1.4))
        colors = ["tab:green" if lab == win else "tab:orange" if lab == ru else "tab:gray" for lab in labels]
        ax.barh(labels[::-1], [s.fraction for s in sc][::-1], color=colors[::-1])
        for lab, score in zip(labels, sc):
            tag = "winner" if lab == win else ("runner-up" if win else "nearest (not accepted)") if lab == ru else ""
            if tag:
                ax.annotate(f" {tag}", (score.fraction, labels[::-1].index(lab)), va="center", fontsize=8)
        ax.set_xlabel("score test: share of the training residual\na joint step (effect + adaptable parameters) would remove")
        ax.set_xlim(0, max(1e-3, max(s.fraction for s in sc)) * 1.25)
        ax.set_title("candidates (green: named by the held-out fits; orange: " + ("runner-up)" if win else
                     "the nearest by held-out gap, not accepted)"), fontsize=9)
        fig.tight_layout()
        figs["scores"] = ("scores.png", fig)
    if first.comparison is not None and first.evidence:
        fig, axes = plt.subplots(1, len(first.evidence), figsize=(3.3 * len(first.evidence) + 0.6, 3.2), squeeze=False)
        for ax, ev in zip(axes[0], first.evidence):
            ax.plot(ev.centers, ev.a, "-o", ms=3, color="tab:green", label=first.comparison.a)
            ax.plot(ev.centers, ev.b, "-s", ms=3, color="tab:orange", label=first.comparison.b)
            ax.axhline(0.0, color="grey", lw=0.5)
            ax.set_xlabel(ev.variable)
            ax.grid(alpha=0.3)
        axes[0, 0].set_ylabel(f"predicted residual of\n{first.evidence[0].sensor} (K)")
        axes[0, 0].legend(fontsize=7, loc="best")
        fig.suptitle("what each effect says the refitted model gets wrong (refit − fit, binned means)", fontsize=9)
        fig.tight_layout()
        figs["evidence"] = ("winner_vs_runner_up.png", fig)
    return figs


def _temperature_figure(disc: Discovery, plt: ModuleType, t_h: np.ndarray, step: int) -> Figure:
    """Measured against predicted temperature per sensor (refitted model, and with the effects
    added), the operating point (speed, current, ambient) below."""
    data = disc.data
    run = data.run
    ns = len(data.sensors)
    before, after = disc.rounds[0].base, disc.final
    fig, axes = plt.subplots(ns + 1, 1, figsize=(9, 1.9 * ns + 2.4), sharex=True, squeeze=False,
                             gridspec_kw={"height_ratios": [2] * ns + [1.4]})
    name_after = " + ".join(r.fit.label for r in disc.added)
    for j, s in enumerate(data.sensors):
        ax = axes[j, 0]
        ax.plot(t_h[::step], run.columns[s][::step], lw=1.4, color="k", label="measured")
        assert before.traj_T is not None
        ax.plot(t_h[::step], before.traj_T[::step, j], lw=0.9, color="tab:red", label="refitted model (before)")
        if disc.added and after.traj_T is not None:
            ax.plot(t_h[::step], after.traj_T[::step, j], lw=0.9, color="tab:blue", ls="--", label=f"with {name_after} (after)")
        ax.axvline(t_h[data.split], color="k", ls=":", lw=0.8)
        ax.set_ylabel(f"{s}\n(°C)")
        ax.grid(alpha=0.3)
    axes[0, 0].set_title("measured and predicted temperature (open loop from the first sample); "
                         "dotted: start of the held-out part", fontsize=9)
    axes[0, 0].legend(fontsize=7, loc="best")
    _operating_point(axes[ns, 0], disc, t_h, step)
    axes[ns, 0].axvline(t_h[data.split], color="k", ls=":", lw=0.8)
    fig.tight_layout()
    return fig


def _operating_point(ax: Axes, disc: Discovery, t_h: np.ndarray, step: int) -> None:
    """The operating point under a time plot: speed (left axis), current (right axis), the
    ambient range as a note; the x-label is the time axis's."""
    data = disc.data
    speed, current, amb = (data.column(r) for r in (Role.SPEED, Role.CURRENT, Role.AMBIENT))
    if speed is not None:
        ax.plot(t_h[::step], np.abs(speed[::step]), lw=0.8, color="tab:purple")
        ax.set_ylabel("speed (rpm)", color="tab:purple")
    if current is not None:
        ax2 = ax.twinx()
        ax2.plot(t_h[::step], current[::step], lw=0.8, color="tab:olive")
        ax2.set_ylabel("current (A)", color="tab:olive")
    if amb is not None:
        ax.text(0.01, 0.9, f"ambient {np.nanmin(amb):.0f}–{np.nanmax(amb):.0f} °C", transform=ax.transAxes,
                fontsize=7, va="top")
    ax.set_xlabel("time since start (h)")
    ax.grid(alpha=0.3)


def regime_shift(before: R.SensorResiduals, after: R.SensorResiduals) -> list[tuple[str, str, float, float]]:
    """(axis, regime, rms before, rms after), largest drop first."""
    b = {(a, r): rms for a, r, _, _, rms in before.regimes}
    out = [(a, r, b[(a, r)], rms) for a, r, _, _, rms in after.regimes if (a, r) in b]
    return sorted(out, key=lambda x: -(x[2] - x[3]))


NO_GAP_TEXT = "the noise floor × 2 + the smallest accepted gain"


def markdown(disc: Discovery, files: dict[str, str], commands: Sequence[str] = ()) -> str:
    data = disc.data
    first = disc.rounds[0]
    lines: list[str] = []
    add = lines.append
    add(f"# Model-gap discovery: `{disc.model_name}` on `{os.path.basename(disc.source)}`")
    add("")
    g = disc.gap
    if disc.named:
        add(f"**Verdict: missing effect `{disc.named.fit.label}`** — "
            f"{_effect_of(disc.named.fit.label).doc}. Held-out gap {disc.gap_before:.3f} K → {disc.gap_after:.3f} K "
            f"({1 - disc.gap_after / disc.gap_before:.0%} smaller).")
        if disc.ambiguous and disc.runner_up is not None:
            c = first.comparison
            assert c is not None
            more = [r.fit.label for r in disc.confusable[1:]]
            also = f" So do {', '.join(f'`{m}`' for m in more)}." if more else ""
            add("")
            add(f"**Not sure between these:** `{c.b}` explains the residual nearly as well (held-out gap "
                f"{c.gap_b:.3f} K against {c.gap_a:.3f} K, difference {c.gap_b - c.gap_a:+.4f} ± {c.se_diff:.4f} K; "
                f"it achieves {c.share:.0%} of the winner's reduction of the gap).{also} This run cannot separate them; "
                + _separating_sentence(disc)
                + "See section 6.")
        if len(disc.added) > 1:
            add(f"Further effects added in later rounds: {', '.join(r.fit.label for r in disc.added[1:])}.")
        if g is not None and g.status == "partly explained":
            add("")
            add(f"A gap of {g.gap_k:.3f} K remains ({g.ratio:.0f}× the noise floor {g.noise_k:.3f} K) that the "
                "catalogue does not explain (section 7).")
    elif g is not None and g.status == "unexplained":
        add(f"**Verdict: a gap the catalogue does not explain.** The refitted model misses the held-out data by "
            f"{g.gap_k:.3f} K, {g.ratio:.0f}× the sensor noise floor ({g.noise_k:.3f} K), and no catalogue effect "
            f"lowers it by the required {100 * disc.options.min_improvement:.0f} % and {disc.options.min_gain_k:.2f} K "
            "(section 7: where and when, nearest candidates).")
    if disc.unexpressed and disc.signature is not None:
        add("")
        add(f"**Perhaps none of these:** {', '.join(f'`{n.effect.name}`' for n in disc.unexpressed)}, which this "
            f"model cannot express ({disc.unexpressed[0].reason}), would fit the residual, which "
            f"{disc.signature.describe()} (section 8).")
    if not disc.named and not (g is not None and g.status == "unexplained"):
        add(f"**Verdict: no gap.** The refitted model predicts the held-out data to {disc.gap_before:.3f} K, within "
            f"the sensor noise floor ({disc.noise_k:.3f} K; no gap below {NO_GAP_TEXT}); no missing effect found.")
    add("")
    add(_table(["", "value"], [
        ["run", f"{len(data.run)} samples at {data.dt:g} s ({(data.run.t[-1] - data.run.t[0]) / 3600:.2f} h)"],
        ["sensors", ", ".join(data.sensors)],
        ["training / held-out",
         f"first {data.split} samples (fitted at {data.dt * data.factor:g} s steps) / last {len(data.run) - data.split}"],
        ["reference speed, current", f"{data.refs['n_ref']:g} rpm, {data.refs['i_ref']:g} A"],
        ["held-out gap, nominal parameters", f"{disc.nominal.gap:.3f} K"],
        ["held-out gap, refitted (before)", f"{disc.gap_before:.3f} K"],
        ["held-out gap, with the effect(s) (after)", f"{disc.gap_after:.3f} K"],
        ["sensor noise floor (from the data)", f"{disc.noise_k:.3f} K"],
        ["gap above the noise floor, before → after",
         f"{J.above_noise(disc.gap_before, disc.noise_k):.3f} K → {J.above_noise(disc.gap_after, disc.noise_k):.3f} K"],
        ["wall time", f"{disc.wall_s:.1f} s"],
    ]))
    add("")
    add("The gap is the RMS over the sensors (root of the mean per-sensor MSE) of the open-loop prediction "
        "on the held-out part of the run; the model runs from the first sample through the whole run.")
    add("")
    add("## 1. Refit")
    add("")
    names = list(first.base.names)
    if names:
        nom = disc.nominal.values(names)
        ref = first.base.values(names)
        changed = sorted(((n, nom[n], ref[n]) for n in names),
                         key=lambda t: -abs(math.log(t[2] / t[1])) if t[1] > 0 and t[2] > 0 else 0)
        add(f"The model's {len(names)} adaptable parameters were fitted to the training part (Gauss-Newton in "
            "log-parameters within their bounds), so that what remains is structural. Largest changes:")
        add("")
        add(_table(["parameter", "nominal", "refitted", "ratio"],
                   [[n, f"{a:.4g}", f"{b:.4g}", f"{b / a:.2f}"] for n, a, b in changed[:8]]))
    add("")
    add("## 2. Residual analysis (refitted model)")
    add("")
    rows = []
    for s in first.analysis.sensors:
        drv = "; ".join(f"{R.label(v)} η²={a:.2f} (r={r:+.2f})" for v, a, r in s.drivers[:3])
        rows.append([s.sensor, _f(s.rms_train), _f(s.rms_heldout), _f(s.bias), drv])
    add(_table(["sensor", "RMS train K", "RMS held-out K", "bias K", "strongest operating variables"], rows))
    add("")
    add("Residual RMS (K) by operating regime:")
    add("")
    regs = [(a, r) for a, r, *_ in first.analysis.sensors[0].regimes]
    head = ["regime", "share"] + [s.sensor for s in first.analysis.sensors]
    rows = []
    for a, r in regs:
        share = next(sh for aa, rr, sh, _, _ in first.analysis.sensors[0].regimes if (aa, rr) == (a, r))
        vals = []
        for s in first.analysis.sensors:
            m = {(aa, rr): (b, rms) for aa, rr, _, b, rms in s.regimes}
            b, rms = m.get((a, r), (float("nan"), float("nan")))
            vals.append(f"{_f(rms, 2)} (bias {_f(b, 2)})")
        rows.append([f"{a}: {r}", f"{share:.0%}"] + vals)
    add(_table(head, rows))
    add("")
    worst = first.analysis.worst()
    add(f"The gap is carried mostly by **{worst.sensor}** (held-out RMS {worst.rms_heldout:.2f} K); "
        f"its residual follows {R.label(worst.drivers[0][0])} most (η² = {worst.drivers[0][1]:.2f}).")
    add("")
    if "temperature" in files:
        add(f"![measured and predicted temperature, operating point below]({files['temperature']})")
        add("")
    if "time" in files:
        add(f"![residual over time]({files['time']})")
        add("")
    add("## 3. Candidates: score test")
    add("")
    add(f"{len(first.scores)} candidates (catalogue effects on every applicable target). Score test at zero effect "
        "with the refitted parameters: the share of the training residual a joint Gauss-Newton step "
        "(effect + adaptable parameters) would remove. Effects act one way (they add a loss, a conductance, a lag) "
        "except the copper temperature factor, which may also fall (AC copper loss).")
    add("")
    add(_table(["#", "candidate", "score", "step (zero effect + GN step)", "note"], [
        [i + 1, f"`{s.cand.label}`", f"{s.fraction:.3f}", ", ".join(f"{k}={v:.4g}" for k, v in s.step.items()), s.note]
        for i, s in enumerate(first.scores[:12])
    ]))
    add("")
    zero = sum(1 for s in first.scores if s.score <= 0)
    add(f"{zero} candidates scored zero (wrong sign, or indistinguishable from a change of the adaptable parameters).")
    add("")
    add("Screen against the residual at the nominal parameters (catches effects a refit mimics): " +
        ", ".join(f"`{s.cand.label}` {s.fraction:.3f}" for s in first.screen[:5]) + ".")
    add("")
    if "scores" in files:
        add(f"![scores]({files['scores']})")
        add("")
    add("## 4. Full fits, ranked on held-out data")
    add("")
    add(f"Each fit adds the candidate to the model and refits it with the adaptable parameters on the training part; "
        f"it is judged on the held-out part. Accepted: held-out gap at least {100 * disc.options.min_improvement:.0f} % "
        f"and {disc.options.min_gain_k:.2f} K smaller than the refitted model's (or its continued refit, the control), "
        f"or the gap above the noise floor (√(gap² − noise²)) at least {100 * disc.options.min_share_above_noise:.0f} % "
        f"and {disc.options.min_gain_k:.2f} K smaller, "
        f"and a lower BIC N·ln(MSE) + k·ln(N) (N = {first.n_eff:.0f} held-out samples on the fitting grid, "
        f"k the effect's parameters).")
    add("")
    for rd in disc.rounds:
        add(f"Round {rd.index} (reference gap {rd.reference_gap:.3f} K):")
        add("")
        add(_table(["candidate", "from", "held-out gap K", "improvement", "above noise", "ΔBIC", "fitted", "accepted"], [
            [f"`{x.fit.label}`", x.source, _f(x.fit.gap), _pct(x.improvement), _pct(x.improvement_above_noise),
             f"{x.delta_criterion:+.1f}",
             ", ".join(f"{k}={v:.4g}" for k, v in x.fit.values(x.fit.effect_params).items()),
             "**yes**" if x is rd.winner else ("yes" if x.accepted else "no")]
            for x in rd.ranked
        ]))
        add("")
    if disc.named:
        w = disc.named
        add("## 5. The named effect and its evidence")
        add("")
        eff = _effect_of(w.fit.label)
        after = disc.final_analysis
        add(f"**`{w.fit.label}`**: {eff.doc}. Explained variable: {R.label(eff.explains)}.")
        add("")
        if after is not None:
            rows = []
            for sb, sa in zip(first.analysis.sensors, after.sensors):
                eb = dict((v, a) for v, a, _ in sb.drivers).get(eff.explains, float("nan"))
                ea = dict((v, a) for v, a, _ in sa.drivers).get(eff.explains, float("nan"))
                share = 1 - (sa.rms_heldout / sb.rms_heldout) ** 2 if sb.rms_heldout > 0 else float("nan")
                rows.append([sb.sensor, _f(sb.rms_heldout), _f(sa.rms_heldout), _pct(-(1 - sa.rms_heldout / sb.rms_heldout)),
                             f"{share:.0%}", f"{_f(eb, 2)} → {_f(ea, 2)}"])
            add(_table(["sensor", "held-out RMS before K", "after K", "change", "share of MSE explained",
                        f"η² vs {R.label(eff.explains)}"], rows))
            add("")
            shifts = []
            for sb, sa in zip(first.analysis.sensors, after.sensors):
                top = regime_shift(sb, sa)[:2]
                shifts.append(f"{sb.sensor}: " + ", ".join(f"{r} ({a}) {x:.2f} → {y:.2f} K" for a, r, x, y in top))
            add("Conditions where the gap shrank most: " + "; ".join(shifts) + ".")
            add("")
        add(f"Over all sensors it explains {1 - (disc.gap_after / disc.gap_before) ** 2:.0%} of the held-out mean "
            f"squared error ({disc.gap_before:.3f} → {disc.gap_after:.3f} K RMS).")
        add("")
        add("The lines added to the model file (fitted values):")
        add("")
        add("```yaml")
        prev = disc.raw0
        for ranked in disc.added:
            add(f"# {ranked.fit.label}")
            add(yamlpatch.snippet(prev, ranked.fit.raw))
            prev = ranked.fit.raw
        add("```")
        add("")
        if disc.model_out:
            add(f"Augmented model: `{os.path.basename(disc.model_out)}` (the original file with these lines patched in).")
            add("")
        if "var" in files:
            add(f"![residual against {R.label(eff.explains)}]({files['var']})")
            add("")
    elif "var" in files:
        add(f"![residual against the strongest variable]({files['var']})")
        add("")
    _comparison_section(disc, files, add)
    _gap_section(disc, add)
    _signature_section(disc, add)
    if commands:
        add("## Reproduce")
        add("")
        add("```sh")
        lines.extend(commands)
        add("```")
        add("")
    return "\n".join(lines)


def _comparison_section(disc: Discovery, files: dict[str, str], add: Callable[[str], None]) -> None:
    rd = disc.rounds[0]
    c = rd.comparison
    if c is None:
        return
    add("## 6. Winner and runner-up")
    add("")
    state = ("**cannot be separated on this run**" if c.ambiguous else
             f"decided by held-out data from an operating region the training part lacks ({c.decided_by})"
             if c.decided_by else "separated by the held-out gap")
    add(f"Both explain the residual; {state}. Held-out gap with the standard error of the difference from "
        f"{J.N_BLOCKS} contiguous blocks of the held-out part (residuals are correlated over minutes):")
    add("")
    rows = [["held-out gap K", _f(c.gap_a), _f(c.gap_b)],
            ["difference (runner-up − winner) K", "", f"{c.gap_b - c.gap_a:+.4f} ± {c.se_diff:.4f} ({c.z:.1f} SE)"],
            ["share of the winner's gap reduction", "100%", f"{c.share:.0%}"]]
    if np.isfinite(c.novel_gap_a):
        rows.append(["held-out gap in the region the training lacks K", _f(c.novel_gap_a), _f(c.novel_gap_b)])
    add(_table(["", f"winner `{c.a}`", f"runner-up `{c.b}`"], rows))
    add("")
    if rd.evidence:
        add(f"What each predicts the refitted model gets wrong (its prediction minus the refit's, on "
            f"{rd.evidence[0].sensor}, binned means): where the two differ most along each operating variable.")
        add("")
        rows = []
        for ev in rd.evidence:
            x, d = ev.max_diff
            i = ev.centers.index(x) if ev.centers else 0
            rows.append([ev.variable, f"{x:.4g}", _f(ev.a[i]), _f(ev.b[i]), _f(d)])
        add(_table(["variable", "at", "winner K", "runner-up K", "|difference| K"], rows))
        add("")
    if rd.point is not None and not rd.point.sensors_separate(disc.noise_k):
        add(f"**Separating condition:** {_separating_sentence(disc)}")
        add("")
    elif rd.point is not None:
        p = rd.point
        add(f"**Separating condition:** {p.describe()} — the two fitted models differ most there at steady state "
            f"({p.sensor}: {p.t_a:.1f} °C with `{c.a}`, {p.t_b:.1f} °C with `{c.b}`, {p.diff:.1f} K apart); "
            + ("the run held such a point." if p.in_run else "the run never held it: a next test run should."))
        add("")
    if "evidence" in files:
        add(f"![winner and runner-up against speed, current, ambient, time]({files['evidence']})")
        add("")


def _signature_section(disc: Discovery, add: Callable[[str], None]) -> None:
    """The residual's signature beside each candidate's, and the effects the model cannot express."""
    sig = disc.signature
    if sig is None:
        return
    add("## 8. The residual's signature, and what this model cannot express")
    add("")
    lag = f" seen through a {sig.lag_s / 60:.0f}-minute lag" if sig.lag_s > 0 else ""
    add(f"What the refitted model misses on the held-out part (reading − model, mean over the sensors) "
        f"**{sig.describe()}**: its change across the run's range of each variable{lag}, the other held "
        f"constant, ± a block-jackknife standard error; beside it the same for each candidate's correction "
        f"(its prediction − the refit's). A candidate with the residual's signature explains its shape.")
    add("")
    labels = sorted({k for d in sig.dependences for k in d.corrections})
    rows = []
    for d in sig.dependences:
        held = f" (constant {d.held})" if d.held else ""
        res = f"{d.change_k:+.3f} ± {d.se_k:.3f}" if np.isfinite(d.change_k) else "not varied"
        rows.append([f"{d.variable}{held}", res] + [_f(d.corrections.get(k, float('nan'))) for k in labels])
    add(_table(["variable", "residual K"] + [f"`{k}` K" for k in labels], rows))
    add("")
    if not disc.not_placeable:
        add("Every catalogue effect can be placed on this model.")
        add("")
        return
    add("Catalogue effects this model cannot express (they were not offered as candidates):")
    add("")
    rows = []
    for n in disc.not_placeable:
        fits = sig.fits(n.effect.explains)
        rows.append([f"`{n.effect.name}`", n.reason, R.label(n.effect.explains),
                     "not judged by speed, current, ambient" if fits is None else ("**yes**" if fits else "no")])
    add(_table(["effect", "why not", "it would follow", "fits the residual's signature"], rows))
    add("")


def _separating_sentence(disc: Discovery) -> str:
    """The operating condition that would tell winner and runner-up apart, in one sentence."""
    rd = disc.rounds[0]
    p = rd.point
    if p is None:
        return ""
    if p.sensors_separate(disc.noise_k):
        return (f"a test run at **{p.describe()}** would ({p.sensor}: {p.t_a:.1f} °C against {p.t_b:.1f} °C). ")
    trans = max((ev.max_diff[1] for ev in rd.evidence), default=0.0)
    where = ("a sensor closer to one of them would" if not p.node_separates(disc.noise_k) else
             f"a sensor on **{p.node}** would ({p.node_a:.1f} °C against {p.node_b:.1f} °C at that point)")
    return (f"no steady operating point separates them at these sensors by more than {p.diff:.2f} K (largest at "
            f"{p.describe()}), and over the run their predictions differ by at most {trans:.3f} K, both below 3× "
            f"the noise floor ({disc.noise_k:.3f} K): no test run with these sensors tells them apart; {where}. ")


def _gap_section(disc: Discovery, add: Callable[[str], None]) -> None:
    g = disc.gap
    if g is None or g.status in ("none", "explained"):
        return
    add("## 7. The gap the catalogue does not explain")
    add("")
    add(f"Held-out gap {g.gap_k:.3f} K against a noise floor of {g.noise_k:.3f} K ({g.ratio:.0f}×; below "
        f"{g.threshold_k:.3f} K it would count as no gap). It is largest on **{g.worst_sensor}** "
        f"(held-out RMS {g.worst_rms_k:.2f} K).")
    add("")
    add("Where (regimes of the whole run, worst sensor): " + "; ".join(g.where) + ".")
    add("")
    add(f"When (held-out part): {g.when}.")
    add("")
    if g.nearest:
        add("Nearest candidates (full fits, held-out):")
        add("")
        add(_table(["candidate", "held-out gap K", "improvement"], [[f"`{n}`", _f(v), _pct(i)] for n, v, i in g.nearest]))
        add("")


def write(disc: Discovery, out: str | os.PathLike[str], commands: Sequence[str] = ()) -> str:
    """Write ``report.md`` and its figures into ``out``; returns the report path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = figures(disc, out)
    path = out / "report.md"
    path.write_text(markdown(disc, files, commands))
    return str(path)
