"""MkDocs hook: the math of the pages as MathML, rendered by the browser itself.

``pymdownx.arithmatex`` (generic mode) keeps TeX away from the Markdown processor and marks
it ``<span class="arithmatex">\\(...\\)</span>`` (inline) or ``<div class="arithmatex">\\[...\\]</div>``
(display). This hook turns each of those into MathML with ``latex2mathml`` when the page is
built, so the site needs no JavaScript and no network to show equations (MathML Core is
rendered natively by Chromium, Firefox and Safari). A formula ``latex2mathml`` cannot read
is logged as a warning, which fails the ``--strict`` build instead of shipping raw TeX.
"""

from __future__ import annotations

import html
import logging
import re

from latex2mathml.converter import convert

log = logging.getLogger("mkdocs.hooks.mathml")
_MATH = re.compile(r'<(span|div) class="arithmatex">(.*?)</\1>', re.S)


def tex_to_mathml(tex: str, display: bool) -> str:
    """MathML of one formula given with its ``\\( \\)`` or ``\\[ \\]`` delimiters."""
    tex = tex.strip()
    if tex[:2] in ("\\(", "\\[") and tex[-2:] in ("\\)", "\\]"):
        tex = tex[2:-2]
    return convert(tex.strip(), display="block" if display else "inline")


def on_page_content(content: str, page, config, files) -> str:  # noqa: ARG001 (mkdocs hook signature)
    def repl(m: re.Match) -> str:
        tex = html.unescape(m.group(2))
        try:
            return tex_to_mathml(tex, m.group(1) == "div")
        except Exception as exc:  # latex2mathml raises several kinds  # noqa: BLE001
            log.warning("%s: cannot convert math %r to MathML (%s)", page.file.src_path, tex[:80], exc)
            return m.group(0)

    return _MATH.sub(repl, content)
