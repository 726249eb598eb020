"""Generated chain models of any size: a PM machine discretised axially into slices.

A model of ``N`` nodes for benchmarks and tests of how the numerics grow with the model size
(:func:`chain_model`). Each axial slice of the stack holds eight lumped nodes along the radial
heat path (housing, stator yoke, tooth, slot winding, air gap, magnet, rotor iron, shaft), joined
radially within the slice and axially to the next slice; the end windings are chains of nodes
along the conductors at both ends, beside an end-space air node and an end cap. The whole
machine is modelled (no symmetry cell), with the parameter vocabulary of the shipped models:
the fourteen adaptable parameters are the winding conductivities, specific heats and
insulations, the housing and end-cap resistances to ambient, the housing specific heat and
contact, and the standstill convection of the air gap and end spaces. Copper losses (affine in
the winding temperatures) sit at every winding node; iron, magnet and friction losses follow
speed and current as in the shipped 10 kW model.

The geometry and materials are those of a 10 kW, 900 rpm surface-PM machine (stack 92 mm,
bore 183 mm, outer diameter 290 mm); a slice is ``1/S`` of the stack, so the model's steady
state hardly depends on ``N`` while its fastest time constants shrink with the slices.
The model is built as a document and validated by :func:`~thermal_edge.lptn.loader.build_model`,
like a model file.
"""
from __future__ import annotations

from typing import Any

from .loader import build_model
from .model import Model, ModelError
from .vocabulary import DEFAULT_COLUMNS, Role

# the inputs' columns, by role (the vocabulary's names)
_SPEED, _CURRENT, _TORQUE, _AMBIENT = (DEFAULT_COLUMNS[r] for r in (Role.SPEED, Role.CURRENT, Role.TORQUE, Role.AMBIENT))

#: nodes of one axial slice, along the radial heat path, with their roles
SLICE = (("housing", "housing"), ("yoke", "yoke"), ("tooth", "tooth"), ("winding", "winding"),
         ("gap", "air"), ("magnet", "magnet"), ("rotor", "rotor_iron"), ("shaft", "shaft"))
#: nodes outside the slices besides the end windings: an end space and an end cap at each end
END_NODES = 4
#: the smallest model: one slice, the end nodes and one end-winding node per end
MIN_NODES = len(SLICE) + END_NODES + 2

_CONSTANTS = {
    "pi": 3.141592653589793,
    "L_stk": 0.092,            # stack length, m
    "r_hous_o": 0.145, "r_core_o": 0.135, "r_slot_b": 0.120, "r_bore": 0.0915,
    "r_mag_o": 0.0905, "r_rot_o": 0.0865, "r_shaft": 0.030,
    "A_cu": 8.2e-3,            # slot cross-section of all 36 slots (copper, enamel, resin), m^2
    "p_liner": 2.05,           # slot liner perimeter of all slots, m (per m of stack)
    "d_sw": 0.006,             # mean conduction path inside a slot, m
    "l_ew": 0.045,             # end-turn length per end, m
    "A_ew": 0.06,              # end-winding surface per end, m^2
    "A_ew_plate": 0.02,        # end-winding contact with the core end per end, m^2
    "A_es": 0.05,              # end-space wall areas (end cap, housing bore, rotor end), m^2
    "A_sh": 0.02,              # drive-end shaft extension surface, m^2
    "R20_phase": 0.258, "alpha_cu": 0.00393, "f_sw": 0.505, "i_rated": 19.0, "f_el_rated": 90,
    "x_hyst": 0.6, "a_pm0": 0.4,
}

