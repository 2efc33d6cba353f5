"""Cameras without an EM register (sCMOS, qCMOS): the ADC's rounding in the likelihood, a
start outside the comb's aliases, honest errors where the comb ripples, the dark frames'
analog read noise, the camera kind in the manifest, and Huang's folders scanned."""

from __future__ import annotations

import re
import subprocess
import sys
import warnings

import numpy as np
import pytest
import tifffile

import emccdcal
from emccdcal.data.dark import analog_read_out
from emccdcal.errors import FitWarning, ManifestError
from emccdcal.model import adc, noise
from emccdcal.simulate.cmos import CMOSCamera, simulate_cmos_series


def _calibrated(folder, kind, shape, frames, dark_frames, seed, **camera):
    """A simulated camera of ``kind`` written to ``folder`` and its calibration as a user
    runs it (``calibrate(manifest)``: the kind says the method); (simulation, result)."""
    rows, cols = shape
    sim = simulate_cmos_series(
        folder, kind=kind, rows=rows, cols=cols, frames=frames, dark_frames=dark_frames,
        seed=seed, progress=False, **camera,
    )  # fmt: skip
    return sim, emccdcal.calibrate(sim.manifest, progress=False)


def _z(ds, outdir):
    truth = tifffile.imread(outdir / "truth-e_per_adu.tif")
    return ((ds.e_per_adu.values - truth) / ds.e_per_adu_se.values).ravel()


def _exported_channel(ds, name, out):
    """The channel ``name`` of the maps' OME-TIFF export of ``ds`` (written to ``out``)."""
    import xml.etree.ElementTree as ET

    (path,) = emccdcal.export_calibration(ds, "ome-tiff", out)
    with tifffile.TiffFile(path) as tif:
        names = [
            c.get("Name")
            for c in ET.fromstring(tif.ome_metadata).iter()
            if c.tag.endswith("Channel")
        ]
        return tif.asarray()[names.index(name)]


def test_the_rounding_switch_is_seamless():
    """Either side of :data:`ROUNDING_BELOW` the two models are one distribution: the
    rounded one with analog σ just below it, and the density at the integers with the
    dark counts' SD, sqrt(σ² + 1/12), just above it, differ by less than 1e-7 nats per
    frame (Kullback–Leibler), on a comb (1 e⁻ = 9 ADU) and off it."""
    sigma = adc.ROUNDING_BELOW - 1e-9
    sd = np.sqrt(sigma**2 + 1 / 12)
    assert adc.rounds(True, sigma) and not adc.rounds(True, sd)
    for E, phi in ((3.0, 0.11), (400.0, 0.46)):
        mean = 100 + E / phi
        width = 12 * np.sqrt(E / phi**2 + 4) + 20
        k = np.arange(int(max(mean - width, 0)), int(mean + width))
        p = noise.pmf(k, E, 1.0, phi, 100.3, sigma, em_model="gamma")
        q = noise.pmf(k, E, 1.0, phi, 100.3, sd, em_model="gamma")
        keep = p > 0
        assert np.sum(p[keep] * np.log(p[keep] / q[keep])) < 1e-7


def test_the_dark_frames_give_the_analog_read_noise_with_honest_errors():
    """A dark of 0.43 ADU read noise (an sCMOS's 0.2 e⁻) is a rounded normal over one to
    three integers: its counts' SD is not σ, and their mean is off the offset by up to
    0.01 ADU. The fit recovers both, and the inverse Fisher information over n is each
    map's variance (z-scores with RMS ≈ 1 over 400 pixels)."""
    rng = np.random.default_rng(5)
    P, n, sigma = 400, 3000, 0.43
    offset = 100 + rng.random(P)
    dark = np.rint(offset + sigma * rng.standard_normal((n, P))).astype(np.uint16)
    stack = dark.reshape(n, 20, 20)
    mean, sd = stack.mean(axis=0), stack.std(axis=0, ddof=1)
    mu, s = analog_read_out(stack, mean, sd)
    cov = np.linalg.inv(adc.information(mu.ravel(), s.ravel())) / n
    z_mu = (mu.ravel() - offset) / np.sqrt(cov[:, 0, 0])
    z_s = (s.ravel() - sigma) / np.sqrt(cov[:, 1, 1])
    assert 0.8 < np.sqrt(np.mean(z_mu**2)) < 1.25
    assert 0.8 < np.sqrt(np.mean(z_s**2)) < 1.25
    assert abs(np.mean(z_s)) < 0.2  # unbiased, where the SD is biased by tens of SEs
    z_sd = (np.sqrt(np.maximum(sd.ravel() ** 2 - 1 / 12, 0)) - sigma) / np.sqrt(cov[:, 1, 1])
    assert np.sqrt(np.mean(z_sd**2)) > 1.5  # the SD, Sheppard-corrected, is off per pixel


@pytest.mark.slow
@pytest.mark.parametrize("kind,seed", [("qcmos", 11), ("scmos", 12)])
def test_a_camera_without_an_em_register_calibrates_with_honest_errors(tmp_path, kind, seed):
    """Known truth, per pixel: a qCMOS (photon numbers resolved: peaks 9.3 ADU apart,
    σ ≈ 2.5 ADU) and an sCMOS whose quiet pixels show the comb. Before the comb start and
    the profile's errors, the qCMOS's φ was an alias 7–8 % off at a tenth of its pixels
    (|z| up to 28) and the sCMOS's quiet pixels |z| up to 14."""
    sim, ds = _calibrated(tmp_path, kind, (12, 12), 1500, 3000, seed)
    assert ds.attrs["method"] == "is-adu" and ds.attrs["camera_kind"] == kind
    z = _z(ds, sim.outdir)
    assert np.all(np.isfinite(z))
    assert 0.75 < np.sqrt(np.mean(z**2)) < 1.3
    assert np.mean(np.abs(z) < 1.96) > 0.88
    assert np.max(np.abs(z)) < 4.5


def test_the_manifest_names_the_camera_kind(tmp_path):
    base = (
        'camera_kind = "scmos"\n[[acquisition]]\nframes = "a.tif"\noffset = 100\nread_noise = 1.5\n'
    )
    (tmp_path / "a.tif").write_bytes(b"")
    bad = tmp_path / "bad.toml"
    bad.write_text(base + "em_gain_setpoint = 5\n")
    with pytest.raises(
        ManifestError, match=r"acquisition 1 .*em_gain_setpoint = 5.*no EM register"
    ):
        emccdcal.read_manifest(bad)
    unknown = tmp_path / "unknown.toml"
    unknown.write_text(base.replace('"scmos"', '"cmos"'))
    with pytest.raises(ManifestError, match="camera_kind must be one of 'emccd', 'scmos'"):
        emccdcal.read_manifest(unknown)
    missing = tmp_path / "missing.toml"
    missing.write_text(base.replace('camera_kind = "scmos"\n', ""))
    with pytest.raises(ManifestError, match="missing 'em_gain_setpoint'.*camera_kind"):
        emccdcal.read_manifest(missing)


@pytest.mark.slow
def test_a_huang_folder_scans_and_calibrates_with_no_option(tmp_path):
    """``dark.tif``, ``int1.tif`` … as Huang et al.'s protocol names them: ``emccdcal
    scan`` writes a manifest of a camera without an EM register and ``emccdcal calibrate``
    fits φ from it with no option, both as a user runs them (the installed command)."""
    camera = CMOSCamera(kind="qcmos", rows=6, cols=6, frames=800, dark_frames=1500)
    sim = simulate_cmos_series(tmp_path / "sim", camera=camera, seed=4, progress=False)
    folder = tmp_path / "session"
    folder.mkdir()
    for name in ("dark", "int1", "int2", "int3", "int4"):
        (folder / f"{name}.tif").write_bytes((sim.outdir / f"{name}.tif").read_bytes())

    def run(*argv):
        done = subprocess.run(
            [sys.executable, "-m", "emccdcal", *map(str, argv)], capture_output=True, text=True
        )
        assert done.returncode == 0, done.stderr
        return done

    run("scan", folder, "-o", tmp_path / "m.toml")
    text = (tmp_path / "m.toml").read_text()
    assert 'camera_kind = "scmos"' in text and "em_gain_setpoint" not in text
    run("calibrate", tmp_path / "m.toml", "-o", tmp_path / "out", "--quiet")
    ds = emccdcal.load_result(tmp_path / "out")
    assert ds.attrs["method"] == "is-adu"
    truth = tifffile.imread(sim.outdir / "truth-e_per_adu.tif")
    assert np.max(np.abs(ds.e_per_adu.values / truth - 1)) < 0.02


