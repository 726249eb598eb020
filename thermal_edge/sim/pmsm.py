"""The simulated machine's electrical side: the dq voltages an inverter commands for given
currents, speed and temperatures, from a PMSM model richer than the estimator's
(:mod:`thermal_edge.estimation.flux`), so that commissioning on it meets a model error:

* ``ψ_PM(T_m) = ψ_20 (1 + α_PM (T_m − 20))`` (NdFeB, ``α_PM`` about −0.11 %/K);
* ``R_s(T_w) = R_20 (1 + 0.00393 (T_w − 20))``;
* saturating inductances ``L(|i|) = L0 / (1 + (|i| / i_sat)²)`` (not a straight line);
* a dead-time voltage error ``V_dead tanh(|i| / i_dead)`` along the current vector (the commanded
  voltage exceeds the machine's by it);
* white voltage noise (the sampling of the commanded voltage);
* **field weakening**: the voltage the inverter can command is limited to ``u_dc / √3`` (linear
  modulation); above the speed where the steady-state voltage of ``i_d = 0`` would exceed it, the
  current controller adds the negative ``i_d`` that holds the voltage at the limit
  (:meth:`Pmsm.field_weakening`), and ``L_d i_d`` enters the q voltage (and the estimate: an
  inductance error then reaches the magnet's temperature). The ``i_q`` stays that of the torque
  (``k_t``; the small reluctance torque of ``L_d ≠ L_q`` is left out), and the current magnitude,
  what heats the winding, includes ``i_d`` (:meth:`Pmsm.currents`).

The defaults are the packaged 10 kW, 12-pole machine: ``k_t ≈ 5.6 Nm/A_rms`` gives
``ψ = k_t / (1.5 p √2) ≈ 0.44 Wb`` (back-EMF about 171 V rms per phase at 900 rpm). Its 660 V
DC link gives a voltage limit of 381 V (peak phase): field weakening sets in at about 1,400 rpm
under load and reaches ``i_d`` ≈ −10 A at 1,500 rpm and 23 A rms (``L_d i_d`` about 7 % of ``ψ``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

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
    #: DC-link voltage, V: the commanded voltage is at most ``udc_v / √3`` (peak phase, linear modulation)
    udc_v: float = 660.0
    #: the largest field-weakening current, A peak (a drive's field-weakening controller saturates)
    i_d_max: float = 150.0

    @property
    def kt_nm_per_arms(self) -> float:
        """The torque constant this machine has at 20 °C with ``i_d = 0`` (Nm per A rms):
        ``1.5 p ψ √2``."""
        return 1.5 * self.pole_pairs * self.psi20 * math.sqrt(2.0)

    @classmethod
    def with_kt(cls, kt_nm_per_arms: float | None) -> Pmsm:
        """The simulated machine with the flux linkage that gives ``kt_nm_per_arms`` (its other
        electrical values as they are); the default machine when that is its own within 1 %, or
        when no torque constant is given."""
        pm = cls()
        if kt_nm_per_arms is None or abs(kt_nm_per_arms / pm.kt_nm_per_arms - 1.0) < 0.01:
            return pm
        return replace(pm, psi20=float(kt_nm_per_arms) / (1.5 * pm.pole_pairs * math.sqrt(2.0)))

    def describe(self) -> str:
        """One line of what this machine's electrical side is."""
        return (f"{self.pole_pairs} pole pairs, psi {self.psi20:.4g} Wb at 20 degC (kt {self.kt_nm_per_arms:.3g} Nm/A), "
                f"r {self.r20:g} ohm, Ld/Lq {self.ld0 * 1e3:g}/{self.lq0 * 1e3:g} mH")

    @property
    def u_max(self) -> float:
        """The largest voltage the current controller commands, V (peak phase)."""
        return self.udc_v / math.sqrt(3.0)

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

    def field_weakening(self, i_q: np.ndarray, speed_rpm: np.ndarray, winding_c: np.ndarray,
                        magnet_c: np.ndarray) -> np.ndarray:
        """The d current (A peak, ≤ 0) that keeps the steady-state voltage (no noise) of ``i_q`` (A
        peak) at ``speed_rpm`` within :attr:`u_max`: zero where ``i_d = 0`` needs no more; else
        the smallest magnitude that reaches the limit (bisection: the voltage falls monotonically
        as ``i_d`` grows negative over the range the machine runs in), at most :attr:`i_d_max`."""
        i_q = np.asarray(i_q, dtype=float)
        shape = np.broadcast(i_q, np.asarray(speed_rpm), np.asarray(winding_c), np.asarray(magnet_c)).shape

        def over(i_d: np.ndarray) -> np.ndarray:
            u_d, u_q = self.voltages(i_d, i_q, speed_rpm, winding_c, magnet_c, seed=None)
            return np.asarray(np.hypot(u_d, u_q) > self.u_max)

        lo, hi = np.full(shape, -self.i_d_max), np.zeros(shape)
        need = over(hi)
        if not np.any(need):
            return hi
        for _ in range(24):  # 150 A / 2^24: far below the frames' 0.05 A steps
            mid = 0.5 * (lo + hi)
            o = over(mid)
            hi = np.where(o, mid, hi)
            lo = np.where(o, lo, mid)
        return np.where(need, lo, 0.0)

    def currents(self, torque_nm: np.ndarray, kt_nm_per_arms: float, speed_rpm: np.ndarray, winding_c: np.ndarray,
                 magnet_c: np.ndarray, i_limit_arms: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``i_d``, ``i_q`` (A peak) for a torque (Nm) at a speed: ``i_q = √2 T / k_t`` and the
        field-weakening ``i_d``; with ``i_limit_arms`` the current magnitude is kept within that RMS
        limit by reducing ``i_q`` (the torque falls), never ``i_d`` (the voltage limit comes first)."""
        i_q = math.sqrt(2.0) * np.asarray(torque_nm, dtype=float) / kt_nm_per_arms
        i_d = self.field_weakening(i_q, speed_rpm, winding_c, magnet_c)
        if i_limit_arms is not None:
            cap = math.sqrt(2.0) * max(float(i_limit_arms), 0.0)
            want = i_q
            if np.any(np.hypot(i_d, i_q) > cap):
                # i_q = min(wanted, √(cap² − i_d(i_q)²)): less i_q needs less i_d, so the rounds rise
                # to the limit from below and settle within the frames' resolution in a few
                for _ in range(8):
                    q = np.sign(want) * np.minimum(np.abs(want), np.sqrt(np.maximum(cap * cap - i_d * i_d, 0.0)))
                    i_d = self.field_weakening(q, speed_rpm, winding_c, magnet_c)
                    done = np.all(np.abs(q - i_q) < 1e-3)
                    i_q = q
                    if done:
                        break
                # within the limit exactly (less i_q at this i_d only lowers the voltage)
                i_q = np.sign(want) * np.minimum(np.abs(i_q), np.sqrt(np.maximum(cap * cap - i_d * i_d, 0.0)))
        return i_d, i_q
