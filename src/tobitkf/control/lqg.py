r"""LQR, Kalman (LQE) and Tobit-LQE gains, setpoint gains: the control toolkit of Miller Ch. 4–6.

Source: Miller (2015) §4.5 (LQR (4.37)–(4.45), minimum-energy estimation and LQG
(4.46)–(4.53)), §6.1 (setpoint control (6.4)–(6.11), the :math:`\bar N` form of (6.22),
(6.45)) and §3.4.2 / §5.3.3 (the "modified ARE" of the steady-state TKF, (3.57)). Our
deviations: docs/sources/miller2015-ch1-4.md (MA-15, MA-21, MA-23) and
docs/sources/miller2015-ch5-7.md (MB-08, MB-14, MB-15).

Riccati equations. The name says the time domain, as in python-control: ``lqr``/``lqe``/
``tobit_lqe`` are continuous-time (CARE, Hurwitz), ``dlqr``/``dlqe``/``tobit_dlqe`` discrete-time
(DARE, Schur):

.. math::

    \text{LQR (CARE, 4.40)}\quad & A^TP + PA + Q - PBR^{-1}B^TP = 0, \quad K = R^{-1}B^TP \\
    \text{LQR (DARE)}\quad & P = A^TPA - A^TPB(R + B^TPB)^{-1}B^TPA + Q, \quad K = (R + B^TPB)^{-1}B^TPA \\
    \text{LQE (CARE, 4.50–4.53)}\quad & AP + PA^T + GWG^T - PC^TV^{-1}CP = 0, \quad L = PC^TV^{-1} \\
    \text{LQE (DARE)}\quad & \bar P = A\bar PA^T - A\bar PC^T(C\bar PC^T + V)^{-1}C\bar PA^T + GWG^T, \\
                           & K_f = \bar PC^T(C\bar PC^T + V)^{-1} \text{ (filter gain)}, \quad L_p = AK_f \text{ (predictor gain)}

The *Tobit* LQE (steady-state TKF, (3.57) with its spurious second :math:`\bar\Psi` dropped, MA-11)
is the LQE for the modified pair :math:`(A, \Xi C)` with noise :math:`\Upsilon = \mathrm{diag}(\upsilon_i)`,
:math:`\upsilon_i = V_{ii}(1 - a_i\hat\lambda_i - \hat\lambda_i^2)`, :math:`a_i = \Phi^{-1}(\Xi_i)`;
every gain printed in Ch. 5 is the continuous-time version of it (Kalman–Bucy).

Conventions (as python-control, whose names we mirror):

* every weight and noise level is a **covariance** (``W``, ``V``, ``Q``, ``R``); the dissertation's MEE of
  §4.5.3 uses inverse covariances and its "σ_q = .1" is a standard deviation (MA-23);
* results unpack like python-control's: ``K, S, E = lqr(...)``, ``L, P, E = lqe(...)``,
  ``L, P, E = dlqe(...)`` (``L`` the predictor gain, ``P`` the a-priori Riccati solution), and carry
  the rest as attributes (:class:`EstimatorGain`);
* a filter gain and a predictor gain have different names: ``filter_gain`` :math:`K_f` (the gain of
  :class:`~tobitkf.filters.steady_state.SteadyStateTobitKalmanFilter`, x̂ = x̄ + K_f(y − ŷ)) and
  ``predictor_gain`` :math:`L_p = AK_f` (x̂_{k+1} = Ax̂_k + L_p(y_k − ŷ_k)); a continuous-time result has
  only ``gain``;
* every Riccati solution is refined by Newton steps (Newton–Kleinman for the CARE, Newton–Hewer for the
  DARE) until its residual stops decreasing: the solvers' own solutions can be off in the 6th digit for
  the stiff DC motor (the −10° Tobit gain of §5.4.2 read 73.157737 instead of the printed and 50-digit
  73.1575, MB-14).

The LQR and Kalman gains start from python-control (``lqr``, ``dlqr``, ``lqe``, ``dlqe``), after our own
stabilizability / detectability / weight checks, so that a failure names the Riccati equation and the
reason instead of returning NaN.
"""

