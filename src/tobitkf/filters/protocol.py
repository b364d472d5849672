r"""Protocol-based Tobit Kalman filter with integral measurements and sensor failures (PBTKF-IMSF).

Source: Geng, Wang, Zou, Mousavi, Cheng, "Protocol-Based Tobit Kalman Filter under
Integral Measurements and Probabilistic Sensor Failures", Theorems 1–5 and Table I
(seed 003; spec ``spec/003_protocol_tkf.md`` §1.8–2.8). Channel:
:class:`tobitkf.channels.protocol.ProtocolChannel`.

Model (augmented form (9)–(10)), :math:`\xi_k = [x_k^T\; x_{k-1}^T \cdots x_{k-\ell}^T]^T`:

.. math::

    \xi_{k+1} &= \mathcal A_k \xi_k + \mathcal B\omega_k, \qquad
    y_k = \gamma_k\big(\Lambda_{h,k}\mathcal C_{h,k}\xi_k + v_{h,k}\big) + (1-\gamma_k)\tau, \\
    \mathcal C_{h,k} &= \mathbf 1_{\ell+1}^T\otimes C_{h,k},\qquad h = \bar h_k = \mathrm{mod}(k-1,p)+1,
    \qquad \mathbf H_k = \bar\Lambda_{h}\mathcal C_{h,k}

One step (Table I order; :math:`\gamma_k = \mathbb 1[y_k > \tau]` is known to the filter):

.. math::

    \hat\xi^-_k &= \mathcal A_{k-1}\hat\xi_{k-1}, \qquad
    P^-_k = \mathcal A_{k-1}P_{k-1}\mathcal A_{k-1}^T + \mathcal BQ_{k-1}\mathcal B^T   &(17)\text{–}(18)\\
    \bar\vartheta_k &= (\tau - \mathbf H_k\hat\xi^-_k)/\sqrt{\mathcal R_k}, \quad
    \lambda_k = \frac{\phi(\bar\vartheta_k)}{1-\Phi(\bar\vartheta_k)}, \quad
    \varphi_k = \lambda_k(\lambda_k - \bar\vartheta_k)   &(13)\text{–}(16)\\
    \hat y^-_k &= \gamma_k(\mathbf H_k\hat\xi^-_k + \sqrt{\mathcal R_k}\lambda_k) + (1-\gamma_k)\tau   &(21)\\
    P_{\tilde\xi\tilde y} &= \gamma_kP^-_k\mathbf H_k^T, \quad
    P_{\tilde y} = \gamma_k(\mathbf H_kP^-_k\mathbf H_k^T + F_k) + \mathcal R_k(1-\varphi_k)   &(23)\text{–}(24)\\
    K_k &= P_{\tilde\xi\tilde y}P_{\tilde y}^{-1}, \quad \hat\xi_k = \hat\xi^-_k + K_k(y_k - \hat y^-_k), \quad
    P_k = P^-_k - K_kP_{\tilde\xi\tilde y}^T   &(19), (20), (22)\\
    \hat x_k &= \Pi\hat\xi_k, \quad P_{\tilde x_k} = \Pi P_k\Pi^T   &(25)

A censored step (:math:`\gamma_k = 0`) gives :math:`K_k = 0` and an innovation
:math:`\tau - \tau = 0`; the code returns :math:`\hat\xi^-_k, P^-_k` unchanged, bit for bit.

The failure term :math:`F_k` (``failure_term``, spec §2.2 and A1):

========================  ==============================================================
``"variance"`` (default)  :math:`\check\Lambda_h\,\mathcal C_hP^-_k\mathcal C_h^T`
``"literal"``             :math:`(\bar\Lambda_h^2+\check\Lambda_h)\,\mathcal C_hP^-_k\mathcal C_h^T`
``"second_moment"``       :math:`\check\Lambda_h\,\mathcal C_h(P^-_k+\hat\xi^-_k\hat\xi^{-T}_k)\mathcal C_h^T`
``"lmmse_unconditional"`` :math:`\check\Lambda_h\,\mathcal C_h\mathfrak X_k\mathcal C_h^T`, :math:`\mathfrak X_k = E[\xi_k\xi_k^T]`
========================  ==============================================================

Time convention: :math:`x_0 \sim N(\bar x_0, P_0)` with the pre-history
:math:`x_{-1..-\ell}` independent with the same law (spec A5); no measurement at k = 0;
``y`` index k-1 holds :math:`y_k`; output index k-1 holds :math:`\hat x_k` (posterior) and
``pred_mean`` :math:`\hat x^-_k`.

Code names -> paper: ``window`` ℓ, ``threshold`` τ, ``uncensored`` γ_k,
``p_uncensored`` :math:`1-\Phi(\bar\vartheta_k)` (the diagnostic (8), A6), ``theta_bar``
:math:`\bar\vartheta_k`, ``inverse_mills`` λ, ``trunc_var_factor`` φ, ``scheduled`` :math:`\bar h_k`,
``aug_*`` the ξ-space quantities, ``failure_mean`` :math:`\bar\Lambda`, ``failure_variance``
:math:`\check\Lambda`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.special import ndtr

from .._validation import ShapeError, ValidationError, as_float_array, check_instance, check_psd
from ..censored import censored_moments
from ..channels.protocol import NO_FAILURE, ProtocolChannel
from ..models.linear import LinearSystem
from ._common import FilterResult, check_keywords, prepare_measurements, symmetrize
from .core import shift_predict

__all__ = ["ProtocolTobitKalmanFilter", "protocol_tobit_kalman_filter", "baseline_channel",
           "protocol_covariance_bounds", "CovarianceBounds", "augmented_transition", "noise_input",
           "stacked_measurement", "analytic_p_uncensored", "FAILURE_TERMS", "UPPER_FORMS", "LOWER_FORMS"]

FAILURE_TERMS = ("variance", "literal", "second_moment", "lmmse_unconditional")
PRIOR_MEANS = ("repeat", "zero")
UPPER_FORMS = ("expected_riccati", "suboptimal_gain", "paper_literal")
LOWER_FORMS = ("statement", "paper_proof")
PHI_UPPER = ("zero", "mean_trajectory")
_OPTIONS = {"failure_term": FAILURE_TERMS, "prehistory_mean": PRIOR_MEANS,
            "covariance_update": ("joseph", "standard")}
_TINY = 1e-12


# --- augmentation (9)-(10) -------------------------------------------------------------
def augmented_transition(A: np.ndarray, window: int) -> np.ndarray:
    r""":math:`\mathcal A` of (10): ``A`` in the top-left block, identities on the block sub-diagonal."""
    n = A.shape[-1]
    nx = n * (window + 1)
    out = np.zeros((nx, nx))
    out[:n, :n] = A
    out[n:, :-n] = np.eye(n * window)
    return out


def noise_input(n: int, window: int) -> np.ndarray:
    r""":math:`\mathcal B = [I\;0\cdots0]^T` of (10), also the transpose of the selector Π of (25)."""
    out = np.zeros((n * (window + 1), n))
    out[:n] = np.eye(n)
    return out


def stacked_measurement(C_row: np.ndarray, window: int) -> np.ndarray:
    r""":math:`\mathcal C_{m,k} = [C_{m,k}\;\cdots\;C_{m,k}]` (ℓ+1 copies), shape (n(ℓ+1),)."""
    return np.tile(np.asarray(C_row, dtype=float).reshape(-1), window + 1)


def _initial(system: LinearSystem, window: int, prehistory_mean: str, P0_aug: Any):
    n = system.n
    if prehistory_mean == "repeat":
        xi0 = np.tile(system.x0, window + 1)
    else:
        xi0 = np.concatenate([system.x0, np.zeros(n * window)])
    if P0_aug is None:
        M0 = np.kron(np.eye(window + 1), system.P0)
    else:
        M0 = as_float_array(P0_aug, "P0_aug", ndim=2)
        if M0.shape != (n * (window + 1),) * 2:
            raise ShapeError(f"P0_aug: expected ({n * (window + 1)}, {n * (window + 1)}), got {M0.shape}")
        check_psd(M0, "P0_aug")
    return xi0, M0


def _sensor_stats(system: LinearSystem, k: int, h: int):
    C = system.measurement(k)
    R = system.measurement_cov(k)
    r = float(R[h, h])
    if not r > 0:
        raise ValidationError(f"R({k}): sensor {h + 1} needs a positive noise variance, got {r}")
    return C[h], r


def _failure_term(mode: str, Cc: np.ndarray, P_pred: np.ndarray, xi_pred: np.ndarray, lam_mean: float,
                  lam_var: float, X: np.ndarray | None) -> np.ndarray:
    """F_k of spec §2.2, (N,)."""
    if mode == "lmmse_unconditional":
        return np.full(P_pred.shape[0], lam_var * float(Cc @ X @ Cc))
    CPC = np.einsum("i,nij,j->n", Cc, P_pred, Cc)
    if mode == "variance":
        return lam_var * CPC
    if mode == "literal":
        return (lam_mean**2 + lam_var) * CPC
    return lam_var * (CPC + (xi_pred @ Cc) ** 2)            # second_moment


def _check_parts(system: Any, channel: Any) -> None:
    check_instance(system, LinearSystem, "system")
    check_instance(channel, ProtocolChannel, "channel")
    channel.check_system(system)


def protocol_update(xi_pred: np.ndarray, P_pred: np.ndarray, y: np.ndarray, gamma: np.ndarray, Cc: np.ndarray,
                    r: float, tau: float, lam_mean: float, lam_var: float, *, failure_term: str = "variance",
                    second_moment: np.ndarray | None = None, covariance_update: str = "joseph"):
    r"""One measurement update of Theorem 1, (19)–(24), batched over runs.

    Parameters
    ----------
    xi_pred : (N, n_ξ) ndarray
        :math:`\hat\xi^-_k`.
    P_pred : (N, n_ξ, n_ξ) ndarray
        :math:`P^-_k`.
    y : (N,) ndarray
        Received :math:`y_k`.
    gamma : (N,) bool ndarray
        :math:`\gamma_k` (True = uncensored).
    Cc : (n_ξ,) ndarray
        :math:`\mathcal C_{h,k}`.
    r : float
        :math:`\mathcal R_k = R_{h,k}`.
    tau : float
        Threshold.
    lam_mean, lam_var : float
        :math:`\bar\Lambda_h`, :math:`\check\Lambda_h`.
    failure_term : str
        See the module docstring.
    second_moment : (n_ξ, n_ξ) ndarray, optional
        :math:`\mathfrak X_k` for ``"lmmse_unconditional"``.
    covariance_update : {"joseph", "standard"}
        Joseph form of App. D (44) or (20).

    Returns
    -------
    xi, P, info (dict of (N,) arrays: theta_bar, inverse_mills, trunc_var_factor, expected_y,
    innovation, innovation_var)
    """
    H = lam_mean * Cc
    zeta = xi_pred @ H
    sd = np.sqrt(r)
    st = censored_moments(zeta, sd, tau, np.inf)
    lam = st.inverse_mills
    noise = np.maximum(st.truncated_var, _TINY * r)             # R (1 - phi), floored (spec §2.3)
    F = _failure_term(failure_term, Cc, P_pred, xi_pred, lam_mean, lam_var, second_moment)
    PH = P_pred @ H                                             # (N, n_xi)
    S = PH @ H + F + noise                                      # P_y for gamma = 1 (24)
    K = PH / S[:, None]                                         # (22) with (23)
    yhat = zeta + sd * lam                                      # (21), gamma = 1
    e = y - yhat
    xi_up = xi_pred + K * e[:, None]                            # (19)
    if covariance_update == "joseph":
        # (I - K H^T) P (I - H K^T) + (F + noise) K K^T, applying the rank-one factors in turn:
        # M = P - K (H^T P) with H^T P = PH^T (P symmetric), then M (I - H K^T) = M - (M H) K^T;
        # outer products and one GEMV over the stacked rows instead of two batched matmuls
        M = P_pred - K[:, :, None] * PH[:, None, :]
        MH = (M.reshape(-1, H.size) @ H).reshape(K.shape)
        P_up = M - (MH - (F + noise)[:, None] * K)[:, :, None] * K[:, None, :]
    else:
        P_up = P_pred - K[:, :, None] * PH[:, None, :]          # (20)
    g = np.asarray(gamma, dtype=bool)
    xi = np.where(g[:, None], xi_up, xi_pred)                    # censored step: unchanged, bit-exact
    P = np.where(g[:, None, None], symmetrize(P_up), P_pred)
    with np.errstate(divide="ignore", invalid="ignore"):
        theta = (tau - zeta) / sd
    info = {"theta_bar": theta, "inverse_mills": lam, "trunc_var_factor": 1.0 - noise / r,
            "expected_y": np.where(g, yhat, tau), "innovation": np.where(g, e, 0.0),
            "innovation_var": np.where(g, S, noise), "p_uncensored": st.p_uncensored}
    return xi, P, info


def protocol_tobit_kalman_filter(system: LinearSystem, channel: ProtocolChannel, y: Any, *,
                                 uncensored: Any = None, failure_term: str = "variance",
                                 prehistory_mean: str = "repeat", covariance_update: str = "joseph",
                                 P0_aug: Any = None, keep_augmented: bool = False,
                                 check_limits: bool = True) -> FilterResult:
    r"""Run the PBTKF-IMSF (Theorem 1, Table I) over a batch of received records.

    Parameters
    ----------
    system : LinearSystem
        Plant (1) with ``C`` of p rows (row m is sensor m's :math:`C_{m,k}`) and diagonal
        ``R`` (:math:`R_{m,k}` on the diagonal). ``x0``, ``P0`` are :math:`\bar x_0`, :math:`P_0`.
    channel : ProtocolChannel
        Window ℓ, failure laws (only their means and variances are used), schedule, τ.
    y : (..., T, 1) or (T,) array_like
        Received scalar measurements :math:`y_1..y_T` (censored readings equal τ).
    uncensored : (..., T) bool array_like, optional
        :math:`\gamma_k` from the detection device; default ``y > threshold``.
    failure_term : {"variance", "literal", "second_moment", "lmmse_unconditional"}, default "variance"
        The failure term of (24) (spec §2.2, A1).
    prehistory_mean : {"repeat", "zero"}, default "repeat"
        Prior mean of :math:`x_{-1..-\ell}`: :math:`\bar x_0` or 0.
    covariance_update : {"joseph", "standard"}, default "joseph"
        Joseph form (App. D (44)) or (20); equal for the optimal gain.
    P0_aug : (n_ξ, n_ξ) array_like, optional
        :math:`P_{\tilde\xi_0} = M_0`; default :math:`I_{\ell+1}\otimes P_0` (A5).
    keep_augmented : bool, default False
        Also return the ξ-space covariances ``aug_cov``, ``aug_pred_cov`` (memory: N T n_ξ²).
    check_limits : bool, default True
        Raise if a reading lies below τ.

    Returns
    -------
    FilterResult
        ``mean``/``cov`` :math:`\hat x_k, P_{\tilde x_k}` (..., T, n[, n]); ``pred_mean``/``pred_cov``
        the priors. ``extras``: ``aug_mean``, ``aug_pred_mean`` (..., T, n_ξ); ``uncensored``,
        ``p_uncensored``, ``theta_bar``, ``inverse_mills``, ``trunc_var_factor``, ``expected_y``,
        ``innovation``, ``innovation_var`` (..., T); ``scheduled`` (T,).

    Raises
    ------
    ValidationError
        Unknown option, a reading below τ, non-positive sensor variance, bad ``P0_aug``.
    ShapeError
        ``y`` not (..., T, 1); ``C`` not p rows.

    Notes
    -----
    Deviations from the source (each an option; defaults follow spec §2.2–2.3):

    * ``failure_term="variance"`` (default) reads the coefficient of the second term of
      (24) as the failure *variance* :math:`\check\Lambda` (the value the example prints,
      0.065); the paper's definition :math:`\tilde\Lambda = \bar\Lambda^2 + \check\Lambda`
      is ``"literal"``, which does not reduce to the Kalman filter without failures (it keeps
      :math:`\mathcal CP\mathcal C^T`). ``"second_moment"`` uses the state second moment that
      the paper's own (35) calls for; ``"lmmse_unconditional"`` the unconditional one
      (exact LMMSE when τ = -inf).
    * (17) is read with :math:`\mathcal A_{k-1}` (A11); (18) with the posterior :math:`P_{k-1}`.
    * :math:`\vartheta` is divided by :math:`\sqrt{\mathcal R_k}`, not :math:`\mathcal R_k` (A3).
    * The censored step is implemented as "unchanged" (K = 0), avoiding 0/0 (spec §2.3).

    Examples
    --------
    Without failures, integral or censoring, and one sensor, this is the Kalman filter:

    >>> import numpy as np, tobitkf as tk
    >>> from tobitkf.channels.protocol import ProtocolChannel
    >>> sys = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.1]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    >>> y = np.array([[0.5], [1.0], [-0.2]])
    >>> a = protocol_tobit_kalman_filter(sys, ProtocolChannel(1), y).mean
    >>> bool(np.allclose(a, tk.KalmanFilter(sys).filter(y).mean, rtol=0, atol=1e-12))
    True
    """
    check_keywords({"failure_term": failure_term, "prehistory_mean": prehistory_mean,
                    "covariance_update": covariance_update}, _OPTIONS)
    check_instance(system, LinearSystem, "system")
    check_instance(channel, ProtocolChannel, "channel")
    _check_parts(system, channel)
    arr = as_float_array(y, "y", allow_nan=False)
    if arr.ndim == 1:                                   # one record (T,)
        arr = arr[:, None]
    elif arr.ndim >= 2 and arr.shape[-1] != 1:
        raise ShapeError(f"y: expected (..., T, 1) received scalars (or one record (T,)), got shape {arr.shape}")
    y2, batch = prepare_measurements(arr, 1)
    N, T, _ = y2.shape
    tau = channel.threshold
    if check_limits and (y2 < tau).any():
        raise ValidationError(f"y: readings below the threshold tau={tau} cannot come from (4), "
                              f"found {y2[y2 < tau][:3]}")
    if uncensored is None:
        gam = y2[..., 0] > tau
    else:
        gam = np.asarray(uncensored, dtype=bool)
        if gam.shape != batch + (T,):
            raise ShapeError(f"uncensored: expected shape {batch + (T,)}, got {gam.shape}")
        gam = gam.reshape(N, T)
    system.check_horizon(T)
    n, ell = system.n, channel.window
    nxi = n * (ell + 1)
    xi0, M0 = _initial(system, ell, prehistory_mean, P0_aug)
    xi = np.broadcast_to(xi0, (N, nxi)).copy()
    P = np.broadcast_to(symmetrize(M0), (N, nxi, nxi)).copy()   # exactly symmetric (shift_predict needs it)
    X = M0 + np.outer(xi0, xi0) if failure_term == "lmmse_unconditional" else None
    Bn = noise_input(n, ell)
    lam_mean, lam_var = channel.failure_mean, channel.failure_variance
    sched = channel.schedule.scheduled(T)
    # outputs stored time-major (T, N, ...): each step writes one contiguous block; returned as
    # (N, T, ...) views
    out = {key: np.empty((T, N, nxi)) for key in ("aug_mean", "aug_pred_mean")}
    if keep_augmented:
        out.update({key: np.empty((T, N, nxi, nxi)) for key in ("aug_cov", "aug_pred_cov")})
    cov = np.empty((T, N, n, n))
    pcov = np.empty((T, N, n, n))
    info_keys = ("theta_bar", "inverse_mills", "trunc_var_factor", "expected_y", "innovation", "innovation_var",
                 "p_uncensored")
    info_out = {key: np.empty((T, N)) for key in info_keys}
    fixed = not (system.A.varying or system.Q.varying or (system.B is not None and system.B.varying))
    if fixed:
        Aa, BQB = augmented_transition(system.transition(0), ell), Bn @ system.process_cov(0) @ Bn.T
    for k in range(1, T + 1):
        if not fixed:
            Aa = augmented_transition(system.transition(k - 1), ell)
            BQB = Bn @ system.process_cov(k - 1) @ Bn.T
        # (17)-(18): Aa is the block shift of (10) and BQB lives in its top block, so the
        # prediction is block copies and two GEMMs over the stacked runs (== sym(Aa P Aa^T + BQB))
        xi, P = shift_predict(xi, P, Aa[:n, :n], BQB[:n, :n])
        if X is not None:
            X = Aa @ X @ Aa.T + BQB
        out["aug_pred_mean"][k - 1] = xi
        pcov[k - 1] = P[:, :n, :n]
        if keep_augmented:
            out["aug_pred_cov"][k - 1] = P
        h = int(sched[k - 1]) - 1
        C_row, r = _sensor_stats(system, k, h)
        Cc = stacked_measurement(C_row, ell)
        xi, P, info = protocol_update(xi, P, y2[:, k - 1, 0], gam[:, k - 1], Cc, r, tau, float(lam_mean[h]),
                                      float(lam_var[h]), failure_term=failure_term, second_moment=X,
                                      covariance_update=covariance_update)
        out["aug_mean"][k - 1] = xi
        cov[k - 1] = P[:, :n, :n]                                        # (25)
        if keep_augmented:
            out["aug_cov"][k - 1] = P
        for key in info_keys:
            info_out[key][k - 1] = info[key]
    def runs_first(arr: np.ndarray) -> np.ndarray:   # (T, N, ...) -> batch + (T, ...) view
        return np.moveaxis(arr, 0, 1).reshape(batch + (T,) + arr.shape[2:])

    extras: dict[str, Any] = {key: runs_first(val) for key, val in out.items()}
    extras.update({key: runs_first(val) for key, val in info_out.items()})
    extras["uncensored"] = gam.reshape(batch + (T,))
    extras["scheduled"] = sched
    return FilterResult(mean=extras["aug_mean"][..., :n], cov=runs_first(cov),
                        pred_mean=extras["aug_pred_mean"][..., :n], pred_cov=runs_first(pcov), extras=extras)


def baseline_channel(channel: ProtocolChannel) -> ProtocolChannel:
    r"""The PBTKF baseline's (mis-specified) channel model, spec §2.5 (A16).

    Same schedule and τ, but :math:`\ell_{model} = 0` and no failures
    (:math:`\bar\Lambda \equiv 1`, :math:`\check\Lambda \equiv 0`, so :math:`F_k = 0`).
    """
    return channel.replace(window=0, failures=NO_FAILURE)


class ProtocolTobitKalmanFilter:
    r"""PBTKF-IMSF: Tobit Kalman filter under Round-Robin scheduling, integral measurements
    and probabilistic sensor failures (Geng et al., Theorems 1–2, Table I).

    Parameters
    ----------
    system : LinearSystem
        Plant; ``C`` has one row per sensor, ``R`` is diagonal.
    channel : ProtocolChannel
        The channel the filter assumes.
    failure_term : {"variance", "literal", "second_moment", "lmmse_unconditional"}, default "variance"
    prehistory_mean : {"repeat", "zero"}, default "repeat"
    covariance_update : {"joseph", "standard"}, default "joseph"
    P0_aug : array_like, optional
        :math:`M_0`.

    Raises
    ------
    ValidationError
        Unknown option or wrong argument types.

    Notes
    -----
    See :func:`protocol_tobit_kalman_filter` for the equations and the deviations from the
    source. :meth:`baseline` builds the paper's comparison filter PBTKF (spec §2.5).
    """

    def __init__(self, system: LinearSystem, channel: ProtocolChannel, *, failure_term: str = "variance",
                 prehistory_mean: str = "repeat", covariance_update: str = "joseph", P0_aug: Any = None):
        check_keywords({"failure_term": failure_term, "prehistory_mean": prehistory_mean,
                        "covariance_update": covariance_update}, _OPTIONS)
        check_instance(system, LinearSystem, "system")
        check_instance(channel, ProtocolChannel, "channel")
        channel.check_system(system)
        self.system, self.channel = system, channel
        self.options = {"failure_term": failure_term, "prehistory_mean": prehistory_mean,
                        "covariance_update": covariance_update, "P0_aug": P0_aug}

    @classmethod
    def baseline(cls, system: LinearSystem, channel: ProtocolChannel, **options: Any) -> ProtocolTobitKalmanFilter:
        """The PBTKF of the paper's comparisons: this filter with ℓ = 0 and no failures (spec §2.5)."""
        return cls(system, baseline_channel(channel), **options)

    def filter(self, y: Any, *, uncensored: Any = None, keep_augmented: bool = False) -> FilterResult:
        """Filter ``y`` (..., T, 1); see :func:`protocol_tobit_kalman_filter`."""
        return protocol_tobit_kalman_filter(self.system, self.channel, y, uncensored=uncensored,
                                            keep_augmented=keep_augmented, **self.options)

    def bounds(self, steps: int, **options: Any) -> CovarianceBounds:
        """Upper and lower bounds on :math:`E\\{P_{\\tilde x^-_k}\\}`; see :func:`protocol_covariance_bounds`."""
        opts = {"failure_term": self.options["failure_term"], "prehistory_mean": self.options["prehistory_mean"],
                "P0_aug": self.options["P0_aug"]}
        opts.update(options)
        return protocol_covariance_bounds(self.system, self.channel, steps, **opts)

    def __repr__(self) -> str:
        opts = ", ".join(f"{k}={v!r}" for k, v in self.options.items() if k != "P0_aug")
        return f"ProtocolTobitKalmanFilter({self.system!r}, {self.channel!r}, {opts})"


