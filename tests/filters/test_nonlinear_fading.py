"""Fading readings of a NonlinearSystem (y* = theta * h(x) + v): the faded moments, the reductions to the linear
fading filters and to the unfaded nonlinear filters, an independent quadrature of the moments, a Monte Carlo check
against a particle filter of the exact likelihood, the compiled loop against the numpy path, and the errors."""

from __future__ import annotations

import numpy as np
import pytest

import tobitkf as tk
from tobitkf.filters._compiled_fading_moments import fading_moments_batch

TOL = 1e-12

A = np.array([[0.95, 0.1], [-0.1, 0.9]])
C2 = np.array([[1.0, 0.5], [0.0, 1.0]])
Q2 = 0.05 * np.eye(2)
R2 = np.diag([0.3, 0.2])
X0, P0 = np.array([1.0, 0.0]), np.eye(2)
FAD2 = tk.RiceFading.gaussian(0, [[0.8, 1.1]], [[0.05, 0.02]])


def _linear_pair(m: int = 2):
    C, R = C2[:m], R2[:m, :m]
    lin = tk.LinearSystem(A=A, C=C, Q=Q2, R=R, x0=X0, P0=P0)
    nl = tk.NonlinearSystem(
        lambda x, k: x @ A.T, lambda x, k: x @ C.T, Q=Q2, R=R, x0=X0, P0=P0,
        F=lambda x, k: np.broadcast_to(A, x.shape[:-1] + A.shape), H=lambda x, k: np.broadcast_to(C, x.shape[:-1] + C.shape),
    )  # fmt: skip
    return lin, nl


def _f(x, k):
    out = np.empty(x.shape)
    out[..., 0] = x[..., 0] + 0.1 * x[..., 1]
    out[..., 1] = x[..., 1] - 0.1 * np.sin(x[..., 0]) - 0.02 * x[..., 1]
    return out


def _h(x, k):
    out = np.empty(x.shape[:-1] + (2,))
    out[..., 0] = np.sin(x[..., 0]) + 1.0
    out[..., 1] = 0.5 * x[..., 1] + 0.1 * x[..., 0] ** 3
    return out


def _nonlinear() -> tk.NonlinearSystem:
    return tk.NonlinearSystem(
        _f, _h, Q=np.diag([1e-3, 4e-3]), R=np.diag([0.02, 0.05]), x0=[0.8, 0.0], P0=0.1 * np.eye(2)
    )


def _faded(x, h, fading, rng, R):
    """Readings theta * h(x_k) + v for the true states x (N, T+1, n), one fresh gain per run, step and channel."""
    T = x.shape[1] - 1
    hx = np.stack([h(x[:, k], k) for k in range(1, T + 1)], axis=1)
    theta = fading.sample(rng, x.shape[0], T, hx.shape[-1])[:, :, 0, :]
    return theta * hx + rng.standard_normal(hx.shape) * np.sqrt(np.diag(R))


# of order 2: the filters carry the window of past states (tobitkf.filters.nonlinear_fading_window)
FAD_L2 = tk.RiceFading.gaussian(2, [[0.8, 1.1], [0.5, 0.3], [0.3, -0.4]], [[0.05, 0.02], [0.01, 0.03], [0.02, 0.0]])


@pytest.fixture(scope="module", params=[FAD2, FAD_L2], ids=["order 0", "order 2"])
def linear_record(request):
    lin, _ = _linear_pair()
    cens = tk.Censoring(lower=[0.2, -0.3])
    data = tk.simulate(lin, steps=25, runs=6, censoring=cens, measurement=request.param, seed=4)
    y = data.y.copy()
    y[1, 3, 0] = np.nan
    y[2, 0] = np.nan
    return data, cens, y, request.param


# --------------------------------------------------------------------------- exact reductions, linear h


