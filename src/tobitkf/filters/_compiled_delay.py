r"""Compiled (numba) covariance step of the reorganized-innovation LMMSE (Algorithm D of the delay module).

:func:`reorg_cov_step` is :meth:`tobitkf.filters.delay_reorganized.ReorganizedInnovationLMMSE._cov_step`, the numpy
reference, on the same flat ring buffer (layout: :func:`tobitkf.filters.delay._ring_layout`, whose field
offsets are passed in ``offs``): the data-independent part of one step t >= warmup, (a)–(f) of
:func:`~tobitkf.filters.delay_reorganized.reorganized_lmmse` without the means, the moments of Λ(t-d) (R(t), J(t),
Ā(t), Σ(t), Λ(t+1), corrected recursion LD-E2), and the gains the means read. Covered: fading and
multiplicative-noise laws that do not change with t (γ̄, σ², Q_ζ constant), both decorrelation modes and
the re-inserted errata. The products are written as loops (the blocks are n x n with n of a few) into arrays
the step was handed (no array per product), so the results equal the numpy step's to rounding, not bitwise
(tested to 1e-12).
:func:`delay_moments` is the first part, the moments of Λ(t-d), on its own: the chain LMMSE's compiled
moments (Algorithm C), the same code as the reorganized step's.
Compiled on first use and cached on disk; importing this module imports numba.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .._compiled_linalg import gauss_solve

__all__ = ["reorg_cov_step", "reorg_step", "delay_moments", "aug_step", "chain_step"]


@njit(cache=True, error_model="numpy", inline="always")
def _mm(A, B, ta, tb):
    """op(A) op(B) with op the transpose where ``ta``/``tb``; a new array (:func:`_gemm` into it)."""
    out = np.empty((A.shape[1] if ta else A.shape[0], B.shape[0] if tb else B.shape[1]))
    _gemm(out, A, B, ta, tb, 1.0, False)
    return out


@njit(cache=True, error_model="numpy", inline="always")
def _sym_into(M, out):
    """out = (M + M^T) / 2."""
    n = M.shape[0]
    for i in range(n):
        for j in range(n):
            out[i, j] = 0.5 * (M[i, j] + M[j, i])


@njit(cache=True, error_model="numpy", inline="always")
def _right_inverse(B, M):
    """B M^{-1} for a symmetric (m, m) M: (M^{-1} B^T)^T; a division for m = 1 (as the numpy step); a new
    array (:func:`_right_inverse_into` into it)."""
    p, m = B.shape
    out = np.empty((p, m))
    _right_inverse_into(out, B, False, M, np.empty((m, m)), np.empty((m, p)))
    return out


# --------------------------------------------------------------------------- products into preallocated arrays
#
# The covariance step writes every product into an array it was handed (a view of the ring, of the output, or of
# one work array allocated once per call), not into a new array per product as ``_mm`` does. The reorganized step
# of the online benchmark (d = 3, n = 2, m = 1) formed some 80 small arrays per call; also gone: the fifteen
# reshapes of the ring's fields done twice per whole step (numba's reshape helper, ~35 ns each; now five, once) and
# the five arrays of the means (written into the output). In-process A/B, thread CPU time, median of 15 x 5000
# calls, load ~2: ``reorg_step`` 8.6 -> 4.8 µs, ``reorg_cov_step`` (20 arguments: ~1 µs of it is the call)
# 7.2 -> 4.5 µs. Each element is formed in ``_mm``'s order (its sum from 0.0 over j) and scaled and added as the
# array expression it replaces (``Y + a X`` as ``Y + a s``; ``Y - g X`` as ``Y + (-g) s``, the same number, as
# negation is exact), so the results are bitwise those of the former kernel (checked on every ring field and
# output over 120 steps of d = 1..4, one and two channels, both decorrelations, with and without the errata).


@njit(cache=True, error_model="numpy", inline="always")
def _gemm(out, A, B, ta, tb, alpha, acc):
    """``out = alpha op(A) op(B)``, or ``out += alpha op(A) op(B)`` when ``acc`` (op the transpose where
    ``ta``/``tb``); ``out`` must not share memory with ``A`` or ``B``."""
    p = A.shape[1] if ta else A.shape[0]
    q = A.shape[0] if ta else A.shape[1]
    r = B.shape[0] if tb else B.shape[1]
    for i in range(p):
        for k in range(r):
            s = 0.0
            for j in range(q):
                s += (A[j, i] if ta else A[i, j]) * (B[k, j] if tb else B[j, k])
            if acc:
                out[i, k] += alpha * s
            else:
                out[i, k] = alpha * s


@njit(cache=True, error_model="numpy", inline="always")
def _copy_into(out, M, transpose):
    """``out = M`` (``M^T`` when ``transpose``)."""
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            out[i, j] = M[j, i] if transpose else M[i, j]


@njit(cache=True, error_model="numpy", inline="always")
def _right_inverse_into(out, B, bt, M, Mw, X):
    """``out = B M^{-1}`` (p, m) for a symmetric (m, m) ``M`` and ``B`` (p, m) (given as its transpose (m, p)
    when ``bt``), as :func:`_right_inverse` (a division for m = 1, else ``M^{-1} B^T`` by :func:`gauss_solve`);
    ``Mw`` (m, m) and ``X`` (m, p) are work arrays."""
    m = M.shape[0]
    if m == 1:
        d = M[0, 0]
        for i in range(out.shape[0]):
            out[i, 0] = (B[0, i] if bt else B[i, 0]) / d
        return
    _copy_into(X, B, not bt)
    _copy_into(Mw, M, False)
    gauss_solve(Mw, X)
    _copy_into(out, X, True)


#: the number of (L, L) work blocks :func:`_moments_into` takes (L = max(n, m, p))
_MOMENTS_WORK = 12


@njit(cache=True, error_model="numpy", inline="always")
def _work(n, m, p, k):
    """``k`` work blocks (k, L, L), L = max(n, m, p): a block ``w[i, :r, :c]`` is a view formed inline (a reshape
    of a flat work array calls numba's reshape helper, some 13 ns a view, a fifth of the step's arithmetic)."""
    L = max(n, m, p)
    return np.empty((k, L, L))


@njit(cache=True, error_model="numpy")
def _moments_into(
    Lam, A, H, Qv, G, S, Qw, GQG, Ai, q, SQvi, eta, gb, s2, optimal, lam_next, J_out, abar_out, sig_out, Rt, w
):
    r"""What time t needs of the second moment Λ(t-d) = ``Lam`` (the numpy
    :func:`tobitkf.filters.delay._moments_at`): writes Λ(t+1) = sym(AΛA^T + Q_u(t)) (LD-E2), J(t), Ā(t) and
    Σ(t) of the decorrelated predictor into the ``*_out`` arrays and R(t) = Q_v + σ²HΛH^T into ``Rt`` (m, m);
    ``w`` holds :data:`_MOMENTS_WORK` work blocks (:func:`_work`; no array is allocated)."""
    n = A.shape[0]
    m = H.shape[0]
    p = G.shape[1]
    HLH, HL, mult, T = w[0, :m, :m], w[1, :m, :n], w[2, :n, :n], w[3, :n, :n]
    Lq, Sigma, SRinv, Mw = w[4, :n, :n], w[5, :n, :n], w[6, :p, :m], w[7, :m, :m]
    X, Tpp, Tnp, Tnm = w[8, :m, :p], w[9, :p, :p], w[10, :n, :p], w[11, :n, :m]
    _gemm(HL, H, Lam, False, False, 1.0, False)
    _gemm(HLH, HL, H, False, True, 1.0, False)
    for i in range(m):
        for j in range(m):
            Rt[i, j] = Qv[i, j] + s2 * HLH[i, j]
    mult[:, :] = 0.0
    for i in range(q.shape[0]):
        _gemm(T, Ai[i], Lam, False, False, 1.0, False)
        _gemm(mult, T, Ai[i], False, True, q[i], True)
    for i in range(n):
        for j in range(n):
            Lq[i, j] = mult[i, j] + GQG[i, j]
    _gemm(T, A, Lam, False, False, 1.0, False)
    _gemm(Lq, T, A, False, True, 1.0, True)
    _sym_into(Lq, lam_next)
    _copy_into(Sigma, mult, False)
    if optimal:
        _right_inverse_into(SRinv, S, False, Rt, Mw, X)  # S R^{-1}  (p, m)
        _gemm(J_out, G, SRinv, False, False, 1.0, False)
        _copy_into(Tpp, Qw, False)
        _gemm(Tpp, SRinv, S, False, True, -1.0, True)
        _gemm(Tnp, G, Tpp, False, False, 1.0, False)
        _gemm(Sigma, Tnp, G, False, True, 1.0, True)
    else:
        _gemm(J_out, G, SQvi, False, False, 1.0, False)
        _gemm(Tnp, G, eta, False, False, 1.0, False)
        _gemm(Sigma, Tnp, G, False, True, 1.0, True)
        _gemm(Tnm, J_out, HLH, False, False, 1.0, False)
        _gemm(Sigma, Tnm, J_out, False, True, s2, True)
    _copy_into(abar_out, A, False)
    _gemm(abar_out, J_out, H, False, False, -gb, True)
    _sym_into(Sigma, sig_out)


@njit(cache=True, error_model="numpy")
def delay_moments(Lam, A, H, Qv, G, S, Qw, GQG, Ai, q, SQvi, eta, gb, s2, optimal):
    """:func:`_moments_into` into new arrays: ``(R (m, m), J (n, m), Ā (n, n), Σ (n, n), Λ(t+1) (n, n))``, the
    chain LMMSE's step (Algorithm C) for laws constant in t."""
    n, m = A.shape[0], H.shape[0]
    lam_next, J, Abar, Sigma = np.empty((n, n)), np.empty((n, m)), np.empty((n, n)), np.empty((n, n))
    Rt = np.empty((m, m))
    w = _work(n, m, G.shape[1], _MOMENTS_WORK)
    _moments_into(Lam, A, H, Qv, G, S, Qw, GQG, Ai, q, SQvi, eta, gb, s2, optimal, lam_next, J, Abar, Sigma, Rt, w)
    return Rt, J, Abar, Sigma, lam_next


