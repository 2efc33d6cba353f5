"""The camera settings a stack's file records, as one typed record.

Every reader fills what its format holds and leaves the rest ``None``: a field is never
guessed. :func:`emccdcal.data.stacks.stack_settings` returns it for any supported file.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

from ..defaults import RECORDED_KINDS

__all__ = ["CameraSettings", "kind_of_model", "recorded_number"]

#: What a camera's model name says of its kind: the start of its name (upper case,
#: without spaces, hyphens and dots) and the kind. Andor's model numbers: iXon heads
#: (``DU897`` …) EMCCDs, iDus heads (``DU420`` …) CCDs, iStar (``DH…``) intensified;
#: Hamamatsu's from its data sheets: C15550 the ORCA-Quest (qCMOS), C11440/C13440 the
#: ORCA-Flash4.0, C14440/C15440 the ORCA-Fusion (sCMOS), C9100 the ImagEM (EMCCD);
#: Teledyne Princeton Instruments' (the names LightField writes in an SPE file's
#: footer, e.g. ``ProEM-HS: 512BX3``): ProEM EMCCDs, PIXIS, PyLoN, BLAZE and SOPHIA CCDs,
#: PI-MAX intensified, KURO and COSMOS CMOS sensors with an amplifier per pixel.
_MODEL_KINDS = (
    *((f"DU{n}", "emccd") for n in ("860", "885", "887", "888", "897")),
    *((f"DU{n}", "ccd") for n in ("401", "416", "420", "440", "490", "491", "492")),
    ("DH", "iccd"),
    ("IXON", "emccd"),
    ("ISTAR", "iccd"),
    *((name, "scmos") for name in ("ZYLA", "SONA", "NEO", "MARANA", "BALOR")),
    ("C15550", "qcmos"),
    ("ORCAQUEST", "qcmos"),
    *((name, "scmos") for name in ("C11440", "C13440", "C14440", "C15440")),
    *((name, "scmos") for name in ("ORCAFLASH", "ORCAFUSION", "ORCALIGHTNING")),
    ("C9100", "emccd"),
    ("IMAGEM", "emccd"),
    *((name, "scmos") for name in ("PRIMEBSI", "PRIME95B", "KINETIX", "PCOEDGE")),
    *((name, "emccd") for name in ("EVOLVE", "CASCADE")),
    ("PROEM", "emccd"),
    *((name, "ccd") for name in ("PIXIS", "PYLON", "BLAZE", "SOPHIA")),
    ("PIMAX", "iccd"),
    *((name, "scmos") for name in ("KURO", "COSMOS")),
)


def kind_of_model(model) -> str | None:
    """The kind of camera (``emccd``, ``scmos``, ``qcmos``, ``ccd``, ``iccd``) its model
    name says, or None where it says none.

    >>> kind_of_model("C15550-20UP"), kind_of_model("ORCA-Flash4.0 V3"), kind_of_model("DU897_BV")
    ('qcmos', 'scmos', 'emccd')
    >>> kind_of_model("ProEM-HS: 512BX3"), kind_of_model("PIXIS: 1024B"), kind_of_model("KURO: 2048B")
    ('emccd', 'ccd', 'scmos')
    >>> kind_of_model("DemoCamera") is None
    True
    """
    text = "".join(c for c in str(model or "").upper() if c not in " -._")
    return next((kind for start, kind in _MODEL_KINDS if text.startswith(start)), None)


def recorded_number(value) -> float | None:
    """A number a file records (as a number or as text), or None where it is absent, not
    a number or not finite.

    Examples
    --------
    >>> recorded_number("300"), recorded_number(None), recorded_number("n/a")
    (300.0, None, None)
    """
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if math.isfinite(number) else None


@dataclass(frozen=True)
class CameraSettings:
    """Camera settings of one stack (``None``: not recorded in the file).

    Attributes
    ----------
    em_gain_setpoint : float
        The EM gain the camera was set to (dimensionless; 1 = no multiplication). Not
        the true gain, which the calibration measures.
    analog_gain : str
        Pre-amplifier / analog gain setting, as the file names it (e.g. ``"High"``, ``"2"``).
    amplifier : str
        The output amplifier (read-out port) the frames went through, as the file names
        it (e.g. ``"Electron Multiplying"``, ``"Conventional"``, ``"ElectronMultiplied"``):
        each has its own φ and read noise.
    readout_rate_mhz : float
        Pixel readout rate, MHz.
    adc_bits : int
        ADC bit depth, bits.
    temperature_c : float
        Sensor temperature, °C (the reading where recorded, else the set-point).
    exposure_ms : float
        Exposure time, ms.
    serial, model : str
        The camera's serial number and model.
    roi : tuple of int
        ``(x, y, width, height)`` of the region read out, in sensor pixels (x: column of
        the first pixel, y: its row).
    binning : tuple of int
        ``(x, y)`` binning.
    camera_kind : str
        ``emccd``, ``scmos``, ``qcmos``, ``ccd`` or ``iccd`` where the file's model says it
        (:data:`emccdcal.defaults.RECORDED_KINDS`); a camera without an EM register records
        no ``em_gain_setpoint``, whatever its gain field holds.

    Examples
    --------
    What a reader found in a file's header (:func:`emccdcal.data.stacks.stack_settings`),
    or made by hand:

    >>> from emccdcal import CameraSettings
    >>> s = CameraSettings(em_gain_setpoint=300, readout_rate_mhz=10.0, adc_bits=16)
    >>> s.em_gain_setpoint, s.serial is None
    (300, True)
    """

    em_gain_setpoint: float | None = None
    analog_gain: str | None = None
    amplifier: str | None = None
    readout_rate_mhz: float | None = None
    adc_bits: int | None = None
    temperature_c: float | None = None
    exposure_ms: float | None = None
    serial: str | None = None
    model: str | None = None
    roi: tuple[int, int, int, int] | None = None
    binning: tuple[int, int] | None = None
    camera_kind: str | None = None

    def known(self) -> dict:
        """The recorded fields only, as a plain dict (JSON-ready)."""
        return {
            k: (list(v) if isinstance(v, tuple) else v)
            for k, v in asdict(self).items()
            if v is not None
        }

    @classmethod
    def names(cls) -> tuple[str, ...]:
        """The field names, in order."""
        return tuple(f.name for f in fields(cls))

    @classmethod
    def from_record(cls, recorded: dict, source) -> CameraSettings:
        """Settings from a mapping a file holds (a Zarr store's attribute), each field
        checked for its type and range: a wrong one is one :class:`InputError` naming
        ``source`` and the field, never a traceback or a scale of 0 further on.

        Examples
        --------
        >>> CameraSettings.from_record({"adc_bits": 16, "binning": [2, 2]}, "x").binning
        (2, 2)
        """
        from ..errors import InputError

        out = {}
        for key, value in recorded.items():
            if key not in _FIELD_CHECKS:
                raise InputError(f"'{source}': unknown camera setting {key!r}")
            if value is None:
                continue
            checked = _FIELD_CHECKS[key](value)
            if checked is None:
                raise InputError(
                    f"'{source}': camera setting {key} = {value!r} is not {_FIELD_MEANING[key]}"
                )
            out[key] = checked
        return cls(**out)


def _number_in(low, high, integral=False):
    def check(value):
        if isinstance(value, (bool, str, list, dict)):
            return None
        x = recorded_number(value)
        if x is None or not low <= x <= high or (integral and x != int(x)):
            return None
        return int(x) if integral else x

    return check


def _text(value):
    return (
        str(value) if isinstance(value, (str, int, float)) and not isinstance(value, bool) else None
    )


def _ints(count, minima):
    def check(value):
        if not isinstance(value, (list, tuple)) or len(value) != count:
            return None
        if not all(isinstance(v, int) and not isinstance(v, bool) for v in value):
            return None
        if any(v < m or v > 2**31 for v, m in zip(value, minima)):
            return None
        return tuple(int(v) for v in value)

    return check


_FIELD_CHECKS = {
    "em_gain_setpoint": _number_in(1.0, 1e5),
    "analog_gain": _text,
    "amplifier": _text,
    "readout_rate_mhz": _number_in(1e-6, 1e4),
    "adc_bits": _number_in(1, 32, integral=True),
    "temperature_c": _number_in(-273.15, 200.0),
    "exposure_ms": _number_in(0.0, 1e9),
    "serial": _text,
    "model": _text,
    "roi": _ints(4, (0, 0, 1, 1)),
    "binning": _ints(2, (1, 1)),
    "camera_kind": lambda v: v if v in RECORDED_KINDS else None,
}
_FIELD_MEANING = {
    "em_gain_setpoint": "a set-point from 1 to 1e5",
    "analog_gain": "text",
    "amplifier": "text",
    "readout_rate_mhz": "a read-out rate in MHz",
    "adc_bits": "a whole number of bits from 1 to 32",
    "temperature_c": "a temperature in °C",
    "exposure_ms": "an exposure in ms",
    "serial": "text",
    "model": "text",
    "roi": "[x, y, width, height] in whole pixels (width, height >= 1)",
    "binning": "[x, y] whole binning factors >= 1",
    "camera_kind": "one of " + ", ".join(RECORDED_KINDS),
}
