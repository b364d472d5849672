"""The compiled time loop of the protocol TKF (PBTKF-IMSF, Geng et al.) against its numpy reference path.

The numpy path is the reference (tests/filters/test_protocol.py checks it against the source); the
compiled loop must reproduce it to rounding (1e-12 relative) in every case it covers, and every other
case must run on numpy (``backend="auto"``) or be refused (``backend="numba"``).

Mutation checks (done by hand, not kept): the GP-03 misreading ``yhat = zeta + r * lam`` for
``zeta + sd * lam`` in the kernel failed all 72 cases of ``test_kernel_equals_numpy`` (R = 0.5 for
sensor 2), and ``F = lm * CPC`` for ``F = lv * CPC`` in mode 0 failed all 18 ``"variance"`` cases; both
restored. Switching the kernel's Joseph term off was *not* caught, as expected: for the optimal gain
the Joseph and standard forms agree to rounding (measured on the numpy path: 1e-16 in the covariances,
3e-15 in the means).
"""

import numpy as np
import pytest
from scipy.special import ndtr

import tobitkf as tk
from tobitkf._validation import ValidationError
from tobitkf.channels.protocol import LAMBDA_BASE, NO_FAILURE, ProtocolChannel
from tobitkf.filters import _backend
from tobitkf.filters.protocol import ProtocolTobitKalmanFilter
from tobitkf.filters.protocol_model import FAILURE_TERMS

pytest.importorskip("numba")
from tobitkf.filters import _compiled_block, _compiled_entries, _compiled_loop  # noqa: E402

from ._compare import assert_same

FIELDS = ("mean", "cov", "pred_mean", "pred_cov", "var")


def assert_results_equal(r1, r2, rtol=1e-12):
    for f in FIELDS:
        va, vb = getattr(r1, f), getattr(r2, f)
        assert (va is None) == (vb is None), f
        if va is not None:
            assert_same(va, vb, rtol)
    assert r1.extras.keys() == r2.extras.keys()
    for key in r1.extras:
        assert_same(r1.extras[key], r2.extras[key], rtol)
    np.testing.assert_array_equal(r1.times, r2.times)
    assert r1.final.k == r2.final.k
    assert_same(r1.final.x, r2.final.x, rtol)
    assert_same(np.broadcast_to(r1.final.P, r2.final.P.shape), r2.final.P, rtol)
    assert r1.final.carry.keys() == r2.final.carry.keys()
    for key in r1.final.carry:
        assert_same(r1.final.carry[key], r2.final.carry[key], rtol)


def oscillator(R=(1.0, 0.5)):
    """The source example's plant (Sec. IV: rotation by 0.052 pi, two sensors)."""
    w = 0.052 * np.pi
    A = [[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]]
    return tk.LinearSystem(
        A=A, C=[[1.0, 0.0], [0.3, 1.0]], Q=0.0025 * np.eye(2), R=np.diag(R), x0=[5.0, 0.0], P0=np.eye(2)
    )


def channel(window=2, threshold=0.0, failures=LAMBDA_BASE):
    return ProtocolChannel(2, window=window, failures=failures, threshold=threshold)


def data(sys_, ch, shape, steps, seed=0):
    runs = int(np.prod(shape, dtype=int))
    return tk.simulate(sys_, steps, runs, seed=seed, channel=ch).y.reshape(shape + (steps, 1))


def both(sys_, ch, y, **kw):
    filt = {k: kw.pop(k) for k in ("outputs", "state", "uncensored", "x0", "P0") if k in kw}
    a = ProtocolTobitKalmanFilter(sys_, ch, backend="numba", **kw).filter(y, **filt)
    b = ProtocolTobitKalmanFilter(sys_, ch, backend="numpy", **kw).filter(y, **filt)
    return a, b


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("shape", [(), (3,), (2, 2)])
@pytest.mark.parametrize("form", ["joseph", "standard"])
@pytest.mark.parametrize("mode", FAILURE_TERMS)
def test_kernel_equals_numpy(mode, form, shape, seed):
    sys_, ch = oscillator(), channel()
    y = data(sys_, ch, shape, 40, seed)
    a, b = both(sys_, ch, y, failure_term=mode, covariance_update=form)
    assert a.mean.shape == shape + (40, 2)
    assert a.extras["aug_mean"].shape == shape + (40, 6)
    assert_results_equal(a, b)


