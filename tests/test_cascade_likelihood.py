"""The exact (Bernoulli-cascade) EM register in the noise model and the likelihood methods.

The count pmf under the cascade is computed from the register's transform in the count
(ADU) domain (:mod:`emccdcal.model.noise`). It is checked here against

* an independent evaluation by the integer-electron route: the single-electron output
  pmf by exact polynomial composition of the stage PGF, the photoelectrons' compound
  Poisson pmf by Panjer's recursion (sums of positive terms only, so full relative
  accuracy far into the tails) and the read-out's Gaussian summed over electrons;
* Monte Carlo of the stage-by-stage register (χ² tests, with the gamma model as the
  control that the test has power);
* the exact gain pmf of NASA Roman CGI's emccd-detect (a test-only dependency);
* finite differences of its analytic gradients;

and the likelihood methods are checked to recover the gains of exact-cascade data that
the gamma model gets wrong.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from emccdcal import calibrate
from emccdcal.errors import ManifestError, OptionError
from emccdcal.model import cascade, cascade_sampling, noise
from known_truth import truth_manifest
from emccdcal.simulate.series import simulate_gain_series


# --------------------------------------------------------------------------------------
# The independent integer-electron route
# --------------------------------------------------------------------------------------
def single_electron_pmf(gain, stages, y_max):
    """P(one electron leaves the register as y electrons), y = 0 … y_max, by composing
    the stage PGF f(z) = (1 − p)z + pz² exactly: coefficient y of f(G) needs only
    coefficients < y + 1 of G, so truncation at y_max is exact below it."""
    p = gain ** (1.0 / stages) - 1.0
    c = np.zeros(y_max + 1)
    c[1] = 1.0
    for _ in range(stages):
        c = (1.0 - p) * c + p * np.convolve(c, c)[: y_max + 1]
    return c


def compound_poisson_pmf(E, q, x_max):
    """P(X = x), x = 0 … x_max, of the output of Poisson(E) electrons with per-electron
    pmf q (q[0] = 0), by Panjer's recursion P(x) = (E/x) Σ_y y q(y) P(x − y), rescaled
    as it goes (e^{-E} underflows at large E) and normalised at the end."""
    yq = np.arange(q.size) * q
    P = np.zeros(x_max + 1)
    P[0] = 1.0
    Y = q.size - 1
    for x in range(1, x_max + 1):
        m = min(x, Y)
        P[x] = E / x * np.dot(yq[1 : m + 1], P[x - 1 :: -1][:m])
        if P[x] > 1e250:
            P[: x + 1] *= 1e-250
    return P / P.sum()


def integer_electron_logpmf(E, g, phi, S0, sigma, N):
    """(counts, log p) on the whole support of the model, normalised over the integers."""
    mean = E * g
    sd = np.sqrt(E * g * g * cascade.excess_noise_factor(g, N))
    y_max = int(g * 40 + 40)
    x_max = int(mean + 14 * sd + 40 * g + 14 * sigma * phi + 50)
    q = single_electron_pmf(g, N, min(y_max, x_max))
    P = compound_poisson_pmf(E, q, x_max)
    k = np.arange(int(np.floor(S0 - 14 * sigma)), int(np.ceil(S0 + x_max / phi)) + 1)
    x = np.flatnonzero(P > 0)
    f = np.array([np.sum(P[x] * np.exp(-0.5 * ((kk - S0 - x / phi) / sigma) ** 2)) for kk in k]) / (
        sigma * np.sqrt(2 * np.pi)
    )
    return k, np.log(f / f.sum())


#: (E, g, φ, σ, N): the paper's 5x, low gain at high signal, few electrons with an
#: electron lattice finer than the read noise is wide, a dim high-gain pixel, and more.
ROUTE_CASES = [
    (370.0, 4.78, 3.859, 15.5, 536),
    (1e4, 1.5, 30.0, 200.0, 50),
    (0.05, 25.0, 0.3, 0.7, 2000),
    (1e-3, 100.0, 10.0, 3.0, 604),
    (20.0, 100.0, 5.0, 15.0, 536),
    (3.0, 10.0, 1.0, 1.2, 300),
]


@pytest.mark.slow
@pytest.mark.parametrize("E, g, phi, sigma, N", ROUTE_CASES)
def test_logpmf_matches_the_integer_electron_route(E, g, phi, sigma, N):
    S0 = 100.0 + 15 * sigma  # counts are non-negative
    k, ref = integer_electron_logpmf(E, g, phi, S0, sigma, N)
    keep = ref > ref.max() + np.log(1e-10)  # wherever the pmf exceeds 1e-10 of its peak
    k, ref = k[keep], ref[keep]
    got = noise.logpmf(k, E, g, phi, S0, sigma, em_model=noise.EMModel("cascade", N))
    assert np.max(np.abs(got - ref)) < 1e-8


#: High gains, beyond the route's reach: (E, g, φ, σ, N).
QUADRATURE_CASES = [
    (50.0, 300.0, 3.859, 15.5, 536),
    (1.0, 2000.0, 30.0, 200.0, 1000),
    (1e4, 1000.0, 30.0, 50.0, 604),
]


@pytest.mark.slow
@pytest.mark.parametrize("E, g, phi, sigma, N", QUADRATURE_CASES)
def test_logpmf_at_high_gain_matches_high_precision_quadrature(E, g, phi, sigma, N):
    """Above g = 100 the density at k is ``(1/π)∫ Re exp(K(t + iω) − (t + iω)k) dω`` along
    the line through the saddle point t, by mpmath with the register's recursion in the
    same precision (20 digits): no window, band, FFT or tilt bookkeeping."""
    mp = pytest.importorskip("mpmath")
    with mp.workdps(20):
        _compare_with_quadrature(mp, E, g, phi, sigma, N)


def _compare_with_quadrature(mp, E, g, phi, sigma, N):
    S0 = 100.0 + 15 * sigma
    p = mp.power(mp.mpf(g), mp.mpf(1) / N) - 1

    def K(s):
        v = mp.expm1(s / phi)
        for _ in range(N):
            v = v * (1 + p + p * v)
        return s * S0 + mp.mpf(sigma) ** 2 * s**2 / 2 + E * v

    from emccdcal.model import _engine

    rows = noise.EMModel("cascade", N).register.rows(np.array([E]), np.array([g]), np.array([phi]))
    one = lambda x: np.array([float(x)])  # noqa: E731
    # counts at about 1, 1e-6 and 1e-9 of the peak, above the mean
    mean = S0 + E * g / phi
    sd = np.sqrt(float(noise.variance(E, g, phi, S0, sigma, em_model=noise.EMModel("cascade", N))))
    grid = np.unique(np.linspace(mean, mean + 40 * sd + 60 * g / phi, 400).astype(np.int64))
    lp = noise.logpmf(grid, E, g, phi, S0, sigma, em_model=noise.EMModel("cascade", N))
    peak = lp.max()
    chosen = [grid[np.argmin(np.abs(lp - (peak + level)))] for level in (0.0, -13.8, -20.7)]
    for k in chosen:
        t = rows.saddlepoint(one(k), one(S0), one(sigma))
        d2K = _engine.real_cgf(rows, t, one(S0), one(sigma))[2][0]
        t = mp.mpf(float(t[0]))
        # the integrand's scales: the tilted distribution's SD and the read noise's, whose
        # Gaussian alone bounds the integrand where the electrons' part no longer falls
        scales = sorted({1.0 / np.sqrt(d2K), 1.0 / sigma})
        points = sorted({0.0, *(w * j for w in scales for j in (1, 3, 6, 12))})
        f = lambda w: mp.re(mp.exp(K(t + 1j * w) - (t + 1j * w) * k))  # noqa: E731
        # Gauss-Legendre on these smooth pieces: the digits of tanh-sinh at 40 % of
        # the evaluations (each costs the register's N stages in mpmath)
        ref = mp.log(mp.quad(f, points, method="gauss-legendre") / mp.pi)
        got = noise.logpmf(k, E, g, phi, S0, sigma, em_model=noise.EMModel("cascade", N))
        assert abs(float(got - ref)) < 1e-8, (k, float(got), float(ref))


def test_single_electron_pmf_agrees_with_emccd_detect():
    """The reference route's register pmf is emccd-detect's exact gain pmf."""
    rand_em_gain = pytest.importorskip("emccd_detect.rand_em_gain")
    for g, N in ((4.78, 536), (25.0, 604)):
        y = np.arange(1, int(30 * g))
        theirs = rand_em_gain.exact_gain_PDF(g, N, 1, y)
        ours = single_electron_pmf(g, N, int(y.max()))[y]
        assert np.allclose(ours, theirs, rtol=1e-9, atol=0)


# --------------------------------------------------------------------------------------
# Moments, gradients, the model record
# --------------------------------------------------------------------------------------
def test_register_transform_moments_and_derivatives():
    g, N = np.array([5.0, 300.0]), 536
    t = cascade.register_transform(np.zeros(2), g, N, order=2)
    assert np.allclose(t["u"], g, rtol=1e-12)  # mean output
    assert np.allclose(t["uu"] / g**2, cascade.excess_noise_factor(g, N), rtol=1e-12)
    u = np.array([[0.01j, 0.05 + 0.02j], [0.001j, 0.002 + 0.0005j]])
    d = cascade.register_transform(u, g, N, order=2, cic=True)
    h = 1e-6
    for prefix in ("", "cic_"):
        for var, shift in (("u", (h, 0.0)), ("g", (0.0, h))):
            up = cascade.register_transform(
                u + shift[0], g * np.exp(shift[1]), N, order=1, cic=True
            )
            dn = cascade.register_transform(
                u - shift[0], g * np.exp(-shift[1]), N, order=1, cic=True
            )
            fd = (up[prefix + "v"] - dn[prefix + "v"]) / (2 * h)
            assert np.allclose(fd, d[prefix + var], rtol=1e-6, atol=1e-9)
            for first in ("u", "g"):
                key = "".join(sorted(first + var, key="ug".index))
                fd2 = (up[prefix + first] - dn[prefix + first]) / (2 * h)
                assert np.allclose(fd2, d[prefix + key], rtol=1e-5, atol=1e-8)


def _rows(gain, spread, reach, rows=128, freqs=33, seed=0):
    """u = iθ of a block of pixels at one set-point: gains around ``gain`` (relative
    spread), frequencies up to g·θ = ``reach``, each row's own frequency scale."""
    rng = np.random.default_rng(seed)
    g = gain * np.exp(rng.normal(0.0, spread, rows))
    scale = rng.uniform(0.9, 1.1, rows)[:, None]
    theta = np.linspace(0.0, reach, freqs)[None, :] / g[:, None] * scale
    return 1j * theta, g


