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
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from .. import _files, identity
from ..errors import InputError, InputWarning, ManifestError, OptionError, ReadNoiseGrowthWarning
from .dark import check_read_noise_growth, read_out_maps
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
    "Source",
    "Acquisition",
    "AcquisitionEntry",
    "Manifest",
    "ManifestEntries",
    "parse_manifest",
    "read_manifest",
    "resolve_manifest",
    "TOP_LEVEL_KEYS",
    "ACQUISITION_KEYS",
]

#: The camera settings that identify a camera's read-out state (a calibration holds for
#: that state only), recorded in results as ``attrs["camera"]``.
CAMERA_IDENTITY = ("serial", "model", "amplifier", "readout_rate_mhz", "analog_gain", "adc_bits")


# --------------------------------------------------------------------------------------
# Data classes
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Source:
    """Where a map or a number came from: a typed record, never text to decode.

    Attributes
    ----------
    kind : {"value", "map", "dark", "result", "given"}
        A number in the manifest, a map file, a dark stack the maps were reduced from, a
        calibration result (φ and its standard error) or a value given by the caller.
    path : Path, optional
        The file of a map, a dark stack or a result.
    value : float, optional
        The number of a ``"value"``.

    Its text (``str``) is what results and messages show: ``"value 3.859"``, the map's
    path, ``"dark <path>"``, ``"result <path>"`` or ``"given"``.
    """

    kind: str
    path: Path | None = None
    value: float | None = None

    def __str__(self) -> str:
        if self.kind == "value":
            return f"value {self.value!r}"
        if self.kind == "map":
            return str(self.path)
        return self.kind if self.path is None else f"{self.kind} {self.path}"


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
    offset_source, read_noise_source : Source
        Where the maps came from: a map file, a dark stack or a number in the manifest.
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
    offset_source: Source
    read_noise_source: Source
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
        rows, cols = self.offset.shape
        return int(rows), int(cols)

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
    e_per_adu_source : Source or None
        A map file, a number, or a result (φ and its standard error from an ``is-adu`` or
        ``mv-adu`` result, read by the calibration; then ``e_per_adu`` is None), or None
        when ``e_per_adu`` is absent.
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

    Examples
    --------
    >>> import tempfile, emccdcal
    >>> sim = emccdcal.simulate_gain_series(
    ...     tempfile.mkdtemp(), rows=4, cols=6, frames=200, setpoints=(1, 10), seed=1,
    ...     progress=False,
    ... )
    >>> manifest = emccdcal.read_manifest(sim.manifest)
    >>> manifest.shape, [a.name for a in manifest.acquisitions]
    ((4, 6), ['1x', '10x'])
    """

    path: Path
    content_hash: str
    e_per_adu: None | float | np.ndarray = field(repr=False)
    e_per_adu_source: Source | None
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
    #: The EM register's model (``em_model``) and the cascade's ``register_stages`` as
    #: the manifest gives them, or None: not given (the calibration's own default, the
    #: exact cascade with stages from the camera's model or a stated default).
    em_model: str | None = None
    register_stages: int | None = None
    #: What every frames file records alike of the camera (``serial``, ``model``,
    #: ``amplifier``, ``readout_rate_mhz``, ``analog_gain``, ``adc_bits``): the identity a calibration
    #: database keys on. A field the files leave out or disagree on is absent.
    camera: dict = field(default_factory=dict)

    def identity(self) -> dict:
        """What the frames record of the camera and read-out state (``camera`` with
        ``binning``), for :func:`emccdcal.identity.check`."""
        return {**self.camera, **({} if self.binning is None else {"binning": self.binning})}

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
        raise r.error(
            f"the stacks record different regions of the sensor ({texts}): a "
            "calibration needs the same pixels in every acquisition"
        )
    if written is not None:
        if recorded and tuple(written) not in recorded:
            warnings.warn(
                f"{r.path}: origin = {list(written)}, but the files record "
                f"{list(next(iter(recorded)))}; the manifest's is used",
                stacklevel=5,
                category=InputWarning,
            )
        return tuple(int(v) for v in written)
    return next(iter(recorded)) if recorded else None


def _binning(r, recorded: set):
    """The stacks' (x, y) binning where the files record one; different ones are an error."""
    if len(recorded) > 1:
        raise r.error(
            f"the stacks record different binnings ({', '.join(map(str, sorted(recorded)))}): "
            "a calibration needs the same pixels in every acquisition"
        )
    return next(iter(recorded)) if recorded else None


