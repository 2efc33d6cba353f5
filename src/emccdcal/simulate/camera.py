"""Synthetic EMCCD acquisitions with known truth.

The generative model is the paper's (docs/methods.md) plus the effects a real camera adds.
For each pixel and frame t:

1. electrons entering the EM register ``n ~ Poisson(E_t + c)``: ``photoelectrons`` E
   (e⁻ per pixel per frame, optionally drifting linearly over the acquisition, see
   ``drift``) plus clock-induced charge ``cic`` c (e⁻ per pixel per frame, also present
   in dark frames and multiplied like photoelectrons);
2. EM multiplication with true mean gain g (``em_gain``): ``multiplication="cascade"``
   (the default, a real register), the exact Bernoulli cascade of ``stages`` stages
   (:func:`emccdcal.model.cascade_sampling.sample_cascade`, F² < 2), or ``"gamma"``,
   ``X ~ Gamma(shape n, scale g)`` (the paper's model and simulations, excess-noise
   factor F² = 2); at ``em_gain == 1`` no multiplication at all, X = n (the 1× set-point);
3. read-out: ``counts = round(S0 + X/φ + N(0, σ²))`` clipped to ``[0, 2**adc_bits − 1]``
   (``offset`` S0 and ``read_noise`` σ in ADU, ``e_per_adu`` φ in e⁻/ADU).

The read-out noise is continuous and the count is rounded, so the standard deviation of
dark counts (the ``read_noise`` maps written next to the stacks) is ≈ sqrt(σ² + 1/12),
not σ (Sheppard's correction); the noise model's ``read_noise`` is the former.

:func:`simulate_frames` is the in-memory core (one stack, no files).
:func:`simulate_gain_series` and :func:`simulate_intensity_series` write what a real
calibration session produces: uint16 TIFF stacks ``(frames, rows, cols)``, a dark stack
per set-point with its per-pixel ``offset`` and ``read_noise`` maps (float32 TIFF, ADU),
a ``manifest.toml`` in the manifest format (docs/manifest.md), and ``truth.json`` with the true values.
:func:`simulate_beads` writes bead movies for the bead validation (isolated emitters with
a pixel-integrated Gaussian PSF, :func:`bead_scene`) with the same camera, plus
``truth_calibration.nc``, the true calibration in the result contract.
``emccdcal simulate gain-series|intensity-series|beads -o OUT`` is the command line.
``docs/simulation.md`` and ``docs/beads.md`` have examples.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from typing import Any
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .. import defaults
from .._util import check_int, check_map, check_number
from ..errors import OptionError
from ..defaults import DEFAULT_STAGES
from ..model import noise
from ..model.noise import EMModel

__all__ = [
    "Camera",
    "simulate_frames",
    "expected_moments",
    "default_em_gain",
    "offset_at_setpoint",
    "PAPER_SETPOINTS",
    "PAPER_EM_GAIN",
    "PAPER_LEVELS",
    "DEFAULT_OFFSET",
    "DEFAULT_OFFSET_DROP",
]

#: Gain set-points of the paper's gain series.
PAPER_SETPOINTS = (1, 5, 25, 100, 300)
#: True mean EM gain at the paper's set-points (our GS fit of the authors' sample data,
#: docs/validation.md case 10). Other set-points default to a true gain equal to the set-point.
PAPER_EM_GAIN = {1: 1.0, 5: 4.78, 25: 22.95, 100: 90.06, 300: 261.6}
#: Photoelectrons (e⁻ per pixel per frame) of the default intensity series: six
#: log-spaced levels, labelled L1 … L6.
PAPER_LEVELS = (2000.0, 4000.0, 8000.0, 16000.0, 32000.0, 64000.0)

DEFAULT_OFFSET = defaults.DEFAULT_OFFSET
DEFAULT_OFFSET_DROP = defaults.DEFAULT_OFFSET_DROP
_DEFAULTS: dict[str, Any] = defaults.CAMERA_SIMULATION
#: Elements (frames × pixels) simulated at a time; fixes the random stream, so it is a
#: constant, not a tuning knob.
_CHUNK_ELEMENTS = 2**20

_UNITS = {
    "photoelectrons": "e-/px/frame",
    "cic": "e-/px/frame",
    "e_per_adu": "e-/ADU",
    "em_gain": "dimensionless",
    "em_gain_setpoint": "dimensionless",
    "offset": "ADU",
    "offset_drop": "ADU per decade of set-point",
    "offset_spread": "ADU",
    "read_noise": "ADU",
    "drift": "fraction of photoelectrons, first to last frame",
    "excess_noise_factor": "dimensionless",
    "mean": "ADU",
    "variance": "ADU^2",
    "adc_bits": "bits",
}


@dataclass(frozen=True)
class Camera:
    """The simulated camera and session: what every acquisition of a simulation shares.

    The simulators (:func:`emccdcal.simulate.series.simulate_gain_series`,
    :func:`~emccdcal.simulate.series.simulate_intensity_series`,
    :func:`~emccdcal.simulate.beads.simulate_beads`) take a ``camera`` or its fields as
    keyword arguments. Values are checked on construction (:class:`OptionError`).

    Attributes
    ----------
    rows, cols : int
        Sensor size, px (32 × 32).
    frames : int
        Frames per signal stack (5000).
    dark_frames : int
        Frames per dark stack (≥ 2; default: ``frames``).
    e_per_adu : float
        φ, e⁻/ADU (3.859).
    offset : float
        Offset at set-point 1, ADU (587.7).
    offset_drop : float
        Drop of the offset per decade of set-point, ADU (8.68; 0 for none),
        :func:`offset_at_setpoint`.
    offset_spread : float
        SD of a fixed per-pixel offset pattern added at every set-point, ADU (0.5; 0 for
        none); written to ``truth-offset-pattern.tif``.
    read_noise : float
        σ of the Gaussian read-out noise before rounding, ADU (15.5).
    multiplication : {"cascade", "gamma"}
        EM register model (module docstring; default the exact cascade).
    stages : int
        Stages of the cascade register (536).
    cic : float
        Clock-induced charge, e⁻ per pixel per frame (0), multiplied like photoelectrons.
    drift : float
        Linear drift of the illumination over each acquisition, as a fraction of E from
        the first frame to the last (abs(drift) ≤ 2; 0).
    adc_bits : int
        ADC resolution, bits (1–16; 16): counts are clipped to ``[0, 2**adc_bits − 1]``.
    cascade_method : {"pmf", "stages"}
        Exact cascade sampler (:func:`emccdcal.model.cascade_sampling.sample_cascade`).

    Examples
    --------
    >>> import emccdcal, tempfile
    >>> camera = emccdcal.Camera(rows=4, cols=8, frames=500, e_per_adu=4.0)
    >>> camera.shape, round(camera.excess_noise_factor(300), 3)  # F² of a 536-stage register
    ((4, 8), 1.976)
    >>> sim = emccdcal.simulate_gain_series(
    ...     tempfile.mkdtemp(), camera=camera, setpoints=(1, 10), seed=1, progress=False
    ... )  # doctest: +SKIP
    """

    rows: int = _DEFAULTS["rows"]
    cols: int = _DEFAULTS["cols"]
    frames: int = _DEFAULTS["frames"]
    dark_frames: int | None = _DEFAULTS["dark_frames"]
    e_per_adu: float = _DEFAULTS["e_per_adu"]
    offset: float = _DEFAULTS["offset"]
    offset_drop: float = _DEFAULTS["offset_drop"]
    offset_spread: float = _DEFAULTS["offset_spread"]
    read_noise: float = _DEFAULTS["read_noise"]
    multiplication: str = _DEFAULTS["multiplication"]
    stages: int = _DEFAULTS["stages"]
    cic: float = _DEFAULTS["cic"]
    drift: float = _DEFAULTS["drift"]
    adc_bits: int = _DEFAULTS["adc_bits"]
    cascade_method: str = _DEFAULTS["cascade_method"]

    def __post_init__(self):
        frames = check_int("frames", self.frames)
        dark = frames if self.dark_frames is None else self.dark_frames
        checked = dict(
            rows=check_int("rows", self.rows),
            cols=check_int("cols", self.cols),
            frames=frames,
            dark_frames=check_int("dark_frames", dark, minimum=2),
            e_per_adu=check_number("e_per_adu", self.e_per_adu, positive=True),
            offset=check_number("offset", self.offset, minimum=0.0),
            offset_drop=check_number("offset_drop", self.offset_drop),
            offset_spread=check_number("offset_spread", self.offset_spread, minimum=0.0),
            read_noise=check_number("read_noise", self.read_noise, positive=True),
            multiplication=_multiplication(self.multiplication),
            stages=check_int("stages", self.stages),
            cic=check_number("cic", self.cic, minimum=0.0),
            drift=check_number("drift", self.drift, minimum=-2.0, maximum=2.0),
            adc_bits=check_int("adc_bits", self.adc_bits, minimum=1, maximum=16),
            cascade_method=_cascade_method(self.cascade_method),
        )
        for name, value in checked.items():
            object.__setattr__(self, name, value)

    @classmethod
    def of(cls, camera: Camera | None = None, defaults: dict | None = None, **options) -> Camera:
        """``camera`` with ``options`` replaced, or a new camera of ``defaults`` and ``options``.

        An unknown option name is an :class:`OptionError` that suggests the closest field.
        """
        fields = [f.name for f in dataclasses.fields(cls)]
        for key in options:
            if key not in fields:
                close = difflib.get_close_matches(key, fields, n=1)
                hint = f"; did you mean {close[0]!r}?" if close else ""
                raise OptionError(
                    f"unknown camera option {key!r}{hint} (options: {', '.join(fields)})"
                )
        if camera is not None:
            return dataclasses.replace(camera, **options)
        return cls(**{**(defaults or {}), **options})

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols)."""
        return (self.rows, self.cols)

    def register(self) -> dict:
        """The keyword arguments of :func:`simulate_frames` and :func:`expected_moments`
        that describe the camera rather than the acquisition."""
        return dict(
            e_per_adu=self.e_per_adu,
            read_noise=self.read_noise,
            multiplication=self.multiplication,
            stages=self.stages,
            cic=self.cic,
        )

    def excess_noise_factor(self, em_gain: float) -> float:
        """F² of the register at a true gain: 1 without multiplication, 2 for the gamma
        model, the exact value for the cascade."""
        return float(
            EMModel(self.multiplication, self.stages).register.excess_noise_factor(
                np.asarray(float(em_gain))
            )
        )


