"""What tobitkf.fit refuses, when it may say converged, and the pieces that make it scale: data without
information, invalid tolerances and readings, singular starting variances, the stopping rule, the
compiled state-space likelihood against the filters, the direct default against EM's optimum, the
subsample start, bounded memory for long censored runs, progress lines."""

import numpy as np
import pytest
from scipy.signal import lfilter

import tobitkf as tk
from tobitkf._validation import ValidationError
from tobitkf.inference import CensoredAR
from tobitkf.inference._ar_likelihood import _intervals
from tobitkf.inference._optimize import Ticker, central_gradient
from tobitkf.inference.censored_ar import CensoredARData
from tobitkf.inference.state_space import _Likelihood, _loglik, _matrices, em_step


def _censored_ar1(T, seed=1, share=0.3):
    rng = np.random.default_rng(seed)
    xi = lfilter([1.0], [1.0, -0.6], rng.normal(size=T))
    X = np.c_[np.ones(T), rng.normal(size=T)]
    ys = X @ [1.0, 0.5] + xi
    lim = float(np.quantile(ys, share))
    return np.maximum(ys, lim), X, lim


def _scalar_ss(T=300, seed=1):
    rng = np.random.default_rng(seed)
    x, y = 0.0, np.empty(T)
    for t in range(T):
        x = 0.8 * x + rng.normal() * np.sqrt(0.5)
        y[t] = 2.0 + x + rng.normal() * np.sqrt(0.3)
    return y


# --------------------------------------------------------------------------- refusals


@pytest.mark.parametrize("n", [3, 10])
def test_all_readings_at_their_limit_are_refused_at_once(n):
    """Every reading censored: the likelihood grows without bound as the mean moves below the limit (no
    maximum); the search used to run the mean away and the quadrature to ask for 190 GiB."""
    with pytest.raises(ValidationError, match="y: no reading is observed exactly"):
        tk.fit(CensoredAR(1), np.zeros(n), lower=0.0)


def test_records_with_nothing_to_fit_are_refused():
    with pytest.raises(ValidationError, match="y: all 50 readings are missing"):
        tk.fit(CensoredAR(1), np.full(50, np.nan))
    with pytest.raises(ValidationError, match="y: the regressors fit the 20 exactly observed readings without error"):
        tk.fit(CensoredAR(1), np.full(20, 3.0))
    system = tk.LinearSystem(A=[[0.8]], C=[[1.0]], Q=[[0.5]], R=[[0.3]], x0=[0.0], P0=[[1.0]])
    for method in ("direct", "em"):
        with pytest.raises(ValidationError, match="y: all 30 readings are missing"):
            tk.fit(system, np.full((30, 1), np.nan), estimate=("A", "Q", "R"), method=method)


@pytest.mark.parametrize(
    "option", [{"gtol": np.nan}, {"gtol": -1.0}, {"gtol": np.inf}, {"maxiter": 0}, {"maxiter": True}, {"gtol": "1e-3"}]
)
def test_invalid_tolerances_and_counts_are_refused_by_name(option):
    y, X, lim = _censored_ar1(100)
    name = next(iter(option))
    with pytest.raises(ValidationError, match=f"^{name}:"):
        tk.fit(CensoredAR(1), y, X=X, lower=lim, **option)
    system = tk.LinearSystem(A=[[0.8]], C=[[1.0]], Q=[[0.5]], R=[[0.3]], x0=[0.0], P0=[[1.0]])
    for method in ("direct", "em"):
        with pytest.raises(ValidationError, match=f"^{name}:"):
            tk.fit(system, _scalar_ss(50), estimate=("Q", "R"), method=method, **option)
    with pytest.raises(ValidationError, match="^tol:"):
        tk.fit(system, _scalar_ss(50), estimate=("Q", "R"), method="em", tol=np.nan)


def test_text_and_boolean_readings_are_refused():
    rng = np.random.default_rng(0)
    with pytest.raises(ValidationError, match="y: expected an array of numbers, got booleans"):
        tk.fit(CensoredAR(1), rng.normal(size=100) > 0)
    with pytest.raises(ValidationError, match="y: expected an array of numbers, got text"):
        tk.fit(CensoredAR(1), np.array(["1.0", "2.5", "0.3"] * 10))


