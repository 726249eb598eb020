"""The fault bench's test bed: the service as a black box in a process of its own (``thermal-edge
run``), on a ``udp_multicast`` group and port of its own (hop limit 0), with an independent
``TE_Limits`` monitor process, an inverter of the bench's own making and the safety checks.

A check counts *unsafe events*: a ``TE_Limits`` gap over 300 ms while the process lives,
a limit above the maximum, above the safe limit while an input is stale or a required sensor
faulty, above the derating band at the measured winding temperature, and a crash.
"""
from __future__ import annotations

import contextlib
import os
import random
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Self

import yaml

from thermal_edge.shipped import MACHINES, config_path, find

from .. import ROOT
from . import wire

GAP_S = 0.3  # the inverter drops TE_Limits after this long
#: a TE_Limits gap longer than this is an unsafe event; one between GAP_S and it, a target missed. The
#: bench judges by the contract (GAP_S); the test suite, on a shared host busy with other work, raises
#: it to a generous guard: there a gap just past GAP_S measures the host's load as much as the service,
#: a silence of seconds is still the service's
GAP_UNSAFE_S = GAP_S
RESOLUTION_A = 0.05  # TE_CurrentLimit's factor: a limit equal to a bound may read one step above
#: how long a start may take before the service counts as not starting, s: a generous hang guard (a
#: host busy with other work starts a Python process in tens of seconds)
START_TIMEOUT_S = 300.0


#: environment variable: run the service from another source tree (e.g. an export of an older
#: commit, to compare), with that tree's ``config/``; the bench's own processes still run from this one
SERVICE_TREE_ENV = "THERMAL_EDGE_FAULTS_SERVICE_TREE"


def service_config_path(*parts: str) -> Path:
    """A file under the ``config/`` directory of the service's source tree."""
    tree = os.environ.get(SERVICE_TREE_ENV)
    return Path(tree).joinpath("config", *parts) if tree else config_path(*parts)


def service_model_path() -> Path:
    """The model file the service's ``edge.yaml`` names: a path relative to that file, or the name
    of a packaged model."""
    edge = service_config_path("edge.yaml")
    ref = yaml.safe_load(edge.read_text())["model"]["path"]
    found = find(MACHINES, ref, base=edge.parent)
    if found is None:
        raise RuntimeError(f"{edge}: model.path {ref!r} is neither a file nor a packaged model")
    return found


def _edge() -> dict[str, Any]:
    """The shipped ``config/edge.yaml``: the limits every check compares against come from it."""
    return yaml.safe_load(service_config_path("edge.yaml").read_text())


EDGE = _edge()
MAX_A = float(EDGE["derating"]["max_current_a"])
MAX_NM = float(EDGE["derating"]["max_torque_nm"])
KT_NM_PER_A = float(EDGE["derating"]["kt_nm_per_arms"])
SAFE_A = float(EDGE["derating"]["safe_current_a"])
TIMEOUTS_S = {k: float(v) for k, v in EDGE["timeouts"].items()}
TICK_S = float(EDGE["clock"]["tick_s"])
HOT_SPOT_BAND = (float(EDGE["derating"]["limits"]["hot_spot"]["warn_c"]), float(EDGE["derating"]["limits"]["hot_spot"]["max_c"]))


def band_limit_a(winding_c: float) -> float:
    """Largest current the configured hot-spot band allows when the hot spot is at ``winding_c``
    (degC): full current up to the warning temperature, linearly down to zero at the maximum. A
    measured winding temperature is a lower bound of the hot spot, so this bounds the limit."""
    warn, top = HOT_SPOT_BAND
    return MAX_A * min(1.0, max(0.0, (top - winding_c) / (top - warn)))


def unit_memory_max_bytes() -> int:
    """``MemoryMax=`` of the shipped systemd unit, bytes."""
    text = (ROOT / "deploy" / "systemd" / "thermal-edge.service").read_text()
    m = re.search(r"^MemoryMax=(\d+)([KMG]?)\s*$", text, re.MULTILINE)
    if not m:
        raise RuntimeError("deploy/systemd/thermal-edge.service has no MemoryMax=")
    return int(m.group(1)) * {"": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30}[m.group(2)]


