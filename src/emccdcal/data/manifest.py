"""The manifest: the acquisitions of one calibration, checked before anything is fitted.

A calibration starts from a TOML manifest (``docs/manifest.md``): one
``[[acquisition]]`` table per stack of raw counts, with its EM gain set-point and either
per-pixel ``offset`` and ``read_noise`` maps or a ``dark`` stack they are computed from,
and an optional top-level ``e_per_adu``. :func:`read_manifest` reads it and checks
*everything* a fit needs before any fitting starts; every problem is reported as one
line naming the file and the problem (:class:`~emccdcal.errors.ManifestError`).

Units (``docs/results.md``): counts, offset and read noise in ADU; ``e_per_adu`` in
e⁻/ADU; ``em_gain_setpoint`` dimensionless.
"""

from __future__ import annotations

import difflib
import hashlib
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib

from .._util import one_line
from ..errors import InputError, ManifestError, OptionError, ReadNoiseGrowthWarning
from .dark import check_read_noise_growth, fit_dark, maps_from_dark
from .stacks import (
    check_counts,
    content_fingerprint,
    stack_settings,
    check_readable,
    default_adc_max,
    describe_first,
    describe_missing,
    load_stack,
    needs_scan,
    read_map,
    stack_header,
)

__all__ = [
    "Acquisition",
    "Manifest",
    "read_manifest",
    "TOP_LEVEL_KEYS",
    "ACQUISITION_KEYS",
]

#: The camera settings that identify a camera's read-out state (a calibration holds for
#: that state only), recorded in results as ``attrs["camera"]``.
CAMERA_IDENTITY = ("serial", "model", "readout_rate_mhz", "analog_gain", "adc_bits")

#: Keys allowed at the top level of a manifest.
TOP_LEVEL_KEYS = ("e_per_adu", "adc_bits", "origin", "em_model", "register_stages",
                  "acquisition")
#: Keys allowed in an ``[[acquisition]]`` table.
ACQUISITION_KEYS = (
    "frames",
    "em_gain_setpoint",
    "offset",
    "read_noise",
    "dark",
    "level",
    "skip_frames",
    "name",
    "dark_frames",
)


