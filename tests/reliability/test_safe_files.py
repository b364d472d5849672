"""Safe files (issue 9 item 5): sweep and config files are parsed as data (TOML), never
evaluated; output paths stay inside the chosen output directory."""

import builtins
import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import pytest  # noqa: E402

import tobitkf as tk  # noqa: E402
from tobitkf import _io, cli  # noqa: E402
from tobitkf.experiments import _REGISTRY, Experiment  # noqa: E402
from tobitkf.sweep import SweepFileError, parse_sweep, run_sweep  # noqa: E402
from tobitkf.sweep.spec import load_sweep  # noqa: E402

SWEEP = """
[sweep]
runs = 20
steps = 5
seed = 0
{extra}
[model]
A = {A}
C = [[1.0]]
Q = [[0.04]]
R = [[0.01]]
x0 = [0.0]
P0 = [[0.2]]

[censoring]
lower = 0.0

[estimators.tkf]
type = {etype}
{grid}
"""


def sweep_text(A="[[0.9]]", etype='"TobitKalmanFilter"', extra="", grid=""):
    return SWEEP.format(A=A, etype=etype, extra=extra, grid=grid)


MARKERS = ("PWNED", "os.system", "TobitKalmanFilter", "censoring.lower")


@pytest.fixture
def no_eval(monkeypatch):
    """eval/exec of any text taken from a sweep file fails the test."""
    for name in ("eval", "exec"):
        real = getattr(builtins, name)

        def refuse(source, *args, _real=real, **kwargs):
            text = source.decode(errors="replace") if isinstance(source, bytes) else source
            if isinstance(text, str) and any(m in text for m in MARKERS):  # sweep-file text turned into code
                raise AssertionError(f"sweep file text was evaluated: {text!r:.80}")
            return _real(source, *args, **kwargs)  # imports, namedtuple: not ours

        monkeypatch.setattr(builtins, name, refuse)


@pytest.mark.parametrize(
    "text, key",
    [
        (sweep_text(A="\"__import__('os').system('touch PWNED')\""), r"model\.A"),
        (sweep_text(etype='"os.system"'), r"estimators\.tkf\.type"),
        (sweep_text(etype='"__import__"'), r"estimators\.tkf\.type"),
        (sweep_text(grid="[grid]\n\"model.A\" = [\"open('PWNED', 'w')\"]"), r"grid\.model\.A"),
        (sweep_text(grid='[grid]\n"model.__class__" = [1]'), r"grid\.model\.__class__"),
        (sweep_text(grid='[grid]\n"estimators.tkf.__init__" = [1]'), r"grid\.estimators\.tkf\.__init__"),
    ],
)
def test_code_in_a_sweep_file_is_data_and_refused(tmp_path, monkeypatch, no_eval, text, key):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SweepFileError, match=key):
        parse_sweep(text)
    assert not (tmp_path / "PWNED").exists()


def test_a_valid_sweep_runs_without_evaluating_anything(tmp_path, no_eval):
    spec = parse_sweep(sweep_text(grid='[grid]\n"censoring.lower" = [-0.1, 0.1]'), name="ok")
    path = run_sweep(spec, tmp_path)
    assert path.parent == tmp_path.resolve() and path.name == "ok.zarr"


@pytest.mark.parametrize("name", ["../escape", "/tmp/escape", "..", ".hidden", "a/b", "a\\\\b", "", "a\\u0000b"])
def test_sweep_name_cannot_leave_the_output_directory(name):
    with pytest.raises(SweepFileError, match=r"sweep\.name"):
        parse_sweep(sweep_text(extra=f'name = "{name}"'))


def test_sweep_file_name_is_only_a_default_name(tmp_path):
    f = tmp_path / "in" / "my sweep.toml"
    f.parent.mkdir()
    f.write_text(sweep_text())
    spec = load_sweep(f)
    out = run_sweep(spec, tmp_path / "out")
    assert out == (tmp_path / "out" / "my sweep.zarr").resolve()


