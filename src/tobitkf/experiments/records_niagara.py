r"""``data-niagara``: the Niagara River's about biweekly dichlorobenzene record under two detection limits,
fitted (drifting level, season, noise) and smoothed on the daily grid (:func:`niagara_model`)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..plotting import new_figure, save
from . import ExperimentResult, register, setting
from . import _claims as CL
from .records_common import _noop, fit_ml, fit_record
from .records_river import RiverModel

__all__ = ["niagara", "niagara_model"]


def niagara_model() -> RiverModel:
    """The Niagara record as a :class:`RiverModel`: a drifting level (random walk), a seasonal cycle and the
    readings' noise (an AR(1) residual between readings two weeks apart is not identified: its maximum
    likelihood time scale falls below a day)."""
    from ..data import load_niagara

    s = load_niagara(log=True)
    assert s.times is not None, "the Niagara record has calendar dates"
    day = (s.covariates["day"] - 1).astype(int)
    D = int(day.max()) + 1
    grid = s.times[0] + np.arange(D).astype("timedelta64[D]")
    from ..inference.wrtds import decimal_year

    t = decimal_year(grid)
    rows = np.column_stack([np.ones(D), np.sin(2 * np.pi * t), np.cos(2 * np.pi * t), np.ones(D)])
    return RiverModel(
        day=day,
        y=s.y,
        censored=s.censored,
        rows=rows,
        drift=("intercept",),
        coef=("intercept", "sin", "cos"),
        residual_ar=False,
    )


def _plot_niagara(result: ExperimentResult, outdir: Path) -> list[Path]:
    d = result.data
    m, dl = d["model"], d["daily"]
    grid = d["grid"]
    fig, ax = new_figure(1, 1, width=11, height=3.8)
    a = ax[0, 0]
    mu, sd = dl["ln_mean"], dl["ln_sd"]
    a.fill_between(grid, np.exp(mu - 1.96 * sd), np.exp(mu + 1.96 * sd), color="tab:blue", alpha=0.2, lw=0)
    a.plot(grid, np.exp(mu), color="tab:blue", lw=0.8, label="smoothed (median, 95 % band)")
    dates = grid[m.day]
    a.plot(dates[~m.censored], np.exp(m.y[~m.censored]), ".", color="black", ms=3, label="reading")
    a.plot(dates[m.censored], np.exp(m.y[m.censored]), "v", color="tab:red", ms=3, label="below the limit (at it)")
    a.set_yscale("log")
    a.set_ylabel("ng/L")
    a.legend(fontsize=7)
    return [
        save(
            fig,
            outdir,
            "daily.png",
            caption="Niagara River 1,2-dichlorobenzene: readings (censored ones at their detection limit) and the "
            "smoothed daily concentration of the fitted model (median of the latent ln concentration, 95 % band).",
        )
    ]


@register(
    "data-niagara",
    title="Niagara River dichlorobenzene: a short irregular record with two detection limits, fitted and smoothed",
    source="Real censored records (USGS EGRET; lmec; Environment Canada)",
    plot=_plot_niagara,
    default_runs=1,
)
def niagara(*, runs: int = 1, seed: int = 0, progress=None) -> ExperimentResult:
    """ML fit of a drifting level + season + noise to the censored record, and its daily smoothed series."""
    from .. import adf_log_likelihood

    progress = progress or _noop
    model = niagara_model()
    fit = fit_ml(model)
    progress(0.6)
    t0 = time.perf_counter()
    daily = model.daily_smooth(fit["theta"])
    t_daily = time.perf_counter() - t0
    sys_, y, cens, ind = model.daily_system(fit["theta"])
    ll_daily = float(adf_log_likelihood(sys_, cens, y, censored=ind))
    from ..data import load_niagara

    s = load_niagara(log=True)
    assert s.times is not None, "the Niagara record has calendar dates"
    grid = s.times[0] + np.arange(model.rows.shape[0]).astype("timedelta64[D]")
    metrics = {
        "data": {
            "readings": model.n_samples,
            "censored": int(model.censored.sum()),
            "limits_ng_per_l": sorted(set(np.round(np.exp(model.y[model.censored]), 6).tolist())),
            "days": int(model.rows.shape[0]),
        },
        "model": {"parameters": list(model.names), "fit": fit_record(model, fit)},
        "daily_smoother_seconds": round(t_daily, 3),
        "loglik_daily_grid": ll_daily,
        "runs": runs,
    }
    claims = [
        CL.close(
            "(not in the source) the likelihood on the readings' days (each gap one exact step) equals the "
            "assumed-density likelihood on the daily grid",
            quantity="log-likelihood at the estimates: per-gap filter and tobitkf.adf_log_likelihood on the daily "
            "grid (readings NaN on the other days)",
            value=fit["loglik"],
            target=ll_daily,
            tol=1e-8 * max(1.0, abs(ll_daily)),
            tolerance="1e-8 relative: an identity (days without a reading are exact Gaussian predictions)",
        )
    ]
    settings = {
        "data": setting("Niagara River at Fort Erie, 1,2-dichlorobenzene (Environment Canada)", "source"),
        "model": setting("ln c = level_d + b1 sin 2 pi t + b2 cos 2 pi t + N(0, r^2), level a random walk", "default"),
    }
    data = {"model": model, "daily": daily, "grid": grid}
    return ExperimentResult("data-niagara", settings, metrics, data, claims)