@pytest.mark.parametrize(
    "gain, spread, reach, rows, tabulated",
    [
        (1.05, 0.01, 0.5, 128, True),
        (5.0, 0.03, 0.5, 128, True),
        (300.0, 0.03, 0.6, 128, True),
        (25.0, 0.0, 1.0, 128, True),
        (90.0, 0.3, 3.0, 512, True),
        (3000.0, 0.03, 20.0, 512, False),
    ],
)
def test_tabulated_transform_is_the_recursion(gain, spread, reach, rows, tabulated):
    """A block's transform from its Chebyshev table equals the stage recursion to about
    the recursion's own round-off (N·ε of the largest value), every derivative and the
    clock-induced-charge sums included, and the zero frequency exactly. (A wide spread
    of gains or of frequencies needs more nodes, worth it for a larger block; frequencies
    that reach far beyond the transform's scale need more points than the table saves,
    and the recursion runs.)"""
    u, g = _rows(gain, spread, reach, rows)
    N = 536
    for order, cic, by_u in ((0, False, True), (1, False, False), (2, True, True)):
        table = cascade._tabulated(np, u.imag, g, N, order, cic, by_u)
        direct = cascade._register_transform(np, u, g, N, order, cic, by_u)
        if not tabulated:
            assert table is None
            got = cascade.register_transform(u, g, N, order=order, cic=cic, by_u=by_u)
            assert all(np.array_equal(got[k], direct[k]) for k in direct)
            continue
        assert table is not None  # a block this size is tabulated
        assert table.keys() == direct.keys()
        for key, want in direct.items():
            err = np.max(np.abs(table[key] - want)) / np.max(np.abs(want))
            assert err < 4 * N * np.finfo(float).eps, (key, err)
            if "u" not in key.removeprefix("cic_"):
                assert np.all(table[key][:, 0] == 0.0)  # at u = 0, exactly


