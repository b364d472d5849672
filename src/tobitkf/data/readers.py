r"""Readers: censored records in the formats users have, as :class:`CensoredSeries` (one series) or a
:class:`CensoredPanel` (many subjects in one long table).

One function per shape of data, one argument per column; every format ends in the same object::

    s = read_censored("river.csv", y="conc", time="date")                    # "<0.05" / ">750000" strings
    s = read_censored("lab.csv", y="value", censored="flag", lower="dl")      # a value + flag + limit triple
    s = read_censored("egret.csv", time="Date")                               # EGRET's ConcLow / ConcHigh
    s = read_censored("pk.csv", time="TIME")                                  # NONMEM / nlmixr2 DV, CENS, LIMIT
    s = read_censored(df, y="conc")                                           # a pandas DataFrame
    p = read_censored_panel("hiv.csv", id="patient", time="days", y="rna", censored="cens",
                            flag_codes={0: "none", 1: "left", 2: "right"}, duplicates="drop")

The source is a path to a CSV file (UTF-8, a byte-order mark allowed; a header row), a pandas
``DataFrame`` (a ``DatetimeIndex`` gives the times; pandas is imported only when one is passed) or a
mapping of column name to a sequence of cells.

Formats (``format=``; ``"auto"`` picks one when it is unambiguous: ``ConcLow``/``ConcHigh`` columns are
``"interval"``, ``DV``/``CENS`` columns ``"nonmem"``, a ``censored`` column ``"flag"``, otherwise
``"strings"``):

``"strings"``
    ``y`` holds numbers, ``"<L"`` (left-censored at L) or ``">U"`` (right-censored at U), optionally with
    a unit (``"0.05 mg/L"``: every cell of a column must carry the same unit; ``.units`` keeps it).
``"flag"``
    ``y`` and a censoring flag ``censored`` (``1``/``0``, ``true``/``false``, ``yes``/``no``, or ``<``/``>``,
    ``left``/``right``; numeric side codes through ``flag_codes``, e.g. ``{1: "left", 2: "right"}``), with
    limits ``lower``/``upper`` (a column name or a number). Without a limit column, a censored reading holds
    its limit (the usual convention). Without a flag column, the limit rule decides: a reading at a limit is
    censored there.
``"interval"``
    EGRET's interval columns ``low``/``high`` (default ``"ConcLow"``/``"ConcHigh"``): equal = an exact
    reading; ``low`` empty (or 0) and ``high`` = L: left-censored at L; ``high`` empty and ``low`` = U:
    right-censored at U; both empty: missing. A column ``Uncen`` (1 = uncensored), if present, must agree.
``"nonmem"``
    NONMEM / nlmixr2 / Monolix columns ``DV``, ``CENS`` (0 exact, 1 left-censored at DV, -1 right-censored
    at DV) and optionally ``LIMIT`` (the other end of the censoring interval: only an empty or infinite
    LIMIT is supported, i.e. the M3 likelihood); ``MDV`` = 1 marks a missing reading and rows with
    ``EVID`` not 0 (dose records) are skipped.

Blank limits follow one rule, here, in :func:`tobitkf.fit` and in ``tobitkf fit``: a limit that was not
recorded means *no limit* on that reading: the reader writes ``-inf`` (``lower``) or ``+inf`` (``upper``), which is
what :func:`tobitkf.fit` and the filters take for "no limit" (they refuse NaN limits). This is harmless
for an uncensored or missing reading, whose likelihood does not use its limit; a *censored* reading
with a blank limit cell is an error naming the row and the column.

**Rows refused**, each with an error naming the row (the file's line, or the DataFrame's index) and the
column: text that is not a number (``"ND"``, ``"true"``), a ``"<"`` without a number, infinite
readings, mixed units in one column, an uncensored reading outside its own limits, a censored reading
that differs from its limit, ``lower >= upper``, a blank or repeated time, times that go backwards
(``duplicates="drop"`` drops a row that repeats the previous row at the same time with the same
reading, flag and limits; a conflicting repeat is still refused), two columns with the same name.

Times are kept: ``times`` is a ``datetime64`` array for dates (``"2001-03-01"``, ``"1998-10"``,
``"2001-03-01T12:00"``) or a float array for numbers; ``time`` keeps the labels as written.
"""

from __future__ import annotations

import csv
import gc
import io
import math
import os
import re
import time as _time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .._validation import ValidationError
from ._series import CensoredSeries

__all__ = ["CensoredRecord", "CensoredPanel", "read_censored", "read_censored_panel", "write_censored", "FORMATS"]

FORMATS = ("auto", "strings", "flag", "interval", "nonmem")
_MISSING = frozenset({"", "na", "nan", "n/a", "null", "none", "."})
_TRUE = frozenset({"1", "1.0", "true", "t", "yes", "y"})
_FALSE = frozenset({"0", "0.0", "false", "f", "no", "n"})
_SIDES = {"<": -1, "left": -1, "below": -1, ">": 1, "right": 1, "above": 1, "none": 0}
_NUMBER = re.compile(
    r"^\s*(?P<sign><=?|>=?)?\s*(?P<num>[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|[-+]?inf(?:inity)?)?"
    r"\s*(?P<unit>[A-Za-z\u00b5\u03bc%][^,;]*?)?\s*$",
    re.IGNORECASE,
)
#: files at least this large get progress lines (bytes)
PROGRESS_BYTES = 8 * 2**20
_PROGRESS_EVERY = 2.0  # seconds between progress lines


