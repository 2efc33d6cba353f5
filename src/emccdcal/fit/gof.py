"""Goodness of fit of the noise model, per pixel and acquisition, item 3).

A binned Pearson χ² test of each pixel's histogram against the fitted model pmf of
:mod:`emccdcal.model.noise`:

1. **Model.** The pmf of the pixel's counts is evaluated on one integer window per pixel
   with the batched FFT evaluator ``noise.window`` (all pixels of a block at once),
   normalised over the window, and summed into a CDF.
2. **Bins.** ``K = min(max_bins, ⌊n / frames_per_bin⌋)`` (50 and 10 by default) bins
   that are equiprobable under the fitted model: bin edge ``j`` is the first integer
   count whose model CDF reaches ``j/K`` (one ``searchsorted`` over all pixels). The first and last bins are
   open (``(−∞, e₁]`` and ``(e_{K−1}, ∞)``), so both tails are pooled, and data outside
   the model's window (cosmic rays, hot events) land in them. Because counts are
   integers a bin's probability is only close to ``1/K``; any bin whose expected count is
   below ``min_expected`` (5) is merged with its right neighbour (a trailing run of small
   bins with its left neighbour), so every bin used expects at least ``min_expected``
   frames. Expected counts are ``n`` times the exact bin probabilities, not ``n/K``.
3. **Statistic.** ``χ² = Σ_bins (O − nπ)² / (nπ)`` with ``dof = K_eff − 1 − s``, ``s``
   the number of parameters fitted per acquisition (``n_fitted_params``), and
   ``p = scipy.stats.chi2.sf(χ², dof)``.

The degrees of freedom are an approximation, documented in ``docs/gof.md``: the parameters
are maximum-likelihood estimates from the *ungrouped* counts (and, in a gain series, from
other acquisitions too), for which the statistic lies between χ²(K−1−s) and χ²(K−1)
(Chernoff & Lehmann 1954); with K ≈ 50 and s ≤ 3 the difference is small, and using
K−1−s errs towards flagging. Bins placed at the fitted model's quantiles (random cells)
do not change the limiting distribution (Moore & Spruill 1975).

:func:`misfit_warnings` turns p-value maps of several acquisitions into warnings for the
set-points (or levels) where the fraction of misfitting pixels is far above chance.
"""

from __future__ import annotations

import numpy as np
from scipy import special

from .. import _xp
from ..defaults import DEFAULT_EM_MODEL
from ..errors import OptionError
from ..model import noise

__all__ = [
    "gof_pvalues",
    "misfit_warnings",
    "rejected_acquisitions",
    "MOST_PIXELS",
    "DEFAULT_MAX_BINS",
    "DEFAULT_FRAMES_PER_BIN",
    "DEFAULT_MIN_EXPECTED",
]

#: Largest number of bins per pixel.
DEFAULT_MAX_BINS = 50
#: Frames per bin when choosing the number of bins: ``K = min(max_bins, ⌊n / 10⌋)``.
DEFAULT_FRAMES_PER_BIN = 10.0
#: Smallest expected count of a bin; bins below it (integer counts make equiprobable bins
#: only approximately equiprobable) are merged with a neighbour.
DEFAULT_MIN_EXPECTED = 5.0
#: Elements (pixels × window length) of the pmf evaluated at a time.
_BLOCK_ELEMENTS = 2**22
#: Window points summed together on the way to the CDF (:func:`_block_chi2`).
_CDF_CHUNK = 64


def _per_pixel(name, value, P):
    arr = np.asarray(value, dtype=float)
    if arr.size == 1:
        return np.full(P, float(arr.ravel()[0]))
    arr = arr.ravel()
    if arr.size != P:
        raise OptionError(
            f"{name} must be a scalar or have one value per pixel ({P}), got {arr.size} values"
        )
    return arr.copy()


