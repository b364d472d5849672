"""The compiled loop of the nonlinear filters (numba-compiled f and h) against their numpy path.

Every estimator, sigma-point rule, noise term and option the compiled loop covers is run twice on the same model,
once with ``backend="numpy"`` and once with ``backend="numba"``, and must agree to 1e-10 (the numpy path is the
reference: the same equations, batched, tested against filterpy and brute-force quadrature in the other nonlinear
test modules). Two models keep the number of specialisations (each compiled once per process) small: a
two-state oscillator read through a sine and a cube (central-difference Jacobians, no input), and the same with
an input and analytic Jacobians.
"""

from __future__ import annotations

import numpy as np
import pytest

import tobitkf as tk

numba = pytest.importorskip("numba")

from ._nonlinear_oscillator import F_in, H_osc, f_in, f_osc, h_osc  # noqa: E402

TOL = 1e-10


Q = np.diag([1e-3, 4e-3])
R = np.diag([0.02, 0.05])
X0 = np.array([0.8, 0.0])
P0 = np.diag([0.1, 0.1])
CLIP = tk.Censoring(lower=[-0.5, -np.inf], upper=[0.5, 0.1])


def _system(jit: bool, inputs: bool = False) -> tk.NonlinearSystem:
    if inputs:
        return tk.NonlinearSystem(
            f_in if jit else f_in.py_func, h_osc if jit else h_osc.py_func, Q, R, X0, P0,
            F=F_in if jit else F_in.py_func, H=H_osc if jit else H_osc.py_func, inputs=1,
        )  # fmt: skip
    return tk.NonlinearSystem(f_osc if jit else f_osc.py_func, h_osc if jit else h_osc.py_func, Q, R, X0, P0)


@pytest.fixture(scope="module")
def record():
    """Censored readings of 4 runs x 25 steps with lost readings, and inputs."""
    y = tk.simulate(_system(False), 25, 4, channel=CLIP, seed=3).y
    assert CLIP.at_limit(y).mean() > 0.1  # both limits are met
    y[0, 2, 0] = np.nan
    y[1, 5, :] = np.nan
    y[3, 7, 1] = np.nan
    u = np.random.default_rng(4).normal(size=(4, 25, 1))
    return y, u


ESTIMATORS = {
    "ekf": lambda s, b: tk.ExtendedKalmanFilter(s, backend=b),
    "ekf_joseph": lambda s, b: tk.ExtendedKalmanFilter(s, covariance_update="joseph", backend=b),
    "ukf": lambda s, b: tk.UnscentedKalmanFilter(s, alpha=0.5, beta=2.0, kappa=1.0, backend=b),
    "ukf_cubature": lambda s, b: tk.UnscentedKalmanFilter(s, rule="cubature", backend=b),
    "ukf_gauss_hermite": lambda s, b: tk.UnscentedKalmanFilter(s, rule="gauss_hermite", order=4, backend=b),
    "tekf": lambda s, b: tk.TobitExtendedKalmanFilter(s, CLIP, backend=b),
    "tekf_total": lambda s, b: tk.TobitExtendedKalmanFilter(s, CLIP, noise_term="total_variance", backend=b),
    "tukf_exact": lambda s, b: tk.TobitUnscentedKalmanFilter(s, CLIP, noise_term="exact_pv", backend=b),
    "tukf_cubature": lambda s, b: tk.TobitUnscentedKalmanFilter(s, CLIP, rule="cubature", backend=b),
    "adf": lambda s, b: tk.NonlinearAssumedDensityFilter(s, CLIP, backend=b),
    "adf_iterated": lambda s, b: tk.NonlinearAssumedDensityFilter(s, CLIP, iterations=3, backend=b),
    "adf_gauss_hermite": lambda s, b: tk.NonlinearAssumedDensityFilter(s, CLIP, rule="gauss_hermite", backend=b),
}


def _same(a: tk.FilterResult, b: tk.FilterResult) -> None:
    for key in ("mean", "cov", "pred_mean", "pred_cov"):
        np.testing.assert_allclose(getattr(b, key), getattr(a, key), rtol=0, atol=TOL, err_msg=key)
    assert set(a.extras) == set(b.extras)
    for key in a.extras:
        np.testing.assert_allclose(b.extras[key], a.extras[key], rtol=0, atol=TOL, err_msg=key)


@pytest.mark.parametrize("name", sorted(ESTIMATORS))
def test_compiled_equals_numpy(name, record):
    y, _ = record
    mk = ESTIMATORS[name]
    ref = mk(_system(False), "numpy").filter(y)
    est = mk(_system(True), "numba")
    assert est._use_compiled()
    _same(ref, est.filter(y))


