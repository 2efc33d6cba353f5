"""φ chained from an is-adu result into the methods that hold it fixed, with its error;
and the options and results a method cannot use, refused."""

from __future__ import annotations

import re

import numpy as np
import pytest
from conftest import quiet

import emccdcal
from emccdcal import calibrate, cli, load_result
from emccdcal.errors import InputError, ManifestError, MethodError, OptionError
from emccdcal.fit import profile
from emccdcal.fit.series import AcquisitionModel, SeriesLikelihood
from emccdcal.model.noise import EMModel
from emccdcal.simulate.series import simulate_gain_series, simulate_intensity_series

ROWS = COLS = 4
FRAMES = 1500


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    d = tmp_path_factory.mktemp("chain")
    kw = dict(rows=ROWS, cols=COLS, frames=FRAMES)
    adu = simulate_intensity_series(d / "adu", seed=3, **kw)
    gs = simulate_gain_series(d / "gs", seed=4, setpoints=(1, 25, 300), **kw)
    quiet(calibrate, adu.manifest, "is-adu", out=d / "out-adu")
    return d, adu, gs


def test_sensitivity_is_the_derivative_of_the_refit(series):
    # d x̂ / d ln φ from the information equals the finite difference of two refits
    d, _, gs = series
    from emccdcal.data import stats
    from emccdcal.data.manifest import read_manifest

    m = quiet(read_manifest, gs.manifest)
    hists = [stats.histograms(np.asarray(a.frames()), adc_max=m.adc_max) for a in m.acquisitions]
    models = [
        AcquisitionModel(
            a.em_gain_setpoint, a.offset.ravel(), a.read_noise.ravel(), EMModel("gamma")
        )
        for a in m.acquisitions
    ]

    def fit(phi):
        lik = SeriesLikelihood("gs", models, hists, e_per_adu=phi)
        return lik, lik.fit(tol=1e-12)

    lik, base = fit(3.859)
    sens = profile.e_per_adu_sensitivity(lik.layout, lik.blocks, base.x)
    h = 1e-3
    up, down = fit(3.859 * np.exp(h))[1], fit(3.859 * np.exp(-h))[1]
    numeric = (up.x - down.x) / (2 * h)
    np.testing.assert_allclose(sens, numeric, rtol=2e-3, atol=2e-5)
    # in gs, E follows φ (its 1× counts are E/φ ADU) and the gains hardly move
    assert np.all(np.abs(sens[:, 0] - 1) < 0.05) and np.all(np.abs(sens[:, 1:]) < 0.05)


def test_chained_result_gives_phi_and_its_error_to_the_gains(series):
    d, _, gs = series
    adu = load_result(d / "out-adu")
    chained = quiet(calibrate, gs.manifest, "gs", e_per_adu=d / "out-adu")
    fixed = quiet(calibrate, gs.manifest, "gs", e_per_adu=adu.e_per_adu.values)
    np.testing.assert_allclose(chained.e_per_adu, adu.e_per_adu)
    np.testing.assert_allclose(chained.e_per_adu_se, adu.e_per_adu_se)
    assert np.all(np.isnan(fixed.e_per_adu_se))
    # the estimates are those of the same φ given as a map; only the errors grow
    np.testing.assert_allclose(chained.em_gain, fixed.em_gain, rtol=1e-12)
    np.testing.assert_allclose(chained.photoelectrons, fixed.photoelectrons, rtol=1e-12)
    rel_phi = (adu.e_per_adu_se / adu.e_per_adu).values
    E, se_E, se_E0 = (
        chained.photoelectrons.values,
        chained.photoelectrons_se.values,
        fixed.photoelectrons_se.values,
    )
    # E moves with φ one for one: its variance gains (E · SE(φ)/φ)², to a few per cent
    np.testing.assert_allclose(se_E**2 - se_E0**2, (E * rel_phi) ** 2, rtol=0.1)
    assert np.all(chained.em_gain_se >= fixed.em_gain_se - 1e-12)
    assert "e_per_adu" in chained.attrs["standard_errors"]
    assert chained.attrs["e_per_adu_source"].startswith("result ")
    assert chained.attrs["e_per_adu_source"] == f"result {chained.attrs['e_per_adu_result']}"
    assert "e_per_adu_result" not in fixed.attrs


