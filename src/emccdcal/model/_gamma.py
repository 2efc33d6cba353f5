"""The gamma register (the paper's model) and no multiplication (Poisson–normal).

One photoelectron's output in ADU has the moment generating function

    M(s) = 1/(1 − sθ)   (gamma register, θ = g/φ ADU per electron),
    M(s) = exp(s/φ)     (no multiplication, g = 1: the Poisson–normal model),

so ``K_X(s) = E·(M(s) − 1)``. Rows of both kinds go together through the window engine
(:mod:`._engine`); the few-electron exponential tail, where a tilted window would have
to be enormous, is integrated by quadrature of the model's Bessel form instead.
"""

from __future__ import annotations

import numpy as np

from .. import _roots, _xp


class GammaRows:
    """Parameter rows of the gamma register or of no multiplication.

    Parameters
    ----------
    E : ndarray, shape (P,)
        Photoelectrons per row (e⁻).
    scale : ndarray, shape (P,)
        ADU per electron: θ = g/φ (gamma) or 1/φ (Poisson–normal).
    pn : ndarray of bool, shape (P,)
        Rows without multiplication.
    """

    names = ("photoelectrons", "scale")
    #: FFT round-off is ~1e-16 of the peak: above 1e-7 of it the relative error is < 1e-9.
    trusted = 1e-7

    def __init__(self, E, scale, pn):
        self.E, self.scale, self.pn = E, scale, pn

    def take(self, idx):
        return GammaRows(self.E[idx], self.scale[idx], self.pn[idx])

    def cgf(self, s, order=0, names=()):
        """``E·(M(s) − 1)`` (P, M) and its derivatives by E and the scale."""
        xp = _xp.namespace(s)
        E, scale, pn = _xp.like(s, self.E, self.scale, self.pn)
        sa = s * scale[:, None]
        pn_ = pn[:, None]
        Ec = E[:, None]
        # M(s) − 1 without cancellation at small s (each branch only where rows need it:
        # a camera without a register has Poisson–normal rows alone)
        every_pn, no_pn = bool(xp.all(pn)), not bool(xp.any(pn))
        if every_pn:
            v = _xp.expm1(xp, sa)
        elif no_pn:
            v = sa / (1.0 - sa)
        else:
            v = xp.where(pn_, _xp.expm1(xp, sa), sa / (1.0 - sa))
        if order == 0:
            return Ec * v, {}, {}
        m = 1.0 + v  # e^{sa}, or 1/(1 − sa)
        dm = s * m if every_pn else xp.where(pn_, s * m, s * m * m)  # dM/dscale
        first = {"photoelectrons": v, "scale": Ec * dm}
        if order == 1:
            return Ec * v, first, {}
        d2m = s * s * m if every_pn else xp.where(pn_, s * s * m, 2.0 * s * s * m * m * m)
        second = {("photoelectrons", "scale"): dm, ("scale", "scale"): Ec * d2m}
        return Ec * v, first, second

    def tilted(self, t):
        """The exponentially tilted distribution ``f(y) e^{ty − K(t)}`` is again one of
        the family: photoelectron mean E·M(t), scale θ/(1 − tθ) (PN: unchanged)."""
        ta = t * self.scale
        E_t = np.where(self.pn, self.E * np.exp(ta), self.E / (1.0 - ta))
        scale_t = np.where(self.pn, self.scale, self.scale / (1.0 - ta))
        return E_t, scale_t

    def real(self, t):
        """``K_X``, ``K_X'``, ``K_X''`` at real t (PGN requires tθ < 1), and the tilted
        photoelectron mean and scale."""
        ta = t * self.scale
        Ke = self.E * np.where(self.pn, np.expm1(ta), ta / (1.0 - ta))
        E_t, scale_t = self.tilted(t)
        d2 = np.where(self.pn, E_t * scale_t**2, 2.0 * E_t * scale_t**2)
        return Ke, E_t * scale_t, d2, E_t, scale_t

    def band(self, E_t, theta_t, sigma, n, level=80.0):
        """Highest rfft bin m beyond which |Φ(2πm/n)| < e^-level, in closed form.

        −ln|Φ(ω)| is at least B(ω) = σ²ω²/2 + E·ω²θ²/(1 + ω²θ²) for the PGN, and at least
        σ²ω²/2 + 2Eψ²ω²/π² for the PN while ωψ ≤ π (1 − cos x ≥ 2x²/π² there). B is
        increasing, so the ω_c solving B(ω_c) = level bounds the band; for the PGN it is
        the root of a quadratic in ω². Beyond ωψ = π the PN's Poisson factor revives at
        every ωψ = 2πk (its photoelectron comb), under the Gaussian factor alone: the band
        reaches past the last revival above e^-level (:func:`band_limit`).
        """
        return int(band_limit(E_t, theta_t, sigma, self.pn, n, level).max())

    def saddlepoint(self, k, S0, sigma):
        """Tilt t with K'(t) = k (the tilted mean at count k), by bisection."""
        E, scale, pn = self.E, self.scale, self.pn

        def dcgf(t):
            ta = t * scale
            with np.errstate(over="ignore", invalid="ignore"):
                growth = np.where(pn, np.exp(ta), 1.0 / (1.0 - ta) ** 2)
                return S0 + sigma**2 * t + E * scale * growth

        t_lo = np.minimum(0.0, (k - S0 - E * scale) / sigma**2)
        t_hi = np.maximum(0.0, (k - S0) / sigma**2)
        t_hi = np.where(pn, t_hi, np.minimum(t_hi, (1.0 - 1e-12) / scale))
        t_lo, t_hi = _roots.bisect(lambda t: dcgf(t) > k, t_lo, t_hi, 100)
        return 0.5 * (t_lo + t_hi)

    def direct_tail(self, sigma):
        """PGN rows whose single-electron scale exceeds the read noise: their exponential
        tail would need enormous tilted windows; quadrature is exact there."""
        return ~self.pn & (self.scale > sigma)

    def tail(self, k, S0, sigma, grad=False):
        """log f(k) by quadrature (:func:`quadrature_logpdf`), one row per query."""
        return quadrature_logpdf(k, self.E, self.scale, S0, sigma, grad)


