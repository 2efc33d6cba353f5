"""``emccdcal scan``: a folder of camera files → a manifest a person can read and edit.

Files are grouped by what they record (:func:`emccdcal.data.stacks.stack_settings`) and,
where they record nothing, by their names; every rule used is said in the manifest's
header. Darks are the files whose names say so (``dark``, ``no-signal``, ``bias``,
``background``); a stack's EM gain set-point is its recorded one, else the number before
an ``x`` in its name (``25x-gain.tif``) or after ``gain`` (``gain_300.spe``). The
settings that make two acquisitions comparable — readout rate, analog gain, ADC bits,
binning, region and frame size — must agree across the session: a mismatch is an error
naming both files.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass, field
from pathlib import Path

from .._output import Output, atomic_write_text, comment, toml_line
from ..errors import InputError
from .settings import CameraSettings
from .stacks import STACK_SUFFIXES, stack_header, stack_settings

__all__ = ["ScannedFile", "Session", "scan", "manifest_text", "write_manifest"]

_DARK = re.compile(r"dark|no[-_ ]?signal|bias|background", re.IGNORECASE)
_SETPOINT = (re.compile(r"(?<![\d.])(\d+(?:\.\d+)?)\s*x(?![a-z])", re.IGNORECASE),
             re.compile(r"gain[-_ ]?(\d+(?:\.\d+)?)", re.IGNORECASE))
#: Settings that must agree across a session, and how to name them.
_MUST_AGREE = {"readout_rate_mhz": "readout rate (MHz)", "analog_gain": "analog gain",
               "adc_bits": "ADC bits", "binning": "binning", "roi": "region (x, y, w, h)"}


@dataclass
class ScannedFile:
    """One stack of the session: its path, shape, settings and what it was taken as."""

    path: Path
    shape: tuple
    settings: CameraSettings
    dark: bool
    setpoint: float
    setpoint_rule: str  # "recorded" or "name"


@dataclass
class Session:
    """The stacks of a folder, sorted: ``signal`` by set-point then name, ``darks``."""

    folder: Path
    signal: list[ScannedFile]
    darks: list[ScannedFile]
    rules: list[str] = field(default_factory=list)

    @property
    def kind(self) -> str:
        """``"gain-series"`` (one stack per set-point) or ``"intensity-series"``."""
        setpoints = [f.setpoint for f in self.signal]
        return "gain-series" if len(set(setpoints)) == len(setpoints) else "intensity-series"


def _setpoint_of(path: Path, settings: CameraSettings):
    if settings.em_gain_setpoint is not None:
        return float(settings.em_gain_setpoint), "recorded"
    for pattern in _SETPOINT:
        match = pattern.search(path.stem)
        if match:
            return float(match.group(1)), "name"
    raise InputError(f"'{path}': no EM gain set-point: the file records none and its name "
                     "does not say (e.g. '25x-gain' or 'gain_25'); name it so, or write the "
                     "manifest by hand")


def _files(folder: Path):
    for path in sorted(folder.iterdir()):
        if path.suffix.lower() in STACK_SUFFIXES and not path.name.startswith("."):
            # pipes, devices and dangling links are no camera files (and could block)
            if path.is_file() or (path.is_dir() and path.suffix.lower() == ".zarr"):
                yield path


def scan(folder) -> Session:
    """The session of camera files in ``folder`` (not its subfolders).

    Raises
    ------
    InputError
        No stack in the folder; a file without a set-point; settings that disagree
        between two files (both named); several stacks at one set-point alongside
        others (a gain series and an intensity series mixed); a set-point without a
        dark.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"'{folder}' is not a folder")
    stacks = []
    for path in _files(folder):
        shape, _ = stack_header(path)
        if len(shape) != 3:  # maps (offset, read noise) are not scanned
            continue
        settings = stack_settings(path)
        setpoint, rule = _setpoint_of(path, settings)
        stacks.append(ScannedFile(path, tuple(shape), settings, bool(_DARK.search(path.stem)),
                                  setpoint, rule))
    if not stacks:
        raise InputError(f"'{folder}': no stack of frames ({', '.join(STACK_SUFFIXES)})")
    _check_agreement(stacks)
    signal = sorted((f for f in stacks if not f.dark), key=lambda f: (f.setpoint, f.path.name))
    darks = [f for f in stacks if f.dark]
    if not signal:
        raise InputError(f"'{folder}': only darks (names with dark, no-signal, bias or "
                         "background); no illuminated stack")
    by_setpoint: dict[float, list] = {}
    for f in signal:
        by_setpoint.setdefault(f.setpoint, []).append(f)
    if len(by_setpoint) > 1 and any(len(v) > 1 for v in by_setpoint.values()):
        many = [f"{sp:g}" for sp, v in by_setpoint.items() if len(v) > 1]
        raise InputError(f"'{folder}': several stacks at set-point {', '.join(many)} beside "
                         "other set-points: a gain series and an intensity series mixed; scan "
                         "each from its own folder")
    dark_at = {}
    for d in darks:
        dark_at.setdefault(d.setpoint, d)
    missing = sorted({f.setpoint for f in signal} - set(dark_at))
    if missing:
        raise InputError(f"'{folder}': no dark stack at set-point "
                         f"{', '.join(f'{s:g}' for s in missing)} (a dark's name says dark, "
                         "no-signal, bias or background, and its set-point)")
    rules = ["darks: by name (dark, no-signal, bias or background)"]
    by_rule = {r: [f.path.name for f in stacks if f.setpoint_rule == r] for r in ("recorded", "name")}
    if by_rule["recorded"]:
        rules.append("set-points recorded in the files: " + ", ".join(by_rule["recorded"]))
    if by_rule["name"]:
        rules.append("set-points from the file names: " + ", ".join(by_rule["name"]))
    return Session(folder, signal, darks, rules)


