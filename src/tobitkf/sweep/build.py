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

    @property
    def reading_width(self) -> int:
        """Channels of the readings the estimators receive (1 for the protocol channel's scalar)."""
        return 1 if self.parts.get("protocol") is not None else self.system.m

    def channel(self) -> list[Any]:
        """The pieces the simulator draws, in order (the protocol channel censors and schedules itself)."""
        if self.parts.get("protocol") is not None:
            return [self.parts["protocol"]]
        return [p for p in (self.parts.get("fading"), self.parts.get("censoring")) if p is not None]

    def censored(self, y: np.ndarray) -> np.ndarray:
        """(N, T, width) mask of the readings at a censoring limit."""
        if self.parts.get("protocol") is not None:
            return y <= self.parts["protocol"].threshold
        lo, hi = self.parts["censoring"].censored_mask(y)
        return lo | hi

    # the pre-0.2 tuple form: (system, censoring, {key: estimator})
    def __iter__(self):
        return iter((self.system, self.parts.get("censoring"), {k: e for k, (_, e) in self.estimators.items()}))


def _law(tbl: dict[str, Any] | str | None, name: str):
    from ..channels.laws import PMF

    if tbl is None or tbl == "none":
        return None
    if isinstance(tbl, str):
        from ..channels.protocol import LAMBDA_1, LAMBDA_BASE

        laws = {"base": LAMBDA_BASE, "lambda1": LAMBDA_1}
        if tbl not in laws:
            raise ValidationError(
                f"{name}: expected 'none', 'base', 'lambda1' or a table {{values, probs}}, got {tbl!r}"
            )
        return laws[tbl]
    if not isinstance(tbl, dict) or set(tbl) != {"values", "probs"}:
        raise ValidationError(f"{name}: expected a table with 'values' and 'probs', got {tbl!r}")
    return PMF(tbl["values"], tbl["probs"])


def _fading(tbl: dict[str, Any]):
    from ..channels.fading import RiceFading
    from ..channels.laws import Uniform

    if "order" not in tbl:
        raise ValidationError("order: the [fading] channel needs its order L")
    if "low" in tbl or "high" in tbl:
        if "mean" in tbl or "variance" in tbl:
            raise ValidationError("mean: give either mean/variance (Gaussian) or low/high (uniform), not both")
        return RiceFading(tbl["order"], Uniform(tbl.get("low"), tbl.get("high")))
    if "mean" not in tbl:
        raise ValidationError("mean: the [fading] channel needs the coefficients' means (or low/high)")
    return RiceFading.gaussian(tbl["order"], tbl["mean"], tbl.get("variance", 0.0))


def _protocol(tbl: dict[str, Any], system):
    from ..channels.protocol import ProtocolChannel

    kw = {k: v for k, v in tbl.items() if k in ("window", "threshold", "order", "prehistory")}
    if "threshold" in kw:
        kw["threshold"] = float(kw["threshold"])
    failures = _law(tbl.get("failures"), "failures")
    if failures is not None:
        kw["failures"] = failures
    return ProtocolChannel(system.m, **kw)


def build_point(spec: Any, point: dict[str, Any], *, threads: int | None = None) -> Point:
    """System, channel pieces and estimator objects of one grid point (model mode).

    ``threads`` is passed to the estimators that split their runs over threads (the TKF's
    compiled kernel); None keeps their default."""
    from ..channels.censoring import Censoring
    from ..filters.registry import get
    from ..models.linear import LinearSystem

    r = spec.resolved(point)
    sys_ = LinearSystem(**r["model"])
    parts: dict[str, Any] = {}
    if "protocol" in r:
        parts["protocol"] = _protocol(r["protocol"], sys_)
    else:
        cens = Censoring(**r["censoring"])
        cens.check(sys_.m, spec.steps)
        parts["censoring"] = cens
    if "fading" in r:
        parts["fading"] = _fading(r["fading"])
        parts["fading"].check(sys_.m)
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
