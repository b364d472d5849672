"""The compiled loop of the assumed-density filters against their numpy path, and its moments against
:mod:`tobitkf.censored` (the high-precision reference) and ``scipy.special.log_ndtr``.

Every family and option the compiled loop covers is run with ``backend="numba"`` (which refuses a case it
does not cover, so the compiled path is known to have run) and ``backend="numpy"`` on the same readings;
every output and extra agrees to 1e-12 (scaled by the output's size). Cases: one- and two-sided limits,
several regions, limits per step, missing readings, readings 40 standard deviations into either tail, the
recorded indicator, output selections, batch shapes, control inputs, continuing from a state, the online
step loop against the compiled filter; saturation, Rice fading and the protocol channel's failure laws; the
generic assumed-density filter of a quantized sensor (its channel names its compiled block).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import log_ndtr

import tobitkf as tk
from tobitkf.censored import censored_moments
from tobitkf.channels.base import Channel, log_interval_mass
from tobitkf.channels.laws import PMF, Uniform
from tobitkf.channels.protocol import LAMBDA_BASE

pytest.importorskip("numba")

from tobitkf.filters import _compiled_moments as cm  # noqa: E402
from tobitkf.filters._compiled_tobit import GL_W, GL_X  # noqa: E402

TOL = 1e-12
KEYS = ("mean", "cov", "var", "pred_mean", "pred_cov")


def assert_same(a, b, tol=TOL):
    """Every output and extra of two FilterResults equal to ``tol`` times the output's scale."""
    for key in KEYS:
        va, vb = getattr(a, key), getattr(b, key)
        assert (va is None) == (vb is None), key
        if va is not None:
            assert va.shape == vb.shape, (key, va.shape, vb.shape)
            np.testing.assert_allclose(vb, va, rtol=0, atol=tol * max(1.0, np.abs(va).max()), err_msg=key)
    assert set(a.extras) == set(b.extras)
    for key, va in a.extras.items():
        va, vb = np.asarray(va, float), np.asarray(b.extras[key], float)
        assert va.shape == vb.shape, (key, va.shape, vb.shape)
        fin = np.isfinite(va)
        np.testing.assert_array_equal(np.isfinite(vb), fin, err_msg=key)
        scale = max(1.0, np.abs(va[fin]).max(initial=0.0))
        np.testing.assert_allclose(vb[fin], va[fin], rtol=0, atol=tol * scale, err_msg=key)
        np.testing.assert_array_equal(vb[~fin], va[~fin], err_msg=key)
    np.testing.assert_array_equal(a.times, b.times)
    if a.final is not None:
        np.testing.assert_allclose(b.final.x, a.final.x, rtol=0, atol=tol * max(1.0, np.abs(a.final.x).max()))
        Pa = np.broadcast_to(a.final.P, b.final.P.shape)
        np.testing.assert_allclose(b.final.P, Pa, rtol=0, atol=tol * max(1.0, np.abs(Pa).max()))


def both(make, y, **kw):
    return make("numpy").filter(y, **kw), make("numba").filter(y, **kw)


def oscillator(m=1, **kw):
    w = 0.1
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    C = [[1.0, 0.0], [0.3, 1.0], [0.5, -0.4]][:m]
    base = dict(A=A, C=C, Q=1e-2 * np.eye(2), R=np.diag([0.1, 0.2, 0.15][:m]), x0=[0.0, 0.0], P0=0.5 * np.eye(2))
    base.update(kw)
    return tk.LinearSystem(**base)


# --------------------------------------------------------------------------- the moments


