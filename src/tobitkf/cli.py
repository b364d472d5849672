"""Command line: ``tobitkf list``, ``reproduce ID|all``, ``report DIR``, ``sweep FILE``, ``plot RESULT``,
``fit FILE.csv --model MODEL.toml``.

``reproduce`` runs a registered experiment and writes ``DIR/ID/metrics.json`` and
the experiment's figures (PNG), each file atomically, then (re)writes the report of
everything in ``DIR``: ``DIR/index.html`` and ``DIR/REPORT.md`` (see :mod:`tobitkf.report`).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Estimation from censored, fading, delayed and scheduled measurements.")
console = Console(stderr=True)


@app.command("list")
def list_cmd() -> None:
    """List every experiment, one line each: id, default run count, title."""
    from .experiments import all_experiments

    exps = all_experiments()
    width = max(len(e.id) for e in exps)
    for exp in exps:
        typer.echo(f"{exp.id:<{width}}  {exp.default_runs:>6} runs  {exp.title}")


def run_experiment(exp_id: str, *, runs: int | None, seed: int, out: Path, progress: Progress | None = None) -> Path:
    """Run one experiment and write its metrics.json and figures under ``out/exp_id``."""
    import matplotlib

    matplotlib.use("Agg")
    from . import __version__
    from ._io import atomic_write_json, replace_dir, safe_child, staging_dir
    from .experiments import get

    exp = get(exp_id)
    n_runs = exp.default_runs if runs is None else runs
    task = None
    if progress is not None:
        task = progress.add_task(exp_id, total=1.0)

    def report(done: float) -> None:
        if progress is not None:
            progress.update(task, completed=min(max(done, 0.0), 1.0))

    t0 = time.perf_counter()
    result = exp.run(runs=n_runs, seed=seed, progress=report)
    elapsed = time.perf_counter() - t0
    final = safe_child(out, exp_id)
    outdir = staging_dir(final)  # built whole beside the previous result, then swapped in
    figures = exp.plot(result, outdir)
    atomic_write_json(outdir / "metrics.json", {
        "id": exp.id, "title": exp.title, "source": exp.source, "runs": n_runs, "seed": seed,
        "package_version": __version__, "elapsed_seconds": round(elapsed, 3),
        "settings": result.settings, "claims": result.claims, "figures": [Path(f).name for f in figures],
        **result.metrics,
    })
    replace_dir(outdir, final)
    report(1.0)
    return final


def check_out_dir(out: Path) -> None:
    """Refuse an ``--out`` that exists and is not a folder (before any work is done)."""
    from ._validation import ValidationError

    if out.exists() and not out.is_dir():
        raise ValidationError(f"--out: expected a folder, got the file {out}")


def is_complete(out: Path, exp_id: str, *, runs: int | None, seed: int) -> bool:
    """True when ``out/exp_id`` holds a readable metrics.json of the same runs, seed and
    package version whose figures all exist (what ``reproduce --resume`` skips)."""
    import json

    from . import __version__
    from .experiments import get

    folder = out / exp_id
    try:
        meta = json.loads((folder / "metrics.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    n_runs = get(exp_id).default_runs if runs is None else runs
    return (isinstance(meta, dict) and meta.get("runs") == n_runs and meta.get("seed") == seed
            and meta.get("package_version") == __version__
            and isinstance(meta.get("figures", []), list)
            and all(isinstance(f, str) and Path(f).name == f and (folder / f).is_file() for f in meta.get("figures", [])))


@app.command()
def reproduce(
    experiment: Annotated[str, typer.Argument(help="experiment id, or 'all'")],
    runs: Annotated[Optional[int], typer.Option("--runs", min=1, help="Monte Carlo runs (default: the experiment's)")] = None,
    seed: Annotated[int, typer.Option("--seed", help="random seed")] = 0,
    out: Annotated[Path, typer.Option("--out", help="output directory")] = Path("results"),
    resume: Annotated[bool, typer.Option("--resume", help="skip experiments whose OUT/ID/metrics.json is complete "
                                         "for the same runs, seed and package version")] = False,
) -> None:
    """Run an experiment (or all), write metrics.json and figures under OUT/ID/, then the report OUT/index.html."""
    from ._validation import ValidationError
    from .experiments import all_experiments, get

    try:
        ids = [e.id for e in all_experiments()] if experiment == "all" else [get(experiment).id]
        check_out_dir(out)
    except ValidationError as exc:
        console.print(f"[red]error:[/red] {exc}")
        raise typer.Exit(2) from None
    columns = (TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(), TimeRemainingColumn())
    with Progress(*columns, console=console, transient=False) as progress:
        overall = progress.add_task("all experiments", total=len(ids)) if len(ids) > 1 else None
        for exp_id in ids:
            if resume and is_complete(out, exp_id, runs=runs, seed=seed):
                console.print(f"kept {out / exp_id} (complete, --resume)")
                if overall is not None:
                    progress.advance(overall)
                continue
            outdir = run_experiment(exp_id, runs=runs, seed=seed, out=out, progress=progress)
            console.print(f"wrote {outdir}")
            if overall is not None:
                progress.advance(overall)
    _write_report(out)


def _write_report(out: Path) -> None:
    from .report import write_report

    index, md = write_report(out)
    console.print(f"wrote {index} and {md}")


@app.command()
def report(
    results: Annotated[Path, typer.Argument(help="folder written by 'reproduce' (one sub-folder per experiment)")],
) -> None:
    """Write RESULTS/index.html and RESULTS/REPORT.md from every RESULTS/*/metrics.json."""
    from ._validation import ValidationError

    try:
        _write_report(results)
    except ValidationError as exc:
        console.print(f"[red]error:[/red] {exc}")
        raise typer.Exit(2) from None


@app.command()
def sweep(
    file: Annotated[Path, typer.Argument(help="sweep file (TOML)")],
    out: Annotated[Path, typer.Option("--out", help="output directory")] = Path("results/sweeps"),
    scheduler: Annotated[str, typer.Option("--scheduler", help="local | processes | a Dask scheduler address")] = "local",
    workers: Annotated[Optional[int], typer.Option(
        "--workers", min=1, help="threads (local) or worker processes (processes); default: the CPUs")] = None,
) -> None:
    """Run (or resume) a Monte Carlo sweep; results go to OUT/<name>.zarr."""
    from ._validation import ValidationError
    from .sweep import load_sweep, run_sweep

    try:
        spec = load_sweep(file)
        check_out_dir(out)
    except ValidationError as exc:
        console.print(f"[red]error:[/red] {exc}")
        raise typer.Exit(2) from None
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[rate]}"),
               TimeElapsedColumn(), TimeRemainingColumn())
    with Progress(*columns, console=console) as progress:
        task = progress.add_task(f"{spec.name}: blocks", total=None, rate="")

        def report(done: int, total: int, rate: float) -> None:
            progress.update(task, completed=done, total=total, rate=f"{rate:,.0f} runs/s" if rate else "")

        try:
            path = run_sweep(spec, out, scheduler=scheduler, workers=workers, progress=report)
        except ValidationError as exc:
            console.print(f"[red]error:[/red] {exc}")
            raise typer.Exit(2) from None
    console.print(f"wrote {path}")


@app.command()
def plot(
    result: Annotated[Path, typer.Argument(help="a sweep store (DIR/<name>.zarr)")],
    out: Annotated[Optional[Path], typer.Option("--out", help="figure folder (default: next to the store)")] = None,
) -> None:
    """Draw RMSE-over-time and RMSE-versus-parameter figures from a stored sweep."""
    from ._validation import ValidationError
    from .sweep import plot_result

    try:
        paths = plot_result(result, out)
    except ValidationError as exc:
        console.print(f"[red]error:[/red] {exc}")
        raise typer.Exit(2) from None
    for p in paths:
        console.print(f"wrote {p}")


@app.command()
def fit(
    file: Annotated[Path, typer.Argument(help="CSV file with a header row, one row per reading")],
    model: Annotated[Path, typer.Option("--model", help="model file (TOML): columns and model, see tobitkf.inference.fit_cli")],
    out: Annotated[Path, typer.Option("--out", help="output directory")] = Path("fit"),
) -> None:
    """Fit a model to a censored series: writes OUT/fit.json, summary.txt, series.csv and fit.png."""
    from ._validation import ValidationError
    from .inference.fit_cli import run_fit

    try:
        check_out_dir(out)
        paths = run_fit(file, model, out, progress=True)
    except ValidationError as exc:
        console.print(f"[red]error:[/red] {exc}")
        raise typer.Exit(2) from None
    typer.echo((out / "summary.txt").read_text(encoding="utf-8"), nl=False)
    for p in paths:
        console.print(f"wrote {p}")


def main() -> None:  # pragma: no cover - console entry point
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
