"""Nothing lost (issue 9 item 4): result files appear whole or not at all, an interrupted
``reproduce`` or ``sweep`` leaves the previous complete results intact, a rerun completes them.

Interruptions are simulated in-process by raising KeyboardInterrupt at the worst moment
(mid-file, between a figure and metrics.json, between the two renames of the folder swap,
between a sweep block's data and its done flag). The sweep tests in tests/sweep cover a
SIGKILLed sweep process.
"""

import json
import os
import stat
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from typer.testing import CliRunner  # noqa: E402

import tobitkf as tk  # noqa: E402
from tobitkf import (
    _io,  # noqa: E402
    cli,  # noqa: E402
)
from tobitkf.experiments import _REGISTRY, Experiment, ExperimentResult  # noqa: E402
from tobitkf.sweep import load_result, parse_sweep, run_sweep  # noqa: E402
from tobitkf.sweep import run as sweep_run  # noqa: E402
from tobitkf.sweep import store as sweep_store  # noqa: E402


# --- atomic single files ----------------------------------------------------------------
def test_interrupted_json_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path, monkeypatch):
    path = tmp_path / "metrics.json"
    _io.atomic_write_json(path, {"a": 1})
    old = path.read_bytes()

    def boom(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(KeyboardInterrupt):
        _io.atomic_write_json(path, {"a": 2, "big": list(range(10_000))})
    assert path.read_bytes() == old
    assert [p.name for p in tmp_path.iterdir()] == ["metrics.json"]


def test_interrupted_savefig_keeps_the_old_figure(tmp_path, monkeypatch):
    path = tmp_path / "fig.png"
    fig, ax = plt.subplots()
    ax.plot([0, 1], [0, 1])
    _io.atomic_savefig(fig, path)
    old = path.read_bytes()

    def half_write(self, fname, *args, **kwargs):
        Path(fname).write_bytes(b"\x89PNG half")  # a truncated file, then the interruption
        raise KeyboardInterrupt

    monkeypatch.setattr(type(fig), "savefig", half_write)
    with pytest.raises(KeyboardInterrupt):
        _io.atomic_savefig(fig, path)
    plt.close(fig)
    assert path.read_bytes() == old
    assert [p.name for p in tmp_path.iterdir()] == ["fig.png"]


def test_result_files_get_the_ordinary_umask_mode(tmp_path):
    mask = os.umask(0o022)
    try:
        p = _io.atomic_write_text(tmp_path / "x.txt", "x")
    finally:
        os.umask(mask)
    assert stat.S_IMODE(p.stat().st_mode) == 0o644  # mkstemp alone would give 0o600


# --- reproduce: folder swap and --resume ------------------------------------------------
CALLS = []


def _dummy_run(*, runs, seed, progress=None, **kw):
    CALLS.append((runs, seed))
    rng = np.random.default_rng(seed)
    truth = rng.normal(size=(runs, 5, 1))
    est = truth + rng.normal(size=truth.shape)
    return ExperimentResult(
        id="rel-dummy",
        settings={},
        metrics={"estimators": {"e": tk.metrics.summarize(truth, est)}},
        data={"seed": seed},
    )


def _dummy_plot(result, outdir):
    fig, ax = plt.subplots()
    ax.plot([0, result.data["seed"]])
    p1 = _io.atomic_savefig(fig, Path(outdir) / "a.png")
    p2 = _io.atomic_savefig(fig, Path(outdir) / "b.png")
    plt.close(fig)
    return [p1, p2]


@pytest.fixture
def dummy(monkeypatch):
    CALLS.clear()
    exp = Experiment(
        id="rel-dummy", title="dummy", source="test", run=_dummy_run, plot=_dummy_plot, default_runs=3, module=__name__
    )
    monkeypatch.setitem(_REGISTRY, "rel-dummy", exp)
    return exp


def snapshot(folder):
    return {p.name: p.read_bytes() for p in sorted(Path(folder).iterdir())}


def test_reproduce_interrupted_after_a_figure_keeps_the_previous_result(tmp_path, dummy, monkeypatch):
    cli.run_experiment("rel-dummy", runs=3, seed=1, out=tmp_path)
    before = snapshot(tmp_path / "rel-dummy")

    def plot_then_die(result, outdir):
        fig, ax = plt.subplots()
        _io.atomic_savefig(fig, Path(outdir) / "a.png")  # a new figure is written...
        plt.close(fig)
        raise KeyboardInterrupt  # ...then the run is interrupted

    monkeypatch.setitem(_REGISTRY, "rel-dummy", Experiment(**{**dummy.__dict__, "plot": plot_then_die}))
    with pytest.raises(KeyboardInterrupt):
        cli.run_experiment("rel-dummy", runs=3, seed=2, out=tmp_path)
    assert snapshot(tmp_path / "rel-dummy") == before  # old figures and metrics, unmixed
    assert json.loads(before["metrics.json"])["seed"] == 1
    visible = [p.name for p in tmp_path.iterdir() if not p.name.startswith(".")]
    assert visible == ["rel-dummy"]

    monkeypatch.setitem(_REGISTRY, "rel-dummy", dummy)  # the rerun completes and cleans up
    cli.run_experiment("rel-dummy", runs=3, seed=2, out=tmp_path)
    assert json.loads((tmp_path / "rel-dummy" / "metrics.json").read_text())["seed"] == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rel-dummy"]


def test_interruption_between_the_two_renames_is_repaired(tmp_path, dummy, monkeypatch):
    cli.run_experiment("rel-dummy", runs=3, seed=1, out=tmp_path)
    before = snapshot(tmp_path / "rel-dummy")
    real_replace = os.replace
    calls = []

    def second_rename_dies(src, dst):
        calls.append((src, dst))
        if len(calls) == 2 and Path(dst).name == "rel-dummy":
            raise KeyboardInterrupt
        return real_replace(src, dst)

    monkeypatch.setattr(_io.os, "replace", second_rename_dies)
    with pytest.raises(KeyboardInterrupt):
        _io.replace_dir(_io.staging_dir(tmp_path / "rel-dummy"), tmp_path / "rel-dummy")
    monkeypatch.setattr(_io.os, "replace", real_replace)
    assert not (tmp_path / "rel-dummy").exists()  # the old result was moved aside...
    _io.staging_dir(tmp_path / "rel-dummy")  # ...and the next run puts it back first
    assert snapshot(tmp_path / "rel-dummy") == before


def test_resume_skips_complete_experiments_only(tmp_path, dummy):
    runner = CliRunner()
    res = runner.invoke(cli.app, ["reproduce", "rel-dummy", "--runs", "3", "--seed", "5", "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    assert CALLS == [(3, 5)]
    res = runner.invoke(
        cli.app, ["reproduce", "rel-dummy", "--runs", "3", "--seed", "5", "--out", str(tmp_path), "--resume"]
    )
    assert res.exit_code == 0 and CALLS == [(3, 5)]  # complete: kept
    assert cli.is_complete(tmp_path, "rel-dummy", runs=3, seed=5)
    assert not cli.is_complete(tmp_path, "rel-dummy", runs=4, seed=5)  # other run count
    assert not cli.is_complete(tmp_path, "rel-dummy", runs=3, seed=6)  # other seed
    assert cli.is_complete(tmp_path, "rel-dummy", runs=None, seed=5)  # default run count (3) is the same
    (tmp_path / "rel-dummy" / "b.png").unlink()  # a figure lost: incomplete
    assert not cli.is_complete(tmp_path, "rel-dummy", runs=3, seed=5)
    res = runner.invoke(
        cli.app, ["reproduce", "rel-dummy", "--runs", "3", "--seed", "5", "--out", str(tmp_path), "--resume"]
    )
    assert res.exit_code == 0 and CALLS == [(3, 5), (3, 5)]  # rerun completes it
    assert (tmp_path / "rel-dummy" / "b.png").exists()


def test_resume_ignores_a_result_of_another_package_version(tmp_path, dummy):
    cli.run_experiment("rel-dummy", runs=3, seed=0, out=tmp_path)
    m = tmp_path / "rel-dummy" / "metrics.json"
    meta = json.loads(m.read_text())
    meta["package_version"] = "0.0.0-other"
    m.write_text(json.dumps(meta))
    assert not cli.is_complete(tmp_path, "rel-dummy", runs=3, seed=0)
    m.write_text("{ truncated")
    assert not cli.is_complete(tmp_path, "rel-dummy", runs=3, seed=0)


# --- sweep: a block interrupted between its data and its done flag ------------------------
SWEEP = """
[sweep]
runs = 60
steps = 10
seed = 4
block_runs = 20
chunk_blocks = 1

[model]
A = [[0.9]]
C = [[1.0]]
Q = [[0.04]]
R = [[0.01]]
x0 = [0.0]
P0 = [[0.2]]

[censoring]
lower = 0.0

[estimators.tkf]
type = "TobitKalmanFilter"
"""


def test_sweep_block_interrupted_before_its_done_flag_is_recomputed(tmp_path, monkeypatch):
    spec = parse_sweep(SWEEP, name="s")
    ref = load_result(run_sweep(spec, tmp_path / "ref"))
    real = sweep_store.write_blocks
    count = []

    def dies_mid_block(g, point, results):
        count.append(point)
        if len(count) == 2:  # second task: data written, flags not
            b, stats = results[0]
            g["stats"][point, b] = 1e6
            raise KeyboardInterrupt
        return real(g, point, results)

    monkeypatch.setattr(sweep_run, "write_blocks", dies_mid_block)
    with pytest.raises(KeyboardInterrupt):
        run_sweep(spec, tmp_path / "cut")
    monkeypatch.setattr(sweep_run, "write_blocks", real)
    with pytest.raises(tk.ValidationError, match="not finished"):
        load_result(tmp_path / "cut" / "s.zarr")
    resumed = load_result(run_sweep(spec, tmp_path / "cut"))
    for name in ref.data_vars:
        np.testing.assert_array_equal(ref[name].values, resumed[name].values)


def test_sweep_interrupted_while_replacing_its_summary_is_completed_by_a_rerun(tmp_path, monkeypatch):
    spec = parse_sweep(SWEEP, name="s")
    path = run_sweep(spec, tmp_path)
    ref = load_result(path)
    real_rename = Path.rename

    def dies(self, target):
        raise KeyboardInterrupt

    monkeypatch.setattr(Path, "rename", dies)
    with pytest.raises(KeyboardInterrupt):
        run_sweep(spec, tmp_path)  # all blocks done: only the summary is rewritten
    monkeypatch.setattr(Path, "rename", real_rename)
    run_sweep(spec, tmp_path)
    assert (path / "summary").exists()
    again = load_result(path)
    for name in ref.data_vars:
        np.testing.assert_array_equal(ref[name].values, again[name].values)
