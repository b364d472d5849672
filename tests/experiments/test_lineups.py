"""The experiments build their estimators through the registry (``tobitkf.filters.registry``): every line-up
names registry entries with options the entry accepts, ``metrics["lineup"]`` records what ran, and the
registry builds the very estimators the experiments built directly before (the direct constructions are
written out here and run in-process on the same data: equal to the last bit)."""

from __future__ import annotations

import numpy as np
import pytest

import tobitkf as tk
from tobitkf import metrics as mx
from tobitkf.experiments import _optimum, geng2017, li2018, miller_control, miller_tkf, miller_tracker, miller_vision
from tobitkf.experiments import get as get_experiment
from tobitkf.experiments import yardstick as Y
from tobitkf.experiments.geng_protocol import example_channel, example_system
from tobitkf.filters.fading import FadingKalmanFilter
from tobitkf.filters.registry import ENTRIES, describe, get, lineup, make, parts_of
from tobitkf.filters.steady_state import tobit_kalman_filter_controlled

LINEUPS = {
    **{f"yardstick:{k}": v for k, v in Y.LINEUPS.items()},
    "miller-tkf": miller_tkf.THREE,
    "geng2017": geng2017.estimator_lineup({"fading_variance_term": True, "exact_tobit_variance": False}),
    "li2018": li2018.LINEUP,
    "miller-fov": miller_vision.FOV_LINEUP,
    "miller-control": miller_control.ESTIMATION_LINEUP,
    "miller-tracker": miller_tracker.LINEUP,
    "optimum": _optimum.pf_lineup(10, 3),
}


@pytest.mark.parametrize("name", list(LINEUPS))
def test_every_lineup_key_names_an_entry_whose_checks_its_options_pass(name):
    for key, (reg, options) in LINEUPS[name].items():
        assert reg in ENTRIES, (name, key, reg)
        get(reg).check(options)  # raises on an unknown or missing option
        assert set(describe({key: (reg, options)})[key]["options"]) == set(options)


def test_a_lineup_refuses_an_unknown_name_option_or_shape():
    sys_ = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.1]], R=[[0.5]], x0=[0.0], P0=[[1.0]])
    with pytest.raises(tk.ValidationError, match="unknown type 'Kalman'"):
        lineup({"kf": ("Kalman", {})}, sys_, {})
    with pytest.raises(tk.ValidationError, match="noise: not an option of TobitKalmanFilter"):
        lineup({"tkf": ("TobitKalmanFilter", {"noise": "exact_pv"})}, sys_, {"censoring": tk.Censoring()})
    with pytest.raises(tk.ValidationError, match=r"needs the channel piece \[censoring\]"):
        lineup({"tkf": ("TobitKalmanFilter", {})}, sys_, {})
    with pytest.raises(tk.ValidationError, match="expected a pair"):
        lineup({"kf": "KalmanFilter"}, sys_, {})  # type: ignore[dict-item]
    with pytest.raises(tk.ValidationError, match="xi_uncensored: SteadyStateTobitKalmanFilter needs this option"):
        describe({"ss": ("SteadyStateTobitKalmanFilter", {})})
    with pytest.raises(tk.ValidationError, match="two censoring pieces"):
        parts_of([tk.Censoring(), tk.Censoring()])


