"""The systemd units: ``systemd-analyze verify``, the watchdog/notify protocol of the running
service (``READY=1`` then ``WATCHDOG=1`` at half ``WATCHDOG_USEC``), the hardening that must not
hide SocketCAN."""
from __future__ import annotations

import configparser
import os
import re
import shutil
import signal
import socket
import subprocess
import tempfile
import threading
import time
from pathlib import Path

import deploylib as dl
import pytest
from vmrun import INSTALL_TARGET  # tests/vm is on sys.path (conftest.py)

UNIT = dl.DEPLOY / "systemd" / "thermal-edge.service"
VCAN = dl.DEPLOY / "systemd" / "vcan.service"


def unit_entries(path: Path) -> dict[str, list[tuple[str, str]]]:
    """Section -> [(key, value)] in file order (repeated keys kept)."""
    out: dict[str, list[tuple[str, str]]] = {}
    section = None
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            section = line.strip("[]")
            out.setdefault(section, [])
            continue
        key, _, value = line.partition("=")
        assert section is not None, f"{path.name}: {line!r} outside a section"
        out[section].append((key.strip(), value.strip()))
    return out


def value(entries: list[tuple[str, str]], key: str) -> str | None:
    vals = [v for k, v in entries if k == key]
    return vals[-1] if vals else None


def seconds(v: str) -> float:
    total = 0.0
    for num, unit in re.findall(r"(\d+(?:\.\d+)?)\s*(ms|s|min|h)?", v):
        total += float(num) * {"ms": 1e-3, "s": 1.0, "min": 60.0, "h": 3600.0, "": 1.0}[unit]
    return total


def systemd_analyze() -> str:
    exe = shutil.which("systemd-analyze")
    if exe is None:
        pytest.skip(f"systemd-analyze not available (Debian package systemd: `sudo {INSTALL_TARGET}`)")
    return exe


#: the commands the units run besides ours, and the Debian packages that bring them (installed by
#: INSTALL_TARGET): ``verify`` refuses a unit whose ExecStart is not executable (a clean machine has neither)
UNIT_COMMANDS = {Path("/sbin/modprobe"): "kmod", Path("/sbin/ip"): "iproute2"}


def unit_commands_present() -> None:
    missing = {str(cmd): pkg for cmd, pkg in UNIT_COMMANDS.items() if not os.access(cmd, os.X_OK)}
    if missing:
        pytest.skip(f"{', '.join(missing)} not on this machine (Debian packages {' '.join(sorted(set(missing.values())))}: "
                    f"`sudo {INSTALL_TARGET}`): systemd-analyze verify would refuse the units for it")


#: where the unit runs the service (its ExecStart) and reads its configuration
OPT, ETC = "/opt/thermal-edge", "/etc/thermal-edge"


def units_in(root: Path) -> list[Path]:
    """The shipped units copied into ``root``, with ``/opt/thermal-edge`` and ``/etc/thermal-edge``
    moved under it (as the install test does) and an executable ``bin/thermal-edge`` there that
    runs this checkout's service: ``verify`` checks that ExecStart exists, and the host's
    ``/opt`` is left alone. Nothing else in the units changes."""
    exe = root / OPT.lstrip("/") / "bin" / "thermal-edge"
    exe.parent.mkdir(parents=True)
    exe.write_text(f"#!/bin/sh\nexec {' '.join(dl.thermal_edge_cmd())} \"$@\"\n")
    exe.chmod(0o755)
    (root / ETC.lstrip("/")).mkdir(parents=True)
    out = []
    for unit in (UNIT, VCAN):
        text = unit.read_text()
        moved = text.replace(OPT, str(root / OPT.lstrip("/"))).replace(ETC, str(root / ETC.lstrip("/")))
        dest = root / "units" / unit.name
        dest.parent.mkdir(exist_ok=True)
        dest.write_text(moved)
        out.append(dest)
    return out


def test_units_in_moves_only_the_install_paths(tmp_path: Path) -> None:
    """The copies differ from the shipped units only in the two install roots, and run the service."""
    copies = units_in(tmp_path)
    assert [c.name for c in copies] == [UNIT.name, VCAN.name]
    for shipped, copy in zip((UNIT, VCAN), copies):
        back = copy.read_text().replace(str(tmp_path / OPT.lstrip("/")), OPT).replace(str(tmp_path / ETC.lstrip("/")), ETC)
        assert back == shipped.read_text()
    exec_start = value(unit_entries(copies[0])["Service"], "ExecStart") or ""
    assert exec_start.startswith(str(tmp_path / OPT.lstrip("/") / "bin" / "thermal-edge") + " run --config " + str(tmp_path))
    exe = tmp_path / OPT.lstrip("/") / "bin" / "thermal-edge"
    r = subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=120, env=dl.env())
    assert r.returncode == 0 and "run" in r.stdout, r.stderr


