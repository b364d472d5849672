"""Sweep files: TOML parsed as data (never evaluated), validated on load.

A sweep file names either a model + censoring + estimators, or a registered experiment,
plus a parameter grid, the run count, the horizon and a seed::

    [sweep]
    runs = 100000          # Monte Carlo runs per grid point
    steps = 100            # horizon T
    seed = 0
    block_runs = 2000      # runs per block: the unit of seeding and of storage
    chunk_blocks = 5       # blocks per task sent to a worker (does not change the numbers)

    [model]                # LinearSystem arguments (constant matrices)
    A = [[1.0, 0.05], [0.0, 1.0]]
    C = [[1.0, 0.0]]
    Q = [[1e-4, 0.0], [0.0, 1e-3]]
    R = [[0.01]]
    x0 = [0.0, 0.0]
    P0 = [[1.0, 0.0], [0.0, 1.0]]

    [censoring]
    lower = 0.0            # TOML writes infinities as inf / -inf
    upper = inf

    [estimators.tkf]
    type = "TobitKalmanFilter"
    noise_term = "dissertation"

    [estimators.kf]
    type = "KalmanFilter"

    [grid]                 # cartesian product; keys are dotted paths into this file
    "censoring.lower" = [-0.5, 0.0, 0.5]

Channel sections (optional; the pieces of :mod:`tobitkf.channels` the data pass and the estimators
that need them take): ``[fading]`` (``order`` L, the coefficients' ``mean`` and ``variance`` per delay
s = 0..L (a Gaussian law), or ``low``/``high`` (uniform)) and ``[protocol]`` (``window`` ℓ,
``threshold`` τ, ``failures`` = ``"none"``, ``"base"`` (the example's Λ on {0, 0.5, 1}, mean 0.9),
``"lambda1"`` (mean 0.6) or a table ``{values = [...], probs = [...]}``, ``order``, ``prehistory``),
``[quantizer]`` (``width``, ``offset``, ``lower``, ``upper``; it replaces ``[censoring]``), and the table of
any channel class of your own that registers a ``section`` with ``sweep_options``
(:mod:`tobitkf.channels.base`): the tables are the registered channels', not a list kept here.
Estimator types are the registry's families on a linear model (:mod:`tobitkf.filters.registry`):
``KalmanFilter``, ``DroppingKalmanFilter``, ``TobitKalmanFilter``, ``SteadyStateTobitKalmanFilter``
(``xi_uncensored = ...``; it reads the latent readings and censors them itself),
``ControlledLimitTobitKalmanFilter``, ``FadingTobitKalmanFilter``, ``FadingKalmanFilter``
(need ``[fading]``), ``ProtocolTobitKalmanFilter``, ``ProtocolBaselineTobitKalmanFilter`` (need
``[protocol]``, which replaces ``[censoring]``), and for any channel ``AssumedDensityFilter``,
``TobitFilter`` and ``ParticleFilter`` (``seed = ...``).

Experiment mode: ``[sweep] experiment = "miller-oscillator"``, optional ``[settings]``
(keyword overrides of the experiment's ``run``), and grid keys ``"settings.<name>"``.
The runs are split into blocks as in model mode: block ``b`` of a grid point runs the
experiment with ``block_runs`` runs and the integer seed :func:`tobitkf.sweep.run.experiment_seed`
``(seed, b)``, and its per-step RMSE, bias and NEES are turned back into sums (RMSE² × runs,
...), so experiment sweeps stream, resume and parallelise like model sweeps. Use
``block_runs = runs`` to run the experiment once per grid point.

Errors name the key and the line of the file (:class:`SweepFileError`).
"""

from __future__ import annotations

import itertools
import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .._validation import ValidationError

__all__ = ["SweepFileError", "SweepSpec", "load_sweep", "parse_sweep", "ESTIMATOR_TYPES"]


def _estimator_types() -> dict[str, tuple[str, ...]]:
    from ..filters.registry import ENTRIES

    return {
        name: tuple(e.options) for name, e in ENTRIES.items() if e.model == "linear" and set(e.needs) <= _SWEEP_PIECES
    }


