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

from .files import (
    STORE_MARKER,
    OutputError,
    atomic_write,
    atomic_write_text,
    file_sha256,
    given_inputs,
)
from .results import CHECKSUM_BLOCK, read_netcdf, verify_checksum, write_netcdf
from .text import comment, escape_controls, plain_text, slug, toml_line
from .verb import Output, remove_leftovers, staged, written_by_emccdcal
from .verb import _same as same_file

__all__ = [
    "atomic_write",
    "atomic_write_text",
    "file_sha256",
    "Output",
    "OutputError",
    "staged",
    "remove_leftovers",
    "given_inputs",
    "written_by_emccdcal",
    "same_file",
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
