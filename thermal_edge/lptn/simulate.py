"""Simulation of a run and forward sensitivities ``S_k = ∂T_k/∂θ`` (paper eqs. 35–37).

The discrete model (``docs/model-format.md``)::

    T[k+1] = Φ(θ, u_k) T[k] + Γ_U(θ, u_k) U[k] + Γ_P(θ, u_k) P(θ, u_k, T[k])

``Φ`` and ``Γ`` are computed once per distinct operating point of the run (exact grouping on the
values of the inputs that enter conductances). Losses that are affine in the temperatures (the
copper law ``P20 (1 + α (T − 20))``) are split at load time into a part that is evaluated for the
whole run at once and a per-step feedback ``∂P/∂T``; other loss laws are evaluated per step.

Runs of held inputs are stepped in blocks of their transition's powers, without a loop over
the steps (:mod:`.held`); stretches at one operating point where the loss feedback changes every
step (a noisy current) run vectorised in time (:mod:`.stretch`); the rest is stepped.
Sensitivities run after the simulation (:mod:`.sensitivity`): in closed form over runs of held
inputs, vectorised over the same kind of stretches, step by step elsewhere.

A run whose inputs visit more than ``MAX_OPERATING_POINTS`` (128) operating points (a speed that
sweeps continuously) is simulated in time chunks that visit at most that many each, the
temperatures and sensitivities carried from one chunk to the next: the discretisations (``n²``
numbers and more per operating point, several times that with sensitivities) are held for one
chunk at a time, not for the whole run.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from .discretise import Discrete, DiscreteDerivatives, derive, discretise
from .expr import Value
from .held import LEAD, Transitions, run_temperatures, transitions
from .losses import LossLaws
from .model import MissingInputError, Model
from .network import Continuous, Network
from .sensitivity import Sensitivities, held_runs, held_steps
from .stretch import NodeStretch, covered, padded_length, stretches, varying_steps
from .transitions import StepMatrices

#: steps per product of the input-driven part of stepped steps (:meth:`Simulator._forcing`)
FORCING_ROWS = 64
#: operating points discretised at once: a run that visits more is simulated in time chunks
#: (about 0.2 MB per operating point for a 39-node model, 0.3 MB with sensitivities)
MAX_OPERATING_POINTS = 128


def unique_rows(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct rows of ``keys`` (N, c) in lexicographic order, and each row's index into them.

    What ``np.unique(keys, axis=0, return_inverse=True)`` gives, by a lexsort over the columns:
    ``axis=0`` sorts the rows as structured records, about 15 times slower on a run of 10⁴ samples.

    >>> uniq, inv = unique_rows(np.array([[3.0, 1.0], [1.0, 2.0], [3.0, 1.0], [1.0, 0.0]]))
    >>> uniq.tolist(), inv.tolist()
    ([[1.0, 0.0], [1.0, 2.0], [3.0, 1.0]], [2, 1, 2, 0])
    """
    order = np.lexsort(keys.T[::-1])  # the first column is the primary key
    ranked = keys[order]
    new = np.ones(len(keys), dtype=bool)
    new[1:] = np.any(ranked[1:] != ranked[:-1], axis=1)
    inv = np.empty(len(keys), dtype=np.intp)
    inv[order] = np.cumsum(new) - 1
    return ranked[new], inv


@dataclass
class Trajectory:
    """Result of :meth:`Simulator.simulate`.

    Attributes
    ----------
    T : ndarray (N, n)
        Node temperatures at the sample times, °C (``T[0]`` is the initial state).
    P : ndarray (N, n_loss)
        Losses of every loss source at each sample (W); the last row repeats for the final sample.
    S : ndarray (N, n, p) or None
        Sensitivities ``∂T_k/∂θ_j`` (K per parameter unit) for the parameters in ``wrt``
        (only the nodes in ``rows`` when the simulation was asked for a subset).
    """

    T: np.ndarray
    P: np.ndarray
    wrt: tuple[str, ...] = ()
    S: np.ndarray | None = None
    nodes: tuple[str, ...] = ()
    extra: dict[str, object] = field(default_factory=dict)

    def node(self, name: str) -> np.ndarray:
        """Temperature series of one node, °C."""
        return self.T[:, self.nodes.index(name)]


