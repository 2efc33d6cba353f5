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

A flagged pixel's offset states are then counted (:func:`_count_states`): mixtures of
three and four rounded normals of one width, fitted by the same steps (each weight's
logit against the last state's within ±ln 19), a state more kept while it raises twice
the log-likelihood by more than 2 ln(frames): Schwarz's criterion for a mean and a
weight more, whose penalty (16 at 3000 frames) is well above the two-state ratio's null
quantile, so that a two-state pixel is seldom counted three (none of 5760 simulated,
``benchmarks/telegraph_states.py``; docs/cmos.md has the table). A mixture's likelihood
has many maxima: each is fitted from the histogram cut into parts of equal counts and
from the fewer states' fit with its heaviest state split, and the better kept.
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
#: The most offset states counted: a pixel of more is said to have this many.
MAX_STATES = 4
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
    states : ndarray of int8, shape (P,)
        Offset states: 1 where not flagged; where flagged 2 to :data:`MAX_STATES` (that
        many or more), counted by Schwarz's criterion (:func:`_count_states`).
    """

    flagged: np.ndarray
    statistic: np.ndarray
    step: np.ndarray
    threshold: np.ndarray
    false_alarm: float
    states: np.ndarray


def _fit_states(values, counts, start, iterations):
    """Maximum likelihood of a mixture of k rounded normals of one width over each
    pixel's histogram (P, K), by the house's damped Newton steps on (m₁ … m_k, ln s,
    a₁ … a_(k−1)) from ``start`` (P, 2k), each pixel until a step promises under 1e-3
    nats: its log-likelihood (P,) and parameters (P, 2k). State i < k weighs
    w_i = e^(a_i) / (1 + Σ_j e^(a_j)), the last the rest; each a_i is kept within ±ln 19
    (two states: each weight within 5–95 %, module docstring)."""
    from .._optimize import maximize
    from .._util import weighted_gram

    k_states = start.shape[1] // 2

    def evaluate(rows, x):
        k, c = values[rows], counts[rows]
        sd = np.exp(x[:, k_states : k_states + 1])
        w = _weights(x[:, k_states + 1 :])
        fits = [adc.rounded_normal(k, x[:, i : i + 1], sd, derivs=True) for i in range(k_states)]
        p = w[0] * fits[0][0]
        for i in range(1, k_states):
            p = p + w[i] * fits[i][0]
        p = np.maximum(p, 1e-300)
        d_sd = w[0] * fits[0][2]
        for i in range(1, k_states):
            d_sd = d_sd + w[i] * fits[i][2]
        d_weight = []  # ∂p/∂a_i = Σ_(j≠i) w_i w_j (p_i − p_j)
        for i in range(k_states - 1):
            terms = [w[i] * w[j] * (fits[i][0] - fits[j][0]) for j in range(k_states) if j != i]
            d_weight.append(sum(terms[1:], terms[0]) / p)
        score = np.stack(
            [w[i] * fits[i][1] / p for i in range(k_states)] + [sd * d_sd / p] + d_weight,
            axis=-1,
        )
        grad = np.einsum("pk,pki->pi", c, score)
        return (c * np.log(p)).sum(axis=1), grad, weighted_gram(c, score)

    # a width of at least 0.05 ADU (grouped data have no density to shrink onto) and
    # each weight's logit within ±ln 19 (module docstring)
    bound = np.log(19.0)
    lower = np.array([-np.inf] * k_states + [np.log(0.05)] + [-bound] * (k_states - 1))
    upper = np.array([np.inf] * k_states + [np.inf] + [bound] * (k_states - 1))
    opt = maximize(evaluate, start, lower=lower, upper=upper, tol=1e-3, max_iter=iterations)
    return opt.objective, opt.x


def _statistics(values, counts):
    """:func:`_statistic` of histograms (P, K): the ratios and the states' distances
    (P,), and the two states' log-likelihoods (P,) and parameters (P, 4)."""
    return _blockwise(_statistic, values, counts)


def _blockwise(function, *arrays):
    """``function`` of the rows of ``arrays``, :data:`_BLOCK` at a time (a fit's arrays
    are pixels × counts large), its outputs (a tuple of arrays or one) joined."""
    blocks = np.array_split(np.arange(arrays[0].shape[0]), -(-arrays[0].shape[0] // _BLOCK))
    parts = [function(*(a[rows] for a in arrays)) for rows in blocks]
    if not isinstance(parts[0], tuple):
        return np.concatenate(parts)
    return tuple(np.concatenate(p) for p in zip(*parts))


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
    ll1, x = _fit_states(values, counts, start, iterations)
    # fewer than three values: one normal as narrow as they are fits them all (no test)
    statistic = np.where(np.count_nonzero(counts, axis=1) >= 3, 2.0 * (ll1 - ll0), 0.0)
    return np.maximum(statistic, 0.0), np.abs(x[:, 1] - x[:, 0]), ll1, x


def _count_states(values, counts, loglik, x, iterations=100):
    """The offset states of pixels found to hold two or more (histograms (P, K), their
    two states' log-likelihoods (P,) and parameters (P, 4)): a state more while it
    raises twice the log-likelihood by more than 2 ln(frames) (Schwarz's criterion: a
    mean and a weight more), up to :data:`MAX_STATES`. Each mixture of k + 1 states is
    fitted from two starts, the better kept: the histogram cut into k + 1 parts of equal
    counts, and the k states' fit with its heaviest state split in two (module
    docstring). Returns the counts (P,) of int."""
    counts = counts.astype(float)
    n = counts.sum(axis=1)
    states = np.full(values.shape[0], 2)
    for k in range(3, MAX_STATES + 1):
        rows = np.flatnonzero((states == k - 1) & (np.count_nonzero(counts, axis=1) > 2 * k))
        if rows.size == 0:
            break
        v, c = values[rows], counts[rows]
        fits = [
            _fit_states(v, c, start, iterations)
            for start in (_equal_parts(v, c, k), _split_heaviest(x[rows], k - 1))
        ]
        better = fits[1][0] > fits[0][0]
        ll_more = np.where(better, fits[1][0], fits[0][0])
        more = 2.0 * (ll_more - loglik[rows]) > 2.0 * np.log(n[rows])
        states[rows[more]] = k
        loglik, x = loglik.copy(), _padded(x, 2 * k)
        loglik[rows] = ll_more
        x[rows] = np.where(better[:, None], fits[1][1], fits[0][1])
    return states


def _padded(x, columns):
    """Parameters (P, 2k) of k states in the layout of more (P, columns), the extra
    means NaN (rows not refitted keep their k states')."""
    k = x.shape[1] // 2
    more = (columns - 2 * k) // 2
    nan = np.full((x.shape[0], more), np.nan)
    return np.concatenate([x[:, :k], nan, x[:, k : k + 1], x[:, k + 1 :], nan], axis=1)


def _equal_parts(values, counts, k):
    """A start (P, 2k) of k states: the means of the histogram's k parts of equal counts,
    their pooled width and their weights."""
    order = np.argsort(np.where(counts > 0, values, np.inf), axis=1)
    v, c = np.take_along_axis(values, order, 1), np.take_along_axis(counts, order, 1)
    n = c.sum(axis=1, keepdims=True)
    part = np.minimum((k * (np.cumsum(c, axis=1) - c / 2) / n).astype(int), k - 1)
    masses = np.stack([(c * (part == i)).sum(axis=1) for i in range(k)], axis=1)
    means = np.stack([(c * v * (part == i)).sum(axis=1) for i in range(k)], axis=1)
    means /= np.maximum(masses, 1.0)
    spread = (c * (v - np.take_along_axis(means, part, 1)) ** 2).sum(axis=1) / n[:, 0]
    return _start(means, np.sqrt(np.maximum(spread, 0.01)), masses / n)


def _split_heaviest(x, k):
    """A start (P, 2k + 2) of k + 1 states from k states' fit (P, 2k): its heaviest state
    split into two, three quarters of the width either side of its mean."""
    means, sd = x[:, :k], np.exp(x[:, k])
    weights = np.concatenate(_weights(x[:, k + 1 :]), axis=1)
    h = np.argmax(weights, axis=1)[:, None]
    centre = np.take_along_axis(means, h, 1)
    half = np.take_along_axis(weights, h, 1) / 2.0
    means = np.concatenate([means, centre + 0.75 * sd[:, None]], axis=1)
    np.put_along_axis(means, h, centre[:, 0][:, None] - 0.75 * sd[:, None], 1)
    np.put_along_axis(weights, h, half, 1)
    return _start(means, 0.75 * sd, np.concatenate([weights, half], axis=1))


def _weights(logits):
    """The k states' weights, a list of k columns (P, 1), from their logits (P, k − 1)
    (:func:`_fit_states`): 1 / Σ_j e^(z_j − z_i) with z = (a, 0), the last 1 − the
    others' sum; for two states exactly the 1 / (1 + e^(−a)) and 1 − w the null table
    was made with."""
    z = np.concatenate([logits, np.zeros((logits.shape[0], 1))], axis=1)
    w = [
        1.0 / np.exp(z - z[:, i : i + 1]).sum(axis=1, keepdims=True) for i in range(z.shape[1] - 1)
    ]
    return w + [1.0 - sum(w[1:], w[0])]


def _start(means, sd, weights):
    """Parameters (P, 2k) of :func:`_fit_states` from means (P, k), a width (P,) and
    weights (P, k), each weight's logit within the fit's bounds."""
    bound = np.log(19.0)
    w = np.maximum(weights, 1e-3)
    logits = np.clip(np.log(w[:, :-1] / w[:, -1:]), -bound, bound)
    return np.column_stack([means, np.log(np.maximum(sd, 0.05)), logits])


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
    >>> found = telegraph_pixels(dark.astype(np.uint16))
    >>> found.flagged.tolist(), found.states.tolist()
    ([True, False, False, False], [2, 1, 1, 1])
    """
    h = stats.histograms(stack, adc_max=adc_max)
    values = h.values.astype(float)
    statistic, step, loglik, x = _statistics(values, h.counts)
    sigmas = np.array(_NULL_SIGMAS)
    quantiles = np.array(_null_quantiles(int(np.median(h.n)), float(false_alarm), seed))
    sd = np.maximum(np.sqrt(h.var), sigmas[0])  # below the grid: its first quantile
    threshold = np.interp(np.log(sd), np.log(sigmas), quantiles)
    flagged = statistic > threshold
    states = np.ones(flagged.shape, dtype=np.int8)
    rows = np.flatnonzero(flagged)
    if rows.size:
        states[rows] = _blockwise(
            _count_states, values[rows], h.counts[rows], loglik[rows], x[rows]
        )
    return TelegraphTest(
        flagged, statistic, np.where(flagged, step, np.nan), threshold, false_alarm, states
    )
