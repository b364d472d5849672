"""The Tobit ADF as the inference ADF: the recorded censoring indicator, the per-step log-likelihood
and the "uncensored readings first" order, against the inference package's own exact-moment ADF
(the filter the smoothers and fits used before the two were unified) to 1e-12."""

from __future__ import annotations

import numpy as np
import pytest

import tobitkf as tk
from tobitkf._validation import ShapeError, ValidationError

TOL = 1e-12


def _system(m: int, r0: bool = False):
    A = np.array([[0.9, 0.2], [-0.1, 0.8]])
    C = np.array([[1.0, 0.3], [0.2, -1.0]])[:m]
    R = np.diag([0.0 if r0 else 0.2, 0.1][:m])
    return tk.LinearSystem(A=A, C=C, Q=0.3 * np.eye(2), R=R, x0=[0.1, -0.2], P0=np.eye(2),
                           Bu=[[0.5], [0.0]], D=np.full((m, 1), 0.2))


def _case(m: int, seed: int, runs: int = 3, T: int = 9):
    """Readings clipped at two-sided, time-varying limits, some missing, one at the limit recorded as
    uncensored, and the indicator that says so."""
    rng = np.random.default_rng(seed)
    lo = np.full((T, m), -0.4) + 0.1 * np.sin(np.arange(T))[:, None]
    hi = np.full((T, m), 0.9)
    ystar = rng.normal(0.2, 1.0, size=(runs, T, m))
    y = np.clip(ystar, lo, hi)
    flags = (y <= lo) | (y >= hi)
    y[0, 2, 0] = lo[2, 0]                     # at the limit, recorded as uncensored
    flags[0, 2, 0] = False
    y[1, 4, :] = np.nan                       # a missing step
    flags[1, 4, :] = False
    y[2, 6, m - 1] = np.nan
    flags[2, 6, m - 1] = False
    u = rng.normal(size=(T, 1))
    return tk.Censoring(lower=lo, upper=hi), y, flags, u


def _old_adf(system, cens, form="standard"):
    from tobitkf.inference.adf import ADFilter

    return ADFilter(system, cens, covariance_update=form)


def _assert_same(a, b, ll_key="log_lik"):
    for name in ("mean", "cov", "pred_mean", "pred_cov"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), atol=TOL, rtol=0, err_msg=name)
    np.testing.assert_allclose(a.extras["log_likelihood"], b.extras[ll_key], atol=TOL, rtol=0)
    np.testing.assert_array_equal(a.extras["side"], b.extras["side"])


@pytest.mark.parametrize("m,r0", [(1, False), (1, True), (2, False), (2, True)])
@pytest.mark.parametrize("form", ["standard", "joseph"])
@pytest.mark.parametrize("recorded", [False, True])
def test_uncensored_first_order_equals_the_inference_adf(m, r0, form, recorded):
    system = _system(m, r0)
    cens, y, flags, u = _case(m, seed=10 * m + r0)
    kw = {"censored": flags} if recorded else {}
    new = tk.AssumedDensityTobitFilter(system, cens, covariance_update=form, order="uncensored_first")
    got = new.filter(y, u=u, **kw)
    ref = _old_adf(system, cens, form).filter(y, u=u, **kw)
    _assert_same(got, ref)
    if recorded:                              # the reading at the limit recorded as uncensored is a density
        assert got.extras["side"][0, 2, 0] == 0
        assert new.filter(y, u=u).extras["side"][0, 2, 0] == -1


def test_with_one_channel_the_order_does_not_matter():
    system = _system(1)
    cens, y, flags, u = _case(1, seed=3)
    a = tk.AssumedDensityTobitFilter(system, cens).filter(y, u=u, censored=flags)
    b = tk.AssumedDensityTobitFilter(system, cens, order="uncensored_first").filter(y, u=u, censored=flags)
    for name in ("mean", "cov"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), atol=TOL, rtol=0)
    np.testing.assert_allclose(a.extras["log_likelihood"], b.extras["log_likelihood"], atol=TOL, rtol=0)


