"""Result files that know themselves: :func:`write_netcdf` puts the SHA-256 of a NetCDF
file's bytes in a block before them, and :func:`read_netcdf` checks it before parsing."""

from __future__ import annotations

import contextlib
import hashlib
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import InputError

if TYPE_CHECKING:
    import xarray

from .files import _reason, _temporary

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
