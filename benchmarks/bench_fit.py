"""Fitting benchmark: fit times on the real data sets, and parameter recovery on simulated
censored state-space models.

1. Times: exact ML (tk.CensoredAR, standard errors included) on the phosphorus data (AR(1), AR(2)) and
   the cloud-ceiling data (AR(1)), best of ``--repeat`` fits after numba's one-off start-up, wall clock
   and process CPU time (the latter robust on a shared machine; BLAS may add threads). Targets: under
   1 s on phosphorus, under 10 s on the cloud ceiling.
2. Recovery: a regression with AR(2) errors (a state-space model with n = 2: the companion state
   (xi_t, xi_{t-1}), R = 0), y*_t = 1 + 0.5 x_t + xi_t, phi = (0.5, 0.3), sigma2 = 1, left-censored at the
   ``--fractions`` quantiles of each simulated series (default 30 % and 70 %; 0 = uncensored), T =
   ``--steps``, ``--reps`` replications (one value, or one per fraction), fitted by exact ML. Replication r
   of share f draws from its own seed (seed, 100 f, r), so the results do not depend on ``--jobs`` (the
   replications are spread over that many processes, one thread each). For each parameter: the bias with
   its Monte Carlo standard error (sd / sqrt(reps)), and the coverage of the 95 % Wald interval
   (estimate +- 1.96 s.e.) with its binomial standard error sqrt(0.95 * 0.05 / reps). Targets: |bias| < 3
   MC s.e., |coverage - 0.95| < 3 binomial s.e. ``--gaussian-check`` also fits, on each replication's
   uncensored latent series y*, a plain exact Gaussian AR(2) ML written here independently of tobitkf,
   and prints its bias and the paired difference to the censored fit (with 0 % censoring the two are
   the same estimator: a check of the likelihood code; with censoring the difference is what the
   censoring costs).

   The ML estimates of AR coefficients carry the usual O(1/T) small-sample bias (phi2 about -0.009 at
   T = 300 uncensored); the MC s.e. shrinks as 1/sqrt(reps T), so the bias test at a given T needs reps
   small enough against T (T = 300 with 200 replications is too few steps: phi2 fails at 30 %). The
   default T = 1000.

3. Scale (``--scale N ...``, default 100000 1000000; ``--no-scale`` skips it): ``tk.fit`` of a censored
   regression with AR(1) errors (y*_t = 1 + 0.5 x_t + xi_t, phi = 0.6, sigma2 = 1, 30 % left-censored) on
   N readings, once each, wall clock and process CPU time (user and system) with the load average before and
   after (the CPU time is the fair figure on a shared machine); targets: 10^5 under 30 s and converged, 10^6 under
   300 s. And a state-space model with n = 1 (estimate A, Q, R and a mean D on a constant input) on 300
   readings, by the default method (direct quasi-Newton) and by EM (for comparison, maxiter 300); target:
   the default under 2 s, best of ``--repeat`` after the one-off compile.

Run by hand:  PYTHONPATH=src python benchmarks/bench_fit.py [--steps 1000] [--reps 100] [--fractions 0.3 0.7]
              [--jobs 2] [--gaussian-check] [--rows FILE.jsonl (resumable)] [--no-times] [--json OUT]
``--smoke``: 1 repeat of the phosphorus AR(1) fit, 3 replications of T = 100 in one process, the scale
section on 10^4 readings and the state-space fit without EM (a quick check that it runs).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

# one thread per process: the replications are spread over --jobs processes instead
for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402

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
    """One series of the recovery model: (y, X, limit, truth, ystar); ``frac`` = 0 leaves it uncensored
    (limit -inf)."""
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
    lim = float(np.quantile(ystar, frac)) if frac > 0 else -np.inf
    return np.maximum(ystar, lim), X, lim, np.r_[beta, s2, phi], ystar


def gaussian_ar2_mle(y, X):
    """Plain exact Gaussian ML of y = X beta + xi, xi stationary AR(2), written here independently of
    tobitkf: prediction-error decomposition, (xi_1, xi_2) ~ N(0, G) with the AR(2) autocovariances
    gamma0 = s2 (1 - phi2) / ((1 + phi2) ((1 - phi2)^2 - phi1^2)), gamma1 = phi1 gamma0 / (1 - phi2), then
    xi_t | past ~ N(phi1 xi_{t-1} + phi2 xi_{t-2}, s2). Maximised over (beta, log s2, phi) by scipy's
    Nelder-Mead from the OLS start, restarted once. Returns (beta0, beta1, s2, phi1, phi2)."""
    from scipy.optimize import minimize

    T = len(y)

    def nll(th):
        b, s2, p1, p2 = th[:2], np.exp(th[2]), th[3], th[4]
        if not (abs(p2) < 1 and p2 + p1 < 1 and p2 - p1 < 1):
            return 1e300
        e = y - X @ b
        g0 = s2 * (1 - p2) / ((1 + p2) * ((1 - p2) ** 2 - p1**2))
        g1 = p1 * g0 / (1 - p2)
        det = g0**2 - g1**2
        q = (g0 * e[0] ** 2 - 2 * g1 * e[0] * e[1] + g0 * e[1] ** 2) / det
        u = e[2:] - p1 * e[1:-1] - p2 * e[:-2]
        return 0.5 * (np.log(det) + q + (T - 2) * np.log(s2) + u @ u / s2 + T * np.log(2 * np.pi))

    b = np.linalg.lstsq(X, y, rcond=None)[0]
    e = y - X @ b
    Z = np.c_[e[1:-1], e[:-2]]
    p = np.linalg.lstsq(Z, e[2:], rcond=None)[0]
    th = np.r_[b, np.log(np.var(e[2:] - Z @ p)), p]
    for _ in range(2):
        th = minimize(nll, th, method="Nelder-Mead", options={"xatol": 1e-9, "fatol": 1e-11, "maxiter": 20000}).x
    return np.r_[th[:2], np.exp(th[2]), th[3:]]


def _one_replication(task):
    """Worker: simulate replication ``r`` of censoring share ``frac`` from its own seed (so the result does
    not depend on how replications are spread over processes) and fit it."""
    seed, frac, steps, r, gaussian = task
    rng = np.random.default_rng([seed, int(round(frac * 100)), r])
    y, X, lim, truth, ystar = simulate(rng, steps, frac)
    t0 = time.perf_counter()
    f = tk.CensoredAR(2).fit(y, X, lower=lim)
    secs = time.perf_counter() - t0
    out = {
        "seed": seed,
        "T": steps,
        "frac": frac,
        "r": r,
        "theta": [float(v) for v in f.theta],
        "se": [float(f.se[n]) for n in f.names],
        "names": list(f.names),
        "truth": [float(v) for v in truth],
        "censored_share": float(np.mean(ystar <= lim)),
        "seconds": secs,
    }
    if gaussian:
        out["gaussian_mle"] = [float(v) for v in gaussian_ar2_mle(ystar, X)]
    return out


def _init_worker():
    _warm()


def summarise(rows: list[dict], frac: float, steps: int, wall: float) -> dict:
    """Bias with its Monte Carlo s.e. (sd / sqrt(n)), coverage of the 95 % Wald interval with its binomial
    s.e. sqrt(0.95 * 0.05 / n), and the verdicts |bias| < 3 MC s.e., |coverage - 0.95| < 3 binomial s.e."""
    rows = sorted(rows, key=lambda d: d["r"])
    names, truth = rows[0]["names"], np.array(rows[0]["truth"])
    est, se = np.array([d["theta"] for d in rows]), np.array([d["se"] for d in rows])
    ok = np.all(np.isfinite(se), axis=1)
    est, se = est[ok], se[ok]
    n = len(est)
    bias = est.mean(0) - truth
    mcse = est.std(0, ddof=1) / np.sqrt(n)
    cover = (np.abs(est - truth) <= 1.959964 * se).mean(0)
    bse = np.sqrt(0.95 * 0.05 / n)
    share = np.array([d["censored_share"] for d in rows])
    fit_s = np.array([d["seconds"] for d in rows])
    params: dict[str, dict] = {}
    rec: dict = {
        "censored_fraction": frac,
        "censored_share_realised": {"mean": float(share.mean()), "min": float(share.min()), "max": float(share.max())},
        "T": steps,
        "replications": len(rows),
        "usable": n,
        "fit_seconds": {
            "median": float(np.median(fit_s)),
            "q10": float(np.quantile(fit_s, 0.1)),
            "q90": float(np.quantile(fit_s, 0.9)),
        },
        "wall_seconds": round(wall, 1),
        "parameters": params,
    }
    lab = f"{int(round(frac * 100))}% censored"
    print(
        f"{lab}: T = {steps}, R = {len(rows)} ({n} usable), censored share realised {share.mean():.3f} "
        f"({share.min():.3f}-{share.max():.3f}), fit {np.median(fit_s):.2f} s median "
        f"({np.quantile(fit_s, 0.1):.2f}-{np.quantile(fit_s, 0.9):.2f}), wall {wall:.0f} s",
        flush=True,
    )
    print(
        f"  {'param':7s} {'truth':>6s} {'bias':>9s} {'MC s.e.':>8s} {'bias/se':>8s} {'cover':>6s} {'bin.se':>6s}  verdicts"
    )
    for i, nm in enumerate(names):
        b_ok, c_ok = bool(abs(bias[i]) < 3 * mcse[i]), bool(abs(cover[i] - 0.95) < 3 * bse)
        params[nm] = {
            "truth": float(truth[i]),
            "bias": float(bias[i]),
            "mc_se": float(mcse[i]),
            "bias_in_mc_se": float(bias[i] / mcse[i]),
            "coverage": float(cover[i]),
            "coverage_binomial_se": float(bse),
            "bias_met": b_ok,
            "coverage_met": c_ok,
            "met": b_ok and c_ok,
        }
        print(
            f"  {nm:7s} {truth[i]:6.2f} {bias[i]:+9.4f} {mcse[i]:8.4f} {bias[i] / mcse[i]:+8.2f} {cover[i]:6.3f} "
            f"{bse:6.4f}  bias {'met' if b_ok else 'NOT met'}, coverage {'met' if c_ok else 'NOT met'}",
            flush=True,
        )
    if "gaussian_mle" in rows[0]:
        g = np.array([d["gaussian_mle"] for d in rows])[ok]
        gb, gse = g.mean(0) - truth, g.std(0, ddof=1) / np.sqrt(n)
        d = est - g
        rec["gaussian_mle"] = {
            nm: {
                "bias": float(gb[i]),
                "mc_se": float(gse[i]),
                "max_abs_diff_to_fit": float(np.abs(d[:, i]).max()),
                "mean_diff_to_fit": float(d[:, i].mean()),
                "mean_diff_se": float(d[:, i].std(ddof=1) / np.sqrt(n)),
            }
            for i, nm in enumerate(names)
        }
        print("  independent plain-Gaussian AR(2) MLE on the uncensored latent series y*, same replications:")
        for i, nm in enumerate(names):
            print(
                f"  {nm:7s} bias {gb[i]:+9.4f} (MC s.e. {gse[i]:.4f}, {gb[i] / gse[i]:+.2f}); fit - Gaussian MLE: "
                f"mean {d[:, i].mean():+.4f} +- {d[:, i].std(ddof=1) / np.sqrt(n):.4f}, max |.| {np.abs(d[:, i]).max():.2e}",
                flush=True,
            )
    return rec


def recovery(
    reps: list[int], steps: int, seed: int, fractions: list[float], jobs: int, gaussian: bool, rows_file: str | None
) -> dict:
    out = {}
    if len(reps) == 1:
        reps = reps * len(fractions)
    for frac, R in zip(fractions, reps, strict=True):
        rows: list[dict] = []
        if rows_file and Path(rows_file).exists():  # resume: replications already in the file are kept
            with open(rows_file) as fh:
                old = [json.loads(line) for line in fh if line.strip()]
            done = {}
            for d in old:
                if (d.get("seed"), d.get("T"), d.get("frac")) == (seed, steps, frac) and d["r"] < R:
                    if gaussian == ("gaussian_mle" in d):
                        done[d["r"]] = d
            rows.extend(done.values())
            if rows:
                print(f"  resuming: {len(rows)} replications read from {rows_file}", flush=True)
        have = {d["r"] for d in rows}
        tasks = [(seed, frac, steps, r, gaussian) for r in range(R) if r not in have]
        t0 = time.perf_counter()
        sink = open(rows_file, "a") if rows_file else None  # noqa: SIM115
        lab = f"{int(round(frac * 100))}% censored"

        n0 = len(rows)

        def got(row, rows=rows, t0=t0, R=R, sink=sink, lab=lab, n0=n0):
            rows.append(row)
            if sink is not None:
                sink.write(json.dumps(row) + "\n")
                sink.flush()
            k = len(rows)
            if k == R or k % max(1, R // 25) == 0:
                el = time.perf_counter() - t0
                print(f"  [{lab}] {k}/{R} fits, {el:.0f} s elapsed, ~{el / (k - n0) * (R - k):.0f} s left", flush=True)

        if jobs > 1:
            from concurrent.futures import ProcessPoolExecutor

            with ProcessPoolExecutor(jobs, initializer=_init_worker) as ex:
                for row in ex.map(_one_replication, tasks):
                    got(row)
        else:
            for task in tasks:
                got(_one_replication(task))
        if sink is not None:
            sink.close()
        out[lab.split()[0]] = summarise(rows, frac, steps, time.perf_counter() - t0)
    return out


def _scale_series(T: int, seed: int = 1):
    from scipy.signal import lfilter

    rng = np.random.default_rng(seed)
    xi = lfilter([1.0], [1.0, -0.6], rng.normal(size=T))
    X = np.c_[np.ones(T), rng.normal(size=T)]
    ys = X @ [1.0, 0.5] + xi
    lim = float(np.quantile(ys, 0.3))
    return np.maximum(ys, lim), X, lim


def _state_space_series(T: int = 300, seed: int = 1):
    rng = np.random.default_rng(seed)
    x, y = 0.0, np.empty(T)
    for t in range(T):
        x = 0.8 * x + rng.normal() * np.sqrt(0.5)
        y[t] = 2.0 + x + rng.normal() * np.sqrt(0.3)
    return y


def scale(sizes: list[int], repeat: int, with_em: bool) -> dict:
    """The speed targets of tk.fit (module docstring, section 3)."""
    _warm()
    out: dict = {}
    y = _state_space_series()
    u = np.ones((y.size, 1))
    templ = tk.LinearSystem(A=[[0.5]], C=[[1.0]], Q=[[1.0]], R=[[1.0]], x0=[0.0], P0=[[1.0]], D=[[0.0]])
    est = ("A", "Q", "R", "D")
    tk.fit(templ, y[:50], u=u[:50], estimate=est)  # the compiled likelihood's one-off load
    methods = [("auto", 2.0)] + ([("em", None)] if with_em else [])
    for method, limit in methods:
        res = {}

        def run(method=method, res=res):
            res["fit"] = tk.fit(templ, y, u=u, estimate=est, method=method, maxiter=300 if method == "em" else 500)

        load0 = os.getloadavg()[0]
        t = best_time(run, repeat if method == "auto" else 1)
        tc = best_time(run, repeat if method == "auto" else 1, cpu=True)
        f = res["fit"]
        key = f"state-space-n1-T300-{f.method}"
        out[key] = {
            "seconds": round(t, 3),
            "cpu_seconds": round(tc, 3),
            "target_seconds": limit,
            "met": None if limit is None else bool(t < limit and f.converged),
            "converged": f.converged,
            "loglik": f.loglik,
            "evaluations": f.evaluations,
            "load_average": [load0, os.getloadavg()[0]],
        }
        print(
            f"state space n = 1, 300 readings, estimate A, Q, R, D, method {f.method}: {t:.3f} s wall, "
            f"{tc:.3f} s CPU" + ("" if limit is None else f" (target < {limit:g} s)") + f", converged {f.converged}, "
            f"loglik {f.loglik:.6f}, load average {load0:.1f} -> {os.getloadavg()[0]:.1f}",
            flush=True,
        )
    for T in sizes:
        y, X, lim = _scale_series(T)
        limit = 30.0 if T <= 100_000 else 300.0
        load0 = os.getloadavg()[0]
        t0, c0, o0 = time.perf_counter(), time.process_time(), os.times()
        f = tk.fit(tk.CensoredAR(1), y, X=X, lower=lim, progress=None)
        t, tc, o1 = time.perf_counter() - t0, time.process_time() - c0, os.times()
        user, system = o1.user - o0.user, o1.system - o0.system
        load1 = os.getloadavg()[0]
        out[f"censored-ar1-T{T}"] = {
            "seconds": round(t, 2),
            "cpu_seconds": round(tc, 2),
            "user_seconds": round(user, 2),
            "sys_seconds": round(system, 2),
            "target_seconds": limit,
            "met": bool(t < limit and f.converged),
            "converged": f.converged,
            "message": f.message,
            "evaluations": f.evaluations,
            "estimates": f.params,
            "se": f.se,
            "load_average": [load0, load1],
        }
        print(
            f"CensoredAR(1), {T} readings (30 % censored): {t:.1f} s wall, {tc:.1f} s CPU ({user:.1f} s user, "
            f"{system:.1f} s sys) (target < {limit:g} s), "
            f"converged {f.converged} ({f.message}), {f.evaluations} evaluations, load average {load0:.1f} -> "
            f"{load1:.1f}; estimates " + ", ".join(f"{n} {f.params[n]:.4f} +- {f.se[n]:.4f}" for n in f.names),
            flush=True,
        )
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, nargs="+", default=[100], help="replications (one value, or one per fraction)")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--fractions", type=float, nargs="+", default=[0.3, 0.7], help="censored shares (0 = none)")
    ap.add_argument("--jobs", type=int, default=2, help="processes for the replications")
    ap.add_argument(
        "--gaussian-check",
        action="store_true",
        help="also fit an independent plain-Gaussian AR(2) MLE to each uncensored latent series",
    )
    ap.add_argument("--no-times", action="store_true", help="skip the real-data fit times")
    ap.add_argument("--rows", default=None, help="append each replication's result to this JSON-lines file")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--smoke", action="store_true")
    ap.add_argument("--scale", type=int, nargs="+", default=[100_000, 1_000_000], help="record lengths of section 3")
    ap.add_argument("--no-scale", action="store_true", help="skip section 3")
    ap.add_argument("--no-recovery", action="store_true", help="skip section 2")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    if a.smoke:
        a.reps, a.steps, a.repeat, a.jobs, a.scale = [3], 100, 1, 1, [10_000]
        print("smoke run: checks that the benchmark runs; 3 replications make its verdicts meaningless", flush=True)
    print(f"bench_fit: {' '.join(sys.argv[1:]) or '(defaults)'}; load average {os.getloadavg()}", flush=True)
    res: dict = {} if a.no_times else {"times": times(a.repeat, a.smoke)}
    if a.jobs == 1:
        _warm()
    if not a.no_scale:
        res["scale"] = scale(a.scale, a.repeat, with_em=not a.smoke)
    if not a.no_recovery:
        res["recovery"] = recovery(a.reps, a.steps, a.seed, a.fractions, a.jobs, a.gaussian_check, a.rows)
    print(f"load average at the end {os.getloadavg()}", flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
