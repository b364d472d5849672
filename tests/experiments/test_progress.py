"""The main job's progress lines and its two sizes: a line when each experiment starts and ends (with its
time) and every few seconds while it runs, also when the output is not a terminal; ``reproduce --full``
runs an experiment at its full size (run count and settings)."""

from __future__ import annotations

import io
import json
import time

import numpy as np
import pytest
from typer.testing import CliRunner

import tobitkf as tk
from tobitkf import cli
from tobitkf._progress import Heartbeat, format_seconds
from tobitkf.experiments import _REGISTRY, Experiment, ExperimentResult, get, progress_callback

CALLS: list[dict] = []


def _slow_run(*, runs, seed, progress=None, size=1):
    CALLS.append({"runs": runs, "seed": seed, "size": size})
    progress = progress_callback(progress)
    progress(0.5, "half way")
    time.sleep(0.4)
    rng = np.random.default_rng(seed)
    truth = rng.normal(size=(runs, 4, 1))
    return ExperimentResult(
        id="progress-dummy",
        settings={},
        metrics={"estimators": {"e": tk.metrics.summarize(truth, truth + rng.normal(size=truth.shape))}},
    )


def _no_plot(result, outdir):
    return []


@pytest.fixture
def dummy(monkeypatch):
    CALLS.clear()
    exp = Experiment(
        id="progress-dummy",
        title="dummy",
        source="test",
        run=_slow_run,
        plot=_no_plot,
        default_runs=3,
        module=__name__,
        full_runs=7,
        full_settings={"size": 2},
    )
    monkeypatch.setitem(_REGISTRY, "progress-dummy", exp)
    return exp


def test_format_seconds():
    assert format_seconds(4.24) == "4.2 s"
    assert format_seconds(185) == "3 min 05 s"
    assert format_seconds(3720) == "1 h 02 min"


def test_heartbeat_prints_start_progress_and_end_with_its_time():
    out = io.StringIO()
    with Heartbeat("job", every=0.05, stream=out, prefix="[1/2] ") as beat:
        beat(0.25, "estimator tkf")
        time.sleep(0.3)
    lines = out.getvalue().splitlines()
    assert lines[0] == "[1/2] job: started"
    assert lines[-1].startswith("[1/2] job: done in ") and lines[-1].endswith(" s")
    ticks = lines[1:-1]
    assert ticks and all(t.startswith("  job: 25%, estimator tkf (") for t in ticks)
    assert 0.3 <= beat.elapsed < 5


def test_heartbeat_says_when_the_task_stopped():
    out = io.StringIO()
    with pytest.raises(KeyError), Heartbeat("job", every=0, stream=out):
        raise KeyError("x")
    assert out.getvalue().splitlines() == ["job: started", out.getvalue().splitlines()[1]]
    assert out.getvalue().splitlines()[1].startswith("job: stopped (KeyError) in ")


def test_heartbeat_without_announce_prints_the_end_of_a_success_only():
    out = io.StringIO()
    with Heartbeat("job", every=0, stream=out, announce=False):
        pass
    assert [ln.split(" in ")[0] for ln in out.getvalue().splitlines()] == ["job: done"]
    out = io.StringIO()
    with pytest.raises(KeyError), Heartbeat("job", every=0, stream=out, announce=False):
        raise KeyError("x")
    assert out.getvalue() == ""


def test_progress_callback_adapts_one_argument_callbacks():
    got = []
    progress_callback(got.append)(0.5, "note")  # one argument: the fraction only
    progress_callback(lambda f, note=None: got.append((f, note)))(0.7, "n")
    progress_callback(None)(0.1, "nothing happens")
    assert got == [0.5, (0.7, "n")]


