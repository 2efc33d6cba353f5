"""Plug-ins: readers of camera files, localization tools and register models that other
packages add by entry points (as xarray's backends and napari's plug-ins are found), and
emccdcal's own, registered through the same groups in its ``pyproject.toml``.

========================  ==================================================================
entry-point group         what each entry point names, and what it must supply
========================  ==================================================================
``emccdcal.readers``      a module or object: ``SUFFIXES`` (lower-case file name suffixes,
                          ``".tif"``), ``header(path)`` → (shape, dtype, data offset or
                          None, frame stride in bytes or None), ``settings(path)`` →
                          :class:`emccdcal.data.settings.CameraSettings`, and where
                          ``header`` gives no offset ``open_stack(path)`` (an array).
``emccdcal.tools``        a :class:`Tool`: ``name`` (what ``--to``/``--tool`` take),
                          ``title``, ``write`` (the export), and for an audit ``read`` and
                          ``recognizes`` (None where the tool's file cannot be read back).
``emccdcal.registers``    a register model class (:class:`emccdcal.model.RegisterModel`):
                          its ``name``, made with the register's stages.
========================  ==================================================================

A package adds one in its own ``pyproject.toml``, with nothing changed in emccdcal::

    [project.entry-points."emccdcal.readers"]
    rawx = "mypackage.rawx_reader"
    [project.entry-points."emccdcal.tools"]
    toyloc = "mypackage.toyloc:TOOL"

The package's own come first, then the others by package; each package's by name (the
order in which an audit asks which tool a file is: a tool recognises only its own). One that cannot be loaded, lacks
what its group asks, or takes a name (or a suffix) already taken is left out with a
warning naming it: a broken plug-in never stops emccdcal.
"""

from __future__ import annotations

import functools
import importlib.metadata
import warnings
from dataclasses import dataclass
from collections.abc import Callable

__all__ = ["READERS", "TOOLS", "REGISTERS", "Tool", "load", "names"]

READERS = "emccdcal.readers"
TOOLS = "emccdcal.tools"
REGISTERS = "emccdcal.registers"

#: What an entry point of each group must have.
_REQUIRED = {
    READERS: ("SUFFIXES", "header", "settings"),
    TOOLS: ("name", "title", "write", "read", "recognizes"),
    REGISTERS: ("name", "uses_stages", "rows", "excess_noise_factor"),
}


@dataclass(frozen=True)
class Tool:
    """A localization tool (or a format) emccdcal exports to and audits.

    Attributes
    ----------
    name : str
        What ``export --to`` and ``audit --tool`` take.
    title : str
        The tool's own name, for messages (``"ThunderSTORM"``).
    write : callable
        ``write(calibration, setpoint, values, out, qe, pixel_size_nm, camera_name)`` →
        list of the paths written in the folder ``out``; ``values`` are
        :func:`emccdcal.export.tools.camera_values` at ``setpoint`` (both None for a
        format of every set-point).
    read : callable or None
        ``read(path, text, doc, setpoint, tool_gain)`` → list of
        :class:`emccdcal.export.audit.Reading`: the camera entries of the tool's file
        (``text`` its text where it is one, ``doc`` its JSON or YAML where it is one).
    recognizes : callable or None
        ``recognizes(path, text, doc)`` → whether a file is this tool's.
    all_setpoints : bool
        The format holds every set-point (no ``setpoint`` is asked for).
    read_file : callable or None
        ``read_file(path, setpoint)`` → list of readings, or None where the file is not
        one it reads: for a tool whose binary files (a MATLAB ``.mat``) need more than
        their tree of values; asked before the others read such a file.
    """

    name: str
    title: str
    write: Callable
    read: Callable | None = None
    recognizes: Callable | None = None
    all_setpoints: bool = False
    read_file: Callable | None = None


def names(group: str) -> tuple[str, ...]:
    """The names of a group's entry points in their order, without loading any (for a
    command line's choices; :func:`load` then leaves out a broken one)."""
    return tuple(ep.name for ep in _entry_points(group))


def _entry_points(group: str) -> list:
    """A group's entry points: emccdcal's own, then the others by package; by name."""
    found = importlib.metadata.entry_points(group=group)
    own = sorted(
        (ep for ep in found if ep.dist is not None and ep.dist.name == "emccdcal"),
        key=lambda ep: ep.name,
    )
    others = sorted(
        (ep for ep in found if ep not in own),
        key=lambda ep: (ep.dist.name if ep.dist else "", ep.name),
    )
    return own + others


@functools.cache
def load(group: str) -> dict:
    """Every entry point of ``group`` loaded: name → object, in :func:`names`' order."""
    out: dict = {}
    suffixes: set = set()
    for ep in _entry_points(group):
        where = (
            f"plug-in '{ep.name}' ({ep.value}"
            + (f", package '{ep.dist.name}'" if ep.dist else "")
            + f") of {group}"
        )
        try:
            obj = ep.load()
        except Exception as exc:  # noqa: BLE001 - another package's error, in one line
            _leave_out(f"{where} could not be loaded: {type(exc).__name__}: {exc}")
            continue
        missing = [a for a in _REQUIRED[group] if not hasattr(obj, a)]
        taken = suffixes & set(getattr(obj, "SUFFIXES", ()))
        if missing:
            _leave_out(f"{where} lacks {', '.join(missing)}")
        elif group != READERS and obj.name != ep.name:
            _leave_out(f"{where} calls itself '{obj.name}'")
        elif ep.name in out:
            _leave_out(f"{where}: the name is taken")
        elif group == READERS and taken:
            _leave_out(f"{where}: suffix '{sorted(taken)[0]}' is taken")
        else:
            out[ep.name] = obj
            suffixes |= set(getattr(obj, "SUFFIXES", ()))
    return out


def _leave_out(message: str) -> None:
    warnings.warn(f"{message}; left out", stacklevel=3)
