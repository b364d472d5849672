"""Long-run reliability benchmark: one run of 10^6 steps per estimator family.

For each estimator: steps/second, and whether the whole run stayed finite, exactly
symmetric and PSD (smallest eigenvalue >= -1e-9 x the largest entry), with the largest
estimation error |x_hat - x| over the run (bounded = no drift to infinity).

Run by hand:  PYTHONPATH=src python benchmarks/bench_reliability.py [--steps 1000000] [--only KF,TKF]
``--smoke`` runs 2000 steps (CI). The same check at 10^6 steps is the slow-marked test
tests/reliability/test_long_runs.py. Each estimator's run is timed by wall, user and system time
(``benchmarks/_timing.py``), and the script prints the totals at its exit like the other benchmarks.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

import tobitkf as tk
from tobitkf.channels.fading import RiceFading
from tobitkf.channels.protocol import ProtocolChannel
from tobitkf.filters.delay_chain import chain_lmmse
from tobitkf.filters.fading import FadingTobitKalmanFilter
from tobitkf.filters.protocol import ProtocolTobitKalmanFilter
from tobitkf.filters.steady_state import SteadyStateTobitKalmanFilter, tobit_kalman_filter_controlled
from tobitkf.models.delay import paper_example, paper_prior
from tobitkf.simulate.delay import simulate_delay

try:
    import _timing  # run as a script: benchmarks/ is on sys.path (prints the times at exit)
except ImportError:  # imported by path from elsewhere (tests/reliability): the sibling module by its folder
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import _timing


def oscillator() -> tk.LinearSystem:
    w = 0.05
    return tk.LinearSystem(
        A=[[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]],
        C=[[1.0, 0.0]],
        Q=0.01 * np.eye(2),
        R=[[0.1]],
        x0=[0.0, 0.0],
        P0=0.05 * np.eye(2),
    )


def health(mean, cov, truth) -> dict:
    mean, cov = np.asarray(mean), np.asarray(cov)
    finite = bool(np.isfinite(mean).all() and np.isfinite(cov).all())
    sym = bool(np.array_equal(cov, np.swapaxes(cov, -1, -2)))
    worst = float("nan")
    if finite:
        eig = np.linalg.eigvalsh(cov)
        worst = float((eig.min(axis=-1) / np.maximum(np.abs(cov).max(axis=(-1, -2)), 1e-300)).min())
    err = float(np.abs(mean - truth).max()) if finite else float("inf")
    return {
        "finite": finite,
        "symmetric": sym,
        "min_eig_rel": worst,
        "psd": finite and worst >= -1e-9,
        "max_abs_error": err,
    }


def cases(steps: int):
    """name -> callable returning (mean, cov, truth) for one run of ``steps`` steps."""
    s, c = oscillator(), tk.Censoring(lower=0.0)

    def data():
        return tk.simulate(s, steps, 1, censoring=c, seed=11)

    def kf():  # on the latent (uncensored) record: fed censored values the KF is biased by design, and the
        d = data()  # marginally stable oscillator wanders to |x| ~ 100 over 10^6 steps, so its error grows too
        o = tk.KalmanFilter(s).filter(d.y_latent)
        return o.mean, o.cov, d.x[:, 1:]

    def tkf():
        d = data()
        o = tk.TobitKalmanFilter(s, c).filter(d.y)
        return o.mean, o.cov, d.x[:, 1:]

    def tkf_joseph_total():
        d = data()
        o = tk.TobitKalmanFilter(s, c, noise_term="total_variance", covariance_update="joseph").filter(d.y)
        return o.mean, o.cov, d.x[:, 1:]

    def dkf():
        d = data()
        o = tk.DroppingKalmanFilter(s, c).filter(d.y)
        return o.mean, o.cov, d.x[:, 1:]

    def sstkf():
        d = data()
        o = SteadyStateTobitKalmanFilter(s, 0.5).filter_controlled(d.y_latent)
        return o.mean, o.cov, d.x[:, 1:]

    def ctrl():
        d = data()
        o = tobit_kalman_filter_controlled(s, 0.5, d.y_latent)
        return o.mean, o.cov, d.x[:, 1:]

    def ftkf():
        fad = RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
        d = tk.simulate(s, steps, 1, censoring=c, measurement=fad, seed=11)
        o = FadingTobitKalmanFilter(s, fad, c).filter(d.y, keep_smoothed=False)
        return o.mean, o.cov, d.x[:, 1:]

    def ptkf():
        ch = ProtocolChannel(1, window=1, threshold=0.0)
        d = tk.simulate(s, steps, 1, seed=11, channel=ch)
        o = ProtocolTobitKalmanFilter(s, ch).filter(d.y)
        return o.mean, o.cov, d.x[:, 1:]

    def chain():
        sys_, prior = paper_example(), paper_prior()
        d = simulate_delay(sys_, prior, steps, 1, seed=11)
        o = chain_lmmse(sys_, prior, d.y)
        return o.mean, o.cov, d.x[:, :steps]

    return {
        "KF": kf,
        "DKF": dkf,
        "TKF": tkf,
        "TKF total_variance+joseph": tkf_joseph_total,
        "SSTKF": sstkf,
        "controlled TKF": ctrl,
        "TKF-FM": ftkf,
        "PBTKF-IMSF": ptkf,
        "chain LMMSE (delay)": chain,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=1_000_000)
    ap.add_argument("--smoke", action="store_true", help="2000 steps")
    ap.add_argument("--only", default="", help="comma-separated estimator names")
    args = ap.parse_args()
    steps = 2000 if args.smoke else args.steps
    only = {o.strip() for o in args.only.split(",") if o.strip()}
    print(f"one run of {steps:,} steps per estimator")
    print(
        f"{'estimator':28s} {'steps/s':>10s} {'finite':>7s} {'sym':>5s} {'PSD':>5s} {'min eig/scale':>14s} "
        f"{'max |err|':>10s} {'wall s':>7s} {'user s':>7s} {'sys s':>6s}"
    )
    for name, fn in cases(steps).items():
        if only and name not in only:
            continue
        sample, (mean, cov, truth) = _timing.measure(fn)
        h = health(mean, cov, truth)
        print(
            f"{name:28s} {steps / sample.wall:10,.0f} {str(h['finite']):>7s} {str(h['symmetric']):>5s} "
            f"{str(h['psd']):>5s} {h['min_eig_rel']:14.2e} {h['max_abs_error']:10.3g} {sample.wall:7.2f} "
            f"{sample.user:7.2f} {sample.sys:6.2f}",
            flush=True,
        )


if __name__ == "__main__":
    main()
