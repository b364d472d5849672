r"""The measurement moments of a fading reading of a nonlinear model, compiled, written once for every path.

The reading of channel l is :math:`y^*_l = \vartheta_l h_l(x) + v_l` (Rice fading of order 0: Geng et al. 2017,
(2) with :math:`L = 0`, the coefficient :math:`\vartheta_l` of mean :math:`\bar\vartheta_l` and variance
:math:`\tilde\vartheta_l`, Assumption 2), :math:`\vartheta` independent of x, of v and across channels. Given
the moments of the unfaded measurement function under the prediction :math:`x \sim N(\bar x, \bar P)`,
:math:`\hat y = E[h(x)]`, :math:`P_{xy} = \mathrm{Cov}(x, h(x))`, :math:`P_{yy} = \mathrm{Cov}(h(x))` (by
linearisation or by sigma points, :mod:`tobitkf.filters.nonlinear`), the moments of the faded function
:math:`\vartheta\odot h(x)` are exact:

.. math::

    E[\vartheta_lh_l] = \bar\vartheta_l\hat y_l, \qquad
    \mathrm{Cov}(x, \vartheta_lh_l) = \bar\vartheta_lP_{xy,\cdot l}, \qquad
    \mathrm{Cov}(\vartheta_ah_a, \vartheta_bh_b) = \bar\vartheta_a\bar\vartheta_bP_{yy,ab}
      + \delta_{ab}\,\tilde\vartheta_a\big(P_{yy,aa} + \hat y_a^2\big).

The first two are the source's :math:`H_k = \bar\theta_k\mathcal C_k` ((10), used in (21) and (24)) on the
linearised moments; the last adds to :math:`\Sigma_{\tilde y\tilde y}` ((25)–(26)) the fading variance
:math:`\tilde\vartheta\,E[h(x)^2]`, which the source leaves out (docs/sources GF-04) and
:class:`~tobitkf.FadingAssumedDensityFilter` keeps, with the second moment under the prediction, as here:
for a linear :math:`h = Cx` it is that filter's :math:`\tilde\vartheta(cPc^T + (c\bar x)^2)`.

:func:`fading_channel` is the equation for one channel; :func:`fading_moments` applies it (and the product of
the means off the diagonal) to the moments of one run in place, :func:`fading_moments_batch` to a batch of runs
(the numpy path), and the compiled nonlinear loop calls the same two functions
(:mod:`tobitkf.filters._compiled_nonlinear`), so the numbers of the two paths come from one definition.
"""

from __future__ import annotations

from numba import njit

__all__ = ["fading_channel", "fading_moments", "fading_moments_batch"]


@njit(cache=True, error_model="numpy", inline="always")
def fading_channel(mean_gain, var_gain, yhat, pyy):
    r"""One channel: ``(mean, scale, variance)`` of :math:`\vartheta h(x)` from the unfaded :math:`\hat y`, its
    variance :math:`P_{yy}` and the coefficient's mean and variance: :math:`\bar\vartheta\hat y`, the factor
    :math:`\bar\vartheta` of its cross-covariance with x, :math:`\bar\vartheta^2P_{yy} +
    \tilde\vartheta(P_{yy} + \hat y^2)`."""
    return mean_gain * yhat, mean_gain, mean_gain * mean_gain * pyy + var_gain * (pyy + yhat * yhat)


@njit(cache=True, error_model="numpy")
def fading_moments(mean_gain, var_gain, ym, Pxy, Pyy):
    r"""The moments of one run in place: ``ym`` (m,) :math:`\hat y`, ``Pxy`` (n, m), ``Pyy`` (m, m) of h become
    those of :math:`\vartheta\odot h` (module docstring); ``mean_gain``, ``var_gain`` (m,)."""
    m = ym.shape[0]
    n = Pxy.shape[0]
    for a in range(m):
        for b in range(m):
            if a != b:
                Pyy[a, b] *= mean_gain[a] * mean_gain[b]
    for a in range(m):
        mu, scale, var = fading_channel(mean_gain[a], var_gain[a], ym[a], Pyy[a, a])
        ym[a] = mu
        Pyy[a, a] = var
        for i in range(n):
            Pxy[i, a] *= scale


@njit(cache=True, error_model="numpy")
def fading_moments_batch(mean_gain, var_gain, ym, Pxy, Pyy):
    """:func:`fading_moments` for every run of ``ym`` (N, m), ``Pxy`` (N, n, m), ``Pyy`` (N, m, m), in place."""
    for r in range(ym.shape[0]):
        fading_moments(mean_gain, var_gain, ym[r], Pxy[r], Pyy[r])