# --------------------------------------------------------------------------------------
# Data classes
# --------------------------------------------------------------------------------------
@dataclass(eq=False)
class Acquisition:
    """One stack of raw counts at one EM gain set-point, with its offset and read noise.

    Attributes
    ----------
    name : str
        Label: the manifest's ``name``, else the frames file's stem.
    frames_path : Path
        The stack of raw counts, shape (frames, rows, cols).
    em_gain_setpoint : float
        The camera's EM gain setting (dimensionless, ≥ 1; 1 means no multiplication).
    level : str or None
        Label of the illumination level, if given.
    skip_frames : int
        Frames dropped at the start of the stack.
    offset : ndarray of float64, shape (rows, cols)
        Per-pixel offset S0, ADU.
    read_noise : ndarray of float64, shape (rows, cols)
        Per-pixel read noise σ, ADU (> 0).
    offset_source, read_noise_source : str
        Where the maps came from: the map file, the dark stack (``"dark <path>"``), or
        ``"value <number>"`` for a number in the manifest.
    n_frames_total : int
        Frames in the file, before ``skip_frames``.
    dark_frames : int or None
        Dark frames behind the offset and read-noise maps: the dark stack's length, or the
        manifest's ``dark_frames``. ``None`` means the maps are taken as exact.
    dark_event_rate : ndarray or None
        Multiplied electrons per pixel per frame (e⁻) in the dark stack of a multiplied
        acquisition, fitted with its maps (:func:`emccdcal.data.dark.fit_dark`); None for
        maps given as files, 1× darks and darks without events.
    """

    name: str
    frames_path: Path
    em_gain_setpoint: float
    level: str | None
    skip_frames: int
    offset: np.ndarray = field(repr=False)
    read_noise: np.ndarray = field(repr=False)
    offset_source: str
    read_noise_source: str
    n_frames_total: int
    dark_frames: int | None = None
    dark_event_rate: np.ndarray | None = field(default=None, repr=False)

    @property
    def n_frames(self) -> int:
        """Frames used: those in the file minus ``skip_frames``."""
        return self.n_frames_total - self.skip_frames

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the frames."""
        return tuple(int(d) for d in self.offset.shape)

    def frames(self) -> np.ndarray:
        """The (n_frames, rows, cols) stack of raw counts (ADU), after ``skip_frames``.

        A read-only memory map where the file allows it (uncompressed TIFF, ``.npy``),
        so nothing is loaded until used; otherwise the file is read on each call. The
        dtype is the file's (possibly non-native byte order).
        """
        return load_stack(self.frames_path)[self.skip_frames :]


@dataclass(eq=False)
class Manifest:
    """A validated manifest: the acquisitions of one calibration and their settings.

    Attributes
    ----------
    path : Path
        The manifest file.
    content_hash : str
        SHA-256 (hex) of the manifest file's bytes.
    e_per_adu : None, float or ndarray of float64 (rows, cols)
        ADU conversion factor φ, e⁻/ADU, if given: a number stays a number, a map file
        gives a map.
    e_per_adu_source : str or None
        The map file, ``"value <number>"``, ``"result <path>"`` (φ and its standard
        error from an ``is-adu`` or ``mv-adu`` result, read by the calibration; then
        ``e_per_adu`` is None), or None when ``e_per_adu`` is absent.
    acquisitions : list of Acquisition
        In manifest order.
    shape : tuple of int
        (rows, cols) shared by all stacks and maps.
    adc_max : int
        ADC maximum, ADU: ``2**adc_bits - 1``. Counts at or above it are saturated.
    setpoints : tuple of float
        Sorted distinct EM gain set-points.
    levels : tuple of str
        Distinct illumination levels, in order of first appearance (acquisitions without
        a level are not represented).
    warnings : list of str
        Non-fatal findings (e.g. read noise growing with set-point), also issued with
        :func:`warnings.warn`.
    """

    path: Path
    content_hash: str
    e_per_adu: None | float | np.ndarray = field(repr=False)
    e_per_adu_source: str | None
    acquisitions: list[Acquisition]
    shape: tuple[int, int]
    adc_max: int
    setpoints: tuple[float, ...]
    levels: tuple[str, ...]
    warnings: list[str] = field(default_factory=list)
    #: (row, col) of the stacks' first pixel on the sensor: the manifest's ``origin``,
    #: else what the files record (their ROI), else None (unknown).
    origin: tuple[int, int] | None = None
    #: (x, y) binning the files record, or None (not recorded).
    binning: tuple[int, int] | None = None
    #: The EM register's model (``em_model`` and ``register_stages``), or None: not
    #: given (the calibration's own default, the paper's gamma model).
    em_model: object = None
    #: What every frames file records alike of the camera (``serial``, ``model``,
    #: ``readout_rate_mhz``, ``analog_gain``, ``adc_bits``): the identity a calibration
    #: database keys on. A field the files leave out or disagree on is absent.
    camera: dict = field(default_factory=dict)

    @property
    def rows_cols(self) -> str:
        """The sensor rows and columns the stacks cover, for messages."""
        if self.origin is None:
            return f"{self.shape[0]} × {self.shape[1]} px at an unknown place on the sensor"
        return _region_text(self.origin, self.shape)


def _origin(r, written, recorded: set, shape):
    """The stacks' sensor origin: the manifest's, else the one the files record."""
    if len(recorded) > 1:
        texts = "; ".join(_region_text(o, shape) for o in sorted(recorded))
        raise r.error(f"the stacks record different regions of the sensor ({texts}): a "
                      "calibration needs the same pixels in every acquisition")
    if written is not None:
        if recorded and tuple(written) not in recorded:
            warnings.warn(f"{r.path}: origin = {list(written)}, but the files record "
                          f"{list(next(iter(recorded)))}; the manifest's is used", stacklevel=3)
        return tuple(int(v) for v in written)
    return next(iter(recorded)) if recorded else None


def _binning(r, recorded: set):
    """The stacks' (x, y) binning where the files record one; different ones are an error."""
    if len(recorded) > 1:
        raise r.error(f"the stacks record different binnings ({', '.join(map(str, sorted(recorded)))}): "
                      "a calibration needs the same pixels in every acquisition")
    return next(iter(recorded)) if recorded else None


