"""Tobit observer Jacobians, the printed (5.56) diagnostic, the certificate, mean-field error (T6, T7, T10, T11, T20)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tobitkf._validation import ValidationError
from tobitkf.control.stability import (
    COUNTEREXAMPLE,
    certify_tkf_stability,
    closed_loop_jacobian,
    dissertation_jacobian_5_56,
    fixed_gain_tobit_observer,
    mean_field_error,
    mean_observer_map,
    tobit_error_jacobian,
    tobit_jacobian,
)

L_SCALAR = 0.024621130625  # CT Kalman-Bucy gain of §5.3.3 (test_lqg T7)


def fd_jacobian(f, z, h=1e-6):
    z = np.asarray(z, dtype=float)
    cols = []
    for i in range(z.size):
        dz = np.zeros_like(z)
        dz[i] = h
        cols.append((f(z + dz) - f(z - dz)) / (2 * h))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize(
    "lower, upper",
    [
        ([-np.inf, -np.inf], [0.2, 0.5]),  # right
        ([-0.3, 0.1], [np.inf, np.inf]),  # left
        ([-0.4, -1.0], [0.5, 0.3]),  # saturation
        ([-np.inf, 0.0], [0.0, np.inf]),  # multi-region example 1 (one right, one left)
    ],
)
def test_t6_jacobian_equals_finite_differences(lower, upper):
    rng = np.random.default_rng(1)
    A = rng.standard_normal((3, 3)) * 0.4
    L = rng.standard_normal((3, 2))
    C = rng.standard_normal((2, 3))
    sigma = np.array([0.3, 0.6])
    for _ in range(5):
        x, xh = rng.standard_normal(3) * 0.5, rng.standard_normal(3) * 0.5

        def f(z):
            a, b = mean_observer_map(A, L, C, z[:3], z[3:], sigma, lower, upper)
            return np.concatenate([a, b])

        J = tobit_jacobian(A, L, C, x, xh, sigma, lower, upper)
        assert J == pytest.approx(fd_jacobian(f, np.concatenate([x, xh])), rel=1e-5, abs=1e-8)
        # eig(J) = eig(A) U eig(A - L Gamma(xh) C)
        ev = np.sort_complex(np.linalg.eigvals(J))
        ref = np.sort_complex(np.concatenate([np.linalg.eigvals(A), np.linalg.eigvals(J[3:, 3:])]))
        assert ev == pytest.approx(ref, abs=1e-9)

        def g(z):  # error coordinates (x, e)
            a, b = mean_observer_map(A, L, C, z[:3], z[:3] - z[3:], sigma, lower, upper)
            return np.concatenate([a, a - b])

        e = x - xh
        Je = tobit_error_jacobian(A, L, C, x, e, sigma, lower, upper)
        assert Je == pytest.approx(fd_jacobian(g, np.concatenate([x, e])), rel=1e-5, abs=1e-8)
    # at e = 0 the error Jacobian has the eigenvalues of J (Fig 5.4 = Fig 5.5)
    Je0 = tobit_error_jacobian(A, L, C, x, np.zeros(3), sigma, lower, upper)
    J0 = tobit_jacobian(A, L, C, x, x, sigma, lower, upper)
    assert np.sort_complex(np.linalg.eigvals(Je0)) == pytest.approx(np.sort_complex(np.linalg.eigvals(J0)), abs=1e-9)


def test_t7_correct_j22_is_monotone_between_uncensored_and_open_loop():
    T = np.linspace(-3, 3, 121)
    j22 = np.array([tobit_jacobian([[-0.8]], [[L_SCALAR]], [[1.0]], [0.0], [0.0], 0.5, -np.inf, t)[1, 1] for t in T])
    assert np.all(np.diff(j22) < 0)
    assert np.all((j22 >= -0.8 - L_SCALAR - 1e-12) & (j22 <= -0.8))
    # the spec's table with the rounded L = 0.0246: T = -1, 0, 0.5, 1
    tab = [tobit_jacobian([[-0.8]], [[0.0246]], [[1.0]], [0.0], [0.0], 0.5, -np.inf, t)[1, 1] for t in (-1, 0, 0.5, 1)]
    assert tab == pytest.approx([-0.80056, -0.81230, -0.82070, -0.82404], abs=1e-5)


def test_t20_printed_5_56_is_non_monotone_and_differs():
    """The printed Jacobian reproduces the spec's 'local disturbance' table; kept as a documented wrong formula."""
    vals = [
        dissertation_jacobian_5_56([[-0.8]], [[0.0246]], [[1.0]], [0.0], [0.0], 0.5, t)[1, 1]
        for t in (-0.25, 0.0, 0.25, 0.5)
    ]
    assert vals == pytest.approx([-0.81409, -0.81230, -0.81051, -0.81177], abs=1e-5)
    assert not (np.all(np.diff(vals) < 0) or np.all(np.diff(vals) > 0))
    correct = tobit_jacobian([[-0.8]], [[0.0246]], [[1.0]], [0.0], [0.0], 0.5, -np.inf, 0.25)[1, 1]
    assert abs(vals[2] - correct) > 5e-3

    # and it differs from finite differences of the mean map away from T = Cx
    def f(z):
        return mean_observer_map([[-0.8]], [[0.0246]], [[1.0]], [0.0], z, 0.5, -np.inf, 0.25)[1]

    assert fd_jacobian(f, [0.0])[0, 0] == pytest.approx(correct, abs=1e-9)
    with pytest.raises(ValidationError, match="m = 1"):
        dissertation_jacobian_5_56(np.eye(2), np.eye(2), np.eye(2), [0, 0], [0, 0], 0.5, 0.0)