def test_beyond_a_limit_matches_the_reference_far_into_both_tails():
    """Truncated mean and variance of y* beyond a limit (either side) as tobitkf.censored_moments, and the
    log-probability as scipy's log_ndtr, standardized limits from -40 to 40."""
    for a in np.concatenate([np.linspace(-40, 40, 161), [-4.0, -2.0, 2.0, 4.0, 1e-3, -1e-3]]):
        mu, sd = 0.7, 1.3
        lim = mu + a * sd
        for sign in (1.0, -1.0):
            p_other, logp, m, v = cm.beyond(mu, sd, lim, sign)
            ref = censored_moments(mu, sd, lim, np.inf) if sign > 0 else censored_moments(mu, sd, -np.inf, lim)
            assert m == pytest.approx(float(ref.truncated_mean), rel=1e-12, abs=1e-12 * sd), (a, sign)
            assert v == pytest.approx(float(ref.truncated_var), rel=1e-11, abs=1e-300), (a, sign)
            want = log_ndtr(-a) if sign > 0 else log_ndtr(a)
            assert logp == pytest.approx(float(want), rel=1e-12, abs=1e-14), (a, sign)
            other = np.exp(log_ndtr(a)) if sign > 0 else np.exp(log_ndtr(-a))
            assert p_other == pytest.approx(float(other), rel=1e-12, abs=1e-300), (a, sign)


@pytest.mark.parametrize(
    "ea, eb",
    [(-0.5, 0.5), (1.0, 1.3), (38.0, 38.5), (-40.5, -40.0), (-3.0, 6.0), (-np.inf, -40.0), (40.0, np.inf)],
)
def test_interval_event_matches_the_reference(ea, eb):
    """The interval piece a quantizer reuses: truncated moments on [ea, eb] (narrow, wide, in a tail) as
    tobitkf.censored_moments; its log-probability as the log_ndtr differences of the numpy path
    (log_interval_mass: the reference's probability is subnormal beyond ~37 sigma, its logarithm then off by
    1e-12 relative; quadrature of the shifted density agrees with log_interval_mass at (38, 38.5))."""
    mu, sd = 0.0, 1.0
    logp, m, v = cm.interval_event(mu, sd, ea, eb, GL_X, GL_W, np.empty((2, 64)))
    ref = censored_moments(mu, sd, ea, eb)
    assert m == pytest.approx(float(ref.truncated_mean), rel=1e-12, abs=1e-13)
    assert v == pytest.approx(float(ref.truncated_var), rel=1e-10, abs=1e-300)
    assert logp == pytest.approx(float(log_interval_mass(ea, eb)), rel=1e-12, abs=1e-13)


