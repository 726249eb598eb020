"""State observer: a Kalman filter on the node temperatures with the parameters fixed, whose
bands also carry the uncertainty of the parameters.

It gives the service its best current estimate of every node (the unmeasured hot spot and
magnets included) while the adapter fixes the model: the prediction ``T⁺ = Φ T + Γ w(T)`` with
the linearised loss feedback for the covariance, and an update with whichever sensors report
(NaN readings are skipped).

The parameters are not exact: each has a relative spread ``σ_j`` (σ of ``φ_j = log θ_j``, the
model file's ``spread``). Their effect on the temperatures is ``∂T⁺/∂φ_j = θ_j (dΦ_j T + dΓ_j w
+ Γ_P ∂P/∂θ_j)`` per step (the exact derivatives the sensitivities use). Two kinds:

* the *adaptable* parameters (those that vary in service and that the readings show): a consider
  (Schmidt–Kalman) filter. The covariance is kept over ``[T; φ_a]``; the readings never correct
  ``φ_a`` (the adapter estimates it) but the gain knows that part of an innovation comes from it.
* the others (the readings barely see them): only carried into the bands, as the first-order
  error ``S δφ`` of the estimate, ``S ← (I − K H)(M S + ∂T⁺/∂φ)`` with the filter's own gain, and
  variance ``S Σ Sᵀ``. Put in the gain they would make a filter read a winding innovation caused by
  any model error as evidence of a wrong magnet capacity and move the magnet estimate by tens of
  kelvin (measured on the Paderborn machine: magnet MSE 3.6 → 15 K² with a 30 % spread on ``C_pm``).

A node the sensors barely see (the magnets) keeps the band its parameters' spread implies;
without it the band would reflect state noise only and be optimistic wherever the model is.

A direct estimate of one node from elsewhere (the magnet temperature from the inverter's voltages,
:mod:`thermal_edge.estimation.flux`) enters through :meth:`Observer.update_node` with its own
variance. Its gain uses the whole band (state and parameters' part): the magnet's band is mostly
the parameters' part, and a gain from the state part alone would barely move it. Its caller may
name the nodes it corrects (the flux estimate: the rotor's), the others are then considered. The update
refuses an estimate whose 95 % band does not overlap the model's: a wrong electrical calibration
must not pull the magnet down; the refusals are counted.

The considered nodes are left alone by such an estimate in the sensor update as well: from the
first one on, the observer carries beside its covariance the one it would have without any
(:attr:`Observer.unfused`, the same transition, the same sensor updates with their own optimal gain),
and the sensor gain's rows of the considered nodes are that covariance's. Their correction by
their own sensors is then the one of the observer without the estimate, whatever the estimate
told the rotor; the covariance stays that of the estimate (Joseph form, valid for any gain).
"""
from __future__ import annotations

from collections import OrderedDict
from collections.abc import Mapping, Sequence

import numpy as np

from ..lptn import Model, Stepper, discretise
from ..lptn.discretise import DiscreteDerivatives

#: operating points whose derivative discretisation the observer keeps (:meth:`Observer._derivatives`)
DERIVATIVE_CACHE = 16


