"""Test-suite configuration: hypothesis profiles.

``ci`` (the default) keeps every property test to a bounded example count so the suite
stays fast; ``long`` is for a run by hand::

    HYPOTHESIS_PROFILE=long python -m pytest tests/reliability -q

Tests that pass their own ``@settings(max_examples=...)`` keep it (explicit settings win).
"""

import os
import shutil
import subprocess
import sys
import tempfile
import time
from importlib.util import find_spec
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

from . import _compile_once

settings.register_profile(
    "ci", max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large]
)
settings.register_profile(
    "long", max_examples=1000, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large]
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


# The heavy tests: whole experiments, the docs site with every tutorial executed, Monte Carlo recovery.
# They take most of the suite's time, so the default run (the README's test command) leaves them out
# and .ci/run runs them as a second step (`python -m pytest -n 2 -q -m heavy`); run one by hand with
# `-m heavy` (or `-m ""` for everything).
HEAVY = (
    "tests/docs/test_docs.py::test_docs_site_builds_strict",
    "tests/docs/test_docs.py::test_tutorial_code_runs",
    "tests/experiments/test_claims_rule.py::test_every_experiment_follows_the_claims_rule_and_captions_its_figures",
    "tests/experiments/test_verdicts.py::",
    "tests/inference/test_fit.py::test_recovery_of_a_censored_ar1_regression",
    "tests/control/test_closed_loop.py::test_t15_unstable_plant_moving_limit_is_only_locally_stable",
    "tests/reliability/test_fuzz_readers.py::test_randomly_damaged_stores",
    "tests/experiments/test_yardstick.py::test_figures_and_cli",
)


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.nodeid.startswith(HEAVY):
            item.add_marker(pytest.mark.heavy)


# Needless compiles: numba compiles a kernel once per argument type, and a read-only array (np.broadcast_to returns one
# even at the array's own shape) or a strided one (a row of a record) is a type of its own. A caller that hands one
# over compiles the kernel once more in every process with a fresh cache (a minute or more of CPU for the
# whole-record loop). At the end of a run, each kernel of tobitkf that a test process compiled for two argument lists
# differing only in that way is listed in the run's summary (from every xdist worker): pass such arrays through
# tobitkf.filters._outputs.loop_input or np.require(a, dtype, ("C", "W")) before the call.
_NEEDLESS: list[str] = []


def _needless_specialisations() -> list[str]:
    import sys

    if "numba" not in sys.modules:
        return []
    from numba.core import types
    from numba.core.dispatcher import Dispatcher

    def plain(t):
        return (t.dtype, t.ndim) if isinstance(t, types.Array) else t

    found = []
    for name, mod in list(sys.modules.items()):
        if mod is None or not (name == "tobitkf" or name.startswith("tobitkf.")):
            continue
        for attr, obj in list(vars(mod).items()):
            if not isinstance(obj, Dispatcher) or getattr(obj.py_func, "__module__", None) != name:
                continue
            seen: dict = {}
            for sig in obj.signatures:
                key = tuple(plain(t) for t in sig)
                if key in seen:
                    diff = [f"argument {i}: {a} / {b}" for i, (a, b) in enumerate(zip(seen[key], sig)) if a != b]
                    found.append(f"{name}.{attr} ({'; '.join(diff)})")
                    break
                seen[key] = sig
    return found


def pytest_sessionfinish(session):
    try:
        found = _needless_specialisations()
    except Exception as exc:  # noqa: BLE001 - a diagnostic: never fail the run for it
        found = [f"(the check of the compiled kernels failed: {exc!r})"]
    workeroutput = getattr(session.config, "workeroutput", None)
    if workeroutput is not None:  # an xdist worker: the controller reports it
        workeroutput["needless_specialisations"] = found
    else:
        _NEEDLESS.extend(found)


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error):
    _NEEDLESS.extend(getattr(node, "workeroutput", {}).get("needless_specialisations", []))


def pytest_terminal_summary(terminalreporter):
    for line in _WARMUP_LINE:
        terminalreporter.write_line(f"compiled kernels: {line}")
    if _NEEDLESS:
        terminalreporter.section("kernels compiled again for read-only or strided arrays")
        for line in sorted(set(_NEEDLESS)):
            terminalreporter.write_line(line)


