"""Miller (2015), Chapter 3: the Tobit Kalman filter examples (§3.3.6, §3.4; Figs 3.1–3.5).

* ``miller-constant``: Example 1 (§3.3.6.2, Figs 3.1–3.2), a constant below / above the limit.
* ``miller-brownian``: Example 2 (§3.3.6.3, Fig 3.3), a censored random walk.
* ``miller-oscillator``: Example 3 (§3.3.6.4, Fig 3.4), a censored oscillator.
* ``miller-steady-state``: §3.4.2–3.4.3 (Fig 3.5), the controlled censoring limit and the
  steady-state TKF.

The dissertation reports no numbers for these examples, only figures and what they show.
Parameters it does not state are labelled ``"default"`` in ``metrics.json``
(docs/sources/miller2015-ch1-4.md, MA-12 to MA-16); the analytic limits of the biased filters
(the standard KF converges to E[y], the intermittent-measurements KF to E[y | y > T]) are checked
as claims. Estimator keys: ``kf`` (the standard Kalman filter, censored values as data), ``ikf``
(the intermittent-measurements Kalman filter of [16], censored readings dropped), ``tkf`` (the
Tobit Kalman filter), ``sstkf`` (the steady-state TKF of §3.4.2).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .. import metrics as mx
from .._validation import ValidationError
from ..censored import censored_moments
from ..channels.censoring import Censoring
from ..design.pcrlb import posterior_crlb
from ..filters.registry import Lineup, describe, lineup, make
from ..models.linear import LinearSystem
from ..plotting import new_figure, plot_rmse_over_time, save, style
from ..simulate.core import simulate
from . import ExperimentResult, register, setting
from . import _claims as CL
from ._optimum import add_optimum, check_particles

__all__ = ["constant", "brownian", "oscillator", "steady_state"]

_SOURCE = "Miller 2015: Estimation and Control with Censored Data (dissertation)"


def _noop(_: float) -> None:
    pass


THREE: Lineup = {
    "kf": ("KalmanFilter", {}),
    "ikf": ("DroppingKalmanFilter", {}),
    "tkf": ("TobitKalmanFilter", {}),
}
"""The three estimators of the Ch. 3 comparisons, key -> (registry name, options)."""


def _run_three(sys_f: LinearSystem, cens: Censoring, y: np.ndarray):
    """The three estimators of the Ch. 3 comparisons (:data:`THREE`) on the same data."""
    return {key: est.filter(y) for key, est in lineup(THREE, sys_f, {"censoring": cens}).items()}


def _summaries(truth: np.ndarray, outs: dict[str, Any]) -> dict[str, Any]:
    return {key: mx.summarize(truth, o.mean, o.cov) for key, o in outs.items()}


# --------------------------------------------------------------------------------------
# Example 1: constant value
# --------------------------------------------------------------------------------------
_WORDS = {"kf": "standard KF", "ikf": "intermittent-measurements KF", "tkf": "Tobit KF"}


def _plot_constant(result: ExperimentResult, outdir: Path) -> list[Path]:
    paths = []
    for fig_no, name in ((1, "truth-0.1"), (2, "truth+0.1")):
        d = result.data[name]
        fig, ax = new_figure(1, 2, width=10, height=3.4)
        k = np.arange(1, d["y"].shape[0] + 1)
        ax[0, 0].plot(k, d["y"], ".", ms=2, color="0.6", label="censored measurements")
        ax[0, 0].axhline(d["truth"], **style("truth"))
        for key in ("kf", "ikf", "tkf"):
            ax[0, 0].plot(k, d[key], **style(key))
        ax[0, 0].set_ylim(-0.25, 0.35)
        ax[0, 0].set_xlabel("k")
        ax[0, 0].set_title(f"Fig 3.{fig_no}: one run, truth {d['truth']:+.1f}, left-censored at T = 0", fontsize=9)
        ax[0, 0].legend(fontsize=7)
        for key in ("kf", "ikf", "tkf"):
            ax[0, 1].plot(k, d["mean_" + key], **style(key))
        for key, val in d["targets"].items():
            ax[0, 1].axhline(val, color=style(key)["color"], lw=0.6, ls=":")
        ax[0, 1].axhline(d["truth"], **style("truth"))
        ax[0, 1].set_title(f"mean estimate over {result.metrics['runs']} runs (dotted: analytic limits)", fontsize=9)
        ax[0, 1].set_xlabel("k")
        where = "below" if d["truth"] < 0 else "above"
        paths.append(
            save(
                fig,
                outdir,
                f"fig3_{fig_no}_constant_{name}.png",
                caption=f"Fig 3.{fig_no} (constant value {where} the censoring limit): left, one run of the "
                f"standard KF, the intermittent-measurements KF and the Tobit KF on readings "
                f"left-censored at 0 (truth {d['truth']:+.1f}); right, their mean over "
                f"{result.metrics['runs']} runs with the analytic limits E[y] (standard KF) and "
                "E[y | y > T] (intermittent-measurements KF) dotted.",
            )
        )
    return paths


def _seed_int(seed: Any) -> int:
    """The experiment seed as a non-negative int (it is combined with a scenario index)."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValidationError(f"seed: expected a non-negative integer, got {seed!r}")
    return int(seed)


