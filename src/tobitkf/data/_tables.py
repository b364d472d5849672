"""Where a record's cells come from: a CSV file, a pandas DataFrame or a mapping of columns, read into one
table of cells that remembers where each row came from (the file's line, the DataFrame's index), so that
every error of the readers (:mod:`tobitkf.data.readers`) can name the row."""

from __future__ import annotations

import csv
import gc
import io
import os
import time as _time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .._validation import ValidationError

__all__ = ["PROGRESS_BYTES"]

#: files at least this large get progress lines (bytes)
PROGRESS_BYTES = 8 * 2**20
_PROGRESS_EVERY = 2.0  # seconds between progress lines


@dataclass
class _Table:
    """Columns of cells (lists of str / objects, or numeric arrays) and where each row came from."""

    source: str
    columns: dict[str, Any]
    rows: Any  # a CSV's line numbers (int array), or one label per row ("row 3", "row 2020-01-01")
    index_times: np.ndarray | None = None
    announce: Callable[[str], None] | None = None  # progress lines of a large file

    def take(self, idx: np.ndarray) -> _Table:
        cols = {k: (v[idx] if isinstance(v, np.ndarray) else [v[i] for i in idx]) for k, v in self.columns.items()}
        times = None if self.index_times is None else self.index_times[idx]
        rows = self.rows[idx] if isinstance(self.rows, np.ndarray) else [self.rows[i] for i in idx]
        return _Table(self.source, cols, rows, times, self.announce)

    def label(self, i: int) -> str:
        return f"line {self.rows[i]}" if isinstance(self.rows, np.ndarray) else self.rows[i]

    def at(self, i: int, col: str) -> str:
        return f"{self.source} {self.label(i)}, column {col!r}"


def _decode(raw: bytes, path: Path, encoding: str, shown: str) -> str:
    try:
        return raw.decode(encoding)
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise ValidationError(
            f"{path}: line {line} is not {shown} text (byte 0x{raw[exc.start]:02x}); save the file as UTF-8 "
            "or give its encoding (e.g. encoding='latin-1')"
        ) from None
    except LookupError:
        raise ValidationError(f"encoding: unknown text encoding {encoding!r}") from None


def _read_csv(path: Path, encoding: str, progress: Callable[[str], None] | None) -> _Table:
    from .._validation import check_memory

    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ValidationError(f"{path}: cannot read the file ({exc.strerror or exc})") from None
    # the text, its cells as Python strings and the columns: about 40 bytes per byte of a file of short numbers
    check_memory(40 * len(raw), str(path), "reading the file")
    announce = progress if progress is not None and len(raw) >= PROGRESS_BYTES else None
    t0 = _time.perf_counter()
    if announce is not None:
        announce(f"reading {path} ({len(raw) / 2**20:.1f} MB)")
    enc = "utf-8-sig" if encoding.lower().replace("_", "-") in ("utf-8", "utf8") else encoding
    text = _decode(raw, path, enc, encoding)
    del raw
    collect = gc.isenabled()
    gc.disable()  # millions of small lists: the cycle collector would run over them again and again
    try:
        return _csv_records(path, text, announce, t0)
    finally:
        if collect:
            gc.enable()


