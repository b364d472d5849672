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
