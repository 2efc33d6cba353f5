"""The true EM gain from dark frames alone (``emccdcal gain-check``).

A shutter-closed frame at EM gain holds, besides the read-out's Gaussian, electrons
made by clock-induced charge and dark current before the register, which it multiplies
like photoelectrons: their counts stand out of the read noise with a scale of g/φ ADU.
With φ (e⁻/ADU) known from a calibration of the same camera and read-out mode, the
shape of those events gives the gain g. Here every pixel's dark counts are fitted by
maximum likelihood under the register model (the exact cascade, or the gamma model of
Ryan et al. 2021), with the pixel's own offset S0 and read noise σ, and the gain and the
event rate E (e⁻/px/frame) shared by the pixels (or each pixel its own rate); the exact
register may also hold clock-induced charge made inside it (``register_cic``, electrons
per pixel per frame entering at a uniformly random stage, so partly multiplied), shared
too.

The likelihood of a sensor's pixels, which share the register's output distribution and
differ in their read-out, is evaluated by tables (:mod:`emccdcal.model.shared_register`)
rather than an FFT window per pixel: half a million pixels cost a few seconds per pass.
All parameters are fitted at once: the information is an arrow (each pixel's own
parameters, coupled only through the shared ones), so each Newton step of the package's
optimizer (:func:`emccdcal._optimize.maximize`, the information from the outer products
of the per-count scores) is solved through the Schur complement
(:class:`emccdcal._optimize.ArrowLayout`), and that complement, summed over the pixels,
is the shared parameters' information with every pixel's own estimated: its inverse
gives the standard errors. The pixels' histograms are kept in memory where they fit
(:data:`CACHE_BYTES`), else the stacks are read again, a band of rows at a time, on
every pass.

Each pixel's own offset and read noise are incidental parameters: estimated from its
own frames only, their error leaks into the shared gain, which the maximum-likelihood
estimate overstates by an amount proportional to 1/frames (+3.9 % at 100 frames, +1.2 %
at 200, at 300× and 0.005 e⁻/px/frame; docs/gain-check.md). A half-sample jackknife
removes it: a sample of pixels (at most 16384) is fitted with all its frames and again
with each half of them; the halves' mean less the whole estimates the bias (the halves'
is twice the whole's), which is subtracted from the whole sensor's estimate. A sample
first also gives the whole fit its start.
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass, field

import numpy as np

from .._optimize import ArrowLayout, maximize, schur
from .. import _xp
from .._util import ordered_map
from .._util import progress as progress_bar
from ..defaults import DEFAULT_EM_MODEL
from ..data import stats
from ..data.dark import robust_start
from ..errors import InputError, NotConvergedError
from ..model import noise
from ..model.shared_register import MIN_READ_NOISE, SharedRegister

__all__ = ["GainCheck", "check_gain", "MIN_EVENTS", "MAX_RELATIVE_SE", "CACHE_BYTES"]

#: Fewest counts beyond 4 σ of the read-out, over what its Gaussian puts there, to
#: attempt a fit.
MIN_EVENTS = 20
#: A check whose gain has a larger relative standard error is refused as undetermined
#: (its ± would read as "agrees" with any calibration).
MAX_RELATIVE_SE = 0.25
#: The Gaussian's share beyond 4 σ (one side).
_BEYOND_4_SIGMA = 3.167e-5
#: Elements of frames read at once (frames × pixels of a band of rows).
_BAND_ELEMENTS = 2**23
#: Pixels evaluated together (their counts' arrays stay in the processor's caches).
_BLOCK = 1024
#: Histograms of at most this many bytes are kept between passes; beyond, re-read.
CACHE_BYTES = 1 << 30
#: Bounds of ln(event rate): 1e-7 to 2 electrons per pixel per frame.
_LOG_RATE = (math.log(1e-7), math.log(2.0))
#: register_cic is fitted in units of this (e⁻/px/frame), so that a step of 1 is large.
_CIC_UNIT = 0.01
#: Pixels fitted with each half of their frames for the bias correction.
_SAMPLE = 16384
#: Pixels whose model is summed for the figure's expected histogram.
_FIGURE_PIXELS = 256


@dataclass(frozen=True)
class GainCheck:
    """The EM gain found in dark frames, with what it rests on.

    Attributes
    ----------
    em_gain, em_gain_se : float
        The true mean EM gain g (dimensionless) and its standard error.
    setpoint : float or None
        The camera's EM gain set-point of the frames (as recorded or given).
    e_per_adu : float
        φ used, e⁻/ADU (taken as exact: its own error scales g alike).
    em_model : str
        The register model's label (``"gamma"``, ``"cascade, 536 stages"``).
    events : float
        Multiplied events the fit attributes to the data (Σ over pixels of rate × frames).
    event_rate : float
        Median event rate, e⁻ per pixel per frame.
    register_cic, register_cic_se : float or None
        Clock-induced charge made inside the register, e⁻/px/frame (fitted with
        ``fit_register_cic``; else the value assumed, SE None).
    pixels, frames : int
        Pixels fitted and frames per pixel.
    passes : int
        Passes over the pixels (evaluations of the likelihood).
    read_noise : float
        Median read noise of the pixels, ADU.
    em_gain_mle : float
        The maximum-likelihood estimate before the bias correction.
    bias_correction : str
        How the bias from the pixels' own parameters was removed (``"half-sample
        jackknife"``, or ``"none"``).
    device : str
        Where the tables were evaluated (:data:`emccdcal.defaults.DEVICES`).
    histogram : dict
        With ``histogram``: the pooled counts about each pixel's offset (``offset_adu``:
        counts minus the pixel's rounded S0), ``observed`` and ``expected`` under the fit
        (for the figure; not part of :meth:`as_dict`).
    """

    em_gain: float
    em_gain_se: float
    setpoint: float | None
    e_per_adu: float
    em_model: str
    events: float
    event_rate: float
    register_cic: float
    register_cic_se: float | None
    pixels: int
    frames: int
    passes: int
    read_noise: float
    em_gain_mle: float
    bias_correction: str
    device: str = "cpu"
    histogram: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def relative_se(self) -> float:
        """em_gain_se / em_gain."""
        return self.em_gain_se / self.em_gain

    def frames_for(self, target_se: float) -> int:
        """Frames per pixel for a relative SE of ``target_se`` (a fraction), from this
        check's information (it grows in proportion to the frames)."""
        return int(math.ceil(self.frames * (self.relative_se / target_se) ** 2))

    def summary(self, target_se: float | None = None) -> str:
        """One readable line (``gain-check`` without ``--json``); with ``target_se`` (a
        fraction) the frames it needs where this check falls short of it."""
        text = (
            f"em_gain {self.em_gain:.4g} ± {self.em_gain_se:.2g} "
            f"({100 * self.relative_se:.2g} %) at "
            f"{'an unknown set-point' if self.setpoint is None else f'set-point {self.setpoint:g}'}, from "
            f"{self.events:.0f} events ({self.pixels} px × {self.frames} frames, "
            f"{self.event_rate:.3g} e-/px/frame; {self.em_model}, phi "
            f"{self.e_per_adu:.4g} e-/ADU)"
        )
        if target_se is not None and self.relative_se > target_se:
            text += (
                f"; {100 * target_se:g} % needs about {self.frames_for(target_se)} "
                "frames of these pixels"
            )
        return text

    def as_dict(self) -> dict:
        """The JSON record (``gain-check --json``): plain numbers and text."""
        return {
            k: (None if isinstance(v, float) and not math.isfinite(v) else v)
            for k, v in asdict(self).items()
            if k != "histogram"
        }


