"""The README as a newcomer reads it: its code runs as written, its set-up commands are the ones CI
runs, and what it says about installing and about estimators is what the package does."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text(encoding="utf-8")


def _blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", README, re.S)


def test_readme_python_runs_as_written(tmp_path, monkeypatch, capsys):
    import matplotlib

    matplotlib.use("Agg")
    monkeypatch.chdir(tmp_path)
    blocks = _blocks("python")
    assert len(blocks) >= 3  # the ten lines, the online loop, the own-data workflow
    namespace: dict = {"__name__": "readme"}
    for i, code in enumerate(blocks):
        exec(compile(code, f"README.md[python block {i}]", "exec"), namespace)  # noqa: S102 - our own README
    out = capsys.readouterr().out.splitlines()
    tkf_mean, kf_mean = (float(v) for v in out[0].split())
    assert abs(tkf_mean + 0.098) < 0.002 and abs(kf_mean - 0.0083) < 0.001  # what the comment says
    assert out[1] == "(500, 1) (500, 1, 1) 1000"
    assert (tmp_path / "phosphorus_ar1.json").is_file()


def test_readme_fit_command_runs_on_the_shipped_csv(tmp_path):
    (model,) = _blocks("toml")
    (tmp_path / "model.toml").write_text(model, encoding="utf-8")
    command = next(c for c in _blocks("bash") if c.startswith("tobitkf fit "))
    args = command.split()[2:]
    assert args[0] == "src/tobitkf/data/phosphorus.csv" and (ROOT / args[0]).is_file()
    res = subprocess.run(
        [sys.executable, "-m", "tobitkf", "fit", str(ROOT / args[0]), *args[1:]],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        env={**__import__("os").environ, "PYTHONPATH": str(ROOT / "src")},
        timeout=600,
    )
    assert res.returncode == 0, res.stdout + res.stderr
    summary = (tmp_path / "fit" / "summary.txt").read_text(encoding="utf-8")
    assert "converged" in summary and re.search(r"beta1\s+0\.425", summary)
    assert (tmp_path / "fit" / "series.csv").is_file() and (tmp_path / "fit" / "fit.json").is_file()


def test_readme_set_up_commands_are_the_two_that_ci_runs():
    commands = [c.strip() for c in _blocks("bash") if c.startswith("python3 -m venv")]
    assert len(commands) == 2
    install, tests = commands
    assert install.endswith('python -m pip install ".[all]" && tobitkf warmup && tobitkf reproduce all')
    test_command = tests.split(" && ", 2)[2]
    assert test_command == 'python -m pip install ".[test]" && python -m pytest -n 2 -q'
    assert test_command in (ROOT / ".ci" / "run").read_text(encoding="utf-8")


def test_readme_says_how_to_install_and_names_every_extra():
    import tomllib

    assert "`pip install tobitkf` fails" in README and "clone" in README
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]["optional-dependencies"]
    for extra in set(declared) - {"bench"}:
        assert f"`[{extra}]`" in README, extra


def test_readme_names_only_public_estimators_and_never_recommends_total_variance_bare():
    import tobitkf as tk

    for name in re.findall(r"`tk\.([A-Za-z_]+)", README):
        assert hasattr(tk, name), name
    # never without its known limit: in the same table row, or the same paragraph of text
    for para in README.split("\n\n"):
        units = para.splitlines() if para.lstrip().startswith("|") else [para]
        for unit in units:
            if "total-variance" in unit or "total_variance" in unit:
                assert "diverge" in unit, unit


@pytest.mark.parametrize("page", ["tutorials/performance.md", "tutorials/optimum.md", "sources/index.md"])
def test_readme_links_to_docs_pages_that_exist(page):
    assert f"docs/{page}" in README and (ROOT / "docs" / page).is_file()
