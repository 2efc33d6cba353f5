"""Step 1 of reading a manifest: its TOML to frozen entries (:func:`parse_manifest`) through one table of keys, each with its unit, default and check; no other file is opened."""

from __future__ import annotations

import difflib
import hashlib
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path


from ... import _files, defaults
from ...errors import InputError, ManifestError, OptionError
from ..stacks import (
    describe_missing,
)


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


def _seconds_problem(key, value) -> str | None:
    if not _is_number(value) or not math.isfinite(value) or value <= 0:
        return f"'{key}' must be a time in seconds > 0, got {value!r}"
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
        "camera_kind",
        "",
        problem=lambda v: (
            None
            if v in defaults.CAMERA_KINDS
            else f"camera_kind must be one of {', '.join(repr(k) for k in defaults.CAMERA_KINDS)}, "
            f"got {v!r}"
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
        "light",
        "",
        default=True,
        problem=lambda v: (
            None
            if isinstance(v, bool)
            else f"light must be true or false (false: every stack is dark, the photon-free "
            f"path), got {v!r}"
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
    _Key("exposure_s", "s", problem=partial(_seconds_problem, "exposure_s")),
    _Key("dark_exposure_s", "s", problem=partial(_seconds_problem, "dark_exposure_s")),
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
    from ...model.noise import EM_MODELS

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
    exposure_s: float | None = None
    dark_exposure_s: float | None = None


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
    camera_kind: str | None = None
    light: bool = True


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
    kind = top["camera_kind"]
    if kind in defaults.WITHOUT_EM_REGISTER and top["em_model"] is not None:
        raise r.error(f"em_model is an EM register's: a camera_kind = {kind!r} has none")
    entries = tuple(_entry(r, i, table, kind) for i, table in enumerate(top["acquisition"], 1))
    if not top["light"]:
        for e in entries:
            _check_photon_free(r, e)
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
        camera_kind=kind,
        light=top["light"],
    )


def _check_photon_free(r: _Reader, e: AcquisitionEntry) -> None:
    """``light = false`` (the photon-free path): each acquisition is a dark stack at a
    longer exposure than its dark's, at set-point 1."""
    if e.em_gain_setpoint != 1:
        raise r.error(
            f"light = false (photon-free) needs every stack at set-point 1; this one is at "
            f"{e.em_gain_setpoint:g}",
            e.index,
            e.label,
        )
    if e.exposure_s is None or e.dark_exposure_s is None:
        raise r.error(
            "light = false (photon-free) needs 'exposure_s' and 'dark_exposure_s' (s): "
            "the dark signal's growth with exposure is the signal",
            e.index,
            e.label,
        )
    if e.exposure_s <= e.dark_exposure_s:
        raise r.error(
            f"light = false (photon-free): exposure_s = {e.exposure_s:g} s must be longer "
            f"than its dark's, dark_exposure_s = {e.dark_exposure_s:g} s",
            e.index,
            e.label,
        )


def _entry(r: _Reader, i: int, table: dict, kind: str | None = None) -> AcquisitionEntry:
    """One [[acquisition]] table: the key table's checks, then the rules between keys
    (a camera without an EM register has every set-point at 1, written or not)."""
    label = f"frames = '{table['frames']}'" if isinstance(table.get("frames"), str) else ""
    v = r.table(table, _ACQUISITION_KEYS, i, label)
    if kind in defaults.WITHOUT_EM_REGISTER:
        if v["em_gain_setpoint"] not in (None, 1):
            raise r.error(
                f"em_gain_setpoint = {v['em_gain_setpoint']!r}, but a camera_kind = "
                f"{kind!r} has no EM register: leave it out (or write 1)",
                i,
                label,
            )
        v["em_gain_setpoint"] = 1.0
    elif v["em_gain_setpoint"] is None:
        raise r.error(
            "missing 'em_gain_setpoint' (the camera's EM gain setting, >= 1; a camera "
            "without an EM register says so at the top: camera_kind = 'scmos', 'qcmos' "
            "or 'ccd')",
            i,
            label,
        )
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
        exposure_s=None if v["exposure_s"] is None else float(v["exposure_s"]),
        dark_exposure_s=_dark_exposure(v),
    )


def _dark_exposure(v) -> float | None:
    """The exposure (s) of an acquisition's dark: as written, else the frames' own where
    the maps come from a dark stack of the same settings."""
    if v["dark_exposure_s"] is not None:
        return float(v["dark_exposure_s"])
    return None if v["exposure_s"] is None else float(v["exposure_s"])


def _register_stages(r, name, stages):
    """The manifest's ``register_stages`` (or None), refused beside a model without them."""
    from ...model.noise import EMModel

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
