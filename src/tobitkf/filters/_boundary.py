"""What enters a filter call, checked at the door: the readings (:func:`prepare_measurements`), the inputs
(:func:`prepare_inputs`), the prior (:func:`check_prior`), the options (:func:`check_keywords`) and the noise
roots (:func:`process_roots`); :mod:`tobitkf.filters.core` re-exports them for the families."""

from __future__ import annotations

from typing import Any

import numpy as np

from .._linalg import psd_sqrt
from .._validation import (
    ShapeError,
    ValidationError,
    as_float_array,
    check_memory,
    check_option,
    check_psd,
    check_scale,
)

__all__ = ["prepare_measurements", "prepare_inputs", "check_prior", "check_keywords", "process_roots"]

# --------------------------------------------------------------------------- boundary checks


def prepare_measurements(
    y: Any, m: int, name: str = "y", *, allow_nan: bool = True
) -> tuple[np.ndarray, tuple[int, ...]]:
    """Validate ``y`` of shape ``(..., T, m)`` and flatten the batch axes.

    NaN entries are allowed (missing samples) unless ``allow_nan`` is False; infinities are not, nor are
    readings beyond :data:`~tobitkf._validation.READING_LIMIT` in magnitude (their squares overflow). The
    masked entries of a numpy masked array are missing (NaN).

    Returns
    -------
    y2 : (N, T, m) ndarray
    batch_shape : tuple
        The leading shape to restore on outputs (``()`` for a single ``(T, m)`` record).
    """
    if isinstance(y, np.ndarray) and not y.flags.c_contiguous:
        # a broadcast or strided view: the flat layout and the compiled loops copy it. Refused before its values
        # are read (a broadcast of 10^10 readings takes minutes to scan) or converted (a copy)
        check_memory(8 * y.size, name, f"the readings of shape {y.shape} as one contiguous array")
    arr = as_float_array(y, name, allow_nan=allow_nan)
    check_scale(arr, name)
    if arr.ndim < 2:
        raise ShapeError(
            f"{name}: expected (..., T, {m}) (for one scalar channel pass y[:, None]), got shape {arr.shape}"
        )
    if arr.shape[-1] != m:
        raise ShapeError(f"{name}: expected last axis of length m={m} (measurement channels), got shape {arr.shape}")
    if arr.shape[-2] < 1:
        raise ShapeError(f"{name}: expected at least one time step, got shape {arr.shape}")
    batch = arr.shape[:-2]
    if 0 in batch:
        raise ShapeError(f"{name}: expected at least one run (leading axes of positive length), got shape {arr.shape}")
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


def check_prior(system, x0: Any, P0: Any, runs: int, batch: tuple[int, ...] | None = None):
    """Initial (x0, P0) broadcast to ``(N, n)``, ``(N, n, n)``; defaults from the system.

    With ``batch`` (the leading shape of ``y``, N = prod(batch)), per-run priors of shape
    ``batch + (n,)`` / ``batch + (n, n)`` (or broadcastable to them) are accepted.
    """
    n = system.n
    check_runs = getattr(system, "check_runs", None)  # a system with one model per run fits y's runs
    if check_runs is not None:
        check_runs(tuple(batch) if batch is not None else (runs,))
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
        check_option(value, key, allowed[key])  # of the same kind: 1.0 is not True


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


def _noise_variances(R: np.ndarray, name: str, positive: str | None = None) -> np.ndarray:
    """The diagonal of a measurement covariance ``R`` (m, m) the channels are updated from in sequence.

    Raises ValidationError naming ``name`` for an off-diagonal entry (beyond 1e-12 of the largest) or a
    negative variance; with ``positive`` (the filter's name, e.g. ``"the protocol filter"``) also for a zero one.
    """
    d = np.diagonal(R, axis1=-2, axis2=-1).copy()  # (m,), or (N or 1, m) with one R per run
    off = R - d[..., :, None] * np.eye(R.shape[-1])
    diagonal = np.abs(off).max(initial=0.0) <= 1e-12 * max(1.0, np.abs(R).max())
    if positive is not None and (not diagonal or np.any(d <= 0)):
        raise ValidationError(f"{name}: {positive} needs a diagonal R with positive sensor variances")
    if not diagonal:
        raise ValidationError(
            f"{name}: the assumed-density filter processes the channels in sequence and needs a diagonal R"
        )
    if np.any(d < 0):
        raise ValidationError(f"{name}: expected measurement variances >= 0, got {d}")
    return d
