"""What enters an estimator: states (their origin, shapes, covariance, time index, predicted flag), readings
(masked, beyond float64's square range, outside the limits in ``step`` as in ``filter``), allocations that
scale with the input, and the warning of a filter whose updates outgrow its own covariance.

One test per class of defect; each fails on the code before these checks (a KeyError, an IndexError, a read
past an array, a reading applied twice, a mask ignored, a MemoryError or an allocation, a silent divergence).
"""

from __future__ import annotations

import copy
import pickle
import warnings

import numpy as np
import pytest
from scipy.linalg import solve_discrete_lyapunov
from scipy.special import ndtri

import tobitkf as tk
from tobitkf.filters.core import FilterState

from .test_online import case_adf_fading, case_delay_chain, case_fading, case_hinf, case_pf, oscillator


def _tkf(backend="numpy", **kw):
    return tk.TobitKalmanFilter(oscillator(), tk.Censoring(lower=0.0), backend=backend, **kw)


def _unpickled(state: FilterState, **fields) -> FilterState:
    """A state as ``pickle`` hands it back, with some fields overwritten (a corrupted or hand-edited file)."""
    out = pickle.loads(pickle.dumps(state))
    for key, val in fields.items():
        object.__setattr__(out, key, val)
    return out


# --------------------------------------------------------------------------- states


def test_states_the_estimator_made_are_trusted_and_copies_are_not():
    """The token: set by init/step/predict/update/filter, dropped by pickling, copying and replace; a state that
    passed the full check is trusted by that estimator only."""
    from tobitkf.filters.core import is_trusted

    est, other = _tkf(), _tkf()
    s0 = est.init()
    s1 = est.step(s0, np.array([0.3]))
    assert is_trusted(est, s0) and is_trusted(est, s1) and not is_trusted(other, s1)
    assert is_trusted(est, est.predict(s1)) and is_trusted(est, est.update(est.predict(s1), np.array([0.2])))
    assert is_trusted(est, est.filter(np.array([[0.3], [0.1]])).final)
    for copied in (pickle.loads(pickle.dumps(s1)), copy.copy(s1), copy.deepcopy(s1), s1.replace(k=1)):
        assert not is_trusted(est, copied)
        assert "_origin" not in pickle.loads(pickle.dumps(copied)).__dict__
    resumed = pickle.loads(pickle.dumps(s1))
    a, b = est.step(s1, np.array([0.5])), est.step(resumed, np.array([0.5]))
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.P, b.P)
    assert is_trusted(est, resumed)  # checked once, then trusted


@pytest.mark.parametrize("backend", ["numpy", "numba"])
@pytest.mark.parametrize(
    "change, exc, match",
    [
        (lambda s: {"P": -s.P}, tk.ValidationError, "state.P: expected a positive semi-definite"),
        (lambda s: {"P": np.eye(3)[None]}, tk.ShapeError, r"state.P: expected a float64 array of shape \(1, 2, 2\)"),
        (lambda s: {"P": s.P[0]}, tk.ShapeError, "state.P"),
        (
            lambda s: {"P": s.P + np.array([[0.0, 1.0], [0.0, 0.0]])},
            tk.ValidationError,
            "state.P: expected a symmetric",
        ),
        (lambda s: {"P": None}, tk.ValidationError, "state.P: this TobitKalmanFilter keeps a covariance"),
        (lambda s: {"x": s.x[:, :1]}, tk.ShapeError, r"state.x: expected a float64 array of shape \(1, 2\)"),
        (lambda s: {"x": s.x.astype(np.float32)}, tk.ShapeError, "state.x"),
        (lambda s: {"k": 2.5}, tk.ValidationError, "state.k: expected an integer time index, got 2.5"),
        (lambda s: {"k": True}, tk.ValidationError, "state.k: expected an integer"),
        (lambda s: {"k": -1}, tk.ValidationError, r"state.k: expected a time index >= 0"),
        (lambda s: {"batch_shape": (2,)}, tk.ShapeError, r"state.x: expected a float64 array of shape \(2, 2\)"),
        (lambda s: {"batch_shape": [1]}, tk.ValidationError, "state.batch_shape"),
        (lambda s: {"n": 3}, tk.ShapeError, "state.n: expected 2"),
    ],
)
def test_a_corrupted_state_is_refused_by_name(backend, change, exc, match):
    """An unpickled state with a negative, asymmetric or wrongly shaped covariance, a fractional time index...
    was accepted (the compiled step read past the array, k = 2.5 gave an IndexError or a time of 3.5)."""
    est = _tkf(backend)
    s = est.step(est.init(), np.array([0.4]))
    bad = _unpickled(s, **change(s))
    for call in (
        lambda: est.step(bad, np.array([0.2])),
        lambda: est.predict(bad),
        lambda: est.filter([[0.2]], state=bad),
    ):
        with pytest.raises(exc, match=match):
            call()


