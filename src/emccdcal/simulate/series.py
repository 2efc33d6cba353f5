"""Gain and intensity series on disk: what a real calibration session writes.

:func:`simulate_gain_series` and :func:`simulate_intensity_series` write uint16 TIFF
stacks ``(frames, rows, cols)``, a dark stack per set-point with its per-pixel
``offset`` and ``read_noise`` maps (float32 TIFF, ADU), a ``manifest.toml``
(``docs/manifest.md``) and ``truth.json`` with the true values. The camera is a
:class:`~emccdcal.simulate.camera.Camera`; its stacks come from
:func:`~emccdcal.simulate.camera.simulate_frames`. ``docs/simulation.md`` has examples.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import __version__
from .._output import atomic_write, atomic_write_text, comment, toml_line
from .._util import check_int, check_number
from .._util import progress as progress_bar
from ..errors import OptionError
from ..model.noise import EMModel
from .camera import (
    _CHUNK_ELEMENTS,
    _DEFAULTS,
    _UNITS,
    PAPER_LEVELS,
    PAPER_SETPOINTS,
    Camera,
    default_em_gain,
    expected_moments,
    offset_at_setpoint,
    simulate_frames,
)

__all__ = ["SimulatedSeries", "simulate_gain_series", "simulate_intensity_series", "truth_document"]


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


def _write_tiff(path: Path, data: np.ndarray) -> Path:
    import tifffile

    return atomic_write(path, lambda tmp: tifffile.imwrite(tmp, data, photometric="minisblack"))


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


def _label(setpoint: float) -> str:
    return f"{setpoint:g}x"


def _options(camera: Camera, seed) -> dict:
    """The camera's fields and the seed (one drawn if None), as recorded in truth.json."""
    if seed is None:
        entropy = np.random.SeedSequence().entropy
        assert isinstance(entropy, int)  # a fresh SeedSequence draws one integer
        seed = entropy
    else:
        seed = check_int("seed", seed, minimum=0)
    return dataclasses.asdict(camera) | {"seed": seed}


def _setpoint_offset(name: str, value: float | None, setpoint: float, opts: dict) -> float:
    if value is None:
        off = offset_at_setpoint(setpoint, opts["offset"], opts["offset_drop"])
    else:
        off = value
    off = check_number(name, off)
    if off < 0:
        raise OptionError(
            f"{name} at set-point {setpoint:g} is {off:g} ADU, must be >= 0 "
            "(lower offset_drop or raise offset)"
        )
    return off


def _output_dir(outdir) -> Path:
    outdir = Path(outdir)
    if outdir.exists() and not outdir.is_dir():
        raise OptionError(f"outdir '{outdir}' exists and is not a directory")
    outdir.mkdir(parents=True, exist_ok=True)
    return outdir


def _write_stacks(
    outdir: Path,
    kind: str,
    acqs: list[dict],
    darks: list[dict],
    camera: Camera,
    opts: dict,
    progress: bool,
    seeds,
) -> tuple[list[Path], np.ndarray, str]:
    """Simulate and write the signal stacks ``acqs`` and the dark stacks ``darks``.

    ``seeds`` are ``1 + len(acqs) + len(darks)`` children of the run's SeedSequence: the
    offset pattern, then one per signal stack, then one per dark stack. Returns the
    files written, the offset pattern (ADU, as stored) and its file name.
    """
    shape = (opts["rows"], opts["cols"])
    pattern = np.random.default_rng(seeds[0]).normal(0.0, opts["offset_spread"], shape)
    pattern = pattern.astype(np.float32).astype(np.float64)  # exactly what the file holds
    files: list[Path] = []
    common = camera.register()
    total = sum(a["frames_n"] for a in acqs) + sum(d["frames_n"] for d in darks)
    with progress_bar(enabled=progress, desc=f"simulate {kind}", unit="frame", total=total) as bar:
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
                varying=a.get("varying", ()),
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