def test_reproduce_prints_lines_when_not_a_terminal(tmp_path, dummy, monkeypatch):
    """CliRunner's output is not a terminal: a progress line (every 0.1 s here) with the experiment's note,
    the end line with its time (one experiment: no start line, so that an error stays one line)."""
    monkeypatch.setattr(cli, "_HEARTBEAT_SECONDS", 0.1)
    res = CliRunner().invoke(cli.app, ["reproduce", "progress-dummy", "--out", str(tmp_path / "r")])
    assert res.exit_code == 0, res.output
    out = res.output
    assert "started" not in out
    assert "  progress-dummy: 50%, half way (" in out
    assert "progress-dummy: done in " in out
    assert out.index("half way") < out.index("done in")
    assert CALLS == [{"runs": 3, "seed": 0, "size": 1}]
    meta = json.loads((tmp_path / "r" / "progress-dummy" / "metrics.json").read_text())
    assert meta["runs"] == 3 and meta["full"] is False


def test_reproduce_all_prints_a_line_when_each_experiment_starts_and_ends(tmp_path, dummy, monkeypatch):
    from tobitkf import experiments

    second = Experiment("progress-dummy-2", "dummy", "test", _slow_run, _no_plot, 2, __name__)
    monkeypatch.setattr(experiments, "_REGISTRY", {"progress-dummy": dummy, "progress-dummy-2": second})
    monkeypatch.setattr(experiments, "_DISCOVERED", True)
    monkeypatch.setattr(cli, "_HEARTBEAT_SECONDS", 0.1)
    res = CliRunner().invoke(cli.app, ["reproduce", "all", "--jobs", "1", "--out", str(tmp_path / "r")])
    assert res.exit_code == 0, res.output
    out = res.output
    order = [
        "[1/2] progress-dummy: started",
        "  progress-dummy: 50%, half way (",
        "[1/2] progress-dummy: done in ",
        "[2/2] progress-dummy-2: started",
        "  progress-dummy-2: 50%, half way (",
        "[2/2] progress-dummy-2: done in ",
        "2 experiments in ",
        "(the experiments' own times add up to ",
    ]
    at = [out.index(text) for text in order]
    assert at == sorted(at), out
    assert [c["runs"] for c in CALLS] == [3, 2]


def test_a_failing_experiment_is_one_line_alone_and_named_in_all(tmp_path, monkeypatch):
    from tobitkf import experiments

    def broken(*, runs, seed, progress=None):
        raise tk.ValidationError("runs: too many")

    bad = Experiment("progress-broken", "t", "s", broken, _no_plot, 1, __name__)
    monkeypatch.setattr(experiments, "_REGISTRY", {"progress-broken": bad})
    monkeypatch.setattr(experiments, "_DISCOVERED", True)
    res = CliRunner().invoke(cli.app, ["reproduce", "progress-broken", "--out", str(tmp_path / "a")])
    assert res.exit_code == 2 and [ln for ln in res.output.splitlines() if ln.strip()] == ["error: runs: too many"]
    ok = Experiment("progress-ok", "t", "s", _slow_run, _no_plot, 1, __name__)
    monkeypatch.setattr(experiments, "_REGISTRY", {"progress-broken": bad, "progress-ok": ok})
    res = CliRunner().invoke(cli.app, ["reproduce", "all", "--jobs", "1", "--out", str(tmp_path / "b")])
    assert res.exit_code == 2
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert lines[0] == "[1/2] progress-broken: started"
    assert lines[1].startswith("[1/2] progress-broken: stopped (ValidationError) in ")
    assert lines[2:] == ["error: runs: too many"]


def test_reproduce_full_runs_the_full_size_and_resume_tells_the_sizes_apart(tmp_path, dummy):
    runner = CliRunner()
    out = str(tmp_path / "r")
    res = runner.invoke(cli.app, ["reproduce", "progress-dummy", "--full", "--out", out])
    assert res.exit_code == 0, res.output
    assert CALLS == [{"runs": 7, "seed": 0, "size": 2}]
    meta = json.loads((tmp_path / "r" / "progress-dummy" / "metrics.json").read_text())
    assert meta["runs"] == 7 and meta["full"] is True
    assert cli.is_complete(tmp_path / "r", "progress-dummy", runs=None, seed=0, full=True)
    assert not cli.is_complete(tmp_path / "r", "progress-dummy", runs=None, seed=0, full=False)
    res = runner.invoke(cli.app, ["reproduce", "progress-dummy", "--out", out, "--resume"])
    assert res.exit_code == 0 and len(CALLS) == 2 and CALLS[-1]["runs"] == 3  # not the same size: rerun


