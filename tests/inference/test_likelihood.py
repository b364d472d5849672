"""Likelihoods: the assumed-density update and likelihood of one censored reading against quadrature,
the ADF's error on a censored AR(1) with T = 3, and the exact censored-AR likelihood against
independent computations (stacked Gaussian density without censoring, nested quadrature and Genz's
algorithm with censoring), its compiled and numpy paths, and its posterior moments."""

import numpy as np
import pytest
from scipy import integrate
from scipy.stats import multivariate_normal as mvn
from scipy.stats import norm

import tobitkf as tk
from tobitkf._validation import ShapeError, ValidationError
from tobitkf.filters.assumed_density import censored_channel_update
from tobitkf.inference.censored_ar import (
    CensoredAR,
    CensoredARData,
    _log_likelihood,
    ar_autocovariance,
    ar_state_space,
    ar_to_pacf,
    exact_log_likelihood,
    is_stationary,
    pacf_to_ar,
    plan_grid,
    posterior_moments,
)


def test_adf_update_of_one_censored_reading_equals_the_quadrature_moments_of_the_posterior():
    # prior N(m, P) in 2-D, latent z = c'x + v, v ~ N(0, r), the event z <= l: integrate over x on a grid
    m = np.array([0.3, -0.2])
    P = np.array([[1.0, 0.4], [0.4, 0.5]])
    c, r, lim = np.array([1.0, 0.7]), 0.2, 0.1
    x, Pn, _, _, lm = censored_channel_update(m[None], P[None], None, np.array([lim]), c, r, lim, np.inf)
    # exact: p(x | event) ∝ N(x; m, P) Phi((l - c'x)/sqrt(r))
    L = np.linalg.cholesky(P)
    gx, gw = np.polynomial.hermite_e.hermegauss(80)  # Gauss-Hermite (probabilists') in 2-D
    W = np.outer(gw, gw) / (2 * np.pi)
    Z = np.stack(np.meshgrid(gx, gx, indexing="ij"), -1).reshape(-1, 2)
    X = m + Z @ L.T
    lik = norm.cdf((lim - X @ c) / np.sqrt(r))
    w = W.ravel() * lik
    mass = w.sum()
    mean = (w[:, None] * X).sum(0) / mass
    cov = ((w[:, None, None] * (X - mean)[:, :, None] * (X - mean)[:, None, :]).sum(0)) / mass
    assert abs(lm[0] - np.log(mass)) < 1e-10
    np.testing.assert_allclose(x[0], mean, atol=1e-10)
    np.testing.assert_allclose(Pn[0], cov, atol=1e-10)


def test_adf_likelihood_of_one_censored_reading_equals_quadrature_upper_and_lower():
    sys_ = tk.LinearSystem(A=[[0.8]], C=[[1.0]], Q=[[0.5]], R=[[0.3]], x0=[0.4], P0=[[1.2]])
    # y_1 predictive: N(0.8 * 0.4, 0.64 * 1.2 + 0.5 + 0.3)
    mu, s2 = 0.32, 0.64 * 1.2 + 0.8
    for lim, kw, side in ((0.0, {"lower": 0.0}, -1), (1.5, {"upper": 1.5}, 1)):
        ll = float(tk.adf_log_likelihood(sys_, tk.Censoring(**kw), [[lim]]))
        f = lambda z: norm.pdf(z, mu, np.sqrt(s2))  # noqa: E731
        q = integrate.quad(f, -np.inf, lim)[0] if side < 0 else integrate.quad(f, lim, np.inf)[0]
        assert abs(ll - np.log(q)) < 1e-10


def _ar1_exact_T3(y, cens_mask, lim, phi, s2):
    """Brute force for y = (y1 exact, censored at lim, y3 censored or exact): the stationary AR(1) density
    with the censored coordinates integrated out, the last one in closed form and the middle one by
    adaptive quadrature (scipy.integrate.quad)."""
    assert not cens_mask[0] and cens_mask[1]
    s = np.sqrt(s2)
    p1 = norm.logpdf(y[0], 0.0, s / np.sqrt(1 - phi * phi))
    if cens_mask[2]:
        f = lambda a: norm.pdf(a, phi * y[0], s) * norm.cdf((lim - phi * a) / s)  # noqa: E731
    else:
        f = lambda a: norm.pdf(a, phi * y[0], s) * norm.pdf(y[2], phi * a, s)  # noqa: E731
    val = integrate.quad(f, -np.inf, lim, epsabs=1e-14, epsrel=1e-12)[0]
    return p1 + np.log(val)


