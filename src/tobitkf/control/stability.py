r"""Stability of the Tobit observer: Jacobians, mean-field error dynamics, a Lyapunov certificate.

Source: Miller (2015) Ch. 5, (5.1)–(5.56), Figs 5.1–5.9; our deviations are MB-01 to MB-07,
MB-15 and MB-18 of docs/sources/miller2015-ch5-7.md.

The fixed-gain Tobit observer in predictor form (5.2), for a channel censored to
``[lower, upper]`` (right censoring: ``lower = -inf``, ``upper = T``):

.. math::

    \hat x_{k+1} = A\hat x_k + L(y_k - E[\hat y_k]), \qquad E[\hat y_k] = h(\hat x_k) := E[\mathrm{clip}(C\hat x_k + v)]

and its mean-field ("noise replaced by its conditional mean", (5.5)–(5.7)) companion
:math:`x_{k+1} = Ax_k`, :math:`\hat x_{k+1} = A\hat x_k + L(h(x_k) - h(\hat x_k))`.

Key identity (ours, not in the source): :math:`\partial E[y]/\partial\mu = \gamma(\mu) = P(\text{uncensored})`,
so with :math:`\Gamma(x) = \mathrm{diag}_i\,\gamma_i(C_ix)`:

.. math::

    J = \begin{bmatrix} A & 0 \\ L\Gamma(x)C & A - L\Gamma(\hat x)C \end{bmatrix},
    \qquad \mathrm{eig}(J) = \mathrm{eig}(A) \cup \mathrm{eig}(A - L\Gamma(\hat x)C)

and the error :math:`e = x - \hat x` obeys exactly :math:`e_{k+1} = (A - L\bar\Gamma_kC)e_k` with
:math:`\bar\Gamma_k \in [0, 1]^m` diagonal (mean-value theorem). A common quadratic Lyapunov
function for the polytope :math:`\{A - LSC : S = \mathrm{diag}(s), s \in [0,1]^m\}`, checked at its
:math:`2^m` vertices, therefore certifies global convergence of the mean-field error for *any*
censoring limits, fixed or moving (:func:`certify_tkf_stability`).

Deviations from the source (docs/sources MB-01, MB-02, MB-04 to MB-07):

* (5.46)–(5.47) differentiate λ wrongly (missing C/σ on λ², sign) and leave φ_x undefined; the
  printed Jacobian (5.56) is kept only as the documented diagnostic
  :func:`dissertation_jacobian_5_56` (it makes J22(T) non-monotone: the "local disturbance near
  T = 0" of Figs 5.4/5.5 is its artifact). :func:`tobit_jacobian` is the correct one (MB-01).
* (5.23)/(5.25) claim every frozen :math:`A - L\Gamma C`, Γ = diag(γ) ∈ [0, 1]^m, is stable when A and
  A − LC are (MB-02). It holds for n = 1, and for one output (m = 1) with n = 2 (the characteristic
  polynomial is affine in γ and the Schur-stable monic quadratics form a convex set); it fails for one
  output with n = 3 (:data:`COUNTEREXAMPLE`) and already for n = 2 with two outputs
  (:data:`COUNTEREXAMPLE_TWO_OUTPUTS`, where a vertex Γ = diag(1, 0) is unstable). The certificate
  replaces it.
* (5.7)/(5.38) print :math:`-(\gamma + \hat\gamma)T`; the mean map here uses E[y] directly, which
  is the corrected :math:`-(\gamma - \hat\gamma)T` (MB-04).
"""

from __future__ import annotations

import itertools
from typing import Any, NamedTuple

import numpy as np
from scipy.special import ndtr

from .._validation import ShapeError, ValidationError, as_float_array, check_memory
from ..censored import censored_moments
from ..filters.fixed_gain import FixedGainTobitObserver

__all__ = [
    "tobit_jacobian",
    "tobit_error_jacobian",
    "mean_observer_map",
    "dissertation_jacobian_5_56",
    "certify_tkf_stability",
    "StabilityCertificate",
    "mean_field_error",
    "COUNTEREXAMPLE",
    "COUNTEREXAMPLE_TWO_OUTPUTS",
    "closed_loop_jacobian",
    "fixed_gain_tobit_observer",
]

