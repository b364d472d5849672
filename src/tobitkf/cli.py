"""Command line: ``tobitkf list``, ``reproduce ID|all``, ``report DIR``, ``sweep FILE``, ``plot RESULT``,
``fit FILE.csv --model MODEL.toml``.

``reproduce`` runs a registered experiment and writes ``DIR/ID/metrics.json`` and
the experiment's figures (PNG), each file atomically, then (re)writes the report of
everything in ``DIR``: ``DIR/index.html`` and ``DIR/REPORT.md`` (see :mod:`tobitkf.report`).
"""

from __future__ import annotations

import functools
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, Optional

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from ._progress import plural

try:  # typer >= 0.20 carries its own copy of click
    from typer._click import exceptions as _click_errors
except ImportError:  # pragma: no cover - older typer uses click itself
    from click import exceptions as _click_errors  # type: ignore[no-redef]  # the same module, older typer

_ClickException = _click_errors.ClickException
_NoArgsIsHelpError = getattr(_click_errors, "NoArgsIsHelpError", None) or type("_Never", (Exception,), {})


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def fail(message: str, code: int = 2) -> None:
    """Print ``error: MESSAGE`` as one line on stderr (no markup, no wrapping) and exit with ``code``."""
    typer.echo(f"error: {_one_line(message)}", err=True)
    raise typer.Exit(code)


def _describe(exc: BaseException) -> str:
    """One line naming the problem of an exception that reached the command line."""
    from ._extras import missing_extra_message
    from ._validation import ValidationError

    if isinstance(exc, ValidationError):
        return str(exc)
    if isinstance(exc, ImportError) and (message := missing_extra_message(exc)):
        return message
    if isinstance(exc, OSError):
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        return f"{where}{exc.strerror or exc}" + (f" (errno {exc.errno})" if exc.errno else "")
    if isinstance(exc, MemoryError):
        return "out of memory (" + (str(exc) or "an array did not fit") + "); use fewer runs or steps"
    if isinstance(exc, RecursionError):
        return "input nested too deeply to read"
    if isinstance(exc, UnicodeError):
        return f"not UTF-8 text ({exc})"
    return f"unexpected {type(exc).__name__}: {exc} (this is a bug in tobitkf; please report it)"


def cli_errors(command: Callable[..., Any]) -> Callable[..., Any]:
    """Every error that reaches a command becomes exit code 2 and one line naming the problem.

    Input errors (:class:`~tobitkf.ValidationError`), file errors (``OSError``), memory, recursion
    and decoding errors, and anything unexpected: never a traceback (set ``TOBITKF_DEBUG=1`` to
    see one). Ctrl-C stays an interruption (exit 130).
    """

    @functools.wraps(command)
    def run(*args: Any, **kwargs: Any) -> Any:
        try:
            return command(*args, **kwargs)
        except (typer.Exit, typer.Abort, _ClickException, KeyboardInterrupt):
            raise
        except Exception as exc:  # noqa: BLE001 - the command line's promise: one line, exit 2
            if os.environ.get("TOBITKF_DEBUG"):
                raise
            fail(_describe(exc))

    return run