@pytest.mark.parametrize("name", ["../x", "a/../../x", "/etc/x"])
def test_safe_child_refuses_escaping_names(tmp_path, name):
    with pytest.raises(tk.ValidationError, match="would leave the output directory"):
        _io.safe_child(tmp_path, name)


def _plot(result, outdir):
    return []


def _run(*, runs, seed, progress=None):
    from tobitkf.experiments import ExperimentResult

    return ExperimentResult(id="x", settings={}, metrics={})


def test_experiment_id_cannot_write_outside_out(tmp_path, monkeypatch):
    evil = Experiment(id="../evil", title="t", source="s", run=_run, plot=_plot, default_runs=1, module=__name__)
    monkeypatch.setitem(_REGISTRY, "../evil", evil)
    out = tmp_path / "out"
    out.mkdir()
    with pytest.raises(tk.ValidationError, match="would leave the output directory"):
        cli.run_experiment("../evil", runs=1, seed=0, out=out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_symlinked_experiment_folder_pointing_outside_is_refused(tmp_path, monkeypatch):
    ok = Experiment(id="rel-link", title="t", source="s", run=_run, plot=_plot, default_runs=1, module=__name__)
    monkeypatch.setitem(_REGISTRY, "rel-link", ok)
    out, outside = tmp_path / "out", tmp_path / "outside"
    out.mkdir()
    outside.mkdir()
    (outside / "keep.txt").write_text("mine")
    os.symlink(outside, out / "rel-link")
    with pytest.raises(tk.ValidationError, match="would leave the output directory"):
        cli.run_experiment("rel-link", runs=1, seed=0, out=out)
    assert (outside / "keep.txt").read_text() == "mine" and sorted(p.name for p in outside.iterdir()) == ["keep.txt"]


def test_no_module_evaluates_text(tmp_path):
    """Static guard: the package source never calls eval/exec or unpickles files."""
    src = Path(tk.__file__).parent
    offenders = []
    for f in src.rglob("*.py"):
        text = f.read_text(encoding="utf-8")
        for bad in ("eval(", "exec(", "pickle.load", "yaml.load", "__import__("):
            for line in text.splitlines():
                code = line.split("#", 1)[0]
                if bad in code and "literal_eval" not in code and "np.exec" not in code:
                    offenders.append(f"{f.relative_to(src)}: {line.strip()}")
    assert not offenders, offenders


@pytest.mark.parametrize("command", [["reproduce", "miller-brownian", "--runs", "2"], ["sweep", "SWEEPFILE"]])
def test_out_that_is_a_file_is_refused_before_any_work(tmp_path, command):
    from typer.testing import CliRunner

    f = tmp_path / "sweep.toml"
    f.write_text(sweep_text())
    target = tmp_path / "not_a_dir"
    target.write_text("keep")
    args = [str(f) if a == "SWEEPFILE" else a for a in command] + ["--out", str(target)]
    res = CliRunner().invoke(cli.app, args)
    assert res.exit_code == 2 and "--out: expected a folder" in res.output
    assert target.read_text() == "keep"


def test_unknown_experiment_settings_are_refused_by_name(tmp_path):
    from tobitkf.sweep import parse_sweep as ps

    head = '[sweep]\nruns = 2\nseed = 0\nexperiment = "{exp}"\n'
    with pytest.raises(SweepFileError, match=r"settings\.bogus \(line 6\): unknown setting of miller-oscillator"):
        ps(head.format(exp="miller-oscillator") + "[settings]\nbogus = 1\n")
    with pytest.raises(SweepFileError, match=r"grid\.settings\.omegax"):
        ps(head.format(exp="miller-oscillator") + '[grid]\n"settings.omegax" = [1, 2]\n')
    # an experiment taking **overrides checks its own settings when run: a named error, not a TypeError
    spec = ps(head.format(exp="geng-protocol-window") + "[settings]\nbogus = 1\n")
    with pytest.raises(tk.ValidationError, match=r"^settings: .*bogus"):
        run_sweep(spec, tmp_path)
