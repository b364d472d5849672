r"""Monte Carlo error metrics over a batch of runs.

For truth :math:`x^{(i)}_k` and estimates :math:`\hat x^{(i)}_k`, i = 1..N runs:

.. math::

    \mathrm{RMSE}_k(j) = \Big(\frac1N\sum_i (\hat x^{(i)}_k(j) - x^{(i)}_k(j))^2\Big)^{1/2}, \qquad
    \mathrm{bias}_k(j) = \frac1N\sum_i (\hat x^{(i)}_k(j) - x^{(i)}_k(j)), \\
    \mathrm{NEES}_k = \frac1N\sum_i e^{(i)T}_k P^{(i)-1}_k e^{(i)}_k \quad (\approx n \text{ for a consistent filter}).

The time average of the RMSE is :math:`\frac1T\sum_k \mathrm{RMSE}_k(j)` (the
convention of the sources' "RMSE over k" plots averaged over the horizon).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ._validation import ShapeError, ValidationError

__all__ = ["rmse", "bias", "nees", "nees_terms", "summarize", "align_truth"]


def align_truth(truth: np.ndarray, estimate: np.ndarray) -> np.ndarray:
    """Drop x_0 from a ``(N, T+1, n)`` truth so it lines up with ``(N, T, n)`` estimates."""
    truth = np.asarray(truth, dtype=float)
    if estimate.ndim < 3:
        raise ShapeError(f"estimate: expected (N, T, n) with runs on the first axis (one run: add a leading "
                         f"axis), got shape {estimate.shape}")
    if truth.shape[-2] == estimate.shape[-2] + 1:
        truth = truth[..., 1:, :]
    if truth.shape[-2:] != estimate.shape[-2:]:
        raise ShapeError(f"truth: shape {truth.shape} does not match estimates {estimate.shape}")
    return truth


def rmse(truth: Any, estimate: Any) -> np.ndarray:
    """Per-step RMSE over runs (axis 0) of each state component: ``(T, n)``."""
    est = np.asarray(estimate, dtype=float)
    err = est - align_truth(truth, est)
    return np.sqrt(np.mean(err**2, axis=0))


def bias(truth: Any, estimate: Any) -> np.ndarray:
    """Per-step mean error over runs: ``(T, n)``."""
    est = np.asarray(estimate, dtype=float)
    return np.mean(est - align_truth(truth, est), axis=0)


def nees_terms(err: np.ndarray, cov: np.ndarray) -> np.ndarray:
    r"""Per-run, per-step :math:`e^T P^{-1} e` for errors ``(..., n)`` and covariances ``(..., n, n)``.

    ``cov`` broadcasts against ``err`` (a covariance shared by the runs may omit the run axis).
    A linear solve per run and step (never an inverse); a singular covariance gives ``inf`` for
    its own term only. Uses the compiled kernel
    :func:`tobitkf._linalg_kernels.nees_terms` when numba is installed and ``cov``'s leading
    shape is a trailing part of ``err``'s, else ``numpy.linalg.solve``; both agree to rounding.

    Raises
    ------
    ShapeError
        ``cov`` is not ``(..., n, n)`` for errors of dimension n, or does not broadcast
        against ``err``.
    """
    err = np.asarray(err, dtype=float)
    cov = np.asarray(cov, dtype=float)
    n = err.shape[-1] if err.ndim else 0
    if err.ndim < 1 or cov.ndim < 2 or cov.shape[-2:] != (n, n):
        raise ShapeError(f"cov: expected (..., {n}, {n}) for errors of shape {err.shape}, got {cov.shape}")
    try:
        np.broadcast_shapes(err.shape[:-1], cov.shape[:-2])
    except ValueError:
        raise ShapeError(f"cov: leading shape {cov.shape[:-2]} does not broadcast against the errors' "
                         f"{err.shape[:-1]}") from None
    while cov.ndim > 2 and cov.strides[0] == 0:    # a covariance shared by the runs, broadcast
        cov = cov[0]                                # (as the KF returns it): keep one copy
    lead, clead = err.shape[:-1], cov.shape[:-2]
    if cov.shape[-2:] == (n, n) and len(clead) <= len(lead) and lead[len(lead) - len(clead):] == clead:
        from ._compiled import numba_available

        if numba_available():
            from ._linalg_kernels import nees_terms as kernel

            out = np.empty(int(np.prod(lead)))
            kernel(np.ascontiguousarray(err.reshape(-1, n)), np.ascontiguousarray(cov.reshape(-1, n, n)), out)
            return out.reshape(lead)
    try:
        sol = np.linalg.solve(cov, err[..., None])[..., 0]
        return np.einsum("...i,...i->...", err, sol)
    except np.linalg.LinAlgError:
        # one singular matrix makes the batched solve fail for all: redo per run and step
        covb = np.broadcast_to(cov, err.shape + err.shape[-1:])
        val = np.empty(err.shape[:-1])
        for idx in np.ndindex(val.shape):
            try:
                val[idx] = err[idx] @ np.linalg.solve(covb[idx], err[idx])
            except np.linalg.LinAlgError:
                val[idx] = np.inf
        return val


def nees(truth: Any, estimate: Any, cov: Any) -> np.ndarray:
    """Per-step average normalized estimation error squared over runs: ``(T,)``.

    Uses a linear solve per run and step (:func:`nees_terms`); singular covariances give ``inf``.

    Raises
    ------
    ValidationError
        A covariance that is not symmetric positive semi-definite (its NEES would be negative or
        meaningless), naming the first (run, step) where it is not.
    """
    est = np.asarray(estimate, dtype=float)
    err = est - align_truth(truth, est)
    _check_psd_each(np.asarray(cov, dtype=float), "cov")
    return np.mean(nees_terms(err, cov), axis=0)


def _check_psd_each(cov: np.ndarray, name: str, rtol: float = 1e-9) -> None:
    """Raise naming the first index of ``cov`` (..., n, n) that is not symmetric PSD."""
    if cov.ndim < 2 or cov.shape[-1] != cov.shape[-2] or not np.all(np.isfinite(cov)):
        return                                  # shapes are nees_terms' to refuse; NaN stays NaN
    scale = np.maximum(np.abs(cov).max(axis=(-1, -2)), np.finfo(float).tiny)
    asym = np.abs(cov - np.swapaxes(cov, -1, -2)).max(axis=(-1, -2))
    low = np.linalg.eigvalsh(0.5 * (cov + np.swapaxes(cov, -1, -2))).min(axis=-1)
    bad = (asym > rtol * scale) | (low < -rtol * scale)
    if np.any(bad):
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        what = "not symmetric" if asym[idx] > rtol * scale[idx] else f"indefinite (smallest eigenvalue {low[idx]:.3g})"
        raise ValidationError(f"{name}: expected symmetric positive semi-definite covariances, the one at index {idx} "
                              f"is {what}")


def summarize(truth: Any, estimate: Any, cov: Any | None = None, *, skip: int = 0) -> dict[str, Any]:
    """RMSE per step and component, its time average, bias and (if ``cov``) NEES, as a JSON-able dict.

    ``skip`` leaves the first steps out of the time averages (not out of the per-step arrays).
    """
    r = rmse(truth, estimate)
    if isinstance(skip, bool) or not isinstance(skip, (int, np.integer)) or not 0 <= skip < r.shape[0]:
        raise ValidationError(f"skip: expected an integer in [0, {r.shape[0]}) (steps to leave out of the "
                              f"time averages), got {skip!r}")
    out = {
        "rmse": r,
        "rmse_time_avg": r[skip:].mean(axis=0),
        "bias": bias(truth, estimate),
        "bias_time_avg": bias(truth, estimate)[skip:].mean(axis=0),
    }
    if cov is not None:
        ne = nees(truth, estimate, cov)
        out["nees"] = ne
        out["nees_time_avg"] = float(np.mean(ne[skip:]))
    return out
