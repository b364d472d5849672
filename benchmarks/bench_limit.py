"""The core TKF as a user's loop sees it: a plain loop of ``filter`` calls beside the hand-fused kernel and JAX.

Data: the n = 2 oscillator of ``bench_core.py`` (m = 1, left-censored at 0), two kinds of readings: drawn
from the model (about half censored) and drawn apart from it, ``max(2 N(0, 1), 0)`` (readings four times as
noisy as the model allows, which drive the prior into the censored tail). Cases: 10^5 runs x 100 steps and
10^4 runs x 1000 steps. Everything on one thread (BLAS, our kernels with ``threads=1``, XLA's CPU client
single-threaded as far as its flags go).

Harness: each contestant runs a plain loop of ``--repeat`` calls as a user writes it (``r = f.filter(y, ...)``,
the result read, then freed), the contestants one after the other in an order shuffled per case (seeded),
after one untimed call of each (compilation); every call is timed for wall time and, from ``getrusage``, the
process's user and system time and minor page faults (``benchmarks/_timing.py``). Contestants:

* tobitkf's TKF (compiled, ``backend="numba"``): means and covariances; means only; every output (the default
  ``filter(y)``, 1.1 GB at these sizes, which adds the update-size check of the online diagnostics); means and
  covariances with the output pool bypassed (fresh memory for every call); and the KF, means and covariances;
* the hand-fused scalar numba TKF (``benchmarks/_fused_tkf.py``) writing into output arrays allocated and
  touched before the loop (compute only: no filter that returns new arrays can do better), the reference of the
  ratios;
* JAX ``jit(vmap(lax.scan))`` TKF (closed-form statistics through ``jax.scipy.special``) and KF when JAX is
  installed (``pip install .[bench]``), skipped with a note otherwise;
* on the model's readings only: tobitkf's numpy reference path (a tenth of the runs, scaled: its cost per
  run-step does not grow with the batch), filterpy's and pykalman's KF looped over a few runs and scaled.

Printed per contestant: ns per run-step, median of the calls (min-max), for wall, user and system time, the
median minor faults per call, and the ratios of medians (wall) fused/this and JAX TKF/this (> 1: this is
faster). The machine's load average is printed before and after: on a loaded machine wall time exceeds user +
system by the time spent waiting for a core.

Run by hand::

    PYTHONPATH=src python benchmarks/bench_limit.py              # ~5 minutes on an idle machine
    PYTHONPATH=src python benchmarks/bench_limit.py --smoke      # seconds (CI)
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")

import argparse  # noqa: E402

import numpy as np  # noqa: E402

import tobitkf as tk  # noqa: E402
from _timing import HEADER, measure, row, summary  # noqa: E402
from tobitkf.filters import _pool  # noqa: E402
from tobitkf.filters._backend import numba_available  # noqa: E402


def make_system() -> tk.LinearSystem:
    w = 0.05
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    return tk.LinearSystem(A=A, C=[[1.0, 0.0]], Q=0.01 * np.eye(2), R=[[0.1]], x0=[0.0, 0.0], P0=0.05 * np.eye(2))


def _load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def readings(sys_: tk.LinearSystem, cens: tk.Censoring, runs: int, steps: int, kind: str) -> np.ndarray:
    """``(runs, steps, 1)`` readings: ``"model"`` simulated from the model, ``"apart"`` max(2 N(0, 1), 0)."""
    if kind == "model":
        return tk.simulate(sys_, steps, runs, censoring=cens, seed=0).y
    return np.maximum(2.0 * np.random.default_rng(1).standard_normal((runs, steps, 1)), 0.0)


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


def _read(out) -> float:
    """Read a result as a user would (a number from its last step), whatever the contestant returns."""
    if isinstance(out, tk.FilterResult):
        return float(out.mean[:, -1].sum())
    if isinstance(out, tuple):
        return float(np.asarray(out[0][:, -1]).sum())
    return 0.0


def case(runs: int, steps: int, kind: str, repeat: int, peer_runs: int) -> None:
    sys_ = make_system()
    lower = 0.0
    cens = tk.Censoring(lower=lower)
    y = readings(sys_, cens, runs, steps, kind)
    y2 = np.ascontiguousarray(y[:, :, 0])
    sub = max(1, runs // 10)
    pre = tk.TobitKalmanFilter(sys_, cens, backend="numpy").filter(y[: min(runs, 500)], outputs=("pred_mean",))
    a = (lower - pre.pred_mean[..., 0]) / np.sqrt(0.1)  # the standardized limit the filter uses
    what = "readings from the model" if kind == "model" else "readings apart from the model, max(2 N(0,1), 0)"
    print(
        f"\n{runs} runs x {steps} steps, n=2, m=1, {what}: censored fraction {np.mean(y <= lower):.2f}, "
        f"steps with the prior mean > 4 sd below the limit (tail route) ~{np.mean(a > 4):.3f}; "
        f"load {_load()}"
    )

    A, Q = np.ascontiguousarray(sys_.transition(0)), np.ascontiguousarray(sys_.process_cov(0))
    C, sig = np.ascontiguousarray(sys_.measurement(1)[0]), float(np.sqrt(sys_.measurement_cov(1)[0, 0]))
    x0, P0 = np.ascontiguousarray(sys_.x0), np.ascontiguousarray(sys_.P0)
    contestants: dict[str, tuple] = {}  # name -> (fn, run-steps per call)
    full = runs * steps
    fused_name = "hand-fused numba TKF, outputs preallocated"
    if numba_available():
        from _fused_tkf import fused_tkf

        reused = (np.zeros((runs, steps, 2)), np.zeros((runs, steps, 2, 2)))  # allocated and touched, here

        def fused():
            fused_tkf(y2, A, Q, C, sig, lower, x0, P0, *reused)
            return reused

        contestants[fused_name] = (fused, full)
        tkf = tk.TobitKalmanFilter(sys_, cens, backend="numba", threads=1)
        kf = tk.KalmanFilter(sys_, backend="numba")
        contestants["tobitkf TKF, mean + cov"] = (lambda: tkf.filter(y, outputs=("mean", "cov")), full)
        contestants["tobitkf TKF, means only"] = (lambda: tkf.filter(y, outputs=("mean",)), full)
        contestants["tobitkf TKF, every output (default)"] = (lambda: tkf.filter(y), full)

        def fresh():
            with _pool.bypassed():  # new memory for the outputs, the pool's blocks left for the other rows
                return tkf.filter(y, outputs=("mean", "cov"))

        contestants["tobitkf TKF, mean + cov, pool bypassed"] = (fresh, full)
        contestants["tobitkf KF, mean + cov"] = (lambda: kf.filter(y, outputs=("mean", "cov")), full)
    jx = jax_filters(sys_, lower)
    if jx is None:
        print("  (JAX not installed: skipped; pip install '.[bench]')")
    else:
        jkf, jtkf, to_dev = jx
        yj = to_dev(y2)
        contestants["JAX vmap(lax.scan) TKF"] = (lambda: jtkf(yj), full)
        contestants["JAX vmap(lax.scan) KF"] = (lambda: jkf(yj), full)
    if kind == "model":
        tkf_np = tk.TobitKalmanFilter(sys_, cens, backend="numpy")
        contestants["tobitkf TKF numpy path, mean + cov"] = (
            lambda: tkf_np.filter(y[:sub], outputs=("mean", "cov")),
            sub * steps,
        )
        contestants["filterpy KalmanFilter (looped, a KF)"] = (
            lambda: filterpy_runs(sys_, y[:peer_runs]),
            peer_runs * steps,
        )
        try:
            import pykalman  # noqa: F401

            contestants["pykalman KalmanFilter.filter (looped, a KF)"] = (
                lambda: pykalman_runs(sys_, y[:peer_runs]),
                peer_runs * steps,
            )
        except ImportError:
            print("  (pykalman not installed: skipped)")

    for fn, _ in contestants.values():  # compile / warm up outside the timings
        _read(fn())
    samples: dict[str, list] = {k: [] for k in contestants}
    names = list(contestants)
    for i in np.random.default_rng(0).permutation(len(names)):
        name = names[i]
        fn, _ = contestants[name]
        for _ in range(repeat):  # the user's loop: call, read, free
            sample, out = measure(fn)
            _read(out)
            del out
            samples[name].append(sample)
    stats = {k: summary(v, 1e9 / contestants[k][1]) for k, v in samples.items()}
    fused_wall = stats[fused_name].wall if fused_name in stats else None
    jax_wall = stats["JAX vmap(lax.scan) TKF"].wall if "JAX vmap(lax.scan) TKF" in stats else None
    print(f"  ns per run-step, median of {repeat} calls (min-max); faults: minor page faults per call")
    print(f"  {'':44s} {HEADER} {'fused/this':>10s} {'JAX TKF/this':>12s}")

    def ratio(ref, val, width):
        return f"{ref / val:{width}.2f}" if ref else f"{'-':>{width}s}"

    for name, st in stats.items():
        print(f"  {name:44s} {row(st)} {ratio(fused_wall, st.wall, 10)} {ratio(jax_wall, st.wall, 12)}")
    print(f"  load after: {_load()}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="tiny sizes for CI")
    ap.add_argument("--repeat", type=int, default=5, help="timed calls in each contestant's loop (default 5)")
    args = ap.parse_args()
    if args.repeat < 1:
        ap.error("--repeat: expected a positive count")
    cases = [(100_000, 100, 20), (10_000, 1_000, 5)] if not args.smoke else [(400, 40, 2)]
    repeat = args.repeat if not args.smoke else 2
    print(
        f"one thread; load average before: {_load()}; a plain loop of {repeat} calls per contestant, medians; "
        f"output pool limit {tk.output_pool_limit() / 2**30:.1f} GiB"
    )
    for runs, steps, peers in cases:
        for kind in ("model", "apart"):
            case(runs, steps, kind, repeat, peers)
    print(f"\nload average after: {_load()}")


if __name__ == "__main__":
    main()
