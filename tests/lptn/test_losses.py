"""The loss laws in one place (``LossLaws``): values, ∂P/∂T and ∂P/∂θ against central differences
of the values, one state and a batch alike; and the method of a discretisation is its type."""
from __future__ import annotations

import numpy as np
import pytest

from thermal_edge.lptn import (
    Discrete,
    EulerDerivatives,
    Network,
    ZohDerivatives,
    discretise,
)
from thermal_edge.lptn.losses import LossLaws


def _point(model, rng):
    """A random operating point (scalars) and node temperatures (°C)."""
    inputs = {k: float(rng.uniform(0.0, 200.0)) for k in model.inputs}
    return inputs, rng.uniform(20.0, 120.0, len(model.nodes))


@pytest.mark.parametrize("which", ["tiny_plus_model", "paderborn_model"])
def test_derivatives_are_those_of_the_values(which, request):
    model = request.getfixturevalue(which)
    laws, net = LossLaws(model), Network(model)
    rng = np.random.default_rng(3)
    theta = model.nominal()
    inputs, T = _point(model, rng)
    env = net.env(theta, {k: np.asarray(v) for k, v in inputs.items()})
    P = laws.power(env, T)
    assert P.shape == (len(model.losses),) and np.all(np.isfinite(P))
    # ∂P/∂T at the nodes the laws read (the others are not read: changing them changes nothing)
    dT = laws.dT(env, T)
    for c, i in enumerate(laws.nodes):
        h = 1e-4
        up, down = T.copy(), T.copy()
        up[i] += h
        down[i] -= h
        fd = (laws.power(env, up) - laws.power(env, down)) / (2 * h)
        np.testing.assert_allclose(dT[:, c], fd, rtol=1e-6, atol=1e-9 * max(1.0, np.abs(P).max()))
    others = np.setdiff1d(np.arange(len(model.nodes)), laws.nodes)
    if len(others):
        moved = T.copy()
        moved[others] += 10.0
        np.testing.assert_array_equal(laws.power(env, moved), P)
    # ∂P/∂θ for every parameter
    wrt = list(range(len(theta)))
    dth = laws.dtheta(env, T, wrt)
    for j in wrt:
        h = 1e-6 * theta[j]
        th_up, th_down = theta.copy(), theta.copy()
        th_up[j] += h
        th_down[j] -= h
        e_up = net.env(th_up, {k: np.asarray(v) for k, v in inputs.items()})
        e_down = net.env(th_down, {k: np.asarray(v) for k, v in inputs.items()})
        fd = (laws.power(e_up, T) - laws.power(e_down, T)) / (2 * h)
        np.testing.assert_allclose(dth[:, j], fd, rtol=1e-5, atol=1e-9 * max(1.0, np.abs(P).max()) / theta[j],
                                   err_msg=model.parameter_names[j])
    # depends_on: exactly the parameters whose finite-difference column is not zero
    moves = [j for j in wrt if np.any(dth[:, j] != 0.0)]
    assert all(laws.depends_on([j]) for j in moves)
    still = [j for j in wrt if j not in moves]
    assert not laws.depends_on(still)


def test_a_batch_is_its_rows(tiny_plus_model):
    model = tiny_plus_model
    laws, net = LossLaws(model), Network(model)
    rng = np.random.default_rng(4)
    points = [_point(model, rng) for _ in range(5)]
    batch_env = net.env(model.nominal(), {k: np.array([p[0][k] for p in points]) for k in model.inputs})
    T = np.stack([p[1] for p in points])
    P, dT, dth = laws.power(batch_env, T, 5), laws.dT(batch_env, T, 5), laws.dtheta(batch_env, T, [0, 4], 5)
    for b, (inputs, Tb) in enumerate(points):
        env = net.env(model.nominal(), {k: np.asarray(v) for k, v in inputs.items()})
        np.testing.assert_allclose(P[b], laws.power(env, Tb), rtol=1e-14)
        np.testing.assert_allclose(dT[b], laws.dT(env, Tb), rtol=1e-14)
        np.testing.assert_allclose(dth[b], laws.dtheta(env, Tb, [0, 4]), rtol=1e-14)
        step = laws.stepwise(batch_env, 5, laws.nonaffine)
        np.testing.assert_allclose(step(b, Tb), laws.power(env, Tb)[laws.nonaffine], rtol=1e-14)
    assert laws.nonaffine == [1]  # the yoke law ``(1 + 2e-3 (T − 20)) ** 1.5``; the copper law is affine


@pytest.mark.parametrize("method, kind", [("zoh", ZohDerivatives), ("euler", EulerDerivatives)])
def test_the_method_of_a_discretisation_is_its_type(tiny_plus_model, method, kind):
    net = Network(tiny_plus_model)
    op = {k: np.array([500.0]) for k in net.matrix_inputs}
    plain = discretise(net.continuous(tiny_plus_model.nominal(), op), 1.0, method, 0.5)
    assert type(plain) is Discrete
    with_d = discretise(net.continuous(tiny_plus_model.nominal(), op, wrt=[0, 1]), 1.0, method, 0.5)
    assert type(with_d) is kind
    np.testing.assert_array_equal(with_d.Phi, plain.Phi)
    assert with_d.dPhi.shape == (1, 2, 3, 3)
