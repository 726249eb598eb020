"""The README's install steps, followed literally in a scratch directory (without systemd):
a fresh virtual environment, the configuration, ``run --check``, then the installed service
against the simulated machine -- ``thermal-edge demo`` as the README shows it, and the installed
``thermal-edge run`` with the installed inverter emulator as two processes.

Literally means: the README's shell block is run by bash as it stands, except that ``sudo`` is
dropped and ``/opt/thermal-edge`` and ``/etc/thermal-edge`` are moved into the scratch directory.
"""
from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import threading
import time
from pathlib import Path

import deploylib as dl
import pytest
import yaml

README = dl.REPO / "README.md"


def readme_block(marker: str) -> str:
    text = README.read_text(encoding="utf-8")
    i = text.index(f"<!-- {marker}")
    m = re.compile(r"```sh\n(.*?)```", re.S).search(text, i)
    assert m, f"no sh block after <!-- {marker}"
    return m.group(1)


def localise(script: str, root: Path) -> str:
    s = re.sub(r"(^|\|\s*|&&\s*)sudo\s+", r"\1", script, flags=re.M)
    s = s.replace("/opt/thermal-edge", str(root / "opt" / "thermal-edge"))
    return s.replace("/etc/thermal-edge", str(root / "etc" / "thermal-edge"))


def checkout(dest: Path) -> Path:
    """A checkout as the edge computer gets it: what the image's build sees, and the repository's
    ``config`` link to the package data (the install steps copy a model and edge.yaml from it)."""
    src = dl.build_context(dest)
    (src / "config").symlink_to(os.readlink(dl.REPO / "config"))
    return src


def clean_env(root: Path) -> dict[str, str]:
    e = dl.env()
    for k in ("VIRTUAL_ENV", "PYTHONPATH", "PYTHONHOME"):
        e.pop(k, None)
    venv_bin = str(dl.BIN)
    e["PATH"] = os.pathsep.join(p for p in e.get("PATH", "").split(os.pathsep) if p and p != venv_bin)
    e["HOME"] = str(root / "home")
    e["PIP_CACHE_DIR"] = os.environ.get("PIP_CACHE_DIR", str(Path.home() / ".cache" / "pip"))
    return e


def python3_ok(env: dict[str, str]) -> str | None:
    exe = shutil.which("python3", path=env["PATH"])
    if exe is None:
        return "no python3 on PATH"
    r = subprocess.run([exe, "-c", "import sys, venv, ensurepip; sys.exit(sys.version_info < (3, 11))"], capture_output=True,
                       env=env)
    return None if r.returncode == 0 else f"{exe}: Python ≥ 3.11 with venv/ensurepip needed"


@pytest.mark.slow
@pytest.mark.timeout(1500)
def test_readme_install_steps_then_service_against_the_simulated_machine(tmp_path: Path) -> None:
    root = tmp_path / "root"
    (root / "home").mkdir(parents=True)
    src = checkout(tmp_path / "checkout")
    env = clean_env(root)
    why = python3_ok(env)
    if why:
        pytest.skip(why)

    # ---- the install block, literally
    script = localise(readme_block("install-steps"), root)
    t0 = time.monotonic()
    r = subprocess.run(["bash", "-euo", "pipefail", "-c", script], cwd=src, env=env, capture_output=True, text=True,
                       timeout=1200)
    print(f"install steps: {time.monotonic() - t0:.0f} s, exit {r.returncode}")
    assert r.returncode == 0, f"install steps failed:\n{script}\n--- stdout\n{r.stdout[-3000:]}\n--- stderr\n{r.stderr[-5000:]}"
    assert re.search(r"edge\.yaml: ok \(model pm10kw, \d+ nodes, bus socketcan\)", r.stdout), r.stdout
    venv = root / "opt" / "thermal-edge"
    etc = root / "etc" / "thermal-edge"
    assert (venv / "bin" / "thermal-edge").exists()
    assert (etc / "edge.yaml").exists() and (etc / "machines" / "pm10kw.yaml").exists()
    # the file the unit's Documentation= names, from the installed package (a wheel has no checkout)
    assert (venv / "share" / "thermal-edge" / "README.md").read_text(encoding="utf-8") == README.read_text(encoding="utf-8")
    # the configuration runs the installed copy of the model, the one the user edits
    assert yaml.safe_load((etc / "edge.yaml").read_text())["model"]["path"] == "machines/pm10kw.yaml"
    # installed from the checkout, not the repository's editable install
    where = subprocess.run([str(venv / "bin" / "python"), "-c", "import thermal_edge; print(thermal_edge.__file__)"],
                           capture_output=True, text=True, env=env, cwd=tmp_path).stdout.strip()
    assert where.startswith(str(venv)), where

    # ---- "Try it without CAN hardware": the demo block, literally
    demo = localise(readme_block("demo-steps"), root).strip()
    proc = subprocess.Popen(["bash", "-c", f"exec {demo}"], cwd=src, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, start_new_session=True)
    lines: list[str] = []
    status: list[str] = []

    def reader() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line.rstrip("\n"))

    th = threading.Thread(target=reader, daemon=True)
    th.start()
    try:
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline and proc.poll() is None:
            status = [l for l in list(lines) if re.search(r"hot spot .*limit .* A .*reason", l)]
            if len(status) >= 8:
                break
            time.sleep(0.2)
        assert proc.poll() is None, "demo exited early:\n" + "\n".join(lines[-30:])
        os.killpg(proc.pid, signal.SIGINT)
        proc.wait(timeout=60)
        th.join(timeout=10)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    out = "\n".join(lines)
    print("\n".join(lines[:3] + status[-3:] + lines[-2:]))
    m = re.search(r"state: (\S+)", out)  # the demo's own temporary state directory: gone after the demo
    assert m and Path(m.group(1)).name.startswith("thermal-edge-demo-"), out[:2000]
    assert not Path(m.group(1)).exists(), f"make demo left {m.group(1)} behind"
    assert len(status) >= 8, out[-3000:]
    assert any(l.startswith("metrics:") for l in lines), out[:2000]
    assert proc.returncode == 0, out[-3000:]
    assert re.search(r"^done: .* simulated", out, re.M), out[-2000:]


