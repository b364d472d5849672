"""Channel pieces of the protocol-based TKF (spec 003 §1.2-1.4, §3.3, §5.1 items 2-3)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import tobitkf as tk
from tobitkf.channels.laws import PMF, Constant, Gaussian, Uniform
from tobitkf.channels.protocol import (
    LAMBDA_1,
    LAMBDA_BASE,
    NO_FAILURE,
    IntegralMeasurement,
    ProtocolChannel,
    RoundRobin,
    check_failure_law,
)


def example_system(A=None, p=2):
    w = 0.052 * np.pi
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]]) if A is None else A
    C = np.eye(2) if p == 2 else np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])[:p]
    return tk.LinearSystem(
        A=A, C=C, Q=0.0025 * np.eye(2), R=np.diag(np.arange(1.0, p + 1)), x0=[5.0, 0.0], P0=np.eye(2)
    )


# --- failure laws ------------------------------------------------------------------------
def test_example_law_moments_by_hand():
    # 0.05*0 + 0.10*0.5 + 0.85*1 = 0.9 ; E L^2 = 0.10*0.25 + 0.85 = 0.875 ; var = 0.875 - 0.81
    assert LAMBDA_BASE.mean == pytest.approx(0.9, abs=1e-15)
    assert LAMBDA_BASE.second_moment == pytest.approx(0.875, abs=1e-15)
    assert LAMBDA_BASE.variance == pytest.approx(0.065, abs=1e-15)
    # Lambda_1: 0.05 + 0.55 = 0.6 ; 0.025 + 0.55 = 0.575 ; 0.575 - 0.36 = 0.215
    assert LAMBDA_1.mean == pytest.approx(0.6, abs=1e-15)
    assert LAMBDA_1.variance == pytest.approx(0.215, abs=1e-15)


def test_law_sampling_frequencies_within_binomial_interval():
    rng = np.random.default_rng(3)
    n = 200_000
    draws = LAMBDA_BASE.sample(rng, (n,))
    for value, prob in zip(LAMBDA_BASE.values, LAMBDA_BASE.probs):
        freq = np.mean(draws == value)
        assert abs(freq - prob) < 4 * np.sqrt(prob * (1 - prob) / n)


def test_laws_share_random_numbers():
    # one uniform per gain and inverse-cdf sampling: Lambda_1's cdf dominates Lambda_2's,
    # so with common random numbers every Lambda_1 draw is <= the Lambda_2 draw.
    a = LAMBDA_BASE.sample(np.random.default_rng(7), (50, 40))
    b = LAMBDA_1.sample(np.random.default_rng(7), (50, 40))
    assert (b <= a).all() and (b < a).any()


@pytest.mark.parametrize(
    "values, probs, match",
    [
        ([0.0, 1.0], [0.5, 0.6], "sum"),
        ([0.0, 1.0], [-0.1, 1.1], ">= 0"),
    ],
)
def test_bad_failure_law_probabilities(values, probs, match):
    with pytest.raises(ValueError, match=match):
        ProtocolChannel(2, failures=PMF(values, probs))


@pytest.mark.parametrize("values", [[0.0, 1.2], [-0.5, 1.0]])
def test_failure_law_support_must_lie_in_unit_interval(values):
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        ProtocolChannel(2, failures=PMF(values, [0.5, 0.5]))


def test_failure_law_probabilities_checked_even_if_mutated():
    law = PMF([0.0, 1.0], [0.5, 0.5])
    law.probs = np.array([0.5, 0.6])
    with pytest.raises(ValueError, match="sum to 1"):
        check_failure_law(law)


class _MomentLaw:
    """A law known only through its moments (and a sampler)."""

    def __init__(self, mean, variance):
        self.mean, self.variance = mean, variance

    def sample(self, rng, shape=()):
        return np.clip(self.mean + np.sqrt(self.variance) * rng.standard_normal(shape), 0, 1)


def test_shared_laws_are_accepted():
    ch = ProtocolChannel(3, failures=[LAMBDA_BASE, Uniform(0.2, 0.8), Constant(0.7)])
    np.testing.assert_allclose(ch.failure_mean, [0.9, 0.5, 0.7], rtol=1e-15)
    np.testing.assert_allclose(ch.failure_variance, [0.065, 0.03, 0.0], rtol=1e-12, atol=1e-15)
    assert ProtocolChannel(2).laws[0] is NO_FAILURE and float(NO_FAILURE.mean) == 1.0


def test_check_failure_law_accepts_any_law_with_mean_and_variance():
    law = _MomentLaw(0.8, 0.01)
    assert check_failure_law(law) is law
    ch = ProtocolChannel(2, failures=law)
    assert ch.failure_mean.tolist() == [0.8, 0.8] and ch.failure_variance.tolist() == [0.01, 0.01]


@pytest.mark.parametrize(
    "law, match",
    [
        (_MomentLaw(0.5, 0.3), "mean\\(1-mean\\)"),
        (_MomentLaw(1.5, 0.0), r"\[0, 1\]"),
        (_MomentLaw(0.5, -0.1), "variance >= 0"),
        (Uniform(0.5, 1.5), r"\[0, 1\]"),
        (Gaussian(0.9, 0.01), "Gaussian gain"),
        (object(), "no 'mean'"),
    ],
)
def test_check_failure_law_rejects(law, match):
    with pytest.raises(ValueError, match=match):
        check_failure_law(law)


# --- Round-Robin -----------------------------------------------------------------------------
def test_round_robin_sequence_and_indicator():
    assert RoundRobin(2).scheduled(5).tolist() == [1, 2, 1, 2, 1]
    assert RoundRobin(3).scheduled(5).tolist() == [1, 2, 3, 1, 2]
    G = RoundRobin(3).indicator(7)
    assert (G.sum(1) == 1).all() and set(np.unique(G)) == {0.0, 1.0}
    assert (np.argmax(G, 1) + 1).tolist() == RoundRobin(3).scheduled(7).tolist()
    assert RoundRobin(3, order=[3, 1]).scheduled(4).tolist() == [3, 1, 3, 1]


def test_round_robin_select_is_zero_input_sum():
    z = np.random.default_rng(0).normal(size=(4, 6, 3))
    G = RoundRobin(3).indicator(6)
    np.testing.assert_array_equal(RoundRobin(3).select(z)[..., 0], (G * z).sum(-1))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"sensors": 0}, "p >= 1"),
        ({"sensors": -2}, "p >= 1"),
        ({"sensors": 1.5}, "p >= 1"),
        ({"sensors": 2, "order": [1, 3]}, "names sensor 3"),
        ({"sensors": 2, "order": [0, 1]}, "names sensor 0"),
        ({"sensors": 2, "order": []}, "non-empty"),
    ],
)
def test_round_robin_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        RoundRobin(**kwargs)


# --- integral measurement ------------------------------------------------------------------------
@settings(max_examples=25, deadline=None)
@given(ell=st.integers(0, 6), T=st.integers(1, 12), seed=st.integers(0, 1000))
def test_window_sum_matches_naive_loop(ell, T, seed):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(2, T + 1, 3))
    past = rng.normal(size=(2, ell, 3))  # past[:, s-1] = x_{-s}

    def state(k):
        return x[:, k] if k >= 0 else past[:, -k - 1]

    naive = np.stack([sum(state(k - s) for s in range(ell + 1)) for k in range(1, T + 1)], axis=1)
    np.testing.assert_allclose(IntegralMeasurement(ell).window_sum(x, past), naive, rtol=0, atol=1e-12)


@pytest.mark.parametrize("window", [-1, 1.5, True, "2"])
def test_bad_window(window):
    with pytest.raises(ValueError, match="ell >= 0"):
        IntegralMeasurement(window)


# --- the composed channel with the core simulator -------------------------------------------------
def test_simulated_measurements_follow_eq_2_to_7():
    sys_ = example_system()
    ch = ProtocolChannel(2, window=2, failures=LAMBDA_BASE, threshold=0.0)
    d = tk.simulate(sys_, 30, 5, seed=11, channel=ch)
    assert d.y.shape == (5, 30, 1) and d.y_latent.shape == (5, 30, 2)
    lam, past = d.extras["failure_gain"], d.extras["prehistory"]
    assert lam.shape == (5, 30, 2) and past.shape == (5, 2, 2)
    states = np.concatenate([past[:, ::-1], d.x], axis=1)  # x_{-2}..x_T
    # v_{m,k} recovered from the latent readings of both sensors must be the same draw for
    # every scheduled/unscheduled sensor: rebuild y from (2)-(4) with them
    h = np.array([0, 1] * 15)
    for k in range(1, 31):
        s = states[:, k : k + 3].sum(1)  # x_{k-2}+x_{k-1}+x_k
        clean = lam[:, k - 1] * s  # C = I: sensor m sees component m
        v = d.y_latent[:, k - 1] - clean
        ybar = clean[:, h[k - 1]] + v[:, h[k - 1]]
        np.testing.assert_allclose(d.extras["y_transmitted"][:, k - 1, 0], ybar, rtol=0, atol=1e-12)
        np.testing.assert_allclose(d.y[:, k - 1, 0], np.maximum(ybar, 0.0), rtol=0, atol=1e-12)
        np.testing.assert_array_equal(d.y[:, k - 1, 0], np.maximum(d.extras["y_transmitted"][:, k - 1, 0], 0.0))
    np.testing.assert_array_equal(d.extras["uncensored"], d.extras["y_transmitted"] > 0)
    assert d.extras["scheduled"].tolist() == [1, 2] * 15


def test_sensor_noise_has_the_sensor_variance():
    # R = diag(1, 2): the residual of sensor 2 has variance 2 (Monte Carlo, 4 standard errors)
    sys_ = example_system()
    ch = ProtocolChannel(2, window=0)
    d = tk.simulate(sys_, 20, 2000, seed=2, channel=ch)
    v = d.y_latent - d.x[:, 1:]
    var = v.reshape(-1, 2).var(0)
    n = v.shape[0] * v.shape[1]
    np.testing.assert_allclose(var, [1.0, 2.0], atol=4 * np.sqrt(2 / n) * 2)


def test_prehistory_options():
    sys_ = example_system()
    d = tk.simulate(sys_, 5, 3, seed=0, channel=ProtocolChannel(2, window=3, prehistory="hold"))
    np.testing.assert_array_equal(d.extras["prehistory"], np.repeat(d.x[:, :1], 3, axis=1))
    d = tk.simulate(sys_, 5, 3, seed=0, channel=ProtocolChannel(2, window=3, prehistory="zero"))
    assert (d.extras["prehistory"] == 0).all()


def test_common_random_numbers_across_scenarios():
    sys_ = example_system()
    a = tk.simulate(sys_, 20, 4, seed=5, channel=ProtocolChannel(2, window=2, failures=LAMBDA_BASE, threshold=0.0))
    b = tk.simulate(sys_, 20, 4, seed=5, channel=ProtocolChannel(2, window=2, failures=LAMBDA_1, threshold=-5.0))
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.extras["prehistory"], b.extras["prehistory"])
    assert (b.extras["failure_gain"] <= a.extras["failure_gain"]).all()


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"sensors": 0}, "p >= 1"),
        ({"sensors": 2, "window": -1}, "ell >= 0"),
        ({"sensors": 2, "failures": [LAMBDA_BASE]}, "one law or 2 laws"),
        ({"sensors": 2, "threshold": np.inf}, "censor every"),
        ({"sensors": 2, "threshold": np.nan}, "NaN"),
        ({"sensors": 2, "prehistory": "random"}, "prehistory"),
        ({"sensors": 2, "order": [1, 2, 5]}, "names sensor 5"),
    ],
)
def test_channel_bad_input(kwargs, match):
    sensors = kwargs.pop("sensors")
    with pytest.raises(ValueError, match=match):
        ProtocolChannel(sensors, **kwargs)


def test_channel_needs_one_row_per_sensor():
    with pytest.raises(ValueError, match="p=3 rows"):
        tk.simulate(example_system(), 5, 1, seed=0, channel=ProtocolChannel(3))