@register(
    "miller-constant",
    title="TKF example 1: constant below/above the censoring limit (Figs 3.1-3.2)",
    source=_SOURCE,
    plot=_plot_constant,
    default_runs=200,
)
def constant(
    *,
    runs: int = 200,
    seed: int = 0,
    progress=None,
    steps: int = 1000,
    sigma: float = 0.1,
    limit: float = 0.0,
    q: float = 1e-14,
    x0: float = 0.1,
    p0: float = 0.05,
    optimum_particles: int = 250,
    optimum_runs: int = 50,
) -> ExperimentResult:
    """Example 1 (Miller §3.3.6.2): a scalar constant, truth -0.1 and +0.1, left-censored at T.

    Source values: Q = 1e-14, σ = 0.1, x0 = 0.1, Ψ0 = 0.05. Not stated (docs/sources MA-12,
    labelled "default"): T = 0 (left censoring), the horizon 1000. The truth is the constant itself
    (zero prior spread for the truth); the filters start from x0, Ψ0. The optimum (estimator ``pf``,
    not in the source): a particle filter with ``2 optimum_particles`` particles on the first
    ``optimum_runs`` runs of each scenario (0 particles: none), every estimator's ``ratio_to_optimum``.
    """
    progress = progress or _noop
    optimum_particles = check_particles(optimum_particles)
    settings = {
        "A": setting(1.0),
        "C": setting(1.0),
        "Q": setting(q),
        "sigma": setting(sigma, note="std of v; R = sigma^2"),
        "x0_filter": setting(x0),
        "P0_filter": setting(p0),
        "limit": setting(limit, "default", "left censoring at T = 0 implied, not stated (MA-12)"),
        "steps": setting(steps, "default", "horizon not stated (MA-12)"),
        "truths": setting([-0.1, 0.1]),
        "optimum": setting(
            {"particles": 2 * optimum_particles, "runs": optimum_runs},
            "default",
            "particle filter, not in the source (the Bayes-optimal RMSE)",
        ),
    }
    cens = Censoring(lower=limit)
    sys_f = LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[q]], R=[[sigma**2]], x0=[x0], P0=[[p0]])
    scen: dict[str, dict[str, Any]] = {}
    data: dict[str, Any] = {}
    claims: list[dict[str, Any]] = []
    for i, truth in enumerate((-0.1, 0.1)):
        name = f"truth{truth:+.1f}"
        sys_t = LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[q]], R=[[sigma**2]], x0=[truth], P0=[[0.0]])
        sim = simulate(sys_t, steps, runs, censoring=cens, seed=np.random.SeedSequence([_seed_int(seed), i]))
        outs = _run_three(sys_f, cens, sim.y)
        st = censored_moments(truth, sigma, limit, np.inf)
        targets = {"kf": float(st.censored_mean), "ikf": float(st.truncated_mean), "tkf": truth}
        final = {k: o.mean[:, -1, 0] for k, o in outs.items()}
        summ = _summaries(sim.x, outs)
        used = describe(THREE)
        add_optimum(
            summ,
            {k: o.mean for k, o in outs.items()},
            sys_f,
            cens,
            sim.y,
            sim.x,
            particles=optimum_particles,
            seed=_seed_int(seed) + i,
            runs=optimum_runs,
            record=used,
        )
        scen[name] = {
            "estimators": summ,
            "lineup": used,
            "final_mean": {k: float(v.mean()) for k, v in final.items()},
            "final_std": {k: float(v.std(ddof=1)) for k, v in final.items()},
            "analytic_limit": targets,
            "censored_fraction": float((sim.y <= limit).mean()),
        }
        for key in ("kf", "ikf"):
            mean, se = CL.mean_se(final[key])
            # the prior's remaining pull after `steps` readings: (x0 - target) R/P0 / (n + R/P0), n <= steps
            n_eff = steps if key == "kf" else steps * (1 - scen[name]["censored_fraction"])
            pull = abs(x0 - targets[key]) * (sigma**2 / p0) / (n_eff + sigma**2 / p0)
            tol = CL.K_SE * float(se) + pull
            dev, off = abs(float(mean) - targets[key]), abs(float(mean) - truth)
            what = "E[y]" if key == "kf" else "E[y | y > T]"
            claims.append(
                CL.claim(
                    f"truth {truth:+.1f}: the {_WORDS[key]} is biased: its estimate stays in the uncensored region, at "
                    f"{what} (§3.3.6.2, Figs 3.1-3.2)",
                    quantity=f"mean over runs of the final {_WORDS[key]} estimate x̂_N (N = {steps})",
                    measured=f"{mean:.5f} (analytic {what} = {targets[key]:.5f}, truth {truth:+.1f})",
                    test=f"|x̂_N - {what}| <= tol and |x̂_N - truth| > tol",
                    tolerance=f"{CL.K_SE:g} standard errors ({CL.fmt(se, 2)} each, {runs} runs) + the prior's remaining "
                    f"pull {CL.fmt(pull, 2)} = {CL.fmt(tol, 3)}",
                    holds=dev <= tol and off > tol,
                )
            )
        mean, se = CL.mean_se(final["tkf"])
        resolution = 0.1 * abs(truth)
        tol = CL.K_SE * float(se) + resolution
        claims.append(
            CL.close(
                f"truth {truth:+.1f}: the Tobit KF converges to the true value (Figs 3.1-3.2)",
                quantity=f"mean over runs of the final Tobit KF estimate x̂_N (N = {steps})",
                value=float(mean),
                target=truth,
                tol=tol,
                digits=5,
                tolerance=f"{CL.K_SE:g} standard errors ({CL.fmt(se, 2)}, {runs} runs) + 10 % of |truth| "
                f"({resolution:g}: the figures are the source's only evidence, and the TKF's prior-mean "
                f"approximation leaves a slow transient, MA-19) = {CL.fmt(tol, 3)}",
            )
        )
        data[name] = {
            "truth": truth,
            "y": sim.y[0, :, 0],
            "targets": targets,
            **{k: o.mean[0, :, 0] for k, o in outs.items()},
            **{"mean_" + k: o.mean[:, :, 0].mean(axis=0) for k, o in outs.items()},
        }
        progress((i + 1) / 2)
    metrics = {"runs": runs, "scenarios": scen}
    return ExperimentResult("miller-constant", settings, metrics, data, claims)


