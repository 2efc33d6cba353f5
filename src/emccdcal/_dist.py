"""The installed distribution these files came from.

``importlib.metadata`` answers by name with the first distribution of that name on
``sys.path``: an older ``emccdcal-*.dist-info`` earlier on the path (a copy left by
another install, a folder on ``PYTHONPATH``) would give its version and hide every one
of this package's own entry points (its readers, tools and register models). Here the
distribution is the one whose files are these.
"""

from __future__ import annotations

import functools
import importlib.metadata
from pathlib import Path
from urllib.parse import unquote, urlparse

#: This package's folder.
PACKAGE = Path(__file__).resolve().parent


@functools.cache
def own_distribution() -> importlib.metadata.Distribution | None:
    """emccdcal's distribution: among those named ``emccdcal`` on the path, the one that
    installed this folder (its files, or for an editable install the source tree it
    points to); the first one where none says so; None from a source tree not installed."""
    found = list(importlib.metadata.distributions(name="emccdcal"))
    return next((d for d in found if _installed_this(d)), found[0] if found else None)


def version() -> str:
    """The version of :func:`own_distribution` (``"0+unknown"`` where none is installed)."""
    dist = own_distribution()
    return dist.version if dist is not None else "0+unknown"


def _installed_this(dist) -> bool:
    for file in dist.files or ():
        if file.name == "__init__.py" and file.parent.name == PACKAGE.name:
            try:
                if Path(dist.locate_file(file)).resolve() == PACKAGE / "__init__.py":
                    return True
            except OSError:
                continue
    from ._files import load_json
    from .errors import InputError

    text = dist.read_text("direct_url.json")
    try:  # an editable install: the source tree it points to holds this folder
        doc = load_json("direct_url.json", what="install record", text=text) if text else {}
        url = doc.get("url", "") if isinstance(doc, dict) else ""
    except InputError:
        return False
    parsed = urlparse(url)
    if parsed.scheme != "file":
        return False
    return Path(unquote(parsed.path)).resolve() in PACKAGE.parents
