"""The compiled square-root form of the nonlinear filters (numba f and h, ``covariance_update="square_root"``).

It must equal the numpy square-root form (the reference, itself tested equal to the covariance form) and the
compiled covariance form to 1e-10, and stay positive semi-definite where the covariance form's subtraction loses
definiteness (two very precise readings of a correlated prior of variance 1e6).
"""

from __future__ import annotations

import numpy as np
import pytest

import tobitkf as tk

numba = pytest.importorskip("numba")

from ._nonlinear_oscillator import f_osc, h_osc  # noqa: E402

TOL = 1e-10


Q = np.diag([1e-3, 4e-3])
R = np.diag([0.05, 0.1])
SYSTEM = tk.NonlinearSystem(f_osc, h_osc, Q, R, [0.8, 0.1], np.diag([0.2, 0.3]))
CENS = tk.Censoring(lower=[-0.5, -np.inf], upper=[0.5, 0.9])


@pytest.mark.parametrize(
    "make",
    [
        lambda c, b: tk.ExtendedKalmanFilter(SYSTEM, covariance_update=c, backend=b),
        lambda c, b: tk.UnscentedKalmanFilter(SYSTEM, covariance_update=c, backend=b),
        lambda c, b: tk.UnscentedKalmanFilter(SYSTEM, alpha=0.5, covariance_update=c, backend=b),  # negative weight
        lambda c, b: tk.TobitExtendedKalmanFilter(SYSTEM, CENS, covariance_update=c, backend=b),
        lambda c, b: tk.TobitUnscentedKalmanFilter(SYSTEM, CENS, rule="cubature", covariance_update=c, backend=b),
        lambda c, b: tk.NonlinearAssumedDensityFilter(SYSTEM, CENS, iterations=2, covariance_update=c, backend=b),
    ],
    ids=["ekf", "ukf", "ukf-alpha", "tobit-ekf", "tobit-ukf", "adf"],
)
def test_the_compiled_square_root_form_equals_the_numpy_one_and_the_covariance_form(make):
    y = tk.simulate(SYSTEM, 25, 70, channel=CENS, seed=3).y  # 70 runs: two blocks
    y[1, 3, 0] = y[66, 7, 1] = np.nan
    ref = make("square_root", "numpy").filter(y)
    fast_est = make("square_root", "numba")
    assert fast_est._use_compiled()
    fast = fast_est.filter(y)
    cov = make("standard", "numba").filter(y)
    # numba's sin and numpy's may differ in the last bit; a central-difference Jacobian (step ~6e-6) turns that
    # into ~4e-11 of H, which a run's steps can grow a few times: 1e-9 for the extended filters against numpy
    tol = 1e-9 if fast_est.rule is None else TOL
    for key in ("mean", "cov", "pred_mean", "pred_cov"):
        np.testing.assert_allclose(getattr(fast, key), getattr(ref, key), rtol=0, atol=tol, err_msg=key)
        np.testing.assert_allclose(getattr(fast, key), getattr(cov, key), rtol=0, atol=TOL, err_msg=key)
    for key in ref.extras:
        np.testing.assert_allclose(fast.extras[key], ref.extras[key], rtol=0, atol=tol, err_msg=key)
    # the final state carries the factor: continuing from it is the filter of the whole record
    half = fast_est.filter(y[:, :12])
    rest = fast_est.filter(y[:, 12:], state=half.final)
    np.testing.assert_allclose(rest.mean, fast.mean[:, 12:], rtol=0, atol=TOL)


@numba.njit
def f_id(x, k):
    return x.copy()


@numba.njit
def h_ill(x, k):
    out = np.empty(x.shape)
    out[..., 0] = x[..., 0] + 1e-6 * x[..., 0] ** 2
    out[..., 1] = x[..., 1] + x[..., 0]
    return out


