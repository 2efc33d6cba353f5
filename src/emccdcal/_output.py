"""Writing files: one policy for every verb that writes, and the text that goes into them.

Every file emccdcal writes goes through :func:`atomic_write` (text through
:func:`atomic_write_text`): a temporary file beside the target, flushed to disk, then
renamed over it, so a reader never sees half a file. Every verb's output is opened as an
:class:`Output`, which applies the rest of the policy in one place:

* **checked before any computing**: the output can be written, is a folder where a folder
  is meant and a file where a file is, and is none of the run's inputs;
* **never replaced by accident**: an existing output is refused unless ``overwrite``, and
  with ``overwrite`` the old output is replaced only when the new one is complete (every
  file of the run is staged, then renamed into place together);
* **one run at a time**: a lock held while the verb runs; a second run into the same output
  gets one line and exit 2;
* **nothing foreign deleted**: a directory is only removed when it is a store emccdcal
  wrote (its marker lists every file in it) and holds nothing else; a killed run's
  temporary files (named by this module, with 48 random bits) are removed by the next run
  into the same output, and those of a failed run at once.

Result files know themselves: :func:`write_netcdf` puts the SHA-256 of a NetCDF file's
bytes in a block before them, and :func:`read_netcdf` checks it before parsing anything.

Text taken from a file (a serial, a model, a label) is data: :func:`slug` makes a file
name of it, :func:`toml_line` writes it as a TOML value, :func:`comment` puts it on one
comment line.
"""

from __future__ import annotations

import contextlib
import contextvars
import hashlib
import json
import os
import re
import secrets
import shutil
import sys
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING

from . import _files
from .errors import InputError, OptionError

if TYPE_CHECKING:
    import xarray

try:  # POSIX; elsewhere the lock is an exclusively created file
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None

__all__ = [
    "atomic_write",
    "atomic_write_text",
    "file_sha256",
    "Output",
    "OutputError",
    "staged",
    "remove_leftovers",
    "given_inputs",
    "slug",
    "comment",
    "toml_line",
    "plain_text",
    "escape_controls",
    "STORE_MARKER",
    "write_netcdf",
    "read_netcdf",
    "verify_checksum",
    "CHECKSUM_BLOCK",
]

#: The file inside a store (a directory written as one output, e.g. ``.zarr``) that says
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


# --------------------------------------------------------------------------------------
# A verb's output
# --------------------------------------------------------------------------------------
def _resolved(path) -> Path:
    try:
        return Path(path).resolve()
    except (OSError, RuntimeError) as exc:  # a symlink loop
        raise OutputError(f"{path}: cannot be resolved ({' '.join(str(exc).split())})") from None


