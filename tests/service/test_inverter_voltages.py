"""The inverter emulator's optional INV_Voltages on the ``virtual`` bus, read by an independent
python-can client and decoded with cantools from the DBC: the CAN matrix's counter and CRC
(checked with crccheck), one voltage frame with every current frame, and the values of the
steady-state voltage equations written out here from the plant's true temperatures."""
from __future__ import annotations

import asyncio
import math
import time

import can
import cantools
import numpy as np
import pytest
from svc_testlib import CYCLES, DBC, MODEL

from thermal_edge.sim.inverter import EmulatorConfig, InverterEmulator
from thermal_edge.sim.pmsm import Pmsm

crc = pytest.importorskip("crccheck.crc", reason="crccheck is installed with cantools (a core dependency)")

T0 = 1000.0
PLANT_DT_S = 0.5


def test_the_voltage_frame_on_the_bus():
    machine = Pmsm(noise_v=0.0)
    channel = f"te-voltages-{time.monotonic_ns()}"
    cfg = EmulatorConfig(model_path=MODEL, cycle_path=CYCLES / "varied_drive.yaml", t0=T0, current_period_s=0.1,
                         temperature_period_s=1.0, plant_dt_s=PLANT_DT_S, duration_s=60.0, speed=0.0, flow_control=False,
                         closed_loop=False, noise_k=0.0, trace_every_s=PLANT_DT_S, pmsm=machine)
    emu = InverterEmulator(cfg, {"interface": "virtual", "channel": channel, "preserve_timestamps": True})
    rx = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    try:
        asyncio.run(emu.run())
        msgs = []
        while (msg := rx.recv(0)) is not None:
            msgs.append(msg)
    finally:
        rx.shutdown()
    db = cantools.database.load_file(str(DBC))
    volt, cur, mech = (db.get_message_by_name(n) for n in ("INV_Voltages", "INV_Currents", "INV_Mechanics"))
    by_id: dict[int, list[can.Message]] = {}
    for m in msgs:
        by_id.setdefault(m.arbitration_id, []).append(m)
    vs, cs, ms = by_id[volt.frame_id], by_id[cur.frame_id], by_id[mech.frame_id]
    assert volt.frame_id == 0x2D0 and len(vs) == len(cs) == len(ms) == 600
    ref = crc.Crc8SaeJ1850
    for k, m in enumerate(vs):
        did = 0x1000 + m.arbitration_id
        assert m.data[7] == ref.calc(bytes((did & 0xFF, did >> 8)) + bytes(m.data[:7]))
        assert db.decode_message(m.arbitration_id, m.data)["INV_Voltages_Counter"] == k % 16
    nodes = emu.model.nodes
    w, mags = nodes.index("slot_winding_1"), [nodes.index("magnet_1"), nodes.index("magnet_2")]
    T = np.array(emu.trace_T)
    for v, c, me in zip(vs, cs, ms):
        assert v.timestamp == c.timestamp == me.timestamp
        u = db.decode_message(v.arbitration_id, v.data)
        i_q = db.decode_message(c.arbitration_id, c.data)["INV_Iq"]
        n = db.decode_message(me.arbitration_id, me.data)["INV_Speed"]
        Tk = T[int((v.timestamp - T0 + 1e-9) // PLANT_DT_S)]  # the plant's temperatures over that step
        t_w, t_m = Tk[w], float(np.mean(Tk[mags]))
        omega = 6 * 2 * math.pi * n / 60.0
        sat = 1.0 / (1.0 + (abs(i_q) / 60.0) ** 2)
        u_q = 0.25 * (1 + 0.00393 * (t_w - 20)) * i_q + omega * 0.44 * (1 - 0.0011 * (t_m - 20)) \
            + math.copysign(3.0 * math.tanh(abs(i_q) / 2.0), i_q)
        u_d = -omega * 4.4e-3 * sat * i_q
        assert u["INV_Uq"] == pytest.approx(u_q, abs=0.05 + 0.01)  # 0.1 V steps; INV_Iq sent in 0.05 A steps (R_s x 0.025 A)
        assert u["INV_Ud"] == pytest.approx(u_d, abs=0.05 + 0.01)
    assert {round(db.decode_message(m.arbitration_id, m.data)["INV_Speed"]) for m in ms} == {600}  # the cycle's start
    assert emu.summary.frames_sent["INV_Voltages"] == 600


def test_without_a_machine_model_no_voltage_frame():
    cfg = EmulatorConfig(model_path=MODEL, cycle_path=CYCLES / "varied_drive.yaml", t0=T0, current_period_s=0.1,
                         temperature_period_s=1.0, plant_dt_s=PLANT_DT_S, duration_s=5.0, closed_loop=False)
    emu = InverterEmulator(cfg)
    names = set()
    while emu.elapsed < 5.0 - 1e-9:
        names |= {n for _, n, _ in emu.step(None)}
    assert names == {"INV_Currents", "INV_Mechanics", "INV_StatorTemps", "INV_AmbientTemps"}
