"""Verdicts fixed by the claims rule (issue 16): each test fails on the rule they replaced.

Before, these claims held (or were "n/a") because their test compared the wrong thing (a ratio to
the KF, one frame, a fixed 0.1 band) or nothing at all; now each is judged on its own quantity with
a tolerance from its Monte Carlo error, and each of these comes out not held (or measured where it
was n/a). Run sizes are reduced; every verdict below is far from its tolerance at these sizes.
"""

import numpy as np
import pytest

from tobitkf.experiments import (
    geng2017,
    geng_protocol,
    li2018,
    miller_closed_loop,
    miller_robot,
    miller_tkf,
    miller_vision,
    wang2010,
)


def _find(claims, *words):
    found = [c for c in claims if all(w in c["claim"] for w in words)]
    assert len(found) == 1, [c["claim"] for c in claims]
    return found[0]


def test_multi_region_covariance_is_overconfident_outside_the_windows():
    """Was: held, comparing the mean P in and between the windows only."""
    r = miller_vision.multi_region_exp(runs=10, seed=0)
    c = _find(r.claims, "Example 3", "covariance reflects")
    assert c["holds"] is False
    ratio = r.metrics["example3"]["mse_over_mean_P_by_region"]
    assert ratio["outside both"] > 4  # about 10x over-confident there
    assert "outside both" in c["measured"]


def test_panning_covariance_feedback_judged_over_frames_500_to_2000():
    """Was: held, comparing the median P at the final frame only."""
    r = miller_vision.panning(runs=6, seed=0)
    c = _find(r.claims, "Figs 6.36-6.37")
    assert c["holds"] is False
    assert max(r.metrics["scenarios"]["covariance-6.76"]["max_median_P_frames_500_2000"]) > 1.0  # 2 P_ref


def _closed_loop(names, runs):
    scen, data, res = {}, {}, {}
    for i, spec in enumerate(miller_closed_loop.CLOSED_LOOP_SCENARIOS):
        if spec[0] in names:
            scen[spec[0]], data[spec[0]], res[spec[0]] = miller_closed_loop.closed_loop_scenario(i, runs, 0)
    return scen, miller_closed_loop.closed_loop_claims(scen, data, res, runs)


def test_closed_loop_fig_6_2_is_judged_against_the_reference_not_the_kf():
    """Was: held with the TKF's mean speed 0.337 on r = 0.2, because |TKF - r| < 0.2 |KF - r|."""
    scen, claims = _closed_loop({"speed-step-T0.15"}, runs=20)
    c = _find(claims, "Fig 6.2", "TKF observer tracks")
    assert c["holds"] is False
    tkf = np.mean(scen["speed-step-T0.15"]["controllers"]["tkf-lqg"]["mean_output_last"])
    assert tkf == pytest.approx(0.337, abs=0.03)


def test_closed_loop_fig_6_1_at_minus_0_05_is_judged_on_the_tkf_alone():
    """Was: held with a TKF speed of 0.13 (about 3 σ) because it is a fifth of the KF's 5.3."""
    _, claims = _closed_loop({"speed-reg-T-0.05"}, runs=20)
    assert _find(claims, "Fig 6.1 (speed-reg-T-0.05)", "TKF observer")["holds"] is False
    assert _find(claims, "Fig 6.1 (speed-reg-T-0.05)", "KF observer the bias")["holds"] is True


def test_closed_loop_heavy_censoring_growth_is_reported_as_not_held():
    """Was: "n/a" at T = 0.9, where the TKF's position RMSE grows from 0.02 to about 2 after the step."""
    _, claims = _closed_loop({"position-T0.9"}, runs=40)
    assert _find(claims, "Fig 6.4 (position-T0.9)")["holds"] is False
    assert _find(claims, "Fig 6.3 (position-T0.9)", "TKF-LQG holds")["holds"] is False


def test_steady_state_censored_fraction_is_judged_by_its_monte_carlo_error():
    """Was: held with 8.8 % censored against the 5 % target, with a tolerance of 0.1 (absolute)."""
    r = miller_tkf.steady_state(runs=40, seed=0, steps=600)
    c = _find(r.claims, "ξ = 0.95", "censored fraction")
    assert c["holds"] is False and "standard errors" in c["tolerance"]
    assert r.metrics["controlled_limit"]["0.95"]["realised_uncensored_fraction"] < 0.93


def test_steady_state_lqg_95_percent_is_measured_and_not_held():
    """Was: "n/a" for the same shortfall (about 93.6 % uncensored against 95 %)."""
    r = miller_closed_loop.steady_state_lqg(runs=8, seed=0)
    c = _find(r.claims, "95 % of the measurements are uncensored")
    assert c["holds"] is False
    assert r.metrics["uncensored_fraction"]["realized"]["sstkf-lqg"] < 0.945


def test_protocol_window_intertwining_is_measured():
    """Was: "n/a" although measured: with the undamped A, ℓ = 5 is lower at only 2 of 100 steps."""
    r = geng_protocol.window(runs=200, seed=0)
    damped, undamped = (_find(r.claims, f"[{case} A]") for case in ("damped", "undamped"))
    assert undamped["holds"] is False and damped["holds"] is not None
    assert r.metrics["comparison"]["undamped"]["steps_variant_lower"] < 10


def test_protocol_bounds_do_not_bound_the_error():
    """Was: "n/a"; measured, the empirical prior MSE exceeds tr N^u_k at most steps."""
    r = geng_protocol.bounds(runs=200, seed=0)
    for case in ("damped", "undamped"):
        assert _find(r.claims, "also bounds", f"({case} A)")["holds"] is False


def test_wang2010_designs_are_compared_with_doing_nothing():
    """Was: "n/a"; the improved filter (γ = 0.44) has the largest error on the paper's disturbance."""
    r = wang2010.simulation_experiment(runs=200, seed=0)
    assert "zero-filter" in r.metrics["estimators"]
    assert _find(r.claims, "Figs. 1-2", "(improved)")["holds"] is False
    assert _find(r.claims, "smallest certified γ")["holds"] is False
    per = r.metrics["per_estimator"]
    assert per["improved"]["sum_E_err2_paper_x0"] > per["paper-gains"]["sum_E_err2_paper_x0"]


def test_li2018_table_trend_is_a_claim_and_the_tables_are_in_the_report():
    """Was: the source's Table 1 only in metrics.json; its falling MSE (0.2156 -> 0.0750) against ours
    rising (0.009 -> 0.021) was not a claim."""
    r = li2018.run_tables(runs=150, seed=0)
    assert _find(r.claims, "Table 1", "falls with t")["holds"] is False
    titles = [t["title"] for t in r.metrics["report_tables"]]
    assert any("Table 1" in t for t in titles) and any("Table 2" in t for t in titles)


def test_geng2017_radar_levelling_off_is_measured():
    """Was: "n/a"; with the reconstructed model the TKF-FM's RMSE keeps growing."""
    r = geng2017.run_radar(runs=200, seed=0)
    assert _find(r.claims, "levels off")["holds"] is False


def test_robot_kf_boundary_is_measured():
    """Was: "n/a"; the KF loop at 19 m diverges in every run."""
    r = miller_robot.robot(runs=4, seed=0, steps=600)
    assert _find(r.claims, "reliable only up to about ζ = 19 m")["holds"] is False


@pytest.mark.slow
def test_wang2010_design_does_not_give_the_printed_numbers():
    """Was: "n/a"; Clarabel's feasible point is A_f = B_f = 0, not the printed gains."""
    r = wang2010.design_experiment(runs=10, seed=0)
    assert _find(r.claims, "as printed")["holds"] is False
