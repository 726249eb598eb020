"""Run inside the qemu VM (tests/vm/vmrun.py) with real SocketCAN: the manual's vcan0 bench (docs/guide/try-it.md).

The service (``thermal-edge run``, wall clock, ``config/edge.yaml`` with the manual's
``channel: can0`` -> ``vcan0`` edit) under a fake systemd notify socket with a watchdog, and the
inverter emulator (``python -m thermal_edge.sim.inverter --interface socketcan --channel vcan0
--speed 1``) as a second process. Prints one JSON line: notifications seen and the service's
frame counters.
"""
from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[2]
TMP = Path(os.environ.get("TMPDIR", "/tmp")) / "bench"
VENV_BIN = Path(sys.executable).parent
PORT = 19108


def main() -> int:
    # the guest's init leaves the loopback down: the metrics endpoint binds 127.0.0.1
    subprocess.run(["ip", "link", "set", "lo", "up"], check=False)
    TMP.mkdir(parents=True, exist_ok=True)
    (TMP / "machines").mkdir(exist_ok=True)
    (TMP / "state").mkdir(exist_ok=True)
    (TMP / "machines" / "pm10kw.yaml").write_text((REPO / "config" / "machines" / "pm10kw.yaml").read_text())
    text = (REPO / "config" / "edge.yaml").read_text()
    text = re.sub(r"^  channel: can0$", "  channel: vcan0", text, flags=re.M)  # the manual's sed
    text = text.replace("../dbc/thermal_edge.dbc", str(REPO / "dbc" / "thermal_edge.dbc"))
    raw = yaml.safe_load(text)
    assert raw["bus"] == {**raw["bus"], "interface": "socketcan", "channel": "vcan0"}, raw["bus"]
    raw["metrics"]["port"] = PORT
    raw["state"]["dir"] = str(TMP / "state")
    cfg = TMP / "edge.yaml"
    cfg.write_text(yaml.safe_dump(raw, sort_keys=False))

    sock_path = str(TMP / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(sock_path)
    sock.settimeout(0.5)
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "NOTIFY_SOCKET": sock_path, "WATCHDOG_USEC": "10000000"}
    t0 = time.monotonic()
    svc = subprocess.Popen([str(VENV_BIN / "thermal-edge"), "run", "--config", str(cfg)], env=env,
                           stdout=open(TMP / "service.log", "w"), stderr=subprocess.STDOUT)
    notes: list[tuple[float, str]] = []

    def drain(until: float) -> None:
        while time.monotonic() < until:
            try:
                notes.append((time.monotonic() - t0, sock.recv(4096).decode()))
            except TimeoutError:
                pass

    deadline = time.monotonic() + 400
    while time.monotonic() < deadline and not any("READY=1" in n for _, n in notes):
        if svc.poll() is not None:
            break
        drain(time.monotonic() + 1)
    ready_s = next((t for t, n in notes if "READY=1" in n), None)
    emu_env = {k: v for k, v in env.items() if k not in ("NOTIFY_SOCKET", "WATCHDOG_USEC")}
    emu = subprocess.Popen([str(VENV_BIN / "python"), "-m", "thermal_edge.sim.inverter", "--interface", "socketcan",
                            "--channel", "vcan0", "--model", str(TMP / "machines" / "pm10kw.yaml"),
                            "--cycle", str(REPO / "config" / "cycles" / "overload.yaml"), "--speed", "1"],
                           env=emu_env, stdout=open(TMP / "emulator.log", "w"), stderr=subprocess.STDOUT)
    metrics = ""
    scrapes: list[str] = []
    deadline = time.monotonic() + 400
    while time.monotonic() < deadline and svc.poll() is None:
        drain(time.monotonic() + 2)
        try:
            metrics = urllib.request.urlopen(f"http://127.0.0.1:{PORT}/metrics", timeout=30).read().decode()
            scrapes.append(f"{time.monotonic() - t0:.0f}s ok")
        except OSError as exc:
            scrapes.append(f"{time.monotonic() - t0:.0f}s {type(exc).__name__}")
            continue
        rx = re.findall(r'^thermal_edge_frames_received_total\{frame="INV_StatorTemps"\} (\S+)$', metrics, re.M)
        ticks = re.findall(r"^thermal_edge_ticks_total (\S+)$", metrics, re.M)
        if rx and float(rx[0]) >= 20 and ticks and float(ticks[0]) >= 10:
            break
    emu.send_signal(signal.SIGTERM)
    svc.send_signal(signal.SIGTERM)
    drain(time.monotonic() + 3)
    rc_svc = svc.wait(timeout=120)
    rc_emu = emu.wait(timeout=120)

    def counters(name: str) -> dict[str, float]:
        return {m.group(1): float(m.group(2)) for m in re.finditer(rf'^{name}\{{frame="(\w+)"\}} (\S+)$', metrics, re.M)}

    kinds = [l.split("=", 1)[0] for _, n in notes for l in n.splitlines() if "=" in l]
    first = [k for k in kinds if k in ("READY", "WATCHDOG", "STOPPING")]
    out = {
        "ready_s": ready_s,
        "wall_s": round(time.monotonic() - t0, 1),
        "scrapes": scrapes,
        "first_notifications": first[:3],
        "last_notification": first[-1] if first else None,
        "watchdog_pings": kinds.count("WATCHDOG"),
        "status_lines": kinds.count("STATUS"),
        "last_status": next((l for _, n in reversed(notes) for l in n.splitlines() if l.startswith("STATUS=")), None),
        "received": counters("thermal_edge_frames_received_total"),
        "sent": counters("thermal_edge_frames_sent_total"),
        "dropped": sum(float(v) for v in re.findall(r"^thermal_edge_frames_dropped_total\{[^}]*\} (\S+)$", metrics, re.M)),
        "ticks": float((re.findall(r"^thermal_edge_ticks_total (\S+)$", metrics, re.M) or ["0"])[0]),
        "state": re.findall(r'^thermal_edge_state\{thermal_edge_state="(\w+)"\} 1\.0$', metrics, re.M),
        "rc_service": rc_svc,
        "rc_emulator": rc_emu,
        "state_saved": (TMP / "state" / "state.json").exists(),
        "service_log": (TMP / "service.log").read_text()[-1500:],
        "emulator_log": (TMP / "emulator.log").read_text()[-800:],
    }
    art = os.environ.get("VM_ARTIFACTS")
    if art:
        Path(art, "bench-metrics.txt").write_text(metrics)
    print("BENCH " + json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
