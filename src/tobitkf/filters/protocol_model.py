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
from ..channels.protocol import ProtocolChannel
from ..models.linear import LinearSystem
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
        xi_pred, P_pred, y, gamma, Cc, r, H, H[None, :], tau, lam_mean, lam_var, failure_term, second_moment
    )


#: the failure terms' codes in :func:`~tobitkf.filters._compiled_moments.protocol_tkf_block` (its ``mode``)
FAILURE_CODES = {"variance": 0, "literal": 1, "second_moment": 2, "lmmse_unconditional": 3}


def _prediction(xi_pred, P_pred, y, gamma, Cc, r, H, H0, tau, lam_mean, lam_var, failure_term, X):
    r""":func:`protocol_measurement` with the per-sensor constants ``H`` = lam_mean Cc and ``H0`` = H[None, :]
    given (the filter computes them once per sensor). The moments of (13)–(16), (21), (23)–(24) come from
    :func:`~tobitkf.filters._compiled_moments.protocol_tkf_block`, the function the compiled loop calls, over
    the N runs at once: its inputs :math:`\zeta = \mathbf H\hat\xi^-`, :math:`\mathbf HP^-\mathbf H^T`,
    :math:`\mathcal C_hP^-\mathcal C_h^T`, :math:`\mathcal C_h\hat\xi^-` and the reading, its outputs the
    step's scalars and the noise :math:`F_k + \mathcal R(1-\varphi)`; the failure term of
    ``"lmmse_unconditional"`` (the same for every run) from ``X`` here. A lost reading (NaN) is not
    uncensored (γ = 0 whatever ``gamma`` says): the step only predicts."""
    from ._compiled_moments import PROTOCOL_TKF_EXTRAS, protocol_tkf_block
    from ._compiled_tobit import GL_W, GL_X  # read-only, as the compiled loop sees them

    N = xi_pred.shape[0]
    mom = np.empty((20, N))
    mom[0] = xi_pred @ H
    mom[1] = (P_pred @ H) @ H  # (N or 1,): P_pred is never broadcast to the runs
    mom[2] = (P_pred @ Cc) @ Cc
    mom[3] = xi_pred @ Cc
    mom[14] = y
    g = np.array(gamma, dtype=np.bool_).reshape(N) & ~np.isnan(mom[14])
    fixed = lam_var * float(Cc @ X @ Cc) if failure_term == "lmmse_unconditional" else 0.0
    ok = g.copy()
    buf = np.empty((2, GL_X.shape[0]))
    protocol_tkf_block(
        N, mom, ok, math.sqrt(r), float(r), float(tau), float(lam_mean), float(lam_var), fixed,
        FAILURE_CODES[failure_term], GL_X, GL_W, buf,
    )  # fmt: skip
    extras: dict[str, np.ndarray] = {name: mom[4 + i] for i, name in enumerate(PROTOCOL_TKF_EXTRAS)}
    extras["_gamma"] = g
    # expected: y-hat of (21) where gamma = 1 (the runs that take part), tau elsewhere (left out by ``valid``)
    return MeasurementPrediction(
        expected=mom[7][:, None], H0=H0, noise=mom[11][:, None], valid=g[:, None], extras=extras
    )


def _protocol_info(mp: MeasurementPrediction) -> dict[str, np.ndarray]:
    return {k: v for k, v in mp.extras.items() if not k.startswith("_")}


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
    xi, P, _, _, _ = measurement_update(xi_pred, P_pred, None, y[:, None], mp, covariance_update)
    return xi, P, _protocol_info(mp)
