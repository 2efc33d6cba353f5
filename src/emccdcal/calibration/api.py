"""The call (:func:`calibrate`): the options checked, φ read, the fit specified at the door, the output opened, the tiles planned and run, the result assembled, checked and recorded."""

from __future__ import annotations

import contextlib
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .. import _xp, defaults, result
from .._output import Output
from .._util import check_int, nanmedian
from ..errors import (
    FitWarning,
    MethodError,
    OptionError,
)
from ..fit.series import specify
from ..given_phi import e_per_adu_inputs
from ..defaults import DEFAULT_BLOCK, DEFAULT_TILE_PIXELS, INTERVALS, METHODS
from ..runstore import RESULT_FILES, RunStore, remove_run
from .tiles import ESTIMATE_E_PER_ADU, FIXED_E_PER_ADU, TileJob, _labels, _load, plan_tiles
from .datasets import (
    _add_dark_current,
    _add_findings,
    _joined,
    _likelihood_dataset,
    _map_error_sources,
    _mv_dataset,
    _record_provenance,
    _warn_saturated_and_unusable,
)
from .profiling import _fingerprint, _profile_stages
from .schedulers import _reach_or_refuse, _run_tiles, choose_scheduler

if TYPE_CHECKING:
    import xarray


# --------------------------------------------------------------------------------------
# The calibration
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RunRequest:
    """What a :func:`calibrate` call asks for, checked (its parameters say what each is):
    one record for the run instead of twenty arguments."""

    method: str
    e_per_adu: object
    resume: bool
    overwrite: bool
    block_size: int
    tile_pixels: int
    scheduler: object
    options: dict | None
    progress: object
    workers: int
    checks: bool
    map_errors: bool
    intervals: str | None
    em_model: object
    stages: object
    accept_mismatch: tuple
    accept_phi: bool
    device: str | None