@pytest.mark.slow
@pytest.mark.parametrize("kind, read_noise_e", [("scmos", None), ("qcmos", None), ("scmos", 0.3)])
def test_telegraph_pixels_are_found_at_the_stated_false_alarm_rate(kind, read_noise_e):
    """Two offset states 2 read-noise widths apart or more, switching with probability
    0.05 per frame, in 3000 dark frames: every one found (recall measured 1.0; 0.76–0.77
    at 1.5 widths), and of the one-normal pixels about the stated 1 %, also on a quiet
    sCMOS (0.3 e⁻: 0.65 ADU, where the ADC's rounding shapes the dark; a test of
    densities at the integers flagged 22 % of its one-normal pixels; recall 0.96)."""
    from emccdcal.data.telegraph import telegraph_pixels
    from emccdcal.simulate.cmos import simulate_cmos_frames

    quiet = {} if read_noise_e is None else {"read_noise_e": read_noise_e}
    camera = CMOSCamera(kind=kind, rows=40, cols=40, rts_fraction=0.1, rts_step=2.0, **quiet)
    rng = np.random.default_rng(8)
    maps = camera.maps(rng)
    dark = simulate_cmos_frames(0.0, maps, 3000, rng, rts_switch=camera.rts_switch)
    found = telegraph_pixels(dark).flagged
    truth = maps["rts_step"].ravel() > 0
    assert truth.sum() > 100
    assert found[truth].mean() >= 0.9
    assert found[~truth].mean() <= 0.02


def test_the_telegraph_tests_table_is_what_its_simulation_gives():
    """The null quantiles shipped in a table (benchmarks/telegraph_null_table.py) are
    that script's simulation, each cell from its own seed: one recomputed alone equals
    its cell to 1e-12 relative (another CPU's vector instructions may round the last
    digit otherwise), and the test reads the table's row at its frames."""
    from emccdcal.data import _telegraph_null as table
    from emccdcal.data import telegraph

    assert table.SIGMAS == telegraph._NULL_SIGMAS
    i, j = 2, 1
    rng = np.random.default_rng([table.SEED, i, j])
    again = telegraph._null_quantile(
        table.FRAMES[i], table.SIGMAS[j], table.FALSE_ALARM, rng, table.PIXELS
    )
    assert again == pytest.approx(table.QUANTILES[i][j], rel=1e-12, abs=0)
    telegraph._null_quantiles.cache_clear()
    assert telegraph._null_quantiles(table.FRAMES[i], 0.01, 0) == table.QUANTILES[i]


@pytest.mark.slow
@pytest.mark.parametrize("states", [3, 4])
def test_telegraph_pixels_of_more_than_two_states_are_found_too(states):
    """Three or four offset states 1.5 read-noise widths apart (where two states that
    close are found at 0.76–0.77): one normal against two rejects them all the same."""
    from emccdcal.data.telegraph import telegraph_pixels
    from emccdcal.simulate.cmos import simulate_cmos_frames

    camera = CMOSCamera(rows=40, cols=40, rts_fraction=0.1, rts_step=1.5, rts_states=states)
    rng = np.random.default_rng(8)
    maps = camera.maps(rng)
    dark = simulate_cmos_frames(
        0.0, maps, 3000, rng, rts_switch=camera.rts_switch, rts_states=states
    )
    found = telegraph_pixels(dark).flagged
    truth = maps["rts_step"].ravel() > 0
    assert truth.sum() > 100
    assert found[truth].mean() >= 0.9
    assert found[~truth].mean() <= 0.02


@pytest.mark.slow
@pytest.mark.parametrize("states", [2, 3, 4])
def test_a_telegraph_pixels_offset_states_are_counted(states):
    """Two, three or four offset states three read-noise widths apart (5.4 ADU, on the
    typical sCMOS): each flagged pixel's states counted right (measured: every one of 156
    on these darks and 324 on two other seeds'), none of a two-state pixel counted more;
    one-normal pixels flagged by chance counted two."""
    from emccdcal.data.telegraph import telegraph_pixels
    from emccdcal.simulate.cmos import simulate_cmos_frames

    camera = CMOSCamera(rows=40, cols=40, rts_fraction=0.1, rts_step=3.0, rts_states=states)
    rng = np.random.default_rng(1)
    maps = camera.maps(rng)
    dark = simulate_cmos_frames(
        0.0, maps, 3000, rng, rts_switch=camera.rts_switch, rts_states=states
    )
    found = telegraph_pixels(dark)
    truth = maps["rts_step"].ravel() > 0
    assert truth.sum() > 100
    assert np.mean(found.states[truth] == states) >= 0.9
    assert np.mean(found.states[truth] > states) <= 0.02
    assert np.array_equal(found.states > 1, found.flagged)
    assert np.all(found.states[found.flagged & ~truth] == 2)


@pytest.mark.slow
def test_a_calibration_marks_its_telegraph_pixels(tmp_path):
    """The flags and the offset states counted (three, four widths apart) reach the
    result, napari's layers, the report's note and the calibration the exports read; a
    level's check names telegraph pixels whose mean strays as such, not as dead or hot
    (their offset moves between the dark and the level)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sim, ds = _calibrated(
            tmp_path, "scmos", (10, 10), 400, 2000, 4, rts_fraction=0.1, rts_states=3
        )
    said = [str(w.message) for w in caught]
    (strays,) = [s for s in said if "random-telegraph pixel(s), mean more than" in s]
    named = re.findall(r"\((\d+),(\d+)\)", strays.split("median: ")[1].split(";")[0])
    assert named and all(ds.telegraph.values[int(r), int(c)] for r, c in named)
    assert not any(re.search(r"(dead|hot) pixel\(s\)", s) for s in said)
    check = [sys.executable, "-m", "emccdcal", "check", str(sim.manifest)]  # as a user runs it
    table = subprocess.run(check, capture_output=True, text=True).stdout.splitlines()
    header = next(line for line in table if "stuck" in line).split()
    assert header[-1] == "RTS"
    assert any(line.split()[0] == "int1" and line.split()[-1] == str(len(named)) for line in table)
    truth = tifffile.imread(sim.outdir / "truth-rts_step.tif") > 0
    assert truth.sum() >= 3
    flags = ds.telegraph.values.astype(bool)
    assert flags[truth].all() and flags[~truth].sum() <= 2
    states = ds.telegraph_states.values
    assert np.all(states[truth] == 3) and np.all(states[~flags] == 1)
    from emccdcal.napari._layers import result_layers

    layers = {kw["name"]: data for data, kw, _ in result_layers(ds)}
    assert np.array_equal(layers["telegraph pixels"] == 1, flags)
    assert np.array_equal(layers["telegraph states"], states)
    from emccdcal.report.sections import _flags_html

    (note,) = [n for n in _flags_html(ds) if n.startswith("<p class=note>Random-telegraph")]
    assert f"{int(flags.sum())} of 100" in note
    assert f"offset states: 3 at {int(np.sum(states == 3))} pixels" in note
    assert np.array_equal(emccdcal.load_calibration(ds).telegraph_states, states)


@pytest.mark.slow
def test_a_calibration_marks_its_hot_pixels_where_it_measures_the_dark_current(tmp_path):
    """Darks at four exposures (the photon-free path) of an sCMOS whose dark current is
    log-normal, a tenth of its pixels 30 times hotter: each marked (``hot``), few
    others (a log-normal population of spread 0.5 crosses the threshold at 0.7 %: here
    0.7 pixels expected), the threshold recorded; the report, napari and the OME-TIFF's
    masks say which. No dark current measured, no ``hot``."""

    sim = simulate_cmos_series(
        tmp_path / "s", kind="scmos", rows=10, cols=10, frames=600, dark_current=30.0,
        dark_exposures_s=(0.01, 0.5, 1.0, 2.0), hot_fraction=0.1, seed=24, progress=False,
    )  # fmt: skip
    ds = emccdcal.calibrate(sim.manifest, progress=False)
    truth = tifffile.imread(sim.outdir / "truth-hot.tif") > 0
    assert truth.sum() >= 3
    flags = ds.hot.values.astype(bool)
    assert flags[truth].all() and flags[~truth].sum() <= 3
    rate = ds.dark_current.values
    assert np.nanmedian(rate) < ds.hot.attrs["threshold_e_per_s"] < np.nanmin(rate[flags])
    from emccdcal.napari._layers import result_layers
    from emccdcal.report.sections import _flags_html

    layer = {kw["name"]: data for data, kw, _ in result_layers(ds)}["hot pixels"]
    assert np.array_equal(layer == 1, flags)
    assert any(
        "Hot pixels" in note and f"{int(flags.sum())} of 100" in note for note in _flags_html(ds)
    )
    assert np.array_equal(_exported_channel(ds, "hot", tmp_path / "ome") == 1, flags)
    _, plain = _calibrated(tmp_path / "p", "scmos", (4, 4), 200, 400, 3)
    assert "hot" not in plain and "dark_current" not in plain


@pytest.mark.slow
def test_a_movie_of_a_camera_without_an_em_register_converts_at_its_one_setpoint(tmp_path):
    """``apply`` of a movie that records no set-point, by the calibration of a camera
    without an EM register (set-point 1): photoelectrons per pixel and frame, the
    level's within 2 %. An EMCCD's 1× calibration still asks for the movie's set-point."""
    sim, ds = _calibrated(tmp_path / "s", "qcmos", (6, 6), 600, 1200, 9)
    movie = tmp_path / "movie.tif"
    tifffile.imwrite(movie, tifffile.imread(sim.outdir / "int3.tif"))
    out = emccdcal.apply_calibration(ds, movie, tmp_path / "e.tif", progress=False)
    electrons = tifffile.imread(out)
    assert electrons.mean() == pytest.approx(sim.truth["levels"]["int3.tif"], rel=0.02)
    ds.attrs["camera_kind"] = "emccd"
    with pytest.raises(emccdcal.errors.OptionError, match="give --setpoint G"):
        emccdcal.apply_calibration(ds, movie, tmp_path / "e2.tif", progress=False)


