"""Calibrations where they are used: exports (each tool's names and units, and Picasso
itself localizing with an exported camera), ``apply``, the gain curve and the database."""

from __future__ import annotations

import json
import math
import multiprocessing
import os
import subprocess
import sys
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import tifffile
import yaml
from camera_files import write_spe

from emccdcal import cli, result
from emccdcal.export import database
from emccdcal.export.gain_curve import fit_points, measured_gains
from emccdcal.export.movie import apply
from emccdcal.export.tools import TOOLS, export
from emccdcal.simulate.camera import simulate_frames

PHI, OFFSET, SIGMA = 4.0, 100.0, 12.0
GAINS = {1.0: 1.0, 5.0: 4.78, 25.0: 22.95, 100.0: 90.06, 300.0: 261.6}
SHAPE = (8, 10)


def true_result(
    path,
    *,
    phi=PHI,
    gains=GAINS,
    offset=OFFSET,
    sigma=SIGMA,
    shape=SHAPE,
    camera=None,
    spread=0.0,
    seed=0,
):
    """A result holding a known calibration (φ, gains, offsets, read noise)."""
    rng = np.random.default_rng(seed)
    sps = sorted(gains)
    R, C = shape
    g = np.stack(
        [
            gains[s] * (1 + spread * rng.standard_normal(shape)) if s != 1 else np.ones(shape)
            for s in sps
        ]
    )
    ds = result.make_dataset(
        method="gs",
        setpoints=sps,
        e_per_adu=phi,
        e_per_adu_se=0.01,
        em_gain=g,
        em_gain_se=np.where(g == 1, 0.0, 0.002 * g),
        photoelectrons=np.full(shape, 100.0),
        photoelectrons_se=1.0,
        converged=True,
        manifest_hash="0" * 64,
        extra={
            "offset": (("setpoint", "row", "col"), np.full((len(sps), R, C), offset), "ADU"),
            "read_noise": (("setpoint", "row", "col"), np.full((len(sps), R, C), sigma), "ADU"),
        },
        attrs={"em_model": "gamma", **({"camera": json.dumps(camera)} if camera else {})},
    )
    result.save(ds, path)
    return path / result.CALIBRATION_FILE


# --------------------------------------------------------------------------------------
# Exports: every field by the name and unit its tool reads (docs/exports.md)
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    d = tmp_path_factory.mktemp("export")
    res = true_result(d / "res", camera={"serial": "X-123", "model": "iXon 897"})
    files = {
        t: export(
            res,
            t,
            d / t,
            setpoint=100 if t not in ("json", "fits", "tiff-maps") else None,
            qe=0.9,
            pixel_size_nm=107.0,
        )
        for t in TOOLS
    }
    return res, files


def _yaml(path):
    yaml = pytest.importorskip("yaml")
    return yaml.safe_load(path.read_text())


