"""``thermal-edge bench protection``: how much of the machine's thermal headroom each protection
policy delivers, and whether it ever lets the machine overheat.

The closed loop runs on the simulated machine in one process, on the frame clock: the inverter
emulator's plant and frames (:class:`..sim.inverter.InverterEmulator`, stepped directly, no bus),
and for ``thermal_edge`` the service's own :class:`..service.engine.ThermalEngine` (model,
observer, online adaptation in the tick, the derating policy) configured by the packaged example ``edge.yaml``.
The limits it sends are encoded and decoded with the DBC (the inverter obeys the quantised
values); the inverter's frames reach the policies as signals, not encoded (the emulator's readings
are already noisy and quantised like the DBC's, and encoding 20 frames a tick would double the
time). The limits a policy sends clip the cycle's torque demand in the emulator exactly as it
obeys ``TE_Limits`` on the bus. Without a bus the run is as fast as the model steps.

Policies:

* ``thermal_edge``: the service as configured.
* ``thermal_edge_voltages``: the same service with the optional voltage frame: the emulator sends
  ``INV_Voltages`` from its electrical model (:class:`..sim.pmsm.Pmsm`, from the plant's true
  temperatures) and the service fuses the flux-linkage estimate of the magnet into its observer
  (``flux:``), commissioned on a simulated bench run of the nominal machine
  (:func:`.commissioning.commission`, the packaged ``commissioning`` cycle). Its voltage noise
  comes from a random stream of its own: the PT100 readings are those the other policies see.
* ``pt100_linear``: what open drive firmware does (VESC's motor temperature derate): full current
  below the hot spot's warning temperature on the *end-winding PT100*, linearly to zero at its max.
* ``i2t``: the classic I²t overload accumulator of drive firmware set to the machine's continuous
  rating ``I_c`` (the model's ``i_rated``): ``A += (I² - I_c²) dt`` (never below 0); full current
  while ``A`` is below the capacity ``(I_max² - I_c²) · I2T_OVERLOAD_S``, the continuous current
  once it is full. Its image lives in the drive's RAM: after a restart it starts empty.
* ``oracle``: reads the plant's true temperatures and derates linearly over ``ORACLE_BAND_K``
  (2 K) ending ``ORACLE_MARGIN_K`` (0.5 K) below each limited node's max: what a policy that knew
  the truth could deliver without overheating (greedy, so not the optimum of the integral: a
  policy that keeps the machine cooler early can deliver more later).

Plant cases: the plant is the service's model built differently (``--plant NAME=VALUE`` adds a
case ``custom``): ``nominal``; ``r_hous_plus30`` (housing to ambient +30 %); ``sigma_cu_minus25``
(winding conductivity −25 %: ``R20_phase`` / 0.75, copper losses +33 %); ``h_sh1_minus30`` (the
speed-dependent shaft/rotor heat transfer −30 %: a magnet-side parameter the adapter does not
estimate and no sensor sees); ``ambient_40`` (ambient 40 °C instead of 25 °C); ``warm_restart``
(the machine warmed up for 40 min at 110 Nm, stopped 60 s; the service restarts from its saved
state, the I²t image from empty); ``warm_restart_rotor`` (the same restart on a plant whose rotor
differs from the model, unseen by any sensor: magnet losses +60 %, rotor-surface cooling −30 %; the
saved state must carry the magnet's band across the restart); ``electrical_wrong`` (the nominal
plant, but ``thermal_edge_voltages`` runs with the electrical calibration deliberately wrong:
inductances +20 %, the inverter's voltage error doubled; the disagreement check must refuse what
would mislead it, and nothing may overheat).

The simulated machine has the field weakening of its electrical model (:class:`..sim.pmsm.Pmsm`) for
every policy: above about 1,400 rpm under load the inverter adds a negative ``i_d``, which heats
the winding but makes no torque, and which an inductance error carries into the flux estimate.

Figures per case and policy: ``headroom_pct`` (the torque's current-time delivered ÷ demanded, %;
the field-weakening current is not counted),
``oracle_share_pct`` (delivered ÷ the oracle's delivered, %), ``peak_hot_spot_c``,
``peak_magnet_c`` (true plant temperatures), ``seconds_over_max`` (plant time with a limited node
above its max); for ``thermal_edge_voltages`` also ``flux`` (ticks per outcome of the flux
estimate: used, refused for disagreement, ...).
"""
from __future__ import annotations

