"""Test-suite configuration: hypothesis profiles.

``ci`` (the default) keeps every property test to a bounded example count so the suite
stays fast; ``long`` is for a run by hand::

    HYPOTHESIS_PROFILE=long python -m pytest tests/reliability -q

Tests that pass their own ``@settings(max_examples=...)`` keep it (explicit settings win).
"""

import os

import pytest
from hypothesis import HealthCheck, settings

settings.register_profile(
    "ci", max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large]
)
settings.register_profile(
    "long", max_examples=1000, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large]
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


# The heavy tests: whole experiments, the docs site with every tutorial executed, Monte Carlo recovery, and
# (marked in their modules) compiled kernels at the sizes the rest of the suite does not compile, each a version of
# its own to compile on a fresh numba cache. They take most of the suite's time, so the default run (the README's
# test command) leaves them out
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


# The runs-vectorised step (tobitkf.filters._compiled_soa) is compiled once per state size, channel count and update
# (15 to 40 s of CPU each on a fresh numba cache), and the public KF, TKF and censored assumed-density filter take it
# for every problem of up to 4 states: each test of a filter on a system of a size of its own compiled a version of
# its own. Outside the tests marked `vectorised_step`, the test run hands those calls to the compiled loop (one
# version for every size, compiled anyway), which gives the same numbers to rounding: for the whole session (module
# fixtures filter too), undone for each marked test. The step itself is tested equal to the compiled loop, for every
# update it serves, in tests/filters/test_compiled_soa.py (marked: there, and in the other tests marked, the public
# filters route as for a user).
_SOA_ROUTES = ("soa_covers", "censored_covers")


def _not_covered(*args, **kwargs) -> bool:
    return False


@pytest.fixture(scope="session", autouse=True)
def _small_problems_on_the_compiled_loop():
    try:
        from tobitkf.filters import _compiled_soa
    except ImportError:  # no numba: no compiled path
        yield None
        return
    real = {name: getattr(_compiled_soa, name) for name in _SOA_ROUTES}
    patch = pytest.MonkeyPatch()
    for name in _SOA_ROUTES:
        patch.setattr(_compiled_soa, name, _not_covered)
    yield _compiled_soa, real
    patch.undo()


@pytest.fixture(autouse=True)
def _vectorised_step_where_marked(request, _small_problems_on_the_compiled_loop):
    routes = _small_problems_on_the_compiled_loop
    if routes is None or request.node.get_closest_marker("vectorised_step") is None:
        yield
        return
    module, real = routes
    patch = pytest.MonkeyPatch()
    for name, fn in real.items():
        patch.setattr(module, name, fn)
    yield
    patch.undo()


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


# Where the run's compile time goes: the CPU seconds of every outermost numba compile of a tobitkf function (its callees
# compiled inside it included), summed over the processes of the run, the largest listed in the run's summary. On a
# fresh numba cache compiling is most of the default run's time; a function listed with more versions than the tests
# need, or compiled by every worker, is where it can be cut. Each compile is kept as (function, argument types) with
# its CPU seconds and the test that was running (the one that paid for it): the summary lists the costliest versions
# with that test, and the CPU of compiles of a version that another process of the run compiled too (two xdist
# workers needing it at once, before either had written it to the on-disk cache).
_COMPILES: list[tuple[str, str, float, str]] = []
_CURRENT_TEST = {"nodeid": "(outside a test)"}


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    _CURRENT_TEST["nodeid"] = item.nodeid
    yield
    _CURRENT_TEST["nodeid"] = "(outside a test)"


def _short_types(args) -> str:
    """The argument types of a compile, short: ``f8[3C]`` a C-contiguous 3-d float64 array (``R`` read-only, ``A``
    any layout), ``(k)`` a tuple of k numbers (the compile-time sizes and kinds), ``f()`` a compiled function ``f``,
    other types by name."""
    from numba.core import types

    def one(t):
        if isinstance(t, types.Array):
            return f"{t.dtype.name}[{t.ndim}{t.layout}{'' if t.mutable else 'R'}]".replace("float64", "f8")
        if isinstance(t, types.UniTuple):
            return f"({t.count})"
        if isinstance(t, types.Dispatcher):  # a compiled model function: its name, not its address
            return f"{t.dispatcher.py_func.__name__}()"
        return str(t)

    return " ".join(one(t) for t in args)


