"""The nonlinear experiments (tobitkf.experiments.nonlinear): the models against analytic values and independent
oracles, the autopilots' heuristics against the filters they are built from, the bimodality coefficient against
its known values, and the metrics keys the report reads."""

from __future__ import annotations

import json

import numpy as np
import pytest

import tobitkf as tk
from tobitkf.experiments import _nonlinear as NL
from tobitkf.experiments import get
from tobitkf.experiments import nonlinear as E

# --------------------------------------------------------------------------- the oscillator


def test_the_oscillator_map_is_the_van_der_pol_flow_and_keeps_its_parameter():
    from scipy.integrate import solve_ivp

    x0 = np.array([[2.0, -0.3, 1.3], [0.4, 1.1, 0.6]])
    out = E._vdp_map(x0, 0)
    for row, got in zip(x0, out):
        mu = row[2]
        sol = solve_ivp(
            lambda t, z: [z[1], mu * (1 - z[0] ** 2) * z[1] - z[0]],
            (0.0, E.OSCILLATOR_DT),
            row[:2],
            rtol=1e-12,
            atol=1e-12,
        )
        # two RK4 substeps of 0.05: local error O(h^5) per substep, about 1e-7 here
        np.testing.assert_allclose(got[:2], sol.y[:, -1], atol=1e-6)
        assert got[2] == mu
    assert E._vdp_map(x0[0], 0).shape == (3,)  # unbatched too


def test_the_oscillator_is_read_under_a_detection_limit_at_zero():
    system, cens = E.oscillator_system()
    assert (system.n, system.m) == (3, 1)
    data = tk.simulate(system, 60, 20, channel=cens, seed=4)
    np.testing.assert_array_equal(data.y, np.maximum(data.y_latent, 0.0))
    np.testing.assert_array_equal(system.measurement_map(data.x[0, 1:], 1)[:, 0], data.x[0, 1:, 0])
    assert 0.2 < cens.at_limit(data.y).mean() < 0.8


# --------------------------------------------------------------------------- the accelerometer


def test_the_vibration_turns_by_its_frequency_damps_and_its_frequency_reverts():
    x = np.array([[1.5, -0.4, 0.45], [-2.0, 0.7, 0.6]])
    out = E._vibration_map(x, 0)
    w = x[:, 2]
    # (p, v/w) rotated by w: its norm is kept up to the damping; the phase advances by w
    z0 = x[:, 0] + 1j * x[:, 1] / w
    z1 = out[:, 0] + 1j * out[:, 1] / w
    np.testing.assert_allclose(np.abs(z1), E.ACCEL_DAMPING * np.abs(z0), rtol=1e-14)
    np.testing.assert_allclose(np.angle(z1 / z0), -w, rtol=1e-13)
    np.testing.assert_allclose(out[:, 2] - E.ACCEL_OMEGA, E.ACCEL_REVERSION * (w - E.ACCEL_OMEGA), rtol=1e-14)


def test_the_accelerometer_reads_the_acceleration_and_clips_at_its_range():
    system, clip = E.accelerometer_system()
    x = np.array([[3.0, 0.0, 0.5], [-1.0, 2.0, 0.4]])
    np.testing.assert_allclose(system.measurement_map(x, 1)[:, 0], [-0.75, 0.16], rtol=1e-14)
    data = tk.simulate(system, 100, 20, channel=clip, seed=5)
    np.testing.assert_array_equal(data.y, np.clip(data.y_latent, -1.0, 1.0))
    at = clip.at_limit(data.y)
    np.testing.assert_array_equal(at, np.abs(data.y_latent) >= 1.0)
    assert 0.1 < at.mean() < 0.6  # the peaks are clipped, not the whole signal


def test_dropping_clipped_readings_is_the_filter_of_the_record_with_them_missing():
    system, clip = E.accelerometer_system()
    data = tk.simulate(system, 40, 3, channel=clip, seed=6)
    y = data.y.copy()
    y[clip.at_limit(y)] = np.nan
    want = tk.ExtendedKalmanFilter(system).filter(y).mean
    got = NL.DropClipped(tk.ExtendedKalmanFilter(system), clip).filter(data.y).mean
    np.testing.assert_array_equal(got, want)
    assert np.isnan(y).any()


