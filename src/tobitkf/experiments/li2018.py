"""Li, Li & Wang (2018), time-delay systems with fading measurements and correlated noises, Sec. 5.

Three experiments reproduce the numerical example of the source (our deviations:
docs/sources/li2018-delay.md):

* ``li2018-tracking``: Fig. 1, true states and the filter x̂(t|t) of one run.
* ``li2018-fading``: Fig. 2, filter error variances for the pmf variants q = 1, 0.6, 0.3.
* ``li2018-tables``: Tables 1–2 style running-average MSE of filter x̂(t|t) and predictor
  x̂(t+1|t), against a labelled stand-in for the baseline of [28] (LD-12); the source's tables are
  printed next to ours in the report.

Each runs for the cross-covariance S in {0, 0.15, 0.3}. The source does not state S; 0.3 =
sqrt(Q_w Q_v) is inferred from Tables 1–2 (LD-03) and is the headline value
(``metrics["estimators"]``). Estimator keys: ``chain`` (Algorithm C, the default), ``augmented``
(Algorithm A), ``paper-j`` (the source's constant J = ΓSQ_v^{-1}), ``naive-kf`` (stand-in for
[28]: the same estimator told S = 0 and γ ≡ 1; not the method of [28], which this paper does not
specify enough to rebuild).

MSE definitions (LD-10): ``per_step`` is the ensemble mean over runs of the squared error at each
t; ``running_avg`` is (1/(t+1)) Σ_{s<=t} per_step(s) (our reading of the tables). Time index
t = 0..T-1 is the measurement time (y(0) measures x(-3)).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..filters.registry import Lineup, describe, lineup
from ..metrics import summarize
from ..models.delay import paper_example, paper_prior
from ..plotting import save
from ..simulate.delay import simulate_delay
from . import ExperimentResult, register, report_table, setting
from . import _claims as CL

_SOURCE = "Li, Li & Wang 2018: optimal linear estimators for time-delay systems with fading measurements"

S_VALUES = (0.0, 0.15, 0.3)
Q_VALUES = (1.0, 0.6, 0.3)
DEFAULT_S = 0.3
TABLE_TIMES = (25, 50, 75, 100, 125, 150)
KEYS = ("chain", "augmented", "paper-j", "naive-kf")

# An independent prototype's values (Algorithm C, prior x(-k) ~ (0, 0.01 I), not from the source):
# steady-state diag P(t|t) = P(t|t-1), diag P(t-d|t) and Q_ε for d = 3.
REFERENCE = {
    (1.0, 0.0): ((0.44353, 0.36882), (0.11801, 0.09580), 1.16914),
    (1.0, 0.15): ((0.25756, 0.23092), (0.09727, 0.08480), 0.82740),
    (1.0, 0.3): ((0.02392, 0.01280), (0.02179, 0.01159), 0.33376),
    (0.6, 0.0): ((0.57373, 0.43490), (0.25384, 0.19023), 0.86117),
    (0.6, 0.15): ((0.34009, 0.26973), (0.19367, 0.15170), 0.66981),
    (0.6, 0.3): ((0.08623, 0.06528), (0.07316, 0.05501), 0.44593),
    (0.3, 0.0): ((0.85194, 0.57367), (0.56674, 0.38009), 0.82107),
    (0.3, 0.15): ((0.55728, 0.38345), (0.41892, 0.28708), 0.72656),
    (0.3, 0.3): ((0.24812, 0.17011), (0.21677, 0.14821), 0.62389),
}

# Tables 1-2 of the source (this paper's filter and predictor; [28]'s rows), t = 25..150.
SOURCE_TABLES = {
    "filter_x1": (0.2156, 0.1196, 0.0887, 0.0868, 0.0784, 0.0750),
    "filter_x2": (0.0836, 0.0486, 0.0358, 0.0332, 0.0297, 0.0287),
    "filter_x1_[28]": (1.2208, 0.8383, 0.6919, 0.6456, 0.5965, 0.6040),
    "filter_x2_[28]": (1.0700, 0.6941, 0.5705, 0.5296, 0.4876, 0.4783),
    "predictor_x1": (0.2876, 0.1555, 0.1127, 0.1048, 0.0928, 0.0870),
    "predictor_x2": (0.1258, 0.0697, 0.0499, 0.0437, 0.0382, 0.0357),
    "predictor_x1_[28]": (1.2881, 0.8718, 0.7143, 0.6624, 0.6099, 0.6152),
    "predictor_x2_[28]": (0.8933, 0.6056, 0.5115, 0.4854, 0.4522, 0.4488),
}


def _settings(runs: int, steps: int, seed: int, S_values: tuple[float, ...], extra: dict | None = None) -> dict:
    out = {
        "A": setting([[0.4, 0.7], [0.2, 0.6]]),
        "A1": setting([[0.1, 0.2], [0.2, -0.1]]),
        "Q_zeta1": setting(0.16),
        "Gamma": setting([1, 1]),
        "H": setting([0.5, 1]),
        "Qw": setting(0.3),
        "Qv": setting(0.3),
        "d": setting(3),
        "fading_pmf": setting({"values": [0.95, 0.98, 1.0], "probs": [0.05, 0.15, 0.8]}),
        "S": setting(
            list(S_values),
            "reconstructed",
            f"not stated in the source; S = {DEFAULT_S} = sqrt(Qw Qv) inferred from Tables 1-2 (LD-03) "
            "is the headline value; 0 and 0.15 for comparison",
        ),
        "prior": setting(
            "x(-k) ~ (0, 0.01 I), k = 0..3, uncorrelated",
            "reconstructed",
            "source gives x̂(0|0) = 0, P(0|0) = 0.01 I only (LD-01)",
        ),
        "true_history": setting("drawn from the prior (Gaussian)", "default", "not stated in the source (LD-01)"),
        "noise": setting("Gaussian; w = S Qv^-1 v + eta", "default", "LD-03"),
        "steps": setting(steps, "source", "t = 0..150 (tables up to t = 150)"),
        "runs": setting(runs, "source" if runs == 150 else "default", "source: 150 Monte Carlo experiments"),
        "seed": setting(seed, "default"),
        "warmup": setting(
            "none: exact initialization from the prior (the source's ε(i) = 0, i <= 2d+1, not used)", "default", "LD-05"
        ),
    }
    out.update(extra or {})
    return out


LINEUP: Lineup = {
    "chain": ("ChainLMMSE", {}),
    "augmented": ("AugmentedLMMSE", {}),
    "paper-j": ("ChainLMMSE", {"decorrelation": "paper"}),
    "naive-kf": ("ChainLMMSE", {}),
}
"""The estimators, key -> (registry name, options); ``naive-kf`` runs on the model told S = 0 and
gamma = 1 (``system.replace(S=0.0, fading=None)``), the others on the paper's model, all with the
paper's prior (the registry's ``prior`` piece)."""
MISMODELLED = ("naive-kf",)
"""The keys built on the mis-modelled system."""


def _lineup(keys: Any) -> dict[str, Any]:
    """``metrics["lineup"]``: the registry description of ``keys`` (``key@q=...`` described as ``key``)."""
    return {k: describe({k: LINEUP[k.split("@")[0]]})[k] for k in keys}


def _estimate(S: float, q: float, data: Any, keys: tuple[str, ...]) -> dict[str, Any]:
    system = paper_example(S=S, q=q)
    prior = paper_prior()
    out = {}
    for key in keys:
        sys_k = system.replace(S=0.0, fading=None) if key in MISMODELLED else system
        out[key] = lineup({key: LINEUP[key]}, sys_k, {"prior": prior})[key].filter(data.y)
    return out


def _mse(err: np.ndarray) -> dict[str, np.ndarray]:
    per_step = np.mean(err**2, axis=0)  # (T, n)
    running = np.cumsum(per_step, axis=0) / np.arange(1, per_step.shape[0] + 1)[:, None]
    return {"per_step": per_step, "running_avg": running}


def _steady_state(q_values=Q_VALUES, S_values=S_VALUES, horizon: int = 600) -> list[dict[str, Any]]:
    rows = []
    for q in q_values:
        for S in S_values:
            chain = lineup({"chain": LINEUP["chain"]}, paper_example(S=S, q=q), {"prior": paper_prior()})["chain"]
            r = chain.filter(np.zeros((horizon, 1)))  # the covariances do not depend on the readings
            ref = REFERENCE.get((q, S))
            assert r.cov is not None, "filter() records the covariances by default"
            row = {
                "q": q,
                "S": S,
                "P_filter_diag": np.diagonal(r.cov[-1]),
                "P_measured_diag": np.diagonal(r.extras["measured_cov"][-1]),
                "Q_eps": float(r.extras["innovation_cov"][-1, 0, 0]),
            }
            if ref is not None:
                row.update(
                    {"reference_P_filter_diag": ref[0], "reference_P_measured_diag": ref[1], "reference_Q_eps": ref[2]}
                )
                row["matches_4_decimals"] = bool(
                    np.allclose(row["P_filter_diag"], ref[0], atol=5e-5, rtol=0)
                    and np.allclose(row["P_measured_diag"], ref[1], atol=5e-5, rtol=0)
                    and abs(row["Q_eps"] - ref[2]) <= 5e-5
                )
            rows.append(row)
    return rows


def _run_S(S: float, q: float, runs: int, steps: int, seed: int, keys: tuple[str, ...]):
    system = paper_example(S=S, q=q)
    data = simulate_delay(system, paper_prior(), steps, runs, seed=seed)
    est = _estimate(S, q, data, keys)
    truth_f, truth_p = data.x[:, :steps], data.x[:, 1:]
    per = {}
    for key, r in est.items():
        per[key] = {
            "filter": _mse(r.mean - truth_f),
            "predictor": _mse(r.extras["next_mean"] - truth_p),
            "filter_err2": (r.mean - truth_f) ** 2,
            "predictor_err2": (r.extras["next_mean"] - truth_p) ** 2,
            "filter_summary": summarize(truth_f, r.mean, r.cov[0] if r.cov.ndim == 4 else r.cov, skip=10),
            "P_filter_diag": np.diagonal(r.cov[0], axis1=-2, axis2=-1),
            "P_pred_diag": np.diagonal(r.extras["next_cov"][0], axis1=-2, axis2=-1),
        }
    return data, est, per


def _common_run(
    exp_id: str,
    *,
    runs: int,
    seed: int,
    progress,
    q_values: tuple[float, ...],
    S: Any,
    steps: int,
    keys: tuple[str, ...] = KEYS,
):
    S_values = S_VALUES if S is None else tuple(float(s) for s in np.atleast_1d(S))
    headline = DEFAULT_S if DEFAULT_S in S_values else S_values[-1]
    by = {}
    data_keep = {}
    jobs = [(q, s) for q in q_values for s in S_values]
    for i, (q, s) in enumerate(jobs):
        data, est, per = _run_S(s, q, runs, steps, seed, keys)
        by[(q, s)] = per
        if s == headline:
            data_keep[q] = (data, est)
        if progress is not None:
            progress((i + 1) / (len(jobs) + 1))
    return S_values, headline, by, data_keep


def _metrics_block(by, q: float, S_values) -> dict[str, Any]:
    out = {}
    for s in S_values:
        out[f"S={s:g}"] = {
            key: {
                "filter_mse": v["filter"],
                "predictor_mse": v["predictor"],
                "P_filter_diag": v["P_filter_diag"],
                "P_pred_diag": v["P_pred_diag"],
            }
            for key, v in by[(q, s)].items()
        }
    return out


def _chain_vs_augmented(data_keep) -> float:
    worst = 0.0
    for data, est in data_keep.values():
        if "augmented" in est:
            worst = max(
                worst,
                float(np.abs(est["chain"].mean - est["augmented"].mean).max()),
                float(np.abs(est["chain"].extras["next_mean"] - est["augmented"].extras["next_mean"]).max()),
            )
    return worst


def _filter_is_predictor(data_keep) -> float:
    worst = 0.0
    for data, est in data_keep.values():
        r = est["chain"]
        worst = max(worst, float(np.abs(r.mean[:, 1:] - r.extras["next_mean"][:, :-1]).max()))
    return worst


# --------------------------------------------------------------------------- li2018-tracking


def _plot_tracking(result: ExperimentResult, outdir: Path) -> list[Path]:
    import matplotlib.pyplot as plt

    d = result.data
    t = np.arange(d["x"].shape[0])
    fig, axes = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    for i, ax in enumerate(axes):
        ax.plot(t, d["x"][:, i], "k-", lw=1, label=f"x{i + 1}(t)")
        ax.plot(t, d["xhat"][:, i], "r--", lw=1, label=f"x̂{i + 1}(t|t) (chain)")
        ax.set_ylabel(f"x{i + 1}")
        ax.legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("t")
    fig.suptitle(f"Li et al. 2018 Fig. 1: tracking (S = {d['S']:g}, inferred; one run)")
    path = outdir / "fig1_tracking.png"
    save(
        fig,
        path.parent,
        path.name,
        dpi=100,
        tight=False,
        caption=f"Fig. 1 (tracking performance of the state filter): one run of the true x1, x2 and the filter "
        f"x̂(t|t) (Algorithm C) at S = {d['S']:g}, the cross-covariance inferred from Tables 1-2 (LD-03).",
    )
    return [path]


@register(
    "li2018-tracking",
    title="Delay system with fading: filter tracking (Fig. 1)",
    source=_SOURCE,
    plot=_plot_tracking,
    default_runs=150,
)
def run_tracking(*, runs: int, seed: int, progress=None, S: Any = None, steps: int = 151) -> ExperimentResult:
    """Fig. 1: true x1, x2 against x̂(t|t) for one run; ensemble MSE over ``runs`` for every S."""
    S_values, headline, by, keep = _common_run(
        "li2018-tracking", runs=runs, seed=seed, progress=progress, q_values=(1.0,), S=S, steps=steps
    )
    data, est = keep[1.0]
    per = by[(1.0, headline)]
    metrics = {
        "estimators": {k: v["filter_summary"] for k, v in per.items()},
        "lineup": _lineup(per),
        "headline_S": headline,
        "mse": _metrics_block(by, 1.0, S_values),
        "steady_state": _steady_state((1.0,), S_values),
    }
    ratio = per["chain"]["filter"]["per_step"][50:].mean(0) / per["chain"]["P_filter_diag"][50:].mean(0)
    worst = _chain_vs_augmented(keep)
    e2 = per["chain"]["filter_err2"][:, 50:]  # (N, T-50, n)
    mse_ss, mse_se = CL.mean_se(e2.mean(axis=1))
    var_x = np.diagonal(est["chain"].extras["second_moment"][-1])
    shift = _filter_is_predictor(keep)
    claims = [
        CL.at_most(
            "Fig. 1: the filter has good tracking performance",
            quantity=f"steady ensemble MSE of x̂(t|t), t >= 50, against the state's variance (S = {headline:g})",
            value=mse_ss,
            bound=0.1 * var_x,
            tol=CL.K_SE * float(np.max(mse_se)),
            tolerance=f"'good' read as an MSE below 10 % of the state variance ({CL.fmt(var_x, 3)}), plus "
            f"{CL.K_SE:g} standard errors ({CL.fmt(CL.K_SE * np.max(mse_se), 2)}, {runs} runs)",
            note=f"MSE over the filter's own P: {CL.fmt(ratio, 3)}",
        ),
        CL.at_most(
            "Theorems 1-3: the estimator is optimal (it equals the LMMSE of the augmented system)",
            quantity="max |chain - augmented| over runs, steps, filter and predictor",
            value=worst,
            bound=0.0,
            tol=1e-9,
            tolerance="1e-9 (rounding)",
        ),
        CL.greater(
            "Theorem 1: x̂(t|t) is a filter that uses the reading y(t)",
            quantity="max |x̂(t|t) - x̂(t|t-1)| over runs and steps (d = 3, uncorrelated history)",
            a=shift,
            b=0.0,
            names=("difference", "zero"),
            tol=1e-12,
            tolerance="1e-12 (rounding)",
            explanation="the printed model is a pure delay: y(t) measures x(t-d) only, so with an uncorrelated "
            "initial history x̂(t|t) equals the one-step prediction (docs/sources LD-02)",
        ),
    ]
    return ExperimentResult(
        "li2018-tracking",
        _settings(runs, steps, seed, S_values),
        metrics,
        data={"x": data.x[0, :steps], "xhat": est["chain"].mean[0], "S": headline},
        claims=claims,
    )


# --------------------------------------------------------------------------- li2018-fading


def _save_pair(fig: Any, titles: list[str], title: str, path: Path, *, legend_size: int, caption: str) -> Path:
    """Title each of the figure's panels (x1 and x2 over t) with ``titles``, label and legend them, title the
    figure ``title`` and save it as ``path`` with its ``caption``; returns ``path``."""
    for ax, sub in zip(fig.axes, titles):
        ax.set_title(sub)
        ax.set_xlabel("t")
        ax.legend(fontsize=legend_size)
    fig.suptitle(title)
    save(fig, path.parent, path.name, dpi=100, tight=False, caption=caption)
    return path


def _plot_fading(result: ExperimentResult, outdir: Path) -> list[Path]:
    import matplotlib.pyplot as plt

    d = result.data
    paths = []
    for s, curves in d["P"].items():
        fig, axes = plt.subplots(1, 2, figsize=(10, 4))
        for q, (P, mse) in curves.items():
            t = np.arange(P.shape[0])
            for i, ax in enumerate(axes):
                (line,) = ax.plot(t, P[:, i], lw=1.2, label=f"P, q = {q:g}")
                ax.plot(t, mse[:, i], ":", color=line.get_color(), lw=0.8, label=f"MC MSE, q = {q:g}")
        path = _save_pair(
            fig,
            ["(a) x1(t)", "(b) x2(t)"],
            f"Li et al. 2018 Fig. 2: filter error variance, S = {s:g}",
            outdir / f"fig2_fading_S{s:g}.png",
            legend_size=7,
            caption=f"Fig. 2 (comparison of the filter's error variances for P(γ(t) = q) = 0.8, q = 0.3, 0.6, 1) at "
            f"S = {s:g}: the filter's error variance P(t|t) of x1 (a) and x2 (b), with the Monte Carlo MSE "
            "dotted (not in the source).",
        )
        paths.append(path)
    return paths


@register(
    "li2018-fading",
    title="Delay system with fading: error variance vs fading level q (Fig. 2)",
    source=_SOURCE,
    plot=_plot_fading,
    default_runs=150,
    cost=22,
)
def run_fading(*, runs: int, seed: int, progress=None, S: Any = None, steps: int = 151) -> ExperimentResult:
    """Fig. 2: P(t|t) and Monte Carlo MSE for P(γ = q) = 0.8, q = 1, 0.6, 0.3 (docs/sources LD-11)."""
    S_values, headline, by, keep = _common_run(
        "li2018-fading",
        runs=runs,
        seed=seed,
        progress=progress,
        q_values=Q_VALUES,
        S=S,
        steps=steps,
        keys=("chain", "paper-j"),
    )
    metrics = {"estimators": {}, "headline_S": headline, "by_q": {}}
    for q in Q_VALUES:
        metrics["by_q"][f"q={q:g}"] = _metrics_block(by, q, S_values)
        for key, v in by[(q, headline)].items():
            metrics["estimators"][key if q == 1.0 else f"{key}@q={q:g}"] = v["filter_summary"]
    metrics["lineup"] = _lineup(metrics["estimators"])
    metrics["steady_state"] = _steady_state(Q_VALUES, S_values)
    ordered = {}
    for s in S_values:
        ss = [by[(q, s)]["chain"]["P_filter_diag"][-1] for q in Q_VALUES]
        ordered[s] = bool(np.all(ss[0] < ss[1]) and np.all(ss[1] < ss[2]))
    rows_ok = [r["matches_4_decimals"] for r in metrics["steady_state"]]
    claims = [
        CL.claim(
            "Fig. 2: the filter has the highest accuracy when q = 1 (the error variance grows as q falls)",
            quantity="filter error variance diag P(t|t) at t = 150 for q = 1, 0.6, 0.3, each S",
            measured="; ".join(
                f"S={s:g}: " + ", ".join(CL.fmt(by[(q, s)]["chain"]["P_filter_diag"][-1], 4) for q in Q_VALUES)
                for s in S_values
            ),
            test="P(q=1) < P(q=0.6) < P(q=0.3) for both states and every S",
            tolerance="exact (the filter's covariance is deterministic)",
            holds=all(ordered.values()),
        ),
        CL.claim(
            "(not in the source) the steady-state covariances reproduce an independent prototype's to 4 decimals",
            quantity="rows of diag P(t|t), diag P(t-d|t) and Q_ε at t = 600 matching",
            measured=f"{sum(rows_ok)}/{len(rows_ok)} rows",
            test="every row",
            tolerance="5e-5 absolute per entry (4 decimals)",
            holds=all(rows_ok),
        ),
    ]
    data = {
        "P": {
            s: {q: (by[(q, s)]["chain"]["P_filter_diag"], by[(q, s)]["chain"]["filter"]["per_step"]) for q in Q_VALUES}
            for s in S_values
        }
    }
    return ExperimentResult(
        "li2018-fading",
        _settings(
            runs,
            steps,
            seed,
            S_values,
            {"q": setting(list(Q_VALUES), "reconstructed", "pmf {0.95: .05, 0.98: .15, q: .8} (LD-11)")},
        ),
        metrics,
        data=data,
        claims=claims,
    )


# --------------------------------------------------------------------------- li2018-tables

_TABLE_LABELS = {
    "chain": "this paper's estimator (Algorithm C)",
    "augmented": "augmented LMMSE (Algorithm A)",
    "paper-j": "paper's constant J (8)",
    "naive-kf": "stand-in for [28] (S = 0, γ ≡ 1)",
}


def _plot_tables(result: ExperimentResult, outdir: Path) -> list[Path]:
    import matplotlib.pyplot as plt

    d = result.data
    paths = []
    for which, fig_no in (("filter", 3), ("predictor", 4)):
        fig, axes = plt.subplots(1, 2, figsize=(10, 4))
        for key, curves in d[which].items():
            for i, ax in enumerate(axes):
                style = {"chain": "-", "augmented": "--", "paper-j": ":", "naive-kf": "-."}.get(key, "-")
                ax.semilogy(
                    np.arange(1, curves.shape[0] + 1), curves[:, i], style, lw=1.2, label=_TABLE_LABELS.get(key, key)
                )
        path = _save_pair(
            fig,
            [f"x{i + 1}: running-average MSE" for i in range(2)],
            f"Li et al. 2018 Fig. {fig_no}: {which} (S = {d['S']:g}; naive-kf is a stand-in for [28])",
            outdir / f"fig{fig_no}_{which}_mse.png",
            legend_size=8,
            caption=f"Fig. {fig_no} (MSE of the {which} against [28]'s): the running-average MSE of x1 and x2 over t "
            f"at S = {d['S']:g} for our estimators (chain = Algorithm C, augmented = Algorithm A, paper-j = "
            "the paper's constant decorrelation J) and the stand-in for [28] (naive-kf: the same estimator "
            "told S = 0 and γ ≡ 1, not [28] itself).",
        )
        paths.append(path)
    return paths


@register(
    "li2018-tables",
    title="Delay system with fading: filter/predictor MSE tables (Tables 1-2, Figs. 3-4)",
    source=_SOURCE,
    plot=_plot_tables,
    default_runs=150,
)
def run_tables(*, runs: int, seed: int, progress=None, S: Any = None, steps: int = 151) -> ExperimentResult:
    """Tables 1–2: running-average MSE at t = 25..150 for filter and predictor, all estimator keys."""
    S_values, headline, by, keep = _common_run(
        "li2018-tables", runs=runs, seed=seed, progress=progress, q_values=(1.0,), S=S, steps=steps
    )
    rows = {}
    for s in S_values:
        rows[f"S={s:g}"] = {
            key: {
                which: {
                    f"x{i + 1}": [float(v[which]["running_avg"][t, i]) for t in TABLE_TIMES if t < steps]
                    for i in range(2)
                }
                for which in ("filter", "predictor")
            }
            for key, v in by[(1.0, s)].items()
        }
    metrics = {
        "estimators": {k: v["filter_summary"] for k, v in by[(1.0, headline)].items()},
        "lineup": _lineup(by[(1.0, headline)]),
        "headline_S": headline,
        "table_times": list(TABLE_TIMES),
        "tables": rows,
        "source_tables": SOURCE_TABLES,
        "source_tables_note": "not regression targets: the source's S, true initial states and run count are "
        "unknown (LD-01, LD-03, LD-10); compare qualitatively",
        "mse": _metrics_block(by, 1.0, S_values),
        "steady_state": _steady_state((1.0,), S_values),
    }
    data, est = keep[1.0]
    shift = float(np.abs(est["chain"].mean[:, 1:] - est["chain"].extras["next_mean"][:, :-1]).max())
    head = by[(1.0, headline)]
    last = steps - 1

    def run_avg_se(err2, t):
        return CL.jackknife_se(err2[:, : t + 1], lambda mm: mm.mean(axis=-2))

    claims = []
    for which in ("filter", "predictor"):
        a = head["chain"][which]["running_avg"][last]
        b = head["naive-kf"][which]["running_avg"][last]
        g = np.stack([head["chain"][which + "_err2"], head["naive-kf"][which + "_err2"]], axis=1)
        se = CL.jackknife_se(g, lambda mm: mm[..., 1, :, :].mean(-2) - mm[..., 0, :, :].mean(-2))
        claims.append(
            CL.less(
                f"Table {'1' if which == 'filter' else '2'} and Fig. {'3' if which == 'filter' else '4'}: the "
                f"proposed {which} has a lower MSE than [28]'s",
                quantity=f"running-average {which} MSE at t = {last} (S = {headline:g}), ours against the "
                "stand-in naive-kf (S = 0, γ ≡ 1; not [28] itself, LD-12)",
                a=a,
                b=b,
                names=("ours", "stand-in"),
                tol=CL.K_SE * se,
                tolerance=f"{CL.K_SE:g} jackknife standard errors of the paired difference over {runs} runs: "
                f"{CL.fmt(CL.K_SE * se, 2)}",
            )
        )
    t0, t1 = TABLE_TIMES[0], min(TABLE_TIMES[-1], last)
    for which, tab in (("filter", "1"), ("predictor", "2")):
        e2 = head["chain"][which + "_err2"]
        g = e2
        se = CL.jackknife_se(g, lambda mm: mm[..., : t1 + 1, :].mean(-2) - mm[..., : t0 + 1, :].mean(-2))
        ra = head["chain"][which]["running_avg"]
        src = (
            SOURCE_TABLES[f"{which}_x1"][0],
            SOURCE_TABLES[f"{which}_x1"][-1],
            SOURCE_TABLES[f"{which}_x2"][0],
            SOURCE_TABLES[f"{which}_x2"][-1],
        )
        claims.append(
            CL.less(
                f"Table {tab}: the {which} MSE falls with t (x1 from {src[0]} at t = 25 to {src[1]} at t = 150, x2 from "
                f"{src[2]} to {src[3]})",
                quantity=f"our running-average {which} MSE (S = {headline:g}) at t = {t1} and at t = {t0}",
                a=ra[t1],
                b=ra[t0],
                names=(f"t = {t1}", f"t = {t0}"),
                tol=CL.K_SE * se,
                tolerance=f"{CL.K_SE:g} jackknife standard errors of the change over {runs} runs: {CL.fmt(CL.K_SE * se, 2)}",
                explanation="a running average of the ensemble MSE falls only if the early errors are larger than the "
                "steady ones; with our prior x(-k) ~ (0, 0.01 I) the errors start small and grow to their "
                "steady state. The source's decreasing numbers point to a true initial state far from the "
                "prior mean, which the paper does not give (docs/sources LD-01, LD-10)",
            )
        )
    claims.append(
        CL.at_most(
            "(our reading of Tables 1-2, LD-10) the filter and predictor tables differ by a constant "
            "running-sum offset: the per-step filter errors equal the predictor errors one step later",
            quantity="max |x̂(t|t) - x̂(t|t-1)| over runs and steps",
            value=shift,
            bound=0.0,
            tol=0.0,
            tolerance="exact (0)",
        )
    )
    metrics["report_tables"] = _report_tables(rows, headline, steps)
    plot_data = {
        "S": headline,
        "filter": {k: v["filter"]["running_avg"] for k, v in head.items()},
        "predictor": {k: v["predictor"]["running_avg"] for k, v in head.items()},
    }
    return ExperimentResult(
        "li2018-tables", _settings(runs, steps, seed, S_values), metrics, data=plot_data, claims=claims
    )


def _report_tables(rows: dict[str, Any], headline: float, steps: int) -> list[dict[str, Any]]:
    """Tables 1-2 of the source next to ours (running-average MSE at t = 25..150)."""
    times = [t for t in TABLE_TIMES if t < steps]
    out = []
    ours = rows[f"S={headline:g}"]
    for which, tab in (("filter", "Table 1 (filter x̂(t|t))"), ("predictor", "Table 2 (predictor x̂(t+1|t))")):
        table_rows = []
        for comp in ("x1", "x2"):
            table_rows.append([f"{comp}: this paper (printed)", *SOURCE_TABLES[f"{which}_{comp}"][: len(times)]])
            table_rows.append([f"{comp}: ours, chain (S = {headline:g})", *ours["chain"][which][comp]])
            table_rows.append([f"{comp}: [28] (printed)", *SOURCE_TABLES[f"{which}_{comp}_[28]"][: len(times)]])
            table_rows.append([f"{comp}: ours, stand-in for [28]", *ours["naive-kf"][which][comp]])
        out.append(
            report_table(
                f"{tab}: running-average MSE",
                ["row"] + [f"t = {t}" for t in times],
                table_rows,
                note="The source's S, true initial states and run count are unknown (LD-01, LD-03, "
                "LD-10), so the numbers are not expected to agree; the source's fall with t, "
                "ours rise to their steady state. The stand-in for [28] is our estimator told "
                "S = 0 and γ ≡ 1, not the method of [28] (LD-12).",
            )
        )
    return out
