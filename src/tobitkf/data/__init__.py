r"""Real censored data shipped with the package, with their provenance.

Five small public data sets (the provenance and licence of each is in ``README.md`` beside this module,
copied unchanged from the project's shared data folder, and returned by :func:`provenance`):

* :func:`load_phosphorus`: 181 monthly log phosphorus concentrations of the West Fork Cedar River at
  Finchford, Iowa (1998-10 .. 2013-10), left-censored at a time-varying laboratory detection limit
  (log 0.1, log 0.05, log 0.02), 28 censored and 7 missing months, with the log water discharge
  ``lQ`` as a known regressor.
* :func:`load_cloud_ceiling`: 716 hourly log cloud-ceiling heights (San Francisco, March 1989),
  right-censored at the instrument's limit log(120), 290 censored (about 40 %) and 3 missing hours.
  8 readings equal the limit and are *not* censored: the indicator ``censored`` tells them apart,
  the limit rule could not.
* :func:`load_arkansas`: ammonia in the Arkansas River (USGS EGRET's example record): 254 irregular
  samples in 22 years, 115 (45 %) left-censored under three detection limits, the daily discharge
  of every day, and EGRET's WRTDS settings for the record (:class:`SampleRecord`).
* :func:`load_hiv_viral_load`: HIV-1 viral load of 72 children after a treatment interruption, 373
  visits, censored below the assay's limit *and* above its upper limit (:class:`ViralLoadPanel`).
* :func:`load_niagara`: 1,2-dichlorobenzene in the Niagara River, 144 about biweekly readings, 21
  left-censored under two detection limits (a :class:`CensoredSeries` with calendar dates).

The phosphorus and cloud-ceiling loaders and :func:`load_niagara` return a :class:`CensoredSeries`: the
reading ``y`` (NaN = missing), the censoring indicator recorded with the data, the limits per reading
and the regressors. Dates are ``numpy.datetime64[D]``.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

import numpy as np

from ._series import CensoredSeries
from .readers import CensoredPanel, CensoredRecord, read_censored, read_censored_panel, write_censored

__all__ = [
    "CensoredSeries",
    "CensoredRecord",
    "CensoredPanel",
    "read_censored",
    "read_censored_panel",
    "write_censored",
    "SampleRecord",
    "ViralLoadPanel",
    "load_phosphorus",
    "load_cloud_ceiling",
    "load_arkansas",
    "load_hiv_viral_load",
    "load_niagara",
    "provenance",
]


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


def _dates(values: list[str]) -> np.ndarray:
    return np.array(values, dtype="datetime64[D]")


@dataclass(frozen=True)
class SampleRecord:
    r"""A sparse water-quality sample record with its daily discharge, in EGRET's interval convention.

    The concentration of sample i lies in ``[conc_low[i], conc_high[i]]``: equal bounds for a measured
    value, ``conc_low`` NaN and ``conc_high`` = the detection limit for a sample below it. These
    arrays go straight into :class:`tobitkf.wrtds.WRTDS`; :meth:`series` gives the log concentration as
    a :class:`CensoredSeries`.

    Attributes
    ----------
    name : str
    date : (n,) datetime64[D] ndarray
        Sample dates.
    q : (n,) ndarray
        Daily mean discharge on each sample's day (as stored in the EGRET object).
    conc_low, conc_high : (n,) ndarray
        Bounds of the concentration (mg/L); ``conc_low`` NaN: no lower bound (left-censored).
    uncensored : (n,) bool ndarray
        True for a measured value (EGRET's ``Uncen``).
    daily_date : (D,) datetime64[D] ndarray
        Every day of the discharge record.
    daily_q : (D,) ndarray
        Daily mean discharge.
    egret_info : dict
        The settings stored in the EGRET object (``windowY``, ``windowQ``, ``windowS``, ``minNumObs``,
        ``minNumUncen``, ``edgeAdjust``, site and parameter names, ...).
    description : str
    """

    name: str
    date: np.ndarray
    q: np.ndarray
    conc_low: np.ndarray
    conc_high: np.ndarray
    uncensored: np.ndarray
    daily_date: np.ndarray
    daily_q: np.ndarray
    egret_info: dict[str, Any] = field(default_factory=dict)
    description: str = ""

    @property
    def num_samples(self) -> int:
        """Number of samples n."""
        return int(self.date.shape[0])

    @property
    def censored(self) -> np.ndarray:
        """(n,) bool: samples below their detection limit."""
        return ~self.uncensored

    @property
    def detection_limit(self) -> np.ndarray:
        """(n,) detection limit of each censored sample (``conc_high``), NaN for a measured one (its limit
        is not recorded)."""
        return np.where(self.uncensored, np.nan, self.conc_high)

    @property
    def period(self) -> tuple[np.datetime64, np.datetime64]:
        """First and last day of the daily discharge record (the ends EGRET's estimation uses)."""
        return self.daily_date[0], self.daily_date[-1]

    def series(self) -> CensoredSeries:
        r"""The natural-log concentration as a :class:`CensoredSeries`, one reading per sample.

        ``y`` is :math:`\ln c` (the log detection limit for a censored sample), ``lower`` the log
        detection limit on censored samples and ``-inf`` on measured ones (the limit in force on those
        days is not recorded: pass ``censored`` as the indicator rather than relying on the limit
        rule), ``upper`` ``+inf``. A sample known only to lie between two finite bounds (``0 <`` ``conc_low``
        ``<`` ``conc_high``) is an interval reading: ``lower``/``upper`` the log bounds, ``y`` their midpoint.
        Covariate ``"lnQ"``: log discharge on the sample's day.
        """
        cens = self.censored
        y = np.log(self.conc_high)
        with np.errstate(invalid="ignore", divide="ignore"):
            iv = cens & (self.conc_low > 0) & (self.conc_low < self.conc_high)
            ln_low = np.log(np.where(iv, self.conc_low, 1.0))
        lower = np.where(iv, ln_low, np.where(cens, y, -np.inf))
        upper = np.where(iv, y, np.inf)
        y = np.where(iv, 0.5 * (ln_low + y), y)
        return CensoredSeries(
            name=self.name,
            y=y,
            censored=cens.copy(),
            lower=lower,
            upper=upper,
            covariates={"lnQ": np.log(self.q)},
            time=self.date.astype(str),
            description=self.description,
            times=self.date.copy(),
        )


def load_arkansas() -> SampleRecord:
    r"""Ammonia (as N) in the Arkansas River at Murray Lock and Dam, Arkansas (USGS EGRET's ``Arkansas_eList``).

    254 samples (1990-09-18 .. 2012-09-25, 1 to 105 days apart), 115 of them (45 %) left-censored under
    three detection limits over time (0.05, 0.005 and 0.03 mg/L); discharge on every day of
    1989-10-01 .. 2012-09-30 (8401 days); ``egret_info`` holds EGRET's WRTDS settings for this record
    (e.g. ``windowQ`` 1 and ``minNumUncen`` 127). Public domain / CC0 1.0. Provenance: :func:`provenance`.

    Examples
    --------
    >>> from tobitkf.data import load_arkansas
    >>> rec = load_arkansas()
    >>> rec.num_samples, int(rec.censored.sum()), sorted(set(rec.detection_limit[rec.censored].tolist()))
    (254, 115, [0.005, 0.03, 0.05])
    >>> rec.daily_date.shape, str(rec.period[0])
    ((8401,), '1989-10-01')
    """
    rows = _rows("arkansas_ammonia_samples.csv")
    daily = _rows("arkansas_daily_discharge.csv")
    info = json.loads(resources.files(__name__).joinpath("arkansas_egret_info.json").read_text(encoding="utf-8"))
    return SampleRecord(
        name="arkansas-ammonia",
        date=_dates([r["Date"] for r in rows]),
        q=np.array([_num(r["Q"]) for r in rows]),
        conc_low=np.array([_num(r["ConcLow"]) for r in rows]),
        conc_high=np.array([_num(r["ConcHigh"]) for r in rows]),
        uncensored=np.array([r["Uncen"].strip() == "1" for r in rows]),
        daily_date=_dates([r["Date"] for r in daily]),
        daily_q=np.array([_num(r["Q"]) for r in daily]),
        egret_info=info,
        description="ammonia (as N, mg/L), Arkansas River at Murray Lock and Dam (USGS 07263450), 254 samples "
        "1990-2012, left-censored under three detection limits, with daily discharge (EGRET, CC0)",
    )


@dataclass(frozen=True)
class ViralLoadPanel:
    r"""A panel of viral-load visits, long format (one row per visit, in the file's order).

    Attributes
    ----------
    patient : (n,) str ndarray
        Patient id of each visit.
    day : (n,) int ndarray
        Days after the treatment interruption (negative: before).
    followup : (n,) ndarray
        Scheduled follow-up month.
    rna : (n,) ndarray
        Viral load (copies/mL); for a censored visit the limit; NaN: missing.
    censored : (n,) int ndarray
        0 measured, 1 below the assay's lower limit (50 or 400), 2 above its upper limit (750000).
    description : str
    """

    patient: np.ndarray
    day: np.ndarray
    followup: np.ndarray
    rna: np.ndarray
    censored: np.ndarray
    description: str = ""

    @property
    def num_visits(self) -> int:
        """Number of rows n."""
        return int(self.patient.shape[0])

    @property
    def patients(self) -> np.ndarray:
        """The patient ids in order of first appearance."""
        _, first = np.unique(self.patient, return_index=True)
        return self.patient[np.sort(first)]

    @property
    def missing(self) -> np.ndarray:
        """(n,) bool: visits without a reading."""
        return np.isnan(self.rna)

    @property
    def left(self) -> np.ndarray:
        """(n,) bool: below the lower limit of quantification."""
        return (self.censored == 1) & ~self.missing

    @property
    def right(self) -> np.ndarray:
        """(n,) bool: above the upper limit of quantification."""
        return (self.censored == 2) & ~self.missing

    @property
    def duplicate(self) -> np.ndarray:
        """(n,) bool: the visit repeats an earlier row of the same patient (same day, value and censoring)
        under another follow-up code, as distributed; a model that keeps both counts one measurement twice."""
        seen: set[tuple[str, int, float, int]] = set()
        out = np.zeros(self.num_visits, dtype=bool)
        for i in range(self.num_visits):
            key = (str(self.patient[i]), int(self.day[i]), float(self.rna[i]), int(self.censored[i]))
            if not np.isnan(self.rna[i]) and key in seen:
                out[i] = True
            seen.add(key)
        return out

    def log10_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        r"""(low, high), each (n,): what is known of :math:`\log_{10}` of each visit's viral load.

        Measured: both the value; below the limit: ``(-inf, log10 limit)``; above: ``(log10 limit,
        inf)``; missing: NaN, NaN.
        """
        v = np.log10(self.rna)
        low = np.where(self.censored == 1, -np.inf, v)
        high = np.where(self.censored == 2, np.inf, v)
        miss = self.missing
        return np.where(miss, np.nan, low), np.where(miss, np.nan, high)

    def rows(self, patient: str) -> np.ndarray:
        """Row indices of one patient's visits, ordered by day.

        Raises
        ------
        ValidationError
            For an unknown patient id.
        """
        idx = np.flatnonzero(self.patient == patient)
        if idx.size == 0:
            from .._validation import ValidationError

            raise ValidationError(f"patient: unknown id {patient!r}")
        return idx[np.argsort(self.day[idx], kind="stable")]


def load_hiv_viral_load() -> ViralLoadPanel:
    r"""HIV-1 RNA viral load after an unstructured treatment interruption (lmec's ``UTIdata``), a panel.

    72 perinatally infected children and adolescents (Saitoh et al. 2008), 373 visits, 1 to 8 per
    patient at irregular days; 11 visits missing, 26 below the assay's lower limit (50 or 400
    copies/mL) and 7 above its upper limit (750000): censoring on both sides in one series. 15 rows
    repeat another row of the same patient (:attr:`ViralLoadPanel.duplicate`). GPL-2. Provenance:
    :func:`provenance`.

    Examples
    --------
    >>> from tobitkf.data import load_hiv_viral_load
    >>> d = load_hiv_viral_load()
    >>> d.num_visits, d.patients.size, int(d.left.sum()), int(d.right.sum()), int(d.missing.sum())
    (373, 72, 26, 7, 11)
    """
    rows = _rows("hiv_viral_load_uti.csv")
    return ViralLoadPanel(
        patient=np.array([r["patient"] for r in rows]),
        day=np.array([int(r["days_after_ti"]) for r in rows]),
        followup=np.array([_num(r["followup"]) for r in rows]),
        rna=np.array([_num(r["rna_copies_per_ml"]) for r in rows]),
        censored=np.array([int(r["censored"]) for r in rows]),
        description="HIV-1 RNA viral load (copies/mL) after treatment interruption, 72 children (lmec UTIdata), "
        "censored below 50/400 and above 750000",
    )


def load_niagara(*, log: bool = False) -> CensoredSeries:
    r"""1,2-dichlorobenzene in the Niagara River at Fort Erie, Ontario, 2001-03-01 .. 2007-03-22 (cents).

    144 readings about two weeks apart, 21 left-censored at the detection limit in force (``lower``:
    0.214 ng/L, then 0.0878 from the reading of 2005-04-07 on; the distribution's notes date the change
    2005-03-24, the date of the last reading at 0.214); a censored reading holds its limit. ``times`` are the
    calendar dates (day 1 = 2001-03-01), ``time`` the recorded day numbers, covariate ``"day"`` the
    same as numbers. GPL >= 2. Provenance: :func:`provenance`.

    Parameters
    ----------
    log : bool
        Return the natural logarithm of the readings and limits instead of ng/L.

    Examples
    --------
    >>> from tobitkf.data import load_niagara
    >>> d = load_niagara()
    >>> d.steps, int(d.censored.sum()), sorted(set(d.lower.tolist())), str(d.times[0])
    (144, 21, [0.0878, 0.214], '2001-03-01')
    """
    rows = _rows("niagara_dichlorobenzene.csv")
    y = np.array([_num(r["concentration"]) for r in rows])
    limit = np.array([_num(r["limit"]) for r in rows])
    day = np.array([int(r["day"]) for r in rows])
    if log:
        y, limit = np.log(y), np.log(limit)
    return CensoredSeries(
        name="niagara-dichlorobenzene",
        y=y,
        censored=np.array([r["censored"].strip() == "1" for r in rows]),
        lower=limit,
        upper=np.full(y.size, np.inf),
        covariates={"day": day.astype(float)},
        time=np.array([r["day"] for r in rows]),
        description="1,2-dichlorobenzene (" + ("log " if log else "") + "ng/L), Niagara River at Fort Erie "
        "(Environment Canada), about biweekly 2001-2007, left-censored at 0.214 then 0.0878 ng/L",
        times=np.datetime64("2001-03-01") + (day - 1).astype("timedelta64[D]"),
    )
