r"""Compiled (numba) forward recursions of :mod:`tobitkf.inference.censored_ar` for p = 1 and p = 2.

An implementation of the numpy reference :func:`tobitkf.inference._ar_likelihood._forward`, not a second
algorithm: the same nodes and weights (passed in, concatenated over the steps), the same log-domain
recursion

.. math::

    \log\alpha_t(\cdot) = \log w_t + \operatorname{logsumexp}_{\xi_{t-p}}\big(\log N(\xi_t;
      \textstyle\sum_i a_{t,i}\xi_{t-i}, v_t) + \log\alpha_{t-1}\big),

renormalised to max 0 at every step (the shifts summed into the log-likelihood). Equal to the numpy
path to rounding (tested). Compiled on first use and cached on disk.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_LOG_2PI = math.log(2.0 * math.pi)


@njit(cache=True, nogil=True)
def forward_ar1(z, lw, start, count, a, v):  # pragma: no cover - compiled
    """p = 1: ``z``/``lw`` nodes and log weights of all steps, step t at ``start[t]:start[t]+count[t]``;
    ``a[t]``, ``v[t]`` the predictor of step t (a[0] unused). Returns the log-likelihood."""
    T = start.shape[0]
    Mmax = 0
    for t in range(T):
        if count[t] > Mmax:
            Mmax = count[t]
    la = np.empty(Mmax)
    new = np.empty(Mmax)
    total = 0.0
    # t = 0: the stationary marginal
    s0, M0 = start[0], count[0]
    c = -np.inf
    for j in range(M0):
        zz = z[s0 + j]
        new[j] = lw[s0 + j] - 0.5 * (_LOG_2PI + math.log(v[0]) + zz * zz / v[0])
        if new[j] > c:
            c = new[j]
    if not np.isfinite(c):
        return -np.inf
    for j in range(M0):
        la[j] = new[j] - c
    total += c
    Mp, sp = M0, s0
    ea = np.empty(Mmax)
    for t in range(1, T):
        st, M = start[t], count[t]
        at, vt = a[t], v[t]
        lv = _LOG_2PI + math.log(vt)
        half = 0.5 / vt
        for i in range(Mp):
            ea[i] = math.exp(la[i])
        c = -np.inf
        smax = 0.0
        # linear domain: one exp per pair (la <= 0, so no overflow); a row whose every term
        # underflows is negligible beside the others unless they all do (then the log domain)
        for j in range(M):
            zj = z[st + j]
            s = 0.0
            for i in range(Mp):
                d = zj - at * z[sp + i]
                s += ea[i] * math.exp(-half * d * d)
            if s > smax:
                smax = s
            new[j] = lw[st + j] - 0.5 * lv + math.log(s) if s > 0.0 else -np.inf
            if new[j] > c:
                c = new[j]
        if smax < 1e-250:
            c = -np.inf
            for j in range(M):
                zj = z[st + j]
                m = -np.inf
                s = 0.0
                for i in range(Mp):  # one-pass log-sum-exp
                    if la[i] == -np.inf:
                        continue
                    d = zj - at * z[sp + i]
                    val = la[i] - half * d * d
                    if val > m:
                        s = s * math.exp(m - val) + 1.0
                        m = val
                    else:
                        s += math.exp(val - m)
                new[j] = lw[st + j] - 0.5 * lv + m + math.log(s) if m > -np.inf else -np.inf
                if new[j] > c:
                    c = new[j]
        if not np.isfinite(c):
            return -np.inf
        for j in range(M):
            la[j] = new[j] - c
        total += c
        Mp, sp = M, st
    m = -np.inf
    for i in range(Mp):
        if la[i] > m:
            m = la[i]
    s = 0.0
    for i in range(Mp):
        s += math.exp(la[i] - m)
    return total + m + math.log(s)


@njit(cache=True, nogil=True)
def _step_ar2_direct(z, lw, st, M, s1, M1, s2, M2, la, b1, b2, vt, new):  # pragma: no cover - compiled
    """One full AR(2) step in the log domain (one-pass log-sum-exp over the nodes of step t-2)."""
    lv = _LOG_2PI + math.log(vt)
    half = 0.5 / vt
    for j in range(M):
        zj = z[st + j]
        for i in range(M1):
            zi = z[s1 + i]
            m = -np.inf
            s = 0.0
            for k in range(M2):
                if la[i, k] == -np.inf:
                    continue
                zk = z[s2 + k] if s2 >= 0 else 0.0
                d = zj - b1 * zi - b2 * zk
                val = la[i, k] - half * d * d
                if val > m:
                    s = s * math.exp(m - val) + 1.0
                    m = val
                else:
                    s += math.exp(val - m)
            new[j, i] = lw[st + j] - 0.5 * lv + m + math.log(s) if m > -np.inf else -np.inf


@njit(cache=True, nogil=True)
def _step_ar2_gemm(z, lw, st, M, s1, M1, s2, M2, la, b1, b2, vt, new):  # pragma: no cover - compiled
    r"""One full AR(2) step as a matrix product; False when the exponents leave the safe range.

    With centred nodes :math:`\delta = z - c`, :math:`d = r_{ji} - q_k`, :math:`r_{ji} = \delta_j + B_i`,
    :math:`B_i = c_j - b_1c_i - b_2c_k - b_1\delta_i`, :math:`q_k = b_2\delta_k`:
    :math:`e^{-d^2/2v} = e^{-r^2/2v}\,e^{\delta_jq_k/v}\,e^{B_iq_k/v - q_k^2/2v}`, so
    :math:`\sum_k K\alpha = e^{-r^2/2v}(EF^T)_{ji}` with :math:`E_{jk} = e^{\delta_jq_k/v}`,
    :math:`F_{ik} = e^{B_iq_k/v - q_k^2/2v}\alpha_{ik}`: O(M^3) multiply-adds, O(M^2) exponentials.
    """
    lv = _LOG_2PI + math.log(vt)
    cj = 0.0
    for j in range(M):
        cj += z[st + j]
    cj /= M
    ci = 0.0
    for i in range(M1):
        ci += z[s1 + i]
    ci /= M1
    ck = 0.0
    for k in range(M2):
        ck += z[s2 + k]
    ck /= M2
    off = cj - b1 * ci - b2 * ck
    # range check of every exponent
    qmax = 0.0
    for k in range(M2):
        q = abs(b2 * (z[s2 + k] - ck))
        if q > qmax:
            qmax = q
    amax = 0.0
    for j in range(M):
        a = abs(z[st + j] - cj)
        if a > amax:
            amax = a
    bmax = 0.0
    for i in range(M1):
        b = abs(off - b1 * (z[s1 + i] - ci))
        if b > bmax:
            bmax = b
    # every product E F = exp((r q - q^2/2) / v) and each factor stay below exp(600); the
    # exp(-r^2 / 2v) factor is applied in the log domain
    if (amax + bmax) * qmax > 600.0 * vt:
        return False
    E = np.empty((M, M2))
    for j in range(M):
        dj = z[st + j] - cj
        for k in range(M2):
            E[j, k] = math.exp(dj * b2 * (z[s2 + k] - ck) / vt)
    Ft = np.empty((M2, M1))
    for i in range(M1):
        Bi = off - b1 * (z[s1 + i] - ci)
        for k in range(M2):
            q = b2 * (z[s2 + k] - ck)
            Ft[k, i] = math.exp(Bi * q / vt - 0.5 * q * q / vt + la[i, k]) if la[i, k] > -np.inf else 0.0
    G = np.dot(E, Ft)
    for j in range(M):
        dj = z[st + j] - cj
        for i in range(M1):
            r = dj + off - b1 * (z[s1 + i] - ci)
            val = G[j, i]
            new[j, i] = lw[st + j] - 0.5 * lv - 0.5 * r * r / vt + math.log(val) if val > 0.0 else -np.inf
    return True


@njit(cache=True, nogil=True)
def forward_ar2(z, lw, start, count, a1, a2, v):  # pragma: no cover - compiled
    """p = 2: as :func:`forward_ar1` with the predictor ``a1[t]``, ``a2[t]``, ``v[t]`` of step t
    (t = 0: marginal; t = 1: ``a2`` unused). ``la[i, k]`` over the nodes of steps t-1 and t-2."""
    T = start.shape[0]
    Mmax = 1
    for t in range(T):
        if count[t] > Mmax:
            Mmax = count[t]
    la = np.full((Mmax, Mmax), -np.inf)
    new = np.full((Mmax, Mmax), -np.inf)
    total = 0.0
    s0, M0 = start[0], count[0]
    c = -np.inf
    for j in range(M0):
        zz = z[s0 + j]
        new[j, 0] = lw[s0 + j] - 0.5 * (_LOG_2PI + math.log(v[0]) + zz * zz / v[0])
        if new[j, 0] > c:
            c = new[j, 0]
    if not np.isfinite(c):
        return -np.inf
    for j in range(M0):
        la[j, 0] = new[j, 0] - c
    total += c
    M1, s1 = M0, s0  # nodes of step t-1 (axis 0 of la)
    M2, s2 = 1, -1  # nodes of step t-2 (axis 1); -1: a dummy axis of one node
    for t in range(1, T):
        st, M = start[t], count[t]
        b1, b2, vt = a1[t], a2[t], v[t]
        if s2 < 0:
            b2 = 0.0
        done = False
        if M * M1 * M2 >= 4096 and s2 >= 0:
            done = _step_ar2_gemm(z, lw, st, M, s1, M1, s2, M2, la, b1, b2, vt, new)
        if not done:
            _step_ar2_direct(z, lw, st, M, s1, M1, s2, M2, la, b1, b2, vt, new)
        c = -np.inf
        for j in range(M):
            for i in range(M1):
                if new[j, i] > c:
                    c = new[j, i]
        if done and not c > -600.0:  # the product underflowed: redo in the log domain
            _step_ar2_direct(z, lw, st, M, s1, M1, s2, M2, la, b1, b2, vt, new)
            c = -np.inf
            for j in range(M):
                for i in range(M1):
                    if new[j, i] > c:
                        c = new[j, i]
        if not np.isfinite(c):
            return -np.inf
        for j in range(M):
            for i in range(M1):
                la[j, i] = new[j, i] - c
        total += c
        M2, s2 = M1, s1
        M1, s1 = M, st
    m = -np.inf
    for j in range(M1):
        for i in range(M2):
            if la[j, i] > m:
                m = la[j, i]
    s = 0.0
    for j in range(M1):
        for i in range(M2):
            s += math.exp(la[j, i] - m)
    return total + m + math.log(s)


@njit(cache=True, nogil=True)
def fill_legendre(z, lw, start, panels, lo, hi, x, w):  # pragma: no cover - compiled
    """The composite Gauss-Legendre nodes and log weights of the censored steps, written in place: step i
    (``start[i]`` into ``z``/``lw``) cuts ``[lo[i], hi[i]]`` into ``panels[i]`` equal panels of the rule
    ``x``, ``w`` on [-1, 1] (the numbers of the numpy branch of ``_ar_likelihood._node_arrays``)."""
    G = x.shape[0]
    for i in range(start.shape[0]):
        P = panels[i]
        h = (hi[i] - lo[i]) / P
        pos = start[i]
        for q in range(P):
            base = lo[i] + h * q
            for j in range(G):
                z[pos] = base + 0.5 * h * (x[j] + 1.0)
                lw[pos] = math.log(0.5 * h * w[j])
                pos += 1
