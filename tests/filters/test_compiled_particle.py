"""The compiled particle filter (tobitkf.filters._compiled_particle) against the numpy path it implements.

The compiled loop draws its own numbers from the filter's generator, in its own order (documented in
the module). For the same random numbers the two paths must agree: the numpy path is fed, through a
stand-in generator, exactly the numbers the compiled loop drew (replayed from the same generator
state in the compiled order), and every output, the final particles and weights must then agree to
rounding, and the replay must leave the generator where the compiled loop left it. The normal tails
are checked against scipy.special.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import log_ndtr as scipy_log_ndtr
from scipy.special import ndtri_exp as scipy_ndtri_exp

import tobitkf as tk
from tobitkf.channels.base import interval_moments
from tobitkf.filters import _particle_models as pm
from tobitkf.filters import particle as pt
from tobitkf.filters._particle_rng import generator
from tobitkf.filters._readings import LOWER, UPPER, classify_readings

pytest.importorskip("numba")

from tobitkf.filters import _compiled_particle as cp  # noqa: E402

TOL = 1e-12


def system(m):
    A = [[0.95, 0.1], [0.0, 0.9]]
    C = [[1.0, 0.0], [0.5, 1.0]][:m]
    R = np.diag([0.1, 0.2][:m])
    return tk.LinearSystem(A=A, C=C, Q=0.05 * np.eye(2), R=R, x0=[0.2, 0.0], P0=np.eye(2))


CENSORINGS = {
    "lower": lambda m: tk.Censoring(lower=np.zeros(m)),
    "upper": lambda m: tk.Censoring(upper=np.full(m, 0.3)),
    "two-sided": lambda m: tk.Censoring(lower=np.full(m, -0.2), upper=np.full(m, 0.4)),
    "mixed": lambda m: tk.Censoring(lower=[0.0, -np.inf][:m], upper=[np.inf, 0.3][:m]),
    "none": lambda m: None,
}


def record(m, cens, runs=6, steps=12, seed=0):
    y = tk.simulate(system(m), steps, runs, censoring=cens, seed=seed).y.copy()
    y[1, 3, 0] = np.nan  # one channel missing
    y[2, 5] = np.nan  # every channel missing
    return y


class _Feed:
    """Stands in for the numpy path's Generator: serves prepared arrays, in the order the path asks for them."""

    def __init__(self, arrays):
        self.arrays = list(arrays)
        self.bit_generator = self  # the path stores ``bit_generator.state`` in its carry
        self.state = {"bit_generator": "fed"}

    def _next(self, size):
        a = self.arrays.pop(0)
        assert a.shape == (size if isinstance(size, tuple) else (size,)), (a.shape, size)
        return a.copy()

    def random(self, size=None):
        return self._next(size)

    def standard_normal(self, size=None):
        return self._next(size)


def replay(pf, state, y, block):
    """The numbers the compiled loop draws from ``state``'s generator, in its order, as the arrays the numpy
    path asks for per step ((U,) eps, the resampling uniforms); and the generator after them."""
    N, T, m = y.shape
    Np, n = pf.particles, pf.n
    optimal = pf.proposal == "optimal"
    lims = [pf.model.limits(state.k + 1 + k) for k in range(T)]
    lo = np.array([a for a, _ in lims])[None]
    hi = np.array([b for _, b in lims])[None]
    censored = np.isin(classify_readings(y, lo, hi), (LOWER, UPPER))
    channel = getattr(pf.model, "channel", None)
    if channel is not None and not isinstance(pf.model, pm._Saturation):  # a region: a uniform per interval reading
        for k in range(T):
            for l in range(m):
                a, b = channel.region(np.nan_to_num(y[:, k, l]), state.k + 1 + k, l)
                censored[:, k, l] = (a != b) & ~np.isnan(y[:, k, l])
    g = generator(state.carry["rng"])
    U, E, UR = np.full((T, N, Np, m), 0.5), np.empty((T, N, Np, n)), np.full((T, N), 0.5)
    resampled = {}

    def draw_step(k, b, res):
        for p in range(Np):
            if optimal:
                for l in range(m):
                    if censored[b, k, l]:
                        U[k, b, p, l] = g.random()
            for j in range(n):
                E[k, b, p, j] = g.standard_normal()
        if res:
            UR[k, b] = g.random()

    return U, E, UR, g, draw_step, resampled