COUNTEREXAMPLE = {
    "A": np.array([[-2.19, 1.0, 0.0], [-1.748, 0.0, 1.0], [-0.482, 0.0, 0.0]]),
    "L": np.array([[-2.48], [-1.448], [-1.232]]),
    "C": np.array([[1.0, 0.0, 0.0]]),
}
"""One output, n = 3 (MB-02): A and A − LC Schur (ρ = 0.875, 0.916) but ρ(A − 0.25 LC) = 1.084."""

COUNTEREXAMPLE_TWO_OUTPUTS = {
    "A": np.array([[0.3, 0.9], [0.6, 0.0]]),
    "L": np.array([[1.0, 1.0], [-1.0, -0.5]]),
    "C": np.eye(2),
}
"""Two outputs, n = 2 (MB-02): A and A − LC Schur (ρ = 0.9, eigenvalues 0.9, −0.6; ρ = 0.547) but the vertex
A − L·diag(1, 0)·C (the second output censored, the first not) has the eigenvalues 0.9 and −1.6."""


def _expected(C, x, sigma, lower, upper):
    st = censored_moments(x @ C.T, sigma, lower, upper)
    return st.censored_mean, st.p_uncensored


def mean_observer_map(
    A: Any, L: Any, C: Any, x: Any, xhat: Any, sigma: Any, lower: Any = -np.inf, upper: Any = np.inf
) -> tuple[np.ndarray, np.ndarray]:
    r"""Mean-field map (5.6)/(5.7): :math:`(x, \hat x) \mapsto (Ax,\ A\hat x + L(E[y](x) - E[\hat y](\hat x)))`.

    ``x``, ``xhat`` (..., n); ``sigma``, ``lower``, ``upper`` (m,) or scalars. Returns (x⁺, x̂⁺).
    """
    A, L, C = (np.atleast_2d(np.asarray(v, dtype=float)) for v in (A, L, C))
    x, xhat = np.asarray(x, dtype=float), np.asarray(xhat, dtype=float)
    ey, _ = _expected(C, x, sigma, lower, upper)
    eyh, _ = _expected(C, xhat, sigma, lower, upper)
    return x @ A.T, xhat @ A.T + (ey - eyh) @ L.T


def tobit_jacobian(
    A: Any, L: Any, C: Any, x: Any, xhat: Any, sigma: Any, lower: Any = -np.inf, upper: Any = np.inf
) -> np.ndarray:
    r"""Jacobian of :func:`mean_observer_map` (correct form, docs/sources MB-01): ``(..., 2n, 2n)``.

    .. math:: J = [[A, 0], [L\Gamma(x)C, A - L\Gamma(\hat x)C]], \quad \Gamma = \mathrm{diag}(P(\text{uncensored}))

    Examples
    --------
    Scalar example of §5.3.3 at x = x̂ = 0, T = 0: J22 = −0.8 − 0.0246211·0.5.

    >>> J = tobit_jacobian([[-0.8]], [[0.0246211]], [[1.0]], [0.0], [0.0], 0.5, -np.inf, 0.0)
    >>> round(float(J[1, 1]), 6)
    -0.812311
    """
    A, L, C = (np.atleast_2d(np.asarray(v, dtype=float)) for v in (A, L, C))
    x, xhat = np.asarray(x, dtype=float), np.asarray(xhat, dtype=float)
    _, g = _expected(C, x, sigma, lower, upper)
    _, gh = _expected(C, xhat, sigma, lower, upper)
    n = A.shape[0]
    batch = np.broadcast_shapes(g.shape[:-1], gh.shape[:-1])
    J = np.zeros(batch + (2 * n, 2 * n))
    J[..., :n, :n] = A
    J[..., n:, :n] = (L * g[..., None, :]) @ C
    J[..., n:, n:] = A - (L * gh[..., None, :]) @ C
    return J


