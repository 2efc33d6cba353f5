"""Bead fitting with the exact noise model (emccdcal.beads): each frame's intensity and
background, the bead's position and width shared by its frames."""

from __future__ import annotations

import math

import numpy as np
import pytest

from emccdcal.beads import fit as bead_fit
from emccdcal.beads import psf_check
from emccdcal.model import noise, psf
from emccdcal.simulate.beads import bead_scene
from emccdcal.simulate.camera import simulate_frames

PHI = 3.859
SIGMA = 15.5
SIGMA_DARK = math.sqrt(SIGMA**2 + 1.0 / 12.0)  # SD of dark counts: what a fit uses
SHAPE = (32, 48)
TRUE_POS = np.array([[8.3, 9.6], [22.7, 24.2], [12.4, 37.8]])
N_TRUE = 5000.0
WIDTH = 1.3
BACKGROUND = 10.0
FRAMES = 300
#: The register the fits here assume: the one the scenes are simulated with.
GAMMA = noise.EMModel("gamma")


def _offset_map():
    rng = np.random.default_rng(5)
    return 580.0 + rng.normal(0.0, 0.5, SHAPE)


def _stack(g, seed, frames=FRAMES, **kw):
    scene = bead_scene(TRUE_POS, N_TRUE, WIDTH, BACKGROUND, *SHAPE)
    return simulate_frames(
        scene,
        em_gain=g,
        e_per_adu=PHI,
        offset=_offset_map(),
        read_noise=SIGMA,
        frames=frames,
        seed=seed,
        **kw,
    )


@pytest.fixture(scope="module")
def fitted():
    """Fits under the true calibration at 1× (PN), 5× and 300× (gamma data)."""
    out = {}
    for g, seed in ((1.0, 11), (4.78, 12), (261.6, 13)):
        frames = _stack(g, seed)
        pos = np.rint(TRUE_POS).astype(int)
        out[g] = (
            frames,
            bead_fit.fit_beads(
                frames,
                pos,
                offset=_offset_map(),
                read_noise=SIGMA_DARK,
                e_per_adu=PHI,
                em_gain=g,
                em_model=GAMMA,
            ),
        )
    return out


@pytest.mark.slow
@pytest.mark.parametrize("g", [1.0, 4.78, 261.6])
def test_true_calibration_gives_unbiased_intensities_and_honest_errors(fitted, g):
    _, fit = fitted[g]
    assert fit.intensity.shape == (3, FRAMES) and fit.params.shape == (3, FRAMES, 5)
    ok = fit.converged
    assert ok.mean() > 0.98
    N, se = fit.intensity[ok], fit.intensity_se[ok]
    scatter = N.std(ddof=1)
    se_of_mean = scatter / math.sqrt(N.size)
    # unbiased: the mean over frames (and beads) within 1 % of the truth, and within 4 SE
    assert abs(N.mean() / N_TRUE - 1) < 0.01
    assert abs(N.mean() - N_TRUE) < 4 * se_of_mean
    # honest: the RMS standard error agrees with the scatter over frames within 10 %
    assert np.sqrt(np.mean(se**2)) / scatter == pytest.approx(1.0, abs=0.10)
    # positions (sensor coordinates), width and background
    y, x = fit.params[..., 1], fit.params[..., 0]
    np.testing.assert_allclose(np.median(y, axis=1), TRUE_POS[:, 0], atol=0.05)
    np.testing.assert_allclose(np.median(x, axis=1), TRUE_POS[:, 1], atol=0.05)
    assert np.median(fit.params[..., 2][ok]) == pytest.approx(WIDTH, rel=0.02)
    assert np.mean(fit.params[..., 4][ok]) == pytest.approx(BACKGROUND, abs=1.0)


