"""The weighted prediction-error objective, its analytic gradient and Gauss-Newton Hessian.

``Obj(φ) = Σ_k w_k r_kᵀ r_k + ρ Σ_j ((φ_j − φ_j⁰)/σ_j)²`` with residuals ``r_k = S_m T_k − y_k``
(open-loop prediction from the window's first state minus the readings; missing readings give
zero residual), weights ``w_k`` that favour recent samples, and an optional prior toward the
offline values ``φ⁰`` (MAP instead of plain least squares: with few sensors the unmeasured nodes
otherwise pay for a better fit of the measured ones).

Gradient ``2 Σ_k w_k J_kᵀ r_k`` and Gauss-Newton Hessian ``2 Σ_k w_k J_kᵀ J_k`` come from the
forward sensitivities, ``J_k = S_m ∂T_k/∂φ`` (paper eqs. 33–37).

Weights (both normalised to sum 1):

* ``paper``: ``w_k = (1 − e^{−kF}) / Σ_j (1 − e^{−jF})`` with ``F = 0.05`` and ``k`` counted in
  samples from the window start (the paper's §5.1 form): the first ~1/F samples, taken from a
  state the model may not know well, count less.
* ``forgetting``: ``w_k = exp(−(t_N − t_k)/τ)``: exponential forgetting with time constant ``τ``
  (s), so that slow drifts (aging) are followed.

A free start (``start_free``): the window's initial state comes from its first readings, whose
noise the slowest mode remembers for hours; a fit would take that memory for the parameters (on a
simulated fleet, errors of 4 standard deviations on average). The start's offsets along the given
directions are then fitted alongside, by projection (variable projection with the offsets'
response ``G`` fixed at the point of the first evaluation: the system is affine in its initial
state, so ``G`` depends on the parameters only through the transient's shape): residuals and
Jacobian lose their component in the span of ``G``, ``r ← r − G c`` with ``c`` the weighted least
squares offsets, and the information left is the parameters' with the offsets unknown.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..lptn.reduced import AnySimulator
from ..lptn.simulate import SimulatedRun, Simulator, Trajectory
from .common import ParamSpace, Window


def weights(t: np.ndarray, kind: str = "paper", F: float = 0.05, tau_s: float = 3600.0) -> np.ndarray:
    """Sample weights (sum 1) for sample times ``t`` (s)."""
    N = len(t)
    if kind == "paper":
        k = np.arange(1, N + 1)
        w = 1.0 - np.exp(-k * F)
    elif kind == "forgetting":
        w = np.exp(-(t[-1] - t) / tau_s)
    elif kind == "uniform":
        w = np.ones(N)
    else:
        raise ValueError(f"unknown weighting {kind!r} (paper, forgetting, uniform)")
    return w / w.sum()


@dataclass
class Evaluation:
    """Objective, gradient (log-parameters), Gauss-Newton Hessian and the pieces they came from."""

    value: float
    grad: np.ndarray
    hess: np.ndarray
    residuals: np.ndarray  # (N, ns) K, zero where not measured
    jac: np.ndarray  # (N, ns, p) K per unit log-parameter
    sqrt_w: np.ndarray  # (N, 1)
    T: np.ndarray  # (N, n) predicted node temperatures


class Objective:
    """Prediction-error objective of a model over a window, for a set of parameters.

    Parameters
    ----------
    sim : Simulator or ReducedSimulator
    space : ParamSpace
        Which parameters vary (log-scaled), the fixed rest, and the prior.
    window : Window
    sensors : sequence of str
        Sensors used (a subset of the window's).
    weighting : {"paper", "forgetting", "uniform"}
    prior_weight : float
        ``ρ`` relative to the data term at unit residual: the penalty is
        ``ρ · Σ ((φ − φ⁰)/σ)²`` with ``σ`` the parameter's declared ``spread`` (a quarter of its
        log range if it declares none). 0 = plain least squares.
    start_free : ndarray (n, d), optional
        Directions of the window's initial state (K per unit) whose offsets are fitted alongside
        (see the module docstring); default none.
    """

    def __init__(self, sim: AnySimulator, space: ParamSpace, window: Window, sensors: list[str] | None = None,
                 weighting: str = "paper", prior_weight: float = 0.0, tau_s: float = 3600.0,
                 start_free: np.ndarray | None = None) -> None:
        self.sim, self.space, self.window = sim, space, window
        self.start_free = None if start_free is None or not np.size(start_free) else np.asarray(start_free, dtype=float)
        #: G (N, ns, d) and the pseudo-inverse of its weighted, flattened form (d, N ns): built at the first evaluation
        self._start_response: tuple[np.ndarray, np.ndarray] | None = None
        model = sim.model
        self.sensors = list(sensors or window.measured)
        self.rows = [model.sensors[s] for s in self.sensors]
        self.Y = np.column_stack([window.measured[s] for s in self.sensors])
        self.mask = np.isfinite(self.Y)
        self.Y0 = np.where(self.mask, self.Y, 0.0)
        self.w = weights(window.t, weighting, tau_s=tau_s)[:, None] * self.mask
        self.sqrt_w = np.sqrt(self.w)
        self.prior_weight = prior_weight
        spread = np.array([space.model.parameters[i].spread for i in space.index], dtype=float)
        self.sigma = np.where(spread > 0, spread, (np.log(space.upper) - np.log(space.lower)) / 4.0)
        self.evaluations = 0
        #: the last evaluation: its key, itself, whether with derivatives, the simulation kept
        self._last: tuple[bytes, Evaluation, bool, SimulatedRun | None] | None = None

    def _prior(self, phi: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        if not self.prior_weight:
            p = len(phi)
            return 0.0, np.zeros(p), np.zeros((p, p))
        z = (phi - np.log(self.space.prior)) / self.sigma
        return (float(self.prior_weight * z @ z), 2 * self.prior_weight * z / self.sigma,
                np.diag(2 * self.prior_weight / self.sigma**2))

    def evaluate(self, phi: np.ndarray, derivatives: bool = True, keep: bool = False) -> Evaluation:
        """Objective at log-parameters ``phi`` (with gradient and GN Hessian when asked).

        ``keep`` (a value without derivatives): keep the simulation, so that the derivatives at
        this point, when asked for next, come from it (:meth:`~thermal_edge.lptn.Simulator.simulate_run`)
        instead of a second simulation: the same numbers as asking for them at once.
        """
        key = phi.tobytes()
        last = self._last
        if last is not None and last[0] == key:
            if last[2] or not derivatives:
                return last[1]  # a value with derivatives also answers a request for the value
            if last[3] is not None:  # the simulation of this point, kept: its sensitivities only
                traj = last[3].sensitivities(self.space.names, self.rows)
                return self._evaluation(phi, traj, True, None)
        self.evaluations += 1
        theta_sub = self.space.from_log(phi)
        th = self.space.full(theta_sub)
        W = self.window
        if keep and not derivatives and isinstance(self.sim, Simulator):
            run = self.sim.simulate_run(th, W.inputs, W.dt, W.T0)
            return self._evaluation(phi, run.trajectory, False, run)
        traj = self.sim.simulate(th, W.inputs, W.dt, W.T0, wrt=self.space.names if derivatives else None,
                                 rows=self.rows if derivatives else None)
        return self._evaluation(phi, traj, derivatives, None)

    @property
    def nuisance(self) -> int:
        """Offsets of the initial state fitted alongside the parameters (``start_free``'s columns)."""
        return 0 if self.start_free is None else self.start_free.shape[1]

    def _start_projection(self, pred: np.ndarray, th: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``G`` (N, ns, d), the sensors' response to each free direction of the start (zero where
        not measured), and the pseudo-inverse of its weighted, flattened form (d, N ns): computed at
        the first call (``pred`` the predicted sensors there, ``th`` its parameters) and kept."""
        assert self.start_free is not None
        if self._start_response is None:
            W = self.window
            idx = [self.sim.model.node_index(r) for r in self.rows]
            cols = [self.sim.simulate(th, W.inputs, W.dt, W.T0 + d).T[:, idx] - pred for d in self.start_free.T]
            G = np.stack(cols, axis=2) * self.mask[:, :, None]
            self._start_response = G, np.linalg.pinv((G * self.sqrt_w[:, :, None]).reshape(-1, G.shape[2]))
        return self._start_response

    def _free_start(self, G: np.ndarray, Gw_pinv: np.ndarray, x: np.ndarray) -> np.ndarray:
        """``x`` (N, ns[, p]) less its weighted least-squares fit by the start's offsets: ``x − G c``."""
        xw = (x * (self.sqrt_w if x.ndim == 2 else self.sqrt_w[:, :, None])).reshape(Gw_pinv.shape[1], -1)
        fit = (G.reshape(-1, G.shape[2]) @ (Gw_pinv @ xw)).reshape(x.shape)
        out: np.ndarray = x - fit
        return out

    def _evaluation(self, phi: np.ndarray, traj: Trajectory, derivatives: bool, run: SimulatedRun | None) -> Evaluation:
        """The evaluation at ``phi`` from its simulation ``traj`` (with sensitivities when
        ``derivatives``), remembered as the last one (with ``run``, the simulation kept)."""
        theta_sub = self.space.from_log(phi)
        idx = [self.sim.model.node_index(r) for r in self.rows]
        pred = traj.T[:, idx]
        r = np.where(self.mask, pred - self.Y0, 0.0)
        if self.start_free is not None:
            G, Gw = self._start_projection(pred, self.space.full(theta_sub))
            r = self._free_start(G, Gw, r)
        value = float(np.sum(self.w * r * r))
        pv, pg, ph = self._prior(phi)
        p = len(phi)
        if derivatives:
            assert traj.S is not None
            J = traj.S  # the simulation's own array, made for this evaluation: scaled in place
            J *= theta_sub  # ∂/∂log θ
            J *= self.mask[:, :, None]
            if self.start_free is not None:
                J = self._free_start(G, Gw, J)
            grad, hess = self._gradient_hessian(J, r)
        else:
            J, grad, hess = np.zeros((len(r), len(idx), p)), np.zeros(p), np.zeros((p, p))
        ev = Evaluation(value + pv, grad + pg, hess + ph, r, J, self.sqrt_w, traj.T)
        self._last = (phi.tobytes(), ev, derivatives, run)
        return ev

    def _gradient_hessian(self, J: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The data term's gradient ``2 Σ w r J`` and Gauss-Newton Hessian ``2 Σ w JᵀJ`` from the
        Jacobian ``J`` (N, ns, p) and residuals ``r`` (N, ns): each one matrix product."""
        p = J.shape[2]
        grad = 2.0 * ((self.w * r).reshape(-1) @ J.reshape(-1, p))
        Jf = (J * self.sqrt_w[:, :, None]).reshape(-1, p)
        return grad, 2.0 * (Jf.T @ Jf)

    def adopt(self, phi: np.ndarray, full: Evaluation, full_names: Sequence[str]) -> Evaluation:
        """The evaluation at ``phi`` taken from ``full`` instead of a simulation, and remembered as
        :meth:`evaluate`'s last one: ``full`` is an evaluation with derivatives of an objective over
        the same window, sensors, weights and full parameter vector whose parameters
        ``full_names`` include this one's (the screening's, before a fit of the parameters it
        selected). A sensitivity does not depend on which other parameters are differentiated, so
        the columns of ``full``'s Jacobian are this objective's; the prior is this objective's own.
        """
        names = list(full_names)
        if full.jac.shape[2] != len(names) or full.residuals.shape != self.Y.shape:
            raise ValueError("adopt: the evaluation is not of this objective's window and sensors with full_names")
        J = full.jac[:, :, [names.index(n) for n in self.space.names]]
        r = full.residuals
        pv, pg, ph = self._prior(phi)
        grad, hess = self._gradient_hessian(J, r)
        ev = Evaluation(float(np.sum(self.w * r * r)) + pv, grad + pg, hess + ph, r, J, self.sqrt_w, full.T)
        self._last = (phi.tobytes(), ev, True, None)
        return ev

    def value(self, phi: np.ndarray) -> float:
        return self.evaluate(phi, derivatives=False).value

    def value_and_grad(self, phi: np.ndarray) -> tuple[float, np.ndarray]:
        ev = self.evaluate(phi)
        return ev.value, ev.grad

    def grad(self, phi: np.ndarray) -> np.ndarray:
        return self.evaluate(phi).grad

    def residual_vector(self, phi: np.ndarray) -> np.ndarray:
        """Stacked weighted residuals (and prior terms) whose squared sum is the objective."""
        ev = self.evaluate(phi)
        res = (ev.sqrt_w * ev.residuals).ravel()
        if self.prior_weight:
            res = np.concatenate([res, np.sqrt(self.prior_weight) * (phi - np.log(self.space.prior)) / self.sigma])
        return res

    def residual_jacobian(self, phi: np.ndarray) -> np.ndarray:
        """Jacobian of :meth:`residual_vector` with respect to ``phi``."""
        ev = self.evaluate(phi)
        p = len(phi)
        Jr = (ev.sqrt_w[:, :, None] * ev.jac).reshape(-1, p)
        if self.prior_weight:
            Jr = np.vstack([Jr, np.diag(np.sqrt(self.prior_weight) / self.sigma)])
        return Jr
