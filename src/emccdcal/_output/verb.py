"""A verb's output (:class:`Output`): checked before any computing, never replaced by
accident, one run at a time, nothing foreign deleted (the package's docstring)."""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

from .. import _files
from ..errors import InputError

if TYPE_CHECKING:
    pass

try:  # POSIX; elsewhere the lock is an exclusively created file
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None

from .files import (
    _GIVEN_INPUTS,
    _LOCK,
    _STAGING,
    STORE_MARKER,
    OutputError,
    _reason,
    _temporary,
    _temporary_pattern,
)
from .results import _MAGIC


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