def test_simulate_cmos_writes_a_series_that_names_its_camera(tmp_path):
    from emccdcal import cli

    out = tmp_path / "sim"
    argv = ["simulate", "cmos", "-o", str(out), "--camera-kind", "qcmos", "--rows", "3"]
    assert cli.main([*argv, "--cols", "4", "--frames", "50", "--seed", "2", "-q"]) == 0
    m = emccdcal.read_manifest(out / "manifest.toml")
    assert m.camera_kind == "qcmos" and m.shape == (3, 4) and m.setpoints == (1.0,)
    truth = tifffile.imread(out / "truth-e_per_adu.tif")
    assert truth.shape == (3, 4) and abs(np.median(truth) / 0.107 - 1) < 0.05
    # a second run into the same folder is refused without --overwrite
    assert cli.main([*argv, "--cols", "4", "--frames", "50", "--seed", "2", "-q"]) == 2


def test_a_hot_pixel_in_darks_at_one_exposure_is_flagged_as_not_one_normal(tmp_path):
    """``simulate cmos --exposure`` puts the dark current's signal in the dark and every
    level; darks at one exposure measure no dark current, and a hot pixel's dark, a
    Poisson mixture, fails the telegraph test's one normal (docs/cmos.md, "Hot pixels":
    0.86 of them at a median 1.3 e⁻ over eight cameras)."""
    from emccdcal import cli

    out = tmp_path / "sim"
    argv = ["simulate", "cmos", "-o", str(out), "--rows", "10", "--cols", "10", "--frames", "50"]
    argv += ["--dark-frames", "3000", "--dark-current", "0.05", "--exposure", "1"]
    assert cli.main([*argv, "--hot-fraction", "0.1", "--seed", "24", "-q"]) == 0
    rate = tifffile.imread(out / "truth-dark_current.tif")
    hot = tifffile.imread(out / "truth-hot.tif") > 0
    phi = tifffile.imread(out / "truth-e_per_adu.tif")
    excess = tifffile.imread(out / "dark.tif").mean(axis=0) - tifffile.imread(
        out / "truth-offset.tif"
    )
    # the dark's mean above the offset is the dark signal (ADU), within its noise
    np.testing.assert_allclose(excess[hot], rate[hot] / phi[hot], atol=0.25)
    flagged = emccdcal.read_manifest(out / "manifest.toml").acquisitions[0].dark_telegraph
    assert hot.sum() >= 5 and flagged[hot].mean() >= 0.7 and flagged[~hot].mean() < 0.15
    # the photon-free path's exposures are its darks': a lit series' exposure refused
    both = [*argv, "--dark-exposures", "0.1,1", "-o", str(tmp_path / "both"), "-q"]
    assert cli.main(both) == 2


def _andor(src, dst, model, frames):
    """A multi-frame SIF of ``frames`` whose header names another Andor model."""
    from camera_files import multi_frame_sif

    path = multi_frame_sif(src, dst, frames)
    raw = path.read_bytes()
    assert raw.count(b"DU897_BV") >= 1
    path.write_bytes(raw.replace(b"DU897_BV", model.encode()))
    return path


@pytest.mark.slow
@pytest.mark.parametrize(
    "model, kind, gain",
    [("DU897_BV", "emccd", 56.0), ("DU420_BV", "ccd", None), ("DH734_BV", "iccd", None)],
)
def test_andor_files_record_their_kind_and_no_em_gain_without_a_register(
    tmp_path, model, kind, gain
):
    """An iDus's (CCD) and an iStar's (intensified CCD) gain field is not an EM set-point:
    it was read as one (2.0, 180, 2500 on sif_parser's files). A folder of iDus files
    scans as a camera without an EM register; an iStar's is refused in one line."""
    from test_formats import SIF

    pytest.importorskip("sif_parser")
    manifest = _huang_folder_of(
        tmp_path / "session", ".sif", (10, 256, 256), 1, kind, gain,
        lambda path, frames: _andor(SIF / "test.sif", path, model, frames),
    )  # fmt: skip
    if manifest is None:
        return
    wrong = tmp_path / "wrong.toml"
    wrong.write_text(manifest.read_text().replace('camera_kind = "ccd"', 'camera_kind = "scmos"'))
    wrong.replace(manifest.parent / "wrong.toml")
    with pytest.raises(ManifestError, match=r"camera_kind = 'scmos', but .*records a ccd camera"):
        emccdcal.read_manifest(manifest.parent / "wrong.toml")


@pytest.mark.parametrize(
    "model, kind, gain",
    [
        ("ProEM-HS: 512BX3", "emccd", 300.0),
        ("KURO: 2048B", "scmos", None),
        ("PIXIS: 1024B", "ccd", None),
        ("PI-MAX4: 1024i", "iccd", None),
    ],
)
def test_spe_files_record_their_kind_and_no_em_gain_without_a_register(tmp_path, model, kind, gain):
    """LightField's SPE files name the camera's model: a ProEM's EM gain is its set-point;
    a KURO's (sCMOS) or a PIXIS's (CCD) gain field is none, and a folder of their files
    named as Huang et al. name them scans as a camera without an EM register, with no
    set-point asked; a PI-MAX's (intensified) is refused in one line."""
    from camera_files import write_spe

    _huang_folder_of(
        tmp_path / "session", ".spe", (4, 8, 8), 2, kind, gain,
        lambda path, frames: write_spe(path, frames.astype(np.uint16), em_gain=300, model=model),
    )  # fmt: skip


@pytest.mark.parametrize(
    "detector_type, model, kind",
    [
        ("CMOS", "C15550-20UP", "qcmos"),  # the model says more than the type
        ("CMOS", "Camera 7", "scmos"),
        ("CCD", "Camera 7", "ccd"),
        ("EMCCD", "Camera 7", "emccd"),
        ("IntensifiedCCD", "Camera 7", "iccd"),
    ],
)
def test_an_ome_tiff_without_micro_manager_records_its_kind_from_its_detector(
    tmp_path, detector_type, model, kind
):
    """An OME-TIFF of another writer (Bio-Formats, a vendor's export) carries no
    Micro-Manager properties; its OME-XML's detector says the camera: the model where it
    is one known, else the detector's type. A folder of them named as Huang et al. name
    them scans with no set-point asked (an EMCCD's would need one; an intensified
    camera's is refused)."""
    from camera_files import write_ome_tiff

    _huang_folder_of(
        tmp_path / "session", ".ome.tif", (12, 8, 8), 3, kind, None,
        lambda path, frames: write_ome_tiff(
            path, frames.astype(np.uint16), detector_type=detector_type, model=model
        ),
    )  # fmt: skip