@dataclass(frozen=True)
class CensoredRecord(CensoredSeries):
    r"""A :class:`CensoredSeries` read from a user's record, with its sample times and units.

    Besides the attributes of :class:`CensoredSeries`:

    Attributes
    ----------
    times : (T,) ndarray of datetime64 or float, or None
        The sample times, increasing (None when the record has no time column or index).
    units : str
        The unit written with the readings (``"mg/L"``), or ``""``.
    """

    times: np.ndarray | None = None
    units: str = ""

    @property
    def side(self) -> np.ndarray:
        """(T,) int8: -1 left-censored (at ``lower``), +1 right-censored (at ``upper``), 0 otherwise."""
        out = np.zeros(self.steps, dtype=np.int8)
        with np.errstate(invalid="ignore"):
            out[self.censored & (self.y <= self.lower)] = -1
            out[self.censored & (self.y >= self.upper)] = 1
        return out


@dataclass(frozen=True)
class CensoredPanel:
    r"""Many censored series (subjects) read from one long table with an id column.

    Attributes
    ----------
    name : str
    series : dict of str to CensoredRecord
        One record per subject, in the order of first appearance in the table.
    id_column : str
        The column that named the subjects.
    """

    name: str
    series: dict[str, CensoredRecord] = field(default_factory=dict)
    id_column: str = ""

    @property
    def ids(self) -> list[str]:
        """The subjects' ids, in table order."""
        return list(self.series)

    @property
    def steps(self) -> np.ndarray:
        """(S,) int: the number of readings of each subject."""
        return np.array([s.steps for s in self.series.values()], dtype=int)

    def __len__(self) -> int:
        return len(self.series)

    def __iter__(self) -> Iterator[str]:
        return iter(self.series)

    def __getitem__(self, key: str) -> CensoredRecord:
        return self.series[key]


# --------------------------------------------------------------------------- tables


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


# --------------------------------------------------------------------------- cells


def _column(t: _Table, name: Any, what: str) -> Any:
    if not isinstance(name, str):
        raise ValidationError(f"{what}: expected a column name (str), got {name!r}")
    if name not in t.columns:
        raise ValidationError(
            f"{what}: {t.source} has no column {name!r} (columns: {', '.join(repr(c) for c in t.columns)})"
        )
    return t.columns[name]


def _is_missing(c: Any) -> bool:
    if c is None:
        return True
    if isinstance(c, str):
        return c.strip().lower() in _MISSING
    return isinstance(c, (float, np.floating)) and math.isnan(c)


def _fast_numbers(cells: list[Any]) -> np.ndarray | None:
    """Plain numeric text converted at once (a large file of numbers), or None to parse cell by cell."""
    if not _all_text(cells):
        return None
    try:
        return np.fromiter(map(float, cells), dtype=float, count=len(cells))
    except ValueError:
        return None


def _all_text(cells: Sequence[Any]) -> bool:
    """Every cell is text without an underscore (float() would read "1_000" as 1000)."""
    return set(map(type, cells)) == {str} and "_" not in "".join(cells)


def _unsigned(cell: str) -> str:
    b = cell.strip()
    if b[:1] in ("<", ">"):
        b = b[2:] if b[1:2] == "=" else b[1:]
        return b.strip() or "?"  # a sign without a number: let the cell-by-cell parser say so
    return "nan" if b.lower() in _MISSING else b


def _fast_text(cells: list[Any], signs: bool) -> tuple[np.ndarray, np.ndarray] | None:
    """Numbers, blanks and (``signs``) "<L" / ">U" cells without units converted at once, or None."""
    if not _all_text(cells):
        return None
    sign = np.zeros(len(cells), dtype=np.int8)
    try:
        return np.fromiter(map(float, cells), dtype=float, count=len(cells)), sign
    except ValueError:
        pass
    lead = [c.lstrip()[:1] for c in cells]
    first = set(lead)
    if "<" in first or ">" in first:
        if not signs:
            return None
        sign = np.array([-1 if c == "<" else 1 if c == ">" else 0 for c in lead], dtype=np.int8)
    try:
        vals = np.array([_unsigned(c) for c in cells], dtype=float)
    except ValueError:
        return None
    if (np.isnan(vals) & (sign != 0)).any():
        return None
    return vals, sign


