"""Fault cases on the frame clock's time: frames stamped far ahead or behind, and a sender's clock
stepping back, in the live service (frame clock, ``preserve_timestamps``: the soak's set-up); a
CAN log whose time goes back or holds one stamp in 2100, through ``thermal-edge replay``.

Besides the common checks, a case is unsafe when the frame clock stops ticking while valid frames
arrive (the model frozen: with the frame clock ``TE_Limits`` repeats the last tick's limit, which no
longer follows the machine), when the metrics stop answering, and, in a replay, when the peak
hot-spot estimate falls below the clean log's (heat forgotten) or the replay dies (the memory cap
of the unit, ``MemoryMax``, enforced as in the live cases). ``lost``: valid frames sent but not
accepted (live); tick boundaries of the log's frames not ticked (replay: the test's own count from
the log's segments laid end to end).
"""
from __future__ import annotations

import contextlib
import json
import math
import shutil
import subprocess
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from .. import ROOT
from . import wire
from .harness import (
    Bed,
    Case,
    Check,
    Inverter,
    bed,
    common_checks,
    env,
    metric,
    received,
    service_config_path,
    thermal_edge_cmd,
    unit_memory_max_bytes,
)

YEAR_2100 = 4102444800.0
OBSERVE_S = 8.0  # watched after each fault (live)


class ShiftedInverter(Inverter):
    """The bench's inverter with its frames stamped ``time.time() + offset`` (a sender's clock)."""

    offset = 0.0

    def _send_locked(self, name: str) -> None:
        k = self.counters[name]
        self.counters[name] = (k + 1) % 16
        data = wire.encode(name, self.signals[name], k)
        self.sock.sendto(wire.datagram(self.ids[name], data, timestamp=time.time() + self.offset), (self.group, self.port))
        self.sent[name] += 1

    def send_stamped(self, name: str, ts: float) -> None:
        """One valid frame of ``name`` (counter and CRC good, in sequence) stamped ``ts``."""
        with self.lock:
            k = self.counters[name]
            self.counters[name] = (k + 1) % 16
            data = wire.encode(name, self.signals[name], k)
            self.sock.sendto(wire.datagram(self.ids[name], data, timestamp=ts), (self.group, self.port))
            self.sent[name] += 1


@contextlib.contextmanager
def _live(name: str) -> Iterator[tuple[Bed, ShiftedInverter]]:
    with bed(name, inverter=False, clock="frame") as b:
        inv = ShiftedInverter(b.group, b.port).start()
        try:
            yield b, inv
        finally:
            inv.close()


def _counts(b: Bed, inv: ShiftedInverter) -> tuple[dict[str, int], dict[str, float]]:
    with inv.held() as sent:
        m = b.service.metrics()
    return sent, m


def _lost(sent0: dict[str, int], m0: dict[str, float], sent1: dict[str, int], m1: dict[str, float]) -> int:
    if not m0:
        return -1
    if not m1:  # the service is gone: everything sent since
        return sum(sent1[n] - sent0[n] for n in wire.INPUT_FRAMES)
    r0, r1 = received(m0), received(m1)
    return int(sum(max(0, (sent1[n] - sent0[n]) - (r1[n] - r0[n])) for n in wire.INPUT_FRAMES))


def _live_case(name: str, tried: str, fault: Any) -> Case:
    """Start a frame-clock service with the shifted inverter, wait for ticks, apply ``fault(inv)``,
    watch :data:`OBSERVE_S` s: ticks, metrics, RSS, the common checks."""
    with _live(f"clock-{name}") as (b, inv):
        time.sleep(2.0)  # ticking
        sent0, m0 = _counts(b, inv)
        ticks0 = metric(m0, "thermal_edge_ticks_total")
        t0 = time.time()
        fault(inv)
        answered, polls = 0, 0
        while time.time() - t0 < OBSERVE_S and b.service.alive():
            polls += 1
            answered += bool(b.service.metrics())
            time.sleep(1.0)
        t1 = time.time()
        sent1, m1 = _counts(b, inv)
        c = common_checks(b, t0, t1)
        ticks = metric(m1, "thermal_edge_ticks_total") - ticks0 if m1 else 0.0
        expected = (t1 - t0) - 2.0  # a tick a second of frames, less the judging of a jump and slack
        c.add(int(b.service.alive() and ticks < expected),
              f"the frame clock stopped ticking: {ticks:.0f} ticks in {t1 - t0:.0f} s of valid frames (limits frozen)")
        c.add(int(b.service.alive() and answered < polls), f"/metrics answered {answered} of {polls} scrapes")
        fc = {k.split("outcome=")[-1].strip('"}'): v for k, v in m1.items()
              if k.startswith("thermal_edge_frame_clock_jumps_total")}
        did = (f"{ticks:.0f} ticks in {t1 - t0:.1f} s; peak RSS {b.service.peak_rss / 2**20:.0f} MiB"
               f"{' (killed at MemoryMax)' if b.service.oom_killed else ''}; metrics {answered}/{polls}; "
               f"frame_gaps {metric(m1, 'thermal_edge_frame_gaps_total'):.0f}; "
               + (f"jumps {', '.join(f'{k} {v:.0f}' for k, v in fc.items())}; behind "
                  f"{metric(m1, 'thermal_edge_frame_clock_behind_total'):.0f}" if fc else "no frame-clock counters"))
        return Case.of(name, "clock", 1, f"{tried}: {did}", c, _lost(sent0, m0, sent1, m1))