def test_a_stuck_dark_pixel_is_left_out_and_marked_and_a_constant_dark_refused(tmp_path):
    """A pixel whose dark counts never change (dead, or stuck at one value) has no read
    noise the dark can measure: it is left out of the fit (NaN, not converged) with one
    warning naming it, marked ``stuck`` in the result, named in the report, shown in
    napari and carried as a mask by the OME-TIFF export, and the other pixels are fitted
    as without it. (Until 2026-11-30 it refused the whole manifest; before that a rounded
    normal as narrow as one count fitted it: 0.037 ADU, a number of the optimizer's.) A
    dark constant at every pixel is no dark: refused in one line naming the file."""
    import shutil

    from emccdcal.errors import LeftOutWarning
    from emccdcal.napari._layers import result_layers
    from emccdcal.report.sections import _flags_html

    sim = simulate_cmos_series(
        tmp_path / "clean", kind="scmos", rows=4, cols=4, frames=300, dark_frames=300,
        seed=12, progress=False,
    )  # fmt: skip
    reference = emccdcal.calibrate(sim.manifest, progress=False)
    folder = tmp_path / "stuck"
    shutil.copytree(tmp_path / "clean", folder)
    dark = tifffile.imread(folder / "dark.tif")
    dark[:, 2, 3] = dark[0, 2, 3]
    tifffile.imwrite(folder / "dark.tif", dark)
    with pytest.warns(
        LeftOutWarning, match=r"1 of 16 pixel.*dark frames that never change.*\(2, 3\)"
    ):
        ds = emccdcal.calibrate(folder / "manifest.toml", progress=False)
    stuck = np.zeros((4, 4), dtype=np.int8)
    stuck[2, 3] = 1
    np.testing.assert_array_equal(ds.stuck.values, stuck)
    assert not reference.stuck.values.any()
    assert not ds.converged.values[2, 3] and np.isnan(ds.e_per_adu.values[2, 3])
    others = stuck == 0
    np.testing.assert_array_equal(ds.converged.values[others], reference.converged.values[others])
    np.testing.assert_allclose(
        ds.e_per_adu.values[others], reference.e_per_adu.values[others], rtol=1e-6
    )
    layer = {kw["name"]: data for data, kw, _ in result_layers(ds)}["stuck pixels"]
    np.testing.assert_array_equal(layer, stuck)
    assert any(
        "Stuck pixels" in note and "1 of 16" in note and "(2, 3)" in note
        for note in _flags_html(ds)
    )
    np.testing.assert_array_equal(_exported_channel(ds, "stuck", tmp_path / "ome"), stuck)
    assert emccdcal.load_calibration(ds).stuck[2, 3]
    # the sampler, asked for that pixel, says so in one line (not a deep OverflowError)
    with pytest.raises(emccdcal.errors.OptionError, match=r"read noise 0 at pixel \(2, 3\)"):
        emccdcal.sample_posterior(folder / "manifest.toml", "is-adu", [(2, 3)], seed=0)
    dark[:] = 101  # a dark constant at every pixel
    tifffile.imwrite(folder / "dark.tif", dark)
    with pytest.raises(
        ManifestError, match=r"dark\.tif': dark stack's counts never change at any pixel"
    ):
        emccdcal.read_manifest(folder / "manifest.toml")


def _huang_folder_of(folder, suffix, shape, seed, kind, gain, write):
    """``dark``, ``int1`` and ``int2`` stacks of ``shape`` written by ``write(path,
    frames)`` into ``folder``: each records the camera's ``kind`` and ``gain`` (its EM
    set-point, or None); an EMCCD's folder stops there (None), an intensified camera's
    is refused by ``scan`` in one line (None), any other scans as a camera without an
    EM register, the kind from the files' model: its manifest."""
    from emccdcal.data.stacks import stack_settings

    rng = np.random.default_rng(seed)
    folder.mkdir()
    for name, level in (("dark", 0.0), ("int1", 50.0), ("int2", 200.0)):
        write(folder / f"{name}{suffix}", np.rint(100 + level + 2 * rng.standard_normal(shape)))
    s = stack_settings(folder / f"int1{suffix}")
    assert (s.camera_kind, s.em_gain_setpoint) == (kind, gain)
    if kind == "emccd":
        return None
    if kind == "iccd":
        with pytest.raises(
            emccdcal.errors.InputError, match=rf"dark\{suffix}' is of an intensified"
        ):
            emccdcal.scan(folder)
        return None
    manifest = emccdcal.scan(folder)
    assert f'camera_kind = "{kind}"   # the files\' model says so' in manifest.read_text()
    assert emccdcal.read_manifest(manifest).camera_kind == kind
    return manifest


@pytest.mark.parametrize("sigma", [0.45, 0.9, 3.0])
def test_the_plan_asks_for_the_darks_a_read_noise_variance_needs(sigma):
    """The dark frames the planner asks for a 3 % SE of σ² give it: the spread over 600
    simulated pixels of the darks' fitted σ² is 3 % within its own error (a rounded
    normal's below 2 ADU, which needs more frames than a normal's)."""
    from emccdcal.acquire.plan import darks_for_read_noise, plan

    n = darks_for_read_noise(sigma, 3.0)
    rng = np.random.default_rng(int(10 * sigma))
    offset = 100 + rng.random(600)
    dark = np.rint(offset + sigma * rng.standard_normal((n, 600))).astype(np.uint16)
    stack = dark.reshape(n, 20, 30)
    mu, s = analog_read_out(stack, stack.mean(axis=0), stack.std(axis=0, ddof=1))
    if not adc.rounds(True, sigma):
        s = np.sqrt(s**2 - 1 / 12)  # the counts' SD there: the analog σ² is SD² − 1/12
    spread = np.std(s.ravel() ** 2 / sigma**2 - 1)
    assert spread == pytest.approx(0.03, rel=0.15)
    p = plan(
        method="is-adu", e_per_adu=0.46, read_noise=sigma, offset=100, target_se=5,
        read_noise_target_se=3.0,
    )  # fmt: skip
    assert p.dark_frames >= n and p.read_noise_variance_se <= 3.0


@pytest.mark.slow
def test_gdsc_smlms_per_pixel_camera_model_is_written_and_audited_pixel_by_pixel(tmp_path):
    """A camera without an EM register exports gdsc-smlm's per-pixel camera model (Bias,
    Gain, Variance slices, the sensor origin as ImageJ's) and its JSON names it; the audit
    reads it back pixel by pixel: agreeing everywhere, and one pixel's gain 5 % off named."""
    sim, ds = _calibrated(tmp_path / "s", "scmos", (5, 6), 300, 600, 3)
    files = emccdcal.export_calibration(ds, "gdsc", tmp_path / "gdsc")
    model = next(f for f in files if f.name == "gdsc-camera-model.tif")
    with tifffile.TiffFile(model) as tif:
        meta, data = tif.imagej_metadata, tif.asarray()
    assert meta["Labels"] == ["Bias", "Gain", "Variance"] and meta["slices"] == 3
    assert data.shape == (3, 5, 6) and data.dtype == np.float32
    np.testing.assert_allclose(data[1], 1 / ds.e_per_adu.values, rtol=1e-6)
    sigma = ds.read_noise.isel(level=0).values
    np.testing.assert_allclose(data[2], adc.count_variance(sigma, True), rtol=1e-6)
    doc = __import__("json").loads((tmp_path / "gdsc" / "gdsc-calibration.json").read_text())
    assert doc["cameraCalibration"]["cameraModelName"] == "gdsc-camera-model"
    assert doc["cameraCalibration"]["cameraType"] == "SCMOS"
    (audit,) = emccdcal.audit(model, ds)
    assert audit.ok and any(row["field"] == "per pixel" for row in audit.rows)
    data[1, 2, 3] *= 1.05
    tifffile.imwrite(model, data, imagej=True, metadata={**meta, "axes": "ZYX"})
    (audit,) = emccdcal.audit(model, ds)
    assert not audit.ok
    assert "at 1 of 30 pixels" in audit.problems[0] and "(2, 3)" in audit.problems[0]