def _parse_cells(t: _Table, name: str, cells: list[Any], signs: bool) -> tuple[np.ndarray, np.ndarray, str]:
    n = len(cells)
    vals = np.full(n, np.nan)
    sign = np.zeros(n, dtype=np.int8)
    first: dict[str, int] = {}  # unit -> first row with it ("" = no unit)
    for i, c in enumerate(cells):
        if _is_missing(c):
            continue
        if isinstance(c, (bool, np.bool_)):
            raise ValidationError(f"{t.at(i, name)}: {c!r} is a boolean, not a number")
        if isinstance(c, (int, float, np.integer, np.floating)):
            vals[i] = float(c)
            first.setdefault("", i)
        elif not isinstance(c, str):
            raise ValidationError(f"{t.at(i, name)}: expected a number, got {type(c).__name__} {c!r:.40}")
        else:
            m = _NUMBER.match(c)
            if m is None or (m.group("num") is None and m.group("sign") is None):
                raise ValidationError(f"{t.at(i, name)}: expected a number, got {c.strip()!r:.40}")
            if m.group("num") is None:
                raise ValidationError(
                    f"{t.at(i, name)}: {c.strip()!r:.40} has {m.group('sign')!r} but no number; write the limit, "
                    f"e.g. '{m.group('sign')[0]}0.05'"
                )
            if m.group("sign"):
                if not signs:
                    raise ValidationError(
                        f"{t.at(i, name)}: expected a number, got {c.strip()!r:.40} ('<' and '>' only in readings)"
                    )
                sign[i] = -1 if m.group("sign")[0] == "<" else 1
            vals[i] = float(m.group("num"))
            first.setdefault((m.group("unit") or "").strip(), i)
        if len(first) > 1:
            here = next(u for u, j in first.items() if j == i)
            other, j = next((u, j) for u, j in first.items() if u != here)
            raise ValidationError(
                f"{t.at(i, name)}: mixed units in one column: {here or 'no unit'!r} here, {other or 'no unit'!r} "
                f"at {t.label(j)}; convert the column to one unit"
            )
    return vals, sign, next(iter(first), "")


def _numbers(
    t: _Table, name: str, what: str, *, signs: bool = False, allow_inf: bool = False
) -> tuple[np.ndarray, np.ndarray, str]:
    """A column as numbers: ``(values (NaN = missing), sign (-1 "<", +1 ">", 0 none), unit)``.

    Raises ValidationError naming the row and the column of the first cell that is not a number.
    """
    cells = _column(t, name, what)
    if isinstance(cells, np.ndarray):
        if cells.dtype.kind == "b":
            raise ValidationError(f"{t.at(0, name)}: booleans (True/False) are not numbers")
        vals, sign, unit = np.asarray(cells, dtype=float), np.zeros(len(cells), dtype=np.int8), ""
    else:
        fast = _fast_text(cells, signs)
        if fast is not None:
            vals, sign, unit = fast[0], fast[1], ""
        else:
            vals, sign, unit = _parse_cells(t, name, cells, signs)
    bad = np.isinf(vals)
    if bad.any() and not allow_inf:
        i = int(np.argmax(bad))
        raise ValidationError(f"{t.at(i, name)}: {vals[i]} is not a finite number")
    return vals, sign, unit


def _flags(t: _Table, name: str, codes: Mapping[Any, str] | None) -> np.ndarray:
    """A flag column as sides: 0 uncensored, -1 left, +1 right, 2 censored on the side the limits tell."""
    cells = _column(t, name, "censored")
    table: dict[str, int] = {}
    for k, v in (codes or {}).items():
        if v not in ("left", "right", "none", "censored"):
            raise ValidationError(f"flag_codes: {k!r} maps to {v!r}; expected 'left', 'right', 'censored' or 'none'")
        code = {"left": -1, "right": 1, "none": 0, "censored": 2}[v]
        key = str(k).strip().lower()
        table[key] = code
        try:  # 1, 1.0 and "1" are one code
            f = float(key)
            table[repr(f)] = table[str(int(f)) if f.is_integer() else key] = code
        except ValueError:
            pass
    if isinstance(cells, np.ndarray) and cells.dtype.kind == "b":
        return np.where(cells, 2, 0).astype(np.int8)
    vals = cells.tolist() if isinstance(cells, np.ndarray) else list(cells)

    def side(c: Any) -> int | None:
        if _is_missing(c):
            return 0
        if isinstance(c, (bool, np.bool_)):
            return 2 if c else 0
        s = str(c).strip().lower()
        if isinstance(c, (float, np.floating)) and float(c).is_integer():
            s = str(int(c))
        for known in (table, _SIDES):
            if s in known:
                return known[s]
        return 2 if s in _TRUE else 0 if s in _FALSE else None

    if any(type(c) is bool for c in vals):  # True == 1 as dict keys: decide cell by cell
        sides = [side(c) for c in vals]
    else:  # each distinct cell once (a large file has a handful)
        distinct = dict.fromkeys(vals)
        for c in distinct:
            distinct[c] = side(c)
        sides = [distinct[c] for c in vals]
    if None in sides:
        i = sides.index(None)
        s = str(vals[i]).strip()
        raise ValidationError(
            f"{t.at(i, name)}: expected a censoring flag (1/0, true/false, '<'/'>', left/right), got {vals[i]!r:.40}"
            + ("; give flag_codes for numeric side codes" if s.lstrip("-").replace(".", "").isdigit() else "")
        )
    return np.array(sides, dtype=np.int8)


