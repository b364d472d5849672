r"""Small pure helpers shared by the smoothers, likelihoods and fits (batched over leading axes).

* :func:`censoring_sides`: which readings are censored and at which limit, from an explicit
  indicator or (the default) from the limit rule;
* :func:`gaussian_log_density`: :math:`\log N(e; 0, S)` over the observed channels only;
* :func:`solve_psd`: :math:`S^{-1}B` for symmetric PSD :math:`S`, a pseudo-inverse where singular;
* :func:`assumed_density_filter`: the package's one assumed-density filter as the smoothers,
  likelihoods and fits run it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._validation import ShapeError, ValidationError

__all__ = ["censoring_sides", "gaussian_log_density", "solve_psd", "assumed_density_filter", "LOG_2PI"]

LOG_2PI = float(np.log(2.0 * np.pi))


def assumed_density_filter(system, censoring, *, covariance_update: str = "standard"):
    r"""The :class:`~tobitkf.AssumedDensityTobitFilter` of the smoothers, likelihoods and fits: the
    uncensored readings of a step first, then the censored ones (``order="uncensored_first"``), so that
    a step with one censored reading has the exact moments of its posterior under the Gaussian
    prediction and the exact predictive log-likelihood term
    :math:`\log N(y_{k,u}; \hat y_u, S_{uu}) + \log\Phi(\pm(\text{limit} - \mu)/s)`.

    Parameters
    ----------
    system : LinearSystem
        R diagonal (channels in sequence); R = 0 allowed.
    censoring : Censoring
    covariance_update : {"standard", "joseph", "square_root"}, default "standard"

    Returns
    -------
    AssumedDensityTobitFilter

    Raises
    ------
    ValidationError
        The filter's own: non-diagonal or negative R, an unknown option.
    """
    from ..filters.assumed_density import AssumedDensityTobitFilter

    return AssumedDensityTobitFilter(system, censoring, covariance_update=covariance_update, order="uncensored_first")


def censoring_sides(
    y: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    censored: Any = None,
    *,
    rtol: float = 1e-12,
    name: str = "censored",
) -> np.ndarray:
    r"""Side of each reading: 0 uncensored (or missing), -1 censored at ``lower``, +1 at ``upper``.

    Parameters
    ----------
    y : (..., T, m) ndarray
        Readings; NaN = missing (side 0).
    lower, upper : broadcastable to y
        The limits of each reading.
    censored : (..., T, m) bool array_like, optional
        The censoring indicator recorded with the data. Default: the limit rule, a reading within
        ``rtol * max(1, |limit|)`` of a finite limit is censored (as
        :meth:`~tobitkf.Censoring.censored_mask`). With an indicator, a flagged reading is censored at
        the limit it lies at or beyond (within the same tolerance); an unflagged reading is
        uncensored even when it equals a limit (e.g. the 8 such readings of the cloud-ceiling data).

    Returns
    -------
    (..., T, m) int8 ndarray

    Raises
    ------
    ShapeError
        ``censored`` does not have the shape of ``y``.
    ValidationError
        ``censored`` is not boolean (or 0/1), or flags a missing reading or one strictly inside its
        limits.
    """
    lo = np.broadcast_to(lower, y.shape)
    hi = np.broadcast_to(upper, y.shape)
    tol_lo = rtol * np.maximum(1.0, np.abs(np.where(np.isfinite(lo), lo, 0.0)))
    tol_hi = rtol * np.maximum(1.0, np.abs(np.where(np.isfinite(hi), hi, 0.0)))
    with np.errstate(invalid="ignore"):
        at_lo = np.isfinite(lo) & (y <= lo + tol_lo)
        at_hi = np.isfinite(hi) & (y >= hi - tol_hi)
    if censored is None:
        flag = at_lo | at_hi
    else:
        flag = _as_indicator(censored, y.shape, name)
        bad = flag & np.isnan(y)
        if bad.any():
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            raise ValidationError(f"{name}: reading at index {idx} is flagged censored but missing (NaN)")
        bad = flag & ~(at_lo | at_hi)
        if bad.any():
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            raise ValidationError(
                f"{name}: reading {y[idx]:.6g} at index {idx} is flagged censored but lies strictly "
                f"inside its limits [{lo[idx]:.6g}, {hi[idx]:.6g}]"
            )
    side = np.zeros(y.shape, dtype=np.int8)
    side[flag & at_lo] = -1
    side[flag & ~at_lo & at_hi] = 1
    return side


def _as_indicator(censored: Any, shape: tuple[int, ...], name: str) -> np.ndarray:
    arr = np.asarray(censored)
    if arr.dtype != bool:
        if not np.issubdtype(arr.dtype, np.number) or not np.isin(arr, (0, 1)).all():
            raise ValidationError(f"{name}: expected a boolean indicator (True = censored) or 0/1 values")
        arr = arr.astype(bool)
    try:
        return np.broadcast_to(arr, shape)
    except ValueError:
        raise ShapeError(f"{name}: expected the shape of y {shape}, got {arr.shape}") from None


def gaussian_log_density(e: np.ndarray, S: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    r""":math:`\log N(e_o; 0, S_{oo})` of the valid channels o, batched.

    .. math::

        \ell = -\tfrac12\big(|o|\log 2\pi + \log\det S_{oo} + e_o^TS_{oo}^{-1}e_o\big)

    Parameters
    ----------
    e : (N, m) ndarray
        Innovations (entries of invalid channels are ignored).
    S : (N or 1, m, m) ndarray
        Innovation covariances.
    valid : (N, m) bool ndarray, optional
        Channels that take part; default every channel. A run without a valid channel gives 0.

    Returns
    -------
    (N,) ndarray
        ``-inf`` where :math:`S_{oo}` is singular and the innovation leaves its range.
    """
    m = e.shape[-1]
    if valid is None:
        valid = np.ones(e.shape, dtype=bool)
    e = np.where(valid, e, 0.0)
    if m == 1:
        s = S[..., 0, 0]
        v = valid[..., 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            ll = -0.5 * (LOG_2PI + np.log(s) + e[..., 0] ** 2 / s)
        ll = np.where(s > 0, ll, np.where(e[..., 0] == 0, 0.0, -np.inf))
        return np.where(v, ll, 0.0)
    pair = valid[..., :, None] & valid[..., None, :]
    Sm = np.where(pair, S, np.eye(m))
    sign, logdet = np.linalg.slogdet(Sm)
    quad = np.einsum("...i,...i->...", e, _solve_or_inf(Sm, e))
    ll = -0.5 * (valid.sum(-1) * LOG_2PI + logdet + quad)
    return np.where(sign > 0, ll, -np.inf)


def _solve_or_inf(S: np.ndarray, e: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.solve(S, e[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return np.einsum("...ij,...j->...i", np.linalg.pinv(S, hermitian=True), e)


def solve_psd(S: np.ndarray, B: np.ndarray) -> np.ndarray:
    r""":math:`S^{-1}B` for symmetric PSD ``S`` (..., n, n), ``B`` (..., n, r), batched.

    A Cholesky factorization certifies a positive definite ``S`` (then an LU solve); a singular
    ``S`` (a predicted covariance :math:`AP A^T + Q` with a singular Q after an exact reading) takes
    the pseudo-inverse, which is what the RTS gain needs: the range of :math:`A P` lies in the range
    of :math:`APA^T + Q`.
    """
    try:
        np.linalg.cholesky(S)
        return np.linalg.solve(S, B)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(0.5 * (S + np.swapaxes(S, -1, -2)))
        cut = 1e-12 * np.maximum(np.abs(w).max(axis=-1, keepdims=True), np.finfo(float).tiny)
        inv_w = np.where(w > cut, 1.0 / np.where(w > cut, w, 1.0), 0.0)
        return V @ (inv_w[..., :, None] * (np.swapaxes(V, -1, -2) @ B))
