"""The square-root covariance form (``covariance_update="square_root"``) of the KF and the TKF.

The form propagates a factor S with P = S S^T through QR factorizations
(``tobitkf.filters.core.sqrt_predict`` / ``sqrt_update``). In exact arithmetic it is the
same filter as the standard form, so on well-conditioned models the two must agree to
rounding; the hard, ill-conditioned case where only this form stays PSD is tested in
``tests/reliability/test_extremes_families.py`` against a 60-digit reference.

Tolerances: the KF forms differ by a few ulps per step on these models (measured <= 5e-15
relative), so 1e-10 leaves a wide margin yet fails on any algebraic slip (a missing term is
O(1)). The TKF evaluates its channel statistics at the predicted mean, a nonlinear
feedback that carries rounding differences from step to step (measured <= 3e-12 relative
over 30 steps); 1e-10 still separates that from an error in the update.
"""

from __future__ import annotations

import numpy as np
import pytest

import tobitkf as tk
from tobitkf import ValidationError
from tobitkf.channels.fading import RiceFading
from tobitkf.channels.protocol import ProtocolChannel
from tobitkf.filters.core import psd_sqrt, sqrt_predict, sqrt_update
from tobitkf.filters.fading import FadingKalmanFilter, FadingTobitKalmanFilter
from tobitkf.filters.kalman import kalman_filter
from tobitkf.filters.protocol import ProtocolTobitKalmanFilter
from tobitkf.filters.tobit import NOISE_TERMS, tobit_kalman_filter, tobit_update

RTOL = 1e-10


def random_system(n, m, seed, *, diagonal_R):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    A *= 0.9 / np.abs(np.linalg.eigvals(A)).max()
    C = rng.normal(size=(m, n))
    G = rng.normal(size=(n, n))
    Q = G @ G.T / n + 0.01 * np.eye(n)
    if diagonal_R:
        R = np.diag(rng.uniform(0.1, 1.0, size=m))
    else:
        F = rng.normal(size=(m, m))
        R = F @ F.T / m + 0.1 * np.eye(m)
    H = rng.normal(size=(n, n))
    return tk.LinearSystem(A=A, C=C, Q=Q, R=R, x0=rng.normal(size=n), P0=H @ H.T / n + 0.1 * np.eye(n))


def with_gaps(y, seed, frac=0.2):
    y = np.array(y, dtype=float)
    y[np.random.default_rng(seed).random(y.shape) < frac] = np.nan
    return y


def assert_rel(a, b, rtol=RTOL):
    """max |a - b| <= rtol x max |b| (one scale per array: the outputs are O(1) here)."""
    a, b = np.asarray(a), np.asarray(b)
    err = np.abs(a - b).max() / np.abs(b).max()
    assert err <= rtol, err


def assert_same_filter(a, b, rtol=RTOL):
    for name in ("mean", "cov", "pred_mean", "pred_cov"):
        assert_rel(getattr(a, name), getattr(b, name), rtol)


# --- 1. equal to the standard form on ordinary models ---------------------------------------
@pytest.mark.parametrize("n", [1, 2, 4])
@pytest.mark.parametrize("m", [1, 3])
def test_kf_square_root_equals_standard(n, m):
    s = random_system(n, m, seed=10 * n + m, diagonal_R=False)  # the KF allows correlated R
    data = tk.simulate(s, 30, 5, seed=n + m)
    for y in (data.y, with_gaps(data.y, seed=m)):
        ref = tk.KalmanFilter(s, backend="numpy").filter(y)
        out = tk.KalmanFilter(s, covariance_update="square_root").filter(y)
        assert_same_filter(out, ref)
        np.testing.assert_array_equal(out.cov, np.swapaxes(out.cov, -1, -2))
        np.testing.assert_array_equal(out.pred_cov, np.swapaxes(out.pred_cov, -1, -2))


