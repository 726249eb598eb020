"""The effect catalogue: named physical effects a thermal model may lack, as edits of its YAML.

Every effect is an *augmentation* of a model document (the raw YAML mapping): one to three new
parameters and a few changed or added entries (losses, conductances, a node, a sensor), written
in the model's own law grammar, so that adding an effect is writing a few lines of YAML. The
augmented document is validated by :func:`thermal_edge.lptn.loader.build_model` like any model.

Every effect has a *zero-effect* value of its parameters (the model is then unchanged) and a
*default magnitude* used by ``thermal-edge simulate --effect`` to hide it in simulated data; both,
with the bounds, are stated once, in :data:`CATALOGUE` (the table of parameters at the end of
this docstring is generated from it).

Reference scales: ``s = |speed| / n_ref`` and ``current / i_ref`` (the model's inputs of role
speed and current), where ``n_ref`` and ``i_ref`` are the 95th percentiles of the run's speed and
current rounded to two significant digits (:func:`references`); they are written into the laws
as numbers, so magnitudes read as "W (or a factor) at the run's typical high-load point".
Nodes are chosen by their role in the model file (:class:`~thermal_edge.lptn.vocabulary.NodeRole`):
windings, stator iron (yoke, tooth), magnets, the bearing side (shaft, end caps) and the frame
(housing, end caps); the ambient air is the boundary whose input has the role ``ambient``.

=====================================  =========================================================
effect[:target]                        law (X = the existing law)
=====================================  =========================================================
``copper_temperature``                 every winding loss ``X + (k100 - 1) (T.<node> - t_ref) / 100
                                       * X(T=t_ref)``; ``k100`` the loss factor 100 K above
                                       ``t_ref`` (1 = none, < 1 allowed: AC copper loss falls with
                                       temperature)
``speed_convection:<conductance>``     ``g = X * (1 + k * s ** m)`` (``r`` laws are divided)
``iron_loss_frequency``                every stator iron loss ``X * (1 + k * s ** m)``
``magnet_eddy_loss``                   loss ``p * (s * current / i_ref) ** 2`` shared by the
                                       magnet nodes (else the rotor iron)
``bearing_loss``                       loss ``p * s`` shared by the bearing-side nodes (else
                                       the rotor iron, else the magnets)
``housing_radiation``                  heat leaving the frame nodes ``eps_a * 5.67e-8 *
                                       ((T + 273.15)^4 - (T_amb + 273.15)^4)`` (shared by
                                       their conductance to ambient)
``natural_convection``                 heat leaving the frame nodes ``h * max(T - T_amb, 0)
                                       ** 1.25`` (conductance ∝ ΔT^0.25)
``sensor_lag:<sensor>``                a probe node of capacity ``tau * 0.01`` J/K joined to
                                       the sensed node by 0.01 W/K, the sensor moved onto it
``ambient_offset[:<boundary>]``        the air at the machine is ``dT`` warmer than the
                                       boundary input: loss ``dT * g`` at every point joined
                                       to the boundary by ``g``
``contact_resistance:<conductance>``   an extra series resistance ``R`` (K/W) on one
                                       conductance (its magnitudes scale with the path's
                                       nominal resistance)
=====================================  =========================================================

Targets: a *conductance group* (``speed_convection``) is named by the parameters its law uses
(e.g. ``R_e_hous`` = the four housing-to-ambient conductances of pm10kw; ``h_gap0+h_gap1`` =
the air-gap conductances), or by its two ends when the law uses no parameter (``st-pm``). A
single conductance (``contact_resistance``) is named by its two ends, arc faces dropped
(``housing_6-yoke_1``). A sensor target is a sensor name; a boundary target a boundary name.
``applicable(raw, model, refs)`` lists every candidate a model admits.
"""
from __future__ import annotations

import copy
import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from ..lptn.expr import Table, Value, parse
from ..lptn.loader import build_model
from ..lptn.model import Model, ModelError
from ..lptn.vocabulary import (
    BEARING_SIDE,
    FRAME,
    STATOR_IRON,
    TEMP_PREFIX,
    NodeRole,
    Role,
    temperature_name,
)

SIGMA_SB = 5.670374419e-8
PROBE_G = 0.01  # W/K: conductance of a sensor probe node to the sensed node



class EffectError(ModelError):
    """An unknown effect, a target the model does not have, or a bad parameter setting."""


@dataclass(frozen=True)
class EffectParam:
    """One parameter of an effect.

    ``null`` is the zero-effect value (may lie outside ``[lower, upper]``: the model file needs
    ``min > 0``, the score test evaluates at ``null``); ``primary`` parameters are score-tested,
    shape parameters (``primary=False``) stay at ``nominal`` in the score test and are fitted in
    the full fit.
    """

    short: str
    unit: str
    doc: str
    null: float
    nominal: float
    lower: float
    upper: float
    default: float
    primary: bool = True
    two_sided: bool = False  # the effect may go either way from ``null`` (else only up)


