r"""Fitting linear state-space models to (censored) readings: EM with closed-form M-steps and direct maximisation.

Model: :math:`x_k = Ax_{k-1} + B^uu_k + w_{k-1}`, :math:`w \sim N(0, Q)`,
:math:`y^*_k = Cx_k + Du_k + v_k`, :math:`v \sim N(0, R)` (R = 0 allowed), :math:`x_0 \sim N(\bar x_0, P_0)`,
readings censored at the limits (or missing).

**EM** (Shumway & Stoffer 1982; Ghahramani & Hinton 1996). The E-step smooths the state augmented
with the measurement noise, :math:`\tilde x_k = (x_k, v_k)`, :math:`\tilde A = \mathrm{diag}(A, 0)`,
:math:`\tilde Q = \mathrm{diag}(Q, R)`, :math:`\tilde C = [C\ I]`, :math:`\tilde R = 0`, so that every
latent reading :math:`y^*_k = \tilde C\tilde x_k + Du_k` (exact, censored or missing alike) has
posterior moments: exact (Kalman/RTS) without censoring, the assumed-density smoother's
(:class:`~tobitkf.AssumedDensityTobitFilter`, uncensored readings first) with censoring. With
:math:`z_k = (x_{k-1}, u_k)`, :math:`s_k = (x_k, u_k)` and :math:`E` the posterior expectation, the M-step is

.. math::

    {[A\ B^u]} &= \sum_k E[x_kz_k^T]\Big(\sum_k E[z_kz_k^T]\Big)^{-1}, &
    Q &= \frac1T\sum_k E[(x_k - [A\ B^u]z_k)(x_k - [A\ B^u]z_k)^T], \\
    {[C\ D]} &= \sum_k E[y^*_ks_k^T]\Big(\sum_k E[s_ks_k^T]\Big)^{-1}, &
    R &= \frac1T\sum_k E[(y^*_k - [C\ D]s_k)(y^*_k - [C\ D]s_k)^T], \\
    \bar x_0 &= E[x_0], & P_0 &= \mathrm{Cov}(x_0 \mid y_{1:T}),

each only for the matrices in ``estimate`` (the others held; a held block's contribution is
subtracted before the regression). ``prior="stationary"`` ties :math:`P_0` to the solution of
:math:`P = APA^T + Q` after every M-step (the M-step then ignores the prior's dependence on A and Q, a
generalised-EM approximation). Without censoring each iteration increases the exact likelihood; with
censoring the E-step is approximate and so is the fixed point (the direct method maximises the
assumed-density likelihood itself).

**Direct** (the default): a user map :math:`\theta \mapsto` :class:`~tobitkf.LinearSystem`, or the
estimated matrices of a template (covariances through the log-Cholesky map, so that every step is a valid
model), and the Kalman or assumed-density log-likelihood, maximised by BFGS with finite-difference
gradients and the scale-free stopping rule of :func:`~tobitkf.inference._optimize.maximize`. For constant
matrices with a diagonal R (or one channel) each evaluation is one compiled pass of the filter's recursion
(:mod:`tobitkf.inference._compiled_ss`, equal to the filter's log-likelihood to rounding): about a
millisecond for 300 readings, so a fit of A, Q, R and a mean takes a fraction of a second where EM took
tens of seconds. Other models run the filters themselves.

**Convergence**: ``converged`` needs the Newton step with the observed information at the estimates to be
below ``gtol`` standard errors (EM included: EM's own rule, a small relative change of the likelihood,
stops it, but does not make it converged). A singular starting value of an estimated covariance is
refused (EM cannot move a zero variance, and its logarithm is :math:`-\infty`).

Standard errors: the observed information (central-difference Hessian of the log-likelihood) in the
estimated entries (EM: the free entries of each estimated matrix, upper triangles of Q and R) or in
:math:`\theta` (direct). Non-identified parameterisations (all of A, C, Q, R at once) have a singular
information and NaN standard errors.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from .._progress import plural
from .._validation import ShapeError, ValidationError, as_float_array, check_bool
from ..channels.censoring import Censoring
from ..models.linear import LinearSystem
from ._common import censoring_sides
from ._direct import checked_map, fit_map, start_values, system_or_none
from ._optimize import check_iterations, check_tolerance, maximize_closing, observed_information
from ._results import FitResult, _progress_callback

__all__ = ["StateSpaceModel", "fit_state_space", "em_step", "ESTIMABLE"]

ESTIMABLE = ("A", "C", "Q", "R", "Bu", "D", "x0", "P0")


def _required(system: LinearSystem, name: str) -> np.ndarray:
    """A matrix every LinearSystem has (A, C, Q, R), constant in time."""
    value = _const(system, name)
    assert value is not None, f"a LinearSystem always has {name}"
    return value


def _const(system: LinearSystem, name: str) -> np.ndarray | None:
    ts = getattr(system, name)
    if ts is None:
        return None
    if isinstance(ts, np.ndarray):
        return ts
    if ts.varying:
        raise ValidationError(f"{name}: fitting needs time-invariant matrices, got a time-varying {name}")
    return np.array(ts.at(ts.offset), dtype=float)


def _matrices(system: LinearSystem) -> dict[str, Any]:  # name -> array, None for an absent Bu, D
    out = {k: _const(system, k) for k in ("A", "C", "Q", "R", "Bu", "D", "B")}
    if out["B"] is not None:
        out["Q"] = out["B"] @ out["Q"] @ out["B"].T
        out["B"] = None
    out["x0"], out["P0"] = system.x0.copy(), system.P0.copy()
    return out


def _build(M: dict[str, Any]) -> LinearSystem:
    return LinearSystem(
        A=M["A"], C=M["C"], Q=_sym(M["Q"]), R=_sym(M["R"]), x0=M["x0"], P0=_sym(M["P0"]), Bu=M.get("Bu"), D=M.get("D")
    )


def _sym(P):
    return 0.5 * (P + P.T)


def _stationary_cov(A: np.ndarray, Q: np.ndarray) -> np.ndarray:
    from scipy.linalg import solve_discrete_lyapunov

    if np.max(np.abs(np.linalg.eigvals(A))) >= 1:
        raise ValidationError("prior: a stationary prior needs a stable A (spectral radius < 1)")
    return _sym(solve_discrete_lyapunov(A, Q))


class StateSpaceModel:
    """A fitted linear state-space model: the system, its censoring and which matrices were estimated.

    Parameters
    ----------
    system : LinearSystem
        The fitted (or template) system, time-invariant.
    censoring : Censoring, optional
    estimate : tuple of str
        The estimated matrices (EM) or ``("theta",)`` for a user map.
    """

    kind = "state_space"

    def __init__(
        self,
        system: LinearSystem,
        censoring: Censoring | None = None,
        estimate: tuple[str, ...] = (),
        prior: str = "given",
        diagonal_R: bool = False,
    ):
        self.fitted, self.censoring, self.estimate = system, censoring, tuple(estimate)
        self.prior, self.diagonal_R = prior, diagonal_R

    def __repr__(self) -> str:
        return f"StateSpaceModel(n={self.fitted.n}, m={self.fitted.m}, estimate={','.join(self.estimate)})"

    def system(self, theta=None, l: int = 0) -> LinearSystem:
        return self.fitted

    def to_spec(self) -> dict[str, Any]:
        M = _matrices(self.fitted)
        spec = {
            "kind": self.kind,
            "estimate": list(self.estimate),
            "prior": self.prior,
            "diagonal_R": self.diagonal_R,
            "system": {k: (None if v is None else np.asarray(v).tolist()) for k, v in M.items() if k != "B"},
        }
        if self.censoring is not None:
            spec["censoring"] = {
                "lower": np.where(np.isfinite(self.censoring.lower), self.censoring.lower, np.nan).tolist(),
                "upper": np.where(np.isfinite(self.censoring.upper), self.censoring.upper, np.nan).tolist(),
            }
        return spec

    @classmethod
    def from_spec(cls, spec: dict[str, Any]) -> StateSpaceModel:
        S = spec["system"]
        M = {
            k: (None if S.get(k) is None else np.array(S[k], dtype=float))
            for k in ("A", "C", "Q", "R", "Bu", "D", "x0", "P0")
        }
        cens = None
        if spec.get("censoring"):
            lo = np.array(
                [
                    [-np.inf if v is None or v != v else v for v in np.atleast_1d(r)]
                    for r in np.atleast_2d(np.array(spec["censoring"]["lower"], dtype=object))
                ],
                dtype=float,
            )
            hi = np.array(
                [
                    [np.inf if v is None or v != v else v for v in np.atleast_1d(r)]
                    for r in np.atleast_2d(np.array(spec["censoring"]["upper"], dtype=object))
                ],
                dtype=float,
            )
            shape = np.shape(spec["censoring"]["lower"])
            cens = Censoring(lower=lo.reshape(shape), upper=hi.reshape(shape))
        return cls(
            _build(M),
            cens,
            tuple(spec.get("estimate", ())),
            spec.get("prior", "given"),
            bool(spec.get("diagonal_R", False)),
        )

    # after the fit ---------------------------------------------------------------------
    def _filter(self, res, system=None):
        from ..filters.kalman import KalmanFilter
        from ._common import assumed_density_filter

        data = res.data
        system = system or self.fitted
        if self.censoring is None:
            return KalmanFilter(system, backend="numpy").filter(data["y"], u=data.get("u")), None
        r = assumed_density_filter(system, self.censoring).filter(
            data["y"], u=data.get("u"), censored=data.get("censored")
        )
        return r, r.extras["side"]

    def smooth(self, res):
        """Posterior mean and variance of the latent readings :math:`C x_k + D u_k` (T, m)."""
        from .smoothing import rts_smooth

        f, _ = self._filter(res)
        sm = rts_smooth(f, self.fitted)
        C = _const(self.fitted, "C")
        mean = sm.mean @ C.T
        D = _const(self.fitted, "D")
        if D is not None and res.data.get("u") is not None:
            mean = mean + np.asarray(res.data["u"]) @ D.T
        var = np.einsum("ij,tjk,ik->ti", C, sm.cov, C) + np.diagonal(_const(self.fitted, "R"))
        return mean, var

    def residuals(self, res, seed: int = 0):
        from scipy.special import ndtr, ndtri

        f, side = self._filter(res)
        y = np.asarray(res.data["y"], dtype=float)
        y = y[:, None] if y.ndim == 1 else y
        C, R = _required(self.fitted, "C"), _required(self.fitted, "R")
        D = _const(self.fitted, "D")
        assert f.pred_mean is not None and f.pred_cov is not None, "filter() records the predictions by default"
        mean = f.pred_mean @ C.T
        if D is not None and res.data.get("u") is not None:
            mean = mean + np.asarray(res.data["u"]) @ D.T
        sd = np.sqrt(np.einsum("ij,tjk,ik->ti", C, f.pred_cov, C) + np.diagonal(R))
        rng = np.random.default_rng(seed)
        u = ndtr((y - mean) / sd)
        if side is not None and (side != 0).any():
            F = ndtr((y - mean) / sd)
            draw = rng.uniform(size=y.shape)
            u = np.where(side < 0, draw * F, np.where(side > 0, F + draw * (1 - F), u))
        flags = res.data.get("censored")
        if side is not None and flags is not None and self.censoring is not None:
            inside = np.asarray(flags, dtype=bool) & (side == 0) & ~np.isnan(y)  # interval readings
            if inside.any():
                lo, hi = self.censoring.all_limits(*y.shape)
                Fa, Fb = ndtr((lo - mean) / sd), ndtr((hi - mean) / sd)
                u = np.where(inside, Fa + rng.uniform(size=y.shape) * (Fb - Fa), u)
        r = ndtri(np.clip(u, 1e-300, 1 - 1e-16))
        r[np.isnan(y)] = np.nan
        return r[:, 0] if r.shape[1] == 1 else r

    def forecast(self, res, steps: int, *, X=None, level: float = 0.95, lower=None, upper=None):
        r"""Gaussian forecasts from the last filtered state: :math:`\hat x_{T+h|T}`, :math:`P_{T+h|T}`, the latent
        reading :math:`N(C\hat x + Du, CPC^T + R)` with central intervals, and the reading clipped at the limits."""
        from scipy.special import ndtri

        from ..censored import censored_moments

        if X is not None and self.fitted.p is None:
            raise ValidationError("X: the model has no inputs")
        f, _ = self._filter(res)
        x, P = f.final.mean, f.final.cov
        if x.ndim > 1:
            x, P = x.reshape(-1), P.reshape(P.shape[-2:])
        A, Q, C, R = (_required(self.fitted, k) for k in ("A", "Q", "C", "R"))
        Bu, D = _const(self.fitted, "Bu"), _const(self.fitted, "D")
        if self.fitted.p is not None and X is None:
            raise ValidationError(f"X: expected the future inputs ({steps}, {self.fitted.p})")
        Uf = None if X is None else as_float_array(X, "X", ndim=2)
        if Uf is not None and Uf.shape != (steps, self.fitted.p):
            raise ShapeError(f"X: expected the future inputs of shape ({steps}, {self.fitted.p}), got {Uf.shape}")
        m = C.shape[0]
        z = float(ndtri(0.5 + level / 2))
        out: dict[str, Any] = {
            k: np.empty((steps, m))
            for k in ("mean", "sd", "lower", "upper", "censored_mean", "censored_lower", "censored_upper")
        }
        if self.censoring is not None:
            lo_c = self.censoring.lower[-1] if self.censoring.time_varying else self.censoring.lower
            hi_c = self.censoring.upper[-1] if self.censoring.time_varying else self.censoring.upper
        else:
            lo_c, hi_c = -np.inf, np.inf
        lo_c = np.broadcast_to(np.asarray(lo_c if lower is None else lower, dtype=float), (m,))
        hi_c = np.broadcast_to(np.asarray(hi_c if upper is None else upper, dtype=float), (m,))
        for h in range(steps):
            x = A @ x + (0.0 if Uf is None or Bu is None else Bu @ Uf[h])
            P = A @ P @ A.T + Q
            mu = C @ x + (0.0 if Uf is None or D is None else D @ Uf[h])
            s = np.sqrt(np.diagonal(C @ P @ C.T + R))
            out["mean"][h], out["sd"][h] = mu, s
            out["lower"][h], out["upper"][h] = mu - z * s, mu + z * s
            st = censored_moments(mu, np.maximum(s, 1e-300), lo_c, hi_c)
            out["censored_mean"][h] = st.censored_mean
            out["censored_lower"][h] = np.clip(mu - z * s, lo_c, hi_c)
            out["censored_upper"][h] = np.clip(mu + z * s, lo_c, hi_c)
        out["level"] = level
        return out


# --------------------------------------------------------------------------- EM


def _augmented(M: dict[str, Any]) -> LinearSystem:
    """The system with the state augmented by the measurement noise (module docstring)."""
    A, C, Q, R = M["A"], M["C"], M["Q"], M["R"]
    n, m = A.shape[0], C.shape[0]
    Aa = np.zeros((n + m, n + m))
    Aa[:n, :n] = A
    Qa = np.zeros((n + m, n + m))
    Qa[:n, :n] = Q
    Qa[n:, n:] = R
    Ca = np.hstack([C, np.eye(m)])
    x0 = np.concatenate([M["x0"], np.zeros(m)])
    P0 = np.zeros((n + m, n + m))
    P0[:n, :n] = M["P0"]
    Bu = None if M.get("Bu") is None else np.vstack([M["Bu"], np.zeros((m, M["Bu"].shape[1]))])
    return LinearSystem(A=Aa, C=Ca, Q=_sym(Qa), R=np.zeros((m, m)), x0=x0, P0=_sym(P0), Bu=Bu, D=M.get("D"))


def _e_step(M, y, u, censoring, censored):
    """Posterior moments of the augmented state; returns (stats, loglik)."""
    from ..filters.kalman import KalmanFilter
    from ._common import assumed_density_filter
    from .smoothing import rts_smooth

    aug = _augmented(M)
    if censoring is None:
        f = KalmanFilter(aug).filter(y, u=u)
        from .likelihood import prediction_log_densities

        ll = float(prediction_log_densities(aug, y, f, u=u).sum())
    else:
        f = assumed_density_filter(aug, censoring).filter(y, u=u, censored=censored)
        ll = float(np.sum(f.extras["log_likelihood"]))
    sm = rts_smooth(f, aug)
    return sm, ll


def _regression(Ezz, Etz, t, z, u, G, H, fit_G: bool, fit_H: bool):
    r"""Closed-form M-step of a regression :math:`t_k = G z_k + H u_k + e_k` on smoothed moments.

    ``Ezz`` (T, q, q) :math:`E[z_kz_k^T]`, ``Etz`` (T, r, q) :math:`E[t_kz_k^T]`, ``t`` (T, r) and ``z``
    (T, q) their means, ``u`` (T, p) or None the inputs; ``G`` (r, q) and ``H`` (r, p) or None the
    current values. Both fitted: :math:`[G\ H] = (\sum E[t s^T])(\sum E[s s^T])^{-1}` with
    :math:`s = (z, u)`; ``G`` alone: the same with the held ``H``'s part taken off :math:`\sum E[tz^T]`;
    ``H`` alone: the least squares of :math:`t - Gz` on u. The transition (t = x_k, z = x_{k-1},
    :math:`[A\ B^u]`) and the measurement (t = y*_k, z = x_k, :math:`[C\ D]`) both use it. Returns (G, H).
    """
    q = z.shape[1]
    use_u = fit_H and u is not None
    Szz = Ezz.sum(0)
    Stz = Etz.sum(0)
    if use_u and u is not None:
        Szz = np.block(
            [
                [Szz, (z[:, :, None] * u[:, None, :]).sum(0)],
                [(u[:, :, None] * z[:, None, :]).sum(0), (u[:, :, None] * u[:, None, :]).sum(0)],
            ]
        )
        Stz = np.hstack([Stz, (t[:, :, None] * u[:, None, :]).sum(0)])
    elif H is not None and u is not None:  # held input matrix: subtract its effect
        Stz = Stz - H @ (u[:, :, None] * z[:, None, :]).sum(0)
    if not fit_G:  # only H: regress the residual of G z
        r = t - z @ G.T
        assert u is not None, "estimating an input matrix needs the inputs (checked by the caller)"
        H = np.linalg.solve((u[:, :, None] * u[:, None, :]).sum(0), (u[:, :, None] * r[:, None, :]).sum(0)).T
    else:
        W = np.linalg.solve(Szz.T, Stz.T).T
        G = W[:, :q]
        if use_u and u is not None:
            H = W[:, q:]
    return G, H


def _less_inputs(S, d, t, f):
    r""":math:`E[(t - f - d)(t - f - d)^T]` from ``S`` = :math:`E[(t - f)(t - f)^T]` (T, r, r) and a known
    input term ``d`` (T, r): the noise covariance's terms of :math:`d = Hu` (``t`` the target's mean, ``f`` its
    fitted mean :math:`Gz`)."""
    return (
        S
        - d[:, :, None] * t[:, None, :]
        - t[:, :, None] * d[:, None, :]
        + d[:, :, None] * f[:, None, :]
        + f[:, :, None] * d[:, None, :]
        + d[:, :, None] * d[:, None, :]
    )


def em_step(
    M: dict[str, Any],
    y: np.ndarray,
    u: np.ndarray | None,
    censoring,
    censored,
    estimate: tuple[str, ...],
    prior: str = "given",
    diagonal_R: bool = False,
):
    """One EM iteration: E-step at ``M`` (a dict of matrices), M-step for ``estimate``; returns (new M, loglik at M)."""
    sm, ll = _e_step(M, y, u, censoring, censored)
    n, m = M["A"].shape[0], M["C"].shape[0]
    T = y.shape[0]
    X = np.asarray(sm.mean)  # (T, n + m)
    P = np.broadcast_to(sm.cov, (T,) + sm.cov.shape[-2:])
    cross = np.broadcast_to(sm.extras["cross_cov"], (T,) + sm.cov.shape[-2:])
    x_init, P_init = np.asarray(sm.extras["initial_mean"]), np.asarray(sm.extras["initial_cov"])
    xs = X[:, :n]
    Exx = P[:, :n, :n] + xs[:, :, None] * xs[:, None, :]
    prev = np.vstack([x_init[None, :n], xs[:-1]])
    Pprev = np.concatenate([P_init[None, :n, :n], P[:-1, :n, :n]])
    Epp = Pprev + prev[:, :, None] * prev[:, None, :]
    Exp = cross[:, :n, :n] + xs[:, :, None] * prev[:, None, :]  # E[x_k x_{k-1}^T]
    # latent readings y* = [C I] x_aug + D u
    Ca = np.hstack([M["C"], np.eye(m)])
    Du = 0.0 if (u is None or M.get("D") is None) else u @ M["D"].T
    ys = X @ Ca.T + Du  # (T, m)
    Pys = np.einsum("ij,tjk,lk->til", Ca, P, Ca)
    Eyy = Pys + ys[:, :, None] * ys[:, None, :]
    Eyx = np.einsum("ij,tjk->tik", Ca, P[:, :, :n]) + ys[:, :, None] * xs[:, None, :]
    new: dict[str, Any] = {k: (None if v is None else np.array(v, dtype=float)) for k, v in M.items()}
    # --- transition: [A Bu] from x_k on z = (x_{k-1}, u_k)
    if "A" in estimate or "Bu" in estimate:
        new["A"], new["Bu"] = _regression(
            Epp, Exp, xs, prev, u, new["A"], new.get("Bu"), "A" in estimate, "Bu" in estimate
        )
    if "Q" in estimate:
        A, Bu = new["A"], new.get("Bu")
        S = Exx - A @ Exp.transpose(0, 2, 1) - Exp @ A.T + A @ Epp @ A.T
        if Bu is not None and u is not None:
            S = _less_inputs(S, u @ Bu.T, xs, prev @ A.T)
        new["Q"] = _sym(S.mean(0))
    # --- measurement: [C D] from y* on s = (x_k, u_k)
    if "C" in estimate or "D" in estimate:
        new["C"], new["D"] = _regression(Exx, Eyx, ys, xs, u, new["C"], new.get("D"), "C" in estimate, "D" in estimate)
    if "R" in estimate:
        C, D = new["C"], new.get("D")
        du = np.zeros_like(ys) if (D is None or u is None) else u @ D.T
        S = Eyy - np.einsum("tij,kj->tik", Eyx, C) - np.einsum("ij,tkj->tik", C, Eyx) + C @ Exx @ C.T
        R = _sym(_less_inputs(S, du, ys, xs @ C.T).mean(0))
        if diagonal_R:
            R = np.diag(np.maximum(np.diagonal(R), 0.0))
        new["R"] = R
    if "x0" in estimate:
        new["x0"] = x_init[:n].copy()
    if "P0" in estimate and prior != "stationary":
        new["P0"] = _sym(P_init[:n, :n])
    if prior == "stationary":
        new["P0"] = _stationary_cov(new["A"], new["Q"])
    return new, ll


# --------------------------------------------------------------------------- parameter vectors for the s.e.


def _free_entries(M: dict[str, Any], estimate) -> list[tuple[str, tuple[int, ...]]]:
    out: list[tuple[str, tuple[int, ...]]] = []
    for name in ESTIMABLE:
        if name not in estimate or M.get(name) is None:
            continue
        v = M[name]
        if name in ("Q", "R", "P0"):
            for i in range(v.shape[0]):
                for j in range(i, v.shape[1]):
                    out.append((name, (i, j)))
        elif v.ndim == 1:
            out.extend((name, (i,)) for i in range(v.size))
        else:
            out.extend((name, (i, j)) for i in range(v.shape[0]) for j in range(v.shape[1]))
    return out


def _vec(M, entries):
    return np.array([M[n][idx] for n, idx in entries], dtype=float)


def _with(M, entries, vec):
    out = {k: (None if v is None else np.array(v, dtype=float)) for k, v in M.items()}
    for (n, idx), v in zip(entries, vec):
        out[n][idx] = v
        if len(idx) == 2 and n in ("Q", "R", "P0"):
            out[n][idx[::-1]] = v
    return out


_COVS = ("Q", "R", "P0")


def _free_pack(M, names) -> np.ndarray:
    """Unconstrained vector of the estimated matrices: entries as they are, covariances by the log-Cholesky
    map (log of the factor's diagonal, its strict lower triangle), so every vector is a valid model."""
    out = []
    for n in names:
        v = np.asarray(M[n], dtype=float)
        if n in _COVS:
            L = np.linalg.cholesky(_sym(v) + 1e-300 * np.eye(v.shape[0]))
            out.append(np.log(np.diagonal(L)))
            out.append(L[np.tril_indices(v.shape[0], -1)])
        else:
            out.append(v.ravel())
    return np.concatenate(out) if out else np.zeros(0)


def _free_unpack(M, names, u):
    out = {k: (None if v is None else np.array(v, dtype=float)) for k, v in M.items()}
    i = 0
    for n in names:
        shape = np.shape(M[n])
        if n in _COVS:
            k = shape[0]
            L = np.zeros((k, k))
            with np.errstate(over="ignore"):  # a trial step far out: an infinite variance, refused as a model
                L[np.diag_indices(k)] = np.exp(u[i : i + k])
            i += k
            nl = k * (k - 1) // 2
            L[np.tril_indices(k, -1)] = u[i : i + nl]
            i += nl
            out[n] = L @ L.T
        else:
            size = int(np.prod(shape))
            out[n] = np.asarray(u[i : i + size]).reshape(shape)
            i += size
    return out


def _entry_name(n, idx):
    return f"{n}[{','.join(str(i) for i in idx)}]"


# --------------------------------------------------------------------------- the fit


def _loglik(system: LinearSystem, y, u, censoring, censored) -> float:
    from .likelihood import adf_log_likelihood, kalman_log_likelihood

    try:
        if censoring is None:
            return float(kalman_log_likelihood(system, y, u=u))
        return float(adf_log_likelihood(system, censoring, y, u=u, censored=censored))
    except (ValidationError, np.linalg.LinAlgError, FloatingPointError):
        return -np.inf


class _Likelihood:
    """The log-likelihood of the fit's record under a model: the compiled kernel
    (:mod:`tobitkf.inference._compiled_ss`) for constant matrices with a diagonal R (or one channel), else
    :func:`_loglik` through the filters; the readings' classes (inside, censored at which limit) are
    worked out once. ``-inf`` for a matrix set that is not a valid model."""

    def __init__(self, y, u, censoring, censored):
        from .._compiled import numba_available

        self.y, self.u, self.censoring, self.censored = y, u, censoring, censored
        T, m = y.shape
        if censoring is None:
            self.side = np.zeros((T, m), dtype=np.int8)
            self.lim = np.full((T, m), np.nan)
        else:
            lo, hi = censoring.all_limits(T, m)
            self.side = np.ascontiguousarray(censoring_sides(y, lo, hi, censored, intervals=True), dtype=np.int8)
            self.lim = np.ascontiguousarray(np.where(self.side < 0, lo, np.where(self.side > 0, hi, np.nan)))
        # writable: numba types a read-only array (a record the caller froze) apart, one compile of the kernel more
        self.u_k = np.zeros((T, 0)) if u is None else np.require(u, float, ("C", "W"))
        self.y_k = np.require(y, float, ("C", "W"))
        # interval readings (flagged inside their limits) are scored by the filters, not the compiled kernel
        intervals = censored is not None and bool((np.asarray(censored, dtype=bool) & (self.side == 0)).any())
        self.compiled = numba_available() and not intervals

    def of_system(self, system: LinearSystem) -> float:
        try:
            M = _matrices(system)
        except ValidationError:
            return _loglik(system, self.y, self.u, self.censoring, self.censored)
        return self._run(M, system)

    def of_matrices(self, M: dict[str, Any]) -> float:
        try:
            system = _build(M)
        except (ValidationError, np.linalg.LinAlgError):
            return -np.inf
        return self._run(M, system)

    def _run(self, M: dict[str, Any], system: LinearSystem) -> float:
        R = np.asarray(M["R"], dtype=float)
        if not self.compiled or np.any(R - np.diag(np.diagonal(R))):
            return _loglik(system, self.y, self.u, self.censoring, self.censored)
        from . import _compiled_ss

        n, m, p = M["A"].shape[0], R.shape[0], self.u_k.shape[1]
        Bu = np.zeros((n, p)) if M.get("Bu") is None or p == 0 else M["Bu"]
        D = np.zeros((m, p)) if M.get("D") is None or p == 0 else M["D"]

        def c(a, dtype=float):  # C-contiguous and writable (np.diagonal returns a read-only view): one specialisation
            return np.require(a, dtype, ("C", "W"))

        v = float(
            _compiled_ss.log_likelihood(
                c(M["A"], dtype=float),
                c(_sym(M["Q"]), dtype=float),
                c(M["C"], dtype=float),
                c(np.diagonal(R), dtype=float),
                c(Bu, dtype=float),
                c(D, dtype=float),
                c(M["x0"], dtype=float),
                c(_sym(M["P0"]), dtype=float),
                self.y_k,
                self.side,
                self.lim,
                self.u_k,
            )
        )
        return v if np.isfinite(v) else -np.inf


def fit_state_space(
    model: Any,
    y: Any,
    *,
    u: Any = None,
    censoring: Censoring | None = None,
    censored: Any = None,
    lower: Any = None,
    upper: Any = None,
    estimate: Any = None,
    theta0: Any = None,
    method: str = "auto",
    likelihood: str = "auto",
    progress: Any = None,
    maxiter: int = 500,
    tol: float = 1e-7,
    prior: str = "given",
    diagonal_R: bool | None = None,
    standard_errors: bool = True,
    names: Any = None,
    gtol: float = 1e-3,
):
    """State-space fits (module docstring); called by :func:`tobitkf.fit`."""
    t0 = time.perf_counter()
    tol = check_tolerance(tol, "tol")
    gtol = check_tolerance(gtol, "gtol")
    maxiter = check_iterations(maxiter, "maxiter")
    standard_errors = check_bool(standard_errors, "standard_errors")
    if method not in ("auto", "em", "direct"):
        raise ValidationError(f"method: expected 'auto', 'em' or 'direct', got {method!r}")
    arr = as_float_array(y, "y", allow_nan=True)
    y2 = arr[:, None] if arr.ndim == 1 else arr
    if y2.ndim != 2:
        raise ShapeError(f"y: expected one record (T,) or (T, m), got shape {arr.shape}")
    T, m = y2.shape
    if T == 0 or m == 0 or np.isnan(y2).all():
        raise ValidationError(
            f"y: {'the one reading is' if y2.size == 1 else f'all {y2.size} readings are'} missing (NaN) or there are none: there is nothing to fit"
        )
    if censoring is None and (lower is not None or upper is not None):
        lo: Any = -np.inf if lower is None else np.asarray(lower, dtype=float)
        hi: Any = np.inf if upper is None else np.asarray(upper, dtype=float)
        lo = lo[:, None] if np.ndim(lo) == 1 and m == 1 and np.size(lo) == T else lo
        hi = hi[:, None] if np.ndim(hi) == 1 and m == 1 and np.size(hi) == T else hi
        censoring = Censoring(lower=lo, upper=hi)
    c2 = None
    if censored is not None:
        c2 = np.asarray(censored)
        c2 = c2[:, None] if c2.ndim == 1 else c2
    if likelihood not in ("auto", "kalman", "adf"):
        raise ValidationError(f"likelihood: expected 'auto', 'kalman' or 'adf', got {likelihood!r}")
    if likelihood == "kalman":
        censoring = None
    elif likelihood == "adf" and censoring is None:
        raise ValidationError("likelihood: 'adf' needs the censoring limits (censoring or lower/upper)")
    lik_name = "kalman" if censoring is None else "adf"
    if censoring is not None:
        censoring.check(m, T)
        lo_, hi_ = censoring.all_limits(T, m)
        censoring_sides(y2, lo_, hi_, c2, intervals=True)  # validates the indicator (interval readings taken)
    u2 = None if u is None else as_float_array(u, "u", ndim=2)
    if u2 is not None and u2.shape[0] != T:
        raise ShapeError(f"u: expected {T} rows (one per reading), got {u2.shape}")
    if prior not in ("given", "stationary"):
        raise ValidationError(f"prior: expected 'given' or 'stationary', got {prior!r}")
    progress_ = cb, close, ticker = _progress_callback(progress, "fit state-space model")
    data = {"y": y2, "u": u2, "censored": c2}
    lik = _Likelihood(y2, u2, censoring, c2)

    if callable(model) and not isinstance(model, LinearSystem):
        if method == "em":
            raise ValidationError("method: a user map theta -> LinearSystem is fitted directly ('direct')")
        if theta0 is None:
            raise ValidationError("theta0: a callable model needs starting values theta0")
        th0, names = start_values(theta0, names)
        sys_of = checked_map(model, LinearSystem)
        sys_of(th0)

        def ll_of(th):
            s = system_or_none(sys_of, th)
            return -np.inf if s is None else lik.of_system(s)

        return fit_map(
            ll_of,
            th0,
            names,
            gtol=gtol,
            maxiter=maxiter,
            progress=progress_,
            standard_errors=standard_errors,
            started=t0,
            model_of=lambda th: StateSpaceModel(sys_of(th), censoring, ("theta",), prior, False),
            n_obs=int((~np.isnan(y2)).sum()),
            likelihood=lik_name,
            data=data,
            extra={"theta_map": True},
        )

    if not isinstance(model, LinearSystem):
        raise ValidationError(f"model: expected a LinearSystem template, got {type(model).__name__}")
    estimate = ("A", "C", "Q", "R") if estimate is None else tuple(estimate)
    bad = [e for e in estimate if e not in ESTIMABLE]
    if bad:
        raise ValidationError(f"estimate: unknown matrix {bad[0]!r}; expected names from {', '.join(ESTIMABLE)}")
    M = _matrices(model)
    if any(M[k] is None for k in estimate):
        missing = [k for k in estimate if M[k] is None][0]
        raise ValidationError(f"estimate: the template has no {missing} to estimate (give a starting {missing})")
    if ("Bu" in estimate or "D" in estimate) and u2 is None:
        raise ValidationError("u: estimating Bu or D needs the inputs u")
    for k in ("Q", "R", "P0"):
        if k in estimate and not (k == "P0" and prior == "stationary"):
            ev = np.linalg.eigvalsh(_sym(np.asarray(M[k], dtype=float)))
            if not ev.min() > 1e-12 * max(1.0, float(ev.max())):
                raise ValidationError(
                    f"{k}: the starting value of an estimated covariance must be positive definite (a zero "
                    f"variance cannot move: EM keeps it, and its logarithm is -inf); got eigenvalues {ev.tolist()}"
                )
    if method == "auto":
        method = "direct"
    if diagonal_R is None:
        diagonal_R = censoring is not None and m > 1
    if prior == "stationary":
        M["P0"] = _stationary_cov(M["A"], M["Q"])
    entries = _free_entries(M, [e for e in estimate if not (e == "P0" and prior == "stationary")])
    enames = [_entry_name(n, idx) for n, idx in entries]

    def ll_matrices(Mv):  # the log-likelihood of matrices, a stationary prior following A and Q
        if prior == "stationary":
            try:
                Mv["P0"] = _stationary_cov(Mv["A"], Mv["Q"])
            except (ValidationError, np.linalg.LinAlgError):
                return -np.inf
        return lik.of_matrices(Mv)

    if method == "direct":
        free_names = [e for e in ESTIMABLE if e in estimate and not (e == "P0" and prior == "stationary")]

        def ll_free(w):
            return ll_matrices(_free_unpack(M, free_names, w))

        out = maximize_closing(
            ll_free,
            _free_pack(M, free_names),
            progress_,
            gtol=gtol,
            maxiter=maxiter,
            label=lambda w: dict(zip(enames, _vec(_free_unpack(M, free_names, w), entries).tolist())),
        )
        M = _free_unpack(M, free_names, out.x)
        if prior == "stationary":
            M["P0"] = _stationary_cov(M["A"], M["Q"])
        v = _vec(M, entries)

        trace, converged, message, evals = out.trace, out.converged, out.message, out.evaluations
    else:
        trace = []
        converged, message = False, f"EM stopped after {plural(maxiter, 'iteration')}"
        prev_ll = -np.inf
        evals = 0
        try:
            for it in range(1, maxiter + 1):
                M_new, ll = em_step(M, y2, u2, censoring, c2, estimate, prior, diagonal_R)
                evals += 1
                entry = {
                    "iteration": it,
                    "loglik": ll,
                    "params": dict(zip(enames, _vec(M, entries).tolist())),
                    "seconds": round(time.perf_counter() - t0, 4),
                }
                trace.append(entry)
                if cb is not None:
                    cb(entry)
                ticker.tick(f"EM iteration {it}, log-likelihood {ll:.6f}")
                if np.isfinite(prev_ll) and abs(ll - prev_ll) <= tol * max(1.0, abs(ll)):
                    converged, message = True, f"EM stopped: log-likelihood change below {tol:g} (relative)"
                    break
                prev_ll = ll
                M = M_new
        finally:
            close()

        v = _vec(M, entries)

    def it_ll(vv):  # the log-likelihood in the estimated entries at the fit, for the observed information
        return ll_matrices(_with(M, entries, vv))

    system = _build(M)
    ll = lik.of_matrices(M)
    cov = None
    if standard_errors and entries:
        ticker.tick("observed information")
        cov, converged, message, n_ev = observed_information(it_ll, v, ll, gtol, message)
        evals += n_ev
    fitted = StateSpaceModel(system, censoring, estimate, prior, diagonal_R)
    return FitResult(
        model=fitted,
        names=enames,
        theta=v,
        cov=cov,
        loglik=ll,
        n_obs=int((~np.isnan(y2)).sum()),
        n_params=len(entries),
        method=method,
        likelihood=lik_name,
        converged=converged,
        message=message,
        trace=trace,
        fit_seconds=time.perf_counter() - t0,
        evaluations=evals,
        data=data,
    )
