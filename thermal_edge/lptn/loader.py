"""Load a machine model file (YAML, ``docs/model-format.md``) into a validated :class:`Model`.

Every error is a :class:`ModelError` whose message starts with the file name and the key,
e.g. ``pm10kw.yaml: arcs[3].r2: must be greater than r1``.
"""
from __future__ import annotations

import math
import os
from collections import Counter
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..yamlfile import read_document
from .elements import DIRECTIONS, FACES, arc_capacity, arc_resistances
from .expr import Expr, ExprError, Name, Num, evaluate_const, parse
from .model import (
    DEFAULT_SPREAD,
    Discretisation,
    Edge,
    Limit,
    Loss,
    Model,
    ModelError,
    Parameter,
)
from .tables import Lookup, load_table
from .vocabulary import (
    LIMIT,
    TEMPERATURE,
    NodeRole,
    Role,
    is_unit,
    parse_role,
    scaled_unit,
    temperature_name,
    unit_problem,
)

MATERIAL_KEYS = ("k_r", "k_a", "k_c", "rho", "c_p")


class _Ctx:
    """Parsing context: file name for messages, tables, constants, known names."""

    def __init__(self, fname: str) -> None:
        self.fname = fname
        self.tables: dict[str, Lookup] = {}
        self.constants: dict[str, Expr] = {}

    def fail(self, key: str, msg: str) -> ModelError:
        return ModelError(f"{self.fname}: {key}: {msg}")

    def law(self, key: str, value: Any, allowed: set[str], what: str) -> Expr:
        try:
            e = parse(value, self.tables).substitute(self.constants)
        except ExprError as exc:
            raise self.fail(key, str(exc)) from None
        bad = sorted(n for n in e.free() if n not in allowed)
        if bad:
            raise self.fail(key, f"{what} may not use {', '.join(bad)} (unknown, or not allowed here)")
        return e

    def role(self, key: str, value: Any, kind: type[Role] | type[NodeRole]) -> Any:
        try:
            return parse_role(value, kind)
        except ValueError as exc:
            raise self.fail(key, str(exc)) from None

    def number(self, key: str, value: Any, positive: bool = False) -> float:
        try:
            e = parse(value, self.tables).substitute(self.constants)
        except ExprError as exc:
            raise self.fail(key, str(exc)) from None
        if e.free():  # a name that is no constant of the file: most often a typo or a word
            names = ", ".join(sorted(e.free()))
            raise self.fail(key, f"expected a number (or an expression of the file's constants), got {value!r}: "
                                 f"{names} is no constant of the file")
        v = evaluate_const(e)
        if positive and not v > 0:
            raise self.fail(key, f"must be positive, got {v}")
        return v


def _req(ctx: _Ctx, d: Mapping[str, Any], key: str, where: str) -> Any:
    if not isinstance(d, Mapping):
        raise ctx.fail(where, f"expected a mapping, got {type(d).__name__}")
    if key not in d:
        raise ctx.fail(f"{where}.{key}" if where else key, "is required")
    return d[key]


def _only(ctx: _Ctx, d: Any, key: str, allowed: tuple[str, ...]) -> None:
    """Reject keys an entry does not know (a typo must not silently drop a value)."""
    if isinstance(d, Mapping):
        extra = sorted(set(d) - set(allowed))
        if extra:
            raise ctx.fail(f"{key}.{extra[0]}", f"unknown key (known: {', '.join(allowed)})")


def _mapping(ctx: _Ctx, d: Any, key: str) -> Mapping[str, Any]:
    if d is None:
        return {}
    if not isinstance(d, Mapping):
        raise ctx.fail(key, f"expected a mapping, got {type(d).__name__}")
    return d


def _list(ctx: _Ctx, d: Any, key: str) -> list[Any]:
    if d is None:
        return []
    if not isinstance(d, list):
        raise ctx.fail(key, f"expected a list, got {type(d).__name__}")
    return d


