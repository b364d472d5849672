r"""One registry of the estimators: name -> class, the channel pieces it takes, its options.

Sweeps (:mod:`tobitkf.sweep`) build every model-mode estimator from it, so a sweep file can name any
family on a :class:`~tobitkf.LinearSystem` (``type = "FadingTobitKalmanFilter"``, ...), and the
the command line lists it (``tobitkf estimators``). An entry knows

* the **channel pieces** its constructor takes, by section name of a sweep file: ``censoring``
  (:class:`~tobitkf.Censoring`), ``fading`` (:class:`~tobitkf.RiceFading`), ``protocol``
  (:class:`~tobitkf.ProtocolChannel`);
* its **options**: name -> the allowed values (a tuple) or the type of a number (``float``, ``int``);
  ``required`` lists the ones without a default;
* what it **reads**: ``"y"``, the readings the channel delivers, or ``"latent"``, the sensor's latent
  readings, which the estimator censors itself at a limit it sets (the controlled-limit filters);
* its **model** kind (``"linear"``; the delay family's ``"delay"``, the H∞ filter's ``"ross"`` and the
  tracker's ``"frames"`` are listed for completeness: a TOML sweep cannot describe the H∞ plant's
  nonlinearity or the tracker's frames, so those are swept through their experiments).

>>> from tobitkf.filters.registry import get
>>> get("TobitKalmanFilter").needs, sorted(get("TobitKalmanFilter").options)
(('censoring',), ['covariance_update', 'noise_term'])
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

from .._validation import ValidationError

__all__ = ["Entry", "ENTRIES", "get", "names"]


@dataclass(frozen=True)
class Entry:
    """An estimator of the registry (see the module docstring)."""

    name: str
    summary: str
    factory: Callable[..., Any]
    needs: tuple[str, ...] = ()
    options: Mapping[str, Any] = field(default_factory=dict)
    required: tuple[str, ...] = ()
    reads: str = "y"
    model: str = "linear"

    def build(self, system: Any, parts: Mapping[str, Any], options: Mapping[str, Any] | None = None) -> Any:
        """The estimator for ``system`` with the channel ``parts`` (section name -> piece) and ``options``.

        Raises
        ------
        ValidationError
            An unknown or missing option, or a channel piece the entry needs but was not given.
        """
        options = dict(options or {})
        for key in options:
            if key not in self.options:
                raise ValidationError(
                    f"{key}: not an option of {self.name}; expected one of {', '.join(sorted(self.options)) or 'none'}"
                )
        for key in self.required:
            if key not in options:
                raise ValidationError(f"{key}: {self.name} needs this option")
        for part in self.needs:
            if parts.get(part) is None:
                raise ValidationError(f"{part}: {self.name} needs the channel piece [{part}]")
        return self.factory(system, parts, options)

    def run(self, estimator: Any, data: Any, **kwargs: Any) -> Any:
        """Filter the simulated ``data`` (:class:`~tobitkf.SimulationData`) with what the entry reads."""
        if self.reads == "latent":
            return (
                estimator.filter_controlled(data.y_latent, **kwargs)
                if hasattr(estimator, "filter_controlled")
                else estimator.filter(data.y_latent, **kwargs)
            )
        return estimator.filter(data.y, **kwargs)


_FORMS = ("standard", "joseph", "square_root")
_BACKENDS = ("auto", "numpy", "numba")


def _kf(system, parts, o):
    from .kalman import KalmanFilter

    return KalmanFilter(system, **o)


def _dkf(system, parts, o):
    from .kalman import DroppingKalmanFilter

    return DroppingKalmanFilter(system, parts["censoring"], **o)


def _tkf(system, parts, o):
    from .tobit import TobitKalmanFilter

    return TobitKalmanFilter(system, parts["censoring"], **o)


def _sstkf(system, parts, o):
    from .steady_state import SteadyStateTobitKalmanFilter

    o = dict(o)
    return SteadyStateTobitKalmanFilter(system, o.pop("xi_uncensored"), **o)


def _cltkf(system, parts, o):
    from .steady_state import ControlledLimitTobitKalmanFilter

    o = dict(o)
    return ControlledLimitTobitKalmanFilter(system, o.pop("xi_uncensored"), **o)


def _ftkf(system, parts, o):
    from .fading import FadingTobitKalmanFilter

    return FadingTobitKalmanFilter(system, parts["fading"], parts.get("censoring"), **o)


def _fkf(system, parts, o):
    from .fading import FadingKalmanFilter

    return FadingKalmanFilter(system, parts["fading"], **o)


def _ptkf(system, parts, o):
    from .protocol import ProtocolTobitKalmanFilter

    return ProtocolTobitKalmanFilter(system, parts["protocol"], **o)


def _pbtkf(system, parts, o):
    from .protocol import ProtocolTobitKalmanFilter

    return ProtocolTobitKalmanFilter.baseline(system, parts["protocol"], **o)


def _adf(system, parts, o):
    from .assumed_density import AssumedDensityTobitFilter

    return AssumedDensityTobitFilter(system, parts["censoring"], **o)


def _fadf(system, parts, o):
    from .adf_fading import FadingAssumedDensityFilter

    return FadingAssumedDensityFilter(system, parts["fading"], parts.get("censoring"), **o)


def _padf(system, parts, o):
    from .adf_protocol import ProtocolAssumedDensityFilter

    return ProtocolAssumedDensityFilter(system, parts["protocol"], **o)


def _delay(cls_name):
    def make(system, parts, o):
        from . import delay

        return getattr(delay, cls_name)(system, parts["prior"], **o)

    return make


def _hinf(system, parts, o):
    from .hinf import RegionalHinfFilter

    return RegionalHinfFilter(o["Af"], o["Bf"], system.M)


def _tracker(system, parts, o):
    from .tracking import MultiTargetTracker

    return MultiTargetTracker(**o)


_ENTRY_LIST = [
    Entry(
        "KalmanFilter",
        "Kalman filter; fed censored readings, the naive baseline (Miller §2.1)",
        _kf,
        options={"covariance_update": _FORMS, "backend": _BACKENDS},
    ),
    Entry(
        "DroppingKalmanFilter",
        "Kalman filter that drops readings at a censoring limit (Miller §3.3.6)",
        _dkf,
        needs=("censoring",),
        options={"covariance_update": _FORMS, "rtol": float, "backend": _BACKENDS},
    ),
    Entry(
        "TobitKalmanFilter",
        "Tobit Kalman filter, one- and two-sided, multi-region (Miller §3.3, §6.6)",
        _tkf,
        needs=("censoring",),
        options={
            "noise_term": ("dissertation", "total_variance", "exact_pv"),
            "covariance_update": _FORMS,
            "threads": int,
            "backend": _BACKENDS,
        },
    ),
    Entry(
        "SteadyStateTobitKalmanFilter",
        "fixed-gain TKF whose sensor limit is steered from its prior (Miller §3.4)",
        _sstkf,
        options={"xi_uncensored": float, "side": ("upper", "lower"), "backend": _BACKENDS},
        required=("xi_uncensored",),
        reads="latent",
    ),
    Entry(
        "ControlledLimitTobitKalmanFilter",
        "full TKF with the steered limit of (3.56) (Miller §3.4)",
        _cltkf,
        options={
            "xi_uncensored": float,
            "side": ("upper", "lower"),
            "noise_term": ("dissertation", "total_variance", "exact_pv"),
        },
        required=("xi_uncensored",),
        reads="latent",
    ),
    Entry(
        "FadingTobitKalmanFilter",
        "TKF with L-th order Rice fading (Geng et al. 2017)",
        _ftkf,
        needs=("fading",),
        options={
            "p_uncensored_mode": ("augmented", "eq6_stale"),
            "fading_variance_term": (False, True),
            "exact_tobit_variance": (False, True),
            "covariance_update": ("joseph", "standard", "square_root"),
            "backend": _BACKENDS,
        },
    ),
    Entry(
        "FadingKalmanFilter",
        "augmented KF with the fading means, no censoring handling (Geng et al. 2017)",
        _fkf,
        needs=("fading",),
        options={"fading_variance_term": (False, True), "covariance_update": ("joseph", "standard", "square_root")},
    ),
    Entry(
        "ProtocolTobitKalmanFilter",
        "protocol-based TKF: Round-Robin, integral readings, failures (Geng et al.)",
        _ptkf,
        needs=("protocol",),
        options={
            "failure_term": ("variance", "literal", "second_moment", "lmmse_unconditional"),
            "prehistory_prior": ("x0", "zero_mean"),
            "covariance_update": ("joseph", "standard", "square_root"),
            "backend": _BACKENDS,
        },
    ),
    Entry(
        "ProtocolBaselineTobitKalmanFilter",
        "the protocol paper's PBTKF baseline: no window, no failures modelled",
        _pbtkf,
        needs=("protocol",),
        options={"covariance_update": ("joseph", "standard", "square_root")},
    ),
    Entry(
        "AssumedDensityTobitFilter",
        "assumed-density filter: the exact posterior moments of each censored reading (beyond the sources)",
        _adf,
        needs=("censoring",),
        options={"covariance_update": _FORMS, "order": ("channels", "uncensored_first")},
    ),
    Entry(
        "FadingAssumedDensityFilter",
        "assumed-density filter for censored readings through Rice fading (beyond the sources)",
        _fadf,
        needs=("fading",),
        options={"covariance_update": _FORMS},
    ),
    Entry(
        "ProtocolAssumedDensityFilter",
        "protocol-channel filter conditioning on the failure outcome (beyond the sources)",
        _padf,
        needs=("protocol",),
        options={"covariance_update": _FORMS, "nodes": int},
    ),
    Entry(
        "ChainLMMSE",
        "exact LMMSE of a pure-delay system with fading, chain-decoupled (Li, Li & Wang 2018)",
        _delay("ChainLMMSE"),
        needs=("prior",),
        options={"decorrelation": ("optimal", "paper"), "backend": _BACKENDS},
        model="delay",
    ),
    Entry(
        "AugmentedLMMSE",
        "exact LMMSE on the augmented delay state (Li, Li & Wang 2018)",
        _delay("AugmentedLMMSE"),
        needs=("prior",),
        options={"window": int, "covariance_update": _FORMS},
        model="delay",
    ),
    Entry(
        "ReorganizedInnovationLMMSE",
        "the source's reorganized-innovation estimator (Li, Li & Wang 2018)",
        _delay("ReorganizedInnovationLMMSE"),
        needs=("prior",),
        options={"decorrelation": ("optimal", "paper"), "warmup": int, "backend": _BACKENDS},
        model="delay",
    ),
    Entry(
        "RegionalHinfFilter",
        "regional H-infinity filter with given gains (Wang, Shen & Liu)",
        _hinf,
        options={"Af": list, "Bf": list},
        required=("Af", "Bf"),
        model="ross",
    ),
    Entry(
        "MultiTargetTracker",
        "multi-target tracker leaving a field of view (Miller §2.2)",
        _tracker,
        options={
            "gate0": float,
            "gate_slope": float,
            "mu": float,
            "warmup": int,
            "feedback": ("corrected", "printed", "off"),
            "second_map": ("closest", "mutual"),
            "gate": (False, True),
            "covariance_update": _FORMS,
        },
        model="frames",
    ),
]

ENTRIES: dict[str, Entry] = {e.name: e for e in _ENTRY_LIST}
"""Every registered estimator, by name."""


def get(name: str) -> Entry:
    """The entry ``name``; ``ValidationError`` listing the known names otherwise."""
    if not isinstance(name, str) or name not in ENTRIES:
        raise ValidationError(f"estimator: unknown type {name!r}; expected one of {', '.join(ENTRIES)}")
    return ENTRIES[name]


def names(model: str | None = None) -> list[str]:
    """The registered names (of one model kind, e.g. ``"linear"``, when given)."""
    return [k for k, e in ENTRIES.items() if model is None or e.model == model]
