"""Fault cases on when a reading was taken: sensor frames that come just after a tick's boundary or
stamped ahead of the other frames (a sensor age must never read negative), and timestamps that run
backwards, on the live bus (stamps shuffled by up to seconds) and in CAN logs (a reversed or
shuffled log refused with one line; a merged log a little out of order replayed; a log whose
first half second precedes a silence exported without ticks across the silence).

Besides the common checks (``TE_Limits`` gaps, limits, crash), a live case fails when a scrape of
``/metrics`` shows a negative ``thermal_edge_sensor_age_seconds``, when ticks stop while valid frames
arrive, when valid frames are not accepted (``lost``), or when the frames out of order are not
counted (``thermal_edge_frame_clock_behind_total``, with the frame clock). A log case fails when the
command's answer differs from the one the case expects: a refusal is exit 2 with one line naming the
file and the cause and no traceback; a replay is exit 0, its ticks the boundaries the log's frames
cross and the steps back counted.
"""
from __future__ import annotations

import math
import random
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
from .bus import _lost as _lost_wall
from .clock import ShiftedInverter, _counts, _live, _lost, _replay
from .harness import (
    TIMEOUTS_S,
    Bed,
    Case,
    Check,
    Inverter,
    bed,
    common_checks,
    counts,
    env,
    metric,
    service_config_path,
    thermal_edge_cmd,
    unit_memory_max_bytes,
)

AGE_METRIC = "thermal_edge_sensor_age_seconds"
OBSERVE_S = 8.0  # watched after each live fault, s
AGE_S = 5.0  # scraped in each sensor-age case, s (each scrape of a defective service shows a negative age)
SCRAPE_S = 0.05  # between two scrapes of /metrics, s (random phase against the tick)
#: how far after a wall-clock second (the tick's boundary) the stator and ambient frames are sent, s:
#: within the moment between the boundary and the tick that takes them
AFTER_BOUNDARY_S = 0.001
#: how far ahead of the other frames the stator temperatures are stamped (frame clock), s: less than a
#: tick, so the frame clock takes them as they come (it never waits for frames stamped ahead)
AHEAD_S = 0.6
#: stamps of the shuffled live stream: each frame stamped up to this far back, s (beyond a tick, so
#: some steps back are jumps the frame clock must judge, not jitter)
SHUFFLE_S = 3.0
LOG_S = 120  # length of the simulated CAN log of the log cases, s


class BoundaryInverter(Inverter):
    """The bench's inverter on the wall clock's grid: the 10 ms frames at ``k * 10 ms +``
    :data:`AFTER_BOUNDARY_S`, the stator and ambient temperatures with every tenth, so that one of
    them lands just after each whole second, the service's tick boundary, before the tick has run."""

    def _loop(self) -> None:
        while not self._stop.is_set():
            now = time.time()
            k = math.floor((now - AFTER_BOUNDARY_S) / 0.01) + 1
            time.sleep(max(0.0, k * 0.01 + AFTER_BOUNDARY_S - time.time()))
            if self._hold.is_set():
                continue
            frames = ("INV_Currents", "INV_Mechanics") + (("INV_StatorTemps", "INV_AmbientTemps") if k % 10 == 0 else ())
            for name in frames:
                if name not in self.paused:
                    self._send(name)


def _ages(m: dict[str, float]) -> list[float]:
    return [v for k, v in m.items() if k.startswith(AGE_METRIC + "{")]


def _scrape(b: Bed, seconds: float) -> tuple[list[float], int, int]:
    """Scrape ``/metrics`` for ``seconds`` at random phases: (every sensor age seen, scrapes tried,
    answered)."""
    rng = random.Random(1)
    ages: list[float] = []
    tried = answered = 0
    end = time.monotonic() + seconds
    while time.monotonic() < end and b.service.alive():
        tried += 1
        m = b.service.metrics()
        answered += bool(m)
        ages += _ages(m)
        time.sleep(SCRAPE_S * (0.5 + rng.random()))
    return ages, tried, answered


def _judge_ages(c: Check, ages: list[float], tried: int, answered: int) -> str:
    negative = [a for a in ages if a < 0]
    c.add(len(negative), f"{len(negative)} negative sensor age(s) scraped (lowest {min(negative, default=0.0):.3f} s)")
    c.add(int(not ages), "no sensor age scraped")
    c.add(tried - answered, f"/metrics answered {answered} of {tried} scrapes")
    lo, hi = min(ages, default=math.nan), max(ages, default=math.nan)
    return f"{len(ages)} sensor ages in {answered} scrapes, {lo:.3f}..{hi:.3f} s"