_PARAMETERS: dict[str, dict[str, Any]] = {
    "k_r_sw": {"value": 1.0, "min": 0.3, "max": 8.0, "unit": "W/(m K)", "adaptable": True,
               "doc": "slot winding equivalent radial conductivity"},
    "k_a_sw": {"value": 160, "min": 60, "max": 300, "unit": "W/(m K)", "adaptable": True,
               "doc": "slot winding conductivity along the conductors"},
    "c_p_sw": {"value": 530, "min": 200, "max": 900, "unit": "J/(kg K)", "adaptable": True,
               "doc": "slot winding specific heat (density 4170 kg/m3)"},
    "k_r_ew": {"value": 0.7, "min": 0.2, "max": 5.0, "unit": "W/(m K)", "adaptable": True,
               "doc": "end winding equivalent conductivity across the conductors"},
    "k_a_ew": {"value": 160, "min": 60, "max": 300, "unit": "W/(m K)", "adaptable": True,
               "doc": "end winding conductivity along the conductors"},
    "c_p_ew": {"value": 505, "min": 200, "max": 900, "unit": "J/(kg K)", "adaptable": True,
               "doc": "end winding specific heat (density 4050 kg/m3)"},
    "r_ins_sw": {"value": 1.0e-2, "min": 1.5e-3, "max": 4.0e-2, "unit": "m^2 K/W", "adaptable": True,
                 "doc": "slot liner and air films, winding to stator"},
    "r_ins_ew": {"value": 1.0e-2, "min": 1.5e-3, "max": 4.0e-2, "unit": "m^2 K/W", "adaptable": True,
                 "doc": "end winding to core end insulation"},
    "R_e_hous": {"value": 0.13, "min": 0.04, "max": 0.4, "unit": "K/W", "adaptable": True,
                 "doc": "whole frame to ambient (natural convection and radiation)"},
    "R_e_cap": {"value": 1.25, "min": 0.3, "max": 5.0, "unit": "K/W", "adaptable": True,
                "doc": "one end cap to ambient"},
    "c_p_hous": {"value": 900, "min": 600, "max": 1400, "unit": "J/(kg K)", "adaptable": True,
                 "doc": "housing specific heat"},
    "r_c_hous": {"value": 8.0e-4, "min": 1.0e-4, "max": 4.0e-3, "unit": "m^2 K/W", "adaptable": True,
                 "doc": "stator core to housing bore contact"},
    "h_gap0": {"value": 53, "min": 20, "max": 120, "unit": "W/(m^2 K)", "adaptable": True,
               "doc": "air gap wall to gap air at standstill"},
    "h_es0": {"value": 6, "min": 2, "max": 30, "unit": "W/(m^2 K)", "adaptable": True,
              "doc": "end space to its walls at standstill"},
    "h_gap1": {"value": 12, "min": 1, "max": 60, "unit": "W/(m^2 K)", "doc": "air gap rise at 900 rpm"},
    "h_es1": {"value": 14, "min": 1, "max": 60, "unit": "W/(m^2 K)", "doc": "end space rise at 900 rpm"},
    "h_ew0": {"value": 8, "min": 2, "max": 30, "unit": "W/(m^2 K)", "doc": "end winding to end space at standstill"},
    "h_ew1": {"value": 30, "min": 2, "max": 100, "unit": "W/(m^2 K)", "doc": "its rise at 900 rpm"},
    "h_sh0": {"value": 8, "min": 2, "max": 30, "unit": "W/(m^2 K)", "doc": "shaft extension to ambient at standstill"},
    "h_sh1": {"value": 14, "min": 1, "max": 60, "unit": "W/(m^2 K)", "doc": "its rise at 900 rpm"},
    "r_glue": {"value": 4.0e-4, "min": 5.0e-5, "max": 3.0e-3, "unit": "m^2 K/W", "doc": "magnet glue joint"},
    "r_bearing": {"value": 0.8, "min": 0.1, "max": 5.0, "unit": "K/W", "doc": "one bearing, shaft to end cap"},
    "P_fe_y_ref": {"value": 55, "min": 10, "max": 200, "unit": "W", "doc": "yoke iron loss at 90 Hz"},
    "P_fe_t_ref": {"value": 95, "min": 20, "max": 300, "unit": "W", "doc": "tooth iron loss at 90 Hz"},
    "P_pm_ref": {"value": 12, "min": 1, "max": 100, "unit": "W", "doc": "magnet eddy loss at 90 Hz, rated current"},
    "T_fric": {"value": 0.12, "min": 0.02, "max": 0.6, "unit": "N m", "doc": "bearing friction torque"},
}

#: per slice of length ``l`` (m): capacity laws (J/K) of the slice's nodes
_SLICE_CAPACITY = {
    "housing": "4320 * c_p_hous * pi * (r_hous_o ** 2 - r_core_o ** 2) * {l}",
    "yoke": "7420 * 460 * pi * (r_core_o ** 2 - r_slot_b ** 2) * {l}",
    "tooth": "7420 * 460 * 0.5 * pi * (r_slot_b ** 2 - r_bore ** 2) * {l}",
    "winding": "4170 * c_p_sw * A_cu * {l}",
    "gap": "1.2 * 1005 * 2 * pi * r_bore * 0.001 * {l} + 0.05 * {l}",
    "magnet": "7500 * 440 * 0.8 * 2 * pi * 0.0885 * 0.004 * {l}",
    "rotor": "7420 * 460 * pi * (r_rot_o ** 2 - r_shaft ** 2) * {l}",
    "shaft": "7800 * 460 * pi * r_shaft ** 2 * {l}",
}

_CONV_GAP = "(h_gap0 + h_gap1 * n_rel ** 0.8)"
_CONV_ES = "(h_es0 + h_es1 * n_rel ** 0.8)"
_CONV_EW = "(h_ew0 + h_ew1 * n_rel ** 0.8)"


