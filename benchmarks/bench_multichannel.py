"""The m > 1 path of the compiled kernels against the numpy reference path.

Cases, ns of process CPU time per run-step (median of ``--repeat`` calls after one untimed call that
compiles; spread min-max), one thread, outputs ``"mean"`` only, and the ratio numpy / compiled:

* the TKF (``TobitKalmanFilter``) at n = 16, m = 8 on the random stable system of
  ``bench_scaling.py``, left-censored at 0 in every channel;
* the fading TKF (``FadingTobitKalmanFilter``, the oscillator of ``tests/filters/test_kernels_fading.py``,
  L = 2) with m = 1 and m = 2 channels, left-censored at 0.

The compiled path runs ``--runs`` runs; the numpy path a tenth of them (its cost per run-step is flat
in the run count once the batch fills the vector units), both ``--steps`` steps. Run by hand::

    PYTHONPATH=src nice -n 5 python benchmarks/bench_multichannel.py          # ~2 minutes
    PYTHONPATH=src python benchmarks/bench_multichannel.py --smoke            # seconds (CI)
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402

import numpy as np  # noqa: E402

import _timing  # noqa: E402,F401 (prints the times at exit)
import tobitkf as tk  # noqa: E402
from bench_scaling import random_system, timed  # noqa: E402
from tobitkf.channels.fading import RiceFading  # noqa: E402
from tobitkf.filters._backend import numba_available  # noqa: E402
from tobitkf.filters.fading import FadingTobitKalmanFilter  # noqa: E402


def oscillator(m: int) -> tk.LinearSystem:
    w = 0.052 * np.pi
    A = [[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]]
    C = [[1.0, 0.0], [0.4, 1.0]][:m]
    return tk.LinearSystem(A=A, C=C, Q=0.0025 * np.eye(2), R=np.diag([1.0, 0.5][:m]), x0=[5.0, 0.0], P0=np.eye(2))


def cases(runs: int, steps: int):
    """(name, estimator factory by backend, data) of every case."""
    sys16 = random_system(16, 8)
    cens16 = tk.Censoring(lower=np.zeros(8))
    y16 = tk.simulate(sys16, steps, runs, censoring=cens16, seed=1).y
    yield "tkf n=16 m=8", lambda be: tk.TobitKalmanFilter(sys16, cens16, backend=be, threads=1), y16
    fad = RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    for m in (1, 2):
        sys_, cens = oscillator(m), tk.Censoring(lower=[0.0] * m)
        y = tk.simulate(sys_, steps, runs, censoring=cens, measurement=fad, seed=0).y
        yield f"fading L=2 m={m}", (lambda be, s=sys_, c=cens: FadingTobitKalmanFilter(s, fad, c, backend=be)), y


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=10_000)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--smoke", action="store_true", help="tiny sizes, one repeat (CI)")
    args = ap.parse_args()
    if args.smoke:
        args.runs, args.steps, args.repeat = 200, 20, 1
    if not numba_available():
        print("numba is not installed: nothing to compare")
        return
    print(f"{'case':<18} {'backend':<7} {'runs':>6} {'ns/run-step (min-max)':>28} {'numpy/numba':>12}")
    for name, make, y in cases(args.runs, args.steps):
        per = {}
        for be, yy in (("numba", y), ("numpy", y[: max(1, y.shape[0] // 10)])):
            est = make(be)
            med, lo, hi = timed(lambda e=est, d=yy: e.filter(d, outputs="mean"), args.repeat)
            rs = yy.shape[0] * yy.shape[1]
            per[be] = med / rs
            spread = f"{med / rs * 1e9:.0f} ({lo / rs * 1e9:.0f}-{hi / rs * 1e9:.0f})"
            ratio = f"{per['numpy'] / per['numba']:.2f}x" if be == "numpy" else ""
            print(f"{name:<18} {be:<7} {yy.shape[0]:>6} {spread:>28} {ratio:>12}")


if __name__ == "__main__":
    main()
