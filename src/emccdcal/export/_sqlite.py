"""The calibration database's file: its schema, where it lives by default, and opening
it (one writer at a time, read-only where a verb only reads, never a file that is not
ours)."""

from __future__ import annotations

import contextlib
import os
import secrets
import sqlite3
import sys
from pathlib import Path


from ..errors import EmccdcalError, InputError


_SCHEMA = """
CREATE TABLE IF NOT EXISTS calibration (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    camera TEXT NOT NULL,
    readout TEXT NOT NULL,
    date TEXT NOT NULL,
    added TEXT NOT NULL,
    method TEXT NOT NULL,
    em_model TEXT NOT NULL,
    path TEXT NOT NULL,
    sha256 TEXT NOT NULL UNIQUE,
    note TEXT NOT NULL DEFAULT '',
    summary TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS gain (
    calibration_id INTEGER NOT NULL REFERENCES calibration(id) ON DELETE CASCADE,
    setpoint REAL NOT NULL,
    median REAL NOT NULL,
    se REAL,
    n INTEGER NOT NULL,
    PRIMARY KEY (calibration_id, setpoint)
);
CREATE INDEX IF NOT EXISTS calibration_camera ON calibration(camera, readout, date);
CREATE TABLE IF NOT EXISTS gain_check (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    camera TEXT NOT NULL,
    readout TEXT NOT NULL,
    date TEXT NOT NULL,
    added TEXT NOT NULL,
    setpoint REAL NOT NULL,
    em_gain REAL NOT NULL,
    se REAL NOT NULL,
    em_model TEXT NOT NULL,
    events REAL NOT NULL,
    note TEXT NOT NULL DEFAULT '',
    record TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS gain_check_camera ON gain_check(camera, readout, date);
"""


def default_path() -> Path:
    """``$EMCCDCAL_DB``, else ``calibrations.sqlite`` in the user's data directory
    (``$XDG_DATA_HOME/emccdcal``, ``~/.local/share/emccdcal``; ``~/Library/Application
    Support/emccdcal`` on macOS; ``%LOCALAPPDATA%\\emccdcal`` on Windows)."""
    if os.environ.get("EMCCDCAL_DB"):
        return Path(os.environ["EMCCDCAL_DB"])
    if sys.platform == "win32":
        base = Path(os.environ.get("LOCALAPPDATA", Path.home() / "AppData" / "Local"))
    elif sys.platform == "darwin":
        base = Path.home() / "Library" / "Application Support"
    else:
        base = Path(os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share")
    return base / "emccdcal" / "calibrations.sqlite"


#: The tables by which a file is known as a calibration database.
_TABLES = {"calibration", "gain"}


def _connect(db, *, write: bool = False) -> sqlite3.Connection:
    """The database. To read, an existing emccdcal database is opened read-only (nothing
    is created, nothing of the file changes; a file on read-only storage as immutable);
    to write (``db add``, ``gain-check --record``), a missing one is created. A file that
    is not an emccdcal database (another program's SQLite file, notes, a FIFO) is refused
    either way and left as it was."""
    path = Path(db) if db is not None else default_path()
    exists = path.exists()
    if exists and not path.is_file():
        raise InputError(f"{path}: not a calibration database (not a regular file)")
    if exists:
        _require_ours(path)
    if not write:
        if not exists:
            raise InputError(
                f"{path}: no calibration database here ('emccdcal db add RESULT "
                "--db PATH' creates one); give --db PATH or set EMCCDCAL_DB"
            )
        return _read_only(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(
            f"{path.parent}: cannot create the calibration database's folder "
            f"({exc.strerror or exc}); give --db PATH or set EMCCDCAL_DB"
        ) from None
    if not os.access(path.parent, os.W_OK) or (exists and not os.access(path, os.W_OK)):
        raise InputError(
            f"{path}: the calibration database cannot be written here (read-only "
            "file or folder); give --db PATH or set EMCCDCAL_DB"
        )
    if not exists:
        _create(path)
    try:
        con = sqlite3.connect(path, timeout=60, isolation_level=None)
        con.execute("PRAGMA foreign_keys=ON")
        con.executescript(_SCHEMA)  # tables added since the file was made
    except sqlite3.DatabaseError as exc:
        raise InputError(f"{path}: not a usable calibration database ({exc})") from None
    con.row_factory = sqlite3.Row
    return con


@contextlib.contextmanager
def _opened(db, *, write: bool = False):
    """The database (:func:`_connect`) for one job, closed after it; SQLite's errors and
    undecodable rows of a damaged file become one line naming the file."""
    con = _connect(db, write=write)
    try:
        yield con
    except EmccdcalError:
        raise
    except (sqlite3.DatabaseError, ValueError) as exc:  # ValueError: text, JSON, numbers
        path = Path(db) if db is not None else default_path()
        raise InputError(
            f"{path}: the calibration database cannot be read ({exc}): damaged? "
            "restore it from a copy, or give --db a new path"
        ) from None
    finally:
        con.close()


def _create(path: Path) -> None:
    """A new database with its tables, made beside ``path`` and linked into place, so
    that nobody ever sees a database without them (a concurrent writer's is kept)."""
    tmp = path.parent / f".{path.name}.{secrets.token_hex(6)}.tmp"
    try:
        con = sqlite3.connect(tmp, isolation_level=None)
        try:
            con.execute("PRAGMA journal_mode=WAL")
            con.executescript(_SCHEMA)
        finally:
            con.close()  # checkpointed: everything is in the file
        try:
            os.link(tmp, path)
        except FileExistsError:  # made meanwhile by another writer
            pass
    except (OSError, sqlite3.DatabaseError) as exc:
        raise InputError(f"{path}: cannot create the calibration database ({exc})") from None
    finally:
        for leftover in (tmp, tmp.with_name(tmp.name + "-wal"), tmp.with_name(tmp.name + "-shm")):
            leftover.unlink(missing_ok=True)


def _require_ours(path: Path) -> None:
    """Refuse a file that is not an emccdcal database, reading its header and its table
    names only (an immutable read-only look: the file is not changed)."""
    with open(path, "rb") as f:
        header = f.read(16)
    if header != b"SQLite format 3\x00":
        raise InputError(
            f"{path}: not a calibration database (not an SQLite file); give "
            "--db a new path or an emccdcal database"
        )
    try:
        con = _read_only(path)
        try:
            tables = {
                r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type = 'table'")
            }
        finally:
            con.close()
    except (sqlite3.DatabaseError, ValueError) as exc:  # ValueError: undecodable text
        raise InputError(f"{path}: not a usable calibration database ({exc})") from None
    if not _TABLES <= tables:
        raise InputError(
            f"{path}: an SQLite file of another program (no emccdcal "
            "calibration tables); left as it is: give --db a new path"
        )


def _read_only(path: Path) -> sqlite3.Connection:
    """An emccdcal database opened to read: read-only, or immutable where the storage is
    read-only (no journal can be kept there)."""
    writable = os.access(path.parent, os.W_OK) and os.access(path, os.W_OK)
    mode = "ro" if writable else "ro&immutable=1"
    try:
        con = sqlite3.connect(
            f"{path.resolve().as_uri()}?mode={mode}", uri=True, isolation_level=None, timeout=60
        )
    except sqlite3.DatabaseError as exc:
        raise InputError(f"{path}: not a usable calibration database ({exc})") from None
    con.row_factory = sqlite3.Row
    return con
