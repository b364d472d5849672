"""``tobitkf warmup`` and the compile notice.

The notice: one line on stderr when a kernel of tobitkf is actually compiled (a cache miss), once per
process, nothing on a cache hit; ``import tobitkf`` does not import numba for it. Checked in fresh
processes with their own numba cache folder (``NUMBA_CACHE_DIR``) on a one-line kernel, so no test pays
for compiling the real kernels; the real warmup is a heavy test.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from typer.testing import CliRunner

from tobitkf import _warmup, cli
from tobitkf._compiled import COMPILE_NOTICE

SRC = str(Path(__file__).resolve().parents[1] / "src")

KERNELS = textwrap.dedent(
    """
    import numba

    @numba.njit(cache=True)
    def add_one(x):
        return x + 1

    @numba.njit(cache=True)
    def double(x):
        return x * 2
    """
)
USER = textwrap.dedent(
    """
    import sys
    import tobitkf
    assert "numba" not in sys.modules  # importing tobitkf does not import numba
    from tobitkf import _compiled
    _compiled._PACKAGES.append("fakekernels")  # stands for tobitkf's kernels
    import fakekernels
    print(fakekernels.add_one(1), fakekernels.add_one(2.5), fakekernels.double(3))  # three compiles
    print(_compiled.compile_stats()["compiled"])
    """
)


def _run(script: Path, cache: Path) -> subprocess.CompletedProcess:
    env = {
        **os.environ,
        "NUMBA_CACHE_DIR": str(cache),
        "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", ""),
    }
    return subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=600)


def test_the_notice_comes_once_per_process_and_only_when_a_kernel_compiles(tmp_path):
    (tmp_path / "fakekernels.py").write_text(KERNELS)
    script = tmp_path / "user.py"
    script.write_text(USER)
    first = _run(script, tmp_path / "cache")
    assert first.returncode == 0, first.stderr
    assert first.stdout.split() == ["2", "3.5", "6", "3"]
    assert first.stderr.count(COMPILE_NOTICE) == 1  # three compiles, one line
    second = _run(script, tmp_path / "cache")  # the same kernels, now in the disk cache
    assert second.returncode == 0, second.stderr
    assert second.stdout.split() == ["2", "3.5", "6", "0"]
    assert COMPILE_NOTICE not in second.stderr


def test_the_notice_is_silent_for_kernels_of_other_packages(tmp_path):
    (tmp_path / "fakekernels.py").write_text(KERNELS)
    script = tmp_path / "other.py"
    script.write_text("import tobitkf, fakekernels\nprint(fakekernels.add_one(1))\n")
    res = _run(script, tmp_path / "cache")
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["2"] and COMPILE_NOTICE not in res.stderr


def test_warmup_runs_every_target_with_a_line_each(monkeypatch):
    ran = []
    targets = [("first group", lambda: ran.append(1)), ("second group", lambda: ran.append(2))]
    monkeypatch.setattr(_warmup, "TARGETS", targets)
    res = CliRunner().invoke(cli.app, ["warmup", "--jobs", "1"])
    assert res.exit_code == 0, res.output
    assert ran == [1, 2]
    assert "[1/2] first group: " in res.output and "[2/2] second group: " in res.output
    assert "warmup: " in res.output


@pytest.mark.parametrize("count, word", [(1, "1 kernel compiled"), (3, "3 kernels compiled")])
def test_warmup_counts_its_kernels_in_the_right_number(monkeypatch, count, word):
    """One compiled kernel is "1 kernel", not "1 kernels" (what warmup said after compiling one)."""
    from tobitkf import _compiled

    calls = iter([{"compiled": 0, "seconds": 0.0}, {"compiled": count, "seconds": 1.5}])
    monkeypatch.setattr(_compiled, "compile_stats", lambda: next(calls))
    monkeypatch.setattr(_warmup, "TARGETS", [("group", lambda: None)])
    res = CliRunner().invoke(cli.app, ["warmup"])
    assert res.exit_code == 0, res.output
    assert f"warmup: {word} in 1.5 s" in res.output


def test_plural_and_the_messages_that_count():
    """The count-and-noun phrases of user messages agree in number (they said "1 runs", "1 iterations",
    "all 1 readings are missing", "has 1 steps")."""
    import numpy as np

    import tobitkf as tk
    from tobitkf._progress import plural

    assert [plural(n, "kernel") for n in (0, 1, 2)] == ["0 kernels", "1 kernel", "2 kernels"]
    assert plural(1, "series", "series") == "1 series" and plural(2, "child", "children") == "2 children"
    with pytest.raises(tk.ValidationError, match=r"y: the one reading is missing \(NaN\)"):
        tk.fit(tk.CensoredAR(1), np.array([np.nan]))
    sys_ = tk.LinearSystem(
        A=np.eye(1), C=np.ones((1, 1)), Q=np.ones((1, 1)) * 0.1, R=np.ones((1, 1)), x0=[0.0], P0=[[1.0]]
    )
    with pytest.raises(tk.ValidationError, match=r"1 run x 10000000000 steps"):
        tk.simulate(sys_, 10**10, 1)
    cens = tk.Censoring(lower=np.zeros((1, 1)))
    with pytest.raises(tk.ShapeError, match=r"time-varying limits have 1 step, 3 needed"):
        tk.TobitKalmanFilter(sys_, cens).filter(np.zeros((3, 1)))


def _write_pid(path: Path) -> None:  # a warmup target of the test below (module level: the workers import it)
    path.write_text(str(os.getpid()))


def test_warmup_runs_its_targets_in_worker_processes_at_once(monkeypatch, tmp_path):
    """With --jobs 2 each target runs in a worker process (spawned, so each has its own numba state), every
    target gets its line, and the workers' compile counts are summed (here none compile)."""
    import functools

    files = [tmp_path / "a", tmp_path / "b", tmp_path / "c"]
    targets = [(f"group {p.name}", functools.partial(_write_pid, p)) for p in files]
    monkeypatch.setattr(_warmup, "TARGETS", targets)
    res = CliRunner().invoke(cli.app, ["warmup", "--jobs", "2"])
    assert res.exit_code == 0, res.output
    pids = {int(p.read_text()) for p in files}
    assert os.getpid() not in pids and 1 <= len(pids) <= 2
    assert all(f"group {p.name}: " in res.output for p in files)
    assert all(f"[{i}/3] " in res.output for i in (1, 2, 3))
    assert "warmup: every kernel was cached" in res.output