def _region_text(origin, shape) -> str:
    (r0, c0), (h, w) = origin, shape
    return f"sensor rows {r0}–{r0 + h - 1}, cols {c0}–{c0 + w - 1}"


# --------------------------------------------------------------------------------------
# The manifest
# --------------------------------------------------------------------------------------
#: Requirements on map-valued keys: (positive, nonnegative).
_MAP_RULES = {
    "offset": (False, True),
    "read_noise": (True, False),
    "e_per_adu": (True, False),
}


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _unknown_key_message(key: str, allowed) -> str:
    close = difflib.get_close_matches(key, allowed, n=1, cutoff=0.6)
    hint = f"; did you mean '{close[0]}'?" if close else ""
    return f"unknown key '{key}'{hint} (allowed: {', '.join(allowed)})"


class _Reader:
    """The state of one :func:`read_manifest` call: messages name the manifest."""

    def __init__(self, path: Path):
        self.path = path
        self.base = path.parent

    def error(self, message: str, entry: int | None = None, label: str = "") -> ManifestError:
        where = f"{self.path}: "
        if entry is not None:
            where += f"acquisition {entry}" + (f" ({label})" if label else "") + ": "
        return ManifestError(where + message)

    def resolve(self, written: str) -> Path:
        p = Path(written).expanduser()
        return p if p.is_absolute() else self.base / p


