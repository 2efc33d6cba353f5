"""The register base class: a third register model written as a subclass in a few lines
(``PoissonStages`` below, a register whose every stage gives each electron a Poisson
number of new ones) passes ``emccdcal.testing.check_register``, agrees with its closed
forms, and calibrates a simulated series; what the base class computes numerically
agrees with the exact register's own recursions; a subclass without its transform is
refused when it is loaded."""

from __future__ import annotations

import inspect
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

import emccdcal
from emccdcal import plugins
from emccdcal.model import Register, noise
from emccdcal.model.cascade import register_transform
from emccdcal.simulate.series import simulate_gain_series
from emccdcal.testing import check_register


class PoissonStages(Register):
    """In each of N stages every electron makes Poisson(p) new ones: mean gain
    g = (1 + p)^N, excess-noise factor 1 + (g − 1)/(g(1 + p)) (a Galton–Watson process)."""

    name = "poisson-stages"
    description = "Poisson multiplication in every stage"
    uses_stages = True

    def transform(self, u, g):
        p = g ** (1.0 / self.stages) - 1.0
        v = np.expm1(u)  # M − 1 of one electron before the register
        for _ in range(self.stages):  # one stage's pgf, z·e^{p(z−1)}, in terms of z − 1
            v = np.expm1(np.log1p(v) + p * v)
        return v


def test_the_third_model_is_a_few_lines_and_the_one_the_plugins_page_shows():
    source = inspect.getsource(PoissonStages)
    assert len([line for line in source.splitlines() if line.strip()]) < 40
    page = Path(__file__).resolve().parents[1] / "docs" / "plugins.md"
    if page.is_file():  # a source tree: the page shows this very class
        assert source in page.read_text(encoding="utf-8")


@pytest.fixture
def poisson_stages(monkeypatch):
    monkeypatch.setitem(plugins.load(plugins.REGISTERS), PoissonStages.name, PoissonStages)
    return PoissonStages


def test_it_passes_the_plugin_authors_check():
    check_register(PoissonStages, stages=64)


@pytest.mark.parametrize("g", [1.5, 20.0, 300.0])
def test_what_it_inherits_agrees_with_its_closed_forms(g):
    register = PoissonStages(64)
    p = g ** (1 / 64) - 1
    F2 = 1 + (g - 1) / (g * (1 + p))
    assert float(register.excess_noise_factor(np.array(g))) == pytest.approx(F2, rel=1e-11)
    m = register.single_electron_moments(g)
    assert m[0] == pytest.approx(g, rel=1e-12) and m[1] == pytest.approx(F2 * g * g, rel=1e-11)
    gain, slope = register.gain_from_gain_f2(np.array([g * F2]))
    assert gain[0] == pytest.approx(g, rel=1e-12)
    step = 1e-6 * g
    want = ((g + step) * register.excess_noise_factor(g + step) - g * F2) / step
    assert slope[0] == pytest.approx(want, rel=1e-4)
    out = register.sample(np.full(40000, 3), g, np.random.default_rng(5))
    assert np.all(out == np.round(out)) and out.min() >= 3  # whole electrons, none lost
    se_mean = np.sqrt(3 * F2 * g * g / out.size)
    assert abs(out.mean() - 3 * g) < 5 * se_mean
    assert out.var() / (3 * g * g * (F2 - 1)) == pytest.approx(1, abs=0.05)


class NumericCascade(Register):
    """The exact register through the base class's numerics: only its transform."""

    name, description, uses_stages = "numeric-cascade", "test", True

    def transform(self, u, g):
        u, g = np.broadcast_arrays(u, g)  # the recursion takes one gain per element
        v = register_transform(u.ravel(), g.ravel().astype(float), self.stages, order=0)["v"]
        return v.reshape(u.shape)


def test_the_numerical_derivatives_agree_with_the_exact_recursion():
    u = 0.01 * (0.3 + 1j * np.linspace(0.0, 3.0, 7))[None, :] * np.ones((3, 1))
    g = np.array([3.0, 40.0, 250.0])
    u = u / g[:, None]
    exact = register_transform(u, g, 128, order=2)
    numeric = NumericCascade(128).transform_terms(u, g, order=2)
    for key in ("v", "u", "g", "uu", "ug", "gg"):
        scale = np.abs(exact[key]).max(axis=1, keepdims=True)
        assert np.max(np.abs(numeric[key] - exact[key]) / scale) < 2e-7, key


def test_its_likelihood_and_gradients_are_the_exact_registers(monkeypatch):
    monkeypatch.setitem(plugins.load(plugins.REGISTERS), NumericCascade.name, NumericCascade)
    counts = np.arange(90, 700, 7)
    args = (counts, 8.0, 30.0, 4.0, 100.0, 3.0)
    exact = noise.logpmf_grad(*args, em_model=noise.EMModel("cascade", 128))
    numeric = noise.logpmf_grad(*args, em_model=noise.EMModel("numeric-cascade", 128))
    assert np.allclose(numeric[0], exact[0], rtol=0, atol=1e-9)
    for name in ("em_gain", "e_per_adu", "photoelectrons", "offset", "read_noise"):
        assert np.allclose(numeric[1][name], exact[1][name], rtol=1e-6, atol=1e-9), name


def test_a_model_given_as_an_object_is_held_not_looked_up():
    register = PoissonStages(64)
    model = noise.EMModel.of(register)
    assert model.register is register and model.stages == 64
    assert noise.as_em_model(register) == model
    cascade = noise.EMModel("cascade", 300)
    assert cascade.register is cascade.register  # made once


def test_it_calibrates_a_series(poisson_stages, tmp_path):
    """A series simulated with the model, calibrated with it: the gains and φ within
    their standard errors of the truth."""
    sim = simulate_gain_series(
        tmp_path / "series",
        rows=2,
        cols=3,
        frames=400,
        seed=31,
        setpoints=(1, 10, 60),
        photoelectrons=40.0,
        multiplication="poisson-stages",
        stages=24,
        progress=False,
    )
    result = emccdcal.calibrate(sim.manifest, "gs", em_model=PoissonStages(24), progress=False)
    assert result.attrs["em_model"] == "poisson-stages" and result.attrs["register_stages"] == 24
    truth = sim.truth
    assert np.allclose(result["e_per_adu"], truth["e_per_adu"])  # the manifest's φ
    want = xr.DataArray([a["em_gain"] for a in truth["acquisitions"]], dims="setpoint")
    miss = np.abs(result["em_gain"] - want) / result["em_gain_se"]
    assert float(miss.max()) < 4, miss.values


def test_a_subclass_without_its_transform_is_refused_when_loaded():
    class Unfinished(Register):
        name, description = "unfinished", "no transform"

    why = plugins._problem(plugins.REGISTERS, Unfinished)
    assert why == "subclasses Register without defining its transform(u, g)"
    assert plugins._problem(plugins.REGISTERS, PoissonStages) == ""
