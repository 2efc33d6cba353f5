"""Mean–variance (photon-transfer) methods: exact moments, simulated truth, real data."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import REAL_DATA as DATA

from emccdcal.fit.mv import fieller_interval, fit_mv_adu, fit_mv_gain, mean_ratio_gains

Z95 = 1.959963984540054


def coverage(estimate, se, truth):
    """Fraction of 95 % intervals estimate ± 1.96·se that contain the truth."""
    return float(np.mean(np.abs(np.asarray(estimate) - truth) <= Z95 * np.asarray(se)))


def sample_moments(rng, mu, var, n):
    """Simulate n frames of Gaussian counts per pixel; return sample mean and var (ddof=1).

    ``mu`` and ``var`` are per-pixel arrays (P,). Counts ~ N(mu, var), drawn as frames.
    """
    counts = mu + np.sqrt(var) * rng.standard_normal((n, mu.size))
    return counts.mean(axis=0), counts.var(axis=0, ddof=1)


# --------------------------------------------------------------------------------------
# Exact moments: the estimators are consistent (no noise → the truth, to round-off)
# --------------------------------------------------------------------------------------
PHI, S0, SIGMA = 3.5, 100.0, 10.0


def exact_adu_moments(E):
    return S0 + E / PHI, SIGMA**2 + E / PHI**2


@pytest.mark.parametrize("intercept", [False, True])
@pytest.mark.parametrize("weighted", [False, True])
def test_mv_adu_exact_moments(intercept, weighted):
    E = np.array([20.0, 80.0, 300.0, 1200.0])[:, None] * np.array([1.0, 1.5, 2.0])
    mean, var = exact_adu_moments(E)
    fit = fit_mv_adu(mean, var, S0, SIGMA, 5000, intercept=intercept, weighted=weighted)
    np.testing.assert_allclose(fit.e_per_adu, PHI, rtol=1e-12)
    np.testing.assert_allclose(fit.photoelectrons, E, rtol=1e-12)
    np.testing.assert_allclose(fit.chi2, 0.0, atol=1e-18)
    assert fit.dof == (2 if intercept else 3)
    assert fit.valid.all()
    assert np.all(fit.e_per_adu_se > 0) and np.all(fit.photoelectrons_se > 0)


def test_mv_adu_image_shaped_pixels_equal_flat():
    rng = np.random.default_rng(1)
    E = rng.uniform(50, 2000, size=(5, 4, 3))
    mean, var = exact_adu_moments(E)
    var = var * rng.uniform(0.97, 1.03, size=var.shape)
    offset = np.full((4, 3), S0)
    img = fit_mv_adu(mean, var, offset, SIGMA, [1000, 2000, 3000, 4000, 5000])
    flat = fit_mv_adu(
        mean.reshape(5, 12), var.reshape(5, 12), S0, SIGMA, [1000, 2000, 3000, 4000, 5000]
    )
    assert img.e_per_adu.shape == (4, 3) and img.photoelectrons.shape == (5, 4, 3)
    np.testing.assert_allclose(img.e_per_adu.ravel(), flat.e_per_adu)
    np.testing.assert_allclose(img.e_per_adu_se.ravel(), flat.e_per_adu_se)
    np.testing.assert_allclose(img.photoelectrons_se.reshape(5, 12), flat.photoelectrons_se)


def test_mv_gain_exact_moments_single_and_multi_level():
    E = 40.0
    # gain series 1, 5, 150 (one level each) plus an intensity series at 20× (3 levels)
    sp = np.array([1.0, 5.0, 150.0, 20.0, 20.0, 20.0])
    Es = np.array([E, E, E, 10.0, 40.0, 160.0])
    F2 = np.where(sp == 1, 1.0, 2.0)
    mean = (S0 + sp * Es / PHI)[:, None]
    var = (SIGMA**2 + F2 * Es * (sp / PHI) ** 2)[:, None]
    fit = fit_mv_gain(mean, var, S0, SIGMA, 5000, PHI, sp)
    assert fit.setpoints.tolist() == [1.0, 5.0, 20.0, 150.0]
    np.testing.assert_allclose(fit.em_gain[:, 0], [1.0, 5.0, 20.0, 150.0], rtol=1e-12)
    np.testing.assert_allclose(fit.photoelectrons[:, 0], Es, rtol=1e-12)
    assert fit.em_gain_se[0, 0] == 0.0 and np.all(fit.em_gain_se[1:] > 0)
    assert fit.dof.tolist() == [0, 0, 2, 0]
    assert fit.valid.all()


def test_mv_gain_photoelectrons_do_not_depend_on_phi():
    sp = [1.0, 25.0, 100.0]
    mean = np.array([[110.0], [350.0], [1100.0]])
    var = np.array([[103.0], [4000.0], [60000.0]])
    a = fit_mv_gain(mean, var, S0, SIGMA, 5000, 3.5, sp)
    b = fit_mv_gain(mean, var, S0, SIGMA, 5000, 7.0, sp)
    np.testing.assert_allclose(a.photoelectrons[1:], b.photoelectrons[1:])
    np.testing.assert_allclose(b.em_gain[1:], 2 * a.em_gain[1:])
    np.testing.assert_allclose(b.photoelectrons[0], 2 * a.photoelectrons[0])  # 1×: E = x·φ


def test_mean_ratio_gains_exact():
    mean = np.array([[120.0, 130.0], [200.0, 250.0], [580.0, 700.0]])
    offset = np.array([[100.0], [100.0], [98.0]])
    r = mean_ratio_gains(mean, np.full(mean.shape, 150.0), offset, 5000, [1, 5, 25])
    np.testing.assert_allclose(r.em_gain, [[1, 1], [5, 5], [24.1, 602 / 30]])
    assert np.all(r.em_gain_se[0] == 0) and np.all(r.em_gain_se[1:] > 0)


# --------------------------------------------------------------------------------------
# Simulated Gaussian counts with known truth: accuracy and honest standard errors
# --------------------------------------------------------------------------------------
P = 2000  # pixels, simulated at once
N_FRAMES = 1000


@pytest.fixture(scope="module")
def adu_series():
    rng = np.random.default_rng(20210917)
    levels = np.array([20.0, 60.0, 150.0, 400.0, 1000.0, 2500.0])  # E, e⁻
    mean, var = zip(
        *(
            sample_moments(
                rng, np.full(P, S0 + E / PHI), np.full(P, SIGMA**2 + E / PHI**2), N_FRAMES
            )
            for E in levels
        )
    )
    return levels, np.array(mean), np.array(var)


@pytest.mark.parametrize("kw", [{}, {"weighted": False}, {"intercept": True}])
def test_mv_adu_recovers_truth_with_honest_se(adu_series, kw):
    levels, mean, var = adu_series
    fit = fit_mv_adu(mean, var, S0, SIGMA, N_FRAMES, **kw)
    assert fit.valid.all()
    # The mean over pixels within 3 standard errors of the mean, for the fitted slope
    # 1/φ, which is linear in the data. φ = 1/slope itself carries a second-order bias of
    # about φ·(SE/φ)², 0.4 % with an intercept here (documented), which 2000 pixels resolve.
    slope, slope_se = 1 / fit.e_per_adu, fit.e_per_adu_se / fit.e_per_adu**2
    assert abs(slope.mean() - 1 / PHI) < 3 * np.sqrt(np.mean(slope_se**2) / P)
    if not kw:
        se_of_mean = np.sqrt(np.mean(fit.e_per_adu_se**2) / P)
        assert abs(fit.e_per_adu.mean() - PHI) < 3 * se_of_mean
    # the per-pixel SE agrees with the scatter over pixels
    assert 0.9 < fit.e_per_adu.std(ddof=1) / np.sqrt(np.mean(fit.e_per_adu_se**2)) < 1.1
    assert 0.93 <= coverage(fit.e_per_adu, fit.e_per_adu_se, PHI) <= 0.97
    for i in (0, 3, 5):
        assert 0.93 <= coverage(fit.photoelectrons[i], fit.photoelectrons_se[i], levels[i]) <= 0.97
    # chi2 of a correct straight line: mean ≈ dof
    assert abs(fit.chi2.mean() - fit.dof) < 0.15 * fit.dof + 0.2


def test_weighted_fit_is_more_precise_than_ols(adu_series):
    _, mean, var = adu_series
    wls = fit_mv_adu(mean, var, S0, SIGMA, N_FRAMES)
    ols = fit_mv_adu(mean, var, S0, SIGMA, N_FRAMES, weighted=False)
    assert wls.e_per_adu.std() < ols.e_per_adu.std()
    assert np.median(wls.e_per_adu_se) < np.median(ols.e_per_adu_se)


GAINS = np.array([1.0, 5.0, 25.0, 100.0, 300.0])
E_GS = 30.0


@pytest.fixture(scope="module")
def gain_series():
    rng = np.random.default_rng(42)
    offsets = np.array([100.0, 99.0, 97.0, 95.0, 93.0])  # offset drifts with set-point
    sigmas = np.array([10.0, 10.0, 10.5, 11.0, 14.0])
    F2 = np.where(GAINS == 1, 1.0, 2.0)
    mean, var = zip(
        *(
            sample_moments(
                rng,
                np.full(P, s0 + g * E_GS / PHI),
                np.full(P, s**2 + f * E_GS * (g / PHI) ** 2),
                N_FRAMES,
            )
            for g, s0, s, f in zip(GAINS, offsets, sigmas, F2)
        )
    )
    return np.array(mean), np.array(var), offsets[:, None], sigmas[:, None]


def test_mv_gain_single_point_recovers_truth_with_honest_se(gain_series):
    mean, var, offsets, sigmas = gain_series
    fit = fit_mv_gain(mean, var, offsets, sigmas, N_FRAMES, PHI, GAINS)
    assert fit.valid.all()
    np.testing.assert_array_equal(fit.setpoints, GAINS)
    for k in range(1, GAINS.size):
        g, se = fit.em_gain[k], fit.em_gain_se[k]
        assert abs(g.mean() - GAINS[k]) < 3 * np.sqrt(np.mean(se**2) / P)
        assert 0.93 <= coverage(g, se, GAINS[k]) <= 0.97
    for a in range(GAINS.size):
        assert 0.93 <= coverage(fit.photoelectrons[a], fit.photoelectrons_se[a], E_GS) <= 0.97


def test_mv_gain_propagates_phi_uncertainty(gain_series):
    mean, var, offsets, sigmas = gain_series
    rng = np.random.default_rng(7)
    rel = 0.02  # 2 % uncertain φ, different in every pixel
    phi_hat = PHI * (1 + rel * rng.standard_normal(P))
    fit = fit_mv_gain(mean, var, offsets, sigmas, N_FRAMES, phi_hat, GAINS, e_per_adu_se=rel * PHI)
    without = fit_mv_gain(mean, var, offsets, sigmas, N_FRAMES, phi_hat, GAINS)
    assert np.all(fit.em_gain_se[1:] > without.em_gain_se[1:])
    for k in range(1, GAINS.size):
        assert 0.93 <= coverage(fit.em_gain[k], fit.em_gain_se[k], GAINS[k]) <= 0.97
    assert 0.93 <= coverage(fit.photoelectrons[0], fit.photoelectrons_se[0], E_GS) <= 0.97


def test_mv_gain_intensity_series_at_gain():
    rng = np.random.default_rng(3)
    g, levels = 20.0, np.array([5.0, 15.0, 40.0, 100.0])
    mean, var = zip(
        *(
            sample_moments(
                rng,
                np.full(P, S0 + g * E / PHI),
                np.full(P, SIGMA**2 + 2 * E * (g / PHI) ** 2),
                N_FRAMES,
            )
            for E in levels
        )
    )
    fit = fit_mv_gain(np.array(mean), np.array(var), S0, SIGMA, N_FRAMES, PHI, [g] * 4)
    assert fit.setpoints.tolist() == [g] and fit.dof.tolist() == [3]
    assert abs(fit.em_gain[0].mean() - g) < 3 * np.sqrt(np.mean(fit.em_gain_se[0] ** 2) / P)
    assert 0.93 <= coverage(fit.em_gain[0], fit.em_gain_se[0], g) <= 0.97
    for i in range(levels.size):
        assert 0.93 <= coverage(fit.photoelectrons[i], fit.photoelectrons_se[i], levels[i]) <= 0.97


def test_mean_ratio_gains_recover_truth_with_honest_se(gain_series):
    mean, var, offsets, _ = gain_series
    r = mean_ratio_gains(mean, var, offsets, N_FRAMES, GAINS)
    for k in range(1, GAINS.size):
        assert 0.93 <= coverage(r.em_gain[k], r.em_gain_se[k], GAINS[k]) <= 0.97


# --------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------
def test_errors():
    mean = np.array([[150.0, 160.0], [300.0, 320.0]])
    var = np.array([[120.0, 125.0], [160.0, 170.0]])
    with pytest.raises(ValueError, match="var has shape"):
        fit_mv_adu(mean, var[:, :1], S0, SIGMA, 100)
    with pytest.raises(ValueError, match="offset has shape"):
        fit_mv_adu(mean, var, np.full(3, S0), SIGMA, 100)
    with pytest.raises(ValueError, match="at least 1 level"):
        fit_mv_adu(mean[:0], var[:0], S0, SIGMA, 100)
    with pytest.raises(ValueError, match="non-positive signal"):
        fit_mv_adu(mean, var, 155.0, SIGMA, 100)
    with pytest.raises(ValueError, match="at least 2"):
        fit_mv_adu(mean, var, S0, SIGMA, 1)
    with pytest.raises(ValueError, match="n has 3 entries"):
        fit_mv_adu(mean, var, S0, SIGMA, [100, 100, 100])
    with pytest.raises(ValueError, match="NaN"):
        fit_mv_adu(np.where(mean > 299, np.nan, mean), var, S0, SIGMA, 100)
    with pytest.raises(ValueError, match="var must be positive"):
        fit_mv_adu(mean, 0 * var, S0, SIGMA, 100)
    with pytest.raises(ValueError, match="intercept needs at least 2 levels"):
        fit_mv_adu(mean[:1], var[:1], S0, SIGMA, 100, intercept=True)
    with pytest.raises(ValueError, match="one entry per acquisition"):
        fit_mv_gain(mean, var, S0, SIGMA, 100, PHI, [1.0])
    with pytest.raises(ValueError, match="e_per_adu must be positive"):
        fit_mv_gain(mean, var, S0, SIGMA, 100, 0.0, [1.0, 5.0])
    with pytest.raises(ValueError, match="exactly one acquisition at set-point 1"):
        mean_ratio_gains(mean, var, S0, 100, [5.0, 25.0])


def test_one_level_through_origin_is_allowed():
    fit = fit_mv_adu([[400.0]], [[100.0 + 300 / 3.5]], S0, SIGMA, 5000)
    np.testing.assert_allclose(fit.e_per_adu, [3.5])
    assert fit.dof == 0


def test_negative_slope_is_flagged_not_raised():
    # variance below the read noise at every level: the slope is negative
    fit = fit_mv_adu([[150.0], [200.0]], [[90.0], [95.0]], S0, SIGMA, 5000)
    assert not fit.valid[0] and np.isnan(fit.e_per_adu[0])


# --------------------------------------------------------------------------------------
# Real data (docs/validation.md)
# --------------------------------------------------------------------------------------
needs_data = pytest.mark.real_data


def _stack_moments(path):
    import tifffile

    counts = tifffile.imread(path).astype(np.float64)  # (frames, rows, cols)
    return counts.mean(axis=0), counts.var(axis=0, ddof=1), counts.shape[0]


def _map(path):
    import tifffile

    return tifffile.imread(path).astype(np.float64)


@pytest.fixture(scope="module")
def real_adu():
    d = DATA / "ADU"
    stats = [_stack_moments(d / f"1x-gain_level-{i:02d}.tif") for i in range(1, 7)]
    mean = np.array([s[0] for s in stats])
    var = np.array([s[1] for s in stats])
    n = [s[2] for s in stats]
    offset, sigma = _map(d / "1x-gain_no-signal_S0.tif"), _map(d / "1x-gain_no-signal_sigma.tif")
    return mean, var, offset, sigma, n


@pytest.fixture(scope="module")
def real_gs():
    d = DATA / "gain-GS"
    sp = [1, 5, 25, 100, 300]
    stats = [_stack_moments(d / f"{g}x-gain.tif") for g in sp]
    return (
        np.array([s[0] for s in stats]),
        np.array([s[1] for s in stats]),
        np.array([_map(d / f"{g}x-gain_no-signal_S0.tif") for g in sp]),
        np.array([_map(d / f"{g}x-gain_no-signal_sigma.tif") for g in sp]),
        [s[2] for s in stats],
        np.array(sp, dtype=float),
    )


@needs_data
def test_real_mv_adu_classical_fit_reproduces_reference(real_adu):
    # docs/validation.md "ADU 3.780 ± 0.070" is the unweighted fit with a free intercept.
    fit = fit_mv_adu(*real_adu, intercept=True, weighted=False)
    assert fit.valid.all() and fit.e_per_adu.shape == (3, 3)
    assert abs(fit.e_per_adu.mean() - 3.780) < 1e-3
    assert abs(fit.e_per_adu.std(ddof=1) - 0.070) < 1e-3


@needs_data
def test_real_mv_adu_default_fit(real_adu):
    # Our default (weighted, through the origin with the dark-map read noise) gives
    # 3.861 ± 0.079 over the 9 pixels: 0.08 above the classical fit, about one per-pixel
    # SE pair apart, and within a per-pixel SE of the IS-MLE φ of docs/validation.md
    fit = fit_mv_adu(*real_adu)
    assert fit.valid.all()
    assert abs(fit.e_per_adu.mean() - 3.780) < 0.12
    assert abs(fit.e_per_adu.mean() - 3.8624) < 0.01  # IS-MLE, mean of 9
    is_mle = {(0, 0): 3.84163, (1, 1): 3.94014, (2, 2): 3.97789}
    for (r, c), ref in is_mle.items():
        assert abs(fit.e_per_adu[r, c] - ref) < fit.e_per_adu_se[r, c]
    assert np.all((fit.e_per_adu_se > 0.02) & (fit.e_per_adu_se < 0.1))


@needs_data
def test_real_mv_gains_reproduce_reference(real_gs):
    mean, var, offset, sigma, n, sp = real_gs
    fit = fit_mv_gain(mean, var, offset, sigma, n, 3.859, sp)
    assert fit.valid.all()
    np.testing.assert_array_less(
        np.abs(fit.em_gain.mean(axis=(1, 2)) - [1.0, 4.29, 22.83, 89.65, 254.96]),
        [1e-9, 5e-3, 5e-3, 5e-3, 5e-3],
    )
    r = mean_ratio_gains(mean, var, offset, n, sp)
    # to the digits docs/validation.md gives
    np.testing.assert_array_less(
        np.abs(r.em_gain.mean(axis=(1, 2)) - [1.0, 4.791, 23.004, 90.105, 262.10]),
        [1e-9, 5e-4, 5e-4, 5e-4, 5e-3],
    )
    # the 5× single-point MV gain sits ~10 % below the mean ratio (F² < 2, docs/simulation.md)
    assert 0.87 < fit.em_gain[1].mean() / r.em_gain[1].mean() < 0.92


def test_fieller_interval_closed_form():
    """With an exact numerator the bounds are a/(b ± z·SE_b); b within z·SE of 0 → ∞."""
    lo, hi = fieller_interval(6.0, [2.0, 0.3], 0.0, 0.04)
    z = 1.959964
    np.testing.assert_allclose(lo, [6 / (2 + 0.2 * z), 6 / (0.3 + 0.2 * z)])
    np.testing.assert_allclose(hi, [6 / (2 - 0.2 * z), np.inf])
    # b significantly negative: no positive ratio fits
    assert np.isnan(fieller_interval(6.0, -2.0, 0.0, 0.04)).all()


def test_fieller_interval_covers_where_wald_does_not():
    """A ratio whose denominator is 1.5 SE from zero (the weak set-point of a gain series):
    Fieller's bounds cover 95 %, estimate ± 1.96·(delta-method SE) far less."""
    rng = np.random.default_rng(8)
    n, a0, b0, sa, sb, rho = 20000, 10.0, 1.5, 0.5, 1.0, 0.3
    za, zb = rng.standard_normal((2, n))
    a = a0 + sa * za
    b = b0 + sb * (rho * za + np.sqrt(1 - rho**2) * zb)
    cov = rho * sa * sb
    lo, hi = fieller_interval(a, b, sa**2, sb**2, cov)
    truth = a0 / b0
    cover = np.mean((lo <= truth) & (truth <= hi))
    assert 0.94 <= cover <= 0.96
    r = a / b
    se = np.abs(r) * np.sqrt(sa**2 / a**2 + sb**2 / b**2 - 2 * cov / (a * b))
    wald = np.mean(np.abs(r - truth) <= 1.959964 * se)
    assert wald < 0.9
    assert np.isinf(hi).mean() > 0.3  # often the data cannot bound the ratio above


