"""The magnet in the closed loop when the rotor model is wrong (thermal_edge.bench.protection).

Session 8 found the hole: with the magnet losses twice the model's and the air-gap heat transfer
30 % lower, the service let the true magnet reach 121.1 °C (372 s over its max) because the
magnet's band carried no rotor-side uncertainty. The model file now declares the rotor-side loss
and convection coefficients with their spread, and the observer carries them into the band. The
reference is the plant's own temperature (the inverter emulator's plant, built with the changed
values).
"""
from __future__ import annotations

from pathlib import Path

import yaml

from thermal_edge.bench import protection as P
from thermal_edge.lptn import steady_state
from thermal_edge.sim.plant import nominal_values

MAGNET_MAX = 120.0


def cycle(tmp_path: Path) -> Path:
    """45 min at 170 Nm (30 A: the hot spot binds), then 45 min at 1500 rpm and 140 Nm (25 A): the
    bench's high-speed stretch, where the magnets bind."""
    path = tmp_path / "cycle.yaml"
    path.write_text(yaml.safe_dump({"name": "magnet", "dt_s": 1.0, "ambient_c": 25.0, "segments": [
        {"duration_s": 2700, "speed_rpm": 900, "torque_nm": 170, "ramp_s": 10},
        {"duration_s": 2700, "speed_rpm": 1500, "torque_nm": 140, "ramp_s": 30}]}))
    return path


def test_magnet_never_overheats_with_doubled_magnet_losses(tmp_path):
    """The held-out case of session 8 on a short cycle: the plant's magnet would go far past its
    max at the demanded load (its own steady state), the service derates for the magnet, and the
    true magnet never exceeds its max (without the magnet's own limit it reached 121.7 °C, 696 s over max)."""
    case = P.parse_plant_changes(["P_pm_ref=+100%", "h_gap1=-30%"])
    cfg = P.edge_config(tmp_path / "state")
    from thermal_edge.service.engine import load_service_model

    model = load_service_model(cfg)
    plant = P.plant_for(model, case)
    assert nominal_values(plant)["P_pm_ref"] == 2 * nominal_values(model)["P_pm_ref"]
    i = 140.0 / 5.6
    T_ss, _ = steady_state(plant, {"speed_rpm": 1500.0, "i_rms": i, "torque_nm": 140.0, "ambient_c": 25.0})
    magnet = plant.node_index(next(lim.node for lim in plant.limits if lim.name == "magnet"))
    assert T_ss[magnet] > MAGNET_MAX + 30.0  # without derating the magnet would overheat
    res = P.run_case(case, policies=("thermal_edge",), cycle=cycle(tmp_path))["thermal_edge"]
    assert res["seconds_over_max"] == 0.0
    assert res["peak_magnet_c"] <= MAGNET_MAX
    assert res["reason_s"].get("magnet", 0.0) > 60.0  # the magnet limited, for minutes
    assert res["headroom_pct"] > 60.0  # derated, not stopped
