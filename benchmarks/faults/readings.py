"""Readings that lie plausibly, through ``thermal-edge replay``: every PT100 drifting low at once,
the winding PT100s frozen with their converter's noise, and the current frame read ten times low.

One reference or excitation current shared by the inverter's PT100 inputs drifts, and every
temperature reads low by the same growing amount, slowly enough that each reading agrees with the
one before. The observer follows them, a restart after a model fault starts from them, and the
adaptation learns a machine that cools better: the limit rises while the real winding passes its
maximum. The bench simulates the overload cycle (the plant: the model file, open loop: its true
temperatures are the simulation's), writes its CAN log with every ``INV_StatorTemps`` frame
re-encoded (counter and CRC as the matrix says) reading low by the drift, replays it with
adaptation on, and counts the ticks at which the plant's slot winding is above the hot spot's
``max_c`` while the limit sent is above the safe current: each is unsafe. The winding PT100s
frozen from 100 min on, still flickering with 0.1 K of noise in 0.1 K steps (a channel whose
converter holds its last sample), are judged the same way and must be named stuck. The current
frame read ten times low from 50 min on (a DBC scaling, a second sender diluting it) must not be
believed: no tick above the safe current once the check has confirmed, wherever the machine's
current is one it judges. An inverter whose own DBC has a wider status signal flags the slot
winding with a code the matrix does not define while its reading lies low: the reading must be a
sensor fault (``unknown_status``), never a valid one. The control cases (:func:`drift_unguarded`) replay the same logs with
``derating.faults.commissioned_gap_k`` at its upper bound, which the drift never reaches, and with
``current_torque_ratio`` at 0.01: each must be judged unsafe.
"""
from __future__ import annotations

import csv
import re
import subprocess
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import numpy as np
import yaml

from thermal_edge.bus import DerateReason
from thermal_edge.bus.codec import FrameCodec
from thermal_edge.bus.frames import DEFAULT_DBC_PATH

from .. import ROOT
from .harness import Case, Check, env, service_config_path, thermal_edge_cmd

#: K: while the drifted readings are not believed, the estimates published lie at most this far below
#: the machine's (the commissioned prediction they are then judged against is stepped once every ten
#: ticks with their mean inputs: about a kelvin behind an overload's heating)
PUBLISHED_K = 3.0
#: the drift: from this time on (s), this fast (K/s), up to this much (K): 0.5 K/min from 50 min,
#: up to 40 K, the machine overloaded from 100 min on
DRIFT_FROM_S, DRIFT_RATE_K_PER_S, DRIFT_CAP_K = 3000.0, 0.5 / 60.0, 40.0
TEMPS = "INV_StatorTemps"


#: the winding PT100s freeze from this time on (s), flickering with this noise (K, sigma) in steps of
#: their resolution (K)
FREEZE_FROM_S, FREEZE_NOISE_K, RESOLUTION_K = 6000.0, 0.1, 0.1
WINDING = ("INV_T_WindingSlot", "INV_T_EndWinding")

#: a fault: (seconds since the log's first stamp, the frame's temperatures) -> the temperatures read
Fault = Callable[[float, dict[str, float]], dict[str, float]]


def common_drift(dt: float, temps: dict[str, float]) -> dict[str, float]:
    """Every temperature low by the drift ``dt`` s into the log."""
    low = min(max(dt - DRIFT_FROM_S, 0.0) * DRIFT_RATE_K_PER_S, DRIFT_CAP_K)
    return {k: v - low for k, v in temps.items()}


def frozen_with_noise(seed: int = 0) -> Fault:
    """The winding temperatures held at their value at :data:`FREEZE_FROM_S`, with the converter's
    noise, quantised to the resolution."""
    rng = np.random.default_rng(seed)
    held: dict[str, float] = {}

    def fault(dt: float, temps: dict[str, float]) -> dict[str, float]:
        if dt < FREEZE_FROM_S:
            return temps
        if not held:
            held.update({k: temps[k] for k in WINDING})
        noisy = {k: round((v + rng.normal(0.0, FREEZE_NOISE_K)) / RESOLUTION_K) * RESOLUTION_K for k, v in held.items()}
        return {**temps, **noisy}
    return fault


