"""The magnet seen through the inverter: the permanent-magnet flux linkage from the steady-state
voltage equations, and the magnet temperature it implies.

In the rotor frame, at steady state (``ω_el = p · 2π n / 60``)::

    u_q = R_s(T_w) i_q + ω_el (L_d(|i|) i_d + ψ_PM(T_m)) + V_e i_q / |i|
    u_d = R_s(T_w) i_d − ω_el L_q(|i|) i_q                + V_e i_d / |i|

with ``R_s(T_w) = R_20 (1 + 0.00393 (T_w − 20))`` (copper), ``L(|i|) = L0 + L1 |i| / 100 A`` (a
straight line over the current magnitude: saturation), ``V_e`` the inverter's voltage error
(dead time and switch drops: the commanded voltage exceeds the machine's by about ``V_e`` along
the current vector; ``i / max(|i|, 5 A)`` keeps it finite at zero current) and
``ψ_PM(T_m) = ψ_20 + β (T_m − 20)`` (``β / ψ_20`` is the magnet's temperature coefficient, about
−0.1 %/K for NdFeB). Both equations are linear in the eight parameters, so the commissioning fit
(:func:`fit_flux_model`) is one regularised least-squares solve over a recorded run with the
measured magnet temperature: a Gaussian prior per parameter (:data:`DEFAULT_PRIORS`, tighten it
with what the data sheet or a DC resistance test says) keeps those a single operating point
cannot separate (``R_s``, ``V_e`` and ``L_q`` at one current) where the prior puts them, and the
posterior σ says which ones the run did pin down.

The estimate inverts the q equation: ``T_m = 20 + (ψ̂ − ψ_20) / β`` with
``ψ̂ = (u_q − R_s i_q − V_e i_q/|i|) / ω_el − L_d(|i|) i_d``. Its error is a voltage error divided
by ``ω_el β``: at standstill and low speed there is nothing to see, and where the field is
weakened hard (``L_d i_d`` cancels most of ``ψ_PM``) a 1 % error of ``L_d`` is several kelvin. So
the variance is not assumed but measured: by contiguous cross-validation over the commissioning
run (each block predicted by a fit on the others), as the mean square q-voltage residual per
current-magnitude bin, divided by ``(ω_el β)²`` at the speed of use. An operating point is
*informative* only where the commissioning run had enough samples in its current bin, the speed
is at least :data:`SPEED_MARGIN` of the lowest speed the run covered, and the resulting σ is below
``sigma_max_k``;
elsewhere the estimate is flagged and must not be used.

The number of pole pairs scales ``ψ`` and ``L`` together (the data fix ``p ψ`` and ``p L``): a
wrong ``p`` gives the same magnet temperature.
"""
from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from ..errors import ThermalEdgeError
from ..lptn import Role
from ..lptn.vocabulary import OtherUnit, Plausible

#: copper's temperature coefficient of resistance near 20 °C, 1/K
ALPHA_CU = 0.00393
#: reference temperature of ``R_20`` and ``ψ_20``, °C
T_REF_C = 20.0
#: the current scale of the inductances' slope, A
I_SCALE_A = 100.0
#: below this current magnitude the voltage error's direction fades out, A
I_KNEE_A = 5.0
#: the estimate is used down to this share of the commissioning run's 5th-percentile speed: its σ
#: scales as 1/speed (in the variance table's scaling) and a run held at one speed has a 5th
#: percentile within hundredths of an rpm of it, which speed noise alone would undercut
SPEED_MARGIN = 0.9
#: the parameters, in the fit's order
PARAMS = ("r20", "v_err", "psi20", "beta", "ld0", "ld1", "lq0", "lq1")
#: units of :data:`PARAMS`
UNITS = {"r20": "ohm", "v_err": "V", "psi20": "Wb", "beta": "Wb/K", "ld0": "H", "ld1": "H", "lq0": "H", "lq1": "H"}
#: weak priors (mean, σ) for a machine of a few to a few hundred kW; the data decide what they see
DEFAULT_PRIORS: dict[str, tuple[float, float]] = {
    "r20": (0.02, 0.02),
    "v_err": (0.0, 2.0),
    "psi20": (0.1, 0.1),
    "beta": (-1e-4, 1e-3),
    "ld0": (5e-4, 5e-3),
    "ld1": (0.0, 1e-4),  # saturation: a tenth of a millihenry per 100 A at most, unless the data say more
    "lq0": (1e-3, 5e-3),
    "lq1": (0.0, 1e-4),
}


