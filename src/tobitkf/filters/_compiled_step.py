r"""Compiled (numba) form of the shared step of :mod:`tobitkf.filters.core`.

:func:`time_update_runs` is :func:`~tobitkf.filters.core.time_update` (the plain predict and the
block-shift predict of an augmented state) and :func:`measurement_update_runs` is
:func:`~tobitkf.filters.core.measurement_update` (standard and Joseph forms, diagonal or full noise
term, per-run channel scale, the masking rule, a retained variance) for N runs with one covariance
each. They are an *implementation* of those numpy functions, not a second algorithm, and are built
from the blocks of the TKF kernel (:mod:`tobitkf.filters._compiled_block`): the innovation moments
(:func:`~tobitkf.filters._compiled_block._innovation_moments`), the masked gain and mean update
(``_gain`` for one channel, the block solve ``_gain_block`` for several), the covariance update
(``_cov_update``), and the fading kernel's block-shift predict
(:func:`~tobitkf.filters._compiled_fading.shift_predict_block`, the augmentation of the fading and
protocol families; a pure-delay shift, ``source`` > 0, stays on numpy). Results agree with the numpy
path to rounding (tested to 1e-12).

Every Gaussian-update family whose online ``step`` (or Python time loop) runs the numpy step gets
this path when numba imports and its ``backend`` is not ``"numpy"``: one call per predict and one
per update instead of about forty small numpy operations, which is what one run of one reading
costs on the numpy path. Runs are processed in blocks of :func:`~tobitkf.filters._compiled_block.runs_per_block` runs,
copied into structure-of-arrays scratch from the kernels' shared allocators (runs on the last axis, as
in the TKF kernel) and back.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ._compiled_block import (
    _cov_update,
    _gain,
    _gain_block,
    _innovation_moments,
    _load,
    _mean_scratch,
    _store_last,
    _update_scratch,
    runs_per_block,
)
from ._compiled_fading import shift_predict_block

__all__ = ["time_update_runs", "measurement_update_runs"]


@njit(cache=True, error_model="numpy")
def time_update_runs(x, P, A, Qd, bvec, xp_out, Pp_out):
    r"""The predict of N runs by the fading kernel's block-shift predict
    (:func:`~tobitkf.filters._compiled_fading.shift_predict_block`): ``x`` (N, n_x), ``P`` (N, n_x, n_x)
    exactly symmetric, ``A`` (n, n) acting on the top block (n = n_x: the plain predict
    :math:`\bar x = A\hat x`, :math:`\bar P = \mathrm{sym}(APA^T + Q_d)`), ``Qd`` (n, n), ``bvec`` (1 or N, n)
    the offset of the top block; writes ``xp_out`` (N, n_x), ``Pp_out`` (N, n_x, n_x)."""
    N, nx = x.shape
    n = A.shape[0]
    B = min(runs_per_block(nx), N)
    xs = np.empty((nx, B))
    Ps = np.empty((nx, nx, B))
    xp = np.empty((nx, B))
    Pp = np.empty((nx, nx, B))
    X = np.empty((nx, n, B))
    one_b = bvec.shape[0] == 1
    for r0 in range(0, N, B):
        nb = min(B, N - r0)
        _load(x, P, r0, nb, xs, Ps)
        shift_predict_block(A, Qd, xs, Ps, xp, Pp, X, nb)
        _store_last(xp, Pp, r0, nb, xp_out, Pp_out)
        for b in range(nb):
            rb = 0 if one_b else r0 + b
            for i in range(n):
                xp_out[r0 + b, i] += bvec[rb, i]


@njit(cache=True, error_model="numpy")
def measurement_update_runs(
    x, P, e_in, valid, H0, scale, noise, noise_diag, retained, joseph, x_out, P_out, K_out, Ree_out
):
    r"""The measurement update of N runs, as :func:`~tobitkf.filters.core.measurement_update` in the
    standard or Joseph form.

    ``x`` (N, n_x), ``P`` (N, n_x, n_x) the prediction; ``e_in`` (N, m) the innovation (NaN: the channel
    does not take part); ``valid`` (N, m) bool, the channels the family lets take part (no rows: all); ``H0`` (m, n_x); ``scale`` (1 or N, m) the channel scale s
    (H = diag(s) H0); ``noise`` (1 or N, m, m), or (1 or N, m, 1) holding the diagonal when
    ``noise_diag``; ``retained`` (0, 1 or N, m) the retained variance V (no rows: none). A channel takes
    part when its innovation is not NaN and :math:`R_{ee,ll}` is above the smallest normal number.
    Writes the posterior ``x_out``, ``P_out``, the gain ``K_out`` (N, n_x, m) and
    :math:`R_{ee}` ``Ree_out`` (N, m, m)."""
    N, nx = x.shape
    m = H0.shape[0]
    B = min(runs_per_block(nx), N)
    # the block scratch from the kernels' shared allocators
    xn, xp, e, _ = _mean_scratch(nx, m, B)
    blk, run, solve, _ = _update_scratch(nx, nx, m, B, 0)
    Pn, Pp, _, CP, Rxe, Ree, K, MH, nz, gam, ok = blk
    Rs, Ws, Ks, oks, Rxs, ds = run
    Rw, W, d, bad = solve
    one_s = scale.shape[0] == 1
    one_n = noise.shape[0] == 1
    nr = retained.shape[0]
    masked = valid.shape[0] > 0
    for r0 in range(0, N, B):
        nb = min(B, N - r0)
        _load(x, P, r0, nb, xp, Pp)
        for b in range(nb):
            r = r0 + b
            rs = 0 if one_s else r
            rn = 0 if one_n else r
            for l in range(m):
                s = scale[rs, l]
                gam[l, b] = s
                e[l, b] = e_in[r, l] if (not masked or valid[r, l]) else np.nan
                for q in range(m):
                    if noise_diag:
                        nz[l, q, b] = noise[rn, l, 0] if l == q else 0.0
                    else:
                        nz[l, q, b] = noise[rn, l, q]
        _innovation_moments(H0, Pp, gam, nz, e, CP, Rxe, Ree, ok, nb)
        if not noise_diag:  # _innovation_moments adds the diagonal of the noise term only
            for l in range(m):
                for q in range(m):
                    if q != l:
                        for b in range(nb):
                            Ree[l, q, b] += nz[l, q, b]
        if m == 1:
            _gain(Rxe, Ree, ok, K, e, xp, xn, nb, Rs, Ws, Ks, oks, Rxs, ds)
        else:
            _gain_block(Rxe, Ree, ok, K, e, xp, xn, nb, Rw, W, d, bad, Rs, Ws, Ks, oks, Rxs, ds)
        _cov_update(Pp, K, Rxe, H0, gam, nz, joseph, Pn, MH, nb)  # H = diag(s) H0
        if nr > 0:  # P + K V K^T
            for b in range(nb):
                rr = 0 if nr == 1 else r0 + b
                for i in range(nx):
                    for j in range(i, nx):
                        acc = 0.0
                        for l in range(m):
                            acc += K[i, l, b] * retained[rr, l] * K[j, l, b]
                        Pn[i, j, b] += acc
                        if j != i:
                            Pn[j, i, b] += acc
        _store_last(xn, Pn, r0, nb, x_out, P_out)
        for b in range(nb):
            r = r0 + b
            for i in range(nx):
                for l in range(m):
                    K_out[r, i, l] = K[i, l, b]
            for l in range(m):
                for q in range(m):
                    Ree_out[r, l, q] = Ree[l, q, b]
