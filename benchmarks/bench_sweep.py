"""Sweep benchmark: Dask scaling (1 vs 2 worker processes) and memory against the run count.

* Speed: the same sweep file (core TKF, n=2, m=1) on ``--scheduler processes`` with 1 and
  with 2 workers; prints wall times and the speed-up (target >= 1.6x on 2 cores).
* Memory: peak resident memory of a ``local`` sweep process for growing run counts
  (target: flat; 10^6 runs of the core TKF with T = 100 within 2 GB).

Run by hand: ``python benchmarks/bench_sweep.py``; CI: ``--smoke``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SWEEP = """
[sweep]
runs = {runs}
steps = {steps}
seed = 0
block_runs = {block}
chunk_blocks = 5

[model]
A = [[0.99875, -0.04998], [0.04998, 0.99875]]
C = [[1.0, 0.0]]
Q = [[0.01, 0.0], [0.0, 0.01]]
R = [[0.1]]
x0 = [0.0, 0.0]
P0 = [[0.05, 0.0], [0.0, 0.05]]

[censoring]
lower = 0.0

[estimators.tkf]
type = "TobitKalmanFilter"
"""

_PEAK = """
import resource, sys
from tobitkf.sweep import load_sweep, run_sweep
run_sweep(load_sweep(sys.argv[1]), sys.argv[2], scheduler=sys.argv[3], workers=int(sys.argv[4]))
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)
"""


def run(file: Path, out: Path, scheduler: str, workers: int) -> tuple[float, float]:
    t = time.perf_counter()
    res = subprocess.run([sys.executable, "-c", _PEAK, str(file), str(out), scheduler, str(workers)],
                         capture_output=True, text=True, check=True)
    return time.perf_counter() - t, float(res.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true")
    args = ap.parse_args()
    speed_runs, steps, block = (600_000, 100, 2_000) if not args.smoke else (4_000, 20, 1_000)
    mem_runs = [10_000, 100_000, 1_000_000] if not args.smoke else [2_000, 4_000]
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        f = tmp / "bench.toml"
        f.write_text(SWEEP.format(runs=speed_runs, steps=steps, block=block))
        t1, _ = run(f, tmp / "w1", "processes", 1)
        t2, _ = run(f, tmp / "w2", "processes", 2)
        results["dask_processes"] = {"runs": speed_runs, "steps": steps, "one_worker_s": t1, "two_workers_s": t2,
                                     "speedup": t1 / t2}
        print(f"Dask processes, {speed_runs} runs x {steps} steps: 1 worker {t1:.1f} s, 2 workers {t2:.1f} s, "
              f"speed-up x{t1 / t2:.2f}")
        mem = {}
        for runs in mem_runs:
            g = tmp / f"mem{runs}.toml"
            g.write_text(SWEEP.format(runs=runs, steps=steps, block=min(block, runs)))
            t, peak = run(g, tmp / f"m{runs}", "local", 1)
            mem[runs] = peak
            print(f"local, {runs:>9} runs x {steps} steps: {t:7.1f} s, peak RSS {peak:7.1f} MB, "
                  f"{runs * steps / t:,.0f} run-steps/s")
        results["peak_rss_mb"] = mem
    print(json.dumps(results))


if __name__ == "__main__":
    main()
