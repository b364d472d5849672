r"""Assumed-density Tobit filter (ADF): the exact posterior moments of a Gaussian prior given a censored reading.

Not in the sources. The Tobit Kalman filter (Miller 2015, §3.3.4) takes every channel statistic at
the *prior mean* (Assumption A1, (3.35)) and treats a censored reading as a noisy linear one; the
assumed-density filter (Maybeck 1982, §12.7; Lauritzen 1992; Opper 1998; Minka 2001, "assumed-density
filtering") instead conditions the Gaussian prior on what was actually observed and projects the
posterior back onto a Gaussian by matching its mean and covariance. For a censored reading both
are in closed form.

Model: :math:`x_k = A_{k-1}x_{k-1} + B^u_ku_k + w_{k-1}`, :math:`y^*_k = C_kx_k + D_ku_k + v_k`, R
diagonal (channels processed in sequence), :math:`y_k(l) = \mathrm{clip}(y^*_k(l), l_k(l), h_k(l))`.

One channel c = :math:`C_k(l)`, prior :math:`x \sim N(\bar x, \bar P)`. The latent reading is
:math:`y^* \sim N(\mu, s^2)`, :math:`\mu = c\bar x + d`, :math:`s^2 = c\bar Pc^T + r`, jointly Gaussian with
x, so :math:`x \mid y^*` is Gaussian with mean :math:`\bar x + K(y^* - \mu)`, :math:`K = \bar Pc^T/s^2`,
and covariance :math:`\bar P - Ks^2K^T`. What is observed is an event about :math:`y^*`:

=================  =========================================  =======================================
reading            :math:`E[y^* \mid \text{obs}]`              :math:`V = \mathrm{Var}[y^* \mid \text{obs}]`
=================  =========================================  =======================================
:math:`l < y < h`  y                                          0
:math:`y = l`      :math:`\mu - s\,\phi(a)/\Phi(a)`           :math:`s^2[1 - a\phi(a)/\Phi(a) - (\phi(a)/\Phi(a))^2]`
:math:`y = h`      :math:`\mu + s\,\phi(b)/\Phi(-b)`          the mirror image
NaN (missing)      (no update)
=================  =========================================  =======================================

with :math:`a = (l-\mu)/s`, :math:`b = (h-\mu)/s` (the truncated-normal moments of
:func:`tobitkf.censored_moments`, safe 40 σ into the tails), and by the laws of total expectation
and variance the exact posterior moments

.. math::

    \hat x = \bar x + K\,(E[y^* \mid \text{obs}] - \mu), \qquad
    P = \bar P - K\,(s^2 - V)\,K^T.

This is the shared Gaussian update (:func:`~tobitkf.filters.core.measurement_update`) with
:math:`H_0 = c`, noise r, the observed value :math:`E[y^* \mid \text{obs}]` and the retained
variance V, in each covariance form (standard, Joseph, square root). With r = 0 (a noiseless
sensor) the update still exists whenever the prior carries variance along c (:math:`s^2 > 0`).
Infinite limits give the Kalman filter (every reading interior; sequential channels with diagonal
R equal the joint update). Two-sided limits and several regions (stacked channels,
:func:`~tobitkf.multi_region`) need nothing more. With m > 1 channels the posterior after each
channel is projected on a Gaussian before the next (the "in sequence" of the ADF).

Time convention (package-wide): :math:`x_0 \sim N(\bar x_0, P_0)` is the prior, :math:`y_1` is at
index 0, result row k-1 holds :math:`\hat x_{k|k}`, :math:`P_{k|k}` and the prediction.

Symbols: ``mean`` = x̂, ``cov`` = P, ``p_uncensored`` = :math:`\Phi(b) - \Phi(a)` of each channel at
its (sequential) prior, ``log_likelihood`` = :math:`\sum_l \log p(y_k(l) \mid \text{Gaussian prior})`.
"""

from __future__ import annotations

import copy
from contextvars import ContextVar
from typing import Any, Mapping

import numpy as np
from scipy.special import ndtr

from .._validation import ShapeError, ValidationError, as_float_array, check_bool, check_instance
from ..censored import censored_moments
from ..channels.censoring import Censoring
from ..models.linear import LinearSystem
from ._backend import BACKENDS, compiled_module, numba_available
from ._boundary import _noise_variances
from ._outputs import loop_input
from ._readings import (
    _INTERIOR,
    _INTERVAL,
    _LOWER,
    _MISSING,
    _UPPER,
    _as_indicator,
    censored_log_likelihood,
    censoring_sides,
    interval_classes,
)
from ._readings import classify_readings as _classify
from .core import (
    COVARIANCE_FORMS,
    FilterResult,
    FilterState,
    GaussianFilter,
    MeasurementPrediction,
    Transition,
    check_keywords,
    check_prior,
    measurement_update,
    prepare_measurements,
    process_roots,
    psd_sqrt,
)
from .kalman import LinearGaussianFamily
from .likelihood import filter_log_likelihood
from .registry import family_entry, register
from .smoothing import IndicatorFilterMethods, SmoothingMethods

__all__ = [
    "AssumedDensityTobitFilter",
    "AssumedDensityFamily",
    "censored_reading_moments",
    "censored_channel_update",
    "assumed_density_update",
    "merge_gaussians",
    "steered_limits",
]

_ORDERS = ("channels", "uncensored_first")
#: the options every assumed-density family takes (their registry entries)
ADF_OPTIONS = {"covariance_update": COVARIANCE_FORMS, "backend": BACKENDS}
_NUMPY_HOOKS = ("_project", "_sequential", "_update_arrays", "_step_arrays", "_initial", "_transition")
_STEP_DATA: ContextVar[Mapping[str, np.ndarray] | None] = ContextVar("adf_step_data", default=None)
_TINY = np.finfo(np.float64).tiny


