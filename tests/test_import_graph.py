"""The package's modules import one another one way: no import circle, and the filters stand below the
inference.

Read from the source (``ast``), nothing imported: every ``import`` and ``from ... import`` of a module of
``tobitkf``, at the top of a file or inside a function (a deferred import still ties the two files), is
an edge from the importing file to the file it names (``a.b`` is ``a/b.py`` or ``a/b/__init__.py``; in
``from a import b`` a submodule ``b`` is the target, any other name ``a`` itself). The parents a
target's import also runs (``a/__init__.py`` for ``a.b``) are not edges: the package's ``__init__``
files hand names on from below.
"""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = "tobitkf"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in sorted((SRC / PACKAGE).rglob("*.py"))}


def _resolve(name: str, modules: dict[str, Path]) -> str | None:
    """The module of this package that ``name`` (dotted) imports, or None for another package."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def import_graph() -> dict[str, set[str]]:
    """Module -> the modules of the package that it imports (see the module docstring)."""
    modules = _modules()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for mod, path in modules.items():
        is_pkg = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names if a.name.split(".")[0] == PACKAGE]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = mod.split(".")
                    base = base[: len(base) - node.level + (1 if is_pkg else 0)]
                    origin = ".".join(base + ([node.module] if node.module else []))
                else:
                    origin = node.module or ""
                if origin.split(".")[0] != PACKAGE:
                    continue
                for alias in node.names:
                    sub = f"{origin}.{alias.name}"
                    targets.append(sub if sub in modules else origin)
            for t in targets:
                r = _resolve(t, modules)
                if r is not None and r != mod:
                    graph[mod].add(r)
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle ``[a, b, ..., a]``, or None (depth-first search, three colours)."""
    colour = dict.fromkeys(graph, 0)  # 0 unseen, 1 on the path, 2 done
    path: list[str] = []

    def visit(m: str) -> list[str] | None:
        colour[m] = 1
        path.append(m)
        for n in sorted(graph[m]):
            if colour[n] == 1:
                return path[path.index(n) :] + [n]
            if colour[n] == 0 and (found := visit(n)) is not None:
                return found
        path.pop()
        colour[m] = 2
        return None

    for m in sorted(graph):
        if colour[m] == 0 and (found := visit(m)) is not None:
            return found
    return None


def test_cycle_finder_finds_a_planted_circle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert find_cycle(graph) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None


def test_graph_reads_the_deferred_and_relative_imports():
    graph = import_graph()
    assert "tobitkf.filters.kalman" in graph["tobitkf.inference.smoothing"]
    assert "tobitkf.filters.smoothing" in graph["tobitkf.filters.kalman"]
    assert "tobitkf.inference.fitting" in graph["tobitkf.inference.fit_cli"]  # imported inside run_fit


def test_no_import_circle_in_the_package():
    assert find_cycle(import_graph()) is None


def test_filters_never_import_the_inference():
    graph = import_graph()
    bad = sorted(
        (m, t)
        for m, ts in graph.items()
        if m.startswith(f"{PACKAGE}.filters")
        for t in ts
        if t.startswith(f"{PACKAGE}.inference")
    )
    assert bad == []


def test_names_handed_on_are_the_same_objects():
    """What moved below the inference keeps its old public paths, as the very same objects."""
    import tobitkf as tk
    from tobitkf import inference
    from tobitkf.filters import assumed_density, kalman, likelihood, smoothing, tobit
    from tobitkf.inference import _common, _results, fitting
    from tobitkf.inference import likelihood as inf_likelihood
    from tobitkf.inference import smoothing as inf_smoothing

    assert inference.rts_smooth is inf_smoothing.rts_smooth is smoothing.rts_smooth
    assert inference.prediction_log_densities is inf_likelihood.prediction_log_densities
    assert inf_likelihood.prediction_log_densities is likelihood.prediction_log_densities
    assert inf_smoothing.dropping_with_indicator is kalman.dropping_with_indicator
    assert inf_smoothing.check_tobit_indicator is tobit.check_tobit_indicator
    assert _common.assumed_density_filter is assumed_density.assumed_density_filter
    assert _common.gaussian_log_density is likelihood.gaussian_log_density
    assert _common.solve_psd is smoothing.solve_psd
    assert inference.FitResult is fitting.FitResult is _results.FitResult
    assert inference.residual_diagnostics is _results.residual_diagnostics
    assert tk.smooth is inference.smooth and tk.log_likelihood is inference.log_likelihood
    for cls in (tk.KalmanFilter, tk.DroppingKalmanFilter, tk.TobitKalmanFilter, tk.AssumedDensityTobitFilter):
        assert cls.smooth is smoothing.SmoothingMethods.smooth
        assert cls.log_likelihood is smoothing.SmoothingMethods.log_likelihood
    for cls in (tk.DroppingKalmanFilter, tk.TobitKalmanFilter):  # one filter() (a copy per family's docstring)
        assert cls.filter.__code__ is smoothing.IndicatorFilterMethods.filter.__code__
    # the assumed-density filter adds its limits to the same filter (its sample times and indicator branches)
    assert tk.AssumedDensityTobitFilter._filter_record is smoothing.IndicatorFilterMethods._filter_record


def test_control_uses_no_private_name_of_another_layer():
    """Control builds on the estimators' public API (issue "One estimation core"): it imports no
    underscore name from outside ``tobitkf.control`` (the shared helper modules ``_validation`` and
    ``_linalg`` are imported for their public names only)."""
    found = []
    for path in sorted((SRC / PACKAGE / "control").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not isinstance(node, ast.ImportFrom):
                continue
            inside = node.level == 1  # from .x import ...: a module of control itself
            if inside:
                continue
            found += [
                f"{path.name}: from {'.' * node.level}{node.module} import {a.name}"
                for a in node.names
                if a.name.startswith("_")
            ]
    assert found == [], found
