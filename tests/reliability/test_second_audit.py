"""Second reliability audit (issue 15): one test per defect class the first audit missed.

Each class is fixed at a boundary shared by every entry point (``_validation.as_float_array``,
``check_option``, ``check_memory``, the CLI's error wrapper, ``_io.check_replaceable``, the sweep
and report readers); the tests try several variants of each class, not only the issue's example.
Every test here failed before the fixes (the class it names was the defect).
"""

from __future__ import annotations

import json
import shutil
import socket
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from typer.testing import CliRunner  # noqa: E402

import tobitkf as tk  # noqa: E402
from tobitkf import ShapeError, ValidationError, cli  # noqa: E402
from tobitkf._validation import check_option  # noqa: E402
from tobitkf.channels.laws import Gaussian  # noqa: E402
from tobitkf.channels.protocol import ProtocolChannel, RoundRobin  # noqa: E402
from tobitkf.channels.saturation import RandomSaturation  # noqa: E402
from tobitkf.control import dlqr, simulate_closed_loop  # noqa: E402
from tobitkf.experiments import _REGISTRY, Experiment, ExperimentResult  # noqa: E402
from tobitkf.filters.delay_chain import chain_lmmse  # noqa: E402
from tobitkf.filters.tracking import MultiTargetTracker  # noqa: E402
from tobitkf.models.delay import DelayFadingSystem, FadingMoments, HistoryPrior, paper_prior  # noqa: E402
from tobitkf.models.ross import wang2010_model  # noqa: E402
from tobitkf.simulate.delay import simulate_delay  # noqa: E402
from tobitkf.simulate.ross import simulate_ross  # noqa: E402
from tobitkf.sweep import SweepFileError, load_result, parse_sweep, run_sweep  # noqa: E402
from tobitkf.sweep.spec import load_sweep  # noqa: E402

from ._guards import no_hang  # noqa: E402

GOOD = dict(A=[[0.9]], C=[[1.0]], Q=[[0.01]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
SYS = tk.LinearSystem(**GOOD)
CA, CB = np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[0.0], [0.1]])
PLANT = tk.LinearSystem(A=CA, C=[[1.0, 0.0]], Q=0.01 * np.eye(2), R=[[0.1]], x0=[1.0, 0.0], P0=0.1 * np.eye(2), Bu=CB)
DELAY = dict(A=[[0.4, 0.7], [0.2, 0.6]], H=[[0.5, 1.0]], Gamma=[[1.0], [1.0]], Qw=0.3, Qv=0.3, S=0.3, d=3)
LIMIT = 10**11  # bytes; TOBITKF_MEMORY_LIMIT for the size tests, so they do not depend on the machine

SWEEP = """[sweep]
runs = {runs}
steps = {steps}
seed = 0
{extra}
[model]
A = {A}
C = [[1.0]]
Q = [[0.04]]
R = {R}
x0 = [0.0]
P0 = [[0.2]]

[censoring]
lower = 0.0

[estimators.tkf]
type = "TobitKalmanFilter"
{tail}"""


def sweep_text(runs=20, steps=5, extra="", A="[[0.9]]", R="[[0.01]]", tail=""):
    return SWEEP.format(runs=runs, steps=steps, extra=extra, A=A, R=R, tail=tail)


def invoke(args):
    return CliRunner().invoke(cli.app, [str(a) for a in args])


def assert_one_line_error(res, pattern: str):
    """Exit code 2, no traceback, and exactly one output line: ``error: ...`` matching ``pattern``."""
    import re

    assert res.exit_code == 2, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1, res.output
    assert lines[0].startswith("error: ") and re.search(pattern, lines[0]), lines[0]
    assert "Traceback" not in res.output


@pytest.fixture
def fake_experiment(monkeypatch):
    """A registered experiment that records whether it ran (and runs in no time)."""
    calls = []

    def run(*, runs, seed, progress=None):
        calls.append((runs, seed))
        return ExperimentResult(id="rel-fake", settings={}, metrics={})

    exp = Experiment(
        id="rel-fake", title="t", source="s", run=run, plot=lambda r, d: [], default_runs=1, module=__name__
    )
    monkeypatch.setitem(_REGISTRY, "rel-fake", exp)
    return calls


# ---------------------------------------------------------------------------------------------
# silent wrong answers
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "call, pattern",
    [
        (lambda: tk.Censoring(lower="0.5"), r"^lower: expected an array of numbers, got str"),
        (lambda: tk.Censoring(lower=True), r"^lower: .*bool"),
        (lambda: tk.Censoring(upper=[1.0, True]), r"^upper: .*bool"),
        (lambda: tk.LinearSystem(**{**GOOD, "A": [[True]]}), r"^A: .*bool"),
        (lambda: tk.LinearSystem(**{**GOOD, "A": np.array([[True]])}), r"^A: .*booleans"),
        (lambda: tk.LinearSystem(**{**GOOD, "R": [["1.0"]]}), r"^R: .*str"),
        (lambda: tk.LinearSystem(**{**GOOD, "x0": np.array(["0"])}), r"^x0: .*text"),
        (lambda: tk.LinearSystem(**{**GOOD, "A": [[10**400]]}), r"^A: expected an array of numbers"),
        (lambda: Gaussian("1", 0.0), r"^mean: .*str"),
        (lambda: RandomSaturation(True, 0.5), r"^mu: .*bool"),
        (lambda: tk.KalmanFilter(SYS).filter(np.array([[True], [False]])), r"^y: .*booleans"),
    ],
)
def test_text_and_booleans_are_not_numbers(call, pattern):
    import pandas as pd

    with pytest.raises(ValidationError, match=pattern):
        call()
    # integers, integer arrays and pandas numbers stay accepted
    sys_ = tk.LinearSystem(A=[[1]], C=np.array([[1]]), Q=[[1]], R=pd.DataFrame([[2]]), x0=pd.Series([0]), P0=[[1]])
    assert sys_.A.array.dtype == np.float64 and float(sys_.R.array[0, 0]) == 2.0