def _camera_truth(opts: dict, pattern_file: str) -> dict:
    """What truth.json records of the camera (in this order)."""
    return {
        "e_per_adu": opts["e_per_adu"],
        "read_noise": opts["read_noise"],
        "read_noise_dark_sd": math.sqrt(opts["read_noise"] ** 2 + 1.0 / 12.0),
        "cic": opts["cic"],
        "drift": opts["drift"],
        "multiplication": opts["multiplication"],
        "stages": EMModel(opts["multiplication"], opts["stages"]).attrs.get("register_stages"),
        "adc_bits": opts["adc_bits"],
        "offset_pattern": {
            "file": pattern_file,
            "sd": opts["offset_spread"],
            "note": "per-pixel offset = acquisition offset + this map (same at every set-point)",
        },
    }


def _truth_entry(a: dict, camera: Camera, opts: dict, **extra) -> dict:
    """What truth.json records of one acquisition; ``extra`` goes before its offset."""
    maps = {k: a[k] for k in ("offset_map", "read_noise_map") if k in a}
    return {
        "name": a["label"],
        "frames": a["frames"],
        "dark": a["dark"],
        **maps,
        "n_frames": a["frames_n"],
        "n_dark_frames": a.get("dark_frames_n", opts["dark_frames"]),
        "em_gain_setpoint": a["setpoint"],
        "em_gain": a["em_gain"],
        **extra,
        "offset": a["offset"],
        "excess_noise_factor": camera.excess_noise_factor(a["em_gain"]),
    }


