"""Property-based fuzzing of the command line and of the readers of files (issue 15).

The library's own fuzzing is in ``test_fuzz.py``; this file drives what a user hands the CLI:

* random command lines (commands, options, values, paths: files, folders, paths below a file,
  missing paths, overlong names, damaged stores, foreign report files): exit code 0 or 2, and
  for 2 exactly one line ``error: ...``, never a traceback;
* random bytes and edits of a sweep file read by :func:`tobitkf.sweep.spec.load_sweep`:
  a :class:`~tobitkf.sweep.SweepSpec` or a :class:`~tobitkf.sweep.SweepFileError`;
* random ``metrics.json`` documents (deep nesting, huge integers, lone surrogates, random
  bytes) read by the report: the report is written, valid UTF-8, every folder an experiment or
  a listed problem;
* random damage to a sweep store (files truncated, overwritten, deleted, JSON values changed)
  read by :func:`~tobitkf.sweep.load_result`, a rerun and ``tobitkf plot``: the result, or a
  :class:`~tobitkf.ValidationError`.

Example counts come from the hypothesis profile (tests/conftest.py): ``ci`` 25 per test,
``HYPOTHESIS_PROFILE=long`` 1000. Every example runs under a wall-clock guard.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import tempfile
from pathlib import Path
from unittest import mock

import matplotlib

matplotlib.use("Agg")
import pytest  # noqa: E402
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from typer.testing import CliRunner  # noqa: E402

import tobitkf as tk  # noqa: E402
from tobitkf import cli  # noqa: E402
from tobitkf.experiments import _REGISTRY, Experiment, ExperimentResult  # noqa: E402
from tobitkf.sweep import SweepFileError, load_result, parse_sweep, run_sweep  # noqa: E402
from tobitkf.sweep.spec import load_sweep  # noqa: E402
from tobitkf.sweep.store import check_resumable  # noqa: E402

from ._guards import no_hang  # noqa: E402

TIME_LIMIT = 60.0
SWEEP = """[sweep]
runs = 20
steps = 4
seed = 0
block_runs = 10
chunk_blocks = 1
[model]
A = [[0.9]]
C = [[1.0]]
Q = [[0.04]]
R = [[0.01]]
x0 = [0.0]
P0 = [[0.2]]
[censoring]
lower = 0.0
[estimators.tkf]
type = "TobitKalmanFilter"
[grid]
"censoring.lower" = [-0.1, 0.1]
"""
# hypothesis: the fixtures below are built once per module and only read by the examples
FUZZ = settings(
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow, HealthCheck.data_too_large]
)


def check_cli_result(res) -> None:
    """The command line's promise: exit 0, or exit 2 with one line ``error: ...``; never a traceback."""
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    assert "Traceback" not in res.output
    assert res.exit_code in (0, 2), (res.exit_code, res.output)
    if res.exit_code == 2:
        lines = [ln for ln in res.output.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("error: "), res.output


def _fast_run(*, runs, seed, progress=None):
    return ExperimentResult(
        id="fz-fast", settings={"runs": runs}, metrics={"estimators": {"kf": {"rmse_time_avg": [0.1 * runs]}}}
    )


FAST = Experiment(
    id="fz-fast", title="fast", source="fuzz", run=_fast_run, plot=lambda r, d: [], default_runs=1, module=__name__
)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """Paths of every kind the command line may be handed."""
    root = tmp_path_factory.mktemp("world")
    (root / "a_file").write_text("keep")
    (root / "dir").mkdir()
    (root / "sweep.toml").write_text(SWEEP)
    (root / "bad.toml").write_bytes(SWEEP.encode() + b"\n\xff\xfe[[[")
    (root / "foreign").mkdir()
    (root / "foreign" / "index.html").write_text("<p>mine</p>")
    store = run_sweep(parse_sweep(SWEEP, name="good"), root / "stores")
    damaged = root / "stores" / "damaged.zarr"
    shutil.copytree(store, damaged)
    (damaged / "zarr.json").write_text("{not json")
    return {"root": root, "store": store, "damaged": damaged}


def _paths(world):
    r = world["root"]
    return st.sampled_from(
        [
            r / "a_file",
            r / "a_file" / "sub",
            r / "dir",
            r / "missing",
            r / "sweep.toml",
            r / "bad.toml",
            r / "foreign",
            world["store"],
            world["damaged"],
            r / ("n" * 300),
            Path(""),
            r / "dir" / "new",
        ]
    )


VALUES = st.one_of(
    st.integers(-3, 5).map(str),
    st.sampled_from(["", "nan", "1e3", "10" * 12, "-1", "abc", "0x10"]),
    st.text(alphabet="abc-_/.0123456789", max_size=8),
)


@st.composite
def command_lines(draw, world):
    cmd = draw(st.sampled_from(["list", "report", "sweep", "plot", "reproduce", "nosuch"]))
    args: list[str] = [cmd]
    if cmd in ("report", "sweep", "plot"):
        args.append(str(draw(_paths(world))))
    if cmd == "reproduce":
        args.append(draw(st.sampled_from(["fz-fast", "no-such-id", "", "../x"])))
    options = {
        "reproduce": ["--runs", "--seed", "--out", "--resume", "--bogus"],
        "sweep": ["--out", "--workers", "--scheduler"],
        "plot": ["--out"],
    }.get(cmd, [])
    for opt in draw(st.lists(st.sampled_from(options), max_size=3, unique=True)) if options else []:
        if opt == "--resume":
            args.append(opt)
        elif opt == "--out":
            args += [opt, str(draw(_paths(world)))]
        elif opt == "--scheduler":
            args += [opt, draw(st.sampled_from(["local", "nonsense", "tcp://127.0.0.1:1"]))]
        else:
            args += [opt, draw(VALUES)]
    return args


@FUZZ
@given(data=st.data())
def test_random_command_lines_exit_0_or_2_with_one_line(world, data):
    args = data.draw(command_lines(world))
    # outputs go to a fresh folder per example unless the command line names one
    if "--out" not in args and args[0] in ("reproduce", "sweep"):
        args += ["--out", tempfile.mkdtemp(dir=world["root"])]
    cwd = world["root"] / "cwd"  # an empty path means the working folder: keep that one in tmp
    cwd.mkdir(exist_ok=True)
    with mock.patch.dict(_REGISTRY, {"fz-fast": FAST}), no_hang(TIME_LIMIT), contextlib.chdir(cwd):
        res = CliRunner().invoke(cli.app, args)
    check_cli_result(res)
    assert (world["root"] / "a_file").read_text() == "keep"
    assert (world["root"] / "foreign" / "index.html").read_text() == "<p>mine</p>"


# ---------------------------------------------------------------------------------------------
# sweep files
# ---------------------------------------------------------------------------------------------
@st.composite
def sweep_bytes(draw):
    data = bytearray(SWEEP.encode())
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["insert", "overwrite", "nest", "value", "truncate"]))
        pos = draw(st.integers(0, len(data)))
        if kind == "insert":
            data[pos:pos] = draw(st.binary(min_size=1, max_size=8))
        elif kind == "overwrite":
            blob = draw(st.binary(min_size=1, max_size=8))
            data[pos : pos + len(blob)] = blob
        elif kind == "nest":
            depth = draw(st.sampled_from([2, 17, 64, 1000, 5000]))
            data = bytearray(bytes(data).replace(b"[[0.9]]", b"[" * depth + b"0.9" + b"]" * depth, 1))
        elif kind == "value":
            key = draw(st.sampled_from([b"runs = 20", b"steps = 4", b"block_runs = 10", b"R = [[0.01]]"]))
            val = draw(
                st.sampled_from(
                    [b"10" * 20, b"1e-320", b"true", b'"0.5"', b"-1", b"inf", b"[[true]]", b"nan", b"9" * 5000]
                )
            )
            data = bytearray(bytes(data).replace(key, key.split(b"=")[0] + b"= " + val, 1))
        else:
            del data[pos:]
    return bytes(data)


