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
order in which an audit asks which tool a file is: a tool recognises only its own). Each
is checked against the whole of its group's interface when it is loaded: one that cannot
be loaded, lacks any member, or takes a name (or a suffix) already taken is left out
with one line (a :class:`~emccdcal.errors.PluginWarning`) naming what is wrong, is
offered by no command line, and is named with that reason where a user asks for it. A
broken plug-in never stops emccdcal, nor fails in the middle of a fit.
"""

from __future__ import annotations

import functools
import importlib.metadata
import warnings
from dataclasses import dataclass
from collections.abc import Callable

__all__ = [
    "READERS",
    "TOOLS",
    "REGISTERS",
    "Tool",
    "load",
    "names",
    "declared",
    "left_out",
    "unknown",
]

READERS = "emccdcal.readers"
TOOLS = "emccdcal.tools"
REGISTERS = "emccdcal.registers"

#: What an entry point of each group must have (a register model: every member of
#: :class:`emccdcal.model.RegisterModel`, read from the Protocol in :func:`_required`).
_REQUIRED = {
    READERS: ("SUFFIXES", "header", "settings"),
    TOOLS: ("name", "title", "write", "read", "recognizes"),
}

#: Members that must be callable where a plug-in has them (None allowed for a tool's
#: optional ones).
_CALLABLE = {
    READERS: ("header", "settings", "open_stack"),
    TOOLS: ("write", "read", "recognizes", "read_file"),
}


def _required(group: str) -> tuple[str, ...]:
    if group == REGISTERS:
        from .model._protocol import RegisterModel

        return _protocol_members(RegisterModel)
    return _REQUIRED[group]


def _protocol_members(protocol) -> tuple[str, ...]:
    """The members a Protocol declares (its annotations and its own methods and
    properties), in their order."""
    declared = [*getattr(protocol, "__annotations__", {})]
    declared += [n for n in vars(protocol) if not n.startswith("_") and n not in declared]
    return tuple(declared)


def _problem(group: str, obj) -> str:
    """What makes ``obj`` unfit for ``group`` ("" where nothing does): the members it
    lacks, then those that should be callable and are not, then malformed values."""
    missing = [a for a in _required(group) if not hasattr(obj, a)]
    if missing:
        return f"lacks {', '.join(missing)}"
    if group == REGISTERS:
        from .model._protocol import RegisterModel

        methods = [n for n in _required(group) if callable(getattr(RegisterModel, n, None))]
        wrong = [n for n in methods if not callable(getattr(obj, n))]
    else:  # a tool's optional members may be None
        wrong = [n for n in _CALLABLE[group] if not callable(getattr(obj, n, None) or len)]
        if group == TOOLS and obj.write is None:
            wrong.append("write")
    if wrong:
        return f"has {', '.join(wrong)} not callable"
    if group == REGISTERS:
        from .model.register import Register

        if isinstance(obj, type) and issubclass(obj, Register):
            if obj.transform is Register.transform:
                return "subclasses Register without defining its transform(u, g)"
            if not obj.name or not obj.description:
                return "subclasses Register without a name and a description"
    if group == READERS:
        suffixes = obj.SUFFIXES
        if isinstance(suffixes, str) or not all(
            isinstance(x, str) and x.startswith(".") and x == x.lower() for x in suffixes
        ):
            return "has SUFFIXES that are not lower-case suffixes such as '.tif'"
    elif not isinstance(obj.name, str):
        return "has a name that is not text"
    return ""


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
        :func:`emccdcal.export.toolkit.camera_values` at ``setpoint`` (both None for a
        format of every set-point).
    read : callable or None
        ``read(path, text, doc, setpoint, tool_gain)`` → list of
        :class:`emccdcal.export.toolkit.Reading`: the camera entries of the tool's file
        (``text`` its text where it is one, ``doc`` its JSON or YAML where it is one).
    recognizes : callable or None
        ``recognizes(path, text, doc)`` → whether a file is this tool's.
    all_setpoints : bool
        The format holds every set-point (no ``setpoint`` is asked for).
    read_file : callable or None
        ``read_file(path, setpoint)`` → list of readings, or None where the file is not
        one it reads: for a tool whose binary files (a MATLAB ``.mat``) need more than
        their tree of values; asked before the others read such a file.
    write_modes : callable or None
        ``write_modes(rows, setpoint, out, pixel_size_nm, camera_name)`` → the paths
        written, for a tool whose one file holds a table of read-out modes: ``rows`` are
        ``(calibration, set-point, values)``, one per mode
        (:func:`emccdcal.export.tools.export_modes`). None: one mode per file.

    The parts a tool's module is made of (:class:`~emccdcal.export.toolkit.Field`,
    :class:`~emccdcal.export.toolkit.Reading`, the numbers at a set-point, the writers)
    are in :mod:`emccdcal.export.toolkit`.
    """

    name: str
    title: str
    write: Callable
    read: Callable | None = None
    recognizes: Callable | None = None
    all_setpoints: bool = False
    read_file: Callable | None = None
    write_modes: Callable | None = None


