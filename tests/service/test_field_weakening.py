"""Field weakening of the simulated machine (thermal_edge.sim.pmsm) and in the inverter emulator:
the d current holds the commanded voltage at the DC link's limit, written out here from the
steady-state voltage equations; the current magnitude stays within the limit the inverter obeys;
and an inductance table 20 % off reaches the magnet estimate only where the d current flows."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from svc_testlib import MODEL

from thermal_edge.estimation.flux import Electrical, FluxModel
from thermal_edge.sim.inverter import EmulatorConfig, InverterEmulator
from thermal_edge.sim.pmsm import Pmsm

PM = Pmsm(noise_v=0.0)


def voltage(i_d: float, i_q: float, speed_rpm: float, t_w: float, t_m: float) -> float:
    """|u| (V peak) of the simulated machine, written out (saturating L, dead-time error along i)."""
    w = 6 * 2 * math.pi * speed_rpm / 60.0
    ia = math.hypot(i_d, i_q)
    sat = 1.0 / (1.0 + (ia / 60.0) ** 2)
    r = 0.25 * (1 + 0.00393 * (t_w - 20.0)) + (3.0 * math.tanh(ia / 2.0) / ia if ia > 0 else 0.0)
    psi = 0.44 * (1 - 0.0011 * (t_m - 20.0))
    return math.hypot(r * i_d - w * 4.4e-3 * sat * i_q, r * i_q + w * (4.0e-3 * sat * i_d + psi))


@pytest.mark.parametrize("speed,torque,weakens", [(900.0, 220.0, False), (1200.0, 130.0, False),
                                                  (1500.0, 130.0, True), (1500.0, 220.0, True), (1500.0, 0.0, True)])
def test_the_d_current_holds_the_voltage_at_the_dc_links_limit(speed, torque, weakens):
    t_w, t_m = 110.0, 60.0
    i_d, i_q = (float(x) for x in PM.currents(np.array(torque), 5.6, np.array(speed), np.array(t_w), np.array(t_m)))
    u_max = 660.0 / math.sqrt(3.0)
    assert i_q == pytest.approx(math.sqrt(2.0) * torque / 5.6)
    if not weakens:
        assert i_d == 0.0 and voltage(0.0, i_q, speed, t_w, t_m) <= u_max
        return
    assert i_d < -1.0
    assert voltage(i_d, i_q, speed, t_w, t_m) == pytest.approx(u_max, abs=0.01)
    assert voltage(0.99 * i_d, i_q, speed, t_w, t_m) > u_max  # the least d current that does it


def test_the_current_limit_bounds_the_magnitude_the_d_current_included():
    t_w, t_m = 110.0, 60.0
    i_d, i_q = (float(x) for x in PM.currents(np.array(220.0), 5.6, np.array(1500.0), np.array(t_w), np.array(t_m),
                                            i_limit_arms=25.0))
    assert math.hypot(i_d, i_q) / math.sqrt(2.0) <= 25.0 + 1e-6
    assert math.hypot(i_d, i_q) / math.sqrt(2.0) > 24.5  # not more torque given away than the limit asks
    assert voltage(i_d, i_q, 1500.0, t_w, t_m) == pytest.approx(660.0 / math.sqrt(3.0), abs=0.01)


def test_the_emulator_sends_the_d_current_and_obeys_the_limit_with_it(tmp_path):
    cyc = tmp_path / "fw.yaml"
    cyc.write_text("name: fw\ndt_s: 1.0\nambient_c: 25.0\nsegments:\n"
                   "  - {duration_s: 30, speed_rpm: 1500, torque_nm: 200}\n")
    cfg = EmulatorConfig(model_path=MODEL, cycle_path=cyc, t0=0.0, current_period_s=0.1, temperature_period_s=1.0,
                         plant_dt_s=0.5, duration_s=20.0, speed=0.0, flow_control=False, closed_loop=True,
                         noise_k=0.0, pmsm=PM, voltages=False)
    emu = InverterEmulator(cfg)
    emu.current_limit, emu.torque_limit = 30.0, 220.0
    emu.limits_wall, emu.limits_sim = None, 0.0
    cur, mech, names = [], [], set()
    while emu.elapsed < 20.0 - 1e-9:
        emu.limits_sim = emu.sim_time
        emu.limits_wall = 0.0
        for _, name, sig in emu.step(None):
            names.add(name)
            (cur if name == "INV_Currents" else mech if name == "INV_Mechanics" else []).append(sig)
    assert "INV_Voltages" not in names  # the electrical model without the frame
    i_d = np.array([s["INV_Id"] for s in cur])
    i_q = np.array([s["INV_Iq"] for s in cur])
    assert np.all(i_d < -5.0)
    assert np.allclose(np.hypot(i_d, i_q) / math.sqrt(2.0), [s["INV_IphRms"] for s in cur])
    assert np.all(np.hypot(i_d, i_q) / math.sqrt(2.0) <= 30.0 + 1e-6)
    # the torque is the q current's (what the limit left of it), below the demand
    assert np.allclose([s["INV_Torque"] for s in mech], i_q / math.sqrt(2.0) * 5.6)
    assert max(s["INV_Torque"] for s in mech) < 200.0


def test_a_wrong_inductance_reaches_the_magnet_estimate_only_where_the_d_current_flows():
    """An estimator with every inductance 20 % high: at i_d = 0 its magnet is the right one's; in
    field weakening it is off by 0.2 L_d(|i|) i_d / β (written out from the q voltage equation)."""
    p = {"r20": 0.25, "v_err": 3.0, "psi20": 0.44, "beta": -0.44 * 0.0011, "ld0": 4.0e-3, "ld1": -1.0e-3,
         "lq0": 4.4e-3, "lq1": -1.1e-3}
    right = FluxModel(params=p, sigma={}, pole_pairs=6, bin_a=20.0, var_u={}, speed_min_rpm=0.0)
    wrong = replace(right, params={k: v * (1.2 if k[0] == "l" else 1.0) for k, v in p.items()})
    t_w, t_m = 110.0, 80.0
    for speed, torque in ((900.0, 150.0), (1500.0, 150.0)):
        i_d, i_q = (float(x) for x in PM.currents(np.array(torque), 5.6, np.array(speed), np.array(t_w), np.array(t_m)))
        u_d, u_q = PM.voltages(np.array([i_d]), np.array([i_q]), np.array([speed]), np.array([t_w]), np.array([t_m]),
                               seed=None)
        e = Electrical(u_d, u_q, np.array([i_d]), np.array([i_q]), np.array([speed]), np.array([t_w]))
        shift = float(wrong.temperature(e)[0] - right.temperature(e)[0])
        ld = 4.0e-3 - 1.0e-3 * math.hypot(i_d, i_q) / 100.0
        # ψ̂ = (u_q - R i_q - V_e i_q/|i|)/ω - L_d i_d: L_d 20 % high takes 0.2 L_d i_d off ψ̂ (i_d < 0: adds)
        assert shift == pytest.approx(-0.2 * ld * i_d / (-0.44 * 0.0011), rel=1e-6, abs=1e-9)
        if speed == 900.0:
            assert i_d == 0.0 and shift == 0.0
        else:
            assert shift < -10.0  # a magnet tens of kelvin cooler than it is: what the disagreement check refuses
