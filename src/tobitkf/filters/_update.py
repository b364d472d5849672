r"""The one time update and the one measurement update of every Gaussian-update family (numpy path).

What a family contributes (:class:`Transition`, :class:`MeasurementPrediction`) and the shared steps that use it:
the predict (:func:`predict`, the block shift of an augmented state :func:`shift_predict`, the square-root
:func:`sqrt_predict`, :func:`time_update`), and the update (:func:`gain_update`, :func:`sqrt_update`,
:func:`measurement_update`), each with its equations in its docstring. :mod:`tobitkf.filters.core` re-exports
them beside the state, the result and the estimator base classes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any, cast

import numpy as np

from .._linalg import psd_sqrt, symmetrize
from . import _backend

_TINY = np.finfo(np.float64).tiny

__all__ = [
    "Transition",
    "MeasurementPrediction",
    "predict",
    "shift_predict",
    "sqrt_predict",
    "qr_r",
    "time_update",
    "gain_update",
    "sqrt_update",
    "measurement_update",
]

# --------------------------------------------------------------------------- what a family contributes


@dataclass(frozen=True, eq=False)
class Transition:
    r"""One time update :math:`\bar x = A\hat x + b`, :math:`\bar P = APA^T + Q_d`.

    ``A`` (n_x, n_x) dense, or (n, n) acting on block ``source`` of an augmented state when ``shift``
    (the block-shift transition :math:`\xi' = [A\xi_{source} + b;\ \xi_0;\ \dots;\ \xi_{L-1}]` of the
    fading, protocol and delay families); ``Qd`` the noise covariance (of the top block when
    ``shift``); ``b`` (N, n) or 0 an input offset; ``G`` a root of ``Qd`` (``G G^T = Qd``) for the
    square-root form (computed from ``Qd`` when None). ``P_fixed`` replaces the covariance
    recursion by a constant (fixed-gain filters).
    """

    A: np.ndarray
    Qd: np.ndarray
    b: Any = 0.0
    shift: bool = False
    source: int = 0
    G: np.ndarray | None = None
    P_fixed: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class MeasurementPrediction:
    r"""The moments a family hands to :func:`measurement_update` (see the module docstring).

    Attributes
    ----------
    expected : (N, m) ndarray
        :math:`\hat y = E[y_k \mid \text{prior}]`; the innovation is :math:`y_k - \hat y`.
    H0 : (m, n_x) ndarray, or (N or 1, m, n_x): one per run
        The common part of the effective measurement matrix.
    scale : (N, m) ndarray or None
        Per-run channel scale, :math:`H = \mathrm{diag}(s)H_0`; None means 1.
    noise : (N or 1, m) or (N or 1, m, m) ndarray
        The noise term N of :math:`R_{ee} = H\bar PH^T + N`: its diagonal, or the full matrix.
    valid : (N, m) bool ndarray or None
        Channels that take part (a missing reading, NaN, never does).
    observed : (N, m) ndarray or None
        The reading to use instead of the one passed to the step (a sensor in the loop that clips
        at a limit set from the prior).
    gain : (n_x, m) ndarray or None
        A fixed gain (steady-state filters): :math:`\hat x = \bar x + K(y - \hat y)` and the
        covariance is the transition's fixed one.
    posterior_cov : (N or 1, n_x, n_x) ndarray or None
        With a fixed ``gain``: the (constant) covariance after the update.
    retained : (N, m) ndarray or None
        Diagonal variance :math:`V` the reading leaves in the channel (an assumed-density update of a
        censored reading: the variance of the latent reading given that it was censored). The
        posterior covariance gains :math:`KVK^T` in every form: :math:`P = \bar P - K(R_{ee} - V)K^T`.
        None means 0 (the reading removes the whole innovation variance).
    extras : dict
        Per-step quantities the family reports (N, ...).
    """

    expected: np.ndarray
    H0: np.ndarray
    noise: np.ndarray
    scale: np.ndarray | None = None
    valid: np.ndarray | None = None
    observed: np.ndarray | None = None
    gain: np.ndarray | None = None
    posterior_cov: np.ndarray | None = None
    retained: np.ndarray | None = None
    extras: dict[str, Any] = field(default_factory=dict)


# --------------------------------------------------------------------------- the one predict


def predict(x: np.ndarray, P: np.ndarray, A: np.ndarray, Qd: np.ndarray, bx: Any = 0.0):
    r"""Time update :math:`\bar x = A\hat x + B^u u`, :math:`\bar P = \mathrm{sym}(A P A^T + Q)`
    (Miller (2.3), (3.20)–(3.21)), batched.

    ``x`` (N, n), ``P`` (N or 1, n, n); ``A`` (n, n) or (N or 1, n, n) (one per run); ``Qd`` (n, n) or
    (N or 1, n, n) the noise covariance :math:`BQB^T`; ``bx`` (N, n) or 0.
    """
    if A.ndim == 3:  # one transition per run
        xp = np.einsum("...ij,...j->...i", A, x) + bx
        return xp, symmetrize(A @ P @ np.swapaxes(A, -1, -2) + Qd)
    xp = x @ A.T + bx
    n = A.shape[-1]
    if A.ndim == 2 and P.ndim >= 2:
        # one GEMM per product over the stacked rows instead of a batched matmul of tiny
        # matrices (4x faster for 10^4 runs of n = 2): X = P A^T, then X^T A^T = A P^T A^T,
        # which the symmetrization makes equal to sym(A P A^T)
        X = (P.reshape(-1, n) @ A.T).reshape(P.shape)
        Pp = (X.swapaxes(-1, -2).reshape(-1, n) @ A.T).reshape(P.shape) + Qd
    else:
        Pp = A @ P @ A.T + Qd
    return xp, symmetrize(Pp)


def shift_predict(xi: np.ndarray, P: np.ndarray, A: np.ndarray, Qd: np.ndarray, bx: Any = 0.0, *, source: int = 0):
    r"""Time update of a state augmented with its own past (block-shift transition), batched.

    :math:`\xi = \mathrm{col}\{\xi_0, \dots, \xi_L\}` (blocks of size n); the transition puts
    :math:`A\xi_{source} + b` on top and shifts every block down by one:
    :math:`\bar\xi = [A\xi_s + b;\ \xi_0;\ \dots;\ \xi_{L-1}]`, with the noise ``Qd`` in the top block only:

    .. math::

        \bar P_{00} = AP_{ss}A^T + Q_d, \quad \bar P_{0,j+1} = AP_{s,j}, \quad \bar P_{i+1,j+1} = P_{ij}.

    ``source = 0`` is the fading and protocol augmentation (Geng et al. 2017, (17)–(18); Geng et al.,
    (17)–(18)); ``source = d`` the pure-delay model :math:`x(t+1) = Ax(t-d) + \cdots` (Li, Li & Wang).
    ``P`` (N or 1, n_x, n_x) must be **exactly symmetric**; O(N n n_x²) copies and two GEMMs over the
    stacked runs instead of two batched (n_x × n_x) matmuls. Only the top block can come out
    asymmetric (rounding), so only it is symmetrized. Equals ``sym(Aa @ P @ Aa.T + Qa)`` to
    rounding (tested) and is exactly symmetric.
    """
    N, nxi = xi.shape
    n = A.shape[-1]
    s0, s1 = source * n, (source + 1) * n
    if A.ndim == 3 or np.ndim(Qd) == 3:  # one transition per run: the same blocks, batched products
        A3 = A if A.ndim == 3 else A[None]
        xi_p = np.empty_like(xi)
        xi_p[:, :n] = np.einsum("...ij,...j->...i", A3, xi[:, s0:s1]) + bx
        xi_p[:, n:] = xi[:, : nxi - n]
        X = P[:, :, s0:s1] @ np.swapaxes(A3, -1, -2)  # (Np', nxi, n)
        Np = X.shape[0]
        P_p = np.empty((Np, nxi, nxi))
        top = A3 @ X[:, s0:s1] + Qd
        P_p[:, :n, :n] = 0.5 * (top + top.swapaxes(-1, -2))
        P_p[:, n:, :n] = X[:, : nxi - n]
        P_p[:, :n, n:] = X[:, : nxi - n].swapaxes(-1, -2)
        P_p[:, n:, n:] = P[:, : nxi - n, : nxi - n]
        return xi_p, P_p
    xi_p = np.empty_like(xi)
    xi_p[:, :n] = xi[:, s0:s1] @ A.T + bx
    xi_p[:, n:] = xi[:, : nxi - n]
    Np = P.shape[0]
    X = (P[:, :, s0:s1].reshape(-1, n) @ A.T).reshape(Np, nxi, n)  # P[:, :, s] A^T = (A P[:, s, :])^T
    P_p = np.empty_like(P)
    top = (X[:, s0:s1].swapaxes(-1, -2).reshape(-1, n) @ A.T).reshape(Np, n, n) + Qd
    P_p[:, :n, :n] = 0.5 * (top + top.swapaxes(-1, -2))
    P_p[:, n:, :n] = X[:, : nxi - n]
    P_p[:, :n, n:] = X[:, : nxi - n].swapaxes(-1, -2)
    P_p[:, n:, n:] = P[:, : nxi - n, : nxi - n]
    return xi_p, P_p


def sqrt_predict(x: np.ndarray, S: np.ndarray, A: np.ndarray, Qroot: np.ndarray, bx: Any = 0.0):
    r"""Square-root time update: :math:`\bar x = A\hat x + B^u u` and a factor of :math:`\bar P = APA^T + Q`.

    With :math:`P = SS^T` and :math:`Q = Q^{1/2}Q^{1/2\,T}`, the QR factorization

    .. math::

        \begin{bmatrix} S^T A^T \\ Q^{1/2\,T} \end{bmatrix} = \mathcal Q\,U, \qquad
        U^TU = A S S^T A^T + Q = \bar P,

    gives the new lower factor :math:`\bar S = U^T`, so :math:`\bar P = \bar S\bar S^T` is
    PSD by construction. ``x`` (N, n), ``S`` (N or 1, n, n); ``A`` (n, n); ``Qroot`` (n, q) with
    ``Qroot @ Qroot.T`` the noise covariance B Q B^T. Returns x̄ (N, n) and S̄ (N or 1, n, n),
    lower triangular, determined up to the signs of its columns (which do not change S̄S̄^T).
    """
    xp = x @ A.T + bx
    top = np.swapaxes(A @ S, -1, -2)
    bottom = np.broadcast_to(Qroot.T, top.shape[:-2] + Qroot.T.shape)
    U = qr_r(np.concatenate([top, bottom], axis=-2))
    return xp, np.swapaxes(U, -1, -2)


def _dense_shift(A: np.ndarray, nx: int, source: int) -> np.ndarray:
    """The (n_x, n_x) block-shift matrix with A acting on block ``source`` (square-root form)."""
    n = A.shape[-1]
    out = np.zeros((nx, nx))
    out[:n, source * n : (source + 1) * n] = A
    out[n:, : nx - n] = np.eye(nx - n)
    return out


def qr_r(M: np.ndarray) -> np.ndarray:
    """The R factor of the batched QR decomposition of ``M`` (``np.linalg.qr(M, mode="r")``; numpy's type
    stubs declare a QRResult for every mode)."""
    return cast(np.ndarray, np.linalg.qr(M, mode="r"))


def time_update(
    x: np.ndarray, P: np.ndarray | None, S: np.ndarray | None, tr: Transition, form: str, *, compiled: bool = False
):
    """The one predict of every Gaussian family: ``(x̄, P̄, S̄)`` from ``(x, P, S)`` and a :class:`Transition`.

    ``form`` is the covariance form (``"standard"``/``"joseph"`` propagate P, ``"square_root"`` S
    and P = S S^T). A fixed covariance (``tr.P_fixed``) is returned as is. ``compiled=True`` runs the
    compiled form (:func:`tobitkf.filters._compiled_step.time_update_runs`, equal to rounding) when numba
    imports and the case is covered (standard or Joseph form, one covariance per run), else this numpy code.
    """
    shared = np.ndim(tr.A) == 2 and np.ndim(tr.Qd) == 2  # the compiled step: one transition for all runs
    if compiled and shared and P is not None and _compiled_covers(x, P, form) and tr.P_fixed is None and tr.source == 0:
        kern = _core_compiled_module()
        if kern is not None:
            xp, Pp = _compiled_time_update(kern, x, P, tr)
            return xp, Pp, None
    if tr.P_fixed is not None:
        return (_shift_mean(x, tr) if tr.shift else x @ tr.A.T + tr.b), tr.P_fixed, None
    if form == "square_root":
        assert S is not None, "the square-root form carries the factor S"
        nx = x.shape[-1]
        if tr.shift:
            A = _dense_shift(tr.A, nx, tr.source)
            G = tr.G if tr.G is not None else psd_sqrt(tr.Qd)
            Gd = np.zeros((nx, G.shape[-1]))
            Gd[: G.shape[0]] = G
            xp, Sp = sqrt_predict(x, S, A, Gd, 0.0)
            if not (np.isscalar(tr.b) and tr.b == 0.0):
                xp[:, : tr.A.shape[-1]] += tr.b
        else:
            G = tr.G if tr.G is not None else psd_sqrt(tr.Qd)
            xp, Sp = sqrt_predict(x, S, tr.A, G, tr.b)
        return xp, symmetrize(Sp @ np.swapaxes(Sp, -1, -2)), Sp
    assert P is not None, "the standard and Joseph forms carry P"
    if tr.shift:
        xp, Pp = shift_predict(x, P, tr.A, tr.Qd, tr.b, source=tr.source)
    else:
        xp, Pp = predict(x, P, tr.A, tr.Qd, tr.b)
    return xp, Pp, None


def _core_compiled_module():
    """The compiled shared step (:mod:`tobitkf.filters._compiled_step`), or None when the filters' kernels
    cannot be compiled (:func:`tobitkf.filters._backend.numba_available`)."""
    return _load_core() if _backend.numba_available() else None


@lru_cache(maxsize=1)
def _load_core():
    try:
        from . import _compiled_step
    except ImportError:
        return None
    return _compiled_step


def _compiled_covers(x: np.ndarray, P: np.ndarray | None, form: str) -> bool:
    """Whether the compiled shared step covers this case: the standard or Joseph form with one covariance
    per run (a covariance shared by the runs, P (1, n, n) for N > 1, stays on numpy, which keeps it shared)."""
    return form != "square_root" and P is not None and P.ndim == 3 and P.shape[0] == x.shape[0]


def _f64(a: Any) -> np.ndarray:
    """``a`` as a C-contiguous, writeable float64 array: the one array type the compiled step is compiled for
    (a read-only or strided input would compile another specialization, tens of seconds on a loaded machine)."""
    arr = np.ascontiguousarray(a, dtype=np.float64)
    return arr if arr.flags.writeable else arr.copy()


def _compiled_time_update(kern, x: np.ndarray, P: np.ndarray, tr: Transition):
    N, nx = x.shape
    A = _f64(tr.A)
    n = A.shape[0]
    b = tr.b
    if isinstance(b, np.ndarray) and b.ndim == 2:
        bvec = _f64(b)
    else:
        bvec = np.zeros((1, n)) if (np.isscalar(b) and b == 0.0) else _f64(np.broadcast_to(b, (1, n)))
    xp, Pp = np.empty((N, nx)), np.empty((N, nx, nx))
    kern.time_update_runs(_f64(x), _f64(P), A, _f64(tr.Qd), bvec, xp, Pp)
    return xp, Pp


_ONES: dict[int, np.ndarray] = {}
_NO_ROWS: dict[tuple[int, str], np.ndarray] = {}


def _compiled_measurement_update(kern, x: np.ndarray, P: np.ndarray, innov, valid, mp: MeasurementPrediction, joseph):
    N, nx = x.shape
    m = mp.H0.shape[0]
    if mp.scale is None:
        scale = _ONES.get(m)
        if scale is None:
            scale = _ONES[m] = np.ones((1, m))
    else:
        scale = _f64(mp.scale).reshape(-1, m)
    noise = _f64(mp.noise)
    diag = noise.ndim == 2
    if diag:
        noise = noise.reshape(noise.shape[0], m, 1)
    valid = _no_rows(m, "b") if valid is None else np.require(valid, np.bool_, ("C", "W"))  # writable, as _f64
    retained = _no_rows(m, "f") if mp.retained is None else _f64(mp.retained).reshape(-1, m)
    xn, Pn = np.empty((N, nx)), np.empty((N, nx, nx))
    K, Ree = np.empty((N, nx, m)), np.empty((N, m, m))
    kern.measurement_update_runs(
        _f64(x),
        _f64(P),
        _f64(innov),
        valid,
        _f64(mp.H0),
        scale,
        noise,
        bool(diag),
        retained,
        bool(joseph),
        xn,
        Pn,
        K,
        Ree,
    )
    return xn, Pn, None, K, Ree


def _no_rows(m: int, kind: str) -> np.ndarray:
    """An empty (0, m) array (bool for ``kind`` "b"): the kernels' "not given"."""
    arr = _NO_ROWS.get((m, kind))
    if arr is None:
        arr = _NO_ROWS[(m, kind)] = np.empty((0, m), dtype=bool if kind == "b" else np.float64)
    return arr


