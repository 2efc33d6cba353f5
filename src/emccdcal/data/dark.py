"""Offset and read-noise maps from dark stacks.

A dark (shuttered) acquisition recorded at a gain set-point gives, per pixel, the offset
``offset`` = S0 (the mean dark count, ADU) and the read noise ``read_noise`` = σ (the
standard deviation of the dark counts, ADU). The paper records one dark stack right
after each set-point because the offset drifts with the set-point (Ryan et al. 2021, Methods).

At high EM gain the dark frames also contain clock-induced charge and dark current
(spurious electrons that the EM register multiplies), so the dark's plain SD grows with
the set-point and is then not the Gaussian read-out noise (docs/simulation.md):
:func:`check_read_noise_growth` says so. :func:`fit_dark` separates the two: it fits each
pixel's dark counts with the noise model, read-out plus multiplied events, and gives the
offset and read noise of the read-out alone, with the events' rate.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from .. import defaults
from .._optimize import maximize
from .._util import weighted_gram
from ..errors import InputError
from ..model import noise
from . import stats

__all__ = [
    "as_stack",
    "maps_from_dark",
    "fit_dark",
    "read_out_maps",
    "analog_read_out",
    "DarkFit",
    "check_read_noise_growth",
    "DEFAULT_CHUNK_ELEMENTS",
]

#: Elements (frames × pixels) converted to float64 at a time when streaming a dark
#: stack: 2**23 elements = 64 MiB.
DEFAULT_CHUNK_ELEMENTS = 2**23


def as_stack(stack, what="stack"):
    """``stack`` as a (frames, rows, cols) array of numbers (memory maps stay as they are).

    Raises a ValueError naming ``what`` for another shape or a non-numeric dtype.
    """
    if not hasattr(stack, "shape") or not hasattr(stack, "dtype"):
        stack = np.asarray(stack)
    if stack.ndim != 3:
        raise InputError(f"{what} must be 3-D (frames, rows, cols), got shape {tuple(stack.shape)}")
    if stack.dtype.kind not in "uif":
        raise InputError(f"{what} must hold numbers, got dtype {stack.dtype}")
    return stack


def maps_from_dark(stack, *, chunk_frames: int | None = None):
    """Per-pixel offset and read-noise maps of a dark stack.

    The stack is streamed in chunks of frames; only one chunk at a time is converted to
    float64, so a memory-mapped dark larger than memory can be used. Chunks are combined
    with the exact pairwise update of count, mean and sum of squared deviations (Chan,
    Golub & LeVeque), which is as accurate as the two-pass formula.

    Parameters
    ----------
    stack : array_like, shape (frames, rows, cols)
        Raw dark counts (ADU), integer or integer-valued float; a NumPy memmap is read
        chunk by chunk. At least 2 frames.
    chunk_frames : int, optional
        Frames per chunk. Default: as many as fit in :data:`DEFAULT_CHUNK_ELEMENTS`
        elements. The result does not depend on it (up to float64 round-off).

    Returns
    -------
    offset : ndarray of float64, shape (rows, cols)
        Per-pixel mean of the dark counts, ADU.
    read_noise : ndarray of float64, shape (rows, cols)
        Per-pixel standard deviation of the dark counts (ddof=1), ADU.

    Raises
    ------
    ValueError
        If the stack is not 3-D, has fewer than 2 frames, is not numeric, or contains
        NaN or infinite values.

    Examples
    --------
    >>> dark = np.array([[[100, 200]], [[102, 200]], [[104, 200]]], dtype=np.uint16)
    >>> offset, read_noise = maps_from_dark(dark)
    >>> offset.tolist(), read_noise.tolist()
    ([[102.0, 200.0]], [[2.0, 0.0]])
    """
    stack = as_stack(stack, "dark stack")
    n_frames, rows, cols = stack.shape
    if n_frames < 2:
        raise InputError(
            f"dark stack needs at least 2 frames for a standard deviation, got {n_frames}"
        )
    if chunk_frames is None:
        chunk_frames = max(1, DEFAULT_CHUNK_ELEMENTS // max(1, rows * cols))
    elif int(chunk_frames) < 1:
        raise InputError(f"chunk_frames must be >= 1, got {chunk_frames}")
    chunk_frames = int(chunk_frames)

    n = 0
    mean = np.zeros((rows, cols))
    m2 = np.zeros((rows, cols))  # sum of squared deviations from the mean
    for start in range(0, n_frames, chunk_frames):
        # a copy always: the deviations are formed in place, never in the caller's array
        chunk = np.array(stack[start : start + chunk_frames], dtype=np.float64)
        nb = chunk.shape[0]
        mean_b = chunk.mean(axis=0)
        chunk -= mean_b
        m2_b = np.einsum("fij,fij->ij", chunk, chunk)
        delta = mean_b - mean
        total = n + nb
        mean += delta * (nb / total)
        m2 += m2_b + delta**2 * (n * nb / total)
        n = total
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(m2))):
        raise InputError("dark stack contains NaN or infinite values")
    return mean, np.sqrt(m2 / (n - 1))


@dataclass(frozen=True)
class DarkFit:
    """Maps of a dark stack fitted with the noise model (:func:`fit_dark`).

    Attributes
    ----------
    offset, read_noise : ndarray, shape (rows, cols)
        S0 and σ of the read-out alone, ADU (σ in the noise model's convention: the SD of
        dark counts without events, quantisation included).
    event_rate : ndarray, shape (rows, cols)
        Electrons per pixel per frame that the register multiplied (clock-induced charge
        and dark current), e⁻.
    event_scale : float
        Mean output of one such electron, ADU (g/φ of the set-point), shared by the pixels.
    converged : ndarray of bool, shape (rows, cols)
        The pixel's fit converged; elsewhere ``offset`` and ``read_noise`` are the plain
        mean and SD.
    """

    offset: np.ndarray
    read_noise: np.ndarray
    event_rate: np.ndarray
    event_scale: float
    converged: np.ndarray


def fit_dark(stack, *, adc_max=None, sample_pixels=64) -> DarkFit:
    """Offset and read-noise maps of a dark stack with multiplication events.

    A dark frame at EM gain g holds, besides the read-out's Gaussian, electrons made by
    clock-induced charge and dark current that the register multiplies: a long tail above
    the offset. Its plain mean and SD are then biased upwards (the SD by tens of per cent
    at a few hundred times gain). Here every pixel's dark counts are fitted by maximum
    likelihood with the noise model of :mod:`emccdcal.model.noise`: S0 and σ of the
    read-out, and an event rate c (Poisson electrons per frame) multiplied with a mean
    output θ (ADU) shared by the pixels, θ found by profiling the likelihood of a sample of
    ``sample_pixels`` pixels. The events' shape is the gamma model's: at low gain, where
    it differs from an exact register's, events sit inside the read-out's Gaussian and
    hardly matter.

    Parameters
    ----------
    stack : array_like, shape (frames, rows, cols)
        Raw dark counts (ADU), at least 2 frames.
    adc_max : int, optional
        ADC maximum: counts at or above it are left out.
    sample_pixels : int
        Pixels (spread evenly) whose likelihood is profiled for the shared θ.

    Returns
    -------
    DarkFit

    Examples
    --------
    >>> from emccdcal.simulate.camera import simulate_frames
    >>> dark = simulate_frames(0.0, 400.0, 5.2, 500.0, 15.4, frames=4000, rows=4, cols=4,
    ...                        cic=0.05, seed=3)
    >>> fit = fit_dark(dark)
    >>> plain = maps_from_dark(dark)[1]
    >>> bool(abs(fit.read_noise.mean() / 15.4 - 1) < 0.02 < plain.mean() / 15.4 - 1)
    True
    """
    stack = as_stack(stack, "dark stack")
    F, rows, cols = stack.shape
    h = stats.histograms(stack, adc_max=adc_max)
    P = h.n.size
    S0, sigma = robust_start(h)
    check_read_out_spread(sigma, stack.dtype)
    # θ: the mean excess of counts far above the Gaussian (an exponential tail's mean).
    far = h.values > (S0 + 6.0 * sigma)[:, None]
    excess = (h.values - (S0 + 6.0 * sigma)[:, None]) * h.counts * far
    n_far = float((h.counts * far).sum())
    plain_offset, plain_sd = h.mean, np.sqrt(h.var)
    if n_far < 10:
        # No events stand out of the read-out's Gaussian (low gain, or none made): what
        # there is hides in its core, and the plain mean and SD are its fit.
        return DarkFit(
            plain_offset.reshape(rows, cols),
            plain_sd.reshape(rows, cols),
            np.full((rows, cols), np.nan),
            0.0,
            np.ones((rows, cols), bool),
        )
    theta0 = max(float(excess.sum() / n_far), 0.1)
    rate0 = np.maximum((h.counts * far).sum(axis=1) / h.n, 1e-4)
    x0 = np.stack([np.log(rate0), S0, np.log(sigma)], axis=1)
    sample = np.unique(np.linspace(0, P - 1, min(P, sample_pixels)).astype(int))
    sub = take_pixels(h, sample)

    def profile(log_theta):
        x, _ = _fit_events(sub, x0[sample], np.full(sample.size, np.exp(log_theta)))
        return _loglik(sub, x, np.full(sample.size, np.exp(log_theta))).sum()

    grid = np.log(theta0) + np.linspace(-1.2, 1.2, 5)
    values = [profile(v) for v in grid]
    best = int(np.argmax(values))
    lo, hi = grid[max(best - 1, 0)], grid[min(best + 1, grid.size - 1)]
    from scipy.optimize import minimize_scalar

    log_theta = minimize_scalar(
        lambda v: -profile(v), bounds=(lo, hi), method="bounded", options={"xatol": 1e-2}
    ).x
    theta = float(np.exp(log_theta))
    x, ok = np.empty_like(x0), np.empty(P, dtype=bool)
    for b in range(0, P, _BLOCK_PIXELS):  # the windows of a block: bounded memory
        part = slice(b, b + _BLOCK_PIXELS)
        n = x0[part].shape[0]
        x[part], ok[part] = _fit_events(take_pixels(h, part), x0[part], np.full(n, theta))
    offset, read_noise, rate = _maps(x, ok, plain_offset, plain_sd, rows, cols)
    return DarkFit(offset, read_noise, rate, theta, ok.reshape(rows, cols))


#: Pixels fitted together (their FFT windows are held at once).
_BLOCK_PIXELS = 256


#: Largest read-out noise a dark may show, as a fraction of its counts' range (its dtype's):
#: 1/64, 1024 ADU of a 16-bit camera, is tens of times any camera's. Above it the frames
#: are not a read-out's (a byte-swapped or otherwise misread file), and the noise model's
#: windows, which span the read-out's Gaussian, would grow without use.
MAX_READ_OUT_FRACTION = 1 / 64

#: Largest ratio of a multiplied dark's read-out noise to that of the least multiplied
#: dark of the same calibration: the read-out's Gaussian does not depend on the EM gain
#: (its multiplied events sit above the median that the robust width is read below).
MAX_READ_OUT_GROWTH = 10.0


def check_read_out_spread(robust_sd, dtype, reference=None) -> None:
    """Refuse, before any fit, a dark whose read-out noise (``robust_sd``: each pixel's
    counts' width below their median, ADU) no read-out has: above
    :data:`MAX_READ_OUT_FRACTION` of its ``dtype``'s range, or more than
    :data:`MAX_READ_OUT_GROWTH` times the ``reference`` (the read noise, ADU, of the
    least multiplied dark of the same camera and mode)."""
    median = float(np.median(robust_sd))
    dtype = np.dtype(dtype)
    span = (np.iinfo(dtype).max - np.iinfo(dtype).min) if dtype.kind in "iu" else 65535.0
    if median > MAX_READ_OUT_FRACTION * span:
        raise InputError(
            f"its counts spread as a read-out noise of {median:.4g} ADU at the median "
            f"pixel, {median / span:.1%} of the {dtype.name} range: not dark frames as a "
            "camera reads them out (a byte-swapped or misread file?); check the file"
        )
    if reference is not None and median > MAX_READ_OUT_GROWTH * reference:
        raise InputError(
            f"its read-out noise, {median:.4g} ADU at the median pixel, is "
            f"{median / reference:.0f} times that of this calibration's least multiplied "
            f"dark ({reference:.4g} ADU): not dark frames of the same camera and read-out "
            "mode (another mode or speed, a byte-swapped or damaged file?); check the file"
        )


def read_out_maps(stack, setpoint, *, adc_max=None, reference_read_noise=None):
    """The offset and read-noise maps (ADU) a calibration uses from a dark stack taken at
    ``setpoint``, and the rate of multiplied events in it (per pixel per frame, None
    where there are none).

    At 1× the dark is read-out noise alone: its mean and SD (:func:`maps_from_dark`). A
    multiplied dark also holds amplified events (spurious charge, dark current), which
    would inflate an SD: there the read-out is fitted apart from them (:func:`fit_dark`).
    A dark whose read-out noise is implausible (:func:`check_read_out_spread`, against
    ``reference_read_noise``, ADU, the least multiplied dark's median, where known) is
    refused before any fit.
    """
    stack = as_stack(stack, "dark stack")
    h = stats.histograms(stack[:2000], adc_max=adc_max)  # enough frames for a width
    check_read_out_spread(robust_start(h)[1], stack.dtype, reference_read_noise)
    if setpoint == 1:
        offset, read_noise = maps_from_dark(stack)
        return (*analog_read_out(stack, offset, read_noise, adc_max=adc_max), None)
    fitted = fit_dark(stack, adc_max=adc_max)
    events = None if fitted.event_scale == 0 else fitted.event_rate
    return fitted.offset, fitted.read_noise, events


def analog_read_out(stack, offset, sd, *, adc_max=None):
    """The offset and read-noise maps (ADU) of a 1× dark stack as the likelihood uses
    them: where the read noise is below :data:`emccdcal.model.adc.ROUNDING_BELOW`, the
    offset and the analog σ *before* the ADC's rounding, fitted to each pixel's dark counts
    as a rounded normal (:func:`emccdcal.model.adc.fit_rounded_normal`); elsewhere the
    counts' mean and SD (``offset``, ``sd``) as they are."""
    from ..model import adc

    sheppard = np.sqrt(np.maximum(sd**2 - 1.0 / 12.0, 0.0))
    small = np.flatnonzero(adc.rounds(True, sheppard).ravel())
    if small.size == 0:
        return offset, sd
    rows, cols = offset.shape
    frames = np.asarray(stack).reshape(stack.shape[0], -1)[:, small]
    h = stats.histograms(frames.reshape(frames.shape[0], 1, -1), adc_max=adc_max)
    mu, sigma, ok = adc.fit_rounded_normal(h.values, h.counts, h.mean, np.sqrt(h.var))
    offset, sd = offset.astype(float).ravel(), sd.astype(float).ravel()
    offset[small] = np.where(ok, mu, offset[small])
    sd[small] = np.where(ok, sigma, sheppard.ravel()[small])
    return offset.reshape(rows, cols), sd.reshape(rows, cols)


def take_pixels(h, idx):
    """The histograms of pixels ``idx`` (what the fit reads of them)."""
    return SimpleNamespace(values=h.values[idx], counts=h.counts[idx], n=h.n[idx])


def robust_start(h):
    """Median and left half-width (the 15.9 % quantile's distance) of each pixel's counts:
    events only add counts above the offset, so the left half is the read-out's."""
    cdf = np.cumsum(h.counts, axis=1) / h.n[:, None]
    rows = np.arange(h.n.size)
    med = h.values[rows, np.argmax(cdf >= 0.5, axis=1)].astype(float)
    q16 = h.values[rows, np.argmax(cdf >= 0.158655, axis=1)].astype(float)
    return med, np.maximum(med - q16, 0.5)


def _model(h, x, theta, derivs):
    """The noise model at the histogram values: E = event rate, scale θ, S0, σ."""
    rate, S0, sigma = np.exp(x[:, 0]), x[:, 1], np.exp(x[:, 2])
    # Events are the gamma register's multiplied electrons (E the rate, θ their scale):
    # the paper's model, named, whatever the default register.
    rows = noise.EMModel(defaults.PAPER_EM_MODEL).register.rows_at((rate, theta), False)
    lo, hi = noise.window_extent(rows, S0, sigma, width=8.0)
    first, last = h.values[:, 0], h.values.max(axis=1)
    start = np.minimum(np.floor(lo).astype(np.int64), first)
    stop = np.maximum(np.ceil(hi).astype(np.int64), last)
    n = noise.fast_len(int((stop - start).max()) + 1)
    names = ("photoelectrons", "offset", "read_noise")
    p, d1, _ = noise.window(rows, S0 - start, sigma, n, derivs=derivs, names=names)
    flat = h.values - start[:, None] + (np.arange(rate.size) * n)[:, None]
    pv = p.ravel()[flat]
    floor = 1e-14 * p.max(axis=1, keepdims=True)
    low = pv < floor
    pv = np.where(low, floor, pv)
    scores = None
    if derivs:  # by (ln c, S0, ln σ)
        d = [d1[nm].ravel()[flat] for nm in names]
        scores = np.stack([d[0] * rate[:, None], d[1], d[2] * sigma[:, None]], axis=-1)
        scores = np.where(low[..., None], 0.0, scores / pv[..., None])
    return pv, scores


def _loglik(h, x, theta):
    return np.sum(h.counts * np.log(_model(h, x, theta, False)[0]), axis=1)


def _fit_events(h, x0, theta, max_iter=60):
    """Per-pixel maximum likelihood of (ln c, S0, ln σ) at a fixed θ: damped BHHH steps
    (the information from the outer product of the scores) by the package's optimizer.
    Returns the parameters and whether each pixel's fit ended at a maximum (or where
    no step could improve it)."""

    def evaluate(rows, x):
        sub = take_pixels(h, rows)
        pv, s = _model(sub, x, theta[rows], True)
        ll = np.sum(sub.counts * np.log(pv), axis=1)
        grad = np.sum(sub.counts[..., None] * s, axis=1)
        info = weighted_gram(sub.counts, s)
        return ll, grad, info

    lower = np.array([_LOG_RATE[0], -np.inf, -np.inf])
    upper = np.array([_LOG_RATE[1], np.inf, np.inf])
    opt = maximize(
        evaluate, x0, lower=lower, upper=upper, tol=1e-8, max_iter=max_iter, accept_rtol=1e-9
    )
    return opt.x, (opt.done | opt.stuck) & np.all(np.isfinite(opt.x), axis=1)


#: Bounds of ln(event rate): 1e-7 to 2 electrons per pixel per frame.
_LOG_RATE = (np.log(1e-7), np.log(2.0))


def _maps(x, ok, plain_offset, plain_sd, rows, cols):
    offset = np.where(ok, x[:, 1], plain_offset).reshape(rows, cols)
    read_noise = np.where(ok, np.exp(x[:, 2]), plain_sd).reshape(rows, cols)
    rate = np.where(ok, np.exp(x[:, 0]), np.nan).reshape(rows, cols)
    return offset, read_noise, rate


def check_read_noise_growth(
    setpoints: Sequence[float], read_noise_maps: Sequence, *, threshold: float = 0.05
) -> list[str]:
    """Warn when the read noise of the darks grows with the EM gain set-point.

    Compares the median read noise at every set-point with the median at the lowest
    set-point. Where it is more than ``threshold`` (relative) higher, the dark frames
    most likely contain clock-induced charge that the EM register multiplies
    (docs/simulation.md): the dark "σ" is then not pure Gaussian read-out noise. On the shared ProEM data
    the median grows from about 15.5 ADU (1× to 25×) to about 23 ADU at 300×.

    Parameters
    ----------
    setpoints : sequence of float
        EM gain set-point (dimensionless) of each map.
    read_noise_maps : sequence of array_like
        Read-noise maps (ADU), one per set-point entry; several maps with the same
        set-point are pooled.
    threshold : float, optional
        Relative growth that triggers a warning (default 0.05, i.e. 5 %).

    Returns
    -------
    list of str
        One message per set-point whose median read noise exceeds the reference by more
        than ``threshold``, in increasing set-point order; empty when none does.

    Examples
    --------
    >>> maps = [np.full((2, 2), 15.5), np.full((2, 2), 15.6), np.full((2, 2), 23.3)]
    >>> msgs = check_read_noise_growth([1, 100, 300], maps)
    >>> len(msgs), msgs[0].startswith("read noise at EM gain set-point 300")
    (1, True)
    """
    setpoints = [float(s) for s in setpoints]
    read_noise_maps = list(read_noise_maps)
    if len(setpoints) != len(read_noise_maps):
        raise InputError(
            f"got {len(setpoints)} set-points but {len(read_noise_maps)} read-noise maps"
        )
    if not (np.isfinite(threshold) and threshold >= 0):
        raise InputError(f"threshold must be a non-negative number, got {threshold!r}")
    pooled: dict[float, list[np.ndarray]] = {}
    for g, m in zip(setpoints, read_noise_maps):
        pooled.setdefault(g, []).append(np.ravel(np.asarray(m, dtype=np.float64)))
    medians = {g: float(np.median(np.concatenate(ms))) for g, ms in pooled.items()}
    if not all(np.isfinite(m) and m > 0 for m in medians.values()):
        raise InputError(f"read-noise medians must be positive and finite, got {medians}")
    if len(medians) < 2:
        return []
    ordered = sorted(medians)
    g0 = ordered[0]
    ref = medians[g0]
    messages = []
    for g in ordered[1:]:
        growth = medians[g] / ref - 1.0
        if growth > threshold:
            messages.append(
                f"read noise at EM gain set-point {g:g} (median {medians[g]:.1f} ADU) is "
                f"{100 * growth:.0f} % above that at set-point {g0:g} ({ref:.1f} ADU): the "
                "dark frames probably contain clock-induced charge, which the EM register "
                "multiplies, so this read noise is not pure Gaussian read-out noise. It "
                "hardly moves a calibration from light of hundreds of e- per pixel; for "
                f"faint signals at {g:g}x (a few e- per pixel, photon counting) take the "
                f"amplifier's read noise from set-point {g0:g}, {ref:.1f} ADU"
            )
    return messages


def map_variances(offset, read_noise, dark_frames, poisson_normal):
    """The offset and read-noise maps' own variances (ADU², each the maps' shape) from
    the ``dark_frames`` n they were computed from: σ²/n for the offset (a mean's) and
    σ²/(2(n−1)) for the read noise (an SD's); where the ADC's rounding is in the model
    (:mod:`emccdcal.model.adc`: a 1× dark's pixels below 2 ADU) the maps are a rounded
    normal's fit and their variances its inverse Fisher information over n.
    ``(None, None)`` where n is unknown (maps taken as exact).

    >>> o, r = map_variances(np.array([100.0]), np.array([10.0]), 101, False)
    >>> float(o[0]), float(r[0])
    (0.9900990099009901, 0.5)
    """
    from ..model import adc

    if dark_frames is None:
        return None, None
    offset, read_noise = np.asarray(offset, dtype=float), np.asarray(read_noise, dtype=float)
    sigma2 = read_noise**2
    offset_var, read_noise_var = sigma2 / dark_frames, sigma2 / (2.0 * (dark_frames - 1))
    # (a stuck pixel's read noise 0 has no information to invert: its maps are exact)
    rounding = adc.rounds(poisson_normal, read_noise) & np.isfinite(offset) & (read_noise > 0)
    if rounding.any():
        cov = np.linalg.inv(adc.information(offset[rounding], read_noise[rounding]))
        offset_var[rounding] = cov[:, 0, 0] / dark_frames
        read_noise_var[rounding] = cov[:, 1, 1] / dark_frames
    return offset_var, read_noise_var
