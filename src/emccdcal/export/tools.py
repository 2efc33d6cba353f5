"""``emccdcal export``: a calibration in each localization tool's own file, names and units.

Every tool names the same few numbers differently, and three of the names mislead:
ThunderSTORM's ``photons2ADU`` is φ in e⁻/ADU; gdsc-smlm's ``count_per_photon`` is the
total gain QE·g/φ; storm-analysis's ``camera_gain`` is g/φ in ADU per e⁻. Here each is
written once, from the formulas in the table of ``docs/exports.md``, which gives every
tool's file, field, our quantity, unit and formula, with where in the tool's source each
name is read.

A tool that takes one number gets the median over the converged pixels; the files that
allow it also record the pixels' robust spread (1.4826 × MAD) and how many pixels there
were. Per-pixel maps go where a tool reads them (PYME's dark, variance and flat-field
maps; the ``fits`` and ``tiff-maps`` targets). Every file records its provenance: the
emccdcal version, the method, the result files and their SHA-256.

Examples
--------
>>> from emccdcal.export.tools import TOOLS
>>> [t for t in ("picasso", "thunderstorm", "json") if t in TOOLS]
['picasso', 'thunderstorm', 'json']
"""

from __future__ import annotations

import math
from pathlib import Path


from .. import plugins
from ..errors import OptionError
from ..result import format_setpoint, load_calibration
from .toolkit import camera_values, pick_setpoint

# TOOLS comes from the plug-ins, by the module's __getattr__
__all__ = [
    "TOOLS",  # noqa: F822 (from the plug-ins, by __getattr__)
    "export",
    "export_modes",
]


def __getattr__(name):
    if name == "TOOLS":  # the ``--to`` targets: every tool registered (emccdcal.plugins)
        return tuple(plugins.load(plugins.TOOLS))
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def export(
    calibration, to: str, out, *, setpoint=None, qe=None, pixel_size_nm=None, camera_name=None
) -> list[Path]:
    """Write a calibration in a localization tool's own file.

    Parameters
    ----------
    calibration : xarray.Dataset, Calibration, str or Path
        A :class:`~emccdcal.result.Calibration`, or a result (file or directory, or
        several joined by commas) to read with :func:`~emccdcal.result.load_calibration`.
    to : str
        One of :data:`TOOLS`: a tool registered under the entry-point group
        ``emccdcal.tools`` (:mod:`emccdcal.plugins`), emccdcal's own or another package's.
    out : str or Path
        Output directory (created if missing); files are written atomically.
    setpoint : float, optional
        The EM-gain set-point of the movies the tool will read (dimensionless); needed
        where the calibration has several multiplied set-points (not for ``json``,
        ``fits``, ``tiff-maps``, which take them all).
    qe : float, optional
        Quantum efficiency (photoelectrons per photon, 0–1) for tools that take it. Not
        given: tools that need it get 1, so their "photons" are photoelectrons.
    pixel_size_nm : float, optional
        Camera pixel size in the sample plane, nm; written where a tool takes it.
    camera_name : str, optional
        The camera's name in Picasso's configuration (default: model and serial as the
        files recorded them).

    Returns
    -------
    list of Path
        The files written.

    Raises
    ------
    OptionError
        An unknown tool, a set-point missing from the calibration (or needed and not
        given), a QE outside (0, 1], or no offset recorded at that set-point.

    Examples
    --------
    >>> import tempfile, emccdcal
    >>> work = tempfile.mkdtemp()
    >>> sim = emccdcal.simulate_gain_series(
    ...     f"{work}/gs", rows=4, cols=4, frames=400, setpoints=(1, 10), seed=1, progress=False
    ... )
    >>> ds = emccdcal.calibrate(sim.manifest, e_per_adu=sim.truth["e_per_adu"], progress=False)
    >>> [p.name for p in emccdcal.export_calibration(ds, "picasso", f"{work}/p", setpoint=10)]
    ['picasso-config.yaml']
    """
    registered = plugins.load(plugins.TOOLS)
    if to not in registered:
        raise OptionError(f"unknown export target {to!r}; one of {', '.join(registered)}")
    tool = registered[to]
    if qe is not None and not (0 < qe <= 1):
        raise OptionError(f"--qe is photoelectrons per photon, in (0, 1]; got {qe}")
    if pixel_size_nm is not None and not (pixel_size_nm > 0 and math.isfinite(pixel_size_nm)):
        raise OptionError(f"--pixel-size is in nm and positive; got {pixel_size_nm}")
    cal = load_calibration(calibration)
    if tool.all_setpoints:
        s, values = None, None
    else:  # refused before anything is made: no empty folder left behind
        s = pick_setpoint(cal, setpoint)
        values = camera_values(cal, s)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    return tool.write(cal, s, values, out, qe, pixel_size_nm, camera_name)


def export_modes(
    calibrations, to: str, out, *, setpoint=None, qe=None, pixel_size_nm=None, camera_name=None
) -> list[Path]:
    """Write several calibrations of one camera, one per read-out mode (output amplifier,
    read-out rate, pre-amplifier gain), as one tool file keyed by mode.

    Only a tool with a ``write_modes`` holds such a table (of emccdcal's own, Picasso's
    ``config.yaml``, its nested ``Sensitivity`` with ``Sensitivity Categories``); the
    others take one mode per file.

    Parameters
    ----------
    calibrations : sequence of Calibration, str or Path
        One per read-out mode, of one camera.
    to, out, setpoint, qe, pixel_size_nm, camera_name
        As :func:`export`; ``setpoint`` is needed where a mode has several multiplied
        set-points. A mode without multiplication enters at 1×. ``qe`` is accepted for
        the same call as :func:`export` and not written: Picasso uses no QE.

    Raises
    ------
    OptionError
        A tool without a table of modes, calibrations of different cameras, two of one mode,
        or a mode its files do not record.
    """
    registered = plugins.load(plugins.TOOLS)
    if to not in registered:
        raise OptionError(f"unknown export target {to!r}; one of {', '.join(registered)}")
    tool = registered[to]
    if tool.write_modes is None:
        tables = [t.title for t in registered.values() if t.write_modes is not None]
        raise OptionError(
            f"{to} takes one read-out mode per file, and the calibrations given are of "
            f"several: export each mode on its own (a table of modes: {', '.join(tables)})"
        )
    cals = [load_calibration(c) for c in calibrations]
    serials = {c.camera.get("serial") for c in cals}
    if len(serials) > 1:
        raise OptionError(
            "the calibrations are of different cameras (serials "
            f"{', '.join(sorted(map(str, serials)))}); a table of read-out "
            "modes is of one camera"
        )
    multiplied = sorted({x for c in cals for x in c.setpoints if x != 1.0})
    if setpoint is None and len(multiplied) > 1:
        raise OptionError(
            "the calibrations have set-points "
            + ", ".join(format_setpoint(x) + "x" for x in multiplied)
            + "; give --setpoint G (the set-point the movies were recorded at)"
        )
    s = float(setpoint) if setpoint is not None else (multiplied[0] if multiplied else 1.0)
    rows = []  # refused before anything is made
    for c in cals:
        if s not in c.setpoints and len(c.setpoints) > 1:
            c.gain(s)  # raises, naming what it has
        at = s if s in c.setpoints else 1.0  # a mode without EM multiplication: 1x
        rows.append((c, at, camera_values(c, at)))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    return tool.write_modes(rows, s, out, pixel_size_nm, camera_name)
