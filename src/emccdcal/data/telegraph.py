"""Random-telegraph pixels: a dark whose counts are two normals, not one.

A random-telegraph (RTS) pixel's offset jumps between two (or more) levels as a charge
trap in its amplifier fills and empties (common on sCMOS sensors): its dark counts are a
mixture of normals of one width, and its offset and read noise, as one normal's, are
wrong for every frame. Each pixel is tested here: one normal against a mixture of two of
one width, each rounded to the integers as the ADC rounds (a component's probability of
count k its mass within [k − ½, k + ½): :func:`emccdcal.model.adc.rounded_normal`), by
the likelihood ratio on the pixel's histogram: one normal fitted as the dark's maps are
(:func:`emccdcal.model.adc.fit_rounded_normal`), two by expectation–maximisation for
grouped data (each bin's conditional moments of the normal: Dempster, Laird & Rubin
1977). The ratio's
distribution without a second state is not χ² (the mixture's weight sits on its
boundary), but with the rounding modelled a normal's location and scale hardly move it
(its 99 % quantile 4.6–7.7 from 0.3 to 4 ADU of read noise; a model of densities at the
integers put it at 25 to 1900 below 1 ADU, which left a fifth of the one-normal pixels
of a 0.3 e⁻ sCMOS flagged): its quantile is found by simulating normal darks of the same
number of frames and a read noise like the pixels' (seeded: the same data give the same
flags), and a pixel is flagged where its ratio exceeds the quantile of the stated
false-alarm rate.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from ..model import adc
from . import stats

__all__ = ["TelegraphTest", "telegraph_pixels", "FALSE_ALARM"]

#: Default fraction of one-normal pixels flagged by chance.
FALSE_ALARM = 0.01
#: Null simulations per read-noise value (the quantile's own error: ~1e-3 at 1 %).
_NULL_PIXELS = 2000
#: Pixels tested at a time (the fits hold about 20 arrays of pixels × 2 × counts).
_BLOCK = 4096
#: Read noises (ADU) at which the null quantile is simulated; between, interpolated.
_NULL_SIGMAS = (0.3, 0.5, 0.8, 1.2, 2.0, 4.0)


@dataclass(frozen=True)
class TelegraphTest:
    """The test's outcome per pixel (flattened C order).

    Attributes
    ----------
    flagged : ndarray of bool, shape (P,)
        Pixels whose dark is two (or more) offset states.
    statistic : ndarray, shape (P,)
        Twice the log-likelihood ratio of two normals to one (nats × 2).
    step : ndarray, shape (P,)
        Distance between the two states' offsets, ADU (NaN where not flagged).
    threshold : ndarray, shape (P,)
        The statistic's null quantile at each pixel's read noise.
    false_alarm : float
    """

    flagged: np.ndarray
    statistic: np.ndarray
    step: np.ndarray
    threshold: np.ndarray
    false_alarm: float


def _binned(values, means, sd):
    """Each rounded normal's probability of every integer ``values`` (P, K)
    (:func:`emccdcal.model.adc.rounded_normal`), its mean and its second moment about
    its centre within each integer's bin [k − ½, k + ½), for components of ``means``
    (P, J) and one analog width ``sd`` (P,): (P, J, K) each. The truncated normal's
    moments are the probability's derivatives: E[x − m] = s²·∂p/∂m / p and
    E[(x − m)²] = s²·(1 + s·∂p/∂s / p)."""
    s = sd[:, None, None]
    offset = values[:, None, :] - means[:, :, None]
    mass, d_mean, d_sd = adc.rounded_normal(values[:, None, :], means[:, :, None], s, derivs=True)
    tiny = ~(mass > 1e-12)  # far from a component: the bin's middle
    with np.errstate(invalid="ignore", divide="ignore"):
        first = np.where(tiny, offset, s * s * d_mean / mass)
        second = np.where(tiny, offset**2, s * s * (1.0 + s * d_sd / mass))
    return mass, means[:, :, None] + first, second


def _fit(values, counts, means, weights, sd, iterations, tol=1e-3):
    """Expectation–maximisation of a mixture of rounded normals of one width over each
    pixel's histogram (P, K), each pixel until its log-likelihood gains under ``tol``
    nats in a step: its log-likelihood (P,), means (P, J) and width (P,)."""
    means, weights, sd = means.copy(), weights.copy(), sd.copy()
    loglik = np.full(sd.shape, -np.inf)
    live = np.arange(sd.size)
    for _ in range(iterations + 1):
        v, c, m, w, s = values[live], counts[live], means[live], weights[live], sd[live]
        mass, x1, x2 = _binned(v, m, s)
        joint = w[:, :, None] * mass
        total = np.maximum(joint.sum(axis=1, keepdims=True), 1e-300)
        now = (c * np.log(total[:, 0])).sum(axis=1)  # at the parameters before this step
        done = now - loglik[live] < tol
        loglik[live] = now
        if done.all():
            break
        live, v, c, m, joint, total, x1, x2 = (
            a[~done] for a in (live, v, c, m, joint, total, x1, x2)
        )
        r = c[:, None, :] * joint / total  # frames of each bin in each component
        nj = r.sum(axis=2)
        n = c.sum(axis=1)
        weights[live] = np.clip(nj / n[:, None], 1e-6, 1.0)
        new = (r * x1).sum(axis=2) / np.maximum(nj, 1e-12)
        # E[(x − m_new)²] from E[(x − m_old)²] and E[x] within each bin
        shift = (m - new)[:, :, None]
        within = x2 + 2.0 * shift * (x1 - m[:, :, None]) + shift**2
        sd[live] = np.sqrt(np.maximum((r * within).sum(axis=(1, 2)) / n, 1e-4))
        means[live] = new
    return loglik, means, sd


def _statistic(values, counts, iterations=60):
    """Twice the log-likelihood ratio of a two-state mixture to one rounded normal per
    pixel, and the states' distance (ADU), from histograms (P, K)."""
    counts = counts.astype(float)
    n = counts.sum(axis=1)
    mean = (counts * values).sum(axis=1) / n
    var = (counts * (values - mean[:, None]) ** 2).sum(axis=1) / n
    # one rounded normal: the maps' own maximum likelihood (emccdcal.model.adc)
    mu, sigma = adc.fit_rounded_normal(values, counts, mean, np.sqrt(var))[:2]
    ll0 = (
        counts * np.log(np.maximum(adc.rounded_normal(values, mu[:, None], sigma[:, None]), 1e-300))
    ).sum(1)
    # start: the halves below and above the mean
    low = values <= mean[:, None]
    w = np.clip((counts * low).sum(axis=1) / n, 0.05, 0.95)
    m1 = (counts * values * low).sum(axis=1) / np.maximum((counts * low).sum(axis=1), 1)
    m2 = (counts * values * ~low).sum(axis=1) / np.maximum((counts * ~low).sum(axis=1), 1)
    ll1, means, _ = _fit(
        values, counts, np.stack([m1, m2], 1), np.stack([w, 1.0 - w], 1),
        np.sqrt(np.maximum(var / 4.0, 0.01)), iterations,
    )  # fmt: skip
    # fewer than three values: one normal as narrow as they are fits them all (no test)
    statistic = np.where(np.count_nonzero(counts, axis=1) >= 3, 2.0 * (ll1 - ll0), 0.0)
    return np.maximum(statistic, 0.0), np.abs(means[:, 1] - means[:, 0])


