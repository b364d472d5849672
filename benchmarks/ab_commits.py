"""The core filters of two checkouts of tobitkf timed against each other, processes alternated.

Times the core Tobit KF and KF (n = 2, m = 1: every output, means only, means and covariances), the TKF with
two channels, the fading TKF (L = 2) and the protocol TKF (two sensors, Round-Robin, window 2) of whatever
tobitkf each checkout holds, in fresh processes that alternate between the two checkouts, and prints the
medians (min-max) of thread CPU time per run-step and the ratio second / first. Each worker process compiles
(its own numba cache per checkout), simulates the data with the public API, calls each filter once to warm
it, then times ``--calls`` calls, each result read and freed. One thread (BLAS and numba held to 1).

Run by hand (the checkouts' ``src`` folders; an old commit in its own worktree)::

    git worktree add --detach /tmp/old 684b7b7
    python benchmarks/ab_commits.py /tmp/old/src src --alternations 6

Not part of ``run_all.py``: it compares two versions of the package, not the package with its peers.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")


def worker(calls: int, only: str, runs: int, steps: int) -> dict[str, dict[str, float]]:
    """Time the cases in this process; ``{case: {"cpu_ns": median, "wall_ns": median}}`` per run-step."""
    import numpy as np

    import tobitkf as tk
    from tobitkf.channels.fading import RiceFading
    from tobitkf.channels.protocol import LAMBDA_BASE, ProtocolChannel

    w = 0.052 * np.pi
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    osc = tk.LinearSystem(A=A, C=[[1.0, 0.0]], Q=0.0025 * np.eye(2), R=[[1.0]], x0=[5.0, 0.0], P0=np.eye(2))
    osc2 = tk.LinearSystem(A=A, C=np.eye(2), Q=0.0025 * np.eye(2), R=np.eye(2), x0=[5.0, 0.0], P0=np.eye(2))
    cens, cens2 = tk.Censoring(lower=0.0), tk.Censoring(lower=[0.0, 0.0])
    y1 = tk.simulate(osc, steps, runs, censoring=cens, seed=0).y
    y2 = tk.simulate(osc2, steps, runs, censoring=cens2, seed=1).y
    fad = RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    yf = tk.simulate(osc, steps, runs // 4, censoring=cens, measurement=fad, seed=2).y
    ch = ProtocolChannel(2, window=2, failures=LAMBDA_BASE, threshold=0.0)
    yp = tk.simulate(osc2, steps, runs // 4, seed=3, channel=ch).y
    cases = {}
    for out in ("all", "mean", ("mean", "cov")):
        name = out if isinstance(out, str) else "+".join(out)
        cases[f"tkf/{name}"] = (tk.TobitKalmanFilter(osc, cens), y1, out)
        cases[f"kf/{name}"] = (tk.KalmanFilter(osc), y1, out)
    cases["tkf_m2/mean+cov"] = (tk.TobitKalmanFilter(osc2, cens2), y2, ("mean", "cov"))
    for out in ("mean", ("mean", "cov")):
        name = out if isinstance(out, str) else "+".join(out)
        cases[f"fading/{name}"] = (tk.FadingTobitKalmanFilter(osc, fad, cens), yf, out)
        cases[f"protocol/{name}"] = (tk.ProtocolTobitKalmanFilter(osc2, ch), yp, out)
    res = {}
    for name, (f, y, out) in cases.items():
        if not name.startswith(only):
            continue
        f.filter(y, outputs=out)  # compile / warm (the result freed at once)
        cpu, wall = [], []
        for _ in range(calls):
            t0, c0 = time.perf_counter(), time.thread_time()
            r = f.filter(y, outputs=out)
            float(np.asarray(r.mean).ravel()[-1])
            c1, t1 = time.thread_time(), time.perf_counter()
            del r
            cpu.append((c1 - c0) / y.shape[0] / y.shape[1] * 1e9)
            wall.append((t1 - t0) / y.shape[0] / y.shape[1] * 1e9)
        res[name] = {"cpu_ns": float(np.median(cpu)), "wall_ns": float(np.median(wall))}
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("first", nargs="?", help="the first checkout's src folder (the reference)")
    ap.add_argument("second", nargs="?", help="the second checkout's src folder")
    ap.add_argument("--alternations", type=int, default=6, help="process pairs (first, second) run in turn")
    ap.add_argument("--calls", type=int, default=7, help="timed calls per case and process")
    ap.add_argument("--only", default="", help="cases whose name starts with this (tkf/, kf/, fading, ...)")
    ap.add_argument("--runs", type=int, default=20000)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--smoke", action="store_true", help="this checkout against itself, tiny (seconds)")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        print(json.dumps(worker(a.calls, a.only, a.runs, a.steps)))
        return 0
    if a.smoke:
        here = str(Path(__file__).resolve().parents[1] / "src")
        a.first = a.second = here
        a.alternations, a.calls, a.runs, a.steps = 1, 1, 400, 20
    if not a.first or not a.second:
        ap.error("give the two checkouts' src folders (or --smoke)")
    import numpy as np

    env0 = dict(os.environ, **dict.fromkeys(THREAD_VARS, "1"))
    results: dict[str, list[dict]] = {"first": [], "second": []}
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(a.alternations):
            for side, src in (("first", a.first), ("second", a.second)):
                env = dict(
                    env0, PYTHONPATH=src, NUMBA_CACHE_DIR=os.environ.get(f"AB_CACHE_{side.upper()}", f"{tmp}/{side}")
                )
                cmd = [sys.executable, __file__, "--worker", "--calls", str(a.calls), "--only", a.only]
                cmd += ["--runs", str(a.runs), "--steps", str(a.steps)]
                out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True).stdout
                results[side].append(json.loads(out.strip().splitlines()[-1]))
                load = os.getloadavg()[0]
                print(f"  {side} process {i + 1} done (load average {load:.2f})", flush=True)
    print(f"{a.runs} runs x {a.steps} steps (fading, protocol: {a.runs // 4} runs); thread CPU ns per run-step,")
    print(f"medians (min-max) over {a.alternations} processes of the medians of {a.calls} calls")
    print(f"  {'case':18s} {'first':>22s} {'second':>22s}  second/first")
    for case in results["first"][0]:
        f = np.array([r[case]["cpu_ns"] for r in results["first"]])
        s = np.array([r[case]["cpu_ns"] for r in results["second"]])
        fs = f"{np.median(f):7.1f} ({f.min():.1f}-{f.max():.1f})"
        ss = f"{np.median(s):7.1f} ({s.min():.1f}-{s.max():.1f})"
        print(f"  {case:18s} {fs:>22s} {ss:>22s}  {np.median(s) / np.median(f):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