# --------------------------------------------------------------------------------------
# Example 2: Brownian motion
# --------------------------------------------------------------------------------------
def _plot_brownian(result: ExperimentResult, outdir: Path) -> list[Path]:
    d = result.data
    k = np.arange(1, d["y"].size + 1)
    fig, ax = new_figure(2, 1, width=9, height=3.0, sharex=True)
    ax[0, 0].plot(k, d["y"], ".", ms=2, color="0.6", label="censored measurements")
    ax[0, 0].plot(k, d["truth"], **style("truth"))
    for key in ("kf", "ikf", "tkf"):
        ax[0, 0].plot(k, d[key], **style(key))
    ax[0, 0].axhline(0.0, color="k", lw=0.5)
    ax[0, 0].set_title(
        f"Fig 3.3: censored random walk (A = 0.999), left-censored at T = 0; run {d['run']} "
        f"({100 * d['run_censored']:.0f} % censored)",
        fontsize=9,
    )
    ax[0, 0].legend(fontsize=7, ncol=2)
    for key in ("kf", "ikf", "tkf"):
        ax[1, 0].plot(k, d["var_" + key], **style(key))
    ax[1, 0].set_yscale("log")
    ax[1, 0].set_ylabel("posterior variance")
    ax[1, 0].set_xlabel("k")
    ax[1, 0].legend(fontsize=7)
    return [
        save(
            fig,
            outdir,
            "fig3_3_brownian.png",
            caption=f"Fig 3.3 (Brownian motion): top, one run (run {d['run']}, the one whose censored fraction "
            f"is nearest 50 %) of the truth, the censored measurements and the three filters' "
            "estimates; bottom, their posterior variances: the intermittent-measurements KF's grows "
            "during censored stretches, the Tobit KF's much more slowly, the standard KF's not at all.",
        )
    ]


