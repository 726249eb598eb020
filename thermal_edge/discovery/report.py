"""The discovery report: Markdown with PNG figures (matplotlib, imported here only: ``report`` extra)."""
from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Sequence

import numpy as np

from . import effects as E
from . import residuals as R
from . import yamlpatch
from .workflow import Discovery


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


def _binned(ax, x: np.ndarray, e: np.ndarray, color: str, bins: int = 12) -> None:  # type: ignore[no-untyped-def]
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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files: dict[str, str] = {}
    data = disc.data
    run = data.run
    t_h = (run.t - run.t[0]) / 3600.0
    before = disc.rounds[0].analysis
    after = disc.final_analysis or before
    ns = len(data.sensors)
    step = max(1, len(run) // 4000)
    name_after = " + ".join(r.fit.label for r in disc.added) or "refitted (no effect added)"

    fig, axes = plt.subplots(ns, 1, figsize=(9, 2.2 * ns + 0.6), sharex=True, squeeze=False)
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
    axes[-1, 0].set_xlabel("time since start (h)")
    fig.tight_layout()
    files["time"] = "residual_time.png"
    fig.savefig(out / files["time"], dpi=110)
    plt.close(fig)

    var = explained_variable(disc)
    fig, axes = plt.subplots(1, ns, figsize=(3.6 * ns + 0.6, 3.4), squeeze=False)
    for j, s in enumerate(data.sensors):
        ax = axes[0, j]
        x = _xvar(before, s, var)
        if x is None:
            ax.set_visible(False)
            continue
        ax.scatter(x[::step], before.residual[::step, j], s=2, alpha=0.25, color="tab:red", label="refitted model")
        _binned(ax, x, before.residual[:, j], "tab:red")
        if disc.added:
            ax.scatter(x[::step], after.residual[::step, j], s=2, alpha=0.25, color="tab:blue", label=f"with {name_after}")
            _binned(ax, x, after.residual[:, j], "tab:blue")
        ax.axhline(0.0, color="grey", lw=0.5)
        ax.set_xlabel(R.label(var))
        ax.set_ylabel("residual (K)")
        ax.set_title(s, fontsize=9)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, markerscale=4, loc="best")
    fig.tight_layout()
    files["var"] = f"residual_vs_{var.replace(':', '_')}.png"
    fig.savefig(out / files["var"], dpi=110)
    plt.close(fig)

    sc = [s for s in disc.rounds[0].scores if s.fraction > 0][:12]
    if sc:
        fig, ax = plt.subplots(figsize=(8, 0.32 * len(sc) + 1.0))
        ax.barh([s.cand.label for s in sc][::-1], [s.fraction for s in sc][::-1], color="tab:gray")
        ax.set_xlabel("score test: share of the training residual a joint step would remove")
        fig.tight_layout()
        files["scores"] = "scores.png"
        fig.savefig(out / files["scores"], dpi=110)
        plt.close(fig)
    return files


def regime_shift(before: R.SensorResiduals, after: R.SensorResiduals) -> list[tuple[str, str, float, float]]:
    """(axis, regime, rms before, rms after), largest drop first."""
    b = {(a, r): rms for a, r, _, _, rms in before.regimes}
    out = [(a, r, b[(a, r)], rms) for a, r, _, _, rms in after.regimes if (a, r) in b]
    return sorted(out, key=lambda x: -(x[2] - x[3]))


def markdown(disc: Discovery, files: dict[str, str], commands: Sequence[str] = ()) -> str:
    data = disc.data
    first = disc.rounds[0]
    lines: list[str] = []
    add = lines.append
    add(f"# Model-gap discovery: `{disc.model_name}` on `{os.path.basename(disc.source)}`")
    add("")
    if disc.named:
        add(f"**Verdict: missing effect `{disc.named.fit.label}`** — "
            f"{_effect_of(disc.named.fit.label).doc}. Held-out gap {disc.gap_before:.3f} K → {disc.gap_after:.3f} K "
            f"({1 - disc.gap_after / disc.gap_before:.0%} smaller).")
        if len(disc.added) > 1:
            add(f"Further effects added in later rounds: {', '.join(r.fit.label for r in disc.added[1:])}.")
    else:
        add(f"**Verdict: no missing effect found.** After refitting, no catalogue effect lowers the held-out gap "
            f"({disc.gap_before:.3f} K) by the required {100 * disc.options.min_improvement:.0f} % "
            f"and {disc.options.min_gain_k:.2f} K.")
    add("")
    add(_table(["", "value"], [
        ["run", f"{len(data.run)} samples at {data.dt:g} s ({(data.run.t[-1] - data.run.t[0]) / 3600:.2f} h)"],
        ["sensors", ", ".join(data.sensors)],
        ["training / held-out", f"first {data.split} samples (fitted at {data.dt * data.factor:g} s steps) / last {len(data.run) - data.split}"],
        ["reference speed, current", f"{data.refs['n_ref']:g} rpm, {data.refs['i_ref']:g} A"],
        ["held-out gap, nominal parameters", f"{disc.nominal.gap:.3f} K"],
        ["held-out gap, refitted (before)", f"{disc.gap_before:.3f} K"],
        ["held-out gap, with the effect(s) (after)", f"{disc.gap_after:.3f} K"],
        ["sensor noise floor (from the data)", f"{disc.noise_k:.3f} K"],
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
        rows = sorted(((n, nom[n], ref[n]) for n in names), key=lambda t: -abs(math.log(t[2] / t[1])) if t[1] > 0 and t[2] > 0 else 0)
        add(f"The model's {len(names)} adaptable parameters were fitted to the training part (Gauss-Newton in "
            "log-parameters within their bounds), so that what remains is structural. Largest changes:")
        add("")
        add(_table(["parameter", "nominal", "refitted", "ratio"], [[n, f"{a:.4g}", f"{b:.4g}", f"{b / a:.2f}"] for n, a, b in rows[:8]]))
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
        f"and {disc.options.min_gain_k:.2f} K smaller than the refitted model's (or its continued refit, the control) "
        f"and a lower BIC N·ln(MSE) + k·ln(N) (N = {first.n_eff:.0f} held-out samples on the fitting grid, "
        f"k the effect's parameters).")
    add("")
    for rd in disc.rounds:
        add(f"Round {rd.index} (reference gap {rd.reference_gap:.3f} K):")
        add("")
        add(_table(["candidate", "from", "held-out gap K", "improvement", "ΔBIC", "fitted", "accepted"], [
            [f"`{x.fit.label}`", x.source, _f(x.fit.gap), _pct(x.improvement), f"{x.delta_criterion:+.1f}",
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
        for r in disc.added:
            add(f"# {r.fit.label}")
            add(yamlpatch.snippet(prev, r.fit.raw))
            prev = r.fit.raw
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
    if commands:
        add("## Reproduce")
        add("")
        add("```sh")
        lines.extend(commands)
        add("```")
        add("")
    return "\n".join(lines)


def write(disc: Discovery, out: str | os.PathLike[str], commands: Sequence[str] = ()) -> str:
    """Write ``report.md`` and its figures into ``out``; returns the report path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = figures(disc, out)
    path = out / "report.md"
    path.write_text(markdown(disc, files, commands))
    return str(path)