def _direct_yardstick(name, case):
    """The constructions of yardstick._case before the registry (copied from the old code)."""
    sys_, ch = case["system"], case["channel"]
    if name.startswith("miller"):
        return {
            "kf": tk.KalmanFilter(sys_),
            "ikf": tk.DroppingKalmanFilter(sys_, ch),
            "tkf": tk.TobitKalmanFilter(sys_, ch),
            "tkf-total-variance": tk.TobitKalmanFilter(sys_, ch, noise_term="total_variance"),
            "tkf-exact-pv": tk.TobitKalmanFilter(sys_, ch, noise_term="exact_pv"),
            "adf": tk.AssumedDensityTobitFilter(sys_, ch),
        }
    if name == "geng2017-oscillator":
        fading, cens = ch
        return {
            "tkf-fm": tk.FadingTobitKalmanFilter(sys_, fading, cens),
            "tkf-fm-fading-variance": tk.FadingTobitKalmanFilter(sys_, fading, cens, fading_variance_term=True),
            "tkf-fm-exact-variance": tk.FadingTobitKalmanFilter(sys_, fading, cens, exact_tobit_variance=True),
            "tkf-fm-both": tk.FadingTobitKalmanFilter(
                sys_, fading, cens, fading_variance_term=True, exact_tobit_variance=True
            ),
            "tkf": tk.TobitKalmanFilter(sys_, cens),
            "adf": tk.FadingAssumedDensityFilter(sys_, fading, cens),
        }
    if name == "geng-protocol-tracking":
        P = tk.ProtocolTobitKalmanFilter
        return {
            "pbtkf-imsf": P(sys_, ch),
            "pbtkf-imsf-second-moment": P(sys_, ch, failure_term="second_moment"),
            "pbtkf-imsf-literal": P(sys_, ch, failure_term="literal"),
            "pbtkf-imsf-lmmse": P(sys_, ch, failure_term="lmmse_unconditional"),
            "pbtkf": P.baseline(sys_, ch),
            "adf": tk.ProtocolAssumedDensityFilter(sys_, ch),
        }
    assert name == "saturation-oscillator"
    return {"kf": tk.KalmanFilter(sys_), "adf": tk.SaturationAssumedDensityFilter(sys_, ch)}


_ATTRS = ("noise_term", "failure_term", "fading_variance_term", "exact_tobit_variance", "covariance_update", "window")


@pytest.mark.parametrize("name", Y.EXAMPLES)
def test_yardstick_estimators_are_the_direct_ones_to_the_bit(name):
    case = Y._case(name, 4, 15, 3)
    direct = _direct_yardstick(name, case)
    assert list(case["estimators"]) == list(direct)
    for key, est in case["estimators"].items():
        old = direct[key]
        assert type(est) is type(old), key
        for attr in _ATTRS:
            assert getattr(est, attr, None) == getattr(old, attr, None), (key, attr)
        a, b = est.filter(case["sim"].y), old.filter(case["sim"].y)
        np.testing.assert_array_equal(a.mean, b.mean)
        np.testing.assert_array_equal(a.cov, b.cov)


def _old_pf_summary(system, channel, y, x, particles, seed):
    """The optimum of _optimum.pf_check before the registry (the direct ParticleFilter)."""
    pf = tk.ParticleFilter(system, channel, particles=2 * particles, seed=np.random.SeedSequence([int(seed), 7, 1]))
    return mx.summarize(x, pf.filter(y, outputs=("mean", "var")).mean)


def test_yardstick_saturation_example_end_to_end_equals_the_direct_construction():
    res = get_experiment("yardstick").run(
        runs=4, steps=15, random_systems=0, particles=30, seed=3, examples=("saturation-oscillator",)
    )
    ex = res.metrics["examples"]["saturation-oscillator"]
    case = Y._case("saturation-oscillator", 4, 15, 3)
    sim, sys_, sat = case["sim"], case["system"], case["channel"]
    for key, old in (("kf", tk.KalmanFilter(sys_)), ("adf", tk.SaturationAssumedDensityFilter(sys_, sat))):
        np.testing.assert_array_equal(
            ex["estimators"][key]["rmse"], mx.summarize(sim.x, old.filter(sim.y).mean)["rmse"]
        )
    np.testing.assert_array_equal(
        ex["estimators"]["pf"]["rmse"], _old_pf_summary(sys_, sat, sim.y, sim.x, 30, 3)["rmse"]
    )
    assert ex["lineup"]["adf"] == {"type": "SaturationAssumedDensityFilter", "options": {}}
    assert ex["lineup"]["pf"]["type"] == "ParticleFilter" and ex["lineup"]["pf"]["options"]["particles"] == 60
    assert set(ex["lineup"]) == set(ex["estimators"])