def test_a_square_root_state_needs_a_factor_of_its_covariance():
    est = _tkf(covariance_update="square_root")
    s = est.step(est.init(), np.array([0.4]))
    with pytest.raises(tk.ValidationError, match="state.S: expected a factor of state.P"):
        est.step(_unpickled(s, S=2.0 * s.S), np.array([0.2]))
    # P alone (S None): the factor is made from it, as before
    fresh = est.step(_unpickled(s, S=None), np.array([0.2]))
    np.testing.assert_allclose(fresh.P, est.step(s, np.array([0.2])).P, rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "source, target, match",
    [
        (case_adf_fading, case_fading, "state.carry: lacks 'cx_pred'"),  # a KeyError before
        (case_hinf, lambda b, r: (_tkf(), None, None), "state.P: this TobitKalmanFilter keeps a covariance"),
        (case_delay_chain, case_pf, r"state.k: expected a time index >= 0"),
    ],
)
def test_a_state_from_another_estimator_is_refused_by_name(source, target, match):
    rng = np.random.default_rng(0)
    src, _, _ = source((), rng)
    dst, _, _ = target((), rng)
    state = src.init()
    y = np.full(dst.m, 0.5)
    with pytest.raises(tk.ValidationError, match=match):
        dst.step(state, y, **({"u": np.zeros(1)} if getattr(dst.system, "Bu", None) is not None else {}))


def test_a_state_of_the_same_layout_from_another_estimator_continues():
    """A Kalman filter's state continues in a Tobit Kalman filter of the same model (the same layout): the
    check is of the layout, not of the object that made it."""
    kf, tkf = tk.KalmanFilter(oscillator()), _tkf()
    s = kf.step(kf.init(), np.array([0.4]))
    np.testing.assert_allclose(
        tkf.step(s, np.array([0.3])).x, tkf.step(tkf.init().replace(x=s.x, P=s.P, k=1), np.array([0.3])).x
    )