@register(
    "miller-brownian",
    title="TKF example 2: censored Brownian motion (Fig 3.3)",
    source=_SOURCE,
    plot=_plot_brownian,
    default_runs=200,
    cost=40,
)
def brownian(
    *,
    runs: int = 200,
    seed: int = 0,
    progress=None,
    steps: int = 1000,
    alpha: float = 0.999,
    q: float = 0.01,
    sigma: float = 0.05,
    limit: float = 0.0,
    x0: float = 0.05,
    p0: float = 0.05,
    optimum_particles: int = 250,
    optimum_runs: int = 50,
) -> ExperimentResult:
    """Example 2 (Miller §3.3.6.3): x_k = 0.999 x_{k-1} + η_k, Var η = 0.01, σ = 0.05, left-censored at 0.

    (3.45) writes the AR(1) on the latent measurement; it is read as the state (docs/sources MA-13).
    Horizon not stated: 1000 (the text cites samples 350-400). Truth and filter share the
    prior x0 = 0.05, Ψ0 = 0.05. The optimum (``pf``, not in the source): a particle filter with
    ``2 optimum_particles`` particles on the first ``optimum_runs`` runs (0 particles: none).
    """
    from scipy.linalg import solve_discrete_are

    progress = progress or _noop
    optimum_particles = check_particles(optimum_particles)
    settings = {
        "A": setting(alpha),
        "Q": setting(q, note="Var eta = 0.01"),
        "sigma": setting(sigma),
        "limit": setting(limit),
        "x0": setting(x0),
        "P0": setting(p0),
        "model": setting("AR(1) read as the state", "reconstructed", "(3.45) is written on y* (MA-13)"),
        "steps": setting(steps, "default", "not stated; >= 400 since samples 350-400 are cited (MA-13)"),
        "optimum": setting(
            {"particles": 2 * optimum_particles, "runs": optimum_runs},
            "default",
            "particle filter, not in the source (the Bayes-optimal RMSE)",
        ),
    }
    sys_ = LinearSystem(A=[[alpha]], C=[[1.0]], Q=[[q]], R=[[sigma**2]], x0=[x0], P0=[[p0]])
    cens = Censoring(lower=limit)
    sim = simulate(sys_, steps, runs, censoring=cens, seed=seed)
    progress(0.2)
    outs = _run_three(sys_, cens, sim.y)
    progress(0.9)
    est = _summaries(sim.x, outs)
    used = describe(THREE)
    add_optimum(
        est,
        {k: o.mean for k, o in outs.items()},
        sys_,
        cens,
        sim.y,
        sim.x,
        particles=optimum_particles,
        seed=_seed_int(seed),
        runs=optimum_runs,
        record=used,
    )
    var = {k: o.cov[..., 0, 0] for k, o in outs.items()}
    per_run_max = {k: v.max(axis=1) for k, v in var.items()}
    max_var = {k: float(np.median(v)) for k, v in per_run_max.items()}
    censored = sim.y[..., 0] <= limit
    kf_ss = float(var["kf"][0, -1])
    Pp = solve_discrete_are(np.array([[alpha]]), np.array([[1.0]]), np.array([[q]]), np.array([[sigma**2]]))
    kf_dare = float((Pp - Pp**2 / (Pp + sigma**2))[0, 0])
    err = {k: o.mean - sim.x[:, 1:] for k, o in outs.items()}
    overall = {k: float(CL.rmse_whole_run(e)[0][0]) for k, e in err.items()}
    on_cens = {k: float(o.mean[..., 0][censored].mean()) for k, o in outs.items()}

    def per_run_censored_mean(est_x):
        vals = [est_x[r][censored[r]].mean() for r in range(runs) if censored[r].any()]
        return CL.mean_se(np.array(vals))

    claims = [
        CL.close(
            "the standard KF's covariance stays at its uncensored steady state: it shows no sign of the "
            "censoring (§3.3.6.3, Fig 3.3)",
            quantity="standard KF posterior variance at k = N",
            value=kf_ss,
            target=kf_dare,
            digits=6,
            tol=1e-9 * kf_dare,
            tolerance="1e-9 relative (deterministic: the KF's covariance does not depend on "
            "the data; target: the uncensored DARE posterior, solved independently)",
        ),
    ]
    d_max, se_max = CL.mean_se(per_run_max["ikf"] - per_run_max["tkf"])
    tol, tol_text = CL.mc_tolerance(se_max, runs, "the paired difference of the per-run maxima")
    claims.append(
        CL.greater(
            "the intermittent-measurements KF's covariance diverges during censored stretches, the Tobit KF's grows "
            "much more slowly (§3.3.6.3, Fig 3.3)",
            quantity="mean over runs of the per-run maximum posterior variance",
            a=float(per_run_max["ikf"].mean()),
            b=float(per_run_max["tkf"].mean()),
            names=("IKF", "TKF"),
            tol=tol,
            tolerance=tol_text,
            note=f"medians: IKF {max_var['ikf']:.3f}, TKF {max_var['tkf']:.3f}",
        )
    )
    m_kf, se_kf = per_run_censored_mean(outs["kf"].mean[..., 0])
    m_tkf, se_tkf = per_run_censored_mean(outs["tkf"].mean[..., 0])
    tol_kf = CL.K_SE * float(se_kf) + 0.1 * sigma
    tol_tkf = CL.K_SE * float(se_tkf)
    claims.append(
        CL.claim(
            "while censored, the standard KF's estimate converges to the censoring limit, the Tobit KF's goes below it "
            "(§3.3.6.3, Fig 3.3)",
            quantity="mean estimate on the censored samples (per run, then over runs)",
            measured=f"standard KF {m_kf:.4f}, Tobit KF {m_tkf:.4f} (limit T = {limit:g}; truth "
            f"{float(sim.x[:, 1:, 0][censored].mean()):.3f})",
            test="|KF - T| <= tol_KF and TKF < T - tol_TKF",
            tolerance=f"tol_KF = {CL.K_SE:g} s.e. + σ/10 = {CL.fmt(tol_kf, 3)}; tol_TKF = {CL.K_SE:g} s.e. = "
            f"{CL.fmt(tol_tkf, 3)} ({runs} runs)",
            holds=abs(float(m_kf) - limit) <= tol_kf and float(m_tkf) < limit - tol_tkf,
        )
    )
    diff, se_diff = {}, {}
    for k in ("kf", "ikf"):
        dv, ds = CL.rmse_difference(err["tkf"], err[k], whole_run=True)
        diff[k], se_diff[k] = float(dv[0]), float(ds[0])
    tol = CL.K_SE * max(se_diff.values())
    claims.append(
        CL.claim(
            "(not in the source, which shows Fig 3.3 only) the Tobit KF has the lowest RMSE",
            quantity="whole-run RMSE (root of the mean over runs and steps of the squared error; the table below "
            "averages the per-step RMSE instead)",
            measured=", ".join(f"{_WORDS[k]} {v:.3f}" for k, v in overall.items()),
            test="RMSE(KF) - RMSE(TKF) > tol and RMSE(IKF) - RMSE(TKF) > tol",
            tolerance=f"{CL.K_SE:g} jackknife standard errors of the paired differences over {runs} runs = {CL.fmt(tol, 3)}",
            holds=min(diff.values()) > tol,
        )
    )
    metrics = {
        "runs": runs,
        "estimators": est,
        "lineup": used,
        "median_max_variance": max_var,
        "kf_steady_variance": kf_ss,
        "kf_dare_posterior_variance": kf_dare,
        "censored_fraction": float(censored.mean()),
        "rmse_whole_run": overall,
        "mean_estimate_on_censored": on_cens,
    }
    frac = censored.mean(axis=1)
    r = int(np.argmin(np.abs(frac - 0.5)))
    data = {
        "y": sim.y[r, :, 0],
        "truth": sim.x[r, 1:, 0],
        **{k: o.mean[r, :, 0] for k, o in outs.items()},
        **{"var_" + k: v[r] for k, v in var.items()},
        "run": r,
        "run_censored": float(frac[r]),
    }
    progress(1.0)
    return ExperimentResult("miller-brownian", settings, metrics, data, claims)


