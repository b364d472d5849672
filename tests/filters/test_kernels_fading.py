"""The fading TKF (Geng et al. 2017) through the one compiled loop against its numpy reference path.

The numpy path is the reference (tests/filters/test_fading.py checks it against the source); the
compiled loop (update code FADING) must reproduce it to rounding (1e-12) in every case it covers, and every
other case must run on numpy (``backend="auto"``) or be refused (``backend="numba"``).
"""

import numpy as np
import pytest
from scipy.special import ndtr

import tobitkf as tk
from tobitkf._validation import ValidationError
from tobitkf.channels.fading import RiceFading
from tobitkf.filters import _backend
from tobitkf.filters.fading import FadingTobitKalmanFilter, fading_tobit_kalman_filter

pytest.importorskip("numba")
from tobitkf.filters import _compiled_block, _compiled_entries, _compiled_fading, _compiled_loop  # noqa: E402

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
    assert r1.final.k == r2.final.k
    assert_same(r1.final.x, r2.final.x, rtol)
    assert_same(np.broadcast_to(r1.final.P, r2.final.P.shape), r2.final.P, rtol)


def oscillator(m=1):
    w = 0.052 * np.pi
    A = [[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]]
    C = [[1.0, 0.0]] if m == 1 else [[1.0, 0.0], [0.4, 1.0]]
    return tk.LinearSystem(A=A, C=C, Q=0.0025 * np.eye(2), R=np.diag([1.0, 0.5][:m]), x0=[5.0, 0.0], P0=np.eye(2))


def fading(L):
    return RiceFading.gaussian(L, [0.95, 0.75, 0.85][: L + 1], [0.0081, 0.0064, 0.0049][: L + 1])


def data(sys_, fad, cens, runs, steps, seed=0, missing=0.1):
    y = tk.simulate(sys_, steps=steps, runs=runs, censoring=cens, measurement=fad, seed=seed).y
    if missing:
        rng = np.random.default_rng(seed + 1)
        y = np.where(rng.random(y.shape) < missing, np.nan, y)
    return y


def both(sys_, fad, cens, y, **kw):
    filt = {k: kw.pop(k) for k in ("outputs", "keep_smoothed", "state", "x0", "P0") if k in kw}
    a = FadingTobitKalmanFilter(sys_, fad, cens, backend="numba", **kw).filter(y, **filt)
    b = FadingTobitKalmanFilter(sys_, fad, cens, backend="numpy", **kw).filter(y, **filt)
    return a, b


@pytest.mark.parametrize("exact", [False, True])
@pytest.mark.parametrize("form", ["joseph", "standard"])
@pytest.mark.parametrize("sides", ["lower", "two_sided", "upper"])
@pytest.mark.parametrize("m", [1, 2])
def test_kernel_equals_numpy(exact, form, sides, m):
    sys_ = oscillator(m)
    # limits the signal (amplitude ~5) crosses; with [0, 3] for two channels nearly every reading is censored
    # and the numpy path itself turns a 1e-15 change of x0 into 5e-9 in the means (ill-conditioned, measured)
    lim = {
        "lower": {"lower": [0.0] * m},
        "upper": {"upper": [2.5] * m},
        "two_sided": {"lower": [-2.0] * m, "upper": [2.5] * m},
    }
    cens = tk.Censoring(**lim[sides])
    fad = fading(2)
    y = data(sys_, fad, cens, runs=40, steps=30)
    a, b = both(sys_, fad, cens, y, exact_tobit_variance=exact, covariance_update=form)
    # two-sided: a window's truncated variance cancels, and the paths compute Phi differently (scipy's ndtr;
    # the compiled erfcx fits, agreeing to ~1e-14): up to ~2e-12 after the steps (measured 1.9e-12)
    assert_results_equal(a, b, rtol=5e-12 if sides == "two_sided" else 1e-12)