@dataclass(frozen=True)
class Effect:
    """One catalogue effect: its parameters, what it acts on (:meth:`targets`) and how it changes
    a model document (:meth:`change`). One subclass per effect; the catalogue holds one instance
    of each."""

    name: str
    abbr: str
    target_kind: str  # none | group | edge | sensor | boundary
    params: tuple[EffectParam, ...]
    explains: str  # the operating variable the effect follows (residual analysis key)
    doc: str
    scale_by_target: bool = False  # parameter bounds/default scale with the target's nominal resistance
    #: the edit reads laws from the built model (its document must be built before it is applied)
    reads_built_model: ClassVar[bool] = False
    #: the edit moves a sensor onto a new node (the score test gives it a model of its own)
    moves_sensor: ClassVar[bool] = False
    #: the added law is not affine in the node temperatures (simulated step by step)
    nonaffine: ClassVar[bool] = False
    #: where the effect's heat acts, by node role: the first group of roles the model has nodes
    #: of is used (an ordered fallback to the nearest part the model represents); empty for
    #: effects that act on a named target or on every node of one kind
    places: ClassVar[tuple[frozenset[NodeRole], ...]] = ()

    def targets(self, ctx: Context) -> list[str | None]:
        """Every target in the model (``[None]`` when the effect applies and takes none, ``[]``
        when the model has nothing it can act on)."""
        raise NotImplementedError

    def change(self, ctx: Context, target: str | None, P: Mapping[str, str], ed: _Editor) -> None:
        """Edit ``ed.raw`` (through ``ed``) so that it has the effect; ``P`` maps the parameters'
        short names to their model parameter names."""
        raise NotImplementedError


@dataclass
class Candidate:
    """An effect on one target (``target`` None for effects without one)."""

    effect: Effect
    target: str | None = None

    @property
    def label(self) -> str:
        return self.effect.name + (f":{self.target}" if self.target else "")


@dataclass
class Context:
    """What the effects need to know about a model: its raw document, built form and roles."""

    raw: dict[str, Any]
    model: Model
    refs: dict[str, float]
    groups: dict[str, list[int]] = field(default_factory=dict)  # conductance group -> raw indices
    edges: dict[str, int] = field(default_factory=dict)  # single conductance name -> raw index
    edge_r_nominal: dict[int, float] = field(default_factory=dict)  # raw index -> nominal K/W

    @property
    def speed(self) -> str | None:
        """The model's speed input (rpm), None without one."""
        return self.model.find_input(Role.SPEED)

    @property
    def current(self) -> str | None:
        """The model's RMS current input (A), None without one."""
        return self.model.find_input(Role.CURRENT)


# ------------------------------------------------------------------------------------------
# the catalogue

def _p(short: str, unit: str, doc: str, nominal: float, lower: float, upper: float, default: float, null: float = 0.0,
       primary: bool = True, two_sided: bool = False) -> EffectParam:
    return EffectParam(short, unit, doc, null, nominal, lower, upper, default, primary, two_sided)


class CopperTemperature(Effect):
    def targets(self, ctx: Context) -> list[str | None]:
        return [None] if _loss_nodes(ctx, NodeRole.WINDING) else []

    def change(self, ctx: Context, target: str | None, P: Mapping[str, str], ed: _Editor) -> None:
        # X + a (T - t_ref) X(T = t_ref): the loss X rises by a per kelvin above t_ref. Written
        # with X taken at t_ref the law stays affine in T when X is (fast simulation).
        for i in _loss_nodes(ctx, NodeRole.WINDING):
            spec = dict(ed.raw["losses"][i])
            node = spec["node"]
            if node not in ctx.model.nodes:
                continue
            law = _law_str(spec["power"])
            at_ref = re.sub(rf"\b{re.escape(TEMP_PREFIX)}[A-Za-z_][\w]*(?![\w.])", P["t_ref"], law)
            spec["power"] = f"{law} + ({P['k100']} - 1) / 100 * ({temperature_name(node)} - {P['t_ref']}) * ({at_ref})"
            ed.replace("losses", i, spec)


class SpeedConvection(Effect):
    def targets(self, ctx: Context) -> list[str | None]:
        return list(ctx.groups) if ctx.speed else []

    def change(self, ctx: Context, target: str | None, P: Mapping[str, str], ed: _Editor) -> None:
        if target not in ctx.groups:
            raise EffectError(f"speed_convection: unknown conductance group {target!r} (known: {', '.join(ctx.groups)})")
        fac = f"(1 + {P['k']} * ({_speed_law(ctx)}) ** {P['m']})"
        for i in ctx.groups[target]:
            spec = dict(ed.raw["conductances"][i])
            if "g" in spec:
                spec["g"] = f"({_law_str(spec['g'])}) * {fac}"
            else:
                spec["r"] = f"({_law_str(spec['r'])}) / {fac}"
            ed.replace("conductances", i, spec)


