"""Benchmark of the TKF-FM (Geng et al. 2017): steps per second over many runs, cost against L.

Run by hand::

    PYTHONPATH=src python benchmarks/bench_fading.py            # 10^4 runs, 50 steps, L = 0, 2, 5
    PYTHONPATH=src python benchmarks/bench_fading.py --smoke    # tiny version (seconds)

Prints, for the oscillator model of the source (n = 2, m = 1, censoring at 0):
* run-steps per second (runs x steps / wall time) of the TKF-FM for L = 0, 2, 5, of the
  core TKF (the source's comparator) and of the augmented KF baseline (kf-fm);
* the cost per run-step against n_xi = n(L+1), with the log-log slope, to compare with the
  O[(n(L+1))^3] of Remark 10 (the prediction here uses the shift structure of the augmented
  A, so only the Joseph update and the batched solves are cubic);
* a per-run Python loop with filterpy's KalmanFilter on the augmented model (no censoring
  handling, so the work of kf-fm) when filterpy is installed, as the "write it by hand" reference;
* the compiled (numba) TKF-FM against its numpy path at the size of the geng2017 experiment
  (M = 1000 runs, 100 steps, L = 2; ``--smoke``: 200 runs, 20 steps) for each covered option set,
  and the time per step of one run through ``filter`` (``--single-steps`` steps).
"""

from __future__ import annotations

import os

# single-core numbers: the numpy path's BLAS on one thread, as the compiled loops run
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

import tobitkf as tk  # noqa: E402
from _timing import best_time  # noqa: E402
from tobitkf.channels.fading import RiceFading  # noqa: E402
from tobitkf.filters.fading import FadingKalmanFilter, FadingTobitKalmanFilter, augmented_measurement_matrix  # noqa: E402

MEANS = [0.95, 0.75, 0.85, 0.8, 0.7, 0.6]
VARS = [0.0081, 0.0064, 0.0049, 0.004, 0.004, 0.004]


def oscillator() -> tk.LinearSystem:
    w = 0.052 * np.pi
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    return tk.LinearSystem(A=A, C=[[1.0, 0.0]], Q=0.0025 * np.eye(2), R=[[1.0]], x0=[5.0, 0.0], P0=np.eye(2))


def timed(fn, repeat: int) -> float:
    """Best CPU time (``process_time``) of ``repeat`` calls: robust on a machine shared with other jobs."""
    return best_time(fn, repeat, cpu=True)


def filterpy_loop(system, fading, y, runs: int) -> float | None:
    try:
        from filterpy.kalman import KalmanFilter as FPKalman
    except ImportError:  # pragma: no cover
        return None
    n, L = system.n, fading.order
    nxi = n * (L + 1)
    Aa = np.zeros((nxi, nxi))
    Aa[:n, :n] = system.A.at(0)
    for i in range(1, L + 1):
        Aa[i * n : (i + 1) * n, (i - 1) * n : i * n] = np.eye(n)
    Qa = np.zeros((nxi, nxi))
    Qa[:n, :n] = system.process_cov(0)
    Hs = [augmented_measurement_matrix(system, fading, k) for k in range(1, y.shape[1] + 1)]
    t0 = time.process_time()
    for r in range(runs):
        kf = FPKalman(dim_x=nxi, dim_z=1)
        kf.F, kf.Q, kf.R = Aa, Qa, system.R.at(1)
        kf.x = np.zeros(nxi)
        kf.x[:n] = system.x0
        kf.P = np.zeros((nxi, nxi))
        kf.P[:n, :n] = system.P0
        for k in range(y.shape[1]):
            kf.predict()
            kf.update(y[r, k], H=Hs[k])
    return time.process_time() - t0