import copy
import json
import logging
import math
import sys
import tempfile
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..shipped import config_path

__all__ = ["CASES", "POLICIES", "Case", "ThermalEdgePolicy", "closed_loop", "edge_config", "emulator_for", "parse_plant_changes",
           "plant_for", "run", "run_case"]

POLICIES = ("thermal_edge", "thermal_edge_voltages", "pt100_linear", "i2t", "oracle")
#: the service's policies: with and without the voltage frame
SERVICE_POLICIES = ("thermal_edge", "thermal_edge_voltages")
#: I²t: seconds the maximum current may flow from an empty accumulator (drive overload rating,
#: the usual "2 x rated for 60 s" class of servo and traction drives)
I2T_OVERLOAD_S = 60.0
#: oracle: width of its linear derate on the true temperature, K, ending this far below the max, K
#: (cut at the max itself, the magnet still rose 0.4 K on the heat stored in the stator at 40 degC)
ORACLE_BAND_K = 2.0
ORACLE_MARGIN_K = 0.5
#: the simulated machine's frame periods and plant step (accelerated: the plant's inputs are held
#: over a plant step, so more current frames per step would only repeat the same values)
CURRENT_PERIOD_S = 0.25
TEMPERATURE_PERIOD_S = 0.5
PLANT_DT_S = 0.5
T0 = 1_700_000_000.0  # simulated epoch
WARM_UP_S = 2400.0  # warm_restart: warm-up at WARM_UP_TORQUE_NM before the restart
WARM_UP_TORQUE_NM = 110.0
RESTART_DOWNTIME_S = 60.0


@dataclass(frozen=True)
class Case:
    """A plant case: how the plant differs from the service's model."""

    name: str
    factors: Mapping[str, float] = field(default_factory=dict)  # parameter/constant -> factor on its value
    values: Mapping[str, float] = field(default_factory=dict)  # parameter/constant -> absolute value
    ambient_offset_k: float = 0.0
    warm_restart: bool = False
    #: the flux estimate's electrical calibration deliberately wrong (inductances +20 %, voltage error x2)
    flux_miscalibrated: bool = False
    doc: str = ""


CASES: dict[str, Case] = {c.name: c for c in (
    Case("nominal", doc="the plant is the model"),
    Case("r_hous_plus30", {"R_e_hous": 1.3}, doc="housing to ambient resistance +30 %"),
    Case("sigma_cu_minus25", {"R20_phase": 1 / 0.75}, doc="winding conductivity -25 % (copper losses +33 %)"),
    Case("h_sh1_minus30", {"h_sh1": 0.7}, doc="shaft/rotor heat transfer -30 % (magnet side, not identifiable)"),
    Case("ambient_40", ambient_offset_k=15.0, doc="ambient 40 degC"),
    Case("warm_restart", warm_restart=True, doc="service restarts warm from its saved state"),
    Case("warm_restart_rotor", {"P_pm_ref": 1.6, "h_rot1": 0.7}, warm_restart=True,
         doc="warm restart with the rotor built differently (magnet losses +60 %, rotor cooling -30 %)"),
    Case("electrical_wrong", flux_miscalibrated=True,
         doc="nominal plant; the voltages' electrical calibration wrong (inductances +20 %, voltage error doubled)"),
)}


def parse_plant_changes(items: list[str]) -> Case:
    """``--plant NAME=VALUE`` items -> the ``custom`` case.

    ``VALUE`` is an absolute value (``R_e_hous=11.8``) or a relative change in percent
    (``R_e_hous=+30%``, ``h_sh1=-30%``).

    Raises
    ------
    ValueError
        An item that is not ``NAME=VALUE`` with a number.
    """
    factors: dict[str, float] = {}
    values: dict[str, float] = {}
    for item in items:
        name, sep, val = item.partition("=")
        name, val = name.strip(), val.strip()
        if not sep or not name or not val:
            raise ValueError(f"--plant {item!r}: expected NAME=VALUE (e.g. R_e_hous=+30% or R_e_hous=11.8)")
        try:
            if val.endswith("%"):
                factors[name] = 1.0 + float(val[:-1]) / 100.0
            else:
                values[name] = float(val)
        except ValueError:
            raise ValueError(f"--plant {item!r}: {val!r} is not a number or a percentage") from None
    return Case("custom", factors, values, doc=", ".join(items))