class IronLossFrequency(Effect):
    def targets(self, ctx: Context) -> list[str | None]:
        return [None] if ctx.speed and _iron_losses(ctx) else []

    def change(self, ctx: Context, target: str | None, P: Mapping[str, str], ed: _Editor) -> None:
        fac = f"(1 + {P['k']} * ({_speed_law(ctx)}) ** {P['m']})"
        for i in _iron_losses(ctx):
            spec = dict(ed.raw["losses"][i])
            spec["power"] = f"({_law_str(spec['power'])}) * {fac}"
            ed.replace("losses", i, spec)


class MagnetEddyLoss(Effect):
    #: eddy currents flow in the magnets; a model that lumps the magnets into its rotor iron gets
    #: the loss there
    places: ClassVar[tuple[frozenset[NodeRole], ...]] = (
        frozenset({NodeRole.MAGNET}), frozenset({NodeRole.ROTOR_IRON}))

    def targets(self, ctx: Context) -> list[str | None]:
        return [None] if ctx.speed and ctx.current and placed_nodes(ctx, self) else []

    def change(self, ctx: Context, target: str | None, P: Mapping[str, str], ed: _Editor) -> None:
        nodes = placed_nodes(ctx, self)
        x = f"abs({ctx.speed}) / {_fmt(ctx.refs['n_ref'])} * {ctx.current} / {_fmt(ctx.refs['i_ref'])}"
        for node in nodes:
            ed.add_loss(node, f"{P['p']} / {len(nodes)} * ({x}) ** 2")


class BearingLoss(Effect):
    #: the bearings sit in the end shields on the shaft; a model without those parts carries the
    #: rotor's heat in its rotor iron, and a model whose rotor is its magnets in those
    places: ClassVar[tuple[frozenset[NodeRole], ...]] = (
        BEARING_SIDE, frozenset({NodeRole.ROTOR_IRON}), frozenset({NodeRole.MAGNET}))

    def targets(self, ctx: Context) -> list[str | None]:
        return [None] if ctx.speed and placed_nodes(ctx, self) else []

    def change(self, ctx: Context, target: str | None, P: Mapping[str, str], ed: _Editor) -> None:
        nodes = placed_nodes(ctx, self)
        for node in nodes:
            ed.add_loss(node, f"{P['p']} / {len(nodes)} * abs({ctx.speed}) / {_fmt(ctx.refs['n_ref'])}")


class _FrameHeatOut(Effect):
    """Heat leaving the frame nodes to ambient by a law not linear in the temperature rise."""

    nonaffine: ClassVar[bool] = True

    def targets(self, ctx: Context) -> list[str | None]:
        return [None] if _frame_nodes(ctx) else []

    def law(self, node: str, share: float, ambient: str, P: Mapping[str, str]) -> str:
        raise NotImplementedError

    def change(self, ctx: Context, target: str | None, P: Mapping[str, str], ed: _Editor) -> None:
        amb = ambient_boundary(ctx.model) or next(iter(ctx.model.boundaries))
        for node, w in _frame_nodes(ctx):
            ed.add_loss(node, self.law(node, w, ctx.model.boundaries[amb], P))


class HousingRadiation(_FrameHeatOut):
    def law(self, node: str, share: float, ambient: str, P: Mapping[str, str]) -> str:
        return f"-{P['eps_a']} * {_fmt(share)} * {SIGMA_SB:.6g} * ((T.{node} + 273.15) ** 4 - ({ambient} + 273.15) ** 4)"


class NaturalConvection(_FrameHeatOut):
    def law(self, node: str, share: float, ambient: str, P: Mapping[str, str]) -> str:
        return f"-{P['h']} * {_fmt(share)} * max(T.{node} - {ambient}, 0) ** 1.25"


class SensorLag(Effect):
    moves_sensor: ClassVar[bool] = True

    def targets(self, ctx: Context) -> list[str | None]:
        return [s for s, node in ctx.model.sensors.items() if not node.endswith("_probe")]

    def change(self, ctx: Context, target: str | None, P: Mapping[str, str], ed: _Editor) -> None:
        sensors = ed.raw.get("sensors") or {}
        if target is None or target not in sensors:
            raise EffectError(f"sensor_lag: unknown sensor {target!r} (known: {', '.join(sensors)})")
        node = sensors[target]["node"]
        probe = f"{_sanitize(target)}_probe"
        k = 2
        while probe in ctx.model.nodes or probe in (ctx.model.points or ()):
            probe = f"{_sanitize(target)}_probe{k}"
            k += 1
        ed.add("nodes", {"name": probe, "capacity": f"{P['tau']} * {PROBE_G:g}"})
        ed.add("conductances", {"between": [node, probe], "g": PROBE_G})
        sspec = dict(sensors[target])
        sspec["node"] = probe
        ed.raw["sensors"][target] = sspec
        ed.edits.append(Edit("map_replace", "sensors", target, sspec, ed.label))


