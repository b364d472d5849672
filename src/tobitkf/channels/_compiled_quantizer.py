r"""The compiled block of the quantized sensor (:class:`~tobitkf.Quantizer`, its ``compiled_block``): the moments of
its assumed-density update over a block of runs, for the compiled loop of the assumed-density filters
(:mod:`tobitkf.filters._compiled_moments` states the block functions' contract). A module of its own so that
importing the channel does not import numba."""

from __future__ import annotations

import numpy as np
from numba import njit

from ..filters._compiled_moments import MISSING, interval_update

__all__ = ["quantizer_block"]


@njit(cache=True, error_model="numpy")
def quantizer_block(nb, y, cls, hx, hph, rb, lo, hi, par, alpha, beta, ll, pu, comp, glx, glw, buf):
    r"""The assumed-density update of a quantized sensor for the runs ``b < nb``: ``par`` = ``(w, o, j_min, j_max)``
    (width, offset, the end levels' indices, infinite without an end). The reading :math:`\ell = o + jw`,
    :math:`j = \mathrm{rint}((y - o)/w)`, says :math:`y^* \in [\ell - w/2, \ell + w/2)`, open to :math:`-\infty` at
    :math:`j \le j_{min}` and to :math:`+\infty` at :math:`j \ge j_{max}` (the channel's ``region``);
    :func:`~tobitkf.filters._compiled_moments.interval_update` gives :math:`\alpha = (E - \mu)/s^2`,
    :math:`\beta = (s^2 - V)/s^4` and the log-probability of the cell from the truncated moments :math:`(E, V)`
    under :math:`y^* \sim N(\mu, s^2)`, :math:`\mu` = ``hx``, :math:`s^2` = ``hph + rb``. A missing reading: no
    update, no term; a degenerate latent (:math:`s^2` not above the smallest normal number): no update, the term 0
    if :math:`\mu` lies in the cell, else :math:`-\infty`. ``pu`` is 1, ``lo``/``hi``/``comp`` unused."""
    w, o, j_min, j_max = par[0], par[1], par[2], par[3]
    for b in range(nb):
        pu[b] = 1.0
        alpha[b] = 0.0
        beta[b] = 0.0
        if cls[b] == MISSING:
            continue
        j = np.rint((y[b] - o) / w)
        level = o + j * w
        ea = -np.inf if j <= j_min else level - 0.5 * w
        eb = np.inf if j >= j_max else level + 0.5 * w
        a, be, lp = interval_update(hx[b], hph[b] + rb[b], ea, eb, glx, glw, buf)
        alpha[b] = a
        beta[b] = be
        ll[b] += lp
