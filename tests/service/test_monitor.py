"""``thermal-edge monitor`` against a running service: its screen agrees with an independent
scrape of the metrics and with the frames an independent receiver takes off the bus."""
from __future__ import annotations

import asyncio
import math
import sys

import can
import cantools
import pytest
from svc_testlib import DBC, env, running, scrape, sim_until

from thermal_edge.bus import DerateReason, FrameCodec, TeState
from thermal_edge.monitor.snapshot import FrameWatch, from_metrics
from thermal_edge.monitor.view import render


@pytest.mark.async_timeout(90)
async def test_metrics_snapshot_and_the_command_show_what_the_service_serves(tmp_path, channel):
    async with running(tmp_path, channel, metrics=True) as (svc, emu):
        await sim_until(emu, 120)
        port = svc.metrics.port
        text = svc.metrics.text()
        snap = from_metrics(text, "test")
        m = scrape(port)  # parsed independently (svc_testlib's own reading of the exposition)
        # what did not change between the two reads at a standstill of the test's checks
        assert snap.state == TeState(int(m["thermal_edge_state_code"])).name.lower()
        assert snap.reason == DerateReason(int(m["thermal_edge_derate_reason_code"])).name.lower()
        assert 0 < snap.current_limit_a <= 40.0
        names = {n.name for n in snap.nodes}
        assert names == {k.split('limit="')[1].split('"')[0] for k in m if k.startswith("thermal_edge_limited_node_celsius")}
        for n in snap.nodes:
            assert n.estimate_c <= n.upper_c and n.warn_c < n.max_c
        assert {s.name for s in snap.sensors} == {"slot_winding", "end_winding", "housing"}
        assert all(math.isfinite(s.measured_c) and s.age_s < 5 for s in snap.sensors)
        assert snap.stale == []
        screen = render(snap)
        for part in ("state nominal", "reason", "hot_spot", "magnet", "look-ahead", "slot_winding", "stale inputs: none"):
            assert part in screen
        # the command itself, in its own process, against the live endpoint
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "thermal_edge.cli", "monitor", "--once", "--metrics", f"http://127.0.0.1:{port}/metrics",
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, env=env())
        out, err = await asyncio.wait_for(proc.communicate(), 60)
        assert proc.returncode == 0, err.decode()
        lines = out.decode().splitlines()
        assert lines[0].startswith(f"thermal-edge monitor  http://127.0.0.1:{port}/metrics")
        assert any(line.startswith("state nominal") and " A " in line for line in lines)
        assert sum(line.startswith(("hot_spot", "magnet")) for line in lines) == 2


@pytest.mark.async_timeout(90)
async def test_bus_view_shows_the_frames_an_independent_receiver_decodes(tmp_path, channel):
    db = cantools.database.load_file(str(DBC))
    watch = FrameWatch("test", {"TE_Limits": 0.1})
    codec = FrameCodec()
    async with running(tmp_path, channel) as (svc, emu):
        listener = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        try:
            await sim_until(emu, 60)
            seen: dict[str, dict[str, float]] = {}
            heard: set[str] = set()
            for _ in range(2000):
                msg = listener.recv(timeout=0.01)
                if msg is None:
                    await asyncio.sleep(0.01)
                    continue
                frame = codec.decode_message(msg)
                if frame is None:
                    continue
                watch.add(frame)
                heard.add(frame.name)
                if frame.name.startswith("TE_"):
                    seen[frame.name] = db.decode_message(msg.arbitration_id, msg.data, decode_choices=False)
                # the inverter's frames interleave with ours in any order: wait for both kinds
                if len(seen) == 4 and "INV_Currents" in heard:
                    break
        finally:
            listener.shutdown()
    assert set(seen) == {"TE_Limits", "TE_Estimates", "TE_Forecast", "TE_Status"}
    snap = watch.current()
    assert snap.current_limit_a == pytest.approx(seen["TE_Limits"]["TE_CurrentLimit"], abs=0.05)
    assert snap.reason == DerateReason(seen["TE_Limits"]["TE_DerateReason"]).name.lower()
    assert snap.state == TeState(seen["TE_Status"]["TE_State"]).name.lower()
    assert snap.nodes[0].estimate_c == pytest.approx(seen["TE_Estimates"]["TE_T_HotSpot"], abs=0.1)
    assert {"TE_Limits", "INV_Currents"} <= set(snap.frame_ages)
    assert "frame" in render(snap)


def test_monitor_says_in_one_line_when_the_service_cannot_be_reached(tmp_path):
    import subprocess

    from svc_testlib import free_tcp_port

    port = free_tcp_port()  # held by this process, never listening: the connection is refused
    r = subprocess.run([sys.executable, "-m", "thermal_edge.cli", "monitor", "--once", "--metrics",
                        f"http://127.0.0.1:{port}/metrics"], capture_output=True, text=True, env=env(), timeout=300)
    assert r.returncode == 2 and r.stdout == ""
    assert len(r.stderr.strip().splitlines()) == 1 and f"127.0.0.1:{port}" in r.stderr


