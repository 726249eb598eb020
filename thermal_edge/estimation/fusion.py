"""The observer with the magnet temperature from the inverter's voltages as a measurement of the
magnet node(s), tick by tick (:class:`FluxFusion`, what the service runs) and over a recorded run
(:func:`run_fused`).

Where the commissioning run saw the operating point, the flux estimate's error is partly held
over minutes (an operating point's bias does not average out from one sample to the next) and
partly white. The held part is a state of the filter: an offset ``b`` that decays over the
estimate's correlation time (:attr:`~thermal_edge.estimation.flux.FluxModel.tau_s`, first-order
Gauss–Markov, stationary variance the held share of the estimate's), measured with the magnet as
``T_flux = h T + b + w`` (``w`` the white share, :attr:`~thermal_edge.estimation.flux.FluxModel.white_share`).
A minute of samples from one point then tells the magnet what the held error leaves, not what
sixty independent samples would, and the band settles near the estimate's own σ wherever the
voltages keep coming. A current jump of more than one bin starts the offset afresh (another
operating point, another error); an estimate the disagreement check refuses adds no state.

Where it did not (another current, the same speed), the estimate's offset is unknown: the
inductance at that current and the voltage error's share are extrapolations, worth tens of kelvin.
Its *changes* still carry the magnet: they are the flux linkage's changes, scaled by an inductance
and a temperature coefficient the commissioning knows to some per cent. :class:`FluxObserver`
uses them so. The magnet's temperature cannot jump when the operating point does (its thermal time
constant is tens of minutes, the current's milliseconds), so on entering such a point right after
the estimate agreed with the model the filter carries two more states: the estimate's offset ``b``
there (a wide prior: the first samples set it against the model's magnet, with the model's band)
and the relative error ``s`` of its changes (prior σ: the spread of that sensitivity over the
commissioning's forward cross-validation fits, at least :data:`SLOPE_SIGMA_MIN`). The measurement is
``T_flux = T_m + b + s · (T_flux − T_flux,entry)``. ``s`` is a consider state (Schmidt): carried in
every band, never corrected, because nothing the filter reads can tell it (the stator sensors see
the magnet only through the model, whose rotor-side error over a cool-down is as large as the
changes' own; corrected by them, ``s`` would take on the model's error and the band its
confidence). Their cross-covariances with the temperatures follow the observer's own transition
and gains, so the magnet's band narrows by what the changes tell and no more. A wrong calibration
never gets there: it is refused where the commissioning saw the point, and only an estimate
accepted shortly before may enter a new one.

The flux estimate corrects the rotor only (:func:`rotor_nodes`: the magnet node(s) and the nodes
whose role is one of :data:`ROTOR_SIDE`); the stator's nodes are considered (Schmidt): their rows
of the gain are zero, their covariance with the rotor follows the Joseph form. The stator PT100s
read the winding and the yoke every tick to a tenth of a kelvin. What the flux linkage says
about a stator node comes only through the model's cross-covariance, that is through the
rotor–stator coupling and the rotor-side parameters' spread (the part of the model the stator
sensors cannot identify) and through the estimate's own error, held over minutes: moved so, a
stator node takes a share of the flux estimate's error and of the model's rotor-side error, which
its own sensors then have to take back. The rows of the rotor's nodes are the optimal gain's all
the same (a zero row elsewhere does not change them), so the magnet learns what it learnt before.
And the winding's protection (the hot spot) keeps resting on the stator's sensors and the model
alone: an electrical calibration that slips past the disagreement check cannot cool it. The
corrected rotor still reaches the stator, through the model's conduction in the next prediction,
as the heat does. Nor does it reach the stator through the sensor update: the magnet's narrower
band would narrow the stator's predicted band through the same cross-covariance and so shrink the
gain the stator takes from its own sensors. The stator's rows of the sensor gain are therefore
those of the observer without the flux estimate (:meth:`Observer.unfused_gain`, its covariance
carried beside from the first flux estimate on); the rotor's rows and the offset's stay the fused
covariance's optimal gain, and the Joseph form keeps the fused covariance that of the estimate.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..data import Run
from ..lptn import Model
from ..lptn.vocabulary import NodeRole
from .flux import Electrical, FluxModel, steady
from .observer import Observer
from .predict import initial_from_run, model_inputs

#: prior σ of the flux estimate's offset at an operating point the commissioning did not see, K
#: (the extrapolations measured on a real machine miss by 10–40 K; the first samples set it)
OFFSET_PRIOR_K = 50.0
#: an operating point the commissioning did not see is used only if the estimate was accepted
#: within this many of its correlation times before (the anchor: the magnet cannot jump)
ANCHOR_WITHIN_TAU = 1.0
#: the change sensitivity's spread is measured by a step of this size in the d current, A
DI_PROBE_A = 1.0
#: floor of the relative σ of an extrapolated estimate's changes: the fits of one commissioning run
#: share its blind spot (they all saw one current), and a saturating machine's incremental
#: inductance differs by tens of per cent between currents
SLOPE_SIGMA_MIN = 0.3
#: node roles the flux estimate corrects besides the magnet node(s) it measures: the rotor, which
#: no sensor reads; the stator's nodes are considered (see the module's description)
ROTOR_SIDE: frozenset[NodeRole] = frozenset({NodeRole.MAGNET, NodeRole.ROTOR_IRON, NodeRole.SHAFT})


def rotor_nodes(model: Model, magnet: int | Sequence[int]) -> np.ndarray:
    """Indices (ascending) of the nodes the flux estimate corrects: ``magnet`` (the node or nodes it
    measures) and every node whose role is one of :data:`ROTOR_SIDE`."""
    idx = {int(magnet)} if isinstance(magnet, (int, np.integer)) else {int(i) for i in magnet}
    idx |= {model.node_index(x) for x in model.nodes_with(*ROTOR_SIDE)}
    return np.array(sorted(idx), dtype=int)


class FluxObserver(Observer):
    """:class:`~thermal_edge.estimation.observer.Observer` with two more states while the flux
    estimate is used where the commissioning did not see the operating point: its offset ``b``
    (K) and the relative error ``s`` of its changes. Without :meth:`anchor` it is the observer,
    bit for bit.

    The extra states' covariance ``Ve`` (2, 2) and cross-covariance ``Ce`` with ``[T; φ_a]``
    follow the observer's transition (:attr:`Observer.transition`) and every update (Joseph form,
    the gain's rows of the adaptable parameters and of ``s`` zero: Schmidt); ``Se`` (2, p) is their
    first-order error from the parameters carried in the bands only.
    """

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.anchored = False
        self.xe = np.zeros(2)
        self.Ve = np.zeros((2, 2))
        self.Ce = np.zeros((len(self.Pa), 2))
        self.Se = np.zeros((2, self.S.shape[1]))
        #: the offset's decay per step and its stationary variance (K²): 1 and 0 for a constant offset
        self.decay = 1.0
        self.offset_var = 0.0

    def anchor(self, offset_sigma_k: float, slope_sigma: float, decay: float = 1.0) -> None:
        """Start the extra states afresh (an operating point entered): offset and relative change
        error zero with these σ (K, 1), uncorrelated with the temperatures. ``decay`` < 1: the
        offset is a first-order Gauss–Markov error, ``b ← decay · b + w`` per step with the
        stationary σ ``offset_sigma_k`` (the flux estimate's error correlated over its correlation
        time); 1: a constant offset."""
        self.anchored = True
        self.xe = np.zeros(2)
        self.Ve = np.diag([offset_sigma_k**2, slope_sigma**2])
        self.Ce = np.zeros((len(self.Pa), 2))
        self.Se = np.zeros((2, self.S.shape[1]))
        self.decay = float(decay)
        self.offset_var = offset_sigma_k**2 if decay < 1.0 else 0.0

    def release(self) -> None:
        """Drop the extra states (the operating point left)."""
        self.anchored = False

    def extra_covariance(self) -> np.ndarray:
        """Covariance of the offset (K) and the relative change error (2, 2): the state part and
        the parameters' part ``Se Σ Seᵀ``, as :meth:`Observer.covariance` for the temperatures."""
        Ss = self.Se * np.sqrt(self.sigma_phi2[self.n_gain:])[None, :]
        return self.Ve + Ss @ Ss.T

    def predict(self, inputs: Mapping[str, float]) -> np.ndarray:
        T = super().predict(inputs)
        if self.anchored:
            self.Ce = self.transition @ self.Ce
            a = self.decay
            if a < 1.0:  # the Gauss-Markov offset: b <- a b + w, Var w = (1 - a²) σ_b²
                self.xe[0] *= a
                self.Ce[:, 0] *= a
                self.Se[0] *= a
                self.Ve[0, 1] *= a
                self.Ve[1, 0] *= a
                self.Ve[0, 0] = a * a * self.Ve[0, 0] + (1.0 - a * a) * self.offset_var
        return T

    def _joint(self) -> tuple[np.ndarray, np.ndarray]:
        m = len(self.Pa)
        P = np.zeros((m + 2, m + 2))
        P[:m, :m], P[:m, m:], P[m:, :m], P[m:, m:] = self.Pa, self.Ce, self.Ce.T, self.Ve
        S = np.zeros((m + 2, self.S.shape[1]))
        S[: self._n], S[m:] = self.S, self.Se
        return P, S

    def _apply(self, P: np.ndarray, S: np.ndarray, K: np.ndarray, H: np.ndarray, r: np.ndarray, nu: np.ndarray) -> None:
        """Joseph-form update of the joint covariance with gain ``K`` (m+2, l), rows ``H`` (l, m+2)."""
        m, n = len(self.Pa), self._n
        x = K @ nu
        self.T = self.T + x[:n]
        self.xe = self.xe + x[m:]
        A = np.eye(m + 2) - K @ H
        P = A @ P @ A.T + K @ r @ K.T
        P = 0.5 * (P + P.T)
        S = S - K @ (H @ S)
        self.Pa, self.Ce, self.Ve = P[:m, :m], P[:m, m:], P[m:, m:]
        self.S, self.Se = S[:n], S[m:]

    def update(self, measured: Mapping[str, float]) -> np.ndarray:
        """The observer's sensor update; while anchored the extra states take their share of each
        innovation through their correlation with the temperatures."""
        if not self.anchored:
            return super().update(measured)
        ok = [(self.rows[s], float(v)) for s, v in measured.items() if s in self.rows and np.isfinite(v)]
        if not ok:
            return self.T
        idx = [i for i, _ in ok]
        y = np.array([v for _, v in ok])
        P, S = self._joint()
        m, n = len(self.Pa), self._n
        H = np.zeros((len(idx), m + 2))
        H[np.arange(len(idx)), idx] = 1.0
        R = np.eye(len(idx)) * self.r2
        K = np.linalg.solve(P[np.ix_(idx, idx)] + R, P[idx, :]).T
        K[n:m] = 0.0  # the adaptable parameters are the adapter's (Schmidt), as in the observer
        K[m + 1] = 0.0  # and the change error is considered, never corrected
        Ku = self.unfused_gain(idx)
        if Ku is not None:  # the stator's rows: the observer's without the flux estimate, as in Observer.update
            K[self.unfused_rows] = Ku[self.unfused_rows]
        self._apply(P, S, K, H, R, y - self.T[idx])
        return self.T

    def disagrees(self, node: int | Sequence[int], value: float, sigma: float, z: float = 1.959963984540054) -> bool:
        """Whether ``value`` (°C, σ ``sigma`` K) of the mean of ``node`` lies beyond both 95 % bands,
        the model's and its own (counted in :attr:`node_updates_refused`, as
        :meth:`Observer.update_node` counts it)."""
        idx = [int(node)] if isinstance(node, (int, np.integer)) else [int(i) for i in node]
        h = np.zeros(self._n)
        h[idx] = 1.0 / len(idx)
        far = abs(float(value) - float(h @ self.T)) > z * (float(np.sqrt(max(float(h @ self.covariance() @ h), 0.0)))
                                                          + float(sigma))
        if far:
            self.node_updates_refused += 1
        return far

    def update_relative(self, node: int | Sequence[int], value: float, var: float, change: float,
                        z: float = 1.959963984540054, own_sigma: float | None = None,
                        corrects: Sequence[int] | np.ndarray | None = None) -> bool:
        """Correct with ``value = h T + b + s · change`` (°C, white-noise variance ``var`` K²;
        ``change``: the estimate's change since :meth:`anchor`, K) where ``h`` averages ``node``;
        the gain is the optimal one for the whole covariance with the rows of the adaptable
        parameters and of ``s`` zero (Schmidt).
        Refused and counted as :meth:`Observer.update_node` is: beyond both 95 % bands (the
        offset's and the change error's included; with ``own_sigma`` (K) the estimate's own band
        and the model's, ``|value − h T̂| > z (σ_model + own_sigma)``, as :meth:`Observer.update_node`
        judges). ``corrects`` (node indices, default all): the temperatures it may move, the others
        considered, as in :meth:`Observer.update_node` (the offset is always corrected). Requires
        :meth:`anchor`."""
        if not (self.anchored and np.isfinite(value) and np.isfinite(var) and var > 0.0 and np.isfinite(change)):
            return False
        n, m = self._n, len(self.Pa)
        idx = [int(node)] if isinstance(node, (int, np.integer)) else [int(i) for i in node]
        H = np.zeros((1, m + 2))
        H[0, idx] = 1.0 / len(idx)
        H[0, m:] = (1.0, float(change))
        P, S = self._joint()
        Ss = S * np.sqrt(self.sigma_phi2[self.n_gain:])[None, :]
        C = P + Ss @ Ss.T
        Ch = C @ H[0]
        s2 = float(H[0] @ Ch)
        nu = float(value) - float(H[0, :n] @ self.T) - float(H[0, m:] @ self.xe)
        if own_sigma is not None:
            hm = H[0, :n]
            far = abs(float(value) - float(hm @ self.T)) > z * (float(np.sqrt(max(float(hm @ self.covariance() @ hm), 0.0)))
                                                               + float(own_sigma))
        else:
            far = abs(nu) > z * (float(np.sqrt(max(s2, 0.0))) + float(np.sqrt(var)))
        if far:
            self.node_updates_refused += 1
            return False
        K = (Ch / (s2 + var))[:, None]
        K[n:m] = 0.0
        K[m + 1] = 0.0  # the change error: considered (see the module's description)
        if corrects is not None:
            self.consider(corrects)
            K[self.unfused_rows] = 0.0
        self._apply(P, S, K, H, np.array([[var]]), np.array([nu]))
        self.node_updates_used += 1
        return True


