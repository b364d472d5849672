"""The steady-state TKF (Miller 2015, §3.4.2) through the one compiled loop (its fixed-gain code) against its
numpy reference path.

The numpy path is the reference (tests/filters/test_steady_state.py checks it against the source); the
compiled loop must reproduce it to rounding (1e-12) in every case it covers, and every other case must run
on numpy (``backend="auto"``) or be refused (``backend="numba"``).

The family is one-sided by construction (the limit (3.56) is set on one side, ``side``), so "one- and
two-sided" means both sides here; NaN readings are refused by the estimator on either path.
"""

import numpy as np
import pytest

import tobitkf as tk
from tobitkf._validation import ValidationError
from tobitkf.filters import _backend
from tobitkf.filters.steady_state import ControlledLimitTobitKalmanFilter, SteadyStateTobitKalmanFilter

pytest.importorskip("numba")
from tobitkf.filters import _compiled_loop  # noqa: E402

from ._compare import assert_same

FIELDS = ("mean", "cov", "pred_mean", "pred_cov", "var")


def assert_results_equal(r1, r2, rtol=1e-12):
    for f in FIELDS:
        va, vb = getattr(r1, f), getattr(r2, f)
        assert (va is None) == (vb is None), f
        if va is not None:
            assert_same(va, vb, rtol)
            assert va.flags.writeable == vb.flags.writeable, f  # shared covariances: read-only views on both
    assert r1.extras.keys() == r2.extras.keys()
    for key in r1.extras:
        assert_same(r1.extras[key], r2.extras[key], rtol)
    np.testing.assert_array_equal(r1.times, r2.times)
    assert r1.final.k == r2.final.k
    assert_same(r1.final.x, r2.final.x, rtol)
    assert_same(np.broadcast_to(r1.final.P, r2.final.P.shape), r2.final.P, rtol)


def oscillator(m=1, Bu=None):
    w = 0.1
    A = [[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]]
    C = [[1.0, 0.0]] if m == 1 else [[1.0, 0.0], [0.4, 1.0]]
    return tk.LinearSystem(
        A=A, C=C, Q=0.01 * np.eye(2), R=np.diag([0.1, 0.05][:m]), x0=[1.0, 0.0], P0=0.05 * np.eye(2), Bu=Bu
    )


def latent(sys_, runs, steps, seed=0):
    return tk.simulate(sys_, steps=steps, runs=runs, seed=seed).y_latent


def both(sys_, xi, side, y, method="filter", **kw):
    a = SteadyStateTobitKalmanFilter(sys_, xi, side=side, backend="numba")
    b = SteadyStateTobitKalmanFilter(sys_, xi, side=side, backend="numpy")
    return getattr(a, method)(y, **kw), getattr(b, method)(y, **kw)


def censored_at_own_limits(sys_, xi, side, ylat):
    """Readings censored at the limits the filter sets from its own priors (what ``filter`` expects)."""
    return SteadyStateTobitKalmanFilter(sys_, xi, side=side, backend="numpy").filter_controlled(ylat).extras["y"]


@pytest.mark.parametrize("method", ["filter", "filter_controlled"])
@pytest.mark.parametrize("side", ["upper", "lower"])
@pytest.mark.parametrize(("m", "xi"), [(1, 0.5), (1, 0.9), (2, [0.3, 0.8])])
def test_kernel_equals_numpy(method, side, m, xi):
    sys_ = oscillator(m)
    y = latent(
        sys_, runs=133, steps=150
    )  # 133 runs: one full block of 128 (runs_per_block(2)) and a partial one; 150 > CHUNK
    if method == "filter":
        y = censored_at_own_limits(sys_, xi, side, y)
    a, b = both(sys_, xi, side, y, method)
    assert_results_equal(a, b)
    if method == "filter_controlled":
        # the clip happened: every reading the filter received is on the right side of its limit
        rec, lim = a.extras["y"], a.extras["limits"]
        assert np.all(rec <= lim) if side == "upper" else np.all(rec >= lim)


