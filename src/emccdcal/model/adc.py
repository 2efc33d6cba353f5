"""The ADC's rounding of each value to an integer, where the read noise is small.

A camera reports ``round(S0 + X + ε)``, not the analog value: the probability of count k
is the analog density integrated over ``[k − ½, k + ½)``. That is the density of
``S0 + X + ε + U`` at k, with ``U`` uniform on ``(−½, ½)`` and independent, so the
rounding is one more term of the count's cumulant generating function,

    K_U(s) = ln( sinh(s/2) / (s/2) ),

whose transform vanishes at every 2πj, j ≠ 0: the probabilities of the integers sum to
one without the normalising sum a density sampled at the integers needs.

Where the read noise σ is large the two models differ only by the uniform's 1/12 ADU² of
variance (Sheppard's correction), which a read-noise map measured as the dark counts'
SD already holds: there the density at the integers with that SD is the model (the
paper's, and every EMCCD number of this package). Below :data:`ROUNDING_BELOW` ADU, where
a photoelectron comb or the integers themselves begin to show, Poisson–normal rows use
the rounding, and their ``read_noise`` is the analog σ *before* rounding, as a fit of
the dark frames' counts gives it (:func:`fit_rounded_normal`), not their SD.

Either side of the switch the two models agree far below the statistical error: at
σ = 2 ADU their excess kurtosis differs by 1/(120 σ⁴) = 5e-4 (a Kullback–Leibler
divergence of 5e-4 nats in 1e5 frames) and the sampled density's aliases are e^-79; at
1 ADU the divergence would be 0.14 nats in 1e5 frames, and below it the integers and the
comb show (``tests/test_cmos.py`` checks the estimates at the switch).
"""

from __future__ import annotations

import numpy as np

from .. import _xp
from .._util import weighted_gram

__all__ = [
    "ROUNDING_BELOW",
    "rounds",
    "count_variance",
    "cgf",
    "real_cgf",
    "rounded_normal",
    "fit_rounded_normal",
]

#: Read noise (ADU) below which a Poisson–normal row's count is modelled with the ADC's
#: rounding (module docstring).
ROUNDING_BELOW = 2.0


def rounds(pn, sigma):
    """Rows whose model includes the rounding: Poisson–normal rows (``pn``) with read
    noise ``sigma`` (ADU) below :data:`ROUNDING_BELOW`."""
    return np.asarray(pn, dtype=bool) & (np.asarray(sigma) < ROUNDING_BELOW)


def count_variance(read_noise, poisson_normal):
    """The variance (ADU²) the read-out adds to the counts, as a dark's counts show it:
    σ², and the rounding's 1/12 where the model holds σ as the analog read noise (what
    the localization tools' variance maps hold)."""
    read_noise = np.asarray(read_noise, dtype=float)
    return read_noise**2 + rounds(poisson_normal, read_noise) / 12.0


def cgf(s):
    """``K_U(s)`` at complex ``s`` (any array namespace): ``ln(sinh(s/2)/(s/2))``.

    Written through ``w = ±s/2`` with ``Re w ≥ 0`` (the function is even), as
    ``w − ln 2 + ln(−expm1(−2w)) − ln w``, which neither overflows for a large tilt nor
    loses digits near 0; at 2πj (j ≠ 0) the transform is zero to round-off, and 0 is 0.
    """
    xp = _xp.namespace(s)
    w = 0.5 * xp.where(xp.real(s) < 0, -s, s)
    zero = w == 0
    w = xp.where(zero, 1.0 + 0j, w)
    value = w - np.log(2.0) + xp.log(-xp.expm1(-2.0 * w)) - xp.log(w)
    return xp.where(zero, 0.0 + 0j, value)


def real_cgf(t):
    """``K_U``, ``K_U'`` and ``K_U''`` at real tilts ``t`` (NumPy)."""
    t = np.asarray(t, dtype=float)
    a = np.abs(0.5 * t)
    small = a < 1e-3
    safe = np.where(small, 1.0, a)
    K = np.where(small, t * t / 24.0, safe + np.log(-np.expm1(-2.0 * safe)) - np.log(2.0 * safe))
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        coth = 1.0 / np.tanh(np.where(small, 1.0, 0.5 * t))
        d1 = np.where(small, t / 12.0, 0.5 * coth - 1.0 / np.where(small, 1.0, t))
        inv_sinh2 = np.where(a > 300.0, 0.0, 1.0 / np.sinh(np.where(small, 1.0, a)) ** 2)
        d2 = np.where(small, 1.0 / 12.0, 1.0 / np.where(small, 1.0, t) ** 2 - 0.25 * inv_sinh2)
    return K, d1, d2