def _same(a: Path, b: Path) -> bool:
    """Whether two paths name one file (also through links)."""
    if _resolved(a) == _resolved(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def _is_inside(inner: Path, outer: Path) -> bool:
    return _resolved(inner).is_relative_to(_resolved(outer))


def _files_below(folder: Path) -> set[str]:
    return {p.relative_to(folder).as_posix() for p in folder.rglob("*") if not p.is_dir()}


def _is_our_store(folder: Path) -> bool:
    """A directory emccdcal wrote as one output, holding nothing it did not write."""
    try:
        listed = set(_files.load_json(folder / STORE_MARKER, what="store marker")["files"])
    except (InputError, KeyError, TypeError):
        return False
    return _files_below(folder) <= listed | {STORE_MARKER}


#: The folder inside a ``.partial`` directory that the store's writer fills.
_PARTIAL_CONTENT = "store"


def _is_our_partial(folder: Path) -> bool:
    """A ``.partial`` directory :meth:`Output.store` made: its marker says so, and it
    holds nothing but the marker and the content folder the writer was given."""
    try:
        marked = _files.load_json(folder / STORE_MARKER, what="store marker").get("partial") is True
    except (InputError, AttributeError):
        return False
    return marked and {p.name for p in folder.iterdir()} <= {STORE_MARKER, _PARTIAL_CONTENT}


def _remove_ours(path: Path) -> None:
    """Remove a temporary file, or a temporary store of this module: a ``.partial`` that
    :meth:`Output.store` made (the content a run was writing) or an ``.old`` that still
    holds only what emccdcal wrote (the store it replaced); a directory of any other name
    or content is left alone."""
    if path.is_dir() and not path.is_symlink():
        kind = re.search(r"\.[0-9a-f]{12}\.(partial|old)$", path.name)
        if kind and (_is_our_partial(path) if kind.group(1) == "partial" else _is_our_store(path)):
            shutil.rmtree(path, ignore_errors=True)
    elif re.search(r"\.[0-9a-f]{12}\.tmp", path.name):  # only files are written as .tmp
        path.unlink(missing_ok=True)


#: What a file emccdcal wrote holds besides a result's checksum block (:data:`_MAGIC`):
#: a summary's version key, a report's generator tag (in reports before it, a
#: provenance row).
_SIGNATURES = (
    b'"emccdcal_version"',
    b'<meta name="generator" content="emccdcal',
    b"<td>written by emccdcal</td>",
)


def written_by_emccdcal(path) -> bool:
    """Whether ``path`` is a file emccdcal wrote (a result, a summary, a report): the
    test before an earlier run's file is removed, so that a user's file of the same name
    is never deleted."""
    path = Path(path)
    if not path.is_file() or path.is_symlink():
        return False
    signatures = (_MAGIC, *_SIGNATURES)
    longest = max(map(len, signatures))
    tail = b""
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            text = tail + block
            if any(sig in text for sig in signatures):
                return True
            tail = text[-longest:]
    return False


class _Staging:
    """Files written below ``root`` (or ``root`` itself) held back as temporary files,
    to be renamed into place together by :meth:`commit`."""

    def __init__(self, root: Path, *, single_file: bool = False):
        self.root, self.single_file = Path(root), single_file
        self.files: dict[Path, Path] = {}  # final -> temporary

    def holds(self, path: Path) -> bool:
        if self.single_file:
            return _resolved(path) == _resolved(self.root)
        return _is_inside(path, self.root)

    def add(self, path: Path, tmp: Path) -> None:
        old = self.files.pop(path, None)
        if old is not None:
            old.unlink(missing_ok=True)
        self.files[path] = tmp

    def commit(self) -> list[Path]:
        """Rename every staged file into place (each rename atomic, the old file of that
        name replaced only now); the finals, in the order written."""
        done = []
        for final, tmp in list(self.files.items()):
            remove_leftovers(final, keep=tmp)
            os.replace(tmp, final)
            del self.files[final]
            done.append(final)
        return done

    def discard(self) -> None:
        for tmp in self.files.values():
            tmp.unlink(missing_ok=True)
        self.files.clear()


@contextlib.contextmanager
def staged(root, *, single_file: bool = False):
    """Within the block, every :func:`atomic_write` below ``root`` is staged; on leaving
    the block normally the files are renamed into place, on an error they are removed."""
    staging = _Staging(root, single_file=single_file)
    token = _STAGING.set(staging)
    try:
        yield staging
    except BaseException:
        _STAGING.reset(token)
        staging.discard()
        raise
    _STAGING.reset(token)
    try:
        staging.commit()
    finally:
        staging.discard()


def remove_leftovers(target, keep: Path | None = None) -> None:
    """Remove the temporary files a killed run left for ``target`` (never ``keep``)."""
    target = Path(target)
    pattern = _temporary_pattern(target.name)
    if target.parent.is_dir():
        for p in target.parent.iterdir():
            if pattern.match(p.name) and p != keep:
                _remove_ours(p)


#: Locks this process holds: path -> [descriptor, depth].
_HELD: dict[str, list] = {}


class _Lock:
    """An exclusive lock on an output for the duration of a run (``flock`` on a hidden
    file beside or inside it; released by the kernel if the process dies)."""

    def __init__(self, path: Path, output: str, unwritable: str):
        self.path, self.output, self.what, self.fd = path, output, unwritable, None

    def acquire(self) -> None:
        key = str(self.path.resolve())
        if key in _HELD:  # this process holds it already (a verb around a library call)
            _HELD[key][1] += 1
            self.fd = _HELD[key][0]
            return
        try:
            while True:
                if fcntl is None:  # pragma: no cover - Windows
                    self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o666)
                    break
                # never through a link: the lock is truncated, and removed at the end
                fd = os.open(
                    self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o666
                )
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    holder = os.read(fd, 64).decode("ascii", "replace").strip()
                    os.close(fd)
                    raise OutputError(
                        f"{self.output}: another emccdcal run is writing it"
                        + (f" (process {holder})" if holder.isdigit() else "")
                        + "; wait for it to finish or choose another output"
                    ) from None
                # The holder before us may have removed the file between our open and
                # our lock: then the lock is on a file nobody else will find.
                try:
                    if os.fstat(fd).st_ino == os.stat(self.path).st_ino:
                        self.fd = fd
                        break
                except FileNotFoundError:
                    pass
                os.close(fd)
            held_by = os.pread(self.fd, 64, 0).strip() if fcntl is not None else b""
            if held_by and not held_by.isdigit():  # a lock holds a process id, or nothing
                os.close(self.fd)
                self.fd = None
                raise OutputError(
                    f"{self.path}: a file emccdcal did not write stands where "
                    "its lock goes; it is left as it is: move it, or choose "
                    "another output"
                )
            os.ftruncate(self.fd, 0)
            os.write(self.fd, str(os.getpid()).encode())
            _HELD[key] = [self.fd, 1]
        except FileExistsError:  # pragma: no cover - Windows
            raise OutputError(
                f"{self.output}: another emccdcal run is writing it (or one "
                f"was killed: then remove {self.path})"
            ) from None
        except OSError as exc:
            raise OutputError(f"{self.what} ({_reason(exc)})") from None

    def release(self) -> None:
        if self.fd is None:
            return
        key = str(self.path.resolve())
        held = _HELD.get(key)
        if held is not None and held[1] > 1:
            held[1] -= 1
        else:
            _HELD.pop(key, None)
            self.path.unlink(missing_ok=True)
            os.close(self.fd)
        self.fd = None


