r"""Compiled (numba) covariance step of the reorganized-innovation LMMSE (Algorithm D of the delay module).

:func:`reorg_cov_step` is :meth:`tobitkf.filters.delay.ReorganizedInnovationLMMSE._cov_step`, the numpy
reference, on the same flat ring buffer (layout: :func:`tobitkf.filters.delay._ring_layout`, whose field
offsets are passed in ``offs``): the data-independent part of one step t >= warmup, (a)–(f) of
:func:`~tobitkf.filters.delay.reorganized_lmmse` without the means, the moments of Λ(t-d) (R(t), J(t),
Ā(t), Σ(t), Λ(t+1), corrected recursion LD-E2), and the gains the means read. Covered: fading and
multiplicative-noise laws that do not change with t (γ̄, σ², Q_ζ constant), both decorrelation modes and
the re-inserted errata. The products are written as loops (the blocks are n x n with n of a few), so the
results equal the numpy step's to rounding, not bitwise (tested to 1e-12).
:func:`delay_moments` is the first part, the moments of Λ(t-d), on its own: the chain LMMSE's compiled
moments (Algorithm C), the same code as the reorganized step's.
Compiled on first use and cached on disk; importing this module imports numba.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .._linalg_kernels import gauss_solve

__all__ = ["reorg_cov_step", "reorg_step", "delay_moments", "aug_step", "chain_step"]


@njit(cache=True, error_model="numpy", inline="always")
def _mm(A, B, ta, tb):
    """op(A) op(B) with op the transpose where ``ta``/``tb``; a new array."""
    p = A.shape[1] if ta else A.shape[0]
    q = A.shape[0] if ta else A.shape[1]
    r = B.shape[0] if tb else B.shape[1]
    out = np.empty((p, r))
    for i in range(p):
        for k in range(r):
            acc = 0.0
            for j in range(q):
                acc += (A[j, i] if ta else A[i, j]) * (B[k, j] if tb else B[j, k])
            out[i, k] = acc
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
    """B M^{-1} for a symmetric (m, m) M: (M^{-1} B^T)^T; a division for m = 1 (as the numpy step)."""
    m = M.shape[0]
    if m == 1:
        return B / M[0, 0]
    X = np.ascontiguousarray(B.T)
    gauss_solve(M.copy(), X)
    return np.ascontiguousarray(X.T)


@njit(cache=True, error_model="numpy")
def _moments_into(Lam, A, H, Qv, G, S, Qw, GQG, Ai, q, SQvi, eta, gb, s2, optimal, lam_next, J_out, abar_out, sig_out):
    r"""What time t needs of the second moment Λ(t-d) = ``Lam`` (the numpy
    :func:`tobitkf.filters.delay._moments_at`): writes Λ(t+1) = sym(AΛA^T + Q_u(t)) (LD-E2), J(t), Ā(t) and
    Σ(t) of the decorrelated predictor into the ``*_out`` arrays and returns R(t) = Q_v + σ²HΛH^T (m, m)."""
    n = A.shape[0]
    HLH = _mm(_mm(H, Lam, False, False), H, False, True)
    Rt = Qv + s2 * HLH
    mult = np.zeros((n, n))
    for i in range(q.shape[0]):
        mult += q[i] * _mm(_mm(Ai[i], Lam, False, False), Ai[i], False, True)
    Lq = _mm(_mm(A, Lam, False, False), A, False, True) + (mult + GQG)
    _sym_into(Lq, lam_next)
    if optimal:
        SRinv = _right_inverse(S, Rt)  # S R^{-1}  (p, m)
        J = _mm(G, SRinv, False, False)
        Sigma = mult + _mm(_mm(G, Qw - _mm(SRinv, S, False, True), False, False), G, False, True)
    else:
        J = _mm(G, SQvi, False, False)
        Sigma = (
            mult + _mm(_mm(G, eta, False, False), G, False, True) + s2 * _mm(_mm(J, HLH, False, False), J, False, True)
        )
    J_out[:, :] = J
    abar_out[:, :] = A - gb * _mm(J, H, False, False)
    _sym_into(Sigma, sig_out)
    return Rt


@njit(cache=True, error_model="numpy")
def delay_moments(Lam, A, H, Qv, G, S, Qw, GQG, Ai, q, SQvi, eta, gb, s2, optimal):
    """:func:`_moments_into` into new arrays: ``(R (m, m), J (n, m), Ā (n, n), Σ (n, n), Λ(t+1) (n, n))``, the
    chain LMMSE's step (Algorithm C) for laws constant in t."""
    n, m = A.shape[0], H.shape[0]
    lam_next, J, Abar, Sigma = np.empty((n, n)), np.empty((n, m)), np.empty((n, n)), np.empty((n, n))
    Rt = _moments_into(Lam, A, H, Qv, G, S, Qw, GQG, Ai, q, SQvi, eta, gb, s2, optimal, lam_next, J, Abar, Sigma)
    return Rt, J, Abar, Sigma, lam_next


