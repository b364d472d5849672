"""Tests of tobitkf.report (index.html and REPORT.md) and of the CLI's report hooks.

The input is a fake results folder (tests/_report_fake.py) whose claims, settings and
estimator summaries are known, so every check compares the report with what was written
into metrics.json, not with the report's own earlier output.
"""

from __future__ import annotations

import importlib.util
import json
import re
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote

import numpy as np
import pytest
from typer.testing import CliRunner

from tobitkf._validation import ValidationError
from tobitkf.report import collect_results, write_report

_spec = importlib.util.spec_from_file_location("_report_fake", Path(__file__).with_name("_report_fake.py"))
fake = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(fake)

ROOT = Path(__file__).resolve().parents[1]
_VOID = {"meta", "img", "br", "hr", "link", "input", "source", "wbr"}


class Node:
    def __init__(self, tag: str, attrs: dict, parent: Node | None):
        self.tag, self.attrs, self.parent, self.children, self.text_parts = tag, attrs, parent, [], []

    def iter(self, tag: str | None = None):
        for c in self.children:
            if tag is None or c.tag == tag:
                yield c
            yield from c.iter(tag)

    def find_id(self, ident: str) -> Node | None:
        return next((n for n in self.iter() if n.attrs.get("id") == ident), None)

    @property
    def text(self) -> str:
        return " ".join("".join(self.text_parts + [c.text for c in self.children]).split())

    @property
    def classes(self) -> set[str]:
        return set((self.attrs.get("class") or "").split())


class TreeBuilder(HTMLParser):
    """A minimal, strict DOM: every non-void element must be closed in order."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.root = Node("#root", {}, None)
        self.cur = self.root

    def handle_starttag(self, tag, attrs):
        node = Node(tag, dict(attrs), self.cur)
        self.cur.children.append(node)
        if tag not in _VOID:
            self.cur = node

    def handle_endtag(self, tag):
        assert self.cur.tag == tag, f"</{tag}> closes <{self.cur.tag}>"
        self.cur = self.cur.parent

    def handle_data(self, data):
        # text kept in document order relative to children is not needed; append to the open element
        self.cur.children.append(_Text(data, self.cur))


class _Text(Node):
    def __init__(self, data, parent):
        super().__init__("#text", {}, parent)
        self.data = data

    @property
    def text(self):
        return self.data


def parse(html_text: str) -> Node:
    b = TreeBuilder()
    b.feed(html_text)
    b.close()
    assert b.cur is b.root, "unclosed elements"
    return b.root


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    root = tmp_path_factory.mktemp("results")
    written = fake.build_fake_results(root)
    index, md = write_report(root)
    html_text = index.read_text(encoding="utf-8")
    return {
        "root": root,
        "written": written,
        "index": index,
        "md": md,
        "html": html_text,
        "dom": parse(html_text),
        "md_text": md.read_text(encoding="utf-8"),
    }


def _rows(table: Node) -> list[Node]:
    return [r for r in table.iter("tr") if r.parent.tag == "tbody"]


def _verdict(claim) -> str:
    """The verdict's words: a source's claim is reproduced or not, the package's own held or failed."""
    if claim["claim"].startswith("(not in the source)"):
        return {True: "✓ held", False: "✗ failed", None: "n/a"}[claim["holds"]]
    return {True: "✓ reproduced", False: "✗ not reproduced", None: "n/a"}[claim["holds"]]


# ------------------------------------------------------------------ files and figures


def test_writes_both_files_in_results_dir(report):
    assert report["index"] == report["root"] / "index.html"
    assert report["md"] == report["root"] / "REPORT.md"
    assert not [p for p in report["root"].iterdir() if p.name.endswith(".tmp")]


