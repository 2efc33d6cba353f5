"""The main job: a manifest in, a labelled calibration out (``emccdcal calibrate``).

The sensor is processed in tiles of whole blocks of pixels (:func:`plan_tiles`). A tile
reads only the rows that hold its pixels, of every acquisition, once, into per-pixel histograms
(:mod:`emccdcal.data.stats`) and the statistics of the data-quality checks
(:class:`emccdcal.data.quality.StackSummary`); fits its pixels with the likelihood engine
(:mod:`emccdcal.fit.engine`) driven by the method's layout (:mod:`emccdcal.fit.layouts`),
in blocks on threads; and is kept (:class:`emccdcal.runstore.RunStore`) before the next
one is read. Peak memory is set by the tile, not by the sensor, and an interrupted run
can be resumed. Tiles run here or as tasks on a Dask cluster (:func:`run_tile` is all a
worker executes). At the end the tiles are assembled into one labelled result
(:mod:`emccdcal.result`) and the data-quality checks are judged.
"""

from __future__ import annotations

import contextlib
import copy
import functools
import hashlib
import json
import os
import math
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from . import __version__, _xp, result
from ._output import Output
from ._util import check_int, install_hint, nanmedian, one_line
from ._util import progress as progress_bar
from .data import quality, stats
from .data.manifest import Manifest, read_manifest
from .data.stacks import read_band
from .errors import (
    DataQualityWarning,
    LeftOutWarning,
    SaturationWarning,
    FitWarning,
    InputError,
    MethodError,
    OptionError,
)
from .fit import gof, mv
from .fit.series import acquisition_models, fit_series, specify
from .given_phi import e_per_adu_inputs
from .defaults import DEFAULT_BLOCK, DEFAULT_TILE_PIXELS, INTERVALS, METHODS
from .model import noise
from .runstore import RESULT_FILES, RunInterrupted, RunStore, remove_run

if TYPE_CHECKING:
    import xarray

__all__ = [
    "METHODS",
    "INTERVALS",
    "DEFAULT_BLOCK",
    "DEFAULT_TILE_PIXELS",
    "TileJob",
    "calibrate",
    "plan_tiles",
    "run_tile",
    "format_summary",
]

#: Methods that hold φ (e⁻/ADU) fixed at a given value, and those that estimate it.
ESTIMATE_E_PER_ADU = ("mv-adu", "is-adu")
FIXED_E_PER_ADU = tuple(m for m in METHODS if m not in ESTIMATE_E_PER_ADU)

#: Names of the per-acquisition statistics a tile returns for the data-quality checks.
_QUALITY = "quality"


def _load(manifest):
    if isinstance(manifest, Manifest):
        return manifest
    return read_manifest(manifest)


def _labels(acqs):
    return [a.level if a.level is not None else a.name for a in acqs]