@dataclass
class FusedRun:
    """Per sample: the observer's estimate (N, n) °C and σ (N, n) K; the flux estimate of the
    magnet (°C), its σ (K, ``inf`` where uninformative) and whether it was used; counts.
    ``relative``: samples where an estimate at an operating point the commissioning did not see
    was used for its changes (its σ there is the white part only). ``prediction`` (N, n) °C: the
    estimate before the sample's sensor readings (the one-step prediction; a sensor the observer
    reads is judged by it, the estimate after the reading is partly that reading)."""

    estimate: np.ndarray
    sigma: np.ndarray
    flux_c: np.ndarray
    flux_sigma: np.ndarray
    used: np.ndarray
    refused: int
    informative: int
    relative: np.ndarray | None = None
    prediction: np.ndarray | None = None


def slope_sigma(flux: FluxModel, e: Electrical, k: int) -> float:
    """Relative σ of the estimate's changes at sample ``k``: the spread over the forward
    cross-validation's fits of ``∂T/∂i_d`` (a step of :data:`DI_PROBE_A`), relative to the
    commissioned fit's (inductance and temperature coefficient both in it); at least
    :data:`SLOPE_SIGMA_MIN`. ``inf`` without fits."""
    fits = flux.ensemble()
    if len(fits) < 2:
        return float("inf")
    one = Electrical(*(np.atleast_1d(np.asarray(a, dtype=float)[k]) for a in (e.u_d, e.u_q, e.i_d, e.i_q, e.speed_rpm,
                                                                             e.winding_c)))
    step = Electrical(one.u_d, one.u_q, one.i_d + DI_PROBE_A, one.i_q, one.speed_rpm, one.winding_c)

    def sens(p: Mapping[str, float] | None) -> float:
        return float((flux.temperature(step, p) - flux.temperature(one, p))[0])

    g0 = sens(None)
    g = np.array([sens(p) for p in fits])
    if not (np.isfinite(g0) and g0 != 0.0 and np.all(np.isfinite(g))):
        return float("inf")
    return max(float(np.sqrt(np.mean((g - g0) ** 2))) / abs(g0), SLOPE_SIGMA_MIN)