def test_every_figure_referenced_exists_and_every_figure_is_shown(report):
    root, written = report["root"], report["written"]
    imgs = list(report["dom"].iter("img"))
    srcs = [unquote(i.attrs["src"]) for i in imgs]
    expected = [f"{eid}/{f}" for eid, m in written.items() for f in m.get("figures", [])]
    assert sorted(srcs) == sorted(expected)
    for img, src in zip(imgs, srcs):
        assert (root / src).is_file(), src
        assert img.attrs["loading"] == "lazy" and img.attrs["alt"]
        with open(root / src, "rb") as fh:  # intrinsic size from the PNG header (bytes 16-24, big-endian)
            head = fh.read(24)
        assert (img.attrs["width"], img.attrs["height"]) == (
            str(int.from_bytes(head[16:20], "big")),
            str(int.from_bytes(head[20:24], "big")),
        )
    assert "figure img{display:block;width:100%;height:auto}" in report["html"]
    md_links = [unquote(m) for m in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", report["md_text"])]
    assert sorted(md_links) == sorted(expected)


def test_figure_listed_but_missing_is_reported_not_linked(tmp_path):
    fake.build_fake_results(tmp_path)
    (tmp_path / "fake-beta" / "beta.png").unlink()
    index, md = write_report(tmp_path)
    text = index.read_text(encoding="utf-8")
    assert "beta.png" not in [unquote(i.attrs["src"]).split("/")[-1] for i in parse(text).iter("img")]
    assert "fake-beta: figure beta.png is listed in metrics.json but missing" in text
    assert "(fake-beta/beta.png)" not in md.read_text(encoding="utf-8")


# ------------------------------------------------------------------ claims


@pytest.mark.parametrize("exp_id", ["fake-alpha", "fake-beta"])
def test_claims_table_lists_every_claim_with_symbol_and_word(report, exp_id):
    section = report["dom"].find_id(f"exp-{exp_id}")
    tables = [t for t in section.iter("table") if "claims" in t.classes]
    assert len(tables) == 1
    rows = _rows(tables[0])
    claims = report["written"][exp_id]["claims"]
    assert len(rows) == len(claims)
    for row, claim in zip(rows, claims):
        cells = [c for c in row.children if c.tag == "td"]
        whose = "this package's" if claim["claim"].startswith("(not in the source)") else "the source's"
        assert cells[1].text == claim["claim"] + whose
        assert cells[2].text == claim["quantity"]
        assert cells[3].text == claim["measured"]
        assert claim["test"] in cells[4].text and claim["tolerance"] in cells[4].text
        assert _verdict(claim) in cells[5].text  # the word, not only a colour
        assert {True: "held", False: "failed", None: "na"}[claim["holds"]] in row.classes


def test_experiment_without_claims_says_so(report):
    section = report["dom"].find_id("exp-fake-gamma")
    assert not [t for t in section.iter("table")]
    assert "No claims recorded." in section.text and "No figures." in section.text


def test_failed_claims_link_to_an_explanation(report):
    dom = report["dom"]
    claims = report["written"]["fake-alpha"]["claims"]
    rows = _rows(next(t for t in dom.find_id("exp-fake-alpha").iter("table") if "claims" in t.classes))
    failed = [(r, c) for r, c in zip(rows, claims) if c["holds"] is False]
    assert len(failed) == 4  # two of the source's, two of the package's
    for row, claim in failed:
        links = [a.attrs["href"] for a in row.iter("a")]
        assert len(links) == 1 and links[0].startswith("#")
        target = dom.find_id(links[0][1:])
        assert target is not None and "explain" in target.classes
        assert claim["claim"] in target.text and claim["measured"] in target.text
        if "explanation" in claim:
            assert claim["explanation"] in target.text
        # and the explanation links back to its row
        assert f"#{row.attrs['id']}" in [a.attrs["href"] for a in target.iter("a")]
    # the top summary lists each failed claim with a link to the same explanation
    summary = [a.attrs["href"] for a in dom.iter("a") if re.fullmatch(r"\S+ claim \d+", a.text)]
    assert sorted(summary) == sorted(next(row.iter("a")).attrs["href"] for row, _ in failed)


def test_held_claims_have_no_explanation_link(report):
    rows = _rows(next(t for t in report["dom"].find_id("exp-fake-beta").iter("table") if "claims" in t.classes))
    assert all(not list(r.iter("a")) for r in rows)


def _cards(node) -> dict[str, int]:
    cards = {}
    for card in node.iter("div"):
        if "card" in card.classes:
            number = next(card.iter("b")).text
            cards[card.text[len(number) :].strip(" ✓✗–")] = int(number)
    return cards


def test_summary_counts_the_sources_claims_apart_from_the_packages(report):
    claims = [c for m in report["written"].values() for c in m.get("claims", [])]
    ours = [c for c in claims if c["claim"].startswith("(not in the source)")]
    theirs = [c for c in claims if not c["claim"].startswith("(not in the source)")]
    assert ours and theirs
    dom = report["dom"]

    def count(cs, holds):
        return sum(c["holds"] is holds for c in cs)

    source = {
        "reproduced": count(theirs, True),
        "not reproduced": count(theirs, False),
        "n/a (not measurable)": count(theirs, None),
    }
    package = {"held": count(ours, True), "failed": count(ours, False), "n/a (not measurable)": count(ours, None)}
    assert _cards(dom.find_id("summary-source")) == source
    assert _cards(dom.find_id("summary-package")) == package
    # what a failure means is said next to the counts: a source's is a finding, the package's a defect or limitation
    assert "a finding about the source, not a defect" in dom.find_id("summary-source").text
    assert "defect of the package or a limitation" in dom.find_id("summary-package").text
    # the source's claims that did not reproduce are not shown in the red of a defect
    assert "bad" not in next(c for c in dom.find_id("summary-source").iter("div") if "finding" in c.classes).classes
    md_line = report["md_text"].splitlines()[2]
    assert md_line == (
        f"Experiments: {len(report['written'])} · the sources' claims: ✓ reproduced: {source['reproduced']} · "
        f"✗ not reproduced: {source['not reproduced']} · – n/a (not measurable): {source['n/a (not measurable)']} · "
        f"this package's claims: ✓ held: {package['held']} · ✗ failed: {package['failed']} · "
        f"– n/a (not measurable): {package['n/a (not measurable)']}"
    )
    md = report["md_text"]
    assert md.index("## The sources' claims that did not reproduce") < md.index("## This package's claims that failed")


def test_a_failure_of_the_package_without_a_reason_is_called_a_defect(report):
    dom = report["dom"]
    claims = report["written"]["fake-alpha"]["claims"]
    no_reason = claims.index(next(c for c in claims if c["claim"] == "(not in the source) the fit converges")) + 1
    explain = dom.find_id(f"exp-fake-alpha-claim-{no_reason}")
    assert "fails" in explain.text and "no reason recorded" in explain.text and "defect" in explain.text
    stated = claims.index(next(c for c in claims if c.get("explanation") == fake.LIMITATION)) + 1
    assert "no reason recorded" not in dom.find_id(f"exp-fake-alpha-claim-{stated}").text
    # a source's claim that did not reproduce is never called a defect
    source_failed = dom.find_id("exp-fake-alpha-claim-2")
    assert "is not reproduced" in source_failed.text and "defect" not in source_failed.text


def test_deviation_ids_link_to_their_entries_in_docs_sources(report):
    import tobitkf.report as rep

    dom = report["dom"]
    links = [a for a in dom.iter("a") if "dev" in a.classes]
    assert sorted(a.text for a in links) == sorted(fake.LINKED_IDS)  # MA-99 has no entry: not linked
    for a in links:
        path, _, anchor = unquote(a.attrs["href"]).partition("#")
        page = (report["root"] / path).resolve()
        assert page.parent == ROOT / "docs" / "sources" and anchor == a.text.lower()
        assert "{#" + anchor + "}" in page.read_text(encoding="utf-8")
        assert rep.deviation_href(a.text).startswith("docs/sources/")
    md_links = re.findall(r"\[([A-Z]{2}-[EF]?\d+)\]\(([^)]+)\)", report["md_text"])
    assert sorted(i for i, _ in md_links) == sorted(fake.LINKED_IDS)
    for dev_id, href in md_links:
        path, _, anchor = unquote(href).partition("#")
        assert (report["root"] / path).resolve() == ROOT / rep.deviation_href(dev_id).partition("#")[0]
        assert anchor == dev_id.lower()
    # without the docs on this machine, the link is the page's path in the repository
    text = rep.render_markdown(*rep.collect_results(report["root"]))
    assert "[LD-E3](docs/sources/li2018-delay.md#ld-e3)" in text


def test_every_deviation_id_the_experiments_cite_has_an_entry_in_docs_sources():
    import tobitkf.report as rep

    anchors = set()
    for page in (ROOT / "docs" / "sources").glob("*.md"):
        anchors |= {(page.stem, a) for a in re.findall(r"\{#([a-z0-9-]+)\}", page.read_text(encoding="utf-8"))}
    cited = set()
    for path in (ROOT / "src" / "tobitkf").rglob("*.py"):
        cited |= set(rep.deviation_ids(path.read_text(encoding="utf-8")))
    assert len(cited) > 50
    missing = []
    for dev_id in sorted(cited):
        page, _, anchor = rep.deviation_href(dev_id, base="").partition(".md#")
        if (page, anchor) not in anchors:
            missing.append(dev_id)
    assert not missing, f"cited but with no entry in docs/sources: {missing}"


# ------------------------------------------------------------------ escaping and self-containment


def test_text_is_escaped(report):
    html_text, md_text = report["html"], report["md_text"]
    assert "<script" not in html_text.lower()
    assert "&lt;script&gt;alert(&#x27;x&#x27;)&lt;/script&gt;" in html_text
    assert fake.SCRIPT_CLAIM in report["dom"].text  # shown as text, verbatim
    assert "Alpha &amp; Beta 2020, Ch. &lt;1&gt;" in html_text
    assert not re.search(r"(?<!\\)<", md_text) and "\\<script>" in md_text  # every '<' backslash-escaped
    # a '|' in a cell must not split the Markdown table row
    row = next(line for line in md_text.splitlines() if "4 s.e." in line)
    assert "bias 0.2 \\| 4 s.e." in row and len(re.findall(r"(?<!\\)\|", row)) == 7


def test_html_is_self_contained_and_responsive(report):
    html_text, dom = report["html"], report["dom"]
    assert not re.search(r"(src|href)\s*=\s*[\"']?\s*(https?:|//|data:|javascript:)", html_text, re.I)
    assert not list(dom.iter("script")) and not list(dom.iter("link"))
    assert any(
        m.attrs.get("name") == "viewport" and "width=device-width" in m.attrs["content"] for m in dom.iter("meta")
    )
    assert "@media (max-width:600px)" in html_text
    # every in-page link points to an element that exists; the others open a figure of the folder
    for a in dom.iter("a"):
        href = a.attrs["href"]
        if href.startswith("#"):
            assert dom.find_id(href[1:]) is not None, href
        elif "dev" in a.classes:  # a deviation ID: its entry in the docs pages of this clone
            assert (report["root"] / unquote(href).partition("#")[0]).is_file(), href
        else:
            assert (report["root"] / unquote(href)).is_file() and href.endswith(".png"), href
    ids = [n.attrs["id"] for n in dom.iter() if "id" in n.attrs]
    assert len(ids) == len(set(ids))


# ------------------------------------------------------------------ grouping, parameters, RMSE


def test_one_section_per_source_holding_its_experiments(report):
    sections = [s for s in report["dom"].iter("section") if "source" in s.classes]
    got = {}
    for s in sections:
        title = next(s.iter("h2")).text
        got[title] = [e.attrs["id"] for e in s.iter("section") if "exp" in e.classes]
    want = {}
    for eid, m in sorted(report["written"].items()):
        want.setdefault(m["source"], []).append(f"exp-{eid}")
    assert got == want
    assert list(got) == sorted(want, key=str.lower)
    md_heads = [line[3:] for line in report["md_text"].splitlines() if line.startswith("## ")]
    assert md_heads == [
        "The sources' claims that did not reproduce",
        "This package's claims that failed",
        "Contents",
        "Alpha & Beta 2020, Ch. \\<1>",
        "Zeta 2019",
    ]


def test_parameters_flag_values_the_source_does_not_state(report):
    settings = report["written"]["fake-alpha"]["settings"]
    section = report["dom"].find_id("exp-fake-alpha")
    table = next(t for t in section.iter("table") if "settings" in t.classes)
    rows = _rows(table)
    assert [next(r.iter("code")).text for r in rows] == list(settings)
    assert {s["provenance"] for s in settings.values()} == {"source", "reconstructed", "default"}
    for row, s in zip(rows, settings.values()):
        cells = [c for c in row.children if c.tag == "td"]
        assert s["provenance"] in cells[1].text
        if s["provenance"] == "source":
            assert "flagged" not in row.classes and "⚑" not in row.text
        else:
            assert "flagged" in row.classes and "⚑" in cells[1].text
            assert cells[2].text == (s["note"] or "no reason given")
    assert [c for c in rows[0].children if c.tag == "td"][0].text == "[[1, 0.1], [0, 1]]"
    md_rows = [line for line in report["md_text"].splitlines() if line.startswith("| `sigma`")]
    assert md_rows == ["| `sigma` | 0.05 | ⚑ reconstructed | garbled in (3.45); spec A-3.6 |"]


def _rmse_tables(report, exp_id):
    section = report["dom"].find_id(f"exp-{exp_id}")
    return [t for t in section.iter("table") if "rmse" in t.classes]


def test_rmse_table_per_estimator_block_including_nested_scenarios(report):
    for exp_id, blocks in (
        ("fake-alpha", {"all runs": report["written"]["fake-alpha"]["estimators"]}),
        ("fake-beta", {k: v["estimators"] for k, v in report["written"]["fake-beta"]["scenarios"].items()}),
    ):
        tables = _rmse_tables(report, exp_id)
        assert [next(t.iter("caption")).text for t in tables] == list(blocks)
        for table, est in zip(tables, blocks.values()):
            rows = _rows(table)
            assert [next(r.iter("code")).text for r in rows] == list(est)
            for row, summ in zip(rows, est.values()):
                cells = [c.text for c in row.children if c.tag == "td"]
                avg = np.asarray(summ["rmse_time_avg"]).ravel()
                assert [float(x) for x in cells[: avg.size]] == pytest.approx(avg, rel=5e-4)
                assert float(cells[avg.size]) == pytest.approx(summ["nees_time_avg"])


def test_rmse_lowest_value_per_component_is_bold(report):
    est = report["written"]["fake-beta"]["scenarios"]["low"]["estimators"]
    best = min(est, key=lambda k: float(np.ravel(est[k]["rmse_time_avg"])[0]))
    table = _rmse_tables(report, "fake-beta")[0]
    bold = [
        next(r.iter("code")).text for r in _rows(table) if any("best" in c.classes for c in r.children if c.tag == "td")
    ]
    assert bold == [best]
    md_row = next(line for line in report["md_text"].splitlines() if line.startswith(f"| `{best}` | **"))
    assert md_row


def test_no_estimators_block_means_no_rmse_table(report):
    assert _rmse_tables(report, "fake-gamma") == []
    assert "No estimator summaries recorded." in report["dom"].find_id("exp-fake-gamma").text


# ------------------------------------------------------------------ robustness


def test_broken_metrics_json_is_listed_and_the_rest_reported(tmp_path):
    fake.build_fake_results(tmp_path)
    (tmp_path / "fake-beta" / "metrics.json").write_text("{not json", encoding="utf-8")
    (tmp_path / "list-not-dict").mkdir()
    (tmp_path / "list-not-dict" / "metrics.json").write_text("[1, 2]", encoding="utf-8")
    (tmp_path / "no-metrics").mkdir()
    exps, problems = collect_results(tmp_path)
    assert [e.id for e in exps] == ["fake-alpha", "fake-gamma"]
    assert len(problems) == 2
    assert problems[0].startswith("fake-beta/metrics.json could not be read")
    assert problems[1] == "list-not-dict/metrics.json is not a JSON object; experiment skipped"
    text = write_report(tmp_path)[0].read_text(encoding="utf-8")
    assert "Problems" in text and "fake-beta/metrics.json could not be read" in text


def test_figure_names_cannot_leave_the_experiment_folder(tmp_path):
    fake.build_fake_results(tmp_path)
    mfile = tmp_path / "fake-beta" / "metrics.json"
    m = json.loads(mfile.read_text())
    m["figures"] = ["../fake-alpha/fig_a1.png", "beta.png"]
    mfile.write_text(json.dumps(m))
    exps, problems = collect_results(tmp_path)
    beta = next(e for e in exps if e.id == "fake-beta")
    assert beta.figures == ["beta.png"]
    assert problems == ["fake-beta: figure name '../fake-alpha/fig_a1.png' is not a plain file name; skipped"]


def test_claim_verdict_other_than_true_false_null_is_unchecked_and_reported(tmp_path):
    fake.build_fake_results(tmp_path)
    mfile = tmp_path / "fake-beta" / "metrics.json"
    m = json.loads(mfile.read_text())
    m["claims"][0]["holds"] = "yes"
    mfile.write_text(json.dumps(m))
    exps, problems = collect_results(tmp_path)
    assert next(e for e in exps if e.id == "fake-beta").claims[0].holds is None
    assert problems == ["fake-beta: claim 1 has holds='yes'; expected true, false or null (shown as n/a)"]


def test_empty_folder_gives_an_empty_report(tmp_path):
    index, md = write_report(tmp_path)
    assert "No results found" in index.read_text(encoding="utf-8")
    assert "Experiments: 0 · the sources' claims: ✓ reproduced: 0" in md.read_text(encoding="utf-8")


def test_rewriting_unchanged_results_changes_nothing(report):
    before = (report["index"].read_bytes(), report["md"].read_bytes())
    write_report(report["root"])
    assert (report["index"].read_bytes(), report["md"].read_bytes()) == before


def test_not_a_directory_raises(tmp_path):
    with pytest.raises(ValidationError, match=r"results_dir: expected a directory .*nowhere"):
        write_report(tmp_path / "nowhere")
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValidationError, match="results_dir: expected a directory"):
        write_report(tmp_path / "file")