def _find(t: _Table, given: str | None, default: str) -> str | None:
    """The column ``given``, or the one named ``default`` in any letter case (None if absent)."""
    if given is not None:
        _column(t, given, default.lower())
        return given
    hits = [c for c in t.columns if c.lower() == default.lower()]
    return hits[0] if len(hits) == 1 else None


def _limit(t: _Table, spec: Any, what: str) -> tuple[np.ndarray | None, str, str | None]:
    """``lower``/``upper`` given as a column name or a number: (values (NaN = blank) or None, unit, column)."""
    if spec is None:
        return None, "", None
    if isinstance(spec, str):
        vals, _, unit = _numbers(t, spec, what, allow_inf=True)
        return vals, unit, spec
    if isinstance(spec, (bool, np.bool_)) or not isinstance(spec, (int, float, np.integer, np.floating)):
        raise ValidationError(f"{what}: expected a column name or a number, got {spec!r}")
    if math.isnan(spec):
        raise ValidationError(f"{what}: expected a column name or a number, got NaN")
    return np.full(len(t.rows), float(spec)), "", None


def _first(t: _Table, bad: np.ndarray, col: str, message: str) -> None:
    if bad.any():
        i = int(np.argmax(bad))
        raise ValidationError(f"{t.at(i, col)}: {message}")


def _tol(x: np.ndarray) -> np.ndarray:
    return 1e-12 * np.maximum(1.0, np.abs(np.where(np.isfinite(x), x, 0.0)))


def _strings_or_flag(t: _Table, a: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, str]:
    ycol = a["y"]
    if ycol is None:
        raise ValidationError(
            f'y: name the column of the readings (y = "<column>"; columns of {t.source}: '
            f"{', '.join(repr(c) for c in t.columns)}), or use a layout with its own columns "
            "(ConcLow/ConcHigh, DV/CENS)"
        )
    v, sign, unit = _numbers(t, ycol, "y", signs=True)
    n = v.size
    L, lunit, lcol = _limit(t, a["lower"], "lower")
    U, uunit, ucol = _limit(t, a["upper"], "upper")
    for u, col in ((lunit, lcol), (uunit, ucol)):
        if unit and u and u != unit:
            raise ValidationError(f"{col}: the limits are in {u!r}, the readings ({ycol!r}) in {unit!r}; use one unit")
    unit = unit or lunit or uunit
    flag = None if a["censored"] is None else _flags(t, a["censored"], a["flag_codes"])
    side = sign.astype(np.int8)
    if flag is not None:
        fcol = a["censored"]
        _first(
            t, (sign != 0) & (flag == 0), fcol, "the reading is written with '<' or '>' but the flag says uncensored"
        )
        _first(
            t,
            (sign != 0) & (np.abs(flag) == 1) & (flag != sign),
            fcol,
            "the flag's side contradicts the '<'/'>' reading",
        )
        side = np.where(sign != 0, sign, flag).astype(np.int8)
    unknown = side == 2
    if unknown.any():  # censored, the side from the limits given
        if L is not None and U is None:
            side[unknown] = -1
        elif U is not None and L is None:
            side[unknown] = 1
        elif L is not None and U is not None:
            with np.errstate(invalid="ignore"):
                at_lo = np.abs(v - L) <= _tol(L)
                at_hi = np.abs(v - U) <= _tol(U)
            side[unknown & at_lo] = -1
            side[unknown & ~at_lo & at_hi] = 1
            _first(t, side == 2, a["censored"], "flagged censored, but the reading is at neither of its limits")
        else:
            _first(
                t,
                unknown,
                a["censored"],
                "flagged censored, but on which side? give the limit (lower= or upper=) or flag_codes "
                "(e.g. {1: 'left', 2: 'right'})",
            )
    lo = np.full(n, -np.inf) if L is None else np.where(np.isnan(L), -np.inf, L)
    hi = np.full(n, np.inf) if U is None else np.where(np.isnan(U), np.inf, U)
    y = v.copy()
    for s, lim, given, col in ((-1, lo, L, lcol), (1, hi, U, ucol)):
        rows = side == s
        if not rows.any():
            continue
        from_sign = rows & (sign == s)
        if given is None:  # the reading (or the "<L" cell) holds its limit
            _first(t, rows & np.isnan(v), ycol, "a censored reading without its limit (the cell is blank)")
            lim[rows] = v[rows]
        else:
            blank = rows & np.isnan(given)
            if col is not None:
                _first(t, blank & ~from_sign, col, "a censored reading needs its limit, and this cell is blank")
            with np.errstate(invalid="ignore"):
                clash = from_sign & ~blank & (np.abs(given - v) > _tol(given))
            _first(t, clash, col or ycol, f"the limit contradicts the reading's '{'<' if s < 0 else '>'}' value")
            with np.errstate(invalid="ignore"):
                off = rows & ~from_sign & ~np.isnan(v) & (np.abs(given - v) > _tol(given))
            _first(
                t,
                off,
                ycol,
                "a censored reading differs from its limit; write the limit as the reading (or leave it blank)",
            )
            lim[rows] = np.where(from_sign, v, given)[rows]
        y[rows] = lim[rows]
    if flag is None:  # the limit rule on the rest
        with np.errstate(invalid="ignore"):
            at_lo = (side == 0) & np.isfinite(lo) & (y <= lo + _tol(lo))
            at_hi = (side == 0) & np.isfinite(hi) & (y >= hi - _tol(hi))
        side[at_lo] = -1
        side[at_hi & ~at_lo] = 1
    with np.errstate(invalid="ignore"):
        below = (side == 0) & (y < lo - _tol(lo))
        above = (side == 0) & (y > hi + _tol(hi))
    _first(t, below, ycol, "an uncensored reading below its lower limit (a reading below the limit is censored)")
    _first(t, above, ycol, "an uncensored reading above its upper limit (a reading above the limit is censored)")
    _first(t, lo >= hi, lcol or ucol or ycol, "the lower limit is not below the upper limit")
    return y, side, lo, hi, unit