# --------------------------------------------------------------------------------------
# Tiles
# --------------------------------------------------------------------------------------
def plan_tiles(n_pixels: int, tile_pixels: int, block_size: int) -> list[tuple[int, int]]:
    """Ranges of pixels ``(first, stop)`` (C order) of whole blocks, about ``tile_pixels`` each.

    A pixel is fitted with the same block of pixels whatever the tiles, so the result
    does not depend on them: tiles are made of whole blocks of ``block_size``.

    Examples
    --------
    >>> plan_tiles(20, 8, 4)
    [(0, 8), (8, 16), (16, 20)]
    """
    step = max(1, int(tile_pixels) // int(block_size)) * int(block_size)
    return [(p, min(n_pixels, p + step)) for p in range(0, n_pixels, step)]


@dataclass(frozen=True)
class TileJob:
    """One tile of a calibration (a range of pixels) with everything needed to compute it.

    Plain data (picklable): a Dask worker runs :func:`run_tile` on it, reading the rows
    that hold the tile's pixels from the stacks' paths. Maps are those of the tile's
    pixels, shape (A, pixels).
    """

    pixels: tuple[int, int]
    cols: int
    method: str
    frames: tuple[tuple[str, int], ...]  # (path, skip_frames) per acquisition
    setpoints: tuple[float, ...]
    labels: tuple[str, ...]
    offsets: np.ndarray
    read_noise: np.ndarray
    e_per_adu: np.ndarray | None
    dark_frames: tuple
    map_groups: tuple
    adc_max: int
    options: dict | None
    intervals: str
    block_size: int
    threads: int
    checks: bool
    fft_threads: int | None = None
    e_per_adu_se: np.ndarray | None = None
    em_model: noise.EMModel = noise.EMModel()
    device: str | None = None

    @property
    def key(self) -> str:
        """Name of the tile in a run's store."""
        return f"pixels-{self.pixels[0]:09d}-{self.pixels[1]:09d}"

    @property
    def n_pixels(self) -> int:
        """Pixels of the tile."""
        return self.pixels[1] - self.pixels[0]


def run_tile(job: TileJob, progress=None) -> dict:
    """Read, summarise and fit one tile; ``progress(n)`` is told of every n pixels done.

    Returns
    -------
    dict of ndarray
        Per pixel of the tile (C order), pixels first: ``usable`` (every acquisition has
        two or more unsaturated frames that are not all equal), ``n_saturated`` (P, A);
        for the mean–variance methods the moments ``mean``, ``var``, ``n`` (P, A); for the
        likelihood methods the estimates (``photoelectrons``, ``em_gain``, ``e_per_adu``
        with ``_se`` and bounds, (P, A)), ``loglik``, ``gof_pvalue`` (P, A),
        ``converged``, ``n_floored``, ``iterations`` and the hyperparameters of
        ``gs-hierarchical``. With ``checks``, ``quality<a>_<name>`` are the
        :func:`emccdcal.data.quality.band_statistics` of acquisition ``a``.
    """
    p0, p1 = job.pixels
    r0, r1 = p0 // job.cols, -(-p1 // job.cols)  # the rows that hold the tile's pixels

    mean_variance = job.method.startswith("mv-")

    def read(a):
        path, skip = job.frames[a]
        band = read_band(path, r0, r1, skip)
        own = band.reshape(band.shape[0], 1, -1)[:, :, p0 - r0 * job.cols : p1 - r0 * job.cols]
        q = (
            quality.band_statistics(own, job.adc_max, third=job.setpoints[a] == 1)
            if job.checks
            else None
        )
        # The likelihood methods histogram each block's pixels as they fit it (the
        # threads then share the work evenly); the mean–variance methods need moments.
        data = _histograms(job, a, own) if mean_variance else own
        return data, stats.frame_usage(own, job.adc_max), q

    with ThreadPoolExecutor(max_workers=max(1, min(job.threads, len(job.frames)))) as pool:
        read_back = list(pool.map(read, range(len(job.frames))))
    out = {"n_saturated": np.stack([n_sat for _, (_, n_sat), _ in read_back], axis=1)}
    for a, (_, _, q) in enumerate(read_back):
        for name, value in (q or {}).items():
            out[f"{_QUALITY}{a}_{name}"] = value
    usable = np.all([u for _, (u, _), _ in read_back], axis=0)
    if job.e_per_adu is not None:  # a chained φ is NaN where its own fit failed
        usable &= np.isfinite(job.e_per_adu)
    out["usable"] = usable
    fitted = np.flatnonzero(usable)
    data = [d for d, _, _ in read_back]
    del read_back
    if mean_variance:
        for name in ("mean", "var", "n"):
            out[name] = np.stack([getattr(h, name) for h in data], axis=1)
    else:
        out.update(_fit_pixels(job, data, fitted, progress))
    if progress is not None:  # the pixels not fitted here (all of them for mean-variance)
        progress(job.n_pixels - (0 if mean_variance else fitted.size))
    return out


def _histograms(job, a, frames):
    """:func:`emccdcal.data.stats.histograms` of acquisition ``a``'s frames; bad counts
    are one line naming the file and the acquisition."""
    try:
        return stats.histograms(frames, adc_max=job.adc_max)
    except InputError as exc:
        raise InputError(f"'{job.frames[a][0]}' ({job.labels[a]}): {exc}") from None


def _bounds_of(method, intervals):
    """Interval bounds of a likelihood result: (kind, description), or None."""
    if intervals == "profile":
        return (
            "profile-likelihood",
            "profile likelihood, 95 %, widened by the errors of the offset and "
            "read-noise maps where the standard errors include them",
        )
    if method == "gs-hierarchical":
        return (
            "unpooled",
            "95 %, of the same model without the prior (each set-point its own E): "
            "Wald on the log scale, profile likelihood where that is unreliable; "
            "the MAP's own ± 1.96 SE reflect its shrinkage",
        )
    return None


def _fit_pixels(job, frames, usable, progress=None):
    """The likelihood fit of the pixels ``usable`` of a tile, from each acquisition's
    ``frames`` (F, 1, P); NaN (not converged) elsewhere."""
    P, A = job.n_pixels, len(frames)
    out = {
        k: np.full((P, A), np.nan)
        for k in (
            "photoelectrons",
            "photoelectrons_se",
            "em_gain",
            "em_gain_se",
            "e_per_adu",
            "e_per_adu_se",
            "gof_pvalue",
            "acquisition_loglik",
        )
    }
    out.update(
        loglik=np.full(P, np.nan),
        converged=np.zeros(P, dtype=bool),
        n_floored=np.zeros(P, dtype=np.int64),
        iterations=np.zeros(P, dtype=np.int64),
    )
    if job.method == "gs-hierarchical":
        out.update(
            hyper_photoelectrons=np.full(P, np.nan), hyper_sd_photoelectrons=np.full(P, np.nan)
        )

    def fit_block(idx):
        models = acquisition_models(
            job.setpoints,
            job.offsets[:, idx],
            job.read_noise[:, idx],
            job.em_model,
            job.dark_frames,
            job.map_groups,
        )
        sub = lambda v: None if v is None else v[idx]  # noqa: E731
        # the histograms, the fit and its checks, each FFT on the CPUs the tile's
        # threads leave it
        with _xp.computing_on(job.device, fft_workers=job.fft_threads):
            hists = [_histograms(job, a, f[:, :, idx]) for a, f in enumerate(frames)]
            return idx, fit_series(
                job.method,
                models,
                hists,
                e_per_adu=sub(job.e_per_adu),
                e_per_adu_se=sub(job.e_per_adu_se),
                options=job.options,
                intervals=job.intervals,
            )

    chunks = [usable[s : s + job.block_size] for s in range(0, usable.size, job.block_size)]
    # Blocks are independent: threads overlap them (NumPy and the FFT release the GIL),
    # and the result does not depend on how many there are.
    with ThreadPoolExecutor(max_workers=max(1, job.threads)) as pool:
        for idx, e in pool.map(fit_block, chunks):
            for k, v in e.items():
                out.setdefault(k, np.full((P, A), np.nan))[idx] = v
            if progress is not None:
                progress(idx.size)
    return out


def _return_freed_memory() -> None:
    """Give the memory a finished tile freed back to the system (glibc only).

    A tile's large temporary arrays are freed into the allocator's per-thread arenas;
    without this the resident memory of a long run creeps up with the number of tiles.
    """
    try:
        _libc().malloc_trim(0)
    except (OSError, AttributeError):  # not glibc: nothing to do
        pass


@functools.lru_cache(maxsize=1)
def _libc():
    import ctypes
    import ctypes.util

    return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")


def _execute(jobs, scheduler, progress, workers=1):
    """Run tile jobs here, in order, in ``workers`` local processes or on a Dask cluster as
    they finish: (job, arrays). ``progress(n)`` is told of every n pixels done (as they
    are fitted, here)."""
    if scheduler is None:
        for job in jobs:
            arrays = run_tile(job, progress)
            _return_freed_memory()
            yield job, arrays
        return
    if isinstance(scheduler, str) and scheduler == LOCAL_PROCESSES:
        yield from _in_processes(jobs, progress, workers)
        return
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise OptionError(
            "running on a Dask cluster needs the 'dask' extra: " + install_hint("dask")
        ) from None
    if isinstance(scheduler, Client):
        client = scheduler
    else:
        # Reached before a client is made: a client that fails half-made lingers, and
        # closing it at exit waits a minute. Ours is never the process's default either.
        _reach_or_refuse(scheduler)
        try:
            client = Client(scheduler, timeout="30s", set_as_default=False)
        except (ValueError, TypeError, OSError) as exc:  # gone since it was reached
            raise OptionError(
                f"scheduler {scheduler!r}: no Dask scheduler reached ({one_line(exc)})"
            ) from None
    try:
        futures = {client.submit(run_tile, job, pure=False): job for job in jobs}
        # as_completed waits on the loop of the client it is given, else on the process's
        # default client: ours is not one (a caller's may not exist)
        yield from _as_finished(
            futures, functools.partial(as_completed, loop=client.loop), progress
        )
    finally:
        if client is not scheduler:
            client.close()


def _as_finished(futures, as_completed, progress):
    """(job, arrays) of ``futures`` ({future: job}) as each finishes (``as_completed``
    of Dask or of concurrent.futures); ``progress`` told of each one's pixels."""
    for future in as_completed(futures):
        job = futures[future]
        arrays = future.result()
        progress(job.n_pixels)
        yield job, arrays


#: ``scheduler`` that runs the tiles in local processes (one tile each, one thread each).
LOCAL_PROCESSES = "processes"


def _in_processes(jobs, progress, workers):
    """The tiles in ``workers`` fresh processes (spawned: nothing inherited but the jobs),
    as they finish. Threads share one interpreter, whose lock the fit's Python steps
    hold; processes do not, so a sensor's tiles use every core.

    The workers leave Ctrl-C to this process, which ends them at once (a pool that
    waited for their tiles took a minute to stop), and each ends itself when this
    process dies (a SIGKILL here left them running)."""
    import multiprocessing

    context = multiprocessing.get_context("spawn")
    pool = context.Pool(workers, initializer=_worker_start, initargs=(os.getpid(),))
    try:
        for index, arrays in pool.imap_unordered(_indexed_tile, enumerate(jobs)):
            progress(jobs[index].n_pixels)
            yield jobs[index], arrays
        pool.close()
    finally:
        pool.terminate()  # a no-op once closed and done; else the tiles still running go
        pool.join()


def _indexed_tile(item):
    """``(index, run_tile(job))`` of ``(index, job)``: which tile finished, in a worker."""
    index, job = item
    return index, run_tile(job)


def _worker_start(parent: int) -> None:
    """A tile worker's start: Ctrl-C is its parent's to handle (it ends the workers), and
    a thread ends the worker within half a second of its parent's death."""
    import signal
    import threading

    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def watch():
        import time

        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, name="emccdcal-parent-watch", daemon=True).start()