def read_manifest(path) -> Manifest:
    """Read and validate a calibration manifest.

    Everything is checked before any fitting: TOML syntax, keys (with a suggestion for a
    misspelt one), types and ranges of values, that every file exists and is readable,
    that stacks are 3-D and share (rows, cols), that maps have that shape and valid
    values, that stacks hold raw counts (non-negative integers, at most the ADC maximum),
    and that ``skip_frames`` leaves frames to use. Dark stacks are reduced to offset and
    read-noise maps here, each file once: at 1× their mean and SD
    (:func:`emccdcal.data.dark.maps_from_dark`), at a multiplied set-point by a fit of the
    read-out and its multiplied events (:func:`emccdcal.data.dark.fit_dark`), whose plain
    SD the events would inflate.

    Parameters
    ----------
    path : str or Path
        The TOML manifest; relative paths inside it are relative to its folder.

    Returns
    -------
    Manifest

    Raises
    ------
    ManifestError
        A ``ValueError`` whose one-line message names the manifest, the acquisition (1-based,
        in file order), the data file if any, and the problem.

    Warns
    -----
    ReadNoiseGrowthWarning
        When the read noise grows with the set-point by more than 5 %
        (:func:`emccdcal.data.dark.check_read_noise_growth`); also in ``Manifest.warnings``.

    Notes
    -----
    The format, with examples and every error message, is in ``docs/manifest.md``.
    """
    path = Path(path)
    r = _Reader(path)
    if not path.exists():
        raise ManifestError(describe_missing(path, "manifest file"))
    if path.is_dir():
        raise ManifestError(f"{path}: is a directory, not a manifest file")
    raw = path.read_bytes()
    content_hash = hashlib.sha256(raw).hexdigest()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise r.error(f"not UTF-8 text (byte {exc.start}); a manifest is a TOML file") from None
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise r.error(f"invalid TOML: {one_line(exc)}") from None

    # ---- structure, keys and types (cheap; nothing read yet) -------------------------
    for key in doc:
        if key not in TOP_LEVEL_KEYS:
            raise r.error(_unknown_key_message(key, TOP_LEVEL_KEYS))
    entries = doc.get("acquisition")
    if entries is None:
        raise r.error("no [[acquisition]] table; a manifest lists at least one acquisition")
    if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
        raise r.error("'acquisition' must be an array of tables: write each one as [[acquisition]]")
    if not entries:
        raise r.error("no [[acquisition]] table; a manifest lists at least one acquisition")

    origin = doc.get("origin")
    if origin is not None and not (
            isinstance(origin, list) and len(origin) == 2
            and all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in origin)):
        raise r.error(f"origin must be [row, col], the sensor pixel of the stacks' first "
                      f"pixel (integers >= 0), got {origin!r}")
    adc_bits = doc.get("adc_bits")
    if adc_bits is not None and (
        not isinstance(adc_bits, int) or isinstance(adc_bits, bool) or not 1 <= adc_bits <= 32
    ):
        raise r.error(f"adc_bits must be an integer from 1 to 32, got {adc_bits!r}")

    e_value = doc.get("e_per_adu")
    if e_value is not None:
        _check_map_value(r, "e_per_adu", e_value, None, "")
    em_model = _em_model(r, doc.get("em_model"), doc.get("register_stages"))

    specs = []
    for i, entry in enumerate(entries, start=1):
        specs.append(_check_entry(r, i, entry))
    seen: dict[Path, int] = {}
    for i, spec in enumerate(specs, start=1):
        key = spec["frames_path"].expanduser().resolve()
        if key in seen:
            raise r.error(
                f"frames file '{spec['frames']}' is also acquisition {seen[key]}; "
                "each stack may be listed once",
                i,
                spec["label"],
            )
        seen[key] = i

    # ---- files exist; stack headers: 3-D, same (rows, cols), skip_frames --------------
    for i, spec in enumerate(specs, start=1):
        for key in ("frames", "dark", "offset", "read_noise"):
            if isinstance(spec.get(key), str):
                _require_file(r, i, spec, key)
    e_result = None  # e_per_adu chained from an is-adu or mv-adu result
    if isinstance(e_value, str) and is_result_path(r.resolve(e_value)):
        e_result = r.resolve(e_value)
        if not e_result.exists():
            raise r.error(f"e_per_adu: {describe_missing(e_result, 'result')}")
    elif isinstance(e_value, str):
        _require_file(r, None, {"e_per_adu": e_value, "label": ""}, "e_per_adu")

    shape = None
    first_label = ""
    dtypes = []
    for i, spec in enumerate(specs, start=1):
        stack_shape, dtype = _stack_header(r, i, spec, spec["frames_path"], "frames")
        if shape is None:
            shape, first_label = stack_shape[1:], spec["label"]
        elif stack_shape[1:] != shape:
            raise r.error(
                f"frames '{spec['frames_path']}' have (rows, cols) = {stack_shape[1:]}, but "
                f"acquisition 1 ({first_label}) has {shape}; all stacks must cover the same pixels",
                i,
                spec["label"],
            )
        spec["n_frames_total"] = stack_shape[0]
        spec["dtype"] = dtype
        dtypes.append(dtype)
        if spec["skip_frames"] >= stack_shape[0]:
            raise r.error(
                f"skip_frames = {spec['skip_frames']} leaves no frames: "
                f"'{spec['frames_path']}' has {stack_shape[0]} frames",
                i,
                spec["label"],
            )
        if stack_shape[0] - spec["skip_frames"] < 2:
            raise r.error(
                f"'{spec['frames_path']}' has 1 frame{' after skip_frames' * bool(spec['skip_frames'])}: "
                "a histogram of a pixel's counts needs at least 2 (a calibration, thousands)",
                i,
                spec["label"],
            )
        if isinstance(spec.get("dark"), str):
            dark_shape, _ = _stack_header(r, i, spec, spec["dark_path"], "dark")
            if dark_shape[1:] != shape:
                raise r.error(
                    f"dark stack '{spec['dark_path']}' has (rows, cols) = {dark_shape[1:]}, "
                    f"but the frames are {shape}",
                    i,
                    spec["label"],
                )
            spec["dark_frames"] = dark_shape[0]
            if dark_shape[0] < 2:
                raise r.error(
                    f"dark stack '{spec['dark_path']}' has {dark_shape[0]} frame(s); at least "
                    "2 are needed for a read noise",
                    i,
                    spec["label"],
                )

    _refuse_copies(r, specs)

    if adc_bits is not None:
        adc_max = 2**adc_bits - 1
        hint = f" (adc_bits = {adc_bits}); is adc_bits the camera's ADC resolution?"
    else:
        adc_max = max(default_adc_max(d) for d in dtypes)
        hint = (
            f" (default for {', '.join(sorted({str(d) for d in dtypes}))} data); set "
            "adc_bits in the manifest to the camera's ADC resolution"
        )

    # ---- maps: shape and values --------------------------------------------------------
    e_per_adu, e_source = None, None
    if e_result is not None:  # read by the calibration, with its standard errors
        e_source = f"result {e_result}"
    elif e_value is not None:
        e_per_adu, e_source = _map_from_value(r, None, {"label": ""}, "e_per_adu", e_value, shape)
    for i, spec in enumerate(specs, start=1):
        for key in ("offset", "read_noise"):
            if key in spec:
                spec[key + "_map"], spec[key + "_source"] = _map_from_value(
                    r, i, spec, key, spec[key], shape
                )

    # ---- data: raw counts, then darks reduced to maps --------------------------------
    for i, spec in enumerate(specs, start=1):
        if needs_scan(spec["dtype"], adc_max):
            try:
                check_counts(
                    load_stack(spec["frames_path"]),
                    spec["frames_path"],
                    adc_max=adc_max,
                    adc_bits_hint=hint,
                )
            except InputError as exc:
                raise r.error(str(exc), i, spec["label"]) from None
    dark_maps: dict[Path, tuple[np.ndarray, np.ndarray]] = {}
    for i, spec in enumerate(specs, start=1):
        if "dark" not in spec:
            continue
        key = spec["dark_path"].expanduser().resolve()
        if key not in dark_maps:
            try:
                dark = load_stack(spec["dark_path"])
                check_counts(dark, spec["dark_path"], adc_max=adc_max, adc_bits_hint=hint)
            except InputError as exc:
                raise r.error(str(exc), i, spec["label"]) from None
            if spec["em_gain_setpoint"] == 1:
                offset, read_noise = maps_from_dark(dark)  # data checked: cannot fail here
                events = None
            else:  # multiplied events in the dark: the read-out's maps by the noise model
                fitted = fit_dark(dark, adc_max=adc_max)
                offset, read_noise = fitted.offset, fitted.read_noise
                events = None if fitted.event_scale == 0 else fitted.event_rate
            if np.any(read_noise <= 0):
                bad = describe_first(read_noise, read_noise <= 0, 0)
                raise r.error(
                    f"'{spec['dark_path']}': dark stack gives read noise {bad} (constant "
                    "dark counts); read noise must be > 0",
                    i,
                    spec["label"],
                )
            dark_maps[key] = (offset, read_noise, events)
        offset, read_noise, events = dark_maps[key]
        spec["offset_map"], spec["read_noise_map"] = offset.copy(), read_noise.copy()
        spec["dark_event_rate"] = events
        spec["offset_source"] = spec["read_noise_source"] = f"dark {spec['dark_path']}"

    for i, spec in enumerate(specs, start=1):  # maps in other units, or a wrong adc_bits
        for key, what in (("offset", "offset"), ("read_noise", "read noise")):
            m = spec[key + "_map"]
            if np.max(m) >= adc_max:
                bad = describe_first(m, m >= adc_max, 0)
                raise r.error(
                    f"{what} {bad} ({spec[key + '_source']}) is at or above the ADC maximum "
                    f"{adc_max} ADU{hint}; maps must be in ADU of these frames",
                    i, spec["label"])

    acquisitions = [
        Acquisition(
            name=spec["name"],
            frames_path=spec["frames_path"],
            em_gain_setpoint=spec["em_gain_setpoint"],
            level=spec["level"],
            skip_frames=spec["skip_frames"],
            offset=spec["offset_map"],
            read_noise=spec["read_noise_map"],
            offset_source=spec["offset_source"],
            read_noise_source=spec["read_noise_source"],
            n_frames_total=spec["n_frames_total"],
            dark_frames=spec["dark_frames"],
            dark_event_rate=spec.get("dark_event_rate"),
        )
        for spec in specs
    ]
    levels: list[str] = []
    for a in acquisitions:
        if a.level is not None and a.level not in levels:
            levels.append(a.level)
    found = [
        f"{path}: {msg}"
        for msg in check_read_noise_growth(
            [a.em_gain_setpoint for a in acquisitions], [a.read_noise for a in acquisitions]
        )
    ]
    for msg in found:
        warnings.warn(msg, ReadNoiseGrowthWarning, stacklevel=2)
    recorded_origins, recorded_binnings = set(), set()
    cameras = []
    for i, a in enumerate(acquisitions, start=1):
        settings = stack_settings(a.frames_path)
        cameras.append({k: getattr(settings, k) for k in CAMERA_IDENTITY})
        if settings.roi is not None:
            recorded_origins.add((settings.roi[1], settings.roi[0]))  # (row, col) = (y, x)
        if settings.binning is not None:
            recorded_binnings.add(tuple(settings.binning))
        recorded = settings.em_gain_setpoint
        if recorded is not None and recorded != a.em_gain_setpoint:
            msg = (f"{path}: acquisition {i} ({a.name}): the manifest says EM gain set-point "
                   f"{a.em_gain_setpoint:g}, but '{a.frames_path}' records {recorded:g}")
            found.append(msg)
            warnings.warn(msg, stacklevel=2)
    return Manifest(
        path=path,
        content_hash=content_hash,
        e_per_adu=e_per_adu,
        e_per_adu_source=e_source,
        acquisitions=acquisitions,
        shape=tuple(int(d) for d in shape),
        origin=_origin(r, origin, recorded_origins, shape),
        binning=_binning(r, recorded_binnings),
        adc_max=int(adc_max),
        setpoints=tuple(sorted({a.em_gain_setpoint for a in acquisitions})),
        levels=tuple(levels),
        warnings=found,
        em_model=em_model,
        camera={k: cameras[0][k] for k in CAMERA_IDENTITY
                if cameras[0][k] is not None and all(c[k] == cameras[0][k] for c in cameras)},
    )


