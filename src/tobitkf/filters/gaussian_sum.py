r"""The Gaussian-sum assumed-density filter of a nonlinear model read through any channel.

Not in the sources. A Gaussian filter cannot follow a posterior with two separated modes (a target heard by one
beacon lies somewhere on a ring; a beacon out of range removes a disk from the plane). The established remedy is
a Gaussian sum (Alspach & Sorenson 1972): the posterior is carried as a mixture

.. math::

    p(x_k \mid y_{1:k}) \approx \sum_{i=1}^{C_k} w_i\,N(x_k;\ m_i, P_i), \qquad \sum_i w_i = 1,

each component runs the nonlinear assumed-density filter's predict and update
(:class:`~tobitkf.NonlinearAssumedDensityFilter`, with its rule and ``iterations``), and the weights follow
the evidence each component gives the reading,

.. math::

    w_i \leftarrow \frac{w_i\,p_i(y_k)}{\sum_j w_j\,p_j(y_k)}, \qquad
    \log p_i(y_k) = \sum_l \log p_i(y_{k,l}),

:math:`p_i(y_{k,l})` the channel's probability (density) of the reading under the component's first
linearisation of channel l (the assumed-density filter's ``log_likelihood`` extras), so the filter's
log-likelihood of the step is :math:`\log\sum_j w_jp_j(y_k)`.

**Splitting** (where the update is far from Gaussian). After the prediction, the nonlinearity of each component
is measured per channel with a reading by the residual variance of the statistical linearisation of
:math:`h_l` about the component (the variance of :math:`h_l` the affine model misses, in units of the noise):

.. math::

    \eta_{i,l} = \frac{\Omega_{i,l}}{R_{ll}}, \qquad
    \Omega_{i,l} = \mathrm{Var}_i[h_l(x)] - \mathrm{Cov}_i(x, h_l)^TP_i^{-1}\mathrm{Cov}_i(x, h_l),

(the rule's sigma points of :math:`N(m_i, P_i)`). While a run has room (fewer than ``components``
components, two free), its component of the largest :math:`\eta_i = \max_l\eta_{i,l}` is split when
:math:`\eta_i` exceeds ``split_threshold``: along the principal axis v of :math:`P_i` (eigenvalue
:math:`\lambda`) into three components with the weights :math:`w_i(0.2252, 0.5496, 0.2252)`, the means
:math:`m_i - c\sqrt\lambda v,\ m_i,\ m_i + c\sqrt\lambda v` and the covariance
:math:`P_i - (1 - s^2)\lambda vv^T` each (the standard deviation along v times s = 0.6715): the weights and
spread of Huber et al.'s three-component split of a normal law (close to it in density, also when split
again and again: a recursive split of N(0, 1) stays within 0.015 of its density, 4 % of its peak), with the
offset :math:`c = \sqrt{(1 - s^2)/(2\cdot 0.2252)} \approx 1.104` that keeps the component's mean and
covariance exactly. The first step splits the prior the same way.

**Merging** (after the update). Pairs of components are merged, moment-preserving, while the cheapest pair's
cost is below ``merge_threshold``: the upper bound of the Kullback–Leibler divergence that the merge adds to the
mixture (Runnalls 2007),

.. math::

    B_{ij} = \tfrac12\left[(w_i + w_j)\log\det P_{ij} - w_i\log\det P_i - w_j\log\det P_j\right],

with the merged component :math:`w_{ij} = w_i + w_j`, :math:`m_{ij} = (w_im_i + w_jm_j)/w_{ij}`,
:math:`P_{ij} = (w_iP_i + w_jP_j)/w_{ij} + \frac{w_iw_j}{w_{ij}^2}(m_i - m_j)(m_i - m_j)^T`. Components that
have come together, or whose weight has fallen to nothing, merge and free room for the next splits.

**Reported moments.** The mixture's mean and covariance,
:math:`\hat x = \sum_iw_im_i`, :math:`P = \sum_iw_i(P_i + (m_i - \hat x)(m_i - \hat x)^T)`, and the same of
the predicted mixture.

**Reductions** (tested). ``components=1`` never splits: the filter is the nonlinear assumed-density filter. A
measurement map that is affine has :math:`\Omega = 0` and never splits either: on a linear-Gaussian model every
``components`` gives the Kalman filter.

**Limits.** The split mixture is close to the component in density, not in ratio far in its tails, so a mode
that carries little of the prediction's mass (a reading that lands in its tail) gets a rough weight; splitting
stops at ``split_threshold`` or at ``components``, so more components bring the moments closer to the exact
posterior's only down to that level (tested on one step against quadrature).

Shapes: the components of N runs are arrays (N, K, n), (N, K, n, n) and the log-weights (N, K), K =
``components`` (a run's unused slots carry weight 0); every step runs the assumed-density filter once over the
N K components.

Time convention (package-wide): :math:`x_0 \sim N(\bar x_0, P_0)` is the prior, :math:`y_1` is at index 0,
result row k-1 holds the mixture moments of :math:`x_{k|k}` and of the prediction.

References
----------
.. [1] D. L. Alspach, H. W. Sorenson, "Nonlinear Bayesian estimation using Gaussian sum approximations", IEEE
   Trans. Automatic Control 17(4), 1972, 439-448.
.. [2] A. R. Runnalls, "Kullback-Leibler approach to Gaussian mixture reduction", IEEE Trans. Aerospace and
   Electronic Systems 43(3), 2007, 989-999.
.. [3] M. F. Huber, T. Bailey, H. Durrant-Whyte, U. D. Hanebeck, "On entropy approximation for Gaussian mixture
   random vectors", IEEE MFI 2008 (splitting a component where the measurement is nonlinear).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .._linalg import symmetrize
from .._validation import as_float, check_int
from ..models.nonlinear import NonlinearSystem
from ._boundary import _noise_variances
from .core import Estimator, check_prior
from .likelihood import filter_log_likelihood
from .nonlinear import _sigma_moments
from .nonlinear_adf import NonlinearAssumedDensityFilter
from .particle import _mixture_moments, reweight

__all__ = ["GaussianSumAssumedDensityFilter", "split_principal", "SPLIT_WEIGHTS", "SPLIT_OFFSET", "SPLIT_SCALE"]

SPLIT_WEIGHTS = (0.2252, 0.5496, 0.2252)
"""The weights of the three children of a split, as fractions of the parent's weight (Huber et al. 2008)."""
SPLIT_SCALE = 0.6715
"""The children's standard deviation along the principal axis over the parent's (the other axes are kept)."""
SPLIT_OFFSET = math.sqrt((1.0 - SPLIT_SCALE**2) / (2.0 * SPLIT_WEIGHTS[0]))
"""The children's offsets along the principal axis, in standard deviations of the parent along it (about 1.104):
the value that keeps the parent's variance, :math:`2w_1c^2 + s^2 = 1`."""