def test_booleans_in_a_sweep_file_are_not_numbers():
    with pytest.raises(SweepFileError, match=r"model\.A \(line \d+\): A: .*bool"):
        parse_sweep(sweep_text(A="[[true]]"))
    with pytest.raises(SweepFileError, match=r"censoring .*lower: .*bool"):
        parse_sweep(sweep_text().replace("lower = 0.0", "lower = false"))


@pytest.mark.parametrize(
    "call, pattern",
    [
        (
            lambda: tk.FadingTobitKalmanFilter(
                SYS, tk.RiceFading.gaussian(0, [1.0]), tk.Censoring(lower=0.0), fading_variance_term=1.0
            ),
            r"^fading_variance_term: expected one of",
        ),
        (
            lambda: tk.FadingKalmanFilter(SYS, tk.RiceFading.gaussian(0, [1.0]), fading_variance_term=0),
            r"^fading_variance_term",
        ),
        (lambda: check_option(True, "theorem", (1, 2)), r"^theorem: expected one of 1, 2, got True"),
        (lambda: check_option(2.0, "theorem", (1, 2)), r"^theorem: expected one of 1, 2, got 2\.0"),
        (lambda: tk.hinf_analyze(wang2010_model(), np.zeros((3, 3)), np.zeros((3, 2)), theorem=True), r"^theorem"),
    ],
)
def test_options_match_by_kind_not_by_equality(call, pattern):
    with pytest.raises(ValidationError, match=pattern):
        call()


@pytest.mark.parametrize(
    "value, pattern",
    [
        (lambda k: [[0.9 + (1j if k > 0 else 0)]], r"^A\(1\): expected real numbers"),
        (lambda k: [[0.9]] if k == 0 else [["a"]], r"^A\(1\): expected an array of numbers, got str"),
        (lambda k: [[0.9]] if k < 2 else [[True]], r"^A\(2\): .*bool"),
    ],
)
def test_callable_turning_complex_or_text_later_is_refused_naming_k(value, pattern):
    sys_ = None
    with pytest.raises(ValidationError, match=pattern):
        sys_ = tk.LinearSystem(**{**GOOD, "A": value})
        tk.simulate(sys_, 4, 2)
    if sys_ is not None:  # built (k = 0 was fine): the filter refuses it as well
        with pytest.raises(ValidationError, match=pattern):
            tk.KalmanFilter(sys_).filter(np.zeros((4, 1)))


@pytest.mark.parametrize(
    "kwargs, pattern",
    [
        (dict(mu=np.nan), r"^mu: expected finite"),
        (dict(mu=np.inf), r"^mu: expected finite"),
        (dict(mu="0"), r"^mu: .*str"),
        (dict(gate0=np.nan), r"^gate0"),
        (dict(gate0=np.inf), r"^gate0"),
        (dict(gate0="10"), r"^gate0: .*str"),
        (dict(gate0=True), r"^gate0: .*bool"),
        (dict(gate_slope=np.nan), r"^gate_slope"),
        (dict(gate_slope="2"), r"^gate_slope"),
        (dict(warmup=2.5), r"^warmup: expected an integer"),
        (dict(warmup=np.nan), r"^warmup"),
        (dict(warmup=True), r"^warmup"),
        (dict(warmup="5"), r"^warmup"),
        (dict(gate=1.0), r"^gate: expected True or False"),
        (dict(gate="yes"), r"^gate: expected True or False"),
    ],
)
def test_tracker_checks_every_number_and_flag(kwargs, pattern):
    with pytest.raises(ValidationError, match=pattern):
        MultiTargetTracker(**kwargs)


@pytest.mark.parametrize(
    "kwargs, frames, error, pattern",
    [
        (dict(gate=False), [[[np.nan, 0.0]]], ValidationError, r"^detections\[0\]: expected finite numbers, found NaN"),
        ({}, [np.zeros((0, 2)), [[np.inf, 1.0]]], ValidationError, r"^detections\[1\]: .*inf"),
        ({}, [np.zeros((1, 4))], ShapeError, r"^detections\[0\]: expected \(L, 2\) points"),
        ({}, [np.zeros(3)], ShapeError, r"^detections\[0\]: expected \(L, 2\)"),
        ({}, [[["a", "b"]]], ValidationError, r"^detections\[0\]: .*str"),
        ({}, "frames", ValidationError, r"^detections: expected a sequence"),
    ],
)
def test_tracker_checks_every_detection_frame(kwargs, frames, error, pattern):
    with pytest.raises(error, match=pattern):
        MultiTargetTracker(**kwargs).track([[0.0, 0.0], [5.0, 5.0]], frames)
    # a (2,) frame is one point, an empty frame none
    res = MultiTargetTracker().track([[0.0, 0.0]], [[1.0, 1.0], []])
    assert res.assignment.tolist() == [[0], [-1]]


