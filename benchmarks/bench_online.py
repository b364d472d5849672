"""Online benchmark: the latency of one ``step`` (one run, one reading) of every estimator.

Every family is driven as an online user drives it, ``state = est.step(state, y_k)`` in a Python loop,
on its paper's example size, and compared with filterpy's ``predict()`` + ``update()`` of the
equivalent linear model measured in the same process (the peer of the target). Each timing is the
median of ``repeat`` loops over ``steps`` readings, the repeats interleaved across the cases and the
ratio to filterpy taken within each repeat (this machine is shared: medians and the spread min..max are
printed). The KF, TKF and dropping-KF steps run the compiled kernels when numba is installed (a single step
through the block kernel), the fading and protocol TKF steps their compiled loops for one reading, the
steady-state TKF and the tracker (once its gain is fixed) the fixed-gain recursion in numpy, the other
Gaussian families the compiled shared predict and update (:mod:`tobitkf.filters._compiled_step`) around their
own moments; the "(numpy)" rows the reference path.

Targets: KF and TKF step no slower than filterpy's predict + update;
every other family within 5x of it.

``--smoke`` runs a tiny version (CI). Run by hand:  python benchmarks/bench_online.py
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import _timing  # noqa: F401 (prints the process's wall, user and system time at exit)
import tobitkf as tk


def _osc(w: float = 0.05, **kw) -> tk.LinearSystem:
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    base = dict(A=A, C=[[1.0, 0.0]], Q=1e-3 * np.eye(2), R=[[0.01]], x0=[1.0, 0.0], P0=np.eye(2))
    base.update(kw)
    return tk.LinearSystem(**base)


def _loop_times(step, readings, repeat: int) -> list[float]:
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        step(readings)
        out.append((time.perf_counter() - t0) / len(readings))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="tiny sizes for CI")
    args = ap.parse_args()
    steps, repeat = (60, 2) if args.smoke else (1_000, 9)
    from filterpy.kalman import KalmanFilter as FKF

    sys_ = _osc()
    cens = tk.Censoring(lower=0.0)
    y = tk.simulate(sys_, steps, 1, censoring=cens, seed=0).y[0]

    def filterpy(readings):
        f = FKF(dim_x=2, dim_z=1)
        f.F, f.H, f.Q, f.R = sys_.transition(0), sys_.measurement(1), sys_.process_cov(0), sys_.measurement_cov(1)
        f.x, f.P = sys_.x0.reshape(2, 1).copy(), sys_.P0.copy()
        for z in readings:
            f.predict()
            f.update(z)

    def online(est, state0=None):
        def run(readings):
            s = est.init() if state0 is None else state0
            for r in readings:
                s = est.step(s, r)

        return run

    from tobitkf.channels.fading import RiceFading
    from tobitkf.channels.protocol import LAMBDA_BASE
    from tobitkf.models.delay import paper_example, paper_prior
    from tobitkf.simulate.delay import simulate_delay

    fad = RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    yf = tk.simulate(sys_, steps, 1, censoring=cens, measurement=fad, seed=1).y[0]
    sp = _osc(C=np.eye(2), Q=0.0025 * np.eye(2), R=np.eye(2), x0=[5.0, 0.0])
    ch = tk.ProtocolChannel(2, window=2, failures=LAMBDA_BASE, threshold=0.0)
    yp = tk.simulate(sp, steps, 1, channel=ch, seed=2).y[0]
    dsys, dprior = paper_example(), paper_prior()
    yd = simulate_delay(dsys, dprior, steps, 1, seed=3).y[0]
    from tobitkf.design.hinf import WANG2010_PAPER
    from tobitkf.models.ross import wang2010_model

    model = wang2010_model()
    yh = np.random.default_rng(4).normal(size=(steps, 2)) * 0.1
    rng = np.random.default_rng(5)
    frames = [rng.normal(size=(3, 2)) * 0.5 + np.array([[0.0, 0.0], [20.0, 0.0], [40.0, 0.0]]) for _ in range(steps)]
    tracker = tk.MultiTargetTracker()
    cases = [
        ("filterpy predict() + update()", filterpy, y),
        ("KalmanFilter", online(tk.KalmanFilter(sys_)), y),
        ("TobitKalmanFilter", online(tk.TobitKalmanFilter(sys_, cens)), y),
        ("DroppingKalmanFilter", online(tk.DroppingKalmanFilter(sys_, cens)), y),
        ("KalmanFilter (numpy)", online(tk.KalmanFilter(sys_, backend="numpy")), y),
        ("TobitKalmanFilter (numpy)", online(tk.TobitKalmanFilter(sys_, cens, backend="numpy")), y),
        ("SteadyStateTobitKalmanFilter", online(tk.SteadyStateTobitKalmanFilter(sys_, 0.7)), y),
        ("FadingTobitKalmanFilter (L=2)", online(tk.FadingTobitKalmanFilter(sys_, fad, cens)), yf),
        ("ProtocolTobitKalmanFilter (l=2)", online(tk.ProtocolTobitKalmanFilter(sp, ch)), yp),
        ("ChainLMMSE (d=3)", online(tk.ChainLMMSE(dsys, dprior)), yd),
        ("AugmentedLMMSE (d=3)", online(tk.AugmentedLMMSE(dsys, dprior)), yd),
        ("ReorganizedInnovationLMMSE (d=3)", online(tk.ReorganizedInnovationLMMSE(dsys, dprior)), yd),
        (
            "RegionalHinfFilter (n=3, m=2)",
            online(tk.RegionalHinfFilter(WANG2010_PAPER["Af"], WANG2010_PAPER["Bf"], model.M)),
            yh,
        ),
        (
            "MultiTargetTracker (3 targets)",
            online(tracker, tracker.init(np.array([[0.0, 0.0], [20.0, 0.0], [40.0, 0.0]]))),
            frames,
        ),
    ]
    for _, fn, rec in cases:  # compile / warm up outside the timings
        fn(rec[:5])
    # The repeats are interleaved: repeat r times every case once, one after the other, so that each
    # repeat measures every case under the same load, and the ratio to filterpy is taken within the
    # repeat (this machine is shared: a load change between two cases moves their times, not the
    # within-repeat ratios). Reported: the median time, and the median (min..max) of the ratios.
    times = {name: [] for name, _, _ in cases}
    for _ in range(repeat):
        for name, fn, rec in cases:
            times[name].extend(_loop_times(fn, rec, 1))
    ref_name = cases[0][0]
    ref_t = np.array(times[ref_name])
    print(
        f"one run, {steps} readings per loop, {repeat} interleaved repeats; microseconds per step: median "
        "(min..max); ratio to filterpy within each repeat: median (min..max)"
    )
    ratios = {}
    for name, _, _ in cases:
        ts = np.array(times[name]) * 1e6
        rs = np.array(times[name]) / ref_t
        ratios[name] = float(np.median(rs))
        print(
            f"  {name:36s} {np.median(ts):9.2f}  ({ts.min():7.2f}..{ts.max():7.2f})   "
            f"x{np.median(rs):6.2f} ({rs.min():5.2f}..{rs.max():5.2f}) filterpy"
        )
    kf_tkf = max(ratios["KalmanFilter"], ratios["TobitKalmanFilter"])
    skip = (ref_name, "KalmanFilter", "TobitKalmanFilter", "KalmanFilter (numpy)", "TobitKalmanFilter (numpy)")
    worst = max((v, k) for k, v in ratios.items() if k not in skip)
    print(
        f"targets: KF and TKF step <= 1x filterpy: {kf_tkf:.2f}x ({'met' if kf_tkf <= 1 else 'not met'}); "
        f"every other family <= 5x: worst {worst[0]:.2f}x, {worst[1]} ({'met' if worst[0] <= 5 else 'not met'})"
    )


if __name__ == "__main__":
    main()