def truth_document(
    kind: str, camera: Camera, opts: dict, acqs: list[dict], pattern_file: str
) -> dict:
    """The content of ``truth.json``: the camera, and each acquisition of ``acqs`` (dicts
    with label, frames, dark, frames_n, setpoint, em_gain, photoelectrons, offset and,
    where they differ from the camera's, dark_frames_n, offset_map, read_noise_map,
    level), with the moments its counts are expected to have.

    ``opts`` are the camera's fields and the seed (as :func:`_options` makes them);
    ``pattern_file`` names the file of the per-pixel offset pattern.
    """
    common = camera.register()
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
        entry = _truth_entry(
            a,
            camera,
            opts,
            photoelectrons=a["photoelectrons"],
            photoelectrons_with_cic=a["photoelectrons"] + opts["cic"],
        )
        entry["expected"] = {
            "mean": float(mean),
            "variance": float(var),
            "dark_mean": float(d_mean),
            "dark_variance": float(d_var),
        }
        if "level" in a:
            entry = {"level": a["level"], **entry}
        truth_acqs.append(entry)
    options = {k: opts[k] for k in sorted(opts) if k != "manifest_e_per_adu"}
    return {
        "kind": kind,
        "emccdcal_version": __version__,
        "seed": opts["seed"],
        "units": dict(_UNITS),
        **_camera_truth(opts, pattern_file),
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


def _run_series(
    outdir,
    kind: str,
    acqs: list[dict],
    darks: list[dict],
    camera: Camera,
    opts: dict,
    progress: bool,
):
    """Simulate and write the stacks of ``acqs`` (signal) and ``darks``; return the result."""
    outdir = _output_dir(outdir)
    seeds = np.random.SeedSequence(opts["seed"]).spawn(1 + len(acqs) + len(darks))
    files, _, pattern_file = _write_stacks(outdir, kind, acqs, darks, camera, opts, progress, seeds)
    truth = truth_document(kind, camera, opts, acqs, pattern_file)
    truth_path = outdir / "truth.json"
    files.append(atomic_write_text(truth_path, json.dumps(truth, indent=2) + "\n"))

    # manifest.toml, last: its presence means the series is complete
    lines = _manifest_lines(kind, acqs, opts)
    manifest = outdir / "manifest.toml"
    files.append(atomic_write_text(manifest, "\n".join(lines) + "\n"))
    return SimulatedSeries(outdir, manifest, truth_path, truth, tuple(files))


def _manifest_lines(kind: str, acqs: list[dict], opts: dict) -> list[str]:
    """Lines of the manifest of a simulated series (docs/results.md format)."""
    lines = [
        f"# Synthetic {kind} written by emccdcal {__version__} (emccdcal simulate {kind}).",
        "# Known truth: truth.json. Paths are relative to this file.",
    ]
    if opts.get("manifest_e_per_adu", True):
        lines.append(toml_line("e_per_adu", opts["e_per_adu"]))
    lines.append(toml_line("adc_bits", int(opts["adc_bits"])))
    for a in acqs:
        lines += [
            "",
            "[[acquisition]]",
            toml_line("name", str(a["label"])),
            toml_line("frames", str(a["frames"])),
            toml_line("em_gain_setpoint", float(a["setpoint"])),
        ]
        if "level" in a:
            lines.append(toml_line("level", str(a["level"])))
        lines += [
            toml_line("offset", str(a["offset_map"])),
            toml_line("read_noise", str(a["read_noise_map"])),
            toml_line("dark_frames", int(opts["dark_frames"]))
            + "  # the maps' own errors enter the SEs",
            comment(
                "# "
                + toml_line("dark", str(a["dark"]))
                + "  (the stack the maps were computed from)"
            ),
        ]
    return lines


def _gains(em_gain, setpoints) -> list[float]:
    if em_gain is None:
        return [default_em_gain(s) for s in setpoints]
    values = [em_gain] if np.ndim(em_gain) == 0 else list(em_gain)
    if len(values) != len(setpoints):
        raise OptionError(
            f"em_gain has {len(values)} value(s) but there are {len(setpoints)} set-points"
        )
    return [check_number("em_gain", v, minimum=1.0) for v in values]


def _setpoint_list(setpoints) -> list[float]:
    values = [setpoints] if np.ndim(setpoints) == 0 else list(setpoints)
    if not values:
        raise OptionError("setpoints must not be empty")
    out = [check_number("setpoints", s, minimum=1.0) for s in values]
    if len({_label(s) for s in out}) != len(out):
        raise OptionError(f"setpoints must be distinct, got {values!r}")
    return out


def _setpoint_acquisitions(stem, setpoints, gains, photoelectrons, offsets, opts) -> list[dict]:
    """One acquisition per set-point, with its dark stack and maps, for ``_write_stacks``.

    ``stem`` is the files' path without suffix, with ``{}`` for the set-point's label;
    ``offsets`` is None (the camera's offset at each set-point) or one per set-point.
    """
    if offsets is None:
        offsets = [None] * len(setpoints)
    else:
        offsets = [offsets] if np.ndim(offsets) == 0 else list(offsets)
        if len(offsets) != len(setpoints):
            raise OptionError(
                f"offsets has {len(offsets)} value(s) but there are {len(setpoints)} set-points"
            )
    acqs = []
    for s, g, E, off in zip(setpoints, gains, photoelectrons, offsets):
        lab = _label(s)
        base = stem.format(lab)
        acqs.append(
            {
                "label": lab,
                "setpoint": s,
                "em_gain": g,
                "photoelectrons": E,
                "offset": _setpoint_offset(
                    "offsets" if off is not None else "offset", off, s, opts
                ),
                "frames": f"{base}.tif",
                "frames_n": opts["frames"],
                "dark": f"{base}_no-signal.tif",
                "offset_map": f"{base}_no-signal_S0.tif",
                "read_noise_map": f"{base}_no-signal_sigma.tif",
            }
        )
    opts["offsets"] = [a["offset"] for a in acqs]
    return acqs


def simulate_gain_series(
    outdir,
    *,
    setpoints=PAPER_SETPOINTS,
    em_gain=None,
    photoelectrons=_DEFAULTS["photoelectrons"],
    offsets=None,
    frames=None,
    seed=None,
    progress=True,
    camera: Camera | None = None,
    **camera_options,
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
        between acquisitions (what ``gs-hierarchical`` models, docs/methods.md).
    offsets : sequence of float, optional
        Offset per set-point (ADU); overrides the camera's ``offset``/``offset_drop``.
    frames : int or sequence of int, optional
        Signal frames at every set-point, or one number per set-point (what a plan asks
        for, ``emccdcal plan``); default the camera's ``frames``.
    seed : int, optional
        Seed (≥ 0); None draws one, recorded in truth.json. The same seed and options
        give identical files.
    progress : bool, optional
        A progress bar (default): in a notebook or on a terminal; none in a pipe.
    camera : Camera, optional
        The camera (:class:`~emccdcal.simulate.camera.Camera`: sensor size, frames, φ,
        offset, read noise, register, ADC ...).
    **camera_options
        Fields of :class:`~emccdcal.simulate.camera.Camera` (``rows=16``,
        ``e_per_adu=5.2`` ...), replacing those of ``camera`` or of the default camera.

    Returns
    -------
    SimulatedSeries

    Examples
    --------
    >>> import tempfile, emccdcal
    >>> sim = emccdcal.simulate_gain_series(
    ...     tempfile.mkdtemp(), rows=4, cols=4, frames=200, setpoints=(1, 10, 100), seed=1,
    ...     progress=False,
    ... )
    >>> sim.manifest.name, [a["em_gain_setpoint"] for a in sim.truth["acquisitions"]]
    ('manifest.toml', [1.0, 10.0, 100.0])
    """
    if frames is not None and np.ndim(frames) == 0:  # the camera's own field
        camera_options, frames = camera_options | {"frames": frames}, None
    camera = Camera.of(camera, **camera_options)
    opts = _options(camera, seed) | {"setpoints": setpoints, "offsets": offsets}
    sps = _setpoint_list(setpoints)
    gains = _gains(em_gain, sps)
    Es = [photoelectrons] * len(sps) if np.ndim(photoelectrons) == 0 else list(photoelectrons)
    if len(Es) != len(sps):
        raise OptionError(
            f"photoelectrons has {len(Es)} value(s) but there are {len(sps)} set-points"
        )
    Es = [check_number("photoelectrons", v, minimum=0.0) for v in Es]
    opts.update(setpoints=sps, em_gain=gains, photoelectrons=Es[0] if len(set(Es)) == 1 else Es)
    acqs = _setpoint_acquisitions("gain-GS/{}-gain", sps, gains, Es, offsets, opts)
    if frames is not None:
        counts = list(frames)
        if len(counts) != len(sps):
            raise OptionError(
                f"frames has {len(counts)} value(s) but there are {len(sps)} set-points"
            )
        for a, n in zip(acqs, counts):
            a["frames_n"] = check_int("frames", n, minimum=2)
        each = [a["frames_n"] for a in acqs]
        opts["frames"] = each[0] if len(set(each)) == 1 else each
    darks = [a | {"frames_n": opts["dark_frames"]} for a in acqs]
    return _run_series(outdir, "gain-series", acqs, darks, camera, opts, progress)


def simulate_intensity_series(
    outdir,
    *,
    levels=PAPER_LEVELS,
    labels=None,
    setpoint=1,
    em_gain=None,
    seed=None,
    progress=True,
    camera: Camera | None = None,
    **camera_options,
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
    seed, progress, camera, **camera_options
        As in :func:`simulate_gain_series`.

    Returns
    -------
    SimulatedSeries

    Examples
    --------
    >>> import tempfile, emccdcal
    >>> sim = emccdcal.simulate_intensity_series(
    ...     tempfile.mkdtemp(), levels=(2000, 8000), rows=4, cols=4, frames=200, seed=1,
    ...     progress=False,
    ... )
    >>> phi = emccdcal.calibrate(sim.manifest, "is-adu", progress=False)
    >>> phi.e_per_adu.dims, sim.truth["e_per_adu"]
    (('row', 'col'), 3.859)
    """
    camera = Camera.of(camera, **camera_options)
    opts = _options(camera, seed)
    s = check_number("setpoint", setpoint, minimum=1.0)
    if em_gain is not None and np.ndim(em_gain) != 0:
        raise OptionError("em_gain must be a single number for an intensity series")
    g = _gains(em_gain, [s])[0]
    lv = [levels] if np.ndim(levels) == 0 else list(levels)
    if not lv:
        raise OptionError("levels must not be empty")
    lv = [check_number("levels", x, minimum=0.0) for x in lv]
    labs = [f"L{i + 1}" for i in range(len(lv))] if labels is None else [str(x) for x in labels]
    if len(labs) != len(lv):
        raise OptionError(f"labels has {len(labs)} value(s) but there are {len(lv)} levels")
    if len(set(labs)) != len(labs) or not all(x.strip() for x in labs):
        raise OptionError(f"labels must be distinct and non-empty, got {labs!r}")
    bad = [x for x in labs if any(ch in x for ch in '/\\:*?"<>|')]
    if bad:
        raise OptionError(f"labels must be usable in file names, got {bad[0]!r}")
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
    return _run_series(outdir, "intensity-series", acqs, [dark], camera, opts, progress)