@pytest.mark.parametrize(
    "mean, cov, error, pattern",
    [
        (np.array([[np.nan]]), np.eye(1), ValidationError, r"^mean: expected finite numbers, found NaN"),
        (np.array([[np.inf, 0.0]]), np.eye(2), ValidationError, r"^mean: .*inf"),
        (np.zeros((1, 1)), -np.eye(1), ValidationError, r"^cov: expected a positive semi-definite"),
        (np.zeros((1, 2)), np.array([[1.0, 2.0], [0.0, 1.0]]), ValidationError, r"^cov: expected a symmetric"),
        (np.zeros((2, 1)), np.eye(1), ShapeError, r"^cov: expected shape \(2, 2\)"),
        (np.zeros(2), np.eye(2), ShapeError, r"^mean: expected 2 dimension"),
        ("x", np.eye(1), ValidationError, r"^mean: .*str"),
    ],
)
def test_history_prior_built_directly_is_checked(mean, cov, error, pattern):
    with pytest.raises(error, match=pattern):
        HistoryPrior(mean, cov)
    prior = HistoryPrior([[0.0], [1.0]], [[1.0, 0.0], [0.0, 1.0]])  # lists: converted
    assert prior.n == 1 and prior.d == 1


@pytest.mark.parametrize(
    "kwargs, pattern",
    [
        (
            dict(A_mult=[[[0.1, 0.2], [0.2, -0.1]]], q_mult=lambda t: [0.16] if t < 3 else [np.nan]),
            r"^q_mult\(3\): expected finite",
        ),
        (dict(A_mult=[[[0.1, 0.2], [0.2, -0.1]]], q_mult=lambda t: [0.16] if t < 2 else ["x"]), r"^q_mult\(2\): .*str"),
        (dict(fading=FadingMoments(lambda t: 0.9 if t < 3 else np.nan, 0.01)), r"^mean\(3\): expected finite"),
        (dict(fading=FadingMoments(0.9, lambda t: 0.01 if t < 4 else np.inf)), r"^variance\(4\): .*inf"),
        (
            dict(fading=lambda t: Gaussian(0.9 if t < 2 else np.nan, 0.0) if t < 2 else _NanLaw()),
            r"^fading\(2\)\.(mean|sample): expected finite",
        ),
    ],
)
def test_delay_model_callables_are_checked_at_every_t(kwargs, pattern):
    system = DelayFadingSystem(**DELAY, **kwargs)
    with pytest.raises(ValidationError, match=pattern):
        chain_lmmse(system, paper_prior(), np.zeros((10, 1)))
    with pytest.raises(ValidationError, match=pattern):
        simulate_delay(system, paper_prior(), 10, 2, seed=0)


class _NanLaw:
    mean, variance = float("nan"), 0.0

    @staticmethod
    def sample(rng, shape):
        return np.full(shape, np.nan)


@pytest.mark.parametrize(
    "args, pattern",
    [
        ((np.nan, 1.0, 0.0, np.inf), r"^mean: expected finite numbers, found NaN"),
        ((np.inf, 1.0, 0.0, np.inf), r"^mean: expected finite numbers, found inf"),
        (([0.0, -np.inf], 1.0, 0.0, np.inf), r"^mean: .*inf"),
        ((0.0, np.inf, 0.0, np.inf), r"^std: expected finite"),
        (("a", 1.0, 0.0, np.inf), r"^mean: expected an array of numbers, got str"),
        ((0.0, True, 0.0, np.inf), r"^std: .*bool"),
        ((0.0, 1.0, np.nan, np.inf), r"^lower: expected finite numbers, found NaN"),
        (([0.0, 1.0], 1.0, [0.0, 1.0, 2.0], np.inf), r"^mean/std/lower/upper: shapes"),
    ],
)
def test_censored_moments_refuses_non_finite_and_text(args, pattern):
    with pytest.raises(ValidationError, match=pattern):
        tk.censored_moments(*args)


def test_nees_refuses_indefinite_covariances():
    truth, est = np.zeros((2, 3, 1)), np.ones((2, 3, 1))
    cov = np.ones((2, 3, 1, 1))
    cov[1, 2] = -1.0
    with pytest.raises(ValidationError, match=r"^cov: .*index \(1, 2\) is indefinite"):
        tk.metrics.nees(truth, est, cov)
    with pytest.raises(ValidationError, match=r"^cov: .*not symmetric"):
        tk.metrics.nees(np.zeros((1, 2, 2)), np.ones((1, 1, 2)), np.array([[[[1.0, 0.5], [0.0, 1.0]]]]))
    assert np.all(tk.metrics.nees(truth, est, np.ones((2, 3, 1, 1))) == 1.0)


@pytest.mark.parametrize("key", ["R", "Q", "P0"])
def test_subnormal_variances_are_refused(key):
    with pytest.raises(ValidationError, match=rf"^{key}: expected variances of 0 or at least"):
        tk.LinearSystem(**{**GOOD, key: [[1e-320]]})
    tk.LinearSystem(**{**GOOD, key: [[0.0]]} if key != "R" else GOOD)  # an exact 0 stays a valid variance


