"""The service and the simulated machine over SocketCAN on ``vcan0`` where the kernel has it.

SocketCAN stamps frames with the kernel's reception time, so simulated time cannot travel with the
frames: this runs in real time (frame clock = wall clock), briefly. Machines without ``vcan0``
(no AF_CAN, no vcan module) skip it visibly.
"""
from __future__ import annotations

import os
import socket

import pytest
from svc_testlib import edge_raw, emulator_config, write_yaml


def vcan0_reason() -> str | None:
    if not hasattr(socket, "AF_CAN"):
        return "this Python has no AF_CAN"
    if not os.path.exists("/sys/class/net/vcan0"):
        return "no vcan0 interface (kernel without vcan, or not set up: ip link add vcan0 type vcan)"
    try:
        s = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
        s.bind(("vcan0",))
        s.close()
    except OSError as exc:
        return f"cannot open a CAN_RAW socket on vcan0: {exc}"
    return None


@pytest.mark.async_timeout(60)
async def test_closed_loop_over_vcan0(tmp_path):
    why = vcan0_reason()
    if why is not None:
        pytest.skip(f"socketcan on vcan0 unavailable here: {why}")
    from thermal_edge.config import load_config
    from thermal_edge.service import EdgeService
    from thermal_edge.sim.inverter import InverterEmulator

    bus = {"interface": "socketcan", "channel": "vcan0"}
    cfg = load_config(write_yaml(tmp_path / "edge.yaml", edge_raw(tmp_path / "state", bus, table4=False, adapt=False)))
    svc = EdgeService(cfg)
    await svc.start()
    try:
        import time

        emu = InverterEmulator(emulator_config(duration_s=12.0, speed=1.0, t0=time.time(), current_period_s=0.01,
                                               temperature_period_s=0.1, plant_dt_s=0.1, flow_control=False),
                               {"interface": "socketcan", "channel": "vcan0"})
        s = await emu.run()
    finally:
        await svc.stop()
    st = svc.codec.stats
    assert st.lost == 0 and st.crc == 0
    assert svc.engine.ticks >= 10
    assert s.limits_received >= 100 and s.rx_lost == 0  # TE_Limits every 100 ms