def test_manifest_names_a_result_and_the_cli_takes_one(series, tmp_path, capsys):
    d, _, gs = series
    text = gs.manifest.read_text().replace(
        "e_per_adu = 3.859", f'e_per_adu = "{d / "out-adu" / "calibration.nc"}"'
    )
    manifest = gs.manifest.with_name("chained.toml")
    manifest.write_text(text)
    ds = quiet(calibrate, manifest, "gs")
    # the manifest's result is the same chain as the argument's: φ, its error, and the
    # errors it adds to every estimate
    direct = quiet(calibrate, gs.manifest, "gs", e_per_adu=d / "out-adu")
    np.testing.assert_allclose(ds.e_per_adu_se, load_result(d / "out-adu").e_per_adu_se)
    for name in ("em_gain_se", "photoelectrons_se", "e_per_adu"):
        np.testing.assert_allclose(ds[name], direct[name], rtol=1e-12)
    assert (
        cli.main(
            [
                "calibrate",
                str(gs.manifest),
                "-m",
                "gs",
                "-o",
                str(tmp_path / "o"),
                "--e-per-adu",
                str(d / "out-adu"),
                "-q",
            ]
        )
        == 0
    )


def test_what_cannot_be_chained_is_refused(series, tmp_path):
    d, adu, gs = series
    with pytest.raises(OptionError, match="is-adu estimates e_per_adu itself"):
        calibrate(adu.manifest, "is-adu", e_per_adu=3.0)
    quiet(calibrate, gs.manifest, "gs", out=tmp_path / "gs-result")
    with pytest.raises(OptionError, match="a gs result does not estimate e_per_adu"):
        calibrate(gs.manifest, "gs", e_per_adu=tmp_path / "gs-result")
    small = simulate_intensity_series(tmp_path / "small", rows=2, cols=2, frames=300, seed=1)
    quiet(calibrate, small.manifest, "is-adu", out=tmp_path / "small-out")
    with pytest.raises(OptionError, match=r"pixels \(2, 2\) are not the manifest's \(4, 4\)"):
        calibrate(gs.manifest, "gs", e_per_adu=tmp_path / "small-out")
    with pytest.raises(OptionError, match="not a calibration result"):
        calibrate(gs.manifest, "gs", e_per_adu=tmp_path / "phi.txt")


def test_a_quoted_number_in_the_manifest_is_not_a_path(series):
    _, _, gs = series
    bad = gs.manifest.with_name("quoted.toml")
    bad.write_text(gs.manifest.read_text().replace("e_per_adu = 3.859", 'e_per_adu = "3.859"'))
    with pytest.raises(
        ManifestError,
        match=r'e_per_adu = "3.859" is a string, which names a '
        r"map file; write the number without quotes",
    ):
        quiet(calibrate, bad, "gs")


@pytest.mark.slow
def test_a_method_that_fails_for_most_pixels_is_an_error(series, tmp_path):
    # offsets far above the data: no pixel can be fitted, and no number is printed
    _, _, gs = series
    bad = gs.manifest.with_name("high-offset.toml")
    text = re.sub(r'offset = "[^"]*"', "offset = 20000.0", gs.manifest.read_text())
    bad.write_text(text)
    with pytest.raises(MethodError, match=r"only 0 of 16 pixels converged.*nothing was written"):
        quiet(calibrate, bad, "gs", out=tmp_path / "never")
    assert not (tmp_path / "never" / "calibration.nc").exists()


