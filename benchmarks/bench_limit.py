"""Core TKF and KF against the speed limit and the peers, in one process on the same data.

Data: the n = 2 oscillator of ``bench_core.py`` (m = 1, left-censored at 0, about half the
samples censored). Cases: 10^5 runs x 100 steps and 10^4 runs x 1000 steps (the long records
drift further into the censored side: more steps need tail statistics). Everything on one
thread (BLAS, our kernels with ``threads=1``, XLA's CPU client single-threaded); means and
covariances written by every contestant (and, for ours, a means-only row):

* tobitkf TKF and KF, compiled kernels (``backend="numba"``) and numpy reference path
  (``backend="numpy"``, timed on a tenth of the runs and scaled: its cost per run-step does
  not grow with the batch). The compiled rows take their outputs from the output pool
  (``tobitkf.filters._pool``: the memory of a previous call's outputs once that result is freed, as in any
  loop of calls; on by default, up to 1 GiB: the all-outputs row's 1.1 GB does not fit and is fresh every
  call); the row "pool off" writes fresh memory in every call, as the fused limit and JAX do;
* a hand-fused scalar numba TKF (``benchmarks/_fused_tkf.py``): the limit, allocating its
  outputs in the call like every other contestant (fresh memory: first-touch page faults
  included), and once more writing into arrays allocated and touched before the timings
  (compute only: the floor no filter that returns new arrays can reach);
* filterpy ``KalmanFilter`` and pykalman ``KalmanFilter.filter`` looped over a few runs and
  scaled (they have no Tobit update: they do a KF's arithmetic);
* JAX ``jit(vmap(lax.scan))`` KF and TKF (closed-form statistics through
  ``jax.scipy.special.ndtr``/``log_ndtr``) when JAX is installed (``pip install .[bench]``);
  skipped with a note otherwise.

Each contestant runs ``--repeat`` times, interleaved (round r times everyone once, in an order
shuffled every round, seeded), after one untimed call (compilation), each timed call after an
untimed pass over a scratch array as large as the case's mean + covariance outputs. Both because a
contestant's time depended on its predecessor, by more than the differences measured: with a fixed
order, the same kernel took 121 or 210 ns per run-step at 10^5 x 100 by position alone (writing
fresh memory is cheap right after a call that freed some, dear after "outputs reused", which
frees none; on this VM the freed pages seem to be handed back to the host after a while). The
scrub alone did not remove that (``--no-scrub`` turns it off);
printed: median ns per run-step, spread (min-max) and the ratio of
medians against the fused limit and against JAX's TKF (> 1 = faster than it). The machine's
load average is printed before and after, since the machine is shared.

Run by hand::

    PYTHONPATH=src python benchmarks/bench_limit.py              # ~3 minutes on an idle machine
    PYTHONPATH=src python benchmarks/bench_limit.py --smoke      # seconds (CI)
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

import tobitkf as tk  # noqa: E402
from tobitkf.filters import _pool  # noqa: E402
from tobitkf.filters._backend import numba_available  # noqa: E402


def make_system() -> tk.LinearSystem:
    w = 0.05
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    return tk.LinearSystem(A=A, C=[[1.0, 0.0]], Q=0.01 * np.eye(2), R=[[0.1]], x0=[0.0, 0.0], P0=0.05 * np.eye(2))


def _load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


# ---- peers --------------------------------------------------------------------------------------


def filterpy_runs(sys_, y):
    from filterpy.kalman import KalmanFilter as FKF

    for run in y:
        f = FKF(dim_x=2, dim_z=1)
        f.F, f.H = sys_.transition(0), sys_.measurement(1)
        f.Q, f.R = sys_.process_cov(0), sys_.measurement_cov(1)
        f.x, f.P = sys_.x0.reshape(2, 1).copy(), sys_.P0.copy()
        for z in run[:, 0]:
            f.predict()
            f.update(z)


def pykalman_runs(sys_, y):
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


def jax_filters(sys_, lower):
    """``(kf, tkf)``: jitted functions of y (N, T) returning (means, covs), or None without JAX."""
    try:
        import jax
    except ImportError:
        return None
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    from jax import lax
    from jax.scipy.special import log_ndtr, ndtr

    A, Q = jnp.asarray(sys_.transition(0)), jnp.asarray(sys_.process_cov(0))
    C, r = jnp.asarray(sys_.measurement(1)[0]), float(sys_.measurement_cov(1)[0, 0])
    sd = float(np.sqrt(r))
    x0, P0 = jnp.asarray(sys_.x0), jnp.asarray(sys_.P0)
    log_sqrt_2pi = 0.5 * float(np.log(2 * np.pi))

    def kf_step(carry, yt):
        x, P = carry
        xp, Pp = A @ x, A @ P @ A.T + Q
        pc = Pp @ C
        K = pc / (C @ pc + r)
        x = xp + K * (yt - C @ xp)
        P = Pp - jnp.outer(K, pc)
        P = 0.5 * (P + P.T)
        return (x, P), (x, P)

    def tkf_step(carry, yt):
        x, P = carry
        xp, Pp = A @ x, A @ P @ A.T + Q
        mu = C @ xp
        a = (lower - mu) / sd
        gam = ndtr(-a)
        lam = jnp.exp(-0.5 * a * a - log_sqrt_2pi - log_ndtr(-a))
        ruu = r * (1.0 + a * lam - lam * lam)
        ey = (1.0 - gam) * lower + gam * (mu + sd * lam)
        pc = Pp @ C
        K = gam * pc / (gam * gam * (C @ pc) + ruu)
        x = xp + K * (yt - ey)
        P = Pp - gam * jnp.outer(K, pc)
        P = 0.5 * (P + P.T)
        return (x, P), (x, P)

    def make(step):
        run = jax.jit(jax.vmap(lambda yr: lax.scan(step, (x0, P0), yr)[1]))
        return lambda yj: jax.block_until_ready(run(yj))

    return make(kf_step), make(tkf_step), jnp.asarray


# ---- the benchmark ------------------------------------------------------------------------------


def case(runs: int, steps: int, repeat: int, peer_runs: int, scrub: bool = True) -> None:
    sys_ = make_system()
    lower = 0.0
    cens = tk.Censoring(lower=lower)
    y = tk.simulate(sys_, steps, runs, censoring=cens, seed=0).y
    y2 = np.ascontiguousarray(y[:, :, 0])
    sub = max(1, runs // 10)
    st = tk.censored_moments(y[:, :, 0] * 0 + 0.0, 1.0, 0.0, np.inf)  # warm the numpy path's imports
    del st
    pre = tk.TobitKalmanFilter(sys_, cens, backend="numpy").filter(y[: min(runs, 500)], outputs=("pred_mean",))
    a = (lower - pre.pred_mean[..., 0]) / np.sqrt(0.1)  # the standardized limit the filter uses
    print(
        f"\n{runs} runs x {steps} steps, n=2, m=1: censored fraction {np.mean(y <= lower):.2f}, "
        f"steps with the prior mean > 4 sd below the limit (tail route) ~{np.mean(a > 4):.3f}"
    )

    A, Q = np.ascontiguousarray(sys_.transition(0)), np.ascontiguousarray(sys_.process_cov(0))
    C, sig = np.ascontiguousarray(sys_.measurement(1)[0]), float(np.sqrt(sys_.measurement_cov(1)[0, 0]))
    x0, P0 = np.ascontiguousarray(sys_.x0), np.ascontiguousarray(sys_.P0)
    contestants: dict[str, tuple] = {}  # name -> (fn, run-steps per call)
    full = runs * steps
    if numba_available():
        from _fused_tkf import fused_tkf

        def fused():
            means, covs = np.empty((runs, steps, 2)), np.empty((runs, steps, 2, 2))
            fused_tkf(y2, A, Q, C, sig, lower, x0, P0, means, covs)
            return means, covs

        reused = (np.zeros((runs, steps, 2)), np.zeros((runs, steps, 2, 2)))  # touched once, here

        def fused_reused():
            fused_tkf(y2, A, Q, C, sig, lower, x0, P0, *reused)
            return reused

        contestants["hand-fused numba TKF (limit)"] = (fused, full)
        contestants["hand-fused, outputs reused (compute)"] = (fused_reused, full)
        tkf = tk.TobitKalmanFilter(sys_, cens, backend="numba", threads=1)
        kf = tk.KalmanFilter(sys_, backend="numba")
        contestants["tobitkf TKF numba, mean+cov"] = (lambda: tkf.filter(y, outputs=("mean", "cov")), full)

        def fresh():
            with _pool.bypassed():  # new memory for the outputs, the pool's buffers left for the other rows
                return tkf.filter(y, outputs=("mean", "cov"))

        contestants["tobitkf TKF numba, mean+cov, pool off"] = (fresh, full)
        contestants["tobitkf TKF numba, all outputs"] = (lambda: tkf.filter(y), full)
        contestants["tobitkf TKF numba, means only"] = (lambda: tkf.filter(y, outputs=("mean",)), full)
        contestants["tobitkf KF numba, mean+cov"] = (lambda: kf.filter(y, outputs=("mean", "cov")), full)
    tkf_np = tk.TobitKalmanFilter(sys_, cens, backend="numpy")
    kf_np = tk.KalmanFilter(sys_, backend="numpy")
    contestants["tobitkf TKF numpy, mean+cov"] = (lambda: tkf_np.filter(y[:sub], outputs=("mean", "cov")), sub * steps)
    contestants["tobitkf KF numpy, mean+cov"] = (lambda: kf_np.filter(y[:sub], outputs=("mean", "cov")), sub * steps)
    contestants["filterpy KalmanFilter (looped)"] = (lambda: filterpy_runs(sys_, y[:peer_runs]), peer_runs * steps)
    try:
        import pykalman  # noqa: F401

        contestants["pykalman KalmanFilter.filter (looped)"] = (
            lambda: pykalman_runs(sys_, y[:peer_runs]),
            peer_runs * steps,
        )
    except ImportError:
        print("  (pykalman not installed: skipped)")
    jx = jax_filters(sys_, lower)
    if jx is None:
        print("  (JAX not installed: skipped; pip install '.[bench]')")
    else:
        jkf, jtkf, to_dev = jx
        yj = to_dev(y2)
        contestants["JAX vmap(lax.scan) TKF"] = (lambda: jtkf(yj), full)
        contestants["JAX vmap(lax.scan) KF"] = (lambda: jkf(yj), full)

    for fn, _ in contestants.values():  # compile / warm up outside the timings
        fn()
    times: dict[str, list[float]] = {k: [] for k in contestants}
    pad = np.zeros(runs * steps * 6) if scrub else None  # the size of the mean + covariance outputs
    rng = np.random.default_rng(0)
    names = list(contestants)
    for _ in range(repeat):
        for i in rng.permutation(len(names)):  # no fixed predecessor (see the module docstring)
            name = names[i]
            fn, work = contestants[name]
            if pad is not None:
                pad += 1.0  # the same cache state before every timed call (see the module docstring)
            t0 = time.perf_counter()
            fn()
            times[name].append((time.perf_counter() - t0) / work * 1e9)
    med = {k: statistics.median(v) for k, v in times.items()}
    limit = med.get("hand-fused numba TKF (limit)")
    compute = med.get("hand-fused, outputs reused (compute)")
    jax_tkf = med.get("JAX vmap(lax.scan) TKF")
    head = (
        f"  {'':40s} {'ns/run-step':>12s} {'(min-max)':>17s} {'limit/this':>11s} {'compute/this':>13s} "
        f"{'JAX TKF/this':>13s}"
    )
    print(head)

    def ratio(ref, val, width):
        return f"{ref / val:{width}.2f}" if ref else f"{'-':>{width}s}"

    for name, v in times.items():
        print(
            f"  {name:40s} {med[name]:12.1f} {f'({min(v):.0f}-{max(v):.0f})':>17s} {ratio(limit, med[name], 11)} "
            f"{ratio(compute, med[name], 13)} {ratio(jax_tkf, med[name], 13)}"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="tiny sizes for CI")
    ap.add_argument("--repeat", type=int, default=5, help="timed calls per contestant (default 5)")
    ap.add_argument("--no-scrub", action="store_true", help="no cache scrub before each timed call")
    args = ap.parse_args()
    if args.repeat < 1:
        ap.error("--repeat: expected a positive count")
    cases = [(100_000, 100, 20), (10_000, 1_000, 5)] if not args.smoke else [(400, 40, 2)]
    repeat = args.repeat if not args.smoke else 2
    scrubbed = "no scrub" if args.no_scrub else "a cache scrub before each call"
    print(f"one thread; load average before: {_load()}; {repeat} shuffled interleaved repeats, medians; {scrubbed}")
    for runs, steps, peers in cases:
        case(runs, steps, repeat, peers, scrub=not args.no_scrub)
    print(f"\nload average after: {_load()}")


if __name__ == "__main__":
    main()
