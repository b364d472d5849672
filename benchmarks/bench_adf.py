"""Assumed-density filters against the filters they improve on: cost per run-step on the same data.

Two tables. (1) numpy against numpy: each pair runs on the same readings, batched over runs (the
compiled kernels listed for reference): the censored oscillator of Miller Example 3 (n = 2, m = 1) and a
two-channel version (m = 2, channels in sequence), the fading oscillator of Geng et al. 2017 (L = 2) and
the protocol example (ell = 2, failures {0, 0.5, 1}); target: the numpy ADF at most 10x the numpy TKF.
(2) compiled against compiled: the ADF's compiled loop (:mod:`tobitkf.filters._compiled_loop`) against the
compiled TKF on the same readings of random stable systems (n = 2, m = 1 and n = 6, m = 3, censored
below), all outputs and the means alone; target: at most 3x the compiled TKF per run-step. Then the
generic ADF of a quantized sensor (7 levels, saturating ends) on the same systems, compiled against its numpy
loop and against the compiled censored ADF and TKF (on censored readings of the same system: the cost per
run-step of one channel family against another), and the compiled fading, protocol and saturation ADFs
against their numpy loops and the compiled TKF of the same channel where there is one. CPU seconds (best of ``--repeat``; BLAS held to one thread, the compiled loops
run on one thread) per run-step.

Run by hand::

    PYTHONPATH=src python benchmarks/bench_adf.py            # 10^4 runs x 100 steps, ~1 minute
    PYTHONPATH=src python benchmarks/bench_adf.py --smoke    # seconds
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402

import numpy as np  # noqa: E402

import tobitkf as tk  # noqa: E402
from _timing import best_time  # noqa: E402

TARGET = 10.0
TARGET_COMPILED = 3.0


def pairs(runs: int, steps: int):
    c, s = np.cos(0.05), np.sin(0.05)
    osc = tk.LinearSystem(
        A=[[c, -s], [s, c]], C=[[1.0, 0.0]], Q=0.01 * np.eye(2), R=[[0.1]], x0=[0.0, 0.0], P0=0.05 * np.eye(2)
    )
    cens = tk.Censoring(lower=0.0)
    y1 = tk.simulate(osc, steps, runs, censoring=cens, seed=0).y
    osc2 = tk.LinearSystem(
        A=[[c, -s], [s, c]],
        C=[[1.0, 0.0], [0.3, 1.0]],
        Q=0.01 * np.eye(2),
        R=np.diag([0.1, 0.2]),
        x0=[0.0, 0.0],
        P0=0.05 * np.eye(2),
    )
    cens2 = tk.Censoring(lower=[0.0, -0.1], upper=[np.inf, 0.5])
    y2 = tk.simulate(osc2, steps, runs, censoring=cens2, seed=0).y
    w = 0.052 * np.pi
    rot = [[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]]
    fsys = tk.LinearSystem(A=rot, C=[[1.0, 0.0]], Q=0.0025 * np.eye(2), R=[[1.0]], x0=[5.0, 0.0], P0=np.eye(2))
    fad = tk.RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    fy = tk.simulate(fsys, steps, runs, censoring=cens, measurement=fad, seed=0).y
    from tobitkf.channels.protocol import LAMBDA_BASE

    psys = tk.LinearSystem(A=rot, C=np.eye(2), Q=0.0025 * np.eye(2), R=np.eye(2), x0=[5.0, 0.0], P0=np.eye(2))
    ch = tk.ProtocolChannel(2, window=2, failures=LAMBDA_BASE, threshold=0.0)
    py = tk.simulate(psys, steps, runs, channel=ch, seed=0).y
    return [
        (
            "censored oscillator m=1",
            y1,
            tk.AssumedDensityTobitFilter(osc, cens, backend="numpy"),
            {
                "TKF (numpy)": tk.TobitKalmanFilter(osc, cens, backend="numpy"),
                "TKF exact_pv (numpy)": tk.TobitKalmanFilter(osc, cens, noise_term="exact_pv", backend="numpy"),
                "TKF (numba, reference)": tk.TobitKalmanFilter(osc, cens, backend="auto"),
            },
        ),
        (
            "two-sided, m=2 in sequence",
            y2,
            tk.AssumedDensityTobitFilter(osc2, cens2, backend="numpy"),
            {"TKF (numpy)": tk.TobitKalmanFilter(osc2, cens2, backend="numpy")},
        ),
        (
            "fading L=2",
            fy,
            tk.FadingAssumedDensityFilter(fsys, fad, cens, backend="numpy"),
            {
                "TKF-FM (numpy)": tk.FadingTobitKalmanFilter(fsys, fad, cens, backend="numpy"),
                "TKF-FM (numba, reference)": tk.FadingTobitKalmanFilter(fsys, fad, cens),
            },
        ),
        (
            "protocol ell=2",
            py,
            tk.ProtocolAssumedDensityFilter(psys, ch, backend="numpy"),
            {
                "PBTKF-IMSF (numpy)": tk.ProtocolTobitKalmanFilter(psys, ch, backend="numpy"),
                "PBTKF-IMSF (numba, reference)": tk.ProtocolTobitKalmanFilter(psys, ch),
            },
        ),
    ]


def random_system(n: int, m: int, seed: int) -> tk.LinearSystem:
    """A random stable system (spectral radius 0.95), unit process noise scale 0.1, R diagonal."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    A *= 0.95 / np.max(np.abs(np.linalg.eigvals(A)))
    C = rng.normal(size=(m, n))
    R = np.diag(rng.uniform(0.1, 0.5, m))
    return tk.LinearSystem(A=A, C=C, Q=0.1 * np.eye(n), R=R, x0=np.zeros(n), P0=np.eye(n))


