"""``tobitkf fit FILE.csv --model MODEL.toml`` (tobitkf.inference.fit_cli) and the shipped data."""

import json
from importlib import resources

import numpy as np
import pytest
from typer.testing import CliRunner

from tobitkf.cli import app
from tobitkf.data import load_cloud_ceiling, load_phosphorus, provenance

MODEL = """
[data]
y = "lP"
censored = "cc"
lower = "lcl"
regressors = ["lQ"]
time = "time"

[model]
kind = "censored_ar"
p = 1
"""


def _csv():
    return resources.files("tobitkf.data").joinpath("phosphorus.csv")


def test_fit_command_writes_estimates_series_and_a_figure(tmp_path):
    model = tmp_path / "model.toml"
    model.write_text(MODEL)
    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["fit", str(_csv()), "--model", str(model), "--out", str(out)])
    assert res.exit_code == 0, res.output
    rec = json.loads((out / "fit.json").read_text())
    assert set(rec["estimates"]) == {"beta0", "beta1", "sigma2", "phi1"}
    assert rec["likelihood"] == "exact" and rec["converged"]
    lines = (out / "series.csv").read_text().splitlines()
    assert lines[0] == "time,y,censored,lower,upper,smoothed,smoothed_sd" and len(lines) == 182
    assert lines[2].startswith("1998-11,") and lines[2].split(",")[2] == "1"
    assert (out / "fit.png").stat().st_size > 1000
    assert "beta1" in res.output