@pytest.mark.parametrize("origin", [(0, 0), (0, 10), (10, 0), (5, 5), (3, 100)])
@pytest.mark.parametrize("shape", [(8, 8), (20, 4)])
def test_smites_roi_reads_back_as_the_region_meant(origin, shape):
    """smite takes an ROI whose 2nd and 4th values exceed its 1st and 3rd as the older
    [YStart, YEnd, XStart, XEnd] and reorders it: the writer's order survives that."""
    from emccdcal.export.toolfiles.smite import origin_of, roi_of

    roi = roi_of(origin, shape)
    assert origin_of(roi) == origin
    y0, x0, y1, x1 = (
        roi if not (roi[1] > roi[0] and roi[3] > roi[2]) else [roi[0], roi[2], roi[1], roi[3]]
    )
    assert (y1 - y0 + 1, x1 - x0 + 1) == shape


@pytest.mark.slow
def test_smites_calibration_file_is_written_and_audited_pixel_by_pixel(tmp_path):
    from scipy.io import loadmat

    sim, ds = _calibrated(tmp_path / "s", "qcmos", (4, 5), 300, 600, 4)
    (path,) = emccdcal.export_calibration(ds, "smite", tmp_path / "smite")
    params = loadmat(path, squeeze_me=True, struct_as_record=False)["Params"]
    np.testing.assert_allclose(params.Gain, 1 / ds.e_per_adu.values, rtol=1e-6)
    np.testing.assert_allclose(params.CCDOffset, ds.offset.isel(level=0).values, rtol=1e-6)
    assert list(params.CameraObj.ROI) == [1, 1, 4, 5]
    (audit,) = emccdcal.audit(path, ds)
    assert audit.ok and audit.reading.tool == "smite"
    from scipy.io import savemat

    raw = loadmat(path, squeeze_me=True, struct_as_record=False)["Params"]
    gain = np.array(raw.Gain, dtype=np.float32)
    gain[1, 2] *= 1.1
    fields = {k: getattr(raw, k) for k in ("CCDGain", "CCDOffset", "CCDVar")}
    savemat(path, {"Params": {**fields, "Gain": gain, "CameraObj": {"ROI": [1, 1, 4, 5]}}})
    (audit,) = emccdcal.audit(path, ds)
    assert not audit.ok and "at 1 of 20 pixels" in audit.problems[0]
    assert "(1, 2)" in audit.problems[0]


@pytest.mark.slow
def test_smaps_correction_file_is_audited_pixel_by_pixel(tmp_path):
    from scipy.io import loadmat, savemat

    sim, ds = _calibrated(tmp_path / "s", "scmos", (4, 5), 300, 600, 6)
    files = emccdcal.export_calibration(ds, "smap", tmp_path / "smap")
    path = next(f for f in files if f.name == "smap-correction.mat")
    (audit,) = emccdcal.audit(path, ds)
    assert audit.ok and audit.reading.where == "camera correction"
    raw = loadmat(path)
    maps = {k: np.array(raw[k]) for k in ("offsetmap", "gainmap", "varmap")}
    maps["gainmap"][3, 1] *= 1.1
    savemat(path, maps)
    (audit,) = emccdcal.audit(path, ds)
    assert not audit.ok and "at 1 of 20 pixels" in audit.problems[0]
    assert "(3, 1)" in audit.problems[0]


def test_an_ome_tiff_of_the_maps_with_their_errors_is_written_and_audited(tmp_path):
    """The plain OME-TIFF: every map with its SE, the channels named, the telegraph mask;
    the offset's and read noise's SEs honest against the truth; audited pixel by pixel."""
    import json
    import xml.etree.ElementTree as ET

    sim, ds = _calibrated(tmp_path / "s", "qcmos", (6, 6), 300, 1500, 3, rts_fraction=0.15)
    truth = {k: tifffile.imread(sim.outdir / f"truth-{k}.tif") for k in ("offset", "read_noise")}
    rts = tifffile.imread(sim.outdir / "truth-rts_step.tif") > 0
    quiet = ~rts & ds.converged.values.astype(bool)
    for name in ("offset", "read_noise"):  # the maps' own errors, from the dark frames' count
        z = (ds[name].isel(level=0).values - truth[name]) / ds[f"{name}_se"].isel(level=0).values
        assert 0.5 < np.sqrt(np.mean(z[quiet] ** 2)) < 1.6, name
    (path,) = emccdcal.export_calibration(ds, "ome-tiff", tmp_path / "ome")
    with tifffile.TiffFile(path) as tif:
        root = ET.fromstring(tif.ome_metadata)
        data = tif.asarray()
    names = [c.get("Name") for c in root.iter() if c.tag.endswith("Channel")]
    described = json.loads(next(e.text for e in root.iter() if e.tag.endswith("Description")))
    maps = dict(zip(names, data))
    assert data.shape == (len(names), 6, 6) and described["units"]["read_noise_variance"] == "ADU2"
    ok = ds.converged.values.astype(bool)
    np.testing.assert_allclose(maps["e_per_adu"][ok], ds.e_per_adu.values[ok], rtol=1e-6)
    np.testing.assert_allclose(maps["adu_per_e_se"][ok], ds.adu_per_e_se.values[ok], rtol=1e-5)
    sigma, sigma_se = ds.read_noise.isel(level=0).values, ds.read_noise_se.isel(level=0).values
    variance = adc.count_variance(sigma, True)
    np.testing.assert_allclose(maps["read_noise_variance"][ok], variance[ok], rtol=1e-6)
    np.testing.assert_allclose(
        maps["read_noise_variance_se"][ok], (2 * sigma * sigma_se)[ok], rtol=1e-5
    )
    np.testing.assert_allclose(
        maps["read_noise_variance_e"][ok], (variance * ds.e_per_adu.values**2)[ok], rtol=1e-5
    )
    assert np.array_equal(maps["telegraph"] == 1, ds.telegraph.values.astype(bool))
    assert np.array_equal(maps["telegraph_states"], ds.telegraph_states.values)
    (audit,) = emccdcal.audit(path, ds)
    assert audit.ok and audit.reading.tool == "ome-tiff"
    data[names.index("offset"), 2, 4] += 5.0  # a baseline 5 ADU off at one pixel
    tifffile.imwrite(path, data, ome=True, metadata={
        "axes": "CYX", "Channel": {"Name": names}, "Description": json.dumps(described),
    })  # fmt: skip
    (audit,) = emccdcal.audit(path, ds)
    assert not audit.ok and "(2, 4)" in " ".join(audit.problems)


def test_decode_takes_an_scmos_as_its_model_without_em_gain(tmp_path):
    import yaml

    sim, ds = _calibrated(tmp_path / "s", "scmos", (4, 4), 300, 600, 5)
    (path,) = emccdcal.export_calibration(ds, "decode", tmp_path / "decode")
    camera = yaml.safe_load(path.read_text())["Camera"]
    assert camera["em_gain"] is None
    assert camera["e_per_adu"] == pytest.approx(float(np.median(ds.e_per_adu.values)), rel=1e-6)
    (audit,) = emccdcal.audit(path, ds)
    assert audit.ok


def _photon_free(folder, kind, shape, frames, seed, exposures=(0.01, 0.5, 1.0, 2.0)):
    rows, cols = shape
    return simulate_cmos_series(
        folder, kind=kind, rows=rows, cols=cols, frames=frames, dark_current=30.0,
        dark_exposures_s=exposures, seed=seed, progress=False,
    )  # fmt: skip


