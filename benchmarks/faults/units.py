"""Units the CAN matrix gets wrong: the service must refuse them at load or name them, never use them.

A DBC that declares a mapped signal in another unit than its role's (a speed in rad/s, a
temperature in K or degF, a current in mA) is refused by ``run --check`` with one line naming the
key and the unit: a speed 9.5 times too small is still a plausible speed, so only the declared
unit can catch it. A DBC that declares the right unit with a wrong scaling (a temperature decoded
in kelvin, currents 1000 times too large) is refused by ``export`` naming the signal and the unit
its readings look like, instead of a column of NaN or "no run"; currents a tenth of the
machine's, below what the torque reported needs on every tick judged, are refused naming the
current's signals; an ambient that reads 215 degC (an
unplugged channel's raw maximum) is refused as the air's, and a temperature mapped as a sensor's
status signal is refused at load (it would be judged as codes). Each case runs the installed
command in a process of its own, as a user would.
"""
from __future__ import annotations

import re
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import yaml

from thermal_edge.bus.frames import DEFAULT_DBC_PATH
from thermal_edge.shipped import config_path, example_config

from .harness import Case, Check

#: signal, its scaling and unit in the user's DBC, the key and the words the refusal must carry
DECLARED = {
    "speed_in_rad_per_s": ("INV_Speed", "0.01,0", "rad/s", "signals.inputs.speed_rpm", "factor 0.09549297"),
    "housing_in_kelvin": ("INV_T_Housing", "0.1,0", "K", "signals.sensors.housing", "offset -273.15"),
    "ambient_in_fahrenheit": ("INV_T_Ambient", "0.1,0", "degF", "signals.inputs.ambient_c", "factor 0.05555556"),
    "currents_in_milliampere": ("INV_Id", "1,0", "mA", "signals.inputs.i_rms", "factor 0.001"),
}
#: a temperature mapped as a sensor's status signal (judged as codes, 85.3 degC would be code 85):
#: signal, its scaling and unit in the user's DBC, the key and the words the refusal must carry
NOT_A_STATUS = {
    "temperature_mapped_as_a_status": ("INV_S_Housing", "0.1,0", "degC", "signals.sensors.housing.status",
                                       "not a status code"),
}
#: signal and a wrong scaling with the right unit, and the words ``export``'s refusal must carry
SCALED = {
    "housing_decoded_in_kelvin": ("INV_T_Housing", "0.1,223.15", "every reading of housing", "looks like kelvin"),
    "currents_decoded_in_milliampere": ("INV_Id INV_Iq", "50,0", "i_rms (INV_Currents INV_Id/INV_Iq) refused",
                                        "looks like mA"),
    # a tenth of the currents (a factor of 0.005 A for 0.05 A): plausible currents, but below what
    # the torque the inverter reports needs, on every tick judged
    "currents_decoded_tenfold_low": ("INV_Id INV_Iq", "0.005,0", "i_rms (INV_Currents INV_Id/INV_Iq) below",
                                     "a scaling of the current in the DBC"),
    # the ambient channel unplugged, reading its raw maximum: 215 degC is a winding's temperature,
    # inside the PT100s' valid range, but never the air's
    "ambient_unplugged_at_215_degc": ("INV_T_Ambient", "0.1,140", "ambient_c (INV_AmbientTemps INV_T_Ambient) refused",
                                      "215 degC"),
}


def _te(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "thermal_edge.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=600, env={"OPENBLAS_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"})


def rescaled(dbc: str, signal: str, scaling: str, unit: str | None = None) -> str:
    """The DBC text ``dbc`` with ``signal``'s factor and offset set to ``scaling`` (``"0.01,0"``)
    and, if given, its declared ``unit``: a CAN matrix with a unit or scaling error."""
    repl = rf'\g<1>({scaling})\2 "{unit}"' if unit is not None else rf"\g<1>({scaling})\2 \3"
    text, n = re.subn(rf'(SG_ {signal} : [^(]*)\([^)]*\)( \[[^]]*\]) ("[^"]*")', repl, dbc)
    if n != 1:
        raise ValueError(f"no signal {signal} in the DBC text")
    return text


def _config(d: Path, signals: list[str], scaling: str, unit: str | None) -> Path:
    """The example configuration on the shipped DBC with ``signals`` scaled (and declared in ``unit``)."""
    text = DEFAULT_DBC_PATH.read_text()
    for signal in signals:
        text = rescaled(text, signal, scaling, unit)
    (d / "inverter.dbc").write_text(text)
    raw = yaml.safe_load(example_config())
    raw["codec"] = {**(raw.get("codec") or {}), "dbc": str(d / "inverter.dbc")}
    raw["model"]["path"] = str(config_path("machines", "pm10kw.yaml"))
    raw["state"] = {"dir": str(d / "state")}
    (d / "edge.yaml").write_text(yaml.safe_dump(raw))
    return d / "edge.yaml"


def _one_line(c: Check, r: subprocess.CompletedProcess[str], *words: str) -> None:
    c.add(0 if r.returncode == 2 else 1, f"exit status {r.returncode}, not 2")
    c.add(0 if len(r.stderr.strip().splitlines()) == 1 else 1, "not one line on stderr")
    missing = [w for w in words if w not in r.stderr]
    c.add(len(missing), f"the line lacks {missing}: {r.stderr.strip()[:200]}")


def units(full: bool) -> Iterator[Case]:
    """Each wrong unit: refused, one line, the key and the unit named."""
    with tempfile.TemporaryDirectory(prefix="te-bench-units-") as tmp:
        d = Path(tmp)
        checks = [(name, signal, scaling, unit, f"edge.yaml: {key}: inverter.dbc gives {signal} in {unit!r}", words)
                  for name, (signal, scaling, unit, key, words) in DECLARED.items()]
        checks += [(name, signal, scaling, unit, f"edge.yaml: {key}: {signal} in inverter.dbc is scaled", words)
                   for name, (signal, scaling, unit, key, words) in NOT_A_STATUS.items()]
        for name, signal, scaling, unit, first, words in checks:
            (d / name).mkdir()
            r = _te("run", "--check", "--config", _config(d / name, [signal], scaling, unit))
            c = Check()
            _one_line(c, r, first, words)
            yield Case.of(name, "units", 1, f"run --check: exit {r.returncode}: {r.stderr.strip()[-160:]}", c)
        log = d / "drive.log"
        sim = _te("simulate", "--model", "pm10kw", "--cycle", "overload", "--duration", "300" if not full else "1800",
                  "--format", "can", "--out", log)
        if sim.returncode != 0:
            raise RuntimeError(f"simulate --format can failed: {sim.stderr.strip()[-300:]}")
        for name, (signals, scaling, who, unit_words) in SCALED.items():
            (d / name).mkdir()
            r = _te("export", log, "--config", _config(d / name, signals.split(), scaling, None), "--out", d / name / "x.csv")
            c = Check()
            _one_line(c, r, who, unit_words)
            yield Case.of(name, "units", 1, f"export: exit {r.returncode}: {r.stderr.strip()[-160:]}", c)


GROUPS = {"units": units}