def names(group: str) -> tuple[str, ...]:
    """The names of the plug-ins of a group that loaded and fit its interface, in their
    order (what a command line accepts: never one that would fail when used)."""
    return tuple(load(group))


def declared(group: str) -> tuple[str, ...]:
    """The names of a group's entry points, none loaded (a help text's list, which must
    not import the plug-ins: :func:`names` says which of them loaded)."""
    return tuple(dict.fromkeys(ep.name for ep in _entry_points(group)))


def left_out(group: str) -> dict[str, str]:
    """The plug-ins of a group that were left out: name → why (one line)."""
    load(group)
    return dict(_LEFT_OUT.get(group, {}))


def unknown(group: str, name: str, what: str) -> str:
    """The message for ``name`` not among a group's plug-ins: the choices, and why it
    was left out where it was one."""
    why = left_out(group).get(name)
    if why is not None:
        return f"{what} {name!r} was left out: {why}"
    return f"unknown {what} {name!r}; choose one of {', '.join(names(group))}"


def _entry_points(group: str) -> list:
    """A group's entry points: emccdcal's own (of the distribution that installed these
    files, whatever other copy stands on the path), then the others by package; by name."""
    from ._dist import own_distribution

    dist = own_distribution()
    own = sorted(dist.entry_points.select(group=group) if dist else (), key=lambda ep: ep.name)
    others = sorted(
        (
            ep
            for ep in importlib.metadata.entry_points(group=group)
            if ep.dist is None or _normal(ep.dist.name) != "emccdcal"
        ),
        key=lambda ep: (ep.dist.name if ep.dist else "", ep.name),
    )
    return own + others


def _normal(name: str) -> str:
    return name.lower().replace("_", "-").replace(".", "-")


#: group → {name: why}, of the plug-ins :func:`load` left out.
_LEFT_OUT: dict[str, dict[str, str]] = {}


def _conflict(group: str, name: str, obj, loaded: dict, suffixes: set) -> str:
    """How a fit plug-in clashes with those loaded before it ("" where it does not)."""
    if group != READERS and obj.name != name:
        return f"calls itself {obj.name!r}"
    if name in loaded:
        return "the name is taken"
    taken = suffixes & set(getattr(obj, "SUFFIXES", ())) if group == READERS else set()
    return f"suffix '{sorted(taken)[0]}' is taken" if taken else ""


@functools.cache
def load(group: str) -> dict:
    """Every entry point of ``group`` loaded and checked against its interface: name →
    object, in :func:`names`' order. One that cannot be loaded, lacks a member, or takes
    a name or a suffix already taken is left out, with one :class:`PluginWarning`."""
    from ._output import comment
    from .errors import PluginWarning

    out: dict = {}
    suffixes: set = set()
    left = _LEFT_OUT[group] = {}
    for ep in _entry_points(group):
        where = (
            f"plug-in '{ep.name}' ({ep.value}"
            + (f", package '{ep.dist.name}'" if ep.dist else "")
            + f") of {group}"
        )
        try:
            obj = ep.load()
        except Exception as exc:  # noqa: BLE001 - another package's error, in one line
            why = f"could not be loaded: {type(exc).__name__}: {exc}"
        else:
            why = _problem(group, obj) or _conflict(group, ep.name, obj, out, suffixes)
            if not why:
                out[ep.name] = obj
                suffixes |= set(getattr(obj, "SUFFIXES", ()))
                continue
        left[ep.name] = comment(f"{where}: {why}")  # one line, whatever the package says
        warnings.warn(f"{left[ep.name]}; left out", PluginWarning, stacklevel=2)
    return out
