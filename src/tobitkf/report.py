"""Readable report of a results folder: ``DIR/index.html`` and ``DIR/REPORT.md``.

``tobitkf reproduce`` writes one folder per experiment, ``DIR/ID/metrics.json`` plus
PNG figures. :func:`write_report` reads every such folder and writes

* ``DIR/index.html``: one self-contained page (inline CSS, no scripts, no network),
  readable on a phone. A summary at the top keeps two kinds of claims apart: the
  sources' claims (reproduced / not reproduced / n/a: a source's claim that our faithful
  implementation does not reproduce is a finding about the source, not a defect) and this
  package's own claims (held / failed / n/a: each failure is a defect or a limitation
  stated with its reason; :func:`tobitkf.experiments._claims.claim_origin` tells them
  apart), with links to each claim that did not hold; then one section per source and, in it, each
  experiment with its figures (each with its caption, linked to the full-size image),
  its parameters (those not stated by the source are flagged with the reason), the
  source's claims with their quantity, measured value, test and tolerance and the
  verdict as a symbol *and* a word, the tables the source prints next to ours, and the
  time-averaged RMSE of each estimator. A claim that does not hold links to an
  explanation: what was measured, the claim's ``note`` and its optional
  ``explanation``; an n/a claim says why it cannot be measured. Every deviation ID (``MB-09``,
  ``LD-E3``...) in a claim, note, parameter or table links to its entry in the project's
  ``docs/sources/`` pages (:func:`deviation_href`).
* ``DIR/REPORT.md``: the same tables in Markdown, for terminals and diffs.

Both files are written atomically and hold no time stamp, so rerunning the report on
unchanged results changes nothing. The report only reads: a broken ``metrics.json``
or a missing figure is listed under "Problems" instead of stopping the report.

Fields read from ``metrics.json`` (all optional but ``id``): ``id``, ``title``,
``source``, ``runs``, ``seed``, ``package_version``, ``elapsed_seconds``,
``settings`` (``{name: {value, provenance, note}}``), ``claims`` (``[{claim, quantity?,
measured, test?, tolerance?, holds, note?, explanation?, not_measurable?, origin?}]``, the claims
rule of :mod:`tobitkf.experiments._claims`), ``figures`` (file names in the folder),
``figure_captions`` (``{file name: caption}``), ``report_tables`` (``[{title, columns,
rows, note?}]``), ``warnings`` (the texts of the warnings raised while the experiment ran, shown under
"Warnings while it ran") and every ``estimators`` block anywhere in the remaining metrics
(``{key: {rmse_time_avg, nees_time_avg?, ...}}``), e.g. at the top level or under
``scenarios: {name: ...}``.
"""

from __future__ import annotations

import html
import os
import re
from collections.abc import Set as AbstractSet
from pathlib import Path
from typing import Any
from urllib.parse import quote

from ._io import atomic_write_text
from ._report_read import (
    _DEVIATION_ID,
    _HTML_MARKER,
    _MD_MARKER,
    _NO_REASON,
    _ORIGIN_MEANING,
    _ORIGIN_TITLE,
    _RMSE_DEFINITION,
    _VERDICT,
    _WORDS,
    DEVIATION_PAGES,
    Claim,
    ExperimentReport,
    _by_source,
    _finite,
    _Links,
    _links_for,
    _num,
    _totals,
    check_report_targets,
    collect_results,
    deviation_href,
    deviation_ids,
)

__all__ = [
    "write_report",
    "collect_results",
    "render_html",
    "render_markdown",
    "ExperimentReport",
    "check_report_targets",
    "DEVIATION_PAGES",
    "deviation_href",
    "deviation_ids",
]

# --------------------------------------------------------------------------- HTML