class AmbientOffset(Effect):
    reads_built_model: ClassVar[bool] = True

    def targets(self, ctx: Context) -> list[str | None]:
        return list(ctx.model.boundaries)

    def change(self, ctx: Context, target: str | None, P: Mapping[str, str], ed: _Editor) -> None:
        if target not in ctx.model.boundaries:
            raise EffectError(f"ambient_offset: unknown boundary {target!r} (known: {', '.join(ctx.model.boundaries)})")
        by_key = {e.key: e for e in ctx.model.edges}
        for i in _boundary_edges(ctx, target):
            edge = by_key[f"conductances[{i}]"]
            ed.add_loss(edge.a, f"{P['dT']} * ({edge.g})")


class ContactResistance(Effect):
    def targets(self, ctx: Context) -> list[str | None]:
        return [n for n, i in ctx.edges.items() if np.isfinite(ctx.edge_r_nominal.get(i, float("nan")))]

    def change(self, ctx: Context, target: str | None, P: Mapping[str, str], ed: _Editor) -> None:
        if target not in ctx.edges:
            raise EffectError(f"contact_resistance: unknown conductance {target!r}")
        i = ctx.edges[target]
        spec = dict(ed.raw["conductances"][i])
        if "r" in spec:
            spec["r"] = f"{_law_str(spec.pop('r'))} + {P['R']}"
        elif "g" in spec:
            spec["r"] = f"1 / ({_law_str(spec.pop('g'))}) + {P['R']}"
        else:
            spec["r"] = P["R"]
        ed.replace("conductances", i, spec)


CATALOGUE: dict[str, Effect] = {
    e.name: e
    for e in (
        CopperTemperature("copper_temperature", "cuT", "none",
               (_p("k100", "1", "winding loss factor 100 K above t_ref (1: no temperature dependence; below 1 "
                   "when eddy/AC copper loss, which falls with temperature, dominates)", 1.0, 0.3, 3.0, 1.4, null=1.0,
                   two_sided=True),
                _p("t_ref", "degC", "winding temperature at which the modelled loss is right", 20.0, 1.0, 150.0, 20.0,
                   null=20.0, primary=False)),
               "temperature", "winding loss rises with winding temperature"),
        SpeedConvection("speed_convection", "sc", "group",
               (_p("k", "1", "relative rise of the conductance at the reference speed", 1e-4, 1e-5, 30.0, 1.0),
                _p("m", "1", "speed exponent", 1.0, 0.2, 3.0, 1.0, null=1.0, primary=False)),
               "speed", "a conductance grows with speed (fan, air gap, rotating surfaces)"),
        IronLossFrequency("iron_loss_frequency", "feF", "none",
               (_p("k", "1", "relative rise of the iron loss at the reference speed", 1e-4, 1e-5, 20.0, 1.0),
                _p("m", "1", "speed exponent of the rise", 1.0, 0.2, 3.0, 1.0, null=1.0, primary=False)),
               "speed", "iron loss grows faster with speed than modelled"),
        MagnetEddyLoss("magnet_eddy_loss", "pmE", "none",
               (_p("p", "W", "magnet eddy loss at the reference speed and current", 1e-3, 1e-4, 1e4, 100.0),),
               "speed_current2", "rotor/magnet loss proportional to (speed x current)^2"),
        BearingLoss("bearing_loss", "brg", "none",
               (_p("p", "W", "extra mechanical loss at the reference speed", 1e-3, 1e-4, 1e4, 60.0),),
               "speed", "mechanical (bearing, seal) loss at the shaft and end caps proportional to speed"),
        HousingRadiation("housing_radiation", "rad", "none",
               (_p("eps_a", "m^2", "emissivity x radiating area of the frame", 1e-4, 1e-5, 20.0, 0.8),),
               "rise", "radiation from the frame, proportional to T^4 - T_amb^4"),
        NaturalConvection("natural_convection", "nc", "none",
               (_p("h", "W/K^1.25", "natural-convection coefficient x area of the frame", 1e-4, 1e-5, 100.0, 1.0),),
               "rise", "frame-to-ambient conductance grows with the temperature rise as dT^0.25"),
        SensorLag("sensor_lag", "lag", "sensor",
               (_p("tau", "s", "first-order time constant of the sensor", 5.0, 1.0, 3600.0, 300.0, null=1.0),),
               "dTdt", "first-order lag of a sensor (probe node of small capacity)"),
        AmbientOffset("ambient_offset", "amb", "boundary",
               (_p("dT", "K", "air at the machine warmer than the boundary input", 0.1, 1e-3, 40.0, 4.0),),
               "ambient", "the air at the machine is warmer than the ambient sensor"),
        ContactResistance("contact_resistance", "cr", "edge",
               (_p("R", "K/W", "extra series resistance (aged insulation, loose fit)", 1e-3, 1e-4, 100.0, 2.0),),
               "current2", "an extra series resistance on one conductance path", scale_by_target=True),
    )
}


