"""LQR / LQE / Tobit-LQE gains (spec 001b T7–T9, 001a §4.6), setpoint gains, discretization, errors."""

import numpy as np
import pytest
from scipy.linalg import expm, solve_continuous_are, solve_discrete_are
from scipy.special import ndtr

from tobitkf import KalmanFilter, LinearSystem
from tobitkf._validation import ValidationError
from tobitkf.control.lqg import (
    controlled_noise,
    discretize,
    dlqe,
    dlqr,
    equilibrium,
    is_stable,
    lqe,
    lqr,
    reference_gain,
    tobit_dlqe,
    tobit_lqe,
)
from tobitkf.control.plants import dc_motor_position, dc_motor_speed, scalar_example


def printed(value, digits):
    """Tolerance of a number printed with ``digits`` decimals: half a unit of the last digit."""
    return 0.5 * 10.0 ** (-digits)


# ----------------------------------------------------------------- T7: scalar example of §5.3.3
def test_t7_scalar_gain_and_jacobian_eigenvalues():
    s = scalar_example()
    g = lqe(s.A, s.G, s.C, s.W, s.V)
    # printed L = 0.0246 (4 decimals); closed form of the scalar CARE: L = (A + sqrt(A^2 + W/V)) (R=V)
    closed = -0.8 + np.sqrt(0.64 + 0.01 / 0.25)
    assert g.gain[0, 0] == pytest.approx(closed, rel=1e-10)
    assert g.gain[0, 0] == pytest.approx(0.0246, abs=printed(0.0246, 4))
    assert np.sort(np.r_[s.A.ravel(), g.poles.real]) == pytest.approx([-0.824621, -0.8], abs=1e-6)


def test_t7_recomputed_tobit_gain_at_T0():
    s = scalar_example()
    g = tobit_lqe(s.A, s.G, s.C, s.W, V=[[0.25]], xi_uncensored=0.5)
    # scalar modified CARE: L = P Xi / ups, P solving 2 A P + W - (Xi P)^2/ups = 0
    ups = 0.25 * (1 - 2 / np.pi)
    P = (-0.8 + np.sqrt(0.64 + 0.01 * 0.25 / ups)) * ups / 0.25
    assert g.gain[0, 0] == pytest.approx(P * 0.5 / ups, rel=1e-10)
    assert g.gain[0, 0] == pytest.approx(0.03404, abs=1e-5)
    assert (-0.8 - g.gain[0, 0] * 0.5) == pytest.approx(-0.81702, abs=1e-5)


# ----------------------------------------------------------------- T8: DC-motor speed
def test_t8_dc_motor_speed_gains():
    p = dc_motor_speed()
    g = lqe(p.A, p.G, p.C, p.W, p.V)
    assert g.gain[:, 0] == pytest.approx([10.0329, 0.2257], abs=printed(0, 4))
    assert g.gain[:, 0] == pytest.approx([10.0329, 0.2257], rel=1e-3)
    assert np.sort(g.poles.real)[-1] == pytest.approx(-10.631, abs=1e-3)  # A13: the missing number
    t = tobit_lqe(p.A, p.G, p.C, p.W, V=[[0.05**2]], xi_uncensored=ndtr(0.0))
    assert t.noise[0, 0] == pytest.approx(9.0845e-4, rel=1e-4)
    assert t.gain[:, 0] == pytest.approx([16.452, 0.305], abs=printed(0, 3))
    assert t.gain[0, 0] == pytest.approx(16.452, rel=1e-3)


def test_t8_printed_k_typo_does_not_reproduce():
    """k = 9.37E-3 as printed gives A12 far from the printed 226.6111 (spec A9)."""
    assert dc_motor_speed().A[0, 1] == pytest.approx(226.6111, rel=1e-5)
    assert dc_motor_speed(k=9.37e-3).A[0, 1] != pytest.approx(226.6111, rel=1e-2)


