r"""Censoring-limit control for a panning camera, and a TKF whose sensor window is steered each step.

Source: Miller (2015) §6.7 (airborne imager, saturation limits from the frame edges, (6.64)–(6.76));
our deviations MB-34 and MB-36 to MB-39 of docs/sources/miller2015-ch5-7.md.

A camera's field of view, projected on the ground, is a saturation window
:math:`[T_l, T_h]` of fixed width (constant altitude, pure translation, fixed focal length). Moving
the window is moving the censoring limits. The laws below set :math:`T_h` (and
:math:`T_l = T_h - \text{width}`) from the filter's *prior* (set before the frame is taken):

* keep-in-view rule (6.72): :math:`T_h = \max(T_{h,0},\ C\bar x + s\,\Phi^{-1}(p))`, p = 0.9999,
  s = σ (as printed) or :math:`\sqrt{\sigma^2 + C\bar\Psi C^T}` (``prior_var``, MB-39);
* centred window (6.73): :math:`T_{h,l} = C\bar x \pm \sigma\Phi^{-1}((1 + ED)/2)`, so that γ = ED and λ = 0;
* IMR feedback (6.74)–(6.75): :math:`T_h(k) = T_h(k-1) + \kappa\sum_i\lambda_i`, with the
  dissertation's :math:`\lambda_i = (\phi(b_i) - \phi(a_i))/\gamma_i`;
* covariance feedback (6.76): :math:`T_h(k) = T_h(k-1) + \kappa[(P_{11} - P_{ref,1}) - (P_{33} - P_{ref,2})]
  \,\mathrm{sign}(\hat y_1 - \hat y_2)`; single target
  :math:`\kappa\max(0, P_{11} - P_{ref})\,\mathrm{sign}(\hat y - (T_l + T_h)/2)`.

Deviations from the source (MB-37, MB-38): the printed (6.74) :math:`T_h(k) = T_h(k-1) - K\sum\lambda_i`
with K > 0 moves the window *away* from a target near an edge; the sign is corrected
(``kappa > 0``). The sign of (6.76) depends on which target is above; the sign(ŷ₁ − ŷ₂) factor is
added and the single-target law (not printed) is ours.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.special import ndtri

from .._validation import ValidationError, as_float, as_float_array, check_int
from ..censored import censored_moments
from ..channels.censoring import Censoring
from ..filters.tobit import TobitKalmanFilter
from ..models.linear import LinearSystem

__all__ = [
    "keep_in_view_limit",
    "centred_window",
    "imr_panning_step",
    "covariance_panning_step",
    "dissertation_variance_6_61",
    "MovingWindowResult",
    "moving_window_tkf",
    "constant_velocity",
]


def constant_velocity(
    dt: float, sigma_q: float, sigma_r: Any, *, targets: int = 1, cameras: int = 1, x0: Any = None, P0: Any = None
) -> LinearSystem:
    r"""Constant-velocity targets (6.64)–(6.66): state [x_p, x_v] per target, G = [Δ²/2, Δ]σ_q, each target
    position seen by ``cameras`` channels with noise std ``sigma_r``."""
    dt = as_float(dt, "dt", low=0.0, low_open=True)
    sigma_q = as_float(sigma_q, "sigma_q", low=0.0)
    targets, cameras = check_int(targets, "targets", minimum=1), check_int(cameras, "cameras", minimum=1)
    A1 = np.array([[1.0, dt], [0.0, 1.0]])
    G1 = np.array([[dt**2 / 2], [dt]])
    A = np.kron(np.eye(targets), A1)
    G = np.kron(np.eye(targets), G1)
    C1 = np.kron(np.eye(targets), [[1.0, 0.0]])
    C = np.vstack([C1] * cameras)
    m = C.shape[0]
    sr = as_float_array(sigma_r, "sigma_r")
    if sr.size not in (1, m) or (sr <= 0).any():
        raise ValidationError(f"sigma_r: expected one positive noise std or {m}, got {sr}")
    sr = np.broadcast_to(sr.reshape(-1), (m,))
    n = 2 * targets
    return LinearSystem(
        A=A,
        C=C,
        Q=np.eye(targets) * sigma_q**2,
        R=np.diag(sr**2),
        B=G,
        x0=np.zeros(n) if x0 is None else x0,
        P0=np.eye(n) if P0 is None else P0,
    )


def keep_in_view_limit(
    prior_measurement: Any,
    sigma: Any,
    upper0: float,
    *,
    width: float = 50.0,
    probability: float = 0.9999,
    prior_var: Any = None,
) -> tuple[np.ndarray, np.ndarray]:
    r"""Rule (6.72): :math:`T_h = \max(T_{h,0}, C\bar x + s\Phi^{-1}(p))`, :math:`T_l = T_h - \text{width}`.

    ``prior_var`` (:math:`C\bar\Psi C^T`) switches s from σ (printed) to :math:`\sqrt{\sigma^2 + C\bar\Psi C^T}`
    (MB-39). Returns (lower, upper) with the shape of ``prior_measurement``.
    """
    probability = as_float(probability, "probability", low=0.0, high=1.0, low_open=True, high_open=True)
    width = as_float(width, "width", low=0.0, low_open=True)
    upper0 = as_float(upper0, "upper0")
    mu = np.asarray(prior_measurement, dtype=float)
    s = (
        np.asarray(sigma, dtype=float)
        if prior_var is None
        else np.sqrt(np.asarray(sigma, dtype=float) ** 2 + prior_var)
    )
    upper = np.maximum(upper0, mu + s * ndtri(probability))
    return upper - width, upper


def centred_window(prior_measurement: Any, sigma: Any, ed: float) -> tuple[np.ndarray, np.ndarray]:
    r"""Rule (6.73): :math:`C\bar x \mp \sigma\Phi^{-1}((1 + ED)/2)`; γ = ED and λ = 0 at the prior."""
    if not 0 < ed < 1:
        raise ValidationError(f"ed: expected P(uncensored) in the open interval (0, 1), got {ed}")
    mu = np.asarray(prior_measurement, dtype=float)
    z = np.asarray(sigma, dtype=float) * ndtri((1 + ed) / 2)
    return mu - z, mu + z


def imr_panning_step(upper: Any, width: float, prior_measurements: Any, sigma: Any, kappa: float) -> np.ndarray:
    r"""IMR feedback (6.74) with the corrected sign: :math:`T_h \leftarrow T_h + \kappa\sum_i\lambda_i`.

    ``prior_measurements`` (..., m): the targets' predicted positions; all share the window
    [T_h − width, T_h]. λ_i is the dissertation's :math:`(\phi(b_i) - \phi(a_i))/\gamma_i` (positive for a
    target near the upper edge), i.e. minus :attr:`CensoredMoments.inverse_mills`.
    """
    if kappa < 0:
        raise ValidationError(
            f"kappa: expected kappa >= 0 (the printed minus sign moves the window away, MB-37), got {kappa}"
        )
    up = np.asarray(upper, dtype=float)
    st = censored_moments(np.asarray(prior_measurements, dtype=float), sigma, (up - width)[..., None], up[..., None])
    return up + kappa * np.sum(-st.inverse_mills, axis=-1)


def covariance_panning_step(
    upper: Any, P_pos: Any, P_ref: Any, prior_measurements: Any, kappa: float, *, width: float | None = None
) -> np.ndarray:
    r"""Covariance feedback (6.76) with our sign factor (MB-38).

    Two targets: ``P_pos`` (..., 2) = (P11, P33), ``P_ref`` (2,), ``prior_measurements`` (..., 2):
    :math:`T_h + \kappa[(P_{11} - P_{ref,1}) - (P_{33} - P_{ref,2})]\mathrm{sign}(\hat y_1 - \hat y_2)`.
    One target (last axis 1; ``width`` needed):
    :math:`T_h + \kappa\max(0, P - P_{ref})\,\mathrm{sign}(\hat y - (T_l + T_h)/2)`.
    """
    up = np.asarray(upper, dtype=float)
    P = np.asarray(P_pos, dtype=float)
    ref = np.asarray(P_ref, dtype=float)
    y = np.asarray(prior_measurements, dtype=float)
    if P.shape[-1] == 1:
        if width is None:
            raise ValidationError("width: the single-target covariance law needs the window width")
        return up + kappa * np.maximum(0.0, P[..., 0] - ref[0]) * np.sign(y[..., 0] - (up - width / 2))
    if P.shape[-1] != 2:
        raise ValidationError(f"P_pos: expected 1 or 2 targets on the last axis, got {P.shape}")
    return up + kappa * ((P[..., 0] - ref[0]) - (P[..., 1] - ref[1])) * np.sign(y[..., 0] - y[..., 1])


def dissertation_variance_6_61(mean: Any, sigma: Any, lower: Any, upper: Any) -> np.ndarray:
    r"""The printed (6.61)/(6.69) truncated variance, **known to be wrong** (MB-34):
    :math:`\sigma^2(1 - \lambda^2 + \hat y\lambda/\sigma + (T_l\Phi(a) - T_h\Phi(b))/\gamma)`
    (Φ where φ belongs, a missing 1/σ). Kept only as a regression guard; use
    :func:`tobitkf.censored_moments` (the correct V)."""
    from scipy.special import ndtr

    mu, sd, lo, hi = (np.asarray(v, dtype=float) for v in (mean, sigma, lower, upper))
    a, b = (lo - mu) / sd, (hi - mu) / sd
    gam = ndtr(b) - ndtr(a)
    phi = lambda z: np.exp(-0.5 * z * z) / np.sqrt(2 * np.pi)  # noqa: E731
    lam = (phi(b) - phi(a)) / gam
    return sd**2 * (1 - lam**2 + mu * lam / sd + (lo * ndtr(a) - hi * ndtr(b)) / gam)


@dataclass(frozen=True)
class MovingWindowResult:
    """TKF with steered limits: ``mean`` (N, T, n), ``cov`` (N, T, n, n), ``lower``/``upper``/``y`` /
    ``p_uncensored`` (N, T, m)."""

    mean: np.ndarray
    cov: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    y: np.ndarray
    p_uncensored: np.ndarray


def moving_window_tkf(
    system: LinearSystem,
    y_latent: Any,
    law: Callable[[int, np.ndarray, np.ndarray, dict], tuple[np.ndarray, np.ndarray]],
    *,
    x0: Any = None,
    P0: Any = None,
) -> MovingWindowResult:
    r"""Run the TKF while a control law moves the sensor's censoring window each step.

    At step k, through the TKF's public online API: ``predict``; ``law(k, xbar, Pbar, memory)``
    returns the window ``(lower, upper)`` (N, m) set from the prior (``memory`` is a dict the law may
    use to keep its own state, e.g. the previous T_h); the latent reading is clipped there (the
    sensor); then ``update(pred, y_k, lower=, upper=)`` of a :class:`~tobitkf.TobitKalmanFilter`.

    Parameters
    ----------
    system : LinearSystem (time-invariant, diagonal R)
    y_latent : (N, T, m) array_like
    law : callable
    x0, P0 : optional filter prior
    """
    y_latent = np.asarray(y_latent, dtype=float)
    if y_latent.ndim != 3 or y_latent.shape[-1] != system.m:
        raise ValidationError(f"y_latent: expected (N, T, {system.m}), got {y_latent.shape}")
    N, T, m = y_latent.shape
    n = system.n
    tkf = TobitKalmanFilter(system, Censoring(), backend="numpy", check_limits=False)
    state = tkf.init((N,), x0=x0, P0=P0)
    out = {
        k: np.empty((N, T) + s)
        for k, s in (("mean", (n,)), ("cov", (n, n)), ("lower", (m,)), ("upper", (m,)), ("y", (m,)), ("gamma", (m,)))
    }
    memory: dict = {}
    for k in range(1, T + 1):
        pred = tkf.predict(state)
        assert pred.cov is not None, "the TKF carries its covariance"
        lo, hi = law(k, pred.mean, np.broadcast_to(pred.cov, (N, n, n)), memory)
        lo, hi = np.broadcast_to(lo, (N, m)), np.broadcast_to(hi, (N, m))
        yk = np.minimum(np.maximum(y_latent[:, k - 1], lo), hi)
        state = tkf.update(pred, yk, lower=lo, upper=hi)
        out["mean"][:, k - 1], out["cov"][:, k - 1] = state.mean, state.cov
        out["lower"][:, k - 1], out["upper"][:, k - 1], out["y"][:, k - 1] = lo, hi, yk
        out["gamma"][:, k - 1] = state.extras["p_uncensored"]
    return MovingWindowResult(out["mean"], out["cov"], out["lower"], out["upper"], out["y"], out["gamma"])
