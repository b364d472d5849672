r"""The drifting-coefficient censored model of a sample record with daily covariates (:class:`RiverModel`),
and its batched leave-one-out refits (:func:`batched_loo_refit`).

Built for ``data-arkansas`` (ammonia in the Arkansas River: 254 samples on irregular days over 22 years,
45 % below one of three detection limits, discharge known every day) and used by ``data-niagara``. The
model is the state-space counterpart of WRTDS's moving windows: on the daily grid :math:`d = 1..D`,

.. math::

    \ln c_d = \beta_{0,d} + \beta_{1,d}(\ln Q_d - \overline{\ln Q}) + \beta_{2,d}\sin 2\pi t_d
              + \beta_{3,d}\cos 2\pi t_d + \textstyle\sum_j \beta_{j,d} z_{j,d} + \xi_d + v_d,

with some coefficients random walks (:math:`\beta_{j,d+1} = \beta_{j,d} + w_{j,d}`,
:math:`w_{j,d} \sim N(0, q_j/365.25)`, :math:`t` in decimal years; the two seasonal terms share one
:math:`q_2`), optional further known regressors :math:`z_j` (the square of the centred ln Q or a natural
cubic spline in it, a seasonal ln Q slope, an ln Q slope trend, the second seasonal harmonic, a flow anomaly
against the recent mean flow, a slower one, the anomaly times ln Q: :class:`RiverModel`), the residual
:math:`\xi` a daily AR(1) (a sampled Ornstein-Uhlenbeck process, :math:`\phi = e^{-1/\tau}`, stationary
variance :math:`\sigma^2`; optional) and :math:`v_d \sim N(0, r^2)` the sample's own noise, optionally with
an sd that depends on the flow, :math:`r\,e^{\gamma(\ln Q_d - \overline{\ln Q})}` (and on its square, the
season, the flow anomaly's size, the years: :class:`RiverModel`). ``data-arkansas`` compares many
such models (:mod:`~tobitkf.experiments.records_arkansas`). The state is :math:`x_d = (\beta_{\cdot,d},
\xi_d)`, the daily regressors are known time-varying rows :math:`C_d` of a :class:`~tobitkf.LinearSystem`,
the readings are NaN on days without a sample, and a censored sample lies below its own detection limit.
The prior is :math:`\beta_{\cdot,0} = b` (parameters) and :math:`\xi_0 \sim N(0, \sigma^2)`.

The likelihood is the assumed-density filter's (:func:`tobitkf.adf_log_likelihood`). Days without
a sample are pure prediction steps, so the filter on the daily grid equals the filter on the
samples' days with each gap of :math:`\Delta` days taken in one step (:math:`A = \mathrm{diag}(1,1,1,1,
\phi^\Delta)`, :math:`Q = \mathrm{diag}(q\Delta/365.25, \sigma^2(1 - \phi^{2\Delta}))`), tested. The
fits and the leave-one-out refits run on the samples' days: a *batch* of parameter vectors goes
through the filter at once (:func:`~tobitkf.experiments.records_common.adf_pass`: each run its own
:math:`A_k`, :math:`Q_k`, the package's censored channel update, compiled for the likelihood, and its RTS
pass :func:`~tobitkf.filters.smoothing.rts_smooth`), which gives central finite-difference gradients in
one call. The static coefficients are constants with no prior variance: the pass runs on the moving states
only (the drifting coefficients' deviations from their prior means and the residuals, :meth:`RiverModel.reduced`),
the static part of the mean entering each run's readings as a known offset, which is exact and makes the
experiment's model a two-state filter instead of a nine-state one. The daily concentration comes from the
package's RTS pass over the daily grid (:meth:`RiverModel.daily_smooth`, equal to :func:`tobitkf.smooth` on the
daily system, tested).

Leave-one-out (:func:`batched_loo_refit`): for each sample i, the parameters are refitted to the record
without it, warm-started at the full fit, every sample's refit one run of a batched quasi-Newton search, and
the predictive of its ln value is the smoothed state at its day mapped through :math:`C_i`, plus the sample
noise.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._validation import ValidationError
from .records_common import _FD_STEP, _YEAR, adf_pass, fd_gradient, fd_hessian, gap_matrices

__all__ = ["RiverModel", "batched_loo_refit", "flow_anomaly", "flow_spline_basis", "spline_knots"]

_SPLINE_QUANTILES = {
    3: (0.1, 0.5, 0.9),
    4: (0.05, 0.35, 0.65, 0.95),
    5: (0.05, 0.275, 0.5, 0.725, 0.95),
}


def flow_anomaly(z: np.ndarray, days: float) -> np.ndarray:
    r"""The flow anomaly :math:`z_d - m_{d-1}` of a daily series z (D,): the day's value against its exponentially
    weighted mean over the days before, :math:`m_d = m_{d-1} + (z_d - m_{d-1})/L`, :math:`L` = ``days``,
    :math:`m_0 = z_0` (and the anomaly of day 0 is 0)."""
    from scipy.signal import lfilter

    z = np.asarray(z, dtype=float)
    w = 1.0 / days
    m, _ = lfilter([w], [1.0, w - 1.0], z[1:], zi=[(1.0 - w) * z[0]])  # m_d, d = 1..D-1
    return z - np.r_[z[0], z[0], m[:-1]]


def spline_knots(z: np.ndarray, count: int) -> np.ndarray:
    """The ``count`` knots (3, 4 or 5) of :func:`flow_spline_basis` at Harrell's quantiles of ``z``.

    Raises
    ------
    ValidationError
        ``count`` not 3, 4 or 5.
    """
    if count not in _SPLINE_QUANTILES:
        raise ValidationError(f"flow_spline_knots: expected 0 (none), 3, 4 or 5 knots, found {count!r}")
    return np.quantile(np.asarray(z, dtype=float), _SPLINE_QUANTILES[count])


def flow_spline_basis(z: np.ndarray, knots: np.ndarray) -> np.ndarray:
    r"""The K - 2 nonlinear columns (len(z), K - 2) of the restricted (natural) cubic spline with knots
    :math:`k_1 < \dots < k_K` (:class:`RiverModel`'s ``flow_spline_knots``):

    .. math::

        s_j(z) = \frac{(z - k_j)_+^3 - (z - k_{K-1})_+^3\,\frac{k_K - k_j}{k_K - k_{K-1}}
                 + (z - k_K)_+^3\,\frac{k_{K-1} - k_j}{k_K - k_{K-1}}}{(k_K - k_1)^2};

    0 below :math:`k_1`, linear above :math:`k_K` (the cubic and quadratic terms cancel there).
    """
    z = np.asarray(z, dtype=float)
    k = np.asarray(knots, dtype=float)
    K = k.size
    if K < 3 or np.any(np.diff(k) <= 0):
        raise ValidationError(f"knots: expected at least 3 strictly increasing knots, found {k.tolist()}")

    def cube(a: np.ndarray) -> np.ndarray:
        return np.maximum(a, 0.0) ** 3

    span = (k[-1] - k[0]) ** 2
    last = k[-1] - k[-2]
    cols = [
        (cube(z - k[j]) - cube(z - k[-2]) * (k[-1] - k[j]) / last + cube(z - k[-1]) * (k[-2] - k[j]) / last) / span
        for j in range(K - 2)
    ]
    return np.column_stack(cols)


@dataclass
class RiverModel:
    r"""The drifting-coefficient censored model of a sample record with daily covariates (module docstring).

    Parameters
    ----------
    day : (n,) int ndarray
        Day index (0-based on the daily grid) of each sample, strictly increasing; the prior :math:`x_0`
        is the day before day 0.
    y : (n,) ndarray
        ln concentration; the ln detection limit for a censored sample.
    censored : (n,) bool ndarray
        Censored samples: below ``lower`` (their ``y``) or, with ``upper`` finite, between the two (interval
        readings).
    rows : (D, l + 1) ndarray
        :math:`C_d` of every day: the l regressors named by ``coef``, then 1 (the AR residual's column).
    drift : tuple of str
        The coefficient groups that drift as random walks: any of ``"intercept"``, ``"slope"`` (ln Q),
        ``"season"`` (sin and cos, one variance), ``"quadratic"``; ``()`` gives a static regression.
    quadratic : bool
        Add the regressor :math:`(\ln Q - \overline{\ln Q})^2` (centred).
    flow_variance : bool
        Sample noise sd :math:`r\,e^{\gamma(\ln Q - \overline{\ln Q})}` instead of r.
    season_variance : bool
        A seasonal sample noise: the log sd also carries :math:`\gamma_s \sin 2\pi t + \gamma_c \cos 2\pi t`
        (parameters ``gamma_sin``, ``gamma_cos``), so that the noise sd is
        :math:`r\,e^{\gamma(\ln Q - \overline{\ln Q}) + \gamma_s \sin 2\pi t + \gamma_c \cos 2\pi t}`
        (WRTDS's local residual sd varies with the season as well as with the flow).
    season_slope : bool
        Add :math:`\ln Q \sin 2\pi t` and :math:`\ln Q \cos 2\pi t` (a seasonal ln Q slope).
    harmonics : int
        Seasonal harmonics: 1 (sin and cos of :math:`2\pi t`) or 2 (also :math:`\sin 4\pi t = 2\sin\cos`,
        :math:`\cos 4\pi t = \cos^2 - \sin^2`, coefficients ``sin2``, ``cos2``).
    flow_anomaly_days : float
        If positive, add the regressor :math:`\ln Q_d - m_{d-1}`, the day's ln Q against its exponentially
        weighted mean over the days before (:math:`m_d = m_{d-1} + (\ln Q_d - m_{d-1})/L`, :math:`L` this
        many days, :math:`m_0 = \ln Q_0`): a rising or falling flow against a steady one (coefficient
        ``flow_anomaly``).
    coef : tuple of str
        Names of the regressors in ``rows`` (``"intercept"``, ``"ln_q"``, ``"sin"``, ``"cos"`` by default).
    lower, upper : (n,) ndarray, optional
        Each sample's limits; default the limit rule's: ``lower = y`` on censored samples (a detection limit),
        ``-inf`` elsewhere, ``upper = +inf``. A censored sample strictly between finite limits is an interval
        reading (its likelihood the predictive probability of the interval).
    residual_ar : bool
        Include the AR(1) residual (else its state stays 0 and only the sample noise remains).
    fast_residual : bool
        A second Ornstein-Uhlenbeck residual beside the first, with its own time scale and sd (parameters
        ``log_tau_fast_days``, ``log_sigma_fast``): a residual with a short memory (storm events, days)
        and a long one (months); needs ``residual_ar``.
    flow_spline_knots : int
        If 3 or more, a smooth nonlinear response to the flow: the restricted (natural) cubic spline in
        :math:`z = \ln Q - \overline{\ln Q}` with this many knots :math:`k_1 < \dots < k_K` at fixed quantiles
        of the daily z (Harrell's: 0.1, 0.5, 0.9 for 3 knots; 0.05, 0.35, 0.65, 0.95 for 4; 0.05, 0.275, 0.5,
        0.725, 0.95 for 5), adding the K - 2 regressors (coefficients ``ln_q_rcs1`` ...)

        .. math::

            s_j(z) = \frac{(z - k_j)_+^3 - (z - k_{K-1})_+^3\,\frac{k_K - k_j}{k_K - k_{K-1}}
                     + (z - k_K)_+^3\,\frac{k_{K-1} - k_j}{k_K - k_{K-1}}}{(k_K - k_1)^2},
            \quad j = 1..K-2,

        each cubic between the knots and linear beyond the outer ones, so that with the ln Q column the
        flow response is a natural cubic spline (WRTDS fits a different regression at each flow; this is its
        smooth global counterpart).
    slow_anomaly_days : float
        If positive, a second flow anomaly regressor over this many days (coefficient ``flow_anomaly_slow``),
        :math:`\ln Q_d - m'_{d-1}` with :math:`m'` the exponentially weighted mean of ``flow_anomaly_days``'s
        definition over the longer window: a wet or dry season (months) beside the storm (weeks).
    anomaly_slope : bool
        Add the regressor :math:`a_d z_d` (the flow anomaly times the centred ln Q, coefficient
        ``flow_anomaly_ln_q``): the response to a rising or falling flow depends on the flow itself; needs
        ``flow_anomaly_days``.
    slope_trend : bool
        Add the regressor :math:`z_d (t_d - \bar t)/10` (coefficient ``ln_q_trend``, :math:`t` in decimal years,
        :math:`\bar t` the middle of the daily grid): an ln Q slope that changes linearly over the decades;
        needs ``years``.
    flow_variance_square : bool
        The sample noise's log sd also carries :math:`\gamma_2 z^2` (parameter ``gamma_flow_sq``): a noise sd
        that can be larger (or smaller) at both extremes of the flow; needs ``flow_variance``.
    anomaly_variance : bool
        The sample noise's log sd also carries :math:`\gamma_a |a_d|` (parameter ``gamma_anomaly``, :math:`a_d` the
        flow anomaly): a sample taken while the flow rises or falls fast (a storm) scatters more; needs
        ``flow_anomaly_days``.
    variance_trend : bool
        The sample noise's log sd also carries :math:`\gamma_t (t - \bar t)/10` (parameter
        ``gamma_trend``, per decade): a record whose scatter changes over the years; needs ``years``.
    years : (D,) ndarray, optional
        The decimal year of every day of the grid (:meth:`from_record` sets it); needed by ``slope_trend`` and
        ``variance_trend``.
    noise : {"normal", "mixture"}
        The sample noise's law. ``"normal"``: :math:`v_d \sim N(0, s_d^2)`, :math:`s_d` the noise sd above.
        ``"mixture"``: a heavier-tailed two-component scale mixture,

        .. math::

            v_d \sim (1 - w)\,N(0, s_d^2) + w\,N(0, (c\,s_d)^2),

        a fraction w of the samples scattering c times wider (parameters ``logit_outlier_weight``,
        :math:`w = 1/(1 + e^{-\theta})`, and ``log_outlier_scale``, :math:`c = e^\theta`, unless fixed below).
        The filter's update is the exact posterior of the Gaussian prediction under the mixture (a mixture of the
        two components' censored updates, weighted by each one's evidence) collapsed to its mean and covariance
        (:func:`~tobitkf.experiments.records_common.mixture_update`), the likelihood the mixture's evidence
        :math:`\log((1 - w)\ell_1 + w\ell_2)` of each sample, and a sample's predictive the mixture of the two
        components' predictives (:meth:`predictive`). w = 0 is the ``"normal"`` model.
    outlier_weight, outlier_scale : float, optional
        With ``noise="mixture"``, fix w (in [0, 1)) or c (> 0) instead of fitting it (its parameter is then
        absent).

    Attributes
    ----------
    names : tuple of str
        The unconstrained parameters, in order: ``b_<coef>`` (the coefficients' prior means),
        ``log_tau_days``, ``log_sigma`` (the AR residual), ``log_r`` (the sample noise sd),
        ``gamma_flow``, ``gamma_flow_sq``, ``gamma_sin``, ``gamma_cos``, ``gamma_anomaly``, ``gamma_trend`` (the log noise sd's
        coefficients, those of the options chosen), ``log_sd_drift_<group>`` (the random walks' sd per year),
        then with ``noise="mixture"`` ``logit_outlier_weight``, ``log_outlier_scale`` (those not fixed).

    Raises
    ------
    ValueError
        Sample days not strictly increasing, ``rows`` not matching ``coef``, ``flow_variance`` without
        an ln Q regressor, an unknown ``noise``, a fixed ``outlier_weight`` outside [0, 1) or ``outlier_scale``
        not positive (:class:`~tobitkf.ValidationError`).
    """

    day: np.ndarray
    y: np.ndarray
    censored: np.ndarray
    rows: np.ndarray
    drift: tuple[str, ...] = ("intercept", "slope", "season")
    quadratic: bool = False
    flow_variance: bool = False
    season_variance: bool = False
    season_slope: bool = False
    harmonics: int = 1
    flow_anomaly_days: float = 0.0
    coef: tuple[str, ...] = ("intercept", "ln_q", "sin", "cos")
    residual_ar: bool = True
    fast_residual: bool = False
    slow_anomaly_days: float = 0.0
    flow_spline_knots: int = 0
    anomaly_slope: bool = False
    slope_trend: bool = False
    flow_variance_square: bool = False
    anomaly_variance: bool = False
    variance_trend: bool = False
    years: np.ndarray | None = None
    noise: str = "normal"
    outlier_weight: float | None = None
    outlier_scale: float | None = None
    lower: np.ndarray | None = None
    upper: np.ndarray | None = None
    names: tuple[str, ...] = field(init=False)

    GROUPS = {"intercept": ("intercept",), "slope": ("ln_q",), "season": ("sin", "cos"), "quadratic": ("ln_q_sq",)}

    def __post_init__(self) -> None:
        self.day = np.asarray(self.day, dtype=int)
        self.y = np.asarray(self.y, dtype=float)
        self.censored = np.asarray(self.censored, dtype=bool)
        gaps = np.diff(np.r_[-1, self.day])
        if np.any(gaps < 1):
            raise ValueError("day: expected strictly increasing sample days")
        self.gaps = gaps.astype(float)
        self.coef = tuple(self.coef)
        if self.rows.shape[1] != len(self.coef) + 1:
            raise ValueError(f"rows: expected {len(self.coef) + 1} columns (coef and the residual's 1)")
        if self.quadratic:
            z = self.rows[:, self.coef.index("ln_q")]
            self.rows = np.column_stack([self.rows[:, :-1], z**2 - np.mean(z**2), self.rows[:, -1:]])
            self.coef = self.coef + ("ln_q_sq",)
        if self.season_slope:
            z, si, co = (self.rows[:, self.coef.index(c)] for c in ("ln_q", "sin", "cos"))
            self.rows = np.column_stack([self.rows[:, :-1], z * si, z * co, self.rows[:, -1:]])
            self.coef = self.coef + ("ln_q_sin", "ln_q_cos")
        if self.harmonics not in (1, 2):
            raise ValidationError(f"harmonics: expected 1 or 2, found {self.harmonics!r}")
        if self.harmonics == 2:
            si, co = (self.rows[:, self.coef.index(c)] for c in ("sin", "cos"))
            self.rows = np.column_stack([self.rows[:, :-1], 2 * si * co, co**2 - si**2, self.rows[:, -1:]])
            self.coef = self.coef + ("sin2", "cos2")
        for days, name in ((self.flow_anomaly_days, "flow_anomaly"), (self.slow_anomaly_days, "flow_anomaly_slow")):
            if days > 0:
                anomaly = flow_anomaly(self.rows[:, self.coef.index("ln_q")], days)
                self.rows = np.column_stack([self.rows[:, :-1], anomaly, self.rows[:, -1:]])
                self.coef = self.coef + (name,)
        if self.years is not None:
            self.years = np.asarray(self.years, dtype=float)
            if self.years.shape != (self.rows.shape[0],):
                raise ValidationError(
                    f"years: expected one decimal year per day of rows ({self.rows.shape[0]}), found shape "
                    f"{self.years.shape}"
                )
        for opt in ("slope_trend", "variance_trend"):
            if getattr(self, opt) and self.years is None:
                raise ValidationError(f"{opt}: needs years (the decimal year of every day of rows), found None")
        decades = None if self.years is None else (self.years - 0.5 * (self.years[0] + self.years[-1])) / 10.0
        if self.flow_spline_knots:
            z = self.rows[:, self.coef.index("ln_q")]
            basis = flow_spline_basis(z, spline_knots(z, self.flow_spline_knots))
            self.rows = np.column_stack([self.rows[:, :-1], basis, self.rows[:, -1:]])
            self.coef = self.coef + tuple(f"ln_q_rcs{j + 1}" for j in range(basis.shape[1]))
        if self.anomaly_slope:
            if "flow_anomaly" not in self.coef:
                raise ValidationError("anomaly_slope: needs flow_anomaly_days > 0 (the flow anomaly regressor)")
            a, z = (self.rows[:, self.coef.index(c)] for c in ("flow_anomaly", "ln_q"))
            self.rows = np.column_stack([self.rows[:, :-1], a * z, self.rows[:, -1:]])
            self.coef = self.coef + ("flow_anomaly_ln_q",)
        if self.slope_trend:
            assert decades is not None
            z = self.rows[:, self.coef.index("ln_q")]
            self.rows = np.column_stack([self.rows[:, :-1], z * decades, self.rows[:, -1:]])
            self.coef = self.coef + ("ln_q_trend",)
        if self.fast_residual:
            if not self.residual_ar:
                raise ValidationError("fast_residual: needs residual_ar (the second residual beside the first)")
            self.rows = np.column_stack([self.rows, self.rows[:, -1:]])  # its column of ones
        self.nres = 1 + int(self.fast_residual)  # residual states, last
        self.nb = self.rows.shape[1] - self.nres  # regression coefficients
        self.nx = self.nb + self.nres
        self.C = self.rows[self.day]  # (n, nx)
        # the states that move: the drifting coefficients and the residual(s); a static coefficient has no noise
        # and no prior variance, so it is a constant that enters the reading's mean as an offset (run)
        moving = [self.coef.index(c) for g in self.drift for c in self.GROUPS[g]]
        if self.residual_ar or not moving:
            moving += list(range(self.nb, self.nx))
        self.dyn = np.array(sorted(moving), dtype=int)
        self.zcol = self.coef.index("ln_q") if "ln_q" in self.coef else None
        if self.flow_variance and self.zcol is None:
            raise ValueError("flow_variance: needs an ln_q regressor")
        self.z = self.C[:, self.zcol] if self.zcol is not None else np.zeros(self.y.size)
        # the daily covariates of the sample noise's log sd (gamma_flow, gamma_flow_sq, gamma_sin, gamma_cos,
        # gamma_trend, those chosen): V (D, nv), noise sd r exp(V_d gamma)
        zd = self.rows[:, self.zcol] if self.zcol is not None else None
        vcols: list[np.ndarray] = [zd] if self.flow_variance and zd is not None else []
        if self.flow_variance_square:
            if not self.flow_variance or zd is None:
                raise ValidationError("flow_variance_square: needs flow_variance (and an ln_q regressor)")
            vcols.append(zd**2)
        if self.season_variance:
            if "sin" not in self.coef or "cos" not in self.coef:
                raise ValidationError(f"season_variance: needs the sin and cos regressors, found coef={self.coef}")
            vcols += [self.rows[:, self.coef.index("sin")], self.rows[:, self.coef.index("cos")]]
        if self.anomaly_variance:
            if "flow_anomaly" not in self.coef:
                raise ValidationError("anomaly_variance: needs flow_anomaly_days > 0 (the flow anomaly regressor)")
            vcols.append(np.abs(self.rows[:, self.coef.index("flow_anomaly")]))
        if self.variance_trend:
            assert decades is not None
            vcols.append(decades)
        self.V = np.column_stack(vcols) if vcols else np.zeros((self.rows.shape[0], 0))
        if self.lower is None:
            self.lower = np.where(self.censored, self.y, -np.inf)
        self.lower = np.asarray(self.lower, dtype=float)
        self.upper = np.full(self.y.size, np.inf) if self.upper is None else np.asarray(self.upper, dtype=float)
        with np.errstate(invalid="ignore"):
            self.interval = self.censored & (self.y > self.lower) & (self.y < self.upper)
        if self.noise not in ("normal", "mixture"):
            raise ValidationError(f"noise: expected 'normal' or 'mixture', found {self.noise!r}")
        if self.outlier_weight is not None and not 0.0 <= self.outlier_weight < 1.0:
            raise ValidationError(f"outlier_weight: expected a weight in [0, 1), found {self.outlier_weight!r}")
        if self.outlier_scale is not None and not self.outlier_scale > 0.0:
            raise ValidationError(f"outlier_scale: expected a positive sd ratio, found {self.outlier_scale!r}")
        mixture = self.noise == "mixture"
        self.names = (
            tuple(f"b_{c}" for c in self.coef)
            + (("log_tau_days", "log_sigma") if self.residual_ar else ())
            + (("log_tau_fast_days", "log_sigma_fast") if self.fast_residual else ())
            + ("log_r",)
            + (("gamma_flow",) if self.flow_variance else ())
            + (("gamma_flow_sq",) if self.flow_variance_square else ())
            + (("gamma_sin", "gamma_cos") if self.season_variance else ())
            + (("gamma_anomaly",) if self.anomaly_variance else ())
            + (("gamma_trend",) if self.variance_trend else ())
            + tuple(f"log_sd_drift_{g}" for g in self.drift)
            + (("logit_outlier_weight",) if mixture and self.outlier_weight is None else ())
            + (("log_outlier_scale",) if mixture and self.outlier_scale is None else ())
        )

    @classmethod
    def from_record(
        cls,
        rec: Any,
        drift: tuple[str, ...] = ("intercept", "slope", "season"),
        **options: Any,
    ) -> RiverModel:
        """The model of a :class:`tobitkf.data.SampleRecord` (sample days located on its daily record); ``options``
        are the other fields (``quadratic``, ``flow_variance``, ``season_slope``, ``harmonics``,
        ``flow_anomaly_days``)."""
        from ..inference.wrtds import decimal_year

        lq = np.log(rec.daily_q)
        t = decimal_year(rec.daily_date)
        rows = np.column_stack(
            [np.ones(lq.size), lq - lq.mean(), np.sin(2 * np.pi * t), np.cos(2 * np.pi * t), np.ones(lq.size)]
        )
        options.setdefault("years", t)
        day = np.searchsorted(rec.daily_date, rec.date)
        if np.any(rec.daily_date[np.minimum(day, lq.size - 1)] != rec.date):
            raise ValueError("rec: a sample day is not in the daily discharge record")
        s = rec.series()
        return cls(
            day=day,
            y=s.y,
            censored=s.censored,
            lower=s.lower,
            upper=s.upper,
            rows=rows,
            drift=tuple(drift),
            **options,
        )

    @property
    def p(self) -> int:
        return len(self.names)

    @property
    def n_samples(self) -> int:
        return int(self.y.size)

    # ---- parameters
    def natural(self, theta: np.ndarray) -> dict[str, np.ndarray]:
        """The model's quantities from unconstrained parameters ``theta`` (..., p)."""
        th = np.asarray(theta, dtype=float)
        nb = self.nb
        q = np.zeros(th.shape[:-1] + (nb,))
        j = nb + 2 * (int(self.residual_ar) + int(self.fast_residual))  # index of log_r
        nv = self.V.shape[1]
        off = j + 1 + nv
        for i, g in enumerate(self.drift):
            for c in self.GROUPS[g]:
                q[..., self.coef.index(c)] = np.exp(2 * th[..., off + i])
        batch = th.shape[:-1]
        weight, ratio = np.zeros(batch), np.ones(batch)
        if self.noise == "mixture":
            from scipy.special import expit

            k = off + len(self.drift)
            if self.outlier_weight is None:
                weight, k = expit(th[..., k]), k + 1
            else:
                weight = np.full(batch, float(self.outlier_weight))
            ratio = np.exp(th[..., k]) if self.outlier_scale is None else np.full(batch, float(self.outlier_scale))
        return {
            "b": th[..., :nb],
            "tau": np.exp(th[..., nb]) if self.residual_ar else np.ones(th.shape[:-1]),
            "sigma": np.exp(th[..., nb + 1]) if self.residual_ar else np.zeros(th.shape[:-1]),
            "tau_fast": np.exp(th[..., nb + 2]) if self.fast_residual else np.ones(th.shape[:-1]),
            "sigma_fast": np.exp(th[..., nb + 3]) if self.fast_residual else np.zeros(th.shape[:-1]),
            "r": np.exp(th[..., j]),
            "gamma": th[..., j + 1 : j + 1 + nv],  # (..., nv): the log sd's coefficients on the columns of V
            "q": q,  # per year
            "w": weight,  # the outlier weight and sd ratio of the mixture noise (0 and 1 for normal noise)
            "c": ratio,
        }

    def noise_sd(self, nat: dict[str, np.ndarray], days: Any = None) -> np.ndarray:
        r"""The sample noise sd :math:`r\,e^{\gamma^T v_d}` (per run (N, T)) on the days ``days`` (T,) of the
        daily grid (default every day), :math:`v_d` the row of ``V`` (the centred ln Q with ``flow_variance``, its
        square with ``flow_variance_square``, sin and cos with ``season_variance``, the flow anomaly's size with
        ``anomaly_variance``, decades from the middle of the grid with ``variance_trend``)."""
        V = self.V if days is None else self.V[np.asarray(days, dtype=int)]
        shift = np.einsum("...j,tj->...t", nat["gamma"], V)
        return nat["r"][..., None] * np.exp(shift)

    def noise_var(self, nat: dict[str, np.ndarray], k: Any) -> np.ndarray:
        """The sample noise variance of sample(s) k, per run (N,) or (N, len(k)) (:meth:`noise_sd` squared)."""
        v = self.noise_sd(nat, self.day[np.atleast_1d(k)]) ** 2
        return v if np.ndim(k) else v[..., 0]

    def predictive(self, theta: np.ndarray, samples: Any, latent_var: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r"""The components of the predictive of the ln value of sample ``samples[i]`` under ``theta[i]``, given the
        variance ``latent_var[i]`` of its latent mean :math:`C_i x_i`: standard deviations (K, 2)
        :math:`\sqrt{v_i + s_i^2}`, :math:`\sqrt{v_i + c^2 s_i^2}` and weights (K, 2) :math:`(1 - w, w)`
        (:math:`w = 0` for ``noise="normal"``, whose predictive is the first component alone)."""
        th = np.atleast_2d(np.asarray(theta, dtype=float))
        nat = self.natural(th)
        k = np.asarray(samples, dtype=int)
        r2 = self.noise_var(nat, np.arange(self.n_samples))[np.arange(th.shape[0]), k]
        v = np.asarray(latent_var, dtype=float)
        sds = np.sqrt(np.stack([v + r2, v + nat["c"] ** 2 * r2], axis=1))
        return sds, np.stack([1.0 - nat["w"], nat["w"]], axis=1)

    def start(self) -> np.ndarray:
        """Starting values: least squares on the uncensored samples, a month's correlation, small drifts (and for
        the mixture noise 5 % of the samples scattering three times wider)."""
        ok = ~self.censored
        b, *_ = np.linalg.lstsq(self.C[ok, : self.nb], self.y[ok], rcond=None)
        resid = np.std(self.y[ok] - self.C[ok, : self.nb] @ b)
        return np.r_[
            b,
            [np.log(30.0), np.log(0.7 * resid)] if self.residual_ar else [],
            [np.log(3.0), np.log(0.3 * resid)] if self.fast_residual else [],
            np.log(0.5 * resid),
            [0.0] * self.V.shape[1],
            [np.log(0.05)] * len(self.drift),
            [np.log(0.05 / 0.95)] if self.noise == "mixture" and self.outlier_weight is None else [],
            [np.log(3.0)] if self.noise == "mixture" and self.outlier_scale is None else [],
        ]

    # ---- the system, per run
    def continuous(self, nat: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        r"""The diagonal continuous-time model (:func:`~tobitkf.experiments.records_common.gap_matrices`) of
        each run, per day: rates (N, nx) (0 for the coefficients' random walks, :math:`1/\tau` for the AR
        residual) and diffusions (N, nx) (:math:`q_j/365.25`, :math:`2\sigma^2/\tau`)."""
        N, nb = nat["tau"].shape[0], self.nb
        rate = np.zeros((N, self.nx))
        rate[:, nb] = 1.0 / nat["tau"]
        diffusion = np.empty((N, self.nx))
        diffusion[:, :nb] = nat["q"] / _YEAR
        diffusion[:, nb] = 2.0 * nat["sigma"] ** 2 / nat["tau"]
        if self.fast_residual:
            rate[:, nb + 1] = 1.0 / nat["tau_fast"]
            diffusion[:, nb + 1] = 2.0 * nat["sigma_fast"] ** 2 / nat["tau_fast"]
        return rate, diffusion

    def _step_matrices(self, nat: dict[str, np.ndarray], gap: Any) -> tuple[np.ndarray, np.ndarray]:
        """Diagonals of A and Q (D, nx) of one run over gaps ``gap`` (D,) days (or one gap: (1, nx))."""
        rate, diffusion = self.continuous(nat)
        a, qd = gap_matrices(rate[:1], diffusion[:1], np.atleast_1d(np.asarray(gap, dtype=float)))
        return a[0], qd[0]

    def prior(self, nat: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        N, nb = nat["tau"].shape[0], self.nb
        x0 = np.zeros((N, self.nx))
        x0[:, :nb] = nat["b"]
        P0 = np.zeros((N, self.nx, self.nx))
        P0[:, nb, nb] = nat["sigma"] ** 2
        if self.fast_residual:
            P0[:, nb + 1, nb + 1] = nat["sigma_fast"] ** 2
        return x0, P0

    def reduced(self, nat: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
        r"""The model on its moving states only (``dyn``: the drifting coefficients and the residuals).

        A static coefficient :math:`\beta_j = b_j` has no noise and no prior variance, and a drifting one is
        :math:`\beta_{j,d} = b_j + \delta_{j,d}` with :math:`\delta_{j,0} = 0`: the state
        :math:`x_d = \bar x + E\,s_d` with :math:`\bar x = (b, 0)`, :math:`E` the columns ``dyn`` of the
        identity and :math:`s_d` (the deviations of the drifting coefficients and the residuals) starting at
        :math:`s_0 \sim N(0, \mathrm{diag}(0, \sigma^2))`, so the reading is :math:`C_d E s_d + C_d \bar x +
        v_d`, the second term a known offset per run. The filter on :math:`s` equals the filter on :math:`x`
        (the static rows of the gain are 0) at the cost of a model of ``len(dyn)`` states instead of ``nx``.

        Returns
        -------
        s0 (N, m), S0 (N, m, m), rate (N, m), diffusion (N, m), xbar (N, nx); m = ``len(dyn)``
        """
        x0, P0 = self.prior(nat)
        rate, diffusion = self.continuous(nat)
        dyn = self.dyn
        s0 = np.zeros((x0.shape[0], dyn.size))
        return s0, P0[:, dyn][:, :, dyn], rate[:, dyn], diffusion[:, dyn], x0

    def run(
        self, theta: np.ndarray, y: np.ndarray | None = None, *, smooth: bool = False, compiled: bool | None = None
    ) -> dict[str, Any]:
        r"""The assumed-density filter on the samples' days for a batch of parameter vectors (on the moving
        states, :meth:`reduced`; the filtered and smoothed results hold those states).

        Parameters
        ----------
        theta : (N, p) ndarray
            One parameter vector per run.
        y : (N, n) ndarray, optional
            Readings per run (NaN = removed); default the record's for every run.
        smooth : bool
            Also run the RTS pass and return the smoothed ln-value predictive of every sample.
        compiled : bool, optional
            The mixture noise's filter compiled (default when numba imports) or its numpy reference (False), as
            :func:`adf_pass`.

        Returns
        -------
        dict
            See :func:`adf_pass`: ``loglik`` (N,), ``terms`` (N, n); with ``smooth`` ``mean``, ``sd`` (N, n) (the
            sd of the mixture with ``noise="mixture"``: :meth:`predictive` gives its components), ``latent_var``.
        """
        theta = np.atleast_2d(np.asarray(theta, dtype=float))
        N, T = theta.shape[0], self.n_samples
        Y = np.broadcast_to(self.y, (N, T)) if y is None else np.asarray(y, dtype=float)
        nat = self.natural(theta)
        s0, S0, rate, diffusion, xbar = self.reduced(nat)
        r2 = self.noise_var(nat, np.arange(T))
        flags = None
        if self.interval.any():  # interval readings need the indicator (a removed reading is not flagged)
            flags = self.censored & ~np.isnan(Y)
        offset = xbar @ self.C.T  # (N, n): C_k xbar
        mixture = (nat["w"], nat["c"] ** 2) if self.noise == "mixture" else None
        return adf_pass(
            s0, S0, rate, diffusion, self.gaps, self.C[:, self.dyn], Y, self.lower, self.upper, r2, dy=offset,
            smooth=smooth, censored=flags, mixture=mixture, compiled=compiled,
        )  # fmt: skip

    def daily_smooth(self, theta: np.ndarray) -> dict[str, np.ndarray]:
        r"""The smoothed state on every day of the daily grid, for one parameter vector.

        The filter and the package's RTS pass (:func:`~tobitkf.filters.smoothing.rts_smooth`) run on the
        samples' days (:meth:`run`). A day without a sample is only a prediction step, so the RTS pass over
        the daily grid would carry the smoothed state from the next sample day :math:`k+1` back to day
        :math:`d` through a chain of pure predictions; the chain collapses to one step, taken for every day
        at once: with :math:`\bar x_d = a(\Delta_d) \odot \hat x_{k|k}`,
        :math:`\bar P_d = A(\Delta_d)P_{k|k}A(\Delta_d)^T + Q(\Delta_d)` the prediction from the last sample
        :math:`k` before d (the prior before the first) and :math:`A_r = A(t_{k+1} - d)`,

        .. math::

            J_d = \bar P_d A_r^T P_{k+1|k}^{+}, \quad
            \hat x_{d|D} = \bar x_d + J_d(\hat x_{k+1|D} - \hat x_{k+1|k}), \quad
            P_{d|D} = \bar P_d + J_d(P_{k+1|D} - P_{k+1|k})J_d^T

        (the pseudo-inverse of :func:`~tobitkf.filters.smoothing.solve_psd`, as the RTS pass); a sample day
        takes the sample's smoothed moments, a day after the last sample the prediction. All of this on the
        moving states :math:`s` of :meth:`reduced`, mapped back to :math:`x = \bar x + E s` (the static
        coefficients' rows and columns of :math:`P_{d|D}` are 0). Equal to :func:`tobitkf.smooth` on the daily
        system (:meth:`daily_system`), tested.

        Returns
        -------
        dict
            ``mean`` (D, nx), ``cov`` (D, nx, nx) of :math:`x_{d|D}`; ``ln_mean``, ``ln_sd`` (D,): the latent
            daily ln concentration :math:`C_d x_d` (without the sample noise), and ``noise_sd`` (D,) (of the first,
            narrower component with ``noise="mixture"``).
        """
        from ..filters.smoothing import solve_psd

        th = np.atleast_2d(np.asarray(theta, dtype=float))
        nat = self.natural(th)
        out = self.run(th, smooth=True)
        f, sm = out["filtered"], out["smoothed"]
        D, n = self.rows.shape[0], self.n_samples
        days = np.arange(D)
        dyn = self.dyn
        x0, P0, rate, diffusion, xbar = self.reduced(nat)  # the moving states s (reduced), x = xbar + E s
        rate, diffusion = rate[:1], diffusion[:1]

        def step_matrices(gap: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            a, qd = gap_matrices(rate, diffusion, gap)
            return a[0], qd[0]

        m = dyn.size
        # the prediction to each day from the last sample strictly before it (index 0: the prior, day -1)
        prev = np.searchsorted(self.day, days, side="left") - 1
        xf = np.concatenate([x0, f.mean[0]])
        Pf = np.concatenate([P0, f.cov[0]])
        t_prev = np.where(prev >= 0, self.day[np.maximum(prev, 0)], -1)
        a, qd = step_matrices((days - t_prev).astype(float))
        x = a * xf[prev + 1]
        P = Pf[prev + 1] * a[:, :, None] * a[:, None, :]
        P[:, np.arange(m), np.arange(m)] += qd
        nxt = prev + 1  # the next sample on or after each day (n: none)
        on = nxt < n
        k = np.minimum(nxt, n - 1)
        sample_day = on & (self.day[k] == days)
        between = np.flatnonzero(on & ~sample_day)
        kb = k[between]
        ar, _ = step_matrices((self.day[kb] - days[between]).astype(float))
        Pp = f.pred_cov[0][kb]
        J = np.swapaxes(solve_psd(Pp, ar[:, :, None] * P[between]), -1, -2)  # P_d A_r^T Pp^+ (Pp symmetric)
        x[between] += np.einsum("dij,dj->di", J, sm.mean[0][kb] - f.pred_mean[0][kb])
        P[between] += J @ (sm.cov[0][kb] - Pp) @ np.swapaxes(J, -1, -2)
        x[sample_day] = sm.mean[0][k[sample_day]]
        P[sample_day] = sm.cov[0][k[sample_day]]
        rd = self.rows[:, dyn]
        ln_mean = np.einsum("dj,dj->d", x, rd) + self.rows @ xbar[0]
        ln_var = np.einsum("dij,di,dj->d", P, rd, rd)
        X = np.broadcast_to(xbar[0], (D, self.nx)).copy()
        X[:, dyn] += x
        PX = np.zeros((D, self.nx, self.nx))
        PX[:, dyn[:, None], dyn[None, :]] = P
        noise = self.noise_sd(nat)[0]
        return {
            "mean": X,
            "cov": PX,
            "ln_mean": ln_mean,
            "ln_sd": np.sqrt(np.maximum(ln_var, 0)),
            "noise_sd": noise,
        }

    def daily_system(self, theta: np.ndarray):
        """The model on the daily grid as a :class:`~tobitkf.LinearSystem` (time-varying C and R), the readings
        (D, 1) (NaN on days without a sample), the :class:`~tobitkf.Censoring` and the indicator (D, 1).

        Raises
        ------
        ValidationError
            ``noise="mixture"`` (a LinearSystem's noise is Gaussian)."""
        from .. import Censoring, LinearSystem

        if self.noise != "normal":
            raise ValidationError(f"daily_system: needs noise='normal' (a LinearSystem's noise), found {self.noise!r}")

        nat = self.natural(np.asarray(theta, dtype=float)[None])
        a, qd = self._step_matrices(nat, 1.0)
        x0, P0 = self.prior(nat)
        D = self.rows.shape[0]
        y = np.full((D, 1), np.nan)
        y[self.day, 0] = self.y
        cens = np.zeros((D, 1), dtype=bool)
        cens[self.day, 0] = self.censored
        lower = np.full((D, 1), -np.inf)
        lower[self.day, 0] = self.lower
        sys = LinearSystem(
            A=np.diag(a[0]),
            C=self.rows[:, None, :],
            Q=np.diag(qd[0]),
            R=(self.noise_sd(nat)[0] ** 2)[:, None, None],
            x0=x0[0],
            P0=P0[0],
        )
        upper = np.full((D, 1), np.inf)
        upper[self.day, 0] = self.upper
        return sys, y, Censoring(lower=lower, upper=upper), cens

    # ---- likelihood derivatives by finite differences, batched
    def loglik_and_gradient(
        self, theta: np.ndarray, y: np.ndarray | None = None, h: float = _FD_STEP
    ) -> tuple[np.ndarray, np.ndarray]:
        """Log-likelihoods (N,) and central-difference gradients (N, p) of N runs (readings ``y`` (N, n) per
        run, default the record's), in one batched filter pass of N (2p + 1) runs."""

        def ll(pts: np.ndarray, rep: int) -> np.ndarray:
            Y = None if y is None else np.repeat(np.asarray(y, dtype=float), rep, axis=0)
            return self.run(pts, Y)["loglik"]

        return fd_gradient(ll, theta, h)

    def hessian(self, theta: np.ndarray, h: float = 1e-3) -> np.ndarray:
        """Central-difference Hessian (p, p) of the log-likelihood at one ``theta``, one batched pass."""
        return fd_hessian(lambda pts: self.run(pts)["loglik"], theta, h)


def batched_loo_refit(
    model: RiverModel,
    theta: np.ndarray,
    inv_neg_hessian: np.ndarray,
    samples: np.ndarray,
    *,
    gtol: float = 1e-4,
    max_iter: int = 30,
) -> dict[str, Any]:
    r"""Leave-one-out refits of the model, all at once: run i holds the record without sample ``samples[i]``.

    A batched BFGS (maximising each run's log-likelihood): every run starts at the full fit ``theta``
    with the inverse of the full fit's observed information as its inverse Hessian; each iteration
    evaluates every active run's central-difference gradient in one filter pass, takes the quasi-Newton
    step with backtracking (Armijo, halving, batched), and updates each run's inverse Hessian. A run
    stops when the largest gradient component is below ``gtol``.

    Returns
    -------
    dict
        ``theta`` (K, p), ``loglik`` (K,), ``gradient_max`` (K,), ``iterations`` (K,), ``converged`` (K,),
        ``mean``/``sd`` (K,): the smoothed predictive of each removed sample's ln value at its refit (its mean
        and sd), ``component_sd``/``component_weight`` (K, 2): its components (:meth:`RiverModel.predictive`;
        one Gaussian, weights (1, 0), for ``noise="normal"``).
    """
    samples = np.asarray(samples, dtype=int)
    K, p = samples.size, model.p
    Y = np.repeat(model.y[None], K, axis=0)
    Y[np.arange(K), samples] = np.nan
    th = np.repeat(np.asarray(theta, dtype=float)[None], K, axis=0)
    Hinv = np.repeat(np.asarray(inv_neg_hessian, dtype=float)[None], K, axis=0)
    f, g = model.loglik_and_gradient(th, Y)
    iters = np.zeros(K, dtype=int)
    active = np.max(np.abs(g), axis=1) >= gtol
    for _ in range(max_iter):
        if not active.any():
            break
        a = np.flatnonzero(active)
        d = np.einsum("kij,kj->ki", Hinv[a], g[a])  # ascent direction
        slope = np.einsum("ki,ki->k", g[a], d)
        step = np.ones(a.size)
        new_th = th[a] + d
        new_f = model.run(new_th, Y[a])["loglik"]
        for _ls in range(20):
            bad = ~(new_f >= f[a] + 1e-4 * step * slope)
            if not bad.any():
                break
            step[bad] *= 0.5
            new_th[bad] = th[a][bad] + step[bad, None] * d[bad]
            new_f[bad] = model.run(new_th[bad], Y[a][bad])["loglik"]
        f_new, g_new = model.loglik_and_gradient(new_th, Y[a])
        s = new_th - th[a]
        yv = -(g_new - g[a])  # gradient change of the negative log-likelihood
        sy = np.einsum("ki,ki->k", s, yv)
        ok = sy > 1e-12
        Hi = Hinv[a]
        if ok.any():
            rho = 1.0 / sy[ok]
            I = np.eye(p)
            V = I - rho[:, None, None] * np.einsum("ki,kj->kij", s[ok], yv[ok])
            Hi[ok] = V @ Hi[ok] @ V.swapaxes(1, 2) + rho[:, None, None] * np.einsum("ki,kj->kij", s[ok], s[ok])
        Hinv[a] = Hi
        th[a], f[a], g[a] = new_th, f_new, g_new
        iters[a] += 1
        active[a] = np.max(np.abs(g_new), axis=1) >= gtol
    sm = model.run(th, Y, smooth=True)
    idx = np.arange(K)
    sds, weights = model.predictive(th, samples, sm["latent_var"][idx, samples])
    return {
        "theta": th,
        "loglik": f,
        "gradient_max": np.max(np.abs(g), axis=1),
        "iterations": iters,
        "converged": ~active,
        "mean": sm["mean"][idx, samples],
        "sd": sm["sd"][idx, samples],
        "component_sd": sds,
        "component_weight": weights,
    }