def test_fit_command_a_state_space_model_by_em(tmp_path):
    csv = tmp_path / "s.csv"
    rng = np.random.default_rng(0)
    x = np.zeros(120)
    for t in range(1, 120):
        x[t] = 0.8 * x[t - 1] + rng.normal() * 0.7
    y = x + rng.normal(size=120) * 0.4
    y[5] = np.nan
    csv.write_text("y\n" + "\n".join("" if np.isnan(v) else repr(float(v)) for v in y) + "\n")
    model = tmp_path / "m.toml"
    model.write_text(
        '[data]\ny = "y"\nintercept = false\n[model]\nkind = "state_space"\nA = [[0.8]]\nC = [[1.0]]\n'
        'Q = [[1.0]]\nR = [[1.0]]\nx0 = [0.0]\nP0 = [[1.0]]\nestimate = ["Q", "R"]\nmethod = "em"\nmaxiter = 200\n'
    )
    res = CliRunner().invoke(app, ["fit", str(csv), "--model", str(model), "--out", str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
    rec = json.loads((tmp_path / "o" / "fit.json").read_text())
    assert rec["method"] == "em" and rec["model"]["kind"] == "state_space"


@pytest.mark.parametrize(
    "text,match",
    [
        ('[data]\ny = "nope"\n', "column 'nope'"),
        ('[data]\nx = "lP"\n', "unknown key 'x'"),
        ("[data]\n", "name the column of the readings"),
        ('[data]\ny = "lP"\n[model]\nkind = "nn"\n', "unknown model kind"),
        ("[data\n", "not valid TOML"),
        ('[data]\ny = "lP"\nlower = [1]\n', "lower must be"),
    ],
)
def test_fit_command_errors_name_the_key(tmp_path, text, match):
    model = tmp_path / "m.toml"
    model.write_text(text)
    res = CliRunner().invoke(app, ["fit", str(_csv()), "--model", str(model), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2
    assert match in " ".join(res.output.split())


def test_shipped_data_sets_and_their_provenance():
    p = load_phosphorus()
    assert (p.steps, int(p.censored.sum()), int(p.missing.sum())) == (181, 28, 7)
    np.testing.assert_array_equal(p.y[p.censored], p.lower[p.censored])  # censored readings hold their limit
    assert set(np.round(np.exp(np.unique(p.lower)), 6)) == {0.02, 0.05, 0.1}
    assert p.design("lQ").shape == (181, 2)
    c = load_cloud_ceiling()
    assert (c.steps, int(c.censored.sum()), int(c.missing.sum())) == (716, 290, 3)
    at_limit = np.isclose(c.y, np.log(120.0))
    assert int((at_limit & ~c.censored).sum()) == 8 and np.all(at_limit[c.censored])
    text = provenance()
    assert "ARCensReg" in text and "Iowa" in text and "NCAR" in text
    cens = c.censoring()
    assert cens.upper.shape == (716, 1)


# --------------------------------------------------------------------------- hostile inputs, the no-overwrite rule

DL_CSV = (
    "date,conc\n2020-01-01,<0.05\n2020-01-15,0.12\n2020-02-01,0.08\n2020-02-15,<0.05\n2020-03-01,0.2\n"
    "2020-03-15,0.15\n2020-04-01,<0.05\n2020-04-15,0.09\n2020-05-01,0.11\n2020-05-15,0.07\n"
)
DL_MODEL = '[data]\ny = "conc"\ntime = "date"\n[model]\np = 0\n'


def _run(tmp_path, csv_text, model_text, *extra, csv_bytes=None):
    csv = tmp_path / "d.csv"
    if csv_bytes is not None:
        csv.write_bytes(csv_bytes)
    else:
        csv.write_text(csv_text, encoding="utf-8")
    model = tmp_path / "m.toml"
    model.write_text(model_text, encoding="utf-8")
    args = ["fit", str(csv), "--model", str(model)]
    if "--out" not in extra:
        args += ["--out", str(tmp_path / "o")]
    return CliRunner().invoke(app, args + list(extra))


def _one_line_error(res, match):
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output and res.exception is None or isinstance(res.exception, SystemExit)
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.output
    assert match in lines[0], lines[0]


def test_fit_reads_dl_strings_and_keeps_the_dates(tmp_path):
    res = _run(tmp_path, DL_CSV, DL_MODEL)
    assert res.exit_code == 0, res.output
    rows = (tmp_path / "o" / "series.csv").read_text().splitlines()
    assert rows[1].split(",")[:5] == ["2020-01-01", "0.05", "1", "0.05", "inf"]
    assert rows[2].split(",")[:5] == ["2020-01-15", "0.12", "0", "-inf", "inf"]  # no limit recorded


@pytest.mark.parametrize(
    "model_text,match",
    [
        ('[data]\ny = "conc"\n[extra]\n', "unknown section [extra]; expected [data] and [model]"),  # markup-safe
        ('[data]\ny = "conc"\nwhat = 1\n', "unknown key 'what' in [data]"),
        ('[data]\ny = "conc"\n[model]\nmaxiter = "abc"\n', "[model] maxiter: expected an integer >= 1, got 'abc'"),
        ('[data]\ny = "conc"\n[model]\np = true\n', "[model] p: expected an integer >= 0, got True"),
        ('[data]\ny = "conc"\n[model]\np = 1.5\n', "[model] p: expected an integer"),
        ('[data]\ny = "conc"\n[model]\nA = [[1.0]]\n', "[model] A: does not apply to kind = 'censored_ar'"),
        ('[data]\ny = "conc"\nintercept = "yes"\n', "[data] intercept: expected true or false"),
        ('[data]\ny = "conc"\n[model]\nkind = "state_space"\nA = [[0.5]]\n', "needs the starting matrix C"),
        ('[data]\ny = "conc"\nformat = "xls"\n', "[data] format: expected one of"),
    ],
)
def test_fit_model_file_mistakes_end_in_one_line(tmp_path, model_text, match):
    _one_line_error(_run(tmp_path, DL_CSV, model_text), match)


@pytest.mark.parametrize(
    "csv_bytes,match",
    [
        ("conc,site\n0.1,Montréal\n".encode("latin-1"), "line 2 is not utf-8 text (byte 0xe9)"),
        (b"conc,conc\n0.1,0.2\n", "two columns 'conc' (columns 1 and 2)"),
        (b"conc\n0.1\n<\n", "line 3, column 'conc': '<' has '<' but no number"),
        (b"conc\n0.1\nTRUE\n", "line 3, column 'conc': expected a number, got 'TRUE'"),
        (b"date,conc\n2020-01-01,0.1\n2020-01-01,0.2\n", "line 3, column 'date': the time 2020-01-01 repeats"),
    ],
)
def test_fit_bad_files_end_in_one_line(tmp_path, csv_bytes, match):
    time = 'time = "date"\n' if csv_bytes.startswith(b"date") else ""
    _one_line_error(_run(tmp_path, None, '[data]\ny = "conc"\n' + time, csv_bytes=csv_bytes), match)


def test_fit_refuses_an_out_below_a_file(tmp_path):
    (tmp_path / "f").write_text("x")
    _one_line_error(_run(tmp_path, DL_CSV, DL_MODEL, "--out", str(tmp_path / "f" / "sub")), "--out")


def test_fit_error_handler_is_the_command_lines_and_markup_free(tmp_path):
    # the message holds "[data]" and "[model]": the old handler printed it through rich markup,
    # which ate both ("unknown section ; expected and")
    res = _run(tmp_path, DL_CSV, "[data]\ny = 'conc'\n[model]\n[more]\n")
    _one_line_error(res, "expected [data] and [model]")


def test_fit_with_a_utf8_byte_order_mark_finds_its_columns(tmp_path):
    res = _run(tmp_path, None, DL_MODEL, csv_bytes=b"\xef\xbb\xbf" + DL_CSV.encode())
    assert res.exit_code == 0, res.output


def test_fit_does_not_replace_files_it_did_not_write(tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    for name in ("summary.txt", "series.csv", "fit.json"):
        (out / name).write_text("my own notes\n")
        res = _run(tmp_path, DL_CSV, DL_MODEL)
        _one_line_error(res, f"{out / name} was not written by tobitkf")
        assert (out / name).read_text() == "my own notes\n"
        (out / name).unlink()
    assert _run(tmp_path, DL_CSV, DL_MODEL).exit_code == 0
    assert _run(tmp_path, DL_CSV, DL_MODEL).exit_code == 0  # its own files are replaced
    (out / "series.csv").write_text("my own notes\n")
    assert _run(tmp_path, DL_CSV, DL_MODEL, "--force").exit_code == 0
    assert (out / "series.csv").read_text().startswith("time,y,censored")


def test_fit_without_matplotlib_writes_its_files_and_skips_the_figure(tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "matplotlib", None)
    res = _run(tmp_path, DL_CSV, DL_MODEL)
    assert res.exit_code == 0, res.output
    assert "skipped fit.png: the optional extra 'plot' is needed" in " ".join(res.output.split())
    out = tmp_path / "o"
    assert {p.name for p in out.iterdir()} == {"fit.json", "summary.txt", "series.csv"}


def test_fit_blank_limit_is_no_limit_not_the_previous_rows(tmp_path):
    # the old reader carried 0.5 into row 2, so 0.3 lay below its "limit" and the fit refused the data
    text = "y,dl\n0.5,0.5\n0.3,\n0.9,0.5\n0.7,0.5\n1.2,\n0.8,0.5\n0.6,0.5\n1.0,\n"
    res = _run(tmp_path, text, '[data]\ny = "y"\nlower = "dl"\n[model]\np = 0\n')
    assert res.exit_code == 0, res.output
    rows = [r.split(",") for r in (tmp_path / "o" / "series.csv").read_text().splitlines()[1:]]
    assert [r[3] for r in rows[:3]] == ["0.5", "-inf", "0.5"] and [r[2] for r in rows[:3]] == ["1", "0", "0"]
    res = _run(tmp_path, "y,c,dl\n0.5,1,\n0.7,0,0.5\n", '[data]\ny = "y"\ncensored = "c"\nlower = "dl"\n')
    _one_line_error(res, "line 2, column 'dl': a censored reading needs its limit, and this cell is blank")


def _ss_csv(T=80, seed=0):
    rng = np.random.default_rng(seed)
    x = np.zeros(T)
    for t in range(1, T):
        x[t] = 0.7 * x[t - 1] + rng.normal() * 0.5
    y = 2.0 + x + rng.normal(size=T) * 0.3
    lim = float(np.quantile(y, 0.25))
    return "y\n" + "\n".join(repr(float(max(v, lim))) for v in y) + "\n", lim, y < lim


SS_MODEL = (
    '[data]\ny = "y"\nlower = {lim}\n[model]\nkind = "state_space"\nA = [[0.7]]\nC = [[1.0]]\nQ = [[0.25]]\n'
    "R = [[0.1]]\nx0 = [0.0]\nP0 = [[1.0]]\nmaxiter = 40\n"
)


def test_fit_state_space_uses_the_intercept_and_flags_censored_rows(tmp_path):
    text, lim, below = _ss_csv()
    res = _run(tmp_path, text, SS_MODEL.format(lim=lim) + 'estimate = ["Q", "R", "D"]\nmethod = "direct"\n')
    assert res.exit_code == 0, res.output
    rec = json.loads((tmp_path / "o" / "fit.json").read_text())
    # the intercept (true 2.0) is estimated as D; it was ignored before (no D: a zero-mean model)
    assert abs(rec["estimates"]["D[0,0]"] - 2.0) < 3 * rec["se"]["D[0,0]"]
    assert "inputs (columns of D): intercept" in res.output
    flags = [int(r.split(",")[2]) for r in (tmp_path / "o" / "series.csv").read_text().splitlines()[1:]]
    np.testing.assert_array_equal(flags, below.astype(int))  # censored rows flagged (were all 0)
    res = _run(tmp_path, text, SS_MODEL.format(lim=lim) + 'estimate = ["Q", "R"]\n')
    _one_line_error(res, 'add "D" to estimate, give D, or set intercept = false')


def test_fit_format_option_reads_nonmem_columns(tmp_path):
    text = "TIME,DV,CENS\n" + "".join(
        f"{t},{v},{c}\n" for t, (v, c) in enumerate([(0.5, 1), (1.2, 0), (0.9, 0), (0.5, 1), (1.5, 0), (0.7, 0)])
    )
    res = _run(tmp_path, text, '[data]\ntime = "TIME"\n[model]\np = 0\n', "--format", "nonmem")
    assert res.exit_code == 0, res.output
    assert "[data] format" not in res.output
    rows = (tmp_path / "o" / "series.csv").read_text().splitlines()
    assert rows[1].split(",")[:4] == ["0", "0.5", "1", "0.5"]


def test_fit_prints_progress_lines_while_reading_a_large_file(tmp_path, monkeypatch):
    from tobitkf.data import _tables

    monkeypatch.setattr(_tables, "PROGRESS_BYTES", 10)  # every file is "large"
    res = _run(tmp_path, DL_CSV, DL_MODEL)
    assert res.exit_code == 0, res.output
    assert "reading " in res.output and "read 10 rows of d.csv in" in res.output


def test_a_command_without_the_decorator_still_ends_in_one_line():
    import typer

    from tobitkf.cli import _Group

    app2 = typer.Typer(cls=_Group)

    @app2.command()
    def boom() -> None:
        raise RuntimeError("[red]x[/red]")

    @app2.command()
    def other() -> None:
        pass

    res = CliRunner().invoke(app2, ["boom"])
    assert res.exit_code == 2
    assert (
        res.output.strip()
        == "error: unexpected RuntimeError: [red]x[/red] (this is a bug in tobitkf; please report it)"
    )


def test_fit_detects_egret_interval_columns_and_refuses_an_unknown_format(tmp_path):
    from pathlib import Path

    egret = (Path(__file__).parents[1] / "readers_data" / "arkansas_excerpt.csv").read_bytes()
    res = _run(tmp_path, None, '[data]\ntime = "Date"\n[model]\np = 0\n', csv_bytes=egret)
    assert res.exit_code == 0, res.output
    rows = [r.split(",") for r in (tmp_path / "o" / "series.csv").read_text().splitlines()[1:]]
    assert [r[2] for r in rows] == ["1", "1"] + ["0"] * 7 + ["1", "0", "0"]
    assert rows[9][:4] == ["1999-04-13", "0.005", "1", "0.005"]
    _one_line_error(_run(tmp_path, DL_CSV, DL_MODEL, "--format", "excel"), "--format: expected one of auto")