@dataclass
class FluxSamples:
    """What the fusion takes from the flux estimate, per sample.

    Attributes
    ----------
    value : ndarray
        The commissioned estimate, °C (NaN where there is none).
    sigma : ndarray
        Its σ, K; ``inf`` where not to be used (uninformative, not steady, before the start).
    raw : ndarray
        The estimate without the informative-region test, °C (NaN where not to be used for its
        changes).
    white : ndarray
        The white-noise variance of ``raw``, K² (the best commissioned bin's residual at this speed,
        times the error's correlation time in samples).
    changes : ndarray of bool
        Where ``raw`` may be used for its changes (steady, at the commissioning's speeds, another
        current).
    current_a : ndarray
        Current magnitude, A.
    """

    value: np.ndarray
    sigma: np.ndarray
    raw: np.ndarray
    white: np.ndarray
    changes: np.ndarray
    current_a: np.ndarray


def flux_samples(flux: FluxModel, e: Electrical, dt: float, steady_mask: np.ndarray | None = None, start: int = 0,
                 extrapolate: bool = False) -> FluxSamples:
    """:class:`FluxSamples` of ``e`` (a run, or one tick's sample with ``steady_mask`` from the
    previous tick's speed; by default :func:`~thermal_edge.estimation.flux.steady` of ``e``),
    nothing used before sample ``start``. ``extrapolate`` (and the commissioning's
    cross-validation fits in ``flux``) marks where the changes may be used."""
    fc, fs, ok = flux.estimate(e)
    N = len(np.atleast_1d(fc))
    st = steady(e.speed_rpm) if steady_mask is None else np.asarray(steady_mask, dtype=bool)
    ok = np.atleast_1d(ok & st)
    ok[:start] = False
    fs = np.where(ok, fs, np.inf)
    raw, white, far = np.full(N, np.nan), np.full(N, np.inf), np.zeros(N, dtype=bool)
    if extrapolate and len(flux.cv_params) >= 2 and flux.var_u:
        raw = np.atleast_1d(flux.temperature(e))
        far = (~ok & st & np.isfinite(raw) & (np.abs(np.atleast_1d(e.speed_rpm)) >= flux.speed_min_rpm)
               & (np.arange(N) >= start))
        w_el = np.abs(flux.pole_pairs * np.atleast_1d(e.speed_rpm) * (2.0 * np.pi / 60.0) * flux.params["beta"])
        with np.errstate(divide="ignore"):
            white = min(flux.var_u.values()) / w_el**2 * max(1.0, flux.tau_s / dt)
    ia = np.atleast_1d(np.hypot(e.i_d, e.i_q))
    return FluxSamples(np.atleast_1d(fc), fs, raw, white, far, ia)