def tobit_error_jacobian(
    A: Any, L: Any, C: Any, x: Any, e: Any, sigma: Any, lower: Any = -np.inf, upper: Any = np.inf
) -> np.ndarray:
    r"""Jacobian in (x, e) coordinates, e = x − x̂ (correct form of (5.50)–(5.54)): ``(..., 2n, 2n)``.

    :math:`\partial e^+/\partial x = -L(\Gamma(x) - \Gamma(x - e))C`, :math:`\partial e^+/\partial e = A - L\Gamma(x - e)C`.
    At e = 0 it has the eigenvalues of :func:`tobit_jacobian` (so Fig 5.4 and Fig 5.5 show the same curve).
    """
    A, L, C = (np.atleast_2d(np.asarray(v, dtype=float)) for v in (A, L, C))
    x, e = np.asarray(x, dtype=float), np.asarray(e, dtype=float)
    _, g = _expected(C, x, sigma, lower, upper)
    _, gh = _expected(C, x - e, sigma, lower, upper)
    n = A.shape[0]
    batch = np.broadcast_shapes(g.shape[:-1], gh.shape[:-1])
    J = np.zeros(batch + (2 * n, 2 * n))
    J[..., :n, :n] = A
    J[..., n:, :n] = -(L * (g - gh)[..., None, :]) @ C
    J[..., n:, n:] = A - (L * gh[..., None, :]) @ C
    return J


def closed_loop_jacobian(A: Any, B: Any, K: Any, L: Any, C: Any, gamma: Any) -> np.ndarray:
    r"""Local closed-loop matrix with u = −Kx̂ in (x, e) coordinates at e = 0 (ours, not in the source):
    ``[[A − BK, BK], [0, A − LΓC]]``; its eigenvalues are eig(A − BK) ∪ eig(A − LΓC) (local separation)."""
    A, B, K, L, C = (np.atleast_2d(np.asarray(v, dtype=float)) for v in (A, B, K, L, C))
    g = np.atleast_1d(np.asarray(gamma, dtype=float))
    n = A.shape[0]
    J = np.zeros((2 * n, 2 * n))
    J[:n, :n], J[:n, n:] = A - B @ K, B @ K
    J[n:, n:] = A - (L * g) @ C
    return J


def dissertation_jacobian_5_56(A: Any, L: Any, C: Any, x: Any, xhat: Any, sigma: float, T: float) -> np.ndarray:
    r"""The printed Jacobian (5.45)–(5.47)/(5.56), right censoring at T, **known to be wrong** (docs/sources MB-01).

    .. math::

        J_{21} &= L(\varphi_x(Cx - \sigma\lambda - T) + \gamma(C + \tfrac1\sigma C(Cx - T)\lambda + \sigma\lambda^2)) \\
        J_{22} &= A - L(\varphi_{\hat x}(C\hat x - \sigma\hat\lambda - T) + \hat\gamma(C + \tfrac1\sigma C(C\hat x - T)\hat\lambda + \sigma\hat\lambda^2))

    with the undefined :math:`\varphi_x` read as :math:`\phi(\alpha)`, :math:`\alpha = (T - Cx)/\sigma`,
    :math:`\lambda = \phi(\alpha)/\Phi(\alpha)`. Kept only as a diagnostic to reproduce the shape of
    Figs 5.4–5.9 (its J22(T) is non-monotone); single output only. Do not use it for design.
    """
    A, L, C = (np.atleast_2d(np.asarray(v, dtype=float)) for v in (A, L, C))
    if C.shape[0] != 1:
        raise ValidationError("C: the printed (5.56) is for one right-censored output (m = 1)")
    n = A.shape[0]

    def block(z):
        mu = float((C @ np.asarray(z, dtype=float))[0])
        alpha = (T - mu) / sigma
        phi = np.exp(-0.5 * alpha**2) / np.sqrt(2 * np.pi)
        gam = ndtr(alpha)
        lam = phi / gam
        scal = phi * (mu - sigma * lam - T)
        return L @ (scal * C + gam * (C + (1 / sigma) * C * (mu - T) * lam + sigma * lam**2 * C))

    J = np.zeros((2 * n, 2 * n))
    J[:n, :n] = A
    J[n:, :n] = block(x)
    J[n:, n:] = A - block(xhat)
    return J


class StabilityCertificate(NamedTuple):
    """Result of :func:`certify_tkf_stability`.

    ``certified``: True if a common quadratic Lyapunov function P was found; ``P`` (or None);
    ``vertex_radius``: spectral radius (DT) / max real part (CT) of A − LSC at each vertex;
    ``worst_sampled``: the worst value over a grid of the polytope's diagonal s·1 (a necessary
    check, skipped as a shortcut with ``grid=0``); ``worst_s``: where; ``message``: why (not) certified.
    """

    certified: bool
    P: np.ndarray | None
    vertex_radius: np.ndarray
    worst_sampled: float
    worst_s: float
    message: str