def references(model: Model, columns: Mapping[str, np.ndarray]) -> dict[str, float]:
    """Reference speed and current of a run (the model's speed and current inputs): 95th
    percentiles rounded to two significant digits."""
    def nice(x: float, floor: float) -> float:
        if not np.isfinite(x) or x <= 0:
            return floor
        e = math.floor(math.log10(x)) - 1
        return max(round(x / 10**e) * 10**e, floor)

    out = {"n_ref": 1000.0, "i_ref": 10.0}
    for key, role, floor in (("n_ref", Role.SPEED, 1.0), ("i_ref", Role.CURRENT, 0.1)):
        col = model.find_input(role)
        if col is not None and col in columns:
            v = np.abs(np.asarray(columns[col], float))
            out[key] = float(nice(float(np.nanpercentile(v, 95)), floor))
    return out


def ambient_boundary(model: Model) -> str | None:
    """The boundary whose input is the ambient air temperature (by its role), None without one."""
    col = model.find_input(Role.AMBIENT)
    return next((b for b, c in model.boundaries.items() if c == col), None) if col else None


# ------------------------------------------------------------------------------------------
# analysis of a model document

def _dummy_tables(raw: Mapping[str, Any]) -> dict[str, Table]:
    return {k: _unread_table for k in (raw.get("tables") or {})}


def _unread_table(*args: object) -> np.ndarray:
    """Stands for a model's table where only the names a law uses matter (never evaluated)."""
    raise EffectError("a table is not evaluated while the effects analyse a model")


def is_effect_parameter(spec: Any) -> bool:
    """A parameter an effect added (its doc starts with ``<effect>[:<target>]: ``)."""
    doc = str(spec.get("doc", "")) if isinstance(spec, Mapping) else ""
    head = doc.split(": ", 1)[0] if ": " in doc else ""
    return head.split(":", 1)[0] in CATALOGUE


def law_params(raw: Mapping[str, Any], law: Any) -> set[str]:
    """Model parameters a raw law uses (parameters added by effects not counted)."""
    params = raw.get("parameters") or {}
    pnames = {k for k, v in params.items() if not is_effect_parameter(v)}
    return set(parse(law, _dummy_tables(raw)).free()) & pnames


def _end(ref: str) -> str:
    """An endpoint without its arc face suffix (``housing_1.r_out`` -> ``housing_1``)."""
    return str(ref).split(".", 1)[0]


def _sanitize(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9_]", "_", s)


def context(raw: Mapping[str, Any], model: Model | None = None, refs: Mapping[str, float] | None = None,
            build: Callable[[dict[str, Any]], Model] | None = None) -> Context:
    """Analyse a model document: conductance groups, single conductances and their scales."""
    own = copy.deepcopy(dict(raw))
    model = model if model is not None else (build or build_model)(own)
    ctx = Context(own, model, dict(refs or {"n_ref": 1000.0, "i_ref": 10.0}))
    conns = own.get("conductances") or []
    by_key = {e.key: e for e in model.edges}
    theta = model.nominal()
    env_base: dict[str, Value] = dict(zip(model.parameter_names, theta))
    # a typical operating point for nominal values: the reference speed and current, 25 °C
    op = {c: np.array(0.0) for c in model.inputs}
    if ctx.speed:
        op[ctx.speed] = np.array(ctx.refs["n_ref"] / 2)
    if ctx.current:
        op[ctx.current] = np.array(ctx.refs["i_ref"] / 2)
    for c in model.boundaries.values():
        op[c] = np.array(25.0)
    env_base.update(op)
    for k, expr in model.derived.items():
        try:
            env_base[k] = expr.compile()(env_base)
        except Exception:
            env_base[k] = np.array(0.0)
    names: dict[str, int] = {}
    for i, spec in enumerate(conns):
        a, b = (_end(x) for x in spec["between"])
        name = f"{a}-{b}"
        if name in names:
            dup = 2
            while f"{name}#{dup}" in names:
                dup += 1
            name = f"{name}#{dup}"
        names[name] = i
        edge = by_key.get(f"conductances[{i}]")
        if edge is not None:
            try:
                g = float(np.asarray(edge.g.compile()(env_base)))
                ctx.edge_r_nominal[i] = 1.0 / g if g > 0 else float("nan")
            except Exception:
                ctx.edge_r_nominal[i] = float("nan")
        law = spec.get("g", spec.get("r"))
        if law is None:
            continue
        ps = law_params(raw, law)
        key = "+".join(sorted(ps)) if ps else name
        ctx.groups.setdefault(key, []).append(i)
    ctx.edges = names
    return ctx


def _loss_nodes(ctx: Context, *roles: NodeRole) -> list[int]:
    """Raw indices of the losses at nodes of the given roles."""
    nodes = set(ctx.model.nodes_with(*roles))
    return [i for i, spec in enumerate(ctx.raw.get("losses") or []) if str(spec.get("node", "")) in nodes]


def _boundary_edges(ctx: Context, boundary: str) -> list[int]:
    """Raw indices of conductances to a boundary."""
    return [i for i, spec in enumerate(ctx.raw.get("conductances") or []) if boundary in [str(x) for x in spec["between"]]]