@pytest.mark.parametrize("window", [0, 1, 4])
@pytest.mark.parametrize("threshold", [-np.inf, -1.0, 3.0])
def test_kernel_windows_and_thresholds(window, threshold):
    """Other windows (n_xi = 2, 4, 10) and thresholds: none (the general route of the censored statistics),
    rarely and mostly censored (3 sigma above zero: the continued-fraction tail)."""
    sys_, ch = oscillator(), channel(window=window, threshold=threshold)
    y = data(sys_, ch, (5,), 30, seed=3)
    for mode in ("variance", "second_moment"):
        assert_results_equal(*both(sys_, ch, y, failure_term=mode, prehistory_prior="zero_mean"))


@pytest.mark.parametrize("threshold", [-60.0, 60.0])
def test_kernel_thresholds_40_sigma_out(threshold):
    """Thresholds about 40 to 60 predicted-reading sigmas from every reading (the predicted readings stay
    within a few units of zero, their sigma is 1 to 1.5): below, never censored (the lower tail of the
    statistics' one-sided route); above, every reading censored, the window deep in the upper tail. The
    compiled loop must still reproduce numpy to rounding (1e-12), and every output must be finite."""
    sys_, ch = oscillator(), channel(threshold=threshold)
    y = data(sys_, ch, (4,), 30, seed=5)
    for mode in ("variance", "second_moment"):
        a, b = both(sys_, ch, y, failure_term=mode)
        assert_results_equal(a, b)
        assert np.isfinite(a.mean).all() and np.isfinite(a.cov).all()


def test_kernel_given_uncensored_and_continued_state():
    """A detection device that disagrees with y > tau on some steps, a given prior and P0_aug, and a
    continuation from result.final (the schedule and the lmmse recursion X_k picked up at k0 + 1)."""
    sys_, ch = oscillator(), channel()
    y = data(sys_, ch, (4,), 30, seed=5)
    rng = np.random.default_rng(5)
    g = (y > 0.0) ^ (rng.random(y.shape) < 0.1)
    P0_aug = np.kron(np.eye(3), np.diag([2.0, 0.5])) + 0.1
    for mode in ("variance", "lmmse_unconditional"):
        kw = dict(failure_term=mode, P0_aug=P0_aug)
        a, b = both(sys_, ch, y, uncensored=g, x0=[4.0, 1.0], **kw)
        assert_results_equal(a, b)
        fk = ProtocolTobitKalmanFilter(sys_, ch, backend="numba", **kw)
        fn = ProtocolTobitKalmanFilter(sys_, ch, backend="numpy", **kw)
        for split in (1, 7):
            a1, b1 = fk.filter(y[:, :split], uncensored=g[:, :split]), fn.filter(y[:, :split], uncensored=g[:, :split])
            assert_results_equal(a1, b1)
            a2 = fk.filter(y[:, split:], uncensored=g[:, split:], state=a1.final)
            b2 = fn.filter(y[:, split:], uncensored=g[:, split:], state=b1.final)
            assert_results_equal(a2, b2)
            np.testing.assert_array_equal(a2.extras["scheduled"], b2.extras["scheduled"])