def _em_model(r, name, stages):
    """The manifest's ``em_model`` and ``register_stages`` as a noise.EMModel (or None)."""
    from ..model.noise import EM_MODELS, as_em_model

    if name is None and stages is None:
        return None
    if name is not None and name not in EM_MODELS:
        raise r.error(f"em_model must be one of {', '.join(repr(m) for m in EM_MODELS)}, "
                      f"got {name!r}")
    if stages is not None:
        if not isinstance(stages, int) or isinstance(stages, bool) or not 1 <= stages <= 100000:
            raise r.error(f"register_stages must be a whole number of stages (e.g. 536 or "
                          f"604), got {stages!r}")
    try:
        return as_em_model(name or "gamma", stages)
    except OptionError as exc:  # stages given to a model without them
        raise r.error(f"register_stages: {exc}") from None


def _refuse_copies(r: _Reader, specs: list) -> None:
    """Two acquisitions whose frames files hold the same data (one stack copied under two
    set-points or levels) would fit as two measurements of one: an error."""
    seen: dict[str, int] = {}
    for i, spec in enumerate(specs, start=1):
        key = content_fingerprint(spec["frames_path"])
        if key in seen:
            j = seen[key]
            raise r.error(
                f"frames '{spec['frames_path']}' hold the same data as acquisition {j}'s "
                f"('{specs[j - 1]['frames_path']}'): the same stack under two "
                f"{'levels' if spec['level'] is not None else 'set-points'}?", i, spec["label"])
        seen[key] = i