@FUZZ
@given(content=sweep_bytes())
def test_random_sweep_file_bytes_load_or_raise_sweep_file_error(tmp_path_factory, content):
    f = tmp_path_factory.mktemp("sw") / "fz.toml"
    f.write_bytes(content)
    with no_hang(TIME_LIMIT):
        try:
            spec = load_sweep(f)
        except SweepFileError as exc:
            assert str(exc).startswith("sweep file: ") and "\n" not in str(exc).strip()
            return
    assert spec.runs >= 1 and spec.name


# ---------------------------------------------------------------------------------------------
# metrics.json read by the report
# ---------------------------------------------------------------------------------------------
SCALARS = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**600), 10**600),
    st.floats(allow_nan=True),
    st.text(max_size=20),
    st.sampled_from(["\ud800", "![x](https://e.x/p.png)", "<script>", "|"]),
)
JSON = st.recursive(
    SCALARS,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
    max_leaves=20,
)
KEYS = st.sampled_from(
    [
        "id",
        "title",
        "source",
        "runs",
        "seed",
        "settings",
        "claims",
        "figures",
        "estimators",
        "scenarios",
        "package_version",
        "elapsed_seconds",
    ]
)


@st.composite
def metrics_files(draw):
    kind = draw(st.sampled_from(["json", "json", "json", "bytes", "deep", "bigint"]))
    if kind == "bytes":
        return draw(st.binary(max_size=200))
    if kind == "deep":
        depth = draw(st.sampled_from([50, 101, 999, 5000]))
        return b'{"id": "d", "x": ' + b"[" * depth + b"]" * depth + b"}"
    if kind == "bigint":
        return b'{"id": "b", "runs": ' + b"7" * draw(st.sampled_from([300, 301, 4300, 5000])) + b"}"
    doc = draw(st.dictionaries(KEYS, JSON, max_size=6))
    if draw(st.booleans()):
        doc["estimators"] = {"kf": {"rmse_time_avg": draw(JSON), "nees_time_avg": draw(SCALARS)}}
    if draw(st.booleans()):
        doc["claims"] = draw(
            st.lists(
                st.dictionaries(st.sampled_from(["claim", "measured", "holds", "note"]), JSON, max_size=4), max_size=3
            )
        )
    return json.dumps(doc).encode("utf-8", "surrogatepass")


