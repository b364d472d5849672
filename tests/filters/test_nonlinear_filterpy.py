"""The cubature rule and Julier's unscented rule against filterpy's UKF with the same points.

``tests/filters/test_nonlinear.py`` compares the scaled unscented rule with filterpy's
``MerweScaledSigmaPoints``; here the two other point sets filterpy has: the cubature rule is the scaled rule with
alpha = 1, beta = 0, kappa = 0 (2n points at ±sqrt(n) of weight 1/(2n), the centre's weight 0), and Julier's
``JulierSigmaPoints(kappa)`` is the scaled rule with alpha = 1, beta = 0.
"""

from __future__ import annotations

import numpy as np
import pytest

import tobitkf as tk

from .test_nonlinear_model import DT, P0, X0, Q, R, f, h, pendulum

fk = pytest.importorskip("filterpy.kalman")


def _filterpy(points, y):
    ref = fk.UnscentedKalmanFilter(2, 2, DT, hx=lambda x: h(x, 0), fx=lambda x, dt: f(x, 0), points=points)
    ref.x, ref.P, ref.Q, ref.R = X0.copy(), P0.copy(), Q, R
    means, covs = [], []
    for z in y:
        ref.predict()
        ref.update(z)
        means.append(ref.x.copy())
        covs.append(ref.P.copy())
    return np.array(means), np.array(covs)


@pytest.mark.parametrize(
    "ours,points",
    [
        ({"rule": "cubature"}, lambda: fk.MerweScaledSigmaPoints(2, 1.0, 0.0, 0.0)),
        ({"rule": "unscented", "alpha": 1.0, "beta": 0.0, "kappa": 1.0}, lambda: fk.JulierSigmaPoints(2, 1.0)),
        ({"rule": "unscented", "alpha": 1.0, "beta": 0.0, "kappa": 0.5}, lambda: fk.JulierSigmaPoints(2, 0.5)),
    ],
    ids=["cubature", "julier-1", "julier-0.5"],
)
def test_ukf_equals_filterpy_with_the_same_points(ours, points):
    y = tk.simulate(pendulum(), 40, 1, seed=41).y[0]
    got = tk.UnscentedKalmanFilter(pendulum(), **ours).filter(y)
    mean, cov = _filterpy(points(), y)
    np.testing.assert_allclose(got.mean, mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(got.cov, cov, rtol=0, atol=1e-10)
