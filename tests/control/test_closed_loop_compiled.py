"""The compiled closed loop (``simulate_closed_loop(..., backend="numba")``) against the numpy loop.

The numpy loop, which drives each observer through its public online API, is the reference; the
compiled loop must give the same trajectories to rounding (1e-12 relative to each array's scale) from
the same random draws, for every observer, both sides of the moving limit, a feedthrough D, several
channels, time-varying limits, pre-drawn noise, the divergence freeze, and a per-run observer prior.
"""

import numpy as np
import pytest

from tobitkf import Censoring, LinearSystem
from tobitkf._validation import ValidationError
from tobitkf.control import closed_loop as cl
from tobitkf.control.closed_loop import simulate_closed_loop
from tobitkf.control.lqg import discretize, dlqr
from tobitkf.control.plants import dc_motor_position

pytest.importorskip("numba")

FIELDS = ("x", "estimate", "pred_estimate", "cov", "u", "y", "y_latent", "lower", "upper", "p_uncensored")


def motor():
    """Miller §6.4: DC-motor position, n = 3, m = 1, p = 1 (as tests/control/test_closed_loop.py)."""
    p = dc_motor_position()
    Ad, Bd, Qd = discretize(p.A, p.B, p.G, p.W, 0.01)
    n = Ad.shape[0]
    plant = LinearSystem(A=Ad, C=p.C, Q=Qd, R=p.V, x0=np.zeros(n), P0=1e-6 * np.eye(n), Bu=Bd)
    Qlqr = np.zeros((n, n))
    Qlqr[0, 0] = 100.0
    return plant, dlqr(Ad, Bd, Qlqr, [[1e-6]]).gain


def two_channel():
    """A stable 2-state plant with two sensors and a feedthrough D (m = 2, p = 1), diagonal R."""
    A = np.array([[0.95, 0.1], [-0.1, 0.9]])
    Bu = np.array([[0.0], [0.1]])
    C = np.array([[1.0, 0.0], [0.5, 1.0]])
    plant = LinearSystem(
        A=A,
        C=C,
        Q=0.01 * np.eye(2),
        R=np.diag([0.04, 0.09]),
        x0=[0.5, 0.0],
        P0=0.1 * np.eye(2),
        Bu=Bu,
        D=[[0.2], [0.0]],
    )
    return plant, dlqr(A, Bu, np.eye(2), [[0.5]]).gain


def assert_same(a, b, rtol=1e-12):
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    assert a.shape == b.shape
    fin = np.isfinite(b)
    np.testing.assert_array_equal(np.isfinite(a), fin)
    np.testing.assert_array_equal(a[~fin], b[~fin])  # the infinite limits of a one-sided sensor
    scale = max(1.0, float(np.max(np.abs(b[fin]), initial=0.0)))
    np.testing.assert_allclose(a[fin], b[fin], rtol=rtol, atol=rtol * scale)


def assert_loops_equal(plant, K, steps, runs, **kw):
    a = simulate_closed_loop(plant, K, steps, runs, backend="numba", **kw)
    b = simulate_closed_loop(plant, K, steps, runs, backend="numpy", **kw)
    for f in FIELDS:
        assert_same(getattr(a, f), getattr(b, f))
    np.testing.assert_array_equal(a.diverged_step, b.diverged_step)
    np.testing.assert_array_equal(a.reference, b.reference)
    return a, b


