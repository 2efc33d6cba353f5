"""The noise model against docs/validation.md (cases 1–8), an independent mpmath evaluation,
property-based normalisation and moments, gradients, and bad input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from reference import density
from scipy import integrate, special, stats

from emccdcal.model import noise

PHI, S0, SIGMA = 3.859, 587.0, 15.0


def support(E, g, phi, S0, sigma, width=40.0):
    mu = float(noise.mean(E, g, phi, S0))
    sd = float(np.sqrt(noise.variance(E, g, phi, S0, sigma, em_model="gamma")))
    lo = max(0, int(min(S0, mu) - width * max(sd, sigma)) - 10)
    hi = int(mu + width * sd + (60 * g / phi if g > 1 else 0)) + 10
    return np.arange(lo, hi)


# ---------------------------------------------------------------------- case 1, 2
@pytest.mark.parametrize("E", [0.5, 5.0, 370.0])
@pytest.mark.parametrize("g", [5.0, 25.0, 300.0])
def test_normalisation_and_moments(E, g):
    k = support(E, g, PHI, S0, SIGMA)
    p = noise.pmf(k, E, g, PHI, S0, SIGMA, em_model="gamma")
    assert abs(p.sum() - 1) < 1e-12
    mean = np.sum(k * p)
    var = np.sum((k - mean) ** 2 * p)
    assert abs(mean - (S0 + g * E / PHI)) < 1e-8
    assert var == pytest.approx(SIGMA**2 + 2 * E * (g / PHI) ** 2, rel=1e-6)
    if g >= 25:
        k3 = np.sum((k - mean) ** 3 * p)
        assert k3 == pytest.approx(6 * E * (g / PHI) ** 3, rel=1e-4)
        assert k3 == pytest.approx(float(noise.third_cumulant(E, g, PHI, S0, SIGMA)), rel=1e-4)


@pytest.mark.parametrize("E", [0.5, 5.0, 370.0, 1000.0])
def test_poisson_normal_moments(E):
    k = support(E, 1.0, PHI, S0, SIGMA)
    p = noise.pmf(k, E, 1.0, PHI, S0, SIGMA, em_model="gamma")
    mean = np.sum(k * p)
    assert abs(p.sum() - 1) < 1e-12
    assert abs(mean - (S0 + E / PHI)) < 1e-8
    assert np.sum((k - mean) ** 2 * p) == pytest.approx(SIGMA**2 + E / PHI**2, rel=1e-6)


def test_paper_mode_atom_is_flagged_and_documented():
    """Case 1, second part: the authors' atom weight φ e^-E breaks normalisation."""
    assert noise.paper_pmf_grid(0.5, 5, PHI, S0, SIGMA).sum() == pytest.approx(2.862, abs=1e-3)
    assert abs(noise.paper_pmf_grid(20, 5, PHI, S0, SIGMA).sum() - 1) < 1e-8
    assert "not normalised" in noise.paper_pmf_grid.__doc__
    # In the calibration regime the paper's model equals the exact one.
    k = np.arange(20000, 38000)
    exact = noise.logpmf(k, 370, 300, PHI, S0, SIGMA, em_model="gamma")
    paper = noise.paper_logpmf(k, 370, 300, PHI, S0, SIGMA)
    keep = exact > np.log(1e-10)
    assert np.max(np.abs(exact - paper)[keep]) < 1e-8


# ---------------------------------------------------------------------- case 3, 4
def test_zero_signal_limit_is_the_read_noise_gaussian():
    k = support(1e-12, 25.0, PHI, S0, SIGMA)
    p = noise.pmf(k, 1e-12, 25.0, PHI, S0, SIGMA, em_model="gamma")
    assert np.max(np.abs(p - stats.norm.pdf(k, S0, SIGMA))) < 1e-13


def test_gain_one_is_not_the_gamma_model():
    E = 50.0
    k = support(E, 1.0, PHI, S0, SIGMA)
    pn = noise.pmf(k, E, 1.0, PHI, S0, SIGMA, em_model="gamma")
    var_pn = np.sum((k - np.sum(k * pn)) ** 2 * pn)
    assert var_pn == pytest.approx(SIGMA**2 + E / PHI**2, rel=1e-6)
    # the PGN at a gain just above 1 has twice the signal variance
    pgn = noise.pmf(k, E, 1.0 + 1e-9, PHI, S0, SIGMA, em_model="gamma")
    var_pgn = np.sum((k - np.sum(k * pgn)) ** 2 * pgn)
    assert var_pgn == pytest.approx(SIGMA**2 + 2 * E / PHI**2, rel=1e-6)
    assert float(noise.excess_noise_factor(1.0, em_model="gamma")) == 1.0
    assert float(noise.excess_noise_factor(5.0, em_model="gamma")) == 2.0


