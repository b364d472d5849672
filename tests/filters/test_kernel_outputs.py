"""The compiled loops write only the outputs requested: ``outputs=("var",)`` gets the covariance
diagonals without an (N, T, n, n) array (issue 14's "outputs on request"), equal to the diagonals of
the full covariances bit for bit, in every compiled family (KF, TKF with m = 1 and m > 1, fading TKF,
protocol TKF), and the variances of the compiled path equal the numpy path's."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

import tobitkf as tk
from tobitkf.channels.fading import RiceFading
from tobitkf.channels.protocol import LAMBDA_BASE, ProtocolChannel
from tobitkf.filters._backend import numba_available

pytestmark = pytest.mark.skipif(not numba_available(), reason="needs numba")


def _system(n: int, m: int, seed: int = 0) -> tk.LinearSystem:
    rng = np.random.default_rng(seed)
    Qo, _ = np.linalg.qr(rng.standard_normal((n, n)))
    C = rng.standard_normal((m, n))
    return tk.LinearSystem(
        A=0.95 * Qo, C=C, Q=0.05 * np.eye(n), R=np.diag(rng.uniform(0.1, 0.5, m)), x0=np.ones(n), P0=np.eye(n)
    )


def _cases(runs: int, steps: int):
    """(name, estimator factory taking backend=, readings) of every family with a compiled loop."""
    s4 = _system(4, 1)
    cens = tk.Censoring(lower=0.0)
    y4 = tk.simulate(s4, steps, runs, censoring=cens, seed=1).y
    s42 = _system(4, 2, seed=2)
    c2 = tk.Censoring(lower=[0.0, -0.3])
    y42 = tk.simulate(s42, steps, runs, censoring=c2, seed=3).y
    fad = RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    yf = tk.simulate(s4, steps, runs, censoring=cens, measurement=fad, seed=4).y
    s2 = _system(4, 2, seed=5)
    ch = ProtocolChannel(2, window=2, failures=LAMBDA_BASE, threshold=0.0)
    yp = tk.simulate(s2, steps, runs, channel=ch, seed=6).y
    return [
        ("kf", lambda b: tk.KalmanFilter(s4, backend=b), y4),
        ("tkf", lambda b: tk.TobitKalmanFilter(s4, cens, backend=b), y4),
        ("tkf-m2", lambda b: tk.TobitKalmanFilter(s42, c2, backend=b), y42),
        ("fading", lambda b: tk.FadingTobitKalmanFilter(s4, fad, cens, backend=b), yf),
        ("protocol", lambda b: tk.ProtocolTobitKalmanFilter(s2, ch, backend=b), yp),
    ]


@pytest.mark.parametrize("name", ["kf", "tkf", "tkf-m2", "fading", "protocol"])
def test_variances_alone_equal_the_diagonals_of_the_covariances(name):
    (make, y) = {c[0]: c[1:] for c in _cases(7, 30)}[name]
    est = make("numba")
    full = est.filter(y)
    var = est.filter(y, outputs=("mean", "var"))
    assert var.cov is None and var.var.shape == y.shape[:-1] + (4,)
    # the same arithmetic, only the diagonal written: bitwise
    np.testing.assert_array_equal(var.var, np.diagonal(full.cov, axis1=-2, axis2=-1))
    np.testing.assert_array_equal(var.mean, full.mean)
    both = est.filter(y, outputs=("cov", "var"))
    np.testing.assert_array_equal(both.var, np.diagonal(both.cov, axis1=-2, axis2=-1))
    ref = make("numpy").filter(y, outputs=("mean", "var"))
    np.testing.assert_allclose(var.var, ref.var, rtol=1e-12, atol=1e-13)


def _peak(est, y):
    tracemalloc.start()
    res = est.filter(y, outputs=("var",))
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return peak, res.var.nbytes


@pytest.mark.parametrize("name", ["kf", "tkf", "fading", "protocol"])
def test_variances_alone_allocate_no_covariance_array(name):
    """The growth of the call's peak traced memory from T = 40 to T = 80 steps with outputs=("var",)
    (n = 4: a covariance array would add 4x what the variances add) is at most the variances' growth
    plus the readings' plus half the variances' of slack; with the full covariances it would be at least
    5x. (The difference removes what does not grow with T: the state of every run, the scratch.)"""
    (make, y) = {c[0]: c[1:] for c in _cases(2000, 80)}[name]
    est = make("numba")
    est.filter(y[:5, :3], outputs=("var",))  # compile outside the measurement
    p1, v1 = _peak(est, np.ascontiguousarray(y[:, :40]))
    p2, v2 = _peak(est, y)
    grow_y = y.nbytes // 2
    assert p2 - p1 <= 1.5 * (v2 - v1) + grow_y, (p2 - p1, v2 - v1)


def test_output_arrays_are_disjoint_views_of_one_allocation():
    """kalman.output_arrays: every requested output a C-contiguous (runs, T) + shape view, no two sharing an
    element (a wrong offset or size would make neighbours overlap and the kernel overwrite one with another),
    the ones not requested (runs, 0) + shape; cov_spec's layouts of the covariance output."""
    from tobitkf.filters._outputs import cov_spec, output_arrays

    specs = [(True, (3,)), (False, (2, 2)), (True, (1,)), (True, (2, 3, 3)), (True, ()), (False, (5,))]
    arrs = output_arrays(7, 5, *specs)
    assert [a.shape for a in arrs] == [(7, 5, 3), (7, 0, 2, 2), (7, 5, 1), (7, 5, 2, 3, 3), (7, 5), (7, 0, 5)]
    on = [a for a, (flag, _) in zip(arrs, specs) if flag]
    assert all(a.flags.c_contiguous and a.flags.writeable for a in on)
    base = on[0].base
    assert all(a.base is base for a in on)  # one allocation
    for i, a in enumerate(on):
        a[...] = i
    for i, a in enumerate(on):
        assert (a == i).all()  # nothing written through another view
        assert all(not np.shares_memory(a, b) for b in on[i + 1 :])
    expected = {
        ("mean", "cov"): (3, 2, 4, 4),
        ("var",): (3, 2, 4, 1),  # the diagonals alone
        ("mean", "var"): (3, 2, 4, 1),
        ("mean",): (3, 0, 4, 4),  # not written
        ("cov", "var"): (3, 2, 4, 4),
    }
    for want, shape_expected in expected.items():
        (c,) = output_arrays(3, 2, cov_spec(want, 4))
        assert c.shape == shape_expected


@pytest.mark.parametrize("name", ["fading", "protocol"])
def test_outputs_of_one_allocation_share_no_element(name):
    """The fading and protocol loops write every output of a call into one allocation: the result's arrays
    (extras included) share no element, so writing into one cannot change another."""
    (make, y) = {c[0]: c[1:] for c in _cases(5, 12)}[name]
    res = make("numba").filter(y)
    arrays = [res.mean, res.cov, res.pred_mean, res.pred_cov]
    arrays += [v for k, v in res.extras.items() if k not in ("uncensored",)]
    if name == "protocol":  # the extras of the loop's (N, T, 7) array are its columns: disjoint too
        assert res.extras["inverse_mills"].base is not None
    for i, a in enumerate(arrays):
        for b in arrays[i + 1 :]:
            assert not np.shares_memory(a, b)