def _faulted(log: Path, out: Path, t0: float, fault: Fault, frame_name: str = TEMPS, prefix: str = "INV_T_",
             dbc: Path | None = None) -> int:
    """``log`` with every ``frame_name`` frame's signals named ``prefix...`` (by default the
    ``INV_StatorTemps`` temperatures) passed through ``fault`` and re-encoded (the frame's own
    counter, the matrix's CRC; ``t0``: the log's first stamp; ``dbc``: the inverter's own DBC,
    default the shipped one); returns the frames changed."""
    codec = FrameCodec() if dbc is None else FrameCodec(dbc)
    changed = 0
    lines = []
    for line in log.read_text().splitlines():
        stamp, chan, frame, *rest = line.split()  # candump -L: "(stamp) channel id#data [R|T]"
        ident, data = frame.split("#")
        t = float(stamp.strip("()"))
        msg = can.Message(arbitration_id=int(ident, 16), data=bytes.fromhex(data), is_extended_id=len(ident) > 3)
        dec = codec.decode_message(msg)
        if dec is not None and dec.name == frame_name:
            values = fault(t - t0, {k: v for k, v in dec.signals.items() if k.startswith(prefix)})
            data = codec.encode(frame_name, {**dec.signals, **values}, counter=dec.counter).hex().upper()
            changed += 1
        lines.append(" ".join([stamp, chan, f"{ident}#{data}", *rest]))
    out.write_text("\n".join(lines) + "\n")
    return changed


def _replay(workdir: Path, log: Path, faults: dict[str, float], dbc: Path | None = None) -> tuple[list[dict[str, str]], str, int]:
    """Replay ``log`` with the service's configuration (the inverter's DBC ``dbc``, default the
    shipped one), adaptation on and ``faults`` set; returns the per-tick table, stderr and the
    exit status."""
    raw = yaml.safe_load(service_config_path("edge.yaml").read_text())
    if dbc is not None:
        raw["codec"] = {**(raw.get("codec") or {}), "dbc": str(dbc)}
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


def _clean(d: Path, full: bool) -> tuple[Path, list[dict[str, str]], float]:
    """The overload cycle simulated: its CAN log, the plant's temperatures and the log's first stamp."""
    common = ["simulate", "--model", str(service_config_path("machines", "pm10kw.yaml")), "--cycle",
              str(service_config_path("cycles", "overload.yaml")), "--duration", "10800" if full else "7200", "--seed", "0"]
    for fmt, out in (("csv", d / "truth.csv"), ("can", d / "clean.log")):
        subprocess.run(thermal_edge_cmd() + [*common, "--format", fmt, "--out", str(out)], env=env(), cwd=str(ROOT),
                       check=True, capture_output=True, timeout=900)
    truth = list(csv.DictReader(ln for ln in (d / "truth.csv").read_text().splitlines() if not ln.startswith("#")))
    clean = d / "clean.log"
    return clean, truth, float(clean.read_text().split(maxsplit=1)[0].strip("()"))


def _published_short(rows: list[dict[str, str]], truth: list[dict[str, str]]) -> tuple[float, int]:
    """How far (K) the estimates published while the readings were not believed (the ticks whose
    reason is ``model_fault``) lay below the plant's true sensor temperatures, at most over those
    ticks and sensors, and how many such ticks there were."""
    sensors = [c[: -len("_observer")] for c in rows[0] if c.endswith("_observer")] if rows else []
    by_t = {round(float(r["t"])): r for r in truth}
    short, ticks = -np.inf, 0
    for r in rows:
        plant = by_t.get(round(float(r["t"])) + 1)
        if plant is None or int(float(r["reason"])) != int(DerateReason.MODEL_FAULT):
            continue
        ticks += 1
        short = max([short] + [float(plant[s]) - float(r[f"{s}_observer"]) for s in sensors if s in plant])
    return float(short), ticks


