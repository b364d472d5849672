"""The core TKF and KF with the whole step vectorised over the runs against the compiled loop and the fused kernel.

Data and system: those of ``bench_limit.py`` (the n = 2 oscillator, m = 1, left-censored at 0, simulated from the
model). Contestants, all on one thread, all writing into output arrays allocated and touched before the timings
(compute only; what the output pool and a user's loop add is ``bench_limit.py``'s subject):

* the structure-of-arrays step (``tobitkf.filters._compiled_soa``), means only and means + covariances;
* the KF with two channels (the oscillator read through both components, the joint update), means only and
  means + covariances, both ways;
* the TKF and the KF with m channels and n states (``--mn``, the joint update; groups ``tkfm``, the TKF with every
  channel left-censored at 0, ``tkfmw``, the TKF with every channel in the window [-0.5, 0.5], and ``kfm``): a
  rotation of the first two states, the others decaying, channel l reading state l mod n (plus half of the next
  one from l = n on), means only and means + covariances, both ways;
* the compiled loop's TKF entry (``tobitkf.filters._compiled_entries.tobit_loop``: the block path the filters
  run today), the same two output sets, and the KF through both, means only;
* the TKF with two finite limits (the same readings clipped to a window, the split step), means only, both ways;
* the censored assumed-density filter (two finite limits) with its log-likelihood and P(uncensored), both ways
  (``soa_censored_loop`` against ``compiled_loop``), means and the two extras;
* the hand-fused scalar numba TKF (``benchmarks/_fused_tkf.py``, one run at a time, means + covariances: the
  yardstick of ``bench_limit.py``).

Each contestant runs ``--repeat`` times, interleaved (every round calls each once, in an order shuffled every
round, seeded), after one untimed call (compilation). Printed per contestant: the median and the spread
(min-max) of the thread CPU time and of the wall time per run-step, and the ratio of medians (CPU time) of
the fused kernel over it (> 1 = faster than the fused kernel); the machine's load average before and after,
since the machine is shared.

Run by hand::

    PYTHONPATH=src python benchmarks/bench_simd.py            # about a minute on an idle machine
    PYTHONPATH=src python benchmarks/bench_simd.py --smoke    # seconds (CI)
    PYTHONPATH=src python benchmarks/bench_simd.py --which tkfm --mn 2x2,3x2 --sizes 20000x100 --repeat 7
"""

from __future__ import annotations

import argparse
import os
import random
import statistics
import time

import numpy as np

import _timing  # noqa: F401 (prints the process's wall, user and system time at exit)
import tobitkf as tk
from tobitkf.filters._backend import numba_available


def _load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def _system_mn(m: int, n: int) -> tuple[tk.LinearSystem, np.ndarray, np.ndarray, np.ndarray]:
    """n states (a slow rotation of the first two, the others decaying, each fed by the one before), read through m
    channels: channel l reads state l mod n, from l = n on plus half of the next state; noise variances 0.1, 0.2,
    0.15."""
    A = np.zeros((n, n))
    if n == 1:
        A[0, 0] = 0.95
    else:
        w = 0.05
        A[:2, :2] = [[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]]
        for i in range(2, n):
            A[i, i], A[i, i - 1] = 0.9, 0.1
    C = np.zeros((m, n))
    for l in range(m):
        C[l, l % n] = 1.0
        if l >= n:
            C[l, (l + 1) % n] += 0.5
    R = np.diag([0.1, 0.2, 0.15][:m])
    sys_ = tk.LinearSystem(A=A, C=C, Q=0.01 * np.eye(n), R=R, x0=np.zeros(n), P0=0.05 * np.eye(n))
    return sys_, A, C, R


