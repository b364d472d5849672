"""The reading half of the report: what a results folder holds, as :class:`ExperimentReport` objects.

:func:`collect_results` reads every ``DIR/ID/metrics.json`` (bounded: size, depth, digits, UTF-8; a
broken file is listed as a problem, never raised), :func:`check_report_targets` refuses to replace
an ``index.html`` / ``REPORT.md`` that tobitkf did not write, and the deviation IDs of the
``docs/sources/`` pages are found and linked here. The rendering (HTML, Markdown) and the entry
point :func:`~tobitkf.report.write_report` are in :mod:`tobitkf.report`, which documents the fields read.
"""

from __future__ import annotations

import json
import math
import os
import re
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ._validation import ValidationError
from .experiments._claims import claim_origin

__all__ = [
    "collect_results",
    "ExperimentReport",
    "check_report_targets",
    "DEVIATION_PAGES",
    "deviation_href",
    "deviation_ids",
    "Claim",
    "Setting",
    "SourceTable",
    "RmseTable",
]

# Every report carries a marker so that a rerun replaces only files tobitkf wrote
# (:func:`check_report_targets`); the last two are the signatures of reports written before the marker.
_HTML_MARKER = '<meta name="generator" content="tobitkf report">'
_MD_MARKER = '[//]: # "generator: tobitkf report (rewritten by tobitkf report; edits are lost)"'  # invisible
_MARKERS = {
    "index.html": (
        _HTML_MARKER.encode(),
        b'<meta charset="utf-8">\n<meta name="viewport" content="width=device-'
        b'width, initial-scale=1">\n<title>tobitkf results</title>',
    ),
    "REPORT.md": (_MD_MARKER.encode(), b"# tobitkf results\n\nExperiments: "),
}
_MAX_METRICS_BYTES = 64 * 2**20  # a metrics.json larger than this is not one tobitkf wrote
_MAX_DEPTH = 100  # nesting levels of a metrics.json (tobitkf writes fewer than 10)
_MAX_INT_DIGITS = 300  # integers beyond the float range cannot be formatted as numbers

_META_KEYS = {
    "id",
    "title",
    "source",
    "runs",
    "seed",
    "package_version",
    "elapsed_seconds",
    "settings",
    "claims",
    "figures",
    "figure_captions",
    "report_tables",
    "warnings",
}
_RMSE_DEFINITION = (
    "The mean over steps of the per-step RMSE (the root of the mean over runs of the squared error "
    "at each step); a claim that uses another RMSE (e.g. over runs and steps together) says so in "
    "its quantity."
)
_VALUE_LIMIT = 240  # characters of a parameter value shown before "…"
_VERDICT = {True: ("held", "✓", "held"), False: ("failed", "✗", "not held"), None: ("na", "–", "n/a")}
# the words of a verdict by whose claim it is: a source's claim is reproduced or not, the package's held or failed
_WORDS = {
    "source": {True: "reproduced", False: "not reproduced", None: "n/a"},
    "package": {True: "held", False: "failed", None: "n/a"},
}
_ORIGIN_TITLE = {"source": "The sources' claims", "package": "This package's claims"}
_ORIGIN_MEANING = {
    "source": (
        "What each source claims about its own examples, tested on our faithful implementation of it. A claim "
        "that does not reproduce is a finding about the source, not a defect of this package: its explanation "
        "says what we measured and why, and the source's page in docs/sources/ lists the source's known errors."
    ),
    "package": (
        'What this package claims about its own estimators and tools (marked "not in the source"). Each '
        "failure is a defect of the package or a limitation stated with its reason."
    ),
}
_NO_REASON = "no reason recorded: a failure of this package without a stated limitation is a defect"

