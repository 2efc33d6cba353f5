"""Tests of emccdcal.gof: the per-pixel binned χ² goodness-of-fit test."""

from functools import partial

import numpy as np
import pytest
from scipy import stats as st

from emccdcal.data import stats
from emccdcal.fit import engine, gof, layouts
from emccdcal.model import noise
from emccdcal.simulate.camera import simulate_frames

PHI, S0, SIG = 3.859, 587.0, 15.5
#: The model's read noise is the SD of the rounded counts (simulate's docstring).
RN = float(np.hypot(SIG, 12**-0.5))
#: The data here are the gamma register's (``_sim``), tested under it.
pvalues = partial(gof.gof_pvalues, em_model="gamma")


def _sim(E, g, *, frames, rows, cols, seed, mult="gamma"):
    fr = simulate_frames(
        E, g, PHI, S0, SIG, frames=frames, rows=rows, cols=cols, multiplication=mult, seed=seed
    )
    return stats.histograms(fr)


# --------------------------------------------------------------------------------------
# Null distribution: the true model on its own data gives uniform p-values
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "E, g, seed", [(30.0, 100.0, 3), (20.0, 5.0, 4), (50.0, 1.0, 5), (0.3, 300.0, 6)]
)
def test_true_model_gives_uniform_pvalues(E, g, seed):
    h = _sim(E, g, frames=2000, rows=20, cols=20, seed=seed)
    p, chi2, dof = pvalues(h, E, g, PHI, S0, RN, n_fitted_params=0)
    assert p.shape == chi2.shape == dof.shape == (400,)
    assert np.all(np.isfinite(p))
    assert np.all(dof >= 40) and np.all(dof <= 49)
    assert st.kstest(p, "uniform").pvalue > 0.01
    k = int(np.sum(p < 0.05))
    assert st.binomtest(k, 400, 0.05).pvalue > 0.01, k
    # χ² has mean dof under the null
    assert abs(np.mean(chi2 / dof) - 1.0) < 4 * np.sqrt(2.0 / dof.mean() / 400)


def test_wrong_parameters_are_flagged():
    h = _sim(30.0, 100.0, frames=2000, rows=4, cols=4, seed=7)
    p_off = pvalues(h, 30.0, 100.0, PHI, S0 + 60.0, RN)[0]  # offset 0.3 SD off
    p_gain = pvalues(h, 30.0, 80.0, PHI, S0, RN)[0]  # gain 20 % low
    assert np.all(p_off < 1e-3)
    assert np.all(p_gain < 1e-3)


# --------------------------------------------------------------------------------------
# The statistic itself, against a direct per-pixel computation
# --------------------------------------------------------------------------------------
def _reference_chi2(values, counts, E, g, phi, s0, sigma, K):
    """Direct χ² with K equiprobable bins for one pixel (no merging needed)."""
    grid = np.arange(int(s0) - 400, int(s0) + 9000)
    pm = noise.pmf(grid, E, g, phi, s0, sigma, em_model="gamma")
    cdf = np.cumsum(pm) / pm.sum()
    edges = grid[np.searchsorted(cdf, np.arange(1, K) / K)]
    probs = np.diff(np.r_[0.0, cdf[edges - grid[0]], 1.0])
    obs = np.bincount(np.searchsorted(edges, values, side="left"), weights=counts, minlength=K)
    n = counts.sum()
    return np.sum((obs - n * probs) ** 2 / (n * probs))


def test_chi2_matches_direct_computation():
    h = _sim(200.0, 50.0, frames=3000, rows=2, cols=2, seed=8)
    E = np.array([200.0, 210.0, 190.0, 200.0])
    p, chi2, dof = pvalues(h, E, 50.0, PHI, S0, RN, n_fitted_params=2)
    assert np.all(dof == 47.0)  # wide distribution: 50 bins, none merged
    for i in range(4):
        ref = _reference_chi2(h.values[i], h.counts[i], E[i], 50.0, PHI, S0, RN, 50)
        assert chi2[i] == pytest.approx(ref, rel=1e-6)
    np.testing.assert_allclose(p, st.chi2.sf(chi2, 47.0))


def test_bins_and_dof_follow_frames_and_fitted_params():
    h = _sim(30.0, 100.0, frames=200, rows=1, cols=3, seed=9)
    p, chi2, dof = pvalues(h, 30.0, 100.0, PHI, S0, RN, n_fitted_params=0)
    assert np.all(dof == 19.0)  # K = 200 / 10
    dof3 = pvalues(h, 30.0, 100.0, PHI, S0, RN, n_fitted_params=3)[2]
    np.testing.assert_array_equal(dof3, dof - 3)
    dofk = pvalues(h, 30.0, 100.0, PHI, S0, RN, n_fitted_params=0, max_bins=8)[2]
    assert np.all(dofk == 7.0)


