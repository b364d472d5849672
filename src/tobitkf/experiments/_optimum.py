"""The optimum in an experiment: the particle filter as an estimator and every estimator's ratio to it.

Shared by the yardstick and the experiments whose readings pass a random channel. The particle filter
(:class:`~tobitkf.ParticleFilter`) runs with ``2 N_p`` particles (the optimum, key ``pf``) and with
``N_p`` (the convergence check: the relative change of the time-averaged RMSE per component, converged
below 0.3 %) on the first ``runs`` runs of the experiment's own data; every estimator's
``ratio_to_optimum`` is its time-averaged RMSE on those runs over the particle filter's.

The convergence check is a test, not a raw threshold: the relative change :math:`c` of the
time-averaged RMSE on doubling the particles carries Monte Carlo error (over runs and particles), estimated
by the jackknife over runs (each run's particles are independent of the others'); converged means
:math:`|c|` is not significantly above 0.3 % (one-sided, 1 %, Bonferroni over the components).
:func:`tobitkf.design.pcrlb.bound_test` is the calibrated test of "the MSE lies above the bound at every step".
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
from scipy.special import ndtri

from .. import metrics as mx
from .._validation import ValidationError
from ..filters.registry import Lineup, describe, lineup, parts_of

__all__ = [
    "TOLERANCE",
    "LEVEL",
    "pf_check",
    "pf_lineup",
    "pf_rung",
    "add_optimum",
    "check_particles",
    "pop_options",
    "convergence",
    "ratio_stderr",
]

TOLERANCE = 0.003
RUN_BLOCK = 200
"""Runs per particle-filter call of :func:`pf_check`: the runs are independent, so a long experiment's
particle filter runs block by block (block b > 0 of rung i seeded ``SeedSequence([seed, 7, i, b])``, block 0
seeded as an unblocked call), which caps its memory at 200 runs' particles (16000 particles x 1000 runs of the
fading example would otherwise hold ~5 GB); an experiment of at most 200 runs is one call, as before."""
LEVEL = 0.01
"""The level of the convergence check and of the bound test (family-wise)."""


def _time_avg_rmse_jackknife(err2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Time-averaged RMSE (n,) of squared errors ``err2`` (N, T, n) and its leave-one-run-out values (N, n)."""
    N = err2.shape[0]
    mse = err2.mean(0)
    loo = np.sqrt(np.maximum(N * mse - err2, 0.0) / (N - 1)).mean(1)
    return np.sqrt(mse).mean(0), loo


def convergence(err2_half: np.ndarray, err2_full: np.ndarray, tolerance: float = TOLERANCE, level: float = LEVEL):
    r"""Relative change of the time-averaged RMSE from N_p to 2 N_p particles, with its Monte Carlo error.

    :math:`c_i = \bar r_i(N_p)/\bar r_i(2N_p) - 1` per component i (:math:`\bar r` the mean over steps of the
    per-step RMSE over runs). Its standard error is the jackknife over runs,
    :math:`\mathrm{se}^2 = \frac{N-1}{N}\sum_r (c^{(-r)} - \bar c^{(\cdot)})^2`, which holds the error of both
    particle clouds and of the runs (the two filters run on the same readings with independent particles).
    Converged: :math:`|c_i| - z\,\mathrm{se}_i < \mathrm{tol}` for every i, :math:`z = \Phi^{-1}(1 - \alpha/n)`
    (the change is not significantly above the tolerance); ``resolved``: :math:`z\,\mathrm{se}_i <
    \mathrm{tol}` (the check could tell a change of the tolerance from none).

    Parameters
    ----------
    err2_half, err2_full : (N, T, n) ndarray
        Squared errors of the filter with N_p and with 2 N_p particles, same runs, N >= 2.
    tolerance, level : float
        The tolerance on :math:`|c|` and the test's level.

    Returns
    -------
    dict
        ``relative_change``, ``stderr``, ``z``, ``resolved``, ``converged`` (lists per component / bools).
    """
    N = err2_half.shape[0]
    rs, rs_loo = _time_avg_rmse_jackknife(err2_half)
    rb, rb_loo = _time_avg_rmse_jackknife(err2_full)
    c = rs / rb - 1.0
    c_loo = rs_loo / rb_loo - 1.0
    se = np.sqrt((N - 1) / N * ((c_loo - c_loo.mean(0)) ** 2).sum(0))
    z = float(ndtri(1.0 - level / c.size))
    return {
        "relative_change": np.abs(c).tolist(),
        "signed_change": c.tolist(),
        "stderr": se.tolist(),
        "z": z,
        "level": level,
        "tolerance": tolerance,
        "within_tolerance": bool((np.abs(c) < tolerance).all()),
        "resolved": bool((z * se < tolerance).all()),
        "converged": bool((np.abs(c) - z * se < tolerance).all()),
    }