def _compile_listener():
    import time

    from numba.core import event

    class _Listener(event.Listener):
        def __init__(self):
            self.started: list[float] = []

        def on_start(self, ev):
            self.started.append(time.process_time())

        def on_end(self, ev):
            t0 = self.started.pop()
            if self.started:  # a callee compiled inside an outer compile: counted in the outer one
                return
            data = ev.data or {}
            func = getattr(data.get("dispatcher"), "py_func", None)
            mod = getattr(func, "__module__", "") or ""
            if mod.startswith("tobitkf"):
                name = f"{mod}.{func.__qualname__}"
                _COMPILES.append((name, _short_types(data.get("args", ())), time.process_time() - t0,
                                  _CURRENT_TEST["nodeid"]))  # fmt: skip

    return _Listener()


def pytest_configure(config):
    try:
        from numba.core import event
    except ImportError:
        return
    event.register("numba:compile", _compile_listener())


def pytest_sessionfinish(session):
    try:
        found = _needless_specialisations()
    except Exception as exc:  # noqa: BLE001 - a diagnostic: never fail the run for it
        found = [f"(the check of the compiled kernels failed: {exc!r})"]
    workeroutput = getattr(session.config, "workeroutput", None)
    if workeroutput is not None:  # an xdist worker: the controller reports it
        workeroutput["needless_specialisations"] = found
        workeroutput["compiles"] = list(_COMPILES)
    else:
        _NEEDLESS.extend(found)


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error):
    out = getattr(node, "workeroutput", {})
    _NEEDLESS.extend(out.get("needless_specialisations", []))
    _COMPILES.extend(tuple(c) for c in out.get("compiles", []))


def pytest_terminal_summary(terminalreporter):
    if _NEEDLESS:
        terminalreporter.section("kernels compiled again for read-only or strided arrays")
        for line in sorted(set(_NEEDLESS)):
            terminalreporter.write_line(line)
    if _COMPILES:
        _compile_summary(terminalreporter)


def _compile_summary(terminalreporter) -> None:
    """The run's compile CPU: per function (compiles, distinct versions), the costliest versions with the test that
    paid for each (its costliest compile, when two processes compiled it), and what the compiles of a version that
    another process compiled too cost."""
    per_fn: dict[str, list] = {}
    per_version: dict[tuple[str, str], list] = {}
    for name, sig, seconds, test in _COMPILES:
        fn = per_fn.setdefault(name, [0.0, 0, set()])
        fn[0] += seconds
        fn[1] += 1
        fn[2].add(sig)
        per_version.setdefault((name, sig), []).append((seconds, test))
    total = sum(c[2] for c in _COMPILES)
    again = sum(seconds for v in per_version.values() for seconds, _ in sorted(v, reverse=True)[1:])
    write = terminalreporter.write_line
    terminalreporter.section(
        f"numba compiles: {total:.0f} s of CPU in all processes, {len(_COMPILES)} compiles of {len(per_version)} "
        f"versions ({again:.0f} s compiling a version again in another process); the largest functions"
    )
    for name, (seconds, count, sigs) in sorted(per_fn.items(), key=lambda kv: -kv[1][0])[:15]:
        write(f"{seconds:8.1f} s  {count:3d} compiles  {len(sigs):3d} versions  {name}")
    terminalreporter.section("numba compiles: the costliest versions, with the test that paid for each")
    first = {key: max(v) for key, v in per_version.items()}
    for (name, sig), (seconds, test) in sorted(first.items(), key=lambda kv: -kv[1][0])[:25]:
        write(f"{seconds:6.1f} s  {name.rsplit('.', 1)[-1]}  {test}")
        write(f"          {sig[:160]}")
