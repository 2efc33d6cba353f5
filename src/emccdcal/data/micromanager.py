"""Camera settings of Micro-Manager TIFF stacks (MMStack, OME-TIFF written by it).

Micro-Manager stores each frame's properties as JSON in TIFF tag 51123
(``MicroManagerMetadata``). Camera properties are named ``<camera label>-<property>``,
the label being the value of ``Camera``. Andor cameras: ``Gain`` (EM gain), ``EMSwitch``,
``Pre-Amp-Gain``, ``ReadoutMode`` (``"17.000 MHz"``), ``CCDTemperature``, ``Camera``
(``"| type | model | serial |"``). Photometrics: ``MultiplierGain`` (EM gain), ``Gain``
(analog), ``ReadoutRate``, ``BitDepth``, ``CCDTemperature``, ``SerialNumber``,
``ChipName``. Other cameras: the standard properties ``EMGain``, ``ReadoutMode``,
``CameraName`` (model) and ``CameraID``. Core: ``Exposure-ms``, ``BitDepth``, ``ROI``
(``"x-y-width-height"``), ``Binning``. The model names the camera's kind where it says
it (:func:`emccdcal.data.settings.kind_of_model`: a Hamamatsu ``C15550-20UP`` is an
ORCA-Quest, a qCMOS), and a camera without an EM register has no EM set-point.
"""

from __future__ import annotations

import math
import re

from ..errors import InputError
from ..defaults import WITHOUT_EM_REGISTER
from .settings import CameraSettings, kind_of_model

__all__ = ["TAG", "settings_of", "stack_settings"]

#: The TIFF tag holding a frame's Micro-Manager properties.
TAG = 51123


def _number(value):
    match = (
        re.search(r"[-+]?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?", str(value)) if value is not None else None
    )
    if match is None:
        return None
    number = float(match.group())
    return number if math.isfinite(number) else None


def _rate_mhz(value):
    number = _number(value)
    if number is None:
        return None
    text = str(value).lower()
    return number / 1000.0 if "khz" in text else number


def settings_of(md: dict) -> CameraSettings:
    """:class:`CameraSettings` from one frame's Micro-Manager properties."""
    cam = md.get("Camera") or md.get("Core-Camera") or ""
    prop = lambda name: md.get(f"{cam}-{name}")  # noqa: E731
    photometrics = prop("MultiplierGain") is not None
    if photometrics:
        em_gain, analog, amplifier = _number(prop("MultiplierGain")), prop("Gain"), prop("Port")
        rate, serial, model = _rate_mhz(prop("ReadoutRate")), prop("SerialNumber"), prop("ChipName")
    else:  # Andor
        em_gain = _number(prop("Gain") if prop("Gain") is not None else prop("EMGain"))
        if em_gain is not None and str(prop("EMSwitch") or "On").lower() == "off":
            em_gain = 1.0
        analog, rate = prop("Pre-Amp-Gain"), _rate_mhz(prop("ReadoutMode"))
        amplifier = prop("Output_Amplifier")
        parts = [p.strip() for p in str(prop("Camera") or "").strip("|").split("|")]
        model = parts[1] if len(parts) >= 3 else None
        serial = parts[2] if len(parts) >= 3 else prop("CameraID")
        model = model or prop("CameraName")
    kind = kind_of_model(model)
    if kind in WITHOUT_EM_REGISTER:  # an analog gain field is not an EM set-point
        em_gain = None
    bits = _number(md.get("BitDepth") or prop("BitDepth"))
    roi = binning = None
    if md.get("ROI"):
        values = [int(v) for v in re.findall(r"\d+", str(md["ROI"]))]
        roi = tuple(values) if len(values) == 4 else None
    if md.get("Binning") is not None:
        values = [int(v) for v in re.findall(r"\d+", str(md["Binning"]))]
        binning = (values[0], values[-1]) if values else None
    return CameraSettings(
        em_gain_setpoint=em_gain,
        camera_kind=kind,
        analog_gain=None if analog is None else str(analog),
        amplifier=None if amplifier is None else str(amplifier),
        readout_rate_mhz=rate,
        adc_bits=None if bits is None else int(bits),
        temperature_c=_number(prop("CCDTemperature")),
        exposure_ms=_number(md.get("Exposure-ms")),
        serial=None if serial is None else str(serial),
        model=None if model is None else str(model),
        roi=roi,
        binning=binning,
    )


def stack_settings(path, tif) -> CameraSettings:
    """The settings of a TIFF stack's frames: those of its first frame, which its last
    must share (a stack whose settings change between frames is an error)."""
    pages = tif.pages
    first = pages[0].tags.get(TAG)
    if first is None or not isinstance(first.value, dict):
        return CameraSettings()
    head = settings_of(first.value)
    last_page = pages[len(pages) - 1]
    last_page = last_page.aspage() if hasattr(last_page, "aspage") else last_page
    last = last_page.tags.get(TAG)
    if last is not None and isinstance(last.value, dict):
        tail = settings_of(last.value)
        changed = [
            n
            for n in CameraSettings.names()
            if getattr(head, n) != getattr(tail, n) and n != "temperature_c"
        ]
        if changed:
            n = changed[0]
            raise InputError(
                f"'{path}': the camera's {n} changes within the stack "
                f"({getattr(head, n)!r} in its first frame, {getattr(tail, n)!r} "
                "in its last)"
            )
    return head
