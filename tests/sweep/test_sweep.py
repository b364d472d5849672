"""Sweeps: chunking invariance, Dask, resumption after a kill, reduction, validation errors."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import tobitkf as tk
from tobitkf.sweep import SweepFileError, load_result, parse_sweep, plot_result, run_sweep

BASE = """
[sweep]
runs = {runs}
steps = {steps}
seed = 3
block_runs = {block}
chunk_blocks = {chunk}

[model]
A = [[0.95]]
C = [[1.0]]
Q = [[0.04]]
R = [[0.01]]
x0 = [0.0]
P0 = [[0.2]]

[censoring]
lower = 0.0

[estimators.kf]
type = "KalmanFilter"

[estimators.tkf]
type = "TobitKalmanFilter"

[grid]
"censoring.lower" = [-0.2, 0.1]
"""


def spec(runs=140, steps=30, block=20, chunk=7):
    return parse_sweep(BASE.format(runs=runs, steps=steps, block=block, chunk=chunk), name="t")


def arrays(path):
    ds = load_result(path)
    return {v: ds[v].values for v in ds.data_vars}


def test_reduction_equals_direct_computation(tmp_path):
    s = spec(runs=60, block=20)
    path = run_sweep(s, tmp_path)
    ds = load_result(path)
    # independent: simulate the three blocks with the documented seeds and filter directly
    sys_ = tk.LinearSystem(A=[[0.95]], C=[[1.0]], Q=[[0.04]], R=[[0.01]], x0=[0.0], P0=[[0.2]])
    for lower in (-0.2, 0.1):
        cens = tk.Censoring(lower=lower)
        errs = {"kf": [], "tkf": []}
        var = {"kf": [], "tkf": []}
        for b in range(3):
            d = tk.simulate(sys_, 30, 20, censoring=cens, seed=np.random.SeedSequence(3, spawn_key=(b,)))
            for key, f in (("kf", tk.KalmanFilter(sys_)), ("tkf", tk.TobitKalmanFilter(sys_, cens))):
                out = f.filter(d.y)
                errs[key].append(out.mean - d.x[:, 1:])
                var[key].append(out.cov[..., 0, 0])
        for key, e in errs.items():
            e = np.concatenate(e)
            sel = {"censoring.lower": lower, "estimator": key}
            np.testing.assert_allclose(ds["rmse"].sel(sel).values, np.sqrt((e**2).mean(axis=0)), rtol=1e-12)
            np.testing.assert_allclose(ds["bias"].sel(sel).values, e.mean(axis=0), rtol=1e-10, atol=1e-15)
            # n = 1: e^T P^-1 e is e^2 / P, no solve needed
            np.testing.assert_allclose(
                ds["nees"].sel(sel).values, (e[..., 0] ** 2 / np.concatenate(var[key])).mean(axis=0), rtol=1e-12
            )
    assert ds.attrs["sweep"].startswith("\n[sweep]") and ds.attrs["package_version"] == tk.__version__


def test_chunking_and_dask_give_identical_statistics(tmp_path):
    one = arrays(run_sweep(spec(chunk=7), tmp_path / "one", workers=1))  # 1 task per grid point
    seven = arrays(run_sweep(spec(chunk=1), tmp_path / "seven", workers=1))  # 7 tasks per grid point
    threads = arrays(run_sweep(spec(chunk=1), tmp_path / "threads", workers=3))  # 3 threads in-process
    pytest.importorskip("distributed")
    dask = arrays(run_sweep(spec(chunk=2), tmp_path / "dask", scheduler="processes", workers=2))
    for name in one:
        np.testing.assert_array_equal(one[name], seven[name])
        np.testing.assert_array_equal(one[name], threads[name])
        np.testing.assert_array_equal(one[name], dask[name])


def test_processes_cluster_keeps_its_monitors_quiet():
    """``--scheduler processes`` starts its cluster with Dask's periodic monitors made rare (their CPU,
    ~0.1 s per second with the defaults, is taken from the workers when they fill the cores): no
    statistical profiler in the workers, the health tick and the memory monitors once a second, in the
    worker processes and in the scheduler of this process."""
    pytest.importorskip("distributed")
    from tobitkf.sweep import run as R

    client, cluster = R._client("processes", 1)
    try:
        (workers,) = client.run(
            lambda dask_worker: {k: v.callback_time for k, v in dask_worker.periodic_callbacks.items()}
        ).values()
        nannies = [{k: v.callback_time for k, v in n.periodic_callbacks.items()} for n in cluster.workers.values()]
        sched = {k: v.callback_time for k, v in cluster.scheduler.periodic_callbacks.items()}
    finally:
        client.close()
        cluster.close()
    assert "profile" not in workers and "profile-cycle" not in workers
    assert workers["tick"] == workers["memory_monitor"] == 1000 and workers["monitor"] == 5000
    assert nannies and all(n["tick"] == n["memory_monitor"] == 1000 for n in nannies)
    assert sched["tick"] == 1000 and sched["monitor"] == 5000


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="workers are forked on Linux only")
def test_processes_cluster_forks_its_workers_with_the_sweep_imported():
    """On Linux the workers of ``--scheduler processes`` are forked from this process, so they start with
    tobitkf imported (a spawned worker imports Dask, numpy, scipy and tobitkf afresh: ~1.3 s of CPU each);
    their filters still run on one thread (the nanny's OMP_NUM_THREADS=1 reaches a forked worker too)."""
    pytest.importorskip("distributed")
    from tobitkf.sweep import run as R

    def probe():
        import sys

        from tobitkf._compiled import default_threads

        return "tobitkf.sweep.run" in sys.modules, default_threads()

    client, cluster = R._client("processes", 2)
    try:
        got = list(client.run(probe).values())
    finally:
        client.close()
        cluster.close()
    assert got == [(True, 1), (True, 1)]


def test_one_worker_runs_its_filters_on_one_thread(tmp_path, monkeypatch):
    """workers=1 is one thread: the blocks run in sequence with single-threaded filters (threads=1), as in a
    Dask worker (before, they ran with the filters' default threads, all CPUs); with more workers the
    pool's tasks run single-threaded filters too."""
    from tobitkf.sweep import run as R

    seen = []
    real = R.run_task

    def spy(text, name, p, blocks, threads=None):
        seen.append(threads)
        return real(text, name, p, blocks, threads)

    monkeypatch.setattr(R, "run_task", spy)
    run_sweep(spec(chunk=1), tmp_path / "one", workers=1)
    assert seen and set(seen) == {1}
    seen.clear()
    run_sweep(spec(chunk=1), tmp_path / "three", workers=3)  # the pool: each task's filters single-threaded
    assert seen and set(seen) == {1}


def test_stored_blocks_are_released(tmp_path, monkeypatch):
    """A sweep's memory must not grow with its run count: once a task's blocks are in the store, nothing
    of the sweep holds their statistics (before, every finished future stayed in a dict until the end, so
    the results of all tasks stayed in memory). Checked with weak references to each task's results, on
    the in-process pool and on a Dask cluster in this process."""
    import gc
    import weakref

    from tobitkf.sweep import run as R

    class Stats(dict):  # a dict that can be weakly referenced
        pass

    real_task, real_write = R.run_task, R.write_blocks
    refs: list[list] = []
    alive_old: list[int] = []

    def task(text, name, p, blocks, threads=None):
        return [(b, Stats(d)) for b, d in real_task(text, name, p, blocks, threads)]

    def write(g, p, results):
        real_write(g, p, results)
        gc.collect()
        # results stored two or more writes ago: nothing may hold them any more
        alive_old.append(sum(r() is not None for batch in refs[:-1] for r in batch))
        refs.append([weakref.ref(d) for _, d in results])

    monkeypatch.setattr(R, "run_task", task)
    monkeypatch.setattr(R, "write_blocks", write)
    run_sweep(spec(chunk=1), tmp_path / "pool", workers=2)
    assert len(refs) == 14 and max(alive_old) == 0
    distributed = pytest.importorskip("distributed")
    refs.clear()
    alive_old.clear()
    lag = 3  # a released result leaves the worker when the scheduler's message arrives: allow a few writes

    def write_dask(g, p, results):
        real_write(g, p, results)
        for _ in range(40):  # up to 2 s for the release to reach the worker (a loaded machine)
            gc.collect()
            alive = sum(r() is not None for batch in refs[:-lag] for r in batch)
            if not alive:
                break
            time.sleep(0.05)
        alive_old.append(alive)
        refs.append([weakref.ref(d) for _, d in results])

    monkeypatch.setattr(R, "write_blocks", write_dask)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cl:
        run_sweep(spec(chunk=1), tmp_path / "dask", scheduler=cl.scheduler_address)
    assert len(refs) == 14 and max(alive_old) == 0


def test_scheduler_address_runs_on_an_existing_cluster(tmp_path):
    """``--scheduler ADDRESS``: the same file on a cluster started elsewhere gives the same numbers."""
    distributed = pytest.importorskip("distributed")
    ref = arrays(run_sweep(spec(chunk=2), tmp_path / "ref"))
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None
    ) as cluster:
        got = arrays(run_sweep(spec(chunk=2), tmp_path / "addr", scheduler=cluster.scheduler_address))
    for name in ref:
        np.testing.assert_array_equal(ref[name], got[name])