def test_subnormal_noise_in_a_sweep_file_is_refused():
    with pytest.raises(SweepFileError, match=r"model\.R .*expected variances of 0 or at least"):
        parse_sweep(sweep_text(R="[[1e-320]]"))


def test_a_store_of_another_package_version_is_not_resumed(tmp_path):
    import zarr

    spec = parse_sweep(sweep_text(runs=40, extra="block_runs = 10\nchunk_blocks = 1"), name="v")
    path = run_sweep(spec, tmp_path, max_tasks=1)  # partial: 1 of 4 blocks
    zarr.open_group(str(path), mode="a").attrs["package_version"] = "0.0.0-other"
    with pytest.raises(ValidationError, match=r"^--out: .* was written by tobitkf '0\.0\.0-other'"):
        run_sweep(spec, tmp_path)
    assert int(zarr.open_group(str(path), mode="r")["done"][:].sum()) == 1  # nothing mixed in
    assert_one_line_error(
        invoke(["sweep", _write(tmp_path / "v.toml", spec.text), "--out", tmp_path]), r"written by tobitkf"
    )


def _write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


class _Post:
    def __init__(self, out):
        self.out = out

    def apply(self, rng, y, extras):
        return self.out(y)


@pytest.mark.parametrize(
    "out, error, pattern",
    [
        (lambda y: y[0], ShapeError, r"^post\[0\]: apply\(\) returned shape \(5, 1\), expected \(2, 5, channels\)"),
        (lambda y: y[:, :3], ShapeError, r"^post\[0\]: apply\(\) returned shape \(2, 3, 1\)"),
        (lambda y: np.full(y.shape, "x"), ValidationError, r"^post\[0\]: apply\(\): .*text"),
        (lambda y: y + 1j, ValidationError, r"^post\[0\]: apply\(\): expected real numbers"),
        (lambda y: None, ValidationError, r"^post\[0\]: apply\(\)"),
    ],
)
def test_what_a_simulate_hook_returns_is_checked(out, error, pattern):
    with pytest.raises(error, match=pattern):
        tk.simulate(SYS, 5, 2, post=[_Post(out)])
    # a hook that drops readings (NaN) stays fine
    data = tk.simulate(SYS, 5, 2, post=[_Post(lambda y: np.where(y > 0, np.nan, y))])
    assert data.y.shape == (2, 5, 1)


def test_closed_loop_nan_noise_is_named_not_a_shape_error():
    K = dlqr(CA, CB, np.eye(2), [[1.0]]).gain
    noise = {"x0": np.zeros((1, 2)), "w": np.full((1, 3, 2), np.nan), "v": np.zeros((1, 3, 1))}
    with pytest.raises(ValidationError, match=r"^noise\['w'\]: expected finite numbers, found NaN") as info:
        simulate_closed_loop(PLANT, K, 3, 1, observer="kf", noise=noise)
    assert not isinstance(info.value, ShapeError)


# ---------------------------------------------------------------------------------------------
# sizes that cannot fit: refused before anything is allocated, naming the size
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "call, pattern",
    [
        (lambda: tk.simulate(SYS, 10, 10**18), r"^runs/steps: 1000000000000000000 runs x 10 steps .* would need"),
        (lambda: tk.simulate(SYS, 10**12, 1), r"^runs/steps: 1 run x 1000000000000 steps"),
        (lambda: tk.simulate(SYS, 10**400, 1), r"^runs/steps: .*would need about 10\^"),
        (lambda: simulate_delay(DelayFadingSystem(**DELAY), paper_prior(), 10**12, seed=0), r"^runs/steps"),
        (lambda: simulate_ross(wang2010_model(), 10, 10**15, seed=0), r"^runs/steps"),
        (lambda: simulate_closed_loop(PLANT, np.zeros((1, 2)), 10**12, observer="kf"), r"^runs/steps"),
        (lambda: ProtocolChannel(2, window=10**6), r"^window: an integral window of 1000000 steps .* would need"),
        (lambda: RoundRobin(10**15), r"^sensors: "),
        (lambda: paper_prior(d=10**7), r"^d: a history of"),
        (lambda: tk.certify_tkf_stability(CA, [[0.5], [0.1]], [[1.0, 0.0]], grid=10**15, domain="dt"), r"^grid: "),
    ],
)
def test_sizes_that_cannot_fit_are_refused_before_allocating(monkeypatch, call, pattern):
    monkeypatch.setenv("TOBITKF_MEMORY_LIMIT", str(LIMIT))
    with no_hang(), pytest.raises(ValidationError, match=pattern):
        call()


@pytest.mark.parametrize(
    "runs, steps, key",
    [(10**18, 5, r"sweep\.runs"), (20, 10**9, r"sweep\.steps"), (10**12, 10**4, r"sweep\.(runs|steps)")],
)
def test_sweep_sizes_that_cannot_fit_are_refused_on_load_and_leave_no_store(tmp_path, monkeypatch, runs, steps, key):
    monkeypatch.setenv("TOBITKF_MEMORY_LIMIT", str(LIMIT))
    with no_hang(), pytest.raises(SweepFileError, match=rf"^sweep file: {key}.* would need"):
        parse_sweep(sweep_text(runs=runs, steps=steps))
    f = _write(tmp_path / "big.toml", sweep_text(runs=runs, steps=steps))
    with no_hang():
        assert_one_line_error(invoke(["sweep", f, "--out", tmp_path / "out"]), key)
    assert not (tmp_path / "out").exists()


