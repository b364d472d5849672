"""The real-data experiments (tobitkf.experiments.data_sets): metrics.json fields, the hold-out design,
the figures."""

import json

import numpy as np
import pytest

from tobitkf.data import load_cloud_ceiling, load_phosphorus
from tobitkf.experiments import get
from tobitkf.experiments.data_sets import ESTIMATORS, _holdout


@pytest.mark.parametrize("frac", [0.3, 0.5])
def test_holdout_moves_the_limit_into_the_data(frac):
    for s, side in ((load_phosphorus(), -1), (load_cloud_ceiling(), 1)):
        h = _holdout(s, None, frac, side)
        present = ~np.isnan(s.y) & ~s.censored
        n = int(present.sum())
        # readings are rounded: ties can make the target unreachable; the closest count is taken
        counts = np.searchsorted(
            np.sort(np.where(side < 0, s.y - s.lower, s.upper - s.y)[present]),
            np.sort(np.where(side < 0, s.y - s.lower, s.upper - s.y)[present]),
            side="right",
        )
        assert abs(h["held"].sum() - frac * n) == np.min(np.abs(counts - frac * n))
        assert h["fraction"] == pytest.approx(h["held"].sum() / n)
        assert not np.any(h["held"] & ~present)
        assert np.all(h["censored"] == (s.censored | h["held"]))
        lim = h["lower"] if side < 0 else h["upper"]
        np.testing.assert_array_equal(h["y"][h["censored"]], lim[h["censored"]])  # censored at the moved limit
        np.testing.assert_array_equal(h["truth"][present], s.y[present])
        kept = present & ~h["held"]
        assert np.all((h["y"][kept] > lim[kept]) if side < 0 else (h["y"][kept] < lim[kept]))


@pytest.fixture(scope="module")
def phosphorus_result():
    return get("data-phosphorus").run(runs=1, seed=0)


def test_phosphorus_metrics_hold_the_fields_the_issue_names(phosphorus_result):
    m = phosphorus_result.metrics
    for model, names in (
        ("ar1", {"beta0", "beta1", "sigma2", "phi1"}),
        ("ar2", {"beta0", "beta1", "sigma2", "phi1", "phi2"}),
    ):
        rec = m[model]
        assert set(rec["estimates"]) == names and set(rec["se"]) == names
        assert all(v > 0 for v in rec["se"].values())
        k = len(names)
        assert rec["aic"] == pytest.approx(-2 * rec["loglik"] + 2 * k)
        assert rec["bic"] == pytest.approx(-2 * rec["loglik"] + k * np.log(174))
        assert rec["fit_seconds"] > 0 and rec["converged"]
        assert abs(rec["quadrature_check"]["difference"]) < 1e-6
    assert m["ar2"]["loglik"] >= m["ar1"]["loglik"]  # nested models
    for key in ("30%", "50%"):
        h = m["holdout"][key]
        assert set(h["estimators"]) == set(ESTIMATORS)
        assert all(np.isfinite(v["rmse"]) and np.isfinite(v["bias"]) for v in h["estimators"].values())
    json.dumps(m)  # JSON-able as written


def test_phosphorus_figures(phosphorus_result, tmp_path):
    exp = get("data-phosphorus")
    paths = exp.plot(phosphorus_result, tmp_path)
    assert {p.name for p in paths} == {"series.png", "holdout.png", "residuals.png"}
    assert all(p.stat().st_size > 1000 for p in paths)
