r"""No text of the package holds a control character: a LaTeX command in a non-raw string (``"\bar x"``,
``"\vartheta"``, ``"\approx"``) is read by Python as an escape (backspace, vertical tab, bell), and the rendered
docs then show ``ar x`` or drop a parameter's name (griffe warns and the strict docs build fails only for
parameters, not for prose)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[2] / "src" / "tobitkf"
CONTROL = "\x07\x08\x0b\x0c"  # bell (\a), backspace (\b), vertical tab (\v), form feed (\f)


def _python_files() -> list[Path]:
    return sorted(SRC.rglob("*.py"))


def test_the_check_sees_an_escaped_latex_command():
    tree = ast.parse('def f():\n    """:math:`\\bar x`"""\n')
    assert any(isinstance(n, ast.Constant) and "\x08" in n.value for n in ast.walk(tree))


@pytest.mark.parametrize("path", _python_files(), ids=lambda p: str(p.relative_to(SRC)))
def test_no_string_or_source_holds_a_control_character(path):
    text = path.read_text(encoding="utf-8")
    assert not any(c in text for c in CONTROL), f"{path}: a control character in the source"
    found = [
        node.lineno
        for node in ast.walk(ast.parse(text))
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and any(c in node.value for c in CONTROL)
    ]
    assert not found, f'{path}: strings at lines {found} hold an escape (make them raw: r"""...)'