@pytest.mark.parametrize("workers", [0, -1, 1.5, True, "2"])
def test_bad_worker_count_is_refused_by_name(tmp_path, workers):
    with pytest.raises(tk.ValidationError, match="workers: expected a positive integer"):
        run_sweep(spec(), tmp_path / "out", workers=workers)
    assert not (tmp_path / "out").exists()


def test_unreachable_scheduler_fails_before_any_work(tmp_path):
    with pytest.raises(tk.ValidationError, match="--scheduler: cannot connect .*'nonsense'"):
        run_sweep(spec(), tmp_path, scheduler="nonsense")
    assert not (tmp_path / "t.zarr").exists()


def test_resume_after_partial_run_is_identical(tmp_path):
    full = arrays(run_sweep(spec(chunk=1), tmp_path / "full"))
    part = run_sweep(spec(chunk=1), tmp_path / "part", max_tasks=5)
    assert not (part / "summary").exists()
    with pytest.raises(tk.ValidationError, match="not finished"):
        load_result(part)
    run_sweep(spec(chunk=1), tmp_path / "part")
    resumed = arrays(part)
    for name in full:
        np.testing.assert_array_equal(full[name], resumed[name])


def test_resume_with_other_task_size_writes_into_part_chunks(tmp_path):
    """The store's zarr chunks hold ``chunk_blocks`` blocks (7 here); resuming with tasks of 2 blocks
    writes into part-filled chunks and must neither lose nor duplicate a block."""
    full = arrays(run_sweep(spec(chunk=7), tmp_path / "full"))
    part = run_sweep(spec(chunk=7), tmp_path / "part", max_tasks=1)  # point 0 done, point 1 empty
    run_sweep(spec(chunk=2), tmp_path / "part", max_tasks=2)  # blocks 0-3 of point 1
    run_sweep(spec(chunk=3), tmp_path / "part")  # blocks 4-6
    resumed = arrays(part)
    for name in full:
        np.testing.assert_array_equal(full[name], resumed[name])


