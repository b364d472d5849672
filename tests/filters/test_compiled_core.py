"""The compiled shared step (filters/_compiled_step.py) equals the numpy shared step (filters/core.py).

Each case is run twice through the public functions, ``compiled=False`` (the numpy reference) and
``compiled=True``, on random inputs that reach every branch: the plain and the block-shift predict
(source 0; a pure delay, source > 0, runs on numpy), an input offset, one run and more runs than a
kernel block (``runs_per_block(nx)`` runs: 128 at these sizes), one and several channels, the standard and Joseph forms, a diagonal and a full noise term, a per-run channel scale,
family masks, missing readings, a degenerate innovation variance and a retained variance.
"""

from __future__ import annotations

import numpy as np
import pytest

import tobitkf as tk
from tobitkf.filters import _update
from tobitkf.filters.core import MeasurementPrediction, Transition, measurement_update, time_update

pytest.importorskip("numba")

RTOL = 1e-12


def _spd(rng, N, n):
    L = rng.normal(size=(N, n, n))
    P = L @ L.swapaxes(-1, -2) + 0.1 * np.eye(n)
    return 0.5 * (P + P.swapaxes(-1, -2))  # exactly symmetric (the shift predict needs it)


def _close(a, b):
    scale = max(1.0, float(np.abs(b).max()))
    np.testing.assert_allclose(a, b, rtol=0, atol=RTOL * scale)


@pytest.mark.parametrize("N", [1, 3, 133])  # 133: a block of 128 (nx <= 8) and a part
@pytest.mark.parametrize("blocks,source", [(1, 0), (3, 0), (4, 3)])
@pytest.mark.parametrize("offset", ["none", "shared", "per_run"])
def test_time_update_compiled_equals_numpy(N, blocks, source, offset):
    rng = np.random.default_rng(N * 100 + blocks * 10 + source)
    n = 2
    nx = n * blocks
    x = rng.normal(size=(N, nx))
    P = _spd(rng, N, nx)
    A = rng.normal(size=(n, n))
    Qd = _spd(rng, 1, n)[0]
    b = {"none": 0.0, "shared": rng.normal(size=n), "per_run": rng.normal(size=(N, n))}[offset]
    tr = Transition(A=A if blocks > 1 else A, Qd=Qd, b=b, shift=blocks > 1, source=source)
    ref = time_update(x, P, None, tr, "standard")
    got = time_update(x, P, None, tr, "standard", compiled=True)
    _close(got[0], ref[0])
    _close(got[1], ref[1])
    assert got[2] is None
    np.testing.assert_array_equal(got[1], got[1].swapaxes(-1, -2))  # exactly symmetric


def _prediction(rng, N, m, nx, *, noise, scale, mask, missing, degenerate, retained):
    kw = {}
    if scale:
        kw["scale"] = rng.uniform(0.2, 1.5, size=(N, m))
    if noise == "diag":
        kw["noise"] = rng.uniform(0.1, 2.0, size=(N, m))
    elif noise == "shared_diag":
        kw["noise"] = rng.uniform(0.1, 2.0, size=(1, m))
    else:
        kw["noise"] = _spd(rng, N, m)
    if mask:
        kw["valid"] = rng.uniform(size=(N, m)) > 0.3
    if retained:
        kw["retained"] = rng.uniform(0.0, 0.5, size=(N, m))
    H0 = rng.normal(size=(m, nx))
    if degenerate:
        H0[0] = 0.0  # channel 0 carries no information: R_ee,00 is the noise alone, made subnormal below
        if noise != "full":
            kw["noise"] = kw["noise"].copy()
            kw["noise"][..., 0] = 1e-310
    y = rng.normal(size=(N, m))
    if missing:
        y[rng.uniform(size=(N, m)) < 0.25] = np.nan
    return MeasurementPrediction(expected=rng.normal(size=(N, m)), H0=H0, **kw), y


@pytest.mark.parametrize("N", [1, 133])
@pytest.mark.parametrize("m", [1, 2, 3])
@pytest.mark.parametrize("form", ["standard", "joseph"])
@pytest.mark.parametrize(
    "variant",
    [
        dict(noise="diag", scale=False, mask=False, missing=False, degenerate=False, retained=False),
        dict(noise="shared_diag", scale=True, mask=True, missing=True, degenerate=False, retained=False),
        dict(noise="full", scale=True, mask=False, missing=True, degenerate=False, retained=True),
        dict(noise="diag", scale=True, mask=True, missing=False, degenerate=True, retained=True),
    ],
)
def test_measurement_update_compiled_equals_numpy(N, m, form, variant):
    rng = np.random.default_rng(N + 7 * m + (form == "joseph"))
    nx = 4
    x = rng.normal(size=(N, nx))
    P = _spd(rng, N, nx)
    mp, y = _prediction(rng, N, m, nx, **variant)
    ref = measurement_update(x, P, None, y, mp, form)
    got = measurement_update(x, P, None, y, mp, form, compiled=True)
    for g, r in zip(got[:2], ref[:2]):
        _close(g, r)
    assert got[2] is None
    _close(got[3], np.broadcast_to(ref[3], got[3].shape))  # the gain (zero columns where masked)
    _close(got[4], np.broadcast_to(ref[4], got[4].shape))  # R_ee
    np.testing.assert_array_equal(got[1], got[1].swapaxes(-1, -2))