def _region_text(origin, shape) -> str:
    (r0, c0), (h, w) = origin, shape
    return f"sensor rows {r0}–{r0 + h - 1}, cols {c0}–{c0 + w - 1}"


# --------------------------------------------------------------------------------------
# Step 1: parse (the TOML file to frozen entries; no other file is opened)
# --------------------------------------------------------------------------------------
def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _is_int(value, low=None, high=None) -> bool:
    return (
        isinstance(value, int)
        and not isinstance(value, bool)
        and (low is None or value >= low)
        and (high is None or value <= high)
    )


def _is_path(value) -> bool:
    return isinstance(value, str) and bool(value.strip())


#: Requirements on map-valued keys: (positive, nonnegative).
_MAP_RULES = {
    "offset": (False, True),
    "read_noise": (True, False),
    "e_per_adu": (True, False),
}


def _map_problem(key: str, value) -> str | None:
    """A map-valued key holds a path (string) or a number within its range."""
    positive, nonnegative = _MAP_RULES[key]
    if isinstance(value, str):
        if not value.strip():
            return f"'{key}' is an empty path"
        try:
            number = float(value)
        except ValueError:
            return None
        return (
            f'{key} = "{value}" is a string, which names a map file; write the '
            f"number without quotes: {key} = {number:g}"
        )
    if not _is_number(value):
        return f"'{key}' must be a number or the path of a (rows, cols) map, got {value!r}"
    if not math.isfinite(value):
        return f"'{key}' must be finite, got {value!r}"
    if positive and value <= 0:
        return f"'{key}' must be > 0, got {value!r}"
    if nonnegative and value < 0:
        return f"'{key}' must be >= 0, got {value!r}"
    return None


def _setpoint_problem(g) -> str | None:
    if not _is_number(g) or not math.isfinite(g):
        return f"'em_gain_setpoint' must be a number >= 1, got {g!r}"
    if g < 1:
        return f"'em_gain_setpoint' must be >= 1 (1 means no EM multiplication), got {g!r}"
    return None


@dataclass(frozen=True)
class _Key:
    """One key of the manifest: its unit, its default and what is wrong with a value.

    ``problem(value)`` returns the message for a bad value, or None; ``missing`` is the
    message when a required key is absent (None: optional, ``default`` then).
    """

    name: str
    unit: str
    default: object = None
    problem: Callable[[object], str | None] = field(default=lambda value: None, repr=False)
    missing: str | None = None


#: The keys of a manifest's top level (docs/manifest.md).
_TOP_KEYS = (
    _Key("e_per_adu", "e-/ADU", problem=partial(_map_problem, "e_per_adu")),
    _Key(
        "adc_bits",
        "bit",
        problem=lambda v: (
            None if _is_int(v, 1, 32) else f"adc_bits must be an integer from 1 to 32, got {v!r}"
        ),
    ),
    _Key(
        "origin",
        "pixel",
        problem=lambda v: (
            None
            if (isinstance(v, list) and len(v) == 2 and all(_is_int(x, 0) for x in v))
            else f"origin must be [row, col], the sensor pixel of the stacks' first pixel "
            f"(integers >= 0), got {v!r}"
        ),
    ),
    _Key(
        "em_model",
        "",
        problem=lambda v: (
            None
            if v in _em_models()
            else f"em_model must be one of {', '.join(repr(m) for m in _em_models())}, got {v!r}"
        ),
    ),
    _Key(
        "register_stages",
        "stages",
        problem=lambda v: (
            None
            if _is_int(v, 1, 100000)
            else f"register_stages must be a whole number of stages (e.g. 536 or 604), got {v!r}"
        ),
    ),
    _Key(
        "acquisition",
        "",
        missing="no [[acquisition]] table; a manifest lists at least one acquisition",
        problem=lambda v: (
            None
            if (isinstance(v, list) and all(isinstance(e, dict) for e in v))
            else "'acquisition' must be an array of tables: write each one as [[acquisition]]"
        ),
    ),
)

