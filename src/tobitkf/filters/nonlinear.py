r"""Filters of a :class:`~tobitkf.NonlinearSystem`: the prediction turned into the moments the linear update takes.

Every filter here reduces one step of :math:`x_k = f(x_{k-1}, k-1) + w`, :math:`y^*_k = h(x_k, k) + v` to
Gaussian moments and hands them to the shared Gaussian step (:func:`~tobitkf.filters.core.gain_update`):

* the **prediction** :math:`\bar x, \bar P` of :math:`x_k`: by linearisation (extended,
  :math:`\bar x = f(\hat x)`, :math:`\bar P = F\hat PF^T + Q`, :math:`F = \partial f/\partial x` at
  :math:`\hat x`) or by a sigma-point rule (:math:`\bar x = \sum_i w^m_if(\chi_i)`,
  :math:`\bar P = \sum_i w^c_i(f(\chi_i) - \bar x)(\cdot)^T + Q`, :math:`\chi_i` the rule's points of
  :math:`N(\hat x, \hat P)`);
* the **measurement prediction** :math:`\hat y = E[h(x_k)]`, :math:`P_{xy} = \mathrm{Cov}(x_k, h(x_k))`,
  :math:`P_{yy} = \mathrm{Cov}(h(x_k))` under :math:`x_k \sim N(\bar x, \bar P)`: extended
  :math:`\hat y = h(\bar x)`, :math:`P_{xy} = \bar PH^T`, :math:`P_{yy} = H\bar PH^T`; sigma points
  :math:`\chi_i` of :math:`N(\bar x, \bar P)` (redrawn after the prediction) with the same weighted sums.
  That is the affine model :math:`y^* \approx \mathcal Hx + b + e`, :math:`e \sim N(0, \Omega + R)`, with
  :math:`\mathcal H = P_{xy}^T\bar P^{-1}`, :math:`b = \hat y - \mathcal H\bar x`,
  :math:`\Omega = P_{yy} - \mathcal H\bar P\mathcal H^T` (the statistical linearisation; :math:`\Omega = 0`
  for the extended form).

The **update** from these moments is the linear one's with :math:`C` replaced by the linearisation:

* :class:`ExtendedKalmanFilter` / :class:`UnscentedKalmanFilter`: :math:`K = P_{xy}(P_{yy} + R)^{-1}`,
  :math:`\hat x = \bar x + K(y - \hat y)`, :math:`P = \bar P - KP_{xy}^T`;
* :class:`TobitExtendedKalmanFilter` / :class:`TobitUnscentedKalmanFilter`: the Tobit Kalman filter's update
  (Arthur, Attarian, Hamilton & Tran 2018, the Tobit EKF), every statistic at the predicted measurement as
  the TKF takes them (Miller 2015, Assumption A1): per channel l, at :math:`\mu_l = \hat y_l` and the noise's
  :math:`\sigma_l = \sqrt{R_{ll}}`, the reading's mean :math:`E[y_l]`, slope
  :math:`g_l = \partial E[y_l]/\partial\mu_l` (for censoring :math:`E(\mathbf p)`, the probability of an
  uncensored reading) and a noise term :math:`N_l` (for censoring the TKF's ``noise_term``, by default the
  truncated variance of its source; for any other channel its reading's variance
  :math:`\mathrm{Var}[y_l]`, from ``reading_statistics``), and with :math:`G = \mathrm{diag}(g)`

  .. math::

      K = P_{xy}G\,(GP_{yy}G + \mathrm{diag}(N))^{-1}, \qquad \hat x = \bar x + K(y - E[y]),
      \qquad P = \bar P - KGP_{xy}^T,

  for a linear :math:`h` exactly :class:`~tobitkf.TobitKalmanFilter` (censoring, each ``noise_term``) and
  :class:`~tobitkf.TobitFilter` (any channel with ``reading_statistics``), tested;
* :class:`NonlinearAssumedDensityFilter`: channel by channel (R diagonal), the latent reading of channel l
  under the affine model is :math:`y^*_l \sim N(\mu, s^2)`, :math:`\mu = \hat y_l`,
  :math:`s^2 = P_{yy,ll} + R_{ll}`, jointly Gaussian with x with covariance :math:`P_{xy,\cdot l}`; the
  channel's exact moments of the latent reading given its reading (``reading_moments``: censored,
  saturated at a limit, an interval of a quantizer) give the projection
  :math:`\hat x = \bar x + K(E[y^* \mid y] - \mu)`, :math:`P = \bar P - K(s^2 - V)K^T`,
  :math:`K = P_{xy,\cdot l}/s^2` (the linear :class:`~tobitkf.AssumedDensityFilter`'s update, which it equals
  for a linear h). With ``iterations > 1`` the linearisation is redone about the current posterior
  (iterated posterior linearisation, García-Fernández et al. 2015): :math:`\mathcal H, b, \Omega` from the
  sigma points of the posterior, then the update from the prior with :math:`\mu = \mathcal H\bar x + b`,
  :math:`s^2 = \mathcal H\bar P\mathcal H^T + \Omega + R_{ll}`, :math:`K = \bar P\mathcal H^T/s^2`.

Sigma-point rules (``rule=``, unit points :math:`\xi_i` with :math:`\chi_i = \bar x + L\xi_i`,
:math:`LL^T = \bar P` the lower Cholesky factor, an eigen root when P is singular):

``"unscented"`` (alpha, beta, kappa)
    :math:`\lambda = \alpha^2(n + \kappa) - n`; :math:`\xi_0 = 0`, :math:`\xi_{\pm i} = \pm\sqrt{n+\lambda}e_i`;
    :math:`w^m_0 = \lambda/(n+\lambda)`, :math:`w^c_0 = w^m_0 + 1 - \alpha^2 + \beta`, the others
    :math:`1/(2(n+\lambda))` (Wan & van der Merwe 2000; filterpy's ``MerweScaledSigmaPoints``). Exact for
    polynomials of degree 3 in the mean.
``"cubature"``
    :math:`\xi_{\pm i} = \pm\sqrt n e_i`, weights :math:`1/(2n)` (Arasaratnam & Haykin 2009); degree 3.
``"gauss_hermite"`` (order p)
    the tensor product of the p-point Gauss–Hermite rule for :math:`N(0, 1)` (:math:`p^n` points); exact for
    polynomials of degree up to :math:`2p - 1` in each coordinate.

**Square-root form** (``covariance_update="square_root"``, every filter here; a numerical device, not in the
sources): a factor :math:`S`, :math:`P = SS^T`, is carried instead of P. The points are drawn from S itself;
the predicted factor is the triangular factor of one QR of the weighted deviations and the noise root,
:math:`[\sqrt{w^c_i}(f(\chi_i) - \bar x)^T;\ Q^{1/2\,T}]` (a rank-one Cholesky downdate per negative weight);
the update is the array form (:func:`~tobitkf.filters.core.sqrt_update`) of the statistical linearisation,
:math:`\mathcal H = Z^TS^{-1}` with :math:`Z = \sum_iw^c_i\xi_i(h(\chi_i) - \hat y)^T` (so
:math:`P_{xy} = SZ`), and noise :math:`\Omega + R` factored from the residual rows
:math:`\sqrt{w^c_i}(h(\chi_i) - \hat y - Z^T\xi_i)`. Equal to the standard form to rounding, PSD by
construction.

**Known inputs**: with an ``f(x, k, u)`` (:class:`~tobitkf.NonlinearSystem` ``inputs=p``) every ``filter``,
``step``, ``predict`` and ``smooth`` takes ``u`` (row k-1 holds :math:`u_k`, :math:`x_k = f(x_{k-1}, k-1, u_k)`).

Missing readings (NaN) take no part in the update, channel by channel. Time convention (package-wide):
:math:`x_0 \sim N(\bar x_0, P_0)` is the prior, :math:`y_1` is at index 0, result row k-1 holds
:math:`\hat x_{k|k}`, :math:`P_{k|k}` and the prediction.
"""

