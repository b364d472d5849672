r"""Assumed-density filter for censored Rice-fading readings.

Not in the source. Channel of Geng et al. 2017 ((1)–(3); :class:`~tobitkf.RiceFading`), with the
augmented state of (7)–(10), :math:`\xi_k = [x_k^T \cdots x_{k-L}^T]^T`:

.. math::

    y^*_k(l) = \sum_{s=0}^{\min(L,k)} \vartheta_k(s)_l\,C_{k-s}(l)\,x_{k-s} + D_k(l)u_k + v_k(l), \qquad
    y_k(l) = \mathrm{clip}(y^*_k(l), l_k(l), h_k(l)).

Given the Gaussian prior :math:`\xi \sim N(\bar\xi, \bar P)` and independent coefficients
(mean :math:`\bar\vartheta(s)`, variance :math:`\tilde\vartheta(s)`), the first two moments of
:math:`(\xi, y^*_k(l))` are exact:

.. math::

    \mu = H_l\bar\xi + d_l, \qquad \mathrm{Cov}(\xi, y^*) = \bar PH_l^T, \qquad
    s^2 = H_l\bar PH_l^T + \underbrace{\sum_s\tilde\vartheta(s)_l\,c_s(\bar P_{ss} + \bar\xi_s\bar\xi_s^T)c_s^T
      + R_{ll}}_{r_l},

with :math:`H_l = [\bar\vartheta(0)_lc_0, \dots, \bar\vartheta(S)_lc_S, 0 \dots]`, :math:`c_s = C_{k-s}(l)`.
The filter takes :math:`(\xi, y^*)` as jointly Gaussian with these moments and conditions on what was
observed exactly as the assumed-density Tobit filter (:mod:`tobitkf.filters.assumed_density`:
:math:`\hat\xi = \bar\xi + K(E[y^*\mid\text{obs}] - \mu)`, :math:`P = \bar P - K(s^2 - V)K^T`,
:math:`K = \bar PH_l^T/s^2`), channel by channel (diagonal R). The TKF-FM of the source instead takes
the censoring statistics at the prior mean and (by default) leaves out the fading variance.

Time convention (package-wide): :math:`x_0 \sim N(\bar x_0, P_0)`; blocks :math:`s > k` of the
augmented state are zero placeholders (the terms :math:`s > k` do not exist); :math:`y_1` at index 0;
result row k-1 holds :math:`\hat x_{k|k}` (the top block).
"""

from __future__ import annotations

import numpy as np

from .._validation import check_bool, check_instance
from ..channels.censoring import Censoring
from ..channels.fading import RiceFading, measurement_matrix_at
from ..models.linear import LinearSystem
from .assumed_density import ADF_OPTIONS, AssumedDensityFamily, AugmentedWindow, censored_channel_update
from .kalman import LinearGaussianFamily
from .registry import family_entry, register

__all__ = ["FadingAssumedDensityFilter"]


