"""Result files where NetCDF opens: an xarray backend that knows them.

A result file (``calibration.nc``, ``posterior.nc``, ``intensities.nc``) begins with a
512-byte block holding the SHA-256 of the bytes after it (:func:`emccdcal._output.write_netcdf`),
which hides the HDF5 signature that xarray looks for when it guesses a file's engine.
This backend, registered under the entry-point group ``xarray.backends``, recognises
that block, verifies the checksum, and opens the rest with h5netcdf: so
``xarray.open_dataset("OUT/calibration.nc")`` opens a result with no engine named, and a
damaged one is refused as :func:`emccdcal.load_result` refuses it.
"""

from __future__ import annotations

from xarray.backends import BackendEntrypoint

from ._output.results import _MAGIC, verify_checksum

__all__ = ["EmccdcalBackend"]


class EmccdcalBackend(BackendEntrypoint):
    """Open an emccdcal result file (its checksum verified first)."""

    description = "emccdcal result files (NetCDF-4 behind a SHA-256 block)"
    open_dataset_parameters = ("filename_or_obj", "drop_variables")

    def guess_can_open(self, filename_or_obj) -> bool:
        try:
            with open(filename_or_obj, "rb") as f:
                return f.read(len(_MAGIC)) == _MAGIC
        except (OSError, TypeError, ValueError):
            return False

    def open_dataset(self, filename_or_obj, *, drop_variables=None):
        import xarray as xr

        verify_checksum(filename_or_obj)
        return xr.open_dataset(filename_or_obj, engine="h5netcdf", drop_variables=drop_variables)