def compiled_cases(runs: int, steps: int):
    """(label, readings, the compiled ADF, {name: comparator}) of table (2)."""
    out = []
    for n, m in ((2, 1), (6, 3)):
        sys_ = random_system(n, m, seed=n)
        cens = tk.Censoring(lower=np.full(m, -0.3))
        y = tk.simulate(sys_, steps, runs, censoring=cens, seed=1).y
        out.append(
            (
                f"censored n={n}, m={m}",
                y,
                tk.AssumedDensityTobitFilter(sys_, cens, backend="numba"),
                {"TKF (compiled)": tk.TobitKalmanFilter(sys_, cens, backend="numba", threads=1)},
            )
        )
    ((_, _, _, _), (_, _, _, _), (_, fy, fadf, fcomp), (_, py, padf, pcomp)) = pairs(runs, steps)
    out.append(
        (
            "fading L=2",
            fy,
            tk.FadingAssumedDensityFilter(fadf.system, fadf.fading, fadf.censoring, backend="numba"),
            {"ADF (numpy)": fadf, "TKF-FM (compiled)": fcomp["TKF-FM (numba, reference)"]},
        )
    )
    out.append(
        (
            "protocol ell=2",
            py,
            tk.ProtocolAssumedDensityFilter(padf.system, padf.channel, backend="numba"),
            {"ADF (numpy)": padf, "PBTKF-IMSF (compiled)": pcomp["PBTKF-IMSF (numba, reference)"]},
        )
    )
    for n, m in ((2, 1), (6, 3)):
        sys_ = random_system(n, m, seed=n)
        q = tk.Quantizer(0.25, lower=-0.75, upper=0.75)  # 7 levels, both ends saturating
        qy = tk.simulate(sys_, steps, runs, channel=q, seed=3).y
        cens = tk.Censoring(lower=np.full(m, -0.3))
        cy = tk.simulate(sys_, steps, runs, censoring=cens, seed=1).y
        out.append(
            (
                f"quantizer n={n}, m={m}",
                qy,
                tk.AssumedDensityFilter(sys_, q, backend="numba"),
                {
                    "ADF (numpy)": tk.AssumedDensityFilter(sys_, q, backend="numpy"),
                    "censored ADF (compiled)": (tk.AssumedDensityTobitFilter(sys_, cens, backend="numba"), cy),
                    "TKF (compiled)": (tk.TobitKalmanFilter(sys_, cens, backend="numba", threads=1), cy),
                },
            )
        )
    sat_sys = random_system(2, 2, seed=5)
    ch = tk.RandomSaturation([0.3, 0.4], [0.7, 0.75], level=[0.5, 0.8])
    sy = tk.simulate(sat_sys, steps, runs, channel=ch, seed=2).y
    out.append(
        (
            "saturation m=2",
            sy,
            tk.SaturationAssumedDensityFilter(sat_sys, ch, backend="numba"),
            {"ADF (numpy)": tk.SaturationAssumedDensityFilter(sat_sys, ch, backend="numpy")},
        )
    )
    return out


