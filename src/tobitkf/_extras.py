"""Optional dependencies: one helper that imports a module of an extra or says which extra to install.

The core (``pip install tobitkf``: numpy, scipy, numba, typer, rich) filters, simulates and runs
the command line. Features that need more import it through :func:`require` at the point of use,
so ``import tobitkf`` never needs an extra and a missing one is named when it is needed::

    cp = require("cvxpy", extra="lmi")   # MissingExtraError: ... pip install 'tobitkf[lmi]'

The extras (``pyproject.toml``): ``lmi`` (cvxpy, Clarabel, SCS), ``control`` (python-control),
``sweep`` (Dask, xarray, zarr), ``plot`` = ``report`` (matplotlib), ``all``.
"""

from __future__ import annotations

import importlib
from types import ModuleType

__all__ = ["EXTRAS", "MissingExtraError", "require", "extra_of", "missing_extra_message"]

#: what each extra provides (the import names of its packages) and what it is for
EXTRAS: dict[str, tuple[tuple[str, ...], str]] = {
    "lmi": (("cvxpy", "clarabel", "scs"), "the LMI design and certificates (H-infinity design, TKF stability)"),
    "control": (("control",), "LQR/LQE/LQG and transfer functions (python-control)"),
    "sweep": (("dask", "distributed", "xarray", "zarr"), "Monte Carlo sweeps and their stores"),
    "plot": (("matplotlib",), "figures"),
    "report": (("matplotlib",), "the figures of the reproduced experiments"),
}


class MissingExtraError(ImportError):
    """A feature needs a package of an optional extra that is not installed (or does not import).

    An :class:`ImportError`, so code that treats a missing package as such keeps working;
    ``extra`` and ``module`` name what is missing.
    """

    def __init__(self, message: str, *, module: str, extra: str) -> None:
        super().__init__(message, name=module)
        self.module = module
        self.extra = extra


def require(module: str, *, extra: str, feature: str | None = None) -> ModuleType:
    """Import ``module`` (e.g. ``"cvxpy"``, ``"matplotlib.pyplot"``) and return it.

    Raises :class:`MissingExtraError` naming ``extra`` and its install command when the module,
    or a package it needs, cannot be imported. ``feature`` (default: the extra's purpose) says
    what needed it.
    """
    if extra not in EXTRAS:
        raise ValueError(f"unknown extra {extra!r}; one of {sorted(EXTRAS)}")
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        what = feature or EXTRAS[extra][1]
        top = module.partition(".")[0]
        missing = exc.name or top
        if missing.partition(".")[0] == top:
            cause = f"{top} is not installed"
        else:  # the module is there but one of its own imports failed
            cause = f"{module} does not import ({exc})"
        raise MissingExtraError(
            f"the optional extra '{extra}' is needed for {what}: {cause}; install it with "
            f"pip install 'tobitkf[{extra}]' (or 'tobitkf[all]' for every feature)",
            module=top,
            extra=extra,
        ) from exc


def extra_of(module: str) -> str | None:
    """The extra that provides the import name ``module`` (or a submodule of it), or None."""
    top = module.partition(".")[0]
    for extra, (modules, _) in EXTRAS.items():
        if top in modules:
            return extra
    return None


def missing_extra_message(exc: ImportError) -> str | None:
    """The one-line message for an import error of an extra's package (None for any other): what
    :func:`require` says, also for an import that did not go through it."""
    if isinstance(exc, MissingExtraError):
        return str(exc)
    extra = extra_of(exc.name or "")
    if extra is None:
        return None
    return (
        f"the optional extra '{extra}' is needed: {exc.name} is not installed; install it with "
        f"pip install 'tobitkf[{extra}]' (or 'tobitkf[all]' for every feature)"
    )
