"""emccdcal: calibrate EMCCD cameras.

The ADU conversion factor ``e_per_adu`` (e⁻/ADU), the true EM gain ``em_gain`` at every
gain set-point, and the intensities ``photoelectrons`` (e⁻ per pixel per frame), per
pixel, with standard errors, by the gain-series maximum-likelihood method of Ryan et
al., Sci. Rep. 11, 18348 (2021) and the comparison methods of that paper.

Subpackages, data flowing one way (``docs/architecture.md``)::

    model (noise, cascade, psf) <- data (manifest, stacks, dark, stats, quality)
    -> fit (engine, layouts, mv, gof, posterior) -> calibration -> result
    -> beads (fit, cots, validation) -> report (figures, html, corner);
    result -> export (tools, movie, gain_curve, database); simulate; cli

The public API is below; every name is imported on first use, so ``import emccdcal``
is fast.

>>> import emccdcal
>>> emccdcal.calibrate.__module__, emccdcal.noise.__name__
('emccdcal.calibration.api', 'emccdcal.model.noise')
>>> emccdcal.model.noise is emccdcal.noise  # subpackages, too, on first use
True
"""

import importlib as _importlib

#: Public name -> (module, attribute); attribute None means the module itself.
_API = {
    "calibrate": ("emccdcal.calibration", "calibrate"),
    "load_result": ("emccdcal.result", "load"),
    "read_manifest": ("emccdcal.data.manifest", "read_manifest"),
    "scan": ("emccdcal.data.scan", "scan_folder"),
    "plan": ("emccdcal.acquire.plan", "plan"),
    "record": ("emccdcal.acquire.record", "acquire"),
    "check_gain": ("emccdcal.fit.darkgain", "check_gain"),
    "audit": ("emccdcal.export.audit", "audit"),
    "check": ("emccdcal.data.quality", "check_manifest"),
    "simulate_frames": ("emccdcal.simulate.camera", "simulate_frames"),
    "Camera": ("emccdcal.simulate.camera", "Camera"),
    "simulate_gain_series": ("emccdcal.simulate.series", "simulate_gain_series"),
    "simulate_intensity_series": ("emccdcal.simulate.series", "simulate_intensity_series"),
    "simulate_beads": ("emccdcal.simulate.beads", "simulate_beads"),
    "validate": ("emccdcal.beads.validation", "validate"),
    "cots": ("emccdcal.beads.cots_calibration", "cots_calibrate"),
    "sample_posterior": ("emccdcal.sampling", "sample_posterior"),
    "write_report": ("emccdcal.report.html", "write_report"),
    "load_calibration": ("emccdcal.result", "load_calibration"),
    "Calibration": ("emccdcal.result", "Calibration"),
    "Manifest": ("emccdcal.data.manifest", "Manifest"),
    "CameraSettings": ("emccdcal.data.settings", "CameraSettings"),
    "export_calibration": ("emccdcal.export.tools", "export"),
    "apply_calibration": ("emccdcal.export.movie", "apply"),
    "fit_gain_curve": ("emccdcal.export.gain_curve", "fit_gain_curve"),
    "noise": ("emccdcal.model.noise", None),
    "EmccdcalError": ("emccdcal.errors", "EmccdcalError"),
    "EmccdcalWarning": ("emccdcal.errors", "EmccdcalWarning"),
}

__all__ = ["__version__", *_API]

#: Subpackages reached as attributes (``emccdcal.model.noise``), imported on first use as
#: scipy imports its own, so that a fresh interpreter's ``import emccdcal`` reaches them.
_SUBPACKAGES = frozenset(
    (
        "acquire",
        "beads",
        "calibration",
        "data",
        "export",
        "fit",
        "model",
        "report",
        "result",
        "simulate",
    )
)


def __getattr__(name: str):
    if name == "__version__":  # of the distribution that installed these files
        from ._dist import version

        globals()[name] = version()
        return globals()[name]
    if name in _SUBPACKAGES:
        module, attribute = f"emccdcal.{name}", None
    else:
        try:
            module, attribute = _API[name]
        except KeyError:
            raise AttributeError(f"module 'emccdcal' has no attribute {name!r}") from None
    value = _importlib.import_module(module)
    if attribute is not None:
        value = getattr(value, attribute)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__():
    # the API and its subpackages: the helpers above are not for users (type checkers
    # read __init__.pyi)
    return sorted({*__all__, *_SUBPACKAGES})