def _case(d: Path, name: str, group: str, clean: Path, truth: list[dict[str, str]], t0: float, fault: Fault,
          tried: str, said: str | None, faults: dict[str, float], control: bool = False,
          published_k: float | None = None, dbc: Path | None = None, prefix: str = "INV_T_") -> Case:
    """Replay ``clean`` through ``fault`` and judge it: no tick above the safe current while the plant's
    winding is over its max, and ``said`` in the log (not for a control; None: a plain derate, which
    the replay does not log). With ``published_k``: while the readings are not believed, no estimate
    published more than that (K) below the plant's true sensor temperature. ``dbc``: the inverter's
    own DBC, which writes the faulted log and which the replay reads; ``prefix`` names the frame's
    signals ``fault`` sees (default its temperatures)."""
    raw = yaml.safe_load(service_config_path("edge.yaml").read_text())
    max_c = float(raw["derating"]["limits"]["hot_spot"]["max_c"])
    safe_a = float(raw["derating"]["safe_current_a"])
    changed = _faulted(clean, d / f"{name}.log", t0, fault, prefix=prefix, dbc=dbc)
    rows, err, rc = _replay(d, d / f"{name}.log", faults, dbc)
    c = Check()
    c.add(0 if rc == 0 and rows else 1, f"replay exit {rc}: {err.strip()[-200:]}")
    hot, unsafe = _judge(rows, truth, max_c, safe_a)
    c.add(unsafe, f"{unsafe} of {hot} ticks with the slot winding above {max_c:.0f} degC sent more than {safe_a:.0f} A")
    c.add(0 if hot else 1, f"the plant never passed {max_c:.0f} degC: nothing was judged")
    heard = said is not None and said in err
    if not control and said is not None:
        c.add(0 if heard else 1, f"no log line says {said!r}")
    published = ""
    if published_k is not None:
        short, refused = _published_short(rows, truth)
        c.add(0 if refused else 1, "no tick refused the readings: no published estimate judged")
        c.add(int(short > published_k), f"estimates published up to {short:.1f} K below the machine's while the "
                                        f"readings were not believed (allowed {published_k:g} K)")
        published = f"; published estimates at most {short:.1f} K below the machine's over {refused} refused ticks"
    did = (f"{changed} {TEMPS} frames {tried}; winding above max {hot} ticks, {unsafe} of them above {safe_a:.0f} A"
           + (f"; {said!r} logged" if heard else "") + published)
    return Case.of(name, group, 1, did, c, control=control)


#: the current frame's signals read ten times low from this time on (s): a DBC scaling of 0.1 A read
#: as 1 A, or a second sender diluting the frame (20 A read as 6.3 A)
SCALED_FROM_S, CURRENTS = 3000.0, "INV_Currents"


def current_tenfold_low(dt: float, currents: dict[str, float]) -> dict[str, float]:
    """The currents a tenth of the machine's from :data:`SCALED_FROM_S` on."""
    return {k: v * 0.1 for k, v in currents.items()} if dt >= SCALED_FROM_S else currents


def _believed_low(rows: list[dict[str, str]], truth: list[dict[str, str]], judged_a: float, safe_a: float,
                  settle_s: float) -> tuple[int, int]:
    """(ticks after the scaling (and ``settle_s``) whose machine current is at least ``judged_a``,
    of them those with a limit above ``safe_a``: the current a tenth of the machine's believed)."""
    by_t = {round(float(r["t"])): float(r["i_rms"]) for r in truth}
    judged = believed = 0
    for r in rows:
        t = round(float(r["t"])) + 1  # the replay's t counts from the first tick, 1 s in
        i = by_t.get(t)
        if i is not None and t >= SCALED_FROM_S + settle_s and i >= judged_a:
            judged += 1
            believed += float(r["current_limit_a"]) > safe_a + 1e-6
    return judged, believed


