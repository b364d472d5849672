"""Scaling of the cost per run-step with the problem size: n, m, L, the window ell and the delay d.

Cases (each on its own data, ns of process CPU time per run-step, median of ``--repeat`` calls
after one untimed call that compiles; spread min-max). Everything runs on one thread, so CPU time
is the work, and it is steadier than wall time on a shared machine:

* the TKF (``TobitKalmanFilter``, compiled ``backend="numba"`` with ``threads=1`` and the numpy
  reference path) on a random stable system (A = 0.95 x orthogonal, C with unit-scale rows,
  left-censored at 0 in every channel): against n at m = 2 and against m at n = 8;
* the fading TKF (``FadingTobitKalmanFilter``, the oscillator of ``bench_fading.py``) against the
  fading order L;
* the protocol TKF (``protocol_tobit_kalman_filter``, the problem of ``bench_protocol.py``) against
  the integral window ell;
* the delay LMMSE (``chain_lmmse`` and ``reorganized_lmmse`` of ``filters/delay_chain.py`` and ``filters/delay_reorganized.py``, the paper
  example of ``bench_delay.py``) against the delay d.

Writes ``--out``.json and ``--out``.csv (default ``results/bench_scaling``: generated output, not
in git) and, with matplotlib, ``--out``.png: one panel per parameter, log-log. The docs page
``docs/performance.md`` draws the same figure from the numbers of a recorded run.
Single-threaded BLAS. Run by hand::

    PYTHONPATH=src nice python benchmarks/bench_scaling.py            # a few minutes
    PYTHONPATH=src python benchmarks/bench_scaling.py --smoke         # seconds (CI)
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import csv  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

import _timing  # noqa: E402,F401 (prints the times at exit)
import tobitkf as tk  # noqa: E402
from tobitkf.filters._backend import numba_available  # noqa: E402


def random_system(n: int, m: int, seed: int = 0) -> tk.LinearSystem:
    """Stable random model: A = 0.95 x orthogonal, C rows of unit scale, diagonal R."""
    rng = np.random.default_rng(seed)
    Qo, _ = np.linalg.qr(rng.standard_normal((n, n)))
    C = rng.standard_normal((m, n)) / np.sqrt(n)
    return tk.LinearSystem(A=0.95 * Qo, C=C, Q=0.05 * np.eye(n), R=0.1 * np.eye(m), x0=np.zeros(n), P0=np.eye(n))


def timed(fn: Callable[[], object], repeat: int) -> tuple[float, float, float]:
    """(median, min, max) process CPU seconds of ``repeat`` calls, after one untimed call."""
    fn()
    ts = []
    for _ in range(repeat):
        t0 = time.process_time()
        fn()
        ts.append(time.process_time() - t0)
    return statistics.median(ts), min(ts), max(ts)


def tkf_rows(param: str, values, fixed: int, runs: int, steps: int, repeat: int) -> list[dict]:
    backends = ["numpy"] + (["numba"] if numba_available() else [])
    rows = []
    for v in values:
        n, m = (v, fixed) if param == "n" else (fixed, v)
        sys_ = random_system(n, m)
        cens = tk.Censoring(lower=0.0)
        y = tk.simulate(sys_, steps, runs, censoring=cens, seed=1).y
        for be in backends:
            est = tk.TobitKalmanFilter(sys_, cens, backend=be, threads=1)
            med, lo, hi = timed(lambda: est.filter(y), repeat)
            rows.append(_row("tkf", be, param, v, f"n={n} m={m}", med, lo, hi, runs * steps))
    return rows


def fading_rows(orders, runs: int, steps: int, repeat: int) -> list[dict]:
    from bench_fading import MEANS, VARS, oscillator
    from tobitkf.channels.fading import RiceFading
    from tobitkf.filters.fading import FadingTobitKalmanFilter

    system, cens, rows = oscillator(), tk.Censoring(lower=0.0), []
    for L in orders:
        mu = MEANS[: L + 1] if L < len(MEANS) else [0.9] * (L + 1)
        var = VARS[: L + 1] if L < len(VARS) else [0.004] * (L + 1)
        fad = RiceFading.gaussian(L, mu, var)
        y = tk.simulate(system, steps, runs, censoring=cens, measurement=fad, seed=L).y
        est = FadingTobitKalmanFilter(system, fad, cens)
        med, lo, hi = timed(lambda: est.filter(y), repeat)
        rows.append(_row("fading_tkf", "default", "L", L, f"n_xi={2 * (L + 1)}", med, lo, hi, runs * steps))
    return rows


def protocol_rows(windows, runs: int, steps: int, repeat: int) -> list[dict]:
    from tobitkf.channels.protocol import LAMBDA_BASE, ProtocolChannel
    from tobitkf.filters.protocol import protocol_tobit_kalman_filter

    w = 0.052 * np.pi
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    sys_ = tk.LinearSystem(A=A, C=np.eye(2), Q=0.0025 * np.eye(2), R=np.eye(2), x0=[5.0, 0.0], P0=np.eye(2))
    rows = []
    for ell in windows:
        ch = ProtocolChannel(2, window=ell, failures=LAMBDA_BASE, threshold=0.0)
        y = tk.simulate(sys_, steps, runs, seed=0, channel=ch).y
        med, lo, hi = timed(lambda: protocol_tobit_kalman_filter(sys_, ch, y), repeat)
        rows.append(_row("protocol_tkf", "default", "ell", ell, f"n_xi={2 * (ell + 1)}", med, lo, hi, runs * steps))
    return rows


def delay_rows(delays, runs: int, steps: int, repeat: int) -> list[dict]:
    from tobitkf.filters.delay_chain import chain_lmmse
    from tobitkf.filters.delay_reorganized import reorganized_lmmse
    from tobitkf.models.delay import paper_example, paper_prior
    from tobitkf.simulate.delay import simulate_delay

    rows = []
    for d in delays:
        sys_, prior = paper_example(S=0.2, d=d), paper_prior(d)
        y = simulate_delay(sys_, prior, steps, runs, seed=1).y
        for name, fn in (("chain", chain_lmmse), ("reorganized", reorganized_lmmse)):
            med, lo, hi = timed(lambda fn=fn: fn(sys_, prior, y), repeat)
            rows.append(_row("delay_lmmse", name, "d", d, "n=2 m=1", med, lo, hi, runs * steps))
    return rows


def _row(family, variant, param, value, size, med, lo, hi, work) -> dict:
    return {
        "family": family,
        "variant": variant,
        "param": param,
        "value": int(value),
        "size": size,
        "ns_per_run_step": 1e9 * med / work,
        "ns_min": 1e9 * lo / work,
        "ns_max": 1e9 * hi / work,
    }


def plot(rows: list[dict], path: Path) -> None:
    """One log-log panel per parameter (n, m, L, ell, d), a line per family and variant."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    params = [p for p in ("n", "m", "L", "ell", "d") if any(r["param"] == p for r in rows)]
    fig, axes = plt.subplots(1, len(params), figsize=(3.2 * len(params), 3.0), squeeze=False)
    for ax, p in zip(axes[0], params):
        keys = sorted({(r["family"], r["variant"]) for r in rows if r["param"] == p})
        for fam, var in keys:
            sel = sorted(
                (r for r in rows if r["param"] == p and (r["family"], r["variant"]) == (fam, var)),
                key=lambda r: r["value"],
            )
            x = [r["value"] + (1 if p in ("L", "ell", "d") else 0) for r in sel]
            ax.loglog(x, [r["ns_per_run_step"] for r in sel], "o-", label=f"{fam} {var}")
        ax.set_xlabel(f"{p} + 1" if p in ("L", "ell", "d") else p)
        ax.set_title(f"cost against {p}")
        ax.legend(fontsize=7)
    axes[0][0].set_ylabel("CPU ns per run-step")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="tiny sizes (seconds)")
    ap.add_argument("--out", default="results/bench_scaling", help="path stem of the .json/.csv/.png")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    if args.smoke:
        ns, ms, orders, windows, delays = (2, 4), (1, 2), (0, 1), (1, 2), (1, 3)
        runs, steps, repeat = 20, 10, 1
    else:
        ns, ms, orders, windows, delays = (2, 4, 8, 16), (1, 2, 4, 8), (0, 1, 2, 3, 5), (1, 2, 3, 4), (1, 3, 7, 15)
        runs, steps, repeat = 1000, 40, args.repeat
    load0 = os.getloadavg()
    rows = tkf_rows("n", ns, 2, runs, steps, repeat)
    rows += tkf_rows("m", ms, 8, runs, steps, repeat)
    rows += fading_rows(orders, runs, steps, repeat)
    rows += protocol_rows(windows, runs, steps, repeat)
    rows += delay_rows(delays, runs, steps, repeat)
    load1 = os.getloadavg()
    print(f"{runs} runs x {steps} steps, median of {repeat}; load average {load0[0]:.2f} before, {load1[0]:.2f} after")
    print(f"{'family':<14}{'variant':<13}{'param':>6}{'value':>6}  {'size':<12}{'ns/run-step':>12}  (min-max)")
    for r in rows:
        print(
            f"{r['family']:<14}{r['variant']:<13}{r['param']:>6}{r['value']:>6}  {r['size']:<12}"
            f"{r['ns_per_run_step']:>12.0f}  ({r['ns_min']:.0f}-{r['ns_max']:.0f})"
        )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"runs": runs, "steps": steps, "repeat": repeat, "load_before": load0, "load_after": load1}
    out.with_suffix(".json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    with out.with_suffix(".csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    try:
        plot(rows, out.with_suffix(".png"))
    except ImportError:
        print("matplotlib not installed: no figure")
    print(f"wrote {out}.json, .csv, .png")


if __name__ == "__main__":
    main()
