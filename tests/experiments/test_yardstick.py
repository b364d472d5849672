"""The yardstick experiment (tobitkf.experiments.yardstick): structure, the same data as the experiments,
the ratios, the convergence check, the figures and the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

import tobitkf as tk
from tobitkf.cli import app
from tobitkf.experiments import get
from tobitkf.experiments.yardstick import EXAMPLES, optimum_ratios, random_stable_system


@pytest.fixture(scope="module")
def small():
    return get("yardstick").run(runs=12, steps=25, random_systems=2, particles=100, seed=3, doublings=0)


def test_every_example_and_random_system_has_every_estimator_and_its_ratio(small):
    m = small.metrics
    assert list(m["examples"]) == list(EXAMPLES) and list(m["random_systems"]) == ["random-01", "random-02"]
    for name, ex in list(m["examples"].items()) + list(m["random_systems"].items()):
        est = ex["estimators"]
        assert "pf" in est and "adf" in est
        pf = est["pf"]
        assert pf["particles"] == 200 and pf["convergence"]["particles"] == [100, 200]
        assert len(pf["convergence"]["relative_change"]) == len(pf["rmse_time_avg"])
        np.testing.assert_allclose(pf["ratio_to_optimum"], 1.0)
        for key, s in est.items():
            np.testing.assert_allclose(s["ratio_to_optimum"], np.asarray(s["rmse_time_avg"]) / pf["rmse_time_avg"])
        assert ex["runs"] == 12 and ex["steps"] == 25
        assert ("pcrlb" in ex) == (name not in ("miller-constant", "geng-protocol-tracking", "saturation-oscillator"))
    assert {r["example"] for r in m["table"]} == set(EXAMPLES) | {"random-01", "random-02"}
    assert any("1.02x of the optimum" in c["claim"] for c in small.claims)


def test_same_data_as_the_experiments():
    """miller-brownian and geng2017-oscillator: the yardstick's estimators see the experiments' own readings."""
    y = get("yardstick").run(
        runs=8, steps=20, random_systems=0, particles=50, seed=5, examples=("miller-brownian", "geng2017-oscillator")
    )
    b = get("miller-brownian").run(runs=8, seed=5, steps=20)
    np.testing.assert_allclose(
        y.metrics["examples"]["miller-brownian"]["estimators"]["tkf"]["rmse"],
        b.metrics["estimators"]["tkf"]["rmse"],
        rtol=1e-12,
    )
    g = get("geng2017-oscillator").run(runs=8, seed=5, steps=20)
    np.testing.assert_allclose(
        y.metrics["examples"]["geng2017-oscillator"]["estimators"]["tkf-fm"]["rmse"],
        g.metrics["estimators"]["tkf-fm"]["rmse"],
        rtol=1e-12,
    )


def test_particle_ladder_doubles_until_converged_and_reports_every_pair(small):
    """The ladder's first pair is the plain check (same seeds); it doubles only while the check fails, up to
    the cap, and the optimum is the last rung; the protocol row runs the Rao-Blackwellised filter."""
    from tobitkf.experiments._optimum import pf_check

    ex = small.metrics["examples"]["geng-protocol-tracking"]
    assert ex["estimators"]["pf"]["proposal"] == "rao_blackwellised"
    assert small.metrics["examples"]["miller-brownian"]["estimators"]["pf"]["proposal"] == "optimal"
    from tobitkf.experiments.yardstick import _case

    for name, doublings in (("miller-oscillator", 3), ("saturation-oscillator", 2)):
        case = _case(name, 30, 40, 0)
        sim, args = case["sim"], (case["system"], case["channel"], case["sim"].y, case["sim"].x, 2, 0)
        plain, _ = pf_check(*args, proposal="prior")
        keys = ("particles", "relative_change", "stderr", "converged")
        assert plain["ladder"] == [{k: plain["convergence"][k] for k in keys}]
        lad, res = pf_check(*args, proposal="prior", doublings=doublings)
        steps = lad["ladder"]
        assert steps[0] == plain["ladder"][0] and not steps[0]["converged"]  # 2 particles: not converged
        assert [s["particles"] for s in steps] == [[2 * 2**i, 2 * 2 ** (i + 1)] for i in range(len(steps))]
        assert all(not s["converged"] for s in steps[:-1])
        assert steps[-1]["converged"] or len(steps) == doublings + 1
        assert lad["particles"] == steps[-1]["particles"][1]
        assert lad["convergence"]["converged"] == steps[-1]["converged"]
        np.testing.assert_allclose(lad["rmse_time_avg"], np.sqrt(((res.mean - sim.x[:, 1:]) ** 2).mean(0)).mean(0))
    # the two cases: one stops converged before the cap, one reaches the cap unconverged
    assert len(steps) == 3 and not steps[-1]["converged"]
    with pytest.raises(tk.ValidationError, match="doublings: expected an integer >= 0"):
        pf_check(*args, doublings=-1)


def test_random_systems_censor_30_to_90_percent():
    rng = np.random.default_rng(0)
    for _ in range(10):
        sys_, cens, desc = random_stable_system(rng)
        assert max(abs(np.linalg.eigvals(sys_.A.at(0)))) < 0.99
        d = tk.simulate(sys_, 200, 100, censoring=cens, seed=1)
        lo, hi = cens.censored_mask(d.y)
        frac = (lo | hi).mean(axis=(0, 1))
        np.testing.assert_allclose(frac, desc["target_censored_fraction"], atol=0.08)
        assert (0.25 < frac).all() and (frac < 0.95).all()


def test_optimum_ratios():
    s = {"pf": {"rmse_time_avg": [1.0, 2.0]}, "a": {"rmse_time_avg": [1.5, 2.0]}}
    optimum_ratios(s)
    assert s["a"]["ratio_to_optimum"] == [1.5, 1.0] and s["pf"]["ratio_to_optimum"] == [1.0, 1.0]


def test_bad_settings_are_refused():
    run = get("yardstick").run
    with pytest.raises(tk.ValidationError, match="examples: unknown example 'miller-radar'"):
        run(runs=2, examples=("miller-radar",))
    with pytest.raises(tk.ValidationError, match="random_systems: expected an integer >= 0"):
        run(runs=2, random_systems=-1)
    with pytest.raises(tk.ValidationError, match="particles: expected a positive integer or None"):
        run(runs=2, particles=0)
    with pytest.raises(tk.ValidationError, match="doublings: expected an integer >= 0"):
        run(runs=2, doublings=True)


def test_figures_and_cli(tmp_path, small):
    paths = get("yardstick").plot(small, tmp_path)
    names = {p.name for p in paths}
    assert "ratio_to_optimum.png" in names and "rmse_miller-brownian.png" in names and "rmse_random-02.png" in names
    runner = CliRunner()
    res = runner.invoke(app, ["list"])
    assert res.exit_code == 0 and "yardstick" in res.output


def test_metrics_are_json(small):
    import tempfile
    from pathlib import Path

    from tobitkf._io import atomic_write_json

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "m.json"
        atomic_write_json(p, small.metrics)
        back = json.loads(p.read_text())
    assert back["examples"]["miller-oscillator"]["estimators"]["pf"]["convergence"]["tolerance"] == 0.003


def test_particle_check_runs_in_blocks_of_runs(monkeypatch):
    """With more runs than RUN_BLOCK the particle filter runs block by block: block 0 seeded as the unblocked
    call (SeedSequence([seed, 7, i])), block b > 0 with SeedSequence([seed, 7, i, b]), each on its runs; the
    means are the blocks' in order (checked against direct filters), the summary is computed from them."""
    from tobitkf.experiments import _optimum
    from tobitkf.experiments.yardstick import _case

    case = _case("miller-oscillator", 7, 20, 0)
    sys_, cens, sim = case["system"], case["channel"], case["sim"]
    whole, whole_res = _optimum.pf_check(sys_, cens, sim.y, sim.x, 5, 4)
    monkeypatch.setattr(_optimum, "RUN_BLOCK", 3)
    blocked, res = _optimum.pf_check(sys_, cens, sim.y, sim.x, 5, 4)
    assert res.mean.shape == whole_res.mean.shape and res.var.shape == whole_res.var.shape
    for b, r0 in enumerate(range(0, 7, 3)):
        seed = np.random.SeedSequence([4, 7, 1]) if b == 0 else np.random.SeedSequence([4, 7, 1, b])
        direct = tk.ParticleFilter(sys_, cens, particles=10, seed=seed).filter(sim.y[r0 : r0 + 3])
        np.testing.assert_array_equal(res.mean[r0 : r0 + 3], direct.mean)
    # (block 0 is not the unblocked call restricted to its runs: one generator draws for the whole batch)
    np.testing.assert_allclose(
        blocked["rmse_time_avg"], np.sqrt(((res.mean - sim.x[:, 1:]) ** 2).mean(0)).mean(0), rtol=1e-12
    )