@pytest.mark.parametrize("noise_term", NOISE_TERMS)
@pytest.mark.parametrize("n", [1, 2, 4])
@pytest.mark.parametrize("m", [1, 3])
def test_tkf_square_root_equals_standard(noise_term, n, m):
    s = random_system(n, m, seed=10 * n + m, diagonal_R=True)
    cens = tk.Censoring(lower=-0.5, upper=0.8)  # two-sided, both limits active
    data = tk.simulate(s, 30, 5, censoring=cens, seed=n + m)
    lo, hi = cens.censored_mask(data.y)
    assert lo.any() and hi.any()
    y = with_gaps(data.y, seed=m)
    ref = tk.TobitKalmanFilter(s, cens, noise_term=noise_term, backend="numpy").filter(y)
    out = tk.TobitKalmanFilter(s, cens, noise_term=noise_term, covariance_update="square_root").filter(y)
    assert_same_filter(out, ref)
    assert_rel(out.extras["p_uncensored"], ref.extras["p_uncensored"])
    np.testing.assert_array_equal(out.cov, np.swapaxes(out.cov, -1, -2))


def test_time_varying_system_with_inputs_noise_input_and_singular_noise():
    """A_k, C_k, R_k per step, a noise input B with a singular Q (a zero row), control
    inputs, and P0 = 0: the eigen-decomposition roots and the per-step factorizations."""
    T, n, m = 25, 3, 2
    rng = np.random.default_rng(4)
    A = np.array([0.8 * np.eye(n) + 0.1 * rng.normal(size=(n, n)) for _ in range(T)])
    C = rng.normal(size=(T, m, n))
    R = np.array([np.diag(rng.uniform(0.2, 1.0, size=m)) for _ in range(T)])
    B = rng.normal(size=(n, 2))
    Q = np.diag([0.3, 0.0])  # singular: Cholesky fails
    s = tk.LinearSystem(
        A=A, C=C, Q=Q, R=R, B=B, Bu=np.ones((n, 1)), D=0.5 * np.ones((m, 1)), x0=np.zeros(n), P0=np.zeros((n, n))
    )
    u = rng.normal(size=(T, 1))
    y = with_gaps(rng.normal(size=(4, T, m)), seed=1)
    ref = kalman_filter(s, y, u=u, backend="numpy")
    assert_same_filter(kalman_filter(s, y, u=u, covariance_update="square_root"), ref)
    cens = tk.Censoring(lower=-0.3)
    yc = np.maximum(y, -0.3)
    ref = tobit_kalman_filter(s, cens, yc, u=u, backend="numpy")
    assert_same_filter(tobit_kalman_filter(s, cens, yc, u=u, covariance_update="square_root"), ref)


def test_dropping_filter_and_skip_get_the_form():
    s = random_system(2, 3, seed=7, diagonal_R=False)
    cens = tk.Censoring(lower=-0.2)
    data = tk.simulate(s, 40, 3, censoring=cens, seed=2)
    ref = tk.DroppingKalmanFilter(s, cens).filter(data.y)
    out = tk.DroppingKalmanFilter(s, cens, covariance_update="square_root").filter(data.y)
    assert_same_filter(out, ref)


def test_tobit_update_square_root_equals_standard():
    s = random_system(3, 3, seed=1, diagonal_R=True)
    rng = np.random.default_rng(0)
    x = rng.normal(size=(6, 3))
    G = rng.normal(size=(6, 3, 3))
    P = G @ np.swapaxes(G, -1, -2) + 0.1 * np.eye(3)
    y = np.clip(rng.normal(size=(6, 3)), -0.4, 0.6)
    y[2, 1] = np.nan
    sigma = np.sqrt(np.diagonal(s.R.array))
    for nt in NOISE_TERMS:
        a = tobit_update(x, P, y, s.C.array, sigma, np.full(3, -0.4), np.full(3, 0.6), noise_term=nt)
        b = tobit_update(
            x, P, y, s.C.array, sigma, np.full(3, -0.4), np.full(3, 0.6), noise_term=nt, covariance_update="square_root"
        )
        assert_rel(b[0], a[0])
        assert_rel(b[1], a[1])


