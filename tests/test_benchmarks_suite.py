"""The benchmark suite driver (benchmarks/run_all.py): every script listed, records written as documented."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def run_all():
    spec = importlib.util.spec_from_file_location("run_all", ROOT / "benchmarks" / "run_all.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_every_benchmark_script_is_in_the_suite(run_all):
    """CI runs the suite's --smoke form instead of a loop over the folder: a script left out would
    never run in CI."""
    on_disk = {p.name for p in (ROOT / "benchmarks").glob("bench_*.py")}
    listed = [script for _, script, *_ in run_all.SUITE]
    assert sorted(listed) == sorted(set(listed)), "a script listed twice"
    assert on_disk == set(listed)
    assert len({name for name, *_ in run_all.SUITE}) == len(run_all.SUITE)


def test_run_suite_records_output_exit_codes_and_load(run_all, tmp_path, monkeypatch):
    ok = tmp_path / "ok.py"
    ok.write_text("import sys\nprint('args', sys.argv[1:])\n")
    bad = tmp_path / "bad.py"
    bad.write_text("import sys\nprint('partial')\nsys.stderr.write('boom\\n')\nsys.exit(3)\n")
    monkeypatch.setattr(
        run_all,
        "SUITE",
        [("ok", str(ok), ["--x", "{out}/f"], True), ("bad", str(bad), [], True), ("skip", str(ok), [], False)],
    )
    out = tmp_path / "out"
    record = run_all.run_suite(["ok", "bad"], out, smoke=False)
    assert [e["name"] for e in record["scripts"]] == ["ok", "bad"]
    assert [e["returncode"] for e in record["scripts"]] == [0, 3]
    assert (out / "ok.txt").read_text().strip() == f"args ['--x', '{out}/f']"
    assert "boom" in (out / "bad.txt").read_text() and "partial" in (out / "bad.txt").read_text()
    saved = json.loads((out / "run.json").read_text())
    assert saved["scripts"] == record["scripts"]
    for e in saved["scripts"]:
        assert e["load_before"] >= 0 and e["load_after"] >= 0 and e["wall_s"] >= 0
    page = (out / "run.md").read_text()
    assert "## ok:" in page and "## bad:" in page and "partial" in page and "skip" not in page
    smoke = run_all.run_suite(["ok"], tmp_path / "smoke", smoke=True)
    assert (tmp_path / "smoke" / "ok.txt").read_text().strip() == "args ['--smoke']"
    assert smoke["smoke"] is True


def test_run_suite_records_user_and_system_time(run_all, tmp_path, monkeypatch):
    """A script that spins for CPU time shows it as user time, and the page shows the machine."""
    spin = tmp_path / "spin.py"
    spin.write_text("import time\nt = time.process_time()\nwhile time.process_time() - t < 0.5:\n    pass\n")
    monkeypatch.setattr(run_all, "SUITE", [("spin", str(spin), [], True)])
    record = run_all.run_suite(["spin"], tmp_path / "out", smoke=False)
    (e,) = record["scripts"]
    assert e["user_s"] + e["sys_s"] >= 0.4 and e["user_s"] <= e["wall_s"] + 0.2
    assert str(run_all.os.cpu_count()) in record["machine"]
    assert "| user s | system s |" in (tmp_path / "out" / "run.md").read_text()


def test_timing_measures_page_faults_and_cpu():
    """benchmarks/_timing.measure: fresh memory shows as minor faults (one per 4 KiB page with numpy's huge-page
    advice off), reused memory does not; a busy loop shows as user time."""
    import sys

    import numpy as np
    from numpy._core import multiarray

    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import _timing
    finally:
        sys.path.pop(0)
    nbytes = 64 << 20  # above the C library's largest mmap threshold: mapped fresh by every allocation
    advice = multiarray._get_madvise_hugepage()
    multiarray._set_madvise_hugepage(False)
    try:
        fresh, _ = _timing.measure(lambda: np.ones(nbytes // 8))
        buf = np.ones(nbytes // 8)
        reused, _ = _timing.measure(lambda: buf.fill(2.0))
    finally:
        multiarray._set_madvise_hugepage(advice)
    assert fresh.faults >= nbytes // 4096 // 2
    assert reused.faults < nbytes // 4096 // 10

    def spin():
        x = 0
        for i in range(2_000_000):
            x += i
        return x

    busy, out = _timing.measure(spin)
    assert out == sum(range(2_000_000)) and busy.cpu > 0 and busy.user > 0
    s = _timing.summary([busy, busy, fresh], scale=2.0)
    assert s.wall == 2.0 * busy.wall and s.wall_range == (
        2.0 * min(busy.wall, fresh.wall),
        2.0 * max(busy.wall, fresh.wall),
    )
