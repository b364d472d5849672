r"""WRTDS: Weighted Regressions on Time, Discharge and Season (Hirsch, Moyer & Archfield 2010).

The established method for sparse, censored water-quality records, as implemented in the USGS R
package EGRET (``runSurvReg`` / ``run_WRTDS``, ``estCrossVal``, ``triCube``), here as the baseline a
state-space model is compared with. At each estimation point :math:`(t_0, \ln Q_0)` a *local* censored
(Tobit) regression of the log concentration is fitted by weighted maximum likelihood,

.. math::

    \ln c_i = \beta_0 + \beta_1 t_i + \beta_2 \ln Q_i + \beta_3 \sin 2\pi t_i + \beta_4 \cos 2\pi t_i
              + \sigma \varepsilon_i, \qquad \varepsilon_i \sim N(0, 1),

with :math:`t` in decimal years. Sample :math:`i` contributes :math:`w_i \ell_i` to the log-likelihood,
:math:`\ell_i = \log\phi(z_i) - \log\sigma` for a measured value and
:math:`\ell_i = \log(\Phi(z_i^{hi}) - \Phi(z_i^{lo}))` for a value known only to lie in
:math:`[\ln c^{lo}_i, \ln c^{hi}_i]` (EGRET's ``ConcLow``/``ConcHigh``: a left-censored sample has no
``ConcLow``, its ``ConcHigh`` is the detection limit; this is ``survreg`` with
``Surv(log(ConcLow), log(ConcHigh), type = "interval2")`` and a Gaussian distribution). The weight is
the product of three tricube windows :math:`T(d, h) = \max(0, 1 - (|d|/h)^3)^3`:

.. math::

    w_i = T(t_i - t_0, h_Y)\; T(\ln Q_i - \ln Q_0, h_Q)\; T(d^S_i, h_S), \qquad
    d^S_i = \min(\lceil d_i \rceil - d_i,\; d_i - \lfloor d_i \rfloor), \quad d_i = |t_i - t_0|,

(the seasonal distance is the distance of :math:`d_i` to the nearest whole number of years). The
half-windows start at ``window_y`` (7 years), ``window_q`` (2 ln units) and ``window_s`` (0.5 year);
while fewer than ``min_num_obs`` (100) samples or fewer than ``min_num_uncen`` (50) uncensored samples
have a positive weight, :math:`h_Y` and :math:`h_Q` grow by 10 % and :math:`h_S` too, capped at 0.5
(left alone when ``window_s`` > 0.5). With ``edge_adjust`` (EGRET's default), an estimation point
closer than :math:`h_Y` to an end of the period :math:`[t_{low}, t_{high}]` starts from the wider
:math:`2 h_Y - \min(t_0 - t_{low}, t_{high} - t_0)`. The weights are divided by their mean over the
samples with a positive weight (as EGRET does; this does not change the estimates).

At the estimation point the result is the predicted log concentration
:math:`\hat y = x_0^\top \hat\beta`, the fitted scale :math:`\hat\sigma` (EGRET's ``SE``) and the
bias-corrected concentration :math:`\hat c = \exp(\hat y + \hat\sigma^2 / 2)` (EGRET's ``ConcHat``).

Decimal years follow EGRET (``decimalDate``): a date without a time of day is taken at noon,
:math:`t = Y + (\text{day of year} - 1 + 1/2) / (\text{days in } Y)`, in UTC (EGRET uses the R
session's time zone for the start of the year, which can move :math:`t` by a few hours).

Numerics: the weighted likelihood is maximised by Newton's method in Olsen's parameters
:math:`(\gamma, \tau) = (\beta/\sigma, 1/\sigma)`, in which it is concave, with step halving, for all
estimation points at once (a batch axis); the regressors are centred at the estimation point, so that
:math:`\hat y` is the fitted intercept and the decimal year's size does not spoil the conditioning.
EGRET's ``survreg`` stops at a relative change of the log-likelihood of 1e-9; here the Newton
decrement is driven to 1e-20, so the estimates agree with a fully converged fit (not with EGRET's last
digits). EGRET's fall-back of jittering the data when ``survreg`` does not converge is not needed and
not implemented; a point that does not converge is flagged in ``converged``.

Leave-one-out cross-validation (:meth:`WRTDS.cross_validate`, EGRET's ``estCrossVal``): the prediction
at each sample's time and discharge from the data with that sample removed (the windows are widened
without it too); all samples are fitted together as one batch.

:func:`predictive_scores` scores such predictions (mean and sd of the log concentration) against
censored samples: the log predictive score and the RMSE of the uncensored log values.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.special import log_ndtr

from .._validation import ShapeError, ValidationError, as_float_array, check_bool
from ..filters._particle_models import _log_interval

__all__ = [
    "WRTDS",
    "WRTDSEstimate",
    "Windows",
    "PredictiveScores",
    "decimal_year",
    "tricube",
    "settings_from_egret",
    "predictive_scores",
]

_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)
_MAX_WIDENINGS = 10000  # EGRET stops widening after this many rounds ("Problems converging")
_BLOCK = 256  # estimation points fitted together
_NAMES = ("intercept", "decimal_year", "ln_q", "sin_2pi_t", "cos_2pi_t")


def decimal_year(dates: Any) -> np.ndarray:
    r"""EGRET's decimal year of each date: :math:`Y + (\text{seconds since 1 Jan } Y) / (\text{seconds in } Y)`.

    Parameters
    ----------
    dates : array_like
        ``numpy.datetime64`` values, ISO date strings (``"2001-03-01"``) or numbers (taken as decimal
        years already and returned as floats). When no date carries a time of day, every date is
        taken at noon (EGRET's rule), so 1 January of a common year is :math:`Y + 0.5/365`.

    Returns
    -------
    (n,) float ndarray, the shape of ``dates``.

    Raises
    ------
    ValidationError
        When a date cannot be read.
    """
    arr = np.asarray(dates)
    if arr.dtype.kind in "fiu":
        return arr.astype(float)
    try:
        sec = arr.astype("datetime64[s]")
    except (TypeError, ValueError) as exc:
        raise ValidationError(
            f"dates: expected dates (datetime64 or ISO strings) or decimal years, got {exc}"
        ) from None
    if np.isnat(sec).any():
        raise ValidationError(f"dates: {int(np.isnat(sec).sum())} missing date(s) (NaT); every sample needs a date")
    day = sec.astype("datetime64[D]")
    if np.all(sec == day.astype("datetime64[s]")):
        sec = sec + np.timedelta64(12 * 3600, "s")
    year = sec.astype("datetime64[Y]")
    start = year.astype("datetime64[s]")
    length = (year + 1).astype("datetime64[s]") - start
    return (year.astype(np.int64) + 1970) + (sec - start).astype(float) / length.astype(float)


def tricube(d: Any, h: Any) -> np.ndarray:
    r"""Tukey's tricube weight :math:`T(d, h) = \max(0, 1 - (|d|/h)^3)^3` (EGRET's ``triCube``), broadcast."""
    u = np.abs(np.asarray(d, dtype=float)) / np.asarray(h, dtype=float)
    c = np.maximum(0.0, 1.0 - u * u * u)
    return c * c * c


def settings_from_egret(info: dict[str, Any]) -> dict[str, Any]:
    """The keyword arguments of :class:`WRTDS` from EGRET's ``INFO`` fields.

    ``windowY``, ``windowQ``, ``windowS``, ``minNumObs``, ``minNumUncen`` and ``edgeAdjust`` become
    ``window_y``, ``window_q``, ``window_s``, ``min_num_obs``, ``min_num_uncen`` and ``edge_adjust``;
    a field that is absent keeps EGRET's default. Other fields are ignored.
    """
    keys = {
        "windowY": ("window_y", float),
        "windowQ": ("window_q", float),
        "windowS": ("window_s", float),
        "minNumObs": ("min_num_obs", int),
        "minNumUncen": ("min_num_uncen", int),
        "edgeAdjust": ("edge_adjust", bool),
    }
    out: dict[str, Any] = {}
    for src, (dst, kind) in keys.items():
        if src in info and info[src] is not None:
            value = info[src]
            if kind is int and float(value) != int(float(value)):
                raise ValidationError(f"info[{src!r}]: expected a whole number, got {value!r}")
            out[dst] = kind(float(value)) if kind is not bool else bool(value)
    return out


@dataclass(frozen=True)
class Windows:
    """The weights of the local regressions at P estimation points over the n samples.

    Attributes
    ----------
    weights : (P, n) ndarray
        Normalised weights (mean 1 over the samples with a positive weight; 0 outside the windows and
        for a sample left out).
    half_windows : (P, 3) ndarray
        The half-windows used, in time (years), ln Q and season (years), after edge adjustment and
        widening.
    num_obs, num_uncen : (P,) int ndarray
        Samples and uncensored samples with a positive weight.
    widenings : (P,) int ndarray
        How many times the windows were widened.
    """

    weights: np.ndarray
    half_windows: np.ndarray
    num_obs: np.ndarray
    num_uncen: np.ndarray
    widenings: np.ndarray


@dataclass(frozen=True)
class WRTDSEstimate:
    r"""WRTDS at P estimation points.

    Attributes
    ----------
    time : (P,) ndarray
        Decimal years of the estimation points.
    ln_q : (P,) ndarray
        Their log discharge.
    mean : (P,) ndarray
        Predicted log concentration :math:`\hat y` (EGRET's ``yHat``).
    sd : (P,) ndarray
        Fitted residual scale :math:`\hat\sigma` of the local regression (EGRET's ``SE``), the sd of
        the log-concentration prediction.
    conc : (P,) ndarray
        Bias-corrected concentration :math:`\exp(\hat y + \hat\sigma^2/2)` (EGRET's ``ConcHat``).
    coef : (P, 5) ndarray
        Local coefficients on (1, t, ln Q, sin 2πt, cos 2πt), t in decimal years (``coef_names``).
    log_likelihood : (P,) ndarray
        Weighted log-likelihood at the optimum (normalised weights).
    converged : (P,) bool ndarray
        The Newton iterations met their tolerance.
    windows : Windows
        The weights and windows used.
    """

    time: np.ndarray
    ln_q: np.ndarray
    mean: np.ndarray
    sd: np.ndarray
    conc: np.ndarray
    coef: np.ndarray
    log_likelihood: np.ndarray
    converged: np.ndarray
    windows: Windows
    coef_names: tuple[str, ...] = _NAMES


def _as_dates_or_years(value: Any, name: str) -> np.ndarray:
    arr = np.asarray(value)
    if arr.ndim != 1:
        raise ShapeError(f"{name}: expected one dimension, got shape {arr.shape}")
    try:
        t = decimal_year(arr)
    except ValidationError as exc:
        raise ValidationError(str(exc).replace("dates:", f"{name}:", 1)) from None
    if not np.all(np.isfinite(t)):
        raise ValidationError(f"{name}: expected finite dates or decimal years")
    return t


def _interval_bounds(conc_low: np.ndarray, conc_high: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ln bounds: a missing or zero ConcLow is no lower bound; a missing or infinite ConcHigh no upper one
    (both checked non-negative and ConcHigh positive before)."""
    with np.errstate(divide="ignore"):
        lo = np.where(np.isnan(conc_low) | (conc_low <= 0.0), -np.inf, np.log(np.where(conc_low > 0, conc_low, 1.0)))
        hi = np.where(np.isnan(conc_high), np.inf, np.log(np.where(conc_high > 0, conc_high, 1.0)))
    return lo, hi


class WRTDS:
    r"""WRTDS on one censored sample record (see the module docstring for the model).

    Parameters
    ----------
    dates : (n,) array_like
        Sample dates (``datetime64`` or ISO strings) or decimal years.
    q : (n,) array_like
        Daily mean discharge on each sample's day (positive); the regressor is :math:`\ln Q`.
    conc_low, conc_high : (n,) array_like
        EGRET's interval convention: the concentration lies in ``[conc_low, conc_high]``; equal for a
        measured value; ``conc_low`` NaN (or 0) for a left-censored sample, whose ``conc_high`` is the
        detection limit; ``conc_high`` NaN or ``inf`` for a right-censored one; both finite and
        different for an interval.
    window_y, window_q, window_s : float
        Starting half-windows in time (years), ln Q and season (years): EGRET's ``windowY`` (7),
        ``windowQ`` (2), ``windowS`` (0.5).
    min_num_obs, min_num_uncen : int
        Minimum numbers of samples and of uncensored samples with a positive weight (100 and 50).
    edge_adjust : bool
        Widen the time window near the period's ends (EGRET's ``edgeAdjust``, default True).
    period : (2,) array_like, optional
        The ends :math:`t_{low}, t_{high}` of the period for the edge adjustment (dates or decimal
        years). Default: the first and last sample. EGRET's ``modelEstimation`` and ``estCrossVal``
        runs use the first and last day of the daily discharge record.

    Raises
    ------
    ShapeError
        When the arrays are not one-dimensional of one length.
    ValidationError
        For a non-positive discharge, a negative ``conc_low``, a non-positive ``conc_high``, a lower bound
        above the upper bound (naming the sample), non-positive windows or
        minimum counts the record cannot meet (as EGRET, which stops when ``min_num_obs`` or
        ``min_num_uncen`` is not below the record's count).

    Examples
    --------
    >>> import tobitkf as tk
    >>> rec = tk.data.load_arkansas()
    >>> model = tk.wrtds.WRTDS(rec.date, rec.q, rec.conc_low, rec.conc_high, period=rec.period,
    ...                        **tk.wrtds.settings_from_egret(rec.egret_info))
    >>> cv = model.cross_validate()
    >>> cv.mean.shape
    (254,)
    """

    def __init__(
        self,
        dates: Any,
        q: Any,
        conc_low: Any,
        conc_high: Any,
        *,
        window_y: float = 7.0,
        window_q: float = 2.0,
        window_s: float = 0.5,
        min_num_obs: int = 100,
        min_num_uncen: int = 50,
        edge_adjust: bool = True,
        period: Any = None,
    ) -> None:
        self.time = _as_dates_or_years(dates, "dates")
        n = self.time.size
        q = as_float_array(q, "q", ndim=1)
        low = as_float_array(conc_low, "conc_low", ndim=1, allow_nan=True)
        high = as_float_array(conc_high, "conc_high", ndim=1, allow_nan=True, allow_inf=True)
        for name, arr in (("q", q), ("conc_low", low), ("conc_high", high)):
            if arr.shape != (n,):
                raise ShapeError(f"{name}: expected shape ({n},) like dates, got {arr.shape}")
        if np.any(q <= 0):
            i = int(np.flatnonzero(q <= 0)[0])
            raise ValidationError(f"q: expected positive discharge, got {q[i]} at sample {i}")
        for name, arr, ok in (("conc_low", low, ~(low < 0)), ("conc_high", high, ~(high <= 0))):
            if not ok.all():
                i = int(np.flatnonzero(~ok)[0])
                raise ValidationError(
                    f"{name}: expected a positive concentration or NaN (no bound), got {arr[i]} at sample {i}"
                )
        self.ln_low, self.ln_high = _interval_bounds(low, high)
        bad = ~(self.ln_low <= self.ln_high) | (np.isinf(self.ln_low) & np.isinf(self.ln_high))
        if np.any(bad):
            i = int(np.flatnonzero(bad)[0])
            raise ValidationError(
                f"conc_low, conc_high: sample {i} has bounds [{low[i]}, {high[i]}]; expected conc_low <= conc_high "
                "and at least one finite bound"
            )
        self.ln_q = np.log(q)
        self.uncensored = self.ln_low == self.ln_high
        for name, value in (("window_y", window_y), ("window_q", window_q), ("window_s", window_s)):
            if not (np.isfinite(value) and value > 0):
                raise ValidationError(f"{name}: expected a positive half-window, got {value!r}")
        self.window_y, self.window_q, self.window_s = float(window_y), float(window_q), float(window_s)
        self.min_num_obs, self.min_num_uncen = int(min_num_obs), int(min_num_uncen)
        self.edge_adjust = check_bool(edge_adjust, "edge_adjust")
        if period is None:
            self.period = (float(self.time.min()), float(self.time.max()))
        else:
            p = _as_dates_or_years(period, "period")
            if p.shape != (2,) or not p[0] <= p[1]:
                raise ValidationError(f"period: expected (start, end) with start <= end, got {period!r}")
            self.period = (float(p[0]), float(p[1]))
        self._check_counts(n, int(self.uncensored.sum()), "the record")
        self.design = self._design(self.time, self.ln_q)

    @property
    def num_samples(self) -> int:
        """Number of samples n."""
        return int(self.time.size)

    def _check_counts(self, n: int, n_uncen: int, what: str) -> None:
        if self.min_num_obs >= n:
            raise ValidationError(f"min_num_obs: {self.min_num_obs} is not below the {n} samples of {what}")
        if self.min_num_uncen >= n_uncen:
            raise ValidationError(
                f"min_num_uncen: {self.min_num_uncen} is not below the {n_uncen} uncensored samples of {what}"
            )

    @staticmethod
    def _design(t: np.ndarray, lq: np.ndarray) -> np.ndarray:
        return np.stack([np.ones_like(t), t, lq, np.sin(2 * np.pi * t), np.cos(2 * np.pi * t)], axis=-1)

    # ------------------------------------------------------------------ windows
    def windows(self, time: Any, ln_q: Any, *, exclude: Any = None) -> Windows:
        r"""The weights of the local regressions at estimation points ``(time, ln_q)``.

        Parameters
        ----------
        time : (P,) array_like
            Decimal years (or dates) of the estimation points.
        ln_q : (P,) array_like
            Their log discharge.
        exclude : (P,) int array_like, optional
            For each point, a sample to leave out (-1: none): its weight is 0 and it does not count
            towards the minimum numbers.

        Returns
        -------
        Windows
        """
        t0 = np.atleast_1d(_as_dates_or_years(np.atleast_1d(time), "time"))
        lq0 = as_float_array(np.atleast_1d(ln_q), "ln_q", ndim=1)
        if lq0.shape != t0.shape:
            raise ShapeError(f"ln_q: expected shape {t0.shape} like time, got {lq0.shape}")
        P, n = t0.size, self.num_samples
        keep = np.ones((P, n), dtype=bool)
        if exclude is not None:
            ex = np.asarray(exclude, dtype=np.int64).reshape(P)
            rows = np.flatnonzero(ex >= 0)
            keep[rows, ex[rows]] = False
        hy = np.full(P, self.window_y)
        if self.edge_adjust:
            dist = np.minimum(t0 - self.period[0], self.period[1] - t0)
            hy = np.where(dist > hy, hy, 2.0 * hy - dist)
        hq = np.full(P, self.window_q)
        hs = np.full(P, self.window_s)
        dy = np.abs(self.time[None, :] - t0[:, None])  # (P, n)
        dseason = np.minimum(np.ceil(dy) - dy, dy - np.floor(dy))
        dq = self.ln_q[None, :] - lq0[:, None]
        weights = np.zeros((P, n))
        used = np.zeros((P, 3))
        num_obs = np.zeros(P, dtype=np.int64)
        num_uncen = np.zeros(P, dtype=np.int64)
        widenings = np.zeros(P, dtype=np.int64)
        active = np.arange(P)
        for k in range(_MAX_WIDENINGS):
            a = active
            w = (
                tricube(dy[a], hy[a, None])
                * tricube(dq[a], hq[a, None])
                * tricube(dseason[a], hs[a, None])
                * keep[a]
                * (dy[a] <= hy[a, None])
            )
            pos = w > 0
            nobs = pos.sum(axis=1)
            nunc = (pos & self.uncensored[None, :]).sum(axis=1)
            weights[a], num_obs[a], num_uncen[a] = w, nobs, nunc
            used[a] = np.stack([hy[a], hq[a], hs[a]], axis=1)
            widenings[a] = k
            done = (nobs >= self.min_num_obs) & (nunc >= self.min_num_uncen)
            hy[a] *= 1.1
            hq[a] *= 1.1
            if self.window_s <= 0.5:
                hs[a] = np.minimum(hs[a] * 1.1, 0.5)
            active = a[~done]
            if active.size == 0:
                break
        weights /= np.maximum(weights.sum(axis=1, keepdims=True), 1e-300) / np.maximum(num_obs[:, None], 1)
        return Windows(weights=weights, half_windows=used, num_obs=num_obs, num_uncen=num_uncen, widenings=widenings)

    # ------------------------------------------------------------------ fits
    def estimate(self, time: Any, q: Any) -> WRTDSEstimate:
        r"""WRTDS at estimation points (EGRET's ``runSurvReg``).

        Parameters
        ----------
        time : (P,) array_like
            Dates or decimal years.
        q : (P,) array_like
            Discharge at those points (positive).

        Returns
        -------
        WRTDSEstimate

        Notes
        -----
        Each point gets its own local regression. EGRET's daily series (``estSurfaces`` and
        ``estDailyFromSurfaces``) instead fits a grid in time and ln Q and interpolates it to each day,
        which differs from this slightly.
        """
        q = as_float_array(np.atleast_1d(q), "q", ndim=1)
        if np.any(q <= 0):
            raise ValidationError("q: expected positive discharge at every estimation point")
        t0 = _as_dates_or_years(np.atleast_1d(time), "time")
        if q.shape != t0.shape:
            raise ShapeError(f"q: expected shape {t0.shape} like time, got {q.shape}")
        return self._estimate(t0, np.log(q), None)

    def cross_validate(self) -> WRTDSEstimate:
        """Leave-one-out predictions (EGRET's ``estCrossVal``): row i from the record without sample i.

        Each sample's prediction (``mean``, ``sd``, ``conc``) at its own time and discharge comes from the
        local regression fitted to the other n - 1 samples, the windows widened without it.

        Raises
        ------
        ValidationError
            When a record without one of its samples no longer has more samples (uncensored samples)
            than ``min_num_obs`` (``min_num_uncen``), where EGRET stops too.
        """
        n_unc = int(self.uncensored.sum())
        self._check_counts(self.num_samples - 1, n_unc - (1 if n_unc else 0), "the record without one sample")
        return self._estimate(self.time, self.ln_q, np.arange(self.num_samples))

    def _estimate(self, t0: np.ndarray, lq0: np.ndarray, exclude: np.ndarray | None) -> WRTDSEstimate:
        parts = []
        for start in range(0, max(t0.size, 1), _BLOCK):  # blocks of points: the (P, n, 6) arrays stay small
            sl = slice(start, start + _BLOCK)
            parts.append(self._estimate_block(t0[sl], lq0[sl], None if exclude is None else exclude[sl]))
        win = Windows(*(np.concatenate([getattr(p[-1], f) for p in parts]) for f in Windows.__dataclass_fields__))
        mean, sigma, coef, ll, conv = (np.concatenate([p[i] for p in parts]) for i in range(5))
        return WRTDSEstimate(
            time=t0,
            ln_q=lq0,
            mean=mean,
            sd=sigma,
            conc=np.exp(mean + 0.5 * sigma**2),
            coef=coef,
            log_likelihood=ll,
            converged=conv,
            windows=win,
        )

    def _estimate_block(self, t0: np.ndarray, lq0: np.ndarray, exclude: np.ndarray | None):
        win = self.windows(t0, lq0, exclude=exclude)
        x0 = self._design(t0, lq0)  # (P, 5)
        Xc = self.design[None, :, :] - x0[:, None, :]  # centred at each point; intercept column becomes 0
        Xc[..., 0] = 1.0
        beta_c, sigma, ll, conv = fit_weighted_tobit(Xc, self.ln_low, self.ln_high, win.weights)
        mean = beta_c[:, 0]
        coef = beta_c.copy()
        coef[:, 0] = mean - np.einsum("pj,pj->p", beta_c[:, 1:], x0[:, 1:])
        return mean, sigma, coef, ll, conv, win


# ---------------------------------------------------------------------- weighted Tobit by Newton
def _pieces(X: np.ndarray, lo: np.ndarray, hi: np.ndarray, theta: np.ndarray, need: int):
    """Per-sample log-likelihood (and its first/second derivatives w.r.t. the linear arguments) at theta.

    Olsen's parameters theta = (gamma (k,), tau); for a measured value y, r = tau y - x gamma and
    l = log tau - r^2/2 - log sqrt(2 pi); for an interval, u = tau hi - x gamma, v = tau lo - x gamma and
    l = log(Phi(u) - Phi(v)). ``lo``, ``hi`` are (n,); the measured and the censored samples (columns)
    are evaluated apart, so the normal tails are computed only where needed.
    """
    gamma, tau = theta[:, :-1], theta[:, -1]
    xg = (X @ gamma[..., None])[..., 0]
    exact = lo == hi
    ex, ce = np.flatnonzero(exact), np.flatnonzero(~exact)
    ll = np.empty(xg.shape)
    r = tau[:, None] * hi[ex] - xg[:, ex]
    ll[:, ex] = np.log(tau)[:, None] - 0.5 * r**2 - _LOG_SQRT_2PI
    lo_c, hi_c = lo[ce], hi[ce]
    fin_u, fin_v = np.isfinite(hi_c), np.isfinite(lo_c)
    xc = xg[:, ce]
    uf = np.where(fin_u, tau[:, None] * np.where(fin_u, hi_c, 0.0) - xc, 0.0)
    vf = np.where(fin_v, tau[:, None] * np.where(fin_v, lo_c, 0.0) - xc, 0.0)
    log_d = _log_interval(np.where(fin_v, vf, -np.inf), np.where(fin_u, uf, np.inf))
    ll[:, ce] = log_d
    if need == 0:
        return ll
    phi_u = np.where(fin_u, np.exp(-0.5 * uf**2 - _LOG_SQRT_2PI - log_d), 0.0)  # phi(u)/D
    phi_v = np.where(fin_v, np.exp(-0.5 * vf**2 - _LOG_SQRT_2PI - log_d), 0.0)  # phi(v)/D
    # d ll / du, d ll / dv and the second derivatives
    gu, gv, huu, hvv, huv = (np.zeros(xg.shape) for _ in range(5))
    gu[:, ex], huu[:, ex] = -r, -1.0
    gu[:, ce], gv[:, ce] = phi_u, -phi_v
    huu[:, ce] = -uf * phi_u - phi_u**2
    hvv[:, ce] = vf * phi_v - phi_v**2
    huv[:, ce] = phi_u * phi_v
    return ll, gu, gv, huu, hvv, huv


def _objective(X, lo, hi, w, theta):
    ll = _pieces(X, lo, hi, theta, 0)
    return np.sum(np.where(w > 0, w * ll, 0.0), axis=1)


def fit_weighted_tobit(
    X: np.ndarray,
    ln_low: np.ndarray,
    ln_high: np.ndarray,
    weights: np.ndarray,
    *,
    tol: float = 1e-20,
    max_iter: int = 200,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    r"""Weighted censored-normal regression by maximum likelihood, for P weightings at once.

    Maximises :math:`\sum_i w_{pi} \ell_i(\beta_p, \sigma_p)` (module docstring) over
    :math:`(\beta_p, \sigma_p)` for each p, by Newton's method in :math:`(\gamma, \tau) = (\beta/\sigma,
    1/\sigma)` (concave) with step halving, from the weighted least-squares fit to the bounds (the
    finite one, or the midpoint) as start.

    Parameters
    ----------
    X : (P, n, k) ndarray
        Regressors of the n samples for each fit.
    ln_low, ln_high : (n,) ndarray
        Bounds of each sample's value (equal: measured; ``-inf`` / ``inf``: no bound).
    weights : (P, n) ndarray
        Non-negative weights; samples of weight 0 take no part.
    tol : float
        Stop when the Newton decrement :math:`g^\top H^{-1} g` is below ``tol`` (times the weight sum).
    max_iter : int

    Returns
    -------
    beta : (P, k) ndarray
    sigma : (P,) ndarray
    log_likelihood : (P,) ndarray
        Weighted log-likelihood at the optimum.
    converged : (P,) bool ndarray
    """
    P, n, k = X.shape
    w = np.asarray(weights, dtype=float)
    lo, hi = np.asarray(ln_low, dtype=float), np.asarray(ln_high, dtype=float)
    exact = lo == hi
    # derivatives of u = tau hi - x gamma and v = tau lo - x gamma w.r.t. (gamma, tau): (-x, hi), (-x, lo)
    Du_all = np.concatenate([-X, np.broadcast_to(np.where(np.isfinite(hi), hi, 0.0), (P, n))[..., None]], axis=2)
    Dv_all = np.concatenate([-X, np.broadcast_to(np.where(np.isfinite(lo), lo, 0.0), (P, n))[..., None]], axis=2)
    # start: weighted least squares on a representative value of each sample
    yv = np.where(np.isfinite(ln_high), np.where(np.isfinite(ln_low), 0.5 * (ln_low + ln_high), ln_high), ln_low)
    sw = np.sqrt(w)
    A = X * sw[:, :, None]
    G = np.einsum("pnj,pnk->pjk", A, A)
    rhs = np.einsum("pnj,pn->pj", A, sw * yv[None, :])
    beta0 = np.linalg.solve(G + 1e-12 * np.eye(k), rhs[..., None])[..., 0]
    res = yv[None, :] - np.einsum("pnk,pk->pn", X, beta0)
    s0 = np.sqrt(np.sum(w * res**2, axis=1) / np.maximum(w.sum(axis=1), 1e-300))
    s0 = np.maximum(s0, 1e-3 * np.maximum(np.std(yv[np.isfinite(yv)]), 1e-12))
    theta = np.concatenate([beta0 / s0[:, None], 1.0 / s0[:, None]], axis=1)
    wsum = np.maximum(w.sum(axis=1), 1e-300)
    f = _objective(X, lo, hi, w, theta)
    converged = np.zeros(P, dtype=bool)
    active = np.arange(P)
    for _ in range(max_iter):
        a = active
        Xa, wa, th = X[a], w[a], theta[a]
        ll, gu, gv, huu, hvv, huv = _pieces(Xa, lo, hi, th, 2)
        tau = th[:, -1]
        Du, Dv = Du_all[a], Dv_all[a]
        wex = wa[:, exact].sum(axis=1)
        g = (Du.transpose(0, 2, 1) @ (wa * gu)[..., None] + Dv.transpose(0, 2, 1) @ (wa * gv)[..., None])[..., 0]
        g[:, -1] += wex / tau
        DuT, DvT = Du.transpose(0, 2, 1), Dv.transpose(0, 2, 1)
        cross = DuT @ ((wa * huv)[..., None] * Dv)
        H = DuT @ ((wa * huu)[..., None] * Du) + DvT @ ((wa * hvv)[..., None] * Dv) + cross + cross.transpose(0, 2, 1)
        H[:, -1, -1] -= wex / tau**2
        step = np.linalg.solve(-H, g[..., None])[..., 0]
        decrement = np.einsum("pj,pj->p", g, step)
        done = ~(decrement > tol * wsum[a])  # also stops a NaN
        conv_now = np.isfinite(decrement) & done
        converged[a[conv_now]] = True
        go = ~done
        a, step, th = a[go], step[go], th[go]
        if a.size == 0:
            active = a
            break
        f_old = f[a]
        alpha = np.ones(a.size)
        new = th + step
        for _h in range(60):
            bad = (new[:, -1] <= 0) | ~np.isfinite(new).all(axis=1)
            f_new = np.full(a.size, -np.inf)
            ok = ~bad
            if ok.any():
                f_new[ok] = _objective(X[a[ok]], lo, hi, w[a[ok]], new[ok])
            accept = f_new >= f_old - 1e-12 * np.abs(f_old)
            if accept.all():
                break
            alpha = np.where(accept, alpha, 0.5 * alpha)
            new = np.where(accept[:, None], new, th + alpha[:, None] * step)
        theta[a] = new
        f[a] = _objective(X[a], lo, hi, w[a], new)
        active = a
    tau = theta[:, -1]
    return theta[:, :-1] / tau[:, None], 1.0 / tau, f, converged


# ---------------------------------------------------------------------- scores
@dataclass(frozen=True)
class PredictiveScores:
    r"""Scores of Gaussian predictions of (log) values against censored samples.

    Attributes
    ----------
    log_score : (n,) ndarray
        Per-sample log predictive score: :math:`\log \Phi((\ell_i - m_i)/s_i)` for a sample censored
        below its limit :math:`\ell_i` (the predictive probability of lying below it), :math:`\log
        \phi((y_i - m_i)/s_i) - \log s_i` for a measured value :math:`y_i` (the predictive density),
        :math:`\log(\Phi(z^{hi}) - \Phi(z^{lo}))` for an interval.
    mean_log_score : float
        Mean over the samples (higher is better).
    se_mean_log_score : float
        Its standard error, sd of the per-sample scores over :math:`\sqrt{n}`.
    rmse : float
        Root mean squared error :math:`\sqrt{\mathrm{mean}(y_i - m_i)^2}` over the measured samples.
    num_uncensored : int
        Number of measured samples in ``rmse``.
    """

    log_score: np.ndarray
    mean_log_score: float
    se_mean_log_score: float
    rmse: float
    num_uncensored: int

    def to_dict(self) -> dict[str, float | int]:
        """The summary numbers (JSON-ready)."""
        return {
            "mean_log_score": self.mean_log_score,
            "se_mean_log_score": self.se_mean_log_score,
            "rmse_uncensored": self.rmse,
            "num_uncensored": self.num_uncensored,
        }


def predictive_scores(mean: Any, sd: Any, low: Any, high: Any) -> PredictiveScores:
    r"""Log predictive score and RMSE of Gaussian predictions :math:`N(m_i, s_i^2)` of censored values.

    Parameters
    ----------
    mean, sd : (n,) array_like
        Predictive mean and standard deviation of each sample's value (e.g. its log concentration).
    low, high : (n,) array_like
        What is known of the value, on the same scale: ``low == high`` for a measured value; ``low =
        -inf`` and ``high`` = the limit for a sample censored below a detection limit; ``high = inf``
        for one censored above; both finite for an interval. (For EGRET's ``ConcLow``/``ConcHigh`` in
        concentration units, take logs, NaN ``ConcLow`` as ``-inf``.)

    Returns
    -------
    PredictiveScores

    Raises
    ------
    ShapeError, ValidationError
        For arrays of different lengths, a non-positive sd or ``low > high``.
    """
    m = as_float_array(mean, "mean", ndim=1)
    s = as_float_array(sd, "sd", ndim=1)
    lo = as_float_array(low, "low", ndim=1, allow_nan=True, allow_inf=True)
    hi = as_float_array(high, "high", ndim=1, allow_nan=True, allow_inf=True)
    lo = np.where(np.isnan(lo), -np.inf, lo)
    hi = np.where(np.isnan(hi), np.inf, hi)
    for name, arr in (("sd", s), ("low", lo), ("high", hi)):
        if arr.shape != m.shape:
            raise ShapeError(f"{name}: expected shape {m.shape} like mean, got {arr.shape}")
    if np.any(s <= 0):
        raise ValidationError("sd: expected positive standard deviations")
    if np.any(lo > hi):
        i = int(np.flatnonzero(lo > hi)[0])
        raise ValidationError(f"low, high: sample {i} has low {lo[i]} above high {hi[i]}")
    exact = lo == hi
    with np.errstate(invalid="ignore"):
        zl, zh = (lo - m) / s, (hi - m) / s
        interval = _log_interval(np.where(exact, -np.inf, zl), np.where(exact, np.inf, zh))
    one_sided_low = np.isneginf(lo) & ~exact
    interval = np.where(one_sided_low, log_ndtr(np.where(one_sided_low, zh, 0.0)), interval)
    score = np.where(exact, -0.5 * np.where(exact, zl, 0.0) ** 2 - _LOG_SQRT_2PI - np.log(s), interval)
    n = score.size
    n_unc = int(exact.sum())
    rmse = float(np.sqrt(np.mean((lo[exact] - m[exact]) ** 2))) if n_unc else float("nan")
    se = float(np.std(score, ddof=1) / np.sqrt(n)) if n > 1 else float("nan")
    return PredictiveScores(
        log_score=score, mean_log_score=float(np.mean(score)), se_mean_log_score=se, rmse=rmse, num_uncensored=n_unc
    )
