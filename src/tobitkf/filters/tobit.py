r"""The Tobit Kalman filter (TKF): Kalman filtering of censored measurements.

Source: Miller (2015), §3.3.4, (3.18)–(3.43) and (3.55); our deviations: docs/sources/miller2015-ch1-4.md.
Two-sided limits per channel are ours (not in the source; docs/sources MA-20); the multi-region form is
Miller §6.6, (6.51)–(6.69) (docs/sources MB-35).

Model: :math:`x_k = A x_{k-1} + w_{k-1}`, :math:`y^*_k = Cx_k + v_k`,
:math:`y_k(l) = \mathrm{clip}(y^*_k(l), l_k(l), h_k(l))`, with diagonal R (Assumption A2, (3.36)).

Per step (all channel statistics at the *prior* mean, Assumption A1 (3.35)):

.. math::

    \bar x &= A\hat x_{k-1} + B^u u_k, \qquad \bar\Psi = A\Psi_{k-1}A^T + Q  &(3.20)\text{–}(3.21)\\
    \mu_l &= (C\bar x + Du_k)_l,\quad a_l = \frac{l(l)-\mu_l}{\sigma_l},\quad b_l = \frac{h(l)-\mu_l}{\sigma_l} \\
    E(\mathbf p) &= \mathrm{diag}(\Phi(b_l) - \Phi(a_l))  &(3.37)\\
    E(y)_l &= \Phi(a_l)\,l(l) + \gamma_l(\mu_l + \sigma_l\lambda_l) + \Phi(-b_l)\,h(l)  &(3.8)\\
    R_{uu} &= \mathrm{diag}(\mathrm{Var}[y^*_l \mid l < y^*_l < h])  &(3.41), (3.11)\\
    R_{xe} &= \bar\Psi C^T E(\mathbf p), \qquad R_{ee} = E(\mathbf p) C\bar\Psi C^T E(\mathbf p) + R_{uu}  &(3.39), (3.40)\\
    K &= R_{xe}R_{ee}^{-1}, \quad \hat x = \bar x + K(y - E(y)), \quad \Psi = (I_n - K E(\mathbf p) C)\bar\Psi
      &(3.32), (3.22), (3.55)

Time convention: x_0 ~ N(x0, P0) is the prior; y_1 is stored at index 0; output
index k-1 holds x̂_{k|k} and Ψ_{k|k}.

Deviations from the source
--------------------------
* (3.42)/(3.43) print the covariance update as :math:`(I_{m\times m} - E(\mathbf p)KC)\Psi`,
  which does not conform when m != n; the code uses the order of (3.55),
  :math:`(I_n - KE(\mathbf p)C)\bar\Psi` (unavoidable repair, docs/sources MA-08).
* The noise term :math:`R_{uu}` of (3.41) is the *truncated* variance, justified in the
  text by the false identity Var[y|x] = Var[y|y>T] (docs/sources MA-09). It is the default
  (``noise_term="dissertation"``). ``noise_term="total_variance"`` uses the exact
  censored variance Var[y] (the "exact moments" route of later TKF papers) and
  ``noise_term="exact_pv"`` the exact :math:`E[p v^2]`; both are non-dissertation options.
  Known limit of ``"total_variance"``: when the prediction sits many σ inside the censored
  region (a = that distance), Var[y] shrinks like γσ²/a² while :math:`R_{xe}` shrinks only
  like γ, so the gain grows like a²/σ²; a reading that then comes back uncensored can throw
  the estimate far off, and the covariance stays finite and small, so the filter does not
  recover. On 30 random stable systems with one-sided censoring (n = 2..6, each output censored
  30-90 % on one side, 200 runs of 200 steps) it ended 13-1030x the assumed-density filter's RMSE
  on 14 of them; the dissertation's term and ``"exact_pv"`` stayed within 1.8x of it on all 30.
  Do not use it on one-sided censoring without checking it against the assumed-density filter.
  ``filter`` warns (once, with the step and the remedy) when the updates outgrow the filter's own
  covariance (:func:`tobitkf.filters.core.correction_statistic`): on exactly those 14 systems, and
  on none of the 30 for the other noise terms, the assumed-density filter or the KF; the online
  ``step`` does not check this.
* ``covariance_update="square_root"`` (a numerical device, ours, not in the source): the update above is a
  Kalman update with measurement matrix :math:`H = E(\mathbf p)C` and noise
  :math:`R_{uu}`, since :math:`R_{xe} = \bar\Psi H^T` and
  :math:`R_{ee} = H\bar\Psi H^T + R_{uu}` (3.39)–(3.40). :math:`R_{uu}` is diagonal and
  nonnegative for each noise term (a truncated variance, :math:`\mathrm{Var}[y]`, or
  :math:`E[pv^2] = \gamma(V_{tr} + (m_{tr}-\mu)^2)`), so all three take the square-root
  (QR array) form of :func:`tobitkf.filters.kalman.kalman_filter` with
  :math:`R^{1/2} = \mathrm{diag}(\sqrt{R_{uu}})`; (3.55) is then
  :math:`\Psi = \bar\Psi - KH\bar\Psi = SS^T`, positive semidefinite by construction.
* The right-censoring formulas of (3.54) are garbled in the source (pdf for cdf, no T
  term); the general two-sided statistics of :mod:`tobitkf.censored` reduce to the
  corrected (3.54) (docs/sources MA-10).

In the terms of the shared core (:mod:`tobitkf.filters.core`): the measurement prediction is
:math:`\hat y = E(y)`, :math:`H_0 = C`, the per-run channel scale :math:`E(\mathbf p)` and the
diagonal noise :math:`R_{uu}`, since :math:`R_{xe} = \bar\Psi (E(\mathbf p)C)^T` and
:math:`R_{ee} = E(\mathbf p)C\bar\Psi C^TE(\mathbf p) + R_{uu}` ((3.39)–(3.40)). The source
prescribes (3.55), so ``covariance_update="standard"`` is the default.

Symbols: ``mean`` = x̂, ``cov`` = Ψ, ``p_uncensored`` = E(p) (the sources' γ), ``expected_y`` = E(y).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .._validation import ShapeError, ValidationError, as_float_array, check_instance, diagonal_sigma
from ..channels.censoring import Censoring
from ..models.linear import LinearSystem
from ._backend import BACKENDS, check_square_root, check_threads, compiled_ok, run_split
from ._outputs import _empty, compiled_result, loop_array, loop_input, output_arrays, state_specs
from ._readings import censoring_sides
from .assumed_density import assumed_density_filter
from .core import (
    COVARIANCE_FORMS,
    FilterResult,
    FilterState,
    MeasurementPrediction,
    check_keywords,
    measurement_update,
    psd_sqrt,
    step_state,
)
from .kalman import LinearGaussianFamily, _finite_or_none, _loop_arrays, loop_entries, step_constants
from .registry import family_entry, register
from .smoothing import IndicatorFilterMethods, SmoothingMethods

__all__ = [
    "tobit_update",
    "tobit_measurement",
    "tobit_kalman_filter",
    "TobitKalmanFilter",
    "NOISE_TERMS",
    "check_tobit_indicator",
]

NOISE_TERMS = ("dissertation", "total_variance", "exact_pv")
_NOISE_CODES = {term: code for code, term in enumerate(NOISE_TERMS)}  # the compiled loop's noise_code
COVARIANCE_UPDATES = COVARIANCE_FORMS
_OPTIONS = {"noise_term": NOISE_TERMS, "covariance_update": COVARIANCE_UPDATES, "backend": BACKENDS}


def tobit_measurement(
    x_pred: np.ndarray,
    C: np.ndarray,
    sigma: np.ndarray,
    lower: Any,
    upper: Any,
    *,
    dy: Any = 0.0,
    noise_term: str = "dissertation",
) -> MeasurementPrediction:
    r"""The Tobit measurement prediction at the prior (Miller (3.37)–(3.41)), batched over runs.

    All channel statistics at the *prior* mean (Assumption A1, (3.35)): with
    :math:`\mu = C\bar x + Du`,

    .. math::

        E(\mathbf p) = \mathrm{diag}(\Phi(b) - \Phi(a)), \qquad
        E(y)_l = \Phi(a_l)\,l(l) + \gamma_l(\mu_l + \sigma_l\lambda_l) + \Phi(-b_l)\,h(l), \qquad
        R_{uu} = \mathrm{diag}(\ldots)

    and :math:`H = E(\mathbf p)C`: ``expected`` = E(y), ``H0`` = C, ``scale`` = E(p), ``noise`` =
    :math:`R_{uu}` (the truncated variance (3.41) for ``"dissertation"``, the censored variance for
    ``"total_variance"``, :math:`E[pv^2] = \gamma(V_{tr} + (m_{tr} - \mu)^2)` for ``"exact_pv"``).
    ``extras`` hold ``p_uncensored`` and ``expected_y`` (N, m). The censored statistics come from
    :func:`~tobitkf.filters._readings.compiled_censored_moments`, the compiled function the compiled
    loop takes them from (numba), on every backend: the two paths share one implementation.

    Parameters
    ----------
    x_pred : (N, n) ; C : (m, n) or (N or 1, m, n) (one per run) ; sigma : (m,) or (N or 1, m) ;
    lower, upper : (m,) or (N, m) ; dy : (N, m) or 0
    """
    from ._readings import compiled_censored_moments  # numba: imported on first use

    mu = (x_pred @ C.T if C.ndim == 2 else np.einsum("...ij,...j->...i", C, x_pred)) + dy
    st = compiled_censored_moments(mu, sigma, lower, upper)
    gam = st.p_uncensored
    if noise_term == "dissertation":
        Ruu = st.truncated_var
    elif noise_term == "total_variance":
        Ruu = st.censored_var
    else:  # exact_pv: E[p v^2] = gamma (Var_tr + (m_tr - mu)^2)
        Ruu = gam * (st.truncated_var + (st.truncated_mean - mu) ** 2)
    return MeasurementPrediction(
        expected=st.censored_mean,
        H0=C,
        scale=gam,
        noise=Ruu,
        extras={"p_uncensored": gam, "expected_y": st.censored_mean},
    )


def tobit_update(
    x_pred: np.ndarray,
    P_pred: np.ndarray,
    y: np.ndarray,
    C: np.ndarray,
    sigma: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    *,
    dy: Any = 0.0,
    noise_term: str = "dissertation",
    covariance_update: str = "standard",
):
    r"""One Tobit measurement update (Miller (3.37)–(3.43), (3.55)), batched over runs (procedural form).

    :func:`tobit_measurement` followed by the shared :func:`~tobitkf.filters.core.measurement_update`.

    Parameters
    ----------
    x_pred : (N, n) ndarray
        Prior means :math:`\bar x_k`.
    P_pred : (N or 1, n, n) ndarray
        Prior covariances :math:`\bar\Psi_k`.
    y : (N, m) ndarray
        Censored measurements; NaN = missing (channel skipped).
    C : (m, n) ndarray
    sigma : (m,) ndarray
        Measurement-noise standard deviations :math:`\sigma_l = \sqrt{R_{ll}}`.
    lower, upper : (m,) or (N, m) ndarray
        Censoring limits at this step.
    dy : (N, m) array or 0
        Feed-through :math:`D u_k` added to the latent mean.
    noise_term : {"dissertation", "total_variance", "exact_pv"}
        See the module docstring.
    covariance_update : {"standard", "joseph", "square_root"}
        ``"joseph"``: :math:`(I-KE(p)C)\bar\Psi(\cdot)^T + KR_{uu}K^T`. ``"square_root"``:
        the QR array form with :math:`H = E(p)C` and noise :math:`R_{uu}`. Here the factor of ``P_pred``
        is computed afresh (Cholesky, or eigen-decomposition if it is singular), which cannot restore
        accuracy already lost in ``P_pred``; :class:`TobitKalmanFilter` keeps the factor between steps.

    Returns
    -------
    x : (N, n) ; P : (N, n, n) ; stats : CensoredMoments of the channels at the prior
    """
    mp = tobit_measurement(x_pred, C, sigma, lower, upper, dy=dy, noise_term=noise_term)
    S = psd_sqrt(P_pred) if covariance_update == "square_root" else None
    x, P, _, _, _ = measurement_update(x_pred, P_pred, S, y, mp, covariance_update)
    from ._readings import compiled_censored_moments

    return x, P, compiled_censored_moments(x_pred @ C.T + dy, sigma, lower, upper)


class TobitKalmanFilter(IndicatorFilterMethods, SmoothingMethods, LinearGaussianFamily):
    r"""Tobit Kalman filter for left, right, two-sided and multi-region censoring (Miller §3.3.4).

    Parameters
    ----------
    system : LinearSystem
        The model; R must be diagonal (Assumption A2, (3.36)).
    censoring : Censoring
        The censoring limits (time-varying allowed, Miller §3.4).
    noise_term : {"dissertation", "total_variance", "exact_pv"}, default "dissertation"
        :math:`R_{uu}` in (3.40): the dissertation's truncated variance (3.41) with (3.11),
        or one of the exact alternatives (non-dissertation; see the module docstring).
        ``"total_variance"`` diverges on many one-sided systems (its gain grows without bound deep in
        the censored region; the module docstring gives the measured rate); ``filter`` then warns.
    covariance_update : {"standard", "joseph", "square_root"}, default "standard"
        ``"standard"`` is (3.55) :math:`(I - KE(p)C)\bar\Psi`; ``"joseph"`` the
        algebraically equal Joseph form; ``"square_root"`` (ours, not in the source) propagates a factor
        :math:`S`, :math:`\Psi = SS^T`, through QR factorizations (positive semidefinite by
        construction; every ``noise_term``; see :func:`tobit_kalman_filter`).
    backend : {"auto", "numpy", "numba"}, default "auto"
        Compiled path or numpy reference path; see :func:`tobit_kalman_filter`.
        ``"numba"`` has no square-root form and is refused with ``covariance_update="square_root"``.
    threads : int, optional
        Threads for the compiled path; see :func:`tobit_kalman_filter`.
    check_limits : bool, default True
        Raise if a reading lies outside its censoring limits.

    Raises
    ------
    ValidationError
        Non-diagonal or non-positive R, unknown option, wrong argument types.

    Notes
    -----
    See :func:`tobit_kalman_filter` and the module docstring for the equations.
    With the dissertation's noise term the TKF can be *more* confident than the KF
    when lightly censored (:math:`p_u^2\sigma^2 > V_{tr}` for :math:`a \lesssim -0.6`);
    ``"total_variance"`` removes this.

    Online use: :meth:`step` (predict + update), or :meth:`predict` and :meth:`update` separately;
    ``update(state, y, lower=..., upper=...)`` (and ``step``) take this step's limits, (N, m) or
    (m,), for a sensor whose limit is steered from the prediction (Miller §3.4, Ch. 6).

    Examples
    --------
    >>> import numpy as np, tobitkf as tk
    >>> sys = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.01]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    >>> tkf = tk.TobitKalmanFilter(sys, tk.Censoring(lower=0.0))
    >>> state = tkf.init()
    >>> for reading in ([0.4], [0.0], [1.1]):          # 0.0: censored at the limit
    ...     state = tkf.step(state, reading)
    >>> bool(np.allclose(state.mean, tkf.filter([[0.4], [0.0], [1.1]]).mean[-1], rtol=0, atol=1e-12))
    True

    References
    ----------
    .. [1] C. I. Miller, *Estimation and Control with Censored Data*, PhD thesis,
       University of Delaware, 2015, §3.3.
    """

    _name = "TobitKalmanFilter"
    _filter_doc = """Run the Tobit Kalman filter (Miller (3.37)–(3.41), the covariance (3.55)) over a batch of censored
    records ``y`` (..., T, m), censored readings equal to their limit; see :func:`tobit_kalman_filter`."""
    _filter_params = {
        "y": "(..., T, m) array_like\n"
        "    Censored readings y_1..y_T (a censored one equal to its limit); NaN = missing (the channel is\n"
        "    skipped in that step).",
        "censored": "(..., T, m) bool array_like, optional\n"
        "    The censoring indicator recorded with the data, checked against the readings (a flagged one must lie\n"
        "    at its limit); the update is linear in the reading and unchanged by it.",
    }
    _filter_raises = "a reading outside its censoring limits (``check_limits``); a flag on a reading inside them"
    _step_options: tuple[str, ...] = ("lower", "upper")
    _loop_limits: np.ndarray  # (2, 1, m) the constant limits of the compiled step, set on its first call

    def __init__(
        self,
        system: LinearSystem,
        censoring: Censoring,
        *,
        noise_term: str = "dissertation",
        covariance_update: str = "standard",
        backend: str = "auto",
        threads: int | None = None,
        check_limits: bool = True,
    ):
        check_instance(system, LinearSystem, "system")
        check_instance(censoring, Censoring, "censoring")
        check_keywords({"noise_term": noise_term, "covariance_update": covariance_update, "backend": backend}, _OPTIONS)
        check_square_root(backend, covariance_update, "the Tobit Kalman filter")
        censoring.check(system.m)
        if not isinstance(check_limits, (bool, np.bool_)):
            raise ValidationError(f"check_limits: expected True or False, got {check_limits!r}")
        self._sigma = None if system.R.varying else diagonal_sigma(system.measurement_cov(1))
        self._setup_system(system)
        self.censoring = censoring
        self.noise_term, self.covariance_update, self.backend = noise_term, covariance_update, backend
        self.threads = None if threads is None else check_threads(threads)
        self.check_limits = bool(check_limits)

    def _sigma_at(self, k: int) -> np.ndarray:
        return self._sigma if self._sigma is not None else diagonal_sigma(self.system.measurement_cov(k), f"R({k})")

    def _measurement(self, k, xp, Pp, y, u, carry, lower=None, upper=None):
        if lower is None or upper is None:
            lo, hi = self.censoring.limits(k)
            lower = lo if lower is None else lower
            upper = hi if upper is None else upper
        mp = tobit_measurement(
            xp,
            self.system.measurement(k),
            self._sigma_at(k),
            lower,
            upper,
            dy=self._feedthrough(k, u),
            noise_term=self.noise_term,
        )
        return mp, carry

    def _check_record(self, y2, u2, k0, name="y"):
        super()._check_record(y2, u2, k0, name)
        if self.check_limits:  # checks the limits against m and the horizon, then the readings
            self.censoring.check_measurements(y2, name, start=k0 + 1)
        else:
            self.censoring.check(self.m, k0 + y2.shape[1])

    def _prepare_step_options(self, state: FilterState, options: dict[str, Any]) -> dict[str, Any]:
        out = {}
        for key in ("lower", "upper"):
            if options.get(key) is not None:
                arr = as_float_array(options[key], key, allow_inf=True)
                try:
                    out[key] = np.broadcast_to(arr, (state.runs, self.m))
                except ValueError:
                    raise ValidationError(
                        f"{key}: expected this step's limits of shape ({self.m},) or "
                        f"{state.batch_shape + (self.m,)}, got {arr.shape}"
                    ) from None
        if out:
            lo, hi = self.censoring.limits(state.k + (0 if state.carry.get("_predicted") else 1))
            lo = out.get("lower", np.broadcast_to(lo, (state.runs, self.m)))
            hi = out.get("upper", np.broadcast_to(hi, (state.runs, self.m)))
            if not (lo < hi).all():
                raise ValidationError("lower/upper: expected lower < upper for every channel of this step")
            out = {"lower": lo, "upper": hi}
        return out

    # ---- the compiled path ------------------------------------------------------------
    def _compiled_ok(self, u) -> bool:
        return compiled_ok(self, u, "the Tobit Kalman filter", inputs=True)

    def _compiled_filter(self, y2, u2, state, want, batch, step_options=None):
        if not self._compiled_ok(u2):
            return None
        lo, hi = self.censoring.all_limits(y2.shape[1], self.m, start=state.k + 1, check=False)  # checked at _run
        return _finite_or_none(_tkf_compiled_run(self, y2, u2, lo, hi, state, want, batch))

    def _compiled_online_step(self, state, y, u, options):
        if options or not self._compiled_ok(u):
            return None
        return _tkf_compiled_online_step(self, y, u, state)

    def step(self, state: FilterState, y: Any, *, u: Any = None, **options: Any) -> FilterState:
        """One predict + update with the reading ``y`` (``batch_shape + (m,)``; NaN = missing).

        ``lower``/``upper`` (keyword, (m,) or ``batch_shape + (m,)``) replace this step's limits.
        """
        return super().step(state, y, u=u, **options)

    def _check_reading(self, k, y, options):
        if self.check_limits and not options:
            self.censoring.check_reading(y, k)

    def _filter_indicated(self, y: Any, censored: Any, *, u: Any, x0: Any, P0: Any, outputs: Any, state: Any):
        # the recorded indicator is checked against the limits; the update is the limit rule's all the same
        check_tobit_indicator(self.censoring, y, censored, start=(0 if state is None else state.k) + 1)
        return self._run(y, u, x0, P0, outputs=outputs, state=state)

    def _log_likelihood_terms(self, y: Any, *, u: Any, x0: Any, P0: Any, **recorded: Any) -> np.ndarray:
        """The TKF's update defines no likelihood: the assumed-density terms (..., T) of its model (system and
        censoring), :func:`tobitkf.inference.adf_log_likelihood`."""
        adf = assumed_density_filter(self.system, self.censoring)
        return adf._log_likelihood_terms(y, u=u, x0=x0, P0=P0, **recorded)


def _input_terms(est: TobitKalmanFilter, u: np.ndarray | None, N: int, T: int) -> tuple[np.ndarray, np.ndarray]:
    """The compiled loop's input arrays from ``u`` (N, T, p) or None: ``bu`` = :math:`B^uu_k` (N, T, n) and ``du`` =
    :math:`Du_k` (N, T, m) as contiguous float64, each (N, 0, ...) when absent (the same products as the
    numpy path's ``u @ Bu.T`` and ``u @ D.T``, per step)."""
    sys_ = est.system
    if u is None or sys_.Bu is None:
        bu = _empty((N, 0, est.n))
    else:
        bu = np.ascontiguousarray(u @ sys_.Bu.at(1).T, dtype=float)
    if u is None or sys_.D is None:
        du = _empty((N, 0, est.m))
    else:
        du = np.ascontiguousarray(u @ sys_.D.at(1).T, dtype=float)
    return bu, du


def _tkf_compiled_online_step(est: TobitKalmanFilter, y: np.ndarray, u, state: FilterState) -> FilterState | None:
    """One online step through the compiled loop (T = 1); None when the covariance stopped being finite. Without
    an input it enters by :func:`~tobitkf.filters._compiled_entries.tobit_step` (8 arguments, the constants
    flattened once per estimator)."""
    N, m = y.shape
    n = est.n
    cens = est.censoring
    lohi = None if cens.time_varying else est.__dict__.get("_loop_limits")
    if lohi is None:
        lohi = np.empty((2, 1, m))  # writable (a read-only argument would compile the loop once more)
        lohi[0], lohi[1] = cens.limits(state.k + 1)
        if not cens.time_varying:
            est._loop_limits = lohi  # constant limits: converted once
    P = state.P
    assert P is not None, "the compiled path runs the standard form, which carries P"
    if P.shape[0] != N:
        P = np.broadcast_to(P, (N, n, n))
    x_last, P_last = np.empty((N, n)), np.empty((N, n, n))
    out2 = np.empty((2, N, m))  # P(uncensored), E[y]
    x0, P0 = loop_input(state.x), loop_input(P)
    if u is None:
        loop_entries().tobit_step(
            loop_input(y), step_constants(est, _NOISE_CODES[est.noise_term]), lohi, x0, P0, out2, x_last, P_last
        )
    else:
        bu, du = _input_terms(est, u.reshape(N, 1, -1), N, 1)
        A, Qd, H, sigma, joseph = _loop_arrays(est)
        loop_entries().tobit_loop(
            loop_input(y.reshape(N, 1, m)),
            A,
            Qd,
            H,
            sigma,
            lohi[0],
            lohi[1],
            bu,
            du,
            _NOISE_CODES[est.noise_term],
            joseph,
            x0,
            P0,
            _empty((N, 0, n)),
            _empty((N, 0, n, n)),
            _empty((N, 0, n)),
            _empty((N, 0, n, n)),
            out2[0].reshape(N, 1, m),
            out2[1].reshape(N, 1, m),
            x_last,
            P_last,
        )
    if not (all(map(math.isfinite, P_last.ravel().tolist())) if P_last.size <= 16 else np.isfinite(P_last).all()):
        return None
    extras = {"p_uncensored": out2[0], "expected_y": out2[1]}
    return step_state(state.k + 1, state.batch_shape, x_last, P_last, n, None, state.carry, extras)


def _tkf_compiled_run(est: TobitKalmanFilter, y2, u2, lo, hi, state: FilterState, want, batch) -> FilterResult:
    """The TKF through the compiled loop (:func:`tobitkf.filters._compiled_loop.compiled_loop`) from ``state``;
    outputs on request; the runs split over ``est.threads`` threads from 256 runs on."""
    N, T, m = y2.shape
    n = est.n
    x = loop_input(state.x)
    assert state.P is not None, "the compiled path runs the standard form, which carries P"
    # writable: a read-only P (a broadcast view, even of P's own shape) would compile the loop once more
    P = loop_input(np.broadcast_to(state.P, (N, n, n)))

    ext = "extras" in want
    means, covs, pmeans, pcovs, pu, ey = output_arrays(  # one allocation, from the output pool when large
        N,
        T,
        *state_specs(want, n),
        (ext, (m,)),
        (ext, (m,)),
    )
    x_last, P_last = np.empty((N, n)), np.empty((N, n, n))
    # writable copies of read-only limits (cached by the censoring): numba types read-only arrays apart, and each
    # would compile the loop once more
    yc, lo, hi = np.require(y2, float, ("C", "W")), np.require(lo, float, ("C", "W")), np.require(hi, float, ("C", "W"))
    code = _NOISE_CODES[est.noise_term]
    bu, du = _input_terms(est, u2, N, T)

    A, Qd, H, sigma, joseph = _loop_arrays(est)
    entries = loop_entries()
    loop = entries.tobit_loop
    # up to 4 states, one channel or the measured (m, n) of several, limits without NaN and lo < hi: the step
    # vectorised over runs (equal to the loop)
    loop = entries.tobit_entry(loop, m, n, lo, hi)

    def work(a: int, b: int) -> None:  # runs a..b-1; row slices of C-ordered arrays stay contiguous
        loop(
            yc[a:b],
            A,
            Qd,
            H,
            sigma,
            lo,
            hi,
            bu[a:b],
            du[a:b],
            code,
            joseph,
            x[a:b],
            P[a:b],
            means[a:b],
            covs[a:b],
            pmeans[a:b],
            pcovs[a:b],
            pu[a:b],
            ey[a:b],
            x_last[a:b],
            P_last[a:b],
        )

    if N < 256:  # one thread: not worth a pool (and no thread-count lookup per step)
        work(0, N)
    else:
        run_split(work, N, check_threads(est.threads))
    final = FilterState(k=state.k + T, batch_shape=batch, x=x_last, P=P_last, n=n, carry=state.carry)
    extras = {"p_uncensored": loop_array(pu, batch), "expected_y": loop_array(ey, batch)} if "extras" in want else {}
    return compiled_result(want, batch, T, means, covs, pmeans, pcovs, extras, final)


def tobit_kalman_filter(
    system: LinearSystem,
    censoring: Censoring,
    y: Any,
    *,
    u: Any = None,
    noise_term: str = "dissertation",
    covariance_update: str = "standard",
    x0: Any = None,
    P0: Any = None,
    check_limits: bool = True,
    backend: str = "auto",
    threads: int | None = None,
    outputs: Any = "all",
) -> FilterResult:
    r"""Run the Tobit Kalman filter over a batch of censored records.

    Parameters
    ----------
    system : LinearSystem
        The model; R must be diagonal (Assumption A2).
    censoring : Censoring
        Lower/upper limits, per channel, constant or ``(T, m)``.
    y : (..., T, m) array_like
        Censored measurements y_1..y_T (censored readings equal to the limit).
        NaN marks a missing sample (the channel is skipped in that step).
    u : (T, p) or (..., T, p) array_like, optional
        Control inputs.
    noise_term : {"dissertation", "total_variance", "exact_pv"}, default "dissertation"
        The measurement-noise term :math:`R_{uu}` (see the module docstring).
    covariance_update : {"standard", "joseph", "square_root"}, default "standard"
        ``"standard"`` is (3.55); ``"joseph"`` the algebraically equal Joseph form;
        ``"square_root"`` (not in the source) carries a factor :math:`S`,
        :math:`\Psi = SS^T`, through QR factorizations and stays positive semidefinite by
        construction (see Notes); it is available with every ``noise_term`` and runs on the
        numpy path only.
    x0, P0 : array_like, optional
        Override the system's prior.
    check_limits : bool, default True
        Raise if a measurement lies outside its censoring limits.
    backend : {"auto", "numpy", "numba"}, default "auto"
        Implementation of the time loop (same results to rounding, tested to 1e-12).
        ``"numba"`` runs the compiled path (numba), which
        covers time-invariant A, B, C, Q, R, with or without control input through constant
        B^u and D (any limits, multi-region included, NaN samples and noise term; the standard
        and Joseph updates, not the square-root form); ``"numpy"`` the shared loop of :mod:`tobitkf.filters.core`, which covers everything;
        ``"auto"`` the compiled path when numba is installed and the case is covered, else numpy
        (always numpy for ``covariance_update="square_root"``). The numpy loop takes the censored statistics from
        the compiled function the compiled path calls (:func:`tobit_measurement`), on every backend.
    threads : int, optional
        Threads over which the compiled path splits the runs (it releases the GIL; the
        result is identical bit for bit). Default: ``TOBITKF_NUM_THREADS``, else
        ``OMP_NUM_THREADS`` (Dask workers set it to 1), else the number of CPUs. Batches
        below 256 runs per thread are not split. Ignored by the numpy path.
    outputs : str or sequence of str, default "all"
        Per-step outputs to record: ``"all"``, ``"last"`` (only ``result.final``), or names from
        ``mean, cov, var, pred_mean, pred_cov, extras``.

    Returns
    -------
    FilterResult
        ``mean`` (..., T, n), ``cov`` (..., T, n, n), ``pred_mean``, ``pred_cov``; extras
        ``p_uncensored`` and ``expected_y`` (..., T, m) at the prior; ``times`` = 1..T; ``final``.

    Raises
    ------
    ValidationError
        Non-diagonal R, a reading outside its limits, an unknown option, or
        ``backend="numba"`` for a case the compiled path does not cover (including
        ``covariance_update="square_root"``).
    ImportError
        ``backend="numba"`` without numba installed.
    ShapeError
        Malformed ``y``, ``u`` or limits.

    Notes
    -----
    Square-root form. The Tobit update is a Kalman update with :math:`H = E(\mathbf p)C`
    and noise :math:`R_{uu}`: :math:`R_{xe} = \bar\Psi H^T`,
    :math:`R_{ee} = H\bar\Psi H^T + R_{uu}` ((3.39)–(3.40)), with :math:`R_{uu}` diagonal
    and nonnegative for each of the three noise terms (they differ only in its diagonal).
    With :math:`\bar\Psi = \bar S\bar S^T` the QR factorization

    .. math::

        \begin{bmatrix} R_{uu}^{1/2} & 0 \\ \bar S^TC^TE(\mathbf p) & \bar S^T \end{bmatrix}
        = \mathcal Q \begin{bmatrix} U_{11} & U_{12} \\ 0 & U_{22} \end{bmatrix}

    gives :math:`U_{11}^TU_{11} = R_{ee}`, :math:`K = R_{xe}R_{ee}^{-1} = U_{12}^TU_{11}^{-T}`
    and :math:`\Psi = \bar\Psi - KR_{xe}^T = U_{22}^TU_{22}`, so the new factor is
    :math:`S = U_{22}^T`; the time update is the QR of
    :math:`[\,S^TA^T;\ G^T\,]` with :math:`GG^T = BQB^T`. Missing and degenerate channels
    (:math:`R_{ee,ll}` not above the smallest normal number) are left out exactly as in the
    other forms. The channel statistics are the same as in the other forms (at the prior
    mean), so in exact arithmetic the three forms give the same filter. The form is not in
    the source: it is the array form of the square-root filter (Kaminski, Bryson & Schmidt
    1971; Bierman 1977; Grewal & Andrews, *Kalman Filtering: Theory and Practice*). Cost on
    the numpy path (n = 2, m = 1, 10^4 runs of 100 steps): 0.83 s against 0.19 s for the
    standard form.

    Examples
    --------
    With infinite limits the TKF is the Kalman filter (Miller (3.44)):

    >>> import numpy as np, tobitkf as tk
    >>> sys = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.01]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    >>> y = np.array([[0.5], [1.0], [-0.2]])
    >>> a = tk.TobitKalmanFilter(sys, tk.Censoring()).filter(y).mean
    >>> b = tk.KalmanFilter(sys).filter(y).mean
    >>> bool(np.allclose(a, b, rtol=0, atol=1e-12))
    True
    """
    est = TobitKalmanFilter(
        system,
        censoring,
        noise_term=noise_term,
        covariance_update=covariance_update,
        backend=backend,
        threads=threads,
        check_limits=check_limits,
    )
    return est.filter(y, u=u, x0=x0, P0=P0, outputs=outputs)


def check_tobit_indicator(censoring: Censoring, y: Any, censored: Any, *, start: int = 1) -> None:
    r"""Check a recorded indicator against the TKF's readings: a flagged reading must lie at (or beyond) a
    limit. The TKF's update (Miller (3.37)-(3.41)) is linear in the reading and does not branch on it,
    so an unflagged reading at the limit needs nothing else. Called by
    :meth:`tobitkf.TobitKalmanFilter.filter` when ``censored`` is given.

    Raises
    ------
    ShapeError, ValidationError
        See :func:`~tobitkf.filters._readings.censoring_sides`.
    """
    arr = np.asarray(y, dtype=float)
    y2 = arr.reshape((-1,) + arr.shape[-2:])
    lo, hi = censoring.all_limits(y2.shape[1], y2.shape[2], start=start)
    try:
        c2 = np.broadcast_to(np.asarray(censored), arr.shape).reshape(y2.shape)
    except ValueError:
        raise ShapeError(f"censored: expected the shape of y {arr.shape}, got {np.shape(censored)}") from None
    censoring_sides(y2, lo, hi, c2)


register(
    family_entry(
        TobitKalmanFilter,
        "Tobit Kalman filter, one- and two-sided, multi-region (Miller §3.3, §6.6)",
        ("censoring",),
        options={**_OPTIONS, "threads": int},
    )
)