def test_reproduce_with_runs_that_cannot_fit_is_one_line(tmp_path, monkeypatch):
    monkeypatch.setenv("TOBITKF_MEMORY_LIMIT", str(LIMIT))
    for exp_id in ("miller-brownian", "miller-robot", "miller-tracker"):
        with no_hang():
            assert_one_line_error(
                invoke(["reproduce", exp_id, "--runs", 10**12, "--out", tmp_path]), r"runs.* would need"
            )
    assert not any(p.name.startswith("miller") for p in tmp_path.iterdir())


def test_grid_with_too_many_points_is_refused_without_building_them():
    many = ", ".join(str(0.001 * i) for i in range(1000))
    text = sweep_text(
        tail=f'[estimators.kf]\ntype = "KalmanFilter"\n[grid]\n"censoring.lower" = [{many}]\n'
        f'"model.Q" = [{", ".join(f"[[{0.01 + 0.001 * i}]]" for i in range(1000))}]\n'
    )
    with no_hang(), pytest.raises(SweepFileError, match=r"^sweep file: grid .*1000000 grid points, more than the"):
        parse_sweep(text)


# ---------------------------------------------------------------------------------------------
# wrong types and options: named errors, not AttributeError/TypeError from inside
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "kwargs, pattern",
    [
        (dict(gamma="1.5"), r"^gamma: expected a positive number"),
        (dict(gamma=True), r"^gamma"),
        (dict(objective="min_gamma", gamma="x"), r"^gamma"),
        (dict(retries=-1), r"^retries: expected an integer >= 0"),
        (dict(retries=1.5), r"^retries"),
        (dict(iterations=2.5, method="iterate"), r"^iterations: expected an integer"),
        (dict(iterations=-1, method="iterate"), r"^iterations"),
        (dict(iterations="4"), r"^iterations"),
        (dict(bound=np.nan), r"^bound: expected finite"),
        (dict(bound=-1.0), r"^bound"),
        (dict(bound="1e4"), r"^bound"),
        (dict(tol=np.nan, method="iterate"), r"^tol"),
        (dict(tol=-1.0), r"^tol"),
        (dict(margin="1e-6"), r"^margin"),
        (dict(margin=np.inf), r"^margin"),
        (dict(fixed_Q="ab"), r"^fixed_Q: expected a pair"),
    ],
)
def test_hinf_design_numeric_options_are_checked(kwargs, pattern):
    with no_hang(60), pytest.raises(ValidationError, match=pattern):
        tk.hinf_design(wang2010_model(), **kwargs)


@pytest.mark.parametrize(
    "call, pattern",
    [
        (lambda m: tk.hinf_design("model"), r"^model: expected a RossModel, got str"),
        (lambda m: tk.hinf_analyze(None, np.zeros((3, 3)), np.zeros((3, 2))), r"^model: expected a RossModel"),
        (lambda m: tk.hinf_analyze(m, np.zeros((3, 3)), np.zeros((3, 2)), margin=np.nan), r"^margin"),
        (lambda m: tk.hinf_analyze(m, np.zeros((3, 3)), np.zeros((3, 2)), P=np.eye(6), rho="0.2"), r"^rho"),
        (
            lambda m: tk.hinf_verify(m, np.zeros((3, 3)), np.zeros((3, 2)), np.eye(6), [0.5, 0.5], "1", 1.0, 1.5),
            r"^eps1",
        ),
        (
            lambda m: tk.hinf_verify(
                m, np.zeros((3, 3)), np.zeros((3, 2)), np.eye(6), [0.5, 0.5], 1.0, 1.0, 1.5, block_diagonal=1
            ),
            r"^block_diagonal",
        ),
        (lambda m: tk.multi_region("abc", [[(0.0, 1.0)]]), r"^system: expected a LinearSystem, got str"),
        (lambda m: tk.multi_region(SYS, "abc"), r"^regions: expected one sequence"),
        (lambda m: tk.multi_region(SYS, [[("a", 1.0)]]), r"^regions\[0\]\[0\]\[0\]: .*str"),
        (lambda m: tk.multi_region(SYS, [[(0.0, 1.0)]], noise_var=[["x"]]), r"^noise_var\[0\]\[0\]"),
        (lambda m: RoundRobin(2, order=5), r"^order: expected a non-empty sequence"),
        (lambda m: tk.simulate(SYS, 3, 1, seed=True), r"^seed: expected an int"),
        (lambda m: tk.write_report(123), r"^results_dir: expected a path"),
        (lambda m: tk.write_report("a\x00b"), r"^results_dir: a path cannot contain a NUL"),
        (lambda m: load_sweep(None), r"^sweep file: expected a path"),
        (lambda m: load_result(1), r"^result: expected a path"),
        (lambda m: run_sweep("spec", "out"), r"^spec: expected a SweepSpec"),
        (lambda m: parse_sweep(b"[sweep]"), r"^sweep file: expected the text"),
    ],
)
def test_wrong_types_are_named(call, pattern):
    with pytest.raises(ValidationError, match=pattern):
        call(wang2010_model())


