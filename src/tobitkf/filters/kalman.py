r"""Batched Kalman filter and the two naive baselines for censored data.

Source: Miller (2015), §2.1.2, (2.3)–(2.6) (spec 001a §2.2); baselines from §1.2
and §3.3.6 (spec 001a §3.5, "Comparators"):

.. math::

    \bar x_k &= A_{k-1}\hat x_{k-1} + B^u u_k, & \bar P_k &= A_{k-1}P_{k-1}A_{k-1}^T + B Q B^T \\
    K_k &= \bar P_k C_k^T (C_k\bar P_k C_k^T + R_k)^{-1}, &
    \hat x_k &= \bar x_k + K_k(y_k - C_k\bar x_k - D u_k), \quad P_k = (I - K_kC_k)\bar P_k

Time convention: x_0 ~ N(x0, P0) is the prior; y_1 is stored at index 0;
output index k-1 holds x̂_{k|k}, P_{k|k}.

* :class:`KalmanFilter` fed censored values treats them as ordinary
  measurements: the dissertation's "standard KF" baseline (biased under censoring).
* :class:`DroppingKalmanFilter` skips censored readings (x̂ = x̄, P = P̄ for a
  censored channel): the "intermittent-measurements KF" ([16] in Miller; the
  spec's "IKF"). Censoring is detected as a reading within a relative tolerance of
  its limit [non-source]; with vector measurements only the censored rows are
  dropped [non-source].

NaN measurements are treated as missing samples: the channel is skipped in that
step, exactly as a dropped packet.

Covariance forms [non-source]: ``covariance_update="standard"`` is (2.6),
``"joseph"`` the Joseph form, and ``"square_root"`` propagates a factor S with
P = S Sᵀ through QR factorizations (the array form of the Kalman filter; Kaminski, Bryson
& Schmidt 1971; Bierman 1977; Grewal & Andrews, *Kalman Filtering*, ch. on
implementation methods). It is not in the sources; it keeps P positive semidefinite by
construction where the other two lose it (a huge prior with a near-singular R, see
``docs/reliability.md``), costs about 4-6 times the standard form, and runs on the numpy
path only.

Symbols: ``mean`` = x̂, ``cov`` = P, ``pred_mean`` = x̄, ``pred_cov`` = P̄.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._validation import ValidationError, check_instance
from ..channels.censoring import Censoring
from ..models.linear import LinearSystem
from ._backend import BACKENDS, check_square_root, kernels, system_gap, use_kernel
from ._common import (FilterResult, check_keywords, check_prior, gain_update, predict, prepare_inputs,
                      prepare_measurements, process_roots, psd_sqrt, sqrt_predict, sqrt_update, symmetrize)

__all__ = ["kalman_filter", "KalmanFilter", "DroppingKalmanFilter"]

COVARIANCE_UPDATES = ("standard", "joseph", "square_root")
_OPTIONS = {"covariance_update": COVARIANCE_UPDATES, "backend": BACKENDS}


def kalman_filter(system: LinearSystem, y: Any, *, u: Any = None, skip: np.ndarray | None = None,
                  covariance_update: str = "standard", x0: Any = None, P0: Any = None,
                  backend: str = "auto") -> FilterResult:
    r"""Run the Kalman filter (Miller (2.3)–(2.6)) over a batch of records.

    Parameters
    ----------
    system : LinearSystem
        The model.
    y : (..., T, m) array_like
        Measurements y_1..y_T; NaN marks a missing sample (skipped).
    u : (T, p) or (..., T, p) array_like, optional
        Control inputs u_1..u_T.
    skip : (..., T, m) bool array, optional
        Channels to leave out of the update (e.g. censored readings).
    covariance_update : {"standard", "joseph", "square_root"}
        ``"standard"`` is (2.6) :math:`(I-KC)\bar P`; ``"joseph"`` uses
        :math:`(I-KC)\bar P(I-KC)^T + KRK^T`, equal in exact arithmetic and
        better conditioned. ``"square_root"`` (not in the source; a standard numerical
        device, see Notes) carries a factor :math:`S` with :math:`P = SS^T` and stays
        positive semidefinite by construction; numpy path only.
    x0, P0 : array_like, optional
        Override the system's prior (``(..., n)``, ``(..., n, n)``).
    backend : {"auto", "numpy", "numba"}, default "auto"
        Implementation of the time loop (same results to rounding, tested to 1e-12).
        ``"numba"`` runs the compiled kernel of :mod:`tobitkf.filters._kernels`, which
        covers time-invariant A, B, C, Q, R without control input (missing samples,
        ``skip``, per-run priors and the standard and Joseph updates included, not the
        square-root form); ``"numpy"`` the vectorised reference path, which covers
        everything; ``"auto"`` the kernel when numba is installed and the case is covered,
        else numpy (always numpy for ``covariance_update="square_root"``).

    Returns
    -------
    FilterResult
        ``mean`` (..., T, n), ``cov`` (..., T, n, n), ``pred_mean``, ``pred_cov``.
        When no sample is skipped the covariances are the same for every run and
        are returned as read-only broadcast views.

    Raises
    ------
    ShapeError, ValidationError
        On malformed ``y``, ``u``, ``skip`` or an unknown option; ``backend="numba"`` for a
        case the kernel does not cover (including ``covariance_update="square_root"``).
    ImportError
        ``backend="numba"`` without numba installed.

    Notes
    -----
    Square-root form (``covariance_update="square_root"``). With :math:`P = SS^T`,
    :math:`Q_d = BQB^T = GG^T` (a Cholesky factor, or an eigen-decomposition root when Q is
    only semidefinite) and :math:`R = R^{1/2}R^{1/2\,T}`, each step takes two QR
    factorizations, batched over the runs:

    .. math::

        \begin{bmatrix} S^TA^T \\ G^T \end{bmatrix} = \mathcal Q_1 U, \quad \bar S = U^T;
        \qquad
        \begin{bmatrix} R^{1/2\,T} & 0 \\ \bar S^TC^T & \bar S^T \end{bmatrix}
        = \mathcal Q_2 \begin{bmatrix} U_{11} & U_{12} \\ 0 & U_{22} \end{bmatrix}

    Comparing :math:`M^TM = U^TU`: :math:`\bar P = \bar S\bar S^T`,
    :math:`U_{11}^TU_{11} = C\bar PC^T + R`, :math:`U_{12}^TU_{11} = \bar PC^T` and
    :math:`U_{22}^TU_{22} = \bar P - K C \bar P`, so the gain is
    :math:`K = U_{12}^TU_{11}^{-T}` (a triangular solve) and :math:`S = U_{22}^T`. The
    outputs are the covariances :math:`P = SS^T`, not the factors. A missing or skipped
    channel gets a zero row of C and a unit noise decoupled from the others, which leaves it
    out exactly (zero gain column), as in the other forms. Cost: a QR of an
    :math:`(m+n)\times(m+n)` and of a :math:`(n+q)\times n` matrix per run and step; measured on
    the numpy path (n = 2, m = 1, 10^4 runs of 100 steps, 2-core machine): 0.70 s against
    0.12 s for the standard and 0.26 s for the Joseph form. The form is not in the source; it is the
    array (QR) form of the square-root filter of Kaminski, Bryson & Schmidt (1971), Bierman
    (1977) and Grewal & Andrews (*Kalman Filtering: Theory and Practice*).
    """
    check_keywords({"covariance_update": covariance_update, "backend": backend}, _OPTIONS)
    form_gap = check_square_root(backend, covariance_update, "the Kalman filter")
    y2, batch = prepare_measurements(y, system.m)
    N, T, m = y2.shape
    n = system.n
    system.check_horizon(T)
    u2 = prepare_inputs(system, u, N, T)
    missing = np.isnan(y2)
    if skip is not None:
        skip = np.asarray(skip, dtype=bool)
        if skip.shape[-2:] != (T, m):
            raise ValidationError(f"skip: expected (..., {T}, {m}), got {skip.shape}")
        missing = missing | np.broadcast_to(skip.reshape((-1, T, m)), (N, T, m))
    per_run = bool(missing.any()) or x0 is not None and np.ndim(x0) > 1 or P0 is not None and np.ndim(P0) > 2
    x, P = check_prior(system, x0, P0, N, batch)
    if not per_run:
        P = P[:1]
    means = np.empty((N, T, n))
    pmeans = np.empty((N, T, n))
    covs = np.empty((P.shape[0], T, n, n))
    pcovs = np.empty_like(covs)
    joseph = covariance_update == "joseph"
    if use_kernel(backend, form_gap or system_gap(system, u), "the Kalman filter"):
        c64 = np.ascontiguousarray
        kernels().kf_kernel(c64(y2), c64(missing), c64(system.transition(0), dtype=float),
                            c64(system.process_cov(0), dtype=float), c64(system.measurement(1), dtype=float),
                            c64(system.measurement_cov(1), dtype=float), x, P, joseph, means, covs, pmeans, pcovs)
    elif covariance_update == "square_root":
        _sqrt_loop(system, y2, u2, missing if per_run else None, x, P, means, covs, pmeans, pcovs)
    else:
        for k in range(1, T + 1):
            uk = None if u2 is None else u2[:, k - 1]
            bx, dy = system.input_effect(k, uk)
            x, P = predict(x, P, system.transition(k - 1), system.process_cov(k - 1), bx)
            pmeans[:, k - 1], pcovs[:, k - 1] = x, P
            C, R = system.measurement(k), system.measurement_cov(k)
            CP = C @ P
            Ree = CP @ C.T + R
            Rxe = np.swapaxes(CP, -1, -2)
            innov = y2[:, k - 1] - x @ C.T - dy
            valid = ~missing[:, k - 1] if per_run else None
            if joseph:
                x, P, _ = gain_update(x, P, np.nan_to_num(innov), Rxe, Ree, valid, H=C[None], noise=R[None])
            else:
                x, P, _ = gain_update(x, P, np.nan_to_num(innov), Rxe, Ree, valid)
            means[:, k - 1], covs[:, k - 1] = x, P
    if not per_run:
        covs = np.broadcast_to(covs, (N, T, n, n))
        pcovs = np.broadcast_to(pcovs, (N, T, n, n))
    return FilterResult(mean=means.reshape(batch + (T, n)), cov=covs.reshape(batch + (T, n, n)),
                        pred_mean=pmeans.reshape(batch + (T, n)), pred_cov=pcovs.reshape(batch + (T, n, n)))


def _sqrt_loop(system: LinearSystem, y2: np.ndarray, u2: np.ndarray | None, missing: np.ndarray | None,
               x: np.ndarray, P: np.ndarray, means: np.ndarray, covs: np.ndarray, pmeans: np.ndarray,
               pcovs: np.ndarray) -> None:
    """Time loop of the square-root form (:func:`~tobitkf.filters._common.sqrt_predict`,
    :func:`~tobitkf.filters._common.sqrt_update`), filling the output arrays in place.

    ``missing`` (N, T, m) or None when no sample is skipped (then P, S are shared, (1, n, n)).
    """
    T = y2.shape[1]
    S = psd_sqrt(P)
    G = process_roots(system)
    R_root = None if system.R.varying else psd_sqrt(system.measurement_cov(1))
    for k in range(1, T + 1):
        uk = None if u2 is None else u2[:, k - 1]
        bx, dy = system.input_effect(k, uk)
        x, S = sqrt_predict(x, S, system.transition(k - 1), G(k - 1), bx)
        pmeans[:, k - 1], pcovs[:, k - 1] = x, symmetrize(S @ np.swapaxes(S, -1, -2))
        C, R = system.measurement(k), system.measurement_cov(k)
        innov = y2[:, k - 1] - x @ C.T - dy
        valid = None if missing is None else ~missing[:, k - 1]
        root = psd_sqrt(R) if R_root is None else R_root
        x, P, S, _ = sqrt_update(x, S, np.nan_to_num(innov), C[None], R[None], valid, R_root=root[None])
        means[:, k - 1], covs[:, k - 1] = x, P


class KalmanFilter:
    """Kalman filter (Miller (2.3)–(2.6)); fed censored data it is the "standard KF" baseline.

    Parameters
    ----------
    system : LinearSystem
        The model.
    covariance_update : {"standard", "joseph", "square_root"}, default "standard"
        See :func:`kalman_filter`; ``"square_root"`` (a factor :math:`S`, :math:`P = SS^T`,
        from QR factorizations) stays positive semidefinite where the other two fail.
    backend : {"auto", "numpy", "numba"}, default "auto"
        Implementation of the time loop; see :func:`kalman_filter`. ``"numba"`` has no
        square-root form and is refused with ``covariance_update="square_root"``.

    Examples
    --------
    >>> import numpy as np, tobitkf as tk
    >>> sys = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    >>> out = tk.KalmanFilter(sys).filter(np.array([[2.0]]))
    >>> float(out.mean[0, 0]), float(out.cov[0, 0, 0])     # prior and measurement weighted equally
    (1.0, 0.5)
    """

    def __init__(self, system: LinearSystem, *, covariance_update: str = "standard", backend: str = "auto"):
        check_instance(system, LinearSystem, "system")
        check_keywords({"covariance_update": covariance_update, "backend": backend}, _OPTIONS)
        check_square_root(backend, covariance_update, "the Kalman filter")
        self.system = system
        self.covariance_update = covariance_update
        self.backend = backend

    def filter(self, y: Any, *, u: Any = None, x0: Any = None, P0: Any = None) -> FilterResult:
        """Filter measurements ``y`` (..., T, m); see :func:`kalman_filter`."""
        return kalman_filter(self.system, y, u=u, covariance_update=self.covariance_update, x0=x0, P0=P0,
                             backend=self.backend)


class DroppingKalmanFilter:
    """Kalman filter that skips censored readings: the spec's "IKF" baseline (Miller §1.2 item 2, §3.3.6).

    A channel whose reading equals its censoring limit (to relative tolerance
    ``rtol``) is left out of that step's update, so a censored step gives
    x̂ = x̄ and P = P̄ for that channel [non-source detection rule, spec 001a §3.5].

    Parameters
    ----------
    system : LinearSystem
    censoring : Censoring
        The limits used to detect censored readings.
    rtol : float, default 1e-12
        Relative tolerance of the detection.
    covariance_update : {"standard", "joseph", "square_root"}
        See :func:`kalman_filter`.
    """

    def __init__(self, system: LinearSystem, censoring: Censoring, *, rtol: float = 1e-12,
                 covariance_update: str = "standard"):
        check_instance(system, LinearSystem, "system")
        check_instance(censoring, Censoring, "censoring")
        censoring.check(system.m)
        check_keywords({"covariance_update": covariance_update}, _OPTIONS)
        if isinstance(rtol, bool) or not isinstance(rtol, (int, float, np.floating)) or not rtol >= 0:
            raise ValidationError(f"rtol: expected a non-negative tolerance, got {rtol!r}")
        self.system, self.censoring, self.rtol = system, censoring, float(rtol)
        self.covariance_update = covariance_update

    def filter(self, y: Any, *, u: Any = None, x0: Any = None, P0: Any = None) -> FilterResult:
        """Filter ``y`` (..., T, m), skipping censored readings; see :func:`kalman_filter`."""
        y2, batch = prepare_measurements(y, self.system.m)
        self.censoring.check_measurements(y2)
        at_lo, at_hi = self.censoring.censored_mask(y2, rtol=self.rtol)
        T, m = y2.shape[1:]
        out = kalman_filter(self.system, y2.reshape(batch + (T, m)), u=u, skip=(at_lo | at_hi).reshape(batch + (T, m)),
                            covariance_update=self.covariance_update, x0=x0, P0=P0)
        T, n = y2.shape[1], self.system.n
        return FilterResult(mean=out.mean.reshape(batch + (T, n)), cov=out.cov.reshape(batch + (T, n, n)),
                            pred_mean=out.pred_mean.reshape(batch + (T, n)),
                            pred_cov=out.pred_cov.reshape(batch + (T, n, n)),
                            extras={"censored": (at_lo | at_hi).reshape(batch + (T, self.system.m))})