def test_vectorised_mixed_pixels_and_blocks_match_separate_calls(monkeypatch):
    """Pixels with different models in one call (PN and PGN, several blocks) agree with
    one call per group."""
    ha = _sim(50.0, 1.0, frames=1000, rows=1, cols=3, seed=10)
    hb = _sim(5.0, 300.0, frames=1000, rows=1, cols=3, seed=11)
    K = max(ha.values.shape[1], hb.values.shape[1])

    def pad(h):
        v = np.concatenate([h.values, np.repeat(h.values[:, -1:], K - h.values.shape[1], 1)], 1)
        c = np.concatenate([h.counts, np.zeros((h.n.size, K - h.counts.shape[1]))], 1)
        return v, c

    (va, ca), (vb, cb) = pad(ha), pad(hb)
    mixed = engine.AcquisitionBlock(
        values=np.concatenate([va, vb]),
        counts=np.concatenate([ca, cb]),
        offset=np.full(6, S0),
        read_noise=np.full(6, RN),
        poisson_normal=False,
        mean=np.r_[ha.mean, hb.mean],
        var=np.r_[ha.var, hb.var],
        n=np.r_[ha.n, hb.n],
    )
    E = np.r_[np.full(3, 50.0), np.full(3, 5.0)]
    g = np.r_[np.ones(3), np.full(3, 300.0)]
    sep = np.r_[pvalues(ha, 50.0, 1.0, PHI, S0, RN)[1], pvalues(hb, 5.0, 300.0, PHI, S0, RN)[1]]
    together = pvalues(mixed, E, g, PHI, S0, RN)[1]
    np.testing.assert_allclose(together, sep, rtol=1e-9)
    monkeypatch.setattr(gof, "_BLOCK_ELEMENTS", 1)  # one pixel per block
    one_by_one = pvalues(mixed, E, g, PHI, S0, RN)[1]
    np.testing.assert_allclose(one_by_one, sep, rtol=1e-9)


def test_outliers_land_in_the_tail_bins():
    h = _sim(30.0, 100.0, frames=2000, rows=1, cols=2, seed=12)
    base = pvalues(h, 30.0, 100.0, PHI, S0, RN)[1]
    # Add a far outlier (a cosmic ray, 60000 ADU) and a frame at count 0 to pixel 0.
    v = np.concatenate([[[0], [0]], h.values, [[60000], [60000]]], axis=1)
    c = np.concatenate([[[1.0], [0.0]], h.counts, [[1.0], [0.0]]], axis=1)
    blk = engine.AcquisitionBlock(
        v, c, np.full(2, S0), np.full(2, RN), False, h.mean, h.var, h.n + np.array([2, 0])
    )
    p, chi2, _ = pvalues(blk, 30.0, 100.0, PHI, S0, RN)
    assert np.isfinite(chi2).all()
    assert chi2[1] == base[1]
    assert chi2[0] != base[0]


def test_untestable_pixels_are_nan():
    h = _sim(30.0, 100.0, frames=2000, rows=1, cols=4, seed=13)
    E = np.array([30.0, np.nan, 30.0, 30.0])
    g = np.array([100.0, 100.0, 0.5, 100.0])
    p, chi2, dof = pvalues(h, E, g, PHI, S0, RN)
    assert np.isnan(p[1:3]).all() and np.isnan(chi2[1:3]).all() and np.isnan(dof[1:3]).all()
    assert np.isfinite(p[[0, 3]]).all()
    few = _sim(30.0, 100.0, frames=25, rows=1, cols=2, seed=14)  # K = 2: no dof left
    assert np.isnan(pvalues(few, 30.0, 100.0, PHI, S0, RN, n_fitted_params=1)[0]).all()
    with pytest.raises(ValueError, match="one value per pixel"):
        pvalues(h, np.ones(3), 100.0, PHI, S0, RN)
    with pytest.raises(ValueError, match="n_fitted_params"):
        pvalues(h, 30.0, 100.0, PHI, S0, RN, n_fitted_params=-1)


# --------------------------------------------------------------------------------------
# The demonstration: exact cascade data fitted by the gamma model
# --------------------------------------------------------------------------------------
E_TRUE = 370.0  # the authors' sample pixel (docs/simulation.md)
FRAMES = 20000
LOG_B = {k: np.log(v) for k, v in layouts.BOUNDS.items()}


