"""Cells to values, with the checks of the readers (:mod:`tobitkf.data.readers`): numbers and ``"<L"`` /
``">U"`` strings with their units, censoring flags, limits, times and their order. Each refusal names the
row and the column (``_Table.at``)."""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .._validation import ValidationError
from ._tables import _Table

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


def _shown(t: Any) -> str:
    """A time as a user wrote it: a date without its midnight clock (``2020-01-02``), else as it is."""
    if isinstance(t, np.datetime64):
        day = t.astype("datetime64[D]")
        return str(day) if day == t else np.datetime_as_string(t, unit="s")
    return str(t)


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
            raise ValidationError(f"{t.at(i, tcol)}: the time {_shown(times[i])} repeats {t.label(i - 1)}'s {extra}")
    back = times[1:] < times[:-1]
    if back.any():
        i = int(np.argmax(back)) + 1
        raise ValidationError(
            f"{t.at(i, tcol)}: the time {_shown(times[i])} comes before {t.label(i - 1)}'s {_shown(times[i - 1])}; "
            "sort the rows by time"
        )
    return keep