def is_result_path(path: Path) -> bool:
    """Whether ``path`` names a calibration result: a ``.nc`` file or a directory."""
    return path.suffix.lower() == ".nc" or path.is_dir()


def _check_map_value(r: _Reader, key: str, value, entry: int | None, label: str) -> None:
    """A map-valued key holds a path (string) or a number within its range."""
    positive, nonnegative = _MAP_RULES[key]
    if isinstance(value, str):
        if not value.strip():
            raise r.error(f"'{key}' is an empty path", entry, label)
        try:
            number = float(value)
        except ValueError:
            return
        raise r.error(f"{key} = \"{value}\" is a string, which names a map file; write the "
                      f"number without quotes: {key} = {number:g}", entry, label)
    if not _is_number(value):
        raise r.error(
            f"'{key}' must be a number or the path of a (rows, cols) map, got {value!r}",
            entry,
            label,
        )
    if not math.isfinite(value):
        raise r.error(f"'{key}' must be finite, got {value!r}", entry, label)
    if positive and value <= 0:
        raise r.error(f"'{key}' must be > 0, got {value!r}", entry, label)
    if nonnegative and value < 0:
        raise r.error(f"'{key}' must be >= 0, got {value!r}", entry, label)


def _check_entry(r: _Reader, i: int, entry: dict) -> dict:
    """Keys, types and ranges of one [[acquisition]] table; nothing is read."""
    frames = entry.get("frames")
    label = f"frames = '{frames}'" if isinstance(frames, str) else ""
    for key in entry:
        if key not in ACQUISITION_KEYS:
            raise r.error(_unknown_key_message(key, ACQUISITION_KEYS), i, label)
    if frames is None:
        raise r.error("missing 'frames' (the path of the stack of raw counts)", i)
    if not isinstance(frames, str) or not frames.strip():
        raise r.error(f"'frames' must be a path, got {frames!r}", i)

    g = entry.get("em_gain_setpoint")
    if g is None:
        raise r.error("missing 'em_gain_setpoint' (the camera's EM gain setting, >= 1)", i, label)
    if not _is_number(g) or not math.isfinite(g):
        raise r.error(f"'em_gain_setpoint' must be a number >= 1, got {g!r}", i, label)
    if g < 1:
        raise r.error(
            f"'em_gain_setpoint' must be >= 1 (1 means no EM multiplication), got {g!r}", i, label
        )

    has_maps = [k for k in ("offset", "read_noise") if k in entry]
    if "dark" in entry and has_maps:
        raise r.error(
            f"give either 'dark' or 'offset' and 'read_noise', not both "
            f"(found 'dark' and {', '.join(repr(k) for k in has_maps)})",
            i,
            label,
        )
    if "dark" not in entry and len(has_maps) < 2:
        if has_maps:
            missing = ({"offset", "read_noise"} - set(has_maps)).pop()
            raise r.error(
                f"'{has_maps[0]}' is given but '{missing}' is missing; give both maps, or a "
                "'dark' stack",
                i,
                label,
            )
        raise r.error(
            "no offset and read noise: give 'offset' and 'read_noise' (maps or numbers, "
            "ADU) or a 'dark' stack",
            i,
            label,
        )
    for key in has_maps:
        _check_map_value(r, key, entry[key], i, label)
    dark = entry.get("dark")
    if "dark" in entry and (not isinstance(dark, str) or not dark.strip()):
        raise r.error(f"'dark' must be the path of a dark stack, got {dark!r}", i, label)
    dark_frames = entry.get("dark_frames")
    if dark_frames is not None:
        if "dark" in entry:
            raise r.error(
                "'dark_frames' is for offset/read_noise maps; with a 'dark' stack the number "
                "of dark frames is the stack's",
                i,
                label,
            )
        if not isinstance(dark_frames, int) or isinstance(dark_frames, bool) or dark_frames < 2:
            raise r.error(
                f"'dark_frames' (the number of dark frames the maps were computed from) must "
                f"be an integer >= 2, got {dark_frames!r}",
                i,
                label,
            )

    skip = entry.get("skip_frames", 0)
    if not isinstance(skip, int) or isinstance(skip, bool) or skip < 0:
        raise r.error(f"'skip_frames' must be an integer >= 0, got {skip!r}", i, label)

    level = entry.get("level")
    if level is not None:
        if isinstance(level, bool) or not isinstance(level, (str, int)):
            raise r.error(f"'level' must be a string label (e.g. \"L3\"), got {level!r}", i, label)
        level = str(level)

    name = entry.get("name")
    if name is not None and (not isinstance(name, str) or not name.strip()):
        raise r.error(f"'name' must be a non-empty string, got {name!r}", i, label)

    frames_path = r.resolve(frames)
    spec = {
        "label": label,
        "frames": frames,
        "frames_path": frames_path,
        "name": name if name is not None else Path(frames).stem,
        "em_gain_setpoint": float(g),
        "skip_frames": skip,
        "level": level,
        "dark_frames": dark_frames,
    }
    for key in has_maps:
        spec[key] = entry[key]
    if dark is not None:
        spec["dark"] = dark
        spec["dark_path"] = r.resolve(dark)
    return spec