@pytest.mark.slow
def test_the_photon_free_path_gives_phi_and_the_dark_current_with_honest_errors(tmp_path):
    """Darks at four exposures, no light (Diekmann et al. 2022): the thermal signal's
    growth is the signal; φ and the dark current unbiased with honest SEs."""
    sim = _photon_free(tmp_path, "scmos", (10, 10), 1000, 21)
    ds = emccdcal.calibrate(sim.manifest, progress=False)
    assert ds.attrs["photon_free"] == 1 and ds.dark_current.attrs["units"] == "e-/s"
    ok = ds.converged.values.astype(bool)
    assert ok.mean() > 0.95
    for name in ("e_per_adu", "dark_current"):
        truth = tifffile.imread(sim.outdir / f"truth-{name}.tif")
        z = ((ds[name].values - truth) / ds[f"{name}_se"].values)[ok]
        assert abs(z.mean()) < 0.4 and 0.7 < np.sqrt(np.mean(z**2)) < 1.35, name
    assert np.mean(ds.dark_current_pvalue.values[ok] < 0.01) <= 0.05  # linear in exposure
    from emccdcal.napari._layers import result_layers

    layer = {kw["name"]: data for data, kw, _ in result_layers(ds)}["dark current (e-/s)"]
    np.testing.assert_array_equal(layer, ds.dark_current.values)


def test_darks_at_two_exposures_give_the_dark_current_of_a_lit_series(tmp_path):
    """Two acquisitions whose darks were recorded at 0.01 s and 0.5 s: the dark current
    from the darks alone (the frames' own signal is not dark)."""
    sim = _photon_free(tmp_path, "scmos", (6, 6), 600, 22)
    manifest = tmp_path / "lit.toml"
    manifest.write_text(
        'camera_kind = "scmos"\n\n'
        '[[acquisition]]\nframes = "dark-1s.tif"\ndark = "dark-0.01s.tif"\n'
        "exposure_s = 1.0\ndark_exposure_s = 0.01\n\n"
        '[[acquisition]]\nframes = "dark-2s.tif"\ndark = "dark-0.5s.tif"\n'
        "exposure_s = 2.0\ndark_exposure_s = 0.5\n"
    )
    ds = emccdcal.calibrate(manifest, progress=False)
    assert "photon_free" not in ds.attrs and "dark_current_pvalue" not in ds  # two points
    truth = tifffile.imread(sim.outdir / "truth-dark_current.tif")
    ok = ds.converged.values.astype(bool)
    z = ((ds.dark_current.values - truth) / ds.dark_current_se.values)[ok]
    assert 0.5 < np.sqrt(np.mean(z**2)) < 1.6


def test_a_dark_holding_electrons_under_a_resolved_comb_is_warned(tmp_path):
    """A qCMOS's reference dark at 0.5 ms with 30 e-/s: about 0.015 e⁻ in it, a fifth of
    the read-noise variance (0.27 e⁻)², biases φ (docs/cmos.md): said, with the cure."""
    sim = _photon_free(tmp_path, "qcmos", (4, 4), 400, 23, exposures=(0.0005, 0.5, 1.0))
    with pytest.warns(FitWarning):
        ds = emccdcal.calibrate(sim.manifest, progress=False)
    said = [w for w in ds.attrs["warnings"] if "dark signal" in w]
    assert len(said) == 1 and "record the dark at a shorter exposure" in said[0]


@pytest.mark.parametrize(
    "extra, says",
    [
        ("", "needs 'exposure_s' and 'dark_exposure_s'"),
        ("exposure_s = 0.5\ndark_exposure_s = 1.0\n", "must be longer than its dark's"),
        ("exposure_s = -1\n", "'exposure_s' must be a time in seconds > 0"),
    ],
)
def test_a_photon_free_manifest_without_its_exposures_is_one_line(tmp_path, extra, says):
    manifest = tmp_path / "m.toml"
    manifest.write_text(
        'camera_kind = "scmos"\nlight = false\n\n[[acquisition]]\nframes = "a.tif"\n'
        f'dark = "d.tif"\n{extra}'
    )
    with pytest.raises(ManifestError, match=says):
        emccdcal.read_manifest(manifest)


