"""A result's names: its files, the units and long names of its variables, what every result holds, and the package version that wrote it."""

from __future__ import annotations

import re


CALIBRATION_FILE = "calibration.nc"
SUMMARY_FILE = "summary.json"

#: ``units`` attribute of every standard variable and coordinate (ASCII; "1" is
#: dimensionless, "nat" the natural-log unit of a log-likelihood).
UNITS = {
    "e_per_adu": "e-/ADU",
    "adu_per_e": "ADU/e-",
    "em_gain": "1",
    "photoelectrons": "e-",
    "loglik": "nat",
    "converged": "1",
    "offset": "ADU",
    "read_noise": "ADU",
    "setpoint": "1",
    "level": "1",
    "row": "pixel",
    "col": "pixel",
}

LONG_NAMES = {
    "e_per_adu": "ADU conversion factor phi (photoelectrons per ADU count)",
    "adu_per_e": "inverse ADU conversion factor 1/phi (ADU counts per photoelectron)",
    "em_gain": "true mean EM gain g at each gain set-point",
    "photoelectrons": "mean photoelectrons E per pixel per frame",
    "loglik": "maximised log-likelihood (natural log) of the pixel's data",
    "converged": "fit converged (estimates usable)",
    "offset": "offset S0",
    "read_noise": "read-noise standard deviation sigma",
    "setpoint": "EM gain set-point of the camera",
    "level": "illumination level label",
    "row": "sensor row index",
    "col": "sensor column index",
}

#: Variables every result file must hold (``em_gain`` only where there are set-points).
REQUIRED_VARIABLES = (
    "e_per_adu",
    "e_per_adu_se",
    "photoelectrons",
    "photoelectrons_se",
    "loglik",
    "converged",
)

_UNITS_NOTE = (
    "e_per_adu is phi in photoelectrons per ADU count (e-/ADU), adu_per_e = 1/e_per_adu; "
    "em_gain is dimensionless (1 = no multiplication); photoelectrons in e- per pixel per "
    "frame; offset and read_noise in ADU; loglik in nats; every <name>_se is the standard "
    "error of <name>, in the units of <name>"
)
_RESERVED_ATTRS = (
    "method",
    "emccdcal_version",
    "manifest_sha256",
    "manifest_path",
    "created",
    "units_note",
)
_PIXEL_DIMS = ("row", "col")
_HEX64 = re.compile(r"^[0-9a-f]{64}$")


def em_model_summary(ds) -> dict:
    """The EM register model a result was fitted with: ``{"em_model": ..., and for the
    cascade "register_stages": N}``; empty for results without one (mean–variance)."""
    from ..model.noise import EMModel

    model = EMModel.from_attrs(ds.attrs)
    return {} if model is None else model.attrs


def _package_version() -> str:
    from .. import __version__

    return __version__


def _major(version: str) -> int | None:
    m = re.match(r"\s*(\d+)", str(version))
    return int(m.group(1)) if m else None
