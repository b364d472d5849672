r"""Shared pieces of the record experiments: the batched assumed-density pass over runs that each carry
their own model, finite-difference derivatives of a batched likelihood, the maximum-likelihood fit with
standard errors, and the fit's record in ``metrics.json``."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

__all__ = [
    "adf_pass",
    "adf_system",
    "mixture_update",
    "mixture_predictive_scores",
    "gap_matrices",
    "fd_gradient",
    "fd_hessian",
    "fit_ml",
    "inverse_information",
    "fit_record",
]

_YEAR = 365.25
_FD_STEP = 1e-4  # central finite differences in the unconstrained parameters
_CHUNK_NUMBERS = 1 << 23  # the most numbers in one per-run matrix array of adf_pass (64 MB)


# ------------------------------------------------------------------------------- the batched ADF pass
def gap_matrices(rate: np.ndarray, diffusion: np.ndarray, gaps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r"""The exact discretisation of a diagonal continuous-time model over each gap: the diagonals of
    :math:`A` and :math:`Q`,

    .. math::

        a_j = e^{-\lambda_j \Delta}, \qquad q^d_j = q_j \Delta\,\psi(2\lambda_j\Delta), \quad
        \psi(z) = (1 - e^{-z})/z,\ \psi(0) = 1,

    of :math:`dx_j = -\lambda_j x_j\,dt + \sqrt{q_j}\,dW_j` (an Ornstein-Uhlenbeck state of stationary
    variance :math:`q_j/2\lambda_j`; :math:`\lambda_j = 0` a random walk of variance :math:`q_j` per unit
    time).

    Parameters
    ----------
    rate, diffusion : (N, n) :math:`\lambda \ge 0` and :math:`q \ge 0` of each run
    gaps : (T,) or (N, T) :math:`\Delta \ge 0` before each step

    Returns
    -------
    a, qd : (N, T, n)
    """
    rate = np.asarray(rate, dtype=float)
    dt = np.broadcast_to(np.asarray(gaps, dtype=float), (rate.shape[0], np.shape(gaps)[-1]))[:, :, None]
    z = 2.0 * rate[:, None, :] * dt
    psi = np.where(z > 0, -np.expm1(-z) / np.where(z > 0, z, 1.0), 1.0)
    return np.exp(-rate[:, None, :] * dt), np.asarray(diffusion, dtype=float)[:, None, :] * dt * psi


_DIAGONAL_BUFFERS: dict[tuple[str, tuple[int, ...]], np.ndarray] = {}


def _diagonal_matrices(d: np.ndarray, role: str) -> np.ndarray:
    """(..., n, n) diagonal matrices of the diagonals ``d`` (..., n), the diagonal written through a strided view
    into a zero buffer kept per ``role`` and shape (several times faster than ``d[..., None] * eye``, which
    multiplies every entry, and than fresh zeros each call: a fit evaluates the likelihood hundreds of times
    on arrays of one shape). The buffer is rewritten by the next call of the same role and shape: the system
    built on it lives for one pass of :func:`adf_pass`."""
    n = d.shape[-1]
    key = (role, d.shape)
    out = _DIAGONAL_BUFFERS.get(key)
    if out is None:
        if len(_DIAGONAL_BUFFERS) > 8:  # a few shapes at a time (a fit's batch, the Hessian's, the refits')
            _DIAGONAL_BUFFERS.clear()
        out = _DIAGONAL_BUFFERS[key] = np.zeros(d.shape + (n,))
    out.reshape(d.shape[:-1] + (n * n,))[..., :: n + 1] = d  # the off-diagonal entries stay 0
    return out


def adf_system(
    x0: np.ndarray, P0: np.ndarray, rate: np.ndarray, diffusion: np.ndarray, gaps: np.ndarray, C: np.ndarray, r2: Any
):
    r"""The models of N runs as one :class:`~tobitkf.LinearSystem` with a model per run (``batch_ndim=1``):
    :math:`A_{ik} = \mathrm{diag}(a_{ik})`, :math:`Q_{ik} = \mathrm{diag}(q^d_{ik})` (:func:`gap_matrices`),
    the row :math:`c_k` shared, :math:`R_{ik} = r^2_{ik}`, and the offset :math:`d_{ik}` entering as the input
    :math:`u_{ik}` through :math:`D = 1`."""
    from .. import LinearSystem

    N, n = np.shape(rate)
    T = np.shape(C)[0]
    a, qd = gap_matrices(rate, diffusion, gaps)  # (N, T, n)
    r2 = np.broadcast_to(np.asarray(r2, dtype=float), (N, T))
    Cr = np.asarray(C, dtype=float)[None, :, None, :]  # (1, T, 1, n): shared by the runs, per step
    return LinearSystem(
        A=_diagonal_matrices(a, "A"),  # A[:, k]: into reading k + 1 (array index k)
        C=Cr,
        Q=_diagonal_matrices(qd, "Q"),
        R=r2[..., None, None],
        x0=np.zeros(n),
        P0=np.eye(n),
        D=np.ones((1, 1)),
        batch_ndim=1,
    )


def adf_pass(
    x0: np.ndarray,
    P0: np.ndarray,
    rate: np.ndarray,
    diffusion: np.ndarray,
    gaps: np.ndarray,
    C: np.ndarray,
    y: np.ndarray,
    lower: Any,
    upper: Any,
    r2: np.ndarray,
    *,
    dy: Any = 0.0,
    smooth: bool = False,
    censored: Any = None,
    mixture: tuple[Any, Any] | None = None,
    compiled: bool | None = None,
) -> dict[str, Any]:
    r"""The assumed-density filter (and RTS smoother) of N runs of a scalar reading, each run its own model.

    Model of run i: the diagonal continuous-time state of :func:`gap_matrices` (rates :math:`\lambda_i`,
    diffusions :math:`q_i`) taken over each gap exactly, :math:`x_k = \mathrm{diag}(a_{ik})\,x_{k-1} + w_k`,
    :math:`w_k \sim N(0, \mathrm{diag}(q^d_{ik}))`, :math:`y^*_k = c_k x_k + d_{ik} + v_k`,
    :math:`v_k \sim N(0, r^2_{ik})`, :math:`x_0 \sim N(x_{0i}, P_{0i})`, the reading censored at
    ``lower``/``upper``. The package's assumed-density likelihood
    (:func:`~tobitkf.inference.likelihood.adf_log_likelihood`) of the per-run system of :func:`adf_system`,
    and with ``smooth`` its filter and RTS pass (:func:`~tobitkf.filters.smoothing.rts_smooth`).

    Parameters
    ----------
    x0 : (N, n) ; P0 : (N, n, n)
    rate, diffusion : (N, n) the continuous-time model of each run (:func:`gap_matrices`)
    gaps : (T,) or (N, T) time from the previous reading (from the prior's time for the first) to reading k
    C : (T, n) the measurement row of each step (shared by the runs)
    y : (N, T) readings; NaN = missing; a censored reading holds its limit
    lower, upper : scalar, (T,) or (N, T) limits (the limit rule classifies the readings)
    r2 : (N, T) noise variances ; dy : scalar or (N, T) offsets :math:`d_{ik}`
    smooth : also return the smoothed predictive of every reading
    censored : (T,) or (N, T) bool, optional: the recorded indicator (default: the limit rule); a flagged
        reading strictly inside its limits is an interval reading
    mixture : ((N,), (N,)), optional
        The outlier weight :math:`w_i \in [0, 1)` and variance ratio :math:`c_i^2 > 0` of a two-component
        scale-mixture noise, :math:`v_k \sim (1 - w_i)\,N(0, r^2_{ik}) + w_i\,N(0, c_i^2 r^2_{ik})`, instead of
        the Gaussian noise (:func:`mixture_update`, one moment-matched update per reading); :math:`w_i = 0` is
        the Gaussian model.
    compiled : bool, optional
        The mixture filter's loop compiled (default when numba imports; the same numbers to rounding) or the numpy
        reference (False). The Gaussian pass is the package's, compiled when numba imports.

    Returns
    -------
    dict
        ``loglik`` (N,) and ``terms`` (N, T), the assumed-density log-likelihood; with ``smooth``,
        ``mean`` and ``sd`` (N, T): :math:`c_k \hat x_{k|T} + d_{ik}` and
        :math:`\sqrt{c_k P_{k|T} c_k^T + \bar r^2_{ik}}`, the smoothed predictive of each (latent) reading
        (:math:`\bar r^2 = r^2` for Gaussian noise, the mixture's :math:`(1 - w + wc^2) r^2` otherwise),
        ``latent_var`` (N, T) :math:`c_k P_{k|T} c_k^T`, and ``filtered``, ``smoothed`` (the passes' results).
    """
    from .. import Censoring
    from ..filters.assumed_density import assumed_density_filter
    from ..filters.smoothing import rts_smooth
    from ..inference.likelihood import adf_log_likelihood

    N, n = np.shape(rate)
    T = np.shape(y)[-1]
    chunk = max(1, _CHUNK_NUMBERS // (T * n * n))
    if N > chunk:  # the per-run matrices (N, T, n, n) of a large batch, a chunk of runs at a time
        parts = []
        for s in range(0, N, chunk):
            sl = slice(s, s + chunk)

            def cut(v: Any) -> Any:
                return v[sl] if np.ndim(v) >= 2 else v

            parts.append(
                adf_pass(
                    x0[sl], P0[sl], rate[sl], diffusion[sl], cut(gaps), C, y[sl], cut(lower), cut(upper),
                    cut(r2), dy=cut(dy), smooth=smooth, censored=None if censored is None else cut(censored),
                    mixture=None if mixture is None else (np.asarray(mixture[0])[sl], np.asarray(mixture[1])[sl]),
                    compiled=compiled,
                )
            )  # fmt: skip
        return {key: np.concatenate([p[key] for p in parts]) for key in parts[0] if key not in ("filtered", "smoothed")}
    lo = np.broadcast_to(np.asarray(lower, dtype=float), (N, T))[..., None]
    hi = np.broadcast_to(np.asarray(upper, dtype=float), (N, T))[..., None]
    d = np.broadcast_to(np.asarray(dy, dtype=float), (N, T))
    # the per-run LinearSystem: for the Gaussian passes and the RTS pass (the mixture's likelihood does without it)
    system = adf_system(x0, P0, rate, diffusion, gaps, C, r2) if mixture is None or smooth else None
    Y = np.asarray(y, dtype=float)[..., None]
    u = np.ascontiguousarray(d[..., None])
    flags = None if censored is None else np.broadcast_to(np.asarray(censored, dtype=bool), (N, T))[..., None]
    if mixture is not None:
        res, terms = _mixture_filter(
            x0, P0, rate, diffusion, gaps, C, np.asarray(y, dtype=float), lo[..., 0], hi[..., 0], r2, d, mixture,
            None if flags is None else flags[..., 0], store=smooth, compiled=compiled,
        )  # fmt: skip
        w, c2 = (np.asarray(v, dtype=float)[:, None] for v in mixture)
        noise = np.broadcast_to(np.asarray(r2, dtype=float), (N, T)) * (1.0 - w + w * c2)
    elif not smooth:
        assert system is not None, "built for the Gaussian pass"
        terms = adf_log_likelihood(
            system, Censoring(), Y, u=u, x0=x0, P0=P0, per_step=True, lower=lo, upper=hi, censored=flags
        )
        return {"loglik": terms.sum(-1), "terms": terms}
    else:
        res = assumed_density_filter(system, Censoring()).filter(
            Y, u=u, x0=x0, P0=P0, lower=lo, upper=hi, censored=flags
        )
        terms = res.extras["log_likelihood"]
        noise = r2
    if not smooth:
        return {"loglik": terms.sum(-1), "terms": terms}
    assert system is not None, "built for the smoother"
    sm = rts_smooth(res, system, x0=x0, P0=P0)
    assert sm.mean is not None and sm.cov is not None, "the RTS pass returns means and covariances"
    Cn = np.asarray(C, dtype=float)
    out: dict[str, Any] = {"loglik": terms.sum(-1), "terms": terms}
    out["mean"] = np.einsum("ntj,tj->nt", sm.mean, Cn) + d
    v = np.einsum("ntij,ti,tj->nt", sm.cov, Cn, Cn)
    out["latent_var"] = np.maximum(v, 0.0)
    out["sd"] = np.sqrt(out["latent_var"] + noise)
    out["filtered"] = res
    out["smoothed"] = sm
    return out


def mixture_update(
    x: np.ndarray,
    P: np.ndarray,
    y: np.ndarray,
    c: np.ndarray,
    r2: np.ndarray,
    weight: np.ndarray,
    scale2: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    *,
    dy: Any = 0.0,
    cls: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r"""The assumed-density update of a Gaussian prior by one censored reading whose noise is a scale mixture,
    batched over runs.

    Prior :math:`x \sim N(\bar x, \bar P)`, latent reading :math:`y^* = cx + d + v` with
    :math:`v \sim (1 - w)\,N(0, r^2) + w\,N(0, c_s^2 r^2)` (``weight`` w, ``scale2`` :math:`c_s^2`). Given the
    component j (variance :math:`r_j^2`), :math:`(x, y^*)` is jointly Gaussian and the reading (a value, or an
    event :math:`y^* \le l`, :math:`y^* \ge h`, :math:`l < y^* < h`) gives the censored update of the package's
    assumed-density filter (:func:`~tobitkf.filters.assumed_density.censored_channel_update`): the exact
    posterior moments :math:`\hat x_j`, :math:`P_j` and the evidence :math:`\ell_j = p(y \mid j)` (the density
    :math:`N(y; c\bar x + d, c\bar Pc^T + r_j^2)` of a measured value, :math:`\Phi((l - c\bar x - d)/s_j)`
    below a limit). The exact posterior is the two-component mixture with weights
    :math:`\pi_j \propto w_j \ell_j` (:math:`w_1 = 1 - w`, :math:`w_2 = w`), projected on a Gaussian by its
    first two moments (:func:`~tobitkf.filters.assumed_density.merge_gaussians`):

    .. math::

        \hat x = \sum_j \pi_j \hat x_j, \qquad
        P = \sum_j \pi_j \left(P_j + (\hat x_j - \hat x)(\hat x_j - \hat x)^T\right), \qquad
        \log p(y) = \log \sum_j w_j \ell_j .

    Parameters
    ----------
    x : (N, n) ; P : (N, n, n) ; y : (N,) readings (NaN = missing) ; c : (n,) the measurement row
    r2, weight, scale2 : (N,) ; lower, upper : (N,) limits ; dy : (N,) or 0 the reading's known offset
    cls : (N,) int8, optional: the reading classes (:func:`~tobitkf.filters._readings.classify_readings`)

    Returns
    -------
    x (N, n), P (N, n, n), log_likelihood (N,) (0 for a missing reading, which leaves the prior unchanged)
    """
    from ..filters._readings import _MISSING
    from ..filters._readings import classify_readings as _classify
    from ..filters.assumed_density import censored_channel_update, merge_gaussians

    N = x.shape[0]
    cls = _classify(y, lower, upper) if cls is None else cls
    w = np.broadcast_to(np.asarray(weight, dtype=float), (N,))
    r2 = np.broadcast_to(np.asarray(r2, dtype=float), (N,))
    with np.errstate(divide="ignore"):
        log_w = np.stack([np.log1p(-w), np.log(w)])  # (2, N); w = 0 gives the Gaussian model exactly

    def two(v: Any) -> np.ndarray:  # the two components stacked as 2N runs
        v = np.broadcast_to(np.asarray(v, dtype=float), (N,) + np.shape(v)[1:])
        return np.concatenate([v, v])

    # both components in one call of the package's censored update (runs 0..N-1: r^2, N..2N-1: c^2 r^2)
    var: Any = np.concatenate([r2, np.asarray(scale2, dtype=float) * r2])  # r: scalar or (N,) per run
    xj, Pj, _, _, llj = censored_channel_update(
        two(x), two(P), None, two(y), c, var, two(lower),
        two(upper), dy=two(dy), cls=np.concatenate([cls, cls]), compiled=True,
    )  # fmt: skip
    joint = log_w + llj.reshape(2, N)
    ll = np.logaddexp(joint[0], joint[1])
    missing = cls == _MISSING
    ll = np.where(missing, 0.0, ll)
    with np.errstate(invalid="ignore"):
        post = np.exp(joint - ll)  # pi_j
    post = np.where(missing | ~np.isfinite(post), np.exp(log_w), post)
    n = x.shape[-1]
    xm, Pm, _ = merge_gaussians(post, xj.reshape(2, N, n), Pj.reshape(2, N, n, n))
    if missing.any():  # no reading: the prediction itself (not its merge with an equal copy, which rounds)
        xm = np.where(missing[:, None], x, xm)
        Pm = np.where(missing[:, None, None], P, Pm)
    return xm, Pm, ll


def _mixture_filter(
    x0: np.ndarray,
    P0: np.ndarray,
    rate: np.ndarray,
    diffusion: np.ndarray,
    gaps: np.ndarray,
    C: np.ndarray,
    y: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    r2: Any,
    dy: np.ndarray,
    mixture: tuple[Any, Any],
    flags: np.ndarray | None,
    *,
    store: bool = True,
    compiled: bool | None = None,
) -> tuple[Any, np.ndarray]:
    """The filter of :func:`adf_pass` with the mixture noise: the exact diagonal prediction over each gap, then
    :func:`mixture_update`; a :class:`~tobitkf.filters.core.FilterResult` (filtered and predicted moments, for the
    package's RTS pass; None without ``store``) and the log-likelihood terms (N, T).

    ``compiled`` (default: when numba imports): the same filter in one compiled loop
    (:func:`~tobitkf.experiments._compiled_mixture.compiled_mixture_filter`, the same censored block, equal to
    rounding); False: this numpy time loop, the reference."""
    from .._compiled import numba_available
    from ..filters._readings import classify_readings, interval_classes
    from ..filters.core import FilterResult

    N, n = np.shape(rate)
    T = y.shape[-1]
    if compiled is None:
        compiled = numba_available()
    cls = None
    if not compiled or flags is not None:  # the compiled loop applies the limit rule itself
        cls = classify_readings(y, lo, hi)
        if flags is not None:
            cls = interval_classes(cls, flags, lo, hi)
    r2 = np.broadcast_to(np.asarray(r2, dtype=float), (N, T))
    w = np.broadcast_to(np.asarray(mixture[0], dtype=float), (N,))
    c2 = np.broadcast_to(np.asarray(mixture[1], dtype=float), (N,))
    Cn = np.asarray(C, dtype=float)
    if compiled:
        from ..filters._outputs import loop_input as f
        from ._compiled_mixture import compiled_mixture_filter

        shape = (N, T) if store else (0, 0)
        xp, xs = np.empty(shape + (n,)), np.empty(shape + (n,))
        Pp, Ps = np.empty(shape + (n, n)), np.empty(shape + (n, n))
        terms = np.empty((N, T))
        with np.errstate(divide="ignore"):
            logw = np.stack([np.log1p(-w), np.log(w)], axis=1)  # (N, 2); w = 0 gives the Gaussian model exactly

        def rows(v: Any) -> np.ndarray:  # (N or 1, T): one row for an input the runs share (a broadcast view)
            v = np.asarray(v, dtype=float)
            v = v.reshape(1, -1) if v.ndim < 2 else v
            return f(v[:1] if v.shape[0] > 1 and v.strides[0] == 0 else v)

        given = np.zeros((0, 0), np.int8) if cls is None else np.require(cls, np.int8, ("C", "W"))
        compiled_mixture_filter(
            f(x0), f(P0), f(np.asarray(rate, dtype=float)), f(np.asarray(diffusion, dtype=float)), rows(gaps), f(Cn),
            rows(y), given, cls is not None, rows(lo), rows(hi), rows(r2), rows(dy), logw, f(c2),
            store, xp, Pp, xs, Ps, terms,
        )  # fmt: skip
        if not store:
            return None, terms
        return FilterResult(mean=xs, cov=Ps, pred_mean=xp, pred_cov=Pp, extras={"log_likelihood": terms}), terms
    assert cls is not None, "classified above"
    a, qd = gap_matrices(rate, diffusion, gaps)  # (N, T, n)
    xs, Ps = np.empty((N, T, n)), np.empty((N, T, n, n))
    xp, Pp = np.empty((N, T, n)), np.empty((N, T, n, n))
    terms = np.empty((N, T))
    x, P = np.asarray(x0, dtype=float), np.asarray(P0, dtype=float)
    diag = np.arange(n)
    for k in range(T):
        ak = a[:, k]
        x = ak * x
        P = P * ak[:, :, None] * ak[:, None, :]
        P[:, diag, diag] += qd[:, k]
        xp[:, k], Pp[:, k] = x, P
        x, P, terms[:, k] = mixture_update(
            x, P, y[:, k], Cn[k], r2[:, k], w, c2, lo[:, k], hi[:, k], dy=dy[:, k], cls=cls[:, k]
        )
        xs[:, k], Ps[:, k] = x, P
    res = FilterResult(mean=xs, cov=Ps, pred_mean=xp, pred_cov=Pp, extras={"log_likelihood": terms})
    return res, terms


def mixture_predictive_scores(mean: Any, sds: Any, weights: Any, low: Any, high: Any) -> Any:
    r"""Log predictive scores of scale-mixture predictions :math:`\sum_j \omega_{ij} N(m_i, s_{ij}^2)` of censored
    values: per sample :math:`\log \sum_j \omega_{ij} p_j`, with :math:`p_j` the component's density of a measured
    value or its probability of the censored event (:func:`tobitkf.wrtds.predictive_scores` per component, so the
    tails go through ``log_ndtr``); the RMSE of the mean as there.

    Parameters
    ----------
    mean : (n,) ; sds, weights : (n, J) (each row of weights summing to 1) ; low, high : (n,) as in
        :func:`~tobitkf.wrtds.predictive_scores`

    Returns
    -------
    PredictiveScores
    """
    from scipy.special import logsumexp

    from ..inference.wrtds import PredictiveScores, predictive_scores

    sds, weights = np.asarray(sds, dtype=float), np.asarray(weights, dtype=float)
    each = [predictive_scores(mean, sds[:, j], low, high) for j in range(sds.shape[1])]
    with np.errstate(divide="ignore"):
        joint = np.log(weights) + np.stack([e.log_score for e in each], axis=1)
    score = logsumexp(joint, axis=1)
    n = score.size
    return PredictiveScores(
        log_score=score,
        mean_log_score=float(np.mean(score)),
        se_mean_log_score=float(np.std(score, ddof=1) / np.sqrt(n)) if n > 1 else float("nan"),
        rmse=each[0].rmse,
        num_uncensored=each[0].num_uncensored,
    )


def fd_gradient(loglik: Any, theta: np.ndarray, h: float = _FD_STEP) -> tuple[np.ndarray, np.ndarray]:
    """Log-likelihoods (N,) and central-difference gradients (N, p) at N parameter vectors ``theta`` (N, p),
    from one call ``loglik(points, repeat)`` on the N (2p + 1) points (``repeat`` = 2p + 1 points per vector,
    in the vectors' order), so that a batched likelihood evaluates them together."""
    th = np.atleast_2d(np.asarray(theta, dtype=float))
    N, p = th.shape
    E = np.eye(p) * h
    pts = np.concatenate([th[:, None, :], th[:, None, :] + E, th[:, None, :] - E], axis=1)  # (N, 2p+1, p)
    ll = np.asarray(loglik(pts.reshape(-1, p), 2 * p + 1)).reshape(N, 2 * p + 1)
    return ll[:, 0], (ll[:, 1 : p + 1] - ll[:, p + 1 :]) / (2 * h)


def fd_hessian(loglik: Any, theta: np.ndarray, h: float = 1e-3) -> np.ndarray:
    r"""Central-difference Hessian (p, p) at one ``theta`` from one call ``loglik(points)`` on the 2p(p + 1)
    points :math:`\theta \pm h e_i \pm h e_j`, :math:`i \le j`."""
    th = np.asarray(theta, dtype=float).reshape(-1)
    p = th.size
    E = np.eye(p) * h
    corners = ((1, 1), (1, -1), (-1, 1), (-1, -1))
    pairs = [(i, j) for i in range(p) for j in range(i, p)]
    pts = [th + si * E[i] + sj * E[j] for i, j in pairs for si, sj in corners]
    f = np.asarray(loglik(np.array(pts))).reshape(-1, 4)
    H = np.empty((p, p))
    for c, (i, j) in enumerate(pairs):
        H[i, j] = H[j, i] = (f[c, 0] - f[c, 1] - f[c, 2] + f[c, 3]) / (4 * h * h)
    return H


def inverse_information(H: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """Inverse of the observed information -H (eigenvalues floored at 1e-8 of the largest, so that a
    parameter at the edge of its range, where the likelihood is flat, gets a finite, large variance), the
    standard errors (NaN along a floored direction) and whether -H is positive definite."""
    w, V = np.linalg.eigh(-0.5 * (H + H.T))
    floor = 1e-8 * max(float(np.max(np.abs(w))), 1e-300)
    pd = bool(np.all(w > floor))
    cov = (V / np.maximum(w, floor)) @ V.T
    se = np.sqrt(np.diag(cov))
    if not pd:
        flat = np.abs(V[:, w <= floor]).max(axis=1) > 0.1 if np.any(w <= floor) else np.zeros(H.shape[0], bool)
        se = np.where(flat, np.nan, se)
    return cov, se, pd


def fit_ml(model: Any, start: np.ndarray | None = None, gtol: float = 1e-5) -> dict[str, Any]:
    """Maximum likelihood of a model with ``loglik_and_gradient`` (one parameter vector) and ``hessian``: BFGS,
    then the observed information's inverse and standard errors."""
    from scipy.optimize import minimize

    t0 = time.perf_counter()
    x0 = model.start() if start is None else np.asarray(start, dtype=float)

    def fun(th: np.ndarray) -> tuple[float, np.ndarray]:
        f, g = model.loglik_and_gradient(th[None])
        val = float(np.ravel(f)[0])
        if not np.isfinite(val):
            return 1e10, np.zeros_like(th)
        return -val, -np.reshape(g, -1)

    res = minimize(fun, x0, jac=True, method="BFGS", options={"gtol": gtol, "maxiter": 500})
    fit_seconds = time.perf_counter() - t0
    H = model.hessian(res.x)
    cov, se, pd = inverse_information(H)
    return {
        "theta": res.x,
        "loglik": -float(res.fun),
        "hessian": H,
        "cov": cov,
        "se": se,
        "hessian_negative_definite": pd,
        "converged": bool(res.success),
        "message": str(res.message),
        "iterations": int(res.nit),
        "evaluations": int(res.nfev),
        "fit_seconds": fit_seconds,
        "seconds": time.perf_counter() - t0,
    }


def _noop(_: float) -> None:
    pass


def natural_table(model: Any, fit: dict[str, Any]) -> dict[str, Any]:
    """Estimates and standard errors on the fitted (unconstrained) scale, and of exp(.) of the log parameters and
    the logistic function of the logit ones (delta method: se of exp(u) = exp(u) se(u))."""
    th, se = fit["theta"], fit["se"]
    est = dict(zip(model.names, th.tolist()))
    ses = dict(zip(model.names, se.tolist()))
    nat, nat_se = {}, {}
    for name, v, s in zip(model.names, th, se):
        if name.startswith("log_"):
            nat[name[4:]] = float(np.exp(v))
            nat_se[name[4:]] = float(np.exp(v) * s)
        elif name.startswith("logit_"):  # a weight 1/(1 + e^-u): se = w(1 - w) se(u)
            w = float(1.0 / (1.0 + np.exp(-v)))
            nat[name[6:]] = w
            nat_se[name[6:]] = float(w * (1.0 - w) * s)
        else:
            nat[name] = float(v)
            nat_se[name] = float(s)
    return {"estimates": est, "se": ses, "natural": nat, "natural_se": nat_se}


def fit_record(model: Any, fit: dict[str, Any]) -> dict[str, Any]:
    out = natural_table(model, fit)
    out.update(
        {
            "loglik": fit["loglik"],
            "n_params": model.p,
            "aic": -2 * fit["loglik"] + 2 * model.p,
            "converged": fit["converged"],
            "hessian_negative_definite": fit["hessian_negative_definite"],
            "iterations": fit["iterations"],
            "evaluations": fit["evaluations"],
            "fit_seconds": round(fit["fit_seconds"], 3),
            "seconds_with_hessian": round(fit["seconds"], 3),
        }
    )
    return out
