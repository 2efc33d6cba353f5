"""A calibration to use (:class:`Calibration`, :func:`load_calibration`): one result, or a group of them merged over their set-points, checked to be of one camera and read-out state; the identity a result records and the files behind a result."""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import xarray as xr

from .._util import format_setpoint

from .. import defaults, identity
from ..errors import InputError, InputWarning, OptionError
from .flags import PIXEL_FLAGS
from .schema import CALIBRATION_FILE
from .files import _checked_in_memory, load


# --------------------------------------------------------------------------------------
# A calibration to use: one result, or a group of them merged
# --------------------------------------------------------------------------------------
#: Methods that measure φ; in a group, φ comes from the one member that did.
_PHI_METHODS = ("is-adu", "mv-adu")


def _robust_sd(values) -> float | None:
    """1.4826 × the median absolute deviation: the SD of normal values, robust to a
    few outlying pixels."""
    values = values[np.isfinite(values)]
    if values.size < 2:
        return None
    return float(1.4826 * np.median(np.abs(values - np.median(values))))


def pixel_statistics(values) -> dict:
    """``{"median", "spread", "se_of_median", "n"}`` of a map's finite values: the median over
    pixels, its robust spread (1.4826 × MAD, in the map's units), the standard error of
    that median (√(π/2) × spread / √n, as for normal values; it includes the pixels' real
    spread, so it is conservative for the sensor's value) and how many pixels there were.
    Spread and SE are None for fewer than two values.

    Examples
    --------
    >>> pixel_statistics(np.array([[1.0, 2.0], [3.0, np.nan]]))
    {'median': 2.0, 'spread': 1.4826, 'se_of_median': 1.0728..., 'n': 3}
    """
    values = np.asarray(values, dtype=float).ravel()
    finite = values[np.isfinite(values)]
    spread = _robust_sd(finite)
    return {
        "median": float(np.median(finite)) if finite.size else None,
        "spread": spread,
        "se_of_median": None
        if spread is None
        else math.sqrt(math.pi / 2) * spread / math.sqrt(finite.size),
        "n": int(finite.size),
    }