class _Group(typer.core.TyperGroup):
    """The command group; usage errors (unknown option, a value click cannot parse or out of
    range) are one line too, ``error: Invalid value for '--seed': ...``, exit code 2; so is any
    error of a command that is not wrapped by :func:`cli_errors` (the same message)."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode, **extra)
        try:
            rv = super().main(args, prog_name, complete_var, False, **extra)
        except _NoArgsIsHelpError as exc:
            typer.echo(exc.ctx.get_help() if exc.ctx is not None else exc.format_message(), err=True)
            sys.exit(exc.exit_code)
        except _ClickException as exc:
            typer.echo(f"error: {_one_line(exc.format_message())}", err=True)
            sys.exit(exc.exit_code)
        except typer.Abort:
            typer.echo("error: aborted", err=True)
            sys.exit(1)
        except Exception as exc:  # noqa: BLE001 - a command that lacks @cli_errors still ends in one line
            if os.environ.get("TOBITKF_DEBUG"):
                raise
            typer.echo(f"error: {_one_line(_describe(exc))}", err=True)
            sys.exit(2)
        sys.exit(rv if isinstance(rv, int) else 0)


app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    cls=_Group,
    help="Estimation from censored, fading, delayed and scheduled measurements.",
)
console = Console(stderr=True)


def _show_version(value: bool) -> None:
    if value:
        from ._version import __version__

        typer.echo(f"tobitkf {__version__}")
        raise typer.Exit()


@app.callback()
def _options(
    version: Annotated[
        bool,
        typer.Option("--version", callback=_show_version, is_eager=True, help="print the package version and exit"),
    ] = False,
) -> None:
    """Estimation from censored, fading, delayed and scheduled measurements."""


@app.command("list")
@cli_errors
def list_cmd() -> None:
    """List every experiment, one line each: id, default run count, title (and the run count of
    ``reproduce --full`` where it differs)."""
    from .experiments import all_experiments

    exps = all_experiments()
    width = max(len(e.id) for e in exps)
    for exp in exps:
        full = f" (--full: {plural(exp.runs_for(True), 'run')})" if exp.runs_for(True) != exp.default_runs else ""
        typer.echo(
            f"{exp.id:<{width}}  {exp.default_runs:>6} {'run ' if exp.default_runs == 1 else 'runs'}  {exp.title}{full}"
        )


@app.command("estimators")
@cli_errors
def estimators_cmd() -> None:
    """List every registered estimator: name, model kind, the channel pieces it needs, its options."""
    from .filters.registry import ENTRIES

    width = max(len(name) for name in ENTRIES)
    for e in ENTRIES.values():
        needs = ", ".join(e.needs) or "-"
        opts = ", ".join(f"{k}{'*' if k in e.required else ''}" for k in e.options) or "-"
        typer.echo(f"{e.name:<{width}}  {e.model:<7} needs: {needs:<18} options: {opts}")
        typer.echo(f"{'':<{width}}  {e.summary}")
    typer.echo("(* required; a sweep file names them as [[estimators]] type = ...)")


def run_experiment(
    exp_id: str,
    *,
    runs: int | None,
    seed: int,
    out: Path,
    progress: Progress | None = None,
    full: bool = False,
    heartbeat: Any = None,
) -> Path:
    """Run one experiment and write its metrics.json and figures under ``out/exp_id``.

    ``runs`` None: the experiment's default run count, or its full (the sources') run count when
    ``full``. ``heartbeat`` (a :class:`tobitkf._progress.Heartbeat`, optional) receives the
    experiment's progress beside the bar."""
    from ._extras import require

    matplotlib = require("matplotlib", extra="report", feature="the figures of tobitkf reproduce")
    matplotlib.use("Agg")
    from . import __version__
    from ._io import atomic_write_json, replace_dir, safe_child, staging_dir
    from .experiments import get

    exp = get(exp_id)
    n_runs = exp.runs_for(full) if runs is None else runs
    task = None
    if progress is not None:
        task = progress.add_task(exp_id, total=1.0)

    def report(done: float, note: str | None = None) -> None:
        if progress is not None and task is not None:
            progress.update(task, completed=min(max(done, 0.0), 1.0))
        if heartbeat is not None:
            heartbeat(done, note)

    check_experiment_folder(out, exp_id)
    t0 = time.perf_counter()
    result = exp.run(runs=n_runs, seed=seed, progress=report, **exp.settings_for(full))
    elapsed = time.perf_counter() - t0
    final = safe_child(out, exp_id)
    outdir = staging_dir(final)  # built whole beside the previous result, then swapped in
    if heartbeat is not None:
        heartbeat(1.0, "drawing the figures")
    figures = exp.plot(result, outdir)
    atomic_write_json(
        outdir / "metrics.json",
        {
            "id": exp.id,
            "title": exp.title,
            "source": exp.source,
            "runs": n_runs,
            "full": bool(full),
            "seed": seed,
            "package_version": __version__,
            "elapsed_seconds": round(elapsed, 3),
            "settings": result.settings,
            "claims": result.claims,
            "figures": [Path(f).name for f in figures],
            **result.metrics,
        },
    )
    replace_dir(outdir, final)
    report(1.0)
    return final


def check_out_dir(out: Path, name: str = "--out") -> None:
    """Refuse, before any work is done, an ``--out`` that cannot become a writable folder: an
    existing file, a path below a file (``a_file/sub``), a folder without write permission, or a
    name too long for the file system."""
    from ._io import check_writable_dir

    check_writable_dir(out, name)


def check_experiment_folder(out: Path, exp_id: str) -> None:
    """Refuse to replace ``out/exp_id`` unless it is missing, empty, or a result tobitkf wrote
    (a ``metrics.json`` with that id): the folder is swapped out whole."""
    import json

    from ._io import safe_child
    from ._validation import ValidationError

    folder = safe_child(out, exp_id)
    if not (folder.exists() or folder.is_symlink()):
        return
    if not folder.is_dir():
        raise ValidationError(
            f"--out: {folder} is a file, not a result folder of {exp_id}; move it away or choose another --out"
        )
    if not any(folder.iterdir()):
        return
    try:
        meta = json.loads((folder / "metrics.json").read_bytes().decode("utf-8"))
    except (OSError, ValueError, RecursionError):
        meta = None
    if not (isinstance(meta, dict) and meta.get("id") == exp_id):
        raise ValidationError(
            f"--out: {folder} holds files tobitkf did not write (no metrics.json of {exp_id}); "
            "it would be replaced: move it away or choose another --out"
        )


