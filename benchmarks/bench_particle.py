"""Particle filter benchmark: particle-steps per second per core, and memory flat in T.

(a) Throughput: the censored oscillator of Miller Example 3 (n = 2, m = 1, censoring at 0), N runs x
    N_p particles per run, batched; particle-steps / CPU second (best of ``--repeat``; BLAS held to
    one thread, so the figure is per core), for the locally optimal and the bootstrap proposal, and
    for the fading (Geng et al. 2017, n_xi = 6) and protocol (Round-Robin, ell = 2, n_xi = 6) channels.
    The issue's target: >= 1e6 particle-steps/s per core for n = 2, m = 1.
(b) Memory: peak traced allocation (tracemalloc) of ``filter(y, outputs="last")`` for T and 10 T steps:
    the particles are O(N N_p n_x) and nothing grows with T (the ratio should be ~1).

Run by hand::

    PYTHONPATH=src python benchmarks/bench_particle.py            # ~1 minute
    PYTHONPATH=src python benchmarks/bench_particle.py --smoke    # seconds
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import tracemalloc  # noqa: E402

import numpy as np  # noqa: E402

import tobitkf as tk  # noqa: E402
from _timing import best_time  # noqa: E402

TARGET = 1e6


def oscillator(omega: float = 0.05) -> tk.LinearSystem:
    c, s = np.cos(omega), np.sin(omega)
    return tk.LinearSystem(
        A=[[c, -s], [s, c]], C=[[1.0, 0.0]], Q=0.01 * np.eye(2), R=[[0.1]], x0=[0.0, 0.0], P0=0.05 * np.eye(2)
    )


def cases():
    sys_ = oscillator()
    cens = tk.Censoring(lower=0.0)
    w = 0.052 * np.pi
    rot = [[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]]
    fsys = tk.LinearSystem(A=rot, C=[[1.0, 0.0]], Q=0.0025 * np.eye(2), R=[[1.0]], x0=[5.0, 0.0], P0=np.eye(2))
    fad = tk.RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    psys = tk.LinearSystem(A=rot, C=np.eye(2), Q=0.0025 * np.eye(2), R=np.eye(2), x0=[5.0, 0.0], P0=np.eye(2))
    from tobitkf.channels.protocol import LAMBDA_BASE

    ch = tk.ProtocolChannel(2, window=2, failures=LAMBDA_BASE, threshold=0.0)
    return [
        ("censored oscillator, optimal", "n=2 m=1", sys_, cens, {"censoring": cens}, "optimal"),
        ("censored oscillator, bootstrap", "n=2 m=1", sys_, cens, {"censoring": cens}, "prior"),
        (
            "fading L=2, bootstrap",
            "n_xi=6 m=1",
            fsys,
            [fad, tk.Censoring(lower=0.0)],
            {"censoring": tk.Censoring(lower=0.0), "measurement": fad},
            "prior",
        ),
        ("protocol ell=2, optimal", "n_xi=6 m=1", psys, ch, {"channel": ch}, "optimal"),
    ]


def throughput(runs: int, particles: int, steps: int, repeat: int) -> None:
    print(f"(a) throughput: {runs} runs x {particles} particles x {steps} steps (CPU time, BLAS 1 thread)")
    print(f"{'case':<34}{'size':<12}{'particle-steps/s':>18}{'>=1e6':>7}")
    for name, size, sys_, channel, sim_kw, proposal in cases():
        y = tk.simulate(sys_, steps, runs, seed=0, **sim_kw).y
        pf = tk.ParticleFilter(sys_, channel, particles=particles, proposal=proposal, seed=1)
        t = best_time(lambda: pf.filter(y, outputs="mean"), repeat, cpu=True)
        rate = runs * particles * steps / t
        print(f"{name:<34}{size:<12}{rate:18.3g}{'yes' if rate >= TARGET else 'no':>7}", flush=True)


def memory(runs: int, particles: int, steps: int) -> None:
    print(f"(b) memory: peak traced allocation of filter(y, outputs='last'), {runs} runs x {particles} particles")
    sys_, cens = oscillator(), tk.Censoring(lower=0.0)
    peaks = {}
    for T in (steps, 10 * steps):
        y = tk.simulate(sys_, T, runs, censoring=cens, seed=0).y
        pf = tk.ParticleFilter(sys_, cens, particles=particles, seed=1)
        tracemalloc.start()
        pf.filter(y, outputs="last")
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        peaks[T] = peak
        print(f"  T = {T:6d}: peak {peak / 2**20:8.1f} MiB (the readings themselves: {y.nbytes / 2**20:.2f} MiB)")
    print(f"  peak(10 T) / peak(T) = {peaks[10 * steps] / peaks[steps]:.3f}  (flat in T: ~1)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--smoke", action="store_true", help="tiny version (seconds)")
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--particles", type=int, default=10_000)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    if args.smoke:
        throughput(4, 500, 5, 1)
        memory(4, 500, 5)
        return
    throughput(args.runs, args.particles, args.steps, args.repeat)
    memory(args.runs, args.particles // 10, 50)


if __name__ == "__main__":
    main()
