"""A gain check from dark frames (:mod:`emccdcal.fit.darkgain`) against the calibration
it checks."""

from __future__ import annotations

import math

from ..errors import InputError

__all__ = ["compare", "verdict", "e_per_adu_of"]


def e_per_adu_of(calibration) -> float:
    """The φ (e⁻/ADU) a gain check of the camera takes from its calibration: the median
    of the calibration's per-pixel φ (the check's gain is the sensor's)."""
    from ..result import pixel_statistics

    return float(pixel_statistics(calibration.e_per_adu)["median"])


def compare(check, calibration, *, z: float = 3.0) -> dict:
    """The check against a calibration's gain at its set-point.

    The calibration's sensor value is the median of its per-pixel gains at the
    set-point, with that median's standard error (:func:`emccdcal.result.pixel_statistics`);
    the difference is in per cent of it, with the two SEs combined.

    Parameters
    ----------
    check : emccdcal.fit.darkgain.GainCheck
        With its ``setpoint``.
    calibration : str, Path or Calibration
        A result (or group) holding that set-point.
    z : float
        Flag a difference beyond ``z`` combined standard errors.

    Returns
    -------
    dict
        ``calibrated_em_gain``, ``calibrated_em_gain_se``, ``calibrated`` (the result's
        date), ``difference_percent``, ``difference_se_percent``, ``z`` and ``changed``
        (the flag).
    """
    from ..result import load_calibration, pixel_statistics

    cal = load_calibration(calibration)
    if check.setpoint is None:
        raise InputError("the set-point of the dark frames is not known: give it")
    if check.setpoint not in cal.em_gain:
        have = ", ".join(f"{s:g}" for s in sorted(cal.em_gain))
        raise InputError(
            f"the calibration has no gain at set-point {check.setpoint:g} (it has {have})"
        )
    stats_ = pixel_statistics(cal.em_gain[check.setpoint])
    g_cal, se_cal = stats_["median"], stats_["se_of_median"] or 0.0
    combined = math.hypot(check.em_gain_se, se_cal)
    diff = check.em_gain - g_cal
    return {
        "calibrated_em_gain": g_cal,
        "calibrated_em_gain_se": se_cal,
        "calibrated": cal.created[:10],
        "difference_percent": 100.0 * diff / g_cal,
        "difference_se_percent": 100.0 * combined / g_cal,
        "z": diff / combined,
        "changed": bool(abs(diff) > z * combined),
    }


def verdict(comparison: dict) -> str:
    """One line of :func:`compare`'s result: "agrees with its calibration of …" or "the
    gain is … % below its calibration of …: recalibrate"."""
    c = comparison
    diff = f"{c['difference_percent']:+.2g} ± {c['difference_se_percent']:.2g} %"
    if not c["changed"]:
        return (
            f"agrees with its calibration of {c['calibrated']} "
            f"({c['calibrated_em_gain']:.4g}): {diff}"
        )
    side = "above" if c["difference_percent"] > 0 else "below"
    return (
        f"the gain is {abs(c['difference_percent']):.2g} ± "
        f"{c['difference_se_percent']:.2g} % {side} its calibration of "
        f"{c['calibrated']} ({c['calibrated_em_gain']:.4g}, z = {c['z']:+.1f}): "
        "recalibrate"
    )
