r"""Monte Carlo error metrics over a batch of runs.

For truth :math:`x^{(i)}_k` and estimates :math:`\hat x^{(i)}_k`, i = 1..N runs:

.. math::

    \mathrm{RMSE}_k(j) = \Big(\frac1N\sum_i (\hat x^{(i)}_k(j) - x^{(i)}_k(j))^2\Big)^{1/2}, \qquad
    \mathrm{bias}_k(j) = \frac1N\sum_i (\hat x^{(i)}_k(j) - x^{(i)}_k(j)), \\
    \mathrm{NEES}_k = \frac1N\sum_i e^{(i)T}_k P^{(i)-1}_k e^{(i)}_k \quad (\approx n \text{ for a consistent filter}).

The time average of the RMSE is :math:`\frac1T\sum_k \mathrm{RMSE}_k(j)` (the
convention of the sources' "RMSE over k" plots averaged over the horizon).

Alignment: every function takes the estimate as an array or as an estimator's
:class:`~tobitkf.filters.core.FilterResult`, whose ``times`` say which time each row estimates, so
the truth (``(N, K, n)`` holding the states at times 0, 1, ..., as every simulator returns them) is
read at exactly those times: ``truth[:, result.times]``. With a bare array and no ``times``, a truth
with one row more than the estimate is taken to start at x_0 (the package convention).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ._validation import ShapeError, ValidationError

__all__ = ["rmse", "bias", "nees", "nees_terms", "summarize", "align_truth"]


def _unpack(estimate: Any, cov: Any = None, times: Any = None):
    """(mean, cov, times) of a FilterResult, or the arrays as given."""
    if hasattr(estimate, "mean") and hasattr(estimate, "times") and not isinstance(estimate, np.ndarray):
        return (
            np.asarray(estimate.mean, dtype=float),
            estimate.cov if cov is None else cov,
            estimate.times if times is None else times,
        )
    return np.asarray(estimate, dtype=float), cov, times


def align_truth(truth: np.ndarray, estimate: np.ndarray, times: Any = None) -> np.ndarray:
    """The truth at the estimate's rows: ``truth[..., times, :]`` when ``times`` are given (the time of
    each row, e.g. ``FilterResult.times``); otherwise drop x_0 from a ``(N, T+1, n)`` truth so it lines
    up with ``(N, T, n)`` estimates.

    Raises
    ------
    ShapeError
        Estimates without a run axis, truth that does not cover the times, or shapes that do not match.
    """
    truth = np.asarray(truth, dtype=float)
    if times is not None:
        t = np.asarray(times, dtype=int)
        if t.ndim != 1 or t.shape[0] != estimate.shape[-2]:
            raise ShapeError(f"times: expected one time per row of the estimates ({estimate.shape[-2]}), got {t.shape}")
        if t.min(initial=0) < 0 or t.max(initial=0) >= truth.shape[-2]:
            raise ShapeError(
                f"truth: holds times 0..{truth.shape[-2] - 1}, the estimates need {t.min()}..{t.max()} "
                "(for the delay family, whose first reading is y(0), the truth starts at x(0))"
            )
        truth = truth[..., t, :]
        if truth.shape[-2:] != estimate.shape[-2:]:
            raise ShapeError(f"truth: shape {truth.shape} does not match estimates {estimate.shape}")
        return truth
    if estimate.ndim < 3:
        raise ShapeError(
            f"estimate: expected (N, T, n) with runs on the first axis (one run: add a leading "
            f"axis), got shape {estimate.shape}"
        )
    if truth.shape[-2] == estimate.shape[-2] + 1:
        truth = truth[..., 1:, :]
    if truth.shape[-2:] != estimate.shape[-2:]:
        raise ShapeError(f"truth: shape {truth.shape} does not match estimates {estimate.shape}")
    return truth


def rmse(truth: Any, estimate: Any, *, times: Any = None) -> np.ndarray:
    """Per-step RMSE over runs (axis 0) of each state component: ``(T, n)``.

    ``estimate`` is an array ``(N, T, n)`` or a :class:`~tobitkf.filters.core.FilterResult` (aligned by
    its ``times``)."""
    est, _, times = _unpack(estimate, times=times)
    err = est - align_truth(truth, est, times)
    return np.sqrt(np.mean(err**2, axis=0))


def bias(truth: Any, estimate: Any, *, times: Any = None) -> np.ndarray:
    """Per-step mean error over runs: ``(T, n)`` (``estimate`` as in :func:`rmse`)."""
    est, _, times = _unpack(estimate, times=times)
    return np.mean(est - align_truth(truth, est, times), axis=0)


def nees_terms(err: np.ndarray, cov: np.ndarray) -> np.ndarray:
    r"""Per-run, per-step :math:`e^T P^{-1} e` for errors ``(..., n)`` and covariances ``(..., n, n)``.

    ``cov`` broadcasts against ``err`` (a covariance shared by the runs may omit the run axis).
    A linear solve per run and step (never an inverse); a singular covariance gives ``inf`` for
    its own term only. Uses the compiled kernel
    :func:`tobitkf._compiled_linalg.nees_terms` when numba is installed and ``cov``'s leading
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
        raise ShapeError(
            f"cov: leading shape {cov.shape[:-2]} does not broadcast against the errors' {err.shape[:-1]}"
        ) from None
    while cov.ndim > 2 and cov.strides[0] == 0:  # a covariance shared by the runs, broadcast
        cov = cov[0]  # (as the KF returns it): keep one copy
    lead, clead = err.shape[:-1], cov.shape[:-2]
    if cov.shape[-2:] == (n, n) and len(clead) <= len(lead) and lead[len(lead) - len(clead) :] == clead:
        from ._compiled import numba_available

        if numba_available():
            from ._compiled_linalg import nees_terms as kernel

            out = np.empty(int(np.prod(lead)))
            # C-contiguous and writable, as numba types a read-only array (a broadcast covariance) apart
            flat_err, flat_cov = (np.require(a, float, ("C", "W")) for a in (err.reshape(-1, n), cov.reshape(-1, n, n)))
            kernel(flat_err, flat_cov, out)
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


