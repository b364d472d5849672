r"""``tobitkf fit FILE.csv --model MODEL.toml``: fit a model to a user's own censored series.

The model file (TOML) names the columns and the model::

    [data]
    y = "lP"                 # the readings (empty or NA = missing)
    censored = "cc"          # optional: the recorded indicator (1/0 or true/false); default the limit rule
    lower = "lcl"            # optional: a column or a number (left-censoring limit)
    upper = 4.787            # optional: a column or a number (right-censoring limit)
    regressors = ["lQ"]      # optional: columns of known regressors
    intercept = true         # default true
    time = "time"            # optional: a label column copied to the series file

    [model]
    kind = "censored_ar"     # regression with AR(p) errors, exact ML (the default)
    p = 1

or, for a linear state-space model fitted by EM (``kind = "state_space"``): the starting matrices ``A``,
``C``, ``Q``, ``R``, ``x0``, ``P0`` (nested arrays), ``estimate = ["Q", "R"]``, optionally
``prior = "stationary"`` and ``method = "direct"``.

It writes into ``--out``: ``fit.json`` (:meth:`~tobitkf.inference.fitting.FitResult.save`),
``summary.txt``, ``series.csv`` (the readings, the indicator, the limits and the smoothed latent series
with its standard deviation) and ``fit.png`` (readings, limits, smoothed series).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import numpy as np

from .._validation import ValidationError

__all__ = ["run_fit", "read_spec", "read_columns"]

_DATA_KEYS = {"y", "censored", "lower", "upper", "regressors", "intercept", "time"}
_MODEL_KEYS = {"kind", "p", "A", "C", "Q", "R", "x0", "P0", "estimate", "prior", "method", "maxiter"}


def read_spec(path: Path) -> dict[str, Any]:
    """The model file as a dict; ``ValidationError`` naming the file and the key on anything unknown."""
    import tomllib

    try:
        spec = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise ValidationError(f"--model: cannot read {path} ({exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValidationError(f"--model: {path} is not valid TOML ({exc})") from None
    for section, keys in (("data", _DATA_KEYS), ("model", _MODEL_KEYS)):
        part = spec.get(section, {})
        if not isinstance(part, dict):
            raise ValidationError(f"--model: [{section}] must be a table")
        bad = sorted(set(part) - keys)
        if bad:
            raise ValidationError(f"--model: unknown key {bad[0]!r} in [{section}]; expected {', '.join(sorted(keys))}")
    bad = sorted(set(spec) - {"data", "model"})
    if bad:
        raise ValidationError(f"--model: unknown section [{bad[0]}]; expected [data] and [model]")
    if "y" not in spec.get("data", {}):
        raise ValidationError('--model: [data] needs y = "<column of the readings>"')
    return spec


def read_columns(path: Path) -> dict[str, list[str]]:
    """The CSV's columns as lists of strings (header row required)."""
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as exc:
        raise ValidationError(f"FILE: cannot read {path} ({exc})") from None
    if not rows:
        raise ValidationError(f"FILE: {path} has no data rows (a header row and one row per reading expected)")
    return {k: [r[k] for r in rows] for k in rows[0]}


def _column(cols: dict[str, list[str]], name: str, what: str) -> np.ndarray:
    if name not in cols:
        raise ValidationError(
            f"--model: {what} names the column {name!r}, which FILE does not have (columns: {', '.join(cols)})"
        )
    out = []
    for i, v in enumerate(cols[name]):
        v = v.strip()
        if v in ("", "NA", "NaN", "nan"):
            out.append(np.nan)
            continue
        try:
            out.append(float(v))
        except ValueError:
            raise ValidationError(f"FILE: column {name!r} row {i + 2}: expected a number, got {v!r}") from None
    return np.array(out)


def _limit(cols, spec_value, what: str, T: int, default: float) -> np.ndarray:
    if spec_value is None:
        return np.full(T, default)
    if isinstance(spec_value, str):
        arr = _column(cols, spec_value, what)
        # a missing reading's limit does not matter: carry the previous one (or none)
        for i in range(T):
            if np.isnan(arr[i]):
                arr[i] = arr[i - 1] if i > 0 else default
        return arr
    if isinstance(spec_value, (int, float)) and not isinstance(spec_value, bool):
        return np.full(T, float(spec_value))
    raise ValidationError(f"--model: {what} must be a column name or a number, got {spec_value!r}")


def _indicator(cols, name: str, T: int) -> np.ndarray:
    if name not in cols:
        raise ValidationError(f"--model: censored names the column {name!r}, which FILE does not have")
    out = np.zeros(T, dtype=bool)
    for i, v in enumerate(cols[name]):
        s = v.strip().lower()
        if s in ("1", "true", "yes", "1.0"):
            out[i] = True
        elif s in ("0", "false", "no", "0.0", "", "na"):
            out[i] = False
        else:
            raise ValidationError(f"FILE: column {name!r} row {i + 2}: expected 1/0 or true/false, got {v!r}")
    return out


