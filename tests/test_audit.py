"""``emccdcal audit``: a localization tool's camera numbers checked against a calibration,
in the tool's own words, for every tool emccdcal exports to."""

from __future__ import annotations

import re

import numpy as np
import pytest
from scipy.io import savemat
from test_export import GAINS, OFFSET, PHI, true_result

from emccdcal import cli
from emccdcal.errors import InputError
from emccdcal.export.audit import TOOL_NAMES, audit, read_tool_file
from emccdcal.export.tools import export

SETPOINT = 100.0
TRUE_PE_PER_ADU = PHI / GAINS[SETPOINT]

#: Per tool: the file ``export`` writes, and how to put its photon conversion 10 % off
#: (the field a user would have wrong, as text to find and its replacement).
EXPORTED = {
    "picasso": ("picasso-config.yaml", r'("Sensitivity": )([0-9.]+)'),
    "decode": ("decode-camera.yaml", r'("e_per_adu": )([0-9.]+)'),
    "thunderstorm": ("thunderstorm-camera.ijm", r"(photons2adu=)([0-9.]+)"),
    "gdsc": ("gdsc-calibration.json", r'("countPerPhoton": )([0-9.]+)'),
    "smap": ("smap-camera.json", r'("conversion": )([0-9.]+)'),
    "pyme": ("pyme.json", r'("Camera.ElectronsPerCount": )([0-9.]+)'),
    "storm-analysis": ("storm-analysis.xml", r'(<camera_gain type="float">)([0-9.]+)'),
}
#: The field each perturbation changes, as the audit names it.
FIELD = {
    "picasso": "Sensitivity",
    "decode": "e_per_adu",
    "thunderstorm": "photons2adu",
    "gdsc": "countPerPhoton",
    "smap": "conversion",
    "pyme": "Camera.ElectronsPerCount",
    "storm-analysis": "camera_gain",
}


@pytest.fixture(scope="module")
def calibration(tmp_path_factory):
    d = tmp_path_factory.mktemp("audit")
    return true_result(
        d / "res",
        camera={
            "serial": "X-1",
            "model": "iXon 897",
            "readout_rate_mhz": 17.0,
            "analog_gain": "Gain 3",
        },
    )


@pytest.mark.parametrize("tool", sorted(EXPORTED))
def test_an_export_agrees_and_ten_percent_off_is_named(calibration, tool, tmp_path, capsys):
    # smite's file (binary MATLAB) and the OME-TIFF of maps: tests/test_cmos.py puts a
    # pixel of each off
    assert set(EXPORTED) | {"smite", "ome-tiff"} == set(TOOL_NAMES)
    name, pattern = EXPORTED[tool]
    (path,) = [
        f
        for f in export(calibration, tool, tmp_path / "exp", setpoint=SETPOINT, pixel_size_nm=107)
        if f.name == name
    ]
    (found,) = audit(path, calibration, setpoint=SETPOINT)
    assert found.ok and found.reading.tool == tool
    assert abs(found.photon_bias) < 1e-4  # the export's own rounding only
    assert (
        cli.main(["audit", str(path), "--calibration", str(calibration), "--setpoint", "100", "-q"])
        == 0
    )
    assert capsys.readouterr().out == ""  # quiet when all agree
    # the same file with its conversion 10 % off: exit 1, the field and the bias named
    text = path.read_text()
    # storm-analysis and gdsc hold g/phi (ADU per photoelectron): 10 % more is 9.1 % fewer
    # photons
    factor = 1.1
    off = re.sub(pattern, lambda m: f"{m.group(1)}{float(m.group(2)) * factor:.6g}", text, count=1)
    assert off != text
    bad = tmp_path / ("off-" + name)
    bad.write_text(off)
    assert (
        cli.main(["audit", str(bad), "--calibration", str(calibration), "--setpoint", "100"]) == 1
    )
    out = capsys.readouterr().out
    expect = 1 / factor - 1 if tool in ("gdsc", "storm-analysis") else factor - 1
    assert f"OFF: photons {100 * expect:+.1f} % (most of it {FIELD[tool]})" in out
    assert out.startswith(f"{TOOL_NAMES[tool]}: ")