def fed_numpy_path(pf, state, y, compiled, block):
    """The numpy path run from ``state`` on the numbers the compiled loop drew (``compiled``: its result)."""
    N, T, _ = y.shape
    U, E, UR, g, draw_step, _ = replay(pf, state, y, block)
    res = compiled.extras["resampled"].reshape(N, T)
    for r0 in range(0, N, block):
        for k in range(T):
            for b in range(r0, min(N, r0 + block)):
                draw_step(k, b, res[b, k])
    arrays = []
    for k in range(T):
        arrays += ([U[k]] if pf.proposal == "optimal" else []) + [E[k], UR[k]]
    feed = _Feed(arrays)
    orig, backend = pt._generator, pf.backend
    pt._generator, pf.backend = (lambda state: feed), "numpy"
    try:
        out = pf.filter(y, state=state, outputs=("mean", "cov", "pred_mean", "pred_cov", "extras"))
    finally:
        pt._generator, pf.backend = orig, backend
    assert not feed.arrays  # every prepared number was used
    return out, g.bit_generator.state


def assert_same(a, b):
    for key in ("mean", "cov", "pred_mean", "pred_cov"):
        np.testing.assert_allclose(getattr(b, key), getattr(a, key), rtol=0, atol=TOL, err_msg=key)
    np.testing.assert_array_equal(b.extras["resampled"], a.extras["resampled"])
    np.testing.assert_allclose(b.extras["ess"], a.extras["ess"], rtol=TOL, atol=0)
    # the log-likelihood and log weights to rounding relative to their size (thousands, far in the tails)
    np.testing.assert_allclose(b.extras["log_likelihood"], a.extras["log_likelihood"], rtol=1e-14, atol=TOL)
    fa, fb = a.final.carry, b.final.carry
    np.testing.assert_allclose(fb["particles"], fa["particles"], rtol=0, atol=TOL)
    np.testing.assert_allclose(fb["log_weights"], fa["log_weights"], rtol=1e-14, atol=TOL)
    np.testing.assert_allclose(fb["log_likelihood"], fa["log_likelihood"], rtol=1e-14, atol=TOL)


def check_against_numpy(pf, y, block=None, both_branches=True):
    """Run ``pf`` compiled (in blocks of ``block`` runs) and the numpy path on the same numbers; compare."""
    N = int(np.prod(y.shape[:-2]))
    y2 = y.reshape(N, *y.shape[-2:])
    st = pf.init((N,))
    block = block or cp.runs_per_block(pf.particles, pf.n)
    got = cp.filter_blocks(pf, y2, st, frozenset(("mean", "cov", "pred_mean", "pred_cov", "extras")), (N,), block)
    ref, rng_after = fed_numpy_path(pf, st, y2, got, block)
    if both_branches:  # resampling and not resampling are both exercised
        assert ref.extras["resampled"].any() and not ref.extras["resampled"].all()
    assert_same(ref, got)
    assert got.final.carry["rng"] == rng_after  # the compiled loop drew exactly these numbers
    return got


@pytest.mark.parametrize("proposal", ["optimal", "prior"])
@pytest.mark.parametrize("m", [1, 2])
@pytest.mark.parametrize("kind", list(CENSORINGS))
def test_compiled_equals_numpy_for_the_same_random_numbers(proposal, m, kind):
    cens = CENSORINGS[kind](m)
    y = record(m, cens)
    pf = tk.ParticleFilter(system(m), cens, particles=200, proposal=proposal, seed=3, resample_threshold=0.7)
    check_against_numpy(pf, y)


def test_time_varying_limits_and_a_batch_shape():
    cens = tk.Censoring(lower=np.linspace(-0.5, 0.5, 10)[:, None])
    y = tk.simulate(system(1), 10, 6, censoring=cens, seed=1).y.reshape(2, 3, 10, 1)
    pf = tk.ParticleFilter(system(1), cens, particles=150, seed=5, backend="numba")
    b = pf.filter(y)
    assert b.mean.shape == (2, 3, 10, 2) and b.extras["ess"].shape == (2, 3, 10)
    got = check_against_numpy(pf, y)
    np.testing.assert_allclose(b.mean.reshape(6, 10, 2), got.mean, rtol=0, atol=0)