#: the ``docs/sources/`` page of each deviation-ID prefix (``MB-09`` -> ``miller2015-ch5-7.md#mb-09``)
DEVIATION_PAGES = {
    "MA": "miller2015-ch1-4",
    "MB": "miller2015-ch5-7",
    "GF": "geng2017-fading",
    "GP": "geng-protocol",
    "LD": "li2018-delay",
    "WH": "wang-hinf",
}
_DEVIATION_ID = re.compile(r"\b(" + "|".join(DEVIATION_PAGES) + r")-([EF]?\d{1,3})\b")
_DOCS_SOURCES = "docs/sources/"  # the pages' path in the repository


def deviation_ids(text: str) -> list[str]:
    """Every deviation ID (``MA-09``, ``LD-E3``, ``WH-F1``...) in ``text``, in order."""
    return [m.group(0) for m in _DEVIATION_ID.finditer(text)]


def deviation_href(dev_id: str, base: str = _DOCS_SOURCES) -> str:
    """The link to a deviation's entry: ``base + page + ".md#" + anchor`` (the pages write
    ``{#mb-09}`` after each heading), e.g. ``docs/sources/miller2015-ch5-7.md#mb-09``."""
    prefix, _, _ = dev_id.partition("-")
    return f"{base}{DEVIATION_PAGES[prefix]}.md#{dev_id.lower()}"


def _docs_sources_dir() -> Path | None:
    """The project's ``docs/sources`` folder when tobitkf runs from a clone (the source tree, or the
    folder it was installed from), else None."""
    from ._extras import install_folder

    candidates = [Path(__file__).resolve().parents[2]]
    folder = install_folder()
    if folder is not None:
        candidates.append(folder)
    for root in candidates:
        if (root / "docs" / "sources" / "index.md").is_file():
            return root / "docs" / "sources"
    return None


@dataclass(frozen=True)
class _Links:
    """How deviation IDs become links: ``base`` is the path from the report's folder to the
    ``docs/sources/`` pages; ``anchors`` the IDs those pages hold (None: not checked, every ID links)."""

    base: str = _DOCS_SOURCES
    anchors: frozenset[str] | None = None

    def href(self, dev_id: str) -> str | None:
        if self.anchors is not None and dev_id.lower() not in self.anchors:
            return None
        return deviation_href(dev_id, self.base)


def _links_for(results_dir: Path) -> _Links:
    """Links that work from ``results_dir`` when the docs pages are on this machine (a relative path to
    them, only to anchors that exist); else the pages' path in the repository."""
    docs = _docs_sources_dir()
    if docs is None:
        return _Links()
    anchors = set()
    for page in docs.glob("*.md"):
        anchors.update(re.findall(r"\{#([a-z0-9-]+)\}", page.read_text(encoding="utf-8")))
    try:
        base = Path(os.path.relpath(docs, results_dir.resolve())).as_posix() + "/"
    except ValueError:  # another drive (Windows)
        base = docs.as_uri() + "/"
    return _Links(base=base, anchors=frozenset(anchors))


@dataclass(frozen=True)
class Setting:
    """One parameter row: ``flagged`` when the source does not state the value."""

    name: str
    value: str
    provenance: str
    note: str

    @property
    def flagged(self) -> bool:
        return self.provenance != "source"


@dataclass(frozen=True)
class Claim:
    """One claim row; ``holds`` is True, False or None (n/a: not measurable)."""

    number: int
    claim: str
    measured: str
    holds: bool | None
    note: str
    explanation: str
    anchor: str
    quantity: str = ""
    test: str = ""
    tolerance: str = ""
    not_measurable: str = ""
    origin: str = "source"

    @property
    def word(self) -> str:
        """The verdict in words: reproduced / not reproduced (a source's), held / failed (the package's), n/a."""
        return _WORDS[self.origin][self.holds]

    @property
    def needs_explanation(self) -> bool:
        """Failed claims always get an explanation entry; n/a ones when there is text to show."""
        return self.holds is False or (
            self.holds is None and bool(self.note or self.explanation or self.not_measurable)
        )


