"""MkDocs hook: run the tutorials' code when the site is built and show what it prints and draws.

Every fenced ``python`` block of a page under ``tutorials/`` is executed in order, in one
namespace per page (so later blocks see earlier ones), in a temporary working directory, with
matplotlib on its non-interactive Agg backend. After each block the hook inserts

* what the block printed, as a ``text`` block (omitted when nothing was printed), and
* every matplotlib figure the block left open, as a PNG written next to the site's pages
  (``_executed/<page>-<n>.png``, no network needed) inside a ``<figure>`` whose caption is the
  figure's title (or its first axes' title); the image links to the full-size file.

A block that raises fails the build (the error is logged as a warning, which ``mkdocs build
--strict`` turns into a failure), so the published tutorials are the tested ones. The same
blocks are run by ``tests/docs/test_docs.py``.
"""

from __future__ import annotations

import contextlib
import html
import io
import logging
import os
import re
import tempfile
import traceback

log = logging.getLogger("mkdocs.hooks.execute")
FENCE = re.compile(r"^```python\n(.*?)^```\n", re.S | re.M)
PAGES = ("tutorials/",)
_IMAGES: dict[str, bytes] = {}


def _figures() -> list[tuple[bytes, str]]:
    """Every open matplotlib figure as (PNG bytes, caption); the figures are closed."""
    import matplotlib.pyplot as plt

    out = []
    for num in plt.get_fignums():
        fig = plt.figure(num)
        title = fig._suptitle.get_text() if fig._suptitle is not None else ""
        if not title and fig.axes:
            title = fig.axes[0].get_title()
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
        out.append((buf.getvalue(), title))
        plt.close(fig)
    return out


def run_blocks(blocks: list[str], name: str) -> list[tuple[str, list[tuple[bytes, str]], str | None]]:
    """Execute ``blocks`` in one namespace; per block: (stdout, figures, error traceback or None)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.close("all")
    namespace: dict = {"__name__": f"tutorial_{name}"}
    results = []
    cwd = os.getcwd()
    with tempfile.TemporaryDirectory() as tmp:
        os.chdir(tmp)
        try:
            for i, code in enumerate(blocks):
                buf = io.StringIO()
                error = None
                try:
                    with contextlib.redirect_stdout(buf):
                        exec(compile(code, f"{name}[block {i}]", "exec"), namespace)  # noqa: S102 - our own docs
                except Exception:  # noqa: BLE001 - reported as a build warning
                    error = traceback.format_exc(limit=4)
                results.append((buf.getvalue(), _figures(), error))
                if error:
                    break
        finally:
            os.chdir(cwd)
            plt.close("all")
    return results


def _render(stdout: str, figures: list[tuple[bytes, str]], stem: str, prefix: str) -> str:
    out = []
    if stdout.strip():
        out.append('<p class="output-label">Output</p>\n\n```text\n' + stdout.rstrip() + "\n```\n")
    for png, title in figures:
        name = f"{stem}-{len([k for k in _IMAGES if k.startswith(stem + '-')]) + 1}.png"
        _IMAGES[name] = png
        src = f"{prefix}_executed/{name}"
        cap = html.escape(title or "Figure drawn by the code above")
        out.append(f'<figure class="executed"><a href="{src}"><img src="{src}" alt="{cap}"></a>'
                   f"<figcaption>{cap}</figcaption></figure>\n")
    return "\n".join(out)


def on_config(config):
    """Run the code against this checkout's ``src/`` (as mkdocstrings documents it), not an installed copy."""
    import sys

    src = os.path.join(os.path.dirname(config["config_file_path"]), "src")
    if os.path.isdir(src) and src not in sys.path:
        sys.path.insert(0, src)
        for name in [m for m in sys.modules if m == "tobitkf" or m.startswith("tobitkf.")]:
            del sys.modules[name]
    return config


def on_page_markdown(markdown: str, page, config, files) -> str:  # noqa: ARG001 (mkdocs hook signature)
    src = page.file.src_uri
    if not src.startswith(PAGES):
        return markdown
    blocks = [m.group(1) for m in FENCE.finditer(markdown)]
    if not blocks:
        return markdown
    stem = os.path.splitext(os.path.basename(src))[0]
    for key in [k for k in _IMAGES if k.startswith(stem + "-")]:
        del _IMAGES[key]                       # a rebuild (mkdocs serve) replaces the page's figures
    prefix = "../" * page.url.count("/")       # from the page's folder back to the site root
    results = run_blocks(blocks, stem)
    pieces, last, k = [], 0, 0
    for m in FENCE.finditer(markdown):
        pieces.append(markdown[last:m.end()])
        last = m.end()
        if k < len(results):
            stdout, figs, error = results[k]
            if error:
                log.warning("%s: block %d raised while building the docs:\n%s", src, k, error)
                pieces.append(f'\n```text\n{error}```\n')
            else:
                rendered = _render(stdout, figs, stem, prefix)
                if rendered:
                    pieces.append("\n" + rendered + "\n")
        k += 1
    pieces.append(markdown[last:])
    return "".join(pieces)


def on_post_build(config) -> None:
    """Write the figures the tutorials drew into ``site/_executed/``."""
    folder = os.path.join(config["site_dir"], "_executed")
    os.makedirs(folder, exist_ok=True)
    for name, png in _IMAGES.items():
        with open(os.path.join(folder, name), "wb") as fh:
            fh.write(png)
