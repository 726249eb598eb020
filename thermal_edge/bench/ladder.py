"""``bench ladder``: one online adaptation step against the model size, dense and reduced.

For each size of generated chain model (:func:`~thermal_edge.lptn.chain.chain_model`: 40, 80,
160 and 320 nodes by default) a simulated plant (the model with :data:`PLANT` changes) runs
:data:`HOURS` of the varied drive cycle at 1 Hz; its sensors are read with σ :data:`NOISE_K`
noise. An online adapter (the service's :class:`~thermal_edge.estimation.adapter.OnlineAdapter`,
default settings: 3 h window decimated to 20 s steps, 14 adaptable parameters) holds that
history and decides, from the nominal parameters each time: screening, then 3 SQP iterations.
The step is timed with the exact dense simulator and with the reduced one
(:mod:`thermal_edge.lptn.reduced`), in turn, round after round; the ratio is the median of the
rounds' ratios. The reduced bases are built before the timing (once per model and step, as the
service does at its first decision) and their one-off cost is printed apart.

Beside the times: the reduced model's size (states and modes kept) at the optimiser's step, the
stated error bound at the sensors (:meth:`~thermal_edge.lptn.reduction.Reduction.bound`, over
the window's inputs) and the error measured against the dense model over the optimiser's
window at the nominal parameters, and how far the two paths' fitted parameters are apart.
"""
from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, field

import numpy as np

from ..estimation.adapter import AdapterConfig, OnlineAdapter
from ..estimation.common import decimate, window_from_arrays
from ..lptn import Model, Simulator, steady_state
from ..lptn.chain import chain_model
from ..lptn.reduced import ReducedSimulator
from ..shipped import config_path
from ..sim.cycles import cycle_run, load_cycle
from .common import Progress, no_progress

#: model sizes (nodes) of the ladder
SIZES = (40, 80, 160, 320)
#: hours of the drive cycle (the adapter's window)
HOURS = 3.0
#: sensor noise of the simulated readings, K (σ)
NOISE_K = 0.1
#: the plant: the model with these parameters changed (what the adaptation has to find)
PLANT = {"k_r_sw": 1.3, "c_p_sw": 400.0, "R_e_hous": 0.15, "r_ins_sw": 0.012}
#: the target of one adaptation step on the largest model, s
TARGET_S = 1.0


@dataclass
class LadderRow:
    """One model size: times in s (medians of the rounds), errors in K."""

    nodes: int
    dense_s: float  #: one adaptation step with the dense simulator
    reduced_s: float  #: the same step with the reduced one
    ratio: float  #: median over the rounds of dense / reduced
    dense_runs_s: list[float]
    reduced_runs_s: list[float]
    states: int  #: states of the reduced model at the optimiser's step
    modes: int  #: of which modes of the full model
    basis_s: float  #: one-off: building the reduced bases (optimiser's step and 1 s)
    bound_k: float  #: stated error bound at the sensors (largest), at the reference
    measured_k: float  #: largest error at the sensors against the dense model over the window
    fit_rel_diff: float  #: largest relative difference of the two paths' fitted parameters
    selected: tuple[str, ...]  #: the parameters the dense step's screening chose


@dataclass
class LadderResult:
    """What ``bench ladder`` measured."""

    rows: list[LadderRow]
    hours: float
    decimate: int
    params: int
    repeat: int
    target_s: float = TARGET_S
    when: str = field(default_factory=lambda: time.strftime("%Y-%m-%dT%H:%M:%S"))

    @property
    def largest(self) -> LadderRow:
        return max(self.rows, key=lambda r: r.nodes)


def _history(model: Model, hours: float, seed: int) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray],
                                                              np.ndarray, np.ndarray, np.ndarray]:
    """Inputs, noisy readings, the plant's node temperatures, sample times and the initial state."""
    cycle = load_cycle(config_path("cycles", "varied_drive.yaml"))
    run = cycle_run(cycle, model.drive["kt_nm_per_arms"], hours * 3600.0)
    cols = {c: np.asarray(run.columns[c], dtype=float) for c in model.inputs}
    T0, _ = steady_state(model, model.at_rest({c: float(v[0]) for c, v in cols.items()}))
    plant = model.with_parameters(PLANT)
    truth = Simulator(plant).simulate(plant.nominal(), cols, run.dt, T0).T
    rng = np.random.default_rng(seed)
    meas = {s: truth[:, model.node_index(x)] + NOISE_K * rng.standard_normal(len(truth)) for s, x in model.sensors.items()}
    return cols, meas, truth, np.asarray(run.t, dtype=float), T0


