"""The claims rule (experiments/_claims.py) and that every experiment follows it.

Every claim states its quantity, its test and its tolerance; a measured claim is held or not held;
n/a needs the reason it cannot be measured. Every figure has a caption; the report cites no
specification.
"""

import json

import numpy as np
import pytest

from tobitkf.experiments import _claims as CL
from tobitkf.experiments import all_experiments, get

from ..test_no_spec_citations import hits


# ------------------------------------------------------------------ the rule itself
def test_a_claim_without_its_quantity_test_or_tolerance_is_refused():
    good = dict(quantity="q", measured="1", test="q <= 2", tolerance="exact", holds=True)
    CL.check_claim({"claim": "x", **good})
    for key in ("quantity", "measured", "test", "tolerance"):
        with pytest.raises(CL.ClaimError, match=key):
            CL.check_claim({"claim": "x", **{**good, key: ""}})


def test_na_only_with_a_reason_and_a_measured_claim_is_held_or_not():
    with pytest.raises(CL.ClaimError, match="reason"):
        CL.check_claim({"claim": "x", "quantity": "q", "measured": "m", "test": "t", "tolerance": "tol", "holds": None})
    with pytest.raises(CL.ClaimError, match="True, False or None"):
        CL.check_claim(
            {"claim": "x", "quantity": "q", "measured": "m", "test": "t", "tolerance": "tol", "holds": "yes"}
        )
    na = CL.not_measurable("Fig 9 matches", reason="the figure is missing from the source")
    assert na["holds"] is None and "missing" in na["measured"]


def test_a_claimed_difference_needs_evidence_beyond_the_tolerance():
    assert CL.less("a < b", quantity="q", a=1.0, b=1.5, tol=0.1, tolerance="0.1")["holds"] is True
    assert CL.less("a < b", quantity="q", a=1.0, b=1.05, tol=0.1, tolerance="0.1")["holds"] is False
    assert CL.greater("a > b", quantity="q", a=2.0, b=1.0, tol=0.5, tolerance="0.5")["holds"] is True


def test_a_claimed_equality_or_bound_holds_unless_violated_beyond_the_tolerance():
    assert CL.close("q = 1", quantity="q", value=1.05, target=1.0, tol=0.1, tolerance="0.1")["holds"] is True
    assert CL.close("q = 1", quantity="q", value=1.2, target=1.0, tol=0.1, tolerance="0.1")["holds"] is False
    assert CL.at_most("q <= 1", quantity="q", value=1.05, bound=1.0, tol=0.1, tolerance="0.1")["holds"] is True
    assert CL.at_least("q >= 1", quantity="q", value=0.8, bound=1.0, tol=0.1, tolerance="0.1")["holds"] is False


def test_jackknife_of_a_mean_is_the_textbook_standard_error():
    x = np.random.default_rng(0).normal(size=(200, 3))
    se = CL.jackknife_se(x, lambda m: m)
    np.testing.assert_allclose(se, x.std(axis=0, ddof=1) / np.sqrt(200), rtol=1e-12)
    err = np.random.default_rng(1).normal(size=(400, 50, 2)) * 0.3
    value, se = CL.rmse_time_avg(err)
    assert value == pytest.approx([0.3, 0.3], rel=0.05) and np.all(se < 0.01)


def test_printed_numbers_are_matched_to_their_printed_digits():
    assert CL.half_unit("73.1575") == pytest.approx(5e-5)
    assert CL.half_unit(".305") == pytest.approx(5e-4)
    assert CL.half_unit("2.3025E-10") == pytest.approx(5e-15)
    assert CL.matches_print("L", quantity="L", value=[73.157489], printed=["73.1575"])["holds"] is True
    assert CL.matches_print("L", quantity="L", value=[73.157737], printed=["73.1575"])["holds"] is False


def test_a_registered_experiment_that_breaks_the_rule_raises():
    from tobitkf.experiments import ExperimentResult, register

    def plot(result, outdir):
        return []

    @register("test-bad-claim", title="t", source="s", plot=plot, default_runs=1)
    def bad(*, runs, seed, progress=None):
        return ExperimentResult("test-bad-claim", {}, {}, {}, [{"claim": "x", "measured": "1", "holds": True}])

    try:
        with pytest.raises(CL.ClaimError, match="test-bad-claim claim 1: .*quantity"):
            bad(runs=1, seed=0)
    finally:
        from tobitkf import experiments

        experiments._REGISTRY.pop("test-bad-claim", None)


# ------------------------------------------------------------------ every experiment follows it
@pytest.mark.slow
@pytest.mark.parametrize("exp_id", [e.id for e in all_experiments()])
def test_every_experiment_follows_the_claims_rule_and_captions_its_figures(exp_id, tmp_path):
    from tobitkf.cli import run_experiment
    from tobitkf.report import write_report

    folder = run_experiment(exp_id, runs=2, seed=0, out=tmp_path)
    metrics = json.loads((folder / "metrics.json").read_text(encoding="utf-8"))
    assert metrics["claims"]
    CL.check_claims(metrics["claims"], exp_id)
    for c in metrics["claims"]:
        assert c["holds"] in (True, False) or c.get("not_measurable")
    captions = metrics["figure_captions"]
    assert metrics["figures"] and set(captions) == set(metrics["figures"])
    for name, cap in captions.items():
        assert len(cap) > 40, f"{name}: caption {cap!r} does not say what the figure shows"
    for key, est in metrics.get("estimators", {}).items():
        r = np.asarray(est["rmse"])
        assert r.ndim == 2 and np.shape(est["rmse_time_avg"]) == r.shape[1:], key
    for s in metrics["settings"].values():
        assert s["provenance"] in ("source", "reconstructed", "default")
    _, md = write_report(tmp_path)
    found = hits(md.read_text(encoding="utf-8"))
    assert not found, "REPORT.md cites the specifications:\n" + "\n".join(found)


def test_the_report_shows_the_source_tables_of_li2018(tmp_path):
    from tobitkf.cli import run_experiment
    from tobitkf.report import write_report

    run_experiment("li2018-tables", runs=4, seed=0, out=tmp_path)
    index, md = write_report(tmp_path)
    text = md.read_text(encoding="utf-8")
    assert "Table 1 (filter x̂(t\\|t)): running-average MSE" in text  # '|' escaped in Markdown
    assert "| x1: this paper (printed) | 0.2156 | 0.1196 | 0.0887 | 0.0868 | 0.0784 | 0.075 |" in text
    assert "\\[28\\] (printed) | 1.221 |" in text  # '[ ]' escaped in Markdown (issue 15)
    assert "Table 1 (filter x̂(t|t))" in index.read_text(encoding="utf-8")
    assert get("li2018-tables").source.startswith("Li, Li & Wang 2018")
