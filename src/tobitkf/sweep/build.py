"""The objects of one grid point of a model-mode sweep: system, channel pieces and estimators.

Used by the parser (:func:`tobitkf.sweep.spec.parse_sweep` builds every grid point once, so that a
bad matrix fails on load) and by the runner (:mod:`tobitkf.sweep.run`); it needs neither. Every
estimator comes from the one registry (:mod:`tobitkf.filters.registry`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .._validation import ValidationError

__all__ = ["build_point", "Point"]


@dataclass
class Point:
    """System, channel pieces (section name -> piece) and estimators (key -> (registry entry, estimator))."""

    system: Any
    parts: dict[str, Any]
    estimators: dict[str, tuple[Any, Any]]

    def _own(self) -> Any:
        """The piece that carries its own limits (the protocol channel, a quantizer), if any."""
        return next((p for p in self.parts.values() if getattr(p, "replaces_censoring", False)), None)

    @property
    def reading_width(self) -> int:
        """Channels of the readings the estimators receive (1 for the protocol channel's scalar)."""
        own = self._own()
        return self.system.m if own is None else own.reading_width(self.system)

    def channel(self) -> list[Any]:
        """The pieces the simulator draws, in order (a piece with its own limits draws and censors alone)."""
        from ..filters.registry import channel_of

        ch = channel_of(self.parts)
        return [] if ch is None else list(ch) if isinstance(ch, list) else [ch]

    def censored(self, y: np.ndarray) -> np.ndarray:
        """(N, T, width) mask of the readings at a limit of the sensor."""
        own = self._own()
        return (own if own is not None else self.parts["censoring"]).at_limit(y)


def build_point(spec: Any, point: dict[str, Any], *, threads: int | None = None) -> Point:
    """System, channel pieces and estimator objects of one grid point (model mode).

    ``threads`` is passed to the estimators that split their runs over threads (the TKF's
    compiled path); None keeps their default."""
    from ..channels.base import channel_class
    from ..channels.censoring import Censoring
    from ..filters.registry import get
    from ..models.linear import LinearSystem

    r = spec.resolved(point)
    sys_ = LinearSystem(**r["model"])
    parts: dict[str, Any] = {}
    for sec in spec.channels:  # each channel table by its registered class (tobitkf.channels.base)
        parts[sec] = channel_class(sec).from_options(r[sec], sys_)
        parts[sec].check(sys_, spec.steps)
    if not any(p.replaces_censoring for p in parts.values()):
        cens = Censoring(**r["censoring"])
        cens.check(sys_.m, spec.steps)
        parts = {"censoring": cens, **parts}
    estimators = {}
    for key, est in r["estimators"].items():
        entry = get(est["type"])
        if entry.model != "linear":
            raise ValidationError(
                f"type: {entry.name} is not a family on a linear model; sweep it through its "
                "experiment (sweep.experiment)"
            )
        opts = {k: v for k, v in est.items() if k != "type"}
        if threads is not None and entry.name == "TobitKalmanFilter":
            opts["threads"] = threads
        try:
            estimators[key] = (entry, entry.build(sys_, parts, opts))
        except TypeError as exc:  # an option of the wrong kind for the class
            raise ValidationError(f"{next(iter(opts), 'type')}: {exc}") from None
    return Point(sys_, parts, estimators)