@njit(cache=True, error_model="numpy", inline="always")
def _ring_fields(ring, offs, d, W, n, m):
    """The fields psi, kh, pf, psm, pmeas, pp, pm, lam, abar, sig, j, qe, kf, ks, ke of the flat ring buffer
    (layout :func:`tobitkf.filters.delay._ring_layout`: the fields one after the other in this order, from
    the offsets ``offs``) as views.

    Five reshapes, not one per field: a reshape in a compiled function calls numba's reshape helper (some
    35 ns for these 3- and 4-d views; the fifteen fields took 0.54 µs, two of them a step), while an integer
    index of a reshaped group is a view formed inline: Ψ and K H are one (2, W, d+1, n, n) block, the eight
    (W, n, n) covariance fields one (8, W, n, n), and the gains K_f, K_s, K_e one (d+1 or 3, n, m) (their
    offsets are consecutive by the layout)."""
    nn, nm = n * n, n * m
    nks = max(d - 1, 1)
    pk = ring[offs[0] : offs[0] + 2 * W * (d + 1) * nn].reshape((2, W, d + 1, n, n))
    cv = ring[offs[2] : offs[2] + 8 * W * nn].reshape((8, W, n, n))
    gains = ring[offs[12] : offs[12] + (nks + 2) * nm].reshape((nks + 2, n, m))
    return (
        pk[0], pk[1],
        cv[0], cv[1], cv[2], cv[3], cv[4], cv[5], cv[6], cv[7],
        ring[offs[10] : offs[10] + W * nm].reshape((W, n, m)),
        ring[offs[11] : offs[11] + W * m * m].reshape((W, m, m)),
        gains[0], gains[1 : nks + 1], gains[nks + 1],
    )  # fmt: skip