def _frame_nodes(ctx: Context) -> list[tuple[str, float]]:
    """Frame nodes (outer surface to ambient) with their share of the frame's conductance to ambient."""
    amb = [ambient_boundary(ctx.model) or next(iter(ctx.model.boundaries))]
    frame = set(ctx.model.nodes_with(*FRAME))
    out: dict[str, float] = {}
    for b in amb:
        for i in _boundary_edges(ctx, b):
            spec = ctx.raw["conductances"][i]
            node = next(_end(x) for x in spec["between"] if str(x) != b)
            if node in frame:
                r = ctx.edge_r_nominal.get(i, float("nan"))
                out[node] = out.get(node, 0.0) + (1.0 / r if r and np.isfinite(r) and r > 0 else 0.0)
    tot = sum(out.values())
    if not out or tot <= 0:
        return []
    return [(n, g / tot) for n, g in out.items()]


def _iron_losses(ctx: Context) -> list[int]:
    """Stator iron losses: loss laws at iron nodes that depend on speed (directly or via derived inputs)."""
    raw = ctx.raw
    speed_dep = {ctx.speed} if ctx.speed else set()
    for k, expr in ctx.model.derived.items():  # in dependency order
        if expr.free() & speed_dep:
            speed_dep.add(k)
    out: list[int] = []
    for i in _loss_nodes(ctx, *STATOR_IRON):
        law = raw["losses"][i]["power"]
        free = set(parse(law, _dummy_tables(raw)).free())
        if free & speed_dep:
            out.append(i)
    return out


def placed_nodes(ctx: Context, effect: Effect) -> tuple[str, ...]:
    """The nodes an effect with :attr:`Effect.places` acts on: those of the first role group in
    its fallback order that the model has (empty when it has none of them)."""
    for roles in effect.places:
        nodes = ctx.model.nodes_with(*roles)
        if nodes:
            return nodes
    return ()


def placement(ctx: Context, effect: Effect) -> str:
    """Where an applicable effect acts, in words (``"into pm (magnet: no shaft, end cap or rotor
    iron node)"``); empty for effects with a named target."""
    for k, roles in enumerate(effect.places):
        nodes = ctx.model.nodes_with(*roles)
        if nodes:
            missing = sorted({r.value.replace("_", " ") for g in effect.places[:k] for r in g})
            why = f": no {', '.join(missing)} node" if missing else ""
            role_names = "/".join(sorted(r.value.replace("_", " ") for r in roles))
            return f"into {', '.join(nodes)} ({role_names}{why})"
    return ""


def unplaceable_reason(ctx: Context, effect: Effect) -> str:
    """Why an effect has no target on this model (one clause), for the report's "not placeable"."""
    if effect.places:
        wanted = " or ".join(r.value.replace("_", " ") for g in effect.places for r in sorted(g, key=lambda r: r.value))
        if not ctx.speed and effect.explains.startswith("speed"):
            return "the model has no speed input"
        return f"the model has no {wanted} node"
    if isinstance(effect, _FrameHeatOut):
        amb = ambient_boundary(ctx.model)
        where = f"joined to the {amb} boundary" if amb else "(and no ambient boundary)"
        return f"the model has no frame node (housing or end cap) {where}"
    if isinstance(effect, (SpeedConvection, IronLossFrequency)) and not ctx.speed:
        return "the model has no speed input"
    if isinstance(effect, IronLossFrequency):
        return "the model has no speed-dependent loss at a stator iron (yoke, tooth) node"
    if isinstance(effect, CopperTemperature):
        return "the model has no loss at a winding node"
    if isinstance(effect, MagnetEddyLoss) and not ctx.current:
        return "the model has no current input"
    return f"the model offers no {effect.target_kind} it acts on"


@dataclass(frozen=True)
class NotPlaceable:
    """A catalogue effect the model cannot express, and why."""

    effect: Effect
    reason: str


def not_placeable(ctx: Context, names: Sequence[str] | None = None) -> list[NotPlaceable]:
    """The catalogue effects (of ``names``, default all) that have no target on the model."""
    out: list[NotPlaceable] = []
    for name in names or CATALOGUE:
        eff = get(name)
        if not targets(ctx, eff):
            out.append(NotPlaceable(eff, unplaceable_reason(ctx, eff)))
    return out


def targets(ctx: Context, effect: Effect) -> list[str | None]:
    """Every target of ``effect`` in the model (``[None]`` for an applicable effect without one,
    ``[]`` when the model has nothing the effect can act on)."""
    return effect.targets(ctx)


def applicable(ctx: Context, names: Sequence[str] | None = None) -> list[Candidate]:
    """All candidates (effect, target) the model admits."""
    out: list[Candidate] = []
    for name in names or CATALOGUE:
        eff = get(name)
        out.extend(Candidate(eff, t) for t in targets(ctx, eff))
    return out


def get(name: str) -> Effect:
    try:
        return CATALOGUE[name]
    except KeyError:
        raise EffectError(f"unknown effect {name!r} (known: {', '.join(CATALOGUE)})") from None


# ------------------------------------------------------------------------------------------
# parameters and application

