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

:func:`calibration_at` takes a prediction where a calibration lacks the set-point a
movie was recorded at (``export``/``apply --setpoint G --gain-curve FILE``, or the
database's curve): the nearest measured set-point's gain map scaled to the predicted
sensor gain, its offset and read noise, and a record of where the gain came from.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import xarray as xr

from .. import _files
from ..errors import ExportWarning, InputError, OptionError
from ..identity import mismatches as identity_mismatches
from ..result import Calibration, format_setpoint, load_calibration, pixel_statistics

__all__ = [
    "GainCurve",
    "fit_gain_curve",
    "fit_points",
    "measured_gains",
    "read_gain_curve",
    "calibration_at",
]

_Z95 = 1.959963984540054


def _point(setpoint, gain_map, label):
    st = pixel_statistics(gain_map)
    if st["se_of_median"] is None:
        return None
    return float(setpoint), st["median"], st["se_of_median"], label


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
    points: list = []
    seen: dict = {}
    identity = None
    for i, cal in enumerate(calibrations):
        if hasattr(cal, "data_vars"):  # an xarray result dataset
            if "em_gain" not in cal:
                continue
            ok = cal["converged"].values.astype(bool)
            maps = {
                float(s): np.where(ok, cal["em_gain"].sel(setpoint=s).values, np.nan)
                for s in cal["setpoint"].values
            }
            label = str(cal.attrs.get("method", f"result {i + 1}"))
        else:
            cal = load_calibration(cal)
            for f, digest in zip(cal.files, cal.sha256):
                if digest and digest in seen:
                    raise OptionError(
                        f"{f} is given twice (also as {seen[digest]}): each "
                        "result would be counted twice; give it once"
                    )
                seen[digest] = f
            if identity is None:
                identity = (cal.label, cal.identity())
            differ = identity_mismatches(identity[1], cal.identity(), accept=accept_mismatch)
            if differ:
                raise OptionError(
                    f"{cal.label} is of another camera or read-out state than "
                    f"{identity[0]}: {'; '.join(differ.values())}; a gain curve "
                    "is of one camera (--accept-mismatch "
                    f"{' '.join(differ)} if you know better)"
                )
            maps, label = {s: cal.gain(s) for s in cal.setpoints}, cal.label
        points += [
            p for s, m in maps.items() if s != 1.0 for p in [_point(s, m, label)] if p is not None
        ]
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
    camera : dict
        The identity of the camera and read-out state the gains were measured on
        (:meth:`~emccdcal.result.Calibration.identity`), where known.
    results : tuple of dict
        ``{"file", "sha256"}`` of each calibration result it was fitted to.
    """

    setpoints: np.ndarray
    gains: np.ndarray
    gain_se: np.ndarray
    coef: np.ndarray
    cov: np.ndarray
    chi2: float
    dof: int
    camera: dict = field(default_factory=dict)
    results: tuple = ()

    @property
    def degree(self) -> int:
        return len(self.coef) - 1

    def as_dict(self) -> dict:
        """The curve as ``gain-curve.json`` holds it (JSON-ready; :func:`read_gain_curve`)."""
        return {
            "model": f"ln g = sum_k b_k (ln setpoint)^k, k <= {self.degree}",
            "coefficients": self.coef.tolist(),
            "covariance": self.cov.tolist(),
            "chi2": self.chi2,
            "dof": self.dof,
            "measured": [
                {"setpoint": float(s), "gain": float(g), "se_of_median": float(e)}
                for s, g, e in zip(self.setpoints, self.gains, self.gain_se)
            ],
            "camera": {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.camera.items()},
            "results": list(self.results),
        }

    def predict(self, setpoints) -> dict:
        """Gain at any set-points, with SE and the 95 % band.

        Returns
        -------
        dict of ndarray
            ``setpoint``, ``gain``, ``se_of_median`` (the standard error of the sensor's
            gain the curve predicts), ``lower``, ``upper`` and ``extrapolated`` (bool:
            outside the measured set-points).
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
            raise OptionError(
                f"set-point {s[far][0]:g} is too far from the measured ones "
                f"({self.setpoints.min():g}-{self.setpoints.max():g}) to "
                "predict: the curve's band there is not finite"
            )
        return {
            "setpoint": s,
            "gain": gain,
            "se_of_median": gain * sd,
            "lower": np.exp(y - _Z95 * sd),
            "upper": upper,
            "extrapolated": (s < self.setpoints.min()) | (s > self.setpoints.max()),
        }


def _rises(coef, lo, hi) -> bool:
    """d ln g / d ln s > 0 over [lo, hi] (ln set-points)."""
    if len(coef) < 3:
        return coef[1] > 0
    x = np.linspace(lo, hi, 101)
    return bool(np.all(coef[1] + 2 * coef[2] * x > 0))


def fit_points(points) -> GainCurve:
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
        raise OptionError(
            f"a gain curve needs gains at two or more multiplied set-points (have {have})"
        )
    g = np.array([p[1] for p in pts], dtype=float)
    se = np.array([p[2] for p in pts], dtype=float)
    x, y, w = np.log(s), np.log(g), (g / se) ** 2
    for degree in (2, 1) if len(set(s)) >= 4 else (1,):
        X = np.vander(x, degree + 1, increasing=True)
        A = X.T @ (w[:, None] * X)
        coef = np.linalg.solve(A, X.T @ (w * y))
        if _rises(coef, x.min(), x.max()):
            break
    else:
        raise OptionError(
            "the measured gains do not rise with the set-point: "
            + ", ".join(f"{format_setpoint(a)}x: {b:.4g}" for a, b in zip(s, g))
        )
    resid = y - X @ coef
    chi2 = float(np.sum(w * resid**2))
    dof = len(s) - degree - 1
    scale = max(1.0, chi2 / dof) if dof > 0 else 1.0
    return GainCurve(
        setpoints=s,
        gains=g,
        gain_se=se,
        coef=coef,
        cov=np.linalg.inv(A) * scale,
        chi2=chi2,
        dof=dof,
    )


def fit_gain_curve(results, *, accept_mismatch=()) -> GainCurve:
    """The gain curve of calibration results: the gain as a smooth, rising function of the
    set-point, fitted to every measured set-point's median gain with its SE, with the
    camera's identity and the results' SHA-256 recorded.

    Parameters
    ----------
    results : xarray.Dataset, Calibration, str or Path, or a sequence of them
        What :func:`emccdcal.calibrate` or :func:`emccdcal.load_result` returns, a
        calibration, or result files or folders (:func:`emccdcal.load_calibration`); of
        one camera and read-out state.
    accept_mismatch : sequence of str
        Camera identity fields that may differ between the results.

    Returns
    -------
    GainCurve
        ``gain(setpoint)`` and its SE, the points and the fit's χ².

    Raises
    ------
    OptionError
        Fewer than two multiplied set-points, gains that do not rise with the set-point,
        results of different cameras.

    Examples
    --------
    >>> import emccdcal
    >>> curve = emccdcal.fit_gain_curve(ds)  # doctest: +SKIP
    >>> curve.predict([200.0])  # doctest: +SKIP
    """
    if isinstance(results, (str, Path, xr.Dataset, Calibration)):
        results = [results]
    cals = [load_calibration(r) for r in results]
    curve = fit_points(measured_gains(cals, accept_mismatch=accept_mismatch))
    return dataclasses.replace(
        curve,
        camera=cals[0].identity(),
        results=tuple(
            {"file": str(f), "sha256": h} for c in cals for f, h in zip(c.files, c.sha256)
        ),
    )


def read_gain_curve(path) -> GainCurve:
    """A curve from the ``gain-curve.json`` that ``emccdcal gain-curve`` wrote.

    Raises
    ------
    InputError
        Not such a file (missing, not JSON, or written before the file recorded its
        measured points).
    """
    path = Path(path)
    try:
        doc = _files.load_json(path, what="gain curve")
        measured = doc["measured"]
        coef = np.asarray(doc["coefficients"], dtype=float)
        cov = np.asarray(doc["covariance"], dtype=float)
        setpoints = np.array([m["setpoint"] for m in measured], dtype=float)
        gains = np.array([m["gain"] for m in measured], dtype=float)
        se = np.array([m["se_of_median"] for m in measured], dtype=float)
    except OSError as exc:
        raise InputError(f"{path}: cannot read the gain curve ({exc.strerror or exc})") from None
    except (ValueError, KeyError, TypeError):
        raise InputError(
            f"{path}: not a gain curve written by emccdcal gain-curve (or one "
            "from before it recorded its measured points): run gain-curve "
            "again"
        ) from None
    if coef.ndim != 1 or cov.shape != (coef.size, coef.size) or setpoints.size < 2:
        raise InputError(
            f"{path}: a damaged gain curve (coefficients {coef.shape}, "
            f"covariance {cov.shape}, {setpoints.size} measured points)"
        )
    camera = doc.get("camera") or {}
    if "binning" in camera:
        camera["binning"] = tuple(camera["binning"])
    return GainCurve(
        setpoints=setpoints,
        gains=gains,
        gain_se=se,
        coef=coef,
        cov=cov,
        chi2=float(doc.get("chi2", math.nan)),
        dof=int(doc.get("dof", 0)),
        camera=camera,
        results=tuple(doc.get("results", ())),
    )


def _nearest(setpoints, s):
    """The set-point nearest to ``s`` on a log scale (the lower one on a tie)."""
    return min(setpoints, key=lambda v: (abs(math.log(v / s)), v)) if setpoints else None


def calibration_at(
    cal: Calibration, setpoint, curve: GainCurve, *, source: str, accept_mismatch=()
) -> Calibration:
    """The calibration with a gain at a set-point it did not measure, from a gain curve.

    The gain map is the nearest measured set-point's (on a log scale) scaled to the
    curve's sensor gain, which keeps the register's pixel-to-pixel pattern; with no
    measured gain (an ``is-adu`` result alone) it is the curve's gain at every pixel
    with a φ. Each pixel's relative SE is the curve's relative SE combined with that
    pixel's own at the nearest set-point. Offset and read noise (ADU, which the EM gain
    does not change) are those of the nearest set-point with darks. A warning says what
    was predicted; :attr:`~emccdcal.result.Calibration.predicted` and the provenance of
    every file made from the calibration record it, with ``extrapolated``.

    Parameters
    ----------
    cal : Calibration
    setpoint : float
        The set-point to add (dimensionless). Returned unchanged where measured.
    curve : GainCurve
        Of the same camera and read-out state.
    source : str
        Where the curve came from, for messages and the record.
    accept_mismatch : iterable of str
        Identity fields in which the curve's camera may differ.

    Raises
    ------
    OptionError
        The curve is of another camera or read-out state, or the set-point is too far
        from the measured ones to predict.
    """
    s = float(setpoint)
    if s == 1.0 or s in cal.em_gain:
        return cal
    differ = identity_mismatches(cal.identity(), curve.camera, accept=accept_mismatch)
    if differ:
        raise OptionError(
            f"{source}: the gain curve is of another camera or read-out state "
            f"than {cal.label}: {'; '.join(differ.values())} (--accept-mismatch "
            f"{' '.join(differ)} if you know better)"
        )
    p = curve.predict([s])
    gain, se = float(p["gain"][0]), float(p["se_of_median"][0])
    extrapolated = bool(p["extrapolated"][0])
    near = _nearest(list(cal.em_gain), s)
    if near is None:
        gain_map = np.where(np.isfinite(cal.e_per_adu), gain, np.nan)
        rel_se = np.full_like(gain_map, se / gain)
    else:
        base = cal.em_gain[near]
        gain_map = base * (gain / np.nanmedian(base))
        rel_se = np.hypot(se / gain, cal.gain_se(near) / base)
    dark = _nearest(list(cal.offset), s)
    record = {
        "gain": gain,
        "se_of_median": se,
        "extrapolated": extrapolated,
        "curve": source,
        "map_from_setpoint": near,
        "dark_setpoint": dark,
    }
    lo, hi = curve.setpoints.min(), curve.setpoints.max()
    where = (
        f"extrapolated beyond the measured {format_setpoint(lo)}x-{format_setpoint(hi)}x:"
        f" check it with a calibration at {format_setpoint(s)}x"
        if extrapolated
        else f"within the measured {format_setpoint(lo)}x-{format_setpoint(hi)}x"
    )
    warnings.warn(
        f"{cal.label}: set-point {format_setpoint(s)}x was not calibrated; its gain "
        f"{gain:.4g} ± {se:.2g} (standard error of the sensor's gain) is predicted "
        f"by the gain curve {source}, {where}"
        + (
            ""
            if dark is None or dark == s
            else f"; offset and read noise from the {format_setpoint(dark)}x darks"
        ),
        stacklevel=2,
        category=ExportWarning,
    )
    offset, read_noise = dict(cal.offset), dict(cal.read_noise)
    if dark is not None:
        offset[s], read_noise[s] = cal.offset[dark], cal.read_noise.get(dark)
        if read_noise[s] is None:
            del read_noise[s]
    return dataclasses.replace(
        cal,
        em_gain={**cal.em_gain, s: gain_map},
        em_gain_se={**cal.em_gain_se, s: gain_map * rel_se},
        offset=offset,
        read_noise=read_noise,
        predicted={**cal.predicted, s: record},
    )
