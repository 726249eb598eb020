"""``bench jacobian``: analytic sensitivities vs the forward-difference Jacobian (p+1 simulations).

The 39-node 10 kW model, its 14 adaptable parameters, 3 h of the varied drive cycle at 1 Hz; the
output Jacobian at the sensors. Both Jacobians are timed in the same run, in turn, round after
round; the analytic one is checked against central differences (4p simulations, not timed).
The speed-up is the median over rounds of each round's ratio: the two times of a round are taken
seconds apart, so a shared machine that changes speed during the run (seen here: one simulation
taking 42 ms in one minute and 65 ms in the next) changes both alike, where a ratio of two
medians can pair a slow analytic round with fast forward-difference rounds or the reverse
(the ratio of the medians is reported beside it).
The arithmetic limit is the flop count of the sensitivity forcing and recursion, ``2·N·n²·p``
twice, at the rate this machine's BLAS reaches on a matrix product of the same shape, measured in
the same run.

A second case has inputs that vary every sample, as recorded data do: the same cycle with
relative noise :data:`NOISE` on the current and on the speed, the speed then binned to
:data:`SPEED_BIN_RPM` (every distinct speed is an operating point with its own discretisation;
the binning's effect on the sensor temperatures is measured over the first hour against the
unbinned speed and printed). There the new and the old way are timed side by side, round after
round: the analytic Jacobian with stretches at one speed vectorised in time against the same
Jacobian stepped sample by sample (the reference and the way such inputs were computed before),
the simulation vectorised against stepped, and forward differences (p+1 vectorised simulations)
against both Jacobians; every ratio is the median of the rounds' paired ratios. Each call is
timed twice over, wall clock and the process's CPU time: on a busy host the wall clock includes
the time the process waits for a core, the CPU time does not, so the CPU ratios are the ones that
hold from one run to the next.

A third case has a speed that sweeps continuously (the varied cycle's speed plus a slow
oscillation of :data:`SWEEP_RPM`, rounded to 1 rpm, and the noisy current): a new operating point
every few steps, thousands in the run. Its figure is memory: the tracemalloc peak of one
simulation and of one Jacobian with every operating point discretised at once and in time chunks
of at most :data:`~thermal_edge.lptn.simulate.MAX_OPERATING_POINTS`, their wall times (one call
each, outside tracemalloc) and their agreement.

Two figures bound what the ratios can reach. Forward differences are ``p + 1`` simulations and
the analytic Jacobian is one simulation plus the sensitivities, so forward differences / analytic
is below ``(p + 1) × simulation / analytic`` (printed beside it) however cheap the sensitivities
get. The arithmetic limit counts the sensitivity recursion only (no discretisation, no
simulation); it is printed at the BLAS rate of a product into a fresh array (whose pages the
kernel zeroes on first touch, part of any real computation's cost) and into an array already
touched (the rate of the arithmetic alone).
"""
from __future__ import annotations

import statistics
import time
import tracemalloc
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import numpy as np

from ..lptn import Role, Simulator, load_model, steady_state
from ..lptn.sensitivity import held_steps
from ..lptn.simulate import MAX_OPERATING_POINTS
from ..shipped import config_path
from ..sim.cycles import cycle_run, load_cycle
from .common import Progress, no_progress, timed_together

#: relative noise (one standard deviation) on current and speed in the varying-input case
NOISE = 1e-3
#: the noisy speed is rounded to this resolution (rpm): operating points of one discretisation
SPEED_BIN_RPM = 10.0
#: amplitude (rpm) and period (s) of the slow oscillation added to the speed in the sweep case
SWEEP_RPM = 200.0
SWEEP_PERIOD_S = 1200.0


