r"""The Tobit measurement update of a block of runs, compiled (numba).

An *implementation* of the numpy reference path of :mod:`tobitkf.filters.tobit`, not a second algorithm: the
Tobit update (Miller (2015) (3.20)–(3.22), (3.32), (3.37)–(3.41), (3.55)) with the channel masking of
:func:`tobitkf.filters.core.gain_update`, on the censored-normal statistics of
:mod:`tobitkf.filters._compiled_censored` (the one compiled implementation of :func:`tobitkf.censored_moments`;
a channel with one finite limit shared by the runs of a block takes them for all runs at once): the channel
statistics (:func:`tobit_stats_block`), then the update at the effective measurement matrix
(:func:`~tobitkf.filters._compiled_block.scaled_update`). The time loop that runs it is the one compiled loop of the
Gaussian-update families, :func:`tobitkf.filters._compiled_loop.compiled_loop` (which calls the two pieces itself);
the compiled closed loop of :mod:`tobitkf.control` runs it as :func:`tobit_update_block`. Results agree with the
numpy path to rounding (tested to 1e-12).

Functions are compiled on first use and cached on disk (``cache=True``).

Symbols: ``gam`` = E(p) = γ (P(uncensored)), ``lam`` = inverse Mills ratio λ,
``Ruu`` = the noise term :math:`R_{uu}` of (3.40), ``Rxe``/``Ree`` of (3.39)/(3.40).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ._compiled_block import scaled_update
from ._compiled_censored import GL_W, GL_X, censored_moments_array, censored_stats, noise_term, one_sided_block

__all__ = [
    "censored_stats",
    "censored_moments_array",
    "tobit_update_block",
    "tobit_stats_block",
    "NOISE_CODES",
    "GL_X",
    "GL_W",
]

NOISE_CODES = {"dissertation": 0, "total_variance": 1, "exact_pv": 2}

_INF = math.inf
_TINY = float(np.finfo(np.float64).tiny)  # R_ee diagonals not above this count as 0 (as gain_update)


# --- the Tobit Kalman filter -----------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def tobit_stats_block(
    C, sigma, lo, hi, lrow, lstep, y, du, r0, t, noise_code, glx, glw, xp, mu, e, gam, noise, buf, nb
):
    r"""The channel statistics of the Tobit update of a block of ``nb`` runs, all at the prior (Assumption A1,
    (3.35)): for each channel l and run b the mean :math:`\mu = C_l\bar x + Du_k` of its latent reading,
    :math:`\gamma = E(p) = P(\text{uncensored})` (3.22) into ``gam`` (m, B), the noise term :math:`R_{uu}` (3.32)
    of ``noise_code`` (:data:`NOISE_CODES`) into the diagonal of ``noise`` (m, m, B), :math:`E(y)` (3.8) into ``mu``
    (m, B) and the innovation :math:`y - E(y)` into ``e`` (m, B).

    ``C`` (m, n), ``sigma`` (m,) the noise standard deviations, ``xp`` (n, B) the predicted means; run b of the
    block reads its reading at ``y[r0 + b, t]`` (NaN: missing) and its feedthrough :math:`Du_k` at
    ``du[r0 + b, t]`` (``du`` with no steps, ``du.shape[1] == 0``: none); ``lo``/``hi`` (L, m) the limits, run b
    reading row ``lrow + lstep * b`` (``lstep = 0``: one row for the block, the limits of the step; ``lstep = 1``:
    one row per run). A channel whose limits the block shares (``lstep = 0``) with one side infinite gets its
    statistics for all runs at once from :func:`~tobitkf.filters._compiled_censored.one_sided_block` (vectorised;
    8 against 27 ns per run on the central route, 10 against 57 with tails, measured in isolation); any other from
    :func:`censored_stats` run by run (``glx``, ``glw`` its quadrature rule, ``buf`` (2, G) its scratch).

    A function of its own, called (not inlined) from the compiled loop's time loop: inlined there (as
    :func:`tobit_update_block`, its ~25 arguments and the scratch tuples), each array argument and view cost an
    atomic reference-count increment and decrement per step and block, 40 increments in the time loop's LLVM IR
    (n = 4, m = 2); called, 3 remain in the loop, and this function counts its 14 array arguments once per call
    at its entry (numba's reference-count pruning leaves them there), so that a step pays about half as many."""
    m, n = C.shape
    has_du = du.shape[1] > 0
    for l in range(m):
        sd = sigma[l]
        lo_l, hi_l = lo[lrow, l], hi[lrow, l]
        if lstep == 0 and (lo_l == -_INF) != (hi_l == _INF):
            # one finite limit shared by the block (the common Tobit case): the statistics of all runs at
            # once, vectorised (_compiled_censored.one_sided_block); the means C xbar + D u staged in e[l]
            el = e[l]
            for b in range(nb):
                s = 0.0
                for j in range(n):
                    s += xp[j, b] * C[l, j]
                el[b] = s + du[r0 + b, t, l] if has_du else s
            upper = lo_l == -_INF
            one_sided_block(el, sd, hi_l if upper else lo_l, upper, nb, noise_code, gam[l], noise[l, l], mu[l])
            for b in range(nb):
                el[b] = y[r0 + b, t, l] - mu[l, b]
            continue
        for b in range(nb):
            s = 0.0
            for j in range(n):
                s += xp[j, b] * C[l, j]
            mean = s + du[r0 + b, t, l] if has_du else s  # C xbar + D u (the numpy path's x_pred @ C.T + dy)
            r = lrow + lstep * b
            st = censored_stats(mean, sd, lo[r, l], hi[r, l], glx, glw, buf)
            gam[l, b] = st[2]
            noise[l, l, b] = noise_term(noise_code, mean, st[2], st[4], st[5], st[7])
            e[l, b] = y[r0 + b, t, l] - st[6]
            mu[l, b] = st[6]


@njit(cache=True, error_model="numpy", inline="always")
def tobit_update_block(
    C,
    sigma,
    lo,
    hi,
    lrow,
    lstep,
    y,
    du,
    r0,
    t,
    noise_code,
    joseph,
    glx,
    glw,
    xp,
    Pp,
    mu,
    e,
    x,
    P,
    blk,
    run,
    solve,
    buf,
    nb,
):
    r"""The Tobit measurement update of a block of ``nb`` runs (Miller (3.37)–(3.41), (3.39)–(3.40), (3.32),
    (3.22), (3.55)), all channel statistics at the prior (Assumption A1, (3.35)): the channel statistics of
    :func:`tobit_stats_block` (its arguments, by the same names), then
    :math:`R_{xe} = \bar PC^TE(\mathbf p)`, :math:`R_{ee} = E(\mathbf p)C\bar PC^TE(\mathbf p) + R_{uu}`, the masked
    gain and the posterior (:func:`~tobitkf.filters._compiled_block.scaled_update`): the observer's update of the
    compiled closed loop of :mod:`tobitkf.control`. The compiled loop
    (:func:`~tobitkf.filters._compiled_loop.compiled_loop`) calls the same two pieces itself, the second written
    out beside the Kalman filter's update, so that its time loop takes no function inlined with the block's arrays
    as arguments.

    ``xp`` (n, B), ``Pp`` (n, n, B) the prediction; writes the posterior ``x`` (n, B), ``P`` (n, n, B),
    :math:`E(y)` (3.8) in ``mu`` (m, B), the innovation :math:`y - E(y)` in ``e`` (m, B) (0 for a channel left
    out), and in ``blk`` (from :func:`~tobitkf.filters._compiled_block._update_scratch`) ``gam`` =
    :math:`E(\mathbf p)` and the noise term :math:`R_{uu}` among the rest. Inlined (numba ``inline="always"``)."""
    tobit_stats_block(
        C, sigma, lo, hi, lrow, lstep, y, du, r0, t, noise_code, glx, glw, xp, mu, e, blk[9], blk[8], buf, nb
    )
    # Rxe = Pbar C^T E(p), Ree = E(p) C Pbar C^T E(p) + Ruu  (3.39), (3.40); the gain; P with H = diag(E(p)) C (3.41)
    scaled_update(C, joseph, xp, Pp, e, x, P, (blk, run, solve, buf), nb)