# ----------------------------------------------------------------------------------------------
class _Policy:
    """A protection policy in the loop: sees the frames of every plant step, sets the limit."""

    name = ""

    def __init__(self, emu: Any, imax: float, tmax: float) -> None:
        self.emu, self.imax, self.tmax = emu, imax, tmax

    def step(self, frames: list[Any]) -> float:
        """The current limit (A rms) in force from now, after this step's frames."""
        raise NotImplementedError


class _Oracle(_Policy):
    name = "oracle"

    def __init__(self, emu: Any, imax: float, tmax: float, limits: list[tuple[int, float]]) -> None:
        super().__init__(emu, imax, tmax)
        self.limits = limits

    def step(self, frames: list[Any]) -> float:
        T = self.emu.plant.T
        f = min(min(1.0, max(0.0, (mx - ORACLE_MARGIN_K - T[i]) / ORACLE_BAND_K)) for i, mx in self.limits)
        return f * self.imax


class _Pt100Linear(_Policy):
    name = "pt100_linear"

    def __init__(self, emu: Any, imax: float, tmax: float, signal: str, warn_c: float, max_c: float) -> None:
        super().__init__(emu, imax, tmax)
        self.signal, self.warn, self.max = signal, warn_c, max_c
        self.reading = math.nan

    def step(self, frames: list[Any]) -> float:
        for f in frames:
            v = f.signals.get(self.signal) if f.name == "INV_StatorTemps" else None
            if v is not None and math.isfinite(v):
                self.reading = float(v)
        if not math.isfinite(self.reading):
            return self.imax
        return self.imax * min(1.0, max(0.0, (self.max - self.reading) / (self.max - self.warn)))


class _I2t(_Policy):
    name = "i2t"

    def __init__(self, emu: Any, imax: float, tmax: float, i_cont: float) -> None:
        super().__init__(emu, imax, tmax)
        self.ic2 = i_cont * i_cont
        self.i_cont = i_cont
        self.capacity = (imax * imax - self.ic2) * I2T_OVERLOAD_S
        self.acc = 0.0

    def step(self, frames: list[Any]) -> float:
        i2 = [f.signals["INV_IphRms"] ** 2 for f in frames if f.name == "INV_Currents"]
        if i2:
            self.acc = max(0.0, self.acc + (float(np.mean(i2)) - self.ic2) * PLANT_DT_S)
        return self.imax if self.acc < self.capacity else self.i_cont


class ThermalEdgePolicy(_Policy):
    name = "thermal_edge"

    def __init__(self, emu: Any, imax: float, tmax: float, config: Any, restored: Any = None) -> None:
        super().__init__(emu, imax, tmax)
        from ..bus.codec import FrameCodec
        from ..bus.frames import DEFAULT_DBC_PATH, DerateReason
        from ..service.clock import FrameClock
        from ..service.engine import ThermalEngine, load_service_model

        self.config = config
        self.engine = ThermalEngine(config, load_service_model(config), restored, worker_mode="sync")
        self.codec = FrameCodec(config.codec.dbc or DEFAULT_DBC_PATH, resync_after_cycles=1e9)  # service side
        self.clock = FrameClock(config.clock.tick_s)
        self.limits_id = self.codec.frame_id("TE_Limits")
        lim = self.engine.policy.safe(DerateReason.STARTING)
        self.limit = lim.current_a
        self.reason_s: dict[str, float] = {}
        self.reason = lim.reason
        self.last_out: Any = None

    def step(self, frames: list[Any]) -> float:
        for f in frames:
            for b in self.engine.ticks_for(self.clock.observe(f.timestamp)):
                out = self.engine.tick(b)
                self.last_out = out
                # TE_Limits through the DBC (the inverter sees the quantised values)
                self.limit = float(self.emu.codec.decode(self.limits_id, self.codec.encode("TE_Limits", out.limits.signals()),
                                                          timestamp=b).signals["TE_CurrentLimit"])
                self.reason = out.limits.reason
            self.engine.add_frame(f, self.clock.now())
        name = self.reason.name.lower()
        self.reason_s[name] = self.reason_s.get(name, 0.0) + PLANT_DT_S
        return self.limit

    def close(self) -> None:
        self.engine.close()