def test_uncovered_cases_stay_on_numpy():
    """A covariance shared by the runs and the square-root form run the numpy code (bitwise the same)."""
    rng = np.random.default_rng(3)
    x = rng.normal(size=(5, 2))
    P = _spd(rng, 1, 2)  # one covariance for five runs
    tr = Transition(A=rng.normal(size=(2, 2)), Qd=np.eye(2))
    for a, b in zip(time_update(x, P, None, tr, "standard"), time_update(x, P, None, tr, "standard", compiled=True)):
        if a is None:
            assert b is None
        else:
            np.testing.assert_array_equal(a, b)
    mp = MeasurementPrediction(expected=np.zeros((5, 1)), H0=np.array([[1.0, 0.0]]), noise=np.ones((1, 1)))
    y = rng.normal(size=(5, 1))
    a = measurement_update(x, P, None, y, mp, "standard")
    b = measurement_update(x, P, None, y, mp, "standard", compiled=True)
    assert b[1].shape == a[1].shape == (1, 2, 2)
    np.testing.assert_array_equal(a[0], b[0])


def _osc():
    A = np.array([[np.cos(0.05), -np.sin(0.05)], [np.sin(0.05), np.cos(0.05)]])
    return tk.LinearSystem(A=A, C=np.eye(2), Q=0.0025 * np.eye(2), R=np.eye(2), x0=[5.0, 0.0], P0=np.eye(2))


@pytest.mark.parametrize("form", ["joseph", "standard"])
@pytest.mark.parametrize("failure_term", ["variance", "second_moment"])
def test_protocol_filter_and_step_compiled_equal_numpy(form, failure_term):
    """The protocol TKF (no kernel of its own) through the compiled shared step equals backend="numpy",
    in filter (batched) and in the online step of one run (which also takes the float route of (21)-(24))."""
    from tobitkf.channels.protocol import LAMBDA_BASE

    sys_ = _osc()
    ch = tk.ProtocolChannel(2, window=2, failures=LAMBDA_BASE, threshold=0.0)
    y = tk.simulate(sys_, 60, 4, channel=ch, seed=11).y
    kw = dict(covariance_update=form, failure_term=failure_term)
    ref = tk.ProtocolTobitKalmanFilter(sys_, ch, backend="numpy", **kw).filter(y)
    est = tk.ProtocolTobitKalmanFilter(sys_, ch, **kw)
    assert est._compiled_core()
    got = est.filter(y)
    _close(got.mean, ref.mean)
    _close(got.cov, ref.cov)
    for key in ("innovation", "innovation_var", "p_uncensored", "expected_y"):
        _close(got.extras[key], ref.extras[key])
    s = est.init()
    for k in range(y.shape[1]):
        s = est.step(s, y[2, k])
    _close(s.mean, ref.mean[2, -1])
    _close(s.cov, ref.cov[2, -1])
    s = tk.ProtocolTobitKalmanFilter(sys_, ch, backend="numpy", **kw).init()
    est_np = tk.ProtocolTobitKalmanFilter(sys_, ch, backend="numpy", **kw)
    for k in range(y.shape[1]):
        s = est_np.step(s, y[2, k])
    _close(s.mean, ref.mean[2, -1])


def test_protocol_backend_option():
    from tobitkf.channels.protocol import LAMBDA_BASE

    ch = tk.ProtocolChannel(2, window=2, failures=LAMBDA_BASE, threshold=0.0)
    with pytest.raises(tk.ValidationError, match="backend"):
        tk.ProtocolTobitKalmanFilter(_osc(), ch, backend="gpu")
    assert not tk.ProtocolTobitKalmanFilter(_osc(), ch, backend="numpy")._compiled_core()
    assert tk.ProtocolTobitKalmanFilter(_osc(), ch, backend="numba")._compiled_core()


def test_time_varying_tkf_step_compiled_equals_numpy():
    """A TKF the block kernel does not cover (time-varying C) runs the compiled shared step; equal to numpy."""
    A = np.array([[1.0, 0.1], [0.0, 1.0]])
    C = np.stack([[[1.0, 0.2 * np.sin(0.3 * k)]] for k in range(41)])
    sys_ = tk.LinearSystem(A=A, C=C, Q=0.01 * np.eye(2), R=[[0.04]], x0=[0.0, 1.0], P0=np.eye(2))
    cens = tk.Censoring(lower=-0.2, upper=1.5)
    y = tk.simulate(sys_, 40, 3, censoring=cens, seed=2).y
    ref = tk.TobitKalmanFilter(sys_, cens, backend="numpy").filter(y)
    got = tk.TobitKalmanFilter(sys_, cens).filter(y)
    _close(got.mean, ref.mean)
    _close(got.cov, ref.cov)


def test_core_compiled_module_absent_means_numpy(monkeypatch):
    """Without numba (the kernels module fails to import) ``compiled=True`` runs the numpy code."""
    monkeypatch.setattr(_update, "_core_compiled_module", lambda: None)
    rng = np.random.default_rng(0)
    x, P = rng.normal(size=(2, 2)), _spd(rng, 2, 2)
    tr = Transition(A=np.eye(2), Qd=np.eye(2))
    a = time_update(x, P, None, tr, "standard")
    b = time_update(x, P, None, tr, "standard", compiled=True)
    np.testing.assert_array_equal(a[1], b[1])