def rung(nodes: int, repeat: int = 3, hours: float = HOURS, config: AdapterConfig | None = None, seed: int = 0,
         progress: Progress = no_progress) -> LadderRow:
    """Measure one model size (see the module docstring)."""
    model = chain_model(nodes)
    cfg = config or AdapterConfig(threshold_k=0.0)
    cols, meas, truth, t, T0 = _history(model, hours, seed)
    ad = OnlineAdapter(model, cfg, 1.0)
    for k in range(len(t)):
        ad.record(float(t[k]), {c: float(v[k]) for c, v in cols.items()}, {s: float(v[k]) for s, v in meas.items()},
                  truth[k])
    dense, reduced = Simulator(model), ReducedSimulator(model)
    window = decimate(window_from_arrays(model, cols, meas, T0, 1.0, t), cfg.decimate)
    t0 = time.perf_counter()
    red = reduced.reduction(window.dt)
    reduced.reduction(1.0)  # the recent-error checks of a decision run at the recorded 1 s
    basis_s = time.perf_counter() - t0

    times: dict[str, list[float]] = {"dense": [], "reduced": []}
    fits: dict[str, dict[str, float]] = {}
    selected: tuple[str, ...] = ()
    for r in range(repeat):
        progress(f"{nodes} nodes: timed rounds", r, repeat, "round")
        for name, sim in (("dense", dense), ("reduced", reduced)):
            ad.sim = sim
            ad.theta, ad.challenger, ad.iterate = model.nominal(), None, None  # a full fit each time
            d = ad.decide(float(t[-1]))
            times[name].append(d.duration_s)
            fits[name] = d.challenger
            if name == "dense":
                selected = d.selected
    progress(f"{nodes} nodes: timed rounds", repeat, repeat, "round")

    # the reduced model against the dense one over the optimiser's window, and the bound there
    theta = model.nominal()
    full = dense.simulate(theta, window.inputs, window.dt, window.T0)
    approx = reduced.simulate(theta, window.inputs, window.dt, window.T0)
    sensors = [model.node_index(x) for x in model.sensors.values()]
    measured = float(np.max(np.abs(full.T[:, sensors] - approx.T[:, sensors])))
    w = np.column_stack([window.inputs[c] for c in model.boundaries.values()] + [full.P])
    bound = red.bound(window.dt, w)
    rows_ = [red.rows.index(x) for x in model.sensors.values()]
    names = sorted(set(fits["dense"]) | set(fits["reduced"]))
    diff = max((abs(fits["reduced"].get(k, np.nan) - fits["dense"].get(k, np.nan)) / abs(fits["dense"].get(k, np.nan))
                for k in names), default=float("nan"))
    ratios = [a / b for a, b in zip(times["dense"], times["reduced"])]
    return LadderRow(
        nodes=nodes,
        dense_s=statistics.median(times["dense"]),
        reduced_s=statistics.median(times["reduced"]),
        ratio=statistics.median(ratios),
        dense_runs_s=times["dense"],
        reduced_runs_s=times["reduced"],
        states=red.size,
        modes=red.modes,
        basis_s=basis_s,
        bound_k=float(np.max(bound[rows_])),
        measured_k=measured,
        fit_rel_diff=float(diff),
        selected=selected,
    )


def run(sizes: tuple[int, ...] = SIZES, repeat: int = 3, hours: float = HOURS,
        progress: Progress = no_progress) -> LadderResult:
    """The ladder over ``sizes`` (nodes), ``repeat`` timed rounds each."""
    cfg = AdapterConfig(threshold_k=0.0)
    rows = [rung(n, repeat, hours, cfg, progress=progress) for n in sizes]
    return LadderResult(rows=rows, hours=hours, decimate=cfg.decimate, params=len(chain_model(min(sizes)).adaptable),
                        repeat=repeat)


HEADERS = ["nodes", "dense step s", "reduced step s", "dense / reduced", "states (modes)", "error bound K",
           "measured error K", "fit difference"]


def table_rows(r: LadderResult) -> list[list[object]]:
    """The printed table's rows (:data:`HEADERS`)."""
    return [[x.nodes, x.dense_s, x.reduced_s, f"{x.ratio:.1f}x", f"{x.states} ({x.modes})", x.bound_k, x.measured_k,
             f"{100 * x.fit_rel_diff:.2g} %"] for x in r.rows]