from __future__ import annotations

import warnings
from typing import Any, NamedTuple

import numpy as np

from .._extras import require
from .._validation import ShapeError, ValidationError, as_float_array, check_option

__all__ = [
    "RegulatorGain",
    "EstimatorGain",
    "lqr",
    "dlqr",
    "lqe",
    "dlqe",
    "tobit_lqe",
    "tobit_dlqe",
    "controlled_noise",
    "reference_gain",
    "equilibrium",
    "is_stable",
    "uncontrollable_modes",
    "unobservable_modes",
    "discretize",
    "DOMAINS",
    "refine_care",
    "refine_dare",
]

DOMAINS = ("ct", "dt")


def _domain(domain: Any, func: str) -> str:
    """The time domain of ``func``, which is required (the control functions differ in their domain)."""
    if domain is None:
        raise ValidationError(
            f"domain: {func} needs domain='dt' (discrete time) or domain='ct' (continuous time), got none"
        )
    check_option(domain, "domain", DOMAINS)
    return domain


class RegulatorGain(NamedTuple):
    """LQR result, unpacking like python-control's ``K, S, E = lqr(...)``: ``gain`` K (p, n), Riccati
    solution ``cost`` S (n, n), closed-loop ``poles`` E = eig(A − BK)."""

    gain: np.ndarray
    cost: np.ndarray
    poles: np.ndarray