def band_limit(E, scale, sigma, pn, n, level=80.0):
    """Highest rfft bin per row (:meth:`GammaRows.band`), for length-``n`` windows."""
    s2 = 0.5 * sigma**2
    t2 = scale**2
    # PGN: s2·u + E·t2·u/(1 + t2·u) = level, u = ω²  →  a u² + b u − level = 0
    a = s2 * t2
    b = s2 + E * t2 - level * t2
    with np.errstate(divide="ignore", invalid="ignore"):
        u_pgn = np.where(a > 0, (-b + np.sqrt(b * b + 4.0 * a * level)) / (2.0 * a), level / s2)
        u_pn = level / (s2 + 2.0 * E * t2 / np.pi**2)
    w_pn = np.sqrt(u_pn)
    # Around the PN's revival k (ωψ = 2πk, its comb) −ln|Φ| ≥ σ²ω²/2 + 2Eψ²(ω − ω_k)²/π²,
    # at least c·ω_k² (c = ab/(a + b) of the two quadratics' a and b): revivals up to the
    # last with c·ω_k² < level are in the band, each to where its right flank's bound
    # (σ²ω_k²/2 + 2Eψ²δ²/π², δ = ω − ω_k) reaches the level; never beyond the Gaussian
    # factor's own bound. Without this, a comb resolved at a bright level (a qCMOS, σ > 3
    # ADU) lost its revivals, and a pixel's likelihood depended on the pixels beside it
    # (the band is the widest row's).
    gaussian = np.sqrt(level / s2)
    a, b = s2, 2.0 * E * t2 / np.pi**2
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        period = 2.0 * np.pi / scale
        last = np.floor(np.sqrt(level * (a + b) / (a * b)) / period)
        w_k = last * period
        w_rev = w_k + np.sqrt(np.maximum(level - a * w_k**2, 0.0) / b)
    w_rev = np.where(last >= 1, np.fmin(w_rev, gaussian), 0.0)
    # beyond ωψ = π, the Gaussian bound only
    w_pn = np.where(w_pn * scale <= np.pi, np.maximum(w_pn, w_rev), gaussian)
    w = np.where(pn, w_pn, np.sqrt(u_pgn))
    m = np.ceil(w * n / (2.0 * np.pi)).astype(np.int64) + 2
    return np.where(w >= np.pi, n // 2 + 1, np.minimum(m, n // 2 + 1))


def quadrature_logpdf(k, E, theta, S0, sigma, grad=False):
    """log f(k) of the PGN by Gauss–Legendre quadrature of its Bessel form (docs/methods.md).

    ``f(k) = e^{-E} N(k; S0, σ) + ∫ q_c(u) N(k; S0 + u, σ) du`` with the Poisson–gamma
    density ``q_c`` evaluated through ``i1e`` (never overflows). The integrand is positive,
    so the result has full *relative* precision far into the tails, where an FFT window
    cannot reach: used for the exponential tail of few-electron PGN (θ > σ). Arrays of
    shape (Q,), one parameter set per query. With ``grad``, also the derivatives of
    log f by the native parameters (E, θ, S0, σ).
    """
    from scipy import special

    nodes, weights = np.polynomial.legendre.leggauss(16)
    x = (k - S0)[:, None]
    width = 2.0 * np.minimum(sigma, theta)
    lo = np.maximum(0.0, k - S0 - 12.0 * sigma)
    hi = np.maximum(lo, k - S0 + 12.0 * sigma)
    n_panel = np.clip(np.ceil((hi - lo) / width), 1, 256).astype(int)
    M = int(n_panel.max())
    panel = np.arange(M)[None, :]
    h = ((hi - lo) / n_panel)[:, None]
    a = lo[:, None] + panel * h
    u = (a[:, :, None] + 0.5 * h[:, :, None] * (nodes + 1.0)).reshape(k.size, -1)
    w = (0.5 * h[:, :, None] * weights * (panel < n_panel[:, None])[:, :, None]).reshape(k.size, -1)
    Ec, tc, sc = E[:, None], theta[:, None], sigma[:, None]
    u = np.maximum(u, 1e-300)
    z = 2.0 * np.sqrt(Ec * u / tc)
    log_q = (
        0.5 * np.log(Ec / (tc * u)) - (np.sqrt(u / tc) - np.sqrt(Ec)) ** 2 + np.log(special.i1e(z))
    )
    log_n = -0.5 * ((x - u) / sc) ** 2 - np.log(np.sqrt(2.0 * np.pi) * sc)
    with np.errstate(divide="ignore"):
        log_terms = log_q + log_n + np.log(w)
    atom = -E - 0.5 * ((k - S0) / sigma) ** 2 - np.log(np.sqrt(2.0 * np.pi) * sigma)
    stacked = np.concatenate([log_terms, atom[:, None]], axis=1)
    top = stacked.max(axis=1, keepdims=True)
    weight = np.exp(stacked - top)
    total = weight.sum(axis=1)
    logf = top[:, 0] + np.log(total)
    if not grad:
        return logf, {}
    # ∂ ln q_c/∂E = −1 + √(u/(θE))·R(z), ∂ ln q_c/∂θ = (u/θ − (z/2)R(z))/θ, R = I0/I1.
    R = special.i0e(z) / special.i1e(z)
    dE = -1.0 + np.sqrt(u / (tc * Ec)) * R
    dT = (u / tc - 0.5 * z * R) / tc
    share = weight[:, :-1] / total[:, None]
    atom_share = weight[:, -1] / total
    # Offset and read noise act through the Gaussian factor, atom (u = 0) included.
    resid = np.concatenate([x - u, x], axis=1)
    all_share = weight / total[:, None]
    return logf, {
        "photoelectrons": np.sum(share * dE, axis=1) - atom_share,
        "scale": np.sum(share * dT, axis=1),
        "offset": np.sum(all_share * resid, axis=1) / sigma**2,
        "read_noise": (np.sum(all_share * resid**2, axis=1) / sigma**2 - 1.0) / sigma,
    }


class Gamma:
    """The paper's register: the output of n electrons is Gamma(n, g), F² = 2 at every
    gain; at g = 1 no multiplication (Poisson–normal). Its fit coordinates are
    (ln E, ln(g/φ)) — (ln E, ln(1/φ)) without multiplication — since g and φ enter only
    as their ratio."""

    name = "gamma"
    uses_stages = False
    #: Extra public parameters of the likelihood (none).
    parameters = ()
    description = "gamma (the paper's approximation)"
    misfit_hint = (
        "the gamma model of the EM register misfits an exact register's low "
        "gains, whose estimates are then doubtful: calibrate again with the "
        'cascade model (--em-model cascade, em_model = "cascade")'
    )

    def __init__(self, stages=None):
        pass

    def __eq__(self, other):
        return type(other) is Gamma

    def __hash__(self):
        return hash(Gamma)

    def register_for(self, poisson_normal):
        """The register of rows with (True) or without multiplication: this one, both."""
        return self

    @staticmethod
    def excess_noise_factor(g):
        return np.where(g == 1, 1.0, 2.0)

    @staticmethod
    def sample(electrons, g, rng, **options):
        """Output electrons (float) of ``electrons`` entering the register at gain g."""
        from .cascade_sampling import sample_gamma

        return sample_gamma(electrons, g, rng)

    @staticmethod
    def single_electron_moments(g):
        """E[X^k], k = 1…4, of the output X of one electron: ``k!·g^k`` (exponential)."""
        g = float(g)
        return np.array([g, 2.0 * g**2, 6.0 * g**3, 24.0 * g**4])

    @staticmethod
    def gain_from_gain_f2(y):
        """g with ``g·F² = y`` (F² = 2), and the slope ``d(g F²)/dg`` = 2."""
        y = np.asarray(y, dtype=float)
        return y / 2.0, np.full(y.shape, 2.0)

    @staticmethod
    def rows(E, g, phi, cic=None):
        pn = g == 1.0
        return GammaRows(E, np.where(pn, 1.0 / phi, g / phi), pn)

    @staticmethod
    def coordinates(poisson_normal):
        """d(fit coordinates)/d(ln E, ln g, ln φ) (rows: the coordinates)."""
        return _PN_COORDS if poisson_normal else _GAMMA_COORDS

    @staticmethod
    def rows_at(values, poisson_normal):
        """Rows from the exponentiated fit coordinates (E, scale)."""
        E, scale = values
        return GammaRows(E, scale, np.full(E.shape, bool(poisson_normal)))

    @staticmethod
    def public_gradients(d, g, phi):
        """∂ log p by ``em_gain`` (NaN at g = 1) and ``e_per_adu`` from the native ones."""
        pn = g == 1.0
        return {
            "em_gain": np.where(pn, np.nan, d["scale"] / phi),
            "e_per_adu": np.where(pn, -d["scale"] / phi**2, -d["scale"] * g / phi**2),
        }


_GAMMA_COORDS = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, -1.0]])  # ln E, ln(g/φ)
_PN_COORDS = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # ln E, ln(1/φ)
