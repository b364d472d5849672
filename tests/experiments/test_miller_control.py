"""Miller Ch. 5-6 experiments: registry, CLI output, multi-region checks T16-T17, FOV T18."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from tobitkf import Censoring, LinearSystem, TobitKalmanFilter, multi_region, simulate
from tobitkf.cli import app
from tobitkf.experiments import all_experiments, get

IDS = [
    "miller-jacobian-scalar",
    "miller-dc-motor-speed",
    "miller-dc-motor-position",
    "miller-closed-loop",
    "miller-steady-state-lqg",
    "miller-multi-region",
    "miller-fov",
    "miller-panning",
]


def test_registry_has_the_chapter_5_6_experiments():
    ids = [e.id for e in all_experiments()]
    for exp_id in IDS:
        assert exp_id in ids


def test_cli_reproduce_jacobian_scalar(tmp_path):
    res = CliRunner().invoke(app, ["reproduce", "miller-jacobian-scalar", "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    m = json.loads((tmp_path / "miller-jacobian-scalar" / "metrics.json").read_text())
    assert m["gains"]["L_uncensored"]["computed"] == pytest.approx(m["gains"]["L_uncensored"]["printed"], abs=5e-5)
    assert m["j22_printed_5_56"]["0.25"] == pytest.approx(-0.81051, abs=1e-5)
    assert m["recomputed_L"]["0.0"]["J22"] == pytest.approx(-0.81702, abs=1e-5)
    for fig in m["figures"]:
        assert (tmp_path / "miller-jacobian-scalar" / fig).stat().st_size > 1000


def test_t18_fov_covariances_against_the_riccati_values():
    result = get("miller-fov").run(runs=5, seed=1)
    sc = result.metrics["scenarios"]
    non, over = sc["non-overlapping"], sc["overlapping"]
    assert non["mean_P11"]["one camera"] == pytest.approx(non["dare_P11"]["1 camera"], rel=0.1)
    assert over["mean_P11"]["both cameras"] == pytest.approx(over["dare_P11"]["2 cameras"], rel=0.1)
    assert non["mean_P11"]["no camera"] > 2 * non["mean_P11"]["one camera"]
    for est in non["estimators"].values():
        assert np.asarray(est["rmse"]).shape == (300, 2)


def _brownian(sigma, channels=1):
    return LinearSystem(
        A=[[0.99]],
        C=np.ones((channels, 1)),
        Q=[[0.01]],
        R=np.eye(channels) * sigma**2,
        x0=[0.0],
        P0=[[0.01 / (1 - 0.99**2)]],
    )


def test_t16_two_sided_sensors_see_both_half_spaces():
    base = _brownian(0.05)
    sys2, cens2 = multi_region(base, [[(-np.inf, 0.0), (0.0, np.inf)]])
    sim = simulate(sys2, 2000, 5, censoring=cens2, seed=11)
    two = TobitKalmanFilter(sys2, cens2).filter(sim.y).mean[..., 0]
    one = TobitKalmanFilter(base, Censoring(upper=0.0)).filter(sim.y[..., :1]).mean[..., 0]
    x = sim.x[:, 1:, 0]
    pos, neg = x > 0, x <= 0
    r = lambda est, m: np.sqrt(np.mean((est[m] - x[m]) ** 2))  # noqa: E731
    assert r(two, pos) == pytest.approx(r(two, neg), rel=0.2)
    assert r(two, pos) < 0.07
    assert r(one, pos) > 5 * r(one, neg)  # right-censored sensor alone: blind above 0 (0.64 vs 0.069)


def test_t17_mse_decreases_with_the_number_of_sensors():
    sys16 = _brownian(0.5, 16)
    sim = simulate(sys16, 2000, 10, censoring=Censoring(upper=0.0), seed=7)
    mse = []
    for n_y in (1, 4, 16):
        out = TobitKalmanFilter(_brownian(0.5, n_y), Censoring(upper=0.0)).filter(sim.y[..., :n_y])
        mse.append(np.mean((out.mean[..., 0] - sim.x[:, 1:, 0]) ** 2))
    # spec [S]: 0.095, 0.047, 0.029 with SE ~ 0.005
    assert mse[0] > mse[1] + 0.01 and mse[1] > mse[2] + 0.005