def _multiplication(value) -> str:
    known = noise.EM_MODELS  # plug-ins included, as they are now
    if value not in known:
        raise OptionError(
            f"multiplication must be one of {', '.join(map(repr, known))}, got {value!r}"
        )
    return value


def _cascade_method(value) -> str:
    if value not in ("pmf", "stages"):
        raise OptionError(f"cascade_method must be 'pmf' or 'stages', got {value!r}")
    return value


def _shape(rows, cols, *maps) -> tuple[int, int]:
    inferred = next((np.shape(m) for m in maps if np.ndim(m) == 2), None)
    r = (
        check_int("rows", rows)
        if rows is not None
        else (inferred[0] if inferred else _DEFAULTS["rows"])
    )
    c = (
        check_int("cols", cols)
        if cols is not None
        else (inferred[1] if inferred else _DEFAULTS["cols"])
    )
    return int(r), int(c)


def default_em_gain(setpoint) -> float:
    """True mean EM gain used by default at a set-point.

    The paper's values at 5/25/100/300 (:data:`PAPER_EM_GAIN`), 1 at set-point 1, else
    the set-point itself.

    Examples
    --------
    >>> default_em_gain(25), default_em_gain(50)
    (22.95, 50.0)
    """
    s = check_number("em_gain_setpoint", setpoint, minimum=1.0)
    return float(PAPER_EM_GAIN.get(s, s))


