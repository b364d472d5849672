r"""The Gaussian projection of the exact posterior of one step by quadrature over x (internal).

Given the prediction :math:`x \sim N(\bar x, \bar P)`, :math:`\bar P = SS^T`, and the exact log-likelihood
:math:`\log p(y \mid x)` of the step's readings, the posterior :math:`p(x \mid y) \propto N(x; \bar x, \bar P)
\,p(y \mid x)` is integrated in the whitened coordinates :math:`x = \bar x + S\xi`, :math:`\xi \sim N(0, I)`,
by a rule with nodes :math:`\xi_i` and weights :math:`w_i \ge 0`, :math:`\sum_i w_i = 1`:

.. math::

    \log p(y) \approx \log\sum_i w_i\,p(y \mid \bar x + S\xi_i), \qquad
    \pi_i = \frac{w_i\,p(y \mid \bar x + S\xi_i)}{\sum_j w_j\,p(y \mid \bar x + S\xi_j)},

    \hat x = \bar x + S\mu_\xi, \quad \mu_\xi = \sum_i \pi_i\xi_i, \qquad
    P = SC_\xi S^T, \quad C_\xi = \sum_i \pi_i(\xi_i - \mu_\xi)(\xi_i - \mu_\xi)^T,

the weights formed from :math:`\log w_i + \log p(y \mid x_i)` by log-sum-exp, so a reading far in a tail does
not underflow; :math:`C_\xi = U^TU` from one QR of the rows :math:`\sqrt{\pi_i}(\xi_i - \mu_\xi)^T` (PSD by
construction). A further pass re-centres the rule on the previous pass's Gaussian :math:`N(\mu_\xi, GG^T)`,
:math:`G = U^T` (adaptive Gauss–Hermite quadrature): nodes :math:`z_i = \mu_\xi + G\xi_i`, each weight times the
ratio of the prediction's density to the rule's, :math:`\log w_i - \tfrac12|z_i|^2 + \tfrac12|\xi_i|^2 +
\log\det G` (G's diagonal floored at 1e-8), the same moments of the :math:`z_i`; so the nodes sit where the
posterior lives when a reading falls in the prediction's tail.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

from .._validation import ValidationError, check_int
from ._particle_models import logsumexp
from ._update import qr_r
from .nonlinear import SigmaPoints

__all__ = ["quadrature_rule", "default_order", "project_posterior"]

NODE_BUDGET = 4096
"""Nodes of the default tensor Gauss-Hermite rule at most (its order: the largest p <= 40 with p^n <= this)."""


def default_order(n: int) -> int:
    """The order p of the default tensor Gauss–Hermite rule of dimension ``n``: min(40, floor(4096^(1/n))).

    Raises
    ------
    ValidationError
        ``n`` above 12 (the rule would have one node per coordinate): a rule must be chosen.
    """
    p = min(40, int(math.floor(NODE_BUDGET ** (1.0 / n) + 1e-9)))
    if p < 2:
        raise ValidationError(
            f"quadrature: a tensor Gauss-Hermite rule of {n} states with at most {NODE_BUDGET} nodes has one node "
            "per coordinate; pass a rule (an order p, p**n nodes, or SigmaPoints('cubature'), 2n nodes)"
        )
    return p


def quadrature_rule(quadrature: Any, n: int) -> tuple[np.ndarray, np.ndarray, str]:
    """The unit nodes ``(L, n)``, their log-weights ``(L,)`` and a description of ``quadrature``: None (the default
    tensor Gauss–Hermite rule, :func:`default_order`), an order p (the tensor rule of p points per coordinate,
    p^n nodes) or a :class:`~tobitkf.SigmaPoints` rule with non-negative weights.

    Raises
    ------
    ValidationError
        An order outside [2, 40], a rule with a negative weight, anything else.
    """
    if quadrature is None:
        quadrature = default_order(n)
    if isinstance(quadrature, SigmaPoints):
        rule = quadrature
    elif isinstance(quadrature, (int, np.integer)) and not isinstance(quadrature, bool):
        rule = SigmaPoints("gauss_hermite", order=check_int(quadrature, "quadrature", minimum=2, maximum=40))
    else:
        raise ValidationError(
            f"quadrature: expected None, an order (points per coordinate) or a SigmaPoints rule, got {quadrature!r}"
        )
    xi, wm, _ = rule.unit(n)
    if np.any(wm < 0):
        raise ValidationError(
            f"quadrature: the rule {rule!r} has a negative weight; a quadrature of the posterior needs weights >= 0 "
            "(the Gauss-Hermite or cubature rule)"
        )
    with np.errstate(divide="ignore"):
        logw = np.log(wm / wm.sum())
    return xi, logw, repr(rule)


def project_posterior(
    x: np.ndarray,
    S: np.ndarray,
    loglik: Callable[[np.ndarray], np.ndarray],
    xi: np.ndarray,
    logw: np.ndarray,
    *,
    passes: int = 1,
    factor: bool = False,
    runs: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    r"""The Gaussian projection of :math:`N(x; \bar x, SS^T)\,p(y \mid x)` (module docstring).

    Parameters
    ----------
    x : (N, n) ndarray
        Predicted means.
    S : (N, n, n) ndarray
        Factors of the predicted covariances, :math:`\bar P = SS^T` (any square root).
    loglik : callable
        Points (N, L, n) -> :math:`\log p(y \mid x)` (N, L) of each run's readings.
    xi, logw : (L, n), (L,) ndarrays
        The rule's unit nodes and log-weights (:func:`quadrature_rule`).
    passes : int >= 1
        Quadratures: the first over the prediction, each further one over the previous pass's Gaussian (module
        docstring).
    factor : bool
        Also return a factor of the posterior covariance.
    runs : (N,) ndarray, optional
        The runs' indices, for the error message.

    Returns
    -------
    mean, cov, factor, log_evidence : (N, n), (N, n, n), (N, n, n) or None, (N,)
        NaN where the likelihood is (a prediction that is not finite).

    Raises
    ------
    ValidationError
        A run whose readings have zero likelihood at every node.
    """
    N, n = x.shape
    mu, G = np.zeros((N, n)), None  # the rule's Gaussian in the whitened coordinates: N(mu, G G^T)
    for _ in range(passes):
        if G is None:
            Z = np.broadcast_to(xi, (N,) + xi.shape)
        else:  # a floor on the rule's spread: a posterior collapsed in a direction still has a density
            idx = np.arange(n)
            G[:, idx, idx] = np.maximum(G[:, idx, idx], 1e-8)
            Z = mu[:, None, :] + np.einsum("lj,rij->rli", xi, G)
        lw = logw + loglik(x[:, None, :] + np.einsum("rlj,rij->rli", Z, S))
        if G is not None:  # the prediction's density over the rule's: N(z; 0, I) / N(z; mu, G G^T)
            logdet = np.log(np.diagonal(G, axis1=-2, axis2=-1)).sum(-1)
            lw = lw - 0.5 * np.einsum("rli,rli->rl", Z, Z) + 0.5 * np.einsum("li,li->l", xi, xi) + logdet[:, None]
        lz = logsumexp(lw, axis=1)
        if np.isneginf(lz).any():
            bad = int(np.flatnonzero(np.isneginf(lz))[0])
            raise ValidationError(
                f"y: the readings of run {bad if runs is None else int(runs[bad])} have zero likelihood at every "
                "quadrature node of the prediction (a reading the channel cannot give)"
            )
        pi = np.exp(lw - lz[:, None])
        mu = np.einsum("rl,rli->ri", pi, Z)
        D = Z - mu[:, None, :]
        U = qr_r(np.sqrt(pi)[:, :, None] * D)  # C = U^T U, the posterior covariance in the whitened coordinates
        G = _lower(U)
    assert G is not None
    mean = x + np.einsum("rij,rj->ri", S, mu)
    F = S @ G
    P = F @ np.swapaxes(F, -1, -2)
    return mean, 0.5 * (P + np.swapaxes(P, -1, -2)), (F if factor else None), lz


def _lower(U: np.ndarray) -> np.ndarray:
    """The lower factor G (N, n, n) with :math:`GG^T = U^TU` from the R factors U of a QR, its diagonal >= 0."""
    G = np.swapaxes(U, -1, -2)
    sign = np.where(np.diagonal(G, axis1=-2, axis2=-1) < 0, -1.0, 1.0)
    return G * sign[:, None, :]
