r"""``tobitkf fit FILE.csv --model MODEL.toml``: fit a model to a user's own censored series.

The model file (TOML) names the columns and the model::

    [data]
    y = "lP"                 # the readings: numbers, "<0.05" / ">750000" strings; empty or NA = missing
    censored = "cc"          # optional: the recorded flag (1/0, true/false, "<"/">"); default the limit rule
    lower = "lcl"            # optional: a column or a number (left-censoring limit)
    upper = 4.787            # optional: a column or a number (right-censoring limit)
    regressors = ["lQ"]      # optional: columns of known regressors
    intercept = true         # default true
    time = "time"            # optional: the times (dates or numbers), copied to the series file

    [model]
    kind = "censored_ar"     # regression with AR(p) errors, exact ML (the default)
    p = 1

The file's layout (``format``, or ``--format`` on the command line) is one of the readers' formats
(:mod:`tobitkf.data.readers`): ``"strings"`` (readings such as ``"<0.05"``), ``"flag"`` (reading + flag
+ limits, as above), ``"interval"`` (EGRET's ``ConcLow``/``ConcHigh``; keys ``low``/``high`` rename
them), ``"nonmem"`` (``DV``/``CENS``/``LIMIT``; keys ``y``, ``cens``, ``limit``), or ``"auto"`` (the
default: picked from the columns). Further ``[data]`` keys: ``flag_codes`` (a table such as
``{1 = "left", 2 = "right"}``), ``duplicates`` (``"error"`` or ``"drop"``), ``encoding``, ``interval_rows``
(rows whose value lies between two finite ends, EGRET's ``ConcLow < ConcHigh`` or NONMEM's finite ``LIMIT``:
``"keep"``, the default, reads them as interval readings, which the state-space models score by the
interval's probability; ``"error"`` refuses them; ``"left"``/``"right"`` keep one end).

**Blank limits.** A blank limit cell means that no limit was recorded for that reading (``-inf`` /
``+inf``, as :func:`tobitkf.fit` takes it): harmless for an uncensored or missing reading; a censored
reading with a blank limit is refused, naming its line and column.

For a linear state-space model fitted by EM (``kind = "state_space"``): the starting matrices ``A``,
``C``, ``Q``, ``R``, ``x0``, ``P0`` (nested arrays), ``estimate = ["Q", "R"]``, optionally
``prior = "stationary"``, ``method = "direct"`` and ``maxiter``. The intercept and regressors enter as
known inputs through ``D`` (``y_k = C x_k + D u_k + v_k``), starting from ``D`` (default zeros) and
estimated (``"D"`` is added to ``estimate`` when ``estimate`` is not given; with ``estimate`` given,
either list ``"D"``, give a fixed ``D``, or set ``intercept = false`` and no regressors).

For irregular sample times, a model in continuous time (``kind = "ou"``): the intercept and regressors
``u`` enter through ``D`` and the residual is an Ornstein-Uhlenbeck process (a continuous-time AR(1)) with
rate :math:`\theta` per time unit and stationary standard deviation :math:`s`, read with a measurement error
:math:`v \sim N(0, r^2)`,

.. math::

    y(t_k) = D u_k + \ell + \xi(t_k) + v_k, \qquad d\xi = -\theta\xi\,dt + \sqrt{2\theta s^2}\,dW,

each gap discretised exactly (:class:`~tobitkf.ContinuousLinearSystem`) and fitted by maximum likelihood
(:func:`tobitkf.fit` with the sample times; the assumed-density likelihood when a reading is censored). It
needs ``[data] time`` (dates, or numbers in the model's unit). Its ``[model]`` keys: ``level = true`` adds a
level :math:`\ell \sim N(0, \tau^2)` constant within each subject (a subject's own set point; without it
:math:`\ell = 0`), ``noise_sd`` fixes r (default: estimated), ``unit`` the time unit of the rates for dated
times (``"D"``, the default, ``"h"``, ``"W"``, ``"Y"``, ...), ``forecast = H`` the lead of the forecasts (H
time units after each subject's last reading, at 1, 2, ..., H; the regressors held at their last values),
``grid = g`` the step of a smoothed series on a regular grid (every g time units from each subject's first
reading to its last, written to ``grid.csv``), ``align`` (``"first"``: each subject's prior at its first
reading, the default; ``"common"``), ``maxiter``.
The parameters are the coefficients ``beta_<column>``, ``log_rate``, ``log_sd`` and, when estimated,
``log_level_sd`` and ``log_noise_sd``.

**Panels.** ``[data] subject = "id"`` names a column of subject labels: the file is a long table (one row
per reading, each subject's rows in time order) read by :func:`~tobitkf.data.read_censored_panel` into a
:class:`~tobitkf.Panel` and fitted jointly with ``kind = "ou"``; ``series.csv`` and ``forecast.csv`` then
start with a ``subject`` column. ``[data] transform = "log"`` or ``"log10"`` fits the logarithm of the
readings and their limits (a reading or limit that is not above 0 is refused, naming its line and column);
the written series are on that scale.

It writes into ``--out``: ``fit.json`` (:meth:`~tobitkf.inference.fitting.FitResult.save`),
``summary.txt``, ``series.csv`` (the readings, the indicator, the limits and the smoothed latent series
with its standard deviation; for ``kind = "ou"`` the smoothed :math:`D u + \ell + \xi` at each reading
without the measurement error), ``forecast.csv`` (``kind = "ou"`` with ``forecast``: each subject's
predictive mean, standard deviation and 95 % interval of a reading at each lead), ``grid.csv`` (``kind =
"ou"`` with ``grid``: the smoothed series on the grid with its standard deviation and 95 % band) and
``fit.png`` (readings, limits, smoothed series; skipped with a note
when matplotlib is not installed). Files of those names that tobitkf did not write are not replaced
unless ``force`` is set.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from .._io import FIGURE_MARKERS
from .._validation import ValidationError

__all__ = ["run_fit", "read_spec", "check_outputs", "OUTPUTS"]

_DATA_KEYS = {
    "format",
    "y",
    "censored",
    "lower",
    "upper",
    "flag_codes",
    "low",
    "high",
    "cens",
    "limit",
    "regressors",
    "intercept",
    "time",
    "duplicates",
    "encoding",
    "subject",
    "transform",
    "interval_rows",
}
_AR_KEYS = {"kind", "p", "maxiter"}
_SS_KEYS = {"kind", "A", "C", "Q", "R", "x0", "P0", "D", "estimate", "prior", "method", "maxiter"}
_OU_KEYS = {"kind", "level", "noise_sd", "unit", "forecast", "grid", "align", "maxiter"}
_MODEL_KEYS = _AR_KEYS | _SS_KEYS | _OU_KEYS
_KINDS = {"censored_ar": _AR_KEYS, "state_space": _SS_KEYS, "ou": _OU_KEYS}
_SERIES_HEADER = "time,y,censored,lower,upper,smoothed,smoothed_sd"
_PANEL_HEADER = "subject," + _SERIES_HEADER
_FORECAST_HEADER = "time,ahead,mean,sd,lower_95,upper_95"
_GRID_HEADER = "time,smoothed,smoothed_sd,lower_95,upper_95"
_SUMMARY_MARK = "(written by tobitkf fit)"
#: the files ``tobitkf fit`` writes, each with the marker that shows tobitkf wrote it
OUTPUTS: dict[str, tuple[bytes, ...]] = {
    "fit.json": (b'"format": "tobitkf-fit"',),
    "summary.txt": (_SUMMARY_MARK.encode(),),
    "series.csv": ((_SERIES_HEADER + "\n").encode(), (_PANEL_HEADER + "\n").encode()),
    "forecast.csv": ((_FORECAST_HEADER + "\n").encode(), ("subject," + _FORECAST_HEADER + "\n").encode()),
    "grid.csv": ((_GRID_HEADER + "\n").encode(), ("subject," + _GRID_HEADER + "\n").encode()),
    "fit.png": FIGURE_MARKERS,
}


def read_spec(path: Path) -> dict[str, Any]:
    """The model file as a dict; ``ValidationError`` naming the file and the key on anything unknown or
    of the wrong type."""
    import tomllib

    from .._io import as_path

    path = as_path(path, "--model")
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except OSError as exc:
        raise ValidationError(f"--model: cannot read {path} ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise ValidationError(f"--model: {path} is not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    try:
        spec = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValidationError(f"--model: {path} is not valid TOML ({exc})") from None
    bad = sorted(set(spec) - {"data", "model"})
    if bad:
        raise ValidationError(f"--model: unknown section [{bad[0]}]; expected [data] and [model]")
    for section, keys in (("data", _DATA_KEYS), ("model", _MODEL_KEYS)):
        part = spec.setdefault(section, {})
        if not isinstance(part, dict):
            raise ValidationError(f"--model: [{section}] must be a table")
        bad = sorted(set(part) - keys)
        if bad:
            raise ValidationError(f"--model: unknown key {bad[0]!r} in [{section}]; expected {', '.join(sorted(keys))}")
    _check_data(spec["data"])
    _check_model(spec["model"])
    return spec


def _key(section: str, key: str) -> str:
    return f"--model: [{section}] {key}"


def _check_data(d: dict[str, Any]) -> None:
    from ..data.readers import FORMATS, INTERVAL_ROWS

    for k in ("y", "censored", "low", "high", "cens", "time", "encoding", "subject"):
        if k in d and not (isinstance(d[k], str) and d[k]):
            raise ValidationError(f"{_key('data', k)}: expected a column name (text), got {d[k]!r}")
    for k in ("lower", "upper"):
        v = d.get(k)
        if v is not None and (isinstance(v, bool) or not isinstance(v, (str, int, float))):
            raise ValidationError(f"{_key('data', k)}: {k} must be a column name or a number, got {v!r}")
    if "limit" in d and not (d["limit"] is False or isinstance(d["limit"], str)):
        raise ValidationError(f"{_key('data', 'limit')}: expected a column name or false, got {d['limit']!r}")
    if "intercept" in d and not isinstance(d["intercept"], bool):
        raise ValidationError(f"{_key('data', 'intercept')}: expected true or false, got {d['intercept']!r}")
    regs = d.get("regressors", [])
    if not isinstance(regs, list) or not all(isinstance(r, str) for r in regs):
        raise ValidationError(f"{_key('data', 'regressors')}: regressors must be a list of column names, got {regs!r}")
    if "format" in d and d["format"] not in FORMATS:
        raise ValidationError(f"{_key('data', 'format')}: expected one of {', '.join(FORMATS)}, got {d['format']!r}")
    if "duplicates" in d and d["duplicates"] not in ("error", "drop"):
        raise ValidationError(f"{_key('data', 'duplicates')}: expected 'error' or 'drop', got {d['duplicates']!r}")
    if "interval_rows" in d and d["interval_rows"] not in INTERVAL_ROWS:
        raise ValidationError(
            f"{_key('data', 'interval_rows')}: expected one of {', '.join(repr(v) for v in INTERVAL_ROWS)}, got "
            f"{d['interval_rows']!r}"
        )
    if "transform" in d and d["transform"] not in ("none", "log", "log10"):
        raise ValidationError(f"{_key('data', 'transform')}: expected 'none', 'log' or 'log10', got {d['transform']!r}")
    codes = d.get("flag_codes")
    if codes is not None and not (isinstance(codes, dict) and all(isinstance(v, str) for v in codes.values())):
        raise ValidationError(f'{_key("data", "flag_codes")}: expected a table such as {{1 = "left"}}, got {codes!r}')


def _check_model(m: dict[str, Any]) -> None:
    from .._validation import check_int

    kind = m.get("kind", "censored_ar")
    if kind not in _KINDS:
        raise ValidationError(f"--model: unknown model kind {kind!r}; expected 'censored_ar', 'state_space' or 'ou'")
    allowed = _KINDS[kind]
    extra = sorted(set(m) - allowed)
    if extra:
        raise ValidationError(
            f"{_key('model', extra[0])}: does not apply to kind = {kind!r} (its keys: {', '.join(sorted(allowed))})"
        )
    if "p" in m:
        check_int(m["p"], _key("model", "p"), minimum=0)
    if "maxiter" in m:
        check_int(m["maxiter"], _key("model", "maxiter"), minimum=1)
    for k in ("prior", "method"):
        if k in m and not isinstance(m[k], str):
            raise ValidationError(f"{_key('model', k)}: expected text, got {m[k]!r}")
    g = m.get("grid")
    if g is not None and (isinstance(g, bool) or not isinstance(g, (int, float)) or not 0 < g < float("inf")):
        raise ValidationError(f"{_key('model', 'grid')}: expected a step > 0 (in the model's time unit), got {g!r}")
    if "forecast" in m:
        check_int(m["forecast"], _key("model", "forecast"), minimum=0)
    if "level" in m and not isinstance(m["level"], bool):
        raise ValidationError(f"{_key('model', 'level')}: expected true or false, got {m['level']!r}")
    nsd = m.get("noise_sd")
    if nsd is not None and (isinstance(nsd, bool) or not isinstance(nsd, (int, float)) or not nsd > 0):
        raise ValidationError(f"{_key('model', 'noise_sd')}: expected a number > 0, got {nsd!r}")
    if "unit" in m:
        from ..models.continuous import _unit

        try:
            _unit(m["unit"])
        except ValidationError as exc:
            raise ValidationError(f"{_key('model', 'unit')}: {str(exc).removeprefix('unit: ')}") from None
    if "align" in m and m["align"] not in ("first", "common"):
        raise ValidationError(f"{_key('model', 'align')}: expected 'first' or 'common', got {m['align']!r}")
    est = m.get("estimate")
    if est is not None and (not isinstance(est, list) or not all(isinstance(e, str) for e in est)):
        raise ValidationError(f"{_key('model', 'estimate')}: expected a list of matrix names, got {est!r}")


def check_outputs(out: Path, *, force: bool = False) -> None:
    """Refuse, before any work, to replace a file in ``out`` that ``tobitkf fit`` did not write
    (``fit.json``, ``summary.txt``, ``series.csv``, ``fit.png``), unless ``force``; a folder in the way is
    always refused.

    Raises
    ------
    ValidationError
        Naming the file and what to do.
    """
    from .._io import check_replaceable

    for fname, markers in OUTPUTS.items():
        path = out / fname
        if force and path.is_file():
            continue
        try:
            check_replaceable(path, "--out", markers)
        except ValidationError as exc:
            raise ValidationError(f"{exc}; or pass --force to replace it") from None


def _progress_lines(progress: Any) -> Callable[[str], None] | None:
    if progress is None or progress is False:
        return None
    if callable(progress):
        return progress
    import sys

    def echo(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    return echo


def run_fit(
    csv_path: str | Path,
    model_path: str | Path,
    out: str | Path,
    *,
    progress: Any = None,
    format: str | None = None,
    force: bool = False,
    notes: Callable[[str], None] | None = None,
) -> list[Path]:
    """Read FILE and MODEL, fit, write the outputs; returns the written paths.

    ``format`` (the command line's ``--format``) overrides the model file's ``[data] format``;
    ``progress``: True (lines on stderr), a callable or None; ``notes`` receives one-line notes (a skipped
    figure); ``force`` replaces output files that tobitkf did not write.

    Raises
    ------
    ValidationError
        Unreadable or inconsistent inputs (each message names the file and the key, or the line and column).
    """
    from .._io import as_path, atomic_write_text, check_writable_dir
    from ..data.readers import FORMATS, read_censored, read_censored_panel
    from .censored_ar import CensoredAR
    from .fitting import fit

    if format is not None and format not in FORMATS:
        raise ValidationError(f"--format: expected one of {', '.join(FORMATS)}, got {format!r}")
    spec = read_spec(as_path(model_path, "--model"))
    out = check_writable_dir(out, "--out")
    check_outputs(out, force=force)
    d, mspec = spec["data"], spec["model"]
    kind = mspec.get("kind", "censored_ar")
    subject = d.get("subject")
    if subject is not None and kind != "ou":
        raise ValidationError(
            f"{_key('data', 'subject')}: a panel (many subjects) is fitted with the continuous-time model; "
            f'set [model] kind = "ou" (the model file has kind = {kind!r})'
        )
    if kind == "ou" and "time" not in d:
        raise ValidationError(f'{_key("data", "time")}: kind = "ou" needs the sample times; name their column')
    regs = list(d.get("regressors", []))
    lines = _progress_lines(progress)
    columns: dict[str, Any] = dict(
        format=format or d.get("format", "auto"),
        y=d.get("y"),
        censored=d.get("censored"),
        lower=d.get("lower"),
        upper=d.get("upper"),
        flag_codes=d.get("flag_codes"),
        low=d.get("low"),
        high=d.get("high"),
        cens=d.get("cens"),
        limit=d.get("limit"),
        time=d.get("time"),
        covariates=regs,
        duplicates=d.get("duplicates", "error"),
        encoding=d.get("encoding", "utf-8"),
        progress=lines,
        interval_rows=d.get("interval_rows", "keep"),
    )
    ids: list[str] | None = None
    if subject is not None:
        read = read_censored_panel(as_path(csv_path, "FILE"), id=subject, **columns)
        records, ids = list(read.series.values()), read.ids
    else:
        records = [read_censored(as_path(csv_path, "FILE"), **columns)]
    records = [_transformed(r, d.get("transform", "none"), d) for r in records]
    for rec in records:
        for r in regs:
            miss = np.isnan(rec.covariates[r])
            if miss.any():
                raise ValidationError(
                    f"{rec.where(int(np.argmax(miss)), r)}: a blank regressor; regressors must be known for every "
                    "reading"
                )
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValidationError(f"--out: cannot create the folder {out} ({exc.strerror or exc})") from None
    if kind == "ou":
        from .panel import Panel

        panel = Panel.from_records(records, regressors=regs, intercept=d.get("intercept", True), ids=ids)
        return _run_ou(records, panel, ids, d, mspec, regs, out, progress, notes)
    series = records[0]
    y, T = series.y, series.steps
    intercept = d.get("intercept", True)
    X_cols = ([np.ones(T)] if intercept else []) + [series.covariates[r] for r in regs]
    X = np.column_stack(X_cols) if X_cols else None
    names = ["intercept"] * bool(intercept) + regs
    censored = series.censored
    limited = bool(np.isfinite(series.lower).any() or np.isfinite(series.upper).any())
    if kind == "censored_ar":
        if X is None:
            raise ValidationError("--model: the censored AR model needs an intercept or regressors")
        options = {"maxiter": mspec["maxiter"]} if "maxiter" in mspec else {}
        res = fit(
            CensoredAR(mspec.get("p", 1)),
            y,
            X=X,
            lower=series.lower,
            upper=series.upper,
            censored=censored,
            progress=progress,
            **options,
        )
    else:
        res = _fit_state_space(mspec, series, X, names, censored if limited else None, progress)
    paths = [res.save(out / "fit.json")]
    summary = res.summary()
    if names:
        summary += ("\nregressors (beta0, beta1, ...): " if kind == "censored_ar" else "\ninputs (columns of D): ") + (
            ", ".join(names)
        )
    paths.append(atomic_write_text(out / "summary.txt", f"{summary}\n{_SUMMARY_MARK}\n"))
    mean, var = res.smooth()
    mean = np.asarray(mean).reshape(T, -1)[:, 0]
    sd = np.sqrt(np.maximum(np.asarray(var).reshape(T, -1)[:, 0], 0.0))
    flags = series.censored
    label = [str(v) for v in series.time] if series.time is not None else [str(i + 1) for i in range(T)]
    rows = [_SERIES_HEADER]
    for i in range(T):
        cells = [label[i], "" if np.isnan(y[i]) else repr(float(y[i])), str(int(flags[i]))]
        cells += [repr(float(v)) for v in (series.lower[i], series.upper[i], mean[i], sd[i])]
        rows.append(",".join(_csv_cell(c) for c in cells))
    paths.append(atomic_write_text(out / "series.csv", "\n".join(rows) + "\n"))
    figure = _figure(out, y, flags, series.lower, series.upper, mean, sd, res, notes)
    if figure is not None:
        paths.append(figure)
    return paths


def _csv_cell(c: str) -> str:
    return '"' + c.replace('"', '""') + '"' if any(ch in c for ch in ',"\n') else c


def _fit_state_space(mspec: dict[str, Any], series: Any, X: np.ndarray | None, names: list[str], censored, progress):
    from ..channels.censoring import Censoring
    from ..models.linear import LinearSystem
    from .fitting import fit

    need = [k for k in ("A", "C", "Q", "R", "x0", "P0") if k not in mspec]
    if need:
        raise ValidationError(f"--model: a state_space model needs the starting matrix {need[0]}")
    estimate = mspec.get("estimate")
    D = mspec.get("D")
    if X is None and D is not None:
        raise ValidationError("--model: [model] D multiplies the intercept and regressors, and [data] has none")
    if X is not None:
        m = np.atleast_2d(np.asarray(mspec["C"], dtype=float)).shape[0]
        if D is None:
            D = np.zeros((m, X.shape[1]))
            if estimate is not None and "D" not in estimate:
                raise ValidationError(
                    f"--model: [data] gives inputs ({', '.join(names)}), whose coefficients D are neither given nor "
                    'estimated: add "D" to estimate, give D, or set intercept = false without regressors'
                )
        if estimate is None:
            estimate = ["A", "C", "Q", "R", "D"]
    templ = LinearSystem(
        A=mspec["A"],
        C=mspec["C"],
        Q=mspec["Q"],
        R=mspec["R"],
        x0=mspec["x0"],
        P0=mspec["P0"],
        **({"D": D} if X is not None else {}),
    )
    cens = None
    if censored is not None:
        cens = Censoring(lower=series.lower[:, None], upper=series.upper[:, None])
    return fit(
        templ,
        series.y,
        u=X,
        censoring=cens,
        censored=None if censored is None else censored[:, None],
        estimate=estimate,
        method=mspec.get("method", "auto"),
        prior=mspec.get("prior", "given"),
        maxiter=mspec.get("maxiter", 500),
        progress=progress,
    )


def _plotting(notes) -> Any:
    """The package's plotting module with matplotlib on its file backend, or None (and a note) without matplotlib."""
    from .._extras import MissingExtraError, require

    try:
        matplotlib = require("matplotlib", extra="plot", feature="the figure of tobitkf fit")
    except MissingExtraError as exc:
        if notes is not None:
            notes(f"skipped fit.png: {exc}")
        return None
    matplotlib.use("Agg")
    from .. import plotting

    return plotting


def _figure(out: Path, y, flags, lower, upper, mean, sd, res, notes) -> Path | None:
    plotting = _plotting(notes)
    if plotting is None:
        return None
    new_figure, save = plotting.new_figure, plotting.save

    t = np.arange(1, y.size + 1)
    fig, ax = new_figure(1, 1, width=10, height=3.8)
    a = ax[0, 0]
    for lim, name in ((lower, "lower limit"), (upper, "upper limit")):
        if np.isfinite(lim).any():
            a.step(t, np.where(np.isfinite(lim), lim, np.nan), where="mid", color="tab:red", lw=0.8, label=name)
    ok = ~flags & ~np.isnan(y)
    a.plot(t[ok], y[ok], ".", color="black", ms=3, label="reading")
    a.plot(t[flags], y[flags], "x", color="tab:red", ms=3, label="censored (at the limit)")
    a.plot(t, mean, color="tab:blue", lw=1.0, label="smoothed latent series")
    a.fill_between(t, mean - 2 * sd, mean + 2 * sd, color="tab:blue", alpha=0.15, lw=0, label="+-2 sd")
    a.set_title(f"{res.model!r}: log-likelihood {res.loglik:.3f}, AIC {res.aic:.2f}", fontsize=9)
    a.legend(fontsize=7, ncol=3)
    return save(fig, out, "fit.png")


def _transformed(rec: Any, how: str, d: dict[str, Any]) -> Any:
    """``rec`` with the logarithm (``how``: "log" or "log10") of its readings and finite limits; refuses, naming
    the line and column, a reading or a limit that is not above 0."""
    if how == "none":
        return rec
    f = np.log if how == "log" else np.log10
    ycol = d.get("y") or "the readings"
    with np.errstate(invalid="ignore"):
        for vals, col, what in (
            (rec.y, ycol, "reading"),
            (rec.lower, d.get("lower") if isinstance(d.get("lower"), str) else ycol, "lower limit"),
            (rec.upper, d.get("upper") if isinstance(d.get("upper"), str) else ycol, "upper limit"),
        ):
            bad = np.isfinite(vals) & ~(vals > 0)
            if bad.any():
                i = int(np.argmax(bad))
                raise ValidationError(
                    f"{rec.where(i, col)}: the {what} {vals[i]:.6g} is not above 0, so it has no logarithm "
                    f"([data] transform = {how!r})"
                )

    def tr(a: np.ndarray) -> np.ndarray:
        out = a.copy()
        ok = np.isfinite(a)
        out[ok] = f(a[ok])
        return out

    units = f"{how}({rec.units})" if rec.units else how
    return dataclasses.replace(rec, y=tr(rec.y), lower=tr(rec.lower), upper=tr(rec.upper), units=units)


def _ou_system(p: int, level: bool, noise_sd: float | None, unit: str, span: float) -> Callable[[np.ndarray], Any]:
    """The map theta -> ContinuousLinearSystem of ``kind = "ou"`` (module docstring): theta = (beta (p,),
    log rate, log sd, [log level sd], [log noise sd]). A rate so fast that ``rate * span`` (``span`` the longest
    gap or lead) exceeds 600 is refused (the search reads it as a log-likelihood of -inf): the residual has
    forgotten everything over any gap long before, and the discretisation's exponentials would overflow."""
    from ..models.continuous import ContinuousLinearSystem

    def model(th: np.ndarray) -> ContinuousLinearSystem:
        rate, sd = np.exp(th[p]), np.exp(th[p + 1])
        if not rate * span <= 600.0:
            raise ValidationError(f"theta: a rate of {rate:.3g} per {unit} forgets within any gap ({span:.3g} {unit})")
        i = p + 2
        tau = 0.0
        if level:
            tau, i = float(np.exp(th[i])), i + 1
        r = float(noise_sd) if noise_sd is not None else float(np.exp(th[i]))
        q = 2.0 * rate * sd * sd
        if level:
            Ac, Qc = [[0.0, 0.0], [0.0, -rate]], [[0.0, 0.0], [0.0, q]]
            C, x0, P0 = [[1.0, 1.0]], [0.0, 0.0], [[tau * tau, 0.0], [0.0, sd * sd]]
        else:
            Ac, Qc, C, x0, P0 = [[-rate]], [[q]], [[1.0]], [0.0], [[sd * sd]]
        D = [list(th[:p])] if p else None
        return ContinuousLinearSystem(Ac, Qc, C, [[r * r]], x0, P0, D=D, unit=unit)

    return model


def _gaps(records: list[Any], unit: str) -> np.ndarray:
    """The gaps between consecutive readings of every subject, in the model's ``unit``."""
    from ..models.continuous import time_values

    out = [np.diff(time_values(r.times, unit=unit)) for r in records if r.steps > 1]
    return np.concatenate(out) if out else np.zeros(0)


def _ou_start(records: list[Any], Xs: list[Any], p: int, level: bool, noise: bool, unit: str) -> np.ndarray:
    """Starting values: least squares of the present readings (censored ones at their limit) on the inputs; the
    residual's spread split between the process, the level and the noise; a memory of five typical gaps."""
    y = np.concatenate([r.y for r in records])
    ok = ~np.isnan(y)
    if p:
        X = np.concatenate(Xs)[ok]
        beta = np.linalg.lstsq(X, y[ok], rcond=None)[0]
        resid = y[ok] - X @ beta
    else:
        beta, resid = np.zeros(0), y[ok]
    s = max(float(np.std(resid)), 1e-3 * max(1.0, float(np.abs(y[ok]).max(initial=0.0))))
    g = _gaps(records, unit)
    g = g[g > 0]
    gap = float(np.median(g)) if g.size else 1.0
    extra = [np.log(0.5 * s)] * level + [np.log(0.4 * s)] * noise
    return np.concatenate([beta, [np.log(1.0 / (5.0 * gap)), np.log(0.8 * s)], extra])


def _time_after(last: Any, h: float, unit: str) -> str:
    """The label of the time ``h`` units after ``last`` (a date, or a number; ``h`` may be 0)."""
    from ..models.continuous import TIME_UNITS, _unit

    if np.asarray(last).dtype.kind != "M":
        return repr(float(last) + h)
    ns = h * TIME_UNITS[_unit(unit)]
    t = np.datetime64(last, "ns") + np.timedelta64(int(round(ns)), "ns")
    whole_days = np.datetime64(last).dtype == np.dtype("datetime64[D]") and ns % 86400e9 == 0
    return str(t.astype("datetime64[D]")) if whole_days else np.datetime_as_string(t, unit="s")


def _run_ou(records, panel, ids, d, mspec, regs, out: Path, progress: Any, notes) -> list[Path]:
    """``kind = "ou"``: the continuous-time fit of one series or a panel, and its files (module docstring)."""
    from .._io import atomic_write_text
    from ..models.continuous import _unit
    from .fitting import fit

    intercept = d.get("intercept", True)
    names = ["intercept"] * bool(intercept) + regs
    p = len(names)
    Xs = panel.u if p else [None] * len(records)
    level, nsd, unit = mspec.get("level", False), mspec.get("noise_sd"), mspec.get("unit", "D")
    theta0 = _ou_start(records, Xs, p, level, nsd is None, unit)
    span = max(float(_gaps(records, unit).max(initial=1.0)), float(mspec.get("forecast", 0)))
    pnames = [f"beta_{n}" for n in names] + ["log_rate", "log_sd"] + ["log_level_sd"] * level
    pnames += ["log_noise_sd"] * (nsd is None)
    options = {"maxiter": mspec["maxiter"]} if "maxiter" in mspec else {}
    res = fit(
        _ou_system(p, level, nsd, unit, span),
        panel,
        theta0=theta0,
        names=pnames,
        align=mspec.get("align", "first"),
        progress=progress,
        **options,
    )
    paths = [res.save(out / "fit.json")]
    est = res.params
    shown = {"s": "seconds", "min": "minutes", "h": "hours", "D": "days", "W": "weeks", "Y": "years"}
    what = [
        f"memory 1/rate {np.exp(-est['log_rate']):.4g} {shown[_unit(unit)]}",
        f"residual sd {np.exp(est['log_sd']):.4g}",
    ]
    if level:
        what.append(f"level sd between subjects {np.exp(est['log_level_sd']):.4g}")
    what.append(f"noise sd {np.exp(est['log_noise_sd']) if nsd is None else nsd:.4g}" + (" (fixed)" if nsd else ""))
    summary = res.summary() + "\n" + "; ".join(what)
    if p:
        summary += "\ninputs (columns of D): " + ", ".join(names)
    if ids is not None:
        summary += f"\n{panel.n_subjects} subjects, {panel.n_obs} readings"
    paths.append(atomic_write_text(out / "summary.txt", f"{summary}\n{_SUMMARY_MARK}\n"))
    fitted = res.model.fitted
    C = fitted.measurement(1)
    smoothed = res.model.smooth(res)
    lead = "" if ids is None else "subject,"
    rows = [lead + _SERIES_HEADER]
    curves = []
    for i, (rec, sm) in enumerate(zip(records, smoothed)):
        mean = np.asarray(sm["reading_mean"])[:, 0]
        sd = np.sqrt(np.maximum(np.einsum("j,tjk,k->t", C[0], sm["cov"], C[0]), 0.0))
        curves.append((mean, sd))
        label = [str(v) for v in rec.time] if rec.time is not None else [str(k + 1) for k in range(rec.steps)]
        for k in range(rec.steps):
            cells = ([str(ids[i])] if ids is not None else []) + [label[k]]
            cells += ["" if np.isnan(rec.y[k]) else repr(float(rec.y[k])), str(int(rec.censored[k]))]
            cells += [repr(float(v)) for v in (rec.lower[k], rec.upper[k], mean[k], sd[k])]
            rows.append(",".join(_csv_cell(c) for c in cells))
    paths.append(atomic_write_text(out / "series.csv", "\n".join(rows) + "\n"))
    H = int(mspec.get("forecast", 0))
    if H:
        held = np.stack([X[-1] for X in Xs if X is not None]) if p else None
        fc = res.model.forecast(res, H, X=held)
        rows = [lead + _FORECAST_HEADER]
        for i, rec in enumerate(records):
            assert rec.times is not None, "kind = 'ou' reads the times"
            for h in range(H):
                cells = ([str(ids[i])] if ids is not None else []) + [_time_after(rec.times[-1], h + 1, unit)]
                cells += [str(h + 1)] + [repr(float(fc[k][i, h, 0])) for k in ("mean", "sd", "lower", "upper")]
                rows.append(",".join(_csv_cell(c) for c in cells))
        paths.append(atomic_write_text(out / "forecast.csv", "\n".join(rows) + "\n"))
    if mspec.get("grid") is not None:
        paths.append(_ou_grid(out, records, ids, res, float(mspec["grid"]), unit, lead))
    figure = _ou_figure(out, records, ids, curves, res, notes)
    if figure is not None:
        paths.append(figure)
    return paths


def _ou_grid(out: Path, records, ids, res, step: float, unit: str, lead: str) -> Path:
    r"""``grid.csv``: each subject's smoothed :math:`D u + \ell + \xi` every ``step`` time units from its first reading
    to its last (the regressors held from the next reading, as the filter holds them), with its standard deviation
    and 95 % band."""
    from .._io import atomic_write_text
    from ..models.continuous import time_values
    from .panel import panel_smooth

    model = res.model
    fitted = model.fitted
    starts = [time_values(r.times, unit=unit) for r in records]
    origin = min(float(t[0]) for t in starts)
    # each subject's readings on the model's clock: since its first reading (align "first") or the earliest one
    spans = [(t - (t[0] if model.align == "first" else origin))[[0, -1]] for t in starts]
    top = max(float(b) for _, b in spans)
    grid = np.arange(0.0, top + step * 1e-9, step)
    sm = panel_smooth(fitted, res.data, likelihood=model.likelihood, align=model.align, start=model.start, grid=grid)
    C = fitted.measurement(1)
    D = None if fitted.D is None else fitted.D.at(1)
    rows = [lead + _GRID_HEADER]
    for i, (rec, (a, b)) in enumerate(zip(records, spans)):
        keep = (grid >= a - 1e-9 * step) & (grid <= b + 1e-9 * step)
        own = grid[keep] - a  # the grid on the subject's own clock (0 at its first reading)
        mean = np.asarray(sm[i]["grid_mean"])[keep] @ C[0]
        if D is not None and res.data.u[i] is not None:
            nxt = np.minimum(np.searchsorted(starts[i] - starts[i][0], own - 1e-9 * step), rec.steps - 1)
            mean = mean + res.data.u[i][nxt] @ D[0]
        sd = np.sqrt(np.maximum(np.einsum("j,tjk,k->t", C[0], np.asarray(sm[i]["grid_cov"])[keep], C[0]), 0.0))
        for h, m_, s_ in zip(own, mean, sd):
            cells = ([str(ids[i])] if ids is not None else []) + [_time_after(rec.times[0], float(h), unit)]
            cells += [repr(float(v)) for v in (m_, s_, m_ - 1.96 * s_, m_ + 1.96 * s_)]
            rows.append(",".join(_csv_cell(c) for c in cells))
    return atomic_write_text(out / "grid.csv", "\n".join(rows) + "\n")


def _ou_figure(out: Path, records, ids, curves, res, notes) -> Path | None:
    """Readings, censored readings at their limits and the smoothed series with a +-2 sd band: one panel, or the
    first six subjects of a panel."""
    plotting = _plotting(notes)
    if plotting is None:
        return None
    new_figure, save = plotting.new_figure, plotting.save

    k = min(len(records), 6)
    cols = 1 if k == 1 else 2 if k <= 4 else 3
    nrows = -(-k // cols)
    fig, ax = new_figure(nrows, cols, width=10, height=3.8 if k == 1 else 2.4 * nrows)
    for j in range(nrows * cols):
        a = ax[j // cols, j % cols]
        if j >= k:
            a.set_visible(False)
            continue
        rec, (mean, sd) = records[j], curves[j]
        t = rec.times
        ok = ~rec.censored & ~np.isnan(rec.y)
        a.fill_between(t, mean - 2 * sd, mean + 2 * sd, color="tab:blue", alpha=0.15, lw=0, label="+-2 sd")
        a.plot(t, mean, color="tab:blue", lw=1.0, label="smoothed")
        a.plot(t[ok], rec.y[ok], ".", color="black", ms=4, label="reading")
        a.plot(t[rec.censored], rec.y[rec.censored], "v", color="tab:red", ms=4, label="censored (at the limit)")
        if ids is not None:
            a.set_title(f"subject {ids[j]}", fontsize=8)
        if j == 0:
            a.legend(fontsize=7, ncol=2)
    fig.suptitle(f"{res.model!r}: log-likelihood {res.loglik:.3f}, AIC {res.aic:.2f}", fontsize=9)
    return save(fig, out, "fit.png")