#: The keys of an ``[[acquisition]]`` table (docs/manifest.md).
_ACQUISITION_KEYS = (
    _Key(
        "frames",
        "",
        missing="missing 'frames' (the path of the stack of raw counts)",
        problem=lambda v: None if _is_path(v) else f"'frames' must be a path, got {v!r}",
    ),
    _Key(
        "em_gain_setpoint",
        "",
        problem=_setpoint_problem,
        missing="missing 'em_gain_setpoint' (the camera's EM gain setting, >= 1)",
    ),
    _Key("offset", "ADU", problem=partial(_map_problem, "offset")),
    _Key("read_noise", "ADU", problem=partial(_map_problem, "read_noise")),
    _Key(
        "dark",
        "",
        problem=lambda v: (
            None if _is_path(v) else f"'dark' must be the path of a dark stack, got {v!r}"
        ),
    ),
    _Key(
        "level",
        "",
        problem=lambda v: (
            None
            if isinstance(v, (str, int)) and not isinstance(v, bool)
            else f"'level' must be a string label (e.g. \"L3\"), got {v!r}"
        ),
    ),
    _Key(
        "skip_frames",
        "frames",
        default=0,
        problem=lambda v: (
            None if _is_int(v, 0) else f"'skip_frames' must be an integer >= 0, got {v!r}"
        ),
    ),
    _Key(
        "name",
        "",
        problem=lambda v: None if _is_path(v) else f"'name' must be a non-empty string, got {v!r}",
    ),
    _Key(
        "dark_frames",
        "frames",
        problem=lambda v: (
            None
            if _is_int(v, 2)
            else f"'dark_frames' (the number of dark frames the maps were computed from) must "
            f"be an integer >= 2, got {v!r}"
        ),
    ),
)

#: Keys allowed at the top level of a manifest.
TOP_LEVEL_KEYS = tuple(k.name for k in _TOP_KEYS)
#: Keys allowed in an ``[[acquisition]]`` table.
ACQUISITION_KEYS = tuple(k.name for k in _ACQUISITION_KEYS)


def _em_models():
    from ..model.noise import EM_MODELS

    return EM_MODELS


def _unknown_key_message(key: str, allowed) -> str:
    close = difflib.get_close_matches(key, allowed, n=1, cutoff=0.6)
    hint = f"; did you mean '{close[0]}'?" if close else ""
    return f"unknown key '{key}'{hint} (allowed: {', '.join(allowed)})"


class _Reader:
    """Messages naming one manifest, and its relative paths resolved."""

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

    def table(self, table: dict, keys, entry: int | None = None, label: str = "") -> dict:
        """Every key of ``keys`` in ``table``: unknown keys, missing required ones and bad
        values refused; absent optional ones given their default."""
        allowed = tuple(k.name for k in keys)
        for name in table:
            if name not in allowed:
                raise self.error(_unknown_key_message(name, allowed), entry, label)
        values = {}
        for key in keys:
            if key.name not in table:
                if key.missing is not None:
                    raise self.error(key.missing, entry, label)
                values[key.name] = key.default
                continue
            problem = key.problem(table[key.name])
            if problem is not None:
                raise self.error(problem, entry, label)
            values[key.name] = table[key.name]
        return values