def check_gain(
    darks,
    e_per_adu: float,
    *,
    setpoint: float | None = None,
    em_model=DEFAULT_EM_MODEL,
    stages: int | None = None,
    register_cic: float = 0.0,
    fit_register_cic: bool = False,
    pooled_rate: bool = True,
    adc_max: int | None = None,
    region=None,
    bias_correction: bool = True,
    histogram: bool = False,
    tol: float = 1e-3,
    max_passes: int = 60,
    progress: bool = True,
    device: str | None = None,
) -> GainCheck:
    """The EM gain of dark frames by maximum likelihood (module docstring).

    Parameters
    ----------
    darks : sequence of array_like, each (frames, rows, cols)
        Shutter-closed stacks (ADU) of one set-point and read-out mode, the same pixels;
        lazy arrays are read a band of rows at a time.
    e_per_adu : float
        φ of the camera's read-out mode, e⁻/ADU (a calibration's).
    setpoint : float, optional
        The set-point, recorded in the result.
    em_model, stages : optional
        The register model (``"cascade"``, the exact register, or ``"gamma"``).
    register_cic : float
        Clock-induced charge made inside the register, e⁻/px/frame (cascade only):
        the value assumed, or the start with ``fit_register_cic``.
    fit_register_cic : bool
        Fit ``register_cic`` as a second shared parameter (cascade only).
    pooled_rate : bool
        One event rate shared by the pixels (default), else each pixel's own. Per-pixel
        rates are incidental parameters: a pixel's few events estimate its rate and
        inform the gain at once, and the gain comes out low by about one standard error
        where a pixel holds tens of events (measured at 50× and 2000 frames of 0.01
        e⁻/px/frame); pooled, it is unbiased.
    adc_max : int, optional
        ADC maximum: counts at or above it are left out.
    region : (slice, slice), optional
        Rows and columns to use (pixels known to be dark: masked rows, overscan).
    bias_correction : bool
        Remove the bias that estimating every pixel's own offset and read noise puts
        into the gain (proportional to 1/frames: +3.5 % at 100 frames per pixel, 300×),
        by the half-sample jackknife (module docstring; default). Without it, the
        maximum-likelihood estimate itself.
    histogram : bool
        Also the pooled histogram of the counts and the fitted model's
        (:attr:`GainCheck.histogram`, for the figure).
    tol : float
        The fit ends when its next step promises less than this, nats, both in the
        shared parameters and in a typical pixel's own (they then move by less than 5 %
        of their standard errors).
    max_passes : int
        Evaluations of the likelihood before giving up.
    progress : bool
        A progress bar over the passes (default): in a notebook or on a terminal; none
        in a pipe.

    device : {"cpu", "cuda", "jax", "array-api-strict"}, optional
        Where the tables are evaluated, as :func:`emccdcal.calibrate`'s (the tables are
        built on the host and copied there once).

    Returns
    -------
    GainCheck

    Raises
    ------
    InputError
        Too few events stand out of the read noise to fit a gain (the gain too low or
        the frames too few), a gain they do not determine (relative SE above
        :data:`MAX_RELATIVE_SE`; the message says what would), a read noise below
        1.5 ADU, or stacks that differ in their pixels.
    NotConvergedError
        The fit did not settle within ``max_passes``.

    Examples
    --------
    Dark frames at 100x of a camera with clock-induced charge (the events the gain is
    read from):

    >>> import emccdcal
    >>> darks = emccdcal.simulate_frames(
    ...     0.05, em_gain=100, frames=2000, rows=8, cols=8, seed=1
    ... )
    >>> check = emccdcal.check_gain([darks], e_per_adu=3.859, setpoint=100, progress=False)
    >>> abs(check.em_gain / 100 - 1) < 4 * check.em_gain_se / 100
    True
    """
    model = noise.choose_em_model(em_model, stages)[0]
    if fit_register_cic and "register_cic" not in model.register.parameters:
        raise InputError(
            f"register_cic is not a parameter of the {model.name} register "
            "model: use one that has it ("
            + ", ".join(
                n for n in noise.EM_MODELS if "register_cic" in noise.EMModel(n).register.parameters
            )
            + ")"
        )
    phi = float(e_per_adu)
    if not (math.isfinite(phi) and phi > 0):
        raise InputError(f"e_per_adu must be a positive number, got {e_per_adu!r}")
    _xp.resolve(device)  # an unknown or missing device: one line before any work
    data = _Data(_select(darks, region), adc_max, halves=bias_correction)
    bar = progress_bar(None, enabled=progress, desc="gain-check", unit="pass")
    try:
        with _xp.computing_on(device):
            sample = _Fit(
                model, phi, data.whole_sample(), fit_register_cic, pooled_rate, on_pass=bar.update
            )
            x0 = data.start(phi, register_cic, fit_register_cic)
            xs = sample.solve(x0[data.sample], tol, max_passes)
            fit = _Fit(model, phi, data, fit_register_cic, pooled_rate, on_pass=bar.update)
            if data.sample.size == data.n.size:  # the sample is every pixel
                x, fit = xs, sample
            else:  # the sample's shared values: a start a few of their SEs from the whole's
                x0[:, sample.shared] = xs[0, sample.shared]
                x = fit.solve(x0, tol, max_passes, own_first=1)
            shared, cov = fit.shared_estimates(x)
            mle = shared.copy()
            if bias_correction:
                shared = shared - _half_sample_bias(sample, xs, data, tol, max_passes)
    finally:
        bar.close()
    passes = sample.passes + (fit.passes if fit is not sample else 0)
    names = [fit._COLUMNS[c] for c in fit.shared]
    k = names.index("ln_gain")
    g = float(math.exp(shared[k]))
    rate = np.exp(x[:, fit.column("ln_rate")])
    cic, cic_se = float(register_cic), None
    if fit_register_cic:
        j = names.index("register_cic")
        cic, cic_se = _CIC_UNIT * float(shared[j]), _CIC_UNIT * math.sqrt(cov[j, j])
    check = GainCheck(
        em_gain=g,
        em_gain_se=float(g * math.sqrt(cov[k, k])),
        setpoint=None if setpoint is None else float(setpoint),
        e_per_adu=phi,
        em_model=model.label,
        events=float(np.sum(rate * data.n)),
        event_rate=float(np.median(rate)),
        register_cic=cic,
        register_cic_se=cic_se,
        pixels=int(data.n.size),
        frames=data.frames,
        passes=passes,
        read_noise=float(np.median(np.exp(x[:, 1]))),
        em_gain_mle=float(math.exp(mle[k])),
        bias_correction="half-sample jackknife" if bias_correction else "none",
        device=device or "cpu",
        histogram=fit.histogram(x) if histogram else {},
    )
    if not check.relative_se <= MAX_RELATIVE_SE:
        raise InputError(_undetermined(check))
    return check


