"""Calibration-on-the-spot (COTS): the core on one spot, the manifest verb, bad input.

docs/validation.md case 13: a 10 × 10 ROI Gaussian spot (N = 5000 e⁻, b = 20 e⁻/px), gamma EM
register, G = 5 ADU/e⁻, negligible read noise, 200 frames. Estimates are checked at 3 of
their own standard errors; the SEs themselves against the scatter over seeds (docs/cots.md
has the figures).
"""

from __future__ import annotations

import inspect

import numpy as np
import pytest
import tifffile
from scipy import optimize

from emccdcal import cli, errors, result
from emccdcal.beads import cots
from emccdcal.beads.cots_calibration import cots_calibrate
from emccdcal.model import noise, psf
from emccdcal.simulate.beads import simulate_beads
from emccdcal.simulate.camera import simulate_frames

G_TRUE = 5.0  # ADU per photoelectron
S0_TRUE = 100.0  # ADU
SPOT = (0.2, -0.3, 1.3, 5000.0, 20.0)  # x, y (pixel from the ROI centre), s, N, b (e-)


def _spot_stack(seed, frames=200, gain=G_TRUE, size=10, spot=SPOT):
    """Raw counts of one spot: φ = 1 so that the EM gain g equals G (ADU/e⁻). COTS assumes
    F² = 2, the gamma register, which these tests simulate (on the exact register it reads
    low: docs/cots.md)."""
    c = np.arange(size) - (size - 1) / 2
    photo = psf.spot_image(list(spot), c, c)
    return simulate_frames(
        photo,
        em_gain=gain,
        e_per_adu=1.0,
        offset=S0_TRUE,
        read_noise=0.01,
        frames=frames,
        seed=seed,
        multiplication="gamma",
    )


@pytest.fixture(scope="module")
def case13():
    return cots.cots_spot(_spot_stack(seed=13))


# --------------------------------------------------------------------------------------
# The core
# --------------------------------------------------------------------------------------
def test_case13_recovers_gain_within_its_standard_errors(case13):
    r = case13
    assert r.n_used == r.n_frames == 200
    # SE ≈ 2.3 % of G with 200 frames; measured |z| < 1 on this seed, < 3 over 40 seeds.
    assert 0.015 * G_TRUE < r.gain_se < 0.035 * G_TRUE
    assert abs(r.gain - G_TRUE) < 3 * r.gain_se
    # the analytic SE agrees with the scatter of the per-frame estimates
    assert r.gain_se == pytest.approx(r.gain_scatter_se, rel=0.2)


def test_case13_recovers_offset(case13):
    r = case13
    assert 1.0 < r.offset_se < 6.0  # ADU; extrapolated from ≥ 100 ADU above the offset
    assert abs(r.offset - S0_TRUE) < 3 * r.offset_se
    assert r.offset_se == pytest.approx(r.offset_scatter_se, rel=0.2)
    # the width's own SE over 200 frames is ~0.002 px: this is a loose bound on a bias
    assert r.width == pytest.approx(SPOT[2], abs=0.03)
    # photoelectrons N = counts / G: its error is the gain's (the counts' is 0.1 %)
    assert r.spot_counts / r.gain == pytest.approx(SPOT[3], rel=3 * r.gain_se / r.gain)


@pytest.mark.slow
def test_standard_errors_match_the_scatter_over_seeds():
    gains, ses, offsets, off_ses = [], [], [], []
    for seed in range(24):
        r = cots.cots_spot(_spot_stack(seed=100 + seed, frames=100))
        gains.append(r.gain)
        ses.append(r.gain_se)
        offsets.append(r.offset)
        off_ses.append(r.offset_se)
    gains, offsets = np.array(gains), np.array(offsets)
    # 24 seeds: the SD itself is uncertain by ~15 %.
    assert 0.7 < gains.std(ddof=1) / np.mean(ses) < 1.4
    assert 0.7 < offsets.std(ddof=1) / np.mean(off_ses) < 1.4
    # no bias beyond the noise of the mean (first-order bias correction)
    assert abs(gains.mean() - G_TRUE) < 3 * gains.std(ddof=1) / np.sqrt(gains.size)
    assert abs(offsets.mean() - S0_TRUE) < 3 * offsets.std(ddof=1) / np.sqrt(offsets.size)