@pytest.mark.slow
def test_faint_beads_at_1x_converge_and_stay_unbiased():
    """1000 e- beads at 1x (read noise 60 e- per pixel): a per-frame fit of the shape
    converged in 69 % of frames and came out 27 % high; with the shape shared by the
    bead's frames every frame converges and the mean is the truth's."""
    n_true, width, background = 1000.0, 1.4, 15.0
    scene = bead_scene(TRUE_POS, n_true, width, background, *SHAPE)
    frames = simulate_frames(
        scene,
        em_gain=1.0,
        e_per_adu=PHI,
        offset=_offset_map(),
        read_noise=SIGMA,
        frames=FRAMES,
        seed=21,
    )
    fit = bead_fit.fit_beads(
        frames,
        np.rint(TRUE_POS).astype(int),
        offset=_offset_map(),
        read_noise=SIGMA_DARK,
        e_per_adu=PHI,
        em_gain=1.0,
        em_model=GAMMA,
    )
    ok = fit.converged
    assert ok.mean() >= 0.99
    N, se = fit.intensity[ok], fit.intensity_se[ok]
    assert abs(N.mean() - n_true) < 4 * N.std(ddof=1) / math.sqrt(N.size)
    assert abs(N.mean() / n_true - 1) < 0.05
    assert np.sqrt(np.mean(se**2)) / N.std(ddof=1) == pytest.approx(1.0, abs=0.10)
    # the width is the bead's: one value in all its frames, near the truth
    assert np.ptp(fit.params[..., 2], axis=1) == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(fit.params[:, 0, 2], width, rtol=0.05)
    # held fixed where given (e.g. pooled over set-points): the intensities follow it
    wider = bead_fit.fit_beads(
        frames,
        fit.positions,
        offset=_offset_map(),
        read_noise=SIGMA_DARK,
        e_per_adu=PHI,
        em_gain=1.0,
        fixed_width=fit.params[:, 0, 2] * 1.05,
        em_model=GAMMA,
    )
    np.testing.assert_allclose(wider.params[:, 0, 2], fit.params[:, 0, 2] * 1.05)
    assert wider.intensity[ok].mean() > N.mean()


@pytest.mark.slow
def test_a_background_per_frame_where_asked(fitted):
    frames, shared = fitted[261.6]
    fit = bead_fit.fit_beads(
        frames[:60],
        shared.positions,
        offset=_offset_map(),
        read_noise=SIGMA_DARK,
        e_per_adu=PHI,
        em_gain=261.6,
        background="frame",
        em_model=GAMMA,
    )
    assert fit.converged.all()
    assert np.ptp(fit.params[..., 4], axis=1).min() > 0  # one per frame
    assert np.ptp(fit.params[..., 2], axis=1).max() == pytest.approx(0.0, abs=1e-12)
    assert fit.params[..., 4].mean() == pytest.approx(BACKGROUND, abs=1.0)
    assert fit.intensity.mean() == pytest.approx(N_TRUE, rel=0.01)
    with pytest.raises(ValueError, match="background must be 'shared' or 'frame'"):
        bead_fit.fit_beads(
            frames[:5],
            shared.positions,
            offset=_offset_map(),
            read_noise=SIGMA_DARK,
            e_per_adu=PHI,
            em_gain=261.6,
            background="pixel",
            em_model=GAMMA,
        )


@pytest.mark.slow
def test_shared_widths_weigh_each_set_point_by_its_precision(fitted):
    fits = [fitted[g][1] for g in (1.0, 4.78, 261.6)]
    w = psf_check.shared_widths(fits)
    per = np.stack([f.params[:, 0, 2] for f in fits])
    se = np.stack([f.se[:, 0, 2] for f in fits])
    np.testing.assert_allclose(w, (per / se**2).sum(0) / (1 / se**2).sum(0))
    assert np.all(w >= per.min(0)) and np.all(w <= per.max(0))
    np.testing.assert_allclose(w, WIDTH, rtol=0.02)


@pytest.mark.slow
def test_fit_is_the_maximum_of_the_exact_likelihood(fitted):
    """Each frame's intensity maximises that frame's exact likelihood; the bead's
    position, width and background, shared by its frames, maximise the sum over them."""
    frames, fit = fitted[4.78]
    h = bead_fit.DEFAULT_HALF_SIZE
    b = 1
    r, c = fit.positions[b]
    box = np.asarray(frames[:, r - h : r + h + 1, c - h : c + h + 1])
    off = _offset_map()[r - h : r + h + 1, c - h : c + h + 1]
    rows = np.arange(r - h, r + h + 1)
    cols = np.arange(c - h, c + h + 1)

    def loglik(p, f):
        E = psf.spot_image(p, rows, cols)
        return noise.logpmf(box[f], E, 4.78, PHI, off, SIGMA_DARK, em_model="gamma").sum()

    f = 7
    p = fit.params[b, f]
    assert loglik(p, f) == pytest.approx(fit.loglik[b, f], abs=1e-6)
    for i in (3,):  # the frame's own
        for sign in (-1, 1):
            q = p.copy()
            q[i] += sign * 0.3 * fit.se[b, f, i]
            assert loglik(q, f) < loglik(p, f)
    assert np.ptp(fit.params[b, :, [0, 1, 2, 4]], axis=1) == pytest.approx(0.0, abs=1e-12)

    def total(shift):
        E = psf.spot_image(fit.params[b] + shift, rows, cols)  # every frame at once
        return noise.logpmf(box, E, 4.78, PHI, off, SIGMA_DARK, em_model="gamma").sum()

    best = total(0.0)
    assert best == pytest.approx(fit.loglik[b].sum(), abs=1e-5)
    for i in (0, 1, 2, 4):  # the bead's shared position, width and background
        for sign in (-1, 1):
            shift = np.zeros(5)
            shift[i] = sign * 0.3 * fit.se[b, f, i]
            assert total(shift) < best