def _undetermined(check) -> str:
    """Why a check's gain is not determined, and what would determine it."""
    frames = check.frames_for(0.02)
    remedy = (
        f"a 2 % check needs about {frames} frames of these pixels"
        if frames <= 100 * check.frames
        else "more frames will hardly do: take the darks at a higher EM gain"
    )
    return (
        f"these dark frames do not determine the EM gain: {check.em_gain:.3g} ± "
        f"{check.em_gain_se:.2g} ({100 * check.relative_se:.0f} %) from "
        f"{check.events:.0f} events ({check.pixels} px × {check.frames} frames); an "
        f"event's scale (g/φ = {check.em_gain / check.e_per_adu:.3g} ADU) is lost in "
        f"the read noise ({check.read_noise:.3g} ADU) or the events are too few: "
        f"{remedy}"
    )


def _half_sample_bias(sample, xs, data, tol, max_passes):
    """The bias of the shared estimates from the pixels' own parameters (module
    docstring): the sample's pixels, fitted with all their frames (``xs``), fitted again
    with each half of them; the halves' mean less the whole estimates the whole's bias
    (proportional to 1/frames)."""
    whole = xs[0, sample.shared]
    halves = []
    for part in (data.half(0), data.half(1)):
        sub = _Fit(
            sample.model, sample.phi, part, sample.fit_cic, sample.pooled, on_pass=sample.on_pass
        )
        halves.append(sub.shared_estimates(sub.solve(xs, tol, max_passes))[0])
        sample.passes += sub.passes
    return 0.5 * (halves[0] + halves[1]) - whole