def _require_file(r: _Reader, i: int | None, spec: dict, key: str) -> None:
    written = spec[key]
    p = r.resolve(written)
    if not p.exists():
        raise r.error(
            f"{key} file not found: '{written}' (resolved to '{p.expanduser().resolve()}')",
            i,
            spec["label"],
        )
    try:
        check_readable(p)
    except InputError as exc:
        raise r.error(f"{key}: {exc}", i, spec["label"]) from None


def _stack_header(r: _Reader, i: int, spec: dict, p: Path, key: str):
    try:
        shape, dtype = stack_header(p)
    except InputError as exc:
        raise r.error(str(exc), i, spec["label"]) from None
    if len(shape) == 2:
        raise r.error(
            f"{key} '{p}' holds one image of {shape[0]} × {shape[1]} pixels, not a stack of "
            "frames (a stack cut short to its first frame?)", i, spec["label"])
    if len(shape) != 3:
        raise r.error(
            f"{key} '{p}' is not a 3-D (frames, rows, cols) stack: shape {shape}",
            i,
            spec["label"],
        )
    if dtype.kind not in "uif":
        raise r.error(
            f"{key} '{p}' has unsupported data type {dtype}; expected integer counts",
            i,
            spec["label"],
        )
    return shape, dtype


def _map_from_value(r: _Reader, i: int | None, spec: dict, key: str, value, shape):
    """A number expands to a (rows, cols) map (e_per_adu stays a number); a path is read."""
    positive, nonnegative = _MAP_RULES[key]
    if isinstance(value, str):
        p = r.resolve(value)
        try:
            m = read_map(p, shape, name=key, positive=positive, nonnegative=nonnegative)
        except InputError as exc:
            raise r.error(str(exc), i, spec["label"]) from None
        return m, str(p)
    source = f"value {value!r}"
    if key == "e_per_adu":
        return float(value), source
    return np.full(shape, float(value)), source

