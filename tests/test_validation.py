"""Input validation: every public check raises ValidationError/ShapeError naming the argument.

Module-specific checks are also exercised next to their modules (filters, simulate,
channels); this file covers the shared helpers and the ``LinearSystem`` constructor, and
the checks at the filter boundary that apply to every filter.
"""

from __future__ import annotations

import numpy as np
import pytest

from tobitkf import (
    Censoring,
    DroppingKalmanFilter,
    KalmanFilter,
    LinearSystem,
    ShapeError,
    TobitKalmanFilter,
    ValidationError,
)
from tobitkf._validation import TimeSequence, as_float_array, check_finite, check_option, check_probability, check_psd


def test_error_hierarchy():
    assert issubclass(ShapeError, ValidationError) and issubclass(ValidationError, ValueError)


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------
def test_as_float_array():
    out = as_float_array([1, 2], "v", ndim=1)
    assert out.dtype == np.float64
    with pytest.raises(ShapeError, match=r"v: expected 2 dimension\(s\), got shape \(2,\)"):
        as_float_array([1, 2], "v", ndim=2)
    with pytest.raises(ShapeError, match=r"v: expected 0 or 2 dimension\(s\), got shape \(2,\)"):
        as_float_array([1, 2], "v", ndim=(0, 2))
    with pytest.raises(ValidationError, match="v: expected finite numbers, found NaN"):
        as_float_array([1, np.nan], "v")
    with pytest.raises(ValidationError, match="v: expected finite numbers, found inf"):
        as_float_array([1, -np.inf], "v")
    with pytest.raises(ValidationError, match="v: expected an array of numbers, got str"):
        as_float_array("abc", "v")
    with pytest.raises(ValidationError, match="v: expected an array of numbers"):
        as_float_array([[1, 2], [3]], "v")
    assert np.isnan(as_float_array([np.nan], "v", allow_nan=True)).all()
    assert np.isinf(as_float_array([np.inf], "v", allow_inf=True)).all()
    check_finite(np.array([1.0]), "w")


def test_check_option():
    assert check_option("a", "mode", ("a", "b")) == "a"
    with pytest.raises(ValidationError, match="mode: expected one of 'a', 'b', got 'c'"):
        check_option("c", "mode", ("a", "b"))


@pytest.mark.parametrize(
    "value,kw,ok",
    [
        (0.0, {}, True),
        (1.0, {}, True),
        (0.5, {}, True),
        (-0.1, {}, False),
        (1.1, {}, False),
        (0.0, {"open_low": True}, False),
        (1.0, {"open_high": True}, False),
        ([0.2, 0.9], {}, True),
        ([0.2, 1.9], {}, False),
    ],
)
def test_check_probability(value, kw, ok):
    if ok:
        check_probability(value, "p", **kw)
    else:
        with pytest.raises(ValidationError, match=r"p: expected probabilities in [\[(]0, 1[\])]"):
            check_probability(value, "p", **kw)
    with pytest.raises(ValidationError, match="p: expected finite numbers, found NaN"):
        check_probability(np.nan, "p")


def test_check_psd():
    check_psd(np.eye(2), "P")
    check_psd(np.zeros((2, 2)), "P")  # PSD, singular
    check_psd(np.stack([np.eye(2), 2 * np.eye(2)]), "P")  # batched
    with pytest.raises(ValidationError, match="P: expected a symmetric matrix"):
        check_psd(np.array([[1.0, 0.5], [0.0, 1.0]]), "P")
    with pytest.raises(ValidationError, match="P: expected a positive semi-definite matrix, smallest eigenvalue -1"):
        check_psd(np.array([[1.0, 0.0], [0.0, -1.0]]), "P")
    with pytest.raises(ValidationError, match="P: expected a positive semi-definite"):
        check_psd(np.array([[1.0, 2.0], [2.0, 1.0]]), "P")  # symmetric, indefinite
    with pytest.raises(ValidationError, match="P: expected a positive definite matrix"):
        check_psd(np.zeros((2, 2)), "P", strict=True)
    with pytest.raises(ShapeError, match=r"P: expected a square matrix \(\.\.\., n, n\), got shape \(2, 3\)"):
        check_psd(np.ones((2, 3)), "P")
    # rounding-level asymmetry is accepted
    M = np.array([[1.0, 0.3], [0.3 + 1e-15, 1.0]])
    check_psd(M, "P")