def compiled_table(runs: int, steps: int, repeat: int) -> None:
    print(f"\n(2) compiled: {runs} runs x {steps} steps, CPU time per run-step, one thread")
    print(f"{'case':<26}{'estimator':<24}{'outputs':<9}{'us/run-step':>12}{'ADF / it':>10}{'<=3x':>6}")
    for case, y, adf, others in compiled_cases(runs, steps):
        # a comparator is an estimator (on the same readings) or (estimator, its own readings of the same system)
        others = {k: v if isinstance(v, tuple) else (v, y) for k, v in others.items()}
        for est, ye in ((adf, y), *others.values()):  # warm up (compiles on the first call, cached afterwards)
            est.filter(ye[:2, :2])
        for outputs in ("all", ("mean",)):
            label = "all" if outputs == "all" else "mean"
            t_adf = best_time(lambda: adf.filter(y, outputs=outputs), repeat, cpu=True) / (runs * steps)
            print(f"{case:<26}{'ADF (compiled)':<24}{label:<9}{t_adf * 1e6:12.3f}", flush=True)
            for name, (est, ye) in others.items():
                t = best_time(lambda: est.filter(ye, outputs=outputs), repeat, cpu=True) / (runs * steps)
                ratio = t_adf / t
                ok = ("yes" if ratio <= TARGET_COMPILED else "no") if name == "TKF (compiled)" else "-"
                print(f"{'':<26}{name:<24}{label:<9}{t * 1e6:12.3f}{ratio:10.2f}{ok:>6}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--smoke", action="store_true", help="tiny version (seconds)")
    parser.add_argument("--runs", type=int, default=10_000)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    runs, steps, repeat = (50, 10, 1) if args.smoke else (args.runs, args.steps, args.repeat)
    print(f"(1) numpy: {runs} runs x {steps} steps, CPU time per run-step (BLAS 1 thread)")
    print(f"{'case':<28}{'estimator':<26}{'us/run-step':>12}{'ADF / it':>10}{'<=10x':>7}")
    for case, y, adf, others in pairs(runs, steps):
        for est in (adf, *others.values()):  # warm up (the numba kernel compiles on its first call)
            est.filter(y[:2, :2])
        t_adf = best_time(lambda: adf.filter(y), repeat, cpu=True) / (runs * steps)
        print(f"{case:<28}{type(adf).__name__:<26}{t_adf * 1e6:12.3f}", flush=True)
        for name, est in others.items():
            t = best_time(lambda: est.filter(y), repeat, cpu=True) / (runs * steps)
            ratio = t_adf / t
            ok = "-" if "reference" in name else ("yes" if ratio <= TARGET else "no")
            print(f"{'':<28}{name:<26}{t * 1e6:12.3f}{ratio:10.2f}{ok:>7}", flush=True)
    compiled_table(runs, steps, repeat)


if __name__ == "__main__":
    main()