def _stamp_once(ts_fn: Any) -> Any:
    def fault(inv: ShiftedInverter) -> None:
        inv.send_stamped("INV_Currents", ts_fn())
    return fault


def _step_back(seconds: float) -> Any:
    def fault(inv: ShiftedInverter) -> None:
        with inv.lock:
            inv.offset = -seconds
    return fault


def silent_bus() -> Case:
    """The inverter goes silent with the frame clock: no frame, so no tick. TE_Limits must carry the
    safe limit, and the metrics must say what it carries (they showed the last tick's full limit,
    nominal state and fresh inputs), with one WARNING line."""
    with _live("clock-silent") as (b, inv):
        time.sleep(3.0)  # ticking, full current
        t0 = time.time()
        inv.paused.update(wire.INPUT_FRAMES)  # every frame stops
        time.sleep(3.0)  # transmit.bus_silence_s is 1 s
        m = b.service.metrics()
        t1 = time.time()
        lim = b.monitor.read()
        c = common_checks(b, t0, t1, safe_from=t0 + 1.5)
        sent = [(t, i, r) for t, i, r in zip(lim.t, lim.current, lim.reason) if t0 + 1.5 <= t <= t1]
        last_a = sent[-1][1] if sent else float("nan")
        shown_a = metric(m, "thermal_edge_current_limit_amperes") if m else float("nan")
        c.add(int(not sent or abs(shown_a - last_a) > 0.05),
              f"/metrics shows {shown_a:g} A while TE_Limits carries {last_a:g} A")
        stale = [v for k, v in m.items() if k.startswith("thermal_edge_input_stale{")]
        c.add(int(not stale or min(stale) < 1.0), f"/metrics: {sum(stale):.0f} of {len(stale)} inputs stale")
        silent_s = metric(m, "thermal_edge_bus_silent_seconds") if m else 0.0
        c.add(int(silent_s <= 0.0), "/metrics: thermal_edge_bus_silent_seconds 0 on a silent bus")
        warned = b.service.log_text().count("the bus is silent")
        c.add(int(warned != 1), f"{warned} WARNING line(s) on the silence, not one")
        did = (f"every inverter frame stopped (frame clock): TE_Limits {last_a:g} A, /metrics {shown_a:g} A, "
               f"{sum(stale):.0f}/{len(stale)} inputs stale, silent for {silent_s:.1f} s, {warned} WARNING line(s)")
        return Case.of("inverter_silent_frame_clock", "clock", 1, did, c)


def live_cases(full: bool) -> Iterator[Case]:
    yield silent_bus()
    yield _live_case("frame_stamped_2100", "one valid INV_Currents stamped 2100-01-01 (frame clock)",
                     _stamp_once(lambda: YEAR_2100))
    yield _live_case("frame_stamped_1e9s_ahead", "one valid INV_Currents stamped 1e9 s ahead",
                     _stamp_once(lambda: time.time() + 1e9))
    yield _live_case("frame_stamped_1e9s_behind", "one valid INV_Currents stamped 1e9 s behind",
                     _stamp_once(lambda: time.time() - 1e9))
    for s in ((30.0, 600.0) if full else (600.0,)):
        yield _live_case(f"sender_clock_back_{s:.0f}s", f"the inverter's stamps step back {s:.0f} s and stay", _step_back(s))


# ----------------------------------------------------------------------------------------------
def _stamp(line: str) -> float:
    return float(line[1:line.index(")")])


def _restamp(line: str, t: float) -> str:
    return f"({t:.6f})" + line[line.index(")") + 1:]


def _expected_ticks(stamps: list[float], seam: int | None) -> int:
    """Tick boundaries (integer multiples of the tick) of the log's frames: those of the first
    segment, then the second's laid on at the first's end (no gap, nothing twice)."""
    if seam is None:
        return math.floor(max(stamps)) - math.floor(stamps[0])
    end = max(stamps[:seam]) + (max(stamps[seam:]) - stamps[seam])
    return math.floor(end) - math.floor(stamps[0])