@njit(cache=True, error_model="numpy")
def reorg_cov_step(ring, t, offs, d, W, A, H, Qv, G, S, Qw, GQG, Ai, q, SQvi, eta, gconst, s2, optimal, e5, e6, e7):
    """One covariance step t >= warmup of Algorithm D on ``ring`` (in place); see the module docstring.

    ``offs`` are the offsets of the fields psi, kh, pf, psm, pmeas, pp, pm, lam, abar, sig, j, qe, kf, ks,
    ke (in this order); ``gconst``/``s2`` the fading law's mean and variance; ``optimal`` the
    decorrelation mode; ``e5``/``e6``/``e7`` the re-inserted errata.
    """
    F = _ring_fields(ring, offs, d, W, A.shape[0], H.shape[0])
    _reorg_cov(F, t, d, W, A, H, Qv, G, S, Qw, GQG, Ai, q, SQvi, eta, gconst, s2, optimal, e5, e6, e7)


@njit(cache=True, error_model="numpy")
def _reorg_cov(F, t, d, W, A, H, Qv, G, S, Qw, GQG, Ai, q, SQvi, eta, gconst, s2, optimal, e5, e6, e7):
    """:func:`reorg_cov_step` on the ring's fields ``F`` (:func:`_ring_fields`, formed once by the caller)."""
    n = A.shape[0]
    m = H.shape[0]
    p = G.shape[1]
    psi, kh, pf, psm, pmeas, pp, pm, lam, abar, sig, jj, qe, kf, ks, ke = F
    st = t % W
    gb = gconst
    # the work blocks of the step (one array): R(t), Q_ε, H^T Q_ε^{-1}, H^T Q_ε(s)^{-1}, three n x n blocks, the
    # solve's work (m x m and m x n), then the moments' own
    w = _work(n, m, p, 9 + _MOMENTS_WORK)
    Rt, Q, HtQi, Hq = w[0, :m, :m], w[1, :m, :m], w[2, :n, :m], w[3, :n, :m]
    T1, T2, T3, Mw, X = w[4, :n, :n], w[5, :n, :n], w[6, :n, :n], w[7, :m, :m], w[8, :m, :n]
    wm = w[9:]

    # moments of Λ(t-d): R(t), the multiplicative term, Λ(t+1), J(t), Ā(t), Σ(t)
    _moments_into(
        lam[(t - d) % W], A, H, Qv, G, S, Qw, GQG, Ai, q, SQvi, eta, gb, s2, optimal,
        lam[(t + 1) % W], jj[st], abar[st], sig[st], Rt, wm,
    )  # fmt: skip

    # (a) innovation covariance (15); P(t-d|t-1) = last step's smoother covariance, kept as pm[st]
    Pmp = pm[st]
    _copy_into(Pmp, psm[(t - 1) % W], False)
    _gemm(X, H, Pmp, False, False, 1.0, False)
    _copy_into(Q, Rt, False)
    _gemm(Q, X, H, False, True, gb * gb, True)
    if m > 1:
        _sym_into(Q, qe[st])
    else:
        qe[st, 0, 0] = Q[0, 0]
    Q = qe[st]
    _right_inverse_into(HtQi, H, True, Q, Mw, X)  # H^T Q_ε^{-1}  (n, m)
    # (b) filter
    Psd = psi[(t + d - 1) % W, d]
    _gemm(kf, Psd, HtQi, True, False, gb, False)
    KfH = kh[st, 0]
    _gemm(KfH, kf, H, False, False, 1.0, False)
    _copy_into(T1, pp[st], False)
    _gemm(T1, KfH, Psd, False, False, -gb, True)
    _sym_into(T1, pf[st])
    # (c) Ψ_i(t), i = d-1..1, corrected (58)
    if t - d >= 0:
        Abar_td = abar[(t - d) % W]
        g_md = gconst
    else:
        Abar_td = A
        g_md = 0.0
    g_md1 = gconst if t - d + 1 >= 0 else 0.0
    psi_d = psi[st, d]  # read transposed under E6 (not written below: i < d)
    Pm_td = pm[(t - d) % W]
    for i in range(d - 1, 0, -1):
        a = t - d - i + 1
        a5 = a - 1 if e5 else a
        val = psi[st, i]  # written in place: the terms read Ψ_k(t) only for k > i, and other times' Ψ
        _copy_into(T1, psi[(t - i) % W, d - i + 1], True)
        _gemm(T1, kh[(t - d) % W, t - d - a5], Pm_td, False, False, -g_md, True)
        _gemm(val, T1, Abar_td, False, True, 1.0, False)
        _gemm(val, kh[(t - d + 1) % W, t - d + 1 - a], psi_d, False, e6, -g_md1, True)
        top = d - 1 - i if e7 else d - 2 - i
        for j in range(0, top + 1):
            s = t - i - j
            g_s = gconst if s >= 0 else 0.0
            _gemm(val, kh[s % W, s - a], psi[st, i + j + 1], False, False, -g_s, True)
    # (d) fixed-lag d-1 smoother covariance (55)-(57), a = t-d+1
    a = t - d + 1
    _copy_into(T2, pf[a % W], False)
    for i in range(1, d):
        s = t - i + 1
        if s < 0:
            continue
        psi_i = psi[st, i]
        _right_inverse_into(Hq, H, True, qe[s % W], Mw, X)  # H^T Q_ε(s)^{-1}
        Ks = ks[i - 1]
        _gemm(Ks, psi_i, Hq, True, False, gconst, False)
        KsH = kh[s % W, s - a]
        _gemm(KsH, Ks, H, False, False, 1.0, False)
        _gemm(T2, KsH, psi_i, False, False, -gconst, True)
    _sym_into(T2, psm[st])
    # (e) delayed filter and predictor covariances (50)-(52)
    _gemm(ke, Pmp, HtQi, False, False, gb, False)
    KeH = kh[st, d]
    _gemm(KeH, ke, H, False, False, 1.0, False)
    _copy_into(T1, Pmp, False)
    _gemm(T1, KeH, Pmp, False, False, -gb, True)
    _sym_into(T1, pmeas[st])
    Ab = abar[st]
    _gemm(T1, Ab, pmeas[st], False, False, 1.0, False)
    _copy_into(T2, sig[st], False)
    _gemm(T2, T1, Ab, False, True, 1.0, True)
    _sym_into(T2, pp[(t + 1) % W])
    # (f) corrected (39): Ψ_d(t+d) = {Ā(t)[Ψ_1(t) - γ̄ K(t-d|t) H Ψ_1(t)]}^T
    psi1 = psi[st, 1]
    _copy_into(T1, psi1, False)
    _gemm(T1, KeH, psi1, False, False, -gb, True)
    _gemm(T3, Ab, T1, False, False, 1.0, False)
    _copy_into(psi[(t + d) % W, d], T3, True)


