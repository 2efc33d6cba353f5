"""A start for φ that cannot fall into an alias of a resolved photoelectron comb.

Without multiplication a pixel's counts are a comb: peaks 1/φ ADU apart (one per
photoelectron), each as wide as the read noise. Where the read noise in electrons,
σφ, is small enough for the comb to show (an ORCA-Quest's 0.27 e⁻; an sCMOS's quietest
pixels), the likelihood over φ is not one hill: moving φ by a fraction 1/k moves the k-th
peak onto the (k±1)-th, and near those fractions of the brightest level's photoelectrons
it has local maxima, each a few hundredths of a nat to hundreds of nats below the true
one. A start from the moments (the photon transfer through the origin, a few per cent
off with a few thousand frames) can sit in any of them, and Newton's method converges
where it starts.

:func:`profile_start` evaluates the likelihood on a grid of φ around the moment start,
finer than the aliases' spacing and wider than the moments' error, each level's
photoelectrons following φ through its mean (``E = φ·(⟨S⟩ − S0)``, where the likelihood
of E is highest for a given φ), and starts each such pixel at the grid's best point.
"""

from __future__ import annotations

import numpy as np

from ..model import adc
from . import engine

#: A pixel's comb shows where the transform's revival at ω = 2πφ, exp(−2π²(σφ)²) times
#: the rounding's |sinc(πφ)|, exceeds this fraction of 1/√n (its noise in n frames).
VISIBLE = 0.05
#: Grid points per alias spacing (1/E of the brightest level, relative), and at most.
PER_ALIAS = 4
MAX_POINTS = 257


def revival(phi, sigma, rounding):
    """|Φ(2πφ)| of a Poisson–normal count, relative to its value at 0: the comb's
    visibility (φ e⁻/ADU, σ ADU)."""
    sinc = np.where(rounding, np.abs(np.sinc(phi)), 1.0)  # np.sinc(x) = sin(πx)/(πx)
    return np.exp(-2.0 * np.pi**2 * (sigma * phi) ** 2) * sinc


def _revival(block, phi):
    return revival(phi, block.read_noise, adc.rounds(block.poisson_normal, block.read_noise))


def visible(blocks, phi):
    """Pixels (P,) whose comb shows in some level's data at φ (e⁻/ADU)."""
    out = np.zeros(phi.shape, dtype=bool)
    for b in blocks:
        out |= b.poisson_normal & (_revival(b, phi) * np.sqrt(np.maximum(b.n, 1)) > VISIBLE)
    return out


