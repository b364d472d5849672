"""The stationary AR(p) process behind :mod:`tobitkf.inference.censored_ar`: its parameterisations (partial
autocorrelations and coefficients), stationarity, autocovariances, the Durbin–Levinson predictors of its first
p values, and its state-space form."""

from __future__ import annotations

from typing import Any

import numpy as np

from .._validation import ValidationError

__all__ = [
    "pacf_to_ar",
    "ar_to_pacf",
    "is_stationary",
    "ar_autocovariance",
    "ar_predictors",
    "ar_state_space",
    "ar_companion",
]


def pacf_to_ar(r: Any) -> np.ndarray:
    r"""AR coefficients :math:`\phi` from partial autocorrelations :math:`r_k \in (-1, 1)` (stationary by construction).

    Durbin–Levinson (Barndorff-Nielsen & Schou 1973; Monahan 1984):
    :math:`\phi^{(k)}_k = r_k`, :math:`\phi^{(k)}_i = \phi^{(k-1)}_i - r_k\phi^{(k-1)}_{k-i}`.
    """
    r = np.asarray(r, dtype=float)
    phi = np.zeros(0)
    for k, rk in enumerate(r, start=1):
        new = np.empty(k)
        new[: k - 1] = phi - rk * phi[::-1]
        new[k - 1] = rk
        phi = new
    return phi


def ar_to_pacf(phi: Any) -> np.ndarray:
    """Inverse of :func:`pacf_to_ar`; raises ``ValidationError`` when ``phi`` is not stationary."""
    phi = np.asarray(phi, dtype=float).copy()
    p = phi.size
    r = np.empty(p)
    for k in range(p, 0, -1):
        rk = phi[k - 1]
        if not abs(rk) < 1:
            raise ValidationError(f"phi: expected stationary AR coefficients, got {phi.tolist()}")
        r[k - 1] = rk
        if k > 1:
            phi = (phi[: k - 1] + rk * phi[: k - 1][::-1]) / (1.0 - rk * rk)
    return r


def is_stationary(phi: Any) -> bool:
    """True when the roots of :math:`1 - \\sum_i\\phi_iz^i` lie outside the unit circle (every partial
    autocorrelation of the backward Durbin-Levinson recursion inside (-1, 1))."""
    phi = np.asarray(phi, dtype=float).ravel()
    if not np.all(np.isfinite(phi)):
        return False
    k = phi.size
    while k > 0:
        rk = phi[k - 1]
        if not abs(rk) < 1.0:
            return False
        if k > 1:
            phi = (phi[: k - 1] + rk * phi[: k - 1][::-1]) / (1.0 - rk * rk)
        k -= 1
    return True


def ar_autocovariance(phi: Any, sigma2: float, lags: int) -> np.ndarray:
    r"""Autocovariances :math:`\gamma_0..\gamma_{lags}` of the stationary AR(p) (Yule–Walker system).

    Solves :math:`\gamma_k - \sum_i\phi_i\gamma_{|k-i|} = \sigma^2\delta_{k0}`, k = 0..p, then extends
    by the recursion. Raises ``ValidationError`` for a non-stationary ``phi``.
    """
    phi = np.asarray(phi, dtype=float)
    p = phi.size
    if not is_stationary(phi):
        raise ValidationError(f"phi: expected stationary AR coefficients, got {phi.tolist()}")
    M = np.eye(p + 1)
    for k in range(p + 1):
        for i in range(1, p + 1):
            M[k, abs(k - i)] -= phi[i - 1]
    rhs = np.zeros(p + 1)
    rhs[0] = sigma2
    g = np.linalg.solve(M, rhs)
    out = np.empty(max(lags, p) + 1)
    out[: p + 1] = g
    for k in range(p + 1, out.size):
        out[k] = phi @ out[k - 1 :: -1][:p]
    return out[: lags + 1]


def ar_predictors(phi: Any, sigma2: float) -> list[tuple[np.ndarray, float]]:
    r"""The stationary start: for t = 1..p+1, the coefficients :math:`a_t` (on :math:`\xi_{t-1}, \dots, \xi_1`)
    and variance :math:`v_t` of :math:`\xi_t` given the earlier values; entry p+1 onward is
    :math:`(\phi, \sigma^2)`."""
    phi = np.asarray(phi, dtype=float)
    p = phi.size
    g = ar_autocovariance(phi, sigma2, p)
    out = []
    for t in range(1, p + 1):
        q = t - 1
        if q == 0:
            out.append((np.zeros(0), float(g[0])))
            continue
        Gm = np.array([[g[abs(i - j)] for j in range(q)] for i in range(q)])
        rhs = g[1 : q + 1]
        a = np.linalg.solve(Gm, rhs)
        out.append((a, float(g[0] - a @ rhs)))
    out.append((phi.copy(), float(sigma2)))
    return out


# --------------------------------------------------------------------------- state-space form


def ar_companion(phi: Any) -> np.ndarray:
    r"""The companion matrix (p, p) of AR coefficients ``phi`` (p >= 1; an empty ``phi`` gives the 1 x 1 zero):
    first row :math:`\phi`, ones on the subdiagonal, so that :math:`s_{t+1} = As_t + e_1\epsilon_{t+1}` for the
    state :math:`s_t = (\xi_t, \dots, \xi_{t-p+1})`."""
    phi = np.asarray(phi, dtype=float).ravel()
    p = max(phi.size, 1)
    A = np.zeros((p, p))
    A[0, : phi.size] = phi
    if p > 1:
        A[1:, :-1] = np.eye(p - 1)
    return A


def ar_state_space(beta: Any, sigma2: float, phi: Any, *, noise_floor: float = 0.0):
    r"""The model as a :class:`~tobitkf.LinearSystem` for the package's filters and smoothers.

    State :math:`s_t = (\xi_t, \dots, \xi_{t-p+1})` (p >= 1), companion matrix A with first row
    :math:`\phi`, noise :math:`B = e_1`, :math:`Q = \sigma^2`, :math:`C = e_1^T`, the regression as the
    feed-through :math:`D = \beta^T` on the input :math:`u_t = x_t`, :math:`R` = ``noise_floor`` (0: exact
    readings), prior :math:`s_0 \sim N(0, \Gamma_p)` stationary (so :math:`s_1` is stationary too).

    Returns
    -------
    LinearSystem
    """
    from ..models.linear import LinearSystem

    beta = np.asarray(beta, dtype=float).ravel()
    phi = np.asarray(phi, dtype=float).ravel()
    A = ar_companion(phi)
    p = A.shape[0]
    g = ar_autocovariance(phi, sigma2, p)
    G = np.array([[g[abs(i - j)] for j in range(p)] for i in range(p)])
    B = np.zeros((p, 1))
    B[0, 0] = 1.0
    C = np.zeros((1, p))
    C[0, 0] = 1.0
    return LinearSystem(
        A=A, C=C, Q=[[float(sigma2)]], R=[[float(noise_floor)]], x0=np.zeros(p), P0=G, B=B, D=beta[None, :]
    )


# --------------------------------------------------------------------------- the model template