def test_systemd_analyze_verify(tmp_path: Path) -> None:
    """``systemd-analyze verify`` on the shipped units, their install roots moved into a temporary
    directory (:func:`units_in`); every other line as shipped."""
    exe = systemd_analyze()
    print(subprocess.run([exe, "--version"], capture_output=True, text=True).stdout.splitlines()[0])
    unit_commands_present()
    r = subprocess.run([exe, "verify", *map(str, units_in(tmp_path))], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    # verify warns (exit 0) about unknown keys and bad values: none allowed
    noise = [l for l in (r.stdout + r.stderr).splitlines() if l.strip()]
    assert not noise, "\n".join(noise)


def test_systemd_analyze_verify_can_fail(tmp_path: Path) -> None:
    """The same check refuses a unit with an unknown key and one whose ExecStart is missing."""
    exe = systemd_analyze()
    unit_commands_present()
    unit, _ = units_in(tmp_path)
    text = unit.read_text()
    unit.write_text(text.replace("[Service]\n", "[Service]\nNoSuchKey=1\n", 1))
    r = subprocess.run([exe, "verify", str(unit)], capture_output=True, text=True, timeout=120)
    assert "NoSuchKey" in r.stdout + r.stderr
    (tmp_path / OPT.lstrip("/") / "bin" / "thermal-edge").unlink()
    unit.write_text(text)
    r = subprocess.run([exe, "verify", str(unit)], capture_output=True, text=True, timeout=120)
    assert r.returncode != 0 and "thermal-edge" in r.stdout + r.stderr


def test_unit_contract() -> None:
    u = unit_entries(UNIT)
    s = u["Service"]
    assert value(s, "Type") == "notify"
    assert value(s, "ExecStart") == "/opt/thermal-edge/bin/thermal-edge run --config /etc/thermal-edge/edge.yaml"
    assert value(s, "Restart") == "on-failure"
    assert value(s, "StateDirectory") == "thermal-edge"
    assert value(s, "ConfigurationDirectory") == "thermal-edge"
    assert value(s, "DynamicUser") == "yes" or value(s, "User") not in (None, "root")
    wd = seconds(value(s, "WatchdogSec") or "0")
    # the service pings at WatchdogSec/2 and stops pinging when a tick is 3 s (3 ticks) late
    assert 6.0 <= wd <= 60.0, wd
    assert value(s, "RestartPreventExitStatus") == "2"  # bad configuration: restarting cannot help
    for key, want in {"ProtectSystem": "strict", "ProtectHome": "yes", "PrivateTmp": "yes",
                      "NoNewPrivileges": "yes", "CapabilityBoundingSet": ""}.items():
        assert value(s, key) == want, key
    fams = set((value(s, "RestrictAddressFamilies") or "").split())
    assert {"AF_CAN", "AF_NETLINK", "AF_UNIX", "AF_INET", "AF_INET6"} <= fams
    assert any(k == "SystemCallFilter" and v == "@system-service" for k, v in s)
    # nothing that hides can0: no private network namespace, no restricted interfaces
    assert value(s, "PrivateNetwork") in (None, "no")
    assert value(s, "RestrictNetworkInterfaces") is None
    assert value(s, "IPAddressDeny") is None or "any" not in (value(s, "IPAddressDeny") or "")
    assert value(u["Install"], "WantedBy") == "multi-user.target"
    v = unit_entries(VCAN)["Service"]
    assert value(v, "Type") == "oneshot"
    starts = [val for k, val in v if k == "ExecStart"]
    assert any("modprobe vcan" in x for x in starts)
    assert any("link add dev vcan0 type vcan" in x for x in starts)
    assert any(x.endswith("vcan0 mtu 16 up") or x.endswith("vcan0 up") for x in starts)


def test_unit_parses_as_ini() -> None:
    cp = configparser.RawConfigParser(strict=False, interpolation=None)
    cp.optionxform = str
    cp.read_string(UNIT.read_text())
    assert {"Unit", "Service", "Install"} <= set(cp.sections())


@pytest.mark.timeout(900)  # a hang guard
def test_notify_ready_then_watchdog(tmp_path: Path) -> None:
    """The service under a fake systemd: READY=1, then WATCHDOG=1 every WATCHDOG_USEC/2, STOPPING=1 on SIGTERM.

    The pings are waited for and bounded above by the time the service lived (a fixed-rate schedule
    never pings faster than its interval); the interval itself is unit-tested
    (tests/service/test_service_systemd.py). How late a busy host lets a ping come is not the
    service's to promise."""
    state = tmp_path / "state"
    state.mkdir()
    bus = {"interface": "virtual", "channel": f"notify-test-{os.getpid()}"}
    cfg = dl.write_yaml(tmp_path / "edge.yaml", dl.service_config(state, bus=bus, metrics_port=None, clock="wall"))
    sockdir = Path(tempfile.mkdtemp(prefix="te-notify-", dir="/tmp"))  # short path (sun_path < 108)
    sock_path = sockdir / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(sock_path))
    sock.settimeout(0.2)
    log = tmp_path / "service.log"
    watchdog_usec = 2_000_000
    born = time.monotonic()
    proc = subprocess.Popen([*dl.thermal_edge_cmd(), "run", "--config", str(cfg)],
                            env=dl.env(NOTIFY_SOCKET=str(sock_path), WATCHDOG_USEC=str(watchdog_usec)),
                            stdout=log.open("w"), stderr=subprocess.STDOUT)
    msgs: list[tuple[float, str]] = []
    try:
        deadline = time.monotonic() + 600  # a hang guard
        pings = 0
        while time.monotonic() < deadline and pings < 6:
            if proc.poll() is not None:
                break
            try:
                data = sock.recv(4096).decode()
            except TimeoutError:
                continue
            msgs.append((time.monotonic(), data))
            pings += sum(1 for l in data.splitlines() if l == "WATCHDOG=1")
        assert proc.poll() is None, f"service exited {proc.returncode}:\n{log.read_text()}"
        proc.send_signal(signal.SIGTERM)
        end = time.monotonic() + 300
        while time.monotonic() < end:
            try:
                msgs.append((time.monotonic(), sock.recv(4096).decode()))
            except TimeoutError:
                if proc.poll() is not None:
                    break
        rc = proc.wait(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        sock.close()
        shutil.rmtree(sockdir, ignore_errors=True)
    lines = [(t, l) for t, m in msgs for l in m.splitlines()]
    kinds = [l.split("=", 1)[0] for _, l in lines if l.split("=", 1)[0] in ("READY", "WATCHDOG", "STOPPING")]
    assert rc == 0, log.read_text()
    assert kinds and kinds[0] == "READY", f"first notification must be READY=1, got {kinds[:5]}\n{log.read_text()}"
    assert "READY=1" in [l for _, l in lines]
    pings_t = [t for t, l in lines if l == "WATCHDOG=1"]
    stopping_t = next(t for t, l in lines if l.startswith("STOPPING"))
    assert len(pings_t) >= 6, kinds
    # the k-th ping is due k intervals after the first, which came after the process started
    assert len(pings_t) <= (stopping_t - born) / (watchdog_usec / 2e6) + 1, (len(pings_t), stopping_t - born)
    assert kinds[-1] == "STOPPING", kinds[-5:]
    assert any(l.startswith("STATUS=") for _, l in lines)
    assert (state / "state.json").exists(), "state not saved on SIGTERM"


@pytest.mark.timeout(900)  # a hang guard
def test_state_directory_used_when_config_has_no_dir(tmp_path: Path) -> None:
    """Under systemd the state goes to $STATE_DIRECTORY (StateDirectory=) when edge.yaml has no state.dir."""
    raw = dl.service_config(tmp_path, bus={"interface": "virtual", "channel": f"sd-{os.getpid()}"}, metrics_port=None,
                            clock="wall")
    raw["state"].pop("dir")
    cfg = dl.write_yaml(tmp_path / "edge.yaml", raw)
    sd = tmp_path / "var-lib-thermal-edge"
    sd.mkdir()
    proc = subprocess.Popen([*dl.thermal_edge_cmd(), "run", "--config", str(cfg)], env=dl.env(STATE_DIRECTORY=str(sd)),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    try:
        # SIGTERM once the service is up (its handler is installed by then): on a busy host the
        # start takes longer than any fixed sleep, and a signal before it ends the process
        deadline = time.monotonic() + 300  # a hang guard
        while not any("service up" in ln for ln in lines) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        assert proc.poll() is None and any("service up" in ln for ln in lines), "".join(lines)
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    reader.join(5)
    out = "".join(lines)
    assert proc.returncode == 0, out
    assert (sd / "state.json").exists(), out
