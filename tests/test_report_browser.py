"""Render the report in headless Chromium: every figure loads, a phone-width page does not
scroll sideways, and a screenshot is saved as the CI artifact.

The report itself has no scripts. To see whether its images load, the test writes a probe
page next to ``index.html`` (same folder, so the same relative links): the report's own
markup with ``loading="lazy"`` turned eager, one deliberately broken image as a negative
control, and a small script that, once the page has loaded, writes each image's
``naturalWidth`` and the page's scroll width into a ``<pre>``. ``chromium --dump-dom``
prints the DOM after that script ran.

Screenshots go to ``<repo>/results/report_screenshot.png`` (desktop) and
``report_screenshot_phone.png`` (412 px wide), or to ``$TOBITKF_SCREENSHOT_DIR``.
Skipped when no Chromium binary is installed.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from tobitkf.report import write_report

_spec = importlib.util.spec_from_file_location("_report_fake", Path(__file__).with_name("_report_fake.py"))
fake = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(fake)

CHROMIUM = next(
    (
        p
        for p in (
            os.environ.get("CHROMIUM"),
            shutil.which("chromium"),
            shutil.which("chromium-browser"),
            shutil.which("google-chrome"),
        )
        if p
    ),
    None,
)
pytestmark = pytest.mark.skipif(
    CHROMIUM is None,
    reason="headless browser test: no chromium binary found "
    "(install it with `apt-get install -y chromium`, or set $CHROMIUM)",
)

BROKEN = "no-such-figure.png"
PROBE = """<script>
window.addEventListener("load", function () {
  var imgs = Array.prototype.slice.call(document.images);
  var out = document.createElement("pre");
  out.id = "probe";
  out.textContent = JSON.stringify({
    images: imgs.map(function (i) { return [i.getAttribute("src"), i.complete ? i.naturalWidth : -1]; }),
    scrollWidth: document.documentElement.scrollWidth,
    innerWidth: window.innerWidth
  });
  document.body.appendChild(out);
});
</script>"""


def _chromium(tmp_path: Path, *args: str, width: int, height: int) -> subprocess.CompletedProcess:
    cmd = [
        CHROMIUM,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--disable-dev-shm-usage",
        "--hide-scrollbars",
        "--force-device-scale-factor=1",
        f"--user-data-dir={tmp_path / 'chromium-profile'}",
        f"--window-size={width},{height}",
        "--virtual-time-budget=5000",
        *args,
    ]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)


def _probe(tmp_path: Path, root: Path, *, width: int) -> dict:
    html_text = (root / "index.html").read_text(encoding="utf-8")
    assert "<script" not in html_text.lower()
    page = html_text.replace(' loading="lazy"', ' loading="eager"')
    page = page.replace("</body>", f'<img src="{BROKEN}" alt="negative control">{PROBE}</body>')
    probe_file = root / "_probe.html"
    probe_file.write_text(page, encoding="utf-8")
    try:
        res = _chromium(tmp_path, "--dump-dom", probe_file.as_uri(), width=width, height=900)
    finally:
        probe_file.unlink()
    m = re.search(r'<pre id="probe">(.*?)</pre>', res.stdout, re.S)
    assert m, f"probe did not run; chromium exit {res.returncode}, stderr tail: {res.stderr[-600:]}"
    return json.loads(m.group(1).replace("&quot;", '"').replace("&amp;", "&").replace("&lt;", "<").replace("&gt;", ">"))


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    root = tmp_path_factory.mktemp("results")
    written = fake.build_fake_results(root)
    write_report(root)
    return root, written


@pytest.mark.parametrize("width", [1200, 412])
def test_every_figure_loads_and_the_page_fits_the_width(tmp_path, results, width):
    root, written = results
    got = _probe(tmp_path, root, width=width)
    n_figures = sum(len(m.get("figures", [])) for m in written.values())
    loaded = {src: w for src, w in got["images"]}
    assert len(got["images"]) == n_figures + 1
    assert loaded.pop(BROKEN) == 0, "negative control: a missing image must report naturalWidth 0"
    assert all(w > 0 for w in loaded.values()), f"figures that did not load: {loaded}"
    # nothing but the tables' own scroll boxes may be wider than the window (phone: 412 px)
    assert got["scrollWidth"] <= got["innerWidth"], got


def _shot_dir() -> Path:
    env = os.environ.get("TOBITKF_SCREENSHOT_DIR")
    return Path(env) if env else Path(__file__).resolve().parents[1] / "results"


@pytest.mark.parametrize(
    ("name", "width", "height"), [("report_screenshot.png", 1200, 2600), ("report_screenshot_phone.png", 412, 2600)]
)
def test_screenshot_renders(tmp_path, results, name, width, height):
    import matplotlib.image as mpimg

    root, _ = results
    out = _shot_dir()
    out.mkdir(parents=True, exist_ok=True)
    shot = tmp_path / name
    res = _chromium(tmp_path, f"--screenshot={shot}", (root / "index.html").as_uri(), width=width, height=height)
    assert shot.is_file(), f"no screenshot; chromium exit {res.returncode}, stderr tail: {res.stderr[-600:]}"
    img = mpimg.imread(shot)
    assert img.shape[:2] == (height, width)
    # a rendered page, not a blank one: dark text pixels and the red "not held" colour both appear
    rgb = img[..., :3]
    assert (rgb.mean(axis=-1) < 0.3).mean() > 1e-3
    red = (rgb[..., 0] > 0.55) & (rgb[..., 1] < 0.2) & (rgb[..., 2] < 0.2)
    assert red.sum() > 20
    assert np.ptp(rgb) > 0.5
    shutil.copyfile(shot, out / name)
