r"""The block steps of the nonlinear filters' compiled loop (:mod:`tobitkf.filters._compiled_nonlinear_loop`): those
of the covariance form, and those both forms share (the sigma points, the central differences, the copies of the
block state, the Tobit terms).

The loop runs the numpy path of :mod:`tobitkf.filters.nonlinear` (whose module docstring states the equations) over
blocks of :data:`NL_BLOCK` runs. Per step:

* the **prediction**: extended (:math:`\bar x = f(\hat x)`, :math:`\bar P = F\hat PF^T + Q`) or by the sigma-point
  rule (:func:`sigma_moments`: the unit points ``xi`` and weights ``wm``, ``wc`` of
  :class:`~tobitkf.filters.nonlinear.SigmaPoints`, drawn with the lower Cholesky factor, an eigen root when the
  covariance is singular);
* the **update**, by a code: :data:`KALMAN` (:math:`K = P_{xy}(P_{yy} + R)^{-1}` over the channels with a
  reading, standard or Joseph), :data:`TOBIT` (the Tobit update at the predicted measurement, with the
  censored-normal statistics of :func:`~tobitkf.filters._compiled_tobit.censored_stats` and the noise terms of
  :data:`~tobitkf.filters._compiled_tobit.NOISE_CODES`), :data:`ADF` (channel by channel, iterated, the channel's
  moments of the latent reading from :func:`~tobitkf.filters._compiled_moments.family_block`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, types
from numba.extending import overload

from .._compiled_linalg import cholesky_leading, psd_root
from .._compiled_linalg import cholesky_lower as _cholesky
from ._compiled_fading_moments import fading_channel, fading_moments
from ._compiled_moments import CENSORED, classify, family_block
from ._compiled_tobit import GL_W, GL_X, censored_stats

__all__ = ["KALMAN", "TOBIT", "ADF", "NL_BLOCK", "SIZES", "rule_mean", "sigma_moments", "tobit_terms", "point_columns"]

KALMAN, TOBIT, ADF = 0, 1, 2  #: update codes of :func:`~tobitkf.filters._compiled_nonlinear_loop.nonlinear_loop`
_TINY = float(np.finfo(np.float64).tiny)
_CBRT_EPS = float(np.cbrt(np.finfo(np.float64).eps))


@njit(error_model="numpy", cache=True, inline="always")
def rule_mean(Y, wm, ym):
    r"""The rule's mean :math:`\bar y = \sum_l w^m_lY_l` of the mapped points ``Y`` (L, r) into ``ym`` (r,)."""
    L, r = Y.shape
    for a in range(r):
        s = 0.0
        for p in range(L):
            s += wm[p] * Y[p, a]
        ym[a] = s


@njit(error_model="numpy", cache=True)
def sigma_moments(X, x, Y, wm, wc, ym, Pxy, Pyy):
    r"""The rule's moments of the mapped points ``Y`` (L, r) of ``X`` (L, n) about ``x``: :math:`\bar y = \sum_l
    w^m_lY_l` into ``ym``, :math:`P_{xy} = \sum_l w^c_l(X_l - x)(Y_l - \bar y)^T` into ``Pxy`` (n, r) and the
    symmetrised :math:`P_{yy}` into ``Pyy`` (r, r)."""
    L, r = Y.shape
    n = X.shape[1]
    rule_mean(Y, wm, ym)
    Pxy[:] = 0.0
    Pyy[:] = 0.0
    for p in range(L):
        w = wc[p]
        for a in range(r):
            da = w * (Y[p, a] - ym[a])
            for i in range(n):
                Pxy[i, a] += (X[p, i] - x[i]) * da
            for b in range(r):
                Pyy[a, b] += da * (Y[p, b] - ym[b])
    for a in range(r):
        for b in range(a):
            v = 0.5 * (Pyy[a, b] + Pyy[b, a])
            Pyy[a, b] = v
            Pyy[b, a] = v


