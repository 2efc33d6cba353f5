"""The camera settings a stack's file records, as one typed record.

Every reader fills what its format holds and leaves the rest ``None``: a field is never
guessed. :func:`emccdcal.data.stacks.stack_settings` returns it for any supported file.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

__all__ = ["CameraSettings", "recorded_number"]


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

    def known(self) -> dict:
        """The recorded fields only, as a plain dict (JSON-ready)."""
        return {k: (list(v) if isinstance(v, tuple) else v)
                for k, v in asdict(self).items() if v is not None}

    @classmethod
    def names(cls) -> tuple[str, ...]:
        """The field names, in order."""
        return tuple(f.name for f in fields(cls))
