"""The frame clock against wrong timestamps (defects F2 and F3 of the red-team findings).

F2: one frame stamped far in the future made ``FrameClock.observe`` build a list of every tick
boundary crossed (24 GB for a frame in 2100), and after the gap was bridged every correct frame was
"going backwards", so the clock never ticked again. F3: time going backwards in a CAN log was
ignored by the clock: a log whose second half is stamped 300 s earlier replayed to 299 ticks
instead of 599, silently.

Each behaviour is judged against a computation of the test's own (memory by tracemalloc, tick
counts from the segments' spans, counts of frames behind by walking the timestamps).
"""
from __future__ import annotations

import math
import subprocess
import sys
import textwrap

import pytest
from svc_testlib import CYCLES, MODEL, REPO, edge_raw, env, write_yaml

from thermal_edge.config import load_config
from thermal_edge.service.clock import FrameClock

CLOCK_PY = REPO / "thermal_edge" / "service" / "clock.py"


# -- F2: a far-future timestamp ------------------------------------------------------------------
def test_a_jump_of_1e9_s_takes_constant_memory() -> None:
    """A jump of 1e9 s kept to by the frames after it: the boundaries crossed (1e9 of them) in
    constant memory, measured by tracemalloc, in a process capped at 1 GiB of address space (the
    old clock's list of 1e9 floats needs ~32 GB: MemoryError there, not an OOM of the host)."""
    code = textwrap.dedent(f"""
        import importlib.util, resource, tracemalloc
        resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30))
        spec = importlib.util.spec_from_file_location("clock_under_test", {str(CLOCK_PY)!r})
        mod = importlib.util.module_from_spec(spec); spec.loader.exec_module(mod)
        c = mod.FrameClock(1.0)
        c.observe(1000.5)
        tracemalloc.start()
        got = []
        for dt in (0.0, 0.4, 0.8, 1.2):  # the jump and the frames after it (kept to it)
            b = c.observe(1000.5 + 1e9 + dt)
            got.append((len(b), b[0] if len(b) else None, b[-1] if len(b) else None))
        peak = tracemalloc.get_traced_memory()[1]
        print(max(g[0] for g in got), [g for g in got if g[0]], peak)
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=env())
    assert proc.returncode == 0, proc.stderr[-2000:]
    n, peak = int(proc.stdout.split(" ", 1)[0]), int(proc.stdout.split()[-1])
    # the boundaries the test expects: every integer in (1000.5, 1000.5 + 1e9 + 1.2]
    want = math.floor(1000.5 + 1e9 + 1.2) - math.floor(1000.5)
    assert n == want
    print(f"peak traced memory for a 1e9 s jump: {peak} B; {proc.stdout.strip()}")
    assert peak < 64 * 1024


def test_boundaries_behave_as_the_list_they_stand_for() -> None:
    c = FrameClock(0.5)
    c.observe(10.1)
    b = c.observe(12.3)
    want = [10.5, 11.0, 11.5, 12.0]
    assert b == want and list(b) == want and len(b) == 4 and bool(b)
    assert b[-1] == 12.0 and b[0] == 10.5 and b[-1:] == [12.0] and b[1:3] == [11.0, 11.5] and b[::2] == [10.5, 11.5]
    assert not c.observe(12.4) and c.observe(12.4) == []
    with pytest.raises(IndexError):
        b[4]


@pytest.fixture(scope="module")
def engine_config(tmp_path_factory):
    d = tmp_path_factory.mktemp("fc")
    return load_config(write_yaml(d / "edge.yaml", edge_raw(d / "state", {"interface": "virtual"}, table4=False,
                                                                adapt=False)))


def test_engine_bridges_a_confirmed_1e9_s_gap_and_ticks_once(engine_config) -> None:
    from thermal_edge.service.clock import Boundaries  # absent before the fix
    from thermal_edge.service.engine import ThermalEngine

    eng = ThermalEngine(engine_config, worker_mode="sync")
    try:
        b = Boundaries(range(1001, 1001 + 10**9), 1.0)
        ticks = eng.ticks_for(b)
        assert list(ticks) == [float(1000 + 10**9)] and eng.gaps == 1
    finally:
        eng.close()


def _run(clock: FrameClock, stamps: list[float]) -> list[float]:
    out: list[float] = []
    for ts in stamps:
        out.extend(clock.observe(ts))
    return out


def test_one_stamp_far_ahead_is_ignored_and_the_clock_keeps_ticking() -> None:
    """A single frame 1e6 s ahead (1e6 boundaries: safe for the old clock's list too), then the
    frames at the right time again: the clock ignores the stamp, ticks every boundary of the good
    frames, and counts it."""
    stamps = [100.0 + 0.01 * i for i in range(1000)]  # 100.00 .. 109.99
    bad = stamps[:500] + [stamps[500] + 1e6] + stamps[501:]
    c = FrameClock(1.0)
    ticks = _run(c, bad)
    want = [float(k) for k in range(101, 110)]  # the integers in (100.0, 109.99]
    assert ticks == want
    assert (c.stats.ignored, c.stats.ignored_frames, c.stats.ahead) == (1, 1, 0)


def test_a_real_gap_ahead_is_still_a_gap() -> None:
    c = FrameClock(1.0, max_catchup_s=300.0)
    ticks = _run(c, [100.0, 100.5, 1100.0, 1100.4, 1100.8, 1101.2, 1101.6])
    assert len(ticks) == 1001 and ticks[0] == 101.0 and ticks[-1] == 1101.0
    assert c.stats.ahead == 1 and c.stats.ignored == 0


def test_one_stamp_far_behind_is_ignored() -> None:
    stamps = [100.0 + 0.01 * i for i in range(1000)]
    bad = stamps[:500] + [stamps[500] - 1e6] + stamps[501:]
    c = FrameClock(1.0)
    assert _run(c, bad) == [float(k) for k in range(101, 110)]
    assert (c.stats.ignored, c.stats.joined, c.stats.behind) == (1, 0, 1)
    assert c.stats.behind_max_s == pytest.approx(stamps[499] - bad[500], abs=1e-6)


# -- F3: time going backwards -----------------------------------------------------------------
def test_a_step_back_is_joined_on_and_ticked_through() -> None:
    """Frames stepping back by 50 s and staying there: the clock joins the new segment where it
    is and ticks through it (no boundary lost, none twice); jitter under a tick only counted."""
    seg1 = [100.0 + 0.1 * i for i in range(100)]  # 100.0 .. 109.9
    seg2 = [60.0 + 0.1 * i for i in range(100)]  # 60.0 .. 69.9: 49.9 s back
    stamps = seg1 + seg2
    stamps[30], stamps[31] = stamps[31], stamps[30]  # jitter: 0.1 s back
    c = FrameClock(1.0)
    ticks = _run(c, stamps)
    end = seg1[-1] + (seg2[-1] - seg2[0])  # the joined timeline ends here
    want = math.floor(end) - math.floor(seg1[0])
    assert len(ticks) == want and ticks == sorted(set(ticks)) and ticks[0] == 101.0
    assert c.stats.joined == 1 and c.stats.joined_s == pytest.approx(seg1[-1] - seg2[0])
    assert c.stats.jitter == 1 and c.stats.behind_max_s == pytest.approx(seg1[-1] - seg2[0])


def test_stamps_shuffled_by_seconds_are_not_taken_for_new_segments() -> None:
    """A gateway forwarding frames with the stamps they were taken at, each up to 3 s back at
    random: runs of a few frames a tick or more behind are common, yet none brings a tick's traffic
    as a new segment does. The clock keeps to the stamps' own span (it ran 10x ahead when three
    frames in a row confirmed a segment), counts every step back and joins nothing."""
    import random

    rng = random.Random(7)
    true = [100.0 + 0.01 * i for i in range(6000)]  # 60 s at 100 frames/s
    stamps = true[:200] + [t - rng.uniform(0.0, 3.0) for t in true[200:]]
    c = FrameClock(1.0)
    ticks = _run(c, stamps)
    back, latest = 0, stamps[0]  # frames stamped before the latest stamp so far
    for ts in stamps[1:]:
        back += ts < latest
        latest = max(latest, ts)
    # every boundary the stamps cross, counted from the largest stamp: none beyond it, none twice
    assert ticks == sorted(set(ticks)) and ticks[-1] <= max(stamps)
    assert len(ticks) == math.floor(max(stamps)) - math.floor(stamps[0])
    assert c.stats.joined == 0 and c.stats.behind == back > 1000


# -- the same through a replay of a CAN log ------------------------------------------------------
def _stamp(line: str) -> float:
    return float(line[1:line.index(")")])


def _restamp(line: str, t: float) -> str:
    return f"({t:.6f})" + line[line.index(")") + 1:]


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    from thermal_edge.service import replay_candump
    from thermal_edge.sim.inverter import write_log

    d = tmp_path_factory.mktemp("logs")
    log = d / "clean.log"
    write_log(MODEL, CYCLES / "overload.yaml", log, duration_s=240, t0=1.7e9, current_period_s=0.1,
              temperature_period_s=1.0)
    cfg = load_config(write_yaml(d / "edge.yaml", edge_raw(d / "state", {"interface": "virtual"}, table4=False,
                                                              adapt=False)))
    return d, cfg, log.read_text().splitlines(), replay_candump(log, cfg)


def _hot_spot_peak(res) -> float:
    return float(max(res.node("end_winding_2")))


@pytest.mark.parametrize("shift_s", [100.0, 400.0])  # back by less and by more than clock.max_catchup_s (300 s)
def test_replay_of_a_log_whose_second_half_goes_back(clean, shift_s: float) -> None:
    from thermal_edge.service import replay_candump

    d, cfg, lines, ref = clean
    mid = len(lines) // 2
    while _stamp(lines[mid]) == _stamp(lines[mid - 1]):
        mid += 1
    shifted = lines[:mid] + [_restamp(ln, _stamp(ln) - shift_s) for ln in lines[mid:]]
    # jitter (less than a tick back) in both segments, away from the seam: neighbours swapped
    for i in (200, 2000, mid + 2000):
        j = i + 1
        while _stamp(shifted[j]) == _stamp(shifted[i]):
            j += 1
        shifted[i], shifted[j] = shifted[j], shifted[i]
    log = d / f"back{shift_s:g}.log"
    log.write_text("\n".join(shifted) + "\n")
    res = replay_candump(log, cfg)

    # the test's own count: frames stamped before the latest stamp of their segment, less than a tick back
    ts = [_stamp(ln) for ln in shifted]
    jitter = 0
    for seg in (ts[:mid], ts[mid:]):
        top = -math.inf
        for t in seg:
            jitter += t < top and top - t < 1.0
            top = max(top, t)
    drop = max(ts[:mid]) - ts[mid]
    # the boundaries of the two segments laid end to end: every integer in (start, joined end]
    end = max(ts[:mid]) + (max(ts[mid:]) - ts[mid])
    want = math.floor(end) - math.floor(ts[0])
    assert len(res.t) == want, f"{len(res.t)} ticks, {want} boundaries in the two segments (clean log: {len(ref.t)})"
    assert abs(len(res.t) - len(ref.t)) <= 1
    c = res.clock  # the counters, against the test's own counts
    assert c["jitter"] == jitter and jitter >= 3  # each swap puts one or more frames behind
    assert c["joined"] == 1 and c["ignored"] == 0 and c["behind_max_s"] == pytest.approx(drop, abs=1e-6)
    # nothing dropped: the hot spot's peak as the clean log gives it
    assert _hot_spot_peak(res) == pytest.approx(_hot_spot_peak(ref), abs=0.3)
    from thermal_edge.service.replay import clock_line

    line = clock_line(c)
    assert "1 jump(s) back" in line and f"at most {drop:.3f} s" in line and "nothing dropped" in line


def test_replay_of_a_log_with_one_stamp_far_ahead(clean) -> None:
    """One frame stamped 1e6 s ahead in the middle (the old clock: bridged a 1e6 s gap, cooled the
    state, then ticked no more): the same ticks and estimates as the clean log."""
    from thermal_edge.service import replay_candump

    d, cfg, lines, ref = clean
    mid = len(lines) // 2
    bad = lines[:mid] + [_restamp(lines[mid], _stamp(lines[mid]) + 1e6)] + lines[mid + 1:]
    log = d / "ahead.log"
    log.write_text("\n".join(bad) + "\n")
    res = replay_candump(log, cfg)
    assert len(res.t) == len(ref.t)
    assert res.clock["ignored"] == 1 and res.clock["gaps"] == 0
    assert _hot_spot_peak(res) == pytest.approx(_hot_spot_peak(ref), abs=0.05)


def test_replay_summary_says_what_the_clock_did(clean) -> None:
    from thermal_edge.service.replay import format_summary, replay_summary

    d, cfg, lines, _ = clean
    mid = len(lines) // 2
    log = d / "summary.log"
    log.write_text("\n".join(lines[:mid] + [_restamp(ln, _stamp(ln) - 100.0) for ln in lines[mid:]]) + "\n")
    s = replay_summary(log, d / "edge.yaml")
    assert s["frame_clock"]["joined"] == 1
    text = format_summary(s)
    assert "frame clock: " in text and "jump(s) back" in text


def _samples(text: str) -> dict[str, float]:
    from prometheus_client.parser import text_string_to_metric_families

    out = {}
    for fam in text_string_to_metric_families(text):
        for smp in fam.samples:
            lab = ",".join(f'{k}="{v}"' for k, v in sorted(smp.labels.items()))
            out[smp.name + ("{" + lab + "}" if lab else "")] = smp.value
    return out


def test_metrics_show_the_frame_clock_counters(engine_config) -> None:
    from thermal_edge.service.engine import ThermalEngine
    from thermal_edge.service.metrics import ServiceMetrics

    eng = ThermalEngine(engine_config, worker_mode="sync")
    c = FrameClock(1.0)
    eng.frame_clock = c.stats  # as the service wires its frame clock
    m = ServiceMetrics()
    m.attach(eng)
    try:
        text = m.text()
        assert "thermal_edge_frame_clock_behind_total 0.0" in text  # from the first scrape
        stamps = [100.0, 100.5, 100.4, 101.2, 60.0, 60.5, 61.1, 61.5, 62.3]  # jitter, then 41.2 s back
        behind = 0
        top = -math.inf
        for t in stamps[:4]:  # the test's own count before the step back
            behind += t < top
            top = max(top, t)
        for ts in stamps:
            for b in eng.ticks_for(c.observe(ts)):
                eng.tick(b)
        got = _samples(m.text())
        # the jitter before the step back, and the step's frames until the clock took it (the third
        # frame covers a tick: CONFIRM_FRAMES of them)
        assert got["thermal_edge_frame_clock_behind_total"] == behind + c.CONFIRM_FRAMES == 4
        assert got['thermal_edge_frame_clock_jumps_total{outcome="joined"}'] == 1
        assert got["thermal_edge_frame_clock_behind_max_seconds"] == pytest.approx(101.2 - 60.0)
    finally:
        eng.close()
