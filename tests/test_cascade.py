"""The EM register as a Bernoulli cascade: algebra, exact pmf, samplers (docs/simulation.md; numerical test case 9)."""

from __future__ import annotations

import doctest

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from emccdcal.model import cascade, cascade_sampling, noise
from emccdcal.model.cascade import (
    excess_noise_factor,
    mean_gain,
    single_electron_moments,
    single_electron_variance,
    stage_probability,
)
from emccdcal.model.cascade_sampling import output_pmf, sample_cascade, sample_gamma

# docs/simulation.md table of F²(g, N), 4 decimals.
F2_TABLE = {
    2: (1.4987, 1.4987, 1.4988, 1.4989),
    5: (1.7950, 1.7952, 1.7957, 1.7957),
    25: (1.9480, 1.9485, 1.9496, 1.9498),
    100: (1.9723, 1.9731, 1.9746, 1.9750),
    300: (1.9746, 1.9756, 1.9775, 1.9779),
    1000: (1.9722, 1.9734, 1.9758, 1.9763),
}
F2_STAGES = (512, 536, 591, 604)


# --------------------------------------------------------------------------------------
# Algebra
# --------------------------------------------------------------------------------------
def test_case9_values():
    assert excess_noise_factor(5, 536) == pytest.approx(1.795203, abs=5e-7)
    assert excess_noise_factor(300, 536) == pytest.approx(1.975567, abs=5e-7)
    assert excess_noise_factor(25, 604) == pytest.approx(1.949795, abs=5e-7)
    assert stage_probability(5, 536) == pytest.approx(3.007195e-3, rel=2e-7)
    assert single_electron_variance(5, 536) == pytest.approx(19.880073, abs=5e-7)


@pytest.mark.parametrize("g", sorted(F2_TABLE))
def test_f2_table(g):
    got = excess_noise_factor(g, np.array(F2_STAGES))
    # The table is rounded to 4 decimals; two of its entries, (2, 512) and (5, 591), are
    # one in the last digit above the rounded formula (1.498647 and 1.795649).
    np.testing.assert_allclose(got, F2_TABLE[g], atol=6e-5)


def test_f2_limits():
    assert excess_noise_factor(1.0, 536) == 1.0
    assert excess_noise_factor(1 + 1e-9, 536) == pytest.approx(1.0, abs=1e-8)
    # Below 2 at every finite N, approaching 2 − 1/g as N grows.
    assert excess_noise_factor(5.0, 10**7) == pytest.approx(2 - 1 / 5, abs=1e-5)
    assert np.all(excess_noise_factor(np.geomspace(1, 1e4, 50), 536) < 2)


@settings(max_examples=60, deadline=None)
@given(g=st.floats(1.0, 5000.0), n=st.integers(13, 5000))
def test_algebra_consistent(g, n):
    p = stage_probability(g, n)
    assert mean_gain(p, n) == pytest.approx(g, rel=1e-12)
    # F² = 1 + Var₁/g² with Var₁ = (1−p)·m^(N−1)·(m^N − 1), m = 1 + p (Galton–Watson).
    m = 1.0 + p
    var1_gw = (1 - p) * m ** (n - 1) * (m**n - 1)
    assert single_electron_variance(g, n) == pytest.approx(var1_gw, rel=1e-9, abs=1e-12)
    assert excess_noise_factor(g, n) == pytest.approx(1 + var1_gw / g**2, rel=1e-9)


@pytest.mark.parametrize(
    "call, name",
    [
        (lambda: excess_noise_factor(0.5, 536), "em_gain"),
        (lambda: excess_noise_factor(np.nan, 536), "em_gain"),
        (lambda: excess_noise_factor(5, 0), "stages"),
        (lambda: excess_noise_factor(5, 2.5), "stages"),
        (lambda: stage_probability(5, True), "stages"),
        (lambda: stage_probability(5, 2), "em_gain must be <= 2"),
        (lambda: excess_noise_factor(1e4, 10), "em_gain must be <= 2"),
        (lambda: mean_gain(1.5, 10), "p"),
        (lambda: sample_cascade([1, -1], 5, 536, 0), "electrons"),
        (lambda: sample_cascade([1.5], 5, 536, 0), "electrons"),
        (lambda: sample_cascade(["a"], 5, 536, 0), "electrons"),
        (lambda: sample_cascade([1], 0.9, 536, 0), "em_gain"),
        (lambda: sample_cascade([1], [5, 6], 536, 0), "em_gain"),
        (lambda: sample_cascade([1], 5, -3, 0), "stages"),
        (lambda: sample_cascade([1], 5, 536, 0, method="fast"), "method"),
        (lambda: sample_gamma([-2], 5, 0), "electrons"),
        (lambda: sample_gamma([2], 0, 0), "em_gain"),
        (lambda: output_pmf(0, 5), "electrons"),
    ],
)
def test_bad_input_names_parameter(call, name):
    with pytest.raises(ValueError, match=name):
        call()