# ----------------------------------------------------------------- T9: DC-motor position
def test_t9_position_uncensored():
    p = dc_motor_position()
    g = lqe(p.A, p.G, p.C, p.W, p.V)
    assert g.gain[:, 0] == pytest.approx([4.0480, 8.1931, -0.0187], abs=printed(0, 4))
    assert g.gain[:2, 0] == pytest.approx([4.0480, 8.1931], rel=1e-3)
    ev = sorted(g.poles, key=lambda z: z.real)
    assert ev[0].real == pytest.approx(-14826388.3725128, rel=1e-9)
    assert ev[1].real == pytest.approx(-2.32303105520711, rel=1e-6)
    assert abs(ev[1].imag) == pytest.approx(2.28421305934995, rel=1e-6)
    assert np.sort(np.linalg.eigvals(p.A).real) == pytest.approx(
        [-14826388.3725128, -0.598070200532675, 0.0], rel=1e-9, abs=1e-9
    )


@pytest.mark.parametrize(
    "T, L_printed, eig_printed",
    [
        (0.0, [7.281, 13.253, -0.0302], [-3.9395245780726]),
        (-0.174533, [73.1575, 0.6447, -0.0015], [-73.1486, -0.6070]),
    ],
)
def test_t9_position_tobit_gains(T, L_printed, eig_printed):
    p = dc_motor_position()
    t = tobit_lqe(p.A, p.G, p.C, p.W, V=[[0.05**2]], xi_uncensored=ndtr(T / 0.05))
    assert t.gain[:2, 0] == pytest.approx(L_printed[:2], rel=1e-3)
    assert t.gain[2, 0] == pytest.approx(L_printed[2], abs=1e-4)
    # the text prints eig(A - L C) with the Tobit L (A15); the effective poles are eig(A - L Xi C)
    ev = np.linalg.eigvals(p.A - t.gain @ p.C)
    slow = np.sort(ev.real[ev.real > -1e6])
    assert sorted(slow)[: len(eig_printed)] == pytest.approx(sorted(eig_printed), rel=1e-3)
    eff = np.sort(t.poles.real[t.poles.real > -1e6])
    assert np.all(eff >= slow.min() - 1e-9)  # the Xi factor moves poles toward eig(A)


def test_t9_minus_20_degrees_not_reproduced_and_why():
    """The printed -20 deg gain [17.7467, 2.3e-10, -5.2e-13] is not the modified-ARE gain (spec note 1):
    it comes back only if the truncated variance is replaced by sigma^2, which T = 0, -10 deg rule out."""
    p = dc_motor_position()
    xi = ndtr(-0.349066 / 0.05)
    t = tobit_lqe(p.A, p.G, p.C, p.W, V=[[0.05**2]], xi_uncensored=xi)
    assert t.gain[0, 0] == pytest.approx(131.013, rel=1e-3)
    wrong = lqe(p.A, p.G, xi * p.C, p.W, p.V)
    assert wrong.gain[0, 0] == pytest.approx(17.7467, rel=1e-3)


# ----------------------------------------------------------------- oracles and closed forms
def test_mee_identity_of_001a_4_6():
    """MEE weights Q=4, R=0.5 are inverse covariances: Kalman-Bucy with W = 1/R, V = 1/Q."""
    g = lqe([[0, 1], [2, -1]], [[0], [1]], [[1, 0]], [[1 / 0.5]], [[1 / 4]])
    assert g.gain[:, 0] == pytest.approx([2.4537, 3.0104], abs=printed(0, 4))


def test_lqr_matches_scipy_care_and_dlqr_closed_form():
    rng = np.random.default_rng(0)
    A = rng.standard_normal((3, 3))
    B = rng.standard_normal((3, 2))
    Q, R = np.eye(3), np.diag([1.0, 2.0])
    P = solve_continuous_are(A, B, Q, R)
    g = lqr(A, B, Q, R)
    assert g.gain == pytest.approx(np.linalg.solve(R, B.T @ P), rel=1e-8)
    assert is_stable(A - B @ g.gain, domain="ct")
    d = dlqr([[1.0]], [[1.0]], [[1.0]], [[1.0]])
    phi = (1 + np.sqrt(5)) / 2
    assert d.cost[0, 0] == pytest.approx(phi, rel=1e-12)
    assert d.gain[0, 0] == pytest.approx(phi / (1 + phi), rel=1e-12)