def calibrate(
    manifest,
    method=None,
    *,
    e_per_adu=None,
    out=None,
    resume=False,
    overwrite=False,
    block_size=DEFAULT_BLOCK,
    tile_pixels=DEFAULT_TILE_PIXELS,
    scheduler=None,
    options=None,
    progress=True,
    workers=None,
    checks=True,
    map_errors=True,
    intervals="wald",
    em_model=None,
    stages=None,
    accept_mismatch=(),
    accept_phi=False,
    device=None,
) -> xarray.Dataset:
    """Calibrate a camera from the acquisitions of a manifest.

    Parameters
    ----------
    manifest : str, Path or :class:`emccdcal.Manifest`
        The TOML manifest (see ``docs/manifest.md``).
    method : str, optional
        One of :data:`METHODS`: ``mv-adu``, ``mv-gain``, ``is-adu``, ``is-gain``, ``gs``,
        ``gs-no1x``, ``gs-hierarchical``. Default: ``is-adu`` for a camera without an EM
        register (the manifest's ``camera_kind``: sCMOS, qCMOS, CCD), else ``gs``.
    e_per_adu : float, ndarray (rows, cols), str, Path, xarray.Dataset or Calibration, optional
        φ (e⁻/ADU) overriding the manifest's, for the methods that hold it fixed (an
        error for ``is-adu`` and ``mv-adu``, which estimate it): a number, a map, or an
        ``is-adu`` or ``mv-adu`` result (what ``calibrate`` returned, its
        ``calibration.nc`` or directory, or a :class:`emccdcal.Calibration`), whose φ and
        standard error per pixel are then used: the standard errors of E and g include
        φ's (the delta method through the likelihood; :doc:`/results`).
    out : str or Path, optional
        Directory to write ``calibration.nc`` and ``summary.json`` into; finished tiles
        are kept there while the run goes on (:mod:`emccdcal.runstore`).
    resume : bool
        Continue the interrupted run in ``out`` (refused when its inputs differ).
    overwrite : bool
        Replace whatever ``out`` holds of an earlier run. With neither, an ``out`` that
        holds a finished or interrupted run is an error.
    block_size : int
        Pixels fitted together. The result does not depend on it (to round-off: the
        FFTs' lengths are a block's), but where a faint photoelectron comb's rival
        ripples set φ's error (``is-adu`` on an sCMOS's pixels below ~0.7 e⁻), the
        ripple a pixel's fit ends on can differ by one, a small fraction of its SE
        (docs/cmos.md).
    tile_pixels : int
        Pixels per tile, rounded to whole rows (at least one row): what is read, fitted
        and kept at once. Peak memory grows with it, not with the sensor; the result
        does not depend on it but as on ``block_size`` (tiles are whole blocks).
    scheduler : str or distributed.Client, optional
        Run the tiles as tasks on a Dask cluster: the address of its scheduler
        (``"tcp://host:8786"``) or a client. The workers read the files from the paths of
        the manifest, so these must be shared. ``"processes"``: the tiles in ``workers``
        local processes, one thread each (the cores of a large machine, which threads
        share less well); ``"threads"``: here, on ``workers`` threads. Default: local
        processes where they are faster (a sensor of 4096 pixels or more, in at least
        two tiles per worker, on the CPU:
        :func:`emccdcal.calibration.schedulers.default_scheduler`), else here, on
        ``workers`` threads. The result does not depend on where the tiles ran.
    options : dict, optional
        Method options; only ``gs-hierarchical`` takes any (:func:`emccdcal.fit.layouts.check_options`):
        ``mu_sd`` and ``sigma_sd``, the scales of its hyperpriors in photoelectrons (the
        authors' 25 e⁻ by default, for an illumination of about 370 e⁻: scale them in
        proportion to yours), and ``centre`` (``"gs"`` or the authors' ``"setpoint"``).
    progress : bool or callable
        A progress bar (default): in a notebook or on a terminal, none in a pipe; or a
        callable ``progress(done, total)`` told of the
        pixels done instead (a graphical front's bar), which may raise
        :class:`emccdcal.errors.Cancelled` to stop the run between blocks of pixels.
    workers : int, optional
        Threads reading and fitting at once within a tile, or local processes each
        fitting a tile (default: the number of CPUs; 1 on a Dask cluster, whose workers
        run tiles in parallel).
    checks : bool
        Run the data-quality checks (:mod:`emccdcal.data.quality`: drift of the
        illumination, saturation, hot/dead pixels) and store them in the result
        (``attrs["quality"]``, JSON) and ``summary.json``; findings are warnings.
    map_errors : bool
        Include in the standard errors of the likelihood methods the error of offset and
        read-noise maps estimated from dark frames (``dark`` stacks, or maps with
        ``dark_frames`` in the manifest): the offset map's own SE is σ/√n_dark, which moves
        E at 1× by φσ/√n_dark. ``False`` gives SEs conditional on the maps. Maps without a
        known number of dark frames are always taken as exact.
    intervals : {"wald", "profile"}
        ``"profile"`` adds 95 % profile-likelihood bounds ``<name>_lower``/``<name>_upper``
        for the likelihood methods' free parameters: they follow a skewed likelihood
        (few photoelectrons, weak set-points) where ``estimate ± 1.96 SE`` does not. They
        include the maps' errors as the SEs do (their deviance target grows by the ratio
        of the variances with and without them) and cost about ten refits per parameter. The
        mean–variance methods have no likelihood (``"profile"`` is an error there); their
        results always carry 95 % Fieller bounds (:func:`emccdcal.fit.mv.fieller_interval`).
        ``gs-hierarchical`` results always carry bounds too, those of the same model
        without its prior (:func:`emccdcal.fit.layouts.unpooled_bounds`): its MAP ± 1.96 SE
        over-covers where the true E is shared and under-covers where it is not.

    em_model : {"gamma", "cascade"} or noise.EMModel, optional
        The EM register's model in the likelihood methods (and mv-gain's F²): the exact
        Bernoulli cascade (:class:`emccdcal.noise.EMModel`) or the paper's gamma
        approximation; default the manifest's ``em_model``, else the cascade. Pass
        ``"gamma"`` to reproduce the paper's numbers. On an exact register the gamma
        model reads every gain 0.2–0.8 % low in ``gs`` and about F²/2 − 1 low (−3 % at
        25×, −10 % at 5×) where E and g share one set-point's shape (``is-gain``,
        ``gs-no1x``), and misfits the low gains; the cascade costs about 1.3–1.5 times
        the time in ``gs`` (docs/cascade.md).
    stages : int or "auto", optional
        Stages of the cascade: default the manifest's ``register_stages``, else the
        length a public source states for the files' camera model
        (:data:`emccdcal.model.cascade.KNOWN_REGISTERS`), else 536; where it came from is
        ``attrs["register_stages_source"]``. ``"auto"`` takes the length of largest
        likelihood on the sensor's middle pixels over :data:`STAGE_GRID` (128–4096) and
        records the profile (``attrs["register_stages_grid"]``,
        ``attrs["register_stages_profile"]``, Δ log-likelihood in nats).
    accept_mismatch : iterable of str
        Identity fields (:data:`emccdcal.identity.ACCEPTABLE`) in which the frames may
        differ from the result φ is taken from: by default φ of another camera or read-out
        state is refused.
    accept_phi : bool
        Use a given φ even where the 1× acquisition's photon transfer says otherwise
        (:func:`emccdcal.fit.series.specify`); by default such a φ (in ADU/e⁻, say, or of another
        read-out mode) is refused before any fitting.
    device : {"cpu", "cuda", "jax", "array-api-strict"}, optional
        Where the likelihood's windows and sums are computed (docs/running.md): the CPU
        (NumPy, the default); an NVIDIA GPU through CuPy or PyTorch (the extra ``gpu``);
        JAX's first device, its GPU where it has one, else the CPU (the extra ``jax``;
        double precision is turned on in JAX for the process); or array-api-strict, the
        CPU through the array API standard alone (a check, not a speed-up). The numbers
        agree within 1e-9; the result records the device.

    Returns
    -------
    xarray.Dataset
        The calibration (see ``docs/results.md``); ``ds.attrs["seconds"]`` is the wall time.

    Examples
    --------
    >>> ds = calibrate("gain-series/manifest.toml", method="gs")  # doctest: +SKIP
    >>> ds.em_gain.sel(setpoint=300).mean().item()                 # doctest: +SKIP
    261.6
    """
    if method is None:  # the manifest's camera kind says (its TOML only: no data read yet)
        kind = getattr(manifest, "camera_kind", None)
        if not hasattr(manifest, "camera_kind"):
            from ..data.manifest.parse import parse_manifest

            kind = parse_manifest(manifest).camera_kind
        method = defaults.default_method(kind)
    if method not in METHODS:
        raise MethodError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if intervals not in INTERVALS:
        raise OptionError(f"unknown intervals {intervals!r}; choose one of {', '.join(INTERVALS)}")
    if intervals == "profile" and method.startswith("mv-"):
        raise MethodError(
            f"{method} has no likelihood: profile intervals need a "
            f"likelihood method ({method} results always carry Fieller bounds)"
        )
    if e_per_adu is not None and method in ESTIMATE_E_PER_ADU:
        raise OptionError(
            f"{method} estimates e_per_adu itself: a given e_per_adu is for "
            f"the methods that hold it fixed ({', '.join(FIXED_E_PER_ADU)})"
        )
    block_size = check_int("block_size", block_size)
    tile_pixels = check_int("tile_pixels", tile_pixels)
    workers = os.cpu_count() if workers is None else check_int("workers", workers)
    # an unknown device, or one whose library is missing: one line now
    block_size, tile_pixels = _blocks_for(
        _xp.free_bytes(*_xp.resolve(device)), block_size, tile_pixels
    )
    # Every warning of the run (manifest, saturation, convergence, misfit) is recorded in
    # the result and issued again to the caller.
    # The output is locked, and checked, for the whole run (the tiles are kept as they
    # finish, so nothing is staged); the result's files go as one set, the tiles last.
    run = RunRequest(
        method,
        e_per_adu,
        resume,
        overwrite,
        block_size,
        tile_pixels,
        scheduler,
        options,
        progress,
        workers,
        checks,
        map_errors,
        intervals,
        em_model,
        stages,
        tuple(accept_mismatch),
        accept_phi,
        device,
    )
    target = None if out is None else Output(out, kind="folder", stage=False)
    with target or contextlib.nullcontext():
        ds = result.run_recorded(
            lambda: _run_calibration(manifest, run, target),
        )
        if out is not None:
            result.save(ds, out, seconds=ds.attrs["seconds"], stale=RESULT_FILES)
            remove_run(out)
    return ds