# ---------------------------------------------------------------------- case 5, 6
def test_exact_poisson_normal_reference_values():
    k = [90, 100, 103, 110, 130]
    ref = [1.7503385211e-2, 3.8157156576e-2, 3.9728330371e-2, 3.0847696938e-2, 1.0291887305e-3]
    np.testing.assert_allclose(
        noise.pmf(k, 10.0, 1.0, 3.5, 100.0, 10.0, em_model="gamma"), ref, rtol=1e-9
    )


@pytest.mark.parametrize(
    "g,k,ref",
    [
        (
            25.0,
            [80, 100, 120, 150, 200, 400],
            [
                8.1441195614e-6,
                4.9031306776e-4,
                3.8344369644e-3,
                1.1530499396e-2,
                6.9196206859e-3,
                9.0856854491e-8,
            ],
        ),
        (100.0, [100, 200, 400], [2.2832978121e-5, 1.2559545933e-3, 2.9305642395e-3]),
    ],
)
def test_pgn_reference_values(g, k, ref):
    np.testing.assert_allclose(
        noise.pmf(k, 10.0, g, 3.5, 100.0, 10.0, em_model="gamma"), ref, rtol=1e-9
    )


# ---------------------------------------------------------------------- case 7
def _q_c(u, E, g, phi):
    r = phi / g
    z = 2 * np.sqrt(E * u * r)
    return np.sqrt(E * r / u) * np.exp(-((np.sqrt(u * r) - np.sqrt(E)) ** 2)) * special.i1e(z)


def test_poisson_gamma_identities():
    E, g, phi = 0.5, 5.0, PHI
    u = np.linspace(0.01, 40, 200)
    ncx2 = phi * (2 / g) * stats.ncx2.pdf(2 * E, 4, 2 * u * phi / g)
    np.testing.assert_allclose(_q_c(u, E, g, phi), ncx2, rtol=1e-12, atol=1e-13)
    total, _ = integrate.quad(_q_c, 0, np.inf, args=(E, g, phi), limit=200)
    assert total == pytest.approx(1 - np.exp(-E), abs=1e-10)
    assert total == pytest.approx(0.39346934029, abs=1e-10)
    # only g/φ matters for the EM data
    k = support(E, g, phi, S0, SIGMA)
    np.testing.assert_allclose(
        noise.logpmf(k, E, g, phi, S0, SIGMA, em_model="gamma"),
        noise.logpmf(k, E, 2 * g, 2 * phi, S0, SIGMA, em_model="gamma"),
        atol=1e-12,
    )


# ---------------------------------------------------------------------- case 8
PARAMS = ("photoelectrons", "em_gain", "e_per_adu", "offset", "read_noise")