@pytest.mark.slow
def test_a_read_noise_dominated_spot_is_unbiased():
    """Low gain (G = 1.3 ADU/e⁻) under read noise 15.5 ADU, as at 5×: most pixels'
    variance is read noise, the per-frame G scatter by ~45 % and a few per cent of frames
    fit G ≤ 0. Those are kept (dropping them read +5 %), and the bias correction takes
    the read noise out of the higher cumulants: the average is unbiased."""
    c = np.arange(9) - 4.0
    photo = psf.spot_image([0.2, -0.1, 1.3, 5000.0, 10.0], c, c)
    gains, ses = [], []
    for seed in range(4):  # the mean's SE ~0.6 %: dropping G <= 0 frames would be 8 SE
        stack = simulate_frames(
            photo,
            em_gain=1.3,
            e_per_adu=1.0,
            offset=580.0,
            read_noise=15.5,
            frames=800,
            seed=200 + seed,
            multiplication="gamma",
        )
        r = cots.cots_spot(stack, read_noise=15.5)
        raw = r.frame_gain + r.frame_bias[:, 0]
        assert np.any(r.usable & (raw <= 0))  # frames at or below zero are kept
        assert r.n_used >= 0.99 * r.n_frames
        gains.append(r.gain)
        ses.append(r.gain_se)
    assert abs(np.mean(gains) - 1.3) < 3 * np.mean(ses) / np.sqrt(len(gains))
    with pytest.raises(ValueError, match="needs e_per_adu"):
        cots.cots_spot(stack, register=noise.EMModel("cascade").register)
    with pytest.raises(ValueError, match="read_noise must be"):
        cots.cots_spot(stack, read_noise=-1.0)


def test_bias_theory_predicts_the_uncorrected_fits():
    """The hat-matrix bias is large (~13 % here); its theory predicts the raw mean."""
    stack = _spot_stack(seed=7, frames=1000)
    fit = cots.gaussian_mask_fit(stack)
    counts = stack.reshape(len(stack), -1)
    expected = fit.expected.reshape(len(stack), -1)
    alpha, ok = cots.fit_variance_model(counts, expected)
    assert ok.mean() > 0.99
    raw = alpha[ok].mean(axis=0)
    raw_se = alpha[ok].std(axis=0, ddof=1) / np.sqrt(ok.sum())
    truth = np.array([G_TRUE, G_TRUE * S0_TRUE])
    bias, cov = cots.variance_bias_covariance(expected[ok], fit.jacobian[ok], truth)
    predicted = truth + bias.mean(axis=0)
    assert abs(raw[0] - G_TRUE) > 8 * raw_se[0]  # uncorrected: far off
    np.testing.assert_array_less(np.abs(raw - predicted), 3 * raw_se)
    # the sandwich covariance predicts the frame-to-frame scatter of the raw fits
    assert np.sqrt(cov[:, 0, 0].mean()) == pytest.approx(alpha[ok, 0].std(), rel=0.1)
    assert np.sqrt(cov[:, 1, 1].mean()) == pytest.approx(alpha[ok, 1].std(), rel=0.1)


def test_variance_fit_finds_the_nelder_mead_minimum():
    stack = _spot_stack(seed=3, frames=12)
    fit = cots.gaussian_mask_fit(stack)
    counts = stack.reshape(12, -1).astype(float)
    expected = fit.expected.reshape(12, -1)
    alpha, ok = cots.fit_variance_model(counts, expected)
    assert ok.all()
    for f in range(4):
        r2 = (counts[f] - expected[f]) ** 2

        def objective(a, f=f, r2=r2):
            v = 2 * (a[0] * expected[f] - a[1])
            return np.inf if np.any(v <= 0) else np.sum(np.log(v) + r2 / v)

        nm = optimize.minimize(
            objective,
            alpha[f] * [1.1, 0.9],
            method="Nelder-Mead",
            options={"xatol": 1e-8, "fatol": 1e-10, "maxiter": 20000},
        )
        assert objective(alpha[f]) <= nm.fun + 1e-7
        np.testing.assert_allclose(nm.x, alpha[f], rtol=1e-3, atol=1e-3 * abs(alpha[f, 1]))


