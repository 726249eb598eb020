"""``simulate --voltages`` on a model of another machine: the electrical machine whose voltages it
writes has the model's torque constant (its flux linkage from ``drive.kt_nm_per_arms``), and the
command says which machine it simulated. Checked against the steady-state voltage equation
computed here from the run's own currents, speed and true temperatures."""
from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
from cmd_testlib import four_node_machine

from thermal_edge.data import read_run
from thermal_edge.sim.pmsm import Pmsm

FOUR_NODE_KT = 1.5  # Nm per A rms (the four-node model's drive): a quarter of the package's machine's


def test_the_voltages_are_those_of_a_machine_with_the_models_torque_constant(tmp_path):
    out, (model, _) = tmp_path / "v.csv", four_node_machine(tmp_path)
    r = subprocess.run([sys.executable, "-m", "thermal_edge.cli", "simulate", "--model", str(model), "--cycle", "overload",
                        "--duration", "1200", "--voltages", "--all-nodes", "--out", str(out)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    psi20 = FOUR_NODE_KT / (1.5 * Pmsm().pole_pairs * math.sqrt(2.0))
    assert f"psi {psi20:.4g} Wb at 20 degC (kt 1.5 Nm/A)" in r.stdout, r.stdout
    run = read_run(out)
    c = {k: np.asarray(run.column(k), dtype=float) for k in ("speed_rpm", "i_d", "i_q", "u_q_v", "pm", "T_winding")}
    pm = Pmsm()
    w = c["speed_rpm"] * 2 * math.pi / 60 * pm.pole_pairs
    rs = pm.r20 * (1 + pm.alpha_cu * (c["T_winding"] - 20))
    ia = np.hypot(c["i_d"], c["i_q"])
    ld = pm.ld0 / (1 + (ia / pm.i_sat) ** 2)
    dead = pm.v_dead * np.tanh(ia / pm.i_dead) / np.maximum(ia, 1e-9)
    psi = psi20 * (1 + pm.tempco * (c["pm"] - 20))
    u_q = rs * c["i_q"] + w * (ld * c["i_d"] + psi) + dead * c["i_q"]
    fast = c["speed_rpm"] > 500
    assert fast.sum() > 100
    # within the simulated noise (0.3 V) and the CSV's rounding; the package's 0.44 Wb would be ~3x higher
    assert np.abs(c["u_q_v"][fast] - u_q[fast]).max() < 2.0
