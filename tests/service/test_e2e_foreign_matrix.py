"""A foreign CAN matrix end to end: the Acme MC-7 example (``config/examples/acme-mc7``: its own
DBC, other identifiers and scaling, big-endian power-invariant d/q currents, no counter, no CRC,
temperatures on two frames of their own) runs the service on python-can's ``virtual`` bus with
its edge.yaml only. An independent sender encodes the inverter's frames with cantools, an
independent receiver decodes TE_Limits with cantools; the limits must follow the same physical
currents and temperatures as they do with this project's CAN matrix (sent the same way, its CRC
from crccheck).
"""
from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import cantools
import pytest
import yaml
from crccheck.crc import Crc8SaeJ1850
from svc_testlib import DBC, REPO, async_wait_until, edge_raw, write_yaml

from thermal_edge.config import load_config
from thermal_edge.service import EdgeService

EXAMPLE = REPO / "config" / "examples" / "acme-mc7"
FOREIGN_DBC = EXAMPLE / "acme-mc7.dbc"
T0 = 50_000.0
HOT_S, STALE_S = 70.0, 6.0  # hot, first loaded and then light; then the winding temperatures stop
DROP_S = 30.0  # the load drops from 34 A to 8 A


def physics(t: float) -> dict[str, float]:
    """The machine as both inverters see it at time ``t``: RMS phase current (A), speed (rpm),
    torque (Nm) and temperatures (degC). Hot windings that warm slowly under 34 A, then cool
    slowly under 8 A (readings that move: a reading that stands still while the model heats is
    a stuck sensor)."""
    s = t - T0
    if s < DROP_S:
        current, slot, end = 34.0, 149.0 + 0.05 * s, 151.5 + 0.05 * s
    else:
        current, slot, end = 8.0, 150.5 - 0.02 * (s - DROP_S), 153.0 - 0.02 * (s - DROP_S)
    return {"i_rms": current, "speed": 900.0, "torque": 5.6 * current, "slot": round(slot, 1), "end": round(end, 1),
            "housing": 90.0, "ambient": 25.0}


def _schedule(cycles_s: dict[str, float], t_end: float) -> Iterator[tuple[float, str]]:
    """(time, frame) of every cyclic frame up to ``t_end``, in time order."""
    events = []
    for name, cycle in cycles_s.items():
        n = 0
        while (t := T0 + n * cycle) < t_end:
            events.append((round(t, 6), name))
            n += 1
    return iter(sorted(events))


def native_frames(t_end: float, stale_from: float) -> list[can.Message]:
    """The CAN matrix's frames, encoded by cantools; counter and CRC-8/SAE-J1850 (crccheck) added here."""
    db = cantools.database.load_file(str(DBC))
    counters: dict[str, int] = {}
    out = []
    cycles = {"INV_Currents": 0.01, "INV_Mechanics": 0.01, "INV_StatorTemps": 0.1, "INV_AmbientTemps": 0.1}
    for t, name in _schedule(cycles, t_end):
        p = physics(t)
        peak = math.sqrt(2) * p["i_rms"]  # amplitude-invariant d/q: peak amplitudes
        if name == "INV_StatorTemps" and t >= stale_from:
            continue
        values = {
            "INV_Currents": {"INV_Id": -peak * math.sin(0.4), "INV_Iq": peak * math.cos(0.4), "INV_IphRms": p["i_rms"]},
            "INV_Mechanics": {"INV_Speed": p["speed"], "INV_Torque": p["torque"], "INV_Udc": 560.0},
            "INV_StatorTemps": {"INV_T_WindingSlot": p["slot"], "INV_T_EndWinding": p["end"], "INV_T_Housing": p["housing"],
                                "INV_S_WindingSlot": 0, "INV_S_EndWinding": 0, "INV_S_Housing": 0},
            "INV_AmbientTemps": {"INV_T_Ambient": p["ambient"], "INV_T_Coolant": 30.0, "INV_S_Ambient": 0, "INV_S_Coolant": 0},
        }[name]
        msg = db.get_message_by_name(name)
        k = counters[name] = (counters.get(name, -1) + 1) % 16
        data = bytearray(msg.encode({**values, f"{name}_Counter": k, f"{name}_CRC": 0}))
        did = 0x1000 + msg.frame_id
        data[7] = Crc8SaeJ1850.calc(bytes([did & 0xFF, did >> 8]) + bytes(data[:7]))
        out.append(can.Message(timestamp=t, arbitration_id=msg.frame_id, data=bytes(data), is_extended_id=False))
    return out


