"""Per-step transition matrices ``M_k = Φ(u_k) + Γ_P(u_k) ∂P/∂T_k``, built a block at a time.

Steps with the same operating point and the same loss slopes share one matrix (a drive cycle
holds its inputs over a segment). Inputs that change every sample (a measured speed and current)
make a distinct matrix per step: ``n²`` numbers each, about 130 MB for 3 h at 1 Hz of a
39-node network. Only the index of each step's matrix and the few numbers that define it
(operating point, slopes) are kept for the whole run; the matrices themselves are computed
:data:`CHUNK` at a time when a step needs them and dropped when the next block is asked for,
so the memory is bounded by the block, not by the run. Each matrix is computed by the same
operations whichever block it falls in: the results do not depend on the block size.
"""
from __future__ import annotations

from collections.abc import Iterator

import numpy as np

#: distinct matrices computed at once (``CHUNK · n² · 8`` bytes: 3 MB for 39 nodes)
CHUNK = 256


class StepMatrices:
    """The transition matrix of every step of a run, computed in blocks of distinct matrices.

    Parameters
    ----------
    Phi : ndarray (K, n, n)
        Open-loop transition at each operating point.
    GP : ndarray (K, n, nl)
        Input matrix of the losses at each operating point, K/W.
    tv : ndarray of int
        The nodes whose temperatures the loss laws read.
    ops : ndarray (steps,)
        Operating point of each step.
    dPdT : ndarray (steps, nl, len(tv))
        Loss slopes ``∂P/∂T`` at each step, W/K.
    need : ndarray of bool (steps,), optional
        Steps that get a matrix (default all); asking for another step's is an error.
    chunk : int, optional
        Distinct matrices computed at once (default :data:`CHUNK`).
    """

    def __init__(self, Phi: np.ndarray, GP: np.ndarray, tv: np.ndarray, ops: np.ndarray, dPdT: np.ndarray,
                 need: np.ndarray | None = None, chunk: int | None = None) -> None:
        steps = len(ops)
        self.Phi, self.GP, self.tv = Phi, GP, np.asarray(tv, dtype=int)
        self.chunk = max(int(CHUNK if chunk is None else chunk), 1)
        self._cached: tuple[int, list[np.ndarray]] | None = None
        if not len(self.tv) or not np.any(dPdT) or not steps:
            # no temperature feedback: the open-loop matrix of each operating point, all at once
            self._fixed: list[np.ndarray] | None = [Phi[o] for o in range(Phi.shape[0])]
            self.index = np.asarray(ops, dtype=np.intp)
            self._local: list[int] = self.index.tolist()
            self._cuts = np.zeros(0, dtype=np.intp)
            return
        self._fixed = None
        ks = np.arange(steps) if need is None else np.nonzero(need[:steps])[0]
        slopes = dPdT[ks].reshape(len(ks), int(np.prod(dPdT.shape[1:])))
        on = ops[ks]
        # a new matrix where the operating point or the slopes change from the previous needed step
        change = np.ones(len(ks), dtype=bool)
        change[1:] = (on[1:] != on[:-1]) | np.any(slopes[1:] != slopes[:-1], axis=1)
        starts = np.nonzero(change)[0]
        self._ops = on[starts]
        self._slopes = slopes[starts].reshape(len(starts), dPdT.shape[1], len(self.tv))
        index = np.full(steps, -1, dtype=np.intp)
        index[ks] = np.cumsum(change) - 1
        self.index = index
        block = np.where(index >= 0, index // self.chunk, -1)
        self._block = block
        self._local = np.where(index >= 0, index % self.chunk, -1).tolist()
        self._cuts = np.nonzero(block[1:] != block[:-1])[0] + 1  # steps where the block changes

    def __len__(self) -> int:
        """Number of distinct matrices of the run."""
        return len(self._fixed) if self._fixed is not None else len(self._ops)

    def _matrices(self, c: int) -> list[np.ndarray]:
        """Block ``c`` of the distinct matrices (the last one asked for is kept)."""
        if self._fixed is not None:
            return self._fixed
        if c < 0:
            raise IndexError("a step without a transition matrix (run vectorised) was asked for one")
        if self._cached is not None and self._cached[0] == c:
            return self._cached[1]
        self._cached = None  # drop the previous block before building the next
        j0, j1 = c * self.chunk, min((c + 1) * self.chunk, len(self._ops))
        o = self._ops[j0:j1]
        mats = self.Phi[o].copy()  # (block, n, n)
        mats[:, :, self.tv] += self.GP[o] @ self._slopes[j0:j1]
        block = list(mats)
        self._cached = (c, block)
        return block

    def matrix(self, k: int) -> np.ndarray:
        """The transition matrix of step ``k``."""
        if self._fixed is not None:
            return self._fixed[self._local[k]]
        return self._matrices(int(self._block[k]))[self._local[k]]

    def segments(self, a: int, b: int) -> Iterator[tuple[int, int, list[np.ndarray], list[int]]]:
        """Steps ``a .. b−1`` in pieces ``(lo, hi, mats, local)`` whose matrices lie in one block:
        step ``k`` of a piece has the matrix ``mats[local[k]]`` (``local`` indexed by step)."""
        if a >= b:
            return
        if self._fixed is not None:
            yield a, b, self._fixed, self._local
            return
        lo, hi = np.searchsorted(self._cuts, [a, b], side="right")
        bounds = [a, *self._cuts[lo:hi].tolist(), b]
        for s, e in zip(bounds[:-1], bounds[1:]):
            if s < e:
                yield s, e, self._matrices(int(self._block[s])), self._local
