"""Per-step cost of the delay-system estimators: Algorithm C (chain), A (augmented), D (reorganized).

Spec 002 §2.7 / §5 item 11: C's cost per step should not depend on the delay d; dense
augmentation (A) grows like (d+1)^3 once the matrices are large enough for the flops to
dominate the Python overhead; D grows like d^2. The source claims its (D-type) scheme "does
not increase computational and storage load when the delay is large"; this measures it.

Run by hand:  PYTHONPATH=src python benchmarks/bench_delay.py [--smoke] [--runs N]
"""

from __future__ import annotations

import argparse

import numpy as np

from _timing import best_time
from tobitkf.filters.delay_augmented import augmented_lmmse
from tobitkf.filters.delay_chain import chain_lmmse
from tobitkf.filters.delay_reorganized import reorganized_lmmse
from tobitkf.models.delay import DelayFadingSystem, FadingPMF, HistoryPrior, paper_example, paper_prior
from tobitkf.simulate.delay import simulate_delay


def random_model(n: int, d: int, seed: int = 0) -> tuple[DelayFadingSystem, HistoryPrior]:
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((n, n))
    A *= 0.7 / max(abs(np.linalg.eigvals(A)))
    sys = DelayFadingSystem(
        A,
        rng.standard_normal((1, n)),
        np.ones((n, 1)),
        0.3,
        0.3,
        0.2,
        d,
        A_mult=0.1 * rng.standard_normal((1, n, n)),
        q_mult=[0.16],
        fading=FadingPMF([0.95, 0.98, 1.0], [0.05, 0.15, 0.8]),
    )
    return sys, HistoryPrior.repeated(np.zeros(n), 0.01 * np.eye(n), d)


def per_step(fn, y, repeat: int) -> float:
    return best_time(lambda: fn(y), repeat) / y.shape[-2]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="tiny version (seconds)")
    ap.add_argument("--runs", type=int, default=100, help="Monte Carlo runs per call (batched)")
    args = ap.parse_args()
    delays = (1, 3) if args.smoke else (1, 3, 7, 15)
    dims = (2,) if args.smoke else (2, 10)
    T = 40 if args.smoke else 200
    repeat = 1 if args.smoke else 3
    print(f"per-step time in microseconds, T = {T}, runs = {args.runs} (batched), best of {repeat}")
    for n in dims:
        print(f"\nn = {n} ({'paper example' if n == 2 else 'random model'})")
        print(f"{'d':>4} {'C chain':>10} {'A augm.':>10} {'D reorg.':>10} {'A/C':>7} {'D/C':>7} {'steps/s C':>11}")
        rows = []
        for d in delays:
            sys, prior = (paper_example(S=0.2, d=d), paper_prior(d)) if n == 2 else random_model(n, d)
            y = simulate_delay(sys, prior, T, args.runs, seed=1).y
            # uncorrelated prior: D starts at t = 0 with zero Ψ (no augmented warm-up)
            tc = per_step(lambda yy: chain_lmmse(sys, prior, yy), y, repeat)
            ta = per_step(lambda yy: augmented_lmmse(sys, prior, yy), y, repeat)
            td = per_step(lambda yy: reorganized_lmmse(sys, prior, yy), y, repeat)
            rows.append((d, tc, ta, td))
            print(
                f"{d:>4} {tc * 1e6:>10.1f} {ta * 1e6:>10.1f} {td * 1e6:>10.1f} {ta / tc:>7.2f} {td / tc:>7.2f} "
                f"{1 / tc:>11.0f}"
            )
        if len(rows) >= 2:
            dd = np.log([r[0] + 1 for r in rows])
            for name, col in (("C", 1), ("A", 2), ("D", 3)):
                slope = np.polyfit(dd, np.log([r[col] for r in rows]), 1)[0]
                print(
                    f"  log-log slope of {name} time vs (d+1): {slope:.2f}"
                    + ("  (flat = 0)" if name == "C" else "  (dense flops: 3)" if name == "A" else "  (flops: 2)")
                )
            c_spread = max(r[1] for r in rows) / min(r[1] for r in rows)
            print(f"  C max/min over d: {c_spread:.2f}")


if __name__ == "__main__":
    main()