def env(service: bool = False) -> dict[str, str]:
    """Environment of the bench's processes: one BLAS thread, no systemd variables."""
    e = dict(os.environ)
    e.update(OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    tree = e.pop(SERVICE_TREE_ENV, None) if service else None
    e["PYTHONPATH"] = (tree or str(ROOT)) + os.pathsep + e.get("PYTHONPATH", "")
    for k in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "JOURNAL_STREAM"):
        e.pop(k, None)
    return e


def thermal_edge_cmd() -> list[str]:
    """The installed ``thermal-edge`` command of this interpreter's environment."""
    exe = Path(sys.executable).with_name("thermal-edge")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "thermal_edge.cli"]


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def unique_group() -> str:
    """An administratively scoped IPv4 multicast group of this run (239/8; Linux's loopback carries
    IPv4 multicast, and hop limit 0 keeps it on the host)."""
    return f"239.{random.randint(1, 254)}.{random.randint(0, 255)}.{random.randint(1, 254)}"


def edge_config(state_dir: Path, group: str, port: int, *, clock: str = "wall", adapt: bool = False,
                **sections: Any) -> dict[str, Any]:
    """``config/edge.yaml`` for one bench run: this run's bus, metrics on 127.0.0.1 (a free port),
    state in ``state_dir``; ``sections`` replace keys of a section (or a whole value)."""
    raw = _edge()
    raw["bus"] = {"interface": "udp_multicast", "channel": group, "port": port}
    if clock == "frame":
        raw["bus"]["preserve_timestamps"] = True
    raw["codec"]["dbc"] = str(wire.DBC)
    raw["model"]["path"] = str(service_config_path("machines", "pm10kw.yaml"))
    raw["clock"]["mode"] = clock
    raw["adaptation"]["enabled"] = adapt
    raw["metrics"] = {"enabled": True, "address": "127.0.0.1", "port": 0}
    raw["state"]["dir"] = str(state_dir)
    raw["recording"] = {"candump": None}
    for k, v in sections.items():
        raw[k] = {**raw[k], **v} if isinstance(v, dict) and isinstance(raw.get(k), dict) else v
    return raw


# ----------------------------------------------------------------------------------------------
@dataclass
class Limits:
    """``TE_Limits`` as the monitor received them (arrays in arrival order)."""

    t: list[float] = field(default_factory=list)  # kernel receive time, s since the epoch
    current: list[float] = field(default_factory=list)  # A rms
    torque: list[float] = field(default_factory=list)  # Nm
    reason: list[int] = field(default_factory=list)
    crc_ok: list[int] = field(default_factory=list)



