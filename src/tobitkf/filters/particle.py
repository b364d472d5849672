r"""Particle filter: the Bayes-optimal yardstick for every channel of the sources.

Not in the sources; a sequential Monte Carlo (SMC) estimate of the exact posterior
:math:`p(x_k \mid y_{1:k})` of the package's models, against which the Gaussian approximations
(TKF, fading TKF, protocol TKF, the assumed-density filters) are measured (Gordon, Salmond & Smith
1993; Doucet, Godsill & Andrieu 2000; Doucet & Johansen 2011).

Model. The linear Gaussian dynamics of :class:`~tobitkf.LinearSystem`,
:math:`x_k = A_{k-1}x_{k-1} + B^u_ku_k + w_{k-1}`, :math:`w_{k-1} \sim N(0, B_{k-1}Q_{k-1}B_{k-1}^T)`,
:math:`x_0 \sim N(\bar x_0, P_0)`, and one channel of :mod:`tobitkf.channels`, each giving, for a
state (history) :math:`\xi_k`, a *latent* reading that is normal per channel l, possibly as a
mixture over a discrete channel outcome j with probability :math:`\pi_j`,

.. math::

    y^*_{k,l} \mid \xi_k, j \sim N(\mu_{jl}(\xi_k), s_{jl}^2(\xi_k)), \qquad
    y_{k,l} = \mathrm{clip}(y^*_{k,l}, l_{k,l}, h_{k,l}),

* Censoring (or none), state :math:`x_k`: :math:`\mu = C_kx_k + D_ku_k`, :math:`s^2 = R_{k,ll}`.
* RiceFading of order L, state :math:`x_k, \dots, x_{k-L}`:
  :math:`\mu = \sum_{s\le\min(L,k)}\bar\vartheta(s)C_{k-s}x_{k-s}`,
  :math:`s^2 = \sum_s\tilde\vartheta(s)(C_{k-s}x_{k-s})^2 + R_{ll}` (Gaussian coefficients, exact;
  other laws: the coefficients are drawn per particle and :math:`s^2 = R_{ll}`).
* ProtocolChannel, state :math:`x_k, \dots, x_{k-\ell}`: the scheduled sensor :math:`h = \bar h_k`
  (Round-Robin), :math:`\mu_j = \lambda_jC_h\sum_{s=0}^{\ell}x_{k-s}`, :math:`s^2 = R_{hh}`, the
  failure gain :math:`\Lambda = \lambda_j` with probability :math:`\pi_j` (a continuous law: drawn per
  particle), the reading :math:`y = \max(z, \tau)`.
* RandomSaturation, state :math:`x_k`: per sensor i the modes :math:`\mu = \sigma(C_ix_k)`,
  :math:`C_ix_k`, 0 with probabilities :math:`\mu_i`, :math:`(1-\mu_i)\nu_i`,
  :math:`(1-\mu_i)(1-\nu_i)`, :math:`s^2 = R_{ii}`.

(Geng et al. 2017 (2); Geng et al., protocol TKF (2)–(7); Wang, Shen & Liu (2)–(3); Miller (3.18)).
R must be diagonal with positive entries (the channels' noises are independent).

Likelihood of one reading (exact; through ``scipy.special.log_ndtr``, finite at 40 σ and beyond):

.. math::

    \log p(y_{k,l} \mid \xi_k) = \log\sum_j \pi_j \begin{cases}
      \phi\big((y-\mu_j)/s_j\big)/s_j & l < y < h \\
      \Phi\big((l-\mu_j)/s_j\big) & y = l \text{ (censored below)} \\
      \Phi\big((\mu_j-h)/s_j\big) & y = h \text{ (censored above)} \end{cases}

and a NaN reading (missing) contributes nothing. Readings within ``1e-12 max(1, |limit|)`` of a
finite limit count as censored (as :meth:`~tobitkf.Censoring.censored_mask`).

Proposals (``proposal``):

* ``"prior"`` (the bootstrap filter): :math:`\xi_k \sim p(\xi_k \mid \xi_{k-1})`, incremental weight
  :math:`p(y_k \mid \xi_k)`.
* ``"optimal"`` (the locally optimal proposal :math:`p(x_k \mid x_{k-1}, y_k)`, Doucet, Godsill &
  Andrieu 2000, §II.D), where it has a closed form: linear readings with censoring, the
  protocol channel with a discrete failure law, and random saturation (a five-piece mixture per
  sensor, ``_Saturation.propose``; with censoring, one piece's mass by a one-draw estimate). The latent reading is sampled with the state: the
  channels are processed in sequence (diagonal R), each conditioning the Gaussian
  :math:`p(x_k \mid x_{k-1}, y^*_{k,1..l-1})` on :math:`y^*_{k,l}`; an uncensored channel on its value
  (weight :math:`N(y; \mu, s^2)`), a censored one on a draw of the latent reading from its truncated
  normal (weight its mass :math:`\Phi(\cdot)`, the GHK simulator of a multivariate normal
  probability); the failure outcome j of the protocol channel is drawn from its posterior. For one
  channel this is exactly :math:`p(x_k \mid x_{k-1}, y_k)` with weight :math:`p(y_k \mid x_{k-1})`.
* ``"rao_blackwellised"`` (the protocol channel with discrete failure laws; a mixture Kalman filter,
  Chen & Liu 2000; Doucet, de Freitas, Murphy & Russell 2000): the window
  :math:`\xi_k = (x_k, \dots, x_{k-\ell})` is not sampled but carried per particle as a Gaussian
  :math:`N(m^i_k, P^i_k)`; the particles sample only the failure outcomes :math:`j_{1:k}` and, for censored
  readings, the latent readings :math:`z_k \le \tau` (data augmentation, as Chib 1992 for the Tobit
  model). Given both, the model is linear Gaussian: :math:`z_k = \lambda_jH_k\xi_k + v_k`,
  :math:`H_k = [C_h, \dots, C_h]`, so each particle runs the augmented Kalman filter. Per step and particle,
  with the prediction :math:`m^-, P^-` (block shift, :func:`~tobitkf.filters.core.shift_predict`),
  :math:`b = H_km^-`, :math:`s = H_kP^-H_k^T`, :math:`S_j = \lambda_j^2s + R_{hh}`:

  .. math::

      p(y_k \mid j, \cdot) = \begin{cases} N(y_k;\ \lambda_jb,\ S_j) & y_k > \tau \\
        \Phi\big((\tau - \lambda_jb)/\sqrt{S_j}\big) & y_k = \tau \end{cases}, \qquad
      \tilde w = \sum_j\pi_jp(y_k \mid j, \cdot),

  j drawn with probability :math:`\pi_jp(y_k \mid j, \cdot)/\tilde w`, z = y or a draw of
  :math:`N(\lambda_jb, S_j)` truncated to :math:`(-\infty, \tau]`, and the update
  :math:`m = m^- + \lambda_jP^-H_k^T(z - \lambda_jb)/S_j`,
  :math:`P = P^- - \lambda_j^2P^-H_k^TH_kP^-/S_j`. This is the exact (optimal) proposal of the collapsed
  model, with incremental weight :math:`p(y_k \mid j_{1:k-1}, z_{1:k-1}, y_{1:k-1})`; the estimate is the
  mixture's moments :math:`\sum_iW_im^i`, :math:`\sum_iW_i(P^i + (m^i - \bar m)(m^i - \bar m)^T)`.
  Nothing continuous is left to degenerate but the sampled latent readings, which cures the path
  degeneracy of the window states (:math:`x_{k-1..k-\ell}` are fixed per particle under ``"optimal"``):
  on the protocol example's data the asymptotic variance factor of the mean (the squared error against a
  converged reference, times :math:`N_p`, over the posterior variance) is about 1 instead of 13–25, at
  3–4 times the cost per particle. Memory :math:`O(N N_p n_x^2)` (a covariance per particle).
  Without failures and censoring every particle is the augmented Kalman filter (exact, tested).
* ``"linearised"`` (a :class:`~tobitkf.NonlinearSystem` read through a channel with a ``region``): the
  ``"optimal"`` proposal of the readings linearised about each particle's prediction, weighted exactly
  (:mod:`tobitkf.filters.particle_nonlinear`).
* ``"auto"`` (default): ``"optimal"`` where available, else ``"prior"``.

Weights are kept as logarithms, normalized every step; the run's particles are resampled
(systematic resampling, Kitagawa 1996) when the effective sample size
:math:`1/\sum_i W_i^2` falls below ``resample_threshold`` times the particle count. The estimate
of the log-likelihood is :math:`\sum_k \log\sum_i W^i_{k-1}\tilde w^i_k` (unbiased in the
likelihood, Del Moral 2004).

Time convention (package-wide): :math:`x_0 \sim N(\bar x_0, P_0)` is the prior, :math:`y_1` is at
index 0, and result row k-1 holds the particle mean and covariance of :math:`p(x_k \mid y_{1:k})`
(``mean``, ``cov``) and of the prediction :math:`p(x_k \mid y_{1:k-1})` (``pred_mean``,
``pred_cov``: the linear prediction of the weighted particle moments). The random numbers come
from one ``numpy.random.Generator`` built from ``seed``; its state travels in the
:class:`~tobitkf.filters.core.FilterState`, so a pickled state resumes with the same draws.

Symbols: ``particles`` = the number of particles :math:`N_p`, ``ess`` = effective sample size,
``log_likelihood`` = :math:`\log\hat p(y_k \mid y_{1:k-1})` per step.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._linalg import symmetrize
from .._validation import ValidationError, as_float_array, check_instance, check_int, check_memory
from ..channels.base import Channel
from ..channels.censoring import Censoring
from ..models.linear import LinearSystem
from ._backend import BACKENDS, system_gap, use_compiled
from ._particle_models import (
    SYSTEM_MODELS,
    _build_model,
    _Contract,
    _diag_sigma,
    _Fading,
    _Linear,
    _Protocol,
    _Saturation,
)
from ._particle_rng import generator as _generator
from ._particle_rng import rng_state as _rng_state
from ._readings import censored_log_likelihood
from .core import Estimator, FilterState, check_prior
from .kalman import LinearGaussianFamily

__all__ = ["ParticleFilter", "PROPOSALS", "systematic_resample", "censored_log_likelihood"]

PROPOSALS = ("auto", "optimal", "prior", "rao_blackwellised", "linearised")


# --------------------------------------------------------------------------- resampling


def systematic_resample(weights: np.ndarray, u: np.ndarray) -> np.ndarray:
    r"""Systematic resampling (Kitagawa 1996) of every row of ``weights``, batched.

    Row r draws the indices :math:`i` with :math:`\sum_{j<i} W_j \le (u_r + p)/N_p < \sum_{j\le i} W_j`,
    :math:`p = 0..N_p-1`: each particle is copied :math:`\lfloor N_pW_i\rfloor` or
    :math:`\lceil N_pW_i\rceil` times (the lowest-variance of the standard schemes, Douc & Cappé 2005).

    Parameters
    ----------
    weights : (M, Np) ndarray
        Normalized weights (each row sums to 1).
    u : (M,) ndarray
        One uniform draw in [0, 1) per row.

    Returns
    -------
    (M, Np) int ndarray
        The ancestor index of each new particle.

    Examples
    --------
    >>> systematic_resample(np.array([[0.5, 0.25, 0.25, 0.0]]), np.array([0.5])).tolist()
    [[0, 0, 1, 2]]
    """
    M, Np = weights.shape
    cw = np.cumsum(weights, axis=1)
    cw[:, -1] = 1.0
    rows = np.arange(M)[:, None]
    pos = (u[:, None] + np.arange(Np)) / Np
    flat = (cw + rows).ravel()
    idx = np.searchsorted(flat, (pos + rows).ravel(), side="right").reshape(M, Np) - rows * Np
    return np.clip(idx, 0, Np - 1)


# --------------------------------------------------------------------------- the estimator


class ParticleFilter(Estimator):
    r"""Particle filter for the package's models and channels (see the module docstring).

    Batched over runs and particles: the particles of N runs are one ``(N, Np, n_x)`` array; every
    step is a few array operations over all of them, one generator draws for all runs.

    Parameters
    ----------
    system : LinearSystem or NonlinearSystem
        The dynamics (and C, R, D of the readings). R must be diagonal and positive. A
        :class:`~tobitkf.NonlinearSystem` runs the bootstrap proposal (or ``"linearised"``) with one contract
        channel, or with :class:`~tobitkf.RiceFading` of any order or :class:`~tobitkf.RandomSaturation`, either
        with a Censoring (:mod:`tobitkf.filters.particle_nonlinear`).
    channel : Channel or sequence of Channel, optional
        :class:`~tobitkf.Censoring` (one-, two-sided, time-varying; several regions as stacked
        channels, :func:`~tobitkf.multi_region`), :class:`~tobitkf.RiceFading` (with a Censoring),
        :class:`~tobitkf.ProtocolChannel` or :class:`~tobitkf.RandomSaturation` (with a Censoring), or
        any channel of the measurement contract (:class:`~tobitkf.Quantizer`, a channel of your own:
        :mod:`tobitkf.channels.base`; the locally optimal proposal when it has a ``region``);
        None: linear Gaussian readings.
    censoring : Censoring, optional
        The censoring, given separately (the same as adding it to ``channel``).
    particles : int, default 1000
        Particles per run :math:`N_p`.
    resample_threshold : float in [0, 1], default 0.5
        Resample a run when its effective sample size is below this fraction of :math:`N_p`
        (0: never, 1: every step).
    proposal : {"auto", "optimal", "prior", "rao_blackwellised", "linearised"}, default "auto"
        See the module docstring; ``"optimal"`` is refused for channels without a closed form
        (fading, protocol with a continuous failure law, every reading of a NonlinearSystem),
        ``"rao_blackwellised"`` for every channel but the protocol channel with discrete failure laws,
        ``"linearised"`` for everything but a NonlinearSystem read through one channel with a ``region``. With ``"rao_blackwellised"`` the
        ``particles`` of a state's ``carry`` are the particles' Gaussian means (and ``covariances``
        their covariances).
    linearisation_steps : int >= 1, default 1
        Where ``proposal="linearised"`` linearises h for each particle: 1 about its prediction
        :math:`\mu = f(x_{k-1}, k-1)` (the extended Kalman update); s > 1 about the point reached by s - 1
        Gauss–Newton steps on the exact readings from there (the iterated extended Kalman update, towards the
        mode of :math:`p(x_k \mid x_{k-1}, y_k)`). The weights are exact for every choice.
    seed : int, SeedSequence, Generator or None, default None
        Source of the random numbers. Every :meth:`init` restarts from it, so ``filter`` called twice
        gives the same numbers; None draws fresh entropy once, when the filter is built.
    backend : {"auto", "numba", "numpy"}, default "auto"
        ``filter`` of a time-invariant system without input runs compiled
        (:mod:`tobitkf.filters._compiled_particle`: the same equations, in blocks of runs, drawing from the
        same generator in its own order, so equal to the numpy loop in law, and to rounding for the same
        numbers) under ``"auto"`` when numba imports, and always under ``"numba"``, for these models:
        linear readings, censored or not (both proposals); a channel of the measurement contract whose
        likelihood is its ``region``'s (:class:`~tobitkf.Quantizer`, a dead band, a channel of your own; both
        proposals); random saturation and Rice fading with Gaussian coefficients, either with a Censoring
        (the bootstrap proposal ``"prior"``). ``"numba"`` refuses the rest, which runs the numpy loop: the
        locally optimal proposal of random saturation, fading with other coefficient laws, the protocol
        channel, channels with a likelihood of their own and nonlinear models. ``"numpy"`` always runs the
        numpy loop. ``step`` is numpy. The two backends give different particles for the same seed.

    Raises
    ------
    ValidationError
        Unknown channel pieces, more than one reading model, a non-diagonal or non-positive R, a bad
        particle count, threshold, proposal, seed or backend.

    Notes
    -----
    ``filter`` returns the common :class:`~tobitkf.filters.core.FilterResult`: ``mean``/``cov``
    the weighted particle moments of :math:`x_k \mid y_{1:k}`, ``pred_mean``/``pred_cov`` their
    linear prediction, and extras ``ess`` (effective sample size after the reading),
    ``resampled`` (bool) and ``log_likelihood`` (the step's :math:`\log\hat p(y_k\mid y_{1:k-1})`),
    each (..., T). :meth:`log_likelihood` sums the last.

    Memory: :math:`O(N N_p n_x)` for the particles, independent of T (``outputs="last"`` records
    nothing per step). Cost per particle and step: a draw, a matrix-vector product and one
    ``log_ndtr`` or normal density per channel (see ``benchmarks/bench_particle.py``).

    Examples
    --------
    Without censoring the particle filter converges to the Kalman filter:

    >>> import numpy as np, tobitkf as tk
    >>> sys = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.1]], R=[[0.2]], x0=[0.0], P0=[[1.0]])
    >>> data = tk.simulate(sys, 20, 1, seed=1)
    >>> pf = tk.ParticleFilter(sys, particles=20000, seed=2).filter(data.y)
    >>> kf = tk.KalmanFilter(sys).filter(data.y)
    >>> bool(np.abs(pf.mean - kf.mean).max() < 0.02)
    True

    References
    ----------
    .. [1] N. J. Gordon, D. J. Salmond, A. F. M. Smith, Novel approach to nonlinear/non-Gaussian
       Bayesian state estimation, IEE Proc. F 140(2), 1993.
    .. [2] A. Doucet, S. Godsill, C. Andrieu, On sequential Monte Carlo sampling methods for Bayesian
       filtering, Statistics and Computing 10, 2000.
    .. [3] G. Kitagawa, Monte Carlo filter and smoother for non-Gaussian nonlinear state space models,
       J. Comput. Graph. Stat. 5(1), 1996.
    .. [4] R. Chen, J. S. Liu, Mixture Kalman filters, J. R. Stat. Soc. B 62(3), 2000.
    .. [5] A. Doucet, N. de Freitas, K. Murphy, S. Russell, Rao-Blackwellised particle filtering for dynamic
       Bayesian networks, UAI 2000.
    .. [6] S. Chib, Bayes inference in the Tobit censored regression model, J. Econometrics 51, 1992.
    """

    _name = "ParticleFilter"
    _filter_doc = """Filter the readings ``y`` (..., T, m) with the particle filter: each step propagates the particles,
    weights them by the channel's likelihood of the reading and resamples when the effective sample size falls
    below ``resample_threshold`` times the particle count; the mean and covariance are those of the weighted
    particles."""
    _filter_params = {
        "y": "(..., T, m) array_like\n"
        "    Readings y_1..y_T (m = 1 for the protocol channel: the scheduled sensor's reading); NaN = missing.",
        "u": "(T, p) or (..., T, p) array_like, optional\n    Control inputs u_1..u_T.",
        "state": "FilterState, optional\n    Continue from this state (e.g. ``result.final``), generator included.",
    }
    _filter_raises = (
        "a reading outside its censoring limits; a control input ``u`` with a system that has a feedthrough D on"
        " the protocol or random-saturation channel (their readings have none: u enters through Bu)"
    )
    k0 = 0

    def __init__(
        self,
        system: LinearSystem,
        channel: Any = None,
        *,
        censoring: Censoring | None = None,
        particles: int = 1000,
        resample_threshold: float = 0.5,
        proposal: str = "auto",
        seed: Any = None,
        backend: str = "auto",
        linearisation_steps: int = 1,
    ):
        builder = next((b for t, b in SYSTEM_MODELS.items() if isinstance(system, t)), None)
        if builder is None:
            check_instance(system, LinearSystem, "system")
        if censoring is not None:
            check_instance(censoring, Censoring, "censoring")
        if isinstance(particles, bool) or not isinstance(particles, (int, np.integer)) or particles < 1:
            raise ValidationError(f"particles: expected a positive integer, got {particles!r}")
        thr = as_float_array(resample_threshold, "resample_threshold", ndim=0)
        if not 0.0 <= float(thr) <= 1.0:
            raise ValidationError(f"resample_threshold: expected a fraction in [0, 1], got {float(thr)}")
        if proposal not in PROPOSALS:
            raise ValidationError(f"proposal: expected one of {', '.join(map(repr, PROPOSALS))}, got {proposal!r}")
        if backend not in BACKENDS:
            raise ValidationError(f"backend: expected one of {', '.join(map(repr, BACKENDS))}, got {backend!r}")
        self.backend = backend
        self.system = system
        if builder is not None:  # another kind of model (a NonlinearSystem: filters.particle_nonlinear)
            self.model = builder(system, channel, censoring)
        else:
            self.model = _build_model(system, channel, censoring)
        if proposal == "optimal" and not self.model.optimal:
            raise ValidationError(
                f"proposal: 'optimal' has no closed form for {self.model.label} readings (use 'auto' or 'prior'"
                + (", or 'linearised', its linearisation about each particle)" if self.model.linearised else ")")
            )
        if proposal == "linearised" and not self.model.linearised:
            raise ValidationError(
                "proposal: 'linearised' (the optimal proposal of readings linearised about each particle) is for a "
                "NonlinearSystem read through one channel with a region() (Censoring, Quantizer, ...), not for "
                f"{self.model.label} readings (use 'auto' or 'prior')"
            )
        steps = check_int(linearisation_steps, "linearisation_steps", minimum=1, maximum=100)
        if steps != 1 and proposal != "linearised":
            raise ValidationError(
                f"linearisation_steps: {steps} steps set the linearisation of proposal='linearised', not of {proposal!r}"
            )
        self.linearisation_steps = self.model.steps = steps
        if proposal == "rao_blackwellised" and not (isinstance(self.model, _Protocol) and self.model.optimal):
            raise ValidationError(
                "proposal: 'rao_blackwellised' is implemented for the protocol channel with discrete failure "
                f"laws only, not for {self.model.label} readings (use 'auto')"
            )
        if not system.R.varying:
            _diag_sigma(system, 1, "its channels")
        self.proposal = ("optimal" if self.model.optimal else "prior") if proposal == "auto" else proposal
        self.particles = int(particles)
        self.resample_threshold = float(thr)
        self._rng0 = _rng_state(seed)
        self.n, self.m = system.n, self.model.m
        # refused before any cloud is drawn: the particles of one run must fit in memory
        check_memory(self._bytes_per_run(), "particles", f"{self.particles} particles of one run")

    def _bytes_per_run(self) -> int:
        """Bytes of one run's state: its cloud (the particles, their log-weights and a resampling copy of both)
        and, for the Rao-Blackwellised proposal, a covariance per particle, besides the mean and covariance."""
        nx = self._state_dim()
        per = nx + 1 + (nx * nx if self.proposal == "rao_blackwellised" else 0)
        return 8 * (2 * self.particles * per + nx + nx * nx)

    # the linear-system boundary checks are those of the Gaussian families
    _prepare_inputs = LinearGaussianFamily._prepare_inputs
    _step_input = LinearGaussianFamily._step_input

    def _compiled_gap(self, u) -> str | None:
        """Why the compiled loop (:mod:`tobitkf.filters._compiled_particle`) cannot run, or None."""
        model, kind = self.model, type(self.model)
        if kind not in (_Linear, _Saturation, _Fading, _Contract):
            return (
                f"{model.label} readings (compiled: linear readings with censoring, random saturation, Rice fading "
                "with Gaussian coefficients, channels whose likelihood is their region's)"
            )
        if kind in (_Saturation, _Fading) and self.proposal != "prior":
            return f"the {self.proposal!r} proposal of {model.label} readings (compiled: their bootstrap 'prior')"
        if kind is _Fading and not model.gaussian:
            return "Rice fading with coefficients that are not Gaussian (drawn per particle)"
        if kind is _Contract:
            ch = type(model.channel)
            if ch.region is Channel.region or ch.reading_log_likelihood is not Channel.reading_log_likelihood:
                return f"{model.label} readings (compiled: a channel whose likelihood is its region's interval mass)"
        return system_gap(self.system, u)

    def _compiled_filter(self, y2, u2, state, want, batch, step_options=None):
        if not use_compiled(self.backend, self._compiled_gap(u2), "the particle filter"):
            return None
        from ._compiled_particle import filter_blocks

        return filter_blocks(self, y2, state, want, batch)

    def _feedthrough(self, k, u):
        if u is None or self.system.D is None:
            return 0.0
        if not self.model.feedthrough:
            what = "protocol" if isinstance(self.model, _Protocol) else "random-saturation"
            raise ValidationError(
                f"u: the {what} channel's reading has no feedthrough D u (the simulator does not add it "
                "either); give the system no D (a control input enters through Bu only)"
            )
        return u @ self.system.D.at(k).T

    def _state_dim(self) -> int:
        return self.model.nx

    def _check_record(self, y2, u2, k0, name="y"):
        self.system.check_horizon(k0 + y2.shape[1])
        self.model.check_record(y2, k0 + 1)

    def _initial(self, N, x0, P0, batch):
        x, P = check_prior(self.system, x0, P0, N, batch)
        rng = _generator(dict(self._rng0))
        lw = np.full((N, self.particles), -np.log(self.particles))
        carry: dict[str, Any] = {}
        if self.proposal == "rao_blackwellised":
            assert isinstance(self.model, _Protocol)
            X, C = self.model.rb_initial(N, self.particles, x, P)
            carry["covariances"] = C
            xm, Pm = _mixture_moments(X, C, np.exp(lw))
        else:
            X = self.model.initial(rng, N, self.particles, x, P)
            xm, Pm = _moments(X, np.exp(lw))
        carry.update(particles=X, log_weights=lw, rng=rng.bit_generator.state, log_likelihood=np.zeros(N))
        return xm, Pm, carry

    def _step_arrays(self, k, x, P, S, carry, y, u, options=None):
        rng = _generator(carry["rng"])
        X, lw = carry["particles"], carry["log_weights"]
        b = 0.0 if u is None or self.system.Bu is None else u @ self.system.Bu.at(k).T
        b = u if u is not None and getattr(self.model, "takes_input", False) else b  # an f(x, k, u): u_k itself
        dy = self._feedthrough(k, u)
        dy = u if u is not None and getattr(self.model, "feedthrough_input", False) else dy  # an h(x, k, u): u_k
        xp, Pp = self.model.predict_moments(k, x, P, b)
        Cn = None
        if self.proposal == "rao_blackwellised":
            assert isinstance(self.model, _Protocol)
            Xn, Cn, inc = self.model.rb_step(rng, k, X, carry["covariances"], y, b)
        elif self.proposal in ("optimal", "linearised"):
            Xn, inc = self.model.propose(rng, k, X, y, b, dy, xp, Pp)
        else:
            Xn = self.model.propagate(rng, k, X, b)
            inc = self.model.log_likelihood(rng, k, Xn, y, dy)
        W, tot, lw_new, ll = reweight(lw, inc)
        W /= tot[:, None]
        xm, Pm = _moments(Xn, W) if Cn is None else _mixture_moments(Xn, Cn, W)
        ess = 1.0 / np.einsum("rp,rp->r", W, W)
        ur = rng.random(X.shape[0])
        res = ess < self.resample_threshold * self.particles
        if res.any():
            rows = np.flatnonzero(res)
            idx = systematic_resample(W[rows], ur[rows])
            Xn[rows] = np.take_along_axis(Xn[rows], idx[..., None], axis=1)
            if Cn is not None:
                Cn[rows] = np.take_along_axis(Cn[rows], idx[..., None, None], axis=1)
            lw_new[rows] = -np.log(self.particles)
        carry = {
            **({} if Cn is None else {"covariances": Cn}),
            "particles": Xn,
            "log_weights": lw_new,
            "rng": rng.bit_generator.state,
            "log_likelihood": carry["log_likelihood"] + ll,
        }
        extras = {"ess": ess, "resampled": res, "log_likelihood": ll}
        return xm, Pm, None, carry, xp, Pp, extras

    def log_likelihood(
        self,
        y: Any,
        *,
        u: Any = None,
        x0: Any = None,
        P0: Any = None,
        state: FilterState | None = None,
        per_step: bool = False,
    ) -> np.ndarray:
        r"""Estimate of :math:`\log p(y_{1:T})` per run, shaped as :meth:`tobitkf.KalmanFilter.log_likelihood`.

        .. math::

            \log\hat p(y_{1:T}) = \sum_{k=1}^T \log\hat p(y_k \mid y_{1:k-1}), \qquad
            \hat p(y_k \mid y_{1:k-1}) = \sum_{i=1}^{N_p} W_{k-1}^{(i)}\,
            \frac{p(y_k \mid x_k^{(i)})\,p(x_k^{(i)} \mid x_{k-1}^{(i)})}{q(x_k^{(i)} \mid x_{k-1}^{(i)}, y_k)},

        the weighted mean of the incremental weights (the prior proposal: :math:`p(y_k \mid x_k^{(i)})`;
        censored readings by their mass, ``log_ndtr``; NaN readings skipped). The product over k is an
        unbiased estimate of the likelihood (Del Moral 2004; Doucet & Johansen 2011 §4.1); its logarithm
        is biased low by about half its variance, which is of order :math:`\kappa T/N_p`.

        Parameters
        ----------
        y : (..., T, m) array_like
            Readings; NaN = missing.
        u, x0, P0 : optional
            Inputs and a prior override, as :meth:`filter`.
        state : FilterState, optional
            Continue from this state: the sum then runs from the state's own start (the estimate of
            the whole record so far); the per-step terms are those of the new readings.
        per_step : bool, default False
            Return the per-step terms :math:`\log\hat p(y_k \mid y_{1:k-1})` (..., T) (the
            ``log_likelihood`` extras of :meth:`filter`) instead of their sum (...).

        Returns
        -------
        ndarray
            (...) or, with ``per_step``, (..., T); a 0-d value for one (T, m) record. ``-inf`` where no
            particle explains a reading.

        Raises
        ------
        ShapeError, ValidationError
            As :meth:`filter`.
        """
        if per_step:
            return self._run(y, u, x0, P0, outputs=("extras",), state=state).extras["log_likelihood"]
        res = self._run(y, u, x0, P0, outputs="last", state=state)
        final = res.final
        assert final is not None  # outputs="last" always records the final state
        ll = final.carry["log_likelihood"]
        return ll.reshape(final.batch_shape) if final.batch_shape else ll.reshape(())[()]

    def __repr__(self) -> str:
        return (
            f"ParticleFilter({self.model.label}, particles={self.particles}, "
            f"proposal={self.proposal!r}, resample_threshold={self.resample_threshold}"
            + ("" if self.linearisation_steps == 1 else f", linearisation_steps={self.linearisation_steps}")
            + ")"
        )


def reweight(lw: np.ndarray, inc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    r"""The Bayes step of the log-weights ``lw`` (N, P) of a particle set or a Gaussian sum by the readings'
    log-likelihoods ``inc`` (N, P): :math:`\ell_i = \log w_i + \log p_i(y)`, with :math:`t = \max_i \ell_i`
    the step's log-likelihood :math:`\log\sum_i e^{\ell_i} = t + \log\sum_i e^{\ell_i - t}` and the new
    log-weights :math:`\ell_i` minus it. A run that no member explains (every :math:`\ell_i = -\infty`) keeps
    its weights and reports :math:`-\infty`.

    Returns
    -------
    E : (N, P) the unnormalised weights :math:`e^{\ell_i - t}`; tot : (N,) their sums; lw : (N, P) the new
    log-weights; ll : (N,) the step's log-likelihood (:math:`-\infty` for a run no member explains).
    """
    lw_un = lw + inc
    top = lw_un.max(axis=1)
    dead = ~np.isfinite(top)
    if dead.any():  # no member explains the reading: keep the weights, report -inf
        lw_un[dead] = lw[dead]
        top = lw_un.max(axis=1)
    E = np.exp(lw_un - top[:, None])
    tot = E.sum(axis=1)
    ll_norm = np.log(tot) + top
    return E, tot, lw_un - ll_norm[:, None], np.where(dead, -np.inf, ll_norm)


def _mixture_moments(M: np.ndarray, C: np.ndarray, W: np.ndarray):
    r"""Mean (N, nx) and covariance (N, nx, nx) of the Gaussian mixture :math:`\sum_iW_iN(M_i, C_i)`:
    :math:`\bar m = \sum_iW_iM_i`, :math:`\sum_iW_i(C_i + (M_i - \bar m)(M_i - \bar m)^T)`."""
    mean, spread = _moments(M, W)
    within = np.einsum("rp,rpij->rij", W, C)
    return mean, symmetrize(spread + within)


def _moments(X: np.ndarray, W: np.ndarray):
    """Weighted mean (N, nx) and covariance (N, nx, nx) of particles X (N, Np, nx) with weights W (N, Np)
    (two passes: the mean, then the weighted outer products of the deviations, as batched GEMMs)."""
    mean = (W[:, None, :] @ X)[:, 0]
    d = X - mean[:, None, :]
    cov = np.swapaxes(d * W[..., None], 1, 2) @ d
    return mean, symmetrize(cov)