@pytest.mark.parametrize("side", ["upper", "lower"])
def test_tails_at_40_sigma(side):
    """Latent readings +-40 sigma away from the prediction: clipped at the limit on one side, taken as
    they are on the other; the kernel agrees with numpy on both."""
    sys_ = oscillator()
    sig = np.sqrt(0.1)
    ylat = latent(sys_, runs=5, steps=60)
    ylat[:, ::3] += 40 * sig
    ylat[:, 1::3] -= 40 * sig
    a, b = both(sys_, 0.7, side, ylat, "filter_controlled")
    assert_results_equal(a, b)
    a, b = both(sys_, 0.7, side, ylat, "filter")  # readings far outside the limits (the filter does not check)
    assert_results_equal(a, b)


@pytest.mark.parametrize("backend", ["numba", "numpy"])
@pytest.mark.parametrize("method", ["filter", "filter_controlled"])
def test_nan_readings_are_refused_on_both_paths(backend, method):
    sys_ = oscillator()
    y = latent(sys_, runs=3, steps=10)
    y[1, 4, 0] = np.nan
    with pytest.raises(ValidationError, match="cannot skip missing samples"):
        getattr(SteadyStateTobitKalmanFilter(sys_, 0.7, backend=backend), method)(y)


@pytest.mark.parametrize("batch", [(), (1,), (6,), (2, 3)])
def test_batch_shapes_and_continuation(batch):
    sys_ = oscillator(2)
    xi = [0.4, 0.9]
    ylat = latent(sys_, runs=int(np.prod(batch)), steps=30).reshape(batch + (30, 2))
    x0 = np.random.default_rng(3).normal(size=batch + (2,))
    for method in ("filter", "filter_controlled"):
        a, b = both(sys_, xi, "upper", ylat, method, x0=x0)
        assert a.mean.shape == batch + (30, 2)
        assert_results_equal(a, b)
        # continue from the state after 12 steps: the same as one call
        first = getattr(SteadyStateTobitKalmanFilter(sys_, xi, backend="numba"), method)(ylat[..., :12, :], x0=x0)
        rest = getattr(SteadyStateTobitKalmanFilter(sys_, xi, backend="numba"), method)(
            ylat[..., 12:, :], state=first.final
        )
        assert_same(rest.mean, b.mean[..., 12:, :])
        np.testing.assert_array_equal(rest.times, np.arange(13, 31))


@pytest.mark.parametrize("outputs", ["last", ("mean",), ("cov",), ("var",), ("pred_mean", "extras"), "all"])
@pytest.mark.parametrize("method", ["filter", "filter_controlled"])
def test_kernel_honours_the_output_selection(outputs, method):
    sys_ = oscillator(2)
    y = latent(sys_, runs=9, steps=15)
    a, b = both(sys_, 0.6, "lower", y, method, outputs=outputs)
    assert_results_equal(a, b)


def test_divergence_is_reported_as_on_numpy():
    """The fixed-gain observer that the module docstring calls unstable (A = -1, Xi < 0.5, small sigma):
    both paths overflow and warn."""
    sys_ = tk.LinearSystem(A=[[-1.0]], C=[[1.0]], Q=[[0.01]], R=[[1e-4]], x0=[0.0], P0=[[1.0]])
    y = np.full((2, 2000, 1), 50.0)
    with pytest.warns(RuntimeWarning, match="diverged"):
        a = SteadyStateTobitKalmanFilter(sys_, 0.05, backend="numba").filter(y)
    with pytest.warns(RuntimeWarning, match="diverged"):
        b = SteadyStateTobitKalmanFilter(sys_, 0.05, backend="numpy").filter(y)
    np.testing.assert_array_equal(np.isfinite(a.mean), np.isfinite(b.mean))