def test_t10_counterexample_is_not_certified():
    c = COUNTEREXAMPLE
    assert np.max(np.abs(np.linalg.eigvals(c["A"]))) == pytest.approx(0.875, abs=1e-3)
    assert np.max(np.abs(np.linalg.eigvals(c["A"] - c["L"] @ c["C"]))) == pytest.approx(0.916, abs=1e-3)
    assert np.max(np.abs(np.linalg.eigvals(c["A"] - 0.25 * c["L"] @ c["C"]))) == pytest.approx(1.084, abs=1e-3)
    r = certify_tkf_stability(c["A"], c["L"], c["C"], domain="dt")
    assert not r.certified and "not certified" in r.message
    assert np.all(r.vertex_radius < 1)  # the vertex test alone would pass: (5.23) is false
    assert r.worst_sampled == pytest.approx(1.0895, abs=1e-3) and r.worst_s == pytest.approx(0.33, abs=0.01)
    lmi_only = certify_tkf_stability(c["A"], c["L"], c["C"], domain="dt", grid=0)
    assert not lmi_only.certified and "no common quadratic Lyapunov" in lmi_only.message


@settings(max_examples=15, deadline=None)
@given(a=st.floats(-0.95, 0.95), lc=st.floats(-0.95, 0.95))
def test_t10_scalar_cases_certify(a, lc):
    """Scalar: |A| < 1 and |A - LC| < 1 certify (the polytope is an interval inside (-1, 1))."""
    r = certify_tkf_stability([[a]], [[a - lc]], [[1.0]], domain="dt")
    assert r.certified
    P = r.P
    for s in (0.0, 0.3, 1.0):
        M = a - s * (a - lc)
        assert M * P[0, 0] * M - P[0, 0] < 0


def test_certificate_ct_and_two_channels():
    A = np.array([[-1.0, 2.0], [0.0, -0.5]])
    L = np.array([[1.0, 0.0], [0.0, 0.5]])
    r = certify_tkf_stability(A, L, np.eye(2), domain="ct")
    assert r.certified and r.vertex_radius.shape == (4,)
    with pytest.raises(ValidationError, match="expected"):
        certify_tkf_stability(A, L, np.eye(3), domain="dt")


@pytest.mark.parametrize("T_sigma", [-3.0, 0.0, 3.0])
def test_t11_mean_field_error_converges_for_certified_gain(T_sigma):
    A = np.array([[0.9, 0.2], [0.0, 0.7]])
    L = np.array([[0.5], [0.1]])
    C = np.array([[1.0, 0.0]])
    assert certify_tkf_stability(A, L, C, domain="dt").certified
    sigma = 0.2
    rng = np.random.default_rng(3)
    e0 = rng.uniform(-10, 10, size=(20, 2)) * sigma
    x0 = rng.uniform(-1, 1, size=(20, 2))
    _, e = mean_field_error(A, L, C, x0, e0, 400, sigma, -np.inf, T_sigma * sigma)
    assert np.abs(e[:, -1]).max() < 1e-6


def test_t11_scalar_error_between_lqg_and_open_loop_bounds():
    A, L = 0.9, 0.5
    k = np.arange(61)
    for e0 in (2.0, -2.0, 0.7):
        _, e = mean_field_error([[A]], [[L]], [[1.0]], [0.3], [e0], 60, 0.1, -np.inf, 0.0)
        lower = np.abs((A - L) ** k * e0)
        upper = np.abs(A**k * e0)
        err = np.abs(e[:, 0])
        assert np.all(err >= lower - 1e-12) and np.all(err <= upper + 1e-12)