def test_censored_block_is_the_adf_update_of_one_channel():
    """alpha, beta of the block function give the numpy channel update of assumed_density (one step)."""
    from tobitkf.filters.assumed_density import censored_channel_update

    rng = np.random.default_rng(0)
    N, n = 40, 3
    x = rng.normal(size=(N, n))
    L = rng.normal(size=(N, n, n))
    P = L @ np.swapaxes(L, 1, 2) + 0.1 * np.eye(n)
    c = np.array([1.0, -0.5, 0.3])
    r = 0.2
    mu = x @ c
    s = np.sqrt(np.einsum("rij,i,j->r", P, c, c) + r)
    lo, hi = -0.3, 1.5
    y = np.clip(mu + s * rng.normal(size=N) * 3, lo, hi)
    y[::7] = np.nan
    y[3], y[4] = lo, hi  # at the limits, and far into the tails below
    mu[3], mu[4] = lo + 40 * s[3], hi - 40 * s[4]
    x[3] += (mu[3] - x[3] @ c) * c / (c @ c)
    x[4] += (mu[4] - x[4] @ c) * c / (c @ c)
    mu = x @ c
    xn, Pn, _, pu, ll = censored_channel_update(x, P, None, y, c, r, lo, hi)
    cls = tk.filters._readings.classify_readings(y, lo, hi)
    hph = np.einsum("rij,i,j->r", P, c, c)
    alpha, beta, llc, puc, _ = cm.family_array(
        cm.kind(cm.CENSORED),
        y,
        cls,
        mu,
        hph,
        np.full(N, r),
        np.full(N, lo),
        np.full(N, hi),
        np.zeros(0),
        0,
    )
    Pc = P @ c
    np.testing.assert_allclose(x + alpha[:, None] * Pc, xn, rtol=0, atol=1e-12 * np.abs(xn).max())
    Pm = P - beta[:, None, None] * Pc[:, :, None] * Pc[:, None, :]
    np.testing.assert_allclose(Pm, Pn, rtol=0, atol=1e-12 * np.abs(Pn).max())
    np.testing.assert_allclose(llc, ll, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(puc, pu, rtol=0, atol=1e-14)


# --------------------------------------------------------------------------- censoring


CENSORINGS = {
    "lower": lambda m: tk.Censoring(lower=np.full(m, -0.1)),
    "upper": lambda m: tk.Censoring(upper=np.full(m, 0.2)),
    "two-sided": lambda m: tk.Censoring(lower=np.full(m, -0.25), upper=np.full(m, 0.3)),
    "none": lambda m: tk.Censoring(),
}


@pytest.mark.parametrize("kind", list(CENSORINGS))
@pytest.mark.parametrize("m", [1, 3])
@pytest.mark.parametrize("order", ["channels", "uncensored_first"])
def test_censoring_adf_compiled_equals_numpy(kind, m, order):
    sys_ = oscillator(m)
    cens = CENSORINGS[kind](m)
    y = tk.simulate(sys_, 25, 30, censoring=cens, seed=m).y.copy()
    y[::4, 3, 0] = np.nan  # missing readings
    y[2, 5:9] = np.nan
    assert_same(*both(lambda be: tk.AssumedDensityTobitFilter(sys_, cens, order=order, backend=be), y))


def test_censoring_adf_multi_region_and_limits_per_step():
    sys_, cens = tk.multi_region(oscillator(1), [[(-np.inf, 0.0), (0.0, np.inf), (-0.2, 0.25)]])
    y = tk.simulate(sys_, 20, 12, censoring=cens, seed=4).y
    assert_same(*both(lambda be: tk.AssumedDensityTobitFilter(sys_, cens, backend=be), y))
    T = 20
    lo = np.where(np.arange(T)[:, None] % 3 == 0, -np.inf, -0.1 + 0.01 * np.arange(T)[:, None]) * np.ones((1, 2))
    hi = np.where(np.arange(T)[:, None] % 4 == 1, 0.15, np.inf) * np.ones((1, 2))
    sys2 = oscillator(2)
    cens2 = tk.Censoring(lower=lo, upper=hi)
    y2 = tk.simulate(sys2, T, 9, censoring=cens2, seed=5).y
    assert_same(*both(lambda be: tk.AssumedDensityTobitFilter(sys2, cens2, backend=be), y2))


def test_censoring_adf_readings_forty_sigma_into_the_tails():
    """Readings at a limit 40 predicted standard deviations on the wrong side of the latent mean (and at
    a limit 40 sigma on its side), and interior readings with the limits 40 sigma away."""
    sys_ = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.0]], R=[[0.5]], x0=[0.0], P0=[[0.5]])
    s = 1.0  # the latent's predicted sd at the first step: sqrt(0.5 + 0.5)
    for lo, hi, reading in (
        (-40 * s, np.inf, -40 * s),
        (40 * s, np.inf, 40 * s),
        (-np.inf, 40 * s, 40 * s),
        (-np.inf, -40 * s, -40 * s),
        (-40 * s, 40 * s, 0.3),
        (-40 * s, 40 * s, 40 * s),
    ):
        cens = tk.Censoring(lower=lo, upper=hi)
        y = np.array([[[reading]], [[0.1 if np.isfinite(reading) else 0.0]]])
        y[1] = np.clip(y[1], lo, hi)
        a, b = both(lambda be: tk.AssumedDensityTobitFilter(sys_, cens, backend=be), y)
        assert np.isfinite(a.mean).all() and np.isfinite(a.extras["log_likelihood"]).all()
        assert_same(a, b)


