"""Multi-target tracker of Miller §2.2 (spec 001a §6 items 15-17)."""

import numpy as np
import pytest

from tobitkf import KalmanFilter, LinearSystem
from tobitkf._validation import ShapeError, ValidationError
from tobitkf.filters.tracking import MultiTargetTracker, constant_velocity_pixel_model


def test_identity_kept_with_spurious_detections_and_shuffling():
    rng = np.random.default_rng(0)
    start = rng.uniform(50, 300, size=(8, 2))
    truth = start[None] + np.arange(1, 81)[:, None, None] * np.array([1.0, 1.0])
    frames = []
    for k in range(80):
        pts = np.concatenate([truth[k], rng.uniform(0, 640, size=(rng.integers(0, 60), 2))])
        frames.append(pts[rng.permutation(len(pts))])
    res = MultiTargetTracker().track(start, frames)
    for k in range(10, 80):
        for i in range(8):
            assert res.assignment[k, i] >= 0
            assert frames[k][res.assignment[k, i]] == pytest.approx(truth[k, i])
    assert np.abs(res.mean[-1, :, ::2] - truth[-1]).max() < 1e-6


def _occlusion_case():
    c0 = np.array([[100.0, 200.0], [180.0, 200.0], [460.0, 240.0], [540.0, 240.0]])
    v = np.where(np.arange(240)[:, None] < 100, 2.0, -2.0)
    truth = c0[None] + np.stack([np.cumsum(v, 0)[:, 0][:, None].repeat(4, 1), np.zeros((240, 4))], axis=-1)
    frames = [t[t[:, 0] < 640] for t in truth]
    return c0, truth, frames


def test_occluded_feedback_keeps_estimates_with_the_group():
    c0, truth, frames = _occlusion_case()
    err = {}
    for fb in ("corrected", "off"):
        res = MultiTargetTracker(feedback=fb).track(c0, frames)
        e = np.linalg.norm(res.mean[..., ::2] - truth, axis=-1)
        err[fb] = e[res.assignment < 0].max()
        assert np.all(res.assignment[-1] >= 0)
        for i in range(4):
            assert frames[-1][res.assignment[-1, i]] == pytest.approx(truth[-1, i])
    assert err["corrected"] < 0.2 * err["off"]
    # the occluded counter drives the gate and resets on a match
    res = MultiTargetTracker().track(c0, frames)
    assert res.occluded_frames[:, 3].max() > 10 and res.occluded_frames[-1, 3] == 0


def test_printed_feedback_sign_pushes_away():
    c0, truth, frames = _occlusion_case()
    res = MultiTargetTracker(feedback="printed").track(c0, frames)
    e = np.linalg.norm(res.mean[..., ::2] - truth, axis=-1)
    assert e.max() > 1000


def test_gate_rejects_wrong_measurements_where_the_kf_follows_them():
    truth = np.array([100.0, 80.0]) + np.arange(1, 101)[:, None]
    meas = truth.copy()
    meas[40:43] = [400.0, 50.0]
    res = MultiTargetTracker().track(truth[:1] - 1.0, [m[None] for m in meas])
    assert np.all(res.assignment[40:43, 0] == -1)
    assert np.abs(res.mean[20:, 0, ::2] - truth[20:]).max() < 0.05
    A, C = constant_velocity_pixel_model()
    kf = KalmanFilter(
        LinearSystem(A=A, C=C, Q=0.01 * np.eye(4), R=np.eye(2), x0=[100.0, 0, 80.0, 0], P0=np.diag([1.0, 10, 1, 10]))
    ).filter(meas)
    assert np.abs(kf.mean[40:45, ::2] - truth[40:45]).max() > 50
    ungated = MultiTargetTracker(gate=False).track(truth[:1] - 1.0, [m[None] for m in meas])
    assert ungated.mean[:, 0, ::2] == pytest.approx(kf.mean[:, ::2], abs=1e-9)  # no gate, no feedback: a KF


def test_bad_input():
    with pytest.raises(ValidationError, match="feedback"):
        MultiTargetTracker(feedback="x")
    with pytest.raises(ValidationError, match="gate0"):
        MultiTargetTracker(gate0=0.0)
    with pytest.raises(ValidationError, match="warmup"):
        MultiTargetTracker(warmup=-1)
    with pytest.raises(ShapeError, match="initial"):
        MultiTargetTracker().track(np.zeros(3), [])


