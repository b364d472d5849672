"""Monte Carlo sweeps: TOML sweep files, blocked seeding, Dask execution, zarr results.

``tobitkf sweep FILE.toml [--out DIR] [--scheduler local|processes|ADDRESS]`` runs a sweep;
``tobitkf plot RESULT`` draws it. See :mod:`tobitkf.sweep.spec` for the file format.
"""

from .spec import SweepFileError, SweepSpec, load_sweep, parse_sweep
from .store import load_result

__all__ = ["SweepFileError", "SweepSpec", "load_sweep", "parse_sweep", "run_sweep", "load_result", "plot_result"]


def run_sweep(*args, **kwargs):
    """See :func:`tobitkf.sweep.run.run_sweep`."""
    from .run import run_sweep as _run

    return _run(*args, **kwargs)


def plot_result(*args, **kwargs):
    """See :func:`tobitkf.sweep.plot.plot_result`."""
    from .plot import plot_result as _plot

    return _plot(*args, **kwargs)
