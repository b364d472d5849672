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
    right-censored at U; both empty: missing; two finite ends ``low < high``: an *interval* reading, the
    value known only to lie between them. A column ``Uncen`` (1 = uncensored), if present, must agree.
``"nonmem"``
    NONMEM / nlmixr2 / Monolix columns ``DV``, ``CENS`` (0 exact, 1 left-censored at DV, -1 right-censored
    at DV) and optionally ``LIMIT`` (the other end of the censoring interval: empty or infinite, the M3
    likelihood; finite, an interval reading, in [LIMIT, DV] for CENS = 1 and [DV, LIMIT] for CENS = -1,
    the M4 likelihood); ``MDV`` = 1 marks a missing reading and rows with ``EVID`` not 0 (dose records)
    are skipped.

**Interval readings.** A reading known only to lie in ``[lower, upper]`` (both finite: EGRET's
``ConcLow < ConcHigh``, NONMEM's finite ``LIMIT``, or in the ``"flag"`` layout a flagged reading strictly
between its two limits) is kept as one: ``censored`` True, ``lower``/``upper`` its interval, and ``y`` the
interval's midpoint (a value inside it, which the likelihood does not use). The assumed-density filters,
their smoother and likelihood, :func:`tobitkf.fit` and the panels score it by the predictive probability of
the interval. ``interval_rows=`` chooses: ``"keep"`` (the default), ``"error"`` (refuse such rows),
``"left"`` (read as below the upper end: what the lower end says is dropped) or ``"right"`` (above the
lower end). (Until version 0.2 such rows were refused unless ``interval_rows`` said ``"left"`` or
``"right"``.) Strings such as ``"0.05-0.1"`` are not read as intervals (a minus sign makes them
ambiguous).

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
import io
import math
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .._validation import ValidationError
from ._cells import _check_order, _column, _is_missing, _numbers, _times
from ._formats import FORMATS, INTERVAL, INTERVAL_ROWS, _detect, _interval, _nonmem, _nonmem_rows, _strings_or_flag
from ._series import CensoredSeries
from ._tables import PROGRESS_BYTES, _Table, _table

