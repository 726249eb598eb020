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
against both Jacobians; every ratio is the median of the rounds' paired ratios.
"""
from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..lptn import Role, Simulator, load_model, steady_state
from ..lptn.sensitivity import held_steps
from ..shipped import config_path
from ..sim.cycles import cycle_run, load_cycle
from .common import Progress, no_progress, timed, timed_together

#: relative noise (one standard deviation) on current and speed in the varying-input case
NOISE = 1e-3
#: the noisy speed is rounded to this resolution (rpm): operating points of one discretisation
SPEED_BIN_RPM = 10.0


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
    when: str
    #: inputs that vary every sample: the same figures, the binning's effect and the agreement
    varying: dict[str, Any] = field(default_factory=dict)


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
    a_ = np.random.default_rng(0).standard_normal((N, n))
    b_ = np.random.default_rng(1).standard_normal((n, n * p))
    t_blas, _, _ = timed(lambda: a_ @ b_, 5)
    flops = 2.0 * 2.0 * N * n * n * p
    rate = 2.0 * N * n * n * p / t_blas
    varying = _varying(model, cols, dt, T0, theta, wrt, sensor_nodes, idx, repeat, flops / rate,
                       lambda stage, *a: progress(f"varying inputs: {stage}", *a))

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
        when=time.strftime("%Y-%m-%dT%H:%M:%S"),
        varying=varying,
    )


def _varying(model: object, cols: dict[str, np.ndarray], dt: float, T0: np.ndarray, theta: np.ndarray,
             wrt: list[str], sensor_nodes: list[str], idx: np.ndarray, repeat: int, limit_s: float,
             progress: Progress) -> dict[str, object]:
    """The varying-input case (see the module docstring): times side by side (with the arithmetic
    limit ``limit_s``, s), the agreement of the vectorised and stepped Jacobians, and the
    binning's effect on the sensors."""
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
    (t_an, times_an, S), (t_st, times_st, S_st), (t_num, times_num, _), (t_sim, times_sim, T_v), (t_sim_st, times_sim_st, T_s) = \
        timed_together([lambda: jac(sim), lambda: jac(stepper), forward,
                        lambda: sim.simulate(theta, noisy, dt, T0).T, lambda: stepper.simulate(theta, noisy, dt, T0).T],
                       repeat, progress)
    # binning: the first hour with the noisy speed as it is (an operating point per sample) against binned
    hour = min(N, int(round(3600.0 / dt)))
    raw = recorded_like(cols, current, speed, speed_bin=None)
    first = {k: np.asarray(v)[:hour] for k, v in raw.items()}
    binned = {k: np.asarray(v)[:hour] for k, v in noisy.items()}
    T_first, T_binned = sim.simulate(theta, first, dt, T0).T, sim.simulate(theta, binned, dt, T0).T
    bin_err = float(np.max(np.abs(T_first[:, rows] - T_binned[:, rows])))
    def paired(num: list[float], den: list[float]) -> float:
        """The median over rounds of each round's ratio ``num / den`` (times taken seconds apart)."""
        return statistics.median([a / b for a, b in zip(num, den)])

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
    }


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
