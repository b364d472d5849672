"""The test run's compile-once helper (tests/_compile_once.py): processes sharing a lock folder compile each
function once between them, and the warm-up processes share the targets. Checked on one-line kernels in fresh
processes with their own numba cache folder, so no test pays for compiling the real kernels."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytest.importorskip("numba")
pytest.importorskip("fcntl")

ROOT = Path(__file__).resolve().parents[1]

KERNELS = textwrap.dedent(
    """
    import numba

    @numba.njit(cache=True)
    def square_sum(x):
        s = 0.0
        for i in range(x.shape[0]):
            s += x[i] * x[i]
        return s

    @numba.njit(cache=True)
    def plus_one(x):
        return square_sum(x) + 1.0
    """
)
# both processes start their calls together (a file "go"), so that without the locks each would compile every
# signature itself
USER = textwrap.dedent(
    """
    import os, sys, time
    import numpy as np
    from tests import _compile_once
    from numba.core import event
    compiles = []
    class Count(event.Listener):
        def on_start(self, e):
            compiles.append(e.data["dispatcher"].py_func.__name__)
        def on_end(self, e):
            pass
    event.register("numba:compile", Count())
    _compile_once.PACKAGES.append("fakekernels")
    assert _compile_once.install(sys.argv[1])
    import fakekernels
    while not os.path.exists(sys.argv[2]):
        time.sleep(0.01)
    got = [fakekernels.square_sum(np.ones(3)), fakekernels.square_sum(np.ones(3, np.float32)),
           fakekernels.plus_one(np.ones(2))]
    print(got, len(compiles))
    """
)
WARM = textwrap.dedent(
    """
    import sys
    import numpy as np
    from tests import _compile_once
    from tobitkf import _compiled, _warmup
    _compiled._PACKAGES.append("fakekernels")
    _compile_once.PACKAGES.append("fakekernels")
    import fakekernels
    ran = []
    def target(name, fn):
        def run():
            fn()
            ran.append(name)
        return (name, run)
    _warmup.TARGETS = [target("a", lambda: fakekernels.plus_one(np.ones(2))),
                       target("b", lambda: fakekernels.square_sum(np.ones(2, np.float32))),
                       target("c", lambda: fakekernels.square_sum(np.ones(2)))]
    _compile_once.warm(sys.argv[1], sys.argv[2], int(sys.argv[3]))
    print(",".join(ran))
    """
)


def _env(tmp_path: Path) -> dict[str, str]:
    path = os.pathsep.join([str(tmp_path), str(ROOT), str(ROOT / "src"), os.environ.get("PYTHONPATH", "")])
    return {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"), "PYTHONPATH": path}


def test_two_processes_compile_each_signature_once_between_them(tmp_path):
    (tmp_path / "fakekernels.py").write_text(KERNELS)
    (tmp_path / "user.py").write_text(USER)
    (tmp_path / "locks").mkdir()
    go = tmp_path / "go"
    cmd = [sys.executable, str(tmp_path / "user.py"), str(tmp_path / "locks"), str(go)]
    procs = [subprocess.Popen(cmd, env=_env(tmp_path), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)]
    procs.append(subprocess.Popen(cmd, env=_env(tmp_path), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    go.write_text("")
    outs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), [err for _out, err in outs]
    results = [out.rsplit(" ", 1) for out, _err in outs]
    assert all(r[0] == "[3.0, 3.0, 3.0]" for r in results)
    # three outermost compiles are needed (square_sum for float64 and float32, plus_one), each once in all
    assert sum(int(r[1]) for r in results) == 3, outs


def test_warm_up_processes_share_the_targets_and_run_each_once(tmp_path):
    (tmp_path / "fakekernels.py").write_text(KERNELS)
    (tmp_path / "warm.py").write_text(WARM)
    (tmp_path / "locks").mkdir()
    (tmp_path / "claims").mkdir()
    cmds = [
        [sys.executable, str(tmp_path / "warm.py"), str(tmp_path / "locks"), str(tmp_path / "claims"), s] for s in "01"
    ]
    procs = [
        subprocess.Popen(c, env=_env(tmp_path), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for c in cmds
    ]
    outs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), [err for _out, err in outs]
    ran = [name for out, _err in outs for name in out.strip().split(",") if name]
    assert sorted(ran) == ["a", "b", "c"]  # every target once, by one process or the other