@pytest.mark.parametrize("rule", ["unscented", "cubature"])
def test_adf_with_linear_h_is_the_linear_fading_adf(linear_record, rule):
    data, cens, y, fad = linear_record
    lin, nl = _linear_pair()
    a = tk.FadingAssumedDensityFilter(lin, fad, cens, backend="numpy").filter(y)
    b = tk.FadingNonlinearAssumedDensityFilter(nl, fad, cens, rule=rule, backend="numpy").filter(y)
    np.testing.assert_allclose(b.mean, a.mean, rtol=0, atol=TOL)
    np.testing.assert_allclose(b.cov, a.cov, rtol=0, atol=TOL)
    np.testing.assert_allclose(b.pred_cov, a.pred_cov, rtol=0, atol=TOL)
    np.testing.assert_allclose(b.extras["log_likelihood"], a.extras["log_likelihood"], rtol=0, atol=1e-10)
    # of order 2 the window: the fixed-lag estimates x_(k-s|k) and their covariance
    np.testing.assert_allclose(b.final.aug_mean, a.final.aug_mean, rtol=0, atol=TOL)
    np.testing.assert_allclose(b.final.aug_cov, a.final.aug_cov, rtol=0, atol=TOL)


@pytest.mark.parametrize("kind", ["extended", "unscented"])
def test_tobit_forms_with_linear_h_are_the_tkf_fm(linear_record, kind):
    """Without the fading variance (the source's filter) the Tobit forms are Geng et al.'s TKF-FM."""
    data, cens, y, fad = linear_record
    lin, nl = _linear_pair()
    a = tk.FadingTobitKalmanFilter(lin, fad, cens, covariance_update="standard", backend="numpy").filter(y)
    cls = tk.FadingTobitExtendedKalmanFilter if kind == "extended" else tk.FadingTobitUnscentedKalmanFilter
    b = cls(nl, fad, cens, fading_variance_term=False, backend="numpy").filter(y)
    np.testing.assert_allclose(b.mean, a.mean, rtol=0, atol=TOL)
    np.testing.assert_allclose(b.cov, a.cov, rtol=0, atol=TOL)
    np.testing.assert_allclose(b.extras["expected_y"], a.extras["expected_y"], rtol=0, atol=TOL)
    np.testing.assert_allclose(b.extras["slope"], a.extras["p_uncensored"], rtol=0, atol=TOL)


@pytest.mark.parametrize("kind", ["extended", "unscented"])
def test_kalman_forms_with_linear_h_keep_the_exact_fading_variance(linear_record, kind):
    """One channel: the Kalman update with the faded moments is the fading ADF without censoring (its exact
    second moment under the prediction), and differs from it without the fading variance term."""
    data, _, _, fad2 = linear_record
    lin, nl = _linear_pair(1)
    L = fad2.order
    fad = tk.RiceFading.gaussian(L, [0.8, 0.5, 0.3][: L + 1], [0.05, 0.01, 0.02][: L + 1])
    y = data.y_latent[..., :1]
    a = tk.FadingAssumedDensityFilter(lin, fad, backend="numpy").filter(y)
    cls = tk.FadingExtendedKalmanFilter if kind == "extended" else tk.FadingUnscentedKalmanFilter
    b = cls(nl, fad, backend="numpy").filter(y)
    np.testing.assert_allclose(b.mean, a.mean, rtol=0, atol=TOL)
    np.testing.assert_allclose(b.cov, a.cov, rtol=0, atol=TOL)
    c = cls(nl, fad, fading_variance_term=False, backend="numpy").filter(y)
    assert np.abs(c.cov - a.cov).max() > 1e-3


# --------------------------------------------------------------------------- reductions to the unfaded filters


@pytest.mark.parametrize(
    "faded, plain",
    [
        (lambda s, f, c: tk.FadingExtendedKalmanFilter(s, f), lambda s, c: tk.ExtendedKalmanFilter(s)),
        (lambda s, f, c: tk.FadingUnscentedKalmanFilter(s, f, rule="cubature"),
         lambda s, c: tk.UnscentedKalmanFilter(s, rule="cubature")),
        (lambda s, f, c: tk.FadingTobitExtendedKalmanFilter(s, f, c), lambda s, c: tk.TobitExtendedKalmanFilter(s, c)),
        (lambda s, f, c: tk.FadingTobitUnscentedKalmanFilter(s, f, c),
         lambda s, c: tk.TobitUnscentedKalmanFilter(s, c)),
        (lambda s, f, c: tk.FadingNonlinearAssumedDensityFilter(s, f, c, iterations=2),
         lambda s, c: tk.NonlinearAssumedDensityFilter(s, c, iterations=2)),
    ],
)  # fmt: skip
def test_unit_gain_without_variance_is_the_unfaded_filter(faded, plain):
    sys_ = _nonlinear()
    cens = tk.Censoring(lower=[0.9, -np.inf], upper=[np.inf, 0.05])
    data = tk.simulate(sys_, steps=20, runs=5, censoring=cens, seed=2)
    unit = tk.RiceFading.gaussian(0, [1.0], [0.0])
    a = plain(sys_, cens).filter(data.y)
    b = faded(sys_, unit, cens).filter(data.y)
    np.testing.assert_allclose(b.mean, a.mean, rtol=0, atol=TOL)
    np.testing.assert_allclose(b.cov, a.cov, rtol=0, atol=TOL)
    # a gain variance changes the numbers (the test above can fail)
    c = faded(sys_, tk.RiceFading.gaussian(0, [1.0], [0.1]), cens).filter(data.y)
    assert np.abs(c.cov - a.cov).max() > 1e-4