def test_censoring_adf_indicator_outputs_batches_inputs_and_states():
    sys_ = oscillator(2, Bu=[[0.1], [0.0]], D=[[0.2], [-0.1]])
    cens = tk.Censoring(lower=[-0.1, -np.inf], upper=[np.inf, 0.2])
    T = 16
    u = np.sin(np.arange(T))[:, None]
    d = tk.simulate(sys_, T, 12, censoring=cens, inputs=u, seed=6)
    y = d.y.reshape(3, 4, T, 2)
    flags = (d.y != d.y_latent).reshape(3, 4, T, 2)
    assert flags.any()

    def make(be):
        return tk.AssumedDensityTobitFilter(sys_, cens, backend=be)

    for outputs in ("all", "last", ("mean",), ("var",), ("cov", "extras"), ("pred_mean", "pred_cov")):
        assert_same(*both(make, y, u=u, outputs=outputs))
    first = tk.AssumedDensityTobitFilter(sys_, cens, order="uncensored_first", backend="numpy").filter(
        y, u=u, censored=flags
    )
    assert_same(
        first, tk.AssumedDensityTobitFilter(sys_, cens, order="uncensored_first").filter(y, u=u, censored=flags)
    )
    flip = flags.copy()
    flip[0, 0, :] = False  # readings at a limit recorded as exact
    assert_same(*both(make, y, u=u, censored=flags))
    assert_same(*both(make, y, u=u, censored=flip))
    assert_same(*both(make, y[0, 0], u=u))  # a single run (T, m)
    # continuing from a state: the second half from the first half's final state
    a1, b1 = both(make, y[..., :7, :], u=u[:7])
    a2 = make("numpy").filter(y[..., 7:, :], u=u[7:], state=a1.final)
    b2 = make("numba").filter(y[..., 7:, :], u=u[7:], state=b1.final)
    assert_same(a2, b2)
    full = make("numba").filter(y, u=u)
    np.testing.assert_allclose(b2.mean, full.mean[..., 7:, :], rtol=0, atol=1e-12)


def test_step_loop_equals_the_compiled_filter():
    sys_ = oscillator(2)
    cens = tk.Censoring(lower=[-0.1, -0.2], upper=[np.inf, 0.3])
    y = tk.simulate(sys_, 12, 5, censoring=cens, seed=7).y
    out = tk.AssumedDensityTobitFilter(sys_, cens, backend="numba").filter(y)
    est = tk.AssumedDensityTobitFilter(sys_, cens)
    st = est.init((5,))
    for t in range(12):
        st = est.step(st, y[:, t])
        np.testing.assert_allclose(st.mean, out.mean[:, t], rtol=0, atol=1e-12)
        np.testing.assert_allclose(st.cov, out.cov[:, t], rtol=0, atol=1e-12)


def test_backend_choice_and_uncovered_options():
    sys_ = oscillator(1)
    cens = tk.Censoring(lower=-0.1)
    y = tk.simulate(sys_, 10, 4, censoring=cens, seed=8).y
    with pytest.raises(tk.ValidationError, match="backend"):
        tk.AssumedDensityTobitFilter(sys_, cens, backend="fast")
    for kw in ({"covariance_update": "joseph"}, {"covariance_update": "square_root"}):
        with pytest.raises(tk.ValidationError, match="backend"):
            tk.AssumedDensityTobitFilter(sys_, cens, backend="numba", **kw).filter(y)
        auto = tk.AssumedDensityTobitFilter(sys_, cens, **kw).filter(y)  # falls back to the numpy loop
        ref = tk.AssumedDensityTobitFilter(sys_, cens, backend="numpy", **kw).filter(y)
        assert_same(ref, auto)


# --------------------------------------------------------------------------- saturation, fading, protocol


