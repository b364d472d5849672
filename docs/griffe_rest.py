"""Griffe extension for the docs site: the reST pieces of our numpy-style docstrings as Markdown.

The docstrings are written for both ``help()`` and Sphinx-style readers, so they use reST
``:math:`...``` roles, ``.. math::`` blocks, simple tables (``====  ====`` borders) and
cross-reference roles (``:func:`...```). mkdocstrings renders docstrings as Markdown, where
these come out as raw text. This extension rewrites each docstring before it is parsed:

* ``:math:`x``` -> ``\\(x\\)`` and a ``.. math::`` block -> ``\\[ ... \\]`` (a ``split``
  environment when the block uses ``&`` or ``\\\\``, as Sphinx does), both rendered by
  ``pymdownx.arithmatex`` and turned into MathML by ``docs/hooks/mathml.py``;
* a simple table -> a Markdown table (continuation lines, whose first column is blank, are
  joined to the row above);
* ``:func:`~a.b.c``` and the other roles -> a code span (``c`` with ``~``, else ``a.b.c``).

Only the documentation build uses it (``mkdocs.yml``); the docstrings themselves stay reST.
"""

from __future__ import annotations

import inspect
import re

import griffe

__all__ = ["RestToMarkdown", "convert"]

_MATH_ROLE = re.compile(r":math:`([^`]+)`")
_XREF_ROLE = re.compile(r":(?:func|class|mod|meth|data|attr|obj|exc):`(~?)([^`]+)`")
_BORDER = re.compile(r"^(\s*)(=+)( +=+)*\s*$")


def _xref(m: re.Match) -> str:
    target = m.group(2)
    return f"`{target.rsplit('.', 1)[-1] if m.group(1) else target}`"


def _math_blocks(lines: list[str]) -> list[str]:
    out: list[str] = []
    i = 0
    while i < len(lines):
        m = re.match(r"^(\s*)\.\. math::\s*(.*)$", lines[i])
        if not m:
            out.append(lines[i])
            i += 1
            continue
        indent, first = m.group(1), m.group(2).strip()
        body = [first] if first else []
        i += 1
        while i < len(lines) and (not lines[i].strip() or len(lines[i]) - len(lines[i].lstrip()) > len(indent)):
            body.append(lines[i].strip())
            i += 1
        while body and not body[-1]:
            body.pop()
        body = [b for b in body if not b.startswith(":")]   # directive options (:label:, :nowrap:)
        tex = "\n".join(b for b in body if b)
        if "&" in tex or "\\\\" in tex:
            tex = "\\begin{split}\n" + tex + "\n\\end{split}"
        out.extend(["", f"{indent}\\[", *[indent + t for t in tex.splitlines()], f"{indent}\\]", ""])
    return out


def _cells(line: str, starts: list[int]) -> list[str]:
    bounds = starts[1:] + [None]
    return [line[a:b].strip() if b is not None else line[a:].strip() for a, b in zip(starts, bounds)]


def _is_border(line: str) -> bool:
    return bool(_BORDER.match(line)) and len(line.split()) >= 2


def _table_end(lines: list[str], i: int) -> tuple[int, int | None] | None:
    """``(last border, header border or None)`` of the simple table opening at line ``i``.

    reST: a top border, rows, a bottom border; with a header, one more border between the
    header rows and the body. A border followed by a blank line (or the end) closes the table."""
    borders = []
    for j in range(i + 1, len(lines)):
        if _is_border(lines[j]):
            borders.append(j)
            if j + 1 >= len(lines) or not lines[j + 1].strip():
                return (j, borders[0] if len(borders) == 2 else None) if len(borders) <= 2 else None
        elif not lines[j].strip() and j == i + 1:
            return None
    return None


