r"""What a channel's compiled block may call (imports numba; :mod:`tobitkf.channels.base` states the block's contract).

A channel gives the compiled loop of the assumed-density filters its moments by a ``numba.njit`` function, its
``compiled_block``, of the parameters :data:`BLOCK_PARAMETERS`. For a reading that is an interval of the latent
reading (what the channel's ``region`` says) one call per run gives the update:

* :func:`interval_update` ``(mu, s2, lo, hi, glx, glw, buf)`` → ``(alpha, beta, log_p)``: ``lo == hi`` the exact
  reading, else the interval (either end infinite), stable 40 standard deviations into either tail, and the
  degenerate latent (no update; the term 0 when ``mu`` lies in the interval, else :math:`-\infty`);
* :func:`interval_event` ``(mu, sd, lo, hi, glx, glw, buf)`` → ``(log_p, mean, var)``: the log-probability and the
  truncated moments of :math:`y^* \sim N(\mu, sd^2)` given :math:`lo \le y^* \le hi`;
* :data:`MISSING`: the class ``cls[b]`` of a missing reading (no update, no term).

Example (the tutorial "Write your own channel"):

.. code-block:: python

    @njit(error_model="numpy")
    def dead_band_block(nb, y, cls, hx, hph, rb, lo, hi, par, alpha, beta, ll, pu, comp, glx, glw, buf):
        for b in range(nb):
            pu[b] = 1.0
            alpha[b] = beta[b] = 0.0
            if cls[b] != MISSING:
                ea, eb = (-par[0], par[0]) if y[b] == 0.0 else (y[b], y[b])
                alpha[b], beta[b], lp = interval_update(hx[b], hph[b] + rb[b], ea, eb, glx, glw, buf)
                ll[b] += lp
"""

from __future__ import annotations

from ..filters._compiled_moments import BLOCK_PARAMETERS, INTERIOR, MISSING, interval_event, interval_update

__all__ = ["BLOCK_PARAMETERS", "MISSING", "INTERIOR", "interval_update", "interval_event"]
