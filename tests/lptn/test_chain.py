"""Generated chain models: the node count asked for, the shipped vocabulary, and an energy balance
at steady state computed from the model's edges (not through the network code)."""
from __future__ import annotations

import numpy as np
import pytest

from thermal_edge.lptn import ModelError, NodeRole, steady_state
from thermal_edge.lptn.chain import MIN_NODES, chain_model, chain_sizes
from thermal_edge.lptn.expr import Value
from thermal_edge.lptn.losses import LossLaws
from thermal_edge.lptn.network import Network


@pytest.mark.parametrize("nodes", [MIN_NODES, 17, 40, 63, 80])
def test_exactly_the_nodes_asked_for(nodes):
    m = chain_model(nodes)
    assert len(m.nodes) == len(set(m.nodes)) == nodes
    assert m.name == f"chain{nodes}"
    assert len(m.adaptable) == (14 if chain_sizes(nodes)[0] > 1 else 13)  # one slice: no axial slot path
    assert set(m.sensors) == {"slot_winding", "end_winding", "housing"}
    assert all(isinstance(m.node_roles[x], NodeRole) for x in m.nodes)  # every node has a role
    assert len(m.nodes_with(NodeRole.WINDING)) == sum(1 for loss in m.losses if "P_cu20" in loss.power.free())
    assert not m.points  # lumped: the reduced path handles it


def test_too_few_nodes_is_a_model_error():
    with pytest.raises(ModelError, match=f"at least {MIN_NODES} nodes"):
        chain_model(MIN_NODES - 1)


@pytest.mark.parametrize("nodes", [40, 160])
def test_rated_steady_state_balances_losses_and_cooling(nodes):
    """At rated load the heat the losses put in leaves through the edges to ambient (W), each edge
    law evaluated here on its own; the hot spot lies where a 10 kW machine's winding does."""
    m = chain_model(nodes)
    inputs = {"speed_rpm": 900.0, "i_rms": 19.0, "torque_nm": 106.0, "ambient_c": 25.0}
    T, _ = steady_state(m, inputs)
    env: dict[str, Value] = dict(zip(m.parameter_names, (float(v) for v in m.nominal())))
    env.update(Network(m).env(m.nominal(), {k: np.array([v]) for k, v in inputs.items()}))
    out = 0.0
    for edge in m.edges:
        if edge.b == "ambient":
            out += float(np.asarray(edge.g.compile()(env)).ravel()[0]) * (T[m.node_index(edge.a)] - 25.0)
    P = LossLaws(m).power({k: (np.asarray(v).ravel()[0] if np.ndim(v) else v) for k, v in env.items()}, T)
    assert out == pytest.approx(float(P.sum()), rel=1e-9)
    assert 500.0 < P.sum() < 700.0  # about 5 % of 10 kW
    assert 90.0 < T[m.node_index(m.limits[0].node)] < 140.0