def recorded_like(cols: dict[str, np.ndarray], current: str, speed: str, noise: float = NOISE,
                  speed_bin: float | None = SPEED_BIN_RPM, seed: int = 0) -> dict[str, np.ndarray]:
    """The inputs with relative Gaussian noise ``noise`` on ``current`` (A) and ``speed`` (rpm),
    the speed rounded to ``speed_bin`` rpm (None: not rounded); seeded, so runs compare."""
    rng = np.random.default_rng(seed)
    out = dict(cols)
    N = len(cols[current])
    out[current] = np.asarray(cols[current], dtype=float) * (1.0 + noise * rng.standard_normal(N))
    sp = np.asarray(cols[speed], dtype=float) * (1.0 + noise * rng.standard_normal(N))
    out[speed] = sp if speed_bin is None else np.round(sp / speed_bin) * speed_bin
    return out


@dataclass
class JacobianResult:
    """What ``bench jacobian`` measured: times in s (medians of the rounds unless a list), errors relative."""

    nodes: int
    sensors: int
    params: int
    samples: int
    operating_points: int  #: distinct speeds of the cycle
    analytic_s: float
    analytic_runs_s: list[float]
    numerical_s: float
    numerical_runs_s: list[float]
    simulation_s: float
    speedup: float  #: median over the rounds of forward differences / analytic
    speedup_rounds: list[float]
    speedup_of_medians: float
    held_steps: int  #: steps whose inputs are held from the previous one
    analytic_stepped_s: float
    speedup_stepped: float
    closed_vs_stepped_max_rel: float
    max_rel_err: float  #: analytic vs central differences
    flops: float
    blas_gflops: float
    arith_limit_s: float
    analytic_over_limit: float
    arith_limit_reused_s: float  #: the arithmetic limit at the rate of a product into an array already touched
    when: str
    #: inputs that vary every sample: the same figures, the binning's effect and the agreement
    varying: dict[str, Any] = field(default_factory=dict)
    #: a speed that sweeps continuously: peak memory and time in one piece and in chunks
    sweep: dict[str, Any] = field(default_factory=dict)


def central_difference(sim: Simulator, theta: np.ndarray, i: int, cols: dict, dt: float, T0: np.ndarray,
                       rel: float = 1e-2) -> np.ndarray:
    """Fourth-order central difference ``∂T/∂θ_i`` (N, n) with step ``rel · θ_i``."""
    h = rel * theta[i]

    def at(delta: float) -> np.ndarray:
        th = theta.copy()
        th[i] += delta
        return sim.simulate(th, cols, dt, T0).T

    return (-at(2 * h) + 8 * at(h) - 8 * at(-h) + at(-2 * h)) / (12 * h)