class Output:
    """Where one run writes, under the policy of the module docstring.

    Use it as a context manager around everything the run computes and writes::

        with Output(out, kind="folder", inputs=[movie], overwrite=overwrite,
                    names=["camera.yaml"]):
            ...   # every atomic_write below ``out`` is staged; published on success

    Parameters
    ----------
    path : str or Path
        The output.
    kind : {"folder", "file", "store"}
        A folder the run writes files into; one file; or a store, a directory written
        whole as one output (a ``.zarr``), see :meth:`store`.
    inputs : iterable of path
        The run's inputs, which the output may not be or replace (more can be given later
        with :meth:`refuse_inputs`, still before any computing).
    overwrite : bool
        Replace an existing output (else it is refused).
    names : iterable of str
        For a folder: the files the run will write, as far as known up front; an earlier
        run's files of those names are refused without ``overwrite``. Files found only
        when the run publishes are checked then, before anything is renamed.
    stage : bool
        Stage every file written below the output until the run completes (default).
        ``False`` for a run that publishes as it goes (a calibration keeps its tiles).
    what : str
        How to name the output in messages (default: its path).

    Raises
    ------
    OutputError
        On entering: the output cannot be written, is of the wrong kind, is an input, is
        locked by another run, or exists and ``overwrite`` is false (or it is a directory
        emccdcal did not write).
    """

    def __init__(
        self,
        path,
        *,
        kind: str = "folder",
        inputs: Iterable = (),
        overwrite: bool = False,
        names: Iterable[str] = (),
        stage: bool = True,
        what: str | None = None,
    ):
        if kind not in ("folder", "file", "store"):
            raise ValueError(f"unknown output kind {kind!r}")
        self.path, self.kind, self.overwrite = Path(path), kind, overwrite
        self.names = tuple(names)
        self._inputs = [Path(p) for p in (*inputs, *_GIVEN_INPUTS.get())]
        self._what = what or str(self.path)
        self._noun = {"folder": "directory", "file": "file", "store": "store"}[kind]
        self._staging = (
            _Staging(self.path, single_file=kind == "file") if stage and kind != "store" else None
        )
        self._lock = None
        self._created: list[Path] = []
        self._token = None
        self._new_store = None
        self._old_store = None

    # ---- opening ---------------------------------------------------------------------
    def __enter__(self) -> Output:
        self._check_kind()
        folder = self.path if self.kind == "folder" else self.path.parent
        self._created = [d for d in (folder, *folder.parents) if not d.exists()]
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(
                f"{self._what}: cannot write the output {self._noun} ({_reason(exc)})"
            ) from None
        lock = folder / _LOCK if self.kind == "folder" else folder / f".{self.path.name}{_LOCK}"
        self._lock = _Lock(lock, self._what, f"{self._what}: cannot write the output {self._noun}")
        self._lock.acquire()  # also the check that the output can be written
        try:
            self.refuse_inputs(self._inputs)
            self._check_existing()
            for name in self.names if self.kind == "folder" else (self.path.name,):
                remove_leftovers(self.path / name if self.kind == "folder" else self.path)
        except BaseException:
            self._lock.release()
            self._remove_created()
            raise
        if self._staging is not None:
            self._token = _STAGING.set(self._staging)
        return self

    def _check_kind(self) -> None:
        p = self.path
        if self.kind == "folder" and p.exists() and not p.is_dir():
            raise OutputError(f"{self._what}: is a file; give a folder to write into")
        if self.kind == "file" and p.is_dir():
            raise OutputError(f"{self._what}: is a folder; give the name of the file to write")
        if self.kind != "folder" and not p.name:
            raise OutputError(f"{self._what}: give the name of the output to write")
        _resolved(p)

    def refuse_inputs(self, inputs: Iterable, names: Iterable[str] | None = None) -> None:
        """Raise :class:`OutputError` where the output would write over one of ``inputs``
        (the same file, also through a link; for a store, a file inside it; for a folder,
        one of ``names``, default those given when opening). The inputs are remembered,
        and checked again against every file the run publishes."""
        names = self.names if names is None else tuple(names)
        for given in inputs:
            if Path(given) not in self._inputs:
                self._inputs.append(Path(given))
        for p in self._inputs:  # every input known, against the names now given
            if self.kind == "folder":
                hit = any(_same(self.path / n, p) for n in names)
            else:
                hit = _same(self.path, p) or (self.kind == "store" and _is_inside(p, self.path))
            # nothing is written inside an input store (a folder read as one file: .zarr);
            # a plain folder given as input (scan's) may hold the output
            hit = hit or (
                p.is_dir()
                and p.suffix.lower() == ".zarr"
                and (_same(self.path, p) or _is_inside(self.path, p))
            )
            if hit:
                raise OutputError(
                    f"{self._what}: would write over {p}, an input of this "
                    "run; choose another output"
                )

    def _check_existing(self) -> None:
        p = self.path
        if self.kind == "folder":
            there = [n for n in self.names if (p / n).exists()]
            if there and not self.overwrite:
                raise OutputError(
                    f"{self._what}: holds {', '.join(there)} of an earlier run; "
                    "pass --overwrite to replace them, or choose another folder"
                )
            return
        if not (p.exists() or p.is_symlink()):
            return
        if not self.overwrite:
            raise OutputError(
                f"{self._what}: exists; pass --overwrite to replace it, or choose another name"
            )
        if p.is_dir() and not (self.kind == "store" and _is_our_store(p)):
            raise OutputError(
                f"{self._what}: is a folder emccdcal did not write (or holds "
                "files it did not write); --overwrite never removes such a "
                "folder: remove it yourself or choose another name"
            )

    # ---- while running -----------------------------------------------------------------
    def store(self) -> Path:
        """A new, empty temporary directory for a store's content; it takes the output's
        place when the run completes. It lies inside a marked ``.partial`` directory, so
        that a killed run's is known for ours (a writer may empty the folder it is given:
        zarr's ``mode="w"`` does)."""
        if self.kind != "store":
            raise ValueError("store() is for an Output of kind 'store'")
        self._new_store = _temporary(self.path, "partial")
        self._new_store.mkdir()
        (self._new_store / STORE_MARKER).write_text(json.dumps({"partial": True}))
        content = self._new_store / _PARTIAL_CONTENT
        content.mkdir()
        return content

    # ---- the end -----------------------------------------------------------------------
    def __exit__(self, exc_type, exc, tb) -> bool:
        if self._token is not None:
            _STAGING.reset(self._token)
            self._token = None
        try:
            if exc_type is None:
                self._publish()
        finally:
            if self._staging is not None:
                self._staging.discard()
            for tmp in (self._new_store, self._old_store):
                if tmp is not None and tmp.exists():
                    _remove_ours(tmp)
            self._lock.release()
            if exc_type is not None:
                self._remove_created()
        return False

    def _remove_created(self) -> None:
        """The folders this run created, where a failed run left them empty."""
        for d in self._created:
            try:
                d.rmdir()
            except OSError:
                break

    def _publish(self) -> None:
        if self._staging is not None:
            # Every conflict is found before anything is renamed: nothing old is lost.
            for final in self._staging.files:
                for p in self._inputs:
                    if _same(final, p):
                        raise OutputError(
                            f"{final}: is {p}, an input of this run; choose another output"
                        )
                if final.is_dir():
                    raise OutputError(f"{final}: is a folder; it is not replaced by a file")
                if final.exists() and not self.overwrite:
                    raise OutputError(f"{final}: exists; pass --overwrite to replace it")
            self._staging.commit()
        if self._new_store is not None:
            content = self._new_store / _PARTIAL_CONTENT
            files = sorted(_files_below(content) | {STORE_MARKER})
            (content / STORE_MARKER).write_text(json.dumps({"files": files}))
            if self.path.is_dir() and not self.path.is_symlink():
                if not _is_our_store(self.path):  # something was put there meanwhile
                    raise OutputError(
                        f"{self._what}: files that emccdcal did not write "
                        "appeared in it during the run; it is left as it is"
                    )
                self._old_store = _temporary(self.path, "old")
                os.replace(self.path, self._old_store)
            elif self.path.exists() or self.path.is_symlink():
                self.path.unlink()
            os.replace(content, self.path)  # the empty .partial is removed on exit