# --------------------------------------------------------------------------------------
# The data: each usable pixel's histogram, by bands of rows
# --------------------------------------------------------------------------------------
def _select(darks, region):
    from ..data.dark import as_stack

    stacks = [as_stack(d, "dark stack") for d in darks]
    if not stacks:
        raise InputError("no dark stacks given")
    if region is not None:
        stacks = [_Region(s, region) for s in stacks]
    shapes = {tuple(int(v) for v in s.shape[1:]) for s in stacks}
    if len(shapes) > 1:
        raise InputError(f"the dark stacks differ in their frames' shape: {sorted(shapes)}")
    return stacks


class _Region:
    """A stack seen through (rows, cols) slices, read lazily."""

    def __init__(self, stack, region):
        if any(part.step not in (None, 1) for part in region):
            raise InputError("a region's rows and columns are ranges without a step")
        rows, cols = (range(*part.indices(int(n))) for part, n in zip(region, stack.shape[1:]))
        if not rows or not cols:
            raise InputError(
                f"the region holds no pixels of a {stack.shape[1]} × {stack.shape[2]} px frame"
            )
        self.stack, self.top, self.cols = stack, rows.start, slice(cols.start, cols.stop)
        self.shape = (int(stack.shape[0]), len(rows), len(cols))
        self.dtype = stack.dtype

    def __getitem__(self, key):
        """``[:, r0:r1, :]`` of the region (what the bands read)."""
        frames, rows, _ = key
        return self.stack[frames, self.top + rows.start : self.top + rows.stop, self.cols]


