r"""The fading Tobit Kalman filter's (TKF-FM) pieces of the one compiled loop
(:func:`~tobitkf.filters._compiled_loop.compiled_loop`, update code
:data:`~tobitkf.filters._compiled_loop.FADING`).

An *implementation* of the numpy reference path of
:class:`tobitkf.filters.fading.FadingTobitKalmanFilter` (Geng et al. 2017, Table 1, with the
repaired (20')), not a second algorithm: the augmented state
:math:`\xi_k = \mathrm{col}\{x_k, \dots, x_{k-L}\}` of fixed size :math:`n_\xi = n(L+1)`, the
predict (17)–(18) with the block-shift structure of :math:`\mathcal A` (:func:`shift_predict_block`, as
:func:`tobitkf.filters.core.shift_predict`; also the predict of the protocol filter's augmented state), and the
one-sided censored statistics of a block (:func:`fading_lower_block`). The update itself is written in the loop's
``FADING`` branch: the censored statistics at :math:`\hat\chi = H_k\hat\xi_{k|k-1}` (Lemma 1,
:math:`H_k = \bar\theta_k\mathcal C_k`, the loop's rows of the step), :math:`\hat y` (21), the gain scale
:math:`\bar\Upsilon_k` (so :math:`G_k = \bar\Upsilon_kH_k`), the noise :math:`N_k` = the truncated variance (12)
or, with ``exact_tobit_variance``, the censored variance, and the update in the Joseph or the standard form,
both in the rank-m arithmetic of the shared numpy update.

Everything that is not specific to the fading model is shared with the Tobit Kalman filter's update
(:func:`~tobitkf.filters._compiled_tobit.tobit_update_block`): the censored-normal statistics
(:func:`~tobitkf.filters._compiled_censored.censored_stats`; for a lower limit alone the vectorised statistics
of a whole block, :func:`fading_lower_block`), the noise term
(:func:`~tobitkf.filters._compiled_censored.noise_term`: the truncated variance is the TKF's ``"dissertation"``
term, the censored variance its ``"total_variance"``), the moments of the scaled update and the masked gain
(missing or degenerate channels get a zero gain column; for m > 1 the block solve over all runs of a block).
What the fading update adds is the inverse Mills ratio :math:`\lambda` among its outputs.
"""

from __future__ import annotations

from numba import njit

from ._compiled_block import _block_dims, mean_predict
from ._compiled_censored import _one_sided_at

__all__ = [
    "fading_lower_block",
    "shift_predict_block",
    "AUG_BLOCK",
    "aug_block_dims",
]

#: runs per block of the augmented-state loops (this one and the protocol loop), twice the large-n TKF's
#: :data:`~tobitkf.filters._compiled_block.BLOCK`: a step of these loops is some 300 short loops over the runs of a block
#: (n_xi = 6), whose fixed cost per loop 64 runs share better than 32. Measured (1000 runs x 100 steps, all
#: outputs, thread CPU time, old/new processes alternated twice, load 4.5-5.8): fading default 164-167 -> 148-152,
#: protocol "variance" 163 -> 152-157 ns per run-step; the staging of the fading loop's 33 numbers per run-step is
#: then 1.1 MB (64 steps x 64 runs)
AUG_BLOCK = 64


@njit(cache=True)
def aug_block_dims(N, T):
    """``(B, S)`` of the augmented-state loops: :func:`~tobitkf.filters._compiled_block._block_dims` with
    :data:`AUG_BLOCK` runs per block."""
    return _block_dims(N, T, 0, AUG_BLOCK)


@njit(cache=True, error_model="numpy")
def shift_predict_block(A, Qd, x, P, xp, Pp, X, nb):
    r"""Block-shift time update of a block of runs, as :func:`tobitkf.filters.core.shift_predict` (source 0):
    :math:`\bar\xi = [A\xi_0; \xi_0; \dots; \xi_{L-1}]`, :math:`X = P_{:,0}A^T`,
    :math:`\bar P_{00} = \mathrm{sym}(X_0^TA^T + Q_d)`, :math:`\bar P_{i+1,0} = X_i`,
    :math:`\bar P_{i+1,j+1} = P_{ij}`. ``A``, ``Qd`` (n, n); ``x`` (nxi, B), ``P`` (nxi, nxi, B)
    exactly symmetric; ``X`` (nxi, n, B) scratch. O(n n_xi^2) instead of O(n_xi^3)."""
    nxi, n = x.shape[0], A.shape[0]
    mean_predict(A, x, xp, nb)
    for i in range(n, nxi):
        for b in range(nb):
            xp[i, b] = x[i - n, b]
    for i in range(nxi):
        for j in range(n):
            for b in range(nb):
                X[i, j, b] = 0.0
            for k in range(n):
                a = A[j, k]
                for b in range(nb):
                    X[i, j, b] += P[i, k, b] * a
    for i in range(n):
        for j in range(n):
            for b in range(nb):
                Pp[i, j, b] = 0.0
            for k in range(n):
                a = A[j, k]
                for b in range(nb):
                    Pp[i, j, b] += X[k, i, b] * a
            q = Qd[i, j]
            for b in range(nb):
                Pp[i, j, b] += q
    for i in range(n):
        for j in range(i + 1, n):
            for b in range(nb):
                v = 0.5 * (Pp[i, j, b] + Pp[j, i, b])
                Pp[i, j, b] = v
                Pp[j, i, b] = v
    for i in range(n, nxi):
        for j in range(n):
            for b in range(nb):
                v = X[i - n, j, b]
                Pp[i, j, b] = v
                Pp[j, i, b] = v
        for j in range(n, nxi):
            for b in range(nb):
                Pp[i, j, b] = P[i - n, j - n, b]


@njit(cache=True, error_model="numpy")
def fading_lower_block(ym, l, sd, lo, nb, noise_code, gam, lam, noise):
    r"""The statistics of channel ``l`` of the runs ``b < nb`` of a block for a lower limit ``lo`` alone
    (Lemma 1), vectorised: γ into ``gam[l]``, the inverse Mills ratio into ``lam[l]`` (``gam``, ``lam`` (m, B)),
    the noise term of ``noise_code`` (0 the truncated variance (12), 1 the censored variance) into
    ``noise[l, l]`` ((m, m, B)), and :math:`\hat y` (21), the censored mean, over the means ``ym[l]`` ((m, B));
    the numbers of :func:`~tobitkf.filters._compiled_censored.censored_stats`. Compiled apart from the loop (as
    the TKF's :func:`~tobitkf.filters._compiled_censored.one_sided_block`), so that its loop over the runs
    vectorises; the channel by index, not as views of its rows, and no call inside, so that a call costs the
    loop no reference counting (a view made per step and channel, or an array handed to a function that calls
    another, costs an atomic increment and decrement of its reference count per call)."""
    for b in range(nb):
        _plo, g, lm, _tmean, tv, cm, cv = _one_sided_at(ym[l, b], sd, lo)
        gam[l, b] = g
        lam[l, b] = lm
        noise[l, l, b] = tv if noise_code == 0 else cv
        ym[l, b] = cm
