"""Sweep benchmark: Dask scaling (1 vs 2 worker processes) and memory against the run count.

* Speed: the same sweep file (core TKF, n=2, m=1, 10^6 runs x 100 steps) on ``--scheduler
  processes`` with 1 and with 2 workers, each a fresh ``tobitkf sweep``-like process timed
  from start to exit (interpreter start, cluster start, store and summary included); the
  two are run alternately ``--repeat`` times and the best and median wall times are
  printed with the speed-up of the best times (target: >= 1.7x on 2 cores). A ``local``
  run of the same file gives the in-process reference.
* Memory: peak resident memory of a ``local`` sweep process for growing run counts
  (``--mem-runs``, default 10^4, 10^5, 10^6; target: flat, 10^6 runs of the core TKF with T = 100
  within 2 GB), or with ``--mem-scheduler processes`` of a 2-worker Dask sweep, summed over the
  whole process tree (driver, nannies, workers; the target is a 10^7-run sweep with memory
  flat: ``--mem-runs 10000 1000000 10000000 --mem-scheduler processes``), and of an experiment
  sweep (the fading TKF example in blocks of 1000 runs) for 2000 and 20000 runs.

Run by hand: ``python benchmarks/bench_sweep.py``; CI: ``--smoke``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import _timing  # noqa: F401 (prints the process's wall, user and system time at exit)

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

EXPERIMENT_SWEEP = """
[sweep]
experiment = "geng2017-oscillator"
runs = {runs}
seed = 0
block_runs = {block}
"""

_PEAK = """
import resource, sys
from tobitkf.sweep import load_sweep, run_sweep
run_sweep(load_sweep(sys.argv[1]), sys.argv[2], scheduler=sys.argv[3], workers=int(sys.argv[4]))
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)
"""


def run(file: Path, out: Path, scheduler: str, workers: int, tree: bool = False) -> tuple[float, float]:
    """Wall seconds of one sweep process and its peak memory in MB: the process's own peak RSS, or with
    ``tree`` the peak of the summed RSS of the process and all its descendants (Dask's nannies and worker
    processes), sampled every 50 ms with psutil (a spike shorter than that can be missed)."""
    # the output goes to files, not pipes: while the memory is sampled nothing reads a pipe, and a full
    # one (Dask's log lines on stderr) would stall the sweep
    out_f, err_f = tempfile.TemporaryFile("w+"), tempfile.TemporaryFile("w+")
    t = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-c", _PEAK, str(file), str(out), scheduler, str(workers)],
        stdout=out_f,
        stderr=err_f,
        text=True,
    )
    peak_tree = 0.0
    if tree:
        import psutil

        root = psutil.Process(proc.pid)
        while proc.poll() is None:
            total = 0
            try:
                for p in [root, *root.children(recursive=True)]:
                    try:
                        total += p.memory_info().rss
                    except psutil.Error:  # a worker that exited between the listing and the read
                        pass
            except psutil.Error:
                break
            peak_tree = max(peak_tree, total / 2**20)
            time.sleep(0.05)
    proc.wait()
    wall = time.perf_counter() - t
    out_f.seek(0)
    err_f.seek(0)
    stdout, stderr = out_f.read(), err_f.read()
    out_f.close()
    err_f.close()
    if proc.returncode != 0:
        raise subprocess.CalledProcessError(proc.returncode, proc.args, stdout, stderr)
    own = float(stdout.strip().splitlines()[-1])
    return wall, (max(peak_tree, own) if tree else own)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true")
    ap.add_argument("--repeat", type=int, default=3, help="alternating 1-worker/2-worker timings (default 3)")
    ap.add_argument("--runs", type=int, default=None, help="runs of the speed sweep (default 10^6; 4000 with --smoke)")
    ap.add_argument("--speed-only", action="store_true", help="skip the memory measurements")
    ap.add_argument(
        "--mem-runs", type=int, nargs="+", default=None, help="run counts of the memory ladder (default 10^4 10^5 10^6)"
    )
    ap.add_argument(
        "--mem-scheduler",
        choices=["local", "processes"],
        default="local",
        help="scheduler of the memory ladder (processes: 2 Dask workers, the peak of the whole process tree)",
    )
    args = ap.parse_args()
    speed_runs, steps, block = (1_000_000, 100, 2_000) if not args.smoke else (4_000, 20, 1_000)
    if args.runs is not None:
        speed_runs = args.runs
    repeat = args.repeat if not args.smoke else 1
    if args.runs is not None and args.runs < 1:
        ap.error("--runs: expected a positive run count")
    mem_runs = [10_000, 100_000, 1_000_000] if not args.smoke else [2_000, 4_000]
    if args.mem_runs is not None:
        mem_runs = args.mem_runs
    if any(r < 1 for r in mem_runs):
        ap.error("--mem-runs: expected positive run counts")
    exp_runs = [2_000, 20_000] if not args.smoke else [20, 40]
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        f = tmp / "bench.toml"
        f.write_text(SWEEP.format(runs=speed_runs, steps=steps, block=block))
        times: dict[int, list[float]] = {1: [], 2: []}
        for i in range(repeat):
            for w in (1, 2):
                times[w].append(run(f, tmp / f"w{w}-{i}", "processes", w)[0])
        t_local, _ = run(f, tmp / "local", "local", 2)
        t_local1, _ = run(f, tmp / "local1", "local", 1)
        t1, t2 = min(times[1]), min(times[2])
        results["dask_processes"] = {
            "runs": speed_runs,
            "steps": steps,
            "one_worker_s": times[1],
            "two_workers_s": times[2],
            "local_s": t_local,
            "local_one_thread_s": t_local1,
            "speedup_best": t1 / t2,
        }
        print(
            f"Dask processes, {speed_runs} runs x {steps} steps, {repeat} alternating tries: "
            f"1 worker best {t1:.1f} s (median {statistics.median(times[1]):.1f}), "
            f"2 workers best {t2:.1f} s (median {statistics.median(times[2]):.1f}), speed-up x{t1 / t2:.2f} "
            f"(medians x{statistics.median(times[1]) / statistics.median(times[2]):.2f}); "
            f"local (in-process) 2 threads {t_local:.1f} s, 1 thread {t_local1:.1f} s; "
            f"1 worker / local 1 thread = {statistics.median(times[1]) / t_local1:.2f}"
        )
        if args.speed_only:
            print(json.dumps(results))
            return
        mem = {}
        tree = args.mem_scheduler == "processes"
        label = "Dask processes, 2 workers, process tree" if tree else "local (2 threads)"
        for runs in mem_runs:
            g = tmp / f"mem{runs}.toml"
            g.write_text(SWEEP.format(runs=runs, steps=steps, block=min(block, runs)))
            t, peak = run(g, tmp / f"m{runs}", args.mem_scheduler, 2, tree=tree)
            mem[runs] = peak
            print(
                f"{label}, {runs:>9} runs x {steps} steps: {t:7.1f} s, peak RSS {peak:7.1f} MB, "
                f"{runs * steps / t:,.0f} run-steps/s",
                flush=True,
            )
        results["mem_scheduler"] = args.mem_scheduler
        results["peak_rss_mb"] = mem
        # experiment mode streams too: the fading TKF experiment in blocks of 1000 runs
        exp_mem = {}
        for runs in exp_runs:
            g = tmp / f"exp{runs}.toml"
            g.write_text(EXPERIMENT_SWEEP.format(runs=runs, block=min(1_000, runs)))
            t, peak = run(g, tmp / f"e{runs}", "local", 1)
            exp_mem[runs] = peak
            print(f"local, experiment geng2017-oscillator, {runs:>6} runs: {t:6.1f} s, peak RSS {peak:7.1f} MB")
        results["experiment_peak_rss_mb"] = exp_mem
    print(json.dumps(results))


if __name__ == "__main__":
    main()
