"""Optional extras: a feature whose extra is missing says which extra to install; the core alone
imports and runs the README's example.

A missing package is simulated by ``sys.modules[name] = None`` (what Python does for a blocked
import: ``ModuleNotFoundError`` naming the module), undone after each test.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import tobitkf as tk
from tobitkf._extras import EXTRAS, MissingExtraError, extra_of, install_command, missing_extra_message, require
from tobitkf.cli import app

ROOT = Path(__file__).resolve().parents[1]
# the install command names the folder of an install from a clone (the test venv's), else the index
ERR = r"optional extra '{}' is needed.*pip install (-e )?'[^' ]*\[{}\]'"


def block(monkeypatch, *modules: str) -> None:
    for name in modules:
        monkeypatch.setitem(sys.modules, name, None)


def test_require_names_the_extra_and_keeps_import_error(monkeypatch):
    block(monkeypatch, "cvxpy")
    with pytest.raises(MissingExtraError, match=ERR.format("lmi", "lmi")) as info:
        require("cvxpy", extra="lmi")
    assert isinstance(info.value, ImportError) and info.value.extra == "lmi" and info.value.module == "cvxpy"
    assert "cvxpy is not installed" in str(info.value)
    with pytest.raises(ValueError, match="unknown extra"):
        require("numpy", extra="nonsense")
    assert require("numpy", extra="plot") is np


def test_require_reports_a_broken_dependency_of_an_installed_package(monkeypatch, tmp_path):
    (tmp_path / "fakepkg_extras_test.py").write_text("import a_module_that_is_not_there_xyz\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(
        MissingExtraError, match=r"fakepkg_extras_test does not import .*a_module_that_is_not_there_xyz"
    ):
        require("fakepkg_extras_test", extra="plot")


def test_every_extra_is_declared_in_pyproject():
    import tomllib

    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert set(EXTRAS) | {"all", "test", "docs", "lint", "dev"} <= set(declared)
    assert declared["all"] == ["tobitkf[lmi,control,sweep,plot]"]
    assert any(d.startswith("tobitkf[all") for d in declared["test"])
    assert extra_of("matplotlib.pyplot") == "plot" and extra_of("zarr") == "sweep" and extra_of("numpy") is None


# --------------------------------------------------------------------------- lmi
def test_lmi_missing_is_named_by_hinf_design(monkeypatch):
    from tobitkf.models.ross import wang2010_model

    model = wang2010_model()
    block(monkeypatch, "cvxpy")
    with pytest.raises(MissingExtraError, match=ERR.format("lmi", "lmi")):
        tk.hinf_design(model)


def test_lmi_solver_missing_is_named_by_hinf_design(monkeypatch):
    from tobitkf.models.ross import wang2010_model

    block(monkeypatch, "clarabel")
    with pytest.raises(MissingExtraError, match="clarabel is not installed.*\\[lmi\\]'"):
        tk.hinf_design(wang2010_model())


def test_lmi_missing_is_named_by_the_stability_certificate(monkeypatch):
    block(monkeypatch, "cvxpy")
    with pytest.raises(MissingExtraError, match=ERR.format("lmi", "lmi")):
        tk.certify_tkf_stability([[1.0, 0.1], [0.0, 1.0]], [[0.5], [0.1]], [[1.0, 0.0]], grid=5)


# --------------------------------------------------------------------------- control
def test_control_missing_is_named_by_lqr(monkeypatch):
    block(monkeypatch, "control")
    with pytest.raises(MissingExtraError, match=ERR.format("control", "control")):
        tk.control.dlqr([[1.0]], [[1.0]], [[1.0]], [[1.0]])


# --------------------------------------------------------------------------- sweep
def test_sweep_missing_is_named_by_load_result(monkeypatch, tmp_path):
    from tobitkf.sweep import load_result

    block(monkeypatch, "zarr")
    with pytest.raises(MissingExtraError, match=ERR.format("sweep", "sweep")):
        load_result(tmp_path / "x.zarr")


def test_sweep_missing_is_named_by_the_command_line(monkeypatch, tmp_path):
    block(monkeypatch, "zarr")
    res = CliRunner().invoke(
        app, ["sweep", str(ROOT / "examples" / "sweeps" / "tkf_threshold.toml"), "--out", str(tmp_path)]
    )
    assert res.exit_code == 2
    assert install_command("sweep") in " ".join(res.output.split()) and "bug" not in res.output
    assert not list(tmp_path.iterdir())


def test_dask_scheduler_missing_is_named(monkeypatch):
    from tobitkf.sweep.run import _client

    block(monkeypatch, "distributed")
    with pytest.raises(MissingExtraError, match=ERR.format("sweep", "sweep")):
        _client("processes", 1)


# --------------------------------------------------------------------------- plot / report
def test_plot_missing_is_named_by_the_figure_helpers(monkeypatch):
    from tobitkf.plotting import new_figure

    block(monkeypatch, "matplotlib", "matplotlib.pyplot")
    with pytest.raises(MissingExtraError, match=ERR.format("plot", "plot")):
        new_figure()


def test_report_missing_is_named_by_reproduce_before_the_run(monkeypatch, tmp_path):
    block(monkeypatch, "matplotlib", "matplotlib.pyplot")
    res = CliRunner().invoke(app, ["reproduce", "miller-constant", "--runs", "2", "--out", str(tmp_path)])
    assert res.exit_code == 2
    assert install_command("report") in " ".join(res.output.split()) and "bug" not in res.output


def test_an_unwrapped_import_of_an_extra_is_still_named_on_the_command_line():
    exc = ModuleNotFoundError("No module named 'control'", name="control")
    assert install_command("control") in missing_extra_message(exc)
    assert missing_extra_message(ModuleNotFoundError("x", name="not_an_extra_module")) is None


# --------------------------------------------------------------------------- the core alone
CORE_ONLY = textwrap.dedent("""
    import sys
    for name in {blocked!r}:
        sys.modules[name] = None
    import numpy as np, tobitkf as tk

    sys_ = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[1e-14]], R=[[0.01]], x0=[0.1], P0=[[0.05]])
    truth = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[1e-14]], R=[[0.01]], x0=[-0.1], P0=[[0.0]])
    cens = tk.Censoring(lower=0.0)
    data = tk.simulate(truth, steps=200, runs=50, censoring=cens, seed=0)
    tkf = tk.TobitKalmanFilter(sys_, cens).filter(data.y)
    kf = tk.KalmanFilter(sys_).filter(data.y)
    assert abs(tkf.mean[:, -1].mean() + 0.1) < 0.02 and kf.mean[:, -1].mean() > -0.05
    print("ok", tk.__version__)