def test_miller_brownian_end_to_end_equals_the_direct_construction():
    res = get_experiment("miller-brownian").run(runs=4, seed=1, steps=30, optimum_particles=20, optimum_runs=4)
    sys_ = tk.LinearSystem(A=[[0.999]], C=[[1.0]], Q=[[0.01]], R=[[0.05**2]], x0=[0.05], P0=[[0.05]])
    cens = tk.Censoring(lower=0.0)
    sim = tk.simulate(sys_, 30, 4, censoring=cens, seed=1)
    direct = {
        "kf": tk.KalmanFilter(sys_),
        "ikf": tk.DroppingKalmanFilter(sys_, cens),
        "tkf": tk.TobitKalmanFilter(sys_, cens),
    }
    est = res.metrics["estimators"]
    for key, old in direct.items():
        o = old.filter(sim.y)
        s = mx.summarize(sim.x, o.mean, o.cov)
        np.testing.assert_array_equal(est[key]["rmse"], s["rmse"])
        np.testing.assert_array_equal(est[key]["nees"], s["nees"])
    np.testing.assert_array_equal(est["pf"]["rmse"], _old_pf_summary(sys_, cens, sim.y, sim.x, 20, 1)["rmse"])
    assert set(res.metrics["lineup"]) == set(est)
    assert res.metrics["lineup"]["ikf"] == {"type": "DroppingKalmanFilter", "options": {}}


def test_geng_protocol_tracking_end_to_end_equals_the_direct_construction():
    res = get_experiment("geng-protocol-tracking").run(runs=6, seed=1, steps=20, optimum_particles=20, optimum_runs=6)
    sys_, ch = example_system(False), example_channel()
    data = tk.simulate(sys_, 20, 6, channel=ch, seed=1)
    P = tk.ProtocolTobitKalmanFilter
    direct = {
        "pbtkf-imsf": P(sys_, ch, failure_term="variance"),
        "pbtkf-imsf-second-moment": P(sys_, ch, failure_term="second_moment"),
        "pbtkf-imsf-literal": P(sys_, ch, failure_term="literal"),
        "pbtkf-imsf-lmmse": P(sys_, ch, failure_term="lmmse_unconditional"),
        "pbtkf": P.baseline(sys_, ch),
    }
    est, used = res.metrics["estimators"], res.metrics["lineup"]
    for key, old in direct.items():
        o = old.filter(data.y)
        np.testing.assert_array_equal(est[key]["rmse"], mx.summarize(data.x, o.mean, o.cov)["rmse"])
        np.testing.assert_array_equal(est[key]["mect_prior"], np.trace(o.pred_cov, axis1=-2, axis2=-1).mean(0))
    np.testing.assert_array_equal(est["pf"]["rmse"], _old_pf_summary(sys_, ch, data.y, data.x, 20, 1)["rmse"])
    assert set(used) == set(est)
    assert used["pbtkf-imsf-literal"] == {"type": "ProtocolTobitKalmanFilter", "options": {"failure_term": "literal"}}
    assert used["pbtkf"] == {"type": "ProtocolBaselineTobitKalmanFilter", "options": {}}


def test_steady_state_filters_equal_the_direct_ones():
    """miller-steady-state: the SSTKF and the controlled-limit TKF from the registry against the class and
    against tobit_kalman_filter_controlled, which the experiment called before."""
    A = np.array([[np.cos(0.05), -np.sin(0.05)], [np.sin(0.05), np.cos(0.05)]])
    sys_ = tk.LinearSystem(A=A, C=[[1.0, 0.0]], Q=0.01 * np.eye(2), R=[[0.1]], x0=[0.0, 0.0], P0=0.05 * np.eye(2))
    sim = tk.simulate(sys_, 40, 5, censoring=tk.Censoring(upper=0.3), seed=2)
    for xi in (0.95, 0.5):
        a = make("SteadyStateTobitKalmanFilter", sys_, xi_uncensored=xi).filter_controlled(sim.y_latent)
        b = tk.SteadyStateTobitKalmanFilter(sys_, xi).filter_controlled(sim.y_latent)
        np.testing.assert_array_equal(a.mean, b.mean)
        c = make("ControlledLimitTobitKalmanFilter", sys_, xi_uncensored=xi, backend="numpy").filter(sim.y_latent)
        d = tobit_kalman_filter_controlled(sys_, xi, sim.y_latent)
        np.testing.assert_array_equal(c.mean, d.mean)
        np.testing.assert_array_equal(c.cov, d.cov)
        np.testing.assert_array_equal(c.extras["limits"], d.extras["limits"])