def _reach_or_refuse(scheduler) -> None:
    """One line (an OptionError) unless a Dask scheduler answers at ``scheduler`` (and
    the ``dask`` extra is installed), where it is an address: :func:`_reach`."""
    if not isinstance(scheduler, str) or scheduler == LOCAL_PROCESSES:
        return  # here, local processes or a client of the caller's
    try:
        _reach(scheduler)
    except ImportError:
        raise OptionError(
            "running on a Dask cluster needs the 'dask' extra: " + install_hint("dask")
        ) from None
    except (ValueError, TypeError, OSError) as exc:  # not an address, or no one there
        raise OptionError(
            f"scheduler {scheduler!r}: no Dask scheduler reached "
            f"({one_line(exc)}); give its address, tcp://HOST:PORT"
        ) from None


#: Seconds to wait for a scheduler's address to accept a connection, and for its first
#: bytes: a Dask scheduler sends its handshake at once.
_REACH_SECONDS = 5.0


def _reach(address) -> None:
    """Raise ValueError or OSError unless a Dask scheduler answers at ``address`` (within
    seconds): a TCP address must accept a connection and send a Dask handshake's first
    frame (a listener of anything else is refused here, where Dask would read its bytes
    as a length of exabytes); a WebSocket or TLS one must accept a connection; other
    schemes (``inproc://``, of one process; ``ucx://``) cannot be reached from here."""
    import socket
    import struct

    from distributed.comm import parse_address, parse_host_port

    scheme, location = parse_address(str(address))
    if scheme not in ("tcp", "tls", "ws", "wss"):
        raise ValueError(f"a {scheme}:// address is not one this command can reach")
    host, port = parse_host_port(location)
    with socket.create_connection((host, port), timeout=_REACH_SECONDS) as sock:
        if scheme != "tcp":
            return
        head = b""
        try:
            while len(head) < 8:
                more = sock.recv(8 - len(head))
                if not more:
                    break
                head += more
        except TimeoutError:
            pass
    if len(head) < 8:
        raise ValueError(f"what listens there sent no Dask handshake in {_REACH_SECONDS:g} s")
    (size,) = struct.unpack("<Q", head)
    if not 0 < size < 2**20:  # the handshake is a few hundred bytes
        raise ValueError("what listens there is not a Dask scheduler (not its handshake)")


def _run_tiles(jobs, store, scheduler, progress, method, workers=1):
    """Every tile's arrays, in order: those kept by ``store`` and the computed ones."""
    done = {}
    if store is not None:
        wanted = {job.key for job in jobs}
        done = {key: store.load_tile(key) for key in store.tiles() if key in wanted}
    total = sum(job.n_pixels for job in jobs)
    bar = progress_bar(enabled=progress, desc=f"calibrating ({method})", unit="px", total=total)
    bar.update(sum(job.n_pixels for job in jobs if job.key in done))
    try:
        for job, arrays in _execute(
            [j for j in jobs if j.key not in done], scheduler, bar.update, workers
        ):
            if store is not None:
                store.save_tile(job.key, arrays)
            done[job.key] = arrays
    except KeyboardInterrupt:
        if store is None:
            raise
        raise RunInterrupted(
            f"interrupted: {len(store.tiles())} of {len(jobs)} tiles kept in {store.out}; "
            "run the same command with --resume to continue"
        ) from None
    finally:
        bar.close()
    return [done[job.key] for job in jobs]


#: Register lengths ``stages="auto"`` tries: steps of √2 from 128 to 4096 stages.
STAGE_GRID = (128, 181, 256, 362, 512, 724, 1024, 1448, 2048, 2896, 4096)
#: Pixels, the sensor's middle ones, on which the register's length is profiled.
PROFILE_PIXELS = 64


@dataclass(frozen=True)
class StageProfile:
    """The log-likelihood of the profiled pixels at each register length of
    :data:`STAGE_GRID` (``stages="auto"``), each pixel's other parameters fitted anew."""

    stages: tuple[int, ...]
    loglik: np.ndarray  # nats, summed over the pixels converged at every length
    pixels: int

    @property
    def best(self) -> int:
        """The register length of the largest likelihood."""
        return int(self.stages[int(np.argmax(self.loglik))])

    def attrs(self) -> dict:
        """The profile as a result's attributes: the grid, Δ log-likelihood (nats) and a
        sentence saying what was chosen, the lengths within 95 % (Δ > −1.92) and whether
        the data bound the length at all."""
        delta = self.loglik - self.loglik.max()
        within = [n for n, d in zip(self.stages, delta) if d > -1.92]
        source = (
            f"profile likelihood over {self.stages[0]}-{self.stages[-1]} stages on "
            f"{self.pixels} pixels: maximum at {self.best}, {min(within)}-{max(within)} "
            "within 95 %"
        )
        if max(within) == self.stages[-1]:
            source += " (no upper bound in the data: longer registers fit as well)"
        return {
            "register_stages_source": source,
            "register_stages_grid": np.array(self.stages, dtype=np.int64),
            "register_stages_profile": delta,
        }