def _csv_records(path: Path, text: str, announce: Callable[[str], None] | None, t0: float) -> _Table:
    last = t0
    reader = csv.reader(io.StringIO(text, newline=""))
    header: list[str] | None = None
    records: list[list[str]] = []
    lines: list[int] = []
    n = 0
    try:
        for rec in reader:
            if len(rec) != n or header is None:
                if not rec or all(not c.strip() for c in rec):
                    continue
                if header is None:
                    header = [c.strip() for c in rec]
                    n = len(header)
                    seen: dict[str, int] = {}
                    for j, name in enumerate(header):
                        if name and name in seen:
                            raise ValidationError(
                                f"{path}: the header names two columns {name!r} (columns {seen[name] + 1} and "
                                f"{j + 1}); rename one"
                            )
                        seen[name] = j
                    continue
                if len(rec) < n or any(c.strip() for c in rec[n:]):
                    raise ValidationError(
                        f"{path} line {reader.line_num}: {len(rec)} fields, the header has {n}"
                        + (" (a comma inside a number? quote such cells)" if len(rec) > n else "")
                    )
                rec = rec[:n]
            elif not rec[0] and not any(c.strip() for c in rec):
                continue
            records.append(rec)
            lines.append(reader.line_num)
            if announce is not None and len(lines) % 65536 == 0 and _time.perf_counter() - last >= _PROGRESS_EVERY:
                last = _time.perf_counter()
                announce(f"  {len(lines):,} rows read ({last - t0:.0f} s)")
    except csv.Error as exc:
        raise ValidationError(f"{path} line {reader.line_num}: not readable as CSV ({exc})") from None
    if header is None:
        raise ValidationError(f"{path}: the file is empty (a header row and one row per reading expected)")
    if not records:
        raise ValidationError(f"{path}: no data rows (a header row and one row per reading expected)")
    columns = [list(c) for c in zip(*records)]
    del records
    if announce is not None:
        announce(f"read {len(lines):,} rows of {path.name} in {_time.perf_counter() - t0:.1f} s; checking them")
    return _Table(str(path), dict(zip(header, columns)), np.array(lines), announce=announce)


def _is_dataframe(obj: Any) -> bool:
    return type(obj).__module__.partition(".")[0] == "pandas" and hasattr(obj, "columns") and hasattr(obj, "index")


def _from_dataframe(df: Any) -> _Table:
    import importlib

    pd = importlib.import_module("pandas")  # only reached for a DataFrame, so pandas is there (optional)

    if not isinstance(df, pd.DataFrame):
        raise ValidationError(f"source: expected a pandas DataFrame, got {type(df).__name__}")
    names = [str(c).strip() for c in df.columns]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValidationError(f"DataFrame: two columns are named {dup[0]!r}; rename one")
    if len(df) == 0:
        raise ValidationError("DataFrame: no rows")
    cols: dict[str, Any] = {}
    for name, (_, s) in zip(names, df.items()):
        kind = getattr(s.dtype, "kind", "O")
        if kind in "iuf":
            cols[name] = s.to_numpy(dtype=float, na_value=np.nan)
        elif kind == "b":
            cols[name] = np.asarray(s.to_numpy(), dtype=bool)
        else:
            cols[name] = s.astype(object).where(s.notna(), None).tolist()
    idx = df.index
    times = None
    if isinstance(idx, pd.DatetimeIndex):
        times = idx.tz_localize(None).to_numpy() if idx.tz is not None else idx.to_numpy()
        rows = [f"row {t}" for t in idx.astype(str)]
    else:
        rows = [f"row {i}" for i in idx.astype(str)]
    return _Table("DataFrame", cols, rows, times)


def _from_mapping(source: Mapping[str, Any]) -> _Table:
    cols: dict[str, Any] = {}
    n = None
    for k, v in source.items():
        name = str(k)
        if name in cols:
            raise ValidationError(f"source: two columns are named {name!r}")
        arr = np.asarray(v) if isinstance(v, np.ndarray) else None
        if arr is not None and arr.dtype.kind in "iuf":
            vals: Any = arr.astype(float).reshape(-1)
        elif arr is not None and arr.dtype.kind == "b":
            vals = arr.reshape(-1)
        elif isinstance(v, (str, bytes)) or not isinstance(v, (Sequence, np.ndarray)):
            raise ValidationError(f"source: column {name!r} must be a sequence of cells, got {type(v).__name__}")
        else:
            vals = list(v)
        if n is not None and len(vals) != n:
            raise ValidationError(f"source: column {name!r} has {len(vals)} cells, the first column {n}")
        n = len(vals)
        cols[name] = vals
    if not n:
        raise ValidationError("source: no rows")
    return _Table("table", cols, [f"row {i + 1}" for i in range(n)])


def _table(source: Any, encoding: str, progress: Callable[[str], None] | None) -> _Table:
    if isinstance(source, (str, os.PathLike)):
        return _read_csv(Path(source), encoding, progress)
    if _is_dataframe(source):
        return _from_dataframe(source)
    if isinstance(source, Mapping):
        return _from_mapping(source)
    raise ValidationError(
        f"source: expected a CSV path, a pandas DataFrame or a mapping of columns, got {type(source).__name__}"
    )