def test_picasso_as_users_write_it_nested_modes_and_the_typed_gain(calibration, tmp_path, capsys):
    """A hand-written config: no gain in the file (the set-point typed into Picasso's box
    is assumed), Sensitivity nested by read-out mode; the calibration's recorded read-out
    rate and analog gain pick the entry."""
    config = tmp_path / "config.yaml"
    config.write_text(
        "Cameras:\n"
        "  iXon 897:\n"
        "    Baseline: 100\n"
        "    Sensitivity Categories: [Read Mode, Pre-Amp Gain]\n"
        "    Sensitivity:\n"
        "      Electron Multiplying:\n"
        "        17.000 MHz:\n"
        f"          Gain 1: 16.1\n          Gain 3: {PHI}\n"
        "        10.000 MHz:\n"
        "          Gain 3: 3.5\n"
        "    Quantum Efficiency:\n"
        "      525: 0.95\n"
    )
    assert len(read_tool_file(config, setpoint=SETPOINT)) == 3
    (found,) = audit(config, calibration, setpoint=SETPOINT)
    assert found.reading.where.endswith("Electron Multiplying > 17.000 MHz > Gain 3")
    # the gain typed in is the set-point (100), the true gain 90.06: photons 9.9 % low
    assert found.photon_bias == pytest.approx(GAINS[SETPOINT] / SETPOINT - 1, rel=1e-9)
    assert (
        cli.main(["audit", str(config), "--calibration", str(calibration), "--setpoint", "100"])
        == 1
    )
    out = capsys.readouterr().out
    assert (
        "EM gain      100; calibrated EM gain 90.06: +11.04 % (not in the file: the "
        "set-point, as typed into Picasso's EM gain box)" in out
    )
    assert "OFF: photons -9.9 % (most of it EM gain)" in out
    # told the gain really typed in, the same file agrees
    (found,) = audit(config, calibration, setpoint=SETPOINT, tool_gain=GAINS[SETPOINT])
    assert found.ok
    # a baseline 10 ADU off is named too
    config.write_text(config.read_text().replace("Baseline: 100", "Baseline: 110"))
    (found,) = audit(config, calibration, setpoint=SETPOINT, tool_gain=GAINS[SETPOINT])
    assert found.problems == ["Baseline +10 ADU from the calibrated offset 100 ADU, beyond 1 ADU"]


def _cells(rows):
    out = np.empty((len(rows), len(rows[0])), dtype=object)
    for i, row in enumerate(rows):
        for j, value in enumerate(row):
            out[i, j] = value
    return out


def _smap_camera(name, par, states=()):
    """One camera of SMAP's Camera Manager database as its CameraManager.m saves it: a
    parameter table (name, mode, fixed value, metadata field, -, conversion, -) and
    states, each with its own (name, value) table."""
    table = _cells(
        [[k, mode, value, "select", "", "str2double(X)", ""] for k, (mode, value) in par.items()]
    )
    state = np.zeros(
        (1, max(1, len(states))), dtype=[("statelist", "O"), ("defpar", "O"), ("par", "O")]
    )
    for j, values in enumerate(states or [{}]):
        state[0, j] = (
            np.array(["default"], dtype=object),
            _cells([["select", ""]]),
            _cells([[k, values.get(k, "")] for k in par]),
        )
    return {"ID": {"name": name, "tag": "select", "value": ""}, "par": table, "state": state}


def test_smap_cameras_mat_and_pyme_md(calibration, tmp_path):
    mat = tmp_path / "cameras.mat"
    fixed = {
        "EMon": ("fix", "1"),
        "conversion": ("fix", f"{PHI}"),
        "emgain": ("fix", f"{GAINS[SETPOINT]}"),
        "offset": ("fix", f"{OFFSET}"),
    }
    savemat(mat, {"cameras": _smap_camera("iXon", fixed)})
    (found,) = audit(mat, calibration, setpoint=SETPOINT)
    assert found.ok and found.reading.tool == "smap"
    # state-dependent conversion (one state per pre-amp gain), EM gain from the files
    modes = {**fixed, "conversion": ("state dependent", ""), "emgain": ("metadata", "")}
    savemat(
        mat,
        {
            "cameras": _smap_camera(
                "iXon", modes, [{"conversion": f"{PHI}"}, {"conversion": f"{PHI * 1.1}"}]
            )
        },
    )
    right, wrong = audit(mat, calibration, setpoint=SETPOINT, tolerance=0.5)
    assert right.reading.where == "cameras > iXon > state 1"
    assert right.reading.fields[2].value == SETPOINT  # the set-point the files record
    assert wrong.photon_bias == pytest.approx(1.1 * (1 + right.photon_bias) - 1)
    md = tmp_path / "movie.md"
    md.write_text(
        "from PYME.IO.MetaDataHandler import NestedClassMDHandler\n"
        f"md['Camera.ADOffset'] = {OFFSET}\nmd['Camera.ElectronsPerCount'] = "
        f"{PHI * 1.2}\nmd['Camera.TrueEMGain'] = {GAINS[SETPOINT]}\n"
        "md['Camera.Name'] = __import__('os').system('echo never run')\n"
    )
    (found,) = audit(md, calibration, setpoint=SETPOINT)
    assert found.reading.tool == "pyme" and found.photon_bias == pytest.approx(0.2)