@njit(error_model="numpy", cache=True)
def _fill_differences(x, X, delta):
    """The 2n points :math:`x \\pm \\delta_je_j` of the central-difference Jacobian into ``X`` (2n, n) and the
    steps δ into ``delta`` (:func:`tobitkf.models.nonlinear.jacobian_fd`)."""
    n = x.shape[0]
    for j in range(n):
        delta[j] = _CBRT_EPS * max(1.0, abs(x[j]))
    for j in range(n):
        X[j] = x
        X[n + j] = x
        X[j, j] = x[j] + delta[j]
        X[n + j, j] = x[j] - delta[j]


@njit(error_model="numpy", cache=True)
def _difference_jacobian(V, delta, J):
    """The Jacobian (r, n) into ``J`` from the values ``V`` (2n, r) at the points of :func:`_fill_differences`."""
    n = delta.shape[0]
    r = V.shape[1]
    for j in range(n):
        for a in range(r):
            J[a, j] = (V[j, a] - V[n + j, a]) / (2.0 * delta[j])


@njit(error_model="numpy", cache=True)
def _solve_masked(Rxe, Ree, e, ok, K, us):
    r""":math:`K = R_{xe}R_{ee}^{-1}` (n, m) over the channels ``ok`` (the others: zero gain columns), by the
    Cholesky factor of their block of :math:`R_{ee}`; ``e`` is set to 0 where a channel does not take part.
    ``us``: the scratch of :func:`_update_scratch`."""
    n, m = Rxe.shape
    idx, C, Lc, z = us[0], us[1], us[2], us[3]
    q = 0
    for a in range(m):
        if ok[a]:
            idx[q] = a
            q += 1
        else:
            e[a] = 0.0
    K[:] = 0.0
    if q == 0:
        return
    Cq, Lq = C[: q * q].reshape((q, q)), Lc[: q * q].reshape((q, q))  # C-contiguous: one specialisation
    for a in range(q):
        for b in range(q):
            Cq[a, b] = Ree[idx[a], idx[b]]
    if not _cholesky(Cq, Lq):  # not positive definite: the LU solve, as numpy's
        Rs = np.empty((q, n))
        for a in range(q):
            for i in range(n):
                Rs[a, i] = Rxe[i, idx[a]]
        Ks = np.linalg.solve(Cq.copy(), Rs)  # Ree symmetric: K^T = Ree^{-1} Rxe^T
        for i in range(n):
            for a in range(q):
                K[i, idx[a]] = Ks[a, i]
        return
    for i in range(n):  # solve Lc Lc^T k = Rxe[i, idx] for the row k
        for a in range(q):
            s = Rxe[i, idx[a]]
            for c in range(a):
                s -= Lq[a, c] * z[c]
            z[a] = s / Lq[a, a]
        for a in range(q - 1, -1, -1):
            s = z[a]
            for c in range(a + 1, q):
                s -= Lq[c, a] * z[c]
            z[a] = s / Lq[a, a]
        for a in range(q):
            K[i, idx[a]] = z[a]


@njit(error_model="numpy", cache=True)
def _gain_update(x, P, e, Rxe, Ree, ok, H, R, joseph, xo, Po, K, us):
    r"""The masked linear update (:func:`~tobitkf.filters.core.gain_update`): :math:`\hat x = \bar x + Ke`,
    :math:`P = \bar P - KR_{xe}^T` or the Joseph form :math:`(I - KH)\bar P(I - KH)^T + KRK^T` (H's rows of the
    channels left out zeroed), symmetrised; ``K`` (n, m) and ``us`` scratch."""
    n, m = Rxe.shape
    _solve_masked(Rxe, Ree, e, ok, K, us)
    for i in range(n):
        s = x[i]
        for a in range(m):
            s += K[i, a] * e[a]
        xo[i] = s
    if joseph:
        Hm = H.copy()
        for a in range(m):
            if not ok[a]:
                Hm[a] = 0.0
        IKH = np.eye(n) - K @ Hm
        M = IKH @ P @ IKH.T + K @ R @ K.T
        for i in range(n):
            for j in range(n):
                Po[i, j] = 0.5 * (M[i, j] + M[j, i])
        return
    for i in range(n):  # the standard form, the lower triangle mirrored
        for j in range(i + 1):
            s = 0.5 * (P[i, j] + P[j, i])
            for a in range(m):
                s -= 0.5 * (K[i, a] * Rxe[j, a] + K[j, a] * Rxe[i, a])
            Po[i, j] = s
            Po[j, i] = s


