r"""The Kalman filter's and the Tobit Kalman filter's entries into the one compiled loop.

:func:`kalman_loop` and :func:`tobit_loop` take only the arrays their family uses and call
:func:`~tobitkf.filters._compiled_loop.compiled_loop` with the family's code and empty arrays for the rest (made
here, in compiled code). Why not call the loop directly from Python: numba unboxes every argument on every call
(~0.25 µs per array), and the loop's 29 arguments made one online step of a one-run KF 25 % slower than the
former Kalman-filter loop with its 15 (measured in one process, thread CPU time: 12.1 against 9.6 µs per step,
n = 2, m = 1, on a loaded machine); these entries take 14 and 21.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ._compiled_loop import KALMAN, TOBIT, compiled_loop

__all__ = ["kalman_loop", "tobit_loop"]


@njit(cache=True, error_model="numpy", nogil=True)
def kalman_loop(y, A, Qd, H, par, joseph, x0, P0, means, covs, pmeans, pcovs, x_last, P_last):
    """:func:`~tobitkf.filters._compiled_loop.compiled_loop` for the Kalman filter: ``H`` (1, m, n) the rows C,
    ``par`` (1, m, m) the noise covariance R; the other arguments as there."""
    N, _, m = y.shape
    n = A.shape[0]
    zero = N - N  # the integer arguments as run-time int64, not literals: one specialisation of the loop
    compiled_loop(
        zero + KALMAN,
        y,
        np.empty((N, 0, m), dtype=np.int8),
        A.reshape((1, 1) + A.shape),  # shared by the runs and the steps
        Qd.reshape((1, 1) + Qd.shape),
        H,
        np.empty((1, m, 0, n)),
        np.empty((1, 1, m)),
        np.empty((1, 1, m)),
        np.empty((1, 1, m)),
        par,
        zero,
        zero + 1,
        zero,
        joseph,
        np.empty((N, 0, n)),
        np.empty((N, 0, m)),
        x0,
        P0,
        means,
        covs,
        pmeans,
        pcovs,
        np.empty((N, 0, m)),
        np.empty((N, 0, m)),
        np.empty((N, 0)),
        np.empty((N, 0, m, 0)),
        x_last,
        P_last,
    )


@njit(cache=True, error_model="numpy", nogil=True)
def tobit_loop(
    y, A, Qd, H, sigma, lo, hi, bu, du, noise_code, joseph, x0, P0, means, covs, pmeans, pcovs, pu, ey, x_last, P_last
):
    """:func:`~tobitkf.filters._compiled_loop.compiled_loop` for the Tobit Kalman filter: ``H`` (1, m, n) the rows
    C, ``sigma`` (1, m) the noise standard deviations, ``lo``/``hi`` (TL, m) the limits, ``noise_code`` of
    :data:`~tobitkf.filters._kernels.NOISE_CODES`; the other arguments as there."""
    N, _, m = y.shape
    n = A.shape[0]
    zero = N - N  # the integer arguments as run-time int64, not literals: one specialisation of the loop
    compiled_loop(
        zero + TOBIT,
        y,
        np.empty((N, 0, m), dtype=np.int8),
        A.reshape((1, 1) + A.shape),  # shared by the runs and the steps
        Qd.reshape((1, 1) + Qd.shape),
        H,
        np.empty((1, m, 0, n)),
        sigma.reshape((1,) + sigma.shape),
        lo.reshape((1,) + lo.shape),
        hi.reshape((1,) + hi.shape),
        np.empty((1, m, 0)),
        zero,
        zero + 1,
        noise_code,
        joseph,
        bu,
        du,
        x0,
        P0,
        means,
        covs,
        pmeans,
        pcovs,
        pu,
        ey,
        np.empty((N, 0)),
        np.empty((N, 0, m, 0)),
        x_last,
        P_last,
    )
