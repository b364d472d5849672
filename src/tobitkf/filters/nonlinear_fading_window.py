r"""Rice fading of order L > 0 on a :class:`~tobitkf.NonlinearSystem`: the augmented window of the nonlinear fading
filters (internal; the filters are those of :mod:`tobitkf.filters.nonlinear_fading`).

The reading of channel l is Geng et al.'s (2) with :math:`C_{k-s}x_{k-s}` replaced by :math:`h(x_{k-s}, k-s)`:

.. math::

    y^*_{k,l} = \sum_{s=0}^{\min(L,k)}\vartheta_k(s)_l\,h_l(x_{k-s}, k-s) + v_{k,l},

the coefficients independent over k, s and l and of the state and the noise (mean :math:`\bar\vartheta(s)_l`,
variance :math:`\tilde\vartheta(s)_l`). As the linear fading filters (:mod:`tobitkf.filters.fading`, (7)–(10)
of the source) the filters carry the window :math:`\xi_k = [x_k^T\ x_{k-1}^T \cdots x_{k-L}^T]^T`
(:math:`n_\xi = n(L+1)`, the blocks :math:`s > k` zero placeholders of zero covariance, the prior
:math:`x_0 \sim N(\bar x_0, P_0)` in the top block):

* **prediction**: :math:`\xi_k = \phi(\xi_{k-1}) + [w_{k-1}; 0]`,
  :math:`\phi(\xi) = [f(x_{k-1}, k-1);\ x_{k-1};\ \dots;\ x_{k-L}]`, by the filter's rule on the whole window
  (the sigma points of :math:`N(\hat\xi, \hat P)` in :math:`n_\xi` dimensions) or, extended, by the Jacobian
  :math:`\Phi` (block row 0 :math:`[F, 0, \dots]`, block row s an identity in column s-1):
  :math:`\bar P = \Phi\hat P\Phi^T + \mathrm{diag}(Q, 0, \dots)`;
* **measurement moments**: those of the stacked map :math:`g(\xi) = [h(x_k, k); \dots; h(x_{k-L}, k-L)]`
  (term s zero while :math:`s > k`) under the prediction, :math:`\hat g`, :math:`P_{\xi g}`, :math:`P_{gg}` (by
  the rule, or extended with the block-diagonal Jacobian), give the exact moments of the faded reading,
  with :math:`M_{l,(s,l)} = \bar\vartheta(s)_l`:

  .. math::

      \hat y = M\hat g, \qquad P_{\xi y} = P_{\xi g}M^T, \qquad
      P_{yy} = MP_{gg}M^T + \mathrm{diag}_l\Big(\sum_s\tilde\vartheta(s)_l\big(P_{gg,(s,l)(s,l)}
      + \hat g_{(s,l)}^2\big)\Big),

  for L = 0 the moments of :mod:`tobitkf.filters._compiled_fading_moments`;

and the update is the filter's own (Kalman, Tobit, or the assumed-density projection channel by channel) on the
window. For a linear :math:`h = Cx` and :math:`f = Ax` these are the moments of the linear fading filters
(:class:`~tobitkf.FadingAssumedDensityFilter`, :class:`~tobitkf.FadingTobitKalmanFilter`), which the filters
then equal (tested). Block s of the state's ``aug_mean`` is the fixed-lag estimate :math:`\hat x_{k-s|k}`.
The numpy path only (the compiled loop carries no window), the standard covariance form, an ``h(x, k)``
without an input (the delayed terms would need the past inputs), no smoother.
"""

from __future__ import annotations

from typing import Any, cast

import numpy as np

from .._linalg import symmetrize
from .._validation import ValidationError
from .assumed_density import AugmentedWindow
from .nonlinear import _per_point, _sigma_moments

__all__ = ["window_gains", "window_moments", "window_predict", "FadingWindow"]


def window_gains(fading: Any, m: int, fading_variance_term: bool) -> np.ndarray:
    r"""The ``(2, L+1, m)`` array :math:`[\bar\vartheta(s)_l;\ \tilde\vartheta(s)_l]` (the variances zeroed
    without the fading variance term).

    Raises
    ------
    ValidationError
        Coefficient means or variances that are not finite, a negative variance.
    """
    gm, gv = fading.mean_gains(m), fading.var_gains(m)
    if not (np.isfinite(gm).all() and np.isfinite(gv).all() and (gv >= 0).all()):
        raise ValidationError(f"fading: expected finite coefficient means and variances >= 0, got {gm}, {gv}")
    return np.stack([gm, gv if fading_variance_term else np.zeros_like(gv)])