def _profile_stages(tile_job, n_pixels, model, method, used, progress):
    """``(EMModel at the best length, StageProfile)``: the method fitted to the middle
    :data:`PROFILE_PIXELS` pixels at every length of :data:`STAGE_GRID`."""
    if not model.register.uses_stages:
        raise OptionError(
            f"stages='auto' profiles the cascade register's length; the {model} model has none"
        )
    if method.startswith("mv-"):
        raise MethodError(f"stages='auto' needs a likelihood: {method} has none")
    if all(a.em_gain_setpoint == 1 for a in used):
        raise OptionError(
            "stages='auto': every acquisition is at EM gain set-point 1, "
            "where the register's length does not enter the likelihood"
        )
    n = min(PROFILE_PIXELS, n_pixels)
    p0 = (n_pixels - n) // 2
    logliks = []
    for stages in progress_bar(
        STAGE_GRID, enabled=progress, desc="profiling register length", unit="length"
    ):
        job = replace(
            tile_job(p0, p0 + n, noise.EMModel(model.name, stages)), checks=False, intervals="wald"
        )
        logliks.append(run_tile(job)["loglik"])
    logliks = np.array(logliks)
    ok = np.all(np.isfinite(logliks), axis=0)
    if not ok.any():
        raise InputError(
            f"stages='auto': none of the {n} profiled pixels converged at every "
            f"register length ({STAGE_GRID[0]}-{STAGE_GRID[-1]}); give --stages N"
        )
    profile = StageProfile(STAGE_GRID, logliks[:, ok].sum(axis=1), int(ok.sum()))
    return noise.EMModel(model.name, profile.best), profile


def _fingerprint(
    manifest,
    used,
    method,
    options,
    intervals,
    checks,
    map_errors,
    phi_map,
    phi_se,
    tiling,
    em_model,
):
    """What a calibration's result depends on, to refuse resuming a different run."""
    files = {}
    paths = [manifest.path] + [a.frames_path for a in manifest.acquisitions]
    sources = [manifest.e_per_adu_source] + [
        s for a in manifest.acquisitions for s in (a.offset_source, a.read_noise_source)
    ]
    paths += [s.path for s in sources if s is not None and s.path is not None]
    for p in paths:
        st = Path(p).stat()
        files[str(Path(p).resolve())] = [st.st_size, st.st_mtime_ns]
    phi = None if phi_map is None else hashlib.sha256(np.ascontiguousarray(phi_map)).hexdigest()
    if phi_se is not None:
        phi += hashlib.sha256(np.ascontiguousarray(phi_se)).hexdigest()
    return {
        "emccdcal_version": __version__,
        "manifest_sha256": manifest.content_hash,
        "files": files,
        "method": method,
        "acquisitions": [a.name for a in used],
        "options": options,
        "intervals": intervals,
        "checks": bool(checks),
        "map_errors": bool(map_errors),
        "e_per_adu_sha256": phi,
        "blocks_and_tiles": [int(t) for t in tiling],
        "em_model": str(em_model),
    }


# --------------------------------------------------------------------------------------
# The calibration
# --------------------------------------------------------------------------------------
def calibrate(
    manifest,
    method="gs",
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
    method : str
        One of :data:`METHODS`: ``mv-adu``, ``mv-gain``, ``is-adu``, ``is-gain``, ``gs``,
        ``gs-no1x``, ``gs-hierarchical``.
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
        Pixels fitted together.
    tile_pixels : int
        Pixels per tile, rounded to whole rows (at least one row): what is read, fitted
        and kept at once. Peak memory grows with it, not with the sensor; the result does
        not depend on it.
    scheduler : str or distributed.Client, optional
        Run the tiles as tasks on a Dask cluster: the address of its scheduler
        (``"tcp://host:8786"``) or a client. The workers read the files from the paths of
        the manifest, so these must be shared. ``"processes"``: the tiles in ``workers``
        local processes, one thread each (the cores of a large machine, which threads
        share less well). Default: here, on ``workers`` threads.
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
        Threads reading and fitting at once within a tile (default: the number of CPUs;
        1 on a Dask cluster, whose workers run tiles in parallel).
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
    device : {"cpu", "cuda", "array-api-strict"}, optional
        Where the likelihood's windows and sums are computed (docs/running.md): the CPU
        (NumPy, the default); an NVIDIA GPU through CuPy or PyTorch (the extra ``gpu``);
        or array-api-strict, the CPU through the array API standard alone (a check, not a
        speed-up). The numbers agree within 1e-9; the result records the device.

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
    target = None if out is None else Output(out, kind="folder", stage=False)
    with target or contextlib.nullcontext():
        ds = result.run_recorded(
            lambda: _run_calibration(
                manifest,
                method,
                e_per_adu,
                target,
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
                accept_mismatch=accept_mismatch,
                accept_phi=accept_phi,
                device=device,
            ),
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


def _run_calibration(
    manifest,
    method,
    e_per_adu,
    target,
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
    em_model=None,
    stages=None,
    *,
    accept_mismatch=(),
    accept_phi=False,
    device=None,
):
    manifest = _load(manifest)
    auto = isinstance(stages, str) and stages == "auto"
    rows, cols = manifest.shape
    phi_map, phi_se, phi_source = e_per_adu_inputs(manifest, e_per_adu, accept_mismatch)
    spec = specify(  # before any stack is read
        manifest,
        method,
        e_per_adu=phi_map,
        e_per_adu_se=phi_se,
        e_per_adu_source=phi_source,
        accept_phi=accept_phi,
        em_model=em_model,
        stages=None if auto else stages,
        options=options,
    )
    model, stages_source, options = spec.em_model, spec.stages_source, spec.options
    used = list(spec.acquisitions)
    tiles = plan_tiles(rows * cols, tile_pixels, block_size)
    dark_frames, map_groups, se_note = _map_error_sources(used, map_errors)
    offsets = np.stack([a.offset.reshape(-1) for a in used])
    read_noise = np.stack([a.read_noise.reshape(-1) for a in used])
    phi, phi_se_flat = (None if a is None else a.reshape(-1) for a in (phi_map, phi_se))

    def tile_job(p0, p1, model):
        px = slice(p0, p1)
        return TileJob(
            pixels=(p0, p1),
            cols=cols,
            method=method,
            frames=tuple((str(a.frames_path), int(a.skip_frames)) for a in used),
            setpoints=tuple(float(a.em_gain_setpoint) for a in used),
            labels=tuple(_labels(used)),
            offsets=offsets[:, px],
            read_noise=read_noise[:, px],
            e_per_adu=None if phi is None or method.startswith("mv-") else phi[px],
            e_per_adu_se=(
                None if phi_se_flat is None or method.startswith("mv-") else phi_se_flat[px]
            ),
            dark_frames=tuple(dark_frames),
            map_groups=tuple(map_groups),
            adc_max=int(manifest.adc_max),
            options=options,
            intervals=intervals,
            block_size=block_size,
            threads=workers if scheduler is None else 1,
            checks=bool(checks),
            fft_threads=_fft_threads(scheduler, workers),
            em_model=model,
            device=device,
        )

    # where the register's length came from, as the result records it
    register_attrs = {"register_stages_source": stages_source} if stages_source else {}
    if auto:
        model, profile = _profile_stages(tile_job, rows * cols, model, method, used, progress)
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
                method,
                options,
                intervals,
                checks,
                map_errors,
                phi_map,
                phi_se,
                (block_size, tiles[0][1] - tiles[0][0]),
                model,
            ),
            resume=resume,
            overwrite=overwrite,
        )
    jobs = [tile_job(p0, p1, model) for p0, p1 in tiles]
    parts = _run_tiles(jobs, store, scheduler, progress, method, workers)
    arrays = _joined(parts)  # parts keep the data-quality statistics, checked once fitted
    _warn_saturated_and_unusable(manifest, used, arrays)
    if method.startswith("mv-"):
        ds = _mv_dataset(method, manifest, used, arrays, phi_map, phi_se, model)
    else:
        ds = _likelihood_dataset(
            method, manifest, used, arrays, offsets, read_noise, options, intervals, model, se_note
        )
    _record_provenance(
        ds, method, manifest, model, register_attrs, device, phi_source, phi_se is not None
    )
    if checks:
        _add_findings(ds, manifest, used, parts, tiles)
    del parts
    ds.attrs.setdefault("verdict", "stands")  # the methods without a goodness of fit
    _require_convergence(ds, method, store)
    _warn_gain_order(ds)
    return ds


