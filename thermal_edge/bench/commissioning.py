"""Commissioning of the flux-linkage estimate on the simulated machine: what a test-bench run with
a rotor telemetry gives on the real one.

The plant runs a drive cycle open loop (:func:`..sim.plant.simulate_plant`); the simulated inverter's
electrical side (:class:`..sim.pmsm.Pmsm`) gives the dq voltages from the plant's true winding and
magnet temperatures; :func:`~thermal_edge.estimation.flux.fit_flux_model` fits the estimator on
them with the magnet's true temperature as the measured one. The result is what
``thermal-edge flux calibrate`` writes (:meth:`~thermal_edge.estimation.flux.FluxModel.as_dict`).
"""
from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np

from ..estimation.flux import Electrical, FluxModel, fit_flux_model
from ..lptn import DEFAULT_COLUMNS, Model, Role
from ..sim.cycles import SPEED, cycle_run, load_cycle
from ..sim.plant import simulate_plant
from ..sim.pmsm import Pmsm

__all__ = ["commission", "miscalibrated"]


def commission(model: Model, pmsm: Pmsm, cycle: str | os.PathLike[str], winding_node: str, magnet_nodes: Sequence[str],
               params: Mapping[str, float] | None = None, seed: int = 0, duration_s: float | None = None) -> FluxModel:
    """Fit the flux-linkage estimator on a simulated bench run.

    Parameters
    ----------
    model : Model
        The machine (the plant is it with ``params``).
    pmsm : Pmsm
        Its electrical side.
    cycle : path
        The drive cycle of the run (i_d = 0 control, :mod:`..sim.cycles`).
    winding_node, magnet_nodes
        The node whose true temperature the stator resistance has, and those whose mean the flux
        linkage has (the bench's magnet measurement).
    seed : int
        Of the voltage noise.
    duration_s : float, optional
        Simulated seconds of the cycle (default: all of it).
    """
    kt = model.drive.get("kt_nm_per_arms")
    if kt is None:
        raise ValueError(f"model {model.name} has no drive.kt_nm_per_arms: cannot turn torque into current")
    run = cycle_run(load_cycle(cycle), float(kt), duration_s)
    res = simulate_plant(model, run, params, noise_k=0.0, resolution_k=0.0, seed=seed, all_nodes=True)
    c = res.run.columns
    winding = np.asarray(c[f"T_{winding_node}"], dtype=float)
    magnet = np.mean([np.asarray(c[f"T_{n}"], dtype=float) for n in magnet_nodes], axis=0)
    i_d = np.asarray(c[DEFAULT_COLUMNS[Role.CURRENT_D]], dtype=float)
    i_q = np.asarray(c[DEFAULT_COLUMNS[Role.CURRENT_Q]], dtype=float)
    speed = np.asarray(c[SPEED], dtype=float)
    u_d, u_q = pmsm.voltages(i_d, i_q, speed, winding, magnet, seed)
    return fit_flux_model(Electrical(u_d, u_q, i_d, i_q, speed, winding), magnet, pmsm.pole_pairs, dt=res.run.dt,
                          priors=_priors(pmsm))


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
