"""The compiled assumed-density filters against their numpy paths far into the tails, with a check that does not
lean on either path.

- The fading filter with readings 40 predicted standard deviations into either tail (the cases of the censored
  filter's tail test in ``test_compiled_adf.py``), its log-likelihood there against ``scipy.special.log_ndtr``
  and the normal log-density. The latent reading at the first step is y* = theta x_1 + v with
  theta ~ N(0.9, 0.01), x_1 ~ N(0, 0.5), v ~ N(0, 0.5): mean 0, variance 0.81 * 0.5 + 0.01 * 0.5 + 0.5 (the fading
  filter's moments of the faded reading), so the limits sit 40 of its standard deviations from its mean.
- The multi-region filter (censored windows stacked as sensors) with the state far beyond every window.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import log_ndtr
from scipy.stats import norm

import tobitkf as tk

pytest.importorskip("numba")

from .test_compiled_adf import assert_same, both  # noqa: E402

S = float(np.sqrt(0.9**2 * 0.5 + 0.01 * 0.5 + 0.5))  # the latent reading's predicted standard deviation
INF = np.inf

# (lower, upper, reading, log-likelihood of the reading under N(0, S^2))
CASES = {
    "at a lower limit 40 sd below": (-40 * S, INF, -40 * S, log_ndtr(-40.0)),
    "at a lower limit 40 sd above": (40 * S, INF, 40 * S, log_ndtr(40.0)),
    "at an upper limit 40 sd above": (-INF, 40 * S, 40 * S, log_ndtr(-40.0)),
    "at an upper limit 40 sd below": (-INF, -40 * S, -40 * S, log_ndtr(40.0)),
    "at the upper end of a window 40 sd wide": (-40 * S, 40 * S, 40 * S, log_ndtr(-40.0)),
    "inside a window 40 sd wide": (-40 * S, 40 * S, 0.3, norm.logpdf(0.3 / S) - np.log(S)),
}


@pytest.mark.parametrize("case", list(CASES))
def test_fading_adf_readings_forty_sigma_into_the_tails(case):
    lo, hi, reading, want = CASES[case]
    sys_ = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.0]], R=[[0.5]], x0=[0.0], P0=[[0.5]])
    fad = tk.RiceFading.gaussian(0, [0.9], [0.01])
    cens = tk.Censoring(lower=lo, upper=hi)
    y = np.array([[[reading]], [[float(np.clip(0.1, lo, hi))]]])  # two runs of one step
    a, b = both(lambda be: tk.FadingAssumedDensityFilter(sys_, fad, cens, backend=be), y)
    assert np.isfinite(a.mean).all() and np.isfinite(a.cov).all()
    assert a.extras["log_likelihood"][0, 0] == pytest.approx(want, rel=1e-12, abs=1e-300)
    assert_same(a, b)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_multi_region_adf_forty_sigma_beyond_every_window(sign):
    """Two windows with a gap (Miller §6.6 Example 3) and the state 40 noise standard deviations beyond the outer
    limit, above or below: every reading sits at a limit on the side the prediction is certain of, so the update
    learns nothing (the mean stays, the covariance grows by Q each step), on both paths to 1e-12."""
    sigma = 0.05
    x0 = sign * (1.5 + 40 * sigma)
    base = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[1e-6]], R=[[sigma**2]], x0=[x0], P0=[[1e-6]])
    sys_, cens = tk.multi_region(base, [[(-1.5, -0.1), (0.1, 1.5)]])
    y = tk.simulate(sys_, 30, 4, censoring=cens, seed=7).y.copy()
    y[1, 5:8, 0] = np.nan  # lost readings
    a, b = both(lambda be: tk.AssumedDensityTobitFilter(sys_, cens, backend=be), y)
    assert np.nanmin(a.extras["p_uncensored"]) < 1e-300  # the readings do sit far out
    np.testing.assert_allclose(a.mean, x0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.cov[..., 0, 0], np.broadcast_to(1e-6 * (1 + np.arange(1, 31)), (4, 30)), rtol=1e-12)
    assert_same(a, b)