# --------------------------------------------------------------------------- whole online steps (Algorithms A, C, D)
#
# A compiled call pays about 0.06 µs per argument: the whole steps of C and D take the model's constants packed
# in one float array ``cb`` and one integer array ``ib`` (:func:`tobitkf.filters.delay._packed_moment_args`).


@njit(cache=True, error_model="numpy", inline="always")
def _take(cb, o, r, c):
    """The (r, c) block of ``cb`` at offset ``o`` (a view) and the offset after it."""
    return cb[o : o + r * c].reshape((r, c)), o + r * c


@njit(cache=True, error_model="numpy", inline="always")
def _unpack_moments(cb, ib):
    """The constant arguments of :func:`_moments_into` after Λ from the packed ``cb`` (A, H, Q_v, Γ, S, Q_w,
    ΓQ_wΓ^T, A_i, q, SQ_v^{-1}, η row-major, then γ̄, σ²) and ``ib`` (n, m, p, h, optimal, ...): views of ``cb``."""
    n, m, p, h = ib[0], ib[1], ib[2], ib[3]
    A, o = _take(cb, 0, n, n)
    H, o = _take(cb, o, m, n)
    Qv, o = _take(cb, o, m, m)
    G, o = _take(cb, o, n, p)
    S, o = _take(cb, o, p, m)
    Qw, o = _take(cb, o, p, p)
    GQG, o = _take(cb, o, n, n)
    Ai, o = cb[o : o + h * n * n].reshape((h, n, n)), o + h * n * n
    q, o = cb[o : o + h], o + h
    SQvi, o = _take(cb, o, p, m)
    eta, o = _take(cb, o, p, p)
    return A, H, Qv, G, S, Qw, GQG, Ai, q, SQvi, eta, cb[o], cb[o + 1], ib[4] != 0