@pytest.mark.slow
def test_wrong_gain_scales_the_intensities(fitted):
    frames, right = fitted[4.78]
    wrong = bead_fit.fit_beads(
        frames,
        right.positions,
        offset=_offset_map(),
        read_noise=SIGMA_DARK,
        e_per_adu=PHI,
        em_gain=1.1 * 4.78,
        em_model=GAMMA,
    )
    ok = right.converged & wrong.converged
    ratio = wrong.intensity[ok].mean() / right.intensity[ok].mean()
    assert ratio == pytest.approx(1 / 1.1, rel=0.01)


def test_detect_beads_on_the_mean_image():
    frames = _stack(22.95, 3, frames=40)
    found = bead_fit.detect_beads(frames, _offset_map(), width=WIDTH)
    assert sorted(map(tuple, found.positions)) == sorted(map(tuple, np.rint(TRUE_POS).astype(int)))
    img = bead_fit.mean_image(frames, _offset_map())
    assert img.shape == SHAPE
    # offset-subtracted mean in ADU: the background level times g/φ
    assert np.median(img) == pytest.approx(BACKGROUND * 22.95 / PHI, rel=0.05)


def test_saturated_counts_are_left_out():
    frames = _stack(22.95, 4, frames=30)
    pos = np.rint(TRUE_POS).astype(int)
    adc_max = int(np.percentile(frames, 99.9))
    clipped = np.minimum(frames, adc_max)
    fit = bead_fit.fit_beads(
        clipped,
        pos,
        offset=_offset_map(),
        read_noise=SIGMA_DARK,
        e_per_adu=PHI,
        em_gain=22.95,
        adc_max=adc_max,
        em_model=GAMMA,
    )
    h = bead_fit.DEFAULT_HALF_SIZE
    in_boxes = sum(
        int((clipped[:, r - h : r + h + 1, c - h : c + h + 1] >= adc_max).sum()) for r, c in pos
    )
    assert fit.n_saturated == in_boxes > 0
    assert fit.converged.mean() > 0.9
    assert np.mean(fit.intensity[fit.converged]) == pytest.approx(N_TRUE, rel=0.03)


def test_bad_input():
    frames = _stack(1.0, 6, frames=5)
    kw = dict(
        offset=_offset_map(), read_noise=SIGMA_DARK, e_per_adu=PHI, em_gain=1.0, em_model=GAMMA
    )
    with pytest.raises(ValueError, match=r"bead at \(row 2, col 20\) is closer than half_size"):
        bead_fit.fit_beads(frames, [[2, 20]], **kw)
    phi = np.full(SHAPE, PHI)
    phi[22, 25] = np.nan
    with pytest.raises(
        ValueError,
        match=r"e_per_adu is not finite > 0 in the box of the bead "
        r"at \(row 23, col 24\)",
    ):
        bead_fit.fit_beads(frames, [[8, 10], [23, 24]], **(kw | {"e_per_adu": phi}))
    with pytest.raises(ValueError, match="em_gain"):
        bead_fit.fit_beads(frames, [[8, 10]], **(kw | {"em_gain": 0.5}))
    with pytest.raises(ValueError, match="frames, rows, cols"):
        bead_fit.fit_beads(frames[0], [[8, 10]], **kw)
    with pytest.raises(ValueError, match="half_size must be at least 2"):
        bead_fit.fit_beads(frames, [[8, 10]], half_size=1, **kw)
    with pytest.raises(ValueError, match="offset has shape"):
        bead_fit.fit_beads(frames, [[8, 10]], **(kw | {"offset": np.zeros((3, 3))}))
    empty = bead_fit.fit_beads(frames, np.zeros((0, 2), int), **kw)
    assert empty.params.shape == (0, 5, 5)