@pytest.mark.parametrize("form", ["joseph", "standard"])
@pytest.mark.parametrize("mode", FAILURE_TERMS)
def test_kernel_lost_readings_equal_numpy(mode, form):
    """Lost readings (NaN: a whole step of one run, a run of steps, the first step) run through the compiled
    loop (``backend="numba"`` accepts them; the loop's class MISSING) and equal the numpy path to 1e-12, with
    the detection device's gamma given too, True at some lost readings: a lost reading only predicts whatever
    gamma says (reported not uncensored, its innovation 0, its expected reading tau), on both paths."""
    sys_, ch = oscillator(), channel()
    y = data(sys_, ch, (4,), 30, seed=7)
    y[1, 3] = np.nan
    y[2, 10:14] = np.nan
    y[3, 0] = np.nan
    g = y > 0.0
    g[2, 11:13] = True  # "uncensored" at a lost reading
    for kw in ({}, {"uncensored": g}):
        a, b = both(sys_, ch, y, failure_term=mode, covariance_update=form, **kw)
        assert_results_equal(a, b)
        assert np.isfinite(a.mean).all()
        assert not a.extras["uncensored"][2, 10:14].any()
        np.testing.assert_array_equal(a.extras["innovation"][2, 10:14], 0.0)
        np.testing.assert_array_equal(a.extras["expected_y"][2, 10:14], ch.threshold)
    # the step after a lost reading is the prediction of the step before, updated once
    ref = ProtocolTobitKalmanFilter(sys_, ch, backend="numba", failure_term=mode, covariance_update=form)
    r = ref.filter(y, outputs=("mean", "pred_mean", "cov", "pred_cov"))
    assert_same(r.mean[2, 10], r.pred_mean[2, 10], 0.0)
    assert_same(r.cov[2, 10], r.pred_cov[2, 10], 0.0)


def test_numpy_path_takes_the_compiled_moments(monkeypatch):
    """The numpy path's moments of (13)-(16), (21), (23)-(24) are those of the compiled loop's function
    (protocol_tkf_block), called once per step, not a second copy of the equations."""
    from tobitkf.filters import _compiled_moments

    calls = []
    block = _compiled_moments.protocol_tkf_block

    def spy(*args):
        calls.append(args[0])
        return block(*args)

    monkeypatch.setattr(_compiled_moments, "protocol_tkf_block", spy)
    sys_, ch = oscillator(), channel()
    y = data(sys_, ch, (3,), 12)
    for form in ("joseph", "standard", "square_root"):
        calls.clear()
        ProtocolTobitKalmanFilter(sys_, ch, backend="numpy", covariance_update=form).filter(y)
        assert calls == [3] * 12


def three_sensor_case():
    """p = 3 sensors served in the order 3, 1, 3, 2 (sensor 3 twice per cycle), a failure law per sensor,
    window 1, threshold -0.5, on the example's oscillator."""
    from tobitkf.channels.protocol import PMF

    w = 0.052 * np.pi
    A = [[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]]
    C = [[1.0, 0.0], [0.3, 1.0], [-0.5, 0.7]]
    sys_ = tk.LinearSystem(A=A, C=C, Q=0.0025 * np.eye(2), R=np.diag([1.0, 0.5, 2.0]), x0=[5.0, 0.0], P0=np.eye(2))
    laws = [LAMBDA_BASE, NO_FAILURE, PMF([0.2, 1.0], [0.3, 0.7])]
    return sys_, ProtocolChannel(3, window=1, failures=laws, threshold=-0.5, order=[3, 1, 3, 2])


@pytest.mark.parametrize("mode", FAILURE_TERMS)
def test_kernel_three_sensors_custom_order_per_sensor_laws(mode):
    """p = 3 sensors served in the order 3, 1, 3, 2 (sensor 3 twice per cycle), a law per sensor (the
    per-sensor lam_mean, lam_var), continued from result.final at a step inside the cycle."""
    sys_, ch = three_sensor_case()
    y = tk.simulate(sys_, 27, 6, seed=9, channel=ch).y
    a, b = both(sys_, ch, y, failure_term=mode)
    assert_results_equal(a, b)
    fk = ProtocolTobitKalmanFilter(sys_, ch, backend="numba", failure_term=mode)
    fn = ProtocolTobitKalmanFilter(sys_, ch, backend="numpy", failure_term=mode)
    a2 = fk.filter(y[:, 5:], state=fk.filter(y[:, :5]).final)
    b2 = fn.filter(y[:, 5:], state=fn.filter(y[:, :5]).final)
    assert_results_equal(a2, b2)
    assert_same(a2.mean, b.mean[:, 5:])  # the continuation is the whole run's tail


