"""The restructured time loops (GEMMs over stacked runs, sliced stores) against the textbook
dense formulas, step by step, on recorded intermediate quantities."""

from __future__ import annotations

import numpy as np
import pytest

import tobitkf as tk
from tobitkf.channels.fading import RiceFading
from tobitkf.filters.fading import FadingTobitKalmanFilter, augmented_measurement_matrix


def _oscillator(P0=None):
    w = 0.052 * np.pi
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    return tk.LinearSystem(
        A=A, C=[[1.0, 0.0]], Q=0.0025 * np.eye(2), R=[[1.0]], x0=[5.0, 0.0], P0=np.eye(2) if P0 is None else P0
    )


def test_fading_prediction_equals_dense_augmented_recursion():
    """(17)-(18) with the shift structure and one GEMM == sym(A_aug P A_aug^T + B Q B^T), every step."""
    sys_ = _oscillator(P0=[[1.0, 0.3], [0.3, 0.5]])
    cens = tk.Censoring(lower=0.0)
    fad = RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    y = tk.simulate(sys_, 30, 40, censoring=cens, measurement=fad, seed=3).y
    res = FadingTobitKalmanFilter(sys_, fad, cens).filter(y, keep_augmented=True)
    ex = res.extras
    n, nxi = 2, 6
    Aa = np.zeros((nxi, nxi))
    Aa[:n, :n] = sys_.transition(0)
    Aa[n:, : nxi - n] = np.eye(nxi - n)
    Qa = np.zeros((nxi, nxi))
    Qa[:n, :n] = sys_.process_cov(0)
    P = np.zeros((40, nxi, nxi))
    P[:, :n, :n] = sys_.P0
    for k in range(30):
        dense = Aa @ P @ Aa.T + Qa
        dense = 0.5 * (dense + np.swapaxes(dense, -1, -2))
        np.testing.assert_allclose(ex["aug_pred_cov"][:, k], dense, rtol=0, atol=1e-12)
        assert np.array_equal(ex["aug_pred_cov"][:, k], np.swapaxes(ex["aug_pred_cov"][:, k], -1, -2))
        # (20') Joseph form with G = gamma H, from the recorded gain and noise
        H = augmented_measurement_matrix(sys_, fad, k + 1)
        G = ex["p_uncensored"][:, k, :, None] * H
        K = ex["gain"][:, k]
        Rxe = ex["aug_pred_cov"][:, k] @ np.swapaxes(G, -1, -2)  # (24), dense
        np.testing.assert_allclose(K, Rxe / ex["innovation_cov"][:, k], rtol=1e-12, atol=1e-15)
        noise = ex["innovation_cov"][:, k] - G @ ex["aug_pred_cov"][:, k] @ np.swapaxes(G, -1, -2)
        IKG = np.eye(nxi) - K @ G
        joseph = IKG @ ex["aug_pred_cov"][:, k] @ np.swapaxes(IKG, -1, -2) + K @ noise @ np.swapaxes(K, -1, -2)
        np.testing.assert_allclose(
            ex["aug_cov"][:, k], 0.5 * (joseph + np.swapaxes(joseph, -1, -2)), rtol=0, atol=1e-12
        )
        P = ex["aug_cov"][:, k]


def test_fading_smoothed_blocks_are_the_diagonal_blocks():
    sys_ = _oscillator()
    cens = tk.Censoring(lower=0.0)
    fad = RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    y = tk.simulate(sys_, 12, 7, censoring=cens, measurement=fad, seed=5).y
    res = FadingTobitKalmanFilter(sys_, fad, cens).filter(y, keep_augmented=True)
    ac, sc = res.extras["aug_cov"], res.extras["smoothed_cov"]
    for s in range(3):
        blk = ac[:, :, 2 * s : 2 * s + 2, 2 * s : 2 * s + 2]
        defined = np.arange(12) + 1 >= s  # block s at step k is x_{k-s}: defined for k >= s
        assert np.array_equal(sc[:, defined, s], blk[:, defined])
        assert np.isnan(sc[:, ~defined, s]).all()
    assert np.array_equal(res.cov, ac[:, :, :2, :2])