@FUZZ
@given(files=st.lists(metrics_files(), min_size=1, max_size=3))
def test_random_metrics_files_are_reported_or_listed_as_problems(tmp_path_factory, files):
    root = tmp_path_factory.mktemp("rep")
    for i, content in enumerate(files):
        (root / f"e{i}").mkdir()
        (root / f"e{i}" / "metrics.json").write_bytes(content)
    with no_hang(TIME_LIMIT):
        index, md = tk.write_report(root)
        res = CliRunner().invoke(cli.app, ["report", str(root)])
    check_cli_result(res)
    assert res.exit_code == 0
    html_text, md_text = index.read_bytes().decode("utf-8"), md.read_bytes().decode("utf-8")  # valid UTF-8
    assert 'content="tobitkf report"' in html_text and "generator: tobitkf report" in md_text
    from tobitkf.report import collect_results

    experiments, problems = collect_results(root)
    for i in range(len(files)):  # every folder: an experiment or a listed problem
        assert any(e.folder == f"e{i}" for e in experiments) or any(p.startswith(f"e{i}/") for p in problems)


# ---------------------------------------------------------------------------------------------
# damaged sweep stores
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def store(tmp_path_factory):
    spec = parse_sweep(SWEEP, name="st")
    return run_sweep(spec, tmp_path_factory.mktemp("good")), spec


JSON_VALUES = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-3, 10**6),
    st.text(max_size=5),
    st.lists(st.integers(-1, 30), max_size=4),
    st.just({}),
    st.floats(allow_nan=True),
)


def _edit_json(doc, path_choice: int, value, delete: bool):
    """Set (or delete) one value somewhere inside a JSON document."""
    nodes = [(None, None, doc)]
    i = 0
    while i < len(nodes):
        _, _, node = nodes[i]
        items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else []
        nodes.extend((node, k, v) for k, v in items)
        i += 1
    parent, key, _ = nodes[path_choice % len(nodes)]
    if parent is None:
        return value
    if delete and isinstance(parent, dict):
        del parent[key]
    else:
        parent[key] = value
    return doc


@st.composite
def damages(draw):
    return draw(
        st.lists(
            st.tuples(
                st.integers(0, 10**6),
                st.sampled_from(["truncate", "garbage", "delete", "json", "json", "json", "dir_to_file"]),
                st.integers(0, 10**6),
                JSON_VALUES,
                st.booleans(),
                st.binary(max_size=16),
            ),
            min_size=1,
            max_size=3,
        )
    )


def _damage(path: Path, plan) -> None:
    for which, kind, where, value, delete, blob in plan:
        files = sorted(p for p in path.rglob("*") if p.is_file())
        if not files:
            return
        f = files[which % len(files)]
        if kind == "truncate":
            f.write_bytes(f.read_bytes()[: where % (f.stat().st_size + 1)])
        elif kind == "garbage":
            f.write_bytes(blob)
        elif kind == "delete":
            f.unlink()
        elif kind == "dir_to_file":
            folder = f.parent
            if folder != path:
                shutil.rmtree(folder)
                folder.write_bytes(blob)
        elif f.name == "zarr.json":
            try:
                doc = json.loads(f.read_text())
            except (ValueError, UnicodeDecodeError):
                continue
            f.write_text(json.dumps(_edit_json(doc, where, value, delete)))


@FUZZ
@given(plan=damages())
def test_randomly_damaged_stores_are_read_or_refused_by_name(store, tmp_path_factory, plan):
    good, spec = store
    out = tmp_path_factory.mktemp("dmg")
    path = out / "st.zarr"
    shutil.copytree(good, path)
    _damage(path, plan)
    with no_hang(TIME_LIMIT):
        try:
            ds = load_result(path)
        except tk.ValidationError as exc:
            assert "\n" not in str(exc)
        else:
            assert set(ds.data_vars) >= {"rmse", "bias", "nees"}
        try:
            check_resumable(path, spec)  # what a rerun does first
        except tk.ValidationError:
            pass
        check_cli_result(CliRunner().invoke(cli.app, ["plot", str(path), "--out", str(out / "plots")]))
