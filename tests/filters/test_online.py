"""The online API of every estimator: the loop over ``step`` equals ``filter``; states pickle and resume.

Each family is a case (``CASES``): a builder of (estimator, readings, inputs) on its paper's example size
or a small model, with missing readings, control inputs and time-varying matrices where the family takes
them. Tolerances: 1e-12 absolute on the numpy path (the same arithmetic in a different order of calls at
most), exact for the resume from a pickled state.
"""

from __future__ import annotations

import pickle

import numpy as np
import pytest

import tobitkf as tk
from tobitkf.filters.core import FilterState

TOL = 1e-12


def oscillator(**kw):
    w = 0.1
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    base = dict(A=A, C=[[1.0, 0.0]], Q=1e-2 * np.eye(2), R=[[0.04]], x0=[1.0, 0.0], P0=0.5 * np.eye(2))
    base.update(kw)
    return tk.LinearSystem(**base)


def with_gaps(y, rng, frac=0.1):
    y = np.array(y, dtype=float, copy=True)
    y[rng.random(y.shape) < frac] = np.nan
    return y


def case_kf(batch, rng, backend="numpy", form="standard"):
    sys_ = oscillator()
    d = tk.simulate(sys_, 12, int(np.prod(batch)) if batch else 1, seed=1)
    y = with_gaps(d.y, rng).reshape(batch + (12, 1))
    return tk.KalmanFilter(sys_, backend=backend, covariance_update=form), y, None


def case_kf_inputs_tv(batch, rng, backend="numpy", form="standard"):
    T = 10
    As = np.stack([np.array([[1.0, 0.1], [0.0, 1.0 - 0.01 * k]]) for k in range(T)])
    sys_ = tk.LinearSystem(
        A=As,
        C=lambda k: np.array([[1.0, 0.1 * k]]),
        Q=1e-3 * np.eye(2),
        R=[[0.1]],
        x0=[0.0, 1.0],
        P0=np.eye(2),
        Bu=[[0.0], [1.0]],
    )
    N = int(np.prod(batch)) if batch else 1
    u = rng.standard_normal(batch + (T, 1))
    d = tk.simulate(sys_, T, N, inputs=u.reshape(N, T, 1), seed=2)
    y = with_gaps(d.y, rng).reshape(batch + (T, 1))
    return tk.KalmanFilter(sys_, backend=backend, covariance_update=form), y, u


def case_dkf(batch, rng, backend="numpy", form="standard"):
    sys_ = oscillator()
    cens = tk.Censoring(lower=0.0)
    d = tk.simulate(sys_, 15, int(np.prod(batch)) if batch else 1, censoring=cens, seed=3)
    y = with_gaps(d.y, rng).reshape(batch + (15, 1))
    return tk.DroppingKalmanFilter(sys_, cens, backend=backend, covariance_update=form), y, None


def case_tkf(batch, rng, backend="numpy", form="standard"):
    sys_ = oscillator()
    cens = tk.Censoring(lower=0.0, upper=1.2)
    d = tk.simulate(sys_, 15, int(np.prod(batch)) if batch else 1, censoring=cens, seed=4)
    y = with_gaps(d.y, rng).reshape(batch + (15, 1))
    return tk.TobitKalmanFilter(sys_, cens, backend=backend, covariance_update=form), y, None


def case_tkf_tv(batch, rng, backend="numpy", form="standard"):
    T = 12
    lower = np.linspace(-0.5, 0.5, T)[:, None] * np.ones((1, 2))
    cens = tk.Censoring(lower=lower)
    sys_ = tk.LinearSystem(
        A=lambda k: np.array([[0.95, 0.1], [0.0, 0.9 + 0.001 * k]]),
        C=[[1.0, 0.0], [0.5, 1.0]],
        Q=1e-2 * np.eye(2),
        R=np.diag([0.05, 0.1]),
        x0=[0.5, 0.2],
        P0=np.eye(2),
        Bu=np.eye(2),
        D=[[0.0, 0.1], [0.0, 0.0]],
    )
    N = int(np.prod(batch)) if batch else 1
    u = 0.1 * rng.standard_normal(batch + (T, 2))
    d = tk.simulate(sys_, T, N, censoring=cens, inputs=u.reshape(N, T, 2), seed=5)
    y = with_gaps(d.y, rng).reshape(batch + (T, 2))
    return tk.TobitKalmanFilter(sys_, cens, backend=backend, covariance_update=form), y, u


def case_sstkf(batch, rng, backend="numpy", form="standard"):
    sys_ = oscillator(Bu=[[0.0], [1.0]])
    est = tk.SteadyStateTobitKalmanFilter(sys_, 0.7)
    N = int(np.prod(batch)) if batch else 1
    u = 0.1 * rng.standard_normal(batch + (10, 1))
    d = tk.simulate(sys_, 10, N, inputs=u.reshape(N, 10, 1), seed=6)
    y = est.filter_controlled(d.y_latent, u=u.reshape(N, 10, 1)).extras["y"].reshape(batch + (10, 1))
    return est, y, u


def case_cltkf(batch, rng, backend="numpy", form="standard"):
    """The controlled-limit TKF reads the sensor's latent readings and censors them at the limit it steers."""
    from tobitkf.filters.steady_state import ControlledLimitTobitKalmanFilter

    sys_ = oscillator()
    N = int(np.prod(batch)) if batch else 1
    d = tk.simulate(sys_, 10, N, seed=10)
    return ControlledLimitTobitKalmanFilter(sys_, 0.7), d.y_latent.reshape(batch + (10, 1)), None


def case_fading(batch, rng, backend="numpy", form="joseph"):
    from tobitkf.channels.fading import RiceFading

    T = 12
    sys_ = oscillator(Bu=[[0.0], [1.0]], C=lambda k: np.array([[1.0, 0.01 * k]]))
    fad = RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    cens = tk.Censoring(lower=0.0)
    N = int(np.prod(batch)) if batch else 1
    u = 0.1 * rng.standard_normal(batch + (T, 1))
    d = tk.simulate(sys_, T, N, censoring=cens, measurement=fad, inputs=u.reshape(N, T, 1), seed=11)
    y = with_gaps(d.y, rng).reshape(batch + (T, 1))
    est = tk.FadingTobitKalmanFilter(
        sys_, fad, cens, covariance_update=form, p_uncensored_mode="eq6_stale", fading_variance_term=True
    )
    return est, y, u


