r"""The assumed-density filter of a nonlinear model read through any channel, and its smoothers.

:class:`NonlinearAssumedDensityFilter` shares the nonlinear family's predict, sigma-point rules and square-root
form with the extended and unscented filters (:mod:`tobitkf.filters.nonlinear`, whose module docstring states
the rules and the square-root form with their equations); this module holds what is its own: the channel-by-
channel statistical linearisation with the channel's exact moments of the latent reading, the iterated posterior
linearisation (``iterations``), the RTS and iterated posterior-linearisation smoothers, and the likelihood.
"""

from __future__ import annotations

from typing import Any, cast

import numpy as np

from .._linalg import psd_sqrt, symmetrize
from .._validation import ValidationError, check_int
from ..models.nonlinear import NonlinearSystem
from ._boundary import _noise_variances
from ._particle_models import channel_log_likelihood
from ._quadrature import project_posterior, quadrature_rule
from .adf_generic import _contract_channel, _ContractChecks
from .core import (
    _TINY,
    FilterResult,
    check_keywords,
    check_prior,
    gain_update,
    sqrt_update,
)
from .likelihood import filter_log_likelihood
from .nonlinear import (
    SigmaPoints,
    _add_retained,
    _form,
    _full,
    _linearisation,
    _NonlinearFamily,
    _per_point,
    _rule,
    _sigma_factor,
    _sigma_moments,
)

__all__ = ["NonlinearAssumedDensityFilter", "UPDATES"]

UPDATES = ("linearised", "quadrature")


