r"""Assumed-density filter for the protocol channel: conditioning on the sensor-failure outcome.

Not in the source. Channel of Geng et al., protocol-based TKF ((2)–(7); docs/sources/geng-protocol.md, and
:class:`~tobitkf.channels.protocol.ProtocolChannel`): Round-Robin sensor :math:`h = \bar h_k`,
integral window ℓ, failure gain :math:`\Lambda_{h,k}` with a given law, censoring at τ,

.. math::

    \xi_k = [x_k^T \cdots x_{k-\ell}^T]^T, \qquad z_k = \Lambda_{h,k}\,\mathcal C_h\xi_k + v_{h,k}, \qquad
    y_k = \max(z_k, \tau), \qquad \mathcal C_h = \mathbf 1_{\ell+1}^T \otimes C_h.

The PBTKF of the source (:class:`~tobitkf.ProtocolTobitKalmanFilter`) replaces :math:`\Lambda` by
its mean :math:`\bar\Lambda` and adds a failure term to the noise at every step, so a reading from a
failed sensor (:math:`\Lambda = 0`: pure noise) moves the estimate as much as a healthy one.
This filter keeps the failure outcome as a discrete variable: given the Gaussian prior
:math:`N(\bar\xi, \bar P)`, each outcome :math:`\lambda_j` (probability :math:`\pi_j`) makes
:math:`(\xi, z)` jointly Gaussian, with :math:`\mu_j = \lambda_j\mathcal C_h\bar\xi`,
:math:`s_j^2 = \lambda_j^2\mathcal C_h\bar P\mathcal C_h^T + R_{hh}`; the exact posterior is the mixture

.. math::

    p(\xi \mid y) = \sum_j w_j\,p_j(\xi \mid y), \qquad
    w_j \propto \pi_j\begin{cases} \phi((y-\mu_j)/s_j)/s_j & y > \tau \\ \Phi((\tau-\mu_j)/s_j) & y = \tau \end{cases}

where each :math:`p_j` has the assumed-density moments of a (censored) reading
(:mod:`tobitkf.filters.assumed_density`: :math:`\hat\xi_j = \bar\xi + K_j(E_j[z\mid y]-\mu_j)`,
:math:`P_j = \bar P - K_j(s_j^2 - V_j)K_j^T`), and the mixture is merged to one Gaussian by moment
matching (:func:`~tobitkf.filters.assumed_density.merge_gaussians`; a first-order generalized
pseudo-Bayes step, Bar-Shalom, Li & Kirubarajan 2001, §11.6). The merged mean and covariance are the
exact posterior moments of the Gaussian prior. The posterior probabilities :math:`w_j` of the
outcomes are returned (``failure_posterior``). A discrete law (:class:`~tobitkf.channels.laws.PMF`,
a constant) is used as is; a uniform law through a Gauss–Legendre rule of ``nodes`` points.

Prior of the window (the channel's ``prehistory``): ``"prior"`` iid :math:`N(\bar x_0, P_0)` blocks,
``"hold"`` :math:`x_{-s} = x_0` (fully correlated blocks), ``"zero"`` zero blocks.

Time convention (package-wide): :math:`x_0` is the prior, :math:`y_1` at index 0, result row k-1
holds :math:`\hat x_{k|k}` (the top block of :math:`\hat\xi_{k|k}`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._validation import ValidationError, check_instance
from ..channels.laws import PMF, Gaussian, Uniform
from ..channels.protocol import ProtocolChannel
from ..models.linear import LinearSystem
from .assumed_density import (
    ADF_OPTIONS,
    AssumedDensityFamily,
    AugmentedWindow,
    censored_channel_update,
    merge_gaussians,
)
from .registry import family_entry, register

__all__ = ["ProtocolAssumedDensityFilter", "failure_nodes"]


def failure_nodes(law: Any, nodes: int = 16) -> tuple[np.ndarray, np.ndarray]:
    r"""Support points :math:`\lambda_j` and probabilities :math:`\pi_j` of a failure-gain law.

    A :class:`~tobitkf.channels.laws.PMF` gives its own; a constant (zero-variance Gaussian) one point;
    a :class:`~tobitkf.channels.laws.Uniform` on [a, b] the ``nodes``-point Gauss–Legendre rule (exact
    for polynomial moments up to degree 2 nodes - 1).

    Raises
    ------
    ValidationError
        Any other law (no finite representation).
    """
    if isinstance(law, PMF):
        return np.asarray(law.values, float).ravel(), np.asarray(law.probs, float).ravel()
    if isinstance(law, Gaussian) and float(law.variance) == 0.0:
        return np.atleast_1d(float(law.mean)), np.ones(1)
    if isinstance(law, Uniform):
        x, w = np.polynomial.legendre.leggauss(nodes)
        lo, hi = float(law.low), float(law.high)
        return lo + (hi - lo) * (x + 1) / 2, w / 2
    raise ValidationError(
        f"failures: the assumed-density protocol filter needs a PMF, constant or Uniform failure "
        f"law, got {type(law).__name__}"
    )


class ProtocolAssumedDensityFilter(AugmentedWindow, AssumedDensityFamily):
    r"""Protocol-channel filter that conditions on the failure outcome (see the module docstring).

    Parameters
    ----------
    system : LinearSystem
        The model; one row of C per sensor, diagonal R with positive entries.
    channel : ProtocolChannel
        Round-Robin schedule, window ℓ, failure law(s), threshold τ, prehistory.
    covariance_update : {"standard", "joseph", "square_root"}, default "standard"
        Covariance form of each outcome's update (and of the merge: the square root merges factors).
    nodes : int, default 16
        Gauss–Legendre points for a uniform failure law.
    backend : {"auto", "numba", "numpy"}, default "auto"
        ``"auto"``: :meth:`filter` through the compiled loop (:mod:`tobitkf.filters._compiled_loop`) when numba
        is installed and the options are covered (the standard covariance form, time-invariant system matrices, failure laws with the same number of outcomes for every sensor), else the numpy loop; ``"numba"``
        insists on it; ``"numpy"`` never uses it (the same numbers, tested to 1e-12). The numpy loop takes each
        failure outcome's moments from the compiled censored block (the function
        :func:`~tobitkf.filters._compiled_moments.protocol_block` applies per outcome), on every backend.

    Raises
    ------
    ValidationError
        A failure law without a finite representation, non-diagonal or non-positive R, bad option; (when
        filtering) a control input ``u`` with a system that has a feedthrough D (the reading (2) has none:
        u enters through Bu).
    ShapeError
        A system whose C does not have one row per sensor.

    Notes
    -----
    Extras per step: ``failure_posterior`` (..., T, J), the posterior probability of each failure
    outcome of the scheduled sensor; ``p_uncensored`` (..., T), the prior probability of a reading
    above τ; ``log_likelihood`` (..., T), the log-density of the reading under the Gaussian prior.
    Cost: J outcome updates (J = 3 for the example's law) and one merge per step.

    Examples
    --------
    >>> import numpy as np, tobitkf as tk
    >>> from tobitkf.channels.protocol import LAMBDA_BASE
    >>> w = 0.052 * np.pi
    >>> sys = tk.LinearSystem(A=[[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]], C=np.eye(2),
    ...                       Q=0.0025 * np.eye(2), R=np.eye(2), x0=[5.0, 0.0], P0=np.eye(2))
    >>> ch = tk.ProtocolChannel(2, window=2, failures=LAMBDA_BASE, threshold=0.0)
    >>> data = tk.simulate(sys, 30, 50, channel=ch, seed=0)
    >>> out = tk.ProtocolAssumedDensityFilter(sys, ch).filter(data.y)
    >>> out.mean.shape, out.extras["failure_posterior"].shape
    ((50, 30, 2), (50, 30, 3))
    """

    _name = "ProtocolAssumedDensityFilter"

    def __init__(
        self,
        system: LinearSystem,
        channel: ProtocolChannel,
        *,
        covariance_update: str = "standard",
        nodes: int = 16,
        backend: str = "auto",
    ):
        self._configure(system, covariance_update, backend)
        check_instance(channel, ProtocolChannel, "channel")
        channel.check(system)
        if isinstance(nodes, bool) or not isinstance(nodes, (int, np.integer)) or nodes < 1:
            raise ValidationError(f"nodes: expected a positive integer, got {nodes!r}")
        self.channel, self.m = channel, 1  # one reading per step: the scheduled sensor's
        self.ell = channel.window
        self.nx = system.n * (self.ell + 1)
        self.laws = [failure_nodes(law, int(nodes)) for law in channel.laws]

    _compiled_spec = "protocol_spec"
    _positive_noise = "the protocol filter"
    _variances = AssumedDensityFamily._noise_at  # the name the compiled loop's arrays read

    def _initial(self, N, x0, P0, batch):
        return self._window_prior(N, x0, P0, batch, self.channel.prehistory)

    def _project(self, k, xp, Pp, Sp, y, u=None):
        if u is not None and self.system.D is not None:
            raise ValidationError(
                "u: the protocol channel's reading (2) has no feedthrough D u (it would be ambiguous whether "
                "D u is scaled by the failure gain); give the system no D (a control input enters through Bu only)"
            )
        order = self.channel.schedule.order
        h = int(order[(k - 1) % order.size]) - 1
        Cc = np.tile(self.system.measurement(k)[h], self.ell + 1)
        r = float(self._noise_at(k)[h])
        vals, probs = self.laws[h]
        N = xp.shape[0]
        yk = y[:, 0]
        tau = self.channel.threshold
        xs, Ps, Ss, lls, pus = [], [], [], [], []
        for lam in vals:
            x_j, P_j, S_j, pu, ll = censored_channel_update(
                xp, Pp, Sp, yk, lam * Cc, r, tau, np.inf, form=self.covariance_update, compiled=True
            )  # each outcome's moments from the compiled censored block (protocol_block's per outcome)
            xs.append(x_j)
            Ps.append(np.broadcast_to(P_j, (N,) + P_j.shape[1:]))
            Ss.append(None if S_j is None else np.broadcast_to(S_j, (N,) + S_j.shape[1:]))
            lls.append(ll)
            pus.append(pu)
        with np.errstate(divide="ignore"):
            logw = np.log(probs)[:, None] + np.stack(lls)  # (J, N)
        top = logw.max(0)
        w = np.exp(logw - top)
        tot = w.sum(0)
        w /= tot
        x, P, S = merge_gaussians(
            w, np.stack(xs), np.stack(Ps), None if self.covariance_update != "square_root" else np.stack(Ss)
        )
        missing = np.isnan(yk)
        if missing.any():  # a missing reading leaves the prior exactly
            x = np.where(missing[:, None], xp, x)
            P = np.where(missing[:, None, None], Pp, P)
            if S is not None:
                S = np.where(missing[:, None, None], Sp, S)
        extras = {
            "failure_posterior": w.T.copy(),
            "p_uncensored": probs @ np.stack(pus),
            "log_likelihood": np.where(missing, 0.0, np.log(tot) + top),
        }
        return x, P, S, extras

    def _check_record(self, y2, u2, k0, name="y"):
        self.system.check_horizon(k0 + y2.shape[1])
        tau = self.channel.threshold
        with np.errstate(invalid="ignore"):
            bad = y2 < tau - 1e-12 * max(1.0, abs(tau))
        if bad.any():
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            raise ValidationError(
                f"y: reading {y2[idx]:.6g} at index {idx} lies below the protocol threshold tau = {tau:.6g}"
            )

    def __repr__(self) -> str:
        return f"ProtocolAssumedDensityFilter({self.channel!r}, covariance_update={self.covariance_update!r})"


register(
    family_entry(
        ProtocolAssumedDensityFilter,
        "protocol-channel filter conditioning on the failure outcome (beyond the sources)",
        ("protocol",),
        options={**ADF_OPTIONS, "nodes": int},
    )
)
