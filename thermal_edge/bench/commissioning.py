"""Commissioning of the flux-linkage estimate on the simulated machine: what a test-bench run with
a rotor telemetry gives on the real one.

The plant runs a drive cycle (:func:`bench_run`) with the simulated inverter's currents: ``i_q``
from the torque and the field-weakening ``i_d`` at high speed (:meth:`..sim.pmsm.Pmsm.currents`),
under the test bench's own protection: it reads the true temperatures (thermocouples, the rotor
telemetry) and takes the current down linearly over the last :data:`BENCH_BAND_K` below each
limited node's max less :data:`BENCH_MARGIN_K`, as a bench operator stops a run before the winding
burns. The electrical side (:class:`..sim.pmsm.Pmsm`) gives the dq voltages from the plant's true
winding and magnet temperatures; :func:`~thermal_edge.estimation.flux.fit_flux_model` fits the
estimator on them with the magnet's true temperature as the measured one. The result is what
``thermal-edge flux calibrate`` writes (:meth:`~thermal_edge.estimation.flux.FluxModel.as_dict`).
"""
from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from ..estimation.flux import Electrical, FluxModel, fit_flux_model
from ..lptn import Model, Role
from ..sim.cycles import SPEED, TORQUE, cycle_run, load_cycle
from ..sim.plant import Plant
from ..sim.pmsm import Pmsm

__all__ = ["BENCH_BAND_K", "BENCH_MARGIN_K", "BenchRun", "bench_run", "commission", "miscalibrated"]

#: the test bench's protection: the current falls linearly to zero over this band, K, ...
BENCH_BAND_K = 5.0
#: ... ending this far below each limited node's max, K
BENCH_MARGIN_K = 2.0


@dataclass
class BenchRun:
    """A simulated commissioning run, per sample (1 s): ``T`` (N, nodes) the plant's true
    temperatures at the sample (°C), the dq currents (A peak), the speed (rpm), the torque (Nm)
    the bench applied and the one the cycle asked for."""

    t: np.ndarray
    T: np.ndarray
    i_d: np.ndarray
    i_q: np.ndarray
    speed_rpm: np.ndarray
    torque_nm: np.ndarray
    torque_demand_nm: np.ndarray


def bench_run(model: Model, pmsm: Pmsm, cycle: str | os.PathLike[str], params: Mapping[str, float] | None = None,
              winding_node: str = "slot_winding_1", magnet_nodes: Sequence[str] = ("magnet_1", "magnet_2"),
              duration_s: float | None = None) -> BenchRun:
    """Run the plant over a drive cycle as a test bench does: the inverter's field-weakening
    currents (at the plant's true winding and magnet temperatures, the nodes named) and the
    bench's protection on the true temperatures of the model's limited nodes (see the module).

    Raises
    ------
    ValueError
        A model without ``drive.kt_nm_per_arms`` (a torque cycle cannot be turned into current).
    """
    kt = model.drive.get("kt_nm_per_arms")
    if kt is None:
        raise ValueError(f"model {model.name} has no drive.kt_nm_per_arms: cannot turn torque into current")
    kt = float(kt)
    run = cycle_run(load_cycle(cycle), kt, duration_s)
    c = run.columns
    first = {k: float(c[k][0]) for k in model.inputs if k in c}
    plant = Plant(model, params or {}, run.dt, rest_inputs=first)
    w = model.node_index(winding_node)
    mags = [model.node_index(n) for n in magnet_nodes]
    limits = [(model.node_index(lim.node), lim.max_c - BENCH_MARGIN_K) for lim in model.limits]
    current_in = model.find_input(Role.CURRENT)
    torque_in = model.find_input(Role.TORQUE)
    N = len(run)
    T = np.empty((N, len(model.nodes)))
    i_d, i_q, torque = np.zeros(N), np.zeros(N), np.zeros(N)
    speed, demand = np.asarray(c[SPEED], dtype=float), np.asarray(c[TORQUE], dtype=float)
    for k in range(N):
        Tk = plant.T
        T[k] = Tk
        share = min((min(1.0, max(0.0, (top - Tk[i]) / BENCH_BAND_K)) for i, top in limits), default=1.0)
        temps = (np.array(speed[k]), np.array(Tk[w]), np.array(np.mean(Tk[mags])))
        d, q = pmsm.currents(np.array(demand[k]), kt, *temps)
        if share < 1.0:  # the bench's protection: the current magnitude down by that share
            d, q = pmsm.currents(np.array(demand[k]), kt, *temps, i_limit_arms=share * float(np.hypot(d, q)) / math.sqrt(2.0))
        i_d[k], i_q[k] = float(d), float(q)
        torque[k] = i_q[k] / math.sqrt(2.0) * kt
        inputs = {name: float(c[name][k]) for name in model.inputs if name in c}
        if current_in is not None:
            inputs[current_in] = math.hypot(i_d[k], i_q[k]) / math.sqrt(2.0)
        if torque_in is not None:
            inputs[torque_in] = torque[k]
        plant.step(inputs)
    return BenchRun(run.t, T, i_d, i_q, speed, torque, demand)


