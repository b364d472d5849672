"""The sweep results store: per-block sufficient statistics in zarr, reduced to an xarray Dataset.

Layout of ``<out>/<name>.zarr`` (zarr v3 group):

=================  =====================================  ===================================
array              shape                                  meaning
=================  =====================================  ===================================
``sum_err``        (points, blocks, estimators, T, n)     Σ over the block's runs of x̂ - x
``sum_sq``         (points, blocks, estimators, T, n)     Σ (x̂ - x)²
``sum_nees``       (points, blocks, estimators, T)        Σ eᵀP⁻¹e
``censored``       (points, blocks, T, m)                 number of censored readings
``count``          (points, blocks)                       runs in the block
``done``           (points, blocks)                       block finished (written last)
=================  =====================================  ===================================

Every block is one zarr chunk, written by the driver as the block's result arrives; the
``done`` flag is written after the data, so an interrupted sweep never counts a
half-written block, and a rerun of the same command computes only the missing blocks.
Reduction sums the blocks in block order, so the result does not depend on which worker
computed which block or how blocks were grouped into tasks. The group's attributes hold
the sweep file, its canonical form and the package version.
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

__all__ = ["open_store", "write_block", "reduce_store", "load_result"]

_ARRAYS = ("sum_err", "sum_sq", "sum_nees", "censored", "count", "done")


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
    shapes = {"sum_err": (P, B, E, steps, n), "sum_sq": (P, B, E, steps, n), "sum_nees": (P, B, E, steps),
              "censored": (P, B, steps, m), "count": (P, B), "done": (P, B)}
    for name, shape in shapes.items():
        dtype = "bool" if name == "done" else ("i8" if name == "count" else "f8")
        fill = False if name == "done" else 0
        g.create_array(name, shape=shape, chunks=(1, 1) + shape[2:], dtype=dtype, fill_value=fill)
    g.attrs.update({"sweep": spec.text, "canonical": spec.canonical(), "package_version": __version__,
                    "estimators": estimators, "grid": jsonable_grid(spec.grid), "n": n, "m": m, "steps": steps,
                    "runs": spec.runs, "seed": spec.seed, "block_runs": spec.block_runs, "name": spec.name,
                    "experiment": spec.experiment or ""})
    os.replace(tmp, path)  # the store appears whole or not at all
    return zarr.open_group(str(path), mode="a")


def write_block(g, point: int, block: int, stats: dict[str, np.ndarray]) -> None:
    """Write one block's statistics, then its ``done`` flag."""
    for name in ("sum_err", "sum_sq", "sum_nees", "censored", "count"):
        g[name][point, block] = stats[name]
    g["done"][point, block] = True


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
    count = g["count"][:].astype(float)                      # (P, B)
    total = count.sum(axis=1)                                 # blocks summed in order
    s_err = g["sum_err"][:].sum(axis=1) / total[:, None, None, None]
    s_sq = g["sum_sq"][:].sum(axis=1) / total[:, None, None, None]
    s_nees = g["sum_nees"][:].sum(axis=1) / total[:, None, None]
    cens = g["censored"][:].sum(axis=1) / total[:, None, None]
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