class FluxFusion:
    """The flux estimate into a :class:`FluxObserver`, tick by tick: the commissioned estimate
    with its held error as a decaying offset state (:meth:`FluxObserver.anchor` with a decay,
    :meth:`FluxObserver.update_relative` without a change), and where :class:`FluxSamples` allows, an unseen current's
    changes through :meth:`FluxObserver.update_relative`, anchored within
    :data:`ANCHOR_WITHIN_TAU` correlation times of an accepted estimate and started afresh after a
    current jump of more than one bin or as long without any use.

    Parameters
    ----------
    flux : FluxModel
    magnet : int or sequence of int
        The magnet node(s) the flux linkage sees (their mean).
    dt : float
        Tick, s.
    """

    def __init__(self, flux: FluxModel, magnet: int | Sequence[int], dt: float) -> None:
        self.flux = flux
        self.magnet = magnet
        #: the nodes the estimate corrects (:func:`rotor_nodes` of the observer's model, on its first step)
        self.corrects: np.ndarray | None = None
        self.window = ANCHOR_WITHIN_TAU * max(flux.tau_s, dt)
        #: per step, the decay of the estimate's error at a commissioned operating point (its
        #: correlation time :attr:`~thermal_edge.estimation.flux.FluxModel.tau_s`)
        self.decay = float(np.exp(-dt / flux.tau_s)) if flux.tau_s > dt else 0.0
        self.last_ok = -np.inf
        self.entry = np.nan
        self.current_entry = np.nan
        #: the extra states carry the error at a commissioned point (True) or an unseen one's offset
        self.at_commissioned = False

    def step(self, obs: FluxObserver, t_s: float, fs: FluxSamples, k: int, e: Electrical) -> tuple[bool, bool]:
        """Apply sample ``k`` of ``fs`` (of ``e``) at time ``t_s`` (s) after the observer's
        sensor update; returns whether an estimate was used and whether for its changes."""
        ia = float(fs.current_a[k])
        if self.corrects is None:
            self.corrects = rotor_nodes(obs.model, self.magnet)
        if np.isfinite(fs.sigma[k]):
            sig = float(fs.sigma[k])
            white = self.flux.white_share * sig**2
            if self.decay <= 0.0 or self.flux.white_share >= 1.0:  # uncorrelated from one step to the next
                obs.release()
                used = obs.update_node(self.magnet, float(fs.value[k]), sig**2, corrects=self.corrects)
            else:
                # the estimate's error held over tau_s: an offset state that decays over it, started
                # afresh where the operating point jumps (another point, another error); the rest white
                held = sig * np.sqrt(1.0 - self.flux.white_share)
                if not (obs.anchored and self.at_commissioned and abs(ia - self.current_entry) <= self.flux.bin_a):
                    if obs.disagrees(self.magnet, float(fs.value[k]), sig):
                        return False, False  # refused before any state is added: the observer as without it
                    obs.anchor(held, 0.0, self.decay)
                    self.at_commissioned, self.current_entry = True, ia
                obs.offset_var = held**2
                used = obs.update_relative(self.magnet, float(fs.value[k]), max(white, 1e-6 * sig**2), 0.0,
                                           own_sigma=sig, corrects=self.corrects)
            if used:
                self.last_ok = t_s
            return used, False
        if not fs.changes[k]:
            if obs.anchored and t_s - self.last_ok > self.window:
                obs.release()  # away from any usable point for longer than the errors' correlation
            return False, False
        if obs.anchored and (self.at_commissioned or abs(ia - self.current_entry) > self.flux.bin_a):
            obs.release()  # another operating point: another offset
        if not obs.anchored and t_s - self.last_ok <= self.window:
            ss = slope_sigma(self.flux, e, k)
            if np.isfinite(ss):
                obs.anchor(OFFSET_PRIOR_K, ss)
                self.entry, self.current_entry = float(fs.raw[k]), ia
                self.at_commissioned = False
        if not obs.anchored:
            return False, False
        used = obs.update_relative(self.magnet, float(fs.raw[k]), float(fs.white[k]), float(fs.raw[k]) - self.entry,
                                   corrects=self.corrects)
        if used:
            self.last_ok = t_s
            self.current_entry = ia
        return used, used