def is_complete(out: Path, exp_id: str, *, runs: int | None, seed: int, full: bool = False) -> bool:
    """True when ``out/exp_id`` holds a readable metrics.json of the same runs, size (``--full`` or not),
    seed and package version whose figures all exist (what ``reproduce --resume`` skips)."""
    import json

    from . import __version__
    from .experiments import get

    folder = out / exp_id
    try:
        meta = json.loads((folder / "metrics.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    n_runs = get(exp_id).runs_for(full) if runs is None else runs
    return (
        isinstance(meta, dict)
        and meta.get("runs") == n_runs
        and meta.get("seed") == seed
        and bool(meta.get("full", False)) == bool(full)
        and meta.get("package_version") == __version__
        and isinstance(meta.get("figures", []), list)
        and all(isinstance(f, str) and Path(f).name == f and (folder / f).is_file() for f in meta.get("figures", []))
    )


@app.command()
@cli_errors
def reproduce(
    experiment: Annotated[list[str], typer.Argument(help="experiment ids, or 'all'")],
    runs: Annotated[
        Optional[int], typer.Option("--runs", min=1, help="Monte Carlo runs (default: the experiment's)")
    ] = None,
    seed: Annotated[int, typer.Option("--seed", help="random seed")] = 0,
    out: Annotated[Path, typer.Option("--out", help="output directory")] = Path("results"),
    resume: Annotated[
        bool,
        typer.Option(
            "--resume",
            help="skip experiments whose OUT/ID/metrics.json is complete for the same runs, seed and package version",
        ),
    ] = False,
    full: Annotated[
        bool,
        typer.Option(
            "--full",
            help="run every experiment at the sources' sizes (their run counts): about an hour on two cores",
        ),
    ] = False,
    jobs: Annotated[
        Optional[int],
        typer.Option(
            "--jobs",
            min=1,
            help="experiments run at once, each in its own process (default: the cores available; 1: one after "
            "the other in this process)",
        ),
    ] = None,
) -> None:
    """Run experiments (or all), write metrics.json and figures under OUT/ID/, then the report OUT/index.html.

    Several experiments run in parallel worker processes (``--jobs``, default one per core), longest first;
    each experiment's results do not depend on what runs beside it. A line on stderr when each experiment
    starts and ends (with its time; one experiment: when it ends), and every 30 s while it runs when
    stderr is not a terminal (a log, CI); with ``--jobs 1`` on a terminal a progress bar."""
    from ._progress import Heartbeat, format_seconds
    from ._validation import ValidationError, check_int
    from ._warmup import default_jobs
    from .experiments import all_experiments, get
    from .report import check_report_targets

    # everything that can be refused is refused before the first experiment runs
    if "all" in experiment:
        if len(experiment) > 1:
            raise ValidationError("experiment: 'all' runs every experiment; give 'all' alone or experiment ids")
        ids = [e.id for e in all_experiments()]
    else:
        ids = list(dict.fromkeys(get(e).id for e in experiment))  # each once, in the order given
    check_int(seed, "--seed", minimum=0)
    if full and runs is not None:
        raise ValidationError(
            "--full: runs every experiment at the sources' run counts; give --runs or --full, not both"
        )
    check_out_dir(out)
    check_report_targets(out)
    for exp_id in ids:
        check_experiment_folder(out, exp_id)
    number = {exp_id: f"[{i + 1}/{len(ids)}] " if len(ids) > 1 else "" for i, exp_id in enumerate(ids)}
    todo = []
    for exp_id in ids:
        if resume and is_complete(out, exp_id, runs=runs, seed=seed, full=full):
            console.print(f"kept {out / exp_id} (complete, --resume)", markup=False, highlight=False, soft_wrap=True)
        else:
            todo.append(exp_id)
    workers = min(default_jobs() if jobs is None else jobs, len(todo))
    terminal = console.is_terminal
    every = 0 if terminal else _HEARTBEAT_SECONDS
    t_all, spent = time.perf_counter(), 0.0
    if workers > 1:
        spent = _reproduce_in_workers(todo, number, workers, runs=runs, seed=seed, out=out, full=full, every=every)
    else:
        columns = (TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(), TimeRemainingColumn())
        with Progress(*columns, console=console, transient=False, disable=not terminal) as progress:
            overall = progress.add_task("all experiments", total=len(ids)) if len(ids) > 1 else None
            if overall is not None:
                progress.advance(overall, len(ids) - len(todo))
            for exp_id in todo:
                with Heartbeat(exp_id, every=every, prefix=number[exp_id], announce=len(ids) > 1) as beat:
                    outdir = run_experiment(
                        exp_id, runs=runs, seed=seed, out=out, progress=progress, full=full, heartbeat=beat
                    )
                spent += beat.elapsed
                console.print(f"wrote {outdir}", markup=False, highlight=False, soft_wrap=True)
                if overall is not None:
                    progress.advance(overall)
    if len(ids) > 1:
        at_once = f"; {workers} at once" if workers > 1 else ""
        console.print(
            f"{len(ids)} experiments in {format_seconds(time.perf_counter() - t_all)} "
            f"(the experiments' own times add up to {format_seconds(spent)}{at_once})",
            markup=False,
            highlight=False,
            soft_wrap=True,
        )
    _write_report(out)


def _worker_threads(threads: int, notice) -> None:
    """A worker process of ``reproduce --jobs``: its share of the cores for the filters' threads (unless set), and
    the compile notice printed by the first worker that compiles (``notice``, a shared flag)."""
    from ._compiled import share_notice

    os.environ.setdefault("TOBITKF_NUM_THREADS", str(threads))
    share_notice(notice)


def _reproduce_one(exp_id: str, prefix: str, runs: int | None, seed: int, out: Path, full: bool, every: float) -> float:
    """Run one experiment in a worker process of ``reproduce --jobs`` (its lines go to this process's stderr);
    returns its seconds."""
    from ._progress import Heartbeat

    with Heartbeat(exp_id, every=every, prefix=prefix, announce=True) as beat:
        run_experiment(exp_id, runs=runs, seed=seed, out=out, full=full, heartbeat=beat)
    return beat.elapsed


def _reproduce_in_workers(
    ids: list[str], number: dict[str, str], workers: int, *, runs: int | None, seed: int, out: Path, full: bool,
    every: float,
) -> float:  # fmt: skip
    """Run ``ids`` in ``workers`` spawned processes, the longest (:attr:`Experiment.cost`) first; returns the sum of
    their seconds. The first failure is raised once the experiments already running have ended (their results are
    written; the ones not started are not)."""
    import multiprocessing
    from concurrent.futures import FIRST_EXCEPTION, ProcessPoolExecutor, wait

    from ._warmup import default_jobs
    from .experiments import get

    order = sorted(ids, key=lambda e: -get(e).cost)  # stable: equal costs keep the registry's order
    context = multiprocessing.get_context("spawn")  # a fresh interpreter each: no forked numba or thread state
    threads = max(1, default_jobs() // workers)
    notice = context.Value("b", 0)  # the compile notice: once for all the workers
    spent = 0.0
    with ProcessPoolExecutor(
        workers, mp_context=context, initializer=_worker_threads, initargs=(threads, notice)
    ) as pool:
        pending = {pool.submit(_reproduce_one, e, number[e], runs, seed, out, full, every): e for e in order}
        while pending:
            done, _ = wait(pending, return_when=FIRST_EXCEPTION)
            for future in done:
                exp_id = pending.pop(future)
                if future.exception() is not None:
                    for other in pending:
                        other.cancel()
                    raise future.exception()  # type: ignore[misc]
                spent += future.result()
                console.print(f"wrote {out / exp_id}", markup=False, highlight=False, soft_wrap=True)
    return spent


_HEARTBEAT_SECONDS = 30.0
"""Seconds between the progress lines of a running experiment when stderr is not a terminal."""


@app.command()
@cli_errors
def warmup(
    jobs: Annotated[
        Optional[int],
        typer.Option("--jobs", min=1, help="worker processes compiling at once (default: the cores available)"),
    ] = None,
) -> None:
    """Compile the common kernels (filters, online step, smoother, censored-AR fit) into numba's disk cache.

    The first process after an install or upgrade compiles each kernel on its first call (minutes for
    all of them); afterwards they load in seconds. The families' compiled paths compile in parallel
    worker processes, one per core. A line per family on stderr as it finishes."""
    from . import _warmup
    from ._compiled import numba_available
    from ._progress import format_seconds

    if not numba_available():
        typer.echo("numba is not installed: nothing to compile (the filters run their numpy paths)")
        return

    def line(text: str) -> None:
        console.print(text, markup=False, highlight=False, soft_wrap=True)

    n_jobs = _warmup.default_jobs() if jobs is None else jobs
    total, compiled, seconds = _warmup.warmup(report=line, jobs=n_jobs)
    used = min(n_jobs, len(_warmup.TARGETS))
    where = f" of compile time, {used} processes at once" if used > 1 else ""
    what = (
        f"{plural(compiled, 'kernel')} compiled in {format_seconds(seconds)}{where}"
        if compiled
        else "every kernel was cached"
    )
    typer.echo(f"warmup: {what}; {format_seconds(total)} in all")


def _write_report(out: Path) -> None:
    from .report import write_report

    index, md = write_report(out)
    console.print(f"wrote {index} and {md}", markup=False, highlight=False, soft_wrap=True)


@app.command()
@cli_errors
def report(
    results: Annotated[Path, typer.Argument(help="folder written by 'reproduce' (one sub-folder per experiment)")],
) -> None:
    """Write RESULTS/index.html and RESULTS/REPORT.md from every RESULTS/*/metrics.json."""
    _write_report(results)


@app.command()
@cli_errors
def sweep(
    file: Annotated[Path, typer.Argument(help="sweep file (TOML)")],
    out: Annotated[Path, typer.Option("--out", help="output directory")] = Path("results/sweeps"),
    scheduler: Annotated[
        str, typer.Option("--scheduler", help="local | processes | a Dask scheduler address")
    ] = "local",
    workers: Annotated[
        Optional[int],
        typer.Option("--workers", min=1, help="threads (local) or worker processes (processes); default: the CPUs"),
    ] = None,
) -> None:
    """Run (or resume) a Monte Carlo sweep; results go to OUT/<name>.zarr."""
    from .sweep import load_sweep, run_sweep
    from .sweep.store import check_resumable

    spec = load_sweep(file)
    check_out_dir(out)
    check_resumable(out / f"{spec.name}.zarr", spec)  # a file in the way, a damaged or foreign store
    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[rate]}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )
    with Progress(*columns, console=console, disable=not console.is_terminal) as progress:
        task = progress.add_task(f"{spec.name}: blocks", total=None, rate="")

        def report(done: int, total: int, rate: float) -> None:
            progress.update(task, completed=done, total=total, rate=f"{rate:,.0f} runs/s" if rate else "")

        path = run_sweep(spec, out, scheduler=scheduler, workers=workers, progress=report)
    console.print(f"wrote {path}", markup=False, highlight=False, soft_wrap=True)


@app.command()
@cli_errors
def plot(
    result: Annotated[Path, typer.Argument(help="a sweep store (DIR/<name>.zarr)")],
    out: Annotated[Optional[Path], typer.Option("--out", help="figure folder (default: next to the store)")] = None,
) -> None:
    """Draw RMSE-over-time and RMSE-versus-parameter figures from a stored sweep."""
    from .sweep import plot_result

    if out is not None:
        check_out_dir(out)
    paths = plot_result(result, out)
    for p in paths:
        console.print(f"wrote {p}", markup=False, highlight=False, soft_wrap=True)


@app.command()
@cli_errors
def fit(
    file: Annotated[Path, typer.Argument(help="CSV file with a header row, one row per reading")],
    model: Annotated[
        Path, typer.Option("--model", help="model file (TOML): columns and model, see tobitkf.inference.fit_cli")
    ],
    out: Annotated[Path, typer.Option("--out", help="output directory")] = Path("fit"),
    format: Annotated[
        Optional[str],
        typer.Option(
            "--format",
            help="layout of FILE: auto, strings ('<0.05'), flag (value, flag, limit), interval (ConcLow/ConcHigh), "
            "nonmem (DV/CENS/LIMIT); default: the model file's, else auto",
        ),
    ] = None,
    force: Annotated[
        bool,
        typer.Option(
            "--force",
            help="replace fit.json, summary.txt, series.csv, forecast.csv, fit.png even if tobitkf did not write them",
        ),
    ] = False,
) -> None:
    """Fit a model to a censored series or a panel of subjects: writes OUT/fit.json, summary.txt, series.csv,
    forecast.csv (continuous-time model with a forecast lead) and fit.png."""
    from .inference.fit_cli import run_fit

    check_out_dir(out)
    paths = run_fit(file, model, out, progress=True, format=format, force=force, notes=_note)
    typer.echo((out / "summary.txt").read_text(encoding="utf-8"), nl=False)
    for p in paths:
        _note(f"wrote {p}")


def _note(line: str) -> None:
    """One line on stderr, printed as written (no markup: ``[data]`` stays ``[data]``)."""
    console.print(line, markup=False, highlight=False, soft_wrap=True)


def main() -> None:  # pragma: no cover - console entry point
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