@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_a_prediction_takes_its_reading_once(backend):
    """``update`` after ``step(predict(s), y)`` applied the same reading twice: ``step`` (and ``filter``) now
    refuse a prediction, ``update`` a state that is not one. A prediction of a prediction with its reading
    equals a step with the first reading missing, then a step (the model's two-step prediction)."""
    est = _tkf(backend)
    s = est.step(est.init(), np.array([0.4]))
    p = est.predict(s)
    with pytest.raises(tk.ValidationError, match=r"a prediction from predict\(\)"):
        est.step(p, np.array([0.3]))
    with pytest.raises(tk.ValidationError, match=r"a prediction from predict\(\)"):
        est.filter([[0.3]], state=p)
    u = est.update(p, np.array([0.3]))
    with pytest.raises(tk.ValidationError, match="update\\(\\) needs a predicted state"):
        est.update(u, np.array([0.3]))
    two = est.update(est.predict(est.predict(s)), np.array([0.3]))
    ref = est.step(est.step(s, np.array([np.nan])), np.array([0.3]))
    assert two.k == ref.k == 3
    np.testing.assert_allclose(two.x, ref.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(two.P, ref.P, rtol=0, atol=1e-12)


# --------------------------------------------------------------------------- readings


@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_masked_readings_are_missing(backend):
    """numpy masked arrays: the masked entries were read as the numbers under the mask; they are missing (NaN)."""
    est = _tkf(backend)
    y = np.array([[0.5], [100.0], [0.3], [0.0]])
    mask = np.array([[False], [True], [False], [False]])
    ref = est.filter(np.where(mask, np.nan, y))
    got = est.filter(np.ma.masked_array(y, mask=mask))
    np.testing.assert_array_equal(got.mean, ref.mean)
    s = est.init()
    for row, m in zip(y, mask):
        s = est.step(s, np.ma.masked_array(row, mask=m))
    np.testing.assert_allclose(s.mean, ref.mean[-1], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(y[1], [100.0])  # the caller's data untouched
    # a family that cannot skip a reading refuses a masked one, by name
    delay, yd, _ = case_delay_chain((), np.random.default_rng(0))
    with pytest.raises(tk.ValidationError, match="y: expected finite numbers, found 1 masked entries"):
        delay.filter(np.ma.masked_array(yd, mask=np.arange(yd.size).reshape(yd.shape) == 3))


@pytest.mark.parametrize(
    "make",
    [
        lambda: tk.DroppingKalmanFilter(oscillator(), tk.Censoring(lower=0.0)),
        lambda: tk.ParticleFilter(oscillator(), censoring=tk.Censoring(lower=0.0), particles=50, seed=1),
        lambda: _tkf(),
        lambda: tk.AssumedDensityTobitFilter(oscillator(), tk.Censoring(lower=0.0)),
    ],
)
@pytest.mark.parametrize("reading", [-0.5, -1e-7])
def test_step_and_filter_refuse_the_same_readings(make, reading):
    """The dropping KF's and the particle filter's ``step`` took a reading below the limit that ``filter``
    refuses: one rule (the record's check) for both, and for ``update``."""
    est = make()
    with pytest.raises(tk.ValidationError, match="outside its censoring limits"):
        est.filter(np.array([[reading]]))
    with pytest.raises(tk.ValidationError, match="outside its censoring limits"):
        est.step(est.init(), np.array([reading]))
    if hasattr(est, "update"):
        with pytest.raises(tk.ValidationError, match="outside its censoring limits"):
            est.update(est.predict(est.init()), np.array([reading]))
    est.step(est.init(), np.array([0.0]))  # at the limit: censored, accepted by both
    est.filter(np.array([[0.0]]))


@pytest.mark.parametrize("value", [1e308, -1e200, 2e150])
def test_readings_whose_squares_overflow_are_refused_by_name(value):
    """A reading of 1e308 gave a finite-looking estimate of 9e307 (and the fit blamed its start): refused, naming
    ``y`` and the index, in ``filter`` and ``step`` alike; 1e150 itself passes."""
    kf = tk.KalmanFilter(oscillator())
    with pytest.raises(tk.ValidationError, match=r"y: reading .* at index \(1, 0\) is beyond"):
        kf.filter(np.array([[0.5], [value]]))
    with pytest.raises(tk.ValidationError, match=r"y: reading .* at index \(0,\) is beyond"):
        kf.step(kf.init(), np.array([value]))
    assert np.isfinite(kf.filter(np.array([[1e150]])).mean).all()  # one absurd update: a surprise, no warning


def test_smaller_boundary_messages():
    kf = tk.KalmanFilter(oscillator())
    with pytest.raises(tk.ValidationError, match="outputs: expected 'all', 'last', a name or a list of names"):
        kf.filter(np.zeros((3, 1)), outputs=5)
    with pytest.raises(tk.ShapeError, match=r"y: expected at least one run .* got shape \(0, 3, 1\)"):
        kf.filter(np.zeros((0, 3, 1)))


def test_delay_pred_mean_is_the_prediction_before_the_reading():
    """The delay module's docstring: ``pred_mean[t]`` is x̂(t|t-1) (the prior's top block at t = 0) and
    ``extras["next_mean"][t]`` is x̂(t+1|t)."""
    est, y, _ = case_delay_chain((3,), np.random.default_rng(0))
    r = est.filter(y)
    np.testing.assert_array_equal(r.pred_mean[:, 1:], np.asarray(r.extras["next_mean"])[:, :-1])
    np.testing.assert_array_equal(r.pred_mean[:, 0], est.init((3,)).x[:, : est.n])


# --------------------------------------------------------------------------- memory


@pytest.fixture
def small_memory(monkeypatch):
    monkeypatch.setenv("TOBITKF_MEMORY_LIMIT", str(10**6))  # 1 MB: the requests below are refused, not made


def test_allocations_scaled_by_the_input_are_checked_first(small_memory):
    """``init(batch_shape=(10**6, 10**6))`` raised MemoryError (or allocated), ``ParticleFilter(particles=10**9)``
    was built, a broadcast (10^6, 10^4) record was copied: each refused naming the argument and the size."""
    kf = tk.KalmanFilter(oscillator())
    with pytest.raises(tk.ValidationError, match=r"batch_shape: the state of 1000000000000 runs .* would need 48 TB"):
        kf.init(batch_shape=(10**6, 10**6))
    with pytest.raises(tk.ValidationError, match=r"particles: 100000 particles of one run would need 4.8 MB"):
        tk.ParticleFilter(oscillator(), particles=10**5)
    pf = tk.ParticleFilter(oscillator(), particles=1000)
    with pytest.raises(tk.ValidationError, match=r"batch_shape: the state of 100 runs of this ParticleFilter"):
        pf.init((100,))
    y = np.broadcast_to(0.0, (10**6, 10**4, 1))
    with pytest.raises(tk.ValidationError, match=r"y: the readings of shape \(1000000, 10000, 1\) .* would need 80 GB"):
        kf.filter(y)
    with pytest.raises(tk.ValidationError, match=r"y: the outputs \(cov, mean, pred_cov, pred_mean\) of 1000 runs"):
        kf.filter(np.zeros((1000, 100, 1)))
    assert kf.filter(np.zeros((1000, 100, 1)), outputs="last").final.runs == 1000


@pytest.mark.parametrize("fill", [0.0, 0])
def test_a_huge_broadcast_record_is_refused_before_its_values_are_read(monkeypatch, fill):
    """A broadcast (10^6, 10^4) record was refused only after every one of its 10^10 values had been checked
    (minutes), and an integer one was first converted (an 80 GB copy): the memory check now comes first."""
    from tobitkf import _validation

    def scan(*args, **kwargs):
        raise AssertionError("the values were read before the memory check")

    kf = tk.KalmanFilter(oscillator())
    monkeypatch.setattr(_validation, "check_finite", scan)
    monkeypatch.setattr(_validation, "_convert", scan)
    y = np.broadcast_to(fill, (10**6, 10**4, 1))
    with pytest.raises(tk.ValidationError, match=r"y: the readings of shape \(1000000, 10000, 1\) .* would need 80 GB"):
        kf.filter(y)


# --------------------------------------------------------------------------- divergence


def _one_sided_system(seed: int):
    """A random stable system of n in 2..6 states, one output censored below at a stationary quantile
    (30-90 % censored): the family on which the total-variance TKF diverges."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 7))
    M = rng.standard_normal((n, n))
    A = M * (rng.uniform(0.8, 0.98) / np.max(np.abs(np.linalg.eigvals(M))))
    C = rng.standard_normal((1, n))
    q = 10 ** rng.uniform(-2.5, -1.0)
    R = np.diag(10 ** rng.uniform(-2.0, -0.3, 1))
    Sig = solve_discrete_lyapunov(A, q * np.eye(n))
    Sig = 0.5 * (Sig + Sig.T)
    sd = np.sqrt(np.diagonal(C @ Sig @ C.T) + np.diagonal(R))
    lo = sd * ndtri(rng.uniform(0.3, 0.9, 1))
    return tk.LinearSystem(A=A, C=C, Q=q * np.eye(n), R=R, x0=np.zeros(n), P0=Sig), tk.Censoring(lower=lo)


def _warnings_of(est, y):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = est.filter(y)
    return res, [str(w.message) for w in caught if "far larger than its own covariance" in str(w.message)]


@pytest.mark.parametrize("seed", [2, 4])
def test_a_diverging_total_variance_tkf_warns_and_healthy_filters_do_not(seed):
    """On these one-sided systems the total-variance TKF ends 100-1000x off (its covariance finite and small):
    one warning naming the step and the remedy. The dissertation's and exact E[pv^2] terms, the ADF and the KF
    on the same data (all healthy: within 2x of the ADF's RMSE) give none."""
    sys_, cens = _one_sided_system(seed)
    d = tk.simulate(sys_, 200, 20, censoring=cens, seed=seed)
    adf, none = _warnings_of(tk.AssumedDensityTobitFilter(sys_, cens), d.y)
    assert none == []
    best = np.sqrt(np.mean((adf.mean - d.x[:, 1:]) ** 2))
    for kw in ({}, {"noise_term": "exact_pv"}):
        res, none = _warnings_of(tk.TobitKalmanFilter(sys_, cens, **kw), d.y)
        assert none == [] and np.sqrt(np.mean((res.mean - d.x[:, 1:]) ** 2)) < 2 * best
    res, none = _warnings_of(tk.KalmanFilter(sys_), d.y)
    assert none == []
    for backend in ("numpy", "numba"):
        res, found = _warnings_of(tk.TobitKalmanFilter(sys_, cens, noise_term="total_variance", backend=backend), d.y)
        assert np.sqrt(np.nanmean((res.mean - d.x[:, 1:]) ** 2)) > 100 * best  # it did diverge
        assert len(found) == 1
        assert "at step k=" in found[0] and "noise_term='dissertation' or 'exact_pv'" in found[0]


def test_the_correction_check_in_blocks_of_runs_names_the_same_step_and_count(monkeypatch):
    """The check runs over blocks of runs (its temporaries bounded); the step it names, the number of runs it
    counts and the window it reports do not depend on the block size: one run per block, seven, and the whole
    record in one block give the same message, and that message agrees with a direct count of the runs whose
    capped window sum exceeds the threshold."""
    from tobitkf.filters import _online_check as oc

    sys_, cens = _one_sided_system(2)
    d = tk.simulate(sys_, 40, 30, censoring=cens, seed=2)
    est = tk.TobitKalmanFilter(sys_, cens, noise_term="total_variance", backend="numpy")
    messages = []
    for values in (1, 7 * 40 * sys_.n, 1 << 30):
        monkeypatch.setattr(oc, "_CHECK_BLOCK", values)
        res, found = _warnings_of(est, d.y)
        assert len(found) == 1
        messages.append(found[0])
    assert messages[0] == messages[1] == messages[2]
    limit = oc.correction_threshold(1, 20)
    c = np.minimum(oc.correction_statistic(res.mean, res.pred_mean, res.pred_cov), oc.CORRECTION_CAP * limit)
    win = np.stack([c[:, j : j + 20].sum(axis=-1) for j in range(c.shape[-1] - 19)], axis=-1)
    runs = int(((win > limit) & np.isfinite(res.mean).all(axis=(-2, -1))[:, None]).any(axis=-1).sum())
    assert f" in {runs} of 30 runs " in messages[0]


def test_the_correction_statistic_is_below_the_normalised_innovation():
    r"""The bound the threshold rests on, exactly, on a Kalman filter: :math:`\max_i (Ke)_i^2/\bar P_{ii} \le
    e^2/R_{ee}` at every step (m = 1), with the innovation and its variance formed independently of the core."""
    from tobitkf.filters._online_check import correction_statistic, correction_threshold

    sys_ = oscillator()
    d = tk.simulate(sys_, 50, 30, seed=3)
    r = tk.KalmanFilter(sys_, backend="numpy").filter(d.y)
    C, R = np.array([[1.0, 0.0]]), 0.04
    e = d.y[..., 0] - r.pred_mean @ C[0]
    Ree = np.einsum("i,ntij,j->nt", C[0], r.pred_cov, C[0]) + R
    c = correction_statistic(r.mean, r.pred_mean, r.pred_cov)
    assert (c <= e * e / Ree * (1 + 1e-9)).all()
    assert c.max() > 0.1  # not trivially zero
    assert correction_threshold(1) > 100 * 20  # far above the window's chi-square mean (m W = 20)


def test_one_outlier_is_a_surprise_not_a_divergence():
    """A healthy Kalman filter fed one reading 150 predicted standard deviations off (a data error) gives no
    divergence warning (each step adds at most a quarter of the threshold); a burst of such readings does."""
    sys_ = oscillator()
    d = tk.simulate(sys_, 60, 3, seed=5)
    y = d.y.copy()
    y[:, 30] += 40.0  # the predicted sd of a reading is about 0.27 here
    res, found = _warnings_of(tk.KalmanFilter(sys_), y)
    assert found == []
    y[:, 31:40] += 40.0 * (-1.0) ** np.arange(9)[:, None]
    res, found = _warnings_of(tk.KalmanFilter(sys_), y)
    assert len(found) == 1 and "at step k=" in found[0]


def test_the_online_steps_reading_check_evaluates_a_callable_model_once_per_step():
    """``step`` checks its reading by the record's rule, which validates a callable model over the horizon:
    each time index is validated once (an online run of T steps costs O(T) evaluations, not O(T^2))."""
    calls = []

    def C(k):
        calls.append(k)
        return np.array([[1.0, 0.01 * k]])

    sys_ = tk.LinearSystem(A=0.9 * np.eye(2), C=C, Q=0.01 * np.eye(2), R=[[0.1]], x0=[0.0, 0.0], P0=np.eye(2))
    est = tk.DroppingKalmanFilter(sys_, tk.Censoring(lower=-1.0), backend="numpy")
    s, start = est.init(), len(calls)
    for k in range(60):
        s = est.step(s, np.array([0.1]))
    assert len(calls) - start <= 4 * 60


def _step_warnings(est, y):
    """The divergence warnings of an online loop ``state = est.step(state, y_k)`` over the runs of ``y`` (N, T,
    m) at once, and the final state."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s = est.init(batch_shape=(y.shape[0],))
        for k in range(y.shape[1]):
            s = est.step(s, y[:, k])
    return s, [str(w.message) for w in caught if "far larger than its own covariance" in str(w.message)]


@pytest.mark.parametrize("backend", ["numpy", "numba"])
@pytest.mark.parametrize("seed", [2, 4])
def test_a_diverging_total_variance_tkf_warns_from_a_step_loop_and_healthy_ones_do_not(seed, backend):
    """The online form of the check above: the same diverging variant on the same data warns exactly once
    from a ``step`` loop (one run at a time, and 20 runs batched), naming the step and the remedy; the
    dissertation's term, the ADF and the KF do not warn. Before the online check ``step`` never warned."""
    sys_, cens = _one_sided_system(seed)
    d = tk.simulate(sys_, 200, 20, censoring=cens, seed=seed)
    for est in (
        tk.TobitKalmanFilter(sys_, cens, backend=backend),
        tk.AssumedDensityTobitFilter(sys_, cens),
        tk.KalmanFilter(sys_, backend=backend),
    ):
        assert _step_warnings(est, d.y)[1] == []
    tv = tk.TobitKalmanFilter(sys_, cens, noise_term="total_variance", backend=backend)
    s, found = _step_warnings(tv, d.y)
    assert len(found) == 1
    assert "by step k=" in found[0] and "noise_term='dissertation' or 'exact_pv'" in found[0]
    from tobitkf.filters._online_check import has_warned

    assert has_warned(s)  # the lineage remembers it warned
    for run in range(20):  # one run at a time: some run warns, each lineage at most once
        found = _step_warnings(tv, d.y[run : run + 1])[1]
        assert len(found) <= 1
        if found:
            break
    else:
        pytest.fail("no single-run step loop warned")


def test_the_step_check_lives_in_the_state_and_costs_one_time_update_per_stride():
    """The check's memory is carried by the state (a new lineage from an earlier state warns again; the old
    state is unchanged), and it looks at every STRIDE-th step only."""
    from tobitkf.filters import _online_check

    sys_, cens = _one_sided_system(2)
    d = tk.simulate(sys_, 200, 20, censoring=cens, seed=2)
    tv = tk.TobitKalmanFilter(sys_, cens, noise_term="total_variance", backend="numpy")
    s0 = tv.init(batch_shape=(20,))
    s = s0
    for k in range(_online_check.STRIDE - 1):
        s = tv.step(s, d.y[:, k])
        assert "_correction_window" not in s.carry  # not a checked step
    s = tv.step(s, d.y[:, _online_check.STRIDE - 1])
    window = s.carry["_correction_window"]  # the last 20 checked values of each run, then the count
    assert window.shape == (20, 21) and (window[:, 20] == 1).all()
    assert (window[:, 0] > 0).any() and (window[:, 1:20] == 0).all()
    first = _step_warnings(tv, d.y)[1]
    again = _step_warnings(tv, d.y)[1]
    assert len(first) == len(again) == 1
    assert "_correction_window" not in s0.carry
    # a pickled state carries the memory: resuming after the warning does not warn again
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s = tv.init(batch_shape=(20,))
        for k in range(150):
            s = tv.step(s, d.y[:, k])
        s = pickle.loads(pickle.dumps(s))
        for k in range(150, 200):
            s = tv.step(s, d.y[:, k])
    assert sum("far larger" in str(w.message) for w in caught) == 1


@pytest.mark.parametrize("n, m", [(2, 1), (6, 3)])
@pytest.mark.parametrize("family", ["kf", "tkf"])
def test_the_step_checks_statistic_of_one_compiled_run_is_the_predicted_normalised_update(family, n, m):
    """One run of a compiled KF or TKF: the check's statistic (from the transition cached on the estimator, in
    Python floats for n = 2, numpy's products for n = 6) is max_i (x_i - xbar_i)^2 / Pbar_ii with
    xbar = A x_prev, Pbar = A P_prev A^T + Q, computed here in numpy."""
    from tobitkf.filters import _online_check

    rng = np.random.default_rng(n)
    A = 0.9 * np.linalg.qr(rng.normal(size=(n, n)))[0]
    C = rng.normal(size=(m, n))
    Q = 0.01 * np.eye(n) + 0.005 * np.ones((n, n))
    sys_ = tk.LinearSystem(A=A, C=C, Q=Q, R=0.1 * np.eye(m), x0=np.zeros(n), P0=np.eye(n))
    cens = tk.Censoring(lower=-0.5)
    est = (
        tk.KalmanFilter(sys_, backend="numba") if family == "kf" else tk.TobitKalmanFilter(sys_, cens, backend="numba")
    )
    y = tk.simulate(sys_, 12, 1, censoring=cens, seed=3).y[0]
    prev = est.init()
    for k in range(11):
        prev = est.step(prev, y[k])
    new = est.step(prev, y[11])
    got = _online_check._statistic(est, prev, new, None, None, None)
    assert est.__dict__["_check_transition"][1] is not None  # the cached transition was used
    xbar = A @ prev.x[0]
    var = np.diag(A @ prev.P[0] @ A.T + sys_.process_cov(0))
    want = np.max((new.x[0] - xbar) ** 2 / var)
    assert len(got) == 1 and want > 0
    np.testing.assert_allclose(got[0], want, rtol=1e-12)


def test_the_step_checks_cached_fading_transition_gives_the_statistic_of_the_transition_built_each_step():
    """The fading TKF's block shift: the check's statistic from the transition cached on the estimator equals
    the one from the transition built afresh for the step (the path of a time-varying system)."""
    from tobitkf.channels.fading import RiceFading
    from tobitkf.filters import _online_check

    sys_ = oscillator()
    cens = tk.Censoring(lower=0.0)
    fad = RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    y = tk.simulate(sys_, 40, 1, censoring=cens, measurement=fad, seed=1).y[0]
    est = tk.FadingTobitKalmanFilter(sys_, fad, cens)
    prev = est.init()
    for k in range(39):
        prev = est.step(prev, y[k])
    new = est.step(prev, y[39])
    got = _online_check._statistic(est, prev, new, None, None, None)
    assert est.__dict__["_check_transition"][1] is not None
    est.__dict__["_check_transition"] = (est.system, None)  # as for a transition that changes: built each step
    want = _online_check._statistic(est, prev, new, None, None, None)
    assert want[0] > 0
    np.testing.assert_allclose(got, want, rtol=1e-12)


@pytest.mark.parametrize("n", [2, 6])
def test_the_step_checks_statistic_of_one_run_with_an_input_is_the_predicted_normalised_update(n):
    """One run of a KF with a control input (the transition is built at the checked step, with its offset
    b = B^u u): the check's statistic in Python floats (n = 2) and through numpy's products (n = 6) is
    max_i (x_i - xbar_i)^2 / Pbar_ii with xbar = A x_prev + B^u u, Pbar = A P_prev A^T + Q, computed here in numpy;
    the same step batched over two identical runs (the numpy route of the check) gives the same value."""
    from tobitkf.filters import _online_check

    rng = np.random.default_rng(10 + n)
    A = 0.9 * np.linalg.qr(rng.normal(size=(n, n)))[0]
    Bu = rng.normal(size=(n, 1))
    sys_ = tk.LinearSystem(
        A=A, C=rng.normal(size=(1, n)), Q=0.02 * np.eye(n), R=[[0.1]], x0=np.zeros(n), P0=np.eye(n), Bu=Bu
    )
    est = tk.KalmanFilter(sys_, backend="numpy")
    prev = est.init()
    for k in range(5):
        prev = est.step(prev, rng.normal(size=1), u=[0.3])
    u = np.array([[2.0]])  # the step's input as the check sees it: (runs, p)
    new = est.step(prev, np.array([5.0]), u=[2.0])
    got = _online_check._statistic(est, prev, new, u, None, None)
    xbar = A @ prev.x[0] + Bu[:, 0] * 2.0
    var = np.diag(A @ prev.P[0] @ A.T + 0.02 * np.eye(n))
    want = np.max((new.x[0] - xbar) ** 2 / var)
    without_b = np.max((new.x[0] - A @ prev.x[0]) ** 2 / var)
    assert len(got) == 1 and abs(without_b - want) > 1e-3 * want  # the input's offset matters here
    np.testing.assert_allclose(got[0], want, rtol=1e-12)
    two = FilterState(k=prev.k, batch_shape=(2,), x=np.repeat(prev.x, 2, 0), P=np.repeat(prev.P, 2, 0), n=n)
    new2 = FilterState(k=new.k, batch_shape=(2,), x=np.repeat(new.x, 2, 0), P=np.repeat(new.P, 2, 0), n=n)
    batched = _online_check._statistic(est, two, new2, np.repeat(u, 2, 0), None, None)
    np.testing.assert_allclose(batched, [want, want], rtol=1e-12)