def test_a_larger_region_chains_into_a_crop_of_it(tmp_path):
    # φ of 6 × 8 pixels at the sensor's corner; a gain series of 4 × 4 at (1, 2) inside it
    adu = simulate_intensity_series(tmp_path / "adu", rows=6, cols=8, frames=400, seed=5)
    manifest = adu.manifest.read_text()
    adu.manifest.write_text("origin = [0, 0]\n" + manifest)
    big = quiet(calibrate, adu.manifest, "is-adu", out=tmp_path / "big")
    assert list(big.attrs["sensor_origin"]) == [0, 0]
    gs = simulate_gain_series(
        tmp_path / "gs", rows=4, cols=4, frames=400, seed=6, setpoints=(1, 25)
    )
    text = gs.manifest.read_text()
    inside = gs.manifest.with_name("inside.toml")
    inside.write_text("origin = [1, 2]\n" + text)
    ds = quiet(calibrate, inside, "gs", e_per_adu=tmp_path / "big")
    np.testing.assert_array_equal(ds.e_per_adu.values, big.e_per_adu.values[1:5, 2:6])
    np.testing.assert_array_equal(ds.e_per_adu_se.values, big.e_per_adu_se.values[1:5, 2:6])
    assert list(ds.attrs["sensor_origin"]) == [1, 2]
    outside = gs.manifest.with_name("outside.toml")
    outside.write_text("origin = [4, 6]\n" + text)
    with pytest.raises(
        OptionError,
        match=r"covers sensor rows 0–5, cols 0–7; the manifest "
        r"needs sensor rows 4–7, cols 6–9: rows 6–7; cols "
        r"8–9 missing",
    ):
        quiet(calibrate, outside, "gs", e_per_adu=tmp_path / "big")
    with pytest.raises(OptionError, match=r"where they lie on the sensor is not known"):
        quiet(calibrate, gs.manifest, "gs", e_per_adu=tmp_path / "big")


# --- the Python API in one currency ------------------------------------------------------

CURRENCY = """
import filecmp, json, os, sys, warnings
warnings.simplefilter("ignore")
import numpy as np, tifffile
import emccdcal

sim = emccdcal.simulate_gain_series(
    "gs", rows=6, cols=6, frames=500, seed=5, setpoints=(1, 5, 25, 100), progress=False
)
results = {
    "written": emccdcal.calibrate(sim.manifest, "gs", out="out"),  # and kept in memory
    "folder": "out",
    "memory": emccdcal.calibrate(sim.manifest, "gs"),  # never written
}
found = {}
for name, result in results.items():
    emccdcal.export_calibration(result, "picasso", f"picasso-{name}", setpoint=25)
    emccdcal.apply_calibration(
        result, "gs/gain-GS/25x-gain.tif", f"movie-{name}.tif", setpoint=25, progress=False
    )
    curve = emccdcal.fit_gain_curve(result)
    emccdcal.write_report(result, f"report-{name}.html")
    found[name] = {
        "picasso": open(f"picasso-{name}/picasso-config.yaml").read(),
        "movie": tifffile.imread(f"movie-{name}.tif").tolist(),
        "curve": curve.predict([50.0])["gain"].tolist(),
        "report": os.path.getsize(f"report-{name}.html") > 10000,
    }
# phi chained as users hold it: the Dataset, the folder it was written to, a Calibration
adu = emccdcal.simulate_intensity_series("adu", rows=6, cols=6, frames=500, seed=6, progress=False)
phi = emccdcal.calibrate(adu.manifest, "is-adu", out="adu-out")
for name, given in {
    "folder": "adu-out",
    "written": phi,
    "memory": emccdcal.calibrate(adu.manifest, "is-adu"),
    "calibration": emccdcal.load_calibration(phi),
}.items():
    chained = emccdcal.calibrate(sim.manifest, "gs-no1x", e_per_adu=given)
    found.setdefault(name, {})["chained"] = {
        "em_gain": chained.em_gain.values.tolist(),
        "em_gain_se": chained.em_gain_se.values.tolist(),
        "source": chained.attrs["e_per_adu_source"],
    }
print(json.dumps(found))
"""