class GaussianSumAssumedDensityFilter(Estimator):
    r"""A Gaussian sum of nonlinear assumed-density filters, split where the update is far from Gaussian and
    merged where components meet (module docstring).

    Parameters
    ----------
    system : NonlinearSystem
    channel : Channel
        The model (R diagonal, entries >= 0) and the channel (with ``region`` or ``reading_moments``), as
        :class:`~tobitkf.NonlinearAssumedDensityFilter`'s.
    components : int >= 1, default 8
        The most components a run carries (K); 1 is the assumed-density filter.
    split_threshold : float > 0, default 0.05
        A component is split when the variance of h its linearisation misses exceeds this fraction of the noise
        variance on some channel with a reading (:math:`\eta_i`, module docstring).
    merge_threshold : float >= 0, default 1e-3
        Two components are merged while the cheapest pair's Runnalls cost :math:`B_{ij}` is below this.
    rule, alpha, beta, kappa, order, iterations
        The assumed-density filter's sigma-point rule and linearisations per channel
        (:class:`~tobitkf.NonlinearAssumedDensityFilter`); the rule also measures the nonlinearity.

    Raises
    ------
    ValidationError
        As :class:`~tobitkf.NonlinearAssumedDensityFilter`; ``components`` not an integer in [1, 1000], a threshold
        not a finite number in range.

    Notes
    -----
    Extras: ``log_likelihood`` (..., T), :math:`\log\sum_iw_ip_i(y_k)` (0 for a step without readings);
    ``weights`` (..., T, K), the components' weights after the step (0 for an unused slot; they sum to 1);
    ``components`` (..., T), the number in use. A step costs about the assumed-density filter's times the components in use, plus the nonlinearity measure
    of the splits (one sigma-point pass per round).
    The numpy path only (no compiled loop).

    Examples
    --------
    With one component it is the assumed-density filter:

    >>> import numpy as np, tobitkf as tk
    >>> sys = tk.NonlinearSystem(lambda x, k: x, lambda x, k: x**2, Q=[[0.1]], R=[[0.5]], x0=[1.0], P0=[[1.0]])
    >>> cens = tk.Censoring(lower=0.2)
    >>> y = np.array([[0.9], [0.2], [1.4]])
    >>> a = tk.GaussianSumAssumedDensityFilter(sys, cens, components=1).filter(y).mean
    >>> b = tk.NonlinearAssumedDensityFilter(sys, cens).filter(y).mean
    >>> bool(np.allclose(a, b, rtol=0, atol=1e-12))
    True
    """

    _name = "GaussianSumAssumedDensityFilter"
    _filter_doc = (
        "Filter the readings ``y`` (..., T, m) of a batch of records: per step every component's assumed-density "
        "predict and update, the weights by each component's evidence, splits before the update and merges "
        "after it; the rows hold the mixture's moments."
    )
    _filter_params = {
        "u": "(T, p) or (..., T, p) array_like, optional\n"
        "    Known inputs u_1..u_T of an ``f(x, k, u)`` (index k-1 holds u_k; none given: u = 0).",
    }
    _filter_raises = "a reading the channel cannot give (its ``check_readings``)"

    def __init__(
        self,
        system: NonlinearSystem,
        channel: Any,
        *,
        components: int = 8,
        split_threshold: float = 0.05,
        merge_threshold: float = 1e-3,
        rule: Any = "unscented",
        iterations: int = 1,
        alpha: float = 1.0,
        beta: float = 2.0,
        kappa: float = 0.0,
        order: int = 3,
    ):
        self._adf = NonlinearAssumedDensityFilter(
            system,
            channel,
            rule=rule,
            iterations=iterations,
            alpha=alpha,
            beta=beta,
            kappa=kappa,
            order=order,
            backend="numpy",
        )
        self.system, self.channel, self.rule = system, self._adf.channel, self._adf.rule
        self.n, self.m = system.n, system.m
        self.iterations = self._adf.iterations
        self.components = check_int(components, "components", minimum=1, maximum=1000)
        self.split_threshold = as_float(split_threshold, "split_threshold", low=0.0, low_open=True)
        self.merge_threshold = as_float(merge_threshold, "merge_threshold", low=0.0)

    # ---- the boundary checks and inputs are the assumed-density filter's
    def _check_record(self, y2, u2, k0, name="y"):
        self._adf._check_record(y2, u2, k0, name)

    def _check_reading(self, k, y, options):
        self._adf._check_reading(k, y, options)

    def _prepare_inputs(self, u, N, T, batch):
        return self._adf._prepare_inputs(u, N, T, batch)

    def _step_input(self, state, u):
        return self._adf._step_input(state, u)

    def _bytes_per_run(self) -> int:
        n, K = self.n, self.components
        return 8 * (K * (n + n * n + 1) + n + n * n)

    # ---- the prior and the step
    def _initial(self, N: int, x0: Any, P0: Any, batch: tuple[int, ...]):
        x, P = check_prior(self.system, x0, P0, N, batch)
        K, n = self.components, self.n
        M = np.broadcast_to(x[:, None], (N, K, n)).copy()
        Cv = np.broadcast_to(P[:, None], (N, K, n, n)).copy()
        lw = np.full((N, K), -np.inf)
        lw[:, 0] = 0.0
        carry = {"means": M, "covs": Cv, "log_weights": lw, "count": np.ones(N, dtype=np.int64)}
        return x, np.broadcast_to(P, (N, n, n)).copy(), carry

    def _step_arrays(self, k, x, P, S, carry, y, u, options=None):
        K = self.components
        lw, count = carry["log_weights"].copy(), carry["count"].copy()
        adf = self._adf
        # the components in use, gathered flat (run r, slot c): the assumed-density filter runs on those alone
        r, c = _used(count, K)
        Mp, Cp = carry["means"].copy(), carry["covs"].copy()
        Mp[r, c], Cp[r, c], _ = adf._predict(k, Mp[r, c], Cp[r, c], None, _rows(u, r))
        pred_mean, pred_cov = _mixture_moments(Mp, Cp, _weights(lw))
        if K > 1:
            Mp, Cp, lw, count = self._split(k, Mp, Cp, lw, count, y, u)
            r, c = _used(count, K)
        xn, Pn, _, _, ex = adf._update_arrays(k, Mp[r, c], Cp[r, c], None, y[r], _rows(u, r), {}, {})
        Mn, Cn = Mp, Cp
        Mn[r, c], Cn[r, c] = xn, symmetrize(Pn)
        ll = np.zeros(lw.shape)
        ll[r, c] = ex["log_likelihood"]
        _, _, lw, ll_step = reweight(lw, ll)
        if K > 1:
            Mn, Cn, lw, count = _merge(*_drop_weightless(Mn, Cn, lw, count), self.merge_threshold)
        W = _weights(lw)
        mean, cov = _mixture_moments(Mn, Cn, W)
        carry = {"means": Mn, "covs": Cn, "log_weights": lw, "count": count}
        extras = {"log_likelihood": ll_step, "weights": W, "components": count.copy()}
        return mean, cov, None, carry, pred_mean, pred_cov, extras

    def _nonlinearity(self, k: int, M: np.ndarray, Cv: np.ndarray, y: np.ndarray, u: Any, count: np.ndarray):
        r""":math:`\eta_i = \max_l \Omega_{i,l}/R_{ll}` (N, K) over the channels with a reading (module docstring);
        -inf for an unused slot."""
        N, K, _ = M.shape
        adf = self._adf
        assert adf.rule is not None, "the assumed-density filter linearises with sigma points"
        r, c = _used(count, K)
        x, P = M[r, c], Cv[r, c]
        _, Pxy, Pyy = _sigma_moments(adf.rule, adf._h_points(k, _rows(u, r)), x, P)
        try:
            G = np.linalg.solve(P, Pxy)
        except np.linalg.LinAlgError:
            G = np.linalg.pinv(P, hermitian=True) @ Pxy
        omega = np.diagonal(Pyy, axis1=-2, axis2=-1) - np.einsum("rim,rim->rm", Pxy, G)
        noise = adf._r if adf._r is not None else _noise_variances(adf._noise(k), f"R({k})")
        eta = np.maximum(omega, 0.0) / np.maximum(noise, np.finfo(float).tiny)
        out = np.full((N, K), -np.inf)
        out[r, c] = np.where(np.isnan(y[r]), 0.0, eta).max(axis=-1)
        return out

    def _split(self, k, M, Cv, lw, count, y, u):
        """Split, run by run, the most nonlinear component while it exceeds the threshold and two slots are free."""
        K = self.components
        rows_all = np.arange(M.shape[0])
        while True:
            room = count + 2 <= K
            if not room.any():
                break
            eta = self._nonlinearity(k, M, Cv, y, u, count)
            j = np.argmax(eta, axis=1)
            do = room & (eta[rows_all, j] > self.split_threshold)
            if not do.any():
                break
            r, jj, c0 = np.flatnonzero(do), j[do], count[do]
            means, Pc = split_principal(M[r, jj], Cv[r, jj])
            w = lw[r, jj]
            for c, slot in enumerate((c0, jj, c0 + 1)):
                M[r, slot], Cv[r, slot], lw[r, slot] = means[:, c], Pc, w + math.log(SPLIT_WEIGHTS[c])
            count[r] += 2
        return M, Cv, lw, count

    def log_likelihood(self, y: Any, *, u: Any = None, x0: Any = None, P0: Any = None, per_step: bool = False):
        r"""The Gaussian-sum log-likelihood :math:`\sum_k\log\sum_iw_ip_i(y_k)` of ``y`` (..., T, m): (...), or the
        terms (..., T) with ``per_step``; with ``components=1`` the assumed-density filter's.

        Raises
        ------
        ValidationError, ShapeError
            As :meth:`filter`.
        """
        return filter_log_likelihood(self, y, per_step=per_step, u=u, x0=x0, P0=P0)

    def __repr__(self) -> str:
        return (
            f"GaussianSumAssumedDensityFilter({self.system!r}, {self.channel!r}, components={self.components}, "
            f"split_threshold={self.split_threshold:g}, merge_threshold={self.merge_threshold:g}, rule={self.rule!r}"
            + ("" if self.iterations == 1 else f", iterations={self.iterations}")
            + ")"
        )


