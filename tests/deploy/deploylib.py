"""Helpers of the deployment tests (a uniquely named module: importable from any test layout).

They run the real service as the deployment runs it: ``thermal-edge run --config edge.yaml`` in
its own process, against the inverter emulator (``python -m thermal_edge.sim.inverter``) in a
second process, the two on a python-can ``udp_multicast`` bus (hop limit 0: nothing leaves this
host) -- the topology of ``deploy/compose.yaml``. Where multicast loopback is not available the
single-process ``thermal-edge demo`` (service + simulated machine on a virtual bus) stands in.
"""
from __future__ import annotations

import contextlib
import fnmatch
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from own_ports import own_tcp_port, own_udp_port

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"
EDGE_YAML = REPO / "config" / "edge.yaml"
MODEL = REPO / "config" / "machines" / "pm10kw.yaml"
CYCLE = REPO / "config" / "cycles" / "overload.yaml"
DBC = REPO / "dbc" / "thermal_edge.dbc"
PY = sys.executable
BIN = Path(sys.executable).parent

#: metrics the PromQL of the dashboard/alerts may use although the service does not expose them
PROMETHEUS_SYNTHETIC = {"up", "scrape_duration_seconds", "scrape_samples_scraped"}


def env(**extra: str) -> dict[str, str]:
    e = dict(os.environ)
    e.update({"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"})
    for k in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID", "STATE_DIRECTORY", "INVOCATION_ID"):
        e.pop(k, None)
    e.update(extra)
    return e


def thermal_edge_cmd() -> list[str]:
    exe = BIN / "thermal-edge"
    return [str(exe)] if exe.exists() else [PY, "-m", "thermal_edge.cli"]


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 for a server this test starts, no other process's while this one runs."""
    return own_tcp_port()


def free_udp_port() -> int:
    """A UDP port for this test's ``udp_multicast`` buses, no other process's while this one runs."""
    return own_udp_port()


def udp_multicast_works(port: int) -> str | None:
    """None if python-can's udp_multicast loops back on this host, else why not."""
    code = (
        "import can,sys\nfrom can.interfaces.udp_multicast import UdpMulticastBus as U\n"
        f"a=can.Bus(interface='udp_multicast',channel=U.DEFAULT_GROUP_IPv6,port={port},hop_limit=0)\n"
        f"b=can.Bus(interface='udp_multicast',channel=U.DEFAULT_GROUP_IPv6,port={port},hop_limit=0)\n"
        "a.send(can.Message(arbitration_id=0x7FF,data=b'probe',is_extended_id=False))\n"
        "m=b.recv(2.0)\na.shutdown();b.shutdown()\n"
        "sys.exit(0 if m is not None and m.arbitration_id==0x7FF else 3)\n"
    )
    try:
        r = subprocess.run([PY, "-c", code], env=env(), capture_output=True, text=True, timeout=30)
    except subprocess.TimeoutExpired:
        return "probe timed out"
    return None if r.returncode == 0 else (r.stderr.strip().splitlines() or [f"exit {r.returncode}"])[-1]


def service_config(state_dir: Path, *, bus: dict[str, Any], metrics_port: int | None, clock: str = "frame",
                   **sections: Any) -> dict[str, Any]:
    """The shipped ``config/edge.yaml`` with the test's bus, clock, metrics port and state dir."""
    raw = yaml.safe_load(EDGE_YAML.read_text())
    raw["bus"] = dict(bus)
    raw["codec"] = {**(raw.get("codec") or {}), "dbc": str(DBC)}
    if clock == "frame":
        raw["codec"]["resync_after_cycles"] = 1000
    raw["model"] = {**(raw.get("model") or {}), "path": str(MODEL)}
    raw["clock"] = {**(raw.get("clock") or {}), "mode": clock}
    raw["metrics"] = {"enabled": metrics_port is not None, "address": "127.0.0.1", "port": metrics_port or 0}
    raw["state"] = {**(raw.get("state") or {}), "dir": str(state_dir)}
    raw["recording"] = {"candump": None}
    if clock == "frame":  # accelerated: frames 5x coarser than the DBC's cycle
        raw["timeouts"] = {k: max(float(v), 2.0) for k, v in (raw.get("timeouts") or {}).items()}
        raw.setdefault("transmit", {})["bus_silence_s"] = 2.0
    for k, v in sections.items():
        raw[k] = {**raw[k], **v} if isinstance(v, dict) and isinstance(raw.get(k), dict) else v
    return raw


def write_yaml(path: Path, raw: dict[str, Any]) -> Path:
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def scrape(url: str, timeout: float = 5.0) -> str:
    with urllib.request.urlopen(url, timeout=timeout) as r:  # a local test URL
        return r.read().decode()


# ---------------------------------------------------------------------------------------------
# exposition parsing
_SAMPLE = re.compile(r"^([a-zA-Z_:][a-zA-Z0-9_:]*)(\{[^}]*\})?\s+(\S+)")


