r"""Compiled (numba) time loop of :func:`tobitkf.control.closed_loop.simulate_closed_loop`.

An *implementation* of the numpy loop of :mod:`tobitkf.control.closed_loop`, not a second algorithm:
per step k = 1..T and per run, in the numpy loop's order,

.. math::

    u_k &= \bar N r_k - K\hat x_{k-1|k-1}, \qquad x_k = Ax_{k-1} + B^uu_k + w_{k-1}, \qquad
    y^*_k = Cx_k + Du_k + v_k \\
    \bar x_k &= A\hat x_{k-1|k-1} + B^uu_k, \qquad y_k = \mathrm{clip}(y^*_k, l_k, h_k), \qquad
    \hat x_{k|k} = \text{observer update}(\bar x_k, y_k)

with the limits fixed (``"kf"``, ``"tkf"``) or set from the prior by (3.56) (``"tkf-moving"``,
``"sstkf"``), and the divergence freeze of the numpy loop (a run whose state or estimate leaves the
bound keeps its last state, estimate and covariance; its input is recorded as 0). The noises are the
numpy loop's, drawn up front by the caller, so both paths see the same random numbers.

The observer steps are the filters' compiled blocks, not copies: the predict
:func:`~tobitkf.filters._compiled_block.predict_block` and the Tobit update
:func:`~tobitkf.filters._compiled_tobit.tobit_update_block` of the TKF kernel, in its scratch
(:func:`~tobitkf.filters._compiled_block.block_scratch`). The KF observer is that update with infinite limits
(:math:`E(\mathbf p) = 1`, :math:`E(y) = C\bar x + Du`, noise :math:`\sigma_l^2 = R_{ll}`: the Kalman update,
for a diagonal R); the steady-state observer is the fixed-gain update of (3.58),
:math:`\hat x = \bar x + K_\infty(y - E[y])` with the constant :math:`\Psi_\infty`. Equal to the numpy loop
to rounding (tested to 1e-12). Runs are processed in blocks of :func:`~tobitkf.filters._compiled_block.runs_per_block` runs
(innermost loops over the runs of a block).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..filters._compiled_block import (
    CHUNK,
    block_scratch,
    flush_rows,
    predict_block,
    runs_per_block,
    stage_block,
    stage_shape,
)
from ..filters._compiled_tobit import GL_W, GL_X, tobit_update_block

__all__ = ["OBSERVER_CODES", "compiled_closed_loop"]

#: observer name -> kernel code
OBSERVER_CODES = {"kf": 0, "tkf": 1, "tkf-moving": 2, "sstkf": 3}


@njit(cache=True, error_model="numpy", nogil=True)
def compiled_closed_loop(
    obs_code,
    A,
    Bu,
    C,
    D,
    Qd,
    sigma,
    Kc,
    Nbar,
    ref,
    lo_fix,
    hi_fix,
    shift,
    upper_side,
    Kss,
    offset,
    Pss,
    xi,
    w,
    v,
    xh0,
    P0,
    noise_code,
    bound,
    X,
    est,
    pred,
    cov,
    U,
    Y,
    Ylat,
    LO,
    HI,
    GAM,
    dstep,
):
    r"""The closed loop of ``N`` runs over ``T`` steps; fills the output arrays in place.

    ``obs_code`` from :data:`OBSERVER_CODES`; ``A`` (n, n), ``Bu`` (n, p), ``C`` (m, n), ``D`` (m, p) or
    (0, p) without feedthrough, ``Qd`` (n, n) the process covariance, ``sigma`` (m,) the noise standard
    deviations, ``Kc`` (p, n) the feedback gain, ``Nbar`` (p, r), ``ref`` (T, r) the reference;
    ``lo_fix``/``hi_fix`` (T, m) the fixed limits (``"kf"``, ``"tkf"``), ``shift`` (m,) the offset
    :math:`\sigma\Phi^{-1}(\Xi)` of the moving limit (3.56) on side ``upper_side``; ``Kss`` (n, m),
    ``offset`` (m,), ``Pss`` (n, n), ``xi`` (m,) the steady-state observer's gain, the offset
    :math:`E[y] - C\bar x - Du` of its expected reading (3.58) (negative for an upper limit), covariance :math:`\Psi_\infty` and target probability :math:`\Xi` (recorded as its
    :math:`\hat\gamma`); ``w`` (N, T, n), ``v`` (N, T, m) the noises; ``xh0`` (N, n), ``P0`` (N, n, n)
    the observer's prior; ``noise_code`` the Tobit noise term; ``bound`` the divergence bound. ``X``
    (N, T+1, n) holds the true x_0 in row 0 on entry; the other outputs are (N, T, ...) as in
    :class:`~tobitkf.control.closed_loop.ClosedLoopResult`, ``dstep`` (N,) int the step of divergence
    (-1: none).
    """
    N, T, n = w.shape
    m = C.shape[0]
    p = Bu.shape[1]
    r_dim = ref.shape[1]
    has_d = D.shape[0] > 0
    moving = obs_code >= 2
    steady = obs_code == 3
    B = min(runs_per_block(n), max(N, 1))
    (xh, xp, e, mu), (blk, run, solve, buf) = block_scratch(n, m, B, GL_X.shape[0])
    P, Pp, AP = blk[0], blk[1], blk[2]
    gam = blk[9]
    xn = np.empty((n, B))
    Pn = np.empty((n, n, B))
    xt = np.empty((n, B))
    xk = np.empty((n, B))
    uk = np.empty((p, B))
    dy = np.empty((B, 1, m))  # D u_k and the reading of each run, laid out for tobit_update_block
    yk = np.empty((B, 1, m))
    lob = np.empty((B, m))
    hib = np.empty((B, m))
    ylat = np.empty((m, B))
    kf_lo = np.full((B, m), -math.inf)  # the KF observer: the Tobit update with infinite limits
    kf_hi = np.full((B, m), math.inf)
    alive = np.empty(B, dtype=np.bool_)
    ur = np.empty(p)
    pv = np.empty((n, B))  # the recorded prediction (the frozen estimate for a frozen run)
    uo = np.empty((p, B))  # the recorded input (0 for a frozen run)
    go = np.empty((m, B))  # the recorded gamma
    yo = np.empty((m, B))  # the reading, (m, B) for staging
    lot = np.empty((m, B))  # the limits, (m, B) for staging
    hit = np.empty((m, B))
    # outputs staged for S steps of a block, then written run by run (as the filter kernels do)
    S = min(CHUNK, max(T, 1))
    # (S, ..., B): the chunk step first, the run last (the layout of stage_block and flush_rows)
    s_x, s_est, s_pred = np.empty((S, n, B)), np.empty((S, n, B)), np.empty((S, n, B))
    s_cov = np.empty(stage_shape(cov, B, S))
    s_u = np.empty((S, p, B))
    s_y, s_yl, s_lo, s_hi, s_g = (
        np.empty((S, m, B)),
        np.empty((S, m, B)),
        np.empty((S, m, B)),
        np.empty((S, m, B)),
        np.empty((S, m, B)),
    )
    no_cov = np.empty((0, S, n, n))
    for r0 in range(0, N, B):
        nb = min(B, N - r0)
        for b in range(nb):
            alive[b] = True
            dstep[r0 + b] = -1
            for i in range(n):
                xt[i, b] = X[r0 + b, 0, i]
                xh[i, b] = xh0[r0 + b, i]
                for j in range(n):
                    P[i, j, b] = Pss[i, j] if steady else P0[r0 + b, i, j]
        for t in range(T):
            # u_k = Nbar r_k - K xhat  (6.22), (6.45)
            for i in range(p):
                s = 0.0
                for j in range(r_dim):
                    s += ref[t, j] * Nbar[i, j]
                ur[i] = s
            for i in range(p):
                for b in range(nb):
                    s = 0.0
                    for j in range(n):
                        s += xh[j, b] * Kc[i, j]
                    uk[i, b] = ur[i] - s
            # the plant: x_k = A x + B^u u_k + w, y*_k = C x_k + D u_k + v
            for i in range(n):
                for b in range(nb):
                    s = 0.0
                    for j in range(n):
                        s += xt[j, b] * A[i, j]
                    su = 0.0
                    for j in range(p):
                        su += uk[j, b] * Bu[i, j]
                    xk[i, b] = s + su + w[r0 + b, t, i]
            for l in range(m):
                for b in range(nb):
                    sd = 0.0
                    if has_d:
                        for j in range(p):
                            sd += uk[j, b] * D[l, j]
                    dy[b, 0, l] = sd
                    s = 0.0
                    for j in range(n):
                        s += xk[j, b] * C[l, j]
                    ylat[l, b] = s + sd + v[r0 + b, t, l]
            # the observer's predict: xbar = A xhat + B^u u_k, Pbar = A P A^T + Q (Psi-bar_inf for sstkf)
            if steady:  # the covariance is the constant Psi-bar_inf: the mean alone
                for i in range(n):
                    for b in range(nb):
                        s = 0.0
                        for j in range(n):
                            s += xh[j, b] * A[i, j]
                        xp[i, b] = s
            else:
                predict_block(A, Qd, xh, P, xp, Pp, AP, nb)
            for i in range(n):
                for b in range(nb):
                    su = 0.0
                    for j in range(p):
                        su += uk[j, b] * Bu[i, j]
                    xp[i, b] += su
            # the sensor's limits and reading
            for l in range(m):
                for b in range(nb):
                    if moving:
                        s = 0.0
                        for j in range(n):
                            s += xp[j, b] * C[l, j]
                        lim = s + dy[b, 0, l] + shift[l]
                        if upper_side:
                            lob[b, l] = -math.inf
                            hib[b, l] = lim
                        else:
                            lob[b, l] = lim
                            hib[b, l] = math.inf
                    else:
                        lob[b, l] = lo_fix[t, l]
                        hib[b, l] = hi_fix[t, l]
                    yk[b, 0, l] = min(max(ylat[l, b], lob[b, l]), hib[b, l])
            # the observer's update
            if steady:  # xhat = xbar + K_inf (y - E[y]), E[y] = C xbar + D u + offset (3.58)
                for l in range(m):
                    for b in range(nb):
                        s = 0.0
                        for j in range(n):
                            s += xp[j, b] * C[l, j]
                        ybar = s + dy[b, 0, l]
                        e[l, b] = yk[b, 0, l] - (ybar + offset[l])
                for i in range(n):
                    for b in range(nb):
                        s = 0.0
                        for l in range(m):
                            s += e[l, b] * Kss[i, l]
                        xn[i, b] = xp[i, b] + s
                        for j in range(n):
                            Pn[i, j, b] = Pss[i, j]
            else:  # the TKF update (3.37)-(3.41), (3.55); the KF's with infinite limits
                ulo, uhi = (kf_lo, kf_hi) if obs_code == 0 else (lob, hib)
                tobit_update_block(
                    C,
                    sigma,
                    ulo,
                    uhi,
                    0,
                    1,
                    yk,
                    dy,
                    0,
                    0,
                    noise_code,
                    False,
                    GL_X,
                    GL_W,
                    xp,
                    Pp,
                    mu,
                    e,
                    xn,
                    Pn,
                    blk,
                    run,
                    solve,
                    buf,
                    nb,
                )
            # divergence: a run whose state or estimate leaves the bound is frozen at its last values
            for b in range(nb):
                keep = alive[b]
                if keep:
                    for i in range(n):
                        if not (abs(xk[i, b]) < bound and abs(xn[i, b]) < bound):
                            keep = False
                    if not keep:
                        alive[b] = False
                        dstep[r0 + b] = t + 1
                for i in range(n):
                    if keep:
                        xt[i, b] = xk[i, b]
                        xh[i, b] = xn[i, b]
                        for j in range(n):
                            P[i, j, b] = Pn[i, j, b]
                    pv[i, b] = xp[i, b] if keep else xh[i, b]
                for i in range(p):
                    uo[i, b] = uk[i, b] if keep else 0.0
                for l in range(m):
                    yo[l, b] = yk[b, 0, l]
                    lot[l, b] = lob[b, l]
                    hit[l, b] = hib[b, l]
                    if obs_code == 0:
                        go[l, b] = 1.0
                    elif steady:
                        go[l, b] = xi[l]
                    else:
                        go[l, b] = gam[l, b]
            tt = t % S
            stage_block(xt, P, tt, nb, s_x, no_cov)
            stage_block(xh, P, tt, nb, s_est, s_cov)
            stage_block(pv, P, tt, nb, s_pred, no_cov)
            stage_block(uo, P, tt, nb, s_u, no_cov)
            stage_block(yo, P, tt, nb, s_y, no_cov)
            stage_block(ylat, P, tt, nb, s_yl, no_cov)
            stage_block(lot, P, tt, nb, s_lo, no_cov)
            stage_block(hit, P, tt, nb, s_hi, no_cov)
            stage_block(go, P, tt, nb, s_g, no_cov)
            if tt == S - 1 or t == T - 1:
                t0 = t - tt
                flush_rows(s_x, X, r0, t0 + 1, nb, tt + 1)  # X row 0 is x_0
                flush_rows(s_est, est, r0, t0, nb, tt + 1)
                flush_rows(s_pred, pred, r0, t0, nb, tt + 1)
                flush_rows(s_cov, cov, r0, t0, nb, tt + 1)
                flush_rows(s_u, U, r0, t0, nb, tt + 1)
                flush_rows(s_y, Y, r0, t0, nb, tt + 1)
                flush_rows(s_yl, Ylat, r0, t0, nb, tt + 1)
                flush_rows(s_lo, LO, r0, t0, nb, tt + 1)
                flush_rows(s_hi, HI, r0, t0, nb, tt + 1)
                flush_rows(s_g, GAM, r0, t0, nb, tt + 1)