def _replay(log: Path, cap: int) -> tuple[dict[str, Any] | None, str, int, bool]:
    """``thermal-edge replay --format can --json`` (the service's tree) under the unit's memory cap:
    (summary or None, stderr, peak RSS, killed at the cap)."""
    cmd = thermal_edge_cmd() + ["replay", "--format", "can", "--run", str(log), "--config",
                                str(service_config_path("edge.yaml")), "--model",
                                str(service_config_path("machines", "pm10kw.yaml")), "--json"]
    proc = subprocess.Popen(cmd, env=env(service=True), cwd=str(log.parent), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    peak, killed = 0, False

    def watch() -> None:
        nonlocal peak, killed
        while proc.poll() is None:
            with contextlib.suppress(OSError, IndexError, ValueError):
                rss = int(Path(f"/proc/{proc.pid}/status").read_text().split("VmRSS:")[1].split()[0]) * 1024
                peak = max(peak, rss)
                if rss > cap:
                    killed = True
                    proc.kill()
                    return
            time.sleep(0.02)

    w = threading.Thread(target=watch, daemon=True)
    w.start()
    out, err = proc.communicate(timeout=600)
    w.join(2)
    try:
        s = json.loads(out) if proc.returncode == 0 else None
    except ValueError:
        s = None
    return s, err.decode(errors="replace"), peak, killed


def replay_cases(full: bool) -> Iterator[Case]:
    duration = 1800 if full else 600
    workdir = Path(tempfile.mkdtemp(prefix="te-faults-clock-replay-"))
    try:
        clean = workdir / "clean.log"
        # the project's simulator makes the normal traffic (as the soak uses its emulator); the faults are the bench's
        subprocess.run(thermal_edge_cmd() + ["simulate", "--model", str(service_config_path("machines", "pm10kw.yaml")),
                                             "--cycle", str(service_config_path("cycles", "overload.yaml")), "--format", "can",
                                             "--duration", str(duration), "--out", str(clean)],
                       env=env(), cwd=str(ROOT), check=True, capture_output=True, timeout=600)
        lines = clean.read_text().splitlines()
        cap = unit_memory_max_bytes()
        ref, _, _, _ = _replay(clean, cap)
        if ref is None:
            raise RuntimeError("the clean log did not replay")
        ref_peak = float(ref["max_estimate_c"]["hot_spot"])
        mid = len(lines) // 2
        while _stamp(lines[mid]) == _stamp(lines[mid - 1]):
            mid += 1
        variants: dict[str, tuple[str, list[str], int | None]] = {}
        for shift in (300.0, 600.0):
            variants[f"replay_second_half_{shift:.0f}s_back"] = (
                f"the log's second half stamped {shift:.0f} s earlier",
                lines[:mid] + [_restamp(ln, _stamp(ln) - shift) for ln in lines[mid:]], mid)
        variants["replay_one_frame_in_2100"] = ("one frame of the log stamped 2100-01-01",
                                                lines[:mid] + [_restamp(lines[mid], YEAR_2100)] + lines[mid + 1:], None)
        for name, (tried, text, seam) in variants.items():
            log = workdir / f"{name}.log"
            log.write_text("\n".join(text) + "\n")
            stamps = [_stamp(ln) for ln in (text if seam is not None else lines)]
            want = _expected_ticks(stamps, seam)
            s, err, peak, killed = _replay(log, cap)
            c = Check()
            c.add(int(s is None), "replay failed" + (" (killed at MemoryMax)" if killed else f": {err.strip()[-160:]}"))
            ticks = int(s["ticks"]) if s else 0
            hot = float(s["max_estimate_c"]["hot_spot"]) if s and "max_estimate_c" in s else math.nan
            c.add(int(s is not None and not hot >= ref_peak - 0.5),
                  f"peak hot spot {hot:.1f} degC below the clean log's {ref_peak:.1f} degC")
            fc = (s or {}).get("frame_clock")
            said = ("; ".join(f"{k} {v:g}" for k, v in fc.items() if v) or "nothing") if fc is not None else "no word of it"
            warned = sum(1 for ln in err.splitlines() if "frame" in ln and ("went back" in ln or "corrupt" in ln))
            did = (f"{ticks} ticks of {want} boundaries (clean log {ref['ticks']}); peak hot spot {hot:.1f} degC "
                   f"(clean {ref_peak:.1f}); peak RSS {peak / 2**20:.0f} MiB; frame clock: {said}; {warned} warning line(s)")
            yield Case.of(name, "clock", 1, f"{tried}: {did}", c, max(0, want - ticks))
    finally:
        shutil.rmtree(workdir, ignore_errors=True)


def frame_clock(full: bool) -> Iterator[Case]:
    """The frame clock against wrong timestamps: live (F2: a frame stamped in 2100 or 1e9 s away;
    the sender's clock stepping back) and in replays (F3: time going back in a CAN log; F2: one
    frame in 2100)."""
    yield from live_cases(full)
    yield from replay_cases(full)


GROUPS = {"clock": frame_clock}
