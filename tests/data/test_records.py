"""The shipped records (tobitkf.data): the counts, dates and limits their provenance notes state (the
numbers below are those of the data README, not read back from the loaders), and the shapes and
conventions the loaders document."""

from __future__ import annotations

import json
from importlib import resources

import numpy as np
import pytest

import tobitkf as tk
from tobitkf.data import (
    CensoredSeries,
    load_arkansas,
    load_hiv_viral_load,
    load_niagara,
    provenance,
)


def test_arkansas_matches_its_provenance_note():
    rec = load_arkansas()
    n = 254
    assert rec.num_samples == n
    for arr in (rec.date, rec.q, rec.conc_low, rec.conc_high, rec.uncensored):
        assert arr.shape == (n,)
    assert rec.date.dtype == np.dtype("datetime64[D]") and rec.daily_date.dtype == np.dtype("datetime64[D]")
    assert str(rec.date[0]) == "1990-09-18" and str(rec.date[-1]) == "2012-09-25"
    gaps = np.diff(rec.date).astype(int)
    assert gaps.min() == 1 and gaps.max() == 105 and np.median(gaps) == 28
    # 115 censored (45 %) under three limits: 0.05 (1990-1997), 0.005 (1999-2002), 0.03 (2002-2012)
    cens = rec.censored
    assert int(cens.sum()) == 115 and round(100 * cens.mean()) == 45
    years = rec.date.astype("datetime64[Y]").astype(int) + 1970
    lim = rec.detection_limit
    assert set(lim[cens].tolist()) == {0.05, 0.005, 0.03}
    assert np.all((years[cens & (lim == 0.05)] >= 1990) & (years[cens & (lim == 0.05)] <= 1997))
    assert np.all((years[cens & (lim == 0.005)] >= 1999) & (years[cens & (lim == 0.005)] <= 2002))
    assert np.all((years[cens & (lim == 0.03)] >= 2002) & (years[cens & (lim == 0.03)] <= 2012))
    # interval convention: equal bounds when measured, no lower bound when censored
    np.testing.assert_array_equal(rec.conc_low[rec.uncensored], rec.conc_high[rec.uncensored])
    assert np.all(np.isnan(rec.conc_low[cens]))
    assert np.all(np.isnan(lim[rec.uncensored]))
    # the daily record: every day of 1989-10-01 .. 2012-09-30, and the sample's Q is that day's
    assert rec.daily_date.shape == rec.daily_q.shape == (8401,)
    assert rec.period == (np.datetime64("1989-10-01"), np.datetime64("2012-09-30"))
    assert np.all(np.diff(rec.daily_date).astype(int) == 1)
    idx = np.searchsorted(rec.daily_date, rec.date)
    np.testing.assert_array_equal(rec.daily_q[idx], rec.q)
    assert 1e3 <= np.median(rec.daily_q) <= 2e5
    shipped = json.loads(resources.files("tobitkf.data").joinpath("arkansas_egret_info.json").read_text())
    assert rec.egret_info == shipped and rec.egret_info["Gage_number"] == "07263450"


def test_arkansas_series_is_the_log_concentration():
    rec = load_arkansas()
    s = rec.series()
    assert isinstance(s, CensoredSeries) and s.steps == 254
    np.testing.assert_allclose(s.y, np.log(rec.conc_high))
    np.testing.assert_array_equal(s.censored, rec.censored)
    np.testing.assert_allclose(s.lower[s.censored], np.log(rec.conc_high[rec.censored]))
    assert np.all(np.isneginf(s.lower[~s.censored])) and np.all(np.isposinf(s.upper))
    np.testing.assert_allclose(s.covariates["lnQ"], np.log(rec.q))
    np.testing.assert_array_equal(s.times, rec.date)
    assert s.design("lnQ").shape == (254, 2)


def test_hiv_panel_matches_its_provenance_note():
    d = load_hiv_viral_load()
    assert d.num_visits == 373
    for arr in (d.patient, d.day, d.followup, d.rna, d.censored):
        assert arr.shape == (373,)
    assert d.patients.size == 72
    per_patient = np.array([d.rows(p).size for p in d.patients])
    assert per_patient.min() == 1 and per_patient.max() == 8 and per_patient.sum() == 373
    assert int(d.missing.sum()) == 11
    assert int(d.left.sum()) == 26 and int(d.right.sum()) == 7
    assert set(d.rna[d.left].tolist()) == {50.0, 400.0}
    assert set(d.rna[d.right].tolist()) == {750000.0}
    assert np.any(d.day < 0)  # visits before the interruption
    assert int(d.duplicate.sum()) == 15
    low, high = d.log10_bounds()
    meas = (d.censored == 0) & ~d.missing
    np.testing.assert_allclose(low[meas], np.log10(d.rna[meas]))
    np.testing.assert_array_equal(low[meas], high[meas])
    assert np.all(np.isneginf(low[d.left])) and np.all(np.isposinf(high[d.right]))
    np.testing.assert_allclose(high[d.left], np.log10(d.rna[d.left]))
    assert np.all(np.isnan(low[d.missing]) & np.isnan(high[d.missing]))
    r = d.rows("C1")
    assert np.all(np.diff(d.day[r]) >= 0) and np.all(d.patient[r] == "C1")
    with pytest.raises(tk.ValidationError, match="patient"):
        d.rows("no such patient")


def test_niagara_matches_its_provenance_note():
    s = load_niagara()
    assert s.steps == 144
    assert int(s.censored.sum()) == 21
    assert str(s.times[0]) == "2001-03-01" and str(s.times[-1]) == "2007-03-22"
    assert s.times.dtype == np.dtype("datetime64[D]")
    assert set(s.lower.tolist()) == {0.214, 0.0878}
    drop = s.times[np.flatnonzero(s.lower == 0.0878)[0]]
    assert np.all(s.lower[s.times < drop] == 0.214) and np.all(s.lower[s.times >= drop] == 0.0878)
    assert np.datetime64("2005-03-24") <= drop <= np.datetime64("2005-04-21")  # the change "from 2005-03-24"
    assert int(s.censored[s.times < drop].sum()) == 20
    np.testing.assert_array_equal(s.y[s.censored], s.lower[s.censored])  # a censored reading holds its limit
    assert np.all(s.y[~s.censored] > 0)
    gaps = np.diff(s.times).astype(int)
    assert np.median(gaps) == 14
    lg = load_niagara(log=True)
    np.testing.assert_allclose(lg.y, np.log(s.y))
    np.testing.assert_allclose(lg.lower, np.log(s.lower))


def test_provenance_covers_every_shipped_file_and_its_licence():
    text = provenance()
    shipped = sorted(p.name for p in resources.files("tobitkf.data").iterdir() if p.name.endswith((".csv", ".json")))
    assert len(shipped) == 7
    for name in shipped:
        assert name in text, name
    for licence in ("CC0", "GPL-2", "GPL >= 2"):
        assert licence in text


def test_the_package_data_pattern_ships_the_new_files():
    import tomllib
    from fnmatch import fnmatch
    from pathlib import Path

    cfg = tomllib.loads((Path(__file__).resolve().parents[2] / "pyproject.toml").read_text())
    patterns = cfg["tool"]["setuptools"]["package-data"]["tobitkf.data"]
    for p in resources.files("tobitkf.data").iterdir():
        if p.name.endswith((".csv", ".json", ".md")):
            assert any(fnmatch(p.name, pat) for pat in patterns), p.name
