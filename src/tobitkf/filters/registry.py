r"""One registry of the estimators: name -> class, the channel pieces it takes, its options.

Sweeps (:mod:`tobitkf.sweep`) build every model-mode estimator from it, so a sweep file can name any
family on a :class:`~tobitkf.LinearSystem` (``type = "FadingTobitKalmanFilter"``, ...), the
experiments (:mod:`tobitkf.experiments`) declare their line-ups of estimators as data, key ->
(registry name, options), build them with :func:`lineup` and record them with :func:`describe`
(``metrics["lineup"]``), and the command line lists it (``tobitkf estimators``). An entry knows

* the **channel pieces** its constructor takes, by the ``section`` name each channel class registers
  itself under (:mod:`tobitkf.channels.base`; a sweep file's table of that name): ``censoring``
  (:class:`~tobitkf.Censoring`), ``fading`` (:class:`~tobitkf.RiceFading`), ``protocol``
  (:class:`~tobitkf.ProtocolChannel`), ``quantizer`` (:class:`~tobitkf.Quantizer`), ``saturation``
  (:class:`~tobitkf.RandomSaturation`, no sweep-file table), any channel of your own, and the delay
  family's ``prior`` (:class:`~tobitkf.models.delay.HistoryPrior`); ``channel`` means any channel piece
  (the generic :class:`~tobitkf.AssumedDensityFilter`, :class:`~tobitkf.TobitFilter` and the particle
  filter take the channel the pieces make, :func:`channel_of`);
* its **options**: name -> the allowed values (a tuple), the type of a number (``float``, ``int``),
  or ``object`` for a value no TOML scalar expresses (the H∞ filter's designed gains, the particle
  filter's seed: an int, a :class:`numpy.random.SeedSequence` or a Generator), which the estimator
  checks itself; ``required`` lists the ones without a default;
* what it **reads**: ``"y"``, the readings the channel delivers, or ``"latent"``, the sensor's latent
  readings, which the estimator censors itself at a limit it sets (the controlled-limit filters);
* its **model** kind (``"linear"``; the delay family's ``"delay"``, the H∞ filter's ``"ross"`` and the
  tracker's ``"frames"`` are listed for completeness: a TOML sweep cannot describe the H∞ plant's
  nonlinearity or the tracker's frames, so those are swept through their experiments).

>>> from tobitkf.filters.registry import get
>>> get("TobitKalmanFilter").needs, sorted(get("TobitKalmanFilter").options)
(('censoring',), ['backend', 'covariance_update', 'noise_term', 'threads'])

A line-up, built and described:

>>> import tobitkf as tk
>>> from tobitkf.filters.registry import describe, lineup
>>> sys_ = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.1]], R=[[0.5]], x0=[0.0], P0=[[1.0]])
>>> plan = {"kf": ("KalmanFilter", {}), "tkf-tv": ("TobitKalmanFilter", {"noise_term": "total_variance"})}
>>> est = lineup(plan, sys_, {"censoring": tk.Censoring(lower=0.0)})
>>> type(est["tkf-tv"]).__name__, est["tkf-tv"].noise_term
('TobitKalmanFilter', 'total_variance')
>>> describe(plan)["tkf-tv"]
{'type': 'TobitKalmanFilter', 'options': {'noise_term': 'total_variance'}}
"""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib import import_module
from typing import Any, Callable, Mapping

from .._validation import ValidationError
from ._backend import BACKENDS
from .assumed_density import _ORDERS
from .core import COVARIANCE_FORMS
from .delay import _DECORRELATION
from .fading import _KF_OPTIONS as _FADING_KF_OPTIONS
from .fading import _TOBIT_OPTIONS as _FADING_TOBIT_OPTIONS
from .protocol import _OPTIONS as _PROTOCOL_OPTIONS
from .tobit import _OPTIONS as _TOBIT_OPTIONS
from .tobit import NOISE_TERMS