def censored_reading_moments(
    y: np.ndarray, mean: np.ndarray, std: np.ndarray, lower: Any, upper: Any, cls: np.ndarray | None = None
):
    r""":math:`E[y^* \mid \text{obs}]` and :math:`\mathrm{Var}[y^* \mid \text{obs}]` of a latent
    :math:`y^* \sim N(\mu, s^2)` given its censored reading (the table of the module docstring), batched.

    Parameters
    ----------
    y, mean, std, lower, upper : (N,) arrays
        Readings (NaN = missing), latent means and standard deviations (> 0), and the limits.
    cls : (N,) int8 array, optional
        The class of each reading (as returned below), e.g. from a recorded censoring indicator;
        default the limit rule of :func:`~tobitkf.filters._readings.classify_readings`.

    Returns
    -------
    observed : (N,) ndarray
        y for an interior reading, the truncated mean for a censored one, NaN for a missing one.
    retained : (N,) ndarray
        0 for an interior reading, the truncated variance for a censored one (0 when missing).
    cls : (N,) int8 ndarray
        0 missing, 1 interior, 2 at the lower limit, 3 at the upper limit, 4 an interval reading (only from a
        given ``cls``: :math:`y^*` between the limits, its moments truncated to them).
    """
    cls = _classify(y, lower, upper) if cls is None else cls
    lo_w = np.where((cls == _UPPER) | (cls == _INTERVAL), upper, -np.inf)
    lo_w = np.where(cls == _INTERVAL, lower, lo_w)
    hi_w = np.where((cls == _LOWER) | (cls == _INTERVAL), lower, np.inf)
    hi_w = np.where(cls == _INTERVAL, upper, hi_w)
    cens = (cls == _LOWER) | (cls == _UPPER) | (cls == _INTERVAL)
    obs = np.where(cls == _INTERIOR, y, np.nan)
    V = np.zeros(y.shape)
    if cens.any():
        st = censored_moments(mean[cens], std[cens], lo_w[cens], hi_w[cens])
        obs[cens] = st.truncated_mean
        V[cens] = st.truncated_var
    return obs, V, cls


def censored_channel_update(
    x: np.ndarray,
    P: np.ndarray,
    S: np.ndarray | None,
    y: np.ndarray,
    c: np.ndarray,
    r: float,
    lower: Any,
    upper: Any,
    *,
    dy: Any = 0.0,
    form: str = "standard",
    cls: np.ndarray | None = None,
    compiled: bool = False,
):
    r"""The ADF update of one channel (the module docstring's equations), batched over runs.

    Parameters
    ----------
    x : (N, n) ; P : (N or 1, n, n) ; S : (N or 1, n, n) or None (square-root factor)
    y : (N,) readings of the channel (NaN = missing)
    c : (n,) its row of C (of the effective measurement matrix), or (N or 1, n) one per run ;
        r : its noise variance (>= 0), scalar or (N,)
    lower, upper : scalar or (N,) limits
    dy : (N,) or 0, the feed-through D u of the channel
    form : {"standard", "joseph", "square_root"}
    cls : (N,) int8, optional
        The class of each reading (missing / interior / lower / upper, see
        :func:`censored_reading_moments`), e.g. from a recorded indicator; a reading of class missing
        is skipped whatever its value. Default the limit rule.
    compiled : bool, default False
        Take the moments, the log-likelihood and ``p_uncensored`` from the compiled block the compiled loop runs
        (:func:`~tobitkf.filters._compiled_moments.censored_block`): :math:`E[y^* \mid \text{obs}] = \mu +
        \alpha s^2`, :math:`V = s^2 - \beta s^4`. Needs numba; the same numbers to rounding (tested to 1e-12).

    Returns
    -------
    x, P, S : the posterior (S None unless ``form="square_root"``)
    p_uncensored : (N,) probability of an uncensored reading under the prior
    log_likelihood : (N,) log-density (or log-mass) of the reading under the Gaussian prior:
        :math:`\log\phi((y-\mu)/s) - \log s` inside the limits, :math:`\log\Phi((l-\mu)/s)` at l,
        :math:`\log\Phi((\mu-h)/s)` at h (``log_ndtr``), 0 if missing. A degenerate latent
        (:math:`s^2` not above the smallest normal number) gives the indicator of the reading: 0 if
        the point :math:`\mu` agrees with it (equals an interior y, lies beyond the limit of a
        censored one), else ``-inf``; and no update.
    """
    N = x.shape[0]
    rv = np.asarray(r, dtype=float)
    if c.ndim == 2:  # one row per run (N or 1, n)
        mu = np.einsum("ri,ri->r", x, np.broadcast_to(c, x.shape)) + dy
        s2 = np.broadcast_to(np.einsum("rij,ri,rj->r", P, c, c) + rv, (N,))
    else:
        mu = x @ c + dy
        s2 = np.broadcast_to(np.einsum("rij,i,j->r", P, c, c) + rv, (N,))
    ok = s2 > _TINY
    s = np.where(ok, np.sqrt(np.where(ok, s2, 1.0)), 1.0)
    lo = np.broadcast_to(np.asarray(lower, dtype=float), (N,))
    hi = np.broadcast_to(np.asarray(upper, dtype=float), (N,))
    if compiled:
        from ._compiled_moments import CENSORED, family_array, kind

        cls = _classify(y, lo, hi) if cls is None else cls
        f = loop_input  # writable: numba types read-only arrays (broadcast views) apart, one compile more each
        cPc = s2 - rv
        alpha, beta, ll, p_unc, _ = family_array(
            kind(CENSORED), f(y), np.require(cls, np.int8, ("C", "W")), f(mu), f(cPc), f(np.broadcast_to(rv, (N,))),
            f(lo), f(hi), np.zeros(0), 0,
        )  # fmt: skip
        valid = ok & (cls != _MISSING)
        beyond = valid & ((cls == _LOWER) | (cls == _UPPER) | (cls == _INTERVAL))
        obs = np.where(beyond, mu + alpha * s2, np.where(valid, y, np.nan))
        V = np.where(beyond, s2 - beta * s2 * s2, 0.0)
    else:
        obs, V, cls = censored_reading_moments(y, mu, s, lo, hi, cls)
        valid = ok & (cls != _MISSING)
        a, b = (lo - mu) / s, (hi - mu) / s
        p_unc = np.where(np.isneginf(lo), 1.0, ndtr(-a)) - np.where(np.isposinf(hi), 0.0, ndtr(-b))
        ll = np.where(valid, censored_log_likelihood(y, mu, s, lo, hi, classes=cls), 0.0)
    degenerate = ~ok & (cls != _MISSING)
    if degenerate.any() and not compiled:
        with np.errstate(invalid="ignore"):
            inside = (mu >= lo) & (mu <= hi)
            agrees = np.where(
                cls == _LOWER, mu <= lo, np.where(cls == _UPPER, mu >= hi, np.where(cls == _INTERVAL, inside, y == mu))
            )
        ll = np.where(degenerate, np.where(agrees, 0.0, -np.inf), ll)
    if not valid.any():
        return x, P, S, p_unc, ll
    cens = (cls == _LOWER) | (cls == _UPPER) | (cls == _INTERVAL)
    noise = np.full((1, 1), float(rv)) if rv.ndim == 0 else np.broadcast_to(rv, (N,))[:, None]
    mp = MeasurementPrediction(
        expected=mu[:, None],
        H0=c[..., None, :],
        noise=noise,
        observed=np.where(valid, obs, np.nan)[:, None],
        valid=valid[:, None],
        retained=V[:, None] if cens.any() else None,
    )
    xn, Pn, Sn, _, _ = measurement_update(x, P, S, np.where(valid, obs, np.nan)[:, None], mp, form)
    return xn, Pn, Sn, p_unc, ll


