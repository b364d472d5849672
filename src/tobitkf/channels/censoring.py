r"""Tobit censoring of measurements: left, right, two-sided ("saturation"), multi-region.

Miller (2015), Table 1.1 and (3.18), (3.51), (6.59): per channel l,

.. math::

    y_k(l) = \begin{cases} l_k(l) & y^*_k(l) \le l_k(l) \\ y^*_k(l) & l_k(l) < y^*_k(l) < h_k(l) \\
             h_k(l) & y^*_k(l) \ge h_k(l) \end{cases}

with ``lower`` = l (``-inf``: no left censoring) and ``upper`` = h (``+inf``: no
right censoring). Limits are scalars, ``(m,)`` per channel, or ``(T, m)`` per
step and channel (the time-varying limit of Miller §3.4).

Several censored regions for one output (Miller §6.6, "multi-region TKF") are
modelled as the dissertation does: the output is measured by several sensors,
each with its own noise and its own window, stacked as extra channels; see
:func:`multi_region`. The Tobit update itself is unchanged (Miller §6.6).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .._progress import plural
from .._validation import ShapeError, ValidationError, as_float_array
from .base import Channel

__all__ = ["Censoring", "multi_region"]


class Censoring(Channel):
    """Per-channel censoring limits, constant or time-varying.

    Parameters
    ----------
    lower : float or (m,) or (T, m) array_like, default -inf
        Left-censoring limits; ``-inf`` means the channel is not left-censored.
    upper : float or (m,) or (T, m) array_like, default +inf
        Right-censoring limits; ``+inf`` means the channel is not right-censored.

    Raises
    ------
    ShapeError
        If the two limits do not broadcast, or have more than two dimensions.
    ValidationError
        If a limit is NaN, ``lower = +inf``, ``upper = -inf`` or ``lower >= upper``.

    Examples
    --------
    >>> cens = Censoring(lower=0.0)             # left censoring at 0 (Miller Example 1)
    >>> cens.clip(np.array([[-0.3], [0.2]]), k=1).ravel().tolist()
    [0.0, 0.2]
    """

    section = "censoring"
    sweep_options = {"lower": float, "upper": float}

    def __init__(self, lower: Any = -np.inf, upper: Any = np.inf):
        lo = as_float_array(lower, "lower", ndim=(0, 1, 2), allow_inf=True)
        hi = as_float_array(upper, "upper", ndim=(0, 1, 2), allow_inf=True)
        try:
            lo_b, hi_b = np.broadcast_arrays(lo, hi)
        except ValueError:
            raise ShapeError(f"lower/upper: shapes {lo.shape} and {hi.shape} do not broadcast") from None
        if np.isposinf(lo_b).any():
            raise ValidationError("lower: +inf is not a valid lower limit")
        if np.isneginf(hi_b).any():
            raise ValidationError("upper: -inf is not a valid upper limit")
        bad = ~(lo_b < hi_b)
        if bad.any():
            idx = np.argwhere(bad)[0] if bad.ndim else ()
            raise ValidationError(
                f"lower/upper: expected lower < upper, got lower={lo_b[tuple(idx)]} "
                f">= upper={hi_b[tuple(idx)]} at index {tuple(int(i) for i in idx)}"
            )
        self.lower = np.array(lo_b)
        self.upper = np.array(hi_b)
        self.time_varying = self.lower.ndim == 2

    @property
    def channels(self) -> int | None:
        """Number of channels fixed by the limits, or None for scalar limits."""
        return None if self.lower.ndim == 0 else self.lower.shape[-1]

    @property
    def steps(self) -> int | None:
        """Number of steps of time-varying limits, else None."""
        return self.lower.shape[0] if self.time_varying else None

    def check(self, m: Any, steps: int | None = None) -> None:
        """Raise :class:`ShapeError` unless the limits fit ``m`` channels (or a system with ``m``
        outputs) and ``steps`` steps."""
        if not isinstance(m, (int, np.integer)):
            m = m.m
        if self.channels is not None and self.channels not in (1, m):
            raise ShapeError(f"censoring limits: expected {m} channel(s) to match the system, got {self.channels}")
        n_steps = self.steps  # an int whenever the limits are time-varying
        if steps is not None and self.time_varying and n_steps is not None and n_steps < steps:
            raise ShapeError(f"censoring limits: time-varying limits have {plural(n_steps, 'step')}, {steps} needed")

    def limits(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """``(lower, upper)`` for measurement ``y_k`` (k >= 1; array index k-1)."""
        if self.time_varying:
            n_steps = self.steps
            assert n_steps is not None, "time-varying limits have a number of steps"
            if not 1 <= k <= n_steps:
                raise ShapeError(
                    f"censoring limits: time-varying limits have {plural(n_steps, 'step')}, step k={k} requested"
                )
            return self.lower[k - 1], self.upper[k - 1]
        return self.lower, self.upper

    def all_limits(self, steps: int, m: int, *, start: int = 1, check: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Limits broadcast to ``(T, m)`` for k = start..start+T-1 (default k = 1..T); ``check=False`` skips
        :meth:`check` for a caller that made it already (an estimator validates once at its boundary)."""
        if check:
            self.check(m, start - 1 + steps)
        lo = self.lower[start - 1 : start - 1 + steps] if self.time_varying else self.lower
        hi = self.upper[start - 1 : start - 1 + steps] if self.time_varying else self.upper
        return (np.broadcast_to(lo, (steps, m)).copy(), np.broadcast_to(hi, (steps, m)).copy())

    def clip(self, y_latent: np.ndarray, k: int | None = None) -> np.ndarray:
        """Censor latent measurements.

        ``y_latent`` is ``(..., m)`` for a single step ``k``, or ``(..., T, m)``
        with ``k=None`` for a whole record (time-varying limits are aligned
        with the time axis).
        """
        if k is None:
            steps, m = y_latent.shape[-2:]
            lo, hi = self.all_limits(steps, m)
        else:
            lo, hi = self.limits(k)
        return np.minimum(np.maximum(y_latent, lo), hi)

    def censor(self, y_latent: np.ndarray) -> np.ndarray:
        """:meth:`clip` of a whole record ``(..., T, m)`` (the :class:`~tobitkf.channels.base.Channel` stage)."""
        return self.clip(y_latent)

    def censored_mask(self, y: np.ndarray, *, rtol: float = 1e-12, start: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Masks ``(at_lower, at_upper)`` of a record ``(..., T, m)`` reading exactly at a limit.

        A reading counts as censored when it is within ``rtol * max(1, |limit|)`` of the limit
        (ours, not in the source: a reading within ``tol`` of a limit counts as censored). Row 0 is time ``start``.
        """
        steps, m = y.shape[-2:]
        lo, hi = self.all_limits(steps, m, start=start)
        with np.errstate(invalid="ignore"):
            at_lo = np.isfinite(lo) & (y <= lo + rtol * np.maximum(1.0, np.abs(np.where(np.isfinite(lo), lo, 0))))
            at_hi = np.isfinite(hi) & (y >= hi - rtol * np.maximum(1.0, np.abs(np.where(np.isfinite(hi), hi, 0))))
        return at_lo, at_hi

    def check_measurements(self, y: np.ndarray, name: str = "y", *, rtol: float = 1e-9, start: int = 1) -> None:
        """Raise :class:`ValidationError` if a (non-NaN) reading lies outside its limits (row 0 is time ``start``)."""
        steps, m = y.shape[-2:]
        if steps == 1:  # one step (an online step's reading): the same rule in its one-step form
            self.check_reading(y[..., 0, :], start, name, rtol=rtol)
            return
        lo, hi = self.all_limits(steps, m, start=start)
        tol_lo = rtol * np.maximum(1.0, np.abs(np.where(np.isfinite(lo), lo, 0.0)))
        tol_hi = rtol * np.maximum(1.0, np.abs(np.where(np.isfinite(hi), hi, 0.0)))
        # a side whose limits are all infinite cannot be violated (y < -inf, y > inf and NaN compare False):
        # not compared (a left-censored record is one pass over y, not two and an "or")
        bad = np.zeros(y.shape, dtype=bool) if np.isinf(lo).all() else y < lo - tol_lo
        if not np.isinf(hi).all():
            bad |= y > hi + tol_hi
        if bad.any():
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            t, ch = idx[-2], idx[-1]
            raise ValidationError(
                f"{name}: measurement {y[idx]:.6g} at index {idx} lies outside its censoring "
                f"limits [{lo[t, ch]:.6g}, {hi[t, ch]:.6g}]"
            )

    def check_reading(self, y: np.ndarray, k: int, name: str = "y", *, rtol: float = 1e-9) -> None:
        """Raise :class:`ValidationError` if a (non-NaN) reading ``y`` (..., m) of step ``k`` lies outside its
        limits (the one-step form of :meth:`check_measurements`, for online filtering)."""
        cached = self.__dict__.get("_bounds") if not self.time_varying and rtol == 1e-9 else None
        if cached is None:
            lo, hi = self.limits(k)
            tol_lo = rtol * np.maximum(1.0, np.abs(np.where(np.isfinite(lo), lo, 0.0)))
            tol_hi = rtol * np.maximum(1.0, np.abs(np.where(np.isfinite(hi), hi, 0.0)))
            cached = (lo - tol_lo, hi + tol_hi, lo, hi)
            if not self.time_varying and rtol == 1e-9:
                self._bounds = cached  # constant limits: the tolerance band is computed once
        lo_b, hi_b, lo, hi = cached
        m = y.shape[-1]
        if y.size <= 4:  # one reading: Python floats, same verdict
            lists = self.__dict__.get("_bound_lists")
            if lists is None or lists[0] is not cached or len(lists[1]) != m:
                lists = (cached, np.broadcast_to(lo_b, (m,)).tolist(), np.broadcast_to(hi_b, (m,)).tolist())
                if cached is self.__dict__.get("_bounds"):
                    self._bound_lists = lists  # the constant band as lists, made once
            _, lo_l, hi_l = lists
            if not any(v < lo_l[i] or v > hi_l[i] for row in y.reshape(-1, m).tolist() for i, v in enumerate(row)):
                return  # NaN (a missing reading) compares False
        bad = (y < lo_b) | (y > hi_b)  # NaN (a missing reading) compares False
        if bad.any():
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            ch = idx[-1]
            lo_b, hi_b = np.broadcast_to(lo, y.shape[-1:]), np.broadcast_to(hi, y.shape[-1:])
            raise ValidationError(
                f"{name}: measurement {y[idx]:.6g} at step k={k}, channel {ch} lies outside its "
                f"censoring limits [{lo_b[ch]:.6g}, {hi_b[ch]:.6g}]"
            )

    # --- the measurement contract (channels.base) ---------------------------------------------
    def region(self, y: np.ndarray, k: int, l: int) -> tuple[np.ndarray, np.ndarray]:
        """A reading inside the limits is exact (``(y, y)``); one at the lower limit says :math:`y^* \\le l`,
        one at the upper :math:`y^* \\ge h` (within ``1e-12 max(1, |limit|)``, as :meth:`censored_mask`)."""
        lo, hi = (np.broadcast_to(v, (max(self.channels or 1, l + 1),))[l] for v in self.limits(k))
        lo, hi = float(lo), float(hi)
        at_lo = np.isfinite(lo) & (y <= lo + 1e-12 * max(1.0, abs(lo) if np.isfinite(lo) else 0.0))
        at_hi = np.isfinite(hi) & (y >= hi - 1e-12 * max(1.0, abs(hi) if np.isfinite(hi) else 0.0)) & ~at_lo
        return np.where(at_hi, hi, np.where(at_lo, -np.inf, y)), np.where(at_lo, lo, np.where(at_hi, np.inf, y))

    def reading_statistics(
        self, mean: np.ndarray, std: np.ndarray, k: int, l: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The censored reading's mean, slope :math:`\\partial E[y]/\\partial\\mu = P(l < y^* < h)` and
        variance (:func:`tobitkf.censored_moments`: (3.8) in two-sided form, the law of total variance)."""
        from ..censored import unchecked_moments

        lo, hi = (np.broadcast_to(v, (max(self.channels or 1, l + 1),))[l] for v in self.limits(k))
        st = unchecked_moments(mean, std, lo, hi)
        return st.censored_mean, st.p_uncensored, st.censored_var

    def fisher_information(self, mean: np.ndarray, std: np.ndarray, k: int, l: int) -> np.ndarray:
        r"""Fisher information :math:`I_{\mu\mu}` of one censored reading of channel ``l`` at step ``k`` about
        the latent mean, (N,) (:func:`tobitkf.censored_fisher_information` at this channel's limits; without a
        finite limit :math:`1/\sigma^2`): what the PCRLB asks every channel."""
        from ..censored import censored_fisher_information

        lo, hi = (np.broadcast_to(v, (max(self.channels or 1, l + 1),))[l] for v in self.limits(k))
        return censored_fisher_information(mean, std, lo, hi)[0]

    def check_readings(self, y: np.ndarray, start: int = 1, name: str = "y") -> None:
        """:meth:`check_measurements` (the contract's name)."""
        self.check_measurements(y, name, start=start)

    def at_limit(self, y: np.ndarray, start: int = 1) -> np.ndarray:
        """Readings at either limit (:meth:`censored_mask`)."""
        lo, hi = self.censored_mask(y, start=start)
        return lo | hi

    def __repr__(self) -> str:
        def fmt(v):
            return np.array2string(v, threshold=6) if v.ndim else str(float(v))

        return f"Censoring(lower={fmt(self.lower)}, upper={fmt(self.upper)})"


def multi_region(
    system, regions: Sequence[Sequence[tuple[float, float]]], *, noise_var: Sequence[Sequence[float]] | None = None
):
    r"""Model several censored regions of each output as stacked sensors (Miller §6.6).

    Output ``i`` (row ``C_i``) is observed by ``len(regions[i])`` sensors; sensor ``j``
    reads ``clip(C_i x + v_ij, lower_ij, upper_ij)`` with independent noise
    :math:`v_{ij} \sim N(0, \sigma_{ij}^2)`. The dissertation's Example 1 is one
    output with windows ``(-inf, 0)`` (right-censored at 0) and ``(0, inf)``
    (left-censored at 0): ``multi_region(sys, [[(-np.inf, 0.0), (0.0, np.inf)]])``.

    Parameters
    ----------
    system : LinearSystem
        The model whose outputs are measured; must have diagonal, time-invariant R
        unless ``noise_var`` is given.
    regions : sequence over outputs of sequences of ``(lower, upper)``
        Windows for each output.
    noise_var : sequence over outputs of sequences of float, optional
        Per-sensor noise variance; default: ``R[i, i]`` for every sensor of output ``i``.

    Returns
    -------
    system : LinearSystem
        The stacked model (C and D rows repeated, R diagonal; A, Q, B, Bu and the prior kept).
    censoring : Censoring
        The per-sensor limits.

    Raises
    ------
    ShapeError
        If ``regions`` does not list one entry per output or R is time-varying.
    """
    if not all(hasattr(system, a) for a in ("m", "C", "R", "A", "Q", "x0", "P0")) or not hasattr(system.C, "varying"):
        raise ValidationError(f"system: expected a LinearSystem, got {type(system).__name__}")
    if (
        isinstance(regions, (str, bytes))
        or not isinstance(regions, Sequence)
        or any(isinstance(w, (str, bytes)) or not isinstance(w, Sequence) for w in regions)
    ):
        raise ValidationError(
            "regions: expected one sequence of (lower, upper) windows per output, got "
            f"{type(regions).__name__} {regions!r:.60}"
        )
    if noise_var is not None and (
        isinstance(noise_var, (str, bytes))
        or not isinstance(noise_var, Sequence)
        or any(isinstance(v, (str, bytes)) or not isinstance(v, Sequence) for v in noise_var)
    ):
        raise ValidationError(f"noise_var: expected one sequence of variances per output, got {noise_var!r:.60}")
    if len(regions) != system.m:
        raise ShapeError(f"regions: expected one list of windows per output ({system.m}), got {len(regions)}")
    if system.C.varying or system.R.varying:
        raise ShapeError("system: multi_region needs time-invariant C and R")
    C, R = system.C.at(1), system.R.at(1)
    if noise_var is not None and (
        len(noise_var) != len(regions) or any(len(nv) != len(w) for nv, w in zip(noise_var, regions))
    ):
        raise ShapeError(
            "noise_var: expected one variance per window, laid out like regions "
            f"({[len(w) for w in regions]} per output), got {[len(nv) for nv in noise_var]}"
        )
    rows, var, lo, hi, out_idx = [], [], [], [], []
    for i, wins in enumerate(regions):
        if len(wins) == 0:
            raise ShapeError(f"regions[{i}]: expected at least one (lower, upper) window")
        for j, win in enumerate(wins):
            if isinstance(win, (str, bytes)) or not hasattr(win, "__len__") or len(win) != 2:
                raise ShapeError(f"regions[{i}][{j}]: expected a (lower, upper) pair, got {win!r:.60}")
            rows.append(C[i])
            out_idx.append(i)
            if noise_var is None:
                var.append(R[i, i])
            else:
                nv = float(as_float_array(noise_var[i][j], f"noise_var[{i}][{j}]", ndim=0))
                if nv < 0:
                    raise ValidationError(f"noise_var[{i}][{j}]: expected a variance >= 0, got {nv}")
                var.append(nv)
            lo.append(as_float_array(win[0], f"regions[{i}][{j}][0]", ndim=0, allow_inf=True))
            hi.append(as_float_array(win[1], f"regions[{i}][{j}][1]", ndim=0, allow_inf=True))

    def same(ts):
        return None if ts is None else (ts.array if ts.fn is None else ts.fn)

    idx = np.array(out_idx)
    D = system.D
    if D is None:
        D_st = None
    elif D.fn is not None:
        D_st = lambda k, f=D.fn: np.asarray(f(k), dtype=float)[idx]  # noqa: E731  (one row per sensor)
    else:
        D_st = D.array[..., idx, :]
    # the stacked model is of the system's own class (a LinearSystem), built without importing the
    # models layer, which itself uses channel pieces
    stacked = type(system)(
        A=same(system.A),
        C=np.array(rows),
        Q=same(system.Q),
        R=np.diag(var),
        x0=system.x0,
        P0=system.P0,
        B=same(system.B),
        Bu=same(system.Bu),
        D=D_st,
    )
    return stacked, Censoring(lower=np.array(lo, dtype=float), upper=np.array(hi, dtype=float))
