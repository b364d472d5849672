"""Tests of ``tobitkf.metrics`` on hand-computed cases."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from tobitkf import ShapeError
from tobitkf._io import to_jsonable
from tobitkf.metrics import align_truth, bias, nees, nees_terms, rmse, summarize


def _case():
    # 2 runs, 2 steps, 2 states; truth includes x_0 (T+1 = 3 rows)
    truth = np.array(
        [
            [[9.0, 9.0], [0.0, 0.0], [1.0, 1.0]],
            [[9.0, 9.0], [0.0, 0.0], [1.0, 1.0]],
        ]
    )
    est = np.array(
        [
            [[3.0, 0.0], [1.0, 2.0]],
            [[-1.0, 0.0], [1.0, 0.0]],
        ]
    )
    return truth, est


def test_rmse_by_hand():
    truth, est = _case()
    # step 1: errors comp0 (3, -1) -> sqrt((9+1)/2) = sqrt 5; comp1 (0, 0) -> 0
    # step 2: comp0 (0, 0) -> 0; comp1 (1, -1) -> 1
    np.testing.assert_allclose(rmse(truth, est), [[math.sqrt(5), 0.0], [0.0, 1.0]], rtol=1e-15)


def test_bias_by_hand():
    truth, est = _case()
    np.testing.assert_allclose(bias(truth, est), [[1.0, 0.0], [0.0, 0.0]], rtol=1e-15)


def test_truth_without_x0_is_accepted():
    truth, est = _case()
    np.testing.assert_array_equal(rmse(truth[:, 1:], est), rmse(truth, est))
    np.testing.assert_array_equal(align_truth(truth, est), truth[:, 1:])


def test_nees_by_hand():
    truth, est = _case()
    cov = np.broadcast_to(np.diag([1.0, 4.0]), (2, 2, 2, 2)).copy()
    cov[1, 1] = np.array([[2.0, 1.0], [1.0, 2.0]])
    # run 0: e1 = (3, 0) -> 9/1 = 9; e2 = (0, 1) -> 1/4
    # run 1: e1 = (-1, 0) -> 1;      e2 = (0, -1) with P = [[2,1],[1,2]]: P^-1 = [[2,-1],[-1,2]]/3 -> 2/3
    np.testing.assert_allclose(nees(truth, est, cov), [(9 + 1) / 2, (0.25 + 2 / 3) / 2], rtol=1e-14)


def test_nees_of_a_consistent_estimator_is_near_n():
    rng = np.random.default_rng(0)
    N, T, n = 20_000, 3, 2
    P = np.array([[2.0, 0.6], [0.6, 1.0]])
    err = rng.standard_normal((N, T, n)) @ np.linalg.cholesky(P).T
    truth = np.zeros((N, T, n))
    val = nees(truth, err, np.broadcast_to(P, (N, T, n, n)))
    # e^T P^-1 e ~ chi^2_2: mean 2, variance 4 -> SE = 2/sqrt(N)
    assert np.all(np.abs(val - 2.0) < 5 * 2 / math.sqrt(N))


def test_nees_singular_covariance_affects_only_its_step():
    """A singular covariance at one step gives inf there; other steps keep their values (docstring:
    "a linear solve per run and step; singular covariances give inf")."""
    truth, est = _case()
    cov = np.broadcast_to(np.eye(2), (2, 2, 2, 2)).copy()
    cov[0, 1] = np.zeros((2, 2))
    val = nees(truth, est, cov)
    assert val[0] == pytest.approx((9 + 1) / 2)
    assert np.isinf(val[1])


def test_summarize_contents_and_json():
    truth, est = _case()
    cov = np.broadcast_to(np.eye(2), (2, 2, 2, 2))
    s = summarize(truth, est, cov)
    np.testing.assert_allclose(s["rmse"], rmse(truth, est))
    np.testing.assert_allclose(s["rmse_time_avg"], [math.sqrt(5) / 2, 0.5])
    np.testing.assert_allclose(s["bias_time_avg"], [0.5, 0.0])
    assert s["nees_time_avg"] == pytest.approx(np.mean(nees(truth, est, cov)))
    s2 = summarize(truth, est, skip=1)
    np.testing.assert_allclose(s2["rmse_time_avg"], [0.0, 1.0])
    assert "nees" not in s2
    # the summary serialises to JSON (what the CLI writes)
    text = json.dumps(to_jsonable(s))
    assert json.loads(text)["rmse_time_avg"][1] == pytest.approx(0.5)


def test_to_jsonable_non_finite():
    assert to_jsonable({"a": np.array([1.0, np.inf, -np.inf, np.nan]), "b": np.int64(3), "c": np.bool_(True)}) == {
        "a": [1.0, "inf", "-inf", "nan"],
        "b": 3,
        "c": True,
    }


def test_shape_mismatch():
    truth, est = _case()
    with pytest.raises(ShapeError, match="truth: shape"):
        rmse(truth[:, :, :1], est)
    with pytest.raises(ShapeError, match="truth: shape"):
        bias(truth[:, :1], est)


@pytest.mark.parametrize("n", [1, 2, 3, 5])
@pytest.mark.parametrize("shared", [False, True])
def test_nees_terms_compiled_equals_numpy_solve(n, shared, monkeypatch):
    """The numba kernel and numpy.linalg.solve give the same e^T P^-1 e (to rounding), with the
    covariance per run and step or shared by the runs ((T, n, n), broadcast)."""
    pytest.importorskip("numba")
    import tobitkf.filters._backend as backend

    rng = np.random.default_rng(n)
    N, T = 50, 7
    L = rng.standard_normal((T if shared else N * T, n, n))
    cov = (L @ L.transpose(0, 2, 1) + 0.1 * np.eye(n)).reshape(((T,) if shared else (N, T)) + (n, n))
    err = rng.standard_normal((N, T, n))
    fast = nees_terms(err, cov)
    monkeypatch.setattr(backend, "numba_available", lambda: False)
    ref = nees_terms(err, cov)
    direct = np.einsum(
        "...i,...i->...", err, np.linalg.solve(np.broadcast_to(cov, (N, T, n, n)), err[..., None])[..., 0]
    )
    np.testing.assert_allclose(fast, direct, rtol=1e-10)
    np.testing.assert_allclose(ref, direct, rtol=1e-12)


def test_nees_terms_singular_is_inf_for_that_term_on_both_paths(monkeypatch):
    import tobitkf.filters._backend as backend

    err = np.array([[[1.0, 2.0], [1.0, 0.0]]])
    cov = np.array([[[[2.0, 0.0], [0.0, 4.0]], [[1.0, 1.0], [1.0, 1.0]]]])  # the second is singular
    for available in (True, False):
        if available and not backend.numba_available():
            continue
        monkeypatch.setattr(backend, "numba_available", lambda a=available: a)
        val = nees_terms(err, cov)
        assert val[0, 0] == pytest.approx(1.0 / 2.0 + 4.0 / 4.0) and np.isinf(val[0, 1])


def test_nees_terms_of_a_broadcast_covariance_equals_the_materialized_one():
    """The KF returns a covariance shared by the runs as a broadcast view (run-axis stride 0);
    nees_terms reads it once instead of copying it per run, with the same values."""
    rng = np.random.default_rng(3)
    N, T, n = 40, 6, 2
    L = rng.standard_normal((T, n, n))
    P = L @ L.transpose(0, 2, 1) + 0.5 * np.eye(n)
    err = rng.standard_normal((N, T, n))
    view = np.broadcast_to(P, (N, T, n, n))
    assert view.strides[0] == 0
    np.testing.assert_allclose(nees_terms(err, view), nees_terms(err, np.array(view)), rtol=1e-14)


@pytest.mark.parametrize(
    "err_shape, cov_shape",
    [
        ((4, 3, 2), (4, 3, 3, 3)),  # covariance of another dimension
        ((4, 3, 2), (4, 3, 2)),  # not square
        ((4, 3, 2), (5, 3, 2, 2)),  # runs do not broadcast
        ((4, 3, 2), (2,)),  # not a matrix at all
    ],
)
def test_nees_terms_bad_shapes_raise_shape_error(err_shape, cov_shape):
    with pytest.raises(ShapeError, match="cov: "):
        nees_terms(np.zeros(err_shape), np.ones(cov_shape))