def test_warmup_refuses_a_bad_number_of_jobs():
    with pytest.raises(ValueError, match=r"jobs: expected an integer >= 1, got 0"):
        _warmup.warmup(jobs=0)
    res = CliRunner().invoke(cli.app, ["warmup", "--jobs", "0"])
    assert res.exit_code == 2 and "--jobs" in res.output


def test_warmup_failure_is_one_line_and_exit_2(monkeypatch):
    def broken():
        raise ValueError("no such kernel")

    monkeypatch.setattr(_warmup, "TARGETS", [("broken", broken)])
    res = CliRunner().invoke(cli.app, ["warmup", "--jobs", "1"])
    assert res.exit_code == 2
    assert "no such kernel" in res.output and "Traceback" not in res.output


def test_every_target_is_a_labelled_callable():
    assert len(_warmup.TARGETS) >= 5
    assert all(isinstance(label, str) and label and callable(fn) for label, fn in _warmup.TARGETS)


@pytest.mark.heavy
def test_the_real_warmup_exits_0_and_a_second_one_compiles_nothing():
    env = {**os.environ, "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", "")}
    cmd = [sys.executable, "-m", "tobitkf", "warmup"]
    first = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1800)
    assert first.returncode == 0, first.stderr
    assert first.stderr.count(f"[{len(_warmup.TARGETS)}/{len(_warmup.TARGETS)}]") == 1
    second = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1800)
    assert second.returncode == 0, second.stderr
    assert "every kernel was cached" in second.stdout and COMPILE_NOTICE not in second.stderr


WORKERS = textwrap.dedent(
    """
    import multiprocessing
    import os
    import sys
    import time
    from concurrent.futures import ProcessPoolExecutor

    from tobitkf import cli


    def compile_in_worker(name):
        # a barrier on files: each task waits until both have started, so each worker runs one of them
        open(os.path.join(os.environ["BARRIER"], name), "w").close()
        t0 = time.time()
        while len(os.listdir(os.environ["BARRIER"])) < 2 and time.time() - t0 < 120:
            time.sleep(0.01)
        from tobitkf import _compiled
        _compiled._PACKAGES.append("fakekernels")
        import fakekernels
        getattr(fakekernels, name)(3)
        return _compiled.compile_stats()["compiled"]


    if __name__ == "__main__":
        ctx = multiprocessing.get_context("spawn")
        shared = sys.argv[1] == "shared"
        init = {"initializer": cli._worker_threads, "initargs": (1, ctx.Value("b", 0))} if shared else {}
        with ProcessPoolExecutor(2, mp_context=ctx, **init) as pool:
            print(*pool.map(compile_in_worker, ["add_one", "double"]))  # one task each: both workers compile
    """
)


@pytest.mark.parametrize("shared", [True, False])
def test_the_notice_comes_once_for_all_worker_processes_of_reproduce(tmp_path, shared):
    # reproduce's worker processes share a flag (cli._worker_threads): two workers that both compile print one
    # notice; without the flag each process prints its own (the case it guards against)
    (tmp_path / "fakekernels.py").write_text(KERNELS)
    script = tmp_path / "workers.py"
    script.write_text(WORKERS)
    (tmp_path / "barrier").mkdir()
    env = {
        **os.environ,
        "NUMBA_CACHE_DIR": str(tmp_path / "cache"),
        "BARRIER": str(tmp_path / "barrier"),
        "PYTHONPATH": SRC + os.pathsep + str(tmp_path) + os.pathsep + os.environ.get("PYTHONPATH", ""),
    }
    arg = "shared" if shared else "plain"
    res = subprocess.run([sys.executable, str(script), arg], capture_output=True, text=True, env=env, timeout=600)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["1", "1"]  # each worker compiled its kernel
    assert res.stderr.count(COMPILE_NOTICE) == (1 if shared else 2)
