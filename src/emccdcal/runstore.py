"""The output directory of a long run: finished tiles persist, outputs are published as a set.

A calibration of a full sensor is a sequence of tiles (bands of rows). With an output
directory, every finished tile is written at once to ``OUT/.emccdcal-run/`` beside a
*fingerprint* of the run's inputs (the manifest's content, every data file's size and
modification time, the method, its options, the package version, the tiling), so that a
run killed at any point loses only the tiles in flight:

* ``resume=True`` continues an interrupted run, and refuses one whose fingerprint
  differs, saying what changed;
* ``overwrite=True`` discards the kept tiles of an earlier run, and its result files
  once the new ones are complete;
* with neither, a directory that holds a finished or an unfinished run is refused: a
  new run is never mixed into an old one.

The final files (``calibration.nc``, ``summary.json`` ...) are published together
(:func:`publish`, then :func:`remove_run`): all are written to temporary files first, then each is
renamed over its old version, and an old file the new set does not have is removed, so
at no moment is a result missing and a killed run leaves the old set. The run directory
goes last. Whether the directory can be written, and that no other run is writing it,
is found out by the caller's :class:`emccdcal._output.Output` before any computing.
"""

from __future__ import annotations

import contextlib
import json
import re
import tempfile
from pathlib import Path

import numpy as np

from . import _files
from ._output import atomic_write, remove_leftovers, staged, written_by_emccdcal
from ._util import one_line
from .errors import EmccdcalError, InputError, OptionError

__all__ = ["RunStore", "RUN_DIR", "RESULT_FILES", "RunInterrupted", "publish", "remove_run"]

#: Where an unfinished run keeps its tiles, inside the output directory.
RUN_DIR = ".emccdcal-run"
#: The files of a finished result (the report is written beside it when asked for).
RESULT_FILES = ("calibration.nc", "summary.json", "report.html")
_FINGERPRINT = "fingerprint.json"


class RunInterrupted(KeyboardInterrupt):
    """Ctrl-C during a run; the message says what was kept and how to go on."""


class RunStore:
    """The output directory of one run (see the module docstring).

    Parameters
    ----------
    out : str or Path
        The output directory (created with its parents if missing).
    fingerprint : dict
        JSON-serialisable description of everything the result depends on.
    resume, overwrite : bool
        What to do with an earlier run in ``out`` (not both).
    """

    def __init__(self, out, fingerprint: dict, *, resume: bool = False, overwrite: bool = False):
        if resume and overwrite:
            raise OptionError("give resume or overwrite, not both")
        self.out = Path(out)
        self.run_dir = self.out / RUN_DIR
        self.fingerprint = json.loads(json.dumps(fingerprint))  # as it reads back
        self._made_out = not self.out.exists()
        self._check_writable()
        finished = [n for n in RESULT_FILES if (self.out / n).exists()]
        unfinished = (self.run_dir / _FINGERPRINT).is_file()
        if unfinished and not (resume or overwrite) and not self.tiles():
            # a run that kept no tile (refused before its first): nothing to resume, and
            # removed where it is ours only (remove_run); one not ours is still refused
            remove_run(self.out)
            unfinished = (self.run_dir / _FINGERPRINT).is_file()
        if overwrite:  # the old result stays until the new one is published
            remove_run(self.out)
        elif resume:
            if not unfinished:
                what = "a finished result" if finished else "no interrupted run"
                raise OptionError(
                    f"{self.out}: nothing to resume ({what} there); run without "
                    "--resume" + (" and with --overwrite" if finished else "")
                )
            self._check_same_run()
        elif finished or unfinished:
            what = (
                f"an interrupted run ({len(self.tiles())} tile(s) kept)"
                if unfinished
                else f"a finished result ({', '.join(finished)})"
            )
            raise OptionError(
                f"{self.out} holds {what}: pass --resume to continue an "
                "interrupted run or --overwrite to replace it"
            )
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self._remove_temporaries()
        atomic_write(
            self.run_dir / _FINGERPRINT,
            lambda p: Path(p).write_text(json.dumps(self.fingerprint, indent=1)),
        )

    def discard(self) -> None:
        """Remove what this run kept, after a failure that a rerun of the same inputs
        would repeat (every pixel failed): nothing is left to resume, and the output
        directory goes too where this run made it and nothing else is in it."""
        remove_run(self.out)
        if self._made_out:
            with contextlib.suppress(OSError):  # not empty: kept
                self.out.rmdir()

    # ---- opening ---------------------------------------------------------------------
    def _check_writable(self) -> None:
        try:
            self.out.mkdir(parents=True, exist_ok=True)
            # A new file of a name nobody has (created exclusively, removed on closing).
            with tempfile.TemporaryFile(dir=self.out):
                pass
        except OSError as exc:
            raise EmccdcalError(
                f"{self.out}: cannot write the output directory: {one_line(exc)}"
            ) from None
        if not self.out.is_dir():  # pragma: no cover - mkdir would have failed
            raise EmccdcalError(f"{self.out}: not a directory")

    def _check_same_run(self) -> None:
        try:
            old = _files.load_json(self.run_dir / _FINGERPRINT, what="run fingerprint")
        except InputError as exc:
            raise EmccdcalError(
                f"{self.run_dir / _FINGERPRINT}: unreadable "
                f"({one_line(exc)}); pass --overwrite to start again"
            ) from None
        changed = _differences(old, self.fingerprint)
        if changed:
            raise OptionError(
                f"{self.out}: cannot resume, the run differs from the interrupted "
                f"one in {'; '.join(changed[:4])}"
                + (f" and {len(changed) - 4} more" if len(changed) > 4 else "")
                + "; pass --overwrite to start again"
            )

    def _remove_temporaries(self) -> None:
        """Temporary files of a run that was killed while writing (``atomic_write``'s)."""
        for p in self.run_dir.glob("tile-*.npz"):
            remove_leftovers(p)
        remove_leftovers(self.run_dir / _FINGERPRINT)
        for name in RESULT_FILES:
            remove_leftovers(self.out / name)

    # ---- tiles -------------------------------------------------------------------------
    @staticmethod
    def _tile_name(key: str) -> str:
        return f"tile-{key}.npz"

    def tiles(self) -> list[str]:
        """Keys of the tiles kept."""
        return sorted(p.name[5:-4] for p in self.run_dir.glob("tile-*.npz"))

    def save_tile(self, key: str, arrays: dict) -> None:
        """Keep one finished tile (a dict of arrays), atomically."""

        def write(path):
            with open(path, "wb") as fh:
                np.savez(fh, **arrays)

        atomic_write(self.run_dir / self._tile_name(key), write)

    def load_tile(self, key: str) -> dict:
        """The arrays of a kept tile."""
        with np.load(self.run_dir / self._tile_name(key), allow_pickle=False) as f:
            return {k: f[k] for k in f.files}