class Observer:
    """Kalman filter over node temperatures; its bands include the parameters' spread.

    Parameters
    ----------
    model : Model
    T0 : ndarray
        Initial estimate, °C.
    theta : ndarray, optional
        Parameters (default nominal); change them with :meth:`set_parameters`.
    dt : float
        Step, s.
    q_k : float
        Process noise σ per step and node, K (model error).
    r_k : float
        Measurement noise σ, K.
    p0_k : float
        Initial σ of the estimate, K.
    spread : mapping, optional
        Relative σ (of ``log θ``) of each considered parameter; default: every parameter with a
        non-zero ``spread`` in the model file. Empty: state noise only.
    in_gain : sequence of str, optional
        Considered parameters the gain accounts for (default: the model's adaptable ones).
    """

    def __init__(self, model: Model, T0: np.ndarray, theta: np.ndarray | None = None, dt: float = 1.0,
                 q_k: float = 0.02, r_k: float = 0.15, p0_k: float = 2.0,
                 spread: Mapping[str, float] | None = None, in_gain: Sequence[str] | None = None) -> None:
        self.model = model
        self.stepper = Stepper(model, theta, dt)
        self.T = np.asarray(T0, dtype=float).copy()
        n = len(model.nodes)
        if spread is None:
            spread = {p.name: p.spread for p in model.parameters if p.spread > 0}
        gain = set(model.adaptable if in_gain is None else in_gain)
        # the parameters in the gain first, then those carried in the bands only
        self.considered = tuple([c for c in spread if c in gain] + [c for c in spread if c not in gain])
        self.n_gain = sum(1 for c in spread if c in gain)
        self.cidx = model.parameter_index(self.considered) if self.considered else np.zeros(0, dtype=int)
        self.sigma_phi2 = np.square(np.array([float(spread[c]) for c in self.considered]))
        g = self.n_gain
        self.Pa = np.zeros((n + g, n + g))  # covariance over [T; φ in the gain]
        self.Pa[:n, :n] = np.eye(n) * p0_k**2
        self.Pa[n:, n:] = np.diag(self.sigma_phi2[:g])
        self.S = np.zeros((n, len(self.considered) - g))  # ∂T̂/∂φ of the others
        self._n = n
        self.Q = np.eye(n) * q_k**2
        self.r2 = r_k**2
        self.rows = {s: model.node_index(node) for s, node in model.sensors.items()}
        self._nb = len(model.boundaries)
        laws = self.stepper.loss_laws
        # the loss feedback enters the covariance where a law reads a temperature or a considered parameter
        self._loss_params = np.array([q for q, i in enumerate(self.cidx) if any(int(i) in law.d for law in laws.laws)],
                                     dtype=int)
        self._dcache: OrderedDict[tuple[float, ...], DiscreteDerivatives] = OrderedDict()
        self._op = np.zeros(1, dtype=int)  # the one operating point of a cached discretisation, per row
        #: the discretisation of the last step, and the dense forcing map of the point the drive dwells at
        self._last_point: DiscreteDerivatives | None = None
        self._dwell: tuple[DiscreteDerivatives, np.ndarray] | None = None
        #: operating points whose derivatives are kept (see :meth:`_derivatives`)
        self.derivative_cache = DERIVATIVE_CACHE
        #: direct node estimates used and refused by :meth:`update_node`
        self.node_updates_used = 0
        self.node_updates_refused = 0
        #: covariance over ``[T; φ_a]`` (K²) the observer would have without the direct node estimates,
        #: carried from the first one that considers some nodes (None before: it is :attr:`Pa`)
        self.unfused: np.ndarray | None = None
        #: the nodes whose sensor gain is :attr:`unfused`'s (those a direct estimate considers)
        self.unfused_rows = np.zeros(0, dtype=int)

    @property
    def P(self) -> np.ndarray:
        """Covariance of the temperature estimate from the state and the parameters in the gain (n, n), K²."""
        return self.Pa[: self._n, : self._n]

    @P.setter
    def P(self, value: np.ndarray) -> None:
        """Set the temperature covariance; its correlation with the parameters is forgotten (the
        result stays a covariance). :attr:`unfused` is dropped: a covariance set from outside (a
        restart, a gap in the frames) has no unfused counterpart here; the next direct estimate
        starts it again from the covariance then, whose share of earlier estimates the filter
        forgets as it forgets any initial covariance."""
        n = self._n
        self.Pa[:n, :n] = value
        self.Pa[:n, n:] = 0.0
        self.Pa[n:, :n] = 0.0
        self.unfused = None

    def set_parameters(self, theta: np.ndarray) -> None:
        self.stepper.set_parameters(theta)
        self._dcache.clear()
        self._last_point = self._dwell = None

    def _derivatives(self, inputs: Mapping[str, float]) -> DiscreteDerivatives:
        """The discretisation with its derivatives by the considered parameters near this operating
        point: its inputs rounded to two significant digits (they only shape the covariance, and a
        drive that changes speed every tick would otherwise cost a derivative discretisation per
        tick, about 5 ms for the 39-node model with 34 parameters).

        Kept factored (the modal basis and the rank-one factors of ``dA`` and ``dW``, about 0.13 MB
        for pm10kw), never as the dense ``dΦ`` and ``dΓ`` (0.6 MB); only the last
        :attr:`derivative_cache` operating points. A drive ramps through new points and then
        dwells; what it comes back to after more points than that costs one discretisation again.
        """
        st = self.stepper
        key = tuple(float(f"{float(inputs[k]):.2g}") for k in st.net.matrix_inputs)
        hit = self._dcache.get(key)
        if hit is None:
            op = {k: np.array([v]) for k, v in zip(st.net.matrix_inputs, key)}
            d = discretise(st.net.continuous(st.theta, op, K=1, wrt=list(self.cidx)), st.dt, st.method, st.max_substep)
            assert isinstance(d, DiscreteDerivatives)
            self._dcache[key] = hit = d
            while len(self._dcache) > self.derivative_cache:
                self._dcache.popitem(last=False)
        else:
            self._dcache.move_to_end(key)
        return hit

    def _forcing(self, inputs: Mapping[str, float], w: np.ndarray) -> np.ndarray:
        """``dΦ_j T + dΓ_j w`` (n, p) per unit considered parameter at the estimate ``T`` and the
        step's inputs ``w`` (boundary temperatures and losses, those of ``Γ``), °C per unit θ_j.

        From the factored derivatives, one row at a time (:meth:`DiscreteDerivatives.forcing` with
        the operating point given per row): a few hundred kflop, no dense ``dΦ`` built."""
        d = self._derivatives(inputs)
        if self._dwell is not None and self._dwell[0] is d:
            return np.tensordot(np.concatenate([self.T, w]), self._dwell[1], axes=1)
        V, Vi = d.basis(0)
        if self._last_point is d:
            # a second step at this point: the drive dwells here. The forcing is linear in (T, w):
            # its map taken dense once (n + m rows through the factored form, about 0.5 MB for
            # pm10kw, for this one point only) makes each further step one product, a quarter of
            # the factored form's time
            n, m, e = len(self.T), len(w), d.Yt[0].shape[0]
            y = np.concatenate([Vi.T, d.Ht[0].T])
            v = np.concatenate([np.zeros((n, e)), d.Yt[0].T])
            dense: np.ndarray = V @ d.forcing(np.zeros(n + m, dtype=int), y, v)  # (n + m, n, p)
            self._dwell = (d, dense)
            return np.tensordot(np.concatenate([self.T, w]), dense, axes=1)
        self._last_point = d
        y = Vi @ self.T + d.Ht[0] @ w
        v = d.Yt[0] @ w
        X: np.ndarray = V @ d.forcing(self._op, y[None], v[None])[0]
        return X

    def predict(self, inputs: Mapping[str, float]) -> np.ndarray:
        """Advance one step with these inputs; returns the predicted temperatures."""
        st = self.stepper
        Phi, Gam = st.matrices(inputs)
        laws = st.loss_laws
        # the stepper's step with the law environment built once: the losses, their slopes and their
        # parameter derivatives all read it
        env = st.env(inputs)
        w = np.concatenate([st.boundary(inputs), laws.power(env, np.asarray(self.T, dtype=float))])
        T_next = Phi @ self.T + Gam @ w
        p = len(self.cidx)
        M = Phi.copy()
        GP = Gam[:, self._nb:]
        if laws.temperature_dependent:
            M[:, laws.nodes] += GP @ laws.dT(env, self.T)
        n, g = self._n, self.n_gain
        F = np.eye(n + g)
        F[:n, :n] = M
        S = M @ self.S
        if p:
            X = self._forcing(inputs, w)  # (n, p) per unit θ
            if len(self._loss_params):  # ∂P/∂θ of the parameters some loss law reads (the others' are zero)
                dP = np.zeros((len(laws.laws), p))
                dP[:, self._loss_params] = laws.dtheta(env, self.T, self.cidx[self._loss_params])
                X += GP @ dP
            X = X * st.theta[self.cidx][None, :]  # per unit log θ
            F[:n, n:] = X[:, :g]
            S += X[:, g:]
        self.S = S
        self.transition = F  # the step's transition over [T; φ_a]: a state carried beside it follows it
        self.Pa = F @ self.Pa @ F.T
        self.Pa[:n, :n] += self.Q
        if self.unfused is not None:
            self.unfused = F @ self.unfused @ F.T
            self.unfused[:n, :n] += self.Q
        self.T = T_next
        return self.T

    def update(self, measured: Mapping[str, float]) -> np.ndarray:
        """Correct the estimate with the sensors that report (NaN or unknown ones are ignored).

        The gain's parameter rows are zero (Schmidt): the covariance update is the Joseph form
        ``(I − K H) P (I − K H)ᵀ + K R Kᵀ``, valid for that gain. After a direct estimate that
        considered some nodes, their rows are the gain of :attr:`unfused` (:meth:`unfused_gain`).
        """
        ok = [(self.rows[s], float(v)) for s, v in measured.items() if s in self.rows and np.isfinite(v)]
        if not ok:
            return self.T
        idx = [i for i, _ in ok]
        y = np.array([v for _, v in ok])
        n, m = self._n, len(self.Pa)
        Pa = self.Pa
        Sy = Pa[np.ix_(idx, idx)] + np.eye(len(idx)) * self.r2
        K = np.zeros((m, len(idx)))
        K[:n] = np.linalg.solve(Sy, Pa[idx, :n]).T
        Ku = self.unfused_gain(idx)
        if Ku is not None:
            K[self.unfused_rows] = Ku[self.unfused_rows]
        self.T = self.T + K[:n] @ (y - self.T[idx])
        self.Pa = _joseph(Pa, K, idx, self.r2)
        self.S = self.S - K[:n] @ self.S[idx, :]
        return self.T

    def unfused_gain(self, idx: Sequence[int]) -> np.ndarray | None:
        """The sensor gain (m, l) for the sensors at node rows ``idx`` of the observer without the
        direct node estimates (zero parameter rows, as :meth:`update`), and :attr:`unfused`
        advanced by that update; None while there is no :attr:`unfused`.

        The considered nodes take these rows: what a direct estimate of the rotor says about them
        reaches them through the model's cross-covariance only, and that is also how it would
        narrow their predicted band and so shrink their sensors' gain (the magnet heats the
        winding), the same path the estimate is kept from in :meth:`update_node`. With them, a
        considered node is corrected by its sensors as without the estimate, and moved by the
        estimate only where the model's conduction carries the corrected rotor's heat."""
        Pu = self.unfused
        if Pu is None:
            return None
        n, m = self._n, len(Pu)
        Ku = np.zeros((m, len(idx)))
        Ku[:n] = np.linalg.solve(Pu[np.ix_(idx, idx)] + np.eye(len(idx)) * self.r2, Pu[idx, :n]).T
        self.unfused = _joseph(Pu, Ku, idx, self.r2)
        return Ku

    def consider(self, corrects: Sequence[int] | np.ndarray) -> None:
        """A direct estimate corrects only the nodes ``corrects``: the others take their sensor
        gain from :attr:`unfused` from now on (started here as the covariance so far, which holds
        no direct estimate yet, or kept)."""
        self.unfused_rows = np.setdiff1d(np.arange(self._n), np.asarray(corrects, dtype=int))
        if self.unfused is None and len(self.unfused_rows):
            self.unfused = self.Pa.copy()

    def update_node(self, node: int | Sequence[int], value: float, var: float, inflate: float = 1.0,
                    z: float = 1.959963984540054, corrects: Sequence[int] | np.ndarray | None = None) -> bool:
        """Correct the estimate with a direct estimate ``value`` (°C, variance ``var`` K²) of node
        index ``node``, or of the mean of several nodes (the flux linkage sees all magnets, a
        model may split them); returns whether it was used. ``inflate`` (≥ 1) weakens the update
        to ``var · inflate`` without widening the check's band: an estimate whose errors are
        correlated over ``inflate`` samples is one measurement per that many samples.

        Refused (and counted in :attr:`node_updates_refused`) when it disagrees with the model
        beyond both 95 % bands: ``|value − h T̂| > z (σ_model + σ_value)``, or when ``var`` is not a
        finite positive number (an uninformative operating point). The gain is the optimal one for
        the whole covariance ``C = P + S Σ Sᵀ``: ``K = C h / (hᵀ C h + r)``, ``r = var · inflate``;
        the update ``A = I − K hᵀ`` is applied to the state part (Joseph form, ``+ r K Kᵀ``) and to ``S``,
        so the two parts again sum to the covariance of the corrected estimate.

        ``corrects`` (node indices, default all): the nodes the estimate may move; the gain's rows
        of the others are zero (Schmidt–Kalman: those nodes are considered, their covariance with
        the corrected ones follows the Joseph form, which is valid for any gain). The corrected
        rows are the optimal gain's: a zero row elsewhere does not change them. From then on the
        sensor update's rows of the considered nodes are those of the observer without direct
        estimates (:meth:`consider`, :meth:`unfused_gain`).
        """
        if not (np.isfinite(value) and np.isfinite(var) and var > 0.0):
            return False
        n, m = self._n, len(self.Pa)
        idx = [int(node)] if isinstance(node, (int, np.integer)) else [int(i) for i in node]
        h = np.zeros(n)
        h[idx] = 1.0 / len(idx)
        C = self.covariance()
        Ch = C @ h
        s2 = float(h @ Ch)
        nu = float(value) - float(h @ self.T)
        if abs(nu) > z * (float(np.sqrt(max(s2, 0.0))) + float(np.sqrt(var))):
            self.node_updates_refused += 1
            return False
        K = np.zeros(m)
        r = var * max(float(inflate), 1.0)
        K[:n] = Ch / (s2 + r)
        if corrects is not None:
            self.consider(corrects)
            K[self.unfused_rows] = 0.0
        self.T = self.T + K[:n] * nu
        A = np.eye(m)
        A[:, :n] -= np.outer(K, h)
        self.Pa = A @ self.Pa @ A.T + r * np.outer(K, K)
        self.Pa = 0.5 * (self.Pa + self.Pa.T)
        self.S = self.S - np.outer(K[:n], h @ self.S)
        self.node_updates_used += 1
        return True

    def std(self) -> np.ndarray:
        """Standard deviation of each node's estimate, K (state and parameter uncertainty)."""
        return np.sqrt(np.clip(np.diag(self.P) + (self.S**2) @ self.sigma_phi2[self.n_gain:], 0.0, None))

    def covariance(self) -> np.ndarray:
        """Covariance of the estimate's error (n, n), K²: :attr:`P` plus the parameters' part
        ``S Σ Sᵀ`` the bands carry (its diagonal is :meth:`std` squared). What a saved state keeps:
        the parameters' part is an error shared by whole regions (a wrong magnet loss heats the
        magnets, rotor iron and shaft together), so it must survive a restart with that structure,
        not as independent variances the model's conduction would wash out within a minute."""
        Ss = self.S * np.sqrt(self.sigma_phi2[self.n_gain:])[None, :]
        return self.P + Ss @ Ss.T


def _joseph(P: np.ndarray, K: np.ndarray, idx: Sequence[int], r2: float) -> np.ndarray:
    """The Joseph-form update ``(I − K H) P (I − K H)ᵀ + r² K Kᵀ`` (symmetrised) for the gain ``K``
    (m, l) of sensors at rows ``idx`` (``H`` selects them), as rank-l corrections: ``A P = P − K
    P[idx]`` then ``A P Aᵀ = A P − (A P)[:, idx] Kᵀ``, about 4·m²·l flops instead of two dense m×m
    products (4·m³) each tick."""
    AP = P - K @ P[idx, :]
    out = AP + (r2 * K - AP[:, idx]) @ K.T
    return 0.5 * (out + out.T)