def _interval(t: _Table, a: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, str]:
    lcol = _find(t, a["low"], "ConcLow")
    hcol = _find(t, a["high"], "ConcHigh")
    if lcol is None or hcol is None:
        raise ValidationError(
            f"low/high: {t.source} has no interval columns (ConcLow and ConcHigh, or give low=, high=)"
        )
    lo_v, _, u1 = _numbers(t, lcol, "low")
    hi_v, _, u2 = _numbers(t, hcol, "high")
    if u1 and u2 and u1 != u2:
        raise ValidationError(f"low/high: {lcol!r} is in {u1!r}, {hcol!r} in {u2!r}; use one unit")
    with np.errstate(invalid="ignore"):
        exact = lo_v == hi_v
        left = (np.isnan(lo_v) | (lo_v == 0)) & ~np.isnan(hi_v) & ~exact
        right = ~np.isnan(lo_v) & np.isnan(hi_v)
        _first(t, lo_v > hi_v, lcol, "the low end is above the high end")
    inside = ~np.isnan(lo_v) & ~np.isnan(hi_v) & ~exact & ~left
    _first(t, inside, lcol, "an interval with two finite ends is not supported (only left- or right-censored readings)")
    side = np.where(left, -1, np.where(right, 1, 0)).astype(np.int8)
    y = np.where(left, hi_v, lo_v)
    lower = np.where(left, hi_v, -np.inf)
    upper = np.where(right, lo_v, np.inf)
    ucol = _find(t, a.get("uncen"), "Uncen")
    if ucol is not None:
        flag = _flags(t, ucol, None)
        present = ~np.isnan(y)
        _first(t, present & ((flag != 0) != (side == 0)), ucol, "disagrees with the interval columns")
    return y, side, lower, upper, u1 or u2


def _nonmem(t: _Table, a: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, str]:
    dcol = _find(t, a["y"], "DV")
    ccol = _find(t, a["cens"], "CENS")
    if dcol is None or ccol is None:
        raise ValidationError(f"y/cens: {t.source} has no DV and CENS columns (or give y=, cens=)")
    dv, _, unit = _numbers(t, dcol, "y")
    cens, _, _ = _numbers(t, ccol, "cens")
    cens = np.where(np.isnan(cens), 0, cens)
    _first(t, ~np.isin(cens, (0, 1, -1)), ccol, "expected CENS 0, 1 (below the limit DV) or -1 (above the limit DV)")
    side = (-cens).astype(np.int8)
    mcol = _find(t, a["mdv"], "MDV")
    if mcol is not None:
        mdv, _, _ = _numbers(t, mcol, "mdv")
        miss = mdv == 1
        _first(t, miss & (side != 0), mcol, "MDV = 1 (missing) on a censored row")
        dv = np.where(miss, np.nan, dv)
    _first(t, (side != 0) & np.isnan(dv), dcol, "a censored row needs its limit in DV, and DV is blank")
    lim_col = a["limit"] if a["limit"] is not None else _find(t, None, "LIMIT")
    if lim_col is not None and a["limit"] is not False:
        lim, _, _ = _numbers(t, lim_col, "limit", allow_inf=True)
        _first(
            t,
            (side != 0) & np.isfinite(lim),
            lim_col,
            "a finite LIMIT makes the reading interval-censored (between LIMIT and DV), which is not supported; "
            "leave LIMIT blank (or pass limit=False to ignore the column) for censoring on one side",
        )
    lower = np.where(side == -1, dv, -np.inf)
    upper = np.where(side == 1, dv, np.inf)
    return dv, side, lower, upper, unit