@pytest.mark.parametrize(
    "point",
    [
        (12.0, 37.0, 3.6, 500.0, 12.0),
        (12.0, 1.0, 3.6, 500.0, 12.0),
        (0.3, 2.0, 0.5, 20.0, 0.8),
        (4000.0, 1.0, 20.0, 50.0, 3.0),
    ],
)
def test_gradients_match_finite_differences(point):
    k = support(*point, width=4)[:: max(1, support(*point, width=4).size // 25)]
    _, grad = noise.logpmf_grad(k, *point, em_model="gamma")
    for i, name in enumerate(PARAMS):
        if point[1] == 1.0 and name == "em_gain":
            assert np.all(np.isnan(grad[name]))
            continue
        # Richardson-extrapolated central differences
        h = 1e-3 * point[i]

        def fd(step):
            up, down = list(point), list(point)
            up[i] += step
            down[i] -= step
            return (
                noise.logpmf(k, *up, em_model="gamma") - noise.logpmf(k, *down, em_model="gamma")
            ) / (2 * step)

        estimate = (4 * fd(h / 2) - fd(h)) / 3
        scale = np.max(np.abs(estimate)) + 1e-12
        assert np.max(np.abs(grad[name] - estimate)) / scale < 1e-6, name


def test_derivative_identity_in_photoelectrons():
    """∂p/∂E = p ⊛ h − p with h the single-electron output density (docs/methods.md)."""
    E, g, phi, s0, sigma = 12.0, 37.0, 3.6, 500.0, 12.0
    theta = g / phi
    k = np.arange(0, 4000)
    p = noise.pmf(k, E, g, phi, s0, sigma, em_model="gamma")
    _, grad = noise.logpmf_grad(k, E, g, phi, s0, sigma, em_model="gamma")
    # h on the integer grid, exact bin masses of the exponential, convolved with p
    edges = np.arange(0, 4001) - 0.5
    h = np.diff(-np.exp(-np.clip(edges, 0, None) / theta))
    conv = np.convolve(p, h)[: k.size]
    # the exponential's continuous shift is approximated by bins: compare away from S0
    sel = (k > 1000) & (k < 2500)
    np.testing.assert_allclose(
        (p * grad["photoelectrons"])[sel], (conv - p)[sel], rtol=2e-3, atol=1e-9
    )


# ---------------------------------------------------------------------- accuracy spec
ACCURACY_CASES = [
    (10.0, 25.0, 3.5, 100.0, 10.0),
    (0.5, 5.0, 3.859, 587.0, 15.0),
    (370.0, 300.0, 3.859, 587.0, 15.0),
    (1e-3, 2000.0, 0.3, 50.0, 0.7),
    (1e4, 1.5, 30.0, 1e4, 200.0),
    (5.0, 1.0, 0.3, 20.0, 0.7),
    (100.0, 1.0, 30.0, 100.0, 0.7),
    (2.0, 1.5, 0.3, 0.0, 0.7),
    (60.0, 1000.0, 12.0, 1000.0, 40.0),
]


@pytest.mark.slow
@pytest.mark.parametrize("case", ACCURACY_CASES)
def test_logpmf_against_independent_high_precision(case):
    """Within 1e-8 (absolute) of mpmath wherever the pmf exceeds 1e-10 of its peak."""
    import mpmath as mp

    E, g, phi, s0, sigma = case
    k = support(*case, width=12)
    k = k[:: max(1, k.size // 20000)]  # enough to find the region (up to 4e5 counts wide)
    logp = noise.logpmf(k, *case, em_model="gamma")
    peak = logp.max()
    inside = k[logp > peak + np.log(1e-10)]
    # spread the checked points over the whole region, tails included
    pick = np.unique(np.r_[inside[:: max(1, inside.size // 8)], inside[:2], inside[-2:]])
    ours = noise.logpmf(pick, *case, em_model="gamma")
    from emccdcal.model import _engine

    rows = noise.EMModel("gamma").register.rows(
        np.array([E]), np.array([float(g)]), np.array([phi])
    )
    lz = _engine.log_normaliser(rows, np.array([s0]), np.array([sigma]))[0][0]
    ref = np.array([float(mp.log(density(int(v), E, g, phi, s0, sigma))) for v in pick]) - lz
    assert np.max(np.abs(ours - ref)) < 1e-8


@pytest.mark.slow
@pytest.mark.parametrize("sigma", [0.7, 1.5])
def test_small_read_noise_normaliser_by_direct_sum(sigma):
    """Σ_k f(k) computed by summing the independent density, against the normaliser: a
    multiplied count's density sampled at the integers (the paper's model)."""
    import mpmath as mp

    E, g, phi, s0 = 2.0, 1.5, 1.0, 10.3
    k = np.arange(0, 110)  # the exponential tail (θ = g/φ = 1.5 ADU) to below 1e-20
    Z = sum(density(int(v), E, g, phi, s0, sigma) for v in k)
    p = noise.pmf(k, E, g, phi, s0, sigma, em_model="gamma")
    assert abs(p.sum() - 1) < 1e-10
    ref = np.array([float(density(int(v), E, g, phi, s0, sigma) / Z) for v in k])
    keep = ref > 1e-10 * ref.max()
    np.testing.assert_allclose(p[keep], ref[keep], rtol=1e-8)
    assert mp.mpf(Z) != 1  # the normaliser matters at this read noise


@pytest.mark.slow
@pytest.mark.parametrize("sigma", [0.3, 0.7, 1.5])
def test_the_rounded_poisson_normal_by_direct_sum(sigma):
    """Below the rounding's switch a 1× count's probabilities are the normal integrated
    over each integer's bin, summed over the photoelectrons (an independent direct sum):
    they sum to one with no normaliser, and the variance has the ADC's 1/12."""
    from reference import rounded_pn

    E, phi, s0 = 2.0, 0.3, 10.3
    k = np.arange(0, 80)
    p = noise.pmf(k, E, 1.0, phi, s0, sigma, em_model="gamma")
    ref = np.array([float(rounded_pn(int(v), E, phi, s0, sigma)) for v in k])
    keep = ref > 1e-10 * ref.max()
    np.testing.assert_allclose(p[keep], ref[keep], rtol=1e-8)
    assert abs(p.sum() - 1) < 1e-12
    var = float(noise.variance(E, 1.0, phi, s0, sigma, em_model="gamma"))
    assert var == pytest.approx(sigma**2 + 1 / 12 + E / phi**2)


def test_the_transforms_expm1_keeps_the_digits_exp_minus_one_loses():
    """e^z − 1 of a transform's arguments z = (t + iω)·c: ``expm1`` where |z| is small,
    in any order of the columns, ``exp`` elsewhere; as exact as NumPy's complex
    ``expm1`` everywhere (where ``exp(z) − 1`` is off in the 9th digit), through
    array-api-strict as through NumPy."""
    from emccdcal import _xp

    omega = np.linspace(-3.0 * np.pi, np.pi, 401)  # an alias's band and the base band
    c = np.array([[1e-6], [0.05], [0.5], [2.2]])
    z = (np.array([[0.0], [1e-3], [0.0], [-0.01]]) + 1j * omega[None, :]) * c
    shuffled = z[:, np.random.default_rng(3).permutation(omega.size)]
    for values in (z, shuffled, z.real, z[:, 300:]):
        want = np.expm1(values)
        err = np.abs(_xp.expm1(np, values) - want)
        assert np.all(err <= 4 * np.finfo(float).eps * np.abs(want) + 1e-300)
    naive = np.abs(np.exp(z) - 1 - np.expm1(z)) / np.maximum(np.abs(np.expm1(z)), 1e-300)
    assert naive.max() > 1e-10  # what the test would catch
    strict = pytest.importorskip("array_api_strict")
    got = _xp.to_numpy(_xp.expm1(strict, strict.asarray(shuffled)))
    np.testing.assert_allclose(got, np.expm1(shuffled), rtol=4 * np.finfo(float).eps, atol=0)


# ---------------------------------------------------------------------- properties
@settings(max_examples=40, deadline=None)
@given(
    E=st.floats(1e-3, 1e3),
    g=st.one_of(st.just(1.0), st.floats(1.5, 2000.0)),
    phi=st.floats(0.3, 30.0),
    s0=st.floats(0.0, 1e4),
    sigma=st.floats(0.7, 200.0),
)
@pytest.mark.slow
def test_normalisation_and_moments_property(E, g, phi, s0, sigma):
    # Counts are non-negative: keep the model's mass away from count 0.
    assume(s0 > 14 * sigma + 14)
    k = support(E, g, phi, s0, sigma, width=14)
    assume(k.size < 100_000)  # what a test can sum quickly; extremes: the cases above
    p = noise.pmf(k, E, g, phi, s0, sigma, em_model="gamma")
    assert abs(p.sum() - 1) < 1e-10
    mean = np.sum(k * p)
    mu = float(noise.mean(E, g, phi, s0))
    var = float(noise.variance(E, g, phi, s0, sigma, em_model="gamma"))
    # The density sampled at the integers has the continuous model's moments up to
    # aliasing terms ∝ e^-2π²σ²: negligible from σ ≈ 1.5 ADU, a few 0.01 ADU below
    # (checked against the independent quadrature, e.g. E=1, g=106, φ=0.5, σ=0.70).
    if sigma >= 1.5:
        assert abs(mean - mu) < 1e-6 * np.sqrt(var) + 1e-7
        assert np.sum((k - mean) ** 2 * p) == pytest.approx(var, rel=1e-6)
    else:
        assert abs(mean - mu) < 1e-4 * np.sqrt(var) + 0.05
        assert np.sum((k - mean) ** 2 * p) == pytest.approx(var, rel=1e-2)


# ---------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "kwargs,name",
    [
        (dict(photoelectrons=-1.0), "photoelectrons"),
        (dict(photoelectrons=np.nan), "photoelectrons"),
        (dict(em_gain=0.5), "em_gain"),
        (dict(e_per_adu=0.0), "e_per_adu"),
        (dict(offset=-3.0), "offset"),
        (dict(read_noise=0.0), "read_noise"),
        (dict(read_noise=np.inf), "read_noise"),
    ],
)
def test_bad_parameters_name_the_parameter(kwargs, name):
    args = dict(photoelectrons=10.0, em_gain=5.0, e_per_adu=3.0, offset=100.0, read_noise=10.0)
    args.update(kwargs)
    with pytest.raises(ValueError, match=name):
        noise.logpmf([100, 120], **args)


@pytest.mark.parametrize("counts", [[1.5, 2.0], [-1, 5], [np.nan]])
def test_bad_counts(counts):
    with pytest.raises(ValueError, match="counts"):
        noise.logpmf(counts, 10.0, 5.0, 3.0, 100.0, 10.0, em_model="gamma")


def test_broadcasting():
    k = np.array([[100], [130]])
    E = np.array([5.0, 10.0, 20.0])
    out = noise.logpmf(k, E, 25.0, 3.5, 100.0, 10.0, em_model="gamma")
    assert out.shape == (2, 3)
    for i in range(2):
        for j in range(3):
            assert out[i, j] == pytest.approx(
                noise.logpmf(k[i, 0], E[j], 25.0, 3.5, 100.0, 10.0, em_model="gamma")
            )
