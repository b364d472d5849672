"""Miller ch.3 experiments: registry, CLI output, and the analytic claims they check."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from tobitkf._validation import ValidationError
from tobitkf.cli import app
from tobitkf.experiments import all_experiments, get

MILLER = ["miller-brownian", "miller-constant", "miller-oscillator", "miller-steady-state"]


def test_registry_lists_miller_experiments():
    ids = [e.id for e in all_experiments()]
    for exp_id in MILLER:
        assert exp_id in ids
    with pytest.raises(ValidationError, match="unknown id"):
        get("no-such-experiment")


def test_cli_list_and_reproduce_write_metrics_and_figures(tmp_path):
    runner = CliRunner()
    res = runner.invoke(app, ["list"])
    assert res.exit_code == 0 and "miller-constant" in res.output
    res = runner.invoke(app, ["reproduce", "miller-constant", "--runs", "30", "--seed", "3", "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    out = tmp_path / "miller-constant"
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["runs"] == 30 and metrics["seed"] == 3
    for fig in metrics["figures"]:
        assert (out / fig).stat().st_size > 1000
    for scen in metrics["scenarios"].values():
        for key in ("kf", "ikf", "tkf"):
            rmse = np.asarray(scen["estimators"][key]["rmse"])
            assert rmse.shape == (1000, 1)
            np.testing.assert_allclose(scen["estimators"][key]["rmse_time_avg"], rmse.mean(axis=0))
    assert metrics["settings"]["limit"]["provenance"] == "default"
    res = runner.invoke(app, ["reproduce", "nope", "--out", str(tmp_path)])
    assert res.exit_code == 2


def test_same_seed_same_metrics():
    a = get("miller-brownian").run(runs=5, seed=1, steps=100)
    b = get("miller-brownian").run(runs=5, seed=1, steps=100)
    np.testing.assert_array_equal(a.metrics["estimators"]["tkf"]["rmse"], b.metrics["estimators"]["tkf"]["rmse"])


def test_constant_example_analytic_limits_hold():
    """Spec 001a §3.6: KF -> E[y], IKF -> E[y | y > 0], TKF -> truth; tolerance from the run count."""
    res = get("miller-constant").run(runs=200, seed=0, optimum_particles=0)
    assert all(c["holds"] for c in res.claims), res.claims
    lim = res.metrics["scenarios"]["truth-0.1"]["analytic_limit"]
    assert lim["kf"] == pytest.approx(0.00833, abs=1e-5)
    assert lim["ikf"] == pytest.approx(0.05251, abs=1e-5)


def test_steady_state_experiment_hits_dare():
    res = get("miller-steady-state").run(runs=10, seed=0, steps=400)
    for vals in res.metrics["controlled_limit"].values():
        assert vals["full_tkf_cov_minus_dare_at_T"] < 1e-6
        assert vals["full_tkf_max_abs_Ep_minus_xi"] < 1e-9