def case_protocol(batch, rng, backend="numpy", form="joseph"):
    from tobitkf.channels.protocol import LAMBDA_BASE, ProtocolChannel

    T = 12
    w = 0.052 * np.pi
    sys_ = tk.LinearSystem(
        A=lambda k: np.array([[np.cos(w), -np.sin(w)], [np.sin(w), 0.99 * np.cos(w)]]),
        C=np.eye(2),
        Q=0.0025 * np.eye(2),
        R=np.diag([1.0, 0.5]),
        x0=[5.0, 0.0],
        P0=np.eye(2),
    )
    ch = ProtocolChannel(2, window=2, failures=LAMBDA_BASE, threshold=0.0)
    N = int(np.prod(batch)) if batch else 1
    d = tk.simulate(sys_, T, N, channel=ch, seed=12)
    est = tk.ProtocolTobitKalmanFilter(sys_, ch, covariance_update=form, failure_term="second_moment")
    return est, with_gaps(d.y, rng).reshape(batch + (T, 1)), None


def _delay(batch, rng, cls, **kw):
    from tobitkf.models.delay import paper_example, paper_prior
    from tobitkf.simulate.delay import simulate_delay

    sys_, prior = paper_example(), paper_prior()
    N = int(np.prod(batch)) if batch else 1
    y = simulate_delay(sys_, prior, 14, N, seed=13).y.reshape(batch + (14, 1))
    return cls(sys_, prior, **kw), y, None


def case_delay_chain(batch, rng, backend="numpy", form="standard"):
    from tobitkf.filters.delay_chain import ChainLMMSE

    return _delay(batch, rng, ChainLMMSE)


def case_delay_augmented(batch, rng, backend="numpy", form="standard"):
    from tobitkf.filters.delay_augmented import AugmentedLMMSE

    return _delay(batch, rng, AugmentedLMMSE, window=5)


def case_delay_reorganized(batch, rng, backend="numpy", form="standard"):
    from tobitkf.filters.delay_reorganized import ReorganizedInnovationLMMSE

    return _delay(batch, rng, ReorganizedInnovationLMMSE, warmup=3)


def case_fkf(batch, rng, backend="numpy", form="standard"):
    from tobitkf.channels.fading import RiceFading

    T = 12
    sys_ = oscillator(Bu=[[0.0], [1.0]])
    fad = RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    N = int(np.prod(batch)) if batch else 1
    u = 0.1 * rng.standard_normal(batch + (T, 1))
    d = tk.simulate(sys_, T, N, measurement=fad, inputs=u.reshape(N, T, 1), seed=14)
    y = with_gaps(d.y, rng).reshape(batch + (T, 1))
    return tk.FadingKalmanFilter(sys_, fad), y, u


def case_pbtkf(batch, rng, backend="numpy", form="standard"):
    """The protocol family's baseline (PBTKF); readings complete (the family refuses NaN: see its
    ``filter`` docstring)."""
    from tobitkf.channels.protocol import LAMBDA_BASE, ProtocolChannel

    sys_ = tk.LinearSystem(
        A=0.95 * np.eye(2), C=np.eye(2), Q=0.01 * np.eye(2), R=np.diag([1.0, 0.5]), x0=[5.0, 0.0], P0=np.eye(2)
    )
    ch = ProtocolChannel(2, window=2, failures=LAMBDA_BASE, threshold=0.0)
    N = int(np.prod(batch)) if batch else 1
    d = tk.simulate(sys_, 12, N, channel=ch, seed=15)
    return tk.ProtocolTobitKalmanFilter.baseline(sys_, ch), d.y.reshape(batch + (12, 1)), None


def case_multi_region(batch, rng, backend="numpy", form="standard"):
    """Miller's Example 1 layout: one output read by two sensors, right- and left-censored at 0."""
    sys_, cens = tk.multi_region(oscillator(), [[(-np.inf, 0.0), (0.0, np.inf)]])
    N = int(np.prod(batch)) if batch else 1
    d = tk.simulate(sys_, 12, N, censoring=cens, seed=16)
    y = with_gaps(d.y, rng).reshape(batch + (12, sys_.m))
    return tk.TobitKalmanFilter(sys_, cens, backend=backend, covariance_update=form), y, None


def case_hinf(batch, rng, backend="numpy", form="standard"):
    """The H∞ filter (no covariance: the means are compared)."""
    est = tk.RegionalHinfFilter([[0.5, 0.1], [0.0, 0.8]], [[1.0], [0.2]], [[1.0, 0.0]])
    return est, rng.normal(size=batch + (10, 1)), None


def _tv_system(m=1, D=None, **kw):
    """Time-varying A (callable) and C (array over time), a control input through Bu (and D if given)."""
    T = 14
    Cs = np.stack([np.array([[1.0, 0.02 * k], [0.3, 1.0]])[:m] for k in range(1, T + 2)])
    base = dict(
        A=lambda k: np.array([[0.95, 0.1], [-0.05, 0.9 + 0.002 * k]]),
        C=np.concatenate([Cs[:1], Cs]),  # index 0 unused: the first reading is at k = 1
        Q=1e-2 * np.eye(2),
        R=np.diag([0.05, 0.1][:m]),
        x0=[0.5, 0.2],
        P0=np.eye(2),
        Bu=[[0.0], [1.0]],
        D=D,
    )
    base.update(kw)
    return tk.LinearSystem(**base)


def _inputs(batch, rng, T):
    N = int(np.prod(batch)) if batch else 1
    u = 0.1 * rng.standard_normal(batch + (T, 1))
    return N, u, u.reshape(N, T, 1)