def test_inflating_a_clipped_reading_is_the_filter_with_that_steps_noise_inflated():
    system, clip = E.accelerometer_system()
    data = tk.simulate(system, 30, 1, channel=clip, seed=7)
    at = clip.at_limit(data.y)[0, :, 0]
    assert at.any() and not at.all()
    c = 0.7
    R = np.array([system.measurement_cov(k) + (c**2 if at[k - 1] else 0.0) for k in range(1, 31)])
    inflated = tk.NonlinearSystem(
        system.f, system.h, Q=system.process_cov(0), R=R, x0=system.x0, P0=system.P0
    )  # the oracle: the noise of the clipped steps given per step
    want = tk.ExtendedKalmanFilter(inflated).filter(data.y[0])
    got = NL.InflateClipped(system, clip, inflation=c).filter(data.y[0])
    np.testing.assert_allclose(got.mean, want.mean, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.cov, want.cov, rtol=0, atol=1e-12)
    # no clipped reading: the extended Kalman filter itself
    y = np.clip(data.y[0], -0.9, 0.9)
    np.testing.assert_array_equal(
        NL.InflateClipped(system, clip, inflation=c).filter(y).mean, tk.ExtendedKalmanFilter(system).filter(y).mean
    )


# --------------------------------------------------------------------------- the localisation


def test_the_signal_strength_follows_the_path_loss_and_is_censored_beyond_range():
    system, cens = E.localisation_system()
    b = E.BEACONS
    x = np.array([b[0] + [30.0, 40.0]])  # 50 m from beacon 1
    d = np.sqrt(((x[0] - b) ** 2).sum(-1) + 1.0)
    want = E.RSS_P0 - 10 * E.RSS_ETA * np.log10(d)
    np.testing.assert_allclose(system.measurement_map(x, 1)[0], want, rtol=1e-14)
    reach = 10 ** ((E.RSS_P0 - E.RSS_FLOOR) / (10 * E.RSS_ETA))  # the range: the floor's distance
    at_reach = np.array([[b[1, 0] - np.sqrt(reach**2 - 1.0), b[1, 1]]])
    np.testing.assert_allclose(system.measurement_map(at_reach, 1)[0, 1], E.RSS_FLOOR, atol=1e-12)
    data = tk.simulate(system, 50, 20, channel=cens, seed=8)
    np.testing.assert_array_equal(data.y, np.maximum(data.y_latent, E.RSS_FLOOR))
    assert cens.at_limit(data.y).any() and not cens.at_limit(data.y).all()


