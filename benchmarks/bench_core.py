"""Core benchmark: KalmanFilter and TobitKalmanFilter against filterpy and pykalman.

The same simulated data (n = 2 oscillator, m = 1, left-censored at 0, about half the
samples censored) goes through every filter:

(a) many runs:  10^4 runs x 10^3 steps, batched for tobitkf; filterpy's KalmanFilter and
    pykalman looped over runs (timed on a subset of runs and scaled: run-steps/second);
(b) one run of 10^5 steps: seconds per step (online latency).

Prints run-steps/second and ratios to filterpy measured in the same process, for both
tobitkf backends: ``numpy`` (the vectorised reference path) and ``numba`` (the compiled
kernels of ``tobitkf.filters._compiled_tobit``, compiled before timing; skipped without numba).
The single-run numpy rows time 10^4 steps (their cost per step is constant).

(c) TKF at n = 16, m = 8 (a random stable system, left-censored at 0 in every channel, 10^3 runs
    x 100 steps): the compiled kernel (``threads=1``) against the numpy path, median of
    ``repeat`` interleaved calls (min-max), all outputs and means only (target: at least 3x); wall time and,
    from ``getrusage`` around each call, user and system CPU time (the system time is mostly the first touch
    of the fresh output pages, ~450 MB a call with all outputs, whose cost on this VM swings by 10x from call
    to call and is paid by both paths alike: the user time is the arithmetic). The compiled path takes its
    outputs from the output pool (its default: the memory of the previous call's freed result); the row
    "numba, pool off" is the same filter writing fresh memory every call.

(d) multi-region TKF (Miller §6.6 Example 3: x_{k+1} = 0.99 x_k + w, one output seen by two sensors with
    the windows (-1.5, -0.1) and (0.1, 1.5), sigma = 0.05; n = 1, m = 2), without and with a control input
    (B^u, D): the compiled kernel (``threads=1``) against the numpy path at the experiment's size (10 runs x
    2000 steps), at 10^4 runs x 100 steps, and one run through ``filter`` (microseconds per step); median of
    ``repeat`` interleaved calls (min-max) (targets: compiled >= 5x numpy, one run <= 5 us per step).

``--smoke`` runs a tiny version (CI). Run by hand:  python benchmarks/bench_core.py
(``--only-m8`` runs (c) alone, ``--only-multi-region`` (d) alone).
"""

from __future__ import annotations

import os

# one thread for everything: the numpy path's BLAS too (without this it ran OpenBLAS's default of one thread
# per core, whose spinning workers showed as user time above the wall time and shared the 2 cores)
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import contextlib  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

import tobitkf as tk  # noqa: E402
from _timing import best_time  # noqa: E402
from tobitkf.filters import _pool  # noqa: E402
from tobitkf.filters._backend import numba_available  # noqa: E402


def make_system() -> tk.LinearSystem:
    w = 0.05
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    return tk.LinearSystem(A=A, C=[[1.0, 0.0]], Q=0.01 * np.eye(2), R=[[0.1]], x0=[0.0, 0.0], P0=0.05 * np.eye(2))


def filterpy_runs(sys_: tk.LinearSystem, y: np.ndarray) -> None:
    from filterpy.kalman import KalmanFilter as FKF

    for run in y:
        f = FKF(dim_x=2, dim_z=1)
        f.F, f.H = sys_.transition(0), sys_.measurement(1)
        f.Q, f.R = sys_.process_cov(0), sys_.measurement_cov(1)
        f.x, f.P = sys_.x0.reshape(2, 1).copy(), sys_.P0.copy()
        for z in run[:, 0]:
            f.predict()
            f.update(z)


def pykalman_runs(sys_: tk.LinearSystem, y: np.ndarray) -> None:
    from pykalman import KalmanFilter as PKF

    pk = PKF(
        transition_matrices=sys_.transition(0),
        observation_matrices=sys_.measurement(1),
        transition_covariance=sys_.process_cov(0),
        observation_covariance=sys_.measurement_cov(1),
        initial_state_mean=sys_.x0,
        initial_state_covariance=sys_.P0,
    )
    for run in y:
        pk.filter(run)


def random_system(n: int, m: int, seed: int = 0) -> tk.LinearSystem:
    """Stable random model: A = 0.95 x orthogonal, C rows of unit scale, R = 0.1 I."""
    rng = np.random.default_rng(seed)
    Qo, _ = np.linalg.qr(rng.standard_normal((n, n)))
    C = rng.standard_normal((m, n)) / np.sqrt(n)
    return tk.LinearSystem(A=0.95 * Qo, C=C, Q=0.05 * np.eye(n), R=0.1 * np.eye(m), x0=np.zeros(n), P0=np.eye(n))