def _shift_mean(x: np.ndarray, tr: Transition) -> np.ndarray:
    n = tr.A.shape[-1]
    out = np.empty_like(x)
    out[:, :n] = x[:, tr.source * n : (tr.source + 1) * n] @ tr.A.T + tr.b
    out[:, n:] = x[:, : x.shape[-1] - n]
    return out


# --------------------------------------------------------------------------- the one measurement update


def _gain(Rxe: np.ndarray, Ree: np.ndarray) -> np.ndarray:
    """K = Rxe Ree^{-1} for m > 1, solved with Ree scaled to unit diagonal.

    Channels whose innovation variances differ by many orders of magnitude (a nearly
    surely censored channel beside an ordinary one: Ree_ll ~ 1e-77 next to 1) make Ree
    so badly scaled that an unscaled solve returns gain entries wrong by 1e50 and the
    Joseph form turns them into a covariance of 1e33. With D = diag(Ree)^{-1/2},
    K = Rxe D (D Ree D)^{-1} D, and D Ree D is well conditioned. Requires diag(Ree) > 0.
    """
    d = 1.0 / np.sqrt(np.diagonal(Ree, axis1=-2, axis2=-1))
    scaled = Ree * d[..., :, None] * d[..., None, :]
    return np.swapaxes(np.linalg.solve(scaled, np.swapaxes(Rxe * d[..., None, :], -1, -2)), -1, -2) * d[..., None, :]