def test_dlqe_is_the_limit_of_the_core_kalman_filter():
    A = np.array([[1.0, 0.1], [0.0, 0.95]])
    C = np.array([[1.0, 0.0]])
    Q, R = np.diag([1e-3, 1e-2]), np.array([[0.04]])
    g = dlqe(A, None, C, Q, R)
    sys = LinearSystem(A=A, C=C, Q=Q, R=R, x0=[0, 0], P0=np.eye(2))
    out = KalmanFilter(sys).filter(np.zeros((400, 1)))
    assert out.pred_cov[-1] == pytest.approx(g.prior_cov, rel=1e-9)
    assert out.cov[-1] == pytest.approx(g.cov, rel=1e-9)
    assert g.predictor_gain == pytest.approx(A @ g.filter_gain, rel=1e-12)
    assert g.prior_cov == pytest.approx(solve_discrete_are(A.T, C.T, Q, R), rel=1e-9)


@pytest.mark.parametrize(
    "xi, a, lam, ups",
    [
        (0.33, -0.439913, 1.097420, 0.278438),
        (0.5, 0.0, 0.797885, 0.363380),
        (0.8, 0.841621, 0.349952, 0.583006),
        (0.95, 1.644854, 0.108564, 0.809642),
        (0.9999, 3.719016, 3.96e-4, 0.998528),
    ],
)
def test_controlled_noise_table(xi, a, lam, ups):
    lam_hat, upsilon = controlled_noise(xi, 2.0)
    assert lam_hat == pytest.approx(lam, rel=2e-3 if xi > 0.999 else 1e-5)
    assert upsilon / 4.0 == pytest.approx(ups, rel=1e-5)


def test_discretize_matches_van_loan_on_a_mild_system():
    A = np.array([[0.0, 1.0], [-2.0, -0.5]])
    B = np.array([[0.0], [1.0]])
    G = np.array([[0.3], [1.0]])
    W = np.array([[0.7]])
    dt = 0.2
    Ad, Bd, Qd = discretize(A, B, G, W, dt)
    n = 2
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n], M[:n, n:], M[n:, n:] = -A, G @ W @ G.T, A.T
    E = expm(M * dt)
    Qvl = E[n:, n:].T @ E[:n, n:]
    assert Ad == pytest.approx(expm(A * dt), rel=1e-12)
    assert Qd == pytest.approx(Qvl, rel=1e-9, abs=1e-14)
    assert Bd == pytest.approx(np.linalg.solve(A, (expm(A * dt) - np.eye(2)) @ B), rel=1e-10)


def test_reference_gain_and_equilibrium_agree():
    A = np.array([[1.0, 0.1], [0.0, 0.9]])
    B = np.array([[0.0], [0.1]])
    C = np.array([[1.0, 0.0]])
    K = dlqr(A, B, np.diag([10.0, 0.0]), [[1.0]]).gain
    N = reference_gain(A, B, C, K, domain="dt")
    x_ss = np.linalg.solve(np.eye(2) - A + B @ K, B @ N @ [2.0])
    assert C @ x_ss == pytest.approx([2.0], rel=1e-12)
    xe, ue = equilibrium(A, B, C, [[0.0]], [2.0], domain="dt")
    assert xe == pytest.approx(x_ss, rel=1e-10)
    assert (-K @ xe + N @ [2.0]) == pytest.approx(ue, rel=1e-10, abs=1e-12)


# ----------------------------------------------------------------- bad input
def test_not_stabilizable_names_the_riccati_equation():
    with pytest.raises(ValidationError, match=r"LQR DARE .*not stabilizable; uncontrollable unstable mode"):
        dlqr(np.diag([1.2, 0.5]), [[0.0], [1.0]], np.eye(2), [[1.0]])
    with pytest.raises(ValidationError, match=r"LQR CARE \(4.40\) .*not stabilizable"):
        lqr(np.diag([0.3, -1.0]), [[0.0], [1.0]], np.eye(2), [[1.0]])


