"""Peak memory of one ``filter`` call against the size of what it returns (the memory target).

For each estimator and output selection (``outputs="mean"``, ``("mean", "var")``, ``"all"``) one fresh
process loads the readings (10^5 runs x 100 steps, n = 2, m = 1, half the readings censored; the fading
and protocol examples at their papers' sizes), runs ``filter`` once on 100 runs to compile and warm up,
and then measures the call on all runs in two ways:

* **traced**: the peak of ``tracemalloc`` (every numpy allocation, so the outputs and any copies of the
  input; numba's internal scratch is not traced, it is a few kB per block of runs);
* **RSS**: the process's peak resident set during the call (``VmHWM`` of ``/proc/self/status``, reset
  to the current resident set just before the call by writing 5 to ``/proc/self/clear_refs``) minus the
  resident set before it: every allocation that was touched, numba's included (Linux only; elsewhere
  the column is NaN).

Both are printed as multiples of the means array ``(N, T, n)`` float64 that the call returns. The
target: means only, 10^5 runs x 100 steps, peak increment at most 1.3x the means array.

Run: ``PYTHONPATH=src python benchmarks/bench_memory.py`` (``--smoke``: 10^3 runs, for CI;
``--runs N`` to change the size).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

import numpy as np

import _timing  # noqa: F401 (prints the process's wall, user and system time at exit)

OUTPUTS = {"mean": "mean", "mean+var": ["mean", "var"], "all": "all"}
ESTIMATORS = (
    "TobitKalmanFilter",
    "TobitKalmanFilter (numpy)",
    "KalmanFilter",
    "FadingTobitKalmanFilter",
    "ProtocolTobitKalmanFilter",
)


def _problem(name: str):
    import tobitkf as tk

    w = 0.05
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    if name.startswith("Protocol"):
        from tobitkf.channels.protocol import LAMBDA_BASE

        sys_ = tk.LinearSystem(A=A, C=np.eye(2), Q=0.0025 * np.eye(2), R=np.eye(2), x0=[5.0, 0.0], P0=np.eye(2))
        ch = tk.ProtocolChannel(2, window=2, failures=LAMBDA_BASE, threshold=0.0)
        return sys_, {"channel": ch}, lambda: tk.ProtocolTobitKalmanFilter(sys_, ch)
    sys_ = tk.LinearSystem(A=A, C=[[1.0, 0.0]], Q=1e-3 * np.eye(2), R=[[0.01]], x0=[1.0, 0.0], P0=np.eye(2))
    cens = tk.Censoring(lower=0.0)
    if name.startswith("Fading"):
        fad = tk.RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
        return sys_, {"censoring": cens, "measurement": fad}, lambda: tk.FadingTobitKalmanFilter(sys_, fad, cens)
    if name.startswith("Kalman"):
        return sys_, {"censoring": cens}, lambda: tk.KalmanFilter(sys_)
    backend = "numpy" if "numpy" in name else "auto"
    return sys_, {"censoring": cens}, lambda: tk.TobitKalmanFilter(sys_, cens, backend=backend)


def _status_kb(field: str) -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(field + ":"):
                return float(line.split()[1])
    return float("nan")


def _rss_reset() -> float:
    """Reset the peak resident set to the current one; return the current one in bytes (NaN off Linux)."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return _status_kb("VmRSS") * 1024
    except OSError:
        return float("nan")


def child(name: str, outputs_key: str, path: str) -> None:
    """Measure one call (run in a fresh process); prints one JSON line."""
    import tracemalloc

    _, _, make = _problem(name)
    y = np.load(path)
    est = make()
    outputs = OUTPUTS[outputs_key]
    est.filter(y[:100], outputs=outputs)  # compile and warm up
    base = _rss_reset()
    tracemalloc.start()
    res = est.filter(y, outputs=outputs)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    grown = _status_kb("VmHWM") * 1024 - base if base == base else float("nan")
    means = res.mean.nbytes
    print(json.dumps({"traced": peak / means, "rss": grown / means, "means_mb": means / 1e6}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="10^3 runs, for CI")
    ap.add_argument("--runs", type=int, default=None)
    ap.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(*args.child)
        return
    import tobitkf as tk

    runs = args.runs or (1_000 if args.smoke else 100_000)
    steps = 100
    print(
        f"peak memory of one filter call, {runs} runs x {steps} steps, as multiples of the means array; "
        f"load average {os.getloadavg()[0]:.1f}"
    )
    print(f"  {'estimator':32s} {'outputs':9s} {'means MB':>9s} {'traced':>8s} {'RSS':>8s}")
    with tempfile.TemporaryDirectory() as tmp:
        for name in ESTIMATORS:
            sys_, kw, _ = _problem(name)
            path = os.path.join(tmp, "y.npy")
            np.save(path, tk.simulate(sys_, steps, runs, seed=0, **kw).y)
            for key in OUTPUTS:
                env = dict(os.environ)
                env["PYTHONPATH"] = os.pathsep.join(
                    p for p in (os.path.dirname(tk.__path__[0]), env.get("PYTHONPATH")) if p
                )
                out = subprocess.run(
                    [sys.executable, __file__, "--child", name, key, path],
                    capture_output=True,
                    text=True,
                    env=env,
                    check=True,
                )
                # the child's result is its JSON line (the benchmark's exit report of times follows it)
                r = json.loads(next(ln for ln in reversed(out.stdout.splitlines()) if ln.startswith("{")))
                print(f"  {name:32s} {key:9s} {r['means_mb']:9.1f} {r['traced']:7.2f}x {r['rss']:7.2f}x")
    print("target: TobitKalmanFilter, outputs='mean', 10^5 x 100: at most 1.3x")


if __name__ == "__main__":
    main()
