"""Cylindrical arc elements: the T-model resistances of the paper's Table 2 and their capacity.

An arc element spans radii ``r1 < r2`` (m), angle ``theta`` (rad) and axial length ``L`` (m).
Heat flows independently in the radial, circumferential and axial directions. In each direction
the element is a T: two face resistances ``R1`` (outer/forward face) and ``R2`` (inner/backward
face) meet at a mid-point, which is joined to the element's mean-temperature node by the interior
resistance ``R3``. ``R3`` is negative: it corrects the mid-point temperature to the element's
mean temperature when heat is generated inside the element (Mellor, Roberts & Turner 1991).

Radial (conductivity ``k_r``; the outer face sees more of the element's area, so its resistance
is the smaller one)::

    R1 (outer) = 1/(2 θ L k_r) · (1 − 2 r1² ln(r2/r1) / (r2² − r1²))
    R2 (inner) = 1/(2 θ L k_r) · (2 r2² ln(r2/r1) / (r2² − r1²) − 1)
    R3 = −1/(4 θ L k_r (r2² − r1²)) · (r1² + r2² − 4 r1² r2² ln(r2/r1) / (r2² − r1²))

Axial (``k_a``; the area is θ/2 (r2² − r1²))::

    R1 = R2 = L / (k_a θ (r2² − r1²)),   R3 = −L / (3 k_a θ (r2² − r1²))

Circumferential (``k_c``; conductance L k_c ln(r2/r1) per radian)::

    R1 = R2 = θ / (2 L k_c ln(r2/r1)),
    R3 = θ / (12 L k_c) · ((r2² + r1²)/(r2² − r1²) − 3 / ln(r2/r1))

(the paper's Table 2; exact for the area-mean temperature with uniform generation).

Capacity: ``c = c_p ρ θ/2 L (r2² − r1²)`` (J/K). ``count`` identical elements in parallel divide
every resistance and multiply the capacity.

>>> from thermal_edge.lptn.expr import Num, evaluate_const
>>> r = arc_resistances(0.1, 0.2, 0.5, 0.1, Num(1.0), Num(1.0), Num(1.0))
>>> round(evaluate_const(r["axial"][0]), 4), round(evaluate_const(r["axial"][2]), 4)
(6.6667, -2.2222)
"""
from __future__ import annotations

import math

from .expr import Expr, Num

DIRECTIONS = ("radial", "circ", "axial")
#: face name -> (direction, index of its resistance in (R1, R2))
FACES = {
    "r_out": ("radial", 0),
    "r_in": ("radial", 1),
    "c_pos": ("circ", 0),
    "c_neg": ("circ", 1),
    "a_front": ("axial", 0),
    "a_back": ("axial", 1),
}


def arc_resistances(
    r1: float, r2: float, theta: float, length: float, k_r: Expr, k_a: Expr, k_c: Expr, count: float = 1.0
) -> dict[str, tuple[Expr, Expr, Expr]]:
    """T-model resistances (K/W) of an arc element per direction.

    Parameters
    ----------
    r1, r2 : float
        Inner and outer radius, m (``0 <= r1 < r2``; ``r1 = 0`` only without a radial T).
    theta : float
        Angle of one element, rad.
    length : float
        Axial length, m.
    k_r, k_a, k_c : Expr
        Radial, axial and circumferential thermal conductivity laws, W/(m·K).
    count : float
        Number of identical elements in parallel.

    Returns
    -------
    dict
        ``{"radial"|"circ"|"axial": (R1, R2, R3)}``, each a law in the conductivities.
    """
    d2 = r2 * r2 - r1 * r1
    ln = math.log(r2 / r1)
    n = float(count)
    rad = 1.0 / (2.0 * theta * length * n)
    rad1 = rad * (1.0 - 2.0 * r1 * r1 * ln / d2)  # outer face
    rad2 = rad * (2.0 * r2 * r2 * ln / d2 - 1.0)  # inner face
    rad3 = -(r1 * r1 + r2 * r2 - 4.0 * r1 * r1 * r2 * r2 * ln / d2) / (4.0 * theta * length * d2 * n)
    ax = length / (theta * d2 * n)
    ci = theta / (2.0 * length * ln * n)
    return {
        "radial": (Num(rad1) / k_r, Num(rad2) / k_r, Num(rad3) / k_r),
        "circ": (Num(ci) / k_c, Num(ci) / k_c, Num(theta / (12.0 * length * n) * ((r2 * r2 + r1 * r1) / d2 - 3.0 / ln)) / k_c),
        "axial": (Num(ax) / k_a, Num(ax) / k_a, Num(-ax / 3.0) / k_a),
    }


def arc_capacity(r1: float, r2: float, theta: float, length: float, rho: Expr, c_p: Expr, count: float = 1.0) -> Expr:
    """Heat capacity ``count · c_p ρ θ/2 L (r2² − r1²)`` in J/K of an arc element."""
    volume = count * theta / 2.0 * length * (r2 * r2 - r1 * r1)
    return Num(volume) * rho * c_p