class FluxError(ThermalEdgeError, ValueError):
    """A flux-linkage calibration that cannot be made or used (too few samples, a bad prior)."""


@dataclass(frozen=True)
class Electrical:
    """Samples of the inverter's side: dq voltages (V), dq currents (A), speed (rpm) and the
    winding temperature (°C), each an array of equal length (or scalars)."""

    u_d: np.ndarray
    u_q: np.ndarray
    i_d: np.ndarray
    i_q: np.ndarray
    speed_rpm: np.ndarray
    winding_c: np.ndarray

    @staticmethod
    def of(columns: Mapping[str, np.ndarray], u_d: str = "u_d_v", u_q: str = "u_q_v", i_d: str | None = None,
           i_q: str | None = None, speed: str | None = None, winding: str = "stator_winding") -> Electrical:
        """From a run's columns under these names (the currents and the speed by default under
        their roles' usual names); :class:`FluxError` names a missing one."""
        names = (u_d, u_q, i_d or Role.CURRENT_D.default_column, i_q or Role.CURRENT_Q.default_column,
                 speed or Role.SPEED.default_column, winding)
        missing = [n for n in names if n not in columns]
        if missing:
            raise FluxError(f"no column(s) {', '.join(missing)} for the flux-linkage estimate")
        return Electrical(*(np.asarray(columns[n], dtype=float) for n in names))


def omega_el(speed_rpm: np.ndarray, pole_pairs: int) -> np.ndarray:
    """Electrical angular speed, rad/s."""
    return np.asarray(speed_rpm, dtype=float) * (2.0 * np.pi / 60.0) * pole_pairs


