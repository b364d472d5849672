r"""Assumed-density filter (ADF) for censored readings: the exact-moment Gaussian update.

Model (the package's :class:`~tobitkf.LinearSystem` with Tobit censoring, Miller (2015) (3.18)):
:math:`x_k = A_{k-1}x_{k-1} + B^u_ku_k + w_{k-1}`, :math:`y^*_k = C_kx_k + D_ku_k + v_k`,
:math:`y_k = \mathrm{clip}(y^*_k, l_k, h_k)`; R diagonal when m > 1 (as the TKF's Assumption A2),
R = 0 allowed (a state observed exactly when not censored).

The filter keeps a Gaussian :math:`N(\bar x, \bar P)` and replaces each update by the exact moments of
the posterior (moment matching, "assumed density filtering"; Maybeck 1982 §12.7, Minka 2001 ch. 3):

* uncensored readings (jointly): the Kalman update, exact;
* a reading censored at the lower limit l (then each censored channel in turn): with the latent
  :math:`z = C_lx + d_l + v_l \sim N(\mu, s^2)`, :math:`\mu = C_l\bar x + d_l`,
  :math:`s^2 = C_l\bar PC_l^T + R_{ll}`, the posterior :math:`p(x \mid z \le l)` has the moments

  .. math::

      K = \bar PC_l^T/s^2, \qquad E[x \mid z\le l] = \bar x + K(m_{tr} - \mu), \qquad
      \mathrm{Cov}[x \mid z \le l] = \bar P - K(s^2 - V_{tr})K^T,

  :math:`m_{tr}`, :math:`V_{tr}` the mean and variance of :math:`z` truncated to :math:`z \le l`
  (:func:`~tobitkf.censored_moments`); the upper limit alike with :math:`z \ge h`. This is the shared
  :func:`~tobitkf.filters.core.measurement_update` with ``observed`` = :math:`m_{tr}` and ``retained``
  = :math:`V_{tr}` (its :math:`KVK^T` term).

Its log-likelihood (:func:`~tobitkf.inference.likelihood.adf_log_likelihood`) adds, per step, the
predictive density of the uncensored readings and the predictive mass of each censored one,

.. math::

    \log p(y_k \mid y_{1:k-1}) \approx \log N(y_{k,u}; \hat y_u, S_{uu})
      + \sum_{l\ \text{censored}} \log\Phi\!\Big(\pm\frac{\text{limit}_l - \mu_l}{s_l}\Big),

exact for one step from a Gaussian prior (tested against quadrature), approximate over several
censored steps (the filtered density is no longer Gaussian).

Which readings are censored: an explicit indicator ``censored`` (..., T, m) when the data record one;
default the limit rule (a reading within ``rtol`` of a finite limit).

Time convention: :math:`x_0 \sim N(\bar x_0, P_0)` the prior, :math:`y_1` at index 0, output row k-1
holds :math:`\hat x_{k|k}`, :math:`P_{k|k}` and the prediction :math:`\bar x_{k|k-1}`, :math:`\bar P_{k|k-1}`.

This module is the project's own small ADF, written for the smoother and the fits; the
yardstick issue's :class:`AssumedDensityTobitFilter` is meant to replace it (the smoothers and fits
only use :meth:`ADFilter.filter` and its ``extras["log_lik"]``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.special import log_ndtr

from .._validation import ShapeError, ValidationError, check_instance
from ..censored import censored_moments
from ..channels.censoring import Censoring
from ..filters.core import (
    FilterResult,
    FilterState,
    MeasurementPrediction,
    check_keywords,
    measurement_update,
    time_update,
)
from ..filters.kalman import LinearGaussianFamily
from ..models.linear import LinearSystem
from ._common import censoring_sides, gaussian_log_density

__all__ = ["censored_reading_update", "uncensored_update", "ADFilter"]

_FORMS = ("standard", "joseph")


def uncensored_update(
    x: np.ndarray,
    P: np.ndarray,
    y: np.ndarray,
    C: np.ndarray,
    R: np.ndarray,
    dy: Any,
    valid: np.ndarray,
    form: str = "standard",
):
    r"""Kalman update with the valid (uncensored, present) channels and their log predictive density.

    Parameters
    ----------
    x : (N, n) ; P : (N or 1, n, n) ; y : (N, m) ; C : (m, n) ; R : (m, m) ; dy : (N, m) or 0
    valid : (N, m) bool
    form : {"standard", "joseph"}

    Returns
    -------
    x : (N, n) ; P : (N or 1, n, n) ; log_density : (N,) :math:`\log N(y_o; C_o\bar x + d_o, C_o\bar PC_o^T + R_{oo})`
    """
    yhat = x @ C.T + dy
    S = C @ P @ C.T + R
    ll = gaussian_log_density(y - yhat, S, valid)
    if not valid.any():
        return x, P, ll
    mp = MeasurementPrediction(expected=yhat, H0=C, noise=R[None], valid=valid)
    xn, Pn, _, _, _ = measurement_update(x, P, None, np.where(valid, y, 0.0), mp, form)
    return xn, Pn, ll


def censored_reading_update(
    x: np.ndarray,
    P: np.ndarray,
    c: np.ndarray,
    r: float,
    dy: Any,
    limit: np.ndarray,
    side: np.ndarray,
    form: str = "standard",
):
    r"""Exact-moment update of a Gaussian prior by one scalar reading censored at ``limit``.

    The prior :math:`N(\bar x, \bar P)`, the latent :math:`z = c^Tx + d + v`, :math:`v \sim N(0, r)`;
    the event :math:`z \le l` (``side`` = -1) or :math:`z \ge h` (``side`` = +1). Returns the mean and
    covariance of :math:`p(x \mid \text{event})` (see the module docstring) and the log predictive mass
    :math:`\log P(\text{event}) = \log\Phi(\pm(\text{limit} - \mu)/s)` (``log_ndtr``, finite far into
    the tails). Runs with ``side`` = 0 are not updated and get 0. A degenerate latent (:math:`s = 0`)
    gives the indicator of the event (0 or ``-inf``) and no update.

    Parameters
    ----------
    x : (N, n) ; P : (N or 1, n, n) ; c : (n,) ; r : float >= 0 ; dy : (N,) or 0 ; limit : (N,) ; side : (N,) int
    form : {"standard", "joseph"}

    Returns
    -------
    x : (N, n) ; P : (N or 1, n, n) ; log_mass : (N,)
    """
    mu = x @ c + dy
    s2 = np.einsum("i,...ij,j->...", c, P, c) + r
    s2 = np.broadcast_to(s2, mu.shape)
    on = side != 0
    ok = on & (s2 > np.finfo(float).tiny)
    s = np.sqrt(np.where(ok, s2, 1.0))
    lim = np.where(on, limit, 0.0)
    zs = np.where(side < 0, (lim - mu) / s, (mu - lim) / s)
    log_mass = np.where(ok, log_ndtr(zs), 0.0)
    degenerate = on & ~ok
    if degenerate.any():
        inside = np.where(side < 0, mu <= lim, mu >= lim)
        log_mass = np.where(degenerate, np.where(inside, 0.0, -np.inf), log_mass)
    if not ok.any():
        return x, P, log_mass
    lo = np.where(side > 0, lim, -np.inf)
    hi = np.where(side < 0, lim, np.inf)
    st = censored_moments(mu, s, np.where(ok, lo, -np.inf), np.where(ok, hi, np.inf))
    mp = MeasurementPrediction(
        expected=mu[:, None],
        H0=c[None, :],
        noise=np.array([[float(r)]]),
        observed=np.where(ok, st.truncated_mean, mu)[:, None],
        retained=np.where(ok, st.truncated_var, 0.0)[:, None],
        valid=ok[:, None],
    )
    xn, Pn, _, _, _ = measurement_update(x, P, None, mu[:, None], mp, form)
    return xn, Pn, log_mass


class ADFilter(LinearGaussianFamily):
    r"""Assumed-density (exact-moment) filter for censored readings on a :class:`~tobitkf.LinearSystem`.

    Parameters
    ----------
    system : LinearSystem
        The model; R diagonal when m > 1; R = 0 allowed.
    censoring : Censoring
        The limits (constant or ``(T, m)``).
    rtol : float, default 1e-12
        Tolerance of the limit rule (used when no indicator is given).
    covariance_update : {"standard", "joseph"}, default "standard"

    Raises
    ------
    ValidationError
        Non-diagonal R with m > 1, an unknown option.

    Notes
    -----
    ``filter(y, censored=...)`` and ``step(state, y, censored=...)`` take the recorded censoring
    indicator; without it the limit rule decides. ``extras`` of ``filter``: ``log_lik`` (..., T), the
    log predictive density/mass of each step (their sum is
    :func:`~tobitkf.inference.likelihood.adf_log_likelihood`), and ``side`` (..., T, m): -1 / +1 for a
    reading censored at the lower / upper limit, 0 otherwise. The equations are in the module docstring.

    Examples
    --------
    One reading censored at 0 from a standard normal prior: the posterior is the truncated normal
    :math:`z \le 0`, mean :math:`-\sqrt{2/\pi}`, and the log-likelihood is :math:`\log\tfrac12`.

    >>> import numpy as np, tobitkf as tk
    >>> from tobitkf.inference.adf import ADFilter
    >>> sys = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.0]], R=[[0.0]], x0=[0.0], P0=[[1.0]])
    >>> out = ADFilter(sys, tk.Censoring(lower=0.0)).filter([[0.0]])
    >>> bool(np.isclose(out.mean[0, 0], -np.sqrt(2 / np.pi))), bool(np.isclose(out.extras["log_lik"][0], np.log(0.5)))
    (True, True)
    """

    _name = "ADFilter"
    _step_options = ("censored",)

    def __init__(
        self, system: LinearSystem, censoring: Censoring, *, rtol: float = 1e-12, covariance_update: str = "standard"
    ):
        check_instance(system, LinearSystem, "system")
        check_instance(censoring, Censoring, "censoring")
        check_keywords({"covariance_update": covariance_update}, {"covariance_update": _FORMS})
        censoring.check(system.m)
        if isinstance(rtol, bool) or not isinstance(rtol, (int, float, np.floating)) or not rtol >= 0:
            raise ValidationError(f"rtol: expected a non-negative tolerance, got {rtol!r}")
        if system.m > 1:
            for k in (1,) if not system.R.varying else ():
                R = system.measurement_cov(k)
                if np.abs(R - np.diag(np.diagonal(R))).max() > 0:
                    raise ValidationError(
                        "R: the assumed-density filter updates censored channels one at a time "
                        "and needs a diagonal R when m > 1"
                    )
        self._setup_system(system)
        self.censoring = censoring
        self.rtol = float(rtol)
        self.covariance_update = covariance_update

    # the shared hooks ---------------------------------------------------------------
    def _sides(self, y: np.ndarray, k: int, censored: Any = None) -> np.ndarray:
        lo, hi = self.censoring.limits(k)
        return censoring_sides(y, lo, hi, censored, rtol=self.rtol)

    def _prepare_step_options(self, state: FilterState, options: dict[str, Any]) -> dict[str, Any]:
        c = options.get("censored")
        if c is None:
            return {}
        arr = np.asarray(c)
        want = state.batch_shape + (self.m,)
        try:
            arr = np.broadcast_to(arr, want)
        except ValueError:
            raise ShapeError(f"censored: expected this step's indicator of shape {want}, got {arr.shape}") from None
        return {"censored": arr.reshape(state.runs, self.m)}

    def _step_arrays(self, k: int, x, P, S, carry, y, u, options=None):
        options = options or {}
        tr = self._transition(k, u, carry)
        xp, Pp, _ = time_update(x, P, None, tr, "standard")
        side = options.get("side")
        if side is None:
            side = self._sides(y, k, options.get("censored"))
        sys_ = self.system
        C, R = sys_.measurement(k), sys_.measurement_cov(k)
        dy = self._feedthrough(k, u)
        dy = np.broadcast_to(dy, y.shape) if not np.isscalar(dy) else np.full(y.shape, float(dy))  # type: ignore[arg-type]  # a real scalar (isscalar)
        valid = (side == 0) & ~np.isnan(y)
        xn, Pn, ll = uncensored_update(xp, Pp, y, C, R, dy, valid, self.covariance_update)
        if (side != 0).any():
            lo, hi = self.censoring.limits(k)
            lo = np.broadcast_to(lo, y.shape)
            hi = np.broadcast_to(hi, y.shape)
            for l in range(self.m):
                sl = side[:, l]
                if not (sl != 0).any():
                    continue
                lim = np.where(sl < 0, lo[:, l], hi[:, l])
                xn, Pn, lm = censored_reading_update(
                    xn, Pn, C[l], float(R[l, l]), dy[:, l], lim, sl, self.covariance_update
                )
                ll = ll + lm
        return xn, Pn, None, carry, xp, Pp, {"log_lik": ll, "side": side}

    def _check_record(self, y2, u2, k0, name="y"):
        super()._check_record(y2, u2, k0, name)
        self.censoring.check(self.m, k0 + y2.shape[1])
        self.censoring.check_measurements(y2, start=k0 + 1)

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
    ) -> FilterResult:
        """Filter censored readings ``y`` (..., T, m); ``censored`` (..., T, m) the recorded indicator.

        Returns a :class:`~tobitkf.FilterResult` with ``extras["log_lik"]`` (..., T) and
        ``extras["side"]`` (..., T, m); see the class docstring.
        """
        from ..filters.core import prepare_measurements

        y2, batch = prepare_measurements(y, self.m)
        k0 = self.k0 if state is None else state.k
        self.censoring.check(self.m, k0 + y2.shape[1])
        lo, hi = self.censoring.all_limits(y2.shape[1], self.m, start=k0 + 1)
        c2 = None
        if censored is not None:
            arr = np.asarray(censored)
            try:
                c2 = np.broadcast_to(arr, batch + y2.shape[1:]).reshape(y2.shape)
            except ValueError:
                raise ShapeError(f"censored: expected the shape of y {batch + y2.shape[1:]}, got {arr.shape}") from None
        side = censoring_sides(y2, lo, hi, c2, rtol=self.rtol)
        return self._run(y, u, x0, P0, outputs=outputs, state=state, step_data={"side": side})