def test_bead_fits_under_the_exact_register():
    """Beads at 5x from an exact register, fitted with the cascade model under the true
    calibration: unbiased intensities with honest errors, as the gamma model is on gamma
    data."""
    frames = _stack(4.78, 14, frames=150, multiplication="cascade", stages=536)
    pos = np.rint(TRUE_POS).astype(int)
    fit = bead_fit.fit_beads(
        frames,
        pos,
        offset=_offset_map(),
        read_noise=SIGMA_DARK,
        e_per_adu=PHI,
        em_gain=4.78,
        em_model=noise.EMModel("cascade", 536),
    )
    ok = fit.converged
    assert ok.mean() > 0.98
    N = fit.intensity[ok]
    assert abs(N.mean() - N_TRUE) < 4 * N.std(ddof=1) / math.sqrt(N.size)
    assert np.sqrt(np.mean(fit.intensity_se[ok] ** 2)) / N.std(ddof=1) == pytest.approx(
        1.0, abs=0.15
    )


# --------------------------------------------------------------------------------------
# The residual image (the paper's second pass)
# --------------------------------------------------------------------------------------
def test_residual_image_values_and_derivatives():
    q = 4
    nodes = np.linspace(-6.0, 6.0, 49)
    yy, xx = np.meshgrid(nodes, nodes, indexing="ij")
    smooth = 0.01 * np.exp(-0.5 * ((yy - 0.3) ** 2 + (xx + 0.2) ** 2) / 2.0**2) * (1 + 0.3 * xx)
    image = psf.ResidualImage(np.stack([smooth, -smooth]), q)
    assert len(image) == 2 and image.extent == 6.0
    rng = np.random.default_rng(1)
    dy, dx = rng.uniform(-4, 4, (2, 30)), rng.uniform(-4, 4, (2, 30))
    which = np.array([0, 1])
    R, R_dy, R_dx = image.evaluate(which, dy, dx)
    exact = 0.01 * np.exp(-0.5 * ((dy - 0.3) ** 2 + (dx + 0.2) ** 2) / 4.0) * (1 + 0.3 * dx)
    np.testing.assert_allclose(R[0], exact[0], atol=2e-5)  # the spline through the nodes
    np.testing.assert_allclose(R[1], -R[0] * exact[1] / exact[0], atol=2e-5)
    h = 1e-5
    num_dy = (image.evaluate(which, dy + h, dx)[0] - image.evaluate(which, dy - h, dx)[0]) / (2 * h)
    num_dx = (image.evaluate(which, dy, dx + h)[0] - image.evaluate(which, dy, dx - h)[0]) / (2 * h)
    np.testing.assert_allclose(R_dy, num_dy, atol=1e-8)
    np.testing.assert_allclose(R_dx, num_dx, atol=1e-8)
    outside = image.evaluate(np.zeros(1, int), np.full((1, 2), 6.5), np.zeros((1, 2)))
    assert all(np.all(v == 0) for v in outside)
    with pytest.raises(ValueError, match="residual image"):
        psf.ResidualImage(np.zeros((9, 9)), q)


@pytest.mark.slow
def test_residual_pass_on_gaussian_beads_changes_nothing(fitted):
    """The Gaussian is the PSF here: the mean images are described to within their noise,
    and the residual image's pass gives the same intensities."""
    fits = [fitted[g][1] for g in (1.0, 4.78, 261.6)]
    for f in fits:
        assert f.residual.shape == (3, 9, 9)
        m = psf_check.psf_mismatch(f)
        assert 0.7 < m["chi2_per_pixel"] < 1.4
        assert abs(m["missed_fraction"]) < 0.01
    for per_bead in (True, False):
        image = psf_check.residual_image(fits, per_bead=per_bead)
        assert len(image) == (3 if per_bead else 1)
        frames, before = fitted[261.6]
        after = bead_fit.fit_beads(
            frames,
            before.positions,
            offset=_offset_map(),
            read_noise=SIGMA_DARK,
            e_per_adu=PHI,
            em_gain=261.6,
            fixed_width=before.params[:, 0, 2],
            residual=image,
            em_model=GAMMA,
        )
        assert after.converged.all()
        diff = after.intensity.mean(axis=1) / before.intensity.mean(axis=1) - 1
        sem = before.intensity.std(axis=1, ddof=1) / math.sqrt(FRAMES) / N_TRUE
        assert np.all(np.abs(diff) < 2 * sem)  # far below the beads' own noise