def ratio_stderr(err2: np.ndarray, err2_optimum: np.ndarray) -> list[float]:
    r"""Jackknife standard error over runs of an estimator's ratio to the optimum, per component.

    The ratio :math:`\bar r_i/\bar r^{\mathrm{opt}}_i` (time-averaged RMSEs, :math:`\bar r` the mean over
    steps of the per-step RMSE over runs) is paired: both on the same runs. Its standard error,
    :math:`\mathrm{se}^2 = \frac{N-1}{N}\sum_r (q^{(-r)} - \bar q^{(\cdot)})^2` over the leave-one-run-out
    ratios, holds the error of the runs and of the optimum's particles.

    Parameters
    ----------
    err2, err2_optimum : (N, T, n) ndarray
        Squared errors of the estimator and of the optimum on the same runs, N >= 2.
    """
    N = err2.shape[0]
    _, r_loo = _time_avg_rmse_jackknife(err2)
    _, o_loo = _time_avg_rmse_jackknife(err2_optimum)
    q_loo = r_loo / o_loo
    return np.sqrt((N - 1) / N * ((q_loo - q_loo.mean(0)) ** 2).sum(0)).tolist()


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


def pf_rung(particles: int, seed: Any, i: int = 1, proposal: str = "auto") -> tuple[str, dict[str, Any]]:
    """Rung ``i`` of the particle ladder of :func:`pf_check` as a registry entry (name, options):
    :math:`2^iN_p` particles, seeded ``SeedSequence([seed, 7, i])`` (rung 0 is the plain check's N_p
    filter, rung 1 its optimum)."""
    opts = {"particles": particles * 2**i, "seed": np.random.SeedSequence([int(seed), 7, i])}
    if proposal != "auto":
        opts["proposal"] = proposal
    return "ParticleFilter", opts


def pf_lineup(particles: int, seed: Any, proposal: str = "auto") -> Lineup:
    """The two particle filters of the plain check (:func:`pf_check` without doublings) as a registry
    line-up: ``"pf-half"`` with N_p particles (the convergence check) and ``"pf"`` with 2 N_p (the optimum),
    rungs 0 and 1 of :func:`pf_rung`."""
    return {"pf-half": pf_rung(particles, seed, 0, proposal), "pf": pf_rung(particles, seed, 1, proposal)}