def run_fused(model: Model, run: Run, sensors: Sequence[str], flux: FluxModel | None, magnet_node: str | Sequence[str],
              theta: np.ndarray | None = None, electrical: Electrical | None = None, flux_from: int = 0,
              extrapolate: bool = False) -> FusedRun:
    """Replay ``run`` through the observer with the stator ``sensors`` and, where ``flux`` is given
    and the operating point informative (and steady), the flux estimate of ``magnet_node`` (or of
    the mean of several magnet nodes: the flux linkage sees all magnets) (from
    sample ``flux_from`` on: a run whose first part commissioned the flux model is scored on the
    rest with only the rest's flux estimates).

    With ``extrapolate`` (and the commissioning's cross-validation fits in ``flux``), a steady
    operating point at the speeds the commissioning saw but another current is used for its changes
    (:class:`FluxFusion`, :class:`FluxObserver`).

    Without ``flux`` this is the observer as the service runs it (no node updates at all).
    """
    dt = run.dt
    inputs = model_inputs(model, run)
    meas = {s: run.column(s) for s in sensors}
    N, n = len(run), len(model.nodes)
    obs = FluxObserver(model, initial_from_run(model, run, theta), theta, dt)
    m = [model.node_index(magnet_node)] if isinstance(magnet_node, str) else [model.node_index(x) for x in magnet_node]
    est, sig, pred = np.empty((N, n)), np.empty((N, n)), np.empty((N, n))
    used = np.zeros(N, dtype=bool)
    rel = np.zeros(N, dtype=bool)
    e = electrical if electrical is not None or flux is None else Electrical.of(run.columns)
    fs = flux_samples(flux, e, dt, start=flux_from, extrapolate=extrapolate) if flux is not None and e is not None else None
    fusion = FluxFusion(flux, m, dt) if flux is not None else None
    for k in range(N):
        if k:
            obs.predict({c: float(v[k - 1]) for c, v in inputs.items()})
        pred[k] = obs.T
        obs.update({s: float(v[k]) for s, v in meas.items()})
        if fusion is not None and fs is not None and e is not None:
            used[k], rel[k] = fusion.step(obs, k * dt, fs, k, e)
        est[k], sig[k] = obs.T, obs.std()
    if fs is None:
        return FusedRun(est, sig, np.full(N, np.nan), np.full(N, np.inf), used, obs.node_updates_refused, 0, rel, pred)
    return FusedRun(est, sig, fs.value, fs.sigma, used, obs.node_updates_refused, int(np.isfinite(fs.sigma).sum()), rel,
                    pred)