def gof_pvalues(
    histograms_block,
    photoelectrons,
    em_gain,
    e_per_adu,
    offset,
    read_noise,
    *,
    n_fitted_params=2,
    max_bins=DEFAULT_MAX_BINS,
    frames_per_bin=DEFAULT_FRAMES_PER_BIN,
    min_expected=DEFAULT_MIN_EXPECTED,
    em_model=DEFAULT_EM_MODEL,
):
    """Binned Pearson χ² goodness-of-fit test of the model for every pixel of one acquisition.

    Parameters
    ----------
    histograms_block : emccdcal.data.stats.PixelHistograms or emccdcal.fit.engine.AcquisitionBlock
        Per-pixel histograms of the acquisition: ``values`` (P, K) counts in ADU,
        ``counts`` (P, K) frames at each value (0 on padding), and ``n`` (P,) frames.
    photoelectrons : array_like, scalar or P values
        Fitted E of this acquisition, e⁻ per pixel per frame.
    em_gain : array_like, scalar or P values
        Fitted EM gain g (dimensionless, ≥ 1); exactly 1 selects the Poisson–normal model.
    e_per_adu : array_like, scalar or P values
        Fitted φ, e⁻/ADU.
    offset : array_like, scalar or P values
        Offset S0, ADU.
    read_noise : array_like, scalar or P values
        Read noise σ, ADU (the SD of dark counts, as in :mod:`emccdcal.model.noise`).
    n_fitted_params : float, optional
        Parameters fitted per acquisition, subtracted from the degrees of freedom
        (default 2, e.g. E and g of one acquisition). Use 0 for parameters known a
        priori (true values); a parameter shared by A acquisitions may be counted as 1/A.
    max_bins : int, optional
        Largest number of bins K (default 50).
    frames_per_bin : float, optional
        K is at most ``n / frames_per_bin`` (default 10).
    min_expected : float, optional
        No bin used expects fewer frames than this (default 5): smaller bins are merged
        with a neighbour, which lowers the effective number of bins ``K_eff``.
    em_model : str or EMModel, optional
        The EM register's model, as in :func:`emccdcal.model.noise.logpmf` (default
        :data:`emccdcal.defaults.DEFAULT_EM_MODEL`).

    Returns
    -------
    pvalue : ndarray, shape (P,)
        ``chi2.sf(chi2, dof)``; NaN where the test is impossible: non-finite or
        out-of-range parameters (e.g. a failed fit), or too few frames for
        ``dof ≥ 1``.
    chi2 : ndarray, shape (P,)
        Pearson statistic (dimensionless); NaN where ``pvalue`` is.
    dof : ndarray, shape (P,)
        Degrees of freedom ``K_eff − 1 − n_fitted_params`` (float); NaN where ``pvalue`` is.

    Notes
    -----
    Vectorised over pixels: pixels are processed in blocks of bounded memory (P × window
    length ≤ 4 Mi elements) with array operations only.

    Examples
    --------
    >>> from emccdcal.data import stats
    >>> from emccdcal.simulate.camera import simulate_frames
    >>> frames = simulate_frames(30.0, 100.0, 3.859, 587.0, 15.0, frames=2000,
    ...                                   rows=2, cols=2, seed=1)
    >>> p, chi2, dof = gof_pvalues(stats.histograms(frames), 30.0, 100.0, 3.859, 587.0,
    ...                            np.hypot(15.0, 12**-0.5), n_fitted_params=0)
    >>> p.shape, dof.tolist()
    ((4,), [49.0, 49.0, 49.0, 49.0])
    """
    values = np.asarray(histograms_block.values, dtype=np.int64)
    counts = np.asarray(histograms_block.counts, dtype=float)
    if values.ndim != 2 or values.shape != counts.shape:
        raise OptionError("histograms_block must have values and counts of shape (P, K)")
    P = values.shape[0]
    n = np.asarray(histograms_block.n, dtype=float).ravel()
    if n.size != P:
        raise OptionError("histograms_block.n must have one entry per pixel")
    if not np.isfinite(n_fitted_params) or n_fitted_params < 0:
        raise OptionError(f"n_fitted_params must be >= 0, got {n_fitted_params!r}")
    if int(max_bins) < 2:
        raise OptionError(f"max_bins must be >= 2, got {max_bins!r}")
    if not min_expected > 0:
        raise OptionError(f"min_expected must be positive, got {min_expected!r}")
    if not frames_per_bin >= min_expected:
        raise OptionError(f"frames_per_bin must be >= min_expected, got {frames_per_bin!r}")
    E = _per_pixel("photoelectrons", photoelectrons, P)
    g = _per_pixel("em_gain", em_gain, P)
    phi = _per_pixel("e_per_adu", e_per_adu, P)
    S0 = _per_pixel("offset", offset, P)
    sigma = _per_pixel("read_noise", read_noise, P)

    K = np.minimum(int(max_bins), np.floor(n / float(frames_per_bin))).astype(np.int64)
    with np.errstate(invalid="ignore"):
        ok = (
            np.isfinite(E)
            & np.isfinite(g)
            & np.isfinite(phi)
            & np.isfinite(S0)
            & np.isfinite(sigma)
            & (E >= 0)
            & (g >= 1)
            & (phi > 0)
            & (sigma > 0)
            & (K >= 2 + np.ceil(n_fitted_params))
        )
    chi2 = np.full(P, np.nan)
    dof = np.full(P, np.nan)
    idx = np.flatnonzero(ok)
    # One pass per register of the model (the cascade's 1x rows are Poisson–normal).
    for register, part in noise.register_groups(g[idx], em_model):
        sub = idx[part]
        if sub.size == 0:
            continue
        rows = register.rows(E[sub], g[sub], phi[sub], np.zeros(sub.size))
        lo, hi = noise.window_extent(rows, S0[sub], sigma[sub], width=8.0)
        start = np.floor(lo).astype(np.int64)
        length = np.ceil(hi).astype(np.int64) - start + 1
        # Blocks of pixels with similar windows, bounded memory.
        order = sub[np.argsort(length, kind="stable")]
        pos = np.empty(P, dtype=np.int64)
        pos[sub] = np.arange(sub.size)
        i0 = 0
        while i0 < order.size:
            width = int(length[pos[order[min(order.size - 1, i0)]]])
            # Grow the block while it fits the budget at its longest window.
            step = max(1, _BLOCK_ELEMENTS // max(1, width))
            i1 = min(order.size, i0 + step)
            while i1 > i0 + 1 and int(length[pos[order[i1 - 1]]]) * (i1 - i0) > _BLOCK_ELEMENTS:
                i1 = i0 + max(1, (i1 - i0) // 2)
            sel = order[i0:i1]
            r = pos[sel]
            c, d = _block_chi2(
                values[sel],
                counts[sel],
                n[sel],
                K[sel],
                rows.take(r),
                S0[sel],
                sigma[sel],
                start[r],
                length[r],
                float(n_fitted_params),
                float(min_expected),
            )
            chi2[sel], dof[sel] = c, d
            i0 = i1
    bad = ~(dof >= 1)
    chi2[bad] = np.nan
    dof[bad] = np.nan
    with np.errstate(invalid="ignore"):
        pvalue = special.chdtrc(dof, chi2)  # chi2.sf, without importing scipy.stats
    return pvalue, chi2, dof


def _block_chi2(values, counts, n, K, rows, S0, sigma, start, length, s, min_expected):
    """χ² and dof of a block of pixels (all arrays and the register's rows restricted
    to the block), computed where the fit computes (:func:`emccdcal._xp.engine`)."""
    xp, dev = _xp.engine()
    P = values.shape[0]
    # A window of whole chunks: the CDF is summed chunk by chunk (one fast reduction)
    # and only within the chunks where the edges fall (a running sum over all of it
    # took as long as the window's transform).
    c = _CDF_CHUNK
    L = c * noise.fast_len(-(-int(length.max()) // c))
    p = noise.window(rows, S0 - start, sigma, L, xp=(xp, dev))[0]
    B = L // c
    # The CDF unnormalised, its total the window's sum (1 up to round-off): the targets
    # and the edges' values are scaled by it. FFT round-off (~1e-16 of the peak) can make
    # a far tail's value slightly negative: the CDF wiggles by as much there, within
    # 1e-13 of 0 or of its total, where no edge is (every edge is 1/K or more in from
    # either end).
    chunk_end = xp.cumulative_sum(xp.sum(xp.reshape(p, (P, B, c)), axis=2), axis=1)
    total = chunk_end[:, -1:]
    ones = xp.ones((P, 1), dtype=p.dtype, device=dev)

    # Equiprobable edges: edge j (j = 1 … K−1) is the first window index with cdf ≥ j/K;
    # bin j (0-based) holds indices (edge_j, edge_{j+1}], the first and last bins open.
    Kmax = int(K.max())
    j = np.arange(1, Kmax)
    real_edge = j[None, :] < K[:, None]
    target = np.where(real_edge, j[None, :] / K[:, None], 2.0)  # unused edges: beyond
    rows_ = np.arange(P)[:, None]
    exists = np.arange(Kmax)[None, :] < K[:, None]
    after_last = np.arange(Kmax)[None, :] > (K - 1)[:, None]
    real_edge, target, exists, after_last, rows_i, n_, counts, values, start = _xp.on(
        xp, dev, real_edge, target, exists, after_last, rows_, n, counts, values, start
    )
    # The chunk of each edge: the first whose end reaches the target, by one
    # searchsorted over all pixels (row offsets: the CDF lies in [0, 1], rows 2 apart).
    rows_f = xp.astype(rows_i, xp.float64)
    target = target * total
    chunk = xp.searchsorted(
        xp.reshape(chunk_end + 2.0 * rows_f, (-1,)),
        xp.reshape(target + 2.0 * rows_f, (-1,)),
        side="left",
    )
    chunk = xp.clip(xp.reshape(chunk, (P, Kmax - 1)) - rows_i * B, max=B - 1)
    # Within it, the running sum from the previous chunk's end.
    zero = xp.zeros((P, 1), dtype=p.dtype, device=dev)
    before = xp.take_along_axis(xp.concat([zero, chunk_end], axis=1), chunk, axis=1)
    positions = (rows_i * B + chunk)[:, :, None] * c + xp.arange(c, device=dev)[None, None, :]
    inside = xp.take(xp.reshape(p, (-1,)), xp.reshape(positions, (-1,)))
    running = before[:, :, None] + xp.cumulative_sum(xp.reshape(inside, (P, Kmax - 1, c)), axis=2)
    offset = xp.sum(xp.astype(running < target[:, :, None], xp.int64), axis=2)
    offset = xp.clip(offset, max=c - 1)  # round-off: the chunk's end, by the chunk's sum
    edge = chunk * c + offset
    edge = xp.where(real_edge, edge, L - 1)

    # Exact probability of every (unmerged) bin.
    cdf_at = xp.take_along_axis(running, offset[:, :, None], axis=2)[:, :, 0] / total
    cdf_at = xp.where(real_edge, cdf_at, 1.0)
    prob = xp.concat([cdf_at, ones], axis=1) - xp.concat([0.0 * ones, cdf_at], axis=1)

    # Merge bins expecting fewer than min_expected frames: drop the edge above a small
    # bin, and the edge below a trailing run of small bins.
    small = (prob * n_[:, None] < min_expected) & exists
    run = xp.astype(xp.flip(small | after_last, axis=1), xp.int64)
    trailing = (xp.flip(xp.cumulative_prod(run, axis=1), axis=1) != 0) & exists
    keep = ~small[:, :-1] & ~trailing[:, 1:] & real_edge  # edge between bin i and i+1
    keep_i = xp.astype(keep, xp.int64)
    merged_id = xp.concat(
        [xp.zeros((P, 1), dtype=xp.int64, device=dev), xp.cumulative_sum(keep_i, axis=1)], axis=1
    )  # (P, Kmax)
    K_eff = xp.sum(keep_i, axis=1) + 1

    # Observed, per unmerged bin: the frames at or below each edge, from the running
    # count over each pixel's sorted values at the position of the edge among them (one
    # searchsorted of the K edges, row offsets, not of every value among the edges);
    # values outside the window count in the open end bins.
    y = xp.clip(values - start[:, None], min=0, max=L - 1)
    span = L + 1
    K_values = values.shape[1]
    past_edge = xp.searchsorted(
        xp.reshape(y + span * rows_i, (-1,)),
        xp.reshape(edge + span * rows_i, (-1,)),
        side="right",
    )
    frames_to = xp.concat(
        [xp.zeros(1, dtype=counts.dtype, device=dev), xp.cumulative_sum(xp.reshape(counts, (-1,)))]
    )
    row_start = xp.take(frames_to, xp.reshape(rows_i * K_values, (-1,)))[:, None]
    row_total = xp.take(frames_to, xp.reshape((rows_i + 1) * K_values, (-1,)))[:, None]
    at_edge = xp.reshape(xp.take(frames_to, past_edge), (P, Kmax - 1)) - row_start
    cumulative = xp.concat([0.0 * ones, at_edge, row_total - row_start], axis=1)
    observed = _xp.bincount(
        xp,
        xp.reshape(merged_id + rows_i * Kmax, (-1,)),
        xp.reshape(cumulative[:, 1:] - cumulative[:, :-1], (-1,)),
        P * Kmax,
    )
    expected = _xp.bincount(
        xp,
        xp.reshape(merged_id + rows_i * Kmax, (-1,)),
        xp.reshape(xp.where(exists, prob, 0.0) * n_[:, None], (-1,)),
        P * Kmax,
    )
    observed, expected = xp.reshape(observed, (P, Kmax)), xp.reshape(expected, (P, Kmax))
    used = xp.arange(Kmax, device=dev)[None, :] < K_eff[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        terms = xp.where(used, (observed - expected) ** 2 / expected, 0.0)
    chi2 = xp.sum(terms, axis=1)
    dof = xp.astype(K_eff, xp.float64) - 1.0 - s
    return _xp.to_numpy(chi2), _xp.to_numpy(dof)


def misfit_warnings(
    pvalues_by_acquisition, alpha=0.01, *, threshold=1e-3, min_ratio=2.0, kind="set-point"
):
    """Warnings for the acquisitions where the model misfits systematically.

    Under a correct model the per-pixel p-values are uniform, so about a fraction
    ``alpha`` of the pixels have ``p < alpha``. An acquisition is reported when the
    number of such pixels is improbably large — a one-sided binomial test against
    ``alpha`` gives a p-value below ``threshold`` — *and* the fraction is at least
    ``min_ratio · alpha`` (on a full sensor the binomial test alone would flag excesses
    too small to matter).

    Parameters
    ----------
    pvalues_by_acquisition : dict
        Label (set-point or level, e.g. ``5`` or ``"5x"``) → p-values of its pixels
        (any shape; NaN entries, i.e. pixels without a test, are ignored).
    alpha : float, optional
        Per-pixel significance level (default 0.01).
    threshold : float, optional
        Significance of the binomial test (default 1e-3).
    min_ratio : float, optional
        Smallest flagged fraction, in units of ``alpha`` (default 2).
    kind : str, optional
        What a label names, used in the messages (default ``"set-point"``).

    Returns
    -------
    list of str
        One message per flagged acquisition, in the dict's order; empty if none.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> misfit_warnings({5: rng.uniform(size=1000) ** 8, 300: rng.uniform(size=1000)})
    ['set-point 5: 529 of 1000 pixels (52.9 %) misfit the noise model at p < 0.01 (1.0 % expected by chance; binomial p = 0)']
    """
    if not 0 < alpha < 1:
        raise OptionError(f"alpha must be in (0, 1), got {alpha!r}")
    out = []
    for label, pv in pvalues_by_acquisition.items():
        pv = np.asarray(pv, dtype=float).ravel()
        pv = pv[np.isfinite(pv)]
        m = int(pv.size)
        if m == 0:
            continue
        k = int(np.sum(pv < alpha))
        frac = k / m
        binom_p = float(special.bdtrc(k - 1, m, alpha))  # P(X ≥ k), X ~ Binomial(m, alpha)
        if binom_p < threshold and frac >= min_ratio * alpha:
            out.append(
                f"{kind} {label}: {k} of {m} pixels ({100 * frac:.1f} %) misfit the noise "
                f"model at p < {alpha:g} ({100 * alpha:.1f} % expected by chance; "
                f"binomial p = {binom_p:.2g})"
            )
    return out


#: Fraction of an acquisition's pixels whose test rejects the model (at p < 0.01) beyond
#: which the acquisition is misfitted, not its pixels: its estimates are not a result.
MOST_PIXELS = 0.5


def rejected_acquisitions(pvalues_by_acquisition, alpha=0.01, *, kind="set-point") -> list[str]:
    """The acquisitions whose goodness of fit rejects the model at most of their pixels
    (more than :data:`MOST_PIXELS` at p < ``alpha``): one line each, in the dict's
    order. Where the model misfits most pixels the estimates there are not a calibration
    (a dark of another mode, a misread file, a wrong set-point), however many converged.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> rejected_acquisitions({"5x": rng.uniform(size=100), "300x": np.full(100, 1e-9)})
    ['set-point 300x: the noise model is rejected at 100 of 100 pixels (p < 0.01)']
    """
    out = []
    for label, pv in pvalues_by_acquisition.items():
        pv = np.asarray(pv, dtype=float).ravel()
        pv = pv[np.isfinite(pv)]
        k = int(np.sum(pv < alpha))
        if pv.size and k > MOST_PIXELS * pv.size:
            out.append(
                f"{kind} {label}: the noise model is rejected at {k} of {pv.size} pixels "
                f"(p < {alpha:g})"
            )
    return out