@dataclass(frozen=True)
class AcquisitionEntry:
    """One ``[[acquisition]]`` table as written, checked; nothing read.

    ``offset`` and ``read_noise`` are a number (ADU) or a map file as written (None with
    a ``dark``); paths are resolved against the manifest's folder.
    """

    index: int
    label: str
    frames: str
    frames_path: Path
    name: str
    em_gain_setpoint: float
    skip_frames: int
    level: str | None
    dark_frames: int | None
    offset: float | str | None
    read_noise: float | str | None
    dark: str | None
    dark_path: Path | None


@dataclass(frozen=True)
class ManifestEntries:
    """A manifest as written, checked for keys, types and ranges (:func:`parse_manifest`).

    ``e_per_adu`` is a number (e⁻/ADU), a map file or a result as written, or None.
    """

    path: Path
    content_hash: str
    e_per_adu: float | str | None
    adc_bits: int | None
    origin: tuple[int, int] | None
    em_model: str | None
    register_stages: int | None
    acquisitions: tuple[AcquisitionEntry, ...]


def parse_manifest(path) -> ManifestEntries:
    """Read a manifest's TOML and check its keys, types and ranges; no data file is opened.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    ManifestEntries

    Raises
    ------
    ManifestError
        One line naming the manifest, the acquisition and the problem.
    """
    path = Path(path)
    r = _Reader(path)
    if not path.exists():
        raise ManifestError(describe_missing(path, "manifest file"))
    if path.is_dir():
        raise ManifestError(
            f"{path}: is a directory, not a manifest file; 'emccdcal scan "
            f"{path}' writes the manifest of a folder of camera files"
        )
    try:
        raw = _files.read_bytes(path, what="manifest")
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise r.error(f"not UTF-8 text (byte {exc.start}); a manifest is a TOML file") from None
    except InputError as exc:
        raise ManifestError(str(exc)) from None
    try:
        doc = _files.load_toml(path, text=text, what="manifest")
    except InputError as exc:
        raise r.error(f"invalid TOML: {getattr(exc, 'reason', exc)}") from None
    top = r.table(doc, _TOP_KEYS)
    if not top["acquisition"]:
        raise r.error(str(_TOP_KEYS[-1].missing))
    entries = tuple(_entry(r, i, table) for i, table in enumerate(top["acquisition"], 1))
    seen: dict[Path, int] = {}
    for e in entries:
        key = e.frames_path.expanduser().resolve()
        if key in seen:
            raise r.error(
                f"frames file '{e.frames}' is also acquisition {seen[key]}; each "
                "stack may be listed once",
                e.index,
                e.label,
            )
        seen[key] = e.index
    origin = top["origin"]
    return ManifestEntries(
        path=path,
        content_hash=hashlib.sha256(raw).hexdigest(),
        e_per_adu=top["e_per_adu"],
        adc_bits=top["adc_bits"],
        origin=None if origin is None else (int(origin[0]), int(origin[1])),
        em_model=top["em_model"],
        register_stages=_register_stages(r, top["em_model"], top["register_stages"]),
        acquisitions=entries,
    )


def _entry(r: _Reader, i: int, table: dict) -> AcquisitionEntry:
    """One [[acquisition]] table: the key table's checks, then the rules between keys."""
    label = f"frames = '{table['frames']}'" if isinstance(table.get("frames"), str) else ""
    v = r.table(table, _ACQUISITION_KEYS, i, label)
    frames: str = v["frames"]  # required: the key table has refused a table without it
    has_maps = [k for k in ("offset", "read_noise") if v[k] is not None]
    if v["dark"] is not None and has_maps:
        raise r.error(
            f"give either 'dark' or 'offset' and 'read_noise', not both (found "
            f"'dark' and {', '.join(repr(k) for k in has_maps)})",
            i,
            label,
        )
    if v["dark"] is None and len(has_maps) == 1:
        missing = ({"offset", "read_noise"} - set(has_maps)).pop()
        raise r.error(
            f"'{has_maps[0]}' is given but '{missing}' is missing; give both "
            "maps, or a 'dark' stack",
            i,
            label,
        )
    if v["dark"] is None and not has_maps:
        raise r.error(
            "no offset and read noise: give 'offset' and 'read_noise' (maps or "
            "numbers, ADU) or a 'dark' stack",
            i,
            label,
        )
    if v["dark_frames"] is not None and v["dark"] is not None:
        raise r.error(
            "'dark_frames' is for offset/read_noise maps; with a 'dark' stack the "
            "number of dark frames is the stack's",
            i,
            label,
        )
    return AcquisitionEntry(
        index=i,
        label=label,
        frames=frames,
        frames_path=r.resolve(frames),
        name=v["name"] if v["name"] is not None else Path(frames).stem,
        em_gain_setpoint=float(v["em_gain_setpoint"]),
        skip_frames=v["skip_frames"],
        level=None if v["level"] is None else str(v["level"]),
        dark_frames=v["dark_frames"],
        offset=v["offset"],
        read_noise=v["read_noise"],
        dark=v["dark"],
        dark_path=None if v["dark"] is None else r.resolve(v["dark"]),
    )


