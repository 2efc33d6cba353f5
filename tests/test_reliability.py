"""Nothing lost, nothing injected: each case an audit of the writing verbs found, replayed.

Every test here failed on the code before the one output policy (emccdcal._output) and
the results' checksums; docs/reliability.md lists the cases and the threat model.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tifffile
from camera_files import write_spe
from test_export import OFFSET, PHI, SHAPE, SIGMA, true_result

from emccdcal import cli, result
from emccdcal._output import (
    STORE_MARKER,
    Output,
    OutputError,
    atomic_write_text,
    comment,
    file_sha256,
    slug,
    toml_line,
)
from emccdcal.data.dark import maps_from_dark
from emccdcal.errors import InputError
from emccdcal.export import database
from emccdcal.simulate.camera import simulate_frames


def _movie(path, frames=40, seed=1, g=90.06):
    stack = simulate_frames(
        np.full(SHAPE, 30.0),
        em_gain=g,
        e_per_adu=PHI,
        offset=OFFSET,
        read_noise=SIGMA,
        frames=frames,
        seed=seed,
    )
    tifffile.imwrite(path, stack)
    return path


def _run(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _one_line_error(code, err):
    assert code == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err, err


def _resave(ds, path):
    """A result changed by hand and saved properly (its checksum then matches)."""
    result.save(ds, path)
    return path / result.CALIBRATION_FILE


# --------------------------------------------------------------------------------------
# 1. apply never destroys data
# --------------------------------------------------------------------------------------
def test_apply_never_writes_over_its_movie_or_a_foreign_folder(tmp_path, capsys):
    res = true_result(tmp_path / "r")
    movie = _movie(tmp_path / "movie100.tif")
    before = file_sha256(movie)
    for extra in ([], ["--overwrite"]):
        code, _, err = _run(capsys, "apply", res, movie, "--setpoint", 100, "-o", movie, *extra)
        _one_line_error(code, err)
        assert "an input of this run" in err
    assert file_sha256(movie) == before
    keep = tmp_path / "keep.zarr"
    (keep / "sub").mkdir(parents=True)
    (keep / "sub" / "notes.txt").write_text("x")
    for extra in ([], ["--overwrite"]):
        code, _, err = _run(capsys, "apply", res, movie, "--setpoint", 100, "-o", keep, *extra)
        _one_line_error(code, err)
    assert (keep / "sub" / "notes.txt").read_text() == "x"


def test_apply_replaces_its_own_output_only_when_asked(tmp_path, capsys):
    pytest.importorskip("zarr")
    res = true_result(tmp_path / "r")
    movie = _movie(tmp_path / "m.tif")
    for out in (tmp_path / "e.tif", tmp_path / "e.zarr"):
        assert _run(capsys, "apply", res, movie, "--setpoint", 100, "-o", out, "-q")[0] == 0
        code, _, err = _run(capsys, "apply", res, movie, "--setpoint", 100, "-o", out)
        _one_line_error(code, err)
        assert "--overwrite" in err
        assert (
            _run(capsys, "apply", res, movie, "--setpoint", 100, "-o", out, "-q", "--overwrite")[0]
            == 0
        )
    # a store it wrote, with a foreign file put inside, is no longer its to remove
    (tmp_path / "e.zarr" / "mine.txt").write_text("keep")
    code, _, err = _run(
        capsys, "apply", res, movie, "--setpoint", 100, "-o", tmp_path / "e.zarr", "--overwrite"
    )
    _one_line_error(code, err)
    assert (tmp_path / "e.zarr" / "mine.txt").read_text() == "keep"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_a_killed_runs_temporary_files_are_removed_by_the_next(tmp_path, capsys):
    res = true_result(tmp_path / "r")
    movie = _movie(tmp_path / "m.tif")
    left = tmp_path / ".e.tif.0123456789ab.tmp.tif"
    left.write_bytes(b"half")
    foreign = tmp_path / ".e.tif.notes"
    foreign.write_text("mine")
    assert (
        _run(capsys, "apply", res, movie, "--setpoint", 100, "-o", tmp_path / "e.tif", "-q")[0] == 0
    )
    assert not left.exists() and foreign.read_text() == "mine"


# --------------------------------------------------------------------------------------
# 2, 3. Names and settings from files are data
# --------------------------------------------------------------------------------------
def test_a_serial_is_never_a_path(tmp_path, capsys):
    db = tmp_path / "cal.sqlite"
    for i, days in enumerate((1, 40)):
        database.add(
            true_result(tmp_path / f"r{i}", seed=i, spread=0.001),
            db=db,
            camera="../../../ESC",
            date=f"2026-0{i + 1}-{days % 28 + 1:02d}",
        )
    figs = tmp_path / "lab" / "figs"
    code, _, err = _run(capsys, "db", "--db", db, "compare", "--camera", "../../../ESC", "-o", figs)
    assert code in (0, 1), err
    written = [p for p in tmp_path.rglob("*.png")]
    assert written and all(p.parent == figs for p in written), written
    assert slug("../../../ESC") != slug("ESC") and "/" not in slug("a/b") and slug("x") == "x"


def test_a_setting_with_a_newline_stays_a_comment(tmp_path, capsys):
    folder = tmp_path / "session"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for name, g in (("1x-gain", 1), ("1x-gain_dark", 1), ("5x-gain", 5), ("5x-gain_dark", 5)):
        write_spe(
            folder / f"{name}.spe",
            rng.integers(500, 600, (30, 4, 4), dtype=np.uint16),
            em_gain=g,
            analog_gain="High\nskip_frames = 290\n#",
            # as the file's XML holds it: the reader gets the quotes back
            serial="x&quot; \n[[acquisition]]\nframes = &quot;../../etc/passwd",
        )
    assert _run(capsys, "scan", folder, "-q")[0] == 0
    text = (folder / "manifest.toml").read_text()
    doc = tomllib.loads(text)
    assert set(doc) <= {"adc_bits", "acquisition"}
    assert len(doc["acquisition"]) == 2
    assert all("skip_frames" not in a for a in doc["acquisition"])
    assert all(Path(a["frames"]).parent == Path(".") for a in doc["acquisition"])
    assert all(
        not line.strip() or line.startswith(("#", "[[")) or " = " in line
        for line in text.splitlines()
    )


def test_toml_and_comment_writers_round_trip_any_text():
    for text in ('a"b', "a\nb = 1", "\\", "\x00\x1b\x7f", "é ü ∑ \u2028", "#x", "'''"):
        assert tomllib.loads(toml_line("k", text)) == {"k": text}
        line = "# " + comment(text)
        assert "\n" not in line and tomllib.loads(line + "\nk = 1") == {"k": 1}


# --------------------------------------------------------------------------------------
# 4. --overwrite keeps the old result until the new one is complete
# --------------------------------------------------------------------------------------
def test_overwrite_keeps_the_old_result_when_the_new_run_fails(tmp_path, monkeypatch):
    from emccdcal import calibrate, calibration
    from emccdcal.simulate.series import simulate_gain_series

    sim = simulate_gain_series(
        tmp_path / "gs", setpoints=(1, 5), rows=4, cols=4, frames=200, dark_frames=200, seed=3
    )
    out = tmp_path / "out"
    calibrate(sim.manifest, "gs", out=out, progress=False)
    before = file_sha256(out / result.CALIBRATION_FILE)

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(calibration.api, "_run_tiles", interrupted)
    with pytest.raises(KeyboardInterrupt):
        calibrate(sim.manifest, "gs", out=out, overwrite=True, progress=False)
    assert file_sha256(out / result.CALIBRATION_FILE) == before
    result.load(out)


# --------------------------------------------------------------------------------------
# 5. Identity before arithmetic
# --------------------------------------------------------------------------------------
def _camera_result(path, **camera):
    ds = result.load(true_result(path / "src"))
    ds.attrs["camera"] = json.dumps(
        {"serial": "A1", "readout_rate_mhz": 10.0, "analog_gain": "High", "adc_bits": 16, **camera}
    )
    ds.attrs["binning"] = np.array([1, 1])
    return _resave(ds, path / "cal")


def test_apply_refuses_another_camera_or_binning(tmp_path, capsys):
    res = _camera_result(tmp_path)
    frames = simulate_frames(
        np.full(SHAPE, 30.0),
        em_gain=90.06,
        e_per_adu=PHI,
        offset=OFFSET,
        read_noise=SIGMA,
        frames=10,
        seed=1,
    )
    binned = write_spe(tmp_path / "binned.spe", frames, em_gain=100, serial="A1", binning=(2, 2))
    code, _, err = _run(capsys, "apply", res, binned, "-o", tmp_path / "b.tif")
    _one_line_error(code, err)
    assert "binning 2x2 (calibration: 1x1)" in err
    other = write_spe(
        tmp_path / "other.spe",
        frames,
        em_gain=100,
        serial="B2",
        speed_mhz=1.0,
        analog_gain="Low",
        bit_depth=12,
    )
    code, _, err = _run(capsys, "apply", res, other, "-o", tmp_path / "o.tif")
    _one_line_error(code, err)
    for what in ("serial", "read-out rate", "analog", "ADC bits"):
        assert what in err
    same = write_spe(tmp_path / "same.spe", frames, em_gain=100, serial="A1")
    assert _run(capsys, "apply", res, same, "-o", tmp_path / "s.tif", "-q")[0] == 0
    args = [
        "--accept-mismatch",
        "serial",
        "--accept-mismatch",
        "readout_rate_mhz",
        "--accept-mismatch",
        "analog_gain",
        "--accept-mismatch",
        "adc_bits",
    ]
    assert _run(capsys, "apply", res, other, "-o", tmp_path / "o.tif", "-q", *args)[0] == 0


def test_gain_curve_refuses_two_cameras_and_a_result_given_twice(tmp_path, capsys):
    a = _camera_result(tmp_path / "a")
    b = _camera_result(tmp_path / "b", serial="B2")
    code, _, err = _run(capsys, "gain-curve", a, b, "-o", tmp_path / "c")
    _one_line_error(code, err)
    assert "camera serial" in err
    code, _, err = _run(capsys, "gain-curve", a, a.parent, "-o", tmp_path / "c")
    _one_line_error(code, err)
    assert "given twice" in err
    assert not (tmp_path / "c").exists()  # refused before anything was written


# --------------------------------------------------------------------------------------
# 6. Results know themselves
# --------------------------------------------------------------------------------------
def test_a_flipped_exponent_bit_is_found(tmp_path):
    res = true_result(tmp_path / "r")
    data = bytearray(res.read_bytes())
    needle = np.float64(90.06).tobytes()  # the gain at 100x
    at = data.find(needle)
    assert at > 0
    data[at + 7] ^= 0x04  # an exponent bit of the gain of one pixel at 100x
    res.write_bytes(bytes(data))
    with pytest.raises(InputError, match="damaged"):
        result.load(res)


@pytest.mark.parametrize(
    "name,value",
    [
        ("em_gain", -5.0),
        ("em_gain", np.inf),
        ("e_per_adu", 0.0),
        ("e_per_adu", -1.0),
        ("read_noise", 0.0),
    ],
)
def test_values_no_calibration_can_have_are_refused(tmp_path, name, value):
    ds = result.load(true_result(tmp_path / "r"))
    if name == "em_gain":
        ds[name].loc[{"setpoint": 100.0}] = np.where(np.arange(SHAPE[1]) == 3, value, 90.0)
    else:
        ds[name][..., 2, 3] = value
    path = _resave(ds, tmp_path / "bad")
    with pytest.raises(InputError, match=f"not a valid result: {name}"):
        result.load(path)


def test_apply_refuses_a_calibration_with_no_converged_pixel(tmp_path, capsys):
    ds = result.load(true_result(tmp_path / "r"))
    ds["converged"][:] = False
    path = _resave(ds, tmp_path / "none")
    code, _, err = _run(
        capsys,
        "apply",
        path,
        _movie(tmp_path / "m.tif"),
        "--setpoint",
        100,
        "-o",
        tmp_path / "e.tif",
    )
    _one_line_error(code, err)
    assert "converged" in err and not (tmp_path / "e.tif").exists()


def test_a_result_without_its_checksum_is_refused(tmp_path):
    ds = result.load(true_result(tmp_path / "r"))
    ds.to_netcdf(tmp_path / "plain.nc", engine="h5netcdf")  # another program's NetCDF
    with pytest.raises(InputError, match="not an emccdcal result file"):
        result.load(tmp_path / "plain.nc")


# --------------------------------------------------------------------------------------
# 7. A caller's array is never changed
# --------------------------------------------------------------------------------------
def test_dark_maps_leave_the_callers_array_alone():
    stack = np.random.default_rng(0).integers(100, 200, (50, 3, 4)).astype(np.float64)
    copy = stack.copy()
    maps_from_dark(stack)
    np.testing.assert_array_equal(stack, copy)


# --------------------------------------------------------------------------------------
# 8. One run at a time
# --------------------------------------------------------------------------------------
def test_a_second_run_into_a_locked_output_gets_one_line(tmp_path):
    res = true_result(tmp_path / "r")
    out = tmp_path / "exp"
    with Output(out, names=("picasso-config.yaml",)):
        run = subprocess.run(
            [
                sys.executable,
                "-m",
                "emccdcal",
                "export",
                str(res),
                "--to",
                "picasso",
                "--setpoint",
                "100",
                "-o",
                str(out),
            ],
            capture_output=True,
            text=True,
            timeout=120,
        )
    _one_line_error(run.returncode, run.stderr)
    assert "another emccdcal run is writing it" in run.stderr
    assert f"process {os.getpid()}" in run.stderr
    assert not list(out.iterdir())  # the lock went with the run


# --------------------------------------------------------------------------------------
# 9. One line, never a traceback
# --------------------------------------------------------------------------------------
def test_bad_outputs_and_inputs_are_one_line(tmp_path, capsys, monkeypatch):
    res = true_result(tmp_path / "r")
    movie = _movie(tmp_path / "m.tif")
    a_file = tmp_path / "a-file"
    a_file.write_text("")
    (tmp_path / "dir.tif").mkdir()
    loop = tmp_path / "loop.tif"
    loop.symlink_to(loop)
    empty = tmp_path / "empty.npy"
    np.save(empty, np.zeros((0, *SHAPE), dtype=np.uint16))
    cases = [
        ("apply", res, movie, "--setpoint", 100, "-o", tmp_path / "dir.tif"),
        ("apply", res, movie, "--setpoint", 100, "-o", a_file / "e.tif"),
        ("apply", res, loop, "--setpoint", 100, "-o", tmp_path / "e.tif"),
        ("apply", res, empty, "--setpoint", 100, "-o", tmp_path / "e.tif"),
        ("export", res, "--to", "json", "-o", a_file),
        ("gain-curve", res, "-o", a_file),
        ("report", res, "-o", a_file / "r.html"),
        ("scan", loop),
    ]
    for argv in cases:
        code, _, err = _run(capsys, *argv)
        _one_line_error(code, err)
    ds = result.load(res)
    ds.attrs["camera"] = "{not json"
    bad = _resave(ds, tmp_path / "badcam")
    for argv in (
        ("export", bad, "--to", "json", "-o", tmp_path / "x"),
        ("gain-curve", bad, "-o", tmp_path / "y"),
        ("db", "--db", tmp_path / "d.sqlite", "add", bad),
    ):
        code, _, err = _run(capsys, *argv)
        _one_line_error(code, err)
    monkeypatch.delenv("EMCCDCAL_DB", raising=False)
    monkeypatch.setenv("XDG_DATA_HOME", str(a_file / "data"))
    code, _, err = _run(capsys, "db", "add", res, "--camera", "S1")
    _one_line_error(code, err)
    assert "--db" in err


def test_a_damaged_header_is_one_line_without_a_leaked_traceback(tmp_path):
    res = true_result(tmp_path / "r")
    data = bytearray(res.read_bytes())
    data[0:8] = b"\x00" * 8  # the HDF5 signature
    res.write_bytes(bytes(data))
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "emccdcal",
            "export",
            str(res),
            "--to",
            "json",
            "-o",
            str(tmp_path / "x"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    _one_line_error(run.returncode, run.stderr)


# --------------------------------------------------------------------------------------
# 10. The smaller ones
# --------------------------------------------------------------------------------------
def test_scan_skips_a_pipe_instead_of_blocking(tmp_path, capsys):
    folder = tmp_path / "s"
    folder.mkdir()
    os.mkfifo(folder / "5x-gain.tif")
    run = subprocess.run(
        [sys.executable, "-m", "emccdcal", "scan", str(folder)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    _one_line_error(run.returncode, run.stderr)
    assert "no stack" in run.stderr


def test_paths_with_a_comma_dates_in_the_future_and_far_predictions(tmp_path, capsys):
    res = true_result(tmp_path / "a,b")
    assert _run(capsys, "export", res.parent, "--to", "json", "-o", tmp_path / "j", "-q")[0] == 0
    code, _, err = _run(
        capsys,
        "db",
        "add",
        res,
        "--db",
        tmp_path / "d.sqlite",
        "--camera",
        "S1",
        "--date",
        "9999-12-31",
    )
    _one_line_error(code, err)
    assert "future" in err
    code, _, err = _run(capsys, "gain-curve", res, "-o", tmp_path / "c", "--predict", "1e300")
    _one_line_error(code, err)


def test_apply_refuses_counts_no_camera_gives(tmp_path, capsys):
    res = true_result(tmp_path / "r")
    for bad in (np.nan, -3.0):
        stack = np.full((5, *SHAPE), 500.0, dtype=np.float32)
        stack[3, 1, 1] = bad
        movie = tmp_path / "f.tif"
        tifffile.imwrite(movie, stack)
        code, _, err = _run(
            capsys, "apply", res, movie, "--setpoint", 100, "-o", tmp_path / "e.tif"
        )
        _one_line_error(code, err)
        assert "frame 3" in err
    assert not (tmp_path / "e.tif").exists()


def test_db_options_after_the_action_remove_and_relocate(tmp_path, capsys):
    db = tmp_path / "d.sqlite"
    res = true_result(tmp_path / "r", camera={"serial": "S1"})
    assert _run(capsys, "db", "add", res, "--db", db, "-q")[0] == 0
    code, out, _ = _run(capsys, "db", "list", "--db", db, "--json")
    (entry,) = json.loads(out)
    moved = tmp_path / "moved"
    (tmp_path / "r").rename(moved)
    assert _run(capsys, "db", "relocate", entry["id"], moved, "--db", db, "-q")[0] == 0
    assert database.find("S1", 100, db=db).path == str((moved / "calibration.nc").resolve())
    code, _, err = _run(
        capsys, "db", "relocate", entry["id"], true_result(tmp_path / "o"), "--db", db
    )
    _one_line_error(code, err)
    assert _run(capsys, "db", "remove", entry["id"], "--db", db, "-q")[0] == 0
    assert database.entries(db=db) == [] and (moved / "calibration.nc").is_file()


def test_check_flags_constant_and_repeated_frames(tmp_path, capsys):
    from emccdcal.simulate.series import simulate_gain_series

    sim = simulate_gain_series(
        tmp_path / "gs", setpoints=(1, 5), rows=4, cols=4, frames=300, dark_frames=200, seed=3
    )
    frames_file = sim.outdir / sim.truth["acquisitions"][1]["frames"]
    stack = tifffile.imread(frames_file)
    stack[100:150] = 0
    stack[200] = stack[10]
    tifffile.imwrite(frames_file, stack)
    code, out, err = _run(capsys, "check", sim.manifest, "--strict")
    assert code == 1
    text = out + err
    assert "50 of 300 frames have every pixel at one value" in text
    assert "1 of 300 frames repeat an earlier frame" in text


def test_output_refusals_are_found_before_computing(tmp_path):
    (tmp_path / "f").write_text("")
    with pytest.raises(OutputError, match="is a file"):
        with Output(tmp_path / "f"):
            pass
    with pytest.raises(OutputError, match="an input"):
        with Output(tmp_path / "x.txt", kind="file", inputs=[tmp_path / "x.txt"]):
            pass
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]


def test_a_result_given_twice_is_refused_everywhere(tmp_path, capsys):
    res = true_result(tmp_path / "r")
    for argv in (
        ("report", res, res.parent, "-o", tmp_path / "rep.html"),
        ("export", f"{res},{res.parent}", "--to", "json", "-o", tmp_path / "x"),
        ("gain-curve", res, res, "-o", tmp_path / "c"),
    ):
        code, _, err = _run(capsys, *argv)
        _one_line_error(code, err)
        assert "twice" in err
    with pytest.raises(ValueError, match="twice"):
        from emccdcal.beads.validation import validate
        from emccdcal.simulate.beads import TRUTH_CALIBRATION_FILE, simulate_beads

        sim = simulate_beads(
            tmp_path / "beads",
            beads=2,
            rows=40,
            cols=40,
            frames=20,
            dark_frames=50,
            seed=1,
            setpoints=(1, 5),
        )
        truth = sim.outdir / TRUTH_CALIBRATION_FILE
        validate(sim.manifest, [truth, truth], progress=False)


def test_a_database_on_read_only_storage_can_be_listed(tmp_path, capsys, monkeypatch):
    db = tmp_path / "d.sqlite"
    database.add(true_result(tmp_path / "r"), db=db, camera="S1", date="2025-01-02")
    real = os.access
    monkeypatch.setattr(
        os, "access", lambda p, mode: False if mode == os.W_OK else real(p, mode)
    )  # as on read-only storage (root writes anyway)
    code, out, err = _run(capsys, "db", "list", "--db", db)
    assert code == 0 and "S1" in out, err
    code, _, err = _run(
        capsys, "db", "add", true_result(tmp_path / "r2", seed=3), "--db", db, "--camera", "S1"
    )
    _one_line_error(code, err)
    assert "cannot be written" in err and "read-only" in err


def test_demo_refuses_an_earlier_demo_unless_overwrite(tmp_path, capsys):
    argv = (
        "demo",
        "-o",
        tmp_path / "d",
        "--rows",
        4,
        "--cols",
        4,
        "--frames",
        300,
        "-q",
        "--no-report",
    )
    assert _run(capsys, *argv)[0] == 0
    code, _, err = _run(capsys, *argv)
    _one_line_error(code, err)
    assert _run(capsys, *argv, "--overwrite")[0] == 0
    result.load(tmp_path / "d" / "result-gs")


def test_float_frames_of_integer_counts_calibrate_and_bad_ones_are_named(tmp_path, capsys):
    from emccdcal.simulate.series import simulate_gain_series

    sim = simulate_gain_series(
        tmp_path / "gs", setpoints=(1, 5), rows=4, cols=4, frames=200, dark_frames=200, seed=3
    )
    frames_file = sim.outdir / sim.truth["acquisitions"][1]["frames"]
    stack = tifffile.imread(frames_file).astype(np.float64)
    tifffile.imwrite(frames_file, stack, photometric="minisblack")
    assert (
        _run(capsys, "calibrate", sim.manifest, "--method", "gs", "-o", tmp_path / "o", "-q")[0]
        == 0
    )  # checks on: float64 integer counts are counts
    stack[7, 1, 1] += 0.5
    tifffile.imwrite(frames_file, stack, photometric="minisblack")
    code, _, err = _run(
        capsys, "calibrate", sim.manifest, "--method", "gs", "-o", tmp_path / "o2", "--no-checks"
    )
    _one_line_error(code, err)
    assert frames_file.name in err and "not integer" in err


def test_a_result_emccdcal_makes_always_loads(tmp_path):
    ds = result.load(true_result(tmp_path / "r"))
    g = ds.em_gain.values.copy()
    g[2, 1, 1] = -5.0  # a fit gone wrong at one converged pixel
    with pytest.warns(UserWarning, match="1 pixel.*marked not converged"):
        made = result.make_dataset(
            method="gs",
            setpoints=ds.setpoint.values,
            e_per_adu=ds.e_per_adu.values,
            e_per_adu_se=ds.e_per_adu_se.values,
            em_gain=g,
            em_gain_se=ds.em_gain_se.values,
            photoelectrons=ds.photoelectrons.values,
            photoelectrons_se=ds.photoelectrons_se.values,
            converged=True,
            manifest_hash="0" * 64,
        )
    assert not made.converged.values[1, 1]
    assert int(made.converged.values.sum()) == made.converged.size - 1
    result.save(made, tmp_path / "made")
    assert not result.load(tmp_path / "made").converged.values[1, 1]


def test_saving_a_result_leaves_other_files_of_its_folder(tmp_path):
    res = true_result(tmp_path / "r")
    (tmp_path / "r" / "report.html").write_text("a report made by hand")
    result.save(result.load(res), tmp_path / "r")  # what cots and posterior do
    assert (tmp_path / "r" / "report.html").read_text() == "a report made by hand"


def test_a_store_that_gains_a_foreign_file_during_the_run_is_kept(tmp_path):
    store = tmp_path / "s.zarr"
    with Output(store, kind="store") as out:
        (out.store() / "a").write_text("1")
    with pytest.raises(OutputError, match="did not write"):
        with Output(store, kind="store", overwrite=True) as out:
            (out.store() / "a").write_text("2")
            (store / "mine.txt").write_text("keep")  # put there while the run goes on
    assert (store / "mine.txt").read_text() == "keep" and (store / "a").read_text() == "1"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.zarr"]


# --------------------------------------------------------------------------------------
# Every deletion removes only what a run itself made
# --------------------------------------------------------------------------------------
def test_leftover_cleaning_removes_only_a_partial_store_that_a_run_made(tmp_path):
    """A killed run's ``.partial`` store is known by its marker; a directory of the same
    form without it (or holding more) is someone else's and stays."""
    from emccdcal._output import remove_leftovers

    target = tmp_path / "movie.zarr"
    with pytest.raises(KeyboardInterrupt):  # a run that dies while writing its store
        with Output(target, kind="store") as out:
            content = out.store()
            (content / "zarr.json").write_text("{}")
            partial = content.parent
            raise KeyboardInterrupt
    assert not partial.exists() and not target.exists()
    # as a kill -9 leaves it: the marked .partial with its content
    killed = tmp_path / ".movie.zarr.0123456789ab.partial"
    (killed / "store").mkdir(parents=True)
    (killed / STORE_MARKER).write_text('{"partial": true}')
    (killed / "store" / "zarr.json").write_text("{}")
    foreign = tmp_path / ".movie.zarr.aaaaaaaaaaaa.partial"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    grown = tmp_path / ".movie.zarr.bbbbbbbbbbbb.partial"
    (grown / "store").mkdir(parents=True)
    (grown / STORE_MARKER).write_text('{"partial": true}')
    (grown / "notes.txt").write_text("mine")
    remove_leftovers(target)
    assert not killed.exists()
    assert (foreign / "notes.txt").read_text() == "mine"
    assert (grown / "notes.txt").read_text() == "mine"


