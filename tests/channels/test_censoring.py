"""Tests of the censoring channel (``tobitkf.channels.censoring``): clipping, limits, masks, multi_region."""

from __future__ import annotations

import numpy as np
import pytest

from tobitkf import Censoring, LinearSystem, ShapeError, ValidationError, multi_region


def _sys(m=1, R=None):
    C = np.ones((m, 1))
    return LinearSystem(A=[[0.99]], C=C, Q=[[0.01]], R=np.eye(m) * 0.0025 if R is None else R, x0=[0.0], P0=[[1.0]])


def test_clip_follows_table_1_1():
    """Left: y = T if y* <= T; right: y = T if y* >= T; two-sided: saturation (Miller Table 1.1, (6.59))."""
    ystar = np.array([[-2.0], [-0.5], [0.0], [0.3], [1.0], [5.0]])
    left = Censoring(lower=0.0).clip(ystar, k=1)
    right = Censoring(upper=0.0).clip(ystar, k=1)
    sat = Censoring(lower=-1.0, upper=1.0).clip(ystar, k=1)
    np.testing.assert_array_equal(left.ravel(), [0, 0, 0, 0.3, 1, 5])
    np.testing.assert_array_equal(right.ravel(), [-2, -0.5, 0, 0, 0, 0])
    np.testing.assert_array_equal(sat.ravel(), [-1, -0.5, 0, 0.3, 1, 1])
    # no limits: identity
    np.testing.assert_array_equal(Censoring().clip(ystar, k=1), ystar)


def test_per_channel_limits():
    cens = Censoring(lower=[0.0, -np.inf, -1.0], upper=[np.inf, 0.5, 1.0])
    y = np.array([[-3.0, 3.0, 3.0], [3.0, -3.0, -3.0]])
    np.testing.assert_array_equal(cens.clip(y, k=7), [[0.0, 0.5, 1.0], [3.0, -3.0, -1.0]])
    assert cens.channels == 3 and not cens.time_varying


def test_time_varying_limits_align_with_measurement_index():
    """Row k-1 of a (T, m) limit array belongs to y_k, as y_k is stored at index k-1."""
    lo = np.array([[0.0], [1.0], [2.0], [3.0]])
    cens = Censoring(lower=lo)
    assert cens.time_varying and cens.steps == 4
    for k in range(1, 5):
        lk, hk = cens.limits(k)
        assert float(lk[0]) == k - 1 and np.isposinf(hk).all()
    y = np.zeros((2, 4, 1))
    out = cens.clip(y)  # whole record, k=None
    np.testing.assert_array_equal(out[0, :, 0], [0.0, 1.0, 2.0, 3.0])
    np.testing.assert_array_equal(cens.clip(np.zeros((1,)), k=3), [2.0])
    lo_all, hi_all = cens.all_limits(3, 1)
    assert lo_all.shape == hi_all.shape == (3, 1)
    np.testing.assert_array_equal(lo_all[:, 0], [0.0, 1.0, 2.0])


def test_time_varying_limits_out_of_range_step():
    """k counts measurements from 1; k = 0 must not silently wrap to the last row (numpy index -1)."""
    cens = Censoring(lower=np.array([[0.0], [1.0], [2.0]]))
    for k in (0, 4):
        with pytest.raises(ShapeError, match=rf"censoring limits: time-varying limits have 3 steps, step k={k}"):
            cens.limits(k)
    Censoring(lower=0.0).limits(0)  # constant limits hold at every step


def test_all_limits_broadcasts_scalars_and_channels():
    lo, hi = Censoring(lower=-1.0, upper=2.0).all_limits(5, 3)
    assert lo.shape == hi.shape == (5, 3)
    assert (lo == -1).all() and (hi == 2).all()
    lo, hi = Censoring(lower=[0.0, 1.0]).all_limits(2, 2)
    np.testing.assert_array_equal(lo, [[0.0, 1.0], [0.0, 1.0]])
    assert np.isposinf(hi).all()
    # the returned arrays are writable copies, not views into the channel's limits
    lo[0, 0] = 99.0
    assert Censoring(lower=[0.0, 1.0]).all_limits(2, 2)[0][0, 0] == 0.0