def _register_stages(r, name, stages):
    """The manifest's ``register_stages`` (or None), refused beside a model without them."""
    from ..model.noise import EMModel

    if stages is None or name is None:
        return None if stages is None else int(stages)
    try:
        if not EMModel(name, stages).register.uses_stages:  # stages of a model without them
            raise OptionError(
                f"stages are the cascade model's: the {name} model has none (delete "
                "register_stages, or give em_model = 'cascade')"
            )
    except OptionError as exc:
        raise r.error(f"register_stages: {exc}") from None
    return int(stages)


# --------------------------------------------------------------------------------------
# Step 2: resolve (headers, maps, dark fits: everything a fit needs, checked)
# --------------------------------------------------------------------------------------
def read_manifest(path) -> Manifest:
    """Read and validate a calibration manifest.

    Everything is checked before any fitting: TOML syntax, keys (with a suggestion for a
    misspelt one), types and ranges of values (:func:`parse_manifest`), then
    (:func:`resolve_manifest`) that every file exists and is readable, that stacks are
    3-D and share (rows, cols), that maps have that shape and valid values, that stacks
    hold raw counts (non-negative integers, at most the ADC maximum), and that
    ``skip_frames`` leaves frames to use. Dark stacks are reduced to offset and
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

    Examples
    --------
    >>> import tempfile, emccdcal
    >>> work = tempfile.mkdtemp()
    >>> sim = emccdcal.simulate_gain_series(
    ...     f"{work}/gs", rows=4, cols=4, frames=400, setpoints=(1, 10), seed=1, progress=False
    ... )
    >>> manifest = emccdcal.read_manifest(sim.manifest)
    >>> manifest.shape, [a.em_gain_setpoint for a in manifest.acquisitions]
    ((4, 4), [1.0, 10.0])
    """
    return resolve_manifest(parse_manifest(path))


