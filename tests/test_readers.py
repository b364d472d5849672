"""The readers of censored records (tobitkf.data.readers): real excerpts, round trips, malformed rows."""

from pathlib import Path

import numpy as np
import pytest

import tobitkf as tk
from tobitkf import ValidationError
from tobitkf.data import CensoredSeries
from tobitkf.data.readers import CensoredRecord, read_censored, read_censored_panel, write_censored

HERE = Path(__file__).parent / "readers_data"
inf = np.inf


def _csv(tmp_path, text, name="r.csv", encoding="utf-8"):
    path = tmp_path / name
    path.write_bytes(text.encode(encoding))
    return path


# --------------------------------------------------------------------------- real records (excerpts)


def test_egret_interval_columns_of_the_arkansas_record():
    s = read_censored(HERE / "arkansas_excerpt.csv", time="Date", covariates=["Q"])
    assert s.description.endswith("(interval format)")  # detected from ConcLow/ConcHigh
    assert s.steps == 12
    # rows 1, 2 (ConcLow empty, ConcHigh 0.05) and 10 (empty, 0.005) are below the detection limit
    np.testing.assert_array_equal(np.flatnonzero(s.censored), [0, 1, 9])
    np.testing.assert_array_equal(s.y[[0, 1, 9]], [0.05, 0.05, 0.005])
    np.testing.assert_array_equal(s.lower[[0, 1, 9]], [0.05, 0.05, 0.005])
    assert s.y[2] == 0.06 and s.lower[2] == -inf and np.all(s.upper == inf)
    assert s.times[0] == np.datetime64("1990-09-18") and s.times[-1] == np.datetime64("1999-06-08")
    assert s.covariates["Q"][0] == 1730.0 and s.time[0] == "1990-09-18"
    np.testing.assert_array_equal(s.side[[0, 2]], [-1, 0])


def test_value_flag_limit_triple_of_the_niagara_record():
    s = read_censored(HERE / "niagara_excerpt.csv", y="concentration", censored="censored", lower="limit", time="day")
    assert s.description.endswith("(flag format)") and s.steps == 12
    np.testing.assert_array_equal(s.censored, [False] * 11 + [True])
    assert s.y[-1] == 0.0878 and s.lower[-1] == 0.0878
    np.testing.assert_array_equal(s.lower[:7], 0.214)  # the limit in force, also on uncensored rows
    np.testing.assert_array_equal(s.lower[7:], 0.0878)
    assert s.times.dtype == float and s.times[0] == 1.0 and s.times[-1] == 1807.0


def test_panel_with_left_and_right_censoring_of_the_hiv_record():
    kw = dict(id="patient", time="days_after_ti", y="rna_copies_per_ml", censored="censored")
    codes = {1: "left", 2: "right"}
    with pytest.raises(
        ValidationError, match=r"hiv_excerpt.csv line 4, column 'days_after_ti': the time 125.0 repeats"
    ):
        read_censored_panel(HERE / "hiv_excerpt.csv", flag_codes=codes, **kw)
    p = read_censored_panel(HERE / "hiv_excerpt.csv", flag_codes=codes, duplicates="drop", **kw)
    assert p.ids == ["C11", "C18", "C9", "C15"] and p.steps.tolist() == [3, 5, 6, 7]
    c18, c9, c15 = p["C18"], p["C9"], p["C15"]
    assert c18.side.tolist() == [0, 0, 0, 0, 1] and c18.upper[-1] == 750000 and c18.lower[-1] == -inf
    assert c9.side.tolist() == [-1, -1, 0, 0, 0, 0] and c9.lower[:2].tolist() == [50, 400]
    assert np.isnan(c15.y).sum() == 2 and not c15.censored.any()
    assert p["C11"].times.tolist() == [0.0, 125.0, 413.0]
    # without the codes, a flag 2 is not a censoring flag this reader knows
    with pytest.raises(ValidationError, match=r"line 10, column 'censored'.*flag_codes"):
        read_censored_panel(HERE / "hiv_excerpt.csv", duplicates="drop", **kw)


# --------------------------------------------------------------------------- round trips


def _series(**extra):
    y = np.array([0.05, 0.31, np.nan, 2.5, 0.12, 0.05])
    cens = np.array([True, False, False, True, False, True])
    lower = np.array([0.05, -inf, -inf, -inf, -inf, 0.05])
    upper = np.array([inf, inf, inf, 2.5, inf, inf])
    times = np.array(["2001-03-01", "2001-03-15", "2001-04-02", "2001-05-01", "2001-05-02", "2001-06-30"], "M8[D]")
    return CensoredRecord(
        name="x",
        y=y,
        censored=cens,
        lower=lower,
        upper=upper,
        covariates={"q": np.arange(6.0) / 3},
        times=times,
        **extra,
    )