@dataclass
class _Grouped:
    env: dict[str, Value]  # per-sample law environment (arrays of length N)
    uniq: np.ndarray  # the distinct operating points (K, len(matrix_inputs))
    ops: np.ndarray  # operating point index per step (N-1,)


@dataclass
class _Prepared:
    ops: np.ndarray  # operating point index per step (N-1,)
    disc: Discrete
    U: np.ndarray  # (N, nb)
    env: dict[str, Value]  # per-sample law environment (arrays of length N)
    cont: Continuous  # the continuous system at the operating points
    op: dict[str, np.ndarray]  # the operating points' values of the inputs that enter conductances


@dataclass
class _Chunk:
    """A simulated chunk and what its sensitivities reuse (:meth:`Simulator._chunk_sensitivities`)."""

    theta: np.ndarray
    dt: float
    prep: _Prepared
    T: np.ndarray  # (N, n)
    P: np.ndarray  # (N, nl)
    dPdT: np.ndarray | None  # slopes along the run of laws not affine in T (when asked for)
    slopes: np.ndarray  # (steps, nl, ntv) ∂P/∂T of the affine laws
    stepped: np.ndarray  # (steps,) the steps the simulation stepped
    in_span: np.ndarray  # (steps,) the steps in vectorised stretches
    held_spans: list[tuple[int, int]]  # held runs for the sensitivities' closed form
    spans: list[tuple[int, int]]  # vectorised stretches
    prepared: dict[tuple[int, int], NodeStretch]


class SimulatedRun:
    """A simulated run whose sensitivities can follow (:meth:`Simulator.simulate_run`).

    Attributes
    ----------
    trajectory : Trajectory
        The temperatures and losses (no sensitivities).
    """

    def __init__(self, sim: Simulator, args: tuple[np.ndarray, Mapping[str, np.ndarray], float, np.ndarray],
                 trajectory: Trajectory, chunk: _Chunk | None) -> None:
        self._sim, self._args, self._chunk = sim, args, chunk
        self.trajectory = trajectory

    def sensitivities(self, wrt: Sequence[str], rows: Sequence[str] | None = None) -> Trajectory:
        """The run with its sensitivities by ``wrt`` (``rows`` only, default all nodes): what
        :meth:`Simulator.simulate` with ``wrt`` and ``rows`` returns. From the simulation kept:
        the derivatives of its continuous system from its elimination, of its discretisation
        from its eigendecomposition, the recursion from its temperatures and losses (a run
        simulated in time chunks keeps none: it is simulated again)."""
        sim, names = self._sim, tuple(wrt)
        if not names:
            return self.trajectory
        if self._chunk is None:
            return sim.simulate(*self._args, wrt=names, rows=rows)
        keep = None if rows is None else sim._rows(rows)
        widx = list(sim.model.parameter_index(names))
        S, _ = sim._chunk_sensitivities(self._chunk, widx, keep, None)
        tr = self.trajectory
        return Trajectory(T=tr.T, P=tr.P, wrt=names, nodes=tr.nodes, S=S)


