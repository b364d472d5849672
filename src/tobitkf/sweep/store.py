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

from .._validation import ValidationError
from .spec import SweepSpec, jsonable_grid, scalar_axis

__all__ = ["open_store", "write_blocks", "reduce_store", "load_result", "layout", "pack", "unpack"]



def layout(estimators: int, steps: int, n: int, m: int) -> dict[str, tuple[int, ...]]:
    """Shapes of the statistics of one block, in packing order."""
    return {"sum_err": (estimators, steps, n), "sum_sq": (estimators, steps, n), "sum_nees": (estimators, steps),
            "censored": (steps, m), "count": ()}


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
                "state dimension cannot share one store: run one sweep per value")
        parts.append(a.ravel())
    return np.concatenate(parts)


def unpack(vec: np.ndarray, shapes: dict[str, tuple[int, ...]]) -> dict[str, np.ndarray]:
    """Split packed statistics ``(..., S)`` into named arrays ``(..., *shape)``."""
    out, i = {}, 0
    lead = vec.shape[:-1]
    for name, shape in shapes.items():
        size = int(np.prod(shape))
        out[name] = vec[..., i:i + size].reshape(lead + tuple(shape))
        i += size
    return out


def open_store(path: Path, spec: SweepSpec, estimators: list[str], n: int, m: int, steps: int):
    """Create the store, or reopen it to resume; refuse a store made by another sweep."""
    import zarr

    from .. import __version__

    P, B, E = int(np.prod(spec.grid_shape)) if spec.grid else 1, spec.blocks, len(estimators)
    if path.exists():
        g = zarr.open_group(str(path), mode="a")
        if g.attrs.get("canonical") != spec.canonical():
            raise ValidationError(f"--out: {path} holds a different sweep; choose another output directory "
                                  "or delete it to start over")
        return g
    tmp = path.with_name(path.name + ".creating")
    if tmp.exists():
        shutil.rmtree(tmp)
    g = zarr.open_group(str(tmp), mode="w")
    shapes = layout(E, steps, n, m)
    size = sum(int(np.prod(s)) for s in shapes.values())
    per_chunk = max(1, min(spec.chunk_blocks, B))
    g.create_array("stats", shape=(P, B, size), chunks=(1, per_chunk, size), dtype="f8", fill_value=0.0)
    g.create_array("done", shape=(P, B), chunks=(1, per_chunk), dtype="bool", fill_value=False)
    g.attrs.update({"sweep": spec.text, "canonical": spec.canonical(), "package_version": __version__,
                    "estimators": estimators, "grid": jsonable_grid(spec.grid), "n": n, "m": m, "steps": steps,
                    "runs": spec.runs, "seed": spec.seed, "block_runs": spec.block_runs, "name": spec.name,
                    "experiment": spec.experiment or "",
                    "layout": {k: list(v) for k, v in shapes.items()}})
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
    for run in runs:
        g["stats"][point, run[0][0]:run[-1][0] + 1] = np.stack([pack(st, shapes) for _, st in run])
    for run in runs:
        g["done"][point, run[0][0]:run[-1][0] + 1] = True


def reduce_store(g):
    """The xarray Dataset of a finished store: dims (grid axes..., estimator, time, state).

    Variables: ``rmse``, ``bias`` (…, estimator, time, state), ``nees`` (…, estimator, time),
    ``censored_fraction`` (…, time, channel), ``runs`` (grid axes).
    """
    import xarray as xr

    done = g["done"][:]
    if not done.all():
        raise ValidationError(f"sweep store: {int((~done).sum())} of {done.size} blocks are not finished; "
                              "rerun the sweep to complete it")
    attrs = dict(g.attrs)
    grid = attrs["grid"]
    shape = tuple(len(v) for v in grid.values())
    sums = unpack(g["stats"][:].sum(axis=1), _shapes(g))     # blocks summed in order: (P, ...)
    total = sums["count"]                                      # (P,)
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
        attrs={"sweep": attrs["sweep"], "package_version": attrs["package_version"],
               "grid": json.dumps(grid), "seed": attrs["seed"], "name": attrs["name"]},
    )
    return ds


def load_result(path: str | Path):
    """Open a finished sweep store and return its reduced :class:`xarray.Dataset`."""
    import zarr

    path = Path(path)
    if not (path / "zarr.json").exists():
        raise ValidationError(f"result: {path} is not a sweep store (no zarr.json)")
    return reduce_store(zarr.open_group(str(path), mode="r"))
