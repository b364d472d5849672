"""The compiled particle filter (tobitkf.filters._compiled_particle) against the numpy path it implements.

The compiled loop draws the numpy path's random numbers (same Generator calls, same order), so with
the runs in one block its results equal the numpy path's to rounding: means, covariances, the
extras, the final particles and the generator's state. With several blocks, block j equals the
numpy path run on those runs alone, continuing the generator where block j-1 left it. The normal
tails are checked against scipy.special.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import log_ndtr as scipy_log_ndtr
from scipy.special import ndtri_exp as scipy_ndtri_exp

import tobitkf as tk
from tobitkf.filters.core import FilterState

pytest.importorskip("numba")

from tobitkf.filters import _compiled_particle as cp  # noqa: E402

TOL = 1e-12


def system(m):
    A = [[0.95, 0.1], [0.0, 0.9]]
    C = [[1.0, 0.0], [0.5, 1.0]][:m]
    R = np.diag([0.1, 0.2][:m])
    return tk.LinearSystem(A=A, C=C, Q=0.05 * np.eye(2), R=R, x0=[0.2, 0.0], P0=np.eye(2))


CENSORINGS = {
    "lower": lambda m: tk.Censoring(lower=np.zeros(m)),
    "upper": lambda m: tk.Censoring(upper=np.full(m, 0.3)),
    "two-sided": lambda m: tk.Censoring(lower=np.full(m, -0.2), upper=np.full(m, 0.4)),
    "mixed": lambda m: tk.Censoring(lower=[0.0, -np.inf][:m], upper=[np.inf, 0.3][:m]),
    "none": lambda m: None,
}


def record(m, cens, runs=6, steps=12, seed=0):
    y = tk.simulate(system(m), steps, runs, censoring=cens, seed=seed).y.copy()
    y[1, 3, 0] = np.nan  # one channel missing
    y[2, 5] = np.nan  # every channel missing
    return y


def assert_same(a, b):
    for key in ("mean", "cov", "pred_mean", "pred_cov"):
        np.testing.assert_allclose(getattr(b, key), getattr(a, key), rtol=0, atol=TOL, err_msg=key)
    np.testing.assert_array_equal(b.extras["resampled"], a.extras["resampled"])
    np.testing.assert_allclose(b.extras["ess"], a.extras["ess"], rtol=TOL, atol=0)
    np.testing.assert_allclose(b.extras["log_likelihood"], a.extras["log_likelihood"], rtol=0, atol=TOL)
    fa, fb = a.final.carry, b.final.carry
    np.testing.assert_allclose(fb["particles"], fa["particles"], rtol=0, atol=TOL)
    np.testing.assert_allclose(fb["log_weights"], fa["log_weights"], rtol=0, atol=TOL)
    np.testing.assert_allclose(fb["log_likelihood"], fa["log_likelihood"], rtol=0, atol=TOL)
    assert fb["rng"] == fa["rng"]


@pytest.mark.parametrize("proposal", ["optimal", "prior"])
@pytest.mark.parametrize("m", [1, 2])
@pytest.mark.parametrize("kind", list(CENSORINGS))
def test_compiled_equals_numpy_for_the_same_random_numbers(proposal, m, kind):
    cens = CENSORINGS[kind](m)
    y = record(m, cens)
    kw = dict(particles=200, proposal=proposal, seed=3, resample_threshold=0.7)
    a = tk.ParticleFilter(system(m), cens, backend="numpy", **kw).filter(y)
    b = tk.ParticleFilter(system(m), cens, backend="numba", **kw).filter(y)
    assert a.extras["resampled"].any() and not a.extras["resampled"].all()  # both branches are exercised
    assert_same(a, b)


def test_time_varying_limits_and_a_batch_shape():
    cens = tk.Censoring(lower=np.linspace(-0.5, 0.5, 10)[:, None])
    y = tk.simulate(system(1), 10, 6, censoring=cens, seed=1).y.reshape(2, 3, 10, 1)
    kw = dict(particles=150, seed=5)
    a = tk.ParticleFilter(system(1), cens, backend="numpy", **kw).filter(y)
    b = tk.ParticleFilter(system(1), cens, backend="numba", **kw).filter(y)
    assert b.mean.shape == (2, 3, 10, 2)
    assert_same(a, b)


@pytest.mark.parametrize("proposal", ["optimal", "prior"])
def test_blocks_of_runs_continue_the_generator(proposal):
    cens = CENSORINGS["two-sided"](1)
    y = record(1, cens, runs=7)
    pf = tk.ParticleFilter(system(1), cens, particles=120, proposal=proposal, seed=9, backend="numpy")
    st = pf.init((7,))
    got = cp.filter_blocks(pf, y, st, frozenset(("mean", "cov", "extras")), (7,), block=3)
    rng = st.carry["rng"]
    for r0 in range(0, 7, 3):
        r1 = min(7, r0 + 3)
        sub = FilterState(
            k=0,
            batch_shape=(r1 - r0,),
            x=st.x[r0:r1],
            P=st.P[r0:r1],
            n=2,
            S=None,
            carry={
                "particles": st.carry["particles"][r0:r1],
                "log_weights": st.carry["log_weights"][r0:r1],
                "rng": rng,
                "log_likelihood": np.zeros(r1 - r0),
            },
        )
        ref = pf.filter(y[r0:r1], state=sub)
        rng = ref.final.carry["rng"]
        np.testing.assert_allclose(got.mean[r0:r1], ref.mean, rtol=0, atol=TOL)
        np.testing.assert_allclose(got.cov[r0:r1], ref.cov, rtol=0, atol=TOL)
        np.testing.assert_array_equal(got.extras["resampled"][r0:r1], ref.extras["resampled"])
        np.testing.assert_allclose(got.final.carry["particles"][r0:r1], ref.final.carry["particles"], atol=TOL)
    assert got.final.carry["rng"] == rng


def test_a_filter_continued_from_its_final_state_equals_one_call():
    cens = CENSORINGS["lower"](1)
    y = record(1, cens, steps=14)
    pf = tk.ParticleFilter(system(1), cens, particles=100, seed=2, backend="numba")
    whole = pf.filter(y)
    first = pf.filter(y[:, :6])
    rest = pf.filter(y[:, 6:], state=first.final)
    np.testing.assert_allclose(rest.mean, whole.mean[:, 6:], rtol=0, atol=TOL)
    np.testing.assert_allclose(rest.final.carry["log_likelihood"], whole.final.carry["log_likelihood"], atol=TOL)
    np.testing.assert_array_equal(rest.times, np.arange(7, 15))
    # outputs on request: nothing recorded but the final state; the variances only
    last = pf.filter(y, outputs="last")
    assert last.mean is None and last.extras == {}
    np.testing.assert_allclose(last.final.x, whole.final.x, atol=TOL)
    var = pf.filter(y, outputs="var").var
    np.testing.assert_allclose(var, np.diagonal(whole.cov, axis1=-2, axis2=-1), atol=TOL)


def test_dispatch_covers_linear_readings_only():
    fad = tk.RiceFading.gaussian(1, [0.9, 0.5], [0.01, 0.01])
    sys_ = system(1)
    with pytest.raises(tk.ValidationError, match="backend: the numba kernel of the particle filter"):
        tk.ParticleFilter(sys_, fad, particles=10, backend="numba").filter(np.zeros((5, 1)))
    with pytest.raises(tk.ValidationError, match="backend: expected one of"):
        tk.ParticleFilter(sys_, particles=10, backend="jax")
    # "auto" falls back to numpy for fading: equal to backend="numpy" exactly
    y = np.abs(np.random.default_rng(0).normal(size=(3, 5, 1)))
    a = tk.ParticleFilter(sys_, fad, particles=50, seed=1, backend="auto").filter(y)
    b = tk.ParticleFilter(sys_, fad, particles=50, seed=1, backend="numpy").filter(y)
    np.testing.assert_array_equal(a.mean, b.mean)
    # a control input is not covered by the compiled loop
    sys_u = tk.LinearSystem(
        A=sys_.A.at(0), C=[[1.0, 0.0]], Q=0.05 * np.eye(2), R=[[0.1]], x0=[0.0, 0.0], P0=np.eye(2), Bu=np.eye(2)
    )
    with pytest.raises(tk.ValidationError, match="control inputs"):
        tk.ParticleFilter(sys_u, particles=10, backend="numba").filter(np.zeros((5, 1)), u=np.zeros((5, 2)))


def test_log_ndtr_matches_scipy_in_both_tails():
    x = np.concatenate([np.linspace(-80.0, 12.0, 3001), [-1e4, -1e3, -35.4, -35.3, -20.0, 0.0, 6.0, 40.0]])
    ours = np.array([cp.log_ndtr(v) for v in x])
    np.testing.assert_allclose(ours, scipy_log_ndtr(x), rtol=1e-13, atol=0)
    assert cp.log_ndtr(np.inf) == 0.0 and cp.log_ndtr(-np.inf) == -np.inf


def test_ndtri_exp_inverts_log_ndtr():
    t = -np.concatenate([np.logspace(-300, 4, 3000), [np.log(2.0), 0.02, 3.7]])
    ours = np.array([cp.ndtri_exp(v) for v in t])
    np.testing.assert_allclose(ours, scipy_ndtri_exp(t), rtol=1e-12, atol=1e-12)
    back = np.array([cp.log_ndtr(z) for z in ours])
    # the round trip is conditioned by |z| (d log t / dz ~ z far in the upper tail): 40 ulp of z
    np.testing.assert_allclose(back, t, rtol=1e-12, atol=0)
    assert cp.ndtri_exp(-np.inf) == -np.inf and cp.ndtri_exp(0.0) == np.inf and np.isnan(cp.ndtri_exp(0.5))
