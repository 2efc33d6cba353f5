"""The true EM gain from dark frames alone (``emccdcal gain-check``).

A shutter-closed frame at EM gain holds, besides the read-out's Gaussian, electrons
made by clock-induced charge and dark current before the register, which it multiplies
like photoelectrons: their counts stand out of the read noise with a scale of g/φ ADU.
With φ (e⁻/ADU) known from a calibration of the same camera and read-out mode, the
shape of those events gives the gain g. Here every pixel's dark counts are fitted by
maximum likelihood under the register model (the exact cascade, or the gamma model of
Ryan et al. 2021), with the pixel's own offset S0, read noise σ and event rate E
(e⁻/px/frame), and the gain shared by the pixels; the exact register may also hold
clock-induced charge made inside it (``register_cic``, electrons per pixel per frame
entering at a uniformly random stage, so partly multiplied), shared too.

The fit profiles the shared parameters: each pass over the pixels refits every pixel's
(ln E, S0, ln σ) at the current shared values, and sums the pixels' scores of the shared
ones (the profile's gradient, by the envelope theorem) and their expected (Fisher)
information with the pixel's own parameters eliminated (the Schur complement: what the
pixel tells of the shared ones once its nuisances are estimated); a Fisher-scoring step
follows. The standard error is that information's inverse at the maximum. Pixels are
read a band of rows at a time on every pass, so memory holds only the per-pixel
parameters, never the frames.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from .._optimize import maximize, solve
from .._util import progress
from ..data import stats
from ..data.dark import robust_start, take_pixels
from ..errors import InputError, NotConvergedError
from ..model import noise

__all__ = ["GainCheck", "check_gain", "MIN_EVENTS"]

#: Fewest counts beyond 4 σ of the read-out, over what its Gaussian puts there, to
#: attempt a fit.
MIN_EVENTS = 20
#: The Gaussian's share beyond 4 σ (one side).
_BEYOND_4_SIGMA = 3.167e-5
#: Elements of frames read at once (frames × pixels of a band of rows).
_BAND_ELEMENTS = 2**23
#: Window points (pixels × counts) evaluated together.
_WINDOW_POINTS = 2**21
#: Bounds of ln(event rate): 1e-7 to 2 electrons per pixel per frame.
_LOG_RATE = (math.log(1e-7), math.log(2.0))


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
        The register model's label (``gamma`` or ``cascade:N``).
    events : float
        Multiplied events the fit attributes to the data (Σ over pixels of rate × frames).
    event_rate : float
        Median event rate, e⁻ per pixel per frame.
    register_cic, register_cic_se : float or None
        Clock-induced charge made inside the register, e⁻/px/frame (fitted with
        ``fit_register_cic``; else the value assumed, SE None).
    pixels, frames : int
        Pixels fitted (converged) and frames per pixel.
    passes : int
        Passes over the pixels (profile steps).
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

    @property
    def relative_se(self) -> float:
        """em_gain_se / em_gain."""
        return self.em_gain_se / self.em_gain

    def frames_for(self, target_se: float) -> int:
        """Frames per pixel for a relative SE of ``target_se`` (a fraction), from this
        check's information (it grows in proportion to the frames)."""
        return int(math.ceil(self.frames * (self.relative_se / target_se) ** 2))

    def as_dict(self) -> dict:
        """The JSON record (``gain-check --json``): plain numbers and text."""
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in asdict(self).items()}


