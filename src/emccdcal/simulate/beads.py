"""Bead movies with known truth, for the bead validation (``emccdcal simulate beads``).

A field of isolated fluorescent beads (Ryan et al. 2021, bead validation): every pixel
receives Poisson photoelectrons with mean ``E_k = Σ_b N_b·P_k + b`` (:func:`bead_scene`,
a pixel-integrated Gaussian PSF, optionally with a wider halo), then the camera of
:func:`~emccdcal.simulate.camera.simulate_frames` at each set-point. Besides the stacks,
darks and maps, :func:`simulate_beads` writes ``truth_calibration.nc``: the true
calibration in the result contract. ``docs/beads.md`` has examples.
"""

from __future__ import annotations

import hashlib
import json
import math

import numpy as np

from .. import __version__, defaults, result
from .._output import atomic_write, atomic_write_text, write_netcdf
from .._util import check_int, check_number
from ..errors import OptionError
from ..model.noise import EMModel
from ..model.psf import spot_image
from .camera import _UNITS, PAPER_SETPOINTS, Camera
from .series import (
    SimulatedSeries,
    _camera_truth,
    _gains,
    _manifest_lines,
    _options,
    _output_dir,
    _setpoint_acquisitions,
    _setpoint_list,
    _truth_entry,
    _write_stacks,
)

__all__ = [
    "simulate_beads",
    "bead_scene",
    "BEAD_DEFAULTS",
    "CAMERA_DEFAULTS",
    "TRUTH_CALIBRATION_FILE",
]

#: Defaults of the bead simulation (``docs/beads.md``) and its camera, where it differs
#: from the camera simulator's (declared in :mod:`emccdcal.defaults`).
BEAD_DEFAULTS = defaults.BEAD_SIMULATION
CAMERA_DEFAULTS = defaults.BEAD_CAMERA
#: File written beside the stacks: the true calibration in the result contract.
TRUTH_CALIBRATION_FILE = "truth_calibration.nc"