def test_the_screen_shows_the_voltage_input_the_silence_and_no_inf():
    """The voltage input's counts and last fused magnet, a silent bus, and a time to limit beyond
    the horizon in words, from exposition text written here."""
    from thermal_edge.monitor.snapshot import from_metrics
    from thermal_edge.monitor.view import render

    text = "\n".join([
        "# TYPE thermal_edge_flux_used counter", "thermal_edge_flux_used_total 12",
        "# TYPE thermal_edge_flux_refused counter",
        'thermal_edge_flux_refused_total{reason="stale"} 1', 'thermal_edge_flux_refused_total{reason="disagreement"} 2',
        'thermal_edge_flux_refused_total{reason="implausible"} 0',
        "# TYPE thermal_edge_flux_magnet_celsius gauge", "thermal_edge_flux_magnet_celsius 63.25",
        "# TYPE thermal_edge_flux_magnet_stddev_celsius gauge", "thermal_edge_flux_magnet_stddev_celsius 1.21",
        "# TYPE thermal_edge_bus_silent_seconds gauge", "thermal_edge_bus_silent_seconds 4.5",
        "# TYPE thermal_edge_time_to_limit_seconds gauge", "thermal_edge_time_to_limit_seconds +Inf", ""])
    screen = render(from_metrics(text))
    assert "voltages: used 12 ticks, refused 3 (disagreement 2, stale 1); last fused magnet 63.2 °C, σ 1.2 K" in screen
    assert "BUS SILENT for 4.5 s" in screen
    assert "time to limit at this load not within the horizon" in screen and "inf" not in screen
    quiet = render(from_metrics("# TYPE thermal_edge_bus_silent_seconds gauge\nthermal_edge_bus_silent_seconds 0\n"))
    assert "voltages:" not in quiet and "BUS SILENT" not in quiet


def test_the_bus_view_lists_the_frames_of_the_configurations_own_matrix(tmp_path):
    """``monitor --bus --config`` with an inverter's own DBC (the MC-7 example): its frames, sent
    here by an independent python-can bus encoded with cantools, are listed with their age, not
    only the ``TE_*`` frames of the shipped matrix."""
    import threading

    import yaml
    from cli_in_process import te_here

    assert te_here("config", "inverter-example", tmp_path / "mc7").returncode == 0
    raw = yaml.safe_load((tmp_path / "mc7" / "edge.yaml").read_text())
    channel = f"monitor-mc7-{tmp_path.name}"
    raw["bus"] = {"interface": "virtual", "channel": channel}
    raw["state"] = {"dir": str(tmp_path / "state")}
    cfg = tmp_path / "mc7" / "edge.yaml"
    cfg.write_text(yaml.safe_dump(raw))
    db = cantools.database.load_file(str(tmp_path / "mc7" / "acme-mc7.dbc"))
    msg = db.get_message_by_name("MC7_Currents")
    data = msg.encode({s.name: 0 for s in msg.signals}, strict=False)
    stop = threading.Event()

    def send() -> None:
        bus = can.Bus(interface="virtual", channel=channel)
        try:
            while not stop.is_set():
                bus.send(can.Message(arbitration_id=msg.frame_id, data=data, is_extended_id=False))
                stop.wait(0.01)
        finally:
            bus.shutdown()

    sender = threading.Thread(target=send, daemon=True)
    sender.start()
    try:
        r = te_here("monitor", "--bus", "--once", "--config", cfg)
    finally:
        stop.set()
        sender.join(10)
    assert r.returncode == 0, r.stderr
    assert "MC7_Currents" in r.stdout, r.stdout


def test_the_bus_view_of_a_silent_bus_says_nothing_was_heard(tmp_path):
    """``monitor --bus --once`` on a bus where nobody sends: every frame of the matrix with a cycle
    time (read here from the DBC by cantools) is listed as never heard, and the screen says that
    the inverter has no TE_Limits; "stale inputs: none" alone read as all inputs fresh."""
    from cli_in_process import te_here

    from thermal_edge.bus.frames import DEFAULT_DBC_PATH

    db = cantools.database.load_file(str(DEFAULT_DBC_PATH))
    cyclic = sorted(m.name for m in db.messages if m.cycle_time)
    r = te_here("monitor", "--bus", "--once", "--interface", "virtual", "--channel", f"silent-{tmp_path.name}")
    assert r.returncode == 0, r.stderr
    heard = next(line for line in r.stdout.splitlines() if line.startswith("never heard: "))
    assert heard.removeprefix("never heard: ").split(", ") == cyclic
    assert "no TE_Limits heard: the inverter is on its own protection" in r.stdout
