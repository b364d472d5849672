"""Particle filter benchmark: particle-steps per second per core, and memory flat in T.

(a) Throughput: the censored oscillator of Miller Example 3 (n = 2, m = 1, censoring at 0), N runs x
    N_p particles per run, batched; particle-steps / CPU second (best of ``--repeat``; BLAS held to
    one thread, so the figure is per core), for the locally optimal and the bootstrap proposal, and
    for the fading (Geng et al. 2017, n_xi = 6) and protocol (Round-Robin, ell = 2, n_xi = 6) channels.
    The target: >= 1e6 particle-steps/s per core for n = 2, m = 1.
(b) Memory: peak traced allocation (tracemalloc) of ``filter(y, outputs="last")`` for T and 10 T steps:
    the particles are O(N N_p n_x) and nothing grows with T (the ratio should be ~1).
(c) The target: the censored oscillator (n = 2, m = 1, censoring at 0), ``ParticleFilter`` compiled
    against a plain vectorised numpy particle filter written here (:func:`plain_filter`, the filter one
    would write by hand: all runs' particles as one array, the same proposals, log-sum-exp weights,
    systematic resampling), for the optimal and the bootstrap proposal, in the same process,
    interleaved, medians and (min-max) of 5 of CPU (user + system), user, system and wall time (µs per
    run-step), the ratio per round (plain / ours) as median and (min-max), by CPU time (the figure that
    holds on a loaded machine) and by wall time, the load average stated. Target: the compiled optimal filter at least 3x the plain one at 10^3 runs x 100 steps x
    4,000 particles (``--target``; the default is smaller). ``--numpy-path`` adds ParticleFilter's own
    numpy path.
(d) Peers on the same *uncensored* bootstrap model (the packages have no censored proposal): ours
    compiled, the ``particles`` package (N. Chopin's SMC library: one run per ``SMC`` object, its
    bootstrap filter, systematic resampling at ESS < N/2, the filtering moments collected) and
    cuthbert's JAX particle filter (``vmap`` over runs of its ``lax.scan`` filter, adaptive systematic
    resampling, JIT-compiled before timing), medians of 5; a peer that is not installed is skipped
    (``pip install "tobitkf[bench]"`` for cuthbert; ``pip install --no-deps particles``, which keeps numpy 2).
    Target: ours faster than both.
(e) The channels beyond censoring, compiled against ParticleFilter's own numpy path (the same model and
    proposal), interleaved, µs per run-step (CPU and wall), medians and (min-max) of ``--repeat``: random
    saturation (two sensors, bootstrap), a quantizer (two channels; its default, the locally optimal proposal,
    and the bootstrap) and Rice fading of order 2 (n_xi = 6, bootstrap), at ``--channel-runs`` x
    ``--target-steps`` x ``--target-particles``.

Run by hand::

    PYTHONPATH=src python benchmarks/bench_particle.py            # ~1 minute
    PYTHONPATH=src python benchmarks/bench_particle.py --smoke    # seconds
    PYTHONPATH=src python benchmarks/bench_particle.py --target    # (c) and (d) at the target size
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import statistics  # noqa: E402
import tracemalloc  # noqa: E402

import numpy as np  # noqa: E402
from scipy.special import log_ndtr, ndtri_exp  # noqa: E402

import tobitkf as tk  # noqa: E402
from _timing import best_time, measure  # noqa: E402

TARGET = 1e6


def oscillator(omega: float = 0.05) -> tk.LinearSystem:
    c, s = np.cos(omega), np.sin(omega)
    return tk.LinearSystem(
        A=[[c, -s], [s, c]], C=[[1.0, 0.0]], Q=0.01 * np.eye(2), R=[[0.1]], x0=[0.0, 0.0], P0=0.05 * np.eye(2)
    )


def other_channels():
    """(e): the channels beyond censoring: (name, system, channel, proposal)."""
    two = tk.LinearSystem(
        A=[[0.95, 0.1], [0.0, 0.9]], C=[[1.0, 0.0], [0.5, 1.0]], Q=0.05 * np.eye(2), R=np.diag([0.1, 0.2]),
        x0=[0.2, 0.0], P0=np.eye(2),
    )  # fmt: skip
    sat = tk.RandomSaturation([0.3, 0.2], [0.8, 0.9], level=[0.5, 0.4])
    quant = tk.Quantizer(0.2, lower=-0.6, upper=0.6)
    _, _, fsys, fch, _, _ = cases()[2]
    return [
        ("saturation m=2, bootstrap", two, sat, "prior"),
        ("quantizer m=2, optimal", two, quant, "optimal"),
        ("quantizer m=2, bootstrap", two, quant, "prior"),
        ("fading L=2, bootstrap", fsys, fch, "prior"),
    ]


def channels_vs_numpy(runs: int, particles: int, steps: int, repeat: int) -> dict:
    """(e): µs per run-step of the compiled filter and ParticleFilter's numpy path on the channels beyond
    censoring, interleaved; ratios per round = numpy time / compiled time."""
    print(
        f"(e) the channels beyond censoring, compiled vs ParticleFilter's numpy path: {runs} runs x {steps} steps x "
        f"{particles} particles; µs per run-step, medians (min-max) of {repeat}, interleaved; {_load()}"
    )
    print(HEAD)
    out = {}
    for name, sys_, channel, proposal in other_channels():
        pieces = channel if isinstance(channel, list) else [channel]
        cens = next((c for c in pieces if isinstance(c, tk.Censoring)), None)
        drawer = next((c for c in pieces if not isinstance(c, tk.Censoring)), None)
        y = tk.simulate(sys_, steps, runs, channel=drawer, censoring=cens, seed=0).y
        pfs = {
            be: tk.ParticleFilter(sys_, channel, particles=particles, proposal=proposal, seed=1, backend=be)
            for be in ("numba", "numpy")
        }
        pfs["numba"].filter(y[:1, :2])  # compile (or load the cache)
        t = interleaved({be: (lambda pf=pf: pf.filter(y, outputs="mean")) for be, pf in pfs.items()}, repeat)
        r = ratios(t["numpy"], t["numba"])
        print(f"  {name}")
        print(_row("ours (compiled)", t["numba"], runs * steps))
        print(_row("ours (numpy path)", t["numpy"], runs * steps))
        print(f"  -> compiled faster by CPU {_med(r['cpu'])}, wall {_med(r['wall'])}", flush=True)
        out[name] = dict(samples=t, ratio=statistics.median(r["cpu"]), ratios=r)
    return out


def cases():
    sys_ = oscillator()
    cens = tk.Censoring(lower=0.0)
    w = 0.052 * np.pi
    rot = [[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]]
    fsys = tk.LinearSystem(A=rot, C=[[1.0, 0.0]], Q=0.0025 * np.eye(2), R=[[1.0]], x0=[5.0, 0.0], P0=np.eye(2))
    fad = tk.RiceFading.gaussian(2, [0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    psys = tk.LinearSystem(A=rot, C=np.eye(2), Q=0.0025 * np.eye(2), R=np.eye(2), x0=[5.0, 0.0], P0=np.eye(2))
    from tobitkf.channels.protocol import LAMBDA_BASE

    ch = tk.ProtocolChannel(2, window=2, failures=LAMBDA_BASE, threshold=0.0)
    return [
        ("censored oscillator, optimal", "n=2 m=1", sys_, cens, {"censoring": cens}, "optimal"),
        ("censored oscillator, bootstrap", "n=2 m=1", sys_, cens, {"censoring": cens}, "prior"),
        (
            "fading L=2, bootstrap",
            "n_xi=6 m=1",
            fsys,
            [fad, tk.Censoring(lower=0.0)],
            {"censoring": tk.Censoring(lower=0.0), "measurement": fad},
            "prior",
        ),
        ("protocol ell=2, optimal", "n_xi=6 m=1", psys, ch, {"channel": ch}, "optimal"),
    ]


def throughput(runs: int, particles: int, steps: int, repeat: int) -> None:
    print(f"(a) throughput: {runs} runs x {particles} particles x {steps} steps (CPU time, BLAS 1 thread)")
    print(f"{'case':<34}{'size':<12}{'particle-steps/s':>18}{'>=1e6':>7}")
    for name, size, sys_, channel, sim_kw, proposal in cases():
        y = tk.simulate(sys_, steps, runs, seed=0, **sim_kw).y
        pf = tk.ParticleFilter(sys_, channel, particles=particles, proposal=proposal, seed=1)
        t = best_time(lambda: pf.filter(y, outputs="mean"), repeat, cpu=True)
        rate = runs * particles * steps / t
        print(f"{name:<34}{size:<12}{rate:18.3g}{'yes' if rate >= TARGET else 'no':>7}", flush=True)


def memory(runs: int, particles: int, steps: int) -> None:
    print(f"(b) memory: peak traced allocation of filter(y, outputs='last'), {runs} runs x {particles} particles")
    sys_, cens = oscillator(), tk.Censoring(lower=0.0)
    peaks = {}
    for T in (steps, 10 * steps):
        y = tk.simulate(sys_, T, runs, censoring=cens, seed=0).y
        pf = tk.ParticleFilter(sys_, cens, particles=particles, seed=1)
        tracemalloc.start()
        pf.filter(y, outputs="last")
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        peaks[T] = peak
        print(f"  T = {T:6d}: peak {peak / 2**20:8.1f} MiB (the readings themselves: {y.nbytes / 2**20:.2f} MiB)")
    print(f"  peak(10 T) / peak(T) = {peaks[10 * steps] / peaks[steps]:.3f}  (flat in T: ~1)")


def plain_filter(sys_: tk.LinearSystem, y: np.ndarray, lower: float, particles: int, proposal: str, seed: int):
    """A plain vectorised numpy particle filter for one channel censored below at ``lower`` (n states, m = 1):
    all runs' particles as one (N, Np, n) array, the bootstrap or the locally optimal proposal (a
    truncated-normal draw of the latent reading when censored), log-sum-exp weights, systematic resampling
    when the ESS falls below half the particles. Returns the filtered means (N, T, n)."""
    rng = np.random.default_rng(seed)
    A, Q = sys_.transition(0), sys_.process_cov(0)
    c, r = sys_.measurement(1)[0], float(sys_.measurement_cov(1)[0, 0])
    n, (N, T, _) = A.shape[0], y.shape
    Np = particles
    X = sys_.x0 + rng.standard_normal((N, Np, n)) @ np.linalg.cholesky(sys_.P0).T
    logw = np.full((N, Np), -np.log(Np))
    Lq = np.linalg.cholesky(Q)
    s2 = c @ Q @ c + r
    g = Q @ c / s2
    Lc = np.linalg.cholesky(Q - s2 * np.outer(g, g))
    s, sr = np.sqrt(s2), np.sqrt(r)
    means = np.empty((N, T, n))
    for t in range(T):
        yt = y[:, t, 0][:, None]
        cens = yt <= lower
        if proposal == "optimal":
            M = X @ A.T
            pred = M @ c
            lm = log_ndtr((lower - pred) / s)
            z = np.where(cens, pred + ndtri_exp(np.log(rng.random((N, Np))) + lm) * s, yt)
            inc = np.where(cens, lm, -0.5 * ((yt - pred) / s) ** 2 - np.log(s))
            X = M + (z - pred)[..., None] * g + rng.standard_normal((N, Np, n)) @ Lc.T
        else:
            X = X @ A.T + rng.standard_normal((N, Np, n)) @ Lq.T
            mu = X @ c
            inc = np.where(cens, log_ndtr((lower - mu) / sr), -0.5 * ((yt - mu) / sr) ** 2)
        logw = logw + inc
        top = logw.max(axis=1, keepdims=True)
        W = np.exp(logw - top)
        W /= W.sum(axis=1, keepdims=True)
        logw = np.log(W)
        means[:, t] = np.einsum("rp,rpi->ri", W, X)
        ess = 1.0 / (W * W).sum(axis=1)
        rows = np.flatnonzero(ess < 0.5 * Np)
        if rows.size:
            cw = np.cumsum(W[rows], axis=1)
            cw[:, -1] = 1.0
            pos = (rng.random((rows.size, 1)) + np.arange(Np)) / Np
            idx = np.array([np.searchsorted(cw[i], pos[i]) for i in range(rows.size)])
            X[rows] = np.take_along_axis(X[rows], np.minimum(idx, Np - 1)[..., None], axis=1)
            logw[rows] = -np.log(Np)
    return means


def interleaved(contestants: dict, repeat: int) -> dict:
    """The samples (:class:`_timing.Sample`: wall, user, system, precise CPU) of ``repeat`` rounds per contestant;
    each round calls every contestant once, in turn (so a change of the machine's load hits all of them)."""
    got: dict = {name: [] for name in contestants}
    for _ in range(repeat):
        for name, fn in contestants.items():
            got[name].append(measure(fn)[0])
    return got


def _load() -> str:
    one, five, _ = os.getloadavg()
    return f"load average {one:.1f} (1 min), {five:.1f} (5 min) on {os.cpu_count()} cores"


def _med(xs) -> str:
    """Median (min-max)."""
    return f"{statistics.median(xs):.2f}x ({min(xs):.2f}-{max(xs):.2f})"


HEAD = f"  {'contestant':<30}{'CPU':>8}{'(min-max)':>14}{'user':>8}{'sys':>7}{'wall':>8}{'(min-max)':>14}"


def _row(name: str, samples: list, run_steps: int) -> str:
    """µs per run-step: CPU (user + system, the process's precise clock) and wall, medians and (min-max)."""
    sc = 1e6 / run_steps

    def mm(xs):
        xs = [x * sc for x in xs]
        return f"{statistics.median(xs):8.1f}{f'({min(xs):.0f}-{max(xs):.0f})':>14}"

    user = statistics.median([s.user for s in samples]) * sc
    sys_ = statistics.median([s.sys for s in samples]) * sc
    return f"  {name:<30}{mm([s.cpu for s in samples])}{user:8.1f}{sys_:7.1f}{mm([s.wall for s in samples])}"


def ratios(ref: list, ours: list, per_ref: float = 1.0, per_ours: float = 1.0) -> dict:
    """Per round, reference time / our time (each per unit of work): CPU and wall, median and (min-max)."""
    cpu = [(a.cpu / per_ref) / (b.cpu / per_ours) for a, b in zip(ref, ours)]
    wall = [(a.wall / per_ref) / (b.wall / per_ours) for a, b in zip(ref, ours)]
    return {"cpu": cpu, "wall": wall}


def compiled_vs_plain(
    runs: int, particles: int, steps: int, repeat: int, numpy_path: bool = False, proposals=("optimal", "prior")
) -> dict:
    """(c): µs per run-step (CPU, user, system, wall; medians and spreads of ``repeat``) of the compiled filter and
    the plain numpy filter, interleaved in this process; ratios per round = plain time / ours."""
    print(
        f"(c) ours compiled vs a plain vectorised numpy filter: censored oscillator n=2 m=1, {runs} runs x "
        f"{steps} steps x {particles} particles; µs per run-step, medians (min-max) of {repeat}, interleaved; "
        f"{_load()}"
    )
    sys_, cens = oscillator(), tk.Censoring(lower=0.0)
    y = tk.simulate(sys_, steps, runs, censoring=cens, seed=0).y
    rs = runs * steps
    tk.ParticleFilter(sys_, cens, particles=8, backend="numba").filter(y[:1, :2])  # compile (or load the cache)
    print(HEAD)
    out = {}
    for proposal in proposals:
        pf = tk.ParticleFilter(sys_, cens, particles=particles, proposal=proposal, seed=1, backend="numba")
        contestants = {
            "ours (compiled)": lambda pf=pf: pf.filter(y, outputs="mean"),
            "plain numpy": lambda p=proposal: plain_filter(sys_, y, 0.0, particles, p, 1),
        }
        if numpy_path:
            pn = tk.ParticleFilter(sys_, cens, particles=particles, proposal=proposal, seed=1, backend="numpy")
            contestants["ours (numpy path)"] = lambda pn=pn: pn.filter(y, outputs="mean")
        t = interleaved(contestants, repeat)
        print(f"  {proposal} proposal")
        for name, v in t.items():
            print(_row(name, v, rs), flush=True)
        r = ratios(t["plain numpy"], t["ours (compiled)"])
        ratio = statistics.median(r["cpu"])
        at_target = runs >= 1000 and steps == 100 and particles == 4000
        verdict = (
            ("meets" if ratio >= 3 else "misses") + " the 3x target" if at_target else "the 3x target: 1000x100x4000"
        )
        print(
            f"  -> ours faster than the plain numpy filter by CPU {_med(r['cpu'])}, wall {_med(r['wall'])} ({verdict})"
        )
        out[proposal] = dict(samples=t, ratio=ratio, ratios=r)
    return out


def _particles_peer(sys_: tk.LinearSystem, y: np.ndarray, particles: int):
    """The ``particles`` package's bootstrap filter, one SMC object per run; None when it is not installed."""
    try:
        import particles as smc
        from particles import collectors
        from particles import distributions as dists
        from particles import state_space_models as ssm
    except ImportError:
        return None
    A, Q, c = sys_.transition(0), sys_.process_cov(0), sys_.measurement(1)[0]
    sd = float(np.sqrt(sys_.measurement_cov(1)[0, 0]))
    x0, P0 = sys_.x0, sys_.P0

    class Model(ssm.StateSpaceModel):
        def PX0(self):
            return dists.MvNormal(loc=x0, cov=P0)

        def PX(self, t, xp):
            return dists.MvNormal(loc=xp @ A.T, cov=Q)

        def PY(self, t, xp, x):
            return dists.Normal(loc=x @ c, scale=sd)

    def run():
        for r in range(y.shape[0]):
            fk = ssm.Bootstrap(ssm=Model(), data=list(y[r, :, 0]))
            alg = smc.SMC(fk=fk, N=particles, resampling="systematic", ESSrmin=0.5, collect=[collectors.Moments()])
            alg.run()

    return run


def _cuthbert_peer(sys_: tk.LinearSystem, y: np.ndarray, particles: int, block: int = 8):
    """cuthbert's particle filter, vmapped over blocks of runs, the weighted means computed inside the compiled
    function; None when cuthbert (or JAX) is not installed."""
    try:
        import jax
        import jax.numpy as jnp
        from cuthbert import filter as cfilter
        from cuthbert.smc import particle_filter
        from cuthbertlib.resampling import systematic
        from cuthbertlib.resampling.adaptive import ess_decorator
    except ImportError:
        return None
    jax.config.update("jax_enable_x64", True)
    A, Lq = jnp.asarray(sys_.transition(0)), jnp.asarray(np.linalg.cholesky(sys_.process_cov(0)))
    c, sd = jnp.asarray(sys_.measurement(1)[0]), float(np.sqrt(sys_.measurement_cov(1)[0, 0]))
    x0, L0 = jnp.asarray(sys_.x0), jnp.asarray(np.linalg.cholesky(sys_.P0))
    n = A.shape[0]

    def init_sample(key):
        return x0 + L0 @ jax.random.normal(key, (n,))

    def propagate_sample(key, x, yk):
        return A @ x + Lq @ jax.random.normal(key, (n,))

    def log_potential(xp, x, yk):
        z = (yk - c @ x) / sd
        return -0.5 * z * z

    pf = particle_filter.build_filter(
        init_sample, propagate_sample, log_potential, particles, ess_decorator(systematic.resampling, 0.5)
    )

    def one(key, yr):
        k0, k1 = jax.random.split(key)
        states = cfilter(pf, yr, pf.init_prepare(key=k0), key=k1)
        W = jax.nn.softmax(states.log_weights, axis=-1)
        return jnp.einsum("tp,tpi->ti", W, states.particles)[1:]

    batched = jax.jit(jax.vmap(one))
    yj = jnp.asarray(y[..., 0])
    N = y.shape[0]
    B = min(block, N)
    keys = jax.random.split(jax.random.PRNGKey(0), N)
    batched(keys[:B], yj[:B]).block_until_ready()  # compile before timing

    def run():
        for r0 in range(0, N - B + 1, B):
            batched(keys[r0 : r0 + B], yj[r0 : r0 + B]).block_until_ready()

    return run, (N // B) * B


def peers(runs: int, particles: int, steps: int, repeat: int) -> dict:
    """(d): ours compiled, ``particles`` and cuthbert on the uncensored bootstrap model, µs per run-step."""
    print(
        f"(d) peers on the uncensored bootstrap model (oscillator n=2 m=1), {runs} runs x {steps} steps x "
        f"{particles} particles; µs per run-step, medians (min-max) of {repeat}, interleaved; {_load()}"
    )
    sys_ = oscillator()
    y = tk.simulate(sys_, steps, runs, seed=0).y
    pf = tk.ParticleFilter(sys_, particles=particles, proposal="prior", seed=1, backend="numba")
    pf.filter(y[:1, :2])
    contestants = {"ours (compiled)": lambda: pf.filter(y, outputs="mean")}
    per_run = {"ours (compiled)": runs}
    got = _particles_peer(sys_, y, particles)
    if got is None:
        print("  particles: not installed (pip install --no-deps particles), skipped")
    else:
        contestants["particles (N. Chopin)"] = got
        per_run["particles (N. Chopin)"] = runs
    cg = _cuthbert_peer(sys_, y, particles)
    if cg is None:
        print("  cuthbert: not installed (pip install cuthbert), skipped")
    else:
        contestants["cuthbert (JAX)"], per_run["cuthbert (JAX)"] = cg
    t = interleaved(contestants, repeat)
    print(HEAD + f"{'ours faster by (CPU; wall)':>34}")
    out = {}
    ours = t["ours (compiled)"]
    for name, v in t.items():
        k = per_run[name] * steps
        r = ratios(v, ours, per_run[name], per_run["ours (compiled)"])
        out[name] = dict(samples=v, run_steps=k, ratio=statistics.median(r["cpu"]), ratios=r)
        tail = f"  {_med(r['cpu'])}; {_med(r['wall'])}" if name != "ours (compiled)" else ""
        print(_row(name, v, k) + tail, flush=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--smoke", action="store_true", help="tiny version (seconds)")
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--particles", type=int, default=10_000)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--target", action="store_true", help="(c) and (d) only, at the target size")
    parser.add_argument("--target-runs", type=int, default=None, help="(c): runs (default 50; --target: 1000)")
    parser.add_argument("--target-steps", type=int, default=100, help="(c): steps (the target: 100)")
    parser.add_argument("--target-particles", type=int, default=4000, help="(c): particles per run")
    parser.add_argument("--peer-runs", type=int, default=40, help="(d): runs")
    parser.add_argument("--numpy-path", action="store_true", help="(c): also ParticleFilter's numpy path")
    parser.add_argument(
        "--proposal", choices=("optimal", "prior", "both"), default="both", help="(c): the proposals timed"
    )
    parser.add_argument("--no-peers", action="store_true", help="skip (d)")
    parser.add_argument("--channel-runs", type=int, default=20, help="(e): runs")
    parser.add_argument("--channels", action="store_true", help="(e) only")
    args = parser.parse_args()
    if args.smoke:
        throughput(4, 500, 5, 1)
        memory(4, 500, 5)
        compiled_vs_plain(4, 500, 5, 1, numpy_path=True)
        peers(8, 200, 5, 1)
        channels_vs_numpy(4, 200, 5, 1)
        return
    if args.channels:
        channels_vs_numpy(args.channel_runs, args.target_particles, args.target_steps, args.repeat)
        return
    props = ("optimal", "prior") if args.proposal == "both" else (args.proposal,)
    if args.target:
        compiled_vs_plain(args.target_runs or 1000, 4000, 100, args.repeat, args.numpy_path, props)
        if not args.no_peers:
            peers(args.peer_runs, 4000, 100, args.repeat)
        return
    throughput(args.runs, args.particles, args.steps, min(args.repeat, 3))
    memory(args.runs, args.particles // 10, 50)
    compiled_vs_plain(
        args.target_runs or 50, args.target_particles, args.target_steps, args.repeat, args.numpy_path, props
    )
    if not args.no_peers:
        peers(args.peer_runs, args.target_particles, args.target_steps, args.repeat)
    channels_vs_numpy(args.channel_runs, args.target_particles, args.target_steps, args.repeat)


if __name__ == "__main__":
    main()
