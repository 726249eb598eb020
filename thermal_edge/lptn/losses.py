"""The loss laws of a model, compiled once: their values and their derivatives.

Every part that needs the losses ``P(θ, u, T)`` (W) or their derivatives asks a
:class:`LossLaws`: the 1 Hz stepper, the steady state, the simulator (whole runs at once and the
laws that are not affine in temperature step by step), the observer and the EKF (the loss
feedback ``∂P/∂T`` and ``∂P/∂θ`` of their Jacobians).

An *environment* is the mapping of names to values a law reads: parameters, inputs and derived
inputs (:meth:`thermal_edge.lptn.network.Network.env`); the node temperatures are added here
from ``T``, scalars for one state (n,) or series for a batch (B, n).
"""
from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np

from .expr import Value, compile_many, is_affine
from .model import Model
from .network import _Law
from .vocabulary import temperature_name


class LossLaws:
    """The loss laws of ``model`` with their derivatives by node temperature and by parameter.

    Attributes
    ----------
    nodes : ndarray of int
        The nodes whose temperatures the laws read (in state order): the columns of :meth:`dT`.
    affine : list of bool
        Per law: affine in those temperatures (by structure, :func:`~thermal_edge.lptn.expr.is_affine`).
    nonaffine : list of int
        Indices of the laws that are not.
    """

    def __init__(self, model: Model) -> None:
        tnames = [temperature_name(x) for x in model.nodes]
        read = {t for loss in model.losses for t in loss.power.free()}
        used = [i for i, t in enumerate(tnames) if t in read]
        self.nodes = np.array(used, dtype=int)
        self._tnames = [tnames[i] for i in used]
        self.laws = [_Law(loss.power, model.parameter_names) for loss in model.losses]
        self._keys = [loss.key for loss in model.losses]
        self.affine = [is_affine(loss.power, frozenset(self._tnames)) for loss in model.losses]
        self.nonaffine = [j for j, a in enumerate(self.affine) if not a]
        # the laws, and each ∂P_j/∂T at a node it reads (law, column of dT), as one generated
        # function each: one call per evaluation
        self._power_all = compile_many([law.expr for law in self.laws])
        self._dT_at = [(j, i) for j, law in enumerate(self.laws) for i, t in enumerate(self._tnames)
                       if t in law.expr.free()]
        self._dT_all = compile_many([self.laws[j].expr.diff(self._tnames[i]) for j, i in self._dT_at])
        self._params = list(model.parameter_names)
        self._dtheta_all: dict[tuple[int, ...], tuple[list[tuple[int, int]], Callable[..., list[Value]]]] = {}

    def __len__(self) -> int:
        return len(self.laws)

    @property
    def reads(self) -> list[list[int]]:
        """Per law, the columns of :meth:`dT` (indices into :attr:`nodes`) it reads."""
        out: list[list[int]] = [[] for _ in self.laws]
        for j, i in self._dT_at:
            out[j].append(i)
        return out

    @property
    def temperature_dependent(self) -> bool:
        """Whether any law reads a node temperature."""
        return bool(len(self.nodes))

    def at(self, env: Mapping[str, Value], T: np.ndarray | None) -> dict[str, Value]:
        """``env`` with the node temperatures of ``T`` (n,) or (B, n), °C; None: all zero (the
        constant part of an affine law)."""
        e = dict(env)
        for i, t in zip(self.nodes, self._tnames):
            e[t] = 0.0 if T is None else T[..., i]
        return e

    def power(self, env: Mapping[str, Value], T: np.ndarray | None, batch: int | None = None) -> np.ndarray:
        """Losses (W) of every law: (n_loss,) for one state, (B, n_loss) for ``batch=B`` samples.

        Parameters
        ----------
        env : mapping
            Parameters and inputs (scalars, or series of length B).
        T : ndarray or None
            Node temperatures (n,) or (B, n), °C (see :meth:`at`).
        batch : int, optional
            Number of samples; default: one state (the values are floats).
        """
        values = self._power_all(self.at(env, T))
        if batch is None:
            return np.array([float(v) for v in values])
        P = np.empty((batch, len(self.laws)))
        for j, v in enumerate(values):
            P[:, j] = v
        return P

    def not_finite(self, P: np.ndarray) -> str | None:
        """``losses[j].power is -inf`` for the first law whose value in ``P`` (n_loss,) (from
        :meth:`power`) is not finite (a logarithm or a division by 0 at these inputs); None if all are."""
        bad = np.nonzero(~np.isfinite(P))[0]
        return None if not len(bad) else f"{self._keys[int(bad[0])]}.power is {float(P[int(bad[0])]):g}"

    def dT(self, env: Mapping[str, Value], T: np.ndarray | None, batch: int | None = None) -> np.ndarray:
        """``∂P/∂T`` (W/K) at the nodes the laws read (columns :attr:`nodes`): (n_loss, len(nodes)),
        or (B, n_loss, len(nodes)) for ``batch=B`` samples (arguments as :meth:`power`)."""
        out = np.zeros((len(self.laws), len(self.nodes)) if batch is None else (batch, len(self.laws), len(self.nodes)))
        if self._dT_at:
            for (j, i), v in zip(self._dT_at, self._dT_all(self.at(env, T))):
                out[..., j, i] = v
        return out

    def slope_entries(self, env: Mapping[str, Value], T: np.ndarray | None,
                      batch: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The entries of :meth:`dT` that a law can make nonzero, for ``batch`` samples: the law
        and the column of each, and their values (batch, entries) in W/K. A model with a loss at
        each of hundreds of nodes has a dense ``dT`` of mostly zeros (and of gigabytes over a run)."""
        out = np.empty((batch, len(self._dT_at)))
        if self._dT_at:
            for k, v in enumerate(self._dT_all(self.at(env, T))):
                out[:, k] = v
        return (np.array([j for j, _ in self._dT_at], dtype=int), np.array([i for _, i in self._dT_at], dtype=int), out)

    def dtheta(self, env: Mapping[str, Value], T: np.ndarray | None, wrt: Sequence[int] | np.ndarray,
               batch: int | None = None) -> np.ndarray:
        """``∂P/∂θ`` (W per parameter unit) for the parameter indices ``wrt``: (n_loss, p), or
        (B, n_loss, p) for ``batch=B`` samples (arguments as :meth:`power`)."""
        out = np.zeros((len(self.laws), len(wrt)) if batch is None else (batch, len(self.laws), len(wrt)))
        at, f = self._dtheta_laws(wrt)
        if at:
            for (j, q), v in zip(at, f(self.at(env, T))):
                out[..., j, q] = v
        return out

    def _dtheta_laws(self, wrt: Sequence[int] | np.ndarray) -> tuple[list[tuple[int, int]], Callable[..., list[Value]]]:
        """The nonzero entries of :meth:`dtheta` for ``wrt`` (law, column) and one function giving them."""
        key = tuple(int(pi) for pi in wrt)
        hit = self._dtheta_all.get(key)
        if hit is None:
            at = [(j, q) for j, law in enumerate(self.laws) for q, pi in enumerate(key) if pi in law.d]
            f = compile_many([self.laws[j].expr.diff(self._params[key[q]]) for j, q in at])
            hit = self._dtheta_all[key] = (at, f)
        return hit

    def depends_on(self, wrt: Sequence[int] | np.ndarray) -> bool:
        """Whether some law depends on one of the parameter indices ``wrt`` (else :meth:`dtheta` is zero)."""
        return any(int(pi) in law.d for law in self.laws for pi in wrt)

    def stepwise(self, env: Mapping[str, Value], N: int, which: Sequence[int]) -> Callable[[int, np.ndarray], np.ndarray]:
        """An evaluator ``at(k, T)`` of the laws ``which`` at sample ``k`` of a run of ``N`` samples
        and temperatures ``T`` (n,): for a simulation that evaluates them step by step.

        Only the names these laws read enter its environment (a step costs a dict of a few
        entries, not of every input and parameter).
        """
        needed: set[str] = set()
        for j in which:
            needed |= self.laws[j].expr.free()
        scal = {k: v for k, v in env.items() if k in needed and np.ndim(v) == 0}
        series = [(k, np.broadcast_to(np.asarray(v, dtype=float), (N,))) for k, v in env.items()
                  if k in needed and np.ndim(v) > 0]
        fs = [self.laws[j].f for j in which]
        temps = [(i, t) for i, t in zip(self.nodes, self._tnames) if t in needed]

        def at(k: int, x: np.ndarray) -> np.ndarray:
            e = dict(scal)
            for key, arr in series:
                e[key] = arr[k]
            for i, t in temps:
                e[t] = x[i]
            return np.array([float(g(e)) for g in fs])

        return at