def multichannel(smoke: bool) -> None:
    """(c): TKF n = 16, m = 8, compiled against numpy, median of interleaved repeats."""
    runs, steps, repeat = (50, 20, 3) if smoke else (1000, 100, 5)
    sys_, cens = random_system(16, 8), tk.Censoring(lower=0.0)
    y = tk.simulate(sys_, steps, runs, censoring=cens, seed=1).y
    print(
        f"(c) TKF n=16, m=8: {runs} runs x {steps} steps, censored fraction {np.mean(y <= 0):.2f}, "
        f"median of {repeat} (min-max), ns per run-step; load {os.getloadavg()[0]:.2f}"
    )
    if not numba_available():
        print("  numba not installed: skipped")
        return
    for outputs in ("all", "mean"):
        ests = {be: tk.TobitKalmanFilter(sys_, cens, backend=be, threads=1) for be in ("numba", "numpy")}
        ests["numba, pool off"] = ests["numba"]  # the same filter writing fresh memory (_pool.bypassed)
        times: dict[str, list[float]] = {be: [] for be in ests}
        users: dict[str, list[float]] = {be: [] for be in ests}
        syss: dict[str, list[float]] = {be: [] for be in ests}
        for est in ests.values():
            est.filter(y[:2, :3])  # compile / warm up outside the timings
        work = runs * steps / 1e9
        for _ in range(repeat):
            for be, est in ests.items():
                r0 = resource.getrusage(resource.RUSAGE_SELF)
                t0 = time.perf_counter()
                with _pool.bypassed() if be.endswith("pool off") else contextlib.nullcontext():
                    est.filter(y, outputs=outputs)
                times[be].append((time.perf_counter() - t0) / work)
                r1 = resource.getrusage(resource.RUSAGE_SELF)
                users[be].append((r1.ru_utime - r0.ru_utime) / work)
                syss[be].append((r1.ru_stime - r0.ru_stime) / work)
        med = {be: statistics.median(ts) for be, ts in times.items()}
        umed = {be: statistics.median(ts) for be, ts in users.items()}
        for be, ts in times.items():
            print(
                f"  outputs={outputs:4s} {be:15s} wall {med[be]:8.0f} ({min(ts):.0f}-{max(ts):.0f})  user "
                f"{umed[be]:8.0f} ({min(users[be]):.0f}-{max(users[be]):.0f})  system {statistics.median(syss[be]):6.0f} "
                f"({min(syss[be]):.0f}-{max(syss[be]):.0f})"
            )
        print(
            f"  outputs={outputs:4s} compiled is x{med['numpy'] / med['numba']:.2f} the numpy path in wall time, "
            f"x{umed['numpy'] / umed['numba']:.2f} in user CPU time (target >= 3); pool off: "
            f"x{med['numpy'] / med['numba, pool off']:.2f} wall, x{umed['numpy'] / umed['numba, pool off']:.2f} user"
        )
    print(f"  load after {os.getloadavg()[0]:.2f}")


