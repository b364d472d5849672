"""Pieces shared by the batched filters: result type, input preparation, gain update."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._linalg import psd_sqrt, symmetrize
from .._validation import ShapeError, ValidationError, as_float_array, check_option, check_psd

__all__ = ["FilterResult", "prepare_measurements", "gain_update", "symmetrize", "predict", "psd_sqrt", "sqrt_predict",
           "sqrt_update", "process_roots"]


@dataclass(frozen=True)
class FilterResult:
    """Output of a batched filter.

    Index ``k-1`` holds time ``k``: ``mean[..., k-1, :]`` is x̂_{k|k} and
    ``pred_mean[..., k-1, :]`` is x̂_{k|k-1}.

    Attributes
    ----------
    mean : (..., T, n) ndarray
        Filtered means x̂_{k|k}.
    cov : (..., T, n, n) ndarray
        Filtered covariances P_{k|k}.
    pred_mean : (..., T, n) ndarray
        Predicted means x̂_{k|k-1}.
    pred_cov : (..., T, n, n) ndarray
        Predicted covariances P_{k|k-1}.
    extras : dict
        Estimator-specific per-step quantities (e.g. ``p_uncensored`` (..., T, m)).
    """

    mean: np.ndarray
    cov: np.ndarray
    pred_mean: np.ndarray
    pred_cov: np.ndarray
    extras: dict[str, Any] = field(default_factory=dict)


def prepare_measurements(y: Any, m: int, name: str = "y") -> tuple[np.ndarray, tuple[int, ...]]:
    """Validate ``y`` of shape ``(..., T, m)`` and flatten the batch axes.

    NaN entries are allowed (missing samples); infinities are not.

    Returns
    -------
    y2 : (N, T, m) ndarray
    batch_shape : tuple
        The leading shape to restore on outputs (``()`` for a single ``(T, m)`` record).
    """
    arr = as_float_array(y, name, allow_nan=True)
    if arr.ndim < 2:
        raise ShapeError(f"{name}: expected (..., T, {m}) (for one scalar channel pass y[:, None]), got shape {arr.shape}")
    if arr.shape[-1] != m:
        raise ShapeError(f"{name}: expected last axis of length m={m} (measurement channels), got shape {arr.shape}")
    if arr.shape[-2] < 1:
        raise ShapeError(f"{name}: expected at least one time step, got shape {arr.shape}")
    batch = arr.shape[:-2]
    return arr.reshape((-1,) + arr.shape[-2:]), batch


def prepare_inputs(system, u: Any, runs: int, steps: int) -> np.ndarray | None:
    """Validate control inputs ``(T, p)`` or ``(..., T, p)`` and broadcast to ``(N, T, p)``."""
    if u is None:
        return None
    arr = system.check_inputs(u, steps)
    if arr.ndim == 2:
        return np.broadcast_to(arr, (runs, steps, arr.shape[-1]))
    flat = arr.reshape((-1,) + arr.shape[-2:])
    if flat.shape[0] != runs:
        raise ShapeError(f"u: expected (T, p) or the batch shape of y, got {arr.shape}")
    return flat


def predict(x: np.ndarray, P: np.ndarray, A: np.ndarray, Qd: np.ndarray, bx: Any = 0.0):
    r"""Time update :math:`\bar x = A\hat x + B^u u`, :math:`\bar P = A P A^T + Q` (Miller (2.3), (3.20)–(3.21)).

    ``x`` (N, n), ``P`` (N, n, n); ``A`` (n, n); ``Qd`` (n, n) the noise covariance B Q B^T.
    """
    xp = x @ A.T + bx
    n = A.shape[-1]
    if A.ndim == 2 and P.ndim >= 2:
        # one GEMM per product over the stacked rows instead of a batched matmul of tiny
        # matrices (4x faster for 10^4 runs of n = 2): X = P A^T, then X^T A^T = A P^T A^T,
        # which the symmetrization makes equal to sym(A P A^T)
        X = (P.reshape(-1, n) @ A.T).reshape(P.shape)
        Pp = (np.swapaxes(X, -1, -2).reshape(-1, n) @ A.T).reshape(P.shape) + Qd
    else:
        Pp = A @ P @ A.T + Qd
    return xp, symmetrize(Pp)


def _gain(Rxe: np.ndarray, Ree: np.ndarray) -> np.ndarray:
    """K = Rxe Ree^{-1} for m > 1, solved with Ree scaled to unit diagonal.

    Channels whose innovation variances differ by many orders of magnitude (a nearly
    surely censored channel beside an ordinary one: Ree_ll ~ 1e-77 next to 1) make Ree
    so badly scaled that an unscaled solve returns gain entries wrong by 1e50 and the
    Joseph form turns them into a covariance of 1e33. With D = diag(Ree)^{-1/2},
    K = Rxe D (D Ree D)^{-1} D, and D Ree D is well conditioned. Requires diag(Ree) > 0.
    """
    d = 1.0 / np.sqrt(np.diagonal(Ree, axis1=-2, axis2=-1))
    scaled = Ree * d[..., :, None] * d[..., None, :]
    return np.swapaxes(np.linalg.solve(scaled, np.swapaxes(Rxe * d[..., None, :], -1, -2)), -1, -2) * d[..., None, :]


def gain_update(x: np.ndarray, P: np.ndarray, innov: np.ndarray, Rxe: np.ndarray, Ree: np.ndarray,
                valid: np.ndarray | None = None, *, H: np.ndarray | None = None,
                noise: np.ndarray | None = None):
    r"""Linear MMSE measurement update, batched, with per-run channel masks.

    .. math::

        K = R_{xe} R_{ee}^{-1}, \qquad \hat x = \bar x + K e, \qquad P = \bar P - K R_{xe}^T

    (Miller (3.32), (3.22), (3.42) corrected as in (3.55)). Channels where
    ``valid`` is False (missing, dropped, or with :math:`R_{ee,ll} = 0`, which includes a
    subnormal :math:`R_{ee,ll}` such as :math:`\gamma^2 C\bar P C^T` after γ underflowed) are removed
    from the update exactly: their rows and columns of :math:`R_{ee}` are replaced
    by the identity and their gain columns are zero.

    When ``H`` (N or 1, m, n) and ``noise`` (N or 1, m, m) are given, the covariance
    uses the Joseph form :math:`(I - KH)\bar P(I - KH)^T + K\,\mathrm{noise}\,K^T`.

    Parameters
    ----------
    x : (N, n) ; P : (N, n, n) ; innov : (N, m) ; Rxe : (N, n, m) ; Ree : (N, m, m)
    valid : (N, m) bool, optional

    Returns
    -------
    x, P, K
    """
    m = Ree.shape[-1]
    diag = np.diagonal(Ree, axis1=-2, axis2=-1)
    # a subnormal diagonal (e.g. a TKF channel 40 sigma into the censored side) counts as 0:
    # LAPACK's solve takes its reciprocal, which overflows and turns the whole gain into NaN
    degenerate = ~(diag > np.finfo(np.float64).tiny)
    if valid is None and not degenerate.any():
        if m == 1:
            K = Rxe / Ree
        else:
            K = _gain(Rxe, Ree)
        e = innov
    else:
        ok = ~degenerate if valid is None else (valid & ~degenerate)
        pair = ok[..., :, None] & ok[..., None, :]
        Ree = np.where(pair, Ree, np.eye(m))
        Rxe = Rxe * ok[..., None, :]
        e = np.where(ok, innov, 0.0)
        if m == 1:
            K = Rxe / Ree
        else:
            K = _gain(Rxe, Ree)
        if H is not None:
            H = H * ok[..., :, None]
    x_new = x + np.einsum("...ij,...j->...i", K, e)
    if H is None:
        P_new = P - K @ np.swapaxes(Rxe, -1, -2)
    else:
        n = P.shape[-1]
        IKH = np.eye(n) - K @ H
        P_new = IKH @ P @ np.swapaxes(IKH, -1, -2) + K @ noise @ np.swapaxes(K, -1, -2)
    return x_new, symmetrize(P_new), K


def sqrt_predict(x: np.ndarray, S: np.ndarray, A: np.ndarray, Qroot: np.ndarray, bx: Any = 0.0):
    r"""Square-root time update: :math:`\bar x = A\hat x + B^u u` and a factor of :math:`\bar P = APA^T + Q`.

    With :math:`P = SS^T` and :math:`Q = Q^{1/2}Q^{1/2\,T}`, the QR factorization

    .. math::

        \begin{bmatrix} S^T A^T \\ Q^{1/2\,T} \end{bmatrix} = \mathcal Q\,U, \qquad
        U^TU = A S S^T A^T + Q = \bar P,

    gives the new lower factor :math:`\bar S = U^T`, so :math:`\bar P = \bar S\bar S^T` is
    PSD by construction. ``x`` (N, n), ``S`` (N, n, n); ``A`` (n, n); ``Qroot`` (n, q) with
    ``Qroot @ Qroot.T`` the noise covariance B Q B^T. Returns x̄ (N, n) and S̄ (N, n, n),
    lower triangular, determined up to the signs of its columns (which do not change S̄S̄^T).
    """
    xp = x @ A.T + bx
    top = np.swapaxes(A @ S, -1, -2)
    bottom = np.broadcast_to(Qroot.T, top.shape[:-2] + Qroot.T.shape)
    U = np.linalg.qr(np.concatenate([top, bottom], axis=-2), mode="r")
    return xp, np.swapaxes(U, -1, -2)


def process_roots(system):
    r"""The roots :math:`G_k` (n, q), :math:`G_kG_k^T = B_kQ_kB_k^T`, of the process noise, as a function of k.

    :math:`B_k Q_k^{1/2}` with :math:`Q_k^{1/2}` from :func:`psd_sqrt` (so a singular Q,
    e.g. one with zero rows, is fine); factored once when Q and B do not vary with k.
    """
    def root(k: int) -> np.ndarray:
        r = psd_sqrt(system.Q.at(k))
        return r if system.B is None else system.B.at(k) @ r

    if not system.Q.varying and (system.B is None or not system.B.varying):
        fixed = root(0)
        return lambda k: fixed
    return root


def _solve_upper(U: np.ndarray, B: np.ndarray) -> np.ndarray:
    """X with U X = B for upper-triangular U (..., m, m), B (..., m, r): back substitution over m."""
    m = U.shape[-1]
    X = np.empty(np.broadcast_shapes(U.shape[:-2], B.shape[:-2]) + B.shape[-2:])
    for i in range(m - 1, -1, -1):
        acc = B[..., i, :] - np.einsum("...j,...jr->...r", U[..., i, i + 1:], X[..., i + 1:, :])
        X[..., i, :] = acc / U[..., i, i, None]
    return X


def sqrt_update(x: np.ndarray, S: np.ndarray, innov: np.ndarray, H: np.ndarray, R: np.ndarray,
                valid: np.ndarray | None = None, *, R_root: np.ndarray | None = None):
    r"""Square-root (array) form of the Kalman measurement update, batched, with per-run channel masks.

    With the prior factor :math:`\bar P = \bar S\bar S^T` and :math:`R = R^{1/2}R^{1/2\,T}`,
    one QR factorization of the pre-array

    .. math::

        \begin{bmatrix} R^{1/2\,T} & 0 \\ \bar S^T H^T & \bar S^T \end{bmatrix}
        = \mathcal Q \begin{bmatrix} U_{11} & U_{12} \\ 0 & U_{22} \end{bmatrix}

    gives, by comparing :math:`M^TM = U^TU`,
    :math:`U_{11}^TU_{11} = R_{ee} = H\bar PH^T + R`, :math:`U_{12}^TU_{11} = \bar PH^T` and
    :math:`U_{22}^TU_{22} = \bar P - \bar PH^TR_{ee}^{-1}H\bar P = P`. Hence
    :math:`K = \bar PH^TR_{ee}^{-1} = U_{12}^TU_{11}^{-T}` (one triangular solve,
    :math:`K^T = U_{11}^{-1}U_{12}`), :math:`\hat x = \bar x + Ke` and the new factor
    :math:`S = U_{22}^T`. The covariance :math:`P = SS^T` is PSD by construction. Cost per
    run: a QR of an (m+n) x (m+n) matrix, about :math:`\tfrac43(m+n)^3` flops, against
    :math:`\approx 2n^2m + nm^2` for the standard update.

    Channels are left out exactly as in :func:`gain_update`: a channel that is not
    ``valid`` or whose :math:`R_{ee,ll} = (H\bar P H^T)_{ll} + R_{ll}` is not above the
    smallest normal number gets a zero row of H, a unit noise decoupled from the other
    channels (its rows and columns of R replaced by the identity) and a zero innovation;
    its column of the pre-array is then a unit vector orthogonal to the others, so its gain
    column is exactly zero and the other channels' update is that of the reduced model.

    Parameters
    ----------
    x : (N, n) ; S : (N or 1, n, n) prior factor ; innov : (N, m)
    H : (N or 1, m, n) ; R : (N or 1, m, m) measurement-noise covariance (PSD)
    valid : (N, m) bool, optional
    R_root : (N or 1, m, m), optional
        A root of ``R`` to use when no channel is left out (saves a factorization).

    Returns
    -------
    x : (N, n) ; P : (N or 1, n, n) symmetric ; S : (N or 1, n, n) ; K : (N or 1, n, m)
    """
    m, n = H.shape[-2], H.shape[-1]
    HS = H @ S
    Rdiag = np.diagonal(R, axis1=-2, axis2=-1)
    diag = np.einsum("...ij,...ij->...i", HS, HS) + Rdiag
    degenerate = ~(diag > np.finfo(np.float64).tiny)
    e = innov
    if valid is None and not degenerate.any():
        root = psd_sqrt(R) if R_root is None else R_root
    else:
        ok = ~degenerate if valid is None else (valid & ~degenerate)
        HS = HS * ok[..., :, None]
        e = np.where(ok, innov, 0.0)
        off_diagonal = np.count_nonzero(R - Rdiag[..., :, None] * np.eye(m)) > 0
        if off_diagonal:
            pair = ok[..., :, None] & ok[..., None, :]
            root = psd_sqrt(np.where(pair, R, np.eye(m)))
        else:
            root = np.sqrt(np.where(ok, Rdiag, 1.0))[..., :, None] * np.eye(m)
    batch = np.broadcast_shapes(HS.shape[:-2], S.shape[:-2], root.shape[:-2])
    M = np.zeros(batch + (m + n, m + n))
    M[..., :m, :m] = np.swapaxes(root, -1, -2)
    M[..., m:, :m] = np.swapaxes(HS, -1, -2)
    M[..., m:, m:] = np.swapaxes(S, -1, -2)
    U = np.linalg.qr(M, mode="r")
    K = np.swapaxes(_solve_upper(U[..., :m, :m], U[..., :m, m:]), -1, -2)
    S_new = np.swapaxes(U[..., m:, m:], -1, -2)
    x_new = x + np.einsum("...ij,...j->...i", K, e)
    return x_new, symmetrize(S_new @ np.swapaxes(S_new, -1, -2)), S_new, K


def check_prior(system, x0: Any, P0: Any, runs: int, batch: tuple[int, ...] | None = None):
    """Initial (x0, P0) broadcast to ``(N, n)``, ``(N, n, n)``; defaults from the system.

    With ``batch`` (the leading shape of ``y``, N = prod(batch)), per-run priors of shape
    ``batch + (n,)`` / ``batch + (n, n)`` (or broadcastable to them) are accepted.
    """
    n = system.n
    x = system.x0 if x0 is None else as_float_array(x0, "x0")
    P = system.P0 if P0 is None else as_float_array(P0, "P0")
    if P0 is not None and P.ndim >= 2:
        check_psd(P, "P0")
    if x.shape[-1:] != (n,) or P.shape[-2:] != (n, n):
        raise ShapeError(f"x0/P0: expected (..., {n}) and (..., {n}, {n}), got {x.shape} and {P.shape}")
    try:
        if batch is not None:  # priors laid out like y's leading axes; else flat (N, ...) as before
            try:
                x = np.broadcast_to(x, tuple(batch) + (n,)).reshape(runs, n)
            except ValueError:
                pass
            try:
                P = np.broadcast_to(P, tuple(batch) + (n, n)).reshape(runs, n, n)
            except ValueError:
                pass
        x = np.broadcast_to(x, (runs, n)).copy()
        P = np.broadcast_to(P, (runs, n, n)).copy()
    except ValueError:
        raise ShapeError(f"x0/P0: batch shapes {x.shape[:-1]} / {P.shape[:-2]} do not match {runs} runs") from None
    return x, P


def check_keywords(options: dict[str, Any], allowed: dict[str, tuple]) -> None:
    """Check each option value against its allowed set."""
    for key, value in options.items():
        if key not in allowed:
            raise TypeError(f"unexpected keyword argument {key!r}")
        check_option(value, key, allowed[key])      # of the same kind: 1.0 is not True