def test_reproduce_full_and_runs_together_are_refused(tmp_path, dummy):
    res = CliRunner().invoke(cli.app, ["reproduce", "progress-dummy", "--full", "--runs", "2", "--out", str(tmp_path)])
    assert res.exit_code == 2
    assert "--full" in res.output and "not both" in res.output
    assert CALLS == []


def test_experiment_sizes():
    exp = Experiment("x", "t", "s", _slow_run, _no_plot, 3, "m")
    assert exp.runs_for() == exp.runs_for(True) == 3 and exp.settings_for(True) == {}
    assert get("yardstick").runs_for(True) >= get("yardstick").runs_for(False)


def test_yardstick_names_what_it_is_doing():
    """The yardstick reports each estimator and each block of the particle filter's runs."""
    notes = []
    get("yardstick").run(
        runs=4,
        steps=8,
        particles=20,
        random_systems=0,
        examples=("miller-brownian",),
        doublings=0,
        progress=lambda f, note=None: notes.append((f, note)),
    )
    text = [n for _, n in notes if n]
    assert "miller-brownian: tkf" in text and "miller-brownian: adf" in text
    assert "miller-brownian: particle filter, 20 particles, runs 1-4 of 4" in text
    assert "miller-brownian: particle filter, 40 particles, runs 1-4 of 4" in text
    fractions = [f for f, _ in notes]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0


def _metrics_without_times(folder):
    """metrics.json without its measured times (every key naming seconds), which differ from run to run."""

    def drop(node):
        if isinstance(node, dict):
            return {k: drop(v) for k, v in node.items() if "seconds" not in k}
        return [drop(v) for v in node] if isinstance(node, list) else node

    return drop(json.loads((folder / "metrics.json").read_text()))


@pytest.mark.heavy
def test_experiments_run_at_once_give_the_results_of_one_after_the_other(tmp_path):
    """``reproduce A B C --jobs 2``: each experiment in a worker process, the same metrics (times aside) as
    ``--jobs 1``, a start and an end line for each, the report over all three."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    src = str(Path(cli.__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": src + os.pathsep + os.environ.get("PYTHONPATH", "")}
    ids = ["data-niagara", "miller-fov", "li2018-tracking"]
    runs = {}
    for jobs in ("1", "2"):
        out = tmp_path / f"jobs{jobs}"
        cmd = [sys.executable, "-m", "tobitkf", "reproduce", *ids, "--runs", "2", "--jobs", jobs, "--out", str(out)]
        runs[jobs] = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900)
        assert runs[jobs].returncode == 0, runs[jobs].stderr
        assert (out / "index.html").is_file()
    err = runs["2"].stderr
    for i, exp_id in enumerate(ids, 1):
        assert err.count(f"[{i}/3] {exp_id}: started") == 1 and err.count(f"[{i}/3] {exp_id}: done in ") == 1, err
        assert err.count(f"wrote {tmp_path / 'jobs2' / exp_id}") == 1, err
        assert _metrics_without_times(tmp_path / "jobs2" / exp_id) == _metrics_without_times(
            tmp_path / "jobs1" / exp_id
        )
    assert "3 experiments in " in err and "; 2 at once)" in err


def test_reproduce_refuses_all_beside_ids_and_a_bad_jobs(tmp_path):
    res = CliRunner().invoke(cli.app, ["reproduce", "all", "miller-fov", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "give 'all' alone" in res.output
    res = CliRunner().invoke(cli.app, ["reproduce", "miller-fov", "--jobs", "0", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "--jobs" in res.output
    res = CliRunner().invoke(cli.app, ["reproduce", "miller-fov", "no-such-experiment", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "no-such-experiment" in res.output
    assert not (tmp_path / "miller-fov").exists()  # refused before anything ran