@njit(error_model="numpy", cache=True)
def _congruence(A, P, G, out):
    r"""The linearised moments of :math:`Ax` for :math:`x \sim N(\cdot, P)`: :math:`G = PA^T` (n, r) into ``G``
    and :math:`AG = APA^T` (r, r), symmetrised, into ``out`` (element loops, no temporaries). The extended
    measurement's :math:`P_{xy}`, :math:`P_{yy}` (A = H) and the extended prediction's :math:`F\hat PF^T`."""
    n = P.shape[0]
    r = A.shape[0]
    for i in range(n):
        for a in range(r):
            s = 0.0
            for j in range(n):
                s += P[i, j] * A[a, j]
            G[i, a] = s
    for a in range(r):
        for b in range(a + 1):
            s1 = 0.0
            s2 = 0.0
            for i in range(n):
                s1 += A[a, i] * G[i, b]
                s2 += A[b, i] * G[i, a]
            v = 0.5 * (s1 + s2)
            out[a, b] = v
            out[b, a] = v


@njit(error_model="numpy", cache=True)
def _update_scratch(n, m):
    """The scratch of :func:`_joint_update` and :func:`_solve_masked`, allocated once per call of the loop: the
    channel indices, two (m * m,) and one (m,) array of the solve, then e, ok, V, R_ee, R_xe, K and the
    quadrature buffer."""
    return (
        np.empty(m, dtype=np.int64), np.empty(m * m), np.empty(m * m), np.empty(m), np.empty(m),
        np.empty(m, dtype=np.bool_), np.empty(m), np.empty((m, m)), np.empty((n, m)), np.empty((n, m)),
        np.empty((2, GL_X.shape[0])),
    )  # fmt: skip


@njit(error_model="numpy", cache=True)
def tobit_terms(ym, R, lo, hi, noise_code, g, E, V, buf):
    r"""The Tobit update's terms of each channel at the predicted measurement ``ym`` (m,) with noise sd
    :math:`\sqrt{R_{aa}}` and limits ``lo``, ``hi``: the slope (the probability of an uncensored reading) into ``g``,
    :math:`E[y]` into ``E`` and the noise term of ``noise_code``
    (:data:`~tobitkf.filters._compiled_tobit.NOISE_CODES`) into ``V``, from
    :func:`~tobitkf.filters._compiled_tobit.censored_stats` (``buf`` its quadrature buffer)."""
    for a in range(ym.shape[0]):
        st = censored_stats(ym[a], math.sqrt(R[a, a]), lo[a], hi[a], GL_X, GL_W, buf)
        g[a] = st[2]
        E[a] = st[6]
        if noise_code == 0:
            V[a] = st[5]
        elif noise_code == 1:
            V[a] = st[7]
        else:
            V[a] = st[2] * (st[5] + (st[4] - ym[a]) ** 2)