def param_names(ctx: Context, cand: Candidate) -> list[str]:
    """The model parameter names of a candidate's parameters (unique in the document)."""
    eff = cand.effect
    tag = f"_{_sanitize(cand.target)}" if cand.target else ""
    taken = set(ctx.raw.get("parameters") or {}) | set(ctx.raw.get("inputs") or {}) | \
        set(ctx.raw.get("derived") or {}) | set(ctx.raw.get("constants") or {})
    out = []
    for p in eff.params:
        base = f"{eff.abbr}{tag}_{p.short}"
        name, k = base, 2
        while name in taken and name not in out:
            name = f"{base}{k}"
            k += 1
        out.append(name)
    return out


def scale(ctx: Context, cand: Candidate) -> float:
    """Scale of the effect's parameters on its target (the nominal resistance for contact_resistance)."""
    if cand.effect.scale_by_target and cand.target is not None:
        r = ctx.edge_r_nominal.get(ctx.edges[cand.target], float("nan"))
        return float(r) if np.isfinite(r) and r > 0 else 1.0
    return 1.0


def param_specs(ctx: Context, cand: Candidate, values: Mapping[str, float] | None = None) -> list[dict[str, Any]]:
    """Parameter entries (``parameters:`` section) of a candidate; ``values`` by short name."""
    sc = scale(ctx, cand)
    values = dict(values or {})
    out = []
    for p in cand.effect.params:
        lo, hi = p.lower * sc, p.upper * sc
        v = float(values.get(p.short, p.nominal * sc))
        lo, hi = min(lo, v), max(hi, v)
        out.append({
            "value": _num(v), "min": _num(lo), "max": _num(hi), "unit": p.unit, "adaptable": False,
            # a wide spread (a quarter of the log range): the fits' prior hardly pulls an effect
            "spread": _num(math.log(hi / lo) / 4),
            "doc": f"{cand.label}: {p.doc}",
        })
    return out


def _num(x: float) -> float:
    return float(f"{x:.6g}")


def _fmt(x: float) -> str:
    return f"{x:.6g}"


@dataclass
class Edit:
    """One change of a model document (for the textual patch of the YAML file)."""

    kind: str  # list_add | list_replace | map_add | map_replace
    section: str
    key: Any  # list index or mapping key (None for list_add)
    entry: Any
    label: str = ""


def _speed_law(ctx: Context) -> str:
    # kept off zero so that a fitted speed exponent has a finite derivative at standstill
    return f"max(abs({ctx.speed}) / {_fmt(ctx.refs['n_ref'])}, 1e-6)"


class _Editor:
    """Changes of one document by one candidate, each recorded as an :class:`Edit`."""

    def __init__(self, raw: dict[str, Any], label: str) -> None:
        self.raw = raw
        self.label = label
        self.edits: list[Edit] = []

    def add(self, section: str, entry: dict[str, Any]) -> None:
        if self.raw.get(section) is None:
            self.raw[section] = []
        self.raw[section].append(entry)
        self.edits.append(Edit("list_add", section, None, entry, self.label))

    def add_loss(self, node: str, law: str) -> None:
        self.add("losses", {"node": node, "power": law})

    def replace(self, section: str, i: int, entry: dict[str, Any]) -> None:
        self.raw[section][i] = entry
        self.edits.append(Edit("list_replace", section, i, entry, self.label))


def apply(ctx: Context, cand: Candidate, values: Mapping[str, float] | None = None,
          inplace: bool = False) -> tuple[dict[str, Any], list[str], list[Edit]]:
    """Add one candidate to ``ctx.raw`` (a copy is returned and ``ctx`` is left alone, unless ``inplace``).

    Returns the new document, the new parameter names (in the effect's order) and the edits.
    ``values`` sets parameters by short name (default: the zero-effect nominal values).
    """
    raw = ctx.raw if inplace else copy.deepcopy(ctx.raw)
    ed = _Editor(raw, cand.label)
    names = param_names(ctx, cand)
    specs = param_specs(ctx, cand, values)
    if raw.get("parameters") is None:
        raw["parameters"] = {}
    for n, spec in zip(names, specs):
        raw["parameters"][n] = spec
        ed.edits.append(Edit("map_add", "parameters", n, spec, cand.label))
    cand.effect.change(ctx, cand.target, dict(zip((p.short for p in cand.effect.params), names)), ed)
    return raw, names, ed.edits


def _law_str(law: Any) -> str:
    return " ".join(str(law).split()) if isinstance(law, str) else repr(float(law))