def test_gaussian_mask_fit_and_hat_matrix():
    c = np.arange(9) - 4.0
    truth = np.array([[0.3, -0.2, 1.2, 4000.0, 150.0], [-0.4, 0.1, 1.5, 900.0, 80.0]])
    clean = psf.spot_image(truth, c, c)
    fit = cots.gaussian_mask_fit(clean)
    assert fit.converged.all()
    np.testing.assert_allclose(fit.params, truth, rtol=1e-5, atol=1e-5)
    hat = cots.hat_matrix(fit.jacobian)
    assert hat.shape == (2, 81, 81)
    np.testing.assert_allclose(hat, np.swapaxes(hat, 1, 2), atol=1e-12)
    np.testing.assert_allclose(hat @ hat, hat, atol=1e-10)
    np.testing.assert_allclose(np.trace(hat, axis1=1, axis2=2), 5.0, atol=1e-10)


def test_roi_follows_a_moving_spot():
    """A spot 2.4 px off the ROI centre: the ROI is moved and the gain still recovered."""
    c = np.arange(16) - 7.5
    photo = psf.spot_image([2.4, -1.6, 1.3, 5000.0, 20.0], c, c)
    stack = simulate_frames(
        photo,
        em_gain=G_TRUE,
        e_per_adu=1.0,
        offset=S0_TRUE,
        read_noise=0.01,
        frames=60,
        seed=5,
        multiplication="gamma",
    )
    r = cots.cots_spot(stack, roi=(3, 3, 10, 10))
    assert np.all(r.frame_shift[r.usable] == [-2, 2])
    assert np.all(np.abs(r.frame_params[r.usable, :2]) <= 1.0)
    assert abs(r.gain - G_TRUE) < 3 * r.gain_se


def test_saturated_frames_are_left_out():
    stack = _spot_stack(seed=9, frames=40)
    stack[[3, 17, 30], 5, 4] = 65535
    r = cots.cots_spot(stack, adc_max=65535)
    assert r.n_saturated == 3 and r.n_used == 37
    assert not r.usable[[3, 17, 30]].any()


def test_core_rejects_bad_input():
    with pytest.raises(ValueError, match="at least 10 frames"):
        cots.cots_spot(_spot_stack(seed=1, frames=5))
    with pytest.raises(ValueError, match="does not fit"):
        cots.cots_spot(_spot_stack(seed=1, frames=20), roi=(5, 5, 10, 10))
    flat = np.random.default_rng(0).poisson(100, (40, 10, 10)).astype(np.uint16)
    with pytest.raises(ValueError, match="COTS"):
        cots.cots_spot(flat)


# --------------------------------------------------------------------------------------
# A manifest of bead stacks
# --------------------------------------------------------------------------------------
BEADS = ((12, 12), (12, 31), (31, 21))
PHI = 3.859


def _write_beads(
    d,
    *,
    setpoints=(1, 100, 300),
    frames=60,
    e_per_adu=True,
    beads=BEADS,
    seed=0,
    shape=(44, 44),
    multiplication="gamma",
):
    """Bead stacks (gamma EM unless said, negligible read noise) and their manifest, which
    names the register simulated; returns its path."""
    d.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    r, c = np.arange(shape[0]), np.arange(shape[1])
    photo = np.full(shape, 20.0)
    for y, x in beads:
        photo = photo + psf.spot_image(
            [x + rng.uniform(-0.3, 0.3), y + rng.uniform(-0.3, 0.3), 1.3, 3000.0, 0.0], r, c
        )
    lines = [f'em_model = "{multiplication}"']  # the register these frames were simulated with
    lines += [f"e_per_adu = {PHI}"] if e_per_adu else []
    for i, sp in enumerate(setpoints):
        stack = simulate_frames(
            photo,
            em_gain=sp,
            e_per_adu=PHI,
            offset=S0_TRUE,
            read_noise=0.01,
            frames=frames,
            seed=seed * 10 + i,
            multiplication=multiplication,
        )
        tifffile.imwrite(d / f"beads_{sp}x.tif", stack)
        lines += [
            "[[acquisition]]",
            f'frames = "beads_{sp}x.tif"',
            f"em_gain_setpoint = {sp}",
            f"offset = {S0_TRUE}",
            "read_noise = 0.01",
        ]
    path = d / "manifest.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def bead_run(tmp_path_factory):
    base = tmp_path_factory.mktemp("cots")
    manifest = _write_beads(base / "beads")
    out = base / "out"
    code = cli.main(["cots", str(manifest), "-o", str(out), "--quiet"])
    assert code == 0
    return manifest, out, result.load(out)