_CSS = """
:root{--fg:#1d2430;--muted:#5b6573;--line:#d9dee5;--bg:#fff;--soft:#f5f7fa;--ok:#146c2e;--okbg:#e3f4e8;
--bad:#a4161a;--badbg:#fde8e8;--na:#5b6573;--nabg:#eceff3;--warn:#8a5a00;--warnbg:#fff4db;--link:#0b57d0}
*{box-sizing:border-box}
html{-webkit-text-size-adjust:100%}
body{margin:0;background:var(--bg);color:var(--fg);font:15px/1.5 system-ui,-apple-system,"Segoe UI",Roboto,
"Noto Sans","DejaVu Sans",sans-serif}
main{max-width:1040px;margin:0 auto;padding:16px 18px 48px}
a{color:var(--link)}
h1{font-size:1.6rem;margin:.4em 0 .2em}
h2{font-size:1.3rem;margin:2.2em 0 .6em;padding-bottom:.25em;border-bottom:2px solid var(--line)}
h3{font-size:1.12rem;margin:0 0 .3em}
h4{font-size:.95rem;margin:1.4em 0 .4em;color:var(--muted);text-transform:uppercase;letter-spacing:.04em}
code{font:.9em ui-monospace,SFMono-Regular,Menlo,Consolas,"DejaVu Sans Mono",monospace;background:var(--soft);
padding:.05em .3em;border-radius:4px}
.lead{color:var(--muted);margin:0 0 1em}
.cards{display:flex;flex-wrap:wrap;gap:10px;margin:12px 0 8px}
.card{flex:1 1 130px;border:1px solid var(--line);border-radius:10px;padding:10px 12px;background:var(--soft)}
.card b{display:block;font-size:1.6rem;line-height:1.2}
.card.ok{background:var(--okbg);border-color:#b5dfc2;color:var(--ok)}
.card.bad{background:var(--badbg);border-color:#f3b9b9;color:var(--bad)}
.card.na{background:var(--nabg);color:var(--na)}
.card.finding{background:var(--warnbg);border-color:#f0d48a;color:var(--warn)}
.group{margin:14px 0 4px}.group h3{margin:0 0 .2em}.group p{margin:0 0 .4em;color:var(--muted);font-size:.9rem}
.toc{padding-left:1.2em}.toc li{margin:.2em 0}.toc ul{padding-left:1.1em}
.exp{border:1px solid var(--line);border-radius:12px;padding:16px 16px 8px;margin:18px 0;background:var(--bg)}
.meta{color:var(--muted);font-size:.88rem;margin:0 0 .6em}
.meta span{white-space:nowrap;margin-right:1em}
.figs{display:grid;grid-template-columns:minmax(0,1fr);gap:12px;margin:10px 0}
figure{margin:0;border:1px solid var(--line);border-radius:8px;padding:6px;background:#fff}
figure img{display:block;width:100%;height:auto}
figcaption{font-size:.85rem;color:var(--fg);margin-top:4px;overflow-wrap:anywhere}
figcaption .file{color:var(--muted);font-size:.8rem}
.scroll{overflow-x:auto;-webkit-overflow-scrolling:touch;margin:6px 0 10px}
table{border-collapse:collapse;width:100%;font-size:.9rem}
caption{text-align:left;font-weight:600;padding:4px 0;color:var(--muted)}
th,td{border-bottom:1px solid var(--line);padding:6px 8px;text-align:left;vertical-align:top}
thead th{background:var(--soft);font-weight:600;white-space:nowrap}
td.num,th.num{text-align:right;font-variant-numeric:tabular-nums;white-space:nowrap}
td.val{font-family:ui-monospace,SFMono-Regular,Menlo,Consolas,"DejaVu Sans Mono",monospace;font-size:.85em;
overflow-wrap:anywhere;min-width:6em}
td.best{font-weight:700}
table.rmse{width:auto;min-width:min(100%,420px)}
table.rmse th[scope=row]{padding-right:24px}
tr.flagged,tr.flagged td{background:var(--warnbg)}
tr.flagged>:first-child{box-shadow:inset 4px 0 0 #e0a800}
tr.failed,tr.failed td{background:var(--badbg)}
tr.failed>:first-child{box-shadow:inset 4px 0 0 var(--bad)}
tr.failed.finding,tr.failed.finding td{background:var(--warnbg)}
tr.failed.finding>:first-child{box-shadow:inset 4px 0 0 #e0a800}
.badge{display:inline-block;white-space:nowrap;border-radius:999px;padding:1px 9px;font-size:.82rem;font-weight:600;
border:1px solid transparent}
.badge.held{background:var(--okbg);color:var(--ok);border-color:#b5dfc2}
.badge.failed{background:var(--badbg);color:var(--bad);border-color:#f3b9b9}
.badge.na{background:var(--nabg);color:var(--na);border-color:#d3d8df}
.badge.failed.finding{background:var(--warnbg);color:var(--warn);border-color:#f0d48a}
.badge.source{color:var(--muted);font-weight:400;padding-left:0}
.badge.reconstructed,.badge.default,.badge.unspecified{background:var(--warnbg);color:var(--warn);
border-color:#f0d48a}
.why{display:inline-block;margin-top:3px;font-size:.85rem}
.explain{border-left:4px solid var(--bad);background:var(--badbg);border-radius:0 8px 8px 0;padding:8px 12px;
margin:8px 0}
.explain.na{border-left-color:#9aa3ad;background:var(--nabg)}
.explain.finding{border-left-color:#e0a800;background:var(--warnbg)}
.how{display:block;color:var(--muted);font-size:.85rem;margin-top:2px}
.explain p{margin:.25em 0}
.counts{font-size:.85rem;color:var(--muted)}
.meta span.claims{white-space:normal}
.problems{border:1px solid #f0d48a;background:var(--warnbg);border-radius:8px;padding:8px 12px 8px 28px}
.empty{color:var(--muted);font-style:italic}
.top{font-size:.85rem;text-align:right;margin:0}
@media (max-width:600px){body{font-size:14px}main{padding:10px 10px 40px}.exp{padding:12px 10px 6px;
border-radius:10px}th,td{padding:5px 6px}h2{margin-top:1.6em}
table.settings thead,table.claims thead{display:none}
table.settings tr,table.claims tr{display:grid;border-bottom:1px solid var(--line);padding:4px 0}
table.settings th,table.settings td,table.claims td{border:0;padding:2px 6px}
table.settings tr{grid-template-columns:10.5em minmax(0,1fr)}
table.claims tr{grid-template-columns:2em minmax(0,1fr)}
table.claims td:nth-child(n+3){grid-column:2}
table.claims td:nth-child(3)::before{content:"quantity: ";color:var(--muted)}
table.claims td:nth-child(4)::before{content:"measured: ";color:var(--muted)}
table.claims td:nth-child(5)::before{content:"test: ";color:var(--muted)}
table.claims td.num{text-align:left}
tr.flagged{box-shadow:inset 4px 0 0 #e0a800}tr.failed{box-shadow:inset 4px 0 0 var(--bad)}
tr.flagged>:first-child,tr.failed>:first-child{box-shadow:none}}
@media print{.exp{break-inside:avoid-page}a{color:inherit}}
"""