def test_every_export_names_and_units(exported):
    res, files = exported
    g, total = GAINS[100.0], GAINS[100.0] / PHI
    sha = result.load_calibration(res).sha256[0]

    cam = _yaml(files["picasso"][0])["Cameras"]["iXon 897 X-123"]
    # Picasso's window takes an integer gain: the ratio that makes its photons is kept.
    assert cam["DefaultGain"] == 90 and isinstance(cam["DefaultGain"], int)
    assert cam["Sensitivity"] / cam["DefaultGain"] == pytest.approx(PHI / g, rel=2e-5)
    assert cam["Baseline"] == pytest.approx(OFFSET) and cam["Pixelsize"] == 107.0
    assert sha in files["picasso"][0].read_text()
    # Picasso does not use a QE (and would key it by wavelength): not written, and said so
    assert "Quantum Efficiency" not in cam
    assert (
        "photons = photoelectrons / 0.9 (the QE given) are not written"
        in files["picasso"][0].read_text()
    )

    md = json.loads(files["pyme"][0].read_text())
    assert md["Camera.ElectronsPerCount"] == pytest.approx(PHI)
    assert md["Camera.TrueEMGain"] == pytest.approx(g)
    assert md["Camera.ADOffset"] == pytest.approx(OFFSET)
    assert md["Camera.ReadNoise"] == pytest.approx(SIGMA * PHI)  # e-
    assert md["Camera.NoiseFactor"] == 1.41
    assert sha in md["emccdcal.Provenance"]
    # the maps by their names beside pyme.json: no absolute path of this machine
    here = files["pyme"][0].parent
    assert all(md[k] == Path(md[k]).name for k in md if k.endswith("MapID"))
    var = tifffile.imread(here / md["Camera.VarianceMapID"])
    assert var.shape == SHAPE and np.allclose(var, (SIGMA * PHI) ** 2)  # e-^2
    assert np.allclose(tifffile.imread(here / md["Camera.DarkMapID"]), OFFSET)
    assert np.allclose(tifffile.imread(here / md["Camera.FlatfieldMapID"]), 1.0)

    dec = _yaml(files["decode"][0])["Camera"]
    assert dec["e_per_adu"] == pytest.approx(PHI) and dec["em_gain"] == pytest.approx(g)
    assert dec["baseline"] == pytest.approx(OFFSET) and dec["qe"] == 0.9
    assert dec["read_sigma"] == pytest.approx(SIGMA * PHI) and dec["px_size"] == [107.0, 107.0]
    assert dec["convert2photons"] is True

    ijm = files["thunderstorm"][0].read_text()
    line = [x for x in ijm.splitlines() if x.startswith("run(")][0]
    opts = dict(kv.split("=") for kv in line.split('"')[3].split())
    assert float(opts["photons2adu"]) == pytest.approx(PHI)  # e-/ADU despite its name
    assert float(opts["gainem"]) == pytest.approx(g) and opts["isemgain"] == "true"
    assert float(opts["offset"]) == pytest.approx(OFFSET)
    assert float(opts["quantumefficiency"]) == 0.9 and float(opts["pixelsize"]) == 107.0

    smap = json.loads(files["smap"][0].read_text())["loc_cameraSettings"]
    assert smap["conversion"] == pytest.approx(PHI) and smap["emgain"] == pytest.approx(g)
    assert smap["EMon"] is True and smap["offset"] == pytest.approx(OFFSET)
    assert smap["cam_pixelsize_um"] == pytest.approx(0.107)
    from scipy.io import loadmat

    mat = loadmat(files["smap"][1])
    assert np.allclose(mat["gainmap"], PHI / g, rtol=1e-6)  # photons per ADU
    assert np.allclose(mat["offsetmap"], OFFSET) and np.allclose(mat["varmap"], SIGMA**2)

    gd = json.loads(files["gdsc"][0].read_text())
    assert gd["intensityCalibration"]["countPerPhoton"] == pytest.approx(0.9 * total)
    assert gd["intensityCalibration"]["intensityUnit"] == "COUNT"
    cc = gd["cameraCalibration"]
    assert cc["cameraType"] == "EMCCD" and cc["bias"] == pytest.approx(OFFSET)
    assert cc["readNoise"] == pytest.approx(SIGMA)  # counts
    assert cc["quantumEfficiency"] == 0.9
    assert gd["distanceCalibration"]["nmPerPixel"] == 107.0

    root = ET.parse(files["storm-analysis"][0]).getroot()
    assert root.tag == "settings"
    assert float(root.find("camera_gain").text) == pytest.approx(total)  # ADU per e-
    assert root.find("camera_gain").get("type") == "float"
    assert float(root.find("camera_offset").text) == pytest.approx(OFFSET)

    doc = json.loads(files["json"][0].read_text())
    assert doc["by_setpoint"]["300"]["em_gain"]["median"] == pytest.approx(GAINS[300.0])
    assert doc["camera"]["serial"] == "X-123"

    names = {p.name for p in files["tiff-maps"]}
    assert {"e_per_adu.tif", "em_gain_25x.tif", "offset_100x.tif"} <= names
    desc = json.loads(tifffile.TiffFile(files["tiff-maps"][0]).pages[0].description)
    assert desc["units"] == "e-/ADU" and desc["results"][0]["sha256"] == sha

    fits = pytest.importorskip("astropy.io.fits")
    with fits.open(files["fits"][0]) as hdul:
        assert hdul["EM_GAIN_100X"].header["BUNIT"] == "1"
        assert np.allclose(hdul["EM_GAIN_100X"].data, g)
        assert hdul[0].header["SHA2560"] == sha


def test_export_needs_a_setpoint_and_says_which(tmp_path):
    res = true_result(tmp_path / "r")
    with pytest.raises(ValueError, match=r"has set-points 1x, 5x, 25x, 100x, 300x.*--setpoint"):
        export(res, "picasso", tmp_path / "o")
    assert not (tmp_path / "o").exists()  # refused before anything is made
    with pytest.raises(ValueError, match=r"set-point 50x is missing .*gain-curve"):
        export(res, "picasso", tmp_path / "o", setpoint=50)
    code = cli.main(["export", str(res), "--to", "pyme", "-o", str(tmp_path / "o"), "-q"])
    assert code == 2
    assert not (tmp_path / "o").exists()  # no empty folder left behind