def case_adf(batch, rng, backend="numpy", form="standard"):
    """The assumed-density Tobit filter: time-varying A, C and two-sided limits, inputs through Bu and D."""
    T = 12
    sys_ = _tv_system(m=2, D=[[0.1], [0.0]])
    cens = tk.Censoring(lower=np.linspace(-0.5, 0.2, T)[:, None] * np.ones((1, 2)), upper=1.0)
    N, u, u3 = _inputs(batch, rng, T)
    d = tk.simulate(sys_, T, N, censoring=cens, inputs=u3, seed=17)
    y = with_gaps(d.y, rng).reshape(batch + (T, 2))
    return tk.AssumedDensityTobitFilter(sys_, cens, covariance_update=form), y, u


def case_adf_fading(batch, rng, backend="numpy", form="standard"):
    """The fading ADF of order 2: time-varying A and C, inputs through Bu and D, censoring at 0."""
    from tobitkf.channels.fading import RiceFading

    T = 12
    sys_ = _tv_system(m=1, D=[[0.2]])
    fad = RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    cens = tk.Censoring(lower=0.0)
    N, u, u3 = _inputs(batch, rng, T)
    d = tk.simulate(sys_, T, N, censoring=cens, measurement=fad, inputs=u3, seed=18)
    y = with_gaps(d.y, rng).reshape(batch + (T, 1))
    return tk.FadingAssumedDensityFilter(sys_, fad, cens, covariance_update=form), y, u


def case_adf_protocol(batch, rng, backend="numpy", form="standard"):
    """The protocol ADF (window 2, the example's failure law, tau = 0): time-varying A and C, inputs
    through Bu (the channel has no feedthrough D: refused, test_channels_without_feedthrough_refuse_u_with_D)."""
    from tobitkf.channels.protocol import LAMBDA_BASE, ProtocolChannel

    T = 12
    sys_ = _tv_system(m=2, R=np.diag([1.0, 0.5]), x0=[5.0, 0.0])
    ch = ProtocolChannel(2, window=2, failures=LAMBDA_BASE, threshold=0.0)
    N, u, u3 = _inputs(batch, rng, T)
    d = tk.simulate(sys_, T, N, channel=ch, inputs=u3, seed=19)
    y = with_gaps(d.y, rng).reshape(batch + (T, 1))
    return tk.ProtocolAssumedDensityFilter(sys_, ch, covariance_update=form), y, u


def case_adf_saturation(batch, rng, backend="numpy", form="standard"):
    """The saturation ADF (the H-infinity example's probabilities): time-varying A and C, inputs through Bu."""
    T = 12
    sys_ = _tv_system(m=2)
    ch = tk.RandomSaturation([0.3, 0.2], [0.8, 0.9], level=0.5)
    N, u, u3 = _inputs(batch, rng, T)
    d = tk.simulate(sys_, T, N, channel=ch, inputs=u3, seed=20)
    y = with_gaps(d.y, rng).reshape(batch + (T, 2))
    return tk.SaturationAssumedDensityFilter(sys_, ch, covariance_update=form), y, u


def _particle(batch, rng, piece, sys_, seed, particles=64, **sim):
    T = 12
    N, u, u3 = _inputs(batch, rng, T)
    d = tk.simulate(sys_, T, N, inputs=u3, seed=seed, **sim)
    y = with_gaps(d.y, rng).reshape(batch + (T, d.y.shape[-1]))
    return tk.ParticleFilter(sys_, piece, particles=particles, seed=seed), y, u


def case_pf(batch, rng, backend="numpy", form="standard", particles=64):
    """The particle filter on censored readings (optimal proposal): time-varying A, C and limits, Bu and D."""
    sys_ = _tv_system(m=2, D=[[0.1], [0.0]])
    cens = tk.Censoring(lower=np.linspace(-0.5, 0.2, 12)[:, None] * np.ones((1, 2)), upper=1.0)
    return _particle(batch, rng, cens, sys_, 21, particles, censoring=cens)


def case_pf_fading(batch, rng, backend="numpy", form="standard", particles=64):
    from tobitkf.channels.fading import RiceFading

    fad = RiceFading.gaussian(1, [0.9, 0.6], [0.01, 0.01])
    return _particle(batch, rng, fad, _tv_system(m=1, D=[[0.2]]), 22, particles, measurement=fad)


def case_pf_protocol(batch, rng, backend="numpy", form="standard", particles=64):
    from tobitkf.channels.laws import PMF
    from tobitkf.channels.protocol import ProtocolChannel

    ch = ProtocolChannel(2, window=1, failures=PMF([0.0, 1.0], [0.2, 0.8]), threshold=0.0)
    return _particle(batch, rng, ch, _tv_system(m=2), 23, particles, channel=ch)


def case_pf_saturation(batch, rng, backend="numpy", form="standard", particles=64):
    ch = tk.RandomSaturation([0.3, 0.2], [0.8, 0.9], level=0.5)
    return _particle(batch, rng, ch, _tv_system(m=2), 24, particles, channel=ch)


CASES = {
    "adf": case_adf,
    "adf-fading": case_adf_fading,
    "adf-protocol": case_adf_protocol,
    "adf-saturation": case_adf_saturation,
    "pf": case_pf,
    "pf-fading": case_pf_fading,
    "pf-protocol": case_pf_protocol,
    "pf-saturation": case_pf_saturation,
    "fkf": case_fkf,
    "cltkf": case_cltkf,
    "pbtkf": case_pbtkf,
    "multi-region": case_multi_region,
    "hinf": case_hinf,
    "kf": case_kf,
    "kf-inputs-tv": case_kf_inputs_tv,
    "dkf": case_dkf,
    "tkf": case_tkf,
    "tkf-tv": case_tkf_tv,
    "sstkf": case_sstkf,
    "fading": case_fading,
    "protocol": case_protocol,
    "delay-chain": case_delay_chain,
    "delay-augmented": case_delay_augmented,
    "delay-reorganized": case_delay_reorganized,
}
BATCHES = [(), (5,), (2, 3)]