@pytest.mark.parametrize("fmt", ["strings", "flag", "interval", "nonmem"])
def test_each_format_round_trips(tmp_path, fmt):
    s = _series()
    path = write_censored(s, tmp_path / f"{fmt}.csv", format=fmt)
    kw = {"y": "y"} if fmt in ("strings", "flag") else {}
    if fmt == "flag":
        kw.update(censored="censored", lower="lower", upper="upper")
    back = read_censored(path, format="auto", time="time", covariates=["q"], **kw)
    assert back.description.endswith(f"({fmt} format)")
    np.testing.assert_array_equal(back.y, s.y)
    np.testing.assert_array_equal(back.censored, s.censored)
    np.testing.assert_array_equal(back.lower, s.lower)
    np.testing.assert_array_equal(back.upper, s.upper)
    np.testing.assert_array_equal(back.covariates["q"], s.covariates["q"])
    np.testing.assert_array_equal(back.times, s.times)


def test_flag_format_keeps_limits_of_uncensored_readings(tmp_path):
    s = _series()
    s = CensoredRecord(**{**s.__dict__, "lower": np.array([0.05, 0.05, 0.05, 0.02, 0.02, 0.05])})
    back = read_censored(
        write_censored(s, tmp_path / "f.csv"), y="y", censored="censored", lower="lower", upper="upper"
    )
    np.testing.assert_array_equal(back.lower, s.lower)
    np.testing.assert_array_equal(back.censored, s.censored)


def test_dataframe_with_a_datetime_index_round_trips():
    pd = pytest.importorskip("pandas")
    s = _series()
    cells = ["<0.05", 0.31, None, ">2.5", 0.12, "<0.05"]
    df = pd.DataFrame({"conc": cells, "q": s.covariates["q"]}, index=pd.DatetimeIndex(s.times))
    back = read_censored(df, y="conc", covariates=["q"])
    for a in ("y", "censored", "lower", "upper"):
        np.testing.assert_array_equal(getattr(back, a), getattr(s, a))
    np.testing.assert_array_equal(back.times, s.times.astype("M8[ns]"))
    df_bool = pd.DataFrame({"conc": [True, False]})
    with pytest.raises(ValidationError, match="column 'conc': booleans"):
        read_censored(df_bool, y="conc")


def test_strings_with_one_unit_and_the_examples_of_the_docstrings():
    s = read_censored({"c": ["<0.05 mg/L", "0.12 mg/L", "", "0.3mg/L"]}, y="c")
    assert s.units == "mg/L" and s.y[1] == 0.12 and s.censored.tolist() == [True, False, False, False]
    assert isinstance(s, CensoredSeries) and s.steps == 4


# --------------------------------------------------------------------------- malformed rows