def test_tables_are_kept_within_a_scope_and_serve_whoever_comes_next(monkeypatch):
    """Within ``transform_tables`` a table serves later calls whose gains it covers (a
    fit's iterations, and the next block's fit): the grid's rectangle that holds a
    call's gains and frequencies, so that a call's values are the same whatever was
    tabulated before it. Outside a scope each call tabulates its own; a call too small
    for a table is the recursion itself."""
    builds = []
    build = cascade._build_table
    monkeypatch.setattr(cascade, "_build_table", lambda *a: builds.append(1) or build(*a))
    monkeypatch.setattr(cascade, "_KEPT", type(cascade._KEPT)())
    u, g = _rows(300.0, 0.03, 0.6)
    first = cascade.register_transform(u, g, 536)
    cascade.register_transform(u[:100], g[:100] * 1.01, 536)
    assert len(builds) == 2
    with cascade.transform_tables():
        with cascade.transform_tables():  # nested: the same tables
            inside = cascade.register_transform(u, g, 536)
        moved = cascade.register_transform(u[:100], g[:100] * 1.01, 536)
    with cascade.transform_tables():  # another fit: the tables kept
        again = cascade.register_transform(u, g, 536)
    assert len(builds) == 3
    assert all(np.array_equal(again[k], inside[k]) for k in inside)
    np.testing.assert_allclose(inside["v"], first["v"], rtol=0, atol=1e-13)
    direct = cascade._register_transform(np, u[:100], g[:100] * 1.01, 536, 1, False, True)
    np.testing.assert_allclose(moved["g"], direct["g"], rtol=0, atol=1e-13)
    # the same call in a process that tabulated nothing before: the same numbers
    monkeypatch.setattr(cascade, "_KEPT", type(cascade._KEPT)())
    with cascade.transform_tables():
        alone = cascade.register_transform(u[:100], g[:100] * 1.01, 536)
    assert all(np.array_equal(alone[k], moved[k]) for k in moved)
    small = cascade.register_transform(u[:2, :5], g[:2], 536)
    direct = cascade._register_transform(np, u[:2, :5], g[:2], 536, 1, False, True)
    assert all(np.array_equal(small[k], direct[k]) for k in direct)