def run_steps(est, y, u, batch, T, start=None):
    state = est.init(batch) if start is None else start
    means, covs = [], []
    for k in range(T):
        uk = None if u is None else u[..., k, :]
        state = est.step(state, y[..., k, :], u=uk) if uk is not None else est.step(state, y[..., k, :])
        means.append(state.mean)
        covs.append(state.cov)
    if covs[0] is None:  # a family without a covariance (the H∞ filter)
        return state, np.stack(means, axis=-2), None
    return state, np.stack(means, axis=-2), np.stack(covs, axis=-3)


def filter_of(est, y, u, **kw):
    return est.filter(y, u=u, **kw) if u is not None else est.filter(y, **kw)


@pytest.mark.parametrize("batch", BATCHES, ids=str)
@pytest.mark.parametrize("name", sorted(CASES))
def test_step_loop_equals_filter(name, batch):
    rng = np.random.default_rng(0)
    est, y, u = CASES[name](batch, rng)
    T = y.shape[-2]
    res = filter_of(est, y, u)
    state, means, covs = run_steps(est, y, u, batch, T)
    k0 = est.k0  # the prior's time index: 0, or -1 for the delay family (y(0) first)
    assert res.mean.shape == batch + (T, est.n) and res.times.tolist() == list(range(k0 + 1, k0 + T + 1))
    np.testing.assert_allclose(means, res.mean, rtol=0, atol=TOL)
    assert (covs is None) == (res.cov is None)
    if covs is not None:
        np.testing.assert_allclose(covs, res.cov, rtol=0, atol=TOL)
    assert state.k == k0 + T and res.final.k == k0 + T
    np.testing.assert_allclose(state.mean, res.final.mean, rtol=0, atol=TOL)


@pytest.mark.parametrize("name", sorted(CASES))
def test_pickled_state_resumes_identically(name):
    rng = np.random.default_rng(1)
    batch = (4,)
    est, y, u = CASES[name](batch, rng)
    T = y.shape[-2]
    half = T // 2
    state, _, _ = run_steps(est, y[..., :half, :], None if u is None else u[..., :half, :], batch, half)
    revived = pickle.loads(pickle.dumps(state))
    assert isinstance(revived, FilterState) and revived.k == est.k0 + half
    a, ma, _ = run_steps(est, y[..., half:, :], None if u is None else u[..., half:, :], batch, T - half, start=state)
    b, mb, _ = run_steps(est, y[..., half:, :], None if u is None else u[..., half:, :], batch, T - half, start=revived)
    np.testing.assert_array_equal(ma, mb)
    assert (a.cov is None) == (b.cov is None)
    if a.cov is not None:
        np.testing.assert_array_equal(a.cov, b.cov)
    # filter() continues from a state too, and the two halves make the whole record
    whole = filter_of(est, y, u)
    second = est.filter(y[..., half:, :], state=revived, **({} if u is None else {"u": u[..., half:, :]}))
    assert second.times.tolist() == list(range(est.k0 + half + 1, est.k0 + T + 1))
    np.testing.assert_allclose(second.mean, whole.mean[..., half:, :], rtol=0, atol=TOL)


@pytest.mark.parametrize("name", ["kf", "dkf", "tkf"])
def test_compiled_step_equals_numpy_step(name):
    pytest.importorskip("numba")
    rng = np.random.default_rng(2)
    est_np, y, u = CASES[name]((3,), rng, backend="numpy")
    est_nb, _, _ = CASES[name]((3,), np.random.default_rng(2), backend="numba")
    _, m_np, c_np = run_steps(est_np, y, u, (3,), y.shape[-2])
    _, m_nb, c_nb = run_steps(est_nb, y, u, (3,), y.shape[-2])
    np.testing.assert_allclose(m_nb, m_np, rtol=0, atol=TOL)
    np.testing.assert_allclose(c_nb, c_np, rtol=0, atol=TOL)


@pytest.mark.parametrize("backend", ["numpy", "numba"])
@pytest.mark.parametrize("batch", [(), (3,)], ids=str)
def test_dropping_step_leaves_out_the_readings_of_the_limit_rule(backend, batch):
    """The online step's dropped readings (a band computed once for constant limits) are those of the limit
    rule applied per reading: two-sided limits, an infinite one, a wide rtol and readings on either side of
    the tolerance edge; the step loop equals the filter and a KF fed the dropped readings as NaN."""
    if backend == "numba":
        pytest.importorskip("numba")
    sys_ = tk.LinearSystem(
        A=[[0.9, 0.1], [0.0, 0.95]], C=np.eye(3, 2), Q=1e-2 * np.eye(2), R=0.05 * np.eye(3),
        x0=[0.3, 0.1], P0=np.eye(2),
    )  # fmt: skip
    cens = tk.Censoring(lower=[0.0, -np.inf, -2.0], upper=[1.0, 0.5, np.inf])
    rtol = 1e-3
    est = tk.DroppingKalmanFilter(sys_, cens, rtol=rtol, backend=backend)
    tol = rtol * np.maximum(1.0, np.abs(np.array([0.0, 0.5, -2.0])))
    edges = [0.0 + tol[0], 1.0 - tol[0], 0.5 - tol[1], -2.0 + tol[2]]
    N = int(np.prod(batch)) if batch else 1
    rng = np.random.default_rng(8)
    T = 16
    y = np.clip(0.4 * rng.standard_normal((N, T, 3)), [0.0, -np.inf, -2.0], [1.0, 0.5, np.inf])
    y[:, 3] = [edges[0], 0.2, edges[3]]  # at the edges: dropped
    y[:, 4] = [edges[1], edges[2], 0.1]
    y[:, 5] = [edges[0] + 1e-9, edges[2] - 1e-9, edges[3] + 1e-9]  # just inside: kept
    y[:, 6, 1] = np.nan
    y = y.reshape(batch + (T, 3))
    expected = np.isnan(y) | np.stack([est._dropped(y[..., t, :], t + 1) for t in range(T)], axis=-2)
    assert expected[..., 3, [0, 2]].all() and expected[..., 4, :2].all() and not expected[..., 5, :].any()
    state = est.init(batch)
    means = []
    for t in range(T):
        state = est.step(state, y[..., t, :])
        means.append(state.mean)
        dropped = expected[..., t, :] & ~np.isnan(y[..., t, :])  # the step's extra: dropped, not missing
        np.testing.assert_array_equal(np.reshape(state.extras["censored"], dropped.shape), dropped)
    res = est.filter(y)
    kf = tk.KalmanFilter(sys_, backend="numpy").filter(np.where(expected, np.nan, y))
    np.testing.assert_array_equal(res.extras["censored"], expected & ~np.isnan(y))
    np.testing.assert_allclose(np.stack(means, axis=-2), res.mean, rtol=0, atol=TOL)
    np.testing.assert_allclose(np.stack(means, axis=-2), kf.mean, rtol=0, atol=TOL)
    np.testing.assert_allclose(state.cov, kf.final.cov, rtol=0, atol=TOL)


