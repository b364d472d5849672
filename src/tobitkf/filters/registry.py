r"""One registry of the estimators: name -> class, the channel pieces it takes, its options.

Sweeps (:mod:`tobitkf.sweep`) build every model-mode estimator from it, so a sweep file can name any
family on a :class:`~tobitkf.LinearSystem` (``type = "FadingTobitKalmanFilter"``, ...), the
experiments (:mod:`tobitkf.experiments`) declare their line-ups of estimators as data, key ->
(registry name, options), build them with :func:`lineup` and record them with :func:`describe`
(``metrics["lineup"]``), and the command line lists it (``tobitkf estimators``). Each family's module
registers its own estimators beside their classes (``register(family_entry(cls, summary, pieces, options=...))``,
as a channel class registers its ``section``): this module names no family, and a new family needs no edit here.
An entry knows

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
from typing import Any, Callable, Mapping

from .._validation import ValidationError

__all__ = [
    "Entry",
    "ENTRIES",
    "register",
    "family_entry",
    "get",
    "names",
    "make",
    "lineup",
    "describe",
    "parts_of",
    "channel_of",
    "Lineup",
]


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


ENTRIES: dict[str, Entry] = {}
"""Every registered estimator, by name, in the order the families registered them (each family's module
declares its own entries: :func:`register`)."""


def register(*entries: Entry) -> None:
    """Add ``entries`` to the registry (a family's module calls this beside its classes, as a channel class
    registers its ``section``): afterwards :func:`get`, the sweep files, the line-ups and ``tobitkf estimators``
    know them, with no edit to this module.

    Raises
    ------
    ValidationError
        A name that another entry (a different summary) has already taken.
    """
    for entry in entries:
        old = ENTRIES.get(entry.name)
        if old is not None and old.summary != entry.summary:
            raise ValidationError(f"estimator: {entry.name!r} is already registered ({old.summary}); give another name")
        ENTRIES[entry.name] = entry


def _maker(cls: Callable[..., Any], pieces: tuple[str, ...]) -> Callable[..., Any]:
    """The factory of ``cls``: it takes the system, then the channel ``pieces`` by section name (a name ending in
    ``?`` is optional: None when not given; ``"channel"`` is the channel the pieces make, :func:`channel_of`),
    then the options."""

    def make(system, parts, o):
        args = [
            channel_of(parts) if p == "channel" else parts.get(p[:-1]) if p.endswith("?") else parts[p] for p in pieces
        ]
        return cls(system, *args, **o)

    return make


def family_entry(cls: Any, summary: str, takes: tuple[str, ...] = (), **fields: Any) -> Entry:
    """The entry of the estimator class ``cls``, built as ``cls(system, *pieces, **options)`` with the channel
    pieces ``takes`` by section name (:func:`_maker`): it needs those not marked optional (``?``). ``fields`` are
    the entry's other fields (``options``, ``required``, ``reads``, ``model``); a ``name`` other than the class's,
    ``needs`` (a channel piece the estimator can do without) and a ``factory`` of its own
    (``factory(system, parts, options)``) replace the defaults."""
    needs = fields.pop("needs", tuple(p for p in takes if not p.endswith("?")))
    name = fields.pop("name", None) or cls.__name__
    factory = fields.pop("factory", None) or _maker(cls, takes)
    return Entry(name, summary, factory, needs=needs, **fields)


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