def pf_check(
    system,
    channel,
    y,
    x,
    particles: int,
    seed: Any,
    *,
    proposal: str = "auto",
    doublings: int = 0,
    note: Any = None,
) -> tuple[dict[str, Any], Any]:
    r"""The PF with 2 N_p particles (the optimum) and with N_p (the convergence check), on the same data,
    built from the registry (:func:`pf_rung`).

    With ``doublings`` = d > 0 the particle ladder goes on while the check fails: the pair
    :math:`(2^iN_p, 2^{i+1}N_p)` for i = 0, 1, ..., d, stopping at the first converged pair (each rung is
    run once; rung i with the seed ``SeedSequence([seed, 7, i])``, so d = 0 and the first pair of any
    ladder are the numbers of the plain check). The optimum is the last rung run; its ``convergence``
    is that of the last pair, and ``ladder`` lists every pair tried (particles, changes, converged), so a
    row that stops at the cap unconverged says so. Each pair is tested at the check's level, with no
    correction for the repeated look (the change itself halves with each doubling).
    More than :data:`RUN_BLOCK` runs are filtered block by block (see there).

    Parameters
    ----------
    proposal : str, default "auto"
        The particle filter's proposal (:class:`~tobitkf.ParticleFilter`).
    doublings : int >= 0, default 0
        At most this many extra doublings of the particle count.
    note : callable, optional
        ``note(text)`` before each block of runs (e.g. ``"particle filter, 4000 particles, runs 1-200 of
        1000"``), for the progress lines of a long experiment.

    Returns the summary of the optimum (``mx.summarize`` plus ``particles``, ``proposal``,
    ``convergence``, ``ladder`` and ``lineup``, the optimum's registry description) and its
    :class:`~tobitkf.filters.core.FilterResult` (mean and var)."""
    if isinstance(doublings, bool) or not isinstance(doublings, (int, np.integer)) or doublings < 0:
        raise ValidationError(f"doublings: expected an integer >= 0, got {doublings!r}")
    parts = parts_of(channel)

    def rung(i: int):
        name, opts = pf_rung(particles, seed, i, proposal)
        pfs, parts_out = [], []
        for b, r0 in enumerate(range(0, y.shape[0], RUN_BLOCK)):  # blocks of runs: memory capped
            if note is not None:
                r1 = min(r0 + RUN_BLOCK, y.shape[0])
                note(f"particle filter, {opts['particles']} particles, runs {r0 + 1}-{r1} of {y.shape[0]}")
            o = dict(opts) if b == 0 else {**opts, "seed": np.random.SeedSequence([int(seed), 7, i, b])}
            pfs.append(lineup({"pf": (name, o)}, system, parts)["pf"])
            parts_out.append(pfs[-1].filter(y[r0 : r0 + RUN_BLOCK], outputs=("mean", "var")))
        if len(parts_out) == 1:
            return pfs[0], parts_out[0]
        res = replace(
            parts_out[0],
            mean=np.concatenate([r.mean for r in parts_out]),
            var=np.concatenate([r.var for r in parts_out]),
            final=None,
        )
        return pfs[0], res

    pf0, small = rung(0)
    truth = mx.align_truth(x, np.asarray(small.mean))
    ladder = []
    last = 1
    for i in range(int(doublings) + 1):
        _, big = rung(i + 1)
        last = i + 1
        m_small, m_big = np.asarray(small.mean), np.asarray(big.mean)
        conv = convergence((m_small - truth) ** 2, (m_big - truth) ** 2)
        conv = {
            "particles": [particles * 2**i, particles * 2 ** (i + 1)],
            "rmse_time_avg_half": mx.rmse(x, small.mean).mean(0).tolist(),
            **conv,
        }
        ladder.append({k: conv[k] for k in ("particles", "relative_change", "stderr", "converged")})
        if conv["converged"]:
            break
        small = big
    summ = mx.summarize(x, big.mean)
    summ["particles"] = conv["particles"][1]
    summ["proposal"] = pf0.proposal
    summ["convergence"] = conv
    summ["ladder"] = ladder
    summ["lineup"] = describe({"pf": pf_rung(particles, seed, last, proposal)})["pf"]
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
    record: dict[str, Any] | None = None,
) -> None:
    """Add ``summaries[key]`` (the optimum) and ``summaries[k]["ratio_to_optimum"]`` for every k of ``means``,
    in place (nothing if ``particles`` is 0), and the optimum's registry description to ``record[key]``
    (an experiment's ``metrics["lineup"]``) when given.

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
    if record is not None:
        record[key] = pf.pop("lineup")
    else:
        pf.pop("lineup")