# Compile once, not once per worker. On a fresh numba cache (a clean clone, an edit of a compiled module) every xdist
# worker would compile the same kernels at the same moment: the whole-record loop alone takes about three minutes of
# CPU in each. In a distributed run the controller first runs the targets of `tobitkf warmup` (the common kernels, at
# the argument types a user's call passes) in one process per worker, the processes compiling different kernels side
# by side; the workers then load them from the on-disk cache. Workers and warm-up processes take turns on any one
# function (tests/_compile_once.py): a kernel outside the warm-up is compiled by the first worker that needs it and
# loaded by the other; and the workers start on different shares of the suite (pytest_xdist_make_scheduler), so they
# first need different kernels. With the cache already filled this costs seconds (kernels loaded, not compiled); without
# xdist or without numba nothing changes (one process compiles each kernel once anyway, on first use). The warm-up
# runs when the run names a folder (or nothing: the testpaths); TOBITKF_TEST_WARMUP=0 turns it off.
_WARMUP_LINE: list[str] = []
_LOCKS: list[str] = []


def _distributed(config) -> bool:
    """This process is the controller of an xdist run (not a worker, not a plain run)."""
    return not hasattr(config, "workerinput") and config.pluginmanager.has_plugin("dsession")


def pytest_configure(config):
    locks = os.environ.get(_compile_once.ENV)
    if hasattr(config, "workerinput") and locks and os.path.isdir(locks):
        _compile_once.install(locks)


def pytest_sessionstart(session):
    config = session.config
    if not _distributed(config) or find_spec("numba") is None or find_spec("fcntl") is None:
        return
    locks = tempfile.mkdtemp(prefix="tobitkf-compile-")
    _LOCKS.append(locks)
    os.environ[_compile_once.ENV] = locks  # the workers, started after this hook, inherit it
    if os.environ.get("TOBITKF_TEST_WARMUP", "1") == "0" or not _runs_a_folder(config):
        return
    here = Path(__file__).resolve()
    src = str(here.parents[1] / "src")  # the tobitkf the workers import (pytest's pythonpath = src)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (src, os.environ.get("PYTHONPATH")) if p)}
    claims = tempfile.mkdtemp(dir=locks)
    workers = max(1, len(getattr(config.option, "tx", None) or [None]))
    reporter = config.pluginmanager.get_plugin("terminalreporter")
    if reporter is not None:
        reporter.write_line(
            f"compiling the common kernels before the workers start (tobitkf warmup, {workers} processes)"
        )
    n = len(_warmup_targets())
    script = str(here.parent / "_compile_once.py")
    t0 = time.perf_counter()
    procs: list[subprocess.Popen] = []
    try:
        procs += [
            subprocess.Popen(
                [sys.executable, script, locks, claims, str(i * n // workers)],
                env=env,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
            for i in range(workers)
        ]
        done = [p.communicate(timeout=3600) for p in procs]
    except (OSError, subprocess.SubprocessError) as exc:  # the workers compile on first use, as without it
        for p in procs:
            p.kill()
        _WARMUP_LINE.append(f"the warm-up did not run ({exc!r}); the workers compile on first use")
        return
    took = time.perf_counter() - t0
    failed = [err for p, (_out, err) in zip(procs, done) if p.returncode != 0]
    if failed:
        tail = (failed[0].strip().splitlines() or ["?"])[-1]
        _WARMUP_LINE.append(f"the warm-up failed after {took:.0f} s ({tail}); the workers compile on first use")
    else:
        compiled = sum(_last_int(out) for out, _err in done)
        _WARMUP_LINE.append(f"`tobitkf warmup` before the workers: {compiled} kernels compiled in {took:.0f} s")


def _last_int(out: str) -> int:
    """The count a warm-up process prints last (0 if it printed none)."""
    try:
        return int((out.strip().splitlines() or ["0"])[-1])
    except ValueError:
        return 0


def _runs_a_folder(config) -> bool:
    """The run names a folder of tests (or none: the testpaths), not only test files or tests: a run of a few files
    needs few kernels, and its workers compile those once between them without the warm-up."""
    return any(Path(str(arg).split("::")[0]).is_dir() for arg in config.args)


def _dist_asked_for(config) -> bool:
    """The run names a distribution mode itself (command line, PYTEST_ADDOPTS or the ini's addopts)."""
    args = [*config.invocation_params.args, *os.environ.get("PYTEST_ADDOPTS", "").split(), *config.getini("addopts")]
    return any(a in ("--dist", "-d", "--distload") or a.startswith("--dist=") for a in args)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """`-n N` alone: each worker starts on its own share of the suite (work stealing) rather than both on the
    same first tests (xdist's default `load`), so that on a fresh cache the workers first need, and compile,
    different kernels side by side; an idle worker takes tests from the other at the end. An explicit --dist
    keeps its mode."""
    if config.getvalue("dist") != "load" or _dist_asked_for(config):
        return None
    from xdist.scheduler import WorkStealingScheduling

    return WorkStealingScheduling(config, log)


def _warmup_targets() -> list:
    from tobitkf import _warmup

    return _warmup.TARGETS


def pytest_unconfigure(config):
    for locks in _LOCKS:
        shutil.rmtree(locks, ignore_errors=True)