@pytest.mark.parametrize("name", ["ekf", "ukf", "tukf_exact", "adf_iterated"])
def test_compiled_blocks_of_runs(name):
    """More runs than one block of the compiled loop (the last block partial), readings lost on a channel for a
    whole block at one step and for some runs of a block at another: equal to numpy run by run."""
    from tobitkf.filters._compiled_nonlinear import NL_BLOCK

    N = 2 * NL_BLOCK + 3
    y = tk.simulate(_system(False), 6, N, channel=CLIP, seed=7).y
    y[:NL_BLOCK, 1, 0] = np.nan  # the whole first block loses channel 0 at step 2
    y[NL_BLOCK : NL_BLOCK + 5, 2, :] = np.nan  # a few runs of the second block lose both
    y[-1, 3, 1] = np.nan  # the last run of the partial block
    mk = ESTIMATORS[name]
    _same(mk(_system(False), "numpy").filter(y), mk(_system(True), "numba").filter(y))


@pytest.mark.parametrize("name", ["ekf", "ukf", "tukf_exact", "adf"])
def test_compiled_with_inputs_and_jacobians(name, record):
    """An f(x, k, u) and given Jacobians F, H are called from the compiled loop as from numpy."""
    y, u = record
    mk = ESTIMATORS[name]
    _same(mk(_system(False, True), "numpy").filter(y, u=u), mk(_system(True, True), "numba").filter(y, u=u))


def test_compiled_time_varying_noise(record):
    """Q and R given per step reach the loop step by step (the uncensored filters)."""
    y, _ = record
    T = y.shape[1]
    Qs = Q * (1.0 + np.arange(T))[:, None, None] / T
    Rs = R * (2.0 - np.arange(T) / T)[:, None, None]
    sys_np = tk.NonlinearSystem(f_osc.py_func, h_osc.py_func, Qs, Rs, X0, P0)
    sys_nb = tk.NonlinearSystem(f_osc, h_osc, Qs, Rs, X0, P0)
    _same(tk.UnscentedKalmanFilter(sys_np).filter(y), tk.UnscentedKalmanFilter(sys_nb, backend="numba").filter(y))


def test_compiled_quantizer_adf():
    """The assumed-density filter of a quantized sensor: the interval moments of the compiled block."""
    quant = tk.Quantizer(0.25)
    y = tk.simulate(_system(False), 20, 3, channel=quant, seed=5).y
    y[1, 4, 0] = np.nan
    ref = tk.NonlinearAssumedDensityFilter(_system(False), quant).filter(y)
    _same(ref, tk.NonlinearAssumedDensityFilter(_system(True), quant, backend="numba").filter(y))


@pytest.mark.parametrize("name", ["ekf", "tukf_exact", "adf_iterated"])
def test_compiled_step_equals_filter(name, record):
    """The compiled online step, run by run and batched, is the compiled filter's row (and the numpy step's)."""
    y, _ = record
    est = ESTIMATORS[name](_system(True), "numba")
    res = est.filter(y)
    state = est.init((y.shape[0],))
    for i in range(y.shape[1]):
        state = est.step(state, y[:, i])
        np.testing.assert_allclose(state.x, res.mean[:, i], rtol=0, atol=1e-12)
        np.testing.assert_allclose(state.P, res.cov[:, i], rtol=0, atol=1e-12)
        for key, val in res.extras.items():
            np.testing.assert_allclose(state.extras[key], val[:, i], rtol=0, atol=1e-12)
    one = est.init()
    for i in range(y.shape[1]):
        one = est.step(one, y[2, i])
    np.testing.assert_allclose(one.x[0], res.mean[2, -1], rtol=0, atol=1e-12)