def test_the_bimodality_coefficient_has_its_known_values():
    rng = np.random.default_rng(0)
    P = 200_000
    # Gaussian 1/3, uniform 5/9, two equal point masses 1: along the principal axis of a 2-D cloud
    gauss = rng.standard_normal((1, P, 2)) * [3.0, 0.5]
    unif = np.stack([rng.uniform(-1, 1, P), 0.01 * rng.standard_normal(P)], -1)[None]
    two = np.zeros((1, P, 2))
    two[0, : P // 2, 1], two[0, P // 2 :, 1] = -1.0, 1.0
    lw = np.zeros((1, P))
    got = [float(E.bimodality(c, lw)[0]) for c in (gauss, unif, two)]
    # sampling error of a moment ratio over 2e5 draws: below 0.01
    np.testing.assert_allclose(got, [1 / 3, 5 / 9, 1.0], atol=0.01)
    # the weights count: a cloud with half its particles weighted zero is the other half
    cloud = np.concatenate([gauss[:, : P // 2], two[:, : P // 2] + 100.0], axis=1)
    w = np.concatenate([np.zeros(P // 2), np.full(P // 2, -np.inf)])[None]
    np.testing.assert_allclose(E.bimodality(cloud, w), E.bimodality(gauss[:, : P // 2], lw[:, : P // 2]), rtol=1e-9)


# --------------------------------------------------------------------------- the random systems


def test_random_nonlinear_systems_censor_about_their_drawn_fraction():
    for i in range(3):
        rng = np.random.default_rng(100 + i)
        system, cens, desc = E.random_nonlinear_system(rng)
        assert desc["n"] in (2, 3) and desc["m"] in (1, 2) and (system.n, system.m) == (desc["n"], desc["m"])
        frac = np.asarray(desc["target_censored_fraction"])
        assert np.all((0.3 <= frac) & (frac <= 0.9))
        data = tk.simulate(system, 100, 100, channel=cens, seed=200 + i)
        got = cens.at_limit(data.y).reshape(-1, system.m).mean(0)
        # the limit is the quantile of a pilot of 20 runs x 100 correlated steps (a few hundred effective
        # samples: standard error about 0.035); 0.1 is about three of them
        np.testing.assert_allclose(got, frac, atol=0.1)
        lo, hi = cens.limits(1)
        for l, side in enumerate(desc["side"]):
            assert np.isfinite(hi[l] if side == "upper" else lo[l])
            assert np.isinf(lo[l] if side == "upper" else hi[l])


# --------------------------------------------------------------------------- the experiments' metrics


@pytest.fixture(scope="module")
def tiny():
    kw = dict(runs=3, seed=1, steps=12, particles=40, compare_runs=5)
    return {
        "nonlinear-oscillator": get("nonlinear-oscillator").run(**kw),
        "nonlinear-accelerometer": get("nonlinear-accelerometer").run(**kw),
        "nonlinear-localisation": get("nonlinear-localisation").run(**kw, bimodality_runs=2),
        "nonlinear-random": get("nonlinear-random").run(**kw, systems=2),
    }


def _blocks(result):
    m = result.metrics
    return list(m["systems"].values()) if "systems" in m else [m]


@pytest.mark.parametrize(
    "exp_id", ["nonlinear-oscillator", "nonlinear-accelerometer", "nonlinear-localisation", "nonlinear-random"]
)
def test_each_experiment_writes_the_metrics_the_report_reads(tiny, exp_id):
    result = tiny[exp_id]
    want = set(NL.LINEUP) | {"pf"} | ({"ekf-inflate", "ekf-drop"} if exp_id == "nonlinear-accelerometer" else set())
    want |= {"gsf"} if exp_id == "nonlinear-localisation" else set()
    for block in _blocks(result):
        est = block["estimators"]
        assert set(est) == want
        assert "errors" not in block  # the errors stay out of metrics.json
        for key, s in est.items():
            n = len(s["rmse_time_avg"])
            assert np.shape(s["rmse"]) == (12, n)
            np.testing.assert_allclose(
                s["ratio_to_optimum"], np.asarray(s["rmse_time_avg"]) / est["pf"]["rmse_time_avg"]
            )
            assert s["cost_us_per_run_step"] > 0 and s["diverged_runs"] >= 0
            assert key == "pf" or len(s["ratio_stderr"]) == n
        assert est["pf"]["convergence"]["particles"] == [40, 80]
        assert block["runs"] == 3 and block["steps"] == 12
        assert block["comparison"]["runs"] == 5 and "compare_errors" not in block
        assert {"adf", "tobit-ekf", "tobit-ukf"} <= set(block["comparison"]["estimators"])
    assert result.metrics["report_tables"] and result.metrics["lineup"]["pf"]["options"]["particles"] == 80
    texts = [c["claim"] for c in result.claims]
    for c in result.claims:
        if "more accurate than" in c["claim"]:
            assert "on the same 5 runs" in c["quantity"]  # measured on the comparison runs
    for case in list(result.metrics["systems"]) if exp_id == "nonlinear-random" else [None]:
        mine = [t for t in texts if case is None or f" {case}:" in t]
        assert sum("within" in t for t in mine) == (2 if exp_id == "nonlinear-localisation" else 1)
        assert sum("more accurate than the tobit-ekf" in t for t in mine) == 1
        assert sum("more accurate than the tobit-ukf" in t for t in mine) == 1
        assert sum("converged" in t for t in mine) == 1
    json.dumps(result.metrics, default=lambda a: np.asarray(a).tolist())  # JSON-able


def test_the_localisation_reports_where_the_posterior_is_bimodal(tiny):
    b = tiny["nonlinear-localisation"].metrics["bimodality"]
    assert b["runs"] == 2 and b["threshold"] == pytest.approx(5 / 9)
    assert b["bimodal"]["fraction"] + b["unimodal"]["fraction"] == pytest.approx(1.0)
    assert tiny["nonlinear-localisation"].data["bimodality"].shape == (2, 12)
    assert np.isfinite(b["bimodal"]["rmse_position_gsf"]) or b["bimodal"]["fraction"] * 24 < 2


def test_the_localisation_claims_the_gaussian_sum_filter_beside_the_target(tiny):
    res = tiny["nonlinear-localisation"]
    within = [c for c in res.claims if "within" in c["claim"]]
    assert "nonlinear assumed-density filter" in within[0]["claim"]
    assert "Gaussian-sum assumed-density filter (8 components)" in within[1]["claim"]
    assert res.metrics["lineup"]["gsf"] == {"type": "GaussianSumAssumedDensityFilter", "options": {"components": 8}}


@pytest.mark.heavy  # the experiment at its default horizon and particles (seconds)
def test_the_report_shows_the_ratios_and_costs(tmp_path):
    from tobitkf.cli import run_experiment
    from tobitkf.report import write_report

    folder = run_experiment("nonlinear-accelerometer", runs=2, seed=0, out=tmp_path)
    metrics = json.loads((folder / "metrics.json").read_text(encoding="utf-8"))
    assert set(metrics["figure_captions"]) == {"rmse_accelerometer.png", "ratio_accelerometer.png"}
    _, md = write_report(tmp_path)
    text = md.read_text(encoding="utf-8")
    assert "RMSE / optimum and cost" in text and "µs per run-step" in text and "ekf-inflate" in text


def test_the_comparison_runs_are_the_experiments_runs_and_more_of_the_same_model():
    # the oracle: the two simulations made by hand (the runs' seed stream and the comparison's own) and the filters
    # run on each; the comparison's RMSE is over all the runs together, the claim measured on them
    system, clip = E.accelerometer_system()
    seed, runs, more, steps = 3, 4, 6, 20
    ev, _ = E._case("a", system, clip, runs, steps, 30, seed, lambda *a, **k: None, 0.0, 1.0, None, runs + more)
    sims = [
        tk.simulate(system, steps, r, channel=clip, seed=np.random.SeedSequence([seed, s]))
        for r, s in ((runs, 0), (more, 5))
    ]
    assert ev["comparison"]["runs"] == runs + more
    for key, est in NL.standard_estimators(system, clip).items():
        if key not in ("adf", "tobit-ekf", "tobit-ukf"):
            assert key not in ev["comparison"]["estimators"]
            continue
        err = np.concatenate([est.filter(s.y).mean - s.x[:, 1:] for s in sims])
        np.testing.assert_allclose(ev["compare_errors"][key], err, rtol=0, atol=1e-12)
        want = np.sqrt((err**2).mean(0)).mean(0)
        np.testing.assert_allclose(ev["comparison"]["estimators"][key]["rmse_time_avg"], want, rtol=1e-12)
    claim = NL.better_claim("a", ev, "tobit-ekf")
    alone = NL.better_claim(
        "a", {k: v for k, v in ev.items() if k not in ("compare_errors", "comparison")}, "tobit-ekf"
    )
    assert f"same {runs + more} runs" in claim["quantity"] and f"same {runs} runs" in alone["quantity"]


def test_sizes_are_checked():
    with pytest.raises(tk.ValidationError, match="particles: expected a positive integer"):
        get("nonlinear-oscillator").run(runs=2, particles=0)
    with pytest.raises(tk.ValidationError, match="compare_runs: expected a positive integer"):
        get("nonlinear-random").run(runs=2, compare_runs=0)


def test_the_bound_on_the_ratio_to_the_exact_optimum():
    # the 2 N_p filter's excess RMSE is bounded by the change on doubling plus z standard errors (none below 0)
    conv = {"signed_change": [0.01, -0.02], "relative_change": [0.01, 0.02], "stderr": [0.002, 0.001], "z": 2.0}
    worst, excess = NL.optimum_bound([1.0, 0.98], conv)
    np.testing.assert_allclose(excess, [0.014, 0.0], rtol=1e-12)
    np.testing.assert_allclose(worst, [1.014, 0.98], rtol=1e-12)


def test_a_comparison_carried_by_a_few_runaway_runs_is_not_shown_and_says_why():
    # 38 runs where both filters err by 0.1 and 2 where the rival runs away (error 10): the rival's RMSE is far
    # the larger, but the jackknife over runs (leaving out one runaway run moves it by about 0.66) gives a standard
    # error of about 0.9, three of which exceed the margin of about 2.14
    N, T = 40, 5
    ea = np.full((N, T, 1), 0.1)
    eb = ea.copy()
    eb[:2] = 10.0
    ev = {"errors": {"adf": ea, "rival": eb}, "runs": N, "estimators": {}}
    c = NL.better_claim("case", ev, "rival")
    assert not c["holds"]
    assert "loses the track" in c["explanation"] and "carry 100% of rival's squared error" in c["explanation"]
    # every run with the rival three times the filter's error: shown
    ev["errors"]["rival"] = 3 * ea * (1 + 0.1 * np.random.default_rng(0).random((N, 1, 1)))
    assert NL.better_claim("case", ev, "rival")["holds"]


def test_the_robust_views_count_runaway_runs_and_compare_medians():
    # 38 runs where the filter errs by 0.1 and the rival by 0.3, 2 where the rival runs away (error 10); the prior
    # mean errs by 1 on every run: the rival ran away on those 2 runs (RMSE 10 > 1), the filter on none
    N, T = 40, 5
    ea = np.full((N, T, 1), 0.1)
    eb = np.full((N, T, 1), 0.3) * (1 + 0.1 * np.random.default_rng(1).random((N, 1, 1)))
    eb[:2] = 10.0
    ev = {"errors": {"adf": ea, "rival": eb}, "prior_errors": np.ones((N, T, 1)), "runs": N, "estimators": {}}
    run, away = NL.runaways(eb, ev["prior_errors"])
    np.testing.assert_allclose(run[:2], 10.0)
    assert away.sum() == 2
    median, share = NL.robust_claims("case", ev, "rival")
    assert median["holds"]  # 0.1 against about 0.31, every resample
    # 2 of 40: the paired indicators' standard error is sqrt(0.05 * 0.95 * 40 / 39 / 40) = 0.0349, three of which
    # (0.105) exceed the difference 0.05: not shown
    assert not share["holds"] and "2 of 40 for rival" in share["note"]
    # a non-finite estimate is a runaway run with an infinite RMSE
    eb[5, 2, 0] = np.nan
    run, away = NL.runaways(eb, ev["prior_errors"])
    assert np.isinf(run[5]) and away[5]


def test_the_tail_index_of_a_pareto_law_is_its_exponent():
    # Hill's estimate from the k = 1 % largest of N draws of a Pareto law of index alpha: by Renyi's representation
    # 1/alpha_hat is a gamma variable of mean 1/alpha and relative standard deviation 1/sqrt(k) (k = 400 here:
    # 5 %); four of them
    rng = np.random.default_rng(3)
    N = 40_000
    k = int(0.01 * N)
    for alpha in (0.5, 1.5, 4.0):
        v = rng.pareto(alpha, N) + 1.0
        got = NL.tail_index(v)
        assert abs(alpha / got - 1.0) < 4.0 / np.sqrt(k), (alpha, got)
    # too few runs for 10 tail values, a non-finite (diverged) run or a zero: no estimate
    assert np.isnan(NL.tail_index(np.ones(999) + rng.random(999)))
    assert np.isfinite(NL.tail_index(rng.random(1000) + 1.0))
    assert np.isnan(NL.tail_index(np.r_[rng.random(2000) + 1.0, np.inf]))
    assert np.isnan(NL.tail_index(np.r_[rng.random(2000) + 1.0, 0.0]))


def test_the_runaway_claim_gives_the_exact_sign_test_of_the_runs_where_one_ran_away():
    # the rival ran away on 9 runs, the filter on 1 other: of the 10 runs where exactly one did, 9 are the rival's,
    # P(Bin(10, 1/2) >= 9) = 11/1024
    N, T = 200, 4
    prior = np.ones((N, T, 1))
    ea = np.full((N, T, 1), 0.5)
    eb = ea.copy()
    eb[:9] = 5.0
    ea[20] = 5.0
    ev = {"errors": {"adf": ea, "rival": eb}, "prior_errors": prior, "runs": N, "estimators": {}}
    _, share = NL.robust_claims("case", ev, "rival")
    assert "on the 10 runs where exactly one ran away, rival did on 9" in share["note"]
    assert f"p = {11 / 1024:.2g}" in share["note"]


def test_a_rival_whose_squared_error_has_an_infinite_mean_says_so():
    # 2000 runs; the rival's per-run squared error Pareto of index 0.5 (its mean infinite), the filter's constant:
    # the note gives the Hill estimate (within 4 of its relative standard errors 1/sqrt(20) of 0.5: below 1)
    rng = np.random.default_rng(4)
    N, T = 2000, 3
    ea = np.full((N, T, 1), 0.1)
    eb = np.broadcast_to(np.sqrt(rng.pareto(0.5, N) + 1.0)[:, None, None], (N, T, 1)).copy()
    c = NL.better_claim("case", {"errors": {"adf": ea, "rival": eb}, "runs": N, "estimators": {}}, "rival")
    alpha = NL.tail_index((eb**2).mean(axis=(1, 2)))
    assert alpha < 1 and f"tail index of rival's per-run mean squared error is {alpha:.2f}" in c["note"]
    assert "below 1 its mean" in c["note"]
    # a light tail: nothing said
    eb = 0.2 + 0.01 * rng.random((N, T, 1))
    c = NL.better_claim("case", {"errors": {"adf": ea, "rival": eb}, "runs": N, "estimators": {}}, "rival")
    assert "tail index" not in c["note"]


def test_the_localisation_splits_the_excess_by_beacons_in_range(tiny):
    # by hand: two runs of three steps; the filter's squared position error 25 (3, 4) where one beacon is in range,
    # the optimum's 0 there and 1 elsewhere (the filter's too): all the excess (2 x 25) falls on the one-beacon steps
    err = {"adf": np.zeros((2, 3, 2)), "pf": np.zeros((2, 3, 2))}
    in_range = np.array([[1, 2, 3], [1, 3, 3]])
    err["adf"][in_range == 1] = [3.0, 4.0]
    err["adf"][in_range != 1] = [1.0, 0.0]
    err["pf"][in_range != 1] = [0.0, 1.0]
    out, rows = E._excess_by_range(err, in_range)
    assert set(out) == {"1", "2", "3"}
    assert out["1"]["share_of_excess"] == 1.0 and out["3"]["share_of_excess"] == 0.0
    assert out["1"]["rmse_position_adf"] == 5.0 and out["1"]["rmse_position_pf"] == 0.0
    assert out["3"]["share_of_steps"] == pytest.approx(0.5) and out["2"]["rmse_position_pf"] == 1.0
    assert [r[0] for r in rows] == [1, 2, 3]
    got = tiny["nonlinear-localisation"].metrics["beacons_in_range"]
    assert sum(v["share_of_steps"] for v in got.values()) == pytest.approx(1.0)


@pytest.mark.parametrize(("count", "shown"), [(8, False), (9, True)])
def test_with_no_runaway_of_the_filter_nine_of_the_rivals_show_the_difference(count, shown):
    # the paired indicators' difference has mean c/N and standard error sqrt(c/N (1 - c/N) / (N - 1)): three of them
    # are below c/N iff c > 9 N / (N + 8), i.e. c >= 9 at N = 3000 (the accelerometer's comparison runs)
    N, T = 3000, 2
    ea = np.full((N, T, 1), 0.5)
    eb = ea.copy()
    eb[:count] = 5.0
    ev = {"errors": {"adf": ea, "rival": eb}, "prior_errors": np.ones((N, T, 1)), "runs": N, "estimators": {}}
    assert NL.robust_claims("case", ev, "rival")[1]["holds"] is shown