#
# A compiled function returning a tuple of k arrays pays about a microsecond to box each (dominant in a step
# of one run), and even one returned array a few tenths (numba unpickles its type at every call): the whole-step
# kernels write their outputs into one flat array ``out`` the caller allocates, the 2-D blocks in a fixed order
# and the trace of the step's covariance last, and :func:`tobitkf.filters.delay._flat_views` cuts the views.


@njit(cache=True, error_model="numpy", inline="always")
def _put(out, o, M):
    """Copy the 2-D ``M`` row-major into ``out[o:]``; the offset after it."""
    r, c = M.shape
    for i in range(r):
        for j in range(c):
            out[o + i * c + j] = M[i, j]
    return o + r * c


@njit(cache=True, error_model="numpy", inline="always")
def _flat_into(out, blocks, P):
    """The 2-D arrays of the tuple ``blocks`` one after the other in the flat ``out``, then the trace of the
    square ``P`` (the step's covariance: the caller's check that it is finite, without a numpy call)."""
    o = 0
    for M in blocks:
        o = _put(out, o, M)
    tr = 0.0
    for i in range(P.shape[0]):
        tr += P[i, i]
    out[o] = tr


@njit(cache=True, error_model="numpy", inline="always")
def _innovation_row(e, y, x, H, gb, r):
    """Row r of the innovation ε = y - γ̄ H x (``e``, ``y`` (N, m), ``x`` (N, n_x), ``H`` (m, n_x))."""
    for l in range(H.shape[0]):
        acc = 0.0
        for j in range(H.shape[1]):
            acc += H[l, j] * x[r, j]
        e[r, l] = y[r, l] - gb * acc


