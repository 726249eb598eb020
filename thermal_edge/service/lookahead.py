"""Look-ahead: the largest RMS current that keeps every limited node under its limit over a
horizon, and the time to limit at the present load.

Over the horizon the inputs are held (present speed and ambient, constant current ``i``). The
network is affine in the losses, and at a given speed every loss is affine in ``i²`` (copper
``3 R20 i² (1 + α (T - 20))``, the current-dependent parts of iron and magnet losses). With the
temperature coefficient of the copper evaluated at a fixed, conservative temperature (the highest
limit of the model, so the winding resistance is never underestimated), the trajectory at every
checkpoint ``k`` of the horizon is

    T_k = c_k + i² d_k,

where ``c_k`` follows from the present (upper-band) state with the current-independent losses and
``d_k`` from the loss per ampere² starting at zero. Each limited node ``l`` then allows
``i² <= (max_l - c_k,l) / d_k,l`` at every checkpoint: the look-ahead current is the square root
of the smallest bound (and the limit it belongs to binds). No search. The time to limit at the
present ``i²`` is the first checkpoint where ``c_k + i² d_k`` reaches a limit (interpolated linearly between checkpoints).

The checkpoints' rows of ``Φ^k`` and ``Σ_{j<k} Φ^j`` come from the step's modal form
``Φ = V diag(μ) V⁻¹`` (ZOH), built once per operating point and kept for a few of them.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..lptn import Model, Role, Stepper, discretise
from ..lptn.discretise import Discrete

__all__ = ["Lookahead", "LookaheadResult"]


@dataclass
class LookaheadResult:
    current_a: float  # largest RMS current that keeps every limit over the horizon (inf if unbounded)
    time_to_limit_s: float  # at the present load; inf if not within the horizon, 0 if already over
    binding: int = 0  # index (in ``limits``) of the limit that sets ``current_a``


def _loss_inputs(model: Model) -> set[str]:
    """Model inputs the loss laws depend on (through derived quantities too)."""
    seen: set[str] = set()
    todo = [n for loss in model.losses for n in loss.power.free()]
    while todo:
        n = todo.pop()
        if n in seen:
            continue
        seen.add(n)
        if n in model.derived:
            todo.extend(model.derived[n].free())
    return seen & set(model.inputs)


def _checkpoint_rows(d: Discrete, rows: np.ndarray, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``rows`` of ``Φ^k`` and of ``Σ_{j<k} Φ^j`` for k = 1..steps (each (steps, len(rows), n))
    from the modal form ``Φ = V diag(μ) V⁻¹`` of a one-point discretisation ``d``: the powers of
    ``Φ`` are those of ``μ``, one product for all checkpoints instead of a matrix power per step."""
    V, Vi = d.basis(0)
    mu = d.mu[0]
    powers = mu[None, :] ** np.arange(1, steps + 1)[:, None]  # μ^k (steps, n)
    sums = np.ones_like(powers)  # Σ_{j<k} μ^j
    np.cumsum(powers[:-1], axis=0, out=sums[1:])
    sums[1:] += 1.0
    Vr = V[rows]
    R = (Vr[None, :, :] * powers[:, None, :]) @ Vi
    S = (Vr[None, :, :] * sums[:, None, :]) @ Vi
    return R, S