def _channel_keys() -> dict[str, set[str]]:
    """The channel tables a sweep file may have (every registered channel class with ``sweep_options``, but
    ``[censoring]``, which a model-mode sweep always has) and the keys each accepts (tobitkf.channels.base)."""
    from ..channels.base import registered_channels

    return {
        sec: set(cls.sweep_options)
        for sec, cls in registered_channels().items()
        if cls.sweep_options and sec != "censoring"
    }


def _own_limits(sec: str) -> bool:
    from ..channels.base import channel_class

    return channel_class(sec).replaces_censoring


# the channel pieces a sweep file describes (its sections), and "channel": any of them
_SWEEP_PIECES = {"censoring", "channel", *_channel_keys()}
# estimator types a sweep file may name (every registered family on a LinearSystem whose channel pieces a
# sweep file describes, tobitkf.filters.registry), with the options each accepts (checked on load)
ESTIMATOR_TYPES: dict[str, tuple[str, ...]] = _estimator_types()
_SWEEP_KEYS = {"runs", "steps", "seed", "block_runs", "chunk_blocks", "name", "experiment"}
_MODEL_KEYS = {"A", "C", "Q", "R", "x0", "P0", "B"}
_CENS_KEYS = {"lower", "upper"}
_TOP = {"sweep", "model", "censoring", "estimators", "grid", "settings"}  # and the channel tables


class SweepFileError(ValidationError):
    """A sweep file is malformed; the message names the key and its line."""


MAX_FILE_BYTES = 16 * 2**20  # a sweep file is a few kB; this bounds what is read
MAX_DEPTH = 16  # tables/arrays nested deeper than this are no sweep (a grid of time-varying
# matrices needs 5 levels)
MAX_GRID_POINTS = 10_000  # every point is built once on load; more would take minutes to check
MAX_NAME_BYTES = 200  # of the store's name, leaving room for ".zarr", "_plots" and temporary suffixes


def _depth(obj: Any, limit: int) -> tuple[int, str]:
    """Deepest nesting of tables/arrays below the top level (counted without recursion) and the
    top-level key where it is; stops beyond ``limit``."""
    deepest, where = 0, ""
    stack = [(v, 1, k) for k, v in obj.items()] if isinstance(obj, dict) else []
    while stack:
        v, d, top = stack.pop()
        if isinstance(v, (dict, list)):
            if d > deepest:
                deepest, where = d, top
            if d > limit:
                break
            stack.extend((x, d + 1, top) for x in (v.values() if isinstance(v, dict) else v))
    return deepest, where


def _check_name(text: str, key: str, sname: Any) -> None:
    if (
        not isinstance(sname, str)
        or not sname
        or any(c in sname for c in "/\\")
        or sname.startswith(".")
        or not sname.isprintable()
    ):
        raise _fail(text, key, f"expected a plain file name, got {sname!r}")
    size = len(sname.encode("utf-8", "surrogatepass"))
    if size > MAX_NAME_BYTES:
        raise _fail(
            text,
            key,
            f"expected a name of at most {MAX_NAME_BYTES} bytes (it names the store folder), "
            f"got {size} bytes ({sname[:20]!r}...)",
        )


def _line_of(text: str, dotted: str) -> int | None:
    """1-based line where ``dotted`` (``section.key`` or ``section``) is defined, if found."""
    parts = dotted.split(".")
    section, key = (".".join(parts[:-1]), parts[-1]) if len(parts) > 1 else ("", parts[0])
    current = ""
    for i, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if line.startswith("[") and line.endswith("]"):
            current = line.strip("[]").strip().replace('"', "")
            if current == dotted:
                return i
            continue
        if "=" in line:
            lhs = line.split("=", 1)[0].strip().strip('"')
            if (
                (current == section and lhs == key)
                or (current == "" and lhs == dotted)
                or (current == parts[0] and lhs == ".".join(parts[1:]))
            ):
                return i
    return None


def _fail(text: str, key: str, message: str) -> SweepFileError:
    line = _line_of(text, key)
    where = f" (line {line})" if line else ""
    return SweepFileError(f"sweep file: {key}{where}: {message}")


