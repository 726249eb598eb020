"""The service on real SocketCAN (vcan0) in the qemu VM: closed loop with the inverter emulator,
can-utils as an independent client, and a bus fault (link down/up).

One VM boot runs ``tests/vm/guest_service_scenario.py`` (one ``thermal-edge run`` through three
phases, ~3-4 min under software emulation); the tests below judge its metrics snapshots and the
``candump -L vcan0`` capture on the host. The frames fed with ``cansend`` are encoded here on the
host with the DBC (``FrameCodec.encode``); the capture is decoded here with ``python -m cantools
decode`` and ``FrameCodec.decode`` and replayed with ``replay_summary``.
"""
from __future__ import annotations

import json
import math
import os
import re
import statistics
import subprocess
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
VENV_PY = REPO / ".venv" / "bin" / "python"
DBC = REPO / "dbc" / "thermal_edge.dbc"
# closed loop in the guest, s: 4,000 current frames and 400 TE_Limits periods (60 s cost 20 s more of the suite's longest test)
EMU_S = 40.0
FEED_N = 48  # cansend rounds in phase B (3 x the 16 counter values)
SAFE_A = 10.0  # derating.safe_current_a of config/edge.yaml (the guest uses it unchanged)

#: What the cansend feed carries (physical values; encoded on the host).
FEED_VALUES: dict[str, dict[str, float]] = {
    "INV_Currents": {"INV_Id": -5.0, "INV_Iq": 20.0, "INV_IphRms": 14.6},
    "INV_Mechanics": {"INV_Speed": 900.0, "INV_Torque": 80.0, "INV_Udc": 400.0},
    "INV_StatorTemps": {"INV_T_WindingSlot": 31.2, "INV_T_EndWinding": 33.4, "INV_T_Housing": 27.5,
                        "INV_S_WindingSlot": 0, "INV_S_EndWinding": 0, "INV_S_Housing": 0},
    "INV_AmbientTemps": {"INV_T_Ambient": 25.0, "INV_T_Coolant": 26.0, "INV_S_Ambient": 0, "INV_S_Coolant": 0},
}

_CANDUMP = re.compile(r"^\((\d+\.\d+)\)\s+(\w+)\s+([0-9A-Fa-f]+)#([0-9A-Fa-f]*)\s*$")


def parse_candump(text: str) -> list[tuple[float, str, int, bytes]]:
    out = []
    for line in text.splitlines():
        m = _CANDUMP.match(line)
        if m:
            out.append((float(m.group(1)), m.group(2), int(m.group(3), 16), bytes.fromhex(m.group(4))))
    return out


def codec():
    from thermal_edge.bus import FrameCodec

    return FrameCodec(DBC)


def lost_without_loss(d: Path) -> int:
    """How many frames the service may count lost in the emulator's part of the capture (up to
    its last INV_Currents) though every one arrived, from the capture itself: 16 (a counter wrap)
    for each frame delivered after a later one of its identifier (on an SMP guest vcan may swap two
    frames when the sender moves between CPUs; their kernel time stamps keep the true order: the
    4-bit counter then reads as a jump of 15), and the missing cycles of each stall of 16 cycles or
    more (the emulator descheduled in a TCG guest on a busy host). 0 on a quiet host."""
    c = codec()
    frames = parse_candump((d / "candump-all.log").read_text())
    n_cur = json.loads((d / "emulator-summary.json").read_text())["frames_sent"]["INV_Currents"]
    cur = [t for t, _, fid, _ in frames if fid == c.frame_id("INV_Currents")]
    t_end = cur[n_cur - 1]
    by_id: dict[int, list[float]] = {}
    for t, _, fid, _ in frames:
        if fid < 0x200 and t <= t_end:  # the emulator's frames, in the order delivered
            by_id.setdefault(fid, []).append(t)
    total = 0
    for fid, ts in by_id.items():
        cycle = c.cycle_time_s(fid) or 0.0
        for a, b in zip(ts, ts[1:]):
            if b < a:
                total += 16
            elif cycle and round((b - a) / cycle) >= 16:
                total += round((b - a) / cycle) - 1
    return total


