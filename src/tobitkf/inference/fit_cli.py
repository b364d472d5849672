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
``{1 = "left", 2 = "right"}``), ``duplicates`` (``"error"`` or ``"drop"``), ``encoding``.

**Blank limits.** A blank limit cell means that no limit was recorded for that reading (``-inf`` /
``+inf``, as :func:`tobitkf.fit` takes it): harmless for an uncensored or missing reading; a censored
reading with a blank limit is refused, naming its line and column.

For a linear state-space model fitted by EM (``kind = "state_space"``): the starting matrices ``A``,
``C``, ``Q``, ``R``, ``x0``, ``P0`` (nested arrays), ``estimate = ["Q", "R"]``, optionally
``prior = "stationary"``, ``method = "direct"`` and ``maxiter``. The intercept and regressors enter as
known inputs through ``D`` (``y_k = C x_k + D u_k + v_k``), starting from ``D`` (default zeros) and
estimated (``"D"`` is added to ``estimate`` when ``estimate`` is not given; with ``estimate`` given,
either list ``"D"``, give a fixed ``D``, or set ``intercept = false`` and no regressors).

It writes into ``--out``: ``fit.json`` (:meth:`~tobitkf.inference.fitting.FitResult.save`),
``summary.txt``, ``series.csv`` (the readings, the indicator, the limits and the smoothed latent series
with its standard deviation) and ``fit.png`` (readings, limits, smoothed series; skipped with a note
when matplotlib is not installed). Files of those names that tobitkf did not write are not replaced
unless ``force`` is set.
"""

from __future__ import annotations

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
}
_AR_KEYS = {"kind", "p", "maxiter"}
_SS_KEYS = {"kind", "A", "C", "Q", "R", "x0", "P0", "D", "estimate", "prior", "method", "maxiter"}
_MODEL_KEYS = _AR_KEYS | _SS_KEYS
_SERIES_HEADER = "time,y,censored,lower,upper,smoothed,smoothed_sd"
_SUMMARY_MARK = "(written by tobitkf fit)"
#: the files ``tobitkf fit`` writes, each with the marker that shows tobitkf wrote it
OUTPUTS: dict[str, tuple[bytes, ...]] = {
    "fit.json": (b'"format": "tobitkf-fit"',),
    "summary.txt": (_SUMMARY_MARK.encode(),),
    "series.csv": ((_SERIES_HEADER + "\n").encode(),),
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
    from ..data.readers import FORMATS

    for k in ("y", "censored", "low", "high", "cens", "time", "encoding"):
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
    codes = d.get("flag_codes")
    if codes is not None and not (isinstance(codes, dict) and all(isinstance(v, str) for v in codes.values())):
        raise ValidationError(f'{_key("data", "flag_codes")}: expected a table such as {{1 = "left"}}, got {codes!r}')


def _check_model(m: dict[str, Any]) -> None:
    from .._validation import check_int

    kind = m.get("kind", "censored_ar")
    if kind not in ("censored_ar", "state_space"):
        raise ValidationError(f"--model: unknown model kind {kind!r}; expected 'censored_ar' or 'state_space'")
    allowed = _AR_KEYS if kind == "censored_ar" else _SS_KEYS
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
    from ..data.readers import FORMATS, read_censored
    from .censored_ar import CensoredAR
    from .fitting import fit

    if format is not None and format not in FORMATS:
        raise ValidationError(f"--format: expected one of {', '.join(FORMATS)}, got {format!r}")
    spec = read_spec(as_path(model_path, "--model"))
    out = check_writable_dir(out, "--out")
    check_outputs(out, force=force)
    d, mspec = spec["data"], spec["model"]
    regs = list(d.get("regressors", []))
    lines = _progress_lines(progress)
    series = read_censored(
        as_path(csv_path, "FILE"),
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
    )
    y, T = series.y, series.steps
    for r in regs:
        miss = np.isnan(series.covariates[r])
        if miss.any():
            raise ValidationError(
                f"FILE: regressor column {r!r} is blank at reading {int(np.argmax(miss)) + 1}; regressors must be "
                "known for every reading"
            )
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValidationError(f"--out: cannot create the folder {out} ({exc.strerror or exc})") from None
    intercept = d.get("intercept", True)
    X_cols = ([np.ones(T)] if intercept else []) + [series.covariates[r] for r in regs]
    X = np.column_stack(X_cols) if X_cols else None
    names = ["intercept"] * bool(intercept) + regs
    censored = series.censored
    limited = bool(np.isfinite(series.lower).any() or np.isfinite(series.upper).any())
    kind = mspec.get("kind", "censored_ar")
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


def _figure(out: Path, y, flags, lower, upper, mean, sd, res, notes) -> Path | None:
    from .._extras import MissingExtraError, require

    try:
        matplotlib = require("matplotlib", extra="plot", feature="the figure of tobitkf fit")
    except MissingExtraError as exc:
        if notes is not None:
            notes(f"skipped fit.png: {exc}")
        return None
    matplotlib.use("Agg")
    from ..plotting import new_figure, save

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