# ------------------------------------------------------------------ CLI


def test_cli_report_command(tmp_path):
    from tobitkf.cli import app

    fake.build_fake_results(tmp_path)
    res = CliRunner().invoke(app, ["report", str(tmp_path)])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "index.html").is_file() and (tmp_path / "REPORT.md").is_file()
    res = CliRunner().invoke(app, ["report", str(tmp_path / "missing")])
    assert res.exit_code == 2
    assert "results_dir: expected a directory" in res.output


def test_cli_reproduce_writes_the_report_of_the_whole_folder(tmp_path, monkeypatch):
    """A single-experiment reproduce still reports every experiment already in the folder."""
    import tobitkf.cli as cli
    import tobitkf.experiments as experiments

    fake.build_fake_results(tmp_path)
    ran = []

    class _Exp:
        id = "fake-beta"

    def fake_run(exp_id, *, runs, seed, out, **_options):  # progress, full, heartbeat: not used here
        ran.append((exp_id, runs, seed, Path(out)))
        return Path(out) / exp_id

    monkeypatch.setattr(experiments, "get", lambda i: _Exp())
    monkeypatch.setattr(cli, "run_experiment", fake_run)
    res = CliRunner().invoke(cli.app, ["reproduce", "fake-beta", "--runs", "2", "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    assert ran == [("fake-beta", 2, 0, tmp_path)]
    md = (tmp_path / "REPORT.md").read_text(encoding="utf-8")
    assert all(f"`{eid}`" in md for eid in ("fake-alpha", "fake-beta", "fake-gamma"))


# ------------------------------------------------------------------ captions, links, source tables, n/a


def test_figures_have_their_captions_and_link_to_the_full_size_image(report):
    section = report["dom"].find_id("exp-fake-alpha")
    figs = [f for f in section.iter("figure")]
    assert len(figs) == 2
    cap = next(figs[0].iter("figcaption")).text
    assert fake.CAPTION_A1 in cap and "fig_a1.png" in cap
    links = [a.attrs["href"] for a in figs[0].iter("a")]
    img = next(figs[0].iter("img")).attrs["src"]
    assert links == [img]
    assert "fig+a2 (censored).png" in next(figs[1].iter("figcaption")).text  # no caption: the file name
    md = report["md_text"]
    assert f"*{fake.CAPTION_A1.replace('&', '&')}* (fig_a1.png)" in md


def test_the_source_tables_are_in_both_reports(report):
    section = report["dom"].find_id("exp-fake-alpha")
    tables = [t for t in section.iter("table") if "source-table" in t.classes]
    assert len(tables) == 1 and "Table 9: printed and ours" in tables[0].text
    assert "0.009336" in tables[0].text and "not expected to agree" in section.text
    assert "| ours | 0.009336 | 0.0208 |" in report["md_text"]


def test_na_claims_say_why_they_cannot_be_measured(report):
    dom = report["dom"]
    claims = report["written"]["fake-alpha"]["claims"]
    na = [i for i, c in enumerate(claims, start=1) if c["holds"] is None]
    target = dom.find_id(f"exp-fake-alpha-claim-{na[0]}")
    assert "cannot be measured" in target.text and "the figure has no axis scale" in target.text
    assert "n/a (not measurable)" in dom.text and "unchecked" not in report["html"]


def test_whose_claim_it_is():
    from tobitkf.experiments._claims import ClaimError, check_claim, claim_origin

    assert claim_origin({"claim": "Fig 3.2: the TKF tracks the truth"}) == "source"
    assert claim_origin({"claim": "(not in the source) the ADF is within 1.02x"}) == "package"
    assert claim_origin({"claim": "  (Not in the source, which shows Fig 3.3 only) x"}) == "package"
    assert claim_origin({"claim": "the PF converges"}, "tobitkf (not in the sources): particle filter") == "package"
    assert claim_origin({"claim": "(not in the source) x", "origin": "source"}) == "source"  # explicit wins
    assert claim_origin("not a dict") == "source"
    base = {"claim": "c", "quantity": "q", "measured": "m", "test": "t", "tolerance": "tol", "holds": True}
    assert check_claim({**base, "origin": "package"})["origin"] == "package"
    with pytest.raises(ClaimError, match="origin must be one of"):
        check_claim({**base, "origin": "ours"})