def host_feed() -> tuple[dict, dict[str, dict[str, float]]]:
    """{frame: {"id": "0A0", "hex": [16 payloads, counter 0..15]}} and the values the DBC gives back."""
    enc, dec = codec(), codec()
    feed, decoded = {}, {}
    for name, values in FEED_VALUES.items():
        hexes = [enc.encode(name, values, counter=k).hex().upper() for k in range(16)]
        fid = enc.frame_id(name)
        feed[name] = {"id": f"{fid:03X}", "hex": hexes}
        d = dec.decode(fid, bytes.fromhex(hexes[0]))
        assert d is not None, name
        decoded[name] = d.signals
    return feed, decoded


def metric(snap: dict[str, float], name: str, **labels: str) -> float | None:
    want = [f'{k}="{v}"' for k, v in labels.items()]
    for key, value in snap.items():
        if key == name or (key.startswith(name + "{") and all(w in key for w in want)):
            return value
    return None


def msum(snap: dict[str, float], name: str) -> float:
    return sum(v for k, v in snap.items() if k == name or k.startswith(name + "{"))


def delta(a: dict[str, float], b: dict[str, float], name: str) -> float:
    return msum(b, name) - msum(a, name)


# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def scenario(request, tmp_path_factory):
    """The scenario's result; ``THERMAL_EDGE_VM_SERVICE_REUSE=DIR`` judges the artifacts of an earlier
    run kept in DIR instead of booting the VM (for working on the assertions)."""
    feed, decoded = host_feed()
    reuse = os.environ.get("THERMAL_EDGE_VM_SERVICE_REUSE")
    if reuse:
        out, wall, kernel, boot = Path(reuse), float("nan"), "?", float("nan")
    else:
        vm = request.getfixturevalue("vm")
        t = time.monotonic()
        res = vm.run(f"{VENV_PY} tests/vm/guest_service_scenario.py", timeout=900,
                     env={"SCENARIO_EMU_S": str(EMU_S), "SCENARIO_FEED_N": str(FEED_N)},
                     files={"feed.json": json.dumps(feed)})
        wall = time.monotonic() - t
        out = tmp_path_factory.mktemp("vm_service")
        for name, data in res.artifacts.items():
            (out / name).write_bytes(data)
        assert "scenario.json" in res.artifacts, (
            f"no result (exit {res.returncode}):\n{res.stdout[-4000:]}\n{res.stderr[-3000:]}\n{res.console[-2000:]}")
        kernel, boot = res.kernel, res.boot_seconds
    result = json.loads((out / "scenario.json").read_text())
    result["_dir"] = out
    result["_vm_wall_s"] = wall
    result["_feed"] = feed
    result["_feed_decoded"] = decoded
    print(f"\n[vm service] guest kernel {kernel}, VM wall {wall:.0f} s (boot {boot:.1f} s), "
          f"READY at {result.get('ready_s')} s, scenario {result.get('wall_s')} s; artifacts in {out}")
    for t_s, what in result.get("events", []):
        print(f"  [{t_s:7.1f}s] {what}")
    return result


def _service_log(sc) -> str:
    p = sc["_dir"] / "service.log"
    return p.read_text()[-3000:] if p.exists() else "(no service.log)"