@pytest.mark.parametrize(
    "text,kw,match",
    [
        ("y\n0.1\n<\n", {"y": "y"}, r"line 3, column 'y': '<' has '<' but no number"),
        ("y\n0.1\n<DL\n", {"y": "y"}, r"line 3, column 'y': '<DL' has '<' but no number"),
        ("y,c,dl\n0.1,0,0.05\n0.03,0,0.05\n", {"y": "y", "censored": "c", "lower": "dl"}, r"line 3, column 'y'.*below"),
        ("y,c,ul\n0.1,0,0.5\n0.7,0,0.5\n", {"y": "y", "censored": "c", "upper": "ul"}, r"line 3, column 'y'.*above"),
        ("y\n0.05 mg/L\n50 ug/L\n", {"y": "y"}, r"line 3, column 'y': mixed units.*'ug/L' here, 'mg/L' at line 2"),
        ("y\n0.05 mg/L\n0.07\n", {"y": "y"}, r"line 3, column 'y': mixed units"),
        (
            "t,y\n2001-01-01,1\n2001-01-01,2\n",
            {"y": "y", "time": "t"},
            r"line 3, column 't': the time 2001-01-01 repeats",
        ),
        ("t,y\n2001-01-02,1\n2001-01-01,2\n", {"y": "y", "time": "t"}, r"line 3, column 't'.*sort the rows"),
        ("t,y\n2001-01-02,1\n,2\n", {"y": "y", "time": "t"}, r"line 3, column 't': a blank time"),
        ("t,y\n2001-01-02,1\n02/01/2001,2\n", {"y": "y", "time": "t"}, r"line 3, column 't': expected a date"),
        ("y,c,dl\n0.1,0,0.05\n0.05,1,\n", {"y": "y", "censored": "c", "lower": "dl"}, r"line 3, column 'dl'.*blank"),
        (
            "y,c,dl\n0.1,0,0.05\n0.04,1,0.05\n",
            {"y": "y", "censored": "c", "lower": "dl"},
            r"line 3, column 'y'.*differs",
        ),
        ("y\n0.1\ntrue\n", {"y": "y"}, r"line 3, column 'y': expected a number, got 'true'"),
        ("y\n0.1\nND\n", {"y": "y"}, r"line 3, column 'y': expected a number, got 'ND'"),
        ("y\n0.1\ninf\n", {"y": "y"}, r"line 3, column 'y': inf is not a finite number"),
        ('y\n0.1\n"1,234"\n', {"y": "y"}, r"line 3, column 'y': expected a number"),
        ("y\n0.1\n1_000\n", {"y": "y"}, r"line 3, column 'y': expected a number"),
        ("y,y\n1,2\n", {"y": "y"}, r"two columns 'y' \(columns 1 and 2\)"),
        ("y,x\n1,2\n3\n", {"y": "y"}, r"line 3: 1 fields, the header has 2"),
        (
            "ConcLow,ConcHigh\n0.1,0.1\n0.1,0.2\n",
            {"interval_rows": "error"},
            r"line 3, column 'ConcLow': an interval with two finite ends",
        ),
        ("ConcLow,ConcHigh\n0.3,0.1\n", {}, r"line 2, column 'ConcLow': the low end is above"),
        ("ConcLow,ConcHigh,Uncen\n,0.1,1\n", {}, r"line 2, column 'Uncen': disagrees"),
        ("DV,CENS\n1,0\n2,2\n", {}, r"line 3, column 'CENS': expected CENS 0, 1"),
        ("DV,CENS,LIMIT\n1,0,\n2,1,0\n", {"interval_rows": "error"}, r"line 3, column 'LIMIT': a finite LIMIT"),
        ("DV,CENS,LIMIT\n1,0,\n2,1,3\n", {}, r"line 3, column 'LIMIT': CENS = 1 needs LIMIT below DV"),
        ("DV,CENS,LIMIT\n1,0,\n2,-1,1\n", {}, r"line 3, column 'LIMIT': CENS = -1 needs LIMIT above DV"),
        ("DV,CENS\n1,0\n,1\n", {}, r"line 3, column 'DV': a censored row needs its limit"),
        ("y,c\n1,1\n", {"y": "y", "censored": "c"}, r"line 2, column 'c': flagged censored, but on which side"),
        ("y\n1\n", {"y": "nope"}, r"y: .* has no column 'nope' \(columns: 'y'\)"),
        ("y\n", {"y": "y"}, r"no data rows"),
        (
            "y,dl\n0.5,0.5\n0.3,\n",
            {"y": "y", "lower": "dl", "upper": 0.2},
            r"line 2, column 'dl': the lower limit is not",
        ),
    ],
)
def test_malformed_rows_are_refused_naming_line_and_column(tmp_path, text, kw, match):
    with pytest.raises(ValidationError, match=match):
        read_censored(_csv(tmp_path, text), **kw)


def test_encodings_byte_order_mark_and_latin1(tmp_path):
    s = read_censored(_csv(tmp_path, "\ufeffy,t\n1.5,1\n2.5,2\n"), y="y", time="t")  # Excel's UTF-8 with a BOM
    assert s.y.tolist() == [1.5, 2.5]
    latin = _csv(tmp_path, "y,site\n1.5,Montréal\n", encoding="latin-1")
    with pytest.raises(ValidationError, match=r"line 2 is not utf-8 text \(byte 0xe9\).*encoding="):
        read_censored(latin, y="y")
    assert read_censored(latin, y="y", encoding="latin-1").y.tolist() == [1.5]


def test_blank_limit_means_no_limit_and_agrees_with_fit(tmp_path):
    # an uncensored reading with a blank limit cell has no limit (-inf), not the previous row's limit
    s = read_censored(_csv(tmp_path, "y,dl\n0.5,0.5\n0.3,\n0.9,0.5\n"), y="y", lower="dl")
    assert s.lower.tolist() == [0.5, -inf, 0.5] and s.censored.tolist() == [True, False, False]
    # tk.fit takes -inf as "no limit" and refuses NaN: the reader hands it what it accepts
    with pytest.raises(ValidationError):
        tk.fit(tk.CensoredAR(0), s.y, lower=np.where(np.isinf(s.lower), np.nan, s.lower))