@pytest.mark.parametrize("method", ["direct", "em"])
def test_a_zero_starting_variance_of_an_estimated_covariance_is_refused(method):
    """EM cannot move R from 0 (it reported convergence at R = 0); its logarithm is -inf for direct."""
    templ = tk.LinearSystem(A=[[0.5]], C=[[1.0]], Q=[[1.0]], R=[[0.0]], x0=[0.0], P0=[[1.0]])
    with pytest.raises(ValidationError, match="^R: the starting value of an estimated covariance"):
        tk.fit(templ, _scalar_ss(100), estimate=("A", "Q", "R"), method=method)
    # R = 0 held (not estimated) stays allowed: exact readings
    f = tk.fit(templ, _scalar_ss(100), estimate=("A", "Q"), standard_errors=False)
    assert np.isfinite(f.loglik)


def test_a_runaway_quadrature_is_refused_before_it_is_allocated():
    """Parameters far from the data (a variance near 0, the mean far below the limit) would need more
    nodes than any machine holds: refused with an error naming y, nothing allocated."""
    y, X, lim = _censored_ar1(200)
    data = CensoredARData.build(y, X, lower=lim)
    with pytest.raises(ValidationError, match="^y: the quadrature of reading"):
        CensoredAR(1).plan(data, np.array([-50.0, 0.5, 1e-16, 0.5]))


def test_a_censored_run_as_long_as_the_record_costs_memory_linear_in_its_length():
    """The run structure used to keep a (L, L) lag matrix per run: 320 GB for one run of 2e5 readings."""
    T = 200_000
    y = np.zeros(T)
    y[:5] = [1.0, 0.5, 2.0, 1.5, 0.7]
    data = CensoredARData.build(y, lower=0.0)
    m, sd, lo, hi, width, pure = _intervals(data, np.array([1.0]), 1.0, np.array([0.5]), 8.0)
    # far from the anchors the conditional is the stationary law N(0, 1 / (1 - 0.25))
    assert abs(m[-1]) < 1e-12 and abs(sd[-1] - np.sqrt(1 / 0.75)) < 1e-12
    # next to the last exact reading (xi = 0.7 - 1 = -0.3): N(0.5 * -0.3, 1)
    assert abs(m[5] - 0.5 * -0.3) < 1e-12 and abs(sd[5] - 1.0) < 1e-12


# --------------------------------------------------------------------------- convergence


def test_converged_means_a_newton_step_on_the_models_rule_below_gtol_standard_errors():
    """An independent check of the stopping rule: at the reported optimum, a central-difference gradient of
    the exact log-likelihood and the reported covariance give a Newton step below gtol s.e."""
    y, X, lim = _censored_ar1(400, seed=4)
    f = tk.fit(CensoredAR(1), y, X=X, lower=lim)
    assert f.converged, f.message
    model, data = f.model, f.data
    plan = model.plan(data, f.theta)
    g = central_gradient(lambda th: model.log_likelihood(data, th, plan), f.theta, step=1e-6)
    step = f.cov @ g
    se = np.sqrt(np.diagonal(f.cov))
    assert np.max(np.abs(step) / se) < 1e-3


def test_an_em_run_stopped_by_a_small_likelihood_change_far_from_the_optimum_is_not_converged():
    """EM crawls: with tol = 1e-4 it stops where the likelihood still changes slowly but the optimum is
    several standard errors away; it used to report converged=True."""
    u = np.ones((300, 1))
    templ = tk.LinearSystem(A=[[0.5]], C=[[1.0]], Q=[[1.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]], D=[[0.0]])
    y = _scalar_ss(300)
    em = tk.fit(templ, y, u=u, estimate=("A", "Q", "R", "D"), method="em", tol=1e-4)
    direct = tk.fit(templ, y, u=u, estimate=("A", "Q", "R", "D"))
    assert direct.converged, direct.message
    gap = max(abs(em.params[n] - direct.params[n]) / direct.se[n] for n in direct.names)
    assert gap > 1.0 and not em.converged and em.message.startswith("EM stopped")