@pytest.mark.parametrize("m", [1, 2])
def test_saturation_adf_compiled_equals_numpy(m):
    sys_ = oscillator(m, R=np.diag([0.05, 0.1][:m]))
    ch = tk.RandomSaturation([0.3, 0.5][:m], [0.7, 0.8][:m], level=[0.4, 0.2][:m])
    y = tk.simulate(sys_, 25, 30, channel=ch, seed=9).y.copy()
    y[::5, 2] = np.nan
    for outputs in ("all", ("mean", "extras")):
        assert_same(*both(lambda be: tk.SaturationAssumedDensityFilter(sys_, ch, backend=be), y, outputs=outputs))


def test_saturation_adf_forty_sigma_beyond_the_level():
    """A prior 40 standard deviations beyond the saturation level (either side): the pieces of the
    saturated mode far into their tails."""
    sys_ = tk.LinearSystem(A=np.eye(1), C=[[1.0]], Q=[[1e-4]], R=[[0.01]], x0=[0.0], P0=[[1e-2]])
    ch = tk.RandomSaturation([0.5], [0.9], level=[0.2])
    for x0, reading in ((4.2, 0.2), (-3.8, -0.2), (4.2, 4.2), (0.0, 0.2)):
        y = np.array([[[reading], [reading]], [[np.nan], [reading]]])

        def make(be, x0=x0):
            return tk.SaturationAssumedDensityFilter(sys_, ch, backend=be)

        a, b = make("numpy").filter(y, x0=[x0]), make("numba").filter(y, x0=[x0])
        assert np.isfinite(a.mean).all()
        assert_same(a, b)


@pytest.mark.parametrize("censored", [False, True])
def test_fading_adf_compiled_equals_numpy(censored):
    sys_ = oscillator(2, Bu=[[0.1], [0.05]], D=[[0.1], [0.0]])
    fad = tk.RiceFading(2, Uniform([0.5, 0.2, 0.1], [1.0, 0.6, 0.3]))
    cens = tk.Censoring(lower=[-0.1, -np.inf], upper=[np.inf, 0.4]) if censored else None
    rng = np.random.default_rng(10)
    T = 20
    y = 0.3 * rng.normal(size=(2, 3, T, 2))
    if cens is not None:
        y = np.clip(y, [-0.1, -np.inf], [np.inf, 0.4])
    y[0, 1, 4] = np.nan
    u = np.cos(np.arange(T))[:, None]

    def make(be):
        return tk.FadingAssumedDensityFilter(sys_, fad, cens, backend=be)

    assert_same(*both(make, y, u=u))
    assert_same(*both(make, y, outputs=("mean", "var", "extras")))
    a1 = make("numpy").filter(y[..., :1, :])  # a state within the first L steps
    assert_same(
        make("numpy").filter(y[..., 1:, :], state=a1.final), make("numba").filter(y[..., 1:, :], state=a1.final)
    )


@pytest.mark.parametrize(
    "law, window, threshold, mode",
    [
        (LAMBDA_BASE, 2, 0.0, "prior"),
        (PMF([0.0, 1.0], [0.2, 0.8]), 1, 0.0, "hold"),
        (Uniform(0.3, 1.0), 0, -np.inf, "zero"),
        (PMF([0.0, 0.5, 1.0], [0.05, 0.10, 0.85]), 2, 4.0, "prior"),
        (PMF([0.0, 0.5, 1.0], [0.05, 0.10, 0.85]), 1, 45.0, "prior"),  # every reading at tau, ~40 sigma away
    ],
)
def test_protocol_adf_compiled_equals_numpy(law, window, threshold, mode):
    w = 0.052 * np.pi
    sys_ = tk.LinearSystem(
        A=[[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]],
        C=np.eye(2),
        Q=0.0025 * np.eye(2),
        R=np.diag([1.0, 0.5]),
        x0=[5.0, 0.0],
        P0=np.eye(2),
    )
    ch = tk.ProtocolChannel(2, window=window, failures=law, threshold=threshold, prehistory=mode)
    y = tk.simulate(sys_, 25, 20, channel=ch, seed=11).y.copy()
    y[3, 4:6] = np.nan
    for outputs in ("all", ("mean", "extras")):
        assert_same(
            *both(lambda be: tk.ProtocolAssumedDensityFilter(sys_, ch, nodes=5, backend=be), y, outputs=outputs)
        )