def resolve_manifest(entries: ManifestEntries) -> Manifest:
    """Open what a parsed manifest names and check it: see :func:`read_manifest`."""
    r = _Reader(entries.path)
    acqs = entries.acquisitions
    e_result = _require_files(r, entries)
    shape, headers = _stack_headers(r, acqs)
    _refuse_copies(r, acqs)
    dtypes = [dtype for _, dtype, _ in headers]
    if entries.adc_bits is not None:
        adc_max = 2**entries.adc_bits - 1
        hint = f" (adc_bits = {entries.adc_bits}); is adc_bits the camera's ADC resolution?"
    else:
        adc_max = max(default_adc_max(d) for d in dtypes)
        hint = (
            f" (default for {', '.join(sorted({str(d) for d in dtypes}))} data); set "
            "adc_bits in the manifest to the camera's ADC resolution"
        )
    e_per_adu, e_source = None, None
    if e_result is not None:  # read by the calibration, with its standard errors
        e_source = Source("result", Path(e_result))
    elif entries.e_per_adu is not None:
        e_per_adu, e_source = _map_from_value(r, None, "", "e_per_adu", entries.e_per_adu, shape)
    for a, (_, dtype, _) in zip(acqs, headers):
        if needs_scan(dtype, adc_max):
            try:
                check_counts(
                    load_stack(a.frames_path), a.frames_path, adc_max=adc_max, adc_bits_hint=hint
                )
            except InputError as exc:
                raise r.error(str(exc), a.index, a.label) from None
    maps = _read_out_maps(r, acqs, shape, adc_max, hint)
    acquisitions = [
        Acquisition(
            name=a.name,
            frames_path=a.frames_path,
            em_gain_setpoint=a.em_gain_setpoint,
            level=a.level,
            skip_frames=a.skip_frames,
            offset=m["offset"],
            read_noise=m["read_noise"],
            offset_source=m["offset_source"],
            read_noise_source=m["read_noise_source"],
            n_frames_total=n_total,
            dark_frames=dark_frames,
            dark_event_rate=m["events"],
        )
        for a, m, (n_total, _, dark_frames) in zip(acqs, maps, headers)
    ]
    found = [
        f"{entries.path}: {msg}"
        for msg in check_read_noise_growth(
            [a.em_gain_setpoint for a in acquisitions], [a.read_noise for a in acquisitions]
        )
    ]
    for msg in found:
        warnings.warn(msg, ReadNoiseGrowthWarning, stacklevel=3)
    origin, binning, camera = _recorded(r, entries, acquisitions, shape, found)
    levels = tuple(dict.fromkeys(a.level for a in acquisitions if a.level is not None))
    return Manifest(
        path=entries.path,
        content_hash=entries.content_hash,
        e_per_adu=e_per_adu,
        e_per_adu_source=e_source,
        acquisitions=acquisitions,
        shape=(int(shape[0]), int(shape[1])),
        origin=origin,
        binning=binning,
        adc_max=int(adc_max),
        setpoints=tuple(sorted({a.em_gain_setpoint for a in acqs})),
        levels=levels,
        warnings=found,
        em_model=entries.em_model,
        register_stages=entries.register_stages,
        camera=camera,
    )


def _require_files(r: _Reader, entries: ManifestEntries) -> Path | None:
    """Every file named exists and is readable; returns the result φ is chained from."""
    for a in entries.acquisitions:
        for key in ("frames", "dark", "offset", "read_noise"):
            if isinstance(getattr(a, key), str):
                _require_file(r, a.index, a.label, key, getattr(a, key))
    e_value = entries.e_per_adu
    if isinstance(e_value, str) and is_result_path(r.resolve(e_value)):
        e_result = r.resolve(e_value)
        if not e_result.exists():
            raise r.error(f"e_per_adu: {describe_missing(e_result, 'result')}")
        return e_result
    if isinstance(e_value, str):
        _require_file(r, None, "", "e_per_adu", e_value)
    return None


def _stack_headers(r: _Reader, acqs):
    """The stacks' shared (rows, cols) and, per acquisition, (frames in the file, dtype,
    dark frames behind its maps), from the headers only."""
    shape, first_label, headers = None, "", []
    for a in acqs:
        i, label = a.index, a.label
        stack_shape, dtype = _stack_header(r, i, label, a.frames_path, "frames")
        if shape is None:
            shape, first_label = stack_shape[1:], label
        elif stack_shape[1:] != shape:
            raise r.error(
                f"frames '{a.frames_path}' have (rows, cols) = {stack_shape[1:]}, "
                f"but acquisition 1 ({first_label}) has {shape}; all stacks must "
                "cover the same pixels",
                i,
                label,
            )
        n = stack_shape[0]
        if a.skip_frames >= n:
            raise r.error(
                f"skip_frames = {a.skip_frames} leaves no frames: '{a.frames_path}' has {n} frames",
                i,
                label,
            )
        if n - a.skip_frames < 2:
            raise r.error(
                f"'{a.frames_path}' has 1 frame"
                f"{' after skip_frames' * bool(a.skip_frames)}: a histogram of a "
                "pixel's counts needs at least 2 (a calibration, thousands)",
                i,
                label,
            )
        dark_frames = a.dark_frames
        if a.dark is not None:
            dark_shape, _ = _stack_header(r, i, label, a.dark_path, "dark")
            if dark_shape[1:] != shape:
                raise r.error(
                    f"dark stack '{a.dark_path}' has (rows, cols) = "
                    f"{dark_shape[1:]}, but the frames are {shape}",
                    i,
                    label,
                )
            if dark_shape[0] < 2:
                raise r.error(
                    f"dark stack '{a.dark_path}' has {dark_shape[0]} frame(s); at "
                    "least 2 are needed for a read noise",
                    i,
                    label,
                )
            dark_frames = dark_shape[0]
        headers.append((n, dtype, dark_frames))
    return shape, headers


