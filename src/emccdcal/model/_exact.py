"""The exact register: a Bernoulli cascade of N stages (docs/cascade.md).

One electron's output has the probability generating function ``G_N`` of the register
(:func:`emccdcal.model.cascade.register_transform`), so with ``u = s/φ``

    K_X(s) = E·v(u) + c·v̄(u),   v = G_N(e^u) − 1,

where ``v̄`` is the mean of ``v`` over the stages at which a register clock-induced-charge
electron (rate c per pixel per frame) enters. The gain and c enter through the
register's transform; the rows' ``scale`` is 1/φ (ADU per electron). Beyond the longest
window the far tail is the saddlepoint approximation.
"""

from __future__ import annotations

import numpy as np

from .. import _roots, _xp
from . import _engine
from ._gamma import GammaRows, band_limit
from .cascade import (
    excess_noise_factor,
    gain_from_gain_f2,
    register_transform,
    sample_cascade,
    sample_register_cic,
    single_electron_moments,
)


class CascadeRows:
    """Parameter rows of the exact register: photoelectrons E (e⁻), scale 1/φ (ADU per
    electron), N stages, each row's mean gain g and register clock-induced-charge rate
    (e⁻ per pixel per frame entering the register at a uniformly random stage)."""

    #: The transform comes from N stages of a recursion whose relative round-off grows to
    #: ~N·1e-16 (1e-13 at 536 stages): windows are trusted only closer to their peak,
    #: and tilted windows centred on the rest.
    trusted = 1e-4

    def __init__(self, E, scale, stages, gain, cic=0.0):
        self.E, self.scale = E, scale
        self.stages = int(stages)
        self.gain = np.asarray(gain, dtype=float)
        self.cic = np.broadcast_to(np.asarray(cic, dtype=float), self.gain.shape)
        self.pn = np.zeros(self.gain.shape, dtype=bool)

    def take(self, idx):
        return CascadeRows(self.E[idx], self.scale[idx], self.stages, self.gain[idx], self.cic[idx])

    @property
    def has_cic(self) -> bool:
        return bool(np.any(self.cic > 0))

    @property
    def names(self):
        """Native parameters (``register_cic`` only where it is used)."""
        return ("photoelectrons", "scale", "em_gain") + (("register_cic",) if self.has_cic else ())

    def _transform(self, u, order, cic, by_u=True):
        return register_transform(u, self.gain, self.stages, order=order, cic=cic, by_u=by_u)

    def cgf(self, s, order=0, names=()):
        """``K_X(s)`` (P, M) and its derivatives by ``names`` (without ``scale``, the
        register's transform skips its u-derivatives); ``second`` holds both orders of a
        pair."""
        cic = self.has_cic or "register_cic" in names
        by_u = "scale" in names
        E, scale, gain, cic_rate = _xp.like(s, self.E, self.scale, self.gain, self.cic)
        T = register_transform(
            s * scale[:, None], gain, self.stages, order=order, cic=cic, by_u=by_u
        )
        Ec, c, g = E[:, None], cic_rate[:, None], gain[:, None]

        def mix(key):  # E·v + c·v̄, and likewise for a derivative of v
            return Ec * T[key] + c * T["cic_" + key] if cic else Ec * T[key]

        first, sec = {}, {}
        if order >= 1:
            first = {"photoelectrons": T["v"], "em_gain": mix("g") / g}
            if by_u:
                first["scale"] = s * mix("u")
            if cic:
                first["register_cic"] = T["cic_v"]
        if order >= 2:
            sec = {
                ("photoelectrons", "em_gain"): T["g"] / g,
                ("em_gain", "em_gain"): (mix("gg") - mix("g")) / g**2,
            }
            if by_u:
                sec.update(
                    {
                        ("photoelectrons", "scale"): s * T["u"],
                        ("scale", "scale"): s * s * mix("uu"),
                        ("scale", "em_gain"): s * mix("ug") / g,
                    }
                )
            if cic:
                sec[("em_gain", "register_cic")] = T["cic_g"] / g
                if by_u:
                    sec[("scale", "register_cic")] = s * T["cic_u"]
            sec.update({(b, a): v for (a, b), v in list(sec.items())})
        return mix("v"), first, sec

    def real(self, t):
        """``K_X``, ``K_X'``, ``K_X''`` at real tilts t, the tilted photoelectron mean and
        single-electron mean output (ADU)."""
        E, scale = self.E, self.scale
        if not self.has_cic and not np.any(t):
            # Untilted: the moments in closed form (mean output g, second moment g²F²).
            g = self.gain
            F2 = excess_noise_factor(g, self.stages)
            return np.zeros(E.shape), E * g * scale, E * (g * scale) ** 2 * F2, E, g * scale
        cic = self.has_cic
        T = self._transform(t * scale, 2, cic)

        def mix(key):
            return E * T[key] + self.cic * T["cic_" + key] if cic else E * T[key]

        growth = 1.0 + T["v"]  # G(e^{t/φ}): the tilted photoelectron mean is E·G
        # The tilted single-electron output; far below the mean it is one electron.
        with np.errstate(divide="ignore", invalid="ignore"):
            theta = np.where(growth > 0, scale * T["u"] / growth, scale)
        return mix("v"), scale * mix("u"), scale**2 * mix("uu"), E * growth, theta

    def band(self, E_t, theta_t, sigma, n):
        """DFT bins to evaluate: the gamma model's bound at e^-40 with half the
        photoelectrons (the cascade's transform decays like the gamma model's with
        F²/2 ≥ ½ of them at low frequencies, and like it saturates at high ones), which
        the engine widens where the transform has not died out at the edge. Where the
        read noise does not suppress the electron lattice's revival of the transform at
        ω = 2πφ, the Gaussian's band."""
        full = n // 2 + 1
        w_gauss = np.sqrt(160.0) / sigma
        if np.any(2.0 * np.pi / self.scale < w_gauss):
            m = int(np.ceil(float(w_gauss.max()) * n / (2.0 * np.pi))) + 2
            return min(m, full)
        pn = np.zeros(E_t.shape, dtype=bool)
        return int(band_limit(0.5 * E_t, theta_t, sigma, pn, n, level=40.0).max())

    def saddlepoint(self, k, S0, sigma):
        """Tilt t that puts the tilted mean K'(t) within half a tilted SD of count k:
        Newton's method on K' from the gamma model's saddlepoint, kept inside a bracket,
        bisecting where it leaves the bracket or stops converging. (Any tilt gives exact
        values; the saddlepoint only centres the window on the target.)

        The bracket: the electron part of K' is positive and increasing in t, so
        ``S0 + σ²t ≤ K'(t)`` everywhere and ``K'(t) ≤ K'(0) + σ²t`` for t ≤ 0.
        """
        E = self.E
        mean0 = _engine.real_cgf(self, np.zeros(E.shape), S0, sigma)[1]
        lo = np.minimum(0.0, (k - mean0) / sigma**2)
        hi = (k - S0) / sigma**2
        # Start from the gamma model's saddlepoint (closed-form cumulants, cheap): its
        # register differs only in F², so Newton then needs a few steps, not a bisection.
        gamma = GammaRows(E, self.gain * self.scale, np.zeros(E.shape, dtype=bool))
        t = gamma.saddlepoint(k, S0, sigma)
        t = np.where((t > lo) & (t < hi), t, 0.5 * (lo + hi))

        def residual(t):
            _, dK, d2K, _, _ = _engine.real_cgf(self, t, S0, sigma)
            return dK - k, d2K

        # solved once the miss is below half the tilted distribution's SD
        return _roots.newton_in_bracket(
            residual, lo, hi, t, max_iter=100, close=lambda miss, d2K: miss < 0.5 * np.sqrt(d2K)
        )

    def direct_tail(self, sigma):
        """None: every count first gets a (tilted) window."""
        return np.zeros(self.E.shape, dtype=bool)

    def tail(self, k, S0, sigma, grad=False):
        """Saddlepoint approximation of log f(k) beyond the longest window (relative error
        of order 1/(number of electrons) there, far below 1e-10 of the peak):
        ``K(t) − tk − ½ ln(2πK''(t))`` at ``K'(t) ≈ k``; gradients by the envelope
        theorem, ``∂K/∂λ`` at the fixed t."""
        t = self.saddlepoint(k, S0, sigma)
        K, _, d2K, _, _ = _engine.real_cgf(self, t, S0, sigma)
        logf = K - t * k - 0.5 * np.log(2.0 * np.pi * d2K)
        if not grad:
            return logf, {}
        names = self.names + _engine.READOUT
        _, first, _ = _engine.cgf(self, t[:, None].astype(complex), S0, sigma, 1, names)
        grads = {name: first[name][:, 0].real for name in names}
        grads["offset"] = grads["offset"] - t
        return logf, grads


