"""Calibrations where they are used: files for localization tools, movies in
photoelectrons, the gain curve, and the calibration database.

- :mod:`.tools`: ``export`` — each localization tool's own file, names and units;
- :mod:`.movie`: ``apply`` — raw frames to photoelectrons, streaming;
- :mod:`.gain_curve`: the gain as a smooth monotone function of the set-point;
- :mod:`.database`: the calibration database (SQLite) that tracks a camera's ageing.

Each reads results through :func:`emccdcal.result.load_calibration`.
"""

from .._lazy import submodules as _submodules

# its modules as attributes, imported on first use (as after `import emccdcal`)
__getattr__, __dir__ = _submodules(__name__, __path__)