from __future__ import annotations

import math
import sys
from functools import lru_cache
from typing import Any, cast

import numpy as np

from .._linalg import psd_sqrt, symmetrize
from .._validation import ShapeError, ValidationError, as_float_array, check_instance, check_int, diagonal_sigma
from ..channels.censoring import Censoring
from ..models.nonlinear import NonlinearSystem
from . import _online_check
from ._backend import BACKENDS, use_compiled
from .adf_generic import _contract_channel, _ContractChecks
from .core import (
    FilterResult,
    FilterState,
    GaussianFilter,
    check_keywords,
    check_prior,
    entering_state,
    gain_update,
    mark_trusted,
    prepare_inputs,
    process_roots,
    qr_r,
    sqrt_update,
)
from .tobit import NOISE_TERMS, tobit_measurement

__all__ = [
    "SigmaPoints",
    "ExtendedKalmanFilter",
    "UnscentedKalmanFilter",
    "TobitExtendedKalmanFilter",
    "TobitUnscentedKalmanFilter",
]

RULES = ("unscented", "cubature", "gauss_hermite")


# --------------------------------------------------------------------------- sigma-point rules


class SigmaPoints:
    r"""A sigma-point rule for :math:`E[g(x)]`, :math:`x \sim N(\bar x, \bar P)` (the module docstring).

    Parameters
    ----------
    rule : {"unscented", "cubature", "gauss_hermite"}, default "unscented"
    alpha, beta, kappa : float, default 1, 2, 0
        The unscented rule's parameters (``alpha > 0``, ``n + kappa > 0``); ignored by the other rules.
    order : int >= 1, default 3
        Points per coordinate of the Gauss–Hermite rule; ignored by the other rules.

    Raises
    ------
    ValidationError
        An unknown rule, a non-positive alpha or order, a kappa with ``n + kappa <= 0`` (at first use).
    """

    def __init__(
        self, rule: str = "unscented", *, alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0, order: int = 3
    ):
        check_keywords({"rule": rule}, {"rule": RULES})
        self.rule = rule
        self.alpha, self.beta, self.kappa = float(alpha), float(beta), float(kappa)
        if not (math.isfinite(self.alpha) and self.alpha > 0):
            raise ValidationError(f"alpha: expected a positive number, got {alpha!r}")
        if not (math.isfinite(self.beta) and math.isfinite(self.kappa)):
            raise ValidationError(f"beta/kappa: expected finite numbers, got {beta!r}, {kappa!r}")
        self.order = check_int(order, "order", minimum=1, maximum=40)

    def unit(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The unit points ``(L, n)`` and the mean and covariance weights ``(L,)`` for dimension ``n``."""
        return _unit(self.rule, n, self.alpha, self.beta, self.kappa, self.order)

    def points(self, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        r"""The points :math:`\chi_i = x + L\xi_i` (N, L, n) of :math:`N(x, P)`, x (N, n), P (N or 1, n, n)."""
        xi = self.unit(x.shape[-1])[0]
        root = psd_sqrt(P)
        return x[:, None, :] + np.einsum("lj,rij->rli", xi, root)

    def __repr__(self) -> str:
        if self.rule == "unscented":
            return f"SigmaPoints('unscented', alpha={self.alpha}, beta={self.beta}, kappa={self.kappa})"
        if self.rule == "gauss_hermite":
            return f"SigmaPoints('gauss_hermite', order={self.order})"
        return "SigmaPoints('cubature')"


@lru_cache(maxsize=64)
def _unit(rule: str, n: int, alpha: float, beta: float, kappa: float, order: int):
    eye = np.eye(n)
    if rule == "unscented":
        if n + kappa <= 0:
            raise ValidationError(f"kappa: expected n + kappa > 0 (n = {n}), got kappa = {kappa}")
        lam = alpha**2 * (n + kappa) - n
        c = n + lam
        xi = np.concatenate([np.zeros((1, n)), math.sqrt(c) * eye, -math.sqrt(c) * eye])
        wm = np.full(2 * n + 1, 0.5 / c)
        wc = wm.copy()
        wm[0] = lam / c
        wc[0] = lam / c + (1.0 - alpha**2 + beta)
    elif rule == "cubature":
        xi = np.concatenate([math.sqrt(n) * eye, -math.sqrt(n) * eye])
        wm = np.full(2 * n, 0.5 / n)
        wc = wm
    else:
        nodes, weights = np.polynomial.hermite_e.hermegauss(order)
        weights = weights / weights.sum()
        grids = np.meshgrid(*([nodes] * n), indexing="ij")
        xi = np.stack([g.ravel() for g in grids], axis=-1)
        wgrids = np.meshgrid(*([weights] * n), indexing="ij")
        wm = np.prod(np.stack([g.ravel() for g in wgrids], axis=-1), axis=-1)
        wc = wm
    for arr in (xi, wm, wc):
        arr.setflags(write=False)
    return xi, wm, wc


def _sigma_moments(rule: SigmaPoints, fun, x: np.ndarray, P: np.ndarray):
    r"""``(ȳ, P_xy, P_yy)`` of :math:`y = g(x)`, :math:`x \sim N(x, P)`: (N, r), (N, n, r), (N, r, r).

    ``fun`` maps the points (N L, n), run-outermost, to (N L, r)."""
    N, n = x.shape
    _, wm, wc = rule.unit(n)
    X = rule.points(x, P)
    L = X.shape[1]
    Y = fun(X.reshape(N * L, n)).reshape(N, L, -1)
    ym = np.einsum("l,rla->ra", wm, Y)
    dY = Y - ym[:, None, :]
    dX = X - x[:, None, :]
    Pyy = np.einsum("l,rla,rlb->rab", wc, dY, dY)
    Pxy = np.einsum("l,rla,rlb->rab", wc, dX, dY)
    return ym, Pxy, symmetrize(Pyy)


def _per_point(u: np.ndarray | None, points: int) -> np.ndarray | None:
    """The input of each run (N, p) repeated for its ``points`` sigma points (run-outermost rows)."""
    return None if u is None else np.repeat(u, points, axis=0)


def _sigma_factor(rule: SigmaPoints, fun, x: np.ndarray, S: np.ndarray):
    r"""The points of :math:`N(x, SS^T)` (S a factor of N or 1 runs) through ``fun``: ``(ȳ, dY, ξ, w^c)`` with
    :math:`\bar y = \sum_i w^m_ig(\chi_i)` (N, r) and the deviations :math:`g(\chi_i) - \bar y` (N, L, r)."""
    N, n = x.shape
    xi, wm, wc = rule.unit(n)
    L = xi.shape[0]
    X = x[:, None, :] + np.einsum("lj,rij->rli", xi, S)
    Y = fun(X.reshape(N * L, n)).reshape(N, L, -1)
    ym = np.einsum("l,rla->ra", wm, Y)
    return ym, Y - ym[:, None, :], xi, wc


def _weighted_factor(E: np.ndarray, wc: np.ndarray, root: np.ndarray | None) -> np.ndarray:
    r"""Lower factor W (N, r, r) of :math:`\sum_i w_ie_ie_i^T + \text{root}\,\text{root}^T` from the rows
    ``E`` (N, L, r) and ``root`` ((r, c) or (N, r, c)): one QR of :math:`[\sqrt{w_i}e_i^T;\ \text{root}^T]` over the non-negative weights, then a
    rank-one downdate per negative weight."""
    N, L, r = E.shape
    pos = wc >= 0
    rows = np.sqrt(wc[pos])[None, :, None] * E[:, pos, :]
    if root is not None:
        rows = np.concatenate([rows, np.broadcast_to(np.swapaxes(root, -1, -2), (N,) + root.shape[-2:])], axis=1)
    if rows.shape[1] < r:  # fewer rows than columns: pad with zeros (a singular factor)
        rows = np.concatenate([rows, np.zeros((N, r - rows.shape[1], r))], axis=1)
    W = np.swapaxes(qr_r(rows), -1, -2)
    sign = np.where(np.diagonal(W, axis1=-2, axis2=-1) < 0, -1.0, 1.0)
    W = W * sign[:, None, :]
    for i in np.flatnonzero(~pos):
        W = _chol_downdate(W, math.sqrt(-wc[i]) * E[:, i, :])
    return W


def _chol_downdate(L: np.ndarray, v: np.ndarray) -> np.ndarray:
    r"""The lower factor of :math:`LL^T - vv^T`, batched ((N, r, r), (N, r)); NaN rows where it is indefinite."""
    L, v = L.copy(), v.copy()
    r = L.shape[-1]
    for j in range(r):
        d = L[:, j, j]
        rad = d * d - v[:, j] ** 2
        bad = ~(rad >= 0)
        new = np.sqrt(np.where(bad, 0.0, rad))
        safe = np.where(d > 0, d, 1.0)
        c, s_ = np.where(d > 0, new / safe, 1.0), np.where(d > 0, v[:, j] / safe, 0.0)
        L[:, j, j] = new
        if j + 1 < r:
            cs = np.where(c > 0, c, 1.0)
            col = (L[:, j + 1 :, j] - s_[:, None] * v[:, j + 1 :]) / cs[:, None]
            v[:, j + 1 :] = c[:, None] * v[:, j + 1 :] - s_[:, None] * col
            L[:, j + 1 :, j] = col
        L[bad] = np.nan
    return L


def _add_retained(S: np.ndarray, K: np.ndarray, V: np.ndarray) -> np.ndarray:
    r"""The factor of :math:`SS^T + KVK^T` (V (N, m) diagonal, >= 0) by one QR: PSD by construction."""
    KV = K * np.sqrt(np.maximum(V, 0.0))[..., None, :]
    Sb = np.broadcast_to(S, KV.shape[:-2] + S.shape[-2:])
    U = qr_r(np.concatenate([np.swapaxes(Sb, -1, -2), np.swapaxes(KV, -1, -2)], axis=-2))
    return np.swapaxes(U, -1, -2)


def _linearisation(S: np.ndarray, dY: np.ndarray, xi: np.ndarray, wc: np.ndarray):
    r"""The statistical linearisation of :math:`g` from its points about :math:`N(x, SS^T)`: ``(HS, H, E)`` with
    :math:`HS = Z^T` (N, r, n), :math:`\mathcal H = Z^TS^{-1}` (N, r, n; a least-squares solve when S is
    singular) and the residuals E (N, L, r) (:func:`_sigma_factor`)."""
    Z = np.einsum("l,lj,rla->rja", wc, xi, dY)  # (N, n, r)
    HS = np.swapaxes(Z, -1, -2)
    E = dY - np.einsum("lj,rja->rla", xi, Z)
    Sb = np.broadcast_to(S, (Z.shape[0],) + S.shape[-2:])
    try:
        H = np.swapaxes(np.linalg.solve(np.swapaxes(Sb, -1, -2), Z), -1, -2)
    except np.linalg.LinAlgError:
        H = HS @ np.linalg.pinv(Sb)
    return HS, H, E


# --------------------------------------------------------------------------- the shared family


class _NonlinearFamily(GaussianFilter):
    """A filter of a :class:`~tobitkf.NonlinearSystem`: prior, predict and the measurement moments by
    linearisation (``rule=None``) or sigma points; the update is the family's."""

    system: Any  # a NonlinearSystem (Any: the contract checks' mixin declares a LinearSystem)
    _forms: tuple[str, ...] = ("standard", "square_root")

    _filter_doc = (
        "Filter the readings ``y`` (..., T, m) of a batch of records: one predict and update per step (f, h or a "
        "Jacobian returning the wrong shape: a ShapeError naming it)."
    )
    _filter_params = {
        "u": "(T, p) or (..., T, p) array_like, optional\n"
        "    Known inputs u_1..u_T of an ``f(x, k, u)`` (index k-1 holds u_k; none given: u = 0).",
    }
    _filter_raises = "a reading the channel cannot give (its ``check_readings``)"

    #: the update code of the compiled loop (:mod:`tobitkf.filters._compiled_nonlinear_loop`): 0 Kalman, 1 Tobit, 2 ADF
    _compiled_code = 0

    def _setup(self, system: Any, covariance_update: str, rule: SigmaPoints | None, backend: str = "auto") -> None:
        check_instance(system, NonlinearSystem, "system")
        check_keywords(
            {"covariance_update": covariance_update, "backend": backend},
            {"covariance_update": self._forms, "backend": BACKENDS},
        )
        self.backend = backend
        self.system = system
        self.n, self.m = system.n, system.m
        self.covariance_update = covariance_update
        self.rule = rule
        if rule is not None:
            rule.unit(self.n)  # a kappa that does not fit n is refused here
        self._qroot: Any = process_roots(system) if covariance_update == "square_root" else None

    def _compiled_core(self) -> bool:
        return False

    # ---- the compiled path (:mod:`tobitkf.filters._compiled_nonlinear_loop`)
    def _compiled_gap(self) -> str | None:
        """Why the compiled loop cannot run this estimator, or None."""
        sys_ = self.system
        plain = [name for name in ("f", "h", "F", "H") if not _is_jitted(getattr(sys_, name))]
        if plain:
            return f"{', '.join(plain)} not compiled with numba.njit"
        from . import _compiled_nonlinear_loop

        return _compiled_nonlinear_loop.channel_gap(self)

    def _use_compiled(self) -> bool:
        """Whether ``filter`` and ``step`` run the compiled loop: decided once per estimator by its ``backend``
        (``"auto"``: when f and h are numba-compiled and the case is covered; ``"numba"``: always, else an error).

        Raises
        ------
        ValidationError
            ``backend="numba"`` with f or h (or a given F, H) that are not ``numba.njit`` functions, or a case the
            compiled loop does not cover.
        """
        cached = self.__dict__.get("_compiled_ok")
        if cached is None:
            if self.backend == "numpy":
                cached = False
            else:
                gap = self._compiled_gap()
                if gap is not None and self.backend == "numba" and "numba.njit" in gap:
                    raise ValidationError(
                        f"backend: 'numba' runs f and h compiled, but {gap}; decorate them with @numba.njit "
                        "(written for a batch of points (..., n) as for numpy), or use backend='auto' or 'numpy'"
                    )
                cached = use_compiled(self.backend, gap, f"the {self._name}")
            self._compiled_ok = cached
        return cached

    def _compiled_filter(self, y2, u2, state, want, batch, step_options=None):
        if not self._use_compiled():
            return None
        from . import _compiled_nonlinear_loop

        return _compiled_nonlinear_loop.compiled_run(self, y2, u2, state, want, batch)

    def step(self, state: FilterState, y: Any, *, u: Any = None, **options: Any) -> FilterState:
        """One predict + update with the reading ``y`` (``batch_shape + (m,)``; NaN = missing); ``u`` the input
        :math:`u_{k+1}` of an ``f(x, k, u)``. Equal to one row of :meth:`filter`.

        With numba-compiled f and h (``backend`` "auto" or "numba") the step runs the compiled loop over one
        step: the same checks of the state and the reading, and the same consistency check of the updates as
        the numpy step (from the step's own prediction); a covariance that stops being finite reruns the step on
        the numpy path, which reports it.
        """
        if options or not self._use_compiled() or self.covariance_update == "square_root":
            return super().step(state, y, u=u, **options)  # the square-root form's online step runs on numpy
        state = entering_state(self, state)
        if state.carry.get("_predicted"):
            return super().step(state, y, u=u)  # refuses a predicted state, with the numpy step's message
        yk = self._reading(state, y)
        uk = self._step_input(state, u)
        self._check_reading(state.k + 1, yk, {})
        from . import _compiled_nonlinear_loop

        out = _compiled_nonlinear_loop.compiled_run(
            self, yk[:, None], None if uk is None else uk[:, None], state, frozenset(), state.batch_shape, online=True
        )
        if out is None:
            return super().step(state, y, u=u)
        new, xp, Pp = out
        return mark_trusted(self, _online_check.check_step(self, state, new, uk, xp, Pp))

    def _initial(self, N: int, x0: Any, P0: Any, batch: tuple[int, ...]):
        x, P = check_prior(self.system, x0, P0, N, batch)
        per_run = (x0 is not None and np.ndim(x0) > 1) or (P0 is not None and np.ndim(P0) > 2)
        return x, (P if per_run else P[:1].copy()), {}

    def _check_record(self, y2: np.ndarray, u2, k0: int, name: str = "y") -> None:
        self.system.check_horizon(k0 + y2.shape[1])

    def _prepare_inputs(self, u: Any, N: int, T: int, batch: tuple[int, ...]) -> np.ndarray | None:
        return prepare_inputs(self.system, u, N, T)

    def _step_input(self, state: FilterState, u: Any) -> np.ndarray | None:
        if u is None:
            return None
        p = self.system.p
        if p is None:
            raise ShapeError("u: this NonlinearSystem takes no input (write f(x, k, u) or h(x, k, u), with inputs=p)")
        arr = as_float_array(u, "u")
        want = state.batch_shape + (p,)
        try:
            arr = np.broadcast_to(arr, want)
        except ValueError:
            raise ShapeError(f"u: expected one input of shape {want} (batch_shape + (p,)), got {arr.shape}") from None
        return arr.reshape(state.runs, p)

    def _predict(self, k: int, x: np.ndarray, P: np.ndarray, S: np.ndarray | None = None, u: np.ndarray | None = None):
        r""":math:`\bar x_k, \bar P_k` (and the factor :math:`\bar S_k` in the square-root form, else None) from
        the posterior at k-1, with the input :math:`u_k` (N, p) or None."""
        sys_, Q = self.system, self.system.process_cov(k - 1)
        if self.rule is None:
            xp = sys_.transition_map(x, k - 1, u)
            F = sys_.transition_jacobian(x, k - 1, u)
            if S is not None:
                root = self._qroot(k - 1)
                rows = np.concatenate(
                    [np.swapaxes(F @ S, -1, -2), np.broadcast_to(root.T, (F.shape[0],) + root.T.shape)], axis=-2
                )
                Sp = np.swapaxes(qr_r(rows), -1, -2)
                return xp, symmetrize(Sp @ np.swapaxes(Sp, -1, -2)), Sp
            return xp, symmetrize(F @ P @ F.swapaxes(-1, -2) + Q), None
        if S is not None:
            L = self.rule.unit(self.n)[0].shape[0]
            xp, dX, xi, wc = _sigma_factor(self.rule, lambda z: sys_.transition_map(z, k - 1, _per_point(u, L)), x, S)
            Sp = _weighted_factor(dX, wc, self._qroot(k - 1))
            return xp, symmetrize(Sp @ np.swapaxes(Sp, -1, -2)), Sp
        L = self.rule.unit(self.n)[0].shape[0]
        xp, _, Pf = _sigma_moments(self.rule, lambda z: sys_.transition_map(z, k - 1, _per_point(u, L)), x, P)
        return xp, symmetrize(Pf + Q), None

    def _measurement_moments(self, k: int, xp: np.ndarray, Pp: np.ndarray, u: np.ndarray | None = None):
        """``(ŷ, P_xy, P_yy, H)`` of :math:`h(x_k)` (or :math:`h(x_k, k, u_k)`, ``u`` (N, p) or None) under the
        prediction (H the Jacobian, None for sigma points)."""
        sys_ = self.system
        if self.rule is None:
            yhat = sys_.measurement_map(xp, k, u)
            H = sys_.measurement_jacobian(xp, k, u)
            Pxy = Pp @ H.swapaxes(-1, -2)
            return yhat, Pxy, symmetrize(H @ Pxy), H
        yhat, Pxy, Pyy = _sigma_moments(self.rule, self._h_points(k, u), xp, Pp)
        return yhat, Pxy, Pyy, None

    def _h_points(self, k: int, u: np.ndarray | None, l: int | None = None):
        """The measurement map of the rule's points (N L, n) -> (N L, m) (or channel ``l`` alone, (N L, 1)), with
        the input of each run repeated for its points."""
        sys_ = self.system
        assert self.rule is not None, "sigma points need a rule"
        L = self.rule.unit(self.n)[0].shape[0]
        uL = _per_point(u, L)
        if l is None:
            return lambda z: sys_.measurement_map(z, k, uL)
        return lambda z: sys_.measurement_map(z, k, uL)[:, l : l + 1]

    def _measurement_factor(self, k: int, xp: np.ndarray, Sp: np.ndarray, u: np.ndarray | None = None):
        r"""Square-root form: ``(ŷ, H, E, wc)``, the statistical linearisation :math:`\mathcal H` (N, m, n) of h
        about :math:`N(\bar x, \bar S\bar S^T)` and its residual rows (:func:`_linearisation`); the extended
        form: ŷ = h(x̄), the Jacobian and no residual (None, None)."""
        sys_ = self.system
        if self.rule is None:
            return sys_.measurement_map(xp, k, u), sys_.measurement_jacobian(xp, k, u), None, None
        ym, dY, xi, wc = _sigma_factor(self.rule, self._h_points(k, u), xp, Sp)
        _, H, E = _linearisation(Sp, dY, xi, wc)
        return ym, H, E, wc

    def _step_arrays(self, k: int, x, P, S, carry, y, u, options=None):
        xp, Pp, Sp = self._predict(k, x, P, S, u)
        xn, Pn, Sn, carry, extras = self._update_arrays(k, xp, Pp, Sp, y, u, carry, options or {})
        return xn, Pn, Sn, carry, xp, Pp, extras

    def predict(self, state: FilterState, *, u: Any = None) -> FilterState:
        r"""The time update alone: the prediction :math:`\bar x_{k+1}`, :math:`\bar P_{k+1}` as a state whose
        ``k`` is the predicted time (pass it to :meth:`update` with that time's reading); ``u`` the input
        :math:`u_{k+1}` of an ``f(x, k, u)``."""
        state = entering_state(self, state)
        uk = self._step_input(state, u)
        k = state.k + 1
        assert state.P is not None, "a Gaussian filter's state carries P"
        xp, Pp, Sp = self._predict(k, state.x, state.P, state.S, uk)
        carry = dict(state.carry)
        carry["_predicted"] = True
        carry.pop("_u", None)
        if uk is not None:  # the update's h(x, k, u) reads the same step's input
            carry["_u"] = uk
        return FilterState(k=k, batch_shape=state.batch_shape, x=xp, P=Pp, n=self.n, S=Sp, carry=carry)

    def _noise(self, k: int) -> np.ndarray:
        return self.system.measurement_cov(k)

    def smooth(self, y: Any, *, u: Any = None, x0: Any = None, P0: Any = None) -> FilterResult:
        r"""Fixed-interval (RTS) smoother of ``y`` (..., T, m) over this filter's moments.

        The backward pass of the extended RTS smoother (a filter without sigma points: the cross-covariance
        :math:`C_k = P_{k|k}F_k^T`, :math:`F_k = \partial f/\partial x` at :math:`\hat x_{k|k}`) or of the
        sigma-point RTS smoother (Särkkä 2008: :math:`C_k = \sum_i w^c_i(\chi_i - \hat x_{k|k})
        (f(\chi_i, k) - \bar x_{k+1})^T`, the rule's points of :math:`N(\hat x_{k|k}, P_{k|k})`), over the
        filtered and predicted moments of :meth:`filter`:

        .. math::

            G_k = C_k\bar P_{k+1}^{-1}, \qquad \hat x_{k|T} = \hat x_{k|k} + G_k(\hat x_{k+1|T} - \bar x_{k+1}),
            \qquad P_{k|T} = P_{k|k} + G_k(P_{k+1|T} - \bar P_{k+1})G_k^T.

        For a linear model it is the Kalman (RTS) smoother. ``u`` are the inputs of an ``f(x, k, u)``, as for
        :meth:`filter`.

        Returns
        -------
        FilterResult
            ``mean`` :math:`\hat x_{k|T}` (..., T, n), ``cov`` :math:`P_{k|T}` (..., T, n, n), ``extras``
            ``filtered_mean``, ``filtered_cov`` and ``gain`` (:math:`G_k`, (..., T, n, n); zero in the last row);
            ``times`` as the filter's.

        Raises
        ------
        ValidationError, ShapeError
            As :meth:`filter`.
        """
        res = self.filter(y, u=u, x0=x0, P0=P0)
        assert res.mean is not None and res.cov is not None and res.pred_mean is not None and res.pred_cov is not None
        assert res.times is not None
        batch, (T, n) = res.mean.shape[:-2], res.mean.shape[-2:]
        xf, Pf = res.mean.reshape(-1, T, n), np.broadcast_to(res.cov, batch + (T, n, n)).reshape(-1, T, n, n)
        xp, Pp = res.pred_mean.reshape(-1, T, n), np.broadcast_to(res.pred_cov, batch + (T, n, n)).reshape(-1, T, n, n)
        N = xf.shape[0]
        u2 = self._prepare_inputs(u, N, T, batch)
        xs, Ps, gain = np.empty_like(xf), np.empty((N, T, n, n)), np.zeros((N, T, n, n))
        xs[:, -1], Ps[:, -1] = xf[:, -1], Pf[:, -1]
        k_first = int(res.times[0])
        for i in range(T - 2, -1, -1):
            k = k_first + i  # row i holds x_k; x_{k+1} = f(x_k, k, u_{k+1}) + w_k, u_{k+1} in row i + 1
            C = self._cross_cov(k, xf[:, i], Pf[:, i], None if u2 is None else u2[:, i + 1])
            G = np.linalg.solve(Pp[:, i + 1], C.swapaxes(-1, -2)).swapaxes(-1, -2)  # C P̄^{-1}, P̄ symmetric
            xs[:, i] = xf[:, i] + np.einsum("rij,rj->ri", G, xs[:, i + 1] - xp[:, i + 1])
            Ps[:, i] = symmetrize(Pf[:, i] + G @ (Ps[:, i + 1] - Pp[:, i + 1]) @ G.swapaxes(-1, -2))
            gain[:, i] = G
        shape_x, shape_P = batch + (T, n), batch + (T, n, n)
        return FilterResult(
            mean=xs.reshape(shape_x),
            cov=Ps.reshape(shape_P),
            pred_mean=None,
            pred_cov=None,
            extras={
                "filtered_mean": res.mean,
                "filtered_cov": res.cov,
                "gain": gain.reshape(shape_P),
            },
            times=res.times,
        )

    def _cross_cov(self, k: int, x: np.ndarray, P: np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
        r""":math:`\mathrm{Cov}(x_k, f(x_k, k, u_{k+1}))` (N, n, n) under :math:`N(x, P)`: extended or by the rule."""
        sys_ = self.system
        if self.rule is None:
            return P @ sys_.transition_jacobian(x, k, u).swapaxes(-1, -2)
        L = self.rule.unit(self.n)[0].shape[0]
        return _sigma_moments(self.rule, lambda z: sys_.transition_map(z, k, _per_point(u, L)), x, P)[1]


def _is_jitted(fn: Any) -> bool:
    """Whether ``fn`` is a numba-compiled function (None, an absent Jacobian, counts as one); numba is not imported
    for the question (a function cannot be compiled by numba before numba is imported)."""
    if fn is None:
        return True
    if "numba" not in sys.modules:
        return False
    from numba.extending import is_jitted

    return bool(is_jitted(fn))


def _form(est: Any) -> str:
    return "" if est.covariance_update == "standard" else f", covariance_update={est.covariance_update!r}"


def _masked(y: np.ndarray, expected: np.ndarray):
    """The innovation with missing readings set to 0 and the mask of the readings present."""
    valid = ~np.isnan(y)
    return np.where(valid, y - expected, 0.0), (None if valid.all() else valid)


def _full(P: np.ndarray, N: int) -> np.ndarray:
    return P if P.shape[0] == N else np.broadcast_to(P, (N,) + P.shape[1:]).copy()


# --------------------------------------------------------------------------- the uncensored baselines


class _KalmanUpdate:
    def _update_arrays(self, k, xp, Pp, Sp, y, u, carry, options):
        R = self._noise(k)
        if Sp is not None:  # the array form on the linearisation: noise Ω + R with the factor of both
            yhat, H, E, wc = self._measurement_factor(k, xp, Sp, u)
            innov, valid = _masked(y, yhat)
            Rroot = psd_sqrt(R)
            if E is None:
                noise, root = R[None], Rroot[None]
            else:
                root = _weighted_factor(E, wc, Rroot)
                noise = root @ np.swapaxes(root, -1, -2)
            x, P, S, _ = sqrt_update(xp, Sp, innov, H, noise, valid, R_root=root)
            return x, P, S, carry, None
        yhat, Pxy, Pyy, H = self._measurement_moments(k, xp, Pp, u)
        innov, valid = _masked(y, yhat)
        if self.covariance_update == "joseph":
            x, P, _ = gain_update(xp, Pp, innov, Pxy, Pyy + R, valid, H=H, noise=R[None])
        else:
            x, P, _ = gain_update(xp, Pp, innov, Pxy, Pyy + R, valid)
        return x, P, None, carry, None


class ExtendedKalmanFilter(_KalmanUpdate, _NonlinearFamily):
    r"""The extended Kalman filter of a :class:`~tobitkf.NonlinearSystem` (module docstring), the uncensored baseline.

    Prediction :math:`\bar x = f(\hat x)`, :math:`\bar P = F\hat PF^T + Q`; update with :math:`H = \partial h/\partial x`
    at :math:`\bar x`: :math:`K = \bar PH^T(H\bar PH^T + R)^{-1}`, :math:`\hat x = \bar x + K(y - h(\bar x))`.
    The Jacobians are the system's ``F``, ``H`` or central differences.

    Parameters
    ----------
    system : NonlinearSystem
    covariance_update : {"standard", "joseph", "square_root"}, default "standard"
        :math:`P = \bar P - K H\bar P`, or the Joseph form :math:`(I-KH)\bar P(I-KH)^T + KRK^T` (filterpy's), or
        the square-root (Cholesky) form: a factor :math:`S` with :math:`P = SS^T` carried through QR array
        steps (prediction :math:`[S^TF^T;\ Q^{1/2\,T}]`, update
        :func:`~tobitkf.filters.core.sqrt_update`), PSD by construction (a numerical device, equal to the
        standard form to rounding).

    Raises
    ------
    ValidationError
        ``system`` not a NonlinearSystem, an unknown option.

    Examples
    --------
    >>> import numpy as np, tobitkf as tk
    >>> sys = tk.NonlinearSystem(lambda x, k: x, lambda x, k: 2.0 * x, Q=[[0.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    >>> out = tk.ExtendedKalmanFilter(sys).filter([[2.0]])      # the Kalman filter of C = 2
    >>> round(float(out.mean[0, 0]), 12), round(float(out.cov[0, 0, 0]), 12)
    (0.8, 0.2)
    """

    _name = "ExtendedKalmanFilter"
    _forms: tuple[str, ...] = ("standard", "joseph", "square_root")

    def __init__(self, system: NonlinearSystem, *, covariance_update: str = "standard", backend: str = "auto"):
        self._setup(system, covariance_update, None, backend)

    def __repr__(self) -> str:
        return f"ExtendedKalmanFilter({self.system!r}, covariance_update={self.covariance_update!r})"


def _rule(rule: Any, alpha: float, beta: float, kappa: float, order: int) -> SigmaPoints:
    if isinstance(rule, SigmaPoints):
        return rule
    return SigmaPoints(rule, alpha=alpha, beta=beta, kappa=kappa, order=order)


class UnscentedKalmanFilter(_KalmanUpdate, _NonlinearFamily):
    r"""The sigma-point (unscented, cubature, Gauss–Hermite) Kalman filter of a :class:`~tobitkf.NonlinearSystem`.

    Prediction and measurement moments by the sigma-point ``rule`` (module docstring; the points of the
    measurement are redrawn from the prediction), update :math:`K = P_{xy}(P_{yy} + R)^{-1}`,
    :math:`\hat x = \bar x + K(y - \hat y)`, :math:`P = \bar P - KP_{xy}^T`. For a linear model every rule gives
    the Kalman filter (tested).

    Parameters
    ----------
    system : NonlinearSystem
    rule : {"unscented", "cubature", "gauss_hermite"} or SigmaPoints, default "unscented"
    alpha, beta, kappa : float, default 1, 2, 0
        The unscented rule's parameters (filterpy's ``MerweScaledSigmaPoints(n, alpha, beta, kappa)``).
    order : int, default 3
        Points per coordinate of the Gauss–Hermite rule.
    covariance_update : {"standard", "square_root"}, default "standard"
        ``"square_root"`` carries a factor :math:`S`, :math:`P = SS^T`, through QR array steps: the sigma
        points from S, the predicted factor from one QR of :math:`[\sqrt{w^c_i}(f(\chi_i) - \bar x)^T;\
        Q^{1/2\,T}]`, the update as the array form of the statistical linearisation
        (:math:`\mathcal H = P_{xy}^T\bar P^{-1}`, noise :math:`\Omega + R` factored from the residual rows).
        PSD by construction; equal to the standard form to rounding when that stays PSD (tested), and
        still PSD where the standard form's subtraction loses definiteness (very precise readings).

    Raises
    ------
    ValidationError
        ``system`` not a NonlinearSystem, an unknown rule or a bad parameter.
    """

    _name = "UnscentedKalmanFilter"

    def __init__(
        self,
        system: NonlinearSystem,
        *,
        rule: Any = "unscented",
        alpha: float = 1.0,
        beta: float = 2.0,
        kappa: float = 0.0,
        order: int = 3,
        covariance_update: str = "standard",
        backend: str = "auto",
    ):
        self._setup(system, covariance_update, _rule(rule, alpha, beta, kappa, order), backend)

    def __repr__(self) -> str:
        return f"UnscentedKalmanFilter({self.system!r}, rule={self.rule!r}{_form(self)})"


# --------------------------------------------------------------------------- the Tobit update


class _TobitUpdate(_ContractChecks):
    _who = "the Tobit extended/unscented Kalman filter"
    _compiled_code = 1

    def _tobit_setup(self, system: NonlinearSystem, channel: Any, noise_term: str | None) -> None:
        self.channel = _contract_channel(channel, "statistics", self._who)
        self.channel.check(system)
        censoring = isinstance(self.channel, Censoring)
        if noise_term is None:
            noise_term = "dissertation" if censoring else "total_variance"
        check_keywords({"noise_term": noise_term}, {"noise_term": NOISE_TERMS})
        if not censoring and noise_term != "total_variance":
            raise ValidationError(
                f"noise_term: {noise_term!r} is a noise term of censored readings; a {type(self.channel).__name__} "
                "reading's noise term is its variance ('total_variance')"
            )
        self.noise_term = noise_term
        self._eye = np.eye(system.m)
        self._sigma = None if system.R.varying else self._sigmas(system.measurement_cov(1), "R")

    def _sigmas(self, R: np.ndarray, name: str) -> np.ndarray:
        return diagonal_sigma(R, name, who=self._who, why="independent channels")

    def _update_arrays(self, k, xp, Pp, Sp, y, u, carry, options):
        if Sp is not None:  # the array form: H -> G H, noise G Ω G + diag(N), with the factor of the noise
            yhat, H, Eres, wc = self._measurement_factor(k, xp, Sp, u)
            E, g, V = self._tobit_statistics(k, yhat)
            Vroot = np.sqrt(np.maximum(V, 0.0))[:, :, None] * np.eye(self.m)
            root = Vroot if Eres is None else _weighted_factor(Eres * g[:, None, :], wc, Vroot)
            innov, valid = _masked(y, E)
            x, P, S, _ = sqrt_update(
                xp, Sp, innov, g[:, :, None] * H, root @ np.swapaxes(root, -1, -2), valid, R_root=root
            )
            return x, P, S, carry, {"expected_y": E, "slope": g}
        yhat, Pxy, Pyy, _ = self._measurement_moments(k, xp, Pp, u)
        E, g, V = self._tobit_statistics(k, yhat)
        Rxe = Pxy * g[:, None, :]
        Ree = g[:, :, None] * Pyy * g[:, None, :] + V[:, :, None] * np.eye(self.m)
        innov, valid = _masked(y, E)
        x, P, _ = gain_update(xp, Pp, innov, Rxe, Ree, valid)
        return x, P, None, carry, {"expected_y": E, "slope": g}

    def _tobit_statistics(self, k: int, yhat: np.ndarray):
        """The reading's mean E[y], slope g and noise term N at the predicted measurement ŷ (N, m) each."""
        sigma = self._sigma if self._sigma is not None else self._sigmas(cast(Any, self)._noise(k), f"R({k})")
        N, m = yhat.shape
        if isinstance(self.channel, Censoring):  # the Tobit Kalman filter's own statistics, with C = I on ŷ
            lo, hi = (np.broadcast_to(v, (m,)) for v in self.channel.limits(k))
            mp = tobit_measurement(yhat, self._eye, sigma, lo, hi, noise_term=self.noise_term)
            E, V = mp.expected, np.asarray(mp.noise)
            assert mp.scale is not None, "the Tobit measurement has a channel scale"
            g = mp.scale
        else:
            E, g, V = np.empty((N, m)), np.empty((N, m)), np.empty((N, m))
            for l in range(m):
                E[:, l], g[:, l], V[:, l] = self.channel.reading_statistics(
                    np.ascontiguousarray(yhat[:, l]), np.full(N, sigma[l]), k, l
                )
        return E, g, V


class TobitExtendedKalmanFilter(_TobitUpdate, _NonlinearFamily):
    r"""The Tobit extended Kalman filter (Arthur et al. 2018): the Tobit Kalman filter's update with
    :math:`C` replaced by the Jacobian :math:`H = \partial h/\partial x` at the prediction (module docstring).

    Parameters
    ----------
    system : NonlinearSystem
        The model; R diagonal with positive entries.
    channel : Channel
        A channel with ``reading_statistics`` (:class:`~tobitkf.Censoring`, :class:`~tobitkf.Quantizer`, ...).
    noise_term : {"dissertation", "total_variance", "exact_pv"}, optional
        The noise term of a censored reading, as :class:`~tobitkf.TobitKalmanFilter`'s (default there and here
        ``"dissertation"``, the truncated variance of the source); a channel other than
        :class:`~tobitkf.Censoring` has only its reading's variance, ``"total_variance"`` (the default for it).
    covariance_update : {"standard", "square_root"}, default "standard"
        ``"square_root"``: the update as the array form with :math:`H \to GH` and noise
        :math:`\mathrm{diag}(N)` (:func:`~tobitkf.filters.core.sqrt_update`), a factor carried throughout.

    Raises
    ------
    ValidationError
        ``system`` not a NonlinearSystem, a channel without ``reading_statistics``, R not diagonal or a
        variance not positive.

    Notes
    -----
    Extras: ``expected_y`` (..., T, m), the reading's mean :math:`E[y]` at the predicted measurement, and
    ``slope`` (..., T, m), :math:`g = \partial E[y]/\partial\mu` (for censoring the probability of an
    uncensored reading). Readings the channel cannot give are refused (its ``check_readings``).

    References
    ----------
    .. [1] R. Arthur, A. Attarian, F. Hamilton, H. Tran, "Nonlinear Kalman filtering with censored
       observations", Applied Mathematics and Computation 316 (2018) 155-166.
    """

    _name = "TobitExtendedKalmanFilter"

    def __init__(
        self,
        system: NonlinearSystem,
        channel: Any,
        *,
        noise_term: str | None = None,
        covariance_update: str = "standard",
        backend: str = "auto",
    ):
        self._setup(system, covariance_update, None, backend)
        self._tobit_setup(system, channel, noise_term)

    def __repr__(self) -> str:
        return (
            f"TobitExtendedKalmanFilter({self.system!r}, {self.channel!r}, noise_term={self.noise_term!r}{_form(self)})"
        )


class TobitUnscentedKalmanFilter(_TobitUpdate, _NonlinearFamily):
    r"""The Tobit update on the sigma-point measurement prediction: :class:`TobitExtendedKalmanFilter` with
    :math:`\bar PH^T` and :math:`H\bar PH^T` replaced by the statistical :math:`P_{xy}` and :math:`P_{yy}`
    (module docstring).

    Parameters
    ----------
    system : NonlinearSystem
        The model; R diagonal with positive entries.
    channel : Channel
        A channel with ``reading_statistics``.
    rule, alpha, beta, kappa, order
        The sigma-point rule, as :class:`UnscentedKalmanFilter`.
    noise_term : {"dissertation", "total_variance", "exact_pv"}, optional
        As :class:`TobitExtendedKalmanFilter`.
    covariance_update : {"standard", "square_root"}, default "standard"
        As :class:`UnscentedKalmanFilter`, with :math:`\mathcal H \to G\mathcal H` and noise
        :math:`G\Omega G + \mathrm{diag}(N)` in the array update.

    Raises
    ------
    ValidationError
        As :class:`TobitExtendedKalmanFilter`, and an unknown rule or a bad parameter.

    Notes
    -----
    Extras: ``expected_y`` (..., T, m), the reading's mean :math:`E[y]` at the predicted measurement, and
    ``slope`` (..., T, m), :math:`g = \partial E[y]/\partial\mu` (for censoring the probability of an
    uncensored reading). Readings the channel cannot give are refused (its ``check_readings``).
    """

    _name = "TobitUnscentedKalmanFilter"

    def __init__(
        self,
        system: NonlinearSystem,
        channel: Any,
        *,
        rule: Any = "unscented",
        alpha: float = 1.0,
        beta: float = 2.0,
        kappa: float = 0.0,
        order: int = 3,
        noise_term: str | None = None,
        covariance_update: str = "standard",
        backend: str = "auto",
    ):
        self._setup(system, covariance_update, _rule(rule, alpha, beta, kappa, order), backend)
        self._tobit_setup(system, channel, noise_term)

    def __repr__(self) -> str:
        return (
            f"TobitUnscentedKalmanFilter({self.system!r}, {self.channel!r}, rule={self.rule!r}, "
            f"noise_term={self.noise_term!r}{_form(self)})"
        )
