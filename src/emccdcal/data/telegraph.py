"""Random-telegraph pixels: a dark whose counts are two normals, not one.

A random-telegraph (RTS) pixel's offset jumps between two (or more) levels as a charge
trap in its amplifier fills and empties (common on sCMOS sensors): its dark counts are a
mixture of normals of one width, and its offset and read noise, as one normal's, are
wrong for every frame. Each pixel is tested here: one normal against a mixture of two of
one width (each component's probabilities at the integers, the read noise widened by the
ADC's 1/12), by the likelihood ratio, maximised by expectation–maximisation on the
pixel's histogram. The ratio's distribution without a second state is not χ² (the
mixture's weight sits on its boundary), but a normal's location and scale do not move
it: its quantile is found by simulating normal darks of the same number of frames and a
read noise like the pixels' (seeded: the same data give the same flags), and a pixel is
flagged where its ratio exceeds the quantile of the stated false-alarm rate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import stats

__all__ = ["TelegraphTest", "telegraph_pixels", "FALSE_ALARM"]

#: Default fraction of one-normal pixels flagged by chance.
FALSE_ALARM = 0.01
#: Null simulations per read-noise value (the quantile's own error: ~1e-3 at 1 %).
_NULL_PIXELS = 2000
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


def _normal_at(values, mean, sd):
    z = (values - mean) / sd
    return np.exp(-0.5 * z * z) / (np.sqrt(2.0 * np.pi) * sd)


def _statistic(values, counts, iterations=60):
    """Twice the log-likelihood ratio of a two-state mixture to one normal per pixel,
    and the states' distance (ADU), from histograms (P, K)."""
    counts = counts.astype(float)
    n = counts.sum(axis=1)
    mean = (counts * values).sum(axis=1) / n
    var = (counts * (values - mean[:, None]) ** 2).sum(axis=1) / n
    sd0 = np.sqrt(var + 1.0 / 12.0)  # the rounding's width, as in both hypotheses
    ll0 = (
        counts * np.log(np.maximum(_normal_at(values, mean[:, None], sd0[:, None]), 1e-300))
    ).sum(1)
    # start: the halves below and above the mean
    low = values <= mean[:, None]
    w = np.clip((counts * low).sum(axis=1) / n, 0.05, 0.95)
    m1 = (counts * values * low).sum(axis=1) / np.maximum((counts * low).sum(axis=1), 1)
    m2 = (counts * values * ~low).sum(axis=1) / np.maximum((counts * ~low).sum(axis=1), 1)
    sd = np.sqrt(np.maximum(var / 4.0, 0.05))
    for _ in range(iterations):
        width = np.sqrt(sd**2 + 1.0 / 12.0)[:, None]
        a = w[:, None] * _normal_at(values, m1[:, None], width)
        b = (1.0 - w)[:, None] * _normal_at(values, m2[:, None], width)
        total = np.maximum(a + b, 1e-300)
        ra, rb = counts * a / total, counts * b / total
        na, nb = ra.sum(axis=1), rb.sum(axis=1)
        w = np.clip(na / n, 1e-6, 1 - 1e-6)
        m1 = (ra * values).sum(axis=1) / np.maximum(na, 1e-12)
        m2 = (rb * values).sum(axis=1) / np.maximum(nb, 1e-12)
        within = (ra * (values - m1[:, None]) ** 2 + rb * (values - m2[:, None]) ** 2).sum(1) / n
        sd = np.sqrt(np.maximum(within - 1.0 / 12.0, 0.01))
    width = np.sqrt(sd**2 + 1.0 / 12.0)[:, None]
    mix = w[:, None] * _normal_at(values, m1[:, None], width) + (1.0 - w)[:, None] * _normal_at(
        values, m2[:, None], width
    )
    ll1 = (counts * np.log(np.maximum(mix, 1e-300))).sum(axis=1)
    return np.maximum(2.0 * (ll1 - ll0), 0.0), np.abs(m2 - m1)


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
    statistic, step = _statistic(values, h.counts)
    rng = np.random.default_rng(seed)
    frames = int(np.median(h.n))
    sigmas = np.array(_NULL_SIGMAS)
    quantiles = np.array([_null_quantile(frames, s, false_alarm, rng) for s in sigmas])
    sd = np.sqrt(h.var)
    threshold = np.interp(np.log(sd), np.log(sigmas), quantiles)
    flagged = statistic > threshold
    return TelegraphTest(
        flagged, statistic, np.where(flagged, step, np.nan), threshold, false_alarm
    )