def run(repeat: int = 7, model_path: str | None = None, cycle_path: str | None = None, hours: float = 3.0,
        progress: Progress = no_progress) -> JacobianResult:
    """Time both Jacobians (``repeat`` rounds) and check the analytic one; ``progress`` as it goes."""
    model = load_model(model_path or config_path("machines", "pm10kw.yaml"))
    cycle = load_cycle(cycle_path or config_path("cycles", "varied_drive.yaml"))
    inputs = cycle_run(cycle, model.drive["kt_nm_per_arms"], hours * 3600.0)
    cols = {c: inputs.columns[c] for c in model.inputs}
    dt = inputs.dt
    wrt = list(model.adaptable)
    theta = model.nominal()
    T0, _ = steady_state(model, model.at_rest({c: float(v[0]) for c, v in cols.items()}))
    sim = Simulator(model)
    idx = model.parameter_index(wrt)
    sensor_nodes = list(model.sensors.values())
    rows = [model.node_index(x) for x in sensor_nodes]
    N, n, p = len(inputs), len(model.nodes), len(wrt)

    def analytic() -> np.ndarray:
        """The output Jacobian at the sensors, ∂y_k/∂θ (N, sensors, p), simulation included."""
        tr = sim.simulate(theta, cols, dt, T0, wrt=wrt, rows=sensor_nodes)
        assert tr.S is not None
        return tr.S

    def forward() -> np.ndarray:
        return forward_differences(sim, theta, cols, dt, T0, idx, rows)

    stepper = Simulator(model, closed_form=False, vectorised=False)

    def analytic_stepped() -> np.ndarray:
        """The same Jacobian with every sample stepped (what inputs that change every step cost)."""
        tr = stepper.simulate(theta, cols, dt, T0, wrt=wrt, rows=sensor_nodes)
        assert tr.S is not None
        return tr.S

    sim.simulate(theta, cols, dt, T0, wrt=wrt)  # warm-up (imports, caches of numpy)
    (t_an, times_an, S), (t_st, _, S_st), (t_num, times_num, _), (t_sim, _, _) = timed_together(
        [analytic, analytic_stepped, forward, lambda: sim.simulate(theta, cols, dt, T0)], repeat, progress)
    assert isinstance(S, np.ndarray) and isinstance(S_st, np.ndarray)

    # arithmetic limit: 2 products of N x n by n x (n p) (forcing and recursion), at the BLAS rate
    # of one such product into a fresh array and into one already touched (wall and CPU)
    a_ = np.random.default_rng(0).standard_normal((N, n))
    b_ = np.random.default_rng(1).standard_normal((n, n * p))
    out_ = a_ @ b_
    (t_blas, _, _, c_blas, _), (t_warm, _, _, c_warm, _) = _rounds(
        [lambda: a_ @ b_, lambda: np.matmul(a_, b_, out=out_)], 7)
    flops = 2.0 * 2.0 * N * n * n * p
    rate = 2.0 * N * n * n * p / t_blas
    limits = {"arith_limit_s": 2.0 * t_blas, "arith_limit_cpu_s": 2.0 * c_blas,
              "arith_limit_reused_s": 2.0 * t_warm, "arith_limit_reused_cpu_s": 2.0 * c_warm}
    varying = _varying(model, cols, dt, T0, theta, wrt, sensor_nodes, idx, repeat, limits,
                       lambda stage, *a: progress(f"varying inputs: {stage}", *a))
    progress("sweeping speed", 0, 1, "case")
    sweep = _sweep(model, cols, dt, T0, theta, wrt, sensor_nodes)
    progress("sweeping speed", 1, 1, "case")

    # accuracy: fourth-order central differences (step 1 % of the value: the simulation's own
    # round-off, ~1e-10 K, swamps smaller steps), relative error on entries above 1 % of that
    # parameter's largest sensitivity
    max_rel = 0.0
    for j, i in enumerate(idx):
        progress("central differences", j, p, "parameter")
        fd = central_difference(sim, theta, i, cols, dt, T0)[:, rows]
        a = S[:, :, j]
        big = np.abs(fd) > 1e-2 * np.abs(fd).max()
        if big.any():
            max_rel = max(max_rel, float(np.max(np.abs(a[big] - fd[big]) / np.abs(fd[big]))))
    progress("central differences", p, p, "parameter")

    ratios = [t / a for t, a in zip(times_num, times_an)]  # each round's forward differences ÷ analytic
    return JacobianResult(
        nodes=n,
        sensors=len(rows),
        params=p,
        samples=N,
        operating_points=int(len(np.unique(cols[model.input_name(Role.SPEED)]))),
        analytic_s=t_an,
        analytic_runs_s=times_an,
        numerical_s=t_num,
        numerical_runs_s=times_num,
        simulation_s=t_sim,
        speedup=statistics.median(ratios),
        speedup_rounds=ratios,
        speedup_of_medians=t_num / t_an,
        held_steps=int(np.count_nonzero(held_steps(sim.net.env(theta, cols), N - 1))),
        analytic_stepped_s=t_st,
        speedup_stepped=t_num / t_st,
        closed_vs_stepped_max_rel=float(np.max(np.abs(S - S_st)) / np.max(np.abs(S_st))),
        max_rel_err=max_rel,
        flops=flops,
        blas_gflops=rate / 1e9,
        arith_limit_s=flops / rate,
        analytic_over_limit=t_an / (flops / rate),
        arith_limit_reused_s=2.0 * t_warm,
        when=time.strftime("%Y-%m-%dT%H:%M:%S"),
        varying=varying,
        sweep=sweep,
    )


