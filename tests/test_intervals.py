"""Profile-likelihood intervals (``calibrate(..., intervals="profile")``)."""

import warnings

import numpy as np
import pytest
from scipy import stats

from emccdcal import calibrate
from emccdcal.data import stats as pixel_stats
from emccdcal.data.manifest import read_manifest
from emccdcal.fit import engine, profile
from emccdcal.fit.series import AcquisitionModel, SeriesLikelihood
from emccdcal.model.noise import EMModel
from emccdcal.simulate.series import simulate_gain_series


@pytest.fixture(scope="module")
def gain_series(tmp_path_factory):
    return simulate_gain_series(
        tmp_path_factory.mktemp("gs"), rows=3, cols=3, frames=500, seed=4, progress=False
    )


def _layout_and_fit(manifest, method, phi):
    return _layout_and_fit_acquisitions(read_manifest(manifest).acquisitions, method, phi)


def _layout_and_fit_acquisitions(acqs, method, phi, dark_frames=None):
    hists = [pixel_stats.histograms(a.frames()) for a in acqs]
    dark_frames = [None] * len(acqs) if dark_frames is None else dark_frames
    models = [
        AcquisitionModel(
            a.em_gain_setpoint, a.offset.ravel(), a.read_noise.ravel(), EMModel("gamma"), n
        )
        for a, n in zip(acqs, dark_frames)
    ]
    lik = SeriesLikelihood(method, models, hists, e_per_adu=phi, options={})
    return lik.layout, lik.blocks, lik.fit()


def test_bounds_are_where_the_deviance_reaches_the_quantile(gain_series):
    layout, blocks, fit = _layout_and_fit(
        gain_series.manifest, "gs", gain_series.truth["e_per_adu"]
    )
    assert fit.converged.all()
    target = stats.chi2.ppf(0.95, 1)
    for j in (0, layout.n_free - 1):  # ln E and ln g at the highest set-point
        lower, upper = profile.profile_bounds(layout, blocks, fit, j)
        assert np.all(lower < fit.x[:, j]) and np.all(fit.x[:, j] < upper)
        for bound in (lower, upper):
            pinned = profile._Pinned(layout, j, bound)
            refit = engine.fit(pinned, blocks, np.delete(fit.x, j, axis=1))
            np.testing.assert_allclose(2 * (fit.objective - refit.objective), target, atol=0.05)
        # a well-determined parameter: the profile interval is the Wald interval
        se = np.sqrt(fit.cov[:, j, j])
        np.testing.assert_allclose((upper - lower) / (2 * 1.959964 * se), 1.0, atol=0.03)


@pytest.mark.slow
def test_bounds_include_the_errors_of_the_maps(gain_series):
    """Maps from few dark frames: the profile interval of a well-determined parameter is
    the Wald interval of the SE that includes the maps' errors, not the conditional one."""
    acqs = read_manifest(gain_series.manifest).acquisitions
    layout, blocks, fit = _layout_and_fit_acquisitions(
        acqs, "gs", gain_series.truth["e_per_adu"], dark_frames=[10] * len(acqs)
    )
    conditional = np.linalg.inv(engine._evaluate(layout, blocks, fit.x, 2)[4])
    j = 0  # ln E, whose variance the error of the 1× offset map more than doubles here
    assert np.all(fit.cov[:, j, j] > 2 * conditional[:, j, j])
    lower, upper = profile.profile_bounds(layout, blocks, fit, j)
    np.testing.assert_allclose(
        (upper - lower) / (2 * 1.959964 * np.sqrt(fit.cov[:, j, j])), 1.0, atol=0.03
    )


def test_parameters_where_the_model_is_undefined_have_no_likelihood(gain_series):
    """A trial step's NaN is hopeless by its own test (log-likelihood −inf, so the step is
    refused), not by how the CPU casts NaN to an integer (x86: its least; ARM: 0), and
    quietly: a user would read numpy's "invalid value" as a fault."""
    layout, blocks, fit = _layout_and_fit(
        gain_series.manifest, "gs", gain_series.truth["e_per_adu"]
    )
    x = fit.x.copy()
    x[1] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nor is its NaN arithmetic a warning to a user
        value = engine.objective(layout, blocks, x)
    assert value[1] == -np.inf
    np.testing.assert_allclose(np.delete(value, 1), np.delete(fit.objective, 1), rtol=1e-12)


@pytest.mark.slow
def test_calibrate_writes_bounds_on_the_estimate_dims(gain_series):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = calibrate(gain_series.manifest, "gs", intervals="profile", checks=False)
    assert ds.em_gain_lower.dims == ("setpoint", "row", "col")
    assert ds.photoelectrons_upper.dims == ("row", "col")
    assert ds.photoelectrons_lower.attrs["units"] == "e-"
    assert "e_per_adu_lower" not in ds  # φ is fixed by gs
    assert np.all(np.isnan(ds.em_gain_lower.sel(setpoint=1)))  # 1× is fixed
    for name in ("em_gain", "photoelectrons"):
        est = ds[name].values[..., 1:, :, :] if name == "em_gain" else ds[name].values
        lo = (
            ds[f"{name}_lower"].values[..., 1:, :, :]
            if name == "em_gain"
            else ds[f"{name}_lower"].values
        )
        hi = (
            ds[f"{name}_upper"].values[..., 1:, :, :]
            if name == "em_gain"
            else ds[f"{name}_upper"].values
        )
        assert np.all(lo < est) and np.all(est < hi)
    assert ds.attrs["intervals"].startswith("profile")


