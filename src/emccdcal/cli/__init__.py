"""The command line: ``emccdcal VERB ...``, a thin layer over the library.

One module per verb (``cli/<verb>.py``) with ``add_parser(subparsers)``, whose parser
sets ``func`` to the verb's ``run(args)`` (returns the exit code); every verb imports its
implementation inside ``run``, and only the parser of the verb being run is built, so
``emccdcal --help`` and ``--version`` import no numerics. Options shared by verbs are
declared once in :mod:`emccdcal.cli._common`.

Errors: an :class:`emccdcal.errors.EmccdcalError` (bad input) is printed as one line and
exits 2, and every warning as one line, ``warning: ...``; any other exception is a bug
and shows its traceback. Ctrl-C prints one line and exits 130.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import sys
import warnings

from .. import __version__
from .._output import given_inputs
from ..errors import EmccdcalError

__all__ = [
    "main",
    "build_parser",
    "reference_parser",
    "VERBS",
    "paths_given",
    "check_numbers",
    "OUTPUT_DESTS",
]

#: The arguments that name where a verb writes; every other path it is given is an input.
OUTPUT_DESTS = ("out", "dir")

#: Verbs in the order of ``--help``, with their one-line help.
VERBS = {
    "demo": "simulate the paper's data and calibrate it (is-adu, then gs)",
    "plan": "what to record to reach a target precision (light, frames, darks)",
    "acquire": "record a plan through Micro-Manager (or the simulated EMCCD)",
    "simulate": "write synthetic stacks, darks, a manifest and truth.json",
    "calibrate": "calibrate from a manifest (the main job)",
    "posterior": "MCMC posterior of single pixels",
    "scan": "write the manifest of a folder of camera files",
    "check": "data-quality checks of a manifest's acquisitions (no fitting)",
    "report": "write a self-contained HTML report of calibration results",
    "validate": "bead validation: fit beads under each calibration, compare set-points",
    "cots": "calibration-on-the-spot: EM gain and offset from bead frames",
    "export": "write a calibration in a localization tool's own file",
    "audit": "check a localization tool's camera settings against a calibration",
    "apply": "convert a movie to photoelectrons per pixel, (S - offset) * phi / g",
    "gain-curve": "fit the gain against the set-point; predict set-points not measured",
    "gain-check": "the EM gain from dark frames alone, against its calibration",
    "db": "the calibration database: add, list, show, compare (ageing), remove, relocate",
}


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line and exit code 2."""

    def error(self, message: str) -> None:  # noqa: D401 - argparse API
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser(verb: str | None = None, *, every_verb: bool = False) -> argparse.ArgumentParser:
    """The parser of ``emccdcal``; only ``verb``'s own options are built (with None,
    placeholders that list the verbs: a run needs its own verb's alone), or every verb's
    with ``every_verb`` (the command reference, :func:`reference_parser`)."""
    parser = _Parser(
        prog="emccdcal",
        description="Calibrate EMCCD cameras: the ADU conversion factor (e-/ADU) and the true "
        "EM gain at every set-point, per pixel, with standard errors.",
    )
    parser.add_argument("--version", action="version", version=f"emccdcal {__version__}")
    subparsers = parser.add_subparsers(dest="verb", metavar="VERB", parser_class=_Parser)
    for name, text in VERBS.items():
        if name == verb or every_verb:
            importlib.import_module(f"{__name__}.{name.replace('-', '_')}").add_parser(subparsers)
        else:
            subparsers.add_parser(name, help=text, add_help=False)
    return parser


def reference_parser() -> argparse.ArgumentParser:
    """The parser with every verb's options built: what the command reference
    (docs/cli.rst) renders, each verb with its options and their defaults."""
    return build_parser(every_verb=True)