@njit(error_model="numpy", cache=True)
def _joint_update(code, yt, ym, Pxy, Pyy, R, lo, hi, noise_code, joseph, Hj, xp, Pp, x, P, E, g, us):
    r"""The update of all channels at once from the measurement moments: :data:`KALMAN`
    (:math:`K = P_{xy}(P_{yy} + R)^{-1}`) or :data:`TOBIT` (the Tobit update at the predicted measurement
    :math:`\hat y` = ``ym``, with :math:`E[y]` into ``E`` and the slope into ``g``); a NaN reading and a
    channel with a degenerate innovation variance take no part. Writes ``x``, ``P``; ``us`` the scratch of
    :func:`_update_scratch` (no allocation on the standard form's path)."""
    m = ym.shape[0]
    n = xp.shape[0]
    e, ok, V, Ree, Rxe, K, buf = us[4], us[5], us[6], us[7], us[8], us[9], us[10]
    if code == KALMAN:
        for a in range(m):
            for b in range(m):
                Ree[a, b] = Pyy[a, b] + R[a, b]
        for a in range(m):
            e[a] = yt[a] - ym[a]
            ok[a] = not math.isnan(yt[a]) and Ree[a, a] > _TINY
        _gain_update(xp, Pp, e, Pxy, Ree, ok, Hj, R, joseph, x, P, K, us)
        return
    tobit_terms(ym, R, lo, hi, noise_code, g, E, V, buf)
    for i in range(n):
        for a in range(m):
            Rxe[i, a] = Pxy[i, a] * g[a]
    for a in range(m):
        for b in range(m):
            Ree[a, b] = g[a] * Pyy[a, b] * g[b] + (V[a] if a == b else 0.0)
    for a in range(m):
        e[a] = yt[a] - E[a]
        ok[a] = not math.isnan(yt[a]) and Ree[a, a] > _TINY
    _gain_update(xp, Pp, e, Rxe, Ree, ok, Hj, R, False, x, P, K, us)


def _call(fn, X, k, U):  # pragma: no cover - compiled only (its overload below)
    """``fn(X, k)`` or, with input rows ``U``, ``fn(X, k, U)``."""


@overload(_call)
def _call_overload(fn, X, k, U):
    if isinstance(U, types.NoneType):
        return lambda fn, X, k, U: fn(X, k)
    return lambda fn, X, k, U: fn(X, k, U)


def _input_scratch(u, rows):  # pragma: no cover - compiled only (its overload below)
    """The scratch (rows, p) of the input rows of a block; an empty array without inputs."""


@overload(_input_scratch)
def _input_scratch_overload(u, rows):
    if isinstance(u, types.NoneType):
        return lambda u, rows: np.empty((0, 0))
    return lambda u, rows: np.empty((rows, u.shape[2]))


def _block_inputs(u, r0, nb, t, rows, U):  # pragma: no cover - compiled only (its overload below)
    """The inputs of the runs r0..r0+nb-1 at step t, each repeated for its ``rows`` points, (nb * rows, p) in
    ``U``; None without inputs."""


@overload(_block_inputs)
def _block_inputs_overload(u, r0, nb, t, rows, U):
    if isinstance(u, types.NoneType):
        return lambda u, r0, nb, t, rows, U: None

    def rows_of(u, r0, nb, t, rows, U):
        for b in range(nb):
            for i in range(rows):
                U[b * rows + i] = u[r0 + b, t]
        return U[: nb * rows]

    return rows_of


# --------------------------------------------------------------------------- the block steps
# The loop runs the runs in blocks of NL_BLOCK: at every step it stacks the points of a block's runs into one
# array, calls the user's function once on it (f(X, k) with X (nb * L, n), as the batched numpy path calls it)
# and hands the values to the block steps below, which do the per-run algebra. One call per block and step
# instead of one per run: a compiled f or h allocates its result and temporaries on every call, and at n = 4
# those allocations cost more than the arithmetic. Every helper is cached on disk; only nonlinear_loop (the
# calls of the user's functions and the loops over blocks, steps, channels and linearisations) is specialised
# on f, h, F, H and compiled in each process. For the same reason the block steps allocate nothing per run or
# step: their scratch is allocated once per call of the loop (_scratch, _adf_scratch, _update_scratch), and a run's
# rows are copied by element loops, not slice assignments. The state size reaches them as a type (SIZES), so that
# their loops over the state are unrolled at n <= NL_MAX_UNROLL.

NL_BLOCK = 64  #: runs per block of the compiled nonlinear loop
NL_MAX_UNROLL = 6  #: the largest state size passed to the block steps as a compile-time constant
#: the state size as a type (a tuple of n zeros, whose length numba folds to a constant, so that the block steps'
#: loops over the state are unrolled: at n = 4 the loops' own overhead was most of their time); larger states
#: pass ``()`` and the block steps read n from their arrays
SIZES = {n: (0,) * n for n in range(1, NL_MAX_UNROLL + 1)}