def exposed_names(text: str) -> set[str]:
    """Every metric name of an exposition: # TYPE names and sample names (incl. _bucket, _total)."""
    names: set[str] = set()
    for line in text.splitlines():
        if line.startswith("# TYPE ") or line.startswith("# HELP "):
            names.add(line.split()[2])
        elif line and not line.startswith("#"):
            m = _SAMPLE.match(line)
            if m:
                names.add(m.group(1))
    return names


def sample_value(text: str, name: str, labels: str | None = None) -> float | None:
    for line in text.splitlines():
        m = _SAMPLE.match(line)
        if m and m.group(1) == name and (labels is None or (m.group(2) or "").find(labels) >= 0):
            try:
                return float(m.group(3))
            except ValueError:
                return None
    return None


# ---------------------------------------------------------------------------------------------
# PromQL -> metric names
PROMQL_KEYWORDS = {
    "by", "without", "on", "ignoring", "group_left", "group_right", "bool", "and", "or", "unless", "offset",
    "inf", "nan", "atan2", "sum", "min", "max", "avg", "count", "stddev", "stdvar", "topk", "bottomk",
    "quantile", "count_values", "group", "limitk", "limit_ratio",
}


def promql_metric_names(expr: str) -> set[str]:
    """Metric names a PromQL expression reads (functions, keywords, labels and variables stripped)."""
    s = re.sub(r'"(?:[^"\\]|\\.)*"|\'(?:[^\'\\]|\\.)*\'|`[^`]*`', '""', expr)  # strings
    s = re.sub(r"\$\{[^}]*\}|\$\w+|\[\[[^\]]*\]\]", "1", s)  # Grafana variables
    s = re.sub(r"\{[^}]*\}", "", s)  # label matchers
    s = re.sub(r"\[[^\]]*\]", "", s)  # range / subquery selectors
    s = re.sub(r"\b(by|without|on|ignoring|group_left|group_right)\s*\([^)]*\)", " ", s)  # label lists
    s = re.sub(r"\boffset\s+-?\d+\w*", " ", s)
    names = set()
    for m in re.finditer(r"(?<![\w.])([a-zA-Z_:][a-zA-Z0-9_:]*)(\s*\()?", s):
        word, call = m.group(1), m.group(2)
        if call or word.lower() in PROMQL_KEYWORDS or re.fullmatch(r"\d.*", word):
            continue
        if re.fullmatch(r"[eE]\d*|\d+[smhdwy]", word):
            continue
        names.add(word)
    return names


def missing_metrics(names: set[str], exposed: set[str]) -> set[str]:
    """Names neither exposed nor histogram/summary/counter parts of an exposed family."""
    out = set()
    for n in names:
        if n in exposed or n in PROMETHEUS_SYNTHETIC:
            continue
        base = re.sub(r"_(bucket|sum|count)$", "", n)
        if base in exposed:
            continue
        out.add(n)
    return out


# ---------------------------------------------------------------------------------------------
# the running service
@dataclass
class LiveService:
    url: str
    mode: str  # "run+emulator" or "demo"
    procs: list[subprocess.Popen[str]] = field(default_factory=list)
    logs: list[Path] = field(default_factory=list)

    def log_tail(self, n: int = 40) -> str:
        out = []
        for p in self.logs:
            if p.exists():
                lines = p.read_text(errors="replace").splitlines()[-n:]
                out.append(f"--- {p.name}\n" + "\n".join(lines))
        return "\n".join(out)


def _stop(procs: list[subprocess.Popen[str]]) -> None:
    for p in reversed(procs):
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    for p in reversed(procs):
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout=5)


def wait_metrics(svc: LiveService, ready: Any, timeout: float = 90.0) -> str:
    """Scrape until ``ready(text)`` is true; returns the last scrape."""
    deadline = time.monotonic() + timeout
    last = ""
    while time.monotonic() < deadline:
        for p in svc.procs:
            if p.poll() is not None:
                raise RuntimeError(f"{p.args!r} exited with {p.returncode}\n{svc.log_tail()}")
        try:
            last = scrape(svc.url)
            if ready(last):
                return last
        except OSError:
            pass
        time.sleep(0.5)
    raise TimeoutError(f"service at {svc.url} not ready within {timeout:.0f} s\n{svc.log_tail()}")