@pytest.mark.parametrize(
    "y,cens,measured",
    [
        ([0.2, 0.0, 0.0], [False, True, True], 3.67e-3),  # two censored readings at the end
        ([0.2, 0.0, 0.5], [False, True, False], -2.36e-2),  # a censored reading, then an exact one
    ],
)
def test_adf_error_on_a_censored_ar1_with_three_steps_against_exact_quadrature(y, cens, measured):
    """Stationary AR(1), phi = 0.8, sigma2 = 1, left-censored at 0, R = 0, T = 3. The ADF log-likelihood
    minus the exact one (nested scipy quadrature): +3.67e-3 and -2.36e-2 (the ``measured`` column). The
    ADF's predictive mass of the first censored reading is exact; its error comes from the Gaussian
    projection of the truncated posterior that the next reading is predicted from."""
    phi, s2 = 0.8, 1.0
    y, cens = np.array(y), np.array(cens)
    exact_nquad = _ar1_exact_T3(y, cens, 0.0, phi, s2)
    exact_grid = exact_log_likelihood(CensoredARData.build(y, lower=0.0), [0.0], s2, [phi])
    adf = float(
        tk.adf_log_likelihood(ar_state_space([0.0], s2, [phi]), tk.Censoring(lower=0.0), y[:, None], u=np.ones((3, 1)))
    )
    assert abs(exact_grid - exact_nquad) < 1e-9
    assert abs((adf - exact_nquad) - measured) < 1e-4


def _gamma(phi, s2, T):
    g = ar_autocovariance(phi, s2, T)
    return g[np.abs(np.subtract.outer(np.arange(T), np.arange(T)))]


@pytest.mark.parametrize("phi", [[0.6], [0.5, 0.3], [1.2, -0.5], []])
def test_exact_likelihood_without_censoring_is_the_stacked_gaussian_density(phi):
    rng = np.random.default_rng(1)
    T = 12
    y = rng.normal(size=T)
    y[[3, 4, 9]] = np.nan
    X = np.c_[np.ones(T), np.arange(T) / T]
    beta = np.array([0.1, 0.3])
    d = CensoredARData.build(y, X)
    G = _gamma(np.array(phi), 0.7, T) if phi else 0.7 * np.eye(T)
    o = ~np.isnan(y)
    ref = mvn(mean=(X @ beta)[o], cov=G[np.ix_(o, o)]).logpdf(y[o])
    # the missing runs take a 16-node Gauss-Hermite rule: 4e-10 off for the strongly oscillating AR(2)
    assert abs(exact_log_likelihood(d, beta, 0.7, phi) - ref) < 1e-8


@pytest.mark.parametrize("phi,side", [([0.7], -1), ([0.5, 0.3], -1), ([0.85], 1), ([1.1, -0.4], 1)])
def test_exact_censored_likelihood_equals_genz_box_probabilities(phi, side):
    # the independent route: density of the exact readings times the box probability of the censored
    # ones given them (Genz's QMC with 4 seeds, relative tolerance 1e-8, at most 10^6 points each)
    rng = np.random.default_rng(3)
    T = 14
    G = _gamma(np.array(phi), 1.0, T)
    ystar = np.linalg.cholesky(G) @ rng.normal(size=T)
    lim = 0.2 if side < 0 else -0.2
    y = np.maximum(ystar, lim) if side < 0 else np.minimum(ystar, lim)
    kw = {"lower": lim} if side < 0 else {"upper": lim}
    d = CensoredARData.build(y, **kw)
    c = d.side != 0
    o = ~c
    assert 2 <= c.sum() <= 11
    W = np.linalg.solve(G[np.ix_(o, o)], G[np.ix_(o, c)]).T
    cm, cc = W @ y[o], G[np.ix_(c, c)] - W @ G[np.ix_(o, c)]
    bound = np.full(c.sum(), lim)
    sgn = 1.0 if side < 0 else -1.0
    Ps = [
        mvn.cdf(sgn * bound, mean=sgn * cm, cov=cc, abseps=1e-13, releps=1e-8, maxpts=10**6, rng=seed)
        for seed in (1, 2, 3, 4)
    ]
    P = float(np.mean(Ps))
    qmc_err = float(np.std(Ps, ddof=1) / np.sqrt(len(Ps)) / P)  # relative s.e. of the QMC estimate
    ref = mvn(cov=G[np.ix_(o, o)]).logpdf(y[o]) + np.log(P)
    # 6 standard errors of the QMC estimate of log P (the quadrature's own error is below 1e-9 here)
    assert abs(exact_log_likelihood(d, [0.0], 1.0, phi) - ref) < 6 * qmc_err + 1e-9


