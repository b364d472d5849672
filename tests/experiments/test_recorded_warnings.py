"""Warnings raised while an experiment runs are recorded, not printed: the registered run collects each
distinct text once into ``metrics["warnings"]``, ``tobitkf reproduce`` writes it into metrics.json and the
report shows it under the experiment. Before, a diverging variant's warning went to the console of the main
job and nowhere else."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from typer.testing import CliRunner

import tobitkf as tk
from tobitkf import cli
from tobitkf.experiments import _REGISTRY, ExperimentResult, recorded_warnings, register

from ..filters.test_state_integrity import _one_sided_system

ID = "warnings-dummy"


def _run(*, runs, seed, progress=None):
    """An experiment comparing a healthy and a diverging variant, as the tracker and yardstick experiments do."""
    sys_, cens = _one_sided_system(2)
    d = tk.simulate(sys_, 200, runs, censoring=cens, seed=seed)
    est = {}
    for key, kw in (("tkf", {}), ("tkf_total_variance", {"noise_term": "total_variance"})):
        for _ in range(2):  # the same warning twice: recorded once
            res = tk.TobitKalmanFilter(sys_, cens, backend="numpy", **kw).filter(d.y)
        est[key] = tk.metrics.summarize(d.x[:, 1:], res.mean)
    warnings.warn("a second, different warning", UserWarning, stacklevel=1)
    return ExperimentResult(id=ID, settings={}, metrics={"estimators": est})


def _no_plot(result, outdir):
    return []


@pytest.fixture
def dummy():
    run = register(ID, title="warnings", source="test", plot=_no_plot, default_runs=20)(_run)
    yield run
    _REGISTRY.pop(ID, None)


def test_recorded_warnings_keeps_each_text_once_in_order():
    with warnings.catch_warnings(record=True) as outer:
        warnings.simplefilter("always")
        with recorded_warnings() as found:
            for text in ("b", "a", "b", "c  with   spaces"):
                warnings.warn(text, RuntimeWarning, stacklevel=1)
    assert found == ["b", "a", "c with spaces"]
    assert outer == []  # nothing escapes the block


def test_an_experiments_warnings_go_to_metrics_json_and_the_report_not_the_console(dummy, tmp_path):
    res = CliRunner().invoke(cli.app, ["reproduce", ID, "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    assert "far larger" not in res.output and "different warning" not in res.output
    metrics = json.loads((tmp_path / ID / "metrics.json").read_text())
    found = metrics["warnings"]
    assert len(found) == 2, found
    assert "far larger than its own covariance" in found[0]
    assert "noise_term='dissertation' or 'exact_pv'" in found[0]
    assert found[1] == "a second, different warning"
    html = (tmp_path / "index.html").read_text()
    md = (tmp_path / "REPORT.md").read_text()
    for text in ("Warnings while it ran", "a second, different warning", "far larger than its own covariance"):
        assert text in html and text in md
    # the healthy variant is not what warned: its RMSE is far below the diverging one's
    est = metrics["estimators"]
    assert np.mean(est["tkf"]["rmse_time_avg"]) * 10 < np.mean(est["tkf_total_variance"]["rmse_time_avg"])


def test_an_experiment_without_warnings_records_an_empty_list_and_the_report_no_section(dummy, tmp_path):
    def quiet(*, runs, seed, progress=None):
        return ExperimentResult(id=ID, settings={}, metrics={})

    register(ID, title="warnings", source="test", plot=_no_plot, default_runs=2)(quiet)
    res = CliRunner().invoke(cli.app, ["reproduce", ID, "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    assert json.loads((tmp_path / ID / "metrics.json").read_text())["warnings"] == []
    assert "Warnings while it ran" not in (tmp_path / "index.html").read_text()
