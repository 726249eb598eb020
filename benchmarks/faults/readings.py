"""Readings that lie together: every PT100 drifting low at once, through ``thermal-edge replay``.

One reference or excitation current shared by the inverter's PT100 inputs drifts, and every
temperature reads low by the same growing amount, slowly enough that each reading agrees with the
one before. The observer follows them, a restart after a model fault starts from them, and the
adaptation learns a machine that cools better: the limit rises while the real winding passes its
maximum. The bench simulates the overload cycle (the plant: the model file, open loop: its true
temperatures are the simulation's), writes its CAN log with every ``INV_StatorTemps`` frame
re-encoded (counter and CRC as the matrix says) reading low by the drift, replays it with
adaptation on, and counts the ticks at which the plant's slot winding is above the hot spot's
``max_c`` while the limit sent is above the safe current: each is unsafe. The control case
(:func:`drift_unguarded`) replays the same log with ``derating.faults.commissioned_gap_k`` at its
upper bound, which the drift never reaches: it must be judged unsafe.
"""
from __future__ import annotations

import csv
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import can
import yaml

from thermal_edge.bus.codec import FrameCodec

from .. import ROOT
from .harness import Case, Check, env, service_config_path, thermal_edge_cmd

#: the drift: from this time on (s), this fast (K/s), up to this much (K) -- the black-box finding
#: that showed it: 0.5 K/min from 50 min, up to 40 K, the machine overloaded from 100 min on
DRIFT_FROM_S, DRIFT_RATE_K_PER_S, DRIFT_CAP_K = 3000.0, 0.5 / 60.0, 40.0
TEMPS = "INV_StatorTemps"


def _drifted(log: Path, out: Path, t0: float) -> int:
    """``log`` with every ``INV_StatorTemps`` frame re-encoded reading low by the drift at its
    stamp (``t0``: the log's first stamp); returns the frames changed."""
    codec = FrameCodec()
    changed = 0
    lines = []
    for line in log.read_text().splitlines():
        stamp, chan, frame, *rest = line.split()  # candump -L: "(stamp) channel id#data [R|T]"
        ident, data = frame.split("#")
        t = float(stamp.strip("()"))
        msg = can.Message(arbitration_id=int(ident, 16), data=bytes.fromhex(data), is_extended_id=len(ident) > 3)
        dec = codec.decode_message(msg)
        if dec is not None and dec.name == TEMPS:
            low = min(max(t - t0 - DRIFT_FROM_S, 0.0) * DRIFT_RATE_K_PER_S, DRIFT_CAP_K)
            sig = {k: (v - low if k.startswith("INV_T_") else v) for k, v in dec.signals.items()}
            data = codec.encode(TEMPS, sig, counter=dec.counter).hex().upper()
            changed += 1
        lines.append(" ".join([stamp, chan, f"{ident}#{data}", *rest]))
    out.write_text("\n".join(lines) + "\n")
    return changed


def _replay(workdir: Path, log: Path, faults: dict[str, float]) -> tuple[list[dict[str, str]], str, int]:
    """Replay ``log`` with the service's configuration, adaptation on and ``faults`` set; returns
    the per-tick table, stderr and the exit status."""
    raw = yaml.safe_load(service_config_path("edge.yaml").read_text())
    raw["model"]["path"] = str(service_config_path("machines", "pm10kw.yaml"))
    raw["adaptation"]["enabled"] = True
    raw["derating"].setdefault("faults", {}).update(faults)
    raw["state"] = {"dir": str(workdir / "state")}
    cfg = workdir / f"edge-{log.stem}.yaml"
    cfg.write_text(yaml.safe_dump(raw))
    table = workdir / f"{log.stem}-ticks.csv"
    r = subprocess.run(thermal_edge_cmd() + ["replay", "--format", "can", "--run", str(log), "--config", str(cfg),
                                             "--out", str(table)],
                       env=env(service=True), cwd=str(workdir), capture_output=True, text=True, timeout=900)
    rows = list(csv.DictReader(ln for ln in table.read_text().splitlines() if not ln.startswith("#"))) \
        if table.exists() else []
    return rows, r.stderr, r.returncode


