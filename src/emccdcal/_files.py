"""Reading a file a user hands in, within bounds: one loader for each text format.

A manifest, a plan, a session record, a localization tool's settings: each is data from
outside, and none of it may hang a verb, exhaust its memory or reach it as a number
beyond what a float holds. Every such file is read here:

* :func:`read_bytes` refuses what is not a regular file (a FIFO would wait forever, a
  device such as ``/dev/zero`` never ends, a folder is not a file) before opening it, and
  a file larger than the format's budget;
* :func:`load_json`, :func:`load_toml`, :func:`load_yaml` and :func:`load_xml` parse with
  a bound on nesting depth, YAML with a small budget of aliases (a kilobyte of nested
  aliases, the "billion laughs", would expand to gigabytes) and XML without entity
  declarations; whole numbers beyond 64 bits, and NaN or infinity where JSON forbids
  them, are refused;
* every failure is one :class:`~emccdcal.errors.InputError` line naming the file.

Standard library only, PyYAML imported where a YAML file is read.
"""

from __future__ import annotations

import json
import math
import os
import stat
from pathlib import Path

from .errors import InputError

__all__ = [
    "read_bytes",
    "read_text",
    "load_json",
    "load_toml",
    "load_yaml",
    "load_xml",
    "check_tree",
    "check_mat",
    "MAX_TEXT_BYTES",
    "MAX_MAT_BYTES",
    "MAX_DEPTH",
    "MAX_YAML_ALIASES",
    "MAX_INTEGER",
]

#: Largest text file read (a manifest, a plan, a tool's settings are kilobytes).
MAX_TEXT_BYTES = 8 << 20
#: Deepest nesting of lists and tables accepted.
MAX_DEPTH = 32
#: Most YAML aliases accepted (configuration files written by hand use a few at most).
MAX_YAML_ALIASES = 64
#: Largest whole number accepted (a 64-bit integer: TOML's own range).
MAX_INTEGER = 2**63 - 1


def _kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def read_bytes(path, *, what: str = "file", max_bytes: int = MAX_TEXT_BYTES) -> bytes:
    """The bytes of a regular file of at most ``max_bytes``, or one line saying why not.

    Examples
    --------
    >>> read_bytes("/dev/null")
    Traceback (most recent call last):
    ...
    emccdcal.errors.InputError: '/dev/null': is a device, not a file
    """
    path = Path(path)
    try:
        info = os.stat(path)
    except FileNotFoundError:
        raise InputError(f"'{path}': no such {what}") from None
    except OSError as exc:  # a loop of links, a name too long, no permission
        raise InputError(f"'{path}': cannot read this {what} ({exc.strerror or exc})") from None
    if not stat.S_ISREG(info.st_mode):
        raise InputError(f"'{path}': is {_kind(info.st_mode)}, not a {what}")
    if info.st_size > max_bytes:
        raise InputError(
            f"'{path}': {info.st_size} bytes, more than a {what} holds ({max_bytes} at most)"
        )
    # O_NONBLOCK: were it swapped for a FIFO since the check, opening does not wait
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as exc:
        raise InputError(f"'{path}': cannot read this {what} ({exc.strerror or exc})") from None
    with os.fdopen(fd, "rb") as f:
        if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
            raise InputError(f"'{path}': is not a regular file, not a {what}")
        data = f.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise InputError(f"'{path}': more than a {what} holds ({max_bytes} bytes at most)")
    return data


def read_text(path, *, what: str = "file", max_bytes: int = MAX_TEXT_BYTES) -> str:
    """A regular file's UTF-8 text (:func:`read_bytes`)."""
    raw = read_bytes(path, what=what, max_bytes=max_bytes)
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"'{path}': not UTF-8 text (byte {exc.start}); a {what} is text") from None


def check_tree(doc, path, *, max_depth: int = MAX_DEPTH, finite: bool = True):
    """``doc`` (parsed lists, tables and scalars) checked: nested at most ``max_depth``
    deep, whole numbers within 64 bits, floats finite (unless not ``finite``: TOML
    writes nan and inf on purpose, and the reader of each key refuses them by name).
    Returns ``doc``."""
    stack = [(doc, 0)]
    while stack:
        node, depth = stack.pop()
        if depth > max_depth:
            raise InputError(f"'{path}': nested more than {max_depth} levels deep")
        if isinstance(node, dict):
            stack.extend((v, depth + 1) for v in node.values())
            stack.extend((k, depth + 1) for k in node if not isinstance(k, str))
        elif isinstance(node, (list, tuple)):
            stack.extend((v, depth + 1) for v in node)
        elif isinstance(node, bool):
            continue
        elif isinstance(node, int) and abs(node) > MAX_INTEGER:
            raise InputError(
                f"'{path}': a whole number of {len(str(abs(node)))} digits, beyond 64 bits"
            )
        elif finite and isinstance(node, float) and not math.isfinite(node):
            raise InputError(f"'{path}': a number that is not finite ({node!r})")
    return doc


def _nesting(text: str, opening: str, closing: str) -> int:
    """The deepest bracket nesting of ``text`` (strings not told apart: an upper bound),
    measured before a recursive parser meets it."""
    depth = deepest = 0
    for ch in text:
        if ch in opening:
            depth += 1
            deepest = max(deepest, depth)
        elif ch in closing:
            depth -= 1
    return deepest


def _refuse_constant(name):
    raise ValueError(f"{name} is not a number JSON allows")