def assumed_density_update(
    x_pred: np.ndarray,
    P_pred: np.ndarray,
    y: np.ndarray,
    C: np.ndarray,
    R_diag: Any,
    lower: Any,
    upper: Any,
    *,
    dy: Any = 0.0,
    covariance_update: str = "standard",
):
    r"""One ADF measurement update of all channels in sequence (procedural form), batched over runs.

    Parameters
    ----------
    x_pred : (N, n) ; P_pred : (N or 1, n, n) ; y : (N, m) (NaN = missing) ; C : (m, n)
    R_diag : (m,) noise variances (>= 0) ; lower, upper : (m,) or (N, m) ; dy : (N, m) or 0
    covariance_update : {"standard", "joseph", "square_root"}
        The square-root form factors ``P_pred`` afresh; :class:`AssumedDensityTobitFilter` keeps the factor.

    Returns
    -------
    x : (N, n) ; P : (N or 1, n, n)

    Examples
    --------
    A reading at the limit of a scalar state, prior N(0, 1), no noise: the posterior is the
    half-normal's, mean :math:`-\sqrt{2/\pi}`, variance :math:`1 - 2/\pi`.

    >>> x, P = assumed_density_update(np.zeros((1, 1)), np.ones((1, 1, 1)), np.zeros((1, 1)), np.eye(1), [0.0],
    ...                               [0.0], [np.inf])
    >>> bool(np.isclose(x[0, 0], -np.sqrt(2 / np.pi))), bool(np.isclose(P[0, 0, 0], 1 - 2 / np.pi))
    (True, True)
    """
    N, m = y.shape
    r = np.broadcast_to(np.asarray(R_diag, dtype=float), (m,))
    lo = np.broadcast_to(np.asarray(lower, dtype=float), (N, m))
    hi = np.broadcast_to(np.asarray(upper, dtype=float), (N, m))
    d = np.broadcast_to(np.asarray(dy, dtype=float), (N, m))
    S = psd_sqrt(P_pred) if covariance_update == "square_root" else None
    x, P = x_pred, P_pred
    for l in range(m):
        x, P, S, _, _ = censored_channel_update(
            x, P, S, y[:, l], C[l], r[l], lo[:, l], hi[:, l], dy=d[:, l], form=covariance_update
        )
    return x, P


def merge_gaussians(weights: np.ndarray, means: np.ndarray, covs: np.ndarray, factors: np.ndarray | None = None):
    r"""Moment matching of a Gaussian mixture: :math:`\hat x = \sum_j w_j\hat x_j`,
    :math:`P = \sum_j w_j\,(P_j + (\hat x_j - \hat x)(\hat x_j - \hat x)^T)`, batched over runs.

    Parameters
    ----------
    weights : (J, N) ; means : (J, N, n) ; covs : (J, N or 1, n, n)
    factors : (J, N or 1, n, n), optional
        Square-root factors :math:`P_j = S_jS_j^T`; the merged factor is then the triangular factor of
        the QR of :math:`[\sqrt{w_j}S_j^T;\ \sqrt{w_j}(\hat x_j - \hat x)^T]_j` (PSD by construction).

    Returns
    -------
    x : (N, n) ; P : (N, n, n) ; S : (N, n, n) or None
    """
    w = weights[..., None]
    x = (w * means).sum(0)
    d = means - x[None]
    P = (w[..., None] * (covs + d[..., :, None] * d[..., None, :])).sum(0)
    P = 0.5 * (P + np.swapaxes(P, -1, -2))
    if factors is None:
        return x, P, None
    J, N, n = means.shape
    sw = np.sqrt(np.maximum(weights, 0.0))[..., None, None]
    Fs = np.broadcast_to(factors, (J, N, n, n))
    blocks = np.concatenate([np.swapaxes(sw * Fs, -1, -2), (sw[..., 0] * d)[..., None, :]], axis=-2)  # (J, N, n+1, n)
    M = np.moveaxis(blocks, 0, 1).reshape(N, J * (n + 1), n)
    U = np.linalg.qr(M, mode="r")
    Sm = np.swapaxes(U, -1, -2)
    return x, 0.5 * (Sm @ U + np.swapaxes(Sm @ U, -1, -2)), Sm