def test_a_store_is_published_whole_and_its_partial_removed(tmp_path):
    target = tmp_path / "movie.zarr"
    with Output(target, kind="store") as out:
        (out.store() / "a").write_text("1")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["movie.zarr"]
    assert sorted(p.name for p in target.iterdir()) == [STORE_MARKER, "a"]


def test_leftover_cleaning_keeps_an_old_store_that_holds_a_users_file(tmp_path):
    """A killed run's ``.old`` store is removed only while it holds nothing but what
    emccdcal wrote; a ``.tmp`` leftover of the same output is removed."""
    from emccdcal._output import remove_leftovers

    target = tmp_path / "movie.zarr"
    old = tmp_path / ".movie.zarr.0123456789ab.old"
    old.mkdir()
    (old / STORE_MARKER).write_text(json.dumps({"files": [STORE_MARKER]}))
    (old / "notes.txt").write_text("mine")  # not in the marker's list
    tmp = tmp_path / ".movie.zarr.0123456789ab.tmp"
    tmp.write_text("half")
    remove_leftovers(target)
    assert (old / "notes.txt").read_text() == "mine"
    assert not tmp.exists()
    (old / "notes.txt").unlink()
    remove_leftovers(target)
    assert not old.exists()  # only emccdcal's files: its own leftover