def run_fit(csv_path: str | Path, model_path: str | Path, out: str | Path, *, progress: Any = None) -> list[Path]:
    """Read FILE and MODEL, fit, write the outputs; returns the written paths.

    Raises
    ------
    ValidationError
        Unreadable or inconsistent inputs (each message names the file and the key or column).
    """
    from .._io import atomic_write_text
    from ..channels.censoring import Censoring
    from ..models.linear import LinearSystem
    from .censored_ar import CensoredAR
    from .fitting import fit

    spec = read_spec(Path(model_path))
    cols = read_columns(Path(csv_path))
    dspec, mspec = spec["data"], spec.get("model", {})
    y = _column(cols, dspec["y"], "y")
    T = y.size
    lower = _limit(cols, dspec.get("lower"), "lower", T, -math.inf)
    upper = _limit(cols, dspec.get("upper"), "upper", T, math.inf)
    censored = _indicator(cols, dspec["censored"], T) if dspec.get("censored") else None
    if censored is not None:
        censored = censored & ~np.isnan(y)
    regs = dspec.get("regressors", [])
    if not isinstance(regs, list) or not all(isinstance(r, str) for r in regs):
        raise ValidationError("--model: regressors must be a list of column names")
    X_cols = ([np.ones(T)] if dspec.get("intercept", True) else []) + [_column(cols, r, "regressors") for r in regs]
    for r, c in zip(regs, X_cols[-len(regs) :] if regs else []):
        if np.isnan(c).any():
            raise ValidationError(f"FILE: regressor column {r!r} has missing values")
    X = np.column_stack(X_cols) if X_cols else None
    kind = mspec.get("kind", "censored_ar")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if kind == "censored_ar":
        p = mspec.get("p", 1)
        if X is None:
            raise ValidationError("--model: the censored AR model needs an intercept or regressors")
        res = fit(
            CensoredAR(int(p) if isinstance(p, int) else p),
            y,
            X=X,
            lower=lower,
            upper=upper,
            censored=censored,
            progress=progress,
        )
        names = ["intercept"] * bool(dspec.get("intercept", True)) + regs
    elif kind == "state_space":
        need = [k for k in ("A", "C", "Q", "R", "x0", "P0") if k not in mspec]
        if need:
            raise ValidationError(f"--model: a state_space model needs the starting matrix {need[0]}")
        templ = LinearSystem(A=mspec["A"], C=mspec["C"], Q=mspec["Q"], R=mspec["R"], x0=mspec["x0"], P0=mspec["P0"])
        cens = None
        if np.isfinite(lower).any() or np.isfinite(upper).any():
            cens = Censoring(lower=lower[:, None], upper=upper[:, None])
        res = fit(
            templ,
            y,
            censoring=cens,
            censored=None if censored is None else censored[:, None],
            estimate=mspec.get("estimate"),
            method=mspec.get("method", "auto"),
            prior=mspec.get("prior", "given"),
            maxiter=int(mspec.get("maxiter", 500)),
            progress=progress,
        )
        names = []
    else:
        raise ValidationError(f"--model: unknown model kind {kind!r}; expected 'censored_ar' or 'state_space'")
    paths = [res.save(out / "fit.json")]
    summary = res.summary()
    if names:
        summary += "\nregressors (beta0, beta1, ...): " + ", ".join(names)
    paths.append(atomic_write_text(out / "summary.txt", summary + "\n"))
    mean, var = res.smooth()
    mean = np.asarray(mean).reshape(T, -1)[:, 0]
    sd = np.sqrt(np.maximum(np.asarray(var).reshape(T, -1)[:, 0], 0.0))
    side = res.data.side if hasattr(res.data, "side") else None
    flags = (side != 0) if side is not None else (censored if censored is not None else np.zeros(T, bool))
    label = cols[dspec["time"]] if dspec.get("time") in cols else [str(i + 1) for i in range(T)]
    lines = ["time,y,censored,lower,upper,smoothed,smoothed_sd"]
    for i in range(T):
        lines.append(
            ",".join(
                [
                    label[i],
                    "" if np.isnan(y[i]) else repr(float(y[i])),
                    str(int(flags[i])),
                    repr(float(lower[i])),
                    repr(float(upper[i])),
                    repr(float(mean[i])),
                    repr(float(sd[i])),
                ]
            )
        )
    paths.append(atomic_write_text(out / "series.csv", "\n".join(lines) + "\n"))
    paths.append(_figure(out, y, flags, lower, upper, mean, sd, res))
    return paths


def _figure(out: Path, y, flags, lower, upper, mean, sd, res) -> Path:
    from .._extras import require

    matplotlib = require("matplotlib", extra="plot", feature="the figure of tobitkf fit")
    matplotlib.use("Agg")
    from ..plotting import new_figure, save

    t = np.arange(1, y.size + 1)
    fig, ax = new_figure(1, 1, width=10, height=3.8)
    a = ax[0, 0]
    for lim, name in ((lower, "lower limit"), (upper, "upper limit")):
        if np.isfinite(lim).any():
            a.step(t, lim, where="mid", color="tab:red", lw=0.8, label=name)
    ok = ~flags & ~np.isnan(y)
    a.plot(t[ok], y[ok], ".", color="black", ms=3, label="reading")
    a.plot(t[flags], y[flags], "x", color="tab:red", ms=3, label="censored (at the limit)")
    a.plot(t, mean, color="tab:blue", lw=1.0, label="smoothed latent series")
    a.fill_between(t, mean - 2 * sd, mean + 2 * sd, color="tab:blue", alpha=0.15, lw=0, label="+-2 sd")
    a.set_title(f"{res.model!r}: log-likelihood {res.loglik:.3f}, AIC {res.aic:.2f}", fontsize=9)
    a.legend(fontsize=7, ncol=3)
    return save(fig, out, "fit.png")