@dataclass(frozen=True)
class Calibration:
    """A calibration ready to use: per-pixel φ, and per set-point the gain, offset and read
    noise, each with what its result says of it.

    Read with :func:`load_calibration` from one result or a group (an ``is-adu`` result
    with ``is-gain`` results, say). Maps are NaN where the pixel did not converge.

    Attributes
    ----------
    label : str
        How it was named: a file, or files joined by commas.
    files : tuple of Path
        The result files it was read from.
    sha256 : tuple of str
        SHA-256 (hex) of each file's bytes, in the order of ``files``: provenance.
    method : str
        The method of the result, or the members' methods joined by ``+``.
    e_per_adu, e_per_adu_se : ndarray, shape (R, C)
        φ (e⁻/ADU) and its standard error (NaN where the result has none: a φ held fixed).
    em_gain, em_gain_se : dict of float to ndarray (R, C)
        Gain per set-point (dimensionless) and its SE; set-point 1 excluded (it is 1).
    offset, read_noise : dict of float to ndarray (R, C)
        Offset S0 and read-noise σ (ADU) per set-point where the results record them:
        from the first member that has the set-point (the median over an intensity
        series' levels).
    offset_se, read_noise_se : dict of float to ndarray (R, C)
        Their standard errors (ADU), where the results record them (from the dark
        frames' count).
    stuck : ndarray (R, C) of bool, or None
        Pixels whose dark counts never changed in a member's darks (dead or stuck: left
        out of its fit), where a member reduced dark stacks.
    telegraph : ndarray (R, C) of bool, or None
        Pixels a member found to hold two or more offset states (random-telegraph pixels), where
        a member tested for them.
    telegraph_states : ndarray (R, C) of int8, or None
        The offset states the members counted (1 for one normal; 2 to 4, 4 meaning four or
        more), the most any member counted; where a member tested for them.
    hot : ndarray (R, C) of bool, or None
        Pixels a member found hot (a dark current far above the median pixel's), where
        a member measured the dark current.
    em_model : noise.EMModel
        The EM register model the gains were fitted with (the gamma model for results
        that record none).
    camera : dict
        What the stacks recorded of the camera (``serial``, ``model``, ``amplifier``,
        ``readout_rate_mhz``, ``analog_gain``, ``adc_bits``), merged over members.
    origin : tuple of int or None
        ``(row, col)`` of the first pixel on the sensor, where known.
    binning : tuple of int or None
        ``(x, y)`` binning the frames were read out with, where recorded.
    created : str
        Creation time of the newest member (ISO 8601 UTC).
    predicted : dict of float to dict
        Set-points not measured whose gain a gain curve predicts
        (:func:`emccdcal.export.gain_curve.calibration_at`): ``gain`` and ``se_of_median``
        of the sensor, ``extrapolated``, the ``curve`` it came from and the
        ``dark_setpoint`` whose offset and read noise stand in. Empty for a calibration
        read from results; recorded in :meth:`provenance`.

    Examples
    --------
    What every function that takes a calibration reads the Dataset of
    :func:`emccdcal.calibrate`, or a result's path, as:

    >>> import tempfile, emccdcal
    >>> sim = emccdcal.simulate_gain_series(
    ...     tempfile.mkdtemp(), rows=4, cols=4, frames=400, setpoints=(1, 10), seed=1,
    ...     progress=False,
    ... )
    >>> ds = emccdcal.calibrate(sim.manifest, e_per_adu=sim.truth["e_per_adu"], progress=False)
    >>> cal = emccdcal.load_calibration(ds)
    >>> cal.method, cal.setpoints, cal.gain(10).shape
    ('gs', (1.0, 10.0), (4, 4))
    """

    label: str
    files: tuple
    method: str
    e_per_adu: np.ndarray
    em_gain: dict
    e_per_adu_se: np.ndarray | None = None
    em_gain_se: dict = field(default_factory=dict)
    offset: dict = field(default_factory=dict)
    read_noise: dict = field(default_factory=dict)
    offset_se: dict = field(default_factory=dict)
    read_noise_se: dict = field(default_factory=dict)
    stuck: np.ndarray | None = None
    telegraph: np.ndarray | None = None
    telegraph_states: np.ndarray | None = None
    hot: np.ndarray | None = None
    em_model: object = None
    camera: dict = field(default_factory=dict)
    origin: tuple | None = None
    #: The results' ``camera_kind`` (``scmos``, ...), or None where they name none.
    camera_kind: str | None = None
    binning: tuple | None = None
    created: str = ""
    sha256: tuple = ()
    predicted: dict = field(default_factory=dict)

    @property
    def setpoints(self) -> tuple:
        """Set-points it has a gain for, 1 included (sorted)."""
        return tuple(sorted({1.0, *map(float, self.em_gain)}))

    @property
    def shape(self) -> tuple:
        """(rows, cols) of its maps."""
        return self.e_per_adu.shape

    def _missing(self, what, setpoint):
        have = ", ".join(format_setpoint(v) + "x" for v in self.setpoints)
        return OptionError(
            f"{self.label}: {what}set-point {format_setpoint(setpoint)}x is missing from this "
            f"calibration (it has {have}); add a result that has it, e.g. "
            "adu.nc,gain5x.nc,... (or predict it: emccdcal gain-curve)"
        )

    def gain(self, setpoint) -> np.ndarray:
        """Gain map at a set-point (1 at set-point 1).

        Raises
        ------
        OptionError
            The set-point is not in the calibration (the message names its files).
        """
        s = float(setpoint)
        if s == 1.0:
            return np.ones_like(self.e_per_adu)
        if s not in self.em_gain:
            raise self._missing("", s)
        return self.em_gain[s]

    def gain_se(self, setpoint) -> np.ndarray:
        """SE of the gain map at a set-point (0 at set-point 1)."""
        s = float(setpoint)
        if s == 1.0:
            return np.zeros_like(self.e_per_adu)
        self.gain(s)
        return self.em_gain_se.get(s, np.full_like(self.e_per_adu, np.nan))

    def dark(self, setpoint) -> tuple[np.ndarray, np.ndarray]:
        """Offset and read-noise maps (ADU) at a set-point.

        Raises
        ------
        OptionError
            No member recorded the offset at that set-point.
        """
        s = float(setpoint)
        if s not in self.offset:
            have = ", ".join(format_setpoint(v) + "x" for v in sorted(self.offset)) or "none"
            raise OptionError(
                f"{self.label}: no offset recorded at set-point {format_setpoint(s)}x "
                f"(offsets at: {have}); give the offset of the camera at that set-point"
            )
        return self.offset[s], self.read_noise.get(s, np.full_like(self.offset[s], np.nan))

    def identity(self) -> dict:
        """What identifies the camera and its read-out state: ``camera`` with ``binning``."""
        return {**self.camera, **({} if self.binning is None else {"binning": self.binning})}

    def provenance(self) -> dict:
        """What a file made from this calibration records of where it came from."""
        from .. import __version__

        doc = {
            "emccdcal_version": __version__,
            "method": self.method,
            "created": self.created,
            "em_model": str(self.em_model),
            "results": [{"file": str(f), "sha256": h} for f, h in zip(self.files, self.sha256)],
        }
        if self.predicted:
            doc["predicted_gains"] = [
                {"setpoint": s, **p} for s, p in sorted(self.predicted.items())
            ]
        return doc