@njit(error_model="numpy", cache=True, inline="always")
def _n(size, xs):
    """The state size: ``len(size)`` (a compile-time constant) or, for ``size = ()``, ``xs.shape[1]``."""
    return len(size) if len(size) > 0 else xs.shape[1]


def point_columns(xi: np.ndarray) -> np.ndarray:
    """For each unit point of ``xi`` (L, n): -1 when it is the origin, the column of its one nonzero
    coordinate, or -2 (several): the shortcut of :func:`_block_points`."""
    nz = xi != 0.0
    count = nz.sum(axis=1)
    return np.where(count == 0, -1, np.where(count == 1, nz.argmax(axis=1), -2)).astype(np.int64)


@njit(error_model="numpy", cache=True)
def _scratch(B, n, m, rows):
    """The block state and scratch of :func:`nonlinear_loop`, allocated once per call."""
    return (
        np.empty((B, n)), np.empty((B, n, n)), np.empty((B, n)), np.empty((B, n, n)), np.empty((B, n)),
        np.empty((B, n, n)), np.empty((B * rows, n)), np.empty((B, n)), np.empty((B, n)), np.empty((B, n, n)),
        np.zeros((B, m, n)), np.ones(B, dtype=np.bool_), np.empty(B, dtype=np.bool_), np.empty(B),
    )  # fmt: skip


@njit(error_model="numpy", cache=True)
def _adf_scratch(B, n):
    """The scratch of :func:`_adf_project`, allocated once per call of the loop: the runs' indices, ten rows of
    per-run statistics, the reading classes, the cross-covariances (B, n), a vector (n,), the components (3, B)
    (the modes of random saturation) and the quadrature buffer."""
    return (
        np.empty(B, dtype=np.int64), np.empty((10, B)), np.empty(B, dtype=np.int8), np.empty((B, n)), np.empty(n),
        np.empty((3, B)), np.empty((2, GL_X.shape[0])),
    )  # fmt: skip


@njit(error_model="numpy", cache=True)
def _block_start(x0, P0, r0, nb, xs, Ps):
    """The prior of the runs r0..r0+nb-1 into the block state."""
    for b in range(nb):
        xs[b] = x0[r0 + b]
        Ps[b] = P0[r0 + b if P0.shape[0] > 1 else 0]


@njit(error_model="numpy", cache=True)
def _block_end(xs, Ps, r0, nb, x_last, P_last):
    """The last state of the block's runs into ``x_last``, ``P_last``."""
    for b in range(nb):
        x_last[r0 + b] = xs[b]
        P_last[r0 + b] = Ps[b]


@njit(error_model="numpy", cache=True)
def _block_copy(size, xs, Ps, xo, Po, nb):
    """``xo[b], Po[b] = xs[b], Ps[b]`` for the runs b < nb (element loops: a slice copy per run costs more than
    the copy at this size)."""
    n = _n(size, xs)
    for b in range(nb):
        for i in range(n):
            xo[b, i] = xs[b, i]
            for j in range(n):
                Po[b, i, j] = Ps[b, i, j]


@njit(error_model="numpy", cache=True)
def _block_rows(xs, X, nb):
    """The means of the block's runs as the rows of ``X`` (the points of the extended form)."""
    for b in range(nb):
        X[b] = xs[b]