def compiled_vs_numpy(system: tk.LinearSystem, runs: int, steps: int, single: int, repeat: int) -> None:
    """Compiled (numba) TKF-FM against its numpy path (L = 2, censoring at 0), and one run's time per step."""
    from tobitkf.filters._backend import numba_available

    if not numba_available():
        print("compiled TKF-FM: numba not installed, skipped")
        return
    cens = tk.Censoring(lower=0.0)
    fad = RiceFading.gaussian(2, MEANS[:3], VARS[:3])
    y = tk.simulate(system, steps, runs, censoring=cens, measurement=fad, seed=1).y
    y1 = tk.simulate(system, single, 1, censoring=cens, measurement=fad, seed=2).y[0]
    print(f"compiled TKF-FM (L=2, n_xi=6) vs numpy, {runs} runs x {steps} steps, best CPU time of {repeat}")
    print(f"{'options':<34}{'numpy s':>9}{'numba s':>9}{'ratio':>8}{'1 run us/step':>15}")
    for opts in ({}, {"exact_tobit_variance": True}, {"covariance_update": "standard"}):
        fn = FadingTobitKalmanFilter(system, fad, cens, backend="numpy", **opts)
        fc = FadingTobitKalmanFilter(system, fad, cens, backend="numba", **opts)
        fc.filter(y[:2, :3])  # compile (or load the cache) outside the timing
        t_np = timed(lambda: fn.filter(y), repeat)  # noqa: B023
        t_nb = timed(lambda: fc.filter(y), max(repeat, 3))  # noqa: B023
        t_1 = timed(lambda: fc.filter(y1), max(repeat, 3))  # noqa: B023
        label = ", ".join(f"{k}={v}" for k, v in opts.items()) or "default (joseph, eq. (12))"
        print(f"{label:<34}{t_np:>9.3g}{t_nb:>9.3g}{t_np / t_nb:>8.1f}{1e6 * t_1 / single:>15.3g}")
    fn = FadingTobitKalmanFilter(system, fad, cens, backend="numpy")
    fc = FadingTobitKalmanFilter(system, fad, cens, backend="numba")
    t_np = timed(lambda: fn.filter(y, outputs=("mean",)), repeat)
    t_m = timed(lambda: fc.filter(y, outputs=("mean",)), max(repeat, 3))
    t_1m = timed(lambda: fc.filter(y1, outputs=("mean",)), max(repeat, 3))
    print(f"{'default, outputs=(mean,)':<34}{t_np:>9.3g}{t_m:>9.3g}{t_np / t_m:>8.1f}{1e6 * t_1m / single:>15.3g}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--smoke", action="store_true", help="tiny version: 200 runs, 20 steps")
    parser.add_argument("--runs", type=int, default=10_000)
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--orders", type=int, nargs="+", default=[0, 2, 5])
    parser.add_argument("--compiled-runs", type=int, default=1000, help="runs of the compiled/numpy comparison")
    parser.add_argument("--compiled-steps", type=int, default=100, help="steps of the compiled/numpy comparison")
    parser.add_argument("--single-steps", type=int, default=2000, help="steps of the one-run timing")
    parser.add_argument("--compiled-only", action="store_true", help="only the compiled/numpy comparison")
    args = parser.parse_args()
    if args.smoke:
        args.compiled_runs, args.compiled_steps, args.single_steps = 200, 20, 500
    compiled_vs_numpy(oscillator(), args.compiled_runs, args.compiled_steps, args.single_steps, 1 if args.smoke else 3)
    if args.compiled_only:
        return
    runs, steps, repeat = (200, 20, 1) if args.smoke else (args.runs, args.steps, 3)
    system = oscillator()
    cens = tk.Censoring(lower=0.0)
    print(f"TKF-FM benchmark: oscillator (n=2, m=1), {runs} runs x {steps} steps, best CPU time of {repeat}")
    print(f"{'estimator':<16}{'L':>3}{'n_xi':>6}{'run-steps/s':>14}{'us/run-step':>13}{'vs TKF':>9}")
    fad0 = RiceFading.gaussian(0, [1.0], 0.0)
    y0 = tk.simulate(system, steps, runs, censoring=cens, measurement=fad0, seed=0).y
    tk.TobitKalmanFilter(system, cens).filter(y0[:2, :3])  # compile (or load) the kernel outside the timing
    t_tkf = timed(lambda: tk.TobitKalmanFilter(system, cens).filter(y0), repeat)
    work = runs * steps
    print(f"{'tkf (core)':<16}{0:>3}{2:>6}{work / t_tkf:>14.3g}{1e6 * t_tkf / work:>13.3g}{1.0:>9.2f}")
    sizes, costs = [], []
    for L in args.orders:
        fad = RiceFading.gaussian(
            L,
            MEANS[: L + 1] if L < len(MEANS) else [0.9] * (L + 1),
            VARS[: L + 1] if L < len(VARS) else [0.004] * (L + 1),
        )
        y = tk.simulate(system, steps, runs, censoring=cens, measurement=fad, seed=L).y
        t = timed(lambda: FadingTobitKalmanFilter(system, fad, cens).filter(y), repeat)
        t_kf = timed(lambda: FadingKalmanFilter(system, fad).filter(y), repeat)
        nxi = 2 * (L + 1)
        sizes.append(nxi)
        costs.append(t / work)
        print(f"{'tkf-fm':<16}{L:>3}{nxi:>6}{work / t:>14.3g}{1e6 * t / work:>13.3g}{t / t_tkf:>9.2f}")
        print(f"{'kf-fm':<16}{L:>3}{nxi:>6}{work / t_kf:>14.3g}{1e6 * t_kf / work:>13.3g}{t_kf / t_tkf:>9.2f}")
        if L == 2:
            few = min(runs, 20)
            t_fp = filterpy_loop(system, fad, y, few)
            if t_fp is not None:
                per = t_fp / (few * steps)
                print(
                    f"{'filterpy loop':<16}{L:>3}{nxi:>6}{1 / per:>14.3g}{1e6 * per:>13.3g}{per * work / t_tkf:>9.2f}"
                    f"   (per-run Python loop, {few} runs; kf-fm is {per * work / t_kf:.0f}x faster)"
                )
    if len(sizes) >= 2:
        slope = np.polyfit(np.log(sizes), np.log(costs), 1)[0]
        ratios = ", ".join(
            f"L={L}: {c / costs[0]:.2f}x (cubic law {(s / sizes[0]) ** 3:.0f}x)"
            for L, s, c in zip(args.orders, sizes, costs)
        )
        print(f"cost per run-step relative to L={args.orders[0]}: {ratios}")
        print(
            f"log-log slope of cost against n_xi = n(L+1): {slope:.2f} (Remark 10 states O[(n(L+1))^3]; at these "
            "sizes the batched numpy calls are dominated by per-call overhead and O(n_xi^2) memory traffic)"
        )


if __name__ == "__main__":
    main()