def load_model(path: str | os.PathLike[str], data_dir: str | os.PathLike[str] | None = None) -> Model:
    """Load and validate a machine model file.

    Parameters
    ----------
    path : path-like
        The YAML model file.
    data_dir : path-like, optional
        Where the model's table files are; default: ``$THERMAL_EDGE_DATA_DIR``, else the file's
        ``data_dir`` key (relative to the file).

    Raises
    ------
    ModelError
        Naming the file and the key of the first problem found.
    """
    path = Path(path)
    return build_model(read_yaml(path, ModelError), fname=path.name, path=path, data_dir=data_dir)


def read_yaml(path: str | os.PathLike[str], error: type[Exception]) -> Any:
    """Parse a YAML file (UTF-8: :mod:`thermal_edge.yamlfile`'s encoding policy); a missing,
    unreadable, binary or non-UTF-8 file or bad YAML raises ``error`` with one line naming the file."""
    return read_document(path, error)


def build_model(
    raw: Any, fname: str = "<model>", path: Path | None = None, data_dir: str | os.PathLike[str] | None = None
) -> Model:
    """Validate an already-parsed model document (see :func:`load_model`)."""
    ctx = _Ctx(fname)
    if not isinstance(raw, Mapping):
        raise ctx.fail("(top)", "expected a mapping of model sections")
    known = {
        "name", "description", "discretisation", "inputs", "boundaries", "constants", "derived", "tables",
        "data_dir", "parameters", "materials", "arcs", "nodes", "points", "conductances", "losses", "sensors",
        "limits", "drive",
    }
    extra = sorted(set(raw) - known)
    if extra:
        raise ctx.fail(extra[0], f"unknown section (known: {', '.join(sorted(known))})")
    name = str(_req(ctx, raw, "name", ""))

    # constants first: they may refer to earlier constants
    for k, v in _mapping(ctx, raw.get("constants"), "constants").items():
        ctx.constants[k] = Num(ctx.number(f"constants.{k}", v))

    # tables
    base = Path(
        data_dir
        or os.environ.get("THERMAL_EDGE_DATA_DIR")
        or ((path.parent if path else Path.cwd()) / str(raw.get("data_dir", ".")))
    )
    for k, spec in _mapping(ctx, raw.get("tables"), "tables").items():
        key = f"tables.{k}"
        _only(ctx, spec, key, ("file", "kind", "lookup", "doc"))
        for choice, allowed in (("kind", ("curve", "grid2d")), ("lookup", ("nearest", "linear"))):
            if choice in spec and spec[choice] not in allowed:
                raise ctx.fail(f"{key}.{choice}", f"must be one of {', '.join(allowed)}, got {spec[choice]!r}")
        f = base / str(_req(ctx, spec, "file", key))
        if not f.exists():
            raise ctx.fail(f"{key}.file", f"table file {f} not found (give the directory of the model's tables: "
                                          "the model file's data_dir:, --data-dir or THERMAL_EDGE_DATA_DIR)")
        try:
            ctx.tables[k] = load_table(k, f, str(spec.get("kind", "curve")), str(spec.get("lookup", "nearest")))
        except (ValueError, IndexError) as exc:
            raise ctx.fail(key, f"cannot read {f}: {exc}") from None

    raw_inputs = _mapping(ctx, raw.get("inputs"), "inputs")
    inputs = tuple(str(k) for k in raw_inputs)
    if not inputs:
        raise ctx.fail("inputs", "at least one input is required")
    input_roles: dict[str, Role] = {}
    for k, spec in raw_inputs.items():
        key = f"inputs.{k}"
        spec = _mapping(ctx, spec, key)
        _only(ctx, spec, key, ("unit", "doc", "role"))
        if "role" in spec:
            role = ctx.role(f"{key}.role", spec["role"], Role)
            if "unit" in spec and (why := unit_problem(role, str(spec["unit"]))):
                raise ctx.fail(f"{key}.unit", why)
            if role in input_roles.values():
                other = next(n for n, r in input_roles.items() if r is role)
                raise ctx.fail(f"{key}.role", f"role {role.value!r} is already the role of input {other!r}")
            input_roles[str(k)] = role
    boundaries = {str(k): str(v) for k, v in _mapping(ctx, raw.get("boundaries"), "boundaries").items()}
    for b, col in boundaries.items():
        if col not in inputs:
            raise ctx.fail(f"boundaries.{b}", f"input {col!r} is not declared under inputs")
        # a boundary is a temperature: an input with another role or unit would be read as degC
        role, unit = input_roles.get(col), str(_mapping(ctx, raw_inputs[col], f"inputs.{col}").get("unit", ""))
        if role is not None and role.plausible.unit != TEMPERATURE.unit:
            raise ctx.fail(f"boundaries.{b}", f"input {col!r} is the {role.value} ({role.plausible.unit}), not a temperature")
        if role is None and unit and not is_unit(TEMPERATURE.unit, unit):
            raise ctx.fail(f"boundaries.{b}", f"input {col!r} is in {unit!r}, not a temperature (degC)")

    derived: dict[str, Expr] = {}
    for k, v in _mapping(ctx, raw.get("derived"), "derived").items():
        derived[k] = ctx.law(f"derived.{k}", v, set(inputs) | set(derived), "a derived input")

    params: list[Parameter] = []
    for k, spec in _mapping(ctx, raw.get("parameters"), "parameters").items():
        key = f"parameters.{k}"
        _only(ctx, spec, key, ("value", "min", "max", "unit", "adaptable", "doc", "spread"))
        if k in inputs or k in derived or k in ctx.constants:
            raise ctx.fail(key, "name already used by an input, derived input or constant")
        value = ctx.number(f"{key}.value", _req(ctx, spec, "value", key))
        lo = ctx.number(f"{key}.min", _req(ctx, spec, "min", key), positive=True)
        hi = ctx.number(f"{key}.max", _req(ctx, spec, "max", key))
        if not lo <= value <= hi:
            raise ctx.fail(key, f"value {value} outside [min, max] = [{lo}, {hi}]")
        if is_unit(TEMPERATURE.unit, str(spec.get("unit", ""))):  # a temperature, degC
            for what, v in (("value", value), ("min", lo), ("max", hi)):
                if (why := TEMPERATURE.problem(v)):
                    raise ctx.fail(f"{key}.{what}", why)
        if (scaled := scaled_unit(str(spec.get("unit", "")))) is not None:
            si, factor = scaled
            raise ctx.fail(f"{key}.unit", f"{spec['unit']!r} is not SI: give the values in {si} "
                                          f"({value:g} {spec['unit']} = {value * factor:g} {si})")
        spread = ctx.number(f"{key}.spread", spec["spread"]) if "spread" in spec else DEFAULT_SPREAD
        if spread < 0:
            raise ctx.fail(f"{key}.spread", f"must be >= 0 (relative σ of the value), got {spread}")
        params.append(
            Parameter(k, value, lo, hi, str(spec.get("unit", "")), bool(spec.get("adaptable", False)), str(spec.get("doc", "")),
                      spread)
        )
    pnames = {p.name for p in params}
    op_names = set(inputs) | set(derived)

    materials: dict[str, dict[str, Expr]] = {}
    for k, spec in _mapping(ctx, raw.get("materials"), "materials").items():
        materials[k] = _material(ctx, f"materials.{k}", spec, pnames)

    builder = _Builder(ctx)
    for i, spec in enumerate(_list(ctx, raw.get("arcs"), "arcs")):
        builder.arc(f"arcs[{i}]", spec, materials, {p.name: Num(p.value) for p in params})
    for i, spec in enumerate(_list(ctx, raw.get("nodes"), "nodes")):
        key = f"nodes[{i}]"
        _only(ctx, spec, key, ("name", "capacity", "role", "doc"))
        nname = str(_req(ctx, spec, "name", key))
        cap = ctx.law(f"{key}.capacity", _req(ctx, spec, "capacity", key), pnames, "a capacity")
        builder.add_node(key, nname, cap)
        if "role" in spec:
            builder.node_roles[nname] = ctx.role(f"{key}.role", spec["role"], NodeRole)
    for i, pname in enumerate(_list(ctx, raw.get("points"), "points")):
        builder.add_point(f"points[{i}]", str(pname))
    for b in boundaries:
        builder.declare(f"boundaries.{b}", b)

    conns = _list(ctx, raw.get("conductances"), "conductances")
    builder.connect(conns, pnames | op_names, boundaries)
    _check_positive(ctx, builder.positive, {p.name: p for p in params})
    _check_units(ctx, builder.positive, {p.name: p for p in params})
    builder.check_connected(boundaries)

    temp_names = {temperature_name(n) for n in builder.nodes}
    losses: list[Loss] = []
    for i, spec in enumerate(_list(ctx, raw.get("losses"), "losses")):
        key = f"losses[{i}]"
        _only(ctx, spec, key, ("node", "power", "doc"))
        target = str(_req(ctx, spec, "node", key))
        if target not in builder.nodes and target not in builder.points:
            raise ctx.fail(f"{key}.node", f"unknown node or point {target!r}")
        law = ctx.law(f"{key}.power", _req(ctx, spec, "power", key), pnames | op_names | temp_names, "a loss")
        losses.append(Loss(target, law, key))

    # an adaptable parameter no law reads would be "adapted" with no effect on any temperature: its
    # uncertainty is infinite, and the adapter would report changes of nothing
    used = frozenset().union(*(e.g.free() for e in builder.edges), *(c.free() for c in builder.caps),
                             *(loss.power.free() for loss in losses))
    for p in params:
        if p.adaptable and p.name not in used:
            raise ctx.fail(f"parameters.{p.name}.adaptable", "no capacity, conductance or loss reads this parameter: "
                                                             "nothing can be learned about it")

    sensors: dict[str, str] = {}
    for k, spec in _mapping(ctx, raw.get("sensors"), "sensors").items():
        _only(ctx, spec, f"sensors.{k}", ("node", "doc"))
        node = str(_req(ctx, spec, "node", f"sensors.{k}"))
        if node not in builder.nodes:
            raise ctx.fail(f"sensors.{k}.node", f"{node!r} is not a node with heat capacity")
        sensors[k] = node
    limits = []
    for k, spec in _mapping(ctx, raw.get("limits"), "limits").items():
        key = f"limits.{k}"
        _only(ctx, spec, key, ("node", "warn_c", "max_c", "doc"))
        node = str(_req(ctx, spec, "node", key))
        if node not in builder.nodes:
            raise ctx.fail(f"{key}.node", f"{node!r} is not a node with heat capacity")
        warn = ctx.number(f"{key}.warn_c", _req(ctx, spec, "warn_c", key))
        mx = ctx.number(f"{key}.max_c", _req(ctx, spec, "max_c", key))
        for what, v in (("warn_c", warn), ("max_c", mx)):
            if (why := LIMIT.problem(v)):
                raise ctx.fail(f"{key}.{what}", why)
        if not warn < mx:
            raise ctx.fail(key, f"warn_c ({warn}) must be below max_c ({mx})")
        limits.append(Limit(k, node, warn, mx))

    disc = _mapping(ctx, raw.get("discretisation"), "discretisation")
    _only(ctx, disc, "discretisation", ("method", "max_substep_s"))
    method = str(disc.get("method", "zoh"))
    if method not in ("zoh", "euler"):
        raise ctx.fail("discretisation.method", f"must be zoh or euler, got {method!r}")
    sub = disc.get("max_substep_s")
    substep = None if sub is None else ctx.number("discretisation.max_substep_s", sub, positive=True)
    # the torque constant divides a torque into a current: zero or negative gives no or negative current
    drive = {str(k): ctx.number(f"drive.{k}", v, positive=str(k) == "kt_nm_per_arms")
             for k, v in _mapping(ctx, raw.get("drive"), "drive").items()}
    if not builder.nodes:
        raise ctx.fail("nodes", "the model has no node with heat capacity")
    return Model(
        name=name,
        path=path,
        description=str(raw.get("description", "")),
        inputs=inputs,
        derived=derived,
        boundaries=boundaries,
        parameters=tuple(params),
        nodes=tuple(builder.nodes),
        capacities=tuple(builder.caps),
        points=tuple(builder.points),
        edges=tuple(builder.edges),
        losses=tuple(losses),
        sensors=sensors,
        limits=tuple(limits),
        discretisation=Discretisation(method, substep),
        drive=drive,
        input_roles=input_roles,
        node_roles=dict(builder.node_roles),
    )