# --------------------------------------------------------------------------- the quantizer (generic filter)

QUANTIZERS = {
    "both ends": lambda: tk.Quantizer([0.4, 0.7], offset=[0.0, 0.1], lower=[-0.8, -1.3], upper=[0.8, 1.5]),
    "one end each": lambda: tk.Quantizer([0.5, 0.3], lower=[-0.5, -np.inf], upper=[np.inf, 0.6]),
    "no ends": lambda: tk.Quantizer(0.25),
    "two levels": lambda: tk.Quantizer(1.0, offset=0.5, lower=-0.5, upper=0.5),  # a binary sensor
}


def quantized_adf(sys_, q):
    return lambda be: tk.AssumedDensityFilter(sys_, q, backend=be)


@pytest.mark.parametrize("kind", list(QUANTIZERS))
def test_quantizer_adf_compiled_equals_numpy(kind):
    """Missing readings, readings at the saturated ends, output selections and batch shapes."""
    sys_ = oscillator(2)
    q = QUANTIZERS[kind]()
    y = tk.simulate(sys_, 25, 12, channel=q, seed=3).y.copy()
    y[::4, 3, 0] = np.nan
    y[2, 5:9] = np.nan
    if kind != "no ends":
        assert q.at_limit(y).any()  # saturated readings are in the record
    make = quantized_adf(sys_, q)
    assert isinstance(make("numba"), tk.AssumedDensityFilter)
    for outputs in ("all", "last", ("mean",), ("var", "extras"), ("pred_mean", "pred_cov")):
        assert_same(*both(make, y, outputs=outputs))
    assert_same(*both(make, y.reshape(3, 4, 25, 2)))
    assert_same(*both(make, y[0]))  # a single run (T, m)


def test_quantizer_adf_forty_sigma_into_the_tails():
    """The reading's cell 40 predicted standard deviations below and above the latent mean: a saturated end
    (one-sided), an inner cell (two-sided, narrow against the distance), and the cell that holds the mean."""
    sys_ = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.0]], R=[[0.5]], x0=[0.0], P0=[[0.5]])  # s = 1
    q = tk.Quantizer(1.0, lower=-45.0, upper=45.0)
    for x0 in (40.0, -40.0, 45.0, -45.0, 0.3):
        y = np.array([[[0.0], [0.0]], [[-45.0], [1.0]], [[45.0], [-1.0]], [[np.nan], [0.0]]])
        make = quantized_adf(sys_, q)
        a, b = make("numpy").filter(y, x0=[x0]), make("numba").filter(y, x0=[x0])
        assert np.isfinite(a.mean).all() and np.isfinite(a.extras["log_likelihood"]).all()
        assert_same(a, b)


def test_quantizer_adf_inputs_states_and_degenerate_latents():
    sys_ = oscillator(2, Bu=[[0.1], [0.0]], D=[[0.2], [-0.1]])
    q = tk.Quantizer(0.3, lower=-0.6, upper=0.6)
    T = 16
    u = np.sin(np.arange(T))[:, None]
    y = tk.simulate(sys_, T, 8, channel=q, inputs=u, seed=6).y
    make = quantized_adf(sys_, q)
    assert_same(*both(make, y, u=u))
    a1, b1 = both(make, y[:, :7], u=u[:7])
    assert_same(
        make("numpy").filter(y[:, 7:], u=u[7:], state=a1.final), make("numba").filter(y[:, 7:], u=u[7:], state=b1.final)
    )
    # no noise and a known state: the latent is degenerate; no update, the term 0 in the reading's cell, else -inf
    exact = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.0]], R=[[0.0]], x0=[0.1], P0=[[0.0]])
    yd = np.array([[[0.0]], [[1.0]]])
    a, b = both(quantized_adf(exact, tk.Quantizer(0.5)), yd)
    np.testing.assert_array_equal(a.extras["log_likelihood"][:, 0], [0.0, -np.inf])
    assert_same(a, b)


