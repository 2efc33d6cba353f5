"""Random-telegraph pixels: a dark whose counts are two normals, not one.

A random-telegraph (RTS) pixel's offset jumps between two (or more) levels as a charge
trap in its amplifier fills and empties (common on sCMOS sensors): its dark counts are a
mixture of normals of one width, and its offset and read noise, as one normal's, are
wrong for every frame. Each pixel is tested here: one normal against a mixture of two of
one width, each rounded to the integers as the ADC rounds (a component's probability of
count k its mass within [k − ½, k + ½): :func:`emccdcal.model.adc.rounded_normal`), by
the likelihood ratio on the pixel's histogram: one normal fitted as the dark's maps are
(:func:`emccdcal.model.adc.fit_rounded_normal`), two by the same damped Newton steps
(:func:`emccdcal._optimize.maximize`; each state's weight kept within 5–95 %: a state
fitted to a few counts of a normal's tail would make one-normal pixels' ratios large,
and a rare state far off still gains at the bound). The ratio's distribution without a
second state is not χ² (the mixture's weight sits on its boundary), and hardly depends
on the read noise or the frames once the rounding is modelled (its 99 % quantile 8.4–9.8
from 0.8 to 4 ADU and 100 to 50 000 frames, 0.8–5.9 at 0.3 ADU; a model of densities at
the integers put it at 25 to 1900 below 1 ADU, which left a fifth of the one-normal
pixels of a 0.3 e⁻ sCMOS flagged): its quantile is that of normal darks of the same
number of frames and a read noise like the pixels', from a table simulated once at the
default rate (:mod:`emccdcal.data._telegraph_null`, written by
``benchmarks/telegraph_null_table.py``), else simulated when asked (seeded: the same
data give the same flags), and a pixel is flagged where its ratio exceeds the quantile
of the stated false-alarm rate.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from ..model import adc
from . import _telegraph_null as table
from . import stats

__all__ = ["TelegraphTest", "telegraph_pixels", "FALSE_ALARM"]

#: Default fraction of one-normal pixels flagged by chance.
FALSE_ALARM = 0.01
#: Null simulations per read-noise value where the table does not serve (the rate's
#: own error: ~2e-3 at 1 %).
_NULL_PIXELS = 2000
#: Pixels tested at a time (a fit holds about 20 arrays of pixels × counts).
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


def _fit_two(values, counts, start, iterations):
    """Maximum likelihood of a mixture of two rounded normals of one width over each
    pixel's histogram (P, K), by the house's damped Newton steps on (m₁, m₂, ln s,
    logit w) from ``start`` (P, 4), each pixel until a step promises under 1e-3 nats:
    its log-likelihood (P,) and parameters (P, 4)."""
    from .._optimize import maximize
    from .._util import weighted_gram

    def evaluate(rows, x):
        k, c = values[rows], counts[rows]
        sd, w = np.exp(x[:, 2:3]), 1.0 / (1.0 + np.exp(-x[:, 3:4]))
        p1, d_mean1, d_sd1 = adc.rounded_normal(k, x[:, :1], sd, derivs=True)
        p2, d_mean2, d_sd2 = adc.rounded_normal(k, x[:, 1:2], sd, derivs=True)
        p = np.maximum(w * p1 + (1.0 - w) * p2, 1e-300)
        score = np.stack(
            [
                w * d_mean1 / p,
                (1.0 - w) * d_mean2 / p,
                sd * (w * d_sd1 + (1.0 - w) * d_sd2) / p,
                w * (1.0 - w) * (p1 - p2) / p,
            ],
            axis=-1,
        )
        grad = np.einsum("pk,pki->pi", c, score)
        return (c * np.log(p)).sum(axis=1), grad, weighted_gram(c, score)

    # a width of at least 0.05 ADU (grouped data have no density to shrink onto) and
    # each weight within 5–95 % (module docstring)
    lower = np.array([-np.inf, -np.inf, np.log(0.05), -np.log(19.0)])
    upper = np.array([np.inf, np.inf, np.inf, np.log(19.0)])
    opt = maximize(evaluate, start, lower=lower, upper=upper, tol=1e-3, max_iter=iterations)
    return opt.objective, opt.x


def _statistics(values, counts):
    """:func:`_statistic` of histograms (P, K), :data:`_BLOCK` pixels at a time (a fit's
    arrays are pixels × counts large): the ratios and the states' distances (P,)."""
    blocks = np.array_split(np.arange(values.shape[0]), -(-values.shape[0] // _BLOCK))
    parts = [_statistic(values[rows], counts[rows]) for rows in blocks]
    statistic, step = (np.concatenate(p) for p in zip(*parts))
    return statistic, step


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
    start = np.column_stack(
        [m1, m2, 0.5 * np.log(np.maximum(var / 4.0, 0.01)), np.log(w / (1.0 - w))]
    )
    ll1, x = _fit_two(values, counts, start, iterations)
    # fewer than three values: one normal as narrow as they are fits them all (no test)
    statistic = np.where(np.count_nonzero(counts, axis=1) >= 3, 2.0 * (ll1 - ll0), 0.0)
    return np.maximum(statistic, 0.0), np.abs(x[:, 1] - x[:, 0])


@functools.lru_cache(maxsize=16)
def _null_quantiles(frames, false_alarm, seed) -> tuple:
    """The null quantile at each of :data:`_NULL_SIGMAS`: the shipped table's
    (:mod:`emccdcal.data._telegraph_null`, interpolated in log frames) at its rate,
    within its frames and with seed 0; else simulated from ``seed``, the same for the
    same arguments, so kept (a session's calibrations share their darks' frames)."""
    if (
        false_alarm == table.FALSE_ALARM
        and seed == 0
        and table.FRAMES[0] <= frames <= table.FRAMES[-1]
    ):
        at = np.log(frames)
        return tuple(
            float(np.interp(at, np.log(table.FRAMES), column))
            for column in np.array(table.QUANTILES).T
        )
    rng = np.random.default_rng(seed)
    return tuple(_null_quantile(frames, s, false_alarm, rng) for s in _NULL_SIGMAS)


def _null_quantile(frames, sigma, false_alarm, rng, pixels=_NULL_PIXELS):
    """The statistic's (1 − false_alarm) quantile for normal darks of ``frames`` frames
    and read noise ``sigma`` (ADU), simulated on ``pixels`` pixels."""
    statistic = _statistics(*_null_histograms(frames, sigma, pixels, rng))[0]
    return float(np.quantile(statistic, 1.0 - false_alarm))


def _null_histograms(frames, sigma, pixels, rng):
    """Histograms (values, counts), as :func:`emccdcal.data.stats.histograms` gives
    them, of ``frames`` rounded normal counts of read noise ``sigma`` (ADU) at each of
    ``pixels`` pixels of offsets uniform within a count: drawn as multinomials of the
    rounded normal's probabilities, as the counts' histograms are distributed (memory
    and time independent of the frames)."""
    offset = 100.0 + rng.random(pixels)
    half = int(np.ceil(8.0 * sigma + 2.0))  # the mass beyond: below 1e-15
    k = np.floor(offset)[:, None] + np.arange(-half, half + 1)[None, :]
    p = adc.rounded_normal(k, offset[:, None], sigma)
    counts = rng.multinomial(frames, p / p.sum(axis=1, keepdims=True)).astype(float)
    # each pixel's observed values first, in order; zero counts after
    seen = counts > 0
    order = np.argsort(~seen, axis=1, kind="stable")[:, : int(seen.sum(axis=1).max())]
    return np.take_along_axis(k, order, axis=1), np.take_along_axis(counts, order, axis=1)


def telegraph_pixels(stack, *, false_alarm=FALSE_ALARM, seed=0, adc_max=None) -> TelegraphTest:
    """Test every pixel of a 1× dark stack for two offset states (module docstring).

    Parameters
    ----------
    stack : array_like, shape (frames, rows, cols)
        Raw dark counts (ADU) at 1× (no multiplied events).
    false_alarm : float
        Fraction of one-normal pixels flagged by chance (default 1 %).
    seed : int
        Seed of the null simulation, where the table does not serve (another
        ``false_alarm``, frames outside 100–50 000) or a seed other than 0 asks for one.
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
    statistic, step = _statistics(h.values.astype(float), h.counts)
    sigmas = np.array(_NULL_SIGMAS)
    quantiles = np.array(_null_quantiles(int(np.median(h.n)), float(false_alarm), seed))
    sd = np.maximum(np.sqrt(h.var), sigmas[0])  # below the grid: its first quantile
    threshold = np.interp(np.log(sd), np.log(sigmas), quantiles)
    flagged = statistic > threshold
    return TelegraphTest(
        flagged, statistic, np.where(flagged, step, np.nan), threshold, false_alarm
    )