def _read_out_maps(r: _Reader, acqs, shape, adc_max, hint) -> list[dict]:
    """Each acquisition's offset and read-noise maps (ADU) with their sources, and the
    multiplied events of its dark: from the maps given, or each dark stack reduced once."""
    darks: dict[Path, tuple] = {}
    # the least multiplied dark first: its read noise is the others' reference
    for a in sorted((a for a in acqs if a.dark is not None), key=lambda a: a.em_gain_setpoint):
        key = a.dark_path.expanduser().resolve()
        if key not in darks:
            reference = float(np.median(next(iter(darks.values()))[1])) if darks else None
            darks[key] = _reduce_dark(r, a, adc_max, hint, reference)
    out = []
    for a in acqs:
        if a.dark is None:
            m: dict = {"events": None}
            for key in ("offset", "read_noise"):
                m[key], m[key + "_source"] = _map_from_value(
                    r, a.index, a.label, key, getattr(a, key), shape
                )
        else:
            offset, read_noise, events = darks[a.dark_path.expanduser().resolve()]
            source = Source("dark", a.dark_path)
            m = {
                "offset": offset.copy(),
                "read_noise": read_noise.copy(),
                "events": events,
                "offset_source": source,
                "read_noise_source": source,
            }
        for key, what in (("offset", "offset"), ("read_noise", "read noise")):
            if np.max(m[key]) >= adc_max:  # maps in other units, or a wrong adc_bits
                bad = describe_first(m[key], m[key] >= adc_max, 0)
                raise r.error(
                    f"{what} {bad} ({m[key + '_source']}) is at or above the ADC "
                    f"maximum {adc_max} ADU{hint}; maps must be in ADU of these "
                    "frames",
                    a.index,
                    a.label,
                )
        out.append(m)
    return out


def _reduce_dark(r: _Reader, a: AcquisitionEntry, adc_max, hint, reference=None):
    """(offset, read noise, multiplied events or None) of an acquisition's dark stack;
    ``reference`` the read noise (ADU) of the calibration's least multiplied dark."""
    assert a.dark_path is not None  # only an acquisition with a dark stack comes here
    try:
        dark = load_stack(a.dark_path)
        check_counts(dark, a.dark_path, adc_max=adc_max, adc_bits_hint=hint)
    except InputError as exc:
        raise r.error(str(exc), a.index, a.label) from None
    try:
        offset, read_noise, events = read_out_maps(
            dark, a.em_gain_setpoint, adc_max=adc_max, reference_read_noise=reference
        )
    except InputError as exc:  # an implausible dark: named with its file
        raise r.error(f"dark '{a.dark_path}': {exc}", a.index, a.label) from None
    if np.any(read_noise <= 0):
        bad = describe_first(read_noise, read_noise <= 0, 0)
        raise r.error(
            f"'{a.dark_path}': dark stack gives read noise {bad} (constant dark "
            "counts); read noise must be > 0",
            a.index,
            a.label,
        )
    return offset, read_noise, events