def _check_positive(ctx: _Ctx, laws: list[tuple[str, str, Expr]], params: Mapping[str, Parameter]) -> None:
    """Refuse a capacity, conductance or resistance that is not positive: a constant one, or one of
    the parameters alone at their nominal values or at any one parameter's min or max (where the
    adaptation may take it). A law of the operating point is judged where it is evaluated."""
    nominal = {k: p.value for k, p in params.items()}
    for key, unit, law in laws:
        free = law.free()
        if not free <= set(params):
            continue
        f = law.compile()
        where = [("at the nominal parameters" if free else "", nominal)]
        where += [(f"at {k} = {b:g} (its {side})", {**nominal, k: b}) for k in sorted(free)
                  for side, b in (("min", params[k].lower), ("max", params[k].upper))]
        for at, env in where:
            with np.errstate(all="ignore"):
                v = float(np.asarray(f(env)))
            if not v > 0.0:  # NaN too
                raise ctx.fail(key, f"must be positive, is {v:g} {unit}" + (f" {at}" if at else ""))


#: what a law in each unit is, and the key it is given under
_UNIT_OF = {"J/K": ("a capacity", "capacity"), "W/K": ("a conductance", "g"), "K/W": ("a resistance", "r")}


def _check_units(ctx: _Ctx, laws: list[tuple[str, str, Expr]], params: Mapping[str, Parameter]) -> None:
    """Refuse a capacity, conductance or resistance given as one parameter declared in another of
    J/K, W/K and K/W (a resistance written as ``g:``, a conductance as a capacity)."""
    for key, unit, law in laws:
        if not isinstance(law, Name) or law.name not in params:
            continue
        declared = next((u for u in _UNIT_OF if is_unit(u, params[law.name].unit)), None)
        if declared is None or declared == unit:
            continue
        (was, was_key), (want, field) = _UNIT_OF[declared], _UNIT_OF[unit]
        hint = f": give it as {was_key}: {law.name}" if {declared, unit} == {"W/K", "K/W"} else ""
        raise ctx.fail(key, f"parameter {law.name} is in {declared}, {was}{hint} ({field} is {want}, in {unit})")


