r"""LQR, Kalman (LQE) and Tobit-LQE gains, setpoint gains: the control toolkit of Miller Ch. 4–6.

Source: Miller (2015) §4.5 (LQR (4.37)–(4.45), minimum-energy estimation and LQG
(4.46)–(4.53)), §6.1 (setpoint control (6.4)–(6.11), the :math:`\bar N` form of (6.22),
(6.45)) and §3.4.2 / §5.3.3 (the "modified ARE" of the steady-state TKF); spec 001a §4,
001b §0.3, §2.1.

Riccati equations (``domain="ct"``: continuous time, Hurwitz; ``"dt"``: discrete, Schur):

.. math::

    \text{LQR (CARE, 4.40)}\quad & A^TP + PA + Q - PBR^{-1}B^TP = 0, \quad K = R^{-1}B^TP \\
    \text{LQR (DARE)}\quad & P = A^TPA - A^TPB(R + B^TPB)^{-1}B^TPA + Q, \quad K = (R + B^TPB)^{-1}B^TPA \\
    \text{LQE (CARE, 4.50–4.53)}\quad & AP + PA^T + GWG^T - PC^TV^{-1}CP = 0, \quad L = PC^TV^{-1} \\
    \text{LQE (DARE)}\quad & \bar P = A\bar PA^T - A\bar PC^T(C\bar PC^T + V)^{-1}C\bar PA^T + GWG^T, \\
                           & K_f = \bar PC^T(C\bar PC^T + V)^{-1} \text{ (filter form)}, \quad L_p = AK_f \text{ (predictor form)}

The *Tobit* LQE (steady-state TKF, (3.57) corrected, spec 001b §0.3) is the LQE for the modified
pair :math:`(A, \Xi C)` with noise :math:`\Upsilon = \mathrm{diag}(\upsilon_i)`,
:math:`\upsilon_i = \sigma_i^2(1 - a_i\hat\lambda_i - \hat\lambda_i^2)`, :math:`a_i = \Phi^{-1}(\Xi_i)`;
every gain printed in Ch. 5 is the CT version of it (Kalman–Bucy, σ's are standard deviations).

Conventions: all weights and noise levels are **covariances** (the dissertation's MEE of
§4.5.3 uses inverse covariances, spec A-4.3; its "σ_q = .1" is a standard deviation). The LQR
and Kalman gains come from python-control (``lqr``, ``dlqr``, ``lqe``, ``dlqe``), after our own
stabilizability / detectability / weight checks, so that a failure names the Riccati equation and
the reason instead of returning NaN.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from .._extras import require
from .._validation import ShapeError, ValidationError, as_float_array, check_option

__all__ = ["RegulatorGain", "EstimatorGain", "lqr", "dlqr", "lqe", "dlqe", "tobit_lqe", "controlled_noise",
           "reference_gain", "equilibrium", "is_stable", "uncontrollable_modes", "unobservable_modes",
           "discretize", "DOMAINS"]

DOMAINS = ("ct", "dt")


class RegulatorGain(NamedTuple):
    """LQR result: ``gain`` K (p, n), Riccati solution ``cost`` P (n, n), closed-loop ``poles`` eig(A − BK)."""

    gain: np.ndarray
    cost: np.ndarray
    poles: np.ndarray


class EstimatorGain(NamedTuple):
    r"""LQE result.

    ``gain``: the observer gain L with closed-loop matrix A − L C̃ (CT Kalman–Bucy gain, or the DT
    *predictor* gain :math:`L_p = AK_f`); ``filter_gain``: the DT filter-form gain :math:`K_f`
    (equal to ``gain`` in CT); ``prior_cov``: the Riccati solution (DT: a-priori :math:`\bar P`);
    ``cov``: DT a-posteriori :math:`(I - K_f\tilde C)\bar P` (CT: the Riccati solution);
    ``poles``: eig(A − L C̃); ``measurement``: the C̃ used (ΞC for the Tobit LQE);
    ``noise``: the measurement covariance used (Υ for the Tobit LQE).
    """

    gain: np.ndarray
    filter_gain: np.ndarray
    prior_cov: np.ndarray
    cov: np.ndarray
    poles: np.ndarray
    measurement: np.ndarray
    noise: np.ndarray


# --------------------------------------------------------------------------- checks
def _mat(value: Any, name: str, shape: tuple[int | None, int | None]) -> np.ndarray:
    arr = as_float_array(value, name)
    if arr.ndim == 0:
        arr = arr.reshape(1, 1)
    if arr.ndim != 2:
        raise ShapeError(f"{name}: expected a 2-D matrix, got shape {arr.shape}")
    for got, want in zip(arr.shape, shape):
        if want is not None and got != want:
            raise ShapeError(f"{name}: expected shape {tuple('?' if s is None else s for s in shape)}, got {arr.shape}")
    return arr


def _weight(value: Any, name: str, size: int, *, definite: bool, what: str) -> np.ndarray:
    W = _mat(value, name, (size, size))
    if not np.allclose(W, W.T, rtol=1e-10, atol=1e-14 * max(1.0, np.abs(W).max())):
        raise ValidationError(f"{name}: the {what} must be symmetric")
    ev = np.linalg.eigvalsh(0.5 * (W + W.T))
    scale = max(1.0, np.abs(ev).max())
    if definite and ev.min() <= 1e-14 * scale:
        raise ValidationError(f"{name}: the {what} must be positive definite (smallest eigenvalue {ev.min():.3g}); "
                              "a singular weight makes the Riccati gain undefined")
    if not definite and ev.min() < -1e-10 * scale:
        raise ValidationError(f"{name}: the {what} must be positive semi-definite (smallest eigenvalue {ev.min():.3g})")
    return 0.5 * (W + W.T)


def _unstable(ev: np.ndarray, domain: str, tol: float = 1e-9) -> np.ndarray:
    return ev.real >= -tol if domain == "ct" else np.abs(ev) >= 1.0 - tol


def _on_boundary(ev: np.ndarray, domain: str, tol: float = 1e-9) -> np.ndarray:
    return np.abs(ev.real) <= tol if domain == "ct" else np.abs(np.abs(ev) - 1.0) <= tol


def uncontrollable_modes(A: Any, B: Any, *, which: str = "unstable", domain: str = "dt",
                         rtol: float = 1e-9) -> np.ndarray:
    r"""Eigenvalues λ of A with rank [A − λI, B] < n (PBH test), restricted by ``which``.

    ``which``: ``"unstable"`` (the modes that make (A, B) not stabilizable), ``"boundary"``
    (on the imaginary axis / unit circle) or ``"all"``.
    """
    check_option(which, "which", ("unstable", "boundary", "all"))
    check_option(domain, "domain", DOMAINS)
    A = np.asarray(A, dtype=float)
    B = np.asarray(B, dtype=float)
    n = A.shape[0]
    ev = np.linalg.eigvals(A)
    if which == "unstable":
        ev = ev[_unstable(ev, domain)]
    elif which == "boundary":
        ev = ev[_on_boundary(ev, domain)]
    out = []
    # balance A (a diagonal similarity, which keeps the PBH ranks) so that badly scaled plants such as
    # the DC motor (entries from 1 to 1.5e7) do not fool the rank test
    from scipy.linalg import matrix_balance

    _, (sc, _) = matrix_balance(A, permute=False, separate=True)
    A = A * (1.0 / sc)[:, None] * sc[None, :]
    B = B / sc[:, None]
    # detectability/stabilizability do not change when the columns of B are rescaled: normalise them,
    # so that a weak but present input (e.g. a Tobit C scaled by a tiny Xi) is not mistaken for none
    norms = np.linalg.norm(B, axis=0)
    B = B[:, norms > 0] / norms[norms > 0]
    scale = max(1.0, np.abs(A).max())
    for lam in ev:
        M = np.hstack([A - lam * np.eye(n), B.astype(complex)])
        s = np.linalg.svd(M, compute_uv=False)
        if s.size < n or s[n - 1] <= rtol * scale:
            out.append(lam)
    return np.array(out)


def unobservable_modes(A: Any, C: Any, *, which: str = "unstable", domain: str = "dt",
                       rtol: float = 1e-9) -> np.ndarray:
    """Eigenvalues λ of A with rank [A − λI; C] < n (PBH test); see :func:`uncontrollable_modes`."""
    return uncontrollable_modes(np.asarray(A, dtype=float).T, np.asarray(C, dtype=float).T, which=which,
                                domain=domain, rtol=rtol)


def _fmt(ev: np.ndarray) -> str:
    return ", ".join(f"{complex(v).real:.4g}" + (f"{complex(v).imag:+.4g}j" if abs(complex(v).imag) > 1e-12 else "")
                     for v in ev)


def _diagnose(A, B, Wh, domain, first, weight, why, *, observe: bool = False) -> str:
    """Reason for a failed Riccati equation: (A, B) not stabilizable, or a boundary mode unseen by the weight."""
    bad = uncontrollable_modes(A, B, domain=domain)
    if bad.size:
        kind = "unobservable" if observe else "uncontrollable"
        return f"{first}; {kind} unstable mode(s) {_fmt(bad)}"
    bad = unobservable_modes(A, Wh, which="boundary", domain=domain)
    if bad.size:
        return (f"mode(s) {_fmt(bad)} on the stability boundary are not "
                + ("excited by the " if observe else "seen by the ") + weight)
    return why


def is_stable(M: Any, *, domain: str = "dt") -> bool:
    """True if ``M`` is Hurwitz (``"ct"``: all Re λ < 0) or Schur (``"dt"``: spectral radius < 1); spec A-4.1."""
    check_option(domain, "domain", DOMAINS)
    ev = np.linalg.eigvals(np.asarray(M, dtype=float))
    return bool(np.all(ev.real < 0)) if domain == "ct" else bool(np.all(np.abs(ev) < 1))


# --------------------------------------------------------------------------- LQR
def _lqr(A, B, Q, R, domain: str) -> RegulatorGain:
    control = require("control", extra="control")

    check_option(domain, "domain", DOMAINS)
    A = _mat(A, "A", (None, None))
    n = A.shape[0]
    if A.shape != (n, n):
        raise ShapeError(f"A: expected a square matrix, got {A.shape}")
    B = _mat(B, "B", (n, None))
    p = B.shape[1]
    Q = _weight(Q, "Q", n, definite=False, what="LQR state weight")
    R = _weight(R, "R", p, definite=True, what="LQR input weight")
    eq = "CARE (4.40)" if domain == "ct" else "DARE"
    w, V = np.linalg.eigh(Q)
    Qh = (V * np.sqrt(np.clip(w, 0, None))).T
    K = S = None
    try:
        K, S, _ = (control.lqr if domain == "ct" else control.dlqr)(A, B, Q, R)
        K, S = np.asarray(K, dtype=float), np.asarray(S, dtype=float)
        ok = bool(np.all(np.isfinite(K)) and np.all(np.isfinite(S)) and is_stable(A - B @ K, domain=domain))
        why = "the solution does not stabilize A - B K"
    except (np.linalg.LinAlgError, ValueError) as exc:
        ok, why = False, str(exc)
    if not ok:
        raise ValidationError(f"LQR {eq} has no stabilizing solution: "
                              + _diagnose(A, B, Qh, domain, "(A, B) is not stabilizable", "state weight Q", why))
    return RegulatorGain(K, 0.5 * (S + S.T), np.linalg.eigvals(A - B @ K))


def lqr(A: Any, B: Any, Q: Any, R: Any) -> RegulatorGain:
    r"""Continuous-time LQR (Miller (4.39)–(4.41)) via ``control.lqr``.

    Parameters
    ----------
    A : (n, n) array_like
    B : (n, p) array_like
    Q : (n, n) array_like
        State weight, symmetric PSD.
    R : (p, p) array_like
        Input weight, symmetric positive definite.

    Returns
    -------
    RegulatorGain
        ``gain`` K (p, n) with u = −Kx, ``cost`` P, ``poles`` eig(A − BK) (Hurwitz).

    Raises
    ------
    ValidationError
        Singular or indefinite weights, (A, B) not stabilizable, a mode on the imaginary axis
        unseen by Q, or a solver failure; the message names the CARE and the reason.
    ShapeError
        Non-conforming matrices.

    Examples
    --------
    Scalar integrator, Q = R = 1: P = 1, K = 1.

    >>> round(float(lqr([[0.0]], [[1.0]], [[1.0]], [[1.0]]).gain[0, 0]), 12)
    1.0
    """
    return _lqr(A, B, Q, R, "ct")


def dlqr(A: Any, B: Any, Q: Any, R: Any) -> RegulatorGain:
    r"""Discrete-time LQR via ``control.dlqr``; the DT counterpart of (4.40)–(4.41).

    Same parameters, returns and errors as :func:`lqr`, with the DARE and Schur poles.

    Examples
    --------
    >>> g = dlqr([[1.0]], [[1.0]], [[1.0]], [[1.0]])   # P = (1 + sqrt 5)/2, K = P/(1+P)
    >>> bool(np.isclose(g.gain[0, 0], 0.6180339887))
    True
    """
    return _lqr(A, B, Q, R, "dt")


# --------------------------------------------------------------------------- LQE
def _lqe(A, G, C, W, V, domain: str, *, tag: str = "LQE") -> EstimatorGain:
    control = require("control", extra="control")

    check_option(domain, "domain", DOMAINS)
    A = _mat(A, "A", (None, None))
    n = A.shape[0]
    if A.shape != (n, n):
        raise ShapeError(f"A: expected a square matrix, got {A.shape}")
    G = np.eye(n) if G is None else _mat(G, "G", (n, None))
    C = _mat(C, "C", (None, n))
    m = C.shape[0]
    W = _weight(W, "W", G.shape[1], definite=False, what="process-noise covariance")
    V = _weight(V, "V", m, definite=True, what="measurement-noise covariance")
    eq = "CARE (Kalman–Bucy)" if domain == "ct" else "DARE"
    Qd = G @ W @ G.T
    w, U = np.linalg.eigh(0.5 * (Qd + Qd.T))
    Gh = U[:, w > 1e-300] * np.sqrt(w[w > 1e-300])
    try:
        if domain == "ct":
            L, P, _ = control.lqe(A, G, C, W, V)
        else:
            L, P, _ = control.dlqe(A, G, C, W, V)     # predictor gain A P C'(C P C' + V)^-1, P a-priori
        L, P = np.asarray(L, dtype=float), np.asarray(P, dtype=float)
        ok = bool(np.all(np.isfinite(L)) and np.all(np.isfinite(P)) and is_stable(A - L @ C, domain=domain))
        why = "the solution does not stabilize A - L C"
    except (np.linalg.LinAlgError, ValueError) as exc:
        ok, why = False, str(exc)
    if not ok:
        raise ValidationError(f"{tag} {eq} has no stabilizing solution: "
                              + _diagnose(A.T, C.T, Gh.T, domain, "(A, C) is not detectable",
                                          "process noise G W G^T", why, observe=True))
    P = 0.5 * (P + P.T)
    if domain == "ct":
        return EstimatorGain(L, L, P, P, np.linalg.eigvals(A - L @ C), C, V)
    S = C @ P @ C.T + V
    Kf = np.linalg.solve(S, C @ P).T
    post = (np.eye(n) - Kf @ C) @ P
    Lp = A @ Kf
    return EstimatorGain(Lp, Kf, P, 0.5 * (post + post.T), np.linalg.eigvals(A - Lp @ C), C, V)


def lqe(A: Any, G: Any, C: Any, W: Any, V: Any) -> EstimatorGain:
    r"""Continuous-time Kalman–Bucy gain (Miller (4.50)–(4.53) with covariances) via ``control.lqe``.

    Parameters
    ----------
    A : (n, n) array_like
    G : (n, q) array_like or None
        Noise input (identity if None).
    C : (m, n) array_like
    W : (q, q) array_like
        Process-noise covariance (PSD).
    V : (m, m) array_like
        Measurement-noise covariance (positive definite).

    Returns
    -------
    EstimatorGain
        ``gain`` L = P C^T V^{-1}; ``poles`` eig(A − LC).

    Raises
    ------
    ValidationError
        (A, C) not detectable, a boundary mode not excited by the noise, singular V; the
        message names the CARE and the reason.

    Notes
    -----
    The MEE form (4.50)–(4.51) with weights Q = V^{-1}, R = W^{-1} gives the same L (spec 001a §4.6).

    Examples
    --------
    The scalar example of §5.3.3 (A = −0.8, σ_q = 0.1, σ = 0.5), printed L = 0.0246:

    >>> round(float(lqe([[-0.8]], None, [[1.0]], [[0.01]], [[0.25]]).gain[0, 0]), 7)
    0.0246211
    """
    return _lqe(A, G, C, W, V, "ct")


def dlqe(A: Any, G: Any, C: Any, W: Any, V: Any) -> EstimatorGain:
    r"""Discrete-time steady-state Kalman gains via ``control.dlqe`` (DARE).

    Returns both the predictor gain ``gain`` :math:`L_p = AK_f` (observer
    :math:`\hat x_{k+1} = A\hat x_k + L_p(y_k - C\hat x_k)`) and the filter gain
    ``filter_gain`` :math:`K_f = \bar PC^T(C\bar PC^T + V)^{-1}` (spec 001a A-3.8). Parameters
    and errors as :func:`lqe`.

    Examples
    --------
    >>> g = dlqe([[1.0]], None, [[1.0]], [[1.0]], [[1.0]])   # Pbar = golden ratio
    >>> bool(np.isclose(g.prior_cov[0, 0], 1.6180339887))
    True
    """
    return _lqe(A, G, C, W, V, "dt")


def controlled_noise(xi_uncensored: Any, sigma: Any) -> tuple[np.ndarray, np.ndarray]:
    r"""Constant Tobit statistics under a controlled limit (3.56): :math:`(\hat\lambda, \upsilon)`.

    :math:`\hat\lambda = \phi(a)/\Xi` (the right-censoring IMR) and
    :math:`\upsilon = \sigma^2(1 - a\hat\lambda - \hat\lambda^2)`, :math:`a = \Phi^{-1}(\Xi)`;
    the two entries of :func:`tobitkf.filters.steady_state.controlled_limit_statistics` a control
    design needs.

    Raises
    ------
    ValidationError
        If some Ξ is outside the open interval (0, 1) or σ <= 0.
    """
    from ..filters.steady_state import controlled_limit_statistics

    _, lam, upsilon, _ = controlled_limit_statistics(xi_uncensored, sigma)
    return np.broadcast_arrays(lam, upsilon)


def tobit_lqe(A: Any, G: Any, C: Any, W: Any, sigma: Any, xi_uncensored: Any, *,
              domain: str = "ct") -> EstimatorGain:
    r"""Steady-state Tobit observer gain: the LQE of :math:`(A, \Xi C)` with noise :math:`\Upsilon` (§0.3 of spec 001b).

    This is the "modified ARE" of Miller §3.4.2 and §5.3.3–§5.4 ((3.57) without its spurious
    second :math:`\bar\Psi`). With a fixed limit T and the state held at :math:`x_{eq}`, use
    :math:`\Xi = \Phi((T - Cx_{eq})/\sigma)` (right censoring), as the text does for the printed
    Tobit gains of §5.3.3 and §5.4.

    Parameters
    ----------
    A, G, C, W : as in :func:`lqe`
    sigma : float or (m,) array_like
        Measurement-noise standard deviations (not variances; spec A-12).
    xi_uncensored : float or (m,) array_like in (0, 1)
        Probability Ξ of an uncensored reading per channel.
    domain : {"ct", "dt"}, default "ct"
        "ct" reproduces the printed gains (Kalman–Bucy, spec A-8); "dt" gives the modified DARE
        (``filter_gain`` K∞, ``prior_cov`` Ψ̄∞, ``cov`` Ψ∞).

    Returns
    -------
    EstimatorGain
        With ``measurement`` = ΞC and ``noise`` = Υ; ``poles`` = eig(A − LΞC) (the effective
        observer poles; the text prints eig(A − LC), spec A-15).

    Raises
    ------
    ValidationError
        Ξ outside (0, 1), (A, C) not detectable, or a failed Riccati equation (named).

    Examples
    --------
    DC-motor speed model, T = 0 (Ξ = 0.5): printed L = [16.452, .305] (spec T8).
    """
    C = _mat(C, "C", (None, None))
    xi_arr = as_float_array(xi_uncensored, "xi_uncensored")
    if xi_arr.ndim > 1 or xi_arr.size not in (1, C.shape[0]):
        raise ShapeError(f"xi_uncensored: expected a scalar or shape ({C.shape[0]},) (one per row of C), "
                         f"got shape {xi_arr.shape}")
    lam, ups = controlled_noise(np.broadcast_to(xi_arr.reshape(-1), (C.shape[0],)),
                                np.broadcast_to(as_float_array(sigma, "sigma"), (C.shape[0],)))
    xi = np.broadcast_to(np.asarray(xi_uncensored, dtype=float), (C.shape[0],))
    return _lqe(A, G, xi[:, None] * C, W, np.diag(ups), domain, tag="Tobit LQE (modified ARE)")


# --------------------------------------------------------------------------- setpoints
def reference_gain(A: Any, B: Any, Cz: Any, K: Any, *, domain: str = "dt") -> np.ndarray:
    r"""Feed-forward :math:`\bar N` for unit DC gain from r to z = C_z x under u = N̄r − Kx (6.22), (6.45).

    CT: :math:`\bar N = -[C_z(A - BK)^{-1}B]^{-1}`; DT: :math:`\bar N = [C_z(I - A + BK)^{-1}B]^{-1}`
    (spec 001b §2.1).

    Raises
    ------
    ValidationError
        If the DC gain matrix is singular or not square (the plant cannot track the reference:
        a transmission zero at s = 0 / z = 1, or more outputs than inputs), or A − BK is not stable.
    """
    check_option(domain, "domain", DOMAINS)
    A, B, Cz, K = (np.atleast_2d(as_float_array(v, name)) for v, name in ((A, "A"), (B, "B"), (Cz, "Cz"), (K, "K")))
    n = A.shape[0]
    p = B.shape[-1]
    for name, M_, shape in (("A", A, (n, n)), ("B", B, (n, p)), ("K", K, (p, n))):
        if M_.shape != shape:
            raise ShapeError(f"{name}: expected shape {shape}, got {M_.shape}")
    if Cz.ndim != 2 or Cz.shape[1] != n:
        raise ShapeError(f"Cz: expected (r, {n}), got {Cz.shape}")
    Acl = A - B @ K
    if not is_stable(Acl, domain=domain):
        raise ValidationError("K: the closed loop A - B K is not stable, the reference gain is undefined")
    M = -Acl if domain == "ct" else np.eye(n) - Acl
    dc = Cz @ np.linalg.solve(M, B)
    if dc.shape[0] != dc.shape[1]:
        raise ValidationError(f"Cz: the plant cannot track the reference: {dc.shape[0]} tracked outputs but "
                              f"{dc.shape[1]} inputs (the DC gain must be square)")
    if np.linalg.cond(dc) > 1e12:
        raise ValidationError("Cz: the plant cannot track the reference: the closed-loop DC gain "
                              f"C_z({'-(A-BK)' if domain == 'ct' else 'I-A+BK'})^-1 B is singular "
                              "(a transmission zero at " + ("s = 0)" if domain == "ct" else "z = 1)"))
    return np.linalg.inv(dc)


def equilibrium(A: Any, B: Any, G: Any, H: Any, r: Any, *, domain: str = "dt") -> tuple[np.ndarray, np.ndarray]:
    r"""Equilibrium :math:`(x_{eq}, u_{eq})` with output :math:`Gx_{eq} + Hu_{eq} = r` (Miller (6.4)–(6.5)).

    Solves :math:`[[A - I\,(\text{DT}) \text{ or } A, B], [G, H]]\,[x_{eq}; u_{eq}] = [0; r]` in the
    least-squares sense and checks that the residual vanishes.

    Raises
    ------
    ValidationError
        If no equilibrium produces ``r`` (the reference cannot be tracked).
    """
    check_option(domain, "domain", DOMAINS)
    A, B, G, H = (np.atleast_2d(np.asarray(v, dtype=float)) for v in (A, B, G, H))
    r = np.atleast_1d(np.asarray(r, dtype=float))
    n, p = B.shape
    top = A - np.eye(n) if domain == "dt" else A
    M = np.block([[top, B], [G, H]])
    rhs = np.concatenate([np.zeros(n), r])
    sol, *_ = np.linalg.lstsq(M, rhs, rcond=None)
    res = np.linalg.norm(M @ sol - rhs)
    if res > 1e-8 * max(1.0, np.linalg.norm(rhs)):
        raise ValidationError(f"r: the plant cannot track the reference {r.tolist()}: no equilibrium of (6.4) gives "
                              f"this output (residual {res:.3g})")
    return sol[:n], sol[n:]


# --------------------------------------------------------------------------- discretization
def discretize(A: Any, B: Any, G: Any, W: Any, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r"""Exact zero-order-hold discretization of :math:`\dot x = Ax + Bu + Gw` with noise covariance.

    .. math::

        A_d = e^{A\Delta}, \quad B_d = \int_0^\Delta e^{A\tau}d\tau\,B, \quad
        Q_d = \int_0^\Delta e^{A\tau}GWG^Te^{A^T\tau}d\tau

    :math:`A_d, B_d` come from the matrix exponential of the augmented matrix; :math:`Q_d` from the
    eigendecomposition :math:`A = V\Lambda V^{-1}`,
    :math:`Q_d = V[M_{ij}(e^{(\lambda_i+\bar\lambda_j)\Delta} - 1)/(\lambda_i + \bar\lambda_j)]V^H` with
    :math:`M = V^{-1}GWG^TV^{-H}` (Van Loan's method overflows for the stiff DC motor, spec 001b §1.6).
    A must be diagonalizable.

    Returns
    -------
    Ad (n, n), Bd (n, p), Qd (n, n)
    """
    from scipy.linalg import expm

    A = _mat(A, "A", (None, None))
    n = A.shape[0]
    B = _mat(B, "B", (n, None))
    G = _mat(G, "G", (n, None))
    W = _weight(W, "W", G.shape[1], definite=False, what="process-noise covariance")
    if not dt > 0:
        raise ValidationError(f"dt: expected a positive time step, got {dt}")
    p = B.shape[1]
    M = np.zeros((n + p, n + p))
    M[:n, :n], M[:n, n:] = A * dt, B * dt
    E = expm(M)
    Ad, Bd = E[:n, :n], E[:n, n:]
    lam, V = np.linalg.eig(A)
    if np.linalg.cond(V) > 1e10:
        raise ValidationError("A: discretize needs a diagonalizable A (the eigenvector matrix is near singular)")
    Vi = np.linalg.inv(V)
    Mq = Vi @ (G @ W @ G.T) @ Vi.conj().T
    s = lam[:, None] + lam.conj()[None, :]
    with np.errstate(over="ignore", invalid="ignore"):
        f = np.where(np.abs(s * dt) < 1e-12, dt, np.expm1(s * dt) / np.where(s == 0, 1, s))
    Qd = (V @ (Mq * f) @ V.conj().T).real
    return Ad, Bd, 0.5 * (Qd + Qd.T)