def test_a_samplers_likelihood_evaluates_within_the_tables_scope(monkeypatch):
    """The posterior's sampler calls a pixel's objective thousands of times with moving
    gains: within the tables' scope they share the kept tables (measured: a cascade
    posterior of 1035 steps in 29.7 s, 60.0 s when each call tabulated its own)."""
    from emccdcal.fit import engine
    from emccdcal.fit.series import AcquisitionModel, SeriesLikelihood

    seen = []
    monkeypatch.setattr(engine, "objective", lambda *a: seen.append(cascade._SCOPE.get()))
    models = [
        AcquisitionModel(s, np.array([100.0]), np.array([5.0]), noise.EMModel("cascade", 536))
        for s in (1, 10)
    ]
    SeriesLikelihood("gs", models, e_per_adu=2.0).objective(np.zeros((1, 2)))
    assert seen == [True] and not cascade._SCOPE.get()


def test_register_transform_runs_on_the_array_api_standard():
    """The transform, its table and its recursion use the array API standard only: on
    array-api-strict arrays (which refuse anything outside it) they return that
    namespace's arrays, the same numbers as NumPy's."""
    xs = pytest.importorskip("array_api_strict")
    u, g = _rows(300.0, 0.03, 0.6)
    cases = [
        (u, g),
        (u[:2, :5], g[:2]),
        (np.full((3, 4), 1e-4), g[:3]),
        (np.zeros(2), np.array([5.0, 300.0])),
    ]  # a table, the recursion, a tilt, 1-D
    for uu, gg in cases:
        for order, cic, by_u in ((0, False, True), (1, False, False), (2, True, True)):
            want = cascade.register_transform(uu, gg, 536, order=order, cic=cic, by_u=by_u)
            got = cascade.register_transform(
                xs.asarray(uu), xs.asarray(gg), 536, order=order, cic=cic, by_u=by_u
            )
            assert got.keys() == want.keys()
            for key, value in got.items():
                assert isinstance(value, type(xs.asarray(0.0)))
                np.testing.assert_allclose(np.asarray(value), want[key], rtol=1e-15, atol=0)