@pytest.mark.slow
def test_the_result_calibrate_returns_goes_into_every_function_that_takes_one(tmp_path):
    """In a fresh interpreter, the Dataset ``calibrate()`` returns goes as it is into
    ``export_calibration``, ``apply_calibration``, ``fit_gain_curve`` and
    ``write_report``: the same files as through the written folder (a result written
    knows its file: the same provenance too), and, never written, the same numbers."""
    import json
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, "-c", CURRENCY], cwd=tmp_path, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr[-3000:]
    found = json.loads(done.stdout.strip().splitlines()[-1])
    chained = {k: found[k].pop("chained") for k in ("folder", "written", "memory", "calibration")}
    folder, written, memory = found["folder"], found["written"], found["memory"]
    assert written == folder  # byte for byte: the file, the movie, the curve, the report
    assert all(found[k]["report"] for k in ("folder", "written", "memory"))

    def numbers(text):  # the Picasso file without its provenance comments
        return [line for line in text.splitlines() if not line.startswith("#")]

    assert numbers(memory["picasso"]) == numbers(folder["picasso"])
    assert memory["movie"] == folder["movie"] and memory["curve"] == folder["curve"]
    # calibrate(e_per_adu=...) takes φ and its error from each as from the folder
    for k, c in chained.items():
        assert c["em_gain"] == chained["folder"]["em_gain"], k
        assert c["em_gain_se"] == chained["folder"]["em_gain_se"], k
    assert chained["written"]["source"] == "result adu-out/calibration.nc"  # the file it knows
    assert chained["memory"]["source"] == "given"


@pytest.mark.slow
def test_the_posterior_takes_a_chained_phi_with_its_error_and_its_checks(series):
    """The sampler reads φ as calibrate does: a chained result's SE widens the gains'
    draws as it widens calibrate's SEs, and a φ the data contradict is refused."""
    d, adu, gs = series
    pixel, kw = (1, 2), dict(em_model="gamma", seed=3, n_steps=500, min_ess=400, progress=False)
    chained = quiet(
        emccdcal.sample_posterior, gs.manifest, "gs", [pixel], e_per_adu=d / "out-adu", **kw
    )
    phi = load_result(d / "out-adu").e_per_adu.values
    fixed = quiet(emccdcal.sample_posterior, gs.manifest, "gs", [pixel], e_per_adu=phi, **kw)
    engine = quiet(  # without the maps' errors, which the sampler holds exact
        calibrate, gs.manifest, "gs", e_per_adu=d / "out-adu", em_model="gamma", map_errors=False
    )
    assert chained.attrs["e_per_adu_source"].startswith("result ")
    assert chained.attrs["e_per_adu_se_included"] == 1 and fixed.attrs["e_per_adu_se_included"] == 0
    for setpoint in (25, 300):  # a gain hardly moves with φ (g ∝ mean ratio), but it may
        name = f"em_gain[{setpoint}x]"
        sd = float(chained.sd.sel(parameter=name)[0])
        se = float(engine.em_gain_se.sel(setpoint=setpoint).values[pixel])
        assert sd == pytest.approx(se, rel=0.2), (name, sd, se)
        assert float(chained.mle_se.sel(parameter=name)[0]) == pytest.approx(se, rel=1e-6)
    # E moves one for one with φ: its draws carry φ's error, as its standard error does
    for name in [str(p) for p in chained.parameter.values if str(p).startswith("photoelectrons")]:
        sd, sd_fixed = (float(ds.sd.sel(parameter=name)[0]) for ds in (chained, fixed))
        se = float(chained.mle_se.sel(parameter=name)[0])
        assert sd == pytest.approx(se, rel=0.2) and sd > 1.5 * sd_fixed, (name, sd, se, sd_fixed)
    with pytest.raises(InputError, match="times what this 1x acquisition"):
        emccdcal.sample_posterior(gs.manifest, "gs", [pixel], e_per_adu=1 / phi, **kw)
