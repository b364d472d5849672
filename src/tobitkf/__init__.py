"""tobitkf: state estimation and control from imperfect measurements.

Censored (Tobit), saturated, fading, delayed, missing, failed, integrated and
protocol-scheduled measurements; batched over Monte Carlo runs.

Public API (stable):

- :class:`LinearSystem` -- the state-space model; :class:`NonlinearSystem` (with :func:`discretize` and
  :func:`augment_parameters` for tracking unknown parameters) the
  nonlinear one.
- :class:`Censoring`, :func:`multi_region` -- censoring limits; :class:`Quantizer` -- a quantized sensor;
  :class:`Channel` -- the contract a channel of your own implements (:mod:`tobitkf.channels.base`), served by
  :class:`AssumedDensityFilter`, :class:`TobitFilter` and :class:`ParticleFilter`.
- :func:`simulate` -- batched truth and measurements.
- :class:`KalmanFilter`, :class:`DroppingKalmanFilter`, :class:`TobitKalmanFilter`,
  :class:`SteadyStateTobitKalmanFilter` -- estimators.
- :func:`censored_moments` -- censored-normal statistics, safe in the tails.
- :class:`FadingTobitKalmanFilter` (Rice fading, Geng et al. 2017), with :class:`RiceFading`
  and the coefficient :mod:`~tobitkf.channels.laws`.
- :class:`RossModel`, :func:`hinf_design`, :func:`hinf_analyze`, :class:`RegionalHinfFilter`
  (regional H-infinity filtering with random saturation, Wang et al. 2010).
- :class:`ProtocolTobitKalmanFilter` with :class:`ProtocolChannel` (Round-Robin scheduling, integral
  measurements, sensor failures) and :func:`protocol_covariance_bounds` (Geng et al.).
- :class:`DelayFadingSystem`, :func:`chain_lmmse` and relatives: optimal linear filter, predictor
  and smoothers for time-delay systems with fading measurements (Li et al. 2018).
- :class:`ParticleFilter` (the Bayes-optimal yardstick for every channel), the assumed-density filter of
  any channel :class:`AssumedDensityFilter` and its named forms :class:`AssumedDensityTobitFilter`, :class:`FadingAssumedDensityFilter`,
  :class:`ProtocolAssumedDensityFilter`, :class:`SaturationAssumedDensityFilter`, and
  :func:`posterior_crlb` (posterior Cramér–Rao bound).
- :mod:`tobitkf.control` -- LQR/LQE/LQG via python-control, closed loops with (Tobit) Kalman observers,
  Tobit Jacobians and a stability certificate, censoring-limit control; :class:`MultiTargetTracker`.
- :mod:`tobitkf.metrics` -- RMSE, bias, NEES; :mod:`tobitkf.sweep` -- Monte Carlo sweeps;
  :func:`write_report` -- the reproduction report.
- :func:`smooth`, :class:`FixedLagSmoother`, :func:`log_likelihood`, :func:`fit` (with :class:`CensoredAR`),
  :class:`FitResult`, :func:`load_fit` -- smoothing, likelihood and learning from censored data
  (:mod:`tobitkf.inference`); :mod:`tobitkf.data` -- real censored data sets.
"""