class Monitor:
    """The independent ``TE_Limits`` receiver (:func:`wire.monitor` in a process of its own)."""

    def __init__(self, group: str, port: int, workdir: Path) -> None:
        self.path = workdir / f"limits-{port}.txt"
        self.proc = subprocess.Popen([sys.executable, "-m", "benchmarks.faults.wire", "monitor", "--group", group,
                                      "--port", str(port), "--out", str(self.path)], env=env(), cwd=str(ROOT),
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self._pos = 0
        self.limits = Limits()
        deadline = time.monotonic() + START_TIMEOUT_S  # a hang guard: a busy host starts it late
        while time.monotonic() < deadline and not (self.path.exists() and self.path.read_text().startswith("ready")):
            time.sleep(0.02)

    def read(self) -> Limits:
        """Everything received so far."""
        with open(self.path) as fh:
            fh.seek(self._pos)
            chunk = fh.read()
        end = chunk.rfind("\n") + 1
        self._pos += len(chunk[:end].encode())
        for line in chunk[:end].splitlines():
            p = line.split()
            if len(p) != 7:
                continue
            self.limits.t.append(float(p[0]))
            self.limits.current.append(float(p[1]))
            self.limits.torque.append(float(p[2]))
            self.limits.reason.append(int(p[3]))
            self.limits.crc_ok.append(int(p[6]))
        return self.limits

    def first_after(self, t0: float, timeout: float) -> float | None:
        """Receive time of the first ``TE_Limits`` after ``t0`` (None if none within ``timeout`` s)."""
        deadline = time.monotonic() + timeout
        while True:
            lim = self.read()
            got = next((t for t in reversed(lim.t) if t >= t0), None)
            if got is not None:
                return min(t for t in lim.t if t >= t0)
            if time.monotonic() > deadline:
                return None
            time.sleep(0.02)

    def close(self) -> None:
        self.proc.kill()
        self.proc.wait()


class Service:
    """``thermal-edge run --config`` as a subprocess; its log in ``workdir``."""

    def __init__(self, raw: dict[str, Any], workdir: Path, name: str = "svc") -> None:
        self.workdir = workdir
        self.config = workdir / f"{name}.yaml"
        self.config.write_text(yaml.safe_dump(raw, sort_keys=False))
        self.log = workdir / f"{name}.log"
        self.proc: subprocess.Popen[bytes] | None = None
        self.started = 0.0
        self.metrics_port: int | None = None
        self.peak_rss = 0  # bytes, sampled every 20 ms while it runs
        self.oom_killed = False
        self.cpu_samples: list[tuple[float, float]] = []  # (wall time, CPU time used), every 20 ms

    def start(self) -> None:
        """Spawn the service; a thread samples its resident memory every 20 ms and kills it above
        the unit's ``MemoryMax`` as systemd would (:attr:`oom_killed`), so a runaway load cannot
        take the host down."""
        self.metrics_port = None
        self.oom_killed = False
        with open(self.log, "ab") as out:
            self.started = time.time()
            self.proc = subprocess.Popen(thermal_edge_cmd() + ["run", "--config", str(self.config), "--log-level", "info"],
                                         cwd=str(self.workdir), env=env(service=True), stdout=out, stderr=subprocess.STDOUT)
        threading.Thread(target=self._watch_memory, args=(self.proc, unit_memory_max_bytes()), daemon=True).start()

    def _watch_memory(self, proc: subprocess.Popen[bytes], cap: int) -> None:
        tick = os.sysconf("SC_CLK_TCK")
        while proc.poll() is None:
            rss = self.rss()
            self.peak_rss = max(self.peak_rss, rss)
            if rss > cap:
                self.oom_killed = True
                proc.kill()
                return
            with contextlib.suppress(OSError, ValueError, IndexError):
                fields = Path(f"/proc/{proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
                self.cpu_samples.append((time.time(), (int(fields[11]) + int(fields[12])) / tick))
            time.sleep(0.02)

    def cpu_at(self, t: float) -> float:
        """CPU time (user + system, s) the service had used at wall time ``t``: a start-up measure
        that other processes on a shared machine barely disturb, unlike wall time."""
        return max((c for w, c in self.cpu_samples if w <= t), default=0.0)

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def log_text(self) -> str:
        return self.log.read_text(errors="replace") if self.log.exists() else ""

    def tracebacks(self) -> int:
        return self.log_text().count("Traceback (most recent call last)")

    def wait_metrics(self, timeout: float = START_TIMEOUT_S) -> int | None:
        """The metrics port the service logged (None if it did not within ``timeout``)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and self.alive():
            m = re.search(r"metrics on http://127\.0\.0\.1:(\d+)/metrics", self.log_text())
            if m:
                self.metrics_port = int(m.group(1))
                return self.metrics_port
            time.sleep(0.05)
        return None

    def metrics(self) -> dict[str, float]:
        """``/metrics`` as {sample name with labels: value} (empty if unreachable)."""
        from prometheus_client.parser import text_string_to_metric_families

        if self.metrics_port is None:
            return {}
        try:
            # a generous time-out: a scrape answered late on a busy host is answered
            text = urllib.request.urlopen(f"http://127.0.0.1:{self.metrics_port}/metrics", timeout=30).read().decode()
        except OSError:
            return {}
        out: dict[str, float] = {}
        for fam in text_string_to_metric_families(text):
            for s in fam.samples:
                key = s.name + ("{" + ",".join(f'{k}="{v}"' for k, v in sorted(s.labels.items())) + "}" if s.labels else "")
                out[key] = s.value
        return out

    def rss(self) -> int:
        with contextlib.suppress(OSError):
            for line in Path(f"/proc/{self.pid}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
        return 0

    def catches(self, sig: int, timeout: float = START_TIMEOUT_S) -> bool:
        """Wait until the process has a handler for ``sig`` (``SigCgt`` in ``/proc/<pid>/status``);
        False if it exits or ``timeout`` passes first."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and self.alive():
            try:
                status = Path(f"/proc/{self.pid}/status").read_text()
            except OSError:
                return False
            caught = next((int(ln.split()[1], 16) for ln in status.splitlines() if ln.startswith("SigCgt:")), 0)
            if caught >> (sig - 1) & 1:
                return True
            time.sleep(0.002)
        return False

    def kill(self, sig: int = signal.SIGKILL) -> None:
        if self.alive():
            assert self.proc is not None
            self.proc.send_signal(sig)

    def stop(self, timeout: float = 20.0, sig: int = signal.SIGTERM) -> int | None:
        """``sig`` (a stop signal), then SIGKILL after ``timeout``; the exit code."""
        if self.proc is None:
            return None
        if self.alive():
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode


def metric(m: dict[str, float], name: str) -> float:
    """Sum of a metric over its labels."""
    return sum(v for k, v in m.items() if k == name or k.startswith(name + "{"))


def histogram_quantile(m: dict[str, float], name: str, q: float, since: dict[str, float] | None = None) -> float:
    """Quantile ``q`` of a Prometheus histogram from its buckets (upper bound of the bucket holding
    it), of the observations after the scrape ``since`` if given; s."""
    base = since or {}
    buckets = sorted((float(re.search(r'le="([^"]+)"', k).group(1)), v - base.get(k, 0.0))  # type: ignore[union-attr]
                     for k, v in m.items() if k.startswith(name + "_bucket{"))
    if not buckets or buckets[-1][1] == 0:
        return float("nan")
    want = q * buckets[-1][1]
    return next(le for le, c in buckets if c >= want)


# ----------------------------------------------------------------------------------------------
class Inverter:
    """The inverter's four frames at their DBC cycles in a thread (wall clock), every field settable
    while it runs: signals, paused or frozen frames, raw payload overrides, counters skipped or
    repeated."""

    def __init__(self, group: str, port: int) -> None:
        self.group, self.port = group, port
        self.sock = wire.sender_socket(group)
        self.signals = wire.idle_signals()
        self.paused: set[str] = set()
        #: frames resent unchanged at their cycle, alive counter frozen (a hung inverter task)
        self.frozen: set[str] = set()
        self.sent = dict.fromkeys(wire.INPUT_FRAMES, 0)
        self.counters = dict.fromkeys(wire.INPUT_FRAMES, 0)
        self.ids = {n: wire.frame_id(n) for n in wire.INPUT_FRAMES}
        #: per frame: when (``time.monotonic``) the first regular frame after the last :meth:`burst` left
        #: (None until it has)
        self.resumed_at: dict[str, float | None] = {}
        self.lock = threading.Lock()
        self._stop = threading.Event()
        self._hold = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def start(self) -> Self:
        self._thread.start()
        return self

    def _send(self, name: str) -> None:
        with self.lock:
            self._send_locked(name)
            if name in self.resumed_at and self.resumed_at[name] is None:
                self.resumed_at[name] = time.monotonic()

    def _send_locked(self, name: str) -> None:
        k = self.counters[name]
        self.counters[name] = (k + 1) % 16
        data = wire.encode(name, self.signals[name], k)
        self.sock.sendto(wire.datagram(self.ids[name], data), (self.group, self.port))
        self.sent[name] += 1

    def _loop(self) -> None:
        t0 = time.monotonic()
        n = 0
        while not self._stop.is_set():
            if not self._hold.is_set():
                for name in ("INV_Currents", "INV_Mechanics") + (("INV_StatorTemps", "INV_AmbientTemps") if n % 10 == 0 else ()):
                    if name in self.frozen:
                        self.repeat_last(name)
                    elif name not in self.paused:
                        self._send(name)
            n += 1
            time.sleep(max(0.0, t0 + n * 0.01 - time.monotonic()))

    def skip(self, name: str, count: int) -> None:
        """Leave out ``count`` frames of ``name`` (a real loss the receiver can count): a frame, the
        hole, the next frame at once, so that the hole is judged by the counter and not taken for
        a long pause (the thread may be late on a busy machine)."""
        with self.lock:
            self._send_locked(name)
            self.counters[name] = (self.counters[name] + count) % 16
            self._send_locked(name)

    def repeat_last(self, name: str) -> None:
        """Send the last frame of ``name`` again, counter unchanged."""
        with self.lock:
            k = (self.counters[name] - 1) % 16
            data = wire.encode(name, self.signals[name], k)
            self.sock.sendto(wire.datagram(self.ids[name], data), (self.group, self.port))

    def burst(self, name: str, signals: dict[str, float], n: int) -> None:
        """``n`` frames of ``name`` with ``signals`` at once, counters continuing (valid frames,
        far above their cycle); the regular signals after them."""
        with self.lock:
            regular = self.signals[name]
            self.signals[name] = signals
            try:
                for _ in range(n):
                    self._send_locked(name)
            finally:
                self.signals[name] = regular
                self.resumed_at[name] = None

    def inject(self, payload: bytes) -> None:
        self.sock.sendto(payload, (self.group, self.port))

    @contextlib.contextmanager
    def held(self) -> Iterator[dict[str, int]]:
        """Stop sending for a moment (well below the shortest timeout) and yield the counts sent, so
        that a scrape meanwhile compares with frames all delivered."""
        self._hold.set()
        time.sleep(0.06)
        with self.lock:
            counts = dict(self.sent)
        try:
            yield counts
        finally:
            self._hold.clear()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.sock.close()


def received(m: dict[str, float]) -> dict[str, float]:
    return {n: m.get(f'thermal_edge_frames_received_total{{frame="{n}"}}', 0.0) for n in wire.INPUT_FRAMES}


# ----------------------------------------------------------------------------------------------
@dataclass
class Bed:
    """One service with its own group/port, the monitor and (optionally) the inverter."""

    workdir: Path
    group: str
    port: int
    service: Service
    monitor: Monitor
    inverter: Inverter | None
    #: the last reading of :func:`counts`: frames sent and the service's metrics
    last_counts: tuple[dict[str, int], dict[str, float]] | None = None


#: longest a reading of the service's counters waits for the frames sent since the bed's last reading
#: to be taken in, s: on a host busy with other work they may wait in the receive queue for a while;
#: what is still missing after it is lost
CATCH_UP_S = 10.0


def counts(b: Bed, inverter: Inverter) -> tuple[dict[str, int], dict[str, float]]:
    """Frames ``inverter`` sent and the service's metrics, read while it holds, once the service has
    taken in every valid frame sent since the bed's last reading (or :data:`CATCH_UP_S` passed)."""
    with inverter.held() as sent:
        m = b.service.metrics()
        if b.last_counts is not None and b.last_counts[1] and m:
            s0, m0 = b.last_counts
            r0 = received(m0)
            deadline = time.monotonic() + CATCH_UP_S
            while (b.service.alive() and time.monotonic() < deadline
                   and any(received(m)[n] - r0[n] < sent[n] - s0[n] for n in wire.INPUT_FRAMES)):
                time.sleep(0.05)
                m = b.service.metrics() or m
        sent = dict(sent)
    b.last_counts = (sent, m)
    return sent, m


@contextlib.contextmanager
def bed(name: str, *, inverter: bool = True, state_dir: Path | None = None, prepare: Any = None,
        **config: Any) -> Iterator[Bed]:
    """A running service (waited for its first ``TE_Limits`` and metrics) on a fresh group and port."""
    workdir = Path(tempfile.mkdtemp(prefix=f"te-faults-{name}-"))
    try:
        group, port = unique_group(), free_port()
        sd = state_dir or workdir / "state"
        raw = edge_config(sd, group, port, **config)
        if prepare is not None:
            prepare(sd)
        mon = Monitor(group, port, workdir)
        inv = Inverter(group, port).start() if inverter else None
        svc = Service(raw, workdir)
        svc.start()
        try:
            if mon.first_after(svc.started, START_TIMEOUT_S) is None:
                raise RuntimeError(f"no TE_Limits within {START_TIMEOUT_S:g} s of the start:\n{svc.log_text()[-1500:]}")
            svc.wait_metrics(5)
            yield Bed(workdir, group, port, svc, mon, inv)
        finally:
            if inv is not None:
                inv.close()
            svc.stop()
            mon.close()
    finally:
        shutil.rmtree(workdir, ignore_errors=True)


def gaps(lim: Limits, t0: float, t1: float, limit_s: float = GAP_S) -> list[float]:
    """``TE_Limits`` gaps longer than ``limit_s`` within [t0, t1] (the ends count: silence from t0
    to the first frame, and from the last one to t1)."""
    ts = [t0] + [t for t in lim.t if t0 <= t <= t1] + [t1]
    return [b - a for a, b in zip(ts, ts[1:]) if b - a > limit_s]


def forced_reasons() -> frozenset[int]:
    """``TE_DerateReason`` values that say the service does not trust its estimate (from the DBC)."""
    choices = wire.dbc().get_message_by_frame_id(wire.TE_LIMITS_ID).get_signal_by_name("TE_DerateReason").choices
    return frozenset(int(k) for k, v in choices.items() if str(v) in ("starting", "model_fault", "stale_input", "sensor_fault"))


def runs_above(lim: Limits, t0: float, t1: float, bound: float, reasons: frozenset[int] | None = None) -> int:
    """Runs of consecutive ``TE_Limits`` in [t0, t1] whose current is above ``bound`` (+ one step);
    with ``reasons``, only frames giving one of those reasons count."""
    runs, inside = 0, False
    for t, c, r in zip(lim.t, lim.current, lim.reason):
        if t0 <= t <= t1:
            above = c > bound + RESOLUTION_A and (reasons is None or r in reasons)
            runs += above and not inside
            inside = above
    return runs


@dataclass
class Check:
    """Unsafe events found by the checks, and what they saw; and performance targets missed.

    An unsafe event breaks a promise the service makes whatever the host's load (a bound of the CAN
    contract, a limit, a crash). A target is a performance figure a loaded host can push past
    without the service being wrong (tick time, a gap tighter than the contract's); it is reported,
    and counted apart.
    """

    unsafe: int = 0
    notes: list[str] = field(default_factory=list)
    missed: int = 0
    missed_notes: list[str] = field(default_factory=list)

    def add(self, n: int, note: str) -> None:
        if n:
            self.unsafe += n
            self.notes.append(note)

    def target(self, met: bool, note: str) -> None:
        """A performance target: ``note`` says which and by how much when it was not ``met``."""
        if not met:
            self.missed += 1
            self.missed_notes.append(note)


def common_checks(b: Bed, t0: float, t1: float, *, safe_from: float | None = None, band_c: float | None = None,
                  gap_limit_s: float = GAP_S) -> Check:
    """Gaps while alive, limits above the maximum, above the safe limit from ``safe_from`` on, above
    the band at the measured winding ``band_c`` while the service says it does not trust its
    estimate, crash."""
    lim = b.monitor.read()
    c = Check()
    alive = b.service.alive()
    end = t1 if alive else min(t1, time.time())
    g = gaps(lim, t0, end, gap_limit_s)
    unsafe_s = max(gap_limit_s, GAP_UNSAFE_S)
    long_g = [x for x in g if x > unsafe_s]
    c.add(len(long_g), f"{len(long_g)} TE_Limits gap(s) > {unsafe_s * 1e3:.0f} ms (max {max(g, default=0) * 1e3:.0f} ms)")
    c.target(len(long_g) == len(g), f"{len(g)} TE_Limits gap(s) > {gap_limit_s * 1e3:.0f} ms "
                                    f"(max {max(g, default=0) * 1e3:.0f} ms)")
    over = sum(1 for t, i, tq in zip(lim.t, lim.current, lim.torque)
               if t0 <= t <= t1 and (i > MAX_A + RESOLUTION_A or tq > MAX_NM + 0.1))
    c.add(over, f"{over} limit(s) above the maximum")
    # the torque limit the inverter obeys never exceeds what the current limit beside it carries,
    # in a tick's limits and in those the sender decides between ticks alike
    loose = sum(1 for t, i, tq in zip(lim.t, lim.current, lim.torque)
                if t0 <= t <= t1 and tq > KT_NM_PER_A * (i + RESOLUTION_A) + 0.1)
    c.add(loose, f"{loose} torque limit(s) above kt x the current limit")
    bad_crc = sum(1 for t, ok in zip(lim.t, lim.crc_ok) if t0 <= t <= t1 and not ok)
    c.add(bad_crc, f"{bad_crc} TE_Limits with a bad CRC")
    if safe_from is not None and safe_from < t1:
        n = runs_above(lim, safe_from, t1, SAFE_A)
        c.add(n, "above the safe limit while an input was stale or a sensor faulty")
        if not any(safe_from <= t <= t1 for t in lim.t):
            c.add(1, "no TE_Limits to derate with")
    if band_c is not None:
        # the configured band at a measured temperature is what is left when the model is not trusted
        # (the derating policy); a trusted model may give the headroom between warn and max,
        # but not past max: at a measured max every limit must be zero
        bound = band_limit_a(band_c)
        n = runs_above(lim, t0, t1, bound, None if bound <= 0 else forced_reasons())
        c.add(n, f"above the band at the measured {band_c:g} degC ({band_limit_a(band_c):.1f} A) while the "
                 "estimate was not trusted")
    if not alive or b.service.tracebacks():
        c.add(1, f"crash (exit {b.service.proc.returncode if b.service.proc else None}, {b.service.tracebacks()} traceback(s)"
                 + (", killed at the unit's MemoryMax" if b.service.oom_killed else "") + ")")
    return c


def reasons_in(lim: Limits, t0: float, t1: float) -> str:
    """The derate reasons ``TE_Limits`` gave in [t0, t1], in order (names from the DBC's value table)."""
    names = {int(k): str(v) for k, v in wire.dbc().get_message_by_frame_id(wire.TE_LIMITS_ID)
             .get_signal_by_name("TE_DerateReason").choices.items()}
    seen: list[int] = []
    for t, r in zip(lim.t, lim.reason):
        if t0 <= t <= t1 and (not seen or seen[-1] != r):
            seen.append(r)
    return " > ".join(names.get(r, str(r)) for r in seen[:6]) or "none received"


def min_current(lim: Limits, t0: float, t1: float) -> float:
    return min((c for t, c in zip(lim.t, lim.current) if t0 <= t <= t1), default=float("nan"))


@dataclass
class Case:
    """One row of the bench: what was tried how often, what the service did, what was lost (frames
    or persisted state items), how many unsafe events were seen and how many performance targets
    were missed. A ``control`` case is a fault the service cannot mask (the bench makes it itself):
    it passes when the bench judges it unsafe, which shows that the checks can fail."""

    name: str
    group: str
    tried: int
    did: str
    lost: int = 0
    unsafe: int = 0
    seconds: float = 0.0
    missed: int = 0
    control: bool = False

    @property
    def passed(self) -> bool:
        """Nothing lost and nothing unsafe; for a control case: judged unsafe."""
        return self.unsafe > 0 if self.control else not (self.lost or self.unsafe)

    @classmethod
    def of(cls, name: str, group: str, tried: int, did: str, check: Check, lost: int = 0, control: bool = False) -> Case:
        notes, missed = "; ".join(check.notes), "; ".join(check.missed_notes)
        did += (f" | UNSAFE: {notes}" if notes else "") + (f" | TARGET MISSED: {missed}" if missed else "")
        return cls(name, group, tried, did, int(lost), check.unsafe, missed=check.missed, control=control)
