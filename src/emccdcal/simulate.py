"""Synthetic EMCCD acquisitions with known truth.

The generative model is the paper's (METHODS §0) plus the effects a real camera adds.
For each pixel and frame t:

1. electrons entering the EM register ``n ~ Poisson(E_t + c)``: ``photoelectrons`` E
   (e⁻ per pixel per frame, optionally drifting linearly over the acquisition, see
   ``drift``) plus clock-induced charge ``cic`` c (e⁻ per pixel per frame, also present
   in dark frames and multiplied like photoelectrons);
2. EM multiplication with true mean gain g (``em_gain``): ``multiplication="gamma"``,
   ``X ~ Gamma(shape n, scale g)`` (the paper's model, excess-noise factor F² = 2), or
   ``"cascade"``, the exact Bernoulli cascade of ``stages`` stages
   (:func:`emccdcal.cascade.sample_cascade`, F² < 2); at ``em_gain == 1`` no
   multiplication at all, X = n (the 1× set-point);
3. read-out: ``counts = round(S0 + X/φ + N(0, σ²))`` clipped to ``[0, 2**adc_bits − 1]``
   (``offset`` S0 and ``read_noise`` σ in ADU, ``e_per_adu`` φ in e⁻/ADU).

The read-out noise is continuous and the count is rounded, so the standard deviation of
dark counts (the ``read_noise`` maps written next to the stacks) is ≈ sqrt(σ² + 1/12),
not σ (Sheppard's correction); the noise model's ``read_noise`` is the former.

:func:`simulate_frames` is the in-memory core (one stack, no files).
:func:`simulate_gain_series` and :func:`simulate_intensity_series` write what a real
calibration session produces: uint16 TIFF stacks ``(frames, rows, cols)``, a dark stack
per set-point with its per-pixel ``offset`` and ``read_noise`` maps (float32 TIFF, ADU),
a ``manifest.toml`` in the DESIGN format, and ``truth.json`` with the true values.
:func:`simulate_beads` writes bead movies for the bead validation (isolated emitters with
a pixel-integrated Gaussian PSF, :func:`bead_scene`) with the same camera, plus
``truth_calibration.nc``, the true calibration in the result contract.
``emccdcal simulate gain-series|intensity-series|beads OUTDIR`` is the command line.
``docs/simulation.md`` and ``docs/beads.md`` have examples.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import operator
import os
import secrets
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import __version__
from .cascade import DEFAULT_STAGES, excess_noise_factor, sample_cascade, sample_gamma

__all__ = [
    "simulate_frames",
    "simulate_gain_series",
    "simulate_intensity_series",
    "simulate_beads",
    "bead_scene",
    "expected_moments",
    "default_em_gain",
    "offset_at_setpoint",
    "SimulatedSeries",
    "PAPER_SETPOINTS",
    "PAPER_EM_GAIN",
    "PAPER_LEVELS",
    "add_parser",
]

#: Gain set-points of the paper's gain series.
PAPER_SETPOINTS = (1, 5, 25, 100, 300)
#: True mean EM gain at the paper's set-points (our GS fit of the authors' sample data,
#: METHODS §10 case 10). Other set-points default to a true gain equal to the set-point.
PAPER_EM_GAIN = {1: 1.0, 5: 4.78, 25: 22.95, 100: 90.06, 300: 261.6}
#: Photoelectrons (e⁻ per pixel per frame) of the default intensity series: six
#: log-spaced levels, labelled L1 … L6.
PAPER_LEVELS = (2000.0, 4000.0, 8000.0, 16000.0, 32000.0, 64000.0)

#: Default offset at set-point 1, ADU, and its drop per decade of set-point, ADU: a line
#: in log10(set-point) through the sample data's dark means at 1× (587.7) and 300×
#: (566.2); it gives 581.6, 575.6, 570.3 at 5×, 25×, 100× (data: 583.9, 575.9, 570.9).
DEFAULT_OFFSET = 587.7
DEFAULT_OFFSET_DROP = 8.68

_DEFAULTS = {
    "rows": 32,
    "cols": 32,
    "frames": 5000,
    "photoelectrons": 370.0,
    "e_per_adu": 3.859,
    "offset": DEFAULT_OFFSET,
    "offset_drop": DEFAULT_OFFSET_DROP,
    "offset_spread": 0.5,
    "read_noise": 15.5,
    "multiplication": "gamma",
    "stages": DEFAULT_STAGES,
    "cic": 0.0,
    "drift": 0.0,
    "adc_bits": 16,
}
_MULTIPLICATIONS = ("gamma", "cascade")
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


# --------------------------------------------------------------------------------------
# Checking
# --------------------------------------------------------------------------------------
def _int(name: str, value, *, minimum: int = 1, maximum: int | None = None) -> int:
    if isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    try:
        out = operator.index(value)
    except TypeError:
        if isinstance(value, (float, np.floating)) and float(value).is_integer():
            out = int(value)
        else:
            raise ValueError(f"{name} must be an integer, got {value!r}") from None
    if out < minimum or (maximum is not None and out > maximum):
        rng = f">= {minimum}" if maximum is None else f"from {minimum} to {maximum}"
        raise ValueError(f"{name} must be an integer {rng}, got {value!r}")
    return out


def _number(name: str, value, *, positive=False, minimum=None, maximum=None, scalar=True):
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if scalar and arr.ndim != 0:
        raise ValueError(f"{name} must be a single number, got an array of shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {value!r}")
    if positive and np.any(arr <= 0):
        raise ValueError(f"{name} must be > 0, got {value!r}")
    if minimum is not None and np.any(arr < minimum):
        raise ValueError(f"{name} must be >= {minimum:g}, got {value!r}")
    if maximum is not None and np.any(arr > maximum):
        raise ValueError(f"{name} must be <= {maximum:g}, got {value!r}")
    return float(arr) if scalar else arr


def _map(name: str, value, shape, **kw) -> np.ndarray:
    arr = _number(name, value, scalar=False, **kw)
    if arr.ndim not in (0, 2):
        raise ValueError(f"{name} must be a number or a (rows, cols) map, got shape {arr.shape}")
    if arr.ndim == 2 and arr.shape != shape:
        raise ValueError(f"{name} map has shape {arr.shape}, expected (rows, cols) = {shape}")
    return np.broadcast_to(arr, shape)


def _multiplication(value) -> str:
    if value not in _MULTIPLICATIONS:
        raise ValueError(f"multiplication must be 'gamma' or 'cascade', got {value!r}")
    return value


def _shape(rows, cols, *maps) -> tuple[int, int]:
    inferred = next((np.shape(m) for m in maps if np.ndim(m) == 2), None)
    r = _int("rows", rows) if rows is not None else (inferred[0] if inferred else _DEFAULTS["rows"])
    c = _int("cols", cols) if cols is not None else (inferred[1] if inferred else _DEFAULTS["cols"])
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
    s = _number("em_gain_setpoint", setpoint, minimum=1.0)
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
    s = _number("em_gain_setpoint", setpoint, minimum=1.0)
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
    multiplication="gamma",
    stages=DEFAULT_STAGES,
    cic=0.0,
    drift=0.0,
    adc_bits=16,
    seed=None,
    cascade_method="pmf",
    callback: Callable[[int], object] | None = None,
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
    multiplication : {"gamma", "cascade"}, optional
        EM register model (module docstring). Ignored at ``em_gain == 1``.
    stages : int, optional
        Stages of the cascade register (default 536).
    cic : float, optional
        Clock-induced charge, e⁻ per pixel per frame (≥ 0; default 0), multiplied like
        photoelectrons.
    drift : float, optional
        Linear drift of the illumination: the photoelectron rate goes from
        ``E·(1 − drift/2)`` at the first frame to ``E·(1 + drift/2)`` at the last, so
        that its mean over the frames is E (|drift| ≤ 2; default 0).
    adc_bits : int, optional
        ADC resolution, bits (1–16; default 16): counts are clipped to
        ``[0, 2**adc_bits − 1]``.
    seed : int, numpy.random.SeedSequence or numpy.random.Generator, optional
        Seed of the random draws; the same seed gives the same stack.
    cascade_method : {"pmf", "stages"}, optional
        Exact cascade sampler (:func:`emccdcal.cascade.sample_cascade`).
    callback : callable, optional
        Called with the number of frames done after each chunk (for progress bars).

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
    n_frames = _int("frames", frames)
    E = _map("photoelectrons", photoelectrons, shape, minimum=0.0)
    g = _number("em_gain", em_gain, minimum=1.0)
    phi = _number("e_per_adu", e_per_adu, positive=True)
    S0 = _map("offset", offset, shape, minimum=0.0)
    sigma = _map("read_noise", read_noise, shape, positive=True)
    mult = _multiplication(multiplication)
    n_stages = _int("stages", stages)
    c = _number("cic", cic, minimum=0.0)
    d = _number("drift", drift, minimum=-2.0, maximum=2.0)
    bits = _int("adc_bits", adc_bits, minimum=1, maximum=16)
    if cascade_method not in ("pmf", "stages"):
        raise ValueError(f"cascade_method must be 'pmf' or 'stages', got {cascade_method!r}")
    rng = np.random.default_rng(seed)

    adc_max = 2**bits - 1
    factors = _drift_factors(n_frames, d)
    out = np.empty((n_frames,) + shape, dtype=np.uint16)
    step = max(1, _CHUNK_ELEMENTS // (shape[0] * shape[1]))
    dark = not np.any(E) and c == 0
    for f0 in range(0, n_frames, step):
        f1 = min(n_frames, f0 + step)
        if dark:
            n = np.zeros((f1 - f0,) + shape, dtype=np.int64)
        else:
            lam = E * factors[f0:f1, None, None] + c
            n = rng.poisson(lam)
        if g == 1.0:
            x = n.astype(float)
        elif mult == "gamma":
            x = sample_gamma(n, g, rng)
        else:
            x = sample_cascade(n, g, n_stages, rng, method=cascade_method).astype(float)
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
    multiplication="gamma",
    stages=DEFAULT_STAGES,
    cic=0.0,
    drift=0.0,
):
    """Mean and variance of one pixel's simulated counts over the frames.

    ``mean = S0 + g(E + c)/φ`` and
    ``variance = σ² + 1/12 + (g/φ)²·(F²·(E + c) + Var_t(E_t))``, with F² = 1 at g = 1,
    2 for the gamma model, :func:`emccdcal.cascade.excess_noise_factor` for the cascade,
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
    (1042.205, 1375.7)
    """
    E = _number("photoelectrons", photoelectrons, minimum=0.0, scalar=False)
    g = _number("em_gain", em_gain, minimum=1.0)
    phi = _number("e_per_adu", e_per_adu, positive=True)
    S0 = _number("offset", offset, minimum=0.0, scalar=False)
    sigma = _number("read_noise", read_noise, positive=True, scalar=False)
    n_frames = _int("frames", frames)
    mult = _multiplication(multiplication)
    c = _number("cic", cic, minimum=0.0)
    d = _number("drift", drift, minimum=-2.0, maximum=2.0)
    if g == 1.0:
        f2 = 1.0
    elif mult == "gamma":
        f2 = 2.0
    else:
        f2 = float(excess_noise_factor(g, _int("stages", stages)))
    var_t = 0.0 if n_frames == 1 else (d * E) ** 2 * (n_frames + 1) / (12.0 * (n_frames - 1))
    mean = S0 + g * (E + c) / phi
    var = sigma**2 + 1.0 / 12.0 + (g / phi) ** 2 * (f2 * (E + c) + var_t)
    return mean[()] if np.ndim(mean) == 0 else mean, var[()] if np.ndim(var) == 0 else var


# --------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SimulatedSeries:
    """What a series simulation wrote.

    Attributes
    ----------
    outdir : Path
        The output directory.
    manifest : Path
        ``outdir/manifest.toml``, the input of ``emccdcal calibrate``.
    truth_path : Path
        ``outdir/truth.json``.
    truth : dict
        Its content: the true values, the seed and all options.
    files : tuple of Path
        Every file written (stacks, dark stacks, maps, truth pattern, truth, manifest).
    """

    outdir: Path
    manifest: Path
    truth_path: Path
    truth: dict
    files: tuple[Path, ...]


def _atomic_write(path: Path, write: Callable[[str], object]) -> Path:
    """Write through a temporary file in the same directory, then ``os.replace``.

    The temporary file is created with the usual permissions (0o666 less the umask).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        tmp = path.parent / f".{path.name}.{secrets.token_hex(6)}.tmp{path.suffix}"
        try:
            os.close(os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666))
            break
        except FileExistsError:  # pragma: no cover - 48 random bits
            continue
    try:
        write(str(tmp))
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return path