def test_resume_after_killed_process_is_identical(tmp_path):
    text = BASE.format(runs=2000, steps=200, block=100, chunk=1)
    f = tmp_path / "killme.toml"
    f.write_text(text)
    env = dict(os.environ, PYTHONPATH=str(Path(tk.__file__).parents[1]))
    cmd = [sys.executable, "-m", "tobitkf", "sweep", str(f), "--out", str(tmp_path / "out")]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    import zarr

    store = tmp_path / "out" / "killme.zarr"
    deadline = time.time() + 120
    done = 0
    while time.time() < deadline:
        if (store / "zarr.json").exists():
            try:
                done = int(zarr.open_group(str(store), mode="r")["done"][:].sum())
            except Exception:  # the store may be mid-creation
                done = 0
            if done >= 3:
                break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert 3 <= done < 40, f"kill did not land mid-sweep (done={done})"
    assert not (store / "summary").exists()
    res = subprocess.run(cmd, env=env, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    resumed = arrays(store)
    full = arrays(run_sweep(parse_sweep(text, name="killme"), tmp_path / "ref"))
    for name in full:
        np.testing.assert_array_equal(full[name], resumed[name])


def test_store_of_another_sweep_is_refused(tmp_path):
    run_sweep(spec(runs=40), tmp_path)
    with pytest.raises(tk.ValidationError, match="different sweep"):
        run_sweep(spec(runs=60), tmp_path)


def test_plot_writes_both_figures(tmp_path):
    path = run_sweep(spec(runs=40), tmp_path)
    paths = plot_result(path, tmp_path / "figs")
    names = sorted(p.name for p in paths)
    assert names == ["rmse_over_time.png", "rmse_vs_censoring.lower.png"]
    assert all(p.stat().st_size > 2000 for p in paths)


@pytest.mark.parametrize(
    "lowers, panels, curves",
    [
        ([-0.2, 0.0, 0.1], 3, 2),  # a column per grid point, a curve per estimator
        ([-0.3, -0.2, -0.1, 0.0, 0.1, 0.2, 0.3], 2, 7),  # > 6 points: a column per estimator, a curve per point
    ],
)
def test_rmse_over_time_layout(tmp_path, monkeypatch, lowers, panels, curves):
    import tobitkf.sweep.plot as sp

    text = BASE.format(runs=20, steps=10, block=20, chunk=1).replace(
        '"censoring.lower" = [-0.2, 0.1]', f'"censoring.lower" = {lowers}'
    )
    path = run_sweep(parse_sweep(text, name="t"), tmp_path)
    figs = {}
    monkeypatch.setattr(sp, "save", lambda fig, outdir, name: figs.setdefault(name, fig) and Path(outdir) / name)
    plot_result(path, tmp_path / "figs")
    axes = figs["rmse_over_time.png"].axes
    assert len(axes) == panels  # one state component (n = 1): one row
    assert all(len(ax.lines) == curves for ax in axes)
    # the estimators' curves share the y scale of their row
    assert len({ax.get_ylim() for ax in axes}) == 1


def test_experiment_mode_combines_blocks_of_the_experiment(tmp_path):
    """Experiment mode in blocks: block b runs the experiment with the documented integer seed
    (the first 63 bits of SeedSequence(seed, spawn_key=(b,))'s state) and the blocks' RMSE, bias
    and NEES combine as sums; computed here from direct runs of the experiment."""
    text = """
[sweep]
experiment = "miller-brownian"
runs = 6
seed = 2
block_runs = {block}
chunk_blocks = {chunk}
[settings]
steps = 50
[grid]
"settings.sigma" = [0.05, 0.1]
"""
    ds = load_result(run_sweep(parse_sweep(text.format(block=3, chunk=1), name="exp"), tmp_path / "a"))
    from tobitkf.experiments import get

    parts = []
    for b in range(2):
        seed = int(np.random.SeedSequence(2, spawn_key=(b,)).generate_state(1, np.uint64)[0]) >> 1
        parts.append(get("miller-brownian").run(runs=3, seed=seed, steps=50, sigma=0.1).metrics["estimators"]["tkf"])
    rmse = np.sqrt(sum(3 * np.asarray(p["rmse"]) ** 2 for p in parts) / 6)
    bias = sum(3 * np.asarray(p["bias"]) for p in parts) / 6
    sel = {"settings.sigma": 0.1, "estimator": "tkf"}
    np.testing.assert_allclose(ds["rmse"].sel(sel).values, rmse, rtol=1e-12)
    np.testing.assert_allclose(ds["bias"].sel(sel).values, bias, rtol=1e-12, atol=1e-15)
    assert int(ds["runs"].sel({"settings.sigma": 0.1})) == 6
    # the same blocks in one task per grid point, and resumed after one task: identical numbers
    one = load_result(run_sweep(parse_sweep(text.format(block=3, chunk=2), name="exp"), tmp_path / "b"))
    run_sweep(parse_sweep(text.format(block=3, chunk=1), name="exp"), tmp_path / "c", max_tasks=2)
    resumed = load_result(run_sweep(parse_sweep(text.format(block=3, chunk=1), name="exp"), tmp_path / "c"))
    for name in ds.data_vars:
        np.testing.assert_array_equal(ds[name].values, one[name].values)
        np.testing.assert_array_equal(ds[name].values, resumed[name].values)


def test_grid_that_changes_the_horizon_is_refused_with_the_reason(tmp_path):
    """One store has one time axis: a grid over an experiment's horizon cannot share it, and the
    error says so instead of failing inside zarr."""
    text = """
[sweep]
experiment = "miller-brownian"
runs = 4
seed = 2
[grid]
"settings.steps" = [20, 30]
"""
    with pytest.raises(tk.ValidationError, match="change the horizon.*one sweep per value"):
        run_sweep(parse_sweep(text, name="h"), tmp_path)


@pytest.mark.parametrize(
    "text, match",
    [
        ("not toml = = 1", "not valid TOML"),
        ("[model]\nA=[[1.0]]", "missing the \\[sweep\\] table"),
        ("[sweep]\nruns = 0\nsteps = 5\nseed = 0", "sweep.runs \\(line 2\\): expected an integer >= 1"),
        ("[sweep]\nruns = 5\nsteps = 5\nseed = 0\nrun = 3", "sweep.run \\(line 5\\): unknown key"),
        ("[sweep]\nruns = 5\nsteps = 5", "missing required key 'seed'"),
        ("[sweep]\nruns = 5\nsteps = 5\nseed = 0\n[modle]\nA = 1", "modle \\(line 5\\): unknown table"),
    ],
)
def test_sweep_file_errors_name_key_and_line(text, match):
    with pytest.raises(SweepFileError, match=match):
        parse_sweep(text)


def _with(old, new):
    return BASE.format(runs=10, steps=5, block=5, chunk=1).replace(old, new)


@pytest.mark.parametrize(
    "old, new, match",
    [
        ('type = "KalmanFilter"', 'type = "Kalman"', "estimators.kf.type \\(line \\d+\\): unknown estimator type"),
        (
            'type = "TobitKalmanFilter"',
            'type = "TobitKalmanFilter"\nnoise = 1',
            "estimators.tkf.noise \\(line \\d+\\): unknown option",
        ),
        (
            '"censoring.lower" = [-0.2, 0.1]',
            '"censoring.lower" = []',
            "grid.censoring.lower \\(line \\d+\\): expected a non-empty list",
        ),
        ('"censoring.lower" = [-0.2, 0.1]', '"sweep.seed" = [1, 2]', "grid keys are dotted paths"),
        ('"censoring.lower" = [-0.2, 0.1]', '"censoring.lower" = [0.0, inf]', "invalid at grid point .*lower"),
        ("Q = [[0.04]]", "Q = [[-0.04]]", "model.Q \\(line \\d+\\): Q: expected a positive semi-definite"),
        ("x0 = [0.0]\n", "", "missing required key 'x0'"),
        ("[censoring]\nlower = 0.0", "[censoring]\nlow = 0.0", "censoring.low \\(line \\d+\\): unknown key"),
        ("[sweep]", '[sweep]\nname = "../escape"', "sweep.name .*plain file name"),
        ("[sweep]", '[sweep]\nexperiment = "nope"', "unknown id"),
    ],
)
def test_sweep_content_errors(old, new, match):
    with pytest.raises(SweepFileError, match=match):
        parse_sweep(_with(old, new))


def test_cli_sweep_and_plot(tmp_path):
    from typer.testing import CliRunner

    from tobitkf.cli import app

    f = tmp_path / "s.toml"
    f.write_text(BASE.format(runs=40, steps=20, block=20, chunk=1))
    runner = CliRunner()
    res = runner.invoke(app, ["sweep", str(f), "--out", str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["plot", str(tmp_path / "o" / "s.zarr")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "o" / "s_plots" / "rmse_over_time.png").exists()
    bad = tmp_path / "bad.toml"
    bad.write_text("[sweep]\nruns = -1\nsteps = 2\nseed = 0\n")
    res = runner.invoke(app, ["sweep", str(bad)])
    assert res.exit_code == 2 and "sweep.runs" in res.output


# --- every family on a linear model, from the estimator registry --------------------------------
FAMILIES = """
[sweep]
runs = 40
steps = 15
seed = 5
block_runs = 20

[model]
A = [[0.95, 0.1], [0.0, 0.9]]
C = [[1.0, 0.0]]
Q = [[0.01, 0.0], [0.0, 0.01]]
R = [[0.05]]
x0 = [1.0, 0.0]
P0 = [[0.5, 0.0], [0.0, 0.5]]

[censoring]
lower = 0.2

[fading]
order = 1
mean = [0.9, 0.4]
variance = [0.01, 0.02]

[estimators.tkf-fm]
type = "FadingTobitKalmanFilter"
p_uncensored_mode = "eq6_stale"

[estimators.kf-fm]
type = "FadingKalmanFilter"

[estimators.sstkf]
type = "SteadyStateTobitKalmanFilter"
xi_uncensored = 0.8

[grid]
"fading.variance" = [[0.0, 0.0], [0.01, 0.02]]
"""

PROTOCOL = """
[sweep]
runs = 30
steps = 12
seed = 6
block_runs = 10

[model]
A = [[0.98, -0.16], [0.16, 0.98]]
C = [[1.0, 0.0], [0.0, 1.0]]
Q = [[0.0025, 0.0], [0.0, 0.0025]]
R = [[1.0, 0.0], [0.0, 0.5]]
x0 = [5.0, 0.0]
P0 = [[1.0, 0.0], [0.0, 1.0]]

[protocol]
window = 2
threshold = 0.0
failures = "base"

[estimators.pbtkf-imsf]
type = "ProtocolTobitKalmanFilter"
failure_term = "second_moment"

[estimators.pbtkf]
type = "ProtocolBaselineTobitKalmanFilter"

[grid]
"protocol.window" = [1, 2]
"""


def _direct_rmse(make_data, estimators, blocks, seed):
    """RMSE per step of each estimator from the documented block seeds, filtered directly."""
    errs = {k: [] for k in estimators}
    for b in range(blocks):
        d = make_data(np.random.SeedSequence(seed, spawn_key=(b,)))
        for key, run in estimators.items():
            out = run(d)
            errs[key].append(out.mean - d.x[:, 1:])
    return {k: np.sqrt((np.concatenate(e) ** 2).mean(axis=0)) for k, e in errs.items()}


def test_fading_and_steady_state_families_sweep_like_a_direct_run(tmp_path):
    from tobitkf.channels.fading import RiceFading

    ds = load_result(run_sweep(parse_sweep(FAMILIES, name="fam"), tmp_path))
    sys_ = tk.LinearSystem(
        A=[[0.95, 0.1], [0.0, 0.9]], C=[[1.0, 0.0]], Q=0.01 * np.eye(2), R=[[0.05]], x0=[1.0, 0.0], P0=0.5 * np.eye(2)
    )
    cens = tk.Censoring(lower=0.2)
    for i, var in enumerate(([0.0, 0.0], [0.01, 0.02])):
        fad = RiceFading.gaussian(1, [0.9, 0.4], var)
        ref = _direct_rmse(
            lambda seed: tk.simulate(sys_, 15, 20, channel=[fad, cens], seed=seed),
            {
                "tkf-fm": lambda d: tk.FadingTobitKalmanFilter(sys_, fad, cens, p_uncensored_mode="eq6_stale").filter(
                    d.y
                ),
                "kf-fm": lambda d: tk.FadingKalmanFilter(sys_, fad).filter(d.y),
                "sstkf": lambda d: tk.SteadyStateTobitKalmanFilter(sys_, 0.8).filter_controlled(d.y_latent),
            },
            2,
            5,
        )
        for key, r in ref.items():
            got = ds["rmse"].isel({"fading.variance": i}).sel(estimator=key).values
            np.testing.assert_allclose(got, r, rtol=1e-12)


def test_protocol_family_sweeps_like_a_direct_run(tmp_path):
    from tobitkf.channels.protocol import LAMBDA_BASE

    ds = load_result(run_sweep(parse_sweep(PROTOCOL, name="prot"), tmp_path))
    sys_ = tk.LinearSystem(
        A=[[0.98, -0.16], [0.16, 0.98]],
        C=np.eye(2),
        Q=0.0025 * np.eye(2),
        R=np.diag([1.0, 0.5]),
        x0=[5.0, 0.0],
        P0=np.eye(2),
    )
    assert ds["censored_fraction"].shape == (2, 12, 1)  # one scalar reading per step
    for ell in (1, 2):
        ch = tk.ProtocolChannel(2, window=ell, threshold=0.0, failures=LAMBDA_BASE)
        ref = _direct_rmse(
            lambda seed: tk.simulate(sys_, 12, 10, channel=ch, seed=seed),
            {
                "pbtkf-imsf": lambda d: tk.ProtocolTobitKalmanFilter(sys_, ch, failure_term="second_moment").filter(
                    d.y
                ),
                "pbtkf": lambda d: tk.ProtocolTobitKalmanFilter.baseline(sys_, ch).filter(d.y),
            },
            3,
            6,
        )
        for key, r in ref.items():
            np.testing.assert_allclose(ds["rmse"].sel({"protocol.window": ell, "estimator": key}).values, r, rtol=1e-12)


@pytest.mark.parametrize(
    "text, match",
    [
        (
            FAMILIES.replace('type = "FadingKalmanFilter"', 'type = "ChainLMMSE"'),
            "ChainLMMSE is not a family on a linear model",
        ),
        (FAMILIES.replace("[fading]\norder = 1\n", "[fading]\n"), "order: the \\[fading\\] channel needs its order L"),
        (
            FAMILIES.replace("xi_uncensored = 0.8\n", ""),
            "xi_uncensored: SteadyStateTobitKalmanFilter needs this option",
        ),
        (PROTOCOL.replace("[protocol]", "[censoring]\nlower = 0.0\n\n[protocol]"), "drop \\[censoring\\]"),
        (PROTOCOL.replace('failures = "base"', 'failures = "often"'), "failures: expected 'none', 'base', 'lambda1'"),
        (FAMILIES.replace('"fading.variance"', '"fading.speed"'), "expected a key of the file's \\[fading\\] table"),
    ],
)
def test_channel_sections_are_checked_on_load(text, match):
    with pytest.raises(SweepFileError, match=match):
        parse_sweep(text, name="bad")


def test_a_sweep_refuses_an_entry_whose_channel_piece_no_sweep_file_describes():
    text = BASE.replace('type = "TobitKalmanFilter"', 'type = "SaturationAssumedDensityFilter"')
    with pytest.raises(SweepFileError, match="its pieces: saturation"):
        parse_sweep(text.format(runs=40, steps=10, block=20, chunk=1), name="sat")


PARTICLE = BASE.replace(
    '[estimators.tkf]\ntype = "TobitKalmanFilter"',
    '[estimators.tkf]\ntype = "TobitKalmanFilter"\n\n[estimators.pf]\ntype = "ParticleFilter"\nparticles = 40\nseed = 11',
)


def test_a_particle_filter_sweeps_like_a_direct_run(tmp_path):
    """The registry's ParticleFilter in a sweep: the channel of the point, the seed given, the block data."""
    assert "ParticleFilter" in PARTICLE
    text = PARTICLE.format(runs=40, steps=10, block=20, chunk=1)
    ds = load_result(run_sweep(parse_sweep(text, name="pf"), tmp_path))
    sys_ = tk.LinearSystem(A=[[0.95]], C=[[1.0]], Q=[[0.04]], R=[[0.01]], x0=[0.0], P0=[[0.2]])
    for i, lo in enumerate((-0.2, 0.1)):
        cens = tk.Censoring(lower=lo)
        ref = _direct_rmse(
            lambda seed: tk.simulate(sys_, 10, 20, censoring=cens, seed=seed),
            {"pf": lambda d: tk.ParticleFilter(sys_, cens, particles=40, seed=11).filter(d.y)},
            2,
            3,
        )
        got = ds["rmse"].isel({"censoring.lower": i}).sel(estimator="pf").values
        np.testing.assert_allclose(got, ref["pf"], rtol=1e-12)


def test_a_sweep_particle_filter_needs_its_seed():
    text = PARTICLE.replace("\nseed = 11", "").format(runs=40, steps=10, block=20, chunk=1)
    with pytest.raises(SweepFileError, match="seed: ParticleFilter needs this option"):
        parse_sweep(text, name="pf")