@pytest.mark.slow
@pytest.mark.timeout(1500)
def test_installed_run_with_installed_emulator(tmp_path: Path) -> None:
    """``thermal-edge run`` and ``python -m thermal_edge.sim.inverter`` from a README install, as two
    processes on a udp_multicast bus (the compose demo's topology; vcan0 on a bench)."""
    root = tmp_path / "root"
    (root / "home").mkdir(parents=True)
    src = checkout(tmp_path / "checkout")
    env = clean_env(root)
    why = python3_ok(env)
    if why:
        pytest.skip(why)
    udp_port = dl.free_udp_port()
    if dl.udp_multicast_works(udp_port):
        pytest.skip("udp_multicast loopback not available here")
    r = subprocess.run(["bash", "-euo", "pipefail", "-c", localise(readme_block("install-steps"), root)], cwd=src, env=env,
                       capture_output=True, text=True, timeout=1200)
    assert r.returncode == 0, r.stderr[-4000:]
    venv, etc = root / "opt" / "thermal-edge", root / "etc" / "thermal-edge"
    raw = yaml.safe_load((etc / "edge.yaml").read_text())
    port = dl.free_tcp_port()
    state = tmp_path / "state"
    state.mkdir()
    raw["bus"] = {"interface": "udp_multicast", "port": udp_port, "preserve_timestamps": True}
    raw["clock"]["mode"] = "frame"
    raw["codec"]["resync_after_cycles"] = 1000
    raw["metrics"] = {"enabled": True, "address": "127.0.0.1", "port": port}
    raw["state"]["dir"] = str(state)
    cfg = dl.write_yaml(etc / "edge-bench.yaml", raw)  # beside edge.yaml: machines/ resolves the same
    log_s, log_e = tmp_path / "service.log", tmp_path / "emulator.log"
    svc = subprocess.Popen([str(venv / "bin" / "thermal-edge"), "run", "--config", str(cfg)], env=env, cwd=tmp_path,
                           stdout=log_s.open("w"), stderr=subprocess.STDOUT)
    procs = [svc]
    live = dl.LiveService(f"http://127.0.0.1:{port}/metrics", "installed", procs, [log_s, log_e])
    try:
        dl.wait_metrics(live, lambda t: "thermal_edge_build_info" in t, timeout=90)
        procs.append(subprocess.Popen(
            [str(venv / "bin" / "python"), "-m", "thermal_edge.sim.inverter", "--interface", "udp_multicast", "--port",
             str(udp_port), "--model", str(etc / "machines" / "pm10kw.yaml"), "--cycle", "overload",
             "--speed", "30", "--current-period", "0.05"], env=env, cwd=src, stdout=log_e.open("w"), stderr=subprocess.STDOUT))
        text = dl.wait_metrics(live, lambda t: (dl.sample_value(t, "thermal_edge_ticks_total") or 0) >= 30, timeout=120)
    finally:
        dl._stop(procs)
    rx = sum(float(v) for v in re.findall(r'^thermal_edge_frames_received_total\{frame="INV_\w+"\} (\S+)$', text, re.M))
    assert rx > 100, text[:3000]
    assert (dl.sample_value(text, "thermal_edge_frames_dropped_total") or 0) == 0
    assert svc.returncode == 0, log_s.read_text()[-3000:]
    assert (state / "state.json").exists()