class _Data:
    """The usable pixels' histograms (two or more frames, not all equal), band by band:
    kept in memory where they fit in :data:`CACHE_BYTES`, else read again; and those of
    a sample of them (:data:`_SAMPLE` pixels spread evenly), fitted first for a start,
    with ``halves`` also from each half of the frames, for the bias correction."""

    def __init__(self, stacks, adc_max, *, halves=False):
        self.stacks, self.adc_max = stacks, adc_max
        self.frames = sum(int(s.shape[0]) for s in stacks)
        self.rows, self.cols = (int(v) for v in stacks[0].shape[1:])
        every = max(1, math.ceil(self.rows * self.cols / _SAMPLE))
        self.halves = halves
        self.cache, size, n, sample, parts = [], 0, [], [], []
        for h, chosen, split in self._read(every):
            size += h.values.size * 8
            self.cache.append(h if size <= CACHE_BYTES else None)
            sample.append(chosen + sum(x.size for x in n))
            n.append(h.n)
            parts.append(split)
        self.n = np.concatenate(n)
        if not self.n.size:
            raise InputError("no pixel has two or more distinct unsaturated counts")
        self.sample = np.concatenate(sample)
        self._parts = [[part[k] for part in parts if part[k].n.size] for k in range(3)]

    def _read(self, every):
        """Per band: its histograms, the sampled pixels (indices among the band's usable
        ones) and their histograms of all frames and of each half (as _Memory parts)."""
        band = max(1, _BAND_ELEMENTS // max(1, self.frames * self.cols))
        half = self.frames // 2

        def histograms(r0):
            r1 = min(self.rows, r0 + band)
            block = np.concatenate([np.asarray(s[:, r0:r1, :]) for s in self.stacks], axis=0)
            h = _usable(block, self.adc_max)
            chosen = np.zeros(0, dtype=np.intp)
            split = (_Histograms.empty(),) * 3
            if every:
                pixel = np.arange(r0 * self.cols, r1 * self.cols)[h.used]  # raw index
                chosen = np.flatnonzero(pixel % every == 0)
                split = (h.part(chosen),) + split[1:]
            if every and self.halves:  # the sample's pixels usable in each half too
                flat = block.reshape(block.shape[0], -1)[:, h.used][:, chosen]
                halves = [
                    _usable(flat[:half, None, :], self.adc_max),
                    _usable(flat[half:, None, :], self.adc_max),
                ]
                keep = halves[0].used & halves[1].used
                chosen = chosen[keep]
                split = (h.part(chosen),) + tuple(
                    x.part(np.flatnonzero(keep[x.used])) for x in halves
                )
            return h, chosen, split

        yield from ordered_map(histograms, range(0, self.rows, band), min(2, _threads()))

    def bands(self):
        """Each band's histograms, in order (from memory, or read again)."""
        if all(h is not None for h in self.cache):
            yield from self.cache
            return
        for cached, (h, _, _) in zip(self.cache, self._read(0)):
            yield cached if cached is not None else h

    def whole_sample(self):
        """The sampled pixels' histograms of all frames."""
        return _Memory(self._parts[0], self.frames)

    def half(self, k):
        """The sampled pixels' histograms of half ``k`` (0, 1) of the frames."""
        half = self.frames // 2
        return _Memory(self._parts[1 + k], half if k == 0 else self.frames - half)

    def start(self, phi, register_cic, fit_register_cic):
        """Starting values (pixels × columns of :class:`_Fit`): each pixel's read-out from
        the core of its counts (:func:`_core_start`); the
        events' scale θ = g/φ from the pooled excess cumulants (single multiplied
        electrons, nearly exponential: an excess variance 2Eθ² and third cumulant 6Eθ³
        over the read-out's, so θ = κ3 / (3 κ2)), and the rate E from them."""
        own, k2, k3, far_n, values = [], 0.0, 0.0, 0.0, 0
        for h in self.bands():
            counts, v = h.counts.astype(float), h.values.astype(float)
            S0, sigma = _core_start(h, v, counts)
            mean = np.sum(counts * v, axis=1) / h.n
            dev = v - mean[:, None]
            k2 += float(np.sum(np.sum(counts * dev**2, axis=1) / (h.n - 1) - sigma**2))
            k3 += float(np.sum(np.sum(counts * dev**3, axis=1) / h.n))
            far_n += float(np.sum(counts * (v > (S0 + 4.0 * sigma)[:, None])))
            values += int(h.n.sum())
            own.append(np.stack([S0, np.log(sigma)], axis=1))
        events = far_n - _BEYOND_4_SIGMA * values  # less what the read-out alone puts there
        if events < MIN_EVENTS or not (k2 > 0 and k3 > 0):
            raise InputError(
                f"only {max(events, 0):.0f} dark counts stand out of the read noise "
                f"(beyond 4 σ, more than its Gaussian puts there; at least {MIN_EVENTS} are "
                "needed): the EM gain is too low for a check from dark frames, or the "
                "frames too few"
            )
        own = np.concatenate(own)
        _refuse_lit(np.exp(own[:, 1]))
        theta = max(k3 / (3.0 * k2), 1.5 / phi)
        rate = float(np.clip(math.log(k2 / self.n.size / (2.0 * theta**2)), *_LOG_RATE))
        P = own.shape[0]
        cic = max(register_cic, 1e-3) if fit_register_cic else register_cic
        return np.column_stack(
            [own, np.full(P, rate), np.full(P, math.log(theta * phi)), np.full(P, cic / _CIC_UNIT)]
        )


def _threads() -> int:
    return max(
        1,
        len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1),
    )