def test_robot_printed_input_matrix_is_not_stabilizable():
    """Spec §2.3: B_p acting on position only leaves the velocity modes uncontrollable."""
    Ap = np.kron(np.eye(2), [[1.0, 0.1], [0.0, 1.0]])
    Bp = np.array([[1.0, 0], [0, 0], [0, 1.0], [0, 0]])
    with pytest.raises(ValidationError, match="not stabilizable"):
        dlqr(Ap, Bp, np.eye(4), np.eye(2))


def test_not_detectable_and_unexcited_boundary_mode():
    with pytest.raises(ValidationError, match=r"LQE DARE .*not detectable; unobservable unstable mode\(s\) 1.1"):
        dlqe(np.diag([0.5, 1.1]), None, [[1.0, 0.0]], np.eye(2), [[1.0]])
    with pytest.raises(ValidationError, match="not excited by the process noise"):
        dlqe(np.eye(2), [[1.0], [0.0]], np.eye(2), [[1.0]], np.eye(2))
    with pytest.raises(ValidationError, match="Tobit LQE .*not detectable"):
        tobit_dlqe(np.diag([0.5, 1.1]), None, [[1.0, 0.0]], np.eye(2), V=[[0.01]], xi_uncensored=0.5)
    with pytest.raises(ValidationError, match="not seen by the state weight Q"):
        dlqr(np.diag([1.0, 0.5]), np.eye(2), np.diag([0.0, 1.0]), np.eye(2))


def test_singular_and_indefinite_weights():
    with pytest.raises(ValidationError, match="R: the LQR input weight must be positive definite"):
        lqr([[0.0]], [[1.0]], [[1.0]], [[0.0]])
    with pytest.raises(ValidationError, match="Q: the LQR state weight must be positive semi-definite"):
        dlqr([[0.5]], [[1.0]], [[-1.0]], [[1.0]])
    with pytest.raises(ValidationError, match="V: the measurement-noise covariance must be positive definite"):
        lqe([[-1.0]], None, [[1.0]], [[1.0]], [[0.0]])
    with pytest.raises(ValidationError, match="must be symmetric"):
        dlqr(np.eye(2), np.eye(2), [[1.0, 0.5], [0.0, 1.0]], np.eye(2))


@pytest.mark.parametrize("xi", [0.0, 1.0, -0.1, 1.5])
def test_xi_outside_open_unit_interval(xi):
    with pytest.raises(ValidationError, match=r"xi_uncensored: expected probabilities in the open interval \(0, 1\)"):
        tobit_lqe([[-1.0]], None, [[1.0]], [[1.0]], V=[[0.01]], xi_uncensored=xi)


def test_untrackable_reference():
    # zero of the plant at z = 1: C (I - A + B K)^-1 B = 0
    A = np.diag([0.5, 0.8])
    B = np.array([[1.0], [0.0]])
    C = np.array([[0.0, 1.0]])
    K = np.array([[0.1, 0.0]])
    with pytest.raises(ValidationError, match="cannot track the reference.*singular"):
        reference_gain(A, B, C, K, domain="dt")
    with pytest.raises(ValidationError, match="cannot track the reference.*2 tracked outputs but 1 inputs"):
        reference_gain(A, B, np.eye(2), K, domain="dt")
    with pytest.raises(ValidationError, match="r: the plant cannot track the reference"):
        equilibrium(A, B, C, [[0.0]], [1.0], domain="dt")
    with pytest.raises(ValidationError, match="A - B K is not stable"):
        reference_gain(np.diag([1.5, 0.8]), B, C, K, domain="dt")


# ----------------------------------------------------------------- printed digits, Newton refinement
PRINTED_GAINS = [  # (model, T or None for the uncensored gain, printed entries as printed)
    (dc_motor_speed, None, ["10.0329", "0.2257"]),  # (5.61)
    (dc_motor_speed, 0.0, ["16.452", ".305"]),  # §5.4.1, T = 0
    (dc_motor_position, None, ["4.0480", "8.1931", "-0.0187"]),  # (5.67)
    (dc_motor_position, 0.0, ["7.281", "13.253", "-0.0302"]),  # §5.4.2, T = 0
    (dc_motor_position, -0.174533, ["73.1575", "0.6447", "-0.0015"]),  # §5.4.2, T = -10 deg
]


