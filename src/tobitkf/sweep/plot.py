"""Figures from a stored sweep: RMSE over time and RMSE versus each swept parameter."""

from __future__ import annotations

from pathlib import Path

from .._extras import require
from ..plotting import new_figure, save

__all__ = ["plot_result"]

_MAX_POINT_COLUMNS = 6


def _safe(dim: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in dim)


def _as_tuple(value) -> tuple:
    return value if isinstance(value, tuple) else (value,)


def plot_result(path: str | Path, outdir: str | Path | None = None) -> list[Path]:
    """Draw ``rmse_over_time.png`` and ``rmse_vs_<param>.png`` for a finished sweep store.

    Returns the written paths (default folder: ``<store>/../<name>_plots``).
    """
    matplotlib = require("matplotlib", extra="plot", feature="tobitkf plot")

    matplotlib.use("Agg")
    from .._io import FIGURE_MARKERS, as_path, check_replaceable, check_writable_dir
    from .store import load_result

    path = as_path(path, "result")
    ds = load_result(path)
    outdir = as_path(outdir, "--out") if outdir is not None else path.parent / f"{path.stem}_plots"
    check_writable_dir(outdir, "--out")
    grid_dims = [d for d in ds["rmse"].dims if d not in ("estimator", "time", "state")]
    names = ["rmse_over_time.png"] + [f"rmse_vs_{_safe(d)}.png" for d in grid_dims]
    for name in names:  # a figure of the same name tobitkf did not draw is never replaced
        check_replaceable(outdir / name, "--out", FIGURE_MARKERS)
    stacked = ds["rmse"].stack(point=grid_dims) if grid_dims else ds["rmse"].expand_dims(point=[0])
    ests, n = list(ds["estimator"].values), ds.sizes["state"]
    points = stacked.sizes["point"]
    paths = []
    t = ds["time"].values
    if points <= _MAX_POINT_COLUMNS:
        # rows: state components; columns: grid points; curves: estimators (the comparison a
        # study is after), on a common y scale per row
        fig, axes = new_figure(n, points, width=max(5.0, 4.2 * points), height=2.8, sharey="row")
        for p in range(points):
            title = ", ".join(f"{d} = {v}" for d, v in zip(grid_dims, _as_tuple(stacked["point"].values[p])))
            for i in range(n):
                ax = axes[i, p]
                for est in ests:
                    ax.plot(t, stacked.sel(estimator=est).isel(point=p, state=i).values, lw=0.9, label=str(est))
                ax.set_title(f"RMSE of x{i + 1}" + (f" ({title})" if title else ""), fontsize=9)
                ax.set_xlabel("k")
                ax.legend(fontsize=7)
    else:
        # many grid points: one column per estimator, one curve per grid point
        fig, axes = new_figure(n, len(ests), width=4.2 * len(ests), height=2.8, sharey="row")
        for j, est in enumerate(ests):
            for i in range(n):
                ax = axes[i, j]
                for p in range(points):
                    ax.plot(t, stacked.sel(estimator=est).isel(point=p, state=i).values, lw=0.7)
                ax.set_title(f"{est}: RMSE of x{i + 1}, {points} grid points", fontsize=9)
                ax.set_xlabel("k")
    paths.append(save(fig, outdir, "rmse_over_time.png"))
    avg = ds["rmse"].mean("time")
    for dim in grid_dims:
        others = [d for d in grid_dims if d != dim]
        fig, axes = new_figure(1, n, width=4.5 * n, height=3.2)
        for i in range(n):
            ax = axes[0, i]
            for est in ests:
                curve = avg.sel(estimator=est).isel(state=i)
                if others:
                    curve = curve.mean(others)
                ax.plot(ds[dim].values, curve.values, "o-", label=est)
            ax.set_xlabel(dim)
            ax.set_ylabel(f"time-averaged RMSE of x{i + 1}")
            ax.legend(fontsize=7)
        paths.append(save(fig, outdir, f"rmse_vs_{_safe(dim)}.png"))
    return paths