#: What must agree between a calibration and the frames it is used on (where both
#: record it), with how to name it.
IDENTITY_FIELDS = defaults.IDENTITY_FIELDS


def identity_attrs(manifest) -> dict:
    """The attributes by which every result knows the camera, read-out state and pixels it
    holds for: ``camera`` (JSON), ``binning`` and ``sensor_origin``, as far as the
    manifest's frames record them, and ``camera_kind`` where the manifest names it."""
    attrs: dict[str, object] = {"camera": json.dumps(manifest.camera)} if manifest.camera else {}
    if getattr(manifest, "camera_kind", None):
        attrs["camera_kind"] = manifest.camera_kind
    if manifest.origin is not None:
        attrs["sensor_origin"] = np.array(manifest.origin, dtype=np.int64)
    if manifest.binning is not None:
        attrs["binning"] = np.array(manifest.binning, dtype=np.int64)
    return attrs


def result_files(specs) -> list[Path]:
    """The result files named by ``specs`` (files, directories, comma-joined groups, and
    results in memory that were read or written)."""
    files = []
    for spec in specs:
        for part in _members(spec):
            if isinstance(part, xr.Dataset):  # in memory: the file it was read or written as
                part = part.encoding.get("source")
            if part is not None:
                p = Path(part)
                files.append(p / CALIBRATION_FILE if p.is_dir() else p)
    return files


def camera_of(ds, path) -> dict:
    """What a result records of its camera (``attrs["camera"]``, JSON), checked."""
    text = ds.attrs.get("camera", "{}")
    try:
        camera = json.loads(str(text))
        if not isinstance(camera, dict):
            raise ValueError("not an object")
    except ValueError as exc:
        raise InputError(f"{path}: its camera attribute is not a JSON object ({exc})") from None
    return camera


def _members(spec):
    """The members of a calibration argument: paths (text) and results in memory."""
    if isinstance(spec, xr.Dataset):
        return [spec]
    if isinstance(spec, (str, Path)) and "," in str(spec) and Path(spec).exists():
        return [str(spec)]  # a path with a comma in its name
    if isinstance(spec, (list, tuple)):
        parts = [p if isinstance(p, xr.Dataset) else str(p) for p in spec]
    else:
        parts = [p.strip() for p in str(spec).split(",")]
    parts = [p for p in parts if isinstance(p, xr.Dataset) or p]
    if not parts:
        raise OptionError(f"empty calibration argument {spec!r}")
    return parts


def _span(values):
    values = np.asarray(values)
    return f"{values.min()}–{values.max()}" if values.size else "(none)"


def _acquisition_setpoints(ds, dim):
    """The set-point of each entry of a per-acquisition dimension: the set-points
    themselves, or for ``level`` the result's one set-point (an intensity series)."""
    if dim == "setpoint":
        return ds["setpoint"].values.astype(float)
    setpoints = ds["setpoint"].values.astype(float) if "setpoint" in ds.coords else [1.0]
    return np.full(ds.sizes[dim], float(setpoints[0]) if len(setpoints) == 1 else np.nan)


def _load_members(parts, label, shape, of) -> list:
    """``[(file, dataset)]`` of a group's members, each given once and, where ``shape``
    is given, covering exactly that sensor region."""
    loaded: list = []
    for part in parts:
        if isinstance(part, xr.Dataset):  # a result in memory: checked as a file is
            ds = _checked_in_memory(part)
            # its file, where it was read from one or written to one (its provenance)
            loaded.append((Path(ds.encoding.get("source", "<the result given>")), ds))
            continue
        p = Path(part)
        ds = load(p)
        f = p / CALIBRATION_FILE if p.is_dir() else p
        twice = [g for g, _ in loaded if g.resolve() == f.resolve()]
        if twice:
            raise OptionError(f"{label}: {f} is given twice; give each result once")
        rows, cols = ds["row"].values, ds["col"].values
        if shape is not None:
            R, C = shape
            if not (np.array_equal(rows, np.arange(R)) and np.array_equal(cols, np.arange(C))):
                raise OptionError(
                    f"{f}: calibration covers rows {_span(rows)} and columns {_span(cols)}, "
                    f"but {of} are {R}×{C} (rows 0–{R - 1}, columns 0–{C - 1}); "
                    "a calibration of the same sensor region is needed"
                )
        loaded.append((f, ds))
    return loaded