@pytest.mark.parametrize("L", [0, 1, 2])
@pytest.mark.parametrize("shape", [(), (5,), (2, 3)])
def test_kernel_batch_shapes_and_orders(L, shape):
    sys_ = oscillator()
    cens = tk.Censoring(lower=0.0)
    fad = fading(L)
    runs = int(np.prod(shape, dtype=int))
    y = data(sys_, fad, cens, runs=runs, steps=12).reshape(shape + (12, 1))
    a, b = both(sys_, fad, cens, y)
    assert a.mean.shape == shape + (12, 2)
    assert a.extras["smoothed_mean"].shape == shape + (12, L + 1, 2)
    assert_results_equal(a, b)


@pytest.mark.parametrize("dist", [8.0, 40.0])
@pytest.mark.parametrize("where", ["below", "above"])
def test_kernel_limits_far_in_the_tails(dist, where):
    """Limits +-dist sigma from every prediction: the continued-fraction and quadrature routes of the
    shared censored statistics, and channels that are almost surely censored or uncensored."""
    sys_ = oscillator()
    fad = fading(2)
    lo = -dist if where == "below" else 5.0 + dist
    cens = tk.Censoring(lower=lo, upper=lo + 0.5 if where == "above" else np.inf)
    y = np.clip(
        data(sys_, fad, tk.Censoring(), runs=6, steps=20, missing=0.0), lo, lo + 0.5 if where == "above" else None
    )
    a, b = both(sys_, fad, cens, y, check_limits=False, exact_tobit_variance=True)
    assert_results_equal(a, b)


def test_kernel_time_varying_limits_continued_state_and_per_run_prior():
    """(T, m) limits, a per-run prior and a continuation from result.final across k <= L (the H_k of
    the first L steps) and beyond."""
    sys_ = oscillator(2)
    fad = fading(2)
    T = 16
    rng = np.random.default_rng(4)
    cens = tk.Censoring(lower=rng.uniform(-1.0, 0.5, (T, 2)), upper=rng.uniform(3.0, 5.0, (T, 2)))
    y = data(sys_, fad, cens, runs=7, steps=T)
    x0 = rng.normal(0.0, 1.0, (7, 2)) + [5.0, 0.0]
    P0 = np.broadcast_to(np.eye(2), (7, 2, 2)) * rng.uniform(0.5, 2.0, (7, 1, 1))
    for split in (1, 2, 5):
        fk = FadingTobitKalmanFilter(sys_, fad, cens, backend="numba")
        fn = FadingTobitKalmanFilter(sys_, fad, cens, backend="numpy")
        a1, b1 = fk.filter(y[:, :split], x0=x0, P0=P0), fn.filter(y[:, :split], x0=x0, P0=P0)
        assert_results_equal(a1, b1)
        a2, b2 = fk.filter(y[:, split:], state=a1.final), fn.filter(y[:, split:], state=b1.final)
        assert_results_equal(a2, b2)
        whole = fn.filter(y, x0=x0, P0=P0)
        assert_same(a2.mean, whole.mean[:, split:])


def loop_block(nxi):
    """Runs per block of the compiled loop at state size ``nxi``."""
    return _compiled_block.runs_per_block(nxi)


def test_kernel_many_runs_cross_blocks():
    sys_ = oscillator()
    cens = tk.Censoring(lower=0.0)
    fad = fading(2)
    B = loop_block(6)
    y = data(sys_, fad, cens, runs=2 * B + 12, steps=10)  # two full blocks and a partial one
    assert_results_equal(*both(sys_, fad, cens, y))


@pytest.mark.parametrize("lower", [2.0, 10.0])
def test_kernel_tail_continued_fractions_of_a_block(lower):
    """A lower limit above the signal (amplitude ~5): at 2 the runs of a block mix the direct formulas and
    the continued fraction beyond 4 sigma, at 10 every run is in the tail with its own number of terms (the
    block computes them together); equal to the numpy path, readings and covariances alike."""
    sys_ = oscillator()
    cens = tk.Censoring(lower=lower)
    fad = fading(2)
    y = data(sys_, fad, cens, runs=loop_block(6) + 5, steps=40)
    a, b = both(sys_, fad, cens, y)
    assert_results_equal(a, b)
    assert (b.extras["p_uncensored"] < ndtr(-4.0)).any()