def test_the_compiled_square_root_form_stays_psd_where_the_covariance_form_does_not():
    # two readings of variance 1e-12 of a prior of variance 1e6 (correlation 0.99): the covariance form subtracts
    # numbers of order 1e6 to leave ones of order 1, and its rounding makes the numpy path's posterior indefinite
    # (the compiled covariance form, summing in another order, happens to stay PSD here); the factor of the array
    # form is PSD by construction, on both paths and the same on both
    P0 = 1e6 * np.array([[1.0, 0.99], [0.99, 1.0]])
    system = tk.NonlinearSystem(f_id, h_ill, np.zeros((2, 2)), 1e-12 * np.eye(2), [1.0, 2.0], P0)
    y = np.array([[1.5, 3.5]])
    eps = np.finfo(float).eps
    for make in (
        lambda c, b: tk.UnscentedKalmanFilter(system, covariance_update=c, backend=b),
        lambda c, b: tk.NonlinearAssumedDensityFilter(
            system, tk.Censoring(upper=[1e3, 1e3]), covariance_update=c, backend=b
        ),
    ):
        with np.errstate(all="ignore"), _quiet():
            std = make("standard", "numpy").filter(y).cov[0]
        sq_est = make("square_root", "numba")
        assert sq_est._use_compiled()
        sq = sq_est.filter(y).cov[0]
        ref = make("square_root", "numpy").filter(y).cov[0]
        scale = np.abs(sq).max()
        assert np.linalg.eigvalsh(sq).min() >= -4 * eps * scale  # PSD to the rounding of its eigenvalues
        np.testing.assert_allclose(sq, ref, rtol=1e-6, atol=1e-6 * scale)
        assert np.linalg.eigvalsh(std).min() < -1e3 * eps * scale  # indefinite far beyond rounding


class _quiet:
    def __enter__(self):
        import warnings

        self._ctx = warnings.catch_warnings()
        self._ctx.__enter__()
        warnings.simplefilter("ignore")

    def __exit__(self, *exc):
        return self._ctx.__exit__(*exc)


@pytest.mark.parametrize("n", [3, 8])  # a state size unrolled in the block steps, and one that is not
@pytest.mark.parametrize("rule", ["unscented", "gauss_hermite"])  # points on the axes, and points off them
def test_the_points_of_a_carried_factor_are_those_of_its_covariance(n, rule):
    """The block step that places the sigma points serves both forms: from the factor S the square-root form
    carries, and from P = SS^T (its Cholesky factor, S again when S is that factor) in the standard form: the
    same points, to the bit, and both x + S xi (numpy) to rounding; a singular P falls back to its eigen root."""
    from tobitkf._compiled_linalg import cholesky_lower
    from tobitkf.filters._compiled_nonlinear import SIZES, _block_points, point_columns

    rng = np.random.default_rng(n)
    nb = 5
    xs = rng.normal(size=(nb, n))
    G = rng.normal(size=(nb, n, n))
    Ps = G @ G.transpose(0, 2, 1) + 0.1 * np.eye(n)
    Ps[-1] = np.outer(G[-1, 0], G[-1, 0])  # rank one: no Cholesky factor
    Ss = np.zeros((nb - 1, n, n))
    assert all(cholesky_lower(P, S) for P, S in zip(Ps[:-1], Ss))  # the factor the standard form takes
    np.testing.assert_allclose(Ss, np.linalg.cholesky(Ps[:-1]), rtol=0, atol=1e-12 * np.abs(Ss).max())
    xi, _, wc = tk.SigmaPoints(rule, order=2).unit(n)
    xi = np.array(xi)  # writable, as the loop is handed it (the rule's own array is read-only: a second version)
    L = xi.shape[0]
    size, xcol = SIZES.get(n, ()), point_columns(xi)
    act = np.ones(nb, dtype=bool)
    from_cov, from_factor = np.empty((nb * L, n)), np.empty(((nb - 1) * L, n))
    assert _block_points(size, xs, Ps, xi, xcol, np.empty((n, n)), from_cov, nb, act, False) == nb
    assert _block_points(size, xs, Ss, xi, xcol, np.empty((0, 0)), from_factor, nb - 1, act, True) == nb - 1
    np.testing.assert_array_equal(from_cov[: (nb - 1) * L], from_factor)
    expected = (xs[:-1, None, :] + np.einsum("bij,lj->bli", Ss, xi)).reshape(-1, n)
    np.testing.assert_allclose(from_factor, expected, rtol=0, atol=1e-13)
    pts = from_cov[(nb - 1) * L :] - xs[-1]  # an eigen root R (RR^T = P): the rule's spread of the points is P
    np.testing.assert_allclose(np.einsum("l,li,lj->ij", wc, pts, pts), Ps[-1], rtol=0, atol=1e-12 * Ps[-1].max())