def _check_agreement(stacks) -> None:
    first = stacks[0]
    for f in stacks[1:]:
        if f.shape[1:] != first.shape[1:]:
            raise InputError(f"'{f.path}' has frames of {f.shape[1]} × {f.shape[2]} px, but "
                             f"'{first.path}' {first.shape[1]} × {first.shape[2]}: a session "
                             "covers one region")
    for name, what in _MUST_AGREE.items():
        known = [(f, getattr(f.settings, name)) for f in stacks
                 if getattr(f.settings, name) is not None]
        for f, value in known[1:]:
            if value != known[0][1]:
                raise InputError(f"{what} {value} in '{f.path}' but {known[0][1]} in "
                                 f"'{known[0][0].path}': a series is taken with one {what}")


def manifest_text(session: Session, where: Path) -> str:
    """The manifest of ``session`` as TOML with comments, paths relative to ``where``."""
    where = Path(where).resolve().parent

    def rel(path: Path) -> str:
        try:
            return str(path.resolve().relative_to(where))
        except ValueError:
            return str(path.resolve())

    kind = session.kind
    lines = [comment(f"# {kind} scanned from {session.folder} by emccdcal scan, "
                     f"{time.strftime('%Y-%m-%d %H:%M', time.localtime())}."),
             "# Rules used:"] + [comment(f"#   {r}") for r in session.rules]
    lines.append("# Check it, then: emccdcal calibrate THIS.toml --method "
                 + ("gs" if kind == "gain-series" else "is-adu") + " -o OUT")
    bits = {f.settings.adc_bits for f in session.signal + session.darks} - {None}
    if len(bits) == 1:
        lines.append(toml_line("adc_bits", int(bits.pop())))
    else:
        lines.append("# adc_bits = 16   # not recorded: the camera's ADC resolution, if known")
    if kind == "gain-series":
        lines.append("# e_per_adu = \"../out-adu\"   # phi from an is-adu result, for the gain methods")
    darks = {}
    for d in session.darks:
        darks.setdefault(d.setpoint, d)
    for i, f in enumerate(session.signal, start=1):
        lines += ["", "[[acquisition]]"]
        known = f.settings.known()
        if known:  # text from the file: one comment line, whatever it holds
            lines.append(comment("# recorded: " + ", ".join(f"{k} {v}" for k, v in known.items())))
        lines.append(toml_line("name", f.path.stem))
        lines.append(toml_line("frames", rel(f.path)))
        lines.append(toml_line("em_gain_setpoint", f.setpoint)
                     + ("" if f.setpoint_rule == "recorded" else "  # from the file name"))
        if kind == "intensity-series":
            lines.append(toml_line("level", f"L{i}"))
        lines.append(toml_line("dark", rel(darks[f.setpoint].path)))
    return "\n".join(lines) + "\n"


def write_manifest(session: Session, out, *, overwrite: bool = False) -> Path:
    """Write :func:`manifest_text` to ``out`` (atomically); an existing file only with
    ``overwrite``, and never one of the session's stacks."""
    out = Path(out)
    inputs = [f.path for f in session.signal + session.darks]
    with Output(out, kind="file", inputs=inputs, overwrite=overwrite):
        atomic_write_text(out, manifest_text(session, out))
    return out