@pytest.mark.parametrize("proposal", ["optimal", "prior"])
def test_blocks_of_runs_draw_one_block_after_the_other(proposal):
    cens = CENSORINGS["two-sided"](1)
    y = record(1, cens, runs=7)
    pf = tk.ParticleFilter(system(1), cens, particles=120, proposal=proposal, seed=9, resample_threshold=0.7)
    check_against_numpy(pf, y, block=3)


def test_readings_far_in_the_tails():
    # a prior mean near 0 and readings censored at -40 and +45 (the latent reading ~40 standard deviations
    # from the prediction): the censored draws come from the far tails of the quantile
    cens = tk.Censoring(lower=[-40.0], upper=[45.0])
    y = np.array([[[-40.0]] * 3, [[45.0]] * 3, [[0.1], [-40.0], [0.3]]])
    pf = tk.ParticleFilter(system(1), cens, particles=300, seed=4, resample_threshold=0.7, proposal="optimal")
    got = check_against_numpy(pf, y, both_branches=False)
    assert np.isfinite(got.mean).all() and np.isfinite(got.extras["log_likelihood"]).all()


def _arrays(obj, seen=None):
    """Every ndarray reachable from a result (its fields, extras and final state)."""
    seen = set() if seen is None else seen
    if id(obj) in seen:
        return []
    seen.add(id(obj))
    if isinstance(obj, np.ndarray):
        return [obj]
    if isinstance(obj, dict):
        return [a for v in obj.values() for a in _arrays(v, seen)]
    if isinstance(obj, (list, tuple)):
        return [a for v in obj for a in _arrays(v, seen)]
    if hasattr(obj, "__dict__"):
        return [a for v in vars(obj).values() for a in _arrays(v, seen)]
    return []


@pytest.mark.parametrize("backend", ["numba", "numpy"])
def test_memory_is_flat_in_the_number_of_steps(backend):
    import tracemalloc

    N, T, Np = 3, 31, 997  # sizes no other axis shares
    cens = CENSORINGS["lower"](1)
    pf = tk.ParticleFilter(system(1), cens, particles=Np, seed=1, backend=backend)
    res = pf.filter(tk.simulate(system(1), T, N, censoring=cens, seed=0).y)
    shapes = [a.shape for a in _arrays(res)]
    assert (N, Np, 2) in shapes  # the final particles are kept (the state to continue from)...
    assert not [s for s in shapes if Np in s and T in s]  # ...but nothing per step and particle
    # the peak of a filter that records nothing per step does not grow with T (beyond the readings)
    peaks = {}
    for steps in (T, 8 * T):
        y = tk.simulate(system(1), steps, N, censoring=cens, seed=0).y
        pf.filter(y[:, :2], outputs="last")  # compiled functions and caches loaded before measuring
        tracemalloc.start()
        pf.filter(y, outputs="last")
        peaks[steps] = tracemalloc.get_traced_memory()[1] - y.nbytes
        tracemalloc.stop()
    assert peaks[T] > 8 * N * Np * 2  # the particles are counted...
    # ...and 7 T more steps add at most a few numbers per step (the limits), not a particle array (24 kB a step)
    assert peaks[8 * T] - peaks[T] < 7 * T * 100


def test_a_filter_continued_from_its_final_state_equals_one_call():
    cens = CENSORINGS["lower"](1)
    y = record(1, cens, steps=14)
    pf = tk.ParticleFilter(system(1), cens, particles=100, seed=2, backend="numba")
    whole = pf.filter(y)
    first = pf.filter(y[:, :6])
    rest = pf.filter(y[:, 6:], state=first.final)
    np.testing.assert_allclose(rest.mean, whole.mean[:, 6:], rtol=0, atol=TOL)
    np.testing.assert_allclose(rest.final.carry["log_likelihood"], whole.final.carry["log_likelihood"], atol=TOL)
    np.testing.assert_array_equal(rest.times, np.arange(7, 15))
    # outputs on request: nothing recorded but the final state; the variances only
    last = pf.filter(y, outputs="last")
    assert last.mean is None and last.extras == {}
    np.testing.assert_allclose(last.final.x, whole.final.x, atol=TOL)
    var = pf.filter(y, outputs="var").var
    np.testing.assert_allclose(var, np.diagonal(whole.cov, axis1=-2, axis2=-1), atol=TOL)