def _e(s: Any) -> str:
    return html.escape(str(s), quote=True)


def _el(s: Any, links: _Links) -> str:
    """Escaped text with every deviation ID linked to its ``docs/sources/`` entry."""

    def link(m: re.Match) -> str:
        href = links.href(m.group(0))
        return m.group(0) if href is None else f'<a class="dev" href="{_e(href)}">{m.group(0)}</a>'

    return _DEVIATION_ID.sub(link, _e(s))


def _claim_classes(c: Claim) -> str:
    cls = _VERDICT[c.holds][0]
    return f"{cls} finding" if c.holds is False and c.origin == "source" else cls


def _badge(c: Claim) -> str:
    _, sym, _ = _VERDICT[c.holds]
    return f'<span class="badge {_claim_classes(c)}"><span aria-hidden="true">{sym}</span> {c.word}</span>'


def _counts_text(e: ExperimentReport, sep: str = " · ") -> list[tuple[str, str]]:
    """Per origin with claims: (title, "a ✓ reproduced · b ✗ not reproduced · c n/a")."""
    out = []
    for origin in ("source", "package"):
        if any(c.origin == origin for c in e.claims):
            words = _WORDS[origin]
            text = sep.join(
                f"{e.count(h, origin)} {sym} {words[h]}".replace(" – ", " ")
                for h, sym in ((True, "✓"), (False, "✗"), (None, "–"))
            )
            out.append(("the source's" if origin == "source" else "this package's", text))
    return out


def _html_counts(e: ExperimentReport) -> str:
    parts = _counts_text(e)
    if not parts:
        return '<span class="counts">none</span>'
    return "; ".join(f'<span class="counts">{_e(who)}: {_e(text)}</span>' for who, text in parts)


def _html_settings(e: ExperimentReport, links: _Links) -> list[str]:
    if not e.settings:
        return ['<p class="empty">No parameters recorded.</p>']
    out = [
        '<div class="scroll"><table class="settings">',
        '<thead><tr><th scope="col">parameter</th><th scope="col">value</th><th scope="col">provenance</th>'
        '<th scope="col">note / reason</th></tr></thead><tbody>',
    ]
    for s in e.settings:
        cls = ' class="flagged"' if s.flagged else ""
        prov = _e(s.provenance)
        badge = f'<span class="badge {prov if s.flagged else "source"}">{"⚑ " if s.flagged else ""}{prov}</span>'
        if s.flagged and not s.note:
            note = '<span class="empty">no reason given</span>'
        else:
            note = _el(s.note, links)
        out.append(
            f'<tr{cls}><th scope="row"><code>{_e(s.name)}</code></th><td class="val">{_e(s.value)}</td>'
            f"<td>{badge}</td><td>{note}</td></tr>"
        )
    out.append("</tbody></table></div>")
    return out


