"""Profile-likelihood intervals (``calibrate(..., intervals="profile")``)."""

import warnings

import numpy as np
import pytest
from scipy import stats

from emccdcal import fitting, io, methods
from emccdcal import stats as pixel_stats
from emccdcal.calibrate import calibrate
from emccdcal.simulate import simulate_gain_series


@pytest.fixture(scope="module")
def gain_series(tmp_path_factory):
    return simulate_gain_series(tmp_path_factory.mktemp("gs"), rows=3, cols=3, frames=500,
                                seed=4, progress=False)


def _layout_and_fit(manifest, method, phi):
    acqs = io.read_manifest(manifest).acquisitions
    hists = [pixel_stats.histograms(a.frames()) for a in acqs]
    P = hists[0].n.size
    offsets = np.stack([a.offset.ravel() for a in acqs])
    read_noise = np.stack([a.read_noise.ravel() for a in acqs])
    setpoints = np.array([a.em_gain_setpoint for a in acqs])
    blocks = methods.make_blocks(hists, offsets, read_noise, setpoints, np.arange(P))
    series = methods.Series(blocks, setpoints, [a.name for a in acqs], np.full(P, phi))
    layout, x0 = methods.build_layout(method, series, {})
    return layout, blocks, fitting.fit(layout, blocks, x0)


def test_bounds_are_where_the_deviance_reaches_the_quantile(gain_series):
    layout, blocks, fit = _layout_and_fit(gain_series.manifest, "gs", gain_series.truth["e_per_adu"])
    assert fit.converged.all()
    target = stats.chi2.ppf(0.95, 1)
    for j in (0, layout.n_free - 1):  # ln E and ln g at the highest set-point
        lower, upper = fitting.profile_bounds(layout, blocks, fit, j)
        assert np.all(lower < fit.x[:, j]) and np.all(fit.x[:, j] < upper)
        for bound in (lower, upper):
            pinned = fitting._Pinned(layout, j, bound)
            refit = fitting.fit(pinned, blocks, np.delete(fit.x, j, axis=1))
            np.testing.assert_allclose(2 * (fit.objective - refit.objective), target, atol=0.05)
        # a well-determined parameter: the profile interval is the Wald interval
        se = np.sqrt(fit.cov[:, j, j])
        np.testing.assert_allclose((upper - lower) / (2 * 1.959964 * se), 1.0, atol=0.03)


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
        lo = ds[f"{name}_lower"].values[..., 1:, :, :] if name == "em_gain" else ds[f"{name}_lower"].values
        hi = ds[f"{name}_upper"].values[..., 1:, :, :] if name == "em_gain" else ds[f"{name}_upper"].values
        assert np.all(lo < est) and np.all(est < hi)
    assert ds.attrs["intervals"].startswith("profile")


def test_bad_intervals(gain_series):
    with pytest.raises(ValueError, match="unknown intervals 'bayes'"):
        calibrate(gain_series.manifest, "gs", intervals="bayes")
    with pytest.raises(ValueError, match="mv-gain has no likelihood"):
        calibrate(gain_series.manifest, "mv-gain", intervals="profile")
