"""The Tobit ADF as the inference ADF: the recorded censoring indicator, the per-step log-likelihood
and the "uncensored readings first" order, to 1e-12 against the inference package's own exact-moment
ADF (the filter the smoothers and fits used before the two were unified; equal to it to 1e-12 while
both existed), here written out plainly as the reference, one run and one step at a time."""

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
    return tk.LinearSystem(
        A=A, C=C, Q=0.3 * np.eye(2), R=R, x0=[0.1, -0.2], P0=np.eye(2), Bu=[[0.5], [0.0]], D=np.full((m, 1), 0.2)
    )


def _case(m: int, seed: int, runs: int = 3, T: int = 9):
    """Readings clipped at two-sided, time-varying limits, some missing, one at the limit recorded as
    uncensored, and the indicator that says so."""
    rng = np.random.default_rng(seed)
    lo = np.full((T, m), -0.4) + 0.1 * np.sin(np.arange(T))[:, None]
    hi = np.full((T, m), 0.9)
    ystar = rng.normal(0.2, 1.0, size=(runs, T, m))
    y = np.clip(ystar, lo, hi)
    flags = (y <= lo) | (y >= hi)
    y[0, 2, 0] = lo[2, 0]  # at the limit, recorded as uncensored
    flags[0, 2, 0] = False
    y[1, 4, :] = np.nan  # a missing step
    flags[1, 4, :] = False
    y[2, 6, m - 1] = np.nan
    flags[2, 6, m - 1] = False
    u = rng.normal(size=(T, 1))
    return tk.Censoring(lower=lo, upper=hi), y, flags, u


def _reference_adf(system, cens, y, u, flags=None):
    """The inference ADF written out plainly, one run and one step at a time (no batching, no shared
    core): the present uncensored readings jointly (the Kalman update and its Gaussian log-density),
    then each censored reading in channel order (the truncated-normal moments of the latent reading in
    closed form, the update :math:`\\bar x + K(m_{tr} - \\mu)`, :math:`\\bar P - K(s^2 - V_{tr})K^T` and
    the log predictive mass). Returns mean, cov, pred_mean, pred_cov, log_lik, side."""
    from scipy.stats import multivariate_normal, norm

    A, Q, C, R = system.A.at(0), system.Q.at(0), system.C.at(1), system.R.at(1)
    Bu, D = system.Bu.at(1), system.D.at(1)
    runs, T, m = y.shape
    n = A.shape[0]
    out = {
        k: np.zeros((runs, T) + sh)
        for k, sh in (
            ("mean", (n,)),
            ("cov", (n, n)),
            ("pred_mean", (n,)),
            ("pred_cov", (n, n)),
            ("log_lik", ()),
            ("side", (m,)),
        )
    }
    for i in range(runs):
        x, P = np.asarray(system.x0, float), np.asarray(system.P0, float)
        for t in range(T):
            x, P = A @ x + Bu @ u[t], A @ P @ A.T + Q
            out["pred_mean"][i, t], out["pred_cov"][i, t] = x, P
            lo, hi = cens.limits(t + 1)
            lo, hi = np.broadcast_to(lo, (m,)), np.broadcast_to(hi, (m,))
            yt, d = y[i, t], D @ u[t]
            at_lo = (yt <= lo + 1e-12 * np.maximum(1, abs(lo))) & np.isfinite(lo)
            at_hi = (yt >= hi - 1e-12 * np.maximum(1, abs(hi))) & np.isfinite(hi) & ~at_lo
            fl = (at_lo | at_hi) if flags is None else flags[i, t]
            side = np.where(fl & at_lo, -1, np.where(fl & at_hi, 1, 0))
            o = (side == 0) & ~np.isnan(yt)
            ll = 0.0
            if o.any():
                Co = C[o]
                S = Co @ P @ Co.T + R[np.ix_(o, o)]
                e = yt[o] - Co @ x - d[o]
                ll += multivariate_normal(np.zeros(o.sum()), S).logpdf(e)
                K = P @ Co.T @ np.linalg.inv(S)
                x, P = x + K @ e, P - K @ S @ K.T
            for l in np.flatnonzero(side):
                c = C[l]
                mu, s2 = c @ x + d[l], c @ P @ c + R[l, l]
                s = np.sqrt(s2)
                if side[l] < 0:
                    a = (lo[l] - mu) / s
                    lam = norm.pdf(a) / norm.cdf(a)
                    mtr, V, ll = mu - s * lam, s2 * (1 - a * lam - lam * lam), ll + norm.logcdf(a)
                else:
                    b = (hi[l] - mu) / s
                    lam = norm.pdf(b) / norm.sf(b)
                    mtr, V, ll = mu + s * lam, s2 * (1 + b * lam - lam * lam), ll + norm.logsf(b)
                K = P @ c / s2
                x, P = x + K * (mtr - mu), P - (s2 - V) * np.outer(K, K)
            out["mean"][i, t], out["cov"][i, t], out["log_lik"][i, t], out["side"][i, t] = x, P, ll, side
    return out


