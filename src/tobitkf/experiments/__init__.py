"""Registry of the sources' numerical examples, each a named, reproducible experiment.

An experiment is a function ``run(*, runs, seed, progress=None, **settings) ->
ExperimentResult`` registered with :func:`register`, plus a ``plot(result, outdir)``
function that draws its figures. The CLI only calls them. Every module in this
package is imported by :func:`all_experiments`, so a new experiment module registers
itself by being placed here.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .._validation import ValidationError

__all__ = ["Experiment", "ExperimentResult", "register", "get", "all_experiments", "setting"]


@dataclass
class ExperimentResult:
    """What an experiment returns.

    Attributes
    ----------
    id : str
        The experiment id.
    settings : dict
        Every parameter used, each ``{"value": ..., "provenance": "source" | "reconstructed"
        | "default", "note": str}`` (see :func:`setting`).
    metrics : dict
        JSON-able results; ``metrics["estimators"][key]`` holds at least ``rmse`` (T, n)
        and ``rmse_time_avg`` (n,) for every estimator.
    data : dict
        Arrays for plotting (not written to metrics.json).
    claims : list of dict
        The source's claims checked by this experiment: ``{"claim", "measured", "holds"}``.
    """

    id: str
    settings: dict[str, Any]
    metrics: dict[str, Any]
    data: dict[str, Any] = field(default_factory=dict)
    claims: list[dict[str, Any]] = field(default_factory=list)


@dataclass(frozen=True)
class Experiment:
    """A registered experiment."""

    id: str
    title: str
    source: str
    run: Callable[..., ExperimentResult]
    plot: Callable[[ExperimentResult, Path], list[Path]]
    default_runs: int
    module: str


_REGISTRY: dict[str, Experiment] = {}
_DISCOVERED = False


def setting(value: Any, provenance: str = "source", note: str = "") -> dict[str, Any]:
    """A parameter with its provenance: ``"source"`` (stated in the source), ``"reconstructed"``
    (missing in the source, rebuilt by the spec) or ``"default"`` (not stated; our choice)."""
    if provenance not in ("source", "reconstructed", "default"):
        raise ValidationError(f"provenance: expected 'source', 'reconstructed' or 'default', got {provenance!r}")
    return {"value": value, "provenance": provenance, "note": note}


def register(id: str, *, title: str, source: str, plot: Callable[[ExperimentResult, Path], list[Path]],
             default_runs: int):
    """Decorator registering ``run`` under ``id``."""

    def deco(run: Callable[..., ExperimentResult]) -> Callable[..., ExperimentResult]:
        if id in _REGISTRY and _REGISTRY[id].module != run.__module__:
            raise ValueError(f"experiment id {id!r} registered twice")
        _REGISTRY[id] = Experiment(id=id, title=title, source=source, run=run, plot=plot,
                                   default_runs=default_runs, module=run.__module__)
        return run

    return deco


def _discover() -> None:
    global _DISCOVERED
    if _DISCOVERED:
        return
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda i: i.name):
        if not info.name.startswith("_"):
            importlib.import_module(f"{__name__}.{info.name}")
    _DISCOVERED = True


def all_experiments() -> list[Experiment]:
    """Every registered experiment, sorted by id."""
    _discover()
    return [_REGISTRY[k] for k in sorted(_REGISTRY)]


def get(id: str) -> Experiment:
    """The experiment registered under ``id``; ``ValidationError`` listing the ids otherwise."""
    _discover()
    if id not in _REGISTRY:
        raise ValidationError(f"experiment: unknown id {id!r}; known: {', '.join(sorted(_REGISTRY))}")
    return _REGISTRY[id]