def rounded_normal(k, mu, sigma, derivs=False):
    """P(round(μ + σz) = k), z ~ N(0, 1), and its derivatives by μ and σ.

    Parameters
    ----------
    k : ndarray of float
        Integer counts (ADU).
    mu, sigma : ndarray
        Offset (ADU) and analog read noise (ADU), broadcast against ``k``.

    Returns
    -------
    p : ndarray
    d_mu, d_sigma : ndarray (with ``derivs``)
    """
    from scipy import special

    a = (k - 0.5 - mu) / sigma
    b = (k + 0.5 - mu) / sigma
    # the smaller tail of each side: no cancellation far from μ
    upper = a > 0
    p = np.where(upper, special.ndtr(-a) - special.ndtr(-b), special.ndtr(b) - special.ndtr(a))
    if not derivs:
        return p
    pa, pb = np.exp(-0.5 * a * a), np.exp(-0.5 * b * b)
    norm = 1.0 / (np.sqrt(2.0 * np.pi) * sigma)
    return p, (pa - pb) * norm, (a * pa - b * pb) * norm


def fit_rounded_normal(values, counts, mu0, sigma0, max_iter=60):
    """Per-pixel maximum likelihood of (μ, σ) from histograms of rounded normal counts.

    Parameters
    ----------
    values, counts : ndarray, shape (P, K)
        Each pixel's count values (ADU) and frames at each (0 for padding).
    mu0, sigma0 : ndarray, shape (P,)
        Starting values: the counts' mean and SD.

    Returns
    -------
    mu, sigma : ndarray, shape (P,)
        Offset and analog read noise (ADU).
    converged : ndarray of bool, shape (P,)
        False also where a pixel's counts take fewer than three values: no width is
        best there (the likelihood grows as σ → 0), and the start is returned.
    """
    from .._optimize import maximize

    values = np.asarray(values, dtype=float)
    counts = np.asarray(counts, dtype=float)
    start = np.column_stack([mu0, np.log(np.maximum(sigma0**2 - 1.0 / 12.0, 0.01) ** 0.5)])
    # fewer than three values: the likelihood grows as σ → 0, no width is best
    fitted = np.flatnonzero(np.count_nonzero(counts > 0, axis=1) >= 3)
    values, counts = values[fitted], counts[fitted]

    def evaluate(rows, x):
        k, c = values[rows], counts[rows]
        mu, sigma = x[:, :1], np.exp(x[:, 1:])
        p, dmu, dsig = rounded_normal(k, mu, sigma, derivs=True)
        p = np.maximum(p, 1e-300)
        score = np.stack([dmu / p, dsig * sigma / p], axis=-1)  # by (μ, ln σ)
        ll = np.sum(c * np.log(p), axis=1)
        grad = np.einsum("pk,pki->pi", c, score)
        info = weighted_gram(c, score)
        return ll, grad, info

    inf = np.full(2, np.inf)
    opt = maximize(
        evaluate, start[fitted], lower=-inf, upper=inf, tol=1e-10, max_iter=max_iter,
        accept_rtol=1e-12,
    )  # fmt: skip
    x, converged = start.copy(), np.zeros(len(start), dtype=bool)
    x[fitted], converged[fitted] = opt.x, opt.done | opt.stuck
    return x[:, 0], np.exp(x[:, 1]), converged


def information(mu, sigma):
    """Expected Fisher information of (μ, σ) per rounded-normal count (P, 2, 2), ADU⁻²,
    by summing over the counts within 12 σ + 1 of μ."""
    mu, sigma = np.asarray(mu, dtype=float), np.asarray(sigma, dtype=float)
    half = int(np.ceil(12.0 * float(np.max(sigma)) + 2.0))
    k = np.floor(mu)[:, None] + np.arange(-half, half + 1)[None, :]
    p, dmu, dsig = rounded_normal(k, mu[:, None], sigma[:, None], derivs=True)
    live = p > 1e-300
    p = np.where(live, p, 1.0)
    g = np.stack([dmu, dsig], axis=-1) * (live / p)[..., None]
    return weighted_gram(p, g)