def test_the_direct_default_reaches_the_maximum_em_climbs_to():
    """The default for a state-space template (direct quasi-Newton) against EM: its optimum is a fixed point
    of EM (an EM step from it changes the exact likelihood by < 1e-8 and the estimates by < 0.01 s.e.),
    and EM from the template never gets above it."""
    u = np.ones((300, 1))
    templ = tk.LinearSystem(A=[[0.5]], C=[[1.0]], Q=[[1.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]], D=[[0.0]])
    y = _scalar_ss(300)
    est = ("A", "Q", "R", "D")
    direct = tk.fit(templ, y, u=u, estimate=est)
    assert direct.method == "direct" and direct.converged, direct.message
    M = _matrices(direct.system())
    M_next, ll = em_step(M, y[:, None], u, None, None, est, "given", False)
    assert abs(ll - direct.loglik) < 1e-8
    M_after, ll_after = em_step(M_next, y[:, None], u, None, None, est, "given", False)
    assert ll_after - ll < 1e-8
    for name in direct.names:
        mat, idx = name.split("[")[0], tuple(int(i) for i in name[:-1].split("[")[1].split(","))
        assert abs(M_next[mat][idx] - direct.params[name]) < 0.01 * direct.se[name], name
    em = tk.fit(templ, y, u=u, estimate=est, method="em", maxiter=150, standard_errors=False)
    assert em.loglik <= direct.loglik + 1e-9


# --------------------------------------------------------------------------- the pieces that scale


@pytest.mark.parametrize(("n", "m", "censored"), [(1, 1, False), (1, 1, True), (2, 2, True), (3, 2, True)])
def test_the_compiled_state_space_likelihood_equals_the_filters(n, m, censored):
    """The kernel of the direct fits against the assumed-density filter's (or the Kalman filter's)
    log-likelihood: both limits, missing readings, inputs; equal to rounding."""
    rng = np.random.default_rng(10 * n + m)
    T = 150
    system = tk.LinearSystem(
        A=rng.normal(size=(n, n)) * 0.4,
        C=rng.normal(size=(m, n)),
        Q=np.eye(n) * 0.5,
        R=np.diag(rng.uniform(0.1, 0.5, m)),
        x0=rng.normal(size=n),
        P0=np.eye(n),
        Bu=rng.normal(size=(n, 1)),
        D=rng.normal(size=(m, 1)),
    )
    u = rng.normal(size=(T, 1))
    y = rng.normal(size=(T, m)).cumsum(0) * 0.3
    y[rng.random((T, m)) < 0.1] = np.nan
    cens = None
    if censored:
        lo, hi = np.nanquantile(y, 0.3, axis=0), np.nanquantile(y, 0.85, axis=0)
        y = np.clip(y, lo, hi)
        cens = tk.Censoring(lower=lo, upper=hi)
    got = _Likelihood(y, u, cens, None).of_system(system)
    want = _loglik(system, y, u, cens, None)
    assert np.isfinite(want) and abs(got - want) < 1e-10 * abs(want)


def test_the_subsample_start_reaches_the_same_optimum():
    y, X, lim = _censored_ar1(3000, seed=7)
    cold = CensoredAR(1).fit(y, X, lower=lim, warm_start=False)
    warm = CensoredAR(1).fit(y, X, lower=lim, warm_start=True)
    assert cold.converged and warm.converged
    se = np.array([cold.se[n] for n in cold.names])
    assert np.max(np.abs(warm.theta - cold.theta) / se) < 5e-3
    assert abs(warm.loglik - cold.loglik) < 1e-6


def test_progress_lines_go_to_stderr_as_plain_text(capsys):
    t = Ticker("fit X", after=0.0, every=0.0)
    t.tick("iteration 3")
    assert "fit X: iteration 3" in capsys.readouterr().err
    y, X, lim = _censored_ar1(200)
    CensoredAR(1).fit(y, X, lower=lim, progress=True)  # stderr is not a terminal here: plain lines
    assert "fit CensoredAR(p=1) to 200 readings" in capsys.readouterr().err
    CensoredAR(1).fit(y, X, lower=lim, progress=False)
    assert capsys.readouterr().err == ""


def test_a_reading_whose_square_overflows_is_refused_by_name_in_the_censored_ar_fit():
    # a reading of 1e308 used to surface as an error about 'start' (the search's starting values)
    y = np.array([0.3, 1e308, 0.1, 0.5, 0.2])
    with pytest.raises(tk.ValidationError, match=r"^y: "):
        tk.fit(tk.CensoredAR(1), y, lower=0.0)
