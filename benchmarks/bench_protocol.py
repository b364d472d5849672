"""Protocol-based TKF benchmark: PBTKF-IMSF (batched) against filterpy on the same augmented data.

Data: the example of Geng et al. (spec 003 §3.1): n = 2, p = 2 sensors under Round-Robin,
integral window ell = 2 (augmented state of size 6), failure law {0, 0.5, 1}, tau = 0.

(a) many runs: 10^4 runs x 100 steps. tobitkf runs batched over runs (every failure-term
    mode, and the bounds recursion once); filterpy's KalmanFilter on the augmented model
    (no Tobit or failure terms, so it does less work per step) is looped over a subset of
    runs and scaled: run-steps/second and ratios to filterpy.
(b) one run of 10^4 steps: microseconds per step (online latency).
(c) the compiled time loop (backend="numba", :mod:`tobitkf.filters._compiled_loop`) against the
    numpy reference path (backend="numpy") and against the numpy loop around the compiled shared step
    (the default before the loop existed), 1000 runs x 100 steps, each failure-term mode, Joseph form:
    median of ``repeat`` interleaved calls (min-max), ns per run-step, and the load average.

(a) and (b) run the default backend ("auto"), i.e. the compiled loop where numba imports.
``--smoke`` runs a tiny version, ``--only-compiled`` only (c). Run by hand:
PYTHONPATH=src python benchmarks/bench_protocol.py
"""

from __future__ import annotations

import os

# single-core numbers: the numpy path's BLAS on one thread, as the compiled loops run
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

import tobitkf as tk  # noqa: E402
from _timing import best_time  # noqa: E402
from tobitkf.channels.protocol import LAMBDA_BASE, ProtocolChannel  # noqa: E402
from tobitkf.design.protocol_bounds import protocol_covariance_bounds  # noqa: E402
from tobitkf.filters._backend import numba_available  # noqa: E402
from tobitkf.filters.protocol import ProtocolTobitKalmanFilter, protocol_tobit_kalman_filter  # noqa: E402
from tobitkf.filters.protocol_model import FAILURE_TERMS, augmented_transition, noise_input, stacked_measurement  # noqa: E402


def make_problem():
    w = 0.052 * np.pi
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    sys_ = tk.LinearSystem(A=A, C=np.eye(2), Q=0.0025 * np.eye(2), R=np.eye(2), x0=[5.0, 0.0], P0=np.eye(2))
    return sys_, ProtocolChannel(2, window=2, failures=LAMBDA_BASE, threshold=0.0)


def filterpy_runs(sys_, ch, y: np.ndarray) -> None:
    """filterpy's KF on the augmented model, H switching with the Round-Robin schedule."""
    from filterpy.kalman import KalmanFilter as FKF

    ell = ch.window
    F = augmented_transition(sys_.transition(0), ell)
    B = noise_input(2, ell)
    Hs = [(0.9 * stacked_measurement(sys_.measurement(1)[h], ell))[None, :] for h in range(2)]
    sched = ch.schedule.scheduled(y.shape[1]) - 1
    for run in y:
        f = FKF(dim_x=F.shape[0], dim_z=1)
        f.F, f.Q, f.R = F, B @ sys_.process_cov(0) @ B.T, np.eye(1)
        f.x, f.P = np.tile(sys_.x0, ell + 1).reshape(-1, 1), np.eye(F.shape[0])
        for k, z in enumerate(run[:, 0]):
            f.predict()
            f.update(z, H=Hs[sched[k]])