def chain_sizes(nodes: int) -> tuple[int, int, int]:
    """Axial slices and end-winding nodes at the front and back of a chain model of ``nodes``.

    >>> chain_sizes(40), chain_sizes(320)
    ((4, 2, 2), (39, 2, 2))
    """
    if nodes < MIN_NODES:
        raise ModelError(f"a chain model needs at least {MIN_NODES} nodes, got {nodes}")
    slices = (nodes - END_NODES - 2) // len(SLICE)
    ew = nodes - END_NODES - len(SLICE) * slices
    return slices, ew // 2, ew - ew // 2


def chain_document(nodes: int) -> dict[str, Any]:
    """The model document (what a model file holds, as parsed YAML) of :func:`chain_model`."""
    S, e_front, e_back = chain_sizes(nodes)
    l = f"(L_stk / {S})"
    doc: dict[str, Any] = {
        "name": f"chain{nodes}",
        "description": f"Generated chain model: {S} axial slices of 8 nodes, {e_front} + {e_back} end-winding "
                       f"nodes, end spaces and end caps ({nodes} nodes).",
        "discretisation": {"method": "zoh"},
        "inputs": {
            _SPEED: {"role": Role.SPEED.value, "unit": "rpm"},
            _CURRENT: {"role": Role.CURRENT.value, "unit": "A"},
            _TORQUE: {"role": Role.TORQUE.value, "unit": "Nm"},
            _AMBIENT: {"role": Role.AMBIENT.value, "unit": "degC"},
        },
        "boundaries": {"ambient": _AMBIENT},
        "constants": dict(_CONSTANTS),
        "derived": {
            "n_rel": f"abs({_SPEED}) / 900",
            "f_rel": f"abs({_SPEED}) / 60 * 6 / f_el_rated",
            "i_rel": f"{_CURRENT} / i_rated",
            "P_cu20": f"3 * R20_phase * {_CURRENT} ** 2",
            "fe_pu": "(x_hyst * f_rel + (1 - x_hyst) * f_rel ** 2) * (1 + 0.2 * i_rel ** 2) / 1.2",
            "pm_pu": "f_rel ** 2 * (a_pm0 + (1 - a_pm0) * i_rel ** 2)",
            "omega_m": f"abs({_SPEED}) * 2 * pi / 60",
        },
        "parameters": {k: dict(v) for k, v in _PARAMETERS.items()},
        "nodes": [],
        "conductances": [],
        "losses": [],
        "drive": {"kt_nm_per_arms": 5.6},
    }
    nodes_, conds, losses = doc["nodes"], doc["conductances"], doc["losses"]

    def node(name: str, role: str, capacity: str) -> None:
        nodes_.append({"name": name, "role": role, "capacity": capacity})

    def g(a: str, b: str, law: str, kind: str = "g") -> None:
        conds.append({"between": [a, b], kind: law})

    for i in range(1, S + 1):
        for part, role in SLICE:
            node(f"{part}_{i}", role, _SLICE_CAPACITY[part].format(l=l))
        # radial path within the slice
        g(f"housing_{i}", "ambient", f"R_e_hous * {S}", "r")
        g(f"housing_{i}", f"yoke_{i}", f"r_c_hous / (2 * pi * r_core_o * {l}) + 0.0075 / (28 * 2 * pi * 0.128 * {l})", "r")
        g(f"yoke_{i}", f"tooth_{i}", f"0.02 / (28 * pi * r_slot_b * {l})", "r")
        g(f"winding_{i}", f"tooth_{i}", f"r_ins_sw / (0.7 * p_liner * {l}) + d_sw / (k_r_sw * 0.7 * p_liner * {l})", "r")
        g(f"winding_{i}", f"yoke_{i}", f"r_ins_sw / (0.3 * p_liner * {l}) + d_sw / (k_r_sw * 0.3 * p_liner * {l})", "r")
        g(f"tooth_{i}", f"gap_{i}", f"{_CONV_GAP} * 2 * pi * r_bore * {l}")
        g(f"gap_{i}", f"magnet_{i}", f"{_CONV_GAP} * 2 * pi * r_mag_o * {l}")
        g(f"magnet_{i}", f"rotor_{i}", f"r_glue / (0.8 * 2 * pi * r_rot_o * {l})", "r")
        g(f"rotor_{i}", f"shaft_{i}", f"0.17 / (2 * pi * 28 * {l}) + 3.0e-4 / (2 * pi * r_shaft * {l})", "r")
        losses.append({"node": f"winding_{i}", "power": f"P_cu20 * f_sw / {S} * (1 + alpha_cu * (T.winding_{i} - 20))"})
        losses.append({"node": f"yoke_{i}", "power": f"P_fe_y_ref * fe_pu / {S}"})
        losses.append({"node": f"tooth_{i}", "power": f"P_fe_t_ref * fe_pu / {S}"})
        losses.append({"node": f"magnet_{i}", "power": f"P_pm_ref * pm_pu / {S}"})
        if i < S:  # axial path to the next slice
            j = i + 1
            g(f"housing_{i}", f"housing_{j}", f"140 * pi * (r_hous_o ** 2 - r_core_o ** 2) / {l}")
            g(f"yoke_{i}", f"yoke_{j}", f"1.5 * pi * (r_core_o ** 2 - r_slot_b ** 2) / {l}")
            g(f"tooth_{i}", f"tooth_{j}", f"1.5 * 0.5 * pi * (r_slot_b ** 2 - r_bore ** 2) / {l}")
            g(f"winding_{i}", f"winding_{j}", f"k_a_sw * A_cu / {l}")
            g(f"gap_{i}", f"gap_{j}", f"(0.02 + 0.1 * n_rel) * 0.092 / {l}")
            g(f"magnet_{i}", f"magnet_{j}", f"9 * 0.8 * 2 * pi * 0.0885 * 0.004 / {l}")
            g(f"rotor_{i}", f"rotor_{j}", f"1.5 * pi * (r_rot_o ** 2 - r_shaft ** 2) / {l}")
            g(f"shaft_{i}", f"shaft_{j}", f"45 * pi * r_shaft ** 2 / {l}")

    for end, first, count in (("front", 1, e_front), ("back", S, e_back)):
        k = 1 if end == "front" else 2
        es, cap = f"end_space_{k}", f"end_cap_{k}"
        node(es, "air", "2.3")
        node(cap, "end_cap", "1.2 * 900")
        g(es, cap, f"{_CONV_ES} * A_es")
        g(es, f"housing_{first}", f"{_CONV_ES} * A_es")
        g(es, f"rotor_{first}", f"{_CONV_ES} * A_es")
        g(es, f"gap_{first}", "0.02 + 0.1 * n_rel ** 0.8")
        g(cap, "ambient", "R_e_cap", "r")
        g(cap, f"housing_{first}", "0.05", "r")
        g(cap, f"shaft_{first}", "r_bearing", "r")
        losses.append({"node": f"shaft_{first}", "power": "T_fric * omega_m / 2"})
        seg = f"(l_ew / {count})"
        prev = f"winding_{first}"
        for m in range(1, count + 1):
            ew = f"end_winding_{k}_{m}"
            node(ew, "winding", f"4050 * c_p_ew * A_cu * {seg}")
            g(prev, ew, f"k_a_ew * A_cu / {seg}")
            g(ew, es, f"1 / ({_CONV_EW} * A_ew / {count}) + 0.004 / (k_r_ew * A_ew / {count})", "r")
            g(ew, f"yoke_{first}", f"r_ins_ew / (A_ew_plate / {count})", "r")
            losses.append({"node": ew, "power": f"P_cu20 * (1 - f_sw) / 2 / {count} * (1 + alpha_cu * (T.{ew} - 20))"})
            prev = ew
    g("shaft_1", "ambient", "(h_sh0 + h_sh1 * n_rel ** 0.8) * A_sh")
    mid = S // 2 + 1
    doc["sensors"] = {
        "slot_winding": {"node": f"winding_{mid}"},
        "end_winding": {"node": f"end_winding_1_{e_front}"},
        "housing": {"node": f"housing_{mid}"},
    }
    doc["limits"] = {
        "hot_spot": {"node": f"end_winding_2_{e_back}", "warn_c": 140, "max_c": 155},
        "magnet": {"node": f"magnet_{mid}", "warn_c": 100, "max_c": 120},
    }
    if S == 1:  # one slice has no axial path in the slot: nothing reads the slot's axial conductivity
        doc["parameters"]["k_a_sw"]["adaptable"] = False
    return doc


def chain_model(nodes: int) -> Model:
    """A generated chain model of exactly ``nodes`` nodes (at least :data:`MIN_NODES`).

    Parameters
    ----------
    nodes : int
        Number of dynamic nodes (with heat capacity).

    Returns
    -------
    Model
        Validated as a model file is; named ``chain<nodes>``, three sensors (slot winding,
        end winding, housing), two limits, fourteen adaptable parameters (thirteen with one slice,
        whose slot has no axial path).

    Raises
    ------
    ModelError
        Fewer nodes than :data:`MIN_NODES`.
    """
    return build_model(chain_document(nodes), fname=f"chain{nodes}")