@njit(cache=True, error_model="numpy", inline="always")
def _ring_fields(ring, offs, d, W, n, m):
    """The fields psi, kh, pf, psm, pmeas, pp, pm, lam, abar, sig, j, qe, kf, ks, ke of the flat ring buffer
    (offsets ``offs``; layout :func:`tobitkf.filters.delay._ring_layout`) as views."""
    nn, nm = n * n, n * m
    out3 = []
    for k in range(2, 10):  # pf .. sig: (W, n, n) each
        out3.append(ring[offs[k] : offs[k] + W * nn].reshape((W, n, n)))
    nks = max(d - 1, 1)
    return (
        ring[offs[0] : offs[0] + W * (d + 1) * nn].reshape((W, d + 1, n, n)),
        ring[offs[1] : offs[1] + W * (d + 1) * nn].reshape((W, d + 1, n, n)),
        out3[0], out3[1], out3[2], out3[3], out3[4], out3[5], out3[6], out3[7],
        ring[offs[10] : offs[10] + W * nm].reshape((W, n, m)),
        ring[offs[11] : offs[11] + W * m * m].reshape((W, m, m)),
        ring[offs[12] : offs[12] + nm].reshape((n, m)),
        ring[offs[13] : offs[13] + nks * nm].reshape((nks, n, m)),
        ring[offs[14] : offs[14] + nm].reshape((n, m)),
    )  # fmt: skip