@pytest.mark.slow
def test_manifest_result_contract(bead_run):
    _, out, ds = bead_run
    assert ds.attrs["method"] == "cots"
    assert (out / result.SUMMARY_FILE).is_file()
    assert ds.setpoint.values.tolist() == [1.0, 100.0, 300.0]
    assert ds.sizes["bead"] == 3
    assert sorted(zip(ds.bead_row.values.tolist(), ds.bead_col.values.tolist())) == sorted(BEADS)
    for name, units in (
        ("cots_gain_adu_per_e", "ADU/e-"),
        ("cots_offset_se", "ADU"),
        ("cots_em_gain", "1"),
        ("bead_row", "pixel"),
        ("em_gain", "1"),
        ("photoelectrons", "e-"),
    ):
        assert ds[name].attrs["units"] == units
    # 1x: no multiplication, everywhere; COTS values only in the beads' 9x9 ROIs
    assert np.all(ds.em_gain.sel(setpoint=1).values == 1)
    assert np.all(np.isnan(ds.cots_gain_adu_per_e.sel(setpoint=1).values))
    conv = ds.converged.values
    assert conv.sum() == 3 * 81
    g300 = ds.em_gain.sel(setpoint=300).values
    assert np.all(np.isfinite(g300[conv])) and np.all(np.isnan(g300[~conv]))
    r, c = BEADS[0]
    bead = int(np.flatnonzero((ds.bead_row.values == r) & (ds.bead_col.values == c))[0])
    assert g300[r, c] == pytest.approx(float(ds.cots_em_gain.sel(setpoint=300)[bead]))
    # photoelectrons: COTS's mean e- per pixel per frame in the ROI (background 20 e-)
    pe = ds.photoelectrons.sel(setpoint=300).values
    assert np.nanmin(pe) == pytest.approx(20.0, abs=8.0)
    assert np.nanmax(pe) > 200


def test_manifest_recovers_the_em_gain(bead_run):
    _, _, ds = bead_run
    for sp in (100.0, 300.0):
        g = ds.cots_em_gain.sel(setpoint=sp).values
        se = ds.cots_em_gain_se.sel(setpoint=sp).values
        assert np.all(np.abs(g - sp) < 3.5 * se)  # per bead (60 frames: SE ≈ 4 %)
        mean_se = np.sqrt(np.sum(se**2)) / se.size
        assert abs(g.mean() - sp) < 3 * mean_se
        G = ds.cots_gain_adu_per_e.sel(setpoint=sp).values
        np.testing.assert_allclose(G * PHI, g)


@pytest.mark.slow
def test_cli_prints_a_summary(bead_run, capsys):
    manifest, out, _ = bead_run
    assert cli.main(["cots", str(manifest), "-o", str(out / "again"), "--half-size", "3"]) == 0
    text = capsys.readouterr().out
    assert "300x: em_gain" in text and "100x: em_gain" in text and "1x: em_gain 1" in text
    assert result.load(out / "again").sizes["bead"] == 3


@pytest.mark.slow
def test_an_exact_register_is_read_through_its_own_excess_noise(tmp_path):
    """Beads of the exact 536-stage cascade at 5x (F^2 = 1.795) and 25x: COTS under the
    cascade finds the true gain (bead mean within 3 SE), under the gamma model (F^2 = 2,
    COTS as published) about 10 % low at 5x; both from the same spots, related by
    g_gamma * 2 = g * F^2(g) per bead (to the register's cumulants in the bias
    correction). The result records its register."""
    from emccdcal.model.cascade import excess_noise_factor

    manifest = _write_beads(
        tmp_path / "beads", setpoints=(5, 25), frames=120, multiplication="cascade", seed=3
    )
    exact = cots_calibrate(manifest)  # the manifest's register: the cascade
    paper = cots_calibrate(manifest, em_model="gamma")
    assert exact.attrs["em_model"] == "cascade" and exact.attrs["register_stages"] == 536
    assert paper.attrs["em_model"] == "gamma" and "register_stages" not in paper.attrs
    for sp in (5.0, 25.0):
        g = exact.cots_em_gain.sel(setpoint=sp).values
        se = exact.cots_em_gain_se.sel(setpoint=sp).values
        assert abs(g.mean() - sp) < 3 * np.sqrt(np.sum(se**2)) / se.size, (sp, g)
        g_gamma = paper.cots_em_gain.sel(setpoint=sp).values
        # the same slope, but for the bias correction's cumulants (c3 2.98 against 3)
        np.testing.assert_allclose(2 * g_gamma, g * excess_noise_factor(g, 536), rtol=1e-3)
        np.testing.assert_allclose(
            exact.cots_offset.sel(setpoint=sp), paper.cots_offset.sel(setpoint=sp), rtol=1e-3
        )
    low = paper.cots_em_gain.sel(setpoint=5.0).values.mean() / 5.0 - 1
    assert -0.14 < low < -0.06


