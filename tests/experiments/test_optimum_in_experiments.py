"""The optimum inside the experiments whose readings pass a random channel: key ``pf`` with its particle
count and convergence check, and every estimator's ``ratio_to_optimum`` on the same runs."""

from __future__ import annotations

import numpy as np
import pytest

import tobitkf as tk
from tobitkf.experiments import get

CASES = {
    "miller-constant": dict(steps=30),
    "miller-brownian": dict(steps=30),
    "miller-oscillator": dict(steps=30, omega_sweep=(0.05,)),
    "geng2017-oscillator": dict(steps=20),
    "geng2017-radar": dict(steps=15),
    "geng-protocol-tracking": dict(steps=20),
    "geng-protocol-bounds": dict(steps=15),
    "geng-protocol-threshold": dict(steps=15),
}


def _blocks(metrics):
    if "scenarios" in metrics:
        return [s["estimators"] for s in metrics["scenarios"].values()]
    return [metrics["estimators"]]


@pytest.mark.parametrize("exp_id", sorted(CASES))
def test_pf_and_ratios_are_in_the_metrics(exp_id):
    res = get(exp_id).run(runs=12, seed=2, optimum_particles=40, optimum_runs=8, **CASES[exp_id])
    for est in _blocks(res.metrics):
        pfs = [k for k in est if k == "pf" or k.startswith("pf-")]
        assert pfs
        for key in pfs:
            pf = est[key]
            assert pf["particles"] == 80 and pf["ratio_runs"] == 8
            assert set(pf["convergence"]) >= {"particles", "relative_change", "converged", "tolerance"}
        for key, s in est.items():
            if not key.startswith("pf"):
                assert "ratio_to_optimum" in s and len(s["ratio_to_optimum"]) == len(s["rmse_time_avg"])
                assert all(v > 0 for v in s["ratio_to_optimum"])


def test_the_ratio_is_taken_on_the_same_runs():
    res = get("miller-brownian").run(runs=12, seed=2, steps=30, optimum_particles=40, optimum_runs=12)
    est = res.metrics["estimators"]
    np.testing.assert_allclose(
        est["tkf"]["ratio_to_optimum"], np.asarray(est["tkf"]["rmse_time_avg"]) / est["pf"]["rmse_time_avg"]
    )


def test_no_particle_filter_on_request_and_bad_counts_refused():
    res = get("miller-brownian").run(runs=5, seed=1, steps=20, optimum_particles=0)
    assert "pf" not in res.metrics["estimators"]
    with pytest.raises(tk.ValidationError, match="optimum_particles: expected an integer >= 0"):
        get("geng-protocol-mect").run(runs=5, seed=1, steps=10, optimum_particles=-1)
    with pytest.raises(tk.ValidationError, match="optimum_runs: expected a positive integer"):
        get("geng-protocol-mect").run(runs=5, seed=1, steps=10, optimum_runs=0)