def boundary_readings(full: bool) -> Iterator[Case]:
    """Wall clock: the stator and ambient frames arrive 1 ms after each tick boundary, so the tick
    takes readings newer than its own time; ``/metrics`` scraped meanwhile at random phases."""
    seconds = 3 * AGE_S if full else AGE_S
    with bed("age-boundary", inverter=False) as b:
        inv = BoundaryInverter(b.group, b.port).start()
        try:
            time.sleep(3.0)  # past the start-up state, ticking on the bench's readings
            sent0, m0 = counts(b, inv)
            t0 = time.time()
            ages, tried, answered = _scrape(b, seconds)
            t1 = time.time()
            sent1, m1 = counts(b, inv)
            c = common_checks(b, t0, t1)
            did = _judge_ages(c, ages, tried, answered)
            ticks = metric(m1, "thermal_edge_ticks_total") - metric(m0, "thermal_edge_ticks_total") if m0 and m1 else 0.0
            # a tick per second of the wall clock is a target (a busy host delays ticks, the wall clock
            # then skips the missed ones); none at all is the service's failure
            c.add(int(ticks < 1), f"{ticks:.0f} ticks in {t1 - t0:.0f} s")
            c.target(ticks >= (t1 - t0) - 2.0, f"{ticks:.0f} ticks in {t1 - t0:.0f} s")
            lost = _lost_wall(sent0, m0, sent1, m1)
            yield Case.of("stator_frames_just_after_the_tick_boundary", "sensor age", int(answered),
                          f"stator and ambient frames {AFTER_BOUNDARY_S * 1e3:.0f} ms after each boundary: {did}; "
                          f"{ticks:.0f} ticks", c, lost)
        finally:
            inv.close()


def _behind(m: dict[str, float]) -> float:
    return metric(m, "thermal_edge_frame_clock_behind_total")


def stamped_ahead(full: bool) -> Iterator[Case]:
    """Frame clock: the stator temperatures stamped :data:`AHEAD_S` ahead of the other frames (a
    sensor box whose clock runs ahead) while ``/metrics`` is scraped; the other frames then come
    behind the clock, which must count them and use them."""
    seconds = 3 * AGE_S if full else AGE_S
    with _live("age-ahead") as (b, inv):
        time.sleep(2.0)
        sent0, m0 = _counts(b, inv)
        t0 = time.time()
        stop = threading.Event()

        def ahead() -> None:  # the stator frame again, stamped ahead, between the inverter's own
            while not stop.wait(0.1):
                inv.send_stamped("INV_StatorTemps", time.time() + AHEAD_S)

        with inv.lock:
            inv.paused.add("INV_StatorTemps")
        th = threading.Thread(target=ahead, daemon=True)
        th.start()
        try:
            ages, tried, answered = _scrape(b, seconds)
        finally:
            stop.set()
            th.join(2)
            with inv.lock:
                inv.paused.discard("INV_StatorTemps")
        t1 = time.time()
        sent1, m1 = _counts(b, inv)
        c = common_checks(b, t0, t1)
        did = _judge_ages(c, ages, tried, answered)
        behind = _behind(m1) - _behind(m0) if m0 and m1 else 0.0
        c.add(int(behind < 1), "the frames behind the stator's stamps were not counted")
        ticks = metric(m1, "thermal_edge_ticks_total") - metric(m0, "thermal_edge_ticks_total") if m0 and m1 else 0.0
        c.add(int(ticks < (t1 - t0) - 2.0), f"the frame clock stopped ticking: {ticks:.0f} ticks in {t1 - t0:.0f} s")
        stale = TIMEOUTS_S["INV_StatorTemps"]
        yield Case.of(f"stator_stamped_{AHEAD_S * 1e3:.0f}ms_ahead", "sensor age", int(answered),
                      f"INV_StatorTemps stamped {AHEAD_S:g} s ahead (timeout {stale:g} s): {did}; {behind:.0f} frames "
                      f"counted behind the clock; {ticks:.0f} ticks", c, _lost(sent0, m0, sent1, m1))


def sensor_age(full: bool) -> Iterator[Case]:
    """A sensor age never reads negative: readings that come after the tick's boundary, readings
    stamped ahead."""
    yield from boundary_readings(full)
    yield from stamped_ahead(full)


# ----------------------------------------------------------------------------------------------
class ShuffledInverter(ShiftedInverter):
    """The bench's inverter with each frame stamped ``time.time()`` less a random ``0..shuffle_s``
    (0: in order)."""

    shuffle_s = 0.0
    rng = random.Random(2)

    def _send_locked(self, name: str) -> None:
        k = self.counters[name]
        self.counters[name] = (k + 1) % 16
        data = wire.encode(name, self.signals[name], k)
        ts = time.time() + self.offset - self.shuffle_s * self.rng.random()
        self.sock.sendto(wire.datagram(self.ids[name], data, timestamp=ts), (self.group, self.port))
        self.sent[name] += 1