@pytest.mark.parametrize("outputs", ["all", ("var", "pred_mean")])
def test_kernel_outputs_across_chunks_and_a_partial_block(outputs):
    """The staged outputs (laid out step-major, run innermost, transposed when a chunk is written): a full block
    of runs and a partial one, more than two chunks of steps, and a continuation whose record starts inside the
    first L steps (smoothed blocks s > k NaN) and a second one whose chunks start at k0 = 70."""

    sys_ = oscillator(2)
    cens = tk.Censoring(lower=[0.0, -0.5])
    fad = fading(2)
    T = 2 * _compiled_block.CHUNK + 7
    y = data(sys_, fad, cens, runs=loop_block(6) + 5, steps=T + 71)
    fast = FadingTobitKalmanFilter(sys_, fad, cens, backend="numba")
    ref = FadingTobitKalmanFilter(sys_, fad, cens, backend="numpy")
    a, b = fast.filter(y[:, :1], outputs=outputs), ref.filter(y[:, :1], outputs=outputs)
    assert_results_equal(a, b)
    for lo, hi in ((1, 71), (71, T + 71)):
        a = fast.filter(y[:, lo:hi], outputs=outputs, state=a.final)
        b = ref.filter(y[:, lo:hi], outputs=outputs, state=b.final)
        assert_results_equal(a, b)
    if outputs == "all":
        assert np.isfinite(a.extras["smoothed_cov"]).all()


@pytest.mark.parametrize("form", ["joseph", "standard"])
def test_kernel_block_gain_solve_three_channels(form):
    """m = 3: the block gain solve (elimination over the runs of a block, without pivoting on the
    unit-diagonal R_ee) with a partly missing channel (its gain column zeroed on those steps) and a
    channel whose readings are all missing, over two blocks of runs; equal to numpy to rounding."""
    w = 0.052 * np.pi
    A = [[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]]
    C = [[1.0, 0.0], [0.4, 1.0], [-0.3, 0.8]]
    sys_ = tk.LinearSystem(A=A, C=C, Q=0.0025 * np.eye(2), R=np.diag([1.0, 0.5, 0.3]), x0=[5.0, 0.0], P0=np.eye(2))
    cens = tk.Censoring(lower=[0.0, -1.0, -np.inf], upper=[np.inf, 3.0, 2.0])
    fad = fading(1)
    y = data(sys_, fad, cens, runs=loop_block(4) + 8, steps=25)  # a full block and a partial one
    y[:, ::4, 1] = np.nan
    y[5, :, 2] = np.nan
    a, b = both(sys_, fad, cens, y, covariance_update=form)
    assert_results_equal(a, b)


OUTPUTS = ["last", ("mean",), ("cov",), ("var",), ("pred_mean", "extras"), ("var", "extras"), ("extras",), "all"]


@pytest.mark.parametrize("outputs", OUTPUTS)
@pytest.mark.parametrize("keep_smoothed", [True, False])
def test_kernel_honours_the_output_selection(outputs, keep_smoothed):
    """Every selection, with the smoothed blocks (the loop then writes every block of the mean and the diagonal
    blocks of the covariance, of which the mean and the covariance are the first) and without."""
    sys_ = oscillator(2)
    cens = tk.Censoring(lower=[0.0, -0.5])
    fad = fading(2)
    y = data(sys_, fad, cens, runs=9, steps=15)
    a, b = both(sys_, fad, cens, y, outputs=outputs, keep_smoothed=keep_smoothed)
    assert_results_equal(a, b)


# --- dispatch -----------------------------------------------------------------------------------


def _raise(*args):
    raise AssertionError("fading kernel used")


def _no_loop(monkeypatch):
    """Make the compiled loop (``filter``) and the fading TKF's one-step entry (``step``) raise when called."""
    monkeypatch.setattr(_compiled_loop, "compiled_loop", _raise)
    monkeypatch.setattr(_compiled_entries, "fading_step", _raise)


