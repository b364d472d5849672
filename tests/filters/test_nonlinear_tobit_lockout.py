"""The Tobit extended Kalman filter's update against the literature's equations, and its known lock-out.

The update of Arthur, Attarian, Hamilton & Tran (2018) is the Tobit Kalman filter's with C replaced by the
Jacobian at the prediction, every censoring statistic taken at the predicted measurement with the noise's
standard deviation alone. The oracle below writes those equations out with scipy's truncated normal (an
implementation independent of the package's censored moments). The same equations give the lock-out that makes
the filter run away on the clipped accelerometer: when the predicted measurement sits many noise standard
deviations beyond a limit, the probability of an uncensored reading computed there is about 0, so even an
uncensored reading moves the estimate by almost nothing (the assumed-density filter, whose latent reading has
the prediction's spread too, does move).
"""

from __future__ import annotations

import numpy as np
from scipy import stats

import tobitkf as tk

LO, HI, SIGMA = -1.0, 1.0, 0.1


def f(x, k):
    return x


def h(x, k):  # the accelerometer's reading: -omega^2 p
    return (-(x[..., 1] ** 2) * x[..., 0])[..., None]


def _oracle(xp, Pp, y):
    """One Tobit EKF update (Arthur et al. 2018) from the prediction, by the equations with scipy."""
    mu = float(h(xp, 1)[0])
    H = np.array([[-(xp[1] ** 2), -2.0 * xp[1] * xp[0]]])
    a, b = (LO - mu) / SIGMA, (HI - mu) / SIGMA
    g = stats.norm.cdf(b) - stats.norm.cdf(a)  # probability of an uncensored reading at the predicted mean
    tn = stats.truncnorm(a, b, loc=mu, scale=SIGMA)
    Ey = LO * stats.norm.cdf(a) + g * tn.mean() + HI * stats.norm.sf(b)
    V = tn.var()  # the noise term: the truncated variance (the Tobit Kalman filter's default)
    Pxy = Pp @ H.T
    Ree = g * (H @ Pp @ H.T) * g + V
    K = Pxy * g / Ree
    return xp + (K * (y - Ey))[:, 0], Pp - K @ (g * Pxy.T)


def test_one_update_is_the_literatures_tobit_ekf_update():
    system = tk.NonlinearSystem(f, h, np.zeros((2, 2)), [[SIGMA**2]], [2.0, 0.5], np.diag([0.3, 0.001]))
    est = tk.TobitExtendedKalmanFilter(system, tk.Censoring(lower=LO, upper=HI))
    for x0, y in (([2.0, 0.5], -0.45), ([4.5, 0.5], -1.0), ([3.9, 0.5], -0.97)):  # inside, at the limit, near it
        out = est.filter([[y]], x0=x0)
        xo, Po = _oracle(np.array(x0), system.P0, y)
        np.testing.assert_allclose(out.mean[0], xo, rtol=0, atol=1e-7)  # central-difference Jacobian: ~1e-10
        np.testing.assert_allclose(out.cov[0], Po, rtol=0, atol=1e-7)


def test_a_prediction_far_beyond_a_limit_locks_the_update_out():
    # predicted reading -omega^2 p = -1.6, six noise standard deviations below the lower limit; the reading
    # -0.4 is uncensored and far from it, yet the Tobit update's probability of an uncensored reading is
    # Phi(-6) - 0 ~ 1e-9, and the estimate barely moves: the filter ignores the data (the same equations)
    system = tk.NonlinearSystem(f, h, np.zeros((2, 2)), [[SIGMA**2]], [6.4, 0.5], np.diag([1.0, 0.001]))
    cens = tk.Censoring(lower=LO, upper=HI)
    tobit = tk.TobitExtendedKalmanFilter(system, cens).filter([[-0.4]])
    xo, _ = _oracle(system.x0, system.P0, -0.4)
    np.testing.assert_allclose(tobit.mean[0], xo, rtol=0, atol=1e-9)
    assert abs(tobit.mean[0, 0] - 6.4) < 1e-6
    assert tobit.extras["slope"][0, 0] < 1e-8
    # the assumed-density filter spreads the latent reading by the prediction's variance (s^2 = H P H' + R):
    # the same reading pulls p most of the way towards the value that explains it (p = 0.4 / 0.25 = 1.6)
    adf = tk.NonlinearAssumedDensityFilter(system, cens).filter([[-0.4]])
    assert adf.mean[0, 0] < 4.0