def _assert_same(a, ref):
    for name in ("mean", "cov", "pred_mean", "pred_cov"):
        np.testing.assert_allclose(getattr(a, name), ref[name], atol=TOL, rtol=0, err_msg=name)
    np.testing.assert_allclose(a.extras["log_likelihood"], ref["log_lik"], atol=TOL, rtol=0)
    np.testing.assert_array_equal(a.extras["side"], ref["side"])


@pytest.mark.parametrize("m,r0", [(1, False), (1, True), (2, False), (2, True)])
@pytest.mark.parametrize("form", ["standard", "joseph", "square_root"])
@pytest.mark.parametrize("recorded", [False, True])
def test_uncensored_first_order_is_the_inference_adf(m, r0, form, recorded):
    system = _system(m, r0)
    cens, y, flags, u = _case(m, seed=10 * m + r0)
    kw = {"censored": flags} if recorded else {}
    new = tk.AssumedDensityTobitFilter(system, cens, covariance_update=form, order="uncensored_first")
    got = new.filter(y, u=u, **kw)
    _assert_same(got, _reference_adf(system, cens, y, u, flags if recorded else None))
    if recorded:  # the reading at the limit recorded as uncensored is a density
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
        np.testing.assert_allclose(st.extras["log_likelihood"], full.extras["log_likelihood"][:, i], atol=TOL, rtol=0)
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
    # a flagged reading strictly inside its limits is an interval reading (between the limits), not an error;
    # inside limits of which one is infinite the flag contradicts the reading and is refused
    inside = flags.copy()
    i = np.argwhere(~flags & ~np.isnan(y) & (y > -0.3) & (y < 0.8))[0]
    inside[tuple(i)] = True
    ll_iv = est.filter(y, u=u, censored=inside).extras["log_likelihood"]
    assert np.all(np.isfinite(ll_iv)) and ll_iv[tuple(i[:2])] <= 0.0
    free = tk.AssumedDensityTobitFilter(system, tk.Censoring())
    with pytest.raises(ValidationError, match="censored.*two finite limits"):
        free.filter(np.nan_to_num(y), u=u, censored=inside)
    missing = flags.copy()
    missing[1, 4, 0] = True
    with pytest.raises(ValidationError, match="censored.*missing"):
        est.filter(y, u=u, censored=missing)
    with pytest.raises(ValidationError, match="censored"):
        est.filter(y, u=u, censored=flags.astype(float) * 0.5)
    st = free.init((3,))
    with pytest.raises(ValidationError, match="censored.*two finite limits"):
        j = np.argwhere(~flags[:, 0] & (y[:, 0] > -0.3) & (y[:, 0] < 0.8))[0]
        bad = flags[:, 0].copy()
        bad[tuple(j)] = True
        free.step(st, np.nan_to_num(y[:, 0]), u=u[0], censored=bad)
    with pytest.raises(ValidationError, match="order"):
        tk.AssumedDensityTobitFilter(system, cens, order="nope")


def test_log_likelihood_of_one_step_is_the_censored_normal_likelihood():
    # one step from a Gaussian prior: interior density, lower and upper masses (log_ndtr, 40 sigma out)
    from scipy.stats import norm

    sys_ = tk.LinearSystem(A=[[0.8]], C=[[1.0]], Q=[[0.5]], R=[[0.3]], x0=[0.4], P0=[[1.2]])
    mu, s = 0.32, np.sqrt(0.64 * 1.2 + 0.8)
    cens = tk.Censoring(lower=0.0, upper=1.5)
    est = tk.AssumedDensityTobitFilter(sys_, cens)
    for yv, want in (
        (0.7, norm.logpdf(0.7, mu, s)),
        (0.0, norm.logcdf(-mu / s)),
        (1.5, norm.logsf((1.5 - mu) / s)),
        (np.nan, 0.0),
    ):
        got = est.filter([[yv]]).extras["log_likelihood"][0]
        assert abs(got - want) < 1e-12
    # recorded as uncensored at the limit: the density there
    got = est.filter([[0.0]], censored=[[False]]).extras["log_likelihood"][0]
    assert abs(got - norm.logpdf(0.0, mu, s)) < 1e-12
    from scipy.special import log_ndtr

    lim = mu - 40 * s  # 40 sigma into the lower tail: log Phi(-40), finite
    far = tk.AssumedDensityTobitFilter(sys_, tk.Censoring(lower=lim)).filter([[lim]])
    assert abs(far.extras["log_likelihood"][0] - float(log_ndtr(-40.0))) < 1e-9