class _MomentsOnly(tk.Channel):
    """A channel with a likelihood of its own (its moments), not a region's."""

    def reading_moments(self, y, mean, std, k, l):
        return interval_moments(mean, std, y - 0.1, y + 0.1)


def test_dispatch_names_what_runs_numpy():
    sys_ = system(1)
    uniform = tk.RiceFading(1, tk.laws.Uniform([0.8, 0.2], [1.0, 0.6]))  # coefficients drawn per particle
    sat = tk.RandomSaturation([0.3], [0.8], level=0.5)
    for channel, proposal, gap in [
        (uniform, "auto", "coefficients that are not Gaussian"),
        (sat, "optimal", "the 'optimal' proposal of saturation readings"),
        (_MomentsOnly(), "auto", "_MomentsOnly readings"),
        (
            tk.ProtocolChannel(1, window=1, failures=tk.laws.PMF([1.0, 0.0], [0.9, 0.1]), threshold=0.0),
            "prior",
            "protocol",
        ),
    ]:
        with pytest.raises(tk.ValidationError, match=f"backend: the compiled path of the particle filter .*{gap}"):
            pf = tk.ParticleFilter(sys_, channel, particles=10, proposal=proposal, backend="numba")
            pf.filter(np.ones((5, 1)))
    with pytest.raises(tk.ValidationError, match="backend: expected one of"):
        tk.ParticleFilter(sys_, particles=10, backend="jax")
    # "auto" falls back to numpy where the loop does not cover the model: equal to backend="numpy" exactly
    y = np.abs(np.random.default_rng(0).normal(size=(3, 5, 1)))
    a = tk.ParticleFilter(sys_, sat, particles=50, seed=1, backend="auto").filter(y)
    b = tk.ParticleFilter(sys_, sat, particles=50, seed=1, backend="numpy").filter(y)
    np.testing.assert_array_equal(a.mean, b.mean)
    # a control input is not covered by the compiled loop
    sys_u = tk.LinearSystem(
        A=sys_.A.at(0), C=[[1.0, 0.0]], Q=0.05 * np.eye(2), R=[[0.1]], x0=[0.0, 0.0], P0=np.eye(2), Bu=np.eye(2)
    )
    with pytest.raises(tk.ValidationError, match="control inputs"):
        tk.ParticleFilter(sys_u, particles=10, backend="numba").filter(np.zeros((5, 1)), u=np.zeros((5, 2)))


class _DeadBand(tk.Channel):
    """A sensor that reads 0 inside the band (-0.1, 0.1) and the latent reading itself outside: exact readings and
    intervals."""

    def censor(self, y_latent):
        return np.where(np.abs(y_latent) < 0.1, 0.0, y_latent)

    def region(self, y, k, l):
        inside = y == 0.0
        return np.where(inside, -0.1, y), np.where(inside, 0.1, y)


# The channels beyond censoring: random saturation (three modes, one of them of probability 0 on the second sensor),
# a quantizer (interval readings, open at the saturated ends), a dead band (exact readings and intervals) and Rice
# fading of order 2 (a window of states, a variance per particle); their bootstrap proposal, and the locally optimal
# one of the region channels. One compiled version serves them and the censored readings: the readings' model
# travels as arrays.
OTHER_CHANNELS = {
    "saturation": (
        2,
        lambda: tk.RandomSaturation([0.3, 0.0], [0.8, 0.9], level=[0.5, 0.4]),
        tk.Censoring(lower=[-0.3, -np.inf], upper=[np.inf, 0.35]),
    ),
    "quantizer": (2, lambda: tk.Quantizer(0.2, lower=-0.6, upper=0.6), None),
    "dead band": (2, lambda: _DeadBand(), None),
    "fading": (1, lambda: tk.RiceFading.gaussian(2, [0.9, 0.5, 0.3], [0.01, 0.02, 0.03]), tk.Censoring(lower=[0.0])),
}