def test_counterexample_mean_field_does_not_converge_at_25_percent():
    """Spec note 8: fixed T at 25 % uncensored, A Schur, but the mean error never converges."""
    c = COUNTEREXAMPLE
    sigma = 1.0
    T = sigma * -0.6744897501960817  # Phi(T/sigma) = 0.25 at x = 0
    _, e = mean_field_error(c["A"], c["L"], c["C"], np.zeros(3), [1e-6, 0, 0], 3000, sigma, -np.inf, T)
    assert np.abs(e[-200:]).max() > 1.0


def test_closed_loop_jacobian_separation():
    A = np.array([[1.0, 0.1], [0.0, 1.0]])
    B = np.array([[0.0], [0.1]])
    K = np.array([[3.0, 2.5]])
    L = np.array([[0.5], [0.8]])
    C = np.array([[1.0, 0.0]])
    J = closed_loop_jacobian(A, B, K, L, C, [0.4])
    ref = np.concatenate([np.linalg.eigvals(A - B @ K), np.linalg.eigvals(A - 0.4 * L @ C)])
    assert np.sort_complex(np.linalg.eigvals(J)) == pytest.approx(np.sort_complex(ref), abs=1e-12)


def test_fixed_gain_observer_infinite_limit_is_luenberger():
    rng = np.random.default_rng(0)
    y = rng.standard_normal((3, 50, 1))
    a = fixed_gain_tobit_observer([[0.9]], [[0.3]], [[1.0]], y, 0.2)
    b = fixed_gain_tobit_observer([[0.9]], [[0.3]], [[1.0]], y, 0.2, gain_form="linear")
    assert a == pytest.approx(b, abs=1e-13)
    with pytest.raises(ValidationError, match="gain_form"):
        fixed_gain_tobit_observer([[0.9]], [[0.3]], [[1.0]], y, 0.2, gain_form="x")


def test_fixed_gain_filter_form_is_predictor_form_times_A():
    rng = np.random.default_rng(2)
    A, Kf, C = np.array([[0.9, 0.1], [0.0, 0.8]]), np.array([[0.4], [0.1]]), np.array([[1.0, 0.0]])
    y = np.minimum(rng.standard_normal((2, 30, 1)), 0.2)
    filt = fixed_gain_tobit_observer(A, Kf, C, y, 0.3, -np.inf, 0.2, form="filter")
    pred = fixed_gain_tobit_observer(A, A @ Kf, C, y, 0.3, -np.inf, 0.2, xhat0=np.zeros(2) @ A.T, form="predictor")
    # predictor x_{k+1|k} = A x_{k|k}, with the filter's prior x_{1|0} = A x_0 = 0 as the predictor's start
    assert pred[:, :] == pytest.approx(filt @ A.T, abs=1e-12)


def test_two_output_counterexample_fails_at_n_2():
    """(5.23) already fails for n = 2 with two outputs (MB-02): A and A - LC are Schur, the vertex with
    the second output censored is not, so no certificate exists; and one output with n = 2 cannot fail."""
    from tobitkf.control.stability import COUNTEREXAMPLE_TWO_OUTPUTS

    c = COUNTEREXAMPLE_TWO_OUTPUTS
    A, L, C = c["A"], c["L"], c["C"]
    rho = lambda M: max(abs(np.linalg.eigvals(M)))  # noqa: E731
    assert rho(A) == pytest.approx(0.9) and rho(A - L @ C) < 0.6
    assert rho(A - L @ np.diag([1.0, 0.0]) @ C) == pytest.approx(1.6)
    r = certify_tkf_stability(A, L, C, domain="dt")
    assert not r.certified and "vertex" in r.message
    rng = np.random.default_rng(3)
    checked = 0
    while checked < 200:  # m = 1, n = 2: the segment A - sLC stays Schur
        A1, L1, C1 = rng.normal(size=(2, 2)), rng.normal(size=(2, 1)), rng.normal(size=(1, 2))
        if rho(A1) < 1 and rho(A1 - L1 @ C1) < 1:
            checked += 1
            assert max(rho(A1 - s * L1 @ C1) for s in np.linspace(0, 1, 51)) < 1


def test_certificate_domain_must_be_given():
    c = COUNTEREXAMPLE
    with pytest.raises(ValidationError, match="certify_tkf_stability needs domain"):
        certify_tkf_stability(c["A"], c["L"], c["C"])