# --------------------------------------------------------------------------------------
# Example 3: oscillator
# --------------------------------------------------------------------------------------
def _rotation(omega: float, alpha: float = 1.0) -> np.ndarray:
    """(3.46): α [[cos ω, -sin ω], [sin ω, cos ω]]."""
    c, s = np.cos(omega), np.sin(omega)
    return alpha * np.array([[c, -s], [s, c]])


def _plot_oscillator(result: ExperimentResult, outdir: Path) -> list[Path]:
    d = result.data
    k = np.arange(1, d["y"].size + 1)
    fig, ax = new_figure(2, 1, width=9, height=3.0, sharex=True)
    ax[0, 0].plot(k, d["y"], ".", ms=1.5, color="0.6", label="censored measurements")
    for comp in (0, 1):
        ax[comp, 0].plot(k, d["truth"][:, comp], **style("truth"))
        for key in ("kf", "ikf", "tkf"):
            ax[comp, 0].plot(k, d[key][:, comp], **style(key))
        ax[comp, 0].set_ylabel(f"x{comp + 1}")
        ax[comp, 0].legend(fontsize=7, ncol=2)
    ax[0, 0].set_title(
        f"Fig 3.4: sinusoidal model, ω = {d['omega']} (default), left-censored at T = 0; one run", fontsize=9
    )
    ax[1, 0].set_xlabel("k")
    paths = [
        save(
            fig,
            outdir,
            "fig3_4_oscillator.png",
            caption=f"Fig 3.4 (sinusoidal model, ω = {d['omega']} rad/sample, our choice): one run of the truth "
            "and the three filters' estimates of the measured first state (top) and the unmeasured "
            "second state (bottom), readings left-censored at 0.",
        )
    ]
    fig, ax = new_figure(1, 2, width=10, height=3.2)
    for comp in (0, 1):
        plot_rmse_over_time(
            ax[0, comp],
            result.metrics["estimators"],
            comp,
            title=f"RMSE over {result.metrics['runs']} runs, ω = {d['omega']}",
        )
        if "pcrlb_rmse" in result.metrics:
            b = np.asarray(result.metrics["pcrlb_rmse"])[:, comp]
            ax[0, comp].plot(np.arange(1, b.size + 1), b, color="tab:green", lw=0.8, ls=":", label="PCRLB (sqrt)")
            ax[0, comp].legend(fontsize=7)
    paths.append(
        save(
            fig,
            outdir,
            "oscillator_rmse.png",
            caption=f"Not in the source: the per-step RMSE of each state over {result.metrics['runs']} "
            "runs for the standard KF, the intermittent-measurements KF and the Tobit KF, with the "
            "optimum (particle filter, where run) and the square root of the posterior Cramér-Rao bound.",
        )
    )
    return paths