def foreign_frames(t_end: float, stale_from: float) -> list[can.Message]:
    """The MC-7's frames, encoded by cantools from its own DBC (power-invariant d/q currents)."""
    db = cantools.database.load_file(str(FOREIGN_DBC))
    out = []
    cycles = {"MC7_Currents": 0.02, "MC7_Motion": 0.02, "MC7_StatorTemps": 0.2, "MC7_Environment": 0.5}
    for t, name in _schedule(cycles, t_end):
        p = physics(t)
        mag = math.sqrt(3) * p["i_rms"]  # power-invariant: i_d² + i_q² = 3 I_rms²
        if name == "MC7_StatorTemps" and t >= stale_from:
            continue
        values = {
            "MC7_Currents": {"MC7_CurrentD": -mag * math.sin(0.4), "MC7_CurrentQ": mag * math.cos(0.4),
                             "MC7_DcLinkVoltage": 560.0},
            "MC7_Motion": {"MC7_MotorSpeed": p["speed"], "MC7_TorqueEst": p["torque"], "MC7_OperatingState": 2},
            "MC7_StatorTemps": {"MC7_TempWindingU": p["slot"], "MC7_TempWindingV": p["end"], "MC7_TempWindingW": p["end"]},
            "MC7_Environment": {"MC7_TempHousing": p["housing"], "MC7_TempCoolantIn": 30.0,
                                "MC7_TempAmbient": p["ambient"], "MC7_TempPowerStage": 50.0},
        }[name]
        msg = db.get_message_by_name(name)
        out.append(can.Message(timestamp=t, arbitration_id=msg.frame_id, data=msg.encode(values), is_extended_id=False))
    return out


def foreign_config(tmp: Path, channel: str, **signals_override: Any) -> Any:
    """The example's edge.yaml as it is, but on the test's virtual bus, in simulated time (frame
    clock), with a temporary state directory; its relative paths made absolute (the copy lives elsewhere)."""
    raw = yaml.safe_load((EXAMPLE / "edge.yaml").read_text())
    raw["bus"] = {"interface": "virtual", "channel": channel, "preserve_timestamps": True}
    raw["codec"]["dbc"] = str(FOREIGN_DBC)
    raw["model"]["path"] = str((EXAMPLE / raw["model"]["path"]).resolve())
    raw["clock"] = {"mode": "frame"}
    raw["state"] = {"dir": str(tmp / "state")}
    raw["metrics"] = {"enabled": False}
    raw["adaptation"] = {"enabled": False}
    for name, override in signals_override.items():
        raw["signals"]["inputs"][name].update(override)
    return load_config(write_yaml(tmp / "edge.yaml", raw))


def native_config(tmp: Path, channel: str) -> Any:
    """The shipped edge.yaml with the example's timeouts (so that both go stale alike)."""
    raw = edge_raw(tmp / "state", {"interface": "virtual", "channel": channel}, table4=False, adapt=False,
                   timeouts={"INV_Currents": 0.2, "INV_Mechanics": 0.2, "INV_StatorTemps": 1.0, "INV_AmbientTemps": 2.0})
    raw["model"]["parameters"] = {}
    return load_config(write_yaml(tmp / "edge.yaml", raw))


Rows = dict[str, list[tuple[float, dict[str, float]]]]