def multi_region_case(smoke: bool) -> None:
    """(d): multi-region TKF, compiled against numpy, median of interleaved repeats."""
    repeat = 3 if smoke else 7
    sizes = [(4, 50), (50, 20), (1, 200)] if smoke else [(10, 2000), (10_000, 100), (1, 2000)]
    print(
        f"(d) multi-region TKF (Miller 6.6 Example 3, n=1, m=2): median of {repeat} (min-max); load {os.getloadavg()[0]:.2f}"
    )
    if not numba_available():
        print("  numba not installed: skipped")
        return
    for with_input in (False, True):
        extra = {"Bu": [[0.05]], "D": [[0.1]]} if with_input else {}
        base = tk.LinearSystem(A=[[0.99]], C=[[1.0]], Q=[[0.01]], R=[[0.05**2]], x0=[0.0], P0=[[0.01]], **extra)
        sys_, cens = tk.multi_region(base, [[(-1.5, -0.1), (0.1, 1.5)]])
        for runs, steps in sizes:
            u = np.random.default_rng(2).normal(size=(runs, steps, 1)) if with_input else None
            y = tk.simulate(sys_, steps, runs, censoring=cens, inputs=u, seed=1).y
            if runs == 1:
                y, u = y[0], (None if u is None else u[0])  # one run, (T, m), as an online user passes it
            ests = {be: tk.TobitKalmanFilter(sys_, cens, backend=be, threads=1) for be in ("numba", "numpy")}
            for est in ests.values():  # compile / warm up outside the timings
                est.filter(y[..., :3, :], u=None if u is None else u[..., :3, :])
            times: dict[str, list[float]] = {be: [] for be in ests}
            for _ in range(repeat):
                for be, est in ests.items():
                    t0 = time.perf_counter()
                    est.filter(y, u=u)
                    times[be].append((time.perf_counter() - t0) / (runs * steps) * 1e9)
            med = {be: statistics.median(ts) for be, ts in times.items()}
            label = f"{'input' if with_input else 'no input':8s} {runs:>6d} runs x {steps:<5d}"
            for be, ts in times.items():
                print(f"  {label} {be:6s} {med[be]:10.0f} ns/run-step ({min(ts):.0f}-{max(ts):.0f})")
            note = f"; one run: {med['numba'] / 1e3:.2f} us/step (target <= 5)" if runs == 1 else ""
            print(f"  {label} compiled is x{med['numpy'] / med['numba']:.1f} the numpy path (target >= 5){note}")
    print(f"  load after {os.getloadavg()[0]:.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="tiny sizes for CI")
    ap.add_argument("--only-m8", action="store_true", help="only (c), the n = 16, m = 8 TKF")
    ap.add_argument("--only-multi-region", action="store_true", help="only (d), the multi-region TKF")
    args = ap.parse_args()
    if args.only_m8:
        multichannel(args.smoke)
        return
    if args.only_multi_region:
        multi_region_case(args.smoke)
        return
    runs, steps, long_steps, peer_runs, repeat = (10_000, 1_000, 100_000, 20, 2)
    if args.smoke:
        runs, steps, long_steps, peer_runs, repeat = (200, 50, 2_000, 2, 1)
    sys_ = make_system()
    cens = tk.Censoring(lower=0.0)
    data = tk.simulate(sys_, steps, runs, censoring=cens, seed=0)
    y = data.y
    print(f"(a) {runs} runs x {steps} steps, n=2, m=1, censored fraction {np.mean(y <= 0):.2f}")
    rows = []
    import filterpy.kalman  # noqa: F401  (import outside the timings)
    import pykalman  # noqa: F401

    t_fp = best_time(lambda: filterpy_runs(sys_, y[:peer_runs]), repeat) / (peer_runs * steps)
    rows.append(("filterpy KalmanFilter (looped)", 1.0 / t_fp))
    t_pk = best_time(lambda: pykalman_runs(sys_, y[:peer_runs]), repeat) / (peer_runs * steps)
    rows.append(("pykalman KalmanFilter.filter (looped)", 1.0 / t_pk))
    backends = ["numpy"] + (["numba"] if numba_available() else [])
    if "numba" in backends:  # compile (or load the cached machine code) outside the timings
        tk.KalmanFilter(sys_, backend="numba").filter(y[:2, :5])
        tk.TobitKalmanFilter(sys_, cens, backend="numba").filter(y[:2, :5])
    rates = {}
    for be in backends:
        t_kf = best_time(lambda: tk.KalmanFilter(sys_, backend=be).filter(y), repeat) / (runs * steps)
        rows.append((f"tobitkf KalmanFilter (batched, {be})", 1.0 / t_kf))
        t_tkf = best_time(lambda: tk.TobitKalmanFilter(sys_, cens, backend=be).filter(y), repeat) / (runs * steps)
        rows.append((f"tobitkf TobitKalmanFilter (batched, {be})", 1.0 / t_tkf))
        rates[be] = 1.0 / t_tkf
    for name, rate in rows:
        print(f"  {name:44s} {rate:12.4g} run-steps/s   x{rate * t_fp:8.2f} filterpy")

    long = tk.simulate(sys_, long_steps, 1, censoring=cens, seed=1).y
    short = long[:, : min(long_steps, 10_000)]
    print(f"(b) one run x {long_steps} steps: microseconds per step")
    t_fp1 = best_time(lambda: filterpy_runs(sys_, long), 1) / long_steps
    t_pk1 = best_time(lambda: pykalman_runs(sys_, long), 1) / long_steps
    rows = [("filterpy KalmanFilter", t_fp1), ("pykalman KalmanFilter.filter", t_pk1)]
    lat = {}
    for be in backends:
        rec = long if be == "numba" else short
        t_kf1 = best_time(lambda: tk.KalmanFilter(sys_, backend=be).filter(rec), repeat) / rec.shape[1]
        t_tkf1 = best_time(lambda: tk.TobitKalmanFilter(sys_, cens, backend=be).filter(rec), repeat) / rec.shape[1]
        rows += [(f"tobitkf KalmanFilter ({be})", t_kf1), (f"tobitkf TobitKalmanFilter ({be})", t_tkf1)]
        lat[be] = t_tkf1
    for name, t in rows:
        print(f"  {name:44s} {t * 1e6:10.2f} us/step   filterpy/this = {t_fp1 / t:6.2f}")
    best = "numba" if "numba" in backends else "numpy"
    print(
        f"targets: batched TKF >= 30x filterpy: x{rates[best] * t_fp:.1f} ({best}); "
        f"single-run TKF no slower per step than filterpy: {lat[best] * 1e6:.2f} vs {t_fp1 * 1e6:.2f} us/step"
    )
    multichannel(args.smoke)
    multi_region_case(args.smoke)


if __name__ == "__main__":
    main()