# --------------------------------------------------------------------------- the moments against quadrature


def test_faded_moments_equal_a_quadrature_over_state_and_gain():
    """E[theta h], Cov(x, theta h), Var(theta h) of a polynomial h under x ~ N(m, P), theta ~ N(g, s2) by a
    tensor Gauss-Hermite rule over (x, theta) (exact for these polynomials), against the filter's moments (its
    Gauss-Hermite rule, exact for h, then the fading formulas)."""
    m, P, g, s2, R = 0.3, 0.5, 0.7, 0.09, 0.2
    sys_ = tk.NonlinearSystem(lambda x, k: x, lambda x, k: x + 0.2 * x**2 - 0.1 * x**3, Q=[[0.1]], R=[[R]],
                              x0=[m], P0=[[P]])  # fmt: skip
    est = tk.FadingUnscentedKalmanFilter(sys_, tk.RiceFading.gaussian(0, [g], [s2]), rule="gauss_hermite", order=4)
    yhat, Pxy, Pyy, _ = est._measurement_moments(1, np.array([[m]]), np.array([[[P]]]))
    z, w = np.polynomial.hermite_e.hermegauss(12)
    w = w / w.sum()
    X = m + np.sqrt(P) * z[:, None]
    TH = g + np.sqrt(s2) * z[None, :]
    W = w[:, None] * w[None, :]
    Yv = TH * (X + 0.2 * X**2 - 0.1 * X**3)
    ey = (W * Yv).sum()
    np.testing.assert_allclose(yhat[0, 0], ey, rtol=1e-12)
    np.testing.assert_allclose(Pxy[0, 0, 0], (W * (X - m) * (Yv - ey)).sum(), rtol=1e-12)
    np.testing.assert_allclose(Pyy[0, 0, 0], (W * (Yv - ey) ** 2).sum(), rtol=1e-12)


def test_faded_moments_off_the_diagonal_are_the_product_of_the_means():
    ym, Pxy = np.array([[1.0, -2.0]]), np.array([[[0.3, 0.1], [0.2, -0.4]]])
    Pyy = np.array([[[2.0, 0.5], [0.5, 1.0]]])
    gm, gv = np.array([0.5, 2.0]), np.array([0.1, 0.0])
    fading_moments_batch(gm, gv, ym, Pxy, Pyy)
    np.testing.assert_allclose(ym, [[0.5, -4.0]], rtol=0, atol=TOL)
    np.testing.assert_allclose(Pxy, [[[0.15, 0.2], [0.1, -0.8]]], rtol=0, atol=TOL)
    np.testing.assert_allclose(Pyy, [[[0.25 * 2.0 + 0.1 * (2.0 + 1.0), 0.5], [0.5, 4.0]]], rtol=0, atol=TOL)


# --------------------------------------------------------------------------- Monte Carlo against the particle filter


def _scalar_model():
    f = lambda x, k: 0.8 * x + 0.4 * np.sin(x)  # noqa: E731
    h = lambda x, k: x + 0.1 * x**2  # noqa: E731
    return tk.NonlinearSystem(f, h, Q=[[0.1]], R=[[0.05]], x0=[1.0], P0=[[0.5]]), f, h