@pytest.mark.parametrize("p", [1, 2])
def test_compiled_recursion_equals_the_numpy_reference(p):
    from tobitkf.data import load_phosphorus

    s = load_phosphorus()
    d = CensoredARData.build(s.y, s.design("lQ"), s.lower, s.upper, s.censored)
    beta, s2 = np.array([-4.8, 0.42]), 0.31
    phi = np.array([0.1] if p == 1 else [0.9, -0.3])
    plan = plan_grid(d, beta, s2, phi, nodes=6, panel_sd=2.0)
    a = _log_likelihood(d, beta, s2, phi, plan, "auto")
    b = _log_likelihood(d, beta, s2, phi, plan, "numpy")
    assert abs(a - b) < 1e-10


@pytest.mark.parametrize("name,p", [("phosphorus", 1), ("phosphorus", 2), ("cloud", 1)])
def test_exact_likelihood_on_the_real_data_has_converged_in_the_quadrature(name, p):
    from tobitkf.data import load_cloud_ceiling, load_phosphorus

    s = load_phosphorus() if name == "phosphorus" else load_cloud_ceiling()
    X = s.design("lQ") if name == "phosphorus" else s.design()
    d = CensoredARData.build(s.y, X, s.lower, s.upper, s.censored)
    th = {
        ("phosphorus", 1): [-4.83, 0.425, 0.311, 0.091],
        ("phosphorus", 2): [-4.85, 0.429, 0.308, 0.075, 0.118],
        ("cloud", 1): [4.40, 1.057, 0.876],
    }[(name, p)]
    a = CensoredAR(p).log_likelihood(d, th)
    b = CensoredAR(p, nodes=12, span=10.0, panel_sd=1.0, hermite=24).log_likelihood(d, th)
    assert abs(a - b) < 1e-6


def test_posterior_moments_equal_brute_force_quadrature():
    # AR(1), T = 4, readings (0.5, c, c, 0.3) left-censored at 0: the posterior of (xi_2, xi_3) =: (a, b).
    # Given a, the b-integral is closed form: N(b; phi a, s2) N(0.3; phi b, s2) is Gaussian in b with
    # precision (1 + phi^2)/s2 and mean phi (a + 0.3)/(1 + phi^2); the a-integral by adaptive quadrature.
    phi, s2, y4 = 0.7, 1.0, 0.3
    y = np.array([0.5, 0.0, 0.0, y4])
    d = CensoredARData.build(y, lower=0.0)
    post = posterior_moments(d, [0.0], s2, [phi])
    s = np.sqrt(s2)
    sb = s / np.sqrt(1 + phi * phi)

    def inner(a, k):  # int_{b<=0} b^k N(b; phi a) N(y4; phi b) db, k = 0, 1
        mb = phi * (a + y4) / (1 + phi * phi)
        c = norm.pdf(y4, phi * phi * a, s * np.sqrt(1 + phi * phi))
        z = -mb / sb
        return c * norm.cdf(z) if k == 0 else c * (mb * norm.cdf(z) - sb * norm.pdf(z))

    pa = lambda a: norm.pdf(a, phi * 0.5, s)  # noqa: E731
    q = lambda f: integrate.quad(f, -np.inf, 0.0, epsabs=1e-14, epsrel=1e-12)[0]  # noqa: E731
    Z = q(lambda a: pa(a) * inner(a, 0))
    m2 = q(lambda a: a * pa(a) * inner(a, 0)) / Z
    m3 = q(lambda a: pa(a) * inner(a, 1)) / Z
    v2 = q(lambda a: a * a * pa(a) * inner(a, 0)) / Z - m2**2
    np.testing.assert_allclose(post.mean, [0.5, m2, m3, y4], atol=1e-9)
    assert abs(post.var[1] - v2) < 1e-9
    assert post.var[0] == 0.0 and post.var[3] == 0.0
    ll = norm.logpdf(0.5, 0, s / np.sqrt(1 - phi * phi)) + np.log(Z)
    assert abs(post.loglik - ll) < 1e-9