def window_moments(gains: np.ndarray, gbar: np.ndarray, Pxg: np.ndarray, Pgg: np.ndarray):
    r"""The faded reading's moments ``(ŷ, P_ξy, P_yy)`` ((N, m), (N, n_ξ, m), (N, m, m)) from those of the stacked
    map g (module docstring): ``gains`` (2, L+1, m), ``gbar`` (N, (L+1) m) ordered delay-major, ``Pxg``
    (N, n_ξ, (L+1) m), ``Pgg`` (N, (L+1) m, (L+1) m)."""
    gm, gv = gains
    L1, m = gm.shape
    N, nx = Pxg.shape[:2]
    G = gbar.reshape(N, L1, m)
    yhat = np.einsum("sl,rsl->rl", gm, G)
    Pxy = np.einsum("sl,risl->ril", gm, Pxg.reshape(N, nx, L1, m))
    Pyy = np.einsum("sa,rsatb,tb->rab", gm, Pgg.reshape(N, L1, m, L1, m), gm)
    dvar = np.einsum("sl,rsl->rl", gv, np.diagonal(Pgg, axis1=-2, axis2=-1).reshape(N, L1, m) + G * G)
    return yhat, Pxy, symmetrize(Pyy + dvar[:, :, None] * np.eye(m))


def _window_map(system: Any, nx: int, k: int, u: np.ndarray | None):
    r""":math:`\phi` of the module docstring on (M, n_ξ) rows (``u`` the input of each row, or None)."""
    n = system.n
    return lambda z: np.concatenate([system.transition_map(z[:, :n], k - 1, u), z[:, : nx - n]], axis=1)


def _window_noise(system: Any, nx: int, k: int) -> np.ndarray:
    r""":math:`\mathrm{diag}(Q_{k-1}, 0, \dots)` (n_ξ, n_ξ)."""
    n = system.n
    Qa = np.zeros((nx, nx))
    Qa[:n, :n] = system.process_cov(k - 1)
    return Qa


def window_predict(rule: Any, system: Any, nx: int, k: int, x: np.ndarray, P: np.ndarray, u: np.ndarray | None):
    r"""The window's prediction :math:`\bar\xi_k, \bar P_k` ((N, n_ξ), (N, n_ξ, n_ξ)) by the sigma-point ``rule``
    from the posterior ``x`` (N, n_ξ), ``P`` (N or 1, n_ξ, n_ξ) at k-1, with the input ``u`` (N, p) or None."""
    points = rule.unit(nx)[0].shape[0]
    xp, _, Pf = _sigma_moments(rule, _window_map(system, nx, k, _per_point(u, points)), x, P)
    return xp, symmetrize(Pf + _window_noise(system, nx, k))