CASES = {
    "kf": {"observer": "kf", "censoring": Censoring(upper=0.05)},
    "tkf": {"observer": "tkf", "censoring": Censoring(upper=0.05)},
    "tkf-exact_pv": {"observer": "tkf", "censoring": Censoring(lower=-0.02, upper=0.05), "noise_term": "exact_pv"},
    "tkf-moving": {"observer": "tkf-moving", "xi_uncensored": 0.95},
    "tkf-moving-lower": {"observer": "tkf-moving", "xi_uncensored": 0.8, "side": "lower"},
    "sstkf": {"observer": "sstkf", "xi_uncensored": 0.95},
    "sstkf-lower": {"observer": "sstkf", "xi_uncensored": 0.9, "side": "lower"},
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_motor_loop_equals_numpy(case):
    plant, K = motor()
    r = np.zeros(300)
    r[50:] = 1.0
    a, _ = assert_loops_equal(plant, K, 300, 133, reference=r, seed=3, **CASES[case])  # a block (128) and a part
    assert not a.diverged.any()
    if case.startswith("tkf"):
        assert (a.y != a.y_latent).any()  # the sensor did censor


@pytest.mark.parametrize("case", ["kf", "tkf", "tkf-moving", "sstkf"])
def test_two_channels_feedthrough_and_time_varying_limits(case):
    plant, K = two_channel()
    kw = dict(CASES[case])
    if "censoring" in kw:
        steps = 120
        lo = np.where(np.arange(steps)[:, None] % 10 < 5, -0.3, -np.inf) * np.ones((1, 2))
        kw["censoring"] = Censoring(lower=lo, upper=np.full((steps, 2), 0.4))
    assert_loops_equal(plant, K, 120, 5, reference=0.3, Cz=[[1.0, 0.0]], seed=1, **kw)


def test_predrawn_noise_and_per_run_prior():
    plant, K = motor()
    rng = np.random.default_rng(4)
    noise = {
        "x0": rng.normal(size=(6, 3)) * 1e-3,
        "w": rng.normal(size=(6, 80, 3)) * 1e-3,
        "v": rng.normal(size=(6, 80, 1)),
    }
    x0e = rng.normal(size=(6, 3)) * 1e-3
    P0e = np.array([np.eye(3) * s for s in np.linspace(1e-6, 1e-3, 6)])
    assert_loops_equal(
        plant, K, 80, 6, observer="tkf", censoring=Censoring(upper=0.0), noise=noise, x0_estimate=x0e, P0_estimate=P0e
    )
    noise1 = {key: val[:1] for key, val in noise.items()}  # one run (the latency case) and a broadcast noise
    assert_loops_equal(plant, K, 80, 1, observer="tkf-moving", xi_uncensored=0.9, noise=noise1)


@pytest.mark.parametrize("observer", ["kf", "tkf", "sstkf"])
def test_divergence_freeze_equals_numpy(observer):
    """A small bound freezes some runs part way (their state, estimate and covariance stay, u is 0)."""
    plant, K = motor()
    kw = {"xi_uncensored": 0.95} if observer == "sstkf" else {"censoring": Censoring(upper=0.5)}
    free = simulate_closed_loop(plant, K, 200, 12, observer=observer, reference=1.0, seed=2, backend="numpy", **kw)
    peak = np.maximum(np.abs(free.x[:, 1:]).max(axis=(1, 2)), np.abs(free.estimate).max(axis=(1, 2)))
    bound = float(np.median(peak))  # about half of the runs leave it, at different steps
    a, _ = assert_loops_equal(plant, K, 200, 12, observer=observer, reference=1.0, divergence_bound=bound, seed=2, **kw)
    assert a.diverged.any() and not a.diverged.all()
    frozen = a.diverged_step[a.diverged]
    assert frozen.min() < 200 and (a.u[a.diverged, -1] == 0.0).all()


def test_auto_runs_the_compiled_loop_and_numpy_does_not(monkeypatch):
    plant, K = motor()
    calls = []
    real = cl._compiled_loop

    def spy(*args, **kwargs):
        calls.append(args[2])
        return real(*args, **kwargs)

    monkeypatch.setattr(cl, "_compiled_loop", spy)
    for obs, kw in (("kf", {}), ("tkf", {}), ("tkf-moving", {"xi_uncensored": 0.9}), ("sstkf", {"xi_uncensored": 0.9})):
        simulate_closed_loop(plant, K, 5, 2, observer=obs, **kw)
        simulate_closed_loop(plant, K, 5, 2, observer=obs, backend="numpy", **kw)
    assert calls == ["kf", "tkf", "tkf-moving", "sstkf"]


def test_kf_with_correlated_noise_stays_on_numpy():
    plant, K = two_channel()
    corr = LinearSystem(
        A=plant.transition(0),
        C=plant.measurement(1),
        Q=plant.process_cov(0),
        R=[[0.04, 0.01], [0.01, 0.09]],
        x0=plant.x0,
        P0=plant.P0,
        Bu=plant.Bu.at(1),
    )
    with pytest.raises(ValidationError, match="does not cover the KF observer with a non-diagonal R"):
        simulate_closed_loop(corr, K, 10, 2, observer="kf", backend="numba")
    a = simulate_closed_loop(corr, K, 10, 2, observer="kf")
    b = simulate_closed_loop(corr, K, 10, 2, observer="kf", backend="numpy")
    np.testing.assert_array_equal(a.estimate, b.estimate)  # auto fell back to the very same loop
    with pytest.raises(ValidationError, match="backend"):
        simulate_closed_loop(corr, K, 10, 2, observer="kf", backend="fast")
