r"""The protocol-based TKF's measurement model on the augmented state (Geng et al., (9)–(10), (21)–(24)).

The augmentation :math:`\xi_k = [x_k; x_{k-1}; \dots; x_{k-\ell}]` of (9)–(10)
(:func:`augmented_transition`, :func:`noise_input`, :func:`stacked_measurement`) and its prior, the
scheduled sensor's statistics, the failure term of (24) (docs/sources GP-01) and the measurement
moments of the update (21)–(24) (:func:`protocol_measurement`, :func:`protocol_update`). The filter
built on them, its compiled path and its options are in :mod:`tobitkf.filters.protocol`; the covariance
bounds of Theorems 3–5 in :mod:`tobitkf.design.protocol_bounds`. Time convention and code names:
:mod:`tobitkf.filters.protocol`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .._validation import (
    ShapeError,
    ValidationError,
    as_float_array,
    check_instance,
    check_psd,
)
from ..censored import CensoredMoments, _small_moments, unchecked_moments
from ..channels.protocol import ProtocolChannel
from ..models.linear import LinearSystem
from ._backend import kernels
from .core import (
    MeasurementPrediction,
)

__all__ = [
    "FAILURE_TERMS",
    "PREHISTORY_PRIORS",
    "augmented_transition",
    "noise_input",
    "stacked_measurement",
    "protocol_measurement",
    "protocol_update",
]

FAILURE_TERMS = ("variance", "literal", "second_moment", "lmmse_unconditional")


PREHISTORY_PRIORS = ("x0", "zero_mean")


_TINY = 1e-12


# --- augmentation (9)-(10) -------------------------------------------------------------
def augmented_transition(A: np.ndarray, window: int) -> np.ndarray:
    r""":math:`\mathcal A` of (10): ``A`` in the top-left block, identities on the block sub-diagonal."""
    n = A.shape[-1]
    nx = n * (window + 1)
    out = np.zeros((nx, nx))
    out[:n, :n] = A
    out[n:, :-n] = np.eye(n * window)
    return out


def noise_input(n: int, window: int) -> np.ndarray:
    r""":math:`\mathcal B = [I\;0\cdots0]^T` of (10), also the transpose of the selector Π of (25)."""
    out = np.zeros((n * (window + 1), n))
    out[:n] = np.eye(n)
    return out


def stacked_measurement(C_row: np.ndarray, window: int) -> np.ndarray:
    r""":math:`\mathcal C_{m,k} = [C_{m,k}\;\cdots\;C_{m,k}]` (ℓ+1 copies), shape (n(ℓ+1),)."""
    return np.tile(np.asarray(C_row, dtype=float).reshape(-1), window + 1)


def _initial(system: LinearSystem, window: int, prehistory_prior: str, P0_aug: Any, x0: Any = None, P0: Any = None):
    n = system.n
    mean = system.x0 if x0 is None else x0
    cov = system.P0 if P0 is None else P0
    if prehistory_prior == "x0":
        xi0 = np.tile(mean, window + 1)
    else:
        xi0 = np.concatenate([mean, np.zeros(n * window)])
    if P0_aug is None:
        M0 = np.kron(np.eye(window + 1), cov)
    else:
        M0 = as_float_array(P0_aug, "P0_aug", ndim=2)
        if M0.shape != (n * (window + 1),) * 2:
            raise ShapeError(f"P0_aug: expected ({n * (window + 1)}, {n * (window + 1)}), got {M0.shape}")
        check_psd(M0, "P0_aug")
    return xi0, M0


def _sensor_stats(system: LinearSystem, k: int, h: int):
    C = system.measurement(k)
    R = system.measurement_cov(k)
    r = float(R[h, h])
    if not r > 0:
        raise ValidationError(f"R({k}): sensor {h + 1} needs a positive noise variance, got {r}")
    return C[h], r


def _failure_term(
    mode: str,
    Cc: np.ndarray,
    P_pred: np.ndarray,
    xi_pred: np.ndarray,
    lam_mean: float,
    lam_var: float,
    X: np.ndarray | None,
) -> np.ndarray:
    """F_k, the failure term of (24) (docs/sources GP-01), (N,) or (1,) (a covariance shared by the runs;
    it broadcasts)."""
    if mode == "lmmse_unconditional":
        return np.full(P_pred.shape[0], lam_var * float(Cc @ X @ Cc))
    CPC = (P_pred @ Cc) @ Cc  # (N or 1,): C P C^T of each run's covariance, P_pred never broadcast
    if mode == "variance":
        return lam_var * CPC
    if mode == "literal":
        return (lam_mean**2 + lam_var) * CPC
    return lam_var * (CPC + (xi_pred @ Cc) ** 2)  # second_moment


def _check_parts(system: Any, channel: Any) -> None:
    check_instance(system, LinearSystem, "system")
    check_instance(channel, ProtocolChannel, "channel")
    channel.check_system(system)


def protocol_measurement(
    xi_pred: np.ndarray,
    P_pred: np.ndarray,
    y: np.ndarray,
    gamma: np.ndarray,
    Cc: np.ndarray,
    r: float,
    tau: float,
    lam_mean: float,
    lam_var: float,
    *,
    failure_term: str = "variance",
    second_moment: np.ndarray | None = None,
) -> MeasurementPrediction:
    r"""The measurement prediction of Theorem 1, (21)–(24), batched over runs.

    With :math:`\mathbf H = \bar\Lambda_h\mathcal C_h`, :math:`\zeta = \mathbf H\hat\xi^-_k`,
    :math:`\bar\vartheta = (\tau - \zeta)/\sqrt{\mathcal R}` and the Mills ratio
    :math:`\lambda`: ``expected`` :math:`\zeta + \sqrt{\mathcal R}\lambda` (21) for an uncensored
    reading, ``H0`` :math:`\mathbf H`, ``noise`` :math:`F_k + \mathcal R(1-\varphi)` (24) with
    :math:`\mathcal R(1-\varphi)` floored at :math:`10^{-12}\mathcal R`, the reading taking part only
    when :math:`\gamma_k = 1` (K = 0 otherwise: the prediction is kept, bit for bit).

    Parameters
    ----------
    xi_pred : (N, n_ξ) ; P_pred : (N or 1, n_ξ, n_ξ) ; y : (N,) received :math:`y_k` ; gamma : (N,) bool
    Cc : (n_ξ,) :math:`\mathcal C_{h,k}` ; r : :math:`\mathcal R_k = R_{h,k}` ; tau : threshold
    lam_mean, lam_var : :math:`\bar\Lambda_h`, :math:`\check\Lambda_h`
    failure_term : see the module docstring
    second_moment : (n_ξ, n_ξ), for ``"lmmse_unconditional"``
    """
    H = lam_mean * Cc
    return _prediction(
        xi_pred, P_pred, y, gamma, Cc, r, np.sqrt(r), H, H[None, :], tau, lam_mean, lam_var, failure_term, second_moment
    )


def _prediction(xi_pred, P_pred, y, gamma, Cc, r, sd, H, H0, tau, lam_mean, lam_var, failure_term, X, compiled=False):
    """:func:`protocol_measurement` with the per-sensor constants ``sd`` = sqrt(r), ``H`` = lam_mean Cc and
    ``H0`` = H[None, :] given (the filter computes them once per sensor). ``compiled``: the censored moments of
    several runs from the compiled statistics of the TKF kernel
    (:func:`tobitkf.filters._compiled_tobit.censored_moments_array`, equal to :func:`~tobitkf.censored.unchecked_moments`
    to rounding) instead of the array code."""
    if xi_pred.shape[0] == 1 and failure_term != "lmmse_unconditional":
        one = _prediction_one(xi_pred, P_pred, y, gamma, Cc, r, sd, H, H0, tau, lam_mean, lam_var, failure_term)
        if one is not None:
            return one
    zeta = xi_pred @ H
    if compiled and np.isfinite(zeta).all():
        kern = kernels()
        K = zeta.shape[0]
        rows = kern.censored_moments_array(
            np.ascontiguousarray(zeta, dtype=float),
            np.full(K, float(sd)),
            np.full(K, float(tau)),
            np.full(K, math.inf),
            kern.GL_X,
            kern.GL_W,
        )
        st = CensoredMoments(*rows)
    else:
        st = unchecked_moments(zeta, sd, tau, np.inf)
    lam = st.inverse_mills
    noise = np.maximum(st.truncated_var, _TINY * r)  # R (1 - phi), floored
    F = _failure_term(failure_term, Cc, P_pred, xi_pred, lam_mean, lam_var, X)
    yhat = zeta + sd * lam  # (21), gamma = 1
    g = gamma if isinstance(gamma, np.ndarray) and gamma.dtype == bool else np.asarray(gamma, dtype=bool)
    if math.isfinite(tau):  # tau - zeta cannot be inf - inf; sd > 0, so no division by zero
        theta = (tau - zeta) / sd
    else:
        with np.errstate(divide="ignore", invalid="ignore"):
            theta = (tau - zeta) / sd
    extras = {
        "theta_bar": theta,
        "inverse_mills": lam,
        "trunc_var_factor": 1.0 - noise / r,
        "expected_y": np.where(g, yhat, tau),
        "innovation": np.where(g, y - yhat, 0.0),
        "p_uncensored": st.p_uncensored,
        "_noise": noise,
        "_gamma": g,
    }
    return MeasurementPrediction(
        expected=yhat[:, None], H0=H0, noise=(F + noise)[:, None], valid=g[:, None], extras=extras
    )


def _prediction_one(xi_pred, P_pred, y, gamma, Cc, r, sd, H, H0, tau, lam_mean, lam_var, failure_term):
    """:func:`_prediction` of one run (the online step) on Python floats: the same equations (21)-(24) in the
    same order, the censored moments from the scalar route of :func:`~tobitkf.censored.unchecked_moments`
    (tested equal to the array route to 1e-13). None when that route does not apply (the array code runs)."""
    xi = xi_pred[0]
    zeta = float(xi @ H)
    row = _small_moments(zeta, float(sd), float(tau), math.inf)
    if row is None:
        return None
    gam_u, lam, tvar = row[2], row[3], row[5]
    noise = max(tvar, _TINY * r)  # R (1 - phi), floored
    F = float(_failure_term(failure_term, Cc, P_pred, xi_pred, lam_mean, lam_var, None)[0])  # (24), one formula
    yhat = zeta + sd * lam  # (21), gamma = 1
    g = bool(np.asarray(gamma).reshape(-1)[0])
    theta = (tau - zeta) / sd if math.isfinite(tau) else math.copysign(math.inf, tau)
    y0 = float(y[0])
    extras = {
        "theta_bar": np.array([theta]),
        "inverse_mills": np.array([lam]),
        "trunc_var_factor": np.array([1.0 - noise / r]),
        "expected_y": np.array([yhat if g else tau]),
        "innovation": np.array([y0 - yhat if g else 0.0]),
        "p_uncensored": np.array([gam_u]),
        "_noise": np.array([noise]),
        "_gamma": np.array([g]),
    }
    return MeasurementPrediction(
        expected=np.array([[yhat]]), H0=H0, noise=np.array([[F + noise]]), valid=np.array([[g]]), extras=extras
    )


def _protocol_info(mp: MeasurementPrediction, Ree: np.ndarray | None) -> dict[str, np.ndarray]:
    info = {k: v for k, v in mp.extras.items() if not k.startswith("_")}
    g = mp.extras["_gamma"]
    S = mp.extras["_noise"] if Ree is None else Ree[..., 0, 0]
    info["innovation_var"] = np.where(g, S, mp.extras["_noise"])
    return info


def protocol_update(
    xi_pred: np.ndarray,
    P_pred: np.ndarray,
    y: np.ndarray,
    gamma: np.ndarray,
    Cc: np.ndarray,
    r: float,
    tau: float,
    lam_mean: float,
    lam_var: float,
    *,
    failure_term: str = "variance",
    second_moment: np.ndarray | None = None,
    covariance_update: str = "joseph",
):
    r"""One measurement update of Theorem 1, (19)–(24), batched over runs (procedural form).

    :func:`protocol_measurement` followed by the shared :func:`~tobitkf.filters.core.measurement_update`
    (Joseph form of App. D (44), or (20)).

    Returns
    -------
    xi, P, info (dict of (N,) arrays: theta_bar, inverse_mills, trunc_var_factor, expected_y,
    innovation, innovation_var, p_uncensored)
    """
    from .core import measurement_update

    mp = protocol_measurement(
        xi_pred, P_pred, y, gamma, Cc, r, tau, lam_mean, lam_var, failure_term=failure_term, second_moment=second_moment
    )
    xi, P, _, _, Ree = measurement_update(xi_pred, P_pred, None, y[:, None], mp, covariance_update)
    return xi, P, _protocol_info(mp, Ree)