@pytest.mark.slow
def test_logpmf_grad_matches_finite_differences():
    counts = np.array([700, 1100, 1500])
    base = dict(photoelectrons=370.0, em_gain=5.0, e_per_adu=3.859, offset=587.0, read_noise=15.5)
    model = dict(em_model=noise.EMModel("cascade", 536), register_cic=0.1)
    _, grad = noise.logpmf_grad(counts, **base, **model)
    for name in list(base) + ["register_cic"]:
        h = 1e-5 * max(1.0, abs(base.get(name, 0.1)))
        up, dn = dict(base, **model), dict(base, **model)
        up[name] = up[name] + h
        dn[name] = dn[name] - h
        fd = (noise.logpmf(counts, **up) - noise.logpmf(counts, **dn)) / (2 * h)
        assert np.allclose(grad[name], fd, rtol=1e-5, atol=1e-7), name


@pytest.mark.slow
def test_cascade_moments_and_the_gamma_limit_at_one():
    counts = np.arange(300, 4000)
    p = noise.pmf(counts, 370.0, 5.0, 3.859, 587.0, 15.5, em_model=noise.EMModel("cascade", 536))
    mean = np.sum(p * counts)
    var = np.sum(p * counts**2) - mean**2
    assert abs(mean - (587.0 + 370.0 * 5.0 / 3.859)) < 1e-6
    F2 = cascade.excess_noise_factor(5.0, 536)
    assert abs(var - (15.5**2 + 370.0 * 25.0 * F2 / 3.859**2)) < 1e-4
    # g = 1 is no multiplication under either model
    assert np.allclose(
        noise.logpmf(counts[:50], 3.0, 1.0, 0.5, 300.0, 2.0, em_model="cascade"),
        noise.logpmf(counts[:50], 3.0, 1.0, 0.5, 300.0, 2.0, em_model="gamma"),
    )


