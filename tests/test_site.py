"""The documentation site: what it must hold, and every page opened in a real browser.

The source checks need no build: the API page names every public name, the gallery has
its seven workflows. The built site (``make docs``, docs/_build/html, or
``$EMCCDCAL_SITE``) is served on 127.0.0.1 and a harness page opens every HTML page of it
in headless Chromium, one after another in a frame of the same origin; for each it
records the images as the browser decoded them, the links as the page holds them once
its scripts ran, and its element ids. Then every image must have decoded, and every link
into the site must reach a file that is there and, where it names an anchor, an element
with that id. Skips where the site is not built or Chromium is missing (``.ci/run``
builds the site before the tests).
"""

from __future__ import annotations

import ast
import html
import json
import os
import re
import threading
from functools import partial
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import unquote, urlsplit

import pytest

import emccdcal
from emccdcal.cli import build_parser, reference_parser

import chromium

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
SITE = Path(os.environ.get("EMCCDCAL_SITE", DOCS / "_build" / "html"))
# The workflows the gallery shows, each a script executed when the site is built.
GALLERY = [
    "plot_gain_series",
    "plot_chained_phi",
    "plot_noise_model",
    "plot_plan_and_acquire",
    "plot_gain_from_darks",
    "plot_export_and_audit",
    "plot_bead_validation",
]

needs_source = pytest.mark.skipif(
    not (DOCS / "conf.py").exists(), reason="not a source tree (an installed package)"
)
needs_site = pytest.mark.skipif(
    not (SITE / "index.html").exists(), reason=f"the site is not built ({SITE}; make docs)"
)


def _api_names() -> set[str]:
    """The names docs/api.rst documents: its autosummary entries and ``.. data::``."""
    names, listing = set(), False
    for line in (DOCS / "api.rst").read_text(encoding="utf-8").splitlines():
        if line.startswith(".. data::"):
            names.add(line.split("::")[1].strip())
        elif line.startswith(".. autosummary::"):
            listing = True
        elif listing and line.startswith("   ") and not line.strip().startswith(":"):
            names.add(line.strip())
        elif line and not line.startswith(" "):
            listing = False
    return names


@needs_source
def test_the_api_page_names_every_public_name():
    documented = _api_names()
    missing = [
        n
        for n in emccdcal.__all__
        if n not in documented and not (n == "noise" and "model.noise" in documented)
    ]
    assert not missing, f"docs/api.rst leaves out {missing}"
    assert "EmccdcalError" in documented and "calibrate" in documented


@needs_source
def test_the_gallery_holds_the_seven_workflows():
    scripts = sorted(p.stem for p in (ROOT / "examples").glob("plot_*.py"))
    assert sorted(GALLERY) == scripts
    for name in scripts:  # each a script with a title and at least one figure
        text = (ROOT / "examples" / f"{name}.py").read_text(encoding="utf-8")
        doc = ast.get_docstring(ast.parse(text))
        assert doc and "=====" in doc, name
        assert "plt.show()" in text, name