@pytest.mark.parametrize("backend", ["numba", "numpy"])
@pytest.mark.parametrize("method", ["filter", "filter_controlled"])
def test_divergence_warning_names_the_caller_and_the_step(backend, method):
    """The kernel reports its means' finiteness itself (no second pass over them): the warning is the
    numpy path's, with the same step, pointing at the caller's line; none without the means."""
    # filter: the constant readings above; filter_controlled: the latent readings of test_extremes_families
    sys_ = tk.LinearSystem(A=[[-1.0]], C=[[1.0]], Q=[[0.15]], R=[[1e-4]], x0=[0.0], P0=[[1.0]])
    y = np.full((3, 2000, 1), 50.0) if method == "filter" else tk.simulate(sys_, 1000, 3, seed=0).y_latent
    est = SteadyStateTobitKalmanFilter(sys_, 0.1, backend=backend)
    ref = SteadyStateTobitKalmanFilter(sys_, 0.1, backend="numpy")
    with np.errstate(over="ignore", invalid="ignore"), pytest.warns(RuntimeWarning, match="diverged") as rec:
        res = getattr(est, method)(y)
    step = int(np.argmax(~np.isfinite(res.mean[0]).all(axis=-1))) + 1
    assert f"at step k={step};" in str(rec[0].message)
    assert rec[0].filename == __file__
    with np.errstate(over="ignore", invalid="ignore"), pytest.warns(RuntimeWarning, match="diverged"):
        np.testing.assert_array_equal(np.isfinite(getattr(ref, method)(y).mean), np.isfinite(res.mean))
    with np.errstate(over="ignore", invalid="ignore"):  # no means recorded: nothing to report (as before)
        getattr(est, method)(y, outputs=("pred_mean",))


# --- dispatch -----------------------------------------------------------------------------------


def _raise(*args):
    raise AssertionError("steady-state kernel used")


def test_auto_uses_the_kernel_when_covered(monkeypatch):
    sys_ = oscillator()
    y = latent(sys_, runs=2, steps=5)
    monkeypatch.setattr(_compiled_loop, "compiled_loop", _raise)
    for method in ("filter", "filter_controlled"):
        with pytest.raises(AssertionError, match="steady-state kernel used"):
            getattr(SteadyStateTobitKalmanFilter(sys_, 0.7), method)(y)
        getattr(SteadyStateTobitKalmanFilter(sys_, 0.7, backend="numpy"), method)(y)  # numpy never touches it


@pytest.mark.parametrize("method", ["filter", "filter_controlled"])
def test_input_falls_back_to_numpy_or_is_refused(method, monkeypatch):
    sys_ = oscillator(Bu=[[0.1], [0.0]])
    y = latent(oscillator(), runs=2, steps=20)
    u = np.ones((20, 1))
    ref = getattr(SteadyStateTobitKalmanFilter(sys_, 0.7, backend="numpy"), method)(y, u=u)
    match = "compiled path of the steady-state Tobit Kalman filter does not cover control inputs"
    with pytest.raises(ValidationError, match=match):
        getattr(SteadyStateTobitKalmanFilter(sys_, 0.7, backend="numba"), method)(y, u=u)
    monkeypatch.setattr(_compiled_loop, "compiled_loop", _raise)
    auto = getattr(SteadyStateTobitKalmanFilter(sys_, 0.7), method)(y, u=u)
    assert_results_equal(auto, ref, 0.0)


def test_without_numba(monkeypatch):
    monkeypatch.setattr(_backend, "_load", lambda: None)
    sys_ = oscillator()
    y = latent(sys_, runs=2, steps=10)
    with pytest.raises(ImportError, match="needs the numba package"):
        SteadyStateTobitKalmanFilter(sys_, 0.7, backend="numba").filter(y)
    auto = SteadyStateTobitKalmanFilter(sys_, 0.7).filter(y)
    assert_results_equal(auto, SteadyStateTobitKalmanFilter(sys_, 0.7, backend="numpy").filter(y), 0.0)


def test_backend_option_is_checked():
    with pytest.raises(ValidationError, match="backend"):
        SteadyStateTobitKalmanFilter(oscillator(), 0.7, backend="cuda")


def test_controlled_limit_tkf_has_no_kernel():
    """The full TKF with the limit set from its prior: numpy under "auto", refused under "numba"."""
    sys_ = oscillator()
    y = latent(sys_, runs=2, steps=10)
    with pytest.raises(ValidationError, match="controlled-limit TKF does not cover a limit set from"):
        ControlledLimitTobitKalmanFilter(sys_, 0.7, backend="numba").filter(y)
    auto = ControlledLimitTobitKalmanFilter(sys_, 0.7).filter(y)
    ref = ControlledLimitTobitKalmanFilter(sys_, 0.7, backend="numpy").filter(y)
    assert_results_equal(auto, ref, 1e-12)  # the compiled shared step around the numpy moments