def _half_unit(text):
    decimals = len(text.split(".")[1]) if "." in text else 0
    return 0.5 * 10.0**-decimals


def _gain(model, T):
    p = model()
    if T is None:
        return lqe(p.A, p.G, p.C, p.W, p.V).gain
    return tobit_lqe(p.A, p.G, p.C, p.W, V=p.V, xi_uncensored=ndtr(T / 0.05)).gain


@pytest.mark.parametrize("model, T, printed_L", PRINTED_GAINS, ids=lambda v: getattr(v, "__name__", str(v)))
def test_printed_gains_to_their_printed_digits(model, T, printed_L):
    """Every printed gain of §5.3.3-§5.4 except the -20 deg one rounds to its printed digits (MB-14)."""
    L = _gain(model, T)[:, 0]
    for got, text in zip(L, printed_L):
        assert abs(got - float(text)) <= _half_unit(text), (got, text)


def _decimal_care_gain(A, Q, Ct, V, P0, digits=60, steps=6):
    """Kalman-Bucy gain of A P + P A' + Q - P Ct' V^-1 Ct P = 0 by Newton-Kleinman in decimal arithmetic."""
    from decimal import Decimal, localcontext

    n = A.shape[0]
    with localcontext() as ctx:
        ctx.prec = digits
        D = lambda M: [[Decimal(float(v)) for v in row] for row in np.atleast_2d(M)]  # noqa: E731

        def mul(X, Y):
            return [[sum(X[i][k] * Y[k][j] for k in range(len(Y))) for j in range(len(Y[0]))] for i in range(len(X))]

        tr = lambda X: [list(r) for r in zip(*X)]  # noqa: E731
        add = lambda X, Y, s=1: [[x + s * y for x, y in zip(r, q)] for r, q in zip(X, Y)]  # noqa: E731
        Ad, Qd, Cd, P = D(A), D(Q), D(Ct), D(P0)
        Vinv = Decimal(1) / Decimal(float(V[0, 0]))
        S = [[v * Vinv for v in row] for row in mul(tr(Cd), Cd)]
        for _ in range(steps):
            Ak = add(Ad, mul(P, S), -1)
            rhs = add(Qd, mul(mul(P, S), P))  # Ak X + X Ak' = -(Q + P S P)
            # the n^2 x n^2 linear system (I kron Ak + Ak kron I) vec X = -vec rhs, Gaussian elimination
            N = n * n
            M = [[Decimal(0)] * (N + 1) for _ in range(N)]
            for i in range(n):
                for j in range(n):
                    r = i * n + j
                    for k in range(n):
                        M[r][k * n + j] += Ak[i][k]
                        M[r][i * n + k] += Ak[j][k]
                    M[r][N] = -rhs[i][j]
            for c in range(N):
                piv = max(range(c, N), key=lambda r: abs(M[r][c]))
                M[c], M[piv] = M[piv], M[c]
                for r in range(N):
                    if r != c and M[r][c] != 0:
                        f = M[r][c] / M[c][c]
                        M[r] = [a - f * b for a, b in zip(M[r], M[c])]
            x = [M[r][N] / M[r][r] for r in range(N)]
            P = [[x[i * n + j] for j in range(n)] for i in range(n)]
        L = [[v * Vinv for v in row] for row in mul(P, tr(Cd))]
        return np.array([[float(v) for v in row] for row in L])


def test_newton_refinement_matches_a_60_digit_solution():
    """The -10 deg Tobit gain: python-control's CARE solution reads 73.157737; one Newton-Kleinman step
    gives the 60-digit solution 73.157489 (which rounds to the printed 73.1575)."""
    import control

    p = dc_motor_position()
    g = tobit_lqe(p.A, p.G, p.C, p.W, V=p.V, xi_uncensored=ndtr(-0.174533 / 0.05))
    Q = p.G @ p.W @ p.G.T
    L_raw, P_raw, _ = control.lqe(p.A, p.G, g.measurement, p.W, g.noise)
    L_ref = _decimal_care_gain(p.A, Q, g.measurement, g.noise, P_raw)
    assert g.gain[:, 0] == pytest.approx(L_ref[:, 0], rel=1e-9)
    assert L_ref[0, 0] == pytest.approx(73.157489, abs=1e-6)
    assert abs(np.asarray(L_raw)[0, 0] - 73.1575) > 5e-5  # the unrefined solve misses the print