def test_control_helpers_check_their_numbers():
    from tobitkf.control.panning import constant_velocity, keep_in_view_limit
    from tobitkf.control.plants import dc_motor_speed
    from tobitkf.control.robot import robot_setup, simulate_robot

    for call, pattern in [
        (lambda: robot_setup(dt="0.1"), r"^dt: .*str"),
        (lambda: robot_setup(mass=True), r"^mass"),
        (lambda: simulate_robot(robot_setup(), radius="27", steps=3), r"^radius"),
        (lambda: simulate_robot(robot_setup(), steps=2.5), r"^steps"),
        (lambda: constant_velocity("1", 0.1, 1.0), r"^dt"),
        (lambda: constant_velocity(1.0, 0.1, [1.0, 2.0]), r"^sigma_r"),
        (lambda: keep_in_view_limit([0.0], [1.0], 10.0, width=np.nan), r"^width"),
        (lambda: dc_motor_speed(k="x"), r"^k: "),
        (lambda: dc_motor_speed(k=np.inf), r"^k: "),
        (
            lambda: simulate_closed_loop(PLANT, np.zeros((1, 2)), 3, observer="kf", divergence_bound=True),
            r"^divergence_bound",
        ),
        (
            lambda: simulate_closed_loop(PLANT, np.zeros((1, 2)), 3, observer="sstkf", xi_uncensored=[0.5, 0.5]),
            r"^xi_uncensored",
        ),
    ]:
        with pytest.raises(ValidationError, match=pattern):
            call()


def test_a_closed_scheduler_port_is_refused_at_once(tmp_path):
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    sock.close()  # nothing listens there now
    spec = parse_sweep(sweep_text(), name="s")
    with pytest.raises(ValidationError, match=rf"^--scheduler: connection refused at 127\.0\.0\.1:{port}"):
        run_sweep(spec, tmp_path, scheduler=f"tcp://127.0.0.1:{port}")
    assert not (tmp_path / "s.zarr").exists()


# ---------------------------------------------------------------------------------------------
# the command line: exit 2 and one line, never a traceback, nothing done first
# ---------------------------------------------------------------------------------------------
def test_reproduce_refuses_bad_seed_and_unusable_out_before_running(tmp_path, fake_experiment):
    a_file = _write(tmp_path / "a_file", "keep")
    cases = [
        (["--seed", "-1", "--out", tmp_path / "o"], r"^error: --seed: expected an integer >= 0, got -1"),
        (["--seed", "abc", "--out", tmp_path / "o"], r"--seed"),
        (["--runs", "0", "--out", tmp_path / "o"], r"--runs"),
        (["--out", a_file / "sub"], r"^error: --out: .*a_file/sub cannot be created: .*a_file is a file"),
        (["--out", a_file], r"^error: --out: expected a folder"),
        (["--out", tmp_path / ("x" * 300)], r"^error: --out: the folder name .* 300 bytes long"),
        (["--bogus"], r"No such option"),
    ]
    for extra, pattern in cases:
        assert_one_line_error(invoke(["reproduce", "rel-fake", *extra]), pattern)
    assert fake_experiment == [] and a_file.read_text() == "keep" and not (tmp_path / "o").exists()


def test_an_unexpected_error_is_one_line_too(tmp_path, monkeypatch):
    def broken(*, runs, seed, progress=None):
        raise RuntimeError("something inside broke\nover two lines")

    monkeypatch.setitem(
        _REGISTRY,
        "rel-broken",
        Experiment(
            id="rel-broken", title="t", source="s", run=broken, plot=lambda r, d: [], default_runs=1, module=__name__
        ),
    )
    assert_one_line_error(
        invoke(["reproduce", "rel-broken", "--out", tmp_path]),
        r"^error: unexpected RuntimeError: something inside broke over two lines",
    )


@pytest.mark.parametrize(
    "make, pattern",
    [
        (
            lambda d: d.joinpath("f.toml").write_bytes(sweep_text().encode() + b"\n# \xff\xfe\n") and d / "f.toml",
            r"^error: sweep file: .*f\.toml is not UTF-8 text \(byte 0xff on line \d+\)",
        ),
        (lambda d: _write(d / "f.toml", sweep_text(A="[" * 3000 + "]" * 3000)), r"nested too deeply"),
        (lambda d: _write(d / "f.toml", sweep_text(A="[" * 40 + "0.9" + "]" * 40)), r"nested more than 16 levels"),
        (
            lambda d: _write(d / "f.toml", sweep_text(extra='name = "' + "a" * 300 + '"')),
            r"sweep\.name \(line \d+\): expected a name of at most 200 bytes",
        ),
        (lambda d: _write(d / "f.toml", sweep_text(runs=10**30)), r"sweep\.runs"),
        (lambda d: d, r"^error: sweep file: .* is a folder"),
        (lambda d: d / "missing.toml", r"^error: sweep file: cannot read"),
    ],
)
def test_sweep_files_that_cannot_be_read_are_one_line(tmp_path, make, pattern):
    with no_hang():
        assert_one_line_error(invoke(["sweep", make(tmp_path), "--out", tmp_path / "out"]), pattern)
    assert not (tmp_path / "out").exists()


