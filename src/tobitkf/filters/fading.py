r"""Tobit Kalman filter with Rice fading measurements (TKF-FM) and its baselines.

Source: Geng, Wang, Liang et al., "Tobit Kalman filter with fading measurements",
*Signal Processing* 140 (2017) 60–68; our deviations: docs/sources/geng2017-fading.md.

Model ((1)–(3) of the source):

.. math::

    x_{k+1} &= A_k x_k + B_k\omega_k, \qquad
    y^*_k = \sum_{s=0}^{\ell_k}\vartheta_k(s)C_{k-s}x_{k-s} + \upsilon_k, \quad \ell_k = \min\{L,k\} \\
    y_k &= \max(y^*_k, \mathcal I) \quad\text{(element-wise lower censoring)}

Augmented model (7)–(10), **fixed size** :math:`n_\xi = n(L+1)` from k = 0 (docs/sources GF-07):
:math:`\xi_k = \mathrm{col}\{x_k, x_{k-1}, \dots, x_{k-L}\}`, the square shift matrix
:math:`\mathcal A_k` (block row 0 :math:`[A_k, 0, \dots]`, block row i an identity in
column i-1), :math:`\mathcal B_k = [B_k; 0; \dots]`,
:math:`H_k = \bar\theta_k\mathcal C_k = [\bar\vartheta(0)C_k, \dots, \bar\vartheta(\ell_k)C_{k-\ell_k}, 0, \dots]`.
The blocks for :math:`s > k` are zero-mean, zero-covariance placeholders with zero
columns in :math:`H_k`; they are never updated, so the filter equals the
growing-dimension one (tested).

Per step, in the order of Table 1 of the source, :math:`\sigma_m = \sqrt{R^{mm}_k}`:

.. math::

    \hat\xi_{k|k-1} &= \mathcal A_{k-1}\hat\xi_{k-1|k-1}, \quad
    \mathcal P_{k|k-1} = \mathcal A_{k-1}\mathcal P_{k-1|k-1}\mathcal A_{k-1}^T + \mathcal B_{k-1}Q_{k-1}\mathcal B_{k-1}^T
      & (17), (18) \\
    \hat x_{k|k-1} &= \Gamma\hat\xi_{k|k-1}, \quad P_{k|k-1} = \Gamma\mathcal P_{k|k-1}\Gamma^T & (27), (28) \\
    \hat\chi_{k|k-1} &= H_k\hat\xi_{k|k-1}, \quad z^m = (\mathcal I^m - \hat\chi^m)/\sigma_m, \quad
      \lambda = \frac{\phi(z)}{1-\Phi(z)}, \quad \psi = \lambda(\lambda - z) & \text{Lemma 1, (13), (14)} \\
    \bar\gamma^m &= \Phi\big((\hat\chi^m - \mathcal I^m)/\sigma_m\big) & (6) \\
    \hat y^m_{k|k-1} &= \bar\gamma^m(\hat\chi^m + \sigma_m\lambda^m) + (1-\bar\gamma^m)\mathcal I^m & (21), (37) \\
    \Sigma_{\tilde\xi\tilde y} &= \mathcal P_{k|k-1}G_k^T, \quad G_k = \bar\Upsilon_k H_k & (24) \\
    \Sigma_{\tilde y\tilde y} &= G_k\mathcal P_{k|k-1}G_k^T + N_k, \quad N_k = \mathrm{diag}\{R^{mm}_k(1-\psi^m)\}
      & (25), (26) \\
    K_k &= \Sigma_{\tilde\xi\tilde y}\Sigma_{\tilde y\tilde y}^{-1}, \quad
    \hat\xi_{k|k} = \hat\xi_{k|k-1} + K_k(y_k - \hat y_{k|k-1}) & (23), (19) \\
    \mathcal P_{k|k} &= (I - K_kG_k)\mathcal P_{k|k-1}(I - K_kG_k)^T + K_kN_kK_k^T & (20') \\
    \hat x_{k|k} &= \Gamma\hat\xi_{k|k}, \quad P_{k|k} = \Gamma\mathcal P_{k|k}\Gamma^T & (29), (30)

Block s of :math:`\hat\xi_{k|k}` is the fixed-lag smoothed :math:`\hat x_{k-s|k}`, with the
(s, s) block of :math:`\mathcal P_{k|k}` its covariance; both are returned (``extras``).

Repairs of the source (unavoidable, always on)
----------------------------------------------
* (20) is garbled in the source (a stray :math:`\bar\Upsilon_k` and a doubled
  :math:`\Sigma_{\tilde y}^{-1}`; it does not conform). We use the orthogonal-projection
  result the proof appeals to, :math:`\mathcal P_{k|k} = \mathcal P_{k|k-1} - K\Sigma_{\tilde y\tilde y}K^T`
  (docs/sources GF-02), in Joseph form by default.
* Typos read as in docs/sources GF-11: (17) is the augmented :math:`\mathcal A_{k-1}`; (27) defines
  :math:`\hat x_{k|k-1}`; :math:`\bar\theta_k` runs over s = 0..ℓ_k.
* :math:`\bar\gamma` in (6) is written with the letter of the Mills ratio; we call it
  ``p_uncensored`` and the stale mean of (6) :math:`\hat\mu` (GF-11).

Options (all off by default; "Deviation from the source")
---------------------------------------------------------
* ``p_uncensored_mode``: ``"augmented"`` (default, docs/sources GF-03) evaluates (6) at
  :math:`\hat\chi_{k|k-1} = H_k\hat\xi_{k|k-1}`, consistent with (21)–(26).
  ``"eq6_stale"`` is (6) literally: :math:`\hat\mu^m = \sum_s \bar\vartheta^m(s)[C_{k-s}\hat x_{k-s|k-s-1}]^m`
  with the one-step predictions made at earlier steps (:math:`\hat x_{0|-1} := \bar x_0`) (GF-03).
* ``fading_variance_term=True`` adds :math:`\bar\Upsilon_kD_k\bar\Upsilon_k` to :math:`N_k`,
  :math:`D_k^{mm} = \sum_s\tilde\vartheta^m(s)[C_{k-s}X_{k-s}C_{k-s}^T]^{mm}`,
  :math:`X_{j+1} = A_jX_jA_j^T + B_jQ_jB_j^T`, :math:`X_0 = \bar x_0\bar x_0^T + P_0` (docs/sources GF-04;
  the source never uses the fading variances, so its filter is over-confident).
* ``exact_tobit_variance=True`` replaces (12) by the censored variance (law of total
  variance), :math:`N^{mm} = \bar\gamma R^{mm}(1-\psi) + \bar\gamma(1-\bar\gamma)(\hat\chi+\sigma\lambda-\mathcal I)^2`
  (docs/sources GF-05; (12) is the variance of the *uncensored part* only).
* ``covariance_update="standard"`` uses :math:`\mathcal P_{k|k-1} - K\Sigma_{\tilde y\tilde y}K^T`
  instead of the Joseph form (equal in exact arithmetic).

In the terms of the shared core (:mod:`tobitkf.filters.core`): the state is the augmented
:math:`\xi_k`, the transition the block shift of (17)–(18), and the measurement prediction
:math:`\hat y_{k|k-1}` (21) with :math:`H_0 = H_k = \bar\theta_k\mathcal C_k`, the per-run channel
scale :math:`\bar\gamma_k` (so that :math:`G_k = \bar\Upsilon_kH_k`) and the diagonal noise
:math:`N_k`; the shared update in Joseph form is (20'). ``covariance_update="square_root"`` (not in the
source) is available too.

Upper limits (two-sided censoring) are ours (not in the source): all censoring statistics are the
censored-normal statistics (:func:`tobitkf.censored_moments`, which reduces to Lemma 1 for a lower limit),
taken on every path from the compiled function the compiled loop calls
(:func:`~tobitkf.filters._readings.compiled_censored_moments`).

Time convention: x_0 ~ N(x̄_0, P_0) is the prior; no update at k = 0; y_1 (stored at
index 0) is the first measurement and mixes x_1 and x_0 when L >= 1 (docs/sources GF-10). Output
index k-1 holds x̂_{k|k}.

Code names -> paper symbols: ``mean`` x̂_{k|k}; ``cov`` P_{k|k}; ``pred_mean`` x̂_{k|k-1};
``p_uncensored`` :math:`\bar\gamma_k`; ``inverse_mills`` λ; ``expected_y`` :math:`\hat y_{k|k-1}`;
``smoothed_mean[..., k-1, s, :]`` :math:`\hat x_{k-s|k}`; ``aug_mean`` :math:`\hat\xi_{k|k}`;
``aug_cov`` :math:`\mathcal P_{k|k}`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._validation import check_instance, diagonal_sigma
from ..channels.censoring import Censoring
from ..channels.fading import RiceFading, measurement_matrix_at
from ..models.linear import LinearSystem
from ._backend import BACKENDS, check_square_root, system_gap, use_compiled
from ._online_check import system_only
from ._outputs import _empty, compiled_result, loop_array, loop_input, output_arrays, state_specs
from .core import (
    FilterResult,
    FilterState,
    MeasurementPrediction,
    check_keywords,
    check_prior,
    step_state,
    symmetrize,
)
from .kalman import KalmanFilter, LinearGaussianFamily, _finite_or_none, finite_variances, loop_entries
from .registry import family_entry, register
from .tobit import TobitKalmanFilter

__all__ = [
    "fading_tobit_kalman_filter",
    "FadingTobitKalmanFilter",
    "fading_kalman_filter",
    "FadingKalmanFilter",
    "augmented_measurement_matrix",
    "fading_estimators",
    "P_UNCENSORED_MODES",
]

P_UNCENSORED_MODES = ("augmented", "eq6_stale")
_BOOL = (False, True)
_FORMS = ("joseph", "standard", "square_root")
_TOBIT_OPTIONS = {
    "p_uncensored_mode": P_UNCENSORED_MODES,
    "fading_variance_term": _BOOL,
    "exact_tobit_variance": _BOOL,
    "covariance_update": _FORMS,
    "backend": BACKENDS,
}
_KF_OPTIONS = {"fading_variance_term": _BOOL, "covariance_update": _FORMS}
_STEP_OUTPUTS = frozenset({"extras"})  # what a compiled online step needs from the loop: the step's extras


def augmented_measurement_matrix(system: LinearSystem, fading: RiceFading, k: int) -> np.ndarray:
    r""":math:`H_k = \bar\theta_k\mathcal C_k`, zero-padded to ``(m, n(L+1))`` (docs/sources GF-07).

    Block s (columns ``s*n:(s+1)*n``) is :math:`\bar\vartheta(s)C_{k-s}` for s <= min(L, k), else 0.
    """
    n, m, L = system.n, system.m, fading.order
    thb = fading.mean_gains(m)
    H = np.zeros((m, n * (L + 1)))
    for s in range(min(L, k) + 1):
        H[:, s * n : (s + 1) * n] = thb[s][:, None] * measurement_matrix_at(system, k - s)
    return H


def _sigma_of(R: np.ndarray, name: str) -> np.ndarray:
    # App. B of the source assumes cov{y^m, y^t} = 0 for m != t: R must be diagonal (docs/sources GF-13).
    return diagonal_sigma(
        R,
        name,
        who="the fading Tobit Kalman filter",
        why="Geng et al. 2017, App. B: uncorrelated channels",
        positive="expected positive measurement variances",
    )


def _check_parts(system: Any, fading: Any, censoring: Any) -> None:
    check_instance(system, LinearSystem, "system")
    check_instance(fading, RiceFading, "fading")
    fading.check(system.m)
    if censoring is not None:
        check_instance(censoring, Censoring, "censoring")
        censoring.check(system.m)


def _limit_terms(p: np.ndarray, limit: np.ndarray) -> np.ndarray:
    """``p * limit`` with 0 where the limit is infinite (and so p = 0)."""
    finite = np.isfinite(limit)
    if finite.all():  # the same numbers with fewer operations (the online step of one run)
        return p * limit
    if not finite.any():
        return np.zeros(np.broadcast_shapes(np.shape(p), np.shape(limit)))
    return np.where(finite, p * np.where(finite, limit, 0.0), 0.0)


class _FadingFamily(LinearGaussianFamily):
    """The augmented fading filter of Table 1; ``tobit=False`` is the fading KF baseline."""

    _step_options = ("keep_smoothed", "keep_augmented")

    def _setup(
        self,
        system,
        fading,
        censoring,
        *,
        tobit,
        p_uncensored_mode="augmented",
        fading_variance_term=False,
        exact_tobit_variance=False,
        covariance_update="joseph",
        check_limits=True,
    ):
        _check_parts(system, fading, censoring)
        if not system.R.varying:
            _sigma_of(system.measurement_cov(1), "R")
        self._setup_system(system)
        self.fading, self.censoring = fading, censoring
        self._cens = Censoring() if censoring is None else censoring
        self.tobit = tobit
        self.p_uncensored_mode = p_uncensored_mode
        self.fading_variance_term = bool(fading_variance_term)
        self.exact_tobit_variance = bool(exact_tobit_variance)
        self.covariance_update = covariance_update
        self.check_limits = check_limits
        self.L = fading.order
        self._nxi = system.n * (self.L + 1)
        self._thb, self._thv = fading.mean_gains(system.m), fading.var_gains(system.m)
        self._sigma = None if system.R.varying else _sigma_of(system.measurement_cov(1), "R")
        self._stale = tobit and p_uncensored_mode == "eq6_stale"

    def _state_dim(self) -> int:
        return self._nxi

    def _initial(self, N, x0, P0, batch):
        # fixed-size augmentation: xi_0|0 = [x0; 0...], P_0|0 = blkdiag(P0, 0...)  (docs/sources GF-07, GF-10)
        n, nxi, m, L = self.n, self._nxi, self.m, self.L
        x_init, P_init = check_prior(self.system, x0, P0, N, batch)
        per_run = (x0 is not None and np.ndim(x0) > 1) or (P0 is not None and np.ndim(P0) > 2)
        if not per_run:
            P_init = P_init[:1]
        xi = np.zeros((N, nxi))
        xi[:, :n] = x_init
        P = np.zeros((P_init.shape[0], nxi, nxi))
        P[:, :n, :n] = symmetrize(P_init)  # exactly symmetric (the shift prediction relies on it)
        carry: dict[str, Any] = {}
        C0 = measurement_matrix_at(self.system, 0)
        if self._stale:  # C_j x̂_{j|j-1} for j = k, k-1, ..., k-L, with x̂_{0|-1} := x̄_0 (docs/sources GF-03)
            cx = np.zeros((N, L + 1, m))
            cx[:, 0] = x_init @ C0.T
            carry["cx_pred"] = cx
        if self.fading_variance_term:  # diag(C_j X_j C_j^T), X_j = E[x_j x_j^T] (docs/sources GF-04)
            cxxc = np.zeros((N, L + 1, m))
            cxxc[:, 0] = np.einsum("ij,njk,ik->ni", C0, np.broadcast_to(P_init, (N, n, n)), C0) + (x_init @ C0.T) ** 2
            carry.update(mom_mean=x_init.copy(), mom_cov=np.broadcast_to(P_init, (N, n, n)).copy(), cxxc=cxxc)
        return xi, P, carry

    def _augmented_H(self, k: int) -> np.ndarray:
        """:func:`augmented_measurement_matrix` at k; for a constant C it is the same for every k > L:
        built once and kept (read-only) instead of at every step."""
        if self.system.C.varying or k <= self.L:
            return augmented_measurement_matrix(self.system, self.fading, k)
        H = self.__dict__.get("_H_steady")
        if H is None:
            H = augmented_measurement_matrix(self.system, self.fading, k)
            H.setflags(write=False)
            self._H_steady = H
        return H

    @system_only
    def _transition(self, k, u, carry):
        return self._linear_transition(k, u, shift=True)  # (17)-(18) with the shift structure of the augmented A

    def _measurement(self, k, xp, Pp, y, u, carry, **options):
        sys_, L, m, n = self.system, self.L, self.m, self.n
        H = self._augmented_H(k)  # (m, nxi)
        dy = self._feedthrough(k, u)
        chi = xp @ H.T + dy  # Lemma 1 at the prediction
        sigma = self._sigma if self._sigma is not None else _sigma_of(sys_.measurement_cov(k), f"R({k})")
        lo, hi = self._cens.limits(k)
        N = xp.shape[0]
        carry = dict(carry)
        top = min(L, k)
        Ck = measurement_matrix_at(sys_, k)
        if self._stale:
            cx = np.empty_like(carry["cx_pred"])
            cx[:, 1:] = carry["cx_pred"][:, :-1]
            cx[:, 0] = xp[:, :n] @ Ck.T
            carry["cx_pred"] = cx
        if self.fading_variance_term:
            A, Qd = sys_.transition(k - 1), sys_.process_cov(k - 1)
            bx = 0.0 if u is None or sys_.Bu is None else u @ sys_.Bu.at(k).T
            mom_mean = carry["mom_mean"] @ A.T + bx
            mom_cov = A @ carry["mom_cov"] @ A.T + Qd
            cxxc = np.empty_like(carry["cxxc"])
            cxxc[:, 1:] = carry["cxxc"][:, :-1]
            cxxc[:, 0] = np.einsum("ij,njk,ik->ni", Ck, mom_cov, Ck) + (mom_mean @ Ck.T) ** 2
            carry.update(mom_mean=mom_mean, mom_cov=mom_cov, cxxc=cxxc)
        if self.tobit:  # the statistics of the compiled loop's function, on every backend
            from ._readings import compiled_censored_moments

            st = compiled_censored_moments(chi, sigma, lo, hi)
            if self._stale:  # (6) literally: mu = sum_s thbar(s) C_{k-s} x̂_{k-s|k-s-1}
                mu = dy + sum(self._thb[s] * carry["cx_pred"][:, s] for s in range(top + 1))
                sp = compiled_censored_moments(mu, sigma, lo, hi)
                p_lo, gam, p_hi = sp.p_lower, sp.p_uncensored, sp.p_upper
            else:
                p_lo, gam, p_hi = st.p_lower, st.p_uncensored, st.p_upper
            tmean = st.truncated_mean  # chi + sigma*lambda (34)
            yhat = _limit_terms(p_lo, lo) + gam * tmean + _limit_terms(p_hi, hi)  # (21), (37)
            if self.exact_tobit_variance:  # law of total variance (option, docs/sources GF-05)
                with np.errstate(invalid="ignore"):
                    noise = (
                        gam * (st.truncated_var + (tmean - yhat) ** 2)
                        + _limit_terms(p_lo, (lo - yhat) ** 2)
                        + _limit_terms(p_hi, (hi - yhat) ** 2)
                    )
            else:
                noise = st.truncated_var  # R (1 - psi), (25)-(26), (12)
            lam = st.inverse_mills
        else:  # fading means, no censoring handling: gamma = 1, lambda = psi = 0
            gam = np.ones((N, m))
            yhat = chi
            noise = np.broadcast_to(sigma**2, (N, m))
            lam = np.zeros((N, m))
        if self.fading_variance_term:
            Dk = sum(self._thv[s] * carry["cxxc"][:, s] for s in range(top + 1))
            noise = noise + gam**2 * Dk
        mp = MeasurementPrediction(
            expected=yhat,
            H0=H,
            scale=gam,
            noise=noise,
            extras={"p_uncensored": gam, "expected_y": yhat, "inverse_mills": lam},
        )
        return mp, carry

    def _extras(self, k, xp, Pp, x, P, mp, K, Ree, options):
        extras = dict(mp.extras)
        n, L = self.n, self.L
        N = x.shape[0]
        if options.get("keep_smoothed", True):
            sm_mean = x.reshape(N, L + 1, n).copy()
            Pb = np.broadcast_to(P, (N,) + P.shape[1:])
            sm_cov = np.empty((N, L + 1, n, n))
            for s in range(L + 1):  # diagonal blocks by slicing (a fancy-index gather costs 5x more)
                sm_cov[:, s] = Pb[:, s * n : (s + 1) * n, s * n : (s + 1) * n]
            if k <= L:  # blocks s > k stand for x_{k-s}, k-s < 0: not defined
                sm_mean[:, k + 1 :] = np.nan
                sm_cov[:, k + 1 :] = np.nan
            extras["smoothed_mean"], extras["smoothed_cov"] = sm_mean, sm_cov
        if options.get("keep_augmented", False):
            extras.update(
                aug_mean=x,
                aug_cov=np.broadcast_to(P, (N,) + P.shape[1:]),
                aug_pred_mean=xp,
                aug_pred_cov=np.broadcast_to(Pp, (N,) + Pp.shape[1:]),
                gain=np.broadcast_to(K, (N,) + K.shape[1:]),
                innovation_cov=None if Ree is None else np.broadcast_to(Ree, (N,) + Ree.shape[1:]),
            )
            if extras["innovation_cov"] is None:
                del extras["innovation_cov"]
        return extras

    def _check_record(self, y2, u2, k0, name="y"):
        super()._check_record(y2, u2, k0, name)
        self._cens.check(self.m, k0 + y2.shape[1])
        if self.tobit and self.check_limits:
            self._cens.check_measurements(y2, name, start=k0 + 1)

    def _check_reading(self, k, y, options):
        # the checks of _check_record for one step, without its record-wide calls (the limits' channels were
        # checked at construction; the one-step limit check directly): ~2.5 µs of an online step
        self._check_horizon(k)
        cens = self._cens
        if cens.time_varying:
            cens.check(self.m, k)
        if self.tobit and self.check_limits:
            cens.check_reading(y, k)

    def _prepare_step_options(self, state, options):
        # a plain step has none: no comprehension's frame (~0.2 µs) for an empty dict
        return {k: bool(v) for k, v in options.items()} if options else {}

    _filter_params = {
        "x0": "array_like, optional\n"
        "    Override the prior mean of :math:`x_0` (the augmented state's window blocks start from it), ``(n,)``\n"
        "    or ``(..., n)``.",
        "keep_augmented": "bool, default False\n"
        "    Also return the full augmented :math:`\\hat\\xi`, :math:`\\mathcal P` (filtered and predicted), the gain\n"
        "    and :math:`\\Sigma_{\\tilde y\\tilde y}` in ``extras``.",
        "keep_smoothed": "bool, default True\n"
        "    Return the fixed-lag smoothed blocks (``extras['smoothed_mean']``, ``extras['smoothed_cov']``); False\n"
        "    saves memory ((..., T, L+1, n, n)) in large Monte Carlo runs and changes nothing else.",
    }

    def filter(
        self,
        y: Any,
        *,
        u: Any = None,
        x0: Any = None,
        P0: Any = None,
        keep_augmented: bool = False,
        keep_smoothed: bool = True,
        outputs: Any = "all",
        state: FilterState | None = None,
    ) -> FilterResult:
        # the shared loop with the two keywords as step options (not ``super().filter``: it takes none)
        return self._run(
            y,
            u,
            x0,
            P0,
            outputs=outputs,
            state=state,
            step_options={"keep_smoothed": keep_smoothed, "keep_augmented": keep_augmented},
        )


class FadingTobitKalmanFilter(_FadingFamily):
    r"""Tobit Kalman filter with L-th order Rice fading measurements (TKF-FM; Geng et al. 2017).

    Parameters
    ----------
    system : LinearSystem
        The state model and the (unfaded) measurement matrix :math:`C_k`; diagonal R.
    fading : RiceFading
        The fading channel (order L, coefficient law).
    censoring : Censoring, optional
        Censoring limits; default none.
    p_uncensored_mode : {"augmented", "eq6_stale"}, default "augmented"
    fading_variance_term : bool, default False
    exact_tobit_variance : bool, default False
    covariance_update : {"joseph", "standard", "square_root"}, default "joseph"
        See :func:`fading_tobit_kalman_filter` and the module docstring ("Deviation from the source");
        the Joseph form is the default because the source's repaired (20') is stated in it.
    check_limits : bool, default True
        Raise if a reading lies outside its censoring limits.
    backend : {"auto", "numpy", "numba"}, default "auto"
        ``filter`` and ``step`` through the one compiled loop of :mod:`tobitkf.filters._compiled_loop` or the
        numpy reference path; see :func:`fading_tobit_kalman_filter`.

    Raises
    ------
    ValidationError
        Wrong argument types, an unknown option value, non-diagonal R.
    TypeError
        An unknown keyword.

    Examples
    --------
    The oscillator of the source (Sec. 4.1) with L = 2 fading and censoring at 0:

    >>> import numpy as np, tobitkf as tk
    >>> from tobitkf.channels.fading import RiceFading
    >>> w = 0.052 * np.pi
    >>> sys = tk.LinearSystem(A=[[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]], C=[[1.0, 0.0]],
    ...                       Q=0.0025 * np.eye(2), R=[[1.0]], x0=[5.0, 0.0], P0=np.eye(2))
    >>> fad = RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    >>> cens = tk.Censoring(lower=0.0)
    >>> data = tk.simulate(sys, steps=50, runs=200, censoring=cens, measurement=fad, seed=0)
    >>> out = FadingTobitKalmanFilter(sys, fad, cens).filter(data.y)
    >>> out.mean.shape, out.extras["smoothed_mean"].shape       # x̂_{k|k} and x̂_{k-s|k}, s = 0..2
    ((200, 50, 2), (200, 50, 3, 2))
    >>> bool(tk.metrics.rmse(data.x, out.mean).mean() < 0.5)
    True

    Notes
    -----
    Cost per step :math:`O((n(L+1))^3 + m^3)` (Remark 10), dominated by the Joseph update;
    the prediction uses the shift structure of :math:`\mathcal A_k`. The covariance recursion
    depends on the data (through :math:`\bar\gamma, \lambda, \psi`), so it is run per run.
    Online use: :meth:`step` (``keep_smoothed``/``keep_augmented`` are filter options only).

    References
    ----------
    .. [1] H. Geng, Z. Wang, Y. Liang, Y. Cheng, F. E. Alsaadi, "Tobit Kalman filter with fading
       measurements", Signal Processing 140 (2017) 60–68.
    .. [2] B. Allik, C. Miller, M. J. Piovoso, R. Zurakowski, "The Tobit Kalman filter: an estimator
       for censored measurements", IEEE TCST 24(1) (2016) 365–371.
    """

    _name = "FadingTobitKalmanFilter"
    _filter_doc = """Filter censored fading measurements ``y`` (..., T, m) with the TKF-FM (Geng et al. 2017, the
    repaired (20'), (25)); see :func:`fading_tobit_kalman_filter`."""
    _filter_raises = "a reading outside its censoring limits (``check_limits``)"
    _fading_mats: tuple[Any, tuple[np.ndarray, ...]]  # the system; its A, Qd, H_0..H_L, sigma for the loop; set once
    _fading_flat: tuple[Any, np.ndarray]  # the system and the online step's flat constants, set once
    _loop_limits: np.ndarray  # the online step's constant limits (2, 1, m), set once

    def __init__(
        self,
        system: LinearSystem,
        fading: RiceFading,
        censoring: Censoring | None = None,
        *,
        p_uncensored_mode: str = "augmented",
        fading_variance_term: bool = False,
        exact_tobit_variance: bool = False,
        covariance_update: str = "joseph",
        check_limits: bool = True,
        backend: str = "auto",
    ):
        _check_parts(system, fading, censoring)
        check_keywords(
            {
                "p_uncensored_mode": p_uncensored_mode,
                "fading_variance_term": fading_variance_term,
                "exact_tobit_variance": exact_tobit_variance,
                "covariance_update": covariance_update,
                "backend": backend,
            },
            _TOBIT_OPTIONS,
        )
        check_square_root(backend, covariance_update, "the fading Tobit Kalman filter")
        self.backend = backend
        self._setup(
            system,
            fading,
            censoring,
            tobit=True,
            p_uncensored_mode=p_uncensored_mode,
            fading_variance_term=fading_variance_term,
            exact_tobit_variance=exact_tobit_variance,
            covariance_update=covariance_update,
            check_limits=check_limits,
        )
        self.options = {
            "p_uncensored_mode": p_uncensored_mode,
            "fading_variance_term": fading_variance_term,
            "exact_tobit_variance": exact_tobit_variance,
            "covariance_update": covariance_update,
        }

    # ---- the compiled path (``filter``, and ``step`` through _compiled_step) ----------------------------------
    def _compiled_filter(self, y2, u2, state, want, batch, step_options=None):
        ok = self._compiled_ok(u2, bool(step_options.get("keep_augmented")))
        return (
            _finite_or_none(_compiled_run(self, y2, u2, state, want, batch, bool(step_options["keep_smoothed"])))
            if ok
            else None
        )

    def _compiled_online_step(self, state, y, u, options):
        """One online step through the compiled loop (T = 1), with the numpy step's extras; None (the numpy step
        runs) where the loop does not cover the case or the covariance stopped being finite."""
        keep_smoothed = bool(options.get("keep_smoothed", True)) if options else True
        if u is None and not (options and options.get("keep_augmented")):  # the plain step: decided once
            ok = self.__dict__.get("_compiled_static")
            if ok is None:
                ok = self._compiled_ok(None, False)
            return _compiled_step(self, y, state, keep_smoothed) if ok else None
        if not self._compiled_ok(u, bool(options.get("keep_augmented"))):
            return None
        N = y.shape[0]
        res = _compiled_run(
            self, y.reshape(N, 1, self.m), u.reshape(N, 1, -1), state, _STEP_OUTPUTS, (N,), keep_smoothed
        )
        if not finite_variances(res.final.P):
            return None
        extras = {key: val[:, 0] for key, val in res.extras.items()}
        return step_state(state.k + 1, state.batch_shape, res.final.x, res.final.P, self.n, None, state.carry, extras)

    def _compiled_ok(self, u, keep_augmented: bool) -> bool:
        """Whether the compiled loop runs this call: decided once per estimator for the call without input and
        ``keep_augmented``, else afresh (raises for ``backend="numba"`` and a case it does not cover)."""
        what = "the fading Tobit Kalman filter"
        if u is None and not keep_augmented:
            ok = self.__dict__.get("_compiled_static")
            if ok is None:
                ok = self._compiled_static = use_compiled(self.backend, _compiled_gap(self, None), what)
            return ok
        return use_compiled(self.backend, "keep_augmented=True" if keep_augmented else _compiled_gap(self, u), what)


class FadingKalmanFilter(_FadingFamily):
    r"""Augmented Kalman filter with the fading means, no censoring handling (baseline "kf-fm").

    Parameters
    ----------
    system : LinearSystem
    fading : RiceFading
    fading_variance_term : bool, default False
    covariance_update : {"joseph", "standard", "square_root"}, default "joseph"
        See :func:`fading_kalman_filter`.
    """

    _name = "FadingKalmanFilter"
    _filter_doc = """Filter fading measurements ``y`` (..., T, m) with the augmented Kalman filter on the fading means
    (no censoring handling, the baseline "kf-fm"); see :func:`fading_kalman_filter`."""

    def __init__(
        self,
        system: LinearSystem,
        fading: RiceFading,
        *,
        fading_variance_term: bool = False,
        covariance_update: str = "joseph",
    ):
        _check_parts(system, fading, None)
        check_keywords(
            {"fading_variance_term": fading_variance_term, "covariance_update": covariance_update}, _KF_OPTIONS
        )
        self._setup(
            system,
            fading,
            None,
            tobit=False,
            fading_variance_term=fading_variance_term,
            covariance_update=covariance_update,
            check_limits=False,
        )
        self.options = {"fading_variance_term": fading_variance_term, "covariance_update": covariance_update}


def fading_tobit_kalman_filter(
    system: LinearSystem,
    fading: RiceFading,
    censoring: Censoring | None,
    y: Any,
    *,
    u: Any = None,
    p_uncensored_mode: str = "augmented",
    fading_variance_term: bool = False,
    exact_tobit_variance: bool = False,
    covariance_update: str = "joseph",
    x0: Any = None,
    P0: Any = None,
    keep_augmented: bool = False,
    keep_smoothed: bool = True,
    check_limits: bool = True,
    backend: str = "auto",
) -> FilterResult:
    r"""Run the Tobit Kalman filter with fading measurements (Theorems 1–2, Table 1) over a batch.

    Parameters
    ----------
    system : LinearSystem
        :math:`A_k, B_k, Q_k, C_k, R_k, \bar x_0, P_0`; R must be diagonal (App. B, GF-13).
    fading : RiceFading
        Channel order L and the law of :math:`\vartheta(s)`; the filter uses the means
        :math:`\bar\vartheta(s)` (and the variances only with ``fading_variance_term``).
    censoring : Censoring or None
        Limits :math:`\mathcal I` (the source: lower only); None for no censoring.
    y : (..., T, m) array_like
        Censored measurements y_1..y_T (a censored reading equals its limit); NaN = missing.
    u : (T, p) or (..., T, p) array_like, optional
        Control inputs (not in the source; enter the first block through ``Bu`` and the
        measurement unfaded through ``D``).
    p_uncensored_mode : {"augmented", "eq6_stale"}, default "augmented"
        How :math:`\bar\gamma_k` of (6) is evaluated (module docstring, GF-03).
    fading_variance_term : bool, default False
        Add the fading-variance term to (25) (module docstring, GF-04).
    exact_tobit_variance : bool, default False
        Use the exact censored variance instead of (12) in (25) (module docstring, GF-05).
    covariance_update : {"joseph", "standard", "square_root"}, default "joseph"
        Form of the repaired (20') (``"square_root"``: the QR array form, not in the source).
    x0, P0 : array_like, optional
        Override the system's prior ``(..., n)``, ``(..., n, n)``.
    keep_augmented : bool, default False
        Also return the full augmented :math:`\hat\xi`, :math:`\mathcal P` (filtered and
        predicted), the gain and :math:`\Sigma_{\tilde y\tilde y}` in ``extras``.
    keep_smoothed : bool, default True
        Return the fixed-lag smoothed blocks; False saves memory ((..., T, L+1, n, n)) in
        large Monte Carlo runs and changes nothing else.
    check_limits : bool, default True
        Raise if a reading lies outside its censoring limits.
    backend : {"auto", "numpy", "numba"}, default "auto"
        ``"numba"`` runs the one compiled loop of :mod:`tobitkf.filters._compiled_loop` (equal to the
        numpy path to rounding; it covers a time-invariant system, control inputs through a constant
        ``Bu`` and ``D``, ``p_uncensored_mode="augmented"``, ``fading_variance_term=False``, the Joseph
        and standard forms, ``keep_augmented=False``) and raises for another case; ``"auto"`` uses it when numba is
        installed and the case is covered, else numpy; ``"numpy"`` always runs the numpy loop (its censored
        statistics from the compiled function the compiled loop calls, on every backend).

    Returns
    -------
    FilterResult
        ``mean`` (..., T, n) :math:`\hat x_{k|k}`, ``cov`` (..., T, n, n), ``pred_mean``,
        ``pred_cov`` (27)–(28); ``extras``: ``p_uncensored``, ``expected_y``,
        ``inverse_mills`` (..., T, m); ``smoothed_mean`` (..., T, L+1, n) and
        ``smoothed_cov`` (..., T, L+1, n, n), block s at index k-1 being
        :math:`\hat x_{k-s|k}` (NaN for s > k); with ``keep_augmented`` also ``aug_mean``,
        ``aug_cov``, ``aug_pred_mean``, ``aug_pred_cov``, ``gain``, ``innovation_cov``.

    Raises
    ------
    ValidationError
        Non-diagonal R, an unknown option, a reading outside the limits, wrong types;
        ``backend="numba"`` for a case the compiled loop does not cover.
    ImportError
        ``backend="numba"`` without numba installed.
    ShapeError
        Malformed ``y``, ``u``, limits, or a fading law that does not fit m channels.

    Examples
    --------
    With L = 0, unit gain and no censoring the filter is the Kalman filter:

    >>> import numpy as np, tobitkf as tk
    >>> from tobitkf.channels.fading import RiceFading
    >>> sys = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.01]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    >>> y = np.array([[0.5], [1.0], [-0.2]])
    >>> a = fading_tobit_kalman_filter(sys, RiceFading(0, [1.0]), None, y).mean
    >>> bool(np.allclose(a, tk.KalmanFilter(sys).filter(y).mean, rtol=0, atol=1e-12))
    True
    """
    est = FadingTobitKalmanFilter(
        system,
        fading,
        censoring,
        p_uncensored_mode=p_uncensored_mode,
        fading_variance_term=fading_variance_term,
        exact_tobit_variance=exact_tobit_variance,
        covariance_update=covariance_update,
        check_limits=check_limits,
        backend=backend,
    )
    return est.filter(y, u=u, x0=x0, P0=P0, keep_augmented=keep_augmented, keep_smoothed=keep_smoothed)


def fading_kalman_filter(
    system: LinearSystem,
    fading: RiceFading,
    y: Any,
    *,
    u: Any = None,
    fading_variance_term: bool = False,
    covariance_update: str = "joseph",
    x0: Any = None,
    P0: Any = None,
    keep_augmented: bool = False,
    keep_smoothed: bool = True,
) -> FilterResult:
    r"""Kalman filter on the augmented model with the fading means and no censoring handling.

    The baseline "KF with fading means" (ours, not in the source; docs/sources GF-17): the TKF-FM with
    :math:`\bar\gamma \equiv 1`, :math:`\lambda \equiv \psi \equiv 0`, i.e. a Kalman filter with
    :math:`H_k = \bar\theta_k\mathcal C_k` and :math:`R_k`, fed censored readings as if they
    were exact. With ``fading_variance_term=True`` and no censoring it is the LMMSE fading
    filter (Hu, Wang, Gao 2013, the source's ref. [40]).

    Parameters and returns as :func:`fading_tobit_kalman_filter` (without censoring options).
    """
    est = FadingKalmanFilter(
        system, fading, fading_variance_term=fading_variance_term, covariance_update=covariance_update
    )
    return est.filter(y, u=u, x0=x0, P0=P0, keep_augmented=keep_augmented, keep_smoothed=keep_smoothed)


def fading_estimators(
    system: LinearSystem, fading: RiceFading, censoring: Censoring | None = None, **options: Any
) -> dict[str, Any]:
    """The TKF-FM and its baselines, keyed as in the experiments.

    The source compares with the TKF only; the others are ours (docs/sources GF-17).

    ``"tkf-fm"`` :class:`FadingTobitKalmanFilter` (``options`` passed on); ``"tkf"`` the
    TKF of Allik et al. [11] on the unfaded model (the source's comparator, mis-modelled
    on fading data); ``"kf"`` the plain Kalman filter; ``"kf-fm"`` :class:`FadingKalmanFilter`.
    """
    cens = Censoring() if censoring is None else censoring
    return {
        "tkf-fm": FadingTobitKalmanFilter(system, fading, censoring, **options),
        "tkf": TobitKalmanFilter(system, cens),
        "kf": KalmanFilter(system),
        "kf-fm": FadingKalmanFilter(system, fading),
    }


# --------------------------------------------------------------------------- the compiled path


def _compiled_gap(est: FadingTobitKalmanFilter, u) -> str | None:
    """Why the compiled loop cannot run ``est`` on input ``u`` (None when it can); ``keep_augmented`` is checked by
    the caller."""
    gap = check_square_root(est.backend, est.covariance_update, "the fading Tobit Kalman filter")
    gap = gap or system_gap(est.system, u, inputs=True)
    if gap is None and est.p_uncensored_mode != "augmented":
        gap = f"p_uncensored_mode={est.p_uncensored_mode!r}"
    if gap is None and est.fading_variance_term:
        gap = "fading_variance_term=True"
    return gap


def _loop_constants(est: FadingTobitKalmanFilter) -> tuple[np.ndarray, ...]:
    """A, B Q B^T (n, n), the stack H_0..H_L (L+1, m, nxi) and σ (m,) as contiguous float64, once per estimator
    (keyed on the system: an estimator copied onto another)."""
    cached = est.__dict__.get("_fading_mats")
    if cached is None or cached[0] is not est.system:
        sys_ = est.system
        Hs = np.stack([augmented_measurement_matrix(sys_, est.fading, j) for j in range(est.L + 1)])
        mats = tuple(
            np.ascontiguousarray(a, dtype=float) for a in (sys_.transition(0), sys_.process_cov(0), Hs, est._sigma)
        )
        cached = est._fading_mats = (sys_, mats)
    return cached[1]


def fading_step_constants(est: FadingTobitKalmanFilter) -> np.ndarray:
    """The constants of :func:`~tobitkf.filters._compiled_entries.fading_step` as one flat float64 array, built once
    per estimator: n, the noise code (1: the censored variance), the Joseph flag, then ``A``, ``B Q B^T``, ``H_0 ..
    H_L`` and σ of :func:`_loop_constants`."""
    cached = est.__dict__.get("_fading_flat")
    if cached is None or cached[0] is not est.system:  # keyed on the system (an estimator copied onto another)
        head = [float(est.n), float(est.exact_tobit_variance), float(est.covariance_update == "joseph")]
        flat = np.concatenate([np.array(head)] + [a.ravel() for a in _loop_constants(est)])
        cached = est._fading_flat = (est.system, flat)
    return cached[1]


def _undefined_blocks(sm_mean: np.ndarray, sm_cov: np.ndarray | None, k0: int, L: int) -> None:
    """NaN into the smoothed blocks s > k (x_{k-s} before the record's start) of the steps k = k0 + 1 .. L, in
    place: ``sm_mean`` (N, T, L+1, n), ``sm_cov`` (N, T, L+1, n, n) (the numpy path's ``_extras``)."""
    for t in range(min(sm_mean.shape[1], L - k0)):
        k = k0 + t + 1
        sm_mean[:, t, k + 1 :] = np.nan
        if sm_cov is not None:
            sm_cov[:, t, k + 1 :] = np.nan


def _compiled_run(est: FadingTobitKalmanFilter, y2, u2, state: FilterState, want, batch, keep_smoothed):
    """The compiled loop (update :data:`~tobitkf.filters._compiled_loop.FADING`) from ``state`` (augmented x, P);
    outputs on request, as the numpy path's. With the smoothed blocks requested the loop writes the mean (top block)
    and then every block of the state into one output ((N, T, n + nxi)), the covariance's top block and then the
    diagonal blocks into another ((N, T, n + nxi, n)), and ``mean``, ``cov`` and the smoothed blocks are views
    of them (:func:`~tobitkf.filters._compiled_block._stage_mean`, ``_stage_cov``)."""
    from ._compiled_loop import FADING_KIND, compiled_loop
    from ._loop_specs import LoopArguments

    N, T, m = y2.shape
    n, L, nxi = est.n, est.L, est._nxi
    A, Qd, Hs, sigma = _loop_constants(est)
    k0 = state.k
    TH = min(T, max(L - k0, 0) + 1)  # the rows H_min(k, L) of the steps k0 + 1 .. k0 + TH (then constant)
    H = Hs[np.minimum(k0 + 1 + np.arange(TH), L)]
    lo, hi = est._cens.all_limits(T, m, start=k0 + 1)
    assert state.P is not None, "the compiled loop runs the Joseph and standard forms, which carry P"
    ext = "extras" in want
    sm = ext and keep_smoothed
    state_out: tuple[tuple[bool, tuple[int, ...]], ...] = state_specs(want, n)[:2]
    top = n if sm and "mean" in want else 0  # the mean's rows ahead of the smoothed blocks (_stage_mean)
    ctop = n if sm and ("cov" in want or "var" in want) else 0
    if sm:
        state_out = ((True, (top + nxi,)), (True, (ctop + nxi, n)))
    means, covs, pmeans, pcovs, pu, ey, lam = output_arrays(
        N,
        T,
        *state_out,
        ("pred_mean" in want, (n,)),
        ("pred_cov" in want, (n, n)),
        (ext, (m,)),
        (ext, (m,)),
        (ext, (m, 1)),
    )
    bu, du = _input_terms(est, u2, N, T)
    x_last, P_last = np.empty((N, nxi)), np.empty((N, nxi, nxi))
    args = LoopArguments(
        FADING_KIND, loop_input(y2), A=A[None, None], Qd=Qd[None, None], H=np.ascontiguousarray(H), r=sigma[None, None],
        lo=loop_input(lo)[None], hi=loop_input(hi)[None], J=1, noise_code=int(est.exact_tobit_variance),
        joseph=est.covariance_update == "joseph", bu=bu, du=du, x0=loop_input(state.x), P0=loop_input(state.P),
        means=means, covs=covs, pmeans=pmeans, pcovs=pcovs, pu=pu, ey=ey, comp=lam, x_last=x_last, P_last=P_last,
    )  # fmt: skip
    compiled_loop(*args.filled())

    def out(a):
        return loop_array(a, batch)

    extras: dict[str, Any] = {}
    if ext:
        extras = {"p_uncensored": out(pu), "expected_y": out(ey), "inverse_mills": out(lam.reshape(N, T, m))}
    if sm:
        sm_mean, sm_cov = means[:, :, top:].reshape(N, T, L + 1, n), covs[:, :, ctop:].reshape(N, T, L + 1, n, n)
        _undefined_blocks(sm_mean, sm_cov, k0, L)
        extras.update(smoothed_mean=out(sm_mean), smoothed_cov=out(sm_cov))
        # the mean and the covariance: the rows the loop wrote ahead of the smoothed blocks, views (no copy; the
        # result's arrays share no element)
        means = means[:, :, :n] if top else _empty((N, 0, n))
        if "cov" in want:
            covs = covs[:, :, :n]
        elif "var" in want:  # the layout of cov_spec: the variances alone
            covs = np.diagonal(covs[:, :, :n], axis1=-2, axis2=-1)[..., None].copy()
        else:
            covs = _empty((N, 0, n, n))
    final = FilterState(k=k0 + T, batch_shape=batch, x=x_last, P=P_last, n=n, carry=state.carry)
    return compiled_result(want, batch, T, means, covs, pmeans, pcovs, extras, final)


def _input_terms(est: FadingTobitKalmanFilter, u2, N: int, T: int) -> tuple[np.ndarray, np.ndarray]:
    """The loop's input arrays from ``u2`` (N, T, p) or None: ``bu`` = :math:`B^uu_k` (N, T, n) entering the top
    block of the prediction and ``du`` = :math:`Du_k` (N, T, m) the readings' feedthrough, each (N, 0, ...) when
    absent (the numpy path's ``u @ Bu.T``, ``u @ D.T``)."""
    sys_ = est.system
    bu = _empty((N, 0, est.n)) if u2 is None or sys_.Bu is None else loop_input(u2 @ sys_.Bu.at(1).T)
    du = _empty((N, 0, est.m)) if u2 is None or sys_.D is None else loop_input(u2 @ sys_.D.at(1).T)
    return bu, du


def _compiled_step(est: FadingTobitKalmanFilter, y: np.ndarray, state: FilterState, keep_smoothed: bool):
    """One online step (y (N, m), no input) through the loop by its entry of 11 arguments
    (:func:`~tobitkf.filters._compiled_entries.fading_step`): the constants flattened into one array and the limits
    into another, once per estimator for constant limits; None when the covariance stopped being finite (the numpy
    step then reruns it and reports the divergence)."""
    N, m = y.shape
    n, L, nxi = est.n, est.L, est._nxi
    k = state.k + 1
    cens = est._cens
    lohi = None if cens.time_varying else est.__dict__.get("_loop_limits")
    if lohi is None:
        lohi = np.empty((2, 1, m))  # writable (a read-only argument would compile the loop once more)
        lohi[0], lohi[1] = cens.limits(k)
        if not cens.time_varying:
            est._loop_limits = lohi  # constant limits: converted once
    out3 = np.empty((3, N, m))  # p_uncensored, E[y], the inverse Mills ratios
    if keep_smoothed:
        sm_mean, sm_cov = np.empty((N, L + 1, n)), np.empty((N, L + 1, n, n))
    else:
        sm_mean, sm_cov = _empty((N, 0, n)), _empty((N, 0, n, n))
    x_last, P_last = np.empty((N, nxi)), np.empty((N, nxi, nxi))
    assert state.P is not None, "the compiled loop runs the Joseph and standard forms, which carry P"
    loop_entries().fading_step(
        loop_input(y),
        fading_step_constants(est),
        lohi,
        k,
        loop_input(state.x),
        loop_input(state.P),
        out3,
        sm_mean,
        sm_cov,
        x_last,
        P_last,
    )
    if not finite_variances(P_last):  # the check of _finite_or_none
        return None
    extras = {"p_uncensored": out3[0], "expected_y": out3[1], "inverse_mills": out3[2]}
    if keep_smoothed:
        if k <= L:  # blocks s > k stand for x_{k-s}, k-s < 0: not defined
            sm_mean[:, k + 1 :] = np.nan
            sm_cov[:, k + 1 :] = np.nan
        extras["smoothed_mean"], extras["smoothed_cov"] = sm_mean, sm_cov
    return step_state(k, state.batch_shape, x_last, P_last, n, None, state.carry, extras)


register(
    family_entry(
        FadingTobitKalmanFilter,
        "TKF with L-th order Rice fading (Geng et al. 2017)",
        ("fading", "censoring?"),
        options=_TOBIT_OPTIONS,
    ),
    family_entry(
        FadingKalmanFilter,
        "augmented KF with the fading means, no censoring handling (Geng et al. 2017)",
        ("fading",),
        options=_KF_OPTIONS,
    ),
)