def test_monte_carlo_against_the_particle_filter():
    """The fading UKF on a scalar nonlinear model: its error variance matches its reported variance (NEES of 1
    within four standard errors of the run mean), and its MSE is within 5 % (plus three standard errors of the
    paired difference) of a particle filter's with the exact likelihood; without the fading variance the NEES is
    far above 1 (the filter is over-confident, as the source's, docs/sources GF-04)."""
    sys_, _, h = _scalar_model()
    g, s2 = 0.9, 0.09
    fad = tk.RiceFading.gaussian(0, [g], [s2])
    N, T = 300, 30
    data = tk.simulate(sys_, steps=T, runs=N, seed=11)
    y = _faded(data.x, h, fad, np.random.default_rng(12), sys_.R.at(1))
    truth = data.x[:, 1:, 0]
    out = tk.FadingUnscentedKalmanFilter(sys_, fad).filter(y)
    err2 = (out.mean[..., 0] - truth) ** 2
    nees = (err2 / out.cov[..., 0, 0]).mean(axis=1)
    se = nees.std(ddof=1) / np.sqrt(N)
    assert abs(nees.mean() - 1.0) < 4 * se, (nees.mean(), se)
    means_only = tk.FadingUnscentedKalmanFilter(sys_, fad, fading_variance_term=False).filter(y)
    nees0 = (((means_only.mean[..., 0] - truth) ** 2) / means_only.cov[..., 0, 0]).mean(axis=1)
    assert nees0.mean() - 1.0 > 4 * nees0.std(ddof=1) / np.sqrt(N), nees0.mean()
    # the particle filter of the exact likelihood y | x ~ N(g h(x), s2 h(x)^2 + R), resampled every step
    pf = tk.ParticleFilter(sys_, fad, particles=2000, resample_threshold=1.0, seed=13).filter(y).mean[..., 0]
    mse_ukf, mse_pf = err2.mean(axis=1), ((pf - truth) ** 2).mean(axis=1)
    d = mse_ukf - mse_pf
    assert d.mean() < 0.05 * mse_pf.mean() + 3 * d.std(ddof=1) / np.sqrt(N), (mse_ukf.mean(), mse_pf.mean())


# --------------------------------------------------------------------------- batches, steps, compiled


def test_batched_equals_per_run_equals_step_by_step():
    sys_ = _nonlinear()
    cens = tk.Censoring(lower=[0.9, -np.inf])
    data = tk.simulate(sys_, steps=12, runs=6, censoring=cens, seed=5)
    y = data.y.reshape(2, 3, 12, 2)
    est = tk.FadingTobitUnscentedKalmanFilter(sys_, FAD2, cens, backend="numpy")
    full = est.filter(y)
    for i in range(2):
        for j in range(3):
            one = est.filter(y[i, j])
            np.testing.assert_allclose(one.mean, full.mean[i, j], rtol=0, atol=TOL)
            np.testing.assert_allclose(one.cov, full.cov[i, j], rtol=0, atol=TOL)
    state = est.init(batch_shape=(2, 3))
    for t in range(12):
        state = est.step(state, y[:, :, t])
        np.testing.assert_allclose(state.x.reshape(2, 3, 2), full.mean[:, :, t], rtol=0, atol=TOL)