# ------------------------------------------------------------------------------------------------
def test_service_and_simulated_machine_on_vcan0(scenario):
    sc, d = scenario, scenario["_dir"]
    assert sc["ready_s"] is not None, _service_log(sc)
    print(f"kernel {sc['kernel']}; vcan0: {sc['vcan0'].splitlines()[0]}")
    assert "vcan0" in sc["vcan0"] and "link/can" in sc["vcan0"] and re.search(r"\bvcan\b", sc["vcan0"])
    assert sc["rc_emulator"] == 0, (d / "emulator.log").read_text()[-3000:]
    summary = json.loads((d / "emulator-summary.json").read_text())
    a0, a1 = sc["snapshots"]["A_start"], sc["snapshots"]["A_end"]
    sent = summary["frames_sent"]
    received = {k: metric(a1, "thermal_edge_frames_received_total", frame=k) for k in sent}
    te_sent = (metric(a1, "thermal_edge_frames_sent_total", frame="TE_Limits")
               - metric(a0, "thermal_edge_frames_sent_total", frame="TE_Limits"))
    print(f"emulator: sim {summary['sim_seconds']:.0f} s in wall {summary['wall_seconds']:.1f} s, sent {sent}, "
          f"received {summary['frames_received']}, limits_received {summary['limits_received']}, "
          f"limits_applied_s {summary['limits_applied_s']:.1f}, limited_s {summary['limited_s']:.1f}, "
          f"true max {summary['true_max_c']}")
    print(f"service: received {received}, dropped {msum(a1, 'thermal_edge_frames_dropped_total')}, "
          f"lost {msum(a1, 'thermal_edge_frames_lost_all_total')}, resync {msum(a1, 'thermal_edge_frames_resynced_total')}, "
          f"TE_Limits sent in A {te_sent}")
    # frames flow both ways, none lost or corrupted
    assert summary["sim_seconds"] == pytest.approx(EMU_S)
    assert all(n > 0 for n in sent.values()) and set(sent) >= set(FEED_VALUES)
    assert received == sent, (received, sent)
    for reason in ("crc", "counter_repeat", "unknown_id", "dlc", "decode_error"):
        assert metric(a1, "thermal_edge_frames_dropped_total", reason=reason) == 0, reason
    frames = parse_candump((d / "candump-all.log").read_text())
    bound = lost_without_loss(d)  # every frame arrived (received == sent)
    assert msum(a1, "thermal_edge_frames_lost_all_total") <= bound, bound
    assert summary["rx_lost"] == 0 and sum(summary["rx_dropped"].values()) == 0 and summary["send_failures"] == 0
    assert summary["frames_received"].get("TE_Limits", 0) > 0 and summary["frames_received"].get("TE_Status", 0) > 0
    assert frames and all(ch == "vcan0" for _, ch, _, _ in frames)
    c = codec()
    lim_id, cur_id = c.frame_id("TE_Limits"), c.frame_id("INV_Currents")
    inv_ts = [t for t, _, i, _ in frames if i == cur_id]
    t_a0, t_a1 = inv_ts[0], inv_ts[sent["INV_Currents"] - 1]  # the emulator's first and last INV_Currents
    # counter_resync counts frames of one ID arriving more than 8 cycles (80 ms for INV_Currents)
    # after the previous one: a stall of the emulated machine (none on an idle host; 82-381 of 13,200
    # frames with the host busy). Counted again from candump's capture (the kernel's time stamps on
    # another socket: a gap within 1 % of the threshold may fall either way)
    sure = possible = 0
    for name in sent:
        fid, limit = c.frame_id(name), 8 * c.cycle_time_s(name)
        ts = [t for t, _, i, _ in frames if i == fid and t <= t_a1 + 0.05]
        gaps = [b - a for a, b in zip(ts, ts[1:])]
        sure += sum(g > limit * 1.01 for g in gaps)
        possible += sum(g > limit * 0.99 for g in gaps)
    resynced = msum(a1, "thermal_edge_frames_resynced_total")
    print(f"resyncs: service {resynced:.0f}, candump's gaps above 8 cycles {sure}-{possible}")
    assert sure <= resynced <= possible
    # every frame of phase A on the wire, both directions: CRC good, alive counter +1 each (judged
    # without timestamps, so no gap can hide behind a resync)
    hc = codec()
    acc = sum(1 for t, _, fid, data in frames if t <= t_a1 + 0.05 and hc.decode(fid, data) is not None)
    n_a = sum(1 for t, _, _, _ in frames if t <= t_a1 + 0.05)
    print(f"host FrameCodec over the phase-A capture: {acc}/{n_a} accepted, lost {hc.stats.lost}, drops {hc.stats.dropped}")
    assert acc == n_a and hc.stats.lost == 0 and sum(hc.stats.dropped.values()) == 0
    # TE_Limits at its cycle (0.1 s) during phase A, from the capture of the bus
    lim_ts = [t for t, _, i, _ in frames if i == lim_id and t_a0 <= t <= t_a1]
    gaps = [b - a for a, b in zip(lim_ts, lim_ts[1:])]
    gaps_sorted = sorted(gaps)
    p99 = gaps_sorted[int(0.99 * (len(gaps) - 1))]
    print(f"TE_Limits in phase A: {len(lim_ts)} over {t_a1 - t_a0:.1f} s, median gap {statistics.median(gaps) * 1e3:.1f} ms, "
          f"p99 {p99 * 1e3:.0f} ms, max {max(gaps) * 1e3:.0f} ms")
    late = [(round(g, 3), round(a - t_a0, 2)) for g, a in zip(gaps, lim_ts) if g > 0.3]
    print(f"TE_Limits gaps > 300 ms (gap s, at s after the emulator's first frame): {late}")
    # never faster than its cycle (a fixed-rate sender that skips missed periods puts at most span / 0.1
    # + 3 frames into a span). How regular the cadence stays in an emulated guest on a host busy with
    # other work (median, p99, gaps past the inverter's 300 ms) is reported above: it measures the host;
    # the 300 ms contract is judged by the fault bench (benchmarks/faults)
    assert len(lim_ts) >= 2 and len(lim_ts) <= (lim_ts[-1] - lim_ts[0]) / 0.1 + 3
    # the closed loop obeys the limit: every INV_Currents after the first TE_Limits is within the
    # largest current limit sent in the 0.5 s before it (the emulator applies the latest it got)
    import cantools

    db = cantools.database.load_file(str(DBC))
    limits: list[tuple[float, float, float]] = []
    checked = violations = clamped = absent = 0
    last_absent = -math.inf
    over: list = []
    worst = 0.0
    for t, _, fid, data in frames:
        if t > t_a1:
            break
        if fid == lim_id:
            s = db.decode_message(fid, data, decode_choices=False)
            limits.append((t, float(s["TE_CurrentLimit"]), float(s["TE_TorqueLimit"])))
        elif fid == cur_id and limits:
            s = db.decode_message(fid, data)
            # not judged: the first step (none received yet); no TE_Limits for 300 ms (the emulator's
            # limit timed out, unclamped) and the plant step after it
            if t - t_a0 < 0.2 or t - limits[-1][0] > 0.3 or t - last_absent < 0.5:
                absent += 1
                last_absent = t if t - limits[-1][0] > 0.3 else last_absent
                continue
            allowed = max(l[1] for l in limits if t - 0.5 <= l[0] <= t)
            checked += 1
            worst = max(worst, s["INV_IphRms"] - allowed)
            if s["INV_IphRms"] > allowed + 0.06:
                violations += 1
                over.append((round(t - t_a0, 3), s["INV_IphRms"], allowed))
            if abs(s["INV_IphRms"] - allowed) <= 0.06:
                clamped += 1
    lim_values = sorted({l[1] for l in limits})
    print(f"closed loop: {checked} INV_Currents checked against TE_CurrentLimit, {violations} above, {clamped} at the limit, "
          f"{absent} without a TE_Limits in the last 300 ms (not judged), "
          f"worst excess {worst:+.2f} A {over[:10]}; limits sent {lim_values[:3]}..{lim_values[-3:]}")
    # (how many INV_Currents had a TE_Limits of the last 300 ms to be judged against, and how long the
    # emulator applied limits, depend on the gaps a busy host leaves: reported, not bounded)
    assert checked > 0 and violations == 0 and clamped > 0
    assert summary["limits_applied_s"] > 0


