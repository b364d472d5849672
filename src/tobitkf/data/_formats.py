"""The layouts of the readers (:mod:`tobitkf.data.readers`): readings as numbers and ``"<L"`` strings or
with a flag and limits, EGRET's interval columns, NONMEM's ``DV``/``CENS``/``LIMIT``. Each turns a table
into ``(y, side, lower, upper, unit)``: the readings (a censored one at its limit, an interval one at the
midpoint of its interval), the side (-1 left, +1 right, 0 none, :data:`INTERVAL` a value known only to lie
between ``lower`` and ``upper``), the limits per reading (``-inf``/``+inf`` for none) and the readings'
unit."""

from __future__ import annotations

from typing import Any

import numpy as np

from .._validation import ValidationError
from ._cells import _find, _first, _flags, _limit, _numbers, _tol
from ._tables import _Table

FORMATS = ("auto", "strings", "flag", "interval", "nonmem")
INTERVAL_ROWS = ("keep", "error", "left", "right")
INTERVAL = 2
"""The side code of an interval reading (censored into [lower, upper], both ends finite)."""


def _midpoint(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """A value strictly inside each finite interval (its midpoint): what ``y`` holds for an interval reading."""
    with np.errstate(invalid="ignore"):
        return lo + 0.5 * (hi - lo)


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
    unknown = side == 2  # (the reader's code for "censored, side not given"; INTERVAL once resolved)
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
            with np.errstate(invalid="ignore"):
                inside = unknown & ~at_lo & ~at_hi & (v > L) & (v < U)
            if a.get("interval_rows", "keep") == "keep":  # between its two limits: an interval reading
                side[inside] = INTERVAL
                unknown = unknown & ~inside
            _first(
                t,
                unknown & (side == 2),
                a["censored"],
                "flagged censored, but the reading is at neither of its limits (nor between them)"
                if a.get("interval_rows", "keep") == "keep"
                else "flagged censored, but the reading is at neither of its limits",
            )
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
    iv = side == INTERVAL
    y[iv] = _midpoint(lo[iv], hi[iv])  # the reading's own value, unused by the likelihood, kept inside
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
    how = a.get("interval_rows", "keep")
    if how == "error":
        _first(
            t,
            inside,
            lcol,
            f"an interval with two finite ends ({lcol} < {hcol}): a reading known only to lie between them, "
            "refused by interval_rows='error'; the default interval_rows='keep' reads it as an interval reading",
        )
    elif how == "left":
        left = left | inside
        inside = inside & False
    elif how == "right":
        right = right | inside
        inside = inside & False
    side = np.where(left, -1, np.where(right, 1, np.where(inside, INTERVAL, 0))).astype(np.int8)
    y = np.where(left, hi_v, np.where(inside, _midpoint(lo_v, hi_v), lo_v))
    lower = np.where(left, hi_v, np.where(inside, lo_v, -np.inf))
    upper = np.where(right, lo_v, np.where(inside, hi_v, np.inf))
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
    lower = np.where(side == -1, dv, -np.inf)
    upper = np.where(side == 1, dv, np.inf)
    if lim_col is not None and a["limit"] is not False:
        lim, _, _ = _numbers(t, lim_col, "limit", allow_inf=True)
        finite = (side != 0) & np.isfinite(lim)
        how = a.get("interval_rows", "keep")
        if how == "error":
            _first(
                t,
                finite,
                lim_col,
                "a finite LIMIT makes the reading interval-censored (between LIMIT and DV), refused by "
                "interval_rows='error'; the default interval_rows='keep' reads it as an interval reading",
            )
        elif how == "keep":
            with np.errstate(invalid="ignore"):
                _first(
                    t, finite & (side == -1) & ~(lim < dv), lim_col, "CENS = 1 needs LIMIT below DV (y in [LIMIT, DV])"
                )
                _first(
                    t, finite & (side == 1) & ~(lim > dv), lim_col, "CENS = -1 needs LIMIT above DV (y in [DV, LIMIT])"
                )
            lower = np.where(finite & (side == 1), dv, np.where(finite, lim, lower))
            upper = np.where(finite & (side == -1), dv, np.where(finite, lim, upper))
            dv = np.where(finite, _midpoint(lower, upper), dv)
            side = np.where(finite, INTERVAL, side).astype(np.int8)
        # "left"/"right": the one-sided reading at DV, what LIMIT says is dropped
    return dv, side, lower, upper, unit


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
