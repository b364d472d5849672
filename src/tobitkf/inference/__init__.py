"""Smoothing, likelihood and learning from censored data.

- :func:`smooth` -- fixed-interval smoothers (RTS for the KF; the TKF's linearisation and the
  assumed-density smoother for censored readings) with lag-one cross-covariances;
  :class:`FixedLagSmoother` on the online API.
- :func:`log_likelihood`, :func:`kalman_log_likelihood`, :func:`adf_log_likelihood` -- per run;
  :func:`~tobitkf.inference.censored_ar.exact_log_likelihood` for a censored regression with AR errors.
- :func:`fit` with :class:`CensoredAR` (exact ML), a :class:`~tobitkf.LinearSystem` template (EM) or a map
  theta -> LinearSystem (direct); :class:`FitResult` (estimates, s.e., AIC/BIC, trace, forecasts,
  residuals, JSON), :func:`load_fit`, :func:`residual_diagnostics`.
- :class:`Panel` (many short irregular series sharing a continuous-time model), :func:`fit_panel`,
  :func:`panel_log_likelihood`, :func:`panel_smooth`, :func:`panel_forecast` (per subject).
- :mod:`~tobitkf.inference.wrtds` -- WRTDS (weighted regressions on time, discharge and season, USGS
  EGRET), the established baseline for sparse censored water-quality records, with its leave-one-out
  cross-validation and predictive scores.
"""

from . import wrtds
from .censored_ar import CensoredAR, CensoredARData, exact_log_likelihood, posterior_moments
from .fitting import FitResult, fit, load_fit, residual_diagnostics
from .likelihood import adf_log_likelihood, kalman_log_likelihood, log_likelihood, prediction_log_densities
from .panel import Panel, fit_panel, panel_forecast, panel_log_likelihood, panel_smooth
from .smoothing import FixedLagSmoother, FixedLagState, rts_smooth, smooth

__all__ = [
    "smooth",
    "rts_smooth",
    "FixedLagSmoother",
    "FixedLagState",
    "log_likelihood",
    "kalman_log_likelihood",
    "adf_log_likelihood",
    "prediction_log_densities",
    "CensoredAR",
    "CensoredARData",
    "exact_log_likelihood",
    "posterior_moments",
    "fit",
    "FitResult",
    "load_fit",
    "residual_diagnostics",
    "wrtds",
    "Panel",
    "fit_panel",
    "panel_log_likelihood",
    "panel_smooth",
    "panel_forecast",
]