@pytest.mark.slow
def test_residual_image_describes_a_psf_with_a_halo():
    """A PSF with 20 % of its light in a halo of SD 3 px: the Gaussian misses it (the
    mean images' chi2 per pixel far above 1 at 300x); with each bead's residual image
    added, the model describes them, and the intensities stay consistent between 1x
    and 300x."""
    scene = bead_scene(TRUE_POS, N_TRUE, WIDTH, BACKGROUND, *SHAPE, halo=0.2, halo_width=3.0)
    pos = np.rint(TRUE_POS).astype(int)
    fits, stacks = [], {}
    for g, seed in ((1.0, 31), (261.6, 32)):
        stacks[g] = simulate_frames(
            scene,
            em_gain=g,
            e_per_adu=PHI,
            offset=_offset_map(),
            read_noise=SIGMA,
            frames=FRAMES,
            seed=seed,
        )
        fits.append(
            bead_fit.fit_beads(
                stacks[g],
                pos,
                offset=_offset_map(),
                read_noise=SIGMA_DARK,
                e_per_adu=PHI,
                em_gain=g,
                em_model=GAMMA,
            )
        )
    assert psf_check.psf_mismatch(fits[1])["chi2_per_pixel"] > 2.0
    widths = psf_check.shared_widths(fits)
    image = psf_check.residual_image(fits)
    second = [
        bead_fit.fit_beads(
            stacks[g],
            pos,
            offset=_offset_map(),
            read_noise=SIGMA_DARK,
            e_per_adu=PHI,
            em_gain=g,
            fixed_width=widths,
            residual=image,
            em_model=GAMMA,
        )
        for g in (1.0, 261.6)
    ]
    assert all(f.converged.all() for f in second)
    assert psf_check.psf_mismatch(second[1])["chi2_per_pixel"] < 1.3
    ratio = second[1].intensity.mean() / second[0].intensity.mean()
    err = math.hypot(
        *(
            f.intensity.std(ddof=1) / math.sqrt(f.intensity.size) / f.intensity.mean()
            for f in second
        )
    )
    assert abs(ratio - 1) < 4 * err


@pytest.mark.slow
def test_offset_map_error_of_the_mean_intensity(fitted):
    """``intensity_offset_se`` is the linear response of a bead's mean intensity to its
    offset map: with an error in one pixel only, shifting that pixel's offset by its SE
    moves the mean intensity by the SE (1x: every pixel's read noise, 60 e-)."""
    frames, fit = fitted[1.0]
    r, c = fit.positions[0]
    one = np.zeros(SHAPE)
    one[r, c] = 1.0  # ADU
    base = bead_fit.fit_beads(
        frames,
        fit.positions,
        offset=_offset_map(),
        read_noise=SIGMA_DARK,
        e_per_adu=PHI,
        em_gain=1.0,
        offset_se=one,
        em_model=GAMMA,
    )
    shifted = bead_fit.fit_beads(
        frames,
        fit.positions,
        offset=_offset_map() + one,
        read_noise=SIGMA_DARK,
        e_per_adu=PHI,
        em_gain=1.0,
        em_model=GAMMA,
    )
    moved = shifted.intensity.mean(axis=1) - base.intensity.mean(axis=1)
    assert abs(moved[0]) == pytest.approx(base.intensity_offset_se[0], rel=0.05)
    assert base.intensity_offset_se[1:] == pytest.approx(0.0)
    # 2000 dark frames: every pixel's offset known to 15.5/sqrt(2000) ADU
    full = bead_fit.fit_beads(
        frames,
        fit.positions,
        offset=_offset_map(),
        read_noise=SIGMA_DARK,
        e_per_adu=PHI,
        em_gain=1.0,
        offset_se=SIGMA / math.sqrt(2000),
        em_model=GAMMA,
    )
    rel = full.intensity_offset_se / N_TRUE
    assert np.all((rel > 0.0005) & (rel < 0.01))


