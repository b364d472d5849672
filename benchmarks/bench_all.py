"""Throughput of every non-core estimator family at its paper's example size, against filterpy.

For each family: 10^4 runs x 100 steps (``--runs``, ``--steps``), batched over runs, and
run-steps/second = runs x steps / CPU seconds (best of ``--repeat``; BLAS held to one thread,
so the figures are single-core). Where the family has a linear counterpart, filterpy's
``KalmanFilter`` on the equivalent (augmented) linear model, on the same data, looped over
``--peer-runs`` runs and scaled, gives the ratio (filterpy does no Tobit, fading, failure or
delay-correlation terms, so it does less arithmetic per step than the estimator it is set
against). The target is 10^6 run-steps/s.

Families and sizes (n state, m measurements, augmented size in brackets):

* fading    TKF-FM / KF-FM, Geng et al. 2017 oscillator: n=2, m=1, L=2 (n_xi = n(L+1) = 6)
* protocol  PBTKF-IMSF, Geng et al. protocol example: n=2, 2 sensors Round-Robin, ell=2 (n_xi = 6)
* delay     Algorithms C (chain), A (augmented), D (reorganized), paper example: n=2, m=1, d=3
            (A carries n(d+1) = 8); covariances are common to all runs, only means are per run
* hinf      regional H-infinity filter (5), Wang et al. 2010: n=3, m=2, r=2 (fixed gains, no
            covariance; filterpy has no counterpart)
* sstkf     steady-state TKF with the controlled limit (Miller §3.4.3 oscillator): n=2, m=1
* closed    LQG loop with a (Tobit) Kalman observer, DC-motor position (Miller §6.4): n=3, m=1,
            p=1; each run-step also simulates the plant (filterpy: the KF observer alone); the compiled
            loop (default) and the numpy loop, interleaved repeats, medians (min-max) and their ratio
            (target: >= 5x), and one run's microseconds per step

Run by hand::

    PYTHONPATH=src python benchmarks/bench_all.py            # ~2 minutes
    PYTHONPATH=src python benchmarks/bench_all.py --smoke    # tiny version (CI)
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402

import numpy as np  # noqa: E402

import tobitkf as tk  # noqa: E402
from _timing import best_time  # noqa: E402

TARGET = 1e6


def cpu_time(fn, repeat: int) -> float:
    """Best CPU time of ``repeat`` calls (robust on a machine shared with other jobs)."""
    return best_time(fn, repeat, cpu=True)


def filterpy_rate(F, Q, Hs, R, x0, P0, y, runs: int, repeat: int) -> float | None:
    """run-steps/s of filterpy's KalmanFilter looped over ``runs`` runs of ``y`` (N, T, m);
    ``Hs`` is one (m, n) matrix or a list of T of them."""
    try:
        from filterpy.kalman import KalmanFilter as FKF
    except ImportError:  # pragma: no cover
        return None
    nx, m = F.shape[0], y.shape[-1]
    T = y.shape[1]
    Hl = [np.atleast_2d(Hs)] * T if not isinstance(Hs, list) else [np.atleast_2d(h) for h in Hs]

    def loop():
        for run in y[:runs]:
            f = FKF(dim_x=nx, dim_z=m)
            f.F, f.Q, f.R = F, Q, np.atleast_2d(R)
            f.x, f.P = np.asarray(x0, float).reshape(nx, 1).copy(), np.asarray(P0, float).copy()
            for k in range(T):
                f.predict()
                f.update(run[k].reshape(m, 1), H=Hl[k])

    return runs * T / cpu_time(loop, repeat)


class Table:
    def __init__(self):
        self.rows = []
        print(f"{'family':<9}{'estimator':<34}{'size':<30}{'run-steps/s':>12}{'x filterpy':>11}{'>=1e6':>6}")

    def add(self, family, name, size, rate, fp=None):
        ratio = f"{rate / fp:11.1f}" if fp else f"{'-':>11}"
        print(f"{family:<9}{name:<34}{size:<30}{rate:12.3g}{ratio}{'yes' if rate >= TARGET else 'no':>6}", flush=True)
        self.rows.append((family, name, size, rate, None if not fp else rate / fp))


def bench_fading(tab, runs, steps, peer, repeat):
    from tobitkf.channels.fading import RiceFading
    from tobitkf.filters.fading import FadingKalmanFilter, FadingTobitKalmanFilter, augmented_measurement_matrix

    w = 0.052 * np.pi
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    sys_ = tk.LinearSystem(A=A, C=[[1.0, 0.0]], Q=0.0025 * np.eye(2), R=[[1.0]], x0=[5.0, 0.0], P0=np.eye(2))
    cens = tk.Censoring(lower=0.0)
    fad = RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    y = tk.simulate(sys_, steps, runs, censoring=cens, measurement=fad, seed=0).y
    nxi = 6
    Aa = np.zeros((nxi, nxi))
    Aa[:2, :2] = A
    Aa[2:, :4] = np.eye(4)
    Qa = np.zeros((nxi, nxi))
    Qa[:2, :2] = sys_.process_cov(0)
    Pa = np.zeros((nxi, nxi))
    Pa[:2, :2] = sys_.P0
    Hs = [augmented_measurement_matrix(sys_, fad, k) for k in range(1, steps + 1)]
    fp = filterpy_rate(Aa, Qa, Hs, [[1.0]], np.r_[sys_.x0, np.zeros(4)], Pa, y, peer, repeat)
    size = "n=2 m=1 L=2 (n_xi=6)"
    FadingTobitKalmanFilter(sys_, fad, cens).filter(y[:2, :3])  # compile (or load) the kernel outside the timing
    t = cpu_time(lambda: FadingTobitKalmanFilter(sys_, fad, cens).filter(y), repeat)
    tab.add("fading", "TKF-FM (tkf-fm)", size, runs * steps / t, fp)
    t = cpu_time(lambda: FadingTobitKalmanFilter(sys_, fad, cens, backend="numpy").filter(y), repeat)
    tab.add("fading", "TKF-FM, numpy path", size, runs * steps / t, fp)
    t = cpu_time(lambda: FadingKalmanFilter(sys_, fad).filter(y), repeat)
    tab.add("fading", "fading KF baseline (kf-fm)", size, runs * steps / t, fp)


def bench_protocol(tab, runs, steps, peer, repeat):
    from tobitkf.channels.protocol import LAMBDA_BASE, ProtocolChannel
    from tobitkf.filters.protocol import protocol_tobit_kalman_filter
    from tobitkf.filters.protocol_model import augmented_transition, noise_input, stacked_measurement

    w = 0.052 * np.pi
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    sys_ = tk.LinearSystem(A=A, C=np.eye(2), Q=0.0025 * np.eye(2), R=np.eye(2), x0=[5.0, 0.0], P0=np.eye(2))
    ch = ProtocolChannel(2, window=2, failures=LAMBDA_BASE, threshold=0.0)
    y = tk.simulate(sys_, steps, runs, seed=0, channel=ch).y
    ell = 2
    F = augmented_transition(A, ell)
    B = noise_input(2, ell)
    sched = ch.schedule.scheduled(steps) - 1
    Hs = [(0.5 * stacked_measurement(sys_.measurement(1)[h], ell))[None, :] for h in sched]
    fp = filterpy_rate(
        F, B @ sys_.process_cov(0) @ B.T, Hs, [[1.0]], np.tile(sys_.x0, ell + 1), np.eye(6), y, peer, repeat
    )
    t = cpu_time(lambda: protocol_tobit_kalman_filter(sys_, ch, y), repeat)
    tab.add("protocol", "PBTKF-IMSF (variance term)", "n=2 p=2 RR ell=2 (n_xi=6)", runs * steps / t, fp)


def bench_delay(tab, runs, steps, peer, repeat):
    from tobitkf.filters.delay_augmented import _augmented_matrices, augmented_lmmse
    from tobitkf.filters.delay_chain import chain_lmmse
    from tobitkf.filters.delay_reorganized import reorganized_lmmse
    from tobitkf.models.delay import paper_example, paper_prior
    from tobitkf.simulate.delay import simulate_delay

    d = 3
    sys_, prior = paper_example(S=0.3, d=d), paper_prior(d)
    y = simulate_delay(sys_, prior, steps, runs, seed=1).y
    AA, _, G, HH, *_ = _augmented_matrices(sys_, d)
    fp = filterpy_rate(
        AA,
        G @ np.atleast_2d(sys_.Qw) @ G.T,
        sys_.gamma_mean(0) * HH,
        np.atleast_2d(sys_.Qv),
        prior.mean.reshape(-1),
        prior.cov,
        y,
        peer,
        repeat,
    )
    size = "n=2 m=1 d=3"
    t = cpu_time(lambda: chain_lmmse(sys_, prior, y), repeat)
    tab.add("delay", "Algorithm C (chain_lmmse)", size, runs * steps / t, fp)
    t = cpu_time(lambda: augmented_lmmse(sys_, prior, y), repeat)
    tab.add("delay", "Algorithm A (augmented_lmmse)", size + " (n(d+1)=8)", runs * steps / t, fp)
    t = cpu_time(lambda: reorganized_lmmse(sys_, prior, y), repeat)
    tab.add("delay", "Algorithm D (reorganized_lmmse)", size, runs * steps / t, fp)


def bench_hinf(tab, runs, steps, peer, repeat):
    from tobitkf.design.hinf import WANG2010_PAPER
    from tobitkf.filters.hinf import RegionalHinfFilter
    from tobitkf.models.ross import wang2010_model
    from tobitkf.simulate.ross import simulate_ross, wang2010_disturbances

    model = wang2010_model()
    w, v = wang2010_disturbances(steps)
    y = simulate_ross(model, steps, runs, x0=WANG2010_PAPER["x0"], w=w, v=v, seed=0).y
    filt = RegionalHinfFilter(WANG2010_PAPER["Af"], WANG2010_PAPER["Bf"], model.M)
    t = cpu_time(lambda: filt.filter(y), repeat)
    tab.add("hinf", "RegionalHinfFilter (5)", "n=3 m=2 r=2", runs * steps / t)


def bench_sstkf(tab, runs, steps, peer, repeat):
    from tobitkf.filters.steady_state import SteadyStateTobitKalmanFilter

    w = 0.1
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    sys_ = tk.LinearSystem(A=A, C=[[1.0, 0.0]], Q=0.01 * np.eye(2), R=[[0.1]], x0=[0.0, 0.0], P0=0.05 * np.eye(2))
    ylat = tk.simulate(sys_, steps, runs, seed=0).y_latent
    fp = filterpy_rate(
        A, sys_.process_cov(0), sys_.measurement(1), sys_.measurement_cov(1), sys_.x0, sys_.P0, ylat, peer, repeat
    )
    ss = SteadyStateTobitKalmanFilter(sys_, 0.95)
    ss.filter_controlled(ylat[:2, :3])  # compile (or load) the kernel outside the timing
    t = cpu_time(lambda: ss.filter_controlled(ylat), repeat)
    tab.add("sstkf", "SteadyStateTKF.filter_controlled", "n=2 m=1", runs * steps / t, fp)
    ss = SteadyStateTobitKalmanFilter(sys_, 0.95, backend="numpy")
    t = cpu_time(lambda: ss.filter_controlled(ylat), repeat)
    tab.add("sstkf", "SteadyStateTKF, numpy path", "n=2 m=1", runs * steps / t, fp)


def bench_closed(tab, runs, steps, peer, repeat):
    from tobitkf.control.closed_loop import simulate_closed_loop
    from tobitkf.control.plants import dc_motor_position
    from tobitkf.experiments.miller_control import _motor_lqr, _motor_plant

    plant, _ = _motor_plant(dc_motor_position)
    K = _motor_lqr(plant)
    sim = tk.simulate(plant, steps, min(runs, peer), seed=0)
    fp = filterpy_rate(
        plant.transition(0),
        plant.process_cov(0),
        plant.measurement(1),
        plant.measurement_cov(1),
        plant.x0,
        plant.P0,
        sim.y,
        peer,
        repeat,
    )
    C = plant.measurement(1)
    upper = float(np.sqrt(plant.measurement_cov(1)[0, 0]))
    notes = []
    # the batch of the table, and the size of Miller's §6.4 example (40 runs x 3000 steps; smoke: 4 x 100)
    sizes = [(runs, steps), (40, 3000) if steps >= 100 else (4, 100)]
    for obs, kw in (
        ("kf", {}),
        ("tkf", {"censoring": tk.Censoring(upper=upper)}),
        ("tkf-moving", {"xi_uncensored": 0.95}),
        ("sstkf", {"xi_uncensored": 0.95}),
    ):
        simulate_closed_loop(plant, K, 3, 2, observer=obs, seed=0, **kw)  # compile outside the timing
        for N, T in sizes:
            # the compiled loop (default) and the numpy loop, interleaved; CPU time per call
            times: dict[str, list[float]] = {"auto": [], "numpy": []}
            for _ in range(max(repeat, 1)):
                for be in times:
                    times[be].append(
                        cpu_time(
                            lambda: simulate_closed_loop(plant, K, T, N, observer=obs, seed=0, backend=be, **kw), 1
                        )
                    )
            med = {be: float(np.median(ts)) for be, ts in times.items()}
            if (N, T) == (runs, steps):
                for be, label in (("auto", "compiled"), ("numpy", "numpy loop")):
                    tab.add(
                        "closed", f"closed loop {obs} ({label})", f"n={plant.n} m={C.shape[0]} p=1", N * T / med[be], fp
                    )
            spread = ", ".join(
                f"{be} {med[be] / (N * T) * 1e9:.0f} ns ({min(ts) / (N * T) * 1e9:.0f}-{max(ts) / (N * T) * 1e9:.0f})"
                for be, ts in times.items()
            )
            notes.append(
                f"  closed {obs} {N} runs x {T} steps: per run-step, median of {len(times['auto'])} (min-max): "
                f"{spread}; compiled x{med['numpy'] / med['auto']:.1f} the numpy loop (target >= 5)"
            )
        one = min(steps * 20, 2000)
        lat = [
            cpu_time(lambda: simulate_closed_loop(plant, K, one, 1, observer=obs, seed=0, **kw), 1) for _ in range(3)
        ]
        notes.append(f"  closed {obs}: one run x {one} steps, compiled: {np.median(lat) / one * 1e6:.2f} us/step")
    print("\n".join(notes))


FAMILIES = {
    "fading": bench_fading,
    "protocol": bench_protocol,
    "delay": bench_delay,
    "hinf": bench_hinf,
    "sstkf": bench_sstkf,
    "closed": bench_closed,
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="tiny version for CI (200 runs x 20 steps)")
    ap.add_argument("--runs", type=int, default=10_000)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--peer-runs", type=int, default=20, help="runs of the filterpy loop (scaled)")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--only", nargs="+", choices=sorted(FAMILIES), help="families to run")
    args = ap.parse_args()
    runs, steps, peer, repeat = args.runs, args.steps, args.peer_runs, args.repeat
    if args.smoke:
        runs, steps, peer, repeat = 200, 20, 2, 1
    print(f"{runs} runs x {steps} steps, single-core CPU time, best of {repeat}; filterpy looped over {peer} runs")
    tab = Table()
    for name in args.only or FAMILIES:
        FAMILIES[name](tab, runs, steps, peer, repeat)


if __name__ == "__main__":
    main()