def _tables(lines: list[str]) -> list[str]:
    out: list[str] = []
    i = 0
    while i < len(lines):
        found = _table_end(lines, i) if _is_border(lines[i]) else None
        if found is None:
            out.append(lines[i])
            i += 1
            continue
        end, head = found
        indent = lines[i][:len(lines[i]) - len(lines[i].lstrip())]
        starts = [s.start() for s in re.finditer(r"=+", lines[i])]
        rows: list[list[str]] = []
        header = [""] * len(starts)
        for j in range(i + 1, end):
            if j == head:
                header = [" ".join(filter(None, col)) for col in zip(*rows)]
                rows = []
                continue
            if not lines[j].strip():
                continue
            cells = _cells(lines[j], starts)
            if rows and not cells[0]:          # continuation line: join to the row above
                rows[-1] = [(a + " " + b).strip() for a, b in zip(rows[-1], cells)]
            else:
                rows.append(cells)
        esc = [[c.replace("|", "\\|") for c in r] for r in [header] + rows]
        out.append("")
        out.append(indent + "| " + " | ".join(esc[0]) + " |")
        out.append(indent + "|" + "---|" * len(starts))
        out.extend(indent + "| " + " | ".join(r) + " |" for r in esc[1:])
        out.append("")
        i = end + 1
    return out


def convert(text: str) -> str:
    """The Markdown form of a docstring written with reST math, tables and roles."""
    lines = _tables(_math_blocks(text.splitlines()))
    text = "\n".join(lines)
    text = _MATH_ROLE.sub(lambda m: "\\(" + m.group(1) + "\\)", text)
    return _XREF_ROLE.sub(_xref, text)


def _filter_docstrings(pkg: griffe.Module) -> None:
    """Each estimator's ``filter`` with the docstring it has at run time.

    The package writes that docstring once and completes it per family when the class is defined
    (``tobitkf.filters._filter_doc``), which reading the source cannot see: a ``filter`` written without a
    docstring gets the run-time one, and a class that inherits ``filter`` with a summary of its own (the
    run time gives it a ``filter`` of its own) gets a member of that signature with its text.
    """
    import importlib

    try:
        base = pkg.get_member("filters.core.Estimator.filter")
    except (KeyError, AttributeError):  # not the tobitkf package
        return
    for module in _modules(pkg.get_member("filters")):  # where the estimators live
        try:
            live = importlib.import_module(module.path)
        except ImportError:
            continue
        for cls in list(module.classes.values()):
            if cls.is_alias:
                continue
            obj = getattr(live, cls.name, None)
            fn = getattr(obj, "__dict__", {}).get("filter")
            doc = getattr(fn, "__doc__", None)
            if not doc:
                continue
            member = cls.members.get("filter")
            if member is None:
                member = griffe.Function("filter", parameters=_parameters(fn), returns=base.returns)
                cls.set_member("filter", member)
            if member.is_alias or (member.docstring is not None and member.docstring.value.strip()):
                continue
            member.docstring = griffe.Docstring(convert(inspect.cleandoc(doc)), parent=member)


def _parameters(fn) -> griffe.Parameters:
    """The parameters of the function ``fn`` as griffe's (names, kinds, defaults; no annotations)."""
    params = []
    for p in inspect.signature(fn).parameters.values():
        default = None if p.default is inspect.Parameter.empty else repr(p.default)
        params.append(griffe.Parameter(p.name, kind=griffe.ParameterKind(p.kind.description), default=default))
    return griffe.Parameters(*params)


def _modules(module: griffe.Module):
    yield module
    for sub in module.modules.values():
        if not sub.is_alias:
            yield from _modules(sub)


class RestToMarkdown(griffe.Extension):
    """Rewrite every loaded docstring with :func:`convert`; give each estimator's ``filter`` its run-time
    docstring (:func:`_filter_docstrings`)."""

    def on_instance(self, *, obj: griffe.Object, **kwargs) -> None:  # noqa: D102
        if obj.docstring is not None:
            obj.docstring.value = convert(obj.docstring.value)

    def on_package(self, *, pkg: griffe.Module, **kwargs) -> None:  # noqa: D102
        _filter_docstrings(pkg)