""")


def test_the_core_alone_imports_and_filters():
    blocked = sorted({m for mods, _ in EXTRAS.values() for m in mods} | {"matplotlib.pyplot"})
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    out = subprocess.run(
        [sys.executable, "-c", CORE_ONLY.format(blocked=blocked)], capture_output=True, text=True, env=env, timeout=300
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == f"ok {tk.__version__}"


def test_version_has_one_source():
    from tobitkf._version import __version__

    assert tk.__version__ == __version__
    res = CliRunner().invoke(app, ["--version"])
    assert res.exit_code == 0 and res.output.strip() == f"tobitkf {__version__}"


# --------------------------------------------------------------------------- the install command
def _dist(tmp_path, direct_url: dict | str | None):
    """An installed distribution of tobitkf in ``tmp_path`` with the given ``direct_url.json``."""
    import importlib.metadata
    import json

    info = tmp_path / "site" / "tobitkf-9.9.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: tobitkf\nVersion: 9.9\n")
    if direct_url is not None:
        text = direct_url if isinstance(direct_url, str) else json.dumps(direct_url)
        (info / "direct_url.json").write_text(text)
    return importlib.metadata.Distribution.at(info)


def test_install_command_names_the_clone_a_package_was_installed_from(tmp_path):
    clone = tmp_path / "my clone"  # a space: the command must quote the path
    clone.mkdir()
    plain = _dist(tmp_path / "a", {"url": clone.as_uri(), "dir_info": {}})
    assert install_command("plot", plain) == f"pip install '{clone}[plot]'"
    editable = _dist(tmp_path / "b", {"url": clone.as_uri(), "dir_info": {"editable": True}})
    assert install_command("lmi", editable) == f"pip install -e '{clone}[lmi]'"
    # the command is one a shell splits into pip's arguments: the path with the extra, unsplit
    import shlex

    assert shlex.split(install_command("lmi", editable)) == ["pip", "install", "-e", f"{clone}[lmi]"]


def test_install_command_for_an_index_a_vcs_url_and_a_vanished_folder(tmp_path):
    assert install_command("plot", _dist(tmp_path / "a", None)) == "pip install 'tobitkf[plot]'"
    assert install_command("plot", _dist(tmp_path / "b", "not json")) == "pip install 'tobitkf[plot]'"
    vcs = _dist(tmp_path / "c", {"url": "https://example.org/x/tobitkf.git", "vcs_info": {"vcs": "git"}})
    assert install_command("sweep", vcs) == "pip install 'tobitkf[sweep] @ git+https://example.org/x/tobitkf.git'"
    gone = tmp_path / "deleted-clone"
    cmd = install_command("plot", _dist(tmp_path / "d", {"url": gone.as_uri(), "dir_info": {}}))
    assert cmd.startswith(f"pip install '{gone}[plot]'") and "clone" in cmd and "gone" in cmd


def test_the_message_gives_the_command_for_this_installation(monkeypatch, tmp_path):
    import tobitkf._extras as extras

    clone = tmp_path / "clone"
    clone.mkdir()
    dist = _dist(tmp_path, {"url": clone.as_uri(), "dir_info": {}})
    monkeypatch.setattr(extras.importlib.metadata, "distribution", lambda name: dist)
    block(monkeypatch, "matplotlib", "matplotlib.pyplot")
    with pytest.raises(MissingExtraError) as info:
        require("matplotlib.pyplot", extra="plot")
    assert f"pip install '{clone}[plot]'" in str(info.value) and f"pip install '{clone}[all]'" in str(info.value)
    assert "'tobitkf[plot]'" not in str(info.value)
    exc = ModuleNotFoundError("No module named 'zarr'", name="zarr")
    assert f"pip install '{clone}[sweep]'" in (missing_extra_message(exc) or "")