@pytest.mark.parametrize(
    "make",
    [
        lambda s, c, b: tk.FadingExtendedKalmanFilter(s, FAD2, backend=b),
        lambda s, c, b: tk.FadingUnscentedKalmanFilter(s, FAD2, backend=b),
        lambda s, c, b: tk.FadingTobitExtendedKalmanFilter(s, FAD2, c, backend=b),
        lambda s, c, b: tk.FadingTobitUnscentedKalmanFilter(s, FAD2, c, rule="cubature", backend=b),
        lambda s, c, b: tk.FadingNonlinearAssumedDensityFilter(s, FAD2, c, backend=b),
        lambda s, c, b: tk.FadingNonlinearAssumedDensityFilter(s, FAD2, c, iterations=3, backend=b),
    ],
    ids=["ekf", "ukf", "tobit-ekf", "tobit-ukf", "adf", "adf-iterated"],
)
def test_compiled_loop_equals_numpy_path_filter_and_step(make):
    """On the compiled oscillator the compiled nonlinear filters' own tests use (its f is this module's, its h
    without the offset of channel 0): the faded loop is the same compiled version as the unfaded one (the gains are
    an argument), so these cases compile nothing of their own."""
    pytest.importorskip("numba")
    from ._nonlinear_oscillator import f_osc, h_osc

    sys_ = tk.NonlinearSystem(f_osc, h_osc, Q=np.diag([1e-3, 4e-3]), R=np.diag([0.02, 0.05]), x0=[0.8, 0.0],
                              P0=0.1 * np.eye(2))  # fmt: skip
    cens = tk.Censoring(lower=[0.3, -np.inf], upper=[np.inf, 0.05])
    rng = np.random.default_rng(6)
    data = tk.simulate(sys_, steps=15, runs=5, seed=6)
    y = cens.clip(_faded(data.x, sys_.h, FAD2, rng, sys_.R.at(1)))
    assert 0.1 < cens.at_limit(y).mean() < 0.9  # both limits are met
    y[2, 4, 1] = np.nan
    a = make(sys_, cens, "numpy").filter(y)
    est = make(sys_, cens, "numba")
    b = est.filter(y)
    np.testing.assert_allclose(b.mean, a.mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(b.cov, a.cov, rtol=0, atol=1e-10)
    for key in a.extras:
        np.testing.assert_allclose(b.extras[key], a.extras[key], rtol=0, atol=1e-10)
    state = est.init(batch_shape=(5,))
    for t in range(15):
        state = est.step(state, y[:, t])
    np.testing.assert_allclose(state.x, a.mean[:, -1], rtol=0, atol=1e-10)


# --------------------------------------------------------------------------- errors


def test_bad_fading_parameters_are_refused_with_the_argument_named():
    sys_ = _nonlinear()
    with pytest.raises(tk.ValidationError, match="fading"):
        tk.FadingExtendedKalmanFilter(sys_, [0.9])
    with pytest.raises(tk.ShapeError, match="channels"):
        tk.FadingExtendedKalmanFilter(sys_, tk.RiceFading.gaussian(0, [[0.9, 0.8, 0.7]], [[0.0, 0.0, 0.0]]))
    with pytest.raises(tk.ValidationError, match="variance"):
        tk.RiceFading.gaussian(0, [0.9], [-0.1])
    with pytest.raises(tk.ValidationError, match="fading_variance_term"):
        tk.FadingExtendedKalmanFilter(sys_, tk.RiceFading(0, [0.9]), fading_variance_term="yes")
    with pytest.raises(tk.ValidationError, match="covariance_update"):
        tk.FadingUnscentedKalmanFilter(sys_, tk.RiceFading(0, [0.9]), covariance_update="square_root")
    with pytest.raises(tk.ValidationError, match="censoring"):
        tk.FadingTobitExtendedKalmanFilter(sys_, tk.RiceFading(0, [0.9]), "lower")
    lin, _ = _linear_pair()
    with pytest.raises(tk.ValidationError, match="system"):
        tk.FadingExtendedKalmanFilter(lin, tk.RiceFading(0, [0.9]))


# --------------------------------------------------------------------------- simulation


def test_simulate_draws_faded_readings_of_a_nonlinear_system_then_censors_them():
    sys_ = tk.NonlinearSystem(_f, _h, Q=np.diag([1e-3, 4e-3]), R=1e-20 * np.eye(2), x0=[0.8, 0.0], P0=0.1 * np.eye(2))
    cens = tk.Censoring(lower=[0.9, -np.inf])
    N, T = 400, 10
    data = tk.simulate(sys_, steps=T, runs=N, channel=[FAD2, cens], seed=8)
    theta = data.extras["fading"][:, :, 0, :]
    hx = np.stack([_h(data.x[:, k], k) for k in range(1, T + 1)], axis=1)
    np.testing.assert_allclose(data.y_latent, theta * hx, rtol=0, atol=1e-8)  # v has a standard deviation 1e-10
    np.testing.assert_array_equal(data.y, cens.clip(data.y_latent))
    # the gains' law: mean and variance per channel within five standard errors of N T draws
    flat = theta.reshape(-1, 2)
    mean, var = FAD2.mean_gains(2)[0], FAD2.var_gains(2)[0]
    assert (np.abs(flat.mean(0) - mean) < 5 * np.sqrt(var / flat.shape[0])).all()
    assert (np.abs(flat.var(0) - var) < 5 * var * np.sqrt(2 / flat.shape[0])).all()