def test_shift_predict_equals_dense_block_shift():
    from tobitkf.filters.core import shift_predict

    rng = np.random.default_rng(11)
    N, n, blocks = 9, 3, 4
    nxi = n * blocks
    B = rng.standard_normal((N, nxi, nxi))
    P = B @ np.swapaxes(B, -1, -2)
    P = 0.5 * (P + np.swapaxes(P, -1, -2))
    xi = rng.standard_normal((N, nxi))
    A = rng.standard_normal((n, n))
    Qd = np.eye(n) * 0.3
    bx = rng.standard_normal((N, n))
    Aa = np.zeros((nxi, nxi))
    Aa[:n, :n] = A
    Aa[n:, :-n] = np.eye(nxi - n)
    Qa = np.zeros((nxi, nxi))
    Qa[:n, :n] = Qd
    xp, Pp = shift_predict(xi, P, A, Qd, bx)
    dense = Aa @ P @ Aa.T + Qa
    np.testing.assert_allclose(Pp, 0.5 * (dense + np.swapaxes(dense, -1, -2)), rtol=1e-13, atol=1e-12)
    assert np.array_equal(Pp, np.swapaxes(Pp, -1, -2))
    np.testing.assert_allclose(xp, xi @ Aa.T + np.pad(bx, ((0, 0), (0, nxi - n))), rtol=1e-14, atol=1e-14)
    assert np.array_equal(xp[:, n:], xi[:, :-n])


def test_protocol_prediction_equals_dense_augmented_recursion():
    from tobitkf.channels.protocol import LAMBDA_BASE, ProtocolChannel
    from tobitkf.filters.protocol import protocol_tobit_kalman_filter
    from tobitkf.filters.protocol_model import FAILURE_TERMS, augmented_transition

    w = 0.052 * np.pi
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    sys_ = tk.LinearSystem(A=A, C=np.eye(2), Q=0.0025 * np.eye(2), R=np.eye(2), x0=[5.0, 0.0], P0=np.eye(2))
    ch = ProtocolChannel(2, window=2, failures=LAMBDA_BASE, threshold=0.0)
    y = tk.simulate(sys_, 25, 30, seed=2, channel=ch).y
    Aa = augmented_transition(A, 2)
    Qa = np.zeros((6, 6))
    Qa[:2, :2] = sys_.process_cov(0)
    for mode in FAILURE_TERMS:
        res = protocol_tobit_kalman_filter(sys_, ch, y, failure_term=mode, keep_augmented=True)
        ex = res.extras
        for k in range(1, 25):
            dense = Aa @ ex["aug_cov"][:, k - 1] @ Aa.T + Qa
            np.testing.assert_allclose(
                ex["aug_pred_cov"][:, k], 0.5 * (dense + np.swapaxes(dense, -1, -2)), rtol=0, atol=1e-12
            )
            np.testing.assert_allclose(ex["aug_pred_mean"][:, k], ex["aug_mean"][:, k - 1] @ Aa.T, rtol=0, atol=1e-12)


def test_protocol_joseph_rank_one_equals_dense_joseph():
    """protocol_update's Joseph form (rank-one factors applied in turn) == the dense product to 1e-12."""
    from tobitkf.filters.protocol_model import protocol_update

    rng = np.random.default_rng(4)
    N, nxi = 50, 6
    B = rng.standard_normal((N, nxi, nxi))
    P = B @ np.swapaxes(B, -1, -2)
    P = 0.5 * (P + np.swapaxes(P, -1, -2))
    xi = rng.standard_normal((N, nxi))
    Cc = np.tile([1.0, 0.5], 3)
    y = np.abs(rng.standard_normal(N)) + 0.1
    gam = np.ones(N, dtype=bool)
    for mode in ("variance", "literal", "second_moment"):
        _, P_new, info = protocol_update(xi, P, y, gam, Cc, 1.0, 0.0, 0.5, 0.25, failure_term=mode)
        H = 0.5 * Cc
        PH = P @ H
        S = info["innovation_var"]
        K = PH / S[:, None]
        extra = S - PH @ H  # F + noise of (24)
        IKH = np.eye(nxi) - K[:, :, None] * H
        dense = IKH @ P @ np.swapaxes(IKH, -1, -2) + extra[:, None, None] * (K[:, :, None] * K[:, None, :])
        np.testing.assert_allclose(
            P_new, 0.5 * (dense + np.swapaxes(dense, -1, -2)), rtol=0, atol=1e-12 * np.abs(dense).max()
        )
        assert np.array_equal(P_new, np.swapaxes(P_new, -1, -2))