def test_kernel_many_runs_cross_blocks():
    sys_, ch = oscillator(), channel()
    y = data(sys_, ch, (140,), 12, seed=6)  # 140 = 2 full blocks of 64 and one of 12 (AUG_BLOCK)
    assert_results_equal(*both(sys_, ch, y))


@pytest.mark.parametrize("threshold", [2.0, 8.0])
def test_kernel_tail_continued_fractions_of_a_block(threshold):
    """A threshold above the signal: the block's runs mix the direct formulas and the continued fraction
    beyond 4 sigma (2.0), or are all in the tail with their own numbers of terms (8.0); equal to numpy."""
    sys_, ch = oscillator(), channel(threshold=threshold)
    y = data(sys_, ch, (69,), 40)
    a, b = both(sys_, ch, y)
    assert_results_equal(a, b)
    assert (b.extras["p_uncensored"] < ndtr(-4.0)).any()


@pytest.mark.parametrize("outputs", ["all", ("var", "extras")])
def test_kernel_outputs_across_chunks_and_a_partial_block(outputs):
    """The staged outputs (laid out step-major, run innermost, transposed when a chunk is written): 69 runs
    (a full block of 64 and a partial one), more than two chunks of steps, continued from a state at k0 = 5."""

    sys_, ch = oscillator(), channel()
    T = 2 * _compiled_block.CHUNK + 7
    y = data(sys_, ch, (69,), T + 5)
    fast = ProtocolTobitKalmanFilter(sys_, ch, backend="numba")
    ref = ProtocolTobitKalmanFilter(sys_, ch, backend="numpy")
    a, b = fast.filter(y[:, :5], outputs=outputs), ref.filter(y[:, :5], outputs=outputs)
    assert_results_equal(a, b)
    a = fast.filter(y[:, 5:], outputs=outputs, state=a.final)
    b = ref.filter(y[:, 5:], outputs=outputs, state=b.final)
    assert_results_equal(a, b)


@pytest.mark.parametrize("outputs", ["last", ("mean",), ("cov",), ("var",), ("pred_mean", "extras"), "all"])
def test_kernel_honours_the_output_selection(outputs):
    sys_, ch = oscillator(), channel()
    y = data(sys_, ch, (3,), 15, seed=7)
    assert_results_equal(*both(sys_, ch, y, outputs=outputs))


def test_kernel_reduces_to_the_kalman_filter():
    """An independent oracle: one sensor, no window, no failures, no threshold is the Kalman filter."""
    w = 0.052 * np.pi
    A = [[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]]
    sys_ = tk.LinearSystem(A=A, C=[[1.0, 0.0]], Q=0.0025 * np.eye(2), R=[[1.0]], x0=[5.0, 0.0], P0=np.eye(2))
    ch = ProtocolChannel(1, window=0, failures=NO_FAILURE, threshold=-np.inf)
    y = tk.simulate(sys_, 25, 4, seed=8).y
    for form in ("joseph", "standard"):
        got = ProtocolTobitKalmanFilter(sys_, ch, backend="numba", covariance_update=form).filter(y)
        ref = tk.KalmanFilter(sys_, backend="numpy").filter(y)
        assert_same(got.mean, ref.mean, 1e-12)
        assert_same(got.cov, ref.cov, 1e-12)


def test_one_compiled_specialization_for_every_call():
    """One run (batch ()), read-only readings and detection flags, a continuation, the online step: all one
    signature of the protocol TKF's own version of the compiled loop (another would compile or load a second
    specialization on the first such call)."""
    sys_, ch = oscillator(), channel()
    y = data(sys_, ch, (4,), 10)
    ProtocolTobitKalmanFilter(sys_, ch, backend="numba").filter(y)
    before = len(_compiled_loop.compiled_loop.signatures)
    assert before >= 1  # the protocol TKF runs the family's version of the loop
    y.flags.writeable = False
    g = y > 0.0
    g.flags.writeable = False
    est = ProtocolTobitKalmanFilter(sys_, ch, backend="numba")
    r = est.filter(y, uncensored=g)
    est.filter(y[0], uncensored=g[0])
    est.filter(y, state=r.final)
    st = est.step(est.step(est.init(), y[0, 0], uncensored=g[0, 0]), y[0, 1])  # the online step's call too
    est.step(est.init((4,)), y[:, 0])
    assert st.k == 2 and len(_compiled_loop.compiled_loop.signatures) == before