def _reason(exc: OSError) -> str:
    return exc.strerror or " ".join(str(exc).split())


# --------------------------------------------------------------------------------------
# Result files that know themselves
# --------------------------------------------------------------------------------------
#: A result file begins with this block (an HDF5 user block, which HDF5 and every NetCDF
#: reader skip): the magic, then the SHA-256 of every byte after the block.
CHECKSUM_BLOCK = 512
_MAGIC = b"emccdcal result file; SHA-256 of the bytes after this 512-byte block: "


def write_netcdf(ds: xarray.Dataset, path) -> None:
    """Write a result dataset as NetCDF-4 (h5netcdf) behind a block holding the SHA-256
    of the file's bytes. Every result file emccdcal writes goes through this (inside an
    atomic write), and :func:`read_netcdf` checks the bytes before parsing any of them,
    so a damaged file is refused, never used, and never parsed (a damaged HDF5 header
    can send a reader into an endless loop)."""
    path = Path(path)
    # A new name of the temporary family of ``path`` (a killed run's is cleaned up by
    # remove_leftovers): never a file someone else has.
    body = _temporary(path, "tmp")
    try:
        ds.to_netcdf(body, engine="h5netcdf")
        digest = hashlib.sha256()
        with open(body, "rb") as src, open(path, "wb") as out:
            out.write(b" " * CHECKSUM_BLOCK)
            for block in iter(lambda: src.read(1 << 20), b""):
                digest.update(block)
                out.write(block)
            out.seek(0)
            out.write((_MAGIC + digest.hexdigest().encode() + b"\n").ljust(CHECKSUM_BLOCK))
    finally:
        body.unlink(missing_ok=True)


