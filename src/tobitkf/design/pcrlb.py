r"""Posterior Cramér–Rao lower bound (PCRLB) for censored and fading readings.

Not in the sources. For any estimator :math:`\hat x_k(y_{1:k})` of the state of a model whose
prior, dynamics and readings are the ones the truth is drawn from, the MSE matrix is bounded below
by the inverse of the Bayesian information :math:`J_k` (van Trees 1968; Tichavský, Muravchik &
Nehorai 1998, (21)):

.. math::

    E[(\hat x_k - x_k)(\hat x_k - x_k)^T] \succeq B_k = J_k^{-1}, \qquad
    J_{k} = D^{22}_{k-1} - D^{21}_{k-1}(J_{k-1} + D^{11}_{k-1})^{-1}D^{12}_{k-1}.

For linear Gaussian dynamics :math:`x_k = A_{k-1}x_{k-1} + w_{k-1}`, :math:`w \sim N(0, Q_d)`,
:math:`D^{11} = A^TQ_d^{-1}A`, :math:`D^{12} = -A^TQ_d^{-1}`, :math:`D^{22} = Q_d^{-1} + E[J_z(x_k)]`,
and the recursion is, by the matrix-inversion lemma, the Kalman-like

.. math::

    \bar B_k = A_{k-1}B_{k-1}A_{k-1}^T + Q_{d,k-1}, \qquad
    B_k = (\bar B_k^{-1} + E[J_z(x_k)])^{-1} = \bar B_k(I + E[J_z]\bar B_k)^{-1}, \qquad B_0 = P_0

(the last form needs neither :math:`Q_d` nor :math:`\bar B_k` invertible, so augmented states with
deterministic blocks are fine). :math:`J_z(x) = E[-\nabla^2_x\log p(y_k\mid x)\mid x]` is the Fisher
information of one reading, averaged over the state by Monte Carlo over true trajectories.

Fisher information of a censored normal reading :math:`y = \mathrm{clip}(y^*, l, h)`,
:math:`y^* \sim N(\mu, \sigma^2)`, in the parameters :math:`(\mu, \sigma)`, with
:math:`a = (l-\mu)/\sigma`, :math:`b = (h-\mu)/\sigma`, :math:`\Delta = \Phi(b) - \Phi(a)`,
:math:`T_a = \phi(a)^2/\Phi(a)`, :math:`T_b = \phi(b)^2/\Phi(-b)` and
:math:`I_2 = \int_a^b z^2\phi = \Delta + a\phi(a) - b\phi(b)` (the censored masses' scores are
:math:`\mp\phi/(\sigma\Phi)` and :math:`\mp a\phi/(\sigma\Phi)`; the interior's :math:`z/\sigma`,
:math:`(z^2-1)/\sigma`):

.. math::

    \sigma^2 I_{\mu\mu} &= T_a + I_2 + T_b \\
    \sigma^2 I_{\mu\sigma} &= aT_a + (a^2+1)\phi(a) - (b^2+1)\phi(b) + bT_b \\
    \sigma^2 I_{\sigma\sigma} &= a^2T_a + a^3\phi(a) - b^3\phi(b) + I_2 + \Delta + b^2T_b

(no censoring: :math:`1/\sigma^2`, 0, :math:`2/\sigma^2`). Through the chain rule,
:math:`J_z = I_{\mu\mu}\nabla\mu\nabla\mu^T + I_{\mu\sigma}(\nabla\mu\nabla\sigma^T + \nabla\sigma\nabla\mu^T)
+ I_{\sigma\sigma}\nabla\sigma\nabla\sigma^T`, summed over channels (diagonal R):

* censored linear readings :math:`\mu = C_k(l)x + D_k(l)u`, :math:`\sigma = \sqrt{R_{ll}}`:
  :math:`\nabla\mu = C_k(l)^T`, :math:`\nabla\sigma = 0`;
* Rice fading with Gaussian coefficients (on the augmented state of (7)–(10) of Geng et al. 2017):
  given :math:`\xi_k` the latent reading is normal with :math:`\mu = H_l\xi_k`,
  :math:`\sigma^2 = \sum_s\tilde\vartheta(s)_l(C_{k-s}(l)x_{k-s})^2 + R_{ll}`, so
  :math:`\nabla\mu = H_l^T` and :math:`\nabla\sigma` has block s equal to
  :math:`\tilde\vartheta(s)_l(C_{k-s}(l)x_{k-s})C_{k-s}(l)^T/\sigma`.

Tail safety: :math:`T_a`, :math:`T_b` through ``log_ndtr`` (finite 40 σ and more into either tail).
Time convention: row k-1 of the result bounds the MSE of :math:`\hat x_{k|k}` (k = 1..T).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.special import ndtr, ndtri

from .._linalg import symmetrize
from .._validation import ShapeError, ValidationError, as_float_array, check_count, check_instance
from ..censored import censored_fisher_information
from ..channels.base import Channel
from ..channels.censoring import Censoring
from ..channels.fading import RiceFading, measurement_matrix_at
from ..channels.laws import Gaussian
from ..models.linear import LinearSystem

__all__ = ["censored_fisher_information", "posterior_crlb", "PosteriorCRLB", "bound_test"]


@dataclass(frozen=True)
class PosteriorCRLB:
    """The bound of :func:`posterior_crlb`.

    Attributes
    ----------
    bound : (T, n, n) ndarray
        :math:`B_k` for the reported state, k = 1..T (row k-1).
    var : (T, n) ndarray
        Its diagonal: lower bounds on the MSE of each component.
    aug_bound : (T, n_x, n_x) ndarray
        The bound of the whole (augmented) state.
    information : (T, n_x, n_x) ndarray
        :math:`E[J_z(x_k)]`, the Monte Carlo average of the readings' Fisher information.
    times : (T,) ndarray
        1..T.
    """

    bound: np.ndarray
    var: np.ndarray
    aug_bound: np.ndarray
    information: np.ndarray
    times: np.ndarray


def _split(channel: Any, censoring: Any):
    """The reading's channel (a channel of the contract that gives its reading's Fisher information, the
    :class:`Censoring` among them; an uncensored one when none is given) and the Rice fading (or None)."""
    pieces = [] if channel is None else (list(channel) if isinstance(channel, (list, tuple)) else [channel])
    if censoring is not None:
        pieces.append(censoring)
    fad = [p for p in pieces if isinstance(p, RiceFading)]
    cens = [p for p in pieces if isinstance(p, Censoring)]
    other = [p for p in pieces if not isinstance(p, (Censoring, RiceFading))]
    fisher = [p for p in other if isinstance(p, Channel) and p.supports("fisher")]
    if len(fad) > 1 or len(cens) > 1 or len(other) != len(fisher) or len(fisher) + len(cens) > 1 or (fad and fisher):
        names = ", ".join(type(p).__name__ for p in pieces)
        raise ValidationError(
            f"channel: the PCRLB covers censored linear readings and Rice fading (at most one "
            f"Censoring and one RiceFading), and channels that give their reading's Fisher information "
            f"(fisher_information, tobitkf.channels.base), got {names}"
        )
    reading = (fisher or cens or [Censoring()])[0]
    return reading, (fad[0] if fad else None)


def _sigmas(system: LinearSystem, k: int) -> np.ndarray:
    R = system.measurement_cov(k)
    off = R - np.diag(np.diagonal(R))
    if np.abs(off).max(initial=0.0) > 1e-12 * max(1.0, np.abs(R).max()) or np.any(np.diagonal(R) <= 0):
        raise ValidationError("R: the PCRLB needs a diagonal R with positive entries (independent channels)")
    return np.sqrt(np.diagonal(R))


def posterior_crlb(
    system: LinearSystem,
    channel: Any = None,
    *,
    censoring: Censoring | None = None,
    truth: Any = None,
    steps: int | None = None,
    runs: int = 2000,
    seed: Any = 0,
) -> PosteriorCRLB:
    r"""Posterior Cramér–Rao bound (Tichavský–Muravchik–Nehorai recursion) for censored or fading readings.

    Parameters
    ----------
    system : LinearSystem
        The model the truth is drawn from (its prior :math:`N(\bar x_0, P_0)` is :math:`B_0`);
        diagonal, positive R.
    channel : Censoring or RiceFading or a sequence of both, or a Channel, optional
        The readings' channel (fading coefficients must be Gaussian); or one channel that gives the Fisher
        information of its reading (``fisher_information``: :class:`~tobitkf.Quantizer`, a channel of your
        own; then :math:`J_z = C_k^T\mathrm{diag}(E[I_{\mu\mu}])C_k`); None: linear readings.
    censoring : Censoring, optional
        The censoring, given separately.
    truth : (N, T+1, n) array_like, optional
        True trajectories :math:`x_0..x_T` to average the Fisher information over (e.g. the ``x`` of
        the simulation the estimators ran on). Default: ``runs`` trajectories drawn from the model.
    steps : int, optional
        Horizon T when ``truth`` is not given.
    runs : int, default 2000
        Trajectories drawn when ``truth`` is not given.
    seed : int, SeedSequence or Generator, default 0
        For the drawn trajectories.

    Returns
    -------
    PosteriorCRLB
        ``bound`` (T, n, n), ``var`` (T, n), the augmented bound and the averaged information.

    Raises
    ------
    ValidationError
        An unsupported channel (protocol, saturation), non-Gaussian fading coefficients, a
        non-diagonal R, neither ``truth`` nor ``steps``.
    ShapeError
        ``truth`` not of shape (N, T+1, n).

    Notes
    -----
    The bound holds for the MSE averaged over the joint law of truth and readings, so compare it
    with the MSE over Monte Carlo runs whose truth is drawn from the same prior (not with a fixed
    truth). Without censoring and fading it is the Kalman filter's covariance (tested).

    Examples
    --------
    >>> import numpy as np, tobitkf as tk
    >>> sys = tk.LinearSystem(A=[[0.95]], C=[[1.0]], Q=[[0.1]], R=[[0.5]], x0=[0.0], P0=[[1.0]])
    >>> b = tk.posterior_crlb(sys, steps=20)
    >>> kf = tk.KalmanFilter(sys).filter(np.zeros((20, 1)))
    >>> bool(np.allclose(b.bound, kf.cov, rtol=1e-12, atol=0))
    True
    >>> c = tk.posterior_crlb(sys, tk.Censoring(lower=0.0), steps=20, runs=500)
    >>> bool((c.var >= b.var).all())                   # censoring loses information
    True
    """
    check_instance(system, LinearSystem, "system")
    cens, fad = _split(channel, censoring)
    if fad is not None:
        fad.check(system.m)
        if not isinstance(fad.coefficients, Gaussian):
            raise ValidationError(
                "channel: the fading PCRLB needs Gaussian coefficients (the reading is then normal given the states)"
            )
    cens.check(system.m)
    if truth is None:
        if steps is None:
            raise ValidationError("steps: give the horizon T (or the true trajectories as truth)")
        T = check_count(steps, "steps")
        from ..simulate.core import simulate

        X = simulate(system, T, check_count(runs, "runs"), seed=seed).x
    else:
        X = as_float_array(truth, "truth", ndim=3)
        if X.shape[-1] != system.n or X.shape[1] < 2:
            raise ShapeError(f"truth: expected (N, T+1, {system.n}) trajectories x_0..x_T, got {X.shape}")
        T = X.shape[1] - 1
    system.check_horizon(T)
    n, m = system.n, system.m
    L = fad.order if fad is not None else 0
    nx = n * (L + 1)
    if fad is not None:
        mg, vg = fad.mean_gains(m), fad.var_gains(m)
    B = np.zeros((nx, nx))
    B[:n, :n] = system.P0
    bounds, infos = np.empty((T, nx, nx)), np.empty((T, nx, nx))
    for k in range(1, T + 1):
        A, Qd = system.transition(k - 1), system.process_cov(k - 1)
        Bp = np.zeros((nx, nx))
        Bp[:n, :n] = A @ B[:n, :n] @ A.T + Qd
        if nx > n:
            Bp[n:, :n] = B[: nx - n, :n] @ A.T
            Bp[:n, n:] = Bp[n:, :n].T
            Bp[n:, n:] = B[: nx - n, : nx - n]
        sig = _sigmas(system, k)
        J = np.zeros((nx, nx))
        if fad is None:  # every channel alike: the Fisher information of its reading about the latent mean
            C = system.measurement(k)
            mu = X[:, k] @ C.T  # (N, m)
            Imm = np.stack([cens.fisher_information(mu[:, l], np.full(mu.shape[0], sig[l]), k, l) for l in range(m)], 1)
            J = (C.T * Imm.mean(0)) @ C
        else:
            lo, hi = cens.limits(k)
            lo, hi = np.broadcast_to(lo, (m,)), np.broadcast_to(hi, (m,))
            S_ = min(L, k)
            Cs = [measurement_matrix_at(system, k - s) for s in range(S_ + 1)]
            for l in range(m):
                H = np.zeros(nx)
                cx = np.stack([X[:, k - s] @ Cs[s][l] for s in range(S_ + 1)], axis=1)  # (N, S+1)
                for s in range(S_ + 1):
                    H[s * n : (s + 1) * n] = mg[s, l] * Cs[s][l]
                mu = cx @ mg[: S_ + 1, l]
                sd = np.sqrt((cx * cx) @ vg[: S_ + 1, l] + sig[l] ** 2)
                Imm, Ims, Iss = censored_fisher_information(mu, sd, lo[l], hi[l])
                G = np.zeros((X.shape[0], nx))  # grad sigma per run
                for s in range(S_ + 1):
                    G[:, s * n : (s + 1) * n] = (vg[s, l] * cx[:, s] / sd)[:, None] * Cs[s][l]
                HG = (Ims[:, None] * G).mean(0)
                J += (
                    Imm.mean() * np.outer(H, H)
                    + np.outer(H, HG)
                    + np.outer(HG, H)
                    + (G * Iss[:, None]).T @ G / X.shape[0]
                )
        B = symmetrize(np.linalg.solve(np.eye(nx) + Bp @ J, Bp))
        bounds[k - 1], infos[k - 1] = B, J
    return PosteriorCRLB(
        bound=bounds[:, :n, :n].copy(),
        var=np.diagonal(bounds[:, :n, :n], axis1=1, axis2=2).copy(),
        aug_bound=bounds,
        information=infos,
        times=np.arange(1, T + 1),
    )


def bound_test(err2: Any, bound: Any, level: float = 0.01) -> dict[str, Any]:
    r"""Calibrated test of :math:`E[e_{k,i}^2] \ge B_{k,i}` at every step k and component i (e.g. a PCRLB).

    Per step and component, the one-sided p-value of the lower-tail inequality for a mean of
    nonnegative variables (:math:`X = e^2 \ge 0`: :math:`P(\bar X \le \mu - t) \le
    \exp(-Nt^2 / (2E[X^2]))`), with the sample second moment :math:`\overline{X^2}` for :math:`E[X^2]`,
    floored at :math:`B^2` (under the null :math:`E[X^2] \ge (E X)^2 \ge B^2`; without the floor a few
    runs that happen to be small make the plug-in small, and at N = 12 a nominal 1 % rejects 4.6 %):

    .. math::

        p_{k,i} = \exp\bigl(-N\,(B_{k,i} - \overline{e^2}_{k,i})_+^2 /
        (2\max(\overline{e^4}_{k,i}, B_{k,i}^2))\bigr).

    The normal approximation of the t statistic is not used: the squared errors are skewed
    (chi-square-like), low sample means come with low sample variances, and at N = 200 a nominal 1 %
    test rejects about 2.5 % of true nulls with Gaussian errors (more with heavier tails). The family of
    :math:`K = Tn` p-values is tested by Holm's step-down procedure at ``level`` (family-wise, valid
    for any dependence between steps, which is strong: the steps share the runs). The verdict holds
    when Holm rejects nothing (:math:`\min p > \alpha / K`). The errors' tails beyond what the runs
    show are not covered: with Student-t(5) errors at N = 200 a nominal 1 % rejects 1.6 %.

    Also reported: the time-averaged test, per run :math:`s_r = \operatorname{mean}_{k,i} e^2_{r,k,i}/B_{k,i}`
    (independent over runs, nearly normal mean), one-sided p-value of :math:`E[s] \ge 1`.

    Parameters
    ----------
    err2 : (N, T, n) array_like
        Squared errors over N >= 2 runs.
    bound : (T, n) array_like
        The lower bound per step and component, > 0.
    level : float
        The family-wise level.

    Returns
    -------
    dict
        ``p`` (T, n), ``rejected`` (T, n) Holm's rejections, ``steps_rejected``, ``holds``,
        ``naive_steps_rejected`` (the per-step normal test at ``level``, for comparison),
        ``mean_ratio`` (mean of :math:`s_r`), ``mean_ratio_stderr``, ``mean_ratio_p``.
    """
    e2 = np.asarray(err2, dtype=float)
    B = np.asarray(bound, dtype=float)
    N = e2.shape[0]
    m = e2.mean(0)
    m2 = np.maximum((e2 * e2).mean(0), B * B)  # under the null E[X^2] >= (E X)^2 >= B^2
    with np.errstate(divide="ignore", invalid="ignore"):
        expo = np.where(m < B, N * (B - m) ** 2 / (2.0 * m2), 0.0)
    p = np.exp(-np.nan_to_num(expo, nan=np.inf))
    flat = p.ravel()
    K = flat.size
    order = np.argsort(flat, kind="stable")
    thresh = level / (K - np.arange(K))
    ok = flat[order] <= thresh
    n_rej = K if ok.all() else int(np.argmin(ok))
    rej = np.zeros(K, dtype=bool)
    rej[order[:n_rej]] = True
    rej = rej.reshape(p.shape)
    se = e2.std(0, ddof=1) / np.sqrt(N)
    naive = m + float(ndtri(1.0 - level)) * se < B
    s = (e2 / B).reshape(N, -1).mean(1)
    s_se = float(s.std(ddof=1) / np.sqrt(N))
    return {
        "p": p,
        "rejected": rej,
        "steps_rejected": int(rej.any(axis=-1).sum()) if rej.ndim > 1 else int(rej.sum()),
        "holds": bool(n_rej == 0),
        "level": level,
        "naive_steps_rejected": int(naive.any(axis=-1).sum()) if naive.ndim > 1 else int(naive.sum()),
        "mean_ratio": float(s.mean()),
        "mean_ratio_stderr": s_se,
        "mean_ratio_p": float(ndtr((s.mean() - 1.0) / s_se)) if s_se > 0 else float(s.mean() >= 1.0),
    }
