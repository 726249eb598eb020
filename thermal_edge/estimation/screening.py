"""Screening: which parameters can reduce the objective most within their bounds (paper eqs. 38–41).

In log-parameters ``φ``: the contribution of parameter ``k`` to a first-order change of the
objective is ``Λ_k = ∂Obj/∂φ_k`` per unit change; its optimisation potential within
``[log L_k, log U_k]`` is ``o_k = max(Λ_k (φ_k − log L_k), −Λ_k (log U_k − φ_k), 0) / Z``
(``Z`` scales all potentials alike and cancels in the selection). The parameters with the largest
potentials are kept until they cover ``coverage`` (98 %) of the total; the screening is repeated
before every optimisation.

Identifiability comes first: a parameter the sensors cannot pin
down (its relative standard deviation from the Fisher information of the window, all adaptable
parameters free, above a limit: :mod:`.uncertainty`) is not offered to the optimiser however
large its gradient looks.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Screening:
    """Outcome of a screening: potentials and the chosen parameters, in ``names`` order."""

    names: tuple[str, ...]
    gradient: np.ndarray
    potential: np.ndarray
    information: np.ndarray
    selected: tuple[str, ...]

    def as_dict(self) -> dict[str, object]:
        return {
            "potential": dict(zip(self.names, map(float, self.potential))),
            "information": dict(zip(self.names, map(float, self.information))),
            "selected": list(self.selected),
        }


def potentials(grad: np.ndarray, phi: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Optimisation potential of each log-parameter within its (log) bounds."""
    return np.maximum.reduce([grad * (phi - np.log(lower)), -grad * (np.log(upper) - phi), np.zeros_like(grad)])


def select(names: tuple[str, ...], potential: np.ndarray, coverage: float = 0.98) -> tuple[str, ...]:
    """Largest potentials until their cumulative share reaches ``coverage`` (at least one)."""
    total = float(potential.sum())
    if total <= 0:
        return ()
    order = np.argsort(-potential)
    cum = np.cumsum(potential[order]) / total
    k = int(np.searchsorted(cum, coverage) + 1)
    return tuple(names[i] for i in order[:k] if potential[i] > 0)


def screen(
    names: tuple[str, ...], grad: np.ndarray, hess: np.ndarray, phi: np.ndarray, lower: np.ndarray, upper: np.ndarray,
    coverage: float = 0.98, identifiable: np.ndarray | None = None,
) -> Screening:
    """Screen parameters from the gradient at ``phi``; only ``identifiable`` ones (default all) may
    be chosen. ``hess`` (Gauss-Newton) is kept for the record: its diagonal is each parameter's
    Fisher information."""
    info = np.clip(np.diag(hess), 0.0, None)
    pot = potentials(grad, phi, lower, upper)
    seen = np.ones(len(names), dtype=bool) if identifiable is None else np.asarray(identifiable, dtype=bool)
    chosen = select(tuple(n for n, s in zip(names, seen) if s), pot[seen], coverage)
    return Screening(names, grad, pot, info, chosen)