def _add_findings(ds, manifest, used, parts, tiles) -> None:
    """The data-quality checks' findings, warned and in ``ds.attrs["quality"]``: they
    quote the light this fit found, not a rough guess of it."""
    report, messages = _quality(manifest, used, parts, tiles, _fitted_light(ds, used))
    for w in messages:  # a finding knows its kind (drift, read-noise growth ...)
        warnings.warn(w, stacklevel=3, category=getattr(w, "category", DataQualityWarning))
    if report is not None:
        ds.attrs["quality"] = json.dumps(report)

    # a finding after which the result does not stand makes the verdict doubtful, one that
    # asks for a check says so: its subject and what was found (the warning says what to do)
    def subjects(flag):
        return [": ".join(w.split(": ")[:2]) for w in messages if getattr(w, flag, False)]

    before = str(ds.attrs.get("verdict", "stands"))
    if subjects("doubtful"):
        found = "; ".join(subjects("doubtful")) + " (its warning says what to do)"
        rest = "" if before == "stands" else "; " + before.removeprefix("doubtful: ")
        ds.attrs["verdict"] = "doubtful: " + found + rest
    elif subjects("caution") and before == "stands":  # stands, once a check is made
        ds.attrs["verdict"] = (
            "stands; check first " + "; ".join(subjects("caution")) + " (its warning says how)"
        )


def _joined(parts) -> dict:
    """The tiles' per-pixel arrays joined, each moved out of ``parts`` (one copy at a
    time); the data-quality statistics stay in ``parts``."""
    return {
        key: np.concatenate([p.pop(key) for p in parts])
        for key in [k for k in parts[0] if not k.startswith(_QUALITY)]
    }


def _record_provenance(
    ds, method, manifest, model, register_attrs, device, phi_source, phi_has_se: bool
) -> None:
    """Write into ``ds.attrs`` what the numbers came from: the register model, the device,
    the camera's identity, where φ came from."""
    if method != "mv-adu":  # the register model of the likelihood, or mv-gain's F²
        ds.attrs.update(model.attrs, **register_attrs)
    if not method.startswith("mv-"):  # where the likelihood was computed
        ds.attrs["device"] = device or "cpu"
    ds.attrs.update(result.identity_attrs(manifest))  # the camera and pixels it holds for
    if phi_source is not None:
        ds.attrs["e_per_adu_source"] = str(phi_source)
        if phi_source.kind == "result":  # chained: the result φ and its error came from
            ds.attrs["e_per_adu_result"] = str(phi_source.path)
    if phi_has_se:
        ds.attrs["standard_errors"] += (
            f"; and the error of e_per_adu ({phi_source}): it moves every E and g of a pixel "
            "together (delta method through the likelihood, or the photon-transfer formulas)"
        )


def _warn_saturated_and_unusable(manifest, used, arrays):
    rows, cols = manifest.shape
    for a, acq in enumerate(used):
        n_sat = arrays["n_saturated"][:, a]
        if n_sat.sum():
            warnings.warn(
                f"{acq.frames_path.name}: {int(n_sat.sum())} frame values at the ADC maximum "
                f"({manifest.adc_max} ADU) in {int((n_sat > 0).sum())} pixel(s) were "
                "excluded from the fit, so those pixels' gain and light read low; the other "
                "pixels' results stand; lower the light (or the EM gain) and record again "
                "for these",
                stacklevel=3,
                category=SaturationWarning,
            )
    bad = np.flatnonzero(~arrays["usable"])
    if bad.size:
        where = ", ".join(f"({p // cols}, {p % cols})" for p in bad[:5])
        warnings.warn(
            f"{bad.size} of {rows * cols} pixel(s) have fewer than 2 usable frames, or frames "
            f"that never change, in some acquisition (saturated, dead or stuck): {where}"
            f"{', ...' if bad.size > 5 else ''}; they are left out (NaN, converged = False), "
            "and the other pixels' results stand",
            stacklevel=3,
            category=LeftOutWarning,
        )