#: On a GPU: the device memory a block's pixel may take (its windows, their derivatives
#: and FFTs, five acquisitions of up to 16 384 counts: an estimate, not yet measured), the
#: share of the free memory blocks may fill, and the largest block (a tile's histograms
#: are held on the host, about 16 bytes per frame, pixel and acquisition at high gain).
_DEVICE_BYTES_PER_PIXEL = 16 * 2**20
_DEVICE_SHARE = 0.25
_DEVICE_MAX_BLOCK = 8192


def _blocks_for(free_bytes, block_size, tile_pixels) -> tuple[int, int]:
    """(block_size, tile_pixels) for a device with ``free_bytes`` of free memory (None:
    the CPU, whose defaults stand): blocks as large as a quarter of the free memory holds
    (up to :data:`_DEVICE_MAX_BLOCK`), where the caller kept the default; a GPU runs a
    few large batches fast and many small ones slowly. Tiles hold whole blocks."""
    if free_bytes is None or block_size != DEFAULT_BLOCK:
        return block_size, tile_pixels
    fits = int(free_bytes * _DEVICE_SHARE) // _DEVICE_BYTES_PER_PIXEL
    block_size = max(DEFAULT_BLOCK, min(_DEVICE_MAX_BLOCK, fits))
    return block_size, max(tile_pixels, block_size)