class NonlinearAssumedDensityFilter(_ContractChecks, _NonlinearFamily):
    r"""The assumed-density filter of a :class:`~tobitkf.NonlinearSystem` read through any contract channel.

    Channel by channel, the measurement is linearised statistically with the sigma-point ``rule`` and the
    channel's exact moments of the latent reading (censored, at a saturation limit, within a quantizer's
    cell) give the posterior moments by the projection formula (module docstring); with
    ``iterations > 1`` the linearisation is redone about the current posterior (iterated posterior
    linearisation). For a linear ``h`` one iteration is the linear :class:`~tobitkf.AssumedDensityFilter`
    (tested), and its update the exact posterior moments of one channel from a Gaussian prior.

    Parameters
    ----------
    system : NonlinearSystem
        The model; R diagonal (the channels are updated in sequence), entries >= 0.
    channel : Channel
        A channel with ``region`` or ``reading_moments`` (:class:`~tobitkf.Censoring`,
        :class:`~tobitkf.Quantizer`, a channel of your own).
    rule : {"unscented", "cubature", "gauss_hermite"} or SigmaPoints, default "unscented"
        The rule of the prediction and of the statistical linearisation; parameters as
        :class:`UnscentedKalmanFilter` (``alpha``, ``beta``, ``kappa``, ``order``).
    iterations : int >= 1, optional
        Linearisations per channel and step (default 1); with ``update="quadrature"`` the quadratures per step
        (default 2: the first over the prediction, the second re-centred on the first one's posterior, below).
    covariance_update : {"standard", "square_root"}, default "standard"
        ``"square_root"``: a factor carried throughout, each channel's projection as the array form of its
        linearisation (noise :math:`\Omega + R_{ll}`) plus one QR for :math:`+KVK^T`; PSD by construction
        and equal to the standard form to rounding when that stays PSD. With ``update="quadrature"`` the
        posterior factor is :math:`SU^T`, U from one QR of the weighted node deviations (below).
    update : {"linearised", "quadrature"}, default "linearised"
        ``"linearised"``: the statistical linearisation above, channel by channel. ``"quadrature"``: the
        Gaussian projection of the exact posterior of the step's readings (not in the sources; below); the
        prediction stays the rule's.
    quadrature : None, int or SigmaPoints, optional
        The rule over x of ``update="quadrature"``: None, the tensor Gauss–Hermite rule of order
        :math:`p = \min(40, \lfloor 4096^{1/n}\rfloor)` (40 points for n <= 2, 16 for n = 3, 8 for n = 4, ...;
        refused above n = 12); an int p in [2, 40], the tensor rule of :math:`p^n` nodes; a
        :class:`~tobitkf.SigmaPoints` rule with weights >= 0 (``SigmaPoints("cubature")``, 2n nodes: cheap,
        exact only for moments of degree 3 of the integrand, so rough for a peaked likelihood).

    Raises
    ------
    ValidationError
        ``system`` not a NonlinearSystem, a channel without ``region``/``reading_moments``, a non-diagonal or
        negative R, an unknown rule or a bad parameter; with ``update="quadrature"``: a zero variance in R (the
        reading's likelihood needs noise), a rule with a negative weight,
        ``quadrature`` without it; when filtering, readings with zero likelihood at every node.

    Notes
    -----
    Extras: ``log_likelihood`` (..., T), :math:`\sum_l \log p(y_k(l))` under the first linearisation of each
    channel (the channel's third ``reading_moments`` output; 0 for a missing reading); with
    ``update="quadrature"`` the quadrature's evidence :math:`\log p(y_k)` below (0 for a step without a
    reading).

    **The quadrature update** (``update="quadrature"``). With the prediction :math:`x_k \sim N(\bar x, \bar P)`
    and the exact likelihood of the step's readings through the channel (R diagonal),

    .. math::

        p(y_k \mid x) = \prod_l p\big(y_{k,l} \mid y^*_{k,l} \sim N(h_l(x, k), R_{ll})\big)

    (the channel's ``reading_log_likelihood``: the normal density at :math:`h_l(x)` for a measured reading, the
    normal tail mass :math:`\Phi((c - h_l(x))/\sqrt{R_{ll}})` through ``log_ndtr`` for one censored at c, the
    mass of its interval for a quantizer; a missing reading contributes 1), the posterior
    :math:`p(x \mid y_k) \propto N(x; \bar x, \bar P)\,p(y_k \mid x)` is projected on a Gaussian by
    quadrature in the whitened coordinates of the prediction, :math:`x_i = \bar x + S\xi_i`,
    :math:`SS^T = \bar P` the Cholesky factor (the carried factor in the square-root form), nodes
    :math:`\xi_i` and weights :math:`w_i` of the rule ``quadrature`` for N(0, I):

    .. math::

        \log p(y_k) = \log\sum_i w_i\,p(y_k \mid x_i), \qquad
        \pi_i = w_i\,p(y_k \mid x_i)/p(y_k), \qquad
        \hat x = \bar x + S\mu, \quad P = SCS^T,

    :math:`\mu = \sum_i\pi_i\xi_i`, :math:`C = \sum_i\pi_i(\xi_i - \mu)(\xi_i - \mu)^T`, the weights
    :math:`\pi_i` by log-sum-exp (no underflow for a reading far in a tail). All channels of a step are taken
    together (the linearised update takes them in sequence), so the update is the projection of the exact
    one-step posterior to the rule's accuracy, whatever h; its ``log_likelihood`` is the evidence of that
    posterior, and :func:`tobitkf.fit` maximises it with ``update="quadrature"``. For a linear h and one
    channel it is the linearised update (the exact projection; tested to 1e-10 with 40 nodes). The rule
    must resolve the likelihood: when a reading is much more precise than the prediction (:math:`R_{ll}`
    small against the spread of :math:`h_l` under the prediction), few nodes fall where the likelihood
    lives and the projection is rough; raise the order. Cost per step and run: L nodes (:math:`p^n` for
    the tensor rule) evaluations of h and of the channel's likelihood of each reading, against the
    linearised update's 2n + 1 sigma points per channel: for n = 2 and the default 1600 nodes, about 100
    times the linearised update's evaluations. Runs on numpy (``backend="auto"`` falls back to it).

    Examples
    --------
    For a linear h it is the linear assumed-density filter:

    >>> import numpy as np, tobitkf as tk
    >>> cens = tk.Censoring(lower=0.0)
    >>> nl = tk.NonlinearSystem(lambda x, k: 0.9 * x, lambda x, k: x, Q=[[0.1]], R=[[0.5]], x0=[0.0], P0=[[1.0]])
    >>> lin = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.1]], R=[[0.5]], x0=[0.0], P0=[[1.0]])
    >>> y = np.array([[0.3], [0.0], [0.8]])
    >>> a = tk.NonlinearAssumedDensityFilter(nl, cens).filter(y).mean
    >>> b = tk.AssumedDensityFilter(lin, cens).filter(y).mean
    >>> bool(np.allclose(a, b, rtol=0, atol=1e-12))
    True

    References
    ----------
    .. [1] P. S. Maybeck, *Stochastic Models, Estimation and Control*, vol. 2, Academic Press, 1982, §12.7.
    .. [2] Á. F. García-Fernández, L. Svensson, M. R. Morelande, S. Särkkä, "Posterior linearization filter:
       principles and implementation using sigma points", IEEE Trans. Signal Processing 63(20), 2015.
    """

    _name = "NonlinearAssumedDensityFilter"
    _compiled_code = 2  # the channel-by-channel projection of the compiled loop

    def __init__(
        self,
        system: NonlinearSystem,
        channel: Any,
        *,
        rule: Any = "unscented",
        iterations: int | None = None,
        alpha: float = 1.0,
        beta: float = 2.0,
        kappa: float = 0.0,
        order: int = 3,
        covariance_update: str = "standard",
        update: str = "linearised",
        quadrature: Any = None,
        backend: str = "auto",
    ):
        self._setup(system, covariance_update, _rule(rule, alpha, beta, kappa, order), backend)
        check_keywords({"update": update}, {"update": UPDATES})
        if iterations is None:
            iterations = 2 if update == "quadrature" else 1
        self.iterations = check_int(iterations, "iterations", minimum=1, maximum=1000)
        self.update_method = update
        self._take_channel(system, channel)
        self._nodes: tuple[np.ndarray, np.ndarray, str] | None = None
        if update == "quadrature":
            own = [
                name
                for name in ("_take_channel", "_latent_moments", "_channel_moments")
                if getattr(type(self), name) is not getattr(NonlinearAssumedDensityFilter, name)
            ]
            if own:
                raise ValidationError(
                    f"update: {type(self).__name__} reads its channel through a model of its own; 'quadrature' "
                    "integrates a contract channel's reading likelihood (NonlinearAssumedDensityFilter)"
                )
            self._nodes = quadrature_rule(quadrature, self.n)
            if self._r is not None:
                _noise_variances(system.measurement_cov(1), "R", positive="the quadrature update")
        elif quadrature is not None:
            raise ValidationError("quadrature: an option of update='quadrature'")

    def _compiled_gap(self) -> str | None:
        if self.update_method == "quadrature":
            return "the quadrature update (it runs on numpy)"
        return super()._compiled_gap()

    def _take_channel(self, system: NonlinearSystem, channel: Any) -> None:
        """Check and keep ``channel`` (``self.channel``) and the constant noise variances ``self._r`` (m,) (None
        for an R given per step): the one part of the set-up a channel family of this filter replaces."""
        self.channel = _contract_channel(channel, "moments", "the nonlinear assumed-density filter")
        self.channel.check(system)
        self._r = None if system.R.varying else _noise_variances(system.measurement_cov(1), "R")

    def _update_arrays(self, k, xp, Pp, Sp, y, u, carry, options):
        N = xp.shape[0]
        r = self._r if self._r is not None else _noise_variances(self._noise(k), f"R({k})")
        if self._nodes is not None:
            return self._quadrature_update(k, xp, Pp, Sp, y, u, r, carry)
        ll = np.zeros(N)
        if Sp is not None:
            x, S = xp, _full(Sp, N)
            for l in range(self.m):
                x, S, lll = self._channel_sqrt(k, l, x, S, y[:, l], r[l], u)
                ll += lll
            return x, symmetrize(S @ np.swapaxes(S, -1, -2)), S, carry, {"log_likelihood": ll}
        x, P = xp, _full(Pp, N)
        for l in range(self.m):
            x, P, lll = self._channel(k, l, x, P, y[:, l], r[l], u)
            ll += lll
        return x, P, None, carry, {"log_likelihood": ll}

    def _quadrature_update(self, k, xp, Pp, Sp, y, u, r, carry):
        r"""The projection of the exact posterior of the step's readings (class docstring) for the runs with a
        reading; the others keep the prediction."""
        assert self._nodes is not None
        if np.any(r <= 0):
            _noise_variances(self._noise(k), f"R({k})", positive="the quadrature update")
        N, n = xp.shape
        xi, logw, _ = self._nodes
        ll = np.zeros(N)
        S = _full(Sp if Sp is not None else psd_sqrt(Pp), N)
        x, P = xp.copy(), _full(Pp, N).copy()
        Sn = S.copy() if Sp is not None else None
        rows = np.flatnonzero(~np.isnan(y).all(axis=1))
        if rows.size:
            sd = np.sqrt(r)
            L = xi.shape[0]
            uL = None if u is None else np.repeat(u[rows], L, axis=0)
            sys_, yr = self.system, y[rows]

            def loglik(X: np.ndarray) -> np.ndarray:
                mu = sys_.measurement_map(X.reshape(-1, n), k, uL).reshape(rows.size, L, -1)
                return channel_log_likelihood(self.channel, k, yr, mu, sd)

            x[rows], P[rows], F, ll[rows] = project_posterior(
                xp[rows],
                S[rows],
                loglik,
                xi,
                logw,
                passes=self.iterations,
                factor=Sn is not None,
                runs=rows,
            )
            if Sn is not None:
                Sn[rows] = F
        return x, P, Sn, carry, {"log_likelihood": ll}

    def _channel_sqrt(
        self, k: int, l: int, x: np.ndarray, S: np.ndarray, y: np.ndarray, r: float, u: np.ndarray | None = None
    ):
        r"""The square-root form of :meth:`_channel`: the linearisation :math:`\mathcal H, \Omega` from the factor
        (:func:`_linearisation`), the Kalman part :math:`\bar P - K s^2K^T` by the array form
        (:func:`~tobitkf.filters.core.sqrt_update`, noise :math:`\Omega + R_{ll}`) and :math:`+KVK^T` by one more
        QR, so the factor stays PSD by construction."""
        rule, h_l, has, ll = self._channel_setup(k, l, y, u)
        if not has.any():
            return x, S, ll
        xm, Sm = x, S
        for it in range(self.iterations):
            ybar, dY, xi, wc = _sigma_factor(rule, h_l, xm, Sm)
            _, Hl, Eres = _linearisation(Sm, dY, xi, wc)
            omega = np.einsum("l,rl->r", wc, Eres[:, :, 0] ** 2)
            # about the prior (it == 0) the affine model reproduces the moments; later ones apply it to the prior
            mu = ybar[:, 0] + (0.0 if it == 0 else np.einsum("ri,ri->r", Hl[:, 0], x - xm))
            HS = np.einsum("ri,rij->rj", Hl[:, 0], S)
            s2 = np.einsum("rj,rj->r", HS, HS) + np.maximum(omega, 0.0) + r
            ok, obs, V = self._latent_moments(k, l, y, has, mu, s2, ll if it == 0 else None)
            if not ok.any():
                return x, S, ll
            noise = (np.maximum(omega, 0.0) + r)[:, None, None]
            xm, _, Sm, K = sqrt_update(x, S, (obs - mu)[:, None], Hl, noise, ok[:, None], R_root=np.sqrt(noise))
            Sm = _add_retained(Sm, K, V[:, None])
        return xm, Sm, ll

    def smooth(self, y: Any, *, u: Any = None, x0: Any = None, P0: Any = None, iterations: int = 1) -> FilterResult:
        r"""Fixed-interval smoother of ``y`` (..., T, m); with ``iterations > 1`` the iterated posterior-linearisation
        smoother (IPLS; García-Fernández, Svensson & Särkkä 2017).

        ``iterations=1``: the sigma-point RTS smoother over this filter's moments (as the other nonlinear
        filters' :meth:`~_NonlinearFamily.smooth`). Each further iteration re-linearises the model about the
        smoothed posterior of the previous one and smooths the linearised model exactly as the filter
        treats a linear one: with the rule's statistical linear regression of a map g about
        :math:`N(\hat x_{k|T}, P_{k|T})`,

        .. math::

            \mathcal A = \mathrm{Cov}(g(x), x)P_{k|T}^{-1}, \quad a = E[g(x)] - \mathcal A\hat x_{k|T}, \quad
            \Lambda = \mathrm{Cov}(g(x)) - \mathcal AP_{k|T}\mathcal A^T,

        the transition :math:`x_{k+1} = \mathcal A_kx_k + a_k + w_k`, :math:`w_k \sim N(0, Q_k + \Lambda_k)`
        (g = f about :math:`x_{k|T}`, k = 0..T-1, the prior :math:`x_0` included) and, channel by channel, the
        latent reading :math:`y^*_{k,l} = \mathcal H_{k,l}x_k + b_{k,l} + e`, :math:`e \sim N(0, \Omega_{k,l} +
        R_{k,ll})` (g = h_l about :math:`x_{k|T}`); the forward pass is this filter's projection with those
        moments (the channel's exact moments of each reading), the backward pass the RTS pass with
        :math:`\mathcal A_k` (:func:`~tobitkf.filters.smoothing.rts_smooth`). For a linear model every
        linearisation is the model itself, so every iteration gives the one-pass smoother (tested).

        Parameters
        ----------
        y : (..., T, m) array_like
            Readings; NaN = missing.
        u : (..., T, p) array_like, optional
            Inputs of an ``f(x, k, u)``.
        x0, P0 : array_like, optional
            Override the prior.
        iterations : int >= 1, default 1
            Passes of the smoother (1: no re-linearisation).

        Returns
        -------
        FilterResult
            ``mean`` :math:`\hat x_{k|T}` (..., T, n), ``cov`` (..., T, n, n), ``extras`` ``filtered_mean``,
            ``filtered_cov``, ``gain`` (of the last pass) and, with ``iterations > 1``, ``initial_mean`` /
            ``initial_cov`` (:math:`\hat x_{0|T}`, :math:`P_{0|T}`) and ``cross_cov``.

        Raises
        ------
        ValidationError, ShapeError
            As :meth:`filter`; ``iterations`` not an integer in [1, 1000].

        References
        ----------
        .. [1] Á. F. García-Fernández, L. Svensson, S. Särkkä, "Iterated posterior linearization smoother",
           IEEE Trans. Automatic Control 62(4), 2017, 2056-2063.
        """
        iterations = check_int(iterations, "iterations", minimum=1, maximum=1000)
        if iterations == 1:
            return super().smooth(y, u=u, x0=x0, P0=P0)
        if self.update_method == "quadrature":
            raise ValidationError(
                "iterations: the iterated posterior-linearisation smoother linearises the readings; with "
                "update='quadrature' smooth with iterations=1 (the RTS smoother over the filter's moments)"
            )
        from .smoothing import rts_smooth

        y2, batch = self._prepare_record(y)
        N, T, _ = y2.shape
        xa, Pa = check_prior(self.system, x0, P0, N, batch)
        u2 = self._prepare_inputs(u, N, T, batch)
        self._check_record(y2, u2, 0)
        res = self.filter(y2, u=u2, x0=xa, P0=Pa)
        assert res.mean is not None and res.cov is not None
        xf = np.concatenate([xa[:, None], res.mean], axis=1)  # rows k = 0..T
        Pf = np.concatenate([Pa[:, None], np.broadcast_to(res.cov, (N, T) + Pa.shape[1:])], axis=1)
        trans = self._linearise_f(xf, Pf, u2)[0]  # pass 1: about the filtered densities (the RTS smoother)
        sm = rts_smooth(res, lambda k: trans[:, k], x0=xa, P0=Pa)
        for _ in range(iterations - 1):
            assert sm.mean is not None and sm.cov is not None
            xs = np.concatenate([sm.extras["initial_mean"][:, None], sm.mean], axis=1)
            Ps = np.concatenate([sm.extras["initial_cov"][:, None], np.broadcast_to(sm.cov, (N, T) + Pa.shape[1:])], 1)
            lin_f = self._linearise_f(xs, Ps, u2)
            res = self._linearised_pass(y2, u2, xa, Pa, lin_f, xs, Ps)
            trans = lin_f[0]
            sm = rts_smooth(res, lambda k: trans[:, k], x0=xa, P0=Pa)
        return _unflatten(sm, batch)

    def _linearise_f(self, xs: np.ndarray, Ps: np.ndarray, u2: np.ndarray | None):
        """The statistical linear regressions ``(A, a, Λ)`` ((N, T, n, n), (N, T, n), (N, T, n, n)) of f(·, k, u_{k+1})
        about N(xs[:, k], Ps[:, k]), k = 0..T-1."""
        sys_ = cast(NonlinearSystem, self.system)
        rule = self.rule
        assert rule is not None
        N, T1, n = xs.shape
        A, a, Lam = np.empty((N, T1 - 1, n, n)), np.empty((N, T1 - 1, n)), np.empty((N, T1 - 1, n, n))
        L = rule.unit(n)[0].shape[0]
        for k in range(T1 - 1):
            uk = None if u2 is None else u2[:, k]
            A[:, k], a[:, k], Lam[:, k] = _slr(
                rule, lambda z: sys_.transition_map(z, k, _per_point(uk, L)), xs[:, k], Ps[:, k]
            )
        return A, a, Lam

    def _linearised_pass(self, y2, u2, xa, Pa, lin_f, xs, Ps) -> FilterResult:
        """The forward pass of the model linearised about the smoothed ``xs``, ``Ps`` (rows k = 0..T): the
        filtered and predicted moments as a flat (N, T, ...) :class:`~tobitkf.FilterResult`."""
        sys_ = cast(NonlinearSystem, self.system)
        rule = self.rule
        assert rule is not None
        A, a, Lam = lin_f
        N, T, m = y2.shape
        n = self.n
        out = {key: np.empty((N, T, n)) for key in ("mean", "pred_mean")}
        out.update({key: np.empty((N, T, n, n)) for key in ("cov", "pred_cov")})
        x, P = xa, Pa
        for i in range(T):
            k = i + 1
            x = np.einsum("rij,rj->ri", A[:, i], x) + a[:, i]
            P = symmetrize(A[:, i] @ P @ A[:, i].swapaxes(-1, -2) + Lam[:, i] + sys_.process_cov(k - 1))
            out["pred_mean"][:, i], out["pred_cov"][:, i] = x, P
            r = self._r if self._r is not None else _noise_variances(self._noise(k), f"R({k})")
            uk = None if u2 is None else u2[:, i]  # u_k, the input of the reading y_k (row k - 1)
            for l in range(m):
                Hl, bl, om = _slr(rule, self._h_points(k, uk, l), xs[:, k], Ps[:, k])
                H1 = Hl[:, 0]  # (N, n)
                cxy = np.einsum("rij,rj->ri", P, H1)
                mu = np.einsum("ri,ri->r", H1, x) + bl[:, 0]
                s2 = np.einsum("ri,ri->r", H1, cxy) + np.maximum(om[:, 0, 0], 0.0) + r[l]
                yl = y2[:, i, l]
                post = self._project(k, l, x, P, yl, ~np.isnan(yl), mu, cxy, s2, None)
                if post is not None:
                    x, P = post
            out["mean"][:, i], out["cov"][:, i] = x, P
        return FilterResult(
            mean=out["mean"],
            cov=out["cov"],
            pred_mean=out["pred_mean"],
            pred_cov=out["pred_cov"],
            extras={},
            times=np.arange(1, T + 1),
        )

    def log_likelihood(
        self, y: Any, *, u: Any = None, x0: Any = None, P0: Any = None, per_step: bool = False
    ) -> np.ndarray:
        r"""The assumed-density log-likelihood :math:`\sum_k \ell_k` of ``y`` (..., T, m): (...), or the terms
        (..., T) with ``per_step`` (the ``log_likelihood`` extras of :meth:`filter`; for a linear h the linear
        :class:`~tobitkf.AssumedDensityFilter`'s); ``u`` the inputs of an ``f(x, k, u)``. Maximised over the
        parameters of f and h by :func:`tobitkf.fit` with a map ``theta -> NonlinearSystem``.

        Raises
        ------
        ValidationError, ShapeError
            As :meth:`filter`.
        """
        return filter_log_likelihood(self, y, per_step=per_step, u=u, x0=x0, P0=P0)

    def _channel(
        self, k: int, l: int, x: np.ndarray, P: np.ndarray, y: np.ndarray, r: float, u: np.ndarray | None = None
    ):
        """The projection of channel ``l``, iterated about the posterior: ``(x, P, log p(y))``."""
        rule, h_l, has, ll = self._channel_setup(k, l, y, u)
        if not has.any():
            return x, P, ll
        xm, Pm = x, P
        for it in range(self.iterations):
            ybar, Pxy, Pyy = self._channel_moments(l, rule, h_l, xm, Pm)
            if it == 0:  # linearised about the prior itself: the moments as they are
                mu, cxy, s2 = ybar[:, 0], Pxy[:, :, 0], Pyy[:, 0, 0] + r
            else:  # the affine model fitted about the posterior, applied to the prior
                Hl = _regress(Pm, Pxy[:, :, 0])  # (N, n)
                omega = np.maximum(Pyy[:, 0, 0] - np.einsum("ri,rij,rj->r", Hl, Pm, Hl), 0.0)
                mu = ybar[:, 0] + np.einsum("ri,ri->r", Hl, x - xm)
                cxy = np.einsum("rij,rj->ri", P, Hl)
                s2 = np.einsum("ri,ri->r", Hl, cxy) + omega + r
            post = self._project(k, l, x, P, y, has, mu, cxy, s2, ll if it == 0 else None)
            if post is None:
                return x, P, ll
            xm, Pm = post
        return xm, Pm, ll

    def _channel_moments(self, l: int, rule: SigmaPoints, h_l: Any, xm: np.ndarray, Pm: np.ndarray):
        """``(ȳ, P_xy, P_yy)`` ((N, 1), (N, n, 1), (N, 1, 1)) of channel ``l``'s measurement map ``h_l`` under
        :math:`N(x_m, P_m)` by the rule (a family reading another function of h, as a faded one, changes them)."""
        return _sigma_moments(rule, h_l, xm, Pm)

    def _project(self, k, l, x, P, y, has, mu, cxy, s2, ll):
        r"""The projection of channel ``l`` under the affine model :math:`y^*_l \sim N(\mu, s^2)`, covariance
        ``cxy`` with x: :math:`\hat x = x + K(E[y^* \mid y] - \mu)`, :math:`P = P - K(s^2 - V)K^T`,
        :math:`K = c_{xy}/s^2`; None when no run takes part."""
        ok, obs, V = self._latent_moments(k, l, y, has, mu, s2, ll)
        if not ok.any():
            return None
        xm, Pm, K = gain_update(x, P, (obs - mu)[:, None], cxy[:, :, None], s2[:, None, None], ok[:, None])
        return xm, symmetrize(Pm + (K * V[:, None, None]) @ K.swapaxes(-1, -2))

    def _channel_setup(self, k: int, l: int, y: np.ndarray, u: np.ndarray | None = None):
        """``(rule, h_l, has, ll)``: the rule, channel ``l``'s measurement map of the points (N L, n) -> (N L, 1)
        (with the input ``u`` (N, p) of each run), the runs with a reading and zeroed log-likelihood terms."""
        rule = self.rule
        assert rule is not None, "the assumed-density filter linearises with sigma points"
        return rule, self._h_points(k, u, l), ~np.isnan(y), np.zeros(y.shape[0])

    def _latent_moments(self, k, l, y, has, mu, s2, ll):
        r"""The channel's moments of the latent reading :math:`y^* \sim N(\mu, s^2)` given ``y`` (N,): ``(ok, E[y^*
        | y], Var[y^* | y])`` with ``ok`` the runs that take part (a reading, :math:`s^2` normal); the log-density
        of each reading is written into ``ll`` when it is given."""
        ok = has & (s2 > _TINY)
        obs, V = np.array(mu), np.zeros(mu.shape[0])
        if ok.any():
            s = np.sqrt(np.where(ok, s2, 1.0))
            obs[ok], V[ok], lp = self.channel.reading_moments(y[ok], mu[ok], s[ok], k, l)
            if ll is not None:
                ll[ok] = lp
        return ok, obs, V

    def _iterations_repr(self) -> str:
        it = "" if self.iterations == 1 else f", iterations={self.iterations}"
        if self._nodes is not None:
            it += f", update='quadrature', quadrature={self._nodes[2]}"
        return it

    def __repr__(self) -> str:
        head = f"{self._name}({self.system!r}, {self.channel!r}, rule={self.rule!r}"
        return f"{head}{self._iterations_repr()}{_form(self)})"