def gain_update(
    x: np.ndarray,
    P: np.ndarray,
    innov: np.ndarray,
    Rxe: np.ndarray,
    Ree: np.ndarray,
    valid: np.ndarray | None = None,
    *,
    H: np.ndarray | None = None,
    noise: np.ndarray | None = None,
):
    r"""Linear MMSE measurement update from its moments, batched, with per-run channel masks.

    .. math::

        K = R_{xe} R_{ee}^{-1}, \qquad \hat x = \bar x + K e, \qquad P = \bar P - K R_{xe}^T

    (Miller (3.32), (3.22), (3.42) corrected as in (3.55)). Channels where
    ``valid`` is False (missing, dropped, or with :math:`R_{ee,ll} = 0`, which includes a
    subnormal :math:`R_{ee,ll}` such as :math:`\gamma^2 C\bar P C^T` after γ underflowed) are removed
    from the update exactly: their rows and columns of :math:`R_{ee}` are replaced
    by the identity and their gain columns are zero.

    When ``H`` (N or 1, m, n) and ``noise`` (N or 1, m, m) are given, the covariance
    uses the Joseph form :math:`(I - KH)\bar P(I - KH)^T + K\,\mathrm{noise}\,K^T`.
    This is the procedural form (filterpy's ``update``); the families call
    :func:`measurement_update`, which computes the moments from a :class:`MeasurementPrediction`.

    Parameters
    ----------
    x : (N, n) ; P : (N or 1, n, n) ; innov : (N, m) ; Rxe : (N or 1, n, m) ; Ree : (N or 1, m, m)
    valid : (N, m) bool, optional

    Returns
    -------
    x, P, K
    """
    K, e, ok = _solve(Rxe, Ree, innov, valid)
    x_new = x + np.einsum("...ij,...j->...i", K, e)
    if H is None:
        P_new = P - K @ np.swapaxes(Rxe, -1, -2)
    else:
        if ok is not None:
            H = H * ok[..., :, None]
        n = P.shape[-1]
        IKH = np.eye(n) - K @ H
        P_new = IKH @ P @ np.swapaxes(IKH, -1, -2) + K @ noise @ np.swapaxes(K, -1, -2)
    return x_new, symmetrize(P_new), K


