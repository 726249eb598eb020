"""Parameters the data cannot separate: infinite σ and not identifiable, never the zero variance a
pseudo-inverse gives a direction without information. Checked against the exact inverse where the
information is regular, and against the null direction built into the sensitivities."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from thermal_edge.estimation.uncertainty import estimate_uncertainty, information_inverse


def _jacobian(kind: str, N: int = 400, seed: int = 3) -> np.ndarray:
    """Sensitivities (N, 1 sensor, 3 log-parameters): ``together``: the third is minus the sum of the
    other two (a capacity, a conductance and a loss scaled alike change nothing: (1, 1, 1) is
    null); ``unused``: the third is zero (a parameter no output reads); ``regular``: independent."""
    rng = np.random.default_rng(seed)
    J = rng.normal(size=(N, 3))
    if kind == "together":
        J[:, 2] = -(J[:, 0] + J[:, 1])
    elif kind == "unused":
        J[:, 2] = 0.0
    return J[:, None, :]


def _uncertainty(J: np.ndarray):
    rng = np.random.default_rng(0)
    obj = SimpleNamespace(w=np.ones(J.shape[:2]), prior_weight=0.0, sigma=np.ones(3), nuisance=0,
                          space=SimpleNamespace(names=("C", "G", "k")))
    ev = SimpleNamespace(jac=J, residuals=0.1 * rng.normal(size=J.shape[:2]))
    return estimate_uncertainty(obj, ev, max_rel_std=0.5)


def test_a_regular_information_is_inverted_exactly():
    J = _jacobian("regular")[:, 0, :]
    inv, unresolved = information_inverse(J.T @ J)
    np.testing.assert_allclose(inv, np.linalg.inv(J.T @ J), rtol=1e-10)
    assert not unresolved.any()
    unc = _uncertainty(_jacobian("regular"))
    assert np.all(np.isfinite(unc.rel_std)) and unc.identifiable.all()


def test_parameters_that_act_only_together_have_infinite_sigma_and_are_not_identifiable():
    J = _jacobian("together")[:, 0, :]
    assert np.abs(J @ np.ones(3)).max() < 1e-12  # the built-in null direction
    _, unresolved = information_inverse(J.T @ J)
    assert unresolved.all()
    unc = _uncertainty(_jacobian("together"))
    assert np.all(np.isinf(unc.rel_std)) and not unc.identifiable.any()
    assert np.all(np.isinf(unc.rel_std_independent))


def test_a_parameter_nothing_reads_is_the_only_one_unresolved():
    unc = _uncertainty(_jacobian("unused"))
    assert list(np.isinf(unc.rel_std)) == [False, False, True]
    assert list(unc.identifiable) == [True, True, False]
    # the prediction's band stays finite: the unseen direction moves no output
    band = unc.node_band(np.array([[[0.3, -0.2, 0.0]]]))
    assert np.all(np.isfinite(band))