def other_channel(kind, steps=12):
    m, make, cens = OTHER_CHANNELS[kind]
    ch = make()
    y = tk.simulate(system(m), steps, 6, channel=ch, censoring=cens, seed=0).y.copy()
    y[1, 3, 0] = np.nan  # one channel missing
    y[2, 5] = np.nan  # every channel missing
    return m, (ch if cens is None else [ch, cens]), y


@pytest.mark.parametrize(
    ("kind", "proposal"),
    [("saturation", "prior"), ("quantizer", "prior"), ("quantizer", "optimal"), ("dead band", "prior"),
     ("dead band", "optimal"), ("fading", "prior")],
)  # fmt: skip
def test_compiled_other_channels_equal_numpy_for_the_same_random_numbers(kind, proposal):
    m, channel, y = other_channel(kind)
    pf = tk.ParticleFilter(system(m), channel, particles=100, proposal=proposal, seed=3, resample_threshold=0.7)
    assert pf._compiled_gap(None) is None
    if kind == "quantizer":  # readings at the saturated ends of the range and between
        assert np.isclose(np.abs(y), 0.6).any() and (np.abs(y) < 0.5).any()
    if kind == "dead band":  # exact readings and intervals
        assert (y == 0.0).any() and (np.abs(y) > 0.1).any()
    check_against_numpy(pf, y)


@pytest.mark.parametrize(
    ("kind", "proposal"), [("quantizer", "prior"), ("quantizer", "optimal"), ("saturation", "prior")]
)
def test_general_readings_far_in_the_tails(kind, proposal):
    # readings 40-90 standard deviations from every particle, and quantizer cells so narrow (a hundredth of the
    # latent reading's deviation at 5 of them) that their masses cancel: those particles are weighted in
    # logarithms throughout, and must still equal the numpy path
    if kind == "quantizer":
        channel = tk.Quantizer(0.01, lower=-20.0, upper=20.0)
        y = np.array([[[15.0]] * 3, [[-20.0]] * 3, [[1.6], [1.7], [0.0]], [[-1.5], [20.0], [0.3]]])
    else:
        channel = tk.RandomSaturation([0.3], [0.8], level=0.5)
        y = np.array([[[30.0]] * 3, [[-25.0], [0.1], [12.0]], [[0.2], [0.4], [-0.1]]])
    pf = tk.ParticleFilter(system(1), channel, particles=150, proposal=proposal, seed=4, resample_threshold=0.7)
    got = check_against_numpy(pf, y, both_branches=False)
    assert np.isfinite(got.mean).all() and got.extras["log_likelihood"][0, 0] < -400  # (the far reading)


def test_fading_continued_from_a_state_inside_its_first_window_equals_one_call():
    # the fading reading sums the terms of the states present: from step 1 (a state continued at k = 1 < L = 2)
    _, channel, y = other_channel("fading", steps=8)
    pf = tk.ParticleFilter(system(1), channel, particles=80, proposal="prior", seed=2, backend="numba")
    whole = pf.filter(y)
    first = pf.filter(y[:, :1])
    rest = pf.filter(y[:, 1:], state=first.final)
    np.testing.assert_allclose(rest.mean, whole.mean[:, 1:], rtol=0, atol=TOL)
    np.testing.assert_allclose(rest.final.carry["log_likelihood"], whole.final.carry["log_likelihood"], atol=TOL)
    assert whole.mean.shape == (6, 8, 2) and whole.final.carry["particles"].shape == (6, 80, 6)


def test_log_ndtr_matches_scipy_in_both_tails():
    x = np.concatenate([np.linspace(-80.0, 12.0, 3001), [-1e4, -1e3, -35.4, -35.3, -20.0, 0.0, 6.0, 40.0]])
    ours = np.array([cp.log_ndtr(v) for v in x])
    np.testing.assert_allclose(ours, scipy_log_ndtr(x), rtol=1e-13, atol=0)
    assert cp.log_ndtr(np.inf) == 0.0 and cp.log_ndtr(-np.inf) == -np.inf