@dataclass(frozen=True)
class SourceTable:
    """A table the source prints, next to our numbers (``metrics["report_tables"]``)."""

    title: str
    columns: list[str]
    rows: list[list[str]]
    note: str


@dataclass(frozen=True)
class RmseTable:
    """Time-averaged RMSE of each estimator in one ``estimators`` block."""

    label: str
    components: int
    rows: list[tuple[str, list[Any], Any]]  # (estimator key, rmse_time_avg values, nees_time_avg or None)
    ratios: dict[str, list[Any]] = field(default_factory=dict)  # key -> RMSE / optimum per component

    @property
    def has_nees(self) -> bool:
        return any(nees is not None for _, _, nees in self.rows)

    @property
    def has_ratio(self) -> bool:
        """True when the block carries the optimum (``ratio_to_optimum``, from a particle filter)."""
        return bool(self.ratios)

    def ratio_text(self, key: str) -> str:
        """``RMSE / optimum`` of one estimator, its components joined by " / " ('' if none)."""
        vals = self.ratios.get(key)
        return " / ".join(_num(v) for v in vals) if vals else ""

    def lowest(self, j: int) -> float | None:
        """Smallest finite value in component column ``j`` (None if there is none)."""
        vals = [v[j] for _, v, _ in self.rows if j < len(v) and _finite(v[j])]
        return min(vals) if vals else None


@dataclass(frozen=True)
class ExperimentReport:
    """What the report shows of one experiment folder."""

    id: str
    title: str
    source: str
    folder: str
    anchor: str
    meta: list[tuple[str, str]]
    settings: list[Setting]
    claims: list[Claim]
    figures: list[str]
    rmse_tables: list[RmseTable]
    problems: list[str] = field(default_factory=list)
    figure_sizes: dict[str, tuple[int, int]] = field(default_factory=dict)
    captions: dict[str, str] = field(default_factory=dict)
    source_tables: list[SourceTable] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    def count(self, holds: bool | None, origin: str | None = None) -> int:
        """Claims with this verdict (of this origin, ``"source"`` or ``"package"``; None: both)."""
        return sum(1 for c in self.claims if c.holds is holds and (origin is None or c.origin == origin))


# --------------------------------------------------------------------------- reading