# ----------------------------------------------------------------------------------------------
def edge_config(state_dir: Path, config_file: Path | None = None, flux_calibration: Path | None = None) -> Any:
    """The packaged example ``edge.yaml`` (or ``config_file``) as the service runs it here: frame
    clock, no bus I/O, no metrics; with ``flux_calibration`` the voltage input on (``flux:``)."""
    import yaml

    from ..config import config_from_mapping

    path = (Path(config_file) if config_file is not None else config_path("edge.yaml")).resolve()
    raw = yaml.safe_load(path.read_text())
    raw["bus"] = {"interface": "virtual", "channel": "bench-protection"}
    raw["clock"] = {**(raw.get("clock") or {}), "mode": "frame"}
    raw["metrics"] = {"enabled": False}
    raw["state"] = {**(raw.get("state") or {}), "dir": str(state_dir)}
    raw["recording"] = {}
    slow = max(CURRENT_PERIOD_S, TEMPERATURE_PERIOD_S)
    raw["timeouts"] = {k: max(float(v), 3 * slow) for k, v in (raw.get("timeouts") or {}).items()}
    if flux_calibration is not None:
        raw["flux"] = {**(raw.get("flux") or {}), "calibration": str(flux_calibration),
                       "timeout_s": max(float((raw.get("flux") or {}).get("timeout_s", 0.5)), 3 * CURRENT_PERIOD_S)}
    return config_from_mapping(raw, path)  # relative paths (and a packaged model's name) as from the file


def plant_for(service_model: Any, case: Case) -> Any:
    from ..sim.plant import nominal_values, plant_model

    nominal = nominal_values(service_model)
    changes: dict[str, float] = {}
    for k, f in case.factors.items():
        if k not in nominal:
            raise ValueError(f"--plant {k}: neither a parameter nor a numeric constant of {service_model.name}")
        changes[k] = nominal[k] * f
    for k, v in case.values.items():
        if k not in nominal:
            raise ValueError(f"--plant {k}: neither a parameter nor a numeric constant of {service_model.name}")
        changes[k] = v
    return plant_model(service_model, changes)


def emulator_for(plant: Any, cycle: Path, case: Case, duration_s: float | None, codec: Any = None,
                 pmsm: Any = None, voltages: bool = False) -> Any:
    """The emulator of a case's plant on the bench's frame periods; with ``pmsm`` (:class:`..sim.pmsm.Pmsm`)
    its currents have the field-weakening ``i_d``, and with ``voltages`` it also sends ``INV_Voltages``."""
    from ..sim.inverter import EmulatorConfig, InverterEmulator

    cfg = EmulatorConfig(model_path=plant.path, cycle_path=cycle, duration_s=duration_s, speed=0.0, t0=T0,
                         current_period_s=CURRENT_PERIOD_S, temperature_period_s=TEMPERATURE_PERIOD_S,
                         plant_dt_s=PLANT_DT_S, closed_loop=True, flow_control=False, trace_every_s=math.inf,
                         record_estimates=False, ambient_offset_k=case.ambient_offset_k, limits_timeout_sim_s=math.inf,
                         pmsm=pmsm, voltages=voltages)
    return InverterEmulator(cfg, codec=codec, model=plant)


def closed_loop(emu: Any, policy: _Policy, kt: float, limits: list[tuple[str, int, float]],
                observe: Callable[[Any, _Policy], None] | None = None) -> dict[str, float]:
    """Run the emulator's cycle with ``policy`` in the loop; the figures of the run.

    Parameters
    ----------
    emu : InverterEmulator
        Stepped directly; frames named in its ``paused`` set are not delivered (a dropout), its
        ``sensor_status`` and ``sensor_offset`` inject sensor faults.
    policy : _Policy
    kt : float
        Torque constant, Nm per A rms.
    limits : list of (name, node row, max °C)
        The limited nodes whose true temperatures are watched.
    observe : callable, optional
        Called after every plant step with the emulator and the policy (tests).
    """
    from ..bus.codec import DecodedFrame

    # every policy reads the signals as the inverter has them (the emulator's readings are already
    # PT100-noisy and quantised to 0.1 K; the DBC's current resolution, 0.05 A, is far below what
    # matters here): encoding and decoding 20 frames a tick would double the bench's time. The
    # limits the service sends do go through the DBC (ThermalEdgePolicy)
    ids = {n: emu.codec.frame_id(n)
           for n in ("INV_Currents", "INV_Mechanics", "INV_StatorTemps", "INV_AmbientTemps", "INV_Voltages")}
    demanded = delivered = over_s = 0.0
    peak = {name: -math.inf for name, _, _ in limits}
    limit = policy.step([])
    while emu.elapsed < emu.duration - 1e-9:
        emu.current_limit, emu.torque_limit = limit, min(policy.tmax, kt * limit)
        emu.limits_wall, emu.limits_sim = 0.0, emu.sim_time
        _, torque_d, _ = emu.demand(emu.elapsed)
        sent = emu.step(None)
        frames = [DecodedFrame(name, ids[name], sig, 0, ts) for ts, name, sig in sent if name not in emu.paused]
        # delivered: the torque's current (the field-weakening share of the current makes no torque)
        i_applied = [abs(sig["INV_Torque"]) / kt for _, name, sig in sent if name == "INV_Mechanics"]
        demanded += abs(torque_d) / kt * PLANT_DT_S
        delivered += (float(np.mean(i_applied)) if i_applied else 0.0) * PLANT_DT_S
        T = emu.plant.T
        over = False
        for name, i, mx in limits:
            peak[name] = max(peak[name], float(T[i]))
            over = over or T[i] > mx
        if over:
            over_s += PLANT_DT_S
        limit = policy.step(frames)
        if observe is not None:
            observe(emu, policy)
    return {"demanded_as": demanded, "delivered_as": delivered, "over_s": over_s, **{f"peak_{k}": v for k, v in peak.items()}}