def _solve(Rxe: np.ndarray, Ree: np.ndarray, innov: np.ndarray, valid: np.ndarray | None):
    """Masked gain: ``(K, e, ok)``; ``ok`` is None when every channel of every run takes part."""
    m = Ree.shape[-1]
    diag = Ree.diagonal(0, -2, -1)
    # a subnormal diagonal (e.g. a TKF channel 40 sigma into the censored side) counts as 0:
    # LAPACK's solve takes its reciprocal, which overflows and turns the whole gain into NaN
    degenerate = ~(diag > _TINY)
    if valid is not None and valid.all():
        valid = None  # every channel takes part: the unmasked solve gives the same gain
    if valid is None and not degenerate.any():
        K = Rxe / Ree if m == 1 else _gain(Rxe, Ree)
        return K, innov, None
    ok = ~degenerate if valid is None else (valid & ~degenerate)
    if m == 1:
        K = Rxe * ok[..., None, :] / np.where(ok, diag, 1.0)[..., None, :]
    else:
        pair = ok[..., :, None] & ok[..., None, :]
        K = _gain(Rxe * ok[..., None, :], np.where(pair, Ree, np.eye(m)))
    return K, np.where(ok, innov, 0.0), ok


def _psd_root(M: np.ndarray) -> np.ndarray:
    return psd_sqrt(M)