def test_steps_with_the_indicator_equal_the_loop():
    system = _system(2)
    cens, y, flags, u = _case(2, seed=5)
    est = tk.AssumedDensityTobitFilter(system, cens, order="uncensored_first")
    full = est.filter(y, u=u, censored=flags)
    st = est.init((3,))
    for i in range(y.shape[1]):
        st = est.step(st, y[:, i], u=u[i], censored=flags[:, i])
        np.testing.assert_allclose(st.mean, full.mean[:, i], atol=TOL, rtol=0)
        np.testing.assert_allclose(st.extras["log_likelihood"], full.extras["log_likelihood"][:, i], atol=TOL,
                                   rtol=0)
    # predict + update with the indicator is the step
    st0 = est.init((3,))
    s1 = est.update(est.predict(st0, u=u[0]), y[:, 0], censored=flags[:, 0])
    np.testing.assert_allclose(s1.mean, full.mean[:, 0], atol=TOL, rtol=0)


def test_the_indicator_is_checked():
    system = _system(1)
    cens, y, flags, u = _case(1, seed=7)
    est = tk.AssumedDensityTobitFilter(system, cens)
    with pytest.raises(ShapeError, match="censored"):
        est.filter(y, u=u, censored=flags[:, :4])
    inside = flags.copy()
    i = np.argwhere(~flags & ~np.isnan(y) & (y > -0.3) & (y < 0.8))[0]
    inside[tuple(i)] = True
    with pytest.raises(ValidationError, match="censored.*inside its limits"):
        est.filter(y, u=u, censored=inside)
    missing = flags.copy()
    missing[1, 4, 0] = True
    with pytest.raises(ValidationError, match="censored.*missing"):
        est.filter(y, u=u, censored=missing)
    with pytest.raises(ValidationError, match="censored"):
        est.filter(y, u=u, censored=flags.astype(float) * 0.5)
    st = est.init((3,))
    with pytest.raises(ValidationError, match="censored.*inside its limits"):
        j = np.argwhere(~flags[:, 0] & (y[:, 0] > -0.3) & (y[:, 0] < 0.8))[0]
        bad = flags[:, 0].copy()
        bad[tuple(j)] = True
        est.step(st, y[:, 0], u=u[0], censored=bad)
    with pytest.raises(ValidationError, match="order"):
        tk.AssumedDensityTobitFilter(system, cens, order="nope")


def test_log_likelihood_of_one_step_is_the_censored_normal_likelihood():
    # one step from a Gaussian prior: interior density, lower and upper masses (log_ndtr, 40 sigma out)
    from scipy.stats import norm

    sys_ = tk.LinearSystem(A=[[0.8]], C=[[1.0]], Q=[[0.5]], R=[[0.3]], x0=[0.4], P0=[[1.2]])
    mu, s = 0.32, np.sqrt(0.64 * 1.2 + 0.8)
    cens = tk.Censoring(lower=0.0, upper=1.5)
    est = tk.AssumedDensityTobitFilter(sys_, cens)
    for yv, want in ((0.7, norm.logpdf(0.7, mu, s)), (0.0, norm.logcdf(-mu / s)), (1.5, norm.logsf((1.5 - mu) / s)),
                     (np.nan, 0.0)):
        got = est.filter([[yv]]).extras["log_likelihood"][0]
        assert abs(got - want) < 1e-12
    # recorded as uncensored at the limit: the density there
    got = est.filter([[0.0]], censored=[[False]]).extras["log_likelihood"][0]
    assert abs(got - norm.logpdf(0.0, mu, s)) < 1e-12
    from scipy.special import log_ndtr

    lim = mu - 40 * s                        # 40 sigma into the lower tail: log Phi(-40), finite
    far = tk.AssumedDensityTobitFilter(sys_, tk.Censoring(lower=lim)).filter([[lim]])
    assert abs(far.extras["log_likelihood"][0] - float(log_ndtr(-40.0))) < 1e-9