@dataclass
class SweepSpec:
    """A validated sweep file."""

    text: str
    name: str
    runs: int
    steps: int
    seed: int
    block_runs: int
    chunk_blocks: int
    experiment: str | None
    model: dict[str, Any]
    censoring: dict[str, Any]
    estimators: dict[str, dict[str, Any]]
    settings: dict[str, Any]
    grid: dict[str, list[Any]] = field(default_factory=dict)
    channels: dict[str, dict[str, Any]] = field(default_factory=dict)

    @property
    def blocks(self) -> int:
        """Number of run blocks per grid point."""
        return -(-self.runs // self.block_runs)

    def block_sizes(self) -> list[int]:
        """Runs in each block: ``block_runs``, the last one the rest."""
        full, rest = divmod(self.runs, self.block_runs)
        return [self.block_runs] * full + ([rest] if rest else [])

    @property
    def grid_shape(self) -> tuple[int, ...]:
        return tuple(len(v) for v in self.grid.values())

    def points(self) -> list[dict[str, Any]]:
        """Every grid point as ``{dotted key: value}`` (row-major over the grid keys)."""
        keys = list(self.grid)
        return [dict(zip(keys, combo)) for combo in itertools.product(*self.grid.values())] or [{}]

    def resolved(self, point: dict[str, Any]) -> dict[str, Any]:
        """Model, censoring, estimators and settings with a grid point applied."""
        out = {
            "model": dict(self.model),
            "censoring": dict(self.censoring),
            "estimators": {k: dict(v) for k, v in self.estimators.items()},
            "settings": dict(self.settings),
        }
        out.update({k: dict(v) for k, v in self.channels.items()})
        for dotted, value in point.items():
            parts = dotted.split(".")
            target = out[parts[0]]
            for p in parts[1:-1]:
                target = target[p]
            target[parts[-1]] = value
        return out

    def check_size(
        self, n: int | None, m: int | None, q: int | None, estimators: int | None, *, parallel: int = 1
    ) -> None:
        """Refuse, before anything is stored or run, a sweep whose arrays cannot fit in memory:
        the ``done`` flags of every block, and (model mode, where the sizes are known) one block's
        simulated data and filter output (times ``parallel`` blocks computed side by side), and the
        statistics the reduction reads at once.

        Raises
        ------
        SweepFileError
            Naming ``sweep.runs``/``sweep.steps``/``sweep.block_runs`` and the sizes.
        """
        from .._validation import check_memory

        points = int(np.prod(self.grid_shape, dtype=object)) if self.grid else 1
        blocks = points * self.blocks
        try:
            check_memory(
                blocks,
                "sweep.runs",
                f"{self.runs} runs in blocks of {self.block_runs} at {points} grid "
                f"point(s) ({blocks} blocks; one flag each)",
            )
            if n is None:
                return
            assert m is not None and q is not None and estimators is not None, "model mode gives every size"
            R, T = self.block_runs, self.steps
            check_memory(
                8 * parallel * R * (T + 1) * (n + q + 3 * m + 3 * n + n * n),
                "sweep.steps",
                ("one block" if parallel == 1 else f"{parallel} blocks side by side (workers)")
                + f" of {R} runs (sweep.block_runs) x {T} steps (n = {n}, m = {m}: simulated data "
                "and one filter's means and covariances)",
            )
            stats = estimators * T * (2 * n + 1) + T * m + 1
            check_memory(
                8 * blocks * stats,
                "sweep.steps",
                f"the statistics of {blocks} blocks x {T} steps, read at once to reduce the sweep",
            )
        except ValidationError as exc:
            key = str(exc).split(":", 1)[0]
            raise _fail(self.text, key, str(exc).split(": ", 1)[1]) from None

    def canonical(self) -> str:
        """A canonical JSON form of everything that determines the numbers (used to refuse
        resuming a store made by a different sweep)."""
        doc = {
            "runs": self.runs,
            "steps": self.steps,
            "seed": self.seed,
            "block_runs": self.block_runs,
            "experiment": self.experiment,
            "model": self.model,
            "censoring": self.censoring,
            "estimators": self.estimators,
            "settings": self.settings,
            "grid": self.grid,
        }
        if self.channels:  # only then: the canonical form of a channel-free sweep is unchanged
            doc["channels"] = self.channels
        return json.dumps(doc, sort_keys=True, default=str)


def _int(text: str, table: dict, key: str, dotted: str, *, default: int | None = None, minimum: int = 1) -> int:
    if key not in table:
        if default is None:
            raise _fail(text, dotted.rsplit(".", 1)[0], f"missing required key {key!r}")
        return default
    val = table[key]
    if isinstance(val, bool) or not isinstance(val, int) or val < minimum:
        raise _fail(text, dotted, f"expected an integer >= {minimum}, got {val!r:.60}")
    return val


def _setting_names(run) -> set[str] | None:
    """Keyword settings an experiment's ``run`` accepts (None when it takes ``**overrides``)."""
    import inspect

    params = inspect.signature(run).parameters.values()
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params):
        return None
    return {p.name for p in params if p.kind is inspect.Parameter.KEYWORD_ONLY} - {"runs", "seed", "progress"}


