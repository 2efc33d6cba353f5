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
def test_the_gallery_holds_twelve_examples_each_through_the_python_api():
    """At least twelve scripts, each with a title and a figure, none reaching into the
    command line's module: a notebook user's code, not a terminal's."""
    scripts = sorted((ROOT / "examples").glob("plot_*.py"))
    assert len(scripts) >= 12, [p.name for p in scripts]
    for path in scripts:
        text = path.read_text(encoding="utf-8")
        tree = ast.parse(text)
        doc = ast.get_docstring(tree)
        assert doc and "=====" in doc, path.name
        assert "plt.show()" in text, path.name
        imported = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                imported |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                imported |= {f"{node.module}.{a.name}" for a in node.names}
        assert not any(name.startswith("emccdcal.cli") for name in imported), path.name
        assert "emccdcal" in imported, path.name


def _text(page: Path) -> str:
    """A built page's text: its markup gone, its entities decoded."""
    markup = page.read_text(encoding="utf-8")
    markup = re.sub(r"<(script|style)\b.*?</\1>", " ", markup, flags=re.S)
    # inline markup (a highlighter's spans) goes without a trace, block markup as a space
    markup = re.sub(r"</?(span|code|kbd|em|strong|a)\b[^>]*>", "", markup)
    return " ".join(html.unescape(re.sub(r"<[^>]+>", " ", markup)).split())


@needs_site
def test_the_site_has_five_sections_a_glossary_and_an_installation_page():
    header = (SITE / "index.html").read_text(encoding="utf-8")
    nav = header[header.index('class="bd-header') :]
    nav = nav[: nav.index("</nav>")]
    sections = re.findall(r'class="nav-link[^"]*"[^>]*href="([^"]+)"[^>]*>\s*([^<]+?)\s*<', nav)
    sections += re.findall(r'href="([^"]+)"[^>]*class="nav-link[^"]*"[^>]*>\s*([^<]+?)\s*<', nav)
    titles = [t for _, t in dict.fromkeys(sections)]
    for wanted in ("Getting started", "User guide", "Gallery", "Reference", "Development"):
        assert wanted in titles, titles
    assert len(set(titles)) == 5, titles  # nothing else, nothing behind "More"
    # each section's pages in its sidebar
    for section, page in (
        ("getting-started", "installation.html"),
        ("user-guide", "results.html"),
        ("reference", "api.html"),
        ("development", "plugins.html"),
    ):
        markup = (SITE / f"{section}.html").read_text(encoding="utf-8")
        sidebar = markup[markup.index("bd-docs-nav") :]  # the section's navigation
        assert f'href="{page}"' in sidebar[: sidebar.index("</nav>")], section
    glossary = (SITE / "glossary.html").read_text(encoding="utf-8")
    for term in ("Bernoulli cascade", "non-centred MAP", "Fieller bounds", "Fisher information"):
        assert f'id="term-{term.replace(" ", "-")}"' in glossary, term
    install = _text(SITE / "installation.html")
    assert "make demo" in install and ".venv/bin/emccdcal" in install and "pipx install" in install
    assert "cupy-cuda12x" in install and "CUDA 13" in install
    for page in SITE.rglob("*.html"):  # no page claims an install from an index
        text = _text(page)
        assert "pip install emccdcal" not in text and "emccdcal[" not in text, page


@needs_site
def test_no_page_of_the_site_names_another_page_by_its_path():
    """Every cross-reference is a link: no "(docs/quality.md)" in the text of any page
    (the docstrings' and the command line's paths become links as the site is built)."""
    pages = sorted(SITE.rglob("*.html"))
    assert len(pages) > 30
    named = {
        str(page.relative_to(SITE)): sorted(
            set(re.findall(r"docs/[a-z0-9-]+\.(?:md|rst)", _text(page)))
        )
        for page in pages
    }
    assert not {k: v for k, v in named.items() if v}


@needs_site
def test_every_public_name_is_documented_with_its_parameters_and_an_example():
    missing = {}
    for name in emccdcal.__all__:
        if name in ("__version__", "noise"):
            continue
        page = SITE / "generated" / f"emccdcal.{name}.html"
        if not page.exists():
            missing[name] = "no page"
            continue
        text = _text(page)
        kind = getattr(emccdcal, name)
        needs = ["Examples"]
        if not (isinstance(kind, type) and issubclass(kind, (Exception, Warning))):
            needs.append("Parameters" if callable(kind) and not isinstance(kind, type) else "")
            if isinstance(kind, type):
                needs[-1] = "Attributes" if "Attributes" in text else "Parameters"
        lacking = [n for n in needs if n and n not in text]
        if lacking:
            missing[name] = lacking
    assert not missing, missing


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
    for name in sorted(p.stem for p in (ROOT / "examples").glob("plot_*.py")):
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