# --- the building blocks against their defining identities -----------------------------------
def test_sqrt_predict_and_update_identities():
    rng = np.random.default_rng(3)
    N, n, m = 5, 3, 2
    S = np.tril(rng.normal(size=(N, n, n)))
    A = rng.normal(size=(n, n))
    Groot = rng.normal(size=(n, 2))  # rank-2 noise
    _, Sp = sqrt_predict(np.zeros((N, n)), S, A, Groot)
    P = S @ np.swapaxes(S, -1, -2)
    np.testing.assert_allclose(Sp @ np.swapaxes(Sp, -1, -2), A @ P @ A.T + Groot @ Groot.T, rtol=1e-12, atol=1e-12)
    assert np.allclose(Sp, np.tril(Sp))
    H = rng.normal(size=(1, m, n))
    R = np.array([[0.5, 0.1], [0.1, 0.3]])[None]
    Pp = Sp @ np.swapaxes(Sp, -1, -2)
    e = rng.normal(size=(N, m))
    x, Pn, Sn, K = sqrt_update(np.zeros((N, n)), Sp, e, H, R)
    Ree = H @ Pp @ np.swapaxes(H, -1, -2) + R
    Kref = np.swapaxes(np.linalg.solve(Ree, H @ Pp), -1, -2)
    np.testing.assert_allclose(K, Kref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(Pn, Pp - Kref @ H @ Pp, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(x, np.einsum("...ij,...j->...i", Kref, e), rtol=1e-12, atol=1e-12)
    # a left-out channel: zero gain column, and the update of the model without it
    valid = np.ones((N, m), bool)
    valid[1, 0] = False
    _, P1, _, K1 = sqrt_update(np.zeros((N, n)), Sp, e, H, R, valid)
    assert np.all(K1[1, :, 0] == 0.0)
    h, r = H[0, 1:], R[0, 1:, 1:]
    k = Pp[1] @ h.T / (h @ Pp[1] @ h.T + r)
    np.testing.assert_allclose(P1[1], Pp[1] - k @ h @ Pp[1], rtol=1e-12, atol=1e-12)


def test_psd_sqrt_of_singular_and_definite_matrices():
    for M in (np.diag([2.0, 0.0, 1.0]), np.zeros((2, 2)), np.array([[4.0, 2.0], [2.0, 3.0]])):
        L = psd_sqrt(M)
        np.testing.assert_allclose(L @ L.T, M, atol=1e-14)


# --- 2. batched equals per-run --------------------------------------------------------------
@pytest.mark.parametrize("which", ["kf", "tkf"])
def test_batched_equals_each_run_alone(which):
    """Each run of a batch equals that run filtered alone (a mix-up of runs would be O(1)).

    The KF agrees to 1e-12 of the scale (measured 2e-16: the same operations, in another
    summation order at most). The TKF re-evaluates its censored statistics at every
    predicted mean, so a one-ulp difference of the batched products is fed back and grows
    where a run is heavily censored (run 0 here reaches p_uncensored = 3e-7): the standard
    form itself shows 8e-13 (and 1e-10 with other limits on the same model) between batched
    and alone; the square-root form 4e-12. Bound for the TKF: 1e-10 relative.
    """
    s = random_system(3, 2, seed=5, diagonal_R=True)
    cens = tk.Censoring(lower=-0.3, upper=1.0)
    data = tk.simulate(s, 30, 4, censoring=cens, seed=9)
    y = with_gaps(data.y, seed=3)
    y[0] = data.y[0]  # a run without gaps (the shared-P path alone)
    if which == "kf":
        run, rtol = (lambda yy: tk.KalmanFilter(s, covariance_update="square_root").filter(yy)), 1e-12
    else:
        run, rtol = (lambda yy: tk.TobitKalmanFilter(s, cens, covariance_update="square_root").filter(yy)), 1e-10
    batch = run(y)
    for i in range(y.shape[0]):
        one = run(y[i])
        for name in ("mean", "cov", "pred_mean", "pred_cov"):
            a, b = getattr(batch, name)[i], getattr(one, name)
            np.testing.assert_allclose(a, b, rtol=0, atol=rtol * np.abs(b).max())


# --- 4. options ------------------------------------------------------------------------------
def test_numba_backend_refuses_square_root():
    s = random_system(2, 1, seed=0, diagonal_R=True)
    y = np.zeros((5, 1))
    msg = "backend: the compiled path of the {} has no square-root form"
    with pytest.raises(ValidationError, match=msg.format("Kalman filter")):
        tk.KalmanFilter(s, covariance_update="square_root", backend="numba")
    with pytest.raises(ValidationError, match=msg.format("Kalman filter")):
        kalman_filter(s, y, covariance_update="square_root", backend="numba")
    with pytest.raises(ValidationError, match=msg.format("Tobit Kalman filter")):
        tk.TobitKalmanFilter(s, tk.Censoring(), covariance_update="square_root", backend="numba")
    with pytest.raises(ValidationError, match=msg.format("Tobit Kalman filter")):
        tobit_kalman_filter(s, tk.Censoring(), y, covariance_update="square_root", backend="numba")


def test_auto_backend_runs_the_numpy_square_root_path():
    s = random_system(2, 2, seed=2, diagonal_R=True)
    y = tk.simulate(s, 20, 3, seed=0).y
    for make in (
        lambda b: tk.KalmanFilter(s, covariance_update="square_root", backend=b),
        lambda b: tk.TobitKalmanFilter(s, tk.Censoring(upper=0.5), covariance_update="square_root", backend=b),
    ):
        a, b = make("auto").filter(np.minimum(y, 0.5)), make("numpy").filter(np.minimum(y, 0.5))
        np.testing.assert_array_equal(a.mean, b.mean)
        np.testing.assert_array_equal(a.cov, b.cov)


def test_unknown_form_lists_the_allowed_values():
    s = random_system(2, 1, seed=0, diagonal_R=True)
    allowed = "expected one of 'standard', 'joseph', 'square_root', got 'sqrt'"
    with pytest.raises(ValidationError, match=f"covariance_update: {allowed}"):
        tk.KalmanFilter(s, covariance_update="sqrt")
    with pytest.raises(ValidationError, match=f"covariance_update: {allowed}"):
        tk.TobitKalmanFilter(s, tk.Censoring(), covariance_update="sqrt")
    with pytest.raises(ValidationError, match=f"covariance_update: {allowed}"):
        tk.DroppingKalmanFilter(s, tk.Censoring(), covariance_update="sqrt")


def test_every_gaussian_family_has_the_square_root_form():
    """The fading and protocol filters (their own update before the shared core) take the form too,
    equal to their Joseph default to rounding (a convention change: they used to refuse it)."""
    s = random_system(2, 1, seed=0, diagonal_R=True)
    fad = RiceFading.gaussian(1, [0.9, 0.5], [0.01, 0.02])
    cens = tk.Censoring(lower=-0.5)
    y = tk.simulate(s, 25, 6, censoring=cens, measurement=fad, seed=3).y
    for make in (
        lambda f: FadingTobitKalmanFilter(s, fad, cens, covariance_update=f),
        lambda f: FadingKalmanFilter(s, fad, covariance_update=f),
    ):
        a, b = make("joseph").filter(y), make("square_root").filter(y)
        assert_rel(b.mean, a.mean)
        assert_rel(b.cov, a.cov)
    ch = ProtocolChannel(1, window=2, threshold=-0.5)
    yp = tk.simulate(s, 25, 6, channel=ch, seed=4).y
    a = ProtocolTobitKalmanFilter(s, ch).filter(yp)
    b = ProtocolTobitKalmanFilter(s, ch, covariance_update="square_root").filter(yp)
    assert_rel(b.mean, a.mean)
    assert_rel(b.cov, a.cov)