def _current_case(d: Path, name: str, group: str, clean: Path, truth: list[dict[str, str]], t0: float,
                  faults: dict[str, float], control: bool = False) -> Case:
    """The current frame ten times low: no tick above the safe current once the check confirms,
    where the machine's current is one the check judges, and its line in the log."""
    from thermal_edge.service.current_torque import CONFIRM_TICKS, JUDGED_FROM

    raw = yaml.safe_load(service_config_path("edge.yaml").read_text())
    safe_a, max_a = float(raw["derating"]["safe_current_a"]), float(raw["derating"]["max_current_a"])
    changed = _faulted(clean, d / f"{name}.log", t0, current_tenfold_low, CURRENTS, "INV_I")
    rows, err, rc = _replay(d, d / f"{name}.log", faults)
    c = Check()
    c.add(0 if rc == 0 and rows else 1, f"replay exit {rc}: {err.strip()[-200:]}")
    # settle: the confirming ticks and one tick of the frames' mean crossing the scaling's start
    judged, believed = _believed_low(rows, truth, JUDGED_FROM * max_a, safe_a, CONFIRM_TICKS + 2.0)
    c.add(believed, f"{believed} of {judged} ticks with the current read ten times low sent more than {safe_a:.0f} A")
    c.add(0 if judged else 1, "the machine never drew a judged current after the scaling: nothing was judged")
    said = "below 0.5 of the"
    heard = said in err
    if not control:
        c.add(0 if heard else 1, f"no log line says {said!r}")
    did = (f"{changed} {CURRENTS} frames a tenth from {SCALED_FROM_S:.0f} s; {judged} ticks judged, {believed} of them "
           f"above {safe_a:.0f} A" + (f"; {said!r} logged" if heard else ""))
    return Case.of(name, group, 1, did, c, control=control)


#: the slot-winding PT100 reads this much above the machine's slot winding from this time on (K, s):
#: a winding whose hottest point is where the model's hot spot is not
SLOT_RAISE_K, SLOT_RAISED_FROM_S = 25.0, 3000.0


def slot_reads_hotter(dt: float, temps: dict[str, float]) -> dict[str, float]:
    """The slot-winding reading :data:`SLOT_RAISE_K` above the machine's from :data:`SLOT_RAISED_FROM_S`."""
    return {**temps, "INV_T_WindingSlot": temps["INV_T_WindingSlot"] + SLOT_RAISE_K} if dt >= SLOT_RAISED_FROM_S \
        else temps


def _slot_as_read(truth: list[dict[str, str]]) -> list[dict[str, str]]:
    """The machine's temperatures with the slot winding as :func:`slot_reads_hotter` reads it: a
    winding read above its maximum is judged as one above it."""
    return [{**r, "slot_winding": str(float(r["slot_winding"]) + (SLOT_RAISE_K if float(r["t"]) >= SLOT_RAISED_FROM_S
                                                                   else 0.0))} for r in truth]


#: from this time on (s) the slot winding's status is a code the matrix does not define, in the 4-bit
#: status signal of another inverter's DBC (:func:`wide_status_dbc`), and the reading it flags lies
#: this far low (K): a sensor its inverter knows to be bad, in words the matrix has no name for
UNKNOWN_FROM_S, UNKNOWN_STATUS, FLAGGED_LOW_K = 3000.0, 5, 40.0
SLOT_STATUS = "INV_S_WindingSlot"