# ----------------------------------------------------------------- conventions of python-control
def test_results_unpack_like_python_control():
    import control

    p = dc_motor_speed()
    L, P, E = lqe(p.A, p.G, p.C, p.W, p.V)
    Lc, Pc, Ec = control.lqe(p.A, p.G, p.C, p.W, p.V)
    np.testing.assert_allclose(L, Lc, rtol=1e-6)
    np.testing.assert_allclose(P, Pc, rtol=1e-6)
    np.testing.assert_allclose(np.sort_complex(E), np.sort_complex(Ec), rtol=1e-6)
    A, C, Q, R = np.array([[1.0, 0.1], [0.0, 0.95]]), np.array([[1.0, 0.0]]), np.diag([1e-3, 1e-2]), [[0.04]]
    L, P, E = dlqe(A, None, C, Q, R)
    Lc, Pc, Ec = control.dlqe(A, np.eye(2), C, Q, R)
    np.testing.assert_allclose(L, Lc, rtol=1e-9)
    np.testing.assert_allclose(P, Pc, rtol=1e-9)
    K, S, E = dlqr(A, np.array([[0.0], [1.0]]), np.eye(2), [[1.0]])
    Kc, Sc, Ec = control.dlqr(A, np.array([[0.0], [1.0]]), np.eye(2), [[1.0]])
    np.testing.assert_allclose(K, Kc, rtol=1e-9)
    g = dlqe(A, None, C, Q, R)
    assert len(g) == 3 and g[0] is g.predictor_gain and g[1] is g.prior_cov and g[2] is g.poles


def test_filter_and_predictor_gains_have_their_own_names():
    A, C, Q, R = np.array([[1.0, 0.1], [0.0, 0.95]]), np.array([[1.0, 0.0]]), np.diag([1e-3, 1e-2]), [[0.04]]
    g = tobit_dlqe(A, None, C, Q, V=R, xi_uncensored=0.7)
    Ct = 0.7 * C
    Kf = g.prior_cov @ Ct.T @ np.linalg.inv(Ct @ g.prior_cov @ Ct.T + g.noise)
    np.testing.assert_allclose(g.filter_gain, Kf, rtol=1e-12)
    np.testing.assert_allclose(g.predictor_gain, A @ Kf, rtol=1e-12)
    with pytest.raises(AttributeError, match="predictor_gain"):
        g.gain  # noqa: B018 (a DT result names its two gains)
    c = lqe([[-0.8]], None, [[1.0]], [[0.01]], [[0.25]])
    with pytest.raises(AttributeError, match=r"one gain, \.gain"):
        c.filter_gain  # noqa: B018
    with pytest.raises(AttributeError, match="one gain"):
        c.predictor_gain  # noqa: B018


def test_tobit_lqe_takes_a_covariance_by_keyword():
    p = dc_motor_speed()
    with pytest.raises(TypeError, match="V="):
        tobit_lqe(p.A, p.G, p.C, p.W, xi_uncensored=0.5)
    with pytest.raises(ValidationError, match="diagonal"):
        tobit_lqe(np.eye(2) * -1, None, np.eye(2), np.eye(2), V=[[1.0, 0.1], [0.1, 1.0]], xi_uncensored=0.5)


@pytest.mark.parametrize(
    "call",
    [
        lambda: is_stable([[0.5]]),
        lambda: reference_gain([[0.5]], [[1.0]], [[1.0]], [[0.1]]),
        lambda: equilibrium([[0.5]], [[1.0]], [[1.0]], [[0.0]], [1.0]),
    ],
)
def test_an_omitted_time_domain_is_refused(call):
    with pytest.raises(ValidationError, match="domain='dt'"):
        call()
