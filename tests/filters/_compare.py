"""Comparisons shared by the kernel tests (compiled path against the numpy path)."""

from __future__ import annotations

import numpy as np


def assert_same(a, b, rtol=1e-12):
    """Equal to rounding relative to the array's scale; NaN exactly where the reference has NaN; booleans equal."""
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape
    if b.dtype == bool:
        np.testing.assert_array_equal(a, b)
        return
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    scale = max(1.0, float(np.nanmax(np.abs(b)))) if np.isfinite(b).any() else 1.0
    np.testing.assert_allclose(a, b, rtol=rtol, atol=rtol * scale)


def assert_results_equal(r1, r2, rtol=1e-12, fields=("mean", "cov", "pred_mean", "pred_cov")):
    """Two FilterResults equal to rounding (:func:`assert_same`) in ``fields`` and in every extra."""
    for f in fields:
        assert_same(getattr(r1, f), getattr(r2, f), rtol)
    assert r1.extras.keys() == r2.extras.keys()
    for key in r1.extras:
        assert_same(r1.extras[key], r2.extras[key], rtol)