def _rounds(fns: Sequence[Callable[[], object]], repeat: int,
            progress: Progress = no_progress) -> list[tuple[float, list[float], object, float, list[float]]]:
    """The functions called in turn, round after round (as :func:`~thermal_edge.bench.common.timed_together`),
    each call timed by the wall clock and by the process's CPU time: per function the median wall
    time (s), the wall times, the last result, the median CPU time (s) and the CPU times."""
    wall: list[list[float]] = [[] for _ in fns]
    cpu: list[list[float]] = [[] for _ in fns]
    outs: list[object] = [None] * len(fns)
    for r in range(repeat):
        progress("timed rounds", r, repeat, "round")
        for i, fn in enumerate(fns):
            c0, t0 = time.process_time(), time.perf_counter()
            outs[i] = fn()
            wall[i].append(time.perf_counter() - t0)
            cpu[i].append(time.process_time() - c0)
    progress("timed rounds", repeat, repeat, "round")
    return [(statistics.median(w), w, out, statistics.median(c), c) for w, c, out in zip(wall, cpu, outs)]


def _varying(model: object, cols: dict[str, np.ndarray], dt: float, T0: np.ndarray, theta: np.ndarray,
             wrt: list[str], sensor_nodes: list[str], idx: np.ndarray, repeat: int, limits: dict[str, float],
             progress: Progress) -> dict[str, object]:
    """The varying-input case (see the module docstring): times side by side, wall and CPU (with
    the arithmetic limits ``limits``, s: ``arith_limit_s`` and the same ``_cpu``, ``_reused``),
    the agreement of the vectorised and stepped Jacobians, and the binning's effect on the
    sensors."""
    current, speed = model.input_name(Role.CURRENT), model.input_name(Role.SPEED)  # type: ignore[attr-defined]
    noisy = recorded_like(cols, current, speed)
    sim, stepper = Simulator(model), Simulator(model, closed_form=False, vectorised=False)  # type: ignore[arg-type]
    rows = [model.node_index(x) for x in sensor_nodes]  # type: ignore[attr-defined]
    N = len(noisy[current])

    def jac(s: Simulator) -> np.ndarray:
        tr = s.simulate(theta, noisy, dt, T0, wrt=wrt, rows=sensor_nodes)
        assert tr.S is not None
        return tr.S

    def forward() -> np.ndarray:
        return forward_differences(sim, theta, noisy, dt, T0, idx, rows)

    jac(sim)  # warm-up
    timings = _rounds([lambda: jac(sim), lambda: jac(stepper), forward,
                       lambda: sim.simulate(theta, noisy, dt, T0).T, lambda: stepper.simulate(theta, noisy, dt, T0).T],
                      repeat, progress)
    (t_an, times_an, S, c_an, cpu_an), (t_st, times_st, S_st, c_st, cpu_st), (t_num, times_num, _, c_num, cpu_num), \
        (t_sim, times_sim, T_v, c_sim, cpu_sim), (t_sim_st, times_sim_st, T_s, c_sim_st, cpu_sim_st) = timings
    # binning: the first hour with the noisy speed as it is (an operating point per sample) against binned
    hour = min(N, int(round(3600.0 / dt)))
    raw = recorded_like(cols, current, speed, speed_bin=None)
    first = {k: np.asarray(v)[:hour] for k, v in raw.items()}
    binned = {k: np.asarray(v)[:hour] for k, v in noisy.items()}
    T_first, T_binned = sim.simulate(theta, first, dt, T0).T, sim.simulate(theta, binned, dt, T0).T
    bin_err = float(np.max(np.abs(T_first[:, rows] - T_binned[:, rows])))
    def paired(num: list[float], den: list[float], scale: float = 1.0) -> float:
        """The median over rounds of each round's ratio ``scale · num / den`` (times taken seconds apart)."""
        return statistics.median([scale * a / b for a, b in zip(num, den)])

    p1 = len(wrt) + 1.0
    limit_s = limits["arith_limit_s"]
    return {
        "noise": NOISE,
        "speed_bin_rpm": SPEED_BIN_RPM,
        "operating_points": int(len(np.unique(noisy[speed]))),
        "binning_max_err_k": bin_err,
        "analytic_s": t_an,
        "analytic_runs_s": times_an,
        "arith_limit_s": limit_s,
        "analytic_over_limit": t_an / limit_s,
        "analytic_stepped_s": t_st,
        "analytic_stepped_runs_s": times_st,
        "stepped_over_limit": t_st / limit_s,
        "numerical_s": t_num,
        "numerical_runs_s": times_num,
        "simulation_s": t_sim,
        "simulation_runs_s": times_sim,
        "simulation_stepped_s": t_sim_st,
        "simulation_stepped_runs_s": times_sim_st,
        "speedup_vs_stepped": paired(times_st, times_an),
        "speedup_vs_forward": paired(times_num, times_an),
        "stepped_speedup_vs_forward": paired(times_num, times_st),
        "simulation_speedup": paired(times_sim_st, times_sim),
        "vectorised_vs_stepped_max_rel": _max_rel(S, S_st),
        "simulation_vs_stepped_max_rel": _max_rel(T_v, T_s),
        # the same in CPU time, and the bounds (see the module docstring)
        **limits,
        "analytic_cpu_s": c_an, "analytic_cpu_runs_s": cpu_an,
        "analytic_stepped_cpu_s": c_st, "analytic_stepped_cpu_runs_s": cpu_st,
        "numerical_cpu_s": c_num, "numerical_cpu_runs_s": cpu_num,
        "simulation_cpu_s": c_sim, "simulation_cpu_runs_s": cpu_sim,
        "simulation_stepped_cpu_s": c_sim_st, "simulation_stepped_cpu_runs_s": cpu_sim_st,
        "cpu_speedup_vs_stepped": paired(cpu_st, cpu_an),
        "cpu_speedup_vs_forward": paired(cpu_num, cpu_an),
        "cpu_stepped_speedup_vs_forward": paired(cpu_num, cpu_st),
        "cpu_simulation_speedup": paired(cpu_sim_st, cpu_sim),
        "forward_bound": paired(times_sim, times_an, p1),
        "stepped_forward_bound": paired(times_sim, times_st, p1),
        "cpu_forward_bound": paired(cpu_sim, cpu_an, p1),
        "cpu_stepped_forward_bound": paired(cpu_sim, cpu_st, p1),
        "cpu_analytic_over_limit": c_an / limits["arith_limit_cpu_s"],
        "cpu_stepped_over_limit": c_st / limits["arith_limit_cpu_s"],
        "analytic_over_reused_limit": t_an / limits["arith_limit_reused_s"],
        "cpu_analytic_over_reused_limit": c_an / limits["arith_limit_reused_cpu_s"],
        # the part the limit counts: the Jacobian less its simulation, per round
        "sensitivities_over_limit": _beyond(times_an, times_sim, limit_s),
        "cpu_sensitivities_over_limit": _beyond(cpu_an, cpu_sim, limits["arith_limit_cpu_s"]),
        "stepped_sensitivities_over_limit": _beyond(times_st, times_sim_st, limit_s),
        "cpu_stepped_sensitivities_over_limit": _beyond(cpu_st, cpu_sim_st, limits["arith_limit_cpu_s"]),
    }


