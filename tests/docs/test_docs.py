"""The documentation: tutorials run as written, and the site builds without warnings."""

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
TUTORIALS = sorted((ROOT / "docs" / "tutorials").glob("*.md"))
FENCE = re.compile(r"```python\n(.*?)```", re.S)


@pytest.mark.parametrize("page", TUTORIALS, ids=lambda p: p.stem)
def test_tutorial_code_runs(page, tmp_path, monkeypatch):
    import matplotlib

    matplotlib.use("Agg")
    monkeypatch.chdir(tmp_path)
    blocks = FENCE.findall(page.read_text(encoding="utf-8"))
    assert blocks, f"{page.name} has no python code"
    namespace: dict = {"__name__": f"tutorial_{page.stem}"}
    for i, code in enumerate(blocks):
        exec(compile(code, f"{page.name}[block {i}]", "exec"), namespace)  # noqa: S102 - our own docs


def test_docs_site_builds_strict(tmp_path):
    pytest.importorskip("mkdocs")
    pytest.importorskip("mkdocstrings")
    exe = shutil.which("mkdocs") or str(Path(sys.executable).with_name("mkdocs"))
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    res = subprocess.run(
        [exe, "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env=env,
    )
    assert res.returncode == 0, res.stdout + res.stderr
    site = tmp_path / "site"
    assert (site / "api" / "filters" / "index.html").exists()
    # the tutorials are rendered with what their code prints and draws, highlighted, with no network
    for page in TUTORIALS:
        html = (site / "tutorials" / page.stem / "index.html").read_text(encoding="utf-8")
        assert 'class="highlight"' in html and '<span class="n">' in html, page.stem
        assert "output-label" in html or "_executed/" in html, page.stem
    figures = sorted(p.name for p in (site / "_executed").glob("*.png"))
    assert {f.split("-")[0] for f in figures} >= {
        "tobit",
        "fading",
        "protocol",
        "delay",
        "hinf",
        "control",
        "steady_state",
    }
    tobit = (site / "tutorials" / "tobit" / "index.html").read_text(encoding="utf-8")
    assert '<figure class="executed"><a href="../../_executed/tobit-1.png">' in tobit
    assert "<figcaption>Miller Fig 3.1" in tobit
    for page in site.rglob("*.html"):
        text = page.read_text(encoding="utf-8")
        assert not re.search(r"""<(script|link|img)[^>]+(src|href)=["']https?://""", text), page
    # every deviation anchor of docs/sources exists on its page
    mb = (site / "sources" / "miller2015-ch5-7" / "index.html").read_text(encoding="utf-8")
    assert 'id="mb-09"' in mb and 'id="mb-f1"' in mb
    # the docstrings' reST math, tables and roles reach the API pages converted, none raw
    for page in (tmp_path / "site" / "api").glob("*/index.html"):
        html = page.read_text(encoding="utf-8")
        for raw in (":math:", ".. math::", ":func:", ":class:", "=========="):
            assert raw not in html, f"{page.parent.name}: raw reST {raw!r} on the page"
    filters = (tmp_path / "site" / "api" / "filters" / "index.html").read_text(encoding="utf-8")
    assert filters.count("<math ") > 20 and 'class="arithmatex"' not in filters  # all converted to MathML


def _rest():
    pytest.importorskip("griffe")
    import importlib.util

    spec = importlib.util.spec_from_file_location("griffe_rest", ROOT / "docs" / "griffe_rest.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_rest_simple_table_with_header_and_continuation_lines():
    text = (
        "Keys:\n\n"
        "=====  ==============\n"
        "key    meaning\n"
        "=====  ==============\n"
        "``a``  first line\n"
        "       and its rest\n"
        "``b``  x | y\n"
        "=====  ==============\n\n"
        "After."
    )
    assert _rest().convert(text).splitlines() == [
        "Keys:",
        "",
        "",
        "| key | meaning |",
        "|---|---|",
        "| ``a`` | first line and its rest |",
        "| ``b`` | x \\| y |",
        "",
        "",
        "After.",
    ]


def test_rest_table_without_header_gets_an_empty_one():
    text = "==  ==\n1   2\n3   4\n==  ==\n"
    assert _rest().convert(text).splitlines()[1:5] == ["|  |  |", "|---|---|", "| 1 | 2 |", "| 3 | 4 |"]


def test_rest_math_roles_blocks_and_cross_references():
    conv = _rest().convert
    assert conv("so :math:`x_k^T P` holds") == "so \\(x_k^T P\\) holds"
    assert (
        conv(":func:`~tobitkf.metrics.nees` and :class:`tobitkf.LinearSystem`") == "`nees` and `tobitkf.LinearSystem`"
    )
    plain = conv("Text:\n\n.. math::\n\n    y = Cx + v\n\nMore.").splitlines()
    assert plain[plain.index("\\[") : plain.index("\\]") + 1] == ["\\[", "y = Cx + v", "\\]"]
    aligned = conv(".. math::\n    :label: eq1\n\n    a &= b \\\\\n    c &= d\n").splitlines()
    assert aligned[aligned.index("\\[") + 1 : aligned.index("\\]")] == [
        "\\begin{split}",
        "a &= b \\\\",
        "c &= d",
        "\\end{split}",
    ]