def _slr(rule: SigmaPoints, fun, x: np.ndarray, P: np.ndarray):
    r"""The statistical linear regression of :math:`g(x)`, :math:`x \sim N(x, P)`, by the rule:
    ``(A, b, Λ)`` (N, r, n), (N, r), (N, r, r) with :math:`A = P_{xg}^TP^{-1}` (the pseudo-inverse when P is
    singular), :math:`b = \bar g - Ax`, :math:`\Lambda = P_{gg} - APA^T` (its negative rounding kept out)."""
    from .smoothing import solve_psd

    ym, Pxy, Pyy = _sigma_moments(rule, fun, x, P)
    A = np.swapaxes(solve_psd(P, Pxy), -1, -2)
    b = ym - np.einsum("rij,rj->ri", A, x)
    Lam = symmetrize(Pyy - A @ P @ np.swapaxes(A, -1, -2))
    w, V = np.linalg.eigh(Lam)
    return A, b, (V * np.maximum(w, 0.0)[..., None, :]) @ np.swapaxes(V, -1, -2)


def _unflatten(res: FilterResult, batch: tuple[int, ...]) -> FilterResult:
    """A flat (N, T, ...) result laid out over the leading axes ``batch``."""

    def lay(v: Any) -> Any:
        return v.reshape(batch + v.shape[1:]) if isinstance(v, np.ndarray) and v.ndim >= 1 else v

    return FilterResult(
        mean=lay(res.mean),
        cov=lay(res.cov),
        pred_mean=lay(res.pred_mean),
        pred_cov=lay(res.pred_cov),
        extras={key: lay(v) for key, v in res.extras.items()},
        times=res.times,
    )


def _regress(P: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The rows :math:`P^{-1}c` (N, n) of the statistical linearisation; a least-squares solve when P is singular
    (a noiseless reading collapsed a direction)."""
    try:
        return np.linalg.solve(P, c[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:
        return np.einsum("rij,rj->ri", np.linalg.pinv(P, hermitian=True), c)