class Simulator:
    """Simulates a :class:`Model` and its parameter sensitivities.

    Parameters
    ----------
    model : Model
    method : {"zoh", "euler"}, optional
        Default: the model's ``discretisation.method``.
    max_substep : float, optional
        Euler sub-step limit (s); default: the model's.
    closed_form : bool, optional
        Runs of held inputs without a loop over their steps: the temperatures in blocks of the
        transition's powers, the sensitivities in closed form (default); False steps every
        sample (the same result to round-off, for checking and for timing the general case).
    vectorised : bool, optional
        Run stretches at one operating point vectorised in time (default,
        ``thermal_edge.lptn.stretch``); False steps them (the reference, to round-off).
    max_operating_points : int, optional
        Operating points discretised at once (default ``MAX_OPERATING_POINTS``, 128); a run that
        visits more is simulated in time chunks.
    """

    def __init__(self, model: Model, method: str | None = None, max_substep: float | None = None,
                 closed_form: bool = True, vectorised: bool = True, max_operating_points: int | None = None) -> None:
        self.model = model
        self.max_operating_points = max_operating_points
        self.closed_form = closed_form
        self.vectorised = vectorised
        self.net = Network(model)
        self.method = method or model.discretisation.method
        self.max_substep = max_substep if max_substep is not None else model.discretisation.max_substep_s
        self.n = len(model.nodes)
        # loss laws: the affine ones are split into constant + slope, the others evaluated per step
        self.losses = LossLaws(model)
        self.tv = self.losses.nodes  # nodes whose temperature enters losses
        #: (law, column of tv) of every temperature a loss law reads
        self._slope_pairs = [(j, i) for j, ds in enumerate(self.losses.reads) for i in ds]
        self._slope_laws = np.array([j for j, _ in self._slope_pairs], dtype=int)
        self._slope_reads = np.array([i for _, i in self._slope_pairs], dtype=int)
        self._slope_live = self._slope_laws * len(self.tv) + self._slope_reads  # flat in (law, column of tv)
        self.nonaffine = self.losses.nonaffine

    # ---------------------------------------------------------------------------------------
    def _grouped(self, theta: np.ndarray, inputs: Mapping[str, np.ndarray]) -> _Grouped:
        """The run's law environment and its steps grouped by operating point."""
        model, net = self.model, self.net
        N = len(next(iter(inputs.values())))
        missing = [c for c in model.inputs if c not in inputs]
        if missing:
            raise MissingInputError(f"run lacks input column(s) {', '.join(missing)} needed by model {model.name}",
                                    tuple(missing))
        env = net.env(theta, {k: np.asarray(v, dtype=float) for k, v in inputs.items()})
        steps = max(N - 1, 1)
        if net.matrix_inputs:
            keys = np.stack([np.broadcast_to(np.asarray(env[k], dtype=float), (N,))[:steps] for k in net.matrix_inputs], axis=1)
            uniq, ops = unique_rows(keys)
        else:
            uniq, ops = np.zeros((1, 0)), np.zeros(steps, dtype=int)
        return _Grouped(env=env, uniq=uniq, ops=np.asarray(ops).reshape(-1))

    def _prepare(self, theta: np.ndarray, inputs: Mapping[str, np.ndarray], dt: float,
                 grouped: _Grouped | None = None, solves: bool = False) -> _Prepared:
        """The run's operating points, their continuous system (its elimination's solves kept
        with ``solves``) and discretisation, the boundary inputs and the law environment."""
        model, net = self.model, self.net
        N = len(next(iter(inputs.values())))
        g = self._grouped(theta, inputs) if grouped is None else grouped
        env, uniq, ops = g.env, g.uniq, g.ops
        op = {k: uniq[:, i] for i, k in enumerate(net.matrix_inputs)}
        cont = net.continuous(theta, op, K=len(uniq), solves=solves)
        disc = discretise(cont, dt, self.method, self.max_substep)
        U = np.zeros((N, 0))
        if model.boundaries:
            U = np.stack([np.broadcast_to(np.asarray(inputs[c], dtype=float), (N,)) for c in model.boundaries.values()], axis=1)
        return _Prepared(ops=np.asarray(ops).reshape(-1), disc=disc, U=U, env=env, cont=cont, op=op)

    def _loss_terms(self, env: dict[str, Value], N: int, T: np.ndarray | None,
                    slopes: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """Losses (N, nl) and, with ``slopes``, ∂P/∂T at the loss-temperature nodes (N, nl, ntv).

        With ``T`` None the temperatures are zero: for affine laws that gives the constant part.
        """
        return self.losses.power(env, T, N), (self.losses.dT(env, T, N) if slopes else None)

    def _rows(self, nodes: Sequence[str]) -> np.ndarray:
        return np.array([self.model.node_index(x) for x in nodes], dtype=int)

    # ---------------------------------------------------------------------------------------
    def simulate(
        self,
        theta: np.ndarray,
        inputs: Mapping[str, np.ndarray],
        dt: float,
        T0: np.ndarray,
        wrt: Sequence[str] | None = None,
        rows: Sequence[str] | None = None,
    ) -> Trajectory:
        """Simulate a run open-loop, optionally with sensitivities.

        Parameters
        ----------
        theta : ndarray
            Full parameter vector in model order.
        inputs : mapping
            Input columns (arrays of length N, one per sample); inputs at sample ``k`` are held
            over ``[t_k, t_k + dt)``.
        dt : float
            Sample period, s.
        T0 : ndarray (n,)
            Node temperatures at the first sample, °C.
        wrt : sequence of str, optional
            Parameters to compute ``S = ∂T/∂θ`` for.
        rows : sequence of str, optional
            Keep the sensitivities of these nodes only (e.g. the sensor nodes); default all.
        """
        names = tuple(wrt or ())
        widx = list(self.model.parameter_index(names)) if names else []
        theta = np.asarray(theta, dtype=float)
        keep = None if rows is None else self._rows(rows)
        N = len(next(iter(inputs.values())))
        grouped = self._grouped(theta, inputs)
        chunks = self._chunks(grouped.ops, N)
        if len(chunks) == 1:
            T, P, S, _ = self._run(theta, inputs, float(dt), np.asarray(T0, dtype=float), names, widx, keep, None,
                                   grouped)
            return Trajectory(T=T, P=P, wrt=names, nodes=self.model.nodes, S=S)
        # chunk by chunk, each from the last sample of the one before (temperatures and full S)
        parts: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]] = []
        Tc, Sc = np.asarray(T0, dtype=float), None
        for a, b in chunks:  # samples a .. b
            piece = {k: (v[a: b + 1] if np.ndim(v) and len(v) == N else v) for k, v in inputs.items()}
            T, P, S, Sc = self._run(theta, piece, float(dt), Tc, names, widx, keep, Sc)
            Tc = T[-1]
            last = b == N - 1
            parts.append((T if last else T[:-1], P if last else P[:-1], None if S is None else (S if last else S[:-1])))
        S_all = np.concatenate([x[2] for x in parts if x[2] is not None]) if names else None
        return Trajectory(T=np.concatenate([x[0] for x in parts]), P=np.concatenate([x[1] for x in parts]),
                          wrt=names, nodes=self.model.nodes, S=S_all)

    def simulate_run(self, theta: np.ndarray, inputs: Mapping[str, np.ndarray], dt: float,
                     T0: np.ndarray) -> SimulatedRun:
        """Simulate a run open-loop, keeping what its sensitivities need (:class:`SimulatedRun`).

        For an optimiser that asks for a value first and for the gradient at some of the points
        only (a line search's rejected trials need none): :meth:`SimulatedRun.sensitivities`
        adds them later without simulating again, the same numbers as :meth:`simulate` with
        ``wrt``. Parameters as :meth:`simulate`.
        """
        theta = np.asarray(theta, dtype=float)
        N = len(next(iter(inputs.values())))
        grouped = self._grouped(theta, inputs)
        args = (theta.copy(), inputs, float(dt), np.array(T0, dtype=float))
        if len(self._chunks(grouped.ops, N)) > 1:  # chunks are not kept (memory): simulated again if asked
            return SimulatedRun(self, args, self.simulate(*args), None)
        ch = self._simulate_chunk(args[0], inputs, args[2], args[3], grouped, sens=True)
        return SimulatedRun(self, args, Trajectory(T=ch.T, P=ch.P, nodes=self.model.nodes), ch)

    def _chunks(self, ops: np.ndarray, N: int) -> list[tuple[int, int]]:
        """Sample ranges ``(a, b)`` (samples ``a .. b``, consecutive ranges sharing their end
        sample) whose steps (operating points ``ops``) visit at most ``max_operating_points``
        operating points; one range for the whole run when it visits no more."""
        if N < 2:
            return [(0, max(N - 1, 0))]
        limit = max(int(MAX_OPERATING_POINTS if self.max_operating_points is None else self.max_operating_points), 1)
        if ops.max() < limit:
            return [(0, N - 1)]
        chunks: list[tuple[int, int]] = []
        a, seen = 0, set[int]()
        for k, o in enumerate(ops.tolist()):
            if o not in seen and len(seen) == limit:  # step k starts the next chunk
                chunks.append((a, k))
                a, seen = k, set()
            seen.add(o)
        chunks.append((a, N - 1))
        return chunks

    def _run(self, theta: np.ndarray, inputs: Mapping[str, np.ndarray], dt: float, T0: np.ndarray,
             names: tuple[str, ...], widx: list[int], rows: np.ndarray | None,
             S0: np.ndarray | None, grouped: _Grouped | None = None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
        """One chunk of :meth:`simulate` from ``T0`` and ``S0`` (full, n × p; None: zero): the
        temperatures, losses, sensitivities (``rows``) and the full ``S`` at the last sample
        (``grouped``: the chunk's steps grouped by operating point, when already known)."""
        # the temperatures first, then the derivatives from what the simulation kept: the same
        # numbers as discretising with the derivatives at once, and the simulation runs without
        # their arrays in the cache
        ch = self._simulate_chunk(theta, inputs, dt, T0, grouped, sens=bool(names))
        if not names:
            return ch.T, ch.P, None, None
        S, S_end = self._chunk_sensitivities(ch, widx, rows, S0)
        return ch.T, ch.P, S, S_end

    def _simulate_chunk(self, theta: np.ndarray, inputs: Mapping[str, np.ndarray], dt: float, T0: np.ndarray,
                        grouped: _Grouped | None, sens: bool) -> _Chunk:
        """The temperatures of one chunk and, when ``sens``, what its sensitivities reuse: the
        elimination's solves and the states from which :meth:`_chunk_sensitivities` adds them
        for any parameters."""
        N = len(next(iter(inputs.values())))
        prep = self._prepare(theta, inputs, dt, grouped, solves=sens)
        d = prep.disc
        n, nb = self.n, prep.U.shape[1]
        GP = d.Gam[:, :, nb:]
        P0, dPdT0 = self._loss_terms(prep.env, N, None)
        assert dPdT0 is not None  # asked for with the slopes
        na = self.nonaffine
        P0[:, na] = 0.0  # laws not affine in T are evaluated per step instead
        dPdT0[:, na] = 0.0
        ops = prep.ops[: max(N - 1, 0)]
        T = np.empty((N, n))
        T[0] = T0
        steps = max(N - 1, 0)
        # runs of held inputs in closed form (:mod:`.held`; their modes serve the sensitivities
        # too), stretches of one operating point where the loss feedback changes every step
        # vectorised in time (losses affine in T only: the others are evaluated step by step)
        held = held_steps(prep.env, steps)
        closed_ok = self.closed_form and not len(na)
        held_spans = held_runs(held, closed_ok)  # the sensitivities' closed form
        varying = np.zeros(steps, dtype=bool)
        if self.vectorised and not len(na):
            # the slopes a loss law can have (the temperatures it reads): the others are zero
            varying = varying_steps(dPdT0[:steps, self._slope_laws, self._slope_reads], may_change=~held)
        spans = stretches(ops, varying & ~covered(held_spans, steps))
        in_span = covered(spans, steps)
        # the simulation's held runs: every run of held inputs from its LEAD-th step on, in blocks
        # of its transition's powers (the steps before, and shorter runs, are stepped). Which steps
        # run in blocks, and how the blocks fall, depends only on the inputs up to them: a run
        # that goes on longer gives the same temperatures up to any of its steps
        blocks = [(a + LEAD, b) for a, b in held_runs(held, closed_ok, LEAD + 1) if not in_span[a:b].any()]
        closed: list[tuple[int, int, int]] = []  # (a, b, transition)
        sim_tr = None
        if blocks:
            sim_tr = transitions(d, GP, self.tv, ops, dPdT0[:steps], np.array([a for a, _ in blocks]))
            closed = [(a, b, int(u)) for (a, b), u in zip(blocks, sim_tr.index)]
        stepped = ~in_span & ~covered(blocks, steps)
        # the input-driven part of the stepped steps and of each block run's first step (the
        # stretches make their own, in the modal basis)
        want = stepped.copy()
        want[[a for a, _, _ in closed]] = True
        f = self._forcing(d.Gam, ops, prep.U, P0, want)
        mats = self._step_matrices(d.Phi, GP, ops, dPdT0, stepped)
        step_losses = self.losses.stepwise(prep.env, N, na) if na else None
        GPna = [GP[o][:, na] for o in range(GP.shape[0])] if na else []
        opl = ops.tolist()

        def step(a: int, b: int) -> None:
            # the matrices a block at a time (:mod:`.transitions`): bounded memory on noisy inputs
            for lo, hi, ms, mi in mats.segments(a, b):
                if step_losses is None:
                    for k in range(lo, hi):
                        np.matmul(ms[mi[k]], T[k], out=T[k + 1])
                        T[k + 1] += f[k]
                else:
                    for k in range(lo, hi):
                        np.matmul(ms[mi[k]], T[k], out=T[k + 1])
                        T[k + 1] += f[k]
                        T[k + 1] += GPna[opl[k]] @ step_losses(k, T[k])  # losses at T_k, before the update

        done = 0
        prepared: dict[tuple[int, int], NodeStretch] = {}  # shared with the sensitivities' stretches
        events = sorted([(a, b, u) for a, b, u in closed] + [(a, b, -1) for a, b in spans])
        for a, b, u in events:
            step(done, a)
            if u >= 0:
                assert sim_tr is not None
                run_temperatures(sim_tr.powers(u), f[a], T[a], T[a + 1: b + 1])
            else:
                o = int(ops[a])
                V, Vi = d.basis(o)
                ns = prepared[(a, b)] = NodeStretch(V, Vi, d.mu[o], GP[o], self.tv, dPdT0[a:b], self._slope_live)
                fm = np.zeros((n, 1, padded_length(b - a)))
                wab = np.concatenate([prep.U[a:b], P0[a:b]], axis=1)
                np.matmul(Vi @ d.Gam[o], wab.T, out=fm[:, 0, : b - a])
                Ta, _ = ns.solve(fm, T[a][:, None], states=sens)  # modal temperatures for the sensitivities
                T[a + 1: b + 1] = Ta[:, 0, :].T
            done = b
        step(done, steps)
        if na:  # the slopes along the run only serve the sensitivities of laws not affine in T
            P, dPdT = self._loss_terms(prep.env, N, T, slopes=sens)
        else:  # affine laws: P(T) = P(0) + ∂P/∂T T, for the few laws that read a temperature
            P, dPdT = P0, None
            for j, i in self._slope_pairs:
                P[:, j] += dPdT0[:, j, i] * T[:, self.tv[i]]
        return _Chunk(theta=theta, dt=dt, prep=prep, T=T, P=P, dPdT=dPdT, slopes=dPdT0[:steps],
                      stepped=stepped, in_span=in_span, held_spans=held_spans, spans=spans, prepared=prepared)

    def _sensitivity_steps(self, d: Discrete, GP: np.ndarray, ops: np.ndarray, slopes: np.ndarray,
                           held_spans: list[tuple[int, int]], stepped: np.ndarray,
                           in_span: np.ndarray) -> tuple[Transitions | None, np.ndarray]:
        """The closed-loop modes of the held runs (None without any) and the steps that get a
        step matrix: those the simulation steps and those the sensitivities step (not in a
        stretch nor in a held run in closed form)."""
        steps = len(stepped)
        sens_closed: list[tuple[int, int]] = []
        held_tr = None
        if held_spans:
            held_tr = transitions(d, GP, self.tv, ops, slopes, np.array([a for a, _ in held_spans]))
            ok = held_tr.modes.ok[held_tr.index]
            sens_closed = [r for r, good in zip(held_spans, ok) if good]
        return held_tr, stepped | (~in_span & ~covered(sens_closed, steps))

    def _chunk_sensitivities(self, ch: _Chunk, widx: list[int], rows: np.ndarray | None,
                             S0: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The sensitivities by ``widx`` of a chunk simulated with ``sens`` (:meth:`_simulate_chunk`)
        (``rows``; and the full ``S`` at its last sample): the derivatives of its continuous
        system from the solves it kept, of its discretisation from its eigendecomposition
        (:func:`~.discretise.derive`), the step matrices of the steps the sensitivities step,
        the recursion over its temperatures and losses."""
        prep = ch.prep
        cont = self.net.derivatives(prep.cont, ch.theta, prep.op, widx)
        prep = replace(prep, disc=derive(prep.disc, cont, ch.dt, self.method))
        d, nb = prep.disc, prep.U.shape[1]
        ops = prep.ops[: len(ch.stepped)]
        held_tr, need = self._sensitivity_steps(d, d.Gam[:, :, nb:], ops, ch.slopes, ch.held_spans, ch.stepped, ch.in_span)
        mats = self._step_matrices(d.Phi, d.Gam[:, :, nb:], ops, ch.slopes, need)
        return self._sensitivities(prep, ch.T, ch.P, ch.dPdT, widx, rows, mats, ch.held_spans, ch.spans, ch.slopes,
                                   ch.prepared, held_tr, S0)

    @staticmethod
    def _forcing(Gam: np.ndarray, ops: np.ndarray, U: np.ndarray, P: np.ndarray, want: np.ndarray) -> np.ndarray:
        """``f_k = Γ(u_k) [U_k; P_k]`` (steps, n) at the steps in ``want`` (the others are left
        uninitialised), grouped by operating point: products of :data:`FORCING_ROWS` steps of
        one operating point. Every product has that one shape (the last of each operating point
        padded), so that a step's forcing does not depend on how many other steps are asked for
        (a product's kernel, and with it the order of its sums, can change with its shape)."""
        ks = np.nonzero(want)[0]
        n = Gam.shape[1]
        f = np.empty((len(ops), n))
        order = ks[np.argsort(ops[ks], kind="stable")]  # the steps of each operating point together
        bounds = np.searchsorted(ops[order], np.arange(Gam.shape[0] + 1))
        fs = np.empty((len(order), n))
        wo = np.concatenate([U[order], P[order]], axis=1)
        buf, res = np.zeros((FORCING_ROWS, wo.shape[1])), np.empty((FORCING_ROWS, n))
        for op in np.nonzero(np.diff(bounds))[0].tolist():
            for lo in range(int(bounds[op]), int(bounds[op + 1]), FORCING_ROWS):
                hi = min(lo + FORCING_ROWS, int(bounds[op + 1]))
                buf[: hi - lo] = wo[lo:hi]
                np.matmul(buf, Gam[op].T, out=res)
                fs[lo:hi] = res[: hi - lo]
        f[order] = fs
        return f

    def _step_matrices(
        self, Phi: np.ndarray, GP: np.ndarray, ops: np.ndarray, dPdT: np.ndarray, need: np.ndarray | None = None
    ) -> StepMatrices:
        """Per-step transition matrices ``Φ + Γ_P ∂P/∂T`` (temperature feedback of the losses folded in).

        Steps with the same operating point and the same loss slopes share one matrix (a drive
        cycle holds its current over a segment); the matrices are computed a block at a time
        when stepped (:class:`~thermal_edge.lptn.transitions.StepMatrices`). Only the steps in
        ``need`` (default all) get one (the others are run vectorised).
        """
        return StepMatrices(Phi, GP, self.tv, ops, dPdT, need)

    def _sensitivities(self, prep: _Prepared, T: np.ndarray, P: np.ndarray, dPdT: np.ndarray | None, widx: Sequence[int],
                       rows: np.ndarray | None, steps: StepMatrices,
                       held_spans: list[tuple[int, int]], spans: list[tuple[int, int]],
                       slopes: np.ndarray, prepared: dict[tuple[int, int], NodeStretch],
                       held: Transitions | None, S0: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        d = prep.disc
        assert isinstance(d, DiscreteDerivatives)  # discretised with the derivatives by ``wrt``
        N = T.shape[0]
        ops = prep.ops[: max(N - 1, 0)]
        if self.nonaffine:  # the simulation's matrices leave these laws' temperature feedback out
            assert dPdT is not None  # the simulation computes the slopes for laws not affine in T
            steps = self._step_matrices(d.Phi, d.Gam[:, :, prep.U.shape[1]:], ops, dPdT[: N - 1])
        env = prep.env

        def at(k: np.ndarray) -> dict[str, Value]:
            return {key: (v[k] if isinstance(v, np.ndarray) and v.ndim == 1 and len(v) == N else v) for key, v in env.items()}

        sens = Sensitivities(d, ops, steps, T, prep.U, P,
                             losses=lambda k, temps: self._loss_terms(at(k), len(temps), temps, slopes=False)[0],
                             loss_theta=lambda k, temps: self.losses.dtheta(at(k), temps, widx, len(temps)),
                             loss_nodes=self.tv, slopes=slopes, prepared=prepared,
                             loss_wrt=self.losses.depends_on(widx), held=held)
        return sens.run(held_spans, spans, rows, S0)
