"""A register model is one module: a third one, defined here, runs through the public
noise model, goodness of fit and the fit engine without a change anywhere else.

The model: multiplication without excess noise, every electron becomes exactly g/φ ADU
(F² = 1). Its pmf is a Poisson sum of Gaussians, computed here independently.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats as sps

from emccdcal import plugins
from emccdcal.data import stats
from emccdcal.fit import engine, gof
from emccdcal.model import noise
from emccdcal.model._gamma import Gamma, GammaRows


class Noiseless:
    """No excess noise: the Poisson–normal rows' lattice, spaced g/φ. Written from the
    interface alone (``emccdcal.model.RegisterModel``), subclassing no model."""

    name = "noiseless"
    uses_stages = False
    parameters = ()
    description = "multiplication without excess noise (a test model)"
    misfit_hint = None

    def __init__(self, stages=None):
        pass

    def __eq__(self, other):
        return type(other) is Noiseless

    def __hash__(self):
        return hash(Noiseless)

    def register_for(self, poisson_normal):
        return Gamma() if poisson_normal else self

    @staticmethod
    def excess_noise_factor(g):
        return np.ones(np.shape(g))

    @staticmethod
    def gain_from_gain_f2(y):
        y = np.asarray(y, dtype=float)
        return y, np.ones(y.shape)

    @staticmethod
    def single_electron_moments(g):
        return float(g) ** np.arange(1, 5)

    @staticmethod
    def sample(electrons, g, rng, **options):
        return np.asarray(electrons, dtype=float) * g

    @staticmethod
    def rows(E, g, phi, cic=None):
        return GammaRows(E, g / phi, np.ones(np.shape(E), dtype=bool))

    @staticmethod
    def rows_at(values, poisson_normal):
        E, scale = values
        return GammaRows(E, scale, np.ones(E.shape, dtype=bool))

    @staticmethod
    def coordinates(poisson_normal):
        return np.array([[1.0, 0.0, 0.0], [0.0, 1.0, -1.0]])  # ln E, ln(g/φ)

    @staticmethod
    def public_gradients(d, g, phi):
        return {"em_gain": d["scale"] / phi, "e_per_adu": -d["scale"] * g / phi**2}


@pytest.fixture
def noiseless(monkeypatch):
    monkeypatch.setitem(plugins.load(plugins.REGISTERS), "noiseless", Noiseless)
    return noise.EMModel("noiseless")


E, G, PHI, S0, SIGMA = 6.0, 30.0, 4.0, 500.0, 4.0


def _direct(k, E=E, g=G, phi=PHI, S0=S0, sigma=SIGMA):
    n = np.arange(0, 200)
    dens = sps.norm.pdf(np.asarray(k)[:, None], S0 + n * g / phi, sigma)
    return np.log(np.sum(sps.poisson.pmf(n, E) * dens, axis=1))


def test_its_pmf_is_the_poisson_sum(noiseless):
    k = np.arange(480, 700)
    ours = noise.logpmf(k, E, G, PHI, S0, SIGMA, em_model=noiseless)
    ref = _direct(k)
    keep = ref > ref.max() + np.log(1e-12)  # where the direct sum is itself exact
    # the engine's stated accuracy: ~1e-9 relative above 1e-7 of the peak, FFT round-off
    np.testing.assert_allclose(ours[keep], ref[keep], rtol=0, atol=1e-8)
    assert np.all(np.isfinite(ours))
    assert noise.excess_noise_factor(G, em_model=noiseless) == 1.0
    assert str(noiseless) == "noiseless" and noiseless.attrs == {"em_model": "noiseless"}


def test_its_gradient_is_the_derivative(noiseless):
    k = np.array([500, 540, 560, 600, 650])
    _, grad = noise.logpmf_grad(k, E, G, PHI, S0, SIGMA, em_model=noiseless)
    for name, value in (
        ("photoelectrons", E),
        ("em_gain", G),
        ("e_per_adu", PHI),
        ("offset", S0),
        ("read_noise", SIGMA),
    ):
        h = 1e-5 * value
        args = dict(photoelectrons=E, em_gain=G, e_per_adu=PHI, offset=S0, read_noise=SIGMA)
        up = noise.logpmf(k, **{**args, name: value + h}, em_model=noiseless)
        down = noise.logpmf(k, **{**args, name: value - h}, em_model=noiseless)
        np.testing.assert_allclose(grad[name], (up - down) / (2 * h), rtol=1e-5, atol=1e-7)


def test_goodness_of_fit_and_the_fit_engine_use_it(noiseless):
    rng = np.random.default_rng(11)
    n = rng.poisson(E, size=(4000, 3))
    frames = np.rint(S0 + n * G / PHI + SIGMA * rng.standard_normal(n.shape)).astype(np.uint16)
    h = stats.histograms(frames[:, None, :])
    p, _, _ = gof.gof_pvalues(h, E, G, PHI, S0, SIGMA, n_fitted_params=0, em_model=noiseless)
    assert np.all(p > 1e-3)  # the right model fits its own data
    p_gamma, _, _ = gof.gof_pvalues(h, E, G, PHI, S0, SIGMA, n_fitted_params=0)
    assert np.all(p_gamma < 1e-6)  # the gamma model's excess noise does not
    P = h.n.size
    block = engine.AcquisitionBlock(
        values=h.values,
        counts=h.counts,
        offset=np.full(P, S0),
        read_noise=np.full(P, SIGMA),
        poisson_normal=False,
        mean=h.mean,
        var=h.var,
        n=h.n,
        em_model=noiseless,
    )
    coords = [np.full(P, np.log(E)), np.full(P, np.log(G / PHI))]
    loglik = engine._acquisition_terms(block, coords, 0)[0]
    ref = [
        np.sum(h.counts[i] * noise.logpmf(h.values[i], E, G, PHI, S0, SIGMA, em_model=noiseless))
        for i in range(P)
    ]
    np.testing.assert_allclose(loglik, ref, rtol=1e-11)


# --------------------------------------------------------------------------------------
# Every registered model, and the test's own, through the same checks (as scipy.stats
# runs every distribution through test_continuous_basic)
# --------------------------------------------------------------------------------------
@pytest.fixture(params=[*noise.EM_MODELS, "noiseless"])
def any_model(request, monkeypatch):
    monkeypatch.setitem(plugins.load(plugins.REGISTERS), "noiseless", Noiseless)
    return noise.EMModel(request.param, 64)


def test_every_register_model_supplies_the_interface(any_model):
    from emccdcal.model import RegisterModel, RegisterRows

    register = any_model.register
    assert isinstance(register, RegisterModel), any_model
    rows = register.rows(np.array([E]), np.array([G]), np.array([PHI]))
    assert isinstance(rows, RegisterRows), any_model
    assert str(any_model).startswith(any_model.name)
    assert noise.EMModel.from_attrs(any_model.attrs) == any_model


def test_every_register_models_pmf_is_a_distribution_with_its_moments(any_model):
    """Sums to 1, and its mean and variance are those its excess-noise factor says:
    S0 + E·g/φ and σ² + E·F²·(g/φ)²."""
    k = np.arange(300, 2400)
    p = noise.pmf(k, E, G, PHI, S0, SIGMA, em_model=any_model)
    assert p.sum() == pytest.approx(1.0, abs=1e-6)
    mean = float(np.sum(k * p))
    var = float(np.sum((k - mean) ** 2 * p))
    F2 = float(any_model.register.excess_noise_factor(np.array(G)))
    assert mean == pytest.approx(S0 + E * G / PHI, rel=1e-6)
    # the pmf is the density at the integers (not a rounded count): no 1/12 is added
    assert var == pytest.approx(SIGMA**2 + E * F2 * (G / PHI) ** 2, rel=1e-6)
    g, slope = any_model.register.gain_from_gain_f2(np.array([G * F2]))
    assert float(g[0]) == pytest.approx(G, rel=1e-9)


def test_the_packages_own_registers_are_its_entry_points():
    """The package registers its own models through the group another package uses, and
    they are exactly those ``defaults.EM_MODELS`` declares."""
    import importlib.metadata

    from emccdcal import defaults

    own = {
        ep.name
        for ep in importlib.metadata.entry_points(group=plugins.REGISTERS)
        if ep.dist.name == "emccdcal"
    }
    assert own == set(defaults.EM_MODELS) <= set(noise.EM_MODELS)
    assert defaults.DEFAULT_EM_MODEL in own and defaults.PAPER_EM_MODEL in own
