"""Executing a sweep: blocks of runs, seeded independently, on a laptop or a Dask cluster.

Seeding: block ``b`` of every grid point draws from
``numpy.random.SeedSequence(seed).spawn``-style children, concretely
``SeedSequence(seed, spawn_key=(b,))`` — the ``b``-th child of the sweep's seed. The
numbers therefore do not depend on how blocks are grouped into tasks or on the number of
workers, and grid points share common random numbers (differences between grid points
are not blurred by sampling noise).

Each task returns sufficient statistics only (sums of errors, squared errors, NEES and
censoring counts, see :mod:`tobitkf.sweep.store`), never trajectories, so memory does not
grow with the run count.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from .._extras import require
from .._validation import ValidationError
from ..metrics import nees_terms
from .build import build_point
from .spec import SweepSpec
from .store import _read, check_resumable, open_store, reduce_store, write_blocks

__all__ = ["build_point", "run_block", "run_sweep", "experiment_seed"]


def run_block(
    spec: SweepSpec, point: dict[str, Any], block: int, runs: int, *, threads: int | None = None
) -> dict[str, np.ndarray]:
    """Simulate ``runs`` runs of block ``block`` and return its sufficient statistics."""
    from ..simulate.core import simulate

    pt = build_point(spec, point, threads=threads)
    data = simulate(
        pt.system, spec.steps, runs, channel=pt.channel(), seed=np.random.SeedSequence(spec.seed, spawn_key=(block,))
    )
    s_err, s_sq, s_nees = [], [], []
    for entry, est in pt.estimators.values():
        out = entry.run(est, data, outputs=("mean", "cov"))
        err = out.mean - data.x[:, out.times]  # the truth at the rows' times
        s_err.append(err.sum(axis=0))
        s_sq.append((err**2).sum(axis=0))
        s_nees.append(nees_terms(err, out.cov).sum(axis=0))
    return {
        "sum_err": np.stack(s_err),
        "sum_sq": np.stack(s_sq),
        "sum_nees": np.stack(s_nees),
        "censored": pt.censored(data.y).sum(axis=0).astype(float),
        "count": np.int64(runs),
    }


def experiment_seed(seed: int, block: int) -> int:
    """The integer seed of block ``block`` of an experiment sweep: the first 63 bits of the
    state of ``SeedSequence(seed, spawn_key=(block,))`` (the block's seed in model mode).
    Experiments take integer seeds (they combine them with scenario indices)."""
    return int(np.random.SeedSequence(seed, spawn_key=(block,)).generate_state(1, np.uint64)[0] >> np.uint64(1))


def _experiment_block(
    spec: SweepSpec, point: dict[str, Any], block: int, runs: int
) -> tuple[list[str], dict[str, Any]]:
    """Run the experiment for one block and turn its per-step RMSE, bias and NEES into sums."""
    from ..experiments import get

    r = spec.resolved(point)
    assert spec.experiment is not None, "an experiment block belongs to an experiment sweep"
    try:
        res = get(spec.experiment).run(runs=runs, seed=experiment_seed(spec.seed, block), **r["settings"])
    except TypeError as exc:  # an experiment taking **overrides refuses an unknown setting this way
        raise ValidationError(f"settings: {spec.experiment} refused the settings {r['settings']}: {exc}") from None
    est = res.metrics.get("estimators")
    if not est:
        raise ValidationError(
            f"sweep.experiment: {spec.experiment!r} reports no top-level 'estimators' block and cannot be swept"
        )
    keys = list(est)
    rmse = np.stack([np.asarray(est[k]["rmse"], dtype=float) for k in keys])
    bias = np.stack([np.asarray(est[k]["bias"], dtype=float) for k in keys])
    nees = np.stack([np.asarray(est[k].get("nees", np.full(rmse.shape[1], np.nan)), dtype=float) for k in keys])
    stats = {
        "sum_err": bias * runs,
        "sum_sq": rmse**2 * runs,
        "sum_nees": nees * runs,
        "censored": np.zeros((rmse.shape[1], 1)),
        "count": np.int64(runs),
    }
    return keys, stats


@lru_cache(maxsize=4)
def _parsed(spec_text: str, name: str) -> SweepSpec:
    """The validated sweep, parsed once per worker process (validation builds every grid point)."""
    from .spec import parse_sweep

    return parse_sweep(spec_text, name=name)


def run_task(
    spec_text: str, name: str, point_index: int, blocks: list[int], threads: int | None = None
) -> list[tuple[int, dict]]:
    """A unit of work for a worker: some blocks of one grid point (top-level so Dask can pickle it).

    ``threads``: threads of the filters inside a block (None: their default, which is 1 in a
    Dask worker, where Dask sets OMP_NUM_THREADS=1)."""
    spec = _parsed(spec_text, name)
    point = spec.points()[point_index]
    sizes = spec.block_sizes()
    if spec.experiment is not None:
        return [(b, _experiment_block(spec, point, b, sizes[b])[1]) for b in blocks]
    return [(b, run_block(spec, point, b, sizes[b], threads=threads)) for b in blocks]


def _probe(scheduler: str, timeout: float = 5.0) -> None:
    """Refuse at once a TCP scheduler address where nothing listens (Dask's Client would retry
    for its whole connect timeout, 30 s, before giving up)."""
    from urllib.parse import urlsplit

    if not isinstance(scheduler, str) or not scheduler:
        raise ValidationError(f"--scheduler: expected 'local', 'processes' or a scheduler address, got {scheduler!r}")
    address = scheduler if "://" in scheduler else f"tcp://{scheduler}"
    try:
        parts = urlsplit(address)
        host, port = parts.hostname, parts.port
    except ValueError as exc:  # a port that is not a number or out of range
        raise ValidationError(
            f"--scheduler: {scheduler!r} is not a scheduler address ({exc}); expected "
            "'local', 'processes' or e.g. tcp://host:8786"
        ) from None
    if parts.scheme not in ("tcp", "tls") or not host or port is None:
        return  # other protocols (inproc, ucx, ws): left to Dask
    import socket

    try:
        socket.create_connection((host, port), timeout=timeout).close()
    except ConnectionRefusedError:
        raise ValidationError(
            f"--scheduler: connection refused at {host}:{port} (no Dask scheduler listens "
            "there); start one or use --scheduler local"
        ) from None
    except socket.gaierror as exc:
        raise ValidationError(f"--scheduler: unknown host {host!r} ({exc.strerror})") from None
    except OSError:
        return  # a timeout or a filtered port: Dask's own error follows


_QUIET = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "1s",
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.admin.system-monitor.interval": "5s",
}
"""Dask settings of the cluster ``--scheduler processes`` starts: its periodic monitors made rare.

With Dask's defaults an idle 2-worker cluster costs about 0.1 s of CPU per second (measured with
psutil: the driver, which holds the scheduler and the nannies, 35-45 ms/s, each worker 26-31
ms/s): the statistical profiler samples every worker's stacks every 10 ms, the event-loop health
tick runs every 20 ms, the memory monitors poll psutil every 100 ms, the system monitor every
500 ms. On a machine whose cores all run workers that CPU is taken from the workers. The profiler
and the system monitor feed only the dashboard, which this cluster does not start; the memory
limits stay enforced, checked every second. Quiet, the idle cluster costs about 11 ms/s."""


def _start_method() -> str:
    """How ``--scheduler processes`` starts its workers: ``fork`` on Linux, else Dask's default ``spawn``.

    A spawned worker is a fresh interpreter that imports Dask, numpy, scipy and tobitkf again before its
    first block: measured 1.2-1.4 s of CPU per worker (1.67-2.05 s for a 1-block sweep against 0.52-0.69 s
    forked, 3 alternating pairs), a fixed cost in every run, on the critical path with one worker and with
    two. A forked worker starts with this process's modules. Not forked: on other systems (macOS's
    frameworks are not fork-safe), and when this process has started numba's thread pool with a threading
    layer other than ``workqueue`` (numba: TBB and GNU OpenMP do not survive a fork)."""
    import multiprocessing

    if not sys.platform.startswith("linux") or "fork" not in multiprocessing.get_all_start_methods():
        return "spawn"
    numba = sys.modules.get("numba")
    if numba is not None:
        try:
            layer = numba.threading_layer()
        except ValueError:  # the thread pool was never started in this process
            layer = None
        if layer not in (None, "workqueue"):
            return "spawn"
    return "fork"


def _client(scheduler: str, workers: int):
    distributed = require("distributed", extra="sweep", feature="a Dask scheduler (--scheduler)")
    Client, LocalCluster = distributed.Client, distributed.LocalCluster
    if scheduler == "processes":
        dask = require("dask", extra="sweep", feature="a Dask scheduler (--scheduler)")

        # Dask starts its workers with MALLOC_TRIM_THRESHOLD_=65536, which makes glibc hand every
        # freed block back to the kernel at once; a block's ~30 MB of simulated data and filter
        # outputs is then page-faulted in afresh for every block (measured: 20–40 % more time per
        # block in the worker). A worker of ours holds one task's blocks at a time, so keeping
        # glibc's default lets it reuse that memory instead.
        settings = {
            "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
            "distributed.worker.multiprocessing-method": _start_method(),
            **_QUIET,
        }
        with dask.config.set(settings):
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None)
        return Client(cluster), cluster
    _probe(scheduler)
    try:
        return Client(scheduler), None
    except (OSError, ValueError, TypeError) as exc:  # unreachable, timed out, or not an address
        raise ValidationError(
            f"--scheduler: cannot connect to a Dask scheduler at {scheduler!r} ({exc}); expected "
            "'local', 'processes' or the address of a running scheduler, e.g. "
            "tcp://host:8786"
        ) from None


MAX_WORKERS = 1024
"""The most threads or worker processes a sweep starts on one machine."""


def run_sweep(
    spec: SweepSpec,
    out: str | Path,
    *,
    scheduler: str = "local",
    workers: int | None = None,
    progress: Callable[[int, int, float], None] | None = None,
    max_tasks: int | None = None,
):
    """Run (or resume) a sweep and return the path of its store.

    Parameters
    ----------
    spec : SweepSpec
    out : path
        Output directory; the store is ``out/<name>.zarr``.
    scheduler : {"local", "processes"} or a Dask scheduler address
        ``local`` runs in this process; ``processes`` starts a ``distributed.LocalCluster``
        with ``workers`` single-threaded worker processes (forked from this process on Linux, see
        :func:`_start_method`; Dask's periodic monitors made rare, see ``_QUIET``); an address
        connects to a cluster.
    workers : int, optional
        ``local``: threads that run tasks side by side in this process (model mode; the
        compiled filters and numpy's random generator release the GIL), each block's filters
        then single-threaded; an experiment sweep runs its tasks one after the other. With
        ``workers=1`` a model sweep runs on one thread (its filters too, which otherwise take
        :func:`~tobitkf.filters._backend.default_threads`).
        ``processes``: worker processes. Default: :func:`~tobitkf.filters._backend.default_threads`
        (``TOBITKF_NUM_THREADS``, else ``OMP_NUM_THREADS``, else the number of CPUs). Ignored
        for a scheduler address (the cluster has its workers).
    progress : callable(done_blocks, total_blocks, runs_per_second), optional
    max_tasks : int, optional
        Stop after this many tasks (used to test resumption).

    Returns
    -------
    Path
        The store; the reduced Dataset is written to its ``summary`` group when every block is done.

    Raises
    ------
    ValidationError
        A store of a different sweep at ``out``, an unreachable scheduler, an experiment that
        refuses the settings or reports no estimators, or a grid point whose statistics do
        not fit the store (e.g. a grid over the horizon).
    """
    from .._compiled import default_threads
    from .._io import check_writable_dir, safe_child
    from .._validation import check_instance
    from .spec import SweepSpec

    check_instance(spec, SweepSpec, "spec")
    if workers is None:
        workers = default_threads()
    elif isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValidationError(f"workers: expected a positive integer or None, got {workers!r}")
    elif workers > MAX_WORKERS:
        # a typo such as --workers 40000 would start that many threads or processes on one machine
        raise ValidationError(f"workers: expected at most {MAX_WORKERS} workers on one machine, got {workers}")
    out = Path(out)
    check_writable_dir(out, "--out")
    out.mkdir(parents=True, exist_ok=True)
    path = safe_child(out, f"{spec.name}.zarr")
    check_resumable(path, spec)  # a file in the way, a damaged or foreign store: refused before any work
    points = spec.points()
    # connect first: a wrong address fails before any work is done
    client, cluster = _client(scheduler, workers) if scheduler != "local" else (None, None)
    try:
        _run(spec, path, points, client, progress, max_tasks, workers)
    finally:
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()
    return path


def _run(spec: SweepSpec, path: Path, points: list[dict[str, Any]], client, progress, max_tasks, threads: int) -> None:
    """Create or reopen the store, run the missing blocks (in-process, on ``threads`` threads,
    when ``client`` is None) and write the summary once every block is done."""
    if spec.experiment is not None and path.exists():
        g = open_store(path, spec, [], 0, 1, 0)  # resuming: the store knows its shapes
    elif spec.experiment is not None:
        # the first block tells the store its shapes (estimators, horizon, state)
        keys, first = _experiment_block(spec, points[0], 0, spec.block_sizes()[0])
        steps, n = first["sum_sq"].shape[1:]
        g = open_store(path, spec, keys, n, 1, steps)
        write_blocks(g, 0, [(0, first)])
    else:
        pt = build_point(spec, points[0])
        if client is None and threads > 1:  # blocks computed side by side in this process
            spec.check_size(
                pt.system.n,
                pt.reading_width,
                pt.system.q,
                len(pt.estimators),
                parallel=min(threads, len(points) * spec.blocks),
            )
        g = open_store(path, spec, list(pt.estimators), pt.system.n, pt.reading_width, spec.steps)
    done = _read(g, "done")
    tasks = []
    for p in range(len(points)):
        todo = [b for b in range(spec.blocks) if not done[p, b]]
        for i in range(0, len(todo), spec.chunk_blocks):
            tasks.append((p, todo[i : i + spec.chunk_blocks]))
    if max_tasks is not None:
        tasks = tasks[:max_tasks]
    total = int(done.size)
    finished = int(done.sum())
    sizes = spec.block_sizes()
    t0 = time.perf_counter()
    runs_done = 0

    def record(p: int, results: list[tuple[int, dict]]) -> None:
        nonlocal finished, runs_done
        write_blocks(g, p, results)
        for b, _ in results:
            finished += 1
            runs_done += sizes[b]
        if progress is not None:
            progress(finished, total, runs_done / max(time.perf_counter() - t0, 1e-9))

    if progress is not None:
        progress(finished, total, 0.0)
    if client is None and (threads == 1 or spec.experiment is not None or len(tasks) < 2):
        # one worker asked for (workers=1): one thread, the filters' too (as in a Dask worker, where
        # OMP_NUM_THREADS=1); otherwise a sequential run leaves the filters their default threads
        inner = 1 if threads == 1 else None
        for p, blocks in tasks:
            record(p, run_task(spec.text, spec.name, p, blocks, inner))
    elif client is None:
        from concurrent.futures import ThreadPoolExecutor
        from concurrent.futures import as_completed as done_first

        pool = ThreadPoolExecutor(max_workers=threads)
        try:
            futs = {pool.submit(run_task, spec.text, spec.name, p, blocks, 1): p for p, blocks in tasks}
            for fut in done_first(list(futs)):
                # dropped once stored: a finished future holds its blocks' statistics, so keeping
                # them all would make the sweep's memory grow with its run count
                record(futs.pop(fut), fut.result())
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
    else:
        as_completed = require("distributed", extra="sweep").as_completed

        futs = {client.submit(run_task, spec.text, spec.name, p, blocks, pure=False): p for p, blocks in tasks}
        for fut in as_completed(list(futs)):
            # dropped once stored: while the client holds a future, its worker keeps the result
            # (the blocks' statistics), so keeping them all would grow the workers with the run count
            record(futs.pop(fut), fut.result())
            fut.release()
    if bool(_read(g, "done").all()):
        _write_summary(path, reduce_store(g))


def _write_summary(path: Path, ds) -> None:
    """Write the reduced Dataset to the store's ``summary`` group (replaced whole)."""
    import shutil
    import warnings

    tmp = path / "summary.tmp"
    if tmp.exists():
        shutil.rmtree(tmp)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds.to_zarr(str(path), group="summary.tmp", mode="w", consolidated=False)
    final = path / "summary"
    if final.exists():
        shutil.rmtree(final)
    tmp.rename(final)