def augment(raw: Mapping[str, Any], cands: Sequence[tuple[Candidate, Mapping[str, float] | None]],
            refs: Mapping[str, float], build: Callable[[dict[str, Any]], Model] | None = None,
            model: Model | None = None) -> tuple[dict[str, Any], list[list[str]], list[Edit]]:
    """Apply several candidates in turn (each on the document the previous one produced).

    Returns the document, the parameter names of each candidate and all edits.
    """
    build = build or build_model
    doc = copy.deepcopy(dict(raw))
    names, edits = [], []
    original = context(doc, model if model is not None else build(doc), refs, build)
    model, built, version = original.model, 0, 0
    for cand, values in cands:
        # targets are resolved on the original document (later edits rename groups); the
        # built model is refreshed only where an effect reads laws from it (ambient_offset)
        if cand.effect.reads_built_model and built != version:
            model, built = build(doc), version
        ctx = Context(doc, model, dict(refs), original.groups, original.edges, original.edge_r_nominal)
        doc, pn, ed = apply(ctx, cand, values, inplace=True)
        version += 1
        names.append(pn)
        edits.extend(ed)
    return doc, names, edits


# ------------------------------------------------------------------------------------------
# the --effect syntax

def parse_spec(text: str) -> tuple[str, str | None, dict[str, float]]:
    """Parse ``NAME[:TARGET][=PARAM=VALUE,...]`` into (name, target, {param: value}).

    >>> parse_spec("speed_convection:R_e_hous=k=0.8,m=1.2")
    ('speed_convection', 'R_e_hous', {'k': 0.8, 'm': 1.2})
    """
    head, sep, rest = text.strip().partition("=")
    name, _, target = head.partition(":")
    name = name.strip()
    eff = get(name)
    values: dict[str, float] = {}
    if sep:
        for item in rest.split(","):
            k, s2, v = item.partition("=")
            if not s2:
                raise EffectError(f"--effect {text!r}: expected PARAM=VALUE, got {item!r}")
            k = k.strip()
            if k not in [p.short for p in eff.params]:
                raise EffectError(f"--effect {text!r}: {name} has no parameter {k!r} "
                                  f"(has: {', '.join(p.short for p in eff.params)})")
            try:
                values[k] = float(v)
            except ValueError:
                raise EffectError(f"--effect {text!r}: {v!r} is not a number") from None
    return name, (target.strip() or None), values


def hidden_candidate(ctx: Context, spec: str) -> tuple[Candidate, dict[str, float]]:
    """The candidate and parameter values (defaults filled in) of one ``--effect`` spec."""
    name, target, values = parse_spec(spec)
    eff = get(name)
    tg = targets(ctx, eff)
    if not tg:
        raise EffectError(f"--effect {spec!r}: model {ctx.model.name} has nothing {name} can act on")
    if tg == [None]:
        if target is not None:
            raise EffectError(f"--effect {spec!r}: {name} takes no target")
    elif target is None:
        if eff.target_kind == "boundary" and tg:
            amb = ambient_boundary(ctx.model)
            target = amb if amb in tg else tg[0]
        else:
            raise EffectError(f"--effect {spec!r}: {name} needs a target, one of: {', '.join(map(str, tg))}")
    elif target not in tg:
        raise EffectError(f"--effect {spec!r}: unknown target {target!r} for {name} (one of: {', '.join(map(str, tg))})")
    cand = Candidate(eff, target)
    sc = scale(ctx, cand)
    full = {p.short: (p.default * sc if p.primary else p.default) for p in eff.params}
    for p in eff.params:  # a value the effect's law cannot take (its bounds say which sign it has)
        v = values.get(p.short)
        if v is None:
            continue
        unit = "" if p.unit in ("", "1") else f" {p.unit}"
        if not math.isfinite(v):
            raise EffectError(f"--effect {spec!r}: {p.short} must be a finite number, got {v:g}")
        if p.lower > 0 and not v > 0:
            raise EffectError(f"--effect {spec!r}: {p.short} must be > 0{unit} (the effect's range is "
                              f"{p.lower * sc:g} to {p.upper * sc:g}{unit}), got {v:g}")
    full.update(values)
    return cand, full


def catalogue_table() -> str:
    """The parameters of every effect (unit, zero-effect value, default magnitude, bounds) as a
    reStructuredText table, from :data:`CATALOGUE` (appended to this module's docstring)."""
    rows = [("effect", "parameter", "unit", "zero effect", "default", "bounds", "kind")]
    for eff in CATALOGUE.values():
        per = " × nominal R" if eff.scale_by_target else ""
        for p in eff.params:
            rows.append((eff.name, p.short, p.unit, f"{p.null:g}", f"{p.default:g}{per if p.primary else ''}",
                         f"{p.lower:g} – {p.upper:g}", "magnitude" if p.primary else "shape"))
    widths = [max(len(r[k]) for r in rows) for k in range(len(rows[0]))]
    rule = "  ".join("=" * w for w in widths)
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
    return "\n".join([rule, lines[0], rule, *lines[1:], rule])


__doc__ = (__doc__ or "") + "\nParameters of the catalogue:\n\n" + catalogue_table() + "\n"


__all__ = [
    "CATALOGUE",
    "Candidate",
    "Context",
    "Edit",
    "Effect",
    "EffectError",
    "EffectParam",
    "ambient_boundary",
    "applicable",
    "apply",
    "augment",
    "catalogue_table",
    "context",
    "get",
    "hidden_candidate",
    "param_names",
    "param_specs",
    "parse_spec",
    "references",
    "targets",
]