def _finite(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _text(v: Any) -> str:
    """A field as one line of plain text ('' for None)."""
    if v is None:
        return ""
    s = v if isinstance(v, str) else _format_value(v, limit=10**6)
    return " ".join(s.split())


def _format_value(v: Any, limit: int = _VALUE_LIMIT) -> str:
    """Compact text for a parameter value (numbers to 6 significant digits), cut at ``limit``."""

    def fmt(x: Any) -> str:
        if isinstance(x, bool) or x is None:
            return str(x)
        if isinstance(x, float):
            return f"{x:.6g}"
        if isinstance(x, (int, str)):
            return str(x)
        if isinstance(x, (list, tuple)):
            return "[" + ", ".join(fmt(y) for y in x) + "]"
        if isinstance(x, dict):
            return "{" + ", ".join(f"{k}: {fmt(y)}" for k, y in x.items()) + "}"
        return str(x)

    s = fmt(v)
    return s if len(s) <= limit else s[: limit - 1] + "…"


def _png_size(path: Path) -> tuple[int, int] | None:
    """(width, height) in pixels from a PNG header, None if the file is not a PNG."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(24)
    except OSError:
        return None
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
        w, h = struct.unpack(">II", head[16:24])
        return int(w), int(h)
    return None


def _slug(text: str, taken: set[str], prefix: str) -> str:
    base = prefix + (re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-") or "x")
    slug, i = base, 2
    while slug in taken:
        slug, i = f"{base}-{i}", i + 1
    taken.add(slug)
    return slug


def _find_estimator_blocks(obj: Any, path: tuple[str, ...] = ()) -> list[tuple[tuple[str, ...], dict]]:
    """Every ``estimators`` mapping inside ``obj`` (depth first, in insertion order) with its path."""
    found: list[tuple[tuple[str, ...], dict]] = []
    if isinstance(obj, dict):
        for key, val in obj.items():
            if key == "estimators" and isinstance(val, dict) and any(isinstance(s, dict) for s in val.values()):
                found.append((path, val))
            elif isinstance(val, (dict, list)):
                found.extend(_find_estimator_blocks(val, path + (str(key),)))
    elif isinstance(obj, list):
        for i, val in enumerate(obj):
            if isinstance(val, (dict, list)):
                found.extend(_find_estimator_blocks(val, path + (f"[{i}]",)))
    return found


def _rmse_table(path: tuple[str, ...], block: dict) -> RmseTable:
    label = " / ".join(p for p in path if p != "scenarios") or "all runs"
    rows = []
    ratios: dict[str, list[Any]] = {}
    for key, summ in block.items():
        if not isinstance(summ, dict):
            continue
        avg = summ.get("rmse_time_avg")
        if avg is None:
            values: list[Any] = []
        elif isinstance(avg, list):
            values = _flatten(avg)
        else:
            values = [avg]
        rows.append((str(key), values, summ.get("nees_time_avg")))
        ratio = summ.get("ratio_to_optimum")
        if isinstance(ratio, list):
            ratios[str(key)] = _flatten(ratio)
    comps = max((len(v) for _, v, _ in rows), default=0)
    return RmseTable(label=label, components=comps, rows=rows, ratios=ratios)


def _flatten(x: Any) -> list[Any]:
    if isinstance(x, list):
        return [z for y in x for z in _flatten(y)]
    return [x]


def _read_experiment(folder: Path, metrics: dict, taken: set[str]) -> ExperimentReport:
    exp_id = _text(metrics.get("id")) or folder.name
    anchor = _slug(exp_id, taken, "exp-")
    problems = []
    meta = []
    for key, label in (
        ("runs", "runs"),
        ("seed", "seed"),
        ("package_version", "tobitkf"),
        ("elapsed_seconds", "time (s)"),
    ):
        if metrics.get(key) is not None:
            meta.append((label, _format_value(metrics[key])))

    settings = []
    raw_settings = metrics.get("settings") or {}
    if isinstance(raw_settings, dict):
        for name, s in raw_settings.items():
            if isinstance(s, dict) and "value" in s:
                settings.append(
                    Setting(
                        str(name),
                        _format_value(s.get("value")),
                        _text(s.get("provenance")) or "unspecified",
                        _text(s.get("note")),
                    )
                )
            else:
                settings.append(Setting(str(name), _format_value(s), "unspecified", ""))

    claims = []
    raw_claims = metrics.get("claims") or []
    for i, c in enumerate(raw_claims if isinstance(raw_claims, list) else [], start=1):
        if not isinstance(c, dict):
            c = {"claim": c}
        holds = c.get("holds")
        if holds is not None and not isinstance(holds, bool):
            problems.append(f"{exp_id}: claim {i} has holds={holds!r}; expected true, false or null (shown as n/a)")
        claims.append(
            Claim(
                number=i,
                claim=_text(c.get("claim")),
                measured=_text(c.get("measured")),
                holds=holds if isinstance(holds, bool) else None,
                note=_text(c.get("note")),
                explanation=_text(c.get("explanation")),
                anchor=f"{anchor}-claim-{i}",
                quantity=_text(c.get("quantity")),
                test=_text(c.get("test")),
                tolerance=_text(c.get("tolerance")),
                not_measurable=_text(c.get("not_measurable")),
                origin=claim_origin(c, _text(metrics.get("source"))),
            )
        )

    listed = metrics.get("figures")
    if isinstance(listed, list):
        names = [str(f) for f in listed]
    else:
        names = sorted(p.name for p in folder.glob("*.png") if not p.name.startswith("."))
    figures = []
    for name in names:
        if Path(name).name != name or name in ("", ".", ".."):
            problems.append(f"{exp_id}: figure name {name!r} is not a plain file name; skipped")
        elif not (folder / name).is_file():
            problems.append(f"{exp_id}: figure {name} is listed in metrics.json but missing")
        else:
            figures.append(name)

    captions = {}
    raw_captions = metrics.get("figure_captions") or {}
    if isinstance(raw_captions, dict):
        captions = {str(k): _text(v) for k, v in raw_captions.items() if _text(v)}
    source_tables = []
    raw_tables = metrics.get("report_tables") or []
    for j, t in enumerate(raw_tables if isinstance(raw_tables, list) else [], start=1):
        cols = t.get("columns") if isinstance(t, dict) else None
        rows = t.get("rows") if isinstance(t, dict) else None
        if (
            not isinstance(cols, list)
            or not isinstance(rows, list)
            or not all(isinstance(r, list) and len(r) == len(cols) for r in rows)
        ):
            problems.append(
                f"{exp_id}: report table {j} is not {{title, columns, rows}} with rows of equal length; skipped"
            )
            continue
        source_tables.append(
            SourceTable(
                _text(t.get("title")) or f"table {j}",
                [_text(c) for c in cols],
                [[_cell(v) for v in r] for r in rows],
                _text(t.get("note")),
            )
        )

    raw_warnings = metrics.get("warnings") or []
    if not isinstance(raw_warnings, list):
        problems.append(f"{exp_id}: warnings is not a list of texts; skipped")
        raw_warnings = []
    warned = [t for t in (_text(w) for w in raw_warnings) if t]

    rest = {k: v for k, v in metrics.items() if k not in _META_KEYS}
    tables = [_rmse_table(p, b) for p, b in _find_estimator_blocks(rest)]
    return ExperimentReport(
        id=exp_id,
        title=_text(metrics.get("title")),
        source=_text(metrics.get("source")) or "unknown source",
        folder=folder.name,
        anchor=anchor,
        meta=meta,
        settings=settings,
        claims=claims,
        figures=figures,
        rmse_tables=tables,
        problems=problems,
        figure_sizes={f: size for f in figures if (size := _png_size(folder / f))},
        captions=captions,
        source_tables=source_tables,
        warnings=warned,
    )


def collect_results(results_dir: str | os.PathLike) -> tuple[list[ExperimentReport], list[str]]:
    """Read every ``results_dir/*/metrics.json``.

    Returns
    -------
    experiments : list of ExperimentReport
        Sorted by source, then id.
    problems : list of str
        Unreadable files, missing figures and the like, one line each.

    Raises
    ------
    ValidationError
        If ``results_dir`` is not a directory.
    """
    from ._io import as_path

    root = as_path(results_dir, "results_dir")
    if not root.is_dir():
        raise ValidationError(f"results_dir: expected a directory of experiment results, got {str(root)!r}")
    experiments, problems = [], []
    taken: set[str] = set()
    try:
        folders = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    except OSError as exc:
        raise ValidationError(f"results_dir: cannot list {str(root)!r} ({exc.strerror})") from None
    for folder in folders:
        mfile = folder / "metrics.json"
        if not mfile.is_file():
            if mfile.exists() or mfile.is_symlink():  # a folder, a broken link, a device
                problems.append(f"{_printable(folder.name)}/metrics.json is not a regular file; experiment skipped")
            continue
        if not _is_utf8(folder.name):
            problems.append(f"{_printable(folder.name)}/metrics.json: the folder name is not UTF-8; experiment skipped")
            continue
        metrics, why = _load_metrics(mfile)
        if why:
            problems.append(f"{folder.name}/metrics.json {why}; experiment skipped")
            continue
        assert metrics is not None, "_load_metrics gives the metrics or the reason"
        exp = _read_experiment(folder, metrics, taken)
        experiments.append(exp)
        problems.extend(exp.problems)
    experiments.sort(key=lambda e: (e.source.lower(), e.id))
    return experiments, problems


def _is_utf8(name: str) -> bool:
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:  # undecodable bytes of the file name (surrogate escapes)
        return False
    return True


def _printable(name: str) -> str:
    return name.encode("utf-8", "surrogateescape").decode("utf-8", "replace")


def _bounded_int(digits: str) -> int:
    if len(digits.lstrip("-")) > _MAX_INT_DIGITS:
        raise ValueError(f"an integer of {len(digits.lstrip('-'))} digits (at most {_MAX_INT_DIGITS} are read)")
    return int(digits)


def _depth(obj: Any, limit: int) -> int:
    """Nesting depth of lists/dicts in ``obj``, counted without recursion, up to ``limit + 1``."""
    deepest, stack = 0, [(obj, 1)]
    while stack:
        v, d = stack.pop()
        if isinstance(v, (dict, list)):
            deepest = max(deepest, d)
            if d > limit:
                return d
            stack.extend((x, d + 1) for x in (v.values() if isinstance(v, dict) else v))
    return deepest


def _load_metrics(mfile: Path) -> tuple[dict | None, str]:
    """The JSON object of ``mfile``, or None and the reason it cannot be shown (never raises)."""
    try:
        size = mfile.stat().st_size
        if size > _MAX_METRICS_BYTES:
            return None, f"is {size / 2**20:.0f} MiB, more than the {_MAX_METRICS_BYTES // 2**20} MiB read"
        metrics = json.loads(mfile.read_bytes().decode("utf-8"), parse_int=_bounded_int)
    except OSError as exc:
        return None, f"could not be read ({exc.strerror})"
    except UnicodeDecodeError as exc:
        return None, f"could not be read (not UTF-8 text: {exc.reason} at byte {exc.start})"
    except RecursionError:
        return None, "could not be read (nested too deeply)"
    except ValueError as exc:  # JSONDecodeError, and the integers refused by _bounded_int
        return None, f"could not be read ({exc})"
    if not isinstance(metrics, dict):
        return None, "is not a JSON object"
    if _depth(metrics, _MAX_DEPTH) > _MAX_DEPTH:
        return None, f"nests lists/objects deeper than {_MAX_DEPTH} levels"
    return metrics, ""


def check_report_targets(results_dir: str | os.PathLike) -> None:
    """Refuse, before anything is written, to replace an ``index.html`` or ``REPORT.md`` in
    ``results_dir`` that tobitkf did not write (no report marker), or that is a folder.

    Raises
    ------
    ValidationError
        Naming the file.
    """
    from ._io import as_path, check_replaceable

    root = as_path(results_dir, "results_dir")
    for fname, markers in _MARKERS.items():
        check_replaceable(root / fname, fname, markers)


def _by_source(experiments: list[ExperimentReport]) -> list[tuple[str, str, list[ExperimentReport]]]:
    groups: dict[str, list[ExperimentReport]] = {}
    for e in experiments:
        groups.setdefault(e.source, []).append(e)
    taken: set[str] = set()
    return [(src, _slug(src, taken, "src-"), exps) for src, exps in groups.items()]


def _totals(experiments: list[ExperimentReport], origin: str | None = None) -> tuple[int, int, int]:
    return (
        sum(e.count(True, origin) for e in experiments),
        sum(e.count(False, origin) for e in experiments),
        sum(e.count(None, origin) for e in experiments),
    )


def _num(v: Any) -> str:
    if _finite(v):
        return f"{v:.4g}"
    return "—" if v is None else _text(v)


def _cell(v: Any) -> str:
    """A report-table cell: numbers to 4 significant digits, text as it is."""
    if isinstance(v, bool) or v is None or isinstance(v, str):
        return "—" if v is None else _text(v)
    if isinstance(v, (int, float)):
        return _num(v)
    return _text(v)
