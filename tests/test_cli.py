"""The command line as a layer: fast help, one-line errors, tracebacks for bugs, Ctrl-C,
any locale, options spelled alike across verbs."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from emccdcal import cli
from emccdcal.errors import InputError, OptionError

HEAVY = ("numpy", "scipy", "xarray", "matplotlib", "tifffile", "pandas")


def _imported_after(argv):
    code = (
        f"import sys; from emccdcal.cli import main; main({argv!r}); "
        f"print(sorted({{m.split('.')[0] for m in sys.modules}} & set({HEAVY!r})))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return out.stdout.strip().splitlines()[-1]


@pytest.mark.parametrize("argv", [["--help"], ["--version"], []])
def test_help_and_version_import_no_numerics(argv):
    assert _imported_after(argv) == "[]"


def test_every_verbs_help_imports_no_numerics():
    """Choices and defaults come from emccdcal.defaults: `VERB --help` answers at once
    (calibrate --help took 3 s when it imported the engine and xarray)."""
    code = (
        "import sys; from emccdcal.cli import main, VERBS\n"
        "for verb in VERBS:\n"
        "    try:\n        main([verb, '--help'])\n    except SystemExit:\n        pass\n"
        f"print(sorted({{m.split('.')[0] for m in sys.modules}} & set({HEAVY!r})))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-1] == "[]"


def test_a_calibration_does_not_import_scipy_stats(tmp_path):
    """scipy.stats took ~0.6 s of every command's cold start for three functions that
    scipy.special has (chi2.sf, chi2.ppf, norm.ppf): a calibration with its bounds, in a
    fresh interpreter, imports none of it."""
    from emccdcal.simulate.series import simulate_gain_series

    sim = simulate_gain_series(
        tmp_path / "gs", setpoints=(1, 50), rows=2, cols=2, frames=200, dark_frames=100, seed=3
    )
    argv = ["calibrate", str(sim.manifest), "-o", str(tmp_path / "out"), "-q"]
    argv += ["--intervals", "profile"]
    code = (
        "import sys, warnings; warnings.simplefilter('ignore')\n"
        f"from emccdcal.cli import main; code = main({argv!r})\n"
        "print(code, 'scipy.stats' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.stdout.split() == ["0", "False"], out.stdout + out.stderr


def test_help_lists_every_verb(capsys):
    assert cli.main(["--help"]) == 0
    out = capsys.readouterr().out
    for verb in cli.VERBS:
        assert verb in out


@pytest.mark.parametrize("verb", list(cli.VERBS))
def test_every_verb_help_prints_under_a_cp1252_console(verb):
    env = dict(os.environ, PYTHONIOENCODING="cp1252")
    out = subprocess.run(
        [sys.executable, "-m", "emccdcal", verb, "--help"], env=env, capture_output=True
    )
    assert out.returncode == 0, out.stderr.decode("cp1252", "replace")
    assert b"usage: emccdcal " + verb.encode() in out.stdout


def _verb_raising(monkeypatch, exc):
    def run(args):
        raise exc

    import emccdcal.cli.check as check

    real = check.add_parser

    def add_parser(subparsers):
        p = real(subparsers)
        p.set_defaults(func=run)
        return p

    monkeypatch.setattr(check, "add_parser", add_parser)


@pytest.mark.parametrize("exc", [InputError("'x.tif': truncated"), OptionError("bad option")])
def test_user_errors_are_one_line_and_exit_2(monkeypatch, capsys, exc):
    _verb_raising(monkeypatch, exc)
    assert cli.main(["check", "m.toml"]) == 2
    err = capsys.readouterr().err
    assert err == f"emccdcal check: error: {exc}\n"


def test_a_bug_keeps_its_traceback(monkeypatch):
    _verb_raising(monkeypatch, ValueError("a NumPy bug"))
    with pytest.raises(ValueError, match="a NumPy bug"):
        cli.main(["check", "m.toml"])


def test_ctrl_c_is_one_line_and_exit_130(monkeypatch, capsys):
    _verb_raising(monkeypatch, KeyboardInterrupt())
    assert cli.main(["check", "m.toml"]) == 130
    assert capsys.readouterr().err == "emccdcal check: interrupted\n"


def test_usage_errors_exit_2_in_one_line(capsys):
    assert cli.main(["calibrate", "m.toml", "-o", "out", "--e-per-adu", "-1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--e-per-adu" in err[0]
    assert cli.main(["no-such-verb"]) == 2


def test_options_are_spelled_alike_across_verbs():
    parser_of = {}
    for verb in cli.VERBS:
        sub = cli.build_parser(verb)._subparsers._group_actions[0].choices[verb]
        parser_of[verb] = {s for a in sub._actions for s in a.option_strings}
    writes = {
        "demo",
        "simulate",
        "calibrate",
        "posterior",
        "report",
        "validate",
        "cots",
        "export",
        "apply",
        "gain-curve",
        "gain-check",
    }
    for verb in writes - {"simulate"}:
        assert {"-o", "--out"} <= parser_of[verb], verb
    for verb in cli.VERBS:
        assert {"-q", "--quiet"} <= parser_of[verb] or verb == "simulate", verb
    figures = {verb for verb, opts in parser_of.items() if "--no-figures" in opts}
    assert figures == {"posterior", "validate", "gain-curve", "gain-check"}
    for verb in ("calibrate", "posterior"):
        assert "--e-per-adu" in parser_of[verb]


def test_simulate_kinds_take_out_and_quiet():
    parser = cli.build_parser("simulate")
    sim = parser._subparsers._group_actions[0].choices["simulate"]
    for kind, sub in sim._subparsers._group_actions[0].choices.items():
        options = {s for a in sub._actions for s in a.option_strings}
        assert {"-o", "--out", "-q", "--quiet"} <= options, kind


@pytest.mark.slow
def test_simulate_takes_its_output_as_a_word_or_with_o(tmp_path, capsys):
    opts = [
        "--rows",
        "2",
        "--cols",
        "2",
        "--frames",
        "10",
        "--setpoints",
        "1,5",
        "--seed",
        "1",
        "-q",
    ]
    assert cli.main(["simulate", "gain-series", str(tmp_path / "a"), *opts]) == 0
    assert cli.main(["simulate", "gain-series", "-o", str(tmp_path / "b"), *opts]) == 0
    for name in ("gain-GS/5x-gain.tif", "truth.json"):
        a, b = (tmp_path / d / name for d in "ab")
        if name.endswith(".tif"):
            assert a.read_bytes() == b.read_bytes()
    capsys.readouterr()
    assert cli.main(["simulate", "gain-series", *opts]) == 2
    assert "OUT or -o OUT" in capsys.readouterr().err
    assert (
        cli.main(["simulate", "gain-series", str(tmp_path / "c"), "-o", str(tmp_path / "d"), *opts])
        == 2
    )


def _all_parsers(parser):
    """A parser and every sub-parser under it (verbs, then actions such as db's)."""
    import argparse

    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in dict.fromkeys(action.choices.values()):
                yield from _all_parsers(sub)


@pytest.mark.parametrize("verb", list(cli.VERBS))
def test_help_texts_read_as_written(verb):
    """No literal '%%' (argparse formats help strings, not descriptions), no list shown
    as a Python list, no positional argument without a help text."""
    root = cli.build_parser(verb)
    for parser in _all_parsers(root):
        if parser is root:
            continue
        text = parser.format_help()
        assert "%%" not in text, parser.prog
        assert "(default [" not in text, parser.prog
        for action in parser._actions:
            if not action.option_strings and action.dest not in ("help",) and not action.choices:
                assert action.help, f"{parser.prog}: {action.dest} has no help"


def test_validate_and_cots_expect_the_same_spot_width():
    """One default for the PSF's expected width (px), whichever verb fits the beads."""
    from emccdcal.model.psf import DEFAULT_WIDTH

    argv = {
        "validate": ["validate", "m.toml", "--calibration", "c.nc", "-o", "o"],
        "cots": ["cots", "m.toml", "-o", "o"],
    }
    widths = {verb: cli.build_parser(verb).parse_args(args).width for verb, args in argv.items()}
    assert widths == {"validate": DEFAULT_WIDTH, "cots": DEFAULT_WIDTH}


def test_a_closed_pipe_ends_quietly(tmp_path):
    """`emccdcal db list --json | head` once printed a BrokenPipeError traceback."""
    from emccdcal.export import _sqlite

    _sqlite._connect(tmp_path / "cal.sqlite", write=True).close()  # an empty database
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "emccdcal",
            "db",
            "list",
            "--json",
            "--db",
            str(tmp_path / "cal.sqlite"),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    proc.stdout.close()  # the reader goes away before the first line
    err = proc.stderr.read().decode()
    assert proc.wait(60) == 0 and "Traceback" not in err and "BrokenPipe" not in err, err