__all__ = ["Entry", "ENTRIES", "get", "names", "make", "lineup", "describe", "parts_of", "channel_of", "Lineup"]


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
        self.check(options, parts)
        return self.factory(system, parts, options)

    def check(self, options: Mapping[str, Any], parts: Mapping[str, Any] | None = None) -> None:
        """What :meth:`build` checks before it builds: every option known, every required one given, and
        (when ``parts`` is given) every channel piece the entry needs present. The values are the
        estimator's to check.

        Raises
        ------
        ValidationError
            An unknown or missing option, or a channel piece the entry needs but was not given.
        """
        for key in options:
            if key not in self.options:
                raise ValidationError(
                    f"{key}: not an option of {self.name}; expected one of {', '.join(sorted(self.options)) or 'none'}"
                )
        for key in self.required:
            if key not in options:
                raise ValidationError(f"{key}: {self.name} needs this option")
        for part in self.needs if parts is not None else ():
            if part == "channel" and parts is not None:
                if channel_of(parts) is None:
                    raise ValidationError(f"channel: {self.name} needs a channel piece")
            elif parts is not None and parts.get(part) is None:
                raise ValidationError(f"{part}: {self.name} needs the channel piece [{part}]")

    def run(self, estimator: Any, data: Any, **kwargs: Any) -> Any:
        """Filter the simulated ``data`` (:class:`~tobitkf.SimulationData`) with what the entry reads."""
        if self.reads == "latent":
            return (
                estimator.filter_controlled(data.y_latent, **kwargs)
                if hasattr(estimator, "filter_controlled")
                else estimator.filter(data.y_latent, **kwargs)
            )
        return estimator.filter(data.y, **kwargs)


# the option values are the families' own constants (each family checks its options against them)
_FORMS = COVARIANCE_FORMS
_ADF_OPTIONS = {"covariance_update": COVARIANCE_FORMS, "backend": BACKENDS}


def _maker(module: str, name: str, *pieces: str) -> Callable[..., Any]:
    """The factory of the class ``name`` of ``tobitkf.filters.<module>`` (imported when first built): it takes
    the system, then the channel ``pieces`` by section name (a name ending in ``?`` is optional: None when not
    given; ``"channel"`` is the channel the pieces make, :func:`channel_of`), then the options."""

    def make(system, parts, o):
        cls = getattr(import_module(f"{__package__}.{module}"), name)
        args = [
            channel_of(parts) if p == "channel" else parts.get(p[:-1]) if p.endswith("?") else parts[p] for p in pieces
        ]
        return cls(system, *args, **o)

    return make


def _pbtkf(system, parts, o):
    from .protocol import ProtocolTobitKalmanFilter

    return ProtocolTobitKalmanFilter.baseline(system, parts["protocol"], **o)


_DELAY_MODULES = {"ChainLMMSE": "delay_chain", "AugmentedLMMSE": "delay_augmented"}


def _family(name: str, summary: str, module: str, takes: tuple[str, ...] = (), **fields: Any) -> Entry:
    """The entry of the class ``name`` of ``tobitkf.filters.<module>``, built by :func:`_maker` with the channel
    pieces ``takes``: it needs those not marked optional (``?``). ``fields`` are the entry's other fields."""
    needs = tuple(p for p in takes if not p.endswith("?"))
    return Entry(name, summary, _maker(module, name, *takes), needs=needs, **fields)


def _delay(name: str, summary: str, **fields: Any) -> Entry:
    """A delay-family entry (:func:`_family`): its class takes the history prior."""
    return _family(name, summary, _DELAY_MODULES.get(name, "delay_reorganized"), ("prior",), model="delay", **fields)


