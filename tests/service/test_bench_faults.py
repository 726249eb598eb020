"""``bench faults`` in its short form, group by group: every case must lose nothing and show no
unsafe event. The service runs as a black box (``thermal-edge run`` in its own process on a
``udp_multicast`` group of its own, hop limit 0); the bench's frames, CRC and ``TE_Limits`` decoding
come from the DBC through cantools, not from the project's codec.

A case that fails because of an issue-14 defect still being fixed is listed in
:data:`KNOWN_DEFECTS` (and a case whose only failures are TE_Limits gaps counts as defect 5): its
group's test then reports it as an expected failure, but any other failing case fails the test.
Remove an entry (and :func:`_gaps_only`) once its defect is fixed.
"""
from __future__ import annotations

import time

import pytest

from thermal_edge.bench import faults
from thermal_edge.bench.faults import harness, wire

_D5 = "issue 14 defect 5 (TE_Limits gaps over 300 ms under host load), being fixed"
#: case name -> why it is expected to fail today (measured at 03:59 UTC on 2026-11-24; remove when fixed)
KNOWN_DEFECTS: dict[str, str] = {
}

#: groups within the suite's budget (the whole suite must stay under 10 min on 2 cores); the rest are
#: marked slow (make test-all; the bench itself runs them all)
FAST = ("bad_frames", "security", "metrics")
SLOW = ("floods", "stale", "bus", "sensors", "stuck", "absurd", "band", "configs", "states", "crash", "load", "soak",
        "persist", "clock")


def _gaps_only(case: dict) -> bool:
    """Whether a case's only failures are TE_Limits gaps over 300 ms (defect 5: seen intermittently
    in any case while the shared machine is loaded, so not listed case by case)."""
    notes = case["did"].split(" | UNSAFE: ", 1)[-1].split("; ")
    return case["lost"] == 0 and all("TE_Limits gap(s) > 300 ms" in n for n in notes)


def _known(case: dict) -> str | None:
    return KNOWN_DEFECTS.get(case["name"]) or (_D5 if _gaps_only(case) else None)


def _check_group(group: str) -> None:
    r = faults.run(only=[group], progress=False)
    print("\n" + faults.report_table(r))
    assert r["total_cases"] >= 1
    assert not any(c["name"].endswith("_bench_error") for c in r["cases"]), r["cases"]
    bad = [c for c in r["cases"] if c["lost"] or c["unsafe"]]
    unexpected = [c for c in bad if _known(c) is None]
    assert not unexpected, "\n".join(f"{c['name']}: lost {c['lost']}, unsafe {c['unsafe']}: {c['did']}" for c in unexpected)
    if bad:
        pytest.xfail("; ".join(f"{c['name']} ({_known(c)})" for c in bad))


@pytest.mark.parametrize("group", FAST)
def test_fault_group_short(group: str, udp_ok: None) -> None:
    _check_group(group)


@pytest.mark.slow
@pytest.mark.parametrize("group", SLOW)
def test_fault_group_short_slow(group: str, udp_ok: None) -> None:
    _check_group(group)


def test_every_group_is_in_the_suite() -> None:
    assert set(FAST) | set(SLOW) == set(faults.GROUPS)


def test_the_lists_hold_the_issue_counts(tmp_path) -> None:
    """Every bad frame kind of the issues (the undecodable ones among them), ≥ 20 broken
    configurations, ≥ 15 corrupt or foreign state files, every sensor fault on each stator sensor
    (counted from the bench's own lists, without running anything)."""
    from thermal_edge.bench.faults import bus, state

    assert {"bad_crc", "short_dlc", "unknown_id", "extended_id", "remote_frame", "error_frame", "can_fd", "not_msgpack",
            "classic_12_bytes", "std_id_0x800", "remote_with_data"} <= set(wire.BAD_KINDS)
    assert wire.UNDECODABLE <= set(wire.BAD_KINDS)
    seed = {"format": "thermal_edge.state", "parameters": {}, "T": [25.0] * 39,
            "nodes": ["magnet"] + [f"n{k}" for k in range(38)]}
    assert len(state._state_variants(seed, full=False)) >= 15
    assert len(state._config_variants(harness.edge_config(tmp_path, "ff15::1", 1), tmp_path)) >= 20
    assert set(bus.SENSORS) == {"slot_winding", "end_winding", "housing"} and "not_fitted" in bus.SENSOR_FAULTS


# ---- the bench's own pieces, against independent values --------------------------------------
def test_crc_is_the_matrix_check_value_and_agrees_with_the_service_codec() -> None:
    from thermal_edge.bus import FrameCodec

    assert wire.crc8_j1850(b"123456789") == 0x4B
    sig = {"INV_Id": 1.0, "INV_Iq": 20.0, "INV_IphRms": 14.1}
    for k in range(16):
        assert wire.encode("INV_Currents", sig, k) == FrameCodec().encode("INV_Currents", sig, counter=k)


def test_band_limit_is_linear_between_warning_and_maximum() -> None:
    warn, top = harness.HOT_SPOT_BAND
    assert harness.band_limit_a(warn - 10) == harness.MAX_A
    assert harness.band_limit_a(top) == 0.0
    assert harness.band_limit_a((warn + top) / 2) == pytest.approx(harness.MAX_A / 2)


def test_gaps_count_the_silence_at_both_ends() -> None:
    lim = harness.Limits(t=[10.0, 10.1, 10.2, 10.9, 11.0], current=[5.0] * 5, torque=[1.0] * 5, reason=[0] * 5, crc_ok=[1] * 5)
    assert harness.gaps(lim, 9.5, 11.2) == pytest.approx([0.5, 0.7])
    assert harness.runs_above(harness.Limits(t=[1, 2, 3, 4], current=[9, 11, 9, 12], torque=[0] * 4, reason=[0] * 4,
                                             crc_ok=[1] * 4), 0, 5, 10.0) == 2


def test_monitor_stamps_te_limits_from_an_independent_socket(udp_ok: None, tmp_path) -> None:
    """The monitor process decodes TE_Limits sent by hand (and skips an undecodable datagram)."""
    group, port = harness.unique_group(), harness.free_port()
    mon = harness.Monitor(group, port, tmp_path)
    try:
        sock = wire.sender_socket(group)
        sock.sendto(b"\xc1 not msgpack", (group, port))
        for k in range(3):
            data = wire.encode("TE_Limits", {"TE_TorqueLimit": 56.0, "TE_CurrentLimit": 10.0, "TE_DerateActive": 1,
                                             "TE_DerateReason": 5}, k)
            sock.sendto(wire.datagram(wire.TE_LIMITS_ID, data), (group, port))
            time.sleep(0.05)
        sock.close()
        deadline = time.monotonic() + 5
        while len(mon.read().t) < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        lim = mon.read()
        assert lim.current == [10.0] * 3 and lim.reason == [5] * 3 and lim.crc_ok == [1] * 3
        assert all(0.03 < b - a < 0.2 for a, b in zip(lim.t, lim.t[1:]))
    finally:
        mon.close()


def test_only_gap_failures_are_taken_for_defect_5() -> None:
    gaps = "x | UNSAFE: 2 TE_Limits gap(s) > 300 ms (max 703 ms)"
    assert _gaps_only({"lost": 0, "did": gaps})
    assert not _gaps_only({"lost": 3, "did": gaps})
    assert not _gaps_only({"lost": 0, "did": gaps + "; 1 limit(s) above the maximum"})