def verify_checksum(path, what: str = "result") -> str:
    """Raise :class:`~emccdcal.errors.InputError` unless ``path`` begins with the block
    of :func:`write_netcdf` and its bytes match the SHA-256 written there. Returns the
    SHA-256 of the whole file (as :func:`file_sha256`, from the same one read)."""
    p = Path(path)
    try:
        with open(p, "rb") as f:
            head = f.read(CHECKSUM_BLOCK)
            whole, digest = hashlib.sha256(head), hashlib.sha256()
            for block in iter(lambda: f.read(1 << 20), b""):
                digest.update(block)
                whole.update(block)
    except OSError as exc:
        raise InputError(f"{p}: cannot be read ({_reason(exc)})") from None
    recorded = head[len(_MAGIC) : len(_MAGIC) + 64]
    if len(head) < CHECKSUM_BLOCK or not head.startswith(_MAGIC):
        raise InputError(
            f"{p}: not an emccdcal {what} file, or damaged (it does not begin "
            "with emccdcal's checksum block; files of earlier emccdcal "
            f"versions have none): make the {what} again"
        )
    if recorded != digest.hexdigest().encode():
        raise InputError(
            f"{p}: damaged: its bytes do not match the checksum it was written "
            f"with; make the {what} again or restore it from a copy"
        )
    return whole.hexdigest()