def _fitted_light(ds, used) -> list:
    """What the fit found for each used acquisition, for the checks' findings to quote:
    None where the method estimates no E for it, else a dict: ``photoelectrons`` (E, e⁻
    per pixel and frame), ``absorbed`` (whether the spread of a drifting light biases an
    estimate there: not where the estimates come from the acquisition's mean, as at 1×
    with φ given, or in ``gs``, whose E is shared with the 1× light) and
    ``relative_se`` (that estimate's, the EM gain or φ at 1×, or None); medians over
    converged pixels."""
    if "photoelectrons" not in ds:
        return [None] * len(used)
    ok = ds.converged.values.astype(bool)
    phi_given = "e_per_adu_source" in ds.attrs
    pinned = phi_given and ds.attrs.get("method") == "gs"

    def median_at(name, a):
        sel = ds[name]
        if "setpoint" in sel.dims:
            sel = sel.sel(setpoint=a.em_gain_setpoint)
        if "level" in sel.dims:
            sel = sel.sel(level=a.level)
        values = np.asarray(sel.values, dtype=float)
        return float(nanmedian(values[ok])) if values.shape == ok.shape else math.nan

    out: list[dict | None] = []
    for a in used:
        try:
            light = median_at("photoelectrons", a)
        except (KeyError, ValueError):
            light = math.nan
        if not (math.isfinite(light) and light > 0):
            out.append(None)
            continue
        what = "em_gain" if a.em_gain_setpoint != 1 and "em_gain" in ds else "e_per_adu"
        try:
            rse = median_at(f"{what}_se", a) / median_at(what, a)
        except (KeyError, ValueError):
            rse = math.nan
        out.append(
            {
                "photoelectrons": light,
                "absorbed": not (pinned or (phi_given and a.em_gain_setpoint == 1)),
                "relative_se": rse if math.isfinite(rse) and rse > 0 else None,
            }
        )
    return out


def _quality(manifest, used, parts, tiles, fitted=None):
    """Data-quality checks (drift, saturation, defects) of the used stacks,
    from the statistics the tiles gathered as they read them; ``fitted``: for each
    stack, what :func:`_fitted_light` found (or None), which the findings quote.

    Returns the report and its findings as messages for the caller to issue.
    """
    summaries = []
    for a, acq in enumerate(used):
        summary = quality.StackSummary(acq.n_frames, manifest.shape, manifest.adc_max)
        for (p0, _), part in zip(tiles, parts):
            prefix = f"{_QUALITY}{a}_"
            summary.add(p0, {k[len(prefix) :]: v for k, v in part.items() if k.startswith(prefix)})
        summaries.append(summary)
    sub = copy.copy(manifest)
    sub.acquisitions = list(used)
    try:
        report = quality.check_manifest(sub, summaries=summaries, fitted=fitted)
    except ValueError as exc:  # frame means that cannot be tested (not finite)
        return None, [f"data-quality checks skipped: {exc}"]
    grown = set(manifest.warnings)  # read-noise growth was already reported by the manifest
    return report, [w for w in report["warnings"] if not any(w in g or g in w for g in grown)]


def _map_error_sources(used, map_errors):
    """Dark-frame counts and sharing groups of the maps, and a note for the result."""
    dark_frames = [a.dark_frames if map_errors else None for a in used]
    # Acquisitions whose maps come from one file (or one dark stack) share their errors.
    groups = [a.offset_source if a.offset_source.kind != "value" else i for i, a in enumerate(used)]
    known = [f"{a.name}: {n} dark frames" for a, n in zip(used, dark_frames) if n is not None]
    exact = [a.name for a, n in zip(used, dark_frames) if n is None]
    if not map_errors:
        note = "conditional on the offset and read-noise maps (map errors not included)"
    elif not known:
        note = (
            "conditional on the offset and read-noise maps (no dark-frame counts known; "
            "give 'dark' stacks or 'dark_frames' in the manifest to include their errors)"
        )
    else:
        note = "include the errors of the offset and read-noise maps (" + "; ".join(known)
        note += f"; taken as exact: {', '.join(exact)})" if exact else ")"
    return dark_frames, groups, note


def _warn_fit_problems(method, used, arrays, model) -> None:
    """Warn of pixels that did not converge and of acquisitions the model misfits."""
    setpoints = [a.em_gain_setpoint for a in used]
    converged, gof_p = arrays["converged"], arrays["gof_pvalue"]
    not_conv = int((~converged & arrays["usable"]).sum())
    if not_conv:
        warnings.warn(
            f"{method}: {not_conv} of {int(arrays['usable'].sum())} fitted pixel(s) "
            "did not converge (converged = False): their numbers are not estimates "
            "and must not be used; the converged pixels' results stand",
            stacklevel=4,
            category=FitWarning,
        )
    kind, keys = _acquisition_keys(method, used)
    multiplied = [k for k, sp in zip(keys, setpoints) if sp != 1]
    for w in gof.misfit_warnings(dict(zip(keys, gof_p.T)), kind=kind):
        hint = model.register.misfit_hint
        if hint and any(w.startswith(f"{kind} {k}:") for k in multiplied):
            # An approximate register's commonest misfit (the gamma model's excess noise
            # is 2, an exact register's below it, most at low gain).
            w += "; " + hint
        else:
            w += (
                ": the estimates there are doubtful; the checks' findings (or 'emccdcal "
                "check MANIFEST') name a cause to fix (drift, saturation, offset or "
                "read-noise maps of another mode, a mislabelled set-point); where they name "
                "none, leave that acquisition out of the manifest and compare"
            )
        warnings.warn(w, stacklevel=4, category=FitWarning)


