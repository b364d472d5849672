r"""Real censored time series shipped with the package, with their provenance.

Two small public data sets (the provenance is in ``README.md`` beside this module, copied unchanged
from the project's shared data folder; the readings are public-domain US agency data, distributed with
the R package ARCensReg 3.0.2):

* :func:`load_phosphorus`: 181 monthly log phosphorus concentrations of the West Fork Cedar River at
  Finchford, Iowa (1998-10 .. 2013-10), left-censored at a time-varying laboratory detection limit
  (log 0.1, log 0.05, log 0.02), 28 censored and 7 missing months, with the log water discharge
  ``lQ`` as a known regressor.
* :func:`load_cloud_ceiling`: 716 hourly log cloud-ceiling heights (San Francisco, March 1989),
  right-censored at the instrument's limit log(120), 290 censored (about 40 %) and 3 missing hours.
  8 readings equal the limit and are *not* censored: the indicator ``censored`` tells them apart,
  the limit rule could not.

Each loader returns a :class:`CensoredSeries`: the reading ``y`` (NaN = missing), the censoring
indicator recorded with the data, the limits per reading and the regressors.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

import numpy as np

__all__ = ["CensoredSeries", "load_phosphorus", "load_cloud_ceiling", "provenance"]


@dataclass(frozen=True)
class CensoredSeries:
    r"""One censored scalar time series as recorded.

    Attributes
    ----------
    name : str
        Short name of the data set.
    y : (T,) ndarray
        Readings; a censored reading holds its limit; NaN marks a missing reading.
    censored : (T,) bool ndarray
        The censoring indicator recorded with the data (False for missing readings).
    lower, upper : (T,) ndarray
        Censoring limits of each reading (``-inf`` / ``+inf``: no limit on that side).
    covariates : dict of str to (T,) ndarray
        Known regressors (e.g. ``"lQ"``, the log discharge).
    time : (T,) ndarray of str
        Time labels as recorded.
    description : str
        One line on what the series is.
    """

    name: str
    y: np.ndarray
    censored: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    covariates: dict[str, np.ndarray] = field(default_factory=dict)
    time: np.ndarray | None = None
    description: str = ""

    @property
    def steps(self) -> int:
        """Number of readings T."""
        return int(self.y.shape[0])

    @property
    def missing(self) -> np.ndarray:
        """(T,) bool: readings that are missing."""
        return np.isnan(self.y)

    def censoring(self):
        """The limits as a :class:`~tobitkf.Censoring` of one channel, ``(T, 1)``."""
        from ..channels.censoring import Censoring

        return Censoring(lower=self.lower[:, None], upper=self.upper[:, None])

    def design(self, *names: str, intercept: bool = True) -> np.ndarray:
        """The regressor matrix ``(T, l)``: a column of ones (when ``intercept``) and the named covariates."""
        cols = [np.ones(self.steps)] if intercept else []
        for nm in names:
            if nm not in self.covariates:
                from .._validation import ValidationError

                raise ValidationError(f"names: unknown covariate {nm!r}; known: {', '.join(self.covariates) or 'none'}")
            cols.append(self.covariates[nm])
        return np.column_stack(cols) if cols else np.zeros((self.steps, 0))


def _rows(filename: str) -> list[dict[str, str]]:
    text = resources.files(__name__).joinpath(filename).read_text(encoding="utf-8")
    return list(csv.DictReader(text.splitlines()))


def _num(s: str) -> float:
    return float(s) if s not in ("", "NA") else np.nan


def provenance() -> str:
    """The provenance notes shipped with the data (``README.md``)."""
    return resources.files(__name__).joinpath("README.md").read_text(encoding="utf-8")


def load_phosphorus() -> CensoredSeries:
    r"""Monthly log phosphorus concentration of the West Fork Cedar River (Iowa), 1998-10 .. 2013-10.

    181 readings; 28 left-censored at the month's detection limit (``lower``: log 0.1, log 0.05 or
    log 0.02); 7 missing (2008-09 .. 2009-03, for which the file has no limit: the previous month's
    limit is used, which does not matter for a missing reading). Regressor ``"lQ"``: log water
    discharge (cubic feet per second). The model of the literature is
    :math:`lP_t = \beta_0 + \beta_1 lQ_t + \xi_t`, :math:`\xi_t` AR(1) or AR(2), stationary from the
    start. Provenance: :func:`provenance`.

    Examples
    --------
    >>> from tobitkf.data import load_phosphorus
    >>> d = load_phosphorus()
    >>> d.steps, int(d.censored.sum()), int(d.missing.sum())
    (181, 28, 7)
    """
    rows = _rows("phosphorus.csv")
    y = np.array([_num(r["lP"]) for r in rows])
    cens = np.array([r["cc"].strip() == "1" for r in rows]) & ~np.isnan(y)
    lcl = np.array([_num(r["lcl"]) for r in rows])
    for i in range(lcl.size):  # missing months have no limit: carry the last one
        if np.isnan(lcl[i]):
            lcl[i] = lcl[i - 1] if i > 0 else -np.inf
    lq = np.array([_num(r["lQ"]) for r in rows])
    return CensoredSeries(
        name="phosphorus",
        y=y,
        censored=cens,
        lower=lcl,
        upper=np.full(y.size, np.inf),
        covariates={"lQ": lq},
        time=np.array([r["time"] for r in rows]),
        description="log phosphorus concentration, West Fork Cedar River at Finchford (Iowa DNR, "
        "USGS discharge), monthly 1998-10..2013-10, left-censored at the detection limit",
    )


def load_cloud_ceiling() -> CensoredSeries:
    r"""Hourly log cloud-ceiling height (hundreds of feet), San Francisco, March 1989 (NCAR).

    716 readings; 290 right-censored at the instrument's limit log(120) (``upper``); 3 missing; 8
    readings equal to the limit are recorded as *not* censored. The model of the literature (Park,
    Genton & Ghosh 2007): :math:`y_t = \mu + \xi_t`, :math:`\xi_t` AR(1). Provenance: :func:`provenance`.

    Examples
    --------
    >>> from tobitkf.data import load_cloud_ceiling
    >>> d = load_cloud_ceiling()
    >>> d.steps, int(d.censored.sum()), int(d.missing.sum())
    (716, 290, 3)
    """
    rows = _rows("cloudceiling.csv")
    y = np.array([_num(r["y"]) for r in rows])
    cens = np.array([r["cc"].strip() == "1" for r in rows]) & ~np.isnan(y)
    limit = float(np.log(120.0))
    return CensoredSeries(
        name="cloud-ceiling",
        y=y,
        censored=cens,
        lower=np.full(y.size, -np.inf),
        upper=np.full(y.size, limit),
        covariates={},
        time=np.array([r["t"] for r in rows]),
        description="log cloud ceiling (hundreds of feet), San Francisco, hourly, March 1989 (NCAR), "
        "right-censored at log(120)",
    )