def _regressors(e: Electrical, magnet_c: np.ndarray, pole_pairs: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows of the q and d equations over :data:`PARAMS` (each (N, 8))."""
    w = omega_el(e.speed_rpm, pole_pairs)
    kr = 1.0 + ALPHA_CU * (e.winding_c - T_REF_C)
    ia = np.hypot(e.i_d, e.i_q)
    dirn = np.maximum(ia, I_KNEE_A)
    s = ia / I_SCALE_A
    z = np.zeros_like(w)
    aq = np.column_stack([kr * e.i_q, e.i_q / dirn, w, w * (magnet_c - T_REF_C), w * e.i_d, w * e.i_d * s, z, z])
    ad = np.column_stack([kr * e.i_d, e.i_d / dirn, z, z, z, z, -w * e.i_q, -w * e.i_q * s])
    return aq, ad


@dataclass
class FluxModel:
    """A commissioned flux-linkage estimator of the magnet temperature.

    Attributes
    ----------
    params : dict
        :data:`PARAMS` -> value (units :data:`UNITS`).
    sigma : dict
        Posterior σ of each parameter (same units): how closely the run pinned it down.
    pole_pairs : int
    bin_a : float
        Width of the current-magnitude bins of the variance table, A peak (the dq current's
        magnitude, amplitude-invariant: the phase current's amplitude).
    var_u : dict
        Bin index (``int(|i| / bin_a)``) -> mean square cross-validated q-voltage residual, V².
    speed_min_rpm : float
        Lowest |speed| at which the estimate is used: :data:`SPEED_MARGIN` times the 5th
        percentile of the commissioning run's speeds (below it the model is an extrapolation).
    sigma_max_k : float
        The estimate is uninformative where its σ exceeds this, K.
    tau_s : float
        Integrated autocorrelation time of the cross-validated error, s: errors closer in time
        than this are one error, not independent ones.
    cov : list of list
        Posterior covariance of :data:`PARAMS` (their units); its part of the estimate's variance
        is added to the table's (it grows away from the temperatures and currents of the run).
    beta_spread : float
        σ of ``β`` over the forward cross-validation's fits, Wb/K: how well the run really pins
        the slope down (the posterior σ does not see the slope's confounding with the currents
        and the winding temperature that move with the magnet's). Its part of the variance,
        ``((T − magnet_mean_c) beta_spread / β)²``, grows with the distance from the run's
        temperatures.
    magnet_mean_c : float
        The commissioning run's mean magnet temperature, °C.
    fit_info : dict
        Figures of the fit (samples, residuals, cross-validated RMS error).
    cv_params : list of list
        :data:`PARAMS` of each forward cross-validation fit: how far fits on less of the run
        disagree where the run has not been (the spread of an extrapolation, see
        :mod:`thermal_edge.estimation.fusion`). Empty: nothing is extrapolated.
    white_share : float
        Share of the cross-validated error's variance that is white (from one sample to the
        next: half the mean square of consecutive differences), 0 to 1; the rest holds over
        :attr:`tau_s` and the fusion carries it as a state. 0 (a file without it): all of it held.
    """

    params: dict[str, float]
    sigma: dict[str, float]
    pole_pairs: int
    bin_a: float
    var_u: dict[int, float]
    speed_min_rpm: float
    sigma_max_k: float = 10.0
    tau_s: float = 0.0
    cov: list[list[float]] = field(default_factory=list)
    beta_spread: float = 0.0
    magnet_mean_c: float = T_REF_C
    fit_info: dict[str, float] = field(default_factory=dict)
    cv_params: list[list[float]] = field(default_factory=list)
    white_share: float = 0.0

    @property
    def tempco_per_k(self) -> float:
        """The magnet's temperature coefficient of flux linkage ``β / ψ_20``, 1/K."""
        return self.params["beta"] / self.params["psi20"]

    def flux_linkage(self, e: Electrical) -> np.ndarray:
        """``ψ̂`` from the q equation (Wb); NaN at zero speed."""
        p = self.params
        w = omega_el(e.speed_rpm, self.pole_pairs)
        ia = np.hypot(e.i_d, e.i_q)
        r = p["r20"] * (1.0 + ALPHA_CU * (np.asarray(e.winding_c, dtype=float) - T_REF_C))
        ld = p["ld0"] + p["ld1"] * ia / I_SCALE_A
        back = np.asarray(e.u_q, dtype=float) - r * e.i_q - p["v_err"] * e.i_q / np.maximum(ia, I_KNEE_A)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(w != 0.0, back / np.where(w != 0.0, w, 1.0) - ld * e.i_d, np.nan)

    def temperature(self, e: Electrical, params: Mapping[str, float] | None = None) -> np.ndarray:
        """The magnet temperature the equations give (°C) with these parameters (default the
        commissioned ones), wherever the speed is not zero: no informative-region test."""
        m = self if params is None else replace(self, params={k: float(params[k]) for k in PARAMS})
        return np.asarray(T_REF_C + (m.flux_linkage(e) - m.params["psi20"]) / m.params["beta"])

    def ensemble(self) -> list[dict[str, float]]:
        """The forward cross-validation's fits (:attr:`cv_params`) as parameter mappings."""
        return [dict(zip(PARAMS, (float(x) for x in row))) for row in self.cv_params]

    def estimate(self, e: Electrical) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Magnet temperature (°C), its σ (K) and whether the operating point is informative.

        Where it is not, the temperature may be NaN and σ is ``inf``.
        """
        p = self.params
        T = self.temperature(e)
        ia = np.hypot(e.i_d, e.i_q)
        w = np.abs(omega_el(e.speed_rpm, self.pole_pairs))
        b = np.floor(ia / self.bin_a).astype(int)
        vu = np.array([self.var_u.get(int(k), np.inf) for k in np.atleast_1d(b)]).reshape(np.shape(b))
        with np.errstate(divide="ignore", invalid="ignore"):
            var = vu / (w * p["beta"]) ** 2
            if self.cov:
                g = self._gradient(e, T, ia)
                var = var + np.einsum("...i,ij,...j->...", g, np.asarray(self.cov), g)
            var = var + ((T - self.magnet_mean_c) * self.beta_spread / p["beta"]) ** 2
            sig = np.sqrt(var)
        ok = (np.abs(np.asarray(e.speed_rpm, dtype=float)) >= self.speed_min_rpm) & np.isfinite(sig) \
            & (sig <= self.sigma_max_k) & np.isfinite(T)
        return np.asarray(T), np.where(ok, sig, np.inf), np.asarray(ok)

    def sigma_table(self, speed_rpm: float) -> dict[str, float]:
        """The variance table as σ (K) per current bin (``"a-b A peak"``: the dq current's magnitude,
        the phase current's amplitude) at this speed, the parameters' part left out."""
        wb = abs(float(omega_el(np.asarray(speed_rpm), self.pole_pairs)) * self.params["beta"])
        return {f"{b * self.bin_a:g}-{(b + 1) * self.bin_a:g} A peak": float(np.sqrt(v)) / wb
                for b, v in sorted(self.var_u.items())}

    def _gradient(self, e: Electrical, T: np.ndarray, ia: np.ndarray) -> np.ndarray:
        """``∂T/∂θ`` over :data:`PARAMS` (..., 8)."""
        p = self.params
        b = p["beta"]
        wb = omega_el(e.speed_rpm, self.pole_pairs) * b
        kr = 1.0 + ALPHA_CU * (np.asarray(e.winding_c, dtype=float) - T_REF_C)
        i_d, i_q = np.asarray(e.i_d, dtype=float), np.asarray(e.i_q, dtype=float)
        z = np.zeros_like(T)
        cols = [-kr * i_q / wb, -(i_q / np.maximum(ia, I_KNEE_A)) / wb, np.full_like(T, -1.0 / b), -(T - T_REF_C) / b,
                -i_d / b, -(ia / I_SCALE_A) * i_d / b, z, z]
        return np.stack(np.broadcast_arrays(*cols), axis=-1)

    def as_dict(self) -> dict[str, object]:
        """Plain values (a YAML or JSON file's content)."""
        d = asdict(self)
        d["var_u"] = {int(k): float(v) for k, v in self.var_u.items()}
        return d

    @staticmethod
    def from_dict(d: Any) -> FluxModel:
        """Inverse of :meth:`as_dict`: every entry :meth:`as_dict` writes, each of its type (a JSON
        number, not a string holding one), else :class:`FluxError` naming the entry."""
        if not isinstance(d, Mapping):
            raise FluxError(f"flux model: the file holds a {_json_type(d)}, not an object with params, sigma, ...")
        params, sigma = _mapping(d, "params"), _mapping(d, "sigma")
        missing = ([f"params.{k}" for k in PARAMS if k not in params] if "params" in d else ["params"]) \
            + [k for k in REQUIRED if k not in d]
        if missing:
            raise FluxError(f"flux model: no {', '.join(missing)}")
        pole_pairs = d["pole_pairs"]
        if isinstance(pole_pairs, float) and pole_pairs.is_integer():
            pole_pairs = int(pole_pairs)
        if not isinstance(pole_pairs, int) or isinstance(pole_pairs, bool):
            raise FluxError(f"flux model: pole_pairs must be a whole number, got {_shown(pole_pairs)}")
        var_u = _mapping(d, "var_u")
        bins = {}
        for k, v in var_u.items():
            try:
                bins[int(k)] = _number(f"var_u.{k}", v)
            except ValueError:
                raise FluxError(f"flux model: var_u: bin {k!r} is not a whole number (the current bin index)") from None
        return _validated(FluxModel(
            {k: _number(f"params.{k}", params[k]) for k in PARAMS},
            {str(k): _number(f"sigma.{k}", v) for k, v in sigma.items()},
            pole_pairs, _number("bin_a", d["bin_a"]), bins, _number("speed_min_rpm", d["speed_min_rpm"]),
            _number("sigma_max_k", d["sigma_max_k"]), _number("tau_s", d["tau_s"]), _matrix(d, "cov"),
            _number("beta_spread", d["beta_spread"]), _number("magnet_mean_c", d["magnet_mean_c"]),
            {str(k): _number(f"fit_info.{k}", v) for k, v in _mapping(d, "fit_info").items()},
            _matrix(d, "cv_params"), _number("white_share", d.get("white_share", 0.0))))


#: The entries besides ``params`` a file must hold: one left out would silently change the
#: estimate's σ (``cov``, ``beta_spread``) or where it is used. ``fit_info`` and ``cv_params`` may
#: be absent (figures of the fit; without the forward fits nothing is extrapolated).
REQUIRED = ("sigma", "pole_pairs", "bin_a", "var_u", "speed_min_rpm", "sigma_max_k", "tau_s", "cov", "beta_spread",
            "magnet_mean_c")
#: Plausible flux linkage ``ψ_20`` of a PM machine, Wb: from a small servo's few tenths of a mWb to a
#: direct-drive generator's few Wb; outside, the value is in another unit (mWb) or of another quantity.
PSI20 = Plausible("Wb", 1e-4, 20.0, (OtherUnit("mWb", 1e-3),), what="flux linkage")
#: Plausible temperature coefficient ``β / ψ_20`` of a magnet's flux linkage, 1/K: SmCo about
#: −0.03 %/K, NdFeB −0.1 %/K, ferrite −0.2 %/K; ten times ferrite's is no magnet.
TEMPCO_MIN_PER_K = -0.02


def _json_type(v: object) -> str:
    """What JSON calls ``v``'s type."""
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "boolean"
    if isinstance(v, (int, float)):
        return "number"
    if isinstance(v, str):
        return "string"
    return "list" if isinstance(v, (list, tuple)) else "object" if isinstance(v, Mapping) else type(v).__name__


def _shown(v: object) -> str:
    """``v`` as a message shows it: its JSON text when short, and its JSON type."""
    try:
        text = json.dumps(v)
    except (TypeError, ValueError):
        text = ""
    kind = _json_type(v)
    return text if kind == "null" else f"{text} (a {kind})" if 0 < len(text) <= 40 else f"a {kind}"


def _number(key: str, v: object) -> float:
    """``v`` if it is a JSON number, as float; else :class:`FluxError` naming ``key``."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise FluxError(f"flux model: {key} must be a number, got {_shown(v)}")
    return float(v)


def _mapping(d: Mapping[str, Any], key: str) -> Mapping[str, Any]:
    """``d[key]`` (empty if absent) if it is a JSON object, else :class:`FluxError` naming ``key``."""
    v = d.get(key, {})
    if not isinstance(v, Mapping):
        raise FluxError(f"flux model: {key} must be an object, got {_shown(v)}")
    return v


def _matrix(d: Mapping[str, Any], key: str) -> list[list[float]]:
    """``d[key]`` (empty if absent) if it is a list of lists of numbers, else :class:`FluxError`."""
    v = d.get(key, [])
    if not isinstance(v, list) or not all(isinstance(row, list) for row in v):
        raise FluxError(f"flux model: {key} must be a list of rows of numbers, got {_shown(v)}")
    return [[_number(f"{key}[{i}][{j}]", x) for j, x in enumerate(row)] for i, row in enumerate(v)]


def _validated(m: FluxModel) -> FluxModel:
    """``m`` if it is a model :func:`fit_flux_model` could have written, else :class:`FluxError`
    naming the entry: a file edited by hand or written for another machine must fail where it is
    read, not as a division by zero in the service's tick."""
    def bad(key: str, why: str) -> FluxError:
        return FluxError(f"flux model: {key} {why}")

    for k in PARAMS:
        if not math.isfinite(m.params[k]):
            raise bad(f"params.{k}", f"is not a finite number ({m.params[k]})")
    for k, why in (("r20", "the stator resistance"), ("psi20", "the flux linkage"), ("ld0", "L_d at zero current"),
                   ("lq0", "L_q at zero current")):
        if not m.params[k] > 0:
            raise bad(f"params.{k}", f"must be positive ({why}), got {m.params[k]:g}")
    if not m.params["beta"] < 0:  # a magnet's flux linkage falls as it warms: no other sign is a magnet
        raise bad("params.beta", f"must be negative (the flux linkage falls with temperature), got {m.params['beta']:g}")
    psi_problem = PSI20.problem(m.params["psi20"])
    if psi_problem is not None:
        raise bad("params.psi20", psi_problem)
    if m.tempco_per_k < TEMPCO_MIN_PER_K:
        raise bad("params.beta", f"{m.params['beta']:g} Wb/K is {100 * m.tempco_per_k:+.2f} %/K of params.psi20: no "
                  f"magnet's flux linkage falls faster than {100 * TEMPCO_MIN_PER_K:g} %/K (NdFeB about -0.1 %/K)")
    if not 1 <= m.pole_pairs <= 100:
        raise bad("pole_pairs", f"must be 1 to 100, got {m.pole_pairs}")
    for key, v, lo in (("bin_a", m.bin_a, 0.0), ("sigma_max_k", m.sigma_max_k, 0.0)):
        if not (math.isfinite(v) and v > lo):
            raise bad(key, f"must be positive, got {v:g}")
    for key, v in (("speed_min_rpm", m.speed_min_rpm), ("tau_s", m.tau_s), ("beta_spread", m.beta_spread)):
        if not (math.isfinite(v) and v >= 0):
            raise bad(key, f"must be zero or more, got {v:g}")
    if not (math.isfinite(m.white_share) and 0.0 <= m.white_share <= 1.0):
        raise bad("white_share", f"must be between 0 and 1, got {m.white_share:g}")
    if not m.var_u:
        raise bad("var_u", "is empty: no current bin has a variance (the estimate would never be informative)")
    if any(not (math.isfinite(v) and v >= 0) for v in m.var_u.values()) or any(b < 0 for b in m.var_u):
        raise bad("var_u", "holds a negative or non-finite variance or bin")
    if (len(m.cov) != len(PARAMS) or any(len(row) != len(PARAMS) for row in m.cov)
                  or not np.all(np.isfinite(np.asarray(m.cov, dtype=float)))):
        raise bad("cov", f"must be a finite {len(PARAMS)} x {len(PARAMS)} matrix ({', '.join(PARAMS)})")
    if any(len(row) != len(PARAMS) for row in m.cv_params):
        raise bad("cv_params", f"rows must have {len(PARAMS)} entries ({', '.join(PARAMS)})")
    return m


def _solve(aq: np.ndarray, ad: np.ndarray, uq: np.ndarray, ud: np.ndarray, mu: np.ndarray, sd: np.ndarray,
           iterations: int = 3, d_weight: float = 1.0) -> tuple[np.ndarray, np.ndarray, float, float]:
    """MAP estimate under the priors with each equation's noise σ re-estimated from its residuals
    (inflated by their correlation time in samples); returns θ, its posterior covariance and the
    two effective noise σ (V)."""
    sq = sdd = 1.0
    theta = mu.copy()
    cov = np.diag(sd**2)
    for _ in range(iterations):
        A = np.vstack([aq / sq, d_weight * ad / sdd, np.diag(1.0 / sd)])
        y = np.concatenate([uq / sq, d_weight * ud / sdd, mu / sd])
        # columns differ by orders of magnitude (Ω against H·rad/s): solve on scaled columns
        scale = np.linalg.norm(A, axis=0)
        scale[scale == 0] = 1.0
        As = A / scale
        theta = np.linalg.lstsq(As, y, rcond=None)[0] / scale
        cov = np.linalg.inv(As.T @ As) / np.outer(scale, scale)
        # residuals correlated over τ samples carry the information of N/τ independent ones:
        # without this the model errors of one operating point would outweigh every prior
        rq, rd = uq - aq @ theta, ud - ad @ theta
        sq = max(float(np.sqrt(np.mean(rq**2) * _autocorrelation_time(rq, 1.0))), 1e-6)
        sdd = max(float(np.sqrt(np.mean(rd**2) * _autocorrelation_time(rd, 1.0))), 1e-6)
    return theta, cov, sq, sdd


def steady(speed_rpm: np.ndarray, rel: float = 0.02, floor_rpm: float = 20.0) -> np.ndarray:
    """Samples whose speed differs from the previous sample's by at most ``rel`` of it (or
    ``floor_rpm``): the voltage equations hold in the steady state only (``L di/dt`` and the
    averaging of a ramp over a sample period are not in them). The first sample counts as steady."""
    n = np.abs(np.asarray(speed_rpm, dtype=float))
    d = np.abs(np.diff(n, prepend=n[:1]))
    return d <= np.maximum(rel * n, floor_rpm)


def back_emf(e: Electrical) -> np.ndarray:
    """Samples at (nearly) zero current, below :data:`I_KNEE_A`: there ``u_q = ω_el ψ_PM`` holds
    in a speed ramp as well (no inductance, no ``L di/dt``, and the voltage and the speed it is
    divided by move together), so they measure the flux linkage directly, the standard open-circuit
    back-EMF test of a commissioning."""
    return np.hypot(np.asarray(e.i_d, dtype=float), np.asarray(e.i_q, dtype=float)) < I_KNEE_A


def _autocorrelation_time(e: np.ndarray, dt: float) -> float:
    """Integrated autocorrelation time (s), summed to the first non-positive lag."""
    x = e - e.mean()
    v = float(x @ x)
    if len(x) < 3 or v == 0.0:
        return dt
    tau = 1.0
    for k in range(1, len(x) // 2):
        r = float(x[:-k] @ x[k:]) / v
        if r <= 0.0:
            break
        tau += 2.0 * r
    return tau * dt


def fit_flux_model(e: Electrical, magnet_c: np.ndarray, pole_pairs: int, dt: float,
                   priors: Mapping[str, tuple[float, float]] | None = None, speed_min_rpm: float = 500.0,
                   folds: int = 5, bin_a: float = 20.0, min_samples: int = 20, sigma_max_k: float = 10.0) -> FluxModel:
    """Commission the estimator on a recorded run with the measured magnet temperature.

    Parameters
    ----------
    e : Electrical
        The run's inverter side (voltages V, currents A, speed rpm, winding °C).
    magnet_c : ndarray
        Measured magnet temperature, °C (NaN samples skipped).
    pole_pairs : int
    dt : float
        Sample period, s (for the error's correlation time).
    priors : mapping, optional
        Parameter -> (mean, σ) overriding :data:`DEFAULT_PRIORS`.
    speed_min_rpm : float
        Samples slower than this are not used (nothing to see there), nor those outside the
        steady state (:func:`steady`) unless at zero current (:func:`back_emf`).
    folds : int
        Forward cross-validation steps for the variance table (the run is cut into ``folds + 1``
        contiguous blocks; each after the first is predicted by a fit on those before it). The
        early fits have seen little: the table is conservative, the more so the narrower the
        temperature range of the run's first part.
    bin_a : float
        Current-magnitude bin width of the variance table, A peak (the dq current's magnitude).
    min_samples : int
        A bin needs this many cross-validated samples to be informative.
    sigma_max_k : float
        Largest σ at which an operating point still counts as informative, K.
    """
    if pole_pairs < 1:
        raise FluxError(f"pole pairs must be at least 1, got {pole_pairs}")
    pri = dict(DEFAULT_PRIORS)
    for k, v in (priors or {}).items():
        if k not in pri:
            raise FluxError(f"prior for unknown parameter {k!r} (known: {', '.join(PARAMS)})")
        if not (len(v) == 2 and float(v[1]) > 0):
            raise FluxError(f"prior for {k}: need (mean, sigma > 0), got {v!r}")
        pri[k] = (float(v[0]), float(v[1]))
    mu = np.array([pri[k][0] for k in PARAMS])
    sd = np.array([pri[k][1] for k in PARAMS])
    magnet_c = np.asarray(magnet_c, dtype=float)
    use = (np.abs(e.speed_rpm) >= speed_min_rpm) & np.isfinite(magnet_c) & (steady(e.speed_rpm) | back_emf(e))
    for a in (e.u_d, e.u_q, e.i_d, e.i_q, e.winding_c):
        use &= np.isfinite(a)
    idx = np.flatnonzero(use)
    if len(idx) < max(2 * folds, min_samples):
        raise FluxError(f"only {len(idx)} samples at or above {speed_min_rpm:g} rpm with a magnet reading; "
                        f"need at least {max(2 * folds, min_samples)}")
    aq, ad = _regressors(e, magnet_c, pole_pairs)
    aq, ad = aq[idx], ad[idx]
    uq, ud = np.asarray(e.u_q, dtype=float)[idx], np.asarray(e.u_d, dtype=float)[idx]
    theta, cov, sq, sdd = _solve(aq, ad, uq, ud, mu, sd)
    # the variance table from contiguous blocks, each predicted by a fit on the blocks before it (as
    # the estimate is used: forward in time, often at temperatures the run has not reached yet),
    # bias from temperatures or currents the earlier part missed included
    res_u = np.full(len(idx), np.nan)
    res_t = np.full(len(idx), np.nan)
    blocks = np.array_split(np.arange(len(idx)), folds + 1)
    w = omega_el(e.speed_rpm[idx], pole_pairs)
    betas = []
    fits = []
    for j in range(1, len(blocks)):
        keep, blk = np.concatenate(blocks[:j]), blocks[j]
        th = _solve(aq[keep], ad[keep], uq[keep], ud[keep], mu, sd)[0]
        fits.append([float(x) for x in th])
        betas.append(float(th[PARAMS.index("beta")]))
        res_u[blk] = uq[blk] - aq[blk] @ th
        res_t[blk] = res_u[blk] / (w[blk] * th[PARAMS.index("beta")])
    # the white share of the error: consecutive samples' differences (the held part cancels in them)
    nxt = (np.diff(idx) == 1) & np.isfinite(res_u[1:]) & np.isfinite(res_u[:-1])
    total = float(np.nanmean(res_u**2))
    white = float(np.mean(np.diff(res_u)[nxt] ** 2)) / 2.0 if nxt.any() else total
    white_share = min(1.0, white / total) if total > 0 else 1.0
    ia = np.hypot(e.i_d[idx], e.i_q[idx])
    bins = np.where(np.isfinite(res_u), np.floor(ia / bin_a), -1).astype(int)
    res_t = res_t[np.isfinite(res_t)]
    var_u = {int(b): float(np.mean(res_u[bins == b] ** 2)) for b in np.unique(bins[bins >= 0])
             if np.sum(bins == b) >= min_samples}
    params = {k: float(v) for k, v in zip(PARAMS, theta)}
    # the speeds the variance table speaks for: those of the steady samples (a ramp's back-EMF
    # samples pass through speeds where no loaded point was seen)
    steady_idx = idx[steady(e.speed_rpm)[idx]]
    speed_of = steady_idx if len(steady_idx) else idx
    model = FluxModel(params, {k: float(np.sqrt(cov[i, i])) for i, k in enumerate(PARAMS)}, int(pole_pairs),
                      float(bin_a), var_u, float(SPEED_MARGIN * np.percentile(np.abs(e.speed_rpm[speed_of]), 5.0)),
                      float(sigma_max_k),
                      _autocorrelation_time(res_t, dt), cov.tolist(),
                      float(np.std(betas + [float(theta[PARAMS.index("beta")])])), float(np.mean(magnet_c[idx])),
                      {"samples": float(len(idx)), "q_residual_v": sq, "d_residual_v": sdd,
                       "cv_rms_k": float(np.sqrt(np.mean(res_t**2)))},
                      fits + [[float(x) for x in theta]], float(white_share))
    if params["beta"] >= 0.0:
        raise FluxError(f"the fitted flux linkage rises with the magnet temperature (beta {params['beta']:.3g} Wb/K): "
                        "the run does not show the magnet (too little temperature change, or a wrong column)")
    return model
