"""The simulated machine's electrical side: the dq voltages an inverter commands for given
currents, speed and temperatures, from a PMSM model richer than the estimator's
(:mod:`thermal_edge.estimation.flux`), so that commissioning on it meets a model error:

* ``ψ_PM(T_m) = ψ_20 (1 + α_PM (T_m − 20))`` (NdFeB, ``α_PM`` about −0.11 %/K);
* ``R_s(T_w) = R_20 (1 + 0.00393 (T_w − 20))``;
* saturating inductances ``L(|i|) = L0 / (1 + (|i| / i_sat)²)`` (not a straight line);
* a dead-time voltage error ``V_dead tanh(|i| / i_dead)`` along the current vector (the commanded
  voltage exceeds the machine's by it);
* white voltage noise (the sampling of the commanded voltage).

The defaults are the packaged 10 kW, 12-pole machine: ``k_t ≈ 5.6 Nm/A_rms`` gives
``ψ = k_t / (1.5 p √2) ≈ 0.44 Wb`` (back-EMF about 171 V rms per phase at 900 rpm).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Pmsm:
    """Electrical parameters of the simulated machine (SI units; temperatures °C)."""

    pole_pairs: int = 6
    psi20: float = 0.44
    tempco: float = -0.0011
    r20: float = 0.25
    ld0: float = 4.0e-3
    lq0: float = 4.4e-3
    i_sat: float = 60.0
    v_dead: float = 3.0
    i_dead: float = 2.0
    noise_v: float = 0.3
    #: copper's temperature coefficient of resistance, 1/K
    alpha_cu: float = 3.93e-3
    #: the reference temperature of ``r20`` and ``psi20``, °C
    t_ref_c: float = 20.0

    def psi(self, magnet_c: np.ndarray) -> np.ndarray:
        """Permanent-magnet flux linkage at the magnet temperature, Wb."""
        return self.psi20 * (1.0 + self.tempco * (np.asarray(magnet_c, dtype=float) - self.t_ref_c))

    def voltages(self, i_d: np.ndarray, i_q: np.ndarray, speed_rpm: np.ndarray, winding_c: np.ndarray,
                 magnet_c: np.ndarray, seed: int | None = 0) -> tuple[np.ndarray, np.ndarray]:
        """Commanded ``u_d``, ``u_q`` (V) at steady state; ``seed`` None: no noise."""
        i_d, i_q = np.asarray(i_d, dtype=float), np.asarray(i_q, dtype=float)
        w = np.asarray(speed_rpm, dtype=float) * (2.0 * np.pi / 60.0) * self.pole_pairs
        r = self.r20 * (1.0 + self.alpha_cu * (np.asarray(winding_c, dtype=float) - self.t_ref_c))
        ia = np.hypot(i_d, i_q)
        sat = 1.0 / (1.0 + (ia / self.i_sat) ** 2)
        ld, lq = self.ld0 * sat, self.lq0 * sat
        ve = self.v_dead * np.tanh(ia / self.i_dead) / np.maximum(ia, 1e-9)  # per ampere, along the current
        u_d = r * i_d - w * lq * i_q + ve * i_d
        u_q = r * i_q + w * (ld * i_d + self.psi(magnet_c)) + ve * i_q
        if seed is not None and self.noise_v > 0:
            g = np.random.default_rng(seed)
            u_d = u_d + g.normal(0.0, self.noise_v, u_d.shape)
            u_q = u_q + g.normal(0.0, self.noise_v, u_q.shape)
        return u_d, u_q
