"""The observer's parameter derivatives: taken from the factored discretisation of a few operating
points, they are the dense derivatives' (computed independently at every step), and how many
points it keeps changes its memory, never its estimate."""
from __future__ import annotations

import numpy as np

from thermal_edge.estimation.observer import Observer
from thermal_edge.lptn import discretise
from thermal_edge.lptn.discretise import DiscreteDerivatives


class DenseObserver(Observer):
    """The same filter with ``dΦ T + dΓ w`` from the dense derivatives, discretised at every step."""

    def _forcing(self, inputs, w):
        st = self.stepper
        key = tuple(float(f"{float(inputs[k]):.2g}") for k in st.net.matrix_inputs)
        op = {k: np.array([v]) for k, v in zip(st.net.matrix_inputs, key)}
        d = discretise(st.net.continuous(st.theta, op, K=1, wrt=list(self.cidx)), st.dt, st.method, st.max_substep)
        assert isinstance(d, DiscreteDerivatives)
        return (d.dPhi[0] @ self.T + d.dGam[0] @ w).T


def _drive(observers, model, ticks=240):
    """The same inputs (speeds through 30 operating points, back and forth) and readings to each."""
    rng = np.random.default_rng(4)
    sensors = list(model.sensors)
    for k in range(ticks):
        u = {c: 25.0 for c in model.inputs}
        u.update({"speed_rpm": 300.0 + 40.0 * (k % 30), "i_rms": 20.0 + 5.0 * np.sin(k / 20.0)})
        for obs in observers:
            obs.predict(u)
        y = {s: 40.0 + 0.1 * k + float(rng.normal(0, 0.1)) for s in sensors}
        for obs in observers:
            obs.update(y)


def test_factored_derivatives_give_the_dense_derivatives_bands(pm10kw):
    T0 = np.full(len(pm10kw.nodes), 40.0)
    obs, dense = Observer(pm10kw, T0), DenseObserver(pm10kw, T0)
    _drive([obs, dense], pm10kw)
    assert 0 < len(obs._dcache) <= obs.derivative_cache
    assert np.allclose(obs.std(), dense.std(), rtol=1e-9, atol=0)
    assert np.allclose(obs.covariance(), dense.covariance(), rtol=1e-9, atol=1e-12)
    assert np.abs(obs.T - dense.T).max() < 1e-9  # K


def test_the_number_of_points_kept_does_not_change_the_estimate(pm10kw):
    T0 = np.full(len(pm10kw.nodes), 40.0)
    one, every = Observer(pm10kw, T0), Observer(pm10kw, T0)
    one.derivative_cache, every.derivative_cache = 1, 1000
    _drive([one, every], pm10kw)
    points = {float(f"{300.0 + 40.0 * i:.2g}") for i in range(30)}  # the drive's speeds to two digits
    assert len(one._dcache) == 1 and len(every._dcache) == len(points)
    assert np.array_equal(one.T, every.T) and np.array_equal(one.Pa, every.Pa) and np.array_equal(one.S, every.S)


def test_a_drive_that_dwells_gets_the_dense_derivatives_estimate(pm10kw):
    """Speeds held for six steps each (and back): from the second step at a point the forcing is
    its dense map, taken once from the factored form; estimate, covariance and sensitivities stay
    those of the dense derivatives discretised at every step."""
    T0 = np.full(len(pm10kw.nodes), 40.0)
    obs, dense = Observer(pm10kw, T0), DenseObserver(pm10kw, T0)
    rng = np.random.default_rng(5)
    sensors = list(pm10kw.sensors)
    dwelt = 0
    for k in range(120):
        u = {c: 25.0 for c in pm10kw.inputs}
        u.update({"speed_rpm": (600.0, 1500.0, 3000.0, 1500.0)[(k // 6) % 4], "i_rms": 20.0 + 5.0 * np.sin(k / 20.0)})
        for o in (obs, dense):
            o.predict(u)
        dwelt += obs._dwell is not None and obs._dwell[0] is obs._last_point
        y = {s: 40.0 + 0.1 * k + float(rng.normal(0, 0.1)) for s in sensors}
        for o in (obs, dense):
            o.update(y)
    assert dwelt >= 120 * 5 // 6 - 1  # every step but the first at each point
    assert np.allclose(obs.covariance(), dense.covariance(), rtol=1e-9, atol=1e-12)
    assert np.abs(obs.T - dense.T).max() < 1e-9  # K
    assert np.allclose(obs.S, dense.S, rtol=1e-9, atol=1e-12)


class DenseJosephObserver(Observer):
    """The same filter with the sensor update's covariance as the two dense products of its
    definition, ``A P Aᵀ + r² K Kᵀ`` with ``A = I − K H`` (``H`` selecting the sensors' rows)."""

    def update(self, measured):
        ok = [(self.rows[s], float(v)) for s, v in measured.items() if s in self.rows and np.isfinite(v)]
        idx = [i for i, _ in ok]
        y = np.array([v for _, v in ok])
        n, m = self._n, len(self.Pa)
        P = self.Pa
        K = np.zeros((m, len(idx)))
        K[:n] = np.linalg.solve(P[np.ix_(idx, idx)] + np.eye(len(idx)) * self.r2, P[idx, :n]).T
        H = np.zeros((len(idx), m))
        H[np.arange(len(idx)), idx] = 1.0
        A = np.eye(m) - K @ H
        self.T = self.T + K[:n] @ (y - self.T[idx])
        self.Pa = A @ P @ A.T + self.r2 * (K @ K.T)
        self.S = self.S - K[:n] @ self.S[idx, :]
        return self.T


def test_the_sensor_update_is_the_dense_joseph_form(pm10kw):
    """The rank-l covariance update gives the Joseph form's covariance, bands and estimate."""
    T0 = np.full(len(pm10kw.nodes), 40.0)
    obs, dense = Observer(pm10kw, T0), DenseJosephObserver(pm10kw, T0)
    _drive([obs, dense], pm10kw)
    assert np.allclose(obs.Pa, dense.Pa, rtol=1e-10, atol=1e-13)
    assert np.allclose(obs.std(), dense.std(), rtol=1e-10, atol=0)
    assert np.abs(obs.T - dense.T).max() < 1e-10  # K
    assert not np.array_equal(obs.Pa, Observer(pm10kw, T0).Pa)  # the drive did move the covariance