def _groups_mn(runs: int, steps: int, mn: list[tuple[int, int]], which: set[str]) -> dict:
    """The contestants of the groups ``tkfm``, ``tkfmw`` and ``kfm`` for each (m, n) of ``mn``: the runs-vectorised
    step against the compiled loop, means only and means + covariances, outputs allocated and touched here."""
    from tobitkf.filters._compiled_entries import kalman_loop, tobit_loop
    from tobitkf.filters._compiled_soa import soa_kalman_loop, soa_tobit_loop

    out = {}
    N, T = runs, steps
    for m, n in mn:
        sys_, A, C, Rm = _system_mn(m, n)
        Q = 0.01 * np.eye(n)
        H = np.ascontiguousarray(C[None])
        sig = np.sqrt(np.diag(Rm))[None].copy()
        x0 = np.zeros((N, n))
        P0 = np.ascontiguousarray(np.broadcast_to(0.05 * np.eye(n), (N, n, n)))
        bu, du = np.empty((N, 0, n)), np.empty((N, 0, m))
        e_m, e_c, e_y = np.empty((N, 0, n)), np.empty((N, 0, n, n)), np.empty((N, 0, m))
        means, covs = np.zeros((N, T, n)), np.zeros((N, T, n, n))
        xl, Pl = np.empty((N, n)), np.empty((N, n, n))
        tag = f"m={m} n={n}"
        if "tkfm" in which or "tkfmw" in which:
            lat = np.ascontiguousarray(tk.simulate(sys_, steps, runs, seed=2).y, dtype=float)
        for g, (lo_v, hi_v) in (("tkfm", (0.0, np.inf)), ("tkfmw", (-0.5, 0.5))):
            if g not in which:
                continue
            lo, hi = np.full((1, m), lo_v), np.full((1, m), hi_v)
            y = np.ascontiguousarray(np.clip(lat, lo_v, hi_v))
            name = "TKF" if g == "tkfm" else "TKF win"
            for label, fn in (("SoA", soa_tobit_loop), ("loop", tobit_loop)):
                for what, cov in (("means only", e_c), ("mean+cov", covs)):
                    out[f"{label} {name} {tag}, {what}"] = (
                        lambda fn=fn, y=y, lo=lo, hi=hi, cov=cov, A=A, Q=Q, H=H, sig=sig, bu=bu, du=du, x0=x0, P0=P0,
                        means=means, e_m=e_m, e_c=e_c, e_y=e_y, xl=xl, Pl=Pl: fn(
                            y, A, Q, H, sig, lo, hi, bu, du, 0, False, x0, P0, means, cov, e_m, e_c, e_y, e_y, xl, Pl
                        )
                    )  # fmt: skip
        if "kfm" in which:
            yk = np.ascontiguousarray(tk.simulate(sys_, steps, runs, seed=3).y, dtype=float)
            R = Rm[None].copy()
            for label, fn in (("SoA", soa_kalman_loop), ("loop", kalman_loop)):
                for what, cov in (("means only", e_c), ("mean+cov", covs)):
                    out[f"{label} KF {tag}, {what}"] = (
                        lambda fn=fn, yk=yk, cov=cov, A=A, Q=Q, H=H, R=R, x0=x0, P0=P0, means=means, e_m=e_m,
                        e_c=e_c, xl=xl, Pl=Pl: fn(yk, A, Q, H, R, False, x0, P0, means, cov, e_m, e_c, xl, Pl)
                    )  # fmt: skip
    return out


