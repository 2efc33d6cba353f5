"""The guarantees every verb gets from the house, each enumerated over the verbs.

1. Identity: every verb that uses a calibration on frames refuses frames of another
   camera, read-out state or set-point (:func:`emccdcal.identity.check`).
2. Inputs: no verb writes over, or inside a store among, a path it was given
   (:func:`emccdcal.cli.paths_given` registers them with every output it opens).
3. Bounds: every file a user hands in is read by one of :mod:`emccdcal._files`' loaders.
4. File text is data: what a file recorded cannot forge a line, drive the terminal, or be
   parsed as mathematics by a figure.
5. A database is read without being created or changed.

A new verb that takes a calibration, or writes, fails the enumerating tests until it is
given its probe here (or a reason it needs none).
"""

from __future__ import annotations

import ast
import os
import sqlite3
import time
from pathlib import Path

import numpy as np
import pytest
import tifffile
from camera_files import write_spe, write_zarr
from test_export import GAINS, OFFSET, PHI, SHAPE, SIGMA, true_result

from emccdcal import cli, result
from emccdcal.cli import _common
from emccdcal._output import file_sha256
from emccdcal.simulate.camera import simulate_frames

SRC = Path(cli.__file__).parents[1]


def _run(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _refused(code, err, *words):
    assert code == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for word in words:
        assert word in err, err


def _frames(setpoint, n=12, seed=1):
    return simulate_frames(
        np.full(SHAPE, 30.0),
        em_gain=GAINS[setpoint],
        e_per_adu=PHI,
        offset=OFFSET,
        read_noise=SIGMA,
        frames=n,
        seed=seed,
    )


def _parsers() -> dict:
    """Every verb's own parser."""
    out = {}
    for verb in cli.VERBS:
        root = cli.build_parser(verb)
        sub = next(a for a in root._actions if a.dest == "verb")
        out[verb] = sub.choices[verb]
    return out


def _dests(parser) -> set:
    found = set()
    for action in parser._actions:
        found.add(action.dest)
        for sub in getattr(action, "choices", None) or {}:
            if isinstance(action.choices, dict):
                found |= _dests(action.choices[sub])
    return found


@pytest.fixture(scope="module")
def camera_a(tmp_path_factory):
    """A calibration of camera CAM-A (10 MHz, 16 bits), and frames of camera CAM-B."""
    d = tmp_path_factory.mktemp("identity")
    cal = true_result(
        d / "cal", camera={"serial": "CAM-A", "readout_rate_mhz": 10.0, "adc_bits": 16}
    )
    ds = result.load(cal)  # the same calibration, as an is-adu result φ can come from
    ds.attrs["method"] = "is-adu"
    result.save(ds, d / "phi")
    files = {
        sp: write_spe(d / f"b{sp:g}.spe", _frames(sp), em_gain=sp, serial="CAM-B")
        for sp in (1.0, 100.0)
    }
    lines = []
    for sp, f in files.items():
        lines += [
            "[[acquisition]]",
            f'frames = "{f.name}"',
            f"em_gain_setpoint = {sp:g}",
            f"offset = {OFFSET}",
            f"read_noise = {SIGMA}",
        ]
    (d / "b.toml").write_text("\n".join(lines) + "\n")
    return {"cal": cal, "phi": d / "phi", "frames": files, "manifest": d / "b.toml", "dir": d}


# --------------------------------------------------------------------------------------
# 1. Identity wherever a calibration meets frames
# --------------------------------------------------------------------------------------
#: Each verb that takes a calibration and frames, with the command that gives it CAM-A's
#: calibration and CAM-B's frames.
IDENTITY_PROBES = {
    "apply": lambda c, o: ["apply", c["cal"], c["frames"][100.0], "-o", o / "e.tif"],
    "gain-check": lambda c, o: [
        "gain-check",
        c["frames"][100.0],
        "--calibration",
        c["cal"],
        "--setpoint",
        100,
    ],
    "validate": lambda c, o: ["validate", c["manifest"], "-c", c["cal"], "-o", o / "v"],
    "calibrate": lambda c, o: [
        "calibrate",
        c["manifest"],
        "--method",
        "gs",
        "--e-per-adu",
        c["phi"],
        "-o",
        o / "g",
    ],
}
#: Verbs that take a calibration but no frames to check it against, and why.
NO_FRAMES = {
    "export": "writes a calibration into a tool's file: no frames",
    "gain-curve": "fits the gains of calibrations (checked against each other): no frames",
    "report": "draws calibrations: no frames",
    "db": "stores and compares calibrations (one camera each): no frames",
    "plan": "takes a camera's numbers from a result to plan: no frames yet",
    "posterior": "takes phi as a number only: no calibration",
    "acquire": "--camera names a Micro-Manager device: no calibration",
    "simulate": "--camera names the simulated camera: no calibration",
    "audit": "a tool's settings file records no camera identity to check, only a name "
    "its user typed; the set-point is checked",
}
CALIBRATION_DESTS = {"results", "calibration", "e_per_adu", "camera"}


def test_every_verb_taking_a_calibration_is_probed_for_identity():
    takes = {v for v, p in _parsers().items() if _dests(p) & CALIBRATION_DESTS}
    unknown = takes - set(IDENTITY_PROBES) - set(NO_FRAMES)
    assert not unknown, (
        f"{sorted(unknown)} take a calibration: give each an identity "
        "probe (or a reason it meets no frames)"
    )
    assert set(IDENTITY_PROBES) <= takes


@pytest.mark.parametrize("verb", sorted(IDENTITY_PROBES))
def test_a_calibration_is_refused_on_another_cameras_frames(verb, camera_a, tmp_path, capsys):
    argv = IDENTITY_PROBES[verb](camera_a, tmp_path)
    code, _, err = _run(capsys, *argv)
    _refused(code, err, "camera serial 'CAM-B' (calibration: 'CAM-A')", "--accept-mismatch serial")
    assert not any(tmp_path.iterdir())  # refused before anything was written


def test_darks_pooled_are_of_one_setpoint_and_each_given_once(camera_a, tmp_path, capsys):
    d = camera_a["dir"]
    at300 = write_spe(tmp_path / "d300.spe", _frames(300.0), em_gain=300, serial="CAM-B")
    dark = camera_a["frames"][100.0]
    code, _, err = _run(capsys, "gain-check", dark, at300, "--e-per-adu", PHI, "--setpoint", 300)
    _refused(code, err, "set-point 300", "records 100")
    code, _, err = _run(capsys, "gain-check", dark, "--e-per-adu", PHI, "--setpoint", 300)
    _refused(code, err, "records EM-gain set-point 100, used at 300")
    code, _, err = _run(capsys, "gain-check", dark, d / dark.name, "--e-per-adu", PHI)
    _refused(code, err, "given twice")


def test_frames_that_record_no_identity_are_said(camera_a, tmp_path, capsys):
    plain = tmp_path / "plain.tif"
    tifffile.imwrite(plain, _frames(100.0))
    code, _, err = _run(
        capsys, "apply", camera_a["cal"], plain, "--setpoint", 100, "-o", tmp_path / "e.tif", "-q"
    )
    assert code == 0
    assert "could not check" in err and "the frames record none of it" in err, err


def test_a_cots_result_records_the_camera(tmp_path):
    from test_cots import _write_beads

    manifest = _write_beads(tmp_path / "beads", setpoints=(1, 300), frames=40)
    text = manifest.read_text()
    for tif in sorted(manifest.parent.glob("*.tif")):
        sp = float(tif.stem.split("_")[1].rstrip("x"))
        write_spe(tif.with_suffix(".spe"), tifffile.imread(tif), em_gain=sp, serial="CAM-C")
        text = text.replace(f'"{tif.name}"', f'"{tif.stem}.spe"')
    manifest.write_text(text)
    assert cli.main(["cots", str(manifest), "-o", str(tmp_path / "out"), "-q"]) == 0
    assert result.camera_of(result.load(tmp_path / "out"), "out")["serial"] == "CAM-C"


# --------------------------------------------------------------------------------------
# 2. No verb writes over (or inside a store among) what it was given
# --------------------------------------------------------------------------------------
def test_every_path_a_verb_is_given_is_registered_as_an_input():
    """Built from the parsers: for every verb, every argument that takes a path (or a
    calibration) is among :func:`cli.paths_given`, except the output itself."""
    import argparse

    for verb, parser in _parsers().items():
        values, expected = {}, set()
        for action in parser._actions:
            if action.dest == "help":
                continue
            if action.dest in cli.OUTPUT_DESTS:
                values.setdefault(action.dest, Path(f"{verb}-out"))
                continue
            kind = action.type
            if (
                kind is Path
                or getattr(kind, "__name__", "") == "number_or_path"
                or action.dest in ("results", "calibration")
            ):
                value = Path(f"{verb}-{action.dest}")
                expected.add(value)
                values[action.dest] = [value] if action.nargs in ("+", "*") else value
            else:
                values[action.dest] = action.default
        got = set(cli.paths_given(argparse.Namespace(**values)))
        assert expected <= got, (verb, expected - got)
        assert Path(f"{verb}-out") not in got


def _db(path):
    from emccdcal.export import _sqlite

    _sqlite._connect(path, write=True).close()
    return path


#: Each verb asked to write over (or inside) one of its inputs, with the input that must
#: come out unchanged.
OVERWRITE_PROBES = {
    "plan": lambda c, t: (
        ["plan", "--check", c["plan"], "-o", c["plan"], "--overwrite"],
        c["plan"],
    ),
    "report": lambda c, t: (
        ["report", c["cal"], "--db", c["db"], "-o", c["db"], "--overwrite"],
        c["db"],
    ),  # a database named db.html
    "apply": lambda c, t: (
        ["apply", c["cal"], c["movie"], "--setpoint", 100, "-o", c["movie"], "--overwrite"],
        c["movie"],
    ),
    "gain-check": lambda c, t: (
        [
            "gain-check",
            c["store"],
            "--e-per-adu",
            PHI,
            "--setpoint",
            100,
            "-o",
            c["store"] / "check",
        ],
        c["store"] / ".zattrs",
    ),
    "calibrate": lambda c, t: (
        [
            "calibrate",
            c["manifest"],
            "--method",
            "gs",
            "--e-per-adu",
            c["plain_phi"],
            "-o",
            c["plain_phi"],
            "--overwrite",
        ],
        c["plain_phi"] / result.CALIBRATION_FILE,
    ),
    "validate": lambda c, t: (
        ["validate", c["manifest"], "-c", c["named"], "-o", c["named"].parent, "--overwrite"],
        c["named"],
    ),
    "gain-curve": lambda c, t: (
        ["gain-curve", c["curve"], "-o", c["curve"].parent, "--overwrite"],
        c["curve"],
    ),
}


@pytest.fixture()
def inputs(camera_a, tmp_path):
    plan = tmp_path / "plan.toml"
    assert cli.main(
        [
            "plan",
            "--e-per-adu",
            "3.9",
            "--read-noise",
            "15",
            "--offset",
            "600",
            "-o",
            str(plan),
            "-q",
        ]
    ) in (0, 1)
    plan.write_text(plan.read_text() + "# my notes\n")
    movie = tmp_path / "movie.tif"
    tifffile.imwrite(movie, _frames(100.0))
    store = write_zarr(tmp_path / "darks.zarr", _frames(100.0), em_gain=100)
    plain = true_result(tmp_path / "plain").parent  # results of no camera: nothing to refuse
    ds = result.load(plain)
    ds.attrs["method"] = "is-adu"
    result.save(ds, tmp_path / "plain-phi")
    curve = tmp_path / "curve" / "gain-curve.json"  # a result named as gain-curve's output
    curve.parent.mkdir()
    true_result(tmp_path / "c").rename(curve)
    named = tmp_path / "v" / "validation.json"  # a result named as validate's output
    named.parent.mkdir()
    true_result(tmp_path / "w").rename(named)
    return {
        "named": named,
        **camera_a,
        "plan": plan,
        "db": _db(tmp_path / "db.html"),
        "movie": movie,
        "store": store,
        "plain": plain,
        "plain_phi": tmp_path / "plain-phi",
        "curve": curve,
    }


def test_every_writing_verb_is_probed(tmp_path):
    writes = {v for v, p in _parsers().items() if _dests(p) & set(cli.OUTPUT_DESTS)}
    elsewhere = {
        "demo": "writes only what it simulates, into a new folder",
        "simulate": "reads nothing",
        "acquire": "its plan and configuration are inputs (tests/test_acquire.py)",
        "posterior": "its manifest is an input like calibrate's",
        "scan": "writes a manifest beside the files it lists (tests/test_scan.py)",
        "cots": "its manifest is an input like calibrate's",
        "export": "its calibration is an input like apply's",
        "db": "compare's figure; the database is opened read-only",
        "check": "its manifest is an input like calibrate's",
    }
    unknown = writes - set(OVERWRITE_PROBES) - set(elsewhere)
    assert not unknown, f"{sorted(unknown)} write: give each an overwrite probe"


@pytest.mark.parametrize("verb", sorted(OVERWRITE_PROBES))
def test_no_verb_writes_over_what_it_read(verb, inputs, tmp_path, capsys):
    argv, kept = OVERWRITE_PROBES[verb](inputs, tmp_path)
    before = file_sha256(kept) if kept.is_file() else None
    code, _, err = _run(capsys, *argv)
    _refused(code, err, "an input of this run")
    assert (file_sha256(kept) if kept.is_file() else None) == before


# --------------------------------------------------------------------------------------
# 3. Every file a user hands in is read within bounds
# --------------------------------------------------------------------------------------
#: Calls that parse a user's file, allowed only in emccdcal._files.
_PARSERS = {
    ("tomllib", "loads"),
    ("tomllib", "load"),
    ("yaml", "safe_load"),
    ("yaml", "load"),
    ("ET", "parse"),
    ("ET", "fromstring"),
    ("json", "load"),
}


def test_every_loader_of_a_user_file_is_bounded():
    """No module but emccdcal._files parses TOML, YAML or XML, or JSON read from a file;
    SciPy's loadmat is called only after _files.check_mat."""
    for path in SRC.rglob("*.py"):
        if path.name == "_files.py":
            continue
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if not isinstance(node, ast.Call) or not isinstance(node.func, ast.Attribute):
                continue
            owner = node.func.value
            name = owner.id if isinstance(owner, ast.Name) else None
            assert (name, node.func.attr) not in _PARSERS, (
                f"{path.relative_to(SRC)}:{node.lineno}: {name}.{node.func.attr}: read user "
                "files through emccdcal._files"
            )
            if (name, node.func.attr) == ("json", "loads") and node.args:
                inner = ast.unparse(node.args[0])
                assert "read_text" not in inner and "read_bytes" not in inner, (
                    f"{path.relative_to(SRC)}:{node.lineno}: JSON from a file: use _files.load_json"
                )
        text = path.read_text()
        if "loadmat(" in text:
            assert "check_mat(" in text, f"{path.relative_to(SRC)}: loadmat without check_mat"


BOMB = (
    "\n".join(
        ["a: &a [x, x, x, x, x, x, x, x, x]"]
        + [
            f"{chr(98 + i)}: &{chr(98 + i)} [" + ", ".join([f"*{chr(97 + i)}"] * 9) + "]"
            for i in range(9)
        ]
    )
    + "\n"
)


@pytest.mark.parametrize(
    "content, words",
    [
        (BOMB, "YAML aliases"),
        ("[" * 5000 + "]" * 5000, "nested"),
        ('{"Cameras": {"x": {"Sensitivity": ' + "9" * 400 + "}}}", "64 bits"),
        ('{"Cameras": {"x": {"Sensitivity": NaN}}}', "not a number JSON allows"),
    ],
)
def test_audit_refuses_hostile_settings_quickly(content, words, camera_a, tmp_path, capsys):
    f = tmp_path / "config.yaml"
    f.write_text(content)
    t0 = time.perf_counter()
    code, _, err = _run(capsys, "audit", f, "--calibration", camera_a["cal"], "--setpoint", 100)
    assert time.perf_counter() - t0 < 20  # a bound, not a timing: it hung for minutes
    _refused(code, err, words)


def test_a_mat_bomb_is_refused_before_it_inflates(camera_a, tmp_path, capsys):
    from scipy.io import savemat

    f = tmp_path / "cameras.mat"
    savemat(f, {"zeros": np.zeros((12000, 1000))}, do_compression=True)  # 96 MB inflated
    assert f.stat().st_size < 1_000_000
    code, _, err = _run(capsys, "audit", f, "--calibration", camera_a["cal"], "--setpoint", 100)
    _refused(code, err, "MiB once decompressed")


@pytest.mark.parametrize("verb", ["plan", "audit"])
def test_fifos_devices_and_folders_are_refused_before_opening(verb, camera_a, tmp_path, capsys):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    tail = [] if verb == "plan" else ["--calibration", camera_a["cal"], "--setpoint", 100]
    head = ["plan", "--check"] if verb == "plan" else ["audit"]
    for target, words in ((fifo, "FIFO"), (Path("/dev/zero"), "a device"), (tmp_path, "a folder")):
        code, _, err = _run(capsys, *head, target, *tail)
        _refused(code, err, words)


def test_a_plan_with_huge_or_deep_values_is_one_line(tmp_path, capsys):
    for text, words in (
        ("x = " + "9" * 5000 + "\n", "not a readable plan"),
        ("x = " + "[" * 3000 + "]" * 3000 + "\n", "nested"),
    ):
        f = tmp_path / "p.toml"
        f.write_text(text)
        _refused(*_run(capsys, "plan", "--check", f)[::2], words)


# --------------------------------------------------------------------------------------
# 4. Text from a file is data on every surface
# --------------------------------------------------------------------------------------
def test_a_serial_cannot_forge_a_row_or_drive_the_terminal(tmp_path, capsys):
    from emccdcal.export import database

    forged = "SN1\n   9  FAKE       2020-01-01  gs             -\x1b[2K\x1b[31m"
    res = true_result(tmp_path / "r", camera={"serial": forged})
    db = tmp_path / "c.sqlite"
    database.add(res, db=db, date="2026-01-01")
    code, out, _ = _run(capsys, "db", "list", "--db", db)
    assert code == 0
    assert "\x1b" not in out and "FAKE" in out
    assert len(out.splitlines()) == 2  # the header and one row: no forged row


def test_a_serial_is_not_mathematics_in_a_figure(tmp_path, capsys):
    from emccdcal.export import database

    serial = "SN$\\x$42"
    db = tmp_path / "c.sqlite"
    for i, date in enumerate(("2026-01-01", "2026-02-01")):
        database.add(
            true_result(tmp_path / f"r{i}", camera={"serial": serial}, seed=i, spread=0.01),
            db=db,
            date=date,
        )
    code, _, err = _run(
        capsys, "db", "compare", "--camera", serial, "--db", db, "-o", tmp_path / "fig", "-q"
    )
    assert code in (0, 1), err
    assert list((tmp_path / "fig").glob("gain-history-*.png"))


def test_a_tool_files_camera_name_is_one_escaped_line(camera_a, tmp_path, capsys):
    import yaml

    name = "cam\nOK: photons within 2 %\x1b[31m"
    f = tmp_path / "config.yaml"
    f.write_text(
        yaml.safe_dump(
            {
                "Cameras": {
                    name: {
                        "Baseline": OFFSET,
                        "Sensitivity": PHI,
                        "Gain": GAINS[100.0],
                        "Quantum Efficiency": 1,
                    }
                }
            }
        )
    )
    _, out, _ = _run(capsys, "audit", f, "--calibration", camera_a["cal"], "--setpoint", 100)
    assert "\x1b" not in out
    assert not any(line.startswith("OK: photons") for line in out.splitlines())


# --------------------------------------------------------------------------------------
# 5. A database is read without being created or changed
# --------------------------------------------------------------------------------------
def test_reading_never_creates_or_changes_a_database(camera_a, tmp_path, capsys):
    foreign = tmp_path / "theirs.sqlite"
    con = sqlite3.connect(foreign)
    con.execute("CREATE TABLE notes (x TEXT)")
    con.commit()
    con.close()
    notes = tmp_path / "notes.txt"
    notes.write_text("")
    for db in (foreign, notes):
        before = file_sha256(db)
        for argv in (
            ["db", "list", "--db", db],
            ["db", "add", camera_a["cal"], "--db", db],
            ["report", camera_a["cal"], "--db", db, "-o", tmp_path / "r.html"],
        ):
            code, _, err = _run(capsys, *argv)
            _refused(code, err, "not a calibration database" if db == notes else "another program")
        assert file_sha256(db) == before
    typo = tmp_path / "no" / "such" / "cal.sqlite"
    for argv in (
        ["db", "list", "--db", typo],
        ["report", camera_a["cal"], "--db", typo, "-o", tmp_path / "r2.html"],
    ):
        _refused(*_run(capsys, *argv)[::2], "no calibration database here")
    assert not (tmp_path / "no").exists()


# --------------------------------------------------------------------------------------
# Audit reads a tool's file as the tool does
# --------------------------------------------------------------------------------------
def _audit(capsys, camera_a, path):
    return _run(capsys, "audit", path, "--calibration", camera_a["cal"], "--setpoint", 100)


def test_audit_skips_commented_macro_lines(camera_a, tmp_path, capsys):
    macro = tmp_path / "camera.ijm"
    good = f'run("Camera setup", "offset={OFFSET} photons2adu={PHI} isemgain=true gainem=90.06");'
    macro.write_text(
        '// run("Camera setup", "offset=1 photons2adu=9 isemgain=false");\n'
        f"{good}\n/* {good.replace('90.06', '5')} */\n"
    )
    code, out, err = _audit(capsys, camera_a, macro)
    assert code == 0 and "photons2adu  4" in out.replace("4.0", "4"), out + err
    macro.write_text(good + "\n" + good.replace("90.06", "300") + "\n")
    _refused(*_audit(capsys, camera_a, macro)[::2], "2 different Camera setup lines")


def test_audit_never_takes_an_expression_for_a_number(camera_a, tmp_path, capsys):
    md = tmp_path / "meta.md"
    md.write_text(f"md['Camera.ElectronsPerCount'] = {PHI}*10\nmd['Camera.TrueEMGain'] = 90\n")
    _refused(*_audit(capsys, camera_a, md)[::2], "an expression, never evaluated")


@pytest.mark.parametrize("qe", ["NaN", "-0.9", "90", "true"])
def test_audit_refuses_a_quantum_efficiency_outside_0_1(qe, camera_a, tmp_path, capsys):
    f = tmp_path / "config.yaml"
    f.write_text(
        f"Cameras:\n  cam:\n    Baseline: {OFFSET}\n    Sensitivity: {PHI}\n"
        f"    Gain: 90.06\n    Quantum Efficiency: {qe}\n"
    )
    _refused(*_audit(capsys, camera_a, f)[::2], "Quantum Efficiency")


# --------------------------------------------------------------------------------------
# Numbers are checked for range before any work
# --------------------------------------------------------------------------------------
PLAN = ["plan", "--e-per-adu", "3.9", "--read-noise", "15", "--offset", "600", "-q"]


@pytest.mark.parametrize(
    "change, words",
    [
        (("--e-per-adu", "1e-300"), "--e-per-adu 1e-300 is outside"),
        (("--read-noise", "1e-300"), "--read-noise 1e-300 is outside"),
        (("--stages", "100000000"), "--stages 1e+08 is outside"),
        (("--target-se", "1e-9"), "--target-se 1e-09 is outside"),
        (("--offset", "1e302"), "--offset 1e+302 is outside"),  # was "negative"
    ],
)
def test_a_number_out_of_range_is_refused_before_any_work(change, words, capsys):
    argv = list(PLAN)
    if change[0] in argv:
        argv[argv.index(change[0]) + 1] = change[1]
    else:
        argv += list(change)
    t0 = time.perf_counter()
    _refused(*_run(capsys, *argv)[::2], words)
    assert time.perf_counter() - t0 < 20  # it ran past 120 s


_NUMERIC_TYPES = {
    float,
    int,
    _common.positive_float,
    _common.positive_int,
    _common.nonnegative_int,
    _common.number_list,
    _common.number_or_path,
    _common.stages_or_auto,
}


def _numeric_options():
    """(verb, option, dest) of every numeric option of every verb (sub-verbs included)."""
    found = []

    def walk(parser, verb):
        for action in parser._actions:
            if isinstance(action.choices, dict):
                for name, sub in action.choices.items():
                    walk(sub, f"{verb} {name}")
            elif action.type in _NUMERIC_TYPES and action.option_strings:
                found.append((verb, action.option_strings[-1], action.dest))

    for verb, parser in _parsers().items():
        walk(parser, verb)
    return found


def test_every_numeric_option_has_a_range():
    """A new numeric option without a range fails here: name its quantity in
    defaults.BOUNDS or defaults.OPTION_QUANTITY."""
    from emccdcal.defaults import BOUNDS, OPTION_QUANTITY

    options = _numeric_options()
    assert len(options) > 100
    unbounded = [o for o in options if OPTION_QUANTITY.get(o[2], o[2]) not in BOUNDS]
    assert not unbounded, unbounded
    assert set(OPTION_QUANTITY.values()) <= set(BOUNDS)


@pytest.mark.parametrize("huge", [1e302, -1e302, float("nan")])
def test_every_numeric_option_refuses_a_number_out_of_its_range(huge):
    """The one check every verb goes through (cli.check_numbers), on each numeric option."""
    import argparse

    from emccdcal.defaults import BOUNDS, OPTION_QUANTITY
    from emccdcal.errors import OptionError

    for verb, option, dest in _numeric_options():
        low = BOUNDS[OPTION_QUANTITY.get(dest, dest)][0]
        cli.check_numbers(argparse.Namespace(**{dest: low}))  # its lowest is taken
        for value in (huge, [low, huge]):
            with pytest.raises(OptionError, match=rf"^{option} (nan|-?1e\+302) is outside"):
                cli.check_numbers(argparse.Namespace(**{dest: value}))


def test_a_bead_width_out_of_range_is_refused(tmp_path, capsys):
    from test_cots import _write_beads

    manifest = _write_beads(tmp_path / "beads", setpoints=(1, 300), frames=40)
    _refused(
        *_run(capsys, "cots", manifest, "-o", tmp_path / "o", "--width", "1e300")[::2],
        "--width 1e+300 is outside",
    )


# --------------------------------------------------------------------------------------
# A full disk is one line, and loses nothing already written
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("verb", ["report", "gain-check"])
def test_a_full_disk_is_one_line_and_loses_nothing(verb, camera_a, tmp_path, capsys, monkeypatch):
    import errno

    import emccdcal._output.files as output

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("earlier")
    monkeypatch.setattr(output.os, "fsync", full)  # the disk fills as the file is flushed
    darks = tmp_path / "darks.tif"
    if verb == "gain-check":  # clock-induced charge only, at 100x
        tifffile.imwrite(
            darks,
            simulate_frames(
                np.full(SHAPE, 0.05),
                em_gain=GAINS[100.0],
                e_per_adu=PHI,
                offset=OFFSET,
                read_noise=SIGMA,
                frames=1500,
                seed=2,
            ),
        )
    argv = (
        ["report", camera_a["cal"], "-o", out / "r.html"]
        if verb == "report"
        else ["gain-check", darks, "--e-per-adu", PHI, "--setpoint", 100, "-o", out, "-q"]
    )
    code, _, err = _run(capsys, *argv)
    _refused(code, err, "No space left on device")
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]


