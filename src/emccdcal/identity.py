"""Which camera and read-out state frames come from, and whether a calibration holds for it.

A calibration holds for one camera in one read-out state: its serial, model, output
amplifier, read-out rate, analog gain, ADC bits and binning (:data:`IDENTITY_FIELDS`).
Every verb that uses a calibration on frames (``apply``, ``gain-check``, ``validate``,
``calibrate`` with φ from a result, the napari widgets) goes through :func:`check`,
which

* refuses frames that differ among themselves (darks of two cameras or two set-points
  pooled into one check, or the same file given twice),
* refuses frames whose set-point is not the one they are used at,
* refuses frames that differ from the calibration in a field both record, naming the
  field and the option that lets it through (``--accept-mismatch FIELD``),
* and warns, once, where one side records nothing of a field the other records, so that
  a plain TIFF of another camera is not converted without a word.

Standard library only: the command line's parsers import it.
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Mapping
from pathlib import Path

from .defaults import IDENTITY_FIELDS
from .errors import EmccdcalWarning, InputError, OptionError, spelled

__all__ = [
    "IDENTITY_FIELDS",
    "ACCEPTABLE",
    "IdentityWarning",
    "mismatches",
    "of_frames",
    "check",
    "recorded",
]

#: What ``--accept-mismatch`` takes: the identity fields and the set-point.
ACCEPTABLE = (*IDENTITY_FIELDS, "setpoint")


class IdentityWarning(EmccdcalWarning):
    """The identity of frames could not be checked (one side records nothing)."""


def _value(key, value):
    """A recorded value in the form two records are compared in (None: not recorded)."""
    if value is None:
        return None
    if key == "binning":
        return tuple(int(v) for v in value)
    if key in ("readout_rate_mhz", "adc_bits", "setpoint"):
        number = float(value)
        return number if math.isfinite(number) else None
    return str(value).strip() or None


def _shown(value) -> str:
    if isinstance(value, tuple):
        return "x".join(map(str, value))
    if isinstance(value, float):
        return f"{value:g}"
    return repr(value)


def _accepted(accept) -> set:
    accept = set(accept)
    unknown = accept - set(ACCEPTABLE)
    if unknown:
        raise OptionError(
            f"--accept-mismatch takes {', '.join(ACCEPTABLE)}; got {', '.join(sorted(unknown))}"
        )
    return accept


def mismatches(expected: Mapping, found: Mapping, *, accept=()) -> dict[str, str]:
    """The identity fields that both record and that differ, each with a phrase
    ``"camera serial 'B' (calibration: 'A')"``; ``accept`` names fields let through.

    Examples
    --------
    >>> mismatches({"serial": "A", "adc_bits": 16}, {"serial": "B"})
    {'serial': "camera serial 'B' (calibration: 'A')"}
    """
    accept = _accepted(accept)
    out = {}
    for key, what in IDENTITY_FIELDS.items():
        a, b = _value(key, expected.get(key)), _value(key, found.get(key))
        if key not in accept and a is not None and b is not None and a != b:
            out[key] = f"{what} {_shown(b)} (calibration: {_shown(a)})"
    return out


def recorded(settings) -> dict:
    """The identity fields and the set-point a file's settings record (a
    :class:`~emccdcal.data.settings.CameraSettings` or a mapping), None left out."""
    get = settings.get if isinstance(settings, Mapping) else (lambda k: getattr(settings, k, None))
    found = {k: _value(k, get(k)) for k in IDENTITY_FIELDS}
    found["setpoint"] = _value(
        "setpoint", get("em_gain_setpoint") if get("setpoint") is None else get("setpoint")
    )
    return {k: v for k, v in found.items() if v is not None}


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return Path(a).absolute() == Path(b).absolute()


def _items(frames) -> list:
    return list(frames.items()) if isinstance(frames, Mapping) else list(frames)


def of_frames(frames: Mapping, *, what: str = "frames", setpoints: bool = True) -> dict:
    """The identity that every file of ``frames`` records alike, refusing files that
    differ (two cameras, two read-out states or two set-points pooled) or the same file
    given twice.

    Parameters
    ----------
    frames : mapping of path to settings, or sequence of (path, settings)
        Each file with what it records (:func:`recorded`'s input); a sequence may name a
        file twice, which is refused.
    what : str
        What the files are, for the messages ("dark stacks", "bead frames").
    setpoints : bool
        Whether the files must also record one set-point (pooled into one estimate), or
        may span several (a gain series).

    Returns
    -------
    dict
        Each field recorded by at least one file, with its one value.
    """
    items = _items(frames)
    paths = [path for path, _ in items]
    for i, a in enumerate(paths):
        for b in paths[:i]:
            if _same_file(Path(a), Path(b)):
                raise InputError(f"{a}: given twice among the {what} (it would count double)")
    joint: dict = {}
    first: dict = {}
    for path, settings in items:
        for key, value in recorded(settings).items():
            if key == "setpoint" and not setpoints:
                continue
            if key in joint and joint[key] != value:
                name = IDENTITY_FIELDS.get(key, "EM-gain set-point")
                raise InputError(
                    f"{path}: {name} {_shown(value)}, but {first[key]} records "
                    f"{_shown(joint[key])}: {what} of one camera, read-out state and "
                    "set-point are pooled, never several"
                )
            joint.setdefault(key, value)
            first.setdefault(key, path)
    return joint


def check(
    calibration: Mapping | None,
    frames: Mapping,
    *,
    label: str = "the calibration",
    setpoint=None,
    accept=(),
    what: str = "frames",
) -> dict:
    """Refuse ``frames`` that a calibration does not hold for; warn where it cannot tell.

    Parameters
    ----------
    calibration : mapping or None
        What the calibration records of its camera (``Calibration.identity()``), or None
        where only the frames are checked among themselves (a gain check without one).
    frames : mapping of path to settings, or sequence of (path, settings)
        The files the calibration is used on, each with what it records.
    label : str
        The calibration's name in messages.
    setpoint : float, optional
        The set-point the frames are used at (given by the user or their files): a file
        recording another is refused.
    accept : iterable of str
        Fields let through (:data:`ACCEPTABLE`).
    what : str
        What the frames are, for the messages (which name ``--accept-mismatch`` as the
        interface in use spells it: :func:`emccdcal.errors.spelled`).

    Returns
    -------
    dict
        The frames' joint identity (:func:`of_frames`).

    Raises
    ------
    InputError
        One line naming the file, the fields that differ and how to let them through.

    Warns
    -----
    IdentityWarning
        Where the calibration records a field that none of the frames records, or the
        other way round: the identity could not be checked there.
    """
    accept = _accepted(accept)
    option = spelled("--accept-mismatch")
    joint = of_frames(frames, what=what)
    first = next((path for path, _ in _items(frames)), "the frames")
    if setpoint is not None and "setpoint" not in accept:
        given = _value("setpoint", setpoint)
        for path, settings in _items(frames):
            found = recorded(settings).get("setpoint")
            if found is not None and given is not None and found != given:
                raise InputError(
                    f"{path}: records EM-gain set-point {found:g}, used at "
                    f"{given:g}; give the set-point of these frames (or, if "
                    f"the file is wrong: {option} setpoint)"
                )
    if calibration is None:
        return joint
    expected = {k: v for k, v in recorded(calibration).items() if k != "setpoint"}
    differ = mismatches(expected, joint, accept=accept)
    if differ:
        raise InputError(
            f"{first}: not what {label} calibrated: {'; '.join(differ.values())}"
            "; a calibration holds for one camera and read-out state (if you "
            f"know better: {' '.join(f'{option} {k}' for k in differ)})"
        )
    unchecked = []
    for side, have, lack in (
        (f"the {what} record", expected, joint),
        (f"{label} records", joint, expected),
    ):
        fields = [
            IDENTITY_FIELDS[k]
            for k in IDENTITY_FIELDS
            if k in have and k not in lack and k not in accept
        ]
        if fields and not any(k in lack for k in IDENTITY_FIELDS):
            unchecked.append(f"{side} none of it")
        elif fields:
            unchecked.append(f"{side} no {', '.join(fields)}")
    if unchecked:
        warnings.warn(
            f"{first}: could not check that these {what} are of the camera and "
            f"read-out state {label} calibrated ({'; '.join(unchecked)}): make "
            "sure they are",
            IdentityWarning,
            stacklevel=2,
        )
    return joint