def test_ndtri_exp_inverts_log_ndtr():
    t = -np.concatenate([np.logspace(-300, 4, 3000), [np.log(2.0), 0.02, 3.7]])
    ours = np.array([cp.ndtri_exp(v) for v in t])
    np.testing.assert_allclose(ours, scipy_ndtri_exp(t), rtol=1e-12, atol=1e-12)
    back = np.array([cp.log_ndtr(z) for z in ours])
    # the round trip is conditioned by |z| (d log t / dz ~ z far in the upper tail): 40 ulp of z
    np.testing.assert_allclose(back, t, rtol=1e-12, atol=0)
    assert cp.ndtri_exp(-np.inf) == -np.inf and cp.ndtri_exp(0.0) == np.inf and np.isnan(cp.ndtri_exp(0.5))


@pytest.mark.parametrize("proposal", ["optimal", "prior"])
def test_weights_spread_beyond_1e100_return_to_logarithms(proposal):
    # never resampling, the weights of a run spread over hundreds of orders of magnitude: the compiled loop's
    # linear weights hand over to logarithms, which must equal the numpy path's
    cens = CENSORINGS["lower"](1)
    y = record(1, cens, runs=3, steps=40, seed=2)
    y[:, 10:] = np.where(np.arange(10, 40) % 2, 12.0, 0.0)[:, None]  # far readings and censored ones, in turn
    pf = tk.ParticleFilter(system(1), cens, particles=150, proposal=proposal, seed=6, resample_threshold=0.0)
    got = check_against_numpy(pf, y, both_branches=False)
    lw = got.final.carry["log_weights"]
    assert (lw.max(axis=1) - lw.min(axis=1) > np.log(1e100)).all()


@pytest.mark.parametrize("proposal", ["optimal", "prior"])
def test_censored_masses_under_1e200_go_to_the_log_part(proposal):
    # readings censored 20-30 standard deviations below the prediction (not beyond 35, where the mass is taken
    # in logarithms anyway): a mass under the linear weights' floor of 1e-200 (optimal proposal: the first, ~1e-208;
    # bootstrap: the product of ~1e-159 and ~1e-80), every weight small
    lim = -12.0 if proposal == "optimal" else -8.5
    cens = tk.Censoring(lower=[lim, lim])
    y = np.full((3, 4, 2), lim)
    y[0, 1] = [0.2, 0.1]
    pf = tk.ParticleFilter(system(2), cens, particles=200, proposal=proposal, seed=8, resample_threshold=0.7)
    got = check_against_numpy(pf, y, both_branches=False)
    assert (got.extras["log_likelihood"][:, 0] < np.log(1e-100)).all()  # every weight small: the exact rescaling


def test_tail_mass_matches_scipy():
    # the censored masses come from the package's compiled censored statistics, vectorised over particles;
    # the oracle is scipy's ndtr, to the accuracy the module states (1e-14 within 8 sd, 2e-13 out to 35)
    from scipy.special import ndtr

    from tobitkf.filters._compiled_particle import _tail_mass

    x = np.concatenate([np.linspace(-8.0, 8.0, 4001), [0.0, 1e-300, -2.0, 2.0, 4.0, -4.0]])
    ours = np.array([_tail_mass(v) for v in x])
    np.testing.assert_allclose(ours, ndtr(-np.abs(x)), rtol=5e-14, atol=0)
    far = np.linspace(8.0, 35.4, 2001)
    np.testing.assert_allclose([_tail_mass(v) for v in far], ndtr(-far), rtol=1e-12, atol=0)


def test_draws_on_the_bit_generator_are_the_generators_stream():
    # the compiled loop calls numba's implementations of Generator.random and .standard_normal on the bit
    # generator itself (not through the Generator's methods); interleaved as in the loop, they must give
    # numpy's own numbers and leave the generator where numpy's calls leave it
    from numba import njit

    @njit
    def draw(rng, k):
        bg = rng.bit_generator
        out = np.empty((k, 3))
        for i in range(k):
            out[i, 0] = cp._next_double(bg)
            out[i, 1] = cp._standard_normal(bg)
            out[i, 2] = cp._standard_normal(bg)
        return out

    k = 5000  # enough for the ziggurat's rare branches (its tail and wedges: about 1 % of the normals)
    a = np.random.default_rng(11)
    got = draw(a, k)
    b = np.random.default_rng(11)
    want = np.empty((k, 3))
    for i in range(k):
        want[i, 0] = b.random()
        want[i, 1:] = b.standard_normal(2)
    np.testing.assert_array_equal(got, want)
    assert a.bit_generator.state == b.bit_generator.state