def test_geng2017_lineup_is_the_old_fading_estimators():
    sys_, fading, cens = geng2017.build("geng2017-oscillator", geng2017.oscillator_settings())
    opts = {"fading_variance_term": True, "exact_tobit_variance": True, "p_uncensored_mode": "augmented"}
    new = lineup(geng2017.estimator_lineup(opts), sys_, {"fading": fading, "censoring": cens})
    old = tk.filters.fading.fading_estimators(sys_, fading, cens, **opts)
    assert list(new) == list(old)
    y = tk.simulate(sys_, 15, 3, censoring=cens, measurement=fading, seed=4).y
    for key in old:
        assert type(new[key]) is type(old[key])
        for attr in ("fading_variance_term", "exact_tobit_variance", "p_uncensored_mode"):
            assert getattr(new[key], attr, None) == getattr(old[key], attr, None)
        np.testing.assert_array_equal(new[key].filter(y).mean, old[key].filter(y).mean)
    assert isinstance(new["kf-fm"], FadingKalmanFilter)


def test_li2018_estimators_equal_the_functions_the_experiment_called():
    from tobitkf.filters.delay_augmented import augmented_lmmse
    from tobitkf.filters.delay_chain import chain_lmmse
    from tobitkf.models.delay import paper_example, paper_prior
    from tobitkf.simulate.delay import simulate_delay

    system, prior = paper_example(S=0.3, q=0.6), paper_prior()
    data = simulate_delay(system, prior, 25, 3, seed=5)
    got = li2018._estimate(0.3, 0.6, data, tuple(li2018.LINEUP))
    want = {
        "chain": chain_lmmse(system, prior, data.y),
        "augmented": augmented_lmmse(system, prior, data.y),
        "paper-j": chain_lmmse(system, prior, data.y, decorrelation="paper"),
        "naive-kf": chain_lmmse(system.replace(S=0.0, fading=None), prior, data.y),
    }
    for key, w in want.items():
        np.testing.assert_array_equal(got[key].mean, w.mean)
        np.testing.assert_array_equal(got[key].cov, w.cov)
        np.testing.assert_array_equal(got[key].extras["next_mean"], w.extras["next_mean"])


def test_the_hinf_and_tracker_entries_build_what_the_experiments_built():
    from tobitkf.filters.hinf import RegionalHinfFilter
    from tobitkf.models.ross import wang2010_model
    from tobitkf.simulate.ross import simulate_ross, wang2010_disturbances

    model = wang2010_model()
    m, n = model.C.shape
    rng = np.random.default_rng(0)
    Af, Bf = 0.3 * rng.standard_normal((n, n)), 0.2 * rng.standard_normal((n, m))
    w, v = wang2010_disturbances(12)
    y = simulate_ross(model, 12, 2, w=w, v=v, seed=1).y
    a = make("RegionalHinfFilter", model, Af=Af, Bf=Bf).filter(y, outputs="mean")
    b = RegionalHinfFilter(Af, Bf, model.M).filter(y, outputs="mean")
    np.testing.assert_array_equal(a.mean, b.mean)
    assert describe({"h": ("RegionalHinfFilter", {"Af": Af, "Bf": Bf})})["h"]["options"]["Af"] == Af.tolist()
    t = make("MultiTargetTracker", None, feedback="off")
    assert type(t) is tk.MultiTargetTracker and t.feedback == "off"
