r"""The block machinery every compiled loop shares: runs per block, the structure-of-arrays scratch, the
block linear algebra (predict, innovation moments, gain and covariance update, the small solves) and the
output staging (stage a chunk of steps, flush it run by run into the ``(N, T, ...)`` outputs).

Used by the Kalman and Tobit Kalman loops of :mod:`tobitkf.filters._compiled_tobit`, the shared core's
loop (:mod:`tobitkf.filters._compiled_step`), the fading, protocol and steady-state kernels, the
compiled assumed-density loop (:mod:`tobitkf.filters._compiled_loop`) and the compiled closed loop of
:mod:`tobitkf.control`. Compiled on first use and cached on disk (``cache=True``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .._compiled_linalg import gauss_solve as _gauss_solve

__all__ = [
    "predict_block",
    "block_scratch",
    "stage_block",
    "flush_rows",
    "stage_shape",
    "runs_per_block",
    "BLOCK",
    "CHUNK",
]

_INF = math.inf
_TINY = float(np.finfo(np.float64).tiny)  # R_ee diagonals not above this count as 0 (as gain_update)


# --- block helpers -------------------------------------------------------------------------
# State of a block of up to runs_per_block(n) runs in structure-of-arrays layout: x[i, b], P[i, j, b].
# Runs are independent, so the innermost loops over b carry no dependency: the CPU
# overlaps the recursions of the runs (one run alone is a long latency chain) and LLVM
# vectorises the dense algebra over b.

BLOCK = 32  # runs per block from n = 13 on (runs_per_block: more at smaller n)
CHUNK = 64
FLUSH_BY_STEP = 32  # numbers per run-step from which _flush goes step by step
BLOCKED_N = 8  # state size from which the block products take the blocked loops (_predict_blocked)
STAGE_BYTES = 1 << 18  # at most this many bytes per staging buffer of the compiled loop (fewer steps at large n)
# Outputs are staged for CHUNK steps of a block and then written run by run: writing
# every step straight into (N, T, ...) arrays touches B rows T*n*8 bytes apart,
# which for long records alias in the cache and miss the TLB on every store. The staging
# buffers are laid out (S, ..., B), the run innermost as in the block's state, so that the
# per-step copies into them are contiguous, vectorised loops over the block; the transpose
# to the run-major (N, T, ...) layout happens once per chunk in _flush (strided reads from
# the cache-resident buffer, contiguous writes). Measured on the steady-state TKF (n = 2,
# 10^4 runs x 100 steps, outputs preallocated): 15.6 ns per run-step against 21.2 ns with
# (B, S, ...) buffers written run by run at every step, and 17.2 ns writing the outputs directly.
# At large n a chunk of CHUNK steps no longer fits the core's L2 cache (n = 16: 64 steps x 256 numbers x 32
# runs = 4 MB per covariance buffer), and the staged copies went out to L3 and back: the TKF stages
# at most STAGE_BYTES per buffer (n = 16: 4 steps; n = 2 keeps 64). Measured at n = 16, m = 8, all
# outputs into reused arrays (in-process A/B, thread CPU time, load 5.7): 3477 -> 2967 ns per run-step.


# --- the block scratch ---------------------------------------------------------------------
# One allocator of the block scratch for every kernel (here, the loop, the closed loop), called once per kernel
# call (never per block or step) and inlined into the kernel at the numba IR level. One array per piece of
# scratch: in numba an array made costs ~22 ns (its allocation and release) whatever its size, and a view of a
# slice of one workspace reshaped to a piece's shape as much (the reshape goes through numba's run-time helper;
# measured in isolation, 10 arrays a call, thread CPU time, load 9-16: 374-402 ns allocating them, 355 ns
# allocating them empty, 368-392 ns cutting them from one workspace by slice and reshape, 167-219 ns by integer
# index of one (10, ...) array, 152 ns the call alone); the compiled loop with its scratch cut by slice and
# reshape made the one-run Kalman filter's step slower (4.7 against 4.2 us per call of the step's entry). Not a
# workspace made by the Python driver and passed in: a tuple of arrays passed in is unboxed array by array on
# every call (28 arrays: 7.3 us per call).


@njit(cache=True)
def runs_per_block(n):
    """Runs per block of the Kalman-type kernels (TKF, KF, steady-state, closed loop, the shared step) at
    state size ``n``: 128 up to n = 8, 64 up to n = 12, :data:`BLOCK` (32) beyond, plus 8 where slabs alias
    (below).

    A step of a block is some tens of short loops over its runs; at small n each loop's set-up (the
    vector loop's alias checks and remainder) is paid per loop, not per run, so more runs per block
    amortise it, until the block's arrays (n x n x B numbers each) leave the L1/L2 caches and the staging
    buffers get few steps (:data:`STAGE_BYTES`). Measured (4 Dec 2026, TKF kernel, outputs reused,
    thread CPU time, ns per run-step, B = 32 / 64 / 128): n = 2, m = 1 mean + cov 46.9 / 40.0 / 35.1,
    means 40.4 / 36.0 / 28.2, KF 24.4 / 30.2 / 17.1; n = 4, m = 1 mean + cov 91.6 / 104 / 78.0; n = 6, m = 2
    252-270 / 222-239 / 220-224; n = 8, m = 2 355-468 / 316-318 / 331-346; n = 12, m = 4 897-982 /
    845-870 / 852-858; n = 16, m = 8 mean + cov 2023 / 2186 / 2316 (the blocked slab loops run over all
    of a block's lanes at once already).

    From n = :data:`BLOCKED_N` on, 8 runs more when a slab ``P[k]`` of the block (``n * B * 8`` bytes; n = 16,
    B = 32: 4 KB) is a multiple of 4 KB: the slab products (:func:`_rows_times`) read four slabs and update
    four at once, and slabs 4 KB apart all fall into the same set of the 8-way L1 cache and evict each other.
    Measured at n = 16, m = 8, 10^3 runs x 100 steps (in-process A/B, thread CPU time, outputs reused, load
    1.6): means only 1408 -> 1344, all outputs 2303 -> 2071 ns per run-step with 40 runs per block against 32
    (48: the same as 40); at n = 8 (128 runs: 8 KB slabs) 136 runs against 128, alternated twice (load 1.7):
    n = 8, m = 2 mean + cov 257-270 against 283-306, m = 8 568-572 against 607-750 ns per run-step."""
    B = BLOCK
    if n <= 8:
        B = 128
    elif n <= 12:
        B = 64
    if n >= BLOCKED_N and (n * B * 8) % 4096 == 0:
        B += 8
    return B


@njit(cache=True)
def _block_dims(N, T, d=0, block=BLOCK):
    """``(B, S)``: runs per block and staged steps of a call of ``N`` runs x ``T`` steps (a single run,
    the online step, gets a single column, a single step a single staging slot). ``d`` the largest
    number of staged values per run-step (0: not given): S is cut so that one staging buffer holds at
    most :data:`STAGE_BYTES`; ``block`` the most runs per block (:data:`BLOCK`; the augmented-state loops
    take 64)."""
    B = min(block, max(N, 1))
    S = min(CHUNK, max(T, 1))
    if d > 0:
        S = max(1, min(S, STAGE_BYTES // (8 * d * B)))
    return B, S


@njit(cache=True, inline="always")
def _mean_scratch(dim, m, B):
    """The scratch of the mean recursion of a block: ``x``, ``xp`` (dim, B), ``e``, ``ybar`` (m, B)."""
    return np.empty((dim, B)), np.empty((dim, B)), np.empty((m, B)), np.empty((m, B))


@njit(cache=True, inline="always")
def _update_scratch(dim, ntop, m, B, G):
    """The scratch of the covariance recursion and the masked gain of a block of ``B`` runs.

    ``dim`` the state size, ``ntop`` the size of the block the transition acts on (``dim`` for the TKF
    and the KF, ``n`` for the shifted fading state), ``m`` channels, ``G`` quadrature nodes. Returns
    ``(P, Pp, AP, CP, Rxe, Ree, K, MH, noise, gam, ok)`` (``AP`` (dim, ntop, B), ``MH`` the scratch of
    :func:`_cov_update`, ``noise``
    (m, m, B) zeroed), the per-run solve scratch ``(Rs, Ws, Ks, oks, Rxs, ds)`` of :func:`_gain_of_run`,
    the block solve scratch ``(Rw, Wb, db, bad)`` of :func:`_gain_block` (empty for m = 1) and the
    (2, G) quadrature buffer of :func:`censored_stats`."""
    g = m if m > 1 else 0
    gb = B if m > 1 else 0
    blk = (
        np.empty((dim, dim, B)),  # P
        np.empty((dim, dim, B)),  # Pp
        np.empty((dim, ntop, B)),  # AP
        np.empty((m, dim, B)),  # CP
        np.empty((dim, m, B)),  # Rxe
        np.empty((m, m, B)),  # Ree
        np.empty((dim, m, B)),  # K
        np.empty((dim, m, B)),  # MH
        np.zeros((m, m, B)),  # noise
        np.empty((m, B)),  # gam
        np.empty((m, B), dtype=np.bool_),  # ok
    )
    run = (
        np.empty((m, m)),  # Rs
        np.empty((m, dim)),  # Ws
        np.empty((dim, m)),  # Ks
        np.empty(m, dtype=np.bool_),  # oks
        np.empty((dim, m)),  # Rxs
        np.empty(m),  # ds
    )
    solve = (np.empty((g, g, gb)), np.empty((g, dim if g else 0, gb)), np.empty((g, gb)), np.empty(gb, dtype=np.bool_))
    return blk, run, solve, np.empty((2, G))


@njit(cache=True)
def _stage_shape(out, B, S):
    """Shape of the staging buffer of the output ``out`` (N, T, ...): ``(S, ..., B)`` (chunk step first,
    run last: ``buf[tt, ..., b]``), or ``(0, ..., B)`` when the output is not requested
    (``out.shape[1] == 0``: no staging, not written)."""
    return (S if out.shape[1] > 0 else 0,) + out.shape[2:] + (B,)


@njit(cache=True, error_model="numpy")
def _mirror(P, nb):
    """Copy the upper triangle of the block's ``P[i, j, b]`` onto the lower (the products below
    compute only ``j >= i`` of a symmetric result: half the work of the full product and its
    symmetrization, equal to it to rounding)."""
    n = P.shape[0]
    for i in range(n):
        for j in range(i + 1, n):
            for b in range(nb):
                P[j, i, b] = P[i, j, b]


@njit(cache=True, error_model="numpy")
def _predict(A, Qd, x, P, xp, Pp, AP, nb):
    r""":math:`\bar x = A\hat x`, :math:`\bar P = \mathrm{sym}(A P A^T + Q)` (Miller (2.3), (3.20)–(3.21)).

    From n = :data:`BLOCKED_N` on by :func:`_predict_blocked`; below, these short loops (the blocked
    ones made the n = 2, m = 1 TKF ~8% slower: 86 against 79 ns per run-step, in-process A/B)."""
    n = A.shape[0]
    if n >= BLOCKED_N:
        _predict_blocked(A, Qd, x, P, xp, Pp, AP, nb)
        return
    mean_predict(A, x, xp, nb)
    for i in range(n):
        for j in range(n):
            for b in range(nb):
                AP[i, j, b] = 0.0
            for k in range(n):
                a = A[i, k]
                for b in range(nb):
                    AP[i, j, b] += a * P[k, j, b]
    for i in range(n):
        for j in range(i, n):
            for b in range(nb):
                Pp[i, j, b] = 0.0
            for k in range(n):
                a = A[j, k]
                for b in range(nb):
                    Pp[i, j, b] += AP[i, k, b] * a
            q = 0.5 * (Qd[i, j] + Qd[j, i])
            for b in range(nb):
                Pp[i, j, b] += q
    _mirror(Pp, nb)


@njit(cache=True, error_model="numpy")
def _predict_blocked(A, Qd, x, P, xp, Pp, AP, nb):
    r""":math:`\bar x = A\hat x`, :math:`\bar P = \mathrm{sym}(A P A^T + Q)` (Miller (2.3), (3.20)–(3.21)).

    Loop order for speed at larger n: ``AP`` row by row as :math:`(AP)_{i\cdot} = \sum_k A_{ik}P_{k\cdot}` over
    the whole contiguous slabs ``P[k]`` (n B numbers, all lanes of the block: lanes past ``nb`` hold an
    earlier block's values and are never read back) by :func:`_rows_times`, four rows and four terms per pass;
    :math:`\bar P_{ij}` (only ``j >= i``, mirrored) by :func:`_sym_times`, four entries and four terms per
    pass over the runs. Measured at n = 16, B = 32 (in isolation, thread CPU time, load 1.2): 659 -> 427 ns
    per run (one row and one term per pass for ``AP``, one entry and eight terms for :math:`\bar P`: 1040 ->
    ~600 ns before that, against one short loop over the runs per term)."""
    n = A.shape[0]
    W = P.shape[2]
    L = n * W
    mean_predict(A, x, xp, nb)
    _rows_times(AP.reshape((n, L)), A, P.reshape((n, L)), n, L, False)
    _sym_times(Pp, AP, A, Qd, True, n, W, False)
    _mirror(Pp, W)


@njit(cache=True, error_model="numpy")
def _rows_times(out, M, X, nk, L, skip_zero):
    """``out[i, q] = sum_k M[i, k] X[k, q]`` for every row i of ``M`` (``out`` (rows, L), ``X`` (nk, L), 2-d
    contiguous): the block products over the whole slabs of a block's lanes (:func:`_predict_blocked`,
    :func:`_innovation_moments_blocked`), in register tiles of four rows and four terms per pass over ``q``
    (four loads of ``X``, four loads and stores of the accumulators per sixteen products; one row and one
    term per pass loads and stores the accumulator once per product). Measured at n = 16, B = 32 (A P, in
    isolation, thread CPU time, load 1.2): 446 -> 298 ns per run. ``skip_zero``: a term whose coefficient
    is 0 is left out (the augmented measurement matrix of the fading TKF is mostly zeros), so that a tile
    with a zero coefficient takes its terms one at a time."""
    nr = M.shape[0]
    r4 = nr - nr % 4
    for i0 in range(0, r4, 4):
        for r in range(4):
            for q in range(L):
                out[i0 + r, q] = 0.0
        k = 0
        while k < nk:
            tile = k + 4 <= nk
            if tile and skip_zero:
                for r in range(4):
                    for c in range(4):
                        if M[i0 + r, k + c] == 0.0:
                            tile = False
            if tile:
                a00, a01, a02, a03 = M[i0, k], M[i0, k + 1], M[i0, k + 2], M[i0, k + 3]
                a10, a11, a12, a13 = M[i0 + 1, k], M[i0 + 1, k + 1], M[i0 + 1, k + 2], M[i0 + 1, k + 3]
                a20, a21, a22, a23 = M[i0 + 2, k], M[i0 + 2, k + 1], M[i0 + 2, k + 2], M[i0 + 2, k + 3]
                a30, a31, a32, a33 = M[i0 + 3, k], M[i0 + 3, k + 1], M[i0 + 3, k + 2], M[i0 + 3, k + 3]
                for q in range(L):
                    p0, p1, p2, p3 = X[k, q], X[k + 1, q], X[k + 2, q], X[k + 3, q]
                    out[i0, q] += (a00 * p0 + a01 * p1) + (a02 * p2 + a03 * p3)
                    out[i0 + 1, q] += (a10 * p0 + a11 * p1) + (a12 * p2 + a13 * p3)
                    out[i0 + 2, q] += (a20 * p0 + a21 * p1) + (a22 * p2 + a23 * p3)
                    out[i0 + 3, q] += (a30 * p0 + a31 * p1) + (a32 * p2 + a33 * p3)
                k += 4
                continue
            for r in range(4):
                a = M[i0 + r, k]
                if a != 0.0 or not skip_zero:
                    for q in range(L):
                        out[i0 + r, q] += a * X[k, q]
            k += 1
    for i in range(r4, nr):
        for q in range(L):
            out[i, q] = 0.0
        for k in range(nk):
            a = M[i, k]
            if a != 0.0 or not skip_zero:
                for q in range(L):
                    out[i, q] += a * X[k, q]


@njit(cache=True, error_model="numpy")
def _sym_times(out, X, M, Q, with_q, nk, W, skip_zero):
    r"""The upper triangle of ``out[i, j, b] = q_ij + sum_k X[i, k, b] M[j, k]`` (``j >= i``, ``k < nk``,
    ``b < W``; :math:`q_{ij}` the symmetric part of ``Q`` when ``with_q``, else 0): :math:`\bar P = (AP)A^T +
    \mathrm{sym}(Q)` of :func:`_predict_blocked` and :math:`C\bar PC^T` of :func:`_innovation_moments_blocked`,
    four entries ``j`` and four terms ``k`` per pass over the runs (the four loads of ``X[i, k]`` shared by
    the four entries; the last ``n - i`` mod 4 entries of a row one at a time). ``skip_zero``: a tile whose
    sixteen (or four) coefficients are all 0 is left out (the fading TKF's augmented C; a zero coefficient
    inside a tile adds an exact 0 for finite ``X``). Measured at n = 16, B = 32 ((AP)A^T in isolation,
    thread CPU time, load 1.2): 207 -> 149 ns per run against one entry and eight terms per pass (160 against
    320 ns for one term per pass)."""
    nr = out.shape[1]
    for i in range(out.shape[0]):
        j = i
        while j < nr:
            four = j + 4 <= nr
            jn = 4 if four else 1
            for r in range(jn):
                qr = 0.5 * (Q[i, j + r] + Q[j + r, i]) if with_q else 0.0
                for b in range(W):
                    out[i, j + r, b] = qr
            k = 0
            while k < nk:
                kn = 4 if k + 4 <= nk else 1
                if skip_zero:
                    nz = False
                    for r in range(jn):
                        for c in range(kn):
                            if M[j + r, k + c] != 0.0:
                                nz = True
                    if not nz:
                        k += kn
                        continue
                if four and kn == 4:
                    a00, a01, a02, a03 = M[j, k], M[j, k + 1], M[j, k + 2], M[j, k + 3]
                    a10, a11, a12, a13 = M[j + 1, k], M[j + 1, k + 1], M[j + 1, k + 2], M[j + 1, k + 3]
                    a20, a21, a22, a23 = M[j + 2, k], M[j + 2, k + 1], M[j + 2, k + 2], M[j + 2, k + 3]
                    a30, a31, a32, a33 = M[j + 3, k], M[j + 3, k + 1], M[j + 3, k + 2], M[j + 3, k + 3]
                    for b in range(W):
                        p0, p1, p2, p3 = X[i, k, b], X[i, k + 1, b], X[i, k + 2, b], X[i, k + 3, b]
                        out[i, j, b] += (a00 * p0 + a01 * p1) + (a02 * p2 + a03 * p3)
                        out[i, j + 1, b] += (a10 * p0 + a11 * p1) + (a12 * p2 + a13 * p3)
                        out[i, j + 2, b] += (a20 * p0 + a21 * p1) + (a22 * p2 + a23 * p3)
                        out[i, j + 3, b] += (a30 * p0 + a31 * p1) + (a32 * p2 + a33 * p3)
                elif four:
                    a0, a1, a2, a3 = M[j, k], M[j + 1, k], M[j + 2, k], M[j + 3, k]
                    for b in range(W):
                        p = X[i, k, b]
                        out[i, j, b] += a0 * p
                        out[i, j + 1, b] += a1 * p
                        out[i, j + 2, b] += a2 * p
                        out[i, j + 3, b] += a3 * p
                elif kn == 4:
                    a0, a1, a2, a3 = M[j, k], M[j, k + 1], M[j, k + 2], M[j, k + 3]
                    for b in range(W):
                        out[i, j, b] += (X[i, k, b] * a0 + X[i, k + 1, b] * a1) + (
                            X[i, k + 2, b] * a2 + X[i, k + 3, b] * a3
                        )
                else:
                    a = M[j, k]
                    for b in range(W):
                        out[i, j, b] += X[i, k, b] * a
                k += kn
            j += jn


@njit(cache=True, error_model="numpy")
def _solve_gain(Ree, Rxe, ok, K, W, d):
    r"""One run: :math:`K = R_{xe}R_{ee}^{-1}` with channels ``~ok`` removed (zero gain column), as
    :func:`~tobitkf.filters.core.gain_update`. ``Ree`` (m, m) is overwritten; Gaussian
    elimination with partial pivoting, like LAPACK gesv."""
    n, m = Rxe.shape
    for i in range(m):
        for j in range(m):
            if not (ok[i] and ok[j]):
                Ree[i, j] = 1.0 if i == j else 0.0
    for j in range(m):
        for i in range(n):
            W[j, i] = Rxe[i, j] if ok[j] else 0.0
    # scale Ree to unit diagonal (as core._gain): channels whose variances differ by ~1e77
    # otherwise give gain entries wrong by ~1e54 and a Joseph covariance of ~1e33
    # (``d`` (m,) is the caller's scratch: nothing is allocated per call)
    for i in range(m):
        d[i] = 1.0 / np.sqrt(Ree[i, i]) if Ree[i, i] > 0.0 else 1.0
    for i in range(m):
        for j in range(m):
            Ree[i, j] *= d[i] * d[j]
        for k in range(n):
            W[i, k] *= d[i]
    if not _gauss_solve(Ree, W):
        raise np.linalg.LinAlgError("Singular matrix")  # as numpy.linalg.solve
    for i in range(n):
        for j in range(m):
            K[i, j] = W[j, i] * d[j]


@njit(cache=True, error_model="numpy")
def _gain_of_run(Rxe, Ree, ok, K, b, Rs, Ws, Ks, oks, Rxs, ds):
    """The masked gain of run ``b`` of a block by :func:`_solve_gain` (partial pivoting), copied out
    into the scratch ``Rs``, ``Rxs``, ``oks`` and back into ``K[:, :, b]``."""
    n, m = Rxe.shape[0], Rxe.shape[1]
    for i in range(m):
        oks[i] = ok[i, b]
        for j in range(m):
            Rs[i, j] = Ree[i, j, b]
    for i in range(n):
        for j in range(m):
            Rxs[i, j] = Rxe[i, j, b]
    _solve_gain(Rs, Rxs, oks, Ks, Ws, ds)
    for i in range(n):
        for j in range(m):
            K[i, j, b] = Ks[i, j]


@njit(cache=True, error_model="numpy")
def _mean_update(K, e, xp, x, nb):
    r""":math:`\hat x = \bar x + K e` for a block of runs (the runs on the last axis)."""
    n, m = K.shape[0], K.shape[1]
    for i in range(n):
        for b in range(nb):
            x[i, b] = xp[i, b]
        for l in range(m):
            for b in range(nb):
                x[i, b] += K[i, l, b] * e[l, b]


@njit(cache=True, error_model="numpy")
def _gain(Rxe, Ree, ok, K, e, xp, x, nb, Rs, Ws, Ks, oks, Rxs, ds):
    r"""Block gain and mean update: :math:`K = R_{xe}R_{ee}^{-1}` (masked), :math:`\hat x = \bar x + Ke`.

    Masked channels (``ok`` False) get a zero gain column and ``e`` set to 0."""
    n, m = Rxe.shape[0], Rxe.shape[1]
    if m == 1:
        for b in range(nb):
            good = ok[0, b]
            r = Ree[0, 0, b] if good else 1.0
            for i in range(n):
                K[i, 0, b] = (Rxe[i, 0, b] if good else 0.0) / r
    else:
        for b in range(nb):
            _gain_of_run(Rxe, Ree, ok, K, b, Rs, Ws, Ks, oks, Rxs, ds)
    _mean_update(K, e, xp, x, nb)


@njit(cache=True, error_model="numpy")
def _gain_block(Rxe, Ree, ok, K, e, xp, x, nb, Rw, W, d, bad, Rs, Ws, Ks, oks, Rxs, ds):
    r"""Block gain and mean update for ``m > 1``, vectorised over the runs of the block:
    :math:`K = R_{xe}R_{ee}^{-1}` with channels ``~ok`` removed (zero gain column, ``e`` set to 0),
    :math:`\hat x = \bar x + Ke`; the result of :func:`_gain`, without copying each run out.

    With :math:`D = \mathrm{diag}(R_{ee})^{-1/2}` (as :func:`_solve_gain`), the unit-diagonal
    :math:`S = D R_{ee} D` is symmetric positive definite, so Gaussian elimination *without*
    pivoting is stable on it: :math:`S\,Z = D R_{xe}^T` is solved in place for all runs of the
    block at once (innermost loops over the runs: no dependency, vectorised), and
    :math:`K = (DZ)^T`. ``Ree`` is left unchanged (``Rw`` (m, m, B) holds the elimination,
    ``W`` (m, n, B) the right-hand sides, ``d`` (m, B) the scaling, ``bad`` (B,) the flags). A run
    whose pivot is not positive (a singular or non-finite :math:`R_{ee}`) is solved again by
    :func:`_solve_gain` (partial pivoting, raising like ``numpy.linalg.solve``), so the block path
    changes nothing but the speed. Allocates nothing; ``Rs``, ``Ws``, ``Ks``, ``oks``, ``Rxs``,
    ``ds`` are :func:`_gain`'s per-run scratch for that fallback.
    """
    n, m = Rxe.shape[0], Rxe.shape[1]
    for i in range(m):
        for b in range(nb):
            v = Ree[i, i, b]
            d[i, b] = 1.0 / math.sqrt(v) if (ok[i, b] and v > 0.0) else 1.0
    for i in range(m):
        for j in range(m):
            for b in range(nb):
                if ok[i, b] and ok[j, b]:
                    Rw[i, j, b] = Ree[i, j, b] * d[i, b] * d[j, b]
                else:
                    Rw[i, j, b] = 1.0 if i == j else 0.0
        for k in range(n):
            for b in range(nb):
                W[i, k, b] = Rxe[k, i, b] * d[i, b] if ok[i, b] else 0.0
    for b in range(nb):
        bad[b] = False
    for c in range(m):
        for b in range(nb):
            if not Rw[c, c, b] > 0.0:  # also NaN
                bad[b] = True
                Rw[c, c, b] = 1.0  # keeps the other runs' arithmetic finite; this run is redone
        for q in range(c + 1, m):
            for b in range(nb):
                Rw[q, c, b] = Rw[q, c, b] / Rw[c, c, b]  # the multiplier, stored below the diagonal
            for j in range(c + 1, m):
                for b in range(nb):
                    Rw[q, j, b] -= Rw[q, c, b] * Rw[c, j, b]
            for k in range(n):
                for b in range(nb):
                    W[q, k, b] -= Rw[q, c, b] * W[c, k, b]
    for c in range(m - 1, -1, -1):
        for j in range(c + 1, m):
            for k in range(n):
                for b in range(nb):
                    W[c, k, b] -= Rw[c, j, b] * W[j, k, b]
        for k in range(n):
            for b in range(nb):
                W[c, k, b] = W[c, k, b] / Rw[c, c, b]
    for i in range(n):
        for j in range(m):
            for b in range(nb):
                K[i, j, b] = W[j, i, b] * d[j, b]
    for b in range(nb):
        if bad[b]:
            _gain_of_run(Rxe, Ree, ok, K, b, Rs, Ws, Ks, oks, Rxs, ds)
    _mean_update(K, e, xp, x, nb)


@njit(cache=True, error_model="numpy", inline="always")
def _take_part(Ree, e, ok, m, nb):
    """The channels that take part (``ok``): innovation variance above the smallest normal number and
    innovation not NaN; the innovation of one that does not is set to 0 (both forms of
    :func:`_innovation_moments`)."""
    for l in range(m):
        for b in range(nb):
            good = (Ree[l, l, b] > _TINY) and not math.isnan(e[l, b])
            ok[l, b] = good
            if not good:
                e[l, b] = 0.0


@njit(cache=True, error_model="numpy", inline="always")
def mean_predict(A, x, xp, nb):
    r""":math:`\bar x = A\hat x` for the top ``A.shape[0]`` rows of a block's means (``x``, ``xp`` (dim, B)):
    the mean of both forms of :func:`_predict`, of the fading kernel's block shift and of the steady-state
    kernel."""
    n = A.shape[0]
    for i in range(n):
        for b in range(nb):
            xp[i, b] = 0.0
        for k in range(n):
            a = A[i, k]
            for b in range(nb):
                xp[i, b] += a * x[k, b]


@njit(cache=True, error_model="numpy")
def _innovation_moments(C, Pp, gam, noise, e, CP, Rxe, Ree, ok, nb):
    r"""The moments of a scaled update for a block of runs (the runs on the last axis):
    :math:`R_{xe} = \bar P C^T \Gamma`, :math:`R_{ee} = \Gamma C \bar P C^T \Gamma + N` with
    :math:`\Gamma = \mathrm{diag}(\gamma)` (for the TKF (3.39), (3.40); for the fading TKF (24)-(26) with
    C the augmented measurement matrix, whose zero entries are skipped). A channel takes part
    (``ok``) when its innovation variance is positive and its innovation ``e`` not NaN; the
    innovation of one that does not is set to 0. Writes ``CP`` (m, dim, nb), ``Rxe``, ``Ree``,
    ``ok``, ``e`` in place. From dim = :data:`BLOCKED_N` on by :func:`_innovation_moments_blocked`."""
    m, dim = C.shape
    if dim >= BLOCKED_N:
        _innovation_moments_blocked(C, Pp, gam, noise, e, CP, Rxe, Ree, ok, nb)
        return
    for l in range(m):
        for j in range(dim):
            for b in range(nb):
                CP[l, j, b] = 0.0
            for k in range(dim):
                c = C[l, k]
                if c != 0.0:
                    for b in range(nb):
                        CP[l, j, b] += c * Pp[k, j, b]
    for l in range(m):
        for j in range(dim):
            for b in range(nb):
                Rxe[j, l, b] = CP[l, j, b] * gam[l, b]
        for q in range(m):
            for b in range(nb):
                Ree[l, q, b] = 0.0
            for k in range(dim):
                c = C[q, k]
                for b in range(nb):
                    Ree[l, q, b] += CP[l, k, b] * c
            for b in range(nb):
                Ree[l, q, b] = Ree[l, q, b] * gam[l, b] * gam[q, b]
        for b in range(nb):
            Ree[l, l, b] += noise[l, l, b]
    _take_part(Ree, e, ok, m, nb)


@njit(cache=True, error_model="numpy")
def _innovation_moments_blocked(C, Pp, gam, noise, e, CP, Rxe, Ree, ok, nb):
    r""":func:`_innovation_moments` at larger dim: :math:`C\bar P` row by row over the contiguous slabs
    ``Pp[k]`` of all lanes of the block (as :func:`_predict_blocked`; zero entries of C skipped) and
    :math:`R_{ee}` on its upper triangle, mirrored (measured at n = 16, m = 8: 500 -> 310 ns per run), both
    in register tiles (:func:`_rows_times`, :func:`_sym_times`; in isolation, B = 40, thread CPU time, one
    process, load 4.4: 507 ns per run one row and one term per pass, 334 with the tiles of C P, 231 with
    those of R_ee too)."""
    m, dim = C.shape
    W = Pp.shape[2]
    L = dim * W
    Ppf = Pp.reshape((dim, L))
    CPf = CP.reshape((m, L))
    _rows_times(CPf, C, Ppf, dim, L, True)  # CP[l] = sum_k C[l, k] Pp[k] over the slabs (as _predict_blocked)
    _sym_times(Ree, CP, C, C, False, dim, W, True)  # the upper triangle of C Pbar C^T (scaled below)
    for l in range(m):
        for j in range(dim):
            for b in range(nb):
                Rxe[j, l, b] = CP[l, j, b] * gam[l, b]
        for q in range(l, m):  # symmetric: q >= l, mirrored (C Pbar C^T by _sym_times above)
            for b in range(nb):
                Ree[l, q, b] = Ree[l, q, b] * gam[l, b] * gam[q, b]
                Ree[q, l, b] = Ree[l, q, b]
        for b in range(nb):
            Ree[l, l, b] += noise[l, l, b]
    _take_part(Ree, e, ok, m, nb)


@njit(cache=True, error_model="numpy")
def _cov_update(Pp, K, Rxe, C, gam, noise, joseph, P, MH, nb):
    r"""The covariance update of a block of runs, the one compiled form of every kernel (TKF, KF, fading,
    protocol, the shared step), as the numpy update of :mod:`tobitkf.filters.core`, with the effective
    measurement matrix :math:`H = \mathrm{diag}(\gamma)C` (``C`` (m, n) shared, ``gam`` (m, B) per run):

    standard form :math:`P = \bar P - KR_{xe}^T`; Joseph form
    :math:`(I-KH)\bar P(I-KH)^T + KNK^T`, applied in rank-m products as
    :math:`P = M - (MH^T - KN)K^T`, :math:`M = \bar P - KR_{xe}^T` (the two are equal for
    any gain K with :math:`R_{xe} = \bar PH^T`; O(n^2 m) instead of O(n^3)). ``noise`` (m, m, B) the
    noise term N; ``MH`` (n, m, B) scratch. :math:`MH^T` is formed from the *computed* M, so M's
    rounding error :math:`\delta M` enters P as :math:`\delta M(I - H^TK^T)`, damped as in the
    Joseph form, not as :math:`\delta M` (the reason for this order: with a flat prior the
    cancellation in M is all of P's error otherwise). M and P are computed on the upper triangle and
    mirrored (M is symmetric in exact arithmetic; the mirrored M is the one both steps use). A masked
    channel has a zero gain column, so its row of H does not matter."""
    n, m = K.shape[0], K.shape[1]
    m4 = m - m % 4
    for i in range(n):  # the sum over the channels four terms per pass over the runs (as _sym_times)
        for j in range(i, n):
            for b in range(nb):
                P[i, j, b] = Pp[i, j, b]
            for l in range(0, m4, 4):
                for b in range(nb):
                    P[i, j, b] -= (K[i, l, b] * Rxe[j, l, b] + K[i, l + 1, b] * Rxe[j, l + 1, b]) + (
                        K[i, l + 2, b] * Rxe[j, l + 2, b] + K[i, l + 3, b] * Rxe[j, l + 3, b]
                    )
            for l in range(m4, m):
                for b in range(nb):
                    P[i, j, b] -= K[i, l, b] * Rxe[j, l, b]
    _mirror(P, nb)
    if not joseph:
        return
    for i in range(n):
        for l in range(m):
            for b in range(nb):
                MH[i, l, b] = 0.0
            for k in range(n):
                c = C[l, k]
                if c != 0.0:
                    for b in range(nb):
                        MH[i, l, b] += P[i, k, b] * c
            for b in range(nb):
                MH[i, l, b] = MH[i, l, b] * gam[l, b]
            for q in range(m):
                for b in range(nb):
                    MH[i, l, b] -= K[i, q, b] * noise[q, l, b]
    for i in range(n):
        for j in range(i, n):
            for l in range(m):
                for b in range(nb):
                    P[i, j, b] -= MH[i, l, b] * K[j, l, b]
    _mirror(P, nb)


@njit(cache=True, error_model="numpy", inline="always")
def scaled_update(C, joseph, xp, Pp, e, x, P, scratch, nb):
    r"""The update of a block at the effective measurement matrix :math:`H = \mathrm{diag}(\gamma)C` once its
    channel statistics are in: :math:`R_{xe}`, :math:`R_{ee}` (:func:`_innovation_moments`, ``gam`` and the
    noise term in ``blk``), the masked gain and :math:`\hat x = \bar x + Ke` (:func:`_gain_block` for m > 1,
    :func:`_gain`), the covariance (:func:`_cov_update`, standard or Joseph form): the tail of the Tobit
    update (Miller (3.39)–(3.41)) and of the fading TKF's (Geng et al. (23)–(26), (19), (20')), written once.
    ``C`` (m, dim), ``xp``, ``Pp`` the prediction, ``e`` (m, B) the innovations, ``x``, ``P`` the posterior
    written; ``scratch`` the ``(blk, run, solve, buf)`` of :func:`_update_scratch`."""
    blk, run, solve, _buf = scratch
    _P, _Pp, _AP, CP, Rxe, Ree, K, MH, noise, gam, ok = blk
    Rs, Ws, Ks, oks, Rxs, ds = run
    Rw, Wb, db, bad = solve
    _innovation_moments(C, Pp, gam, noise, e, CP, Rxe, Ree, ok, nb)
    if C.shape[0] > 1:
        _gain_block(Rxe, Ree, ok, K, e, xp, x, nb, Rw, Wb, db, bad, Rs, Ws, Ks, oks, Rxs, ds)
    else:
        _gain(Rxe, Ree, ok, K, e, xp, x, nb, Rs, Ws, Ks, oks, Rxs, ds)
    _cov_update(Pp, K, Rxe, C, gam, noise, joseph, P, MH, nb)


@njit(cache=True, error_model="numpy")
def _load(x0, P0, r0, nb, x, P):
    n = x.shape[0]
    for b in range(nb):
        for i in range(n):
            x[i, b] = x0[r0 + b, i]
            for j in range(n):
                P[i, j, b] = P0[r0 + b, i, j]


@njit(cache=True, error_model="numpy")
def _stage(xv, Pv, tt, nb, mbuf, cbuf):
    """Copy a block's x[i, b], P[i, j, b] into the staging buffers at chunk step ``tt`` (:func:`_stage_mean`,
    :func:`_stage_cov`); a buffer with no steps (that output was not requested) is skipped."""
    _stage_mean(xv, mbuf, tt, nb)
    _stage_cov(Pv, cbuf, tt, nb)


@njit(cache=True, error_model="numpy")
def _stage_mean(xv, mbuf, tt, nb):
    """Copy the top ``d`` rows of a block's x[i, b] (d = ``mbuf.shape[1]`` at most the state size) into the
    staging buffer ``mbuf`` (S, d, B) at chunk step ``tt``; with d = w + n_x above the state size n_x, its top
    w rows and then all n_x (the fading TKF's mean and its smoothed blocks in one output: no copy of the
    mean out of them afterwards). Skipped when ``mbuf`` has no steps."""
    if mbuf.shape[0] == 0:
        return
    d, nx = mbuf.shape[1], xv.shape[0]
    off = d - nx if d > nx else 0
    for i in range(d):
        ii = i - off if i >= off else i
        for b in range(nb):
            mbuf[tt, i, b] = xv[ii, b]


@njit(cache=True, error_model="numpy")
def _stage_rows(v, buf, tt, nb):
    """Copy a block's values ``v`` (d, B) into the staging buffer ``buf`` (S, ..., B) (d numbers per run-step)
    at chunk step ``tt``; skipped when ``buf`` has no steps (that output was not requested)."""
    if buf.shape[0] == 0:
        return
    d = v.shape[0]
    dst = buf.reshape((buf.shape[0], d, buf.shape[buf.ndim - 1]))
    for i in range(d):
        for b in range(nb):
            dst[tt, i, b] = v[i, b]


@njit(cache=True, error_model="numpy")
def _stage_cov(Pv, cbuf, tt, nb):
    """Copy the top-left ``n x n`` block of a block's P[i, j, b] (n = ``cbuf.shape[1]``) into the staging
    buffer ``cbuf`` (S, n, n, B) at chunk step ``tt``, or only its diagonal into ``cbuf`` (S, n, 1, B) (the
    variances, for ``outputs=("var",)``: no (N, T, n, n) array), or, for ``cbuf`` (S, n_x, w, B) with w < n_x,
    the w x w diagonal blocks of an augmented state, stacked (row s w + i, column j: P[s w + i, s w + j]; the
    fading TKF's smoothed covariances), or for ``cbuf`` (S, w + n_x, w, B) the top w x w block and then those
    diagonal blocks (the fading TKF's covariance and its smoothed covariances in one output); skipped when
    ``cbuf`` has no steps."""
    if cbuf.shape[0] == 0:
        return
    n, w = cbuf.shape[1], cbuf.shape[2]
    nx = Pv.shape[0]
    off = n - nx if n > nx else 0  # rows of the top block ahead of the diagonal blocks
    if w == 1:  # the variances (a scalar state's 1 x 1 blocks too, after its top block when off = 1)
        for i in range(n):
            ii = i - off if i >= off else i
            for b in range(nb):
                cbuf[tt, i, 0, b] = Pv[ii, ii, b]
        return
    if w < n:
        for i in range(n):
            ii = i - off if i >= off else i
            o = ii - ii % w
            for j in range(w):
                for b in range(nb):
                    cbuf[tt, i, j, b] = Pv[ii, o + j, b]
        return
    for i in range(n):
        for j in range(n):
            for b in range(nb):
                cbuf[tt, i, j, b] = Pv[i, j, b]


@njit(cache=True, error_model="numpy")
def _flush(buf, out, r0, t0, nb, cnt):
    """Write ``cnt`` staged steps of ``nb`` runs, ``buf[tt, ..., b]`` (S, ..., B), to
    ``out[r0 + b, t0:t0 + cnt]`` (the transpose; contiguous writes per run). An output with no time axis
    (``out.shape[1] == 0``) was not requested and is skipped."""
    if out.shape[1] == 0:
        return
    S, B = buf.shape[0], buf.shape[buf.ndim - 1]
    d = buf.size // (S * B)
    src = buf.reshape((S, d, B))
    if d >= FLUSH_BY_STEP:
        # large per-step blocks (n = 16: d = 256, a 4 MB buffer): step by step, so that the strided
        # reads stay in one step's slab (d * B * 8 bytes, in cache) instead of sweeping the whole
        # buffer once per run (measured: n = 16, m = 8, all outputs 8.0-11.5 us against 5.0 us per
        # run-step for the run-major loop order before the (S, ..., B) layout)
        # (then 8 x 8 tiles, below)
        dst = out.reshape((out.shape[0], out.shape[1] * d))
        b8, d8 = nb - nb % 8, d - d % 8
        for s in range(cnt):
            o = (t0 + s) * d
            for b0 in range(0, b8, 8):
                # 8 runs x 8 numbers at a time (measured in isolation at d = 256, B = 32, 200 MB of
                # outputs: 303 -> 185 ns per run-step against one run at a time): the eight strided
                # reads of a run share their cache lines with the tile's other runs, and each run's
                # eight writes fill a whole cache line at once
                for q0 in range(0, d8, 8):
                    for u in range(8):
                        for v in range(8):
                            dst[r0 + b0 + u, o + q0 + v] = src[s, q0 + v, b0 + u]
                for u in range(8):
                    for q in range(d8, d):
                        dst[r0 + b0 + u, o + q] = src[s, q, b0 + u]
            for b in range(b8, nb):
                for q in range(d):
                    dst[r0 + b, o + q] = src[s, q, b]
        return
    for b in range(nb):
        dst = out[r0 + b, t0 : t0 + cnt].reshape(-1)
        for s in range(cnt):
            for q in range(d):
                dst[s * d + q] = src[s, q, b]


@njit(cache=True, error_model="numpy")
def _store_last(xv, Pv, r0, nb, x_last, P_last):
    """The block's state after its last step into ``x_last[r0 + b]``, ``P_last[r0 + b]``."""
    n = xv.shape[0]
    for b in range(nb):
        for i in range(n):
            x_last[r0 + b, i] = xv[i, b]
            for j in range(n):
                P_last[r0 + b, i, j] = Pv[i, j, b]


@njit(cache=True, error_model="numpy")
def predict_block(A, Qd, x, P, xp, Pp, AP, nb):
    r""":math:`\bar x = A\hat x`, :math:`\bar P = \mathrm{sym}(APA^T + Q)` of a block of runs (the predict of
    :func:`~tobitkf.filters._compiled_loop.compiled_loop`, shared with the compiled closed loop of :mod:`tobitkf.control`);
    ``x`` (n, B), ``P`` (n, n, B) in, ``xp``, ``Pp`` out, ``AP`` (n, n, B) scratch."""
    _predict(A, Qd, x, P, xp, Pp, AP, nb)


# the output staging of the kernels, shared with the compiled closed loop of tobitkf.control: stage_block
# copies a block's (dim, B) [and (n, n, B)] arrays into (S, ..., B) buffers at a chunk step, flush_rows
# writes the staged steps run by run into the (N, T, ...) outputs (see CHUNK)
stage_block = _stage
flush_rows = _flush
stage_shape = _stage_shape


@njit(cache=True, inline="always")
def block_scratch(n, m, B, G):
    """The block scratch of a Kalman-type step of ``B`` runs (state size ``n``, ``m`` channels, ``G``
    quadrature nodes): ``(x, xp, e, ey)`` of :func:`_mean_scratch` and ``(blk, run, solve, buf)`` of
    :func:`_update_scratch`, for a kernel outside this module (the compiled closed loop)."""
    return _mean_scratch(n, m, B), _update_scratch(n, n, m, B, G)