def test_sweep_outputs_that_cannot_be_written_are_refused_before_any_work(tmp_path):
    f = _write(tmp_path / "s.toml", sweep_text())
    a_file = _write(tmp_path / "a_file", "keep")
    assert_one_line_error(invoke(["sweep", f, "--out", a_file / "sub"]), r"a_file is a file, not a folder")
    (tmp_path / "o").mkdir()
    _write(tmp_path / "o" / "s.zarr", "mine")  # a file where the store goes
    assert_one_line_error(invoke(["sweep", f, "--out", tmp_path / "o"]), r"s\.zarr exists and is not a sweep store")
    (tmp_path / "o2" / "s.zarr").mkdir(parents=True)  # a folder of the user's, not a store
    assert_one_line_error(invoke(["sweep", f, "--out", tmp_path / "o2"]), r"not a sweep store \(no zarr\.json\)")
    assert (tmp_path / "o" / "s.zarr").read_text() == "mine" and a_file.read_text() == "keep"
    assert list((tmp_path / "o2" / "s.zarr").iterdir()) == []


# ---------------------------------------------------------------------------------------------
# data loss: a report file tobitkf did not write is never replaced
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["index.html", "REPORT.md"])
def test_report_never_replaces_a_file_tobitkf_did_not_write(tmp_path, fake_experiment, name):
    mine = _write(tmp_path / name, "my own notes, not a tobitkf report\n")
    assert_one_line_error(invoke(["report", tmp_path]), rf"^error: {name}: .* was not written by tobitkf")
    assert_one_line_error(invoke(["reproduce", "rel-fake", "--out", tmp_path]), rf"{name}: .* not written by tobitkf")
    assert mine.read_text() == "my own notes, not a tobitkf report\n"
    assert fake_experiment == []  # refused before the experiment ran
    other = "REPORT.md" if name == "index.html" else "index.html"
    assert not (tmp_path / other).exists()  # neither file written
    with pytest.raises(ValidationError, match="not written by tobitkf"):
        tk.write_report(tmp_path)
    # a report tobitkf wrote is replaced as before
    mine.unlink()
    assert invoke(["report", tmp_path]).exit_code == 0
    assert invoke(["report", tmp_path]).exit_code == 0


def test_reproduce_never_replaces_a_result_folder_tobitkf_did_not_write(tmp_path, fake_experiment):
    mine = tmp_path / "rel-fake"
    mine.mkdir()
    _write(mine / "notes.txt", "mine")
    assert_one_line_error(
        invoke(["reproduce", "rel-fake", "--out", tmp_path]), r"rel-fake holds files tobitkf did not write"
    )
    _write(mine / "metrics.json", '{"id": "other"}')  # not this experiment's result
    assert_one_line_error(invoke(["reproduce", "rel-fake", "--out", tmp_path]), r"did not write")
    with pytest.raises(ValidationError, match="did not write"):
        cli.run_experiment("rel-fake", runs=1, seed=0, out=tmp_path)
    assert fake_experiment == [] and (mine / "notes.txt").read_text() == "mine"
    shutil.rmtree(mine)
    _write(tmp_path / "rel-fake", "a file")  # a file where the folder goes
    assert_one_line_error(invoke(["reproduce", "rel-fake", "--out", tmp_path]), r"is a file")
    (tmp_path / "rel-fake").unlink()
    assert invoke(["reproduce", "rel-fake", "--out", tmp_path]).exit_code == 0  # its own result: replaced
    assert invoke(["reproduce", "rel-fake", "--out", tmp_path]).exit_code == 0
    assert len(fake_experiment) == 2


def test_plot_never_replaces_a_figure_tobitkf_did_not_draw(tmp_path, good_store):
    store, _ = good_store
    out = tmp_path / "figs"
    out.mkdir()
    _write(out / "rmse_over_time.png", "my own figure")
    assert_one_line_error(invoke(["plot", store, "--out", out]), r"rmse_over_time\.png was not written by tobitkf")
    assert (out / "rmse_over_time.png").read_text() == "my own figure"
    (out / "rmse_over_time.png").unlink()
    assert invoke(["plot", store, "--out", out]).exit_code == 0
    assert invoke(["plot", store, "--out", out]).exit_code == 0  # its own figures: replaced


def test_report_refuses_a_folder_where_its_file_goes(tmp_path):
    (tmp_path / "index.html").mkdir()
    (tmp_path / "index.html" / "keep").write_text("x")
    assert_one_line_error(invoke(["report", tmp_path]), r"^error: index\.html: .* is a folder")
    assert (tmp_path / "index.html" / "keep").read_text() == "x"


def test_reports_written_before_the_marker_are_still_replaced(tmp_path):
    from tobitkf import report

    tk.write_report(tmp_path)
    for name, marker in (("index.html", report._HTML_MARKER), ("REPORT.md", report._MD_MARKER)):
        path = tmp_path / name
        path.write_text(path.read_text(encoding="utf-8").replace(marker + "\n", ""), encoding="utf-8")
        assert marker not in path.read_text(encoding="utf-8")
    tk.write_report(tmp_path)  # the previous format's signature is recognised
    assert report._HTML_MARKER in (tmp_path / "index.html").read_text(encoding="utf-8")


