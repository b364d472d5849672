"""Divergence: an unstable plant predicted without readings for so long that its covariance overflows.

The answer is either correct (the square-root form keeps its factor finite, about 1.5^1000 ~ 1e176, and
the mean returns to the readings when they come back) or the call warns once, naming the first step where
the covariance stopped being finite and the remedy, and the affected runs' means are NaN from there on:
never a finite, wrong mean. (Before: the compiled path skipped the NaN channel and kept predicting, a
finite mean of 1e175 after the readings had returned.)
"""

from __future__ import annotations

import numpy as np
import pytest

import tobitkf as tk

SYS = tk.LinearSystem(A=[[1.5]], C=[[1.0]], Q=[[0.01]], R=[[0.1]], x0=[0.0], P0=[[1.0]])


def record():
    """Run 0: 10 readings, 940 lost, then 50 readings of 1e5; run 1 reads 0.3 throughout (stays healthy)."""
    y = np.full((2, 1000, 1), np.nan)
    y[:, :10] = tk.simulate(SYS, 10, 1, seed=0).y
    y[1, 10:] = 0.3
    y[:, 950:] = 1e5
    return y


MAKERS = {
    "kf": lambda b, f: tk.KalmanFilter(SYS, backend=b, covariance_update=f),
    "dkf": lambda b, f: tk.DroppingKalmanFilter(SYS, tk.Censoring(lower=-1e9), backend=b, covariance_update=f),
    "tkf": lambda b, f: tk.TobitKalmanFilter(SYS, tk.Censoring(), backend=b, covariance_update=f),
}


@pytest.mark.parametrize("form", ["standard", "joseph"])
@pytest.mark.parametrize("backend", ["numpy", "auto"])
@pytest.mark.parametrize("name", sorted(MAKERS))
def test_overflow_warns_once_and_gives_nan_never_a_finite_wrong_mean(name, backend, form):
    est = MAKERS[name](backend, form)
    y = record()
    with pytest.warns(RuntimeWarning, match=r"covariance stopped being finite at step k=\d+.*square_root") as rec:
        out = est.filter(y)
    assert len([w for w in rec if "stopped being finite" in str(w.message)]) == 1
    k = int(str(rec[0].message).split("k=")[1].split(" ")[0])
    assert 800 < k < 950  # 2.25^k * P0 passes 1.8e308 near k = 875
    bad = ~np.isfinite(out.mean[0, :, 0])
    assert bad[k - 1 :].all() and not bad[: k - 1].any()  # NaN from the first bad step, finite before
    healthy = out.mean[1]
    assert np.isfinite(healthy).all() and abs(healthy[-1, 0] - 1.5e5) < 1e4  # the other run is untouched


@pytest.mark.parametrize("name", sorted(MAKERS))
def test_square_root_form_stays_finite_and_returns_to_the_readings(name):
    out = MAKERS[name]("numpy", "square_root").filter(record())
    assert np.isfinite(out.mean).all()
    assert np.isfinite(out.final.S).all() and np.abs(out.final.S).max() < 1e3  # small again after the readings
    # after the readings return, the lost run agrees with the run that never lost them
    np.testing.assert_allclose(out.mean[0, -1], out.mean[1, -1], rtol=1e-6)


def test_online_step_warns_once_per_run_of_bad_steps():
    kf = tk.KalmanFilter(SYS, backend="numpy")
    y = record()
    state = kf.init((2,))
    warned = 0
    for k in range(1000):
        with _Count() as c:
            state = kf.step(state, y[:, k])
        warned += c.count
    assert warned == 1 and np.isnan(state.mean[0]).all() and np.isfinite(state.mean[1]).all()


class _Count:
    """Count the divergence warnings of one call."""

    def __enter__(self):
        import warnings

        self._cm = warnings.catch_warnings(record=True)
        self._rec = self._cm.__enter__()
        warnings.simplefilter("always")
        return self

    def __exit__(self, *exc):
        self._cm.__exit__(*exc)
        self.count = sum("stopped being finite" in str(w.message) for w in self._rec)
        return False
