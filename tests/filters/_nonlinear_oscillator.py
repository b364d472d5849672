"""The numba-compiled models shared by the compiled nonlinear filters' tests (import after
``pytest.importorskip("numba")``): a two-state oscillator read through a sine and a cube, the same driven by an
input, and analytic Jacobians. One set of compiled functions serves every module, so that the loops specialised
on them are compiled once per process."""

from __future__ import annotations

import numba
import numpy as np


@numba.njit
def f_osc(x, k):
    out = np.empty(x.shape)
    out[..., 0] = x[..., 0] + 0.1 * x[..., 1]
    out[..., 1] = x[..., 1] - 0.1 * np.sin(x[..., 0]) - 0.02 * x[..., 1]
    return out


@numba.njit
def h_osc(x, k):
    out = np.empty(x.shape[:-1] + (2,))
    out[..., 0] = np.sin(x[..., 0])
    out[..., 1] = 0.5 * x[..., 1] + 0.1 * x[..., 0] ** 3
    return out


@numba.njit
def f_in(x, k, u):
    out = np.empty(x.shape)
    out[..., 0] = x[..., 0] + 0.1 * x[..., 1]
    out[..., 1] = x[..., 1] - 0.1 * np.sin(x[..., 0]) + 0.1 * u[..., 0]
    return out


@numba.njit
def F_in(x, k, u):
    out = np.zeros(x.shape + (2,))
    out[..., 0, 0] = 1.0
    out[..., 0, 1] = 0.1
    out[..., 1, 0] = -0.1 * np.cos(x[..., 0])
    out[..., 1, 1] = 1.0
    return out


@numba.njit
def H_osc(x, k):
    out = np.zeros(x.shape[:-1] + (2, 2))
    out[..., 0, 0] = np.cos(x[..., 0])
    out[..., 1, 0] = 0.3 * x[..., 0] ** 2
    out[..., 1, 1] = 0.5
    return out