def test_compiled_continues_from_state(record):
    y, _ = record
    est = tk.NonlinearAssumedDensityFilter(_system(True), CLIP, backend="numba")
    whole = est.filter(y)
    first = est.filter(y[:, :10])
    rest = est.filter(y[:, 10:], state=first.final)
    np.testing.assert_allclose(rest.mean, whole.mean[:, 10:], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(rest.times, whole.times[10:])


def test_backend_choice(record):
    y, _ = record
    # auto: compiled only for compiled f and h
    assert tk.UnscentedKalmanFilter(_system(True))._use_compiled()
    assert not tk.UnscentedKalmanFilter(_system(False))._use_compiled()
    assert not tk.UnscentedKalmanFilter(_system(True), backend="numpy")._use_compiled()
    # the square-root form runs its own compiled loop under auto (tests/filters/test_nonlinear_compiled_sqrt.py)
    sq = tk.UnscentedKalmanFilter(_system(True), covariance_update="square_root")
    assert sq._use_compiled()
    ref = tk.UnscentedKalmanFilter(_system(False), covariance_update="square_root").filter(y)
    np.testing.assert_allclose(sq.filter(y).mean, ref.mean, rtol=0, atol=TOL)
    # a channel the loop does not cover: the numpy path
    quant = tk.Quantizer(0.25)
    assert not tk.TobitUnscentedKalmanFilter(_system(True), quant)._use_compiled()


def test_numba_backend_refuses_python_functions(record):
    y, _ = record
    est = tk.NonlinearAssumedDensityFilter(_system(False), CLIP, backend="numba")
    with pytest.raises(tk.ValidationError, match=r"backend: 'numba' runs f and h compiled, but f, h not compiled"):
        est.filter(y)
    half = tk.NonlinearSystem(f_osc, h_osc.py_func, Q, R, X0, P0)
    with pytest.raises(tk.ValidationError, match=r"but h not compiled with numba\.njit"):
        tk.ExtendedKalmanFilter(half, backend="numba").init()
        tk.ExtendedKalmanFilter(half, backend="numba").filter(y)
    assert tk.UnscentedKalmanFilter(_system(True), covariance_update="square_root", backend="numba")._use_compiled()
    with pytest.raises(tk.ValidationError, match="backend"):
        tk.UnscentedKalmanFilter(_system(True), backend="gpu")


@pytest.mark.parametrize("name", ["tekf", "ekf_joseph", "adf_gauss_hermite"])
def test_compiled_blocks_of_runs_other_updates(name):
    """The Tobit and Joseph updates and a rule with points off the axes (of the nine unit points of the
    Gauss–Hermite rule of order 3 in 2-D, four have two nonzero coordinates, four one, the centre none: every
    branch of the points' shortcut), over a full and a partial block with readings lost in both: equal to numpy
    run by run."""
    from tobitkf.filters._compiled_nonlinear import NL_BLOCK

    N = NL_BLOCK + 5
    y = tk.simulate(_system(False), 5, N, channel=CLIP, seed=8).y
    y[: NL_BLOCK // 2, 1, 1] = np.nan
    y[NL_BLOCK:, 3, 0] = np.nan  # every run of the partial block loses channel 0 at step 4
    mk = ESTIMATORS[name]
    _same(mk(_system(False), "numpy").filter(y), mk(_system(True), "numba").filter(y))


def test_point_columns():
    """The shortcut of the sigma points: the centre, the axis points of the unscented rule, a point off the axes."""
    from tobitkf.filters._compiled_nonlinear import point_columns

    xi = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, -2.0], [1.0, 1.0, 0.0]])
    np.testing.assert_array_equal(point_columns(xi), [-1, 0, 2, -2])
    assert point_columns(np.empty((0, 3))).shape == (0,)


def test_compiled_singular_prior():
    """A prior covariance that is singular in every run: the eigen root replaces the Cholesky factor at the
    first step (the numpy path's rule when its Cholesky fails), the shortcut of the points applied to it."""
    y = tk.simulate(_system(False), 8, 3, channel=CLIP, seed=9).y
    P0s = np.diag([0.1, 0.0])
    ref = tk.NonlinearAssumedDensityFilter(tk.NonlinearSystem(f_osc.py_func, h_osc.py_func, Q, R, X0, P0s), CLIP)
    est = tk.NonlinearAssumedDensityFilter(tk.NonlinearSystem(f_osc, h_osc, Q, R, X0, P0s), CLIP, backend="numba")
    _same(ref.filter(y), est.filter(y))


@numba.njit
def f_big(x, k):
    out = np.empty(x.shape)
    n = x.shape[-1]
    for i in range(n):
        out[..., i] = 0.95 * x[..., i] + 0.05 * np.sin(x[..., (i + 1) % n])
    return out


@numba.njit
def h_big(x, k):
    out = np.empty(x.shape[:-1] + (2,))
    out[..., 0] = np.sin(x[..., 0])
    out[..., 1] = x[..., 3] + 0.1 * x[..., 6] ** 2
    return out


def test_compiled_state_beyond_the_unrolled_sizes():
    """A state larger than the block steps unroll (n = 7): they read n from their arrays; equal to numpy."""
    from tobitkf.filters._compiled_nonlinear import NL_MAX_UNROLL

    n = 7
    assert n > NL_MAX_UNROLL
    Qb, P0b, x0b = 1e-3 * np.eye(n), 0.05 * np.eye(n), np.linspace(-0.5, 0.5, n)
    clip = tk.Censoring(lower=[-0.4, -np.inf], upper=[0.4, 0.3])
    sys_np = tk.NonlinearSystem(f_big.py_func, h_big.py_func, Qb, R, x0b, P0b)
    y = tk.simulate(sys_np, 6, 3, channel=clip, seed=10).y
    y[1, 2, 0] = np.nan
    ref = tk.NonlinearAssumedDensityFilter(sys_np, clip).filter(y)
    est = tk.NonlinearAssumedDensityFilter(tk.NonlinearSystem(f_big, h_big, Qb, R, x0b, P0b), clip, backend="numba")
    _same(ref, est.filter(y))
