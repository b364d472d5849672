r"""Compiled (numba) time loop of the steady-state Tobit Kalman filter with a controlled limit.

An *implementation* of the numpy reference path of
:class:`tobitkf.filters.steady_state.SteadyStateTobitKalmanFilter` (Miller 2015, §3.4.2), not a
second algorithm. The covariances and the gain are the constants of the modified DARE (3.57),
computed once by the estimator, so only the means run here:

.. math::

    \bar x_k = A\hat x_{k-1}, \qquad \bar y_k = C\bar x_k, \qquad
    E[y_k] = \bar y_k \mp \text{offset} \quad (3.58), \qquad
    \hat x_k = \bar x_k + K_\infty(y_k - E[y_k]),

and, for latent readings (``filter_controlled``), the sensor's clip at the limit (3.56)
:math:`T_k = \bar y_k \pm \sigma\Phi^{-1}(\Xi)`: :math:`y_k = \min(y^*_k, T_k)` (right censoring) or
:math:`\max(y^*_k, T_k)` (left). The Tobit statistics are constants (:math:`\Xi`, :math:`\hat\lambda`,
:math:`\upsilon`), so the kernel needs no censored-normal statistics at run time.

Covered (the dispatcher in ``steady_state.py`` decides): no control input (the model is
time-invariant by construction), both sides, censored and latent readings. NaN readings are refused
by the estimator before either path runs.

Runs are taken in blocks of :func:`~tobitkf.filters._compiled_block.runs_per_block` runs, state (n, B), every inner loop
over the block and branch-free (the side and ``latent`` tests are hoisted out of it), so the
compiler vectorises across runs. Measured at n = 2, m = 1 without outputs: one run at a time
(latency-bound) ~27 ns per run-step, blocks with the branches inside ~25 ns, this form ~8 ns.
Outputs are staged for :data:`~tobitkf.filters._compiled_block.CHUNK` steps per block and written run by
run with the TKF kernel's :func:`~tobitkf.filters._compiled_block._flush` (contiguous); an output of shape
``(N, 0, ...)`` is not requested: it gets no staging and is not written.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ._compiled_block import _block_dims, _flush, _mean_scratch, _stage_shape, mean_predict, runs_per_block

__all__ = ["steady_tkf_kernel"]


@njit(cache=True, error_model="numpy", nogil=True)
def steady_tkf_kernel(y, A, C, K, offset, shift, upper, latent, x0, means, pmeans, lim_out, y_out, x_last):
    """Fixed-gain TKF means over ``N`` runs of ``T`` steps from ``x0`` (N, n).

    ``y`` (N, T, m) censored readings (``latent=False``) or latent ones (``latent=True``, clipped here
    at the limit); ``A`` (n, n), ``C`` (m, n), ``K`` (n, m) the gain :math:`K_\\infty`; ``offset`` (m,)
    of (3.58) and ``shift`` (m,) :math:`= \\sigma\\Phi^{-1}(\\Xi)` of (3.56); ``upper`` selects right
    censoring. Outputs: ``means``/``pmeans`` (N, T, n), ``lim_out``/``y_out`` (N, T, m) (the limits and
    the clipped readings, latent only), each of shape ``(N, 0, ...)`` when not requested; ``x_last``
    (N, n) receives the mean after the last step.

    Returns True when every mean :math:`\\hat x_k` of every run was finite (the divergence check of the
    estimator without a second pass over ``means``): ``fin[b]`` accumulates :math:`\\sum_{k,i}0\\cdot\\hat x_{k,i}`,
    which is 0 for finite numbers and NaN once one is inf or NaN.
    """
    N, T, m = y.shape
    n = A.shape[0]
    B, S = _block_dims(N, T, 0, runs_per_block(n))  # outputs staged for S steps, then written run by run (contiguous)
    x, xp, e, ybar = _mean_scratch(n, m, B)
    fin = np.zeros(B)
    finite = True
    s_mean, s_pmean = np.empty(_stage_shape(means, B, S)), np.empty(_stage_shape(pmeans, B, S))
    s_lim, s_y = np.empty(_stage_shape(lim_out, B, S)), np.empty(_stage_shape(y_out, B, S))
    want_m, want_pm, want_x = means.shape[1] > 0, pmeans.shape[1] > 0, lim_out.shape[1] > 0
    sgn = -1.0 if upper else 1.0
    for r0 in range(0, N, B):
        nb = min(B, N - r0)
        for b in range(nb):
            for i in range(n):
                x[i, b] = x0[r0 + b, i]
        for t in range(T):
            tt = t % S
            mean_predict(A, x, xp, nb)  # x_bar = A x
            for l in range(m):
                for b in range(nb):
                    ybar[l, b] = 0.0
                for j in range(n):
                    c = C[l, j]
                    for b in range(nb):
                        ybar[l, b] += c * xp[j, b]
                for b in range(nb):
                    e[l, b] = y[r0 + b, t, l]
                if latent:  # the sensor's clip at the limit (3.56)
                    sh = sgn * shift[l]
                    if upper:
                        for b in range(nb):
                            e[l, b] = min(e[l, b], ybar[l, b] - sh)
                    else:
                        for b in range(nb):
                            e[l, b] = max(e[l, b], ybar[l, b] - sh)
                    if want_x:
                        for b in range(nb):
                            s_lim[tt, l, b] = ybar[l, b] - sh
                            s_y[tt, l, b] = e[l, b]
                off = sgn * offset[l]
                for b in range(nb):
                    e[l, b] = e[l, b] - (ybar[l, b] + off)  # y - E[y] (3.58)
            for i in range(n):  # x = x_bar + K e
                for b in range(nb):
                    x[i, b] = xp[i, b]
                for l in range(m):
                    k = K[i, l]
                    for b in range(nb):
                        x[i, b] += k * e[l, b]
                for b in range(nb):
                    fin[b] += 0.0 * x[i, b]
            if want_pm:
                for i in range(n):
                    for b in range(nb):
                        s_pmean[tt, i, b] = xp[i, b]
            if want_m:
                for i in range(n):
                    for b in range(nb):
                        s_mean[tt, i, b] = x[i, b]
            if tt == S - 1 or t == T - 1:
                t0 = t - tt
                _flush(s_mean, means, r0, t0, nb, tt + 1)
                _flush(s_pmean, pmeans, r0, t0, nb, tt + 1)
                _flush(s_lim, lim_out, r0, t0, nb, tt + 1)
                _flush(s_y, y_out, r0, t0, nb, tt + 1)
        for b in range(nb):
            for i in range(n):
                x_last[r0 + b, i] = x[i, b]
            finite = finite and fin[b] == 0.0
            fin[b] = 0.0
    return finite