def offset_at_setpoint(setpoint, offset=DEFAULT_OFFSET, offset_drop=DEFAULT_OFFSET_DROP) -> float:
    """Offset level at a gain set-point, ADU: ``offset − offset_drop·log10(setpoint)``.

    Parameters
    ----------
    setpoint : float
        EM gain set-point (≥ 1).
    offset : float, optional
        Offset at set-point 1, ADU (default 587.7).
    offset_drop : float, optional
        Drop of the offset per decade of set-point, ADU (default 8.68; 0 for none).

    Examples
    --------
    >>> round(offset_at_setpoint(300), 1)
    566.2
    """
    s = check_number("em_gain_setpoint", setpoint, minimum=1.0)
    return float(offset - offset_drop * math.log10(s))


def _drift_factors(frames: int, drift: float) -> np.ndarray:
    """Photoelectron rate of each frame relative to the mean: ``1 + drift·(t/(T−1) − ½)``."""
    if frames == 1 or drift == 0:
        return np.ones(frames)
    return 1.0 + drift * (np.arange(frames) / (frames - 1) - 0.5)


# --------------------------------------------------------------------------------------
# In-memory core
# --------------------------------------------------------------------------------------
def simulate_frames(
    photoelectrons,
    em_gain=1.0,
    e_per_adu=_DEFAULTS["e_per_adu"],
    offset=DEFAULT_OFFSET,
    read_noise=_DEFAULTS["read_noise"],
    *,
    frames=_DEFAULTS["frames"],
    rows=None,
    cols=None,
    multiplication=defaults.DEFAULT_EM_MODEL,
    stages=DEFAULT_STAGES,
    cic=0.0,
    drift=0.0,
    adc_bits=16,
    seed=None,
    cascade_method="pmf",
    callback: Callable[[int], object] | None = None,
    varying=(),
    register_cic=0.0,
) -> np.ndarray:
    """Simulate one stack of raw EMCCD counts in memory.

    Parameters
    ----------
    photoelectrons : float or array_like (rows, cols)
        E, mean photoelectrons per pixel per frame (e⁻, ≥ 0), averaged over the frames.
    em_gain : float, optional
        g, true mean EM gain (dimensionless, ≥ 1; 1 = no multiplication). Default 1.
    e_per_adu : float, optional
        φ, ADU conversion factor, e⁻/ADU (default 3.859).
    offset : float or array_like (rows, cols), optional
        S0, offset, ADU (≥ 0; default 587.7).
    read_noise : float or array_like (rows, cols), optional
        σ, standard deviation of the Gaussian read-out noise before rounding, ADU
        (> 0; default 15.5).
    frames : int, optional
        Number of frames (default 5000).
    rows, cols : int, optional
        Frame size, px; default: the shape of a map argument, else 32 × 32.
    multiplication : {"cascade", "gamma"}, optional
        EM register model (module docstring; default the exact cascade). Ignored at
        ``em_gain == 1``.
    stages : int, optional
        Stages of the cascade register (default 536).
    cic : float, optional
        Clock-induced charge, e⁻ per pixel per frame (≥ 0; default 0), multiplied like
        photoelectrons.
    drift : float, optional
        Linear drift of the illumination: the photoelectron rate goes from
        ``E·(1 − drift/2)`` at the first frame to ``E·(1 + drift/2)`` at the last, so
        that its mean over the frames is E (abs(drift) ≤ 2; default 0).
    adc_bits : int, optional
        ADC resolution, bits (1–16; default 16): counts are clipped to
        ``[0, 2**adc_bits − 1]``.
    seed : int, numpy.random.SeedSequence or numpy.random.Generator, optional
        Seed of the random draws; the same seed gives the same stack.
    cascade_method : {"pmf", "stages"}, optional
        Exact cascade sampler (:func:`emccdcal.model.cascade_sampling.sample_cascade`).
    callback : callable, optional
        Called with the number of frames done after each chunk (for progress bars).
    varying : sequence of (array_like (rows, cols), array_like (frames,)), optional
        Parts of ``photoelectrons`` whose rate changes from frame to frame: for each
        ``(part, factors)`` the rate in frame f is ``photoelectrons + part·(factors[f] −
        1)`` (e.g. one bead's light, fading as it bleaches or off while it blinks). The
        rate must stay ≥ 0.
    register_cic : float, optional
        Clock-induced charge made inside the register, e⁻ per pixel per frame (≥ 0;
        default 0; the cascade only): each electron enters at a uniformly random stage
        and is multiplied by the stages after it
        (:func:`emccdcal.model.cascade_sampling.sample_register_cic`).

    Returns
    -------
    ndarray of uint16, shape (frames, rows, cols)
        Raw counts, ADU.

    Examples
    --------
    >>> s = simulate_frames(370.0, em_gain=4.78, offset=583.9, frames=2000, rows=4, cols=4, seed=1)
    >>> s.shape, s.dtype.name
    ((2000, 4, 4), 'uint16')
    >>> bool(abs(s.mean() - (583.9 + 4.78 * 370 / 3.859)) < 2)
    True
    """
    shape = _shape(rows, cols, photoelectrons, offset, read_noise)
    n_frames = check_int("frames", frames)
    E = check_map("photoelectrons", photoelectrons, shape, minimum=0.0)
    g = check_number("em_gain", em_gain, minimum=1.0)
    phi = check_number("e_per_adu", e_per_adu, positive=True)
    S0 = check_map("offset", offset, shape, minimum=0.0)
    sigma = check_map("read_noise", read_noise, shape, positive=True)
    mult = _multiplication(multiplication)
    n_stages = check_int("stages", stages)
    c = check_number("cic", cic, minimum=0.0)
    c_reg = check_number("register_cic", register_cic, minimum=0.0)
    register = EMModel(mult, n_stages).register
    if c_reg and ("register_cic" not in register.parameters or g == 1.0):
        raise OptionError(
            "register_cic is charge made inside an exact (cascade) register "
            "at EM gain: give multiplication='cascade' and em_gain > 1"
        )
    d = check_number("drift", drift, minimum=-2.0, maximum=2.0)
    bits = check_int("adc_bits", adc_bits, minimum=1, maximum=16)
    _cascade_method(cascade_method)
    rng = np.random.default_rng(seed)

    adc_max = 2**bits - 1
    if np.max(S0) >= adc_max:
        raise OptionError(
            f"offset {float(np.max(S0)):g} ADU is at or above the ADC maximum "
            f"{adc_max} ADU of {bits} bits: every count would be clipped to it"
        )
    factors = _drift_factors(n_frames, d)
    parts = []
    for part, fs in varying:
        part = check_map("varying part", part, shape, minimum=0.0)
        fs = np.asarray(fs, dtype=float)
        if fs.shape != (n_frames,) or not np.all(np.isfinite(fs) & (fs >= 0)):
            raise OptionError(f"varying factors must be {n_frames} numbers >= 0, one per frame")
        parts.append((part, fs))
    out = np.empty((n_frames,) + shape, dtype=np.uint16)
    step = max(1, _CHUNK_ELEMENTS // (shape[0] * shape[1]))
    dark = not np.any(E) and c == 0 and not parts  # (register charge is added apart)
    for f0 in range(0, n_frames, step):
        f1 = min(n_frames, f0 + step)
        if dark:
            n = np.zeros((f1 - f0,) + shape, dtype=np.int64)
        else:
            lam = E * factors[f0:f1, None, None] + c
            for part, fs in parts:
                lam = lam + part * (fs[f0:f1, None, None] - 1.0)
            n = rng.poisson(np.maximum(lam, 0.0))
        if g == 1.0:
            x = n.astype(float)
        else:
            x = register.sample(n, g, rng, method=cascade_method)
        if c_reg:
            made = rng.poisson(c_reg, n.shape)
            where = np.repeat(np.arange(made.size), made.ravel())
            np.add.at(x.reshape(-1), where, register.sample_register_cic(where.size, g, rng))
        x /= phi
        x += S0
        x += sigma * rng.standard_normal(n.shape)
        np.rint(x, out=x)
        np.clip(x, 0, adc_max, out=x)
        out[f0:f1] = x
        if callback is not None:
            callback(f1 - f0)
    return out


def expected_moments(
    photoelectrons,
    em_gain=1.0,
    e_per_adu=_DEFAULTS["e_per_adu"],
    offset=DEFAULT_OFFSET,
    read_noise=_DEFAULTS["read_noise"],
    *,
    frames=_DEFAULTS["frames"],
    multiplication=defaults.DEFAULT_EM_MODEL,
    stages=DEFAULT_STAGES,
    cic=0.0,
    drift=0.0,
):
    """Mean and variance of one pixel's simulated counts over the frames.

    ``mean = S0 + g(E + c)/φ`` and
    ``variance = σ² + 1/12 + (g/φ)²·(F²·(E + c) + Var_t(E_t))``, with F² = 1 at g = 1,
    2 for the gamma model, :func:`emccdcal.model.cascade.excess_noise_factor` for the cascade,
    ``1/12`` the rounding to integers, and ``Var_t(E_t) = (drift·E)²(T + 1)/(12(T − 1))``
    the spread of the drifting rate over T frames. ADC clipping is ignored.

    Parameters are those of :func:`simulate_frames` (scalars or maps).

    Returns
    -------
    mean : float or ndarray
        ADU.
    variance : float or ndarray
        ADU².

    Examples
    --------
    >>> m, v = expected_moments(370.0, 4.78, 3.859, 583.9, 15.5)
    >>> round(float(m), 3), round(float(v), 1)
    (1042.205, 1254.3)
    >>> round(float(expected_moments(370.0, 4.78, 3.859, 583.9, 15.5, multiplication="gamma")[1]), 1)
    1375.7
    """
    E = check_number("photoelectrons", photoelectrons, minimum=0.0, scalar=False)
    g = check_number("em_gain", em_gain, minimum=1.0)
    phi = check_number("e_per_adu", e_per_adu, positive=True)
    S0 = check_number("offset", offset, minimum=0.0, scalar=False)
    sigma = check_number("read_noise", read_noise, positive=True, scalar=False)
    n_frames = check_int("frames", frames)
    mult = _multiplication(multiplication)
    c = check_number("cic", cic, minimum=0.0)
    d = check_number("drift", drift, minimum=-2.0, maximum=2.0)
    f2 = Camera(multiplication=mult, stages=stages).excess_noise_factor(g)
    var_t = 0.0 if n_frames == 1 else (d * E) ** 2 * (n_frames + 1) / (12.0 * (n_frames - 1))
    mean = S0 + g * (E + c) / phi
    var = sigma**2 + 1.0 / 12.0 + (g / phi) ** 2 * (f2 * (E + c) + var_t)
    return mean[()] if np.ndim(mean) == 0 else mean, var[()] if np.ndim(var) == 0 else var
