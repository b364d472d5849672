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
