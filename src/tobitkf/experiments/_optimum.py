"""The optimum in an experiment: the particle filter as an estimator and every estimator's ratio to it.

Shared by the yardstick and the experiments whose readings pass a random channel. The particle filter
(:class:`~tobitkf.ParticleFilter`) runs with ``2 N_p`` particles (the optimum, key ``pf``) and with
``N_p`` (the convergence check: the relative change of the time-averaged RMSE per component, converged
below 0.3 %) on the first ``runs`` runs of the experiment's own data; every estimator's
``ratio_to_optimum`` is its time-averaged RMSE on those runs over the particle filter's.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .. import metrics as mx
from .._validation import ValidationError
from ..filters.particle import ParticleFilter

__all__ = ["TOLERANCE", "pf_check", "add_optimum", "check_particles", "pop_options"]

TOLERANCE = 0.003


def check_particles(value: Any, name: str = "optimum_particles") -> int:
    """A particle count N_p >= 0 (0: no particle filter)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
        raise ValidationError(f"{name}: expected an integer >= 0 (0: no particle filter), got {value!r}")
    return int(value)


def pop_options(overrides: dict[str, Any], particles: int, runs: int = 200) -> dict[str, int]:
    """Take ``optimum_particles`` and ``optimum_runs`` out of an experiment's keyword overrides (checked)."""
    p = check_particles(overrides.pop("optimum_particles", particles))
    r = overrides.pop("optimum_runs", runs)
    if isinstance(r, bool) or not isinstance(r, (int, np.integer)) or r < 1:
        raise ValidationError(f"optimum_runs: expected a positive integer, got {r!r}")
    return {"particles": p, "runs": int(r)}


def pf_check(system, channel, y, x, particles: int, seed: Any) -> tuple[dict[str, Any], Any]:
    """The PF with 2 N_p particles (the optimum) and with N_p (the convergence check), on the same data.

    Returns the summary of the optimum (``mx.summarize`` plus ``particles``, ``proposal`` and
    ``convergence``) and its :class:`~tobitkf.filters.core.FilterResult` (mean and var)."""
    results = []
    for j, Np in enumerate((particles, 2 * particles)):
        pf = ParticleFilter(system, channel, particles=Np, seed=np.random.SeedSequence([int(seed), 7, j]))
        results.append(pf.filter(y, outputs=("mean", "var")))
    small, big = results
    r_small = mx.rmse(x, small.mean).mean(0)
    summ = mx.summarize(x, big.mean)
    change = np.abs(r_small / np.asarray(summ["rmse_time_avg"]) - 1.0)
    summ["particles"] = 2 * particles
    summ["proposal"] = ParticleFilter(system, channel, particles=1).proposal
    summ["convergence"] = {
        "particles": [particles, 2 * particles],
        "rmse_time_avg_half": r_small.tolist(),
        "relative_change": change.tolist(),
        "tolerance": TOLERANCE,
        "converged": bool((change < TOLERANCE).all()),
    }
    return summ, big


def add_optimum(
    summaries: dict[str, Any],
    means: dict[str, np.ndarray],
    system,
    channel,
    y,
    x,
    *,
    particles: int,
    seed: Any,
    runs: int = 200,
    key: str = "pf",
) -> None:
    """Add ``summaries[key]`` (the optimum) and ``summaries[k]["ratio_to_optimum"]`` for every k of ``means``,
    in place (nothing if ``particles`` is 0).

    ``means[k]`` (N, T, n) are the estimators' means on ``y`` (N, T, m), ``x`` (N, T+1, n) the truth;
    the particle filter and the ratios use the first ``runs`` runs."""
    if not particles:
        return
    r = min(int(runs), y.shape[0])
    pf, _ = pf_check(system, channel, y[:r], x[:r], particles, seed)
    pf["ratio_runs"] = r
    ref = np.asarray(pf["rmse_time_avg"], dtype=float)
    for k, m in means.items():
        if k in summaries:
            summaries[k]["ratio_to_optimum"] = (mx.rmse(x[:r], m[:r]).mean(0) / ref).tolist()
    pf["ratio_to_optimum"] = [1.0] * ref.size
    summaries[key] = pf