def _write_tiff(path: Path, data: np.ndarray) -> Path:
    import tifffile

    return _atomic_write(path, lambda tmp: tifffile.imwrite(tmp, data, photometric="minisblack"))


def _write_text(path: Path, text: str) -> Path:
    def write(tmp):
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)

    return _atomic_write(path, write)


def _dark_maps(dark: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel mean and standard deviation (ddof=1) of a dark stack, ADU, float32.

    Two passes over chunks of frames, so that only a chunk is ever held in float64.
    """
    n = dark.shape[0]
    step = max(1, _CHUNK_ELEMENTS // max(1, dark[0].size))
    total = np.zeros(dark.shape[1:])
    for f0 in range(0, n, step):
        total += dark[f0 : f0 + step].sum(axis=0, dtype=np.float64)
    mean = total / n
    ss = np.zeros(dark.shape[1:])
    for f0 in range(0, n, step):
        ss += np.sum((dark[f0 : f0 + step] - mean) ** 2, axis=0)
    return mean.astype(np.float32), np.sqrt(ss / (n - 1)).astype(np.float32)


def _toml_value(value) -> str:
    if isinstance(value, str):
        return json.dumps(value)  # a TOML basic string
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    v = float(value)
    return str(int(v)) if v.is_integer() and abs(v) < 2**53 else repr(v)


def _label(setpoint: float) -> str:
    return f"{setpoint:g}x"


def _check_common(opts: dict) -> dict:
    """Validate the options shared by both series; return them normalised."""
    o = dict(opts)
    o["rows"] = _int("rows", o["rows"])
    o["cols"] = _int("cols", o["cols"])
    o["frames"] = _int("frames", o["frames"])
    o["dark_frames"] = o["frames"] if o["dark_frames"] is None else o["dark_frames"]
    o["dark_frames"] = _int("dark_frames", o["dark_frames"], minimum=2)
    o["e_per_adu"] = _number("e_per_adu", o["e_per_adu"], positive=True)
    o["offset"] = _number("offset", o["offset"], minimum=0.0)
    o["offset_drop"] = _number("offset_drop", o["offset_drop"])
    o["offset_spread"] = _number("offset_spread", o["offset_spread"], minimum=0.0)
    o["read_noise"] = _number("read_noise", o["read_noise"], positive=True)
    o["multiplication"] = _multiplication(o["multiplication"])
    o["stages"] = _int("stages", o["stages"])
    o["cic"] = _number("cic", o["cic"], minimum=0.0)
    o["drift"] = _number("drift", o["drift"], minimum=-2.0, maximum=2.0)
    o["adc_bits"] = _int("adc_bits", o["adc_bits"], minimum=1, maximum=16)
    if o["cascade_method"] not in ("pmf", "stages"):
        raise ValueError(f"cascade_method must be 'pmf' or 'stages', got {o['cascade_method']!r}")
    if o["seed"] is None:
        o["seed"] = int(np.random.SeedSequence().entropy)
    else:
        o["seed"] = _int("seed", o["seed"], minimum=0)
    return o


def _setpoint_offset(name: str, value: float, setpoint: float, opts: dict) -> float:
    if value is None:
        off = offset_at_setpoint(setpoint, opts["offset"], opts["offset_drop"])
    else:
        off = value
    off = _number(name, off)
    if off < 0:
        raise ValueError(
            f"{name} at set-point {setpoint:g} is {off:g} ADU, must be >= 0 "
            "(lower offset_drop or raise offset)"
        )
    return off


def _output_dir(outdir) -> Path:
    outdir = Path(outdir)
    if outdir.exists() and not outdir.is_dir():
        raise ValueError(f"outdir '{outdir}' exists and is not a directory")
    outdir.mkdir(parents=True, exist_ok=True)
    return outdir


def _write_stacks(outdir: Path, kind: str, acqs: list[dict], darks: list[dict], opts: dict,
                  progress: bool, seeds) -> tuple[list[Path], np.ndarray, str]:
    """Simulate and write the signal stacks ``acqs`` and the dark stacks ``darks``.

    ``seeds`` are ``1 + len(acqs) + len(darks)`` children of the run's SeedSequence: the
    offset pattern, then one per signal stack, then one per dark stack. Returns the
    files written, the offset pattern (ADU, as stored) and its file name.
    """
    from tqdm import tqdm

    shape = (opts["rows"], opts["cols"])
    pattern = np.random.default_rng(seeds[0]).normal(0.0, opts["offset_spread"], shape)
    pattern = pattern.astype(np.float32).astype(np.float64)  # exactly what the file holds
    files: list[Path] = []
    common = dict(
        e_per_adu=opts["e_per_adu"],
        read_noise=opts["read_noise"],
        multiplication=opts["multiplication"],
        stages=opts["stages"],
        cic=opts["cic"],
    )
    total = sum(a["frames_n"] for a in acqs) + sum(d["frames_n"] for d in darks)
    with tqdm(
        total=total, unit="frame", desc=f"simulate {kind}", disable=not progress, file=sys.stderr
    ) as bar:
        for d, ss in zip(darks, seeds[1 + len(acqs) :]):
            bar.set_postfix_str(f"dark {d['label']}")
            stack = simulate_frames(
                0.0,
                em_gain=d["em_gain"],
                offset=np.clip(d["offset"] + pattern, 0.0, None),
                frames=d["frames_n"],
                adc_bits=opts["adc_bits"],
                seed=ss,
                cascade_method=opts["cascade_method"],
                callback=bar.update,
                **common,
            )
            files.append(_write_tiff(outdir / d["dark"], stack))
            off_map, sd_map = _dark_maps(stack)
            del stack
            files.append(_write_tiff(outdir / d["offset_map"], off_map))
            files.append(_write_tiff(outdir / d["read_noise_map"], sd_map))
        for a, ss in zip(acqs, seeds[1 : 1 + len(acqs)]):
            bar.set_postfix_str(a["label"])
            stack = simulate_frames(
                a["photoelectrons"],
                em_gain=a["em_gain"],
                offset=np.clip(a["offset"] + pattern, 0.0, None),
                frames=a["frames_n"],
                drift=opts["drift"],
                adc_bits=opts["adc_bits"],
                seed=ss,
                cascade_method=opts["cascade_method"],
                callback=bar.update,
                **common,
            )
            files.append(_write_tiff(outdir / a["frames"], stack))
            del stack
    pattern_file = "truth-offset-pattern.tif"
    files.append(_write_tiff(outdir / pattern_file, pattern.astype(np.float32)))
    return files, pattern, pattern_file


def _run_series(outdir, kind: str, acqs: list[dict], darks: list[dict], opts: dict, progress: bool):
    """Simulate and write the stacks of ``acqs`` (signal) and ``darks``; return the result."""
    outdir = _output_dir(outdir)
    seeds = np.random.SeedSequence(opts["seed"]).spawn(1 + len(acqs) + len(darks))
    files, _, pattern_file = _write_stacks(outdir, kind, acqs, darks, opts, progress, seeds)
    common = dict(
        e_per_adu=opts["e_per_adu"],
        read_noise=opts["read_noise"],
        multiplication=opts["multiplication"],
        stages=opts["stages"],
        cic=opts["cic"],
    )

    # truth.json
    truth_acqs = []
    for a in acqs:
        mean, var = expected_moments(
            a["photoelectrons"],
            a["em_gain"],
            offset=a["offset"],
            frames=a["frames_n"],
            drift=opts["drift"],
            **common,
        )
        d_mean, d_var = expected_moments(0.0, a["em_gain"], offset=a["offset"], frames=2, **common)
        if a["em_gain"] == 1.0:
            f2 = 1.0
        elif opts["multiplication"] == "gamma":
            f2 = 2.0
        else:
            f2 = float(excess_noise_factor(a["em_gain"], opts["stages"]))
        entry = {
            "name": a["label"],
            "frames": a["frames"],
            "dark": a["dark"],
            "offset_map": a["offset_map"],
            "read_noise_map": a["read_noise_map"],
            "n_frames": a["frames_n"],
            "n_dark_frames": opts["dark_frames"],
            "em_gain_setpoint": a["setpoint"],
            "em_gain": a["em_gain"],
            "photoelectrons": a["photoelectrons"],
            "photoelectrons_with_cic": a["photoelectrons"] + opts["cic"],
            "offset": a["offset"],
            "excess_noise_factor": f2,
            "expected": {
                "mean": float(mean),
                "variance": float(var),
                "dark_mean": float(d_mean),
                "dark_variance": float(d_var),
            },
        }
        if "level" in a:
            entry = {"level": a["level"], **entry}
        truth_acqs.append(entry)
    options = {k: opts[k] for k in sorted(opts) if k != "manifest_e_per_adu"}
    truth = {
        "kind": kind,
        "emccdcal_version": __version__,
        "seed": opts["seed"],
        "units": dict(_UNITS),
        "e_per_adu": opts["e_per_adu"],
        "read_noise": opts["read_noise"],
        "read_noise_dark_sd": math.sqrt(opts["read_noise"] ** 2 + 1.0 / 12.0),
        "cic": opts["cic"],
        "drift": opts["drift"],
        "multiplication": opts["multiplication"],
        "stages": opts["stages"] if opts["multiplication"] == "cascade" else None,
        "adc_bits": opts["adc_bits"],
        "offset_pattern": {
            "file": pattern_file,
            "sd": opts["offset_spread"],
            "note": "per-pixel offset = acquisition offset + this map (same at every set-point)",
        },
        "acquisitions": truth_acqs,
        "notes": [
            "photoelectrons: illumination only, mean over frames; "
            "the count model sees photoelectrons_with_cic",
            "expected: per-pixel mean and variance of the counts at the acquisition offset "
            "(rounding adds 1/12 ADU^2; ADC clipping ignored)",
            "read_noise is the SD of the Gaussian read-out before rounding; "
            "dark-map SD ~ sqrt(read_noise^2 + 1/12)",
        ],
        "options": options,
    }
    truth_path = outdir / "truth.json"
    files.append(_write_text(truth_path, json.dumps(truth, indent=2) + "\n"))

    # manifest.toml, last: its presence means the series is complete
    lines = _manifest_lines(kind, acqs, opts)
    manifest = outdir / "manifest.toml"
    files.append(_write_text(manifest, "\n".join(lines) + "\n"))
    return SimulatedSeries(outdir, manifest, truth_path, truth, tuple(files))


def _manifest_lines(kind: str, acqs: list[dict], opts: dict) -> list[str]:
    """Lines of the manifest of a simulated series (DESIGN format)."""
    lines = [
        f"# Synthetic {kind} written by emccdcal {__version__} (emccdcal simulate {kind}).",
        "# Known truth: truth.json. Paths are relative to this file.",
    ]
    if opts.get("manifest_e_per_adu", True):
        lines.append(f"e_per_adu = {_toml_value(opts['e_per_adu'])}")
    lines.append(f"adc_bits = {opts['adc_bits']}")
    for a in acqs:
        lines += [
            "",
            "[[acquisition]]",
            f"name = {_toml_value(a['label'])}",
            f"frames = {_toml_value(a['frames'])}",
            f"em_gain_setpoint = {_toml_value(a['setpoint'])}",
        ]
        if "level" in a:
            lines.append(f"level = {_toml_value(a['level'])}")
        lines += [
            f"offset = {_toml_value(a['offset_map'])}",
            f"read_noise = {_toml_value(a['read_noise_map'])}",
            f"dark_frames = {opts['dark_frames']}  # the maps' own errors enter the SEs",
            f"# dark = {_toml_value(a['dark'])}  (the stack the maps were computed from)",
        ]
    return lines


def _gains(em_gain, setpoints) -> list[float]:
    if em_gain is None:
        return [default_em_gain(s) for s in setpoints]
    values = [em_gain] if np.ndim(em_gain) == 0 else list(em_gain)
    if len(values) != len(setpoints):
        raise ValueError(
            f"em_gain has {len(values)} value(s) but there are {len(setpoints)} set-points"
        )
    return [_number("em_gain", v, minimum=1.0) for v in values]


def _setpoint_list(setpoints) -> list[float]:
    values = [setpoints] if np.ndim(setpoints) == 0 else list(setpoints)
    if not values:
        raise ValueError("setpoints must not be empty")
    out = [_number("setpoints", s, minimum=1.0) for s in values]
    if len({_label(s) for s in out}) != len(out):
        raise ValueError(f"setpoints must be distinct, got {values!r}")
    return out


def simulate_gain_series(
    outdir,
    *,
    setpoints=PAPER_SETPOINTS,
    em_gain=None,
    photoelectrons=_DEFAULTS["photoelectrons"],
    e_per_adu=_DEFAULTS["e_per_adu"],
    rows=_DEFAULTS["rows"],
    cols=_DEFAULTS["cols"],
    frames=_DEFAULTS["frames"],
    dark_frames=None,
    offset=DEFAULT_OFFSET,
    offset_drop=DEFAULT_OFFSET_DROP,
    offsets=None,
    offset_spread=_DEFAULTS["offset_spread"],
    read_noise=_DEFAULTS["read_noise"],
    multiplication="gamma",
    stages=DEFAULT_STAGES,
    cic=0.0,
    drift=0.0,
    adc_bits=16,
    seed=None,
    cascade_method="pmf",
    progress=False,
) -> SimulatedSeries:
    """Simulate a gain series (fixed illumination, several EM gain set-points) on disk.

    Writes ``outdir/gain-GS/<s>x-gain.tif`` (signal), ``<s>x-gain_no-signal.tif`` (dark)
    and its maps ``<s>x-gain_no-signal_S0.tif`` / ``_sigma.tif`` per set-point s,
    ``truth-offset-pattern.tif``, ``truth.json`` and ``manifest.toml`` (with
    ``e_per_adu``).

    Parameters
    ----------
    outdir : path
        Output directory (created; files of the same names are replaced).
    setpoints : sequence of float, optional
        EM gain set-points (≥ 1, distinct), default 1, 5, 25, 100, 300.
    em_gain : sequence of float, optional
        True mean EM gain per set-point (≥ 1; 1 = no multiplication). Default
        :func:`default_em_gain` of each set-point (the paper's 4.78, 22.95, 90.06, 261.6
        at 5, 25, 100, 300).
    photoelectrons : float or sequence of float, optional
        E, photoelectrons per pixel per frame (e⁻): one number for the same illumination
        at every set-point (370), or one per set-point for an illumination that differs
        between acquisitions (what ``gs-hierarchical`` models, METHODS §6).
    e_per_adu : float, optional
        φ, e⁻/ADU (3.859).
    rows, cols, frames : int, optional
        Frame size (px) and frames per signal stack (32, 32, 5000).
    dark_frames : int, optional
        Frames per dark stack (≥ 2; default: ``frames``).
    offset, offset_drop : float, optional
        Offset at set-point 1 (ADU, 587.7) and its drop per decade of set-point (ADU,
        8.68), :func:`offset_at_setpoint`.
    offsets : sequence of float, optional
        Offset per set-point (ADU); overrides ``offset``/``offset_drop``.
    offset_spread : float, optional
        SD of a fixed per-pixel offset pattern added at every set-point (ADU, 0.5;
        0 for none); written to ``truth-offset-pattern.tif``.
    read_noise : float, optional
        σ of the Gaussian read-out noise before rounding, ADU (15.5).
    multiplication, stages, cic, drift, adc_bits, cascade_method
        As in :func:`simulate_frames`.
    seed : int, optional
        Seed (≥ 0); None draws one, recorded in truth.json. The same seed and options
        give identical files.
    progress : bool, optional
        Show a tqdm progress bar on stderr.

    Returns
    -------
    SimulatedSeries
    """
    opts = _check_common(locals() | {"progress": None})
    opts.pop("outdir")
    opts.pop("progress")
    sps = _setpoint_list(setpoints)
    gains = _gains(em_gain, sps)
    Es = [photoelectrons] * len(sps) if np.ndim(photoelectrons) == 0 else list(photoelectrons)
    if len(Es) != len(sps):
        raise ValueError(
            f"photoelectrons has {len(Es)} value(s) but there are {len(sps)} set-points"
        )
    Es = [_number("photoelectrons", v, minimum=0.0) for v in Es]
    if offsets is not None:
        offs = [offsets] if np.ndim(offsets) == 0 else list(offsets)
        if len(offs) != len(sps):
            raise ValueError(
                f"offsets has {len(offs)} value(s) but there are {len(sps)} set-points"
            )
    else:
        offs = [None] * len(sps)
    opts.update(setpoints=sps, em_gain=gains,
                photoelectrons=Es[0] if len(set(Es)) == 1 else Es)
    acqs = []
    for s, g, E, off in zip(sps, gains, Es, offs):
        lab = _label(s)
        stem = f"gain-GS/{lab}-gain"
        off_name = "offsets" if off is not None else "offset"
        acqs.append(
            {
                "label": lab,
                "setpoint": s,
                "em_gain": g,
                "photoelectrons": E,
                "offset": _setpoint_offset(off_name, off, s, opts),
                "frames": f"{stem}.tif",
                "frames_n": opts["frames"],
                "dark": f"{stem}_no-signal.tif",
                "offset_map": f"{stem}_no-signal_S0.tif",
                "read_noise_map": f"{stem}_no-signal_sigma.tif",
            }
        )
    opts["offsets"] = [a["offset"] for a in acqs]
    darks = [a | {"frames_n": opts["dark_frames"]} for a in acqs]
    return _run_series(outdir, "gain-series", acqs, darks, opts, progress)


def simulate_intensity_series(
    outdir,
    *,
    levels=PAPER_LEVELS,
    labels=None,
    setpoint=1,
    em_gain=None,
    e_per_adu=_DEFAULTS["e_per_adu"],
    rows=_DEFAULTS["rows"],
    cols=_DEFAULTS["cols"],
    frames=_DEFAULTS["frames"],
    dark_frames=None,
    offset=DEFAULT_OFFSET,
    offset_drop=DEFAULT_OFFSET_DROP,
    offset_spread=_DEFAULTS["offset_spread"],
    read_noise=_DEFAULTS["read_noise"],
    multiplication="gamma",
    stages=DEFAULT_STAGES,
    cic=0.0,
    drift=0.0,
    adc_bits=16,
    seed=None,
    cascade_method="pmf",
    progress=False,
) -> SimulatedSeries:
    """Simulate an intensity series (several illumination levels, one set-point) on disk.

    Writes ``outdir/intensity-IS/<s>x-gain_<label>.tif`` per level, one dark stack
    ``<s>x-gain_no-signal.tif`` with its maps ``_S0.tif`` / ``_sigma.tif`` shared by all
    levels, ``truth-offset-pattern.tif``, ``truth.json`` and ``manifest.toml`` (each
    acquisition with its ``level``; ``e_per_adu`` only when the set-point is above 1,
    since at 1× the series is what measures it).

    Parameters
    ----------
    outdir : path
        Output directory.
    levels : sequence of float, optional
        Photoelectrons per pixel per frame of each level (e⁻; default 2000, 4000, …,
        64000).
    labels : sequence of str, optional
        Level labels (default ``L1``, ``L2``, …).
    setpoint : float, optional
        EM gain set-point of the series (≥ 1; default 1, the ADU calibration).
    em_gain : float, optional
        True mean EM gain (default :func:`default_em_gain` of the set-point).
    Others
        As in :func:`simulate_gain_series`.

    Returns
    -------
    SimulatedSeries
    """
    opts = _check_common(locals() | {"progress": None})
    opts.pop("outdir")
    opts.pop("progress")
    s = _number("setpoint", setpoint, minimum=1.0)
    if em_gain is not None and np.ndim(em_gain) != 0:
        raise ValueError("em_gain must be a single number for an intensity series")
    g = _gains(em_gain, [s])[0]
    lv = [levels] if np.ndim(levels) == 0 else list(levels)
    if not lv:
        raise ValueError("levels must not be empty")
    lv = [_number("levels", x, minimum=0.0) for x in lv]
    labs = [f"L{i + 1}" for i in range(len(lv))] if labels is None else [str(x) for x in labels]
    if len(labs) != len(lv):
        raise ValueError(f"labels has {len(labs)} value(s) but there are {len(lv)} levels")
    if len(set(labs)) != len(labs) or not all(x.strip() for x in labs):
        raise ValueError(f"labels must be distinct and non-empty, got {labs!r}")
    bad = [x for x in labs if any(ch in x for ch in '/\\:*?"<>|')]
    if bad:
        raise ValueError(f"labels must be usable in file names, got {bad[0]!r}")
    off = _setpoint_offset("offset", None, s, opts)
    opts.update(setpoint=s, em_gain=g, levels=lv, labels=labs, manifest_e_per_adu=s != 1)
    stem = f"intensity-IS/{_label(s)}-gain"
    dark = {
        "label": _label(s),
        "setpoint": s,
        "em_gain": g,
        "offset": off,
        "dark": f"{stem}_no-signal.tif",
        "offset_map": f"{stem}_no-signal_S0.tif",
        "read_noise_map": f"{stem}_no-signal_sigma.tif",
        "frames_n": opts["dark_frames"],
    }
    acqs = [
        dark
        | {
            "label": f"{_label(s)}-{lab}",
            "level": lab,
            "photoelectrons": E,
            "frames": f"{stem}_{lab}.tif",
            "frames_n": opts["frames"],
        }
        for lab, E in zip(labs, lv)
    ]
    return _run_series(outdir, "intensity-series", acqs, [dark], opts, progress)


# --------------------------------------------------------------------------------------
# Beads
# --------------------------------------------------------------------------------------
#: Defaults of the bead simulation (``docs/beads.md``).
BEAD_DEFAULTS = {
    "beads": 10,
    "photoelectrons": 5000.0,
    "width": 1.3,
    "background": 10.0,
    "rows": 64,
    "cols": 64,
    "frames": 500,
    "dark_frames": 2000,
    "min_separation": 12.0,
    "margin": 6.0,
}
#: File written beside the stacks: the true calibration in the result contract.
TRUTH_CALIBRATION_FILE = "truth_calibration.nc"


def _place_beads(n, rows, cols, margin, min_separation, rng) -> np.ndarray:
    """Random bead centres (row, col), at least ``margin`` px from the edges and
    ``min_separation`` px apart, by sequential rejection sampling."""
    lo_r, hi_r = margin, rows - 1 - margin
    lo_c, hi_c = margin, cols - 1 - margin
    if hi_r < lo_r or hi_c < lo_c:
        raise ValueError(
            f"a {rows}×{cols} sensor has no room for beads {margin:g} px from every edge"
        )
    placed: list[tuple[float, float]] = []
    for _ in range(200 * n + 1000):
        if len(placed) == n:
            break
        r, c = rng.uniform(lo_r, hi_r), rng.uniform(lo_c, hi_c)
        if all(math.hypot(r - pr, c - pc) >= min_separation for pr, pc in placed):
            placed.append((r, c))
    if len(placed) < n:
        raise ValueError(
            f"cannot place {n} beads at least {min_separation:g} px apart and {margin:g} px "
            f"from the edges of a {rows}×{cols} sensor; use fewer beads, a smaller "
            "min_separation or a larger sensor"
        )
    return np.array(placed)


def bead_scene(positions, photoelectrons, width, background, rows, cols) -> np.ndarray:
    """Expected photoelectrons per pixel per frame of a field of beads, e⁻.

    ``E_k = Σ_b N_b·P_k(x_b, y_b, s) + background`` with the pixel-integrated Gaussian
    :func:`emccdcal.psf.spot_image`.

    Parameters
    ----------
    positions : array_like, shape (B, 2)
        Bead centres (row, col), pixel (pixel (r, c) is centred at integer indices).
    photoelectrons : float or array_like, shape (B,)
        N_b, each bead's total photoelectrons per frame (e⁻).
    width : float
        PSF standard deviation s (pixel).
    background : float
        Uniform background b (e⁻ per pixel per frame).
    rows, cols : int
        Sensor size (pixel).

    Returns
    -------
    ndarray, shape (rows, cols)

    Examples
    --------
    >>> E = bead_scene([[10.0, 12.0]], 5000.0, 1.3, 10.0, 24, 24)
    >>> round(float(E.sum() - 10.0 * 24 * 24))
    5000
    """
    from .psf import spot_image

    pos = np.asarray(positions, dtype=float).reshape(-1, 2)
    n = np.broadcast_to(np.asarray(photoelectrons, dtype=float), (len(pos),))
    params = np.column_stack([pos[:, 1], pos[:, 0], np.full(len(pos), width), n,
                              np.zeros(len(pos))])
    image = spot_image(params, np.arange(rows), np.arange(cols)).sum(axis=0) if len(pos) \
        else np.zeros((rows, cols))
    return image + background


def simulate_beads(
    outdir,
    *,
    beads=BEAD_DEFAULTS["beads"],
    photoelectrons=BEAD_DEFAULTS["photoelectrons"],
    width=BEAD_DEFAULTS["width"],
    background=BEAD_DEFAULTS["background"],
    positions=None,
    min_separation=BEAD_DEFAULTS["min_separation"],
    margin=BEAD_DEFAULTS["margin"],
    setpoints=PAPER_SETPOINTS,
    em_gain=None,
    e_per_adu=_DEFAULTS["e_per_adu"],
    rows=BEAD_DEFAULTS["rows"],
    cols=BEAD_DEFAULTS["cols"],
    frames=BEAD_DEFAULTS["frames"],
    dark_frames=BEAD_DEFAULTS["dark_frames"],
    offset=DEFAULT_OFFSET,
    offset_drop=DEFAULT_OFFSET_DROP,
    offsets=None,
    offset_spread=_DEFAULTS["offset_spread"],
    read_noise=_DEFAULTS["read_noise"],
    multiplication="gamma",
    stages=DEFAULT_STAGES,
    cic=0.0,
    drift=0.0,
    adc_bits=16,
    seed=None,
    cascade_method="pmf",
    progress=False,
) -> SimulatedSeries:
    """Simulate bead movies at several EM gain set-points, with darks and the true calibration.

    A field of isolated fluorescent beads (the paper's validation, METHODS §5.1): every
    pixel receives Poisson photoelectrons with mean ``E_k = Σ_b N_b·P_k + b``
    (:func:`bead_scene`: pixel-integrated Gaussian PSF of SD ``width``, ``N_b``
    photoelectrons per bead per frame, uniform background b), then the camera of
    :func:`simulate_frames` (multiplication, read noise, offset pattern, ADC) at each
    set-point. Writes ``outdir/beads/<s>x-beads.tif`` per set-point, a dark stack
    ``<s>x-beads_no-signal.tif`` with its offset and read-noise maps ``_S0.tif`` /
    ``_sigma.tif`` per set-point, ``truth-offset-pattern.tif``, ``truth.json`` (with
    ``beads``: a list of ``{"row", "col", "photoelectrons"}``), ``truth_calibration.nc``
    (the true φ and gains in the calibration result contract, method ``"truth"``) and
    ``manifest.toml`` (last).

    Parameters
    ----------
    outdir : path
        Output directory (created; files of the same names are replaced).
    beads : int, optional
        Number of beads (10), placed at random unless ``positions`` is given.
    photoelectrons : float or sequence of float, optional
        Photoelectrons per bead per frame, e⁻ (5000), one value or one per bead.
    width : float, optional
        PSF standard deviation, pixel (1.3).
    background : float, optional
        Uniform background, e⁻ per pixel per frame (10).
    positions : array_like (beads, 2), optional
        Bead centres (row, col), pixel; overrides the random placement.
    min_separation, margin : float, optional
        Random placement: least distance between beads (12 px) and from the sensor's
        edges (6 px), so that each bead has a clean fitting box.
    setpoints, em_gain, e_per_adu, offset, offset_drop, offsets, offset_spread, read_noise
        As in :func:`simulate_gain_series` (set-points 1, 5, 25, 100, 300 and the paper's
        true gains by default).
    rows, cols, frames, dark_frames : int, optional
        Sensor size (64 × 64 px), frames per bead movie (500) and per dark stack (2000).
    multiplication, stages, cic, drift, adc_bits, cascade_method, seed, progress
        As in :func:`simulate_gain_series`.

    Returns
    -------
    SimulatedSeries
    """
    opts = _check_common(locals() | {"progress": None})
    for key in ("outdir", "progress", "positions"):
        opts.pop(key)
    sps = _setpoint_list(setpoints)
    gains = _gains(em_gain, sps)
    n_beads = _int("beads", beads, minimum=0) if positions is None else None
    s = _number("width", width, positive=True)
    b = _number("background", background, minimum=0.0)
    sep = _number("min_separation", min_separation, minimum=0.0)
    edge = _number("margin", margin, minimum=0.0)
    shape = (opts["rows"], opts["cols"])
    if offsets is not None:
        offs = [offsets] if np.ndim(offsets) == 0 else list(offsets)
        if len(offs) != len(sps):
            raise ValueError(
                f"offsets has {len(offs)} value(s) but there are {len(sps)} set-points"
            )
    else:
        offs = [None] * len(sps)
    children = np.random.SeedSequence(opts["seed"]).spawn(2 + 2 * len(sps))
    if positions is None:
        pos = _place_beads(n_beads, shape[0], shape[1], edge, sep,
                           np.random.default_rng(children[-1]))
    else:
        pos = np.asarray(_number("positions", positions, scalar=False), dtype=float)
        pos = pos.reshape(-1, 2) if pos.size else np.zeros((0, 2))
        if pos.ndim != 2 or pos.shape[1] != 2:
            raise ValueError(f"positions must be (beads, 2) rows and columns, got shape {pos.shape}")
        outside = (pos < 0).any(axis=1) | (pos[:, 0] > shape[0] - 1) | (pos[:, 1] > shape[1] - 1)
        if outside.any():
            raise ValueError(
                f"bead position {pos[np.argmax(outside)].tolist()} is outside the "
                f"{shape[0]}×{shape[1]} sensor"
            )
        n_beads = len(pos)
    n_values = [photoelectrons] if np.ndim(photoelectrons) == 0 else list(photoelectrons)
    if len(n_values) not in (1, n_beads):
        raise ValueError(
            f"photoelectrons has {len(n_values)} values but there are {n_beads} beads"
        )
    n_values = [_number("photoelectrons", v, minimum=0.0) for v in n_values]
    N = np.broadcast_to(np.array(n_values), (n_beads,)).astype(float)
    scene = bead_scene(pos, N, s, b, *shape)
    opts.update(setpoints=sps, em_gain=gains, beads=n_beads, photoelectrons=n_values, width=s,
                background=b, min_separation=sep, margin=edge)
    acqs = []
    for sp, g, off in zip(sps, gains, offs):
        lab = _label(sp)
        stem = f"beads/{lab}-beads"
        acqs.append(
            {
                "label": lab,
                "setpoint": sp,
                "em_gain": g,
                "photoelectrons": scene,
                "offset": _setpoint_offset("offsets" if off is not None else "offset", off, sp, opts),
                "frames": f"{stem}.tif",
                "frames_n": opts["frames"],
                "dark": f"{stem}_no-signal.tif",
                "offset_map": f"{stem}_no-signal_S0.tif",
                "read_noise_map": f"{stem}_no-signal_sigma.tif",
            }
        )
    opts["offsets"] = [a["offset"] for a in acqs]
    darks = [a | {"frames_n": opts["dark_frames"]} for a in acqs]

    outdir = _output_dir(outdir)
    files, pattern, pattern_file = _write_stacks(outdir, "beads", acqs, darks, opts, progress,
                                                 children[:-1])
    dark_sd = math.sqrt(opts["read_noise"] ** 2 + 1.0 / 12.0)
    truth_acqs = []
    for a in acqs:
        if a["em_gain"] == 1.0:
            f2 = 1.0
        elif opts["multiplication"] == "gamma":
            f2 = 2.0
        else:
            f2 = float(excess_noise_factor(a["em_gain"], opts["stages"]))
        truth_acqs.append({
            "name": a["label"],
            "frames": a["frames"],
            "dark": a["dark"],
            "offset_map": a["offset_map"],
            "read_noise_map": a["read_noise_map"],
            "n_frames": a["frames_n"],
            "n_dark_frames": opts["dark_frames"],
            "em_gain_setpoint": a["setpoint"],
            "em_gain": a["em_gain"],
            "offset": a["offset"],
            "excess_noise_factor": f2,
        })
    lines = _manifest_lines("beads", acqs, opts)
    lines[0] = f"# Synthetic bead movies written by emccdcal {__version__} (emccdcal simulate beads)."
    manifest_text = "\n".join(lines) + "\n"
    manifest = outdir / "manifest.toml"

    # The true calibration, in the result contract (emccdcal.result).
    from . import result

    ds = result.make_dataset(
        method="truth",
        setpoints=sps,
        e_per_adu=opts["e_per_adu"],
        e_per_adu_se=0.0,
        em_gain=np.broadcast_to(np.array(gains)[:, None, None], (len(sps),) + shape),
        em_gain_se=0.0,
        photoelectrons=scene,
        photoelectrons_se=0.0,
        converged=True,
        manifest_hash=hashlib.sha256(manifest_text.encode("utf-8")).hexdigest(),
        manifest_path=str(manifest.resolve()),
        extra={
            "offset": (("setpoint", "row", "col"),
                       np.stack([np.clip(a["offset"] + pattern, 0.0, None) for a in acqs]),
                       "ADU", "true offset S0 (set-point level plus the pixel pattern)"),
            "read_noise": (("setpoint", "row", "col"),
                           np.full((len(sps),) + shape, dark_sd), "ADU",
                           "true read noise: SD of dark counts, sqrt(sigma^2 + 1/12)"),
        },
        attrs={
            "note": "true values of a bead simulation (emccdcal simulate beads); "
                    "photoelectrons is the expected bead scene per pixel per frame, "
                    "background included, CIC excluded",
            "multiplication": opts["multiplication"],
        },
    )
    nc_path = outdir / TRUTH_CALIBRATION_FILE
    _atomic_write(nc_path, lambda tmp: ds.to_netcdf(tmp, engine="h5netcdf"))
    files.append(nc_path)

    options = {k: opts[k] for k in sorted(opts)}
    units = dict(_UNITS) | {"width": "pixel", "background": "e-/px/frame",
                            "bead photoelectrons": "e-/frame (whole bead)",
                            "row": "pixel", "col": "pixel"}
    truth = {
        "kind": "beads",
        "emccdcal_version": __version__,
        "seed": opts["seed"],
        "units": units,
        "beads": [{"row": float(r), "col": float(c), "photoelectrons": float(n)}
                  for (r, c), n in zip(pos, N)],
        "width": s,
        "background": b,
        "e_per_adu": opts["e_per_adu"],
        "read_noise": opts["read_noise"],
        "read_noise_dark_sd": dark_sd,
        "cic": opts["cic"],
        "drift": opts["drift"],
        "multiplication": opts["multiplication"],
        "stages": opts["stages"] if opts["multiplication"] == "cascade" else None,
        "adc_bits": opts["adc_bits"],
        "offset_pattern": {
            "file": pattern_file,
            "sd": opts["offset_spread"],
            "note": "per-pixel offset = acquisition offset + this map (same at every set-point)",
        },
        "calibration": TRUTH_CALIBRATION_FILE,
        "acquisitions": truth_acqs,
        "notes": [
            "beads: centre (row, col) in pixels, pixel (r, c) centred at integer indices; "
            "photoelectrons per bead per frame (the whole PSF, also beyond any box)",
            "every pixel: Poisson photoelectrons with mean sum_b N_b P_k + background (+ cic)",
            "read_noise is the SD of the Gaussian read-out before rounding; "
            "dark-map SD ~ sqrt(read_noise^2 + 1/12)",
        ],
        "options": options,
    }
    truth_path = outdir / "truth.json"
    files.append(_write_text(truth_path, json.dumps(truth, indent=2) + "\n"))
    files.append(_write_text(manifest, manifest_text))
    return SimulatedSeries(outdir, manifest, truth_path, truth, tuple(files))


# --------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------
def _number_list(text: str) -> list[float]:
    parts = [p.strip() for p in text.split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated numbers, got {text!r}"
        ) from None
    return values


def _label_list(text: str) -> list[str]:
    return [p.strip() for p in text.split(",")]


def _common_options(p: argparse.ArgumentParser, sizes: dict | None = None) -> None:
    sizes = {**_DEFAULTS, "dark_frames": None, **(sizes or {})}
    p.add_argument(
        "--rows",
        type=int,
        default=sizes["rows"],
        help="frame rows, px (default %(default)s)",
    )
    p.add_argument(
        "--cols",
        type=int,
        default=sizes["cols"],
        help="frame columns, px (default %(default)s)",
    )
    p.add_argument(
        "--frames",
        type=int,
        default=sizes["frames"],
        help="frames per stack (default %(default)s)",
    )
    p.add_argument(
        "--dark-frames",
        type=int,
        default=sizes["dark_frames"],
        help="frames per dark stack (default: "
        + ("--frames)" if sizes["dark_frames"] is None else "%(default)s)"),
    )
    p.add_argument(
        "--e-per-adu",
        type=float,
        default=_DEFAULTS["e_per_adu"],
        help="φ, e⁻/ADU (default %(default)s)",
    )
    p.add_argument(
        "--offset",
        type=float,
        default=DEFAULT_OFFSET,
        help="offset at set-point 1, ADU (default %(default)s)",
    )
    p.add_argument(
        "--offset-drop",
        type=float,
        default=DEFAULT_OFFSET_DROP,
        help="offset drop per decade of set-point, ADU (default %(default)s; 0 for none)",
    )
    p.add_argument(
        "--offset-spread",
        type=float,
        default=_DEFAULTS["offset_spread"],
        help="SD of the fixed per-pixel offset pattern, ADU (default %(default)s)",
    )
    p.add_argument(
        "--read-noise",
        type=float,
        default=_DEFAULTS["read_noise"],
        help="σ of the Gaussian read-out noise before rounding, ADU (default %(default)s)",
    )
    p.add_argument(
        "--multiplication",
        choices=_MULTIPLICATIONS,
        default="gamma",
        help="EM register model: gamma (the paper's) or the exact Bernoulli cascade "
        "(default %(default)s)",
    )
    p.add_argument(
        "--stages",
        type=int,
        default=DEFAULT_STAGES,
        help="cascade stages (default %(default)s)",
    )
    p.add_argument(
        "--cascade-method",
        choices=("pmf", "stages"),
        default="pmf",
        help="exact cascade sampler: pmf tables (fast) or stage-by-stage binomials "
        "(default %(default)s)",
    )
    p.add_argument(
        "--cic",
        type=float,
        default=0.0,
        help="clock-induced charge, e⁻/px/frame (default 0)",
    )
    p.add_argument(
        "--drift",
        type=float,
        default=0.0,
        help="illumination drift, fractional change from first to last frame (default 0)",
    )
    p.add_argument(
        "--adc-bits",
        type=int,
        default=16,
        help="ADC bits; counts clip at 2^bits−1 (default 16)",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=None,
        help="random seed (default: drawn and recorded in truth.json)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _common_kwargs(args) -> dict:
    return dict(
        rows=args.rows,
        cols=args.cols,
        frames=args.frames,
        dark_frames=args.dark_frames,
        e_per_adu=args.e_per_adu,
        offset=args.offset,
        offset_drop=args.offset_drop,
        offset_spread=args.offset_spread,
        read_noise=args.read_noise,
        multiplication=args.multiplication,
        stages=args.stages,
        cascade_method=args.cascade_method,
        cic=args.cic,
        drift=args.drift,
        adc_bits=args.adc_bits,
        seed=args.seed,
        progress=not args.quiet,
    )


def _report(res: SimulatedSeries, what: str) -> None:
    t = res.truth
    a0 = t["acquisitions"][0]
    rows, cols = t["options"]["rows"], t["options"]["cols"]
    print(
        f"wrote {what}: {len(t['acquisitions'])} stacks of {a0['n_frames']} frames × "
        f"{rows}×{cols} px ({t['multiplication']} multiplication, seed {t['seed']})"
    )
    print(f"  manifest: {res.manifest}")
    print(f"  truth:    {res.truth_path}")
    print(f"  stacks:   {res.outdir / Path(a0['frames']).parent}{os.sep}")


def _run_gain_series(args) -> int:
    res = simulate_gain_series(
        args.outdir,
        setpoints=args.setpoints,
        em_gain=args.em_gain,
        photoelectrons=args.photoelectrons,
        offsets=args.offsets,
        **_common_kwargs(args),
    )
    _report(res, "gain series")
    return 0


def _run_intensity_series(args) -> int:
    res = simulate_intensity_series(
        args.outdir,
        levels=args.levels,
        labels=args.labels,
        setpoint=args.setpoint,
        em_gain=args.em_gain,
        **_common_kwargs(args),
    )
    _report(res, "intensity series")
    return 0


def _run_beads(args) -> int:
    res = simulate_beads(
        args.outdir,
        beads=args.beads,
        photoelectrons=args.photoelectrons,
        width=args.width,
        background=args.background,
        min_separation=args.min_separation,
        margin=args.margin,
        setpoints=args.setpoints,
        em_gain=args.em_gain,
        offsets=args.offsets,
        **_common_kwargs(args),
    )
    _report(res, "bead movies")
    print(f"  true calibration: {res.outdir / TRUTH_CALIBRATION_FILE}")
    return 0


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add ``simulate {gain-series,intensity-series,beads}`` to the ``emccdcal`` command line."""
    p = subparsers.add_parser(
        "simulate",
        help="write synthetic stacks, darks, a manifest and truth.json",
        description="Write synthetic EMCCD acquisitions with known truth (docs/simulation.md).",
    )

    def no_kind(args) -> int:
        p.print_usage(sys.stderr)
        print("emccdcal simulate: error: choose gain-series, intensity-series or beads",
              file=sys.stderr)
        return 2

    p.set_defaults(func=no_kind)
    kinds = p.add_subparsers(dest="kind", metavar="KIND")

    gs = kinds.add_parser(
        "gain-series",
        help="fixed illumination at several EM gain set-points",
        description="Simulate a gain series: one illumination, several EM gain set-points, "
        "with a dark stack and offset/read-noise maps per set-point.",
    )
    gs.add_argument("outdir", metavar="OUTDIR", help="output directory (created)")
    gs.add_argument(
        "--setpoints",
        type=_number_list,
        default=list(PAPER_SETPOINTS),
        help="EM gain set-points, comma-separated (default 1,5,25,100,300)",
    )
    gs.add_argument(
        "--em-gain",
        type=_number_list,
        default=None,
        help="true mean EM gain per set-point, comma-separated "
        "(default 1,4.78,22.95,90.06,261.6 at the paper's set-points, else the set-point)",
    )
    gs.add_argument(
        "--photoelectrons",
        type=float,
        default=_DEFAULTS["photoelectrons"],
        help="photoelectrons per pixel per frame, e⁻ (default %(default)s)",
    )
    gs.add_argument(
        "--offsets",
        type=_number_list,
        default=None,
        help="offset per set-point, ADU, comma-separated (overrides --offset/--offset-drop)",
    )
    _common_options(gs)
    gs.set_defaults(func=_run_gain_series)

    is_ = kinds.add_parser(
        "intensity-series",
        help="several illumination levels at one EM gain set-point",
        description="Simulate an intensity series: several illumination levels at one EM gain "
        "set-point, with one dark stack and its offset/read-noise maps.",
    )
    is_.add_argument("outdir", metavar="OUTDIR", help="output directory (created)")
    is_.add_argument(
        "--levels",
        type=_number_list,
        default=list(PAPER_LEVELS),
        help="photoelectrons per pixel per frame of each level, e⁻, comma-separated "
        "(default 2000,4000,8000,16000,32000,64000)",
    )
    is_.add_argument(
        "--labels",
        type=_label_list,
        default=None,
        help="level labels (default L1,L2,…)",
    )
    is_.add_argument("--setpoint", type=float, default=1.0, help="EM gain set-point (default 1)")
    is_.add_argument(
        "--em-gain",
        type=float,
        default=None,
        help="true mean EM gain (default: from the set-point)",
    )
    _common_options(is_)
    is_.set_defaults(func=_run_intensity_series)

    bd = kinds.add_parser(
        "beads",
        help="isolated beads at several EM gain set-points (bead validation)",
        description="Simulate bead movies: isolated emitters with a pixel-integrated Gaussian "
        "PSF on a uniform background at several EM gain set-points, with a dark stack and "
        "offset/read-noise maps per set-point, truth.json and truth_calibration.nc "
        "(docs/beads.md).",
    )
    bd.add_argument("outdir", metavar="OUTDIR", help="output directory (created)")
    bd.add_argument("--beads", type=int, default=BEAD_DEFAULTS["beads"],
                    help="number of beads (default %(default)s)")
    bd.add_argument(
        "--photoelectrons",
        type=_number_list,
        default=[BEAD_DEFAULTS["photoelectrons"]],
        help="photoelectrons per bead per frame, e⁻: one value or one per bead, "
        "comma-separated (default %(default)s)",
    )
    bd.add_argument("--width", type=float, default=BEAD_DEFAULTS["width"],
                    help="PSF standard deviation, px (default %(default)s)")
    bd.add_argument("--background", type=float, default=BEAD_DEFAULTS["background"],
                    help="uniform background, e⁻/px/frame (default %(default)s)")
    bd.add_argument("--min-separation", type=float, default=BEAD_DEFAULTS["min_separation"],
                    help="least distance between beads, px (default %(default)s)")
    bd.add_argument("--margin", type=float, default=BEAD_DEFAULTS["margin"],
                    help="least distance of a bead from the sensor edge, px (default %(default)s)")
    bd.add_argument(
        "--setpoints",
        type=_number_list,
        default=list(PAPER_SETPOINTS),
        help="EM gain set-points, comma-separated (default 1,5,25,100,300)",
    )
    bd.add_argument(
        "--em-gain",
        type=_number_list,
        default=None,
        help="true mean EM gain per set-point, comma-separated "
        "(default 1,4.78,22.95,90.06,261.6 at the paper's set-points, else the set-point)",
    )
    bd.add_argument(
        "--offsets",
        type=_number_list,
        default=None,
        help="offset per set-point, ADU, comma-separated (overrides --offset/--offset-drop)",
    )
    _common_options(bd, {k: BEAD_DEFAULTS[k] for k in ("rows", "cols", "frames", "dark_frames")})
    bd.set_defaults(func=_run_beads)
    return p