class _Memory:
    """Histograms held in memory, with what :class:`_Fit` asks of data."""

    def __init__(self, parts, frames):
        self.parts, self.frames = parts, frames
        self.n = np.concatenate([h.n for h in parts])

    def bands(self):
        return iter(self.parts)


def _refuse_lit(read_noise) -> None:
    """Refuse, before any table is built, pixels that light reaches: the core of their
    counts spreads more than :data:`emccdcal.data.dark.MAX_READ_OUT_GROWTH` times as wide
    as the read-out of the darkest tenth of the pixels (a movie's lit part, without
    ``--region``); their tables would span thousands of read noises, gigabytes deep."""
    from ..data.dark import MAX_READ_OUT_GROWTH

    reference = float(np.quantile(read_noise, 0.1))
    lit = read_noise > MAX_READ_OUT_GROWTH * reference
    if lit.any():
        raise InputError(
            f"{int(lit.sum())} of {lit.size} pixels are not dark: their counts spread "
            f"{float(np.median(read_noise[lit])):.4g} ADU wide about their centre, more "
            f"than {MAX_READ_OUT_GROWTH:g} times the read noise of the darkest pixels "
            f"({reference:.4g} ADU): light reaches them; give --region with the "
            "masked or covered rows only (a region of dark frames)"
        )


def _usable(block, adc_max):
    """The histograms of the pixels of ``block`` (frames, rows, cols) that a fit can use
    (two or more unsaturated frames, not all equal), compactly, with that mask."""
    h = stats.histograms(block, adc_max=adc_max)
    use = (h.n >= 2) & (h.max > h.min)
    k = int(np.max(np.sum(h.counts[use] > 0, axis=1), initial=1))
    return _Histograms(
        h.values[use, :k].astype(np.int32), h.counts[use, :k].astype(np.float32), h.n[use], use
    )


def _core_start(h, values, counts, half_width=2.5):
    """Each pixel's offset and read noise from the counts within ``half_width`` read
    noises of its centre (their mean, and their variance over that of a Gaussian cut
    there), twice, from the median and the left half-width: events, above the offset,
    hardly reach into the core."""
    S0, sigma = robust_start(h)
    c = half_width
    inside = math.erf(c / math.sqrt(2.0))
    shrink = 1.0 - 2.0 * c * math.exp(-0.5 * c * c) / math.sqrt(2.0 * math.pi) / inside
    for _ in range(2):
        w = counts * (np.abs(values - S0[:, None]) <= c * sigma[:, None])
        n = np.maximum(w.sum(axis=1), 1.0)
        mean = np.sum(w * values, axis=1) / n
        var = np.sum(w * (values - mean[:, None]) ** 2, axis=1) / np.maximum(n - 1.0, 1.0)
        S0, sigma = mean, np.maximum(np.sqrt(var / shrink), MIN_READ_NOISE)
    return S0, sigma