def _place_beads(n, rows, cols, margin, min_separation, rng) -> np.ndarray:
    """Random bead centres (row, col), at least ``margin`` px from the edges and
    ``min_separation`` px apart: by sequential rejection sampling, else (a tight fit,
    where early beads block the rest) on a jittered grid of such points."""
    lo_r, hi_r = margin, rows - 1 - margin
    lo_c, hi_c = margin, cols - 1 - margin
    if hi_r < lo_r or hi_c < lo_c:
        raise OptionError(
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
        placed = _grid_places(n, (lo_r, hi_r), (lo_c, hi_c), min_separation, rng)
    if placed is None:
        raise OptionError(
            f"cannot place {n} beads at least {min_separation:g} px apart and {margin:g} px "
            f"from the edges of a {rows}×{cols} sensor; use fewer beads, a smaller "
            "min_separation or a larger sensor"
        )
    return np.array(placed)


def _grid_places(n, rows, cols, min_separation, rng):
    """``n`` of the points of the widest grid spaced at least ``min_separation`` over the
    ranges ``rows`` and ``cols`` (px), chosen at random and each moved at random by at most
    half the spare spacing, within the ranges (so they stay ``min_separation`` apart);
    None if the grid holds fewer than ``n``."""
    axes = []
    for lo, hi in (rows, cols):
        k = int((hi - lo) // min_separation) + 1 if min_separation > 0 else n
        step = (hi - lo) / (k - 1) if k > 1 else 0.0
        spare = (step - min_separation) / 2 if k > 1 else (hi - lo) / 2
        axes.append((lo + step * np.arange(k) if k > 1 else np.array([(lo + hi) / 2]), spare))
    (r_at, r_spare), (c_at, c_spare) = axes
    points = [(r, c) for r in r_at for c in c_at]
    if len(points) < n:
        return None
    chosen = rng.choice(len(points), size=n, replace=False)
    # kept in the ranges: clipping only undoes an outward move, so the spacing holds
    return [
        (
            float(np.clip(points[i][0] + rng.uniform(-r_spare, r_spare), *rows)),
            float(np.clip(points[i][1] + rng.uniform(-c_spare, c_spare), *cols)),
        )
        for i in chosen
    ]


def bead_images(
    positions, photoelectrons, width, rows, cols, *, halo=0.0, halo_width=None
) -> np.ndarray:
    """Each bead's expected photoelectrons per pixel per frame, e⁻, shape (B, rows, cols).

    The PSF is the pixel-integrated Gaussian :func:`emccdcal.model.psf.spot_image` of SD
    ``width``, or with ``halo`` > 0 the mixture ``(1 − h)·G(width) + h·G(halo_width)``: a
    core and a wider halo, the simplest PSF that a single Gaussian does not describe
    (real objectives' wings, out-of-focus light). Every bead's light sums to its
    ``photoelectrons`` over an unbounded sensor.
    """
    pos = np.asarray(positions, dtype=float).reshape(-1, 2)
    n = np.broadcast_to(np.asarray(photoelectrons, dtype=float), (len(pos),))
    if not len(pos):
        return np.zeros((0, rows, cols))
    r, c = np.arange(rows), np.arange(cols)

    def gaussian(sd, total):
        params = np.column_stack(
            [pos[:, 1], pos[:, 0], np.full(len(pos), sd), total, np.zeros(len(pos))]
        )
        return spot_image(params, r, c)

    if halo == 0:
        return gaussian(width, n)
    return gaussian(width, (1.0 - halo) * n) + gaussian(halo_width, halo * n)


def bead_scene(
    positions, photoelectrons, width, background, rows, cols, *, halo=0.0, halo_width=None
) -> np.ndarray:
    """Expected photoelectrons per pixel per frame of a field of beads, e⁻.

    ``E_k = Σ_b N_b·P_k(x_b, y_b) + background`` with the PSF of :func:`bead_images`
    (the pixel-integrated Gaussian :func:`emccdcal.model.psf.spot_image`, or a core and
    a halo).

    Parameters
    ----------
    positions : array_like, shape (B, 2)
        Bead centres (row, col), pixel (pixel (r, c) is centred at integer indices).
    photoelectrons : float or array_like, shape (B,)
        N_b, each bead's total photoelectrons per frame (e⁻).
    width : float
        PSF standard deviation s (pixel); the core's with a halo.
    background : float
        Uniform background b (e⁻ per pixel per frame).
    rows, cols : int
        Sensor size (pixel).
    halo : float, optional
        Fraction of each bead's light in the halo (0: a Gaussian PSF).
    halo_width : float, optional
        The halo's standard deviation (pixel).

    Returns
    -------
    ndarray, shape (rows, cols)

    Examples
    --------
    >>> E = bead_scene([[10.0, 12.0]], 5000.0, 1.3, 10.0, 24, 24)
    >>> round(float(E.sum() - 10.0 * 24 * 24))
    5000
    >>> E = bead_scene([[20.0, 20.0]], 5000.0, 1.3, 0.0, 41, 41, halo=0.2, halo_width=3.0)
    >>> round(float(E.sum())), round(float(E[20, 20] / 5000), 4)
    (5000, 0.0753)
    """
    return (
        bead_images(
            positions, photoelectrons, width, rows, cols, halo=halo, halo_width=halo_width
        ).sum(axis=0)
        + background
    )


def _blinking(beads, frames, off_fraction, mean_off, rng) -> np.ndarray:
    """Each bead's on (1) / off (0) state in every frame of the series, shape (B, T): a
    two-state Markov chain per bead, off a fraction ``off_fraction`` of the frames in
    runs of ``mean_off`` frames on average, started in its stationary state."""
    if off_fraction == 0:
        return np.ones((beads, frames))
    to_on = 1.0 / mean_off
    to_off = to_on * off_fraction / (1.0 - off_fraction)
    u = rng.random((beads, frames))
    on = np.empty((beads, frames), bool)
    on[:, 0] = u[:, 0] >= off_fraction
    for t in range(1, frames):
        on[:, t] = np.where(on[:, t - 1], u[:, t] >= to_off, u[:, t] < to_on)
    return on.astype(float)


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
    offsets=None,
    seed=None,
    progress=True,
    camera: Camera | None = None,
    bleaching=BEAD_DEFAULTS["bleaching"],
    halo=BEAD_DEFAULTS["halo"],
    halo_width=BEAD_DEFAULTS["halo_width"],
    blinking=BEAD_DEFAULTS["blinking"],
    blink_frames=BEAD_DEFAULTS["blink_frames"],
    repeat=None,
    **camera_options,
) -> SimulatedSeries:
    """Simulate bead movies at several EM gain set-points, with darks and the true calibration.

    A field of isolated fluorescent beads (the paper's validation, docs/beads.md): every
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
    setpoints, em_gain, offsets, seed, progress
        As in :func:`~emccdcal.simulate.series.simulate_gain_series` (set-points 1, 5, 25,
        100, 300 and the paper's true gains by default).
    bleaching : float, optional
        Fraction of every bead's light lost to photobleaching from the first frame of the
        series to its last (0; e.g. 0.02): an exponential decay in the frames recorded,
        the set-points one after another in the order given. ``photoelectrons`` is the
        intensity at the first frame; the background does not fade.
    halo : float, optional
        Fraction of every bead's light in a wider Gaussian halo (0: the Gaussian PSF the
        bead fits assume; e.g. 0.2 for a PSF the fits do not describe, to test the
        residual-image pass of :func:`emccdcal.beads.validation.validate`).
    halo_width : float, optional
        The halo's standard deviation, pixel (default 3 × ``width``).
    blinking : float, optional
        Fraction of the frames in which a bead is off (0): every bead switches on and off
        independently, as a two-state Markov chain in the frames of the series, started
        in its stationary state; an off bead emits nothing in that frame.
    blink_frames : float, optional
        Mean length of an off run, frames (5).
    repeat : float, optional
        A set-point recorded again at the end of the series (e.g. 1): files
        ``beads/<s>x-repeat-beads.tif`` and an acquisition ``<s>x-repeat`` last in the
        manifest, which lets the validation see what changed over the series.
    camera, **camera_options
        As in :func:`~emccdcal.simulate.series.simulate_gain_series`; the default camera
        here is 64 × 64 px with 500 frames per bead movie and 2000 per dark stack
        (:data:`CAMERA_DEFAULTS`).

    Returns
    -------
    SimulatedSeries

    Examples
    --------
    >>> import tempfile, emccdcal
    >>> beads = emccdcal.simulate_beads(
    ...     tempfile.mkdtemp(), beads=3, setpoints=(1, 10), rows=40, cols=40, frames=20,
    ...     seed=1, progress=False,
    ... )
    >>> len(beads.truth["beads"])
    3
    """
    camera = Camera.of(camera, CAMERA_DEFAULTS, **camera_options)
    opts = _options(camera, seed) | {"setpoints": setpoints, "offsets": offsets}
    sps = _setpoint_list(setpoints)
    gains = _gains(em_gain, sps)
    n_beads = check_int("beads", beads, minimum=0) if positions is None else None
    s = check_number("width", width, positive=True)
    b = check_number("background", background, minimum=0.0)
    sep = check_number("min_separation", min_separation, minimum=0.0)
    edge = check_number("margin", margin, minimum=0.0)
    shape = (opts["rows"], opts["cols"])
    if repeat is not None:
        repeat = check_number("repeat", repeat, minimum=1.0)
        if repeat not in sps:
            raise OptionError(f"repeat = {repeat:g} is not one of the set-points {sps}")
    n_acqs = len(sps) + (repeat is not None)
    # Children 0 … 2A: the stacks; 2A + 1: the placement; 2A + 2: blinking.
    children = np.random.SeedSequence(opts["seed"]).spawn(3 + 2 * n_acqs)
    stack_seeds, place_seed, blink_seed = children[:-2], children[-2], children[-1]
    pos = _bead_positions(positions, n_beads, shape, edge, sep, np.random.default_rng(place_seed))
    n_beads = len(pos)
    n_values = [photoelectrons] if np.ndim(photoelectrons) == 0 else list(photoelectrons)
    if len(n_values) not in (1, n_beads):
        raise OptionError(
            f"photoelectrons has {len(n_values)} values but there are {n_beads} beads"
        )
    n_values = [check_number("photoelectrons", v, minimum=0.0) for v in n_values]
    N = np.broadcast_to(np.array(n_values), (n_beads,)).astype(float)
    h = check_number("halo", halo, minimum=0.0, maximum=1.0)
    h_sd = 3.0 * s if halo_width is None else check_number("halo_width", halo_width, positive=True)
    images = bead_images(pos, N, s, *shape, halo=h, halo_width=h_sd)
    scene = images.sum(axis=0) + b
    fade = check_number("bleaching", bleaching, minimum=0.0, maximum=0.99)
    off = check_number("blinking", blinking, minimum=0.0, maximum=0.9)
    off_run = check_number("blink_frames", blink_frames, minimum=1.0)
    opts.update(
        setpoints=sps,
        em_gain=gains,
        beads=n_beads,
        photoelectrons=n_values,
        width=s,
        background=b,
        min_separation=sep,
        margin=edge,
        bleaching=fade,
        halo=h,
        halo_width=h_sd if h else None,
        blinking=off,
        blink_frames=off_run,
    )
    acqs = _setpoint_acquisitions("beads/{}-beads", sps, gains, [scene] * len(sps), offsets, opts)
    if repeat is not None:
        again = dict(acqs[sps.index(repeat)])
        again["label"] += "-repeat"
        for key in ("frames", "dark", "offset_map", "read_noise_map"):
            again[key] = again[key].replace("-beads", "-repeat-beads")
        acqs.append(again)
        opts["repeat"] = repeat
    frames_off = _light_over_series(
        acqs,
        images,
        scene - b,
        fade,
        off,
        off_run,
        opts["frames"],
        np.random.default_rng(blink_seed),
    )
    darks = [a | {"frames_n": opts["dark_frames"]} for a in acqs]

    outdir = _output_dir(outdir)
    files, pattern, pattern_file = _write_stacks(
        outdir, "beads", acqs, darks, camera, opts, progress, stack_seeds
    )
    truth_acqs = [_truth_entry(a, camera, opts) for a in acqs]
    lines = _manifest_lines("beads", acqs, opts)
    lines[0] = (
        f"# Synthetic bead movies written by emccdcal {__version__} (emccdcal simulate beads)."
    )
    manifest_text = "\n".join(lines) + "\n"
    manifest = outdir / "manifest.toml"

    files.append(
        _write_truth_calibration(
            outdir, opts, sps, gains, scene, acqs, pattern, manifest, manifest_text
        )
    )
    truth = _bead_truth(opts, pos, N, frames_off, pattern_file, truth_acqs)
    truth_path = outdir / "truth.json"
    files.append(atomic_write_text(truth_path, json.dumps(truth, indent=2) + "\n"))
    files.append(atomic_write_text(manifest, manifest_text))
    return SimulatedSeries(outdir, manifest, truth_path, truth, tuple(files))


def _bead_truth(opts, pos, N, frames_off, pattern_file, truth_acqs) -> dict:
    """truth.json's content for :func:`simulate_beads` (the options already checked)."""
    units = dict(_UNITS) | {
        "width": "pixel",
        "background": "e-/px/frame",
        "bead photoelectrons": "e-/frame (whole bead)",
        "row": "pixel",
        "col": "pixel",
    }
    truth = {
        "kind": "beads",
        "emccdcal_version": __version__,
        "seed": opts["seed"],
        "units": units,
        "beads": [
            {"row": float(r), "col": float(c), "photoelectrons": float(n)}
            | ({"frames_off": k} if opts["blinking"] > 0 else {})
            for (r, c), n, k in zip(pos, N, frames_off)
        ],
        "width": opts["width"],
        "background": opts["background"],
        "bleaching": opts["bleaching"],
        "halo": opts["halo"],
        "halo_width": opts["halo_width"],
        "blinking": opts["blinking"],
        **_camera_truth(opts, pattern_file),
        "calibration": TRUTH_CALIBRATION_FILE,
        "acquisitions": truth_acqs,
        "notes": [
            "beads: centre (row, col) in pixels, pixel (r, c) centred at integer indices; "
            "photoelectrons per bead per frame (the whole PSF, also beyond any box)",
            "every pixel: Poisson photoelectrons with mean sum_b N_b P_k + background (+ cic)",
            "read_noise is the SD of the Gaussian read-out before rounding; "
            "dark-map SD ~ sqrt(read_noise^2 + 1/12)",
        ],
        "options": {k: opts[k] for k in sorted(opts)},
    }
    return truth


def _bead_positions(positions, n_beads, shape, margin, min_separation, rng) -> np.ndarray:
    """The beads' (row, col) centres: placed at random, or the ones given, checked."""
    if positions is None:
        return _place_beads(n_beads, shape[0], shape[1], margin, min_separation, rng)
    pos = np.asarray(check_number("positions", positions, scalar=False), dtype=float)
    pos = pos.reshape(-1, 2) if pos.size else np.zeros((0, 2))
    if pos.ndim != 2 or pos.shape[1] != 2:
        raise OptionError(f"positions must be (beads, 2) rows and columns, got shape {pos.shape}")
    outside = (pos < 0).any(axis=1) | (pos[:, 0] > shape[0] - 1) | (pos[:, 1] > shape[1] - 1)
    if outside.any():
        raise OptionError(
            f"bead position {pos[np.argmax(outside)].tolist()} is outside the "
            f"{shape[0]}×{shape[1]} sensor"
        )
    return pos


def _light_over_series(acqs, images, beads_light, fade, off, off_run, frames, rng) -> list:
    """The beads' light over the frames of the whole series, set on each acquisition as
    its ``varying`` part: bleaching decays it, blinking switches each bead off for runs of
    frames. Returns each bead's frames off."""
    total = frames * len(acqs)
    rate = -math.log1p(-fade) / max(1, total - 1)  # per frame
    decay = np.exp(-rate * np.arange(total))
    states = _blinking(len(images), total, off, off_run, rng)
    for i, a in enumerate(acqs):
        t = slice(i * frames, (i + 1) * frames)
        if off > 0:
            a["varying"] = [(image, decay[t] * on[t]) for image, on in zip(images, states)]
        elif fade > 0:
            a["varying"] = [(beads_light, decay[t])]
    return [int(v) for v in (1 - states).sum(axis=1)]


def _write_truth_calibration(
    outdir, opts, sps, gains, scene, acqs, pattern, manifest, manifest_text
):
    """The true calibration in the result contract (:mod:`emccdcal.result`), written."""
    shape = scene.shape
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
            "offset": (
                ("setpoint", "row", "col"),
                np.stack([np.clip(a["offset"] + pattern, 0.0, None) for a in acqs[: len(sps)]]),
                "ADU",
                "true offset S0 (set-point level plus the pixel pattern)",
            ),
            "read_noise": (
                ("setpoint", "row", "col"),
                np.full((len(sps),) + shape, math.sqrt(opts["read_noise"] ** 2 + 1.0 / 12.0)),
                "ADU",
                "true read noise: SD of dark counts, sqrt(sigma^2 + 1/12)",
            ),
        },
        attrs={
            "note": "true values of a bead simulation (emccdcal simulate beads); "
            "photoelectrons is the expected bead scene per pixel per frame, "
            "background included, CIC excluded",
            "multiplication": opts["multiplication"],
            # the register that made the frames: what a fit under this calibration uses
            **EMModel(opts["multiplication"], opts["stages"]).attrs,
        },
    )
    nc_path = outdir / TRUTH_CALIBRATION_FILE
    atomic_write(nc_path, lambda tmp: write_netcdf(ds, tmp))
    return nc_path