def _material(ctx: _Ctx, key: str, spec: Any, pnames: set[str]) -> dict[str, Expr]:
    spec = _mapping(ctx, spec, key)
    out = {}
    for m in MATERIAL_KEYS:
        out[m] = ctx.law(f"{key}.{m}", _req(ctx, spec, m, key), pnames, "a material property")
    extra = sorted(set(spec) - set(MATERIAL_KEYS) - {"doc"})
    if extra:
        raise ctx.fail(f"{key}.{extra[0]}", f"unknown material property (known: {', '.join(MATERIAL_KEYS)})")
    return out


class _Builder:
    """Expands arcs and connections into nodes, points and edges."""

    def __init__(self, ctx: _Ctx) -> None:
        self.ctx = ctx
        self.nodes: list[str] = []
        self.caps: list[Expr] = []
        self.points: list[str] = []
        self.edges: list[Edge] = []
        self.names: dict[str, str] = {}  # name -> key that declared it
        self.faces: dict[str, tuple[str, Expr]] = {}  # "arc.face" -> (mid-point, face resistance)
        self.node_roles: dict[str, NodeRole] = {}
        #: the laws the file gives that must be positive: (key, unit, law) (:func:`_check_positive`)
        self.positive: list[tuple[str, str, Expr]] = []

    def declare(self, key: str, name: str, internal: bool = False) -> None:
        """Reserve a name; user-given names may not contain ``/`` or ``.`` (kept for arc parts)."""
        if name in self.names:
            raise self.ctx.fail(key, f"name {name!r} already declared at {self.names[name]}")
        if not internal and (not name or "/" in name or "." in name):
            raise self.ctx.fail(key, f"invalid name {name!r} ('/' and '.' are reserved for arc mid- and face points)")
        self.names[name] = key

    def add_node(self, key: str, name: str, cap: Expr) -> None:
        self.declare(key, name)
        self.nodes.append(name)
        self.caps.append(cap)
        self.positive.append((f"{key}.capacity", "J/K", cap))

    def add_point(self, key: str, name: str, internal: bool = False) -> None:
        self.declare(key, name, internal)
        self.points.append(name)

    def arc(self, key: str, spec: Any, materials: dict[str, dict[str, Expr]], nominal: dict[str, Expr]) -> None:
        ctx = self.ctx
        _only(ctx, spec, key, ("name", "r1", "r2", "theta", "length", "count", "material", "role", "doc"))
        name = str(_req(ctx, spec, "name", key))
        if "role" in spec:
            self.node_roles[name] = ctx.role(f"{key}.role", spec["role"], NodeRole)
        r1 = ctx.number(f"{key}.r1", _req(ctx, spec, "r1", key), positive=True)
        r2 = ctx.number(f"{key}.r2", _req(ctx, spec, "r2", key), positive=True)
        if not r2 > r1:
            raise ctx.fail(f"{key}.r2", f"must be greater than r1 ({r1} m), got {r2} m")
        theta = ctx.number(f"{key}.theta", _req(ctx, spec, "theta", key), positive=True)
        length = ctx.number(f"{key}.length", _req(ctx, spec, "length", key), positive=True)
        count = ctx.number(f"{key}.count", spec.get("count", 1), positive=True)
        # count arcs of theta side by side around the machine: at most a full circle (theta in rad;
        # an angle in degrees is the usual cause)
        if count * theta > 2.0 * math.pi * 1.001:  # (an angle rounded in the file: 12 x 0.5236 rad)
            raise ctx.fail(f"{key}.theta", f"count x theta = {count:g} x {theta:g} rad = {count * theta:.4g} rad exceeds a "
                                           f"full circle (2π = 6.283 rad): theta is in rad ({theta:g} deg = "
                                           f"{math.radians(theta):.4g} rad)")
        mat = _req(ctx, spec, "material", key)
        if isinstance(mat, str):
            if mat not in materials:
                raise ctx.fail(f"{key}.material", f"unknown material {mat!r} (declared: {', '.join(materials)})")
            props = materials[mat]
        else:
            props = _material(ctx, f"{key}.material", mat, set(nominal))
        res = arc_resistances(r1, r2, theta, length, props["k_r"], props["k_a"], props["k_c"], count)
        self.add_node(key, name, arc_capacity(r1, r2, theta, length, props["rho"], props["c_p"], count))
        for d in DIRECTIONS:
            mid = f"{name}/{d}"
            self.add_point(key, mid, internal=True)
            r3 = res[d][2]
            self.edges.append(Edge(name, mid, Num(1.0) / r3, f"{key} ({d} interior)"))
        for face, (d, i) in FACES.items():
            self.faces[f"{name}.{face}"] = (f"{name}/{d}", res[d][i])
        # each direction's T must be passive on its own: R_face + R3 > 0 at nominal values
        for d in DIRECTIONS:
            r_1, r_2, r_3 = res[d]
            vals = [evaluate_const(x.substitute(nominal)) for x in (r_1, r_2, r_3)]
            if min(vals[0], vals[1]) + vals[2] <= 0:
                raise ctx.fail(key, f"{d} T-model is not passive (R1={vals[0]:.3g}, R2={vals[1]:.3g}, R3={vals[2]:.3g})")

    def check_connected(self, boundaries: Mapping[str, str]) -> None:
        """Every node and point reaches a boundary through conductances (else its heat has no way
        out: its temperature grows without bound and the network cannot be solved); with no
        boundary at all, every node is connected to another at least."""
        links: dict[str, set[str]] = {n: set() for n in (*self.nodes, *self.points, *boundaries)}
        for e in self.edges:
            links.setdefault(e.a, set()).add(e.b)
            links.setdefault(e.b, set()).add(e.a)
        if not boundaries:
            for n in self.nodes:
                if not links[n] and len(self.nodes) > 1:
                    raise self.ctx.fail(self.names.get(n, "nodes"), f"node {n!r} is connected to nothing")
            return
        reached, todo = set(boundaries), list(boundaries)
        while todo:
            for m in links.get(todo.pop(), ()):
                if m not in reached:
                    reached.add(m)
                    todo.append(m)
        for n in (*self.nodes, *self.points):
            if n not in reached:
                kind = "node" if n in self.nodes else "point"
                raise self.ctx.fail(self.names.get(n.split("/")[0], "conductances"),
                                    f"{kind} {n!r} is not connected to any boundary ({', '.join(boundaries)}) through "
                                    "conductances: its heat has no way out")

    def endpoint(self, key: str, ref: str, boundaries: Mapping[str, str]) -> str:
        if ref in self.faces or ref in self.nodes or ref in self.points or ref in boundaries:
            return ref
        raise self.ctx.fail(key, f"unknown node, point, arc face or boundary {ref!r}")

    def connect(self, conns: list[Any], allowed: set[str], boundaries: Mapping[str, str]) -> None:
        ctx = self.ctx
        parsed = []
        for i, spec in enumerate(conns):
            key = f"conductances[{i}]"
            _only(ctx, spec, key, ("between", "g", "r", "doc"))
            between = _req(ctx, spec, "between", key)
            if not isinstance(between, list) or len(between) != 2:
                raise ctx.fail(f"{key}.between", "expected a list of two endpoints")
            a, b = (self.endpoint(f"{key}.between", str(x), boundaries) for x in between)
            if a == b:
                raise ctx.fail(f"{key}.between", f"both ends are {a!r}")
            if a in boundaries and b in boundaries:
                raise ctx.fail(f"{key}.between", "a conductance between two boundaries does nothing")
            if a in boundaries:
                a, b = b, a
            has_g, has_r = "g" in spec, "r" in spec
            if has_g and has_r:
                raise ctx.fail(key, "give either g (W/K) or r (K/W), not both")
            law = None
            if has_g:
                law = ("g", ctx.law(f"{key}.g", spec["g"], allowed, "a conductance"))
            elif has_r:
                law = ("r", ctx.law(f"{key}.r", spec["r"], allowed, "a resistance"))
            if law is not None:
                self.positive.append((f"{key}.{law[0]}", "W/K" if law[0] == "g" else "K/W", law[1]))
                _check_positive(ctx, [self.positive[-1]], {})  # a constant one now, before 1/r divides by it
            parsed.append((key, a, b, law))
        uses = Counter(e for _, a, b, _ in parsed for e in (a, b) if e in self.faces)
        # a face with several connections becomes a point of its own
        for face, n in uses.items():
            if n > 1:
                mid, rf = self.faces[face]
                fp = face.replace(".", "/", 1)
                self.add_point(f"face {face}", fp, internal=True)
                self.edges.append(Edge(mid, fp, Num(1.0) / rf, f"face {face}"))
                self.faces[face] = (fp, Num(0.0))
        for key, a, b, law in parsed:
            series: Expr = Num(0.0)
            ends = []
            for e in (a, b):
                if e in self.faces:
                    pt, rf = self.faces[e]
                    series = series + rf
                    ends.append(pt)
                else:
                    ends.append(e)
            if law is None:
                if series == Num(0.0):
                    raise ctx.fail(key, "needs g or r (no arc face resistance to stand for it)")
                g = Num(1.0) / series
            elif law[0] == "r":
                g = Num(1.0) / (series + law[1])
            elif series == Num(0.0):
                g = law[1]
            else:
                g = Num(1.0) / (series + Num(1.0) / law[1])
            self.edges.append(Edge(ends[0], ends[1], g, key))


__all__ = ["load_model", "build_model", "read_yaml", "ModelError"]