def shuffled_live(full: bool) -> Iterator[Case]:
    """Frame clock: every frame stamped up to :data:`SHUFFLE_S` back at random (a gateway that
    forwards frames out of order with the stamps they were taken at): the frames are used, the
    steps back counted, the ticks go on."""
    seconds = 3 * OBSERVE_S if full else OBSERVE_S
    with bed("back-shuffled", inverter=False, clock="frame") as b:
        inv = ShuffledInverter(b.group, b.port).start()
        try:
            time.sleep(2.0)
            sent0, m0 = _counts(b, inv)
            t0 = time.time()
            with inv.lock:
                inv.shuffle_s = SHUFFLE_S
            time.sleep(seconds)
            with inv.lock:
                inv.shuffle_s = 0.0
            t_clear = time.time()
            time.sleep(2.0)  # in order again
            t1 = time.time()
            sent1, m1 = _counts(b, inv)
        finally:
            inv.close()
        c = common_checks(b, t0, t1)
        behind = _behind(m1) - _behind(m0) if m0 and m1 else 0.0
        c.add(int(behind < 1), "the frames stamped back were not counted")
        ticks = metric(m1, "thermal_edge_ticks_total") - metric(m0, "thermal_edge_ticks_total") if m0 and m1 else 0.0
        c.add(int(b.service.alive() and ticks < (t_clear - t0) - 2.0),
              f"the frame clock stopped ticking: {ticks:.0f} ticks in {t1 - t0:.0f} s of valid frames")
        jumps = {k.split("outcome=")[-1].strip('"}'): v - m0.get(k, 0.0) for k, v in m1.items()
                 if k.startswith("thermal_edge_frame_clock_jumps_total")}
        # a run of frames a tick or more back is taken for a new recording segment only when it brings
        # a tick's traffic: random stamps never do, so the model's time keeps to the stamps' span
        span = t1 - t0
        c.add(int(ticks > span + 2.0), f"the model's time ran {ticks / span:.1f}x the span of the stamps "
                                       f"({jumps.get('joined', 0):.0f} steps back taken as new segments)")
        did = (f"{seconds:.0f} s of frames stamped up to {SHUFFLE_S:g} s back at random: {behind:.0f} counted behind the "
               f"clock; jumps {', '.join(f'{k} {v:.0f}' for k, v in jumps.items()) or 'none'}; {ticks:.0f} ticks in "
               f"{t1 - t0:.0f} s")
        yield Case.of(f"stamps_shuffled_{SHUFFLE_S:.0f}s_live", "time back", 1, did, c, _lost(sent0, m0, sent1, m1))


def _stamp(line: str) -> float:
    return float(line[1:line.index(")")])


def _restamp(line: str, t: float) -> str:
    return f"({t:.6f})" + line[line.index(")") + 1:]


def _refused(name: str, tried: str, log: Path, cause: str) -> Case:
    """``replay --format can`` of ``log`` must exit 2 with one line naming the file and ``cause``."""
    cmd = thermal_edge_cmd() + ["replay", "--format", "can", "--run", str(log), "--config",
                                str(service_config_path("edge.yaml")), "--model",
                                str(service_config_path("machines", "pm10kw.yaml")), "--json"]
    r = subprocess.run(cmd, env=env(service=True), cwd=str(log.parent), capture_output=True, text=True, timeout=600)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    c = Check()
    c.add(int(r.returncode != 2), f"exit {r.returncode}, not 2")
    c.add(int("Traceback" in r.stderr), "a traceback")
    c.add(int(len(lines) != 1), f"{len(lines)} lines on stderr, not one")
    c.add(int(not lines or log.name not in lines[0] or cause not in lines[0]), f"the line does not name the file and '{cause}'")
    said = lines[0].split("error: ", 1)[-1] if lines else "nothing"
    return Case.of(name, "time back", 1, f"{tried}: exit {r.returncode}, {said[:140]}", c)


def log_cases(full: bool) -> Iterator[Case]:
    """CAN logs whose time runs backwards, through ``thermal-edge replay --format can``."""
    workdir = Path(tempfile.mkdtemp(prefix="te-faults-back-"))
    try:
        clean = workdir / "clean.log"
        subprocess.run(thermal_edge_cmd() + ["simulate", "--model", str(service_config_path("machines", "pm10kw.yaml")),
                                             "--cycle", str(service_config_path("cycles", "overload.yaml")), "--format", "can",
                                             "--duration", str(LOG_S * (5 if full else 1)), "--out", str(clean)],
                       env=env(), cwd=str(ROOT), check=True, capture_output=True, timeout=600)
        lines = clean.read_text().splitlines()
        rev = workdir / "reversed.log"
        rev.write_text("\n".join(reversed(lines)) + "\n")
        yield _refused("replay_reversed_log", "the log's lines in reverse order", rev, "backwards")
        shuffled = list(lines)
        random.Random(3).shuffle(shuffled)
        shuf = workdir / "shuffled.log"
        shuf.write_text("\n".join(shuffled) + "\n")
        yield _refused("replay_shuffled_log", "the log's lines shuffled", shuf, "backwards")
        yield _merged(workdir, lines)
        yield _silence_first(workdir, lines)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)


