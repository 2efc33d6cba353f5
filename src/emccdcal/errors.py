"""The errors and warnings of emccdcal: one base class for everything a user can cause.

Every problem with the user's input (a manifest, a data file, an option, a method that
the data cannot support) is an :class:`EmccdcalError` whose message is one line naming
the file, the acquisition and the problem. The command line prints exactly that line
and exits with code 2; any other exception is a bug in emccdcal and shows its
traceback. The classes also derive from the built-in exception they refine
(``ValueError``, ``FileNotFoundError``, ``RuntimeError``), so code that catches those
keeps working.
"""

from __future__ import annotations

import contextlib
import contextvars

__all__ = [
    "spelled",
    "spelling",
    "EmccdcalError",
    "OptionError",
    "InputError",
    "ManifestError",
    "MissingFileError",
    "MethodError",
    "NotConvergedError",
    "Cancelled",
    "EmccdcalWarning",
    "InputWarning",
    "ReadNoiseGrowthWarning",
    "DataQualityWarning",
    "DriftWarning",
    "SaturationWarning",
    "LeftOutWarning",
    "FitWarning",
    "ExportWarning",
    "BeadWarning",
    "PluginWarning",
    "Finding",
    "issue_once_per_kind",
]


class EmccdcalError(Exception):
    """Base class of the errors a user can cause; the message is one line.

    Examples
    --------
    >>> import emccdcal
    >>> try:
    ...     emccdcal.calibrate("no-such-manifest.toml")
    ... except emccdcal.EmccdcalError as error:
    ...     print(error)
    manifest file not found: 'no-such-manifest.toml' (resolved to '...')
    """


class OptionError(EmccdcalError, ValueError):
    """An argument or option out of its range or of the wrong type."""


class InputError(EmccdcalError, ValueError):
    """A data file is missing, unreadable, or holds data that cannot be used.

    The message is one line that names the file and the problem.
    """


class ManifestError(InputError):
    """A manifest, or a file it names, is invalid. One line naming the file and the problem."""


class MissingFileError(InputError, FileNotFoundError):
    """A file or directory that was named does not exist."""


class MethodError(EmccdcalError, ValueError):
    """A calibration method that does not exist or that the data cannot support."""


class NotConvergedError(EmccdcalError, RuntimeError):
    """A posterior chain did not meet the convergence criteria within its step budget."""


class Cancelled(EmccdcalError):
    """A run stopped because its caller asked it to (a progress callback raised it:
    a graphical front's Cancel button)."""


class EmccdcalWarning(UserWarning):
    """Base class of every warning of emccdcal: ``warnings.simplefilter("ignore",
    emccdcal.EmccdcalWarning)`` silences them all (each is also in a result's
    ``warnings`` attribute and its report).

    Examples
    --------
    >>> import warnings, emccdcal
    >>> warnings.simplefilter("ignore", emccdcal.EmccdcalWarning)  # all of emccdcal's
    >>> issubclass(emccdcal.errors.DriftWarning, emccdcal.EmccdcalWarning)
    True
    >>> warnings.resetwarnings()
    """


class InputWarning(EmccdcalWarning):
    """Something of the input is off but usable: a file read in full despite damage
    around its data (a TIFF's page index), a manifest and its files that disagree."""


class ReadNoiseGrowthWarning(EmccdcalWarning):
    """The darks' read noise grows with the EM gain set-point (clock-induced charge)."""


class DataQualityWarning(EmccdcalWarning):
    """A finding of the data-quality checks: drift, saturation, pixels left out, a φ
    that could not be checked against the data."""


class DriftWarning(DataQualityWarning):
    """The frame mean of an acquisition drifts: the illumination or the EM gain was not
    steady while it was recorded."""


class SaturationWarning(DataQualityWarning):
    """Counts at the ADC's maximum: left out of the fits, so those pixels read low."""


class LeftOutWarning(DataQualityWarning):
    """Pixels left out of the fit (too few usable frames: saturated, dead or stuck)."""