def _serve(root: Path, harness: str):
    """The site's files on 127.0.0.1 (a free port), and the harness page at /__harness__."""
    _Site.harness = harness.encode()
    server = ThreadingHTTPServer(("127.0.0.1", 0), partial(_Site, directory=str(root)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


class _Site(SimpleHTTPRequestHandler):
    harness = b""

    def do_GET(self):
        if self.path != "/__harness__":
            return super().do_GET()
        self.send_response(200)
        self.send_header("Content-Type", "text/html; charset=utf-8")
        self.send_header("Content-Length", str(len(self.harness)))
        self.end_headers()
        self.wfile.write(self.harness)

    def log_message(self, *args):  # no line on stderr per request
        pass


HARNESS = """<!DOCTYPE html><html><body><iframe id="f" width="1200" height="900"></iframe>
<script>
const pages = %s;
const found = {};
const frame = document.getElementById("f");
function visit(i) {
  if (i >= pages.length) {
    const out = document.createElement("pre");
    out.id = "probe-result";
    out.textContent = JSON.stringify(found);
    document.body.appendChild(out);
    return;
  }
  frame.onload = () => {
    const doc = frame.contentDocument;
    found[pages[i]] = {
      images: Array.from(doc.images).map((img) => ({src: img.currentSrc || img.src,
        ok: img.complete && img.naturalWidth > 0})),
      links: Array.from(doc.querySelectorAll("a[href]")).map((a) => a.href),
      ids: Array.from(doc.querySelectorAll("[id]")).map((e) => e.id),
    };
    visit(i + 1);
  };
  frame.src = pages[i];
}
visit(0);
</script></body></html>"""


@pytest.fixture(scope="module")
def site_in_browser(tmp_path_factory):
    """Every page of the built site as Chromium found it: ``{page: {images, links, ids}}``
    and the address it was served at."""
    if chromium.CHROMIUM is None:
        pytest.skip(chromium.NOT_HERE)
    pages = sorted(
        p.relative_to(SITE).as_posix() for p in SITE.rglob("*.html") if "_sources" not in p.parts
    )
    server = _serve(SITE, HARNESS % json.dumps(["/" + p for p in pages]))
    try:
        base = f"http://127.0.0.1:{server.server_address[1]}"
        dom = chromium.run(
            tmp_path_factory.mktemp("site"),
            "--virtual-time-budget=120000",
            "--dump-dom",
            f"{base}/__harness__",
            timeout=300,
        )
    finally:
        server.shutdown()
        server.server_close()
    m = re.search(r'<pre id="probe-result">(.*?)</pre>', dom, re.DOTALL)
    assert m, "the harness did not finish: a page did not load"
    found = json.loads(html.unescape(m.group(1)))
    assert sorted(found) == ["/" + p for p in pages]
    return found, base


@pytest.mark.slow
@needs_site
def test_every_image_of_the_site_decodes(site_in_browser):
    found, _ = site_in_browser
    broken = [(page, i["src"]) for page, f in found.items() for i in f["images"] if not i["ok"]]
    assert not broken, broken
    # the gallery's figures are among them: every example drew at least one
    for name in GALLERY:
        images = found[f"/auto_examples/{name}.html"]["images"]
        assert any("sphx_glr_" + name in i["src"] for i in images), name


@pytest.mark.slow
@needs_site
def test_every_internal_link_of_the_site_resolves(site_in_browser):
    found, base = site_in_browser
    broken = []
    for page, f in found.items():
        for href in f["links"]:
            if not href.startswith(base):
                continue  # another site, or mailto:
            parts = urlsplit(href)
            path = unquote(parts.path)
            target = SITE / path.lstrip("/")
            if target.is_dir():
                target, path = target / "index.html", path.rstrip("/") + "/index.html"
            if not target.is_file():
                broken.append((page, href, "no such file"))
            elif (
                parts.fragment
                and path in found
                and unquote(parts.fragment) not in found[path]["ids"]
            ):
                broken.append((page, href, "no such anchor"))
    assert not broken, broken[:20]


@pytest.mark.slow
@needs_site
def test_the_site_documents_every_public_name_and_verb(site_in_browser):
    found, _ = site_in_browser
    api = found["/api.html"]
    for name in emccdcal.__all__:
        anchor = "emccdcal.model.noise" if name == "noise" else f"emccdcal.{name}"
        assert any(anchor in link for link in api["links"]) or anchor in api["ids"], name
    verbs = next(a for a in build_parser()._actions if a.dest == "verb").choices
    cli_ids = " ".join(found["/cli.html"]["ids"])
    missing = [v for v in verbs if f"emccdcal-{v}" not in cli_ids and v not in cli_ids]
    assert not missing, missing


@pytest.mark.slow
@needs_site
def test_the_command_reference_shows_every_verbs_options():
    """Each verb's section of the built page holds each of its options (the sub-parsers
    are built for it: a run builds only its own verb's)."""
    page = html.unescape((SITE / "cli.html").read_text(encoding="utf-8"))

    def text(markup):  # inline markup (the usage's highlighting splits "--" from
        # "overwrite") goes without a trace, block markup as a space
        return re.sub(r"<[^>]+>", " ", re.sub(r"</?(span|code|kbd|em|strong)\b[^>]*>", "", markup))

    for needed in ("--e-per-adu", "--setpoint", "--to", "--target-se", "--scheduler"):
        assert needed in text(page), needed
    verbs = next(a for a in reference_parser()._actions if a.dest == "verb").choices
    starts = {verb: page.find(f'<section id="emccdcal-{verb}"') for verb in verbs}
    assert -1 not in starts.values(), starts
    for verb, sub in verbs.items():
        later = [at for at in starts.values() if at > starts[verb]]
        section = text(page[starts[verb] : min(later, default=len(page))])
        options = [
            o
            for a in sub._actions
            for o in a.option_strings
            if o.startswith("--") and o != "--help"
        ]
        lost = [o for o in options if o not in section]
        assert not lost, f"{verb}: {lost}"