def channel_of(parts: Mapping[str, Any]) -> Any:
    """The channel the pieces ``parts`` (section name -> piece) make, as the simulator draws it and the
    generic filters take it: a piece that carries its own limits (``replaces_censoring``: the protocol
    channel, the quantizer) alone; else the reading model (the last piece other than the censoring that is a
    channel) with the ``censoring`` (left out when it has no finite limit); one piece alone, none as None. Pieces that are no channel (the delay
    family's prior) are left out.

    >>> import tobitkf as tk
    >>> channel_of({"censoring": tk.Censoring(lower=0.0), "quantizer": tk.Quantizer(0.5)})
    Quantizer(0.5)
    """
    import numpy as np

    from ..channels.base import Channel

    pieces = [p for p in parts.values() if isinstance(p, Channel)]
    own = [p for p in pieces if p.replaces_censoring]
    if own:
        return own[0]
    cens = parts.get("censoring")
    drawers = [p for p in pieces if p is not cens]
    if drawers and cens is not None and not (np.isfinite(cens.lower).any() or np.isfinite(cens.upper).any()):
        cens = None  # a censoring without a finite limit (a sweep file's default) censors nothing
    chosen = [p for p in (drawers[-1] if drawers else None, cens) if p is not None]
    return chosen[0] if len(chosen) == 1 else (chosen or None)


def _hinf(system, parts, o):
    from .hinf import RegionalHinfFilter

    return RegionalHinfFilter(o["Af"], o["Bf"], system.M)


def _tracker(system, parts, o):
    from .tracking import MultiTargetTracker

    return MultiTargetTracker(**o)