def _members_em_model(label, loaded):
    """The one register model of a group's members: that of those that measured a gain
    (1x has no register); of a 1x-only group, the model it was fitted with, else the
    default."""
    from ..model.noise import EMModel

    models = {
        EMModel.from_attrs(ds.attrs)
        for _, ds in loaded
        if "em_gain" in ds and np.any(ds["setpoint"].values != 1)
    } - {None}
    if len(models) > 1:
        raise OptionError(
            f"{label}: its members were fitted with different EM register "
            f"models ({', '.join(sorted(map(str, models)))}); group results "
            "of one model"
        )
    if not models:  # 1x only (is-adu): the model it was fitted with, else the default's
        models = {
            next(
                (m for m in (EMModel.from_attrs(ds.attrs) for _, ds in loaded) if m),
                EMModel(defaults.DEFAULT_EM_MODEL),
            )
        }
    return models.pop()


def _dark_maps(loaded, masked) -> dict:
    """What the members' dark frames gave, for :class:`Calibration`: per set-point the
    offset and read-noise maps and their SEs (from the first member that has the
    set-point; an intensity series' levels merged by their median), and the pixels any
    member flagged (:data:`emccdcal.result.flags.PIXEL_FLAGS`) with the offset states
    counted at random-telegraph pixels."""
    out: dict[str, dict] = {
        name: {} for name in ("offset", "read_noise", "offset_se", "read_noise_se")
    }
    flags: dict[str, np.ndarray | None] = dict.fromkeys(PIXEL_FLAGS)
    states = None
    for _, ds in loaded:
        for name, kept in flags.items():
            if name in ds:
                found = ds[name].transpose("row", "col").values.astype(bool)
                flags[name] = found if kept is None else kept | found
        if "telegraph_states" in ds:
            counted = ds["telegraph_states"].transpose("row", "col").values.astype(np.int8)
            states = counted if states is None else np.maximum(states, counted)
        for name in out:
            maps, store = masked(ds, name), out[name]
            if maps is None:
                continue
            dim = ds[name].dims[0] if ds[name].ndim == 3 else None
            at = _acquisition_setpoints(ds, dim) if dim else [1.0]
            maps = maps if dim else maps[None]
            for s in dict.fromkeys(at):  # first member first; levels at one set-point merged
                if np.isfinite(s) and s not in store:
                    with warnings.catch_warnings():  # a pixel left out: NaN, not a warning
                        warnings.filterwarnings("ignore", "All-NaN slice", RuntimeWarning)
                        store[s] = np.nanmedian(maps[np.asarray(at) == s], axis=0)
    return {**out, **flags, "telegraph_states": states}