def _indicator(censored: Any, shape: tuple[int, ...]) -> np.ndarray:
    """The recorded indicator as a bool array of ``shape`` (ShapeError / ValidationError naming ``censored``)."""
    return np.ascontiguousarray(_as_indicator(censored, shape, "censored"))


def _recorded_classes(
    cls: np.ndarray, flags: np.ndarray, y: np.ndarray, k: int, lo: np.ndarray, hi: np.ndarray
) -> np.ndarray:
    """Reading classes by the recorded indicator (:func:`~tobitkf.filters._readings.interval_classes`): a
    flagged reading keeps the limit it lies at (or beyond), a flagged one strictly inside its limits is an
    interval reading if both limits are finite, an unflagged one at a limit is interior. Raises if a flagged
    reading is missing or inside limits of which one is infinite."""
    bad = flags & ((cls == _MISSING) | ((cls == _INTERIOR) & ~(np.isfinite(lo) & np.isfinite(hi))))
    if bad.any():
        run, l = (int(i) for i in np.argwhere(bad)[0])
        what = (
            "missing (NaN)"
            if cls[run, l] == _MISSING
            else f"{y[run, l]:.6g}, strictly inside its limits (an interval reading needs two finite limits)"
        )
        raise ValidationError(
            f"censored: the reading of channel {l} at time {k} (run {run}) is flagged censored but {what}"
        )
    return interval_classes(cls, flags, lo, hi)


def steered_limits(censoring: Censoring, state: FilterState, options: Mapping[str, Any], m: int) -> dict[str, Any]:
    """The limits of one online step (the ``lower``/``upper`` keywords of ``step`` and ``update`` of the censoring
    filters, a limit steered from the prediction): ``{"lower": (N, m), "upper": (N, m)}`` with the censoring's
    limit of the step where only one is given, or ``{}`` when neither is.

    Raises
    ------
    ValidationError
        A limit that does not broadcast to ``state.batch_shape + (m,)``, or lower >= upper in a channel.
    """
    out = {}
    for key in ("lower", "upper"):
        if options.get(key) is not None:
            arr = as_float_array(options[key], key, allow_inf=True)
            try:
                out[key] = np.broadcast_to(arr, (state.runs, m))
            except ValueError:
                raise ValidationError(
                    f"{key}: expected this step's limits of shape ({m},) or {state.batch_shape + (m,)}, got {arr.shape}"
                ) from None
    if not out:
        return out
    lo, hi = censoring.limits(state.k + (0 if state.carry.get("_predicted") else 1))
    lo = out.get("lower", np.broadcast_to(lo, (state.runs, m)))
    hi = out.get("upper", np.broadcast_to(hi, (state.runs, m)))
    if not (lo < hi).all():
        raise ValidationError("lower/upper: expected lower < upper for every channel of this step")
    return {"lower": lo, "upper": hi}


