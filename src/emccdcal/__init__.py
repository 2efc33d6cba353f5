"""emccdcal: calibrate EMCCD cameras.

The ADU conversion factor ``e_per_adu`` (e⁻/ADU), the true EM gain ``em_gain`` at every
gain set-point, and the intensities ``photoelectrons`` (e⁻ per pixel per frame), per
pixel, with standard errors, by the gain-series maximum-likelihood method of Ryan et
al., Sci. Rep. 11, 18348 (2021) and the comparison methods of that paper.

Data flow, one module per stage::

    io (manifest, readers) -> dark (offset / read-noise maps) -> stats (histograms)
    -> fitting (likelihood engine) driven by methods (parameter layouts)
    -> result (xarray dataset) -> report / validation

The noise model everything stands on is :mod:`emccdcal.noise`.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("emccdcal")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0+unknown"

from . import noise  # noqa: E402

__all__ = ["__version__", "noise"]

from .calibrate import calibrate  # noqa: E402

__all__ += ["calibrate"]
