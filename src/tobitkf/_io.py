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

__all__ = [
    "atomic_write_text",
    "atomic_write_json",
    "atomic_savefig",
    "to_jsonable",
    "safe_child",
    "staging_dir",
    "replace_dir",
    "check_writable_dir",
    "check_replaceable",
    "as_path",
]

_NAME_MAX = 255  # bytes of one path component on the usual file systems (ext4, xfs, APFS, NTFS)
FIGURE_SOFTWARE = "tobitkf (matplotlib)"
# figures tobitkf wrote: its own marker, or (written before the marker) matplotlib's default Software chunk
FIGURE_MARKERS = (b"Software\x00tobitkf", b"Software\x00Matplotlib version")


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
    if path.suffix.lower() == ".png":  # the marker check_replaceable looks for (PNG tEXt "Software")
        kwargs.setdefault("metadata", {"Software": FIGURE_SOFTWARE})
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


def as_path(value: Any, name: str) -> Path:
    """A path from a ``str`` or ``os.PathLike``; anything else, or a NUL byte in it, is refused by name."""
    from ._validation import ValidationError

    if isinstance(value, bool) or not isinstance(value, (str, os.PathLike)):
        raise ValidationError(f"{name}: expected a path (str or os.PathLike), got {type(value).__name__}")
    path = Path(value)
    if "\x00" in str(path):
        raise ValidationError(f"{name}: a path cannot contain a NUL character, got {str(path)!r:.80}")
    return path


def check_writable_dir(path: str | os.PathLike, name: str) -> Path:
    """Refuse a folder that cannot be used for output, before any work is done.

    Refused: an existing file (or a broken link) at ``path``; a path below a file (``a_file/sub``,
    which would fail with NotADirectoryError only when the first file is written); an existing
    ancestor without write permission; a component longer than the file system allows.

    Raises
    ------
    ValidationError
        Naming ``name`` (e.g. ``--out``), the path and the reason.
    """
    from ._validation import ValidationError

    path = as_path(path, name)
    for part in path.parts:
        if len(os.fsencode(part)) > _NAME_MAX:
            raise ValidationError(
                f"{name}: the folder name {part[:40]!r}... is {len(os.fsencode(part))} bytes long, "
                f"more than the {_NAME_MAX} a file system allows"
            )
    if path.exists() or path.is_symlink():
        if not path.is_dir():
            raise ValidationError(f"{name}: expected a folder, got the file {path}")
        target = path
    else:
        target = path.parent
        while not (target.exists() or target.is_symlink()) and target != target.parent:
            target = target.parent
        if not target.is_dir():
            raise ValidationError(f"{name}: {path} cannot be created: {target} is a file, not a folder")
    if not os.access(target, os.W_OK | os.X_OK):
        raise ValidationError(f"{name}: no permission to write in {target}")
    return path


def check_replaceable(path: str | os.PathLike, name: str, markers: tuple[bytes, ...]) -> None:
    """Refuse to replace a file that tobitkf did not write.

    ``path`` may be missing (nothing to lose) or a regular file whose first or last 64 KiB hold one
    of ``markers`` (the marker tobitkf writes into its own files). Anything else (a file of the
    user's, a folder, a device) is refused, so an atomic rename never destroys it.

    Raises
    ------
    ValidationError
        Naming ``name``, the path and what to do.
    """
    from ._validation import ValidationError

    path = Path(path)
    if not (path.exists() or path.is_symlink()):
        return
    if path.is_dir():
        raise ValidationError(f"{name}: {path} is a folder; expected a file written by tobitkf (move it away)")
    if not path.is_file():
        raise ValidationError(f"{name}: {path} is not a regular file; refusing to replace it (move it away)")
    try:
        with open(path, "rb") as fh:
            head = fh.read(65536)
            if len(head) == 65536:
                fh.seek(max(fh.seek(0, os.SEEK_END) - 65536, 65536))
                head += fh.read(65536)
    except OSError as exc:
        raise ValidationError(f"{name}: cannot read {path} to check that tobitkf wrote it ({exc.strerror})") from None
    if not any(m in head for m in markers):
        raise ValidationError(
            f"{name}: {path} was not written by tobitkf; refusing to replace it (move it away or choose another folder)"
        )