def _beyond(total: Sequence[float], part: Sequence[float], limit: float) -> float:
    """The median over rounds of ``(total − part) / limit``: a Jacobian's time beyond its
    simulation's (the same round's), in arithmetic limits."""
    return statistics.median([(a - b) / limit for a, b in zip(total, part)])


def swept(cols: dict[str, np.ndarray], speed: str, dt: float, amplitude: float = SWEEP_RPM,
          period_s: float = SWEEP_PERIOD_S) -> dict[str, np.ndarray]:
    """The inputs with a slow oscillation of ``amplitude`` rpm and period ``period_s`` added to
    ``speed`` where the machine turns, rounded to 1 rpm: a speed that sweeps continuously."""
    out = dict(cols)
    sp = np.asarray(cols[speed], dtype=float)
    t = np.arange(len(sp)) * dt
    out[speed] = np.where(sp > 0.0, np.round(sp + amplitude * np.sin(2.0 * np.pi * t / period_s)), 0.0)
    return out


def _peak(fn: Callable[[], Any]) -> tuple[Any, float]:
    """``fn()`` and the tracemalloc peak of the call (MB)."""
    tracemalloc.start()
    try:
        out = fn()
        return out, tracemalloc.get_traced_memory()[1] / 1e6
    finally:
        tracemalloc.stop()