@pytest.mark.slow
def test_the_error_of_a_beads_shared_parameters_is_in_its_mean():
    """A bead's position, width and background are one estimate for all its frames: their
    error moves every frame's intensity alike and never averages away. At 1x (read noise
    60 e- a pixel) it is larger than the frames' scatter. Over 30 seeds of 3 beads x 60
    frames, z = (mean - truth)/SE is standard normal with it (SD 0.8-1.25), about twice
    too wide with the frames' scatter alone."""
    z_scatter, z_full = [], []
    pos = np.rint(TRUE_POS).astype(int)
    for seed in range(30):
        fit = bead_fit.fit_beads(
            _stack(1.0, 500 + seed, frames=60),
            pos,
            offset=_offset_map(),
            read_noise=SIGMA_DARK,
            e_per_adu=PHI,
            em_gain=1.0,
            em_model=GAMMA,
        )
        for b in range(3):
            N = fit.intensity[b][fit.converged[b]]
            scatter = N.std(ddof=1) / math.sqrt(N.size)
            z_scatter.append((N.mean() - N_TRUE) / scatter)
            z_full.append((N.mean() - N_TRUE) / math.hypot(scatter, fit.intensity_shared_se[b]))
    assert 0.8 < np.std(z_full, ddof=1) < 1.25
    assert np.std(z_scatter, ddof=1) > 1.5
    assert abs(np.mean(z_full)) < 3 / math.sqrt(len(z_full))


def test_a_held_widths_error_enters_the_mean_as_its_linear_response():
    """A width held at a value with an SE (pooled over set-points): the mean intensity's
    shared SE gains |d mean(N)/dw|·SE, and that slope is the refit's (finite difference)."""
    frames = _stack(1.0, 7, frames=100)
    pos = np.rint(TRUE_POS).astype(int)
    kw = dict(
        offset=_offset_map(), read_noise=SIGMA_DARK, e_per_adu=PHI, em_gain=1.0, em_model=GAMMA
    )
    width, step = np.full(3, WIDTH), 0.002
    held = bead_fit.fit_beads(frames, pos, fixed_width=width, **kw)
    known = bead_fit.fit_beads(
        frames, pos, fixed_width=width, fixed_width_se=np.array([0.01, 0.0, 0.0]), **kw
    )
    moved = bead_fit.fit_beads(frames, pos, fixed_width=width + step, **kw)
    mean = lambda f: np.array([f.intensity[b][f.converged[b]].mean() for b in range(3)])
    slope = (mean(moved) - mean(held)) / step  # e- per pixel of width, about N/w
    added = np.sqrt(known.intensity_shared_se**2 - held.intensity_shared_se**2)
    assert added[0] == pytest.approx(abs(slope[0]) * 0.01, rel=0.02)
    np.testing.assert_allclose(added[1:], 0.0, atol=1e-6)


def test_residual_is_per_unit_intensity_of_the_frames_it_averages():
    """A bead off (held at N = 0) in half its frames: its residual is averaged over the
    frames with light, and so is the intensity it is divided by."""
    B, F, n = 1, 10, 9
    params = np.zeros((B, F, 5))
    params[..., :3] = [10.0, 10.0, 1.3]
    params[0, :, 3] = [1000.0] * 5 + [1e-3] * 5
    fit = bead_fit.BeadFits(
        positions=np.array([[10, 10]]),
        params=params,
        se=np.ones((B, F, 5)),
        loglik=np.zeros((B, F)),
        converged=np.ones((B, F), bool),
        iterations=np.ones((B, 3), int),
        retabulated=0,
        n_saturated=0,
        residual=np.full((B, n, n), 10.0),
        residual_se=np.full((B, n, n), 1.0),
        intensity_offset_se=np.zeros(B),
    )
    assert psf_check.psf_mismatch(fit)["missed_fraction"] == pytest.approx(81 * 10 / 1000)
    image = psf_check.residual_image([fit], per_bead=True)
    R = image.evaluate(np.zeros(1, int), np.zeros((1, 1)), np.zeros((1, 1)))[0]
    assert R[0, 0] == pytest.approx(10 / 1000, rel=0.01)