def _solve_upper(U: np.ndarray, B: np.ndarray) -> np.ndarray:
    """X with U X = B for upper-triangular U (..., m, m), B (..., m, r): back substitution over m."""
    m = U.shape[-1]
    X = np.empty(np.broadcast_shapes(U.shape[:-2], B.shape[:-2]) + B.shape[-2:])
    for i in range(m - 1, -1, -1):
        acc = B[..., i, :] - np.einsum("...j,...jr->...r", U[..., i, i + 1 :], X[..., i + 1 :, :])
        X[..., i, :] = acc / U[..., i, i, None]
    return X


def sqrt_update(
    x: np.ndarray,
    S: np.ndarray,
    innov: np.ndarray,
    H: np.ndarray,
    R: np.ndarray,
    valid: np.ndarray | None = None,
    *,
    R_root: np.ndarray | None = None,
):
    r"""Square-root (array) form of the Kalman measurement update, batched, with per-run channel masks.

    With the prior factor :math:`\bar P = \bar S\bar S^T` and :math:`R = R^{1/2}R^{1/2\,T}`,
    one QR factorization of the pre-array

    .. math::

        \begin{bmatrix} R^{1/2\,T} & 0 \\ \bar S^T H^T & \bar S^T \end{bmatrix}
        = \mathcal Q \begin{bmatrix} U_{11} & U_{12} \\ 0 & U_{22} \end{bmatrix}

    gives, by comparing :math:`M^TM = U^TU`,
    :math:`U_{11}^TU_{11} = R_{ee} = H\bar PH^T + R`, :math:`U_{12}^TU_{11} = \bar PH^T` and
    :math:`U_{22}^TU_{22} = \bar P - \bar PH^TR_{ee}^{-1}H\bar P = P`. Hence
    :math:`K = \bar PH^TR_{ee}^{-1} = U_{12}^TU_{11}^{-T}` (one triangular solve,
    :math:`K^T = U_{11}^{-1}U_{12}`), :math:`\hat x = \bar x + Ke` and the new factor
    :math:`S = U_{22}^T`. The covariance :math:`P = SS^T` is PSD by construction. Cost per
    run: a QR of an (m+n) x (m+n) matrix, about :math:`\tfrac43(m+n)^3` flops, against
    :math:`\approx 2n^2m + nm^2` for the standard update. The form is not in the sources; it is
    the array form of the square-root filter (Kaminski, Bryson & Schmidt 1971; Bierman 1977).

    Channels are left out exactly as in :func:`gain_update`: a channel that is not
    ``valid`` or whose :math:`R_{ee,ll} = (H\bar P H^T)_{ll} + R_{ll}` is not above the
    smallest normal number gets a zero row of H, a unit noise decoupled from the other
    channels (its rows and columns of R replaced by the identity) and a zero innovation;
    its column of the pre-array is then a unit vector orthogonal to the others, so its gain
    column is exactly zero and the other channels' update is that of the reduced model.

    Parameters
    ----------
    x : (N, n) ; S : (N or 1, n, n) prior factor ; innov : (N, m)
    H : (N or 1, m, n) ; R : (N or 1, m, m) measurement-noise covariance (PSD)
    valid : (N, m) bool, optional
    R_root : (N or 1, m, m), optional
        A root of ``R`` to use when no channel is left out (saves a factorization).

    Returns
    -------
    x : (N, n) ; P : (N or 1, n, n) symmetric ; S : (N or 1, n, n) ; K : (N or 1, n, m)
    """
    m, n = H.shape[-2], H.shape[-1]
    HS = H @ S
    Rdiag = np.diagonal(R, axis1=-2, axis2=-1)
    diag = np.einsum("...ij,...ij->...i", HS, HS) + Rdiag
    degenerate = ~(diag > _TINY)
    e = innov
    if valid is None and not degenerate.any():
        root = psd_sqrt(R) if R_root is None else R_root
    else:
        ok = ~degenerate if valid is None else (valid & ~degenerate)
        HS = HS * ok[..., :, None]
        e = np.where(ok, innov, 0.0)
        off_diagonal = np.count_nonzero(R - Rdiag[..., :, None] * np.eye(m)) > 0
        if off_diagonal:
            pair = ok[..., :, None] & ok[..., None, :]
            root = psd_sqrt(np.where(pair, R, np.eye(m)))
        else:
            root = np.sqrt(np.where(ok, Rdiag, 1.0))[..., :, None] * np.eye(m)
    batch = np.broadcast_shapes(HS.shape[:-2], S.shape[:-2], root.shape[:-2])
    M = np.zeros(batch + (m + n, m + n))
    M[..., :m, :m] = np.swapaxes(root, -1, -2)
    M[..., m:, :m] = np.swapaxes(HS, -1, -2)
    M[..., m:, m:] = np.swapaxes(S, -1, -2)
    U = qr_r(M)
    K = np.swapaxes(_solve_upper(U[..., :m, :m], U[..., :m, m:]), -1, -2)
    S_new = np.swapaxes(U[..., m:, m:], -1, -2)
    x_new = x + np.einsum("...ij,...j->...i", K, e)
    return x_new, symmetrize(S_new @ np.swapaxes(S_new, -1, -2)), S_new, K