def run_service(config: Any, channel: str, frames: list[can.Message]) -> Rows:
    """Run the service on the virtual bus, send ``frames``, and return what an independent
    receiver decoded of TE_Limits and TE_Forecast: per frame name, (time, signals)."""
    shipped = cantools.database.load_file(str(DBC))
    wanted = {shipped.get_message_by_name(n).frame_id: shipped.get_message_by_name(n) for n in ("TE_Limits", "TE_Forecast")}
    receiver = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    sender = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)  # the frames' own times

    async def main() -> None:
        svc = EdgeService(config)
        await svc.start()
        try:
            await asyncio.to_thread(lambda: [sender.send(m) for m in frames])
            assert await async_wait_until(lambda: sum(svc.codec.stats.received.values()) >= len(frames), 120)
        finally:
            await svc.stop()

    try:
        asyncio.run(main())
        got: Rows = {m.name: [] for m in wanted.values()}
        while (msg := receiver.recv(0.2)) is not None:
            m = wanted.get(msg.arbitration_id)
            if m is not None:
                got[m.name].append((msg.timestamp, {k: float(v) for k, v in m.decode(msg.data, decode_choices=False).items()}))
        return got
    finally:
        receiver.shutdown()
        sender.shutdown()


def _channel() -> str:
    return f"te-foreign-{time.monotonic_ns()}"


@pytest.fixture(scope="module")
def limits(tmp_path_factory) -> dict[str, Rows]:
    out = {}
    t_end, stale_from = T0 + HOT_S + STALE_S, T0 + HOT_S
    runs: dict[str, tuple[Callable[[Path, str], Any], Callable[[float, float], list[can.Message]]]] = {
        "native": (native_config, native_frames),
        "foreign": (foreign_config, foreign_frames),
        "foreign, d/q taken as amplitude-invariant": (
            lambda tmp, ch: foreign_config(tmp, ch, i_rms={"dq": "amplitude_invariant"}), foreign_frames),
    }
    for name, (make_config, make_frames) in runs.items():
        channel = _channel()
        out[name] = run_service(make_config(tmp_path_factory.mktemp("foreign"), channel), channel,
                                make_frames(t_end, stale_from))
    return out


def _by_tick(rows: Rows) -> dict[float, tuple[float, float, int]]:
    """(current limit A, torque limit Nm, reason) of the last TE_Limits of each tick (frames sent
    before the first one carry no time)."""
    return {round(t, 3): (v["TE_CurrentLimit"], v["TE_TorqueLimit"], int(v["TE_DerateReason"]))
            for t, v in rows["TE_Limits"] if t >= T0}


def _time_to_limit(rows: Rows) -> dict[float, float]:
    """TE_TimeToLimit (s) of each tick: the time to the first limit at the present load."""
    return {round(t, 3): v["TE_TimeToLimit"] for t, v in rows["TE_Forecast"] if t >= T0}


def test_the_foreign_matrix_derates_as_the_native_one(limits):
    native, foreign = _by_tick(limits["native"]), _by_tick(limits["foreign"])
    # from the third second: the first ticks wait for each frame's first arrival, which the two
    # matrices' cycles order differently
    common = sorted(t for t in set(native) & set(foreign) if t >= T0 + 3)
    assert len(common) >= HOT_S + STALE_S - 6, (len(native), len(foreign))
    for t in common:
        (a_n, nm_n, r_n), (a_f, nm_f, r_f) = native[t], foreign[t]
        # equal up to one step of the limit's hysteresis: the currents' quantisation differs (0.05 A
        # peak d/q against 0.1 A power-invariant d/q)
        assert abs(a_f - a_n) <= 0.5 and abs(nm_f - nm_n) <= 2.8, (t - T0, native[t], foreign[t])
        assert r_f == r_n, (t - T0, native[t], foreign[t])
    # hot and warming under 34 A: derated for the winding, ever more
    loaded = [foreign[t] for t in common if T0 + 18 <= t < T0 + DROP_S]
    assert loaded and all(a < 20.0 and r == 1 for a, _, r in loaded)
    assert loaded[-1][0] < loaded[0][0] - 5.0
    # cooling under 8 A: the limit climbs back (at its rise rate)
    light = [foreign[t] for t in common if T0 + DROP_S + 25 <= t < T0 + HOT_S]
    assert light and all(r == 1 for _, _, r in light)
    assert min(a for a, _, _ in light) > min(foreign[t][0] for t in common) + 5.0
    end = [foreign[t] for t in common if t >= T0 + HOT_S + 2]
    assert end and all(a == 10.0 and r == 5 for a, _, r in end)  # stale winding temperatures: the safe limit


