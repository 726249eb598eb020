"""Runs of held inputs: the transitions they share, stepped in blocks, and their closed-loop modes.

Over a run where every input is the same (a drive cycle's segment, a test bench's set point) and
the losses are affine in temperature, one step is ``T[k+1] = M T[k] + f`` with a constant
transition ``M = Φ + Γ_P ∂P/∂T`` and a constant forcing ``f = Γ w``. Runs that meet a set point
again share ``M`` (:func:`transitions` groups them).

The temperatures of a run (:func:`run_temperatures`) come from the powers ``M, M², …, M^B``
(:data:`POWERS` of them, built by doubling): the states at the
block starts ``s[j+1] = M^B s[j] + c_B`` (one matrix-vector product per ``B`` steps), then every
step of every block in one product, ``T[jB + i] = M^i s[j] + c_i`` with ``c_i = Σ_{l<i} M^l f``.
That is ``2·n²`` flops a step, as many as stepping, without a loop over the steps, and the
round-off of stepping (products of ``M``): a closed form through the eigenvalues of ``M`` would
carry their round-off divided by ``1 − μ`` (about 1e-4 for the slowest mode at 1 Hz), enough to
be seen by finite differences of the simulation.

The sensitivities' closed form (:mod:`.sensitivity`) needs ``M``'s modes: ``Φ`` is similar to a
symmetric matrix (``Φ = V diag(μ_Φ) V⁻¹``, :class:`~thermal_edge.lptn.discretise.Discrete`), and
the copper-loss feedback keeps that: in the modal basis of ``Φ``, scaled by ``r = √phi``, ``M``
is symmetric when each loss law reads the temperature of its own node only, so
``M = Om diag(μ) Xi`` with real ``μ`` (:func:`closed_loop_modes`, computed when first asked for).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .discretise import Discrete

#: powers of a held run's transition (steps per block of :func:`run_temperatures`): the
#: products that build them grow with it, the loop over the blocks shrinks
POWERS = 16
#: steps of a held run stepped before its blocks start (shorter runs are stepped whole): the
#: powers cost about as much as this many steps
LEAD = 16
#: block rows per product in :func:`run_temperatures`: every product has this one shape, so
#: that a step's temperatures do not depend on how long its run goes on (a product's kernel,
#: and with it the order of its sums, can change with its shape)
ROWS = 32
#: the powers μ^k of a held run are built in blocks of this many steps, ``μ^(jB + i) = μ^(jB) μ^i``:
#: ``exp`` for one block and the block offsets, one product for the rest
POW_BLOCK = 64
#: floor of the exponents of both factors: their product stays above e^−708 (no subnormals, which
#: would slow the product of the basis with the coefficients), and e^−350 is far below round-off
#: of any term that matters
LOG_FLOOR = -350.0


class Modes(NamedTuple):
    """Closed-loop modes ``ξ`` of transitions (leading axis): eigenvalues ``mu`` and whether the
    closed form applies (``ok``); ``rQ2``/``Q2r`` map ``ξ`` to the modal basis of ``Φ`` and back,
    ``Om``/``Xi`` to node temperatures and back."""

    mu: np.ndarray
    ok: np.ndarray
    rQ2: np.ndarray
    Q2r: np.ndarray
    Om: np.ndarray
    Xi: np.ndarray


class Transitions:
    """The distinct transitions of a run's held runs: each run's transition (``index``), the first
    run of each transition (``first``), the runs of each (``members``), the transitions ``M``
    (U, n, n) at their operating points ``ops`` (U,), their modes (:attr:`modes`, computed when
    first asked for) and powers (:meth:`powers`)."""

    def __init__(self, d: Discrete, index: np.ndarray, first: np.ndarray, members: list[np.ndarray],
                 M: np.ndarray, ops: np.ndarray) -> None:
        self.d, self.index, self.first, self.members, self.M, self.ops = d, index, first, members, M, ops
        self._modes: Modes | None = None

    @property
    def modes(self) -> Modes:
        """The closed-loop modes of every transition (:func:`closed_loop_modes`)."""
        if self._modes is None:
            self._modes = closed_loop_modes(self.d, self.ops, self.M)
        return self._modes

    def powers(self, u: int) -> np.ndarray:
        """``M^1 .. M^B`` (B, n, n) of transition ``u``, ``B =`` :data:`POWERS`, by doubling:
        ``[M .. M^m]`` stacked on top of each other times ``M^m``, one product each. Not kept:
        a few hundred kilobytes per transition, which the allocator reuses from one to the next."""
        n = self.M.shape[1]
        pw = np.empty((POWERS, n, n))
        pw[0] = self.M[u]
        m = 1
        while m < POWERS:
            k = min(m, POWERS - m)
            np.matmul(pw[:k].reshape(k * n, n), pw[m - 1], out=pw[m: m + k].reshape(k * n, n))
            m += k
        return pw


def closed_loop_modes(d: Discrete, ops: np.ndarray, M: np.ndarray) -> Modes:
    """Eigendecomposition of the transitions ``M`` (U, n, n) at operating points ``ops`` (U,):
    in the modal basis of ``Φ``, ``diag(r)^-1 V⁻¹ M V diag(r)`` with ``r = √phi`` is symmetric
    (up to round-off) when no loss law couples nodes; ``ok`` is False where it is not, or where
    an eigenvalue falls outside (0, 1)."""
    V, Vi = d.basis(ops)  # modal basis of Φ at each operating point
    r = np.sqrt(d.phi[ops])
    Sym = (Vi @ M @ V) * r[:, None, :] / r[:, :, None]
    asym = np.max(np.abs(Sym - np.swapaxes(Sym, -1, -2)), axis=(1, 2)) / np.max(np.abs(Sym), axis=(1, 2))
    mu, Q2 = np.linalg.eigh((Sym + np.swapaxes(Sym, -1, -2)) / 2.0)
    ok = (asym < 1e-9) & (mu.min(axis=1) > -1e-12) & (mu.max(axis=1) < 1.0)
    rQ2 = r[:, :, None] * Q2
    Q2r = np.swapaxes(Q2, -1, -2) / r[:, None, :]
    # modes far faster than the step (e^(λ dt) below round-off) are zero after one step
    return Modes(mu=np.maximum(mu, 1e-300), ok=ok, rQ2=rQ2, Q2r=Q2r, Om=V @ rQ2, Xi=Q2r @ Vi)


def transitions(d: Discrete, GP: np.ndarray, tv: np.ndarray, ops: np.ndarray, slopes: np.ndarray,
                starts: np.ndarray) -> Transitions:
    """Group the held runs starting at steps ``starts`` by their transition
    ``M = Φ + Γ_P ∂P/∂T`` (operating point and loss slopes: a set point met again) and decompose
    each distinct one.

    Parameters
    ----------
    d : Discrete
        The run's discretisation.
    GP : ndarray (K, n, nl)
        ``Γ_P`` at each operating point, K/W.
    tv : ndarray of int
        The nodes whose temperatures the loss laws read.
    ops : ndarray (steps,)
        Operating point of each step.
    slopes : ndarray (steps, nl, len(tv))
        ``∂P/∂T`` of each step, W/K.
    starts : ndarray of int
        First step of each run.
    """
    o = ops[starts]
    M = d.Phi[o].copy()
    if len(tv):
        M[:, :, tv] += GP[o] @ slopes[starts]
    seen: dict[bytes, int] = {}
    index = np.array([seen.setdefault(m.tobytes(), len(seen)) for m in M], dtype=np.intp)
    first = np.unique(index, return_index=True)[1]
    members = np.split(np.argsort(index, kind="stable"), np.cumsum(np.bincount(index))[:-1])
    return Transitions(d, index, first, members, M[first], o[first])


def power_basis(logmu: np.ndarray, L: int, out: np.ndarray) -> np.ndarray:
    """``μ^k`` for ``k = 1 .. L`` (len(mu), L) into ``out`` (len(mu), ≥ L rounded up to
    :data:`POW_BLOCK`), from ``log μ``; returns the view of the ``L`` columns.

    In blocks: ``exp`` for one block and the block offsets, one product for the rest
    (``μ^(jB + i) = μ^(jB) μ^i``); exponents below :data:`LOG_FLOOR` are floored.

    >>> out = np.empty((1, 64))
    >>> np.round(power_basis(np.log(np.array([0.5])), 3, out), 12).tolist()
    [[0.5, 0.25, 0.125]]
    """
    nb = -(-L // POW_BLOCK)
    blocks = out[:, : nb * POW_BLOCK].reshape(len(logmu), nb, POW_BLOCK)
    first = np.exp(np.maximum(logmu[:, None] * np.arange(1.0, POW_BLOCK + 1.0), LOG_FLOOR))
    offset = np.exp(np.maximum(logmu[:, None] * (POW_BLOCK * np.arange(nb)), LOG_FLOOR))
    np.multiply(offset[:, :, None], first[:, None, :], out=blocks)
    res: np.ndarray = out[:, :L]
    return res


def run_temperatures(powers: np.ndarray, f: np.ndarray, T0: np.ndarray, out: np.ndarray) -> None:
    """The temperatures of a held run from its transition's powers ``M^1 .. M^B`` (B, n, n), its
    forcing ``f`` (n,) K a step and ``T0`` (n,) °C at its start: ``out`` (L, n) receives
    ``T[1] .. T[L]`` (see the module docstring)."""
    B, n, _ = powers.shape
    L = len(out)
    c = np.empty((B, n))  # c_i = Σ_{l<i} M^l f, i = 1 .. B
    c[0] = f
    c[1:] = powers[:-1] @ f
    np.cumsum(c, axis=0, out=c)
    nb = -(-L // B)  # blocks, the last one maybe partial
    # the block starts with a trailing 1: [s; 1] → [M^B s + c_B; 1], one product a block
    aug = np.zeros((n + 1, n + 1))
    aug[:n, :n], aug[:n, n], aug[n, n] = powers[-1], c[-1], 1.0
    starts_1 = np.empty((nb, n + 1))
    starts_1[0, :n], starts_1[0, n] = T0, 1.0
    for j in range(nb - 1):
        np.matmul(aug, starts_1[j], out=starts_1[j + 1])
    P2 = powers.transpose(2, 0, 1).reshape(n, B * n)  # column (i, r): row r of M^(i+1)
    S = np.zeros((ROWS, n))
    Y = np.empty((ROWS, B * n))
    for j0 in range(0, nb, ROWS):  # ROWS blocks a product: T[jB + i] = M^i s[j] + c_i
        m = min(ROWS, nb - j0)
        r0 = j0 * B
        r1 = min(L, r0 + m * B)
        S[:m] = starts_1[j0: j0 + m, :n]
        whole = r1 - r0 == ROWS * B  # straight into the output, else through Y
        dest = out[r0:r1].reshape(ROWS, B * n) if whole else Y
        np.matmul(S, P2, out=dest)
        dest.reshape(ROWS, B, n)[:] += c
        if not whole:
            out[r0:r1] = Y.reshape(ROWS * B, n)[: r1 - r0]