def _moments(P: np.ndarray, mp: MeasurementPrediction):
    """``(R_xe (Np, n_x, m), R_ee (Np', m, m), P H0^T)`` with GEMMs over the stacked runs."""
    H0 = mp.H0
    m, nx = H0.shape[-2:]
    Np = P.shape[0]
    if H0.ndim == 3:  # one measurement matrix per run (N or 1, m, nx)
        PH = P @ H0.swapaxes(-1, -2)
        HPH = H0 @ PH
    else:
        # P H0^T for every run as one GEMM over the stacked rows (P symmetric): (Np, nx, m)
        PH = (P.reshape(Np * nx, nx) @ H0.T).reshape(Np, nx, m)
        HPH = (PH.swapaxes(-1, -2).reshape(Np * m, nx) @ H0.T).reshape(Np, m, m)
    s = mp.scale
    if s is None:
        Rxe, Ree = PH, HPH
    else:
        Rxe = PH * s[:, None, :]
        Ree = HPH * s[:, :, None] * s[:, None, :]
    noise = mp.noise
    if noise.ndim == Ree.ndim - 1:  # diagonal noise (N or 1, m)
        Ree = Ree + (noise[..., :, None] if m == 1 else noise[..., :, None] * np.eye(m))
    else:
        Ree = Ree + noise
    return Rxe, Ree, PH