def case(runs: int, steps: int, repeat: int, which: set[str], mn: list[tuple[int, int]]) -> None:
    from _fused_tkf import fused_tkf
    from tobitkf.filters._compiled_entries import kalman_loop, tobit_loop
    from tobitkf.filters._compiled_loop import compiled_loop
    from tobitkf.filters._compiled_moments import CENSORED, kind
    from tobitkf.filters._compiled_soa import soa_censored_loop, soa_kalman_loop, soa_tobit_loop

    w = 0.05
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    sys_ = tk.LinearSystem(A=A, C=[[1.0, 0.0]], Q=0.01 * np.eye(2), R=[[0.1]], x0=[0.0, 0.0], P0=0.05 * np.eye(2))
    cens = tk.Censoring(lower=0.0)
    y = np.ascontiguousarray(tk.simulate(sys_, steps, runs, censoring=cens, seed=0).y, dtype=float)
    n, N, T = 2, runs, steps
    Q = np.ascontiguousarray(sys_.process_cov(0))
    H = np.array([[[1.0, 0.0]]])
    sig = np.array([[np.sqrt(0.1)]])
    R = np.array([[[0.1]]])
    lo, hi = np.zeros((1, 1)), np.full((1, 1), np.inf)
    x0 = np.zeros((N, n))
    P0 = np.ascontiguousarray(np.broadcast_to(0.05 * np.eye(n), (N, n, n)))
    bu, du = np.empty((N, 0, n)), np.empty((N, 0, 1))
    e_m, e_c, e1 = np.empty((N, 0, n)), np.empty((N, 0, n, n)), np.empty((N, 0, 1))
    means, covs = np.zeros((N, T, n)), np.zeros((N, T, n, n))  # touched once, here
    xl, Pl = np.empty((N, n)), np.empty((N, n, n))
    y2 = np.ascontiguousarray(y[:, :, 0])
    print(f"\n{runs} runs x {steps} steps, n=2, m=1, censored fraction {np.mean(y <= 0.0):.2f}")

    def tkf(fn, cov):
        return lambda: fn(y, A, Q, H, sig, lo, hi, bu, du, 0, False, x0, P0, means, cov, e_m, e_c, e1, e1, xl, Pl)

    def kf(fn):
        return lambda: fn(y, A, Q, H, R, False, x0, P0, means, e_c, e_m, e_c, xl, Pl)

    # two finite limits: the window [-0.5, 0.5] (about a third of the readings at a limit)
    lo2, hi2 = np.full((1, 1), -0.5), np.full((1, 1), 0.5)
    yw = np.clip(y, -0.5, 0.5)
    pu, ll = np.zeros((N, T, 1)), np.zeros((N, T))
    cls0 = np.empty((N, 0, 1), dtype=np.int8)

    def tkf2(fn):
        return lambda: fn(yw, A, Q, H, sig, lo2, hi2, bu, du, 0, False, x0, P0, means, e_c, e_m, e_c, e1, e1, xl, Pl)

    def adf(fn):
        return lambda: fn(
            kind(CENSORED), yw, cls0, A[None, None], Q[None, None], H, np.zeros((1, 1, 0, n)), R, lo2[None], hi2[None],
            np.zeros((1, 1, 0)), 0, 1, 0, False, bu, du, x0, P0, means, e_c, e_m, e_c, pu, e1, ll,
            np.empty((N, 0, 1, 0)), xl, Pl,
        )  # fmt: skip

    # the KF with two channels (the joint update): the oscillator read through both components
    sys2 = tk.LinearSystem(
        A=A, C=np.eye(2), Q=0.01 * np.eye(2), R=np.diag([0.1, 0.2]), x0=[0.0, 0.0], P0=0.05 * np.eye(2)
    )
    y_2 = np.ascontiguousarray(tk.simulate(sys2, steps, runs, seed=1).y, dtype=float)
    H2, R2 = np.eye(2)[None], np.diag([0.1, 0.2])[None]

    def kf2(fn, cov):
        return lambda: fn(y_2, A, Q, H2, R2, False, x0, P0, means, cov, e_m, e_c, xl, Pl)

    groups = {
        "tkf": {
            "SoA TKF, means only": tkf(soa_tobit_loop, e_c),
            "SoA TKF, mean+cov": tkf(soa_tobit_loop, covs),
            "compiled loop TKF, means only": tkf(tobit_loop, e_c),
            "compiled loop TKF, mean+cov": tkf(tobit_loop, covs),
        },
        "kf": {"SoA KF, means only": kf(soa_kalman_loop), "compiled loop KF, means only": kf(kalman_loop)},
        "kf2": {
            "SoA KF m=2, means only": kf2(soa_kalman_loop, e_c),
            "loop KF m=2, means only": kf2(kalman_loop, e_c),
            "SoA KF m=2, mean+cov": kf2(soa_kalman_loop, covs),
            "loop KF m=2, mean+cov": kf2(kalman_loop, covs),
        },
        "tkf2": {"SoA TKF 2-sided, means only": tkf2(soa_tobit_loop), "loop TKF 2-sided, means only": tkf2(tobit_loop)},
        "adf": {
            "SoA ADF 2-sided, mean+extras": adf(soa_censored_loop),
            "loop ADF 2-sided, mean+extras": adf(compiled_loop),
        },
    }
    contestants = {k: v for g, c in groups.items() if g in which for k, v in c.items()}
    contestants.update(_groups_mn(runs, steps, mn, which))
    contestants["hand-fused TKF, mean+cov"] = lambda: fused_tkf(
        y2, A, Q, H[0, 0], 0.1**0.5, 0.0, x0[0], P0[0], means, covs
    )
    for fn in contestants.values():
        fn()  # compilation, first touch
    cpu: dict[str, list[float]] = {k: [] for k in contestants}
    wall: dict[str, list[float]] = {k: [] for k in contestants}
    order = list(contestants)
    rng = random.Random(0)
    print(f"load average before: {_load()}")
    for _ in range(repeat):
        rng.shuffle(order)
        for name in order:
            t0, c0 = time.perf_counter(), time.thread_time()
            contestants[name]()
            c1, t1 = time.thread_time(), time.perf_counter()
            cpu[name].append((c1 - c0) / (N * T) * 1e9)
            wall[name].append((t1 - t0) / (N * T) * 1e9)
    print(f"load average after:  {_load()}")
    ref = statistics.median(cpu["hand-fused TKF, mean+cov"])
    print(f"{'contestant':32s} {'CPU ns/run-step (min-max)':>28s} {'wall ns/run-step (min-max)':>28s} {'fused/it':>9s}")
    for name in contestants:
        c, wl = cpu[name], wall[name]
        mc, mw = statistics.median(c), statistics.median(wl)
        print(
            f"{name:32s} {mc:10.1f} ({min(c):6.1f}-{max(c):6.1f}) {mw:10.1f} ({min(wl):6.1f}-{max(wl):6.1f}) "
            f"{ref / mc:8.2f}x"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="tiny sizes for CI")
    ap.add_argument("--repeat", type=int, default=5, help="timed calls per contestant (default 5)")
    ap.add_argument(
        "--which",
        default="tkf,kf,kf2,tkf2,adf,tkfm",
        help="contestant groups, comma-separated: tkf, kf, kf2, tkf2, adf, tkfm, tkfmw, kfm (default all but the last "
        "two)",
    )
    ap.add_argument("--sizes", default="100000x100,10000x1000", help="runs x steps, comma-separated")
    ap.add_argument("--mn", default="2x2", help="channels x states of the groups tkfm, tkfmw, kfm (default 2x2)")
    args = ap.parse_args()
    mn = [tuple(int(v) for v in c.split("x")) for c in args.mn.split(",")]
    if not numba_available():
        print("numba is not installed: nothing to measure")
        return
    sizes = [tuple(int(v) for v in c.split("x")) for c in args.sizes.split(",")]
    cases = sizes if not args.smoke else [(300, 20)]
    for runs, steps in cases:
        case(runs, steps, args.repeat if not args.smoke else 2, set(args.which.split(",")), mn)  # type: ignore[arg-type]


if __name__ == "__main__":
    main()