def _sweep(model: Any, cols: dict[str, np.ndarray], dt: float, T0: np.ndarray, theta: np.ndarray,
           wrt: list[str], sensor_nodes: list[str]) -> dict[str, Any]:
    """The sweeping-speed case (see the module docstring): peak memory (MB) and wall time (s) of a
    simulation and a Jacobian in one piece and in chunks, and their agreement."""
    current, speed = model.input_name(Role.CURRENT), model.input_name(Role.SPEED)
    inputs = swept(recorded_like(cols, current, speed, speed_bin=None), speed, dt)
    N = len(inputs[speed])
    out: dict[str, Any] = {"operating_points": int(len(np.unique(inputs[speed][: N - 1]))),
                           "max_operating_points": MAX_OPERATING_POINTS, "amplitude_rpm": SWEEP_RPM}
    results = {}
    for label, sim in (("whole", Simulator(model, max_operating_points=N)), ("chunked", Simulator(model))):
        for what, kw in (("simulation", {}), ("jacobian", {"wrt": wrt, "rows": sensor_nodes})):
            call = partial(sim.simulate, theta, inputs, dt, T0, **kw)
            results[label, what], out[f"{label}_{what}_peak_mb"] = _peak(call)
            t0 = time.perf_counter()
            call()
            out[f"{label}_{what}_s"] = time.perf_counter() - t0
    out["temperatures_max_rel"] = _max_rel(results["chunked", "simulation"].T, results["whole", "simulation"].T)
    out["sensitivities_max_rel"] = _max_rel(results["chunked", "jacobian"].S, results["whole", "jacobian"].S)
    return out


def _max_rel(a: object, ref: object) -> float:
    """Largest difference of ``a`` from ``ref`` relative to the largest entry of ``ref``."""
    x, y = np.asarray(a), np.asarray(ref)
    return float(np.max(np.abs(x - y)) / np.max(np.abs(y)))


def forward_differences(sim: Simulator, theta: np.ndarray, cols: Any, dt: float, T0: np.ndarray,
                        idx: Any, rows: Any) -> np.ndarray:
    """The output Jacobian (N, sensors, p) by forward differences (relative step 1e-6), p + 1
    simulations: the baseline the analytic Jacobian is compared with."""
    base = sim.simulate(theta, cols, dt, T0).T[:, rows]
    J = np.empty((base.shape[0], len(rows), len(idx)))
    for j, i in enumerate(idx):
        h = 1e-6 * theta[i]
        th = theta.copy()
        th[i] += h
        J[:, :, j] = (sim.simulate(th, cols, dt, T0).T[:, rows] - base) / h
    return J
