"""Pointwise evaluation of the noise model: logpmf_rows and LogpmfTable against logpmf."""

from __future__ import annotations

import doctest

import numpy as np
import pytest

from emccdcal.model import noise, pointwise

PHI = 3.859


def _cases(rng, K, gains):
    g = rng.choice(gains, K)
    phi = rng.uniform(3.6, 4.1, K)
    S0 = rng.uniform(560.0, 600.0, K)
    sigma = rng.uniform(14.0, 17.0, K)
    return g, phi, S0, sigma


def _counts(rng, E, g, phi, S0, sigma, spread=1.0):
    """Counts around the model's mean, up to ``spread``·4 SDs away (tails included)."""
    mean = noise.mean(E, g, phi, S0)
    sd = np.sqrt(noise.variance(E, g, phi, S0, sigma, em_model="gamma"))
    return np.maximum(0, np.rint(mean + spread * sd * rng.uniform(-4, 4, np.shape(E)))).astype(int)


def test_logpmf_rows_matches_logpmf_and_gradient():
    rng = np.random.default_rng(0)
    U = 30
    E = rng.uniform(0.5, 400.0, U)
    g, phi, S0, sigma = _cases(rng, U, [1.0, 4.78, 22.95, 261.6])
    row = rng.integers(0, U, 400)
    k = _counts(rng, E[row], g[row], phi[row], S0[row], sigma[row], spread=1.5)
    lp, dE = pointwise.logpmf_rows(k, row, E, g, phi, S0, sigma, grad=True, em_model="gamma")
    ref, rgrad = noise.logpmf_grad(
        k, E[row], g[row], phi[row], S0[row], sigma[row], em_model="gamma"
    )
    np.testing.assert_allclose(lp, ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(dE, rgrad["photoelectrons"], rtol=1e-7, atol=1e-10)


def test_logpmf_rows_chunks_give_the_same_values(monkeypatch):
    rng = np.random.default_rng(1)
    U = 12
    E = rng.uniform(5.0, 300.0, U)
    g, phi, S0, sigma = _cases(rng, U, [1.0, 25.0, 300.0])
    row = np.repeat(np.arange(U), 7)
    k = _counts(rng, E[row], g[row], phi[row], S0[row], sigma[row])
    whole = pointwise.logpmf_rows(k, row, E, g, phi, S0, sigma, em_model="gamma")
    monkeypatch.setattr(pointwise, "_ROWS_POINTS", 1)  # one row per batch
    # the same numbers up to FFT round-off (batch shapes differ)
    np.testing.assert_allclose(
        pointwise.logpmf_rows(k, row, E, g, phi, S0, sigma, em_model="gamma"),
        whole,
        rtol=0,
        atol=1e-11,
    )


def test_logpmf_rows_bad_input():
    with pytest.raises(ValueError, match="row must hold integer indices"):
        pointwise.logpmf_rows([600], [2], [10.0, 20.0], 1.0, PHI, 587.0, 15.0, em_model="gamma")
    with pytest.raises(ValueError, match="one value per row"):
        pointwise.logpmf_rows(
            [600], [0], [10.0, 20.0], [1.0, 1.0, 1.0], PHI, 587.0, 15.0, em_model="gamma"
        )
    with pytest.raises(ValueError, match="row has 2 entries"):
        pointwise.logpmf_rows([600], [0, 0], [10.0], 1.0, PHI, 587.0, 15.0, em_model="gamma")
    with pytest.raises(ValueError, match="em_gain"):
        pointwise.logpmf_rows([600], [0], [10.0], 0.5, PHI, 587.0, 15.0, em_model="gamma")
    assert pointwise.logpmf_rows([], [], [10.0], 1.0, PHI, 587.0, 15.0, em_model="gamma").shape == (
        0,
    )


@pytest.mark.parametrize(
    "gains, e_lo, ratio",
    [
        ([1.0], 100.0, 3.0),  # 1×, bright pixels, 16 nodes
        ([4.78, 22.95], 200.0, 3.5),  # low gain, 16 nodes
        ([90.06, 261.6], 2.0, 20.0),  # high gain, dim pixels, 24 nodes
        ([1.0, 261.6], 0.0, 40.0),  # from E = 0 (the table minimum): in ln E
        ([22.95, 4.78], 0.5, 120.0),  # wider than a factor 40: in ln E, 32 nodes
        ([90.06], 0.0, 500.0),  # E = 0.001 … 500
    ],
)
def test_table_matches_exact_model(gains, e_lo, ratio):
    rng = np.random.default_rng(int(100 * ratio))
    K, per = 8, 25
    g, phi, S0, sigma = _cases(rng, K, gains)
    lo = np.full(K, e_lo)
    hi = np.maximum(lo, 1.0) * ratio
    pix = np.repeat(np.arange(K), per)
    # data drawn anywhere in the range, queried anywhere in the range
    E_data = rng.uniform(lo[pix], hi[pix])
    k = _counts(rng, E_data, g[pix], phi[pix], S0[pix], sigma[pix], spread=0.6)
    table = pointwise.LogpmfTable(k, pix, lo, hi, g, phi, S0, sigma, em_model="gamma")
    E = np.maximum(rng.uniform(lo[pix], hi[pix]), pointwise.TABLE_MIN_PHOTOELECTRONS)
    lp, d1, d2, outside = table.evaluate(E)
    assert not outside.any()
    ref, rgrad = noise.logpmf_grad(k, E, g[pix], phi[pix], S0[pix], sigma[pix], em_model="gamma")
    assert np.max(np.abs(lp - ref)) < 1e-7
    scale = np.abs(rgrad["photoelectrons"]) + 1.0 / np.maximum(E, 1.0)
    assert np.max(np.abs(d1 - rgrad["photoelectrons"]) / scale) < 1e-5
    # second derivative against central differences of the exact first derivative
    h = 1e-4 * np.maximum(E, 1.0)
    up = noise.logpmf_grad(k, E + h, g[pix], phi[pix], S0[pix], sigma[pix], em_model="gamma")[1][
        "photoelectrons"
    ]
    dn = noise.logpmf_grad(k, E - h, g[pix], phi[pix], S0[pix], sigma[pix], em_model="gamma")[1][
        "photoelectrons"
    ]
    num = (up - dn) / (2 * h)
    assert np.median(np.abs(d2 - num) / (np.abs(num) + 1e-12)) < 1e-4
    assert np.max(np.abs(d2 - num) / (np.abs(num) + scale / np.maximum(E, 1.0))) < 1e-2


def test_table_subsets_clamping_and_new_ranges():
    counts = np.array([700, 720, 3000, 3100])
    pixel = np.array([0, 0, 1, 1])
    g = np.array([1.0, 25.0])
    table = pointwise.LogpmfTable(
        counts, pixel, [100.0, 50.0], [200.0, 150.0], g, PHI, 587.0, 15.5, em_model="gamma"
    )
    assert table.degree.tolist() == [16, 16] and not table.log.any()
    lo, hi = table.e_range
    np.testing.assert_allclose(lo, [100.0, 50.0])
    np.testing.assert_allclose(hi, [200.0, 150.0])
    # a subset of the counts, by index
    lp, _, _, out = table.evaluate(np.array([120.0, 140.0]), index=np.array([1, 3]))
    ref = noise.logpmf([720, 3100], [120.0, 140.0], [1.0, 25.0], PHI, 587.0, 15.5, em_model="gamma")
    np.testing.assert_allclose(lp, ref, atol=1e-8)
    assert not out.any()
    # outside the range: clamped to its end and flagged
    lp, _, _, out = table.evaluate(np.array([90.0, 300.0]), index=np.array([0, 2]))
    assert out.tolist() == [True, True]
    np.testing.assert_allclose(
        lp,
        noise.logpmf([700, 3000], [100.0, 150.0], [1.0, 25.0], PHI, 587.0, 15.5, em_model="gamma"),
        atol=1e-8,
    )
    # widen pixel 1 and evaluate there exactly
    table.set_range([1], 100.0, 400.0)
    lp, _, _, out = table.evaluate(np.array([300.0]), index=np.array([2]))
    assert not out.any()
    np.testing.assert_allclose(
        lp, noise.logpmf(3000, 300.0, 25.0, PHI, 587.0, 15.5, em_model="gamma"), atol=1e-8
    )
    # pixel 0 untouched
    np.testing.assert_allclose(table.e_range[0], [100.0, 100.0])


def test_table_bad_input():
    with pytest.raises(ValueError, match="0 <= e_lo < e_hi"):
        pointwise.LogpmfTable([700], [0], [100.0], [50.0], 1.0, PHI, 587.0, 15.5, em_model="gamma")
    with pytest.raises(ValueError, match="pixel must hold integer indices"):
        pointwise.LogpmfTable([700], [3], [10.0], [50.0], 1.0, PHI, 587.0, 15.5, em_model="gamma")
    with pytest.raises(ValueError, match="pixel has 2 entries"):
        pointwise.LogpmfTable(
            [700], [0, 0], [10.0], [50.0], 1.0, PHI, 587.0, 15.5, em_model="gamma"
        )


def test_docstring_examples():
    for obj in (pointwise.logpmf_rows, pointwise.LogpmfTable):
        finder = doctest.DocTestFinder()
        runner = doctest.DocTestRunner()
        for test in finder.find(obj, globs={"np": np, **vars(pointwise)}):
            runner.run(test)
        assert runner.tries >= 2, f"{obj.__name__}: its examples did not run"
        assert runner.failures == 0