def wide_status_dbc(d: Path) -> Path:
    """Another inverter's DBC: the shipped one with the slot winding's status 4 bits wide (bits
    42-45, free in the matrix), written into ``d``."""
    text, n = re.subn(rf"SG_ {SLOT_STATUS} : 36\|2@1\+ \(1,0\) \[0\|3\]", f"SG_ {SLOT_STATUS} : 42|4@1+ (1,0) [0|15]",
                      DEFAULT_DBC_PATH.read_text())
    if n != 1:
        raise ValueError(f"no 2-bit {SLOT_STATUS} at bit 36 in the shipped DBC")
    (d / "wide-status.dbc").write_text(text)
    return d / "wide-status.dbc"


def flagged_unknown(dt: float, signals: dict[str, float]) -> dict[str, float]:
    """From :data:`UNKNOWN_FROM_S` on, the slot winding :data:`FLAGGED_LOW_K` low under status
    :data:`UNKNOWN_STATUS`."""
    if dt < UNKNOWN_FROM_S:
        return signals
    return {**signals, SLOT_STATUS: float(UNKNOWN_STATUS), "INV_T_WindingSlot": signals["INV_T_WindingSlot"] - FLAGGED_LOW_K}


DRIFT_TRIED = f"{DRIFT_RATE_K_PER_S * 60:.1f} K/min low from {DRIFT_FROM_S:.0f} s (up to {DRIFT_CAP_K:.0f} K)"


def drift(full: bool) -> Iterator[Case]:
    """Every PT100 drifting low together: not believed; the winding PT100s frozen with noise: stuck.
    Either way the safe limit while the winding is over its max."""
    with tempfile.TemporaryDirectory(prefix="te-faults-readings-") as tmp:
        d = Path(tmp)
        clean, truth, t0 = _clean(d, full)
        yield _case(d, "pt100_common_drift", "readings", clean, truth, t0, common_drift, DRIFT_TRIED,
                    "readings not believed", {}, published_k=PUBLISHED_K)
        yield _case(d, "winding_pt100s_frozen_with_noise", "readings", clean, truth, t0, frozen_with_noise(),
                    f"with the windings held from {FREEZE_FROM_S:.0f} s (+ {FREEZE_NOISE_K} K noise, "
                    f"{RESOLUTION_K} K steps)", "stuck at", {})
        yield _current_case(d, "current_dbc_scaled_tenfold_low", "readings", clean, truth, t0, {})
        yield _case(d, "status_code_the_matrix_does_not_define", "readings", clean, truth, t0, flagged_unknown,
                    f"with the slot winding's status {UNKNOWN_STATUS} (a 4-bit signal of the inverter's own DBC) and its "
                    f"reading {FLAGGED_LOW_K:.0f} K low from {UNKNOWN_FROM_S:.0f} s", "slot_winding (unknown_status)", {},
                    dbc=wide_status_dbc(d), prefix="INV_")
        yield _case(d, "slot_pt100_hotter_than_the_hot_spot", "readings", clean, _slot_as_read(truth), t0,
                    slot_reads_hotter, f"with the slot winding {SLOT_RAISE_K:.0f} K hotter from {SLOT_RAISED_FROM_S:.0f} s",
                    None, {})


def drift_unguarded(full: bool) -> Iterator[Case]:
    """The common drift with ``commissioned_gap_k`` at its upper bound, which the drift never
    reaches, and the current ten times low with ``current_torque_ratio`` at 0.01: each must be
    judged unsafe."""
    with tempfile.TemporaryDirectory(prefix="te-faults-readings-") as tmp:
        d = Path(tmp)
        clean, truth, t0 = _clean(d, full)
        yield _case(d, "pt100_common_drift_guard_off", "control", clean, truth, t0, common_drift, DRIFT_TRIED,
                    "readings not believed", {"commissioned_gap_k": 100.0}, control=True)
        yield _current_case(d, "current_tenfold_low_check_off", "control", clean, truth, t0,
                            {"current_torque_ratio": 0.01}, control=True)


GROUPS = {"readings": drift}
CONTROLS = {"readings_control": drift_unguarded}