def test_a_micro_manager_folder_of_an_orca_quest_scans_as_a_qcmos_with_its_exposures(tmp_path):
    """Huang's folder recorded through Micro-Manager's DCAM adapter: the model names the
    camera a qCMOS, the frames' exposure goes into the manifest, no option is needed."""
    import tomllib

    from camera_files import write_micromanager_tiff

    sim = simulate_cmos_series(
        tmp_path / "sim", kind="qcmos", rows=4, cols=5, frames=200, seed=24, progress=False
    )
    folder = tmp_path / "session"
    folder.mkdir()
    for name in ("dark", "int1", "int2", "int3"):
        frames = tifffile.imread(sim.outdir / f"{name}.tif")
        write_micromanager_tiff(
            folder / f"{name}.ome.tif", frames, style="hamamatsu", exposure_ms=20.0, roi="0-0-5-4"
        )
    done = subprocess.run(
        [sys.executable, "-m", "emccdcal", "scan", str(folder), "-q"],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr
    text = (folder / "manifest.toml").read_text()
    doc = tomllib.loads(text)
    assert doc["camera_kind"] == "qcmos" and "the files' model says so" in text
    assert all(a["exposure_s"] == 0.02 for a in doc["acquisition"])
    assert all("em_gain_setpoint" not in a for a in doc["acquisition"])
    ds = emccdcal.calibrate(folder / "manifest.toml", progress=False)
    assert ds.attrs["method"] == "is-adu" and ds.attrs["camera_kind"] == "qcmos"


@pytest.mark.slow
def test_bright_levels_leave_no_pixel_overconfident(tmp_path):
    """Levels of thousands of e⁻ (what the planner picks for an sCMOS) on pixels of 0.6–1
    e⁻: the likelihood's ripples, 1/E apart and a millionth of a nat deep, had given
    SEs 20 times too small (|z| up to 32); the envelope's fit gives the error."""
    sim, ds = _calibrated(
        tmp_path, "scmos", (6, 6), 300, 50, 25, read_noise_e=1.0,
        levels=(800.0, 6400.0, 26000.0),
    )  # fmt: skip
    z = _z(ds, sim.outdir)[ds.converged.values.ravel()]
    assert z.size > 30 and np.abs(z).max() < 5
    assert abs(z.mean()) < 0.4 and 0.7 < np.sqrt(np.mean(z**2)) < 1.35


def test_a_folder_of_darks_at_several_exposures_scans_as_the_photon_free_path(tmp_path):
    """Darks only, their exposures in their names: scan takes the shortest as the others'
    dark and writes light = false; calibrate then needs no option."""
    import tomllib

    sim = _photon_free(tmp_path / "darks", "scmos", (4, 4), 300, 26, exposures=(0.01, 1.0, 2.0))
    manifest = tmp_path / "scanned.toml"
    done = subprocess.run(
        [sys.executable, "-m", "emccdcal", "scan", str(sim.outdir), "-o", str(manifest), "-q"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    doc = tomllib.loads(manifest.read_text())
    assert doc["light"] is False
    assert [(a["exposure_s"], a["dark_exposure_s"]) for a in doc["acquisition"]] == [
        (1.0, 0.01),
        (2.0, 0.01),
    ]
    ds = emccdcal.calibrate(manifest, progress=False)
    assert ds.attrs["photon_free"] == 1 and np.isfinite(ds.dark_current.values).any()


def test_the_alias_of_a_comb_is_its_nearest_mirror():
    """Counts at the integers give the same cos 2πφk for φ and k − φ: an sCMOS's 0.466
    e⁻/ADU and 0.534 are one comb, 1.4 and 1.6 too; a qCMOS's 0.107 has none near."""
    from emccdcal.fit import comb

    np.testing.assert_allclose(comb.mirror(np.array([0.466, 0.534, 1.4])), [0.534, 0.466, 1.6])
    assert np.isnan(comb.mirror(np.array([0.107]))).all()
    k = np.arange(200)
    for phi in (0.466, 1.4):
        np.testing.assert_allclose(
            np.cos(2 * np.pi * phi * k),
            np.cos(2 * np.pi * comb.mirror(np.array([phi]))[0] * k),
            atol=1e-9,
        )


@pytest.mark.slow
def test_a_resolved_combs_dimmest_level_is_climbed_to_its_top(tmp_path):
    """A qCMOS pixel of 0.25 e⁻ read noise on the planner's ladder (0.5 … 40.5 e⁻, 200
    frames a level, 400 darks). At 0.5 e⁻ the dimmest level's hill in ln φ is a few per
    cent wide and the grid over it a quarter a step (E < 1): its best point lay 26 %
    from the truth, in another basin of the next level, and the fit ended at an alias
    40 % off (z = 7.7, its goodness of fit at p < 0.01 on three levels). Found in the
    plan's check (seed 7, pixel (4, 2)); each grid point is now climbed to its basin's
    top before the brighter levels are added. The pixel and its neighbours, cut out."""
    sim = simulate_cmos_series(
        tmp_path / "sim", kind="qcmos", rows=10, cols=10, frames=200, dark_frames=400,
        levels=(0.5, 1.5, 4.5, 13.5, 40.5), seed=7, progress=False,
    )  # fmt: skip
    cut = tmp_path / "cut"
    cut.mkdir()
    region = np.s_[3:6, 1:4]
    for path in sim.outdir.glob("*.tif"):
        stack = tifffile.imread(path)
        tifffile.imwrite(cut / path.name, stack[(Ellipsis,) + region])
    (cut / "manifest.toml").write_text(sim.manifest.read_text())
    ds = emccdcal.calibrate(cut / "manifest.toml", progress=False)
    z = _z(ds, cut).reshape(3, 3)
    print(f"z of the pixel {z[1, 1]:.2f}; of the nine {np.round(z, 2).tolist()}")
    assert np.abs(z).max() < 4
    assert ds.gof_pvalue.values[:, 1, 1].min() > 1e-3


def _cut_pixel(sim, out, pixel):
    """The series of ``sim`` cut down to one pixel (row, col), written to ``out``: its
    manifest."""
    out.mkdir()
    r, c = pixel
    for path in sim.outdir.glob("*.tif"):
        tifffile.imwrite(out / path.name, tifffile.imread(path)[..., r : r + 1, c : c + 1])
    (out / "manifest.toml").write_text(sim.manifest.read_text())
    return out / "manifest.toml"


@pytest.mark.slow
@pytest.mark.parametrize("seed, pixel", [(35, (6, 1)), (28, (6, 7))])
def test_nearly_tied_basins_of_a_resolved_comb_widen_the_error(tmp_path, seed, pixel):
    """A qCMOS of 0.5 e⁻ read noise (levels up to 10 e⁻): at 0.45 e⁻ a pixel's likelihood
    can hold two basins 6–8 % apart in φ within a nat of each other, each 1 % wide, on a
    grid whose step (2.7 %) is wider than either. The first pixel's rival top stood 0.2
    nats below the fit's but no envelope could be drawn through two tops; the second's
    true basin lay between two points of the grid, unseen. Both had ended at the other
    basin with their one basin's curvature as the SE: z = −12.5 and −6.9 (found in a
    study of 20 cameras, 9 pixels of 2000 beyond |z| = 6). Every point of so coarse a
    grid is now climbed, and the SE reaches the far edge of the profile likelihood's
    95 % set."""
    camera = CMOSCamera(
        kind="qcmos", rows=10, cols=10, frames=1500, dark_frames=3000, read_noise_e=0.5
    )
    sim = simulate_cmos_series(
        tmp_path / "sim", camera=camera, seed=1000 * seed + 7, progress=False
    )
    ds = emccdcal.calibrate(_cut_pixel(sim, tmp_path / "cut", pixel), progress=False)
    truth = tifffile.imread(sim.outdir / "truth-e_per_adu.tif")[pixel]
    phi, se = float(ds.e_per_adu.values.ravel()[0]), float(ds.e_per_adu_se.values.ravel()[0])
    print(f"phi {phi:.5f} against {truth:.5f}, SE {se / phi:.2%}")
    assert abs(np.log(phi / truth)) < 2.0 * se / phi and se / phi > 0.03


def test_a_hill_with_ripples_on_it_is_estimated_at_its_top_and_its_width():
    """A profile likelihood that is one hill (curvature 1/s²) with ripples on it a
    fraction of an SE apart, each of its own depth up to 0.8 nats (the data's noise):
    which ripple is highest wanders by about an SE from one camera to the next, the
    hill's top does not. The envelope's SE is s and its estimate the hill's top, where
    the ripples are fine on the hill."""
    from emccdcal.fit import comb

    s, top, spacing = 0.018, 0.004, 0.0025  # ln φ: SE, true top, the ripples' spacing
    t = np.linspace(-0.072, 0.072, 231)
    ripple = np.floor(t / spacing + 0.5).astype(int)  # each ripple between two troughs
    rng = np.random.default_rng(7)
    depth = rng.uniform(0.0, 0.8, (8, ripple.max() - ripple.min() + 1))[:, ripple - ripple.min()]
    value = -0.5 * ((t - top) / s) ** 2 + depth * np.cos(2 * np.pi * t / spacing)
    best = np.argmax(value, axis=1)  # the fit ends on the highest ripple
    se, vertex = comb._envelope_se(
        np.broadcast_to(t, value.shape), value, t[best], value[np.arange(8), best],
        np.full(8, t[1] - t[0]),
    )  # fmt: skip
    assert np.ptp(t[best]) > 0.5 * s  # the highest ripple wanders
    np.testing.assert_allclose(se, s, rtol=0.05)
    np.testing.assert_allclose(vertex, top, atol=0.1 * s)
    # a grid as coarse as the ripples' spacing (a resolved comb's aliases, a few per cent
    # apart): each ripple is a basin of its own, and the fit stays on its own
    _, vertex = comb._envelope_se(
        np.broadcast_to(t, value.shape), value, t[best], value[np.arange(8), best],
        np.full(8, 0.025),
    )  # fmt: skip
    assert np.isnan(vertex).all()
    # ripples deeper than one hill holds (rivals, each a basin of its own): no top
    deep = -0.5 * ((t - top) / s) ** 2 + 4.0 * np.cos(2 * np.pi * t / 0.02)
    _, vertex = comb._envelope_se(
        t[None], deep[None], t[[np.argmax(deep)]], deep.max()[None], np.array([t[1] - t[0]])
    )
    assert np.isnan(vertex).all()


@pytest.mark.slow
def test_a_comb_too_faint_for_the_grids_tops_leaves_no_pixel_overconfident(tmp_path):
    """An sCMOS of 0.6 e⁻ median read noise: at its pixels of 0.65–0.8 e⁻ the bright
    levels' ripples are a few thousandths of a nat deep, too shallow or too few to make
    the grid's tops a parabola, yet curved enough to be most of the observed information;
    their SEs had been 0.3–0.5 of the moments' (|z| up to 6.6 here, coverage 0.72–0.78 over
    58 such pixels of three cameras). The likelihood is one hill on the grid: its
    parabola's curvature gives the error."""
    sim, ds = _calibrated(tmp_path, "scmos", (10, 10), 1500, 3000, 4007, read_noise_e=0.6)
    z = _z(ds, sim.outdir)
    assert np.all(np.isfinite(z))
    assert np.abs(z).max() < 4.5 and np.sqrt(np.mean(z**2)) < 1.35


def _comb_pixels(phi, E, seed, sigma=0.42 / 0.46, frames=1500):
    """A :class:`~emccdcal.fit.series.SeriesLikelihood` of ``is-adu`` for pixels of an
    sCMOS whose comb barely shows: φ (e⁻/ADU), levels ``E`` (P, A) e⁻ and read noise σ
    (ADU; one, or one per pixel), simulated (Poisson, normal, the ADC's rounding: not
    the engine) and histogrammed."""
    from emccdcal.data.stats import histograms
    from emccdcal.fit.series import AcquisitionModel, SeriesLikelihood

    offset = 100.0
    rng = np.random.default_rng(seed)
    P = E.shape[0]
    sigma = np.broadcast_to(np.asarray(sigma, dtype=float), (P,))
    hists = [
        histograms(
            np.rint(
                offset
                + rng.poisson(E[:, a], (frames, P)) / phi
                + sigma * rng.standard_normal((frames, P))
            ).reshape(frames, 1, P)
        )
        for a in range(E.shape[1])
    ]
    model = noise.EMModel("cascade")
    models = [AcquisitionModel(1.0, np.full(P, offset), sigma.copy(), model)] * E.shape[1]
    return SeriesLikelihood("is-adu", models, hists)


def _comb_grid(pixels, x):
    """The profile likelihood of ``pixels`` along E = φ·(mean − offset) on the grid the
    fit's check takes about ``x`` (±4 moments' SEs, four points a ripple): the levels'
    signal (P, A), the moments' relative SE and the step (P,), and (ln φ, values), each
    (P, G)."""
    from emccdcal.fit import comb

    signal = np.stack([b.mean - b.offset for b in pixels.blocks], axis=1)
    rel = comb.moment_se(pixels.blocks, np.exp(x[:, 0]), lambda b: b.read_noise**2 + 1 / 12)
    E_max = signal.max(axis=1) * np.exp(x[:, 0])
    step = 1.0 / (comb.PER_RIPPLE * E_max)
    grid = comb._path_grid(pixels.layout, pixels.blocks, x, signal, 4.0 * rel, step)
    return signal, rel, step, grid


def test_a_pixels_likelihood_is_its_own_whatever_pixels_share_its_block():
    """A qCMOS pixel (0.107 e⁻/ADU) of 3.5 ADU of read noise (0.37 e⁻) at 40 e⁻: its
    comb shows (revivals of the transform at every 2πφ, e^-2.7 of its peak). Its
    log-likelihood alone, beside a quieter pixel, and by the direct sum over
    photoelectron numbers agree. The transform's band had stopped short of the revivals
    where no pixel in the block needed more: alone, the pixel's likelihood lost its comb
    (10 nats here; up to 2 at a simulated qCMOS's pixels), beside the quieter one it had it, so
    a fit's result depended on the pixels fitted with it."""
    from scipy import stats

    from emccdcal.fit import engine

    phi, E = 0.107, 40.0
    pixels = _comb_pixels(phi, np.full((2, 1), E), 9, sigma=np.array([3.5, 2.5]))
    x = np.log([[phi, E], [phi, E]])
    beside = engine.objective(pixels.layout, pixels.blocks, x)[0]
    block = pixels.blocks[0].take([0])
    alone = engine.objective(pixels.layout.subset([0]), [block], x[:1])[0]
    held = block.counts[0] > 0
    values, counts = block.values[0][held], block.counts[0][held]
    k = np.arange(200)
    density = stats.poisson.pmf(k, E) * stats.norm.pdf(values[:, None], 100.0 + k / phi, 3.5)
    direct = np.sum(counts * np.log(density.sum(axis=1)))
    assert alone == pytest.approx(direct, rel=1e-12, abs=1e-9)
    assert beside == pytest.approx(direct, rel=1e-12, abs=1e-9)


@pytest.mark.slow
def test_where_rival_ripples_compete_the_estimate_is_the_highest():
    """Where the comb barely shows (0.42 e⁻ of read noise on an sCMOS of 0.46 e⁻/ADU),
    the likelihood over φ holds rival ripples within a nat of each other. The estimate is
    the highest of them, as its bootstrap (which replays the estimate) assumes: no point
    of the profile likelihood's grid about it is higher. A fit kept on its own ripple
    unless another was a nat higher stopped below the grid's best at a third of such
    pixels (up to 0.9 nats), and those estimates scattered more than their SEs said."""
    pixels = _comb_pixels(0.46, np.tile([20.0, 60.0, 150.0, 400.0], (16, 1)), 5)
    fit = pixels.fit()
    _, _, _, (ln_phi, value) = _comb_grid(pixels, fit.x)
    # the grid's values are the likelihood along the mean's path, at most the profile's
    assert np.all(value.max(axis=1) <= fit.objective + 1e-6)


@pytest.mark.slow
def test_profile_intervals_where_rival_ripples_compete_are_as_wide_as_the_error():
    """``intervals="profile"`` where the comb barely shows: the χ²₁ quantile of φ's
    deviance ends within the estimate's own ripple (bounds a few hundredths of the SE
    wide, covering 58 % of the truths at 0.35–0.5 e⁻ on an sCMOS), so there the bounds
    of φ and of every E are the Wald bounds of the widened error on the log scale."""
    pixels = _comb_pixels(0.46, np.tile([20.0, 60.0, 150.0, 400.0], (8, 1)), 6)
    fit = pixels.fit()
    e = pixels.estimates(fit, intervals="profile", gof_test=False)
    widened = e["e_per_adu_se"][:, 0] > 2 * np.sqrt(fit.cov[:, 0, 0]) * e["e_per_adu"][:, 0]
    assert widened.sum() >= 4  # the case at hand: the ripples set the error
    for name in ("e_per_adu", "photoelectrons"):
        value, se = e[name][widened], e[f"{name}_se"][widened]
        lower, upper = e[f"{name}_lower"][widened], e[f"{name}_upper"][widened]
        np.testing.assert_allclose(np.log(upper / value), 1.959964 * se / value, rtol=1e-6)
        np.testing.assert_allclose(np.log(value / lower), 1.959964 * se / value, rtol=1e-6)


def test_the_wald_se_of_heavy_tailed_errors_holds_95_percent_of_them():
    """The errors of an estimate among rival ripples are a spike and wide wings: ±1.96
    of their SD holds too few of them, the SE of :func:`emccdcal.fit.comb.wald_se` 95 %;
    normal errors get their SD."""
    from emccdcal.fit import comb

    rng = np.random.default_rng(8)
    B = 20000
    spike_and_wings = np.where(rng.random(B) < 0.6, 0.05, 1.0) * rng.standard_normal(B)
    normal = rng.standard_normal(B)
    errors = np.stack([spike_and_wings, normal])
    se = comb.wald_se(errors)
    held = np.mean(np.abs(errors) <= 1.96 * se[:, None], axis=1)
    by_sd = np.mean(np.abs(errors) <= 1.96 * errors.std(axis=1, ddof=1)[:, None], axis=1)
    assert by_sd[0] < 0.93 and held[0] == pytest.approx(0.95, abs=0.003)
    assert se[1] == pytest.approx(np.std(normal, ddof=1), rel=0.02)


@pytest.mark.slow
def test_the_bootstrap_of_rival_ripples_is_the_scatter_of_the_estimate_refitted(monkeypatch):
    """Where rival ripples compete (a pixel of 0.42 e⁻ of read noise on an sCMOS of
    0.46 e⁻/ADU: its comb barely resolved), the SE of ln φ holds 95 % of the estimate's
    own errors, which :func:`emccdcal.fit.comb.bootstrap_errors` draws from the model
    evaluated once for all its replicates. Against the slow way: 48 replicates simulated
    at the pixel's fit (Poisson, normal, the ADC's rounding: not the engine), each
    fitted as the pixel was. The estimates are a spike at the fit's ripple and wings
    out to twenty ripples, so the slow SD has a sampling error of some 20 % and the
    fast one of some 10 %: the two agree within 40 %. A bootstrap along one path for
    every replicate (their means' noise, a fraction of a ripple, left out) gave SDs
    down to a tenth of this."""
    from emccdcal.fit import comb

    pixel = _comb_pixels(0.46, np.array([[20.0, 60.0, 150.0, 400.0]]), 3)
    fit = pixel.fit()
    x = fit.x
    signal, rel, step, _ = _comb_grid(pixel, x)
    errors = comb.bootstrap_errors(pixel.layout, pixel.blocks, x, signal, 4.0 * rel, step)
    fast = np.std(errors[0], ddof=1)
    se = float(np.ravel(pixel.estimates(fit)["e_per_adu_se"])[0]) / np.exp(x[0, 0])
    assert se >= comb.wald_se(errors)[0] >= fast  # the pixel's SE holds them
    # The replicates' estimates as the pixel's, not their SEs: their own bootstraps (which
    # move an SE's floor, never x) are left out.
    monkeypatch.setattr(
        comb, "bootstrap_errors", lambda layout, *a: np.zeros((layout.constant.shape[0], 2))
    )
    replicates = _comb_pixels(float(np.exp(x[0, 0])), np.repeat(np.exp(x[:, 1:]), 48, axis=0), 4)
    slow = np.std(replicates.fit(covariance=False).x[:, 0], ddof=1)
    print(f"SD of ln phi: bootstrap {fast:.5f}, refitted {slow:.5f}; the pixel's SE {se:.5f}")
    assert fast == pytest.approx(slow, rel=0.4)