def test_a_residual_images_variance_is_its_sampling_variance():
    """The image is linear in the residuals it is built from: over many draws of them,
    the variance of its nodes is the variance it reports (and at pixels what
    ``variance_at`` interpolates, to within the spline's ~10 %)."""
    B, F, n = 2, 10, 9
    rng = np.random.default_rng(3)
    params = np.zeros((B, F, 5))
    params[..., 2:4] = [1.3, 1000.0]
    params[0, :, :2], params[1, :, :2] = [10.3, 10.2], [20.7, 30.4]  # x, y
    pos = np.array([[10, 10], [30, 21]])
    se = rng.uniform(0.5, 2.0, (B, n, n))

    def fit_with_noise():
        r = rng.normal(0.0, 1.0, (2, B, n, n)) * se
        return bead_fit.BeadFits(
            positions=pos,
            params=params,
            se=np.ones((B, F, 5)),
            loglik=np.zeros((B, F)),
            converged=np.ones((B, F), bool),
            iterations=np.ones((B, 3), int),
            retabulated=0,
            n_saturated=0,
            residual=r[0],
            residual_se=se,
            intensity_offset_se=np.zeros(B),
            residual_halves=r,
            residual_halves_se=np.stack([se, se]),
        )

    images = [
        psf_check.residual_image([fit_with_noise(), fit_with_noise()], half=0) for _ in range(400)
    ]
    variance = images[0].variance
    used = variance > 0
    ratio = np.var([im.values for im in images], axis=0)[used] / variance[used]
    assert ratio.mean() == pytest.approx(1.0, abs=0.03)  # 400 draws: ±0.07 per node
    local = np.arange(n) - n // 2
    dy = (pos[0, 0] + local - 10.2)[:, None] * np.ones(n)
    dx = np.ones(n)[:, None] * (pos[0, 1] + local - 10.3)
    at_pixels = np.var([im.evaluate(np.zeros(n, int), dy, dx)[0] for im in images], axis=0)
    assert np.median(at_pixels / images[0].variance_at(np.zeros(n, int), dy, dx)) == pytest.approx(
        1.0, abs=0.1
    )
    # two fits pooled: the image's variance is half a single residual's, per unit N
    assert np.median(
        images[0].variance_at(np.zeros(n, int), dy, dx) / (se[0] / 1000.0) ** 2
    ) == pytest.approx(0.5, abs=0.1)
    with pytest.raises(ValueError, match="half must be"):
        psf_check.residual_image([fit_with_noise()], half=2)


@pytest.mark.slow
def test_a_residual_image_is_scored_on_frames_it_was_not_built_on(fitted):
    """Held out: on Gaussian beads, the residual model's χ² per pixel on the half of the
    frames its image was not built on is 1 within its sampling error (the image's own
    variance counted). A halo that appears halfway through an acquisition, which the
    first half's image never saw, is flagged when the frames are split in time; split
    into even and odd frames, both halves see it and the image learns it."""
    fits = [fitted[g][1] for g in (1.0, 4.78, 261.6)]
    image = psf_check.residual_image(fits, half=0)
    frames, before = fitted[261.6]
    kw = dict(
        offset=_offset_map(), read_noise=SIGMA_DARK, e_per_adu=PHI, em_gain=261.6, em_model=GAMMA
    )
    after = bead_fit.fit_beads(
        frames, before.positions, fixed_width=before.params[:, 0, 2], residual=image, **kw
    )
    held_out = psf_check.psf_mismatch(after, half=1, image=image)
    assert abs(held_out["chi2_per_pixel"] - 1.0) < 3 * held_out["chi2_per_pixel_se"]

    halo = bead_scene(TRUE_POS, N_TRUE, WIDTH, BACKGROUND, *SHAPE, halo=0.2, halo_width=3.0)
    later = simulate_frames(
        halo,
        em_gain=261.6,
        e_per_adu=PHI,
        offset=_offset_map(),
        read_noise=SIGMA,
        frames=FRAMES // 4,
        seed=33,
    )
    stack = np.concatenate([frames[: FRAMES // 4], later])  # 150 frames: the halo at 5+ SE
    chi2 = {}
    for split in ("time", "alternate"):
        gauss = bead_fit.fit_beads(stack, before.positions, residual_split=split, **kw)
        image = psf_check.residual_image([gauss], half=0)
        third = bead_fit.fit_beads(
            stack,
            before.positions,
            residual=image,
            fixed_width=gauss.params[:, 0, 2],
            residual_split=split,
            **kw,
        )
        chi2[split] = psf_check.psf_mismatch(third, half=1, image=image)["chi2_per_pixel"]
    assert chi2["time"] > 2.0  # validate's PSF_CHI2: flagged
    assert chi2["alternate"] < 1.5
    with pytest.raises(ValueError, match="split must be"):
        bead_fit.fit_beads(frames, before.positions, residual_split="random", **kw)