# --- performance bounds (Sec. IV, spec §2.7-2.8) -------------------------------------------
@dataclass(frozen=True)
class CovarianceBounds:
    r"""Bounds :math:`N^l_k \preceq N_k = E\{P_{\tilde x^-_k}\} \preceq N^u_k` (Theorem 5), k = 1..T.

    Attributes
    ----------
    upper, lower : (T, n, n) ndarray
        :math:`N^u_k`, :math:`N^l_k` (index k-1 holds step k).
    upper_aug, lower_aug : (T, n_ξ, n_ξ) ndarray
        :math:`M^u_k`, :math:`M^l_k`.
    p_uncensored : (T,) ndarray
        The deterministic :math:`\bar\gamma_k` used.
    """

    upper: np.ndarray
    lower: np.ndarray
    upper_aug: np.ndarray
    lower_aug: np.ndarray
    p_uncensored: np.ndarray


def _gl_nodes(lo: float, hi: float, n: int = 64):
    """Gauss-Legendre nodes on [lo, hi] and weights of the uniform density there (summing to 1)."""
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (hi - lo) * x + 0.5 * (hi + lo), 0.5 * w


def analytic_p_uncensored(system: LinearSystem, channel: ProtocolChannel, steps: int, *,
                          prehistory_mean: str = "repeat", P0_aug: Any = None) -> np.ndarray:
    r"""Unconditional :math:`\bar\gamma_k = P(\bar y_k > \tau)` under the true model, k = 1..T (spec §2.8).

    .. math::

        \bar\gamma_k = \sum_j \pi_j\Big[1 - \Phi\Big(\frac{\tau - \lambda_j\mathcal C_h\mathfrak m_k}
        {\sqrt{\lambda_j^2\mathcal C_h\Sigma_k\mathcal C_h^T + \mathcal R_k}}\Big)\Big]

    with the unconditional mean :math:`\mathfrak m_k` and covariance :math:`\Sigma_k` of
    :math:`\xi_k`. Discrete laws (``values``/``probs``) are summed, constant gains (variance 0)
    are a single point, uniform laws (``low``/``high``) are integrated by 64-point Gauss–Legendre
    quadrature.

    Raises
    ------
    ValidationError
        For a law that is neither discrete nor uniform (pass γ̄ explicitly then).
    """
    n, ell = system.n, channel.window
    xi0, M0 = _initial(system, ell, prehistory_mean, P0_aug)
    Bn = noise_input(n, ell)
    nodes = []
    for i, law in enumerate(channel.laws):
        if hasattr(law, "values") and hasattr(law, "probs"):
            nodes.append((np.asarray(law.values, float).ravel(), np.asarray(law.probs, float).ravel()))
        elif hasattr(law, "low") and hasattr(law, "high"):
            lo, hi = float(law.low), float(law.high)
            nodes.append(_gl_nodes(lo, hi) if hi > lo else (np.array([lo]), np.array([1.0])))
        elif float(law.variance) == 0.0:
            nodes.append((np.array([float(law.mean)]), np.array([1.0])))
        else:
            raise ValidationError(f"failures[{i}]: the analytic p_uncensored needs a discrete (values/probs) or "
                                  f"uniform (low/high) law, got {type(law).__name__}; pass p_uncensored explicitly")
    sched = channel.schedule.scheduled(steps)
    m, S = xi0, M0
    out = np.empty(steps)
    for k in range(1, steps + 1):
        Aa = augmented_transition(system.transition(k - 1), ell)
        m = Aa @ m
        S = Aa @ S @ Aa.T + Bn @ system.process_cov(k - 1) @ Bn.T
        h = int(sched[k - 1]) - 1
        C_row, r = _sensor_stats(system, k, h)
        Cc = stacked_measurement(C_row, ell)
        vals, wts = nodes[h]
        mu = vals * (Cc @ m)
        sd = np.sqrt(vals**2 * (Cc @ S @ Cc) + r)
        out[k - 1] = float(wts @ ndtr((mu - channel.threshold) / sd))
    return out