_ENTRY_LIST = [
    _family(
        "KalmanFilter",
        "Kalman filter; fed censored readings, the naive baseline (Miller §2.1)",
        "kalman",
        options={"covariance_update": _FORMS, "backend": BACKENDS},
    ),
    _family(
        "DroppingKalmanFilter",
        "Kalman filter that drops readings at a censoring limit (Miller §3.3.6)",
        "kalman",
        ("censoring",),
        options={"covariance_update": _FORMS, "rtol": float, "backend": BACKENDS},
    ),
    _family(
        "TobitKalmanFilter",
        "Tobit Kalman filter, one- and two-sided, multi-region (Miller §3.3, §6.6)",
        "tobit",
        ("censoring",),
        options={**_TOBIT_OPTIONS, "threads": int},
    ),
    _family(
        "SteadyStateTobitKalmanFilter",
        "fixed-gain TKF whose sensor limit is steered from its prior (Miller §3.4)",
        "steady_state",  # xi_uncensored: an option by keyword
        options={"xi_uncensored": float, "side": ("upper", "lower"), "backend": BACKENDS},
        required=("xi_uncensored",),
        reads="latent",
    ),
    _family(
        "ControlledLimitTobitKalmanFilter",
        "full TKF with the steered limit of (3.56) (Miller §3.4)",
        "steady_state",
        options={
            "xi_uncensored": float,
            "side": ("upper", "lower"),
            "noise_term": NOISE_TERMS,
            "backend": BACKENDS,  # no compiled path: "auto" and "numpy" run numpy, "numba" refuses
        },
        required=("xi_uncensored",),
        reads="latent",
    ),
    _family(
        "FadingTobitKalmanFilter",
        "TKF with L-th order Rice fading (Geng et al. 2017)",
        "fading",
        ("fading", "censoring?"),
        options=_FADING_TOBIT_OPTIONS,
    ),
    _family(
        "FadingKalmanFilter",
        "augmented KF with the fading means, no censoring handling (Geng et al. 2017)",
        "fading",
        ("fading",),
        options=_FADING_KF_OPTIONS,
    ),
    _family(
        "ProtocolTobitKalmanFilter",
        "protocol-based TKF: Round-Robin, integral readings, failures (Geng et al.)",
        "protocol",
        ("protocol",),
        options={**_PROTOCOL_OPTIONS, "backend": BACKENDS},
    ),
    Entry(
        "ProtocolBaselineTobitKalmanFilter",
        "the protocol paper's PBTKF baseline: no window, no failures modelled",
        _pbtkf,
        needs=("protocol",),
        options={"covariance_update": _PROTOCOL_OPTIONS["covariance_update"]},
    ),
    _family(
        "AssumedDensityTobitFilter",
        "assumed-density filter: the exact posterior moments of each censored reading (beyond the sources)",
        "assumed_density",
        ("censoring",),
        options={**_ADF_OPTIONS, "order": _ORDERS},
    ),
    _family(
        "FadingAssumedDensityFilter",
        "assumed-density filter for censored readings through Rice fading (beyond the sources)",
        "adf_fading",
        ("fading", "censoring?"),
        options=_ADF_OPTIONS,
    ),
    _family(
        "ProtocolAssumedDensityFilter",
        "protocol-channel filter conditioning on the failure outcome (beyond the sources)",
        "adf_protocol",
        ("protocol",),
        options={**_ADF_OPTIONS, "nodes": int},
    ),
    _family(
        "SaturationAssumedDensityFilter",
        "assumed-density filter for random saturation with missing readings (beyond the sources)",
        "adf_saturation",
        ("saturation",),
        options=_ADF_OPTIONS,
    ),
    _family(
        "AssumedDensityFilter",
        "assumed-density filter of any channel: a named form where one exists, else the channel's moments",
        "adf_generic",
        ("channel",),
        options={"covariance_update": _FORMS},
    ),
    _family(
        "TobitFilter",
        "the Tobit Kalman filter's update for any channel with reading statistics (beyond the sources)",
        "adf_generic",
        ("channel",),
        options={"covariance_update": _FORMS, "linearization": ("prior_mean", "predictive")},
    ),
    Entry(
        "ParticleFilter",
        "bootstrap / optimal-proposal particle filter on any channel: the Bayes optimum (beyond the sources)",
        _maker("particle", "ParticleFilter", "channel"),
        options={
            "particles": int,
            "resample_threshold": float,
            "proposal": ("auto", "optimal", "prior", "rao_blackwellised"),
            "seed": object,
            "backend": BACKENDS,  # compiled for linear readings with censoring; the other channels run numpy
        },
        required=("seed",),  # a registry-built particle filter draws the same particles on every run
    ),
    _delay(
        "ChainLMMSE",
        "exact LMMSE of a pure-delay system with fading, chain-decoupled (Li, Li & Wang 2018)",
        options={"decorrelation": _DECORRELATION, "backend": BACKENDS},
    ),
    _delay(
        "AugmentedLMMSE",
        "exact LMMSE on the augmented delay state (Li, Li & Wang 2018)",
        options={"window": int, "covariance_update": _FORMS},
    ),
    _delay(
        "ReorganizedInnovationLMMSE",
        "the source's reorganized-innovation estimator (Li, Li & Wang 2018)",
        options={"decorrelation": _DECORRELATION, "warmup": int, "backend": BACKENDS},
    ),
    Entry(
        "RegionalHinfFilter",
        "regional H-infinity filter with given gains (Wang, Shen & Liu)",
        _hinf,
        options={"Af": object, "Bf": object},  # the designed gains (n, n) and (n, m), array_like
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


Lineup = Mapping[str, tuple[str, Mapping[str, Any]]]
"""A line-up of estimators as data: key -> (registry name, options)."""


def make(
    name: str,
    system: Any,
    *,
    censoring: Any = None,
    fading: Any = None,
    protocol: Any = None,
    saturation: Any = None,
    prior: Any = None,
    **options: Any,
) -> Any:
    """The estimator ``name`` of the registry for ``system``, its channel pieces and ``options``.

    The pieces given (not None) are the ``parts`` of :meth:`Entry.build`, whose checks apply; a keyword named
    after another registered channel section (``quantizer=``, a channel of your own) whose value is a
    :class:`~tobitkf.Channel` is a piece too.

    Raises
    ------
    ValidationError
        An unknown name, an unknown or missing option, a piece the entry needs but was not given.

    >>> import tobitkf as tk
    >>> sys_ = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.1]], R=[[0.5]], x0=[0.0], P0=[[1.0]])
    >>> make("DroppingKalmanFilter", sys_, censoring=tk.Censoring(lower=0.0), rtol=1e-9).rtol
    1e-09
    >>> make("DroppingKalmanFilter", sys_)
    Traceback (most recent call last):
    ...
    tobitkf._validation.ValidationError: censoring: DroppingKalmanFilter needs the channel piece [censoring]
    """
    from ..channels.base import Channel, registered_channels

    given = {"censoring": censoring, "fading": fading, "protocol": protocol, "saturation": saturation, "prior": prior}
    sections = registered_channels()
    for key in [k for k, v in options.items() if k in sections and isinstance(v, Channel)]:
        given[key] = options.pop(key)
    return get(name).build(system, {k: v for k, v in given.items() if v is not None}, options)


def parts_of(channel: Any) -> dict[str, Any]:
    """The channel pieces of ``channel`` (one piece, a list of pieces, or None) by the section name their class
    registered (:class:`~tobitkf.Censoring` -> ``censoring``, :class:`~tobitkf.RiceFading` -> ``fading``,
    :class:`~tobitkf.ProtocolChannel` -> ``protocol``, :class:`~tobitkf.RandomSaturation` -> ``saturation``,
    :class:`~tobitkf.Quantizer` -> ``quantizer``, a channel of your own -> its ``section``).

    Raises
    ------
    ValidationError
        A piece that is no registered channel, or two pieces of one section.

    >>> import tobitkf as tk
    >>> sorted(parts_of([tk.RandomSaturation([0.5], [0.9]), tk.Censoring(lower=0.0)]))
    ['censoring', 'saturation']
    """
    from ..channels.base import registered_channels, section_of

    pieces = [] if channel is None else list(channel) if isinstance(channel, (list, tuple)) else [channel]
    out: dict[str, Any] = {}
    for piece in pieces:
        section = section_of(piece)
        if section is None:
            raise ValidationError(
                f"channel: expected registered channel pieces ({', '.join(sorted(registered_channels()))}), "
                f"got {type(piece).__name__}"
            )
        if section in out:
            raise ValidationError(f"channel: two {section} pieces; expected at most one of each")
        out[section] = piece
    return out


def _check_lineup(plan: Lineup) -> None:
    if not isinstance(plan, Mapping):
        raise ValidationError(f"lineup: expected a mapping key -> (registry name, options), got {type(plan).__name__}")
    for key, item in plan.items():
        if not (isinstance(item, tuple) and len(item) == 2 and isinstance(item[1], Mapping)):
            raise ValidationError(f"lineup[{key!r}]: expected a pair (registry name, options mapping), got {item!r}")
        get(item[0]).check(item[1])


def lineup(plan: Lineup, system: Any, parts: Mapping[str, Any]) -> dict[str, Any]:
    """The estimators of a line-up: ``{key: get(name).build(system, parts, options)}``, in the
    order of ``plan`` (``plan`` maps key -> (registry name, options); ``parts`` section name -> piece,
    as for :meth:`Entry.build`; a piece an entry does not use is ignored by it).

    Raises
    ------
    ValidationError
        A malformed line-up, an unknown name, or what :meth:`Entry.build` raises.
    """
    _check_lineup(plan)
    return {key: get(name).build(system, parts, options) for key, (name, options) in plan.items()}


def _jsonable(value: Any) -> Any:
    import numpy as np

    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, (np.integer, np.floating, np.bool_)):
        return value.item()
    if isinstance(value, (list, tuple, np.ndarray)):
        return np.asarray(value).tolist()
    if isinstance(value, np.random.SeedSequence):
        return {"SeedSequence": np.asarray(value.entropy).tolist(), "spawn_key": list(value.spawn_key)}
    return repr(value)


def describe(plan: Lineup) -> dict[str, dict[str, Any]]:
    """A line-up as JSON-able data, ``{key: {"type": name, "options": {...}}}`` (for ``metrics["lineup"]``):
    numbers, strings and booleans as they are, arrays as nested lists, a SeedSequence as its entropy
    and spawn key, anything else as its ``repr``.

    Raises
    ------
    ValidationError
        A malformed line-up or an unknown name.
    """
    _check_lineup(plan)
    return {
        key: {"type": name, "options": {k: _jsonable(v) for k, v in options.items()}}
        for key, (name, options) in plan.items()
    }