@njit(error_model="numpy", cache=True)
def _block_points(size, xs, Ps, xi, xcol, root, X, nb, act, factors):
    """The sigma points of N(``xs[b]``, ``Ps[b]``) of the runs b < nb with ``act[b]``, stacked in ``X`` (L rows a
    run, in order): :math:`\\chi_l = x + S\\xi_l` with S the lower Cholesky factor of ``Ps[b]`` (an eigen root
    when it fails: :func:`~tobitkf._compiled_linalg.psd_root`) taken into ``root``, or, with ``factors`` (the
    square-root form), ``Ps[b]`` itself; returns how many runs. Indexes the block arrays directly (no per-run
    views or calls); a point with one nonzero unit coordinate (``xcol[l]`` = its column, -1 for the centre:
    :func:`point_columns`) is :math:`x + \\xi_{lj}S_{:,j}`, the full sum's value (its other terms are exact
    zeros) at 1/n of its cost."""
    L = xi.shape[0]
    n = _n(size, xs)
    q = 0
    for b in range(nb):
        if not act[b]:
            continue
        if factors:
            S = Ps[b]
        else:
            if not cholesky_leading(Ps[b], root, n):
                psd_root(Ps[b], root)
            S = root
        base = q * L
        for p in range(L):
            col = xcol[p]
            if col == -1:
                for i in range(n):
                    X[base + p, i] = xs[b, i]
            elif col >= 0:
                v = xi[p, col]
                for i in range(n):
                    X[base + p, i] = xs[b, i] + S[i, col] * v
            else:
                for i in range(n):
                    s = xs[b, i]
                    for j in range(n):
                        s += S[i, j] * xi[p, j]
                    X[base + p, i] = s
        q += 1
    return q


@njit(error_model="numpy", cache=True)
def _block_differences(xs, X, deltas, nb):
    """The central-difference points of every run of the block stacked in ``X`` (2n rows a run), their steps in
    ``deltas`` (B, n)."""
    n = xs.shape[1]
    for b in range(nb):
        _fill_differences(xs[b], X[2 * n * b : 2 * n * (b + 1)], deltas[b])


@njit(error_model="numpy", cache=True)
def _block_jacobians(V, deltas, J, nb):
    """The Jacobians ``J[b]`` (r, n) from the values ``V`` (nb * 2n, r) at the points of
    :func:`_block_differences`."""
    n = deltas.shape[1]
    for b in range(nb):
        _difference_jacobian(V[2 * n * b : 2 * n * (b + 1)], deltas[b], J[b])


@njit(error_model="numpy", cache=True)
def _predict_sigma(size, Y, wm, wc, Q, xps, Pps, dv, nb):
    r"""The sigma-point prediction of the block's runs from the mapped points ``Y`` = f(``X``):
    :math:`\bar x = \sum_l w^m_lf(\chi_l)`, :math:`\bar P = \sum_l w^c_l(f(\chi_l) - \bar x)(\cdot)^T + Q`
    (the lower triangle summed and mirrored, Q symmetrised; ``dv`` (n,) scratch)."""
    L = wm.shape[0]
    n = _n(size, xps)
    for b in range(nb):
        base = b * L
        for a in range(n):
            s = 0.0
            for p in range(L):
                s += wm[p] * Y[base + p, a]
            xps[b, a] = s
        for a in range(n):
            for c in range(a + 1):
                Pps[b, a, c] = 0.5 * (Q[a, c] + Q[c, a])
        for p in range(L):
            w = wc[p]
            for a in range(n):
                dv[a] = Y[base + p, a] - xps[b, a]
            for a in range(n):
                da = w * dv[a]
                for c in range(a + 1):
                    Pps[b, a, c] += da * dv[c]
        for a in range(n):
            for c in range(a):
                Pps[b, c, a] = Pps[b, a, c]


@njit(error_model="numpy", cache=True)
def _predict_extended(Y1, J, Ps, Q, xps, Pps, G, nb):
    r"""The extended prediction of the block's runs: :math:`\bar x = f(\hat x)` from ``Y1`` (nb, n),
    :math:`\bar P = F\hat PF^T + Q` from the Jacobians ``J`` (nb, n, n) (:func:`_congruence`, ``G`` (n, n)
    scratch for :math:`\hat PF^T`), Q symmetrised."""
    n = Ps.shape[1]
    for b in range(nb):
        for i in range(n):
            xps[b, i] = Y1[b, i]
        _congruence(J[b], Ps[b], G, Pps[b])
        for i in range(n):
            for j in range(i + 1):
                v = Pps[b, i, j] + 0.5 * (Q[i, j] + Q[j, i])
                Pps[b, i, j] = v
                Pps[b, j, i] = v