from . import channels as _channels
from . import control, data, metrics
from ._validation import ShapeError, ValidationError
from ._version import __version__
from .censored import CensoredMoments, censored_moments
from .channels import *  # noqa: F403 - every channel of the package (channels.__all__): a new one edits no file here
from .channels import laws
from .channels.fading import RiceFading
from .channels.protocol import IntegralMeasurement, ProtocolChannel, RoundRobin
from .channels.saturation import RandomSaturation
from .control import certify_tkf_stability, simulate_closed_loop, tobit_dlqe, tobit_lqe
from .design.hinf import analyze as hinf_analyze
from .design.hinf import design as hinf_design
from .design.hinf import verify as hinf_verify
from .design.pcrlb import PosteriorCRLB, censored_fisher_information, posterior_crlb
from .design.protocol_bounds import protocol_covariance_bounds
from .filters import (
    DroppingKalmanFilter,
    FilterResult,
    KalmanFilter,
    TobitKalmanFilter,
    kalman_filter,
    tobit_kalman_filter,
)
from .filters._pool import output_pool_limit, set_output_pool
from .filters.adf_fading import FadingAssumedDensityFilter
from .filters.adf_generic import AssumedDensityFilter, TobitFilter
from .filters.adf_protocol import ProtocolAssumedDensityFilter
from .filters.adf_saturation import SaturationAssumedDensityFilter
from .filters.assumed_density import AssumedDensityTobitFilter
from .filters.delay_augmented import AugmentedLMMSE, augmented_lmmse
from .filters.delay_chain import ChainLMMSE, chain_lmmse, smooth_interval, smooth_point
from .filters.delay_reorganized import ReorganizedInnovationLMMSE, reorganized_lmmse
from .filters.fading import (
    FadingKalmanFilter,
    FadingTobitKalmanFilter,
    fading_kalman_filter,
    fading_tobit_kalman_filter,
)
from .filters.gaussian_sum import GaussianSumAssumedDensityFilter
from .filters.hinf import RegionalHinfFilter
from .filters.nonlinear import (
    ExtendedKalmanFilter,
    SigmaPoints,
    TobitExtendedKalmanFilter,
    TobitUnscentedKalmanFilter,
    UnscentedKalmanFilter,
)
from .filters.nonlinear_adf import NonlinearAssumedDensityFilter
from .filters.nonlinear_fading import (
    FadingExtendedKalmanFilter,
    FadingNonlinearAssumedDensityFilter,
    FadingTobitExtendedKalmanFilter,
    FadingTobitUnscentedKalmanFilter,
    FadingUnscentedKalmanFilter,
)
from .filters.nonlinear_saturation import SaturationNonlinearAssumedDensityFilter
from .filters.particle import ParticleFilter
from .filters.particle_nonlinear import nonlinear_model as _nonlinear_particle_model  # registers it
from .filters.protocol import ProtocolTobitKalmanFilter, protocol_tobit_kalman_filter
from .filters.steady_state import SteadyStateTobitKalmanFilter, tobit_kalman_filter_controlled
from .filters.tracking import MultiTargetTracker
from .inference import (
    CensoredAR,
    FitResult,
    FixedLagSmoother,
    Panel,
    adf_log_likelihood,
    fit,
    kalman_log_likelihood,
    load_fit,
    log_likelihood,
    smooth,
    wrtds,
)
from .models import ContinuousLinearSystem, LinearSystem
from .models.delay import DelayFadingSystem, FadingMoments, FadingPMF, HistoryPrior
from .models.nonlinear import NonlinearSystem, augment_parameters, discretize
from .models.ross import RossModel
from .report import write_report
from .simulate import SimulationData, simulate
from .simulate.delay import simulate_delay

__all__ = [
    "LinearSystem",
    "ContinuousLinearSystem",
    "NonlinearSystem",
    "discretize",
    "augment_parameters",
    "ExtendedKalmanFilter",
    "UnscentedKalmanFilter",
    "SigmaPoints",
    "TobitExtendedKalmanFilter",
    "TobitUnscentedKalmanFilter",
    "NonlinearAssumedDensityFilter",
    "GaussianSumAssumedDensityFilter",
    "FadingExtendedKalmanFilter",
    "FadingUnscentedKalmanFilter",
    "FadingTobitExtendedKalmanFilter",
    "FadingTobitUnscentedKalmanFilter",
    "FadingNonlinearAssumedDensityFilter",
    "SaturationNonlinearAssumedDensityFilter",
    "AssumedDensityFilter",
    "TobitFilter",
    "simulate",
    "SimulationData",
    "KalmanFilter",
    "DroppingKalmanFilter",
    "TobitKalmanFilter",
    "kalman_filter",
    "tobit_kalman_filter",
    "SteadyStateTobitKalmanFilter",
    "tobit_kalman_filter_controlled",
    "FilterResult",
    "censored_moments",
    "CensoredMoments",
    "metrics",
    "ShapeError",
    "ValidationError",
    "laws",
    "RiceFading",
    "FadingTobitKalmanFilter",
    "FadingKalmanFilter",
    "fading_tobit_kalman_filter",
    "fading_kalman_filter",
    "RandomSaturation",
    "RossModel",
    "RegionalHinfFilter",
    "hinf_design",
    "hinf_analyze",
    "hinf_verify",
    "DelayFadingSystem",
    "HistoryPrior",
    "FadingPMF",
    "FadingMoments",
    "simulate_delay",
    "chain_lmmse",
    "augmented_lmmse",
    "reorganized_lmmse",
    "smooth_interval",
    "smooth_point",
    "ChainLMMSE",
    "AugmentedLMMSE",
    "ReorganizedInnovationLMMSE",
    "ProtocolChannel",
    "RoundRobin",
    "IntegralMeasurement",
    "ProtocolTobitKalmanFilter",
    "protocol_tobit_kalman_filter",
    "protocol_covariance_bounds",
    "write_report",
    "control",
    "simulate_closed_loop",
    "certify_tkf_stability",
    "tobit_lqe",
    "tobit_dlqe",
    "MultiTargetTracker",
    "ParticleFilter",
    "AssumedDensityTobitFilter",
    "FadingAssumedDensityFilter",
    "ProtocolAssumedDensityFilter",
    "SaturationAssumedDensityFilter",
    "posterior_crlb",
    "PosteriorCRLB",
    "censored_fisher_information",
    "smooth",
    "FixedLagSmoother",
    "log_likelihood",
    "kalman_log_likelihood",
    "adf_log_likelihood",
    "fit",
    "FitResult",
    "load_fit",
    "CensoredAR",
    "Panel",
    "data",
    "wrtds",
    "set_output_pool",
    "output_pool_limit",
    "__version__",
]
__all__ += _channels.__all__