class AssumedDensityFamily(GaussianFilter):
    r"""What the assumed-density families share: the predict + update of :meth:`step`, :meth:`update` and
    :meth:`filter` around a family's own projection.

    A family's measurement update is no linear (Kalman) update but the projection of the exact
    posterior onto a Gaussian (moment matching): ``_project(k, x̄, P̄, S̄, y, u, **step_options)`` →
    ``(x, P, S, extras)`` on arrays (N runs, no validation inside), with ``S`` the square-root factor
    (None unless ``covariance_update="square_root"``). It replaces the Kalman-type update of
    :class:`~tobitkf.filters.core.GaussianFilter` (the ``_update_arrays`` hook); the time update, :meth:`step`,
    :meth:`predict` and :meth:`update` are the shared ones, and so is :meth:`filter`. A family's constructor
    calls :meth:`_configure` (the system, ``covariance_update``, ``backend`` and its own keyword options checked,
    R diagonal) and checks its channel; :meth:`_noise_at` gives the measurement variances of a step
    (``_positive_noise`` names a family that needs them positive); a family whose reading sees past states
    takes :class:`AugmentedWindow` (the stacked state, its prior and shift). Taken by
    :class:`AssumedDensityTobitFilter`, :class:`~tobitkf.filters.adf_fading.FadingAssumedDensityFilter`,
    :class:`~tobitkf.filters.adf_protocol.ProtocolAssumedDensityFilter`,
    :class:`~tobitkf.filters.adf_saturation.SaturationAssumedDensityFilter` and the generic
    :class:`~tobitkf.filters.adf_generic.AssumedDensityFilter`.
    """

    _filter_doc = """Filter the readings ``y`` (..., T, m) by the assumed-density update: the exact posterior of each
    step's reading projected onto a Gaussian (its mean and covariance matched)."""
    _filter_params = {
        "x0": "array_like, optional\n"
        "    Override the prior mean of :math:`x_0` (and of an augmented state's window blocks), ``(n,)`` or\n"
        "    ``(..., n)``.",
        "P0": "array_like, optional\n    Override the prior covariance, ``(n, n)`` or ``(..., n, n)``.",
    }
    _filter_raises = (
        "a reading the channel cannot give (outside the censoring limits, below a protocol's threshold τ, refused"
        " by a channel's own ``check_readings``); a measurement covariance R that is not diagonal (or, where the"
        " family needs it, not positive) at a step"
    )

    def _project(self, k, xp, Pp, Sp, y, u, **options):  # pragma: no cover - abstract
        raise NotImplementedError

    #: None: the channels take a measurement variance >= 0; a filter's name (e.g. ``"the protocol filter"``):
    #: every variance must be positive (its likelihood divides by it), and the error names that filter
    _positive_noise: str | None = None
    _r: np.ndarray | None = None
    system: LinearSystem

    def _configure(self, system: LinearSystem, covariance_update: str, backend: str, **options: Any) -> None:
        """The checks and settings every family's constructor shares: ``system`` a :class:`LinearSystem`, the
        ``covariance_update`` and ``backend`` (and the family's own keyword ``options``, name -> (value,
        choices)) among their choices, R diagonal (checked now when it is constant, else at each step); sets
        ``system``, ``n``, ``m`` and the process-noise roots of the square-root form.

        Raises ValidationError naming the argument."""
        check_instance(system, LinearSystem, "system")
        check_keywords(
            {"covariance_update": covariance_update, "backend": backend, **{k: v for k, (v, _) in options.items()}},
            {"covariance_update": COVARIANCE_FORMS, "backend": BACKENDS, **{k: c for k, (_, c) in options.items()}},
        )
        self.covariance_update = covariance_update
        self.backend = backend
        self._r = None if system.R.varying else self._noise_of(system, 1, "R")
        self.system, self.n, self.m = system, system.n, system.m
        self._roots = process_roots(system)

    def _noise_of(self, system: LinearSystem, k: int, name: str) -> np.ndarray:
        return _noise_variances(system.measurement_cov(k), name, self._positive_noise)

    def _noise_at(self, k: int) -> np.ndarray:
        """The measurement variances (m,) at step ``k`` (:func:`_noise_variances`; computed once when R is constant)."""
        return self._r if self._r is not None else self._noise_of(self.system, k, f"R({k})")

    #: the builder of the family's arrays for the compiled loop (a ``*_spec`` function of
    #: :mod:`tobitkf.filters._compiled_loop`), None: no compiled path
    _compiled_spec: str | None = None

    def _update_arrays(self, k, xp, Pp, Sp, y, u, carry, options):
        xn, Pn, Sn, extras = self._project(k, xp, Pp, Sp, y, u, **options)
        return xn, Pn, Sn, carry, extras

    def _run(self, y, u=None, x0=None, P0=None, *, step_data=None, **kwargs):
        token = _STEP_DATA.set(step_data)  # the recorded data of the call, for the compiled loop
        try:
            return super()._run(y, u, x0, P0, step_data=step_data, **kwargs)
        finally:
            _STEP_DATA.reset(token)

    def _own_hooks(self) -> bool:
        """Whether the numpy hooks are those of the class that names the compiled arrays: a subclass that
        changes them (its own projection or extras) keeps the numpy loop, which runs them."""
        cls = type(self)
        owner = next(c for c in cls.__mro__ if "_compiled_spec" in c.__dict__)
        return all(getattr(cls, h, None) is getattr(owner, h, None) for h in _NUMPY_HOOKS)

    def _compiled_filter(self, y2, u2, state, want, batch, step_options=None):
        """The compiled loop (:mod:`tobitkf.filters._compiled_loop`) when the ``backend`` allows it and covers
        the options; None: the numpy loop runs."""
        backend = getattr(self, "backend", "numpy")
        data = _STEP_DATA.get() or {}
        per_run_limits = "lower" in data  # limits per run: only the censoring family's compiled arrays take them
        own = self._compiled_spec == "censoring_spec" or not per_run_limits
        if self._compiled_spec is None or backend == "numpy" or step_options or not own or not self._own_hooks():
            return None
        if not numba_available():
            if backend == "numba":
                compiled_module()  # raises: numba is not installed
            return None
        from . import _loop_specs

        spec_of = getattr(_loop_specs, self._compiled_spec)
        return _loop_specs.compiled_filter(self, y2, u2, state, want, batch, _STEP_DATA.get(), spec_of)