def load_json(path, *, what: str = "JSON file", text: str | None = None):
    """A JSON file (or its ``text``), bounded; NaN and Infinity refused."""
    text = read_text(path, what=what) if text is None else text
    if _nesting(text, "[{", "]}") > 4 * MAX_DEPTH:
        raise InputError(f"'{path}': nested more than {MAX_DEPTH} levels deep")
    try:
        doc = json.loads(text, parse_constant=_refuse_constant)
    except (ValueError, RecursionError) as exc:
        raise InputError(f"'{path}': not a readable {what} ({str(exc).splitlines()[0]})") from None
    return check_tree(doc, path)


def load_toml(path, *, what: str = "TOML file", text: str | None = None):
    """A TOML file (or its ``text``), bounded."""
    try:
        import tomllib
    except ModuleNotFoundError:  # pragma: no cover - Python 3.10
        import tomli as tomllib

    text = read_text(path, what=what) if text is None else text
    if _nesting(text, "[{", "]}") > 4 * MAX_DEPTH:
        raise InputError(f"'{path}': nested more than {MAX_DEPTH} levels deep")
    try:
        doc = tomllib.loads(text)
    except (tomllib.TOMLDecodeError, RecursionError, ValueError) as exc:
        reason = " ".join(str(exc).split()) or type(exc).__name__
        if "integer string conversion" in reason:  # Python's advice is not the user's
            reason = "a whole number of thousands of digits"
        err = InputError(f"'{path}': not a readable {what} ({reason})")
        err.reason = reason  # the parser's words, for a caller with its own prefix
        raise err from None
    return check_tree(doc, path, finite=False)


def load_yaml(path, *, what: str = "YAML file", text: str | None = None):
    """A YAML file (or its ``text``) by PyYAML's safe loader (no object is ever built
    from a tag), with at most :data:`MAX_YAML_ALIASES` aliases and bounded nesting."""
    import yaml

    text = read_text(path, what=what) if text is None else text

    class _Bounded(yaml.SafeLoader):
        aliases = 0

        def compose_node(self, parent, index):
            if self.check_event(yaml.AliasEvent):
                self.aliases += 1
                if self.aliases > MAX_YAML_ALIASES:
                    raise InputError(
                        f"'{path}': more than {MAX_YAML_ALIASES} YAML aliases (an expansion bomb?)"
                    )
            depth = getattr(self, "_depth", 0) + 1
            if depth > MAX_DEPTH:
                raise InputError(f"'{path}': nested more than {MAX_DEPTH} levels deep")
            self._depth = depth
            try:
                return super().compose_node(parent, index)
            finally:
                self._depth = depth - 1

    loader = None
    try:
        loader = _Bounded(text)  # its reader refuses a control character at once (a NUL)
        doc = loader.get_single_data()
    except yaml.YAMLError as exc:
        raise InputError(f"'{path}': not a readable {what} ({str(exc).splitlines()[0]})") from None
    except RecursionError:
        raise InputError(f"'{path}': nested more than {MAX_DEPTH} levels deep") from None
    finally:
        if loader is not None:
            loader.dispose()
    return check_tree(doc, path)


def load_xml(path, *, what: str = "XML file", text: bytes | None = None):
    """An XML file's root element (or of ``text``), without a document type or entity
    declarations (the way XML expands a few bytes into gigabytes), bounded."""
    import xml.etree.ElementTree as ET

    raw = read_bytes(path, what=what) if text is None else text
    if b"<!DOCTYPE" in raw.upper() or b"<!ENTITY" in raw.upper():
        raise InputError(f"'{path}': declares a document type or entities; a {what} needs none")
    try:
        root = ET.fromstring(raw)
    except ET.ParseError as exc:
        raise InputError(f"'{path}': not readable XML ({exc})") from None
    deepest = 0
    stack = [(root, 1)]
    while stack:
        node, depth = stack.pop()
        deepest = max(deepest, depth)
        if deepest > MAX_DEPTH:
            raise InputError(f"'{path}': nested more than {MAX_DEPTH} levels deep")
        stack.extend((child, depth + 1) for child in node)
    return root


#: Largest MATLAB file read, and the most its variables may hold once decompressed.
MAX_MAT_BYTES = 64 << 20


def check_mat(path, *, max_bytes: int = MAX_MAT_BYTES) -> None:
    """Refuse a MATLAB (v5) file whose variables would take more than ``max_bytes`` once
    decompressed (a few hundred kilobytes of compressed zeros become gigabytes), counting
    each compressed element by a bounded decompression before SciPy reads anything."""
    import struct
    import zlib

    raw = read_bytes(path, what="MATLAB file", max_bytes=max_bytes)
    if len(raw) < 128:
        raise InputError(f"'{path}': not a MATLAB file (shorter than its header)")
    order = {b"IM": "<", b"MI": ">"}.get(raw[126:128])
    if order is None:  # v7.3 (HDF5) and others: SciPy says what they are
        return
    total, at = 0, 128
    while at + 8 <= len(raw):
        kind, size = struct.unpack(order + "II", raw[at : at + 8])
        body = raw[at + 8 : at + 8 + size]
        if kind == 15:  # miCOMPRESSED: count what it inflates to, never more than allowed
            inflate = zlib.decompressobj()
            try:
                while body and total <= max_bytes:
                    total += len(inflate.decompress(body, 1 << 20))
                    body = inflate.unconsumed_tail
            except zlib.error as exc:
                raise InputError(f"'{path}': a damaged compressed variable ({exc})") from None
        else:
            total += size
        if total > max_bytes:
            raise InputError(
                f"'{path}': its variables hold more than {max_bytes >> 20} MiB "
                "once decompressed; a settings file is kilobytes"
            )
        at += 8 + size + (-size % 8 if kind != 15 else 0)