@register(
    "miller-oscillator",
    title="TKF example 3: censored oscillator (Fig 3.4)",
    source=_SOURCE,
    plot=_plot_oscillator,
    default_runs=100,
)
def oscillator(
    *,
    runs: int = 100,
    seed: int = 0,
    progress=None,
    steps: int = 2000,
    omega: float = 0.05,
    omega_sweep: tuple[float, ...] = (0.01, 0.05, 0.2),
    q: float = 0.01,
    r: float = 0.1,
    limit: float = 0.0,
    p0: float = 0.05,
    optimum_particles: int = 250,
    optimum_runs: int = 50,
) -> ExperimentResult:
    """Example 3 (Miller §3.3.6.4): (3.46) with α = 1, C = [1 0], Q = 0.01 I, R = 0.1, x0 = 0, Ψ0 = 0.05 I.

    ω, T and the horizon are not stated (docs/sources MA-14): ω = 0.05 rad/sample, T = 0 (left),
    2000 steps, labelled "default". The ranking TKF < IKF < KF is also checked for the
    ω values of ``omega_sweep``. The optimum (``pf``, not in the source, for ``omega`` only): a
    particle filter with ``2 optimum_particles`` particles on the first ``optimum_runs`` runs.
    """
    progress = progress or _noop
    optimum_particles = check_particles(optimum_particles)
    settings = {
        "alpha": setting(1.0),
        "C": setting([[1.0, 0.0]]),
        "Q": setting(f"{q} I"),
        "R": setting(r),
        "x0": setting([0.0, 0.0]),
        "P0": setting(f"{p0} I"),
        "omega": setting(omega, "default", "not stated (MA-14)"),
        "omega_sweep": setting(list(omega_sweep), "default", "ω is free; the ranking is checked over a range (MA-14)"),
        "limit": setting(limit, "default", "left censoring at 0 as in Examples 1-2 (MA-14)"),
        "steps": setting(steps, "default", "not stated; >= 1400 since sample 1350 is cited (MA-14)"),
        "optimum": setting(
            {"particles": 2 * optimum_particles, "runs": optimum_runs},
            "default",
            "particle filter, not in the source (the Bayes-optimal RMSE), for omega only",
        ),
    }
    cens = Censoring(lower=limit)
    omegas = list(dict.fromkeys([omega, *omega_sweep]))
    sweep, est, data, checks = {}, None, {}, {}
    used = describe(THREE)  # at every omega; the optimum at omega only
    for i, om in enumerate(omegas):
        sys_ = LinearSystem(A=_rotation(om), C=[[1.0, 0.0]], Q=q * np.eye(2), R=[[r]], x0=[0.0, 0.0], P0=p0 * np.eye(2))
        sim = simulate(sys_, steps, runs, censoring=cens, seed=np.random.SeedSequence([_seed_int(seed), i]))
        outs = _run_three(sys_, cens, sim.y)
        summ = _summaries(sim.x, outs)
        sweep[f"omega={om}"] = {k: s["rmse_time_avg"] for k, s in summ.items()}
        err = {k: o.mean - sim.x[:, 1:] for k, o in outs.items()}
        d1, s1 = CL.rmse_difference(err["tkf"], err["ikf"])
        d2, s2 = CL.rmse_difference(err["ikf"], err["kf"])
        checks[f"omega={om}"] = (d1, s1, d2, s2)
        if om == omega:
            add_optimum(
                summ,
                {k: o.mean for k, o in outs.items()},
                sys_,
                cens,
                sim.y,
                sim.x,
                particles=optimum_particles,
                seed=_seed_int(seed) + i,
                runs=optimum_runs,
                record=used,
            )
            pcrlb = np.sqrt(posterior_crlb(sys_, cens, truth=sim.x).var)
            est = summ
            bias = (outs["ikf"].mean[..., 0] - sim.x[:, 1:, 0]).mean(axis=1)
            data = {"omega": om, "y": sim.y[0, :, 0], "truth": sim.x[0, 1:], **{k: o.mean[0] for k, o in outs.items()}}
        progress((i + 1) / len(omegas))
    claims = []
    for name, vals in sweep.items():
        d1, s1, d2, s2 = checks[name]
        tol1, tol2 = CL.K_SE * np.asarray(s1), CL.K_SE * np.asarray(s2)
        t, ik, kf = (np.asarray(vals[k]) for k in ("tkf", "ikf", "kf"))
        claims.append(
            CL.claim(
                f"{name}: the Tobit KF tracks closely while the intermittent-measurements KF is biased, and the standard "
                "KF worse (Fig 3.4 and its text): RMSE ordering TKF < IKF < KF for both states",
                quantity="time-averaged per-step RMSE of x1 and x2",
                measured=f"TKF {CL.fmt(t, 3)}, IKF {CL.fmt(ik, 3)}, KF {CL.fmt(kf, 3)}",
                test="IKF - TKF > tol1 and KF - IKF > tol2, both states",
                tolerance=f"{CL.K_SE:g} jackknife standard errors of each paired difference over {runs} runs: tol1 = "
                f"{CL.fmt(tol1, 2)}, tol2 = {CL.fmt(tol2, 2)}; margins IKF - TKF {CL.fmt(d1, 2)}, KF - IKF "
                f"{CL.fmt(d2, 2)}",
                holds=bool(np.all(d1 > tol1) and np.all(d2 > tol2)),
            )
        )
    b_mean, b_se = CL.mean_se(bias)
    tol, tol_text = CL.mc_tolerance(b_se, runs, "the time-averaged bias")
    claims.append(
        CL.greater(
            "the intermittent-measurements KF has a positive bias: it places heavy emphasis on stray "
            "uncensored data (§3.3.6.4)",
            quantity="time-averaged bias of the IKF's x1 estimate (mean over runs)",
            a=float(b_mean),
            b=0.0,
            names=("bias", "zero"),
            tol=tol,
            tolerance=tol_text,
        )
    )
    metrics = {
        "runs": runs,
        "estimators": est,
        "lineup": used,
        "rmse_time_avg_by_omega": sweep,
        "pcrlb_rmse": pcrlb,
    }
    return ExperimentResult("miller-oscillator", settings, metrics, data, claims)