@njit(cache=True, error_model="numpy", inline="always")
def _predict_row(out, Abar, x, J, y, r):
    """Row r of the decorrelated prediction Ā x + J y (``out``, ``x`` (N, n_x), ``y`` (N, m))."""
    for i in range(Abar.shape[0]):
        acc = 0.0
        for j in range(Abar.shape[1]):
            acc += Abar[i, j] * x[r, j]
        for l in range(J.shape[1]):
            acc += J[i, l] * y[r, l]
        out[r, i] = acc


@njit(cache=True, error_model="numpy")
def _update_predict(x, P, y, gb, H, Rn, Abar, Qd, J):
    r"""The shared update and decorrelated predict of Algorithms A and C for one covariance ``P`` (n_x, n_x)
    common to the N runs (the numpy :func:`~tobitkf.filters.core.measurement_update`, standard form, and
    :func:`~tobitkf.filters.core.time_update` with a :class:`~tobitkf.filters.core.Transition`):

    .. math::

        R_{xe} = \bar\gamma PH^T,\ Q_\varepsilon = \bar\gamma HR_{xe} + R_n,\ K = R_{xe}Q_\varepsilon^{-1},\
        \varepsilon = y - \bar\gamma H x,\ \hat x = x + K\varepsilon,\ P^+ = \mathrm{sym}(P - KR_{xe}^T), \\
        x^- = \bar A\hat x + Jy,\ P^- = \mathrm{sym}(\bar AP^+\bar A^T + Q_d).

    ``x`` (N, n_x), ``y`` (N, m), ``H`` (m, n_x). Returns ``(x̂ (N, n_x), P⁺, x⁻ (N, n_x), P⁻, K (n_x, m),
    Q_ε (m, m), ε (N, m))``."""
    N, nx = x.shape
    m = H.shape[0]
    Rxe = gb * _mm(P, H, False, True)
    Q = gb * _mm(H, Rxe, False, False) + Rn
    if m > 1:
        Qs = np.empty((m, m))
        _sym_into(Q, Qs)
        Q = Qs
    K = _right_inverse(Rxe, Q)
    eps = np.empty((N, m))
    xf = np.empty((N, nx))
    xp = np.empty((N, nx))
    for r in range(N):
        _innovation_row(eps, y, x, H, gb, r)
        for i in range(nx):
            acc = x[r, i]
            for l in range(m):
                acc += K[i, l] * eps[r, l]
            xf[r, i] = acc
        _predict_row(xp, Abar, xf, J, y, r)
    Pf = np.empty((nx, nx))
    _sym_into(P - _mm(K, Rxe, False, True), Pf)
    Pp = np.empty((nx, nx))
    _sym_into(_mm(_mm(Abar, Pf, False, False), Abar, False, True) + Qd, Pp)
    return xf, Pf, xp, Pp, K, Q, eps


@njit(cache=True, error_model="numpy")
def aug_step(X, P, LamX, y, AA, Ai, q, HH, GQG, GS_T, Qv, gb, s2, out):
    r"""One reading of Algorithm A for one covariance common to the runs (the numpy
    :func:`tobitkf.filters.delay_augmented._aug_step`, standard form, for laws constant in t):
    :math:`R = \mathrm{sym}(\sigma^2\mathfrak h\Lambda_X\mathfrak h^T + Q_v)`, the update of X(t|t-1) with
    :math:`H = \bar\gamma\mathfrak h`, then :math:`J = \mathfrak G SR^{-1}`, :math:`\bar A = \mathfrak A - \bar\gamma J\mathfrak h`,
    :math:`Q_u = \mathfrak G Q_w\mathfrak G^T + \sum_i q_i\mathfrak A_i\Lambda_X\mathfrak A_i^T`,
    X(t+1|t) = ĀX(t|t) + Jy, P(t+1|t) = sym(ĀPĀ^T + sym(Q_u - JRJ^T)), Λ_X(t+1) = sym(𝔄Λ_X𝔄^T + Q_u).
    ``X`` (N, n_x), ``P``/``LamX`` (n_x, n_x), ``y`` (N, m). Writes X(t|t) (N, n_x), X(t+1|t) (N, n_x),
    ε (N, m), P(t|t), P(t+1|t), Q_ε (m, m) and Λ_X(t+1) one after the other, then trace P(t|t), in ``out``
    (:func:`_flat_into`)."""
    nx = X.shape[1]
    m = HH.shape[0]
    R = np.empty((m, m))
    _sym_into(s2 * _mm(_mm(HH, LamX, False, False), HH, False, True) + Qv, R)
    Qu = GQG.copy()
    for i in range(q.shape[0]):
        Qu += q[i] * _mm(_mm(Ai[i], LamX, False, False), Ai[i], False, True)
    J = _right_inverse(np.ascontiguousarray(GS_T.T), R)  # 𝔊S R^{-1} (n_x, m)
    Abar = AA - gb * _mm(J, HH, False, False)
    Qd = np.empty((nx, nx))
    _sym_into(Qu - _mm(_mm(J, R, False, False), J, False, True), Qd)
    Xf, Pf, Xp, Pp, _, Qe, eps = _update_predict(X, P, y, gb, HH, R, Abar, Qd, J)
    Lam_next = np.empty((nx, nx))
    _sym_into(_mm(_mm(AA, LamX, False, False), AA, False, True) + Qu, Lam_next)
    _flat_into(out, (Xf, Xp, eps, Pf, Pp, Qe, Lam_next), Pf)