def _likelihood_dataset(
    method, manifest, used, arrays, offsets, read_noise, options, intervals, model, se_note
):
    """The result of a likelihood method from the per-pixel arrays of every tile."""
    rows, cols = manifest.shape
    setpoints = np.array([a.em_gain_setpoint for a in used])
    est, gof_p, converged = arrays, arrays["gof_pvalue"], arrays["converged"]
    _warn_fit_problems(method, used, arrays, model)
    grid = lambda a: a.T.reshape((-1, rows, cols)) if a.ndim == 2 else a.reshape(rows, cols)  # noqa: E731
    labels = _labels(used)
    per_acq_dim = "level" if method.startswith("is-") else "setpoint"
    loglik = arrays["loglik"]
    extra = {
        "offset": ((per_acq_dim, "row", "col"), grid(offsets.T), "ADU"),
        "read_noise": ((per_acq_dim, "row", "col"), grid(read_noise.T), "ADU"),
        "n_saturated": ((per_acq_dim, "row", "col"), grid(arrays["n_saturated"]), "1"),
        "n_floored": (("row", "col"), grid(arrays["n_floored"]), "1"),
        "iterations": (("row", "col"), grid(arrays["iterations"]), "1"),
        "gof_pvalue": (
            (per_acq_dim, "row", "col"),
            grid(gof_p),
            "1",
            "p-value of the binned chi-square goodness-of-fit test",
        ),
        "acquisition_loglik": (
            (per_acq_dim, "row", "col"),
            grid(arrays["acquisition_loglik"]),
            "nats",
            "each acquisition's part of loglik",
        ),
    }
    if any(a.dark_event_rate is not None for a in used):  # darks fitted with their events
        rates = np.stack(
            [
                np.full((rows, cols), np.nan) if a.dark_event_rate is None else a.dark_event_rate
                for a in used
            ]
        )
        extra["dark_event_rate"] = (
            (per_acq_dim, "row", "col"),
            rates,
            "e-",
            "multiplied electrons per pixel per frame in the dark "
            "stack (clock-induced charge, dark current)",
        )
    fixed_phi_se = grid(est["e_per_adu_se"][:, 0])  # NaN unless φ came with its error
    common = dict(
        loglik=grid(loglik),
        converged=grid(converged),
        manifest_hash=manifest.content_hash,
        manifest_path=str(manifest.path.resolve()),
        extra=extra,
    )
    if method == "is-adu":
        ds = result.make_dataset(
            method=method,
            setpoints=[1.0],
            levels=labels,
            e_per_adu=grid(est["e_per_adu"][:, 0]),
            e_per_adu_se=grid(est["e_per_adu_se"][:, 0]),
            em_gain=np.ones((1, rows, cols)),
            em_gain_se=np.zeros((1, rows, cols)),
            photoelectrons=grid(est["photoelectrons"]),
            photoelectrons_se=grid(est["photoelectrons_se"]),
            photoelectrons_dims=("level", "row", "col"),
            **common,
        )
    elif method == "is-gain":
        ds = result.make_dataset(
            method=method,
            setpoints=[float(setpoints[0])],
            levels=labels,
            e_per_adu=grid(est["e_per_adu"][:, 0]),
            e_per_adu_se=fixed_phi_se,
            em_gain=grid(est["em_gain"][:, :1]),
            em_gain_se=grid(est["em_gain_se"][:, :1]),
            photoelectrons=grid(est["photoelectrons"]),
            photoelectrons_se=grid(est["photoelectrons_se"]),
            photoelectrons_dims=("level", "row", "col"),
            **common,
        )
    else:
        shared = method in ("gs", "gs-no1x")
        if method == "gs-hierarchical":
            extra["hyper_photoelectrons"] = (
                ("row", "col"),
                grid(arrays["hyper_photoelectrons"]),
                "e-",
            )
            extra["hyper_sd_photoelectrons"] = (
                ("row", "col"),
                grid(arrays["hyper_sd_photoelectrons"]),
                "e-",
            )
        ds = result.make_dataset(
            method=method,
            setpoints=[float(s) for s in setpoints],
            e_per_adu=grid(est["e_per_adu"][:, 0]),
            e_per_adu_se=fixed_phi_se,
            em_gain=grid(est["em_gain"]),
            em_gain_se=grid(est["em_gain_se"]),
            photoelectrons=grid(est["photoelectrons"][:, 0])
            if shared
            else grid(est["photoelectrons"]),
            photoelectrons_se=grid(est["photoelectrons_se"][:, 0])
            if shared
            else grid(est["photoelectrons_se"]),
            photoelectrons_dims=("row", "col") if shared else ("setpoint", "row", "col"),
            attrs={"options": json.dumps(options)} if options else None,
            **common,
        )
    bounds = _bounds_of(method, intervals)
    if bounds is not None:
        _add_bounds(ds, est, grid, *bounds)
    ds.attrs["standard_errors"] = se_note
    ds.attrs["verdict"] = _verdict(method, used, gof_p, model)
    return ds


def _acquisition_keys(method, used) -> tuple[str, list[str]]:
    """What the acquisitions are ("level" or "set-point") and their labels in messages."""
    if method.startswith("is-"):
        return "level", _labels(used)
    return "set-point", [result.format_setpoint(a.em_gain_setpoint) + "x" for a in used]


def _verdict(method, used, gof_p, model) -> str:
    """``"stands"``, or ``"doubtful: ..."`` naming each acquisition whose goodness of fit
    rejects the model at most pixels (:func:`emccdcal.fit.gof.rejected_acquisitions`) and
    what to check: such a result is never reported as a success."""
    kind, keys = _acquisition_keys(method, used)
    rejected = gof.rejected_acquisitions(dict(zip(keys, gof_p.T)), kind=kind)
    if not rejected:
        return "stands"
    check = (
        "check that acquisition's dark or maps (another read-out mode or speed, a "
        "byte-swapped or damaged file), its set-point and the data-quality checks' "
        "findings ('emccdcal check MANIFEST')"
    )
    if model.register.misfit_hint:
        check += "; " + model.register.misfit_hint
    return "doubtful: " + "; ".join(rejected) + "; " + check


def _add_bounds(ds, est, grid, kind, description):
    """Bounds ``<name>_lower/_upper`` of ``est`` beside each estimate, on its dims."""
    bounds = {}
    for name in ("photoelectrons", "em_gain", "e_per_adu"):
        lower, upper = est[f"{name}_lower"], est[f"{name}_upper"]
        if np.all(np.isnan(lower)):
            continue  # fixed by the method
        da = ds[name]
        pick = (lambda a: a[:, 0]) if da.ndim == 2 else (lambda a: a[:, : da.shape[0]])  # noqa: E731
        bounds[name] = grid(pick(lower)), grid(pick(upper))
    _add_interval_vars(ds, bounds, kind, description)


def _add_interval_vars(ds, bounds, kind, description):
    """Store ``{name: (lower, upper)}`` as ``<name>_lower/_upper`` on the dims of ``name``."""
    for name, pair in bounds.items():
        da = ds[name]
        for side, arr in zip(("lower", "upper"), pair):
            ds[f"{name}_{side}"] = (
                da.dims,
                np.asarray(arr),
                {
                    "units": da.attrs["units"],
                    "long_name": f"{side} bound of the 95 % {kind} interval of {name}",
                },
            )
    ds.attrs["intervals"] = description