class Cascade:
    """The exact register of ``stages`` stages, in each of which every electron makes one
    more with probability p = g^{1/N} − 1; its excess-noise factor is below 2 (1.795 at
    g = 5, N = 536). Fit coordinates (ln E, ln(1/φ), ln g): the gain shapes the
    distribution, not only its scale. Rows without multiplication are the gamma
    module's Poisson–normal ones."""

    name = "cascade"
    uses_stages = True
    parameters = ("register_cic",)
    misfit_hint = None

    def __init__(self, stages):
        self.stages = int(stages)

    def __eq__(self, other):
        return type(other) is Cascade and other.stages == self.stages

    def __hash__(self):
        return hash((Cascade, self.stages))

    @property
    def description(self):
        return f"exact Bernoulli cascade, {self.stages} stages"

    def register_for(self, poisson_normal):
        """The register of rows with (True) or without multiplication."""
        from ._gamma import Gamma

        return Gamma() if poisson_normal else self

    def excess_noise_factor(self, g):
        return np.asarray(excess_noise_factor(g, self.stages))

    def sample(self, electrons, g, rng, method="pmf"):
        """Output electrons (float) of ``electrons`` entering the register at gain g
        (:func:`emccdcal.model.cascade.sample_cascade`'s ``method``)."""
        return sample_cascade(electrons, g, self.stages, rng, method=method).astype(float)

    def sample_register_cic(self, count, g, rng):
        """Output electrons (float) of ``count`` electrons made inside the register at
        gain g (:func:`emccdcal.model.cascade.sample_register_cic`)."""
        return sample_register_cic(count, g, self.stages, rng).astype(float)

    def single_electron_moments(self, g):
        """E[X^k], k = 1…4, of the output X of one electron
        (:func:`emccdcal.model.cascade.single_electron_moments`)."""
        return single_electron_moments(g, self.stages)

    def gain_from_gain_f2(self, y):
        """g with ``g·F²(g, N) = y`` and the slope ``d(g F²)/dg`` there."""
        return gain_from_gain_f2(y, self.stages)

    def rows(self, E, g, phi, cic=0.0):
        return CascadeRows(E, 1.0 / phi, self.stages, g, cic)

    @staticmethod
    def coordinates(poisson_normal):
        return _CASCADE_COORDS

    def rows_at(self, values, poisson_normal):
        E, scale, gain = values
        return CascadeRows(E, scale, self.stages, gain, 0.0)

    @staticmethod
    def public_gradients(d, g, phi):
        return {
            "em_gain": d["em_gain"],
            "e_per_adu": -d["scale"] / phi**2,
            "register_cic": d.get("register_cic", np.zeros(g.shape)),
        }


_CASCADE_COORDS = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
