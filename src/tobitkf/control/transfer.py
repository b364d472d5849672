r"""Transfer functions of the steady-state TKF-LQG loop (Miller §6.4.1, (6.46)–(6.50); docs/sources MB-32).

With the censoring limit moved by (5.68) so that :math:`\hat\gamma \equiv \Xi` (``xi_uncensored``),
the steady-state Tobit observer is linear, and the loop has transfer functions (CT, python-control
objects):

.. math::

    \hat C(s) &= K(sI - A + L\Xi C + BK)^{-1}L \qquad (6.46), (6.50) \\
    \hat P(s) &= \Xi C(sI - A)^{-1}B \qquad (6.47), (6.50) \\
    \hat y &= \hat P(I + \hat C\hat P)^{-1}(N + \hat C)\,\hat r \qquad (6.48)

``gain="tobit"`` uses the Tobit gain of the modified ARE (6.49), ``gain="uncensored"`` the
uncensored LQE gain with :math:`\Xi C` (6.50); the text does not say which one Figs 6.14/6.15 use
(MB-32), so both are offered.

Note (ours, MB-32): (6.48) is the loop :math:`u = Nr + \hat C(r - y)`, not the observer-based
:math:`u = \bar Nr - K\hat x` with the reference entering plant and observer alike; the latter's
:math:`r \to y` map :math:`C(sI - A + BK)^{-1}B\bar N` does not depend on Ξ or L at all
(:func:`observer_based_reference_response`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._extras import require
from .._validation import check_option
from .lqg import lqe, tobit_lqe

__all__ = ["tkf_lqg_loop", "observer_based_reference_response"]


def tkf_lqg_loop(
    A: Any,
    B: Any,
    G: Any,
    C: Any,
    W: Any,
    sigma: float,
    K: Any,
    xi_uncensored: float,
    *,
    gain: str = "tobit",
    N: float | None = None,
):
    r"""The r → y transfer function (6.48) of the TKF-LQG loop at censoring level Ξ (CT).

    Parameters
    ----------
    A, B, G, C, W : plant and process noise (as :func:`~tobitkf.control.lqg.lqe`)
    sigma : float
        Measurement-noise standard deviation σ (a standard deviation, as the name says; the gains are
        computed with the covariance σ²).
    K : (1, n) array_like
        LQR gain.
    xi_uncensored : float in (0, 1]
        P(uncensored) = ED; 1 means no censoring.
    gain : {"tobit", "uncensored"}
        (6.49) or (6.50).
    N : float, optional
        Feed-forward gain of (6.48); default: unit DC gain of the *uncensored* loop (not given in
        the text; labelled default).

    Returns
    -------
    (T_ry, C_hat, P_hat) : control.StateSpace objects
    """
    control = require("control", extra="control")

    check_option(gain, "gain", ("tobit", "uncensored"))
    A, B, C, K = (np.atleast_2d(np.asarray(v, dtype=float)) for v in (A, B, C, K))
    xi = float(xi_uncensored)
    V = np.array([[sigma**2]])
    if gain == "tobit" and xi < 1:
        L = tobit_lqe(A, G, C, W, V=V, xi_uncensored=xi).gain
    else:
        L = lqe(A, G, C, W, V).gain
    Chat = control.ss(A - xi * L @ C - B @ K, L, K, 0)
    Phat = control.ss(A, B, xi * C, 0)
    if N is None:
        L0 = lqe(A, G, C, W, V).gain
        P0 = control.ss(A, B, C, 0)
        C0 = control.ss(A - L0 @ C - B @ K, L0, K, 0)
        p0, c0 = float(np.real(control.dcgain(P0))), float(np.real(control.dcgain(C0)))
        N = (1.0 + c0 * p0) / p0 - c0
    loop = control.feedback(Phat, Chat)
    T_ry = control.series(control.parallel(control.ss([], [], [], [[N]]), Chat), loop)
    return T_ry, Chat, Phat


def observer_based_reference_response(A: Any, B: Any, C: Any, K: Any, Nbar: Any):
    r""":math:`C(sI - A + BK)^{-1}B\bar N`: the r → y map of u = N̄r − Kx̂ with the reference fed to plant and
    observer alike; independent of the observer gain and of Ξ (ours, not in the source: docs/sources MB-32)."""
    control = require("control", extra="control")

    A, B, C, K, Nbar = (np.atleast_2d(np.asarray(v, dtype=float)) for v in (A, B, C, K, Nbar))
    return control.ss(A - B @ K, B @ Nbar, C, 0)