class FadingWindow:
    """The window of a nonlinear fading filter of order L > 0 (module docstring): its prior, prediction, stacked
    measurement map and moments. Every hook defers to the filter's own for order 0 (``_lags == 0``)."""

    system: Any
    n: int
    nx: int
    rule: Any
    fading: Any  # the RiceFading
    fading_variance_term: bool
    _fade: np.ndarray  # order 0: (2, m), the gains read by the compiled loop
    _lags: int = 0
    _gains: np.ndarray  # order L > 0: (2, L+1, m)

    def _window_setup(self, system: Any, fading: Any, fading_variance_term: bool) -> None:
        """Set the window of ``fading`` (order L): nothing to do for order 0.

        Raises
        ------
        ValidationError
            An h that takes an input, with L > 0.
        """
        self._lags = fading.order
        if self._lags == 0:
            return
        if system.h_takes_input:
            raise ValidationError(
                f"fading: an h(x, k, u) with fading of order L={self._lags} is not covered (the delayed terms "
                "h(x_(k-s), k-s) would need the past inputs); fold the input into h or use order 0"
            )
        self._gains = window_gains(fading, system.m, fading_variance_term)
        self.nx = system.n * (self._lags + 1)

    def _state_dim(self) -> int:
        return self.nx if self._lags else self.n

    def _compiled_gap(self) -> str | None:
        if self._lags:
            return f"fading of order L={self._lags} (the window of past states runs on numpy)"
        return super()._compiled_gap()  # type: ignore[misc]

    def _initial(self, N: int, x0: Any, P0: Any, batch: tuple[int, ...]):
        if not self._lags:
            return super()._initial(N, x0, P0, batch)  # type: ignore[misc]
        return AugmentedWindow._window_prior(cast(Any, self), N, x0, P0, batch, "zero")

    def _predict(self, k: int, x: np.ndarray, P: np.ndarray, S: np.ndarray | None = None, u: np.ndarray | None = None):
        if not self._lags:
            return super()._predict(k, x, P, S, u)  # type: ignore[misc]
        sys_, n, nx = self.system, self.n, self.nx
        if self.rule is not None:
            return (*window_predict(self.rule, sys_, nx, k, x, P, u), None)
        Phi = np.zeros((x.shape[0], nx, nx))
        Phi[:, :n, :n] = sys_.transition_jacobian(x[:, :n], k - 1, u)
        Phi[:, n:, : nx - n] = np.eye(nx - n)
        xp = _window_map(sys_, nx, k, u)(x)
        return xp, symmetrize(Phi @ P @ np.swapaxes(Phi, -1, -2) + _window_noise(sys_, nx, k)), None

    def _stacked(self, k: int, l: int | None = None):
        r"""The stacked map :math:`g` on (M, n_ξ) rows: (M, (L+1) m) delay-major, or channel ``l``'s (M, L+1)."""
        sys_, n, m, L = self.system, self.n, self.system.m, self._lags
        cols = slice(None) if l is None else slice(l, l + 1)

        def g(z: np.ndarray) -> np.ndarray:
            out = np.zeros((z.shape[0], L + 1, m))
            for s in range(min(L, k) + 1):
                out[:, s] = sys_.measurement_map(z[:, s * n : (s + 1) * n], k - s)
            return out[:, :, cols].reshape(z.shape[0], -1)

        return g

    def _h_points(self, k: int, u: np.ndarray | None, l: int | None = None):
        if not self._lags:
            return super()._h_points(k, u, l)  # type: ignore[misc]
        return self._stacked(k, l)

    def _window_measurement(self, k: int, xp: np.ndarray, Pp: np.ndarray):
        """``(ŷ, P_ξy, P_yy, H)`` of the faded reading under the window's prediction (H the faded Jacobian of the
        extended form, None for sigma points)."""
        sys_, n, m, L, nx = self.system, self.n, self.system.m, self._lags, self.nx
        N = xp.shape[0]
        if self.rule is None:
            gbar = self._stacked(k)(xp)
            G = np.zeros((N, L + 1, m, nx))
            for s in range(min(L, k) + 1):
                G[:, s, :, s * n : (s + 1) * n] = sys_.measurement_jacobian(xp[:, s * n : (s + 1) * n], k - s)
            G = G.reshape(N, (L + 1) * m, nx)
            Pxg = Pp @ np.swapaxes(G, -1, -2)
            yhat, Pxy, Pyy = window_moments(self._gains, gbar, Pxg, symmetrize(G @ Pxg))
            return yhat, Pxy, Pyy, np.einsum("sl,rsli->rli", self._gains[0], G.reshape(N, L + 1, m, nx))
        gbar, Pxg, Pgg = _sigma_moments(self.rule, self._stacked(k), xp, Pp)
        return (*window_moments(self._gains, gbar, Pxg, Pgg), None)

    def _window_channel(self, l: int, gbar: np.ndarray, Pxg: np.ndarray, Pgg: np.ndarray):
        """Channel ``l``'s faded moments ((N, 1), (N, n_ξ, 1), (N, 1, 1)) from those of its stacked map."""
        return window_moments(np.ascontiguousarray(self._gains[:, :, l : l + 1]), gbar, Pxg, Pgg)

    def smooth(self, y: Any, *args: Any, **kwargs: Any) -> Any:
        if self._lags:
            raise ValidationError(
                f"smooth: fading of order L={self._lags} has no smoother here; the filter's state carries the "
                "fixed-lag estimates x_(k-s|k) (aug_mean)"
            )
        return super().smooth(y, *args, **kwargs)  # type: ignore[misc]
