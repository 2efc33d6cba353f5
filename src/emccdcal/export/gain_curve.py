"""The gain curve: the true EM gain as a smooth, monotone function of the set-point.

A camera's EM gain grows steeply with the register's clock voltage, and its set-point
scale is the maker's approximation of that: on a log–log scale the measured gain against
the set-point is close to a straight line with a slight bend. The curve here is a
weighted least-squares polynomial in ``x = ln(set-point)`` for ``y = ln(gain)``,

    y = b0 + b1 x + b2 x²      (quadratic with four or more multiplied set-points,
                                a line with two or three),

each point the sensor's gain at a measured set-point (the median over converged pixels)
weighted by the inverse variance of its log, ``(SE/g)²`` with SE = 1.2533 × robust
spread / √n, the standard error of a median. Set-point 1 is not a measurement (the gain
there is 1 by definition of the methods) and is left out. The quadratic is used only
where it rises over the whole measured range; otherwise the line. Where the points
scatter about the curve more than their errors allow (reduced χ² > 1), the covariance is
scaled up by the reduced χ²; it is never scaled down. Predictions carry the standard
error of the curve at that set-point (delta method) and a 95 % band; beyond the measured
set-points they are marked as extrapolated.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import OptionError
from ..result import (Calibration, format_setpoint, identity_mismatches, load_calibration,
                      pixel_statistics)

__all__ = ["GainCurve", "fit_gain_curve", "measured_gains"]

_Z95 = 1.959963984540054


def _point(setpoint, gain_map, label):
    st = pixel_statistics(gain_map)
    return None if st["se"] is None else (float(setpoint), st["median"], st["se"], label)


def measured_gains(calibrations, *, accept_mismatch=()) -> list[tuple[float, float, float, str]]:
    """``(set-point, gain, SE, label)`` of every multiplied set-point of the calibrations
    (results, or result datasets in memory): the median over converged pixels and the
    standard error of that median.

    Raises
    ------
    OptionError
        A result given twice, or results of different cameras or read-out states (unless
        the fields that differ are in ``accept_mismatch``).
    """
    points, seen, identity = [], {}, None
    for i, cal in enumerate(calibrations):
        if hasattr(cal, "data_vars"):  # an xarray result dataset
            if "em_gain" not in cal:
                continue
            ok = cal["converged"].values.astype(bool)
            maps = {float(s): np.where(ok, cal["em_gain"].sel(setpoint=s).values, np.nan)
                    for s in cal["setpoint"].values}
            label = str(cal.attrs.get("method", f"result {i + 1}"))
        else:
            cal = cal if isinstance(cal, Calibration) else load_calibration(cal)
            for f, digest in zip(cal.files, cal.sha256):
                if digest in seen:
                    raise OptionError(f"{f} is given twice (also as {seen[digest]}): each "
                                      "result would be counted twice; give it once")
                seen[digest] = f
            if identity is None:
                identity = (cal.label, cal.identity())
            differ = identity_mismatches(identity[1], cal.identity(), accept=accept_mismatch)
            if differ:
                raise OptionError(f"{cal.label} is of another camera or read-out state than "
                                  f"{identity[0]}: {'; '.join(differ.values())}; a gain curve "
                                  "is of one camera (--accept-mismatch "
                                  f"{' '.join(differ)} if you know better)")
            maps, label = {s: cal.gain(s) for s in cal.setpoints}, cal.label
        points += [p for s, m in maps.items() if s != 1.0
                   for p in [_point(s, m, label)] if p is not None]
    return points


@dataclass(frozen=True)
class GainCurve:
    """A fitted gain curve (see the module's notes).

    Attributes
    ----------
    setpoints, gains, gain_se : ndarray
        The measured points the curve was fitted to (dimensionless).
    coef : ndarray
        ``b0, b1[, b2]`` of ln g against ln(set-point).
    cov : ndarray
        Their covariance (scaled by the reduced χ² where that exceeds 1).
    chi2, dof : float, int
        The fit's χ² and degrees of freedom.
    """

    setpoints: np.ndarray
    gains: np.ndarray
    gain_se: np.ndarray
    coef: np.ndarray
    cov: np.ndarray
    chi2: float
    dof: int

    @property
    def degree(self) -> int:
        return len(self.coef) - 1

    def predict(self, setpoints) -> dict:
        """Gain at any set-points, with SE and the 95 % band.

        Returns
        -------
        dict of ndarray
            ``setpoint``, ``gain``, ``se``, ``lower``, ``upper`` and ``extrapolated``
            (bool: outside the measured set-points).
        """
        s = np.atleast_1d(np.asarray(setpoints, dtype=float))
        if np.any(~(s > 0)):
            raise OptionError("set-points to predict must be positive")
        X = np.vander(np.log(s), self.degree + 1, increasing=True)
        y = X @ self.coef
        sd = np.sqrt(np.einsum("ij,jk,ik->i", X, self.cov, X))
        with np.errstate(over="ignore", invalid="ignore"):
            gain, upper = np.exp(y), np.exp(y + _Z95 * sd)
        far = ~(np.isfinite(gain) & np.isfinite(upper) & np.isfinite(s))
        if far.any():
            raise OptionError(f"set-point {s[far][0]:g} is too far from the measured ones "
                              f"({self.setpoints.min():g}-{self.setpoints.max():g}) to "
                              "predict: the curve's band there is not finite")
        return {"setpoint": s, "gain": gain, "se": gain * sd,
                "lower": np.exp(y - _Z95 * sd), "upper": upper,
                "extrapolated": (s < self.setpoints.min()) | (s > self.setpoints.max())}


def _rises(coef, lo, hi) -> bool:
    """d ln g / d ln s > 0 over [lo, hi] (ln set-points)."""
    if len(coef) < 3:
        return coef[1] > 0
    x = np.linspace(lo, hi, 101)
    return bool(np.all(coef[1] + 2 * coef[2] * x > 0))


def fit_gain_curve(points) -> GainCurve:
    """Fit the gain curve to ``(set-point, gain, SE, …)`` points (:func:`measured_gains`).

    Raises
    ------
    OptionError
        Fewer than two distinct multiplied set-points, or gains that do not rise with
        the set-point.
    """
    pts = [p for p in points if p[0] != 1.0 and p[1] > 0 and p[2] is not None and p[2] > 0]
    s = np.array([p[0] for p in pts], dtype=float)
    if len(set(s)) < 2:
        have = ", ".join(format_setpoint(v) + "x" for v in sorted(set(s))) or "none"
        raise OptionError("a gain curve needs gains at two or more multiplied set-points "
                          f"(have {have})")
    g = np.array([p[1] for p in pts], dtype=float)
    se = np.array([p[2] for p in pts], dtype=float)
    x, y, w = np.log(s), np.log(g), (g / se) ** 2
    for degree in ((2, 1) if len(set(s)) >= 4 else (1,)):
        X = np.vander(x, degree + 1, increasing=True)
        A = X.T @ (w[:, None] * X)
        coef = np.linalg.solve(A, X.T @ (w * y))
        if _rises(coef, x.min(), x.max()):
            break
    else:
        raise OptionError("the measured gains do not rise with the set-point: "
                          + ", ".join(f"{format_setpoint(a)}x: {b:.4g}" for a, b in zip(s, g)))
    resid = y - X @ coef
    chi2 = float(np.sum(w * resid ** 2))
    dof = len(s) - degree - 1
    scale = max(1.0, chi2 / dof) if dof > 0 else 1.0
    return GainCurve(setpoints=s, gains=g, gain_se=se, coef=coef,
                     cov=np.linalg.inv(A) * scale, chi2=chi2, dof=dof)