class _DeadBand(Channel):
    """A channel of the contract without compiled moments (section None: not registered)."""

    def region(self, y, k, l):
        return np.where(y == 0.0, -0.2, y), np.where(y == 0.0, 0.2, y)


def test_generic_adf_backend_choice():
    sys_ = oscillator(1)
    q = tk.Quantizer(0.3)
    y = tk.simulate(sys_, 10, 4, channel=q, seed=8).y
    with pytest.raises(tk.ValidationError, match="backend"):
        tk.AssumedDensityFilter(sys_, q, backend="fast")
    with pytest.raises(tk.ValidationError, match="backend"):
        tk.AssumedDensityFilter(sys_, q, backend="numba", covariance_update="joseph").filter(y)
    ref = tk.AssumedDensityFilter(sys_, q, backend="numpy", covariance_update="joseph").filter(y)
    assert_same(ref, tk.AssumedDensityFilter(sys_, q, covariance_update="joseph").filter(y))  # auto: numpy loop
    # a channel that names no compiled moments runs the numpy loop, and backend="numba" refuses it
    yd = np.where(np.abs(y) < 0.2, 0.0, y)
    with pytest.raises(tk.ValidationError, match="backend"):
        tk.AssumedDensityFilter(sys_, _DeadBand(), backend="numba").filter(yd)
    assert_same(
        tk.AssumedDensityFilter(sys_, _DeadBand(), backend="numpy").filter(yd),
        tk.AssumedDensityFilter(sys_, _DeadBand()).filter(yd),
    )

    class Misnamed(tk.Quantizer):
        compiled_moments = "no_such_block"

    with pytest.raises(tk.ValidationError, match="compiled_moments"):
        tk.AssumedDensityFilter(sys_, Misnamed(0.3), backend="numba").filter(y)


def test_a_compiled_block_that_is_no_block_function_is_refused():
    """``compiled_block`` must be a numba.njit function of the block's parameters (or "module:name" of one)."""
    from numba import njit

    sys_ = oscillator(1)
    yd = np.zeros((2, 4, 1))

    def plain(nb, y, cls, hx, hph, rb, lo, hi, par, alpha, beta, ll, pu, comp, glx, glw, buf):
        pass

    cases = {
        "a numba.njit function": plain,
        "of the 17 parameters": njit(lambda nb, y: None),
        "'module:name'": "tobitkf.channels.no_such_module:block",
    }
    for message, block in cases.items():
        own = type("Own", (_DeadBand,), {"compiled_block": block})
        for be in ("numba", "auto"):
            with pytest.raises(tk.ValidationError, match=f"compiled_block: expected .*{message}"):
                tk.AssumedDensityFilter(sys_, own(), backend=be).filter(yd)


@pytest.mark.parametrize("form", ["joseph", "square_root"])
def test_quantizer_numpy_loop_with_compiled_moments_equals_numpy_moments(form):
    """Where the numpy loop runs (here the Joseph and square-root forms) the quantizer's moments come from the
    compiled block unless backend="numpy": the same numbers as the numpy moments, cells 40 sigma away included."""
    sys_ = oscillator(2)
    q = QUANTIZERS["both ends"]()
    y = tk.simulate(sys_, 20, 6, channel=q, seed=12).y.copy()
    y[1, 2:5] = np.nan
    for x0 in ([0.0, 0.0], [30.0, -20.0]):
        a = tk.AssumedDensityFilter(sys_, q, covariance_update=form, backend="numpy").filter(y, x0=x0)
        b = tk.AssumedDensityFilter(sys_, q, covariance_update=form).filter(y, x0=x0)
        assert np.isfinite(a.extras["log_likelihood"]).all()
        assert_same(a, b)