@functools.lru_cache(maxsize=16)
def _null_quantiles(frames, false_alarm, seed) -> tuple:
    """The null quantile at each of :data:`_NULL_SIGMAS`, simulated from ``seed``: the
    same for the same arguments, so kept (a session's calibrations share their darks'
    frame count)."""
    rng = np.random.default_rng(seed)
    return tuple(_null_quantile(frames, s, false_alarm, rng) for s in _NULL_SIGMAS)


def _null_quantile(frames, sigma, false_alarm, rng):
    """The statistic's (1 − false_alarm) quantile for normal darks of ``frames`` frames
    and read noise ``sigma`` (ADU), simulated."""
    offset = 100.0 + rng.random(_NULL_PIXELS)
    counts = np.rint(offset + sigma * rng.standard_normal((frames, _NULL_PIXELS)))
    h = stats.histograms(counts.reshape(frames, 1, -1).astype(np.int64))
    return float(np.quantile(_statistic(h.values.astype(float), h.counts)[0], 1.0 - false_alarm))


def telegraph_pixels(stack, *, false_alarm=FALSE_ALARM, seed=0, adc_max=None) -> TelegraphTest:
    """Test every pixel of a 1× dark stack for two offset states (module docstring).

    Parameters
    ----------
    stack : array_like, shape (frames, rows, cols)
        Raw dark counts (ADU) at 1× (no multiplied events).
    false_alarm : float
        Fraction of one-normal pixels flagged by chance (default 1 %).
    seed : int
        Seed of the null simulation.
    adc_max : int, optional
        Counts at or above it are left out.

    Returns
    -------
    TelegraphTest

    Examples
    --------
    >>> rng = np.random.default_rng(1)
    >>> dark = np.rint(100 + 1.5 * rng.standard_normal((2000, 2, 2)))
    >>> dark[:, 0, 0] += 6 * (rng.random(2000) < 0.5)          # two offset states
    >>> telegraph_pixels(dark.astype(np.uint16)).flagged.tolist()
    [True, False, False, False]
    """
    h = stats.histograms(stack, adc_max=adc_max)
    values = h.values.astype(float)
    # in blocks of pixels: the fits' arrays are (pixels, states, counts) large
    parts = [
        _statistic(values[rows], h.counts[rows])
        for rows in np.array_split(np.arange(values.shape[0]), -(-values.shape[0] // _BLOCK))
    ]
    statistic, step = (np.concatenate(p) for p in zip(*parts))
    sigmas = np.array(_NULL_SIGMAS)
    quantiles = np.array(_null_quantiles(int(np.median(h.n)), float(false_alarm), seed))
    sd = np.maximum(np.sqrt(h.var), sigmas[0])  # below the grid: its first quantile
    threshold = np.interp(np.log(sd), np.log(sigmas), quantiles)
    flagged = statistic > threshold
    return TelegraphTest(
        flagged, statistic, np.where(flagged, step, np.nan), threshold, false_alarm
    )