def split_principal(m: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r"""The three children of each component :math:`N(m, P)` (m (R, n), P (R, n, n)) split along the principal
    axis v of P (eigenvalue :math:`\lambda`): the means (R, 3, n) :math:`m + jc\sqrt\lambda v`, j = -1, 0, 1
    (c = :data:`SPLIT_OFFSET`), and their common covariance (R, n, n) :math:`P - (1 - s^2)\lambda vv^T`
    (s = :data:`SPLIT_SCALE`); with the weights :data:`SPLIT_WEIGHTS` the mixture has the mean and covariance of
    :math:`N(m, P)` (module docstring)."""
    lam, V = np.linalg.eigh(P)
    v, l1 = V[:, :, -1], np.maximum(lam[:, -1], 0.0)
    d = SPLIT_OFFSET * np.sqrt(l1)[:, None] * v
    Pc = symmetrize(P - (1.0 - SPLIT_SCALE**2) * l1[:, None, None] * v[:, :, None] * v[:, None, :])
    means = m[:, None, :] + np.array([-1.0, 0.0, 1.0])[None, :, None] * d[:, None, :]
    return means, Pc


def _used(count: np.ndarray, K: int) -> tuple[np.ndarray, np.ndarray]:
    """The (run, slot) indices of the components in use, the first ``count[r]`` slots of run r, run-major."""
    r, c = np.nonzero(np.arange(K) < count[:, None])
    return r, c


def _rows(u: np.ndarray | None, r: np.ndarray) -> np.ndarray | None:
    """The input of each run (N, p) for the components of the runs ``r``."""
    return None if u is None else u[r]


def _drop_weightless(M: np.ndarray, Cv: np.ndarray, lw: np.ndarray, count: np.ndarray):
    """Remove the components in use whose weight is 0 (a reading they cannot give), the last one in use moving into
    the freed slot, so that the slots in use stay the first ``count``; a run keeps at least one."""
    N, K = lw.shape
    while True:
        used = np.arange(K) < count[:, None]
        gone = used & np.isneginf(lw) & (count > 1)[:, None]
        if not gone.any():
            return M, Cv, lw, count
        r = np.flatnonzero(gone.any(axis=1))
        j = np.argmax(gone[r], axis=1)
        last = count[r] - 1
        M[r, j], Cv[r, j], lw[r, j] = M[r, last], Cv[r, last], lw[r, last]
        lw[r, last] = -np.inf
        count[r] -= 1


def _weights(lw: np.ndarray) -> np.ndarray:
    """The weights (N, K) of normalised log-weights (-inf: an unused slot, weight 0)."""
    return np.exp(lw)


def _logdet(P: np.ndarray) -> np.ndarray:
    sign, ld = np.linalg.slogdet(P)
    return np.where(sign > 0, ld, -np.inf)


def _merge(M: np.ndarray, Cv: np.ndarray, lw: np.ndarray, count: np.ndarray, threshold: float):
    r"""Merge, run by run, the pair of least Runnalls cost while it is below ``threshold`` (module docstring); the
    last used slot moves into the freed one, so a run's used slots stay the first ``count``."""
    N, K, n = M.shape
    rows = np.arange(N)
    iu, ju = np.triu_indices(K, 1)
    while True:
        W = np.exp(lw)
        wi, wj = W[:, iu], W[:, ju]
        used = np.isfinite(lw[:, iu]) & np.isfinite(lw[:, ju])
        if not used.any():
            break
        wij = np.where(used, wi + wj, 1.0)
        a, b = wi / wij, wj / wij
        dm = M[:, iu] - M[:, ju]
        Pij = (
            a[..., None, None] * Cv[:, iu]
            + b[..., None, None] * Cv[:, ju]
            + (a * b)[..., None, None] * dm[..., :, None] * dm[..., None, :]
        )
        ld = _logdet(Cv)
        with np.errstate(invalid="ignore"):
            cost = 0.5 * (wij * _logdet(Pij) - wi * ld[:, iu] - wj * ld[:, ju])
        cost = np.where(used & np.isfinite(cost), cost, np.inf)
        best = np.argmin(cost, axis=1)
        do = cost[rows, best] < threshold
        if not do.any():
            break
        r, p = np.flatnonzero(do), best[do]
        i, j = iu[p], ju[p]
        M[r, i] = a[r, p, None] * M[r, i] + b[r, p, None] * M[r, j]
        Cv[r, i] = symmetrize(Pij[r, p])
        lw[r, i] = np.log(wij[r, p])
        last = count[r] - 1
        M[r, j], Cv[r, j], lw[r, j] = M[r, last], Cv[r, last], lw[r, last]
        M[r, last], Cv[r, last], lw[r, last] = M[r, 0], Cv[r, 0], -np.inf
        count[r] -= 1
    return M, Cv, lw, count
