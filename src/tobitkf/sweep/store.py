"""The sweep results store: per-block sufficient statistics in zarr, reduced to an xarray Dataset.

Layout of ``<out>/<name>.zarr`` (zarr v3 group): two arrays,

=================  =====================================  ===================================
array              shape                                  meaning
=================  =====================================  ===================================
``stats``          (points, blocks, S)                    the block's statistics, packed
``done``           (points, blocks)                       block finished (written last)
=================  =====================================  ===================================

where the vector of length S of one block is the concatenation (C order) of

=================  =====================================  ===================================
statistic          shape                                  meaning
=================  =====================================  ===================================
``sum_err``        (estimators, T, n)                     Σ over the block's runs of x̂ - x
``sum_sq``         (estimators, T, n)                     Σ (x̂ - x)²
``sum_nees``       (estimators, T)                        Σ eᵀP⁻¹e
``censored``       (T, m)                                 number of censored readings
``count``          ()                                     runs in the block
=================  =====================================  ===================================

(:func:`unpack` splits it; the group attribute ``layout`` records the shapes). The
statistics are packed because every zarr write costs about 2 ms of the driver's CPU
whatever its size, and the driver shares the machine with the workers: one array instead
of five cut the driver's writing time of a 600-block sweep from 1.1 s to a fifth of it.

The driver writes the blocks of each task as the task's result arrives, consecutive blocks
in one slice assignment (a zarr chunk holds ``chunk_blocks`` blocks, so a task normally
writes one chunk). The ``done`` flags are written after the data, so an interrupted sweep
never counts a half-written block, and a rerun of the same command computes only the
missing blocks. Reduction sums the blocks in block order, so the result does not depend on
which worker computed which block or how blocks were grouped into tasks. The group's
attributes hold the sweep file, its canonical form and the package version.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from .._extras import require
from .._validation import ValidationError, check_memory
from .spec import SweepSpec, jsonable_grid, scalar_axis

__all__ = [
    "open_store",
    "write_blocks",
    "reduce_store",
    "load_result",
    "layout",
    "pack",
    "unpack",
    "check_store_path",
    "check_resumable",
    "read_store",
]

# attributes every store has, with their JSON types (checked when a store is reopened or read)
_ATTRS: dict[str, type] = {
    "sweep": str,
    "canonical": str,
    "package_version": str,
    "estimators": list,
    "grid": dict,
    "n": int,
    "m": int,
    "steps": int,
    "runs": int,
    "seed": int,
    "block_runs": int,
    "name": str,
    "experiment": str,
    "layout": dict,
}


_MAX_CHUNKS = 10**6  # tobitkf writes one chunk per task; far more means a damaged chunk grid


def _damaged(path: Path, what: str, exc: BaseException | None = None) -> ValidationError:
    detail = f" ({type(exc).__name__}: {' '.join(str(exc).split())[:200]})" if exc is not None else ""
    return ValidationError(
        f"sweep store: {path} is damaged or not a sweep store: {what}{detail}; delete it and run the sweep again"
    )


def check_store_path(path: Path, name: str = "--out") -> None:
    """Refuse a store path that exists but is not a folder (a file, a broken link), before any work."""
    path = Path(path)
    if (path.exists() or path.is_symlink()) and not path.is_dir():
        if name == "--out":
            raise ValidationError(
                f"--out: {path} exists and is not a sweep store folder (a file of that name is "
                "in the way); move it away or choose another output directory"
            )
        raise ValidationError(f"{name}: {path} is a file, not a sweep store (a folder DIR/<name>.zarr)")


def check_resumable(path: Path, spec: SweepSpec) -> None:
    """Refuse, before any work, an existing ``path`` that a run of the given sweep cannot resume: a file
    in the way, a damaged store, a store of another sweep or of another package version."""
    from .. import __version__

    path = Path(path)
    check_store_path(path)
    if not path.exists():
        return
    g = read_store(path, mode="r", name="--out")
    if g.attrs["canonical"] != spec.canonical():
        raise ValidationError(
            f"--out: {path} holds a different sweep; choose another output directory or delete it to start over"
        )
    if g.attrs["package_version"] != __version__:
        raise ValidationError(
            f"--out: {path} was written by tobitkf {g.attrs['package_version']!r}, this is "
            f"{__version__!r}; blocks of different versions are not mixed: delete the store "
            "to start over or choose another output directory"
        )
    P = int(np.prod(spec.grid_shape, dtype=object)) if spec.grid else 1
    if g["done"].shape != (P, spec.blocks):
        raise _damaged(path, f"it holds {g['done'].shape} blocks, the sweep has ({P}, {spec.blocks})")


def read_store(path: str | Path, *, mode: str = "r", name: str = "result"):
    """Open an existing store and check its structure: the group, its attributes (names and
    types) and the two arrays (shapes and types) as :func:`open_store` wrote them.

    Raises
    ------
    ValidationError
        ``sweep store: PATH is damaged or not a sweep store: ...`` for garbage metadata, a missing
        attribute or array, an array where the group should be, or shapes that disagree.
    """
    zarr = require("zarr", extra="sweep", feature="sweep stores")

    from .._io import as_path

    path = as_path(path, name)
    check_store_path(path, name)
    if not (path / "zarr.json").is_file():
        raise ValidationError(f"{name}: {path} is not a sweep store (no zarr.json)")
    try:
        g = zarr.open_group(str(path), mode=mode)
        attrs = dict(g.attrs)
    except Exception as exc:  # noqa: BLE001 - zarr raises JSON, key, value and its own errors for damage
        raise _damaged(path, "its zarr.json cannot be read as a group", exc) from None
    for key, typ in _ATTRS.items():
        if key not in attrs:
            raise _damaged(path, f"the attribute {key!r} is missing")
        if not isinstance(attrs[key], typ) or isinstance(attrs[key], bool):
            raise _damaged(path, f"the attribute {key!r} is a {type(attrs[key]).__name__}, expected {typ.__name__}")
    try:
        shapes = {k: tuple(int(d) for d in v) for k, v in attrs["layout"].items()}
    except (TypeError, ValueError) as exc:
        raise _damaged(path, "the attribute 'layout' does not hold shapes", exc) from None
    if list(shapes) != list(layout(1, 1, 1, 1)) or any(d < 0 for sh in shapes.values() for d in sh):
        raise _damaged(path, f"the attribute 'layout' names {list(shapes)}, expected {list(layout(1, 1, 1, 1))}")
    if not all(isinstance(v, list) and v for v in attrs["grid"].values()):
        raise _damaged(path, "the attribute 'grid' does not hold a list of values per key")
    P = int(np.prod([len(v) for v in attrs["grid"].values()], dtype=object)) if attrs["grid"] else 1
    size = sum(int(np.prod(sh, dtype=object)) for sh in shapes.values())
    for name, ndim, kind in (("stats", 3, "f"), ("done", 2, "b")):
        try:
            arr = g[name]
        except Exception as exc:  # noqa: BLE001 - KeyError for a missing array, zarr errors for garbage
            raise _damaged(path, f"the array {name!r} is missing or unreadable", exc) from None
        if not isinstance(arr, zarr.Array):
            raise _damaged(path, f"{name!r} is a group, expected an array")
        if arr.ndim != ndim or np.dtype(arr.dtype).kind != kind:
            raise _damaged(path, f"the array {name!r} has shape {arr.shape} and type {arr.dtype}")
    stats_shape, done_shape = g["stats"].shape, g["done"].shape
    B = -(-attrs["runs"] // attrs["block_runs"]) if attrs["block_runs"] > 0 and attrs["runs"] > 0 else -1
    if stats_shape[:2] != done_shape or stats_shape[0] != P or stats_shape[2] != size or done_shape[1] != B:
        raise _damaged(
            path,
            f"the arrays have shapes {stats_shape} (stats) and {done_shape} (done), expected "
            f"({P}, {B}, {size}) and ({P}, {B})",
        )
    for name in ("stats", "done"):
        arr = g[name]
        try:
            chunks = int(np.prod([-(-s // max(int(c), 1)) for s, c in zip(arr.shape, arr.chunks)], dtype=object))
        except Exception as exc:  # noqa: BLE001 - a chunk grid zarr cannot describe
            raise _damaged(path, f"the array {name!r} has no regular chunk grid", exc) from None
        if chunks > _MAX_CHUNKS:
            raise _damaged(path, f"the array {name!r} is split into {chunks} chunks (more than {_MAX_CHUNKS})")
    try:
        check_memory(
            int(np.prod(stats_shape, dtype=object)) * 8 + int(np.prod(done_shape, dtype=object)),
            name,
            f"reading the sweep store {path}",
        )
    except ValidationError as exc:
        raise _damaged(path, str(exc).split(": ", 1)[1]) from None
    return g


def _where(g) -> Path:
    """The folder of an open store (for messages)."""
    return Path(str(g.store_path).removeprefix("file://"))


def _read(g, name: str) -> np.ndarray:
    """All of one array, a damaged chunk turned into a named error."""
    try:
        return g[name][:]
    except Exception as exc:  # noqa: BLE001 - codecs raise many kinds of errors for a corrupt chunk
        raise _damaged(_where(g), f"the array {name!r} cannot be read (a corrupt chunk)", exc) from None


def layout(estimators: int, steps: int, n: int, m: int) -> dict[str, tuple[int, ...]]:
    """Shapes of the statistics of one block, in packing order."""
    return {
        "sum_err": (estimators, steps, n),
        "sum_sq": (estimators, steps, n),
        "sum_nees": (estimators, steps),
        "censored": (steps, m),
        "count": (),
    }


def pack(stats: dict[str, np.ndarray], shapes: dict[str, tuple[int, ...]]) -> np.ndarray:
    """One block's statistics as a flat vector (checked against ``shapes``).

    Raises
    ------
    ValidationError
        A statistic whose shape differs from the store's (a grid point that changes the
        horizon, the state dimension or the estimators)."""
    parts = []
    for name, shape in shapes.items():
        a = np.asarray(stats[name], dtype=float)
        if a.shape != shape:
            raise ValidationError(
                f"sweep: a grid point gave {name} of shape {a.shape}, but the store holds {shape} (estimators, "
                "time, state/channel), set by the first grid point; grid values that change the horizon or the "
                "state dimension cannot share one store: run one sweep per value"
            )
        parts.append(a.ravel())
    return np.concatenate(parts)


def unpack(vec: np.ndarray, shapes: dict[str, tuple[int, ...]]) -> dict[str, np.ndarray]:
    """Split packed statistics ``(..., S)`` into named arrays ``(..., *shape)``."""
    out, i = {}, 0
    lead = vec.shape[:-1]
    for name, shape in shapes.items():
        size = int(np.prod(shape))
        out[name] = vec[..., i : i + size].reshape(lead + tuple(shape))
        i += size
    return out


def open_store(path: Path, spec: SweepSpec, estimators: list[str], n: int, m: int, steps: int):
    """Create the store, or reopen it to resume; refuse a store made by another sweep."""
    zarr = require("zarr", extra="sweep", feature="sweep stores")

    from .. import __version__

    P, B, E = int(np.prod(spec.grid_shape)) if spec.grid else 1, spec.blocks, len(estimators)
    if path.exists() or path.is_symlink():
        check_resumable(path, spec)
        return read_store(path, mode="a", name="--out")
    # built under a hidden name of its own (never a name a user's file could have), then renamed
    for old in path.parent.glob(f".{path.name}.creating-*"):
        shutil.rmtree(old, ignore_errors=True)
    import uuid

    tmp = path.with_name(f".{path.name}.creating-{os.getpid()}-{uuid.uuid4().hex[:8]}")
    g = zarr.open_group(str(tmp), mode="w")
    shapes = layout(E, steps, n, m)
    size = sum(int(np.prod(s)) for s in shapes.values())
    per_chunk = max(1, min(spec.chunk_blocks, B))
    g.create_array("stats", shape=(P, B, size), chunks=(1, per_chunk, size), dtype="f8", fill_value=0.0)
    g.create_array("done", shape=(P, B), chunks=(1, per_chunk), dtype="bool", fill_value=False)
    g.attrs.update(
        {
            "sweep": spec.text,
            "canonical": spec.canonical(),
            "package_version": __version__,
            "estimators": estimators,
            "grid": jsonable_grid(spec.grid),
            "n": n,
            "m": m,
            "steps": steps,
            "runs": spec.runs,
            "seed": spec.seed,
            "block_runs": spec.block_runs,
            "name": spec.name,
            "experiment": spec.experiment or "",
            "layout": {k: list(v) for k, v in shapes.items()},
        }
    )
    os.replace(tmp, path)  # the store appears whole or not at all
    return zarr.open_group(str(path), mode="a")


def _shapes(g) -> dict[str, tuple[int, ...]]:
    return {k: tuple(v) for k, v in g.attrs["layout"].items()}


def write_blocks(g, point: int, results: list[tuple[int, dict[str, np.ndarray]]]) -> None:
    """Write the statistics of some blocks of one grid point, then their ``done`` flags.

    ``results`` holds ``(block, stats)`` pairs; each run of consecutive block numbers is
    written with one slice assignment per array.
    """
    shapes = _shapes(g)
    results = sorted(results, key=lambda r: r[0])
    runs: list[list[tuple[int, dict]]] = []
    for b, stats in results:
        if runs and runs[-1][-1][0] == b - 1:
            runs[-1].append((b, stats))
        else:
            runs.append([(b, stats)])
    packed = [np.stack([pack(st, shapes) for _, st in run]) for run in runs]
    try:
        for run, vec in zip(runs, packed):
            g["stats"][point, run[0][0] : run[-1][0] + 1] = vec
        for run in runs:
            g["done"][point, run[0][0] : run[-1][0] + 1] = True
    except OSError:
        raise
    except Exception as exc:  # noqa: BLE001 - a partial chunk is read before it is written: damage shows here
        raise _damaged(_where(g), "a chunk cannot be updated", exc) from None


def reduce_store(g):
    """The xarray Dataset of a finished store: dims (grid axes..., estimator, time, state).

    Variables: ``rmse``, ``bias`` (…, estimator, time, state), ``nees`` (…, estimator, time),
    ``censored_fraction`` (…, time, channel), ``runs`` (grid axes).
    """
    xr = require("xarray", extra="sweep", feature="sweep results")

    done = _read(g, "done")
    if not done.all():
        raise ValidationError(
            f"sweep store: {int((~done).sum())} of {done.size} blocks are not finished; rerun the sweep to complete it"
        )
    attrs = dict(g.attrs)
    grid = attrs["grid"]
    shape = tuple(len(v) for v in grid.values())
    sums = unpack(_read(g, "stats").sum(axis=1), _shapes(g))  # blocks summed in order: (P, ...)
    total = sums["count"]  # (P,)
    if not (np.all(np.isfinite(total)) and np.all(total >= 1)):
        raise _damaged(_where(g), f"its run counts are {total[:4]}")
    s_err = sums["sum_err"] / total[:, None, None, None]
    s_sq = sums["sum_sq"] / total[:, None, None, None]
    s_nees = sums["sum_nees"] / total[:, None, None]
    cens = sums["censored"] / total[:, None, None]
    dims = list(grid)
    coords: dict[str, Any] = {}
    for key, values in grid.items():
        ax = scalar_axis(values)
        coords[key] = ax if ax is not None else np.arange(len(values))
    est = attrs["estimators"]
    coords.update({"estimator": est, "time": np.arange(1, attrs["steps"] + 1)})

    def grid_shaped(a, tail):
        return a.reshape(shape + a.shape[1:]) if dims else a.reshape(a.shape[1:])

    ds = xr.Dataset(
        {
            "rmse": (dims + ["estimator", "time", "state"], grid_shaped(np.sqrt(s_sq), 3)),
            "bias": (dims + ["estimator", "time", "state"], grid_shaped(s_err, 3)),
            "nees": (dims + ["estimator", "time"], grid_shaped(s_nees, 2)),
            "censored_fraction": (dims + ["time", "channel"], grid_shaped(cens, 2)),
            "runs": (dims, total.reshape(shape) if dims else total.reshape(())),
        },
        coords=coords,
        attrs={
            "sweep": attrs["sweep"],
            "package_version": attrs["package_version"],
            "grid": json.dumps(grid),
            "seed": attrs["seed"],
            "name": attrs["name"],
        },
    )
    return ds


def load_result(path: str | Path):
    """Open a finished sweep store and return its reduced :class:`xarray.Dataset`."""
    g = read_store(path, mode="r")
    try:
        return reduce_store(g)
    except ValidationError:
        raise
    except (KeyError, TypeError, ValueError, IndexError) as exc:  # attributes that disagree with the arrays
        raise _damaged(Path(path), "its attributes do not match its arrays", exc) from None