def test_zarr_settings_of_the_wrong_type_are_one_line(tmp_path):
    from emccdcal.data.stacks import stack_settings
    from emccdcal.errors import InputError

    for key, value in (
        ("adc_bits", "16"),
        ("em_gain_setpoint", "abc"),
        ("roi", "abcd"),
        ("binning", [2]),
        ("binning", [0, 0]),
        ("binning", [-1, 2]),
    ):
        store = write_zarr(
            tmp_path / f"{key}{len(str(value))}.zarr", _frames(100.0), **{key: value}
        )
        with pytest.raises(InputError, match=f"camera setting {key}"):
            stack_settings(store)


def test_an_offset_past_the_adc_is_named(capsys):
    """An offset of 1e302 ADU once read as 'leave out the highest set-point' (the option's
    range refuses that one now; an offset within it but past a 16-bit ADC is named)."""
    argv = [a if a != "600" else "70000" for a in PLAN]
    _refused(*_run(capsys, *argv)[::2], "offset 70000 ADU is at or past the ADC's last count")


def test_gain_check_given_a_map_names_the_file(tmp_path, capsys):
    """An offset map given as darks once said 'dark stack must be 3-D' without the file."""
    path = tmp_path / "300x-gain_no-signal_S0.tif"
    tifffile.imwrite(path, np.full((3, 3), 600.0, dtype=np.float32))
    _refused(
        *_run(capsys, "gain-check", path, "--e-per-adu", "3.8", "--setpoint", "300")[::2],
        str(path),
        "not a 3-D",
    )
