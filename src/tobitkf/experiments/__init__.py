"""Registry of the sources' numerical examples, each a named, reproducible experiment.

An experiment is a function ``run(*, runs, seed, progress=None, **settings) ->
ExperimentResult`` (``progress(fraction)`` or ``progress(fraction, note)``, the note saying what it
is doing, e.g. which estimator runs) registered with :func:`register`, plus a ``plot(result, outdir)``
function that draws its figures. The CLI only calls them. Every module in this
package is imported by :func:`all_experiments`, so a new experiment module registers
itself by being placed here.

Every claim an experiment returns follows the claims rule of :mod:`._claims` (its quantity,
test and tolerance; n/a only for what cannot be measured); :func:`register` checks it on
return, and records the warnings raised while it runs (:func:`recorded_warnings`, into
``metrics["warnings"]``: the report shows them, the console stays quiet). Each figure is saved with a caption (:func:`tobitkf.plotting.save`), which the
registered ``plot`` collects into ``metrics["figure_captions"]``; tables the source prints
go into ``metrics["report_tables"]`` (see :func:`report_table`), and the report shows both.
"""

from __future__ import annotations

import importlib
import pkgutil
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .._validation import ValidationError

__all__ = [
    "Experiment",
    "ExperimentResult",
    "register",
    "get",
    "all_experiments",
    "setting",
    "report_table",
    "progress_callback",
    "recorded_warnings",
]


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
        The source's claims checked by this experiment, each following the claims rule of
        :mod:`tobitkf.experiments._claims`: ``{"claim", "quantity", "measured", "test",
        "tolerance", "holds"}`` (+ ``note``, ``explanation``, ``not_measurable``).
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
    full_runs: int | None = None
    full_settings: dict[str, Any] = field(default_factory=dict)
    cost: float = 1.0
    """Roughly its seconds at the default size (a hint: ``tobitkf reproduce`` starts the longest first)."""

    def runs_for(self, full: bool = False) -> int:
        """The run count of a default run, or of a full run (``tobitkf reproduce --full``: the sources' sizes)."""
        return self.full_runs if full and self.full_runs is not None else self.default_runs

    def settings_for(self, full: bool = False) -> dict[str, Any]:
        """Keyword settings beside ``runs`` of a full run (e.g. larger particle counts); none by default."""
        return dict(self.full_settings) if full else {}


_REGISTRY: dict[str, Experiment] = {}
_DISCOVERED = False


def setting(value: Any, provenance: str = "source", note: str = "") -> dict[str, Any]:
    """A parameter with its provenance: ``"source"`` (stated in the source), ``"reconstructed"``
    (missing or wrong in the source, rebuilt by us; ``docs/sources/`` says how) or ``"default"``
    (not stated; our choice)."""
    if provenance not in ("source", "reconstructed", "default"):
        raise ValidationError(f"provenance: expected 'source', 'reconstructed' or 'default', got {provenance!r}")
    return {"value": value, "provenance": provenance, "note": note}


def report_table(title: str, columns: list[str], rows: list[list[Any]], note: str = "") -> dict[str, Any]:
    """A table for the report (``metrics["report_tables"]``): the source's printed numbers next to ours.

    ``rows`` hold plain values (numbers are shown to 4 significant digits); ``note`` says how
    to read the table (e.g. why the numbers are not expected to agree).
    """
    if not columns or any(len(r) != len(columns) for r in rows):
        raise ValidationError(f"report_table {title!r}: every row needs {len(columns)} cells")
    return {"title": title, "columns": list(columns), "rows": [list(r) for r in rows], "note": note}


def register(
    id: str,
    *,
    title: str,
    source: str,
    plot: Callable[[ExperimentResult, Path], list[Path]],
    default_runs: int,
    full_runs: int | None = None,
    full_settings: dict[str, Any] | None = None,
    cost: float = 1.0,
):
    """Decorator registering ``run`` under ``id``.

    ``default_runs`` is the run count of ``tobitkf reproduce``; ``full_runs`` (default: the same) and
    ``full_settings`` (keyword settings, default none) those of ``tobitkf reproduce --full``, the sources'
    sizes, for an experiment whose default is smaller to keep the main job short. ``cost``, roughly its seconds at
    the default size, orders the experiments when ``tobitkf reproduce`` runs several at once (longest first). A smaller default
    must still support every claim: the claims' tolerances come from the run count actually used.

    The registered (and returned) ``run`` checks the claims of its result against the claims
    rule (:func:`tobitkf.experiments._claims.check_claims`); the registered ``plot`` stores the
    figures' captions in ``result.metrics["figure_captions"]``.
    """
    import functools

    from ..plotting import collect_captions
    from ._claims import check_claims

    @functools.wraps(plot)
    def plot_with_captions(result: ExperimentResult, outdir: Path) -> list[Path]:
        with collect_captions() as captions:
            paths = plot(result, outdir)
        result.metrics["figure_captions"] = {Path(p).name: captions.get(Path(p).name, "") for p in paths}
        return paths

    def deco(run: Callable[..., ExperimentResult]) -> Callable[..., ExperimentResult]:
        if id in _REGISTRY and _REGISTRY[id].module != run.__module__:
            raise ValueError(f"experiment id {id!r} registered twice")

        @functools.wraps(run)
        def checked_run(*args: Any, **kwargs: Any) -> ExperimentResult:
            with recorded_warnings() as caught:
                result = run(*args, **kwargs)
            check_claims(result.claims, id)
            result.metrics["warnings"] = caught
            return result

        _REGISTRY[id] = Experiment(
            id=id,
            title=title,
            source=source,
            run=checked_run,
            plot=plot_with_captions,
            default_runs=default_runs,
            module=run.__module__,
            full_runs=full_runs,
            full_settings=dict(full_settings or {}),
            cost=float(cost),
        )
        return checked_run

    return deco


@contextmanager
def recorded_warnings() -> Iterator[list[str]]:
    """Record the warnings raised inside the block instead of printing them: yields a list that holds, when
    the block ends, each distinct warning's text once, in the order first raised (a diverging variant an
    experiment runs on purpose warns once per filter call; the report lists what was said, not how often).
    Every registered experiment runs inside it; its list becomes ``metrics["warnings"]``."""
    found: list[str] = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            yield found
        finally:
            seen: set[str] = set()
            for w in caught:
                text = " ".join(str(w.message).split())
                if text not in seen:
                    seen.add(text)
                    found.append(text)


def progress_callback(progress: Callable[..., Any] | None) -> Callable[..., None]:
    """``progress`` as a callback that takes ``(fraction, note=None)``: a callback of one argument gets the
    fraction only, None becomes a no-op (so an experiment can name what it is doing whatever it was given)."""
    if progress is None:

        def ignore(fraction: float, note: str | None = None) -> None:
            pass

        return ignore
    import inspect

    try:
        params = list(inspect.signature(progress).parameters.values())
    except (TypeError, ValueError):  # a builtin without a signature: the fraction only
        params = []
    takes_note = any(p.kind is p.VAR_POSITIONAL for p in params) or (
        sum(p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) for p in params) >= 2
    )
    user = progress

    def adapted(fraction: float, note: str | None = None) -> None:
        if takes_note:
            user(fraction, note)
        else:
            user(fraction)

    return adapted


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
