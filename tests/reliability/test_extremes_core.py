"""Numerical extremes for the core filters (issue 9 item 3): every output finite, symmetric, PSD."""

import numpy as np
import pytest

import tobitkf as tk


def assert_healthy(out, tol=1e-9):
    assert np.all(np.isfinite(out.mean)) and np.all(np.isfinite(out.cov))
    cov = np.asarray(out.cov)
    np.testing.assert_array_equal(cov, np.swapaxes(cov, -1, -2))
    eig = np.linalg.eigvalsh(cov)
    scale = np.abs(cov).max(axis=(-1, -2))[..., None]
    assert np.all(eig >= -tol * scale), eig.min()


def oscillator(**kw):
    w = 0.05
    args = dict(
        A=[[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]],
        C=[[1.0, 0.0]],
        Q=0.01 * np.eye(2),
        R=[[0.1]],
        x0=[0.0, 0.0],
        P0=0.05 * np.eye(2),
    )
    args.update(kw)
    return tk.LinearSystem(**args)


CASES = {
    "P0 huge (1e8)": dict(P0=1e8 * np.eye(2)),
    "P0 tiny (1e-12)": dict(P0=1e-12 * np.eye(2)),
    "R near singular (1e-12)": dict(R=[[1e-12]]),
    "Q near singular (1e-12)": dict(Q=1e-12 * np.eye(2)),
    "ill-conditioned A": dict(A=[[1.0, 1e4], [0.0, 1.0]], Q=np.diag([1e-6, 1e-10])),
}


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("update", ["standard", "joseph", "square_root"])
def test_kf_and_tkf_stay_finite_symmetric_psd(case, update):
    sys_ = oscillator(**CASES[case])
    for cens in (tk.Censoring(lower=0.0), tk.Censoring(lower=-1.0, upper=1.0)):
        data = tk.simulate(oscillator(), 200, 8, censoring=cens, seed=5)  # data from the nominal model
        assert_healthy(tk.TobitKalmanFilter(sys_, cens, covariance_update=update).filter(data.y))
        assert_healthy(tk.KalmanFilter(sys_, covariance_update=update).filter(data.y))
        assert_healthy(tk.DroppingKalmanFilter(sys_, cens, covariance_update=update).filter(data.y))


@pytest.mark.parametrize("shift", [-40.0, 40.0, -1000.0, 1000.0])
def test_limits_far_inside_and_outside_the_predicted_mean(shift):
    """Limits 40 (and 1000) σ away on either side of the prediction: no NaN; all-censored means open loop."""
    sys_ = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.01]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    T = 30
    cens = tk.Censoring(lower=shift)
    y = np.full((4, T, 1), max(shift, 0.0) if shift > 0 else 0.5)
    out = tk.TobitKalmanFilter(sys_, cens).filter(y)
    assert_healthy(out)
    if shift > 0:  # every reading censored far above the prediction: the update changes nothing
        np.testing.assert_allclose(out.mean, 0.0, atol=1e-12)
        np.testing.assert_allclose(out.cov[0, :, 0, 0], 1.0 + 0.01 * np.arange(1, T + 1), rtol=1e-12)
    else:  # limit far below: the TKF is the KF
        kf = tk.KalmanFilter(sys_).filter(y)
        np.testing.assert_allclose(out.mean, kf.mean, atol=1e-12)


def test_long_run_stays_bounded():
    """A long single run (2e4 steps here; the 1e6-step run is in benchmarks) stays finite and bounded."""
    sys_ = oscillator()
    cens = tk.Censoring(lower=0.0)
    data = tk.simulate(sys_, 20_000, 1, censoring=cens, seed=9)
    out = tk.TobitKalmanFilter(sys_, cens).filter(data.y)
    assert_healthy(out)
    assert np.abs(out.mean - data.x[:, 1:]).max() < 50