@njit(cache=True, error_model="numpy")
def chain_step(x, P, x_pred, P_pred, Lam, y, cb, ib, out):
    r"""One plain reading y(t) of Algorithm C (no lags beyond the window, horizons or fixed point; the numpy
    :meth:`tobitkf.filters.delay_chain.ChainLMMSE._step_arrays`) for one covariance common to the runs.

    ``x`` (N, n(d+1)), ``P`` (n(d+1), n(d+1)) the window x̂(t-1-k|t-1), k = 0..d, after the last reading;
    ``x_pred`` (N, n), ``P_pred`` (n, n) the prediction x̂(t|t-1); ``Lam`` Λ(t-d) of the measured element.
    The moments of Λ(t-d) (:func:`_moments_into`), the update of x(t-d) and the decorrelated predict
    (:func:`_update_predict`, with :math:`\bar\gamma H`, R(t), Ā(t), Σ(t), J(t)). (The cross-covariance Φ of
    the measured element is not formed: a plain step drops the element from the carry.) Writes the window
    x̂(t-k|t) (N, n(d+1)), the window before the reading x̂(t-k|t-1), x̂(t+1|t) (N, n), ε (N, m), the two
    windows' (block-diagonal) covariances, P(t+1|t), Q_ε (m, m) and Λ(t+1) (n, n) one after the other, then the
    trace of the new window's covariance, in ``out`` (:func:`_flat_into`). ``cb``, ``ib``: the packed constants
    (:func:`_unpack_moments`; ``ib[5]`` = d)."""
    A, H, Qv, G, S, Qw, GQG, Ai, q, SQvi, eta, gb, s2, optimal = _unpack_moments(cb, ib)
    d = ib[5]
    N = x.shape[0]
    n = A.shape[0]
    m = H.shape[0]
    nw = n * (d + 1)
    lam_next, J, Abar, Sigma = np.empty((n, n)), np.empty((n, m)), np.empty((n, n)), np.empty((n, n))
    Rt = np.empty((m, m))
    w = _work(n, m, G.shape[1], _MOMENTS_WORK)
    _moments_into(Lam, A, H, Qv, G, S, Qw, GQG, Ai, q, SQvi, eta, gb, s2, optimal, lam_next, J, Abar, Sigma, Rt, w)
    # the window before the reading: x̂(t|t-1) on top of the last window's first d blocks (block diagonal)
    xw = np.empty((N, nw))
    Pw = np.zeros((nw, nw))
    xw[:, :n] = x_pred
    Pw[:n, :n] = P_pred
    if d > 0:
        xw[:, n:] = x[:, : d * n]
        Pw[n:, n:] = P[: d * n, : d * n]
    xe_prior = np.ascontiguousarray(xw[:, d * n :])
    Pe_prior = np.ascontiguousarray(Pw[d * n :, d * n :])
    xe, Pe, xn, Pn, K, Qe, eps = _update_predict(xe_prior, Pe_prior, y, gb, H, Rt, Abar, Sigma, J)
    x_new = xw.copy()
    P_new = Pw.copy()
    x_new[:, d * n :] = xe
    P_new[d * n :, d * n :] = Pe
    _flat_into(out, (x_new, xw, xn, eps, P_new, Pw, Pn, Qe, lam_next), P_new)