def check_gain(darks, e_per_adu: float, *, setpoint: float | None = None,
               em_model="cascade", stages: int | None = None, register_cic: float = 0.0,
               fit_register_cic: bool = False, pooled_rate: bool = True,
               adc_max: int | None = None,
               region=None, tol: float = 1e-5, max_passes: int = 25,
               progress_bars: bool = False) -> GainCheck:
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
    tol : float
        The profile's step in ln g (and in register_cic, e⁻) that ends the fit (a step
        that promises less than 1e-3 nats ends it too).
    max_passes : int
        Passes over the pixels before giving up.
    progress_bars : bool
        A progress bar over the passes.

    Returns
    -------
    GainCheck

    Raises
    ------
    InputError
        Too few events stand out of the read noise to fit a gain (the gain too low or
        the frames too few), or the stacks differ in their pixels.
    NotConvergedError
        The profile did not settle within ``max_passes``.
    """
    model = noise.as_em_model(em_model, stages)
    if fit_register_cic and not model.register.uses_stages:
        raise InputError("register_cic is a parameter of the exact register only: use "
                         "em_model='cascade'")
    phi = float(e_per_adu)
    if not (math.isfinite(phi) and phi > 0):
        raise InputError(f"e_per_adu must be a positive number, got {e_per_adu!r}")
    stacks = _select(darks, region)
    frames = sum(int(s.shape[0]) for s in stacks)
    rows, cols = (int(v) for v in stacks[0].shape[1:])
    fit = _Fit(model, phi, fit_register_cic, pooled_rate)

    # Start: each pixel's read-out from the left half of its counts (events only add
    # counts above the offset); the events' scale θ = g/φ from the pooled excess
    # cumulants (single multiplied electrons, nearly exponential: an excess variance
    # 2Eθ² and third cumulant 6Eθ³ over the read-out's, so θ = κ3 / (3 κ2)), and the
    # rate E from them.
    x = np.empty((rows * cols, 3))
    k2 = k3 = far_n = 0.0
    values = 0
    for pix, h in _bands(stacks, adc_max, rows, cols):
        S0, sigma = robust_start(h)
        dev = h.values - h.mean[:, None]
        k2 += float(np.sum(h.var - sigma**2))
        k3 += float(np.sum((h.counts * dev**3).sum(axis=1) / h.n))
        far = h.values > (S0 + 4.0 * sigma)[:, None]
        far_n += float((h.counts * far).sum())
        values += int(h.n.sum())
        x[pix, 1], x[pix, 2] = S0, np.log(sigma)
    events = far_n - _BEYOND_4_SIGMA * values  # less what the read-out alone puts there
    if events < MIN_EVENTS or not (k2 > 0 and k3 > 0):
        raise InputError(
            f"only {max(events, 0):.0f} dark counts stand out of the read noise (beyond "
            f"4 σ, more than its Gaussian puts there; at least {MIN_EVENTS} are needed): "
            "the EM gain is too low for a check from dark frames, or the frames too few")
    theta = max(k3 / (3.0 * k2), 1.5 / phi)
    x[:, 0] = np.clip(math.log(k2 / x.shape[0] / (2.0 * theta**2)), *_LOG_RATE)
    shared = np.array([math.log(theta * phi)]
                      + ([max(register_cic, 1e-3)] if fit_register_cic else [])
                      + ([float(x[0, 0])] if pooled_rate else []))
    fixed_cic = float(register_cic)

    best, previous, info, passes = -np.inf, None, None, 0
    bar = progress(range(max_passes), enabled=progress_bars, desc="gain-check", unit="pass")
    for passes in bar:
        total, grad, info, ok, events = fit.pass_over(x, shared, fixed_cic,
                                                      _bands(stacks, adc_max, rows, cols))
        if previous is not None and total < best - 1e-6 * abs(best):
            shared = 0.5 * (shared + previous)  # the step overshot: halve it
            continue
        best, previous = total, shared.copy()
        step = solve(info[None], grad[None])[0]
        # done when the step promises less than 1e-3 nats (it moves the estimates by less
        # than 5 % of their standard errors: the pixels' own fits are only that exact)
        # or is below ``tol``
        if 0.5 * float(grad @ step) < 1e-3 or np.all(np.abs(step) < tol):
            break
        step[0] = np.clip(step[0], -0.5, 0.5)
        if fit_register_cic:
            step[1] = max(step[1], -shared[1])  # register_cic ≥ 0
        if pooled_rate:
            step[-1] = np.clip(step[-1], -1.0, 1.0)
        shared = shared + step
        if pooled_rate:
            shared[-1] = np.clip(shared[-1], *_LOG_RATE)
    else:
        raise NotConvergedError(f"the gain did not settle in {max_passes} passes over "
                                "the pixels")
    bar.close()
    cov = np.linalg.inv(info)
    g = float(math.exp(shared[0]))
    rate = np.exp(x[ok, 0])  # (the pooled rate where it is pooled)
    return GainCheck(
        em_gain=g, em_gain_se=float(g * math.sqrt(cov[0, 0])),
        setpoint=None if setpoint is None else float(setpoint), e_per_adu=phi,
        em_model=model.label, events=float(events), event_rate=float(np.median(rate)),
        register_cic=float(shared[1]) if fit_register_cic else fixed_cic,
        register_cic_se=float(math.sqrt(cov[1, 1])) if fit_register_cic else None,
        pixels=int(ok.sum()), frames=frames, passes=passes + 1)


# --------------------------------------------------------------------------------------
# Reading
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
            raise InputError(f"the region holds no pixels of a {stack.shape[1]} × "
                             f"{stack.shape[2]} px frame")
        self.stack, self.top, self.cols = stack, rows.start, slice(cols.start, cols.stop)
        self.shape = (int(stack.shape[0]), len(rows), len(cols))
        self.dtype = stack.dtype

    def __getitem__(self, key):
        """``[:, r0:r1, :]`` of the region (what the bands read)."""
        frames, rows, _ = key
        return self.stack[frames, self.top + rows.start:self.top + rows.stop, self.cols]


def _bands(stacks, adc_max, rows, cols):
    """(pixel indices, histograms) of each band of rows of all the stacks' frames."""
    frames = sum(int(s.shape[0]) for s in stacks)
    band = max(1, _BAND_ELEMENTS // max(1, frames * cols))
    for r0 in range(0, rows, band):
        r1 = min(rows, r0 + band)
        block = np.concatenate([np.asarray(s[:, r0:r1, :]) for s in stacks], axis=0)
        yield slice(r0 * cols, r1 * cols), stats.histograms(block, adc_max=adc_max)


# --------------------------------------------------------------------------------------
# The likelihood of a pixel's dark counts
# --------------------------------------------------------------------------------------
class _SharedRegister:
    """Rows of pixels that share the register (gain, φ, register CIC) and differ in their
    event rate E only: the register's part of K, ``E·v(s) + c·v̄(s)``, is computed for a
    unit rate and for the CIC alone (two rows) and scaled, instead of once per pixel
    (the exact register's transform is most of the cost). Everything else is the rows'.
    """

    def __init__(self, rows, base):
        self._rows, self._base = rows, base  # base: rows (E=1, c=0) and (E=0, c)

    def __getattr__(self, name):
        return getattr(self._rows, name)

    def take(self, idx):
        return _SharedRegister(self._rows.take(idx), self._base)

    def cgf(self, s, order=0, names=()):
        if order > 1 or not np.all(s == s[:1]):  # tilted rows differ in s: row by row
            return self._rows.cgf(s, order, names)
        K, first, _ = self._base.cgf(np.repeat(s[:1], 2, axis=0), order, names)
        E = self._rows.E[:, None]
        out = {}
        for name, d in first.items():
            if name == "photoelectrons":  # ∂(E·v)/∂E = v, the same for every row
                out[name] = np.broadcast_to(d[0], s.shape)
            elif name == "register_cic":  # ∂(c·v̄)/∂c = v̄, likewise
                out[name] = np.broadcast_to(d[1], s.shape)
            else:
                out[name] = E * d[0] + d[1]
        return E * K[0] + K[1], out, {}

class _Fit:
    """Per-pixel (ln E, S0, ln σ) and the shared (ln g[, register_cic]) of one model."""

    def __init__(self, model, phi, fit_cic, pooled):
        self.model, self.phi, self.fit_cic, self.pooled = model, phi, fit_cic, pooled
        # positions in (ln E, S0, ln σ, ln g[, register_cic]) of each pixel's own
        # parameters and of the shared ones, in the order of the shared vector
        # (ln g[, register_cic][, ln E])
        self.own = [1, 2] if pooled else [0, 1, 2]
        self.common = [3] + ([4] if fit_cic else []) + ([0] if pooled else [])

    def _rows(self, E, g, cic):
        return self.model.register.rows(E, np.full(E.shape, g), np.full(E.shape, self.phi),
                                        cic)

    def _rows_at(self, x, shared, cic):
        E, S0, sigma = np.exp(x[:, 0]), x[:, 1], np.exp(x[:, 2])
        g, cic = math.exp(shared[0]), (shared[1] if self.fit_cic else cic)
        rows = _SharedRegister(self._rows(E, g, cic), self._rows(np.array([1.0, 0.0]), g,
                                                                np.array([0.0, cic])))
        return rows, S0, sigma

    def windows(self, h, x, shared, cic):
        """Windows covering the model at (x, shared), with room for the fit to move, and
        the data: (start per pixel, length). Fixed while the pixels are refitted, so
        that their likelihood is smooth."""
        rows, S0, sigma = self._rows_at(x, shared, cic)
        lo, hi = noise.window_extent(rows, S0, sigma, width=10.0)
        lo, hi = lo - 2.0 * sigma, hi + 0.5 * (hi - S0)
        start = np.minimum(np.floor(lo).astype(np.int64), h.values[:, 0])
        stop = np.maximum(np.ceil(hi).astype(np.int64), h.values.max(axis=1))
        # a count far beyond the model (a cosmic ray) does not stretch every window: it
        # is left past the window's end and floored like any value below round-off
        length = np.minimum(stop - start, 4 * (np.ceil(hi).astype(np.int64) - start) + 64)
        return start, noise.fast_len(int(length.max()) + 1)

    def evaluate(self, h, x, shared, cic, window, *, shared_too=True):
        """Log-likelihood (P,), scores at the data (P, K) and the expected (Fisher)
        information (P, K, K) in the coordinates (ln E, S0, ln σ[, ln g[,
        register_cic]]): K = 3 without ``shared_too``, the pixel's own only."""
        rows, S0, sigma = self._rows_at(x, shared, cic)
        # with the shared parameters, the register's own (the gain is θ = g/φ of the
        # gamma model, g of the exact one): its public_gradients make them the gain's
        names = ("photoelectrons", "offset", "read_noise") + (
            rows.names + ("register_cic",) * self.fit_cic if shared_too else ())
        start, n = window
        p, d1, _ = noise.window(rows, S0 - start, sigma, n, derivs=True,
                                names=tuple(dict.fromkeys(names)))
        # to the fit's coordinates: d/d ln E = E d/dE, d/d ln σ = σ d/dσ, d/d ln g = g d/dg
        columns = [d1["photoelectrons"] * rows.E[:, None], d1["offset"],
                   d1["read_noise"] * sigma[:, None]]
        if shared_too:
            g = math.exp(shared[0])
            public = self.model.register.public_gradients(
                d1, np.full((sigma.size, 1), g), np.full((sigma.size, 1), self.phi))
            columns.append(public["em_gain"] * g)
            if self.fit_cic:
                columns.append(public["register_cic"])
        d = np.stack(columns, axis=-1)  # (P, n, K)
        # values below FFT round-off of the peak are floored (an outlier's weight capped)
        floor = 1e-14 * p.max(axis=1, keepdims=True)
        flat = h.values - start[:, None]
        beyond = flat >= n
        pv = np.take_along_axis(p, np.where(beyond, 0, flat), axis=1)
        low = (pv < floor) | beyond
        pv = np.where(low, floor, pv)
        ll = np.sum(h.counts * np.log(pv), axis=1)
        dv = np.take_along_axis(d, np.where(beyond, 0, flat)[..., None], axis=1)
        scores = np.where(low[..., None], 0.0, dv / pv[..., None])
        grad = np.sum(h.counts[..., None] * scores, axis=1)
        # Σ over the window of p·s·sᵀ = d·dᵀ/p (where p is above round-off), times frames
        good = p > floor
        w = np.where(good, h.n[:, None] / np.where(good, p, 1.0), 0.0)
        info = np.swapaxes(d * w[..., None], 1, 2) @ d
        return ll, grad, info

    def pass_over(self, x, shared, cic, bands):
        """Refit every pixel at ``shared``; the total log-likelihood, the shared
        parameters' profile gradient and information, the pixels that converged and
        the events attributed to the data."""
        S, own, common = shared.size, self.own, self.common
        total, grad, info, events = 0.0, np.zeros(S), np.zeros((S, S)), 0.0
        ok_all = np.zeros(x.shape[0], bool)
        lower = np.array([_LOG_RATE[0], -np.inf, -np.inf])[own]
        upper = np.array([_LOG_RATE[1], np.inf, np.inf])[own]
        if self.pooled:
            x[:, 0] = shared[-1]
        for pix, h in bands:
            index = np.arange(pix.start, pix.stop)
            n = self.windows(h, x[index], shared, cic)[1]
            block = max(1, _WINDOW_POINTS // (n * (4 + self.fit_cic)))
            for b in range(0, index.size, block):
                part = slice(b, b + block)
                sub = take_pixels(h, part)
                start, n = self.windows(sub, x[index[part]], shared, cic)

                def evaluate(rows, xo, sub=sub, start=start, n=n, xb=x[index[part]]):
                    xf = xb[rows].copy()
                    xf[:, own] = xo
                    ll, gr, inf = self.evaluate(take_pixels(sub, rows), xf, shared, cic,
                                                (start[rows], n), shared_too=False)
                    return ll, gr[:, own], inf[:, own][:, :, own]

                opt = maximize(evaluate, x[index[part]][:, own], lower=lower, upper=upper,
                               tol=1e-5, max_iter=60, accept_rtol=1e-10)
                ok = (opt.done | opt.stuck) & np.all(np.isfinite(opt.x), axis=1)
                xb = x[index[part]]
                xb[:, own] = np.where(ok[:, None], opt.x, xb[:, own])
                x[index[part]] = xb
                ll, gr, inf = self.evaluate(sub, x[index[part]], shared, cic, (start, n))
                total += float(ll[np.isfinite(ll)].sum())  # every pixel: the same set each pass
                ok &= np.isfinite(ll)
                # the shared parameters' information with the pixel's own eliminated
                inf = inf[ok]
                a = inf[:, common][:, :, common]
                b_ = inf[:, common][:, :, own]
                schur = a - b_ @ np.linalg.solve(inf[:, own][:, :, own], np.swapaxes(b_, 1, 2))
                grad += gr[ok][:, common].sum(axis=0)
                info += schur.sum(axis=0)
                events += float((np.exp(x[index[part]][ok, 0]) * sub.n[ok]).sum())
                ok_all[index[part]] = ok
        return total, grad, info, ok_all, events