@njit(error_model="numpy", cache=True)
def _update_joint(
    code, sigma, X, Y, J, wm, wc, xps, Pps, y, r0, t, R, lo, hi, noise_code, joseph, xs, Ps, Hj, ey, slope, nb, fade
):  # fmt: skip
    """The update of all channels at once (:func:`_joint_update`) of the block's runs from the values ``Y`` of h:
    at the sigma points ``X`` (``sigma``) or at the means, with the Jacobians ``J``; the Tobit extras into
    ``ey``, ``slope``. ``fade`` (2, m): the fading gains' means and variances, whose faded moments
    (:func:`~tobitkf.filters._compiled_fading_moments.fading_moments`) replace those of h; (0, m): no fading."""
    L = wm.shape[0]
    n = xs.shape[1]
    m = y.shape[2]
    ym, Pxy, Pyy, E, g = np.empty(m), np.empty((n, m)), np.empty((m, m)), np.empty(m), np.empty(m)
    us = _update_scratch(n, m)
    for b in range(nb):
        Hb = Hj[b]
        if sigma:
            sigma_moments(X[b * L : (b + 1) * L], xps[b], Y[b * L : (b + 1) * L], wm, wc, ym, Pxy, Pyy)
        else:
            ym[:] = Y[b]
            Hb[:] = J[b]
            _congruence(Hb, Pps[b], Pxy, Pyy)
        if fade.shape[0] > 0:
            fading_moments(fade[0], fade[1], ym, Pxy, Pyy)
        _joint_update(code, y[r0 + b, t], ym, Pxy, Pyy, R, lo, hi, noise_code, joseph, Hb, xps[b], Pps[b], xs[b],
                      Ps[b], E, g, us)  # fmt: skip
        if ey.shape[1] > 0:
            ey[r0 + b, t] = E
            slope[r0 + b, t] = g


@njit(error_model="numpy", cache=True)
def _adf_channel_start(size, y, r0, t, ch, xs, Ps, xms, Pms, act, nb):
    """Start channel ``ch`` of the assumed-density update: the linearisation point is the prior, ``act`` the
    runs with a reading on the channel; returns how many."""
    _block_copy(size, xs, Ps, xms, Pms, nb)
    q = 0
    for b in range(nb):
        act[b] = not math.isnan(y[r0 + b, t, ch])
        if act[b]:
            q += 1
    return q


