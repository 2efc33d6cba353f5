"""Text taken from a file (a serial, a model, a label) is data: :func:`slug` makes a file
name of it, :func:`toml_line` writes it as a TOML value, :func:`comment` puts it on one
comment line."""

from __future__ import annotations

import hashlib
import json
import re
from typing import TYPE_CHECKING


if TYPE_CHECKING:
    pass


# --------------------------------------------------------------------------------------
# Text from files
# --------------------------------------------------------------------------------------
def slug(text, *, fallback: str = "unnamed") -> str:
    """A file-name part made from text a file recorded (a serial, a model, a label).

    Letters, digits, ``-`` and ``_`` are kept; every other run of characters becomes one
    ``_``; at most 64 characters. Where anything was changed, a short hash of the text is
    added, so that two different texts never give the same name.

    Examples
    --------
    >>> slug("12345678"), slug("ProEM+: 512B"), slug("../../ESC")
    ('12345678', 'ProEM_512B-...', 'ESC-...')
    """
    text = str(text)
    kept = re.sub(r"[^A-Za-z0-9_-]+", "_", text).strip("_-")[:64] or fallback
    if kept == text:
        return kept
    return f"{kept}-{hashlib.sha256(text.encode('utf-8', 'surrogatepass')).hexdigest()[:8]}"


#: Characters a terminal acts on (all but tab and line feed) and those that reorder text.
_CONTROLS = re.compile("[\x00-\x08\x0b-\x1f\x7f-\x9f\u2028\u2029\u202a-\u202e\u2066-\u2069]")


def escape_controls(text: str) -> str:
    r"""``text`` with every character a terminal would act on written as an escape, line
    breaks kept: what every verb prints passes through it (:func:`emccdcal.cli.main`),
    so that no text from a file can colour, erase or rewrite the terminal.

    Examples
    --------
    >>> escape_controls("OK\x1b[2K\rforged\n")
    'OK\\x1b[2K\\rforged\n'
    """
    return _CONTROLS.sub(lambda m: json.dumps(m.group())[1:-1].replace("\\u00", "\\x"), text)


def plain_text(text) -> str:
    r"""Text from a file as matplotlib draws it literally (a serial ``SN$x$42`` is not
    mathematics), on one line.

    Examples
    --------
    >>> plain_text("SN$\\x$42")
    'SN\\$\\x\\$42'
    """
    return comment(text).replace("$", "\\$")


def comment(text) -> str:
    """Text on one line for a comment (TOML, YAML, a macro) or a terminal's line: line
    breaks and every other control character written as escapes, so nothing after it can
    start a new line or drive the terminal.

    Examples
    --------
    >>> comment("High\\nskip_frames = 290")
    'High\\\\nskip_frames = 290'
    """
    out = []
    for ch in str(text):
        if ch.isprintable() or ch == " ":
            out.append(ch)
        else:
            out.append(json.dumps(ch)[1:-1] if ord(ch) < 0x10000 else f"\\U{ord(ch):08x}")
    return "".join(out)


def toml_line(key: str, value) -> str:
    """One ``key = value`` line of TOML, written by a TOML writer (``tomli_w``): any
    text, also with quotes, line breaks or control characters, stays one value.

    Examples
    --------
    >>> toml_line("name", 'say "hi"\\nskip_frames = 1')
    'name = "say \\\\"hi\\\\"\\\\nskip_frames = 1"'
    """
    import tomli_w

    if hasattr(value, "item") and not isinstance(value, (str, bytes)):  # NumPy scalars
        value = value.item()
    return tomli_w.dumps({key: value}).rstrip("\n")