@pytest.mark.parametrize("m", [1, 3])
def test_shared_joseph_update_equals_dense_gain_update(m):
    """The shared Joseph update (rank-m products, H = diag(scale) H0) == gain_update(H=G, noise=N) with the
    dense (I-KH)P(I-KH)^T + KNK^T: x, K and P to 1e-12; masks and degenerate R_ee (the former
    m = 1 fast path of the fading filter, now the one update of every family)."""
    from tobitkf.filters.core import MeasurementPrediction, gain_update, measurement_update

    rng = np.random.default_rng(8)
    N, nxi = 40, 6
    B = rng.standard_normal((N, nxi, nxi))
    P = B @ np.swapaxes(B, -1, -2)
    P = 0.5 * (P + np.swapaxes(P, -1, -2))
    x = rng.standard_normal((N, nxi))
    H0 = rng.standard_normal((m, nxi))
    gam = rng.uniform(0.0, 1.0, (N, m))
    gam[:3] = 0.0  # G = 0: R_ee = noise
    noise = rng.uniform(0.1, 1.0, (N, m))
    noise[:2] = 0.0  # R_ee = 0: degenerate, channel dropped
    noise[2] = 1e-310  # subnormal R_ee: dropped as in gain_update
    G = gam[:, :, None] * H0
    Rxe = P @ np.swapaxes(G, -1, -2)
    Ree = G @ Rxe + noise[:, :, None] * np.eye(m)
    yhat = rng.standard_normal((N, m))
    y = yhat + rng.standard_normal((N, m))
    for valid in (None, rng.uniform(size=(N, m)) > 0.3):
        mp = MeasurementPrediction(expected=yhat, H0=H0, scale=gam, noise=noise, valid=valid)
        x1, P1, _, K1, _ = measurement_update(x, P, None, y, mp, "joseph")
        with np.errstate(divide="ignore", invalid="ignore"):
            x2, P2, K2 = gain_update(x, P, y - yhat, Rxe, Ree, valid, H=G, noise=noise[:, :, None] * np.eye(m))
        # the moments come from GEMMs over the stacked runs here, from batched matmuls there: rounding
        np.testing.assert_allclose(K1, K2, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(x1, x2, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(P1, P2, rtol=0, atol=1e-12 * np.abs(P2).max())
        assert np.array_equal(P1, np.swapaxes(P1, -1, -2))
        ok = Ree[:, np.arange(m), np.arange(m)] > 1e-300
        dropped = ~ok.any(axis=1) if valid is None else ~(valid & ok).any(axis=1)
        assert np.array_equal(P1[dropped], P[dropped])


def test_time_major_outputs_keep_batch_layout():
    """Outputs stored (T, N, ...) and returned runs-first: a (2, 3, T, m) batch gives the flat result reshaped."""
    from tobitkf.channels.protocol import LAMBDA_BASE, ProtocolChannel
    from tobitkf.filters.protocol import protocol_tobit_kalman_filter

    sys_ = _oscillator()
    cens = tk.Censoring(lower=0.0)
    fad = RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    y = tk.simulate(sys_, 9, 6, censoring=cens, measurement=fad, seed=1).y
    flat = FadingTobitKalmanFilter(sys_, fad, cens).filter(y)
    nest = FadingTobitKalmanFilter(sys_, fad, cens).filter(y.reshape(2, 3, 9, 1))
    one = FadingTobitKalmanFilter(sys_, fad, cens).filter(y[4])
    for name in ("mean", "cov", "pred_mean", "pred_cov"):
        a, b = getattr(flat, name), getattr(nest, name)
        assert b.shape == (2, 3) + a.shape[1:] and np.array_equal(b.reshape(a.shape), a)
        # one run alone: the GEMMs over stacked runs may round differently with another row count
        np.testing.assert_allclose(getattr(one, name), a[4], rtol=1e-12, atol=1e-14)
    for key in ("smoothed_cov", "p_uncensored"):
        assert np.array_equal(nest.extras[key].reshape(flat.extras[key].shape), flat.extras[key], equal_nan=True)

    w = 0.052 * np.pi
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    sp = tk.LinearSystem(A=A, C=np.eye(2), Q=0.0025 * np.eye(2), R=np.eye(2), x0=[5.0, 0.0], P0=np.eye(2))
    ch = ProtocolChannel(2, window=2, failures=LAMBDA_BASE, threshold=0.0)
    yp = tk.simulate(sp, 9, 6, seed=1, channel=ch).y
    flat = protocol_tobit_kalman_filter(sp, ch, yp)
    nest = protocol_tobit_kalman_filter(sp, ch, yp.reshape((2, 3) + yp.shape[1:]))
    for name in ("mean", "cov", "pred_mean", "pred_cov"):
        a, b = getattr(flat, name), getattr(nest, name)
        assert b.shape == (2, 3) + a.shape[1:] and np.array_equal(b.reshape(a.shape), a)
    assert np.array_equal(nest.extras["innovation"].reshape(6, 9), flat.extras["innovation"])