def _recorded(r: _Reader, entries, acquisitions, shape, found: list):
    """What the frames files record: the region's origin, the binning and the camera
    identity shared by all; a set-point differing from the manifest's is a warning."""
    origins, binnings, recorded_by = set(), set(), {}
    for i, a in enumerate(acquisitions, start=1):
        settings = stack_settings(a.frames_path)
        recorded_by[a.frames_path] = settings
        if settings.roi is not None:
            origins.add((settings.roi[1], settings.roi[0]))  # (row, col) = (y, x)
        if settings.binning is not None:
            binnings.add(tuple(settings.binning))
        recorded = settings.em_gain_setpoint
        if recorded is not None and recorded != a.em_gain_setpoint:
            msg = (
                f"{entries.path}: acquisition {i} ({a.name}): the manifest says EM gain "
                f"set-point {a.em_gain_setpoint:g}, but '{a.frames_path}' records "
                f"{recorded:g}"
            )
            found.append(msg)
            warnings.warn(msg, stacklevel=4, category=InputWarning)
    try:  # the stacks of one calibration are of one camera and read-out state
        joint = identity.of_frames(recorded_by, what="frames of a manifest", setpoints=False)
    except InputError as exc:
        raise r.error(str(exc)) from None
    camera = {
        k: getattr(next(iter(recorded_by.values())), k)
        for k in CAMERA_IDENTITY
        if k in joint and all(getattr(s, k) is not None for s in recorded_by.values())
    }
    return (_origin(r, entries.origin, origins, shape), _binning(r, binnings), camera)


def _refuse_copies(r: _Reader, acqs) -> None:
    """Two acquisitions whose frames files hold the same data (one stack copied under two
    set-points or levels) would fit as two measurements of one: an error."""
    seen: dict[str, AcquisitionEntry] = {}
    for a in acqs:
        key = content_fingerprint(a.frames_path)
        if key in seen:
            b = seen[key]
            raise r.error(
                f"frames '{a.frames_path}' hold the same data as acquisition {b.index}'s "
                f"('{b.frames_path}'): the same stack under two "
                f"{'levels' if a.level is not None else 'set-points'}?",
                a.index,
                a.label,
            )
        seen[key] = a


def is_result_path(path: Path) -> bool:
    """Whether ``path`` names a calibration result: a ``.nc`` file or a directory."""
    return path.suffix.lower() == ".nc" or path.is_dir()


def _require_file(r: _Reader, i: int | None, label: str, key: str, written: str) -> None:
    p = r.resolve(written)
    if not p.exists():
        raise r.error(
            f"{key} file not found: '{written}' (resolved to '{p.expanduser().resolve()}')",
            i,
            label,
        )
    try:
        check_readable(p)
    except InputError as exc:
        raise r.error(f"{key}: {exc}", i, label) from None


def _stack_header(r: _Reader, i: int, label: str, p: Path, key: str):
    try:
        shape, dtype = stack_header(p)
    except InputError as exc:
        raise r.error(str(exc), i, label) from None
    if len(shape) == 2:
        raise r.error(
            f"{key} '{p}' holds one image of {shape[0]} × {shape[1]} pixels, not a "
            "stack of frames (a stack cut short to its first frame?)",
            i,
            label,
        )
    if len(shape) != 3:
        raise r.error(
            f"{key} '{p}' is not a 3-D (frames, rows, cols) stack: shape {shape}", i, label
        )
    if dtype.kind not in "uif":
        raise r.error(
            f"{key} '{p}' has unsupported data type {dtype}; expected integer counts", i, label
        )
    return shape, dtype


def _map_from_value(r: _Reader, i: int | None, label: str, key: str, value, shape):
    """A number expands to a (rows, cols) map (e_per_adu stays a number); a path is read."""
    positive, nonnegative = _MAP_RULES[key]
    if isinstance(value, str):
        p = r.resolve(value)
        try:
            m = read_map(p, shape, name=key, positive=positive, nonnegative=nonnegative)
        except InputError as exc:
            raise r.error(str(exc), i, label) from None
        return m, Source("map", Path(p))
    source = Source("value", value=value)
    if key == "e_per_adu":
        return float(value), source
    return np.full(shape, float(value)), source
