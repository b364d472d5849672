r"""The Kalman filter's and the Tobit Kalman filter's entries into the one compiled loop.

:func:`kalman_loop` and :func:`tobit_loop` take only the arrays their family uses and call
:func:`~tobitkf.filters._compiled_loop.compiled_loop` with the family's code and empty arrays for the rest (made
here, in compiled code). Why not call the loop directly from Python: numba unboxes every argument on every call
(~0.25 µs per array), and the loop's 29 arguments made one online step of a one-run KF 25 % slower than the
former Kalman-filter loop with its 15 (measured in one process, thread CPU time: 12.1 against 9.6 µs per step,
n = 2, m = 1, on a loaded machine); these entries take 14 and 21. The online ``step`` of one reading enters by :func:`kalman_step` and :func:`tobit_step`
(6 and 8 arguments): the constant matrices flattened into one array (built once per estimator), the unused
outputs made here.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ._compiled_loop import KALMAN, TOBIT, compiled_loop
from ._compiled_soa import kalman_entry, tobit_entry  # noqa: F401 - the choice between the runs-vectorised step and the loop

__all__ = ["kalman_loop", "tobit_loop", "kalman_step", "tobit_step"]


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
    :data:`~tobitkf.filters._compiled_tobit.NOISE_CODES`; the other arguments as there."""
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


@njit(cache=True, error_model="numpy", inline="always")
def _unpack(consts, n, m, q):
    """``A``, ``Qd`` (n, n), the rows ``H`` (1, m, n) and ``par`` (1, m, q) from the flat constants of a step entry
    (in that order), and what follows them."""
    nn = n * n
    e = 2 * nn + m * n
    A = consts[0:nn].reshape((n, n))
    Qd = consts[nn : 2 * nn].reshape((n, n))
    H = consts[2 * nn : e].reshape((1, m, n))
    par = consts[e : e + m * q]
    return A, Qd, H, par, consts[e + m * q :]


@njit(cache=True, error_model="numpy", nogil=True)
def kalman_step(y, consts, x0, P0, x_last, P_last):
    """One step of :func:`kalman_loop` (the online ``step``): ``y`` (N, m), ``consts`` the flat ``A, Qd, C, R,
    joseph`` (:func:`~tobitkf.filters.kalman.step_constants`), ``x0`` (N, n), ``P0`` (N or 1, n, n); writes the
    new state into ``x_last``, ``P_last``."""
    N, m = y.shape
    n = x0.shape[1]
    Pn = P0.shape[0]
    A, Qd, H, par, rest = _unpack(consts, n, m, m)
    e_m, e_c = np.empty((N, 0, n)), np.empty((Pn, 0, n, n))
    kalman_loop(
        y.reshape((N, 1, m)),
        A,
        Qd,
        H,
        par.reshape((1, m, m)),
        rest[0] != 0.0,
        x0,
        P0,
        e_m,
        e_c,
        e_m,
        e_c,
        x_last,
        P_last,
    )


@njit(cache=True, error_model="numpy", nogil=True)
def tobit_step(y, consts, lohi, x0, P0, out2, x_last, P_last):
    """One step of :func:`tobit_loop` without inputs (the online ``step``): ``y`` (N, m), ``consts`` the flat ``A,
    Qd, C, sigma, noise_code, joseph`` (:func:`~tobitkf.filters.kalman.step_constants`), ``lohi`` (2, 1, m) the
    step's limits, ``x0`` (N, n), ``P0`` (N, n, n); writes P(uncensored) and E[y] into ``out2`` (2, N, m), the new
    state into ``x_last``, ``P_last``."""
    N, m = y.shape
    n = x0.shape[1]
    A, Qd, H, sigma, rest = _unpack(consts, n, m, 1)
    e_m, e_c = np.empty((N, 0, n)), np.empty((N, 0, n, n))
    tobit_loop(
        y.reshape((N, 1, m)),
        A,
        Qd,
        H,
        sigma.reshape((1, m)),
        lohi[0],
        lohi[1],
        np.empty((N, 0, n)),
        np.empty((N, 0, m)),
        int(rest[0]),
        rest[1] != 0.0,
        x0,
        P0,
        e_m,
        e_c,
        e_m,
        e_c,
        out2[0].reshape((N, 1, m)),
        out2[1].reshape((N, 1, m)),
        x_last,
        P_last,
    )