def _explain_head(c: Claim) -> str:
    if c.holds is None:
        return "cannot be measured"
    return "(the source's) is not reproduced" if c.origin == "source" else "(this package's) fails"


def _html_claims(e: ExperimentReport, links: _Links) -> list[str]:
    if not e.claims:
        return ['<p class="empty">No claims recorded.</p>']
    out = [
        '<div class="scroll"><table class="claims">',
        '<thead><tr><th scope="col" class="num">#</th><th scope="col">claim (whose)</th>'
        '<th scope="col">quantity</th><th scope="col">measured</th><th scope="col">test (tolerance)</th>'
        '<th scope="col">verdict</th></tr></thead><tbody>',
    ]
    for c in e.claims:
        cell = _badge(c)
        if c.needs_explanation:
            text = f"why {c.word}" if c.holds is False else "why n/a"
            cell += f'<br><a class="why" href="#{c.anchor}">{text} →</a>'
        test = _el(c.test or "—", links) + (
            f'<span class="how">tolerance: {_el(c.tolerance, links)}</span>' if c.tolerance else ""
        )
        whose = "the source's" if c.origin == "source" else "this package's"
        out.append(
            f'<tr id="{c.anchor}-row" class="{_claim_classes(c)}"><td class="num">{c.number}</td>'
            f'<td>{_el(c.claim, links)}<span class="how">{whose}</span></td>'
            f"<td>{_el(c.quantity or '—', links)}</td><td>{_el(c.measured, links)}</td><td>{test}</td><td>{cell}</td></tr>"
        )
    out.append("</tbody></table></div>")
    for c in e.claims:
        if not c.needs_explanation:
            continue
        cls = "explain na" if c.holds is None else ("explain finding" if c.origin == "source" else "explain")
        out.append(
            f'<div class="{cls}" id="{c.anchor}"><p><strong>Claim {c.number} {_explain_head(c)}:</strong> '
            f"{_el(c.claim, links)}</p>"
        )
        if c.holds is None and c.not_measurable:
            out.append(f"<p><strong>Why n/a:</strong> {_e(c.not_measurable)}</p>")
        else:
            out.append(
                f"<p><strong>Measured:</strong> {_e(c.measured) or '<span class=empty>nothing recorded</span>'}</p>"
            )
        if c.test:
            out.append(
                f"<p><strong>Test:</strong> {_el(c.test, links)}; tolerance: {_el(c.tolerance or '—', links)}</p>"
            )
        if c.note:
            out.append(f"<p><strong>Note:</strong> {_el(c.note, links)}</p>")
        if c.explanation:
            out.append(f"<p><strong>Explanation:</strong> {_el(c.explanation, links)}</p>")
        if c.holds is False and c.origin == "package" and not (c.note or c.explanation):
            out.append(f'<p><strong>Reason:</strong> <span class="empty">{_e(_NO_REASON)}</span></p>')
        out.append(f'<p><a href="#{c.anchor}-row">↑ back to the claims table</a></p></div>')
    return out


def _html_rmse(e: ExperimentReport) -> list[str]:
    if not e.rmse_tables:
        return ['<p class="empty">No estimator summaries recorded.</p>']
    out = []
    for t in e.rmse_tables:
        out.append('<div class="scroll"><table class="rmse">')
        out.append(f"<caption>{_e(t.label)}</caption>")
        heads = "".join(f'<th scope="col" class="num">x{j + 1}</th>' for j in range(t.components))
        nees = '<th scope="col" class="num">NEES (avg)</th>' if t.has_nees else ""
        ratio = '<th scope="col" class="num">RMSE / optimum</th>' if t.has_ratio else ""
        out.append(f'<thead><tr><th scope="col">estimator</th>{heads}{nees}{ratio}</tr></thead><tbody>')
        lows = [t.lowest(j) for j in range(t.components)]
        for key, vals, nees_v in t.rows:
            cells = []
            for j in range(t.components):
                v = vals[j] if j < len(vals) else None
                best = _finite(v) and lows[j] is not None and v == lows[j] and len(t.rows) > 1
                cls = "num best" if best else "num"
                title = ' title="lowest"' if best else ""
                cells.append(f'<td class="{cls}"{title}>{_e(_num(v))}</td>')
            if t.has_nees:
                cells.append(f'<td class="num">{_e(_num(nees_v))}</td>')
            if t.has_ratio:
                cells.append(f'<td class="num">{_e(t.ratio_text(key))}</td>')
            out.append(f'<tr><th scope="row"><code>{_e(key)}</code></th>{"".join(cells)}</tr>')
        out.append("</tbody></table></div>")
    if any(len(t.rows) > 1 for t in e.rmse_tables):
        out.append('<p class="meta">Bold: the lowest RMSE of that component in the table.</p>')
    if any(t.has_ratio for t in e.rmse_tables):
        out.append(
            '<p class="meta">RMSE / optimum: each component\'s time-averaged RMSE over that of the particle '
            "filter <code>pf</code> (the Bayes-optimal estimate, not in the sources), on the runs the particle "
            "filter used.</p>"
        )
    return out


