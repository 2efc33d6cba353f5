"""Command-line interface: ``emccdcal VERB ...``.

Each verb lives in the module of its topic, which exposes ``add_parser(subparsers)``;
the parser it adds sets ``func`` (called with the parsed namespace, returns an exit
code). This file only assembles them, so that modules can be worked on independently.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from . import __version__

# Modules that contribute verbs, in the order they appear in ``--help``.
_VERB_MODULES = ("demo", "simulate", "calibrate", "posterior", "quality", "report", "validation", "cots")


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line and exit code 2."""

    def error(self, message: str) -> None:  # noqa: D401 - argparse API
        self.exit(2, f"{self.prog}: error: {message}\n")


class UsageError(Exception):
    """Bad user input found after argument parsing: printed as one line, exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="emccdcal",
        description="Calibrate EMCCD cameras: the ADU conversion factor (e-/ADU) and the true "
        "EM gain at every set-point, per pixel, with standard errors.",
    )
    parser.add_argument("--version", action="version", version=f"emccdcal {__version__}")
    subparsers = parser.add_subparsers(dest="verb", metavar="VERB", parser_class=_Parser)
    for name in _VERB_MODULES:
        module = importlib.import_module(f"emccdcal.{name}")
        module.add_parser(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except (UsageError, ValueError, FileNotFoundError) as exc:
        print(f"emccdcal {args.verb}: error: {exc}", file=sys.stderr)
        return 2