def test_mv_gain_bounds_where_the_excess_variance_is_not_seen():
    """A set-point whose excess variance is buried in read noise: the estimate is NaN in
    some pixels, the bounds exist everywhere and contain every defined estimate."""
    rng = np.random.default_rng(2)
    P, n, phi, s0, sigma, E, g = 4000, 2000, 12.0, 1000.0, 40.0, 60.0, 9.1
    x = g * E / phi
    v = sigma**2 + 2 * E * (g / phi) ** 2
    mean = np.stack(
        [
            s0 + E / phi + rng.normal(0, np.sqrt((sigma**2 + E / phi**2) / n), P),
            s0 + x + rng.normal(0, np.sqrt(v / n), P),
        ]
    )
    var = np.stack(
        [np.full(P, sigma**2 + E / phi**2), v + rng.normal(0, v * np.sqrt(2 / (n - 1)), P)]
    )
    fit = fit_mv_gain(mean, var, s0, sigma, n, phi, [1, 10])
    undefined = ~np.isfinite(fit.em_gain[1])
    assert 0.02 < undefined.mean() < 0.2
    ok = ~undefined
    assert np.all(
        (fit.em_gain_lower[1][ok] <= fit.em_gain[1][ok])
        & (fit.em_gain[1][ok] <= fit.em_gain_upper[1][ok])
    )
    assert np.all(
        (fit.photoelectrons_lower[1][ok] <= fit.photoelectrons[1][ok])
        & (fit.photoelectrons[1][ok] <= fit.photoelectrons_upper[1][ok])
    )
    for lo, hi, truth in (
        (fit.em_gain_lower[1], fit.em_gain_upper[1], g),
        (fit.photoelectrons_lower[1], fit.photoelectrons_upper[1], E),
    ):
        assert 0.93 <= np.mean((lo <= truth) & (truth <= hi)) <= 0.97
    assert np.isnan(fit.em_gain_lower[0]).all()  # g at 1× is fixed