#: the commissioning run of the flux estimate (a packaged cycle) and its nodes on the packaged machine
COMMISSIONING_CYCLE = "commissioning.yaml"
FLUX_WINDING_NODE = "slot_winding_1"
FLUX_MAGNET_NODES = ("magnet_1", "magnet_2")


def flux_calibration(service_model: Any, out: Path, miscalibrated: bool = False) -> Path:
    """Commission the flux estimate on a simulated bench run of the nominal machine and write it as
    ``thermal-edge flux calibrate`` does (``miscalibrated``: inductances +20 %, voltage error x2)."""
    from ..sim.pmsm import Pmsm
    from . import commissioning

    flux = commissioning.commission(service_model, Pmsm(), config_path("cycles", COMMISSIONING_CYCLE), FLUX_WINDING_NODE,
                                    FLUX_MAGNET_NODES)
    if miscalibrated:
        flux = commissioning.miscalibrated(flux)
    out.write_text(json.dumps(flux.as_dict(), indent=1) + "\n")
    return out


def run_case(case: Case, policies: tuple[str, ...] = POLICIES, cycle: Path | None = None, duration_s: float | None = None,
             config_file: Path | None = None) -> dict[str, dict[str, Any]]:
    """One plant case, every policy: ``{policy: figures}`` (see the module docstring)."""
    from ..service.engine import load_service_model
    from ..service.persistence import PersistedState
    from ..sim.plant import nominal_values
    from ..sim.pmsm import Pmsm

    cycle = cycle if cycle is not None else config_path("cycles", "protection.yaml")
    out: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory(prefix="te-bench-protection-") as tmp, _quiet_flux_refusals():
        cfg = edge_config(Path(tmp), config_file)
        service_model = load_service_model(cfg)
        cfgs = {"thermal_edge": cfg}
        if "thermal_edge_voltages" in policies:
            cal = flux_calibration(service_model, Path(tmp) / "flux.json", case.flux_miscalibrated)
            cfgs["thermal_edge_voltages"] = edge_config(Path(tmp) / "voltages", config_file, cal)
        plant = plant_for(service_model, case)
        kt = float(cfg.kt(service_model))
        imax, tmax = cfg.derating.max_current_a, cfg.derating.max_torque_nm
        lim_specs = []
        for lim in service_model.limits:
            _, mx = cfg.limit_band(lim)
            lim_specs.append((lim.name, service_model.node_index(lim.node), mx))
        hot = next(lim for lim in service_model.limits if lim.name == cfg.transmit.hot_spot_limit)
        warn_h, max_h = cfg.limit_band(hot)
        sensor = next(s for s, node in service_model.sensors.items() if node.startswith("end_winding"))
        signal = cfg.sensors[sensor].signal
        i_cont = nominal_values(service_model).get("i_rated", imax / 2)  # the continuous rating
        warm: dict[str, dict[str, Any]] = {}
        pmsm = Pmsm()  # every policy's machine has the same electrical side (its field weakening)
        for name in policies:
            voltages = name == "thermal_edge_voltages"
            emu = emulator_for(plant, cycle, case, duration_s, pmsm=pmsm, voltages=voltages)
            restored = None
            if case.warm_restart:
                key = name if name in SERVICE_POLICIES else "thermal_edge"  # the others start from the same machine
                if key not in warm:
                    warm[key] = _warm_start(case, plant, cycle, cfgs[key], kt, pmsm, voltages)
                emu.plant.T = warm[key]["T"].copy()
                restored = copy.deepcopy(warm[key]["state"])
                if isinstance(restored, PersistedState):
                    restored.saved_at = T0 - RESTART_DOWNTIME_S
            pol: _Policy
            if name in SERVICE_POLICIES:
                pol = ThermalEdgePolicy(emu, imax, tmax, cfgs[name], restored)
            elif name == "pt100_linear":
                pol = _Pt100Linear(emu, imax, tmax, signal, warn_h, max_h)
            elif name == "i2t":
                pol = _I2t(emu, imax, tmax, i_cont)
            elif name == "oracle":
                pol = _Oracle(emu, imax, tmax, [(i, mx) for _, i, mx in lim_specs])
            else:
                raise ValueError(f"unknown policy {name!r} (known: {', '.join(POLICIES)})")
            w0 = time.perf_counter()
            try:
                r = closed_loop(emu, pol, kt, lim_specs)
            finally:
                if isinstance(pol, ThermalEdgePolicy):
                    pol.close()
            fig: dict[str, Any] = {
                "headroom_pct": 100.0 * r["delivered_as"] / r["demanded_as"] if r["demanded_as"] > 0 else math.nan,
                "delivered_as": r["delivered_as"],
                "peak_hot_spot_c": r[f"peak_{cfg.transmit.hot_spot_limit}"],
                "peak_magnet_c": r[f"peak_{cfg.transmit.magnet_limit}"],
                "seconds_over_max": r["over_s"],
                "wall_s": time.perf_counter() - w0,
            }
            if isinstance(pol, ThermalEdgePolicy):
                fig["reason_s"] = {k: v for k, v in sorted(pol.reason_s.items())}
                fig["adaptations_accepted"] = pol.engine.adapt_accepted
                if pol.engine.flux is not None:
                    fig["flux"] = dict(sorted(pol.engine.flux.counts.items()))
            out[name] = fig
    ref = out.get("oracle", {}).get("delivered_as")
    for fig in out.values():
        fig["oracle_share_pct"] = 100.0 * fig["delivered_as"] / ref if ref else math.nan
    return out


