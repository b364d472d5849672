"""The nonlinear assumed-density filter's cost: batched against the compiled linear ADF, online against filterpy.

The model (n = 4, m = 2): two coupled pendulums (semi-implicit Euler, dt = 0.05), each read through the
horizontal offset of its bob, :math:`\\sin\\theta_i`, clipped at ±0.5 (both limits censored). ``f`` and ``h``
come twice: as numpy functions and as ``numba.njit`` functions (the same equations); with the njit ones the
nonlinear filters run their compiled loop (:mod:`tobitkf.filters._compiled_nonlinear_loop`), with the numpy ones
their numpy path.

(1) Batched: ``tk.NonlinearAssumedDensityFilter`` (unscented rule, one linearisation) and the uncensored
``tk.UnscentedKalmanFilter`` over 10^4 runs x 100 steps, against the compiled linear
``tk.AssumedDensityTobitFilter`` of the model linearised at rest (:math:`\\sin\\theta \\approx \\theta`, the
same size, the same readings). Target: the nonlinear ADF at most 5x the linear ADF per run-step when f, h
are njit. A last line times the calls of the njit f and h alone, as the compiled loop makes them (per block of 64
runs and step, one f on the block's stacked sigma points and one h per channel): the floor of the compiled
filter, the part of its time that is the user's functions. Printed per run-step: wall, user and system CPU time (best of
``--repeat``; BLAS held to one thread).

(2) Online: one run, ``state = adf.step(state, y_k)`` in a Python loop, against filterpy's
``UnscentedKalmanFilter`` ``predict()`` + ``update()`` (``MerweScaledSigmaPoints(4, alpha=1, beta=2,
kappa=0)``, the same rule) on the same readings in the same process; repeats interleaved and the ratio taken
within each repeat (the machine may be shared: medians and min..max). Target: the nonlinear ADF's step with
njit f, h no slower than filterpy's UKF.

Run by hand::

    PYTHONPATH=src python benchmarks/bench_nonlinear.py            # ~1 minute on an idle machine
    PYTHONPATH=src python benchmarks/bench_nonlinear.py --smoke    # seconds
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import resource  # noqa: E402
import time  # noqa: E402
from typing import Any  # noqa: E402

import numba  # noqa: E402
import numpy as np  # noqa: E402

import tobitkf as tk  # noqa: E402

TARGET_BATCH = 5.0
TARGET_ONLINE = 1.0
DT, COUPLING, DAMPING, LIMIT = 0.05, 0.5, 0.1, 0.5


def _rates(t1, w1, t2, w2):
    a1 = -np.sin(t1) - DAMPING * w1 + COUPLING * (t2 - t1)
    a2 = -np.sin(t2) - DAMPING * w2 + COUPLING * (t1 - t2)
    return a1, a2


def f_numpy(x, k):
    x = np.asarray(x, dtype=float)
    a1, a2 = _rates(x[..., 0], x[..., 1], x[..., 2], x[..., 3])
    out = np.empty(x.shape)
    out[..., 1] = x[..., 1] + DT * a1
    out[..., 3] = x[..., 3] + DT * a2
    out[..., 0] = x[..., 0] + DT * out[..., 1]
    out[..., 2] = x[..., 2] + DT * out[..., 3]
    return out


def h_numpy(x, k):
    x = np.asarray(x, dtype=float)
    return np.sin(x[..., ::2])


@numba.njit(cache=True)
def f_njit(x, k):  # the same equations as f_numpy
    out = np.empty(x.shape)
    t1, w1, t2, w2 = x[..., 0], x[..., 1], x[..., 2], x[..., 3]
    a1 = -np.sin(t1) - DAMPING * w1 + COUPLING * (t2 - t1)
    a2 = -np.sin(t2) - DAMPING * w2 + COUPLING * (t1 - t2)
    out[..., 1] = w1 + DT * a1
    out[..., 3] = w2 + DT * a2
    out[..., 0] = t1 + DT * out[..., 1]
    out[..., 2] = t2 + DT * out[..., 3]
    return out


@numba.njit(cache=True)
def h_njit(x, k):
    out = np.empty(x.shape[:-1] + (2,))
    out[..., 0] = np.sin(x[..., 0])
    out[..., 1] = np.sin(x[..., 2])
    return out


Q = np.diag([1e-5, 4e-3, 1e-5, 4e-3])
R = np.diag([0.01, 0.01])
X0 = np.array([0.6, 0.0, -0.3, 0.0])
P0 = np.diag([0.05, 0.05, 0.05, 0.05])


def systems():
    nl = tk.NonlinearSystem(f_numpy, h_numpy, Q=Q, R=R, x0=X0, P0=P0)
    nl_jit = tk.NonlinearSystem(f_njit, h_njit, Q=Q, R=R, x0=X0, P0=P0)
    A = np.eye(4)
    A[1, 0], A[1, 1], A[1, 2] = -DT * (1 + COUPLING), 1 - DT * DAMPING, DT * COUPLING
    A[3, 2], A[3, 3], A[3, 0] = -DT * (1 + COUPLING), 1 - DT * DAMPING, DT * COUPLING
    A[0] = A[0] + DT * A[1]
    A[2] = A[2] + DT * A[3]
    C = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    lin = tk.LinearSystem(A=A, C=C, Q=Q, R=R, x0=X0, P0=P0)
    return nl, nl_jit, lin, tk.Censoring(lower=-LIMIT, upper=LIMIT)


@numba.njit
def _calls_alone(f, h, runs, steps, L, m, X):  # pragma: no cover - compiled
    """The calls of f and h the compiled ADF makes (every reading present), on fixed points ``X`` (64 L, n)."""
    acc = 0.0
    for r0 in range(0, runs, 64):
        rows = min(64, runs - r0) * L
        for t in range(steps):
            acc += f(X[:rows], t)[0, 0]
            for _ in range(m):
                acc += h(X[:rows], t + 1)[0, 0]
    return acc


def _timed(fn, repeat: int) -> tuple[float, float, float]:
    """Best wall, user and system seconds of ``repeat`` calls (the user and system times of the best wall)."""
    best = (float("inf"), 0.0, 0.0)
    for _ in range(repeat):
        r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        fn()
        t1, r1 = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF)
        cand = (t1 - t0, r1.ru_utime - r0.ru_utime, r1.ru_stime - r0.ru_stime)
        if cand[0] < best[0]:
            best = cand
    return best


def batched(runs: int, steps: int, repeat: int) -> None:
    nl, nl_jit, lin, clip = systems()
    y = tk.simulate(nl, steps, runs, channel=clip, seed=0).y
    print(f"(1) batched: {runs} runs x {steps} steps, n = 4, m = 2, {clip.at_limit(y).mean():.0%} of readings clipped")
    print(f"    per run-step, best of {repeat}: wall / user / sys microseconds; ratio of wall times")
    cases: list[tuple[str, Any]] = [
        ("linear ADF (compiled)", tk.AssumedDensityTobitFilter(lin, clip)),
        ("nonlinear ADF, numpy f, h", tk.NonlinearAssumedDensityFilter(nl, clip)),
        ("nonlinear ADF, njit f, h", tk.NonlinearAssumedDensityFilter(nl_jit, clip)),
        ("UKF (uncensored), njit f, h", tk.UnscentedKalmanFilter(nl_jit)),
    ]
    for _, est in cases:  # compile / warm up outside the timings
        est.filter(y[:4, :5], outputs=("mean",))
    L = 2 * 4 + 1  # the unscented rule's points at n = 4
    X = np.random.default_rng(0).normal(0.0, 0.3, size=(64 * L, 4))
    _calls_alone(f_njit, h_njit, 64, 2, L, 2, X)
    ref = None
    worst = 0.0
    for name, est in cases:
        wall, user, sys_ = _timed(lambda est=est: est.filter(y, outputs=("mean",)), repeat)
        per = 1e6 / (runs * steps)
        ratio = "" if ref is None else f"   x{wall / ref:6.2f} the linear ADF"
        if ref is not None and name.startswith("nonlinear ADF, njit"):
            worst = wall / ref
        print(f"    {name:30s} {wall * per:9.3f} / {user * per:9.3f} / {sys_ * per:7.3f}{ratio}", flush=True)
        ref = wall if ref is None else ref
    assert ref is not None
    wall, user, sys_ = _timed(lambda: _calls_alone(f_njit, h_njit, runs, steps, L, 2, X), repeat)
    print(
        f"    {'f, h calls alone (njit)':30s} {wall * per:9.3f} / {user * per:9.3f} / {sys_ * per:7.3f}"
        f"   x{wall / ref:6.2f} the linear ADF (the floor)",
        flush=True,
    )
    verdict = "met" if worst <= TARGET_BATCH else "not met"
    print(
        f"    target: the nonlinear ADF (njit f, h) <= {TARGET_BATCH:g}x the compiled linear ADF: {worst:.2f}x ({verdict})"
    )


def online(steps: int, repeat: int) -> None:
    from filterpy.kalman import MerweScaledSigmaPoints
    from filterpy.kalman import UnscentedKalmanFilter as FUKF

    nl, nl_jit, _, clip = systems()
    y = tk.simulate(nl, steps, 1, channel=clip, seed=1).y[0]

    def filterpy(readings):
        pts = MerweScaledSigmaPoints(4, alpha=1.0, beta=2.0, kappa=0.0)
        u = FUKF(dim_x=4, dim_z=2, dt=DT, fx=lambda x, dt: f_numpy(x, 0), hx=lambda x: h_numpy(x, 0), points=pts)
        u.x, u.P, u.Q, u.R = X0.copy(), P0.copy(), Q.copy(), R.copy()
        for z in readings:
            u.predict()
            u.update(z)

    def ours(est):
        def run(readings):
            s = est.init()
            for r in readings:
                s = est.step(s, r)

        return run

    cases = [
        ("filterpy UKF predict() + update()", filterpy),
        ("nonlinear ADF step, numpy f, h", ours(tk.NonlinearAssumedDensityFilter(nl, clip))),
        ("nonlinear ADF step, njit f, h", ours(tk.NonlinearAssumedDensityFilter(nl_jit, clip))),
        ("UKF step (uncensored), numpy f, h", ours(tk.UnscentedKalmanFilter(nl))),
        ("UKF step (uncensored), njit f, h", ours(tk.UnscentedKalmanFilter(nl_jit))),
    ]
    for _, fn in cases:
        fn(y[:5])
    times: dict[str, list[tuple[float, float, float]]] = {name: [] for name, _ in cases}
    for _ in range(repeat):  # interleaved: each repeat measures every case under the same load
        for name, fn in cases:
            times[name].append(_timed(lambda fn=fn: fn(y), 1))
    ref = np.array([t[0] for t in times[cases[0][0]]])
    print(f"(2) online: one run, {steps} readings per loop, {repeat} interleaved repeats")
    print("    microseconds per step: wall median (min..max), user / sys median; ratio to filterpy within each repeat")
    ratios = {}
    for name, _ in cases:
        arr = np.array(times[name]) * 1e6 / steps
        rs = np.array([t[0] for t in times[name]]) / ref
        ratios[name] = float(np.median(rs))
        print(
            f"    {name:36s} {np.median(arr[:, 0]):8.1f} ({arr[:, 0].min():7.1f}..{arr[:, 0].max():7.1f})  "
            f"{np.median(arr[:, 1]):7.1f} / {np.median(arr[:, 2]):5.1f}   x{ratios[name]:5.2f} ({rs.min():.2f}.."
            f"{rs.max():.2f})"
        )
    got = ratios["nonlinear ADF step, njit f, h"]
    verdict = "met" if got <= TARGET_ONLINE else "not met"
    print(f"    target: the nonlinear ADF's step (njit f, h) no slower than filterpy's UKF: x{got:.2f} ({verdict})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="tiny sizes (seconds)")
    ap.add_argument("--runs", type=int, default=10_000)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--online-steps", type=int, default=500)
    ap.add_argument("--online-repeat", type=int, default=7)
    a = ap.parse_args()
    print(
        f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (the timings are of a shared machine when it is high)"
    )
    if a.smoke:
        batched(200, 20, 1)
        online(50, 2)
    else:
        batched(a.runs, a.steps, a.repeat)
        online(a.online_steps, a.online_repeat)


if __name__ == "__main__":
    main()