@njit(cache=True, error_model="numpy")
def reorg_cov_step(ring, t, offs, d, W, A, H, Qv, G, S, Qw, GQG, Ai, q, SQvi, eta, gconst, s2, optimal, e5, e6, e7):
    """One covariance step t >= warmup of Algorithm D on ``ring`` (in place); see the module docstring.

    ``offs`` are the offsets of the fields psi, kh, pf, psm, pmeas, pp, pm, lam, abar, sig, j, qe, kf, ks,
    ke (in this order); ``gconst``/``s2`` the fading law's mean and variance; ``optimal`` the
    decorrelation mode; ``e5``/``e6``/``e7`` the re-inserted errata.
    """
    n = A.shape[0]
    m = H.shape[0]
    psi, kh, pf, psm, pmeas, pp, pm, lam, abar, sig, jj, qe, kf, ks, ke = _ring_fields(ring, offs, d, W, n, m)
    st = t % W
    gb = gconst

    # moments of Λ(t-d): R(t), the multiplicative term, Λ(t+1), J(t), Ā(t), Σ(t)
    Rt = _moments_into(
        lam[(t - d) % W], A, H, Qv, G, S, Qw, GQG, Ai, q, SQvi, eta, gb, s2, optimal,
        lam[(t + 1) % W], jj[st], abar[st], sig[st],
    )  # fmt: skip

    # (a) innovation covariance (15)
    Pmp = psm[(t - 1) % W].copy()
    pm[st] = Pmp
    Q = gb * gb * _mm(_mm(H, Pmp, False, False), H, False, True) + Rt
    if m > 1:
        Qs = np.empty((m, m))
        _sym_into(Q, Qs)
        Q = Qs
    qe[st] = Q
    HtQi = _right_inverse(np.ascontiguousarray(H.T), Q)  # H^T Q_ε^{-1}  (n, m)
    # (b) filter
    Psd = psi[(t + d - 1) % W, d]
    Kf = gb * _mm(Psd, HtQi, True, False)
    kf[:, :] = Kf
    KfH = _mm(Kf, H, False, False)
    kh[st, 0] = KfH
    _sym_into(pp[st] - gb * _mm(KfH, Psd, False, False), pf[st])
    # (c) Ψ_i(t), i = d-1..1, corrected (58)
    if t - d >= 0:
        Abar_td = abar[(t - d) % W]
        g_md = gconst
    else:
        Abar_td = A
        g_md = 0.0
    g_md1 = gconst if t - d + 1 >= 0 else 0.0
    psi_d = psi[st, d].T.copy() if e6 else psi[st, d].copy()
    Pm_td = pm[(t - d) % W]
    for i in range(d - 1, 0, -1):
        a = t - d - i + 1
        a5 = a - 1 if e5 else a
        inner = psi[(t - i) % W, d - i + 1].T - g_md * _mm(kh[(t - d) % W, t - d - a5], Pm_td, False, False)
        val = _mm(inner, Abar_td, False, True)
        val = val - g_md1 * _mm(kh[(t - d + 1) % W, t - d + 1 - a], psi_d, False, False)
        top = d - 1 - i if e7 else d - 2 - i
        for j in range(0, top + 1):
            s = t - i - j
            g_s = gconst if s >= 0 else 0.0
            val = val - g_s * _mm(kh[s % W, s - a], psi[st, i + j + 1], False, False)
        psi[st, i] = val
    # (d) fixed-lag d-1 smoother covariance (55)-(57), a = t-d+1
    a = t - d + 1
    Ps = pf[a % W].copy()
    for i in range(1, d):
        s = t - i + 1
        if s < 0:
            continue
        psi_i = psi[st, i]
        Ks = gconst * _mm(psi_i, _right_inverse(np.ascontiguousarray(H.T), qe[s % W]), True, False)
        ks[i - 1] = Ks
        KsH = _mm(Ks, H, False, False)
        kh[s % W, s - a] = KsH
        Ps = Ps - gconst * _mm(KsH, psi_i, False, False)
    _sym_into(Ps, psm[st])
    # (e) delayed filter and predictor covariances (50)-(52)
    Ke = gb * _mm(Pmp, HtQi, False, False)
    ke[:, :] = Ke
    KeH = _mm(Ke, H, False, False)
    kh[st, d] = KeH
    _sym_into(Pmp - gb * _mm(KeH, Pmp, False, False), pmeas[st])
    Ab = abar[st]
    _sym_into(_mm(_mm(Ab, pmeas[st], False, False), Ab, False, True) + sig[st], pp[(t + 1) % W])
    # (f) corrected (39): Ψ_d(t+d) = {Ā(t)[Ψ_1(t) - γ̄ K(t-d|t) H Ψ_1(t)]}^T
    psi1 = psi[st, 1].copy()
    psi[(t + d) % W, d] = _mm(Ab, psi1 - gb * _mm(KeH, psi1, False, False), False, False).T


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
    :func:`tobitkf.filters.delay._aug_step`, standard form, for laws constant in t):
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
    :meth:`tobitkf.filters.delay.ChainLMMSE._step_arrays`) for one covariance common to the runs.

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
    Rt = _moments_into(Lam, A, H, Qv, G, S, Qw, GQG, Ai, q, SQvi, eta, gb, s2, optimal, lam_next, J, Abar, Sigma)
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
    (in place), the means of :meth:`tobitkf.filters.delay.ReorganizedInnovationLMMSE._means_step`, and the
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
    reorg_cov_step(ring, t, offs, d, W, A, H, Qv, G, S, Qw, GQG, Ai, q, SQvi, eta, gconst, s2, optimal, e5, e6, e7)
    n = A.shape[0]
    m = H.shape[0]
    N = y.shape[0]
    nn = n * n
    _, _, pf, psm, pmeas, pp, _, lam, abar, _, jj, qe, kf, ks, ke = _ring_fields(ring, offs, d, W, n, m)
    st, s1 = t % W, (t + 1) % W
    gb = gconst
    e_t = np.empty((N, m))
    xf_t = np.empty((N, n))
    xs_t = np.empty((N, n))
    xm_t = np.empty((N, n))
    xp_n = np.empty((N, n))
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
    means = (xf_t, xs_t, xm_t, xp_n, e_t)
    _flat_into(out, means + (pf[st], pp[st], pmeas[st], pp[s1], psm[st], lam[st], lam[s1], qe[st]), pf[st])