def test_writing_a_result_never_touches_a_file_beside_it(tmp_path):
    from emccdcal._output import write_netcdf

    import xarray as xr

    ds = xr.Dataset({"x": ("a", np.arange(3.0))})
    path = tmp_path / "calibration.nc"
    beside = tmp_path / "calibration.nc.body"
    beside.write_text("a user's file")
    write_netcdf(ds, path)
    assert beside.read_text() == "a user's file"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration.nc", "calibration.nc.body"]


def test_the_writable_check_of_a_run_leaves_every_existing_file(tmp_path):
    from emccdcal.runstore import RunStore

    mine = tmp_path / f".emccdcal-probe-{os.getpid()}"
    mine.write_text("a user's file")
    RunStore(tmp_path, {"run": 1})
    assert mine.read_text() == "a user's file"


def test_a_users_files_where_a_lock_or_a_temporary_goes_are_never_touched(tmp_path):
    """Only what emccdcal wrote is truncated or removed: a user's file named like the
    lock, a link in the lock's place, and a file named like a temporary store stay."""
    out = tmp_path / "out"
    out.mkdir()
    (out / ".emccdcal-lock").write_text("my notes\n")
    with pytest.raises(OutputError, match="a file emccdcal did not write stands where its lock"):
        with Output(out, names=("a.txt",)):
            pass
    assert (out / ".emccdcal-lock").read_text() == "my notes\n"
    (out / ".emccdcal-lock").unlink()
    target = tmp_path / "precious.txt"
    target.write_text("keep me")
    (out / ".emccdcal-lock").symlink_to(target)
    with pytest.raises(OutputError):
        with Output(out, names=("a.txt",)):
            pass
    assert target.read_text() == "keep me" and (out / ".emccdcal-lock").is_symlink()
    # A file (not a folder) named like a temporary store is no temporary of ours.
    (out / ".emccdcal-lock").unlink()
    odd = out / ".a.txt.0123456789ab.partial"
    odd.write_text("not ours")
    with Output(out, names=("a.txt",)):
        atomic_write_text(out / "a.txt", "new")
    assert odd.read_text() == "not ours" and (out / "a.txt").read_text() == "new"
    assert not (out / ".emccdcal-lock").exists()  # the run's own lock is gone
