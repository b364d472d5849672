r"""Tobit Kalman filter with Rice fading measurements (TKF-FM) and its baselines.

Source: Geng, Wang, Liang et al., "Tobit Kalman filter with fading measurements",
*Signal Processing* 2017 (seed ``000_a11dc7eb0f220328``); spec ``000_tkf_fading.md`` §2–4.

Model ((1)–(3) of the source):

.. math::

    x_{k+1} &= A_k x_k + B_k\omega_k, \qquad
    y^*_k = \sum_{s=0}^{\ell_k}\vartheta_k(s)C_{k-s}x_{k-s} + \upsilon_k, \quad \ell_k = \min\{L,k\} \\
    y_k &= \max(y^*_k, \mathcal I) \quad\text{(element-wise lower censoring)}

Augmented model (7)–(10), **fixed size** :math:`n_\xi = n(L+1)` from k = 0 (spec §2 [R], A7):
:math:`\xi_k = \mathrm{col}\{x_k, x_{k-1}, \dots, x_{k-L}\}`, the square shift matrix
:math:`\mathcal A_k` (block row 0 :math:`[A_k, 0, \dots]`, block row i an identity in
column i-1), :math:`\mathcal B_k = [B_k; 0; \dots]`,
:math:`H_k = \bar\theta_k\mathcal C_k = [\bar\vartheta(0)C_k, \dots, \bar\vartheta(\ell_k)C_{k-\ell_k}, 0, \dots]`.
The blocks for :math:`s > k` are zero-mean, zero-covariance placeholders with zero
columns in :math:`H_k`; they are never updated, so the filter equals the
growing-dimension one (tested).

Per step, Table 1 order (spec §4.2), :math:`\sigma_m = \sqrt{R^{mm}_k}`:

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
  (spec A2), in Joseph form by default.
* Typos read as in spec §7 A11: (17) is the augmented :math:`\mathcal A_{k-1}`; (27) defines
  :math:`\hat x_{k|k-1}`; :math:`\bar\theta_k` runs over s = 0..ℓ_k.
* :math:`\bar\gamma` in (6) is written with the letter of the Mills ratio; we call it
  ``p_uncensored`` and the stale mean of (6) :math:`\hat\mu` (A11b).

Options (all off by default; "Deviation from the source")
---------------------------------------------------------
* ``p_uncensored_mode``: ``"augmented"`` (default, spec §4.2 Step 3 [R]) evaluates (6) at
  :math:`\hat\chi_{k|k-1} = H_k\hat\xi_{k|k-1}`, consistent with (21)–(26).
  ``"eq6_stale"`` is (6) literally: :math:`\hat\mu^m = \sum_s \bar\vartheta^m(s)[C_{k-s}\hat x_{k-s|k-s-1}]^m`
  with the one-step predictions made at earlier steps (:math:`\hat x_{0|-1} := \bar x_0`) (A3).
* ``fading_variance_term=True`` adds :math:`\bar\Upsilon_kD_k\bar\Upsilon_k` to :math:`N_k`,
  :math:`D_k^{mm} = \sum_s\tilde\vartheta^m(s)[C_{k-s}X_{k-s}C_{k-s}^T]^{mm}`,
  :math:`X_{j+1} = A_jX_jA_j^T + B_jQ_jB_j^T`, :math:`X_0 = \bar x_0\bar x_0^T + P_0` (spec §4.6-1, A4;
  the source never uses the fading variances, so its filter is over-confident).
* ``exact_tobit_variance=True`` replaces (12) by the censored variance (law of total
  variance), :math:`N^{mm} = \bar\gamma R^{mm}(1-\psi) + \bar\gamma(1-\bar\gamma)(\hat\chi+\sigma\lambda-\mathcal I)^2`
  (spec §4.6-2, A5; (12) is the variance of the *uncensored part* only).
* ``covariance_update="standard"`` uses :math:`\mathcal P_{k|k-1} - K\Sigma_{\tilde y\tilde y}K^T`
  instead of the Joseph form (equal in exact arithmetic).

Upper limits (two-sided censoring) are a non-source extension: all censoring statistics
come from :func:`tobitkf.censored_moments`, which reduces to Lemma 1 for a lower limit.

Time convention: x_0 ~ N(x̄_0, P_0) is the prior; no update at k = 0; y_1 (stored at
index 0) is the first measurement and mixes x_1 and x_0 when L >= 1 (A10). Output
index k-1 holds x̂_{k|k}.

Code names -> paper symbols: ``mean`` x̂_{k|k}; ``cov`` P_{k|k}; ``pred_mean`` x̂_{k|k-1};
``p_uncensored`` :math:`\bar\gamma_k`; ``inverse_mills`` λ; ``expected_y`` :math:`\hat y_{k|k-1}`;
``smoothed_mean[..., k-1, s, :]`` :math:`\hat x_{k-s|k}`; ``aug_mean`` :math:`\hat\xi_{k|k}`;
``aug_cov`` :math:`\mathcal P_{k|k}`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._validation import ValidationError, check_instance
from ..censored import censored_moments
from ..channels.censoring import Censoring
from ..channels.fading import RiceFading, measurement_matrix_at
from ..models.linear import LinearSystem
from ._common import FilterResult, check_keywords, check_prior, gain_update, prepare_inputs, prepare_measurements
from .core import shift_predict
from .kalman import KalmanFilter
from .tobit import TobitKalmanFilter

__all__ = ["fading_tobit_kalman_filter", "FadingTobitKalmanFilter", "fading_kalman_filter",
           "FadingKalmanFilter", "augmented_measurement_matrix", "fading_estimators",
           "P_UNCENSORED_MODES"]

P_UNCENSORED_MODES = ("augmented", "eq6_stale")
_BOOL = (False, True)
_TOBIT_OPTIONS = {"p_uncensored_mode": P_UNCENSORED_MODES, "fading_variance_term": _BOOL,
                  "exact_tobit_variance": _BOOL, "covariance_update": ("joseph", "standard")}
_KF_OPTIONS = {"fading_variance_term": _BOOL, "covariance_update": ("joseph", "standard")}


def augmented_measurement_matrix(system: LinearSystem, fading: RiceFading, k: int) -> np.ndarray:
    r""":math:`H_k = \bar\theta_k\mathcal C_k`, zero-padded to ``(m, n(L+1))`` (spec §2).

    Block s (columns ``s*n:(s+1)*n``) is :math:`\bar\vartheta(s)C_{k-s}` for s <= min(L, k), else 0.
    """
    n, m, L = system.n, system.m, fading.order
    thb = fading.mean_gains(m)
    H = np.zeros((m, n * (L + 1)))
    for s in range(min(L, k) + 1):
        H[:, s * n:(s + 1) * n] = thb[s][:, None] * measurement_matrix_at(system, k - s)
    return H


def _sigma_of(R: np.ndarray, name: str) -> np.ndarray:
    # App. B of the source assumes cov{y^m, y^t} = 0 for m != t: R must be diagonal (A13).
    off = R - np.diag(np.diagonal(R))
    if np.abs(off).max(initial=0.0) > 1e-12 * max(1.0, float(np.abs(R).max())):
        raise ValidationError(f"{name}: the fading Tobit Kalman filter needs a diagonal R "
                              "(Geng et al. 2017, App. B: uncorrelated channels)")
    d = np.diagonal(R)
    if np.any(d <= 0):
        raise ValidationError(f"{name}: expected positive measurement variances, got {d}")
    return np.sqrt(d)


def _check_parts(system: Any, fading: Any, censoring: Any) -> None:
    check_instance(system, LinearSystem, "system")
    check_instance(fading, RiceFading, "fading")
    fading.check(system.m)
    if censoring is not None:
        check_instance(censoring, Censoring, "censoring")
        censoring.check(system.m)


def _limit_terms(p: np.ndarray, limit: np.ndarray) -> np.ndarray:
    """``p * limit`` with 0 where the limit is infinite (and so p = 0)."""
    return np.where(np.isfinite(limit), p * np.where(np.isfinite(limit), limit, 0.0), 0.0)


def _joseph_scalar_update(x: np.ndarray, P: np.ndarray, innov: np.ndarray, Rxe: np.ndarray, Ree: np.ndarray,
                          valid: np.ndarray | None, H0: np.ndarray, gam: np.ndarray, noise: np.ndarray):
    r"""What :func:`gain_update` with ``H=G, noise=N`` returns for one channel (m = 1), faster.

    :math:`K = R_{xe}/R_{ee}` (zero where the channel is missing or :math:`R_{ee}` is not above the
    smallest normal number, as in :func:`gain_update`), :math:`x + Ke`, and the Joseph form
    :math:`(I - KG)P(I - KG)^T + KNK^T` with :math:`G = \gamma H_0`, ``H0`` (n_xi,) common to all runs
    and ``P`` exactly symmetric: the rank-one factors are applied in turn,
    :math:`M = P - K(GP)` with :math:`GP = \gamma(PH_0)^T`, then :math:`M(I - G^TK^T) = M - \gamma(MH_0)K^T`:
    outer products and GEMVs over the stacked runs instead of batched (n_xi x n_xi) matmuls.
    ``x`` and ``K`` are bit-identical to :func:`gain_update`'s, ``P`` equal to rounding (tested).
    ``x`` (N, n_xi), ``P`` (N, n_xi, n_xi), ``innov`` (N, 1), ``Rxe`` (N, n_xi, 1), ``Ree`` (N, 1, 1),
    ``valid`` (N, 1) or None, ``gam`` and ``noise`` (N,).
    """
    N, nxi = x.shape
    ree = Ree[:, 0, 0]
    ok = ree > np.finfo(np.float64).tiny
    if valid is not None:
        ok &= valid[:, 0]
    K = Rxe * ok[:, None, None] / np.where(ok, ree, 1.0)[:, None, None]
    x_new = x + np.einsum("...ij,...j->...i", K, np.where(ok[:, None], innov, 0.0))
    k = K[:, :, 0]
    PG = gam[:, None] * (P.reshape(-1, nxi) @ H0).reshape(N, nxi)
    M = P - k[:, :, None] * PG[:, None, :]
    MG = gam[:, None] * (M.reshape(-1, nxi) @ H0).reshape(N, nxi)
    P_new = M - (MG - noise[:, None] * k)[:, :, None] * k[:, None, :]
    return x_new, 0.5 * (P_new + np.swapaxes(P_new, -1, -2)), K


def _run(system: LinearSystem, fading: RiceFading, censoring: Censoring | None, y: Any, *, u: Any, tobit: bool,
         p_uncensored_mode: str, fading_variance_term: bool, exact_tobit_variance: bool,
         covariance_update: str, x0: Any, P0: Any, keep_augmented: bool, check_limits: bool,
         keep_smoothed: bool = True) -> FilterResult:
    """The time loop shared by the TKF-FM and the fading KF baseline (``tobit=False``)."""
    _check_parts(system, fading, censoring)
    y2, batch = prepare_measurements(y, system.m)
    N, T, m = y2.shape
    n, L = system.n, fading.order
    nxi = n * (L + 1)
    system.check_horizon(T)
    for part in (system.A, system.C, system.Q, system.R, system.B):
        if part is not None:
            part.validate_all(T)
    if censoring is None:
        censoring = Censoring()
    censoring.check(m, T)
    if tobit and check_limits:
        censoring.check_measurements(y2)
    lo_all, hi_all = censoring.all_limits(T, m)
    u2 = prepare_inputs(system, u, N, T)
    x_init, P_init = check_prior(system, x0, P0, N)

    thb, thv = fading.mean_gains(m), fading.var_gains(m)
    Cs = [measurement_matrix_at(system, j) for j in range(T + 1)]
    sigma_const = None if system.R.varying else _sigma_of(system.measurement_cov(1), "R")

    # fixed-size augmentation: xi_0|0 = [x0; 0...], P_0|0 = blkdiag(P0, 0...)  (spec §2, §4.1)
    xi = np.zeros((N, nxi))
    xi[:, :n] = x_init
    P = np.zeros((N, nxi, nxi))
    P[:, :n, :n] = 0.5 * (P_init + np.swapaxes(P_init, -1, -2))   # exactly symmetric (the prediction relies on it)

    stale = tobit and p_uncensored_mode == "eq6_stale"
    if stale:   # C_j x̂_{j|j-1}, j = 0..T, with x̂_{0|-1} := x̄_0 (spec §4.2 Step 3)
        cx_pred = np.zeros((N, T + 1, m))
        cx_pred[:, 0] = x_init @ Cs[0].T
    if fading_variance_term:   # diag(C_j X_j C_j^T), X_j = E[x_j x_j^T] (spec §4.6-1)
        mom_mean, mom_cov = x_init.copy(), P_init.copy()
        cxxc = np.zeros((N, T + 1, m))
        cxxc[:, 0] = np.einsum("ij,njk,ik->ni", Cs[0], mom_cov, Cs[0]) + (mom_mean @ Cs[0].T) ** 2

    # outputs stored time-major (T, N, ...): each step writes one contiguous block instead of N
    # strided pieces; returned as (N, T, ...) views
    means = np.empty((T, N, n))
    covs = np.empty((T, N, n, n))
    pmeans = np.empty((T, N, n))
    pcovs = np.empty((T, N, n, n))
    if keep_smoothed:
        sm_mean = np.empty((T, N, L + 1, n))
        sm_cov = np.empty((T, N, L + 1, n, n))
    pu = np.empty((T, N, m))
    ey = np.empty((T, N, m))
    lam_out = np.empty((T, N, m))
    if keep_augmented:
        aug = {k: np.empty((T, N, nxi)) for k in ("aug_mean", "aug_pred_mean")}
        aug.update({k: np.empty((T, N, nxi, nxi)) for k in ("aug_cov", "aug_pred_cov")})
        aug["gain"] = np.empty((T, N, nxi, m))
        aug["innovation_cov"] = np.empty((T, N, m, m))
    diag = np.arange(m)

    for k in range(1, T + 1):
        A, Qd = system.transition(k - 1), system.process_cov(k - 1)
        uk = None if u2 is None else u2[:, k - 1]
        bx, dy = system.input_effect(k, uk)
        # (17)-(18) with the shift structure of the augmented A: O(n nxi^2) instead of O(nxi^3),
        # as GEMMs over the stacked runs
        xi_p, P_p = shift_predict(xi, P, A, Qd, bx)
        pmeans[k - 1], pcovs[k - 1] = xi_p[:, :n], P_p[:, :n, :n]                 # (27)-(28)

        H = augmented_measurement_matrix(system, fading, k)                     # (m, nxi)
        chi = xi_p @ H.T + dy                                                    # Lemma 1 at the prediction
        sigma = sigma_const if sigma_const is not None else _sigma_of(system.measurement_cov(k), f"R({k})")
        lo, hi = lo_all[k - 1], hi_all[k - 1]
        if stale:
            cx_pred[:, k] = xi_p[:, :n] @ Cs[k].T
        if fading_variance_term:
            mom_mean = mom_mean @ A.T + bx
            mom_cov = A @ mom_cov @ A.T + Qd
            cxxc[:, k] = np.einsum("ij,njk,ik->ni", Cs[k], mom_cov, Cs[k]) + (mom_mean @ Cs[k].T) ** 2

        if tobit:
            st = censored_moments(chi, sigma, lo, hi)
            if stale:   # (6) literally: mu = sum_s thbar(s) C_{k-s} x̂_{k-s|k-s-1}
                mu = dy + sum(thb[s] * cx_pred[:, k - s] for s in range(min(L, k) + 1))
                sp = censored_moments(mu, sigma, lo, hi)
                p_lo, gam, p_hi = sp.p_lower, sp.p_uncensored, sp.p_upper
            else:
                p_lo, gam, p_hi = st.p_lower, st.p_uncensored, st.p_upper
            tmean = st.truncated_mean                                            # chi + sigma*lambda (34)
            yhat = _limit_terms(p_lo, lo) + gam * tmean + _limit_terms(p_hi, hi)  # (21), (37)
            if exact_tobit_variance:   # law of total variance (option, spec §4.6-2)
                with np.errstate(invalid="ignore"):
                    noise = (gam * (st.truncated_var + (tmean - yhat) ** 2)
                             + _limit_terms(p_lo, (lo - yhat) ** 2) + _limit_terms(p_hi, (hi - yhat) ** 2))
            else:
                noise = st.truncated_var                                         # R (1 - psi), (25)-(26), (12)
            lam = st.inverse_mills
        else:   # fading means, no censoring handling: gamma = 1, lambda = psi = 0
            gam = np.ones((N, m))
            yhat = chi
            noise = np.broadcast_to(sigma**2, (N, m))
            lam = np.zeros((N, m))
        if fading_variance_term:
            Dk = sum(thv[s] * cxxc[:, k - s] for s in range(min(L, k) + 1))
            noise = noise + gam**2 * Dk

        G = gam[:, :, None] * H                                                  # (N, m, nxi)
        if m == 1:   # (24)-(25) as GEMVs over the stacked runs (H is common to all runs)
            Rxe = gam[:, :, None] * (P_p.reshape(-1, nxi) @ H[0]).reshape(N, nxi, 1)
            Ree = (gam * (Rxe[:, :, 0] @ H[0])[:, None])[:, :, None]
        else:
            Rxe = P_p @ np.swapaxes(G, -1, -2)                                   # (24)
            Ree = G @ Rxe                                                        # (25)
        Ree[:, diag, diag] += noise
        innov = y2[:, k - 1] - yhat
        missing = np.isnan(innov)
        valid = ~missing if missing.any() else None
        if valid is not None:
            innov = np.where(missing, 0.0, innov)
        if covariance_update == "joseph" and m == 1:                              # (20'), one channel
            xi, P, K = _joseph_scalar_update(xi_p, P_p, innov, Rxe, Ree, valid, H[0], gam[:, 0], noise[:, 0])
        elif covariance_update == "joseph":                                       # (20') Joseph form
            Nmat = np.zeros((N, m, m))
            Nmat[:, diag, diag] = noise
            xi, P, K = gain_update(xi_p, P_p, innov, Rxe, Ree, valid, H=G, noise=Nmat)
        else:                                                                    # (20') P - K S K^T
            xi, P, K = gain_update(xi_p, P_p, innov, Rxe, Ree, valid)

        means[k - 1], covs[k - 1] = xi[:, :n], P[:, :n, :n]                       # (29)-(30)
        if keep_smoothed:
            sm_mean[k - 1] = xi.reshape(N, L + 1, n)
            for s in range(L + 1):   # diagonal blocks by slicing (a fancy-index gather costs 5x more)
                sm_cov[k - 1, :, s] = P[:, s * n:(s + 1) * n, s * n:(s + 1) * n]
            if k <= L:   # blocks s > k stand for x_{k-s}, k-s < 0: not defined
                sm_mean[k - 1, :, k + 1:] = np.nan
                sm_cov[k - 1, :, k + 1:] = np.nan
        pu[k - 1], ey[k - 1], lam_out[k - 1] = gam, yhat, lam
        if keep_augmented:
            aug["aug_mean"][k - 1], aug["aug_cov"][k - 1] = xi, P
            aug["aug_pred_mean"][k - 1], aug["aug_pred_cov"][k - 1] = xi_p, P_p
            aug["gain"][k - 1], aug["innovation_cov"][k - 1] = K, Ree

    def out(arr: np.ndarray) -> np.ndarray:   # (T, N, ...) time-major store -> batch + (T, ...) view
        return np.moveaxis(arr, 0, 1).reshape(batch + (T,) + arr.shape[2:])

    extras = {"p_uncensored": out(pu), "expected_y": out(ey), "inverse_mills": out(lam_out)}
    if keep_smoothed:
        extras["smoothed_mean"] = out(sm_mean)
        extras["smoothed_cov"] = out(sm_cov)
    if keep_augmented:
        extras.update({key: out(val) for key, val in aug.items()})
    return FilterResult(mean=out(means), cov=out(covs), pred_mean=out(pmeans), pred_cov=out(pcovs), extras=extras)


def fading_tobit_kalman_filter(system: LinearSystem, fading: RiceFading, censoring: Censoring | None, y: Any, *,
                               u: Any = None, p_uncensored_mode: str = "augmented",
                               fading_variance_term: bool = False, exact_tobit_variance: bool = False,
                               covariance_update: str = "joseph", x0: Any = None, P0: Any = None,
                               keep_augmented: bool = False, keep_smoothed: bool = True,
                               check_limits: bool = True) -> FilterResult:
    r"""Run the Tobit Kalman filter with fading measurements (Theorems 1–2, Table 1) over a batch.

    Parameters
    ----------
    system : LinearSystem
        :math:`A_k, B_k, Q_k, C_k, R_k, \bar x_0, P_0`; R must be diagonal (App. B, A13).
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
        How :math:`\bar\gamma_k` of (6) is evaluated (module docstring, A3).
    fading_variance_term : bool, default False
        Add the fading-variance term to (25) (module docstring, A4).
    exact_tobit_variance : bool, default False
        Use the exact censored variance instead of (12) in (25) (module docstring, A5).
    covariance_update : {"joseph", "standard"}, default "joseph"
        Form of the repaired (20').
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
        Non-diagonal R, an unknown option, a reading outside the limits, wrong types.
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
    check_keywords({"p_uncensored_mode": p_uncensored_mode, "fading_variance_term": fading_variance_term,
                    "exact_tobit_variance": exact_tobit_variance, "covariance_update": covariance_update},
                   _TOBIT_OPTIONS)
    return _run(system, fading, censoring, y, u=u, tobit=True, p_uncensored_mode=p_uncensored_mode,
                fading_variance_term=bool(fading_variance_term), exact_tobit_variance=bool(exact_tobit_variance),
                covariance_update=covariance_update, x0=x0, P0=P0, keep_augmented=keep_augmented,
                check_limits=check_limits, keep_smoothed=keep_smoothed)


def fading_kalman_filter(system: LinearSystem, fading: RiceFading, y: Any, *, u: Any = None,
                         fading_variance_term: bool = False, covariance_update: str = "joseph",
                         x0: Any = None, P0: Any = None, keep_augmented: bool = False,
                         keep_smoothed: bool = True) -> FilterResult:
    r"""Kalman filter on the augmented model with the fading means and no censoring handling.

    The baseline "KF with fading means" of spec §4.7 [non-source]: the TKF-FM with
    :math:`\bar\gamma \equiv 1`, :math:`\lambda \equiv \psi \equiv 0`, i.e. a Kalman filter with
    :math:`H_k = \bar\theta_k\mathcal C_k` and :math:`R_k`, fed censored readings as if they
    were exact. With ``fading_variance_term=True`` and no censoring it is the LMMSE fading
    filter (Hu, Wang, Gao 2013, the source's ref. [40]).

    Parameters and returns as :func:`fading_tobit_kalman_filter` (without censoring options).
    """
    check_keywords({"fading_variance_term": fading_variance_term, "covariance_update": covariance_update},
                   _KF_OPTIONS)
    return _run(system, fading, None, y, u=u, tobit=False, p_uncensored_mode="augmented",
                fading_variance_term=bool(fading_variance_term), exact_tobit_variance=False,
                covariance_update=covariance_update, x0=x0, P0=P0, keep_augmented=keep_augmented,
                check_limits=False, keep_smoothed=keep_smoothed)


class FadingTobitKalmanFilter:
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
    covariance_update : {"joseph", "standard"}, default "joseph"
        See :func:`fading_tobit_kalman_filter` and the module docstring ("Deviation from the source").

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

    References
    ----------
    .. [1] H. Geng, Z. Wang, Y. Liang, Y. Cheng, F. E. Alsaadi, "Tobit Kalman filter with fading
       measurements", Signal Processing 140 (2017) 60–68 (spec ``000_tkf_fading.md``).
    .. [2] B. Allik, C. Miller, M. J. Piovoso, R. Zurakowski, "The Tobit Kalman filter: an estimator
       for censored measurements", IEEE TCST 24(1) (2016) 365–371.
    """

    def __init__(self, system: LinearSystem, fading: RiceFading, censoring: Censoring | None = None, *,
                 p_uncensored_mode: str = "augmented", fading_variance_term: bool = False,
                 exact_tobit_variance: bool = False, covariance_update: str = "joseph"):
        _check_parts(system, fading, censoring)
        check_keywords({"p_uncensored_mode": p_uncensored_mode, "fading_variance_term": fading_variance_term,
                        "exact_tobit_variance": exact_tobit_variance, "covariance_update": covariance_update},
                       _TOBIT_OPTIONS)
        if not system.R.varying:
            _sigma_of(system.measurement_cov(1), "R")
        self.system, self.fading, self.censoring = system, fading, censoring
        self.options = {"p_uncensored_mode": p_uncensored_mode, "fading_variance_term": fading_variance_term,
                        "exact_tobit_variance": exact_tobit_variance, "covariance_update": covariance_update}

    def filter(self, y: Any, *, u: Any = None, x0: Any = None, P0: Any = None, keep_augmented: bool = False,
               keep_smoothed: bool = True) -> FilterResult:
        """Filter censored fading measurements ``y`` (..., T, m); see :func:`fading_tobit_kalman_filter`."""
        return fading_tobit_kalman_filter(self.system, self.fading, self.censoring, y, u=u, x0=x0, P0=P0,
                                          keep_augmented=keep_augmented, keep_smoothed=keep_smoothed,
                                          **self.options)


class FadingKalmanFilter:
    r"""Augmented Kalman filter with the fading means, no censoring handling (baseline "kf-fm").

    Parameters
    ----------
    system : LinearSystem
    fading : RiceFading
    fading_variance_term : bool, default False
    covariance_update : {"joseph", "standard"}, default "joseph"
        See :func:`fading_kalman_filter`.
    """

    def __init__(self, system: LinearSystem, fading: RiceFading, *, fading_variance_term: bool = False,
                 covariance_update: str = "joseph"):
        _check_parts(system, fading, None)
        check_keywords({"fading_variance_term": fading_variance_term, "covariance_update": covariance_update},
                       _KF_OPTIONS)
        if not system.R.varying:
            _sigma_of(system.measurement_cov(1), "R")
        self.system, self.fading = system, fading
        self.options = {"fading_variance_term": fading_variance_term, "covariance_update": covariance_update}

    def filter(self, y: Any, *, u: Any = None, x0: Any = None, P0: Any = None, keep_augmented: bool = False,
               keep_smoothed: bool = True) -> FilterResult:
        """Filter ``y`` (..., T, m); see :func:`fading_kalman_filter`."""
        return fading_kalman_filter(self.system, self.fading, y, u=u, x0=x0, P0=P0, keep_augmented=keep_augmented,
                                    keep_smoothed=keep_smoothed, **self.options)


def fading_estimators(system: LinearSystem, fading: RiceFading, censoring: Censoring | None = None,
                      **options: Any) -> dict[str, Any]:
    """The TKF-FM and the baselines of spec §4.7, keyed as in the experiments.

    ``"tkf-fm"`` :class:`FadingTobitKalmanFilter` (``options`` passed on); ``"tkf"`` the
    TKF of Allik et al. [11] on the unfaded model (the source's comparator, mis-modelled
    on fading data); ``"kf"`` the plain Kalman filter; ``"kf-fm"`` :class:`FadingKalmanFilter`.
    """
    cens = Censoring() if censoring is None else censoring
    return {"tkf-fm": FadingTobitKalmanFilter(system, fading, censoring, **options),
            "tkf": TobitKalmanFilter(system, cens),
            "kf": KalmanFilter(system),
            "kf-fm": FadingKalmanFilter(system, fading)}
