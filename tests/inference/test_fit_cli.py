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
        ("[data]\n", "needs y"),
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
