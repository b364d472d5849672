"""Miller (2015), Chapters 5–6: TKF stability and TKF output feedback (§5.2–5.4, §6.1–6.4).

* ``miller-jacobian-scalar``: §5.3.3, Figs 5.4–5.9 (Jacobian eigenvalues against T and σ) and the
  mean-field convergence scenarios of §5.2 (Figs 5.1–5.3).
* ``miller-dc-motor-speed``: §5.4.1, gains (5.61) and the Tobit gain at T = 0; Figs 5.10–5.14.
* ``miller-dc-motor-position``: §5.4.2, gains (5.67) and the Tobit gains at T = 0, −10°, −20°;
  Figs 5.15–5.18.

The closed-loop experiments of Chapter 6 (``miller-closed-loop``, ``miller-steady-state-lqg``) are in
:mod:`tobitkf.experiments.miller_closed_loop`.

The dissertation prints gains and eigenvalues (reproduced here next to the printed values, to their
printed digits) but no simulation numbers; simulation parameters it omits are our defaults, labelled
``"default"`` (docs/sources/miller2015-ch5-7.md, MB-21). Simulations run in discrete time (exact ZOH,
Δ = 0.01 s); the printed gains are the continuous-time ones (MB-08).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from scipy.special import ndtr

from .. import metrics as mx
from ..channels.censoring import Censoring
from ..control.lqg import discretize, dlqe, dlqr, lqe, tobit_dlqe, tobit_lqe
from ..control.plants import dc_motor_position, dc_motor_speed, scalar_example
from ..control.stability import dissertation_jacobian_5_56, fixed_gain_tobit_observer, mean_field_error, tobit_jacobian
from ..filters.registry import Lineup, describe, lineup
from ..models.linear import LinearSystem
from ..plotting import new_figure, save
from ..simulate.core import simulate
from . import ExperimentResult, register, setting
from . import _claims as CL

__all__ = ["jacobian_scalar", "dc_motor_speed_exp", "dc_motor_position_exp"]

_SOURCE = "Miller 2015: Estimation and Control with Censored Data (dissertation)"
DT = 0.01


ESTIMATION_LINEUP: Lineup = {"tkf": ("TobitKalmanFilter", {})}
"""The registry estimators of the open-loop estimation runs (the fixed-gain observers beside them,
:func:`~tobitkf.control.stability.fixed_gain_tobit_observer`, are control code, not registry entries)."""


def _noop(_: float) -> None:
    pass


def _c(z) -> list:
    """Complex array -> JSON-able [[re, im], ...] (real numbers stay plain)."""
    z = np.atleast_1d(np.asarray(z))
    if np.all(np.abs(np.imag(z)) < 1e-12):
        return np.real(z).tolist()
    return [[float(v.real), float(v.imag)] for v in z]


def _motor_plant(model, *, P0: float = 1e-6) -> tuple[LinearSystem, Any]:
    p = model()
    Ad, Bd, Qd = discretize(p.A, p.B, p.G, p.W, DT)
    n = Ad.shape[0]
    plant = LinearSystem(A=Ad, C=p.C, Q=Qd, R=p.V, x0=np.zeros(n), P0=P0 * np.eye(n), Bu=Bd)
    return plant, p


def _input_matrix(plant: LinearSystem) -> np.ndarray:
    """B of a motor plant (every plant here is built with its input matrix)."""
    assert plant.Bu is not None, "the motor plants have an input matrix"
    return plant.Bu.at(1)


def _motor_lqr(plant: LinearSystem) -> np.ndarray:
    n = plant.n
    Q = np.zeros((n, n))
    Q[0, 0] = 100.0
    return dlqr(plant.transition(0), _input_matrix(plant), Q, [[1e-6]]).gain


_LQR_SETTINGS = {
    "dt": setting(DT, "default", "exact ZOH discretization; the text gives no time step (MB-21)"),
    "lqr_Q": setting("diag(100, 0[, 0])", "default", "LQR weights not given (MB-21)"),
    "lqr_R": setting(1e-6, "default", "LQR weights not given (MB-21)"),
    "B": setting("[0; (0;) 1/l]", "reconstructed", "voltage input, not given (MB-24)"),
    "k": setting(9.73e-3, "reconstructed", "printed 9.37E-3 is a digit transposition (MB-09)"),
    "sigma_q": setting(0.01, "source", "a standard deviation (the text says variance, MB-12)"),
    "sigma_r": setting(0.05, "source", "a standard deviation (MB-12)"),
}
SIGMA = 0.05


# ======================================================================================
# miller-jacobian-scalar
# ======================================================================================
def _plot_jacobian(result: ExperimentResult, outdir: Path) -> list[Path]:
    d = result.data
    fig, ax = new_figure(1, 2, width=11, height=3.6)
    a = ax[0, 0]
    a.plot(d["T"], d["j22_naive"], color="tab:blue", label="correct J22, naive L = 0.0246 (Fig 5.4/5.5)")
    a.plot(d["T"], d["j22_printed"], color="tab:red", ls="--", label="printed (5.56), naive L (diagnostic)")
    a.plot(d["T"], d["j22_recomputed"], color="tab:green", label="correct J22, L recomputed (Fig 5.6/5.7)")
    a.axhline(-0.8, color="0.5", lw=0.6, ls=":")
    a.axhline(-0.8 - d["L_naive"], color="0.5", lw=0.6, ls=":")
    a.set_xlabel("censoring limit T")
    a.set_ylabel("estimator eigenvalue J22")
    a.set_title("Figs 5.4-5.7: A=-0.8, sigma=0.5, x = xhat = 0", fontsize=9)
    a.legend(fontsize=7)
    b = ax[0, 1]
    b.semilogx(d["sigma"], d["s_naive"], color="tab:blue", label="correct, naive L (Fig 5.8)")
    b.semilogx(d["sigma"], d["s_printed"], color="tab:red", ls="--", label="printed (5.56), naive L")
    b.semilogx(d["sigma"], d["s_recomputed"], color="tab:green", label="correct, L recomputed (Fig 5.9)")
    b.axhline(d["half_censored"], color="r", lw=0.6, label="50 % censored, naive L")
    b.set_ylim(-1.5, -0.78)
    b.set_xlabel("sigma (T = 0.5)")
    b.set_title("Figs 5.8-5.9: sigma sweep (recomputed L reaches -10 at sigma = 0.01)", fontsize=9)
    b.legend(fontsize=7)
    p1 = save(
        fig,
        outdir,
        "fig5_4-5_9_jacobian_sweeps.png",
        caption="Figs 5.4-5.9 (scalar example of §5.3.3, A = -0.8, σ = 0.5): the estimator eigenvalue J22 of the "
        "Tobit Jacobian at x = x̂ = 0 against the censoring limit T (left) and against σ at T = 0.5 "
        "(right): correct Jacobian with the uncensored gain L = 0.0246 (blue), the printed (5.56) with "
        "the same L (red dashed, kept to show where the source's curves come from, MB-01), and the "
        "correct Jacobian with L recomputed per T or σ from the modified ARE (green).",
    )
    fig, ax = new_figure(1, 2, width=11, height=3.4)
    for j, (name, title) in enumerate(
        (
            ("scenario3", "Fig 5.2: x uncensored, xhat censored (e0 < 0)"),
            ("scenario4", "Fig 5.3: x censored, xhat uncensored (e0 > 0)"),
        )
    ):
        s = d[name]
        k = np.arange(s["e"].shape[0])
        ax[0, j].plot(k, np.abs(s["e"]), color="k", label="|e| TKF observer (mean field)")
        ax[0, j].plot(k, np.abs(s["lqg"]), color="m", ls="--", label="LQG bound (A-LC)^k e0")
        ax[0, j].plot(k, np.abs(s["open"]), color="r", ls="--", label="open-loop bound A^k e0")
        ax[0, j].set_yscale("log")
        ax[0, j].set_xlabel("k")
        ax[0, j].set_title(title, fontsize=9)
        ax[0, j].legend(fontsize=7)
    p2 = save(
        fig,
        outdir,
        "fig5_1-5_3_error_bounds.png",
        caption="Figs 5.1-5.3 (convergence from different initial conditions, §5.2): the noise-free mean-field "
        "error of a scalar TKF observer (A = 0.9, L = 0.5, T = 0, σ = 0.1: our values, the text gives "
        "none) between the LQG error (A - LC)^k e0 and the open-loop error A^k e0.",
    )
    return [p1, p2]


@register(
    "miller-jacobian-scalar",
    title="Tobit observer Jacobian vs T and sigma, scalar example (Figs 5.1-5.9)",
    source=_SOURCE,
    plot=_plot_jacobian,
    default_runs=1,
)
def jacobian_scalar(*, runs: int = 1, seed: int = 0, progress=None) -> ExperimentResult:
    """§5.3.3: A = −0.8, C = 1, σ = 0.5, σ_q = 0.1; eigenvalue J22 of the Tobit Jacobian at x = x̂ = 0.

    Deterministic (``runs`` and ``seed`` are unused). The Jacobian is the correct one (docs/sources
    MB-01); the printed (5.56) is drawn as a labelled diagnostic. Figs 5.1–5.3 use the noise-free
    mean-field error of a DT scalar observer (A = 0.9, L = 0.5, T = 0, σ = 0.1: not from the source,
    the text gives no parameters for them, MB-21).
    """
    progress = progress or _noop
    s = scalar_example()
    g = lqe(s.A, s.G, s.C, s.W, s.V)
    L = float(g.gain[0, 0])
    sig = 0.5
    T = np.linspace(-2.0, 2.0, 161)

    def j22(Lv, t, sg=sig):
        return float(tobit_jacobian(s.A, [[Lv]], s.C, [0.0], [0.0], sg, -np.inf, t)[1, 1])

    def j22p(Lv, t, sg=sig):
        return float(dissertation_jacobian_5_56(s.A, [[Lv]], s.C, [0.0], [0.0], sg, t)[1, 1])

    def l_rec(t, sg=sig):
        xi = ndtr(t / sg)
        if xi >= 1.0:  # Phi rounds to 1: the uncensored limit of the modified ARE
            return float(lqe(s.A, s.G, s.C, s.W, [[sg**2]]).gain[0, 0])
        return float(tobit_lqe(s.A, s.G, s.C, s.W, V=[[sg**2]], xi_uncensored=xi).gain[0, 0])

    j_naive = np.array([j22(L, t) for t in T])
    j_print = np.array([j22p(L, t) for t in T])
    j_rec = np.array([j22(l_rec(t), t) for t in T])
    progress(0.5)
    sigmas = np.logspace(-2, 1, 61)
    s_naive = np.array([j22(L, 0.5, sg) for sg in sigmas])
    s_print = np.array([j22p(L, 0.5, sg) for sg in sigmas])
    s_rec = np.array([j22(l_rec(0.5, sg), 0.5, sg) for sg in sigmas])
    # tables of J22 at a few T
    tab_T = [-1.0, 0.0, 0.5, 1.0]
    tab_rec = {t: (l_rec(t), j22(l_rec(t), t)) for t in (-1.0, -0.5, 0.0, 0.5, 1.0, 2.0)}
    printed_tab = [j22p(0.0246, t) for t in (-0.25, 0.0, 0.25, 0.5)]
    # Figs 5.1-5.3: mean-field error between the LQG and open-loop bounds (DT scalar, defaults)
    A_d, L_d, sd = 0.9, 0.5, 0.1
    k = np.arange(101)
    scen = {}
    for name, x0, e0 in (("scenario3", -0.5, -1.0), ("scenario4", 0.5, 1.0)):
        _, e = mean_field_error([[A_d]], [[L_d]], [[1.0]], [x0], [e0], 100, sd, -np.inf, 0.0)
        scen[name] = {"e": e[:, 0], "lqg": (A_d - L_d) ** k * e0, "open": A_d**k * e0}
    between = all(
        np.all(np.abs(v["e"]) >= np.abs(v["lqg"]) - 1e-12) and np.all(np.abs(v["e"]) <= np.abs(v["open"]) + 1e-12)
        for v in scen.values()
    )
    mono_naive = bool(np.all(np.diff(j_naive) < 0))
    interior = (T > -0.5) & (T < 0.5)

    def extrema(v, mask):
        d = np.diff(v)
        turn = np.flatnonzero(np.sign(d[1:]) != np.sign(d[:-1])) + 1
        return [float(T[k]) for k in turn if mask[k]]

    print_turn, rec_turn = extrema(j_print, interior), extrema(j_rec, interior)
    mono_s = bool(np.all(np.diff(s_naive) >= -1e-15))
    ends = (float(j_naive[-1]), float(j_naive[0]))
    claims = [
        CL.matches_print(
            "(5.55): L = 0.0246 and eig(J_unc) = [-0.8, -0.8246]",
            quantity="CT Kalman–Bucy gain L and the second eigenvalue -0.8 - L (σ_q, σ standard deviations, MB-12)",
            value=[L, -0.8 - L],
            printed=["0.0246", "-0.8246"],
        ),
        CL.claim(
            "Figs 5.4/5.5: as T is lowered the estimator eigenvalue moves from the uncensored value (-0.8246) to "
            "the open-loop one (-0.8)",
            quantity="correct J22(T) at x = x̂ = 0, L = 0.0246, T from 2 down to -2 (±4σ)",
            measured=f"J22(2) = {ends[0]:.5f}, J22(-2) = {ends[1]:.5f}; monotone: {mono_naive}",
            test="J22 monotone in T, |J22(2) + 0.8 + L| <= tol, |J22(-2) + 0.8| <= tol",
            tolerance="1e-3 (at ±4σ the uncensored probability is within 3.2e-5 of 0 or 1; deterministic)",
            holds=mono_naive and abs(ends[0] + 0.8 + L) <= 1e-3 and abs(ends[1] + 0.8) <= 1e-3,
        ),
        CL.claim(
            "Fig 5.4: a 'local disturbance' near T = 0 (slightly more censoring is beneficial)",
            quantity="local extrema of the correct J22(T) for -0.5 < T < 0.5 (L = 0.0246)",
            measured=f"none (monotone: {mono_naive}); the printed (5.56) has them at T = "
            f"{[round(t, 2) for t in print_turn]} (values at T = -0.25, 0, 0.25, 0.5: "
            f"{', '.join(f'{v:.5f}' for v in printed_tab)})",
            test="the correct J22(T) has a local extremum in -0.5 < T < 0.5",
            tolerance="exact (grid of 161 T)",
            holds=bool(extrema(j_naive, interior)),
            explanation="the disturbance comes from the wrong derivative in (5.56) (docs/sources MB-01)",
        ),
        CL.claim(
            "Figs 5.6/5.7: with L recomputed per T (modified ARE) the disturbance disappears and the trend is smoother",
            quantity="local extrema of the correct J22(T) with L recomputed per T, -0.5 < T < 0.5",
            measured=f"{[round(t, 2) for t in rec_turn] or 'none'} in the window; global minimum "
            f"{j_rec.min():.5f} at T = {T[np.argmin(j_rec)]:.2f} (faster than the uncensored -0.8246 "
            "because υ < σ²)",
            test="no local extremum in -0.5 < T < 0.5",
            tolerance="exact (grid of 161 T)",
            holds=not rec_turn,
        ),
        CL.claim(
            "Fig 5.8: an overshoot of the eigenvalue for σ slightly above T - x (naive L)",
            quantity="monotonicity of J22(σ) at T = 0.5, L = 0.0246, σ from 0.01 to 10 (non-decreasing up to 1e-15)",
            measured=f"correct J22(σ) monotone: {mono_s}; printed (5.56) monotone: "
            f"{bool(np.all(np.diff(s_print) >= -1e-15))}",
            test="the correct J22(σ) is not monotone (an overshoot exists)",
            tolerance="exact (grid of 61 σ)",
            holds=not mono_s,
            explanation="the correct Jacobian has no overshoot; the printed (5.56) with L = 0.0246 has none on "
            "this grid either, so the overshoot of Fig 5.8 is not reproduced (docs/sources MB-01)",
        ),
        CL.claim(
            "Fig 5.9: a small σ gives a very fast estimator, a large σ behaves as 50 % censored",
            quantity="J22 with L recomputed per σ at T = 0.5: at σ = 0.01; the uncensored probability Φ(T/σ) at σ = 10",
            measured=f"J22(0.01) = {s_rec[0]:.3f}; Φ(0.5/10) = {float(ndtr(0.05)):.4f}",
            test="J22(0.01) < -9 (ten times the open-loop rate) and |Φ(T/σ) - 0.5| <= 0.05 at σ = 10",
            tolerance="0.05 on the probability (deterministic)",
            holds=bool(s_rec[0] < -9 and abs(float(ndtr(0.05)) - 0.5) <= 0.05),
        ),
        CL.claim(
            "Figs 5.1-5.3: the TKF error lies between the LQG and the open-loop error responses",
            quantity="noise-free mean-field error |e_k|, k = 0..100, against |(A - LC)^k e0| and |A^k e0| "
            "(scenarios of Figs 5.2, 5.3)",
            measured=f"inside the bounds in both scenarios: {between}",
            test="|(A - LC)^k e0| - 1e-12 <= |e_k| <= |A^k e0| + 1e-12 at every k",
            tolerance="1e-12 (rounding)",
            holds=between,
        ),
    ]
    settings = {
        "A": setting(-0.8),
        "C": setting(1.0),
        "sigma": setting(sig, note="a standard deviation (MB-12)"),
        "sigma_q": setting(0.1, note="std: Q = 0.01"),
        "gain": setting("CT Kalman-Bucy", "reconstructed", "only the CT gain reproduces L = 0.0246 (MB-08)"),
        "T_grid": setting([-2.0, 2.0, 161], "default"),
        "sigma_grid": setting([0.01, 10.0, 61], "default"),
        "fig5_1_3": setting(
            {"A": A_d, "L": L_d, "sigma": sd, "T": 0.0}, "default", "no parameters in the text (MB-21)"
        ),
    }
    metrics = {
        "gains": {
            "L_uncensored": {"computed": L, "printed": 0.0246},
            "eig_J_uncensored": {"computed": [-0.8, -0.8 - L], "printed": [-0.8, -0.8246]},
        },
        "j22_correct_naive_L": {str(t): j22(0.0246, t) for t in tab_T},
        "j22_printed_5_56": dict(zip(("-0.25", "0", "0.25", "0.5"), printed_tab)),
        "recomputed_L": {str(t): {"L": v[0], "J22": v[1]} for t, v in tab_rec.items()},
        "sigma_sweep_recomputed": {str(sg): j22(l_rec(0.5, sg), 0.5, sg) for sg in (0.01, 0.1, 0.5, 1.0, 10.0)},
        "estimators": {},
    }
    progress(1.0)
    data = {
        "T": T,
        "j22_naive": j_naive,
        "j22_printed": j_print,
        "j22_recomputed": j_rec,
        "sigma": sigmas,
        "s_naive": s_naive,
        "s_printed": s_print,
        "s_recomputed": s_rec,
        "L_naive": L,
        "half_censored": -0.8 - L * 0.5,
        **scen,
    }
    return ExperimentResult("miller-jacobian-scalar", settings, metrics, data, claims)


# ======================================================================================
# miller-dc-motor-speed / -position (estimation, Ch. 5)
# ======================================================================================
_EST_LABELS = {
    "kf-lqg-observer": "naive LQG estimator (censored readings as data)",
    "tkf-fixed-uncensored-gain": "TKF estimator (5.9), original uncensored LQG gain",
    "tkf-fixed-tobit-gain": "TKF estimator (5.9), Tobit gain",
    "tkf": "time-varying TKF (not in the source)",
}
_SHORT = {
    "kf-lqg-observer": "naive LQG",
    "tkf-fixed-uncensored-gain": "TKF + LQG gain",
    "tkf-fixed-tobit-gain": "TKF + Tobit gain",
    "tkf": "time-varying TKF",
}
_EST_COLORS = {
    "kf-lqg-observer": "tab:purple",
    "tkf-fixed-uncensored-gain": "tab:red",
    "tkf-fixed-tobit-gain": "tab:blue",
    "tkf": "tab:green",
}


def _estimation_runs(
    plant: LinearSystem, sigma: float, T: float, steps: int, runs: int, seed, xi: float, xhat0=None
) -> tuple[Any, dict[str, Any], dict[str, Any]]:
    """Open-loop plant, right censoring at T; the estimators of Figs 5.10-5.18 on the same data."""
    cens = Censoring(upper=T)
    sim = simulate(plant, steps, runs, censoring=cens, seed=seed)
    A, Cm = plant.transition(0), plant.measurement(1)
    Qd = plant.process_cov(0)
    g_unc = dlqe(A, None, Cm, Qd, plant.measurement_cov(1))
    g_tob = tobit_dlqe(A, None, Cm, Qd, V=[[sigma**2]], xi_uncensored=xi)
    x0 = np.zeros(plant.n) if xhat0 is None else np.asarray(xhat0, dtype=float)
    filt = LinearSystem(A=A, C=Cm, Q=Qd, R=plant.measurement_cov(1), x0=x0, P0=g_unc.prior_cov)
    est = {
        "kf-lqg-observer": fixed_gain_tobit_observer(
            A, g_unc.filter_gain, Cm, sim.y, sigma, -np.inf, T, xhat0=x0, gain_form="linear", form="filter"
        ),
        "tkf-fixed-uncensored-gain": fixed_gain_tobit_observer(
            A, g_unc.filter_gain, Cm, sim.y, sigma, -np.inf, T, xhat0=x0, form="filter"
        ),
        "tkf-fixed-tobit-gain": fixed_gain_tobit_observer(
            A, g_tob.filter_gain, Cm, sim.y, sigma, -np.inf, T, xhat0=x0, form="filter"
        ),
        **{k: e.filter(sim.y).mean for k, e in lineup(ESTIMATION_LINEUP, filt, {"censoring": cens}).items()},
    }
    gains = {
        "dt_uncensored_filter_gain": g_unc.filter_gain[:, 0].tolist(),
        "dt_tobit_filter_gain": g_tob.filter_gain[:, 0].tolist(),
    }
    return sim, est, gains


def _plot_estimation(result: ExperimentResult, outdir: Path, prefix: str, comp: int, label: str) -> list[Path]:
    paths = []
    for name, d in result.data.items():
        fig, ax = new_figure(1, 2, width=11, height=3.4)
        t = np.arange(1, d["truth"].shape[0] + 1) * DT
        censored = np.isfinite(d["T"])
        ax[0, 0].plot(
            t,
            d["y"],
            ".",
            ms=1.5,
            color="0.6",
            label="measurements, right-censored at T" if censored else "measurements (no censoring)",
        )
        ax[0, 0].plot(t, d["truth"], color="k", lw=1.0, label="truth")
        for key, est in d["est"].items():
            ax[0, 0].plot(t, est, color=_EST_COLORS[key], lw=0.9, label=_EST_LABELS[key])
        if censored:
            ax[0, 0].axhline(d["T"], color="r", lw=0.6, ls=":", label="censoring limit T")
        ax[0, 0].set_xlabel("t [s]")
        ax[0, 0].set_ylabel(label)
        ax[0, 0].set_title(f"{d['title']} (one run)", fontsize=9)
        ax[0, 0].legend(fontsize=6)
        for key, r in d["rmse"].items():
            ax[0, 1].plot(t, r, color=_EST_COLORS[key], lw=0.9, label=_EST_LABELS[key])
        ax[0, 1].set_yscale("log")
        ax[0, 1].set_xlabel("t [s]")
        ax[0, 1].set_title(f"RMSE of {label} over {result.metrics['runs']} runs (not in the source)", fontsize=9)
        paths.append(
            save(
                fig,
                outdir,
                f"{prefix}_{name}.png",
                caption=f"{d['title']}: left, one run of the open-loop plant driven by process noise, the "
                f"{'censored ' if censored else ''}measurements and the estimates of {label} "
                "(the dissertation's red and blue curves are the TKF estimator (5.9) with the "
                "original LQG gain and with the Tobit gain); right, the per-step RMSE over "
                f"{result.metrics['runs']} runs.",
            )
        )
    return paths


def _censored_means(est: dict[str, np.ndarray], truth: np.ndarray, cmask: np.ndarray) -> dict[str, tuple[float, float]]:
    """Per-run mean of each estimate (and the truth) over the censored samples, then mean and s.e. over runs."""
    rows = [r for r in range(cmask.shape[0]) if cmask[r].any()]
    out = {}
    for key, v in {**est, "truth": truth}.items():
        vals = np.array([v[r][cmask[r]].mean() for r in rows])
        m, se = CL.mean_se(vals)
        out[key] = (float(m), float(se))
    return out


def _estimation_experiment(
    exp_id: str, model, printed: dict[str, Any], scenarios: list[tuple], *, runs, seed, steps, progress
) -> tuple[dict, dict, dict, dict]:
    plant, p = _motor_plant(model)
    sigma = SIGMA
    gains: dict[str, Any] = {}
    g = lqe(p.A, p.G, p.C, p.W, p.V)
    gains["uncensored"] = {
        "L": g.gain[:, 0].tolist(),
        "L_printed": printed["uncensored"]["L"],
        "eig_A_minus_LC": _c(g.poles),
        "eig_printed": printed["uncensored"]["eig"],
        "eig_A": _c(np.linalg.eigvals(p.A)),
    }
    for key, T in printed["tobit_T"].items():
        xi = float(ndtr(T / sigma))
        t = tobit_lqe(p.A, p.G, p.C, p.W, V=[[sigma**2]], xi_uncensored=xi)
        gains[key] = {
            "T": T,
            "xi_uncensored": xi,
            "upsilon": float(t.noise[0, 0]),
            "L": t.gain[:, 0].tolist(),
            "L_printed": printed[key]["L"],
            "eig_A_minus_LC (as printed)": _c(np.linalg.eigvals(p.A - t.gain @ p.C)),
            "eig_printed": printed[key]["eig"],
            "eig_A_minus_L_Xi_C (effective)": _c(t.poles),
        }
    scen, data, raw = {}, {}, {}
    for i, (name, T, xhat0, title) in enumerate(scenarios):
        xi = float(ndtr(T / sigma)) if np.isfinite(T) else 1.0 - 1e-12
        xi = min(max(xi, 1e-9), 1 - 1e-9)
        sim, est, dg = _estimation_runs(plant, sigma, T, steps, runs, np.random.SeedSequence([seed, i]), xi, xhat0)
        summ = {k: mx.summarize(sim.x, v) for k, v in est.items()}
        cmask = sim.y_latent[..., 0] >= T
        in_cens = _censored_means({k: v[..., 0] for k, v in est.items()}, sim.x[:, 1:, 0], cmask) if cmask.any() else {}
        cfrac_runs = cmask.mean(axis=1)
        scen[name] = {
            "T": T,
            "xhat0": None if xhat0 is None else list(xhat0),
            "estimators": summ,
            "lineup": describe(ESTIMATION_LINEUP),
            "censored_fraction": float(np.mean(cmask)),
            "censored_fraction_se": float(CL.mean_se(cfrac_runs)[1]),
            "mean_on_censored_samples": {k: v[0] for k, v in in_cens.items()},
            "mean_on_censored_samples_se": {k: v[1] for k, v in in_cens.items()},
            "stationary_std_x1": float(np.std(sim.x[:, -1, 0])),
            **dg,
        }
        raw[name] = {k: v - sim.x[:, 1:] for k, v in est.items()}
        data[name] = {
            "truth": sim.x[0, 1:, 0],
            "y": sim.y[0, :, 0],
            "T": T,
            "title": title,
            "est": {k: v[0, :, 0] for k, v in est.items()},
            "rmse": {k: s["rmse"][:, 0] for k, s in summ.items()},
        }
        progress((i + 1) / len(scenarios))
    return gains, scen, raw, data


def _better(text: str, err: dict[str, np.ndarray], better: str, worse: str, runs: int, what: str) -> dict[str, Any]:
    """Claimed: estimator ``better`` has a lower time-averaged RMSE of x1 than ``worse`` (paired jackknife)."""
    d, se = CL.rmse_difference(err[better][..., :1], err[worse][..., :1])
    tol = CL.K_SE * float(se[0])
    a, b = CL.rmse_time_avg(err[better][..., :1])[0][0], CL.rmse_time_avg(err[worse][..., :1])[0][0]
    return CL.less(
        text,
        quantity=f"time-averaged RMSE of {what}: {_EST_LABELS[better]} vs {_EST_LABELS[worse]}",
        a=float(a),
        b=float(b),
        names=(_SHORT[better], _SHORT[worse]),
        tol=tol,
        tolerance=f"{CL.K_SE:g} jackknife standard errors of the paired difference over {runs} runs = {CL.fmt(tol, 3)}",
    )


_SPEED_PRINTED: dict[str, dict[str, Any]] = {
    "uncensored": {"L": ["10.0329", "0.2257"], "eig": [-10.631, -1.48264e7]},
    "tobit_T": {"tobit_T0": 0.0},
    "tobit_T0": {"L": ["16.452", ".305"], "eig": None},
}


def _plot_speed(result: ExperimentResult, outdir: Path) -> list[Path]:
    return _plot_estimation(result, outdir, "fig5_10-5_14_speed", 0, "theta-dot [rad/s]")


@register(
    "miller-dc-motor-speed",
    title="DC-motor speed: LQG vs Tobit gains and observers (Figs 5.10-5.14)",
    source=_SOURCE,
    plot=_plot_speed,
    default_runs=100,
)
def dc_motor_speed_exp(*, runs: int = 100, seed: int = 0, progress=None, steps: int = 1000) -> ExperimentResult:
    """§5.4.1: printed gains reproduced; open-loop plant driven by process noise, right censoring.

    Scenarios: no censoring (Fig 5.10), T = 0 (Figs 5.11–5.13; T not stated, the text implies 0) with
    the naive LQG estimator, the TKF estimator (5.9) with the uncensored gain, with the Tobit gain
    (Ξ = 0.5) and the time-varying TKF; T = −0.25 with x̂_0 = [0, 0.5] (Fig 5.14, docs/sources MB-42).
    """
    progress = progress or _noop
    scenarios = [
        ("no-censoring", np.inf, None, "Fig 5.10: no censoring"),
        ("T0", 0.0, None, "Figs 5.11-5.13: T = 0"),
        ("T-0.25", -0.25, [0.0, 0.5], "Fig 5.14: T = -0.25, xhat0 = [0, .5]"),
    ]
    gains, scen, err, data = _estimation_experiment(
        "miller-dc-motor-speed",
        dc_motor_speed,
        _SPEED_PRINTED,
        scenarios,
        runs=runs,
        seed=seed,
        steps=steps,
        progress=progress,
    )
    mc, mse = scen["T0"]["mean_on_censored_samples"], scen["T0"]["mean_on_censored_samples_se"]
    gu, gt = gains["uncensored"], gains["tobit_T0"]
    tol_b = CL.K_SE * max(mse["kf-lqg-observer"], mse["tkf-fixed-tobit-gain"], mse["tkf"])
    claims = [
        CL.matches_print(
            "(5.61): the uncensored LQG estimator gain L = [10.0329, 0.2257]",
            quantity="CT Kalman–Bucy gain (k = 9.73E-3, G = [0; 1/l], MB-09 to MB-11)",
            value=gu["L"],
            printed=_SPEED_PRINTED["uncensored"]["L"],
        ),
        CL.matches_print(
            "§5.4.1: the Tobit gain at T = 0 (Ξ = 0.5) is L = [16.452, .305]",
            quantity=f"CT Kalman–Bucy gain of the modified ARE (υ = {gt['upsilon']:.4e})",
            value=gt["L"],
            printed=_SPEED_PRINTED["tobit_T0"]["L"],
        ),
        CL.claim(
            "Fig 5.11: the naive LQG estimator weights censored readings like uncensored ones, biasing its "
            "estimate toward the censoring limit",
            quantity="mean estimate of theta-dot on the censored samples (T = 0; per run, then over runs)",
            measured=f"truth {mc['truth']:.3f}, naive LQG {mc['kf-lqg-observer']:.3f}, TKF (5.9) Tobit gain "
            f"{mc['tkf-fixed-tobit-gain']:.3f}, time-varying TKF {mc['tkf']:.3f}",
            test="naive LQG < min(TKF estimators) - tol (closer to the limit T = 0 from above)",
            tolerance=f"{CL.K_SE:g} standard errors over {runs} runs = {CL.fmt(tol_b, 3)}",
            holds=mc["kf-lqg-observer"] < min(mc["tkf-fixed-tobit-gain"], mc["tkf"]) - tol_b,
        ),
        _better(
            "Fig 5.12: the TKF estimator (5.9) with the original gain is more accurate than the naive LQG estimator",
            err["T0"],
            "tkf-fixed-uncensored-gain",
            "kf-lqg-observer",
            runs,
            "theta-dot at T = 0",
        ),
        _better(
            "Fig 5.13: the updated Tobit gain does better than the original uncensored gain",
            err["T0"],
            "tkf-fixed-tobit-gain",
            "tkf-fixed-uncensored-gain",
            runs,
            "theta-dot at T = 0",
        ),
    ]
    heavy = scen["T-0.25"]
    claims.append(
        CL.at_least(
            "Fig 5.14: with T lowered (T = -0.25) nearly all measurements are censored and the estimator runs open "
            "loop (γ -> 0)",
            quantity="fraction of censored readings at T = -0.25",
            value=heavy["censored_fraction"],
            bound=0.99,
            tol=CL.K_SE * heavy["censored_fraction_se"],
            tolerance=f"'nearly all' read as >= 99 %, less {CL.K_SE:g} standard errors "
            f"({CL.fmt(CL.K_SE * heavy['censored_fraction_se'], 2)})",
            explanation=f"with the process noise of (5.60) (σ_q = 0.01 into the current) theta-dot wanders with std "
            f"{heavy['stationary_std_x1']:.2f}, so T = -0.25 is only about half a std below 0; 'all "
            "censored' holds only near the equilibrium (Ξ = 2.9e-7 there). The x̂0 = [0, .5] current error "
            "dies in one step (pole -1.5e7)",
        )
    )
    settings = {
        **_LQR_SETTINGS,
        "steps": setting(steps, "default", "horizon not given (MB-21)"),
        "T_fig5_11_13": setting(
            0.0, "reconstructed", "implied by 'T = 0 as in the previous example', not stated for the figures"
        ),
        "T_fig5_14": setting(-0.25, "source"),
        "xhat0_fig5_14": setting([0.0, 0.5], "reconstructed", "MB-42"),
        "observer_gains": setting(
            "DT filter gains (dlqe / tobit_dlqe)",
            "default",
            "the printed CT gains are reported in metrics.gains (MB-08)",
        ),
    }
    metrics = {"runs": runs, "gains": gains, "scenarios": scen, "estimators": scen["T0"]["estimators"]}
    return ExperimentResult("miller-dc-motor-speed", settings, metrics, data, claims)


_POS_PRINTED: dict[str, dict[str, Any]] = {
    "uncensored": {
        "L": ["4.0480", "8.1931", "-0.0187"],
        "eig": [-14826388.3725128, [-2.32303105520711, 2.28421305934995], [-2.32303105520711, -2.28421305934995]],
    },
    "tobit_T": {"tobit_T0": 0.0, "tobit_T-10deg": -0.174533, "tobit_T-20deg": -0.349066},
    "tobit_T0": {
        "L": ["7.281", "13.253", "-0.0302"],
        "eig": [-14826388.37, [-3.9395245780726, 1.4449381590563], [-3.9395245780726, -1.4449381590563]],
    },
    "tobit_T-10deg": {"L": ["73.1575", "0.6447", "-0.0015"], "eig": [-14826388.37, -73.1486, -0.6070]},
    "tobit_T-20deg": {"L": ["17.7467", "2.3025E-10", "-5.2485E-13"], "eig": [-14826388.37, -17.7467, -0.59807]},
}


def _plot_position(result: ExperimentResult, outdir: Path) -> list[Path]:
    return _plot_estimation(result, outdir, "fig5_15-5_18_position", 0, "theta [rad]")


@register(
    "miller-dc-motor-position",
    title="DC-motor position: Tobit gains and observers (Figs 5.15-5.18)",
    source=_SOURCE,
    plot=_plot_position,
    default_runs=100,
    cost=34,
)
def dc_motor_position_exp(*, runs: int = 100, seed: int = 0, progress=None, steps: int = 1000) -> ExperimentResult:
    """§5.4.2: gains (5.67) and the Tobit gains at T = 0, −10°, −20° next to the printed values; the
    estimators of Figs 5.15–5.18 on the marginally stable plant (open loop, process noise only).

    Fig 5.18 (T = −20°) is drawn with the Tobit gain the modified ARE gives (the printed one is not
    reproduced, docs/sources MB-14).
    """
    from ..control.stability import certify_tkf_stability

    progress = progress or _noop
    plant, pm = _motor_plant(dc_motor_position)
    A, Cm = plant.transition(0), plant.measurement(1)
    scenarios = [
        ("no-censoring", np.inf, None, "Fig 5.15: no censoring"),
        ("T0", 0.0, None, "Fig 5.16: T = 0"),
        ("T-10deg", -0.174533, None, "Fig 5.17: T = -10 deg"),
        ("T-20deg", -0.349066, None, "Fig 5.18: T = -20 deg"),
    ]
    gains, scen, err, data = _estimation_experiment(
        "miller-dc-motor-position",
        dc_motor_position,
        _POS_PRINTED,
        scenarios,
        runs=runs,
        seed=seed,
        steps=steps,
        progress=progress,
    )
    claims = []
    for key in ("uncensored", "tobit_T0", "tobit_T-10deg"):
        gk = gains[key]
        what = (
            "(5.67): the uncensored LQG estimator gain"
            if key == "uncensored"
            else f"§5.4.2: the Tobit gain at T = {'0' if key == 'tobit_T0' else '-10 deg'}"
        )
        claims.append(
            CL.matches_print(
                f"{what} L = [{', '.join(_POS_PRINTED[key]['L'])}]",
                quantity="CT Kalman–Bucy gain (modified ARE for the Tobit gains), Newton–Kleinman refined",
                value=gk["L"],
                printed=_POS_PRINTED[key]["L"],
            )
        )
    ev = gains["tobit_T-10deg"]["eig_A_minus_LC (as printed)"]
    slow = sorted([e for e in ev if isinstance(e, float) and e > -1e6])
    claims.append(
        CL.matches_print(
            "§5.4.2: at T = -10 deg the eigenvalues of (A - LC) are -73.1486 and -0.6070 (and -14826388.37)",
            quantity="the two slow eigenvalues of A - LC with the computed Tobit gain (as printed: without Ξ, MB-15)",
            value=slow,
            printed=["-73.1486", "-0.6070"],
        )
    )
    g20 = gains["tobit_T-20deg"]
    claims.append(
        CL.matches_print(
            "§5.4.2: at T = -20 deg the Tobit gain is L = [17.7467, 2.3025E-10, -5.2485E-13]",
            quantity=f"CT Kalman–Bucy gain of the modified ARE (Ξ = {g20['xi_uncensored']:.3e})",
            value=g20["L"],
            printed=_POS_PRINTED["tobit_T-20deg"]["L"],
            explanation="the printed values come back (to 3e-5) only with R = σ² instead of υ, which the T = 0 and "
            "-10 deg gains rule out; a 50-digit solution agrees with ours (docs/sources MB-14)",
        )
    )
    eigA = np.sort(np.linalg.eigvals(pm.A).real)[-2:]
    dist = {}
    for k in ("tobit_T0", "tobit_T-10deg", "tobit_T-20deg"):
        eff = np.array(
            [complex(*e) if isinstance(e, list) else complex(e) for e in gains[k]["eig_A_minus_L_Xi_C (effective)"]]
        )
        eff = eff[eff.real > -1e6]
        dist[k] = float(max(min(abs(e - a) for e in eff) for a in eigA))
    d0, d10, d20 = dist["tobit_T0"], dist["tobit_T-10deg"], dist["tobit_T-20deg"]
    claims.append(
        CL.claim(
            "§5.4.2 (Fig 5.18): as T is lowered the estimator eigenvalues approach those of A: the estimator converges "
            "to the open-loop one",
            quantity="largest distance from eig(A)'s slow poles {0, -0.598} to the nearest effective pole of A - LΞC, at "
            "T = 0, -10, -20 deg",
            measured=f"{d0:.4f}, {d10:.4f}, {d20:.4f}",
            test="the distance decreases as T is lowered",
            tolerance="exact (deterministic eigenvalues)",
            holds=d0 > d10 > d20,
            note="the printed eig(A - LC) use the Tobit gain without Ξ (MB-15); the effective poles are those of A - LΞC",
        )
    )
    cert = {}
    for name in ("T0", "T-10deg"):
        Kf = np.array(scen[name]["dt_tobit_filter_gain"])[:, None]
        c = certify_tkf_stability(A, A @ Kf, Cm, domain="dt")
        cert[name] = {
            "certified": c.certified,
            "vertex_spectral_radius": c.vertex_radius.tolist(),
            "message": c.message,
        }
    gains["dt_fixed_gain_certificates"] = cert
    claims.append(
        _better(
            "Fig 5.16 (T = 0): the TKF gain does better than the original uncensored LQG gain",
            err["T0"],
            "tkf-fixed-tobit-gain",
            "tkf-fixed-uncensored-gain",
            runs,
            "theta at T = 0",
        )
    )
    c17 = _better(
        "Fig 5.17 (T = -10 deg): the updated gain recovers and tracks the position, the original LQG gain "
        "performs poorer",
        err["T-10deg"],
        "tkf-fixed-tobit-gain",
        "tkf-fixed-uncensored-gain",
        runs,
        "theta at T = -10 deg",
    )
    c17["explanation"] = (
        f"the fixed DT Tobit gain designed at Ξ = 2.4e-4 is "
        f"{'certified' if cert['T-10deg']['certified'] else 'not certified'} (vertex spectral radii "
        f"{np.round(cert['T-10deg']['vertex_spectral_radius'], 3).tolist()}): once theta drifts "
        "below T and readings are uncensored (γ -> 1) the high gain overshoots; the time-varying "
        "TKF adapts its gain"
    )
    claims.append(c17)
    c20 = scen["T-20deg"]
    claims.append(
        CL.at_least(
            "§5.4.2 (Fig 5.18): at T = -20 deg all measurements become censored",
            quantity="fraction of censored readings at T = -20 deg",
            value=c20["censored_fraction"],
            bound=0.99,
            tol=CL.K_SE * c20["censored_fraction_se"],
            tolerance=f"'all' read as >= 99 %, less {CL.K_SE:g} standard errors ({CL.fmt(CL.K_SE * c20['censored_fraction_se'], 2)})",
            explanation="the position of the marginally stable plant wanders from 0 (a random walk driven by the "
            f"process noise: std {c20['stationary_std_x1']:.2f} rad at the end), so readings are uncensored "
            "whenever it drifts below T",
        )
    )
    settings = {
        **_LQR_SETTINGS,
        "steps": setting(steps, "default", "horizon not given (MB-21)"),
        "fig5_18_gain": setting(
            "modified-ARE Tobit gain", "reconstructed", "the printed T = -20 deg gain is not reproduced (MB-14)"
        ),
    }
    metrics = {
        "runs": runs,
        "gains": gains,
        "scenarios": scen,
        "estimators": scen["T0"]["estimators"],
        "report_tables": [_gain_table(gains)],
    }
    return ExperimentResult("miller-dc-motor-position", settings, metrics, data, claims)


def _gain_table(gains: dict[str, Any]):
    from . import report_table

    rows = []
    for key, label in (
        ("uncensored", "uncensored (5.67)"),
        ("tobit_T0", "Tobit, T = 0"),
        ("tobit_T-10deg", "Tobit, T = -10 deg"),
        ("tobit_T-20deg", "Tobit, T = -20 deg"),
    ):
        g = gains[key]
        for j in range(3):
            rows.append([f"{label}: L{j + 1}", g["L_printed"][j], f"{g['L'][j]:.7g}"])
    return report_table(
        "§5.4.2: printed estimator gains and ours (CT, Newton–Kleinman refined)",
        ["gain entry", "printed", "computed"],
        rows,
        note="Every entry but the T = -20 deg ones rounds to its printed digits (docs/sources MB-14).",
    )


# ======================================================================================
# miller-closed-loop (§6.2, Figs 6.1-6.5)
# ======================================================================================