def profile_start(layout, blocks, x0, read_out_variance, phi_col=0, photoelectron_cols=None):
    """``x0`` with φ (and the levels' E) moved to the best point of a grid where the
    comb shows (module docstring); elsewhere unchanged.

    Parameters
    ----------
    layout : emccdcal.fit.engine.Layout
        An intensity series' (``x = [ln φ, ln E_1 … ln E_A]``).
    blocks : list of AcquisitionBlock
    x0 : ndarray, shape (P, F)
        Moment start.
    read_out_variance : callable
        The read-out's variance (ADU²) of a block (:func:`emccdcal.fit.layouts.read_out_variance`).
    """
    cols = np.arange(1, 1 + len(blocks)) if photoelectron_cols is None else photoelectron_cols
    phi0 = np.exp(x0[:, phi_col])
    live = np.flatnonzero(visible(blocks, phi0))
    if live.size == 0:
        return x0
    signal = np.stack([np.maximum(b.mean - b.offset, 1e-6) for b in blocks], axis=1)[live]
    # the moments' relative error of φ: that of the summed excess variance
    excess = np.stack([np.maximum(b.var - read_out_variance(b), 1e-6) for b in blocks], 1)
    excess = excess[live]
    n = np.stack([np.maximum(b.n, 2) for b in blocks], 1)[live]
    var = np.stack([b.var for b in blocks], 1)[live]
    rel = np.sqrt(np.sum(2.0 * var**2 / (n - 1), axis=1)) / excess.sum(axis=1)
    half = np.clip(5.0 * rel, 0.02, 0.5)
    E_max = (signal * phi0[live, None]).max(axis=1)
    step = np.maximum(1.0 / (PER_ALIAS * np.maximum(E_max, 1.0)), 2.0 * half / (MAX_POINTS - 1))
    points = np.minimum(np.ceil(2.0 * half / step).astype(int) + 1, MAX_POINTS)
    G = int(points.max())
    offsets = (np.arange(G)[None, :] - (points[:, None] - 1) / 2.0) * step[:, None]
    offsets = np.where(np.arange(G)[None, :] < points[:, None], offsets, 0.0)
    rows = np.repeat(live, G)
    ln_phi = np.log(phi0[live])[:, None] + offsets  # (L, G)
    x = np.repeat(x0[live], G, axis=0)
    x[:, phi_col] = ln_phi.ravel()
    x[:, cols] = np.log(signal[:, None, :] * np.exp(ln_phi)[..., None]).reshape(-1, len(cols))
    value = np.empty(rows.size)
    for chunk in np.array_split(np.arange(rows.size), max(1, rows.size // 4096)):
        sub = rows[chunk]
        value[chunk] = engine.objective(layout.subset(sub), [b.take(sub) for b in blocks], x[chunk])
    value = np.where(np.isfinite(value), value, -np.inf).reshape(live.size, G)
    best = np.argmax(value, axis=1)
    out = x0.copy()
    out[live] = x.reshape(live.size, G, -1)[np.arange(live.size), best]
    return out


def moment_se(blocks, phi, read_out_variance):
    """The relative SE of φ (P,) from the moments alone: the photon transfer through the
    origin, whose excess variances each have the variance 2·Var²/(n − 1)."""
    excess = np.stack([np.maximum(b.var - read_out_variance(b), 1e-6) for b in blocks], 1)
    n = np.stack([np.maximum(b.n, 2) for b in blocks], 1)
    var = np.stack([b.var for b in blocks], 1)
    return np.sqrt(np.sum(2.0 * var**2 / (n - 1), axis=1)) / excess.sum(axis=1)


#: A comb whose revival is below this cannot ripple the likelihood of any data set
#: (n·r² nats: 1e-11 in 1e5 frames); an EMCCD's 1× comb is far below it.
RIPPLES = 1e-8
#: The observed information of ln φ is checked against the profile likelihood where it
#: claims at least this factor less variance than the moments' (the comb's share).
CHECK_BELOW = 0.8


def ripple_covariance(layout, blocks, fit, read_out_variance, level=0.95):
    """The covariance of an intensity series' ``x`` (P, F, F), with ln φ's variance at
    least what its profile likelihood says, where a comb is in the model.

    A barely visible comb (an sCMOS pixel of ~0.5–0.8 e⁻ read noise) puts ripples on the
    likelihood over φ, one per 1/E of the brightest level's photoelectrons, hundredths of
    a nat high: the maximum sits on one of them, and the observed information there is the
    ripple's curvature, up to 40 times the information the data hold (the profile
    likelihood's width, which the ripples hardly change). Where the information of ln φ
    claims more than the moments' (``CHECK_BELOW``), its profile-likelihood interval
    (:func:`emccdcal.fit.profile.profile_bounds`) is found, and where half its width over
    the normal quantile exceeds the SE, the variance grows to it along the direction in
    which the other parameters move with φ (each E with it), as a given φ's error would.
    Where the comb is resolved, the two agree and nothing changes.
    """
    from scipy import stats

    from .profile import profile_bounds

    cov = fit.cov
    se = np.sqrt(cov[:, 0, 0])
    phi = np.exp(fit.x[:, 0])
    comb = np.any([b.poisson_normal & (_revival(b, phi) > RIPPLES) for b in blocks], axis=0)
    check = comb & np.isfinite(se) & (se < CHECK_BELOW * moment_se(blocks, phi, read_out_variance))
    idx = np.flatnonzero(check)
    if idx.size == 0:
        return cov
    sub = engine.FitResult(
        fit.x[idx], cov[idx], fit.loglik[idx], fit.converged[idx], fit.iterations[idx],
        fit.n_floored[idx], objective=fit.objective[idx],
    )  # fmt: skip
    lower, upper = profile_bounds(
        layout.subset(idx), [b.take(idx) for b in blocks], sub, 0, level=level
    )
    half = 0.5 * (upper - lower) / stats.norm.ppf(0.5 + level / 2)
    grow = np.where(np.isfinite(half), half**2 - cov[idx, 0, 0], 0.0)
    grow = np.maximum(grow, 0.0)
    b = cov[idx, :, 0] / cov[idx, 0, 0][:, None]  # how x moves with ln φ
    out = cov.copy()
    out[idx] += grow[:, None, None] * b[:, :, None] * b[:, None, :]
    return out