def nees(truth: Any, estimate: Any, cov: Any = None, *, times: Any = None) -> np.ndarray:
    """Per-step average normalized estimation error squared over runs: ``(T,)``.

    Uses a linear solve per run and step (:func:`nees_terms`); singular covariances give ``inf``.
    ``estimate`` as in :func:`rmse` (a FilterResult brings its own ``cov``).

    Raises
    ------
    ValidationError
        A covariance that is not symmetric positive semi-definite (its NEES would be negative or
        meaningless), naming the first (run, step) where it is not.
    """
    est, cov, times = _unpack(estimate, cov, times)
    if cov is None:
        raise ValidationError("cov: expected the estimates' covariances (..., T, n, n)")
    err = est - align_truth(truth, est, times)
    _check_psd_each(np.asarray(cov, dtype=float), "cov")
    return np.mean(nees_terms(err, cov), axis=0)


def _check_psd_each(cov: np.ndarray, name: str, rtol: float = 1e-9) -> None:
    """Raise naming the first index of ``cov`` (..., n, n) that is not symmetric PSD."""
    if cov.ndim < 2 or cov.shape[-1] != cov.shape[-2] or not np.all(np.isfinite(cov)):
        return  # shapes are nees_terms' to refuse; NaN stays NaN
    lead = 0
    while cov.ndim > 2 and cov.strides[0] == 0:  # a covariance shared by the runs: check the one copy
        cov = cov[0]
        lead += 1
    scale = np.maximum(np.abs(cov).max(axis=(-1, -2)), np.finfo(float).tiny)
    asym = np.abs(cov - np.swapaxes(cov, -1, -2)).max(axis=(-1, -2))
    low = np.linalg.eigvalsh(0.5 * (cov + np.swapaxes(cov, -1, -2))).min(axis=-1)
    bad = (asym > rtol * scale) | (low < -rtol * scale)
    if np.any(bad):
        idx = (0,) * lead + tuple(int(i) for i in np.argwhere(bad)[0])
        what = (
            "not symmetric"
            if np.any(asym > rtol * scale) and asym[tuple(idx[lead:])] > rtol * scale[tuple(idx[lead:])]
            else f"indefinite (smallest eigenvalue {low[tuple(idx[lead:])]:.3g})"
        )
        raise ValidationError(
            f"{name}: expected symmetric positive semi-definite covariances, the one at index {idx} is {what}"
        )


def summarize(truth: Any, estimate: Any, cov: Any | None = None, *, skip: int = 0, times: Any = None) -> dict[str, Any]:
    """RMSE per step and component, its time average, bias and (if ``cov``) NEES, as a JSON-able dict.

    ``estimate`` is an array or a :class:`~tobitkf.filters.core.FilterResult` (aligned by its ``times``;
    its ``cov`` is used for the NEES unless ``cov`` is given). ``skip`` leaves the first steps out of
    the time averages (not out of the per-step arrays).
    """
    estimate, res_cov, times = _unpack(estimate, None, times)
    if cov is None:
        cov = res_cov
    r = rmse(truth, estimate, times=times)
    if isinstance(skip, bool) or not isinstance(skip, (int, np.integer)) or not 0 <= skip < r.shape[0]:
        raise ValidationError(
            f"skip: expected an integer in [0, {r.shape[0]}) (steps to leave out of the time averages), got {skip!r}"
        )
    out = {
        "rmse": r,
        "rmse_time_avg": r[skip:].mean(axis=0),
        "bias": bias(truth, estimate, times=times),
        "bias_time_avg": bias(truth, estimate, times=times)[skip:].mean(axis=0),
    }
    if cov is not None:
        ne = nees(truth, estimate, cov, times=times)
        out["nees"] = ne
        out["nees_time_avg"] = float(np.mean(ne[skip:]))
    return out