class _quiet_flux_refusals:
    """The flux input's refusals are counted in the figures; their log lines (one per refused tick,
    thousands with a wrong calibration) are kept off the bench's output."""

    def __enter__(self) -> None:
        self.logger = logging.getLogger("thermal_edge.service.flux_input")
        self.level = self.logger.level
        self.logger.setLevel(logging.ERROR)

    def __exit__(self, *exc: object) -> None:
        self.logger.setLevel(self.level)


def _warm_start(case: Case, plant: Any, cycle: Path, cfg: Any, kt: float, pmsm: Any = None,
                voltages: bool = False) -> dict[str, Any]:
    """warm_restart: the machine at WARM_UP_TORQUE_NM for WARM_UP_S with the service running, then
    stopped for RESTART_DOWNTIME_S; returns the plant's temperatures at the restart and the state the
    service saved when it stopped."""
    import yaml

    from ..lptn import DEFAULT_COLUMNS, Role, Stepper

    with tempfile.TemporaryDirectory(prefix="te-bench-warm-") as tmp:
        warm_cycle = Path(tmp) / "warm.yaml"
        col = DEFAULT_COLUMNS  # a drive cycle is data without a model
        warm_cycle.write_text(yaml.safe_dump({"name": "warm_up", "dt_s": 1.0, col[Role.AMBIENT]: 25.0, "segments": [
            {"duration_s": WARM_UP_S, col[Role.SPEED]: 900.0, col[Role.TORQUE]: WARM_UP_TORQUE_NM, "ramp_s": 10.0}]}))
        emu = emulator_for(plant, warm_cycle, case, None, pmsm=pmsm, voltages=voltages)
        pol = ThermalEdgePolicy(emu, cfg.derating.max_current_a, cfg.derating.max_torque_nm, cfg)
        try:
            closed_loop(emu, pol, kt, [])
            state = pol.engine.persisted(T0 - RESTART_DOWNTIME_S)
        finally:
            pol.close()
        # the machine stands still over the downtime
        ambient = float(emu.run_inputs.columns[plant.input_name(Role.AMBIENT)][-1])
        rest = plant.at_rest({c: ambient for c in plant.temperature_inputs})
        T, _ = Stepper(plant, emu.plant.theta, RESTART_DOWNTIME_S).step(emu.plant.T, rest)
    return {"T": T, "state": state}