def _times(t: _Table, name: str | None) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(times (datetime64 or float) or None, labels as written or None)."""
    if name is None:
        if t.index_times is None:
            return None, None
        return t.index_times, np.array([r.partition(" ")[2] for r in t.rows])
    cells = _column(t, name, "time")
    if isinstance(cells, np.ndarray):
        if cells.dtype.kind == "b":
            raise ValidationError(f"{t.at(0, name)}: booleans are not times")
        times = cells if cells.dtype.kind == "M" else cells.astype(float)
        labels = np.array([str(c) for c in cells])
        blank = np.isnat(times) if times.dtype.kind == "M" else np.isnan(times)
        _first(t, blank, name, "a blank time")
        return times, labels
    texts = [("" if c is None else str(c)).strip() for c in cells]
    nums = _fast_numbers(texts)
    if nums is not None:
        _first(t, np.isnan(nums), name, "a blank time")
        return nums, np.array(texts)
    try:
        parsed = [lab if isinstance(c, str) else np.datetime64(c) for c, lab in zip(cells, texts)]
        times = np.array(parsed, dtype="datetime64")
    except ValueError:
        for i, c in enumerate(texts):
            if _is_missing(c):
                raise ValidationError(f"{t.at(i, name)}: a blank time") from None
            try:
                np.datetime64(c)
            except ValueError:
                raise ValidationError(
                    f"{t.at(i, name)}: expected a date (YYYY-MM-DD, optionally Thh:mm:ss) or a number, got {c!r:.40}"
                ) from None
        raise  # pragma: no cover - some cell failed above
    _first(t, np.isnat(times), name, "a blank time")
    return times, np.array(texts)


def _check_order(
    t: _Table, tcol: str, times: np.ndarray, y: np.ndarray, side: np.ndarray, lo: np.ndarray, hi: np.ndarray, how: str
) -> np.ndarray:
    """Rows to keep: refuse repeated (or, with ``how='drop'``, conflicting repeated) and backward times."""
    keep = np.ones(times.size, dtype=bool)
    if times.size < 2:
        return keep
    same = times[1:] == times[:-1]
    if same.any():

        def eq(a: np.ndarray) -> np.ndarray:
            return (a[1:] == a[:-1]) | (np.isnan(a[1:]) & np.isnan(a[:-1]))

        identical = same & eq(y) & (side[1:] == side[:-1]) & eq(lo) & eq(hi)
        if how == "drop":
            keep[1:] &= ~identical
            bad = same & ~identical
            extra = "with another reading (duplicates='drop' drops only exact repeats)"
        else:
            bad = same
            extra = "(duplicates='drop' drops a row that repeats the previous one exactly)"
        if bad.any():
            i = int(np.argmax(bad)) + 1
            raise ValidationError(f"{t.at(i, tcol)}: the time {times[i]} repeats {t.label(i - 1)}'s {extra}")
    back = times[1:] < times[:-1]
    if back.any():
        i = int(np.argmax(back)) + 1
        raise ValidationError(
            f"{t.at(i, tcol)}: the time {times[i]} comes before {t.label(i - 1)}'s {times[i - 1]}; sort the rows by time"
        )
    return keep


def _nonmem_rows(t: _Table, a: dict[str, Any]) -> _Table:
    ecol = _find(t, a.get("evid"), "EVID")
    if ecol is None:
        return t
    evid, _, _ = _numbers(t, ecol, "evid")
    keep = np.flatnonzero(np.isnan(evid) | (evid == 0))
    if keep.size == 0:
        raise ValidationError(f"evid: {t.source} has no observation rows (EVID = 0)")
    return t.take(keep)


def _detect(t: _Table, a: dict[str, Any]) -> str:
    cols = {c.lower() for c in t.columns}
    interval = a["low"] is not None or a["high"] is not None or {"conclow", "conchigh"} <= cols
    nonmem = a["cens"] is not None or {"dv", "cens"} <= cols
    if interval and nonmem:
        raise ValidationError(
            f"format: {t.source} has both interval (ConcLow/ConcHigh) and NONMEM (DV/CENS) columns; give format="
        )
    if interval:
        return "interval"
    if nonmem:
        return "nonmem"
    return "flag" if a["censored"] is not None else "strings"


def _build(t: _Table, fmt: str, a: dict[str, Any], name: str) -> CensoredRecord:
    if fmt == "auto":
        fmt = _detect(t, a)
    if fmt == "nonmem":
        t = _nonmem_rows(t, a)
        y, side, lo, hi, unit = _nonmem(t, a)
    elif fmt == "interval":
        y, side, lo, hi, unit = _interval(t, a)
    else:
        if fmt == "flag" and a["censored"] is None:
            raise ValidationError("censored: the flag format needs the flag column (censored=...)")
        y, side, lo, hi, unit = _strings_or_flag(t, a)
    times, labels = _times(t, a["time"])
    covs = {}
    for c in a["covariates"]:
        covs[c] = _numbers(t, c, "covariates")[0]
    if times is not None:
        keep = _check_order(t, a["time"] or "index", times, y, side, lo, hi, a["duplicates"])
        if not keep.all():
            y, side, lo, hi, times = y[keep], side[keep], lo[keep], hi[keep], times[keep]
            labels = None if labels is None else labels[keep]
            covs = {k: v[keep] for k, v in covs.items()}
    if t.announce is not None:
        t.announce(
            f"checked {y.size:,} readings ({int((side != 0).sum()):,} censored, {int(np.isnan(y).sum()):,} missing)"
        )
    return CensoredRecord(
        name=name,
        y=y,
        censored=side != 0,
        lower=lo,
        upper=hi,
        covariates=covs,
        time=labels,
        description=f"read from {t.source} ({fmt} format)",
        times=times,
        units=unit,
    )


def _args(**kw: Any) -> dict[str, Any]:
    if kw["format"] not in FORMATS:
        raise ValidationError(f"format: expected one of {', '.join(FORMATS)}, got {kw['format']!r}")
    if kw["duplicates"] not in ("error", "drop"):
        raise ValidationError(f"duplicates: expected 'error' or 'drop', got {kw['duplicates']!r}")
    cov = kw["covariates"]
    if isinstance(cov, str) or not isinstance(cov, (list, tuple)) or not all(isinstance(c, str) for c in cov):
        raise ValidationError(f"covariates: expected a list of column names, got {cov!r}")
    for key in ("y", "censored", "low", "high", "cens", "time", "mdv", "evid", "uncen"):
        if kw.get(key) is not None and not isinstance(kw[key], str):
            raise ValidationError(f"{key}: expected a column name (str), got {kw[key]!r}")
    if kw["flag_codes"] is not None and not isinstance(kw["flag_codes"], Mapping):
        raise ValidationError(f"flag_codes: expected a mapping of flag value to side, got {kw['flag_codes']!r}")
    if not isinstance(kw["encoding"], str):
        raise ValidationError(f"encoding: expected the name of a text encoding, got {kw['encoding']!r}")
    return kw


def read_censored(
    source: Any,
    *,
    format: str = "auto",
    y: str | None = None,
    censored: str | None = None,
    lower: str | float | None = None,
    upper: str | float | None = None,
    flag_codes: Mapping[Any, str] | None = None,
    low: str | None = None,
    high: str | None = None,
    cens: str | None = None,
    limit: str | bool | None = None,
    time: str | None = None,
    covariates: Sequence[str] = (),
    duplicates: str = "error",
    encoding: str = "utf-8",
    name: str | None = None,
    progress: Callable[[str], None] | None = None,
    mdv: str | None = None,
    evid: str | None = None,
    uncen: str | None = None,
) -> CensoredRecord:
    r"""Read one censored series from a CSV file, a pandas DataFrame or a mapping of columns.

    Parameters
    ----------
    source : str, os.PathLike, pandas.DataFrame or mapping of str to sequence
        The record (module docstring).
    format : {"auto", "strings", "flag", "interval", "nonmem"}
        The layout (module docstring); ``"auto"`` picks it from the columns.
    y : str, optional
        The readings' column (``"strings"``, ``"flag"``; ``"nonmem"``: default ``DV``).
    censored : str, optional
        The censoring flag's column (``"flag"``).
    lower, upper : str or float, optional
        The limits: a column (blank cell = no limit, see the module docstring) or one number for all rows.
    flag_codes : mapping, optional
        Flag value -> ``"left"``, ``"right"``, ``"censored"`` or ``"none"`` (e.g. ``{1: "left", 2: "right"}``).
    low, high : str, optional
        The interval columns (default ``ConcLow``, ``ConcHigh``).
    cens, limit, mdv, evid : str, optional
        NONMEM columns (defaults ``CENS``, ``LIMIT``, ``MDV``, ``EVID`` when present; ``limit=False`` ignores
        a LIMIT column).
    uncen : str, optional
        EGRET's ``Uncen`` check column (default: ``Uncen`` when present).
    time : str, optional
        The times' column (dates or numbers); a DataFrame's ``DatetimeIndex`` is used when not given.
    covariates : sequence of str
        Columns of known regressors, read as numbers (blank = NaN).
    duplicates : {"error", "drop"}
        A time that repeats the previous row's: refused, or (``"drop"``) dropped if the row repeats it exactly.
    encoding : str
        The file's text encoding (UTF-8 by default; a byte-order mark is skipped).
    name : str, optional
        The series' name (default: the file's stem).
    progress : callable, optional
        ``progress(line)`` receives a few progress lines while a large file (8 MB or more) is parsed.

    Returns
    -------
    CensoredRecord
        A :class:`CensoredSeries` (``y`` holds a censored reading's limit, ``lower``/``upper`` per reading,
        ``-inf``/``+inf`` where there is none) with ``times`` and ``units``.

    Raises
    ------
    ValidationError
        Each malformed input, naming the row (the file's line) and the column (module docstring).

    Examples
    --------
    >>> from tobitkf.data.readers import read_censored
    >>> s = read_censored({"date": ["2020-01-01", "2020-01-09"], "conc": ["<0.05", "0.12"]}, y="conc", time="date")
    >>> s.y.tolist(), s.censored.tolist(), s.lower.tolist()
    ([0.05, 0.12], [True, False], [0.05, -inf])
    """
    a = _args(**{k: v for k, v in locals().items() if k not in ("source", "name", "progress")})
    a["covariates"] = list(covariates)
    t = _table(source, encoding, progress)
    return _build(t, format, a, name or _default_name(source))


def _default_name(source: Any) -> str:
    return Path(source).stem if isinstance(source, (str, os.PathLike)) else type(source).__name__


def read_censored_panel(
    source: Any,
    *,
    id: str,
    name: str | None = None,
    encoding: str = "utf-8",
    progress: Callable[[str], None] | None = None,
    format: str = "auto",
    **columns: Any,
) -> CensoredPanel:
    r"""Read many censored series from one long table with a subject column ``id``.

    Every other argument is :func:`read_censored`'s, applied to each subject's rows (in table order);
    errors name the row of the whole table. The order and duplicate checks of the times are per subject.

    Returns
    -------
    CensoredPanel
        ``panel[subject]`` is the subject's :class:`CensoredRecord`.

    Raises
    ------
    ValidationError
        A blank id, and every error of :func:`read_censored`.

    Examples
    --------
    >>> from tobitkf.data.readers import read_censored_panel
    >>> p = read_censored_panel({"id": ["a", "a", "b"], "day": [0, 7, 3], "v": ["1.0", "<0.5", "2.0"]},
    ...                         id="id", time="day", y="v")
    >>> p.ids, p.steps.tolist(), p["a"].censored.tolist()
    (['a', 'b'], [2, 1], [False, True])
    """
    known = set(read_censored.__kwdefaults__ or {}) - {"format", "name", "encoding", "progress"}
    bad = sorted(set(columns) - known)
    if bad:
        raise ValidationError(f"{bad[0]}: unknown argument; expected one of {', '.join(sorted(known))}")
    defaults = {k: v for k, v in (read_censored.__kwdefaults__ or {}).items() if k in known}
    a = _args(format=format, encoding=encoding, **{**defaults, **columns})
    a["covariates"] = list(a["covariates"])
    t = _table(source, encoding, progress)
    cells = _column(t, id, "id")
    keys = []
    for i, c in enumerate(cells.tolist() if isinstance(cells, np.ndarray) else cells):
        if _is_missing(c):
            raise ValidationError(f"{t.at(i, id)}: a blank subject id")
        keys.append(str(int(c)) if isinstance(c, (float, np.floating)) and float(c).is_integer() else str(c).strip())
    groups: dict[str, list[int]] = {}
    for i, k in enumerate(keys):
        groups.setdefault(k, []).append(i)
    base = name or _default_name(source)
    series = {k: _build(t.take(np.array(idx)), format, a, f"{base}:{k}") for k, idx in groups.items()}
    return CensoredPanel(name=base, series=series, id_column=id)


# --------------------------------------------------------------------------- writing


def _fmt(x: float) -> str:
    return "" if math.isnan(x) else repr(float(x))


def write_censored(series: CensoredSeries, path: str | os.PathLike, *, format: str = "flag") -> Path:
    r"""Write a :class:`CensoredSeries` as CSV in one of the readers' formats (what they read back).

    Columns: ``time`` (``times`` when the series has them, else the labels ``time``), then for ``"strings"``
    ``y`` (``"<L"``/``">U"`` for censored readings); ``"flag"`` ``y``, ``censored`` (0/1), ``lower``, ``upper``
    (an infinite limit written blank: the blank-limit rule reads it back as no limit); ``"interval"``
    ``ConcLow``, ``ConcHigh``; ``"nonmem"`` ``DV``, ``CENS`` (0, 1, -1), ``MDV``; then the covariates.
    The ``"strings"``, ``"interval"`` and ``"nonmem"`` layouts keep no limit of an uncensored reading.

    Raises
    ------
    ValidationError
        An unknown format.
    """
    from .._io import atomic_write_text

    if format not in FORMATS[1:]:
        raise ValidationError(f"format: expected one of {', '.join(FORMATS[1:])}, got {format!r}")
    T = series.steps
    side = np.zeros(T, dtype=np.int8)
    with np.errstate(invalid="ignore"):
        side[series.censored & (series.y <= series.lower)] = -1
        side[series.censored & (series.y > series.lower)] = 1
    times = getattr(series, "times", None)
    if times is not None:
        tcol = [np.datetime_as_string(x) if times.dtype.kind == "M" else repr(float(x)) for x in times]
    elif series.time is not None:
        tcol = [str(x) for x in series.time]
    else:
        tcol = None
    head = {
        "strings": ["y"],
        "flag": ["y", "censored", "lower", "upper"],
        "interval": ["ConcLow", "ConcHigh"],
        "nonmem": ["DV", "CENS", "MDV"],
    }[format]
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow((["time"] if tcol is not None else []) + head + list(series.covariates))
    for i in range(T):
        v, s = float(series.y[i]), int(side[i])
        if format == "strings":
            cells = [("<" if s < 0 else ">" if s > 0 else "") + _fmt(v)]
        elif format == "flag":
            lo, hi = float(series.lower[i]), float(series.upper[i])
            cells = [
                _fmt(v),
                str(int(s != 0)),
                _fmt(lo) if np.isfinite(lo) else "",
                _fmt(hi) if np.isfinite(hi) else "",
            ]
        elif format == "interval":
            cells = ["" if s < 0 else _fmt(v), "" if s > 0 else _fmt(v)]
        else:
            cells = [_fmt(v), str(-s), "1" if math.isnan(v) else "0"]
        covs = [_fmt(float(c[i])) for c in series.covariates.values()]
        w.writerow(([tcol[i]] if tcol is not None else []) + cells + covs)
    return atomic_write_text(path, out.getvalue())
