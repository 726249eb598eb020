"""The linear recursion of a stretch of steps with one discretisation, run vectorised in time.

Over steps where the operating point (and so ``Φ``, ``Γ``) stays the same, the simulation and the
sensitivities both follow

    x[k+1] = Φ x[k] + f[k] + Γ_P D[k] x[k][tv]

with a forcing ``f`` known for the whole stretch in advance (inputs, or the sensitivities'
``dΦ T + dΓ w``) and the temperature feedback of affine losses ``D[k] = ∂P/∂T`` at step ``k``
(loss sources × loss nodes; it changes every step when the current does). In the modal basis of
``Φ`` (``Φ = V diag(μ) V⁻¹`` with real ``0 ≤ μ < 1``, :class:`~thermal_edge.lptn.discretise.Discrete`)
the open loop is ``n`` independent first-order filters, run in time by blocked matrix products
over all modes and columns at once, time being the last axis (:func:`modal_scan`), and seen
through the wanted rows only (:func:`scan_rows`).

The feedback is low-rank twice over, and solved exactly (no iteration):

* in space: it reads only the loss nodes, ``y[k] = E x[k]`` with ``E = V[tv]`` (a few rows);
* in time: the series ``D[k]`` has a small rank ``r`` (a copper loss ``∝ i²`` gives
  ``D[k] = i[k]² C``: rank one, recognised without a decomposition), ``D[k] = Σ_ρ s[k, ρ] C_ρ``
  (:func:`time_factors`; terms below round-off of the largest are dropped).

So ``x = x₀ + 𝓛z`` with the open-loop response ``x₀`` and ``z[k] = (s[k, ρ] y[k])_ρ`` fed through
``G C_ρ`` (``G = V⁻¹ Γ_P``). The loss nodes obey ``y = y₀ + E 𝓛 z``: lower block-triangular
in time. It is solved in blocks of :data:`BLOCK` steps: inside a block a unit lower-triangular
system of ``BLOCK · ntv`` unknowns (forward substitution: exact up to round-off, with the same
operations the stepped recursion does, reordered), and the feedback's modal state ``q`` carried
from block to block exactly. With rank one the unknowns are ``w = s ∘ y`` and ``q`` together: the
block's triangular matrix then differs from block to block in its diagonal ``1/s`` only, and a
block costs one triangular solve and one product. Then the wanted rows of ``x₀ + 𝓛z``. What depends on the feedback
alone is set up once per stretch (:class:`Stretch`) and serves the simulation and the
sensitivities alike.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg.blas import dtrsm, dtrsv
from scipy.linalg.lapack import dtrtrs

from .scratch import Scratch

#: shortest stretch of one operating point run vectorised (its set-up costs about this many steps)
MIN_STRETCH = 32
#: steps per block, of the open-loop scan and of the loss nodes' triangular solve alike (the
#: scan's flops grow with it, the passes over the blocks shrink)
BLOCK = 16
#: terms of the feedback's time series below this fraction of the largest are round-off
RANK_TOL = 1e-15
#: a feedback series is taken as rank one (:func:`time_factors`) when no entry differs from the
#: rank-one fit by more than this fraction of the largest: a few roundings of each entry
RANK1_TOL = 1e-14
#: powers ``μ^i`` below this are set to zero: they are far below round-off of any term, and
#: subnormal numbers would slow every product they enter by an order of magnitude
TINY = 1e-280


def powers(mu: np.ndarray, B: int) -> np.ndarray:
    """``μ^i`` (n, B+1) for ``i = 0 .. B``, those below :data:`TINY` set to zero."""
    with np.errstate(under="ignore"):
        pw = mu[:, None] ** np.arange(B + 1)
    pw[pw < TINY] = 0.0
    return pw


def time_factors(D: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``D`` (L, q) as ``s Wt``, ``s`` (L, r), ``Wt`` (r, q): the feedback's series in time.

    One current feeding every copper law makes every row a multiple of the largest one: then
    ``r = 1`` (checked entry by entry against :data:`RANK1_TOL`, without a decomposition);
    otherwise the terms of the singular value decomposition above :data:`RANK_TOL` of the largest.

    >>> s, Wt = time_factors(np.outer([1.0, 2.0, 0.0], [3.0, 4.0]))
    >>> s.shape, np.allclose(s @ Wt, [[3, 4], [6, 8], [0, 0]])
    ((3, 1), True)
    """
    big = float(np.max(np.abs(D))) if D.size else 0.0
    if big == 0.0:
        return np.zeros((len(D), 0)), np.zeros((0, D.shape[1]))
    row = D[int(np.argmax(np.max(np.abs(D), axis=1)))]
    s = D @ (row / (row @ row))
    if np.max(np.abs(D - s[:, None] * row)) <= RANK1_TOL * big:
        return s[:, None], row[None, :]
    U_, sv, Wt = np.linalg.svd(D, full_matrices=False)
    r = int(np.count_nonzero(sv > RANK_TOL * sv[0]))
    return U_[:, :r] * sv[:r], Wt[:r]