def test_quantizer_step_loop_equals_the_compiled_filter():
    sys_ = oscillator(2)
    q = QUANTIZERS["one end each"]()
    y = tk.simulate(sys_, 12, 5, channel=q, seed=7).y
    out = tk.AssumedDensityFilter(sys_, q, backend="numba").filter(y)
    est = tk.AssumedDensityFilter(sys_, q)
    st = est.init((5,))
    for t in range(12):
        st = est.step(st, y[:, t])
        np.testing.assert_allclose(st.mean, out.mean[:, t], rtol=0, atol=1e-12)
        np.testing.assert_allclose(st.cov, out.cov[:, t], rtol=0, atol=1e-12)


@pytest.mark.parametrize("form", ["joseph", "square_root"])
def test_censoring_numpy_loop_with_compiled_moments_equals_numpy_moments(form):
    """The censored ADF's numpy loop takes its moments from the compiled block unless backend="numpy": the same
    numbers as the numpy moments (tobitkf.censored), with readings 40 sigma into the tails, per-step limits,
    the recorded indicator and a degenerate latent."""
    sys_ = oscillator(2)
    cens = tk.Censoring(lower=[-0.1, -0.25], upper=[np.inf, 0.3])
    y = tk.simulate(sys_, 20, 6, censoring=cens, seed=13).y.copy()
    y[1, 2:5] = np.nan
    for order in ("channels", "uncensored_first"):
        for x0 in ([0.0, 0.0], [30.0, -20.0]):

            def make(be):
                return tk.AssumedDensityTobitFilter(sys_, cens, covariance_update=form, order=order, backend=be)

            a, b = make("numpy").filter(y, x0=x0), make("auto").filter(y, x0=x0)
            assert np.isfinite(a.extras["log_likelihood"]).all()
            assert_same(a, b)
    flags = (y == np.array([-0.1, -0.25])) | (y == np.array([np.inf, 0.3]))
    flags[0, :, 0] = False
    a = tk.AssumedDensityTobitFilter(sys_, cens, covariance_update=form, backend="numpy").filter(y, censored=flags)
    assert_same(a, tk.AssumedDensityTobitFilter(sys_, cens, covariance_update=form).filter(y, censored=flags))
    st_a = tk.AssumedDensityTobitFilter(sys_, cens, backend="numpy").step(
        tk.AssumedDensityTobitFilter(sys_, cens).init((6,)), y[:, 0], lower=[-0.05, -0.2], upper=[0.2, 0.3]
    )
    est = tk.AssumedDensityTobitFilter(sys_, cens)
    st_b = est.step(est.init((6,)), y[:, 0], lower=[-0.05, -0.2], upper=[0.2, 0.3])
    np.testing.assert_allclose(st_b.mean, st_a.mean, rtol=0, atol=1e-12)
    np.testing.assert_allclose(st_b.cov, st_a.cov, rtol=0, atol=1e-12)
    exact = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.0]], R=[[0.0]], x0=[0.1], P0=[[0.0]])
    c1 = tk.Censoring(lower=0.0)
    yd = np.array([[[0.0]], [[0.1]], [[0.3]]])
    a, b = (
        tk.AssumedDensityTobitFilter(exact, c1, covariance_update=form, backend=be).filter(yd)
        for be in ("numpy", "auto")
    )
    np.testing.assert_array_equal(a.extras["log_likelihood"][:, 0], [-np.inf, 0.0, -np.inf])
    assert_same(a, b)
