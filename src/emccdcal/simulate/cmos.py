"""Synthetic sCMOS and qCMOS calibration series with per-pixel truth.

A camera without an EM register has, at every pixel p, its own offset S0_p (ADU),
conversion factor φ_p (e⁻/ADU) and read noise σ_p (ADU); in frame t

    count = clip(round(S0_p + a_p·s_t + n/φ_p + σ_p·z), 0, 2**adc_bits − 1),
    n ~ Poisson(E),  z ~ N(0, 1),

with E the level's photoelectrons per pixel per frame (a flat field) and, at a
random-telegraph (RTS) pixel, ``s_t ∈ {0, 1}`` a two-state Markov chain that switches
with probability ``rts_switch`` per frame and a step ``a_p`` of ``rts_step`` read-noise
widths (``s_t = 0`` elsewhere; with ``rts_states`` k > 2, ``s_t ∈ {0 … k − 1}``, each
switch to one of the others at random). The ADC's rounding is part of the model: the dark
counts' standard deviation is about sqrt(σ² + 1/12) ADU, not σ.

:func:`simulate_cmos_series` writes what Huang et al.'s protocol (Nat. Methods 10:653,
2013) has a user record: ``dark.tif`` and ``int1.tif`` … ``intN.tif`` (uint16, frames ×
rows × cols), a ``manifest.toml`` naming the camera kind, ``truth.json`` and the true
maps as float32 TIFFs (``truth-*.tif``). :data:`PRESETS` holds the two cameras' typical
values: an ORCA-Flash4.0-like sCMOS (0.46 e⁻/ADU, 1.4 e⁻ median read noise with a long
tail) and an ORCA-Quest-like qCMOS (0.107 e⁻/ADU, 0.27 e⁻: photon numbers resolved).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass

import numpy as np

from .. import __version__
from .._output import atomic_write_text, toml_line
from .._util import check_int, check_number
from .._util import progress as progress_bar
from ..errors import OptionError
from .series import SimulatedSeries, _output_dir, _write_tiff

__all__ = ["CMOSCamera", "PRESETS", "simulate_cmos_frames", "simulate_cmos_series"]

#: Typical values of the two kinds (read noise in e⁻, the data sheets' unit).
PRESETS = {
    "scmos": dict(
        e_per_adu=0.46, e_per_adu_spread=0.02, offset=100.0, offset_spread=2.0,
        read_noise_e=1.4, read_noise_spread=0.35,
    ),
    "qcmos": dict(
        e_per_adu=0.107, e_per_adu_spread=0.01, offset=200.0, offset_spread=1.0,
        read_noise_e=0.27, read_noise_spread=0.15,
    ),
}  # fmt: skip

#: Photoelectrons per pixel per frame of the default levels (``int1`` … ``int4``).
DEFAULT_LEVELS = {"scmos": (20.0, 60.0, 150.0, 400.0), "qcmos": (0.5, 1.5, 4.0, 10.0)}


@dataclass(frozen=True)
class CMOSCamera:
    """A simulated camera without an EM register, and its per-pixel truth's distribution.

    Attributes
    ----------
    kind : {"scmos", "qcmos"}
        Which preset fills the values not given.
    rows, cols : int
        Sensor size, px (24 × 24).
    frames : int
        Frames per illuminated stack (2000).
    dark_frames : int
        Frames of the dark stack (default: ``frames``).
    e_per_adu : float
        Median conversion factor φ, e⁻/ADU.
    e_per_adu_spread : float
        Relative SD of φ over the pixels (a normal, dimensionless).
    offset, offset_spread : float
        Mean and SD of the per-pixel offset, ADU.
    read_noise_e : float
        Median read noise, e⁻ (rms, before the ADC's rounding).
    read_noise_spread : float
        SD of ln σ over the pixels (a log-normal: a tail of noisy pixels).
    read_noise_min_e : float
        Smallest read noise any pixel has, e⁻ (0.2).
    rts_fraction : float
        Fraction of pixels with a random-telegraph offset (0).
    rts_step : float
        Step between an RTS pixel's neighbouring offset states, in its read-noise widths (4).
    rts_switch : float
        Probability per frame that an RTS pixel switches state (0.05).
    rts_states : int
        Offset states of an RTS pixel, ``rts_step`` apart (2).
    adc_bits : int
        ADC resolution, bits (16).
    dark_current : float
        Median dark current, e⁻ per pixel per second (0; a series of darks at several
        exposures, :func:`simulate_cmos_series`'s ``dark_exposures_s``, needs it).
    dark_current_spread : float
        SD of the log dark current over the pixels (0.5: a log-normal).
    hot_fraction : float
        Fraction of hot pixels (0): their dark current is ``hot_factor`` times what the
        log-normal gave them.
    hot_factor : float
        How much a hot pixel's dark current exceeds its draw (30).
    """

    kind: str = "scmos"
    rows: int = 24
    cols: int = 24
    frames: int = 2000
    dark_frames: int | None = None
    e_per_adu: float | None = None
    e_per_adu_spread: float | None = None
    offset: float | None = None
    offset_spread: float | None = None
    read_noise_e: float | None = None
    read_noise_spread: float | None = None
    read_noise_min_e: float = 0.2
    rts_fraction: float = 0.0
    rts_step: float = 4.0
    rts_switch: float = 0.05
    rts_states: int = 2
    adc_bits: int = 16
    dark_current: float = 0.0
    dark_current_spread: float = 0.5
    hot_fraction: float = 0.0
    hot_factor: float = 30.0

    def __post_init__(self):
        if self.kind not in PRESETS:
            raise OptionError(f"kind must be one of {', '.join(PRESETS)}, got {self.kind!r}")
        values = {k: v for k, v in dataclasses.asdict(self).items() if v is not None}
        values = PRESETS[self.kind] | values
        frames = check_int("frames", values["frames"])
        checked = dict(
            rows=check_int("rows", values["rows"]),
            cols=check_int("cols", values["cols"]),
            frames=frames,
            dark_frames=check_int("dark_frames", values.get("dark_frames", frames), minimum=2),
            e_per_adu=check_number("e_per_adu", values["e_per_adu"], positive=True),
            e_per_adu_spread=check_number(
                "e_per_adu_spread", values["e_per_adu_spread"], minimum=0.0, maximum=0.3
            ),
            offset=check_number("offset", values["offset"], minimum=0.0),
            offset_spread=check_number("offset_spread", values["offset_spread"], minimum=0.0),
            read_noise_e=check_number("read_noise_e", values["read_noise_e"], positive=True),
            read_noise_spread=check_number(
                "read_noise_spread", values["read_noise_spread"], minimum=0.0
            ),
            read_noise_min_e=check_number(
                "read_noise_min_e", values["read_noise_min_e"], positive=True
            ),
            rts_fraction=check_number(
                "rts_fraction", values["rts_fraction"], minimum=0.0, maximum=1.0
            ),
            rts_step=check_number("rts_step", values["rts_step"], positive=True),
            rts_switch=check_number("rts_switch", values["rts_switch"], positive=True, maximum=1.0),
            rts_states=check_int("rts_states", values["rts_states"], minimum=2, maximum=8),
            adc_bits=check_int("adc_bits", values["adc_bits"], minimum=1, maximum=16),
            dark_current=check_number("dark_current", values["dark_current"], minimum=0.0),
            dark_current_spread=check_number(
                "dark_current_spread", values["dark_current_spread"], minimum=0.0
            ),
            hot_fraction=check_number(
                "hot_fraction", values["hot_fraction"], minimum=0.0, maximum=1.0
            ),
            hot_factor=check_number("hot_factor", values["hot_factor"], minimum=1.0),
        )
        for name, value in checked.items():
            object.__setattr__(self, name, value)

    @property
    def shape(self) -> tuple:
        """(rows, cols) of the sensor, px."""
        return (self.rows, self.cols)

    def maps(self, rng) -> dict:
        """The per-pixel truth drawn from ``rng``: ``e_per_adu`` (e⁻/ADU), ``offset``
        (ADU), ``read_noise`` (ADU, before rounding), ``rts_step`` (ADU, 0 where the
        pixel has one offset state), ``dark_current`` (e⁻/s), ``hot`` (1 at a hot pixel,
        else 0)."""
        shape = (self.rows, self.cols)
        phi = self.e_per_adu * (1.0 + self.e_per_adu_spread * rng.standard_normal(shape))
        phi = np.maximum(phi, 0.5 * self.e_per_adu)
        offset = self.offset + self.offset_spread * rng.standard_normal(shape)
        sigma_e = self.read_noise_e * np.exp(self.read_noise_spread * rng.standard_normal(shape))
        sigma = np.maximum(sigma_e, self.read_noise_min_e) / phi
        rts = rng.random(shape) < self.rts_fraction
        spread = np.exp(self.dark_current_spread * rng.standard_normal(shape))
        # drawn last, and only where asked: every other draw as without hot pixels
        hot = rng.random(shape) < self.hot_fraction if self.hot_fraction else np.zeros(shape, bool)
        return dict(
            e_per_adu=phi,
            offset=offset,
            read_noise=sigma,
            rts_step=np.where(rts, self.rts_step * sigma, 0.0),
            dark_current=self.dark_current * spread * np.where(hot, self.hot_factor, 1.0),
            hot=hot.astype(float),
        )


def _telegraph(frames, rts_step, switch, rng, states=2):
    """The RTS offset (frames, rows, cols), ADU: each RTS pixel's chain of ``states``
    offset states, started in its stationary distribution (uniform)."""
    live = np.flatnonzero(rts_step)
    out = np.zeros((frames,) + rts_step.shape)
    if live.size == 0:
        return out
    flips = rng.random((frames, live.size)) < switch
    if states == 2:
        flips[0] = rng.random(live.size) < 0.5
        state = np.cumsum(flips, axis=0) % 2
    else:  # a switch goes to one of the other states, each alike
        jumps = flips * rng.integers(1, states, flips.shape)
        jumps[0] = rng.integers(0, states, live.size)
        state = np.cumsum(jumps, axis=0) % states
    out.reshape(frames, -1)[:, live] = state * rts_step.ravel()[live]
    return out


def simulate_cmos_frames(
    photoelectrons, maps, frames, rng, *, adc_bits=16, rts_switch=0.05, rts_states=2
):
    """One stack of raw counts (frames, rows, cols), uint16, ADU (module docstring).

    Parameters
    ----------
    photoelectrons : float or ndarray (rows, cols)
        E, photoelectrons per pixel per frame (e⁻; 0 for a dark without dark current).
    maps : dict
        Per-pixel truth, as :meth:`CMOSCamera.maps` draws it.
    frames : int
    rng : numpy.random.Generator
    adc_bits : int
    rts_switch : float
        RTS switching probability per frame.
    rts_states : int
        Offset states of an RTS pixel.
    """
    shape = maps["offset"].shape
    lam = np.broadcast_to(np.asarray(photoelectrons, dtype=float), shape)
    n = rng.poisson(lam, (frames,) + shape) if lam.any() else 0.0
    x = (
        maps["offset"]
        + n / maps["e_per_adu"]
        + maps["read_noise"] * rng.standard_normal((frames,) + shape)
    )
    x += _telegraph(frames, maps["rts_step"], rts_switch, rng, rts_states)
    return np.clip(np.rint(x), 0, 2**adc_bits - 1).astype(np.uint16)


def _exposures(camera, dark_exposures_s):
    """The photon-free series' exposures (s), sorted, or None for a lit series."""
    if dark_exposures_s is None:
        return None
    t = sorted(check_number("dark_exposures_s", x, positive=True) for x in dark_exposures_s)
    if len(set(t)) < 2:
        raise OptionError("dark_exposures_s needs two or more different exposures (s)")
    if camera.dark_current <= 0:
        raise OptionError(
            "dark exposures need a camera with a dark current > 0 (dark_current, "
            "--dark-current: e-/px/s)"
        )
    return t


def simulate_cmos_series(
    outdir,
    *,
    camera: CMOSCamera | None = None,
    levels=None,
    dark_exposures_s=None,
    exposure_s=None,
    seed=None,
    progress=True,
    **options,
) -> SimulatedSeries:
    """Simulate a Huang-protocol calibration of an sCMOS or qCMOS camera on disk.

    Writes ``dark.tif`` (``dark_frames`` frames, shutter closed), ``int1.tif`` …
    ``intN.tif`` (one per level), ``truth-e_per_adu.tif``, ``truth-offset.tif``,
    ``truth-read_noise.tif`` (ADU, before rounding), ``truth-rts_step.tif`` (RTS step,
    ADU; 0 elsewhere), ``truth-dark_current.tif`` (e⁻/s), ``truth-hot.tif`` (1 at a hot
    pixel), ``truth.json`` and ``manifest.toml``. The manifest names the
    camera kind and no EM gain: ``emccdcal calibrate manifest.toml`` needs no option.

    Parameters
    ----------
    outdir : path
    camera : CMOSCamera, optional
        The camera; ``options`` are its fields otherwise (``kind="qcmos"``, ...).
    levels : sequence of float, optional
        Photoelectrons per pixel per frame of each level (e⁻; :data:`DEFAULT_LEVELS`).
    dark_exposures_s : sequence of float, optional
        The photon-free path (Diekmann et al. 2022): no light; dark stacks
        ``dark-<t>s.tif`` at these exposures (s), the shortest the others' dark, each
        with the camera's ``dark_current`` (e⁻/s) times its exposure; the manifest says
        ``light = false`` and every exposure. ``levels`` is then not used.
    exposure_s : float, optional
        A lit series' exposure (s): the dark current's signal, ``dark_current`` times
        it (e⁻ per pixel per frame), in the dark and in every level (the levels' light
        as ``levels`` says). None (default): none, whatever the dark current.
    seed : int
        Seed of every draw (truth maps and frames).
    progress : bool

    Examples
    --------
    >>> import tempfile, emccdcal
    >>> from emccdcal.simulate.cmos import simulate_cmos_series
    >>> sim = simulate_cmos_series(tempfile.mkdtemp(), kind="qcmos", rows=2, cols=3,
    ...                            frames=50, seed=1, progress=False)
    >>> sorted(p.name for p in sim.files if p.name.startswith(("dark", "int")))
    ['dark.tif', 'int1.tif', 'int2.tif', 'int3.tif', 'int4.tif']
    """
    camera = camera if camera is not None else CMOSCamera(**options)
    if camera is not None and options:
        camera = dataclasses.replace(camera, **options)
    seed = check_int(
        "seed", seed if seed is not None else np.random.SeedSequence().entropy % 2**63, minimum=0
    )
    exposures = _exposures(camera, dark_exposures_s)
    if exposure_s is not None and exposures is not None:
        raise OptionError(
            "exposure_s is a lit series' exposure; the photon-free path's are dark_exposures_s"
        )
    if exposures is None:
        lv = DEFAULT_LEVELS[camera.kind] if levels is None else tuple(levels)
        lv = [check_number("levels", x, positive=True) for x in lv]
        if not lv:
            raise OptionError("levels must not be empty")
    else:
        lv = exposures[1:]
    outdir = _output_dir(outdir)
    streams = [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(2 + len(lv))]
    maps = camera.maps(streams[0])
    files = [
        _write_tiff(outdir / f"truth-{name}.tif", value.astype(np.float32))
        for name, value in maps.items()
    ]
    if exposures is None:
        thermal = 0.0
        if exposure_s is not None:
            thermal = maps["dark_current"] * check_number("exposure_s", exposure_s, positive=True)
        stacks = [("dark.tif", thermal, camera.dark_frames)] + [
            (f"int{i + 1}.tif", E + thermal, camera.frames) for i, E in enumerate(lv)
        ]
    else:  # the thermal signal of each exposure, the shortest the others' dark
        stacks = [
            (f"dark-{t:g}s.tif", maps["dark_current"] * t, n)
            for t, n in zip(exposures, [camera.dark_frames] + [camera.frames] * len(lv))
        ]
    bar = progress_bar(enabled=progress, desc="simulate", unit="stack", total=len(stacks))
    for (name, E, frames), rng in zip(stacks, streams[1:]):
        data = simulate_cmos_frames(
            E, maps, frames, rng, adc_bits=camera.adc_bits, rts_switch=camera.rts_switch,
            rts_states=camera.rts_states,
        )  # fmt: skip
        files.append(_write_tiff(outdir / name, data))
        bar.update(1)
    bar.close()
    truth = {
        "kind": f"{camera.kind}-series",
        "emccdcal_version": __version__,
        "camera": camera.kind,
        "seed": seed,
        "levels": dict(zip((s[0] for s in stacks[1:]), lv)),
        "exposures_s": None if exposures is None else dict(zip((s[0] for s in stacks), exposures)),
        "exposure_s": exposure_s if exposures is None else None,
        "maps": {name: f"truth-{name}.tif" for name in maps},
        "units": {
            "levels": "e-/px/frame",
            "e_per_adu": "e-/ADU",
            "offset": "ADU",
            "read_noise": "ADU (rms, before the ADC's rounding)",
            "rts_step": "ADU",
            "dark_current": "e-/px/s",
            "hot": "1 at a hot pixel, else 0",
            "exposures_s": "s",
            "exposure_s": "s",
        },
        "options": dataclasses.asdict(camera),
    }
    truth_path = atomic_write_text(outdir / "truth.json", json.dumps(truth, indent=2) + "\n")
    files.append(truth_path)
    lines = [
        f"# Synthetic {camera.kind} calibration written by emccdcal {__version__}.",
        "# Known truth: truth.json and truth-*.tif. Paths are relative to this file.",
        toml_line("camera_kind", camera.kind),
        toml_line("adc_bits", camera.adc_bits),
    ]
    if exposures is not None:
        lines.append(toml_line("light", False))
    for i, (name, _, _) in enumerate(stacks[1:], 1):
        stem = name.removesuffix(".tif")
        lines += ["", "[[acquisition]]", toml_line("frames", name), toml_line("level", stem)]
        lines.append(toml_line("dark", stacks[0][0]))
        if exposures is not None:
            lines.append(toml_line("exposure_s", exposures[i]))
            lines.append(toml_line("dark_exposure_s", exposures[0]))
    manifest = atomic_write_text(outdir / "manifest.toml", "\n".join(lines) + "\n")
    files.append(manifest)
    return SimulatedSeries(outdir, manifest, truth_path, truth, tuple(files))