def test_duplicates_drop_only_exact_repeats(tmp_path):
    s = read_censored(_csv(tmp_path, "t,y\n1,1.0\n1,1.0\n2,<0.5\n"), y="y", time="t", duplicates="drop")
    assert s.y.tolist() == [1.0, 0.5] and s.times.tolist() == [1.0, 2.0]
    with pytest.raises(ValidationError, match=r"line 3, column 't'.*with another reading"):
        read_censored(_csv(tmp_path, "t,y\n1,1.0\n1,1.5\n"), y="y", time="t", duplicates="drop")


def test_nonmem_skips_dose_records_and_honours_mdv(tmp_path):
    text = "ID,TIME,DV,CENS,MDV,EVID,LIMIT\n1,0,0,0,1,1,\n1,1,5.2,0,0,0,\n1,2,0.1,1,0,0,-inf\n1,3,,0,1,0,\n1,4,90,-1,0,0,\n"
    s = read_censored(_csv(tmp_path, text), time="TIME")
    assert s.times.tolist() == [1.0, 2.0, 3.0, 4.0]
    assert s.side.tolist() == [0, -1, 0, 1] and np.isnan(s.y[2])
    assert s.lower[1] == 0.1 and s.upper[3] == 90.0


def test_format_detection_and_its_errors(tmp_path):
    both = _csv(tmp_path, "ConcLow,ConcHigh,DV,CENS\n1,1,1,0\n")
    with pytest.raises(ValidationError, match="both interval"):
        read_censored(both)
    with pytest.raises(ValidationError, match="format: expected one of"):
        read_censored(both, format="excel")
    with pytest.raises(ValidationError, match="source: expected a CSV path"):
        read_censored(42)


# --------------------------------------------------------------------------- interval rows, panels, row labels


def test_egret_rows_between_two_finite_ends_are_interval_readings(tmp_path):
    text = "Date,ConcLow,ConcHigh\n2001-01-01,0.1,0.1\n2001-02-01,0.02,0.05\n2001-03-01,,0.05\n2001-04-01,0.3,\n"
    path = _csv(tmp_path, text)
    s = read_censored(path, time="Date")  # the default keeps the interval [0.02, 0.05]
    assert s.censored.tolist() == [False, True, True, True] and s.interval.tolist() == [False, True, False, False]
    assert s.side.tolist() == [0, 2, -1, 1]
    assert s.lower[1] == 0.02 and s.upper[1] == 0.05 and s.lower[1] < s.y[1] < s.upper[1]
    with pytest.raises(ValidationError, match=r"line 3, column 'ConcLow': an interval with two finite ends") as err:
        read_censored(path, time="Date", interval_rows="error")
    assert "interval_rows='keep'" in str(err.value)
    left = read_censored(path, time="Date", interval_rows="left")  # known below 0.05 (the 0.02 dropped)
    assert left.side.tolist() == [0, -1, -1, 1] and left.y.tolist() == [0.1, 0.05, 0.05, 0.3]
    assert left.lower.tolist() == [-inf, 0.05, 0.05, -inf] and left.upper.tolist() == [inf, inf, inf, 0.3]
    right = read_censored(path, time="Date", interval_rows="right")  # known above 0.02
    assert right.side.tolist() == [0, 1, -1, 1] and right.y[1] == 0.02 and right.upper[1] == 0.02
    # what was read writes back and reads back the same
    back = read_censored(write_censored(left, tmp_path / "w.csv", format="interval"), time="time")
    np.testing.assert_array_equal(back.y, left.y)
    np.testing.assert_array_equal(back.side, left.side)
    with pytest.raises(ValidationError, match="interval_rows: expected one of 'keep', 'error', 'left', 'right'"):
        read_censored(path, time="Date", interval_rows="mid")


@pytest.mark.parametrize("fmt", ["flag", "interval", "nonmem"])
def test_interval_readings_round_trip_every_layout_that_has_a_form_for_them(tmp_path, fmt):
    text = "Date,ConcLow,ConcHigh\n2001-01-01,0.1,0.1\n2001-02-01,0.02,0.05\n2001-03-01,,0.05\n2001-04-01,0.3,\n"
    s = read_censored(_csv(tmp_path, text), time="Date")
    cols = {"y": "y", "censored": "censored", "lower": "lower", "upper": "upper"} if fmt == "flag" else {}
    back = read_censored(write_censored(s, tmp_path / f"w_{fmt}.csv", format=fmt), format=fmt, time="time", **cols)
    for key in ("y", "censored", "lower", "upper", "side", "interval"):
        np.testing.assert_array_equal(getattr(back, key), getattr(s, key), err_msg=key)
    with pytest.raises(ValidationError, match="reading 2 is an interval reading"):
        write_censored(s, tmp_path / "w.csv", format="strings")