def test_em_model_arguments_are_checked():
    with pytest.raises(OptionError, match="unknown em_model"):
        noise.logpmf(10, 1.0, 2.0, 1.0, 0.0, 1.0, em_model="binomial")
    with pytest.raises(OptionError, match="stages"):
        noise.logpmf(10, 1.0, 2.0, 1.0, 0.0, 1.0, em_model=noise.EMModel("cascade", 0))
    with pytest.raises(OptionError, match="em_model must be one of"):
        noise.logpmf(10, 1.0, 2.0, 1.0, 0.0, 1.0, em_model=536)
    with pytest.raises(OptionError, match="register_cic"):
        noise.logpmf(10, 1.0, 2.0, 1.0, 0.0, 1.0, register_cic=0.1, em_model="gamma")
    with pytest.raises(OptionError, match="stages are the cascade model's"):
        noise.choose_em_model("gamma", 604)
    # a run: the exact cascade unless told; the caller's choice over the manifest's,
    # the manifest's over what is known of the camera, that over the stated default;
    # stages alone mean the cascade
    choose, cascade = noise.choose_em_model, noise.EMModel("cascade", 536)
    assert choose() == (cascade, "default")
    assert choose(stages=604) == (noise.EMModel("cascade", 604), "given")
    assert choose(stages=604, manifest_model="gamma")[0] == noise.EMModel("cascade", 604)
    assert choose("gamma", manifest_model="cascade", manifest_stages=604) == (
        noise.EMModel("gamma"),
        "",
    )
    assert choose(manifest_model="gamma") == (noise.EMModel("gamma"), "")
    assert choose("cascade", manifest_stages=604) == (noise.EMModel("cascade", 604), "manifest")
    assert choose(manifest_stages=591, camera_model="iXon Ultra 888")[1] == "manifest"
    assert choose(camera_model="iXon Ultra 888") == (
        noise.EMModel("cascade", 604),
        "camera model 'iXon Ultra 888': Andor iXon Ultra 888, a CCD201-20 sensor",
    )
    assert choose(camera_model="ProEM+: 512B eXcelon") == (cascade, "default")
    assert choose(noise.EMModel("cascade", 604)) == (noise.EMModel("cascade", 604), "given")
    with pytest.raises(OptionError, match="disagrees"):
        choose(noise.EMModel("cascade", 604), stages=536)


# --------------------------------------------------------------------------------------
# Monte Carlo of the stage-by-stage register
# --------------------------------------------------------------------------------------
def _chi2_pvalue(counts, p_model, support):
    """Pearson χ² p-value of sampled counts against a pmf on ``support``, bins merged
    until each expects at least 20."""
    from scipy import stats

    observed = np.bincount(counts - support[0], minlength=support.size)[: support.size]
    expected = p_model * counts.size
    edges, acc = [0], 0.0
    for i, e in enumerate(expected):
        acc += e
        if acc >= 20:
            edges.append(i + 1)
            acc = 0.0
    edges[-1] = support.size
    o = np.add.reduceat(observed, edges[:-1])
    e = np.add.reduceat(expected, edges[:-1])
    chi2 = np.sum((o - e) ** 2 / e)
    return stats.chi2.sf(chi2, len(o) - 1)


@pytest.mark.slow
@pytest.mark.parametrize("g, E, N, n_draws", [(4.78, 20.0, 536, 200_000), (25.0, 5.0, 64, 400_000)])
def test_stage_by_stage_register_fits_the_cascade_not_the_gamma(g, E, N, n_draws):
    # The gamma model's misfit shrinks with the gain and the stages: 2e5 draws reject it
    # at 5x on 536 stages; at 25x that takes 1.3e6 (its χ² noncentrality is 3e-4 per
    # draw), so there a 64-stage register (2e-3 per draw) keeps the stage-by-stage
    # sampler's cost (draws × stages) small. The exact model must pass both.
    rng = np.random.default_rng(2026)
    phi, S0, sigma = 3.859, 200.0, 4.0
    electrons = cascade_sampling.sample_cascade(rng.poisson(E, n_draws), g, N, rng, method="stages")
    counts = np.rint(S0 + electrons / phi + rng.normal(0.0, sigma, n_draws)).astype(np.int64)
    support = np.arange(counts.min(), counts.max() + 1)
    sd = np.sqrt(sigma**2 + 1 / 12)  # read noise of the rounded counts
    exact = noise.pmf(support, E, g, phi, S0, sd, em_model=noise.EMModel("cascade", N))
    gamma = noise.pmf(support, E, g, phi, S0, sd, em_model="gamma")
    assert _chi2_pvalue(counts, exact, support) > 1e-3
    assert _chi2_pvalue(counts, gamma, support) < 1e-6