class AugmentedWindow:
    r"""The state of the assumed-density families whose reading sees a window of past states: the stacked
    :math:`\xi_k = [x_k^T \cdots x_{k-W}^T]^T` (``nx`` = n (W + 1)), its shift transition and its prior.

    Taken by :class:`~tobitkf.filters.adf_fading.FadingAssumedDensityFilter` (W = L, the fading order) and
    :class:`~tobitkf.filters.adf_protocol.ProtocolAssumedDensityFilter` (W = ℓ, the integral window); the
    family sets ``system``, ``n``, ``nx``, ``covariance_update`` and ``_roots``.
    """

    system: LinearSystem
    n: int
    nx: int
    covariance_update: str
    _roots: Any

    _prepare_inputs = LinearGaussianFamily._prepare_inputs
    _step_input = LinearGaussianFamily._step_input
    _linear_transition = LinearGaussianFamily._linear_transition

    def _state_dim(self) -> int:
        return self.nx

    def _window_prior(self, N: int, x0: Any, P0: Any, batch: tuple[int, ...], mode: str):
        r"""The prior of :math:`\xi_0` (N runs): the top block :math:`N(\bar x_0, P_0)` and the window blocks by
        ``mode``: ``"zero"`` zero blocks (terms that do not exist yet), ``"prior"`` iid :math:`N(\bar x_0, P_0)`
        blocks, ``"hold"`` :math:`x_{-s} = x_0` (fully correlated blocks). The covariance keeps one copy
        (1, nx, nx) unless ``x0`` or ``P0`` is given per run."""
        x, P = check_prior(self.system, x0, P0, N, batch)
        per_run = (x0 is not None and np.ndim(x0) > 1) or (P0 is not None and np.ndim(P0) > 2)
        if not per_run:
            P = P[:1]
        P = 0.5 * (P + np.swapaxes(P, -1, -2))
        n, W = self.n, self.nx // self.n - 1
        xi = np.zeros((N, self.nx))
        M = np.zeros((P.shape[0], self.nx, self.nx))
        for s in range(W + 1):
            if s == 0 or mode != "zero":
                xi[:, s * n : (s + 1) * n] = x
            for t in range(W + 1):
                if (s == t and (s == 0 or mode != "zero")) or mode == "hold":
                    M[:, s * n : (s + 1) * n, t * n : (t + 1) * n] = P
        return xi, M, {}

    def _transition(self, k, u, carry) -> Transition:
        return self._linear_transition(k, u, shift=True, source=0)


def _run_limits(given: Any, own: np.ndarray, batch: tuple[int, ...], shape: tuple[int, ...], name: str) -> np.ndarray:
    """Limits (N, T, m) of every run and step: ``given`` broadcast to ``batch + (T, m)``, else the censoring's."""
    if given is None:
        return np.ascontiguousarray(np.broadcast_to(own, shape))
    arr = as_float_array(given, name, allow_inf=True)
    try:
        full = np.broadcast_to(arr, batch + shape[1:])
    except ValueError:
        raise ShapeError(f"{name}: expected a shape broadcastable to {batch + shape[1:]}, got {arr.shape}") from None
    return np.ascontiguousarray(full.reshape(shape))