# --------------------------------------------------------------------------------------
# §3.4: controlled censoring limit and the steady-state TKF
# --------------------------------------------------------------------------------------
def _plot_steady_state(result: ExperimentResult, outdir: Path) -> list[Path]:
    d = result.data
    k = np.arange(1, d["y_latent"].size + 1)
    fig, ax = new_figure(2, 1, width=9, height=3.0, sharex=True)
    ax[0, 0].plot(k, d["y_latent"], color="0.7", lw=0.8, label="latent measurement y*")
    ax[0, 0].plot(k, d["limits"], color="tab:purple", lw=0.8, label=f"controlled limit T_k (ξ = {d['xi']})")
    ax[0, 0].plot(k, d["y"], ".", ms=1.5, color="0.3", label="reported (censored) y")
    ax[0, 0].axhline(d["fixed_limit"], color="k", ls=":", lw=0.8, label=f"fixed limit T = {d['fixed_limit']}")
    ax[0, 0].set_title("Fig 3.5: changing T to keep a constant expectation of censoring (one run)", fontsize=9)
    ax[0, 0].legend(fontsize=7, ncol=2)
    ax[1, 0].plot(k, d["truth"], **style("truth"))
    ax[1, 0].plot(k, d["sstkf"], **style("sstkf"))
    ax[1, 0].plot(k, d["tkf"], **{**style("tkf"), "label": "full TKF (3.55) with the same controlled limit"}, alpha=0.7)
    ax[1, 0].set_ylabel("x1")
    ax[1, 0].set_xlabel("k")
    ax[1, 0].legend(fontsize=7)
    paths = [
        save(
            fig,
            outdir,
            "fig3_5_controlled_limit.png",
            caption=f"Fig 3.5 (changing the censoring limit T to maintain a constant expectation of censoring): "
            f"top, one run's latent measurement, the limit T_k of (3.56) for ξ = {d['xi']} "
            "(probability of an uncensored reading) and the censored readings; bottom, the truth, the "
            "steady-state TKF and the full TKF with the same moving limit.",
        )
    ]
    fig, ax = new_figure(1, 1, width=7, height=3.2)
    for key, s in result.metrics["estimators"].items():
        r = np.asarray(s["rmse"])[:, 0]
        ax[0, 0].plot(np.arange(1, r.size + 1), r, label=_SS_LABELS.get(key, key))
    ax[0, 0].set_yscale("log")
    ax[0, 0].set_xlabel("k")
    ax[0, 0].set_ylabel("RMSE of x1")
    ax[0, 0].legend(fontsize=7)
    ax[0, 0].set_title("fixed limit T = 3 vs the controlled limit (3.56)", fontsize=9)
    paths.append(
        save(
            fig,
            outdir,
            "steady_state_rmse.png",
            caption="Not in the source: per-step RMSE of x1 for the three filters at the fixed limit T = 3 "
            "and for the steady-state TKF and the full TKF under the controlled limit.",
        )
    )
    return paths


_SS_LABELS = {
    "kf": "standard KF, fixed T",
    "ikf": "intermittent-measurements KF, fixed T",
    "tkf": "Tobit KF, fixed T",
    "sstkf": "steady-state TKF, controlled T (first ξ)",
}