@pytest.mark.parametrize(
    "name",
    ["kf", "dkf", "tkf", "tkf-tv", "kf-inputs-tv", "fading", "protocol"]
    + ["adf", "adf-fading", "adf-protocol", "adf-saturation"],
)
def test_square_root_form_equals_standard(name):
    rng = np.random.default_rng(3)
    std, y, u = CASES[name]((4,), rng)
    sq, _, _ = CASES[name]((4,), np.random.default_rng(3), form="square_root")
    a, b = filter_of(std, y, u), filter_of(sq, y, u)
    np.testing.assert_allclose(b.mean, a.mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(b.cov, a.cov, rtol=0, atol=1e-10)
    _, ms, _ = run_steps(sq, y, u, (4,), y.shape[-2])
    np.testing.assert_allclose(ms, b.mean, rtol=0, atol=TOL)


def test_missing_reading_only_predicts():
    sys_ = oscillator()
    kf = tk.KalmanFilter(sys_, backend="numpy")
    s0 = kf.init((2,))
    s1 = kf.step(s0, [[np.nan], [0.3]])
    pred = kf.predict(s0)
    np.testing.assert_array_equal(s1.mean[0], pred.mean[0])
    np.testing.assert_array_equal(s1.cov[0], pred.cov[0])
    assert not np.allclose(s1.mean[1], pred.mean[1])


@pytest.mark.parametrize(
    "name",
    ["protocol", "fading", "tkf", "dkf", "fkf", "multi-region"]
    + ["adf", "adf-fading", "adf-protocol", "adf-saturation"],
)
def test_a_lost_reading_only_predicts_in_every_family(name):
    """A NaN reading of one run: that run's state after the step is the prediction (mean and covariance),
    the other runs are updated."""
    est, y, u = CASES[name]((3,), np.random.default_rng(5))
    s0 = est.init((3,))
    yk = np.where(np.isnan(y[:, 0]), 0.0, y[:, 0])  # complete first readings (0: valid for every case), run 0 lost
    yk[0] = np.nan
    uk = None if u is None else u[:, 0]
    s1 = est.step(s0, yk) if uk is None else est.step(s0, yk, u=uk)
    pred = est.predict(s0) if uk is None else est.predict(s0, u=uk)
    P1, Pp = np.broadcast_to(s1.cov, (3,) + s1.cov.shape[-2:]), np.broadcast_to(pred.cov, (3,) + pred.cov.shape[-2:])
    np.testing.assert_allclose(s1.mean[0], pred.mean[0], rtol=0, atol=TOL)
    np.testing.assert_allclose(P1[0], Pp[0], rtol=0, atol=TOL)
    assert np.abs(P1[1:] - Pp[1:]).max() > 1e-6  # the others are updated


@pytest.mark.parametrize("name", ["pf", "pf-fading", "pf-protocol", "pf-saturation"])
def test_a_lost_reading_only_predicts_in_the_particle_filter(name):
    """A NaN reading of one run: its log-weights are unchanged (exactly), its likelihood term is 0, and its
    particles are the transition of the carried cloud: their weighted mean is A m + B^u u, m the weighted
    mean of the carried particles, up to sum_i W_i G z_i, of covariance Q / ESS (|z| < 5; measured N(0, 1)
    over 30 seeds for each channel). The optimal proposals draw the transition noise their own way, so no
    exact equality. The other runs are updated."""
    est, y, u = CASES[name]((3,), np.random.default_rng(5), particles=20000)
    s1 = est.step(est.init((3,)), y[:, 0], u=u[:, 0])
    yk = np.where(np.isnan(y[:, 1]), 0.0, y[:, 1])  # complete readings (0: valid for every case), run 0 lost
    yk[0] = np.nan
    res = est.filter(yk[:, None], u=u[:, 1:2], state=s1)
    ll = res.extras["log_likelihood"][:, 0]
    assert ll[0] == 0.0 and not res.extras["resampled"][0, 0] and np.all(ll[1:] != 0.0)
    np.testing.assert_array_equal(res.final.carry["log_weights"][0], s1.carry["log_weights"][0])
    W, X = np.exp(s1.carry["log_weights"][0]), s1.carry["particles"][0][:, : est.n]
    pred = est.system.transition(1) @ (W @ X) + est.system.Bu.at(2) @ u[0, 1]
    z = (res.mean[0, 0] - pred) / np.sqrt(np.diagonal(est.system.process_cov(1)) * (W @ W))
    assert np.all(np.abs(z) < 5.0), z
    np.testing.assert_array_equal(res.final.carry["particles"][0][:, est.n :], s1.carry["particles"][0][:, : -est.n])


def test_channels_without_feedthrough_refuse_u_with_D():
    """The protocol and random-saturation readings have no D u: with a system that has D, a control input
    is refused with the reason (it used to be dropped silently), by the assumed-density filters and the
    particle filter, in filter, step and update, and by the simulator's draw of those channels; Bu alone
    is taken."""
    from tobitkf.channels.laws import PMF
    from tobitkf.channels.protocol import ProtocolChannel

    sys_ = _tv_system(m=2, D=[[1.0], [0.5]])
    prot = ProtocolChannel(2, window=1, failures=PMF([0.0, 1.0], [0.2, 0.8]), threshold=0.0)
    sat = tk.RandomSaturation([0.3, 0.2], [0.8, 0.9], level=0.5)
    u = np.ones((2, 3, 1))
    for est, m, why in [
        (tk.ProtocolAssumedDensityFilter(sys_, prot), 1, "protocol channel's reading .*has no feedthrough D u"),
        (tk.SaturationAssumedDensityFilter(sys_, sat), 2, "saturation filter's reading .*has no feedthrough D u"),
        (tk.ParticleFilter(sys_, prot, particles=8, seed=0), 1, "protocol channel's reading has no feedthrough"),
        (tk.ParticleFilter(sys_, sat, particles=8, seed=0), 2, "random-saturation channel's reading has no feedth"),
    ]:
        y = np.full((2, 3, m), 0.1)
        with pytest.raises(tk.ValidationError, match=f"u: the {why}"):
            est.filter(y, u=u)
        with pytest.raises(tk.ValidationError, match=f"u: the {why}"):
            est.step(est.init((2,)), y[:, 0], u=u[:, 0])
        if not isinstance(est, tk.ParticleFilter):
            with pytest.raises(tk.ValidationError, match=f"u: the {why}"):
                est.update(est.predict(est.init((2,)), u=u[:, 0]), y[:, 0])
        est.filter(y)  # no input: fine
    for ch, why in [(prot, "protocol channel's reading"), (sat, "randomly saturated reading")]:
        with pytest.raises(tk.ValidationError, match=f"u: the {why} \\(2\\) has no feedthrough D u"):
            tk.simulate(sys_, 3, 2, channel=ch, inputs=u, seed=0)
        tk.simulate(sys_, 3, 2, channel=ch, seed=0)  # no input: fine


def test_predict_then_update_equals_step():
    sys_ = oscillator()
    tkf = tk.TobitKalmanFilter(sys_, tk.Censoring(lower=0.0), backend="numpy")
    s0 = tkf.init((3,))
    y = np.array([[0.0], [0.4], [1.0]])
    a = tkf.step(s0, y)
    b = tkf.update(tkf.predict(s0), y)
    np.testing.assert_array_equal(a.mean, b.mean)
    np.testing.assert_array_equal(a.cov, b.cov)


def test_steered_limits_in_update_equal_a_filter_with_those_limits():
    sys_ = oscillator()
    T = 8
    lower = np.linspace(-0.2, 0.3, T)[:, None]
    d = tk.simulate(sys_, T, 3, censoring=tk.Censoring(lower=lower), seed=7)
    ref = tk.TobitKalmanFilter(sys_, tk.Censoring(lower=lower), backend="numpy").filter(d.y)
    tkf = tk.TobitKalmanFilter(sys_, tk.Censoring(), backend="numpy")
    state = tkf.init((3,))
    for k in range(T):
        state = tkf.update(tkf.predict(state), d.y[:, k], lower=lower[k])
        np.testing.assert_allclose(state.mean, ref.mean[:, k], rtol=0, atol=TOL)


def test_step_state_is_the_dataclass_state():
    """The steps' constructor (no frozen __init__) makes the object FilterState(...) makes: same fields, a
    fresh empty dict for each default, frozen, and it pickles."""
    import dataclasses

    from tobitkf.filters.core import step_state

    x, P = np.zeros((1, 2)), np.eye(2)[None]
    a = step_state(3, (), x, P, 2)
    b = FilterState(k=3, batch_shape=(), x=x, P=P, n=2)
    assert type(a) is FilterState and vars(a).keys() == vars(b).keys()
    assert all(
        getattr(a, f.name) is getattr(b, f.name) for f in dataclasses.fields(b) if f.name not in ("carry", "extras")
    )
    assert (
        a.carry == {} and a.extras == {} and a.carry is not a.extras and a.carry is not step_state(3, (), x, P, 2).carry
    )
    with pytest.raises(dataclasses.FrozenInstanceError):
        a.k = 4  # type: ignore[misc]
    c = pickle.loads(pickle.dumps(step_state(1, (1,), x, P, 2, None, {"O": 1}, {"e": 2})))
    assert (c.k, c.batch_shape, c.carry, c.extras) == (1, (1,), {"O": 1}, {"e": 2}) and np.array_equal(c.P, P)


def test_bad_state_and_reading_are_refused():
    sys_ = oscillator()
    kf = tk.KalmanFilter(sys_)
    with pytest.raises(tk.ValidationError, match="state: expected a FilterState"):
        kf.step("prior", [0.0])
    with pytest.raises(tk.ShapeError, match=r"y: expected one reading of shape \(3, 1\)"):
        kf.step(kf.init((3,)), np.zeros((2, 1)))
    with pytest.raises(tk.ValidationError, match="batch_shape: expected a tuple of positive integers"):
        kf.init((0,))
    with pytest.raises(TypeError, match="unexpected keyword argument 'lower'"):
        kf.step(kf.init(), [0.0], lower=0.0)
    with pytest.raises(tk.ValidationError, match="update\\(\\) needs a predicted state"):
        kf.update(kf.init(), [0.0])


def test_outputs_on_request():
    sys_ = oscillator()
    d = tk.simulate(sys_, 20, 50, censoring=tk.Censoring(lower=0.0), seed=8)
    for backend in ("numpy", "auto"):
        tkf = tk.TobitKalmanFilter(sys_, tk.Censoring(lower=0.0), backend=backend)
        full = tkf.filter(d.y)
        means = tkf.filter(d.y, outputs="mean")
        assert means.cov is None and means.pred_mean is None and means.pred_cov is None and means.extras == {}
        np.testing.assert_allclose(means.mean, full.mean, rtol=0, atol=TOL)
        var = tkf.filter(d.y, outputs=("mean", "var"))
        np.testing.assert_allclose(var.var, np.diagonal(full.cov, axis1=-2, axis2=-1), rtol=0, atol=TOL)
        last = tkf.filter(d.y, outputs="last")
        assert last.mean is None
        np.testing.assert_allclose(last.final.mean, full.mean[:, -1], rtol=0, atol=TOL)
    with pytest.raises(tk.ValidationError, match="outputs: expected 'all', 'last' or names"):
        tkf.filter(d.y, outputs="covariance")


def test_steady_state_latent_step_equals_filter_controlled():
    sys_ = oscillator()
    est = tk.SteadyStateTobitKalmanFilter(sys_, 0.6, side="lower")
    d = tk.simulate(sys_, 12, 4, seed=9)
    ref = est.filter_controlled(d.y_latent)
    state = est.init((4,))
    for k in range(12):
        state = est.step(state, d.y_latent[:, k], latent=True)
        np.testing.assert_allclose(state.mean, ref.mean[:, k], rtol=0, atol=TOL)
    np.testing.assert_array_equal(state.cov, np.broadcast_to(est.cov, (4, 2, 2)))


@pytest.mark.parametrize("side", ["upper", "lower"])
@pytest.mark.parametrize("latent", [False, True])
@pytest.mark.parametrize("batch", [(), (3,)], ids=str)
def test_steady_state_step_without_input_is_the_fixed_gain_recursion(side, latent, batch):
    """The step without an input (its own short path) against the recursion written out,
    x̄ = A x, x = x̄ + K(y - E[y]) with E[y] of (3.58), against the numpy filter (its extras too), and an
    overflowed estimate takes the shared step (NaN innovation: channel left out, the mean stays x̄)."""
    sys_ = oscillator(C=[[1.0, 0.0], [0.3, 1.0]], R=np.diag([0.04, 0.09]))
    est = tk.SteadyStateTobitKalmanFilter(sys_, [0.7, 0.55], side=side, backend="numpy")
    N = int(np.prod(batch)) if batch else 1
    d = tk.simulate(sys_, 10, N, seed=12)
    censored = est.filter_controlled(d.y_latent).extras["y"]
    ref = est.filter_controlled(d.y_latent) if latent else est.filter(censored)
    yin = d.y_latent if latent else censored
    A, C, K = sys_.transition(0), sys_.measurement(1), est.gain
    shift = est.sigma * est.alpha
    x = np.broadcast_to(sys_.x0, (N, 2)).copy()
    state = est.init(batch)
    for k in range(10):
        yk = yin[:, k].reshape(batch + (2,))
        state = est.step(state, yk, **({"latent": True} if latent else {}))
        xb = x @ A.T
        ybar = xb @ C.T
        lim = ybar + shift if side == "upper" else ybar - shift
        obs = (np.minimum if side == "upper" else np.maximum)(yin[:, k], lim) if latent else yin[:, k]
        expected = ybar - est._offset if side == "upper" else ybar + est._offset
        x = xb + (obs - expected) @ K.T
        np.testing.assert_allclose(state.mean, x.reshape(batch + (2,)), rtol=0, atol=TOL)
        np.testing.assert_allclose(state.mean, ref.mean.reshape(N, 10, 2)[:, k].reshape(batch + (2,)), rtol=0, atol=TOL)
        if latent:
            np.testing.assert_allclose(state.extras["limits"], lim, rtol=0, atol=TOL)
            np.testing.assert_allclose(state.extras["y"], obs, rtol=0, atol=TOL)
        else:
            assert state.extras == {}
        np.testing.assert_array_equal(state.cov, np.broadcast_to(est.cov, batch + (2, 2)))
    blown = state.replace(x=np.where(np.arange(2) == 0, np.inf, -np.inf) + 0 * state.x)
    with np.errstate(invalid="ignore"):
        after = est.step(blown, yin[:, 0].reshape(batch + (2,)))
        shared = est._step_arrays(blown.k + 1, blown.x, blown.P, None, {}, yin[:, 0], None, {})
    assert np.isnan(after.x).any()
    np.testing.assert_array_equal(after.x, shared[0])


def test_controlled_full_tkf_step_equals_its_filter():
    sys_ = oscillator()
    est = tk.filters.steady_state.ControlledLimitTobitKalmanFilter(sys_, 0.7)
    d = tk.simulate(sys_, 10, 3, seed=10)
    ref = tk.tobit_kalman_filter_controlled(sys_, 0.7, d.y_latent)
    state = est.init((3,))
    for k in range(10):
        state = est.step(state, d.y_latent[:, k])
        np.testing.assert_allclose(state.mean, ref.mean[:, k], rtol=0, atol=TOL)
        np.testing.assert_allclose(state.cov, ref.cov[:, k], rtol=0, atol=TOL)


def test_steady_state_inverse_mills_has_the_sign_of_censored_moments():
    sys_ = oscillator()
    for side in ("upper", "lower"):
        est = tk.SteadyStateTobitKalmanFilter(sys_, 0.5, side=side)
        lim = est.limit(np.zeros(1))
        lo, hi = (-np.inf, lim) if side == "upper" else (lim, np.inf)
        st = tk.censored_moments(0.0, est.sigma, lo, hi)
        np.testing.assert_allclose(est.inverse_mills, st.inverse_mills, rtol=1e-12)
        np.testing.assert_allclose(est.lambda_hat, np.sqrt(2 / np.pi), rtol=1e-12)  # phi(0) / 0.5


# --- property: batched = per run = step by step, on random models ---------------------------------
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@settings(deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    n=st.integers(1, 3),
    m=st.integers(1, 2),
    seed=st.integers(0, 2**31 - 1),
    family=st.sampled_from(["kf", "tkf", "dkf", "tkf-sqrt", "tkf-joseph"]),
)
def test_batched_equals_per_run_equals_step_by_step(n, m, seed, family):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    A *= 0.95 / max(1e-9, np.abs(np.linalg.eigvals(A)).max())
    G = rng.normal(size=(n, n))
    sys_ = tk.LinearSystem(
        A=A,
        C=rng.normal(size=(m, n)),
        Q=G @ G.T / n + 0.01 * np.eye(n),
        R=np.diag(rng.uniform(0.05, 1.0, m)),
        x0=rng.normal(size=n),
        P0=np.eye(n),
    )
    lower = rng.normal(size=m) * 0.5
    cens = tk.Censoring(lower=lower)
    d = tk.simulate(sys_, 8, 3, censoring=cens, seed=seed)
    y = with_gaps(d.y, rng, 0.15)
    make = {
        "kf": lambda: tk.KalmanFilter(sys_, backend="numpy"),
        "dkf": lambda: tk.DroppingKalmanFilter(sys_, cens, backend="numpy"),
        "tkf": lambda: tk.TobitKalmanFilter(sys_, cens, backend="numpy"),
        "tkf-sqrt": lambda: tk.TobitKalmanFilter(sys_, cens, covariance_update="square_root"),
        "tkf-joseph": lambda: tk.TobitKalmanFilter(sys_, cens, covariance_update="joseph", backend="numpy"),
    }[family]
    est = make()
    batch = est.filter(y)
    for r in range(3):
        one = est.filter(y[r])
        np.testing.assert_allclose(one.mean, batch.mean[r], rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(one.cov, batch.cov[r], rtol=1e-10, atol=1e-12)
    state = est.init((3,))
    for k in range(8):
        state = est.step(state, y[:, k])
    np.testing.assert_allclose(state.mean, batch.mean[:, -1], rtol=0, atol=1e-12)


@pytest.mark.parametrize("form", ["predictor", "filter"])
def test_estimators_without_covariance_step_like_their_filter(form):
    """The fixed-gain Tobit observer (Miller (5.2)) and the H-infinity filter: no covariance, same API."""
    from tobitkf.filters.fixed_gain import FixedGainTobitObserver

    rng = np.random.default_rng(14)
    y = np.maximum(rng.normal(size=(4, 20, 1)), -0.3)
    obs = FixedGainTobitObserver([[0.9]], [[0.4]], [[1.0]], 0.5, -0.3, form=form)
    res = obs.filter(y)
    assert res.cov is None and res.times.tolist() == list(range(1, 21))
    state = obs.init((4,))
    for k in range(20):
        state = obs.step(state, y[:, k])
        np.testing.assert_allclose(state.mean, res.mean[:, k], rtol=0, atol=TOL)
    revived = pickle.loads(pickle.dumps(state))
    assert revived.k == 20 and revived.cov is None
    with pytest.raises(tk.ValidationError, match="y: expected finite numbers, found NaN"):
        obs.step(state, np.full((4, 1), np.nan))
    hinf = tk.RegionalHinfFilter([[0.5, 0.1], [0.0, 0.8]], [[1.0], [0.2]], [[1.0, 0.0]])
    r = hinf.filter(y)
    s = hinf.init((4,))
    for k in range(20):
        s = hinf.step(s, y[:, k])
    np.testing.assert_allclose(s.mean, r.mean[:, -1], rtol=0, atol=TOL)


def test_families_that_refuse_a_lost_reading_say_why():
    from tobitkf.filters.fixed_gain import FixedGainTobitObserver
    from tobitkf.models.delay import paper_example, paper_prior

    y = np.array([[[0.1], [np.nan], [0.2]]])
    cases = [
        (tk.RegionalHinfFilter([[0.5]], [[1.0]], [[2.0]]), "no rule for a lost reading"),
        (FixedGainTobitObserver([[0.9]], [[0.4]], [[1.0]], 0.5, -0.3), "no rule for a lost reading"),
        (tk.ChainLMMSE(paper_example(), paper_prior()), "cannot be skipped"),
    ]
    for est, why in cases:
        with pytest.raises(tk.ValidationError, match=f"found NaN .*{why}"):
            est.filter(y)
        with pytest.raises(tk.ValidationError, match=f"found NaN .*{why}"):
            est.step(est.init((1,)), y[:, 1])


def test_one_run_reading_fast_path_gives_the_general_paths_array_and_errors():
    """``step``'s reading of one run as a float64 (m,) array takes a shortcut (its verdict in Python floats): it
    returns the general path's (1, m) array, the same memory, and every reading it does not pass (NaN where the
    family refuses it, inf, the wrong length, another dtype or shape) gets the general path's error, named as
    before; a list of the same values (always the general path) is the reference."""
    from tobitkf.models.delay import paper_example, paper_prior

    sys_ = oscillator()
    ests = [
        tk.KalmanFilter(sys_),
        tk.TobitKalmanFilter(sys_, tk.Censoring(lower=0.0)),
        tk.ChainLMMSE(paper_example(), paper_prior()),
        tk.RegionalHinfFilter([[0.5]], [[1.0]], [[2.0]]),
    ]
    record = np.array([[0.3, 7.0], [np.nan, 1.0], [np.inf, 0.0], [-np.inf, 2.0], [0.0, 0.0]])
    for est in ests:
        s, s1 = est.init(), est.init((1,))
        for row in record:
            y = row[:1]  # a view of a row of a record, as in a loop over it
            want_err = None
            try:
                want = est._reading(s, y.tolist())
            except ValueError as err:  # ValidationError, ShapeError
                want_err = (type(err), str(err))
            if want_err is None:
                got = est._reading(s, y)
                assert got.shape == (1, 1) and np.shares_memory(got, y)
                np.testing.assert_array_equal(got, want)
                np.testing.assert_array_equal(est._reading(s1, y), want)
            else:
                with pytest.raises(want_err[0]) as info:
                    est._reading(s, y)
                assert str(info.value) == want_err[1]
        for bad in (np.zeros(2), np.zeros(0), np.zeros((1, 1, 1))):  # the wrong length or shape
            with pytest.raises(tk.ShapeError, match="expected one reading of shape"):
                est.step(s, bad)
        # other dtypes and non-contiguous views take the general path, with its numbers
        np.testing.assert_array_equal(est._reading(s, np.array([2], dtype=np.int64)), [[2.0]])
        np.testing.assert_array_equal(est._reading(s, np.array([0.5], dtype=np.float32)), [[0.5]])
        np.testing.assert_array_equal(est._reading(s, record[::2, 1][:1]), [[7.0]])