def commission(model: Model, pmsm: Pmsm, cycle: str | os.PathLike[str], winding_node: str, magnet_nodes: Sequence[str],
               params: Mapping[str, float] | None = None, seed: int = 0, duration_s: float | None = None) -> FluxModel:
    """Fit the flux-linkage estimator on a simulated bench run (:func:`bench_run`).

    Parameters
    ----------
    model : Model
        The machine (the plant is it with ``params``).
    pmsm : Pmsm
        Its electrical side.
    cycle : path
        The drive cycle of the run.
    winding_node, magnet_nodes
        The node whose true temperature the stator resistance has, and those whose mean the flux
        linkage has (the bench's magnet measurement).
    seed : int
        Of the voltage noise.
    duration_s : float, optional
        Simulated seconds of the cycle (default: all of it).
    """
    b = bench_run(model, pmsm, cycle, params, winding_node, magnet_nodes, duration_s)
    winding = b.T[:, model.node_index(winding_node)]
    magnet = np.mean(b.T[:, [model.node_index(n) for n in magnet_nodes]], axis=1)
    u_d, u_q = pmsm.voltages(b.i_d, b.i_q, b.speed_rpm, winding, magnet, seed)
    return fit_flux_model(Electrical(u_d, u_q, b.i_d, b.i_q, b.speed_rpm, winding), magnet, pmsm.pole_pairs,
                          dt=float(b.t[1] - b.t[0]) if len(b.t) > 1 else 1.0, priors=_priors(pmsm))


def _priors(pmsm: Pmsm) -> dict[str, tuple[float, float]]:
    """What a data sheet and a DC resistance test say (loosely): the resistance within 20 %, the
    flux linkage within 10 %, the inductances within 50 %, no slope of them assumed."""
    return {"r20": (pmsm.r20, 0.2 * pmsm.r20), "psi20": (pmsm.psi20, 0.1 * pmsm.psi20),
            "ld0": (pmsm.ld0, 0.5 * pmsm.ld0), "lq0": (pmsm.lq0, 0.5 * pmsm.lq0),
            "ld1": (0.0, 0.5 * pmsm.ld0), "lq1": (0.0, 0.5 * pmsm.lq0),
            "v_err": (0.0, 2.0 * pmsm.v_dead + 1.0)}


def miscalibrated(flux: FluxModel, inductance_factor: float = 1.2, voltage_error_factor: float = 2.0) -> FluxModel:
    """The same estimator with its electrical calibration deliberately wrong: every inductance
    parameter times ``inductance_factor``, the inverter's voltage error times ``voltage_error_factor``."""
    p = dict(flux.params)
    for k in ("ld0", "ld1", "lq0", "lq1"):
        p[k] *= inductance_factor
    p["v_err"] *= voltage_error_factor
    return replace(flux, params=p)
