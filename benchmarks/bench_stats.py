"""Censored-normal statistics in the compiled path: run by run against the vectorised block.

The compiled path has one implementation of the statistics (``tobitkf.filters._compiled_censored``). A channel
whose runs have their own limits takes ``censored_stats`` run by run (a branch on the limits per run); one
whose lower limit the block's runs share takes ``one_sided_block``, the same route without the per-run
branch, vectorised over the runs. (With the same limit for every run, as timed here, the branch of
``censored_stats`` is the same for every run and its loop vectorises too: both take the same time.) Both are timed here in a compiled loop over 4096 means (the TKF's use:
gamma, the noise term and E(y) of each run), with the standardized limits a = (lower - mean) / sd drawn
uniformly from

* [-3, 3] (the central routes),
* [-10, 40] (72 % of the runs beyond 4 sigma: the tail fits, and the underflowing tail),

CPU time of this thread, median of ``--repeat`` interleaved rounds of 2000 calls each; ns per run.

Run by hand::

    PYTHONPATH=src python benchmarks/bench_stats.py
    PYTHONPATH=src python benchmarks/bench_stats.py --smoke
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np

import _timing  # noqa: F401 (prints the process's wall, user and system time at exit)
from tobitkf.filters._backend import numba_available


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="tiny sizes for CI")
    ap.add_argument("--repeat", type=int, default=7, help="interleaved rounds (default 7)")
    args = ap.parse_args()
    if not numba_available():
        print("numba not installed: nothing to time")
        return
    from numba import njit

    from tobitkf.filters._compiled_censored import GL_W, GL_X, censored_stats, one_sided_block

    @njit(error_model="numpy")
    def per_run(mu, sd, lo, g, v, c, calls):
        buf = np.empty((2, GL_X.shape[0]))
        for _ in range(calls):
            for b in range(mu.shape[0]):
                st = censored_stats(mu[b], sd, lo, np.inf, GL_X, GL_W, buf)
                g[b] = st[2]
                v[b] = st[5]
                c[b] = st[6]

    @njit(error_model="numpy")
    def block(mu, sd, lo, g, v, c, calls):
        for _ in range(calls):
            one_sided_block(mu, sd, lo, False, mu.shape[0], 0, g, v, c)

    size, calls, repeat = (4096, 2000, args.repeat) if not args.smoke else (256, 10, 2)
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(f"{size} runs per call, {calls} calls per round, median of {repeat} rounds (min-max), CPU ns per run")
    for lo_a, hi_a in ((-3.0, 3.0), (-10.0, 40.0)):
        a = np.random.default_rng(0).uniform(lo_a, hi_a, size)
        mu = -a  # sd 1, lower limit 0
        out = [np.empty(size) for _ in range(6)]
        per_run(mu, 1.0, 0.0, *out[:3], 1)
        block(mu, 1.0, 0.0, *out[3:], 1)
        np.testing.assert_allclose(out[3], out[0], rtol=1e-13, atol=1e-300)  # the same gamma
        times: dict[str, list[float]] = {"run by run": [], "vectorised block": []}
        for _ in range(repeat):
            for name, fn, o in (("run by run", per_run, out[:3]), ("vectorised block", block, out[3:])):
                t0 = time.thread_time()
                fn(mu, 1.0, 0.0, *o, calls)
                times[name].append((time.thread_time() - t0) / (calls * size) * 1e9)
        med = {k: statistics.median(v) for k, v in times.items()}
        print(f"\na uniform on [{lo_a:g}, {hi_a:g}] ({np.mean(a > 4):.0%} beyond 4 sigma):")
        for k, v in times.items():
            print(f"  {k:26s} {med[k]:7.1f} ({min(v):.1f}-{max(v):.1f})")
        print(f"  run by run / block: {med['run by run'] / med['vectorised block']:.1f}x")
    print(f"\nload average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