@pytest.mark.slow
def test_on_simulated_beads(tmp_path):
    """End to end on the project's own bead simulator (gamma EM), at the highest gains."""
    fn = simulate_beads
    wanted = {
        "frames": 100,
        "seed": 11,
        "multiplication": "gamma",
        "beads": 4,
        "setpoints": (1, 100, 300),
    }
    kwargs = {k: v for k, v in wanted.items() if k in inspect.signature(fn).parameters}
    fn(tmp_path / "beads", **kwargs)
    ds = cots_calibrate(tmp_path / "beads" / "manifest.toml", em_model="gamma")
    assert ds.attrs["em_model"] == "gamma"
    truth = result.load(tmp_path / "beads" / "truth_calibration.nc")
    top = float(ds.setpoint.values.max())
    g_true = float(np.nanmedian(truth.em_gain.sel(setpoint=top).values))
    g = ds.cots_em_gain.sel(setpoint=top).values
    assert np.isfinite(g).sum() >= 1
    # read noise (neglected by COTS) inflates the variance a little even at high gain
    assert np.nanmean(g) == pytest.approx(g_true, rel=0.15)


# --------------------------------------------------------------------------------------
# Bad input: one line naming the file and the problem
# --------------------------------------------------------------------------------------
def _cli_error(capsys, *argv):
    code = cli.main(["cots", *map(str, argv)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err
    return err


def test_missing_e_per_adu(tmp_path, capsys):
    manifest = _write_beads(tmp_path, setpoints=(100,), frames=12, e_per_adu=False)
    with pytest.raises(errors.ManifestError, match="needs e_per_adu"):
        cots_calibrate(manifest)
    err = _cli_error(capsys, manifest, "-o", tmp_path / "out")
    assert str(manifest) in err and "e_per_adu" in err


def test_only_1x(tmp_path, capsys):
    manifest = _write_beads(tmp_path, setpoints=(1,), frames=12)
    err = _cli_error(capsys, manifest, "-o", tmp_path / "out")
    assert str(manifest) in err and "em_gain_setpoint > 1" in err


def test_too_few_frames(tmp_path, capsys):
    manifest = _write_beads(tmp_path, setpoints=(1, 100), frames=6)
    err = _cli_error(capsys, manifest, "-o", tmp_path / "out")
    assert "beads_100x.tif" in err and "at least 10 frames" in err


def test_no_beads_found(tmp_path, capsys):
    manifest = _write_beads(tmp_path, setpoints=(100,), frames=12, beads=())
    with pytest.raises(errors.InputError, match="no beads found"):
        cots_calibrate(manifest)
    err = _cli_error(capsys, manifest, "-o", tmp_path / "out")
    assert "beads_100x.tif" in err and "no beads found" in err


def test_beads_only_at_the_edge(tmp_path):
    manifest = _write_beads(tmp_path, setpoints=(100,), frames=12, beads=((2, 20),))
    with pytest.raises(errors.InputError, match="1 candidate.*edge"):
        cots_calibrate(manifest)


def test_bad_options(tmp_path, capsys):
    manifest = _write_beads(tmp_path, setpoints=(100,), frames=12)
    assert "--half-size" in _cli_error(capsys, manifest, "-o", tmp_path / "o", "--half-size", "0")
    assert "--width" in _cli_error(capsys, manifest, "-o", tmp_path / "o", "--width", "-1")