def protocol_covariance_bounds(system: LinearSystem, channel: ProtocolChannel, steps: int, *,
                               p_uncensored: Any = "analytic", failure_term: str = "variance",
                               upper_form: str = "expected_riccati", lower_form: str = "statement",
                               phi_upper: str = "zero", prehistory_mean: str = "repeat",
                               P0_aug: Any = None) -> CovarianceBounds:
    r"""Upper and lower bounds on the expected prior covariance (Theorems 3–5, spec §2.7–2.8).

    Index convention (A5): :math:`M^u_1 = M^l_1 = P^-_1 = \mathcal A_0M_0\mathcal A_0^T + \mathcal BQ_0\mathcal B^T`;
    then for k = 1..T-1, with step-k quantities (:math:`h = \bar h_k`, :math:`\mathbf H_k`, :math:`\mathcal R_k`,
    :math:`\bar\gamma_k`):

    .. math::

        M^u_{k+1} &= \mathcal AM^u_k\mathcal A^T + \mathcal BQ\mathcal B^T
          - \bar\gamma_k\,\mathcal AM^u_k\mathbf H^T\big[\mathbf HM^u_k\mathbf H^T + F^u_k
          + \mathcal R_k(1-\bar\varphi^u_k)\big]^{-1}\mathbf HM^u_k\mathcal A^T \\
        M^l_{k+1} &= (1-\bar\gamma_k)\mathcal AM^l_k\mathcal A^T + \mathcal BQ\mathcal B^T  &(30)

    and :math:`N^{u,l}_k = \Pi M^{u,l}_k\Pi^T` (32).

    Parameters
    ----------
    system, channel
        As for the filter.
    steps : int
        T.
    p_uncensored : "analytic" or float or (T,) array_like, default "analytic"
        :math:`\bar\gamma_k`: the unconditional probability (:func:`analytic_p_uncensored`), or
        given values (e.g. the Monte Carlo frequency, or a constant).
    failure_term : str, default "variance"
        :math:`F^u_k`: ``"variance"`` :math:`\check\Lambda\mathcal CM^u\mathcal C^T`, ``"literal"``
        :math:`(\bar\Lambda^2+\check\Lambda)\mathcal CM^u\mathcal C^T`, ``"second_moment"`` and
        ``"lmmse_unconditional"`` :math:`\check\Lambda\mathcal C\mathfrak X_k\mathcal C^T`.
    upper_form : {"expected_riccati", "suboptimal_gain", "paper_literal"}, default "expected_riccati"
    lower_form : {"statement", "paper_proof"}, default "statement"
    phi_upper : {"zero", "mean_trajectory"}, default "zero"
        :math:`\bar\varphi^u_k`: 0 (a guaranteed bound) or φ along the mean trajectory (tighter,
        not guaranteed).
    prehistory_mean, P0_aug
        The filter's initialisation.

    Returns
    -------
    CovarianceBounds

    Raises
    ------
    ValidationError
        Unknown option, :math:`\bar\gamma` outside [0, 1] or of the wrong length.

    Notes
    -----
    Deviations from the source (spec A2, A4):

    * (28) uses the random :math:`P_{\xi_k}` in its failure term and never defines
      :math:`\bar\gamma^u, \bar\varphi^u`; the default uses :math:`M^u_k`,
      :math:`\bar\gamma^u = \bar\gamma`, :math:`\bar\varphi^u = 0` and the expected-Riccati
      form (a valid bound by concavity and Jensen under the paper's independence idealization).
      ``"suboptimal_gain"`` is what the proof (38)–(41) yields with :math:`E\gamma^2 = \bar\gamma`
      (valid, looser); ``"paper_literal"`` is (28) with :math:`\bar\gamma^2` inside the braces
      (a diagnostic: it is violated in the transient).
    * (30) as stated is the default; ``lower_form="paper_proof"`` is the proof's (45)–(46)
      version :math:`(1-\bar\gamma)\mathcal AM\mathcal A^T + \bar\gamma\mathcal BQ\mathcal B^T` with
      :math:`M^l_0 = 0`, i.e. :math:`M^l_1 = \mathcal BQ_0\mathcal B^T` (looser, also valid).
    """
    check_keywords({"failure_term": failure_term, "upper_form": upper_form, "lower_form": lower_form,
                    "phi_upper": phi_upper, "prehistory_mean": prehistory_mean},
                   {"failure_term": FAILURE_TERMS, "upper_form": UPPER_FORMS, "lower_form": LOWER_FORMS,
                    "phi_upper": PHI_UPPER, "prehistory_mean": PRIOR_MEANS})
    _check_parts(system, channel)
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1:
        raise ValidationError(f"steps: expected a positive integer, got {steps!r}")
    if isinstance(p_uncensored, str):
        if p_uncensored != "analytic":
            raise ValidationError(f"p_uncensored: expected 'analytic' or numbers in [0, 1], got {p_uncensored!r}")
        gbar = analytic_p_uncensored(system, channel, steps, prehistory_mean=prehistory_mean, P0_aug=P0_aug)
    else:
        gbar = as_float_array(p_uncensored, "p_uncensored", ndim=(0, 1))
        if gbar.ndim == 1 and gbar.shape != (steps,):
            raise ShapeError(f"p_uncensored: expected a scalar or shape ({steps},), got {gbar.shape}")
        if ((gbar < 0) | (gbar > 1)).any():
            raise ValidationError(f"p_uncensored: expected probabilities in [0, 1], got {gbar[(gbar < 0) | (gbar > 1)][:3]}")
        gbar = np.broadcast_to(gbar, (steps,)).astype(float)
    system.check_horizon(steps)
    n, ell = system.n, channel.window
    nxi = n * (ell + 1)
    xi0, M0 = _initial(system, ell, prehistory_mean, P0_aug)
    Bn = noise_input(n, ell)
    lam_mean, lam_var = channel.failure_mean, channel.failure_variance
    sched = channel.schedule.scheduled(steps)
    tau = channel.threshold
    Mu = np.empty((steps, nxi, nxi))
    Ml = np.empty((steps, nxi, nxi))
    A0 = augmented_transition(system.transition(0), ell)
    BQB0 = Bn @ system.process_cov(0) @ Bn.T
    Mu[0] = symmetrize(A0 @ M0 @ A0.T + BQB0)
    Ml[0] = Mu[0] if lower_form == "statement" else BQB0
    mean, X = A0 @ xi0, Mu[0] + np.outer(A0 @ xi0, A0 @ xi0)     # unconditional moments at k = 1
    for k in range(1, steps):
        h = int(sched[k - 1]) - 1
        C_row, r = _sensor_stats(system, k, h)
        Cc = stacked_measurement(C_row, ell)
        H = lam_mean[h] * Cc
        M = Mu[k - 1]
        if failure_term == "variance":
            F = lam_var[h] * (Cc @ M @ Cc)
        elif failure_term == "literal":
            F = (lam_mean[h] ** 2 + lam_var[h]) * (Cc @ M @ Cc)
        else:
            F = lam_var[h] * (Cc @ X @ Cc)
        if phi_upper == "zero":
            phi = 0.0
        else:
            st = censored_moments(H @ mean, np.sqrt(r), tau, np.inf)
            phi = 1.0 - float(st.truncated_var) / r
        g = gbar[k - 1]
        MH = M @ H
        HMH = float(H @ MH)
        if upper_form == "expected_riccati":
            corr = g / (HMH + F + r * (1 - phi))
        elif upper_form == "suboptimal_gain":
            corr = g**2 / (g * (HMH + F) + r * (1 - phi))
        else:
            corr = g**2 / (g**2 * (HMH + F) + r * (1 - phi))
        Aa = augmented_transition(system.transition(k), ell)
        BQB = Bn @ system.process_cov(k) @ Bn.T
        Mpost = M - corr * np.outer(MH, MH)
        Mu[k] = symmetrize(Aa @ Mpost @ Aa.T + BQB)
        low_noise = BQB if lower_form == "statement" else g * BQB
        Ml[k] = symmetrize((1 - g) * (Aa @ Ml[k - 1] @ Aa.T) + low_noise)
        mean = Aa @ mean
        X = Aa @ X @ Aa.T + BQB
    return CovarianceBounds(upper=Mu[:, :n, :n].copy(), lower=Ml[:, :n, :n].copy(), upper_aug=Mu, lower_aug=Ml,
                            p_uncensored=np.asarray(gbar, dtype=float))