def _clutter_case(seed=3, N=5, T=120):
    """Moving targets, each missed in a quarter of the frames, with clutter, shuffled."""
    rng = np.random.default_rng(seed)
    start = rng.uniform(50, 300, size=(N, 2))
    frames = []
    for k in range(T):
        truth = start + (k + 1) * np.array([1.0, 0.5]) + rng.normal(size=(N, 2)) * 0.3
        pts = np.concatenate([truth[rng.random(N) > 0.25], rng.uniform(0, 400, size=(rng.integers(0, 6), 2))])
        frames.append(pts[rng.permutation(len(pts))])
    return start, frames


def _run_steps(tracker, state, frames):
    out = []
    for f in frames:
        state = tracker.step(state, f)
        out.append((state.mean, np.array(state.cov), state.extras["assignment"], state.extras["occluded_frames"]))
    return [np.array(v) for v in zip(*out)]


@pytest.mark.parametrize("kw", [{}, {"second_map": "mutual"}, {"feedback": "printed", "mu": 0.5}])
def test_step_equals_filter_row_by_row(kw):
    start, frames = _clutter_case()
    tr = MultiTargetTracker(**kw)
    mean, cov, asg, occ = _run_steps(tr, tr.init(start), frames)
    res = tr.filter(frames, initial=start)
    assert np.array_equal(res.mean, mean.swapaxes(0, 1)) and np.array_equal(res.cov, cov.swapaxes(0, 1))
    assert np.array_equal(res.extras["assignment"], asg.T) and np.array_equal(res.extras["occluded_frames"], occ.T)
    assert res.cov.flags.writeable and res.pred_cov.flags.writeable  # ordinary arrays, not broadcast views


def test_pickled_state_resumes_identically():
    """A tracker state pickled mid-run (after misses, with feedback memory) resumes bitwise."""
    import pickle

    start, frames = _clutter_case(seed=2)
    tr = MultiTargetTracker()
    s = tr.init(start)
    half = len(frames) // 2
    for f in frames[:half]:
        s = tr.step(s, f)
    revived = pickle.loads(pickle.dumps(s))
    a, b = _run_steps(tr, s, frames[half:]), _run_steps(tr, revived, frames[half:])
    for u, v in zip(a, b):
        assert np.array_equal(u, v)
    whole = _run_steps(tr, tr.init(start), frames)
    assert np.array_equal(whole[0][half:], a[0])


def test_shared_covariance_route_equals_one_covariance_per_target():
    # init shares one P among the targets until one is missed; a state carrying N equal copies
    # (the per-target route throughout) gives the same numbers
    start, frames = _clutter_case(seed=4)
    tr = MultiTargetTracker()
    s0 = tr.init(start)
    assert s0.P.shape == (1, 4, 4)
    per_target = s0.replace(P=np.repeat(s0.P, len(start), axis=0))
    for a, b in zip(_run_steps(tr, s0, frames), _run_steps(tr, per_target, frames)):
        assert np.array_equal(a, b)
    # and all-matched frames keep the covariance shared
    c = np.array([[0.0, 0.0], [20.0, 0.0], [40.0, 0.0]])
    s = tr.init(c)
    for f in np.random.default_rng(5).normal(size=(30, 3, 2)) * 0.5 + c:
        s = tr.step(s, f)
    assert s.P.shape == (1, 4, 4) and s.cov.shape == (3, 4, 4)


def test_python_float_distances_equal_the_array_route(monkeypatch):
    import tobitkf.filters.tracking as trk

    start, frames = _clutter_case(seed=5, N=3)
    tr = MultiTargetTracker()
    ref = tr.init(start).x[:, ::2]
    for f in frames:
        monkeypatch.setattr(trk, "_FEW_PAIRS", 10**9)
        D_py, fin_py = tr._distances(ref, f)
        monkeypatch.setattr(trk, "_FEW_PAIRS", -1)
        D_np, fin_np = tr._distances(ref, f)
        assert D_py == D_np and fin_py and fin_np
    runs = []
    for few in (10**9, -1):
        monkeypatch.setattr(trk, "_FEW_PAIRS", few)
        runs.append(_run_steps(tr, tr.init(start), frames))
    for a, b in zip(*runs):
        assert np.array_equal(a, b)


