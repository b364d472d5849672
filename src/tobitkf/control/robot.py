r"""Mobile robot localised by received signal strength (RSS), controlled through a Tobit observer.

Source: Miller (2015) §6.3, (6.22)–(6.44); our deviations MB-25 to MB-30 of docs/sources/miller2015-ch5-7.md.

Plant (6.22)–(6.25), state :math:`X_p = [x_p, x_v, y_p, y_v]`, a 2-D double integrator:

.. math::

    X_p(k+1) = A_pX_p + B_pU_p + G_pw, \qquad A_p = \mathrm{blkdiag}\Big(\begin{bmatrix}1&\Delta\\0&1\end{bmatrix}\times 2\Big),
    \quad G_p = \begin{bmatrix}\Delta^2/2m & 0\\ \Delta/m & 0\\ 0 & \Delta^2/2m\\ 0&\Delta/m\end{bmatrix}

Ranges to three transmitters as log-distances :math:`\ell_i = \log_{10}d_i` (6.28)–(6.33):
:math:`\ell_i(k+1) = \ell_i(k) + U_{d_i} + \eta_d`, :math:`RSS_i = -10\alpha\ell_i + \eta_{RSS}`, left-censored at
T = −90 dBm; :math:`U_{d_i} = \log_{10}\beta_i`, :math:`\beta_i = d_i(k+1)/d_i(k)` from the estimated position and
velocity. A trilateration (least squares (6.42)–(6.43)) of the ranges :math:`\hat d_i = 10^{\bar\ell_i}` gives two
uncensored pseudo-measurements of the position; measurement vector (6.44):
:math:`Z = [\hat x^{LS}, \hat y^{LS}, RSS_1, RSS_2, RSS_3]`. Control (6.22): :math:`U_p = \bar Nr - K\hat X_p`, LQR with
output/effort weighting 1000:1.

Deviations and reconstructions (all labelled in the experiment):

* B_p printed as [[1,0],[0,0],[0,1],[0,0]] acts on positions only: (A_p, B_p) is not stabilizable (the
  LQR fails with an error naming the uncontrollable modes). The force input B_p = G_p is used
  (MB-25); ``input_matrix="printed"`` reproduces the failure.
* (6.33) sets :math:`U_d = \tfrac12\log_{10}\beta_i` although β already includes the square root; the default is
  :math:`\log_{10}\beta_i` (MB-28); ``half_log=True`` gives the printed ½.
* (6.27)'s P_L(d_0) constant is dropped (MB-27): RSS = −60 log₁₀ d + η, so −90 dBm is d = 31.62 m.
* Δ, m, horizon, ω and the direction are not given: Δ = 0.1, m = 1, N = 1000, ω = 2π/(NΔ),
  r(k) = ζ[sin(ωkΔ), cos(ωkΔ)] from (0, ζ) (MB-26). η_RSS = 2 dB, σ_q = 0.1, σ_r = 0.05 are standard
  deviations; Ψ_0 = 0.1 I (MB-29). The range estimate for the pseudo-measurement is the a-priori
  ℓ̄ of the current step (MB-30).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .._progress import plural
from .._validation import as_float, as_generator, check_count, check_memory, check_option
from ..channels.censoring import Censoring
from ..filters.kalman import KalmanFilter
from ..filters.tobit import TobitKalmanFilter
from ..models.linear import LinearSystem
from .lqg import dlqr, reference_gain

__all__ = ["RobotSetup", "robot_setup", "simulate_robot", "RobotResult", "trilaterate", "TRANSMITTERS"]

#: Transmitter positions of §6.3.6.
TRANSMITTERS = np.array([[0.0, 10.0], [10.0, -10.0], [-10.0, -10.0]])


@dataclass(frozen=True)
class RobotSetup:
    """Matrices and constants of the robot problem (see the module docstring)."""

    dt: float
    Ap: np.ndarray
    Bp: np.ndarray
    Gp: np.ndarray
    Cp: np.ndarray
    K: np.ndarray
    Nbar: np.ndarray
    alpha: float
    sigma_q: float
    sigma_r: float
    sigma_rss: float
    eta_d: float
    limit: float
    transmitters: np.ndarray


def robot_setup(
    *,
    dt: float = 0.1,
    mass: float = 1.0,
    alpha: float = 6.0,
    sigma_q: float = 0.1,
    sigma_r: float = 0.05,
    sigma_rss: float = 2.0,
    limit: float = -90.0,
    weight: float = 1000.0,
    input_matrix: str = "force",
) -> RobotSetup:
    """Build the §6.3 problem; ``input_matrix="printed"`` uses the printed B_p (raises: not stabilizable)."""
    check_option(input_matrix, "input_matrix", ("force", "printed"))
    dt, mass, alpha, sigma_q, sigma_r, sigma_rss = (
        as_float(v, name, low=0.0, low_open=True)
        for v, name in (
            (dt, "dt"),
            (mass, "mass"),
            (alpha, "alpha"),
            (sigma_q, "sigma_q"),
            (sigma_r, "sigma_r"),
            (sigma_rss, "sigma_rss"),
        )
    )
    limit, weight = as_float(limit, "limit"), as_float(weight, "weight", low=0.0, low_open=True)
    A1 = np.array([[1.0, dt], [0.0, 1.0]])
    Ap = np.kron(np.eye(2), A1)
    Gp = np.kron(np.eye(2), [[dt**2 / (2 * mass)], [dt / mass]])
    Bp = Gp.copy() if input_matrix == "force" else np.array([[1.0, 0], [0, 0], [0, 1.0], [0, 0]])
    Cp = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    K = dlqr(Ap, Bp, weight * Cp.T @ Cp, np.eye(2)).gain
    Nbar = reference_gain(Ap, Bp, Cp, K, domain="dt")
    eta_d = float(np.log10(1 + sigma_rss / (10 * alpha)))  # (6.37)-(6.40): 0.014240
    return RobotSetup(dt, Ap, Bp, Gp, Cp, K, Nbar, alpha, sigma_q, sigma_r, sigma_rss, eta_d, limit, TRANSMITTERS)


def trilaterate(d: np.ndarray, transmitters: np.ndarray = TRANSMITTERS) -> np.ndarray:
    r"""Least-squares position from ranges (6.42)–(6.43): rows (i, j) of
    :math:`[2(x_j - x_i), 2(y_j - y_i)]\,[x, y]^T = d_i^2 - d_j^2 - x_i^2 - y_i^2 + x_j^2 + y_j^2`.

    ``d`` (..., N_tx) -> (..., 2).
    """
    tx = np.asarray(transmitters, dtype=float)
    pairs = [(i, j) for i in range(len(tx)) for j in range(i + 1, len(tx))]
    M = np.array([[2 * (tx[j, 0] - tx[i, 0]), 2 * (tx[j, 1] - tx[i, 1])] for i, j in pairs])
    rhs = np.stack([d[..., i] ** 2 - d[..., j] ** 2 - tx[i] @ tx[i] + tx[j] @ tx[j] for i, j in pairs], axis=-1)
    sol, *_ = np.linalg.lstsq(M, rhs.reshape(-1, len(pairs)).T, rcond=None)
    return sol.T.reshape(d.shape[:-1] + (2,))


@dataclass(frozen=True)
class RobotResult:
    """``x`` (N, T+1, 4) truth; ``estimate_tkf``/``estimate_kf`` (N, T, 7); ``rss`` (N, T, 3) censored readings;
    ``censored`` (N, T, 3); ``reference`` (T, 2); ``feedback`` the observer in the loop; ``diverged`` (N,) runs
    whose state or estimates left ``divergence_bound`` (frozen from then on, never NaN)."""

    x: np.ndarray
    estimate_tkf: np.ndarray
    estimate_kf: np.ndarray
    rss: np.ndarray
    censored: np.ndarray
    reference: np.ndarray
    feedback: str
    diverged: np.ndarray


def simulate_robot(
    setup: RobotSetup,
    *,
    radius: float = 27.0,
    steps: int = 1000,
    runs: int = 1,
    seed: Any = 0,
    feedback: str = "tkf",
    half_log: bool = False,
    P0: float = 0.1,
    divergence_bound: float = 1e5,
) -> RobotResult:
    r"""Simulate the §6.3 loop: TKF and KF run side by side, one of them (``feedback``) drives the robot.

    Both filters use the same 7-state model (4 robot states + 3 log-ranges), inputs
    :math:`[U_p, U_d]`, measurement :math:`Z` of (6.44); the KF treats censored RSS values as ordinary readings.
    Each step, through the estimators' public online API: ``predict(state, u=b_k)`` with the input
    effect :math:`b_k = [B_pu_k;\ \log_{10}\beta_k]` on a model whose input matrix is the identity,
    pseudo-measurement from the a-priori ranges, then ``update`` of the
    :class:`~tobitkf.TobitKalmanFilter` (censored RSS channels) or the :class:`~tobitkf.KalmanFilter`.

    Raises
    ------
    ValidationError
        Unknown ``feedback``, non-positive radius or steps.
    """
    check_option(feedback, "feedback", ("tkf", "kf"))
    radius = as_float(radius, "radius", low=0.0, low_open=True)
    steps, runs = check_count(steps, "steps"), check_count(runs, "runs")
    check_memory(
        8 * runs * (steps + 1) * 31,
        "runs/steps",
        f"{plural(runs, 'run')} x {plural(steps, 'step')} of the robot (states, two observers, readings, noises)",
    )
    s = setup
    rng = as_generator(seed)
    tx = s.transmitters
    n = 7
    A = np.eye(n)
    A[:4, :4] = s.Ap
    C = np.zeros((5, n))
    C[:2, :4] = s.Cp
    C[2:, 4:] = -10 * s.alpha * np.eye(3)
    Qd = np.zeros((n, n))
    Qd[:4, :4] = s.Gp @ (s.sigma_q**2 * np.eye(2)) @ s.Gp.T
    Qd[4:, 4:] = s.eta_d**2 * np.eye(3)
    sig = np.array([s.sigma_r, s.sigma_r, s.sigma_rss, s.sigma_rss, s.sigma_rss])
    R = np.diag(sig**2)
    lower = np.array([-np.inf, -np.inf, s.limit, s.limit, s.limit])
    upper = np.full(5, np.inf)
    omega = 2 * np.pi / (steps * s.dt)
    kk = np.arange(1, steps + 1)
    ref = radius * np.stack([np.sin(omega * kk * s.dt), np.cos(omega * kk * s.dt)], axis=1)

    def dist(pos):
        return np.maximum(np.linalg.norm(pos[..., None, :] - tx, axis=-1), 1e-6)

    x = np.zeros((runs, steps + 1, 4))
    l0 = np.log10(dist(np.zeros(2)))
    x0 = np.zeros(n)
    x0[4:] = l0
    model = LinearSystem(A=A, C=C, Q=Qd, R=R, x0=x0, P0=P0 * np.eye(n), Bu=np.eye(n))
    filters = {
        "tkf": TobitKalmanFilter(model, Censoring(lower=lower, upper=upper), backend="numpy", check_limits=False),
        "kf": KalmanFilter(model, backend="numpy"),
    }
    states = {key: f.init((runs,)) for key, f in filters.items()}
    stores = {key: np.empty((runs, steps, n)) for key in filters}
    rss_out = np.empty((runs, steps, 3))
    cens = np.empty((runs, steps, 3), dtype=bool)
    w = rng.standard_normal((runs, steps, 2)) * s.sigma_q
    v = rng.standard_normal((runs, steps, 3)) * s.sigma_rss
    vls = rng.standard_normal((runs, steps, 2)) * s.sigma_r
    alive = np.ones(runs, dtype=bool)
    for k in range(1, steps + 1):
        xf = states[feedback].mean
        u = ref[k - 1] @ s.Nbar.T - xf[:, :4] @ s.K.T
        xnew = x[:, k - 1] @ s.Ap.T + u @ s.Bp.T + w[:, k - 1] @ s.Gp.T
        alive &= (
            np.all(np.abs(xnew) < divergence_bound, axis=1)
            & np.all(np.abs(states["tkf"].mean[:, :4]) < divergence_bound, axis=1)
            & np.all(np.abs(states["kf"].mean[:, :4]) < divergence_bound, axis=1)
        )
        x[:, k] = np.where(alive[:, None], xnew, x[:, k - 1])
        rss_lat = -10 * s.alpha * np.log10(dist(x[:, k, [0, 2]])) + v[:, k - 1]
        rss = np.maximum(rss_lat, s.limit)
        rss_out[:, k - 1], cens[:, k - 1] = rss, rss_lat <= s.limit
        for key, f in filters.items():
            st = states[key]
            xh = st.mean
            pos = xh[:, [0, 2]]
            pos_next = pos + s.dt * xh[:, [1, 3]]  # (6.31)
            ud = np.log10(dist(pos_next) / dist(pos))  # log10 beta, (6.33) corrected
            if half_log:
                ud = 0.5 * ud
            pred = f.predict(st, u=np.concatenate([u @ s.Bp.T, ud], axis=1))
            ls = trilaterate(10.0 ** np.clip(pred.mean[:, 4:], -6.0, 6.0), tx) + vls[:, k - 1]  # pseudo-measurement
            new = f.update(pred, np.concatenate([ls, rss], axis=1))
            if not alive.all():  # a diverged run is frozen at its last estimate
                assert st.P is not None and new.P is not None, "the robot's filter carries its covariance"
                P_old = np.broadcast_to(st.P, (runs,) + st.P.shape[1:])
                P_new = np.broadcast_to(new.P, (runs,) + new.P.shape[1:])
                new = new.replace(
                    x=np.where(alive[:, None], new.x, st.x), P=np.where(alive[:, None, None], P_new, P_old)
                )
            states[key] = new
            stores[key][:, k - 1] = new.mean
    return RobotResult(x, stores["tkf"], stores["kf"], rss_out, cens, ref, feedback, ~alive)
