"""Atomic result files: write to a temporary file in the same folder, then rename.

An interrupted run therefore never leaves a half-written metrics.json or PNG;
the previous complete file (if any) stays in place until the new one is whole.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["atomic_write_text", "atomic_write_json", "atomic_savefig", "to_jsonable", "safe_child", "staging_dir",
           "replace_dir"]


def to_jsonable(obj: Any) -> Any:
    """Convert numpy arrays/scalars (and nested containers) to JSON types; non-finite floats to strings."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        f = float(obj)
        return f if math.isfinite(f) else ("nan" if math.isnan(f) else ("inf" if f > 0 else "-inf"))
    return obj


def _default_mode() -> int:
    """0o666 minus the umask: the mode an ordinary open() would give (mkstemp gives 0o600)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``path`` atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, _default_mode())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def atomic_write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write ``obj`` as indented JSON atomically (numpy types converted)."""
    return atomic_write_text(path, json.dumps(to_jsonable(obj), indent=1, sort_keys=False) + "\n")


def atomic_savefig(fig, path: str | os.PathLike, **kwargs) -> Path:
    """Save a matplotlib figure atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        fig.savefig(tmp, **kwargs)
        os.chmod(tmp, _default_mode())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def safe_child(root: str | os.PathLike, name: str) -> Path:
    """``root / name`` resolved, refusing names that escape ``root``."""
    from ._validation import ValidationError

    root_p = Path(root).resolve()
    child = (root_p / name).resolve()
    if root_p != child and root_p not in child.parents:
        raise ValidationError(f"output path: {name!r} would leave the output directory {root_p}")
    return child


def staging_dir(final: str | os.PathLike) -> Path:
    """A fresh hidden folder beside ``final`` to build a complete result in (see :func:`replace_dir`).

    Leftovers of earlier interrupted runs (``.NAME.partial-*``) are removed, and a result that
    was moved aside by an interrupted :func:`replace_dir` (``.NAME.old-*`` while ``final``
    is missing) is put back first, so the previous complete result is never lost.
    """
    import shutil

    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    for old in sorted(final.parent.glob(f".{final.name}.old-*")):
        if not final.exists():
            os.replace(old, final)
        else:
            shutil.rmtree(old, ignore_errors=True)
    for part in final.parent.glob(f".{final.name}.partial-*"):
        shutil.rmtree(part, ignore_errors=True)
    import uuid

    stage = final.parent / f".{final.name}.partial-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    stage.mkdir()  # (not mkdtemp: its 0700 mode would become the result folder's)
    return stage


def replace_dir(stage: str | os.PathLike, final: str | os.PathLike) -> Path:
    """Put the complete folder ``stage`` in place of ``final`` with renames only.

    The old ``final`` is first renamed aside, then ``stage`` renamed to ``final``, then the
    old one deleted; an interruption between the two renames is repaired by the next
    :func:`staging_dir` call.
    """
    import shutil

    stage, final = Path(stage), Path(final)
    aside = None
    if final.exists():
        aside = final.with_name(f".{final.name}.old-{os.getpid()}")
        os.replace(final, aside)
    os.replace(stage, final)
    if aside is not None:
        shutil.rmtree(aside, ignore_errors=True)
    return final
