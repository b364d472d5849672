r"""Performance bounds of the protocol-based TKF: Theorems 3–5 of Geng et al. (Sec. IV, App. C–D).

The upper and lower bounds :math:`N^u_k`, :math:`N^l_k` on the expected prior covariance of
:class:`~tobitkf.filters.protocol.ProtocolTobitKalmanFilter` are computed before any data is seen
(Riccati-type recursions over the schedule), so they live with the designs; the filter, its
augmentation (9)–(10) and its options are in :mod:`tobitkf.filters.protocol`. Our deviations from
the source: docs/sources GP-02, GP-04, GP-06.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.special import ndtr

from .._linalg import symmetrize
from .._validation import ShapeError, ValidationError, as_float_array, check_int, check_memory
from ..censored import unchecked_moments
from ..channels.protocol import ProtocolChannel
from ..filters.core import check_keywords
from ..filters.protocol_model import (
    FAILURE_TERMS,
    PREHISTORY_PRIORS,
    _check_parts,
    _initial,
    _sensor_stats,
    augmented_transition,
    noise_input,
    stacked_measurement,
)
from ..models.linear import LinearSystem

__all__ = [
    "protocol_covariance_bounds",
    "CovarianceBounds",
    "analytic_p_uncensored",
    "UPPER_FORMS",
    "LOWER_FORMS",
    "PHI_UPPER",
]

UPPER_FORMS = ("expected_riccati", "suboptimal_gain", "paper_literal")
LOWER_FORMS = ("statement", "paper_proof")
PHI_UPPER = ("zero", "mean_trajectory")


# --- performance bounds (Sec. IV and App. C–D of the source; docs/sources GP-02, GP-04, GP-06) ------------
@dataclass(frozen=True)
class CovarianceBounds:
    r"""Bounds :math:`N^l_k \preceq N_k = E\{P_{\tilde x^-_k}\} \preceq N^u_k` (Theorem 5), k = 1..T.

    Attributes
    ----------
    upper, lower : (T, n, n) ndarray
        :math:`N^u_k`, :math:`N^l_k` (index k-1 holds step k).
    upper_aug, lower_aug : (T, n_ξ, n_ξ) ndarray
        :math:`M^u_k`, :math:`M^l_k`.
    p_uncensored : (T,) ndarray
        The deterministic :math:`\bar\gamma_k` used.
    """

    upper: np.ndarray
    lower: np.ndarray
    upper_aug: np.ndarray
    lower_aug: np.ndarray
    p_uncensored: np.ndarray


def _gl_nodes(lo: float, hi: float, n: int = 64):
    """Gauss-Legendre nodes on [lo, hi] and weights of the uniform density there (summing to 1)."""
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (hi - lo) * x + 0.5 * (hi + lo), 0.5 * w


def analytic_p_uncensored(
    system: LinearSystem,
    channel: ProtocolChannel,
    steps: int,
    *,
    prehistory_prior: str = "x0",
    P0_aug: Any = None,
) -> np.ndarray:
    r"""Unconditional :math:`\bar\gamma_k = P(\bar y_k > \tau)` under the true model, k = 1..T (docs/sources GP-06).

    .. math::

        \bar\gamma_k = \sum_j \pi_j\Big[1 - \Phi\Big(\frac{\tau - \lambda_j\mathcal C_h\mathfrak m_k}
        {\sqrt{\lambda_j^2\mathcal C_h\Sigma_k\mathcal C_h^T + \mathcal R_k}}\Big)\Big]

    with the unconditional mean :math:`\mathfrak m_k` and covariance :math:`\Sigma_k` of
    :math:`\xi_k`. Discrete laws (``values``/``probs``) are summed, constant gains (variance 0)
    are a single point, uniform laws (``low``/``high``) are integrated by 64-point Gauss–Legendre
    quadrature.

    Raises
    ------
    ValidationError
        For a law that is neither discrete nor uniform (pass γ̄ explicitly then).
    """
    n, ell = system.n, channel.window
    xi0, M0 = _initial(system, ell, prehistory_prior, P0_aug)
    Bn = noise_input(n, ell)
    nodes = []
    for i, law in enumerate(channel.laws):
        if hasattr(law, "values") and hasattr(law, "probs"):
            nodes.append((np.asarray(law.values, float).ravel(), np.asarray(law.probs, float).ravel()))
        elif hasattr(law, "low") and hasattr(law, "high"):
            lo, hi = float(law.low), float(law.high)
            nodes.append(_gl_nodes(lo, hi) if hi > lo else (np.array([lo]), np.array([1.0])))
        elif float(law.variance) == 0.0:
            nodes.append((np.array([float(law.mean)]), np.array([1.0])))
        else:
            raise ValidationError(
                f"failures[{i}]: the analytic p_uncensored needs a discrete (values/probs) or "
                f"uniform (low/high) law, got {type(law).__name__}; pass p_uncensored explicitly"
            )
    sched = channel.schedule.scheduled(steps)
    m, S = xi0, M0
    out = np.empty(steps)
    for k in range(1, steps + 1):
        Aa = augmented_transition(system.transition(k - 1), ell)
        m = Aa @ m
        S = Aa @ S @ Aa.T + Bn @ system.process_cov(k - 1) @ Bn.T
        h = int(sched[k - 1]) - 1
        C_row, r = _sensor_stats(system, k, h)
        Cc = stacked_measurement(C_row, ell)
        vals, wts = nodes[h]
        mu = vals * (Cc @ m)
        sd = np.sqrt(vals**2 * (Cc @ S @ Cc) + r)
        out[k - 1] = float(wts @ ndtr((mu - channel.threshold) / sd))
    return out


def protocol_covariance_bounds(
    system: LinearSystem,
    channel: ProtocolChannel,
    steps: int,
    *,
    p_uncensored: Any = "analytic",
    failure_term: str = "variance",
    upper_form: str = "expected_riccati",
    lower_form: str = "statement",
    phi_upper: str = "zero",
    prehistory_prior: str = "x0",
    P0_aug: Any = None,
) -> CovarianceBounds:
    r"""Upper and lower bounds on the expected prior covariance (Theorems 3–5 of the source).


    Sec. IV and App. C–D of the source; our deviations docs/sources GP-02, GP-04, GP-06. Index convention
    (docs/sources GP-05):
    :math:`M^u_1 = M^l_1 = P^-_1 = \mathcal A_0M_0\mathcal A_0^T + \mathcal BQ_0\mathcal B^T`;
    then for k = 1..T-1, with step-k quantities (:math:`h = \bar h_k`, :math:`\mathbf H_k`, :math:`\mathcal R_k`,
    :math:`\bar\gamma_k`):

    .. math::

        M^u_{k+1} &= \mathcal AM^u_k\mathcal A^T + \mathcal BQ\mathcal B^T
          - \bar\gamma_k\,\mathcal AM^u_k\mathbf H^T\big[\mathbf HM^u_k\mathbf H^T + F^u_k
          + \mathcal R_k(1-\bar\varphi^u_k)\big]^{-1}\mathbf HM^u_k\mathcal A^T \\
        M^l_{k+1} &= (1-\bar\gamma_k)\mathcal AM^l_k\mathcal A^T + \mathcal BQ\mathcal B^T  &(30)

    and :math:`N^{u,l}_k = \Pi M^{u,l}_k\Pi^T` (32).

    Parameters
    ----------
    system, channel
        As for the filter.
    steps : int
        T.
    p_uncensored : "analytic" or float or (T,) array_like, default "analytic"
        :math:`\bar\gamma_k`: the unconditional probability (:func:`analytic_p_uncensored`), or
        given values (e.g. the Monte Carlo frequency, or a constant).
    failure_term : str, default "variance"
        :math:`F^u_k`: ``"variance"`` :math:`\check\Lambda\mathcal CM^u\mathcal C^T`, ``"literal"``
        :math:`(\bar\Lambda^2+\check\Lambda)\mathcal CM^u\mathcal C^T`, ``"second_moment"`` and
        ``"lmmse_unconditional"`` :math:`\check\Lambda\mathcal C\mathfrak X_k\mathcal C^T`.
    upper_form : {"expected_riccati", "suboptimal_gain", "paper_literal"}, default "expected_riccati"
    lower_form : {"statement", "paper_proof"}, default "statement"
    phi_upper : {"zero", "mean_trajectory"}, default "zero"
        :math:`\bar\varphi^u_k`: 0 (a guaranteed bound) or φ along the mean trajectory (tighter,
        not guaranteed).
    prehistory_prior, P0_aug
        The filter's initialisation.

    Returns
    -------
    CovarianceBounds

    Raises
    ------
    ValidationError
        Unknown option, :math:`\bar\gamma` outside [0, 1] or of the wrong length.

    Notes
    -----
    Deviations from the source (docs/sources GP-02, GP-04):

    * (28) uses the random :math:`P_{\xi_k}` in its failure term and never defines
      :math:`\bar\gamma^u, \bar\varphi^u`; the default uses :math:`M^u_k`,
      :math:`\bar\gamma^u = \bar\gamma`, :math:`\bar\varphi^u = 0` and the expected-Riccati
      form (a valid bound by concavity and Jensen under the paper's independence idealization).
      ``"suboptimal_gain"`` is what the proof (38)–(41) yields with :math:`E\gamma^2 = \bar\gamma`
      (valid, looser); ``"paper_literal"`` is (28) with :math:`\bar\gamma^2` inside the braces
      (a diagnostic: it is violated in the transient).
    * (30) as stated is the default; ``lower_form="paper_proof"`` is the proof's (45)–(46)
      version :math:`(1-\bar\gamma)\mathcal AM\mathcal A^T + \bar\gamma\mathcal BQ\mathcal B^T` with
      :math:`M^l_0 = 0`, i.e. :math:`M^l_1 = \mathcal BQ_0\mathcal B^T` (looser, also valid).
    """
    check_keywords(
        {
            "failure_term": failure_term,
            "upper_form": upper_form,
            "lower_form": lower_form,
            "phi_upper": phi_upper,
            "prehistory_prior": prehistory_prior,
        },
        {
            "failure_term": FAILURE_TERMS,
            "upper_form": UPPER_FORMS,
            "lower_form": LOWER_FORMS,
            "phi_upper": PHI_UPPER,
            "prehistory_prior": PREHISTORY_PRIORS,
        },
    )
    _check_parts(system, channel)
    steps = check_int(steps, "steps", minimum=1)
    check_memory(
        8 * 4 * int(steps) * (system.n * (channel.window + 1)) ** 2, "steps", f"covariance bounds over {steps} steps"
    )
    if isinstance(p_uncensored, str):
        if p_uncensored != "analytic":
            raise ValidationError(f"p_uncensored: expected 'analytic' or numbers in [0, 1], got {p_uncensored!r}")
        gbar = analytic_p_uncensored(system, channel, steps, prehistory_prior=prehistory_prior, P0_aug=P0_aug)
    else:
        gbar = as_float_array(p_uncensored, "p_uncensored", ndim=(0, 1))
        if gbar.ndim == 1 and gbar.shape != (steps,):
            raise ShapeError(f"p_uncensored: expected a scalar or shape ({steps},), got {gbar.shape}")
        if ((gbar < 0) | (gbar > 1)).any():
            raise ValidationError(
                f"p_uncensored: expected probabilities in [0, 1], got {gbar[(gbar < 0) | (gbar > 1)][:3]}"
            )
        gbar = np.broadcast_to(gbar, (steps,)).astype(float)
    system.check_horizon(steps)
    n, ell = system.n, channel.window
    nxi = n * (ell + 1)
    xi0, M0 = _initial(system, ell, prehistory_prior, P0_aug)
    Bn = noise_input(n, ell)
    lam_mean, lam_var = channel.failure_mean, channel.failure_variance
    sched = channel.schedule.scheduled(steps)
    tau = channel.threshold
    Mu = np.empty((steps, nxi, nxi))
    Ml = np.empty((steps, nxi, nxi))
    A0 = augmented_transition(system.transition(0), ell)
    BQB0 = Bn @ system.process_cov(0) @ Bn.T
    Mu[0] = symmetrize(A0 @ M0 @ A0.T + BQB0)
    Ml[0] = Mu[0] if lower_form == "statement" else BQB0
    mean, X = A0 @ xi0, Mu[0] + np.outer(A0 @ xi0, A0 @ xi0)  # unconditional moments at k = 1
    for k in range(1, steps):
        h = int(sched[k - 1]) - 1
        C_row, r = _sensor_stats(system, k, h)
        Cc = stacked_measurement(C_row, ell)
        H = lam_mean[h] * Cc
        M = Mu[k - 1]
        if failure_term == "variance":
            F = lam_var[h] * (Cc @ M @ Cc)
        elif failure_term == "literal":
            F = (lam_mean[h] ** 2 + lam_var[h]) * (Cc @ M @ Cc)
        else:
            F = lam_var[h] * (Cc @ X @ Cc)
        if phi_upper == "zero":
            phi = 0.0
        else:
            st = unchecked_moments(H @ mean, np.sqrt(r), tau, np.inf)
            phi = 1.0 - float(st.truncated_var) / r
        g = gbar[k - 1]
        MH = M @ H
        HMH = float(H @ MH)
        if upper_form == "expected_riccati":
            corr = g / (HMH + F + r * (1 - phi))
        elif upper_form == "suboptimal_gain":
            corr = g**2 / (g * (HMH + F) + r * (1 - phi))
        else:
            corr = g**2 / (g**2 * (HMH + F) + r * (1 - phi))
        Aa = augmented_transition(system.transition(k), ell)
        BQB = Bn @ system.process_cov(k) @ Bn.T
        Mpost = M - corr * np.outer(MH, MH)
        Mu[k] = symmetrize(Aa @ Mpost @ Aa.T + BQB)
        low_noise = BQB if lower_form == "statement" else g * BQB
        Ml[k] = symmetrize((1 - g) * (Aa @ Ml[k - 1] @ Aa.T) + low_noise)
        mean = Aa @ mean
        X = Aa @ X @ Aa.T + BQB
    return CovarianceBounds(
        upper=Mu[:, :n, :n].copy(),
        lower=Ml[:, :n, :n].copy(),
        upper_aug=Mu,
        lower_aug=Ml,
        p_uncensored=np.asarray(gbar, dtype=float),
    )