def test_divergence_reruns_on_numpy():
    """A non-finite covariance from the kernel: the call reruns on numpy, which warns and NaNs the means."""
    sys_ = tk.LinearSystem(A=[[1e200]], C=[[1.0]], Q=[[1.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    ch = ProtocolChannel(1, window=1, threshold=-1.0)
    y = np.zeros((2, 4, 1))
    with pytest.warns(RuntimeWarning, match="stopped being finite"):
        out = ProtocolTobitKalmanFilter(sys_, ch, backend="numba").filter(y)
    with pytest.warns(RuntimeWarning, match="stopped being finite"):
        ref = ProtocolTobitKalmanFilter(sys_, ch, backend="numpy").filter(y)
    assert np.isnan(out.mean[:, -1]).all()
    assert_same(out.mean, ref.mean, 0.0)


# --- dispatch -----------------------------------------------------------------------------------


def _raise(*args):
    raise AssertionError("protocol kernel used")  # the compiled loop or its online-step entry


def test_auto_uses_the_kernel_when_covered(monkeypatch):
    sys_, ch = oscillator(), channel()
    y = data(sys_, ch, (2,), 5)
    monkeypatch.setattr(_compiled_loop, "compiled_loop", _raise)
    with pytest.raises(AssertionError, match="protocol kernel used"):
        ProtocolTobitKalmanFilter(sys_, ch).filter(y)
    with pytest.raises(AssertionError, match="protocol kernel used"):
        tk.protocol_tobit_kalman_filter(sys_, ch, y, failure_term="literal", covariance_update="standard")
    ProtocolTobitKalmanFilter(sys_, ch, backend="numpy").filter(y)  # numpy never touches it
    st = ProtocolTobitKalmanFilter(sys_, ch, backend="numpy").init((2,))
    ProtocolTobitKalmanFilter(sys_, ch, backend="numpy").step(st, y[:, 0])  # nor its online step
    monkeypatch.setattr(_compiled_entries, "protocol_tkf_step", _raise)  # the online step's entry into the loop
    with pytest.raises(AssertionError, match="protocol kernel used"):
        ProtocolTobitKalmanFilter(sys_, ch).step(st, y[:, 0])  # the online step runs it too (T = 1)


def _time_varying():
    sys_ = oscillator()
    return tk.LinearSystem(
        A=np.stack([sys_.transition(0)] * 20), C=sys_.measurement(1), Q=0.0025 * np.eye(2), R=np.diag([1.0, 0.5]),
        x0=[5.0, 0.0], P0=np.eye(2),
    )  # fmt: skip


CASES = {
    "keep_augmented": ({}, {"keep_augmented": True}, "keep_augmented=True"),
    "time_varying": ({}, {}, "time-varying"),
    "square_root": ({"covariance_update": "square_root"}, {}, "covariance_update='square_root'"),
}


@pytest.mark.parametrize("which", sorted(CASES))
def test_uncovered_cases_fall_back_to_numpy(which, monkeypatch):
    opts, call, match = CASES[which]
    sys_ = _time_varying() if which == "time_varying" else oscillator()
    ch = channel()
    y = data(oscillator(), ch, (3,), 20)
    ref = ProtocolTobitKalmanFilter(sys_, ch, backend="numpy", **opts).filter(y, **call)
    with pytest.raises(
        ValidationError, match=f"compiled path of the protocol Tobit Kalman filter does not cover {match}"
    ):
        ProtocolTobitKalmanFilter(sys_, ch, backend="numba", **opts).filter(y, **call)
    monkeypatch.setattr(_compiled_loop, "compiled_loop", _raise)
    auto = ProtocolTobitKalmanFilter(sys_, ch, **opts).filter(y, **call)
    # not the protocol kernel (it raises) but the compiled shared step around the numpy moments: to rounding
    assert_results_equal(auto, ref, 1e-12)


def test_without_numba(monkeypatch):
    monkeypatch.setattr(_backend, "_load", lambda: None)
    sys_, ch = oscillator(), channel()
    y = data(sys_, ch, (2,), 10)
    with pytest.raises(ImportError, match="needs the numba package"):
        ProtocolTobitKalmanFilter(sys_, ch, backend="numba")
    auto = ProtocolTobitKalmanFilter(sys_, ch).filter(y)
    assert_results_equal(auto, ProtocolTobitKalmanFilter(sys_, ch, backend="numpy").filter(y), 1e-12)


def test_bad_sensor_variance_is_reported_as_on_numpy():
    sys_ = oscillator(R=(1.0, 0.0))
    ch = channel()
    y = data(oscillator(), ch, (2,), 6)
    for backend in ("numba", "numpy"):
        with pytest.raises(ValidationError, match=r"R\(2\): sensor 2 needs a positive noise variance"):
            ProtocolTobitKalmanFilter(sys_, ch, backend=backend).filter(y)


def _steps(est, y, shape, gamma=None, resume_at=None):
    import pickle

    st, states = est.init(shape), []
    for k in range(y.shape[-2]):
        kw = {} if gamma is None else {"uncensored": gamma[..., k, :]}
        st = est.step(st, y[..., k, :], **kw)
        if k == resume_at:
            st = pickle.loads(pickle.dumps(st))
        states.append(st)
    return states


@pytest.mark.parametrize("shape", [(), (3,)])
@pytest.mark.parametrize("mode", FAILURE_TERMS)
def test_online_kernel_step_equals_the_numpy_step(mode, shape):
    """The compiled online step (T = 1 through the loop, the sensors' terms kept as first scheduled): p = 3
    sensors in the order 3, 1, 3, 2 with a law each, a detection device disagreeing with y > tau on some
    steps, a lost reading (that step runs numpy), a pickled state resumed: every state's x, P, extras and
    carry equal the numpy step's, and the stream the numpy filter's rows; lmmse_unconditional (its carried
    X_k) runs numpy."""
    sys_, ch = three_sensor_case()
    runs = int(np.prod(shape, dtype=int))
    T = 19
    y = tk.simulate(sys_, T, runs, seed=9, channel=ch).y.reshape(shape + (T, 1))
    gamma = y > -0.5
    gamma[..., 4, :] = ~gamma[..., 4, :]
    gamma[..., 11, :] = True
    y[..., 7, :] = np.nan
    fast = _steps(ProtocolTobitKalmanFilter(sys_, ch, backend="auto", failure_term=mode), y, shape, gamma, 9)
    ref = _steps(ProtocolTobitKalmanFilter(sys_, ch, backend="numpy", failure_term=mode), y, shape, gamma, 9)
    for a, b in zip(fast, ref):
        assert a.k == b.k and a.batch_shape == b.batch_shape
        assert_same(a.x, b.x)
        assert_same(np.broadcast_to(a.P, b.P.shape), b.P)
        assert a.extras.keys() == b.extras.keys() and a.carry.keys() == b.carry.keys()
        for key in b.extras:
            assert_same(a.extras[key], b.extras[key])
        for key in b.carry:
            assert_same(a.carry[key], b.carry[key])
    res = ProtocolTobitKalmanFilter(sys_, ch, backend="numpy", failure_term=mode).filter(y, uncensored=gamma)
    assert_same(np.stack([s.mean for s in fast], axis=-2), res.mean)


@pytest.mark.parametrize("mode", ["variance", "second_moment"])
def test_plain_online_step_equals_the_general_step(mode, monkeypatch):
    """A plain step call (no keyword, float64 readings in [tau, inf)) goes straight to the compiled step: a
    (2, 3) batch from the shared prior covariance, three sensors in the order 3, 1, 3, 2, readings set to
    tau (censored) on some steps, a lost reading (that step takes the general route), a pickled state
    resumed. Its states equal those of the general step (the same detections given as ``uncensored``) to
    1e-12 and the numpy step's to 1e-12; the general route ran only at the first step (which decides on the
    kernel), at the lost reading and at the resumed (unpickled) state, which it checks in full once; a reading
    below tau or a wrong shape is refused as by the general step."""
    sys_, ch = three_sensor_case()
    shape, T = (2, 3), 17
    y = tk.simulate(sys_, T, 6, seed=4, channel=ch).y.reshape(shape + (T, 1))
    y[0, :, 3] = ch.threshold
    y[..., 6, :] = ch.threshold
    y[1, 2, 10] = np.nan
    general = ProtocolTobitKalmanFilter._compiled_online_step
    calls = []

    def spy(self, *args):
        calls.append(1)
        return general(self, *args)

    monkeypatch.setattr(ProtocolTobitKalmanFilter, "_compiled_online_step", spy)
    plain = _steps(ProtocolTobitKalmanFilter(sys_, ch, failure_term=mode), y, shape, resume_at=8)
    assert len(calls) == 3
    given = _steps(ProtocolTobitKalmanFilter(sys_, ch, failure_term=mode), y, shape, y > ch.threshold, 8)
    ref = _steps(ProtocolTobitKalmanFilter(sys_, ch, backend="numpy", failure_term=mode), y, shape, resume_at=8)
    for a, b, c in zip(plain, given, ref):
        assert a.k == b.k == c.k and a.batch_shape == c.batch_shape
        assert a.extras.keys() == c.extras.keys() and a.carry.keys() == c.carry.keys()
        for other in (b, c):
            assert_same(a.x, other.x, 1e-12)
            assert_same(np.broadcast_to(a.P, other.P.shape), np.broadcast_to(other.P, a.P.shape), 1e-12)
            for key in c.extras:
                assert_same(a.extras[key], other.extras[key], 1e-12)
    res = ProtocolTobitKalmanFilter(sys_, ch, failure_term=mode).filter(y)
    assert_same(np.stack([s.mean for s in plain], axis=-2), res.mean, 1e-12)
    est = ProtocolTobitKalmanFilter(sys_, ch, failure_term=mode)
    st = est.step(est.init(shape), y[..., 0, :])
    below = y[..., 1, :].copy()
    below[0, 1] = ch.threshold - 1.0
    with pytest.raises(ValidationError, match="below the threshold"):
        est.step(st, below)
    with pytest.raises(tk.ShapeError, match="batch_shape"):
        est.step(st, y[0, :2, 1, :])


def test_online_kernel_step_reports_a_bad_sensor_variance_and_diverges_as_numpy():
    sys_ = oscillator(R=(1.0, 0.0))
    ch = channel()
    y = data(oscillator(), ch, (2,), 6)
    for backend in ("auto", "numpy"):
        est = ProtocolTobitKalmanFilter(sys_, ch, backend=backend)
        st = est.step(est.init((2,)), y[:, 0])  # sensor 1: fine
        with pytest.raises(ValidationError, match=r"R\(2\): sensor 2 needs a positive noise variance"):
            est.step(st, y[:, 1])
    sys_ = tk.LinearSystem(A=[[1e200]], C=[[1.0]], Q=[[1.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    ch = ProtocolChannel(1, window=1, threshold=-1.0)
    states = []
    for backend in ("auto", "numpy"):
        est = ProtocolTobitKalmanFilter(sys_, ch, backend=backend)
        st = est.init()
        with pytest.warns(RuntimeWarning, match="stopped being finite"):
            for _ in range(4):
                st = est.step(st, [0.0])
        states.append(st)
    assert np.isnan(states[0].mean).all()
    assert_same(states[0].x, states[1].x, 0.0)