@dataclass
class _Histograms:
    values: np.ndarray  # (P, K) int32, ADU
    counts: np.ndarray  # (P, K) float32
    n: np.ndarray  # (P,)
    used: np.ndarray = None  # which pixels of the block read these are (bool)

    def part(self, index):
        """These pixels' histograms, cut to the longest of them (the padding of a band's
        longest is work for nothing)."""
        counts = self.counts[index]
        k = int(np.max(np.count_nonzero(counts, axis=1), initial=1))
        return _Histograms(self.values[index][:, :k], counts[:, :k], self.n[index])

    @staticmethod
    def empty():
        return _Histograms(
            np.zeros((0, 1), np.int32), np.zeros((0, 1), np.float32), np.zeros(0, np.int64)
        )


# --------------------------------------------------------------------------------------
# The fit
# --------------------------------------------------------------------------------------
class _Fit:
    """Every pixel's columns (offset, ln σ, ln E, ln g, register_cic / _CIC_UNIT): which
    are the pixel's own and which are shared, the likelihood of all pixels, and the
    information of the last pass."""

    _COLUMNS = ("offset", "ln_read_noise", "ln_rate", "ln_gain", "register_cic")

    def __init__(self, model, phi, data, fit_cic, pooled, on_pass=None):
        self.model, self.phi, self.data = model, phi, data
        self.fit_cic, self.pooled = fit_cic, pooled
        c = self.column
        self.own = [c("offset"), c("ln_read_noise")] + ([] if pooled else [c("ln_rate")])
        self.shared = (
            [c("ln_gain")]
            + ([c("register_cic")] if fit_cic else [])
            + ([c("ln_rate")] if pooled else [])
        )
        lower = np.array([-np.inf, math.log(MIN_READ_NOISE), _LOG_RATE[0], math.log(1.01), 0.0])
        upper = np.array([np.inf, np.inf, _LOG_RATE[1], math.log(1e5), np.inf])
        self.layout = ArrowLayout(
            data.n.size, len(self._COLUMNS), self.shared, self.own, lower, upper
        )
        self.template = np.zeros((data.n.size, len(self._COLUMNS)))
        self.passes, self.on_pass, self._last = 0, on_pass, None

    def column(self, name):
        return self._COLUMNS.index(name)

    def solve(self, x0, tol, max_passes, *, own_first=0):
        """Every pixel's columns at the maximum of the likelihood, from ``x0``; with
        ``own_first``, that many passes first move the pixels' own parameters only (the
        shared held at their start: a good start of the shared ones is not thrown off by
        the first step of pixels far from theirs)."""
        packed = self.layout.pack(x0)
        if own_first:
            k = len(self.shared)
            lower, upper = self.layout.lower.copy(), self.layout.upper.copy()
            lower[:k] = upper[:k] = packed[0, :k]
            packed = maximize(
                self.evaluate,
                packed,
                lower=lower,
                upper=upper,
                tol=tol,
                max_iter=own_first,
                accept_rtol=1e-12,
                step=self.layout.step,
                decrement=self.layout.decrement,
            ).x
        opt = maximize(
            self.evaluate,
            packed,
            lower=self.layout.lower,
            upper=self.layout.upper,
            tol=tol,
            max_iter=max_passes,
            accept_rtol=1e-12,
            step=self.layout.step,
            decrement=self.layout.decrement,
        )
        if not opt.done[0]:
            raise NotConvergedError(
                f"the gain did not settle in {self.passes} passes over the pixels"
            )
        return self.layout.unpack(opt.x, self.template)

    def shared_estimates(self, x):
        """The shared parameters (in the order of ``self.shared``) and their covariance
        at ``x``: the inverse of the information's Schur complement, every pixel's own
        parameters eliminated."""
        info = self.evaluate(None, self.layout.pack(x))[2]
        S, _, _ = schur(info, self.shared, self.own)
        return x[0, self.shared], np.linalg.inv(S[0])

    def tables(self, x, per_pixel_rates=None):
        """The shared register's tables at the shared values of ``x`` (pixel rows)."""
        c = self.column
        names = (
            ("ln_gain",)
            + (("register_cic",) if self.fit_cic else ())
            + (("ln_rate",) if self.pooled else ())
        )
        rate = np.exp(x[:, c("ln_rate")])
        return SharedRegister(
            self.model.register,
            math.exp(x[0, c("ln_gain")]),
            self.phi,
            np.exp(x[:, c("ln_read_noise")]),
            rate=float(rate[0] if self.pooled else rate.max()),
            register_cic=_CIC_UNIT * float(x[0, c("register_cic")]),
            per_pixel_rate=not self.pooled,
            shared=names,
        )

    def evaluate(self, rows, packed):
        """The optimizer's objective: the whole sensor's log-likelihood, its gradient
        and each pixel's (D × D) information, at ``packed`` (1, ·); the last pass's
        again where it is asked for the same point (a second fit's start)."""
        if self._last is not None and np.array_equal(self._last[0], packed):
            return self._last[1]
        result = self._evaluate(packed)
        self._last = (packed.copy(), result)
        return result

    def _evaluate(self, packed):
        x = self.layout.unpack(packed, self.template)
        table = self.tables(x)
        # the tables' columns → this fit's: own (offset, ln σ[, ln E]) then the shared
        to = (
            [self.column("offset"), self.column("ln_read_noise")]
            + ([] if self.pooled else [self.column("ln_rate")])
            + [self.column(n) for n in table.shared]
        )
        scale = np.ones(len(to))
        if self.fit_cic:
            scale[len(to) - len(table.shared) + table.shared.index("register_cic")] = _CIC_UNIT
        D = len(self._COLUMNS)
        grad = np.zeros((x.shape[0], D))
        info = np.zeros((x.shape[0], D, D))
        to = np.array(to)
        sigma = np.exp(x[:, 1])
        # Fisher scoring where the rate is pooled: each pixel's expected information is
        # its frames times one frame's at its reference read noise; with rates of their
        # own, the outer products of the scores
        expected = table.information() if self.pooled else None
        where = _xp.engine()  # (the blocks' threads do not inherit this thread's choice)

        def block(item):  # blocks are independent: threads overlap them (NumPy frees the GIL)
            sl, h = item
            rates = None if self.pooled else np.exp(x[sl, self.column("ln_rate")])
            ll, g_, outer, _ = table.evaluate(
                h.values, h.counts, x[sl, 0], sigma[sl], rates, outer=not self.pooled, xp=where
            )
            if self.pooled:
                outer = h.n[:, None, None] * expected[table.classes(sigma[sl])]
            grad[sl, to] = g_ * scale
            info[sl, to[:, None], to[None, :]] = outer * scale[:, None] * scale[None, :]
            return float(ll.sum())

        total = sum(ordered_map(block, self._blocks(), _threads()))
        self.passes += 1
        if self.on_pass is not None:
            self.on_pass(1)
        return np.array([total]), self.layout.gradient(grad), info[None]

    def _blocks(self):
        """(pixel slice, histograms) of every block of :data:`_BLOCK` pixels."""
        first = 0
        for h in self.data.bands():
            for b in range(0, h.n.size, _BLOCK):
                sl = slice(b, min(h.n.size, b + _BLOCK))
                yield slice(first + sl.start, first + sl.stop), h.part(sl)
            first += h.n.size

    def histogram(self, x):
        """The pooled counts about each pixel's rounded offset, observed and expected
        (the model summed over up to :data:`_FIGURE_PIXELS` pixels spread evenly, scaled
        to all of them)."""
        P = x.shape[0]
        base = np.rint(x[:, 0]).astype(np.int64)
        shifts, weights = [], []
        for sl, h in self._blocks():
            keep = h.counts > 0
            shifts.append((h.values - base[sl, None])[keep])
            weights.append(h.counts[keep])
        shift, weight = np.concatenate(shifts), np.concatenate(weights)
        lo = int(shift.min())
        observed = np.bincount(shift - lo, weights=weight)
        offsets = np.arange(lo, lo + observed.size)
        pick = np.unique(np.linspace(0, P - 1, min(P, _FIGURE_PIXELS)).astype(int))
        rates = None if self.pooled else np.exp(x[pick, self.column("ln_rate")])
        p = self.tables(x).pmf(
            base[pick, None] + offsets[None, :], x[pick, 0], np.exp(x[pick, 1]), rates
        )
        n = self.data.n
        expected = (n[pick, None] * p).sum(axis=0) * (n.sum() / n[pick].sum())
        return {
            "offset_adu": offsets.tolist(),
            "observed": observed.tolist(),
            "expected": expected.tolist(),
        }