def _block(h, pn):
    P = h.n.size
    return engine.AcquisitionBlock(
        h.values, h.counts, np.full(P, S0), np.full(P, RN), pn, h.mean, h.var, h.n
    )


def _gain_series_fit(h1, h_em):
    """Fit E (shared, anchored by the 1× acquisition) and g of the EM acquisition with the
    gamma (PGN) model and φ fixed at its true value: x = [ln E, ln g]."""
    P = h1.n.size
    M = np.zeros((2, 3, 2))
    M[:, 0, 0] = 1.0  # ln E shared by both acquisitions
    M[1, 1, 1] = 1.0  # ln g of the EM acquisition (1× has g = 1)
    C = np.zeros((P, 2, 3))
    C[:, :, 2] = np.log(PHI)
    layout = engine.Layout(
        ["ln_photoelectrons", "ln_em_gain"],
        np.r_[LOG_B["photoelectrons"][0], LOG_B["em_gain"][0]],
        np.r_[LOG_B["photoelectrons"][1], LOG_B["em_gain"][1]],
        M,
        C,
    )
    E0 = (h1.mean - S0) * PHI
    g0 = (h_em.mean - S0) * PHI / E0
    res = engine.fit(
        layout, [_block(h1, True), _block(h_em, False)], np.stack([np.log(E0), np.log(g0)], axis=1)
    )
    assert res.converged.all()
    return np.exp(res.x[:, 0]), np.exp(res.x[:, 1])


@pytest.fixture(scope="module")
def one_x():
    return _sim(E_TRUE, 1.0, frames=FRAMES, rows=4, cols=4, seed=21)


@pytest.fixture(scope="module")
def cascade_pvalues(one_x):
    out = {}
    for g, seed in ((5.0, 22), (300.0, 23)):
        h = _sim(E_TRUE, g, frames=FRAMES, rows=4, cols=4, seed=seed, mult="cascade")
        E, g_fit = _gain_series_fit(one_x, h)
        out[g] = pvalues(h, E, g_fit, PHI, S0, RN, n_fitted_params=1)[0]
    return out


def test_cascade_at_5x_is_flagged_at_300x_not(cascade_pvalues):
    p5, p300 = cascade_pvalues[5.0], cascade_pvalues[300.0]
    assert np.mean(p5 < 0.01) >= 0.75, p5
    assert np.mean(p300 < 0.01) <= 2 / 16, p300


def test_gamma_data_at_5x_is_not_flagged(one_x):
    h = _sim(E_TRUE, 5.0, frames=FRAMES, rows=4, cols=4, seed=24)
    E, g = _gain_series_fit(one_x, h)
    p = pvalues(h, E, g, PHI, S0, RN, n_fitted_params=1)[0]
    assert np.mean(p < 0.01) <= 2 / 16, p


def test_misfit_warnings_name_the_misfitting_setpoint(cascade_pvalues):
    msgs = gof.misfit_warnings(cascade_pvalues)
    assert len(msgs) == 1
    assert msgs[0].startswith("set-point 5.0:")
    assert gof.misfit_warnings({300.0: cascade_pvalues[300.0]}) == []


# --------------------------------------------------------------------------------------
# misfit_warnings on its own
# --------------------------------------------------------------------------------------
def test_misfit_warnings_fire_only_for_systematic_excess():
    rng = np.random.default_rng(1)
    uniform = rng.uniform(size=10000)
    bad = uniform.copy()
    bad[:500] = 1e-4  # 5 % of pixels misfit (+ 1 % by chance)
    slight = uniform.copy()
    slight[:60] = 1e-4  # 1.6 %: significant on 10000 pixels, but below 2·alpha
    with_nan = np.r_[bad, np.full(100, np.nan)]
    msgs = gof.misfit_warnings({"5x": bad, "300x": uniform, "25x": slight}, alpha=0.01)
    assert len(msgs) == 1 and msgs[0].startswith("set-point 5x:")
    assert "of 10000 pixels" in msgs[0]
    msgs = gof.misfit_warnings({2: with_nan}, kind="level")
    assert msgs[0].startswith("level 2:") and "of 10000 pixels" in msgs[0]
    assert gof.misfit_warnings({"25x": slight}, min_ratio=1.0) != []
    assert gof.misfit_warnings({"none": np.full(5, np.nan)}) == []
    with pytest.raises(ValueError):
        gof.misfit_warnings({1: uniform}, alpha=1.5)