# --------------------------------------------------------------------------------------
# The likelihood methods under the cascade
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def cascade_series(tmp_path_factory):
    base = tmp_path_factory.mktemp("cascade-gs")
    sim = simulate_gain_series(
        base,
        setpoints=(1, 5, 25, 100, 300),
        em_gain=(1, 4.78, 22.95, 90.06, 261.6),
        photoelectrons=370.0,
        seed=3,
        rows=8,
        cols=16,
        frames=2000,
        dark_frames=10,
        e_per_adu=3.859,
        read_noise=15.5,
        offset=587.7,
        multiplication="cascade",
        stages=536,
    )
    return sim, truth_manifest(sim, 15.5)


def _fit(manifest, **kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ds = calibrate(manifest, "gs", checks=False, **kw)
    return ds, [str(w.message) for w in caught]


@pytest.mark.slow
def test_gs_with_the_cascade_recovers_the_gains_the_gamma_model_misses(cascade_series):
    sim, manifest = cascade_series
    true_g = np.array([1, 4.78, 22.95, 90.06, 261.6])
    exact, exact_warnings = _fit(manifest)  # the default: the cascade, 536 stages
    gamma, gamma_warnings = _fit(manifest, em_model="gamma")
    assert exact.attrs["em_model"] == "cascade" and int(exact.attrs["register_stages"]) == 536
    assert exact.attrs["register_stages_source"] == "default"
    assert gamma.attrs["em_model"] == "gamma"
    for a, g in enumerate(true_g[1:], start=1):
        est = exact.em_gain.values[a].ravel()
        sem = est.std(ddof=1) / np.sqrt(est.size)
        assert abs(est.mean() - g) < 3 * sem  # unbiased
        biased = gamma.em_gain.values[a].ravel()
        assert biased.mean() < g - 3 * sem  # the gamma's bias
    # the goodness of fit: the gamma model misfits 5x and says what to try
    assert any("5x" in w and "cascade" in w for w in gamma_warnings)
    assert not any("misfit" in w for w in exact_warnings)


@pytest.mark.slow
def test_manifest_selects_the_model_and_the_caller_overrides_it(cascade_series, tmp_path):
    sim, manifest = cascade_series
    text = manifest.read_text()
    chosen = manifest.with_name("manifest-cascade.toml")
    chosen.write_text('em_model = "cascade"\nregister_stages = 604\n' + text)
    ds, _ = _fit(chosen, out=tmp_path / "out")
    assert ds.attrs["em_model"] == "cascade" and int(ds.attrs["register_stages"]) == 604
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["em_model"] == "cascade" and summary["register_stages"] == 604
    ds, _ = _fit(chosen, em_model="gamma")
    assert ds.attrs["em_model"] == "gamma" and "register_stages" not in ds.attrs
    # a length alone: the default model, the cascade, of that length
    alone = manifest.with_name("manifest-stages.toml")
    alone.write_text("register_stages = 604\n" + text)
    ds, _ = _fit(alone)
    assert ds.attrs["em_model"] == "cascade" and int(ds.attrs["register_stages"]) == 604
    assert ds.attrs["register_stages_source"] == "manifest"
    bad = manifest.with_name("manifest-bad.toml")
    bad.write_text('em_model = "gamma"\nregister_stages = 604\n' + text)
    with pytest.raises(ManifestError, match="register_stages: stages are the cascade model"):
        calibrate(bad, "gs")
    bad.write_text('em_model = "binomial"\n' + text)
    with pytest.raises(ManifestError, match="em_model must be one of"):
        calibrate(bad, "gs")


def test_engine_gradient_and_observed_information_under_the_cascade():
    from emccdcal.data import stats
    from emccdcal.fit import engine
    from emccdcal.simulate.camera import simulate_frames

    frames = simulate_frames(
        370.0,
        4.78,
        3.859,
        587.0,
        15.5,
        frames=1500,
        rows=2,
        cols=3,
        seed=5,
        multiplication="cascade",
        stages=536,
    )
    h = stats.histograms(frames)
    P = h.n.size
    acq = engine.AcquisitionBlock(
        h.values,
        h.counts,
        np.full(P, 587.0),
        np.full(P, 15.5),
        False,
        h.mean,
        h.var,
        h.n,
        em_model=noise.EMModel("cascade", 536),
    )
    coords = [np.full(P, np.log(372.0)), np.full(P, -np.log(3.85)), np.full(P, np.log(4.75))]
    ll, grad, obs, *_ = engine._acquisition_terms(acq, coords, 2)
    step = 1e-5
    for i in range(3):
        plus = [c + step * (j == i) for j, c in enumerate(coords)]
        minus = [c - step * (j == i) for j, c in enumerate(coords)]
        lp = engine._acquisition_terms(acq, plus, 1)
        lm = engine._acquisition_terms(acq, minus, 1)
        assert np.allclose((lp[0] - lm[0]) / (2 * step), grad[:, i], rtol=1e-5, atol=1e-4)
        # the observed information is minus the derivative of the gradient
        assert np.allclose(-(lp[1] - lm[1]) / (2 * step), obs[:, :, i], rtol=1e-4, atol=1e-2)
    # and the log-likelihood is that of the public noise model
    ref = [
        np.sum(
            h.counts[p]
            * noise.logpmf(
                h.values[p], 372.0, 4.75, 3.85, 587.0, 15.5, em_model=noise.EMModel("cascade", 536)
            )
        )
        for p in range(P)
    ]
    assert np.allclose(ll, ref, rtol=1e-10)


def test_mv_gain_with_the_exact_excess_noise_factor():
    from emccdcal.fit.mv import fit_mv_gain

    phi, s0, sigma, E, N = 3.859, 100.0, 15.5, 370.0, 536
    g = np.array([1.0, 4.78, 22.95, 261.6])
    F2 = np.where(g == 1, 1.0, cascade.excess_noise_factor(g, N))
    mean = (s0 + g * E / phi)[:, None]
    var = (sigma**2 + F2 * E * (g / phi) ** 2)[:, None]
    exact = fit_mv_gain(
        mean, var, s0, sigma, 5000, phi, [1, 5, 25, 300], em_model=noise.EMModel("cascade", N)
    )
    gamma = fit_mv_gain(mean, var, s0, sigma, 5000, phi, [1, 5, 25, 300])
    np.testing.assert_allclose(exact.em_gain[:, 0], g, rtol=1e-10)
    np.testing.assert_allclose(exact.photoelectrons[:, 0], E, rtol=1e-10)
    # F² = 2 reads the 5x gain F²/2 − 1 low
    assert gamma.em_gain[1, 0] / g[1] - 1 == pytest.approx(F2[1] / 2 - 1, rel=1e-9)
    assert np.isnan(cascade.gain_from_gain_f2(0.5, N)[0])


@pytest.mark.slow
def test_command_line_takes_the_model(cascade_series, tmp_path):
    from emccdcal.cli import main

    _, manifest = cascade_series
    out = tmp_path / "out"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        code = main(
            [
                "calibrate",
                str(manifest),
                "--em-model",
                "cascade",
                "--stages",
                "604",
                "--no-checks",
                "-q",
                "-o",
                str(out),
            ]
        )
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["em_model"], summary["register_stages"]) == ("cascade", 604)