def test_auto_uses_the_kernel_when_covered(monkeypatch):
    sys_ = oscillator()
    cens = tk.Censoring(lower=0.0)
    fad = fading(2)
    y = data(sys_, fad, cens, runs=2, steps=5)
    _no_loop(monkeypatch)
    with pytest.raises(AssertionError, match="fading kernel used"):
        FadingTobitKalmanFilter(sys_, fad, cens).filter(y)
    with pytest.raises(AssertionError, match="fading kernel used"):
        fading_tobit_kalman_filter(sys_, fad, cens, y, exact_tobit_variance=True, covariance_update="standard")
    FadingTobitKalmanFilter(sys_, fad, cens, backend="numpy").filter(y)  # numpy never touches it


def _time_varying():
    sys_ = oscillator()
    return tk.LinearSystem(
        A=np.stack([sys_.transition(0)] * 20),
        C=[[1.0, 0.0]],
        Q=0.0025 * np.eye(2),
        R=[[1.0]],
        x0=[5.0, 0.0],
        P0=np.eye(2),
    )


def _with_input(m=1, varying=False, feedthrough=False):
    sys_ = oscillator(m)
    Bu = np.array([[0.1], [0.0]])
    return tk.LinearSystem(
        A=sys_.transition(0),
        C=sys_.measurement(1),
        Q=0.0025 * np.eye(2),
        R=sys_.measurement_cov(1),
        x0=[5.0, 0.0],
        P0=np.eye(2),
        Bu=np.stack([Bu] * 20) if varying else Bu,
        D=0.3 * np.ones((m, 1)) if feedthrough else None,
    )


CASES = {
    "eq6_stale": ({"p_uncensored_mode": "eq6_stale"}, {}, "p_uncensored_mode='eq6_stale'"),
    "fading_variance": ({"fading_variance_term": True}, {}, "fading_variance_term=True"),
    "keep_augmented": ({}, {"keep_augmented": True}, "keep_augmented=True"),
    "time_varying": ({}, {}, "time-varying"),
    "input": ({}, {"u": np.ones((20, 1))}, "time-varying input matrices"),
}


@pytest.mark.parametrize("which", sorted(CASES))
def test_uncovered_cases_fall_back_to_numpy(which, monkeypatch):
    opts, call, match = CASES[which]
    sys_ = {"time_varying": _time_varying(), "input": _with_input(varying=True)}.get(which, oscillator())
    cens = tk.Censoring(lower=0.0)
    fad = fading(2)
    y = data(oscillator(), fad, cens, runs=2, steps=20)
    ref = FadingTobitKalmanFilter(sys_, fad, cens, backend="numpy", **opts).filter(y, **call)
    with pytest.raises(
        ValidationError, match=f"compiled path of the fading Tobit Kalman filter does not cover {match}"
    ):
        FadingTobitKalmanFilter(sys_, fad, cens, backend="numba", **opts).filter(y, **call)
    _no_loop(monkeypatch)
    auto = FadingTobitKalmanFilter(sys_, fad, cens, **opts).filter(y, **call)
    # not the compiled loop (it raises), but the compiled shared step around the numpy moments: equal to rounding
    assert_results_equal(auto, ref, 1e-12)


def test_square_root_form_falls_back_or_is_refused(monkeypatch):
    sys_ = oscillator()
    cens = tk.Censoring(lower=0.0)
    fad = fading(1)
    y = data(sys_, fad, cens, runs=2, steps=10)
    with pytest.raises(ValidationError, match="no square-root form"):
        FadingTobitKalmanFilter(sys_, fad, cens, covariance_update="square_root", backend="numba")
    ref = FadingTobitKalmanFilter(sys_, fad, cens, covariance_update="square_root", backend="numpy").filter(y)
    _no_loop(monkeypatch)
    auto = FadingTobitKalmanFilter(sys_, fad, cens, covariance_update="square_root").filter(y)
    assert_same(auto.mean, ref.mean, 0.0)


