r"""The Kalman filter's, the Tobit Kalman filter's and the fading Tobit Kalman filter's entries into the one
compiled loop.

:func:`kalman_loop` and :func:`tobit_loop` take only the arrays their family uses and call
:func:`~tobitkf.filters._compiled_loop.compiled_loop` through :func:`loop_call`, which makes the arrays the family
does not use (here, in compiled code). Why not call the loop directly from Python: numba unboxes every argument on
every call (~0.25 µs per array), and the loop's 29 arguments made one online step of a one-run KF 25 % slower than
the former Kalman-filter loop with its 15 (measured in one process, thread CPU time: 12.1 against 9.6 µs per step,
n = 2, m = 1, on a loaded machine); these entries take 14 and 21. The online ``step`` of one reading enters by
:func:`kalman_step` and :func:`tobit_step` (6 and 8 arguments), the fading TKF's by :func:`fading_step` (11; its
``filter`` calls the loop directly): the constant matrices flattened into one array (built once per estimator), the
unused outputs made here.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ._compiled_loop import FADING_KIND, KALMAN_KIND, PROTOCOL_TKF_KIND, TOBIT_KIND, compiled_loop
from ._compiled_soa import kalman_entry, tobit_entry  # noqa: F401 - the choice between the runs-vectorised step and the loop

__all__ = ["loop_call", "kalman_loop", "tobit_loop", "kalman_step", "tobit_step", "protocol_tkf_step", "fading_step"]


@njit(cache=True, error_model="numpy", nogil=True)
def loop_call(
    family,
    y,
    A,
    Qd,
    H,
    x0,
    P0,
    x_last,
    P_last,
    cls=None,
    F=None,
    r=None,
    lo=None,
    hi=None,
    par=None,
    J=None,
    npass=None,
    noise_code=None,
    joseph=None,
    bu=None,
    du=None,
    means=None,
    covs=None,
    pmeans=None,
    pcovs=None,
    pu=None,
    ey=None,
    ll=None,
    comp=None,
):
    """:func:`~tobitkf.filters._compiled_loop.compiled_loop` (its arguments, by the same names) with what a family
    does not give made here: the arrays the loop reads as absent (``cls`` (N, 0, m) int8, ``F`` (1, m, 0, n_x),
    ``r``/``lo``/``hi`` (1, 1, m), ``par`` (1, m, 0), ``bu`` (N, 0, n), ``du`` (N, 0, m); outputs with a T axis
    of length 0: not written), ``J`` = 0, ``npass`` = 1, ``noise_code`` = 0, ``joseph`` False. ``family`` a kind
    (:func:`~tobitkf.filters._compiled_moments.kind`): each family's entries share that family's version of the
    loop, which holds its update alone; the integers go to the loop as run-time int64 (a module constant is a
    literal to numba), so that the entries of a family share one specialisation."""
    N, _, m = y.shape
    nx, n = x0.shape[1], A.shape[2]
    zero = N - N
    cls = np.empty((N, 0, m), dtype=np.int8) if cls is None else cls
    F = np.empty((1, m, 0, nx)) if F is None else F
    r = np.empty((1, 1, m)) if r is None else r
    lo = np.empty((1, 1, m)) if lo is None else lo
    hi = np.empty((1, 1, m)) if hi is None else hi
    par = np.empty((1, m, 0)) if par is None else par
    J = zero if J is None else zero + J
    npass = zero + 1 if npass is None else zero + npass
    noise_code = zero if noise_code is None else zero + noise_code
    joseph = N < 0 if joseph is None else joseph
    bu = np.empty((N, 0, n)) if bu is None else bu
    du = np.empty((N, 0, m)) if du is None else du
    means = np.empty((N, 0, n)) if means is None else means
    covs = np.empty((N, 0, n, n)) if covs is None else covs
    pmeans = np.empty((N, 0, n)) if pmeans is None else pmeans
    pcovs = np.empty((N, 0, n, n)) if pcovs is None else pcovs
    pu = np.empty((N, 0, m)) if pu is None else pu
    ey = np.empty((N, 0, m)) if ey is None else ey
    ll = np.empty((N, 0)) if ll is None else ll
    comp = np.empty((N, 0, m, J)) if comp is None else comp
    compiled_loop(
        family, y, cls, A, Qd, H, F, r, lo, hi, par, J, npass, noise_code, joseph, bu, du, x0, P0,
        means, covs, pmeans, pcovs, pu, ey, ll, comp, x_last, P_last,
    )  # fmt: skip


@njit(cache=True, error_model="numpy", nogil=True)
def kalman_loop(y, A, Qd, H, par, joseph, x0, P0, means, covs, pmeans, pcovs, x_last, P_last):
    """:func:`~tobitkf.filters._compiled_loop.compiled_loop` for the Kalman filter: ``H`` (1, m, n) the rows C,
    ``par`` (1, m, m) the noise covariance R; the other arguments as there."""
    loop_call(
        KALMAN_KIND, y, A.reshape((1, 1) + A.shape), Qd.reshape((1, 1) + Qd.shape), H, x0, P0, x_last, P_last,
        par=par, joseph=joseph, means=means, covs=covs, pmeans=pmeans, pcovs=pcovs,
    )  # fmt: skip


@njit(cache=True, error_model="numpy", nogil=True)
def tobit_loop(
    y, A, Qd, H, sigma, lo, hi, bu, du, noise_code, joseph, x0, P0, means, covs, pmeans, pcovs, pu, ey, x_last, P_last
):
    """:func:`~tobitkf.filters._compiled_loop.compiled_loop` for the Tobit Kalman filter: ``H`` (1, m, n) the rows
    C, ``sigma`` (1, m) the noise standard deviations, ``lo``/``hi`` (TL, m) the limits, ``noise_code`` of
    :data:`~tobitkf.filters._compiled_tobit.NOISE_CODES`; the other arguments as there."""
    loop_call(
        TOBIT_KIND, y, A.reshape((1, 1) + A.shape), Qd.reshape((1, 1) + Qd.shape), H, x0, P0, x_last, P_last,
        r=sigma.reshape((1,) + sigma.shape), lo=lo.reshape((1,) + lo.shape), hi=hi.reshape((1,) + hi.shape),
        noise_code=noise_code, joseph=joseph, bu=bu, du=du, means=means, covs=covs, pmeans=pmeans, pcovs=pcovs,
        pu=pu, ey=ey,
    )  # fmt: skip


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
    """One step of the Kalman filter through :func:`loop_call` (the online ``step``): ``y`` (N, m), ``consts`` the
    flat ``A, Qd, C, R, joseph`` (:func:`~tobitkf.filters.kalman.step_constants`), ``x0`` (N, n), ``P0`` (N or 1,
    n, n); writes the new state into ``x_last``, ``P_last``."""
    N, m = y.shape
    n = x0.shape[1]
    A, Qd, H, par, rest = _unpack(consts, n, m, m)
    loop_call(
        KALMAN_KIND, y.reshape((N, 1, m)), A.reshape((1, 1, n, n)), Qd.reshape((1, 1, n, n)), H, x0, P0, x_last, P_last,
        par=par.reshape((1, m, m)), joseph=rest[0] != 0.0,
    )  # fmt: skip


@njit(cache=True, error_model="numpy", nogil=True)
def tobit_step(y, consts, lohi, x0, P0, out2, x_last, P_last):
    """One step of the Tobit Kalman filter without inputs through :func:`loop_call` (the online ``step``): ``y``
    (N, m), ``consts`` the flat ``A, Qd, C, sigma, noise_code, joseph``
    (:func:`~tobitkf.filters.kalman.step_constants`), ``lohi`` (2, 1, m) the step's limits, ``x0`` (N, n), ``P0``
    (N, n, n); writes P(uncensored) and E[y] into ``out2`` (2, N, m), the new state into ``x_last``, ``P_last``."""
    N, m = y.shape
    n = x0.shape[1]
    A, Qd, H, sigma, rest = _unpack(consts, n, m, 1)
    loop_call(
        TOBIT_KIND, y.reshape((N, 1, m)), A.reshape((1, 1, n, n)), Qd.reshape((1, 1, n, n)), H, x0, P0, x_last, P_last,
        r=sigma.reshape((1, 1, m)), lo=lohi[0].reshape((1, 1, m)), hi=lohi[1].reshape((1, 1, m)),
        noise_code=int(rest[0]), joseph=rest[1] != 0.0, pu=out2[0].reshape((N, 1, m)), ey=out2[1].reshape((N, 1, m)),
    )  # fmt: skip


@njit(cache=True, error_model="numpy", nogil=True)
def protocol_tkf_step(y, cls, consts, row, x0, P0, comp, x_last, P_last):
    """One step of the protocol Tobit Kalman filter through the loop (the online ``step``, code
    :data:`~tobitkf.filters._compiled_loop.PROTOCOL_TKF`): ``y`` (N, 1, 1), ``cls`` (N, 1, 1) int8 (1: γ = 1),
    ``consts`` the flat ``A, Qd`` (n, n), τ, the failure-term code and the Joseph flag (built once per estimator),
    ``row`` the scheduled sensor's flat :math:`\\mathbf H`, :math:`\\mathcal C_h` (n_ξ each), :math:`\\mathcal R_h`,
    :math:`\\bar\\Lambda_h`, :math:`\\check\\Lambda_h` and 0, ``x0`` (N, n_ξ), ``P0`` (N or 1, n_ξ, n_ξ); writes the
    step's extras into ``comp`` (N, 1, 1, 7 + 2 n_ξ), the new state into ``x_last``, ``P_last``. Returns whether
    every variance of ``P_last`` is finite (the check the numpy step would otherwise make in Python)."""
    N = y.shape[0]
    nx = x0.shape[1]
    nn = (consts.shape[0] - 3) // 2
    n = int(np.sqrt(nn) + 0.5)
    loop_call(
        PROTOCOL_TKF_KIND, y, consts[0:nn].reshape((1, 1, n, n)), consts[nn : 2 * nn].reshape((1, 1, n, n)),
        row[0:nx].reshape((1, 1, nx)), x0, P0, x_last, P_last, cls=cls, F=row[nx : 2 * nx].reshape((1, 1, 1, nx)),
        r=row[2 * nx : 2 * nx + 1].reshape((1, 1, 1)), lo=consts[2 * nn : 2 * nn + 1].reshape((1, 1, 1)),
        hi=np.full((1, 1, 1), np.inf), par=row[2 * nx + 1 : 2 * nx + 4].reshape((1, 1, 3)),
        noise_code=int(consts[2 * nn + 1]), joseph=consts[2 * nn + 2] != 0.0, comp=comp,
    )  # fmt: skip
    for b in range(N):
        for i in range(nx):
            if not np.isfinite(P_last[b, i, i]):
                return False
    return True


@njit(cache=True, error_model="numpy", nogil=True)
def fading_step(y, consts, lohi, k, x0, P0, out3, sm_mean, sm_cov, x_last, P_last):
    """One step of the fading Tobit Kalman filter (:data:`~tobitkf.filters._compiled_loop.FADING`, the online
    ``step``): ``y`` (N, m); ``consts`` the flat ``n, noise_code, joseph, A, Qd`` (n, n), the rows ``H_0 .. H_L``
    (L+1, m, n_x) and the standard deviations σ (m,) (:func:`~tobitkf.filters.fading.fading_step_constants`);
    ``lohi`` (2, 1, m) the step's limits; ``k`` the step's time index (its rows :math:`H_{\\min(k, L)}`); ``x0``
    (N, n_x), ``P0`` (N or 1, n_x, n_x). Writes P(uncensored), E[y] and the inverse Mills ratios into ``out3``
    (3, N, m), the smoothed estimates (every block of the new state and its diagonal blocks) into ``sm_mean``
    (N, L+1, n), ``sm_cov`` (N, L+1, n, n) (each (N, 0, ...): not written), the new state into ``x_last``,
    ``P_last``. 11 arguments where the loop takes 29: numba unboxes each argument of a call from Python."""
    N, m = y.shape
    nxi = x0.shape[1]
    n = int(consts[0])
    nn = n * n
    L1 = nxi // n
    e = 3 + 2 * nn
    A = consts[3 : 3 + nn].reshape((1, 1, n, n))
    Qd = consts[3 + nn : e].reshape((1, 1, n, n))
    j = min(k, L1 - 1)
    H = consts[e + j * m * nxi : e + (j + 1) * m * nxi].reshape((1, m, nxi))
    e += L1 * m * nxi
    ts = 1 if sm_mean.shape[1] > 0 else 0
    loop_call(
        FADING_KIND, y.reshape((N, 1, m)), A, Qd, H, x0, P0, x_last, P_last, r=consts[e : e + m].reshape((1, 1, m)),
        lo=lohi[0].reshape((1, 1, m)), hi=lohi[1].reshape((1, 1, m)), J=1, noise_code=int(consts[1]),
        joseph=consts[2] != 0.0, means=sm_mean.reshape((N, ts, nxi)), covs=sm_cov.reshape((N, ts, nxi, n)),
        pu=out3[0].reshape((N, 1, m)), ey=out3[1].reshape((N, 1, m)), comp=out3[2].reshape((N, 1, m, 1)),
    )  # fmt: skip
