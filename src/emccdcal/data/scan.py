"""``emccdcal scan``: a folder of camera files → a manifest a person can read and edit.

Files are grouped by what they record (:func:`emccdcal.data.stacks.stack_settings`) and,
where they record nothing, by their names; every rule used is said in the manifest's
header, and every file of the folder is either used or skipped with its reason.

- A **stack** (frames × rows × cols) is a dark where its name says so (``dark``,
  ``no-signal``, ``bias``, ``background``), else illuminated. Its EM gain set-point is
  the recorded one, else the number before an ``x`` in its name (``25x-gain.tif``) or
  after ``gain`` (``gain_300.spe``).
- A **map** (rows × cols) is an offset map where its name says ``S0``, ``offset``,
  ``bias`` or ``mean``, a read-noise map where it says ``sigma``, ``std``, ``rn`` or
  ``read-noise``; an offset map and a read-noise map at one set-point (from the name)
  are one dark, as the published ProEM folders of Ryan et al. (2021) hold them. A dark
  stack at the same set-point is preferred (it also gives the maps' frame count).
- The settings that make two acquisitions comparable — readout rate, analog gain, ADC
  bits, binning, region and frame size — must agree across the session: a mismatch is an
  error naming both files.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

from .. import defaults
from .._output import Output, atomic_write_text, comment, toml_line
from ..errors import InputError
from .settings import CameraSettings
from .stacks import STACK_SUFFIXES, setpoint_in_name, stack_header, stack_settings

__all__ = ["ScannedFile", "MapPair", "Session", "scan", "manifest_text", "write_manifest"]

_DARK = re.compile(r"dark|no[-_ ]?signal|bias|background", re.IGNORECASE)
#: An exposure in a file's name (``dark-0.5s``, ``dark_500ms``, ``20us``), and its unit's
#: seconds.
_EXPOSURE = re.compile(r"(?<![0-9.])(\d+(?:\.\d+)?)\s*(ms|us|µs|s)(?![a-z])", re.IGNORECASE)
_EXPOSURE_UNIT = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6}


def _word(alternatives: str) -> re.Pattern:
    """A whole word of a file name (between separators), case-insensitive."""
    return re.compile(rf"(?<![a-z0-9])(?:{alternatives})(?![a-z0-9])", re.IGNORECASE)


#: What a map's name says it holds.
_MAP_KINDS = {
    "offset": _word(r"s0|offset|bias|mean"),
    "read_noise": _word(r"sigma|std|rn|read[-_ ]?noise|noise"),
    "e_per_adu": _word(r"adu|e[-_]?per[-_]?adu|conversion"),
}
#: Settings that must agree across a session, and how to name them.
_MUST_AGREE = {
    "amplifier": "output amplifier",
    "readout_rate_mhz": "readout rate (MHz)",
    "analog_gain": "analog gain",
    "adc_bits": "ADC bits",
    "binning": "binning",
    "roi": "region (x, y, w, h)",
}
_DARK_HELP = (
    "name a dark stack with its set-point and 'dark' (e.g. '{sp}x-dark.tif'), or "
    "an offset and a read-noise map ('{sp}x_S0.tif' and '{sp}x_sigma.tif'); or "
    'write the manifest by hand, each acquisition with dark = "FILE" or offset = '
    '"FILE" and read_noise = "FILE" (docs/manifest.md)'
)


@dataclass(frozen=True)
class ScannedFile:
    """One stack of the session: its path, shape, settings and what it was taken as."""

    path: Path
    shape: tuple
    settings: CameraSettings
    dark: bool
    setpoint: float
    setpoint_rule: str  # "recorded" or "name"
    #: The exposure (s) the file records, else the one its name says, else None; and
    #: which ("recorded" or "name").
    exposure_s: float | None = None
    exposure_rule: str | None = None


@dataclass(frozen=True)
class MapPair:
    """The offset and read-noise maps (ADU) of one dark, at one set-point (by name)."""

    offset: Path
    read_noise: Path
    setpoint: float


@dataclass
class Session:
    """The folder's stacks, sorted (``signal`` by set-point then name), the dark of each
    set-point (a stack or a map pair), and what was skipped and why."""

    folder: Path
    signal: list[ScannedFile]
    darks: dict[float, ScannedFile | MapPair]
    rules: list[str] = field(default_factory=list)
    skipped: list[tuple[str, str]] = field(default_factory=list)
    e_per_adu_map: Path | None = None
    #: ``"scmos"`` for a folder of Huang's names with no set-point anywhere (a camera
    #: without an EM register), else None.
    camera_kind: str | None = None
    #: False for a folder of darks only, at several exposures (the photon-free path).
    light: bool = True

    @property
    def kind(self) -> str:
        """``"gain-series"`` (one stack per set-point) or ``"intensity-series"``."""
        setpoints = [f.setpoint for f in self.signal]
        return "gain-series" if len(set(setpoints)) == len(setpoints) else "intensity-series"

    def summary(self) -> list[str]:
        """What was found, used and skipped, one line each (the console's report)."""
        setpoints = sorted({f.setpoint for f in self.signal})
        n_maps = sum(isinstance(d, MapPair) for d in self.darks.values())
        dark_words = (
            [f"{len(self.darks) - n_maps} dark stack(s)"] if n_maps < len(self.darks) else []
        )
        if n_maps:
            dark_words.append(f"{n_maps} offset/read-noise map pair(s)")
        if self.kind == "gain-series":
            head = (
                f"gain-series: {len(setpoints)} set-points "
                f"({', '.join(f'{s:g}' for s in setpoints)})"
            )
        else:
            head = (
                f"intensity-series: {len(self.signal)} levels at set-point "
                f"{', '.join(f'{s:g}' for s in setpoints)}"
            )
        lines = [f"{head}; darks: {' and '.join(dark_words)}", "used:"]
        for f in self.signal:
            dark = self.darks[f.setpoint]
            what = (
                f"dark {dark.path.name}"
                if isinstance(dark, ScannedFile)
                else f"offset {dark.offset.name}, read noise {dark.read_noise.name}"
            )
            lines.append(f"  {f.path.name} (set-point {f.setpoint:g}, {f.setpoint_rule}); {what}")
        if self.skipped:
            lines.append("skipped:")
            lines += [f"  {name}: {why}" for name, why in self.skipped]
        lines += [f"rule: {r}" for r in self.rules]
        return lines


#: The rule of a stack of a camera without an EM register: Huang et al.'s (2013) names.
_NO_REGISTER = "no EM register: no file records or names a set-point (sCMOS/qCMOS names)"


def _setpoint_of(path: Path, settings: CameraSettings):
    if settings.em_gain_setpoint is not None:
        return float(settings.em_gain_setpoint), "recorded"
    setpoint = setpoint_in_name(path)
    if setpoint is not None:
        return setpoint, "name"
    return None, None


#: The rule of a folder of darks only (Diekmann et al. 2022).
_PHOTON_FREE = "photon-free: darks only, at several exposures; the shortest is the others' dark"


def _exposure_of(path: Path, settings: CameraSettings):
    """(seconds, rule) of a stack's exposure: recorded, else in its name, else None."""
    if settings.exposure_ms is not None:
        return settings.exposure_ms / 1000.0, "recorded"
    found = _EXPOSURE.search(path.stem)
    if found is None:
        return None, None
    return float(found.group(1)) * _EXPOSURE_UNIT[found.group(2).lower()], "from the file name"


def _photon_free(stacks):
    """A folder of darks only at two or more known exposures: (the shortest, the others
    as the series' stacks, their dark signal its signal); else None."""
    if not stacks or not all(f.dark and f.setpoint == 1.0 for f in stacks):
        return None
    if any(f.exposure_s is None for f in stacks) or len({f.exposure_s for f in stacks}) < 2:
        return None
    ordered = sorted(stacks, key=lambda f: (f.exposure_s, f.path.name))
    return ordered[0], [replace(f, dark=False) for f in ordered[1:]]


def _no_setpoint(path: Path) -> InputError:
    return InputError(
        f"'{path}': no EM gain set-point: the file records none and its name "
        "does not say (e.g. '25x-gain' or 'gain_25'); name it so, or write the "
        "manifest by hand"
    )


def _files(folder: Path):
    """(camera files, other files) of ``folder``, not hidden, not in subfolders."""
    camera, other = [], []
    for path in sorted(folder.iterdir()):
        if path.name.startswith("."):
            continue
        # pipes, devices and dangling links are no camera files (and could block)
        if path.suffix.lower() in STACK_SUFFIXES and (
            path.is_file() or (path.is_dir() and path.suffix.lower() == ".zarr")
        ):
            camera.append(path)
        elif path.is_file():
            other.append(path)
    return camera, other


def _subfolders_with_stacks(folder: Path) -> list[str]:
    return [
        d.name
        for d in sorted(folder.iterdir())
        if d.is_dir()
        and not d.name.startswith(".")
        and d.suffix.lower() != ".zarr"
        and _files(d)[0]
    ]


def _refuse_unfinished(folder: Path) -> None:
    """An acquisition session that did not finish holds stacks short of their plan (or
    a store begun with no frame): refused, with the command that finishes it."""
    from .. import _files as files
    from ..defaults import SESSION_FILE

    record = folder / SESSION_FILE
    if not record.is_file():
        return
    try:
        state = files.load_json(record, what="session record")
    except InputError:
        return  # not a session acquire wrote: the files are scanned as they are
    status = state.get("status") if isinstance(state, dict) else None
    if status not in (None, "complete"):
        raise InputError(
            f"{folder}: an acquisition session that has not finished "
            f"({comment(str(status))}): its stacks are short of the plan; "
            f"finish it with 'emccdcal acquire {folder / 'plan.toml'} -o {folder} "
            "--resume'"
        )


def scan(folder) -> Session:
    """The session of camera files in ``folder`` (not its subfolders).

    Raises
    ------
    InputError
        No stack in the folder (naming subfolders that hold some); a stack without a
        set-point; settings that disagree between two files (both named); several stacks
        at one set-point alongside others (a gain series and an intensity series mixed);
        a set-point with neither a dark stack nor an offset and read-noise map pair (the
        message says what to rename, or which manifest lines to write).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"'{folder}' is not a folder")
    _refuse_unfinished(folder)
    camera, other = _files(folder)
    stacks, maps, skipped = [], [], []
    found = [(p, stack_header(p)[0]) for p in camera]
    stack_paths = [p for p, shape in found if len(shape) == 3]
    settings_of = {p: stack_settings(p) for p in stack_paths}
    said = {p: _setpoint_of(p, settings_of[p]) for p in stack_paths}
    # A camera without an EM register: no stack says a set-point, and the files say so
    # (their models) or one is a dark (Huang et al.'s dark.tif, int1.tif …).
    kinds = {settings_of[p].camera_kind for p in stack_paths} - {None}
    if "iccd" in kinds:
        path = next(p for p in stack_paths if settings_of[p].camera_kind == "iccd")
        raise InputError(
            f"'{path}' is of an intensified camera (its model {settings_of[path].model}): its "
            "gain is an image intensifier's, which no model here describes"
        )
    no_register = (
        len(stack_paths) >= 2
        and all(sp is None for sp, _ in said.values())
        and (
            (len(kinds) == 1 and kinds <= set(defaults.WITHOUT_EM_REGISTER))
            or (not kinds and any(_DARK.search(p.stem) for p in stack_paths))
        )
    )
    kind = next(iter(kinds)) if kinds else "scmos"
    for path, shape in found:
        if len(shape) == 3:
            settings = settings_of[path]
            setpoint, rule = said[path]
            if setpoint is None and no_register:
                setpoint, rule = 1.0, "no EM register"
            elif setpoint is None:
                raise _no_setpoint(path)
            stacks.append(
                ScannedFile(
                    path, tuple(shape), settings, bool(_DARK.search(path.stem)), setpoint, rule,
                    *_exposure_of(path, settings),
                )
            )  # fmt: skip
        elif len(shape) == 2:
            maps.append((path, tuple(shape)))
        else:
            skipped.append(
                (path.name, f"{len(shape)}-dimensional: neither a stack of frames nor a map")
            )
    if not stacks:
        inner = _subfolders_with_stacks(folder)
        where = f"; its subfolders {', '.join(inner)} hold some: scan each" if inner else ""
        raise InputError(f"'{folder}': no stack of frames ({', '.join(STACK_SUFFIXES)}){where}")
    _check_agreement(stacks)
    photon_free = _photon_free(stacks) if no_register else None
    if photon_free is not None:  # the longer darks are the signal, the shortest their dark
        stacks = [photon_free[0], *photon_free[1]]
    signal = sorted(
        (f for f in stacks if not f.dark),
        key=lambda f: (f.setpoint, f.exposure_s or 0.0, f.path.name),
    )
    if not signal:
        raise InputError(
            f"'{folder}': only darks (names with dark, no-signal, bias or "
            "background); no illuminated stack"
        )
    _check_one_kind(folder, signal)
    frame = signal[0].shape[1:]
    wanted = {f.setpoint for f in signal}
    pairs, e_per_adu_map = _map_pairs(maps, frame, wanted, skipped)
    darks: dict[float, ScannedFile | MapPair] = {}
    for d in sorted((f for f in stacks if f.dark), key=lambda f: f.path.name):
        if d.setpoint not in wanted:
            skipped.append(
                (d.path.name, f"a dark at set-point {d.setpoint:g}, where no illuminated stack is")
            )
        elif d.setpoint in darks:
            skipped.append(
                (
                    d.path.name,
                    f"a second dark at set-point {d.setpoint:g}: "
                    f"{darks[d.setpoint].path.name} is used",
                )
            )
        else:
            darks[d.setpoint] = d
    for sp, pair in pairs.items():
        if sp in darks:
            for p in (pair.offset, pair.read_noise):
                skipped.append(
                    (
                        p.name,
                        f"the dark stack {darks[sp].path.name} at set-point {sp:g} is used instead",
                    )
                )
        else:
            darks[sp] = pair
    missing = sorted(wanted - set(darks))
    if missing:
        seen = (
            "; seen and not used: " + ", ".join(f"{name} ({why})" for name, why in skipped)
            if skipped
            else ""
        )
        raise InputError(
            f"'{folder}': no dark at set-point "
            f"{', '.join(f'{s:g}' for s in missing)}: "
            + _DARK_HELP.format(sp=f"{missing[0]:g}")
            + seen
        )
    if other:
        names = ", ".join(p.name for p in other[:5]) + (", …" if len(other) > 5 else "")
        skipped.append((f"{len(other)} other file(s)", f"not camera files ({names})"))
    rules = _rules(stacks, pairs, darks) + ([_NO_REGISTER] if no_register else [])
    rules += [_PHOTON_FREE] if photon_free is not None else []
    return Session(
        folder, signal, darks, rules, skipped, e_per_adu_map, kind if no_register else None,
        light=photon_free is None,
    )  # fmt: skip


def _check_one_kind(folder: Path, signal) -> None:
    by_setpoint: dict[float, list] = {}
    for f in signal:
        by_setpoint.setdefault(f.setpoint, []).append(f)
    if len(by_setpoint) > 1 and any(len(v) > 1 for v in by_setpoint.values()):
        many = [f"{sp:g}" for sp, v in by_setpoint.items() if len(v) > 1]
        raise InputError(
            f"'{folder}': several stacks at set-point {', '.join(many)} beside "
            "other set-points: a gain series and an intensity series mixed; scan "
            "each from its own folder"
        )


def _map_pairs(maps, frame, wanted, skipped):
    """The offset/read-noise map pairs by set-point, and a map named for e⁻/ADU; every
    other map goes to ``skipped`` with its reason."""
    found: dict[float, dict[str, list[Path]]] = {}
    e_per_adu_map = None
    for path, shape in maps:
        kinds = [k for k, pattern in _MAP_KINDS.items() if pattern.search(path.stem)]
        setpoint = setpoint_in_name(path)
        if kinds == ["e_per_adu"]:
            e_per_adu_map = e_per_adu_map or path
            skipped.append(
                (
                    path.name,
                    "a map named for e⁻/ADU, not a dark: see the manifest's "
                    "commented e_per_adu line",
                )
            )
        elif len(kinds) != 1:
            skipped.append(
                (
                    path.name,
                    "a map whose name says neither offset (S0, offset, bias, "
                    "mean) nor read noise (sigma, std, rn, read-noise)"
                    if not kinds
                    else "a map whose name says both " + " and ".join(kinds),
                )
            )
        elif shape != frame:
            skipped.append(
                (
                    path.name,
                    f"a {shape[0]} × {shape[1]} px map; the frames are {frame[0]} × {frame[1]} px",
                )
            )
        elif setpoint is None:
            skipped.append((path.name, "a map whose name gives no set-point (e.g. '25x_S0')"))
        elif setpoint not in wanted:
            skipped.append(
                (path.name, f"a map at set-point {setpoint:g}, where no illuminated stack is")
            )
        else:
            found.setdefault(setpoint, {"offset": [], "read_noise": []})[kinds[0]].append(path)
    pairs = {}
    for sp, by_kind in sorted(found.items()):
        offsets, noises = by_kind["offset"], by_kind["read_noise"]
        if offsets and noises:
            pairs[sp] = MapPair(offsets[0], noises[0], sp)
        for p in offsets[1:] + noises[1:]:
            skipped.append((p.name, f"a second map of its kind at set-point {sp:g}"))
        for p in (offsets or noises)[:1] if not (offsets and noises) else ():
            other = "read-noise" if offsets else "offset"
            skipped.append((p.name, f"no {other} map at set-point {sp:g} to pair it with"))
    return pairs, e_per_adu_map


def _rules(stacks, pairs, darks) -> list[str]:
    rules = []
    if any(isinstance(d, ScannedFile) for d in darks.values()):
        rules.append("dark stacks: by name (dark, no-signal, bias or background)")
    if any(isinstance(d, MapPair) for d in darks.values()):
        rules.append(
            "dark maps: by name (offset: S0, offset, bias or mean; read noise: "
            "sigma, std, rn or read-noise), set-points from the names"
        )
    by_rule = {
        r: [
            f.path.name
            for f in sorted(stacks, key=lambda f: (f.setpoint, f.path.name))
            if f.setpoint_rule == r
        ]
        for r in ("recorded", "name")
    }
    if by_rule["recorded"]:
        rules.append("set-points recorded in the files: " + ", ".join(by_rule["recorded"]))
    if by_rule["name"]:
        rules.append("set-points from the file names: " + ", ".join(by_rule["name"]))
    return rules


def _check_agreement(stacks) -> None:
    first = stacks[0]
    for f in stacks[1:]:
        if f.shape[1:] != first.shape[1:]:
            raise InputError(
                f"'{f.path}' has frames of {f.shape[1]} × {f.shape[2]} px, but "
                f"'{first.path}' {first.shape[1]} × {first.shape[2]}: a session "
                "covers one region"
            )
    for name, what in _MUST_AGREE.items():
        known = [
            (f, getattr(f.settings, name)) for f in stacks if getattr(f.settings, name) is not None
        ]
        for f, value in known[1:]:
            if value != known[0][1]:
                raise InputError(
                    f"{what} {value} in '{f.path}' but {known[0][1]} in "
                    f"'{known[0][0].path}': a series is taken with one {what}"
                )


def _name_of(path: Path) -> str:
    """An acquisition's name: its file's, without the suffixes (``.ome.zarr``)."""
    stem = path.stem
    return stem[:-4] if stem.lower().endswith(".ome") and len(stem) > 4 else stem


def manifest_text(session: Session, where: Path) -> str:
    """The manifest of ``session`` as TOML with comments, paths relative to ``where``."""
    where = Path(where).resolve().parent

    def rel(path: Path) -> str:
        try:
            return str(path.resolve().relative_to(where))
        except ValueError:
            return str(path.resolve())

    kind = session.kind
    lines = [
        comment(
            f"# {kind} scanned from {session.folder} by emccdcal scan, "
            f"{time.strftime('%Y-%m-%d %H:%M', time.localtime())}."
        ),
        "# Rules used:",
    ] + [comment(f"#   {r}") for r in session.rules]
    lines += [comment(f"# Skipped: {name}: {why}") for name, why in session.skipped]
    if any(isinstance(d, MapPair) for d in session.darks.values()):
        lines.append(
            "# Offset and read-noise maps are taken as exact; add dark_frames = N "
            "to an acquisition whose maps came from N dark frames."
        )
    lines.append(
        "# Check it, then: emccdcal calibrate THIS.toml"
        + (
            ""
            if session.camera_kind
            else " --method " + ("gs" if kind == "gain-series" else "is-adu")
        )
        + " -o OUT"
    )
    recorded = {f.settings.camera_kind for f in session.signal} == {session.camera_kind}
    if session.camera_kind is not None:
        lines.append(
            toml_line("camera_kind", session.camera_kind)
            + (
                "   # the files' model says so"
                if recorded
                else "   # or 'qcmos' or 'ccd': the files do not say; all calibrate alike"
            )
        )
    if not session.light:
        lines.append(toml_line("light", False) + "   # darks only: the photon-free path")
    bits = {f.settings.adc_bits for f in session.signal} - {None}
    bits |= {d.settings.adc_bits for d in session.darks.values() if isinstance(d, ScannedFile)} - {
        None
    }
    if len(bits) == 1:
        lines.append(toml_line("adc_bits", int(bits.pop())))
    else:
        lines.append("# adc_bits = 16   # not recorded: the camera's ADC resolution, if known")
    if kind == "gain-series":
        if session.e_per_adu_map is not None:
            lines.append(
                comment(
                    "# "
                    + toml_line("e_per_adu", rel(session.e_per_adu_map))
                    + "   # a map named for e-/ADU in the folder: use it only "
                    "if it holds e-/ADU of this camera"
                )
            )
        lines.append(
            '# e_per_adu = "../out-adu"   # phi from an is-adu result, for the gain methods'
        )
    for i, f in enumerate(session.signal, start=1):
        lines += ["", "[[acquisition]]"]
        known = f.settings.known()
        if known:  # text from the file: one comment line, whatever it holds
            lines.append(comment("# recorded: " + ", ".join(f"{k} {v}" for k, v in known.items())))
        lines.append(toml_line("name", _name_of(f.path)))
        lines.append(toml_line("frames", rel(f.path)))
        if session.camera_kind is None:
            lines.append(
                toml_line("em_gain_setpoint", f.setpoint)
                + ("" if f.setpoint_rule == "recorded" else "  # from the file name")
            )
        if kind == "intensity-series":
            lines.append(toml_line("level", f"L{i}"))
        if f.exposure_s is not None:
            lines.append(toml_line("exposure_s", f.exposure_s) + f"   # {f.exposure_rule}")
        dark = session.darks[f.setpoint]
        if isinstance(dark, MapPair):
            lines.append(toml_line("offset", rel(dark.offset)))
            lines.append(toml_line("read_noise", rel(dark.read_noise)))
        else:
            lines.append(toml_line("dark", rel(dark.path)))
            if dark.exposure_s is not None and dark.exposure_s != f.exposure_s:
                lines.append(
                    toml_line("dark_exposure_s", dark.exposure_s) + f"   # {dark.exposure_rule}"
                )
    return "\n".join(lines) + "\n"


def manifest_path(out, folder) -> Path:
    """Where ``scan`` writes: ``OUT`` itself when it names a ``.toml`` file, else
    ``OUT/manifest.toml`` (``OUT`` a folder, as every other verb's ``-o``); without
    ``OUT``, ``FOLDER/manifest.toml``."""
    if out is None:
        return Path(folder) / "manifest.toml"
    out = Path(out)
    return out if out.suffix.lower() == ".toml" else out / "manifest.toml"


def write_manifest(session: Session, out, *, overwrite: bool = False) -> Path:
    """Write :func:`manifest_text` to ``out`` (atomically); an existing file only with
    ``overwrite``, and never one of the session's files."""
    out = Path(out)
    inputs = [f.path for f in session.signal]
    for dark in session.darks.values():
        inputs += [dark.offset, dark.read_noise] if isinstance(dark, MapPair) else [dark.path]
    with Output(out, kind="file", inputs=inputs, overwrite=overwrite):
        atomic_write_text(out, manifest_text(session, out))
    return out


def scan_folder(folder, out=None, *, overwrite: bool = False) -> Path:
    """Write the manifest of a folder of camera files, as ``emccdcal scan`` does.

    The folder's stacks are grouped into a gain series or an intensity series by the
    settings they record (else by their names: the manifest says every rule it used),
    each paired with its dark; the manifest lists the files used and skipped, and why.

    Parameters
    ----------
    folder : str or Path
        The folder of camera files (not its subfolders).
    out : str or Path, optional
        The folder to write ``manifest.toml`` into, or the manifest's own name ending in
        ``.toml`` (default ``folder/manifest.toml``).
    overwrite : bool
        Replace an existing manifest (never one of the folder's camera files).

    Returns
    -------
    Path
        The manifest written, for :func:`emccdcal.calibrate`.

    Raises
    ------
    InputError
        As :func:`scan`: the message names the file and says what to rename or write.

    Examples
    --------
    >>> import emccdcal, tempfile
    >>> work = tempfile.mkdtemp()
    >>> sim = emccdcal.simulate_gain_series(
    ...     f"{work}/gs", rows=4, cols=4, frames=200, setpoints=(1, 10), seed=1, progress=False
    ... )
    >>> emccdcal.scan(f"{work}/gs/gain-GS", f"{work}/scanned.toml").name
    'scanned.toml'
    """
    return write_manifest(scan(folder), manifest_path(out, folder), overwrite=overwrite)