def test_smap_camera_manager_file_export_is_what_smap_reads(calibration, tmp_path, capsys):
    """The exported ``smap-cameras.mat`` is a Camera Manager database SMAP's
    getCameraCalibration can use: one camera named Default (SMAP's fallback for files it
    does not recognise), its 15-row parameter table in SMAP's order, one state; audit reads
    it back as agreeing, and with its conversion 10 % off names the field."""
    from scipy.io import loadmat

    with pytest.warns(UserWarning, match="SMAP's default 0.1 µm is written; give --pixel-size"):
        files = export(calibration, "smap", tmp_path / "exp", setpoint=SETPOINT)
    (mat,) = [f for f in files if f.name == "smap-cameras.mat"]
    raw = loadmat(mat, struct_as_record=False, squeeze_me=True)
    camera = raw["cameras"]
    assert camera.ID.name == "Default" and [str(x) for x in raw["camtab"]] == [
        "Default",
        "select",
        "[]",
    ]
    table = np.asarray(camera.par, dtype=object)
    assert table.shape == (15, 7)
    assert list(table[:, 0]) == [
        "EMon",
        "cam_pixelsize_um",
        "conversion",
        "emgain",
        "offset",
        "roi",
        "exposure",
        "timediff",
        "comment",
        "numberOfFrames",
        "Width",
        "Height",
        "roimode",
        "correctionfile",
        "imagemetadata",
    ]
    rows = {row[0]: row for row in table}
    assert float(rows["conversion"][2]) == pytest.approx(PHI)
    assert float(rows["emgain"][2]) == pytest.approx(GAINS[SETPOINT])
    assert rows["EMon"][2] == "1" and rows["correctionfile"][2] == "smap-correction"
    assert np.asarray(camera.state.par, dtype=object).shape == (15, 2)
    (found,) = audit(mat, calibration, setpoint=SETPOINT)
    assert found.ok and found.reading.where == "cameras > Default"
    # the same database with its conversion 10 % off
    raw = loadmat(mat, struct_as_record=False)
    cam = raw["cameras"][0, 0]
    cam.par[2, 2] = np.array([f"{PHI * 1.1!r}"])
    off = tmp_path / "cameras.mat"
    savemat(
        off,
        {
            "cameras": {
                "ID": {"name": "Default", "tag": "select", "value": ""},
                "par": cam.par,
                "state": cam.state[0, 0],
            }
        },
    )
    assert (
        cli.main(["audit", str(off), "--calibration", str(calibration), "--setpoint", "100"]) == 1
    )
    assert "OFF: photons +10.0 % (most of it conversion)" in capsys.readouterr().out
    # given the pixel size, no warning and SMAP's micrometres
    files = export(calibration, "smap", tmp_path / "px", setpoint=SETPOINT, pixel_size_nm=107)
    raw = loadmat(files[-1], struct_as_record=False, squeeze_me=True)
    assert float(np.asarray(raw["cameras"].par, dtype=object)[1, 2]) == pytest.approx(0.107)


def test_files_that_are_no_tools_camera_are_one_line(calibration, tmp_path, capsys):
    junk = tmp_path / "notes.yaml"
    junk.write_text("hello: world\n")
    with pytest.raises(
        InputError,
        match=r"notes\.yaml': not a camera file of a tool "
        r"emccdcal knows \(DECODE, gdsc-smlm, OME-TIFF maps, Picasso",
    ):
        audit(junk, calibration, setpoint=SETPOINT)
    bad = tmp_path / "config.yaml"
    bad.write_text('Cameras:\n  cam:\n    Sensitivity: "four"\n')
    assert (
        cli.main(["audit", str(bad), "--calibration", str(calibration), "--setpoint", "100"]) == 2
    )
    err = capsys.readouterr().err
    assert err.strip().endswith("'four', not a number") and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


def test_a_nul_in_yaml_and_a_smap_state_without_its_table_are_one_line(
    calibration, tmp_path, capsys
):
    """A YAML file holding a NUL (PyYAML refused it while building its reader) and a
    SMAP camera whose state lacks its parameter table (the reader asked for it): each
    one line naming the file, exit 2."""
    nul = tmp_path / "config.yaml"
    nul.write_bytes(b"Cameras:\n  cam:\n    Baseline: 1\x00\n")
    mat = tmp_path / "cameras.mat"
    camera = _smap_camera("iXon", {"conversion": ("state dependent", ""), "emgain": ("fix", "5")})
    camera["state"] = np.zeros((1, 1), dtype=[("statelist", "O")])
    camera["state"][0, 0] = (np.array(["default"], dtype=object),)
    savemat(mat, {"cameras": camera})
    for path, says in ((nul, "not a readable"), (mat, "SMAP cannot read it (AttributeError")):
        argv = ["audit", str(path), "--calibration", str(calibration), "--setpoint", "100"]
        assert cli.main(argv) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and f"'{path}': " in err and says in err, err


def test_a_field_of_another_magnitude_is_said_in_a_few_digits(calibration, tmp_path, capsys):
    """A Sensitivity of 1e302 (typed wrong): its difference is "+2.59e+303 %", never
    three hundred digits."""
    path = tmp_path / "config.yaml"
    path.write_text("Cameras:\n  ProEM:\n    Baseline: 566\n    Sensitivity: 1e302\n")
    cli.main(["audit", str(path), "--calibration", str(calibration), "--setpoint", "100"])
    out = capsys.readouterr().out
    assert "e+303 %" in out and max(map(len, out.split())) < 40, out
