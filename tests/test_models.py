"""Tests of ``LinearSystem``: time-index conventions, accessors, inputs (module docstring table)."""

from __future__ import annotations

import numpy as np
import pytest

from tobitkf import LinearSystem, ShapeError


def _tv(T, n, base):
    """(T, n, n) with entry [k] = base * (k + 1) so the index is readable from the value."""
    return np.stack([base * (k + 1) for k in range(T)])


def test_dimensions_and_constant_accessors():
    sys = LinearSystem(A=np.eye(3), C=np.ones((2, 3)), Q=np.eye(3), R=np.eye(2), x0=np.zeros(3), P0=np.eye(3))
    assert (sys.n, sys.m, sys.q, sys.p) == (3, 2, 3, None)
    assert sys.time_invariant
    for k in (0, 1, 50):
        np.testing.assert_array_equal(sys.transition(k), np.eye(3))
        np.testing.assert_array_equal(sys.process_cov(k), np.eye(3))
    np.testing.assert_array_equal(sys.measurement(1), np.ones((2, 3)))
    np.testing.assert_array_equal(sys.measurement_cov(7), np.eye(2))
    assert "n=3, m=2" in repr(sys) and "time-invariant" in repr(sys)


def test_time_index_convention_of_arrays():
    """A, Q, B are indexed A[k] for k = 0..T-1; C, R, Bu, D are indexed C[k-1] for k = 1..T."""
    T = 4
    one = np.array([[1.0]])
    sys = LinearSystem(
        A=_tv(T, 1, one),
        C=_tv(T, 1, one),
        Q=_tv(T, 1, one),
        R=_tv(T, 1, one),
        x0=[0.0],
        P0=[[1.0]],
        B=_tv(T, 1, one),
        Bu=_tv(T, 1, one),
        D=_tv(T, 1, one),
    )
    assert not sys.time_invariant and "time-varying" in repr(sys)
    for k in range(T):
        assert sys.transition(k)[0, 0] == k + 1
        assert sys.process_cov(k)[0, 0] == (k + 1) ** 3  # B Q B^T
    for k in range(1, T + 1):
        assert sys.measurement(k)[0, 0] == k
        assert sys.measurement_cov(k)[0, 0] == k
    bx, dy = sys.input_effect(2, np.array([[1.0], [2.0]]))
    np.testing.assert_array_equal(bx, [[2.0], [4.0]])  # Bu[k-1] = Bu[1] = 2
    np.testing.assert_array_equal(dy, [[2.0], [4.0]])  # D[1] = 2
    with pytest.raises(ShapeError, match=r"A: time-indexed array has 4 steps, step k=4 \(index 4\) requested"):
        sys.transition(4)
    with pytest.raises(ShapeError, match=r"C: time-indexed array has 4 steps, step k=0 \(index -1\) requested"):
        sys.measurement(0)


def test_callables_are_called_with_paper_time():
    calls = {"A": [], "C": []}

    def A(k):
        calls["A"].append(k)
        return np.array([[0.5 + k]])

    def C(k):
        calls["C"].append(k)
        return np.array([[float(k)]])

    sys = LinearSystem(A=A, C=C, Q=[[1.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    assert calls == {"A": [0], "C": [1]}  # shapes probed at the first use of each
    assert sys.transition(3)[0, 0] == 3.5 and sys.measurement(5)[0, 0] == 5.0
    assert not sys.time_invariant and sys.A.steps is None


def test_noise_input_matrix():
    G = np.array([[0.5], [1.0]])
    sys = LinearSystem(A=np.eye(2), C=[[1.0, 0.0]], Q=[[0.04]], R=[[1.0]], x0=[0, 0], P0=np.eye(2), B=G)
    assert sys.q == 1
    np.testing.assert_allclose(sys.process_cov(0), 0.04 * G @ G.T, rtol=0, atol=1e-17)


def test_control_input_dimension_from_Bu_or_D():
    s1 = LinearSystem(A=np.eye(2), C=[[1.0, 0.0]], Q=np.eye(2), R=[[1.0]], x0=[0, 0], P0=np.eye(2), Bu=np.ones((2, 3)))
    assert s1.p == 3
    s2 = LinearSystem(A=np.eye(2), C=[[1.0, 0.0]], Q=np.eye(2), R=[[1.0]], x0=[0, 0], P0=np.eye(2), D=np.ones((1, 2)))
    assert s2.p == 2
    bx, dy = s2.input_effect(1, np.array([1.0, 2.0]))
    assert bx == 0.0 and float(dy[0]) == 3.0
    assert s2.input_effect(1, None) == (0.0, 0.0)


def test_check_inputs_and_horizon():
    sys = LinearSystem(A=np.stack([np.eye(1)] * 5), C=[[1.0]], Q=[[1.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]], Bu=[[1.0]])
    sys.check_horizon(5)
    with pytest.raises(ShapeError, match="A: time-indexed array has 5 steps, 6 needed"):
        sys.check_horizon(6)
    assert sys.check_inputs(None, 5) is None
    assert sys.check_inputs(np.zeros((5, 1)), 5).shape == (5, 1)
    assert sys.check_inputs(np.zeros((3, 5, 1)), 5).shape == (3, 5, 1)
    with pytest.raises(ShapeError, match=r"u: expected \(\.\.\., 5, 1\), got \(4, 1\)"):
        sys.check_inputs(np.zeros((4, 1)), 5)
    with pytest.raises(ShapeError, match=r"inputs: expected \(\.\.\., 5, 1\)"):
        sys.check_inputs(np.zeros(5), 5, "inputs")
    plain = LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[1.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    with pytest.raises(ShapeError, match="u: the system has no control input"):
        plain.check_inputs(np.zeros((5, 1)), 5)


def test_singular_covariances_are_allowed():
    """PSD, not PD: Q = 0 (random constant), P0 = 0 (known start), R with a zero is valid for the model."""
    sys = LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.0]], R=[[0.0]], x0=[0.0], P0=[[0.0]])
    assert sys.process_cov(0)[0, 0] == 0.0
