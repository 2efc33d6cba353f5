"""One file written atomically: a temporary file beside the target, flushed to disk, then
renamed over it, so a reader never sees half a file; the inputs a call was given, and
a file's SHA-256."""

from __future__ import annotations

import contextlib
import contextvars
import hashlib
import os
import re
import secrets
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import OptionError

if TYPE_CHECKING:
    pass

#: emccdcal wrote it and lists its files.
STORE_MARKER = ".emccdcal-store.json"
_LOCK = ".emccdcal-lock"
_TOKEN = 12  # hex digits of the random part of a temporary name


class OutputError(OptionError):
    """An output that cannot or may not be written (one line naming it)."""


def _temporary_pattern(name: str) -> re.Pattern:
    """Names of the temporary files and directories this module makes for ``name``."""
    return re.compile(rf"^\.{re.escape(name)}\.[0-9a-f]{{{_TOKEN}}}\.(tmp|partial|old)")


def _temporary(path: Path, kind: str) -> Path:
    # The suffix is kept: writers such as matplotlib and tifffile choose the format by it.
    suffix = path.suffix if kind == "tmp" else ""
    return path.parent / f".{path.name}.{secrets.token_hex(_TOKEN // 2)}.{kind}{suffix}"


def _umask() -> int:
    # os.umask can only be read by setting it; this is process-wide but immediate.
    mask = os.umask(0)
    os.umask(mask)
    return mask


# --------------------------------------------------------------------------------------
# One file
# --------------------------------------------------------------------------------------
_STAGING: contextvars.ContextVar = contextvars.ContextVar("emccdcal_staging", default=None)
_GIVEN_INPUTS: contextvars.ContextVar = contextvars.ContextVar("emccdcal_inputs", default=())


@contextlib.contextmanager
def given_inputs(paths: Iterable):
    """Every :class:`Output` opened inside the block also refuses to write over (or inside
    a store among) ``paths``: the command line registers every path a verb was given,
    except its output, so that no verb can write over something it read, whether or not
    it names it."""
    token = _GIVEN_INPUTS.set(tuple(Path(p) for p in paths))
    try:
        yield
    finally:
        _GIVEN_INPUTS.reset(token)


def atomic_write(path, write: Callable[[str], object], *, durable: bool = True) -> Path:
    """Write ``path`` through ``write(tmp)`` to a temporary file beside it, then replace it.

    The temporary file is in the same directory (so the rename is atomic), gets the mode a
    new file would get (0o666 less the umask: a shared result stays readable by
    colleagues), is flushed to disk before the rename and removed if anything fails, so a
    reader never sees a half-written file and an interrupted write leaves any earlier file
    of the same name intact. The parent directory is created if missing. Inside an
    :class:`Output` that stages its files, the file is renamed into place only when the
    whole output is complete.

    Parameters
    ----------
    path : str or Path
        The file to write.
    write : callable
        Called with the temporary file's path (str); writes the whole content there.
    durable : bool
        Flush the file to disk before the rename (default). Without it the rename is
        still atomic for any reader, but a power cut may lose the new content: for a
        record rewritten every second while the disk is busy, whose fsync would wait for
        the disk (seconds, under gigabytes of other writes).

    Returns
    -------
    Path
        ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        tmp = _temporary(path, "tmp")
        try:
            os.close(os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666))
            break
        except FileExistsError:  # pragma: no cover - 48 random bits
            continue
    try:
        write(str(tmp))
        os.chmod(tmp, 0o666 & ~_umask())  # some writers recreate the file
        if durable:
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
        staging = _STAGING.get()
        if staging is not None and staging.holds(path):
            staging.add(path, tmp)
        else:
            os.replace(tmp, path)
    except OSError as exc:  # a full disk, a quota, storage gone read-only: one line
        tmp.unlink(missing_ok=True)
        raise OutputError(
            f"{path}: cannot be written ({_reason(exc)}); any earlier file of "
            "that name is as it was"
        ) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def atomic_write_text(path, text: str, *, durable: bool = True) -> Path:
    """:func:`atomic_write` of a text file (UTF-8)."""
    return atomic_write(
        path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"), durable=durable
    )


def file_sha256(path) -> str:
    """SHA-256 (hex) of a file's bytes, read in 1 MiB blocks (any size, bounded memory)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _reason(exc: OSError) -> str:
    return exc.strerror or " ".join(str(exc).split())