class FadingAssumedDensityFilter(AugmentedWindow, AssumedDensityFamily):
    r"""Assumed-density filter for censored readings through a Rice fading channel (module docstring).

    Parameters
    ----------
    system : LinearSystem
        The state model and the unfaded C; diagonal R (entries >= 0).
    fading : RiceFading
        Order L and the coefficient law (its mean and variance are used).
    censoring : Censoring, optional
        The limits; default none.
    covariance_update : {"standard", "joseph", "square_root"}, default "standard"
        Covariance form of the shared update.
    check_limits : bool, default True
        Raise if a reading lies outside its limits.
    backend : {"auto", "numba", "numpy"}, default "auto"
        ``"auto"``: :meth:`filter` through the compiled loop (:mod:`tobitkf.filters._compiled_loop`) when numba
        is installed and the options are covered (the standard covariance form, time-invariant system matrices, inputs through constant ``Bu``/``D``), else the numpy loop; ``"numba"``
        insists on it; ``"numpy"`` never uses it (the same numbers, tested to 1e-12). The numpy loop takes each
        channel's moments from the compiled loop's block (:func:`~tobitkf.filters._compiled_moments.censored_block`,
        with the fading variance in the noise term), on every backend.

    Raises
    ------
    ValidationError
        Non-diagonal or negative R, bad option or argument type.
    ShapeError
        A fading law whose channels do not match the system.

    Notes
    -----
    Extras: ``p_uncensored`` (..., T, m) at each channel's prior, ``log_likelihood`` (..., T).

    Examples
    --------
    Unit deterministic fading of order 0 and no censoring is the Kalman filter:

    >>> import numpy as np, tobitkf as tk
    >>> sys = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.1]], R=[[0.5]], x0=[0.0], P0=[[1.0]])
    >>> y = np.array([[0.3], [-0.4], [1.2]])
    >>> a = tk.FadingAssumedDensityFilter(sys, tk.RiceFading(0, [1.0])).filter(y).mean
    >>> bool(np.allclose(a, tk.KalmanFilter(sys).filter(y).mean, rtol=0, atol=1e-12))
    True
    """

    _name = "FadingAssumedDensityFilter"

    def __init__(
        self,
        system: LinearSystem,
        fading: RiceFading,
        censoring: Censoring | None = None,
        *,
        covariance_update: str = "standard",
        check_limits: bool = True,
        backend: str = "auto",
    ):
        self._configure(system, covariance_update, backend)
        check_instance(fading, RiceFading, "fading")
        if censoring is not None:
            check_instance(censoring, Censoring, "censoring")
        fading.check(system.m)
        censoring = Censoring() if censoring is None else censoring
        censoring.check(system.m)
        self.check_limits = check_bool(check_limits, "check_limits")
        self.fading, self.censoring, self.L = fading, censoring, fading.order
        self.nx = system.n * (self.L + 1)
        self.mean_g, self.var_g = fading.mean_gains(system.m), fading.var_gains(system.m)

    _compiled_spec = "fading_spec"

    _feedthrough = LinearGaussianFamily._feedthrough

    def _initial(self, N, x0, P0, batch):
        return self._window_prior(N, x0, P0, batch, "zero")  # blocks s > k: the terms do not exist yet

    def _project(self, k, xp, Pp, Sp, y, u):
        n, m = self.n, self.m
        N = xp.shape[0]
        S_ = min(self.L, k)
        Cs = [measurement_matrix_at(self.system, k - s) for s in range(S_ + 1)]
        r = self._noise_at(k)
        lo, hi = self.censoring.limits(k)
        lo, hi = np.broadcast_to(lo, (m,)), np.broadcast_to(hi, (m,))
        dy = np.broadcast_to(self._feedthrough(k, u), (N, m))
        x, P, S = xp, Pp, Sp
        pu, ll = np.empty((N, m)), np.zeros(N)
        for l in range(m):
            H = np.zeros(self.nx)
            var = np.full(N, r[l])
            for s in range(S_ + 1):
                c = Cs[s][l]
                H[s * n : (s + 1) * n] = self.mean_g[s, l] * c
                if self.var_g[s, l] > 0:
                    blk = slice(s * n, (s + 1) * n)
                    var = var + self.var_g[s, l] * (
                        np.einsum("rij,i,j->r", P[:, blk, blk], c, c) + (x[:, blk] @ c) ** 2
                    )
            x, P, S, pu[:, l], lll = censored_channel_update(
                x, P, S, y[:, l], H, var, lo[l], hi[l], dy=dy[:, l], form=self.covariance_update, compiled=True
            )  # the moments of the compiled loop's block (censored_block), on every backend
            ll += lll
        return x, P, S, {"p_uncensored": pu, "log_likelihood": ll}

    def _check_record(self, y2, u2, k0, name="y"):
        self.system.check_horizon(k0 + y2.shape[1])
        self.censoring.check(self.m, k0 + y2.shape[1])
        if self.check_limits:
            self.censoring.check_measurements(y2, start=k0 + 1)

    def __repr__(self) -> str:
        return f"FadingAssumedDensityFilter({self.fading!r}, {self.censoring!r})"


register(
    family_entry(
        FadingAssumedDensityFilter,
        "assumed-density filter for censored readings through Rice fading (beyond the sources)",
        ("fading", "censoring?"),
        options=ADF_OPTIONS,
    )
)