def test_can_utils_client_cansend_candump_cantools(scenario):
    sc, d = scenario, scenario["_dir"]
    assert sc["ready_s"] is not None, _service_log(sc)
    snaps = sc["snapshots"]
    a1, b2, b_end = snaps["A_end"], snaps["B_2"], snaps["B_end"]
    dec = sc["_feed_decoded"]
    # 1. cansend -> the service decodes exactly what the host encoded
    meas = {s: metric(b2, "thermal_edge_sensor_measurement_celsius", sensor=s)
            for s in ("slot_winding", "end_winding", "housing")}
    inputs = {k: metric(b2, "thermal_edge_input_value", input=k) for k in ("i_rms", "speed_rpm", "torque_nm", "ambient_c")}
    st, cu, me, am = dec["INV_StatorTemps"], dec["INV_Currents"], dec["INV_Mechanics"], dec["INV_AmbientTemps"]
    print(f"cansend feed: service measured {meas}, inputs {inputs}")
    assert meas == {"slot_winding": pytest.approx(st["INV_T_WindingSlot"], abs=1e-9),
                    "end_winding": pytest.approx(st["INV_T_EndWinding"], abs=1e-9),
                    "housing": pytest.approx(st["INV_T_Housing"], abs=1e-9)}
    assert st["INV_T_WindingSlot"] == pytest.approx(31.2, abs=1e-9)
    i_rms = math.sqrt((cu["INV_Id"] ** 2 + cu["INV_Iq"] ** 2) / 2)
    assert inputs["i_rms"] == pytest.approx(i_rms, abs=1e-9)
    assert inputs["speed_rpm"] == pytest.approx(round(me["INV_Speed"]), abs=1e-9)
    assert inputs["torque_nm"] == pytest.approx(me["INV_Torque"], abs=1e-9)
    assert inputs["ambient_c"] == pytest.approx(am["INV_T_Ambient"], abs=1e-9)
    # every cansend that succeeded was received and accepted; nothing dropped as corrupt
    feed_log = (d / "cansend-feed-B.log").read_text().splitlines()
    ok = {n: sum(1 for l in feed_log if l.startswith(f"ok {n} ")) for n in FEED_VALUES}
    fail = sum(1 for l in feed_log if l.startswith("fail "))
    got = {n: metric(b_end, "thermal_edge_frames_received_total", frame=n)
           - metric(a1, "thermal_edge_frames_received_total", frame=n)
           for n in FEED_VALUES}
    drops = {r: metric(b_end, "thermal_edge_frames_dropped_total", reason=r)
             for r in ("crc", "counter_repeat", "unknown_id", "dlc", "decode_error")}
    print(f"cansend (phase B): ok {ok}, failed {fail}; service received {got}; drops {drops}; "
          f"counter resync (+) {delta(a1, b_end, 'thermal_edge_frames_resynced_total')} (feed ~10 Hz vs 10 ms cycle), "
          f"lost (+) {delta(a1, b_end, 'thermal_edge_frames_lost_all_total')}")
    assert ok == {n: FEED_N for n in FEED_VALUES} and fail == 0
    assert got == ok
    assert delta(a1, b_end, "thermal_edge_frames_lost_all_total") == 0
    assert all(v == 0 for v in drops.values())
    # 2. candump -L vcan0 captured the service's transmissions: python -m cantools decodes every one,
    #    FrameCodec.decode (fresh, in order) accepts every one: counters and CRCs valid
    cap = (d / "candump-all.log").read_text() + (d / "candump-after-up.log").read_text()
    frames = parse_candump(cap)
    te = [f for f in frames if f[2] >= 0x200]
    assert te, "no service frames captured"
    log_te = "".join(f"({t:.6f}) {ch} {fid:03X}#{data.hex().upper()}\n" for t, ch, fid, data in te)
    out = subprocess.run([str(VENV_PY), "-m", "cantools", "decode", "--single-line", str(DBC)], input=log_te,
                         capture_output=True, text=True, timeout=300, env={**os.environ, "MPLBACKEND": "Agg"})
    assert out.returncode == 0, out.stderr
    lines = [l for l in out.stdout.splitlines() if l.strip()]
    names = {}
    for l in lines:
        m = re.search(r"\b(TE_\w+)\(", l)
        assert m, l
        names[m.group(1)] = names.get(m.group(1), 0) + 1
    assert len(lines) == len(te)
    counts_per_file = {}
    c = codec()
    for name in ("candump-all.log", "candump-after-up.log"):
        c = codec()  # the after-up capture starts a new run of counters
        fr = [f for f in parse_candump((d / name).read_text()) if f[2] >= 0x200]
        accepted = sum(1 for t, _, fid, data in fr if c.decode(fid, data, timestamp=t) is not None)
        st_ = c.stats
        counts_per_file[name] = dict(frames=len(fr), accepted=accepted, lost=st_.lost, resync=st_.counter_resync,
                                     **st_.dropped)
        assert accepted == len(fr), (name, counts_per_file[name])
        assert st_.crc == 0 and st_.counter_repeat == 0 and st_.dlc == 0 and st_.decode_error == 0
    print(f"candump -L capture: {len(frames)} frames, {len(te)} from the service decoded by cantools {names}; "
          f"FrameCodec: {counts_per_file}")
    assert counts_per_file["candump-all.log"]["lost"] == 0
    # 3. the capture replays (thermal-edge replay --format candump equivalent) on the host
    from thermal_edge.service.replay import replay_summary

    cfg = d / "edge.yaml"
    rep = replay_summary(d / "candump-all.log", cfg)
    print("replay of the capture: " + json.dumps({k: v for k, v in rep.items() if k not in ("parameters",)})[:1500])
    assert rep["frames"] > 0 and rep["ticks"] >= EMU_S * 0.8
    assert rep["malformed_lines"] == 0 and rep["frames_lost"] <= lost_without_loss(d)
    assert sum(rep["frames_dropped"].values()) == 0, rep["frames_dropped"]
    rec = d / "service-can.log"
    if rec.exists():
        rep2 = replay_summary(rec, cfg)
        keys = ("frames", "ticks", "frames_lost", "frames_dropped", "malformed_lines")
        print("replay of the service's own recording: " + json.dumps({k: rep2[k] for k in keys}))


