"""The exact register: a Bernoulli cascade of N stages (docs/cascade.md).

One electron's output has the probability generating function ``G_N`` of the register
(:func:`emccdcal.model.cascade.register_transform`), so with ``u = s/φ``

    K_X(s) = E·v(u) + c·v̄(u),   v = G_N(e^u) − 1,

where ``v̄`` is the mean of ``v`` over the stages at which a register clock-induced-charge
electron (rate c per pixel per frame) enters. A subclass of the register base class
(:class:`emccdcal.model.register.Register`): it inherits the rows, the fit coordinates and
the saddlepoint tail, and overrides the rest with the cascade's exact recursions.
"""

from __future__ import annotations

import numpy as np

from ._gamma import band_limit
from .cascade import (
    excess_noise_factor,
    gain_from_gain_f2,
    register_transform,
    single_electron_moments,
)
from .cascade_sampling import sample_cascade, sample_register_cic
from .register import Register


class Cascade(Register):
    """The exact register of ``stages`` stages, in each of which every electron makes one
    more with probability p = g^{1/N} − 1; its excess-noise factor is below 2 (1.795 at
    g = 5, N = 536). Fit coordinates (ln E, ln(1/φ), ln g): the gain shapes the
    distribution, not only its scale. Rows without multiplication are the gamma
    module's Poisson–normal ones."""

    name = "cascade"
    uses_stages = True
    parameters = ("register_cic",)
    #: The transform comes from N stages of a recursion whose relative round-off grows to
    #: ~N·1e-16 (1e-13 at 536 stages): windows are trusted only closer to their peak,
    #: and tilted windows centred on the rest.
    trusted = 1e-4

    def __init__(self, stages):
        self.stages = int(stages)

    @property
    def description(self):
        return f"exact Bernoulli cascade, {self.stages} stages"

    def transform(self, u, g):
        return register_transform(u, g, self.stages, order=0)["v"]

    def transform_terms(self, u, g, order=1, cic=False, by_u=True):
        """The transform and its derivatives by the register's own recursion (forward
        mode, exact; :func:`emccdcal.model.cascade.register_transform`)."""
        return register_transform(u, g, self.stages, order=order, cic=cic, by_u=by_u)

    def window_band(self, E_t, theta_t, sigma, scale, n):
        """DFT bins to evaluate: the gamma model's bound at e^-40 with half the
        photoelectrons (the cascade's transform decays like the gamma model's with
        F²/2 ≥ ½ of them at low frequencies, and like it saturates at high ones), which
        the engine widens where the transform has not died out at the edge. Where the
        read noise does not suppress the electron lattice's revival of the transform at
        ω = 2πφ, the Gaussian's band."""
        if np.any(2.0 * np.pi / scale < np.sqrt(160.0) / sigma):
            return super().window_band(E_t, theta_t, sigma, scale, n)
        pn = np.zeros(E_t.shape, dtype=bool)
        return int(band_limit(0.5 * E_t, theta_t, sigma, pn, n, level=40.0).max())

    def excess_noise_factor(self, g):
        return np.asarray(excess_noise_factor(g, self.stages))

    def sample(self, electrons, g, rng, method="pmf"):
        """Output electrons (float) of ``electrons`` entering the register at gain g
        (:func:`emccdcal.model.cascade_sampling.sample_cascade`'s ``method``)."""
        return sample_cascade(electrons, g, self.stages, rng, method=method).astype(float)

    def sample_register_cic(self, count, g, rng):
        """Output electrons (float) of ``count`` electrons made inside the register at
        gain g (:func:`emccdcal.model.cascade_sampling.sample_register_cic`)."""
        return sample_register_cic(count, g, self.stages, rng).astype(float)

    def single_electron_moments(self, g):
        """E[X^k], k = 1…4, of the output X of one electron
        (:func:`emccdcal.model.cascade.single_electron_moments`)."""
        return single_electron_moments(g, self.stages)

    def gain_from_gain_f2(self, y):
        """g with ``g·F²(g, N) = y`` and the slope ``d(g F²)/dg`` there."""
        return gain_from_gain_f2(y, self.stages)
