"""``tobitkf fit`` with the continuous-time model (``kind = "ou"``): one irregular series and a panel of subjects."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

import tobitkf as tk
from tobitkf.cli import app
from tobitkf.inference.panel import panel_forecast, panel_log_likelihood

LOW, HIGH = 0.4, 2.6


def _panel_csv(seed=3, subjects=5):
    """A long table: id, day, a reading with "<0.4" / ">2.6" strings, a regressor; and the latent values."""
    rng = np.random.default_rng(seed)
    rows, latent = ["id,day,v,z"], {}
    for s in range(subjects):
        days = np.sort(rng.choice(60, size=5, replace=False)).astype(float)
        x = rng.normal(0, 0.8)
        vals = []
        for k, t in enumerate(days):
            if k:
                a = np.exp(-(t - days[k - 1]) / 20)
                x = a * x + np.sqrt(0.64 * (1 - a * a)) * rng.normal()
            z = rng.normal()
            v = 1.2 + 0.3 * z + x + 0.2 * rng.normal()
            vals.append(v)
            cell = f"<{LOW}" if v < LOW else f">{HIGH}" if v > HIGH else repr(round(float(v), 6))
            rows.append(f"p{s},{t:g},{cell},{z!r}")
        latent[f"p{s}"] = (days, np.array(vals))
    return "\n".join(rows) + "\n", latent


MODEL = '[data]\nsubject = "id"\ntime = "day"\ny = "v"\nregressors = ["z"]\n[model]\nkind = "ou"\nforecast = 3\n'


def _run(tmp_path, csv_text, model_text, *extra):
    (tmp_path / "d.csv").write_text(csv_text, encoding="utf-8")
    (tmp_path / "m.toml").write_text(model_text, encoding="utf-8")
    args = ["fit", str(tmp_path / "d.csv"), "--model", str(tmp_path / "m.toml"), "--out", str(tmp_path / "o")]
    return CliRunner().invoke(app, args + list(extra))


def _one_line_error(res, match):
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.output
    assert match in lines[0], lines[0]


def _rows(path):
    lines = path.read_text().splitlines()
    return lines[0], [r.split(",") for r in lines[1:]]


def test_a_panel_is_fitted_jointly_and_written_per_subject(tmp_path):
    text, latent = _panel_csv()
    res = _run(tmp_path, text, MODEL)
    assert res.exit_code == 0, res.output
    out = tmp_path / "o"
    rec = json.loads((out / "fit.json").read_text())
    assert rec["model"]["kind"] == "continuous_panel" and "5 subjects, 25 readings" in res.output
    est = rec["estimates"]
    assert set(est) == {"beta_intercept", "beta_z", "log_rate", "log_sd", "log_noise_sd"}
    # the same panel built by hand: the written log-likelihood is the panel's at the written estimates
    cells = [r.split(",") for r in text.splitlines()[1:]]
    ids = list(dict.fromkeys(c[0] for c in cells))
    sub = [[c for c in cells if c[0] == i] for i in ids]
    y = [[float(c[2].lstrip("<>")) for c in s] for s in sub]
    lower = [[LOW if c[2].startswith("<") else -np.inf for c in s] for s in sub]
    upper = [[HIGH if c[2].startswith(">") else np.inf for c in s] for s in sub]
    u = [np.array([[1.0, float(c[3])] for c in s]) for s in sub]
    panel = tk.Panel([[float(c[1]) for c in s] for s in sub], y, lower=lower, upper=upper, u=u, ids=ids)
    rate, sd, r = (np.exp(est[k]) for k in ("log_rate", "log_sd", "log_noise_sd"))
    system = tk.ContinuousLinearSystem(
        [[-rate]],
        [[2 * rate * sd**2]],
        [[1.0]],
        [[r * r]],
        [0.0],
        [[sd**2]],
        D=[[est["beta_intercept"], est["beta_z"]]],
    )
    assert panel_log_likelihood(system, panel) == pytest.approx(rec["loglik"], rel=1e-9, abs=1e-9)
    # series.csv: one row per reading, subject first, censored rows flagged at their limits
    head, rows = _rows(out / "series.csv")
    assert head == "subject,time,y,censored,lower,upper,smoothed,smoothed_sd" and len(rows) == 25
    flagged = [c[2][:1] in "<>" for c in cells]
    assert [r[3] == "1" for r in rows] == flagged
    assert all(float(r[7]) < sd for r in rows)  # a reading narrows the stationary spread
    # forecast.csv: three leads per subject, from each subject's last visit, the regressor held
    head, rows = _rows(out / "forecast.csv")
    assert head == "subject,time,ahead,mean,sd,lower_95,upper_95" and len(rows) == 15
    last = np.array([[1.0, float(s[-1][3])] for s in sub])
    fc = panel_forecast(system, panel, 2.0, u=last)
    got = [r for r in rows if r[2] == "2"]
    assert [g[0] for g in got] == ids
    assert [float(g[1]) for g in got] == [float(s[-1][1]) + 2 for s in sub]
    np.testing.assert_allclose([float(g[3]) for g in got], fc["reading_mean"][:, 0], rtol=1e-9)
    np.testing.assert_allclose([float(g[4]) for g in got], fc["reading_sd"][:, 0], rtol=1e-9)
    assert (out / "fit.png").stat().st_size > 1000


def test_one_dated_series_with_a_log_transform(tmp_path):
    days = np.datetime64("2020-01-01") + np.array([0, 9, 30, 31, 45, 80, 90, 120, 150, 151])
    vals = ["0.5", "<0.2", "0.9", "1.4", "0.35", "<0.2", "0.7", "2.0", "1.1", "0.8"]
    text = "date,conc\n" + "".join(f"{d},{v}\n" for d, v in zip(days, vals))
    model = '[data]\ny = "conc"\ntime = "date"\ntransform = "log"\n[model]\nkind = "ou"\nnoise_sd = 0.1\nforecast = 2\n'
    res = _run(tmp_path, text, model)
    assert res.exit_code == 0, res.output
    head, rows = _rows(tmp_path / "o" / "series.csv")
    assert head == "time,y,censored,lower,upper,smoothed,smoothed_sd"
    assert rows[1][:5] == ["2020-01-10", repr(float(np.log(0.2))), "1", repr(float(np.log(0.2))), "inf"]
    assert float(rows[0][1]) == pytest.approx(np.log(0.5))
    _, fc = _rows(tmp_path / "o" / "forecast.csv")
    assert [r[0] for r in fc] == ["2020-06-01", "2020-06-02"]  # 1 and 2 days after the last sample
    assert "noise sd 0.1 (fixed)" in res.output


@pytest.mark.parametrize(
    "csv_text,model_text,match",
    [
        ("id,day,v\na,0,1\n", '[data]\nsubject = "id"\ny = "v"\ntime = "day"\n', 'set [model] kind = "ou"'),
        ("day,v\n0,1\n", '[data]\ny = "v"\n[model]\nkind = "ou"\n', '[data] time: kind = "ou" needs'),
        ("id,day,v\na,0,1\n,3,2\n", MODEL.replace('["z"]', "[]"), "line 3, column 'id': a blank subject id"),
        ("id,day,v\na,0,1\na,0,2\n", MODEL.replace('["z"]', "[]"), "line 3, column 'day': the time 0.0 repeats"),
        ("id,day,v\na,0,1\nb,3,<\n", MODEL.replace('["z"]', "[]"), "line 3, column 'v': '<' has '<' but no number"),
        ("id,day,v,z\na,0,1,0.5\nb,3,2,\n", MODEL, "line 3, column 'z': a blank regressor"),
        (
            "day,v\n0,1\n4,0\n",
            '[data]\ny = "v"\ntime = "day"\ntransform = "log"\n',
            "line 3, column 'v': the reading 0",
        ),
        ("day,v\n0,1\n", '[data]\ny = "v"\ntransform = "ln"\n', "[data] transform: expected 'none', 'log'"),
        ("day,v\n0,1\n", '[data]\ny = "v"\ninterval_rows = "mid"\n', "[data] interval_rows: expected one of 'keep'"),
        (
            "Date,ConcLow,ConcHigh\n2001-01-01,0.02,0.05\n",
            '[data]\ntime = "Date"\ninterval_rows = "error"\n',
            "line 2, column 'ConcLow': an interval with two finite ends",
        ),
        ("day,v\n0,1\n", '[data]\ny = "v"\n[model]\nkind = "ou"\nlevel = 1\n', "[model] level: expected true"),
        ("day,v\n0,1\n", '[data]\ny = "v"\n[model]\nkind = "ou"\nnoise_sd = 0\n', "[model] noise_sd: expected"),
        (
            "day,v\n0,1\n",
            '[data]\ny = "v"\n[model]\nkind = "ou"\nunit = "fortnight"\n',
            "[model] unit: expected one of",
        ),
        ("day,v\n0,1\n", '[data]\ny = "v"\n[model]\nkind = "ou"\np = 2\n', "does not apply to kind = 'ou'"),
    ],
)
def test_malformed_inputs_end_in_one_line_naming_row_and_column(tmp_path, csv_text, model_text, match):
    _one_line_error(_run(tmp_path, csv_text, model_text), match)


def test_a_forecast_file_it_did_not_write_is_not_replaced(tmp_path):
    text, _ = _panel_csv(subjects=2)
    out = tmp_path / "o"
    out.mkdir()
    (out / "forecast.csv").write_text("my own notes\n")
    _one_line_error(_run(tmp_path, text, MODEL), f"{out / 'forecast.csv'} was not written by tobitkf")
    assert (out / "forecast.csv").read_text() == "my own notes\n"


def test_the_hiv_record_as_distributed_is_read_as_a_panel_and_fitted(tmp_path):
    from pathlib import Path

    text = (Path(__file__).parents[1] / "readers_data" / "hiv_excerpt.csv").read_text()
    model = (
        '[data]\nsubject = "patient"\ntime = "days_after_ti"\ny = "rna_copies_per_ml"\ncensored = "censored"\n'
        'flag_codes = {1 = "left", 2 = "right"}\nduplicates = "drop"\ntransform = "log10"\n'
        '[model]\nkind = "ou"\nforecast = 1\n'
    )
    res = _run(tmp_path, text, model)
    assert res.exit_code == 0, res.output
    cells = [r.split(",") for r in text.splitlines()[1:]]
    ids = list(dict.fromkeys(c[0] for c in cells))
    head, rows = _rows(tmp_path / "o" / "series.csv")
    assert [r[0] for r in rows[:1]] == ids[:1] and list(dict.fromkeys(r[0] for r in rows)) == ids
    # each kept row: log10 of the copies (blank: missing), right-censored ones (2) flagged at their upper limit
    for r in rows:
        src = next(c for c in cells if c[0] == r[0] and float(c[1]) == float(r[1]))
        if not src[3]:
            assert r[2] == "" and r[3] == "0"
            continue
        assert float(r[2]) == pytest.approx(np.log10(float(src[3])))
        assert r[3] == ("1" if src[4] in ("1", "2") else "0")
        if src[4] == "2":
            assert float(r[5]) == pytest.approx(np.log10(float(src[3])))
    _, fc = _rows(tmp_path / "o" / "forecast.csv")
    assert [r[0] for r in fc] == ids


def test_without_matplotlib_the_panel_files_are_written_and_the_figure_skipped(tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "matplotlib", None)
    text, _ = _panel_csv(subjects=3)
    res = _run(tmp_path, text, MODEL)
    assert res.exit_code == 0, res.output
    assert "skipped fit.png: the optional extra 'plot' is needed" in " ".join(res.output.split())
    assert {p.name for p in (tmp_path / "o").iterdir()} == {"fit.json", "summary.txt", "series.csv", "forecast.csv"}


def test_the_grid_series_agrees_with_the_smoothed_readings_at_the_sample_times(tmp_path):
    text, latent = _panel_csv(subjects=3)
    res = _run(tmp_path, text, MODEL.replace("forecast = 3", "grid = 1"))
    assert res.exit_code == 0, res.output
    _, series = _rows(tmp_path / "o" / "series.csv")
    head, grid = _rows(tmp_path / "o" / "grid.csv")
    assert head == "subject,time,smoothed,smoothed_sd,lower_95,upper_95"
    for sid, (days, _) in latent.items():
        mine = [g for g in grid if g[0] == sid]
        # every day from the subject's first sample to its last
        assert [float(g[1]) for g in mine] == list(np.arange(days[0], days[-1] + 1))
        at = {float(g[1]): g for g in mine}
        for r in (r for r in series if r[0] == sid):
            g = at[float(r[1])]  # a sample day: the same smoothed value and sd (the regressor of that sample)
            assert float(g[2]) == pytest.approx(float(r[6]), rel=1e-9, abs=1e-12)
            assert float(g[3]) == pytest.approx(float(r[7]), rel=1e-9, abs=1e-12)
        sds = np.array([float(g[3]) for g in mine])
        on_sample = np.isin([float(g[1]) for g in mine], days)
        assert sds[~on_sample].min() >= sds[on_sample].min()  # a day without a sample is known less well
    _one_line_error(_run(tmp_path, text, MODEL + "grid = 0\n"), "[model] grid: expected a step > 0")


def test_egret_interval_rows_through_tobitkf_fit(tmp_path):
    days = np.datetime64("2020-01-01") + np.array([0, 9, 30, 31, 45, 80, 90, 120, 150, 151])
    low = ["0.5", "", "0.9", "1.4", "0.02", "", "0.7", "2.0", "0.03", "0.8"]
    high = ["0.5", "0.2", "0.9", "1.4", "0.05", "0.2", "0.7", "2.0", "0.3", "0.8"]
    text = "Date,ConcLow,ConcHigh\n" + "".join(f"{d},{a},{b}\n" for d, a, b in zip(days, low, high))
    model = '[data]\ntime = "Date"\ntransform = "log"\n[model]\nkind = "ou"\nnoise_sd = 0.1\n'
    res = _run(tmp_path, text, model, "--format", "interval")
    assert res.exit_code == 0, res.output
    _, rows = _rows(tmp_path / "o" / "series.csv")
    assert rows[4][2:5] == ["1", repr(float(np.log(0.02))), repr(float(np.log(0.05)))]  # kept as an interval
    assert rows[1][2:5] == ["1", repr(float(np.log(0.2))), "inf"]  # left-censored at 0.2
    ll_keep = json.loads((tmp_path / "o" / "fit.json").read_text())["loglik"]
    left = model.replace("[model]", 'interval_rows = "left"\n[model]')
    res = _run(tmp_path, text, left, "--format", "interval", "--force")
    assert res.exit_code == 0, res.output
    _, rows = _rows(tmp_path / "o" / "series.csv")
    assert rows[4][2:5] == ["1", repr(float(np.log(0.05))), "inf"]  # read as below 0.05 instead
    assert abs(json.loads((tmp_path / "o" / "fit.json").read_text())["loglik"] - ll_keep) > 1e-3