#: share of the merged log's frames stamped back (below the reader's refusal), and by how much, s
MERGED_SHARE, MERGED_BACK_S = 0.15, 0.004


def _merged(workdir: Path, lines: list[str]) -> Case:
    """A log merged from two interfaces by a logger: :data:`MERGED_SHARE` of its frames a few ms
    out of order. Replayed: every tick boundary ticked, the steps back counted by the frame clock."""
    rng = random.Random(4)
    out = list(lines)
    back = 0
    for i in range(1, len(out) - 1):
        if rng.random() < MERGED_SHARE:
            out[i] = _restamp(out[i], _stamp(out[i]) - MERGED_BACK_S)
            back += 1
    log = workdir / "merged.log"
    log.write_text("\n".join(out) + "\n")
    stamps = [_stamp(ln) for ln in lines]
    want = math.floor(max(stamps)) - math.floor(stamps[0])
    s, err, _, killed = _replay(log, unit_memory_max_bytes())
    c = Check()
    c.add(int(s is None), "replay failed" + (" (killed at MemoryMax)" if killed else f": {err.strip()[-160:]}"))
    ticks = int(s["ticks"]) if s else 0
    fc: dict[str, Any] = (s or {}).get("frame_clock") or {}
    steps_back = sum(1 for a, b in zip(out, out[1:]) if _stamp(b) < _stamp(a))
    c.add(int(s is not None and fc.get("behind", 0) < 1), "the frames out of order were not counted")
    did = (f"{back} of {len(out)} frames {MERGED_BACK_S * 1e3:g} ms back ({steps_back} steps back): exit "
           f"{'0' if s else 'non-zero'}; {ticks} ticks of {want} boundaries; frame clock: "
           + ("; ".join(f"{k} {v:g}" for k, v in fc.items() if v) or "nothing"))
    return Case.of("replay_merged_log_a_few_ms_out_of_order", "time back", 1, did, c, max(0, want - ticks))


#: the silent start's log: frames for this long, then none for this long, then the rest, s
FIRST_S, SILENT_S = 0.5, 21.5


def _silence_first(workdir: Path, lines: list[str]) -> Case:
    """A log whose first :data:`FIRST_S` of frames is followed by :data:`SILENT_S` without any (a
    drive switched off just after the logger started): ``export`` must not make ticks across the
    silence from the frames before it (each such tick is drive data nobody measured)."""
    t0 = _stamp(lines[0])
    kept = [ln for ln in lines if not t0 + FIRST_S <= _stamp(ln) < t0 + FIRST_S + SILENT_S]
    log = workdir / "silent-start.log"
    log.write_text("\n".join(kept) + "\n")
    out = workdir / "silent-start.csv"
    r = subprocess.run(thermal_edge_cmd() + ["export", "--config", str(service_config_path("edge.yaml")), "--out", str(out),
                                             str(log)], env=env(service=True), cwd=str(workdir), capture_output=True,
                       text=True, timeout=600)
    ticks = 0
    for csv_path in sorted(workdir.glob("silent-start*.csv")):
        ticks += sum(1 for ln in csv_path.read_text().splitlines()[1:] if ln and not ln.startswith("#"))
    # the tick boundaries the traffic after the silence spans (and the tick it ends in): at most that
    # many ticks are measured ones
    measured = math.floor(_stamp(kept[-1])) - math.floor(t0 + FIRST_S + SILENT_S) + 1
    invented = max(0, ticks - measured)
    c = Check()
    c.add(int(r.returncode != 0), f"export exit {r.returncode}: {r.stderr.strip()[-160:]}")
    c.add(invented, f"{invented} ticks beyond the {measured} s of traffic after the silence")
    return Case.of("export_log_whose_first_frames_precede_a_silence", "time back", 1,
                   f"{FIRST_S:g} s of frames, {SILENT_S:g} s silent, then {measured} s: exported {ticks} ticks, "
                   f"{invented} invented", c)


def time_back(full: bool) -> Iterator[Case]:
    """Time running backwards: shuffled stamps on the live bus, reversed, shuffled and merged CAN logs."""
    yield from shuffled_live(full)
    yield from log_cases(full)


GROUPS = {"sensor_age": sensor_age, "time_back": time_back}