def measurement_update(
    x: np.ndarray,
    P: np.ndarray | None,
    S: np.ndarray | None,
    y: np.ndarray,
    mp: MeasurementPrediction,
    form: str = "standard",
    *,
    compiled: bool = False,
):
    r"""The one measurement update of every Gaussian family, in the covariance form ``form``.

    Computes :math:`R_{xe} = \bar PH^T`, :math:`R_{ee} = H\bar PH^T + N` from the family's
    :class:`MeasurementPrediction` (H = diag(scale) H0), the masked gain (channels that are not
    ``valid``, whose reading is NaN, or whose :math:`R_{ee,ll}` is not above the smallest normal
    number are left out exactly), and the posterior

    * ``"standard"``: :math:`P = \bar P - KR_{xe}^T`;
    * ``"joseph"``: :math:`(I - KH)\bar P(I - KH)^T + KNK^T`, applied as
      :math:`M = \bar P - KR_{xe}^T`, :math:`P = M - (MH^T - KN)K^T` (rank-m products over the
      stacked runs instead of dense (n_x × n_x) products; equal to rounding, tested);
    * ``"square_root"``: the QR array form of :func:`sqrt_update` on the factor ``S``;

    plus :math:`KVK^T` when the family retains a variance V (``mp.retained``); or, with a fixed gain (``mp.gain``), :math:`\hat x = \bar x + K(y - \hat y)` and the covariance
    unchanged.

    Parameters
    ----------
    x : (N, n_x) ; P : (N or 1, n_x, n_x) ; S : (N or 1, n_x, n_x) or None ; y : (N, m)
    mp : MeasurementPrediction
    form : {"standard", "joseph", "square_root"}
    compiled : bool, default False
        Run the compiled form (:func:`tobitkf.filters._compiled_step.measurement_update_runs`, equal to
        rounding) when numba imports and the case is covered (the standard or Joseph form, one covariance
        per run, no fixed gain), else this numpy code.

    Returns
    -------
    x : (N, n_x) ; P ; S (or None) ; K : gain ; Ree : innovation covariance (None for a fixed gain)
    """
    obs = y if mp.observed is None else mp.observed
    innov = obs - mp.expected
    missing = np.isnan(innov)
    valid = mp.valid
    if missing.any():
        valid = ~missing if valid is None else (valid & ~missing)
        innov = np.where(missing, 0.0, innov)
    if mp.gain is not None:
        e = innov if valid is None else np.where(valid, innov, 0.0)
        return x + e @ mp.gain.T, (P if mp.posterior_cov is None else mp.posterior_cov), S, mp.gain, None
    if compiled and _compiled_covers(x, P, form) and mp.H0.ndim == 2:
        kern = _core_compiled_module()
        if kern is not None:
            assert P is not None
            return _compiled_measurement_update(kern, x, P, innov, valid, mp, form == "joseph")
    if form == "square_root":
        H0 = mp.H0 if mp.H0.ndim == 3 else mp.H0[None]
        H = H0 if mp.scale is None else H0 * mp.scale[:, :, None]
        noise = mp.noise
        m = mp.H0.shape[-2]
        if noise.ndim == 2:
            nz = np.maximum(noise, 0.0)
            R = nz[..., :, None] * np.eye(m)
            root = np.sqrt(nz)[..., :, None] * np.eye(m)
        else:
            R = noise
            root = None
        assert S is not None, "the square-root form carries the factor S"
        xn, Pn, Sn, K = sqrt_update(x, S, innov, H, R, valid, R_root=root)
        if mp.retained is not None:
            # P + K V K^T as the factor of [S, K V^{1/2}]: one more QR, PSD by construction
            KV = K * np.sqrt(np.maximum(mp.retained, 0.0))[..., None, :]
            Sb = np.broadcast_to(Sn, KV.shape[:-2] + Sn.shape[-2:])
            U = qr_r(np.concatenate([np.swapaxes(Sb, -1, -2), np.swapaxes(KV, -1, -2)], axis=-2))
            Sn = np.swapaxes(U, -1, -2)
            Pn = symmetrize(Sn @ np.swapaxes(Sn, -1, -2))
        return xn, Pn, Sn, K, None
    assert P is not None, "the standard and Joseph forms carry P"
    Rxe, Ree, _ = _moments(P, mp)
    K, e, ok = _solve(Rxe, Ree, innov, valid)
    if K.shape[-1] == 1:  # one channel: K e and K R_xe^T are plain products (the same numbers, no einsum)
        x_new = x + K[..., 0] * e
        M = P - K * Rxe.swapaxes(-1, -2)
    else:
        x_new = x + np.einsum("...ij,...j->...i", K, e)
        M = P - K @ Rxe.swapaxes(-1, -2)
    if form == "joseph":
        nx = x.shape[-1]
        Nk = K.shape[0]
        if mp.H0.ndim == 3:
            MH = M @ mp.H0.swapaxes(-1, -2)
        else:
            MH = (M.reshape(Nk * nx, nx) @ mp.H0.T).reshape(Nk, nx, -1)  # M H0^T
        if mp.scale is not None:
            MH = MH * mp.scale[:, None, :]
        noise = mp.noise
        KN = K * noise[..., None, :] if noise.ndim == K.ndim - 1 else K @ noise
        M = M - (MH - KN) @ K.swapaxes(-1, -2)
    if mp.retained is not None:
        M = M + (K * mp.retained[..., None, :]) @ K.swapaxes(-1, -2)
    return x_new, symmetrize(M), None, K, Ree
