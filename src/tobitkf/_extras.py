"""Optional dependencies: one helper that imports a module of an extra or says which extra to install.

The core (numpy, scipy, numba, typer, rich) filters, simulates and runs the command line.
Features that need more import it through :func:`require` at the point of use, so
``import tobitkf`` never needs an extra and a missing one is named when it is needed::

    cp = require("cvxpy", extra="lmi")   # MissingExtraError: ... pip install '/path/to/clone[lmi]'

The install command in the message follows how tobitkf was installed (:func:`install_command`):
from a local folder (a clone, ``pip install .`` or ``pip install -e .``) it names that folder, since
``pip install 'tobitkf[lmi]'`` would look for the package on PyPI, where it is not published.

The extras (``pyproject.toml``): ``lmi`` (cvxpy, Clarabel, SCS), ``control`` (python-control),
``sweep`` (Dask, xarray, zarr), ``plot`` = ``report`` (matplotlib), ``all``.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import json
import shlex
from pathlib import Path
from types import ModuleType
from typing import Any
from urllib.parse import unquote, urlparse
from urllib.request import url2pathname

__all__ = [
    "EXTRAS",
    "MissingExtraError",
    "require",
    "extra_of",
    "missing_extra_message",
    "install_command",
    "install_folder",
]

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
            f"the optional extra '{extra}' is needed for {what}: {cause}; {_install_advice(extra)}",
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
    return f"the optional extra '{extra}' is needed: {exc.name} is not installed; {_install_advice(extra)}"


def _install_advice(extra: str) -> str:
    return f"install it with {install_command(extra)} (or {install_command('all')} for every feature)"


def _local_folder(url: str) -> Path | None:
    """The local path of a ``file://`` URL (None for any other URL)."""
    parsed = urlparse(url)
    if parsed.scheme != "file":
        return None
    return Path(url2pathname(unquote(parsed.path)))


def _direct_url(dist: Any = None) -> dict[str, Any]:
    """The installed distribution's ``direct_url.json`` (PEP 610) as a dict ({} when there is none).
    ``dist`` defaults to ``importlib.metadata.distribution("tobitkf")``."""
    if dist is None:
        try:
            dist = importlib.metadata.distribution("tobitkf")
        except importlib.metadata.PackageNotFoundError:
            return {}
    try:
        raw = dist.read_text("direct_url.json")
        loaded = json.loads(raw) if raw else {}
    except (OSError, ValueError):
        return {}
    return loaded if isinstance(loaded, dict) else {}


def install_folder(dist: Any = None) -> Path | None:
    """The local folder tobitkf was installed from (a clone: ``pip install .`` or ``-e .``), or None
    (installed from an index, an archive or a URL, or not installed)."""
    info = _direct_url(dist)
    url = info.get("url")
    if not isinstance(url, str) or not isinstance(info.get("dir_info"), dict):
        return None
    return _local_folder(url)


def install_command(extra: str, dist: Any = None) -> str:
    """The command that installs ``extra`` for this installation of tobitkf.

    ``dist`` is the installed distribution (default: ``importlib.metadata.distribution("tobitkf")``).
    Its ``direct_url.json`` (PEP 610, written by pip for an install from a folder, an archive or
    a version-control URL) says where it came from:

    * a local folder (``pip install .``, a clone): ``pip install '/path/to/clone[extra]'``, with
      ``-e`` when the install is editable, so that the extra is added to the same installation;
    * a version-control URL: ``pip install 'tobitkf[extra] @ git+https://...'``;
    * a local archive or wheel: ``pip install '/path/to/file.tar.gz[extra]'``;
    * anything else (an index, or no metadata at all): ``pip install 'tobitkf[extra]'``.

    A folder that no longer exists is still named (it says where the package came from), with a
    note that the user's clone is what to install from.
    """
    info = _direct_url(dist)
    url = info.get("url")
    if not isinstance(url, str) or not url:
        return f"pip install {shlex.quote(f'tobitkf[{extra}]')}"
    vcs = info.get("vcs_info")
    if isinstance(vcs, dict) and isinstance(vcs.get("vcs"), str):
        spec = f"tobitkf[{extra}] @ {vcs['vcs']}+{url}"
        return f"pip install {shlex.quote(spec)}"
    folder = _local_folder(url)
    if folder is None:
        return f"pip install {shlex.quote(f'tobitkf[{extra}] @ {url}')}"
    dir_info = info.get("dir_info")
    editable = isinstance(dir_info, dict) and dir_info.get("editable") is True
    command = f"pip install {'-e ' if editable else ''}{shlex.quote(f'{folder}[{extra}]')}"
    if not folder.exists():
        command += f" (run from your clone of tobitkf: {folder}, where it was installed from, is gone)"
    return command