@njit(cache=True, error_model="numpy")
def reorg_step(ring, t, cb, ib, y, xp_t, xsm_prev, xf_a, eps_prev, out):
    r"""One whole step t >= warmup of Algorithm D for laws constant in t: :func:`reorg_cov_step` on ``ring``
    (in place), the means of :meth:`tobitkf.filters.delay_reorganized.ReorganizedInnovationLMMSE._means_step`, and the
    ring's Ψ and K(a|·)H of time t-2d-2 zeroed (no longer read).

    ``y`` (N, m); ``xp_t`` x̂(t|t-1), ``xsm_prev`` x̂(t-d|t-1), ``xf_a`` x̂(t-d+1|t-d+1) (N, n; not read for d = 1,
    where it is this step's x̂(t|t)); ``eps_prev`` the
    innovations ε(t-1), ..., ε(t-d+2) (N, m) (a tuple of max(d-2, 1); entries of times < 0 are not read).

    .. math::

        \varepsilon(t) = y - \bar\gamma H\hat x(t-d|t-1),\ \hat x(t|t) = \hat x(t|t-1) + K(t|t)\varepsilon(t),\
        \hat x(t-d+1|t) = \hat x(t-d+1|t-d+1) + \sum_{i=1}^{d-1} K_s(i)\varepsilon(t-i+1), \\
        \hat x(t-d|t) = \hat x(t-d|t-1) + K(t-d|t)\varepsilon(t),\ \hat x(t+1|t) = \bar A(t)\hat x(t-d|t) + J(t)y.

    Writes into the flat ``out`` (:func:`_flat_into`): x̂(t|t), x̂(t-d+1|t), x̂(t-d|t), x̂(t+1|t) (N, n each),
    ε(t) (N, m), then P(t|t), P(t|t-1), P(t-d|t), P(t+1|t), P(t-d+1|t), Λ(t), Λ(t+1) (n, n each), Q_ε(t) (m, m)
    and the trace of P(t|t).
    ``cb``, ``ib``: the packed constants (:func:`_unpack_moments`), ``ib[5:10]`` = d, W and the errata flags
    E5, E6, E7, ``ib[10:]`` the ring's field offsets.
    """
    A, H, Qv, G, S, Qw, GQG, Ai, q, SQvi, eta, gconst, s2, optimal = _unpack_moments(cb, ib)
    d, W, e5, e6, e7, offs = ib[5], ib[6], ib[7] != 0, ib[8] != 0, ib[9] != 0, ib[10:]
    n = A.shape[0]
    m = H.shape[0]
    N = y.shape[0]
    nn = n * n
    F = _ring_fields(ring, offs, d, W, n, m)
    _reorg_cov(F, t, d, W, A, H, Qv, G, S, Qw, GQG, Ai, q, SQvi, eta, gconst, s2, optimal, e5, e6, e7)
    _, _, pf, psm, pmeas, pp, _, lam, abar, _, jj, qe, kf, ks, ke = F
    st, s1 = t % W, (t + 1) % W
    gb = gconst
    # the means straight into their places in ``out`` (x̂(t|t), x̂(t-d+1|t), x̂(t-d|t), x̂(t+1|t), ε(t))
    means = out[: 4 * N * n].reshape((4, N, n))
    xf_t, xs_t, xm_t, xp_n = means[0], means[1], means[2], means[3]
    e_t, o_cov = _take(out, 4 * N * n, N, m)
    Ab, Jt = abar[st], jj[st]
    for r in range(N):
        _innovation_row(e_t, y, xsm_prev, H, gb, r)
        for i in range(n):
            a_f, a_s, a_m = xp_t[r, i], xf_a[r, i], xsm_prev[r, i]
            for l in range(m):
                a_f += e_t[r, l] * kf[i, l]
                a_m += e_t[r, l] * ke[i, l]
            for k in range(1, d):  # K_s(k) ε(t-k+1): ε(t) for k = 1, else eps_prev[k-2]
                if t - k + 1 < 0:
                    continue
                for l in range(m):
                    a_s += (e_t[r, l] if k == 1 else eps_prev[k - 2][r, l]) * ks[k - 1, i, l]
            # d = 1: the smoother's element x(t-d+1) = x(t) is this step's filter estimate
            xf_t[r, i], xs_t[r, i], xm_t[r, i] = a_f, a_f if d == 1 else a_s, a_m
        _predict_row(xp_n, Ab, xm_t, Jt, y, r)
    # Ψ_i and K(a|·)H of time t-2d-2 are no longer read: zeroed (a vanishing Ψ or gain reads as zero)
    old = (t - 2 * d - 2) % W
    blk = (d + 1) * nn
    for o in (offs[0], offs[1]):
        for z in range(blk):
            ring[o + old * blk + z] = 0.0
    _flat_into(out[o_cov:], (pf[st], pp[st], pmeas[st], pp[s1], psm[st], lam[st], lam[s1], qe[st]), pf[st])