def _html_source_tables(e: ExperimentReport, links: _Links) -> list[str]:
    out = []
    for t in e.source_tables:
        out.append('<div class="scroll"><table class="source-table">')
        out.append(f"<caption>{_el(t.title, links)}</caption>")
        out.append("<thead><tr>" + "".join(f'<th scope="col">{_e(c)}</th>' for c in t.columns) + "</tr></thead><tbody>")
        for r in t.rows:
            out.append(
                "<tr>"
                + "".join(f'<td class="{"num" if j else ""}">{_el(v, links)}</td>' for j, v in enumerate(r))
                + "</tr>"
            )
        out.append("</tbody></table></div>")
        if t.note:
            out.append(f'<p class="meta">{_el(t.note, links)}</p>')
    return out


_WARNINGS_HEAD = "Warnings while it ran"
_WARNINGS_NOTE = (
    "What the estimators said during the run (each text once), e.g. a variant the experiment compares that "
    "diverges on some runs: read its numbers with that in mind."
)


def _html_warnings(e: ExperimentReport, links: _Links) -> list[str]:
    if not e.warnings:
        return []
    out = [f"<h4>{_e(_WARNINGS_HEAD)}</h4>", f'<p class="meta">{_e(_WARNINGS_NOTE)}</p>', '<ul class="warnings">']
    out += [f"<li>{_el(w, links)}</li>" for w in e.warnings]
    out.append("</ul>")
    return out


def _html_experiment(e: ExperimentReport, links: _Links) -> list[str]:
    out = [
        f'<section class="exp" id="{e.anchor}" aria-labelledby="{e.anchor}-h">',
        f'<h3 id="{e.anchor}-h"><code>{_e(e.id)}</code>{" — " + _e(e.title) if e.title else ""}</h3>',
    ]
    meta = " ".join(f"<span>{_e(k)}: <b>{_e(v)}</b></span>" for k, v in e.meta)
    out.append(f'<p class="meta">{meta} <span class="claims">claims: {_html_counts(e)}</span></p>')
    if e.figures:
        out.append('<div class="figs">')
        for name in e.figures:
            src = _e(f"{quote(e.folder)}/{quote(name)}")
            # intrinsic size attributes reserve the figure's aspect ratio before a lazy image loads;
            # the CSS (width: 100%; height: auto) scales it to the column
            size = e.figure_sizes.get(name)
            dims = f' width="{size[0]}" height="{size[1]}"' if size else ""
            caption = e.captions.get(name, "")
            text = (
                f'{_el(caption, links)} <span class="file">({_e(name)})</span>'
                if caption
                else f'<span class="file">{_e(name)}</span>'
            )
            alt = f"{_e(e.id)}: {_e(caption or name)}"
            out.append(
                f'<figure><a href="{src}"><img src="{src}" alt="{alt}" loading="lazy" decoding="async"'
                f"{dims}></a><figcaption>{text}</figcaption></figure>"
            )
        out.append("</div>")
    else:
        out.append('<p class="empty">No figures.</p>')
    out.append("<h4>Parameters</h4>")
    out.extend(_html_settings(e, links))
    out.append("<h4>Claims</h4>")
    out.extend(_html_claims(e, links))
    out.extend(_html_warnings(e, links))
    if e.source_tables:
        out.append("<h4>The source's tables and ours</h4>")
        out.extend(_html_source_tables(e, links))
    out.append("<h4>Time-averaged RMSE per estimator</h4>")
    out.append(f'<p class="meta">{_e(_RMSE_DEFINITION)}</p>')
    out.extend(_html_rmse(e))
    out.append('<p class="top"><a href="#top">↑ top</a></p></section>')
    return out