def test_nonmem_finite_limits_are_interval_readings(tmp_path):
    text = "TIME,DV,CENS,LIMIT\n0,0.1,1,0.02\n1,0.5,0,\n2,3,-1,10\n3,0.1,1,\n"
    s = read_censored(_csv(tmp_path, text), time="TIME")
    assert s.side.tolist() == [2, 0, 2, -1]
    assert s.lower.tolist() == [0.02, -inf, 3.0, 0.1] and s.upper.tolist() == [0.1, inf, 10.0, inf]
    one_sided = read_censored(_csv(tmp_path, text), time="TIME", interval_rows="left")  # LIMIT dropped
    assert one_sided.side.tolist() == [-1, 0, 1, -1]


def test_a_flagged_reading_between_its_two_limits_is_an_interval_reading():
    d = {"y": ["0.3", "0.5", "0.2"], "c": ["0", "1", "1"], "lo": ["", "0.1", "0.2"], "hi": ["", "0.9", ""]}
    s = read_censored(d, y="y", censored="c", lower="lo", upper="hi")
    assert s.side.tolist() == [0, 2, -1] and s.interval.tolist() == [False, True, False]
    with pytest.raises(
        ValidationError, match=r"table row 2, column 'c': flagged censored, but the reading is at neither"
    ):
        read_censored(d, y="y", censored="c", lower="lo", upper="hi", interval_rows="error")


def test_a_panel_refuses_units_that_differ_between_subjects(tmp_path):
    # each subject's cells agree within it; the old reader checked them subject by subject only
    text = "id,day,v\na,1,0.5 mg/L\na,2,<0.1 mg/L\nb,1,40 ug/L\nb,3,55 ug/L\n"
    with pytest.raises(ValidationError, match=r"line 4, column 'v': mixed units in one column: 'ug/L' for subject 'b'"):
        read_censored_panel(_csv(tmp_path, text), id="id", time="day", y="v")
    p = read_censored_panel(_csv(tmp_path, text.replace("ug/L", "mg/L")), id="id", time="day", y="v")
    assert p["a"].units == p["b"].units == "mg/L"


@pytest.mark.parametrize(
    "text,match",
    [
        ("id,day,v\na,1,0.5\nb,1,<\n", r"line 3, column 'v': '<' has '<' but no number"),
        ("id,day,v\na,1,0.5\nb,1,2\nb,1,3\n", r"line 4, column 'day': the time 1.0 repeats line 3's"),
        ("id,day,v\na,1,0.5\nb,5,2\na,0,3\n", r"line 4, column 'day': the time 0.0 comes before line 2's 1.0"),
        ("id,day,v,c,dl\na,1,0.5,0,0.1\nb,1,0.05,0,0.1\n", r"line 3, column 'v'.*uncensored reading below its lower"),
        ("id,day,v\na,1,0.5\n,2,1\n", r"line 3, column 'id': a blank subject id"),
    ],
)
def test_panel_errors_name_the_line_of_the_whole_table(tmp_path, text, match):
    kw = {"censored": "c", "lower": "dl"} if ",c,dl" in text else {}
    with pytest.raises(ValidationError, match=match):
        read_censored_panel(_csv(tmp_path, text), id="id", time="day", y="v", **kw)


def test_dataframe_errors_name_the_row_label_and_records_keep_where_each_reading_came_from(tmp_path):
    pd = pytest.importorskip("pandas")
    df = pd.DataFrame({"y": ["0.5", "<0.1", "0.7"]}, index=pd.to_datetime(["2020-01-01", "2020-01-02", "2020-01-02"]))
    with pytest.raises(ValidationError, match=r"DataFrame row 2020-01-02, column 'index': the time 2020-01-02 repeats"):
        read_censored(df, y="y")
    bad = pd.DataFrame({"y": ["0.5 mg/L", "<0.1 ug/L"]}, index=[10, 11])
    with pytest.raises(ValidationError, match=r"DataFrame row 11, column 'y': mixed units"):
        read_censored(bad, y="y")
    s = read_censored(_csv(tmp_path, "t,y\n1,0.5\n\n2,0.7\n"), y="y", time="t")
    assert s.rows.tolist() == [2, 4] and s.where(1, "y").endswith("r.csv line 4, column 'y'")
    assert read_censored(df.iloc[:2], y="y").where(1) == "DataFrame row 2020-01-02"
