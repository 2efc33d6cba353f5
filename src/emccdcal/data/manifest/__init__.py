"""The manifest: the acquisitions of one calibration, checked before anything is fitted.

A calibration starts from a TOML manifest (``docs/manifest.md``): one
``[[acquisition]]`` table per stack of raw counts, with its EM gain set-point and either
per-pixel ``offset`` and ``read_noise`` maps or a ``dark`` stack they are computed from,
and an optional top-level ``e_per_adu``. :func:`read_manifest` reads it and checks
*everything* a fit needs before any fitting starts; every problem is reported as one
line naming the file and the problem (:class:`~emccdcal.errors.ManifestError`).

Units (``docs/results.md``): counts, offset and read noise in ADU; ``e_per_adu`` in
e⁻/ADU; ``em_gain_setpoint`` dimensionless.
"""

from .parse import (
    ACQUISITION_KEYS,
    TOP_LEVEL_KEYS,
    AcquisitionEntry,
    ManifestEntries,
    parse_manifest,
)
from .records import CAMERA_IDENTITY, Acquisition, Manifest, Source
from .resolve import is_result_path, read_manifest, resolve_manifest

__all__ = [
    "Source",
    "Acquisition",
    "AcquisitionEntry",
    "Manifest",
    "ManifestEntries",
    "parse_manifest",
    "read_manifest",
    "resolve_manifest",
    "TOP_LEVEL_KEYS",
    "ACQUISITION_KEYS",
    "CAMERA_IDENTITY",
    "is_result_path",
]
