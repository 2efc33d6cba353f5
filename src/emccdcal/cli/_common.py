"""Options and steps shared by the verbs, declared once so that every verb spells them alike.

- ``-o/--out``: where a verb writes (a directory; ``report`` also takes an ``.html`` file);
- ``-q/--quiet``: no progress bars, no summary;
- ``--no-figures``: skip the figures a verb writes by default;
- ``--e-per-adu``: φ in e-/ADU overriding the manifest's;
- ``--overwrite``: replace an earlier output, once the new one is complete
  (:func:`output` opens every verb's output under the one policy of
  :mod:`emccdcal._output`);
- ``--accept-mismatch``: let frames differ from the calibration in an identity field.

Units in help texts are ASCII, as in the result files: e-, e-/ADU, ADU, px.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import warnings
from pathlib import Path

from .. import plugins
from ..defaults import DEFAULT_EM_MODEL

__all__ = [
    "add_out",
    "add_overwrite",
    "add_accept_mismatch",
    "output",
    "add_out_or_dir",
    "output_of",
    "add_quiet",
    "add_no_figures",
    "add_e_per_adu",
    "positive_float",
    "positive_int",
    "number_list",
    "label_list",
    "pixel",
    "recording_warnings",
    "print_warnings",
    "add_calibration_source",
    "calibration_of",
]


def add_out(
    p: argparse.ArgumentParser,
    what: str = "output directory",
    required: bool = True,
    overwrite: bool = True,
):
    p.add_argument("-o", "--out", type=Path, required=required, metavar="OUT", help=what)
    if overwrite:
        add_overwrite(p)


def add_overwrite(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an earlier output of the same names (only once the new one is complete)",
    )


def add_accept_mismatch(p: argparse.ArgumentParser) -> None:
    from ..identity import ACCEPTABLE

    p.add_argument(
        "--accept-mismatch",
        action="append",
        default=[],
        metavar="FIELD",
        choices=ACCEPTABLE,
        help="let the files differ from the calibration in FIELD (repeatable; "
        f"one of {', '.join(ACCEPTABLE)}): by default a calibration is "
        "used only on frames of the camera, read-out state and set-point it "
        "calibrated",
    )


def output(args, path, *, kind: str = "folder", inputs=(), names=(), stage: bool = True):
    """The verb's output under the one output policy (:class:`emccdcal._output.Output`):
    checked before any computing, locked while the verb runs, its files published
    together when complete (``stage``); ``--overwrite`` from ``args``."""
    from .._output import Output

    return Output(
        path,
        kind=kind,
        inputs=inputs,
        names=names,
        stage=stage,
        overwrite=bool(getattr(args, "overwrite", False)),
    )


def add_out_or_dir(
    p: argparse.ArgumentParser, what: str, required: bool = True, overwrite: bool = True
) -> None:
    """``OUT`` as a positional argument (the verb's original form) or as ``-o OUT``."""
    p.add_argument("dir", nargs="?", type=Path, metavar="OUT", help=f"{what} (or -o OUT)")
    p.add_argument("-o", "--out", type=Path, default=None, help=what)
    if overwrite:
        add_overwrite(p)
    p.set_defaults(_out_required=required)


def output_of(args) -> Path | None:
    """The output of a verb declared with :func:`add_out_or_dir` (one of its two forms)."""
    from ..errors import OptionError

    if args.dir is not None and args.out is not None and args.dir != args.out:
        raise OptionError(f"two outputs given: {args.dir} and -o {args.out}")
    out = args.out if args.out is not None else args.dir
    if out is None and args._out_required:
        raise OptionError("give the output directory: OUT or -o OUT")
    return out


def add_quiet(p: argparse.ArgumentParser) -> None:
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars, no summary")


def add_no_figures(p: argparse.ArgumentParser) -> None:
    p.add_argument("--no-figures", action="store_true", help="do not write the figures")


def add_e_per_adu(p: argparse.ArgumentParser) -> None:
    """``--e-per-adu``: a number, or an is-adu or mv-adu result, which comes with
    ``--accept-mismatch`` (a result is of one camera and read-out state); and
    ``--accept-phi``, for a φ the 1x acquisition contradicts."""
    p.add_argument(
        "--e-per-adu",
        type=number_or_path,
        default=None,
        metavar="PHI",
        help="ADU conversion factor phi, e-/ADU, overriding the manifest's: a "
        "number, or an is-adu or mv-adu result (its directory or calibration.nc), "
        "whose phi and standard error per pixel are then used",
    )
    p.add_argument(
        "--accept-phi",
        action="store_true",
        help="use the given phi even where the 1x acquisition's photon transfer "
        "contradicts it (by default such a phi, in ADU/e- say, is refused)",
    )
    add_accept_mismatch(p)


def plugin_choice(group: str, what: str) -> dict:
    """``add_argument`` keywords of an option naming a plug-in of ``group``: it accepts
    those that loaded and fit their interface (loaded when the option is given, so that
    ``--help`` imports none), refuses one that was left out with the reason, and lists
    the declared names in the help."""

    def parse(text: str) -> str:
        if text in plugins.names(group):
            return text
        why = plugins.left_out(group).get(text)
        if why is not None:
            raise argparse.ArgumentTypeError(f"{what} {text!r} was left out: {why}")
        choices = ", ".join(map(repr, plugins.names(group)))
        raise argparse.ArgumentTypeError(f"invalid choice: {text!r} (choose from {choices})")

    parse.__name__ = what  # argparse names the type in its messages
    return {"type": parse, "metavar": "{" + ",".join(plugins.declared(group)) + "}"}


def add_em_model(p: argparse.ArgumentParser, *, auto: bool = True) -> None:
    g = p.add_argument_group("EM register model", "the register in the likelihood: docs/cascade.md")
    g.add_argument(
        "--em-model",
        **plugin_choice(plugins.REGISTERS, "register model"),
        default=None,
        help="the register in the likelihood: the exact Bernoulli cascade or the "
        "paper's gamma approximation, which reproduces the paper's numbers "
        f"(default: the manifest's em_model, else {DEFAULT_EM_MODEL})",
    )
    g.add_argument(
        "--stages",
        type=stages_or_auto if auto else positive_int,
        default=None,
        metavar="N|auto" if auto else "N",
        help="stages of the cascade register (default: the manifest's "
        "register_stages, else the length known for the files' camera model, "
        "else 536; the gains hardly depend on it)"
        + ("; 'auto': the length of largest likelihood, 128 to 4096" if auto else ""),
    )


def add_device(p) -> None:
    """``--device``: where the likelihood is computed (docs/running.md, "On a GPU")."""
    from ..defaults import DEVICES

    p.add_argument(
        "--device",
        choices=DEVICES,
        default="cpu",
        help="where the likelihood is computed: the CPU, an NVIDIA GPU (needs the "
        "'gpu' extra: CuPy or PyTorch), JAX's first device (a GPU where JAX has one, "
        "else the CPU; needs the 'jax' extra), or array-api-strict (a check of the "
        "array API path, slower); default: %(default)s",
    )


def stages_or_auto(text: str):
    """An argparse type: a positive whole number of stages, or ``auto``."""
    return "auto" if text == "auto" else positive_int(text)


def number_or_path(text: str):
    """An argparse type: a positive number, or else a path (checked by the library)."""
    try:
        float(text)
    except ValueError:
        return Path(text)
    return positive_float(text)


def positive_float(text: str) -> float:
    """An argparse type: a number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive finite number, got {text!r}")
    return value


def _integer(text: str, minimum: int, what: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < minimum:
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """An argparse type: an integer ≥ 1."""
    return _integer(text, 1, "a positive integer")


def nonnegative_int(text: str) -> int:
    """An argparse type: an integer ≥ 0 (a seed)."""
    return _integer(text, 0, "0 or more")


def number_list(text: str) -> list[float]:
    """An argparse type: comma-separated numbers."""
    try:
        return [float(p.strip()) for p in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated numbers, got {text!r}"
        ) from None


def label_list(text: str) -> list[str]:
    """An argparse type: comma-separated labels."""
    return [p.strip() for p in text.split(",")]


def region(text: str) -> tuple[slice, slice]:
    """An argparse type: ``R0:R1,C0:C1``."""
    from .._util import parse_region
    from ..errors import OptionError

    try:
        return parse_region(text)
    except OptionError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def pixel(text: str) -> tuple[int, int]:
    """An argparse type: ``ROW,COL``."""
    from .._util import parse_pixel
    from ..errors import OptionError

    try:
        return parse_pixel(text)
    except OptionError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


@contextlib.contextmanager
def recording_warnings():
    """Record every warning issued inside the block (each shown by :func:`print_warnings`
    after the verb's own output, so that progress bars and summaries stay readable)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield caught


def print_warnings(caught) -> None:
    """Print recorded warnings, each once, as ``warning: ...`` on stderr."""
    from .._output import comment

    for message in dict.fromkeys(str(c.message) for c in caught):
        print(f"warning: {comment(message)}", file=sys.stderr)


def add_calibration_source(
    p: argparse.ArgumentParser, *, many: bool = False, option: bool = False
) -> None:
    """A calibration from result files (``RESULT``, or ``--calibration RESULT`` with
    ``option``) or from the calibration database (``--db``/``--camera``: its newest
    calibration with the set-point asked for)."""
    what = (
        "calibration.nc or its directory; several joined by commas merge (is-adu with "
        "is-gain results)" + ("; several RESULTs merge alike" if many else "")
    )
    if option:
        p.add_argument("--calibration", dest="results", metavar="RESULT", help=what)
    else:
        p.add_argument("results", nargs="*" if many else "?", metavar="RESULT", help=what)
    p.add_argument(
        "--gain-curve",
        type=Path,
        metavar="FILE",
        help="gain-curve.json (emccdcal gain-curve) of the same camera: the gain "
        "at a set-point the calibration did not measure",
    )
    g = p.add_argument_group("from the calibration database instead of RESULT")
    g.add_argument(
        "--camera",
        metavar="SERIAL",
        help="the camera's serial: use its newest calibration at the set-point "
        "(or, where none has it, the gain curve of its newest calibration)",
    )
    g.add_argument("--readout", metavar="TEXT", help="its read-out state, where it has several")
    g.add_argument(
        "--db",
        type=Path,
        metavar="PATH",
        help="database file (default: $EMCCDCAL_DB, else calibrations.sqlite in "
        "the user's data directory)",
    )
    add_accept_mismatch(p)


def calibration_of(args, setpoint):
    """The :class:`~emccdcal.result.Calibration` named by :func:`add_calibration_source`'s
    options, with the gain at ``setpoint`` from a gain curve where it was not measured."""
    from ..errors import OptionError
    from ..result import load_calibration

    results = (
        args.results
        if isinstance(args.results, list)
        else ([] if args.results is None else [args.results])
    )
    if args.camera is None:
        if not results:
            raise OptionError(
                "give a RESULT, or --camera SERIAL (with --setpoint) to use the "
                "calibration database"
            )
        cal = load_calibration(",".join(str(r) for r in results))
        if args.gain_curve is None or setpoint is None:
            return cal
        from ..export.gain_curve import calibration_at, read_gain_curve

        return calibration_at(
            cal,
            setpoint,
            read_gain_curve(args.gain_curve),
            source=str(args.gain_curve),
            accept_mismatch=args.accept_mismatch,
        )
    if results or args.gain_curve is not None:
        raise OptionError("give a RESULT (with --gain-curve) or --camera, not both")
    if setpoint is None:
        raise OptionError("--camera needs --setpoint G: the newest calibration at G is used")
    from ..export import database

    return database.calibration(args.camera, setpoint, db=args.db, readout=args.readout)