def _fft_threads(scheduler, workers) -> int:
    """Threads of each FFT: the CPUs left to each of the ``workers`` threads that fit
    blocks at once (every CPU for one thread; one on a Dask worker, which runs one task
    per CPU already). Threads that each asked for every CPU would share them out
    ``workers`` times over: a 16-core machine ran only twice as fast as a 2-core one."""
    if scheduler is not None:
        return 1
    return max(1, (os.cpu_count() or 1) // workers)


def _warn_gain_order(ds) -> None:
    """The EM gain rises with the set-point on every camera: a measured gain that falls
    means set-points swapped (or mislabelled) in the manifest."""
    sp = ds.setpoint.values
    if sp.size < 2:
        return
    ok = ds.converged.values
    gains = [float(nanmedian(ds.em_gain.values[i][ok])) for i in range(sp.size)]
    order = np.argsort(sp)
    for lo, hi in zip(order, order[1:]):
        if gains[hi] < gains[lo]:
            warnings.warn(
                f"{ds.attrs.get('manifest_path', 'the manifest')}: the measured EM gain falls "
                f"from {gains[lo]:.4g} at set-point {sp[lo]:g} to {gains[hi]:.4g} at set-point "
                f"{sp[hi]:g}; it rises with the set-point on every camera: are the "
                "set-points of those acquisitions swapped? If so, their gains are each "
                "other's: correct their em_gain_setpoint in the manifest and calibrate "
                "again",
                stacklevel=4,
                category=FitWarning,
            )


def _require_convergence(ds, method, store=None) -> None:
    """A method that fails for most pixels has no result to give: an error, not numbers;
    the run's ``store`` keeps nothing to resume then (every tile is done)."""
    ok = int(ds.converged.values.sum())
    total = int(ds.converged.size)
    if ok * 2 < total:
        if store is not None:
            store.discard()
        raise MethodError(
            f"method {method}: only {ok} of {total} pixels converged, so there is no "
            "calibration to report (nothing was written); "
            + (
                _saturated(ds)
                or "check the offset and read-noise maps against the data, the set-points "
                "and whether the method suits the data"
            )
        )


def _saturated(ds) -> str:
    """What saturation explains of a failure: the acquisitions with counts at the ADC
    maximum at most of their pixels, and what to do; "" where none has."""
    if "n_saturated" not in ds:
        return ""
    counts = ds["n_saturated"]
    dim = counts.dims[0]
    hit = [
        (label, int((counts.sel({dim: label}).values > 0).sum())) for label in counts[dim].values
    ]
    pixels = int(ds.converged.size)

    def name(label):
        if dim == "setpoint":
            return f"set-point {result.format_setpoint(label)}x"
        return f"level {label}"

    named = [f"{name(label)} ({n} of {pixels} pixels)" for label, n in hit if n * 2 > pixels]
    if not named:
        return ""
    return (
        f"counts at the ADC maximum (saturated) in {', '.join(named)}: lower the light or "
        "the EM gain there and record it again, or leave it out of the manifest"
    )


def _input_files(manifest, used, phi_source) -> list[Path]:
    """The files a calibration reads, which its output may not replace."""
    files = [manifest.path, *(a.frames_path for a in used)]
    phi = None if phi_source is None else phi_source.path
    if phi is not None and phi.exists():
        files.append(phi / result.CALIBRATION_FILE if phi.is_dir() else phi)
    return files


def _run_calibration(manifest, run: RunRequest, target):
    """One calibration, as :func:`calibrate` asked for it (``run``), into ``target`` (an
    open :class:`~emccdcal._output.Output`, or None for no files)."""
    manifest = _load(manifest)
    auto = isinstance(run.stages, str) and run.stages == "auto"
    rows, cols = manifest.shape
    phi_map, phi_se, phi_source = e_per_adu_inputs(manifest, run.e_per_adu, run.accept_mismatch)
    spec = specify(  # before any stack is read
        manifest,
        run.method,
        e_per_adu=phi_map,
        e_per_adu_se=phi_se,
        e_per_adu_source=phi_source,
        accept_phi=run.accept_phi,
        em_model=run.em_model,
        stages=None if auto else run.stages,
        options=run.options,
    )
    model, stages_source, options = spec.em_model, spec.stages_source, spec.options
    used = list(spec.acquisitions)
    tiles = plan_tiles(rows * cols, run.tile_pixels, run.block_size)
    scheduler = choose_scheduler(run.scheduler, rows * cols, len(tiles), run.workers, run.device)
    dark_frames, map_groups, se_note = _map_error_sources(used, run.map_errors)
    offsets = np.stack([a.offset.reshape(-1) for a in used])
    read_noise = np.stack([a.read_noise.reshape(-1) for a in used])
    phi, phi_se_flat = (None if a is None else a.reshape(-1) for a in (phi_map, phi_se))

    def tile_job(p0, p1, model):
        px = slice(p0, p1)
        return TileJob(
            pixels=(p0, p1),
            cols=cols,
            method=run.method,
            frames=tuple((str(a.frames_path), int(a.skip_frames)) for a in used),
            setpoints=tuple(float(a.em_gain_setpoint) for a in used),
            labels=tuple(_labels(used)),
            offsets=offsets[:, px],
            read_noise=read_noise[:, px],
            e_per_adu=None if phi is None or run.method.startswith("mv-") else phi[px],
            e_per_adu_se=(
                None if phi_se_flat is None or run.method.startswith("mv-") else phi_se_flat[px]
            ),
            dark_frames=tuple(dark_frames),
            map_groups=tuple(map_groups),
            adc_max=int(manifest.adc_max),
            options=options,
            intervals=run.intervals,
            block_size=run.block_size,
            threads=run.workers if scheduler is None else 1,
            checks=bool(run.checks),
            fft_threads=_fft_threads(scheduler, run.workers),
            em_model=model,
            device=run.device,
        )

    # where the register's length came from, as the result records it
    register_attrs = {"register_stages_source": stages_source} if stages_source else {}
    if auto:
        model, profile = _profile_stages(
            tile_job, rows * cols, model, run.method, used, run.progress
        )
        register_attrs = profile.attrs()
    store = None
    _reach_or_refuse(scheduler)  # before the output is begun
    if target is not None:  # an input, or an occupied output, is found before computing
        target.refuse_inputs(_input_files(manifest, used, phi_source), names=RESULT_FILES)
        store = RunStore(
            target.path,
            _fingerprint(
                manifest,
                used,
                run.method,
                options,
                run.intervals,
                run.checks,
                run.map_errors,
                phi_map,
                phi_se,
                (run.block_size, tiles[0][1] - tiles[0][0]),
                model,
            ),
            resume=run.resume,
            overwrite=run.overwrite,
        )
    jobs = [tile_job(p0, p1, model) for p0, p1 in tiles]
    parts = _run_tiles(jobs, store, scheduler, run.progress, run.method, run.workers)
    arrays = _joined(parts)  # parts keep the data-quality statistics, checked once fitted
    _warn_saturated_and_unusable(manifest, used, arrays)
    if run.method.startswith("mv-"):
        ds = _mv_dataset(run.method, manifest, used, arrays, phi_map, phi_se, model)
    else:
        ds = _likelihood_dataset(
            run.method,
            manifest,
            used,
            arrays,
            offsets,
            read_noise,
            options,
            run.intervals,
            model,
            se_note,
        )
    _add_dark_current(ds, manifest, used)
    _record_provenance(
        ds, run.method, manifest, model, register_attrs, run.device, phi_source, phi_se is not None
    )
    if run.checks:
        _add_findings(ds, manifest, used, parts, tiles)
    del parts
    ds.attrs.setdefault("verdict", "stands")  # the methods without a goodness of fit
    _require_convergence(ds, run.method, store)
    _warn_gain_order(ds)
    return ds