def parse_sweep(text: str, *, name: str = "sweep") -> SweepSpec:
    """Parse and validate the text of a sweep file."""
    if not isinstance(text, str):
        raise SweepFileError(f"sweep file: expected the text of a sweep file, got {type(text).__name__}")
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SweepFileError(f"sweep file: not valid TOML: {exc}") from None
    except RecursionError:
        raise SweepFileError(
            f"sweep file: arrays or tables nested too deeply to read (at most {MAX_DEPTH} levels)"
        ) from None
    except ValueError as exc:  # e.g. an integer of more than 4300 digits
        raise SweepFileError(f"sweep file: not valid TOML: {' '.join(str(exc).split())[:200]}") from None
    depth, where = _depth(doc, MAX_DEPTH)
    if depth > MAX_DEPTH:
        raise _fail(text, where, f"nested more than {MAX_DEPTH} levels deep; a sweep file needs at most a few")
    _CHANNEL_KEYS = _channel_keys()  # noqa: N806  (the registered channels when the file is read)
    top = _TOP | set(_CHANNEL_KEYS)
    for key in doc:
        if key not in top:
            raise _fail(text, key, f"unknown table; expected one of {', '.join(sorted(top))}")
    sw = doc.get("sweep")
    if not isinstance(sw, dict):
        raise SweepFileError("sweep file: missing the [sweep] table (runs, steps, seed)")
    for key in sw:
        if key not in _SWEEP_KEYS:
            raise _fail(text, f"sweep.{key}", f"unknown key; expected one of {', '.join(sorted(_SWEEP_KEYS))}")
    runs = _int(text, sw, "runs", "sweep.runs")
    steps = _int(text, sw, "steps", "sweep.steps", default=0, minimum=0)
    seed = _int(text, sw, "seed", "sweep.seed", minimum=0)
    block_runs = _int(text, sw, "block_runs", "sweep.block_runs", default=min(runs, 2000))
    chunk_blocks = _int(text, sw, "chunk_blocks", "sweep.chunk_blocks", default=max(1, 10_000 // block_runs))
    experiment = sw.get("experiment")
    sname = sw.get("name", name)
    _check_name(text, "sweep.name", sname)
    model = doc.get("model", {})
    cens = doc.get("censoring", {})
    ests = doc.get("estimators", {})
    settings = doc.get("settings", {})
    if experiment is not None:
        from ..experiments import get

        if not isinstance(experiment, str):
            raise _fail(text, "sweep.experiment", f"expected an experiment id, got {experiment!r}")
        try:
            exp = get(experiment)
        except ValidationError as exc:
            raise _fail(text, "sweep.experiment", str(exc)) from None
        if not isinstance(settings, dict):
            raise _fail(text, "settings", "expected a table of the experiment's settings")
        known = _setting_names(exp.run)
        grid_settings = [k.split(".", 1)[1] for k in doc.get("grid", {}) if k.startswith("settings.")]
        for key in list(settings) + grid_settings:
            if known is not None and key not in known:
                where = f"settings.{key}" if key in settings else f"grid.settings.{key}"
                raise _fail(text, where, f"unknown setting of {experiment}; known: {', '.join(sorted(known))}")
        for tbl in ("model", "censoring", "estimators", *_CHANNEL_KEYS):
            if tbl in doc:
                raise _fail(text, tbl, "not allowed together with sweep.experiment (use [settings])")
    else:
        if steps < 1:
            raise _fail(text, "sweep.steps" if "steps" in sw else "sweep", "expected an integer >= 1 (the horizon)")
        if "settings" in doc:
            raise _fail(text, "settings", "only allowed with sweep.experiment")
        for key in _MODEL_KEYS - {"B"}:
            if key not in model:
                raise _fail(text, "model", f"missing required key {key!r}")
        for key in model:
            if key not in _MODEL_KEYS:
                raise _fail(text, f"model.{key}", f"unknown key; expected one of {', '.join(sorted(_MODEL_KEYS))}")
        for key in cens:
            if key not in _CENS_KEYS:
                raise _fail(text, f"censoring.{key}", "unknown key; expected 'lower' or 'upper'")
        for sec, allowed_keys in _CHANNEL_KEYS.items():
            tbl = doc.get(sec, {})
            if not isinstance(tbl, dict):
                raise _fail(text, sec, "expected a table")
            for key in tbl:
                if key not in allowed_keys:
                    raise _fail(text, f"{sec}.{key}", f"unknown key; expected one of {', '.join(sorted(allowed_keys))}")
        own = [sec for sec in _CHANNEL_KEYS if sec in doc and _own_limits(sec)]
        if len(own) > 1:
            raise _fail(text, own[1], f"[{own[0]}] and [{own[1]}] each carry their own limits; keep one")
        if own and cens:
            raise _fail(text, "censoring", f"the [{own[0]}] channel carries its own limits; drop [censoring]")
        if not ests:
            raise _fail(text, "estimators", "expected at least one [estimators.<key>] table")
        for key, est in ests.items():
            if not isinstance(est, dict) or "type" not in est:
                raise _fail(text, f"estimators.{key}", "expected a table with a 'type'")
            from ..filters.registry import ENTRIES

            if isinstance(est["type"], str) and est["type"] in ENTRIES and est["type"] not in ESTIMATOR_TYPES:
                raise _fail(
                    text,
                    f"estimators.{key}.type",
                    f"{est['type']} is not a family on a linear model with the channel pieces of a sweep file "
                    f"(its model: {ENTRIES[est['type']].model}, its pieces: "
                    f"{', '.join(ENTRIES[est['type']].needs) or 'none'}); sweep it through its experiment "
                    "(sweep.experiment)",
                )
            if not isinstance(est["type"], str) or est["type"] not in ESTIMATOR_TYPES:
                raise _fail(
                    text,
                    f"estimators.{key}.type",
                    f"unknown estimator type {est['type']!r}; expected one of {', '.join(ESTIMATOR_TYPES)}",
                )
            for opt in est:
                if opt != "type" and opt not in ESTIMATOR_TYPES[est["type"]]:
                    raise _fail(
                        text,
                        f"estimators.{key}.{opt}",
                        f"unknown option for {est['type']}; expected one of "
                        f"{', '.join(ESTIMATOR_TYPES[est['type']]) or 'none'}",
                    )
    grid = doc.get("grid", {})
    if not isinstance(grid, dict):
        raise _fail(text, "grid", "expected a table of dotted keys and lists of values")
    points = 1
    for values in grid.values():
        points *= len(values) if isinstance(values, list) else 1
    if points > MAX_GRID_POINTS:
        raise _fail(
            text,
            "grid",
            f"{points} grid points, more than the {MAX_GRID_POINTS} one sweep may have (split it into several sweeps)",
        )
    for key, values in grid.items():
        if not isinstance(values, list) or not values:
            raise _fail(text, f"grid.{key}", "expected a non-empty list of values")
        root = key.split(".")[0]
        allowed = {"settings"} if experiment is not None else {"model", "censoring", "estimators", *_CHANNEL_KEYS}
        if root not in allowed or "." not in key:
            raise _fail(text, f"grid.{key}", f"grid keys are dotted paths starting with {' or '.join(sorted(allowed))}")
        parts = key.split(".")
        if root == "estimators":
            if len(parts) != 3 or parts[1] not in ests:
                raise _fail(text, f"grid.{key}", "expected 'estimators.<key>.<option>' naming a listed estimator")
            opts = ESTIMATOR_TYPES[ests[parts[1]]["type"]]
            if parts[2] not in opts:
                raise _fail(
                    text,
                    f"grid.{key}",
                    f"unknown option for {ests[parts[1]]['type']}; expected one of {', '.join(opts) or 'none'}",
                )
        elif len(parts) != 2:
            raise _fail(text, f"grid.{key}", f"expected '{root}.<key>' (one level deep)")
        elif root == "model" and parts[1] not in _MODEL_KEYS:
            raise _fail(text, f"grid.{key}", f"unknown model key; expected one of {', '.join(sorted(_MODEL_KEYS))}")
        elif root == "censoring" and parts[1] not in _CENS_KEYS:
            raise _fail(text, f"grid.{key}", "unknown censoring key; expected 'lower' or 'upper'")
        elif root in _CHANNEL_KEYS and (root not in doc or parts[1] not in _CHANNEL_KEYS[root]):
            raise _fail(
                text,
                f"grid.{key}",
                f"expected a key of the file's [{root}] table ({', '.join(sorted(_CHANNEL_KEYS[root]))})",
            )
    spec = SweepSpec(
        text=text,
        name=sname,
        runs=runs,
        steps=steps,
        seed=seed,
        block_runs=block_runs,
        chunk_blocks=chunk_blocks,
        experiment=experiment,
        model=model,
        censoring=cens,
        estimators=ests,
        settings=settings,
        grid=grid,
        channels={sec: dict(doc[sec]) for sec in _CHANNEL_KEYS if sec in doc},
    )
    # build the base model and every grid point once, so that a bad matrix or limit fails on
    # load (naming the key that holds it), not mid-sweep
    if experiment is None:
        from .build import build_point

        try:
            base = build_point(spec, {})
        except ValidationError as exc:
            arg = str(exc).split(":", 1)[0].split("(")[0].strip()
            est_key = next((f"estimators.{k}.{arg}" for k, e in ests.items() if arg in e), None)
            chan = next((f"{sec}.{arg}" for sec in _CHANNEL_KEYS if arg in spec.channels.get(sec, {})), None)
            key = (
                f"model.{arg}"
                if arg in _MODEL_KEYS
                else ("censoring" if arg.startswith(("lower", "upper", "censoring")) else (est_key or chan or "model"))
            )
            raise _fail(text, key, str(exc)) from None
        for point in spec.points():
            try:
                build_point(spec, point)
            except ValidationError as exc:
                key = next(iter(point))
                raise _fail(text, f"grid.{key}", f"invalid at grid point {point}: {exc}") from None
        spec.check_size(base.system.n, base.system.m, base.system.q, len(base.estimators))
    else:
        spec.check_size(None, None, None, None)
    return spec


def load_sweep(path: str | Path) -> SweepSpec:
    """Read and validate a sweep file.

    Raises
    ------
    SweepFileError
        The file cannot be read, is not a regular file, is larger than 16 MiB, is not UTF-8
        text, or its content is refused (:func:`parse_sweep`).
    """
    from .._io import as_path

    path = as_path(path, "sweep file")
    try:
        if path.exists() and not path.is_file():
            raise SweepFileError(
                f"sweep file: {path} is {'a folder' if path.is_dir() else 'not a regular file'}; expected a TOML file"
            )
        size = path.stat().st_size
        if size > MAX_FILE_BYTES:
            raise SweepFileError(
                f"sweep file: {path} is {size / 2**20:.0f} MiB, more than the "
                f"{MAX_FILE_BYTES // 2**20} MiB a sweep file may have"
            )
        raw = path.read_bytes()
    except OSError as exc:
        raise SweepFileError(f"sweep file: cannot read {path}: {exc.strerror or exc}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise SweepFileError(
            f"sweep file: {path} is not UTF-8 text (byte 0x{raw[exc.start]:02x} on line {line}); save it as UTF-8"
        ) from None
    name = path.stem
    if len(name.encode("utf-8", "surrogateescape")) > MAX_NAME_BYTES or not name.isprintable():
        name = "sweep"  # the file name is only the default store name; a [sweep] name = "..." wins
    return parse_sweep(text, name=name)


def jsonable_grid(grid: dict[str, list[Any]]) -> dict[str, list[Any]]:
    """Grid values made JSON-friendly (infinities as strings)."""
    from .._io import to_jsonable

    return {k: to_jsonable(v) for k, v in grid.items()}


def scalar_axis(values: list[Any]) -> np.ndarray | None:
    """The grid values as a float coordinate if they are all scalars, else None."""
    if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
        return np.asarray(values, dtype=float)
    return None