def compose_topology(workdir: Path, metrics_port: int, udp_port: int) -> tuple[Path, list[str]]:
    """deploy/compose.yaml's thermal-edge and simulated-machine, outside containers: the service's
    config (deploy/compose/edge-sim.yaml) and the machine's command line, with the state directory,
    a free metrics port and a free udp_multicast port (model and cycle are packaged ones, by name)."""
    compose = yaml.safe_load((DEPLOY / "compose.yaml").read_text())
    svc, sim = compose["services"]["thermal-edge"], compose["services"]["simulated-machine"]
    cfg_in_image = svc["command"][svc["command"].index("--config") + 1]
    src = next(v.split(":")[0] for v in svc["volumes"] if v.split(":")[1] == cfg_in_image)
    raw = yaml.safe_load((DEPLOY / src).read_text())
    raw["bus"] = {**raw["bus"], "port": udp_port}
    raw["metrics"] = {**raw["metrics"], "port": metrics_port}
    state = workdir / "state"
    state.mkdir(exist_ok=True)
    raw["state"]["dir"] = str(state)
    cfg = write_yaml(workdir / "edge-sim.yaml", raw)
    entry = list(sim["entrypoint"])
    assert entry[0] == "python"
    argv = [PY, *entry[1:]]
    argv += sim["command"]
    argv.append(f"--port={udp_port}")
    return cfg, argv


@contextlib.contextmanager
def live_service(workdir: Path, *, force_demo: bool = False) -> Iterator[LiveService]:
    """The service against the simulated machine, metrics on a free port of 127.0.0.1: the compose
    demo's two processes (``thermal-edge run`` + the inverter emulator on udp_multicast), or
    ``thermal-edge demo`` where multicast loopback is unavailable."""
    workdir.mkdir(parents=True, exist_ok=True)
    port = free_tcp_port()
    url = f"http://127.0.0.1:{port}/metrics"
    udp_port = free_udp_port()
    why = "forced" if force_demo else udp_multicast_works(udp_port)
    procs: list[subprocess.Popen[str]] = []
    logs: list[Path] = []
    try:
        if why is None:
            cfg, sim_argv = compose_topology(workdir, port, udp_port)
            log_s, log_e = workdir / "service.log", workdir / "emulator.log"
            logs += [log_s, log_e]
            procs.append(subprocess.Popen([*thermal_edge_cmd(), "run", "--config", str(cfg)], env=env(),
                                          stdout=log_s.open("w"), stderr=subprocess.STDOUT, text=True))
            svc = LiveService(url, "compose topology: run + emulator", procs, logs)
            # compose starts the machine once the service is healthy (its metrics answer)
            wait_metrics(svc, lambda t: "thermal_edge_build_info" in t, timeout=60)
            procs.append(subprocess.Popen(sim_argv, env=env(), stdout=log_e.open("w"), stderr=subprocess.STDOUT, text=True))
        else:
            log_d = workdir / "demo.log"
            logs.append(log_d)
            procs.append(subprocess.Popen(
                [*thermal_edge_cmd(), "demo", "--metrics-port", str(port), "--speed", "30", "--quiet",
                 "--state-dir", str(workdir / "state")],
                env=env(), stdout=log_d.open("w"), stderr=subprocess.STDOUT, text=True))
            svc = LiveService(url, f"demo ({why})", procs, logs)
        yield svc
    finally:
        _stop(procs)


def ready_for_docs(text: str, min_ticks: float = 20.0) -> bool:
    """Ticks running with frames received and the conditional families present."""
    ticks = sample_value(text, "thermal_edge_ticks_total") or 0.0
    rx = sample_value(text, "thermal_edge_frames_received_total") or 0.0
    names = exposed_names(text)
    return (ticks >= min_ticks and rx > 0 and "thermal_edge_prediction_error_rms_celsius" in names
            and "thermal_edge_lookahead_current_amperes" in names)


def dockerignore_patterns() -> list[tuple[bool, str]]:
    pats = []
    for line in (REPO / ".dockerignore").read_text().splitlines():
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        neg = s.startswith("!")
        pats.append((neg, s[1:] if neg else s))
    return pats


def ignored(rel: str, pats: list[tuple[bool, str]]) -> bool:
    """Docker's rule: the last matching pattern wins; a pattern matching a parent directory matches."""
    parts = rel.split("/")
    result = False
    for neg, pat in pats:
        pat = pat.rstrip("/")
        cands = ["/".join(parts[:i]) for i in range(1, len(parts) + 1)]
        hit = False
        for c in cands:
            if fnmatch.fnmatchcase(c, pat) or (pat.startswith("**/") and fnmatch.fnmatchcase(c.split("/")[-1], pat[3:])):
                hit = True
                break
        if hit:
            result = not neg
    return result


def build_context(dest: Path) -> Path:
    """The files a ``docker build .`` of this repository sees, copied to ``dest``."""
    pats = dockerignore_patterns()
    for root, dirs, files in os.walk(REPO):
        rel_root = Path(root).relative_to(REPO).as_posix()
        dirs[:] = [d for d in dirs if d not in (".git", ".venv", "node_modules")]
        for f in files:
            rel = f if rel_root == "." else f"{rel_root}/{f}"
            if not ignored(rel, pats):
                (dest / rel).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(Path(root) / f, dest / rel)
    return dest


def which(tool: str) -> str | None:
    """A tool on PATH or next to this interpreter (tools pip-installed into the venv)."""
    p = BIN / tool
    return str(p) if p.exists() else shutil.which(tool)