def test_bad_intervals(gain_series):
    with pytest.raises(ValueError, match="unknown intervals 'bayes'"):
        calibrate(gain_series.manifest, "gs", intervals="bayes")
    with pytest.raises(ValueError, match="mv-gain has no likelihood"):
        calibrate(gain_series.manifest, "mv-gain", intervals="profile")


def test_profile_bounds_where_the_information_is_nearly_singular(tmp_path):
    """A set-point whose own data hardly see E (10× on a noisy camera): the profile
    deviance is flat over a decade of E and then rises as a wall where the gain reaches
    its bound of 1. The bounds must still be found (no NaN), on the quantile or at g = 1."""
    sim = simulate_gain_series(
        tmp_path,
        setpoints=(1, 10),
        em_gain=(1, 9.1),
        photoelectrons=60.0,
        rows=4,
        cols=4,
        frames=2000,
        e_per_adu=12.0,
        read_noise=40.0,
        offset=1000.0,
        seed=3,
        progress=False,
    )
    acqs = read_manifest(sim.manifest).acquisitions[1:]  # the 10× acquisition alone
    layout, blocks, fit = _layout_and_fit_acquisitions(acqs, "gs-no1x", 12.0)
    # Where the excess variance is below what a gain of 1 gives the optimum is at g = 1:
    # the fit gets there (an active-set step), with E·g the mean signal, and flags it.
    at_one = fit.x[:, 1] <= layout.lower[1]
    assert at_one.any() and np.isfinite(fit.objective).all()
    log_signal = np.log((blocks[0].mean - blocks[0].offset) * 12.0)  # ln(E·g), e⁻
    np.testing.assert_allclose(fit.x[at_one, 0], log_signal[at_one], atol=0.01)
    assert not fit.converged[at_one].any()
    target = stats.chi2.ppf(0.95, 1)
    for j in (0, 1):
        lower, upper = profile.profile_bounds(layout, blocks, fit, j)
        assert np.all(np.isfinite(lower) & np.isfinite(upper))
        assert np.all(upper - lower > 1.0)  # wider than a factor e: E is barely seen
        for bound, edge in ((lower, layout.lower[j]), (upper, layout.upper[j])):
            pinned = profile._Pinned(layout, j, bound)
            # the other parameter started where E·g gives the mean signal
            refit = engine.fit(pinned, blocks, (log_signal - bound)[:, None])
            deviance = 2 * (fit.objective - refit.objective)
            # on the quantile, or at the layout's bound (g = 1) with the deviance below it
            at_edge = np.abs(bound - edge) < 1e-6
            assert np.all(deviance[at_edge] < target + 0.1)
            np.testing.assert_allclose(deviance[~at_edge], target, atol=0.1)
        assert np.any(np.abs(lower - layout.lower[j]) < 1e-6) == (j == 1)  # some g reach 1


def test_hierarchical_intervals_are_those_of_each_set_point_alone(tmp_path):
    """gs-hierarchical's bounds are those of every set-point fitted alone, without the
    prior: Wald on the log scale where SE(ln θ) ≤ 0.1, profile likelihood elsewhere."""
    # 250 frames: SE(ln E) ≈ 0.11 at 5× (profile), 0.09 above (Wald)
    sim = simulate_gain_series(tmp_path, rows=3, cols=3, frames=250, seed=4, progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # the gamma register, as the likelihoods made below
        ds = calibrate(
            sim.manifest, "gs-hierarchical", checks=False, map_errors=False, em_model="gamma"
        )
    assert ds.attrs["intervals"].startswith("95 %, of the same model without the prior")
    acqs = read_manifest(sim.manifest).acquisitions
    phi = sim.truth["e_per_adu"]
    z = stats.norm.ppf(0.975)
    n_weak = n_wald = 0
    for acq in acqs[1:]:
        layout, blocks, fit = _layout_and_fit_acquisitions([acq], "gs-no1x", phi)
        sp = acq.em_gain_setpoint
        for j, name in enumerate(("photoelectrons", "em_gain")):
            se = np.sqrt(fit.cov[:, j, j])
            lower, upper = np.exp(fit.x[:, j] - z * se), np.exp(fit.x[:, j] + z * se)
            weak = ~(se <= 0.1) | ~fit.converged
            n_weak, n_wald = n_weak + weak.sum(), n_wald + (~weak).sum()
            if weak.any():
                lo, hi = profile.profile_bounds(layout, blocks, fit, j)
                lower[weak], upper[weak] = np.exp(lo[weak]), np.exp(hi[weak])
            got = ds[f"{name}_lower"].sel(setpoint=sp).values.ravel()
            np.testing.assert_allclose(got, lower, rtol=2e-3, err_msg=f"{name} {sp}x")
            got = ds[f"{name}_upper"].sel(setpoint=sp).values.ravel()
            np.testing.assert_allclose(got, upper, rtol=2e-3, err_msg=f"{name} {sp}x")
    assert n_weak > 0 and n_wald > 0