@njit(error_model="numpy", cache=True)
def _adf_project(
    size, it, ch, X, Y, wm, wc, y, r0, t, xs, Ps, xms, Pms, act, rl, family, lo, hi, par, lsum, nb, ws, fade
):  # fmt: skip
    r"""Linearisation ``it`` of channel ``ch`` for the block's runs in ``act``, from the values ``Y`` of h at their
    stacked sigma points ``X`` the rule's moments of
    the channel about :math:`N(x_m, P_m)` (``xms``, ``Pms``), the affine model (about the prior itself when
    ``it`` = 0), the channel's moments of the latent reading for the runs at once
    (:func:`~tobitkf.filters._compiled_moments.family_block`) and the projection of the prior ``xs``, ``Ps``
    into ``xms``, ``Pms``; the log-likelihood of the first linearisation into ``lsum``. A run whose latent
    variance is not above the smallest normal number keeps the prior and leaves ``act``. ``family`` the channel's
    family as a kind (:func:`~tobitkf.filters._compiled_moments.kind`: each family's version holds its own block
    function alone). ``ws``: the scratch of
    :func:`_adf_scratch`; ``fade`` as :func:`_update_joint` (the channel's faded moments,
    :func:`~tobitkf.filters._compiled_fading_moments.fading_channel`)."""
    L = wm.shape[0]
    n = _n(size, xs)
    idx, st, cls, C, c, comp, buf = ws
    yv, hx, hph, rb, lo_c, hi_c, alpha, beta, llb, pu = st[0], st[1], st[2], st[3], st[4], st[5], st[6], st[7], \
        st[8], st[9]  # fmt: skip
    q = 0  # the run's rows in X, Y
    q2 = 0  # the runs that take the update
    for b in range(nb):
        if not act[b]:
            continue
        base = q * L
        q += 1
        s = 0.0
        for p in range(L):
            s += wm[p] * Y[base + p, ch]
        mu0 = s
        for i in range(n):
            c[i] = 0.0
        pyy = 0.0
        for p in range(L):
            da = wc[p] * (Y[base + p, ch] - mu0)
            for i in range(n):
                c[i] += (X[base + p, i] - xms[b, i]) * da
            pyy += da * (Y[base + p, ch] - mu0)
        if fade.shape[0] > 0:
            mu0, scale, pyy = fading_channel(fade[0, ch], fade[1, ch], mu0, pyy)
            for i in range(n):
                c[i] *= scale
        if it == 0:
            mu = mu0
            for i in range(n):
                C[q2, i] = c[i]
            s2 = pyy + rl
        else:  # the affine model fitted about the posterior, applied to the prior
            Hl = np.linalg.solve(Pms[b], c)
            omega = max(pyy - np.dot(Hl, np.dot(Pms[b], Hl)), 0.0)
            mu = mu0 + np.dot(Hl, xs[b] - xms[b])
            cxy = np.dot(Ps[b], Hl)
            C[q2] = cxy
            s2 = np.dot(Hl, cxy) + omega + rl
        if not s2 > _TINY:
            for i in range(n):
                xms[b, i] = xs[b, i]
                for k in range(n):
                    Pms[b, i, k] = Ps[b, i, k]
            act[b] = False
            continue
        yb = y[r0 + b, t, ch]
        idx[q2] = b
        yv[q2], hx[q2], hph[q2], rb[q2], lo_c[q2], hi_c[q2], llb[q2] = yb, mu, s2 - rl, rl, lo, hi, 0.0
        cls[q2] = classify(yb, lo, hi) if len(family) == CENSORED else 1
        q2 += 1
    if q2 == 0:
        return
    family_block(family, q2, yv, cls, hx, hph, rb, lo_c, hi_c, par, alpha, beta, llb, pu, comp, GL_X, GL_W, buf)
    for j in range(q2):
        b = idx[j]
        a, be = alpha[j], beta[j]
        for i in range(n):
            xms[b, i] = xs[b, i] + a * C[j, i]
            for k in range(i + 1):
                v = 0.5 * ((Ps[b, i, k] - be * C[j, i] * C[j, k]) + (Ps[b, k, i] - be * C[j, k] * C[j, i]))
                Pms[b, i, k] = v
                Pms[b, k, i] = v
        if it == 0:
            lsum[b] += llb[j]


@njit(error_model="numpy", cache=True)
def _record(size, xs, Ps, r0, t, nb, means, covs):
    """The block's state at step t into ``means`` (N, T or 0, n) and ``covs`` (N, T or 0, n, n or 1: the
    diagonals)."""
    n = _n(size, xs)
    if means.shape[1] > 0:
        for b in range(nb):
            for i in range(n):
                means[r0 + b, t, i] = xs[b, i]
    if covs.shape[1] > 0:
        for b in range(nb):
            if covs.shape[3] == 1:
                for i in range(n):
                    covs[r0 + b, t, i, 0] = Ps[b, i, i]
            else:
                for i in range(n):
                    for j in range(n):
                        covs[r0 + b, t, i, j] = Ps[b, i, j]


@njit(error_model="numpy", cache=True)
def _record_ll(lsum, r0, t, nb, ll):
    """The block's log-likelihood terms at step t into ``ll`` (N, T or 0)."""
    if ll.shape[1] > 0:
        for b in range(nb):
            ll[r0 + b, t] = lsum[b]