def _mv_dataset(method, manifest, used, arrays, phi_map, phi_se=None, model=None):
    """The result of a mean–variance method from the moments of every tile's pixels."""
    rows, cols = manifest.shape
    offsets = np.stack([a.offset.reshape(-1) for a in used])
    read_noise = np.stack([a.read_noise.reshape(-1) for a in used])
    usable = arrays["usable"]
    # Left-out pixels (no usable frames) get no moments: NaN estimates, not converged.
    mean, var, n = (
        np.where(usable, arrays[k].T, np.nan if k != "n" else 0) for k in ("mean", "var", "n")
    )
    grid = lambda a: np.asarray(a).reshape(np.shape(a)[:-1] + (rows, cols))  # noqa: E731
    labels = _labels(used)
    setpoints = [a.em_gain_setpoint for a in used]
    if method == "mv-adu":
        fit = mv.fit_mv_adu(mean, var, offsets, read_noise, n)
        ds = result.make_dataset(
            method=method,
            setpoints=[1.0],
            levels=labels,
            e_per_adu=grid(fit.e_per_adu),
            e_per_adu_se=grid(fit.e_per_adu_se),
            em_gain=np.ones((1, rows, cols)),
            em_gain_se=np.zeros((1, rows, cols)),
            photoelectrons=grid(fit.photoelectrons),
            photoelectrons_se=grid(fit.photoelectrons_se),
            photoelectrons_dims=("level", "row", "col"),
            converged=grid(fit.valid & usable),
            manifest_hash=manifest.content_hash,
            manifest_path=str(manifest.path.resolve()),
        )
        bounds = {"e_per_adu": (grid(fit.e_per_adu_lower), grid(fit.e_per_adu_upper))}
    else:
        phi = phi_map.ravel()
        fit = mv.fit_mv_gain(
            mean,
            var,
            offsets,
            read_noise,
            n,
            phi,
            np.asarray(setpoints),
            e_per_adu_se=None if phi_se is None else phi_se.ravel(),
            em_model=model,
        )
        by_level = len(set(setpoints)) == 1 and len(setpoints) > 1
        ds = result.make_dataset(
            method=method,
            setpoints=[float(s) for s in fit.setpoints],
            levels=labels if by_level else None,
            e_per_adu=phi_map,
            e_per_adu_se=np.full((rows, cols), np.nan) if phi_se is None else phi_se,
            em_gain=grid(fit.em_gain),
            em_gain_se=grid(fit.em_gain_se),
            photoelectrons=grid(fit.photoelectrons),
            photoelectrons_se=grid(fit.photoelectrons_se),
            photoelectrons_dims=(("level" if by_level else "setpoint"), "row", "col"),
            converged=grid(
                (np.all(fit.valid, axis=0) if np.ndim(fit.valid) > 1 else fit.valid) & usable
            ),
            manifest_hash=manifest.content_hash,
            manifest_path=str(manifest.path.resolve()),
        )
        bounds = {"em_gain": (grid(fit.em_gain_lower), grid(fit.em_gain_upper))}
    bounds["photoelectrons"] = grid(fit.photoelectrons_lower), grid(fit.photoelectrons_upper)
    # Ratios of sample moments: Fieller bounds, valid where the slope is poorly determined
    # (and defined where the estimate is not), unlike estimate ± 1.96 SE.
    _add_interval_vars(
        ds,
        bounds,
        "Fieller",
        "Fieller, 95 %, from the photon-transfer fit, conditional on the offset/read-noise maps",
    )
    ds.attrs["standard_errors"] = "from the photon-transfer fit, conditional on the offset maps"
    return ds


def format_summary(ds):
    """A short human-readable table of a calibration (median over converged pixels)."""
    ok = ds.converged.values
    model = noise.EMModel.from_attrs(ds.attrs)
    lines = [
        f"method {ds.attrs['method']}"
        + (f" ({model.name} register)" if model else "")
        + f": {int(ok.sum())}/{ok.size} pixels converged, "
        f"{ds.attrs.get('seconds', float('nan')):.1f} s; medians over those"
    ]
    if not ok.any():
        return lines[0].replace("; medians over those", "; no estimate to show")
    multiplied = any(float(sp) != 1.0 for sp in ds.setpoint.values)
    if model is not None and model.register.uses_stages and multiplied:
        source = ds.attrs.get("register_stages_source")
        lines.append(
            f"  register length: {model.stages} stages" + (f" ({source})" if source else "")
        )

    def med(v):
        return nanmedian(np.asarray(v)[..., ok], axis=-1)

    phi, phi_se = med(ds.e_per_adu.values), med(ds.e_per_adu_se.values)
    chained = ds.attrs.get("e_per_adu_result")
    if np.isfinite(phi_se) and phi_se > 0:
        how = (
            ""
            if ds.attrs["method"] in ESTIMATE_E_PER_ADU
            else f"; from {chained}"
            if chained
            else "; given with its SE"
        )
        lines.append(
            f"  e_per_adu  {phi:.4f} ± {phi_se:.4f} e-/ADU (adu_per_e {1 / phi:.4f} ADU/e-{how})"
        )
    else:
        lines.append(
            f"  e_per_adu  {phi:.4f} e-/ADU, fixed (given without an error; "
            f"adu_per_e {1 / phi:.4f} ADU/e-)"
        )
    for i, sp in enumerate(ds.setpoint.values):
        g, se = med(ds.em_gain.values[i]), med(ds.em_gain_se.values[i])
        if float(sp) == 1.0:  # no multiplication: g = 1 by the model, not estimated
            lines.append("  em_gain at 1x: 1, fixed (no multiplication)")
        else:
            lines.append(f"  em_gain at {result.format_setpoint(sp)}x: {g:.4f} ± {se:.4f}")
    pe = ds.photoelectrons
    if pe.ndim == 2:
        lines.append(
            f"  photoelectrons {med(pe.values):.2f} ± {med(ds.photoelectrons_se.values):.2f} e-"
        )
    else:
        dim = pe.dims[0]
        for i, lab in enumerate(pe[dim].values):
            lines.append(
                f"  photoelectrons [{dim} {lab}] {med(pe.values[i]):.2f} ± "
                f"{med(ds.photoelectrons_se.values[i]):.2f} e-"
            )
    lines.append("  (± the per-pixel standard error, median over pixels; docs/results.md)")
    return "\n".join(lines)