def certify_tkf_stability(
    A: Any, L: Any, C: Any, *, domain: str | None = None, grid: int = 201
) -> StabilityCertificate:
    r"""Common quadratic Lyapunov certificate for the Tobit observer error (replaces (5.23)/(5.25), MB-02).

    Searches P ⪰ I with :math:`(A - LSC)^TP(A - LSC) - P \preceq -I` (DT) or
    :math:`(A - LSC)^TP + P(A - LSC) \preceq -I` (CT) at all :math:`2^m` vertices
    :math:`S \in \{0, 1\}^m` (cvxpy with Clarabel, SCS as fallback). If found, the mean-field error
    :math:`e_{k+1} = (A - L\bar\Gamma_kC)e_k` converges to 0 for any censoring limits and any
    :math:`\bar\Gamma_k \in [0, 1]^m`, and with noise it stays mean-square bounded.

    ``domain`` ("dt": L is a predictor gain of x̂_{k+1} = Ax̂_k + L(y_k − E[ŷ_k]); "ct": an observer
    gain of the continuous-time error) is required; omitting it raises a ValidationError (the Tobit LQE
    functions differ in their domain, so it must be explicit).

    Returns "not certified" (``certified=False``) for :data:`COUNTEREXAMPLE` (a vertex check alone
    would pass there) and for :data:`COUNTEREXAMPLE_TWO_OUTPUTS` (an unstable vertex). The claim
    (5.23) of the text holds automatically only for n = 1, and for m = 1 with n = 2.

    Raises
    ------
    ValidationError
        Non-conforming matrices or an unknown domain.
    """
    from .._extras import require

    cp = require("cvxpy", extra="lmi", feature="the TKF stability certificate")
    require("clarabel", extra="lmi", feature="the TKF stability certificate")

    from .lqg import _domain

    domain = _domain(domain, "certify_tkf_stability")
    if isinstance(grid, bool) or not isinstance(grid, (int, np.integer)) or grid < 0:
        raise ValidationError(f"grid: expected a non-negative integer, got {grid!r}")
    check_memory(8 * int(grid), "grid", f"a grid of {grid} points")
    A, L, C = (np.atleast_2d(as_float_array(v, name)) for v, name in ((A, "A"), (L, "L"), (C, "C")))
    n, m = A.shape[0], C.shape[0]
    if A.shape != (n, n) or L.shape != (n, m) or C.shape != (m, n):
        raise ValidationError(f"A, L, C: expected (n, n), (n, m), (m, n), got {A.shape}, {L.shape}, {C.shape}")

    def rad(M):
        ev = np.linalg.eigvals(M)
        return float(np.max(np.abs(ev))) if domain == "dt" else float(np.max(ev.real))

    verts = [np.array(s, dtype=float) for s in itertools.product((0.0, 1.0), repeat=m)]
    Av = [A - (L * s) @ C for s in verts]
    vr = np.array([rad(M) for M in Av])
    ss = np.linspace(0.0, 1.0, max(grid, 2))
    samp = np.array([rad(A - s * L @ C) for s in ss])
    worst = int(np.argmax(samp))
    limit = 1.0 if domain == "dt" else 0.0

    def certificate(Pv: np.ndarray | None, message: str) -> StabilityCertificate:  # certified iff a P is given
        return StabilityCertificate(Pv is not None, Pv, vr, float(samp[worst]), float(ss[worst]), message)

    if np.any(vr >= limit):
        return certificate(None, "not certified: a vertex A - L S C is itself unstable")
    if grid > 0 and samp[worst] >= limit:
        return certificate(
            None,
            f"not certified: A - s L C is unstable at s = {ss[worst]:.3f} "
            f"({'spectral radius' if domain == 'dt' else 'max real part'} {samp[worst]:.4f})",
        )
    # scale to keep the LMI well conditioned
    scale = max(1.0, np.abs(A).max())
    P = cp.Variable((n, n), symmetric=True)
    cons = [P >> np.eye(n)]
    for M in Av:
        Mn = M / scale if domain == "ct" else M
        S = Mn.T @ P @ Mn - P if domain == "dt" else Mn.T @ P + P @ Mn
        cons.append(0.5 * (S + S.T) << -np.eye(n))
    prob = cp.Problem(cp.Minimize(cp.trace(P) * 1e-6), cons)
    status = None
    for solver in ("CLARABEL", "SCS"):
        try:
            prob.solve(solver=solver)
            status = prob.status
            if status in ("optimal", "optimal_inaccurate", "infeasible", "infeasible_inaccurate"):
                break
        except cp.error.SolverError:
            continue
    ok = False
    if status in ("optimal", "optimal_inaccurate") and P.value is not None:
        Pv = 0.5 * (P.value + P.value.T)
        ok = bool(np.linalg.eigvalsh(Pv).min() > 0)
        for M in Av:
            Mn = M / scale if domain == "ct" else M
            S = Mn.T @ Pv @ Mn - Pv if domain == "dt" else Mn.T @ Pv + Pv @ Mn
            ok &= bool(np.linalg.eigvalsh(0.5 * (S + S.T)).max() < 0)
    return certificate(
        Pv if ok else None,
        f"certified: common quadratic Lyapunov function over {len(verts)} vertices"
        if ok
        else f"not certified: no common quadratic Lyapunov function (solver status {status})",
    )


