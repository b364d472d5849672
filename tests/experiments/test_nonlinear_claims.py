"""The target claim of the nonlinear experiments says when its verdict rests on the Monte Carlo tolerance alone."""

from __future__ import annotations

from tobitkf.experiments import _nonlinear as NL

CONV = {
    "signed_change": [0.0, 0.0],
    "relative_change": [0.0, 0.0],
    "stderr": [0.001, 0.001],
    "z": 2.2,
    "level": 0.95,
    "particles": [500, 1000],
    "resolved": True,
    "converged": True,
}


def _ev(ratio, se, runs=60):
    return {
        "runs": runs,
        "estimators": {
            "adf": {"ratio_to_optimum": ratio, "ratio_stderr": se},
            "adf-iterated": {"ratio_to_optimum": ratio},
            "pf": {"convergence": CONV},
        },
    }


def test_a_ratio_above_the_target_within_the_tolerance_holds_and_says_it_is_not_resolved():
    # 1.10 against 1.05 with a standard error of 0.03: 3 standard errors (0.09) cover the excess of 0.05
    target, *_ = NL.target_claims("case", _ev([1.0, 1.10], [0.01, 0.03]), 1.05, rivals=())
    assert target["holds"]
    assert "exceeds 1.05 on state component(s) 2 (of 2)" in target["note"]
    assert "not that the target is met" in target["note"] and "60 runs" in target["note"]


def test_a_ratio_below_the_target_or_beyond_the_tolerance_says_nothing_of_the_kind():
    below, *_ = NL.target_claims("case", _ev([1.0, 1.04], [0.01, 0.03]), 1.05, rivals=())
    assert below["holds"] and "not that the target is met" not in below["note"]
    beyond, *_ = NL.target_claims("case", _ev([1.0, 1.20], [0.01, 0.03]), 1.05, rivals=())
    assert not beyond["holds"] and "not that the target is met" not in beyond["note"]