__all__ = [
    "CensoredRecord",
    "CensoredPanel",
    "read_censored",
    "read_censored_panel",
    "write_censored",
    "FORMATS",
    "INTERVAL_ROWS",
    "PROGRESS_BYTES",
]


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
    source : str
        Where the record was read from (the file's path, ``"DataFrame"`` or ``"table"``).
    rows : (T,) ndarray of int or str, or None
        Where each reading came from: the file's line numbers, or the DataFrame's row labels
        (``"row 2020-01-01"``); :meth:`where` turns one into the readers' wording.
    """

    times: np.ndarray | None = None
    units: str = ""
    source: str = ""
    rows: np.ndarray | None = None

    def where(self, i: int, column: str | None = None) -> str:
        """Reading ``i`` (0-based) as the readers name it in an error: ``"FILE line 12, column 'conc'"``."""
        if self.rows is None:
            at = f"reading {i + 1}"
        else:
            r = self.rows[i]
            at = f"line {int(r)}" if np.issubdtype(np.asarray(self.rows).dtype, np.integer) else str(r)
        place = f"{self.source} {at}" if self.source else at
        return place if column is None else f"{place}, column {column!r}"

    @property
    def side(self) -> np.ndarray:
        """(T,) int8: -1 left-censored (at ``lower``), +1 right-censored (at ``upper``), 2 an interval reading
        (between ``lower`` and ``upper``), 0 otherwise."""
        out = np.zeros(self.steps, dtype=np.int8)
        with np.errstate(invalid="ignore"):
            out[self.censored & (self.y <= self.lower)] = -1
            out[self.censored & (self.y >= self.upper)] = 1
        out[self.interval] = INTERVAL
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
    rows = np.asarray(t.rows)
    covs = {}
    for c in a["covariates"]:
        covs[c] = _numbers(t, c, "covariates")[0]
    if times is not None:
        keep = _check_order(t, a["time"] or "index", times, y, side, lo, hi, a["duplicates"])
        if not keep.all():
            y, side, lo, hi, times = y[keep], side[keep], lo[keep], hi[keep], times[keep]
            labels = None if labels is None else labels[keep]
            rows = rows[keep]
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
        source=t.source,
        rows=rows,
    )


def _args(**kw: Any) -> dict[str, Any]:
    if kw["format"] not in FORMATS:
        raise ValidationError(f"format: expected one of {', '.join(FORMATS)}, got {kw['format']!r}")
    if kw.get("interval_rows", "keep") not in INTERVAL_ROWS:
        raise ValidationError(
            f"interval_rows: expected one of {', '.join(repr(v) for v in INTERVAL_ROWS)}, got {kw['interval_rows']!r}"
        )
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
    interval_rows: str = "keep",
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
    interval_rows : {"keep", "error", "left", "right"}
        Rows whose value lies between two finite ends (EGRET's ``ConcLow < ConcHigh``, NONMEM's finite
        ``LIMIT``, a flagged reading between its two limits): kept as interval readings (``"keep"``, the
        default), refused (``"error"``), or read as censored below the upper end (``"left"``: the lower end
        is dropped, a weaker statement than the record's) or above the lower end (``"right"``).

        .. note:: Changed in 0.2: the default was ``"error"`` (such rows were refused); it is now
           ``"keep"``.
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
    first = next(iter(series.values()))
    for rec in series.values():  # each subject's cells agree within it; the column must agree across subjects
        if rec.units != first.units:
            col = a["y"] or "the readings"
            raise ValidationError(
                f"{rec.where(0, col)}: mixed units in one column: {rec.units or 'no unit'!r} for subject "
                f"{rec.name.rpartition(':')[2]!r}, {first.units or 'no unit'!r} at {first.where(0)}; convert the column "
                "to one unit"
            )
    return CensoredPanel(name=base, series=series, id_column=id)


# --------------------------------------------------------------------------- writing


def _fmt(x: float) -> str:
    return "" if math.isnan(x) else repr(float(x))


def write_censored(series: CensoredSeries, path: str | os.PathLike, *, format: str = "flag") -> Path:
    r"""Write a :class:`CensoredSeries` as CSV in one of the readers' formats (what they read back).

    Columns: ``time`` (``times`` when the series has them, else the labels ``time``), then for ``"strings"``
    ``y`` (``"<L"``/``">U"`` for censored readings); ``"flag"`` ``y``, ``censored`` (0/1), ``lower``, ``upper``
    (an infinite limit written blank: the blank-limit rule reads it back as no limit); ``"interval"``
    ``ConcLow``, ``ConcHigh``; ``"nonmem"`` ``DV``, ``CENS`` (0, 1, -1), ``MDV`` (and ``LIMIT`` when the series
    has interval readings); then the covariates. The ``"strings"``, ``"interval"`` and ``"nonmem"`` layouts
    keep no limit of an uncensored reading. An interval reading (:attr:`CensoredSeries.interval`) is written
    as its two ends (``"flag"``: the midpoint flagged between its limits; ``"interval"``: ``ConcLow``,
    ``ConcHigh``; ``"nonmem"``: ``DV`` the upper end, ``CENS`` 1, ``LIMIT`` the lower end).

    Raises
    ------
    ValidationError
        An unknown format; an interval reading in the ``"strings"`` layout (which has no form for it).
    """
    from .._io import atomic_write_text

    if format not in FORMATS[1:]:
        raise ValidationError(f"format: expected one of {', '.join(FORMATS[1:])}, got {format!r}")
    T = series.steps
    side = np.zeros(T, dtype=np.int8)
    with np.errstate(invalid="ignore"):
        side[series.censored & (series.y <= series.lower)] = -1
        side[series.censored & (series.y > series.lower)] = 1
    iv = series.interval
    side[iv] = INTERVAL
    if format == "strings" and iv.any():
        i = int(np.flatnonzero(iv)[0])
        raise ValidationError(
            f"format: reading {i + 1} is an interval reading ([{series.lower[i]!r}, {series.upper[i]!r}]), which "
            "the strings layout cannot write; use format='interval', 'flag' or 'nonmem'"
        )
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
        "nonmem": ["DV", "CENS", "MDV"] + (["LIMIT"] if iv.any() else []),
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
            if s == INTERVAL:
                cells = [_fmt(float(series.lower[i])), _fmt(float(series.upper[i]))]
            else:
                cells = ["" if s < 0 else _fmt(v), "" if s > 0 else _fmt(v)]
        elif s == INTERVAL:
            cells = [_fmt(float(series.upper[i])), "1", "0", _fmt(float(series.lower[i]))]
        else:
            cells = [_fmt(v), str(-s), "1" if math.isnan(v) else "0"] + ([""] if iv.any() else [])
        covs = [_fmt(float(c[i])) for c in series.covariates.values()]
        w.writerow(([tcol[i]] if tcol is not None else []) + cells + covs)
    return atomic_write_text(path, out.getvalue())