def mean_field_error(
    A: Any, L: Any, C: Any, x0: Any, e0: Any, steps: int, sigma: Any, lower: Any = -np.inf, upper: Any = np.inf
) -> tuple[np.ndarray, np.ndarray]:
    r"""Noise-free mean-field trajectories of :func:`mean_observer_map` from (x_0, x̂_0 = x_0 − e_0).

    Returns ``x`` and ``e`` of shape (..., steps+1, n). Used for the bounds of Figs 5.1–5.3
    (LQG error (A − LC)^k e_0 below, open-loop A^k e_0 above).
    """
    x = np.asarray(x0, dtype=float)
    xh = x - np.asarray(e0, dtype=float)
    x, xh = np.broadcast_arrays(x, xh)
    xs = [x]
    es = [x - xh]
    for _ in range(steps):
        x, xh = mean_observer_map(A, L, C, x, xh, sigma, lower, upper)
        xs.append(x)
        es.append(x - xh)
    return np.stack(xs, axis=-2), np.stack(es, axis=-2)


def fixed_gain_tobit_observer(
    A: Any,
    L: Any,
    C: Any,
    y: Any,
    sigma: Any,
    lower: Any = -np.inf,
    upper: Any = np.inf,
    *,
    xhat0: Any = None,
    gain_form: str = "tobit",
    form: str = "predictor",
) -> np.ndarray:
    r"""The fixed-gain observer of Ch. 5 (5.2), batched over runs.

    ``form="predictor"`` (5.2): :math:`\hat x_{k+1} = A\hat x_k + L(y_k - E[\hat y_k])`, ``y`` holds
    y_0..y_{T-1} and the output index k holds x̂_{k+1} (x̂_0 = ``xhat0``, default 0).
    ``form="filter"`` (the package convention): :math:`\bar x_k = A\hat x_{k-1}`,
    :math:`\hat x_k = \bar x_k + L(y_k - E[y_k](\bar x_k))`, ``y`` holds y_1..y_T and output index
    k-1 holds x̂_{k|k} (x̂_0 = ``xhat0``); with L = K_f this is the predictor form with L_p = AK_f.
    ``gain_form="linear"`` replaces E[ŷ] by Cx̂: the uncompensated LQG observer of Fig 5.11.

    Returns ``(..., T, n)``. The observer is
    :class:`~tobitkf.filters.fixed_gain.FixedGainTobitObserver` (online ``init``/``step`` too).
    """
    obs = FixedGainTobitObserver(A, L, C, sigma, lower, upper, gain_form=gain_form, form=form)
    y = as_float_array(y, "y")  # NaN refused: the fixed-gain observer cannot skip a sample
    if y.ndim < 2 or y.shape[-1] != obs.m:
        raise ShapeError(f"y: expected (..., T, {obs.m}), got shape {y.shape}")
    mean = obs.filter(y, x0=xhat0, outputs="mean").mean
    assert mean is not None, "outputs='mean' records the means"
    return mean
