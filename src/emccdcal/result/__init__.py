"""The calibration result: an xarray dataset, its files, and their summary.

Every calibration method ends here. :func:`make_dataset` labels the per-pixel estimates
(dimensions, coordinates, units), :func:`save` writes ``OUT/calibration.nc`` and
``OUT/summary.json`` atomically, :func:`load` reads a result back and checks that it is
one, and :func:`summarize` reduces it to per-parameter statistics over pixels.
``docs/results.md`` describes the files for users.

Dimensions and variables (``R`` rows, ``C`` columns)
----------------------------------------------------
==============================  ===============================  ========
variable (each with ``_se``)    dims                             units
==============================  ===============================  ========
``e_per_adu``                   (row, col)                       e-/ADU
``adu_per_e``                   (row, col)                       ADU/e-
``em_gain``                     (setpoint, row, col)             1
``photoelectrons``              (row, col) or (D, row, col) [*]  e-
==============================  ===============================  ========

[*] ``D`` is ``level`` or ``setpoint``, see below. Without ``_se``: ``loglik`` (row, col)
in nat, and ``converged`` (row, col), bool, units "1".

Coordinates: ``row`` and ``col`` (sensor pixel indices, integers; ``origin`` shifts them
for a tile of a larger sensor), ``setpoint`` (the camera's EM-gain set-points, float, in the
order given) and ``level`` (illumination-level labels, str).

Which dims ``photoelectrons`` gets
----------------------------------
Pass ``photoelectrons_dims`` to say it outright. Otherwise the rule is:

* a 2-D array is ``(row, col)`` — one intensity shared by all acquisitions (``gs``);
* a 3-D array is ``(level, row, col)`` if ``levels`` is given and ``setpoints`` is not,
  ``(setpoint, row, col)`` if ``setpoints`` is given and ``levels`` is not;
* anything else (both given, neither given, other ranks) needs ``photoelectrons_dims``.
"""

from .._util import format_setpoint, one_line
from .dataset import make_dataset
from .files import load, run_recorded, save
from .schema import (
    CALIBRATION_FILE,
    LONG_NAMES,
    REQUIRED_VARIABLES,
    SUMMARY_FILE,
    UNITS,
    em_model_summary,
)
from .summary import is_doubtful, summarize, verdict_line
from .use import (
    IDENTITY_FIELDS,
    Calibration,
    camera_of,
    identity_attrs,
    load_calibration,
    pixel_statistics,
    result_files,
)

__all__ = [
    "UNITS",
    "LONG_NAMES",
    "REQUIRED_VARIABLES",
    "CALIBRATION_FILE",
    "SUMMARY_FILE",
    "make_dataset",
    "save",
    "load",
    "summarize",
    "format_setpoint",
    "run_recorded",
    "Calibration",
    "load_calibration",
    "pixel_statistics",
    "IDENTITY_FIELDS",
    "camera_of",
    "result_files",
    "verdict_line",
    "is_doubtful",
    "identity_attrs",
    "em_model_summary",
    "one_line",
]