def _run_case_args(args: tuple[Case, tuple[str, ...], Path | None, float | None, Path | None]) -> dict[str, dict[str, Any]]:
    return run_case(*args)


@dataclass
class ProtectionResult:
    """``bench protection``: per case and policy the figures of :func:`run_case`, and the totals."""

    cycle: str  #: the drive cycle file
    duration_s: float | None  #: simulated seconds of it (None: all)
    policies: list[str]
    reaction_time_s: float
    max_c: dict[str, float]  #: each limited node's maximum, degC
    cases: dict[str, dict[str, Any]] = field(default_factory=dict)  #: case -> policy -> figures
    case_docs: dict[str, str] = field(default_factory=dict)
    min_oracle_share_pct: float | None = None  #: thermal_edge's worst share of the oracle
    total_seconds_over_max: float | None = None  #: thermal_edge's, over all cases
    #: thermal_edge_voltages' worst share of the oracle, over the cases calibrated right
    min_oracle_share_voltages_pct: float | None = None
    total_seconds_over_max_voltages: float | None = None  #: thermal_edge_voltages', over all cases
    #: the cases whose electrical calibration is wrong on purpose: their share is not a target
    miscalibrated_cases: list[str] = field(default_factory=list)
    totals: dict[str, dict[str, float]] = field(default_factory=dict)  #: policy -> seconds over max
    wall_s: float = 0.0


def run(cases: list[Case] | None = None, policies: tuple[str, ...] = POLICIES, cycle: Path | None = None,
        duration_s: float | None = None, config_file: Path | None = None, jobs: int = 1,
        progress: Callable[[str], None] | None = None) -> ProtectionResult:
    """Every case, every policy; the figures and, for ``thermal_edge``, the worst share of the
    oracle and the total time over max.

    Parameters
    ----------
    cases : list of Case, optional
        Default: all of :data:`CASES`.
    jobs : int
        Cases run in this many processes at once (each case is one process's work).
    progress : callable, optional
        Called with a line per finished case (default: printed to stderr).
    """
    cases = cases if cases is not None else list(CASES.values())
    say = progress if progress is not None else (lambda msg: print(msg, file=sys.stderr, flush=True))
    cycle = cycle if cycle is not None else config_path("cycles", "protection.yaml")
    with tempfile.TemporaryDirectory(prefix="te-bench-protection-") as tmp:
        cfg = edge_config(Path(tmp), config_file)
    res = ProtectionResult(str(cycle), duration_s, list(policies), cfg.derating.reaction_time_s, {})
    from ..service.engine import load_service_model

    for lim in load_service_model(cfg).limits:
        res.max_c[lim.name] = cfg.limit_band(lim)[1]
    w0 = time.perf_counter()
    done = 0

    def report(case: Case, r: dict[str, dict[str, Any]]) -> None:
        nonlocal done
        done += 1
        res.cases[case.name] = r
        res.case_docs[case.name] = case.doc
        te = r.get("thermal_edge")
        te_txt = (f": thermal_edge {te['oracle_share_pct']:.1f} % of the oracle, {te['seconds_over_max']:g} s over max"
                  if te else "")
        tv = r.get("thermal_edge_voltages")
        if tv:
            te_txt += (f"{';' if te else ':'} with voltages {tv['oracle_share_pct']:.1f} %, "
                       f"{tv['seconds_over_max']:g} s over max")
        say(f"bench protection: case {done}/{len(cases)} {case.name}{te_txt} ({time.perf_counter() - w0:.0f} s)")

    work = [(c, policies, cycle, duration_s, config_file) for c in cases]
    if jobs > 1 and len(cases) > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(min(jobs, len(cases))) as pool:
            for case, r in zip(cases, pool.imap(_run_case_args, work)):
                report(case, r)
    else:
        for args in work:
            report(args[0], _run_case_args(args))
    res.cases = {c.name: res.cases[c.name] for c in cases}  # in the order asked
    te_all = [c["thermal_edge"] for c in res.cases.values() if "thermal_edge" in c]
    if te_all:
        res.min_oracle_share_pct = min(f["oracle_share_pct"] for f in te_all)
        res.total_seconds_over_max = sum(f["seconds_over_max"] for f in te_all)
    res.miscalibrated_cases = [c.name for c in cases if c.flux_miscalibrated]
    tv_all = {name: c["thermal_edge_voltages"] for name, c in res.cases.items() if "thermal_edge_voltages" in c}
    if tv_all:
        right = [f["oracle_share_pct"] for name, f in tv_all.items() if name not in res.miscalibrated_cases]
        res.min_oracle_share_voltages_pct = min(right) if right else None
        res.total_seconds_over_max_voltages = sum(f["seconds_over_max"] for f in tv_all.values())
    res.totals = {p: {"seconds_over_max": sum(c[p]["seconds_over_max"] for c in res.cases.values() if p in c)}
                  for p in policies}
    res.wall_s = time.perf_counter() - w0
    return res


