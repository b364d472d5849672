r"""Regional H∞ filtering with randomly occurring sensor saturations (ROSS) and missing measurements.

Source: Z. Wang, B. Shen, X. Liu, "H∞ filtering with randomly occurring sensor
saturations and missing measurements" (eqs. (1)–(22), Theorems 1–3, Section 4); our deviations
are listed in docs/sources/wang-hinf.md (WH-01 to WH-22).

Model (eqs. (1)–(7))
--------------------
Plant :math:`x_{k+1} = f(x_k) + Bw_k`, :math:`z_k = Mx_k`, with the sector condition (4)
:math:`[f(x)-U_1x]^T[f(x)-U_2x] \le 0`, :math:`U_1-U_2 > 0`. Sensors (2):
:math:`\tilde y_k = \Lambda_{\alpha_k}\sigma(\tilde Cx_k) + (I-\Lambda_{\alpha_k})\Lambda_{\beta_k}\tilde Cx_k + D_v\tilde v_k`
(channel :class:`~tobitkf.channels.saturation.RandomSaturation`). Filter (5):
:math:`\hat x_{k+1} = A_f\hat x_k + B_f\tilde y_k`, :math:`\hat z_k = M\hat x_k`. Augmented state
:math:`\eta_k = [x_k;\hat x_k]`, error :math:`\tilde z_k = \bar M\eta_k`, :math:`\bar M = [M,\ -M]`,
disturbance :math:`\bar w_k = [w_k; \tilde v_k]` (deterministic, square summable).

Decomposition used by every condition: :math:`\xi = [x;\hat x; f(x); \sigma(\tilde Cx); w; \tilde v]`
(length N = 3n+2m+p) and

.. math::

    \eta_{k+1} = \mathcal A\xi + \sum_i (\alpha^i-\mu_i)\,c_i\,\sigma_i + ((1-\alpha^i)\beta^i-(1-\mu_i)\nu_i)\,c_i\,C_ix,
    \qquad c_i = [0;\ B_fe_i],

so :math:`E\{V(\eta_{k+1})\mid\eta_k\} = \xi^T\mathcal A^TP\mathcal A\xi + \sum_i c_i^TPc_i\,
(\varrho_i\sigma_i^2 - 2\varsigma_i\sigma_iC_ix + \delta_i(C_ix)^2)` (ours, checked by enumeration). The paper
bounds the cross term with (14) (weights ϱ_i+ς_i and δ_i+ς_i); the saturation is replaced by
the local sector (10) on :math:`\mathcal L(\Lambda\tilde CH) = \{|a_iC_iH\eta|\le u_i\}`.

Time convention (deviation from the package's, forced by the source): the filter (5) is a
one-step predictor, so ``y[..., k, :]`` is :math:`\tilde y_k` for k = 0..T-1 (measured from
x_k) and ``mean[..., k, :]`` is :math:`\hat x_k` for k = 0..T (T+1 entries, x̂_0 first).

What is implemented
-------------------
* :func:`analyze` — Theorem 1 (eq. (11)–(13), mean-square stability) and Theorem 2
  ((16)–(18), regional H∞) for given :math:`A_f, B_f`, with :math:`P = \mathrm{diag}\{Q_1,Q_2\}`
  (paper) or a full :math:`P` (``lyapunov="full"``, not in the paper).
* :func:`design` — ``method="theorem3"``: LMIs (19)–(21) with the reconstructed Π_1 (WH-03) and recovery (22). ``method="coupled"`` (not in the paper): the Lyapunov matrix
  :math:`P = [[X, -W], [-W, W]]`, i.e. :math:`V = x^T(X-W)x + (x-\hat x)^TW(x-\hat x)`,
  with the linearising change of variables :math:`\hat A = WA_f`, :math:`\hat B = WB_f`.
  ``method="iterate"`` (not in the paper): start from ``coupled`` and alternate a full-P
  analysis (gains fixed) with a gain synthesis (P fixed); γ never increases.
* :func:`verify` — independent numpy re-check of every returned certificate; :func:`design`
  and :func:`analyze` refuse (``status="rejected"``, no gains) anything it does not confirm.

Finding (WH-21, asserted in the tests): with the block-diagonal P of Theorems 2–3 no
filter can certify a smaller γ than the zero filter :math:`A_f = B_f = 0`, so Theorem 3's
min-γ design always returns zero gains. The ``coupled`` certificate removes this. On the
paper's example (Clarabel): Theorem 3 min-γ 1.0519 with A_f = B_f = 0 (= zero filter), printed
gains 1.1608; ``coupled`` 0.4438 (its gains analysed with a free full P: 0.4438, so the structure
costs nothing here; ``iterate`` does not improve on it); ``coupled`` with ``covariance="exact"``
0.2727. The certified γ is a worst-case bound: on the paper's slowly varying disturbance the
coupled filter's error energy is larger than the printed filter's (0.19 vs 0.11 from zero start),
at ω = π it is smaller (gain 0.11 vs 0.38).

Code name -> paper symbol
-------------------------
``B`` B, ``M`` M, ``U1``/``U2`` U_1/U_2, ``C`` \tilde C, ``D`` D_v = diag{D_i}, ``mu``/``nu``
\bar Λ_α/\bar Λ_β, ``Af``/``Bf`` A_f/B_f, ``P`` P, ``Q1``/``Q2`` Q_1/Q_2, ``Lambda`` Λ (a_i),
``Z`` Z = ε_2Λ, ``eps1``/``eps2`` ε_1/ε_2, ``pi`` π, ``rho`` ρ of (22), ``rho_star`` the largest ρ
with Ω(P,ρ) ⊂ ℒ for the returned Λ, ``var_alpha``/``var_beta``/``varsigma`` ϱ_i/δ_i/ς_i.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field, replace
from typing import Any, Literal, overload

import numpy as np

from .._validation import (
    ShapeError,
    ValidationError,
    as_float,
    as_float_array,
    check_bool,
    check_instance,
    check_int,
    check_option,
)
from ..channels.saturation import saturate
from ..models.ross import RossModel

__all__ = [
    "HinfCertificate",
    "Verification",
    "augmented_step",
    "expected_lyapunov_next",
    "psi_matrix",
    "verify",
    "analyze",
    "design",
    "zero_filter_gamma",
    "WANG2010_PAPER",
    "METHODS",
    "OBJECTIVES",
    "COVARIANCES",
]

METHODS = ("theorem3", "coupled", "iterate")
OBJECTIVES = ("feasibility", "min_gamma")
COVARIANCES = ("paper", "exact")
SOLVERS = ("CLARABEL", "SCS")


@overload
def _number(
    value: Any, name: str, *, positive: bool = False, nonnegative: bool = False, optional: Literal[False] = False
) -> float: ...
@overload
def _number(
    value: Any, name: str, *, positive: bool = False, nonnegative: bool = False, optional: bool
) -> float | None: ...
def _number(
    value: Any, name: str, *, positive: bool = False, nonnegative: bool = False, optional: bool = False
) -> float | None:
    """A finite real number (None allowed if ``optional``): text, booleans, NaN and inf are refused by name."""
    if value is None and optional:
        return None
    return as_float(value, name, low=0.0 if (positive or nonnegative) else None, low_open=positive)


def _check_gains(model: RossModel, Af: Any, Bf: Any) -> tuple[np.ndarray, np.ndarray]:
    check_instance(model, RossModel, "model")
    n, m = model.n, model.m
    Af = as_float_array(Af, "Af", ndim=2)
    Bf = as_float_array(Bf, "Bf", ndim=2)
    if Af.shape != (n, n):
        raise ShapeError(f"Af: expected shape ({n}, {n}), got {Af.shape}")
    if Bf.shape != (n, m):
        raise ShapeError(f"Bf: expected shape ({n}, {m}), got {Bf.shape}")
    return Af, Bf


def _check_P(model: RossModel, P: Any, name: str = "P") -> np.ndarray:
    n = model.n
    P = as_float_array(P, name, ndim=2)
    if P.shape != (2 * n, 2 * n):
        raise ShapeError(f"{name}: expected shape ({2 * n}, {2 * n}), got {P.shape}")
    return P


# ---------------------------------------------------------------------------------------
# Augmented system (6)-(7) and the one-step expectation
# ---------------------------------------------------------------------------------------
def _mean_map(model: RossModel, Af: np.ndarray, Bf: np.ndarray) -> np.ndarray:
    r""":math:`\mathcal A` (2n × N): mean of η_{k+1} as a linear map of ξ (eqs. (6)–(7))."""
    n, m, p = model.n, model.m, model.p
    ch = model.channel
    G = Bf @ np.diag((1 - ch.mu) * ch.nu) @ model.C  # B_f (I - Λα) Λβ C
    top = np.hstack([np.zeros((n, 2 * n)), np.eye(n), np.zeros((n, m)), model.B, np.zeros((n, m))])
    bot = np.hstack([G, Af, np.zeros((n, n)), Bf * ch.mu, np.zeros((n, p)), Bf * model.D])
    return np.vstack([top, bot])


def _selectors(model: RossModel) -> tuple[np.ndarray, np.ndarray]:
    """Rows picking σ_i (m × N) and C_i x (m × N) out of ξ."""
    n, m, p = model.n, model.m, model.p
    N = 3 * n + 2 * m + p
    rs = np.zeros((m, N))
    rs[:, 3 * n : 3 * n + m] = np.eye(m)
    rc = np.zeros((m, N))
    rc[:, :n] = model.C
    return rs, rc


def _weights(model: RossModel, covariance: str) -> np.ndarray:
    """(m, 2, 2) weight matrices on [σ_i, C_i x]: exact K_i or the (14)-bounded diagonal."""
    ch = model.channel
    rho, dlt, vsg = ch.var_alpha, ch.var_beta, ch.varsigma
    K = np.zeros((model.m, 2, 2))
    if covariance == "exact":
        K[:, 0, 0], K[:, 1, 1], K[:, 0, 1], K[:, 1, 0] = rho, dlt, -vsg, -vsg
    else:  # bound (14)
        K[:, 0, 0], K[:, 1, 1] = rho + vsg, dlt + vsg
    return K


def augmented_step(model: RossModel, Af: Any, Bf: Any, eta: Any, w: Any, v: Any, alpha: Any, beta: Any) -> np.ndarray:
    r"""One step of the augmented system (6), batched over leading axes.

    .. math::

        \eta_{k+1} = \bar f(\eta_k) + \bar A\sigma(\tilde CH\eta_k) + \bar D\bar w_k
        + \sum_i(\alpha_k^i-\mu_i)\bar B_i\sigma(\tilde CH\eta_k)
        + \sum_i((1-\alpha_k^i)\beta_k^i-(1-\mu_i)\nu_i)\bar B_i\tilde CH\eta_k

    with :math:`\bar f, \bar A, \bar B_i, \bar D` of (7). ``eta`` (..., 2n), ``w`` (..., p),
    ``v`` (..., m), ``alpha``/``beta`` (..., m). Requires ``model.f``.
    """
    if model.f is None:
        raise ValidationError("model.f: expected the plant nonlinearity to simulate, got None")
    Af, Bf = _check_gains(model, Af, Bf)
    n, ch = model.n, model.channel
    eta = np.asarray(eta, dtype=float)
    x, xh = eta[..., :n], eta[..., n:]
    c = x @ model.C.T
    s = saturate(c, ch.level)
    mu, nu = ch.mu, ch.nu
    fbar_top = model.nonlinearity(x)
    fbar_bot = (c * ((1 - mu) * nu)) @ Bf.T + xh @ Af.T  # (7): \bar f
    Abar_s = (s * mu) @ Bf.T  # \bar A σ
    Dw_top = np.asarray(w, dtype=float) @ model.B.T  # \bar D \bar w
    Dw_bot = (np.asarray(v, dtype=float) * model.D) @ Bf.T
    a = np.asarray(alpha, dtype=float) - mu
    b = (1 - np.asarray(alpha, dtype=float)) * np.asarray(beta, dtype=float) - (1 - mu) * nu
    rand = (a * s + b * c) @ Bf.T  # Σ_i (...) \bar B_i (...)
    return np.concatenate([fbar_top + Dw_top, fbar_bot + Abar_s + Dw_bot + rand], axis=-1)


def expected_lyapunov_next(
    model: RossModel, Af: Any, Bf: Any, P: Any, eta: Any, w: Any, v: Any, *, covariance: str = "exact"
) -> np.ndarray:
    r""":math:`E\{V(\eta_{k+1})\mid\eta_k\}` for :math:`V(\eta) = \eta^TP\eta` in closed form (ours; checked by enumerating the 4^m outcomes).

    ``covariance="exact"`` is the exact expectation; ``"paper"`` applies the bound (14) (an upper
    bound). Batched over leading axes of ``eta`` (..., 2n), ``w``, ``v``. Any symmetric P.
    """
    check_option(covariance, "covariance", COVARIANCES)
    Af, Bf = _check_gains(model, Af, Bf)
    P = _check_P(model, P)
    n, ch = model.n, model.channel
    eta = np.asarray(eta, dtype=float)
    x = eta[..., :n]
    c = x @ model.C.T
    s = saturate(c, ch.level)
    if model.f is None:
        raise ValidationError("model.f: expected the plant nonlinearity, got None")
    mean = _mean_only(model, Af, Bf, eta, w, v)
    Pb = np.einsum(
        "ji,jk,ki->i", np.vstack([np.zeros((n, model.m)), Bf]), P, np.vstack([np.zeros((n, model.m)), Bf])
    )  # c_i^T P c_i
    K = _weights(model, covariance)
    sv = np.stack([s, c], axis=-1)  # (..., m, 2)
    quad = np.einsum("...ia,iab,...ib->...i", sv, K, sv)
    return np.einsum("...i,ij,...j->...", mean, P, mean) + quad @ Pb


def _mean_only(model: RossModel, Af: np.ndarray, Bf: np.ndarray, eta: np.ndarray, w: Any, v: Any) -> np.ndarray:
    n = model.n
    x = eta[..., :n]
    c = x @ model.C.T
    xi = np.concatenate(
        [
            eta,
            model.nonlinearity(x),
            saturate(c, model.channel.level),
            np.broadcast_to(np.asarray(w, float), eta.shape[:-1] + (model.p,)),
            np.broadcast_to(np.asarray(v, float), eta.shape[:-1] + (model.m,)),
        ],
        axis=-1,
    )
    return xi @ _mean_map(model, Af, Bf).T


# ---------------------------------------------------------------------------------------
# The quadratic form Ψ (17) / Φ (12) for any P, in numpy (the independent re-check)
# ---------------------------------------------------------------------------------------
def psi_matrix(
    model: RossModel,
    Af: Any,
    Bf: Any,
    P: Any,
    Lambda: Any,
    eps1: float,
    eps2: float,
    gamma: float | None = None,
    *,
    covariance: str = "paper",
) -> np.ndarray:
    r"""Matrix of the dissipation inequality in :math:`\xi = [x;\hat x;f;\sigma;w;\tilde v]`.

    .. math::

        \Psi = \mathcal A^TP\mathcal A + \sum_i (c_i^TPc_i)\,R_i^TK_iR_i - \mathrm{diag}(P,0)
        + \bar M^T\bar M - \varepsilon_1 S_f - \varepsilon_2 S_\sigma - \gamma^2\,\mathrm{diag}(0, I_{p+m})

    where :math:`S_f` and :math:`S_\sigma` are the symmetric matrices of
    :math:`[f-U_1x]^T[f-U_2x]` and :math:`[\sigma-\Lambda\tilde Cx]^T[\sigma-\tilde Cx]`, and
    :math:`R_i = [e_i^T\sigma\text{-row}; C_i x\text{-row}]`. With ``P = diag(Q1, Q2)`` and
    ``covariance="paper"`` this is Ψ of (17)–(18); with ``gamma=None`` the w̄ rows and the
    :math:`\bar M^T\bar M` term are dropped and the result is Φ of (12)–(13) (size 3n+m).
    Built from the definitions, not from the block layout of Theorem 3.
    """
    check_option(covariance, "covariance", COVARIANCES)
    Af, Bf = _check_gains(model, Af, Bf)
    P = _check_P(model, P)
    eps1, eps2, gamma = _number(eps1, "eps1"), _number(eps2, "eps2"), _number(gamma, "gamma", optional=True)
    n, m, p = model.n, model.m, model.p
    N = 3 * n + 2 * m + p
    Lam = as_float_array(Lambda, "Lambda")
    if Lam.size != m:
        raise ShapeError(f"Lambda: expected {m} values (one per sensor), got shape {Lam.shape}")
    Lam = Lam.reshape(m)
    A = _mean_map(model, Af, Bf)
    rs, rc = _selectors(model)
    cols = np.vstack([np.zeros((n, m)), Bf])
    wts = np.einsum("ji,jk,ki->i", cols, P, cols)
    K = _weights(model, covariance)
    psi = A.T @ P @ A
    for i in range(m):
        R = np.vstack([rs[i], rc[i]])
        psi += wts[i] * R.T @ K[i] @ R
    psi[: 2 * n, : 2 * n] -= P
    Mbar = _error_map(model, N)
    Lf1 = np.zeros((n, N))
    Lf1[:, :n] = -model.U1
    Lf1[:, 2 * n : 3 * n] = np.eye(n)
    Lf2 = np.zeros((n, N))
    Lf2[:, :n] = -model.U2
    Lf2[:, 2 * n : 3 * n] = np.eye(n)
    Ls1 = -Lam[:, None] * rc + rs
    Ls2 = -rc + rs
    psi -= eps1 * 0.5 * (Lf1.T @ Lf2 + Lf2.T @ Lf1)
    psi -= eps2 * 0.5 * (Ls1.T @ Ls2 + Ls2.T @ Ls1)
    if gamma is None:
        keep = 3 * n + m
        return 0.5 * (psi[:keep, :keep] + psi[:keep, :keep].T)
    psi += Mbar.T @ Mbar
    psi[3 * n + m :, 3 * n + m :] -= gamma**2 * np.eye(p + m)
    return 0.5 * (psi + psi.T)


def _region_matrices(model: RossModel, P: np.ndarray, Z: np.ndarray, pi: float) -> list[np.ndarray]:
    """LMI (20) for each sensor: [[-P, z_i H^T C_i^T], [*, -u_i^2 π]] (u_i = 1 in the paper)."""
    n = model.n
    out = []
    for i in range(model.m):
        h = np.concatenate([model.C[i], np.zeros(n)])[:, None] * Z[i]
        mat = np.block([[-P, h], [h.T, -np.array([[model.channel.level[i] ** 2 * pi]])]])
        out.append(0.5 * (mat + mat.T))
    return out


def _rho_star(model: RossModel, P: np.ndarray, Lambda: np.ndarray) -> float:
    """Largest ρ with Ω(P,ρ) ⊂ ℒ(ΛC̃H): min_i u_i² / (a_i² C_i (P^{-1})_{xx} C_i^T)."""
    n = model.n
    Pinv_xx = np.linalg.solve(P, np.eye(2 * n))[:n, :n]
    g = np.einsum("ij,jk,ik->i", model.C, Pinv_xx, model.C) * Lambda**2
    with np.errstate(divide="ignore"):
        return float(np.min(model.channel.level**2 / g))


# ---------------------------------------------------------------------------------------
# Certificates and their verification
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Verification:
    """Outcome of the numpy re-check of a certificate.

    Attributes
    ----------
    ok : bool
        Every condition holds.
    reasons : list of str
        One line per failed condition (empty when ``ok``).
    max_eig : float
        Largest eigenvalue of Ψ (or Φ for Theorem 1); must be below ``-rounding``.
    max_eig_region : float
        Largest eigenvalue over the LMIs (20); must be <= 0 (tolerance 1e-9 relative).
    min_eig_P : float
        Smallest eigenvalue of P; must be above its rounding margin.
    gamma_min : float or None
        Smallest γ for which Ψ < 0 with this (P, Λ, ε_1, ε_2) (Schur complement on w̄); None for
        Theorem 1 or when the non-w̄ block is not negative definite.
    margin : float
        The certificate's actual slack: ``-max_eig`` (how negative definite Ψ is), which can be far
        smaller than the margin the LMIs asked of the solver.
    rounding : float
        The rounding margin the slack must exceed: ``ROUNDING_FACTOR`` × size × machine ε × ‖Ψ‖₂, a
        bound on the error of the computed eigenvalues of the computed Ψ (a slack below it is lost
        in rounding and proves nothing).
    """

    ok: bool
    reasons: list[str]
    max_eig: float
    max_eig_region: float
    min_eig_P: float
    gamma_min: float | None
    margin: float = float("nan")
    rounding: float = 0.0


@dataclass(frozen=True)
class HinfCertificate:
    """Result of :func:`design` or :func:`analyze`.

    ``Af``, ``Bf``, ``P``... are None unless the solver reported success *and* the numpy
    re-check (:attr:`verification`) confirmed the certificate; ``status`` then is
    ``"optimal"`` (or ``"optimal_inaccurate"``); otherwise ``"infeasible"``, ``"rejected"``
    (solved but refused by the re-check; see ``verification.reasons``) or the solver's status.

    Attributes
    ----------
    status, method, objective, theorem, solver : str
    gamma : float or None
        Certified γ (the fixed value for ``objective="feasibility"``, √(γ²) otherwise).
    Af, Bf : ndarray or None
        Filter gains of (5) ((n, n), (n, m)).
    P : (2n, 2n) ndarray or None
        Lyapunov matrix (diag{Q_1,Q_2} for the paper's theorems).
    Lambda : (m,) ndarray or None
        a_i = z_i/ε_2 of (9).
    eps1, eps2, pi : float or None
        S-procedure multipliers and π of (20).
    rho : float or None
        ρ = ε_2²/π of (22).
    rho_star : float or None
        The tightest ρ for this Λ (WH-14); ρ* >= ρ.
    verification : Verification or None
    history : list of float
        γ after each step (``method="iterate"``).
    seconds : float
        Wall time of the solve(s).
    best_max_eig : float or None
        ``analyze(objective="max_margin")``: the smallest achievable largest eigenvalue of Ψ/Φ.
    lmi_margin : float or None
        The strictness margin the accepted solve asked of the solver (strict LMIs as ``<= -lmi_margin I``);
        the slack the returned certificate actually has is ``verification.margin``.
    """

    status: str
    method: str
    objective: str
    theorem: int
    solver: str
    gamma: float | None = None
    Af: np.ndarray | None = None
    Bf: np.ndarray | None = None
    P: np.ndarray | None = None
    Lambda: np.ndarray | None = None
    eps1: float | None = None
    eps2: float | None = None
    pi: float | None = None
    rho: float | None = None
    rho_star: float | None = None
    verification: Verification | None = None
    history: list[float] = field(default_factory=list)
    seconds: float = 0.0
    best_max_eig: float | None = None
    lmi_margin: float | None = None

    @property
    def ok(self) -> bool:
        """True when gains/P are present (solved and re-verified)."""
        return self.status in ("optimal", "optimal_inaccurate") and self.P is not None

    @property
    def Q1(self) -> np.ndarray | None:
        """Upper-left n×n block of P."""
        return None if self.P is None else self.P[: self.P.shape[0] // 2, : self.P.shape[0] // 2]

    @property
    def Q2(self) -> np.ndarray | None:
        """Lower-right n×n block of P."""
        return None if self.P is None else self.P[self.P.shape[0] // 2 :, self.P.shape[0] // 2 :]

    def summary(self) -> dict[str, Any]:
        """JSON-able summary."""
        ver = self.verification
        return {
            "status": self.status,
            "method": self.method,
            "objective": self.objective,
            "theorem": self.theorem,
            "solver": self.solver,
            "gamma": self.gamma,
            "Af": self.Af,
            "Bf": self.Bf,
            "P": self.P,
            "Lambda": self.Lambda,
            "eps1": self.eps1,
            "eps2": self.eps2,
            "pi": self.pi,
            "rho": self.rho,
            "rho_star": self.rho_star,
            "verified": None if ver is None else ver.ok,
            "verification_reasons": None if ver is None else ver.reasons,
            "max_eig": None if ver is None else ver.max_eig,
            "gamma_min_for_certificate": None if ver is None else ver.gamma_min,
            "history": self.history,
            "seconds": self.seconds,
            "best_max_eig": self.best_max_eig,
            "lmi_margin": self.lmi_margin,
            "verified_margin": None if ver is None else ver.margin,
            "rounding_margin": None if ver is None else ver.rounding,
        }


ROUNDING_FACTOR = 100.0
"""Safety factor of :func:`rounding_margin` over the backward-error bound of a symmetric eigensolver."""


def rounding_margin(M: Any) -> float:
    r"""What rounding can hide in the eigenvalues of the symmetric matrix ``M`` as computed.

    ``ROUNDING_FACTOR · n · ε · max(1, ‖M‖₂)``: the computed eigenvalues of a symmetric matrix are
    within about n·ε·‖M‖₂ of those of the matrix itself, and forming M adds errors of the same order.
    A strict LMI is certified only if its largest eigenvalue is below minus this.
    """
    M = np.asarray(M, dtype=float)
    return float(ROUNDING_FACTOR * M.shape[0] * np.finfo(float).eps * max(1.0, np.linalg.norm(M, 2)))


def verify(
    model: RossModel,
    Af: Any,
    Bf: Any,
    P: Any,
    Lambda: Any,
    eps1: float,
    eps2: float,
    gamma: float | None,
    *,
    pi: float | None = None,
    rho: float | None = None,
    covariance: str = "paper",
    block_diagonal: bool = False,
    region_tol: float = 1e-9,
) -> Verification:
    r"""Independent numpy re-check of a Theorem 1/2 certificate.

    Checks, from the definitions (not the LMI layout): P > 0 (and block-diagonal if
    ``block_diagonal``), 0 < a_i < 1 (9), ε_1, ε_2 > 0, λ_max(Ψ) < 0 (17) (Φ (12) if ``gamma`` is
    None), and the region: LMI (20) with ``pi`` (Z = ε_2Λ), and/or
    :math:`\rho a_i^2C_i(P^{-1})_{xx}C_i^T \le u_i^2` with ``rho`` (⇔ Ω(P,ρ) ⊂ ℒ, (11)/(16)).

    The strict inequalities must hold with a margin above rounding (:func:`rounding_margin`): a
    largest eigenvalue of -1e-13 on a matrix of norm 1e4 proves nothing. The returned
    ``margin`` is the slack the certificate actually has (docs/sources/wang-hinf.md, WH-22).
    """
    Af, Bf = _check_gains(model, Af, Bf)
    P = _check_P(model, P)
    eps1, eps2 = _number(eps1, "eps1"), _number(eps2, "eps2")
    gamma = _number(gamma, "gamma", optional=True)
    pi, rho = _number(pi, "pi", optional=True), _number(rho, "rho", optional=True)
    region_tol = _number(region_tol, "region_tol", nonnegative=True)
    block_diagonal = check_bool(block_diagonal, "block_diagonal")
    Lambda = as_float_array(Lambda, "Lambda")
    n, m = model.n, model.m
    reasons: list[str] = []
    Ps = 0.5 * (P + P.T)
    if np.abs(P - P.T).max() > 1e-9 * max(1.0, np.abs(P).max()):
        reasons.append("P is not symmetric")
    min_eig_P = float(np.linalg.eigvalsh(Ps).min())
    if min_eig_P <= rounding_margin(Ps):
        reasons.append(
            f"P is not positive definite beyond rounding (smallest eigenvalue {min_eig_P:.3g}, rounding "
            f"margin {rounding_margin(Ps):.1e})"
        )
    if block_diagonal and np.abs(P[:n, n:]).max() > 0:
        reasons.append("P is not block-diagonal (Theorems 1-3 require P = diag{Q1, Q2})")
    Lam = np.asarray(Lambda, dtype=float).reshape(m)
    if not ((Lam > 0).all() and (Lam < 1).all()):
        reasons.append(f"Lambda violates (9) 0 < a_i < 1: {Lam}")
    if not (eps1 > 0 and eps2 > 0):
        reasons.append(f"eps1, eps2 must be > 0, got {eps1:.3g}, {eps2:.3g}")
    psi = psi_matrix(model, Af, Bf, Ps, Lam, eps1, eps2, gamma, covariance=covariance)
    max_eig = float(np.linalg.eigvalsh(psi).max())
    rounding = rounding_margin(psi)
    label = "Phi (12)" if gamma is None else "Psi (17)"
    if not max_eig < -rounding:
        reasons.append(
            f"{label} is not negative definite beyond rounding (largest eigenvalue {max_eig:.3g}, "
            f"rounding margin {rounding:.1e})"
        )
    max_eig_region = -np.inf
    if pi is not None:
        if not pi > 0:
            reasons.append(f"pi must be > 0, got {pi:.3g}")
        for mat in _region_matrices(model, Ps, Lam * eps2, pi):
            max_eig_region = max(max_eig_region, float(np.linalg.eigvalsh(mat).max()))
        scale = max(1.0, float(np.abs(Ps).max()))
        if max_eig_region > region_tol * scale:
            reasons.append(f"LMI (20) violated (largest eigenvalue {max_eig_region:.3g})")
    if rho is not None and min_eig_P > 0:
        rs = _rho_star(model, Ps, Lam)
        if not (rho > 0 and rho <= rs * (1 + 1e-7)):
            reasons.append(f"Omega(P, rho) not inside L(Lambda C H) (11): rho={rho:.6g} > rho*={rs:.6g}")
    gamma_min = None
    if gamma is not None:
        k = 3 * n + m
        phi = psi_matrix(model, Af, Bf, Ps, Lam, eps1, eps2, 0.0, covariance=covariance)
        A11, A12, A22 = phi[:k, :k], phi[:k, k:], phi[k:, k:]
        if np.linalg.eigvalsh(A11).max() < 0:
            S = A22 - A12.T @ np.linalg.solve(A11, A12)
            gamma_min = float(np.sqrt(max(np.linalg.eigvalsh(0.5 * (S + S.T)).max(), 0.0)))
    return Verification(
        ok=not reasons,
        reasons=reasons,
        max_eig=max_eig,
        max_eig_region=float(max_eig_region),
        min_eig_P=min_eig_P,
        gamma_min=gamma_min,
        margin=-max_eig,
        rounding=rounding,
    )


# ---------------------------------------------------------------------------------------
# cvxpy helpers
# ---------------------------------------------------------------------------------------
def _cp():
    from .._extras import require

    # imported lazily: the model and simulator do not need it; the solvers are checked here too,
    # so a missing one is named before a design starts
    cp = require("cvxpy", extra="lmi", feature="the H-infinity LMI design")
    require("clarabel", extra="lmi", feature="the H-infinity LMI design")
    require("scs", extra="lmi", feature="the H-infinity LMI design")
    return cp


def _sym(cp, S):
    return (S + S.T) / 2


def _solve(prob, solver: str, fallback: str | None) -> tuple[str, str]:
    """Solve with ``solver``; on a solver error or a non-optimal status retry with ``fallback``."""
    cp = _cp()
    tried = []
    for name in [solver] + ([fallback] if fallback and fallback != solver else []):
        try:
            kwargs = {"max_iters": 20000, "eps": 1e-9} if name == "SCS" else {}
            with warnings.catch_warnings():
                # "Solution may be inaccurate": reported through the status, then re-checked
                warnings.simplefilter("ignore", UserWarning)
                prob.solve(solver=name, **kwargs)
            status = prob.status
        except cp.error.SolverError as exc:  # pragma: no cover - depends on the solver build
            status = f"solver_error: {exc}"
        tried.append(name)
        if status == "optimal" or status in ("infeasible", "unbounded"):
            # a clean answer (including a certificate of infeasibility) is final
            return status, name
    return status, tried[-1]


def _sector_f_terms(cp, model: RossModel, eps1, N: int):
    """−ε_1 S_f as a (N, N) cvxpy expression (x, f rows only)."""
    n = model.n
    Ut1 = (model.U1.T @ model.U2 + model.U2.T @ model.U1) / 2
    Us = (model.U1 + model.U2).T / 2
    E = np.zeros((N, N))
    E[:n, :n] = -Ut1
    F = np.zeros((N, N))
    F[:n, 2 * n : 3 * n] = Us
    F[2 * n : 3 * n, :n] = Us.T
    G = np.zeros((N, N))
    G[2 * n : 3 * n, 2 * n : 3 * n] = -np.eye(n)
    return eps1 * (E + F + G)


def _sector_sigma_terms(cp, model: RossModel, z, eps2, N: int):
    """−ε_2 S_σ with Z = ε_2 Λ: x-block −C^T Z C, σ-block −ε_2 I, x-σ C^T (Z + ε_2 I)/2."""
    n, m = model.n, model.m
    C = model.C
    out = 0
    for i in range(m):
        Exs = np.zeros((N, N))  # x-σ_i coupling C_i^T/2 (symmetric)
        Exs[:n, 3 * n + i] = C[i] / 2
        Exs[3 * n + i, :n] = C[i] / 2
        Exx = np.zeros((N, N))
        Exx[:n, :n] = -np.outer(C[i], C[i])
        Ess = np.zeros((N, N))
        Ess[3 * n + i, 3 * n + i] = -1.0
        out = out + z[i] * (Exx + Exs) + eps2 * (Ess + Exs)
    return out


def _common_vars(cp, model: RossModel, objective: str, gamma: float | None):
    m = model.m
    z = cp.Variable(m)
    pi, e1, e2 = cp.Variable(), cp.Variable(), cp.Variable()
    g2 = cp.Variable() if objective == "min_gamma" else (0.0 if gamma is None else gamma**2)
    return z, pi, e1, e2, g2


def _region_constraints(
    cp, model: RossModel, P, z, pi, e2, margin: float, rho: float | None = None, P_fixed: np.ndarray | None = None
):
    n, m = model.n, model.m
    cons = [z >= margin, e2 - z >= margin, e2 >= margin]  # (19)
    if rho is not None and P_fixed is not None:
        # fixed P and ρ: a_i² ρ C_i (P^{-1})_xx C_i^T <= u_i²  <=>  z_i sqrt(ρ g_i) <= u_i ε_2
        Pinv_xx = np.linalg.solve(P_fixed, np.eye(2 * n))[:n, :n]
        g = np.einsum("ij,jk,ik->i", model.C, Pinv_xx, model.C)
        for i in range(m):
            cons.append(z[i] * np.sqrt(rho * g[i]) <= model.channel.level[i] * e2)
        return cons
    cons.append(pi >= margin)
    for i in range(m):  # (20)
        h = np.concatenate([model.C[i], np.zeros(n)])[:, None]
        blk = cp.bmat(
            [[-P, z[i] * h], [z[i] * h.T, cp.reshape(-(model.channel.level[i] ** 2) * pi, (1, 1), order="C")]]
        )
        cons.append(_sym(cp, blk) << 0)
    return cons


def _multipliers(v: dict[str, Any]) -> dict[str, Any]:
    """The S-procedure multipliers of a solved LMI problem ``v`` (its ``z``, ``e1``, ``e2``, ``pi``) for :func:`_finish`."""
    return {name: v[name].value for name in ("z", "e1", "e2", "pi")}


def _finish(
    model: RossModel,
    *,
    status: str,
    solver: str,
    method: str,
    objective: str,
    theorem: int,
    covariance: str,
    seconds: float,
    gamma: float | None = None,
    Af=None,
    Bf=None,
    P=None,
    z=None,
    e1=None,
    e2=None,
    pi=None,
    block_diagonal: bool = False,
    rho_fixed: float | None = None,
    history: list[float] | None = None,
    margin: float | None = None,
) -> HinfCertificate:
    base: dict[str, Any] = dict(
        method=method,
        objective=objective,
        theorem=theorem,
        solver=solver,
        seconds=seconds,
        history=list(history or []),
        lmi_margin=margin,
    )
    if status not in ("optimal", "optimal_inaccurate"):
        st = "infeasible" if "infeasible" in status else status
        return HinfCertificate(status=st, **base)
    e2v = float(e2)
    Lam = np.asarray(z, dtype=float) / e2v
    P = 0.5 * (P + P.T)
    if block_diagonal:
        n = model.n
        P[:n, n:] = 0.0
        P[n:, :n] = 0.0
    piv = None if pi is None else float(pi)
    if rho_fixed is not None:
        rho = rho_fixed
    else:
        assert piv is not None, "the region LMI (20) has its variable pi whenever rho is not fixed"
        rho = e2v**2 / piv  # (22)
    ver = verify(
        model,
        Af,
        Bf,
        P,
        Lam,
        float(e1),
        e2v,
        gamma,
        pi=piv,
        rho=rho,
        covariance=covariance,
        block_diagonal=block_diagonal,
    )
    if (
        not ver.ok
        and objective == "min_gamma"
        and ver.gamma_min is not None
        and all(r.startswith("Psi") for r in ver.reasons)
    ):
        # The solver's γ sits on the boundary and rounding in the recovered gains (A_f = W^{-1}Â...)
        # can leave λ_max(Ψ) a hair above 0. Certify the same (P, Λ, ε, gains) at the smallest γ
        # the numpy check accepts (Schur complement on the w̄ block), inflated until the slack is
        # above rounding (the first inflation that verifies).
        for inflate in (1e-6, 1e-5, 1e-4, 1e-3):
            gamma_cert = ver.gamma_min * (1 + inflate) + 1e-9
            ver2 = verify(
                model,
                Af,
                Bf,
                P,
                Lam,
                float(e1),
                e2v,
                gamma_cert,
                pi=piv,
                rho=rho,
                covariance=covariance,
                block_diagonal=block_diagonal,
            )
            if ver2.ok:
                gamma, ver = gamma_cert, ver2
                break
    if not ver.ok:
        return HinfCertificate(status="rejected", verification=ver, **base)
    return HinfCertificate(
        status=status,
        gamma=gamma,
        Af=Af,
        Bf=Bf,
        P=P,
        Lambda=Lam,
        eps1=float(e1),
        eps2=e2v,
        pi=piv,
        rho=rho,
        rho_star=_rho_star(model, P, Lam),
        verification=ver,
        **base,
    )


def _check_common(objective: str, gamma: float | None, solver: str, fallback: str | None, covariance: str) -> None:
    check_option(objective, "objective", OBJECTIVES)
    check_option(solver, "solver", SOLVERS)
    if fallback is not None:
        check_option(fallback, "fallback", SOLVERS)
    check_option(covariance, "covariance", COVARIANCES)
    if objective == "feasibility":
        try:
            _number(gamma, "gamma", positive=True)
        except ValidationError:
            raise ValidationError(
                f"gamma: expected a positive number for objective='feasibility', got {gamma!r}"
            ) from None
    elif gamma is not None:
        _number(gamma, "gamma", positive=True)


# ---------------------------------------------------------------------------------------
# Theorems 1-2: analysis for given gains
# ---------------------------------------------------------------------------------------
def analyze(
    model: RossModel,
    Af: Any,
    Bf: Any,
    *,
    theorem: int = 2,
    objective: str | None = None,
    gamma: float | None = None,
    lyapunov: str = "block",
    P: Any = None,
    rho: float | None = None,
    covariance: str = "paper",
    solver: str = "CLARABEL",
    fallback: str | None = "SCS",
    margin: float = 1e-6,
    bound: float | None = 1e4,
) -> HinfCertificate:
    r"""Theorem 1 (``theorem=1``, (11)–(13)) or Theorem 2 (``theorem=2``, (16)–(18)) for given gains.

    Solves for P, Z = ε_2Λ, ε_1, ε_2, π (and γ² for ``objective="min_gamma"``); Ψ is linear in
    these once (A_f, B_f) are fixed. The result is re-verified by :func:`verify`.

    Parameters
    ----------
    model : RossModel
    Af : (n, n) array_like
    Bf : (n, m) array_like
    theorem : {1, 2}
        1: stability only (objective must be "feasibility", gamma ignored); 2: regional H∞.
    objective : {"feasibility", "min_gamma", "max_margin"}, optional
        Default "min_gamma" for theorem 2, "feasibility" for theorem 1. ``"max_margin"``
        minimises the largest eigenvalue t of Ψ (Φ) instead of requiring Ψ < 0 (status
        "infeasible" when the best t is >= 0); useful for a fixed P.
    gamma : float, optional
        γ for ``objective="feasibility"``/``"max_margin"`` and theorem 2.
    lyapunov : {"block", "full"}
        ``"block"``: P = diag{Q_1, Q_2} (paper); ``"full"``: any P > 0 (not in the paper).
    P : (2n, 2n) array_like, optional
        Fix P (then ``rho`` may fix ρ and the region constraint becomes (11) for that ρ).
    rho : float, optional
        Fixed ρ (only with a fixed P).
    covariance : {"paper", "exact"}
        ``"paper"`` uses bound (14); ``"exact"`` the exact Bernoulli covariance (WH-12, not in
        the paper).
    solver, fallback : {"CLARABEL", "SCS"}
    margin : float
        Strictness margin for the strict inequalities.
    bound : float or None
        Upper bound on the eigenvalues of P (keeps min-γ solves bounded, WH-21).

    Returns
    -------
    HinfCertificate

    Raises
    ------
    ValidationError, ShapeError
        Bad options, shapes, a non-positive γ for a feasibility problem.
    """
    check_instance(model, RossModel, "model")
    check_option(theorem, "theorem", (1, 2))
    margin = _number(margin, "margin", positive=True)
    bound = _number(bound, "bound", positive=True, optional=True)
    if rho is not None:
        rho = _number(rho, "rho")
    if objective is None:
        objective = "feasibility" if theorem == 1 else "min_gamma"
    check_option(lyapunov, "lyapunov", ("block", "full"))
    if theorem == 1:
        check_option(objective, "objective", ("feasibility", "max_margin"))
        gamma = None
        check_option(solver, "solver", SOLVERS)
        check_option(covariance, "covariance", COVARIANCES)
    elif objective == "max_margin":
        _check_common("feasibility", gamma, solver, fallback, covariance)
    else:
        _check_common(objective, gamma, solver, fallback, covariance)
    Af, Bf = _check_gains(model, Af, Bf)
    P_fixed = None if P is None else _check_P(model, P)
    if rho is not None and (P_fixed is None or not rho > 0):
        raise ValidationError(
            f"rho: expected a positive value together with a fixed P, got rho={rho!r}, "
            f"P {'given' if P_fixed is not None else 'not given'}"
        )
    cp = _cp()
    t0 = time.perf_counter()
    n, m, p = model.n, model.m, model.p
    N = 3 * n + 2 * m + p
    z, pi, e1, e2, g2 = _common_vars(cp, model, objective, gamma)
    cons = []
    if P_fixed is not None:
        Pv: Any = P_fixed  # a constant, or a cvxpy expression below
    elif lyapunov == "block":
        Q1 = cp.Variable((n, n), symmetric=True)
        Q2 = cp.Variable((n, n), symmetric=True)
        Pv = cp.bmat([[Q1, np.zeros((n, n))], [np.zeros((n, n)), Q2]])
        cons += [Q1 >> margin * np.eye(n), Q2 >> margin * np.eye(n)]
    else:
        Pv = cp.Variable((2 * n, 2 * n), symmetric=True)
        cons.append(Pv >> margin * np.eye(2 * n))
    if bound is not None and P_fixed is None:
        cons.append(Pv << bound * np.eye(2 * n))
    A = _mean_map(model, Af, Bf)
    rs, rc = _selectors(model)
    cols = np.vstack([np.zeros((n, m)), Bf])
    K = _weights(model, covariance)
    psi = A.T @ Pv @ A
    for i in range(m):
        R = np.vstack([rs[i], rc[i]])
        psi = psi + (cols[:, i] @ Pv @ cols[:, i]) * (R.T @ K[i] @ R)
    Eeta = _eta_rows(n, N)
    psi = psi - Eeta.T @ Pv @ Eeta + _sector_f_terms(cp, model, e1, N) + _sector_sigma_terms(cp, model, z, e2, N)
    cons += [e1 >= margin]
    rho_region = rho if P_fixed is not None else None
    cons += _region_constraints(cp, model, Pv, z, pi, e2, margin, rho=rho_region, P_fixed=P_fixed)
    if theorem == 1:
        keep = 3 * n + m
        psi = psi[:keep, :keep]
    else:
        Mbar = _error_map(model, N)
        J = _disturbance_block(model, N)
        psi = psi + Mbar.T @ Mbar - g2 * J
    if objective == "max_margin":
        t_eig = cp.Variable()
        cons += [_sym(cp, psi) << t_eig * np.eye(psi.shape[0]), e1 <= (bound or 1e4), e2 <= (bound or 1e4)]
        prob = cp.Problem(cp.Minimize(t_eig), cons)
    else:
        cons.append(_sym(cp, psi) << -margin * np.eye(psi.shape[0]))
        prob = cp.Problem(cp.Minimize(g2 if objective == "min_gamma" else 0), cons)
    status, used = _solve(prob, solver, fallback)
    seconds = time.perf_counter() - t0
    best_eig = float(t_eig.value) if objective == "max_margin" and status in ("optimal", "optimal_inaccurate") else None
    if best_eig is not None and best_eig >= 0:
        return HinfCertificate(
            status="infeasible",
            method="analysis",
            objective=objective,
            theorem=theorem,
            solver=used,
            best_max_eig=best_eig,
            seconds=seconds,
        )
    ok = status in ("optimal", "optimal_inaccurate")
    gam = (float(np.sqrt(max(g2.value, 0.0))) if objective == "min_gamma" else gamma) if ok and theorem == 2 else gamma
    Pval = (P_fixed if P_fixed is not None else Pv.value) if ok else None
    cert = _finish(
        model,
        status=status,
        solver=used,
        method="analysis",
        objective=objective,
        theorem=theorem,
        gamma=gam,
        Af=Af,
        Bf=Bf,
        P=None if Pval is None else np.array(Pval, dtype=float),
        z=None if not ok else z.value,
        e1=None if not ok else e1.value,
        e2=None if not ok else e2.value,
        pi=None if (not ok or rho_region is not None) else pi.value,
        covariance=covariance,
        block_diagonal=(lyapunov == "block" and P_fixed is None),
        rho_fixed=rho_region,
        seconds=seconds,
        margin=margin,
    )
    return replace(cert, best_max_eig=best_eig)


def zero_filter_gamma(
    model: RossModel, *, lyapunov: str = "block", solver: str = "CLARABEL", covariance: str = "paper"
) -> HinfCertificate:
    """Theorem 2 min-γ for the zero filter A_f = 0, B_f = 0 (the benchmark of WH-21)."""
    return analyze(
        model,
        np.zeros((model.n, model.n)),
        np.zeros((model.n, model.m)),
        theorem=2,
        objective="min_gamma",
        lyapunov=lyapunov,
        solver=solver,
        covariance=covariance,
    )


# ---------------------------------------------------------------------------------------
# Theorem 3 and the improved designs
# ---------------------------------------------------------------------------------------
def _theorem3_problem(
    cp,
    model: RossModel,
    objective: str,
    gamma: float | None,
    margin: float,
    bound: float | None,
    Q_fixed: tuple[np.ndarray, np.ndarray] | None,
):
    """LMIs (19)–(21) in the paper's layout (Π_1 reconstructed, WH-03)."""
    n, m, p = model.n, model.m, model.p
    ch = model.channel
    C, B, M = model.C, model.B, model.M
    O = np.zeros
    z, pi, e1, e2, g2 = _common_vars(cp, model, objective, gamma)
    cons = []
    if Q_fixed is None:
        Q1 = cp.Variable((n, n), symmetric=True)
        Q2 = cp.Variable((n, n), symmetric=True)
        cons += [Q1 >> margin * np.eye(n), Q2 >> margin * np.eye(n)]
        if bound is not None:
            cons += [Q1 << bound * np.eye(n), Q2 << bound * np.eye(n)]
    else:
        Q1, Q2 = Q_fixed
    X = cp.Variable((n, n))
    Y = cp.Variable((n, m))
    P = cp.bmat([[Q1, O((n, n))], [O((n, n)), Q2]])
    cons += [e1 >= margin]
    cons += _region_constraints(cp, model, P, z, pi, e2, margin)  # (19), (20)
    H = np.hstack([np.eye(n), O((n, n))])
    Mb = np.hstack([M, -M])
    Ut1 = H.T @ (model.U1.T @ model.U2 + model.U2.T @ model.U1) @ H / 2  # (13)
    Ut2 = -H.T @ (model.U1.T + model.U2.T) / 2
    Zm = cp.diag(z)
    Sigma = -P + Mb.T @ Mb - e1 * Ut1 - H.T @ C.T @ Zm @ C @ H
    c13 = H.T @ C.T @ (Zm + e2 * np.eye(m)) / 2
    Pi1 = cp.bmat(
        [
            [Sigma, -e1 * Ut2, c13, O((2 * n, p)), O((2 * n, m))],
            [-e1 * Ut2.T, Q1 - e1 * np.eye(n), O((n, m)), Q1 @ B, O((n, m))],
            [c13.T, O((m, n)), -e2 * np.eye(m), O((m, p)), O((m, m))],
            [O((p, 2 * n)), B.T @ Q1, O((p, m)), -g2 * np.eye(p) + B.T @ Q1 @ B, O((p, m))],
            [O((m, 2 * n)), O((m, n)), O((m, m)), O((m, p)), -g2 * np.eye(m)],
        ]
    )
    La, Lb, Dv = np.diag(ch.mu), np.diag(ch.nu), np.diag(model.D)
    FY = cp.hstack([Y @ (np.eye(m) - La) @ Lb @ C, X])  # \tilde F with Y, X
    Pi2 = cp.hstack([FY, O((n, n)), Y @ La, O((n, p)), Y @ Dv]).T
    a1 = np.sqrt(ch.var_beta + ch.varsigma)  # √(δ_i+ς_i)
    a2 = np.sqrt(ch.var_alpha + ch.varsigma)  # √(ϱ_i+ς_i)
    E = [np.diag(np.eye(m)[i]) for i in range(m)]
    S1 = cp.vstack([a1[i] * Y @ E[i] for i in range(m)])  # S_1^Y (nm × m)
    S2 = cp.vstack([a2[i] * Y @ E[i] for i in range(m)])
    Pi3 = cp.hstack([S1 @ C @ H, O((n * m, n)), O((n * m, m)), O((n * m, p)), O((n * m, m))]).T
    Pi4 = cp.hstack([O((n * m, 2 * n)), O((n * m, n)), S2, O((n * m, p)), O((n * m, m))]).T
    Q2t = cp.bmat([[Q2 if i == j else O((n, n)) for j in range(m)] for i in range(m)])
    big = cp.bmat(
        [
            [Pi1, Pi2, Pi3, Pi4],
            [Pi2.T, -Q2, O((n, n * m)), O((n, n * m))],
            [Pi3.T, O((n * m, n)), -Q2t, O((n * m, n * m))],
            [Pi4.T, O((n * m, n)), O((n * m, n * m)), -Q2t],
        ]
    )
    size = 3 * n + 2 * m + p + n + 2 * n * m
    cons.append(_sym(cp, big) << -margin * np.eye(size))  # (21)
    return dict(cons=cons, g2=g2, z=z, pi=pi, e1=e1, e2=e2, Q1=Q1, Q2=Q2, X=X, Y=Y)


def _coupled_problem(
    cp, model: RossModel, objective: str, gamma: float | None, margin: float, bound: float | None, covariance: str
):
    r"""Improved design (not in the paper): :math:`P = [[X, -W], [-W, W]]`, :math:`\hat A = WA_f`,
    :math:`\hat B = WB_f`.

    With :math:`\mathcal A = [R_1; R_2]` (R_1 constant, :math:`WR_2` linear in (Â, B̂)),
    :math:`\mathcal A^TP\mathcal A = R_1^TXR_1 - R_1^T(WR_2) - (WR_2)^TR_1 + (WR_2)^TW^{-1}(WR_2)` and
    :math:`c_i^TPc_i = \hat b_i^TW^{-1}\hat b_i`, so by a Schur complement on W every block is
    linear in (X, W, Â, B̂, Z, ε_1, ε_2, γ²).
    """
    n, m, p = model.n, model.m, model.p
    N = 3 * n + 2 * m + p
    ch = model.channel
    z, pi, e1, e2, g2 = _common_vars(cp, model, objective, gamma)
    X = cp.Variable((n, n), symmetric=True)
    W = cp.Variable((n, n), symmetric=True)
    Ah = cp.Variable((n, n))
    Bh = cp.Variable((n, m))
    P = cp.bmat([[X, -W], [-W, W]])
    cons = [W >> margin * np.eye(n), X - W >> margin * np.eye(n), e1 >= margin]
    if bound is not None:
        cons.append(X << bound * np.eye(n))
    cons += _region_constraints(cp, model, P, z, pi, e2, margin)
    R1 = _plant_rows(model)
    G = _mean_gain(model)
    WR2 = cp.hstack([Bh @ G, Ah, np.zeros((n, n)), Bh @ np.diag(ch.mu), np.zeros((n, p)), Bh @ np.diag(model.D)])
    Eeta = _eta_rows(n, N)
    Mbar = _error_map(model, N)
    J = _disturbance_block(model, N)
    base = (
        R1.T @ X @ R1
        - R1.T @ WR2
        - WR2.T @ R1
        - Eeta.T @ P @ Eeta
        + Mbar.T @ Mbar
        + _sector_f_terms(cp, model, e1, N)
        + _sector_sigma_terms(cp, model, z, e2, N)
        - g2 * J
    )
    rows = [WR2]
    for i, coef in _noise_directions(model, covariance):
        rows.append(cp.reshape(Bh[:, i], (n, 1), order="C") @ coef[None, :])
    k = len(rows)
    blocks = [[base] + [r.T for r in rows]]
    for a in range(k):
        blocks.append([rows[a]] + [(-W if a == b else np.zeros((n, n))) for b in range(k)])
    big = cp.bmat(blocks)
    cons.append(_sym(cp, big) << -margin * np.eye(N + k * n))
    return dict(cons=cons, g2=g2, z=z, pi=pi, e1=e1, e2=e2, X=X, W=W, Ah=Ah, Bh=Bh, P=P)


def _plant_rows(model: RossModel) -> np.ndarray:
    """The plant's block row of the stacked map on ξ = (x, x_f, η, …): ``[0 0 I 0 B 0]`` (n, N)."""
    n, m = model.n, model.m
    return np.hstack([np.zeros((n, 2 * n)), np.eye(n), np.zeros((n, m)), model.B, np.zeros((n, m))])


def _mean_gain(model: RossModel) -> np.ndarray:
    r"""The saturation channel's mean gain on the state, :math:`\operatorname{diag}((1 - μ)ν) C` (m, n)."""
    ch = model.channel
    return np.diag((1 - ch.mu) * ch.nu) @ model.C


def _eta_rows(n: int, N: int) -> np.ndarray:
    """The selector of the stacked state (x, x_f) from the LMI's vector (2n, N)."""
    Eeta = np.zeros((2 * n, N))
    Eeta[:, : 2 * n] = np.eye(2 * n)
    return Eeta


def _error_map(model: RossModel, N: int) -> np.ndarray:
    r"""The estimation error's output map :math:`\bar M = [M\ -M\ 0]` (r, N)."""
    n = model.n
    Mbar = np.zeros((model.r, N))
    Mbar[:, :n], Mbar[:, n : 2 * n] = model.M, -model.M
    return Mbar


def _disturbance_block(model: RossModel, N: int) -> np.ndarray:
    """The selector J of the disturbance entries (the last p + m) of the LMI's vector, (N, N)."""
    n, m, p = model.n, model.m, model.p
    J = np.zeros((N, N))
    J[3 * n + m :, 3 * n + m :] = np.eye(p + m)
    return J


def _noise_directions(model: RossModel, covariance: str):
    """``(i, coef)`` for each nonzero direction of channel i's multiplicative noise: with
    :math:`K_i = LL^T` (:func:`_psd_factor`), ``coef = L[0, j] rs_i + L[1, j] rc_i`` (N,), j = 0, 1."""
    rs, rc = _selectors(model)
    K = _weights(model, covariance)
    for i in range(model.m):
        L = _psd_factor(K[i])  # K_i = L L^T
        for j in range(2):
            coef = L[0, j] * rs[i] + L[1, j] * rc[i]  # (N,)
            if np.abs(coef).max() > 0:
                yield i, coef


def _psd_factor(K: np.ndarray) -> np.ndarray:
    """L with K = L L^T for a 2×2 PSD K (eigen-decomposition: K may be singular)."""
    lam, V = np.linalg.eigh(0.5 * (K + K.T))
    return V * np.sqrt(np.clip(lam, 0.0, None))


def _synthesis_fixed_P(
    cp, model: RossModel, P: np.ndarray, objective: str, gamma: float | None, margin: float, covariance: str
):
    """Gains for a fixed (full) P: Ψ is quadratic in (A_f, B_f) only through 𝒜^TP𝒜 and c_i^TPc_i;
    a Schur complement with P makes it linear."""
    n, m, p = model.n, model.m, model.p
    N = 3 * n + 2 * m + p
    ch = model.channel
    z, pi, e1, e2, g2 = _common_vars(cp, model, objective, gamma)
    Af = cp.Variable((n, n))
    Bf = cp.Variable((n, m))
    G = _mean_gain(model)
    R1 = _plant_rows(model)
    R2 = cp.hstack([Bf @ G, Af, np.zeros((n, n)), Bf @ np.diag(ch.mu), np.zeros((n, p)), Bf @ np.diag(model.D)])
    A = cp.vstack([R1, R2])  # (2n, N)
    Eeta = _eta_rows(n, N)
    Mbar = _error_map(model, N)
    J = _disturbance_block(model, N)
    base = (
        -Eeta.T @ P @ Eeta
        + Mbar.T @ Mbar
        + _sector_f_terms(cp, model, e1, N)
        + _sector_sigma_terms(cp, model, z, e2, N)
        - g2 * J
    )
    rows = [P @ A]
    for i, coef in _noise_directions(model, covariance):
        col = cp.vstack([np.zeros((n, 1)), cp.reshape(Bf[:, i], (n, 1), order="C")])
        rows.append(P @ col @ coef[None, :])
    k = len(rows)
    blocks = [[base] + [r.T for r in rows]]
    for a in range(k):
        blocks.append([rows[a]] + [(-P if a == b else np.zeros((2 * n, 2 * n))) for b in range(k)])
    big = cp.bmat(blocks)
    cons = [e1 >= margin, _sym(cp, big) << -margin * np.eye(N + 2 * n * k)]
    cons += _region_constraints(cp, model, P, z, pi, e2, margin)
    return dict(cons=cons, g2=g2, z=z, pi=pi, e1=e1, e2=e2, Af=Af, Bf=Bf)


def design(
    model: RossModel,
    *,
    method: str = "theorem3",
    objective: str = "feasibility",
    gamma: float | None = 1.5,
    covariance: str = "paper",
    solver: str = "CLARABEL",
    fallback: str | None = "SCS",
    margin: float = 1e-6,
    bound: float | None = 1e4,
    fixed_Q: tuple[Any, Any] | None = None,
    iterations: int = 4,
    tol: float = 1e-4,
    retries: int = 2,
) -> HinfCertificate:
    r"""Design A_f, B_f of the filter (5) with a regional H∞ certificate.

    Parameters
    ----------
    model : RossModel
    method : {"theorem3", "coupled", "iterate"}
        ``"theorem3"``: LMIs (19)–(21) with P = diag{Q_1,Q_2} and recovery (22)
        (:math:`A_f = Q_2^{-1}X`, :math:`B_f = Q_2^{-1}Y`, :math:`\rho = \varepsilon_2^2/\pi`).
        ``"coupled"`` and ``"iterate"`` are not in the paper (see the module docstring).
    objective : {"feasibility", "min_gamma"}
        ``"feasibility"`` at the given ``gamma`` (the paper: γ = 1.5); ``"min_gamma"`` minimises γ².
    gamma : float
        γ for ``objective="feasibility"``.
    covariance : {"paper", "exact"}
        Bound (14) (paper) or the exact Bernoulli covariance (not in the paper; only for
        ``"coupled"``/``"iterate"``, Theorem 3 is the paper's LMI).
    solver, fallback : {"CLARABEL", "SCS"}
        Primary solver and the one retried on failure.
    margin : float
        Strictness margin of (19), (21) and P > 0.
    bound : float or None
        Eigenvalue bound on the Lyapunov blocks (the min-γ Theorem 3 problem drives Q_2 → ∞).
    fixed_Q : (Q1, Q2), optional
        Theorem 3 with the Lyapunov blocks fixed (used to test the printed P, WH-08).
    iterations, tol : int, float
        ``"iterate"``: at most ``iterations`` (analysis, synthesis) rounds; stop when γ drops by
        less than ``tol``.
    retries : int
        When the numpy re-check rejects a solution (or the solver is inaccurate), solve again
        with the margin multiplied by 10, at most ``retries`` times. ``margin`` of the result
        says which margin was used.

    Returns
    -------
    HinfCertificate
        Gains only if the solve succeeded and :func:`verify` confirmed the certificate.

    Raises
    ------
    ValidationError
        Unknown option, γ <= 0 for a feasibility problem, ``covariance="exact"`` with Theorem 3.

    Notes
    -----
    Deviation from the source: with ``method="theorem3"`` the certificate can never beat the zero
    filter (WH-21); ``"coupled"`` couples x and x̂ in P and can.
    """
    check_instance(model, RossModel, "model")
    check_option(method, "method", METHODS)
    _check_common(objective, gamma, solver, fallback, covariance)
    margin = _number(margin, "margin", positive=True)
    bound = _number(bound, "bound", positive=True, optional=True)
    iterations = check_int(iterations, "iterations", minimum=0)
    tol = _number(tol, "tol", nonnegative=True)
    retries = check_int(retries, "retries", minimum=0)
    if fixed_Q is not None and (
        isinstance(fixed_Q, (str, bytes)) or not hasattr(fixed_Q, "__len__") or len(fixed_Q) != 2
    ):
        raise ValidationError(f"fixed_Q: expected a pair (Q1, Q2) of matrices, got {type(fixed_Q).__name__}")
    if method == "theorem3" and covariance != "paper":
        raise ValidationError(
            "covariance: Theorem 3 is the paper's LMI and uses bound (14); "
            "covariance='exact' is only available for method='coupled' or 'iterate'"
        )
    if fixed_Q is not None and method != "theorem3":
        raise ValidationError("fixed_Q: only meaningful for method='theorem3'")
    if objective == "feasibility":
        gamma = as_float(gamma, "gamma")
    if not margin > 0:
        raise ValidationError(f"margin: expected a positive number, got {margin!r}")
    t0 = time.perf_counter()
    cert: HinfCertificate | None = None
    for attempt in range(retries + 1):
        cert = _design_once(
            model,
            method=method,
            objective=objective,
            gamma=gamma,
            covariance=covariance,
            solver=solver,
            fallback=fallback,
            margin=margin * 10**attempt,
            bound=bound,
            fixed_Q=fixed_Q,
            iterations=iterations,
            tol=tol,
        )
        if cert.status not in ("rejected", "optimal_inaccurate") and not cert.status.startswith("solver_error"):
            break
        if cert.status == "optimal_inaccurate" and cert.ok:
            break
    assert cert is not None, "retries >= 0: at least one attempt"
    return replace(cert, seconds=time.perf_counter() - t0)


def _design_once(
    model: RossModel,
    *,
    method: str,
    objective: str,
    gamma: float | None,
    covariance: str,
    solver: str,
    fallback: str | None,
    margin: float,
    bound: float | None,
    fixed_Q: tuple[Any, Any] | None,
    iterations: int,
    tol: float,
) -> HinfCertificate:
    cp = _cp()
    n = model.n
    t0 = time.perf_counter()
    if method == "iterate":
        return _iterate(
            model,
            objective=objective,
            gamma=gamma,
            covariance=covariance,
            solver=solver,
            fallback=fallback,
            margin=margin,
            bound=bound,
            iterations=iterations,
            tol=tol,
        )
    if method == "theorem3":
        Qf = None
        if fixed_Q is not None:
            Qf = (as_float_array(fixed_Q[0], "fixed_Q[0]", ndim=2), as_float_array(fixed_Q[1], "fixed_Q[1]", ndim=2))
            for q in Qf:
                if q.shape != (n, n):
                    raise ShapeError(f"fixed_Q: expected two ({n}, {n}) matrices, got {q.shape}")
        v = _theorem3_problem(cp, model, objective, gamma, margin, bound, Qf)
    else:
        v = _coupled_problem(cp, model, objective, gamma, margin, bound, covariance)
    prob = cp.Problem(cp.Minimize(v["g2"] if objective == "min_gamma" else 0), v["cons"])
    status, used = _solve(prob, solver, fallback)
    seconds = time.perf_counter() - t0
    run: dict[str, Any] = dict(
        status=status,
        solver=used,
        method=method,
        objective=objective,
        theorem=2,
        covariance=covariance,
        seconds=seconds,
        margin=margin,
    )  # what the certificate records of the solve, whether it succeeded or not
    if status not in ("optimal", "optimal_inaccurate"):
        return _finish(model, **run)
    gam = float(np.sqrt(max(v["g2"].value, 0.0))) if objective == "min_gamma" else gamma
    if method == "theorem3":
        Q1 = Qf[0] if Qf is not None else v["Q1"].value
        Q2 = Qf[1] if Qf is not None else v["Q2"].value
        Af = np.linalg.solve(Q2, v["X"].value)  # (22)
        Bf = np.linalg.solve(Q2, v["Y"].value)
        P = np.block([[Q1, np.zeros((n, n))], [np.zeros((n, n)), Q2]])
        blockdiag = True
    else:
        W = v["W"].value
        Af = np.linalg.solve(W, v["Ah"].value)
        Bf = np.linalg.solve(W, v["Bh"].value)
        P = np.array(v["P"].value, dtype=float)
        blockdiag = False
    return _finish(model, **run, gamma=gam, Af=Af, Bf=Bf, P=P, **_multipliers(v), block_diagonal=blockdiag)


def _ok_gamma(cert: HinfCertificate) -> float:
    """The γ of a certificate that is ok (every verified certificate has one)."""
    assert cert.gamma is not None, "a verified certificate carries its gamma"
    return cert.gamma


def _iterate(
    model: RossModel,
    *,
    objective: str,
    gamma: float | None,
    covariance: str,
    solver: str,
    fallback: str | None,
    margin: float,
    bound: float | None,
    iterations: int,
    tol: float,
) -> HinfCertificate:
    """Coupled design, then alternate full-P analysis (gains fixed) and synthesis (P fixed)."""
    cp = _cp()
    t0 = time.perf_counter()
    best = design(
        model,
        method="coupled",
        objective="min_gamma",
        covariance=covariance,
        solver=solver,
        fallback=fallback,
        margin=margin,
        bound=bound,
    )
    if not best.ok:
        return replace(best, method="iterate", seconds=time.perf_counter() - t0)
    history = [_ok_gamma(best)]
    # The improvement steps do not fall back to a second solver: a step that does not solve cleanly
    # ends the iteration (the fallback spent seconds in SCS without ever improving γ, WH-22).
    for _ in range(iterations):
        ana = analyze(
            model,
            best.Af,
            best.Bf,
            theorem=2,
            objective="min_gamma",
            lyapunov="full",
            covariance=covariance,
            solver=solver,
            fallback=None,
            margin=margin,
            bound=bound,
        )
        if ana.ok and _ok_gamma(ana) < _ok_gamma(best):
            best = ana
        assert best.P is not None, "a verified certificate carries its P"
        v = _synthesis_fixed_P(cp, model, best.P, "min_gamma", None, margin, covariance)
        prob = cp.Problem(cp.Minimize(v["g2"]), v["cons"])
        status, used = _solve(prob, solver, None)
        if status in ("optimal", "optimal_inaccurate"):
            cand = _finish(
                model,
                status=status,
                solver=used,
                method="iterate",
                objective="min_gamma",
                theorem=2,
                gamma=float(np.sqrt(max(v["g2"].value, 0.0))),
                Af=v["Af"].value,
                Bf=v["Bf"].value,
                P=best.P.copy(),
                **_multipliers(v),
                covariance=covariance,
                seconds=0.0,
                margin=margin,
            )
            improved = cand.ok and _ok_gamma(cand) < _ok_gamma(best) - tol
            if cand.ok and _ok_gamma(cand) < _ok_gamma(best):
                best = cand
            history.append(_ok_gamma(best))
            if not improved:
                break
        else:
            break
    out = replace(best, method="iterate", objective=objective, history=history, seconds=time.perf_counter() - t0)
    if objective == "feasibility":
        assert gamma is not None, "design() makes gamma a number for the feasibility objective"
        if _ok_gamma(out) > gamma:
            return HinfCertificate(
                status="infeasible",
                method="iterate",
                objective=objective,
                theorem=2,
                solver=out.solver,
                history=history,
                seconds=out.seconds,
            )
        assert out.eps1 is not None and out.eps2 is not None, "a verified certificate carries its multipliers"
        ver = verify(
            model,
            out.Af,
            out.Bf,
            out.P,
            out.Lambda,
            out.eps1,
            out.eps2,
            gamma,
            pi=out.pi,
            rho=out.rho,
            covariance=covariance,
        )
        out = replace(out, gamma=gamma, verification=ver)
    return out


# ---------------------------------------------------------------------------------------
# The paper's example (Section 4)
# ---------------------------------------------------------------------------------------
WANG2010_PAPER: dict[str, Any] = {
    "gamma": 1.5,
    "Af": np.array([[0.2165, 0.0014, 0.0081], [-0.0004, 0.1459, -0.0010], [0.0548, 0.0060, 0.1954]]),
    "Bf": np.array([[0.1035, -0.0096], [0.0, 0.0], [-0.0102, 0.0204]]),
    "P": np.array(
        [
            [1.0895, -0.0362, -0.3883, 0, 0, 0],
            [-0.0362, 1.1292, 0.0189, 0, 0, 0],
            [-0.3883, 0.0189, 2.7617, 0, 0, 0],
            [0, 0, 0, 9.1896, 0.0019, -0.4682],
            [0, 0, 0, 0.0019, 4.5653, 0.0041],
            [0, 0, 0, -0.4682, 0.0041, 5.1266],
        ],
        dtype=float,
    ),
    "rho": 0.2228,
    "x0": np.array([0.3, 0.3, 0.1]),
}
"""The printed design of Section 4 (γ = 1.5). Note (WH-08): the printed triple
(P, A_f, B_f) does not satisfy Theorem 2 for any γ; treat gains and P as separate data."""