def publish(out, writers: dict, *, stale=()) -> dict:
    """Write files into ``out`` as one set: every new file is complete before any is
    renamed over its old version; then the files named in ``stale`` that the new set
    lacks (an earlier run's of the same set, which the caller's output policy let it
    replace) are removed where emccdcal wrote them, so the directory never mixes two
    runs; a user's file of such a name is left."""
    out = Path(out)
    with staged(out):
        for name, write in writers.items():
            atomic_write(out / name, write)
    for name in stale:
        if name not in writers and written_by_emccdcal(out / name):
            (out / name).unlink()
    return {name: out / name for name in writers}


def remove_run(out) -> None:
    """Remove the kept tiles of a run in ``out``: only a run directory that a run's
    fingerprint marks as emccdcal's, and in it only the files a run writes there (its
    tiles, its temporary files, then the fingerprint, last, so that a kill half-way
    leaves the directory still known for ours); a run directory holding other files is
    left, less those."""
    run_dir = Path(out) / RUN_DIR
    fingerprint = run_dir / _FINGERPRINT
    if not run_dir.is_dir() or run_dir.is_symlink() or not written_by_emccdcal(fingerprint):
        return
    ours = re.compile(r"^(tile-pixels-\d{9}-\d{9}\.npz|\..+\.[0-9a-f]{12}\.tmp.*)$")
    for p in run_dir.iterdir():
        if p.is_file() and not p.is_symlink() and ours.match(p.name):
            p.unlink()
    fingerprint.unlink()
    with contextlib.suppress(OSError):  # not empty: something else is there, kept
        run_dir.rmdir()


def _differences(old: dict, new: dict, prefix: str = "") -> list[str]:
    """What differs between two fingerprints, as short phrases."""
    out = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            out += _differences(a, b, f"{prefix}{key}: ")
        elif a != b:
            out.append(f"{prefix}{key} ({_short(a)} then, {_short(b)} now)")
    return out


def _short(value) -> str:
    text = json.dumps(value)
    return text if len(text) <= 40 else text[:37] + "..."
