"""The HTML report in a real browser: headless Chromium renders every figure and section.

A copy of the report gets a small script that, on load, measures every ``<img>`` (decoded
size, and the spread of its pixel values drawn on a canvas: a blank image has none) and
lists the section ids; ``--dump-dom`` prints the resulting DOM. A screenshot of the top of
the page must not be blank either; it is kept in the test's temporary directory (and
copied into ``$EMCCDCAL_SCREENSHOTS`` when that is set). Skips cleanly without Chromium
(Debian package ``chromium``; ``.ci/run`` installs it).
"""

from __future__ import annotations

import html
import json
import os
import re
import shutil
import warnings
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest

from emccdcal import calibrate
from emccdcal.report import html as report_html

import chromium
from chromium import CHROMIUM, NOT_HERE

# A headless browser is the slowest thing the suite starts: `make test` runs these,
# `make test-fast` does not.
pytestmark = [pytest.mark.slow, pytest.mark.skipif(CHROMIUM is None, reason=NOT_HERE)]
from conftest import write_real_manifest  # noqa: E402  (after the marks it shares)

PROBE = """<script>
window.addEventListener("load", () => {
  const images = Array.from(document.images).map((img) => {
    let sd = -1;
    if (img.complete && img.naturalWidth > 0) {
      const c = document.createElement("canvas");
      c.width = img.naturalWidth; c.height = img.naturalHeight;
      const ctx = c.getContext("2d");
      ctx.drawImage(img, 0, 0);
      const d = ctx.getImageData(0, 0, c.width, c.height).data;
      let n = 0, s = 0, s2 = 0;
      for (let i = 0; i < d.length; i += 4) { const v = d[i] + d[i + 1] + d[i + 2]; n++; s += v; s2 += v * v; }
      sd = Math.sqrt(s2 / n - (s / n) ** 2) / 3;
    }
    const fig = img.closest("figure");
    return {figure: fig ? fig.id : "", width: img.naturalWidth, height: img.naturalHeight,
            shown: img.getBoundingClientRect().width, sd: sd};
  });
  const sections = Array.from(document.querySelectorAll("section[id]")).map((s) => s.id);
  const out = document.createElement("pre");
  out.id = "probe-result";
  out.textContent = JSON.stringify({images: images, sections: sections});
  document.body.appendChild(out);
});
</script>"""


def _chromium(tmp_path, *args):
    return chromium.run(tmp_path, *args)


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    """Chromium starts at all (checked once, on a trivial page; skips where it cannot)."""
    out = _chromium(tmp_path_factory.mktemp("chromium"), "--dump-dom", "data:text/html,<p>ok</p>")
    assert "<p>ok</p>" in out


def check_in_browser(report_path, tmp_path, name):
    """Open a report in Chromium; assert every figure rendered; return the screenshot path."""
    text = report_path.read_text(encoding="utf-8")
    n_img = text.count("<img ")
    probe = tmp_path / f"{name}-probe.html"
    probe.write_text(text.replace("</body>", PROBE + "</body>"), encoding="utf-8")
    dom = _chromium(tmp_path, "--virtual-time-budget=10000", "--dump-dom", probe.as_uri())
    m = re.search(r'<pre id="probe-result">(.*?)</pre>', dom, re.DOTALL)
    assert m, "the probe script did not run"
    found = json.loads(html.unescape(m.group(1)))
    assert {"summary", "warnings", "gof", "figures", "provenance"} <= set(found["sections"])
    assert len(found["images"]) == n_img > 0
    for img in found["images"]:
        assert img["width"] > 100 and img["height"] > 100, img  # decoded
        assert img["shown"] > 100, img  # laid out on the page
        assert img["sd"] > 5, img  # not blank (pixel values 0-255)
    shot = tmp_path / f"{name}.png"
    _chromium(tmp_path, "--window-size=1280,1600", f"--screenshot={shot}", report_path.as_uri())
    pixels = matplotlib.image.imread(shot)
    assert pixels.shape[:2] == (1600, 1280) and pixels[..., :3].std() > 0.05
    keep = os.environ.get("EMCCDCAL_SCREENSHOTS")
    if keep:
        Path(keep).mkdir(parents=True, exist_ok=True)
        shutil.copy(shot, Path(keep) / shot.name)
    return found


def test_demo_report_renders_in_chromium(browser, demo_run, tmp_path):
    run, _ = demo_run
    found = check_in_browser(run["report"], tmp_path, "demo-report")
    assert {"fig-result-1-histograms", "fig-result-2-photon-transfer", "fig-gain"} <= {
        i["figure"] for i in found["images"]
    }


@pytest.mark.real_data
def test_real_proem_report_renders_in_chromium(browser, tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the camera's read noise grows with set-point
        calibrate(
            write_real_manifest(tmp_path, "adu"), "is-adu", out=tmp_path / "is-adu", checks=False
        )  # the slow part; gs keeps its data-quality checks
        # the paper's gamma model, whose 5x misfit the report must show
        calibrate(write_real_manifest(tmp_path, "gs"), "gs", out=tmp_path / "gs", em_model="gamma")
        path = report_html.write_report([tmp_path / "is-adu", tmp_path / "gs"], tmp_path / "r.html")
    found = check_in_browser(path, tmp_path, "proem-report")
    assert len(found["images"]) == 11  # 4 per result and 3 comparisons: nothing left out
    text = path.read_text(encoding="utf-8")
    assert "set-point 5x: " in text and "misfit the noise model" in text  # docs/simulation.md
    assert np.isfinite(float(re.search(r"<td>5×</td><td>([0-9.]+)</td>", text).group(1)))