@register(
    "miller-steady-state",
    title="Controlled censoring limit and steady-state TKF (§3.4, Fig 3.5)",
    source=_SOURCE,
    plot=_plot_steady_state,
    default_runs=200,
)
def steady_state(
    *,
    runs: int = 200,
    seed: int = 0,
    progress=None,
    steps: int = 2000,
    omega: float = 0.05,
    q: float = 0.01,
    r: float = 0.1,
    fixed_limit: float = 3.0,
    xis: tuple[float, ...] = (0.95, 0.5),
) -> ExperimentResult:
    """§3.4.2-3.4.3: right censoring; fixed limit vs the controlled limit (3.56).

    The section gives no parameters (docs/sources MA-16): the Example-3 oscillator (ω = 0.05,
    Q = 0.01 I, R = 0.1) is right-censored, at a fixed T = 3 (full TKF, KF, IKF) and at the
    controlled limit T_k = C x̄_k + σΦ⁻¹(ξ) for ξ in ``xis`` (steady-state TKF ``sstkf`` for the
    first ξ, ``sstkf-xi-<ξ>`` for others, and the full TKF steered the same way,
    ``tkf-controlled-xi-<ξ>``). All on the same latent measurements. Reported: censored fractions
    (the realised uncensored fraction is below ξ for ξ > 0.5, MB-F2), RMSE, and the full TKF's
    covariance against the modified-DARE Ψ∞.
    """
    progress = progress or _noop
    settings = {
        "model": setting("Example-3 oscillator, right-censored", "default", "§3.4.3 gives no parameters (MA-16)"),
        "omega": setting(omega, "default"),
        "Q": setting(f"{q} I", "default"),
        "R": setting(r, "default"),
        "fixed_limit": setting(fixed_limit, "default", "the '3 V instead of 5 V' narrative of §3.4.3"),
        "xi_uncensored": setting(list(xis), "default", "ξ = 0.95 and 0.5 (MA-16)"),
        "steps": setting(steps, "default"),
    }
    sys_ = LinearSystem(
        A=_rotation(omega), C=[[1.0, 0.0]], Q=q * np.eye(2), R=[[r]], x0=[0.0, 0.0], P0=0.05 * np.eye(2)
    )
    cens = Censoring(upper=fixed_limit)
    sim = simulate(sys_, steps, runs, censoring=cens, seed=seed)
    progress(0.1)
    outs = _run_three(sys_, cens, sim.y)
    progress(0.4)
    est = _summaries(sim.x, outs)
    claims, per_xi, data, errs = [], {}, {}, {}
    plan = dict(THREE)
    for j, xi in enumerate(xis):
        key = "sstkf" if j == 0 else f"sstkf-xi-{xi}"
        plan[key] = ("SteadyStateTobitKalmanFilter", {"xi_uncensored": xi})
        # the full TKF with the steered limit, as tobit_kalman_filter_controlled builds it
        plan[f"tkf-controlled-xi-{xi}"] = (
            "ControlledLimitTobitKalmanFilter",
            {"xi_uncensored": xi, "backend": "numpy"},
        )
        ss = make(plan[key][0], sys_, **plan[key][1])
        o_ss = ss.filter_controlled(sim.y_latent)
        o_full = make(plan[f"tkf-controlled-xi-{xi}"][0], sys_, **plan[f"tkf-controlled-xi-{xi}"][1]).filter(
            sim.y_latent
        )
        assert o_ss.mean is not None and o_full.mean is not None and o_full.cov is not None, "the default outputs"
        est[key] = mx.summarize(sim.x, o_ss.mean, o_ss.cov)
        est[f"tkf-controlled-xi-{xi}"] = mx.summarize(sim.x, o_full.mean, o_full.cov)
        errs[key] = o_ss.mean - sim.x[:, 1:]
        unc_runs = (o_ss.extras["y"] < o_ss.extras["limits"]).mean(axis=(1, 2))
        unc, unc_se = CL.mean_se(unc_runs)
        cov_gap = float(np.abs(o_full.cov[:, -1] - ss.cov).max())
        pu_gap = float(np.abs(o_full.extras["p_uncensored"] - xi).max())
        per_xi[str(xi)] = {
            "upsilon": ss.upsilon,
            "lambda_hat": ss.lambda_hat,
            "gain": ss.gain,
            "dare_posterior_cov": ss.cov,
            "dare_prior_cov": ss.prior_cov,
            "realised_uncensored_fraction": float(unc),
            "realised_uncensored_fraction_se": float(unc_se),
            "full_tkf_cov_minus_dare_at_T": cov_gap,
            "full_tkf_max_abs_Ep_minus_xi": pu_gap,
        }
        claims.append(
            CL.claim(
                f"ξ = {xi}: with T_k from (3.56) E(p_k) ≡ ξ and the TKF becomes the KF of (A, ξC, υ) (3.57)",
                quantity="max over runs and steps of |E(p_k) - ξ|; max |Ψ_N - Ψ∞| against the modified DARE",
                measured=f"{CL.fmt(pu_gap, 2)}; {CL.fmt(cov_gap, 2)}",
                test="|E(p_k) - ξ| <= 1e-9 and |Ψ_N - Ψ∞| <= 1e-6",
                tolerance="rounding (1e-9) for the identity; 1e-6 for the convergence of the time-varying covariance in "
                f"{steps} steps",
                holds=pu_gap < 1e-9 and cov_gap < 1e-6,
            )
        )
        tol, tol_text = CL.mc_tolerance(unc_se, runs, "the per-run uncensored fraction")
        claims.append(
            CL.close(
                f"ξ = {xi}: the limit (3.56) keeps a constant expectation of censoring: the censored fraction is 1 - ξ = "
                f"{1 - xi:.2f} (§3.4.2, Fig 3.5)",
                quantity="realised fraction of uncensored readings (mean over runs of the per-run fraction)",
                value=float(unc),
                target=xi,
                tol=tol,
                tolerance=tol_text,
                explanation="T_k is set from the filter's prior mean x̄_k, which has error (spread and, because the "
                "TKF evaluates γ at the prior mean only, bias), so the realised fraction is not ξ: for "
                "ξ > 0.5 the spread alone gives about Φ(aσ/√(σ² + CP̄Cᵀ)), a = Φ⁻¹(ξ) (docs/sources "
                "MB-F2, MA-19)",
            )
        )
        if j == 0:
            data = {
                "xi": xi,
                "y_latent": sim.y_latent[0, :, 0],
                "limits": o_ss.extras["limits"][0, :, 0],
                "y": o_ss.extras["y"][0, :, 0],
                "truth": sim.x[0, 1:, 0],
                "sstkf": o_ss.mean[0, :, 0],
                "tkf": o_full.mean[0, :, 0],
                "fixed_limit": fixed_limit,
            }
        progress(0.4 + 0.6 * (j + 1) / len(xis))
    first = str(xis[0])
    dv, ds = CL.rmse_difference(errs["sstkf"], outs["kf"].mean - sim.x[:, 1:])
    tol = CL.K_SE * float(ds[0])
    claims.append(
        CL.greater(
            "highly accurate tracking without the full dynamic range (§3.4.3): the steady-state TKF with the controlled "
            "limit beats the standard KF at the fixed limit",
            quantity=f"time-averaged RMSE of x1: standard KF at fixed T = {fixed_limit} vs steady-state TKF (ξ = {first})",
            a=float(est["kf"]["rmse_time_avg"][0]),
            b=float(est["sstkf"]["rmse_time_avg"][0]),
            names=("KF", "SSTKF"),
            tol=tol,
            tolerance=f"{CL.K_SE:g} jackknife standard errors of the paired difference over {runs} runs = {CL.fmt(tol, 3)}",
            note=f"Tobit KF at the fixed limit: {est['tkf']['rmse_time_avg'][0]:.3f}",
        )
    )
    metrics = {
        "runs": runs,
        "estimators": est,
        "lineup": describe(plan),
        "controlled_limit": per_xi,
        "fixed_limit_censored_fraction": float((sim.y >= fixed_limit).mean()),
    }
    return ExperimentResult("miller-steady-state", settings, metrics, data, claims)