TABLE_HEADERS = ["case", "policy", "headroom %", "of oracle %", "peak hot spot °C", "peak magnet °C", "s over max"]


def table_rows(res: ProtectionResult) -> list[list[Any]]:
    """Rows of the bench's table: one per case and policy."""
    rows: list[list[Any]] = []
    for case, by_policy in res.cases.items():
        for p, f in by_policy.items():
            rows.append([case, p, round(f["headroom_pct"], 1), round(f["oracle_share_pct"], 1), round(f["peak_hot_spot_c"], 1),
                         round(f["peak_magnet_c"], 1), f["seconds_over_max"]])
    return rows


#: the side-by-side table: per case, each policy's share of the oracle (%) and seconds over max
SIDE_BY_SIDE_POLICIES = ("thermal_edge", "thermal_edge_voltages", "pt100_linear", "i2t")
SIDE_BY_SIDE_HEADERS = ["case", "without voltages % / s over", "with voltages % / s over", "PT100 rule % / s over",
                        "I²t % / s over", "flux used / refused"]


def side_by_side_rows(res: ProtectionResult) -> list[list[Any]]:
    """One row per case: thermal_edge without and with the voltage frame beside the PT100 rule and
    I²t, each as ``share of the oracle % / seconds over max``, and the flux estimate's ticks used
    and refused (every cause of :data:`~thermal_edge.service.flux_input.REFUSALS`) with the frame."""
    from ..service.flux_input import REFUSALS

    rows: list[list[Any]] = []
    for case, by_policy in res.cases.items():
        row: list[Any] = [case]
        for p in SIDE_BY_SIDE_POLICIES:
            f = by_policy.get(p)
            row.append(f"{f['oracle_share_pct']:.1f} / {f['seconds_over_max']:g}" if f is not None else "-")
        flux = by_policy.get("thermal_edge_voltages", {}).get("flux")
        row.append(f"{flux.get('used', 0)} / {sum(flux.get(k, 0) for k in REFUSALS)}"
                   if flux is not None else "-")
        rows.append(row)
    return rows


def verdicts(res: ProtectionResult) -> list[str]:
    """Plain sentences: where a baseline overheats, and whether thermal_edge delivers more than each
    baseline that does not."""
    out = []
    for case, by_policy in res.cases.items():
        for p in SERVICE_POLICIES + ("pt100_linear", "i2t", "oracle"):
            f = by_policy.get(p)
            if f is None:
                continue
            if f["seconds_over_max"] > 0:
                out.append(f"{case}: {p} overheats ({f['seconds_over_max']:g} s over max; peaks {f['peak_hot_spot_c']:.1f} / "
                           f"{f['peak_magnet_c']:.1f} degC)")
            elif p in ("pt100_linear", "i2t"):
                for name in SERVICE_POLICIES:
                    te = by_policy.get(name)
                    if te is None:
                        continue
                    more = te["delivered_as"] - f["delivered_as"]
                    beyond = (f", and delivers {f['oracle_share_pct']:.1f} % of what the oracle, which reads the true "
                              f"temperatures, delivers: its early derate left headroom the cycle asks for later"
                              if f["oracle_share_pct"] > 100.0 else "")
                    out.append(f"{case}: {name} delivers {100 * more / f['delivered_as']:+.1f} % vs {p} (which stays below "
                               f"max{beyond})")
    return out
