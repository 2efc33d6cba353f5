"""Standard errors that include the error of offset/read-noise maps made from few darks.

A map from n dark frames has its own error (σ/√n for the offset), the same for every
frame of the acquisition: conditional SEs then cover the truth far less than 95 %.
"""

import re
import warnings

import numpy as np
import pytest

from emccdcal import calibrate
from emccdcal.data.manifest import read_manifest
from emccdcal.simulate.series import simulate_gain_series, simulate_intensity_series

DARK_FRAMES = 60


def _dark_manifest(sim):
    """The simulated manifest with each acquisition's dark stack instead of its maps."""
    text = sim.manifest.read_text()
    text = re.sub(
        r'offset = "[^"]+"\nread_noise = "[^"]+"\ndark_frames = .*\n# dark = "([^"]+)".*',
        r'dark = "\1"',
        text,
    )
    path = sim.outdir / "manifest-dark.toml"
    path.write_text(text)
    return path


def _coverage(ds, name, truth, index=()):
    est = ds[name].values[index].ravel()
    se = ds[f"{name}_se"].values[index].ravel()
    return np.mean(np.abs(est - truth) <= 1.959964 * se)


def _run(manifest, method, map_errors):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return calibrate(manifest, method, map_errors=map_errors, checks=False)


@pytest.fixture(scope="module")
def gain_series(tmp_path_factory):
    sim = simulate_gain_series(
        tmp_path_factory.mktemp("gs"),
        rows=32,
        cols=32,
        frames=1000,
        dark_frames=DARK_FRAMES,
        seed=8,
        progress=False,
    )
    return sim, _dark_manifest(sim)


def test_dark_frames_come_from_the_stack_or_the_manifest(gain_series):
    sim, manifest = gain_series
    assert all(a.dark_frames == DARK_FRAMES for a in read_manifest(manifest).acquisitions)
    # the simulator writes dark_frames beside its maps; without it maps are exact
    assert all(a.dark_frames == DARK_FRAMES for a in read_manifest(sim.manifest).acquisitions)
    text = sim.manifest.read_text().replace(f"dark_frames = {DARK_FRAMES}", "", 4)
    path = sim.outdir / "manifest-counted.toml"
    path.write_text(text)
    counted = [a.dark_frames for a in read_manifest(path).acquisitions]
    assert counted == [None] * 4 + [DARK_FRAMES]


@pytest.mark.slow
def test_gain_series_coverage_with_map_errors(gain_series):
    sim, manifest = gain_series
    acqs = sim.truth["acquisitions"]
    conditional, full = _run(manifest, "gs", False), _run(manifest, "gs", True)
    assert "conditional" in conditional.attrs["standard_errors"]
    assert "60 dark frames" in full.attrs["standard_errors"]
    # the estimates themselves do not change, only their errors
    np.testing.assert_array_equal(full.em_gain.values, conditional.em_gain.values)
    checks = [("photoelectrons", acqs[0]["photoelectrons"], ())]
    checks += [("em_gain", a["em_gain"], (i,)) for i, a in enumerate(acqs) if i > 0]
    for name, truth, index in checks:
        assert _coverage(conditional, name, truth, index) < 0.8, name
        assert 0.93 <= _coverage(full, name, truth, index) <= 0.97, name


@pytest.mark.slow
def test_shared_dark_of_an_intensity_series(tmp_path):
    """Six levels share one dark stack: their map errors are one draw, not six."""
    sim = simulate_intensity_series(
        tmp_path, rows=32, cols=32, frames=1000, dark_frames=DARK_FRAMES, seed=9, progress=False
    )
    manifest = _dark_manifest(sim)
    full = _run(manifest, "is-adu", True)
    conditional = _run(manifest, "is-adu", False)
    phi = sim.truth["e_per_adu"]
    assert _coverage(conditional, "e_per_adu", phi) < 0.8
    assert 0.93 <= _coverage(full, "e_per_adu", phi) <= 0.97
    for i, acq in enumerate(sim.truth["acquisitions"]):
        assert 0.93 <= _coverage(full, "photoelectrons", acq["photoelectrons"], (i,)) <= 0.97