class FitWarning(EmccdcalWarning):
    """Of the fit: pixels that did not converge, acquisitions the model misfits, gains
    that do not rise with the set-point."""


class ExportWarning(EmccdcalWarning):
    """Of a calibration's use: what a tool's file cannot hold, pixels without a
    calibration, a gain predicted by the gain curve."""


class BeadWarning(EmccdcalWarning):
    """Of the beads: beads left out, blinking, fading, spots the model misfits."""


class PluginWarning(EmccdcalWarning):
    """Another package's plug-in was left out: it could not be loaded, lacks a member of
    its interface, or takes a name already taken (:mod:`emccdcal.plugins`)."""


class Finding(str):
    """A message, with the warning class it is issued as (``category``), and whether it
    makes the result doubtful (``doubtful``) or asks for a check before the result is
    trusted (``caution``): a check's findings are text (kept in JSON reports) that also
    know their kind and weight."""

    category: type = EmccdcalWarning
    doubtful: bool = False
    caution: bool = False

    def __new__(
        cls,
        text: str,
        category: type = EmccdcalWarning,
        *,
        doubtful: bool = False,
        caution: bool = False,
    ):
        finding = super().__new__(cls, text)
        finding.category, finding.doubtful, finding.caution = category, doubtful, caution
        return finding


def _weight(message) -> int:
    """Doubtful findings first, then those that ask for a check, then the rest."""
    return -2 * bool(getattr(message, "doubtful", False)) - bool(getattr(message, "caution", False))


def issue_once_per_kind(caught) -> None:
    """Issue again the warnings caught during one call, at most one per class.

    The weightiest message of each class (a :class:`Finding` that makes the result
    doubtful, then one that asks for a check) is issued as it is; where there were more,
    it names what else was found of that kind, each of which is in full in the result's
    ``warnings`` attribute. The warnings are issued from "emccdcal" rather than the
    caller's line, so that neither a terminal nor a notebook echoes that line.
    """
    import warnings

    kinds: dict = {}
    for w in caught:  # the text given to warnings.warn (a Finding knows its weight)
        given = w.message.args[0] if getattr(w.message, "args", None) else w.message
        kinds.setdefault(w.category, {}).setdefault(str(w.message), given)
    for category, found in kinds.items():
        # the weightiest of a kind is the one shown in full
        first, *more = (str(m) for m in sorted(found.values(), key=_weight))
        if more:
            # each message names its subject before its first ": " (an acquisition, a file)
            subjects = [m.split(": ", 1)[0] for m in more]
            named = (
                all(0 < len(s) <= 80 for s in subjects) and first.split(": ", 1)[0] not in subjects
            )
            first += (
                f" (the same kind of finding also for {', '.join(subjects)}"
                if named
                else f" (and {len(more)} more of this kind"
            ) + ": each in full in the result's 'warnings' attribute)"
        warnings.warn_explicit(first, category, "emccdcal", 0, module="emccdcal")


# The words of the interface that shows a message: the command line's options by default,
# a widget's fields where the napari plugin runs the library.
_SPELLING: contextvars.ContextVar = contextvars.ContextVar("emccdcal_spelling", default={})


def spelled(option: str) -> str:
    """How the interface in use names a command-line option (``"--setpoint G"``): as
    it is on the command line, or as :func:`spelling` says (a widget's field).

    Examples
    --------
    >>> spelled("--setpoint G")
    '--setpoint G'
    >>> with spelling({"--setpoint G": "the 'set-point' field"}):
    ...     spelled("--setpoint G")
    "the 'set-point' field"
    """
    return _SPELLING.get().get(option, option)


@contextlib.contextmanager
def spelling(words: dict):
    """Messages raised inside the block name options as ``words`` says."""
    token = _SPELLING.set({**_SPELLING.get(), **words})
    try:
        yield
    finally:
        _SPELLING.reset(token)
