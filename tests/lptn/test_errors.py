"""What the model raises for what a caller gives it wrong: error classes of the one user-error
base (the command line turns them into one line and exit 2), never a ``KeyError``, whose message
Python prints in quotes and which the command line treats as a bug."""
from __future__ import annotations

import numpy as np
import pytest

from thermal_edge.errors import ThermalEdgeError
from thermal_edge.lptn import MissingInputError, ModelError, Network, ParameterError, Simulator


def _user_error(err: pytest.ExceptionInfo[BaseException]) -> str:
    assert isinstance(err.value, ThermalEdgeError) and not isinstance(err.value, KeyError), type(err.value).__mro__
    text = str(err.value)
    assert not text.startswith("'") and "\n" not in text, text
    return text


def test_a_run_without_an_input_column_is_a_missing_input_error(tiny_model):
    sim = Simulator(tiny_model)
    inputs = {k: np.full(5, 25.0) for k in tiny_model.inputs}
    gone = tiny_model.inputs[0]
    del inputs[gone]
    with pytest.raises(MissingInputError) as err:
        sim.simulate(tiny_model.nominal(), inputs, 1.0, np.full(len(tiny_model.nodes), 25.0))
    text = _user_error(err)
    assert f"lacks input column(s) {gone}" in text and "model tiny" in text
    assert err.value.missing == (gone,)


def test_an_operating_point_without_an_input_is_a_missing_input_error(tiny_model):
    net = Network(tiny_model)
    if not net.matrix_inputs:
        pytest.skip("the tiny model's matrix depends on no input")
    with pytest.raises(MissingInputError) as err:
        net.continuous(tiny_model.nominal(), {}, K=1)
    assert set(err.value.missing) == set(net.matrix_inputs)
    assert "model tiny" in _user_error(err)


def test_an_unknown_parameter_is_a_parameter_error_naming_it_and_the_known_ones(tiny_model):
    with pytest.raises(ParameterError) as err:
        tiny_model.parameter_index(["R_nope", tiny_model.parameter_names[0]])
    text = _user_error(err)
    assert err.value.name == "R_nope" and "model tiny" in text
    assert all(p in text for p in tiny_model.parameter_names)


def test_an_unknown_node_is_a_model_error(tiny_model):
    with pytest.raises(ModelError) as err:
        tiny_model.node_index("nowhere")
    assert "'nowhere'" in _user_error(err) and "model tiny" in str(err.value)


def test_the_known_ones_still_index(tiny_model):
    names = list(tiny_model.parameter_names)
    assert list(tiny_model.parameter_index(names[::-1])) == list(range(len(names)))[::-1]
    assert tiny_model.node_index(tiny_model.nodes[-1]) == len(tiny_model.nodes) - 1