def test_the_time_to_limit_follows_the_current_as_with_the_native_matrix(limits):
    """TE_TimeToLimit is the time to the first limit at the present load: it reads the current."""
    native, foreign = _time_to_limit(limits["native"]), _time_to_limit(limits["foreign"])
    common = sorted(t for t in set(native) & set(foreign) if T0 + 3 <= t < T0 + HOT_S)
    assert len(common) >= HOT_S - 6
    for t in common:
        assert abs(foreign[t] - native[t]) <= 1.0, (t - T0, native[t], foreign[t])
    loaded = [foreign[t] for t in common if t < T0 + DROP_S]
    assert all(5 < x < 60 for x in loaded) and loaded[-1] < loaded[0]  # 34 A: the limit comes nearer
    assert all(foreign[t] == 65535 for t in common if t >= T0 + DROP_S + 2)  # 8 A: not within the horizon


def test_the_dq_convention_matters(limits):
    """The same run with the power-invariant d/q currents taken as amplitude-invariant: the service
    sees 1.22x the current, and the time to limit is far shorter (what the tests above would catch)."""
    native = _time_to_limit(limits["native"])
    wrong = _time_to_limit(limits["foreign, d/q taken as amplitude-invariant"])
    common = [t for t in set(native) & set(wrong) if T0 + 3 <= t < T0 + DROP_S]
    assert common and all(wrong[t] < 0.6 * native[t] for t in common)


# -- the guide's commands ------------------------------------------------------------------------------
GUIDE = REPO / "docs" / "guide" / "connect-your-inverter.md"


def _blocks(kind: str) -> list[str]:
    import re

    return re.findall(rf"```{kind}\n(.*?)```", GUIDE.read_text(), re.S)


def test_the_guides_check_command_prints_what_the_guide_shows(tmp_path):
    import shlex

    from cli_in_process import te_here

    consoles = _blocks("console")
    assert consoles
    # the example's files where the guide has them written (``config inverter-example mc7``)
    assert te_here("config", "inverter-example", tmp_path / "mc7").returncode == 0
    for block in consoles:
        command, *shown = block.rstrip("\n").split("\n")
        assert command.startswith("$ thermal-edge ")
        args = [str(tmp_path / a) if a.startswith("mc7/") else a for a in shlex.split(command[2:])[1:]]
        proc = te_here(*args)
        assert proc.returncode == 0, proc.stderr
        assert proc.stdout.rstrip("\n").split("\n") == shown


def test_the_guides_refusal_is_the_one_the_check_gives(tmp_path):
    from cli_in_process import te_here

    (shown,) = [b.strip() for b in _blocks("text")]
    raw = yaml.safe_load((EXAMPLE / "edge.yaml").read_text())
    raw["codec"]["dbc"] = str(FOREIGN_DBC)
    raw["model"]["path"] = str((EXAMPLE / raw["model"]["path"]).resolve())
    raw["state"]["dir"] = str(tmp_path / "state")
    del raw["codec"]["protection"]["MC7_Motion"]
    proc = te_here("run", "--check", "--config", write_yaml(tmp_path / "edge.yaml", raw))
    assert proc.returncode == 2 and proc.stderr.strip() == shown


def test_the_guides_edge_yaml_is_the_examples():
    """The guide's excerpt of the MC-7's edge.yaml says what the example file says."""
    excerpts = [yaml.safe_load(b) for b in _blocks("yaml")]
    excerpt = next(e for e in excerpts if "signals" in e)
    example = yaml.safe_load((EXAMPLE / "edge.yaml").read_text())
    for key in ("codec", "signals", "timeouts"):
        assert excerpt[key] == example[key], key