def test_time_sequence():
    ts = TimeSequence(np.stack([np.eye(2) * k for k in range(3)]), "M", offset=1)
    assert ts.varying and ts.steps == 3 and ts.core_shape == (2, 2)
    np.testing.assert_array_equal(ts.at(1), np.zeros((2, 2)))
    np.testing.assert_array_equal(ts.at(3), 2 * np.eye(2))
    with pytest.raises(ShapeError, match=r"M: time-indexed array has 3 steps, step k=4 \(index 3\) requested"):
        ts.at(4)
    with pytest.raises(ShapeError, match="M: time-indexed array has 3 steps, 4 needed"):
        ts.check_horizon(4)
    fn = TimeSequence(lambda k: np.eye(2) if k < 3 else np.eye(3), "F")
    with pytest.raises(ShapeError, match=r"F\(3\): expected shape \(2, 2\), got \(3, 3\)"):
        fn.at(3)
    with pytest.raises(ShapeError, match=r"F\(3\): expected shape \(2, 2\)"):
        fn.validate_all(5)
    with pytest.raises(ShapeError, match=r"F\(0\): expected 2 dimension"):
        TimeSequence(lambda k: np.ones(2), "F")
    with pytest.raises(ValidationError, match=r"Q\(0\): expected a positive semi-definite"):
        TimeSequence(lambda k: -np.eye(2), "Q", psd=True)
    with pytest.raises(ValidationError, match=r"Q: expected a symmetric matrix"):
        TimeSequence(np.stack([np.eye(2), [[1.0, 1.0], [0.0, 1.0]]]), "Q", psd=True)


# ---------------------------------------------------------------------------------------------
# LinearSystem constructor
# ---------------------------------------------------------------------------------------------
GOOD = dict(A=np.eye(2), C=np.ones((1, 2)), Q=np.eye(2), R=np.eye(1), x0=np.zeros(2), P0=np.eye(2))


@pytest.mark.parametrize(
    "change,exc,match",
    [
        (dict(A=np.ones((2, 3))), ShapeError, r"A: expected a square \(n, n\) matrix, got \(2, 3\)"),
        (dict(A=np.ones(2)), ShapeError, r"A: expected 2 or 3 dimension"),
        (dict(A=[[1.0, np.nan], [0.0, 1.0]]), ValidationError, "A: expected finite numbers, found NaN"),
        (dict(A=lambda k: np.full((2, 2), np.inf)), ValidationError, r"A\(0\): expected finite numbers, found inf"),
        (dict(C=np.ones((1, 3))), ShapeError, r"C: expected \(m, 2\) to match A of size n=2, got \(1, 3\)"),
        (dict(C=[[np.inf, 0.0]]), ValidationError, "C: expected finite numbers, found inf"),
        (dict(R=np.eye(2)), ShapeError, r"R: expected \(1, 1\) to match C with m=1 rows, got \(2, 2\)"),
        (dict(R=[[-1.0]]), ValidationError, "R: expected a positive semi-definite matrix"),
        (dict(R=[[np.nan]]), ValidationError, "R: expected finite numbers, found NaN"),
        (dict(Q=np.eye(3)), ShapeError, r"Q: expected \(2, 2\) \(q = n\), got \(3, 3\)"),
        (dict(Q=[[1.0, 0.5], [0.0, 1.0]]), ValidationError, "Q: expected a symmetric matrix"),
        (dict(Q=[[1.0, 2.0], [2.0, 1.0]]), ValidationError, "Q: expected a positive semi-definite matrix"),
        (dict(Q=np.stack([np.eye(2), -np.eye(2)])), ValidationError, "Q: expected a positive semi-definite"),
        (dict(B=np.ones((3, 1))), ShapeError, r"B: expected \(2, q\), got \(3, 1\)"),
        (dict(B=np.ones((2, 1))), ShapeError, r"Q: expected \(1, 1\) \(q = columns of B\), got \(2, 2\)"),
        (dict(Bu=np.ones((3, 1))), ShapeError, r"Bu: expected \(2, p\), got \(3, 1\)"),
        (dict(Bu=np.ones((2, 1)), D=np.ones((1, 2))), ShapeError, r"D: expected \(1, 1\), got \(1, 2\)"),
        (dict(D=np.ones((2, 1))), ShapeError, r"D: expected \(1, p\), got \(2, 1\)"),
        (dict(x0=np.zeros(3)), ShapeError, r"x0: expected shape \(2,\), got \(3,\)"),
        (dict(x0=np.zeros((2, 1))), ShapeError, r"x0: expected 1 dimension"),
        (dict(x0=[0.0, np.nan]), ValidationError, "x0: expected finite numbers, found NaN"),
        (dict(P0=np.eye(3)), ShapeError, r"P0: expected shape \(2, 2\), got \(3, 3\)"),
        (dict(P0=[[1.0, 0.0], [0.0, -1.0]]), ValidationError, "P0: expected a positive semi-definite matrix"),
        (dict(P0=[[1.0, 0.2], [0.1, 1.0]]), ValidationError, "P0: expected a symmetric matrix"),
        (dict(P0=[[np.nan, 0.0], [0.0, 1.0]]), ValidationError, "P0: expected finite numbers, found NaN"),
    ],
)
def test_linear_system_rejects(change, exc, match):
    with pytest.raises(exc, match=match):
        LinearSystem(**{**GOOD, **change})