def render_html(
    experiments: list[ExperimentReport],
    problems: list[str],
    *,
    title: str = "tobitkf results",
    links: _Links | None = None,
) -> str:
    """The whole ``index.html`` page as a string (self-contained, no scripts). ``links``: how deviation
    IDs link to ``docs/sources/`` (default: the pages' path in the repository)."""
    links = links or _Links()
    groups = _by_source(experiments)
    out = [
        "<!DOCTYPE html>",
        '<html lang="en">',
        "<head>",
        '<meta charset="utf-8">',
        _HTML_MARKER,
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{_e(title)}</title>",
        f"<style>{_CSS}</style>",
        "</head>",
        "<body>",
        '<main id="top">',
        f"<h1>{_e(title)}</h1>",
        '<p class="lead">The sources\' numerical examples as reproduced by <code>tobitkf reproduce</code>: '
        "figures, parameters (⚑ marks values the source does not state), the source's claims with what "
        "we measured, the test and its tolerance, the source's tables next to ours, and the time-averaged "
        "RMSE of each estimator. A measured claim is held or not; n/a marks what cannot be measured. Our "
        "deviations from each source are listed, with their IDs (linked), in the project's "
        "<code>docs/sources/</code> pages.</p>",
        '<div class="cards">',
        f'<div class="card"><b>{len(experiments)}</b>experiments</div>',
        "</div>",
    ]
    for origin in ("source", "package"):
        held, failed, na = _totals(experiments, origin)
        words = _WORDS[origin]
        bad = "finding" if origin == "source" else "bad"
        out += [
            f'<div class="group" id="summary-{origin}"><h3>{_e(_ORIGIN_TITLE[origin])}</h3>',
            f"<p>{_e(_ORIGIN_MEANING[origin])}</p>",
            '<div class="cards">',
            f'<div class="card ok"><b>{held}</b>✓ {words[True]}</div>',
            f'<div class="card {bad}"><b>{failed}</b>✗ {words[False]}</div>',
            f'<div class="card na"><b>{na}</b>– n/a (not measurable)</div>',
            "</div></div>",
        ]
    if problems:
        out.append('<h2 id="problems">Problems</h2><ul class="problems">')
        out.extend(f"<li>{_e(p)}</li>" for p in problems)
        out.append("</ul>")
    for origin, anchor, heading in (
        ("source", "not-reproduced", "The sources' claims that did not reproduce"),
        ("package", "failed", "This package's claims that failed"),
    ):
        failing = [(e, c) for e in experiments for c in e.claims if c.holds is False and c.origin == origin]
        if not failing:
            continue
        out.append(f'<h2 id="{anchor}">{_e(heading)}</h2><ul class="toc">')
        for e, c in failing:
            reason = "" if origin == "source" or c.note or c.explanation else f" <em>({_e(_NO_REASON)})</em>"
            out.append(
                f'<li><a href="#{c.anchor}"><code>{_e(e.id)}</code> claim {c.number}</a>: {_el(c.claim, links)}'
                f"{reason}</li>"
            )
        out.append("</ul>")
    out.append('<h2 id="contents">Contents</h2>')
    if not experiments:
        out.append('<p class="empty">No results found (no <code>*/metrics.json</code> in this folder).</p>')
    out.append('<ul class="toc">')
    for src, anchor, exps in groups:
        out.append(f'<li><a href="#{anchor}">{_e(src)}</a><ul>')
        for e in exps:
            out.append(f'<li><a href="#{e.anchor}"><code>{_e(e.id)}</code></a> {_e(e.title)} {_html_counts(e)}</li>')
        out.append("</ul></li>")
    out.append("</ul>")
    for src, anchor, exps in groups:
        out.append(f'<section id="{anchor}" class="source"><h2>{_e(src)}</h2>')
        for e in exps:
            out.extend(_html_experiment(e, links))
        out.append("</section>")
    out += ["</main>", "</body>", "</html>", ""]
    return "\n".join(out)


# --------------------------------------------------------------------------- Markdown


def _md(s: Any) -> str:
    """Text safe inside a Markdown table cell: no line breaks; pipes, '<', backticks and square
    brackets escaped (so text from a metrics.json cannot form a link or embed a remote image)."""
    s = " ".join(str(s).split())
    return (
        s.replace("\\", "\\\\")
        .replace("|", "\\|")
        .replace("<", "\\<")
        .replace("`", "\\`")
        .replace("[", "\\[")
        .replace("]", "\\]")
    )


def _mdl(s: Any, links: _Links) -> str:
    """:func:`_md` with every deviation ID linked to its ``docs/sources/`` entry."""

    def link(m: re.Match) -> str:
        href = links.href(m.group(0))
        return m.group(0) if href is None else f"[{m.group(0)}]({quote(href, safe='/#:.-_~')})"

    return _DEVIATION_ID.sub(link, _md(s))