def paths_given(args) -> list:
    """Every path on the command line but the output (:data:`OUTPUT_DESTS`): the verb's
    inputs, which no output of the run may write over."""
    from pathlib import Path

    found = []

    def walk(value, results):
        if isinstance(value, Path) or (results and isinstance(value, str)):
            # calibrations may be comma-joined groups (a path with a comma is kept whole)
            parts = [value] if Path(value).exists() or not results else str(value).split(",")
            found.extend(Path(p) for p in parts if str(p).strip())
        elif isinstance(value, (list, tuple)):
            for item in value:
                walk(item, results)

    for dest, value in vars(args).items():
        if dest not in OUTPUT_DESTS:
            walk(value, dest in ("results", "calibration"))
    return found


def check_numbers(args) -> None:
    """Refuse, before any work, a numeric option outside the range of its quantity
    (:data:`emccdcal.defaults.BOUNDS`, named by the option or by
    :data:`~emccdcal.defaults.OPTION_QUANTITY`): a number in another unit, or one that
    would make a computation run for hours."""
    from numbers import Real

    import numpy as np

    from .._util import within_bounds
    from ..defaults import OPTION_QUANTITY

    for dest, value in vars(args).items():
        values = value if isinstance(value, (list, tuple)) else [value]
        for v in values:
            if isinstance(v, Real) and not isinstance(v, bool):
                within_bounds(
                    OPTION_QUANTITY.get(dest, dest),
                    np.asarray(float(v)),
                    f"{v:g}",
                    label=f"--{dest.replace('_', '-')}",
                )


def _verb_of(argv: list[str]) -> str | None:
    """The verb named on the command line: the first word that is not an option."""
    for word in argv:
        if not word.startswith("-"):
            return word if word in VERBS else None
    return None


def _safe_streams() -> None:
    # Help texts and messages must print under any locale (a cp1252 console, a pipe).
    for stream in (sys.stdout, sys.stderr):
        reconfigure = getattr(stream, "reconfigure", None)
        if reconfigure is not None:
            reconfigure(errors="backslashreplace")


class _Escaping:
    """A stream as the verbs see it: every character a terminal acts on is escaped
    (:func:`emccdcal._output.escape_controls`), line breaks kept, so that text a file
    recorded (a serial, a camera's name) cannot drive the terminal, whatever verb prints
    it. Standard error is left to the progress bars, which redraw their line on purpose;
    the errors and warnings printed there are each one escaped line
    (:func:`emccdcal._output.comment`)."""

    def __init__(self, stream):
        self._stream = stream

    def write(self, text):
        from .._output import escape_controls

        return self._stream.write(escape_controls(text))

    def __getattr__(self, name):
        return getattr(self._stream, name)


def main(argv: list[str] | None = None) -> int:
    """Run ``emccdcal`` with ``argv`` (default: the process's arguments); the exit code."""
    _safe_streams()
    out = sys.stdout
    sys.stdout = _Escaping(out)
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _one_line  # those no verb records and prints itself
            return _main(argv)
    finally:
        sys.stdout = out
        if _verb_of(argv) in _COLLECT_AFTER:
            # What the verb left for the garbage collector goes now, in this thread:
            # Micro-Manager's C++ core, collected later by a daemon thread while the
            # interpreter shuts down, aborts the process ("FATAL: exception not
            # rethrown"). Only there: a collection of a large process costs ~0.3 s.
            gc.collect()


def _one_line(message, category, filename, lineno, file=None, line=None) -> None:
    """A warning as the verbs print theirs (:func:`emccdcal.cli._common.print_warnings`):
    ``warning: ...`` on one escaped line, without the source line that raised it."""
    from .._output import comment

    print(f"warning: {comment(message)}", file=file or sys.stderr)


#: Verbs after which the command line collects garbage at once (they hold a C++ core).
_COLLECT_AFTER = frozenset({"acquire"})


def _main(argv):
    parser = build_parser(_verb_of(argv))
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, or a usage error already printed
        return exc.code if isinstance(exc.code, int) else 2
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        check_numbers(args)
        with given_inputs(paths_given(args)):
            return int(args.func(args) or 0)
    except EmccdcalError as exc:  # one line, whatever text of a file it quotes
        from .._output import comment

        print(f"emccdcal {args.verb}: error: {comment(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:  # a long run says what it kept and how to go on
        print(f"emccdcal {args.verb}: {str(exc) or 'interrupted'}", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader went away (| head): end quietly
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
