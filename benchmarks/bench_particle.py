"""Particle filter benchmark: particle-steps per second per core, and memory flat in T.

(a) Throughput: the censored oscillator of Miller Example 3 (n = 2, m = 1, censoring at 0), N runs x
    N_p particles per run, batched; particle-steps / CPU second (best of ``--repeat``; BLAS held to
    one thread, so the figure is per core), for the locally optimal and the bootstrap proposal, and
    for the fading (Geng et al. 2017, n_xi = 6) and protocol (Round-Robin, ell = 2, n_xi = 6) channels.
    The issue's target: >= 1e6 particle-steps/s per core for n = 2, m = 1.
(b) Memory: peak traced allocation (tracemalloc) of ``filter(y, outputs="last")`` for T and 10 T steps:
    the particles are O(N N_p n_x) and nothing grows with T (the ratio should be ~1).
(c) The compiled loop against numpy: the censored oscillator (n = 2, m = 1, censoring at 0), µs per
    run-step (CPU time, best of ``--repeat``) of ``ParticleFilter`` on its numpy path and compiled, and of
    a plain vectorised numpy particle filter written here (:func:`plain_filter`, the filter one would
    write by hand), for the optimal and the bootstrap proposal. The target: the compiled optimal
    filter at least 3x the plain one at 10^3 runs x 100 steps x 4,000 particles
    (``--target-runs 1000 --target-steps 100 --target-particles 4000``; the default is smaller).

Run by hand::

    PYTHONPATH=src python benchmarks/bench_particle.py            # ~1 minute
    PYTHONPATH=src python benchmarks/bench_particle.py --smoke    # seconds
    PYTHONPATH=src python benchmarks/bench_particle.py --compiled-only --target-runs 1000 --target-steps 100
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import tracemalloc  # noqa: E402

import numpy as np  # noqa: E402
from scipy.special import log_ndtr, ndtri_exp  # noqa: E402

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


def plain_filter(sys_: tk.LinearSystem, y: np.ndarray, lower: float, particles: int, proposal: str, seed: int):
    """A plain vectorised numpy particle filter for one channel censored below at ``lower`` (n states, m = 1):
    all runs' particles as one (N, Np, n) array, the bootstrap or the locally optimal proposal (a
    truncated-normal draw of the latent reading when censored), log-sum-exp weights, systematic resampling
    when the ESS falls below half the particles. Returns the filtered means (N, T, n)."""
    rng = np.random.default_rng(seed)
    A, Q = sys_.transition(0), sys_.process_cov(0)
    c, r = sys_.measurement(1)[0], float(sys_.measurement_cov(1)[0, 0])
    n, (N, T, _) = A.shape[0], y.shape
    Np = particles
    X = sys_.x0 + rng.standard_normal((N, Np, n)) @ np.linalg.cholesky(sys_.P0).T
    logw = np.full((N, Np), -np.log(Np))
    Lq = np.linalg.cholesky(Q)
    s2 = c @ Q @ c + r
    g = Q @ c / s2
    Lc = np.linalg.cholesky(Q - s2 * np.outer(g, g))
    s, sr = np.sqrt(s2), np.sqrt(r)
    means = np.empty((N, T, n))
    for t in range(T):
        yt = y[:, t, 0][:, None]
        cens = yt <= lower
        if proposal == "optimal":
            M = X @ A.T
            pred = M @ c
            lm = log_ndtr((lower - pred) / s)
            z = np.where(cens, pred + ndtri_exp(np.log(rng.random((N, Np))) + lm) * s, yt)
            inc = np.where(cens, lm, -0.5 * ((yt - pred) / s) ** 2 - np.log(s))
            X = M + (z - pred)[..., None] * g + rng.standard_normal((N, Np, n)) @ Lc.T
        else:
            X = X @ A.T + rng.standard_normal((N, Np, n)) @ Lq.T
            mu = X @ c
            inc = np.where(cens, log_ndtr((lower - mu) / sr), -0.5 * ((yt - mu) / sr) ** 2)
        logw = logw + inc
        top = logw.max(axis=1, keepdims=True)
        W = np.exp(logw - top)
        W /= W.sum(axis=1, keepdims=True)
        logw = np.log(W)
        means[:, t] = np.einsum("rp,rpi->ri", W, X)
        ess = 1.0 / (W * W).sum(axis=1)
        rows = np.flatnonzero(ess < 0.5 * Np)
        if rows.size:
            cw = np.cumsum(W[rows], axis=1)
            cw[:, -1] = 1.0
            pos = (rng.random((rows.size, 1)) + np.arange(Np)) / Np
            idx = np.array([np.searchsorted(cw[i], pos[i]) for i in range(rows.size)])
            X[rows] = np.take_along_axis(X[rows], np.minimum(idx, Np - 1)[..., None], axis=1)
            logw[rows] = -np.log(Np)
    return means


def compiled_vs_numpy(runs: int, particles: int, steps: int, repeat: int, compiled_only: bool = False) -> dict:
    """(c): µs per run-step of the numpy path, the compiled path and the plain numpy filter."""
    import os as _os

    load = _os.getloadavg()[0] if hasattr(_os, "getloadavg") else float("nan")
    print(
        f"(c) compiled vs numpy: censored oscillator n=2 m=1, {runs} runs x {steps} steps x {particles} particles "
        f"(CPU time, best of {repeat}; load average {load:.1f})"
    )
    sys_, cens = oscillator(), tk.Censoring(lower=0.0)
    y = tk.simulate(sys_, steps, runs, censoring=cens, seed=0).y
    rs = runs * steps
    tk.ParticleFilter(sys_, cens, particles=8, backend="numba").filter(y[:1, :2])  # compile (or load the cache)
    print(f"{'proposal':<10}{'numpy path':>14}{'compiled':>12}{'plain numpy':>14}{'vs plain':>10}{'>=3x':>6}")
    out = {}
    for proposal in ("optimal", "prior"):
        times = {}
        for backend in ("numpy", "numba"):
            if backend == "numpy" and compiled_only:
                times[backend] = float("nan")
                continue
            pf = tk.ParticleFilter(sys_, cens, particles=particles, proposal=proposal, seed=1, backend=backend)
            times[backend] = best_time(lambda pf=pf: pf.filter(y, outputs="mean"), repeat, cpu=True) / rs * 1e6
        times["plain"] = (
            best_time(lambda p=proposal: plain_filter(sys_, y, 0.0, particles, p, 1), repeat, cpu=True) / rs * 1e6
        )
        ratio = times["plain"] / times["numba"]
        out[proposal] = dict(times, ratio=ratio)
        print(
            f"{proposal:<10}{times['numpy']:12.1f}µs{times['numba']:10.1f}µs{times['plain']:12.1f}µs{ratio:9.1f}x"
            f"{'yes' if ratio >= 3 else 'no':>6}",
            flush=True,
        )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--smoke", action="store_true", help="tiny version (seconds)")
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--particles", type=int, default=10_000)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--target-runs", type=int, default=20, help="(c): runs (the target: 1000)")
    parser.add_argument("--target-steps", type=int, default=20, help="(c): steps (the target: 100)")
    parser.add_argument("--target-particles", type=int, default=4000, help="(c): particles per run")
    parser.add_argument("--compiled-only", action="store_true", help="(c) only, without the numpy path")
    args = parser.parse_args()
    if args.smoke:
        throughput(4, 500, 5, 1)
        memory(4, 500, 5)
        compiled_vs_numpy(4, 500, 5, 1)
        return
    if args.compiled_only:
        compiled_vs_numpy(args.target_runs, args.target_particles, args.target_steps, args.repeat, True)
        return
    throughput(args.runs, args.particles, args.steps, args.repeat)
    memory(args.runs, args.particles // 10, 50)
    compiled_vs_numpy(args.target_runs, args.target_particles, args.target_steps, args.repeat)


if __name__ == "__main__":
    main()