# --------------------------------------------------------------------------------------
# Exact pmf tables
# --------------------------------------------------------------------------------------
def _pmf_by_recursion(m, p, stages, size):
    """Output pmf of m electrons, stage by stage: P ← P·T, T[x, y] = Binom(y − x; x, p)."""
    x = np.arange(size)
    T = stats.binom.pmf(x[None, :] - x[:, None], x[:, None], p)
    P = np.zeros(size)
    P[m] = 1.0
    for _ in range(stages):
        P = P @ T
    return P


@pytest.mark.parametrize(
    "m, g, stages, size", [(3, 1.3**10, 10, 3 * 2**10 + 1), (1, 5.0, 536, 320), (4, 5.0, 536, 500)]
)
def test_output_pmf_matches_stage_recursion(m, g, stages, size):
    expected = _pmf_by_recursion(m, float(stage_probability(g, stages)), stages, size)
    x, p = output_pmf(m, g, stages)
    got = np.zeros(size)
    keep = x < size
    got[x[keep]] = p[keep]
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-13)
    assert p[~keep].sum() < 1e-15


@pytest.mark.parametrize("g", [5.0, 25.0, 300.0])
@pytest.mark.parametrize("m", [1, 37, 256])
def test_output_pmf_moments(g, m):
    x, p = output_pmf(m, g, 536)
    assert p.sum() == pytest.approx(1.0, abs=1e-14)
    assert x[0] == m
    mu = np.sum(x * p)
    var = np.sum((x - mu) ** 2 * p)
    assert mu == pytest.approx(m * g, rel=1e-11)
    assert var == pytest.approx(m * single_electron_variance(g, 536), rel=1e-9)


@pytest.mark.parametrize("g", [1.5, 5.0, 300.0])
def test_single_electron_moments_are_the_exact_pmfs(g):
    """The cumulant recursion's raw moments against the exact pmf's (k ≤ 4), and the
    gamma register's: an exponential's k!·g^k."""
    x, p = output_pmf(1, g, 536)
    x = x.astype(float)
    exact = [np.sum(x**k * p) for k in (1, 2, 3, 4)]
    np.testing.assert_allclose(single_electron_moments(g, 536), exact, rtol=1e-8)
    gamma = noise.EMModel("gamma").register.single_electron_moments(g)
    np.testing.assert_allclose(gamma, [g, 2 * g**2, 6 * g**3, 24 * g**4])


@pytest.mark.parametrize("g, m", [(5.0, 1), (261.6, 256), (1.01, 3)])
def test_indexed_search_equals_binary_search(g, m):
    _, _, cdf, guide = cascade_sampling._block_table(float(stage_probability(g, 536)), 536, m)
    rng = np.random.default_rng(0)
    u = np.concatenate(
        (
            rng.random(200_000),
            [0.0, np.nextafter(1.0, 0.0)],
            cdf[:-1],  # exactly on every step of the cdf
            np.nextafter(cdf[:-1], 0.0),
            1.0 - rng.random(1000) * 1e-12,  # far upper tail
        )
    )
    np.testing.assert_array_equal(
        cascade_sampling._invert(cdf, guide, u), np.searchsorted(cdf, u, side="right")
    )


# --------------------------------------------------------------------------------------
# Samplers: Monte Carlo of docs/validation.md case 9
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", [pytest.param("stages", marks=pytest.mark.slow), "pmf"])
def test_cascade_monte_carlo_case9(method):
    rng = np.random.default_rng(9)
    E, g = 20.0, 5.0
    n = rng.poisson(E, 200_000)
    x = sample_cascade(n, g, 536, rng, method=method)
    assert x.dtype == np.int64
    assert x.mean() / (g * E) == pytest.approx(1.0, abs=0.002)
    f2 = x.var() / (g**2 * E)
    assert f2 == pytest.approx(1.795, abs=0.02)
    assert abs(f2 - 2.0) > 0.15  # distinguishable from the gamma model


def test_gamma_monte_carlo_f2():
    rng = np.random.default_rng(10)
    E, g = 20.0, 5.0
    x = sample_gamma(rng.poisson(E, 200_000), g, rng)
    assert x.mean() / (g * E) == pytest.approx(1.0, abs=0.003)
    assert x.var() / (g**2 * E) == pytest.approx(2.0, abs=0.02)