# --------------------------------------------------------------------------------------
# Picasso itself, localizing with the exported camera (extra [clients])
# --------------------------------------------------------------------------------------
@pytest.mark.slow
def test_picasso_localizes_with_the_exported_camera(tmp_path):
    pytest.importorskip("picasso", reason="Picasso is not installed (extra [clients])")
    from emccdcal.beads import validation
    from emccdcal.simulate.beads import simulate_beads

    n_true = 2000.0
    sim = simulate_beads(
        tmp_path / "sim",
        beads=8,
        photoelectrons=n_true,
        width=1.3,
        background=10.0,
        setpoints=(1, 100),
        frames=100,
        dark_frames=200,
        seed=7,
    )
    truth = json.loads(sim.truth_path.read_text())
    truth_nc = tmp_path / "sim" / "truth_calibration.nc"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        doc = validation.validate(sim.manifest, [str(truth_nc)], out=tmp_path / "val")
    ours = np.mean([b["mean_intensity"]["100"] for b in doc["calibrations"][0]["beads"]])

    # φ inverted (ADU/e- given as e-/ADU): Picasso accepts it and is 1/φ² = 15× low.
    ds = result.load(truth_nc)
    ds["e_per_adu"] = 1 / ds["e_per_adu"]
    result.save(ds, tmp_path / "inverted")
    # Both cameras exported and merged into one Picasso configuration as the file tells
    # its user (the second file's camera entry under the first's "Cameras"), both files'
    # lines as written; one run of Picasso localizes with each.
    texts = [
        export(calibration, "picasso", tmp_path / name, setpoint=100, camera_name=name)[
            0
        ].read_text()
        for name, calibration in (("truth", truth_nc), ("inverted", tmp_path / "inverted"))
    ]
    merged = texts[0] + texts[1].split('"Cameras":\n', 1)[1]
    home = tmp_path / "home"
    (home / ".picasso").mkdir(parents=True)
    (home / ".picasso" / "config.yaml").write_text(merged)
    assert set(yaml.safe_load(merged)["Cameras"]) == {"truth", "inverted"}
    env = dict(os.environ, HOME=str(home), NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    # The net gradient acts on raw ADU: a bead of 2000 e- at g/phi = 23 ADU/e- far
    # exceeds 5000, the background's noise does not.
    run = subprocess.run(
        [
            sys.executable,
            str(Path(__file__).with_name("picasso_client.py")),
            str(tmp_path / "sim" / "beads" / "100x-beads.tif"),
            "5000",
            "truth",
            "inverted",
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    found = {}
    for line in run.stdout.strip().splitlines()[-2:]:
        out = json.loads(line)
        x, y, ph = (np.array(out[k]) for k in ("x", "y", "photons"))
        per_bead = []
        for b in truth["beads"]:
            near = (np.abs(x - b["col"]) < 1.5) & (np.abs(y - b["row"]) < 1.5)
            assert near.sum() >= 95  # found in (nearly) every frame
            per_bead.append(ph[near].mean())
        found[out["camera"]] = out["camera_info"], np.mean(per_bead), len(ph)

    info, mean, n_locs = found["truth"]
    print(
        f"Picasso {mean:.1f} e-, validate {ours:.1f} e-, truth {n_true:.0f} e-, "
        f"{n_locs} localizations"
    )
    assert info["Gain"] == 90 and info["Sensitivity"] / 90 == pytest.approx(3.859 / 90.06, rel=2e-5)
    assert n_locs <= 8 * 100 * 1.02  # no spurious spots
    assert mean == pytest.approx(n_true, rel=0.02)
    assert mean == pytest.approx(ours, rel=0.02)
    _, wrong, _ = found["inverted"]
    print(f"phi inverted: Picasso {wrong:.1f} e-")
    assert wrong == pytest.approx(n_true / 3.859**2, rel=0.05)
    assert abs(wrong / n_true - 1) > 0.5


# --------------------------------------------------------------------------------------
# apply
# --------------------------------------------------------------------------------------
def _movie(path, E, g, frames, seed, *, setpoint_tag=None):
    stack = simulate_frames(
        E, em_gain=g, e_per_adu=PHI, offset=OFFSET, read_noise=SIGMA, frames=frames, seed=seed
    )
    tifffile.imwrite(path, stack)
    return stack


def test_apply_recovers_the_photoelectrons(tmp_path):
    res = true_result(tmp_path / "r")
    E = np.full(SHAPE, 30.0)
    E[2:5, 3:7] = 200.0
    _movie(tmp_path / "m.tif", E, GAINS[100.0], 400, seed=3)
    out = apply(res, tmp_path / "m.tif", tmp_path / "e.tif", setpoint=100, progress=False)
    with tifffile.TiffFile(out) as tif:
        e = tif.asarray()
        meta = json.loads(tif.pages[0].description)
    assert e.dtype == np.float32 and e.shape == (400, *SHAPE)
    assert meta["units"].startswith("photoelectrons") and meta["setpoint"] == 100
    # The mean over frames of each region matches its truth within 3 standard errors
    # (ADC rounding biases the mean by less than 0.5 ADU = 0.02 e- here).
    for mask in (E == 30.0, E == 200.0):
        v = e[:, mask].mean(axis=1)
        assert abs(v.mean() - E[mask][0]) < 3 * v.std(ddof=1) / math.sqrt(v.size)
    zarr = pytest.importorskip("zarr")
    z = apply(res, tmp_path / "m.tif", tmp_path / "e.zarr", setpoint=100, progress=False)
    za = zarr.open_array(str(z), mode="r")
    assert np.array_equal(za[:], e) and za.attrs["units"].startswith("photoelectrons")


def test_apply_photon_counting_and_errors(tmp_path):
    res = true_result(tmp_path / "r")
    E = np.full(SHAPE, 0.05)
    stack = _movie(tmp_path / "m.tif", E, GAINS[300.0], 2000, seed=4)
    with pytest.warns(UserWarning, match="clears the 5-sigma threshold in only 40% of cases"):
        out = apply(
            res,
            tmp_path / "m.tif",
            tmp_path / "c.tif",
            setpoint=300,
            photon_counting=True,
            progress=False,
        )
    with tifffile.TiffFile(out) as tif:
        c = tif.asarray()
        meta = json.loads(tif.pages[0].description)
    eff = meta["single_electron_efficiency"]
    assert eff == pytest.approx(math.exp(-5 * SIGMA * PHI / GAINS[300.0]))
    rate = c.mean()  # counts per pixel-frame: P(>=1 e-) × efficiency
    expect = (1 - math.exp(-0.05)) * eff
    assert abs(rate - expect) < 4 * math.sqrt(expect / c.size)
    assert c.dtype == np.uint8 and set(np.unique(c)) <= {0, 1}
    with pytest.raises(ValueError, match="records no EM gain set-point and its name states none"):
        apply(res, tmp_path / "m.tif", tmp_path / "x.tif")
    with pytest.raises(ValueError, match=r"set-point 50x is missing"):
        apply(res, tmp_path / "m.tif", tmp_path / "x.tif", setpoint=50)
    tifffile.imwrite(tmp_path / "big.tif", np.zeros((5, 20, 20), np.uint16))
    with pytest.raises(
        ValueError,
        match=r"big.tif: its 20×20 frames are not the "
        r"calibration's 8×10 pixels .* records no region",
    ):
        apply(res, tmp_path / "big.tif", tmp_path / "x.tif", setpoint=100)
    assert not (tmp_path / "x.tif").exists()
    # An SPE movie records its set-point and its region on the sensor.
    ds = result.load(res)
    ds.attrs["sensor_origin"] = np.array([10, 20])
    result.save(ds, tmp_path / "placed")
    part = stack[:50, 2:6, 3:9]
    write_spe(tmp_path / "m.spe", part, em_gain=300, roi=(23, 12))  # x = col, y = row
    e = tifffile.imread(
        apply(tmp_path / "placed", tmp_path / "m.spe", tmp_path / "p.tif", progress=False)
    )
    assert np.allclose(e, (part - OFFSET) * PHI / GAINS[300.0], rtol=1e-6)
    with pytest.raises(ValueError, match=r"set-point 100 given, but the file records 300"):
        apply(tmp_path / "placed", tmp_path / "m.spe", tmp_path / "q.tif", setpoint=100)
    write_spe(tmp_path / "off.spe", part, em_gain=300, roi=(28, 12))
    with pytest.raises(ValueError, match=r"frames at sensor row 12, column 28 are not inside"):
        apply(tmp_path / "placed", tmp_path / "off.spe", tmp_path / "q.tif")
    code = cli.main(
        [
            "apply",
            str(res),
            str(tmp_path / "m.tif"),
            "-o",
            str(tmp_path / "y.tif"),
            "--setpoint",
            "300",
            "-q",
        ]
    )
    assert code == 0 and tifffile.imread(tmp_path / "y.tif").shape == stack.shape


# --------------------------------------------------------------------------------------
# The gain curve
# --------------------------------------------------------------------------------------
@pytest.mark.slow
def test_gain_curve_predicts_a_setpoint_not_measured(tmp_path):
    # True curve: ln g = a + b ln s + c (ln s)^2; measure four set-points, predict a fifth.
    def truth(s):
        x = np.log(s)
        return np.exp(-0.4 + 1.02 * x - 0.004 * x**2)

    measured = (5.0, 25.0, 100.0, 300.0)
    files = [
        true_result(
            tmp_path / f"r{s:g}",
            gains={1.0: 1.0, s: truth(s)},
            spread=0.01,
            shape=(20, 20),
            seed=int(s),
        )
        for s in measured
    ]
    curve = fit_points(measured_gains(files))
    assert curve.degree == 2 and curve.dof == 1
    p = curve.predict([50.0, 1000.0])
    for i, s in enumerate((50.0, 1000.0)):
        assert abs(p["gain"][i] - truth(s)) < 3 * p["se_of_median"][i]
    assert list(p["extrapolated"]) == [False, True]
    assert p["lower"][0] < p["gain"][0] < p["upper"][0]
    code = cli.main(
        ["gain-curve", *map(str, files), "-o", str(tmp_path / "gc"), "--predict", "50", "-q"]
    )
    assert code == 0
    table = (tmp_path / "gc" / "gain-curve.csv").read_text().splitlines()
    assert table[0].startswith("setpoint,gain,se_of_median") and any(
        r.startswith("50,") for r in table
    )
    assert (tmp_path / "gc" / "gain-curve.png").is_file()
    with pytest.raises(ValueError, match="two or more multiplied set-points"):
        fit_points(measured_gains(files[:1]))


# --------------------------------------------------------------------------------------
# The calibration database
# --------------------------------------------------------------------------------------
def _add_many(db, files):
    for f in files:
        database.add(f, db=db, date=f"2025-{1 + int(Path(f).parent.name[1:]) % 12:02d}-01")


@pytest.mark.slow
def test_database_concurrent_writers_lose_nothing(tmp_path):
    files = [
        true_result(
            tmp_path / f"r{i}",
            camera={"serial": "S1", "readout_rate_mhz": 10.0},
            spread=0.01,
            seed=i,
        )
        for i in range(12)
    ]
    db = tmp_path / "cal.sqlite"
    ctx = multiprocessing.get_context("spawn")
    procs = [ctx.Process(target=_add_many, args=(db, files[k::4])) for k in range(4)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(120)
    assert all(p.exitcode == 0 for p in procs)
    found = database.entries(db=db, camera="S1")
    assert len(found) == 12 and len({e.sha256 for e in found}) == 12
    assert {e.readout for e in found} == {"10 MHz"}
    with pytest.raises(ValueError, match="already in the database as entry"):
        database.add(files[0], db=db)


@pytest.mark.slow
def test_database_flags_an_ageing_register(tmp_path, capsys):
    db = tmp_path / "cal.sqlite"
    # A register losing 1.5 % of its gain a month at every set-point; spread keeps SEs real.
    for month in range(5):
        gains = {s: g * (1 - 0.015 * month) if s != 1 else 1.0 for s, g in GAINS.items()}
        f = true_result(
            tmp_path / f"m{month}",
            gains=gains,
            spread=0.01,
            shape=(16, 16),
            seed=month,
            camera={"serial": "AGE-1"},
        )
        database.add(f, db=db, date=f"2026-{month + 1:02d}-15")
    found, findings = database.compare("AGE-1", db=db, max_age_days=30, now="2026-07-01")
    assert len(found) == 5
    kinds = {(f.kind, f.setpoint) for f in findings}
    assert ("age", None) in kinds and ("change", 100.0) in kinds and ("change", 300.0) in kinds
    # the months' decline is a trend at every multiplied set-point (-16.6 %/year)
    trends = [f for f in findings if f.kind == "trend"]
    assert {f.setpoint for f in trends} == {s for s in GAINS if s != 1}
    assert all("drifts by -1" in f.message for f in trends)
    # A repeat with the same gains is not flagged as a change (the trend stays).
    same = true_result(
        tmp_path / "same",
        gains={s: g * (1 - 0.015 * 4) if s != 1 else 1.0 for s, g in GAINS.items()},
        spread=0.01,
        shape=(16, 16),
        seed=99,
        camera={"serial": "AGE-1"},
    )
    database.add(same, db=db, date="2026-06-20")
    _, findings = database.compare("AGE-1", db=db)
    assert {f.kind for f in findings} == {"trend"}
    # The command line: exit 1 with warnings, a figure, and export/apply through --db.
    code = cli.main(
        [
            "db",
            "--db",
            str(db),
            "compare",
            "--camera",
            "AGE-1",
            "--max-age",
            "1",
            "-o",
            str(tmp_path / "fig"),
        ]
    )
    err = capsys.readouterr().err
    assert code == 1 and "days old, more than 1" in err and "may have aged" not in err
    assert "drifts by" in err
    assert (tmp_path / "fig" / "gain-history-AGE-1.png").is_file()
    code = cli.main(
        [
            "export",
            "--camera",
            "AGE-1",
            "--db",
            str(db),
            "--setpoint",
            "100",
            "--to",
            "json",
            "-o",
            str(tmp_path / "ex"),
            "-q",
        ]
    )
    assert code == 0
    doc = json.loads((tmp_path / "ex" / "emccdcal-camera.json").read_text())
    assert doc["emccdcal"]["results"][0]["file"].endswith("same/calibration.nc")
    assert cli.main(["db", "--db", str(db), "list"]) == 0
    assert "AGE-1" in capsys.readouterr().out
    assert cli.main(["db", "--db", str(db), "show", "1"]) == 0
    assert json.loads(capsys.readouterr().out)["summary"]
    # A result changed after it was added is refused.
    true_result(tmp_path / "same", gains={1.0: 1.0, 100.0: 80.0}, camera={"serial": "AGE-1"})
    with pytest.raises(ValueError, match="has changed since it was added"):
        database.find("AGE-1", 100, db=db)


def test_apply_writes_an_image_series_even_three_pixels_wide_and_photons_with_qe(tmp_path):
    """A (frames, 3, 3) stack is not one RGB image; --qe gives photons."""
    res = true_result(tmp_path / "r", shape=(3, 3))
    narrow = tmp_path / "narrow.tif"
    stack = simulate_frames(
        np.full((3, 3), 80.0),
        em_gain=GAINS[100.0],
        e_per_adu=PHI,
        offset=OFFSET,
        read_noise=SIGMA,
        frames=50,
        seed=4,
    )
    tifffile.imwrite(narrow, stack, photometric="minisblack")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # tifffile's own warnings never reach the user
        out = apply(res, narrow, tmp_path / "e.tif", setpoint=100, progress=False)
        photons = apply(res, narrow, tmp_path / "p.tif", setpoint=100, progress=False, qe=0.8)
    with tifffile.TiffFile(out) as tif:
        series = tif.series[0]
        assert series.shape == (50, 3, 3) and series.axes[-2:] == "YX"
        assert len(tif.pages) == 50 and tif.pages[0].photometric == 1  # MINISBLACK
        e = tif.asarray()
    with tifffile.TiffFile(photons) as tif:
        p = tif.asarray()
        meta = json.loads(tif.pages[0].description)
    assert meta["units"].startswith("photons") and meta["qe"] == 0.8
    np.testing.assert_allclose(p, e / 0.8, rtol=1e-6)
    from emccdcal import cli

    assert (
        cli.main(
            [
                "apply",
                str(res),
                str(narrow),
                "-o",
                str(tmp_path / "c.tif"),
                "--setpoint",
                "100",
                "--qe",
                "0.8",
                "-q",
            ]
        )
        == 0
    )
    np.testing.assert_array_equal(tifffile.imread(tmp_path / "c.tif"), p)
    for bad in (0.0, 1.5):
        with pytest.raises(ValueError, match="quantum efficiency"):
            apply(res, narrow, tmp_path / "x.tif", setpoint=100, progress=False, qe=bad)
    with pytest.raises(ValueError, match="photon counting"):
        apply(
            res,
            narrow,
            tmp_path / "x.tif",
            setpoint=100,
            progress=False,
            qe=0.8,
            photon_counting=True,
        )


def test_export_and_apply_at_a_setpoint_only_the_gain_curve_knows(tmp_path, capsys):
    """--gain-curve (or the database's curve) gives the gain where the calibration has
    none, says so, and records the prediction with its se_of_median and `extrapolated`."""
    camera = {"serial": "GC-1", "readout_rate_mhz": 10.0}
    res = true_result(tmp_path / "r", spread=0.01, shape=(12, 12), camera=camera)
    assert cli.main(["gain-curve", str(res), "-o", str(tmp_path / "gc"), "-q", "--no-figures"]) == 0
    curve_file = tmp_path / "gc" / "gain-curve.json"
    code = cli.main(
        [
            "export",
            str(res),
            "--to",
            "picasso",
            "--setpoint",
            "50",
            "--gain-curve",
            str(curve_file),
            "-o",
            str(tmp_path / "p"),
            "-q",
        ]
    )
    err = capsys.readouterr().err
    assert code == 0 and "set-point 50x was not calibrated" in err and "within the" in err
    text = (tmp_path / "p" / "picasso-config.yaml").read_text()
    assert "gain at 50x was not measured" in text and "extrapolated = false" in text
    predicted = (
        __import__("emccdcal.export.gain_curve", fromlist=["x"])
        .read_gain_curve(curve_file)
        .predict([50.0])["gain"][0]
    )
    cam = next(iter(_yaml(tmp_path / "p" / "picasso-config.yaml")["Cameras"].values()))
    assert cam["Sensitivity"] / cam["DefaultGain"] == pytest.approx(PHI / predicted, rel=1e-3)
    # Beyond the measured set-points: marked extrapolated, in the file and the warning.
    code = cli.main(
        [
            "export",
            str(res),
            "--to",
            "pyme",
            "--setpoint",
            "1000",
            "--gain-curve",
            str(curve_file),
            "-o",
            str(tmp_path / "y"),
            "-q",
        ]
    )
    assert code == 0 and "extrapolated beyond the measured 5x-300x" in capsys.readouterr().err
    prov = json.loads(json.loads((tmp_path / "y" / "pyme.json").read_text())["emccdcal.Provenance"])
    (pred,) = prov["predicted_gains"]
    assert pred["setpoint"] == 1000 and pred["extrapolated"] is True and pred["se_of_median"] > 0
    # apply: a movie recorded at 50x, converted with the predicted gain.
    E = np.full((12, 12), 120.0)
    _movie(tmp_path / "m.tif", E, predicted, 300, seed=5)
    code = cli.main(
        [
            "apply",
            str(res),
            str(tmp_path / "m.tif"),
            "-o",
            str(tmp_path / "e.tif"),
            "--setpoint",
            "50",
            "--gain-curve",
            str(curve_file),
            "-q",
        ]
    )
    assert code == 0
    with tifffile.TiffFile(tmp_path / "e.tif") as tif:
        e = tif.asarray()
        meta = json.loads(tif.pages[0].description)
    assert meta["emccdcal"]["predicted_gains"][0]["extrapolated"] is False
    assert abs(e.mean() - 120.0) < 3 * e.mean(axis=(1, 2)).std(ddof=1) / math.sqrt(300) + 1.0
    # Another camera's curve is refused, naming the field.
    other = true_result(tmp_path / "o", camera={"serial": "GC-2", "readout_rate_mhz": 10.0})
    code = cli.main(
        [
            "export",
            str(other),
            "--to",
            "picasso",
            "--setpoint",
            "50",
            "--gain-curve",
            str(curve_file),
            "-o",
            str(tmp_path / "q"),
        ]
    )
    assert code == 2 and "camera serial 'GC-1' (calibration: 'GC-2')" in capsys.readouterr().err
    assert (
        cli.main(
            [
                "export",
                str(other),
                "--to",
                "picasso",
                "--setpoint",
                "50",
                "-q",
                "--gain-curve",
                str(curve_file),
                "-o",
                str(tmp_path / "q"),
                "--accept-mismatch",
                "serial",
            ]
        )
        == 0
    )
    # The database: no entry at 50x, so the newest entry's curve predicts it.
    db = tmp_path / "db" / "cal.sqlite"
    database.add(res, db=db, date="2026-03-02")
    code = cli.main(
        [
            "export",
            "--camera",
            "GC-1",
            "--db",
            str(db),
            "--setpoint",
            "50",
            "--to",
            "json",
            "-o",
            str(tmp_path / "j"),
            "-q",
        ]
    )
    err = capsys.readouterr().err
    assert code == 0 and "database entry 1 (2026-03-02)" in err
    doc = json.loads((tmp_path / "j" / "emccdcal-camera.json").read_text())
    assert doc["by_setpoint"]["50"]["em_gain"]["median"] == pytest.approx(predicted, rel=1e-3)
    assert doc["emccdcal"]["predicted_gains"][0]["curve"].startswith("of database entry 1")


def test_database_keys_by_readout_mode_stores_portable_paths_and_compares_like_models(
    tmp_path, capsys
):
    db = tmp_path / "cal.sqlite"
    em = {
        "serial": "RM-1",
        "amplifier": "Electron Multiplying",
        "readout_rate_mhz": 17.0,
        "analog_gain": "3",
    }
    a = true_result(tmp_path / "a", spread=0.0005, camera=em)
    b = true_result(
        tmp_path / "b",
        spread=0.01,
        seed=1,
        phi=14.0,
        camera={**em, "amplifier": "Conventional", "readout_rate_mhz": 3.0},
    )
    database.add(a, db=db, date="2026-01-01")
    database.add(b, db=db, date="2026-01-02")
    states = {e.readout for e in database.entries(db=db, camera="RM-1")}
    assert states == {
        "Electron Multiplying, 17 MHz, analog gain 3",
        "Conventional, 3 MHz, analog gain 3",
    }
    with pytest.raises(ValueError, match="several read-out states"):
        database.find("RM-1", 100, db=db)
    # Stored relative to the database's folder: the folder moves with its results.
    import sqlite3

    with sqlite3.connect(db) as con:
        stored = [r[0] for r in con.execute("SELECT path FROM calibration")]
    assert stored == ["a/calibration.nc", "b/calibration.nc"]
    moved = tmp_path.parent / (tmp_path.name + "-moved")
    os.rename(tmp_path, moved)
    try:
        e = database.find(
            "RM-1",
            100,
            db=moved / "cal.sqlite",
            readout="Electron Multiplying, 17 MHz, analog gain 3",
        )
        assert Path(e.path) == moved / "a" / "calibration.nc"
    finally:
        os.rename(moved, tmp_path)
    # The same data under the gamma model and the cascade is not a change of the register.
    g = {s: v * (1.002 if s != 1 else 1) for s, v in GAINS.items()}
    c = true_result(tmp_path / "c", gains=g, spread=0.0005, seed=3, camera=em)
    ds = result.load(c)
    ds.attrs.update(em_model="cascade", register_stages=604)
    result.save(ds, tmp_path / "c2")
    database.add(tmp_path / "c2" / result.CALIBRATION_FILE, db=db, date="2026-01-03")
    rm = "Electron Multiplying, 17 MHz, analog gain 3"
    _, findings = database.compare("RM-1", db=db, readout=rm, z=3)
    assert not findings
    code = cli.main(["db", "compare", "--camera", "RM-1", "--readout", rm, "--db", str(db)])
    out = capsys.readouterr().out
    assert code == 0 and "se_of_median" in out and "cascade" in out and "gamma" in out


def test_picasso_takes_a_table_of_readout_modes_and_audit_reads_it_back(tmp_path, capsys):
    """Calibrations of several read-out modes make Picasso's nested Sensitivity, keyed by
    the Micro-Manager values of the properties that differ; each mode keeps φ/g."""
    base = {"serial": "MODES-1", "model": "iXon Ultra 897"}
    modes = {
        ("Electron Multiplying", 17.0, "Gain 3"): (4.0, {1.0: 1.0, 100.0: 90.0}),
        ("Electron Multiplying", 10.0, "Gain 3"): (3.6, {1.0: 1.0, 100.0: 88.0}),
        ("Conventional", 3.0, "Gain 3"): (1.5, {1.0: 1.0}),
    }
    files = []
    for i, ((amp, rate, pre), (phi, gains)) in enumerate(modes.items()):
        files.append(
            true_result(
                tmp_path / f"m{i}",
                phi=phi,
                gains=gains,
                camera={**base, "amplifier": amp, "readout_rate_mhz": rate, "analog_gain": pre},
            )
        )
    code = cli.main(
        [
            "export",
            *map(str, files),
            "--to",
            "picasso",
            "--setpoint",
            "100",
            "-o",
            str(tmp_path / "p"),
            "-q",
        ]
    )
    assert code == 0
    cam = _yaml(tmp_path / "p" / "picasso-config.yaml")["Cameras"]["iXon Ultra 897 MODES-1"]
    assert cam["Sensitivity Categories"] == ["Output_Amplifier", "ReadoutMode"]
    d = cam["DefaultGain"]
    sens = cam["Sensitivity"]
    assert sens["Electron Multiplying"]["17.000 MHz"] / d == pytest.approx(4.0 / 90.0, rel=1e-3)
    assert sens["Electron Multiplying"]["10.000 MHz"] / d == pytest.approx(3.6 / 88.0, rel=1e-3)
    assert sens["Conventional"]["3.000 MHz"] / d == pytest.approx(1.5, rel=1e-3)  # g = 1
    # audit picks the mode its calibration recorded, and agrees.
    assert (
        cli.main(
            [
                "audit",
                str(tmp_path / "p" / "picasso-config.yaml"),
                "--calibration",
                str(files[1]),
                "--setpoint",
                "100",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "10.000 MHz" in out and "17.000 MHz" not in out
    # Only Picasso holds a table of modes; two of one mode are refused.
    code = cli.main(
        [
            "export",
            *map(str, files),
            "--to",
            "decode",
            "--setpoint",
            "100",
            "-o",
            str(tmp_path / "d"),
        ]
    )
    assert code == 2 and "one read-out mode per file" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()
    twin = true_result(
        tmp_path / "twin",
        phi=4.1,
        gains={1.0: 1.0, 100.0: 91.0},
        seed=7,
        camera={
            **base,
            "amplifier": "Electron Multiplying",
            "readout_rate_mhz": 17.0,
            "analog_gain": "Gain 3",
        },
    )
    code = cli.main(
        [
            "export",
            *map(str, files),
            str(twin),
            "--to",
            "picasso",
            "--setpoint",
            "100",
            "-o",
            str(tmp_path / "t"),
        ]
    )
    assert code == 2 and "a second calibration of read-out mode" in capsys.readouterr().err
