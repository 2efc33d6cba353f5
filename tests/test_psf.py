"""The bead image model and bead finding."""

import numpy as np
import pytest

from emccdcal.model import psf


def test_fractions_sum_to_one_and_match_integral():
    coords = np.arange(-30, 31)
    frac = psf.pixel_fractions(0.3, coords, 1.7)
    assert frac.sum() == pytest.approx(1.0, abs=1e-12)
    # one pixel against a direct integral of the density
    from scipy import integrate, stats

    ref = integrate.quad(stats.norm(0.3, 1.7).pdf, 1.5, 2.5)[0]
    assert frac[coords == 2][0] == pytest.approx(ref, rel=1e-12)


def test_spot_image_total_and_jacobian():
    rows, cols = np.arange(-6, 7), np.arange(-6, 7)
    p = np.array([0.4, -0.2, 1.3, 5000.0, 12.0])
    img, jac = psf.spot_image(p, rows, cols, jacobian=True)
    assert img.shape == (13, 13) and jac.shape == (13, 13, 5)
    assert (img - 12.0).sum() == pytest.approx(5000.0, rel=1e-5)
    for i in range(5):
        h = 1e-5 * max(1.0, abs(p[i]))
        up, dn = p.copy(), p.copy()
        up[i] += h
        dn[i] -= h
        num = (psf.spot_image(up, rows, cols) - psf.spot_image(dn, rows, cols)) / (2 * h)
        np.testing.assert_allclose(jac[..., i], num, rtol=1e-6, atol=1e-6 * np.abs(num).max())


def test_spot_image_batches():
    rows, cols = np.arange(5), np.arange(7)
    p = np.array([[2.0, 3.0, 1.0, 100.0, 1.0], [4.0, 1.0, 0.8, 50.0, 2.0]])
    both = psf.spot_image(p, rows, cols)
    assert both.shape == (2, 5, 7)
    np.testing.assert_allclose(both[1], psf.spot_image(p[1], rows, cols))
    assert np.unravel_index(both[0].argmax(), (5, 7)) == (3, 2)


def test_find_beads_accepts_isolated_and_rejects_edge_and_close():
    rng = np.random.default_rng(0)
    r, c = np.arange(64), np.arange(64)
    spots = [(20, 20), (20, 44), (44, 30), (2, 30), (50, 55), (53, 58)]
    img = sum(psf.spot_image([x, y, 1.2, 3000.0, 0.0], r, c) for y, x in spots)
    img = img + 10 + rng.normal(0, 1.0, img.shape)
    found = psf.find_beads(img, width=1.2, half_size=4)
    assert sorted(map(tuple, found.positions)) == [(20, 20), (20, 44), (44, 30)]
    assert list(map(tuple, found.at_edge)) == [(2, 30)]
    assert sorted(map(tuple, found.too_close)) == [(50, 55), (53, 58)]


def test_find_beads_on_noise_finds_nothing():
    img = np.random.default_rng(1).normal(100, 5, (40, 40))
    assert len(psf.find_beads(img).positions) == 0
    with pytest.raises(ValueError, match="2-D"):
        psf.find_beads(np.zeros(5))