def test_without_numba(monkeypatch):
    monkeypatch.setattr(_backend, "_load", lambda: None)
    sys_ = oscillator()
    cens = tk.Censoring(lower=0.0)
    fad = fading(2)
    y = data(sys_, fad, cens, runs=2, steps=10)
    with pytest.raises(ImportError, match="needs the numba package"):
        FadingTobitKalmanFilter(sys_, fad, cens, backend="numba").filter(y)
    auto = FadingTobitKalmanFilter(sys_, fad, cens).filter(y)
    assert_results_equal(auto, FadingTobitKalmanFilter(sys_, fad, cens, backend="numpy").filter(y), 0.0)


def test_backend_option_is_checked():
    with pytest.raises(ValidationError, match="backend: expected one of 'auto', 'numpy', 'numba', got 'cuda'"):
        FadingTobitKalmanFilter(oscillator(), fading(1), tk.Censoring(lower=0.0), backend="cuda")


def test_divergence_reruns_on_numpy():
    """A non-finite covariance from the kernel: the call reruns on numpy, which warns (as the TKF kernel)."""
    sys_ = tk.LinearSystem(A=[[1e200]], C=[[1.0]], Q=[[1.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    fad = RiceFading(0, [1.0])
    y = np.zeros((2, 4, 1))
    with pytest.warns(RuntimeWarning):
        out = FadingTobitKalmanFilter(sys_, fad, tk.Censoring(lower=-1.0)).filter(y)
    ref = FadingTobitKalmanFilter(sys_, fad, tk.Censoring(lower=-1.0), backend="numpy")
    with pytest.warns(RuntimeWarning):
        assert_same(out.mean, ref.filter(y).mean, 0.0)


def _stream(est, y, shape, resume_at=None):
    """Step through y (shape + (T, m)) one reading at a time; optionally pickle the state at
    ``resume_at`` and go on from the copy."""
    import pickle

    st, states = est.init(batch_shape=shape), []
    for k in range(y.shape[-2]):
        st = est.step(st, y[..., k, :])
        if k == resume_at:
            st = pickle.loads(pickle.dumps(st))
        states.append(st)
    return states


@pytest.mark.parametrize("shape", [(), (3,), (2, 2)])
@pytest.mark.parametrize("exact", [False, True])
def test_online_step_runs_the_kernel_and_equals_numpy(shape, exact, monkeypatch):
    sys_ = oscillator()
    cens = tk.Censoring(lower=4.0, upper=6.0)
    fad = fading(2)
    runs = int(np.prod(shape, dtype=int))
    y = data(sys_, fad, cens, runs=runs, steps=25, missing=0.15).reshape(shape + (25, 1))
    fast = _stream(FadingTobitKalmanFilter(sys_, fad, cens, backend="numba", exact_tobit_variance=exact), y, shape, 9)
    ref = _stream(FadingTobitKalmanFilter(sys_, fad, cens, backend="numpy", exact_tobit_variance=exact), y, shape, 9)
    for a, b in zip(fast, ref):
        assert a.k == b.k and a.batch_shape == b.batch_shape
        assert_same(a.x, b.x)
        assert_same(np.broadcast_to(a.P, b.P.shape), b.P)
        assert a.extras.keys() == b.extras.keys()
        for key in b.extras:
            assert_same(a.extras[key], b.extras[key])
    # the stream equals the batched filter's rows, and the step really runs the kernel
    res = FadingTobitKalmanFilter(sys_, fad, cens, backend="numpy", exact_tobit_variance=exact).filter(y)
    assert_same(np.stack([s.mean for s in fast], axis=-2), res.mean)
    _no_loop(monkeypatch)
    est = FadingTobitKalmanFilter(sys_, fad, cens, backend="numba", exact_tobit_variance=exact)
    with pytest.raises(AssertionError, match="fading kernel used"):
        est.step(est.init(batch_shape=shape), y[..., 0, :])


@pytest.mark.parametrize("feedthrough", [False, True])
@pytest.mark.parametrize("m", [1, 2])
def test_inputs_run_the_loop_and_equal_numpy(m, feedthrough, monkeypatch):
    """Control inputs (B^u u into the top block of the prediction, D u into the latent readings) through the
    compiled loop: the batch filter across the first L steps and a continuation, and the online step, equal to
    the numpy path to rounding; and the loop really runs them."""
    sys_, fad = _with_input(m, feedthrough=feedthrough), fading(2)
    cens = tk.Censoring(lower=[0.0, -1.0][:m], upper=[np.inf, 2.5][:m])
    T = 14
    rng = np.random.default_rng(7)
    u = rng.normal(0.0, 1.0, (5, T, 1))
    y = np.clip(data(oscillator(m), fad, tk.Censoring(), runs=5, steps=T), [0.0, -1.0][:m], [np.inf, 2.5][:m])
    fast = FadingTobitKalmanFilter(sys_, fad, cens, backend="numba")
    ref = FadingTobitKalmanFilter(sys_, fad, cens, backend="numpy")
    a, b = fast.filter(y[:, :2], u=u[:, :2]), ref.filter(y[:, :2], u=u[:, :2])
    assert_results_equal(a, b)
    assert_results_equal(
        fast.filter(y[:, 2:], u=u[:, 2:], state=a.final), ref.filter(y[:, 2:], u=u[:, 2:], state=b.final)
    )
    sa, sb = fast.init(batch_shape=(5,)), ref.init(batch_shape=(5,))
    for k in range(T):
        sa, sb = fast.step(sa, y[:, k], u=u[:, k]), ref.step(sb, y[:, k], u=u[:, k])
        assert_same(sa.x, sb.x)
        assert_same(np.broadcast_to(sa.P, sb.P.shape), sb.P)
        assert sa.extras.keys() == sb.extras.keys()
        for key in sb.extras:
            assert_same(sa.extras[key], sb.extras[key])
    _no_loop(monkeypatch)
    with pytest.raises(AssertionError, match="fading kernel used"):
        fast.filter(y, u=u)
    with pytest.raises(AssertionError, match="fading kernel used"):
        fast.step(fast.init(batch_shape=(5,)), y[:, 0], u=u[:, 0])


@pytest.mark.parametrize("L", [1, 2])
def test_scalar_state_smoothed_blocks(L):
    """n = 1: the loop's diagonal blocks of the augmented covariance are its diagonal (the 1 x 1 blocks), staged
    by the variances' route; smoothed estimates and every output equal to numpy, filter and step."""
    sys_ = tk.LinearSystem(A=[[0.95]], C=[[1.0]], Q=[[0.1]], R=[[0.5]], x0=[1.0], P0=[[2.0]])
    fad = fading(L)
    cens = tk.Censoring(lower=0.2)
    y = data(sys_, fad, cens, runs=11, steps=9)
    for outputs in ("all", ("var", "extras")):
        a, b = both(sys_, fad, cens, y, outputs=outputs)
        assert_results_equal(a, b)
    assert a.extras["smoothed_cov"].shape == (11, 9, L + 1, 1, 1)
    fast, ref = (FadingTobitKalmanFilter(sys_, fad, cens, backend=be) for be in ("numba", "numpy"))
    sa, sb = fast.init(batch_shape=(11,)), ref.init(batch_shape=(11,))
    for k in range(4):
        sa, sb = fast.step(sa, y[:, k]), ref.step(sb, y[:, k])
        for key in sb.extras:
            assert_same(sa.extras[key], sb.extras[key])


def test_shared_and_per_run_prior_covariance():
    """A prior covariance shared by the runs (one (n_xi, n_xi) matrix, read by every run of a block) and the
    same prior given per run: the same numbers, equal to numpy."""
    sys_, fad, cens = oscillator(), fading(2), tk.Censoring(lower=0.0)
    y = data(sys_, fad, cens, runs=loop_block(6) + 3, steps=8)
    P0 = np.tile(np.eye(2), (y.shape[0], 1, 1))
    shared, per_run = both(sys_, fad, cens, y), both(sys_, fad, cens, y, P0=P0)
    assert shared[0].final.P.shape == per_run[0].final.P.shape == (y.shape[0], 6, 6)
    assert_results_equal(*shared)
    assert_results_equal(*per_run)
    assert_results_equal(shared[0], per_run[0], 0.0)


@pytest.mark.parametrize("keep_smoothed", [True, False])
@pytest.mark.parametrize("shape", [(), (3,)])
def test_online_kernel_step_with_time_varying_limits_and_options(keep_smoothed, shape):
    """The compiled step (its own lean call of the loop) with limits that change every step (converted per
    step, not cached) and keep_smoothed on or off equals the numpy step, extras included, and the rows of
    the batched numpy filter; two channels."""
    sys_, fad = oscillator(m=2), fading(2)
    T = 12
    lower = np.linspace(3.5, 4.5, T)[:, None] * np.ones((1, 2))
    cens = tk.Censoring(lower=lower, upper=lower + 2.0)
    runs = int(np.prod(shape, dtype=int))
    y = data(sys_, fad, cens, runs=runs, steps=T, missing=0.15).reshape(shape + (T, 2))
    fast = FadingTobitKalmanFilter(sys_, fad, cens, backend="numba")
    ref = FadingTobitKalmanFilter(sys_, fad, cens, backend="numpy")
    a, b = fast.init(batch_shape=shape), ref.init(batch_shape=shape)
    means = []
    for k in range(T):
        a = fast.step(a, y[..., k, :], keep_smoothed=keep_smoothed)
        b = ref.step(b, y[..., k, :], keep_smoothed=keep_smoothed)
        assert_same(a.x, b.x)
        assert_same(np.broadcast_to(a.P, b.P.shape), b.P)
        assert a.extras.keys() == b.extras.keys() and ("smoothed_mean" in a.extras) == keep_smoothed
        for key in b.extras:
            assert_same(a.extras[key], b.extras[key])
        means.append(a.mean)
    assert_same(np.stack(means, axis=-2), ref.filter(y).mean)
    assert fast._compiled_static and "_loop_limits" not in vars(fast)  # the loop ran, the limits not cached
    with pytest.raises(tk.ShapeError, match="time-varying limits"):
        fast.step(a, y[..., 0, :])  # step T + 1: beyond the limits, the same error as the numpy step
    with pytest.raises(tk.ShapeError, match="time-varying limits"):
        ref.step(b, y[..., 0, :])


def test_online_kernel_step_divergence_reruns_on_numpy():
    """A step whose covariance overflows in the kernel returns the numpy step's state, which warns."""
    sys_ = tk.LinearSystem(A=[[1e200]], C=[[1.0]], Q=[[1.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    fad = RiceFading(0, [1.0])
    fast = FadingTobitKalmanFilter(sys_, fad, tk.Censoring(lower=-1.0), backend="numba")
    ref = FadingTobitKalmanFilter(sys_, fad, tk.Censoring(lower=-1.0), backend="numpy")
    a, b = fast.init(), ref.init()
    with pytest.warns(RuntimeWarning):
        for _ in range(3):
            a, b = fast.step(a, [0.0]), ref.step(b, [0.0])
    np.testing.assert_array_equal(a.x, b.x)
    assert np.isnan(a.x).any()


def test_augmented_block_dims():
    """The fading and protocol loops' blocks: AUG_BLOCK runs (one run alone: one column), CHUNK staged steps at most;
    the tests of these loops that cross blocks use more runs than AUG_BLOCK."""

    B = _compiled_fading.AUG_BLOCK
    assert _compiled_fading.aug_block_dims(1000, 100) == (B, _compiled_block.CHUNK)
    assert _compiled_fading.aug_block_dims(1, 1) == (1, 1)
    assert _compiled_fading.aug_block_dims(B - 5, 7) == (B - 5, 7)
    assert B < 69 < 2 * B < 140
