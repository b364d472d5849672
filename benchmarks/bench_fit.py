"""Fitting benchmark (issue 18): fit times on the real data sets, and parameter recovery on simulated
censored state-space models.

1. Times: exact ML (tk.CensoredAR, standard errors included) on the phosphorus data (AR(1), AR(2)) and
   the cloud-ceiling data (AR(1)), best of ``--repeat`` fits after numba's one-off start-up, wall clock
   and process CPU time (the latter robust on a shared machine; BLAS may add threads). Targets: under
   1 s on phosphorus, under 10 s on the cloud ceiling.
2. Recovery: a regression with AR(2) errors (a state-space model with n = 2: the companion state
   (xi_t, xi_{t-1}), R = 0), y*_t = 1 + 0.5 x_t + xi_t, phi = (0.5, 0.3), sigma2 = 1, left-censored at the
   30 % and 70 % quantile of each simulated series, T = ``--steps``, ``--reps`` replications, fitted by
   exact ML. For each parameter: the bias with its Monte Carlo standard error (sd / sqrt(reps)), and the
   coverage of the 95 % Wald interval (estimate +- 1.96 s.e.) with its binomial standard error
   sqrt(0.95 * 0.05 / reps). Targets: |bias| < 3 MC s.e., |coverage - 0.95| < 3 binomial s.e.

Run by hand:  PYTHONPATH=src python benchmarks/bench_fit.py [--reps 200] [--steps 300] [--repeat 3]
``--smoke``: 1 repeat of the phosphorus AR(1) fit and 8 replications of T = 150 (a quick check that it runs).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import tobitkf as tk  # noqa: E402
from _timing import best_time  # noqa: E402
from tobitkf.data import load_cloud_ceiling, load_phosphorus  # noqa: E402
from tobitkf.experiments.data_sets import _warm  # noqa: E402


def times(repeat: int, smoke: bool) -> dict:
    _warm()
    p, c = load_phosphorus(), load_cloud_ceiling()
    cases = [
        ("phosphorus", 1, p, p.design("lQ"), 1.0),
        ("phosphorus", 2, p, p.design("lQ"), 1.0),
        ("cloud-ceiling", 1, c, c.design(), 10.0),
    ]
    if smoke:
        cases = cases[:1]
    out = {}
    for name, order, s, X, limit in cases:
        res = {}

        def run():
            res["fit"] = tk.CensoredAR(order).fit(s.y, X, lower=s.lower, upper=s.upper, censored=s.censored)

        t = best_time(run, repeat)
        tc = best_time(run, repeat, cpu=True)
        f = res["fit"]
        out[f"{name}-ar{order}"] = {
            "seconds": round(t, 3),
            "cpu_seconds": round(tc, 3),
            "target_seconds": limit,
            "met": t < limit,
            "evaluations": f.evaluations,
            "loglik": f.loglik,
        }
        print(
            f"{name} AR({order}): best of {repeat} = {t:.3f} s wall, {tc:.3f} s CPU (target < {limit:g} s), "
            f"{f.evaluations} likelihood evaluations, loglik {f.loglik:.6f}",
            flush=True,
        )
    return out


def simulate(rng, T, frac):
    beta, phi, s2 = np.array([1.0, 0.5]), np.array([0.5, 0.3]), 1.0
    from tobitkf.inference.censored_ar import ar_autocovariance

    g = ar_autocovariance(phi, s2, 1)
    G = np.array([[g[0], g[1]], [g[1], g[0]]])
    xi = np.zeros(T + 2)
    xi[:2] = np.linalg.cholesky(G) @ rng.normal(size=2)
    for t in range(2, T + 2):
        xi[t] = phi[0] * xi[t - 1] + phi[1] * xi[t - 2] + rng.normal() * np.sqrt(s2)
    xi = xi[2:]
    X = np.c_[np.ones(T), rng.normal(size=T)]
    ystar = X @ beta + xi
    lim = float(np.quantile(ystar, frac))
    return np.maximum(ystar, lim), X, lim, np.r_[beta, s2, phi]


def recovery(reps: int, steps: int, seed: int) -> dict:
    out = {}
    for frac in (0.3, 0.7):
        rng = np.random.default_rng([seed, int(frac * 100)])
        est, se, truth_all, secs = [], [], None, []
        for r in range(reps):
            y, X, lim, truth = simulate(rng, steps, frac)
            t0 = time.perf_counter()
            f = tk.CensoredAR(2).fit(y, X, lower=lim)
            secs.append(time.perf_counter() - t0)
            est.append(f.theta)
            se.append([f.se[n] for n in f.names])
            truth_all = truth
            names = f.names
        est, se = np.array(est), np.array(se)
        ok = np.all(np.isfinite(se), axis=1)
        est, se = est[ok], se[ok]
        n = len(est)
        bias = est.mean(0) - truth_all
        mcse = est.std(0, ddof=1) / np.sqrt(n)
        cover = (np.abs(est - truth_all) <= 1.959964 * se).mean(0)
        bse = np.sqrt(0.95 * 0.05 / n)
        rec = {
            "censored_fraction": frac,
            "T": steps,
            "replications": reps,
            "usable": n,
            "mean_fit_seconds": round(float(np.mean(secs)), 3),
            "parameters": {},
        }
        for i, nm in enumerate(names):
            rec["parameters"][nm] = {
                "truth": float(truth_all[i]),
                "bias": float(bias[i]),
                "mc_se": float(mcse[i]),
                "bias_in_mc_se": float(bias[i] / mcse[i]),
                "coverage": float(cover[i]),
                "coverage_binomial_se": float(bse),
                "met": bool(abs(bias[i]) < 3 * mcse[i] and abs(cover[i] - 0.95) < 3 * bse),
            }
            print(
                f"{int(frac * 100)}% censored, {nm}: bias {bias[i]:+.4f} ({bias[i] / mcse[i]:+.2f} MC s.e.), "
                f"coverage {cover[i]:.3f} (0.95 +- {3 * bse:.3f})",
                flush=True,
            )
        out[f"{int(frac * 100)}%"] = rec
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=200)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--smoke", action="store_true")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    if a.smoke:
        a.reps, a.steps, a.repeat = 8, 150, 1
    res = {"times": times(a.repeat, a.smoke), "recovery": recovery(a.reps, a.steps, a.seed)}
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