def test_link_down_up_reconnects_and_derates_safely(scenario):
    sc, d = scenario, scenario["_dir"]
    assert sc["ready_s"] is not None, _service_log(sc)
    snaps = sc["snapshots"]
    before = snaps["C_before_down"]
    down = [v for k, v in snaps.items() if k.startswith("C_down_")]
    up = [v for k, v in snaps.items() if k.startswith("C_up_")] + [snaps["C_end"]]
    key = lambda s: (s.get("thermal_edge_transport_bus_errors_total"), s.get("thermal_edge_transport_reconnects_total"),  # noqa: E731
                     s.get("thermal_edge_current_limit_amperes"), s.get("thermal_edge_derate_reason_code"))
    print("bus fault (bus_errors, reconnects, current limit, reason): before " + str(key(before))
          + "; down " + str([key(s) for s in down]) + "; up " + str([key(s) for s in up]))
    print(f"candump -L started before down still alive after down: {sc.get('candump_all_alive_after_down')}")
    assert key(before)[2] is not None
    errs0, rec0 = before["thermal_edge_transport_bus_errors_total"], before["thermal_edge_transport_reconnects_total"]
    assert max(s["thermal_edge_transport_bus_errors_total"] for s in down + up) > errs0
    assert snaps["C_end"]["thermal_edge_transport_reconnects_total"] > rec0
    # blind: the safe limit with reason stale input (5) or sensor fault (4), once the timeouts ran out
    blind = down[1:]
    assert blind and all(s["thermal_edge_current_limit_amperes"] == pytest.approx(SAFE_A) for s in blind), [key(s) for s in blind]
    assert all(int(s["thermal_edge_derate_reason_code"]) in (4, 5) for s in blind), [key(s) for s in blind]
    assert all(s.get("thermal_edge_derate_active") == 1 for s in blind)
    # after up: the service transmits again (captured by a candump started after up), every frame valid
    fr = parse_candump((d / "candump-after-up.log").read_text())
    c = codec()
    lim_id = c.frame_id("TE_Limits")
    lims = [c.decode(fid, data, timestamp=t) for t, _, fid, data in fr if fid == lim_id]
    assert lims and all(x is not None for x in lims)
    seen = [(round(x.signals["TE_CurrentLimit"], 2), int(x.signals["TE_DerateReason"])) for x in lims]
    print(f"after up: {len(lims)} TE_Limits captured, first {seen[:3]}, last {seen[-1]}; "
          f"INV frames received again: {delta(snaps['C_up_0'], snaps['C_end'], 'thermal_edge_frames_received_total')}")
    assert delta(snaps["C_up_0"], snaps["C_end"], "thermal_edge_frames_received_total") > 0


def test_service_recording_marks_received_frames_rx_and_replays(scenario):
    rec = scenario["_dir"] / "service-can.log"
    lines = rec.read_text().splitlines()
    inv = [l for l in lines if re.search(r"\s0B[01]#|\s0A[01]#", l)]
    print(f"service recording: {len(lines)} lines, {len(inv)} inverter frames, "
          f"{sum(1 for l in inv if l.endswith(' T'))} of them marked T")
    assert inv and all(l.endswith(" R") for l in inv)
    from thermal_edge.service.replay import replay_summary

    assert replay_summary(rec, scenario["_dir"] / "edge.yaml")["frames"] > 0