def padded_length(L: int) -> int:
    """The stretch's length rounded up to whole blocks: the time axis :meth:`Stretch.solve` wants."""
    return L if L <= BLOCK else -(-L // BLOCK) * BLOCK


def _toeplitz(pw: np.ndarray, B: int) -> np.ndarray:
    """``μ^(i−l)`` for ``i ≥ l`` (else 0) per mode, as (n, l, i)."""
    i = np.arange(B)
    lag = i[None, :] - i[:, None]
    out: np.ndarray = np.where(lag >= 0, pw[:, np.maximum(lag, 0)], 0.0)
    return out


#: the block filters of a stretch's scans by level (0: the steps, 1: the block starts, ...):
#: block length, powers and Toeplitz matrix, built once per stretch for all its scans
FilterCache = dict[int, tuple[int, np.ndarray, np.ndarray]]


def _filters(mu: np.ndarray, B: int, cache: FilterCache | None, level: int) -> tuple[np.ndarray, np.ndarray]:
    """``powers(mu, B)`` and its block filter ``_toeplitz``, from ``cache`` when built for this level and ``B``."""
    if cache is not None and level in cache and cache[level][0] == B:
        return cache[level][1], cache[level][2]
    pw = powers(mu, B)
    toe = _toeplitz(pw, B)
    if cache is not None:
        cache[level] = (B, pw, toe)
    return pw, toe


def modal_scan(mu: np.ndarray, f: np.ndarray, x0: np.ndarray, cache: FilterCache | None = None,
               level: int = 0) -> np.ndarray:
    """``x[k+1] = μ ∘ x[k] + f[k]``, ``k = 0 .. L−1``, for all modes and columns at once.

    In blocks of :data:`BLOCK` steps: inside a block, each mode's response to the block's
    forcing is one product with the lower-triangular Toeplitz matrix of ``μ^(i−l)`` (one matrix
    product per mode over all blocks and columns, time being the last axis); the states at the
    block starts follow the same recursion with ``μ^BLOCK`` over the blocks' end values (this
    function, one level up).

    Parameters
    ----------
    mu : ndarray (n,)
        Eigenvalues of the transition (dimensionless, in [0, 1)).
    f : ndarray (n, c, L)
        Forcing per mode, column and step (the units of ``x``).
    x0 : ndarray (n, c)
        State at the stretch's first step.
    cache, level : optional
        The block filters already built (:data:`FilterCache`) and this scan's level in it.

    Returns
    -------
    ndarray (n, c, L)
        ``x[1] .. x[L]``.
    """
    n, c, L = f.shape
    B = BLOCK if L > BLOCK else L
    nb = -(-L // B)
    if nb * B != L:
        f = np.concatenate([f, np.zeros((n, c, nb * B - L))], axis=2)
    pw, toe = _filters(mu, B, cache, level)
    out = np.matmul(f.reshape(n, c * nb, B), toe)  # zero-state response inside each block
    starts = _block_starts(pw, out[:, :, B - 1].reshape(n, c, nb), x0, cache, level + 1)
    out += starts.reshape(n, c * nb, 1) * pw[:, None, 1:]
    res: np.ndarray = out.reshape(n, c, nb * B)[:, :, :L]
    return res


def _block_starts(pw: np.ndarray, ends: np.ndarray, x0: np.ndarray, cache: FilterCache | None = None,
                  level: int = 1) -> np.ndarray:
    """The states (n, c, nb) at the start of each block from the blocks' zero-state end values
    ``ends`` (n, c, nb) and ``x0``: ``s[j+1] = μ^B s[j] + ends[j]`` (a scan at ``level``)."""
    n, c, nb = ends.shape
    starts = np.empty((n, c, nb))
    starts[:, :, 0] = x0
    if nb > 1:
        starts[:, :, 1:] = modal_scan(pw[:, -1], ends[:, :, :-1], x0, cache, level)
    return starts


def scan_rows(mu: np.ndarray, f: np.ndarray, x0: np.ndarray, R: np.ndarray,
              L: int, work: Scratch | None = None,
              cache: FilterCache | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`modal_scan` seen through rows: ``R x[1] .. R x[L]`` and ``x[L]``, without the states.

    The blocks' responses to their own forcing are computed for every mode (one product per
    mode), projected on the rows in one product; the part of each block's start state goes to
    the rows directly (``R diag(μ^(i+1))``, a small product), not through every mode and step.

    Parameters
    ----------
    mu : ndarray (n,)
        Eigenvalues (dimensionless, in [0, 1)).
    f : ndarray (n, c, padded_length(L))
        Forcing per mode, column and step, zero after step ``L``.
    x0 : ndarray (n, c)
        State at the first step.
    R : ndarray (nr, n)
        The rows wanted.
    L : int
        Steps.
    work : Scratch, optional
        Where the blocks' responses go (a new array without).
    cache : FilterCache, optional
        The block filters of every level, kept from one scan of a stretch to the next.

    Returns
    -------
    rows : ndarray (nr, c, nb, B)
        ``R x[1] .. R x[Lp]`` in blocks (steps past ``L`` are not meaningful).
    end : ndarray (n, c)
        ``x[L]``.
    """
    n, c, Lp = f.shape
    B = min(BLOCK, Lp)
    nb, nr = Lp // B, R.shape[0]
    pw, toe = _filters(mu, B, cache, 0)
    inner = np.matmul(f.reshape(n, c * nb, B), toe,  # zero-state response inside each block
                      out=None if work is None else work.get("scan", (n, c * nb, B)))
    starts = _block_starts(pw, inner[:, :, B - 1].reshape(n, c, nb), x0, cache)
    if 2 * nr >= n:  # most of the state: the start states into the blocks' responses, then one projection
        inner += starts.reshape(n, c * nb, 1) * pw[:, None, 1:]
        rows = (R @ inner.reshape(n, c * Lp)).reshape(nr, c, nb, B)
        return rows, inner.reshape(n, c, Lp)[:, :, L - 1].copy()
    rows = (R @ inner.reshape(n, c * Lp)).reshape(nr, c, nb, B)
    # R diag(μ^(i+1)) with rows (r, i), so that each block's B steps come out contiguous
    Rp = (R[:, None, :] * pw.T[None, 1:, :]).reshape(nr * B, n)
    rows += (starts.reshape(n, c * nb).T @ Rp.T).reshape(c, nb, nr, B).transpose(2, 0, 1, 3)
    jL, iL = divmod(L - 1, B)
    end = inner.reshape(n, c, Lp)[:, :, L - 1] + pw[:, iL + 1, None] * starts[:, :, jL]
    return rows, end


class Stretch:
    """``x[k+1] = μ ∘ x[k] + f[k] + G D[k] E x[k]`` over a stretch (see the module docstring).

    What depends on the feedback only (its rank, the blocks' triangular matrices) is built once
    and serves every :meth:`solve` (the simulation's temperatures and the sensitivities).

    Parameters
    ----------
    mu : ndarray (n,)
        Eigenvalues of the transition (dimensionless, in [0, 1)).
    G : ndarray (n, nl)
        ``V⁻¹ Γ_P``: how each loss source enters the modes.
    E : ndarray (ntv, n)
        ``V[tv]``: the loss nodes' temperatures from the modes.
    D : ndarray (L, nl, ntv)
        ``∂P/∂T`` at each step (W/K).
    live : ndarray of int, optional
        The entries of ``D[k]`` (flat, ``nl · ntv``) that can be nonzero (the temperatures each
        loss law reads); default: those nonzero somewhere in ``D``.
    """

    def __init__(self, mu: np.ndarray, G: np.ndarray, E: np.ndarray, D: np.ndarray,
                 live: np.ndarray | None = None) -> None:
        self.mu, self.E, self.L = np.maximum(mu, 0.0), E, D.shape[0]
        self.states: np.ndarray | None = None  # the last solve's states, when asked for
        self._rank_one: tuple[np.ndarray, np.ndarray] | None = None  # a rank-one block's matrix and carry
        n, ntv, L = len(mu), E.shape[0], D.shape[0]
        self.Lp = padded_length(L)
        B = self.B = min(BLOCK, self.Lp)
        nblk = self.nblk = self.Lp // B
        self.filters: FilterCache = {}  # what every scan of the stretch uses
        self.pw = _filters(self.mu, B, self.filters, 0)[0].T  # (B+1, n)
        D2 = D.reshape(L, -1)
        # a loss law reads one node or a few: most entries are zero
        cols = np.nonzero(np.any(D2 != 0.0, axis=0))[0] if live is None else live
        self.r = 0
        if not len(cols):
            return
        s_, Wt = time_factors(D2[:, cols])
        r = self.r = s_.shape[1]
        if not r:  # the live entries are zero all along (no current)
            return
        Wfull = np.zeros((r, D2.shape[1]))
        Wfull[:, cols] = Wt
        GC = self.GC = np.concatenate([G @ Wfull[k].reshape(D.shape[1], ntv) for k in range(r)], axis=1)  # (n, r ntv)
        sp = np.zeros((nblk * B, r))
        sp[:L] = s_
        spb = self.spb = sp.reshape(nblk, B, r)
        pw = self.pw
        BT = B * ntv
        i = np.arange(B)
        lag = i[:, None] - 1 - i[None, :]  # m = i − 1 − l for l < i
        # each block's unit lower-triangular system for its loss-node values (B ntv unknowns):
        # y_i − Σ_{l<i} E diag(μ^(i−1−l)) G Σ_ρ s[l, ρ] C_ρ y_l = y₀_i + E diag(μ^i) q, the
        # matrix −Σ_ρ H_ρ diag(s_ρ) with H_ρ the same for every block (built per block in the loop:
        # keeping them all would hold B ntv² numbers a step, ~20 MB for 3 h)
        K = (E[None] * pw[:B, None, :]) @ GC  # (B, ntv, r ntv): E diag(μ^m) G C
        He = np.where((lag >= 0)[:, None, :, None], K[np.maximum(lag, 0)].transpose(0, 2, 1, 3), 0.0)
        self.Hneg = -np.ascontiguousarray(He.reshape(B, ntv, B, r, ntv).transpose(3, 0, 1, 2, 4)).reshape(r, BT, BT)
        # a block's right-hand side y₀ + E diag(μ^i) q, and in one product from [q; y] the next
        # block's start μ^B q + Σ_l diag(μ^(B−1−l)) G Σ_ρ s[l, ρ] C_ρ y_l
        self.EpT = (E[None] * pw[:B, None, :]).reshape(BT, n).T.copy()  # (n, BT)
        Rl = (pw[B - 1:: -1][:B, None, :] * GC.T[None]).reshape(B, r, ntv, n).transpose(1, 0, 2, 3).reshape(r, BT, n)
        if r == 1:
            # one series (one current feeds every copper law): the feedback's inputs w = s ∘ y
            # solve (diag(1/s) + Hneg) w = y₀ + E diag(μ^i) q, the next start is μ^B q + Rl w.
            # Only the diagonal changes from block to block: no matrix to scale per block. A step
            # without feedback (s = 0) has 1/s = inf on the diagonal, and its w is exactly 0
            with np.errstate(divide="ignore"):
                self.inv_s = np.repeat(1.0 / spb[:, :, 0], ntv, axis=1)  # (nblk, BT)
            self.Rl1 = Rl[0]  # (BT, n)
            return
        # s[l, ρ] per unknown (l, b) of each block
        self.scol = np.ascontiguousarray(np.repeat(spb.transpose(2, 0, 1), ntv, axis=2))  # (ρ, nblk, BT)
        # both scaled by the block's s[l, ρ] over the unknowns l: stacked, one product a block
        # gives the block's matrix (first BT rows) and its carry (the rest, transposed)
        self.HR = np.ascontiguousarray(np.concatenate([self.Hneg, Rl.transpose(0, 2, 1)], axis=1))  # (ρ, BT + n, BT)
        # one product of the start state q gives the block's right-hand side part and μ^B q
        self.G = np.ascontiguousarray(np.concatenate([self.EpT, np.diag(pw[B])], axis=1))  # (n, BT + n)

    def solve(self, f: np.ndarray, x0: np.ndarray, W: np.ndarray,
              work: Scratch | None = None, states: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The recursion from ``x[0] = x0`` under the forcing ``f``.

        Parameters
        ----------
        f : ndarray (n, c, L) or (n, c, padded_length(L))
            Forcing per mode, column and step (zero past ``L`` when padded: cheaper, no copy).
        x0 : ndarray (n, c)
            State at the stretch's first step.
        W : ndarray (nr, n)
            The rows wanted at every step, from the modes.
        work : Scratch, optional
            Buffers for the large temporaries (reused from one stretch to the next).
        states : bool, optional
            Keep the states ``x[1] .. x[Lp]`` (n, c, Lp) as :attr:`states` (when ``W`` has most
            of the state's rows: the simulation, whose modal temperatures the sensitivities'
            forcing reads).

        Returns
        -------
        rows : ndarray (nr, c, L)
            ``W x[1] .. W x[L]``.
        end : ndarray (n, c)
            ``x[L]``.
        """
        n, c, _ = f.shape
        L, Lp, B, nblk = self.L, self.Lp, self.B, self.nblk
        if f.shape[2] != Lp:
            f = np.concatenate([f, np.zeros((n, c, Lp - f.shape[2]))], axis=2)
        E = self.E
        ntv, nr = E.shape[0], W.shape[0]
        few = 2 * nr < n
        if not self.r:
            if states and not few:
                return self._states_seen(f, x0, W)
            rows, end = scan_rows(self.mu, f, x0, W, L, work, self.filters)
            return rows.reshape(nr, c, Lp)[:, :, :L], end
        # few rows (the sensors): the open loop seen through them and the loss nodes, the
        # feedback's part added from the blocks' inputs; most of the state (the simulation): the
        # loss nodes' open loop only, then the whole recursion again with the feedback's inputs
        # added to the forcing (one projection on the rows instead of two)
        both, end = scan_rows(self.mu, f, x0, np.concatenate([W, E]) if few else E, L, work, self.filters)
        ye = both[nr:] if few else both
        m, BT = self.r * ntv, B * ntv
        # per block [q | y₀]: the feedback's modal state at its start (filled block by block) and
        # the open-loop loss-node values y₀[k] = E x₀[k], k = 0 .. L−1, columns first
        Zb = np.zeros((nblk + 1, c, n + BT))
        yk = np.moveaxis(Zb[:nblk, :, n:].reshape(nblk, c, B, ntv), 2, 1)  # (nblk, B, c, ntv), a view
        ye = ye.transpose(2, 3, 1, 0)  # (nblk, B, c, ntv): E x[k + 1] at k = j B + i
        yk[0, 0] = (E @ x0).T
        yk[:, 1:] = ye[:, :-1]
        yk[1:, 0] = ye[:-1, -1]
        z, qs = self._blocks(Zb)
        pw = self.pw
        if not few:
            u = self.GC @ z.reshape(nblk, c, B, m).transpose(3, 1, 0, 2).reshape(m, c * Lp)  # (n, c Lp)
            u += f.reshape(n, c * Lp)
            if states:
                return self._states_seen(u.reshape(n, c, Lp), x0, W)
            rows, end = scan_rows(self.mu, u.reshape(n, c, Lp), x0, W, L, work, self.filters)
            return rows.reshape(nr, c, Lp)[:, :, :L], end
        rows = both[:nr]  # (nr, c, nblk, B)
        # the feedback's part of the wanted rows: from each block's start state and inside the block
        Wp = (W[:, None, :] * pw[None, 1: B + 1, :]).reshape(nr * B, n)  # W diag(μ^(i+1)), rows (r, i)
        fb = qs.reshape(nblk * c, n) @ Wp.T  # (nblk c, nr B): each block's steps contiguous
        fb += z.reshape(nblk * c, B * m) @ _inputs_to_rows(W, pw, self.GC, B).T  # W diag(μ^(i−l)) G C, l ≤ i
        rows += fb.reshape(nblk, c, nr, B).transpose(2, 1, 0, 3)
        jL, iL = divmod(L - 1, B)
        # the state at step L: the feedback's from its block's start and the inputs of that block up to L
        carry = pw[iL:: -1][: iL + 1, :, None] * self.GC[None]  # diag(μ^(iL−l)) G C, l = 0 .. iL
        end_fb = pw[iL + 1][:, None] * qs[jL].T + np.tensordot(carry, z[jL].reshape(c, B, m)[:, : iL + 1], axes=([0, 2], [1, 2]))
        return rows.reshape(nr, c, Lp)[:, :, :L], end + end_fb

    def _states_seen(self, f: np.ndarray, x0: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The open loop under ``f`` (n, c, Lp) from ``x0``, its states kept as :attr:`states`; the
        rows ``W x[1] .. W x[L]`` and ``x[L]``."""
        xs = self.states = modal_scan(self.mu, f, x0, self.filters)
        n, c, Lp = xs.shape
        rows = (W @ xs.reshape(n, c * Lp)).reshape(len(W), c, Lp)[:, :, : self.L]
        return rows, xs[:, :, self.L - 1].copy()

    def _blocks(self, Zb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The loss nodes' block-triangular system, block after block, from ``Zb``
        (nblk + 1, c, n + B ntv): per block ``[q | y₀]``, ``q`` zero, ``y₀`` the open-loop values
        (overwritten). Returns the feedback's inputs ``z = s[l, ρ] y_l`` (nblk, c, B r ntv), per
        step ρ-major, and its modal states ``q`` (nblk, c, n) at the blocks' starts."""
        nblk = len(Zb) - 1
        n, BT = self.EpT.shape
        if self.r == 1:
            # [q; w] of a block solve one lower-triangular system, [[I, 0], [−E diag(μ^i), diag(1/s)
            # + Hneg]] [q; w] = [q; y₀] (the start state's part of the right-hand side taken by
            # the solve itself), and the next start is [q | w] [[diag(μ^B)], [Rl]]: two calls a block
            if self._rank_one is None:  # built once per stretch; each block rewrites the diagonal
                M = np.zeros((n + BT, n + BT))
                M[:n, :n] = np.eye(n)
                M[n:, :n] = -self.EpT.T
                M[n:, n:] = self.Hneg[0]
                self._rank_one = (M, np.concatenate([np.diag(self.pw[-1]), self.Rl1]))  # carry (n + BT, n)
            M, carry = self._rank_one
            diag = M.reshape(-1)[n * (n + BT + 1):: n + BT + 1]  # the diagonal of the lower-right block
            # BLAS directly, in place ([q | s ∘ y]), and np.dot into contiguous rows: per block
            # the calls' overhead is most of the cost
            Mt = M.T
            if Zb.shape[1] == 1:
                rows = Zb[:, 0]  # (nblk + 1, n + BT)
                for j, inv_s in enumerate(self.inv_s):
                    diag[:] = inv_s
                    dtrsv(Mt, rows[j], lower=0, trans=1, overwrite_x=1)
                    np.dot(rows[j], carry, out=rows[j + 1, :n])
            else:
                nxt = np.empty((Zb.shape[1], n))
                for j, inv_s in enumerate(self.inv_s):
                    diag[:] = inv_s
                    dtrsm(1.0, Mt, Zb[j].T, lower=0, trans_a=1, overwrite_b=1)
                    np.dot(Zb[j], carry, out=nxt)
                    Zb[j + 1, :, :n] = nxt
            return Zb[:nblk, :, n:], Zb[:nblk, :, :n]
        y = np.ascontiguousarray(Zb[:nblk, :, n:])
        c = y.shape[1]
        Q = np.zeros((nblk + 1, c, n))
        G, HR, scol = self.G, self.HR, self.scol
        tmp = np.empty((c, BT + n))
        HRs = np.empty(HR.shape[1:])  # the block's matrix A (rows :BT) and carry (rows BT:, transposed)
        A, Rs = HRs[:BT], HRs[BT:].T  # A.T is A in Fortran order, for LAPACK
        for j in range(nblk):
            np.multiply(HR[0], scol[0, j], out=HRs)  # the unit diagonal of A is implied (unitdiag)
            for k in range(1, self.r):
                HRs += HR[k] * scol[k, j]
            np.matmul(Q[j], G, out=tmp)
            y[j] += tmp[:, :BT]
            dtrtrs(A.T, y[j].T, lower=0, trans=1, unitdiag=1, overwrite_b=1)  # in place
            np.matmul(y[j], Rs, out=Q[j + 1])
            Q[j + 1] += tmp[:, BT:]
        Yb = y.reshape(nblk, c, self.B, BT // self.B)
        z: np.ndarray = (self.spb[:, None, :, :, None] * Yb[:, :, :, None, :]).reshape(nblk, c, -1)  # s[l, ρ] y_l
        return z, Q[:nblk]


def solve_stretch(mu: np.ndarray, f: np.ndarray, x0: np.ndarray, G: np.ndarray, E: np.ndarray,
                  D: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``x[k+1] = μ ∘ x[k] + f[k] + G D[k] E x[k]`` over a stretch: :meth:`Stretch.solve` once.

    Parameters
    ----------
    mu, G, E, D : see :class:`Stretch`.
    f, x0, W : see :meth:`Stretch.solve`.

    Returns
    -------
    rows : ndarray (nr, c, L)
        ``W x[1] .. W x[L]``.
    end : ndarray (n, c)
        ``x[L]``.
    """
    return Stretch(mu, G, E, D).solve(f, x0, W)


def _inputs_to_rows(W: np.ndarray, pw: np.ndarray, GC: np.ndarray, B: int) -> np.ndarray:
    """``W diag(μ^(i−l)) G C`` for ``l ≤ i`` (the state after step ``i`` of the block from input ``l``),
    as (nr B, B m), rows (r, i)."""
    i = np.arange(B)
    lag = i[:, None] - i[None, :]
    K = (W[None] * pw[:B, None, :]) @ GC  # (lag, nr, m)
    full = np.where((lag >= 0)[None, :, :, None], K[np.maximum(lag, 0)].transpose(2, 0, 1, 3), 0.0)  # (nr, i, l, m)
    return full.reshape(W.shape[0] * B, B * GC.shape[1])


class NodeStretch:
    """A stretch at one operating point in node coordinates: ``x[k+1] = (Φ + Γ_P D[k] E_tv) x[k] + V f[k]``.

    Parameters
    ----------
    V, Vi : ndarray (n, n)
        The modal basis ``V`` of ``Φ`` and ``V⁻¹`` at the operating point.
    mu : ndarray (n,)
        The eigenvalues ``μ`` of ``Φ``.
    GP : ndarray (n, nl)
        ``Γ_P``, K/W.
    tv : ndarray of int (ntv,)
        Nodes whose temperatures the loss laws read.
    D : ndarray (L, nl, ntv)
        ``∂P/∂T`` at each step, W/K.
    live : ndarray of int, optional
        The entries of ``D[k]`` that can be nonzero (see :class:`Stretch`).
    """

    def __init__(self, V: np.ndarray, Vi: np.ndarray, mu: np.ndarray, GP: np.ndarray, tv: np.ndarray,
                 D: np.ndarray, live: np.ndarray | None = None) -> None:
        self.V, self.Vi = V, Vi
        self.core = Stretch(mu, Vi @ GP, V[tv], D, live)
        #: ``V⁻¹ x[0] .. V⁻¹ x[L−1]`` (n, c, L) of the last solve asked to keep them
        self.modal: np.ndarray | None = None

    def solve(self, f: np.ndarray, x0: np.ndarray, keep: np.ndarray | None = None,
              work: Scratch | None = None, states: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The stretch from ``x0``.

        Parameters
        ----------
        f : ndarray (n, c, L)
            The forcing of every step in the modal basis of ``Φ``.
        x0 : ndarray (n, c)
            State in node coordinates at the stretch's start.
        keep : ndarray of int, optional
            The nodes wanted at every step (default all).
        work : Scratch, optional
            Buffers for the large temporaries.
        states : bool, optional
            Keep the states of every step in the modal basis as :attr:`modal` (all nodes
            wanted only: the simulation's temperatures, which the sensitivities' forcing reads
            in that basis).

        Returns
        -------
        rows : ndarray (len(keep), c, L)
            ``x[1] .. x[L]`` at the ``keep`` nodes.
        end : ndarray (n, c)
            ``x[L]`` at every node.
        """
        W = self.V if keep is None else self.V[keep]
        xm0 = self.Vi @ x0
        rows, end = self.core.solve(f, xm0, W, work, states and keep is None)
        if states and keep is None:
            assert self.core.states is not None
            L = self.core.L
            self.modal = np.concatenate([xm0[:, :, None], self.core.states[:, :, : L - 1]], axis=2)
        return rows, self.V @ end


def stretches(ops: np.ndarray, eligible: np.ndarray, min_len: int = MIN_STRETCH) -> list[tuple[int, int]]:
    """Maximal runs ``(a, b)`` of steps ``a .. b−1``, all ``eligible`` and at one operating point,
    at least ``min_len`` long.

    >>> stretches(np.array([0, 0, 0, 1, 1, 0]), np.array([True, True, True, True, False, True]), 2)
    [(0, 3)]
    """
    cut = np.ones(len(ops) + 1, dtype=bool)
    cut[1:-1] = (ops[1:] != ops[:-1]) | (eligible[1:] != eligible[:-1])
    bounds = np.nonzero(cut)[0]
    return [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:]) if eligible[a] and b - a >= min_len]


def varying_steps(D: np.ndarray, window: int = MIN_STRETCH, may_change: np.ndarray | None = None) -> np.ndarray:
    """Steps (L,) whose neighbourhood of ``window`` steps has the feedback ``D`` (L, ...) change on
    at least a quarter of its steps: where a noisy current makes a transition per step. Elsewhere
    (held inputs) one transition serves many steps and the closed form or the step-by-step
    recursion is cheaper than the vectorised stretch.

    ``may_change`` (L,), optional, marks the steps whose ``D`` can differ from the previous
    step's (the others hold their inputs: only these are compared).

    >>> varying_steps(np.array([1.0, 2, 3, 4, 4, 4, 4, 4]), window=4).tolist()
    [True, True, True, True, True, True, False, False]
    """
    L = len(D)
    change = np.zeros(L)
    if L > 1:
        if may_change is None or 4 * np.count_nonzero(may_change) > L:  # most steps: compare them all
            change[1:] = np.any((D[1:] != D[:-1]).reshape(L - 1, -1), axis=1)
        else:
            k = np.nonzero(may_change[1:])[0] + 1
            change[k] = np.any((D[k] != D[k - 1]).reshape(len(k), int(np.prod(D.shape[1:]))), axis=1)
    # changes among the steps k − window/2 .. k + window/2 − 1 (clipped at the ends)
    cs = np.concatenate([[0.0], np.cumsum(change)])
    k = np.arange(L)
    lo, hi = np.clip(k - window // 2, 0, L), np.clip(k + (window - window // 2), 0, L)
    busy: np.ndarray = 4 * (cs[hi] - cs[lo]) >= window
    return busy


def covered(spans: list[tuple[int, int]], steps: int) -> np.ndarray:
    """Boolean mask (steps,) of the steps inside ``spans``."""
    mask = np.zeros(steps, dtype=bool)
    for a, b in spans:
        mask[a:b] = True
    return mask
