"""The numpy path of each family takes its measurement moments from the function the compiled loop calls.

The Tobit Kalman filter and the fading TKF take their censored statistics from
``_readings.compiled_censored_moments`` (over ``censored_stats``, the statistics of the compiled loop); the
fading, protocol and saturation assumed-density filters theirs from ``_compiled_moments.family_array`` (the censored
and the saturation blocks of the compiled loop). Each test replaces that function by a spy and counts its calls on
``backend="numpy"`` in every covariance form: one per step (and channel, failure outcome or pass), not a second
copy of the equations. ``censored.py`` stays the high-precision reference the compiled statistics are tested
against (``test_kernels_censored.py``); here the wrapper's broadcasting is checked against it.
"""

from __future__ import annotations

import numpy as np
import pytest

import tobitkf as tk
from tobitkf.censored import censored_moments
from tobitkf.channels.laws import PMF

pytest.importorskip("numba")

from tobitkf.filters import _compiled_censored, _compiled_moments  # noqa: E402
from tobitkf.filters._readings import compiled_censored_moments  # noqa: E402

FORMS = ("standard", "joseph", "square_root")
N, T = 3, 12


def _spy(monkeypatch, module, name):
    """Replace ``module.name`` by a wrapper that records the length of its first array argument per call."""
    calls = []
    real = getattr(module, name)

    def call(*args):
        first = next(a for a in args if isinstance(a, np.ndarray))
        calls.append(first.shape[0])
        return real(*args)

    monkeypatch.setattr(module, name, call)
    return calls


def _oscillator(m=1):
    w = 0.052 * np.pi
    C = [[1.0, 0.0], [0.3, 1.0]][:m]
    return tk.LinearSystem(
        A=[[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]], C=C, Q=0.01 * np.eye(2), R=0.2 * np.eye(m),
        x0=[0.3, 0.0], P0=0.05 * np.eye(2),
    )  # fmt: skip


def _readings(m, lower=-0.1, upper=np.inf, seed=0):
    y = np.clip(0.4 * np.random.default_rng(seed).normal(size=(N, T, m)), lower, upper)
    y[1, 3] = np.nan
    return y


def test_wrapper_broadcasts_and_matches_the_reference():
    """``compiled_censored_moments`` over broadcast arguments: every field of the broadcast shape, equal to
    ``censored_stats`` entry by entry (``censored_moments_array``) and to ``censored_moments`` to 1e-12
    (central values, where the reference is exact to rounding)."""
    mu = np.linspace(-2.0, 2.0, 15).reshape(5, 3)
    sd = np.array([0.5, 1.0, 2.0])
    lo, hi = np.array([-np.inf, -0.3, 0.1]), np.array([0.8, np.inf, 1.5])
    got = compiled_censored_moments(mu, sd, lo, hi)
    ref = censored_moments(mu, sd, lo, hi)
    flat = [np.ascontiguousarray(a.ravel()) for a in np.broadcast_arrays(mu, sd, lo, hi)]
    rows = _compiled_censored.censored_moments_array(*flat, _compiled_censored.GL_X, _compiled_censored.GL_W)
    for i, (g, r) in enumerate(zip(got, ref)):
        assert g.shape == (5, 3)
        np.testing.assert_array_equal(g.ravel(), rows[i])
        np.testing.assert_allclose(g, r, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("form", FORMS)
def test_tkf_numpy_path_takes_the_compiled_statistics(monkeypatch, form):
    calls = _spy(monkeypatch, _compiled_censored, "censored_moments_array")
    sys_, cens = _oscillator(2), tk.Censoring(lower=[-0.1, -np.inf], upper=[np.inf, 0.5])
    tk.TobitKalmanFilter(sys_, cens, backend="numpy", covariance_update=form).filter(_readings(2, upper=0.5))
    assert calls == [N * 2] * T


@pytest.mark.parametrize("form", FORMS)
@pytest.mark.parametrize(
    "cls, module, function",
    [
        (tk.FadingTobitKalmanFilter, _compiled_censored, "censored_moments_array"),
        (tk.FadingAssumedDensityFilter, _compiled_moments, "family_array"),
    ],
)
def test_fading_numpy_paths_take_the_compiled_moments(monkeypatch, form, cls, module, function):
    """The fading TKF's censored statistics and the fading ADF's block, one call per step (one channel)."""
    calls = _spy(monkeypatch, module, function)
    sys_, fad, cens = _oscillator(), tk.RiceFading(1, [0.8, 0.3]), tk.Censoring(lower=-0.1)
    cls(sys_, fad, cens, backend="numpy", covariance_update=form).filter(_readings(1))
    assert calls == [N] * T


@pytest.mark.parametrize("form", FORMS)
def test_protocol_adf_numpy_path_takes_the_compiled_block(monkeypatch, form):
    """One call per failure outcome (two) and step."""
    sys_ = _oscillator(2)
    ch = tk.ProtocolChannel(2, window=1, failures=PMF([0.2, 1.0], [0.3, 0.7]), threshold=0.0)
    y = tk.simulate(sys_, T, N, channel=ch, seed=1).y
    calls = _spy(monkeypatch, _compiled_moments, "family_array")
    tk.ProtocolAssumedDensityFilter(sys_, ch, backend="numpy", covariance_update=form).filter(y)
    assert calls == [N] * (2 * T)


@pytest.mark.parametrize("form", FORMS)
def test_saturation_adf_numpy_path_takes_the_compiled_block(monkeypatch, form):
    """Two calls per step and sensor: the modes' probabilities, then the saturated mode's moments."""
    calls = _spy(monkeypatch, _compiled_moments, "family_array")
    ch = tk.RandomSaturation(mu=[0.3], nu=[0.8], level=0.5)
    y = 0.6 * np.random.default_rng(2).normal(size=(N, T, 1))
    y[0, 4] = np.nan
    tk.SaturationAssumedDensityFilter(_oscillator(), ch, backend="numpy", covariance_update=form).filter(y)
    assert calls == [N] * (2 * T)