@pytest.mark.parametrize("method", ["stages", "pmf"])
def test_samplers_follow_exact_pmf(method):
    """Chi-square goodness of fit of each sampler against the exact table (m = 3, g = 25)."""
    x, p = output_pmf(3, 25.0, 536)
    draws = sample_cascade(np.full(20_000, 3), 25.0, 536, np.random.default_rng(3), method=method)
    # 25 bins of about equal probability
    edges = np.searchsorted(np.cumsum(p), np.linspace(0, 1, 26)[1:-1])
    expected = np.diff(np.concatenate(([0.0], np.cumsum(p)[edges], [1.0]))) * draws.size
    observed = np.bincount(np.searchsorted(x[edges], draws, side="left"), minlength=25)
    assert stats.chisquare(observed, expected).pvalue > 1e-3


def test_samplers_agree_on_mixed_input():
    """Two-sample check of the two exact samplers on inputs 0 … 60 of every size."""
    n = np.random.default_rng(5).integers(0, 60, size=(40, 250))
    a = sample_cascade(n, 100.0, 536, 11, method="stages")
    b = sample_cascade(n, 100.0, 536, 12, method="pmf")
    assert a.shape == b.shape == n.shape
    assert np.all(a[n == 0] == 0) and np.all(b[n == 0] == 0)
    assert np.all(a >= n) and np.all(b >= n)
    # Standardised by the exact conditional moments, both must be mean 0, variance 1.
    sd = np.sqrt(n * single_electron_variance(100.0, 536))
    for out in (a, b):
        z = (out - 100.0 * n)[n > 0] / sd[n > 0]
        assert abs(z.mean()) < 4 / np.sqrt(z.size)
        se_var = np.std(z**2) / np.sqrt(z.size)  # standard error of the mean of z²
        assert z.var() == pytest.approx(1.0, abs=4 * se_var)
    assert (
        stats.ks_2samp((a - 100 * n)[n > 0] / sd[n > 0], (b - 100 * n)[n > 0] / sd[n > 0]).pvalue
        > 1e-3
    )


def test_large_inputs_use_whole_blocks(monkeypatch):
    """Inputs beyond the largest table are sums of whole blocks; moments stay exact."""
    monkeypatch.setattr(cascade_sampling, "_MAX_GRID", 2**12)
    cascade_sampling._max_block_exponent.cache_clear()
    try:
        p = float(stage_probability(25.0, 536))
        assert 2 ** cascade_sampling._max_block_exponent(p, 536) < 700
        n = np.full(20_000, 700)
        x = sample_cascade(n, 25.0, 536, 4)
        mu, var = 700 * 25.0, 700 * single_electron_variance(25.0, 536)
        assert x.mean() == pytest.approx(mu, abs=4 * np.sqrt(var / n.size))
        assert x.var() == pytest.approx(var, rel=4 * np.sqrt(2 / n.size))
    finally:
        cascade_sampling._max_block_exponent.cache_clear()


@pytest.mark.parametrize("method", [pytest.param("stages", marks=pytest.mark.slow), "pmf"])
def test_gain_one_is_identity_and_pn_limit(method):
    n = np.random.default_rng(0).poisson(30.0, size=(3, 7, 11))
    out = sample_cascade(n, 1.0, 536, 0, method=method)
    assert out.dtype == np.int64 and out.shape == n.shape
    np.testing.assert_array_equal(out, n)
    # p → 0: the cascade tends to no multiplication (Poisson–normal), F² → 1.
    E = 30.0
    x = sample_cascade(np.random.default_rng(1).poisson(E, 200_000), 1.001, 536, 2, method=method)
    assert x.var() / (1.001**2 * E) == pytest.approx(
        float(excess_noise_factor(1.001, 536)), abs=0.01
    )
    assert float(excess_noise_factor(1.001, 536)) == pytest.approx(1.0, abs=2e-3)
    assert sample_gamma(n, 1.0, 0).tolist() == n.astype(float).tolist()


@pytest.mark.parametrize("method", ["stages", "pmf"])
def test_shapes_zero_inputs_and_reproducibility(method):
    n = np.array([[0, 5, 0], [2, 0, 9]], dtype=np.uint16)
    a = sample_cascade(n, 50.0, 536, 123, method=method)
    b = sample_cascade(n, 50.0, 536, np.random.default_rng(123), method=method)
    c = sample_cascade(n, 50.0, 536, 124, method=method)
    assert a.shape == n.shape and a.dtype == np.int64
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert np.all(a[n == 0] == 0) and np.all(a[n > 0] >= n[n > 0])
    assert sample_cascade(np.zeros((0, 4), int), 50.0, 536, 0, method=method).shape == (0, 4)
    assert sample_cascade(7, 50.0, 536, 0, method=method).shape == ()
    g = sample_gamma(n, 50.0, 5)
    assert g.shape == n.shape and np.all(g[n == 0] == 0) and np.all(g[n > 0] > 0)


def test_docstring_examples():
    attempted = 0
    for module in (cascade, cascade_sampling):
        result = doctest.testmod(module, optionflags=doctest.ELLIPSIS)
        assert result.failed == 0, module.__name__
        attempted += result.attempted
    assert attempted > 5