class EstimatorGain:
    r"""LQE result; unpacks like python-control's ``L, P, E = lqe(...)`` / ``dlqe(...)``.

    Iteration (and indexing) gives the three python-control items: the observer gain L (CT: the
    Kalman–Bucy gain :math:`L = PC^TV^{-1}`; DT: the *predictor* gain :math:`L_p = AK_f`), the Riccati
    solution P (DT: the a-priori :math:`\bar P`) and the poles E = eig(A − LC̃). Attributes:

    ``domain``
        ``"ct"`` or ``"dt"``.
    ``gain`` (CT only)
        The Kalman–Bucy gain L.
    ``predictor_gain``, ``filter_gain`` (DT only)
        :math:`L_p = AK_f` and :math:`K_f = \bar P\tilde C^T(\tilde C\bar P\tilde C^T + V)^{-1}`.
    ``prior_cov``
        The Riccati solution (DT: a-priori :math:`\bar P`).
    ``cov``
        DT: the a-posteriori :math:`(I - K_f\tilde C)\bar P`; CT: the Riccati solution.
    ``poles``
        eig(A − LC̃) (DT: eig(A − L_pC̃)).
    ``measurement``, ``noise``
        The C̃ and the measurement covariance used (ΞC and Υ for the Tobit LQE).

    A DT result has no ``gain`` and a CT result no ``filter_gain`` (``AttributeError``): the DT
    ``gain`` would be ambiguous (the predictor gain here, the filter gain in the steady-state TKF).
    """

    __slots__ = ("domain", "_gain", "_filter_gain", "prior_cov", "cov", "poles", "measurement", "noise")

    def __init__(
        self,
        *,
        domain: str,
        gain: np.ndarray,
        filter_gain: np.ndarray | None,
        prior_cov: np.ndarray,
        cov: np.ndarray,
        poles: np.ndarray,
        measurement: np.ndarray,
        noise: np.ndarray,
    ):
        self.domain = domain
        self._gain, self._filter_gain = gain, filter_gain
        self.prior_cov, self.cov, self.poles = prior_cov, cov, poles
        self.measurement, self.noise = measurement, noise

    # python-control's three items
    def _items(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self._gain, self.prior_cov, self.poles

    def __iter__(self):
        return iter(self._items())

    def __len__(self) -> int:
        return 3

    def __getitem__(self, i):
        return self._items()[i]

    def __repr__(self) -> str:
        name = "gain" if self.domain == "ct" else "predictor_gain"
        return f"EstimatorGain(domain={self.domain!r}, {name}={self._gain.tolist()}, poles={self.poles.tolist()})"

    @property
    def predictor_gain(self) -> np.ndarray:
        """DT predictor gain :math:`L_p = AK_f` (observer x̂_{k+1} = Ax̂_k + L_p(y_k − C̃x̂_k))."""
        if self.domain != "dt":
            raise AttributeError("predictor_gain: a continuous-time result has one gain, .gain (Kalman–Bucy)")
        return self._gain

    @property
    def gain(self) -> np.ndarray:
        """CT Kalman–Bucy gain L."""
        if self.domain == "dt":
            raise AttributeError(
                "gain: a discrete-time result has .predictor_gain (A K_f) and .filter_gain (K_f), no .gain"
            )
        return self._gain

    @property
    def filter_gain(self) -> np.ndarray:
        """DT filter gain :math:`K_f`."""
        if self.domain == "ct":
            raise AttributeError("filter_gain: a continuous-time result has one gain, .gain (Kalman–Bucy)")
        assert self._filter_gain is not None, "a discrete-time result has its filter gain"
        return self._filter_gain


# --------------------------------------------------------------------------- Newton refinement
def _residual_care(A, P, Q, S):
    return A.T @ P + P @ A + Q - P @ S @ P


def refine_care(A: Any, Q: Any, S: Any, P: Any, *, steps: int = 6) -> np.ndarray:
    r"""Newton–Kleinman refinement of a solution of :math:`A^TP + PA + Q - PSP = 0` (S = BR^{-1}B^T).

    Each step solves the Lyapunov equation :math:`(A - SP)^T\Delta + \Delta(A - SP) = -\mathcal R(P)` for
    the correction of the residual :math:`\mathcal R`; steps are taken while the residual decreases
    (at most ``steps``). The estimator CARE is the dual (A^T, C^TV^{-1}C). Returns the refined P.
    """
    from scipy.linalg import solve_continuous_lyapunov

    A, Q, S, P = (np.asarray(v, dtype=float) for v in (A, Q, S, P))
    res = np.abs(_residual_care(A, P, Q, S)).max()
    for _ in range(steps):
        if res == 0:
            break
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # near-singular Lyapunov: judged by the residual
            D = solve_continuous_lyapunov((A - S @ P).T, -_residual_care(A, P, Q, S))
        P2 = P + 0.5 * (D + D.T)
        res2 = np.abs(_residual_care(A, P2, Q, S)).max()
        if not np.isfinite(res2) or res2 >= res:
            break
        P, res = P2, res2
    return P


def _residual_dare(A, B, Q, R, P):
    G = R + B.T @ P @ B
    return A.T @ P @ A - A.T @ P @ B @ np.linalg.solve(G, B.T @ P @ A) + Q - P


def refine_dare(A: Any, B: Any, Q: Any, R: Any, P: Any, *, steps: int = 6) -> np.ndarray:
    r"""Newton–Hewer refinement of a solution of :math:`P = A^TPA - A^TPB(R + B^TPB)^{-1}B^TPA + Q`.

    Each step solves :math:`A_k^T\Delta A_k - \Delta = -\mathcal R(P)` with the closed loop
    :math:`A_k = A - B(R + B^TPB)^{-1}B^TPA`; steps are taken while the residual decreases. The
    estimator DARE is the dual (A^T, C^T). Returns the refined P.
    """
    from scipy.linalg import solve_discrete_lyapunov

    A, B, Q, R, P = (np.asarray(v, dtype=float) for v in (A, B, Q, R, P))
    res = np.abs(_residual_dare(A, B, Q, R, P)).max()
    for _ in range(steps):
        if res == 0:
            break
        Ak = A - B @ np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            D = solve_discrete_lyapunov(Ak.T, _residual_dare(A, B, Q, R, P))
        P2 = P + 0.5 * (D + D.T)
        res2 = np.abs(_residual_dare(A, B, Q, R, P2)).max()
        if not np.isfinite(res2) or res2 >= res:
            break
        P, res = P2, res2
    return P


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
        raise ValidationError(
            f"{name}: the {what} must be positive definite (smallest eigenvalue {ev.min():.3g}); "
            "a singular weight makes the Riccati gain undefined"
        )
    if not definite and ev.min() < -1e-10 * scale:
        raise ValidationError(f"{name}: the {what} must be positive semi-definite (smallest eigenvalue {ev.min():.3g})")
    return 0.5 * (W + W.T)


def _unstable(ev: np.ndarray, domain: str, tol: float = 1e-9) -> np.ndarray:
    return ev.real >= -tol if domain == "ct" else np.abs(ev) >= 1.0 - tol


def _on_boundary(ev: np.ndarray, domain: str, tol: float = 1e-9) -> np.ndarray:
    return np.abs(ev.real) <= tol if domain == "ct" else np.abs(np.abs(ev) - 1.0) <= tol


def uncontrollable_modes(
    A: Any, B: Any, *, which: str = "unstable", domain: str | None = None, rtol: float = 1e-9
) -> np.ndarray:
    r"""Eigenvalues λ of A with rank [A − λI, B] < n (PBH test), restricted by ``which``.

    ``which``: ``"unstable"`` (the modes that make (A, B) not stabilizable), ``"boundary"``
    (on the imaginary axis / unit circle) or ``"all"``. ``domain`` ("ct" or "dt") is required
    (omitting it raises a ValidationError).
    """
    check_option(which, "which", ("unstable", "boundary", "all"))
    domain = _domain(domain, "uncontrollable_modes")
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


def unobservable_modes(
    A: Any, C: Any, *, which: str = "unstable", domain: str | None = None, rtol: float = 1e-9
) -> np.ndarray:
    """Eigenvalues λ of A with rank [A − λI; C] < n (PBH test); see :func:`uncontrollable_modes`."""
    domain = _domain(domain, "unobservable_modes")
    return uncontrollable_modes(
        np.asarray(A, dtype=float).T, np.asarray(C, dtype=float).T, which=which, domain=domain, rtol=rtol
    )


def _fmt(ev: np.ndarray) -> str:
    return ", ".join(
        f"{complex(v).real:.4g}" + (f"{complex(v).imag:+.4g}j" if abs(complex(v).imag) > 1e-12 else "") for v in ev
    )


def _diagnose(A, B, Wh, domain, first, weight, why, *, observe: bool = False) -> str:
    """Reason for a failed Riccati equation: (A, B) not stabilizable, or a boundary mode unseen by the weight."""
    bad = uncontrollable_modes(A, B, domain=domain)
    if bad.size:
        kind = "unobservable" if observe else "uncontrollable"
        return f"{first}; {kind} unstable mode(s) {_fmt(bad)}"
    bad = unobservable_modes(A, Wh, which="boundary", domain=domain)
    if bad.size:
        return (
            f"mode(s) {_fmt(bad)} on the stability boundary are not "
            + ("excited by the " if observe else "seen by the ")
            + weight
        )
    return why


def is_stable(M: Any, *, domain: str | None = None) -> bool:
    """True if ``M`` is Hurwitz (``domain="ct"``: all Re λ < 0) or Schur (``"dt"``: spectral radius < 1).

    The domain is required (the dissertation judges discrete-time systems by the continuous-time test,
    docs/sources MA-21); omitting it raises a ValidationError.
    """
    domain = _domain(domain, "is_stable")
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
    K: Any = None
    S: Any = None
    try:
        K, S, _ = (control.lqr if domain == "ct" else control.dlqr)(A, B, Q, R)
        S = np.asarray(S, dtype=float)
        if np.all(np.isfinite(S)):
            S = refine_care(A, Q, B @ np.linalg.solve(R, B.T), S) if domain == "ct" else refine_dare(A, B, Q, R, S)
            K = np.linalg.solve(R, B.T @ S) if domain == "ct" else np.linalg.solve(R + B.T @ S @ B, B.T @ S @ A)
        K = np.asarray(K, dtype=float)
        ok = bool(np.all(np.isfinite(K)) and np.all(np.isfinite(S)) and is_stable(A - B @ K, domain=domain))
        why = "the solution does not stabilize A - B K"
    except (np.linalg.LinAlgError, ValueError) as exc:
        ok, why = False, str(exc)
    if not ok:
        raise ValidationError(
            f"LQR {eq} has no stabilizing solution: "
            + _diagnose(A, B, Qh, domain, "(A, B) is not stabilizable", "state weight Q", why)
        )
    return RegulatorGain(K, 0.5 * (S + S.T), np.linalg.eigvals(A - B @ K))


def lqr(A: Any, B: Any, Q: Any, R: Any) -> RegulatorGain:
    r"""Continuous-time LQR (Miller (4.39)–(4.41)) via ``control.lqr``, Newton–Kleinman refined.

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
        ``gain`` K (p, n) with u = −Kx, ``cost`` P, ``poles`` eig(A − BK) (Hurwitz); unpacks as
        ``K, S, E = lqr(...)`` like python-control.

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
            L, P, _ = control.dlqe(A, G, C, W, V)  # predictor gain A P C'(C P C' + V)^-1, P a-priori
        P = np.asarray(P, dtype=float)
        if np.all(np.isfinite(P)):  # Newton refinement on the dual (A^T, C^T) equation
            P = (
                refine_care(A.T, Qd, C.T @ np.linalg.solve(V, C), P)
                if domain == "ct"
                else refine_dare(A.T, C.T, Qd, V, P)
            )
            L = P @ C.T @ np.linalg.inv(V) if domain == "ct" else A @ np.linalg.solve(C @ P @ C.T + V, C @ P).T
        L = np.asarray(L, dtype=float)
        ok = bool(np.all(np.isfinite(L)) and np.all(np.isfinite(P)) and is_stable(A - L @ C, domain=domain))
        why = "the solution does not stabilize A - L C"
    except (np.linalg.LinAlgError, ValueError) as exc:
        ok, why = False, str(exc)
    if not ok:
        raise ValidationError(
            f"{tag} {eq} has no stabilizing solution: "
            + _diagnose(A.T, C.T, Gh.T, domain, "(A, C) is not detectable", "process noise G W G^T", why, observe=True)
        )
    P = 0.5 * (P + P.T)
    if domain == "ct":
        L = P @ C.T @ np.linalg.inv(V)
        return EstimatorGain(
            domain="ct",
            gain=L,
            filter_gain=None,
            prior_cov=P,
            cov=P,
            poles=np.linalg.eigvals(A - L @ C),
            measurement=C,
            noise=V,
        )
    S = C @ P @ C.T + V
    Kf = np.linalg.solve(S, C @ P).T
    post = (np.eye(n) - Kf @ C) @ P
    Lp = A @ Kf
    return EstimatorGain(
        domain="dt",
        gain=Lp,
        filter_gain=Kf,
        prior_cov=P,
        cov=0.5 * (post + post.T),
        poles=np.linalg.eigvals(A - Lp @ C),
        measurement=C,
        noise=V,
    )


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
        Unpacks as ``L, P, E = lqe(...)`` like python-control: ``gain`` L = P C^T V^{-1}, the CARE
        solution P (``cov``), ``poles`` eig(A − LC). P is Newton–Kleinman refined.

    Raises
    ------
    ValidationError
        (A, C) not detectable, a boundary mode not excited by the noise, singular V; the
        message names the CARE and the reason.

    Notes
    -----
    The MEE form (4.50)–(4.51) with weights Q = V^{-1}, R = W^{-1} gives the same L (docs/sources MA-23).

    Examples
    --------
    The scalar example of §5.3.3 (A = −0.8, σ_q = 0.1, σ = 0.5), printed L = 0.0246:

    >>> L, P, E = lqe([[-0.8]], None, [[1.0]], [[0.01]], [[0.25]])
    >>> round(float(L[0, 0]), 7)
    0.0246211
    """
    return _lqe(A, G, C, W, V, "ct")


def dlqe(A: Any, G: Any, C: Any, W: Any, V: Any) -> EstimatorGain:
    r"""Discrete-time steady-state Kalman gains via ``control.dlqe`` (DARE), Newton–Hewer refined.

    Unpacks as ``L, P, E = dlqe(...)`` like python-control: the predictor gain
    ``predictor_gain`` :math:`L_p = AK_f` (observer :math:`\hat x_{k+1} = A\hat x_k + L_p(y_k - C\hat x_k)`),
    the a-priori DARE solution ``prior_cov`` :math:`\bar P` and ``poles`` eig(A − L_pC). The filter gain
    ``filter_gain`` :math:`K_f = \bar PC^T(C\bar PC^T + V)^{-1}` (x̂ = x̄ + K_f(y − Cx̄)) and the
    a-posteriori ``cov`` are attributes (docs/sources MA-15). Parameters and errors as :func:`lqe`.

    Examples
    --------
    >>> L, P, E = dlqe([[1.0]], None, [[1.0]], [[1.0]], [[1.0]])   # Pbar = golden ratio
    >>> bool(np.isclose(P[0, 0], 1.6180339887))
    True
    """
    return _lqe(A, G, C, W, V, "dt")


def controlled_noise(xi_uncensored: Any, sigma: Any) -> tuple[np.ndarray, np.ndarray]:
    r"""Constant Tobit statistics under a controlled limit (3.56): :math:`(\hat\lambda, \upsilon)`.

    :math:`\hat\lambda = \phi(a)/\Xi` (the dissertation's λ̂ of §3.4, positive; for right censoring
    it is ``-censored_moments(...).inverse_mills``, whose sign convention is the truncated mean
    μ + σ·inverse_mills) and :math:`\upsilon = \sigma^2(1 - a\hat\lambda - \hat\lambda^2)`,
    :math:`a = \Phi^{-1}(\Xi)`; ``sigma`` is the measurement-noise **standard deviation** (the name says
    so). The two entries of :func:`tobitkf.filters.steady_state.controlled_limit_statistics` a control
    design needs.

    Raises
    ------
    ValidationError
        If some Ξ is outside the open interval (0, 1) or σ <= 0.
    """
    from ..filters.steady_state import controlled_limit_statistics

    _, lam, upsilon, _ = controlled_limit_statistics(xi_uncensored, sigma)
    lam_b, upsilon_b = np.broadcast_arrays(lam, upsilon)
    return lam_b, upsilon_b


def _tobit_lqe(A, G, C, W, V, xi_uncensored, domain: str) -> EstimatorGain:
    C = _mat(C, "C", (None, None))
    m = C.shape[0]
    V = _mat(V, "V", (m, m))
    if np.abs(V - np.diag(np.diag(V))).max() > 0:
        raise ValidationError(
            "V: the Tobit LQE needs a diagonal measurement covariance (the channels are censored one by one)"
        )
    var = np.diag(V)
    if np.any(~np.isfinite(var)) or np.any(var <= 0):
        raise ValidationError(f"V: the measurement variances must be positive and finite, got {var.tolist()}")
    xi_arr = as_float_array(xi_uncensored, "xi_uncensored")
    if xi_arr.ndim > 1 or xi_arr.size not in (1, m):
        raise ShapeError(
            f"xi_uncensored: expected a scalar or shape ({m},) (one per row of C), got shape {xi_arr.shape}"
        )
    xi = np.broadcast_to(xi_arr.reshape(-1), (m,))
    lam, ups = controlled_noise(xi, np.sqrt(var))
    return _lqe(A, G, xi[:, None] * C, W, np.diag(ups), domain, tag="Tobit LQE (modified ARE)")


def _tobit_arguments(V: Any, xi_uncensored: Any, func: str) -> tuple[Any, Any]:
    """The (V, xi) of a Tobit LQE call, both required."""
    if V is None or xi_uncensored is None:
        raise TypeError(f"{func}: the measurement covariance V= and the probability xi_uncensored= are required")
    return V, xi_uncensored


def tobit_lqe(
    A: Any,
    G: Any,
    C: Any,
    W: Any,
    *,
    V: Any = None,
    xi_uncensored: Any = None,
) -> EstimatorGain:
    r"""Continuous-time steady-state Tobit observer gain: the Kalman–Bucy LQE of :math:`(A, \Xi C)` with noise :math:`\Upsilon`.

    This is the "modified ARE" of Miller §3.4.2 and §5.3.3–§5.4 ((3.57) without its spurious
    second :math:`\bar\Psi`, docs/sources MA-11), in continuous time, which is how every Tobit gain
    printed in Ch. 5 is computed (MB-08). With a fixed limit T and the state held at
    :math:`x_{eq}`, use :math:`\Xi = \Phi((T - Cx_{eq})/\sigma)` (right censoring), as the text does
    for the printed gains of §5.3.3 and §5.4. :func:`tobit_dlqe` is the discrete-time version.

    Parameters
    ----------
    A, G, C, W : as in :func:`lqe`
    V : (m, m) array_like, keyword
        Measurement-noise covariance, diagonal (variances σ_i², as :func:`lqe` takes).
    xi_uncensored : float or (m,) array_like in (0, 1), keyword
        Probability Ξ of an uncensored reading per channel.

    Returns
    -------
    EstimatorGain
        Unpacks as ``L, P, E``; ``gain`` L = PC̃ᵀΥ⁻¹ with ``measurement`` C̃ = ΞC and ``noise`` Υ;
        ``poles`` = eig(A − LΞC), the effective observer poles (the text prints eig(A − LC), MB-15).

    Raises
    ------
    ValidationError
        Ξ outside (0, 1), a non-diagonal V, (A, C) not detectable, or a failed Riccati equation (named).

    Notes
    -----
    The covariance ``cov`` is what the steady-state filter believes under Assumption 1 with the limit
    steered so that E(p) ≡ Ξ; it is not an upper bound on the actual error, and with a fixed limit
    and a state away from the design point it can be far too optimistic (docs/sources MB-F1).

    Examples
    --------
    DC-motor speed model, T = 0 (Ξ = 0.5): printed L = [16.452, .305] (§5.4.1).

    >>> from tobitkf.control.plants import dc_motor_speed
    >>> p = dc_motor_speed()
    >>> L, P, E = tobit_lqe(p.A, p.G, p.C, p.W, V=[[0.05**2]], xi_uncensored=0.5)
    >>> [round(float(L[0, 0]), 3), round(float(L[1, 0]), 3)]
    [16.452, 0.305]
    """
    V, xi_uncensored = _tobit_arguments(V, xi_uncensored, "tobit_lqe")
    return _tobit_lqe(A, G, C, W, V, xi_uncensored, "ct")


def tobit_dlqe(A: Any, G: Any, C: Any, W: Any, *, V: Any = None, xi_uncensored: Any = None) -> EstimatorGain:
    r"""Discrete-time steady-state Tobit observer gains: the DARE of :math:`(A, \Xi C)` with noise :math:`\Upsilon`.

    The modified DARE of Miller §3.4.2 ((3.57) corrected, docs/sources MA-11): the fixed gain of
    :class:`~tobitkf.filters.steady_state.SteadyStateTobitKalmanFilter`. Same arguments as
    :func:`tobit_lqe` (``V`` a diagonal covariance, ``xi_uncensored``).

    Returns
    -------
    EstimatorGain
        Unpacks as ``L, P, E`` like :func:`dlqe`: ``predictor_gain`` :math:`L_p = AK_\infty`,
        ``prior_cov`` :math:`\bar\Psi_\infty`, ``poles`` eig(A − L_pΞC); ``filter_gain``
        :math:`K_\infty` (the steady-state TKF's ``gain``) and ``cov`` :math:`\Psi_\infty` as attributes.
        Ψ∞ is not an error bound (docs/sources MB-F1).

    Examples
    --------
    >>> L, P, E = tobit_dlqe([[0.9]], None, [[1.0]], [[0.01]], V=[[0.01]], xi_uncensored=0.5)
    >>> g = tobit_dlqe([[0.9]], None, [[1.0]], [[0.01]], V=[[0.01]], xi_uncensored=0.5)
    >>> bool(np.allclose(L, 0.9 * g.filter_gain))
    True
    """
    V, xi_uncensored = _tobit_arguments(V, xi_uncensored, "tobit_dlqe")
    return _tobit_lqe(A, G, C, W, V, xi_uncensored, "dt")


# --------------------------------------------------------------------------- setpoints
def reference_gain(A: Any, B: Any, Cz: Any, K: Any, *, domain: str | None = None) -> np.ndarray:
    r"""Feed-forward :math:`\bar N` for unit DC gain from r to z = C_z x under u = N̄r − Kx (6.22), (6.45).

    CT: :math:`\bar N = -[C_z(A - BK)^{-1}B]^{-1}`; DT: :math:`\bar N = [C_z(I - A + BK)^{-1}B]^{-1}`
    (Miller §6.1). ``domain`` ("ct" or "dt") is required; omitting it raises a
    ValidationError.

    Raises
    ------
    ValidationError
        If the DC gain matrix is singular or not square (the plant cannot track the reference:
        a transmission zero at s = 0 / z = 1, or more outputs than inputs), or A − BK is not stable.
    """
    domain = _domain(domain, "reference_gain")
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
        raise ValidationError(
            f"Cz: the plant cannot track the reference: {dc.shape[0]} tracked outputs but "
            f"{dc.shape[1]} inputs (the DC gain must be square)"
        )
    if np.linalg.cond(dc) > 1e12:
        raise ValidationError(
            "Cz: the plant cannot track the reference: the closed-loop DC gain "
            f"C_z({'-(A-BK)' if domain == 'ct' else 'I-A+BK'})^-1 B is singular "
            "(a transmission zero at " + ("s = 0)" if domain == "ct" else "z = 1)")
        )
    return np.linalg.inv(dc)


def equilibrium(A: Any, B: Any, G: Any, H: Any, r: Any, *, domain: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    r"""Equilibrium :math:`(x_{eq}, u_{eq})` with output :math:`Gx_{eq} + Hu_{eq} = r` (Miller (6.4)–(6.5)).

    Solves :math:`[[A - I\,(\text{DT}) \text{ or } A, B], [G, H]]\,[x_{eq}; u_{eq}] = [0; r]` in the
    least-squares sense and checks that the residual vanishes. ``domain`` ("ct" or "dt") is required
    (omitting it raises a ValidationError).

    Raises
    ------
    ValidationError
        If no equilibrium produces ``r`` (the reference cannot be tracked).
    """
    domain = _domain(domain, "equilibrium")
    A, B, G, H = (np.atleast_2d(np.asarray(v, dtype=float)) for v in (A, B, G, H))
    r = np.atleast_1d(np.asarray(r, dtype=float))
    n, p = B.shape
    top = A - np.eye(n) if domain == "dt" else A
    M = np.block([[top, B], [G, H]])
    rhs = np.concatenate([np.zeros(n), r])
    sol, *_ = np.linalg.lstsq(M, rhs, rcond=None)
    res = np.linalg.norm(M @ sol - rhs)
    if res > 1e-8 * max(1.0, float(np.linalg.norm(rhs))):
        raise ValidationError(
            f"r: the plant cannot track the reference {r.tolist()}: no equilibrium of (6.4) gives "
            f"this output (residual {res:.3g})"
        )
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
    :math:`M = V^{-1}GWG^TV^{-H}` (Van Loan's method overflows for the stiff DC motor, whose eigenvalues span 0 to −1.5e7).
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