@pytest.mark.parametrize(
    "content, problem",
    [
        (b'{"id": "e", "x": ' + b"[" * 5000 + b"]" * 5000 + b"}", r"nested too deeply"),
        (b'{"id": "e", "x": ' + b"[" * 150 + b"]" * 150 + b"}", r"deeper than 100 levels"),
        (b'{"id": "e", "runs": ' + b"1" * 5000 + b"}", r"an integer of 5000 digits"),
        (b'{"id": "e", "estimators": {"kf": {"rmse_time_avg": [' + b"9" * 400 + b"]}}}", r"an integer of 400 digits"),
        (b'{"id": "e\xff"}', r"not UTF-8 text"),
        (b"[1, 2]", r"not a JSON object"),
        (None, r"not a regular file"),
    ],
)
def test_report_reads_hostile_metrics_as_listed_problems(tmp_path, content, problem):
    (tmp_path / "bad").mkdir()
    if content is None:
        (tmp_path / "bad" / "metrics.json").mkdir()  # a folder where the file should be
    else:
        (tmp_path / "bad" / "metrics.json").write_bytes(content)
    (tmp_path / "ok").mkdir()
    (tmp_path / "ok" / "metrics.json").write_text(json.dumps({"id": "ok", "title": "\ud800 lone surrogate"}))
    with no_hang():
        res = invoke(["report", tmp_path])
    assert res.exit_code == 0, res.output
    md = (tmp_path / "REPORT.md").read_text(encoding="utf-8")  # valid UTF-8
    import re

    assert re.search(r"bad/metrics\.json .*" + problem, md), md[:2000]
    assert "`ok`" in md


def test_report_markdown_cannot_embed_a_remote_image(tmp_path):
    (tmp_path / "e").mkdir()
    evil = "![x](https://evil.example/track.png) [click](https://evil.example)"
    (tmp_path / "e" / "metrics.json").write_text(
        json.dumps(
            {
                "id": "e",
                "title": evil,
                "claims": [{"claim": evil, "measured": evil, "holds": False, "note": evil}],
                "settings": {"s": {"value": evil, "provenance": evil}},
            }
        )
    )
    tk.write_report(tmp_path)
    md = (tmp_path / "REPORT.md").read_text(encoding="utf-8")
    import re

    assert not re.search(r"(?<!\\)\[[^\]]*(?<!\\)\]\(https://evil", md), md
    assert "\\[click\\]" in md


# ---------------------------------------------------------------------------------------------
# damaged sweep stores: a named error for plot, a rerun and the library reader
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def good_store(tmp_path_factory):
    out = tmp_path_factory.mktemp("store")
    spec = parse_sweep(
        sweep_text(
            runs=20, extra="block_runs = 10\nchunk_blocks = 1", tail='[grid]\n"censoring.lower" = [-0.1, 0.1]\n'
        ),
        name="s",
    )
    return run_sweep(spec, out), spec


def _json_edit(path: Path, edit) -> None:
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))


def _chunks(path: Path):
    return [c for c in (path / "stats").rglob("*") if c.is_file() and c.name != "zarr.json"]


DAMAGE = {
    "garbage zarr.json": lambda p: (p / "zarr.json").write_text("{garbage"),
    "zarr.json not an object": lambda p: (p / "zarr.json").write_text("[1]"),
    "missing attribute": lambda p: _json_edit(p / "zarr.json", lambda d: d["attributes"].pop("layout")),
    "attribute of the wrong type": lambda p: _json_edit(p / "zarr.json", lambda d: d["attributes"].update(steps="5")),
    "layout not shapes": lambda p: _json_edit(p / "zarr.json", lambda d: d["attributes"].update(layout={"a": "b"})),
    "grid that disagrees": lambda p: _json_edit(
        p / "zarr.json", lambda d: d["attributes"].update(grid={"censoring.lower": [1, 2, 3]})
    ),
    "missing array": lambda p: shutil.rmtree(p / "stats"),
    "garbage array metadata": lambda p: (p / "done" / "zarr.json").write_text("\x00\x01"),
    "corrupt chunk": lambda p: [c.write_bytes(b"garbage") for c in _chunks(p)],
    "truncated chunk": lambda p: [c.write_bytes(c.read_bytes()[:5]) for c in _chunks(p)],
    "group where an array should be": lambda p: (
        shutil.rmtree(p / "stats"),
        (p / "stats").mkdir(),
        (p / "stats" / "zarr.json").write_text('{"zarr_format": 3, "node_type": "group", "attributes": {}}'),
    ),
    "array where the group should be": lambda p: (
        shutil.copytree(p / "stats", p.parent / "tmp_arr"),
        shutil.rmtree(p),
        (p.parent / "tmp_arr").rename(p),
    ),
}


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_a_damaged_store_is_a_named_error(tmp_path, good_store, damage):
    store, spec = good_store
    path = tmp_path / "s.zarr"
    shutil.copytree(store, path)
    DAMAGE[damage](path)
    with pytest.raises(ValidationError, match=r"^(result|sweep store): .*(damaged|not a sweep store)"):
        load_result(path)
    assert_one_line_error(invoke(["plot", path]), r"damaged|not a sweep store")
    f = _write(tmp_path / "s.toml", spec.text)
    assert_one_line_error(invoke(["sweep", f, "--out", tmp_path]), r"damaged|not a sweep store|different sweep")
    assert not (tmp_path / "s_plots").exists()