@pytest.mark.parametrize("kw", [{}, {"second_map": "mutual"}, {"gate": False}, {"gate0": 1.0}])
def test_list_association_equals_the_numpy_argmin_route(kw):
    # the finite-distance route (lists) and the route kept for NaN distances (numpy argmin) agree
    # wherever both apply, ties included (distances rounded to a coarse grid)
    rng = np.random.default_rng(6)
    tr = MultiTargetTracker(**kw)
    for _ in range(300):
        N, L = rng.integers(1, 6), rng.integers(1, 6)
        D = np.round(rng.uniform(0, 15, size=(N, L)))
        O = rng.integers(0, 3, size=N)
        assert tr._associate(D.tolist(), O.tolist()) == tr._associate_nonfinite(D, O)
    # a NaN distance (a diverged track): argmin takes the first NaN, so target 0 chooses detection 0
    # and, among its choosers {0, 1}, wins it (argmin over [NaN, 1.0]); NaN fails the gate, so
    # nobody gets detection 0; target 2 keeps detection 1
    D = np.array([[np.nan, 5.0], [1.0, 2.0], [3.0, 0.5]])
    assert MultiTargetTracker()._associate_nonfinite(D, np.zeros(3, dtype=int)) == [-1, -1, 1]


_BLOCK_Q = np.kron(np.eye(2), [[0.02, 0.005], [0.005, 0.01]])


@pytest.mark.parametrize(
    "kw, fixed_gain",
    [
        ({}, True),
        ({"Q": _BLOCK_Q, "R": np.diag([2.0, 0.5])}, True),  # decoupled x/y: one nonzero per gain row
        ({"R": [[1.0, 0.4], [0.4, 0.8]]}, False),  # coupled channels: the full update every frame
        ({"feedback": "printed", "mu": 0.5}, None),
    ],
)
def test_reused_predict_and_update_equal_fresh_ones(kw, fixed_gain, monkeypatch):
    # the covariance predict (and, for a decoupled model, the gain and posterior covariance) are
    # reused when a frame starts from the same P bit for bit (all targets matched long enough for
    # the recursion to stop changing); clearing the memos before every step, or interleaving another
    # run on the same tracker, gives the same numbers
    import tobitkf.filters.tracking as trk

    c = np.array([[0.0, 0.0], [20.0, 0.0], [40.0, 0.0]])
    frames = np.random.default_rng(5).normal(size=(200, 3, 2)) * 0.5 + c
    start, other = _clutter_case(seed=7, N=3, T=200)
    tr = MultiTargetTracker(**kw)
    gains = []
    update = trk.measurement_update

    def counting(x, P, S, y, mp, form):
        gains.append(mp.gain is not None)
        return update(x, P, S, y, mp, form)

    monkeypatch.setattr(trk, "measurement_update", counting)
    reused = _run_steps(tr, tr.init(c), frames)
    if fixed_gain is not None:
        assert np.array_equal(reused[1][-1], reused[1][-2])  # the case does reach the fixed point
        assert any(gains) == fixed_gain
    fresh, s = [], tr.init(c)
    for f in frames:
        tr._last_predict = tr._last_update = None
        s = tr.step(s, f)
        fresh.append((s.mean, np.array(s.cov), s.extras["assignment"], s.extras["occluded_frames"]))
    s, s2, mixed = tr.init(c), tr.init(start), []
    for f, g in zip(frames, other):
        s, s2 = tr.step(s, f), tr.step(s2, g)
        mixed.append((s.mean, np.array(s.cov), s.extras["assignment"], s.extras["occluded_frames"]))
    for a, b, m in zip(reused, [np.array(v) for v in zip(*fresh)], [np.array(v) for v in zip(*mixed)]):
        assert np.array_equal(a, b) and np.array_equal(a, m)


def test_frame_check_of_a_float_array():
    tr = MultiTargetTracker()
    s = tr.init([[0.0, 0.0]])
    big = np.full((2, 2), 1e308)  # finite points whose sum overflows: accepted
    assert tr.step(s, big).extras["assignment"].tolist() == [-1]
    for bad, word in ((np.array([[np.nan, 0.0]]), "NaN"), (np.array([[np.inf, 0.0]]), "inf")):
        with pytest.raises(ValidationError, match=f"detections: .*{word}"):
            tr.step(s, bad)
    with pytest.raises(ShapeError, match="detections"):
        tr.step(s, np.zeros((2, 3)))
