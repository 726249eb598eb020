"""python-can's own tools reach the service on this host: ``python -m can.player -i udp_multicast``
(stock python-can, the default interface, hop limit 0 so that nothing leaves the host) replays a
CAN recording into a running ``thermal-edge run``, which counts every frame of it."""
from __future__ import annotations

import math
import signal
import subprocess
import sys
from pathlib import Path

import can
from svc_testlib import (
    HANG_S,
    REPO,
    edge_raw,
    env,
    logged_metrics_port,
    metric_sum,
    scrape,
    start_service,
    wait_until,
    write_yaml,
)

from thermal_edge.bus import DEFAULT_UDP_MULTICAST_GROUP, FrameCodec


def _recording(path: Path, seconds: float = 3.0) -> dict[str, int]:
    """A candump -L recording of the inverter's four frames (10 Hz each), written by python-can's
    own writer; the frames per name."""
    codec = FrameCodec()
    counts = {"INV_Currents": 0, "INV_Mechanics": 0, "INV_StatorTemps": 0, "INV_AmbientTemps": 0}
    t0 = 1_000.0
    with can.Logger(str(path)) as writer:
        for k in range(int(seconds * 10)):
            t = t0 + 0.1 * k
            frames = {
                "INV_Currents": {"INV_Id": -3.0, "INV_Iq": 25.0 + math.sin(k / 5), "INV_IphRms": 18.0},
                "INV_Mechanics": {"INV_Speed": 900.0, "INV_Torque": 100.0, "INV_Udc": 560.0},
                "INV_StatorTemps": {"INV_T_WindingSlot": 60.0, "INV_T_EndWinding": 62.0, "INV_T_Housing": 45.0,
                                    "INV_S_WindingSlot": 0, "INV_S_EndWinding": 0, "INV_S_Housing": 0},
                "INV_AmbientTemps": {"INV_T_Ambient": 25.0, "INV_T_Coolant": math.nan, "INV_S_Ambient": 0,
                                     "INV_S_Coolant": 3},
            }
            for j, (name, signals) in enumerate(frames.items()):
                writer.on_message_received(can.Message(timestamp=t + 0.001 * j, arbitration_id=codec.frame_id(name),
                                                       data=codec.encode(name, signals), is_extended_id=False))
                counts[name] += 1
    return counts


def test_can_player_replays_a_recording_into_the_running_service(tmp_path, udp_port):
    log = tmp_path / "drive.log"
    counts = _recording(log)
    raw = edge_raw(tmp_path / "state", {"interface": "udp_multicast", "port": udp_port}, table4=False, adapt=False,
                   metrics_port=0)
    svc = start_service(write_yaml(tmp_path / "edge.yaml", raw), log=tmp_path / "service.log")
    try:
        mport = logged_metrics_port(tmp_path / "service.log")
        assert mport is not None and wait_until(lambda: _up(mport), HANG_S), (tmp_path / "service.log").read_text()
        player = subprocess.run(_guides_player_command(udp_port, log), env=env(), cwd=str(REPO), capture_output=True,
                                text=True, timeout=HANG_S)
        assert player.returncode == 0, player.stderr

        def received() -> dict[str, float]:
            m = scrape(mport)
            return {n: m.get(f'thermal_edge_frames_received_total{{frame="{n}"}}', 0.0) for n in counts}

        wait_until(lambda: received() == counts, HANG_S, interval=0.1)
        assert received() == counts
        m = scrape(mport)
        assert metric_sum(m, "thermal_edge_frames_dropped_total") == 0
        svc.send_signal(signal.SIGTERM)
        assert svc.wait(30) == 0
    finally:
        if svc.poll() is None:
            svc.kill()
            svc.wait()


def _guides_player_command(port: int, log: Path) -> list[str]:
    """The guide's ``python -m can.player`` command (docs/guide/connect-your-inverter.md), on the
    test's port and recording."""
    import re
    import shlex

    (line,) = re.findall(r"^python -m can\.player .*$", (REPO / "docs" / "guide" / "connect-your-inverter.md").read_text(),
                         re.M)
    words = shlex.split(line)
    assert "hop_limit=0" in words and words[words.index("-c") + 1] == DEFAULT_UDP_MULTICAST_GROUP
    words = [f"port={port}" if w.startswith("port=") else str(log) if w == "drive.log" else w for w in words]
    return [sys.executable, *words[1:]]


def _up(port: int) -> bool:
    try:
        return scrape(port).get("thermal_edge_up", 0) == 1
    except OSError:
        return False