def test_the_default_size_runs_fewer_runs_with_the_same_horizons_and_particles():
    """size="default" (tobitkf reproduce) runs each example at _DEFAULT_RUNS, size="full" (--full) at its own
    experiment's run count; the CLI passes size="full" with --full; a bad size is refused."""
    from tobitkf.experiments import yardstick as Y

    kw = {"steps": 3, "particles": 4, "random_systems": 1, "examples": ("geng-protocol-tracking",), "doublings": 0}
    small = Y.run(**kw)
    full = Y.run(size="full", **kw)
    for res, runs in ((small, Y._DEFAULT_RUNS), (full, {**{k: v[0] for k, v in Y._OWN.items()}, "random": 200})):
        ex, rs = res.metrics["examples"]["geng-protocol-tracking"], res.metrics["random_systems"]["random-01"]
        assert ex["runs"] == runs["geng-protocol-tracking"] and rs["runs"] == runs["random"]
        assert ex["steps"] == rs["steps"] == 3 and ex["estimators"]["pf"]["particles"] == 8
    assert full.settings["size"]["value"] == "full" and small.settings["size"]["value"] == "default"
    assert Y.run(runs=7, **kw).metrics["examples"]["geng-protocol-tracking"]["runs"] == 7  # runs caps
    exp = get("yardstick")
    assert exp.settings_for(True) == {"size": "full"} and exp.runs_for(True) >= max(runs.values())
    assert exp.runs_for(False) >= max(Y._DEFAULT_RUNS.values())
    with pytest.raises(tk.ValidationError, match="size: expected one of 'default', 'full'"):
        Y.run(size="huge", **kw)


def test_ratio_stderr_is_the_jackknife_of_the_ratio():
    """ratio_stderr against the leave-one-run-out ratios computed by brute force."""
    from tobitkf.experiments._optimum import ratio_stderr

    rng = np.random.default_rng(2)
    e_opt = rng.gamma(2.0, 1.0, size=(9, 6, 2))
    e_est = e_opt * rng.uniform(1.0, 1.5, size=e_opt.shape)

    def ratio(a, b):
        return np.sqrt(a.mean(0)).mean(0) / np.sqrt(b.mean(0)).mean(0)

    loo = np.array([ratio(np.delete(e_est, r, 0), np.delete(e_opt, r, 0)) for r in range(9)])
    se = np.sqrt(8 / 9 * ((loo - loo.mean(0)) ** 2).sum(0))
    np.testing.assert_allclose(ratio_stderr(e_est, e_opt), se, rtol=1e-12)