def _judge(rows: list[dict[str, str]], truth: list[dict[str, str]], max_c: float, safe_a: float) -> tuple[int, int]:
    """(ticks with the plant's slot winding above ``max_c``, of them those with a limit above
    ``safe_a``). Tick ``k`` (its time from the first tick) is judged by the plant at the same time."""
    by_t = {round(float(r["t"])): float(r["slot_winding"]) for r in truth}
    hot = unsafe = 0
    for r in rows:
        w = by_t.get(round(float(r["t"])) + 1)  # the replay's t counts from the first tick, 1 s in
        if w is not None and w > max_c:
            hot += 1
            unsafe += float(r["current_limit_a"]) > safe_a + 1e-6
    return hot, unsafe


def _cases(full: bool, control: bool) -> Iterator[Case]:
    duration = 10800 if full else 7200
    raw = yaml.safe_load(service_config_path("edge.yaml").read_text())
    max_c = float(raw["derating"]["limits"]["hot_spot"]["max_c"])
    safe_a = float(raw["derating"]["safe_current_a"])
    with tempfile.TemporaryDirectory(prefix="te-faults-readings-") as tmp:
        d = Path(tmp)
        common = ["simulate", "--model", str(service_config_path("machines", "pm10kw.yaml")), "--cycle",
                  str(service_config_path("cycles", "overload.yaml")), "--duration", str(duration), "--seed", "0"]
        for fmt, out in (("csv", d / "truth.csv"), ("can", d / "clean.log")):
            subprocess.run(thermal_edge_cmd() + [*common, "--format", fmt, "--out", str(out)], env=env(), cwd=str(ROOT),
                           check=True, capture_output=True, timeout=900)
        truth = list(csv.DictReader(ln for ln in (d / "truth.csv").read_text().splitlines() if not ln.startswith("#")))
        clean = d / "clean.log"
        t0 = float(clean.read_text().split(maxsplit=1)[0].strip("()"))
        changed = _drifted(clean, d / "drift.log", t0)
        gap = {} if not control else {"commissioned_gap_k": 100.0}
        rows, err, rc = _replay(d, d / "drift.log", gap)
        c = Check()
        c.add(0 if rc == 0 and rows else 1, f"replay exit {rc}: {err.strip()[-200:]}")
        hot, unsafe = _judge(rows, truth, max_c, safe_a)
        c.add(unsafe, f"{unsafe} of {hot} ticks with the slot winding above {max_c:.0f} degC sent more than "
                      f"{safe_a:.0f} A")
        c.add(0 if hot else 1, f"the plant never passed {max_c:.0f} degC: nothing was judged")
        said = "readings not believed" in err
        if not control:
            c.add(0 if said else 1, "no log line says the readings are not believed")
        name = "pt100_common_drift_guard_off" if control else "pt100_common_drift"
        did = (f"{changed} {TEMPS} frames {DRIFT_RATE_K_PER_S * 60:.1f} K/min low from {DRIFT_FROM_S:.0f} s (up to "
               f"{DRIFT_CAP_K:.0f} K); winding above max {hot} ticks, {unsafe} of them above {safe_a:.0f} A"
               + ("; 'readings not believed' logged" if said else ""))
        yield Case.of(name, "control" if control else "readings", 1, did, c, control=control)


def drift(full: bool) -> Iterator[Case]:
    """Every PT100 drifting low together: not believed, the safe limit while the winding is over max."""
    yield from _cases(full, control=False)


def drift_unguarded(full: bool) -> Iterator[Case]:
    """The same drift with the commissioned check out of its reach: must be judged unsafe."""
    yield from _cases(full, control=True)


GROUPS = {"readings": drift}
CONTROLS = {"readings_control": drift_unguarded}