def _md_table(head: list[str], rows: list[list[str]], right: AbstractSet[int] = frozenset()) -> list[str]:
    align = ["---:" if i in right else "---" for i in range(len(head))]
    out = ["| " + " | ".join(head) + " |", "| " + " | ".join(align) + " |"]
    out.extend("| " + " | ".join(r) + " |" for r in rows)
    return out + [""]


def _md_summary_line(experiments: list[ExperimentReport]) -> str:
    parts = [f"Experiments: {len(experiments)}"]
    for origin in ("source", "package"):
        held, failed, na = _totals(experiments, origin)
        words = _WORDS[origin]
        parts.append(
            f"{_ORIGIN_TITLE[origin].lower()}: ✓ {words[True]}: {held} · ✗ {words[False]}: {failed} · "
            f"– n/a (not measurable): {na}"
        )
    return " · ".join(parts)


def render_markdown(
    experiments: list[ExperimentReport],
    problems: list[str],
    *,
    title: str = "tobitkf results",
    links: _Links | None = None,
) -> str:
    """``REPORT.md``: the same tables as the HTML page, in Markdown (``links`` as :func:`render_html`)."""
    links = links or _Links()
    out = [
        f"# {_md(title)}",
        "",
        _md_summary_line(experiments),
        "",
        "Each claim states its quantity, its test and its tolerance (three Monte Carlo standard errors for a "
        "random quantity). Our deviations from each source are listed, with their IDs (linked), in "
        "`docs/sources/`.",
        "",
    ]
    for origin in ("source", "package"):
        out += [f"- **{_ORIGIN_TITLE[origin]}.** {_md(_ORIGIN_MEANING[origin])}"]
    out.append("")
    if problems:
        out += ["## Problems", ""] + [f"- {_md(p)}" for p in problems] + [""]
    for origin, heading in (
        ("source", "The sources' claims that did not reproduce"),
        ("package", "This package's claims that failed"),
    ):
        failing = [(e, c) for e in experiments for c in e.claims if c.holds is False and c.origin == origin]
        if failing:
            out += [f"## {heading}", ""]
            for e, c in failing:
                reason = "" if origin == "source" or c.note or c.explanation else f" *({_md(_NO_REASON)})*"
                out.append(f"- `{_md(e.id)}` claim {c.number}: {_mdl(c.claim, links)}{reason}")
            out.append("")
    groups = _by_source(experiments)
    out += ["## Contents", ""]
    for src, _, exps in groups:
        out.append(f"- {_md(src)}")
        out.extend(
            f"  - `{_md(e.id)}` {_md(e.title)} ("
            + ("; ".join(f"{who}: {text}" for who, text in _counts_text(e, sep=", ")) or "no claims")
            + ")"
            for e in exps
        )
    out.append("")
    for src, _, exps in groups:
        out += [f"## {_md(src)}", ""]
        for e in exps:
            out += [f"### `{_md(e.id)}` {_md(e.title)}", ""]
            if e.meta:
                out += [" · ".join(f"{_md(k)}: {_md(v)}" for k, v in e.meta), ""]
            for n in e.figures:  # one paragraph per figure, so each renders on its own line
                cap = e.captions.get(n, "")
                out += [f"![{_md(e.id)}: {_md(cap or n)}]({quote(e.folder)}/{quote(n)})", ""]
                if cap:
                    out += [f"*{_mdl(cap, links)}* ({_md(n)})", ""]
            out += ["#### Parameters", ""]
            if e.settings:
                rows = [
                    [
                        f"`{_md(s.name)}`",
                        _md(s.value),
                        ("⚑ " if s.flagged else "") + _md(s.provenance),
                        _mdl(s.note, links) if (s.note or not s.flagged) else "*no reason given*",
                    ]
                    for s in e.settings
                ]
                out += _md_table(["parameter", "value", "provenance", "note / reason"], rows)
            else:
                out += ["*No parameters recorded.*", ""]
            out += ["#### Claims", ""]
            if e.claims:
                rows = []
                for c in e.claims:
                    _, sym, _ = _VERDICT[c.holds]
                    verdict = f"{sym} {c.word}" + (f" (see note {c.number} below)" if c.needs_explanation else "")
                    test = _mdl(c.test or "—", links) + (
                        f" (tolerance: {_mdl(c.tolerance, links)})" if c.tolerance else ""
                    )
                    whose = "the source's" if c.origin == "source" else "this package's"
                    rows.append(
                        [
                            str(c.number),
                            f"{_mdl(c.claim, links)} ({whose})",
                            _mdl(c.quantity or "—", links),
                            _mdl(c.measured, links),
                            test,
                            verdict,
                        ]
                    )
                out += _md_table(
                    ["#", "claim (whose)", "quantity", "measured", "test (tolerance)", "verdict"], rows, right={0}
                )
                for c in e.claims:
                    if c.needs_explanation:
                        if c.holds is False:
                            lead = (
                                f"- **Claim {c.number} {_explain_head(c)}.** "
                                f"Measured: {_mdl(c.measured, links) or 'nothing'}."
                            )
                        else:
                            lead = (
                                f"- **Claim {c.number} cannot be measured.** "
                                f"{_md(c.not_measurable or c.measured) or 'no reason recorded'}."
                            )
                        extra = "".join(
                            f" {lbl}: {_mdl(t, links)}."
                            for lbl, t in (("Note", c.note), ("Explanation", c.explanation))
                            if t
                        )
                        if c.holds is False and c.origin == "package" and not (c.note or c.explanation):
                            extra += f" Reason: {_md(_NO_REASON)}."
                        out.append(lead + extra)
                if any(c.needs_explanation for c in e.claims):
                    out.append("")
            else:
                out += ["*No claims recorded.*", ""]
            if e.warnings:
                out += [f"#### {_WARNINGS_HEAD}", "", _md(_WARNINGS_NOTE), ""]
                out += [f"- {_mdl(w, links)}" for w in e.warnings] + [""]
            if e.source_tables:
                out += ["#### The source's tables and ours", ""]
                for t in e.source_tables:
                    out += [f"*{_mdl(t.title, links)}*", ""]
                    out += _md_table(
                        [_md(c) for c in t.columns],
                        [[_mdl(v, links) for v in r] for r in t.rows],
                        right=set(range(1, len(t.columns))),
                    )
                    if t.note:
                        out += [_mdl(t.note, links), ""]
            out += ["#### Time-averaged RMSE per estimator", "", _md(_RMSE_DEFINITION), ""]
            if not e.rmse_tables:
                out += ["*No estimator summaries recorded.*", ""]
            for rt in e.rmse_tables:
                out += [f"*{_md(rt.label)}*", ""]
                lows = [rt.lowest(j) for j in range(rt.components)]
                rows = []
                for key, vals, nees_v in rt.rows:
                    row = [f"`{_md(key)}`"]
                    for j in range(rt.components):
                        v = vals[j] if j < len(vals) else None
                        cell = _md(_num(v))
                        if _finite(v) and v == lows[j] and len(rt.rows) > 1:
                            cell = f"**{cell}**"
                        row.append(cell)
                    if rt.has_nees:
                        row.append(_md(_num(nees_v)))
                    if rt.has_ratio:
                        row.append(_md(rt.ratio_text(key)))
                    rows.append(row)
                head = (
                    ["estimator"]
                    + [f"x{j + 1}" for j in range(rt.components)]
                    + (["NEES (avg)"] if rt.has_nees else [])
                )
                head += ["RMSE / optimum"] if rt.has_ratio else []
                out += _md_table(head, rows, right=set(range(1, len(head))))
    return "\n".join(out).rstrip("\n") + "\n\n" + _MD_MARKER + "\n"


# --------------------------------------------------------------------------- entry point


def write_report(results_dir: str | os.PathLike) -> tuple[Path, Path]:
    """Write ``results_dir/index.html`` and ``results_dir/REPORT.md`` from every ``*/metrics.json``.

    Parameters
    ----------
    results_dir : path
        The ``--out`` folder of ``tobitkf reproduce`` (one sub-folder per experiment).

    Returns
    -------
    index_html, report_md : Path
        The two files written (atomically).

    Raises
    ------
    ValidationError
        If ``results_dir`` is not a directory, or an ``index.html``/``REPORT.md`` in it was not
        written by tobitkf (it is never replaced).
    """
    from ._io import as_path

    root = as_path(results_dir, "results_dir")
    experiments, problems = collect_results(root)
    check_report_targets(root)
    # lone surrogates (from JSON escapes) cannot be written as UTF-8: shown as U+FFFD instead
    links = _links_for(root)
    html_text = render_html(experiments, problems, links=links).encode("utf-8", "replace").decode("utf-8")
    md_text = render_markdown(experiments, problems, links=links).encode("utf-8", "replace").decode("utf-8")
    index = atomic_write_text(root / "index.html", html_text)
    md = atomic_write_text(root / "REPORT.md", md_text)
    return index, md