def test_censored_mask_detects_readings_at_the_limit():
    cens = Censoring(lower=[0.0, -np.inf], upper=[np.inf, 1.0])
    y = np.array([[[0.0, 1.0], [1e-15, 0.999], [0.2, 1.0 - 1e-15], [np.nan, np.nan]]])
    at_lo, at_hi = cens.censored_mask(y)
    np.testing.assert_array_equal(at_lo[0, :, 0], [True, True, False, False])
    np.testing.assert_array_equal(at_hi[0, :, 1], [True, False, True, False])
    assert not at_lo[..., 1].any() and not at_hi[..., 0].any()  # infinite limits never censor
    # the tolerance is relative to the limit's magnitude
    big = Censoring(lower=1e6)
    lo2, _ = big.censored_mask(np.array([[1e6 + 1e-7], [1e6 + 1e-3]]))
    np.testing.assert_array_equal(lo2[:, 0], [True, False])


def test_clip_then_mask_roundtrip():
    rng = np.random.default_rng(3)
    cens = Censoring(lower=np.array([-0.5, 0.0]), upper=np.array([0.5, np.inf]))
    ystar = rng.standard_normal((50, 20, 2))
    y = cens.clip(ystar)
    at_lo, at_hi = cens.censored_mask(y)
    np.testing.assert_array_equal(at_lo, ystar <= np.array([-0.5, 0.0]))
    np.testing.assert_array_equal(at_hi, ystar >= np.array([0.5, np.inf]))
    cens.check_measurements(y)  # clipped data always passes


def test_check_measurements_rejects_readings_outside_limits():
    cens = Censoring(lower=0.0, upper=1.0)
    cens.check_measurements(np.array([[0.0], [1.0], [np.nan], [0.5]]))  # limits and NaN are fine
    with pytest.raises(ValidationError, match=r"y: measurement -0\.1 .*outside its censoring limits \[0, 1\]"):
        cens.check_measurements(np.array([[0.2], [-0.1]]))
    with pytest.raises(ValidationError, match=r"meas: measurement 1\.5"):
        cens.check_measurements(np.array([[1.5]]), name="meas")


def test_check_channel_and_step_counts():
    Censoring(lower=0.0).check(3, 10)
    Censoring(lower=[0.0]).check(3)  # one limit for all channels
    with pytest.raises(ShapeError, match="censoring limits: expected 2 channel"):
        Censoring(lower=[0.0, 0.0, 0.0]).check(2)
    with pytest.raises(ShapeError, match="time-varying limits have 3 steps, 5 needed"):
        Censoring(lower=np.zeros((3, 1))).check(1, 5)


@pytest.mark.parametrize(
    "kwargs,exc,match",
    [
        (dict(lower=1.0, upper=1.0), ValidationError, "lower/upper: expected lower < upper"),
        (dict(lower=[0.0, 2.0], upper=[1.0, 1.0]), ValidationError, r"lower < upper.*index \(1,\)"),
        (dict(lower=np.nan), ValidationError, "lower: expected finite numbers, found NaN"),
        (dict(upper=[0.0, np.nan]), ValidationError, "upper: expected finite numbers, found NaN"),
        (dict(lower=np.inf), ValidationError, r"lower: \+inf is not a valid lower limit"),
        (dict(upper=-np.inf), ValidationError, "upper: -inf is not a valid upper limit"),
        (dict(lower=[0.0, 1.0], upper=[1.0, 2.0, 3.0]), ShapeError, "lower/upper: shapes"),
        (dict(lower=np.zeros((2, 2, 2))), ShapeError, "lower: expected 0 or 1 or 2 dimension"),
        (dict(lower="abc"), ValidationError, "lower: expected an array of numbers"),
    ],
)
def test_constructor_validation(kwargs, exc, match):
    with pytest.raises(exc, match=match):
        Censoring(**kwargs)


def test_repr_mentions_limits():
    assert "lower=0.0" in repr(Censoring(lower=0.0))


# ---------------------------------------------------------------------------------------------
# multi_region (Miller §6.6; spec 001b §2.6)
# ---------------------------------------------------------------------------------------------
def test_multi_region_stacks_sensors():
    """Example 1 of §6.6: one output, right-censored at 0 and left-censored at 0 -> two channels."""
    base = _sys()
    stacked, cens = multi_region(base, [[(-np.inf, 0.0), (0.0, np.inf)]])
    assert stacked.m == 2 and stacked.n == 1
    np.testing.assert_array_equal(stacked.measurement(1), [[1.0], [1.0]])
    np.testing.assert_array_equal(stacked.measurement_cov(1), np.diag([0.0025, 0.0025]))
    np.testing.assert_array_equal(cens.lower, [-np.inf, 0.0])
    np.testing.assert_array_equal(cens.upper, [0.0, np.inf])
    # dynamics and prior carried over
    np.testing.assert_array_equal(stacked.transition(0), base.transition(0))
    np.testing.assert_array_equal(stacked.process_cov(0), base.process_cov(0))
    np.testing.assert_array_equal(stacked.x0, base.x0)
    np.testing.assert_array_equal(stacked.P0, base.P0)


