"""The observer keeps its per-operating-point derivatives in single precision: the bands it gives
agree with those of the same filter in double precision."""
from __future__ import annotations

import numpy as np

from thermal_edge.estimation.observer import Observer
from thermal_edge.lptn import discretise
from thermal_edge.lptn.discretise import DiscreteDerivatives


class DoubleObserver(Observer):
    """The same filter with its derivatives in double precision, computed at every step."""

    def _derivatives(self, inputs):
        st = self.stepper
        key = tuple(float(f"{float(inputs[k]):.2g}") for k in st.net.matrix_inputs)
        op = {k: np.array([v]) for k, v in zip(st.net.matrix_inputs, key)}
        d = discretise(st.net.continuous(st.theta, op, K=1, wrt=list(self.cidx)), st.dt, st.method, st.max_substep)
        assert isinstance(d, DiscreteDerivatives)
        return d.dPhi[0], d.dGam[0]


def test_single_precision_derivatives_give_the_double_precision_bands(pm10kw):
    T0 = np.full(len(pm10kw.nodes), 40.0)
    single, double = Observer(pm10kw, T0), DoubleObserver(pm10kw, T0)
    rng = np.random.default_rng(4)
    sensors = list(pm10kw.sensors)
    for k in range(240):
        u = {c: 25.0 for c in pm10kw.inputs}
        u.update({"speed_rpm": 300.0 + 40.0 * (k % 30), "i_rms": 20.0 + 5.0 * np.sin(k / 20.0)})
        for obs in (single, double):
            obs.predict(u)
        y = {s: 40.0 + 0.1 * k + float(rng.normal(0, 0.1)) for s in sensors}
        for obs in (single, double):
            obs.update(y)
    dPhi, dGam = next(iter(single._dcache.values()))
    assert dPhi.dtype == np.float32 and dGam.dtype == np.float32 and len(single._dcache) > 1
    assert np.allclose(single.std(), double.std(), rtol=1e-5, atol=0)
    assert np.abs(single.T - double.T).max() < 1e-4  # K: through the gain only