# ---------------------------------------------------------------------------------------------
# checks at the filter boundary, for every filter
# ---------------------------------------------------------------------------------------------
SYS = LinearSystem(**GOOD)
FILTERS = [
    ("kf", lambda: KalmanFilter(SYS)),
    ("ikf", lambda: DroppingKalmanFilter(SYS, Censoring(lower=-5.0))),
    ("tkf", lambda: TobitKalmanFilter(SYS, Censoring(lower=-5.0))),
]


@pytest.mark.parametrize("name,make", FILTERS, ids=[f[0] for f in FILTERS])
def test_filter_boundary_checks(name, make):
    f = make()
    y = np.zeros((4, 1))
    with pytest.raises(ShapeError, match=r"y: expected last axis of length m=1"):
        f.filter(np.zeros((4, 2)))
    with pytest.raises(ShapeError, match=r"y: expected \(\.\.\., T, 1\)"):
        f.filter(np.zeros(4))
    with pytest.raises(ShapeError, match="y: expected at least one time step"):
        f.filter(np.zeros((0, 1)))
    with pytest.raises(ValidationError, match="y: expected finite numbers, found inf"):
        f.filter(np.array([[0.0], [np.inf]]))
    with pytest.raises(ValidationError, match="y: expected an array of numbers"):
        f.filter("data")
    with pytest.raises(ShapeError, match="u: the system has no control input"):
        f.filter(y, u=np.zeros((4, 1)))
    with pytest.raises(ShapeError, match="x0/P0"):
        f.filter(y, x0=np.zeros(3))
    with pytest.raises(ShapeError, match="x0/P0"):
        f.filter(y, P0=np.eye(3))
    with pytest.raises(ValidationError, match="x0: expected finite numbers, found NaN"):
        f.filter(y, x0=[np.nan, 0.0])
    with pytest.raises(ValidationError, match="P0: expected a positive semi-definite matrix"):
        f.filter(y, P0=-np.eye(2))
    with pytest.raises(ValidationError, match="P0: expected a symmetric matrix"):
        f.filter(y, P0=[[1.0, 0.5], [0.0, 1.0]])


@pytest.mark.parametrize("name,make", FILTERS[1:], ids=[f[0] for f in FILTERS[1:]])
def test_measurement_outside_limits(name, make):
    with pytest.raises(ValidationError, match=r"y: measurement -6 .* outside its censoring limits \[-5, inf\]"):
        make().filter(np.array([[0.0], [-6.0]]))