class AssumedDensityTobitFilter(IndicatorFilterMethods, SmoothingMethods, AssumedDensityFamily, LinearGaussianFamily):
    r"""Assumed-density filter for censored readings: exact posterior moments, Kalman cost.

    Parameters
    ----------
    system : LinearSystem
        The model; R diagonal, entries >= 0 (0 allowed where the prior carries the variance).
    censoring : Censoring
        Limits (one- or two-sided, time-varying, several regions as stacked channels).
    covariance_update : {"standard", "joseph", "square_root"}, default "standard"
        The covariance form of the shared update: :math:`\bar P - K(s^2 - V)K^T`; the Joseph form
        :math:`(I - Kc)\bar P(I - Kc)^T + KrK^T + KVK^T`; the square root (QR array form, then the
        factor of :math:`P + KVK^T` by one more QR).
    check_limits : bool, default True
        Raise if a reading lies outside its limits.
    order : {"channels", "uncensored_first"}, default "channels"
        The sequence of the channel updates within a step. ``"channels"``: channel 1, 2, ..., m.
        ``"uncensored_first"``: first the readings inside their limits (in channel order; with a
        diagonal R this is the joint Kalman update, exact), then the censored ones (in channel order).
        The two agree for m = 1 and whenever no reading is censored. With at most one censored
        reading in a step, ``"uncensored_first"`` gives the exact moments of
        :math:`p(x_k \mid y_k, \text{the Gaussian prediction})` (the projection comes last) and
        its log-likelihood term is :math:`\log N(y_{k,u}; \hat y_u, S_{uu}) + \log\Phi(\pm(\text{limit}
        - \mu)/s)`; the smoothers, likelihoods and fits of :mod:`tobitkf.inference` use it.
    backend : {"auto", "numba", "numpy"}, default "auto"
        ``"auto"`` runs :meth:`filter` through the compiled loop (:mod:`tobitkf.filters._compiled_loop`) when
        numba is installed and the options are covered (the standard covariance form, either ``order``,
        system matrices constant, per step or per run (``batch_ndim``) with C shared by the runs, limits of
        the censoring or given per run to :meth:`filter`, control inputs through constant ``Bu``/``D``), the numpy loop
        otherwise; ``"numba"`` insists on the compiled loop (raises otherwise); ``"numpy"`` never uses it.
        Both give the same numbers (tested to 1e-12); :meth:`step` (and a case the compiled loop does not cover)
        runs the numpy step, with the moments of the compiled loop's function unless ``"numpy"``.

    Raises
    ------
    ValidationError
        Non-diagonal or negative R, unknown option, wrong argument types.

    Notes
    -----
    See the module docstring for the equations. Online: :meth:`step`, or :meth:`predict` then
    :meth:`update`; both take ``lower``/``upper`` for a limit steered from the prediction and
    ``censored`` (``batch_shape + (m,)``) for the recorded indicator of the reading.
    :meth:`filter` takes the recorded indicator ``censored`` (..., T, m) of the record: a flagged
    reading at (or beyond) a limit counts as censored there; a flagged reading strictly inside two finite
    limits (``lower``/``upper`` given per run and step) is an *interval* reading, :math:`\text{lower} \le y^* \le
    \text{upper}` (its value is unused): its log-likelihood term is the predictive mass
    :math:`\log(\Phi(\beta) - \Phi(\alpha))` of the interval and its update the projection on the normal
    truncated to it (the same event computation as a censored reading's, which is an interval with one
    infinite end: equal to it exactly, tested); an unflagged reading
    is an exact reading even when it equals a limit (e.g. the 8 such readings of the cloud-ceiling data);
    without it a reading within ``1e-12 max(1, |limit|)`` of a finite limit is censored.

    Extras: ``p_uncensored`` (..., T, m), the probability :math:`\Phi(b) - \Phi(a)` of each channel
    at the prior it is updated from; ``log_likelihood`` (..., T), the per-step term

    .. math::

        \ell_k = \sum_l \log p(y_k(l) \mid \text{the Gaussian the channel is updated from}),

    the predictive density :math:`\log\phi((y-\mu)/s) - \log s` of a reading inside its limits and
    the predictive mass :math:`\log\Phi((l-\mu)/s)` / :math:`\log\Phi((\mu-h)/s)` of a reading at
    a limit (``scipy.special.log_ndtr``, finite far into the tails), 0 for a missing one;
    :math:`\sum_k \ell_k` is the assumed-density approximation of :math:`\log p(y_{1:T})`
    (:func:`tobitkf.inference.adf_log_likelihood`), exact for one step from a Gaussian prior;
    ``side`` (..., T, m) int8, -1 / +1 for a reading censored at the lower / upper limit, 0 otherwise.

    Examples
    --------
    With infinite limits the ADF is the Kalman filter:

    >>> import numpy as np, tobitkf as tk
    >>> sys = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.01]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    >>> y = np.array([[0.5], [1.0], [-0.2]])
    >>> a = tk.AssumedDensityTobitFilter(sys, tk.Censoring()).filter(y).mean
    >>> bool(np.allclose(a, tk.KalmanFilter(sys).filter(y).mean, rtol=0, atol=1e-12))
    True

    References
    ----------
    .. [1] P. S. Maybeck, *Stochastic Models, Estimation and Control*, vol. 2, Academic Press, 1982, §12.7.
    .. [2] T. P. Minka, *A family of algorithms for approximate Bayesian inference*, PhD thesis, MIT, 2001, §3.1.
    .. [3] C. I. Miller, *Estimation and Control with Censored Data*, PhD thesis, University of Delaware,
       2015, §3.3 (the TKF it improves on).
    """

    _name = "AssumedDensityTobitFilter"
    _filter_doc = """Filter censored readings ``y`` (..., T, m) by the assumed-density update (the exact posterior of
    a censored reading projected onto a Gaussian), with the recorded indicator or limits per run when given."""
    _filter_params = {
        **AssumedDensityFamily._filter_params,
        "censored": "(..., T, m) bool array_like, optional\n"
        "    The censoring indicator recorded with the data (True = censored); default the limit rule. See the\n"
        "    class Notes.",
        "lower": "array_like broadcastable to (..., T, m), optional\n"
        "    Lower limits of each run and step replacing the censoring's (e.g. each subject's assay limits in a\n"
        "    panel); the censoring's limits stay where one is not given. Every reading must lie within them.",
        "upper": "array_like broadcastable to (..., T, m), optional\n    Upper limits, as ``lower``.",
    }
    _filter_raises = (
        "a reading outside its limits; ``censored`` not boolean (or 0/1), or flagging a missing reading or one inside"
        " limits that are not both finite; ``lower``, ``upper`` or ``censored`` not laid out like ``y`` (a"
        " ShapeError)"
    )
    _step_options = ("lower", "upper", "censored")

    def __init__(
        self,
        system: LinearSystem,
        censoring: Censoring,
        *,
        covariance_update: str = "standard",
        check_limits: bool = True,
        order: str = "channels",
        backend: str = "auto",
    ):
        self._configure(system, covariance_update, backend, order=(order, _ORDERS))
        check_instance(censoring, Censoring, "censoring")
        censoring.check(system.m)
        self.check_limits = check_bool(check_limits, "check_limits")
        self.censoring = censoring
        self.order = order

    _compiled_spec = "censoring_spec"

    def _sequential(self, k, xp, Pp, Sp, y, u, lower=None, upper=None, censored=None):
        if lower is None or upper is None:
            lo, hi = self.censoring.limits(k)
            lower = lo if lower is None else lower
            upper = hi if upper is None else upper
        N, m = y.shape
        lo = np.broadcast_to(np.asarray(lower, dtype=float), (N, m))
        hi = np.broadcast_to(np.asarray(upper, dtype=float), (N, m))
        cls = _classify(y, lo, hi)
        if censored is not None:
            cls = _recorded_classes(cls, censored, y, k, lo, hi)
        C, r = self.system.measurement(k), self._noise_at(k)
        dy = np.broadcast_to(self._feedthrough(k, u), (N, m))
        compiled = (
            getattr(self, "backend", "auto") != "numpy" and numba_available()
        )  # the compiled loop's moments, unless "numpy"
        x, P, S = xp, Pp, Sp
        pu = np.empty((N, m))
        ll = np.zeros(N)
        if self.order == "channels":
            passes = [(cls, np.ones((N, m), dtype=bool))]
        else:
            inside = cls == _INTERIOR
            passes = [(np.where(inside, cls, _MISSING), inside), (np.where(inside, _MISSING, cls), ~inside)]
        for cp, member in passes:
            for l in range(m):
                if not member[:, l].any():
                    continue
                x, P, S, pul, lll = censored_channel_update(
                    x,
                    P,
                    S,
                    y[:, l],
                    C[..., l, :],
                    r[..., l],
                    lo[:, l],
                    hi[:, l],
                    dy=dy[:, l],
                    form=self.covariance_update,
                    cls=cp[:, l],
                    compiled=compiled,
                )
                pu[:, l] = np.where(member[:, l], pul, pu[:, l])
                ll += lll
        side = np.where(cls == _LOWER, -1, np.where(cls == _UPPER, 1, 0)).astype(np.int8)
        return x, P, S, {"p_uncensored": pu, "log_likelihood": ll, "side": side}

    def _project(self, k, xp, Pp, Sp, y, u, **options):
        return self._sequential(k, xp, Pp, Sp, y, u, **options)

    def _prepare_step_options(self, state: FilterState, options: dict[str, Any]) -> dict[str, Any]:
        flags = None
        if options.get("censored") is not None:
            flags = _indicator(options["censored"], state.batch_shape + (self.m,)).reshape(state.runs, self.m)
        out = steered_limits(self.censoring, state, options, self.m)
        if flags is not None:
            out["censored"] = flags
        return out

    def _check_record(self, y2, u2, k0, name="y"):
        super()._check_record(y2, u2, k0, name)
        self.censoring.check(self.m, k0 + y2.shape[1])
        if self.check_limits:
            self.censoring.check_measurements(y2, start=k0 + 1)

    def step(self, state: FilterState, y: Any, *, u: Any = None, **options: Any) -> FilterState:
        """One predict + update with the reading ``y`` (``batch_shape + (m,)``; NaN = missing).

        ``lower``/``upper`` (keyword, (m,) or ``batch_shape + (m,)``) replace this step's limits;
        ``censored`` (keyword, ``batch_shape + (m,)`` bool) is the recorded indicator of the reading.

        Raises
        ------
        ValidationError
            A reading outside its limits; a flagged reading that is missing or inside limits not both finite.
        ShapeError
            Malformed ``y``, ``u``, limits or indicator.
        """
        # the reading is checked by the shared step (GaussianFilter._check_reading: filter's own record check)
        return super().step(state, y, u=u, **options)

    def filter(
        self,
        y: Any,
        *,
        u: Any = None,
        censored: Any = None,
        x0: Any = None,
        P0: Any = None,
        outputs: Any = "all",
        state: FilterState | None = None,
        times: Any = None,
        lower: Any = None,
        upper: Any = None,
    ) -> FilterResult:
        # IndicatorFilterMethods' filter with the limits as record keywords (those given)
        limits = {name: v for name, v in (("lower", lower), ("upper", upper)) if v is not None}
        return self._filter_record(y, u, censored, x0, P0, outputs, state, times, **limits)

    def _filter_indicated(
        self, y: Any, censored: Any, *, u: Any, x0: Any, P0: Any, outputs: Any, state: Any, lower=None, upper=None
    ) -> FilterResult:
        """:meth:`filter` with the recorded indicator ``censored`` and/or limits per run and step (``lower``,
        ``upper``), checked against the readings and handed to the loop as step data."""
        y2, batch = prepare_measurements(y, self.m)
        k0 = self.k0 if state is None else state.k
        self.censoring.check(self.m, k0 + y2.shape[1])
        lo, hi = self.censoring.all_limits(y2.shape[1], self.m, start=k0 + 1)
        data: dict[str, np.ndarray] = {}
        if lower is not None or upper is not None:
            lo, hi = (
                _run_limits(given, own, batch, y2.shape, name)
                for given, own, name in ((lower, lo, "lower"), (upper, hi, "upper"))
            )
            if np.any(lo > hi):
                raise ValidationError("lower/upper: expected lower <= upper at every run and step")
            with np.errstate(invalid="ignore"):
                tol = 1e-12 * np.maximum(1.0, np.where(np.isfinite(lo), np.abs(lo), 0.0))
                below = y2 < lo - tol
                tol = 1e-12 * np.maximum(1.0, np.where(np.isfinite(hi), np.abs(hi), 0.0))
                above = y2 > hi + tol
            if (below | above).any():
                i, t, l = (int(v[0]) for v in np.nonzero(below | above))
                raise ValidationError(
                    f"y: reading {y2[i, t, l]!r} of run {i}, step {t}, channel {l} lies outside its limits "
                    f"[{lo[i, t, l]!r}, {hi[i, t, l]!r}]"
                )
            data.update(lower=lo, upper=hi)
        if censored is not None:
            flags = _indicator(censored, batch + y2.shape[1:]).reshape(y2.shape)
            censoring_sides(y2, lo, hi, flags, intervals=True)  # the record's checks, the index of a bad flag
            data["censored"] = flags
        if "lower" in data and self.check_limits:  # the record is checked against the limits just given
            est = copy.copy(self)
            est.check_limits = False
            return est._run(y, u, x0, P0, outputs=outputs, state=state, step_data=data)
        return self._run(y, u, x0, P0, outputs=outputs, state=state, step_data=data)

    def _log_likelihood_terms(self, y: Any, *, u: Any, x0: Any, P0: Any, **recorded: Any) -> np.ndarray:
        """The ``log_likelihood`` extras of :meth:`filter` (..., T): the terms of :meth:`log_likelihood`."""
        return filter_log_likelihood(self, y, u=u, x0=x0, P0=P0, **recorded)

    def __repr__(self) -> str:
        order = "" if self.order == "channels" else f", order={self.order!r}"
        return f"AssumedDensityTobitFilter({self.censoring!r}, covariance_update={self.covariance_update!r}{order})"


def assumed_density_filter(system, censoring, *, covariance_update: str = "standard"):
    r"""The :class:`AssumedDensityTobitFilter` of the smoothers, likelihoods and fits: the
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
    return AssumedDensityTobitFilter(system, censoring, covariance_update=covariance_update, order="uncensored_first")


register(
    family_entry(
        AssumedDensityTobitFilter,
        "assumed-density filter: the exact posterior moments of each censored reading (beyond the sources)",
        ("censoring",),
        options={**ADF_OPTIONS, "order": _ORDERS},
    )
)