def load_calibration(spec, shape=None, *, of="the frames") -> Calibration:
    """A calibration from what a user has: a result file, a result in memory, or a group
    of them merged; the one door every function that takes a calibration goes through.

    Parameters
    ----------
    spec : str, Path, xarray.Dataset, Calibration or sequence of them
        A ``calibration.nc`` file or its directory, or several joined by commas; a
        result as :func:`emccdcal.calibrate` or :func:`load` returns it; a
        :class:`Calibration` (returned as it is, checked against ``shape``).
    shape : (int, int), optional
        The frames' (rows, cols): every file must cover exactly that sensor region
        (``row`` = 0 … rows − 1 and ``col`` = 0 … cols − 1).
    of : str
        What ``shape`` belongs to, for the message when a file does not fit it.

    Returns
    -------
    Calibration

    Raises
    ------
    FileNotFoundError, ValueError
        A missing or unreadable file, one of another sensor size or region, two members
        giving the same set-point, two members that both measured φ, or members fitted
        with different register models. The message names the file.

    Examples
    --------
    >>> import tempfile, emccdcal
    >>> work = tempfile.mkdtemp()
    >>> sim = emccdcal.simulate_gain_series(
    ...     f"{work}/gs", rows=4, cols=4, frames=400, setpoints=(1, 10), seed=1, progress=False
    ... )
    >>> ds = emccdcal.calibrate(sim.manifest, e_per_adu=sim.truth["e_per_adu"], progress=False)
    >>> cal = emccdcal.load_calibration(ds)
    >>> cal.setpoints, cal.gain(10).shape
    ((1.0, 10.0), (4, 4))
    """

    if isinstance(spec, Calibration):
        if shape is not None and tuple(spec.e_per_adu.shape) != tuple(shape):
            raise OptionError(
                f"{spec.label}: calibration of {spec.e_per_adu.shape[0]}×"
                f"{spec.e_per_adu.shape[1]} px, but {of} are {shape[0]}×{shape[1]}"
            )
        return spec
    parts = _members(spec)
    label = ",".join(p if isinstance(p, str) else "the result given" for p in parts)
    loaded = _load_members(parts, label, shape, of)
    shapes = {(ds.sizes["row"], ds.sizes["col"]) for _, ds in loaded}
    if len(shapes) > 1:
        raise OptionError(f"{label}: the files cover different sensor regions {sorted(shapes)}")
    methods = [str(ds.attrs.get("method", "?")) for _, ds in loaded]

    def masked(ds, name):
        if name not in ds:
            return None
        ok = ds["converged"].transpose("row", "col").values.astype(bool)
        return np.where(ok, ds[name].transpose(..., "row", "col").values.astype(float), np.nan)

    phi_from = [i for i, m in enumerate(methods) if m in _PHI_METHODS]
    if len(phi_from) > 1:
        raise OptionError(
            f"{label}: {loaded[phi_from[0]][0]} and {loaded[phi_from[1]][0]} both measured "
            "e_per_adu; a group takes phi from one of them"
        )
    i_phi = phi_from[0] if phi_from else 0
    phi = masked(loaded[i_phi][1], "e_per_adu")
    gains: dict = {}
    gains_se: dict = {}
    source: dict = {}
    dark = _dark_maps(loaded, masked)
    camera: dict = {}
    other_phi = []
    for f, ds in loaded:
        recorded = camera_of(ds, f)
        differ = identity.mismatches(camera, recorded)
        if differ:
            raise OptionError(
                f"{label}: {f} is of another camera or read-out state than "
                f"the members before it: {'; '.join(differ.values())}"
            )
        camera.update({k: v for k, v in recorded.items() if k not in camera})
        if "em_gain" not in ds:
            continue
        g, g_se = masked(ds, "em_gain"), masked(ds, "em_gain_se")
        for j, s in enumerate(ds["setpoint"].values.astype(float)):
            if s == 1.0:
                continue
            if s in gains:
                raise OptionError(
                    f"{label}: set-point {format_setpoint(s)}x is in both {source[s]} "
                    f"and {f}; give each set-point once"
                )
            gains[s], gains_se[s], source[s] = g[j], g_se[j], f
        # g/φ is what a gain fit measures: note members fitted with another φ.
        other = masked(ds, "e_per_adu")
        both = np.isfinite(other) & np.isfinite(phi)
        if len(loaded) > 1 and both.any() and not np.allclose(other[both], phi[both], rtol=1e-6):
            other_phi.append(f"{f.name} ({np.median(other[both]):.4g})")
    if other_phi:
        warnings.warn(
            f"{label}: gains of {', '.join(other_phi)} were fitted with another e_per_adu "
            f"(median, e-/ADU) than the group's phi from {loaded[i_phi][0].name} "
            f"({np.nanmedian(phi):.4g}); the group uses its phi",
            stacklevel=2,
            category=InputWarning,
        )
    model = _members_em_model(label, loaded)
    origins = {
        tuple(int(v) for v in ds.attrs["sensor_origin"])
        for _, ds in loaded
        if "sensor_origin" in ds.attrs
    }
    binnings = {
        tuple(int(v) for v in np.atleast_1d(ds.attrs["binning"]))
        for _, ds in loaded
        if "binning" in ds.attrs
    }
    if len(binnings) > 1:
        raise OptionError(
            f"{label}: its members were read out with different binnings "
            f"({', '.join('x'.join(map(str, b)) for b in sorted(binnings))})"
        )
    return Calibration(
        label=label,
        files=tuple(f for f, _ in loaded),
        method="+".join(dict.fromkeys(methods)),
        e_per_adu=phi,
        e_per_adu_se=masked(loaded[i_phi][1], "e_per_adu_se"),
        em_gain=gains,
        em_gain_se=gains_se,
        **dark,
        em_model=model,
        camera=camera,
        origin=origins.pop() if len(origins) == 1 else None,
        binning=binnings.pop() if binnings else None,
        created=max(str(ds.attrs.get("created", "")) for _, ds in loaded),
        camera_kind=next(
            (str(ds.attrs["camera_kind"]) for _, ds in loaded if "camera_kind" in ds.attrs), None
        ),
        sha256=tuple(ds.encoding.get("sha256", "") for _, ds in loaded),
    )