def test_ar_algebra():
    for phi in ([0.5], [0.4, 0.3], [1.2, -0.5], [0.1, 0.2, -0.3]):
        r = ar_to_pacf(phi)
        np.testing.assert_allclose(pacf_to_ar(r), phi, atol=1e-13)
        assert is_stationary(phi)
    assert not is_stationary([1.0]) and not is_stationary([0.5, 0.6])
    g = ar_autocovariance([0.5], 2.0, 3)
    np.testing.assert_allclose(g, 2.0 / 0.75 * 0.5 ** np.arange(4), atol=1e-13)
    with pytest.raises(ValidationError, match="phi"):
        ar_autocovariance([1.01], 1.0, 2)


def test_exact_likelihood_errors_name_the_argument():
    d = CensoredARData.build(np.array([0.1, 0.0, 0.3]), lower=0.0)
    with pytest.raises(ShapeError, match="beta"):
        exact_log_likelihood(d, [0.0, 1.0], 1.0, [0.5])
    with pytest.raises(ValidationError, match="sigma2"):
        exact_log_likelihood(d, [0.0], -1.0, [0.5])
    with pytest.raises(ValidationError, match="phi"):
        exact_log_likelihood(d, [0.0], 1.0, [1.5])
    with pytest.raises(ShapeError, match="X"):
        CensoredARData.build(np.zeros(3), X=np.ones((4, 1)))
    with pytest.raises(ValidationError, match="outside its limits"):
        CensoredARData.build(np.array([-1.0, 0.5]), lower=0.0)
    with pytest.raises(ValidationError, match="censored"):
        CensoredARData.build(np.array([0.4, 0.5]), lower=0.0, censored=[True, False])
    with pytest.raises(ShapeError, match="plan"):
        exact_log_likelihood(d, [0.0], 1.0, [0.5], plan=plan_grid(CensoredARData.build(np.zeros(2)), [0.0], 1.0, [0.5]))


def test_the_indicator_decides_readings_at_the_limit():
    # the cloud ceiling's 8 uncensored readings at the limit: censored by the limit rule, not by the record
    from tobitkf.data import load_cloud_ceiling

    s = load_cloud_ceiling()
    rec = CensoredARData.build(s.y, None, s.lower, s.upper, s.censored)
    rule = CensoredARData.build(s.y, None, s.lower, s.upper)
    assert int((rec.side != 0).sum()) == 290 and int((rule.side != 0).sum()) == 298
    th = [4.4, 1.06, 0.876]
    assert CensoredAR(1).log_likelihood(rec, th) < CensoredAR(1).log_likelihood(rule, th)


def _adf(system, cens):
    return tk.AssumedDensityTobitFilter(system, cens, order="uncensored_first")


def test_adf_filter_indicator_and_errors():
    sys_ = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.5]], R=[[0.1]], x0=[0.0], P0=[[1.0]])
    cens = tk.Censoring(lower=0.0)
    y = np.array([[0.0], [0.4], [0.0]])
    flagged = _adf(sys_, cens).filter(y, censored=[[False], [False], [True]])
    rule = _adf(sys_, cens).filter(y)
    assert flagged.extras["side"][:, 0].tolist() == [0, 0, -1]
    assert rule.extras["side"][:, 0].tolist() == [-1, 0, -1]
    # an uncensored reading at the limit is the Kalman update
    kf = tk.KalmanFilter(sys_).filter(y[:1])
    np.testing.assert_allclose(flagged.mean[0], kf.mean[0], atol=1e-12)
    # online steps = the loop
    est = _adf(sys_, cens)
    st = est.init()
    for i, c in enumerate([False, False, True]):
        st = est.step(st, y[i], censored=[c])
    np.testing.assert_allclose(st.mean, flagged.mean[-1], atol=1e-12)
    with pytest.raises(ShapeError, match="censored"):
        _adf(sys_, cens).filter(y, censored=np.zeros((2, 1), bool))
    with pytest.raises(ValidationError, match="diagonal R"):
        _adf(
            tk.LinearSystem(A=np.eye(1), C=[[1.0], [1.0]], Q=[[1.0]], R=[[1.0, 0.5], [0.5, 1.0]], x0=[0.0], P0=[[1.0]]),
            tk.Censoring(lower=0.0),
        )
    # the adf likelihood sums the filter's per-step terms
    assert float(tk.adf_log_likelihood(sys_, cens, y, censored=[[False], [False], [True]])) == pytest.approx(
        float(flagged.extras["log_likelihood"].sum()), abs=1e-12
    )