class Lookahead:
    """Affine look-ahead over ``horizon_s`` with ``steps`` checkpoints.

    Parameters
    ----------
    model : Model
    theta : ndarray
        Parameters (update with :meth:`set_parameters`).
    limits : sequence of (name, node index, max °C)
    horizon_s : float
    steps : int
        Checkpoints over the horizon (the ZOH step is ``horizon_s / steps``).
    loss_temperature_c : float
        Temperature at which temperature-dependent losses are evaluated (conservative: the highest
        limit).
    """

    def __init__(self, model: Model, theta: np.ndarray, limits: Sequence[tuple[str, int, float]], horizon_s: float,
                 steps: int, loss_temperature_c: float | None = None) -> None:
        self.model = model
        self.limits = list(limits)
        self.horizon_s = float(horizon_s)
        self.steps = int(steps)
        self.dt = self.horizon_s / self.steps
        self.stepper = Stepper(model, theta, self.dt, method="zoh")
        self.current_input = model.input_name(Role.CURRENT)  # the RMS current, A
        self.rows = np.array([i for _, i, _ in self.limits], dtype=int)
        self.max_c = np.array([m for _, _, m in self.limits], dtype=float)
        self.loss_T = float(loss_temperature_c if loss_temperature_c is not None else self.max_c.max())
        self.nb = len(model.boundaries)
        # inputs that change the operator: those entering conductances or losses, except the current
        # and the boundary temperatures (which enter through U)
        bounds = set(model.boundaries.values())
        used = set(self.stepper.net.matrix_inputs) | _loss_inputs(model)
        self._key_inputs = tuple(k for k in model.inputs if k in used and k != self.current_input and k not in bounds)
        self._cache: dict[tuple[float, ...], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
        # operating points kept (each ~40 kB for 60 checkpoints and two limits): the key is exact, so
        # a drive whose speed or torque moves misses most ticks whatever the size; a miss costs one
        # discretisation
        self.cache_size = 16

    def set_parameters(self, theta: np.ndarray) -> None:
        self.stepper.set_parameters(theta)
        self._cache.clear()

    def _operator(self, inputs: Mapping[str, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per operating point (the inputs that enter conductances and losses, except the current and
        the boundary temperatures), as flat (steps · limits, ·) maps to the limited rows at every
        checkpoint: of the start state (the rows of ``Φ^k``), of the boundary temperatures and of the
        current-free losses (through ``Σ_{j<k} Φ^j`` and ``Γ``), and the rise per A² (cached; a
        tick is then three matrix-vector products)."""
        st = self.stepper
        key = tuple(float(inputs[k]) for k in self._key_inputs)
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        # the step's discretisation, not kept by the stepper (this cache holds what the checkpoints
        # need of it); ZOH: Φ = V diag(μ) V⁻¹ exactly, so the powers of Φ are those of μ
        op = {k: np.array([float(inputs[k])]) for k in st.net.matrix_inputs}
        d = discretise(st.net.continuous(st.theta, op, K=1), st.dt, st.method, st.max_substep)
        Gam = d.Gam[0]
        n = Gam.shape[0]
        T_eval = np.full(n, self.loss_T)
        P0 = st.losses(T_eval, {**inputs, self.current_input: 0.0})
        P1 = st.losses(T_eval, {**inputs, self.current_input: 1.0}) - P0  # loss per A²
        GU, GP = Gam[:, : self.nb], Gam[:, self.nb:]
        R, S = _checkpoint_rows(d, self.rows, self.steps)
        flat = (self.steps * len(self.rows), n)
        R2, S2 = R.reshape(flat), S.reshape(flat)
        hit = (R2, S2 @ GU, S2 @ (GP @ P0), S2 @ (GP @ P1))
        if len(self._cache) >= self.cache_size:
            self._cache.pop(next(iter(self._cache)))
        self._cache[key] = hit
        return hit

    def compute(self, T_upper: np.ndarray, inputs: Mapping[str, float]) -> LookaheadResult:
        """Look-ahead current and time to limit from the (upper-band) state ``T_upper``."""
        R, SU, s0, s1 = self._operator(inputs)
        U = self.stepper.boundary(inputs)
        c0 = np.asarray(T_upper, dtype=float)
        shape = (self.steps, len(self.rows))
        C = np.empty((self.steps + 1, len(self.rows)))
        D = np.zeros_like(C)
        C[0] = c0[self.rows]
        C[1:] = (R @ c0 + SU @ U + s0).reshape(shape)
        D[1:] = s1.reshape(shape)
        # largest i² with C + i² D <= max at every checkpoint after the start
        room = self.max_c[None, :] - C[1:]
        Dk = D[1:]
        with np.errstate(divide="ignore", invalid="ignore"):
            bound = np.where(Dk > 1e-12, room / Dk, np.where(room >= 0, np.inf, -np.inf))
        per_limit = bound.min(axis=0)
        binding = int(np.argmin(per_limit))
        i2max = float(per_limit[binding])
        current = math.sqrt(i2max) if i2max > 0 else 0.0
        # time to limit at the present load
        i_now = float(inputs.get(self.current_input, 0.0))
        i2 = i_now * i_now if math.isfinite(i_now) else 0.0
        excess = C + i2 * D - self.max_c[None, :]  # (steps+1, n_limits)
        over = np.max(excess, axis=1)
        if over[0] >= 0:
            ttl = 0.0
        else:
            hit = np.nonzero(over >= 0)[0]
            if len(hit) == 0:
                ttl = math.inf
            else:
                k = int(hit[0])
                a, b = over[k - 1], over[k]
                frac = a / (a - b) if b != a else 1.0
                ttl = (k - 1 + frac) * self.dt
        return LookaheadResult(current, ttl, binding)