def compiled_loop(smoke: bool) -> None:
    """(c): the compiled loop against the numpy paths, median of interleaved repeats."""
    runs, steps, repeat = (50, 20, 3) if smoke else (1000, 100, 7)
    sys_, ch = make_problem()
    y = tk.simulate(sys_, steps, runs, seed=2, channel=ch).y
    print(
        f"(c) compiled loop: {runs} runs x {steps} steps, n_xi=6, censored fraction {np.mean(y <= 0):.2f}, "
        f"median of {repeat} interleaved (min-max), ns per run-step; load {os.getloadavg()[0]:.2f}"
    )
    if not numba_available():
        print("  numba not installed: skipped")
        return
    for mode in FAILURE_TERMS:
        ests = {
            "numba": ProtocolTobitKalmanFilter(sys_, ch, failure_term=mode, backend="numba"),
            "numpy": ProtocolTobitKalmanFilter(sys_, ch, failure_term=mode, backend="numpy"),
            "core": ProtocolTobitKalmanFilter(sys_, ch, failure_term=mode, backend="auto"),
        }
        ests["core"]._compiled_static = False  # the numpy loop around the compiled shared step
        times: dict[str, list[float]] = {be: [] for be in ests}
        for est in ests.values():
            est.filter(y[:2, :3])  # compile / warm up outside the timings
        for _ in range(repeat):
            for be, est in ests.items():
                t0 = time.perf_counter()
                est.filter(y)
                times[be].append((time.perf_counter() - t0) / (runs * steps) * 1e9)
        med = {be: statistics.median(ts) for be, ts in times.items()}
        spread = "  ".join(f"{be} {med[be]:7.0f} ({min(ts):.0f}-{max(ts):.0f})" for be, ts in times.items())
        print(
            f"  {mode:20s} {spread}   numpy/numba x{med['numpy'] / med['numba']:.1f}, "
            f"core/numba x{med['core'] / med['numba']:.1f}"
        )
    print(f"  load after {os.getloadavg()[0]:.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="tiny sizes")
    ap.add_argument("--only-compiled", action="store_true", help="only (c), the compiled loop against numpy")
    args = ap.parse_args()
    if args.only_compiled:
        compiled_loop(args.smoke)
        return
    runs, steps, long_steps, peer_runs, repeat = (10_000, 100, 10_000, 20, 2)
    if args.smoke:
        runs, steps, long_steps, peer_runs, repeat = (200, 50, 500, 2, 1)
    sys_, ch = make_problem()
    y = tk.simulate(sys_, steps, runs, seed=0, channel=ch).y
    print(f"(a) {runs} runs x {steps} steps, n_xi=6, censored fraction {np.mean(y <= 0):.2f}")
    t_fp = best_time(lambda: filterpy_runs(sys_, ch, y[:peer_runs]), repeat) / (peer_runs * steps)
    rows = [("filterpy KalmanFilter, augmented (looped)", 1.0 / t_fp)]
    for mode in FAILURE_TERMS:
        t = best_time(lambda: protocol_tobit_kalman_filter(sys_, ch, y, failure_term=mode), repeat) / (runs * steps)
        rows.append((f"tobitkf PBTKF-IMSF {mode} (batched)", 1.0 / t))
    for name, rate in rows:
        print(f"  {name:44s} {rate:12.4g} run-steps/s   x{rate * t_fp:8.2f} filterpy")
    t_b = best_time(lambda: protocol_covariance_bounds(sys_, ch, steps), repeat)
    print(f"  bounds recursion (analytic gamma, {steps} steps): {t_b * 1e3:.1f} ms")

    long = tk.simulate(sys_, long_steps, 1, seed=1, channel=ch).y
    print(f"(b) one run x {long_steps} steps: microseconds per step")
    t_fp1 = best_time(lambda: filterpy_runs(sys_, ch, long), 1) / long_steps
    t_1 = best_time(lambda: protocol_tobit_kalman_filter(sys_, ch, long), 1) / long_steps
    for name, t in (("filterpy KalmanFilter, augmented", t_fp1), ("tobitkf PBTKF-IMSF variance", t_1)):
        print(f"  {name:44s} {t * 1e6:10.2f} us/step   filterpy/this = {t_fp1 / t:6.2f}")
    compiled_loop(args.smoke)


if __name__ == "__main__":
    main()