@contextlib.contextmanager
def _quiet_unraisable():
    # h5netcdf's File.__del__ on a file it failed to open prints "Exception ignored ...
    # Traceback" to stderr; the failure itself is reported as one line. The caller
    # appends to the list it is given when the opening failed: only then is the failed
    # reader collected here (a collection of a large process costs ~0.3 s).
    import gc

    hook = sys.unraisablehook
    sys.unraisablehook = lambda unraisable: None
    failed = []
    try:
        yield failed
    finally:
        if failed:
            gc.collect()
        sys.unraisablehook = hook


def read_netcdf(path, *, what: str = "result") -> xarray.Dataset:
    """A NetCDF file written by :func:`write_netcdf`: its checksum verified
    (:func:`verify_checksum`), then loaded, the whole file's SHA-256 in
    ``ds.encoding["sha256"]``; damage is one :class:`~emccdcal.errors.InputError` naming
    the file."""
    import xarray as xr

    p = Path(path)
    sha256 = verify_checksum(p, what)
    error = None
    with _quiet_unraisable() as failed:  # until a failed reader is collected
        try:
            with xr.open_dataset(p, engine="h5netcdf") as f:
                ds = f.load()
        except (
            OSError,
            ValueError,
            TypeError,
            KeyError,
            RuntimeError,
            AttributeError,
            IndexError,
        ) as exc:
            error = f"{exc.__class__.__name__}: {' '.join(str(exc).split())}"
            failed.append(True)
    if error is not None:
        raise InputError(f"{p}: not a readable NetCDF file ({error})")
    ds.encoding["sha256"] = sha256
    return ds


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