def test_multi_region_several_outputs_and_noise():
    base = LinearSystem(
        A=np.eye(2), C=[[1.0, 0.0], [0.0, 2.0]], Q=np.eye(2) * 0.01, R=np.diag([0.1, 0.2]), x0=[0.0, 0.0], P0=np.eye(2)
    )
    regions = [[(-1.0, 1.0), (2.0, 3.0), (-np.inf, -2.0)], [(0.0, np.inf)]]
    stacked, cens = multi_region(base, regions, noise_var=[[0.1, 0.3, 0.5], [0.7]])
    assert stacked.m == 4
    np.testing.assert_array_equal(stacked.measurement(1), [[1, 0], [1, 0], [1, 0], [0, 2]])
    np.testing.assert_array_equal(np.diag(stacked.measurement_cov(1)), [0.1, 0.3, 0.5, 0.7])
    np.testing.assert_array_equal(cens.lower, [-1.0, 2.0, -np.inf, 0.0])
    np.testing.assert_array_equal(cens.upper, [1.0, 3.0, -2.0, np.inf])
    # default noise: R_ii for every sensor of output i
    _, _ = multi_region(base, regions)
    stacked2, _ = multi_region(base, regions)
    np.testing.assert_array_equal(np.diag(stacked2.measurement_cov(1)), [0.1, 0.1, 0.1, 0.2])


def test_multi_region_keeps_noise_input_matrix():
    base = LinearSystem(
        A=[[1.0, 1.0], [0.0, 1.0]], C=[[1.0, 0.0]], Q=[[0.04]], R=[[1.0]], x0=[0, 0], P0=np.eye(2), B=[[0.5], [1.0]]
    )
    stacked, _ = multi_region(base, [[(-np.inf, 0.0), (0.0, np.inf)]])
    np.testing.assert_allclose(stacked.process_cov(0), base.process_cov(0), rtol=0, atol=0)


def test_multi_region_keeps_control_inputs():
    """The stacked model keeps Bu, and D gets one row per sensor like C (a controlled plant stays controlled)."""
    base = LinearSystem(
        A=[[1.0, 0.1], [0.0, 1.0]],
        C=[[1.0, 0.0], [0.0, 1.0]],
        Q=0.01 * np.eye(2),
        R=np.diag([0.1, 0.2]),
        x0=[0, 0],
        P0=np.eye(2),
        Bu=[[0.0], [0.1]],
        D=[[0.5], [-1.0]],
    )
    stacked, _ = multi_region(base, [[(-np.inf, 0.0), (0.0, np.inf)], [(-1.0, 1.0)]])
    assert stacked.p == 1
    np.testing.assert_array_equal(stacked.Bu.at(1), [[0.0], [0.1]])
    np.testing.assert_array_equal(stacked.D.at(1), [[0.5], [0.5], [-1.0]])
    bx, dy = stacked.input_effect(1, np.array([2.0]))
    np.testing.assert_array_equal(bx, [0.0, 0.2])
    np.testing.assert_array_equal(dy, [1.0, 1.0, -2.0])
    only_bu = LinearSystem(A=np.eye(1), C=[[1.0]], Q=[[0.01]], R=[[0.1]], x0=[0], P0=[[1.0]], Bu=[[1.0]])
    st2, _ = multi_region(only_bu, [[(-np.inf, 0.0), (0.0, np.inf)]])
    assert st2.p == 1 and st2.D is None


@pytest.mark.parametrize(
    "regions,match",
    [
        ([], r"regions: expected one list of windows per output \(1\)"),
        ([[]], r"regions\[0\]: expected at least one"),
        ([[(0.0,)]], r"regions\[0\]\[0\]: expected a \(lower, upper\) pair"),
    ],
)
def test_multi_region_validation(regions, match):
    with pytest.raises(ShapeError, match=match):
        multi_region(_sys(), regions)


def test_multi_region_rejects_bad_windows_and_time_varying_R():
    with pytest.raises(ValidationError, match="lower < upper"):
        multi_region(_sys(), [[(1.0, 0.0)]])
    tv = LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.01]], R=np.full((5, 1, 1), 0.1), x0=[0.0], P0=[[1.0]])
    with pytest.raises(ShapeError, match="system: multi_region needs time-invariant C and R"):
        multi_region(tv, [[(0.0, np.inf)]])
