"""The one ``filter`` of :class:`~tobitkf.filters.core.Estimator` and its docstring, completed per family."""

from __future__ import annotations

import inspect

import numpy as np
import pytest

import tobitkf as tk
from tobitkf.filters.core import Estimator, GaussianFilter
from tobitkf.filters.steady_state import SteadyStateTobitKalmanFilter

FAMILIES = [
    (tk.KalmanFilter, "(2.3)–(2.6)"),
    (tk.DroppingKalmanFilter, "(2.3)–(2.6)"),
    (tk.TobitKalmanFilter, "(3.37)–(3.41)"),
    (tk.AssumedDensityTobitFilter, "assumed-density"),
    (tk.AssumedDensityFilter, "assumed-density"),
    (tk.TobitFilter, "reading statistics"),
    (tk.FadingTobitKalmanFilter, "TKF-FM"),
    (tk.FadingKalmanFilter, "kf-fm"),
    (tk.ProtocolTobitKalmanFilter, "(21)–(24)"),
    (SteadyStateTobitKalmanFilter, "(3.58)"),
    (tk.ParticleFilter, "particle filter"),
]


@pytest.mark.parametrize("cls, equations", FAMILIES, ids=lambda v: getattr(v, "__name__", ""))
def test_each_family_filter_docstring_names_its_equations_and_every_parameter(cls, equations):
    doc = inspect.getdoc(cls.filter)
    assert equations in doc.split("Parameters")[0]  # the family's own summary, not the shared text
    for section in ("Parameters\n----------", "Returns\n-------\nFilterResult", "Raises\n------\nShapeError"):
        assert section in doc
    params = doc.split("Parameters\n----------\n")[1].split("\n\nReturns")[0]
    documented = [line.split(" : ")[0] for line in params.splitlines() if not line.startswith(" ")]
    assert documented == list(inspect.signature(cls.filter).parameters)[1:]  # in the signature's order, all


def test_families_with_the_shared_signature_have_their_own_docstring_but_the_same_code():
    base = Estimator.filter
    for cls in (tk.AssumedDensityFilter, tk.ParticleFilter, tk.TobitFilter):
        assert cls.filter.__code__ is base.__code__
        assert inspect.signature(cls.filter) == inspect.signature(base)
    assert tk.ParticleFilter.filter.__doc__ != tk.AssumedDensityFilter.filter.__doc__


def _one_state():
    return tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.1]], R=[[0.5]], x0=[0.0], P0=[[1.0]])


def test_a_new_family_gets_the_shared_filter_with_its_own_summary():
    class Halving(GaussianFilter):
        """A toy family (one state): x̄ = x / 2, read directly."""

        _filter_doc = "Filter with the halving model (toy equation (7))."
        n, m = 1, 1

        def _initial(self, N, x0, P0, batch):
            return np.zeros((N, 1)), np.ones((1, 1, 1)), {}

        def _transition(self, k, u, carry):
            return tk.filters.core.Transition(A=np.array([[0.5]]), Qd=np.zeros((1, 1)))

        def _measurement(self, k, xp, Pp, y, u, carry, **options):
            mp = tk.filters.core.MeasurementPrediction(expected=xp, H0=np.eye(1), noise=np.ones((1, 1, 1)))
            return mp, carry

    doc = inspect.getdoc(Halving.filter)
    assert doc.startswith("Filter with the halving model (toy equation (7)).")
    assert "u : (T, p)" in doc and "state : FilterState" in doc
    assert Halving.filter.__qualname__ == f"{Halving.__qualname__}.filter"
    res = Halving().filter(np.array([[1.0], [np.nan]]))
    # step 1: prior 0 halved, P̄ = 1/4, gain 1/5 -> x = 0.2, P = 0.2; step 2 (missing): x̄ = 0.1, P̄ = 0.05
    np.testing.assert_allclose(res.mean[:, 0], [0.2, 0.1], rtol=1e-14)
    np.testing.assert_allclose(res.cov[:, 0, 0], [0.2, 0.05], rtol=1e-14)


def test_an_undocumented_keyword_is_refused_when_the_class_is_defined():
    with pytest.raises(TypeError, match="parameter 'window' has no text"):

        class Windowed(tk.KalmanFilter):
            _filter_doc = "Kalman filter with a window."

            def filter(self, y, *, window=3, outputs="all", state=None):
                return super().filter(y, outputs=outputs, state=state)


def test_an_override_with_a_docstring_of_its_own_keeps_it():
    class Own(tk.KalmanFilter):
        def filter(self, y, *, outputs="all", state=None):
            """Own text."""
            return super().filter(y, outputs=outputs, state=state)

    assert Own.filter.__doc__ == "Own text."
    res = Own(_one_state()).filter(np.array([[1.0]]))
    ref = tk.KalmanFilter(_one_state()).filter(np.array([[1.0]]))
    np.testing.assert_array_equal(res.mean, ref.mean)