def test_filter_inputs_batch_mismatch():
    sys = LinearSystem(**{**GOOD, "Bu": np.ones((2, 1))})
    with pytest.raises(ShapeError, match=r"u: expected \(T, p\) or the batch shape of y"):
        KalmanFilter(sys).filter(np.zeros((3, 4, 1)), u=np.zeros((2, 4, 1)))
    with pytest.raises(ShapeError, match=r"u: expected \(\.\.\., 4, 1\)"):
        TobitKalmanFilter(sys, Censoring()).filter(np.zeros((4, 1)), u=np.zeros((5, 1)))


@pytest.mark.parametrize("size", [1, 2, 4, 5, 9])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, None])
def test_check_finite_small_and_large_arrays_agree(size, bad):
    """Up to 4 entries take a Python-float route (the online step's reading); the verdict and the message
    are those of the array route."""
    arr = np.arange(float(size))
    if bad is not None:
        arr[-1] = bad
    for allow_nan in (False, True):
        for allow_inf in (False, True):
            expect = None
            if bad is not None and np.isnan(bad) and not allow_nan:
                expect = "found NaN"
            elif bad is not None and np.isinf(bad) and not allow_inf:
                expect = "found inf"
            if expect is None:
                check_finite(arr, "y", allow_nan=allow_nan, allow_inf=allow_inf)
            else:
                with pytest.raises(ValidationError, match=f"y: expected finite numbers, {expect}"):
                    check_finite(arr, "y", allow_nan=allow_nan, allow_inf=allow_inf)


@pytest.mark.parametrize("size", [2, 4, 5])
@pytest.mark.parametrize("order", ["nan-first", "inf-first"])
def test_check_finite_with_nan_and_inf_names_what_is_refused(size, order):
    """A reading with both a NaN and an inf: the route of up to 4 entries (one pass for the passing verdict,
    then the checks that name what they found) refuses what the array route refuses, NaN before inf."""
    arr = np.zeros(size)
    arr[:2] = (np.nan, np.inf) if order == "nan-first" else (-np.inf, np.nan)
    with pytest.raises(ValidationError, match="found NaN"):
        check_finite(arr, "y")
    with pytest.raises(ValidationError, match="found NaN"):
        check_finite(arr, "y", allow_inf=True)
    with pytest.raises(ValidationError, match="found inf"):
        check_finite(arr, "y", allow_nan=True)
    check_finite(arr, "y", allow_nan=True, allow_inf=True)


def test_byte_swapped_float64_takes_the_general_route():
    """The cheap test of the common case is the native float64 dtype object; a byte-swapped float64 array
    (another descriptor) is converted by the general route, and its NaN or inf still refused."""
    swapped = np.array([0.5, -2.0], dtype=">f8")
    out = as_float_array(swapped, "y")
    assert out.dtype == np.float64 and out.dtype.isnative
    np.testing.assert_array_equal(out, [0.5, -2.0])
    with pytest.raises(ValidationError, match="found NaN"):
        as_float_array(np.array([np.nan], dtype=">f8"), "y")
    with pytest.raises(ValidationError, match="found inf"):
        check_finite(np.array([np.inf], dtype=">f8"), "y")


@pytest.mark.parametrize("shape", [(1, 1), (1, 2), (2, 2), (3, 2)])
def test_check_reading_float_route_agrees(shape):
    """One reading of up to 4 entries is checked on Python floats: same verdict and message as the arrays."""
    import tobitkf as tk

    m = shape[-1]
    cens = tk.Censoring(lower=[0.0] * m, upper=[1.0] * m)
    ok = np.full(shape, 0.5)
    ok[0, 0] = np.nan  # missing: not checked
    cens.check_reading(ok, 3)
    cens.check_reading(ok, 3)  # the cached bounds
    for value in (-1e-3, 1.0 + 1e-3):
        bad = np.full(shape, 0.5)
        bad[-1, -1] = value
        with pytest.raises(ValidationError, match=f"channel {m - 1} lies outside its censoring limits"):
            cens.check_reading(bad, 3)
    edge = np.full(shape, 1.0 + 1e-10)  # inside the tolerance band of the limit
    cens.check_reading(edge, 3)
